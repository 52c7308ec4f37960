"""Measure, validate and summarise the path tracer: against Mitsuba 3, per kernel, per KD-tree.

How to use (the pytest-benchmark suite in ``bench/test_bench_render.py`` does this)::

    bench = RenderBench(load_scene("car"), seed=SEED)
    results = RenderResults()
    results.add(measure_throughput(benchmark, bench, "kdtrace"))
    results.add(measure_throughput(benchmark, bench, "mitsuba"))   # validated against ours
    results.add(measure_frame(benchmark, bench, "naive"))
    results.add(measure_frame(benchmark, bench, "local"))          # validated against naive
    results.finalize(); print(results.table())

Three measurements, all with ``max_depth`` = :data:`MAX_DEPTH` (the paper's setting):

- **throughput**: paths/s of our path tracer (``aux=False``, local
  tree) and of Mitsuba's plain ``path`` integrator in ``llvm_ad_rgb``, same scene,
  camera, resolution, spp and depth. Mitsuba's scene is converted and rendered once
  before timing (scene loading and JIT compilation are never timed); our kernel
  compilation is excluded by ``render`` itself.
- **specialisation**: the kernel specialised for the scene's
  features against the general kernel (``features=ALL_FEATURES``).
- **frame** (the paper's Table 1 time rows): a :data:`FRAME_SIZE`, :data:`FRAME_SPP` spp
  frame on the ``naive`` and on the ``local`` tree.

Our times are ``RenderResult.seconds`` (the kernel's wall time; packing the scene and
the 1x1 warm-up call of ``render`` are outside it, though pytest-benchmark's own
statistics include them), Mitsuba's the wall time of ``mi.render`` plus the copy to
NumPy (which forces evaluation). Every rate uses the *shortest* timed round, as in
``bench/_measure.py``. Because a ratio near 1 drowns in the load of a shared machine,
the second side of the kernel and tree comparisons also measures a *paired* ratio:
the geometric mean over :data:`PAIRS` alternating back-to-back renders of both sides
(:func:`paired_ratio`).

Every measurement validates what it timed afterwards and raises
:class:`~bench._measure.BenchmarkValidationError` on a NaN, a mean radiance that
disagrees with the other renderer beyond :data:`MEAN_SIGMAS` standard errors, or two
renders that should be identical (same seed, different tree or kernel) differing in
more than :data:`MAX_DIFFERING_FRACTION` of the pixels (ties between equally near
triangles may legitimately change a few paths).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, Callable

import numba
import numpy as np
from tabulate import tabulate

from bench._measure import SEED, BenchmarkValidationError, machine_info, timed_call, write_json_atomic
from kdtrace.kdtree import VARIANTS, KDTree, build_kdtree
from kdtrace.render import ALL_FEATURES, RenderResult, render
from kdtrace.scene import Scene
from kdtrace.timing import alternating_seconds, timed

#: Mitsuba's ``max_depth`` convention: 3 = one indirect bounce, the paper's setting.
MAX_DEPTH = 3
#: Resolution (width, height) and spp of the throughput and specialisation renders.
THROUGHPUT_SIZE, THROUGHPUT_SPP = (256, 256), 8
#: The paper's Table 1 frame.
FRAME_SIZE, FRAME_SPP = (512, 512), 4
RENDERERS = ("kdtrace", "mitsuba")
KERNELS = ("specialised", "general")
#: The diffuse-only scene the specialisation benchmark always includes.
SPECIALISATION_SCENE = "cbox-original"
ROUNDS, WARMUP_ROUNDS = 3, 1
#: Alternating (AB, BA, ...) render pairs behind each paired ratio (even: cancels the order effect).
PAIRS = 4
#: Mean radiances of two estimates of one image must agree within this many standard errors (per channel).
MEAN_SIGMAS = 5.0
#: Renders expected to be bit-identical may differ in at most this fraction of pixels (ties).
MAX_DIFFERING_FRACTION = 1e-3
RENDER_PACKAGES = ("mitsuba", "drjit")


# ------------------------------------------------------------------ per-scene state
@dataclass
class RenderBench:
    """Untimed per-scene state: trees, the Mitsuba scene, and images kept for validation.

    Parameters
    ----------
    scene : Scene
    seed : int
        Seed of every render (our RNG key; Mitsuba's sampler seed modulo 2**32).

    Attributes
    ----------
    images : dict
        Our renders kept for validation, keyed by (what, width, height, spp), what
        being ``"throughput"``, ``"kernel-<kernel>"`` or ``"frame-<variant>"``.
    """

    scene: Scene
    seed: int = SEED
    images: dict = field(default_factory=dict, repr=False)
    _cache: dict = field(default_factory=dict, repr=False)

    def _get(self, key, make: Callable[[], Any]):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def tree(self, variant: str) -> KDTree:
        """Our KD-tree of ``variant`` (from the on-disk cache when present), built untimed."""
        return self._get(("tree", variant), lambda: build_kdtree(self.scene, variant))

    def mitsuba(self, width: int, height: int, spp: int) -> tuple[Any, Any, str]:
        """(Mitsuba scene, plain ``path`` integrator, variant) at this resolution, converted untimed."""
        return self._get(("mitsuba", width, height, spp), lambda: _mitsuba_scene(self.scene, width, height, spp))


def _mitsuba_scene(scene: Scene, width: int, height: int, spp: int) -> tuple[Any, Any, str]:
    from references.llvm import activate_variant

    variant = activate_variant(None)  # llvm_ad_rgb, or scalar_rgb with a warning
    import mitsuba as mi

    from references.mitsuba import to_mitsuba

    mitsuba_scene, _ = to_mitsuba(scene, MAX_DEPTH, width, height, spp)
    integrator = mi.load_dict({"type": "path", "max_depth": MAX_DEPTH})
    return mitsuba_scene, integrator, variant


def mitsuba_threads() -> int | None:
    """Dr.Jit's worker threads (the LLVM backend's parallelism), or None before Mitsuba is used."""
    import sys

    if "drjit" not in sys.modules:
        return None
    import drjit as dr

    return int(dr.thread_count())


# ------------------------------------------------------------------ validation
def check_finite(rgb: np.ndarray, label: str) -> None:
    """Raise when ``rgb`` holds a NaN or an infinity."""
    bad = ~np.isfinite(rgb)
    if bad.any():
        raise BenchmarkValidationError(f"{label}: {int(bad.any(axis=-1).sum())} pixels are NaN or infinite")


def _mean_and_error(rgb: np.ndarray, variance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel image mean and its standard error (pixels are independent: sum of pixel variances / N^2)."""
    pixels = rgb.shape[0] * rgb.shape[1]
    mean = rgb.reshape(-1, 3).astype(np.float64).mean(axis=0)
    error = np.sqrt(variance.reshape(-1, 3).astype(np.float64).sum(axis=0)) / pixels
    return mean, error


