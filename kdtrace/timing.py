"""Timing, one module for the report parts, the networks' speed checks and the benchmarks.

How seconds are measured and compared within one run:

* :func:`timed`: one call and its seconds (wall time by default), the primitive of the rest;
* :func:`interleaved_seconds`: several ray intersectors taking turns round by round, so that
  a burst of load from other processes hits all of them alike;
* :func:`paired_speedup`: the median over rounds of the per-round ratio of two of them;
* :func:`alternating_seconds`: two callables in rounds whose order alternates (AB, BA, ...),
  each returning its own seconds;
* :func:`shortest`: the shortest of a few warm calls (renders and networks);
* :func:`median_seconds`: the median of a few warm calls with freed memory kept for reuse
  (the networks and OIDN);
* :func:`timing_ray_sets`: the rays Table 1 and its sensitivity study time.

Which statistic a caller takes (shortest, median, median of ratios, geometric mean of ratios)
is the caller's, documented where it is taken. Absolute seconds depend on the machine; only
ratios measured in one run are compared across runs (the gate, :mod:`reports.gate`).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from kdtrace.allocator import freed_memory_retained
from kdtrace.rays import camera_rays, random_rays

#: Timed rounds per ray set (each times every intersector once; medians), after one warm-up call.
TIMING_ROUNDS = 7
#: Timed warm calls of :func:`shortest` (after its warm-up).
TIMING_REPEATS = 3

Result = TypeVar("Result")


def timed(call: Callable[[], Result], clock: Callable[[], float] = time.perf_counter) -> tuple[Result, float]:
    """Call ``call`` once; its result and the seconds it took.

    Parameters
    ----------
    call : callable
        No arguments.
    clock : callable
        Seconds of a clock, read before and after the call: ``time.perf_counter`` (wall time,
        the default) or ``time.process_time`` (CPU seconds of this process).

    Returns
    -------
    (object, float)
        The call's result and its duration, seconds.
    """
    started = clock()
    result = call()
    return result, clock() - started


def interleaved_seconds(intersectors: dict, origins: np.ndarray, directions: np.ndarray,
                        rounds: int = TIMING_ROUNDS, tmax: np.ndarray | None = None) -> dict[str, list[float]]:
    """Seconds of ``intersect`` (or, given ``tmax``, ``occluded``) per intersector and round,
    the intersectors taking turns.

    Every intersector is called once on a few rays first (compilation, scene commit: never
    timed). Then each round times every intersector once, in an order rotated by one each
    round, so that a burst of load from other processes hits all of them alike and the
    per-round ratios stay meaningful on a shared machine.

    Parameters
    ----------
    intersectors : dict
        Name -> object with ``intersect(origins, directions)`` and ``occluded(origins, directions, tmax)``.
    origins, directions : (N, 3) ndarray
        The timed rays.
    rounds : int
        Timed rounds.
    tmax : (N,) ndarray, optional
        Segment lengths; given, ``occluded`` is timed instead of ``intersect``.

    Returns
    -------
    dict
        Name -> wall seconds of each round, in round order.
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
            _, elapsed = timed(lambda name=name: query(intersectors[name], len(origins)))
            seconds[name].append(elapsed)
    return seconds


def paired_speedup(slow: list[float], fast: list[float]) -> float:
    """Median over rounds of ``slow / fast`` seconds (> 1 when ``fast`` is faster).

    Raises
    ------
    ValueError
        The two lists differ in length.
    """
    return statistics.median(s / f for s, f in zip(slow, fast, strict=True))


def alternating_seconds(first: Callable[[], float], second: Callable[[], float], rounds: int,
                        pause_after_first: float = 0.0) -> tuple[list[float], list[float]]:
    """Seconds of ``first()`` and ``second()`` over ``rounds`` rounds, the order alternating.

    Even rounds call ``first`` then ``second``, odd rounds ``second`` then ``first``, so that an
    order effect (the first call of a pair slower, or faster, whichever it is) cancels over
    an even number of rounds. Nothing is warmed up here: the callers warm both sides first.

    Parameters
    ----------
    first, second : callable
        No arguments; each returns the seconds of what it timed (its own clock, e.g. a
        renderer's kernel time, or :func:`timed`'s wall time).
    rounds : int
        Rounds; each calls both once.
    pause_after_first : float
        Seconds to sleep after every call of ``first`` (e.g. until a renderer's worker
        threads are idle before the other side starts).

    Returns
    -------
    (list of float, list of float)
        The seconds of ``first`` and of ``second``, in round order.
    """
    first_seconds, second_seconds = [], []
    for index in range(rounds):
        for side in (first, second) if index % 2 == 0 else (second, first):
            if side is first:
                first_seconds.append(first())
                time.sleep(pause_after_first)
            else:
                second_seconds.append(second())
    return first_seconds, second_seconds


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
        result, elapsed = timed(run)
        best = min(best, elapsed if seconds_of is None else seconds_of(result))
    return result, best


def median_seconds(call: Callable[[], object], repeats: int = 3, warmup: int = 1) -> tuple[float, object]:
    """Median wall time of ``repeats`` calls after ``warmup`` untimed ones, and the last result.

    The calls run with freed memory kept for reuse (:func:`kdtrace.allocator.freed_memory_retained`).

    Parameters
    ----------
    call : callable
        No arguments.
    repeats : int
        Timed calls, at least 1.
    warmup : int
        Untimed calls first.

    Returns
    -------
    (float, object)
        The median wall time, seconds, and the last result.

    Raises
    ------
    ValueError
        ``repeats`` below 1.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    result = None
    times = []
    with freed_memory_retained():
        for _ in range(warmup):
            result = call()
        for _ in range(repeats):
            result, elapsed = timed(call)
            times.append(elapsed)
    return statistics.median(times), result


def timing_ray_sets(scene, profile) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The timed rays of a scene: ``primary`` (one jittered frame at the profile's size and spp) and ``incoherent``.

    The frame's rays come pixel after pixel, each pixel's samples together, the order in
    which the path tracer traces them (with samples in separate passes instead, 16
    consecutive rays span 16 pixels, and bunny's camera-ray packets ran at 0.85x single
    rays where they run at 1.07x in this order).

    Parameters
    ----------
    scene : kdtrace.scene.Scene
    profile : kdtrace.config.ProfileConfig
        Its ``frame_width``, ``frame_height``, ``frame_spp``, ``timing_rays`` and ``seed``.

    Returns
    -------
    dict
        ``"primary"`` and ``"incoherent"`` -> (origins, directions), each (N, 3).
    """
    frame = [camera_rays(scene.camera, profile.frame_width, profile.frame_height, jitter=True,
                         rng=np.random.default_rng(profile.seed + s)) for s in range(profile.frame_spp)]
    return {
        "primary": tuple(np.stack([f[i] for f in frame], axis=1).reshape(-1, 3) for i in range(2)),
        "incoherent": random_rays(scene, profile.timing_rays, profile.seed),
    }
