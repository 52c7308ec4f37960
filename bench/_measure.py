"""Measure, validate and summarise KD-tree builds and ray traversals against Embree.

How to use (the pytest-benchmark suite in ``bench/test_bench_kdtree.py`` does this)::

    bench = SceneBench(load_scene("car"), rays=200_000, seed=SEED)
    info = measure_traversal(benchmark, bench, "local", "primary", "closest")
    results = Results(); results.add(info); results.finalize(); print(results.table())

Every ``measure_*`` function times through ``benchmark.pedantic`` (so warm-up rounds
are never timed), then validates what it timed against Embree (Embree itself against
the brute-force oracle on a sample) and raises :class:`BenchmarkValidationError` on
any disagreement that ``references.agreement`` cannot explain. Rates are rays over
the *shortest* timed round: on a shared machine the minimum is the least noisy
estimate of what the code can do.
"""

from __future__ import annotations

import ctypes
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numba
import numpy as np
from tabulate import tabulate

from bench._plugins import is_plugin, jsonable, plugin_spec
from kdtrace import provenance
from kdtrace.cache import atomic_write_bytes
from kdtrace.kdtree import VARIANTS, KDTree, build_kdtree
from kdtrace.oracle import intersect_brute_force
from kdtrace.plugins import CheckedAccelerator, load_accelerator
from kdtrace.rays import primary_rays, random_rays
from kdtrace.scene import Scene
from kdtrace.timing import timed
from references.agreement import UNEXPLAINED, WRONG, TriangleGeometry, compare_hits, compare_occlusion
from references.embree import EmbreeIntersector

DEFAULT_SCENES = ("cbox-sphere", "car")
DEFAULT_RAYS = 200_000
SEED = 20240607
#: Intersectors timed per scene; Embree first so the run order matches the ratios' needs.
INTERSECTORS = ("embree", *VARIANTS)
RAY_KINDS = ("primary", "incoherent")
QUERIES = ("closest", "occluded")
BUILD_ROUNDS, BUILD_WARMUP_ROUNDS = 3, 1
TRAVERSAL_ROUNDS, TRAVERSAL_WARMUP_ROUNDS = 5, 1
#: Rays per kind checked after a build benchmark.
BUILD_CHECK_RAYS = 2048
#: Rays of Embree's own answer checked against the float64 brute-force oracle (O(rays x triangles)).
ORACLE_CHECK_RAYS = 256
#: Tree statistics reported by the build benchmark.
TREE_STATS = ("triangle_references", "leaf_references", "interior_references", "tree_bytes", "nodes", "max_depth", "sah_cost")
#: Per-variant (or per ray kind) tables of one scene's summary.
SUMMARY_TABLES = ("references", "tree_bytes", "build_seconds", "build_peak_memory_bytes", "mrays_per_s", "ratios")


class BenchmarkValidationError(AssertionError):
    """A timed result disagrees with the reference in a way the agreement rules cannot explain."""


# ------------------------------------------------------------------ rays and per-scene state
@dataclass(frozen=True)
class RayBatch:
    """One deterministic ray set, in the precision each intersector takes without a copy.

    Attributes
    ----------
    kind : str
        ``"primary"`` (coherent camera rays) or ``"incoherent"`` (``random_rays``).
    origins, directions : (N, 3) float32
        The rays as generated (Embree's input).
    origins64, directions64 : (N, 3) float64
        The same values widened (our trees' input), so neither side pays a conversion.
    tmax : (N,) float64
        Segment lengths for ``occluded`` queries: a uniform fraction of the distance
        at which each ray leaves the scene's bounds (so segments end anywhere inside
        the scene, like shadow rays, whether the origin is inside or outside), the
        bounds diagonal for rays that miss them; rounded through float32 so both
        sides see the same values.
    """

    kind: str
    origins: np.ndarray
    directions: np.ndarray
    origins64: np.ndarray
    directions64: np.ndarray
    tmax: np.ndarray

    def __len__(self) -> int:
        return len(self.origins)

    def head(self, n: int) -> RayBatch:
        """The first ``n`` rays."""
        return RayBatch(self.kind, *(a[:n] for a in (self.origins, self.directions, self.origins64, self.directions64, self.tmax)))


