"""The benchmarks' plug-in options, ``--bench-accelerator`` and ``--bench-denoiser`` (``bench/_plugins.py``).

Runs tiny selections of the pytest-benchmark suite in-process with benchmarking
disabled (one call per test): the traversal group on ``cbox-original`` with 300 rays,
and the denoise group on a 64 x 64 frame with an untrained net (the session's
``ReconstructionBench`` is replaced, as in ``tests/test_reconstruction_bench_smoke.py``).
The example plug-ins (``examples/kdtrace-example-plugins``) are named by
``module:factory`` with their source folder on ``sys.path``, so they need not be
installed; the broken plug-ins below must fail their own benchmarks with the
``PluginError`` message and leave the others passing. A plug-in that cannot be
loaded must be a usage error naming it, not a traceback.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import bench._measure_reconstruction
from bench._measure import INTERSECTORS, QUERIES, RAY_KINDS

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
EXAMPLES_SRC = ROOT / "examples" / "kdtrace-example-plugins" / "src"
BRUTE_FORCE = "kdtrace_example_plugins.brute_force:make"
BILATERAL = "kdtrace_example_plugins.bilateral:make"
BROKEN_ACCELERATOR = "tests.test_bench_plugins:broken_accelerator"
BROKEN_DENOISER = "tests.test_bench_plugins:broken_denoiser"
SCRIBBLING_DENOISER = "tests.test_bench_plugins:scribbling_denoiser"
SCENE, RAYS, SIZE = "cbox-original", 300, 64


# ------------------------------------------------------------------ broken plug-ins (named by the runs below)
class _Broken:
    """An accelerator answering with a triangle index past the scene's and an int 'occluded' array."""

    def __init__(self, n_triangles: int) -> None:
        self.n = n_triangles

    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf):
        n = len(origins)
        return np.ones(n), np.full(n, self.n, np.int32), np.zeros(n), np.zeros(n)

    def occluded(self, origins, directions, tmax):
        return np.zeros(len(origins), np.int64)


def broken_accelerator(scene) -> _Broken:
    return _Broken(len(scene.triangles))


def broken_denoiser():
    return lambda color, albedo, normal: color.astype(np.float64)


def scribbling_denoiser():
    """A valid answer, but it halves the shared noisy colour in place."""

    def denoise(color, albedo, normal):
        color *= 0.5
        return color.copy()

    return denoise


# ------------------------------------------------------------------ running the bench suite in-process
class _Collector:
    """Keeps every test's report, the collected ids and each benchmark's ``extra_info`` dict."""

    def __init__(self) -> None:
        self.reports: dict[str, pytest.TestReport] = {}
        self.extra: dict[str, dict] = {}
        self.collected: list[str] = []

    def pytest_collection_finish(self, session):
        self.collected = [item.nodeid for item in session.items]

    def pytest_runtest_makereport(self, item, call):
        if call.when == "call" and "benchmark" in item.funcargs:
            # the same dict the session's end completes with the same-run ratios
            self.extra[item.nodeid] = item.funcargs["benchmark"].extra_info

    def pytest_runtest_logreport(self, report):
        if report.when == "call" or report.outcome != "passed":
            self.reports.setdefault(report.nodeid, report)


def _run_bench(*args: str) -> tuple[int, _Collector]:
    """``pytest ARGS --benchmark-disable`` in this process; forgets the bench's rootless modules and sys.path entries afterwards."""
    collector = _Collector()
    before, path = set(sys.modules), list(sys.path)
    outer_conftest = sys.modules.get("conftest")
    try:
        code = pytest.main([*args, "--benchmark-disable", "-p", "no:cacheprovider", "-q"], plugins=[collector])
    finally:
        for name in set(sys.modules) - before:
            module_file = getattr(sys.modules[name], "__file__", None)
            if not name.startswith("bench.") and module_file and Path(module_file).parent == BENCH:
                del sys.modules[name]  # conftest, test_bench_*: imported by bare name
        if outer_conftest is not None:
            sys.modules["conftest"] = outer_conftest
        sys.path[:] = path  # the rootless imports put bench/ first
    return code, collector


def _id(*params: str) -> str:
    return "-".join(params)


