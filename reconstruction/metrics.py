"""Image quality metrics, the one module every evaluation uses.

Two image spaces, named in every table that uses them:

**Linear** (HDR radiance, as renderers and the paper's §6 equations produce it):

* **PSNR, RMSE**: linear images clipped to [0, 1], data range 1:
  ``RMSE = sqrt(mean((clip(a) − clip(b))²))``, ``PSNR = −20·log10(RMSE)`` dB (``inf`` for
  identical images). On a dark scene almost every value is near 0, so this rewards the
  black and barely sees the image a person looks at.
* **relMSE** on unclipped images: ``mean((a − b)² / (b² + ε))``, ε = 0.01 (the plain
  relative MSE; :func:`references.ztest.relmse_variance_corrected` is the one that subtracts the
  reference's own variance).
* **SMAPE** on unclipped images: ``mean(|a − b| / (|a| + |b| + ε))``, ε = 0.01, in [0, 1].

**Display** (the image a person sees, and the space of the paper's 0–1 PSNRs): one
tonemapping per view, :func:`to_display`: the linear image times an **exposure** that maps
the reference's 99th-percentile luminance (Rec. 709) to 1 (:func:`auto_exposure`; the same
exposure for every method compared on that view), clipped to [0, 1], then the sRGB transfer
curve. On it:

* **display PSNR, RMSE** (data range 1), **SSIM** (scikit-image, ``data_range=1``,
  ``channel_axis=-1``, 7×7 window), and
* **FLIP**: LDR-FLIP (``flip_evaluator.evaluate(..., "LDR")``) at the default 67 pixels per
  degree, the mean of the error map in [0, 1] (lower is better).

Argument order is always ``(test, reference)``. Accepted shapes: (H, W) or (H, W, C) with
C in {1, 3} (FLIP and the display space: (H, W, 3) only); the two images must have the same
shape and contain only finite values, else ``ValueError``.
"""

from __future__ import annotations

import math

import numpy as np

from kdtrace.imageio import srgb_encode

#: ε of relMSE (stabilises dark reference pixels).
RELMSE_EPSILON = 0.01
#: ε of SMAPE (an all-black pixel pair scores 0, not 0/0).
SMAPE_EPSILON = 0.01
#: The reference's luminance percentile that the automatic exposure maps to display white.
EXPOSURE_PERCENTILE = 99.0
#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)


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


def smape(test, reference) -> float:
    """Symmetric mean absolute percentage error of HDR images, ``mean(|a − b| / (|a| + |b| + 0.01))``."""
    test, reference = _checked_pair(test, reference)
    return float(np.mean(np.abs(test - reference) / (np.abs(test) + np.abs(reference) + SMAPE_EPSILON)))


def luminance(image) -> np.ndarray:
    """Rec. 709 luminance of a linear (H, W, 3) image, (H, W)."""
    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got {image.shape}")
    return image @ np.asarray(LUMINANCE_WEIGHTS)


def auto_exposure(reference, name: str = "reference", percentile: float = EXPOSURE_PERCENTILE) -> float:
    """The exposure that maps the reference's ``percentile`` luminance to display white (1).

    Raises
    ------
    ValueError
        Naming ``name`` (e.g. the view) when the reference has non-finite values or that
        luminance is not positive (an all-black view has no exposure).
    """
    lum = luminance(reference)
    if not np.all(np.isfinite(lum)):
        raise ValueError(f"{name}: no exposure: the reference has {int(np.count_nonzero(~np.isfinite(lum)))} NaN/inf pixels")
    level = float(np.percentile(lum, percentile))
    if not level > 0 or not math.isfinite(1.0 / level):
        raise ValueError(f"{name}: no exposure: the reference's {percentile:g}th-percentile luminance is {level:g}")
    return 1.0 / level


