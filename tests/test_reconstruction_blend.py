"""The validated blend of the denoiser with its input (reconstruction/blend.py), on synthetic images."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruction.blend import BlendWeights, optimal_weight


def _images(seed: int, noise: float, error: float, count: int = 2, size: int = 64):
    """Truth in (0.2, 0.8); noisy = truth + noise, denoised = truth + a smooth error; references exact."""
    rng = np.random.default_rng(seed)
    truth = [rng.uniform(0.2, 0.8, (size, size, 3)) for _ in range(count)]
    noisy = [t + noise * rng.standard_normal(t.shape) for t in truth]
    denoised = [t + error * np.sin(np.arange(size) / 5.0)[None, :, None] for t in truth]
    return noisy, denoised, truth


def test_weight_is_the_least_squares_blend():
    noisy, denoised, truth = _images(0, noise=0.05, error=0.05)
    w = optimal_weight(noisy, denoised, truth)
    grid = np.linspace(0, 1, 201)
    errors = [sum(np.sum((w_ * d + (1 - w_) * n - t) ** 2) for n, d, t in zip(noisy, denoised, truth, strict=True))
              for w_ in grid]
    assert w == pytest.approx(grid[int(np.argmin(errors))], abs=0.005)
    assert 0.2 < w < 0.8


def test_a_clean_denoiser_gets_weight_one_and_a_useless_one_zero():
    noisy, denoised, truth = _images(1, noise=0.1, error=0.0)
    assert optimal_weight(noisy, denoised, truth) == pytest.approx(1.0, abs=0.02)
    noisy, denoised, truth = _images(2, noise=0.001, error=0.2)
    assert optimal_weight(noisy, denoised, truth) == pytest.approx(0.0, abs=0.02)
    assert optimal_weight(noisy, noisy, truth) == 1.0  # nothing to blend


def test_a_noisy_reference_leaves_the_weight_unbiased_and_the_bound_lies_below():
    noisy, denoised, truth = _images(3, noise=0.05, error=0.05, count=8)
    exact = optimal_weight(noisy, denoised, truth)
    rng = np.random.default_rng(4)
    references = [t + 0.05 * rng.standard_normal(t.shape) for t in truth]
    assert optimal_weight(noisy, denoised, references) == pytest.approx(exact, abs=0.05)
    bound = optimal_weight(noisy, denoised, references, quantile=0.1, seed=5)
    assert bound < optimal_weight(noisy, denoised, references)
    assert bound == optimal_weight(noisy, denoised, references, quantile=0.1, seed=5)  # seeded


def test_weights_interpolate_in_log_spp_and_blend():
    weights = BlendWeights((1, 4, 16), (1.0, 0.5, 0.0), views=2)
    assert weights.weight(1) == 1.0 and weights.weight(2) == pytest.approx(0.75) and weights.weight(64) == 0.0
    noisy, denoised = np.zeros((2, 2, 3), np.float32), np.ones((2, 2, 3), np.float32)
    blended = weights.apply(noisy, denoised, 4)
    assert blended.dtype == np.float32 and np.all(blended == 0.5)


@pytest.mark.parametrize("spp, values", [((), ()), ((4, 1), (1.0, 1.0)), ((1, 2), (1.0, 1.5)), ((0,), (1.0,))])
def test_bad_weights_are_refused(spp, values):
    with pytest.raises(ValueError):
        BlendWeights(spp, values, views=1)


def test_bad_calls_are_refused():
    weights = BlendWeights((4,), (0.5,), views=1)
    with pytest.raises(ValueError, match="spp"):
        weights.weight(0)
    with pytest.raises(ValueError, match="shape"):
        weights.apply(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)), 4)
