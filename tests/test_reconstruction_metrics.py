"""Metrics (linear and display-referred) and baselines of the reconstruction stage."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reconstruction import baselines, metrics


def _smooth(height: int, width: int) -> np.ndarray:
    """A smooth colour image in [0.1, 0.9]: gradients and a low-frequency wave."""
    y, x = np.mgrid[0:height, 0:width] / max(height, width)
    return np.stack(
        [0.1 + 0.8 * x, 0.1 + 0.8 * y, 0.5 + 0.4 * np.sin(2 * np.pi * (x + y))], axis=2
    ).astype(np.float32)


def test_psnr_and_rmse_follow_the_paper_convention():
    reference = np.full((8, 8, 3), 0.5)
    test = reference + 0.1
    assert metrics.rmse(test, reference) == pytest.approx(0.1)
    assert metrics.psnr(test, reference) == pytest.approx(20.0)
    assert metrics.psnr(reference, reference) == math.inf
    # values are clipped to [0, 1] first (data range 1)
    assert metrics.rmse(np.full((4, 4), 3.0), np.ones((4, 4))) == 0.0
    assert metrics.psnr(np.full((4, 4, 1), -1.0), np.zeros((4, 4, 1))) == math.inf


def test_ssim_relmse_and_flip():
    reference = _smooth(32, 32)
    assert metrics.ssim(reference, reference) == pytest.approx(1.0)
    noisy = np.clip(reference + np.random.default_rng(0).normal(0, 0.1, reference.shape), 0, 1)
    assert 0 < metrics.ssim(noisy, reference) < 0.9
    hdr_reference = np.full((4, 4, 3), 10.0)
    assert metrics.relmse(hdr_reference * 1.1, hdr_reference) == pytest.approx(1.0 / 100.01)
    assert metrics.flip(reference, reference) == pytest.approx(0.0, abs=1e-6)
    assert 0 < metrics.flip(noisy, reference) < 1
    result = metrics.all_metrics(noisy, reference)
    assert set(result) == {"psnr", "rmse", "ssim", "relmse", "smape", "exposure", "display_psnr", "display_rmse",
                           "display_ssim", "flip"}


def test_smape_by_hand():
    reference = np.full((2, 2, 3), 1.0)
    assert metrics.smape(reference * 3, reference) == pytest.approx(2.0 / 4.01)
    assert metrics.smape(np.zeros((2, 2)), np.zeros((2, 2))) == 0.0


def test_the_display_space_exposes_the_reference_and_applies_the_srgb_curve():
    """A dark scene: linear PSNR sees almost nothing, the displayed image shows the error."""
    reference = np.full((16, 16, 3), 0.002)
    reference[:4] = 0.01  # the brightest 25% of the view: its 99th-percentile luminance
    test = reference * 1.5
    assert metrics.auto_exposure(reference) == pytest.approx(100.0)
    shown = metrics.display_metrics(test, reference)
    assert shown["exposure"] == pytest.approx(100.0)
    # by hand: the bright rows clip to 1 either way; the rest is srgb(0.3) against srgb(0.2)
    srgb = lambda v: 1.055 * v ** (1 / 2.4) - 0.055  # noqa: E731
    rmse = math.sqrt(0.75 * (srgb(0.3) - srgb(0.2)) ** 2)
    assert shown["display_rmse"] == pytest.approx(rmse)
    assert shown["display_psnr"] == pytest.approx(-20 * math.log10(rmse))
    assert metrics.psnr(test, reference) > 50 > shown["display_psnr"] + 25
    assert shown["flip"] > metrics.flip(test, reference)  # unexposed, the dark error is nearly invisible
    # an explicit exposure is used as given
    assert metrics.display_metrics(test, reference, exposure=1.0)["display_psnr"] == pytest.approx(
        metrics.psnr(metrics.to_display(test, 1.0), metrics.to_display(reference, 1.0)))
    error_map, mean = metrics.flip_map(test, reference, 100.0)
    assert error_map.shape == (16, 16) and mean == pytest.approx(float(error_map.mean()), rel=1e-5)


def test_an_exposure_that_cannot_be_defined_names_the_view():
    with pytest.raises(ValueError, match="view 3: no exposure: the reference's 99th-percentile luminance is 0"):
        metrics.auto_exposure(np.zeros((8, 8, 3)), "view 3")
    bad = np.ones((8, 8, 3))
    bad[0, 0, 1] = np.inf
    with pytest.raises(ValueError, match="view 3: no exposure: the reference has 1 NaN/inf"):
        metrics.auto_exposure(bad, "view 3")
    for exposure in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="exposure must be"):
            metrics.to_display(np.ones((2, 2, 3)), exposure)


def test_metrics_reject_bad_input():
    good = np.zeros((8, 8, 3))
    with pytest.raises(ValueError, match="differ in shape"):
        metrics.psnr(good, np.zeros((8, 9, 3)))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        metrics.psnr(np.zeros((8, 8, 2)), np.zeros((8, 8, 2)))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        metrics.flip(np.zeros((8, 8)), np.zeros((8, 8)))
    bad = good.copy()
    bad[0, 0, 0] = np.nan
    for metric in (metrics.psnr, metrics.rmse, metrics.ssim, metrics.relmse, metrics.flip):
        with pytest.raises(ValueError, match="1 NaN/inf"):
            metric(bad, good)
    with pytest.raises(ValueError, match="7×7"):
        metrics.ssim(np.zeros((4, 4)), np.zeros((4, 4)))


def test_oidn_removes_most_of_the_noise():
    clean = _smooth(64, 64)
    noisy = np.clip(clean + np.random.default_rng(1).normal(0, 0.1, clean.shape), 0, None).astype(np.float32)
    albedo = np.full_like(clean, 0.8)
    denoised = baselines.oidn(noisy, albedo)
    assert denoised.shape == clean.shape and denoised.dtype == np.float32
    gain = metrics.psnr(denoised, clean) - metrics.psnr(baselines.noisy_input(noisy), clean)
    assert gain > 5.0
    normal = np.zeros_like(clean)
    normal[:, :, 2] = 1.0
    assert metrics.psnr(baselines.oidn(noisy, albedo, normal), clean) - metrics.psnr(noisy, clean) > 5.0


def test_oidn_rejects_bad_buffers():
    color = np.ones((8, 8, 3), dtype=np.float32)
    with pytest.raises(ValueError, match="albedo must have the colour's shape"):
        baselines.oidn(color, np.ones((8, 4, 3)))
    with pytest.raises(ValueError, match="non-negative"):
        baselines.oidn(-color, color)
    color[2, 2, 1] = np.inf
    with pytest.raises(ValueError, match="NaN/inf"):
        baselines.oidn(color, np.ones_like(color))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        baselines.noisy_input(np.ones((8, 8)))


def test_upsamplers_beat_nearest_on_a_smooth_image():
    high = _smooth(64, 64)
    low = high.reshape(32, 2, 32, 2, 3).mean(axis=(1, 3))
    floor = metrics.psnr(baselines.nearest(low), high)
    for upsample in (baselines.bicubic, baselines.lanczos):
        result = upsample(low)
        assert result.shape == high.shape and result.dtype == np.float32
        assert 0.0 <= result.min() and result.max() <= 1.0
        assert metrics.psnr(result, high) > floor + 3.0


def test_a_display_space_superresolution_net_upsamples_the_shown_image_and_is_measured_as_it_displays():
    import torch

    from reconstruction import evaluate
    from reconstruction.models import Superresolution, superresolve

    rng = np.random.default_rng(3)
    dark = rng.uniform(0.0, 0.02, (16, 24, 3)).astype(np.float32)  # mean pixel 0.01: exposed ~50x
    bright = rng.uniform(0.2, 0.9, (16, 16, 3)).astype(np.float32)
    targets = [dark, bright]
    net = Superresolution("display")  # untrained: returns its bicubic input exactly
    assert net.config["kwargs"] == {"space": "display"} and Superresolution().config["kwargs"] == {}
    results = evaluate.superres_images(net, targets, with_lanczos=False)
    assert results["ours"]["display_psnr"] == pytest.approx(results["bicubic"]["display_psnr"], abs=1e-4)
    # the displayed output against the displayed target, computed directly
    exposures = metrics.display_exposures(targets)[1]
    squared = []
    for target, exposure in zip(targets, exposures, strict=True):
        low = evaluate.downsample_2x(target)
        shown = superresolve(net, metrics.to_display(low, exposure).astype(np.float32))
        squared.append((shown - metrics.to_display(target, exposure)) ** 2)
    direct = -10 * math.log10(np.mean(np.concatenate([s.ravel() for s in squared])))
    assert results["ours"]["display_psnr"] == pytest.approx(direct, abs=1e-3)
    # the linear net on the same targets upsamples radiance: another image, another score
    linear = evaluate.superres_images(Superresolution(), targets, with_lanczos=False)
    assert abs(linear["bicubic"]["display_psnr"] - results["bicubic"]["display_psnr"]) > 0.01
    with pytest.raises(ValueError, match="unknown superresolution space"):
        Superresolution("log")
    with torch.no_grad():
        assert torch.equal(net(torch.full((1, 1, 8, 8), 0.25)), torch.full((1, 1, 8, 8), 0.25))


def test_display_exposures_show_a_black_view_with_the_median_of_the_others():
    lit = [np.full((4, 4, 3), level, np.float32) for level in (0.5, 0.25, 0.125)]
    own, shown = metrics.display_exposures([lit[0], np.zeros((4, 4, 3), np.float32), *lit[1:]])
    assert own[1] is None and shown[1] == pytest.approx(4.0) and shown[0] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="all 1 references are black"):
        metrics.display_exposures([np.zeros((4, 4, 3))])


def test_display_metrics_are_reused_by_content_and_measured_again_when_anything_changes(isolated_cache, monkeypatch):
    from reconstruction import evaluate

    rng = np.random.default_rng(3)
    reference = rng.uniform(0.0, 0.8, (24, 20, 3))
    test = reference + 0.05 * rng.standard_normal(reference.shape)
    first = evaluate.cached_display_metrics(test, reference, 1.5)
    assert first == pytest.approx(metrics.display_metrics(test, reference, 1.5))
    measured = []
    original = metrics.display_metrics
    monkeypatch.setattr(metrics, "display_metrics", lambda *args: measured.append(args) or original(*args))
    assert evaluate.cached_display_metrics(test.copy(), reference, 1.5) == first  # same bytes: reused
    assert measured == []
    changed = test.copy()
    changed[3, 4, 1] += 1e-9
    for args in ((changed, reference, 1.5), (test, reference, 1.25), (test.astype(np.float32), reference, 1.5)):
        evaluate.cached_display_metrics(*args)
    assert len(measured) == 3
    entries = sorted((isolated_cache / "display-metrics").glob("*.json"))
    assert len(entries) == 4
    for entry in entries:
        entry.write_text("[1, 2")  # a torn or foreign entry is measured again and rewritten
    assert evaluate.cached_display_metrics(test, reference, 1.5) == first and len(measured) == 4
    assert evaluate.cached_display_metrics(test, reference, 1.5) == first and len(measured) == 4