def check_mean_radiance(ours: RenderResult, other_rgb: np.ndarray, label: str, other_variance: np.ndarray | None = None) -> dict[str, Any]:
    """Check that ``other_rgb`` and our image have the same mean radiance per channel.

    Without ``other_variance`` the other image's standard error is taken equal to
    ours (both estimate the same image with the same number of samples).

    Returns
    -------
    dict
        ``mean_ours``, ``mean_other``, ``standard_error`` (combined) and the largest
        ``z`` over the channels.

    Raises
    ------
    BenchmarkValidationError
        A NaN in either image, different shapes, or ``z`` > :data:`MEAN_SIGMAS`.
    """
    check_finite(ours.rgb, f"{label} (ours)")
    check_finite(other_rgb, f"{label} (other)")
    if other_rgb.shape != ours.rgb.shape:
        raise BenchmarkValidationError(f"{label}: image shapes differ, {ours.rgb.shape} vs {other_rgb.shape}")
    mean, error = _mean_and_error(ours.rgb, ours.variance)
    other_mean, other_error = _mean_and_error(other_rgb, ours.variance if other_variance is None else other_variance)
    combined = np.hypot(error, other_error)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(mean == other_mean, 0.0, np.abs(mean - other_mean) / combined)
    if not np.all(z <= MEAN_SIGMAS):
        raise BenchmarkValidationError(
            f"{label}: mean radiance {mean.round(5).tolist()} vs {other_mean.round(5).tolist()} differs by "
            f"{np.nan_to_num(z, posinf=np.inf).round(2).tolist()} standard errors (limit {MEAN_SIGMAS})")
    return {"mean_ours": mean.tolist(), "mean_other": other_mean.tolist(), "standard_error": combined.tolist(), "z": float(z.max())}


