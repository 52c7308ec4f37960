"""Plug-ins: the example package through check-embree, bad plug-ins' errors, entry points.

The example package (``examples/kdtrace-example-plugins``) is put on ``sys.path``
rather than installed, and named by ``module:factory``; entry-point lookup is tested
with a fake entry point, and with our own ones from kdtrace's ``pyproject.toml``.
"""

from __future__ import annotations

import importlib.metadata
import textwrap
import tomllib
from pathlib import Path

import numpy as np
import pytest

from kdtrace import plugins
from kdtrace.plugins import ACCELERATOR_GROUP, DENOISER_GROUP, PluginError, load_accelerator, load_denoiser, resolve_factory
from kdtrace.procedural import random_soup

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "kdtrace-example-plugins"
BRUTE_FORCE = "kdtrace_example_plugins.brute_force:make"
BILATERAL = "kdtrace_example_plugins.bilateral:make"


@pytest.fixture
def example_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE / "src"))


@pytest.fixture(scope="module")
def soup():
    return random_soup(200, seed=3)


def _rays(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Rays from random points to random points near the random soup's triangles (``[-1, 1]^3``)."""
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-1.5, 1.5, (n, 3))
    return origins, rng.uniform(-1.0, 1.0, (n, 3)) - origins


def _frame(seed: int = 0) -> tuple[np.ndarray, ...]:
    """Clean and noisy float32 radiance of two walls of different albedo and normal, with albedo and normal."""
    rng = np.random.default_rng(seed)
    albedo = np.zeros((48, 48, 3), np.float32)
    albedo[:, :24], albedo[:, 24:] = (0.8, 0.2, 0.2), (0.2, 0.8, 0.2)
    normal = np.zeros((48, 48, 3), np.float32)
    normal[:24], normal[24:] = (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)
    clean = (albedo * np.linspace(0.5, 1.5, 48)[None, :, None]).astype(np.float32)
    return clean, (clean * rng.gamma(4.0, 0.25, clean.shape)).astype(np.float32), albedo, normal


def test_example_accelerator_through_check_embree(shared_scenes, example_on_path, capsys):
    from kdtrace.cli import main

    assert main(["check-embree", "cbox-original", "--rays", "2000", "--accelerator", BRUTE_FORCE]) == 0
    out = capsys.readouterr().out
    assert f"| {BRUTE_FORCE}" in out and "| local" not in out
    assert "wrong (the float64 oracle finds a nearer hit): 0" in out
    assert "unexplained disagreements: 0" in out
    assert "ours is exact and Embree is not" in out


def test_example_accelerator_matches_our_tree(example_on_path, soup):
    ours = load_accelerator("local", soup)
    theirs = load_accelerator(BRUTE_FORCE, soup)
    origins, directions = _rays(3000)
    t_ours, tri_ours, _, _ = ours.intersect(origins, directions)
    t, tri, u, v = theirs.intersect(origins, directions, 0.0, np.inf)
    assert (tri >= 0).sum() > 200 and np.mean(tri == tri_ours) > 0.999
    np.testing.assert_allclose(t[tri >= 0], t_ours[tri >= 0], rtol=1e-5)
    assert np.array_equal(theirs.occluded(origins, directions, np.inf), tri >= 0)
    assert theirs.stats["references"] == len(soup.triangles)


def test_example_denoiser_removes_noise_and_keeps_edges(example_on_path):
    denoise = load_denoiser(BILATERAL)
    clean, noisy, albedo, normal = _frame()
    out = denoise(noisy, albedo, normal)
    assert out.dtype == np.float32 and out.shape == clean.shape
    assert np.mean((out - clean) ** 2) < np.mean((noisy - clean) ** 2) / 10
    # The albedo edge between columns 23 and 24 stays sharp: green/red is 1/4 and 4 on its two sides.
    assert (out[:, 23, 1] / out[:, 23, 0]).max() < 0.4 and (out[:, 24, 1] / out[:, 24, 0]).min() > 2.5


BAD_PLUGINS = textwrap.dedent('''
    import numpy as np

    class Answer:
        """Answers every ray with a miss, then lets ``spoil`` damage the answer."""
        def __init__(self, spoil):
            self.spoil = spoil
        def intersect(self, origins, directions, tmin=0.0, tmax=np.inf):
            n = len(origins)
            answer = [np.full(n, 2.0), np.zeros(n, np.int32), np.zeros(n), np.zeros(n)]
            return self.spoil(answer)
        def occluded(self, origins, directions, tmax):
            return np.zeros(len(origins), np.int8)

    def boom(answer):
        raise RuntimeError("the traversal stack overflowed")

    def short(answer):
        answer[0] = answer[0][:-1]
        return tuple(answer)

    def nan(answer):
        answer[0][5] = np.nan
        return tuple(answer)

    def out_of_range(answer):
        answer[1][7] = 10**6
        return tuple(answer)

    def float_tri(answer):
        answer[1] = answer[1].astype(np.float64)
        return tuple(answer)

    def raises(scene): return Answer(boom)
    def wrong_shape(scene): return Answer(short)
    def returns_nan(scene): return Answer(nan)
    def tri_out_of_range(scene): return Answer(out_of_range)
    def tri_not_integer(scene): return Answer(float_tri)
    def not_an_accelerator(scene): return object()
    def broken_factory(scene): raise OSError("no licence")

    def denoise_float64(): return lambda color, albedo, normal: color.astype(np.float64)
    def denoise_shape(): return lambda color, albedo, normal: color[1:]
    def denoise_nan(): return lambda color, albedo, normal: np.full_like(color, np.nan)
    def denoise_raises():
        def fn(color, albedo, normal):
            raise MemoryError("out of memory")
        return fn
''')


