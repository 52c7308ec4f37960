"""The validated blend of the denoiser with its input (reconstruction/blend.py), on synthetic images."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from reconstruction import blend
from reconstruction.blend import BlendWeights


def _images(seed: int, noise: float, error: float, count: int = 2, size: int = 64):
    """Truth in (0.2, 0.8); noisy = truth + noise, denoised = truth + a smooth error; references exact."""
    rng = np.random.default_rng(seed)
    truth = [rng.uniform(0.2, 0.8, (size, size, 3)) for _ in range(count)]
    noisy = [t + noise * rng.standard_normal(t.shape) for t in truth]
    denoised = [t + error * np.sin(np.arange(size) / 5.0)[None, :, None] for t in truth]
    return noisy, denoised, truth


def _least_squares_weight(noisy, denoised, references) -> float:
    """The obvious reference: the closed-form minimiser of the squared error, clipped to [0, 1]."""
    numerator = sum(np.sum((d - n) * (r - n)) for n, d, r in zip(noisy, denoised, references, strict=True))
    denominator = sum(np.sum((d - n) ** 2) for n, d in zip(noisy, denoised, strict=True))
    return float(np.clip(numerator / denominator, 0.0, 1.0))


def _linear_curves(noisy, denoised, references, weights=blend.CAP_GRID):
    return np.concatenate([blend.block_error_curves(n, d, r, weights)
                           for n, d, r in zip(noisy, denoised, references, strict=True)], axis=1)


def test_the_minimiser_of_the_curves_is_the_least_squares_blend():
    noisy, denoised, truth = _images(0, noise=0.05, error=0.05)
    w = blend.lower_bound_weight(_linear_curves(noisy, denoised, truth), blend.CAP_GRID, quantile=None)
    assert w == pytest.approx(_least_squares_weight(noisy, denoised, truth), abs=0.005)
    assert 0.2 < w < 0.8


def test_a_clean_denoiser_gets_weight_one_and_a_useless_one_zero():
    for seed, noise, error, expected in ((1, 0.1, 0.0, 1.0), (2, 0.001, 0.2, 0.0)):
        noisy, denoised, truth = _images(seed, noise=noise, error=error)
        assert blend.lower_bound_weight(_linear_curves(noisy, denoised, truth), blend.CAP_GRID) == pytest.approx(
            expected, abs=0.02)


def test_a_noisy_reference_leaves_the_weight_unbiased_and_the_bound_lies_below():
    noisy, denoised, truth = _images(3, noise=0.05, error=0.05, count=8)
    exact = _least_squares_weight(noisy, denoised, truth)
    rng = np.random.default_rng(4)
    references = [t + 0.05 * rng.standard_normal(t.shape) for t in truth]
    curves = _linear_curves(noisy, denoised, references)
    assert blend.lower_bound_weight(curves, blend.CAP_GRID, quantile=None) == pytest.approx(exact, abs=0.05)
    bound = blend.lower_bound_weight(curves, blend.CAP_GRID, seed=5)
    assert bound < blend.lower_bound_weight(curves, blend.CAP_GRID, quantile=None)
    assert bound == blend.lower_bound_weight(curves, blend.CAP_GRID, seed=5)  # seeded
    with pytest.raises(ValueError, match="shape"):
        blend.lower_bound_weight(curves[:-1], blend.CAP_GRID)
    curves[3, 2] = np.nan
    with pytest.raises(ValueError, match="finite"):
        blend.lower_bound_weight(curves, blend.CAP_GRID)


def test_view_error_curves_measure_each_space_of_the_blend():
    """Each space's curve summed over blocks is that space's error of the blended image (the metrics' own code)."""
    from reconstruction import metrics

    noisy, denoised, truth = (images[0] for images in _images(6, noise=0.08, error=0.04, size=40))
    exposure = 1.3
    curves = blend.view_error_curves(noisy, denoised, truth, exposure)
    assert set(curves) == set(blend.SPACES)
    assert all(curve.shape == (len(blend.FIT_GRID), 25) for curve in curves.values())  # 5 x 5 blocks of 8
    pixels = truth.size
    for k in (0, 7, 20):
        image = noisy + blend.FIT_GRID[k] * (denoised - noisy)
        shown = metrics.display_metrics(image, truth, exposure)
        assert -10 * np.log10(curves["linear"][k].sum() / pixels) == pytest.approx(metrics.psnr(image, truth))
        assert -10 * np.log10(curves["display"][k].sum() / pixels) == pytest.approx(shown["display_psnr"])
        assert curves["flip"][k].sum() / truth[..., 0].size == pytest.approx(shown["flip"], rel=1e-5)
    # a bound without the bootstrap is a weight of the grid
    bounds = {space: blend.lower_bound_weight(curve, blend.FIT_GRID, quantile=None) for space, curve in curves.items()}
    assert all(bound in blend.FIT_GRID for bound in bounds.values())


def test_weights_interpolate_in_log_spp_and_blend():
    weights = BlendWeights((1, 4, 16), (1.0, 0.5, 0.0), views=2,
                           by_space={"linear": (1.0, 0.6, 0.0), "flip": (1.0, 0.5, 0.1)})
    assert weights.limiting_space(1) == "linear/flip" and weights.limiting_space(4) == "flip"
    assert weights.weight(1) == 1.0 and weights.weight(2) == pytest.approx(0.75) and weights.weight(64) == 0.0
    noisy, denoised = np.zeros((2, 2, 3), np.float32), np.ones((2, 2, 3), np.float32)
    blended = weights.apply(noisy, denoised, 4)
    assert blended.dtype == np.float32 and np.all(blended == 0.5)


@pytest.mark.parametrize("spp, values", [((), ()), ((4, 1), (1.0, 1.0)), ((1, 2), (1.0, 1.5)), ((0,), (1.0,))])
def test_bad_weights_are_refused(spp, values):
    with pytest.raises(ValueError):
        BlendWeights(spp, values, views=1)


def test_bad_calls_are_refused():
    with pytest.raises(ValueError, match="one value per spp"):
        BlendWeights((1, 4), (0.5, 0.5), views=1, by_space={"flip": (0.5,)})
    weights = BlendWeights((4,), (0.5,), views=1)
    with pytest.raises(ValueError, match="spp"):
        weights.weight(0)
    with pytest.raises(ValueError, match="shape"):
        weights.apply(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)), 4)