@pytest.fixture
def bench_env(shared_scenes, isolated_cache, monkeypatch):
    """Run from the repository root, with the example plug-ins importable."""
    monkeypatch.chdir(ROOT)
    monkeypatch.syspath_prepend(str(EXAMPLES_SRC))


# ------------------------------------------------------------------ tests
def test_traversal_group_times_and_checks_plugin_accelerators(bench_env):
    code, run = _run_bench(str(BENCH / "test_bench_kdtree.py"), "-k", "traversal", "--bench-scenes", SCENE,
                           "--bench-rays", str(RAYS), "--bench-accelerator", BRUTE_FORCE,
                           "--bench-accelerator", BROKEN_ACCELERATOR)
    assert code == pytest.ExitCode.TESTS_FAILED
    intersectors = [*INTERSECTORS, f"plugin:{BRUTE_FORCE}", f"plugin:{BROKEN_ACCELERATOR}"]
    expected = [f"bench/test_bench_kdtree.py::test_traversal[{_id(SCENE, kind, query, name)}]"
                for kind in RAY_KINDS for query in QUERIES for name in intersectors]
    assert run.collected == expected  # ours first (Embree first), then the plug-ins, scene by scene
    for kind in RAY_KINDS:
        for query in QUERIES:
            def node(name, kind=kind, query=query):
                return f"bench/test_bench_kdtree.py::test_traversal[{_id(SCENE, kind, query, name)}]"

            for name in INTERSECTORS:
                assert run.reports[node(name)].passed, run.reports[node(name)].longreprtext
            plugin = node(f"plugin:{BRUTE_FORCE}")
            assert run.reports[plugin].passed, run.reports[plugin].longreprtext
            extra = run.extra[plugin]
            assert extra["variant"] == f"plugin:{BRUTE_FORCE}" and extra["rays"] == RAYS
            assert extra["agreement"]["rays"] == RAYS and extra["mrays_per_s"] > 0
            assert extra["plugin_over_embree"] == pytest.approx(
                extra["mrays_per_s"] / run.extra[node("embree")]["mrays_per_s"])
            assert extra["plugin_stats"]["references"] == 36 and extra["plugin_load_seconds"] > 0
            assert "plugin_over_embree" not in run.extra[node("local")]  # ours keep their own ratios
            assert run.extra[node("local")]["kdtrace_over_embree"] > 0

            broken = run.reports[node(f"plugin:{BROKEN_ACCELERATOR}")]
            assert broken.failed
            message = broken.longreprtext
            assert f"plug-in {BROKEN_ACCELERATOR!r}" in message
            assert ("outside [-1, 36)" if query == "closest" else "occluded's answer must be a bool array") in message
            # the message alone, not a traceback or a chain of exceptions
            assert "Traceback" not in message and "def test_traversal" not in message and "During handling" not in message


