"""Smoke test of the benchmark code paths (``bench/_measure.py``) on a tiny procedural scene.

Runs every build and traversal measurement once, without benchmarking, so CI keeps
the benchmark suite working; and checks that the validation step rejects wrong answers.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench._measure import (
    INTERSECTORS,
    QUERIES,
    RAY_KINDS,
    SEED,
    BenchmarkValidationError,
    Results,
    SceneBench,
    check_answer,
    machine_info,
    measure_build,
    measure_traversal,
    run_query,
    select_scenes,
    summary_document,
    write_json_atomic,
)
from kdtrace.kdtree import VARIANTS
from kdtrace.procedural import random_soup

RAYS = 2000


class DisabledBenchmark:
    """Stand-in for pytest-benchmark's fixture with benchmarking disabled: calls the target once."""

    def pedantic(self, target, rounds, warmup_rounds, iterations):
        return target()


@pytest.fixture
def tiny_bench(isolated_cache) -> SceneBench:
    """A 300-triangle random soup (large triangles, so most rays hit) with 2000 rays per kind; trees cached in a temporary folder."""
    return SceneBench(random_soup(300, seed=3, sizes=(0.1, 0.4)), rays=RAYS, seed=SEED)


def test_every_measurement_runs_validates_and_summarises(tiny_bench, tmp_path):
    results = Results()
    for variant in VARIANTS:
        results.add(measure_build(DisabledBenchmark(), tiny_bench, variant))
    extras = {}
    for kind in RAY_KINDS:
        for query in QUERIES:
            for name in INTERSECTORS:
                extras[kind, query, name] = {}
                results.add(measure_traversal(DisabledBenchmark(), tiny_bench, name, kind, query), extras[kind, query, name])
    results.finalize()

    row = results.summary()[tiny_bench.scene.name]
    assert set(row) == {"triangles", "references", "tree_bytes", "build_seconds", "build_peak_memory_bytes", "mrays_per_s", "ratios"}
    assert row["triangles"] == 300
    assert set(row["references"]) == {"naive", "local", "reduction_pct"}
    assert all(row["build_seconds"][v] > 0 and row["tree_bytes"][v] > 0 for v in VARIANTS)
    for kind in RAY_KINDS:
        for query in QUERIES:
            assert set(row["mrays_per_s"][kind][query]) == set(INTERSECTORS)
            assert all(rate > 0 for rate in row["mrays_per_s"][kind][query].values())
            assert all(ratio > 0 for ratio in row["ratios"][kind][query].values())
            assert extras[kind, query, "local"]["local_over_naive"] > 0
            assert extras[kind, query, "naive"]["kdtrace_over_embree"] > 0
    traversal = [r for r in results.rows if r["benchmark"] == "traversal" and r["variant"] != "embree"]
    assert all(r["rays"] == RAYS and r["agreement"]["unexplained"] == 0 for r in traversal)
    assert all(r["nodes_per_ray"] > 0 and r["tests_per_ray"] > 0 for r in traversal if r["query"] == "closest")
    assert tiny_bench.scene.name in results.table()

    path = tmp_path / "results" / "summary.json"
    write_json_atomic(path, summary_document(results, RAYS, SEED))
    document = json.loads(path.read_text())
    assert document["scenes"][tiny_bench.scene.name]["triangles"] == 300
    assert set(document["machine"]) == set(machine_info())
    assert document["machine"]["packages"]["kdtrace"]
    assert list(tmp_path.joinpath("results").iterdir()) == [path]


def test_traversal_runs_through_pytest_benchmark_fixture(benchmark, tiny_bench):
    info = measure_traversal(benchmark, tiny_bench, "local", "primary", "closest")
    assert info["mrays_per_s"] > 0 and info["agreement"]["rays"] == RAYS


def test_validation_rejects_wrong_answers(tiny_bench):
    scene, batch, tree = tiny_bench.scene, tiny_bench.ray_batch("primary"), tiny_bench.tree("local")
    t, tri, u, v = run_query(tree, batch, "closest")
    reference = tiny_bench.reference("primary", "closest")
    assert check_answer(scene, batch, "closest", (t, tri, u, v), reference)["unexplained"] == 0
    hit = tri >= 0
    assert hit.sum() > 100
    missed = (np.where(hit, np.inf, t), np.where(hit, -1, tri), u, v)
    with pytest.raises(BenchmarkValidationError, match="wrong of"):
        check_answer(scene, batch, "closest", missed, reference)
    too_far = (np.where(hit, 1.5 * t, t), tri, u, v)
    with pytest.raises(BenchmarkValidationError):
        check_answer(scene, batch, "closest", too_far, reference)

    blocked = run_query(tree, batch, "occluded")
    assert 0 < blocked.sum() < len(blocked)
    with pytest.raises(BenchmarkValidationError):
        check_answer(scene, batch, "occluded", ~blocked, tiny_bench.reference("primary", "occluded"))


def test_scene_selection():
    available = ["bunny", "car", "cbox-sphere"]
    assert select_scenes("all", available) == available
    assert select_scenes("cbox-sphere, car", available) == ["cbox-sphere", "car"]
    with pytest.raises(ValueError, match="sponza"):
        select_scenes("car,sponza", available)
