"""Run time against error, the curves: the methods compared and the maths on their measured points.

Pure functions of the points :mod:`reports.error_time` measures (one dict per method and spp:
``seconds``, ``psnr``, ``relmse``, ``display_psnr``, ``flip``): interpolation between points
(piecewise linear in log-log for the errors where lower is better, relMSE and FLIP; PSNR
linearly over log seconds), the seconds a
method needs to reach a threshold (never extrapolated), the equal-time and equal-error
tables and the headline speed-up of a pipeline over a brute-force renderer at equal error.
Nothing here renders, times or writes a file.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from reports.paper_figures import ACCEPTABLE_PSNR

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
    "kdtrace+perceptual": "ours + perceptual denoiser",
    "mitsuba+perceptual": "Mitsuba + perceptual denoiser",
}
#: Our reconstruction pipelines, compared with brute force in the headline.
PIPELINES = ("kdtrace+denoiser", "kdtrace+denoiser-blend", "kdtrace-half+denoiser+superres", "mitsuba+denoiser",
             "kdtrace+demodulated", "mitsuba+demodulated", "kdtrace+perceptual", "mitsuba+perceptual")
#: Every denoising pipeline of the headline: ours and both renderers with OIDN.
DENOISING = (*PIPELINES, "kdtrace+oidn", "mitsuba+oidn")
#: The brute-force renderer each pipeline starts from (its own renderer's curve is the first comparison).
RENDERER = {method: "mitsuba" if method.startswith("mitsuba") else "kdtrace" for method in METHODS}


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
        if all_measured(group, "display_psnr", method):
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


def all_measured(points: pd.DataFrame, error: str, *methods: str) -> bool:
    """Whether every point of ``methods`` has a finite ``error`` (rows measured before a column existed do not)."""
    if error not in points:
        return False
    values = points.loc[points["method"].isin(methods), error]
    return bool(len(values)) and bool(np.isfinite(values.to_numpy(dtype=float)).all())


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
