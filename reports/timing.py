"""Timing, one module for every report part: how seconds are measured and compared within one run.

* :func:`interleaved_seconds`: several ray intersectors taking turns round by round, so that
  a burst of load from other processes hits all of them alike;
* :func:`paired_speedup`: the median over rounds of the per-round ratio of two of them;
* :func:`shortest`: the shortest of a few warm calls (renders and networks);
* :func:`timing_ray_sets`: the rays Table 1 and its sensitivity study time.

Absolute seconds depend on the machine; only ratios measured in one run are compared across
runs (the gate, :mod:`reports.gate`).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from kdtrace.rays import camera_rays, random_rays

#: Timed rounds per ray set (each times every intersector once; medians), after one warm-up call.
TIMING_ROUNDS = 7
#: Timed warm calls of :func:`shortest` (after its warm-up).
TIMING_REPEATS = 3


def interleaved_seconds(intersectors: dict, origins: np.ndarray, directions: np.ndarray,
                        rounds: int = TIMING_ROUNDS, tmax: np.ndarray | None = None) -> dict[str, list[float]]:
    """Seconds of ``intersect`` (or, given ``tmax``, ``occluded``) per intersector and round,
    the intersectors taking turns.

    Every intersector is called once on a few rays first (compilation, scene commit: never
    timed). Then each round times every intersector once, in an order rotated by one each
    round, so that a burst of load from other processes hits all of them alike and the
    per-round ratios stay meaningful on a shared machine.
    """
    def query(intersector, count):
        if tmax is None:
            return intersector.intersect(origins[:count], directions[:count])
        return intersector.occluded(origins[:count], directions[:count], tmax[:count])

    for intersector in intersectors.values():
        query(intersector, 64)
    names = list(intersectors)
    seconds: dict[str, list[float]] = {name: [] for name in names}
    for index in range(rounds):
        shift = index % len(names)
        for name in names[shift:] + names[:shift]:
            started = time.perf_counter()
            query(intersectors[name], len(origins))
            seconds[name].append(time.perf_counter() - started)
    return seconds


def paired_speedup(slow: list[float], fast: list[float]) -> float:
    """Median over rounds of ``slow / fast`` seconds (> 1 when ``fast`` is faster)."""
    return statistics.median(s / f for s, f in zip(slow, fast, strict=True))


def shortest(run: Callable[[], Any], repeats: int = TIMING_REPEATS, warmup: int = 1,
             seconds_of: Callable[[Any], float] | None = None) -> tuple[Any, float]:
    """Call ``run`` ``warmup`` times untimed, then ``repeats`` times; the last result and the shortest time.

    Parameters
    ----------
    run : callable
        No arguments.
    repeats, warmup : int
    seconds_of : callable, optional
        Seconds of one result (e.g. ``RenderResult.seconds``, the kernel's own time);
        default the wall time of the call, ``time.perf_counter``.

    Returns
    -------
    (object, float)
        The last result and the shortest time, seconds.
    """
    for _ in range(warmup):
        run()
    best, result = math.inf, None
    for _ in range(repeats):
        started = time.perf_counter()
        result = run()
        elapsed = time.perf_counter() - started
        best = min(best, elapsed if seconds_of is None else seconds_of(result))
    return result, best


def timing_ray_sets(scene, profile) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The timed rays of a scene: ``primary`` (one jittered frame at the profile's size and spp) and ``incoherent``.

    The frame's rays come pixel after pixel, each pixel's samples together, the order in
    which the path tracer traces them (with samples in separate passes instead, 16
    consecutive rays span 16 pixels, and bunny's camera-ray packets ran at 0.85x single
    rays where they run at 1.07x in this order).
    """
    frame = [camera_rays(scene.camera, profile.frame_width, profile.frame_height, jitter=True,
                         rng=np.random.default_rng(profile.seed + s)) for s in range(profile.frame_spp)]
    return {
        "primary": tuple(np.stack([f[i] for f in frame], axis=1).reshape(-1, 3) for i in range(2)),
        "incoherent": random_rays(scene, profile.timing_rays, profile.seed),
    }