def check_near_identical(a: RenderResult, b: RenderResult, label: str) -> dict[str, Any]:
    """Check that two renders with the same seed are bit-identical up to :data:`MAX_DIFFERING_FRACTION` of pixels.

    Returns
    -------
    dict
        ``identical`` (bool), ``differing_pixels`` and the mean-radiance check.

    Raises
    ------
    BenchmarkValidationError
        A NaN, or too many differing pixels, or different mean radiances.
    """
    check_finite(a.rgb, f"{label} (first)")
    check_finite(b.rgb, f"{label} (second)")
    if a.rgb.shape != b.rgb.shape:
        raise BenchmarkValidationError(f"{label}: image shapes differ, {a.rgb.shape} vs {b.rgb.shape}")
    differing = int((a.rgb != b.rgb).any(axis=-1).sum())
    pixels = a.rgb.shape[0] * a.rgb.shape[1]
    if differing > MAX_DIFFERING_FRACTION * pixels:
        raise BenchmarkValidationError(
            f"{label}: {differing} of {pixels} pixels differ (limit {MAX_DIFFERING_FRACTION:.1%}); "
            f"largest difference {float(np.abs(a.rgb - b.rgb).max()):.3g}")
    means = check_mean_radiance(a, b.rgb, label, b.variance)
    return {"identical": differing == 0, "differing_pixels": differing, "z": means["z"]}


# ------------------------------------------------------------------ measurements
def timed_render(benchmark, fn: Callable[[], RenderResult], rounds: int = ROUNDS,
                 warmup_rounds: int = WARMUP_ROUNDS) -> tuple[RenderResult, float]:
    """Run ``fn`` through ``benchmark.pedantic``; return its last result and the shortest ``.seconds`` of the timed rounds."""
    results: list[RenderResult] = []

    def call():
        result = fn()
        results.append(result)
        return result

    benchmark.pedantic(call, rounds=rounds, warmup_rounds=warmup_rounds, iterations=1)
    timed = results[warmup_rounds:] or results
    return results[-1], min(r.seconds for r in timed)


def paired_ratio(numerator: Callable[[], RenderResult], denominator: Callable[[], RenderResult],
                 pairs: int = PAIRS) -> dict[str, Any]:
    """Geometric mean over ``pairs`` back-to-back renders of ``numerator().seconds / denominator().seconds``.

    The order alternates (AB, BA, AB, BA, ...): on the shared test machine the first
    render of a pair was measurably slower than the second whichever it was, and an
    even number of alternating pairs cancels that order effect. Both sides are warm.
    """
    numerator_seconds, denominator_seconds = alternating_seconds(lambda: numerator().seconds,
                                                                 lambda: denominator().seconds, pairs)
    ratios = [a / b for a, b in zip(numerator_seconds, denominator_seconds, strict=True)]
    return {"geomean": float(np.exp(np.mean(np.log(ratios)))), "ratios": ratios}


def _kdtrace_info(result: RenderResult, seconds: float) -> dict[str, Any]:
    stats = result.stats
    rays = stats["rays"]
    return {
        "seconds": seconds,
        "paths": stats["paths"],
        "paths_per_second": stats["paths"] / seconds,
        "rays": rays,
        "mrays_per_s": {kind: count / seconds / 1e6 for kind, count in rays.items()} | {"total": sum(rays.values()) / seconds / 1e6},
        "features": stats["features"],
        "kernel": stats["kernel"],
        "threads": stats["threads"],
        "compile_seconds": stats["compile_seconds"],
    }


