"""Run time against error: our pipelines against brute-force Mitsuba.

For each reconstruction scene of a profile, at ``sweep_width`` x ``sweep_height`` from the
scene's default camera, the error of five methods against a Mitsuba reference of
``sweep_reference_spp`` samples per pixel, as a function of wall-clock seconds:

``kdtrace``
    our path tracer alone (local-branch tree, no auxiliary buffers), at each ``sweep_spp``;
``mitsuba``
    Mitsuba 3's ``path`` integrator alone, at each ``sweep_spp`` (the scene converted and
    loaded beforehand; one warm-up render at the same spp, so JIT compilation is never
    timed; the render and the copy to NumPy are timed);
``kdtrace+denoiser``
    our path tracer (with albedo) + the scene's own denoiser (Precision Graphics);
``kdtrace-half+denoiser+superres``
    our path tracer at half resolution + the denoiser + 2x superresolution;
``kdtrace+oidn``
    our path tracer (with albedo and normal) + Open Image Denoise;
``kdtrace+denoiser-blend``
    the documented variant that never loses to its input: the denoised frame blended with
    the noisy one, ``w * denoised + (1 - w) * noisy``, ``w = min(w(spp), cap)`` with ``w(spp)``
    fitted per spp on the scene's validation views and, at spp >= 2, ``cap`` the frame's own
    bound from two halves of its samples (:mod:`reconstruction.blend`; the halves are timed
    as its render, the cap's two denoiser passes as reconstruction; the ``weight`` and
    ``frame_cap`` columns record both);
``kdtrace+demodulated``, ``mitsuba+demodulated``
    either renderer (with albedo) + the scene's albedo-demodulated denoiser, the documented
    variant of the paper's network (``Denoiser(demodulate=True)``, same parameters), on the
    scenes of the profile's ``demodulated_scenes``;
``mitsuba+denoiser``, ``mitsuba+oidn``
    Mitsuba's ``path`` integrator wrapped in its ``aov`` integrator (RGB plus albedo and
    shading normal in one render, timed as a whole) + our per-scene denoiser / OIDN: the
    reconstruction's contribution measured on the fastest renderer too. Mitsuba's albedo
    AOV is the BSDF albedo at the first hit (mirrors and glass included), which is what our
    renderer's albedo buffer holds on diffuse surfaces; the networks were trained on ours.

Plug-in denoisers (``kdtrace report --denoiser SPEC``, :mod:`reports.plugins`) add the method
``kdtrace+SPEC``: our path tracer with albedo and normal + the plug-in, measured as
``kdtrace+oidn`` (:func:`measure_plugin_scene`), in every table, the plots and the headline.

Seconds of a pipeline = render + reconstruction, warm: our render time is the kernel's
wall time (``RenderResult.seconds``: scene packing and kernel compilation excluded); a
reconstruction step is timed after one warm-up call on the same input. Every timing is
the shortest of :data:`TIMING_REPEATS` runs. Errors: relMSE on the HDR images and PSNR on
the linear images clipped to [0, 1] (:mod:`reconstruction.metrics`; the superresolution
output is itself clipped to [0, 1], so its relMSE includes the clipping of pixels
brighter than 1).

From the curves: an equal-time table (each method's error at common seconds,
interpolated piecewise linearly in log-log for relMSE and in PSNR over log seconds,
"—" outside a method's measured range), an equal-error table (the seconds each method
needs to reach a threshold; "≤ s" when its fastest point already does, "not reached"
when no measured point does — never extrapolated) and the headline speed-up of our
pipeline over Mitsuba at equal error.

Rows are measured per scene and cached in ``OUT_DIR/rows/error_time/SCENE.json`` with a
content key; a rerun reuses them (and says so), ``fresh=True`` measures again. Plug-in rows
are cached apart, in ``OUT_DIR/rows/error_time-plugins/SCENE/``.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import os
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tabulate import tabulate
from tqdm import tqdm

from kdtrace.allocator import freed_memory_retained
from kdtrace.cache import atomic_write_bytes, content_key
from kdtrace.config import Config, ProfileConfig, ReconstructionProfile
from kdtrace.provenance import stamp
from kdtrace.timing import TIMING_REPEATS, shortest
from reports.metrics import Metric, write_metrics
from reports.notes import ReportNote
from reports.paper_figures import ACCEPTABLE_PSNR

#: Bump when what a row measures changes: cached rows become stale.
ROW_VERSION = 5
#: The methods, in table order, with their labels.
METHODS = {
    "kdtrace": "ours, path tracer",
    "mitsuba": "Mitsuba 3 path",
    "kdtrace+denoiser": "ours + denoiser",
    "kdtrace-half+denoiser+superres": "ours ½ res + denoiser + SR 2x",
    "kdtrace+oidn": "ours + OIDN",
    "kdtrace+denoiser-blend": "ours + denoiser, blended with input",
    "mitsuba+denoiser": "Mitsuba + our denoiser",
    "mitsuba+oidn": "Mitsuba + OIDN",
    "kdtrace+demodulated": "ours + demodulated denoiser",
    "mitsuba+demodulated": "Mitsuba + demodulated denoiser",
}
#: Our reconstruction pipelines, compared with brute force in the headline.
PIPELINES = ("kdtrace+denoiser", "kdtrace+denoiser-blend", "kdtrace-half+denoiser+superres", "mitsuba+denoiser",
             "kdtrace+demodulated", "mitsuba+demodulated")
#: Every denoising pipeline of the headline: ours and both renderers with OIDN.
DENOISING = (*PIPELINES, "kdtrace+oidn", "mitsuba+oidn")
#: The brute-force renderer each pipeline starts from (its own renderer's curve is the first comparison).
RENDERER = {method: "mitsuba" if method.startswith("mitsuba") else "kdtrace" for method in METHODS}
#: Bump when what a plug-in denoiser's row measures changes.
PLUGIN_ROW_VERSION = 1


def plugin_method(spec: str) -> str:
    """The sweep method of the plug-in denoiser ``spec``: ``kdtrace+SPEC`` (``kdtrace+plugin:SPEC`` if that is one of ours)."""
    method = f"kdtrace+{spec}"
    return f"kdtrace+plugin:{spec}" if method in METHODS else method


def method_label(method: str) -> str:
    """A method's label: :data:`METHODS`'s, or ``ours + plug-in SPEC`` for a plug-in denoiser's."""
    return METHODS.get(method) or f"ours + plug-in {method.removeprefix('kdtrace+').removeprefix('plugin:')}"


def methods_of(points: pd.DataFrame) -> list[str]:
    """The methods of ``points`` in table order: ours (:data:`METHODS`) first, then plug-ins in measured order."""
    present = list(dict.fromkeys(points["method"]))
    return [m for m in METHODS if m in present] + [m for m in present if m not in METHODS]


def denoising_methods(methods: Sequence[str]) -> list[str]:
    """The headline's pipelines among ``methods``: :data:`DENOISING` and every plug-in denoiser's."""
    return [m for m in DENOISING if m in methods] + [m for m in methods if m not in METHODS]


#: PSNR thresholds (dB) of the equal-error table: the paper's acceptable 30 dB, and 35 dB.
PSNR_THRESHOLDS = (ACCEPTABLE_PSNR, 35.0)
#: relMSE thresholds of the equal-error table.
RELMSE_THRESHOLDS = (1e-2, 1e-3)
#: Display-referred PSNR thresholds (dB) of the equal-error table (the space of the paper's 30 dB).
DISPLAY_PSNR_THRESHOLDS = (ACCEPTABLE_PSNR, 35.0)
#: The error columns of a point, and whether higher is better: linear PSNR, HDR relMSE, display PSNR, FLIP.
ERRORS = {"psnr": True, "relmse": False, "display_psnr": True, "flip": False}
#: ε of relMSE (as :data:`reconstruction.metrics.RELMSE_EPSILON`).
RELMSE_EPSILON = 0.01


