"""The §6.4 pipeline against brute-force Mitsuba (group ``pipeline``).

Run from the repository root (see ``bench/_measure_pipeline.py`` for what is measured)::

    .venv/bin/pytest bench/test_bench_pipeline.py --benchmark-enable [--bench-scenes all]

Per scene of ``--bench-scenes`` (default the conftest's cheap selection): our path
tracer at half size + the scene's denoiser + 2x superresolution, then Mitsuba at the
same spp and at the spp that reaches the pipeline's PSNR. The networks come from the
``quick`` reconstruction profile (trained on first use, then reused from the cache).
Every side validates its image after timing; PSNRs and the same-run ratios go into
``extra_info`` and a table is printed at the end of the session.
"""

from __future__ import annotations

import pytest

from bench._measure import select_scenes
from bench._measure_pipeline import (
    SIDES,
    PipelineBench,
    PipelineResults,
    measure_pipeline,
)
from kdtrace.config import DEFAULT_CONFIG
from kdtrace.scenes import list_scenes, load_scene
from reports.error_time import Reconstruction

#: The report profile whose reconstruction networks the benchmark uses.
PROFILE = "quick"


def pytest_generate_tests(metafunc):
    """Parametrise by (scene, side), scene-major, over the ``--bench-scenes`` selection."""
    if "pipeline_scene" not in metafunc.fixturenames:
        return
    try:
        scenes = select_scenes(metafunc.config.getoption("bench_scenes"), list_scenes())
    except ValueError as error:
        raise pytest.UsageError(str(error)) from None
    metafunc.parametrize(("pipeline_scene", "side"), [(scene, side) for scene in scenes for side in SIDES])


@pytest.fixture(scope="session")
def pipeline_results(request):
    """The run's :class:`PipelineResults`; ratios filled and the table printed after the last test."""
    results = PipelineResults()
    yield results
    results.finalize()  # before pytest-benchmark saves its JSON (session fixtures are torn down first)
    if results.rows:
        reporter = request.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.section("kdtrace pipeline benchmark summary (seconds: shortest timed round)")
            reporter.write_line(results.table())


@pytest.fixture(scope="session")
def pipeline_bench(bench_seed):
    """``pipeline_bench(name) -> PipelineBench``; keeps only the latest scene (tests run scene by scene)."""
    profile = DEFAULT_CONFIG.profile(PROFILE)
    recon = DEFAULT_CONFIG.reconstruction.profile(profile.reconstruction_profile)
    current: dict[str, PipelineBench] = {}

    def get(name: str) -> PipelineBench:
        if name not in current:
            current.clear()
            models = Reconstruction.load([name], recon, profile.reconstruction_scenes, progress=False)
            current[name] = PipelineBench(load_scene(name), models, seed=bench_seed)
        return current[name]

    return get


@pytest.mark.benchmark(group="pipeline")
def test_pipeline(benchmark, pipeline_bench, pipeline_results, pipeline_scene, side):
    pytest.importorskip("mitsuba")
    info = measure_pipeline(benchmark, pipeline_bench(pipeline_scene), side)
    benchmark.extra_info.update(info)
    pipeline_results.add(info, benchmark.extra_info)