def _common(bench: RenderBench, benchmark_name: str, width: int, height: int, spp: int) -> dict[str, Any]:
    return {"benchmark": benchmark_name, "scene": bench.scene.name, "triangles": int(len(bench.scene.triangles)),
            "width": width, "height": height, "spp": spp, "max_depth": MAX_DEPTH, "seed": bench.seed}


def measure_throughput(benchmark, bench: RenderBench, renderer: str, size: tuple[int, int] = THROUGHPUT_SIZE,
                       spp: int = THROUGHPUT_SPP) -> dict[str, Any]:
    """Paths/s of ``renderer`` (``"kdtrace"`` or ``"mitsuba"``) on one scene, then validate the image.

    Ours renders on the local tree without auxiliary buffers (Mitsuba's ``path``
    integrator makes none); its image is kept in ``bench.images`` and Mitsuba's image
    is checked against it (rendered untimed if the kdtrace benchmark did not run).

    Returns
    -------
    dict
        Settings, seconds, paths, paths_per_second, threads; ours also rays and Mrays/s
        by kind, features and kernel; Mitsuba also its variant and first-render seconds
        (scene upload and JIT compilation, untimed), and the mean-radiance check.
    """
    width, height = size
    info = _common(bench, "throughput", width, height, spp) | {"renderer": renderer}

    def ours() -> RenderResult:
        return render(bench.scene, max_depth=MAX_DEPTH, seed=bench.seed, spp=spp, width=width, height=height,
                      aux=False, tree=bench.tree("local"))

    key = ("throughput", width, height, spp)
    if renderer == "kdtrace":
        result, seconds = timed_render(benchmark, ours)
        check_finite(result.rgb, f"{bench.scene.name} kdtrace throughput")
        bench.images[key] = result
        return info | _kdtrace_info(result, seconds)
    if renderer != "mitsuba":
        raise ValueError(f"unknown renderer {renderer!r}; choose one of {RENDERERS}")

    mitsuba_scene, integrator, variant = bench.mitsuba(width, height, spp)  # activates the variant first
    import mitsuba as mi

    seed = bench.seed % 2**32

    def theirs() -> np.ndarray:
        return np.array(mi.render(mitsuba_scene, integrator=integrator, spp=spp, seed=seed), dtype=np.float32)

    _, first_seconds = timed(theirs)  # JIT compilation and scene upload: never timed (also when benchmarking is disabled)
    image, seconds = timed_call(benchmark, theirs, ROUNDS, WARMUP_ROUNDS)
    if key not in bench.images:
        bench.images[key] = ours()
    check = check_mean_radiance(bench.images[key], image[..., :3], f"{bench.scene.name} mitsuba vs kdtrace")
    paths = width * height * spp
    return info | {"seconds": seconds, "paths": paths, "paths_per_second": paths / seconds, "variant": variant,
                   "threads": mitsuba_threads(), "first_render_seconds": first_seconds, "agreement": check}


def measure_specialisation(benchmark, bench: RenderBench, kernel: str, size: tuple[int, int] = THROUGHPUT_SIZE,
                           spp: int = THROUGHPUT_SPP) -> dict[str, Any]:
    """Time the ``"specialised"`` kernel (features from the scene) or the ``"general"`` one (``ALL_FEATURES``).

    The image is checked to be identical to the other kernel's (rendered untimed if
    its benchmark has not run yet).
    """
    if kernel not in KERNELS:
        raise ValueError(f"unknown kernel {kernel!r}; choose one of {KERNELS}")
    width, height = size
    features = {"specialised": None, "general": ALL_FEATURES}

    def run(which: str) -> RenderResult:
        return render(bench.scene, max_depth=MAX_DEPTH, seed=bench.seed, spp=spp, width=width, height=height,
                      features=features[which], tree=bench.tree("local"))

    return _measure_pair(benchmark, bench, "specialisation", KERNELS, kernel, run, size, spp, image_prefix="kernel",
                         noun="kernel", info_key="kernel_requested", paired_order=("general", "specialised"))


