"""The naive and local-branch SAH KD-trees: build, cache, statistics and ray queries.

``build_kdtree(scene, variant)`` returns a :class:`KDTree` whose ``intersect`` and
``occluded`` run numba kernels (``kdtrace._kdtree_build``, ``kdtrace._kdtree_traverse``)
over flat arrays. Both variants share the same split decisions: the local-branch tree
is the naive tree with Algorithm 3's pull-up applied, so Table 1 compares like with like.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import reprlib
import time
import warnings
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np

from kdtrace import _kdtree_build as build_kernels
from kdtrace import _kdtree_layout as layout_kernels
from kdtrace import _kdtree_traverse as traverse_kernels
from kdtrace import _packet_traverse as packet_kernels
from kdtrace import _ray_order as ray_order
from kdtrace.cache import cache_root, compute_once, content_key, load_npz, save_npz
from kdtrace.config import DEFAULT_CONFIG, KDTreeConfig
from kdtrace.resources import require_memory
from kdtrace.scene import Scene

Variant = Literal["naive", "local"]
VARIANTS: tuple[str, ...] = ("naive", "local")
BUILDER_VERSION = 3  # 2: the O(N log N) presorted build; 3: its branch-free partition (same trees; stats record the seconds)
_TREE_ARRAYS = ("node_meta", "node_split", "node_start", "node_count", "refs")


@dataclass
class TraceCounters:
    """Per-ray work counters of the last query (nodes visited, triangle tests)."""

    nodes_visited: np.ndarray
    triangle_tests: np.ndarray

    def mean(self) -> dict[str, float]:
        return {
            "nodes_per_ray": float(self.nodes_visited.mean()) if self.nodes_visited.size else 0.0,
            "tests_per_ray": float(self.triangle_tests.mean()) if self.triangle_tests.size else 0.0,
        }


#: KDTreeConfig fields that choose how a tree is queried, not how it is built (left out of its
#: cache key), in the order of :class:`KDTree`'s arguments after ``stats``.
TRAVERSAL_CHOICES = ("triangle_test", "vector_spans", "regroup_min_bytes")


def _in_order(traced: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Results of the rays ``order`` (traced in that order) at the rays' own indices."""
    out = np.empty_like(traced)
    out[order] = traced
    return out


