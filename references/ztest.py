"""Statistical agreement of our renders with Mitsuba 3 references.

How to use::

    from references.ztest import z_test, relmse_variance_corrected, loglog_slope, write_failure_artefacts
    result = z_test(ours.rgb, ours.variance, ref.rgb, ref.variance, ours_spp=256, ref_spp=256)
    result.passed, result.pass_rate, result.summary()
    if not result.passed:
        write_failure_artefacts("out/compare", ours.rgb, ref.rgb, result)
    main_compare("cbox-sphere", spp=256, ref_spp=256, max_depth=3, seed=1, width=32, height=32,
                 out_dir="out/compare")  # what ``kdtrace compare-mitsuba`` runs

Settings (module constants): overall significance :data:`ALPHA` = 1 %, scene pass
threshold :data:`PASS_FRACTION` = 99.75 % of pixels, relMSE regulariser
:data:`RELMSE_EPSILON` = 0.01, float32 tolerance of noise-free pixels
:data:`FLOAT32_RTOL`.

The two-sample test
-------------------
Each side gives, per pixel and channel, a sample mean ``a`` (``b``) of ``n_a`` (``n_b``)
independent samples and the estimated variance of that mean ``s_a²`` (``s_b²``). Under the
null hypothesis "both renderers estimate the same pixel value",
``z = (a - b) / sqrt(s_a² + s_b²)`` is approximately standard normal when the variance
estimates are exact. They are not: the variance of a few-spp mean is itself estimated
from few samples (and path-tracing samples are heavy tailed), and at a Šidák-corrected
per-test level of ~1e-6 the normal tail badly underestimates how often ``|z|`` gets
large. We therefore use Welch's test: ``z`` is referred to a Student t distribution with
the Welch–Satterthwaite degrees of freedom

    ν = (s_a² + s_b²)² / (s_a⁴ / (n_a - 1) + s_b⁴ / (n_b - 1)),

which tends to the normal when both sides have many samples and is conservative (wide
tails) when one side's variance rests on few samples. (Measured on Gaussian samples with
``n = 16`` per side and 3,072 tests: the normal approximation rejects a true null in
about 15 % of images instead of 1 %; Welch's t keeps the family-wise rate near 1 %, see
``tests/test_agreement_mitsuba.py``. At 256 spp the two agree.) When the sample counts are not given, the normal
distribution is used.

Channels and the Šidák correction. Each colour channel of each pixel is one test, so
``m = pixels × channels`` (minus the noise-free elements below), and each test runs at
``α_each = 1 - (1 - α)^(1/m)``: if every test is independent and the null holds
everywhere, the probability that *any* element fails is exactly ``α``. A pixel fails
when any of its channels fails; its p-value is the smallest of its channels'. The
channels of one pixel are positively correlated (they come from the same paths), which
only makes the correction conservative. A scene passes when at least
:data:`PASS_FRACTION` of its pixels pass.

Noise-free elements (both variances exactly zero, e.g. a directly visible emitter, or
black background) cannot be tested statistically; they pass iff the two values agree to
float32 rounding (relative :data:`FLOAT32_RTOL`, which covers the accumulation of a mean
in float32) and are not counted in ``m``. A non-finite value on either side fails.

Bias: relMSE against spp
------------------------
``relmse_variance_corrected(a, b, var_b)`` is the mean over pixels and channels of
``((a - b)² - var_b) / (b² + 0.01)``; subtracting the reference's variance of the mean
removes its own noise from the expectation, so for an unbiased renderer
``E[relMSE] = mean(var_a / (b² + 0.01)) ∝ 1/spp``. A bias ``β`` adds a floor
``β² / (b² + 0.01)``, which flattens the log–log curve: the fitted slope
(:func:`loglog_slope`) of relMSE over spp = 4 … 32 must be −1 ± 0.15.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from kdtrace.cache import atomic_write_bytes
from kdtrace.imageio import write_exr, write_png

#: Overall (family-wise) significance of one image comparison.
ALPHA = 0.01
#: A scene passes when at least this fraction of its pixels passes.
PASS_FRACTION = 0.9975
#: Regulariser of the relative MSE's denominator ``b² + ε``.
RELMSE_EPSILON = 0.01
#: Relative tolerance of noise-free elements (about 84 float32 ulps: a mean accumulated in float32).
FLOAT32_RTOL = 1e-5
#: Allowed deviation of the relMSE log–log slope from −1.
SLOPE_TOLERANCE = 0.15


def sidak_alpha(alpha: float, m: int) -> float:
    """Per-test significance ``1 - (1 - alpha)^(1/m)`` giving family-wise level ``alpha`` over ``m`` tests.

    Computed as ``-expm1(log1p(-alpha) / m)`` so it stays accurate for large ``m``.
    """
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    if m < 1:
        raise ValueError(f"the number of tests must be >= 1, got {m}")
    return float(-np.expm1(np.log1p(-alpha) / m))


def welch_dof(var_a: np.ndarray, var_b: np.ndarray, n_a: float, n_b: float) -> np.ndarray:
    """Welch–Satterthwaite degrees of freedom of ``(a - b) / sqrt(var_a + var_b)`` (variances of the means).

    Elements where both variances are zero get ``inf``; a side with ``n <= 1`` samples
    contributes no information about its variance and raises ``ValueError``.
    """
    if n_a < 2 or n_b < 2:
        raise ValueError(f"Welch's test needs >= 2 samples per side, got {n_a} and {n_b}")
    var_a = np.asarray(var_a, np.float64)
    var_b = np.asarray(var_b, np.float64)
    numerator = (var_a + var_b) ** 2
    denominator = var_a**2 / (n_a - 1) + var_b**2 / (n_b - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(denominator > 0, numerator / np.where(denominator > 0, denominator, 1.0), np.inf)


@dataclass(frozen=True)
class ZTestResult:
    """Outcome of :func:`z_test` on two (H, W, C) images.

    Attributes
    ----------
    z : ndarray (H, W, C) float64
        ``(a - b) / sqrt(var_a + var_b)``; 0 for noise-free elements.
    p_value : ndarray (H, W, C) float64
        Two-sided p-value per element (Welch t or normal); noise-free elements get 1 when
        they agree to float32 rounding and 0 when not.
    pixel_p_value : ndarray (H, W)
        Smallest p-value over the channels.
    pixel_failed : ndarray (H, W) bool
        Some channel failed (p < ``alpha_each``, a failed noise-free comparison, or a non-finite value).
    alpha_each : float
        Šidák-corrected significance of one element.
    tests : int
        ``m``: the number of statistically tested elements.
    noise_free : int
        Elements with both variances zero (compared to float32 rounding instead).
    pass_rate : float
        Fraction of pixels that pass.
    passed : bool
        ``pass_rate >= pass_fraction``.
    alpha, pass_fraction : float
        The settings used.
    welch : bool
        Whether Welch's t (rather than the normal) gave the p-values.
    """

    z: np.ndarray
    p_value: np.ndarray
    pixel_p_value: np.ndarray
    pixel_failed: np.ndarray
    alpha_each: float
    tests: int
    noise_free: int
    pass_rate: float
    passed: bool
    alpha: float
    pass_fraction: float
    welch: bool

    @property
    def critical_z(self) -> float:
        """``|z|`` at which a normal-referred element fails (for displaying error maps)."""
        return float(stats.norm.isf(self.alpha_each / 2.0))

    def summary(self) -> dict[str, Any]:
        """JSON-ready figures: pass rate, failed pixels, m, α_each, largest |z|."""
        return {
            "passed": bool(self.passed), "pass_rate": float(self.pass_rate),
            "failed_pixels": int(self.pixel_failed.sum()), "pixels": int(self.pixel_failed.size),
            "tests": int(self.tests), "noise_free": int(self.noise_free), "alpha": self.alpha,
            "alpha_each": self.alpha_each, "pass_fraction": self.pass_fraction, "welch": self.welch,
            "max_abs_z": float(np.max(np.abs(self.z))) if self.z.size else 0.0,
            "mean_z": float(np.mean(self.z)) if self.z.size else 0.0,
        }


def _as_image(name: str, image: np.ndarray) -> np.ndarray:
    image = np.asarray(image, np.float64)
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3:
        raise ValueError(f"{name} must have shape (H, W) or (H, W, C), got {image.shape}")
    return image


def z_test(ours: np.ndarray, ours_variance: np.ndarray, reference: np.ndarray, reference_variance: np.ndarray,
           ours_spp: int | None = None, reference_spp: int | None = None, alpha: float = ALPHA,
           pass_fraction: float = PASS_FRACTION) -> ZTestResult:
    """Per-pixel two-sample test of ``ours`` against ``reference`` (see the module docstring).

    Parameters
    ----------
    ours, reference : ndarray (H, W) or (H, W, C)
        Per-pixel sample means.
    ours_variance, reference_variance : ndarray, same shape
        Variance of those means (sample variance / spp); ``inf`` (a 1-spp render) makes
        the element untestable and it passes trivially.
    ours_spp, reference_spp : int, optional
        Samples per pixel behind each mean: with both, p-values come from Welch's t,
        otherwise from the normal distribution.
    alpha : float
        Family-wise significance (default 1 %), Šidák-corrected over the tested elements.
    pass_fraction : float
        Fraction of pixels that must pass.

    Returns
    -------
    ZTestResult
    """
    a, b = _as_image("ours", ours), _as_image("reference", reference)
    va, vb = _as_image("ours_variance", ours_variance), _as_image("reference_variance", reference_variance)
    if not a.shape == b.shape == va.shape == vb.shape:
        raise ValueError(f"shapes differ: ours {a.shape}, reference {b.shape}, variances {va.shape}, {vb.shape}")
    if (va < 0).any() or (vb < 0).any():
        raise ValueError("variances must be non-negative")
    finite = np.isfinite(a) & np.isfinite(b) & ~np.isnan(va) & ~np.isnan(vb)
    total_var = va + vb
    noisy = finite & (total_var > 0)
    noise_free = finite & (total_var == 0)
    m = max(int(noisy.sum()), 1)
    alpha_each = sidak_alpha(alpha, m)

    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(noisy, (a - b) / np.sqrt(np.where(noisy, total_var, 1.0)), 0.0)
    z = np.where(np.isfinite(z), z, 0.0)  # inf variance: untestable, z = 0
    welch = ours_spp is not None and reference_spp is not None
    if welch:
        with np.errstate(invalid="ignore"):
            dof = welch_dof(np.where(noisy, va, 0.0), np.where(noisy, vb, 0.0), ours_spp, reference_spp)
        dof = np.where(np.isfinite(dof), dof, 1e12)
        p = 2.0 * stats.t.sf(np.abs(z), dof)
    else:
        p = 2.0 * stats.norm.sf(np.abs(z))
    agree = np.abs(a - b) <= FLOAT32_RTOL * np.maximum(np.abs(a), np.abs(b))
    p = np.where(noisy, p, np.where(noise_free & agree, 1.0, 0.0))
    element_failed = np.where(noisy, p < alpha_each, ~(noise_free & agree))
    pixel_failed = element_failed.any(axis=2)
    pass_rate = 1.0 - float(pixel_failed.mean())
    return ZTestResult(z=z, p_value=p, pixel_p_value=p.min(axis=2), pixel_failed=pixel_failed,
                       alpha_each=alpha_each, tests=int(noisy.sum()), noise_free=int(noise_free.sum()),
                       pass_rate=pass_rate, passed=pass_rate >= pass_fraction, alpha=alpha,
                       pass_fraction=pass_fraction, welch=welch)


# ------------------------------------------------------------------ bias: relMSE against spp
def relmse_variance_corrected(image: np.ndarray, reference: np.ndarray, reference_variance: np.ndarray | None = None,
                              epsilon: float = RELMSE_EPSILON) -> float:
    """Mean over pixels and channels of ``((a - b)² - var_b) / (b² + ε)``.

    Parameters
    ----------
    image, reference : ndarray
        Our image and the reference (same shape).
    reference_variance : ndarray, optional
        Variance of the reference's per-pixel mean; subtracted so the reference's own
        noise does not enter the expectation (the result can then be slightly negative
        when our error is tiny).
    epsilon : float
        Regulariser of dark pixels.
    """
    a = np.asarray(image, np.float64)
    b = np.asarray(reference, np.float64)
    squared = (a - b) ** 2
    if reference_variance is not None:
        squared = squared - np.asarray(reference_variance, np.float64)
    return float(np.mean(squared / (b * b + epsilon)))


def loglog_slope(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of ``log y`` against ``log x`` (e.g. relMSE against spp).

    Raises
    ------
    ValueError
        Fewer than two points, or a non-positive value (log undefined).
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if x.shape != y.shape or x.size < 2:
        raise ValueError(f"need two or more matching points, got {x.shape} and {y.shape}")
    if (x <= 0).any() or (y <= 0).any() or not np.isfinite(y).all():
        raise ValueError(f"log-log fit needs positive finite values, got x={x.tolist()} y={y.tolist()}")
    slope, _ = np.polyfit(np.log(x), np.log(y), 1)
    return float(slope)


# ------------------------------------------------------------------ artefacts
def write_failure_artefacts(out_dir: str | Path, ours: np.ndarray, reference: np.ndarray, result: ZTestResult,
                            extra: dict[str, Any] | None = None, exposure: float = 1.0) -> dict[str, Path]:
    """Write the files that explain a comparison into ``out_dir``.

    Files (each written atomically: a temporary name in the folder, then a rename;
    ``summary.json`` is written last, so its presence marks a complete set):

    - ``ours.exr`` / ``ours.png``, ``reference.exr`` / ``reference.png``: the images
      (linear EXR; sRGB PNG clamped after ``exposure``);
    - ``error_sigma.exr``: ``|a - b| / σ`` per channel (σ = sqrt(var_a + var_b));
      ``error_sigma.png``: its channel maximum divided by the critical ``|z|``, so white
      (≥ 1) marks elements beyond the Šidák threshold;
    - ``p_value.exr``: per-pixel smallest p-value over the channels; ``p_value.png``:
      ``log10 p / log10 α_each`` (white = failed);
    - ``failed.png``: the failed pixels in white;
    - ``summary.json``: :meth:`ZTestResult.summary` plus ``extra``.

    Returns
    -------
    dict
        Artefact name -> path.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ours = np.asarray(ours, np.float32)
    reference = np.asarray(reference, np.float32)
    abs_z = np.abs(result.z).astype(np.float32)
    with np.errstate(divide="ignore"):
        log_p = np.log10(np.maximum(result.pixel_p_value, 1e-300)) / math.log10(result.alpha_each)
    written = {
        "ours_exr": write_exr(out_dir / "ours.exr", ours),
        "ours_png": write_png(out_dir / "ours.png", ours, exposure),
        "reference_exr": write_exr(out_dir / "reference.exr", reference),
        "reference_png": write_png(out_dir / "reference.png", reference, exposure),
        "error_sigma_exr": write_exr(out_dir / "error_sigma.exr", abs_z),
        "error_sigma_png": write_png(out_dir / "error_sigma.png", abs_z.max(axis=2) / result.critical_z),
        "p_value_exr": write_exr(out_dir / "p_value.exr", result.pixel_p_value.astype(np.float32)),
        "p_value_png": write_png(out_dir / "p_value.png", np.clip(log_p, 0.0, 1.0).astype(np.float32)),
        "failed_png": write_png(out_dir / "failed.png", result.pixel_failed.astype(np.float32)),
    }
    summary = {**result.summary(), **(extra or {}), "files": sorted(p.name for p in written.values())}
    written["summary"] = atomic_write_bytes(out_dir / "summary.json", json.dumps(summary, indent=2, default=str).encode())
    return written


