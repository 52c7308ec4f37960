"""Image quality metrics, the one module every evaluation uses.

Conventions (argument order is always ``(test, reference)``):

* **PSNR, RMSE** (the paper's §6 metrics): linear images clipped to [0, 1], data range
  1: ``RMSE = sqrt(mean((clip(a) − clip(b))²))``, ``PSNR = −20·log10(RMSE)`` dB
  (``inf`` for identical images).
* **SSIM**: ``skimage.metrics.structural_similarity`` on the clipped images with
  ``data_range=1`` and ``channel_axis=-1`` (Gaussian-free 7×7 default window).
* **relMSE** on HDR (unclipped) images: ``mean((a − b)² / (b² + ε))``, ε = 0.01.
* **FLIP**: LDR-FLIP (``flip_evaluator.evaluate(..., "LDR")``) of the clipped linear
  images sRGB-encoded (:func:`kdtrace.imageio.srgb_encode`), at the default 67 pixels
  per degree; the mean of the error map, in [0, 1] (lower is better).

Accepted shapes: (H, W) or (H, W, C) with C in {1, 3} (FLIP: (H, W, 3) only); the two
images must have the same shape and contain only finite values, else ``ValueError``.
"""

from __future__ import annotations

import math

import numpy as np

from kdtrace.imageio import srgb_encode

#: ε of relMSE (stabilises dark reference pixels).
RELMSE_EPSILON = 0.01


def _checked_pair(test, reference, *, rgb_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
    test = np.asarray(test, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if test.shape != reference.shape:
        raise ValueError(f"test {test.shape} and reference {reference.shape} differ in shape")
    if rgb_only:
        if test.ndim != 3 or test.shape[2] != 3:
            raise ValueError(f"expected an (H, W, 3) image, got {test.shape}")
    elif test.ndim not in (2, 3) or (test.ndim == 3 and test.shape[2] not in (1, 3)):
        raise ValueError(f"expected an (H, W), (H, W, 1) or (H, W, 3) image, got {test.shape}")
    if test.size == 0:
        raise ValueError("images are empty")
    for name, image in (("test", test), ("reference", reference)):
        if not np.all(np.isfinite(image)):
            raise ValueError(f"{name} image contains {int(np.count_nonzero(~np.isfinite(image)))} NaN/inf values")
    return test, reference


def rmse(test, reference) -> float:
    """Root-mean-square error of the images clipped to [0, 1] (see module docstring)."""
    test, reference = _checked_pair(test, reference)
    return float(np.sqrt(np.mean((np.clip(test, 0, 1) - np.clip(reference, 0, 1)) ** 2)))


def psnr(test, reference) -> float:
    """PSNR in dB of the images clipped to [0, 1], data range 1 (``inf`` if identical)."""
    error = rmse(test, reference)
    return math.inf if error == 0 else -20.0 * math.log10(error)


def ssim(test, reference) -> float:
    """Mean SSIM of the images clipped to [0, 1] (scikit-image, ``data_range=1``)."""
    from skimage.metrics import structural_similarity

    test, reference = _checked_pair(test, reference)
    if min(test.shape[:2]) < 7:
        raise ValueError(f"SSIM needs images of at least 7×7 pixels, got {test.shape[:2]}")
    channel_axis = -1 if test.ndim == 3 else None
    return float(
        structural_similarity(np.clip(test, 0, 1), np.clip(reference, 0, 1), data_range=1.0, channel_axis=channel_axis)
    )


def relmse(test, reference) -> float:
    """Relative MSE of HDR images, ``mean((a − b)² / (b² + 0.01))`` (no clipping)."""
    test, reference = _checked_pair(test, reference)
    return float(np.mean((test - reference) ** 2 / (reference**2 + RELMSE_EPSILON)))


def flip(test, reference) -> float:
    """Mean LDR-FLIP error of the sRGB-encoded, clipped linear (H, W, 3) images."""
    import flip_evaluator

    test, reference = _checked_pair(test, reference, rgb_only=True)
    reference_srgb, test_srgb = (np.ascontiguousarray(srgb_encode(image), dtype=np.float32) for image in (reference, test))
    _, mean_error, _ = flip_evaluator.evaluate(reference_srgb, test_srgb, "LDR", applyMagma=False)
    return float(mean_error)


def all_metrics(test, reference) -> dict[str, float]:
    """Every metric that applies: ``psnr``, ``rmse``, ``ssim``, ``relmse`` and, for RGB, ``flip``."""
    test, reference = _checked_pair(test, reference)
    result = {"psnr": psnr(test, reference), "rmse": rmse(test, reference), "relmse": relmse(test, reference)}
    if min(test.shape[:2]) >= 7:
        result["ssim"] = ssim(test, reference)
    if test.ndim == 3 and test.shape[2] == 3:
        result["flip"] = flip(test, reference)
    return result