class KDTree:
    """A built KD-tree over one scene's triangles.

    Attributes
    ----------
    variant : {"naive", "local"}
    triangle_test : {"watertight", "moller-trumbore"}
        Ray-triangle test of the queries (``KDTreeConfig.triangle_test``).
    vector_spans : bool
        The queries on this tree (the batch queries :meth:`intersect` and :meth:`occluded`, and the
        path tracer's) find a node's triangles hit all at once before testing those one by one
        (``KDTreeConfig.vector_spans``; watertight trees only): the same results and counters.
    regroups : bool
        The batch queries trace a batch grouped by origin cell and direction octant unless told
        otherwise: the tree's traversal data and triangle corners take at least
        ``KDTreeConfig.regroup_min_bytes``.
    stats : dict
        nodes, leaves, empty_leaves, max_depth, triangle_references (leaf + interior),
        leaf_references, interior_references, sah_cost, tree_bytes (the build's arrays: 17 bytes
        a node and 4 a reference), traversal_bytes (what the queries read: the 8-byte node
        array with its cold half, padding slots included, plus the references), span_bytes (the
        references' corners again, in node order, that the vector test reads: :attr:`span_corners`,
        0 without :attr:`vector_spans`), build_seconds, zero_area_triangles, cache_hit.
    last_counters : TraceCounters or None
        Work counters of the most recent query.
    """

    def __init__(self, scene: Scene, variant: str, arrays: dict[str, np.ndarray], stats: dict,
                 triangle_test: str = "watertight", vector_spans: bool = True,
                 regroup_min_bytes: int = KDTreeConfig.regroup_min_bytes):
        self.variant = variant
        self.triangle_test = triangle_test
        self.watertight = triangle_test == "watertight"
        self.vector_spans = vector_spans and self.watertight
        self.node_meta = arrays["node_meta"]
        self.node_split = arrays["node_split"]
        self.node_start = arrays["node_start"]
        self.node_count = arrays["node_count"]
        self.refs = arrays["refs"]
        lo, hi = scene.bounds
        self.box = np.concatenate([lo, hi])
        # Traversal copies: 8-byte nodes in cache-line blocks, one triangle in 36 bytes.
        self.packed_nodes = traversal_nodes(self.node_meta, self.node_split, self.node_start, self.node_count)
        # The kernels' flat views of it: int32 words and the same words as float32 splits.
        self.node_words = self.packed_nodes.reshape(-1)
        self.node_splits = self.node_words.view(np.float32)
        span_bytes = 4 * self._span_length() if self.vector_spans else 0  # float32 span_corners
        self.stats = {**stats, "traversal_bytes": int(self.packed_nodes.nbytes + self.refs.nbytes),
                      "span_bytes": span_bytes}
        self.corners = np.ascontiguousarray(scene.vertices[scene.triangles].reshape(-1, 9))
        self.regroups = self.stats["traversal_bytes"] + self.corners.nbytes >= regroup_min_bytes
        self.last_counters: TraceCounters | None = None

    def _span_length(self) -> int:
        """Length of :attr:`span_corners`: 9 values a reference and the padding of one vector pass."""
        return 9 * len(self.refs) + traverse_kernels.SPAN_LANES

    @functools.cached_property
    def span_corners(self) -> np.ndarray:
        """The references' corners, float32, flat, one block per node's span of references (the
        spans of leaves and of local-branch interior nodes partition ``refs``): the span
        ``first .. first + count - 1`` holds coordinate ``c`` (9 per triangle, as in ``corners``)
        of its ``j``-th reference at ``9 first + c count + j``. So the vector span test
        (:func:`kdtrace._kdtree_traverse.span_hits`) reads a span as 9 runs side by side in
        ``36 count`` contiguous bytes; one run per coordinate over all references had spread a
        span over 9 cache lines, and made the bunny's shadow rays slower, not faster.
        36 bytes a reference, made on first use, and :data:`kdtrace._kdtree_traverse.SPAN_LANES`
        zeros at the end (the vector test reads whole passes of lanes and masks the lanes past
        a span's end)."""
        spans = np.flatnonzero(self.node_count > 0)
        spans = spans[np.argsort(self.node_start[spans], kind="stable")]  # in the order of refs
        counts = self.node_count[spans].astype(np.int64)
        span_first = np.repeat(self.node_start[spans].astype(np.int64), counts)
        span_count = np.repeat(counts, counts)
        position = np.arange(len(self.refs)) - span_first
        if len(self.refs) and (position.min() < 0 or (position >= span_count).any()):
            raise AssertionError("the nodes' spans do not partition the references in order")
        out = np.zeros(self._span_length(), np.float32)
        for c in range(9):
            out[9 * span_first + c * span_count + position] = self.corners[self.refs, c]
        return out

    def __repr__(self) -> str:
        return f"KDTree(variant={self.variant!r}, nodes={self.stats['nodes']}, references={self.stats['triangle_references']})"

    def _trace(self, origins, directions, tmin, tmax, any_hit, packets=False, regroup=None, vector_spans=None):
        origins, directions, tmin, tmax = validate_rays(origins, directions, tmin, tmax)
        vector_spans = self.vector_spans if vector_spans is None else bool(vector_spans) and self.watertight
        n = len(origins)
        regroup = self.regroups and not packets if regroup is None else bool(regroup)
        if regroup and packets:
            raise ValueError("packets trace consecutive rays together: pass packets or regroup, not both")
        order = None
        if regroup and n > 1:
            order = ray_order.regroup_order(origins, directions, self.box)
            origins, directions, tmin, tmax = ray_order.gather_rays(order, origins, directions, tmin, tmax)
        out_t = np.empty(n)
        out_tri = np.empty(n, np.int32)
        out_u = np.empty(n)
        out_v = np.empty(n)
        visited = np.empty(n, np.int32)
        tests = np.empty(n, np.int32)
        # Several chunks per thread balance the load; a chunk owns one traversal stack.
        n_chunks = max(1, min(n, 16 * numba.get_num_threads()))
        outputs = (out_t, out_tri, out_u, out_v, visited, tests)
        if packets:
            if np.any(tmin != 0.0):
                raise ValueError("packets trace rays from their origins: tmin must be 0")
            packet_kernels.trace_batch_packets(
                self.node_words, self.node_splits, self.refs, self.box, self.corners, origins, directions, tmax,
                self.watertight, packet_kernels.PACKET_SIZE, n_chunks, *outputs)
        else:
            traverse_kernels.trace_batch(
                self.node_words, self.node_splits, self.refs, self.box, self.corners,
                self.span_corners if vector_spans else traverse_kernels.no_spans(self.corners), origins, directions,
                tmin, tmax, any_hit, self.watertight, n_chunks, *outputs)
        if order is not None:  # back to the caller's order
            outputs = tuple(_in_order(values, order) for values in outputs)
            out_t, out_tri, out_u, out_v, visited, tests = outputs
        self.last_counters = TraceCounters(visited, tests)
        return out_t, out_tri, out_u, out_v

    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf, packets=False, regroup=None, vector_spans=None):
        """Closest hit of every ray ``o + t d`` with ``tmin < t < tmax``.

        Parameters
        ----------
        origins, directions : (N, 3) float arrays
            Ray origins and directions (scene units; directions need not be unit).
        tmin, tmax : float or (N,) array
            Accepted range of the ray parameter t.
        packets : bool
            Trace consecutive rays in packets of :data:`kdtrace._packet_traverse.PACKET_SIZE`
            (as the path tracer traces its camera rays; tmin must be 0): faster for coherent
            rays such as a camera's, with the same results and counters.
        regroup : bool, optional
            Trace the rays grouped by origin cell and direction octant
            (:mod:`kdtrace._ray_order`), results in the caller's order: the same results and
            counters. Default :attr:`regroups` (never with ``packets``).
        vector_spans : bool, optional
            Find a node's triangles hit all at once before testing them one by one
            (:func:`kdtrace._kdtree_traverse.span_hits`; watertight trees, not with ``packets``):
            the same results and counters. Default :attr:`vector_spans`; False is the oracle.

        Returns
        -------
        t : (N,) float64, inf on a miss
        tri : (N,) int32, index into ``scene.triangles``, -1 on a miss
        u, v : (N,) float64, barycentric weights of vertices 1 and 2
        """
        return self._trace(origins, directions, tmin, tmax, False, packets, regroup, vector_spans)

    def occluded(self, origins, directions, tmax, tmin=0.0, regroup=None, vector_spans=None):
        """True for rays that hit anything with ``tmin < t < tmax`` (shadow rays).

        Parameters
        ----------
        origins, directions : (N, 3) float arrays
            Ray origins and directions.
        tmax : float or (N,) array
            End of each segment; required, unlike in :meth:`intersect`, because a shadow
            ray that forgets its length would report the light itself, or anything behind
            it, as a blocker. Pass ``np.inf`` to test whole rays.
        tmin : float or (N,) array
            Start of each segment.
        regroup : bool, optional
            Trace the rays grouped by origin cell and direction octant, as :meth:`intersect`
            does; default :attr:`regroups`.
        vector_spans : bool, optional
            As in :meth:`intersect`; default :attr:`vector_spans`.

        Returns
        -------
        (N,) bool
        """
        t, _, _, _ = self._trace(origins, directions, tmin, tmax, True, regroup=regroup, vector_spans=vector_spans)
        return np.isfinite(t)


