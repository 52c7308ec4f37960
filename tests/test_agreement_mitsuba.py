"""Proof of agreement with Mitsuba 3: per-pixel Z-tests and relMSE slopes.

Statistics on synthetic data first (known answers), then our path tracer against
Mitsuba 3 references rendered by ``references.mitsuba.render_reference`` (cached in the
working directory's ``.cache/kdtrace/mitsuba`` by content hash; the first run renders
them, about 30 s on two cores; later runs take ~60 s). The Z-tests use 32x32 images
with 256 spp on both sides; the slope tests 128x128 images with balanced seeds against
a 1024-spp reference. Larger scenes run under ``-m slow``.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from kdtrace.imageio import read_exr
from references import ztest as zt

SEED = 20261122
#: Z-test settings: our spp, Mitsuba's spp, resolution.
Z_SPP, Z_REF_SPP, Z_SIZE = 256, 256, 32
#: Slope settings: spp levels, resolution, reference spp and seed.
SLOPE_SPPS = (4, 8, 16, 32)
SLOPE_SIZE, SLOPE_REF_SPP, SLOPE_REF_SEED = 128, 1024, 99


@pytest.fixture
def rng():
    return np.random.default_rng(SEED)


# ------------------------------------------------------------------ statistics on synthetic data
def test_sidak_formula():
    assert zt.sidak_alpha(0.01, 1) == pytest.approx(0.01, rel=1e-12)
    for m in (2, 3072, 10**6):
        each = zt.sidak_alpha(0.01, m)
        assert (1.0 - each) ** m == pytest.approx(0.99, rel=1e-9)
        assert 0.01 / m < each < 0.01 / m * 1.01  # just above Bonferroni
    with pytest.raises(ValueError):
        zt.sidak_alpha(0.0, 10)
    with pytest.raises(ValueError):
        zt.sidak_alpha(0.01, 0)


def test_gaussian_images_with_known_variance_pass_at_the_expected_rate(rng):
    trials, shape = 300, (32, 32, 3)
    sigma_a = rng.uniform(0.01, 0.2, shape)
    sigma_b = rng.uniform(0.01, 0.2, shape)
    truth = rng.uniform(0.0, 1.0, shape)
    any_failed, small_p = 0, []
    for _ in range(trials):
        a = truth + sigma_a * rng.standard_normal(shape)
        b = truth + sigma_b * rng.standard_normal(shape)
        result = zt.z_test(a, sigma_a**2, b, sigma_b**2)
        assert result.passed and result.tests == a.size
        any_failed += bool(result.pixel_failed.any())
        small_p.append(np.mean(result.p_value < 0.05))
    # Family-wise rate 1 %: Binomial(300, 0.01) has mean 3, P(> 10) < 1e-3.
    assert any_failed <= 10
    assert np.mean(small_p) == pytest.approx(0.05, abs=0.003)  # p-values are uniform


def _estimated(rng, truth, sigma, n):
    """Sample mean and variance of the mean of ``n`` Gaussian samples per element."""
    samples = truth + sigma * rng.standard_normal((n, *truth.shape))
    return samples.mean(axis=0), samples.var(axis=0, ddof=1) / n


def test_welch_keeps_the_rate_when_variances_are_estimated_from_few_samples(rng):
    trials, n, shape = 200, 16, (32, 32, 3)
    truth = rng.uniform(0.0, 1.0, shape)
    sigma = rng.uniform(0.05, 0.5, shape)
    welch_failed = normal_failed = 0
    for _ in range(trials):
        a, var_a = _estimated(rng, truth, sigma, n)
        b, var_b = _estimated(rng, truth, sigma, n)
        welch_failed += bool(zt.z_test(a, var_a, b, var_b, n, n).pixel_failed.any())
        normal_failed += bool(zt.z_test(a, var_a, b, var_b).pixel_failed.any())
    assert welch_failed <= 8  # about 1 % of 200
    assert normal_failed >= 15  # ~15 %: the normal tail is far too thin for estimated variances


def test_shifted_image_fails(rng):
    shape = (64, 64, 3)
    truth = rng.uniform(0.2, 1.0, shape)
    sigma = np.full(shape, 0.05)
    a = truth + sigma * rng.standard_normal(shape)
    b = truth + sigma * rng.standard_normal(shape)
    whole = zt.z_test(a + 0.5, sigma**2, b, sigma**2)  # a 7-sigma bias everywhere
    assert not whole.passed and whole.pass_rate < 0.01
    assert not zt.z_test(a * 1.5, sigma**2, b, sigma**2).passed  # a 50 % gain

    pixels = shape[0] * shape[1]
    for count, should_pass in ((int(0.01 * pixels), False), (int(0.001 * pixels), True)):
        shifted = a.copy()
        rows, cols = np.unravel_index(rng.choice(pixels, count, replace=False), shape[:2])
        shifted[rows, cols, 1] += 1.0  # 14 sigma in the green channel only
        result = zt.z_test(shifted, sigma**2, b, sigma**2)
        assert result.pixel_failed[rows, cols].all()
        assert result.passed is should_pass, (count, result.pass_rate)


def test_noise_free_pixels_compare_to_float32_rounding():
    zero = np.zeros((1, 4, 3))
    b = np.array([[[17.0, 12.0, 4.0], [0.0, 0.0, 0.0], [0.78, 0.78, 0.78], [1.0, 1.0, 1.0]]])
    a = b.copy()
    a[0, 2] = np.float32(0.78) * (1 + 2.0**-23)  # one float32 ulp away
    result = zt.z_test(a, zero, b, zero)
    assert result.passed and result.noise_free == 12 and result.tests == 0
    a[0, 3, 0] = 1.001
    a[0, 0, 2] = np.nan
    result = zt.z_test(a, zero, b, zero)
    assert result.pixel_failed.tolist() == [[True, False, False, True]]
    # one side noisy, the other noise-free: an ordinary test
    noisy = zt.z_test(np.array([[[1.1]]]), np.array([[[0.01]]]), np.array([[[1.0]]]), np.array([[[0.0]]]))
    assert noisy.tests == 1 and noisy.z[0, 0, 0] == pytest.approx(1.0)


def test_slope_fit_and_relmse():
    spp = np.array([4, 8, 16, 32])
    assert zt.loglog_slope(spp, 0.3 / spp) == pytest.approx(-1.0, abs=1e-12)
    assert zt.loglog_slope(spp, 2.0 / spp**2) == pytest.approx(-2.0, abs=1e-12)
    # a bias floor flattens the curve beyond the tolerance
    assert zt.loglog_slope(spp, 0.3 / spp + 0.005) > -1.0 + zt.SLOPE_TOLERANCE
    with pytest.raises(ValueError):
        zt.loglog_slope(spp, np.array([0.1, 0.0, 0.1, 0.1]))

    # relMSE subtracts the reference's own variance: expectation = mean(var_a / (b^2 + eps))
    rng = np.random.default_rng(SEED)
    shape = (200, 200, 3)
    truth = rng.uniform(0.0, 1.0, shape)
    var_a, var_b = 0.01, 0.004
    a = truth + np.sqrt(var_a) * rng.standard_normal(shape)
    b = truth + np.sqrt(var_b) * rng.standard_normal(shape)
    expected = np.mean(var_a / (truth**2 + zt.RELMSE_EPSILON))
    assert zt.relmse_variance_corrected(a, b, np.full(shape, var_b)) == pytest.approx(expected, rel=0.05)
    assert zt.relmse_variance_corrected(a, b) > 1.2 * expected  # without the subtraction


def test_failure_artefacts(tmp_path, rng):
    shape = (8, 10, 3)
    a = rng.uniform(0.0, 1.0, shape).astype(np.float32)
    var = np.full(shape, 1e-4)
    result = zt.z_test(a + 0.1, var, a, var)
    files = zt.write_failure_artefacts(tmp_path / "failure", a + 0.1, a, result, extra={"scene": "synthetic"})
    names = {path.name for path in files.values()}
    assert {"ours.exr", "reference.exr", "error_sigma.exr", "p_value.exr", "ours.png", "reference.png",
            "error_sigma.png", "p_value.png", "failed.png", "summary.json"} <= names
    assert read_exr(tmp_path / "failure" / "error_sigma.exr").shape == shape
    assert read_exr(tmp_path / "failure" / "p_value.exr").shape[:2] == shape[:2]
    summary = json.loads((tmp_path / "failure" / "summary.json").read_text())
    assert summary["scene"] == "synthetic" and summary["passed"] is False
    assert not list((tmp_path / "failure").glob(".*"))  # no temporary files left


def test_balanced_seeds():
    seeds = zt.balanced_seeds((4, 8, 16, 32), 100)
    assert [len(level) for level in seeds] == [8, 4, 2, 1]
    flat = [s for level in seeds for s in level]
    assert len(set(flat)) == len(flat) and flat[0] == 100


# ------------------------------------------------------------------ against Mitsuba 3
def _load(name: str):
    from kdtrace.scenes import load_scene

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # MTL keys the loader does not use
        return load_scene(name)


@pytest.fixture(scope="module")
def mitsuba():
    return pytest.importorskip("mitsuba")


@pytest.fixture(scope="module")
def scenes():
    """Scene name -> (scene, local KD-tree), loaded once per module."""
    from kdtrace.kdtree import build_kdtree

    cache = {}

    def get(name: str):
        if name not in cache:
            scene = _load(name)
            cache[name] = (scene, build_kdtree(scene, "local"))
        return cache[name]

    return get


def _check_z_test(scenes, tmp_path, name: str, max_depth: int, spp: int = Z_SPP, ref_spp: int = Z_REF_SPP,
                  width: int = Z_SIZE, height: int = Z_SIZE) -> None:
    scene, tree = scenes(name)
    comparison = zt.compare_scene(scene, spp, ref_spp, max_depth, SEED, width, height, tree=tree)
    result = comparison.result
    if not result.passed:
        folder = tmp_path / f"{name}-d{max_depth}"
        zt.write_failure_artefacts(folder, comparison.ours.rgb, comparison.reference.rgb, result,
                                   extra=comparison.summary())
        pytest.fail(f"{name} (max_depth {max_depth}) disagrees with Mitsuba: pass rate {result.pass_rate:.4f} "
                    f"< {result.pass_fraction} ({int(result.pixel_failed.sum())} pixels failed, max |z| "
                    f"{np.abs(result.z).max():.1f}); artefacts in {folder}")
    assert result.tests > 0.25 * result.z.size  # the test saw noise (sky and emitters are noise-free)


def _check_slope(scenes, name: str, max_depth: int, width: int = SLOPE_SIZE, height: int = SLOPE_SIZE,
                 ref_spp: int = SLOPE_REF_SPP, renders_at_max: int = 1) -> None:
    from references.mitsuba import render_reference

    scene, tree = scenes(name)
    reference = render_reference(scene, ref_spp, max_depth, SLOPE_REF_SEED, width, height)
    seeds = zt.balanced_seeds(SLOPE_SPPS, SEED, renders_at_max)
    values, slope = zt.relmse_curve(scene, SLOPE_SPPS, reference, max_depth, seeds, width, height, tree=tree)
    assert abs(slope + 1.0) <= zt.SLOPE_TOLERANCE, (
        f"{name}: relMSE over spp {SLOPE_SPPS} = {np.round(values, 5).tolist()} has log-log slope {slope:.3f}, "
        f"not -1 +- {zt.SLOPE_TOLERANCE}: a bias against Mitsuba")


@pytest.mark.parametrize(("name", "max_depth"), [
    ("cbox-original", 3), ("cbox-mirror", 3), ("cbox-sphere", 3), ("cbox-sphere", 5),
])
def test_z_test_against_mitsuba(mitsuba, scenes, tmp_path, name, max_depth):
    _check_z_test(scenes, tmp_path, name, max_depth)


@pytest.mark.parametrize(("name", "renders_at_max"), [("cbox-original", 1), ("cbox-mirror", 2), ("cbox-sphere", 2)])
def test_relmse_falls_as_one_over_spp(mitsuba, scenes, name, renders_at_max):
    # Mirror and glass add caustic paths (found only by BSDF sampling): rare, bright samples
    # make their relMSE estimates noisier, so they get twice the renders per spp level.
    _check_slope(scenes, name, max_depth=3, renders_at_max=renders_at_max)


def test_main_compare_writes_the_artefacts(mitsuba, tmp_path):
    summary = zt.main_compare("cbox-original", spp=16, ref_spp=16, max_depth=2, seed=SEED, width=16, height=16,
                              out_dir=tmp_path / "compare")
    assert summary["scene"] == "cbox-original" and summary["pixels"] == 256
    assert 0.0 <= summary["pass_rate"] <= 1.0 and summary["relmse"] >= -1.0
    for path in summary["files"].values():
        assert (tmp_path / "compare").joinpath(path.rsplit("/", 1)[-1]).is_file()
    with pytest.raises(ValueError, match="spp >= 2"):
        zt.main_compare("cbox-original", spp=1, ref_spp=16, max_depth=2, seed=SEED, width=8, height=8,
                        out_dir=tmp_path / "bad")


@pytest.mark.slow
@pytest.mark.parametrize(("name", "size"), [("crytek-sponza", (48, 32)), ("car", (48, 32)), ("bunny", (32, 32))])
def test_z_test_large_scenes(mitsuba, scenes, tmp_path, name, size):
    _check_z_test(scenes, tmp_path, name, 3, spp=128, ref_spp=128, width=size[0], height=size[1])


@pytest.mark.slow
def test_relmse_slope_crytek_sponza(mitsuba, scenes):
    _check_slope(scenes, "crytek-sponza", max_depth=3, width=96, height=64, ref_spp=512)