def measure_frame(benchmark, bench: RenderBench, variant: str, size: tuple[int, int] = FRAME_SIZE,
                  spp: int = FRAME_SPP) -> dict[str, Any]:
    """The paper's Table 1 time row: one frame on the ``variant`` tree, checked against the other tree's frame."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; choose one of {VARIANTS}")
    width, height = size

    def run(which: str) -> RenderResult:
        return render(bench.scene, max_depth=MAX_DEPTH, seed=bench.seed, spp=spp, width=width, height=height,
                      tree=bench.tree(which))

    return _measure_pair(benchmark, bench, "frame", VARIANTS, variant, run, size, spp, image_prefix="frame",
                         noun="tree", info_key="variant", paired_order=("local", "naive"))


def _measure_pair(benchmark, bench: RenderBench, group: str, choices: tuple[str, ...], choice: str, run,
                  size: tuple[int, int], spp: int, *, image_prefix: str, noun: str, info_key: str,
                  paired_order: tuple[str, str]) -> dict[str, Any]:
    """Time ``run(choice)``; check its image against the other choice's (rendered untimed if needed).

    Images are kept in ``bench.images`` under ``("<image_prefix>-<choice>", width, height, spp)``. The last choice also records
    the paired ratio ``paired_order[0] / paired_order[1]`` of back-to-back renders.
    """
    width, height = size
    result, seconds = timed_render(benchmark, lambda: run(choice))
    bench.images[(f"{image_prefix}-{choice}", width, height, spp)] = result
    other = next(c for c in choices if c != choice)
    key = (f"{image_prefix}-{other}", width, height, spp)
    reference = bench.images.get(key) or run(other)
    bench.images[key] = reference
    check = check_near_identical(result, reference, f"{bench.scene.name} {choice} vs {other} {noun}")
    info = _common(bench, group, width, height, spp) | {info_key: choice}
    info |= _kdtrace_info(result, seconds)
    if choice == choices[-1]:
        info["paired"] = paired_ratio(lambda: run(paired_order[0]), lambda: run(paired_order[1]))
    return info | {"agreement": check}


# ------------------------------------------------------------------ same-run ratios and summary
def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


@dataclass
class RenderResults:
    """Rows of one run; ``finalize`` adds the same-run ratios to every benchmark's ``extra_info``."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    extras: list[dict[str, Any] | None] = field(default_factory=list)

    def add(self, row: dict[str, Any], extra_info: dict[str, Any] | None = None) -> None:
        """Record ``row``; ``extra_info`` (pytest-benchmark's dict) receives the ratios at ``finalize``."""
        self.rows.append(row)
        self.extras.append(extra_info)

    def finalize(self) -> None:
        """Write each row's ratio to the other side of its comparison into its ``extra_info``."""
        summary = self.summary()
        for row, extra in zip(self.rows, self.extras, strict=True):
            if extra is None:
                continue
            scene = summary[row["scene"]]
            keys = {"throughput": ["kdtrace_over_mitsuba"],
                    "frame": ["local_over_naive_seconds", "paired_local_over_naive_seconds"],
                    "specialisation": ["general_over_specialised_seconds", "paired_general_over_specialised_seconds",
                                       "time_saved_pct"]}[row["benchmark"]]
            for key in keys:
                extra[key] = scene[row["benchmark"]].get(key)

    def summary(self) -> dict[str, dict[str, Any]]:
        """Per scene: throughput (paths/s per renderer, ratio, our Mrays/s by kind), frame seconds, specialisation."""
        scenes: dict[str, dict[str, Any]] = {}
        for row in self.rows:
            scene = scenes.setdefault(row["scene"], {
                "triangles": row["triangles"],
                "throughput": {"paths_per_second": {}, "threads": {}, "mrays_per_s": {}},
                "frame": {"seconds": {}},
                "specialisation": {"seconds": {}, "features": None},
            })
            part = scene[row["benchmark"]]
            part.update({key: row[key] for key in ("width", "height", "spp", "max_depth")})
            if row["benchmark"] == "throughput":
                part["paths_per_second"][row["renderer"]] = row["paths_per_second"]
                part["threads"][row["renderer"]] = row["threads"]
                if row["renderer"] == "kdtrace":
                    part["mrays_per_s"] = row["mrays_per_s"]
                else:
                    part["mitsuba_variant"] = row["variant"]
            elif row["benchmark"] == "frame":
                part["seconds"][row["variant"]] = row["seconds"]
                if "paired" in row:
                    part["paired_local_over_naive_seconds"] = row["paired"]["geomean"]
            else:
                part["seconds"][row["kernel_requested"]] = row["seconds"]
                if "paired" in row:
                    part["paired_general_over_specialised_seconds"] = row["paired"]["geomean"]
                if row["kernel_requested"] == "specialised":
                    part["features"] = row["features"]
        for scene in scenes.values():
            rates, frame, kernels = scene["throughput"]["paths_per_second"], scene["frame"]["seconds"], scene["specialisation"]["seconds"]
            scene["throughput"]["kdtrace_over_mitsuba"] = _ratio(rates.get("kdtrace"), rates.get("mitsuba"))
            scene["frame"]["local_over_naive_seconds"] = _ratio(frame.get("local"), frame.get("naive"))
            speedup = _ratio(kernels.get("general"), kernels.get("specialised"))
            scene["specialisation"]["general_over_specialised_seconds"] = speedup
            paired = scene["specialisation"].get("paired_general_over_specialised_seconds", speedup)
            scene["specialisation"]["time_saved_pct"] = None if paired is None else 100.0 * (1.0 - 1.0 / paired)
        return scenes

    def table(self) -> str:
        """One GitHub-markdown row per scene."""
        rows = []
        for name, scene in self.summary().items():
            rates, frame, kernels = scene["throughput"], scene["frame"], scene["specialisation"]
            rows.append([name, scene["triangles"], rates["paths_per_second"].get("kdtrace"), rates["paths_per_second"].get("mitsuba"),
                         rates["kdtrace_over_mitsuba"], rates["mrays_per_s"].get("total"), frame["seconds"].get("naive"),
                         frame["seconds"].get("local"), frame["local_over_naive_seconds"], frame.get("paired_local_over_naive_seconds"),
                         kernels["seconds"].get("specialised"), kernels["seconds"].get("general"),
                         kernels["general_over_specialised_seconds"], kernels.get("paired_general_over_specialised_seconds")])
        return tabulate(rows, headers=["scene", "triangles", "paths/s ours", "paths/s mitsuba", "ours/mitsuba", "Mrays/s ours",
                                       "frame s naive", "frame s local", "local/naive", "paired", "spec s", "general s",
                                       "general/spec", "paired"],
                        tablefmt="github", floatfmt=".3g", missingval="-")