def traversal_nodes(node_meta, node_split, node_start, node_count) -> np.ndarray:
    """The traversal array of a tree (:mod:`kdtrace._kdtree_layout`), 64-byte aligned.

    Parameters
    ----------
    node_meta, node_split, node_start, node_count : (N,) arrays
        The build's node arrays (``meta = left << 2 | axis`` or ``LEAF``, float32 split,
        first reference and reference count).

    Returns
    -------
    (2 M, 2) int32 array, M >= N a multiple of 8 (padding slots are empty leaves)
    """
    if len(node_meta) >= layout_kernels.MAX_NODES or (len(node_count) and node_count.max() >= layout_kernels.MAX_COUNT):
        raise ValueError(f"a tree of {len(node_meta):,} nodes or a node of more than {layout_kernels.MAX_COUNT:,} "
                         f"triangles does not fit the 8-byte traversal node")
    new_index, n_slots = layout_kernels.blocked_order(node_meta)
    packed = layout_kernels.pack_nodes(node_meta, np.ascontiguousarray(node_split, np.float32).view(np.int32),
                                       node_start, node_count, new_index, n_slots)
    # Align to a cache line so each block of eight nodes is one line.
    buffer = np.empty(packed.nbytes + 64, np.uint8)
    offset = (-buffer.ctypes.data) % 64
    aligned = buffer[offset:offset + packed.nbytes].view(np.int32).reshape(packed.shape)
    aligned[...] = packed
    return aligned


