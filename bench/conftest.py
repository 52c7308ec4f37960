"""Options, shared state and the same-run summary of the KD-tree benchmarks.

Run from the repository root (see ``bench/README.md``)::

    .venv/bin/pytest bench --benchmark-enable [--bench-scenes all] [--bench-rays N]
        [--bench-accelerator SPEC[,SPEC...]] [--bench-denoiser SPEC[,SPEC...]]

``--bench-scenes`` deselects the scenes not asked for and the remaining tests run
scene by scene (builds, then Embree, naive, local per ray kind and query), so only
one scene's trees, Embree BVH and rays are held at a time. At the end of the run the
ratios between intersectors are written into every benchmark's ``extra_info`` (before
pytest-benchmark saves its JSON), a per-scene table is printed and, when
benchmarking is enabled, ``bench/results/summary.json`` is written.

``--bench-accelerator`` / ``--bench-denoiser`` add plug-ins (``bench/_plugins.py``)
to the ``traversal`` and ``denoise`` groups; they are resolved in
:func:`pytest_configure`, and one that does not load is a usage error.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench._measure import (
    DEFAULT_RAYS,
    DEFAULT_SCENES,
    INTERSECTORS,
    QUERIES,
    RAY_KINDS,
    SEED,
    Results,
    SceneBench,
    make_rays,
    run_query,
    select_scenes,
    summary_document,
    write_json_atomic,
)
from bench._plugins import PLUGINS_KEY, BenchPlugins, is_plugin
from kdtrace.allocator import freed_memory_retained
from kdtrace.kdtree import VARIANTS, build_kdtree
from kdtrace.procedural import random_soup
from kdtrace.scenes import list_scenes, load_scene

RESULTS_DIRECTORY = Path(__file__).parent / "results"
SUMMARY_PATH = RESULTS_DIRECTORY / "summary.json"
RESULTS_KEY = pytest.StashKey[Results]()


def pytest_addoption(parser):
    group = parser.getgroup("kdtrace benchmarks")
    group.addoption("--bench-scenes", default=",".join(DEFAULT_SCENES),
                    help=f"comma-separated scene names, or 'all' (default: {','.join(DEFAULT_SCENES)})")
    group.addoption("--bench-rays", type=int, default=DEFAULT_RAYS, help=f"rays per ray kind (default: {DEFAULT_RAYS})")
    group.addoption("--bench-accelerator", action="append", default=[], metavar="SPEC",
                    help="also time this plug-in accelerator in the traversal group: an entry-point name of "
                         "kdtrace.accelerators or package.module:factory (repeatable, or comma-separated)")
    group.addoption("--bench-denoiser", action="append", default=[], metavar="SPEC",
                    help="also time this plug-in denoiser in the denoise group: an entry-point name of "
                         "kdtrace.denoisers or package.module:factory (repeatable, or comma-separated)")


@pytest.fixture(autouse=True)
def _timed_with_freed_memory_retained():
    """Every benchmark runs as the report's timed sections do (:func:`kdtrace.allocator.freed_memory_retained`)."""
    with freed_memory_retained():
        yield


def pytest_configure(config):
    config.stash[RESULTS_KEY] = Results()
    # Raises pytest.UsageError naming a plug-in that cannot be imported or loaded.
    config.stash[PLUGINS_KEY] = BenchPlugins.from_options(config.getoption("bench_accelerator"),
                                                          config.getoption("bench_denoiser"))
    # pytest-benchmark's --benchmark-json does not create its folder.
    RESULTS_DIRECTORY.mkdir(exist_ok=True)


def _order(item, scenes: list[str], accelerators: list[str]) -> tuple:
    """Sort key: scene, builds before traversals, then ray kind, query and intersector (Embree first, plug-ins last)."""
    params = item.callspec.params
    traversal = "kind" in params
    intersector = params.get("intersector", "")
    return (
        scenes.index(params["scene_name"]),
        traversal,
        VARIANTS.index(params["variant"]) if not traversal else 0,
        RAY_KINDS.index(params["kind"]) if traversal else 0,
        QUERIES.index(params["query"]) if traversal else 0,
        (len(INTERSECTORS) + accelerators.index(intersector) if is_plugin(intersector) else INTERSECTORS.index(intersector))
        if traversal else 0,
    )


def pytest_collection_modifyitems(config, items):
    try:
        scenes = select_scenes(config.getoption("bench_scenes"), list_scenes())
    except ValueError as error:
        raise pytest.UsageError(str(error)) from None
    benches = [item for item in items if "scene_name" in getattr(getattr(item, "callspec", None), "params", {})]
    dropped = [item for item in benches if item.callspec.params["scene_name"] not in scenes]
    if dropped:
        config.hook.pytest_deselected(items=dropped)
    accelerators = config.stash[PLUGINS_KEY].accelerator_names
    kept = sorted((item for item in benches if item not in dropped), key=lambda item: _order(item, scenes, accelerators))
    items[:] = [item for item in items if item not in benches] + kept


@pytest.fixture(scope="session")
def bench_results(pytestconfig) -> Results:
    """The run's :class:`Results`, summarised at the end of the session."""
    return pytestconfig.stash[RESULTS_KEY]


@pytest.fixture(scope="session")
def bench_seed() -> int:
    """Base seed of every ray set."""
    return SEED


@pytest.fixture(scope="session")
def compiled() -> None:
    """Compile the numba build and traversal kernels on a tiny scene, so no benchmark times compilation."""
    scene = random_soup(64, seed=0)
    batch = make_rays(scene, "incoherent", 16, 0)
    for variant in VARIANTS:
        tree = build_kdtree(scene, variant, cache=False)
        for query in QUERIES:
            run_query(tree, batch, query)


@pytest.fixture(scope="session")
def scene_bench(pytestconfig, bench_seed):
    """``scene_bench(name) -> SceneBench``; keeps only the latest scene (tests run scene by scene)."""
    current: dict[str, SceneBench] = {}

    def get(name: str) -> SceneBench:
        if name not in current:
            current.clear()
            current[name] = SceneBench(load_scene(name), pytestconfig.getoption("bench_rays"), bench_seed)
        return current[name]

    return get


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_sessionfinish(session):
    # Before pytest-benchmark's own sessionfinish saves --benchmark-json with the extra_info dicts.
    session.config.stash[RESULTS_KEY].finalize()
    yield


def pytest_terminal_summary(terminalreporter, config):
    results = config.stash[RESULTS_KEY]
    if not results.rows:
        return
    terminalreporter.section("kdtrace benchmark summary (rates: rays / shortest timed round)")
    terminalreporter.write_line(results.table())
    enabled = config.getoption("benchmark_enable") or not config.getoption("benchmark_disable")
    if enabled:
        write_json_atomic(SUMMARY_PATH, summary_document(results, config.getoption("bench_rays"), SEED))
        terminalreporter.write_line(f"\nwrote {SUMMARY_PATH}")
    else:
        terminalreporter.write_line("\nbenchmarking disabled (one call per test, no warm-up): summary.json not written")