def render_machine_info() -> dict[str, Any]:
    """:func:`bench._measure.machine_info` plus Mitsuba/Dr.Jit versions and Dr.Jit's thread count."""
    info = machine_info()
    for package in RENDER_PACKAGES:
        try:
            info["packages"][package] = version(package)
        except PackageNotFoundError:
            info["packages"][package] = None
    info["mitsuba_threads"] = mitsuba_threads()
    return info


def render_summary_document(results: RenderResults) -> dict[str, Any]:
    """The content of ``bench/results/render_summary.json``."""
    return {
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "seed": SEED,
        "max_depth": MAX_DEPTH,
        "throughput": {"width": THROUGHPUT_SIZE[0], "height": THROUGHPUT_SIZE[1], "spp": THROUGHPUT_SPP,
                       "kdtrace": "local tree, aux=False", "mitsuba": "plain path integrator"},
        "frame": {"width": FRAME_SIZE[0], "height": FRAME_SIZE[1], "spp": FRAME_SPP},
        "rounds": ROUNDS, "warmup_rounds": WARMUP_ROUNDS,
        "time": "shortest timed round: RenderResult.seconds for ours, mi.render + copy for Mitsuba",
        "machine": render_machine_info() | {"numba_threads": numba.get_num_threads()},
        "scenes": results.summary(),
    }


def write_render_summary(path: Path, results: RenderResults) -> None:
    """Write :func:`render_summary_document` to ``path`` atomically."""
    write_json_atomic(path, render_summary_document(results))