def validate_rays(origins, directions, tmin=0.0, tmax=np.inf):
    """Check and convert a ray batch to contiguous float64 arrays.

    Parameters
    ----------
    origins, directions : (N, 3) float arrays
        Ray origins and directions.
    tmin, tmax : float or (N,) array
        Range of the ray parameter t; a float applies to every ray.

    Returns
    -------
    origins, directions : (N, 3) float64
    tmin, tmax : (N,) float64

    Raises
    ------
    TypeError
        tmin or tmax is None or not a number (or array of numbers).
    ValueError
        Wrong shapes (the message gives the shape passed and the N expected), NaN/inf
        origins or directions, zero directions, NaN tmin or tmax, tmin < 0 or tmin > tmax.
    """
    origins = np.ascontiguousarray(origins, dtype=np.float64)
    directions = np.ascontiguousarray(directions, dtype=np.float64)
    if origins.ndim != 2 or origins.shape[1] != 3:
        raise ValueError(f"origins must have shape (N, 3), got {origins.shape}")
    if directions.shape != origins.shape:
        raise ValueError(f"directions must have the shape of origins {origins.shape}, got {directions.shape}")
    if not np.all(np.isfinite(origins)) or not np.all(np.isfinite(directions)):
        raise ValueError("ray origins and directions must be finite (no NaN or inf)")
    if np.any(~directions.any(axis=1)):
        raise ValueError("ray directions must be non-zero")
    n = len(origins)
    bounds = []
    expected = f"a float or an array of shape ({n},), one value per ray"
    usual = {"tmin": "0.0 to start at the origins", "tmax": "np.inf for rays without an end"}
    for name, value in (("tmin", tmin), ("tmax", tmax)):
        if value is None:
            raise TypeError(f"{name} is required: {expected}, got None; pass {usual[name]}")
        try:
            array = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"{name} must be {expected}, got {type(value).__name__} {reprlib.repr(value)}") from None
        try:
            array = np.broadcast_to(array, (n,))
        except ValueError:
            raise ValueError(f"{name} has shape {array.shape} but there are {n} rays; pass {expected}") from None
        if np.isnan(array).any():
            raise ValueError(f"{name} must be a number, got NaN for ray {np.flatnonzero(np.isnan(array))[0]}")
        # a fresh writable copy: a read-only view (what broadcast_to returns) is another numba
        # signature, compiled again for every kernel it reaches
        bounds.append(np.array(array, dtype=np.float64, order="C"))
    tmin, tmax = bounds
    unordered = np.flatnonzero(tmin > tmax)
    if len(unordered):
        i = unordered[0]
        raise ValueError(f"tmin must be <= tmax; ray {i} has tmin = {tmin[i]} > tmax = {tmax[i]} "
                         f"({len(unordered)} of {n} rays are out of order)")
    if np.any(tmin < 0.0):
        raise ValueError("tmin must be >= 0: the traversal only visits the ray ahead of its origin")
    return origins, directions, tmin, tmax


def max_depth_for(triangles: int, config: KDTreeConfig) -> int:
    """Depth limit ``depth_base + depth_log_factor * log2(N)``, capped below the stack size."""
    depth = config.depth_base + config.depth_log_factor * math.log2(max(triangles, 1))
    return int(min(round(depth), traverse_kernels.STACK_SIZE - 4))