def test_denoise_group_times_plugin_denoisers(bench_env, monkeypatch):
    pytest.importorskip("pyoidn")
    pytest.importorskip("mitsuba")  # the session fixture asks for it
    import torch

    from kdtrace.render import render
    from kdtrace.scenes import load_scene
    from reconstruction.models import Denoiser, Superresolution
    from reconstruction.speed import Frame

    scene = load_scene(SCENE)
    noisy = render(scene, spp=4, max_depth=3, seed=1, width=SIZE, height=SIZE, aux=True)
    reference = render(scene, spp=256, max_depth=3, seed=2, width=SIZE, height=SIZE, aux=False)
    frame = Frame(SCENE, *(np.ascontiguousarray(a, np.float32) for a in (noisy.rgb, noisy.albedo, noisy.normal,
                                                                         reference.rgb)), 4, 256)
    torch.manual_seed(0)
    tiny = bench._measure_reconstruction.ReconstructionBench(scene=SCENE, size=SIZE, frame=frame, denoiser=Denoiser(),
                                                             superres=Superresolution())
    tiny.options = {"denoise": "channels_last", "superres": "fp32"}
    # what the session fixture of bench/test_bench_reconstruction.py builds (imported by name when it is collected)
    monkeypatch.setattr(bench._measure_reconstruction, "ReconstructionBench", lambda: tiny)

    code, run = _run_bench(str(BENCH / "test_bench_reconstruction.py"), "-k", "denoise",
                           "--bench-denoiser", f"{BILATERAL},{BROKEN_DENOISER}", "--bench-denoiser", SCRIBBLING_DENOISER)
    assert code == pytest.ExitCode.TESTS_FAILED
    methods = ["oidn", "ours", f"plugin:{BILATERAL}", f"plugin:{BROKEN_DENOISER}", f"plugin:{SCRIBBLING_DENOISER}"]
    nodes = [f"bench/test_bench_reconstruction.py::test_reconstruction[denoise-{method}]" for method in methods]
    assert run.collected == nodes
    oidn, ours, plugin, broken, scribbling = nodes
    for node in (oidn, ours, plugin):
        assert run.reports[node].passed, run.reports[node].longreprtext
    extra = run.extra[plugin]
    assert extra["method"] == f"plugin:{BILATERAL}" and extra["group"] == "denoise"
    assert extra["seconds"] > 0 and np.isfinite(extra["psnr"]) and np.isfinite(extra["noisy_psnr"])  # recorded, not gated
    assert extra["oidn_over_plugin_seconds"] == pytest.approx(run.extra[oidn]["seconds"] / extra["seconds"])
    assert extra["oidn_over_ours_seconds"] == run.extra[ours]["oidn_over_ours_seconds"]  # the group's ratio, as ever
    assert "oidn_over_plugin_seconds" not in run.extra[ours]
    assert run.reports[broken].failed
    message = run.reports[broken].longreprtext
    assert f"plug-in {BROKEN_DENOISER!r}: the denoiser must return a float32 array" in message
    assert "Traceback" not in message and "During handling" not in message
    assert run.reports[scribbling].failed
    assert f"plug-in {SCRIBBLING_DENOISER!r} modified its input color" in run.reports[scribbling].longreprtext


def test_without_options_nothing_is_added(bench_env):
    code, run = _run_bench(str(BENCH / "test_bench_kdtree.py"), str(BENCH / "test_bench_reconstruction.py"),
                           "--collect-only", "--bench-scenes", SCENE)
    assert code == pytest.ExitCode.OK
    assert not [node for node in run.collected if "plugin:" in node]
    traversal = [node for node in run.collected if "::test_traversal[" in node]
    assert traversal == [f"bench/test_bench_kdtree.py::test_traversal[{_id(SCENE, kind, query, name)}]"
                         for kind in RAY_KINDS for query in QUERIES for name in INTERSECTORS]
    assert [node.split("[")[1] for node in run.collected if "::test_reconstruction[" in node] == [
        "denoise-oidn]", "denoise-ours]", "superres-bicubic]", "superres-ours]"]


def test_a_plugin_that_does_not_load_is_a_usage_error(bench_env, capsys):
    # from the command line: exit status 4 and one line naming the plug-in, no traceback
    completed = subprocess.run([sys.executable, "-m", "pytest", "bench/test_bench_kdtree.py", "--collect-only", "-q",
                                "-p", "no:cacheprovider", "--bench-accelerator", f"{BRUTE_FORCE},no_such_module:make"],
                               cwd=ROOT, capture_output=True, text=True, timeout=120,
                               env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(EXAMPLES_SRC),
                                                                                            os.environ.get("PYTHONPATH"))))})
    assert completed.returncode == pytest.ExitCode.USAGE_ERROR, completed.stdout + completed.stderr
    assert "ERROR: --bench-accelerator: plug-in 'no_such_module:make': cannot import it (ModuleNotFoundError" in completed.stderr
    assert "Traceback" not in completed.stdout + completed.stderr

    code, run = _run_bench(str(BENCH / "test_bench_reconstruction.py"), "--collect-only",
                           "--bench-denoiser", "no-such-denoiser")
    assert code == pytest.ExitCode.USAGE_ERROR and not run.collected
    error = capsys.readouterr().err
    assert "ERROR: --bench-denoiser: plug-in 'no-such-denoiser': no such name in entry-point group 'kdtrace.denoisers'" in error
    assert "oidn" in error  # the installed names are listed
