"""KD-tree benchmarks: build time per scene and variant, Mrays/s per intersector, ray kind and query.

Each test times through ``benchmark.pedantic`` and then validates what it timed
(see ``bench/_measure.py``); the intersector ratios of the same run are added to
``extra_info`` at the end of the session (``bench/conftest.py``). Plug-in
accelerators given with ``--bench-accelerator SPEC`` are further intersectors
``plugin:SPEC`` of the traversal group (``bench/_plugins.py``).
"""

from __future__ import annotations

import pytest

from bench._measure import INTERSECTORS, QUERIES, RAY_KINDS, measure_build, measure_traversal
from bench._plugins import bench_plugins
from kdtrace.kdtree import VARIANTS
from kdtrace.plugins import PluginError
from kdtrace.scenes import list_scenes

SCENES = list_scenes()


def pytest_generate_tests(metafunc):
    """Parametrise the traversals by scene, ray kind, query and intersector: ours, then the plug-ins."""
    if metafunc.definition.name != "test_traversal":
        return
    metafunc.parametrize("scene_name", SCENES)
    metafunc.parametrize("kind", RAY_KINDS)
    metafunc.parametrize("query", QUERIES)
    metafunc.parametrize("intersector", [*INTERSECTORS, *bench_plugins(metafunc.config).accelerator_names])


@pytest.mark.benchmark(group="kdtree-build")
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("scene_name", SCENES)
def test_build(benchmark, compiled, scene_bench, bench_results, scene_name, variant):
    info = measure_build(benchmark, scene_bench(scene_name), variant)
    benchmark.extra_info.update(info)
    bench_results.add(info, benchmark.extra_info)


@pytest.mark.benchmark(group="traversal")
def test_traversal(benchmark, compiled, scene_bench, bench_results, scene_name, kind, query, intersector):
    try:
        info = measure_traversal(benchmark, scene_bench(scene_name), intersector, kind, query)
    except PluginError as error:
        # the plug-in's message alone: no traceback, no chained exception
        raise pytest.fail.Exception(str(error), pytrace=False) from None
    benchmark.extra_info.update(info)
    bench_results.add(info, benchmark.extra_info)