@pytest.fixture
def bad_plugins(tmp_path, monkeypatch):
    (tmp_path / "bad_plugins.py").write_text(BAD_PLUGINS)
    monkeypatch.syspath_prepend(str(tmp_path))


@pytest.mark.parametrize(("factory", "message"), [
    ("raises", "intersect raised RuntimeError: the traversal stack overflowed"),
    ("wrong_shape", "intersect's t must be a float array of shape (50,), got array of shape (49,), dtype float64"),
    ("returns_nan", "intersect returned t[5] = NaN"),
    ("tri_out_of_range", "intersect returned tri[7] = 1000000, outside [-1, 200)"),
    ("tri_not_integer", "intersect's tri must be a integer array of shape (50,), got array of shape (50,), dtype float64"),
])
def test_bad_accelerator_answers_name_the_plugin(bad_plugins, soup, factory, message):
    accelerator = load_accelerator(f"bad_plugins:{factory}", soup)
    with pytest.raises(PluginError, match=f"plug-in 'bad_plugins:{factory}': ") as error:
        accelerator.intersect(*_rays(50))
    assert message in str(error.value)


def test_bad_accelerator_factories_and_occlusion(bad_plugins, soup):
    with pytest.raises(PluginError, match="'bad_plugins:not_an_accelerator': the factory returned a object"):
        load_accelerator("bad_plugins:not_an_accelerator", soup)
    with pytest.raises(PluginError, match="'bad_plugins:broken_factory': the factory raised OSError: no licence"):
        load_accelerator("bad_plugins:broken_factory", soup)
    with pytest.raises(PluginError, match="'bad_plugins:no_such': cannot import it"):
        load_accelerator("bad_plugins:no_such", soup)
    with pytest.raises(PluginError, match=r"occluded's answer must be a bool array of shape \(50,\), got .* dtype int8"):
        load_accelerator("bad_plugins:raises", soup).occluded(*_rays(50), np.inf)


@pytest.mark.parametrize(("factory", "message"), [
    ("denoise_float64", "must return a float32 array of shape (48, 48, 3), got array of shape (48, 48, 3), dtype float64"),
    ("denoise_shape", "must return a float32 array of shape (48, 48, 3), got array of shape (47, 48, 3), dtype float32"),
    ("denoise_nan", "the denoiser returned 6912 NaN or infinite values"),
    ("denoise_raises", "denoising raised MemoryError: out of memory"),
])
def test_bad_denoiser_outputs_name_the_plugin(bad_plugins, factory, message):
    _, noisy, albedo, normal = _frame()
    with pytest.raises(PluginError, match=f"plug-in 'bad_plugins:{factory}': ") as error:
        load_denoiser(f"bad_plugins:{factory}")(noisy, albedo, normal)
    assert message in str(error.value)


def test_cli_reports_a_bad_plugin(shared_scenes, bad_plugins, capsys):
    from kdtrace.cli import main

    assert main(["check-embree", "cbox-original", "--rays", "100", "--accelerator", "local,bad_plugins:returns_nan"]) == 2
    assert "kdtrace: error: plug-in 'bad_plugins:returns_nan': intersect returned t[5] = NaN" in capsys.readouterr().err


def test_short_names_come_from_entry_points(example_on_path, monkeypatch, soup):
    fake = importlib.metadata.EntryPoint(name="brute-force", value=BRUTE_FORCE, group=ACCELERATOR_GROUP)
    monkeypatch.setattr(plugins, "entry_points", lambda group: [fake] if group == ACCELERATOR_GROUP else [])
    accelerator = load_accelerator("brute-force", soup)
    assert accelerator.spec == "brute-force" and accelerator.intersect(*_rays(20))[0].dtype == np.float64
    with pytest.raises(PluginError, match="'bvh8': no such name in entry-point group 'kdtrace.accelerators'; installed: brute-force"):
        load_accelerator("bvh8", soup)
    with pytest.raises(PluginError, match="'oidn': no such name in entry-point group 'kdtrace.denoisers'; installed: none"):
        load_denoiser("oidn")


def test_our_methods_and_the_examples_are_registered(example_on_path):
    from references.embree import EmbreeIntersector

    assert resolve_factory("local", ACCELERATOR_GROUP) is plugins.local_kdtree
    assert resolve_factory("naive", ACCELERATOR_GROUP) is plugins.naive_kdtree
    assert resolve_factory("embree", ACCELERATOR_GROUP) is EmbreeIntersector
    assert resolve_factory("oidn", DENOISER_GROUP) is plugins.oidn
    # The example package's entry points name factories that resolve (what `pip install` would register).
    registered = tomllib.loads((EXAMPLE / "pyproject.toml").read_text())["project"]["entry-points"]
    assert set(registered) == {ACCELERATOR_GROUP, DENOISER_GROUP}
    for group, points in registered.items():
        for value in points.values():
            assert callable(resolve_factory(value, group))