# ------------------------------------------------------------------ driving both renderers
@dataclass
class Comparison:
    """One scene compared: our render, the reference, the Z-test and the relMSE."""

    scene: str
    ours: Any
    reference: Any
    result: ZTestResult
    relmse: float
    settings: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        return {"scene": self.scene, **self.settings, **self.result.summary(), "relmse": self.relmse,
                "ours_seconds": float(self.ours.seconds), "reference_seconds": float(self.reference.seconds),
                "reference_variant": self.reference.variant}


def _load(scene_name: str):
    from kdtrace.scenes import load_scene

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*MTL.*")
        return load_scene(scene_name)


def compare_scene(scene, spp: int, ref_spp: int, max_depth: int, seed: int, width: int, height: int,
                  tree=None) -> Comparison:
    """Render ``scene`` with ours (``spp``) and Mitsuba (``ref_spp``, cached) and Z-test them.

    Both sides need >= 2 spp (the test needs their variance estimates). Our renderer is
    keyed by ``seed``, Mitsuba by ``seed + 1`` so the two sample streams are unrelated.
    """
    from kdtrace.render import render
    from references.mitsuba import render_reference

    if spp < 2 or ref_spp < 2:
        raise ValueError(f"both sides need spp >= 2 for a variance estimate, got {spp} and {ref_spp}")
    ours = render(scene, spp=spp, max_depth=max_depth, seed=seed, width=width, height=height, aux=False, tree=tree)
    reference = render_reference(scene, ref_spp, max_depth, (seed + 1) % 2**32, width, height)
    result = z_test(ours.rgb, ours.variance, reference.rgb, reference.variance, spp, ref_spp)
    settings = {"spp": spp, "ref_spp": ref_spp, "max_depth": max_depth, "seed": seed, "width": width,
                "height": height}
    return Comparison(scene.name, ours, reference, result,
                      relmse_variance_corrected(ours.rgb, reference.rgb, reference.variance), settings)