# ------------------------------------------------------------------ the frame's own cap
def _halves(seed: int, noise: float, error: float, size: int = 96):
    """Two independent halves of a frame: truth + noise of variance ``2 noise^2`` each (the frame: ``noise^2``).

    The "denoiser" returns the truth plus an error of its own, independent of the input's noise.
    """
    rng = np.random.default_rng(seed)
    truth = rng.uniform(0.2, 0.8, (size, size, 3))
    halves = [SimpleNamespace(rgb=truth + np.sqrt(2.0) * noise * rng.standard_normal(truth.shape),
                              albedo=np.ones_like(truth), stats={"spp": 2, "first_sample": 2 * k}) for k in range(2)]

    def denoise(rgb, albedo):
        return truth + error * rng.standard_normal(truth.shape)

    return truth, halves, denoise


def test_block_error_curves_are_the_clipped_squared_error_of_each_block():
    rng = np.random.default_rng(7)
    truth = rng.uniform(0.0, 1.2, (20, 13, 3))  # some pixels above 1: clipped by the metric; edge blocks smaller
    noisy, denoised = truth + 0.2 * rng.standard_normal(truth.shape), truth + 0.1 * np.sin(truth * 9.0)
    weights = np.array([0.0, 0.25, 0.618, 1.0])
    curves = blend.block_error_curves(noisy, denoised, truth, weights)
    assert curves.shape == (4, 3 * 2)  # blocks of 8: 3 rows x 2 columns
    for k, w in enumerate(weights):
        error = (np.clip(noisy + w * (denoised - noisy), 0, 1) - np.clip(truth, 0, 1)) ** 2
        for b, (row, column) in enumerate(np.ndindex(3, 2)):
            expected = error[8 * row : 8 * row + 8, 8 * column : 8 * column + 8].sum()
            assert curves[k, b] == pytest.approx(expected, rel=1e-12)
    assert np.argmin(blend.block_error_curves(noisy, truth, truth).sum(axis=1)) == len(blend.CAP_GRID) - 1
    with pytest.raises(ValueError, match="shapes differ"):
        blend.block_error_curves(noisy, denoised[:-1], truth)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        blend.block_error_curves(noisy, denoised, truth, np.array([0.5, 1.5]))


@pytest.mark.parametrize("noise, error", [(0.05, 0.05), (0.02, 0.1), (0.1, 0.03)])
def test_frame_cap_estimates_the_frames_optimal_weight_without_a_reference(noise, error):
    """Denoised error independent of the noise: the optimum is noise^2 / (noise^2 + error^2)."""
    truth, halves, denoise = _halves(11, noise, error)
    expected = noise**2 / (noise**2 + error**2)
    assert blend.frame_weight_cap(denoise, *halves, quantile=0.5) == pytest.approx(expected, abs=0.03)
    # The cap used is a lower bound: the bootstrap's 10% quantile, at most its median, and not far below it.
    lower = blend.frame_weight_cap(denoise, *halves)
    assert expected - 0.06 < lower <= blend.frame_weight_cap(denoise, *halves, quantile=0.5)
    assert blend.frame_weight_cap(denoise, *halves) == blend.frame_weight_cap(denoise, *halves)  # seeded


def test_the_cap_only_lowers_the_validated_weight_and_halves_combine():
    weights = BlendWeights((1, 4), (1.0, 0.5), views=2)
    assert weights.weight(4, cap=0.2) == 0.2 and weights.weight(4, cap=0.9) == 0.5
    with pytest.raises(ValueError, match="cap"):
        weights.weight(4, cap=1.5)
    _, halves, _ = _halves(3, 0.1, 0.1)
    rgb, albedo = blend.combine_halves(*halves)
    np.testing.assert_allclose(rgb, (halves[0].rgb + halves[1].rgb) / 2, rtol=1e-6)
    assert rgb.dtype == albedo.dtype == np.float32
    with pytest.raises(ValueError, match="adjacent"):
        blend.combine_halves(halves[1], halves[0])


def test_block_errors_kernel_propagates_nan_as_numpy():
    from reconstruction._blend_kernels import clipped_blend_block_errors

    rng = np.random.default_rng(11)
    noisy, change, goal = (rng.uniform(0.0, 1.0, (16, 24, 3)) for _ in range(3))
    noisy[3, 10, 1] = np.nan  # block (0, 1)
    out = clipped_blend_block_errors(noisy, change, goal, 8, np.array([0.0, 0.5]))
    assert out.shape == (2, 6)
    assert np.isnan(out[:, 1]).all() and np.isfinite(np.delete(out, 1, axis=1)).all()