# ------------------------------------------------------------------ curves (pure logic)
def _curve(seconds: Sequence[float], values: Sequence[float], log_values: bool) -> tuple[np.ndarray, np.ndarray]:
    """Points sorted by seconds, in interpolation space (log seconds; log values if asked).

    Points with equal seconds are averaged (in interpolation space), so the abscissa is
    strictly increasing. Non-positive seconds, or non-positive values with
    ``log_values``, raise ``ValueError``.
    """
    x = np.asarray(seconds, np.float64)
    y = np.asarray(values, np.float64)
    if x.shape != y.shape or x.ndim != 1 or x.size == 0:
        raise ValueError(f"need matching non-empty 1-D seconds and values, got {x.shape} and {y.shape}")
    if not (np.all(np.isfinite(x)) and np.all(x > 0)):
        raise ValueError(f"seconds must be positive and finite, got {x.tolist()}")
    if log_values and not np.all(y > 0):
        raise ValueError(f"log interpolation needs positive values, got {y.tolist()}")
    lx = np.log(x)
    ly = np.log(y) if log_values else y
    unique, inverse = np.unique(lx, return_inverse=True)
    means = np.bincount(inverse, weights=ly) / np.bincount(inverse)
    return unique, means


def value_at_seconds(seconds: Sequence[float], values: Sequence[float], at: float, log_values: bool) -> float:
    """A method's error at ``at`` seconds, interpolated between its measured points.

    Parameters
    ----------
    seconds : sequence of float
        Measured wall-clock seconds (any order).
    values : sequence of float
        Error at each point (relMSE, or PSNR in dB).
    at : float
        Seconds to read the curve at.
    log_values : bool
        Interpolate ``log(value)`` (relMSE: straight lines on log-log axes) instead of
        the value itself (PSNR, already logarithmic), always against ``log(seconds)``.

    Returns
    -------
    float
        The interpolated value, or NaN when ``at`` lies outside the measured seconds
        (never extrapolated).
    """
    x, y = _curve(seconds, values, log_values)
    where = math.log(at)
    if not x[0] - 1e-12 <= where <= x[-1] + 1e-12:
        return math.nan
    result = float(np.interp(where, x, y))
    return math.exp(result) if log_values else result


@dataclass(frozen=True)
class Reach:
    """When a method first reaches an error threshold.

    Attributes
    ----------
    seconds : float or None
        Interpolated seconds at the first crossing; the fastest point's seconds when
        that point already meets the threshold; None when not reached.
    kind : str
        ``"exact"`` (interpolated crossing), ``"at most"`` (the fastest measured point
        already meets it: the method may need less) or ``"not reached"``.
    """

    seconds: float | None
    kind: str

    def cell(self) -> str:
        """Table cell: seconds, ``≤ seconds`` or ``not reached``."""
        if self.kind == "not reached":
            return "not reached"
        return ("≤ " if self.kind == "at most" else "") + f"{self.seconds:.3g}"


def seconds_to_reach(seconds: Sequence[float], values: Sequence[float], threshold: float,
                     higher_is_better: bool) -> Reach:
    """Seconds a method needs to reach ``threshold`` (first crossing along increasing seconds).

    Parameters
    ----------
    seconds, values : sequence of float
        The measured curve (values: PSNR in dB with ``higher_is_better``, relMSE without).
    threshold : float
        PSNR to reach or exceed, or relMSE to reach or go below.
    higher_is_better : bool
        True for PSNR (interpolated linearly over log seconds), False for relMSE
        (interpolated in log-log).

    Returns
    -------
    Reach
        The crossing between the last point that misses and the first that meets the
        threshold; curves need not be monotone (the first crossing counts).
    """
    log_values = not higher_is_better
    x, y = _curve(seconds, values, log_values)
    target = math.log(threshold) if log_values else threshold
    meets = y >= target if higher_is_better else y <= target
    if not meets.any():
        return Reach(None, "not reached")
    first = int(np.argmax(meets))
    if first == 0:
        return Reach(float(np.min(np.asarray(seconds, np.float64))), "at most")
    x0, x1, y0, y1 = x[first - 1], x[first], y[first - 1], y[first]
    fraction = (target - y0) / (y1 - y0)
    return Reach(float(math.exp(x0 + fraction * (x1 - x0))), "exact")


def speedup_cell(reference: Reach, ours: Reach, reference_max_seconds: float) -> str:
    """How many times faster ours reaches a threshold than the reference, as a table cell.

    Bounds are stated, never guessed: the reference not reaching it within its
    measured range gives ``> max/ours``; ours reaching it already at its fastest point
    gives a lower bound ``≥``; the reference reaching it at its fastest point gives an
    upper bound ``≤``; both bounded the same way, or ours not reaching it, gives "—".
    """
    if ours.kind == "not reached":
        return "—"
    if reference.kind == "not reached":
        return f"> {reference_max_seconds / ours.seconds:.3g}x"
    ratio = reference.seconds / ours.seconds
    if reference.kind == "exact" and ours.kind == "exact":
        return f"{ratio:.3g}x"
    if reference.kind == "exact":  # ours: at most its fastest seconds
        return f"≥ {ratio:.3g}x"
    if ours.kind == "exact":  # reference: at most its fastest seconds
        return f"≤ {ratio:.3g}x"
    return "—"


def common_seconds(low: float, high: float) -> list[float]:
    """Round seconds (1 and 3 times a power of ten) within ``[low, high]`` for the equal-time table."""
    if not 0 < low <= high:
        raise ValueError(f"need 0 < low <= high, got {low}, {high}")
    grid = []
    for exponent in range(math.floor(math.log10(low)) - 1, math.ceil(math.log10(high)) + 1):
        for mantissa in (1.0, 3.0):
            value = mantissa * 10.0**exponent
            if low <= value <= high:
                grid.append(float(f"{value:.12g}"))
    return grid


def equal_time_table(points: pd.DataFrame, grid: Sequence[float]) -> pd.DataFrame:
    """Each method's PSNR and relMSE at the common seconds of ``grid`` (NaN outside its range).

    Parameters
    ----------
    points : DataFrame
        One scene's points: ``method``, ``seconds``, ``psnr``, ``relmse``.
    grid : sequence of float
        Seconds to read every curve at.

    Returns
    -------
    DataFrame
        Columns ``method``, ``seconds``, ``psnr``, ``relmse``.
    """
    rows = []
    for method, group in points.groupby("method", sort=False):
        for at in grid:
            rows.append({"method": method, "seconds": at,
                         "psnr": value_at_seconds(group["seconds"], group["psnr"], at, log_values=False),
                         "relmse": value_at_seconds(group["seconds"], group["relmse"], at, log_values=True)})
    return pd.DataFrame(rows, columns=["method", "seconds", "psnr", "relmse"])


