"""The §6.4 combined pipeline (``reports/combined.py``): the stage helpers and one tiny end-to-end run."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch

from reconstruction import fingerprint
from reports.combined import estimated_psnr, generate, reduce2x
from reports.metrics import read_metrics
from reports.paper_figures import COMBINED_ESTIMATES
from tests.test_reports_error_time import tiny_config


def test_reduce2x_is_the_2x2_box_mean():
    image = np.arange(4 * 6 * 3, dtype=np.float32).reshape(4, 6, 3)
    reduced = reduce2x(image)
    assert reduced.shape == (2, 3, 3)
    assert reduced[1, 2, 0] == pytest.approx(np.mean(image[2:4, 4:6, 0]))
    with pytest.raises(ValueError, match="even"):
        reduce2x(image[:3])


def test_estimated_psnr_follows_the_papers_rule():
    # Stage RMSEs add before the conversion to PSNR (not the PSNRs, not the MSEs).
    assert estimated_psnr(0.01, 0.01) == pytest.approx(-20 * math.log10(0.02))
    assert estimated_psnr(0.01, 0.01) == pytest.approx(40.0 - 20 * math.log10(2.0))
    assert estimated_psnr(0.0) == math.inf


def test_paper_estimates_are_the_papers():
    assert {k: v["estimated_psnr"] for k, v in COMBINED_ESTIMATES.items()} == {
        "cbox-sphere": 34.64, "car": 33.13, "samurai-monastery": 28.92, "crytek-sponza": 30.32}


def test_generate_end_to_end_and_reuse(shared_scenes, isolated_cache, tmp_path, capsys, monkeypatch):
    pytest.importorskip("mitsuba")
    config, out = tiny_config(), tmp_path / "report"
    metrics = generate(config, "tiny", out, progress=False)
    assert {m.name for m in metrics} == {"combined/cbox-original/psnr", "combined/cbox-original/denoise_stage_psnr",
                                         "combined/cbox-original/display_psnr"}
    assert all(m.kind == "psnr" and m.value > 0 for m in metrics)
    assert [m.name for m in read_metrics(out / "metrics" / "combined.json")] == [m.name for m in metrics]

    table = pd.read_csv(out / "combined.csv")
    record = table.iloc[0]
    assert record["render_size"] == "16x16" and record["final_size"] == "32x32" and record["spp"] == 4
    stages = record["render_seconds"] + record["denoise_seconds"] + record["superres_seconds"]
    assert record["total_seconds"] == pytest.approx(stages) and min(record[["denoise_seconds", "superres_seconds"]]) > 0
    assert math.isnan(record["paper_estimated_psnr"])  # cbox-original stands for none of the paper's scenes
    assert "cbox-original" in (out / "combined.md").read_text()
    # Figure 8, linked from the Markdown.
    assert (out / "figures" / "cbox-original-pipeline.png").stat().st_size > 1000
    assert "](figures/cbox-original-pipeline.png)" in (out / "combined.md").read_text()

    row = json.loads((out / "rows" / "combined" / "cbox-original.json").read_text())["row"]
    assert row["final"]["psnr"] == pytest.approx(-20 * math.log10(row["final"]["rmse"]))
    capsys.readouterr()
    again = generate(config, "tiny", out, progress=False)
    captured = capsys.readouterr()
    assert "combined cbox-original: reusing the row" in captured.out + captured.err
    assert [m.value for m in again] == [m.value for m in metrics]
    # Networks trained or run by other code are other networks: the row is measured again.
    monkeypatch.setattr(fingerprint, "networks_fingerprint", lambda profile=None: "other network code")
    generate(config, "tiny", out, progress=False)
    assert "reusing the row" not in "".join(capsys.readouterr())


# ------------------------------------------------------------------ the pipeline benchmark, once, without timing
class FixedDenoiser(torch.nn.Module):
    """Stand-in denoiser that always outputs one fixed linear image (HDR-encoded, as the real net)."""

    in_channels = 6

    def __init__(self, image: np.ndarray) -> None:
        super().__init__()
        self.encoded = torch.from_numpy(np.log1p(np.maximum(image, 0.0)).transpose(2, 0, 1)[None].astype(np.float32))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.encoded.clone()


def test_pipeline_benchmark_smoke(shared_scenes, isolated_cache):
    """Every side of ``bench/_measure_pipeline.py`` runs and validates; a pipeline worse than its input fails."""
    pytest.importorskip("mitsuba")
    from bench._measure import BenchmarkValidationError
    from bench._measure_pipeline import (
        SIDES,
        PipelineBench,
        PipelineResults,
        measure_pipeline,
    )
    from kdtrace.scenes import load_scene
    from reconstruction.models import Superresolution
    from reports.error_time import Reconstruction
    from tests.test_bench_render_smoke import DisabledBenchmark

    scene = load_scene("cbox-original")
    torch.manual_seed(0)
    superres = Superresolution().eval()
    bench = PipelineBench(scene, Reconstruction({}, superres), size=(32, 32), reference_spp=32, max_spp=16)
    clean = reduce2x(bench.reference().rgb)  # an oracle "denoiser": the reference itself
    bench.models.denoisers[scene.name] = FixedDenoiser(clean)
    results = PipelineResults()
    for side in SIDES:
        extra = {}
        results.add(measure_pipeline(DisabledBenchmark(), bench, side), extra)
    results.finalize()
    ours, same_spp, same_psnr = results.rows
    assert ours["psnr"] > ours["input_psnr"] and ours["beats_input"] and ours["render_width"] == 16
    assert same_spp["spp"] == 4 and same_spp["mean_z"] <= 5.0
    assert same_psnr["target_psnr"] == ours["psnr"]
    assert same_psnr["reached"] == (same_psnr["psnr"] >= ours["psnr"]) and same_psnr["spp"] in (1, 2, 4, 8, 16)
    assert same_psnr["mitsuba_same_psnr_over_pipeline_seconds"] == pytest.approx(same_psnr["seconds"] / ours["seconds"])
    assert "mitsuba-same-psnr" in results.table()

    bench.models.denoisers[scene.name] = FixedDenoiser(np.zeros_like(clean))  # a black frame
    with pytest.raises(BenchmarkValidationError, match="does not beat a flat image"):
        measure_pipeline(DisabledBenchmark(), bench, "pipeline")
