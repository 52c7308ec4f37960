"""Smoke test of the render benchmark code (``bench/_measure_render.py``) on a tiny render of ``cbox-original``.

Runs every measurement once at 16 x 16 pixels without benchmarking (Mitsuba included
when it imports), so CI keeps the render benchmark suite working; and checks that the
validation rejects NaNs, biased means and renders that should be identical but are not.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from bench._measure import SEED, BenchmarkValidationError
from bench._measure_render import (
    KERNELS,
    RENDERERS,
    RenderBench,
    RenderResults,
    check_mean_radiance,
    check_near_identical,
    measure_frame,
    measure_specialisation,
    measure_throughput,
    write_render_summary,
)
from kdtrace.kdtree import VARIANTS
from kdtrace.render import render
from kdtrace.scenes import load_scene

SIZE, SPP = (16, 16), 4


class DisabledBenchmark:
    """Stand-in for pytest-benchmark's fixture with benchmarking disabled: calls the target once."""

    def pedantic(self, target, rounds, warmup_rounds, iterations):
        return target()


@pytest.fixture
def tiny_render_bench(shared_scenes, isolated_cache) -> RenderBench:
    """``cbox-original`` (36 triangles), trees cached in a temporary folder."""
    return RenderBench(load_scene("cbox-original"), seed=SEED)


def test_every_measurement_runs_validates_and_summarises(tiny_render_bench, tmp_path):
    pytest.importorskip("mitsuba")
    bench, results = tiny_render_bench, RenderResults()
    extras = {}
    for renderer in RENDERERS:
        extras[renderer] = {}
        results.add(measure_throughput(DisabledBenchmark(), bench, renderer, size=SIZE, spp=SPP), extras[renderer])
    for kernel in KERNELS:
        extras[kernel] = {}
        results.add(measure_specialisation(DisabledBenchmark(), bench, kernel, size=SIZE, spp=SPP), extras[kernel])
    for variant in VARIANTS:
        extras[variant] = {}
        results.add(measure_frame(DisabledBenchmark(), bench, variant, size=SIZE, spp=SPP), extras[variant])
    results.finalize()

    ours, theirs = results.rows[0], results.rows[1]
    assert ours["paths"] == theirs["paths"] == SIZE[0] * SIZE[1] * SPP
    assert ours["rays"]["camera"] == ours["paths"] and ours["mrays_per_s"]["total"] > 0
    assert theirs["threads"] >= 1 and theirs["agreement"]["z"] <= 5.0
    assert results.rows[2]["kernel"] == "specialised" and results.rows[3]["kernel"] == "general"
    assert all(row["agreement"]["identical"] for row in results.rows[2:])
    assert extras["mitsuba"]["kdtrace_over_mitsuba"] > 0 and extras["kdtrace"]["kdtrace_over_mitsuba"] > 0
    assert extras["general"]["paired_general_over_specialised_seconds"] > 0
    assert extras["naive"]["local_over_naive_seconds"] > 0 and extras["local"]["paired_local_over_naive_seconds"] > 0

    scene = results.summary()["cbox-original"]
    assert set(scene["throughput"]["paths_per_second"]) == set(RENDERERS)
    assert set(scene["frame"]["seconds"]) == set(VARIANTS)
    assert scene["specialisation"]["features"] == ["aux", "emitter_selection", "emitters"]
    assert "cbox-original" in results.table()

    path = tmp_path / "results" / "render_summary.json"
    write_render_summary(path, results)
    document = json.loads(path.read_text())
    assert document["scenes"]["cbox-original"]["throughput"]["kdtrace_over_mitsuba"] > 0
    assert document["machine"]["packages"]["mitsuba"] and document["machine"]["mitsuba_threads"] >= 1
    assert list(path.parent.iterdir()) == [path]


def test_validation_rejects_wrong_images(tiny_render_bench):
    bench = tiny_render_bench

    def run(seed):
        return render(bench.scene, spp=SPP, max_depth=3, seed=seed, width=SIZE[0], height=SIZE[1], tree=bench.tree("local"))

    a, b = run(1), run(2)
    assert check_mean_radiance(a, b.rgb, "other seed")["z"] <= 5.0
    assert check_near_identical(a, run(1), "same seed")["identical"]
    with pytest.raises(BenchmarkValidationError, match="standard errors"):
        check_mean_radiance(a, 3.0 * a.rgb, "biased")
    nan = a.rgb.copy()
    nan[3, 4, 1] = np.nan
    with pytest.raises(BenchmarkValidationError, match="NaN"):
        check_mean_radiance(a, nan, "nan")
    with pytest.raises(BenchmarkValidationError, match="pixels differ"):
        check_near_identical(a, b, "different seeds")
    one_pixel = a.rgb.copy()
    one_pixel[0, 0] += 1e-3  # a single tie-broken pixel out of 256 is still over the 0.1% limit
    with pytest.raises(BenchmarkValidationError, match="pixels differ"):
        check_near_identical(a, dataclasses.replace(a, rgb=one_pixel), "one pixel")
