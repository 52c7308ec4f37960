"""KD-tree benchmarks: build time per scene and variant, Mrays/s per intersector, ray kind and query.

Each test times through ``benchmark.pedantic`` and then validates what it timed
(see ``bench/_measure.py``); the intersector ratios of the same run are added to
``extra_info`` at the end of the session (``bench/conftest.py``).
"""

from __future__ import annotations

import pytest

from bench._measure import INTERSECTORS, QUERIES, RAY_KINDS, measure_build, measure_traversal
from kdtrace.kdtree import VARIANTS
from kdtrace.scenes import list_scenes

SCENES = list_scenes()


@pytest.mark.benchmark(group="kdtree-build")
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("scene_name", SCENES)
def test_build(benchmark, compiled, scene_bench, bench_results, scene_name, variant):
    info = measure_build(benchmark, scene_bench(scene_name), variant)
    benchmark.extra_info.update(info)
    bench_results.add(info, benchmark.extra_info)


@pytest.mark.benchmark(group="traversal")
@pytest.mark.parametrize("intersector", INTERSECTORS)
@pytest.mark.parametrize("query", QUERIES)
@pytest.mark.parametrize("kind", RAY_KINDS)
@pytest.mark.parametrize("scene_name", SCENES)
def test_traversal(benchmark, compiled, scene_bench, bench_results, scene_name, kind, query, intersector):
    info = measure_traversal(benchmark, scene_bench(scene_name), intersector, kind, query)
    benchmark.extra_info.update(info)
    bench_results.add(info, benchmark.extra_info)
