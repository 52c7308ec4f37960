"""Path tracer benchmarks (group ``render``): ours vs Mitsuba 3, specialised vs general kernel, Table 1 frames.

Run from the repository root (see ``bench/_measure_render.py`` for what is measured)::

    .venv/bin/pytest bench/test_bench_render.py --benchmark-enable [--bench-scenes all]

Scenes follow ``--bench-scenes`` (the KD-tree suite's option; default the conftest's
cheap selection); the specialisation benchmark always includes the diffuse-only
``cbox-original``. Each test times through ``benchmark.pedantic`` and validates its
image afterwards. At the end of the session the same-run ratios (ours/Mitsuba,
local/naive, general/specialised) are written into every benchmark's ``extra_info``, a
per-scene table is printed and, when benchmarking is enabled,
``bench/results/render_summary.json`` is written atomically.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench._measure import select_scenes
from bench._measure_render import (
    KERNELS,
    RENDERERS,
    SPECIALISATION_SCENE,
    RenderBench,
    RenderResults,
    measure_frame,
    measure_specialisation,
    measure_throughput,
    write_render_summary,
)
from kdtrace.kdtree import VARIANTS
from kdtrace.scenes import list_scenes, load_scene

RENDER_SUMMARY_PATH = Path(__file__).parent / "results" / "render_summary.json"
#: The second parameter of each test, in run order (the reference side of each comparison first).
SIDES = {"renderer": RENDERERS, "kernel": KERNELS, "variant": VARIANTS}


def pytest_generate_tests(metafunc):
    """Parametrise by (scene, side), scene-major, over the ``--bench-scenes`` selection."""
    if "render_scene" not in metafunc.fixturenames:
        return
    try:
        scenes = select_scenes(metafunc.config.getoption("bench_scenes"), list_scenes())
    except ValueError as error:
        raise pytest.UsageError(str(error)) from None
    if metafunc.definition.name == "test_specialisation" and SPECIALISATION_SCENE not in scenes:
        scenes = [SPECIALISATION_SCENE, *scenes]
    side = next(name for name in SIDES if name in metafunc.fixturenames)
    metafunc.parametrize(("render_scene", side), [(scene, value) for scene in scenes for value in SIDES[side]])


class _SummaryPlugin:
    """Prints the render table in pytest's terminal summary."""

    def __init__(self, results: RenderResults) -> None:
        self.results = results
        self.lines: list[str] = []

    def pytest_terminal_summary(self, terminalreporter):
        if not self.results.rows:
            return
        terminalreporter.section("kdtrace render benchmark summary (times: shortest timed round)")
        terminalreporter.write_line(self.results.table())
        for line in self.lines:
            terminalreporter.write_line(line)


@pytest.fixture(scope="session")
def render_results(pytestconfig):
    """The run's :class:`RenderResults`; finalised, summarised and saved after the last test."""
    results = RenderResults()
    plugin = _SummaryPlugin(results)
    pytestconfig.pluginmanager.register(plugin, "kdtrace-render-summary")
    yield results
    # Session fixtures are torn down before pytest-benchmark saves its JSON, so the ratios reach it.
    results.finalize()
    enabled = pytestconfig.getoption("benchmark_enable") or not pytestconfig.getoption("benchmark_disable")
    if not results.rows:
        return
    if enabled:
        write_render_summary(RENDER_SUMMARY_PATH, results)
        plugin.lines.append(f"\nwrote {RENDER_SUMMARY_PATH}")
    else:
        plugin.lines.append("\nbenchmarking disabled (one call per test, no warm-up): render_summary.json not written")


@pytest.fixture(scope="session")
def render_bench(bench_seed):
    """``render_bench(name) -> RenderBench``; keeps only the latest scene (tests run scene by scene)."""
    current: dict[str, RenderBench] = {}

    def get(name: str) -> RenderBench:
        if name not in current:
            current.clear()
            current[name] = RenderBench(load_scene(name), bench_seed)
        return current[name]

    return get


@pytest.mark.benchmark(group="render")
def test_throughput(benchmark, render_bench, render_results, render_scene, renderer):
    info = measure_throughput(benchmark, render_bench(render_scene), renderer)
    benchmark.extra_info.update(info)
    render_results.add(info, benchmark.extra_info)


@pytest.mark.benchmark(group="render")
def test_specialisation(benchmark, render_bench, render_results, render_scene, kernel):
    info = measure_specialisation(benchmark, render_bench(render_scene), kernel)
    benchmark.extra_info.update(info)
    render_results.add(info, benchmark.extra_info)


@pytest.mark.benchmark(group="render")
def test_frame(benchmark, render_bench, render_results, render_scene, variant):
    info = measure_frame(benchmark, render_bench(render_scene), variant)
    benchmark.extra_info.update(info)
    render_results.add(info, benchmark.extra_info)