def make_rays(scene: Scene, kind: str, n: int, seed: int) -> RayBatch:
    """Generate ``n`` rays of ``kind`` (``"primary"`` or ``"incoherent"``) from ``seed``."""
    generators = {"primary": primary_rays, "incoherent": random_rays}
    if kind not in generators:
        raise ValueError(f"unknown ray kind {kind!r}; choose one of {RAY_KINDS}")
    ray_seed, tmax_seed = np.random.SeedSequence([seed, RAY_KINDS.index(kind)]).generate_state(2)
    origins, directions = generators[kind](scene, n, int(ray_seed))
    origins64, directions64 = origins.astype(np.float64), directions.astype(np.float64)
    fractions = np.random.default_rng(int(tmax_seed)).random(n)
    tmax = (fractions * box_exit(scene, origins64, directions64)).astype(np.float32).astype(np.float64)
    return RayBatch(kind, origins, directions, origins64, directions64, tmax)


def box_exit(scene: Scene, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance (units of ``|d|``) at which each ray leaves ``scene.bounds``; the bounds diagonal if it misses them."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in scene.bounds)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - origins) / directions, (hi - origins) / directions
    near = np.nanmax(np.minimum(t0, t1), axis=1)
    far = np.nanmin(np.maximum(t0, t1), axis=1)
    diagonal = float(np.linalg.norm(hi - lo))
    return np.where((far >= np.maximum(near, 0.0)) & (far > 0.0), far, diagonal)


@dataclass
class SceneBench:
    """Untimed per-scene state shared by the benchmarks: rays, trees, Embree, reference answers.

    Everything is built lazily on first use and kept, so Embree's BVH build, tree
    builds (from the on-disk cache) and ray generation never fall inside a timing.

    Parameters
    ----------
    scene : Scene
    rays : int
        Rays per kind.
    seed : int
        Base seed of the ray generators.
    """

    scene: Scene
    rays: int
    seed: int
    _cache: dict = field(default_factory=dict, repr=False)

    def _get(self, key, make: Callable[[], Any]):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    @property
    def geometry(self) -> TriangleGeometry:
        """Float64 triangle data for ``references.agreement``."""
        return self._get("geometry", lambda: TriangleGeometry.of(self.scene))

    @property
    def embree(self) -> EmbreeIntersector:
        """Embree with as many threads as numba uses."""
        return self._get("embree", lambda: EmbreeIntersector(self.scene, threads=numba.get_num_threads()))

    def tree(self, variant: str) -> KDTree:
        """Our KD-tree of ``variant`` (from the on-disk cache when present)."""
        return self._get(("tree", variant), lambda: build_kdtree(self.scene, variant))

    def plugin(self, spec: str) -> CheckedAccelerator:
        """The plug-in accelerator ``spec`` built on the scene (untimed; its build time in ``plugin_load_seconds``).

        Raises
        ------
        kdtrace.plugins.PluginError
            The factory cannot be imported, raises, or returns no accelerator.
        """
        def load() -> CheckedAccelerator:
            accelerator, self._cache[("plugin_load_seconds", spec)] = timed(lambda: load_accelerator(spec, self.scene))
            return accelerator

        return self._get(("plugin", spec), load)

    def plugin_load_seconds(self, spec: str) -> float:
        """Seconds the factory of the plug-in ``spec`` took on this scene (:meth:`plugin` first)."""
        return self._cache[("plugin_load_seconds", spec)]

    def intersector(self, name: str) -> EmbreeIntersector | KDTree | CheckedAccelerator:
        """``"embree"``, one of our tree variants, or a plug-in accelerator ``"plugin:SPEC"``."""
        if is_plugin(name):
            return self.plugin(plugin_spec(name))
        return self.embree if name == "embree" else self.tree(name)

    def ray_batch(self, kind: str) -> RayBatch:
        """The scene's ``kind`` rays."""
        return self._get(("rays", kind), lambda: make_rays(self.scene, kind, self.rays, self.seed))

    def reference(self, kind: str, query: str):
        """Embree's answer to ``query`` on the ``kind`` rays (computed untimed unless recorded by its benchmark)."""
        return self._get(("reference", kind, query), lambda: run_query(self.embree, self.ray_batch(kind), query))

    def record_reference(self, kind: str, query: str, answer) -> None:
        """Keep Embree's validated benchmark answer as the reference for our variants."""
        self._cache[("reference", kind, query)] = answer


# ------------------------------------------------------------------ timing and queries
def timed_call(benchmark, fn: Callable[[], Any], rounds: int, warmup_rounds: int) -> tuple[Any, float]:
    """Run ``fn`` through ``benchmark.pedantic``; return its last result and the shortest timed round.

    Each call is also timed here (wall time, :func:`kdtrace.timing.timed`) so the rate is
    available whether or not benchmarking is enabled (a disabled pytest-benchmark calls
    ``fn`` once, without warm-up).
    """
    durations = []

    def call():
        result, seconds = timed(fn)
        durations.append(seconds)
        return result

    result = benchmark.pedantic(call, rounds=rounds, warmup_rounds=warmup_rounds, iterations=1)
    timed_rounds = durations[warmup_rounds:] or durations
    return result, min(timed_rounds)


def run_query(intersector: EmbreeIntersector | KDTree | CheckedAccelerator, batch: RayBatch, query: str):
    """Answer ``query`` (``"closest"`` or ``"occluded"``) for ``batch``.

    Embree gets the float32 rays, our trees and plug-in accelerators the float64 ones.

    Returns
    -------
    tuple (t, tri, u, v) for ``"closest"``; (N,) bool for ``"occluded"``.
    """
    if isinstance(intersector, EmbreeIntersector):
        origins, directions = batch.origins, batch.directions
    else:
        origins, directions = batch.origins64, batch.directions64
    if query == "closest":
        return intersector.intersect(origins, directions)
    if query == "occluded":
        return intersector.occluded(origins, directions, batch.tmax)
    raise ValueError(f"unknown query {query!r}; choose one of {QUERIES}")


# ------------------------------------------------------------------ validation
def check_answer(scene: Scene, batch: RayBatch, query: str, answer, reference, geometry: TriangleGeometry | None = None) -> dict[str, int]:
    """Compare ``answer`` with ``reference`` ray by ray; raise on any unexplained disagreement.

    Returns
    -------
    dict
        Ray counts per agreement label (``Comparison.counts``).

    Raises
    ------
    BenchmarkValidationError
        When some ray is labelled ``UNEXPLAINED`` or ``WRONG``.
    """
    if query == "closest":
        comparison = compare_hits(scene, batch.origins, batch.directions, answer, reference, geometry=geometry)
    else:
        comparison = compare_occlusion(scene, batch.origins, batch.directions, batch.tmax, answer, reference, geometry=geometry)
    counts = comparison.counts()
    if counts[UNEXPLAINED] or counts[WRONG]:
        first = np.flatnonzero(np.isin(comparison.labels, (UNEXPLAINED, WRONG)))[:5].tolist()
        raise BenchmarkValidationError(
            f"{scene.name}, {batch.kind} rays, {query}: {counts[UNEXPLAINED]} unexplained and {counts[WRONG]} wrong "
            f"of {counts['rays']} rays (first rays: {first}); counts {counts}"
        )
    return counts


def check_unchanged(who: str, arrays) -> None:
    """Raise if any ``(name, before, after)`` pair differs: ``who`` wrote into inputs every method shares."""
    changed = [name for name, before, after in arrays if not np.array_equal(before, after, equal_nan=True)]
    if changed:
        raise BenchmarkValidationError(f"{who} modified its input {', '.join(changed)} (shared with the other methods)")


def oracle_answer(scene: Scene, batch: RayBatch, query: str):
    """The float64 brute-force oracle's answer to ``query`` (zero-area triangles skipped, as our trees do)."""
    tmax = batch.tmax if query == "occluded" else np.inf
    hits = intersect_brute_force(scene.vertices, scene.triangles, batch.origins, batch.directions, tmax=tmax, skip=scene.degenerate_mask())
    return hits if query == "closest" else np.isfinite(hits[0])


def slice_answer(answer, n: int):
    """The first ``n`` rays of an ``intersect`` tuple or an ``occluded`` array."""
    return tuple(a[:n] for a in answer) if isinstance(answer, tuple) else answer[:n]


# ------------------------------------------------------------------ measurements
def _status_bytes(field_name: str) -> int:
    """A ``/proc/self/status`` memory field (reported in kB) in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field_name + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(field_name)


def peak_memory_during(fn: Callable[[], Any]) -> tuple[Any, int, str]:
    """Run ``fn``; return its result and how far the process's peak RSS rose above its RSS at the start.

    tracemalloc cannot see numba's allocations, so this reads the kernel's
    high-water mark ``VmHWM`` (what ``getrusage().ru_maxrss`` reports). First, glibc's
    ``malloc_trim(0)`` returns freed heap pages to the system (otherwise a build
    reuses the pages of earlier builds and its RSS barely moves), and writing ``5``
    to ``/proc/self/clear_refs`` resets ``VmHWM`` to the current RSS (Linux >= 4.0).
    Then ``VmHWM`` after minus ``VmHWM`` before is the build's own peak of touched
    memory. Where a step is unavailable the difference is only a lower bound (0 when
    the build stays under an earlier peak); the returned method names the steps done.

    Returns
    -------
    result, peak_bytes : object, int
    method : str
    """
    steps = ["VmHWM rise"]
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        steps.append("after malloc_trim")
    except (OSError, AttributeError):
        steps.append("without malloc_trim (lower bound)")
    try:
        Path("/proc/self/clear_refs").write_text("5")
        steps.append("and clear_refs reset")
    except OSError:
        steps.append("without clear_refs reset (lower bound)")
    before = _status_bytes("VmHWM")
    result = fn()
    return result, _status_bytes("VmHWM") - before, " ".join(steps)


def measure_build(benchmark, bench: SceneBench, variant: str) -> dict[str, Any]:
    """Time ``build_kdtree(cache=False)``, then measure its peak memory and check the tree against Embree.

    Numba compilation must already have happened (a build on a tiny scene); the
    warm-up round absorbs first-touch effects. Peak memory comes from one further,
    untimed build, whose tree is the one validated.

    Returns
    -------
    dict
        scene, variant, triangles, the tree statistics (references, bytes, nodes,
        depth, SAH cost), build_seconds, peak_memory_bytes and its method, and the
        agreement counts of the check.
    """
    def build():
        return build_kdtree(bench.scene, variant, cache=False)

    _, seconds = timed_call(benchmark, build, BUILD_ROUNDS, BUILD_WARMUP_ROUNDS)
    tree, peak, method = peak_memory_during(build)
    checked = {}
    for kind in RAY_KINDS:
        sample = bench.ray_batch(kind).head(BUILD_CHECK_RAYS)
        reference = run_query(bench.embree, sample, "closest")
        checked[kind] = check_answer(bench.scene, sample, "closest", run_query(tree, sample, "closest"), reference, bench.geometry)
    stats = tree.stats
    return {
        "benchmark": "build",
        "scene": bench.scene.name,
        "variant": variant,
        "triangles": int(len(bench.scene.triangles)),
        **{key: stats[key] for key in TREE_STATS},
        "build_seconds": seconds,
        "peak_memory_bytes": peak,
        "peak_memory_method": method,
        "checked_rays": {kind: counts["rays"] for kind, counts in checked.items()},
    }


def measure_traversal(benchmark, bench: SceneBench, name: str, kind: str, query: str) -> dict[str, Any]:
    """Time one intersector on one ray kind and query, then validate the timed answer.

    Our trees and plug-in accelerators (``name`` = ``"plugin:SPEC"``) are checked on
    every ray against Embree's answer; Embree's answer is checked on a sample against
    the brute-force oracle and then kept as the reference for the others. A plug-in's
    invalid answer raises :class:`kdtrace.plugins.PluginError` (from the timed call).

    Returns
    -------
    dict
        scene, variant, kind, query, rays, seconds, mrays_per_s, the tree's
        triangles / references / bytes and nodes_per_ray, tests_per_ray (ours),
        threads (Embree), or triangles, plugin_stats and plugin_load_seconds
        (plug-ins), and the agreement counts.
    """
    intersector = bench.intersector(name)
    batch = bench.ray_batch(kind)
    inputs = (batch.origins64.copy(), batch.directions64.copy(), batch.tmax.copy()) if is_plugin(name) else ()
    answer, seconds = timed_call(benchmark, lambda: run_query(intersector, batch, query), TRAVERSAL_ROUNDS, TRAVERSAL_WARMUP_ROUNDS)
    info = {
        "benchmark": "traversal",
        "scene": bench.scene.name,
        "variant": name,
        "kind": kind,
        "query": query,
        "rays": len(batch),
        "seconds": seconds,
        "mrays_per_s": len(batch) / seconds / 1e6,
    }
    if name == "embree":
        sample = batch.head(ORACLE_CHECK_RAYS)
        oracle = oracle_answer(bench.scene, sample, query)
        counts = check_answer(bench.scene, sample, query, slice_answer(answer, len(sample)), oracle, bench.geometry)
        bench.record_reference(kind, query, answer)
        info["threads"] = intersector.threads
    elif is_plugin(name):
        check_unchanged(f"plug-in {plugin_spec(name)!r}", zip(("origins", "directions", "tmax"), inputs,
                                                              (batch.origins64, batch.directions64, batch.tmax), strict=True))
        counts = check_answer(bench.scene, batch, query, answer, bench.reference(kind, query), bench.geometry)
        info.update(triangles=int(len(bench.scene.triangles)), plugin_stats=jsonable(intersector.stats),
                    plugin_load_seconds=bench.plugin_load_seconds(plugin_spec(name)))
    else:
        counters = intersector.last_counters.mean()
        counts = check_answer(bench.scene, batch, query, answer, bench.reference(kind, query), bench.geometry)
        info.update(counters)
        info.update(triangles=int(len(bench.scene.triangles)),
                    triangle_references=intersector.stats["triangle_references"],
                    tree_bytes=intersector.stats["tree_bytes"])
    info["agreement"] = counts
    return info


# ------------------------------------------------------------------ same-run summary
def _ratio(numerator: float | None, denominator: float | None) -> float | None:
    return numerator / denominator if numerator and denominator else None


@dataclass
class Results:
    """The rows measured in one run, and the ratios and summary derived from them.

    ``add`` keeps each row together with the benchmark's ``extra_info`` dict, so
    :meth:`finalize` can write the same-run ratios (``kdtrace_over_embree``,
    ``local_over_naive``; ``plugin_over_embree`` for plug-in accelerators) into rows
    measured before their counterpart.
    """

    rows: list[dict[str, Any]] = field(default_factory=list)
    _extra: list[dict[str, Any]] = field(default_factory=list, repr=False)

    def add(self, info: dict[str, Any], extra_info: dict[str, Any] | None = None) -> None:
        """Record a ``measure_*`` row and the dict (e.g. ``benchmark.extra_info``) that mirrors it."""
        self.rows.append(info)
        self._extra.append(extra_info if extra_info is not None else {})

    def _rates(self) -> dict[tuple, float]:
        return {(r["scene"], r["kind"], r["query"], r["variant"]): r["mrays_per_s"] for r in self.rows if r["benchmark"] == "traversal"}

    def finalize(self) -> None:
        """Fill the same-run ratios into every traversal row.

        ``kdtrace_over_embree`` (our variants), ``local_over_naive`` (local),
        ``plugin_over_embree`` (plug-ins): Mrays/s over Mrays/s on the same rays.
        """
        rates = self._rates()
        for row, extra in zip(self.rows, self._extra, strict=True):
            if row["benchmark"] != "traversal" or row["variant"] == "embree":
                continue
            key = row["scene"], row["kind"], row["query"]
            embree = rates.get((*key, "embree"))
            if is_plugin(row["variant"]):
                ratios = {"plugin_over_embree": _ratio(row["mrays_per_s"], embree)}
                row.update(ratios)
                extra.update(ratios)
                continue
            ratios = {"kdtrace_over_embree": _ratio(row["mrays_per_s"], embree)}
            if row["variant"] == "local":
                ratios["local_over_naive"] = _ratio(row["mrays_per_s"], rates.get((*key, "naive")))
            row.update(ratios)
            extra.update(ratios)

    def summary(self) -> dict[str, dict[str, Any]]:
        """Per-scene summary: triangles, references and their reduction, tree bytes, build seconds, rates, ratios.

        Plug-in accelerators, when any ran, are in a scene's ``plugins`` table (SPEC ->
        stats, load seconds, Mrays/s and ``plugin_over_embree`` per ray kind and
        query), not in the tables of our trees.
        """
        scenes: dict[str, dict[str, Any]] = {}
        rates = self._rates()
        # Build rows first: their tree statistics and build times win over the traversal rows'.
        for row in sorted(self.rows, key=lambda r: r["benchmark"] != "build"):
            scene = scenes.setdefault(row["scene"], {"triangles": None, **{key: {} for key in SUMMARY_TABLES}})
            variant = row["variant"]
            if is_plugin(variant):
                plugin = scene.setdefault("plugins", {}).setdefault(plugin_spec(variant), {})
                plugin.setdefault("stats", row["plugin_stats"])
                plugin.setdefault("load_seconds", row["plugin_load_seconds"])
                continue
            if variant == "embree":
                continue
            scene["triangles"] = row["triangles"]
            scene["references"].setdefault(variant, row["triangle_references"])
            scene["tree_bytes"].setdefault(variant, row["tree_bytes"])
            if row["benchmark"] == "build":
                scene["build_seconds"][variant] = row["build_seconds"]
                scene["build_peak_memory_bytes"][variant] = row["peak_memory_bytes"]
        for (name, kind, query, variant), rate in rates.items():
            if is_plugin(variant):
                plugin = scenes[name]["plugins"][plugin_spec(variant)]
                plugin.setdefault("mrays_per_s", {}).setdefault(kind, {})[query] = rate
                plugin.setdefault("plugin_over_embree", {}).setdefault(kind, {})[query] = _ratio(
                    rate, rates.get((name, kind, query, "embree")))
                continue
            scenes[name]["mrays_per_s"].setdefault(kind, {}).setdefault(query, {})[variant] = rate
        for scene in scenes.values():
            refs = scene["references"]
            if "naive" in refs and "local" in refs:
                scene["references"]["reduction_pct"] = 100.0 * (1.0 - refs["local"] / refs["naive"])
            for kind, queries in scene["mrays_per_s"].items():
                for query, rate in queries.items():
                    scene["ratios"].setdefault(kind, {})[query] = {
                        "local_over_naive": _ratio(rate.get("local"), rate.get("naive")),
                        "local_over_embree": _ratio(rate.get("local"), rate.get("embree")),
                        "naive_over_embree": _ratio(rate.get("naive"), rate.get("embree")),
                    }
        return scenes

    def table(self) -> str:
        """The summary as GitHub-markdown tables: trees per scene, rates per scene, ray kind and query, plug-ins' rates (if any)."""
        summary = self.summary()
        trees, rates, plugins = [], [], []
        for name, scene in summary.items():
            refs, size, build = scene["references"], scene["tree_bytes"], scene["build_seconds"]
            trees.append([name, scene["triangles"], refs.get("naive"), refs.get("local"), refs.get("reduction_pct"),
                          size.get("naive"), size.get("local"), build.get("naive"), build.get("local")])
            for kind, queries in scene["mrays_per_s"].items():
                for query, rate in queries.items():
                    ratio = scene["ratios"][kind][query]
                    rates.append([name, kind, query, rate.get("naive"), rate.get("local"), rate.get("embree"),
                                  ratio["local_over_naive"], ratio["local_over_embree"]])
            for spec, plugin in scene.get("plugins", {}).items():
                for kind, queries in plugin.get("mrays_per_s", {}).items():
                    for query, rate in queries.items():
                        plugins.append([name, kind, query, spec, rate, scene["mrays_per_s"].get(kind, {}).get(query, {}).get("embree"),
                                        plugin["plugin_over_embree"][kind][query]])
        style = {"tablefmt": "github", "floatfmt": ".3g", "missingval": "-"}
        tree_table = tabulate(trees, headers=["scene", "triangles", "refs naive", "refs local", "reduction %", "bytes naive",
                                              "bytes local", "build s naive", "build s local"], **style)
        rate_table = tabulate(rates, headers=["scene", "ray kind", "query", "naive Mrays/s", "local Mrays/s",
                                              "embree Mrays/s", "local/naive", "local/embree"], **style)
        if not plugins:
            return f"{tree_table}\n\n{rate_table}"
        plugin_table = tabulate(plugins, headers=["scene", "ray kind", "query", "plug-in", "plug-in Mrays/s", "embree Mrays/s",
                                                  "plug-in/embree"], **style)
        return f"{tree_table}\n\n{rate_table}\n\n{plugin_table}"