def equal_error_table(points: pd.DataFrame, psnr_thresholds: Sequence[float] = PSNR_THRESHOLDS,
                      relmse_thresholds: Sequence[float] = RELMSE_THRESHOLDS,
                      display_thresholds: Sequence[float] = DISPLAY_PSNR_THRESHOLDS) -> dict[str, dict[str, Reach]]:
    """Per method, the :class:`Reach` of every threshold (keys ``"display 30 dB"``, ``"linear 30 dB"``,
    ``"relMSE 0.01"``); display thresholds only where the points have display PSNRs."""
    table: dict[str, dict[str, Reach]] = {}
    for method, group in points.groupby("method", sort=False):
        cells = {}
        if _measured(group, "display_psnr", method):
            for threshold in display_thresholds:
                cells[f"display {threshold:g} dB"] = seconds_to_reach(group["seconds"], group["display_psnr"], threshold,
                                                                      True)
        for threshold in psnr_thresholds:
            cells[f"linear {threshold:g} dB"] = seconds_to_reach(group["seconds"], group["psnr"], threshold, True)
        for threshold in relmse_thresholds:
            cells[f"relMSE {threshold:g}"] = seconds_to_reach(group["seconds"], group["relmse"], threshold, False)
        table[method] = cells
    return table


def headline(points: pd.DataFrame, spp: int, pipeline: str, reference: str = "mitsuba",
             error: str = "psnr") -> dict[str, Any]:
    """Speed-up of ``pipeline`` at ``spp`` over ``reference`` at the same error.

    The pipeline's ``error`` (a key of :data:`ERRORS`: ``psnr``, ``display_psnr``, ``relmse``,
    ``flip``) at ``spp`` is the target; the reference's seconds to reach it come from
    :func:`seconds_to_reach` on its curve.

    Returns
    -------
    dict
        ``value`` (the pipeline's error) and ``seconds`` of the
        pipeline point, the reference's :class:`Reach`, and ``speedup`` (a cell of :func:`speedup_cell`).
    """
    ours = points[(points["method"] == pipeline) & (points["spp"] == spp)]
    if len(ours) != 1:
        raise ValueError(f"need exactly one {pipeline} point at {spp} spp, found {len(ours)}")
    ours = ours.iloc[0]
    theirs = points[points["method"] == reference]
    reach = seconds_to_reach(theirs["seconds"], theirs[error], float(ours[error]), higher_is_better=ERRORS[error])
    cell = speedup_cell(reach, Reach(float(ours["seconds"]), "exact"), float(theirs["seconds"].max()))
    return {"value": float(ours[error]), "seconds": float(ours["seconds"]), "reference": reach, "speedup": cell}


# ------------------------------------------------------------------ measuring
@dataclass
class Reconstruction:
    """The trained networks of one profile: a denoiser per scene and the superresolution net."""

    denoisers: dict[str, Any]
    superres: Any
    blends: dict[str, Any] = dataclasses.field(default_factory=dict)
    demodulated: dict[str, Any] = dataclasses.field(default_factory=dict)

    @classmethod
    def load(cls, scene_names: Sequence[str], profile: ReconstructionProfile, all_scenes: Sequence[str],
             progress: bool = True, blend_spp: Sequence[int] = (),
             demodulated_scenes: Sequence[str] = ()) -> Reconstruction:
        """Train (or reuse from the cache) the denoiser of each of ``scene_names`` and the SR net.

        The superresolution net is trained on the photographs plus the renders of
        ``all_scenes`` (the profile's reconstruction scenes), as for Table 5. With
        ``blend_spp``, each denoiser's blend weights at those spp are fitted (or reused) on
        its scene's validation views (:func:`reconstruction.blend.fit_blend_weights`). The
        scenes of ``demodulated_scenes`` also get their albedo-demodulated denoiser (Table 2's
        variant, the same cached models).
        """
        from kdtrace.scenes import load_scene
        from reconstruction.blend import fit_blend_weights
        from reconstruction.data import generate_dataset
        from reconstruction.train import train_denoiser, train_superres

        denoisers = {name: train_denoiser([name], profile, progress=progress).model for name in scene_names}
        superres = train_superres(profile, list(all_scenes), progress=progress).model
        blends = {}
        if blend_spp:
            for name, model in denoisers.items():
                blends[name] = fit_blend_weights(model, generate_dataset(name, profile, progress=False),
                                                 load_scene(name), blend_spp, profile.max_depth, profile.seed,
                                                 progress=progress)
        demodulated = {name: train_denoiser([name], profile, progress=progress, demodulate=True).model
                       for name in demodulated_scenes}
        return cls(denoisers, superres, blends, demodulated)


def denoise_frame(model, frame) -> np.ndarray:
    """Our denoiser on a :class:`~kdtrace.render.RenderResult` with albedo (whole frame, float32)."""
    from reconstruction.inference import denoise

    return denoise(model, frame.rgb, frame.albedo)


def superresolve_frame(model, denoised: np.ndarray) -> np.ndarray:
    """2x superresolution of a denoised linear frame, clipped to [0, 1] first (the SR net's domain)."""
    from reconstruction.models import superresolve

    return superresolve(model, np.clip(denoised, 0.0, 1.0))


def timed_reconstruction(steps: Sequence[Callable[[Any], Any]], frame: Any, repeats: int = TIMING_REPEATS) -> tuple[Any, list[float]]:
    """Run a chain of reconstruction steps on ``frame``; each step warm and timed on its own input.

    Returns
    -------
    (object, list of float)
        The last step's output and the shortest seconds of each step.
    """
    seconds = []
    current = frame
    for step in steps:
        current, elapsed = shortest(lambda step=step, value=current: step(value), repeats)
        seconds.append(elapsed)
    return current, seconds