def balanced_seeds(spps: tuple[int, ...], first_seed: int, renders_at_max: int = 1) -> list[list[int]]:
    """Distinct seeds per spp level, ``renders_at_max * max(spps) / spp`` renders at each level.

    Every level then gets the same number of samples. The noise of a relMSE estimate is
    dominated by rare high-value paths (caustics through mirrors and glass): its relative
    variance is about ``kurtosis / (samples per level)``, so equal samples per level gives
    equally reliable points for the slope fit; distinct seeds keep the points independent.
    """
    top = max(spps)
    seeds, next_seed = [], first_seed
    for spp in spps:
        count = max(1, renders_at_max * top // spp)
        seeds.append(list(range(next_seed, next_seed + count)))
        next_seed += count
    return seeds


def relmse_curve(scene, spps: tuple[int, ...], reference, max_depth: int, seeds, width: int, height: int,
                 tree=None) -> tuple[np.ndarray, float]:
    """relMSE of our renders against ``reference`` per spp level (averaged over that level's seeds) and its slope.

    Parameters
    ----------
    scene : Scene
    spps : tuple of int
        Sample counts, e.g. (4, 8, 16, 32).
    reference : Reference
        A Mitsuba reference with many more spp than ``max(spps)`` (its variance is
        subtracted anyway).
    max_depth : int
    seeds : sequence of sequences of int
        Our renderer's seeds for each level (see :func:`balanced_seeds`).
    width, height : int
        Must match the reference.

    Returns
    -------
    (ndarray, float)
        Mean relMSE per spp, and the fitted log–log slope.
    """
    from kdtrace.render import render

    if len(seeds) != len(spps):
        raise ValueError(f"need one seed list per spp level, got {len(seeds)} for {len(spps)}")
    values = np.zeros(len(spps))
    for i, (spp, level_seeds) in enumerate(zip(spps, seeds, strict=True)):
        for seed in level_seeds:
            image = render(scene, spp=spp, max_depth=max_depth, seed=seed, width=width, height=height, aux=False,
                           tree=tree).rgb
            values[i] += relmse_variance_corrected(image, reference.rgb, reference.variance) / len(level_seeds)
    return values, loglog_slope(np.asarray(spps), values)


def main_compare(scene_name: str, spp: int, ref_spp: int, max_depth: int, seed: int, width: int, height: int,
                 out_dir: str | Path) -> dict[str, Any]:
    """Compare one scene with Mitsuba 3 and write the images, error and p-value maps (``kdtrace compare-mitsuba``).

    Parameters
    ----------
    scene_name : str
        A name for :func:`kdtrace.scenes.load_scene` (e.g. ``"cbox-sphere"``).
    spp, ref_spp : int
        Our and Mitsuba's samples per pixel (>= 2 each; 64–256 at 32×32–64×64 give
        reliable variance estimates).
    max_depth : int
        Mitsuba's convention (>= 1; 3 is the paper's setting).
    seed : int
        Our seed; Mitsuba's is ``seed + 1``.
    width, height : int
        Resolution of both renders.
    out_dir : str or Path
        Folder for the artefacts of :func:`write_failure_artefacts` (written whether or
        not the scene passes).

    Returns
    -------
    dict
        Scene, settings, ``passed``, ``pass_rate``, ``failed_pixels``, ``tests``,
        ``alpha_each``, ``max_abs_z``, ``relmse``, render times, ``out_dir`` and ``files``.
    """
    started = time.perf_counter()
    comparison = compare_scene(_load(scene_name), spp, ref_spp, max_depth, seed, width, height)
    summary = comparison.summary()
    files = write_failure_artefacts(out_dir, comparison.ours.rgb, comparison.reference.rgb, comparison.result,
                                    extra={k: v for k, v in summary.items() if k not in comparison.result.summary()})
    summary["out_dir"] = str(Path(out_dir))
    summary["files"] = {name: str(path) for name, path in files.items()}
    summary["seconds"] = time.perf_counter() - started
    return summary
