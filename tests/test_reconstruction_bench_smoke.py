"""Smoke test of the reconstruction benchmark code (``bench/_measure_reconstruction.py``) on a 64 x 64 frame.

Runs both groups once without benchmarking, with untrained nets (no training, no Mitsuba:
the reference is a 256 spp render of our own path tracer), so CI keeps the benchmark
code working; and checks that the validation rejects a broken upsampler.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from bench._measure import BenchmarkValidationError
from bench._measure_reconstruction import (
    DENOISERS,
    UPSAMPLERS,
    ReconstructionBench,
    ReconstructionResults,
    measure_denoise,
    measure_superres,
)
from reconstruction.models import Denoiser, Superresolution
from reconstruction.speed import Frame
from tests.test_bench_render_smoke import DisabledBenchmark

SIZE = 64


@pytest.fixture(scope="module")
def frame(shared_scenes) -> Frame:
    from kdtrace.render import render
    from kdtrace.scenes import load_scene

    scene = load_scene("cbox-original")
    noisy = render(scene, spp=4, max_depth=3, seed=1, width=SIZE, height=SIZE, aux=True)
    reference = render(scene, spp=256, max_depth=3, seed=2, width=SIZE, height=SIZE, aux=False)
    return Frame("cbox-original", noisy.rgb, noisy.albedo, noisy.normal, reference.rgb, 4, 256)


def _bench(frame, superres=None) -> ReconstructionBench:
    torch.manual_seed(0)
    bench = ReconstructionBench(scene=frame.scene, size=SIZE, frame=frame, denoiser=Denoiser(),
                                superres=superres or Superresolution())
    bench.options = {"denoise": "channels_last", "superres": "fp32"}
    return bench


def test_both_groups_run_validate_and_give_ratios(frame, isolated_cache):
    pytest.importorskip("pyoidn")
    bench, results = _bench(frame), ReconstructionResults()
    for method in DENOISERS:
        results.add(measure_denoise(DisabledBenchmark(), bench, method))
    for method in UPSAMPLERS:
        results.add(measure_superres(DisabledBenchmark(), bench, method))
    results.finalize()
    rows = {(row["group"], row["method"]): row for row in results.rows}
    assert set(rows) == {("denoise", "oidn"), ("denoise", "ours"), ("superres", "bicubic"), ("superres", "ours")}
    assert all(row["seconds"] > 0 and np.isfinite(row["psnr"]) for row in results.rows)
    assert rows["denoise", "oidn"]["psnr"] > rows["denoise", "oidn"]["noisy_psnr"]
    assert rows["denoise", "ours"]["option"] == "channels_last"
    # an untrained superresolution net is exactly bicubic (identity on the luma residual)
    assert rows["superres", "ours"]["psnr"] == pytest.approx(rows["superres", "bicubic"]["psnr"], abs=1e-4)
    assert rows["denoise", "ours"]["oidn_over_ours_seconds"] > 0
    assert rows["superres", "bicubic"]["bicubic_over_ours_seconds"] > 0
    assert "bicubic/ours" in results.table()


class _Blank(nn.Module):
    """A broken 'superresolution' net that outputs black."""

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(y)


def test_validation_rejects_a_broken_upsampler(frame):
    bench = _bench(frame, superres=_Blank())
    with pytest.raises(BenchmarkValidationError, match="reduced 2x"):
        measure_superres(DisabledBenchmark(), bench, "ours")
    with pytest.raises(ValueError, match="unknown"):
        measure_denoise(DisabledBenchmark(), bench, "median")