def errors(image: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """The :data:`ERRORS` of ``image`` against ``reference``: ``psnr`` (dB, linear clipped to [0, 1]),
    ``relmse`` (HDR), ``display_psnr`` (dB) and ``flip`` of the displayed images (the reference's
    exposure, :func:`reconstruction.metrics.display_metrics`)."""
    from reconstruction.metrics import display_metrics, psnr, relmse

    shown = display_metrics(image, reference, name="the sweep's reference")
    return {"psnr": psnr(image, reference), "relmse": relmse(image, reference), "display_psnr": shown["display_psnr"],
            "flip": shown["flip"]}


def reference_floor(reference) -> dict[str, float]:
    """The reference's own noise: expected relMSE and the PSNR its variance alone would give.

    Errors near these values measure the reference's noise, not the method's. PSNR is
    computed on images clipped to [0, 1], so only pixels whose reference lies inside
    (0, 1) count towards its noise (clipping hides the rest).
    """
    rgb = reference.rgb.astype(np.float64)
    variance = reference.variance.astype(np.float64)
    floor = float(np.mean(variance / (rgb * rgb + RELMSE_EPSILON)))
    mse = float(np.mean(np.where((rgb > 0.0) & (rgb < 1.0), variance, 0.0)))
    return {"relmse_floor": floor, "psnr_ceiling": math.inf if mse == 0 else -10.0 * math.log10(mse)}


def mitsuba_seed(seed: int, spp: int) -> int:
    """A 32-bit Mitsuba sampler seed of the sweep at ``spp`` (hashed: independent of the reference's passes)."""
    return int(content_key("error-time-mitsuba", seed, spp)[:8], 16)


class MitsubaTimer:
    """Mitsuba's ``path`` integrator on one scene, converted once, rendered warm.

    Parameters
    ----------
    scene : Scene
    max_depth, width, height : int
    """

    def __init__(self, scene, max_depth: int, width: int, height: int) -> None:
        from references.llvm import activate_variant

        self.variant = activate_variant(None)  # llvm_ad_rgb, or scalar_rgb with a warning
        import mitsuba as mi

        from references.mitsuba import to_mitsuba

        self._mi = mi
        self.scene, _ = to_mitsuba(scene, max_depth, width, height, 1)
        path = {"type": "path", "max_depth": int(max_depth)}
        self.integrator = mi.load_dict(path)
        self.aov_integrator = mi.load_dict({"type": "aov", "aovs": "albedo:albedo,normal:sh_normal", "integrator": path})

    def image(self, spp: int, seed: int, aov: bool = False) -> np.ndarray:
        """One render: ``mi.render`` and the copy to NumPy (which forces evaluation), float32.

        (H, W, 3) RGB; with ``aov`` (H, W, 9): RGB, albedo and shading normal.
        """
        integrator = self.aov_integrator if aov else self.integrator
        image = np.array(self._mi.render(self.scene, integrator=integrator, spp=int(spp), seed=int(seed)),
                         dtype=np.float32)
        return image[..., :9] if aov else image[..., :3]

    def render(self, spp: int, seed: int, aov: bool = False) -> tuple[np.ndarray, float]:
        """(image, shortest seconds) after one untimed warm-up render at the same spp (see :meth:`image`)."""
        return shortest(lambda: self.image(spp, seed, aov))

    @property
    def threads(self) -> int:
        """Dr.Jit's worker threads."""
        import drjit as dr

        return int(dr.thread_count())


@dataclass(frozen=True)
class AuxFrame:
    """A frame with the buffers the denoisers take (the fields of a RenderResult they read)."""

    rgb: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray


def _point(method: str, spp: int, width: int, height: int, render_seconds: float,
           reconstruction_seconds: Sequence[float], image: np.ndarray, reference: np.ndarray,
           input_errors: dict[str, float] | None = None, **extra: float) -> dict[str, Any]:
    """One measured point; a reconstruction's also records its noisy input's :func:`errors` (``input_psnr``, ...)."""
    point = {"method": method, "spp": int(spp), "width": int(width), "height": int(height),
             "paths": int(width * height * spp), "render_seconds": float(render_seconds),
             "reconstruction_seconds": float(sum(reconstruction_seconds)),
             "seconds": float(render_seconds + sum(reconstruction_seconds)), **errors(image, reference)}
    for key, value in (input_errors or {}).items():
        point[f"input_{key}"] = float(value)
    return {**point, **{key: float(value) for key, value in extra.items()}}


def measure_scene(name: str, config: Config, profile_name: str, models: Reconstruction,
                  progress: tqdm | None = None) -> dict[str, Any]:
    """Measure every method at every ``sweep_spp`` on one scene (see the module docstring).

    Returns
    -------
    dict
        ``scene``, ``triangles``, ``width``, ``height``, ``reference`` (spp, seconds,
        variant, noise floor), ``points`` (one dict per method and spp: seconds split
        into render and reconstruction, ``psnr``, ``relmse``), thread counts and warnings.
    """
    from kdtrace.kdtree import build_kdtree
    from kdtrace.render import render
    from kdtrace.scenes import load_scene
    from reconstruction.baselines import oidn
    from references.mitsuba import render_reference

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    width, height, depth = profile.sweep_width, profile.sweep_height, recon.max_depth
    if width % 2 or height % 2:
        raise ValueError(f"sweep_width/height must be even for the half-resolution pipeline, got {width}x{height}")

    def status(text: str) -> None:
        if progress is not None:
            progress.set_postfix_str(f"{name}: {text}")

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(name)
        tree = build_kdtree(scene, "local", config.kdtree)
        status(f"reference {profile.sweep_reference_spp} spp")
        reference = render_reference(scene, profile.sweep_reference_spp, depth, profile.seed % 2**32, width, height)
        mitsuba = MitsubaTimer(scene, depth, width, height)
        denoiser, superres = models.denoisers[name], models.superres

        def ours(spp: int, w: int, h: int, aux: bool, first_sample: int = 0):
            return shortest(lambda: render(scene, spp=spp, max_depth=depth, seed=profile.seed, width=w, height=h,
                                           aux=aux, tree=tree, first_sample=first_sample),
                            warmup=0, seconds_of=lambda r: r.seconds)

        def blended(weights, model, spp: int, frame, denoised, denoise_steps, render_seconds):
            """The blend pipeline at ``spp``: (image, render seconds, step seconds, weight, frame cap or NaN).

            At spp >= 2 the frame is rendered as two halves of its samples, which give the
            frame back (the same samples as ``frame``, so its denoised image is reused) and
            the frame's own weight cap (:func:`reconstruction.blend.frame_weight_cap`).
            """
            from reconstruction.blend import combine_halves, frame_weight_cap
            from reconstruction.inference import denoise

            if spp < 2:
                image, steps = timed_reconstruction([lambda d: weights.apply(frame.rgb, d, spp)], denoised)
                return image, render_seconds, denoise_steps + steps, weights.weight(spp), math.nan
            first, first_seconds = ours(spp // 2, width, height, aux=True)
            second, second_seconds = ours(spp - spp // 2, width, height, aux=True, first_sample=spp // 2)
            rgb, albedo = combine_halves(first, second)
            if not (np.allclose(rgb, frame.rgb, rtol=1e-5, atol=1e-6) and np.allclose(albedo, frame.albedo, rtol=1e-5, atol=1e-6)):
                raise RuntimeError(f"{name} at {spp} spp: the two halves do not give the frame back")
            cap, cap_steps = timed_reconstruction(
                [lambda halves: frame_weight_cap(lambda c, a: denoise(model, c, a), *halves)], (first, second))
            image, steps = timed_reconstruction([lambda d: weights.apply(frame.rgb, d, spp, cap)], denoised)
            return (image, first_seconds + second_seconds, denoise_steps + cap_steps + steps, weights.weight(spp, cap),
                    cap)

        points = []
        for spp in profile.sweep_spp:
            status(f"{spp} spp")
            plain, seconds = ours(spp, width, height, aux=False)
            points.append(_point("kdtrace", spp, width, height, seconds, [], plain.rgb, reference.rgb))
            image, seconds = mitsuba.render(spp, mitsuba_seed(profile.seed, spp))
            points.append(_point("mitsuba", spp, width, height, seconds, [], image, reference.rgb))

            frame, frame_seconds = ours(spp, width, height, aux=True)
            frame_errors = errors(frame.rgb, reference.rgb)
            denoised, steps = timed_reconstruction([lambda f: denoise_frame(denoiser, f)], frame)
            points.append(_point("kdtrace+denoiser", spp, width, height, frame_seconds, steps, denoised, reference.rgb,
                                 frame_errors))
            if name in models.blends:
                image, blend_seconds, blend_steps, weight, cap = blended(models.blends[name], denoiser, spp, frame,
                                                                         denoised, steps, frame_seconds)
                points.append(_point("kdtrace+denoiser-blend", spp, width, height, blend_seconds, blend_steps, image,
                                     reference.rgb, frame_errors, weight=weight, frame_cap=cap))
            image, steps = timed_reconstruction([lambda f: oidn(f.rgb, f.albedo, f.normal)], frame)
            points.append(_point("kdtrace+oidn", spp, width, height, frame_seconds, steps, image, reference.rgb,
                                 frame_errors))

            buffers, mitsuba_seconds = mitsuba.render(spp, mitsuba_seed(profile.seed, spp), aov=True)
            mitsuba_frame = AuxFrame(buffers[..., :3], buffers[..., 3:6], buffers[..., 6:9])
            mitsuba_errors = errors(mitsuba_frame.rgb, reference.rgb)
            image, steps = timed_reconstruction([lambda f: denoise_frame(denoiser, f)], mitsuba_frame)
            points.append(_point("mitsuba+denoiser", spp, width, height, mitsuba_seconds, steps, image, reference.rgb,
                                 mitsuba_errors))
            image, steps = timed_reconstruction([lambda f: oidn(f.rgb, f.albedo, f.normal)], mitsuba_frame)
            points.append(_point("mitsuba+oidn", spp, width, height, mitsuba_seconds, steps, image, reference.rgb,
                                 mitsuba_errors))
            if name in models.demodulated:
                for method, source, render_seconds, input_errors in (
                        ("kdtrace+demodulated", frame, frame_seconds, frame_errors),
                        ("mitsuba+demodulated", mitsuba_frame, mitsuba_seconds, mitsuba_errors)):
                    image, steps = timed_reconstruction([lambda f: denoise_frame(models.demodulated[name], f)], source)
                    points.append(_point(method, spp, width, height, render_seconds, steps, image, reference.rgb,
                                         input_errors))

            half, seconds = ours(spp, width // 2, height // 2, aux=True)
            image, steps = timed_reconstruction([lambda f: denoise_frame(denoiser, f),
                                                 lambda d: superresolve_frame(superres, d)], half)
            point = _point("kdtrace-half+denoiser+superres", spp, width, height, seconds, steps, image, reference.rgb)
            point["paths"] = int(width // 2 * (height // 2) * spp)
            points.append(point)
    import torch

    return {
        "scene": name, "triangles": len(scene.triangles), "width": width, "height": height, "max_depth": depth,
        "reference": {"spp": reference.spp, "seconds": reference.seconds, "variant": reference.variant,
                      **reference_floor(reference)},
        "mitsuba_variant": mitsuba.variant, "mitsuba_threads": mitsuba.threads, "torch_threads": torch.get_num_threads(),
        "points": points, "warnings": sorted({str(w.message) for w in caught}),
    }


#: Reconstruction profile fields the sweep's and §6.4's rows do not depend on: the datasets'
#: refined test references (those rows have Mitsuba references of their own).
ROW_INDEPENDENT_FIELDS = ("test_reference_spp_by_scene",)


def row_settings(config: Config, profile: ProfileConfig, recon: ReconstructionProfile) -> list[dict]:
    """The settings in a sweep or §6.4 row's key: the report, reconstruction, tree and render settings."""
    recon_settings = {name: value for name, value in dataclasses.asdict(recon).items()
                      if name not in ROW_INDEPENDENT_FIELDS}
    return [dataclasses.asdict(profile), recon_settings, dataclasses.asdict(config.kdtree),
            dataclasses.asdict(config.render)]


def measure_plugin_scene(name: str, spec: str, config: Config, profile_name: str,
                         progress: tqdm | None = None) -> dict[str, Any]:
    """The plug-in denoiser ``spec`` after our path tracer at every ``sweep_spp`` on one scene.

    Measured as ``kdtrace+oidn`` is in :func:`measure_scene`: the same frame (our render
    with albedo and normal, same seed; its kernel seconds, shortest of
    :data:`TIMING_REPEATS`), the plug-in timed warm on float32 copies of the buffers, the
    same Mitsuba reference (from the cache when the sweep rendered it). A
    :class:`~kdtrace.plugins.PluginError` ends the row: it then holds ``failed``
    (``failed: MESSAGE``) and the points measured before.

    Returns
    -------
    dict
        ``scene``, ``plugin``, ``points`` (method :func:`plugin_method`), ``warnings``, maybe ``failed``.
    """
    from kdtrace.kdtree import build_kdtree
    from kdtrace.plugins import PluginError, load_denoiser
    from kdtrace.render import render
    from kdtrace.scenes import load_scene
    from references.mitsuba import render_reference
    from reports.plugins import failure

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    width, height, depth = profile.sweep_width, profile.sweep_height, recon.max_depth
    method = plugin_method(spec)
    row: dict[str, Any] = {"scene": name, "plugin": spec, "method": method, "points": []}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(name)
        tree = build_kdtree(scene, "local", config.kdtree)
        reference = render_reference(scene, profile.sweep_reference_spp, depth, profile.seed % 2**32, width, height)
        try:
            denoiser = load_denoiser(spec)
            for spp in profile.sweep_spp:
                if progress is not None:
                    progress.set_postfix_str(f"{name}: plug-in {spec}, {spp} spp")
                result, seconds = shortest(lambda spp=spp: render(scene, spp=spp, max_depth=depth, seed=profile.seed,
                                                                  width=width, height=height, aux=True, tree=tree),
                                           warmup=0, seconds_of=lambda r: r.seconds)
                frame = AuxFrame(*(np.ascontiguousarray(a, np.float32) for a in (result.rgb, result.albedo, result.normal)))
                image, steps = timed_reconstruction([lambda f: denoiser(f.rgb, f.albedo, f.normal)], frame)
                row["points"].append(_point(method, spp, width, height, seconds, steps, image, reference.rgb,
                                            errors(frame.rgb, reference.rgb)))
        except PluginError as error:
            row["failed"] = failure(error)
    row["warnings"] = sorted({str(w.message) for w in caught})
    return row


def plugin_scene_rows(specs: Sequence[str], config: Config, profile_name: str, out_dir: Path, fresh: bool,
                      progress: bool) -> list[dict]:
    """:func:`measure_plugin_scene` of every plug-in on every reconstruction scene, cached apart from our rows.

    A row is kept in ``out_dir/rows/error_time-plugins/SCENE/SLUG.json`` under a content
    key of the spec, a hash of the plug-in's source, :data:`PLUGIN_ROW_VERSION` and the
    settings of :func:`scene_rows`; a failed row is measured again on the next run.
    """
    from kdtrace.plugins import DENOISER_GROUP
    from reports.plugins import fingerprint, slug

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    settings = row_settings(config, profile, recon)
    pairs = [(spec, name) for spec in specs for name in profile.reconstruction_scenes]
    rows = []
    bar = tqdm(pairs, unit="row", desc=f"error_time plug-ins ({profile_name})", disable=not progress)
    for spec, name in bar:
        path = out_dir / "rows" / "error_time-plugins" / name / f"{slug(spec)}.json"
        key = content_key("error_time-plugin-row", PLUGIN_ROW_VERSION, name, spec, fingerprint(spec, DENOISER_GROUP),
                          TIMING_REPEATS, settings)
        if not fresh and path.exists():
            saved = json.loads(path.read_text())
            if saved.get("key") == key and not saved["row"].get("failed"):
                bar.write(f"error_time {name}: reusing plug-in {spec}'s row measured {saved['measured_at']}")
                rows.append(saved["row"])
                continue
        row = measure_plugin_scene(name, spec, config, profile_name, bar)
        atomic_write_bytes(path, json.dumps({"key": key, "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"), "row": row},
                                            indent=1).encode())
        rows.append(row)
    return rows


def with_plugins(rows: Sequence[dict], plugin_rows: Sequence[dict]) -> list[dict]:
    """Our rows (copies) with the plug-ins' points appended and their failures under ``plugin_failures``."""
    merged = []
    for row in rows:
        extra = [p for p in plugin_rows if p["scene"] == row["scene"]]
        merged.append({**row, "points": [*row["points"], *(point for p in extra for point in p["points"])],
                       "plugins": {p["plugin"]: p.get("failed") or "ok" for p in extra}})
    return merged


def scene_rows(kind: str, version: int, measure_scene: Callable[..., dict], config: Config, profile_name: str,
               out_dir: Path, fresh: bool, progress: bool, blend_spp: Sequence[int] = (),
               demodulated_scenes: Sequence[str] = (), networks: bool = True) -> list[dict]:
    """Per-scene rows of a report over the profile's reconstruction scenes, reused when their key matches.

    A row is cached in ``out_dir/rows/KIND/SCENE.json`` under a content key of the scene,
    ``version``, :data:`TIMING_REPEATS`, the report and reconstruction profiles, the
    KD-tree and render settings, and the source of the renderer and (with ``networks``) of the
    networks (:func:`reconstruction.fingerprint.networks_fingerprint`). A reused row is announced with the date it was
    measured; each new row is written atomically as soon as it is measured, so an
    interrupted run resumes at the next unfinished scene. The networks
    (:class:`Reconstruction`) are trained or loaded only when some row must be measured.

    Parameters
    ----------
    kind : str
        Report name (folder of the rows, first part of the key).
    version : int
        The report's row version.
    measure_scene : callable
        ``measure_scene(name, config, profile_name, models, progress_bar) -> dict``.
    config, profile_name, out_dir, fresh, progress
        As for :func:`generate`.
    blend_spp : sequence of int
        Fit the denoisers' blend weights at these spp (:meth:`Reconstruction.load`); () skips it.
    demodulated_scenes : sequence of str
        Scenes whose albedo-demodulated denoiser is loaded too (:meth:`Reconstruction.load`).
    networks : bool
        Load the networks for ``measure_scene``; False passes None (a report that renders only).

    Returns
    -------
    list of dict
        One row per scene, in the profile's order.
    """
    from kdtrace.render import renderer_fingerprint  # imported when measuring, as render is
    from reconstruction.fingerprint import networks_fingerprint

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    names = list(profile.reconstruction_scenes)
    settings = row_settings(config, profile, recon)
    models: list[Reconstruction] = []
    rows = []
    bar = tqdm(names, unit="scene", desc=f"{kind} ({profile_name})", disable=not progress)
    for name in bar:
        path = out_dir / "rows" / kind / f"{name}.json"
        key = content_key(f"{kind}-row", version, renderer_fingerprint(), name, TIMING_REPEATS, settings,
                          networks_fingerprint() if networks else None)
        if not fresh and path.exists():
            saved = json.loads(path.read_text())
            if saved.get("key") == key:
                bar.write(f"{kind} {name}: reusing the row measured {saved['measured_at']} (pass fresh=True to measure again)")
                rows.append(saved["row"])
                continue
        if not models:
            bar.set_postfix_str("reconstruction networks" if networks else "")
            models.append(Reconstruction.load(names, recon, names, progress, blend_spp=blend_spp,
                                              demodulated_scenes=demodulated_scenes) if networks else None)
        load_before = os.getloadavg()[0]
        with freed_memory_retained():  # a scene's renders and reconstructions, timed, reuse freed memory
            row = measure_scene(name, config, profile_name, models[0], bar)
        row["load_average"] = [load_before, os.getloadavg()[0]]
        record = {"key": key, "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"), "row": row}
        atomic_write_bytes(path, json.dumps(record, indent=1).encode())
        rows.append(row)
    return rows


def generate(config: Config, profile_name: str, out_dir: str | Path, fresh: bool = False,
             progress: bool = True, denoisers: Sequence[str] = ()) -> list[Metric]:
    """Measure (or reuse) the run-time-against-error sweep and write its report.

    Parameters
    ----------
    config : Config
        Resolved configuration.
    profile_name : str
        Report profile (its ``reconstruction_scenes`` and ``sweep_*`` fields).
    out_dir : str or Path
        Writes ``error_time.md``, ``error_time.csv``, ``error_time/SCENE.png``,
        ``error_time.provenance.json`` and ``metrics/error_time.json``; rows in
        ``rows/error_time/``.
    fresh : bool
        Measure every scene again instead of reusing cached rows.
    progress : bool
        tqdm progress bars.
    denoisers : sequence of str
        Plug-in denoiser specs (``kdtrace report --denoiser``): the method ``kdtrace+SPEC``
        (:func:`measure_plugin_scene`) in the tables, the plots and the headline, cached
        apart from our rows (whose keys do not depend on them).

    Returns
    -------
    list of Metric
        Per scene: ``error_time/SCENE/kdtrace_over_mitsuba_paths_per_second`` (ratio, our
        path tracer over Mitsuba at the largest sweep spp, same run) and
        ``error_time/SCENE/denoiser_psnr_Nspp`` (psnr, ours + denoiser at the denoiser's
        training spp, fixed seeds); per plug-in ``error_time/SCENE/plugin:SPEC/failed``
        (zero) and ``.../psnr_Nspp`` (psnr).
    """
    out_dir = Path(out_dir)
    rows = scene_rows("error_time", ROW_VERSION, measure_scene, config, profile_name, out_dir, fresh, progress,
                      blend_spp=config.profile(profile_name).sweep_spp,
                      demodulated_scenes=config.profile(profile_name).demodulated_scenes)
    if denoisers:
        extra = plugin_scene_rows(list(denoisers), config, profile_name, out_dir, fresh, progress)
        for row in extra:
            if row.get("failed"):
                warnings.warn(f"error_time: plug-in {row['plugin']!r} on {row['scene']}: {row['failed']}", ReportNote,
                              stacklevel=2)
        rows = with_plugins(rows, extra)
    metrics = write_outputs(rows, config, profile_name, out_dir)
    write_metrics(out_dir, "error_time", metrics)
    return metrics


# ------------------------------------------------------------------ outputs
def load_note(rows: Sequence[dict]) -> str:
    """A sentence on the machine's 1-minute load average around the measurements (rows that recorded it)."""
    loads = [value for row in rows for value in row.get("load_average", [])]
    if not loads:
        return ""
    return (f"1-minute load average before/after each scene's measurements: {min(loads):.1f}–{max(loads):.1f} on "
            f"{os.cpu_count()} cores (above the core count, other processes competed for the CPU and times are "
            "inflated, the networks' multi-threaded torch times most). ")


def points_frame(rows: Sequence[dict]) -> pd.DataFrame:
    """All measured points of all scenes as one long table (the CSV)."""
    return pd.DataFrame([{"scene": row["scene"], **point} for row in rows for point in row["points"]])


def scene_metrics(row: dict, profile: ProfileConfig, recon: ReconstructionProfile) -> list[Metric]:
    """The gated metrics of one scene's row (see :func:`generate`)."""
    points = pd.DataFrame(row["points"])
    name, spp = row["scene"], max(profile.sweep_spp)
    rate = {method: float(points[(points["method"] == method) & (points["spp"] == spp)]["seconds"].iloc[0])
            for method in ("kdtrace", "mitsuba")}
    metrics = [Metric(f"error_time/{name}/kdtrace_over_mitsuba_paths_per_second", "ratio", rate["mitsuba"] / rate["kdtrace"],
                      f"paths/s of our path tracer over Mitsuba path ({row['mitsuba_variant']}), {row['width']}x"
                      f"{row['height']} {spp} spp, same run")]
    for method, metric, what in (("kdtrace+denoiser", "denoiser", "per-scene denoiser"),
                                 ("kdtrace+demodulated", "demodulated_denoiser", "demodulated per-scene denoiser")):
        denoised = points[(points["method"] == method) & (points["spp"] == recon.spp)]
        if len(denoised):
            metrics.append(Metric(f"error_time/{name}/{metric}_psnr_{recon.spp}spp", "psnr", float(denoised["psnr"].iloc[0]),
                                  f"dB, ours + {what} at {recon.spp} spp vs Mitsuba {row['reference']['spp']} spp"))
            if _measured(denoised, "display_psnr", method):
                metrics.append(Metric(f"error_time/{name}/{metric}_display_psnr_{recon.spp}spp", "psnr",
                                      float(denoised["display_psnr"].iloc[0]),
                                      f"display-referred dB, ours + {what} at {recon.spp} spp"))
    blended = points[points["method"] == "kdtrace+denoiser-blend"]
    for error, prefix, space in (("psnr", "", "linear"), ("display_psnr", "display_", "display-referred")):
        if len(blended) and _measured(blended, f"input_{error}", "kdtrace+denoiser-blend"):
            margins = blended[error] - blended[f"input_{error}"]
            worst = int(blended["spp"].iloc[int(np.argmin(margins.to_numpy()))])
            metrics.append(Metric(f"error_time/{name}/blended_denoiser_{prefix}margin_over_input_db", "psnr",
                                  float(margins.min()),
                                  f"dB ({space}), the smallest PSNR gain over its own noisy input of ours + denoiser "
                                  f"blended with the input, over the sweep spp (at {worst} spp); >= 0: never below the input"))
    return metrics + plugin_metrics(row, recon)


def plugin_metrics(row: dict, recon: ReconstructionProfile) -> list[Metric]:
    """A scene's plug-in denoiser metrics: ``error_time/SCENE/plugin:SPEC/failed`` (zero), ``.../psnr_Nspp`` (psnr)."""
    from reports.plugins import metric_name

    points = pd.DataFrame(row["points"])
    metrics = []
    for spec, status in row.get("plugins", {}).items():
        failed = status != "ok"
        metrics.append(Metric(metric_name("error_time", row["scene"], spec, "failed"), "zero", int(failed),
                              status if failed else "ran"))
        at = points[(points["method"] == plugin_method(spec)) & (points["spp"] == recon.spp)]
        if len(at) and math.isfinite(float(at["psnr"].iloc[0])):
            metrics.append(Metric(metric_name("error_time", row["scene"], spec, f"psnr_{recon.spp}spp"), "psnr",
                                  float(at["psnr"].iloc[0]),
                                  f"dB, ours + plug-in at {recon.spp} spp vs Mitsuba {row['reference']['spp']} spp"))
    return metrics


def losses_to_input(points: pd.DataFrame, error: str = "psnr") -> pd.DataFrame:
    """Points of reconstructions worse than their own noisy input by ``error`` (:data:`ERRORS`): method, spp,
    the error, the input's, and ``difference`` (the reconstruction's minus the input's)."""
    column = f"input_{error}"
    if column not in points or error not in points:
        return pd.DataFrame(columns=["method", "spp", error, column, "difference"])
    worse = points[error] < points[column] if ERRORS[error] else points[error] > points[column]
    below = points[points[column].notna() & worse].copy()
    below["difference"] = below[error] - below[column]
    return below[["method", "spp", error, column, "difference"]]


def _format(value: float, digits: str) -> str:
    return "—" if value is None or not math.isfinite(value) else format(value, digits)


def plot_scene(row: dict, path: Path) -> Path:
    """Error against seconds of one scene, as a PNG (Agg): display-referred PSNR, HDR relMSE (log-log) and
    linear PSNR, one panel each, the legend below the panels so that it covers no data."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = pd.DataFrame(row["points"])
    panels = [(error, label) for error, label in (("display_psnr", "display PSNR (dB)"), ("relmse", "relMSE (HDR)"),
                                                  ("psnr", "linear PSNR (dB, clipped to [0, 1])")) if error in points]
    figure, axes = plt.subplots(1, len(panels), figsize=(5.0 * len(panels), 4.4), constrained_layout=True)
    for method in methods_of(points):
        group = points[points["method"] == method].sort_values("spp")
        if group.empty:
            continue
        style = ("-o" if method in PIPELINES else "--s" if method == "mitsuba" else "-^" if method in METHODS
                 else ":D")
        for axis, (error, _) in zip(axes, panels, strict=True):
            plot = axis.loglog if error == "relmse" else axis.semilogx
            plot(group["seconds"], group[error], style, label=method_label(method), markersize=4)
            first = group.iloc[0]
            axis.annotate(f"{first['spp']}", (first["seconds"], first[error]), fontsize=7, xytext=(3, 3),
                          textcoords="offset points")
    floor = row["reference"]
    for axis, (error, label) in zip(axes, panels, strict=True):
        if error == "relmse":
            axis.axhline(floor["relmse_floor"], color="grey", linewidth=0.8, linestyle=":", label="reference noise")
        elif error == "psnr" and math.isfinite(floor["psnr_ceiling"]):
            axis.axhline(floor["psnr_ceiling"], color="grey", linewidth=0.8, linestyle=":", label="reference noise")
        for threshold in (PSNR_THRESHOLDS if error == "psnr" else DISPLAY_PSNR_THRESHOLDS if error == "display_psnr"
                          else ()):
            axis.axhline(threshold, color="black", linewidth=0.5, alpha=0.4)
        axis.set(xlabel="seconds (render + reconstruction)", ylabel=label, title=f"{row['scene']}: {label}")
        axis.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="outside lower center", ncol=min(5, len(labels)), fontsize=7)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    return atomic_write_bytes(path, buffer.getvalue())


def scene_markdown(row: dict, recon: ReconstructionProfile) -> str:
    """One scene's section: plot link, headline, equal-error and equal-time tables."""
    points = pd.DataFrame(row["points"])
    name = row["scene"]
    reference = row["reference"]
    about = (f"{row['triangles']:,} triangles, {row['width']}x{row['height']}; reference: Mitsuba {reference['spp']} spp "
             f"({reference['variant']}), whose own noise gives relMSE ≈ {reference['relmse_floor']:.2g} and "
             f"PSNR ≈ {reference['psnr_ceiling']:.1f} dB (errors near these measure the reference).")
    lines = [f"## {name}", "", f"![{name}: error against seconds](error_time/{name}.png)", "", about, ""]
    for error, what, unit in (("display_psnr", "display PSNR", " dB"), ("flip", "FLIP", ""), ("psnr", "linear PSNR", " dB")):
        below = losses_to_input(points, error)
        if len(below):
            cells = [f"{method_label(m)} at {spp} spp ({d:+.3g}{unit})"
                     for m, spp, d in zip(below["method"], below["spp"], below["difference"], strict=True)]
            lines += [f"Worse than their own noisy input by {what}: {'; '.join(cells)}.", ""]
        elif f"input_{error}" in points:
            lines += [f"No reconstruction is worse than its own noisy input by {what} at any spp.", ""]
    if "weight" in points:
        blended = points[points["method"] == "kdtrace+denoiser-blend"].sort_values("spp")
        lines += ["Blend weights w(spp) of the denoiser (fitted on the validation views): "
                  + ", ".join(f"{spp} spp {w:.2f}" for spp, w in zip(blended["spp"], blended["weight"], strict=True))
                  + ".", ""]
    failures = {spec: status for spec, status in row.get("plugins", {}).items() if status != "ok"}
    if failures:
        lines += [f"Plug-in {spec}: {status}" + ("" if not len(points[points["method"] == plugin_method(spec)]) else
                                                  " (its points before the failure are shown)") + "."
                  for spec, status in failures.items()] + [""]
    reach = equal_error_table(points)
    mitsuba_max = float(points[points["method"] == "mitsuba"]["seconds"].max())
    # thresholds every method was measured against (a plug-in row may lack the display space)
    keys = [key for key in reach["mitsuba"] if all(key in cells for cells in reach.values())]
    header = ["method", *keys]
    order = methods_of(points)
    body = [[method_label(method), *(reach[method][key].cell() for key in keys)] for method in order]
    for pipeline in denoising_methods(order):
        body.append([f"speed-up of {method_label(pipeline)} over Mitsuba",
                     *(speedup_cell(reach["mitsuba"][key], reach[pipeline][key], mitsuba_max) for key in keys)])
    lines += ["Equal error: seconds to reach each threshold (display-referred PSNR, linear PSNR clipped to [0, 1], "
              "HDR relMSE).", "", tabulate(body, headers=header, tablefmt="github"), ""]
    grid = common_seconds(float(points["seconds"].min()), float(points["seconds"].max()))
    if grid:
        table = equal_time_table(points, grid)
        body = []
        for method in order:
            part = table[table["method"] == method]
            body.append([method_label(method), *(f"{_format(p, '.1f')} / {_format(r, '.2g')}"
                                            for p, r in zip(part["psnr"], part["relmse"], strict=True))])
        lines += ["Equal time: PSNR dB / relMSE at common seconds (interpolated; — outside the measured range).", "",
                  tabulate(body, headers=["method", *(f"{s:g} s" for s in grid)], tablefmt="github"), ""]
    return "\n".join(lines)


def _measured(points: pd.DataFrame, error: str, *methods: str) -> bool:
    """Whether every point of ``methods`` has a finite ``error`` (rows measured before a column existed do not)."""
    if error not in points:
        return False
    values = points.loc[points["method"].isin(methods), error]
    return bool(len(values)) and bool(np.isfinite(values.to_numpy(dtype=float)).all())


def headline_table(rows: Sequence[dict], recon: ReconstructionProfile) -> str:
    """Per scene and pipeline at the denoiser's spp: PSNR, seconds, and the speed-up at equal PSNR over
    brute force on the pipeline's own renderer and over brute-force Mitsuba."""
    body = []
    for row in rows:
        points = pd.DataFrame(row["points"])
        for pipeline in denoising_methods(methods_of(points)):
            if not ((points["method"] == pipeline) & (points["spp"] == recon.spp)).any():
                continue
            renderer = RENDERER.get(pipeline, "kdtrace")  # a plug-in denoiser runs after our path tracer
            shown = {error: headline(points, recon.spp, pipeline, error=error) for error in ("display_psnr", "relmse")
                     if _measured(points, error, pipeline, "mitsuba")}
            own = headline(points, recon.spp, pipeline, renderer,
                           error="display_psnr" if _measured(points, "display_psnr", pipeline, renderer) else "psnr")
            linear = headline(points, recon.spp, pipeline)
            body.append([row["scene"], method_label(pipeline),
                         f"{shown['display_psnr']['value']:.2f}" if "display_psnr" in shown else "—",
                         f"{linear['seconds']:.3g}", own["speedup"] if renderer == "kdtrace" else "(same)",
                         shown["display_psnr"]["speedup"] if "display_psnr" in shown else "—",
                         shown["relmse"]["speedup"] if "relmse" in shown else "—", linear["speedup"]])
    return tabulate(body, headers=["scene", f"pipeline at {recon.spp} spp", "display PSNR dB", "seconds",
                                   "speed-up over our brute force (display)", "over Mitsuba, equal display PSNR",
                                   "over Mitsuba, equal relMSE", "over Mitsuba, equal linear PSNR"], tablefmt="github")


def write_outputs(rows: Sequence[dict], config: Config, profile_name: str, out_dir: Path) -> list[Metric]:
    """Write the Markdown, CSV, plots and provenance (each atomically); return the gated metrics."""
    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    provenance = stamp(config.to_dict(), profile=profile_name, seed=profile.seed)
    machine = provenance["machine"]
    for row in rows:
        plot_scene(row, out_dir / "error_time" / f"{row['scene']}.png")
    threads = rows[0] if rows else {}
    warned = sorted({w for row in rows for w in row["warnings"]})
    header = (
        f"# Run time against error ({profile_name} profile)\n\n"
        f"Machine: {machine['cpu']}, {machine['cores']} cores; {machine['numba_threads']} numba threads, "
        f"{threads.get('torch_threads', '?')} torch threads, {threads.get('mitsuba_threads', '?')} Dr.Jit threads "
        f"(Mitsuba {threads.get('mitsuba_variant', '?')}); OIDN picks its own thread count; {machine['date']}. "
        f"Frames {profile.sweep_width}x{profile.sweep_height} from each scene's camera, max_depth {recon.max_depth}, "
        f"spp {', '.join(map(str, profile.sweep_spp))}; reference Mitsuba {profile.sweep_reference_spp} spp. "
        f"Networks: reconstruction profile `{profile.reconstruction_profile}` (per-scene denoiser trained on "
        f"{recon.spp} spp inputs at {recon.width}x{recon.height}). Seed {profile.seed}.\n\n"
        "Seconds of a pipeline = render + reconstruction, warm: our render is the kernel's wall time (no scene "
        "packing, no compilation); Mitsuba's is `mi.render` plus the copy to NumPy with the scene already loaded, "
        "after one untimed warm-up render at the same spp; every reconstruction step is timed after a warm-up call. "
        f"Each time is the shortest of {TIMING_REPEATS} runs. {load_note(rows)}Absolute seconds depend on the machine; compare methods "
        "within this table only. PSNR on linear images clipped to [0, 1]; relMSE on HDR images "
        "(the superresolution output is clipped to [0, 1], so its relMSE includes clipping of bright pixels). "
        "Between measured points curves are interpolated (log-log for relMSE, PSNR over log seconds); outside them "
        "nothing is extrapolated: `≤ s` means the fastest measured point already meets the threshold, "
        "`not reached` that no measured point does.\n\n"
        + (f"Warnings during the run: {'; '.join(warned)}\n\n" if warned else "")
    )
    text = (header + f"## Headline: speed-up over brute-force Mitsuba at equal PSNR\n\n"
            f"Each pipeline at {recon.spp} spp (the denoiser's training spp, the paper's operating point) against the "
            f"seconds Mitsuba needs to reach the same PSNR on its measured curve.\n\n" + headline_table(rows, recon)
            + "\n\n" + "\n\n".join(scene_markdown(row, recon) for row in rows) + "\n")
    atomic_write_bytes(out_dir / "error_time.md", text.encode())
    atomic_write_bytes(out_dir / "error_time.csv", points_frame(rows).to_csv(index=False).encode())
    atomic_write_bytes(out_dir / "error_time.provenance.json", json.dumps(provenance, indent=1, default=str).encode())
    return [metric for row in rows for metric in scene_metrics(row, profile, recon)]


def run_cli(generate_report: Callable[..., list[Metric]], description: str, argv: Sequence[str] | None) -> int:
    """Command line of a report generator: ``--profile`` (quick), ``--out`` (results/PROFILE), ``--config``, ``--fresh``."""
    from kdtrace.config import load_config

    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--profile", default="quick")
    parser.add_argument("--out", help="output folder (default results/PROFILE)")
    parser.add_argument("--config", help="TOML file overriding kdtrace/defaults.toml")
    parser.add_argument("--fresh", action="store_true", help="measure every scene again")
    args = parser.parse_args(argv)
    from kdtrace.cli import results_dir

    out = results_dir(args.profile, args.out)
    for metric in generate_report(load_config(args.config), args.profile, out, fresh=args.fresh):
        print(f"{metric.name} = {metric.value:.4g} ({metric.kind})")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m reports.error_time [--profile quick] [--out DIR] [--fresh] [--config FILE]``."""
    return run_cli(generate, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
