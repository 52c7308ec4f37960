"""Reconstruction benchmarks: our denoiser against OIDN (group ``denoise``), our 2x superresolution against bicubic (``superres``).

Run from the repository root (see ``bench/_measure_reconstruction.py`` for what is measured)::

    .venv/bin/pytest bench/test_bench_reconstruction.py --benchmark-enable

The nets are the ``quick`` profile's, trained on ``cbox-original`` (or reused from the
cache); the frame is a 512x512 4 spp render with a 256 spp Mitsuba reference (cached).
Each test validates what it timed. At the end of the session the same-run ratios
(OIDN/ours and bicubic/ours seconds) are written into every benchmark's ``extra_info``,
a table is printed and, when benchmarking is enabled,
``bench/results/reconstruction_summary.json`` is written atomically.

Plug-in denoisers given with ``--bench-denoiser SPEC`` are further methods
``plugin:SPEC`` of the denoise group, after ours (``bench/_plugins.py``)::

    .venv/bin/pytest bench/test_bench_reconstruction.py --benchmark-enable -k denoise --bench-denoiser bilateral
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench._measure_reconstruction import (
    DENOISERS,
    UPSAMPLERS,
    ReconstructionBench,
    ReconstructionResults,
    measure_denoise,
    measure_plugin_denoise,
    measure_superres,
    write_reconstruction_summary,
)
from bench._plugins import bench_plugins, is_plugin, plugin_spec
from kdtrace.plugins import PluginError

SUMMARY_PATH = Path(__file__).parent / "results" / "reconstruction_summary.json"


class _SummaryPlugin:
    """Prints the reconstruction table in pytest's terminal summary."""

    def __init__(self, results: ReconstructionResults) -> None:
        self.results = results
        self.lines: list[str] = []

    def pytest_terminal_summary(self, terminalreporter):
        if not self.results.rows:
            return
        terminalreporter.section("kdtrace reconstruction benchmark summary (times: shortest timed round)")
        terminalreporter.write_line(self.results.table())
        for line in self.lines:
            terminalreporter.write_line(line)


@pytest.fixture(scope="session")
def reconstruction_results(pytestconfig):
    """The run's :class:`ReconstructionResults`; finalised, summarised and saved after the last test."""
    pytest.importorskip("pyoidn")
    pytest.importorskip("mitsuba")
    results = ReconstructionResults()
    plugin = _SummaryPlugin(results)
    pytestconfig.pluginmanager.register(plugin, "kdtrace-reconstruction-summary")
    yield results
    # Session fixtures are torn down before pytest-benchmark saves its JSON, so the ratios reach it.
    results.finalize()
    enabled = pytestconfig.getoption("benchmark_enable") or not pytestconfig.getoption("benchmark_disable")
    if results.rows and enabled:
        write_reconstruction_summary(SUMMARY_PATH, results)
        plugin.lines.append(f"\nwrote {SUMMARY_PATH}")


@pytest.fixture(scope="session")
def reconstruction_bench(reconstruction_results) -> ReconstructionBench:
    """Frame, trained nets and fast-inference choices, made once (untimed)."""
    bench = ReconstructionBench()
    assert set(bench.options) == {"denoise", "superres"}  # decided before any timing
    return bench


#: Group -> (measuring function, methods in run order: the baseline first).
MEASURES = {"denoise": (measure_denoise, DENOISERS), "superres": (measure_superres, UPSAMPLERS)}


def pytest_generate_tests(metafunc):
    """Parametrise by (group, method): ours and the baselines, then the plug-in denoisers in the denoise group."""
    if metafunc.definition.name != "test_reconstruction":
        return
    plugins = {"denoise": bench_plugins(metafunc.config).denoiser_names}
    metafunc.parametrize(("group", "method"), [(group, method) for group, (_, methods) in MEASURES.items()
                                               for method in (*methods, *plugins.get(group, ()))])


def test_reconstruction(benchmark, pytestconfig, reconstruction_bench, reconstruction_results, group, method):
    benchmark.group = group
    try:
        if is_plugin(method):
            denoiser = bench_plugins(pytestconfig).denoisers[plugin_spec(method)]
            info = measure_plugin_denoise(benchmark, reconstruction_bench, denoiser)
        else:
            info = MEASURES[group][0](benchmark, reconstruction_bench, method)
    except PluginError as error:
        # the plug-in's message alone: no traceback, no chained exception
        raise pytest.fail.Exception(str(error), pytrace=False) from None
    benchmark.extra_info.update(info)
    reconstruction_results.add(info, benchmark.extra_info)