# ------------------------------------------------------------------ machine info and output
def machine_info() -> dict[str, Any]:
    """CPU model, cores, numba threads, platform and package versions (:mod:`kdtrace.provenance`)."""
    return {**provenance.machine(), "packages": provenance.package_versions()}


def write_json_atomic(path: Path, data: Any) -> None:
    """Write ``data`` as JSON to ``path`` atomically (:func:`kdtrace.cache.atomic_write_bytes`)."""
    atomic_write_bytes(path, (json.dumps(data, indent=2) + "\n").encode())


def summary_document(results: Results, rays: int, seed: int) -> dict[str, Any]:
    """The content of ``bench/results/summary.json``: run parameters, machine info and per-scene summary."""
    return {
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "rays_per_kind": rays,
        "seed": seed,
        "rate": "rays / shortest of the timed rounds",
        "machine": machine_info(),
        "scenes": results.summary(),
    }


def select_scenes(option: str, available: list[str]) -> list[str]:
    """Scene names from a ``--bench-scenes`` value: a comma list, or ``all``.

    Raises
    ------
    ValueError
        Naming scenes that are not in ``available``.
    """
    if option.strip() == "all":
        return list(available)
    names = [name.strip() for name in option.split(",") if name.strip()]
    unknown = sorted(set(names) - set(available))
    if unknown or not names:
        raise ValueError(f"--bench-scenes: unknown scene(s) {unknown or option!r}; choose from {available} or 'all'")
    return names