def _statistics(variant, arrays, node_area, depth_reached, config, build_seconds, zero_area):
    meta = arrays["node_meta"]
    counts = arrays["node_count"]
    is_leaf = meta == build_kernels.LEAF
    root_area = node_area[0] if node_area[0] > 0 else 1.0
    sah = (
        config.traversal_cost * node_area[~is_leaf].sum()
        + config.intersection_cost * (node_area * counts).sum()
    ) / root_area
    return {
        "variant": variant,
        "nodes": int(len(meta)),
        "leaves": int(is_leaf.sum()),
        "empty_leaves": int((is_leaf & (counts == 0)).sum()),
        "max_depth": int(depth_reached),
        "triangle_references": int(counts.sum()),
        "leaf_references": int(counts[is_leaf].sum()),
        "interior_references": int(counts[~is_leaf].sum()),
        "sah_cost": float(sah),
        "tree_bytes": int(sum(arrays[name].nbytes for name in _TREE_ARRAYS)),
        "build_seconds": float(build_seconds),
        "zero_area_triangles": int(zero_area),
    }


@functools.cache
def _compile_build_kernels() -> None:
    """Run the build kernels once per process on two triangles so compilation is never timed."""
    v0 = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    v1 = v0 + [1.0, 0.0, 0.0]
    v2 = v0 + [0.0, 1.0, 0.0]
    args = (v0, v1, v2, np.arange(2, dtype=np.int32), v0.min(0), v2.max(0) + 1.0, 1.0, 1.0, 0, 4, False, 0.0)
    budget = MIN_REFERENCE_BUDGET
    for arrays in (build_kernels.build_naive(*args, True, False, budget), build_kernels.build_presorted(*args, budget)):
        build_kernels.pull_up(arrays[0], arrays[2], arrays[3], arrays[4])


#: Upper bound of a build's working memory per triangle, in bytes: measured peaks are 291 (Crytek
#: Sponza, 262,267 triangles, 2.4 references each) and 248 (a random soup of 100,000 overlapping
#: triangles, 8.5 references each); 1 KiB leaves room for trees with more references, up to
#: the budget of :data:`MAX_REFERENCES_PER_TRIANGLE`.
BUILD_BYTES_PER_TRIANGLE = 1024
#: A tree holds at most this many references per triangle (or :data:`MIN_REFERENCE_BUDGET`):
#: nodes past the budget become leaves. Real scenes need 2.4 (Crytek Sponza) to 8.5 (an
#: overlapping random soup); without a budget a stack of overlapping coplanar triangles doubles
#: its references at every level until the depth limit.
MAX_REFERENCES_PER_TRIANGLE = 16
#: The budget of a small scene, references (a few huge triangles over many small ones).
MIN_REFERENCE_BUDGET = 65536


def build_bytes(triangles: int) -> int:
    """Upper bound of the bytes a KD-tree build of ``triangles`` triangles allocates (:data:`BUILD_BYTES_PER_TRIANGLE` each)."""
    return triangles * BUILD_BYTES_PER_TRIANGLE