def display_exposures(references) -> tuple[list[float | None], list[float]]:
    """Each view's own display exposure (:func:`auto_exposure`; None for an all-black reference)
    and the exposure it is shown with.

    A view whose reference is entirely black has none of its own (a dataset may hold views that
    no light reaches): it is shown with the median exposure of the others, so that its errors
    still count.

    Parameters
    ----------
    references : sequence of array_like, (H, W, 3)
        Linear radiance of each view's reference.

    Raises
    ------
    ValueError
        No view has an exposure (all references black or not finite).
    """
    own = []
    for reference in references:
        try:
            own.append(auto_exposure(reference))
        except ValueError:
            own.append(None)
    defined = [exposure for exposure in own if exposure is not None]
    if not defined:
        raise ValueError(f"no display exposure: all {len(own)} references are black (or not finite)")
    median = float(np.median(defined))
    return own, [median if exposure is None else exposure for exposure in own]


def to_display(image, exposure: float) -> np.ndarray:
    """The displayed image: ``srgb(clip(image · exposure, 0, 1))`` of a linear (H, W, 3) image, float64 in [0, 1]."""
    if not (math.isfinite(exposure) and exposure > 0):
        raise ValueError(f"exposure must be a positive finite number, got {exposure!r}")
    return srgb_encode(np.asarray(image, dtype=np.float64) * exposure)


def displayed_flip(shown_test: np.ndarray, shown_reference: np.ndarray) -> tuple[np.ndarray, float]:
    """LDR-FLIP error map (H, W) and its mean of two already displayed (H, W, 3) images."""
    import flip_evaluator

    reference_srgb, test_srgb = (np.ascontiguousarray(image, dtype=np.float32) for image in (shown_reference, shown_test))
    error_map, mean_error, _ = flip_evaluator.evaluate(reference_srgb, test_srgb, "LDR", applyMagma=False)
    return np.asarray(error_map).reshape(shown_test.shape[:2]), float(mean_error)


def flip_map(test, reference, exposure: float = 1.0) -> tuple[np.ndarray, float]:
    """LDR-FLIP error map (H, W) of the displayed images and its mean (see module docstring)."""
    test, reference = _checked_pair(test, reference, rgb_only=True)
    return displayed_flip(to_display(test, exposure), to_display(reference, exposure))


def flip(test, reference, exposure: float = 1.0) -> float:
    """Mean LDR-FLIP error of the displayed (H, W, 3) images (``exposure`` 1: sRGB of the clipped linear image)."""
    return flip_map(test, reference, exposure)[1]


def display_metrics(test, reference, exposure: float | None = None, name: str = "reference") -> dict[str, float]:
    """Display-referred metrics of one (H, W, 3) pair: the tonemapping of :func:`to_display`.

    Parameters
    ----------
    test, reference : array_like, (H, W, 3)
        Linear radiance.
    exposure : float, optional
        Default :func:`auto_exposure` of the reference.
    name : str
        Names the view in errors.

    Returns
    -------
    dict
        ``exposure``, ``display_psnr`` (dB), ``display_rmse``, ``display_ssim`` (images of at
        least 7×7) and ``flip``.
    """
    test, reference = _checked_pair(test, reference, rgb_only=True)
    exposure = auto_exposure(reference, name) if exposure is None else float(exposure)
    shown_test, shown_reference = to_display(test, exposure), to_display(reference, exposure)
    result = {"exposure": exposure, "display_psnr": psnr(shown_test, shown_reference),
              "display_rmse": rmse(shown_test, shown_reference)}
    if min(test.shape[:2]) >= 7:
        result["display_ssim"] = ssim(shown_test, shown_reference)
    result["flip"] = displayed_flip(shown_test, shown_reference)[1]
    return result


def all_metrics(test, reference, exposure: float | None = None) -> dict[str, float]:
    """Every metric that applies: linear ``psnr``, ``rmse``, ``ssim``, ``relmse``, ``smape`` and,
    for RGB, the :func:`display_metrics` (``exposure`` as there)."""
    test, reference = _checked_pair(test, reference)
    result = {"psnr": psnr(test, reference), "rmse": rmse(test, reference), "relmse": relmse(test, reference),
              "smape": smape(test, reference)}
    if min(test.shape[:2]) >= 7:
        result["ssim"] = ssim(test, reference)
    if test.ndim == 3 and test.shape[2] == 3:
        result.update(display_metrics(test, reference, exposure))
    return result