def _build_arrays(scene: Scene, variant: str, config: KDTreeConfig):
    degenerate = scene.degenerate_mask()
    triangle_ids = np.flatnonzero(~degenerate).astype(np.int32)
    if len(triangle_ids) == 0:
        raise ValueError(f"scene {scene.name!r}: every triangle has zero area; nothing to build a tree of")
    require_memory(build_bytes(len(scene.triangles)),
                   f"the {variant} KD-tree of scene {scene.name!r} ({len(scene.triangles):,} triangles)")
    corners = scene.vertices.astype(np.float64)[scene.triangles]
    lo, hi = scene.bounds
    _compile_build_kernels()
    started = time.perf_counter()
    args = (np.ascontiguousarray(corners[:, 0]), np.ascontiguousarray(corners[:, 1]),
            np.ascontiguousarray(corners[:, 2]), triangle_ids, lo, hi,
            config.traversal_cost, config.intersection_cost, config.min_leaf_size,
            max_depth_for(len(triangle_ids), config), config.axis_selection == "cycle", config.empty_bonus)
    # Bounding-box splits at triangle bounds sort once (O(N log N)); perfect splits and
    # centroid candidates re-sort per node (the same tree either way for clip_triangles =
    # false and split_candidates = "bounds": tests/test_kdtree.py).
    budget = max(MAX_REFERENCES_PER_TRIANGLE * len(triangle_ids), MIN_REFERENCE_BUDGET)
    if config.clip_triangles or config.split_candidates == "centroids":
        built = build_kernels.build_naive(*args, config.clip_triangles, config.split_candidates == "centroids", budget)
    else:
        built = build_kernels.build_presorted(*args, budget)
    meta, split, start, count, refs, node_area, depth_reached, capped = built
    if capped:
        warnings.warn(f"scene {scene.name!r}: the {variant} KD-tree reached its budget of {budget:,} triangle "
                      f"references ({MAX_REFERENCES_PER_TRIANGLE} per triangle); the nodes past it are leaves",
                      RuntimeWarning, stacklevel=3)
    if variant == "local":
        start, count, refs = build_kernels.pull_up(meta, start, count, refs)
    seconds = time.perf_counter() - started
    arrays = {"node_meta": meta, "node_split": split, "node_start": start, "node_count": count, "refs": refs}
    stats = _statistics(variant, arrays, node_area, depth_reached, config, seconds, degenerate.sum())
    return arrays, stats


def build_kdtree(
    scene: Scene,
    variant: str = "local",
    config: KDTreeConfig | None = None,
    cache: bool = True,
) -> KDTree:
    """Build (or load from the cache) the KD-tree of ``scene``.

    Parameters
    ----------
    scene : Scene
    variant : {"local", "naive"}
        ``"naive"``: Algorithm 1, only leaves hold triangles. ``"local"``: the paper's
        local-branch tree (Algorithm 3 pull-up; traversal per Algorithm 4).
    config : KDTreeConfig, optional
        Build parameters; defaults from ``defaults.toml``.
    cache : bool
        Reuse a tree cached under a hash of the mesh arrays and the build parameters.

    Raises
    ------
    kdtrace.resources.InsufficientMemoryError
        A build (not a cache hit) whose :func:`build_bytes` exceed the memory available.
    kdtrace.cache.DiskFullError
        The tree was built but its cache file did not fit on the disk (nothing half-written is left).

    Notes
    -----
    Zero-area triangles are left out of the tree (a warning counts them); they can
    never be hit by Möller–Trumbore anyway.
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown KD-tree variant {variant!r}; choose one of {VARIANTS}")
    config = config or DEFAULT_CONFIG.kdtree
    zero_area = int(scene.degenerate_mask().sum())
    if zero_area:
        warnings.warn(
            f"scene {scene.name!r}: {zero_area} zero-area triangles left out of the KD-tree",
            stacklevel=2,
        )
    # The triangle test and the vector span test are traversal choices: the trees are the same.
    build_parameters = {k: v for k, v in dataclasses.asdict(config).items()
                        if k not in TRAVERSAL_CHOICES}
    traversal = [getattr(config, name) for name in TRAVERSAL_CHOICES]
    key = content_key("kdtree", BUILDER_VERSION, variant, scene.geometry_hash(), build_parameters)
    path = cache_root() / "kdtrees" / f"{scene.name}-{variant}-{key[:20]}.npz"

    def stored() -> KDTree | None:
        loaded = load_npz(path)
        if loaded is None or not set(_TREE_ARRAYS) <= set(loaded[0]):
            return None
        arrays, stats = loaded
        return KDTree(scene, variant, arrays, dict(stats, cache_hit=True), *traversal)

    def build() -> KDTree:
        arrays, stats = _build_arrays(scene, variant, config)
        stats["cache_hit"] = False
        if cache:
            save_npz(path, arrays, stats)
        return KDTree(scene, variant, arrays, stats, *traversal)

    return compute_once(path, stored, build) if cache else build()
