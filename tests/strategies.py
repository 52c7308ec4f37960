"""Hypothesis strategies and ray makers for the KD-tree stress tests.

Scenes are drawn as *parameters* (kind, size, seed, axis permutation, scale, offset,
duplicates), not as raw arrays, so hypothesis shrinks them to readable cases and a
failure prints everything needed to rebuild the scene (``StressScene.params``).
Rays are made with NumPy from a drawn seed by :func:`make_rays`, aimed at the places
where a KD-tree's floating-point decisions are made: split planes, vertices, edges,
axis-parallel directions (with signed zeros) and planar triangles.
"""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

from kdtrace import procedural
from kdtrace._kdtree_build import LEAF
from kdtrace.config import KDTreeConfig
from kdtrace.scene import Material, Scene

#: Scene kinds; see :func:`unit_corners`.
SCENE_KINDS = (
    "soup",          # random triangles in [-1, 1]^3 (generic; intersecting each other)
    "slivers",       # long thin triangles, aspect ratio up to 1e6
    "heightfield",   # smooth height field over a regular grid
    "flat_grid",     # the same grid with zero amplitude: every triangle in one plane
    "terraces",      # height field quantised to a few levels: flat parts lying in split planes
    "coplanar",      # overlapping triangles in one plane, some exact duplicates
    "flat_soup",     # random soup squashed flat along one axis (all z equal)
    "boxes",         # axis-aligned boxes on a 1/8 lattice: faces in split planes, touching boxes
    "big_and_small",  # small soup plus a few huge triangles and axis-aligned quads (pull-up candidates)
)
#: Kinds whose triangles are in general position (no shared edges, no coplanar sets).
GENERIC_KINDS = ("soup", "slivers")
#: Ray kinds of :func:`make_rays`.
RAY_KINDS = ("random", "axis_parallel", "split_plane", "split_plane_edge", "vertex", "edge", "interior")


class StressScene:
    """A drawn scene and the parameters that rebuild it (``build_scene(**params)``)."""

    def __init__(self, scene: Scene, params: dict):
        self.scene = scene
        self.params = params

    def __repr__(self) -> str:
        return f"StressScene({self.params}, triangles={len(self.scene.triangles)}, zero_area={int(self.scene.degenerate_mask().sum())})"


def _boxes(count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` axis-aligned boxes with corners on a 1/8 lattice of [-1, 1] (12 triangles each)."""
    quads = []
    for _ in range(count):
        lo = rng.integers(-8, 7, size=3)
        hi = lo + rng.integers(1, 5, size=3)
        lo, hi = lo / 8.0, np.minimum(hi, 8) / 8.0
        for axis in range(3):
            u, v = (axis + 1) % 3, (axis + 2) % 3
            for side in (lo[axis], hi[axis]):
                corner = np.empty((4, 3))
                corner[:, axis] = side
                corner[:, u] = [lo[u], hi[u], hi[u], lo[u]]
                corner[:, v] = [lo[v], lo[v], hi[v], hi[v]]
                quads.append(corner)
    quads = np.array(quads)
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def unit_corners(kind: str, size: int, seed: int) -> np.ndarray:
    """Triangle corners (T, 3, 3) of one scene kind in the unit frame, float64.

    ``size`` is a triangle count (about) or, for the grids, cells per side.
    """
    rng = np.random.default_rng(seed)

    def corners_of(scene: Scene) -> np.ndarray:
        return scene.vertices.astype(np.float64)[scene.triangles]

    if kind == "soup":
        return corners_of(procedural.random_soup(size, seed=seed))
    if kind == "slivers":
        return corners_of(procedural.slivers(size, seed=seed, max_aspect=10.0 ** rng.integers(0, 7)))
    if kind == "heightfield":
        return corners_of(procedural.heightfield_grid(size, seed=seed, amplitude=0.3))
    if kind == "flat_grid":
        return corners_of(procedural.heightfield_grid(size, seed=seed, amplitude=0.0))
    if kind == "terraces":
        corners = corners_of(procedural.heightfield_grid(size, seed=seed, amplitude=1.0))
        corners[..., 2] = np.round(corners[..., 2] * 4.0) / 4.0
        return corners
    if kind == "coplanar":
        return corners_of(procedural.coplanar_stack(size, seed=seed, duplicate_fraction=0.3))
    if kind == "flat_soup":
        corners = corners_of(procedural.random_soup(size, seed=seed, sizes=(0.02, 0.4)))
        corners[..., 2] = rng.choice([0.0, 0.5, -0.375])
        return corners
    if kind == "boxes":
        return _boxes(max(1, size // 12), rng)
    if kind == "big_and_small":
        small = corners_of(procedural.random_soup(size, seed=seed, sizes=(0.01, 0.1)))
        big = rng.uniform(-1.0, 1.0, size=(4, 3, 3))
        quad = np.array([[[-1, -1, 0], [1, -1, 0], [1, 1, 0]], [[-1, -1, 0], [1, 1, 0], [-1, 1, 0]]], float)
        planes = []
        for axis, level in ((2, 0.0), (0, 0.25), (1, -0.5)):
            q = quad.copy()
            q[..., 2] = level
            planes.append(np.roll(q, (axis + 1) % 3, axis=-1) if axis != 2 else q)
        return np.concatenate([small, big, *planes])
    raise ValueError(f"unknown scene kind {kind!r}")


def build_scene(
    kind: str,
    size: int,
    seed: int,
    permutation: tuple[int, int, int] = (0, 1, 2),
    flips: tuple[bool, bool, bool] = (False, False, False),
    scale: float = 1.0,
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    duplicates: float = 0.0,
) -> Scene:
    """A stress scene: ``unit_corners`` with axes permuted/flipped, duplicated triangles
    appended (some with rotated corner order), placed at ``corners * scale + offset``
    and rounded to float32 once."""
    corners = unit_corners(kind, size, seed)[..., list(permutation)]
    corners = np.where(np.asarray(flips), -corners, corners)
    if duplicates > 0.0:
        rng = np.random.default_rng(seed + 1)
        copies = corners[rng.integers(0, len(corners), size=max(1, int(duplicates * len(corners))))]
        rotate = rng.random(len(copies)) < 0.5
        copies[rotate] = copies[rotate][:, [1, 2, 0]]
        corners = np.concatenate([corners, copies])[rng.permutation(len(corners) + len(copies))]
    vertices = (corners.reshape(-1, 3) * scale + np.asarray(offset, dtype=np.float64)).astype(np.float32)
    n = len(corners)
    return Scene(f"stress-{kind}", vertices, np.arange(3 * n).reshape(n, 3), np.zeros(n), [Material("grey")])


#: Scales 1e-4 .. 1e5, log-spaced (10 steps per decade).
scales = st.integers(-40, 50).map(lambda k: float(10.0 ** (k / 10.0)))
#: Offsets in units of the scale: mostly none or moderate, up to 1e5 (float32 keeps ~1e-2 of the unit frame there).
offset_factors = st.one_of(
    st.just(0.0),
    st.sampled_from([1.0, -3.0, 100.0, -1e3, 1e4, 1e5, -1e5]),
    st.floats(-1e5, 1e5, allow_nan=False, allow_infinity=False),
)


@st.composite
def stress_scenes(draw, kinds=SCENE_KINDS, max_triangles: int = 600, placement: bool = True, allow_duplicates: bool = True):
    """Draw a :class:`StressScene` of one of ``kinds`` with at most about ``max_triangles`` triangles."""
    kind = draw(st.sampled_from(kinds))
    if kind in ("heightfield", "flat_grid", "terraces"):
        cells = max(1, int(np.sqrt(max_triangles / 2)))
        size = draw(st.sampled_from(sorted({min(c, cells) for c in (1, 2, 4, 8, 16, cells)})))
    elif kind == "boxes":
        size = 12 * draw(st.integers(1, max(1, min(max_triangles // 12, 40))))
    elif kind == "big_and_small":
        size = draw(st.integers(1, max(1, max_triangles - 10)))
    else:
        size = draw(st.integers(1, max_triangles))
    params = {
        "kind": kind,
        "size": size,
        "seed": draw(st.integers(0, 2**16)),
        "permutation": tuple(draw(st.permutations([0, 1, 2]))),
        "flips": tuple(draw(st.tuples(st.booleans(), st.booleans(), st.booleans()))),
    }
    if placement:
        scale = draw(scales)
        params["scale"] = scale
        params["offset"] = tuple(f * scale for f in draw(st.tuples(offset_factors, offset_factors, offset_factors)))
    if allow_duplicates:
        params["duplicates"] = draw(st.sampled_from([0.0, 0.0, 0.1, 0.5]))
    scene = build_scene(**params)
    if scene.degenerate_mask().all():  # nothing to build a tree of (e.g. crushed by a far offset)
        params["offset"] = (0.0, 0.0, 0.0)
        scene = build_scene(**params)
    return StressScene(scene, params)


tree_configs = st.builds(
    KDTreeConfig,
    clip_triangles=st.booleans(),
    axis_selection=st.sampled_from(["all", "cycle"]),
    min_leaf_size=st.sampled_from([1, 2, 8, 16]),  # 16: the default
)


# ------------------------------------------------------------------ rays
def _signed_zero(rng: np.random.Generator, shape) -> np.ndarray:
    return np.where(rng.random(shape) < 0.5, 0.0, -0.0)


def _zero_components(rng: np.random.Generator, directions: np.ndarray, fraction: float = 1.0) -> np.ndarray:
    """Zero one or two components (as +0.0 or -0.0) of a ``fraction`` of the directions."""
    directions = directions.copy()
    n = len(directions)
    chosen = rng.random(n) < fraction
    zeros = rng.integers(1, 3, size=n)
    for i in np.flatnonzero(chosen):
        axes = rng.permutation(3)[: zeros[i]]
        directions[i, axes] = _signed_zero(rng, len(axes))
    return directions


def _box(scene: Scene, margin: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = scene.bounds
    extent = hi - lo
    pad = margin * np.maximum(extent, extent.max() * 0.1 + np.abs(hi).max() * 1e-6)
    return lo - pad, hi + pad


def _corners(scene: Scene) -> np.ndarray:
    return scene.vertices.astype(np.float64)[scene.triangles][~scene.degenerate_mask()]


def split_planes(tree) -> tuple[np.ndarray, np.ndarray]:
    """(axis, position) of every interior node's split plane (position as stored, float32 -> float64)."""
    interior = tree.node_meta != LEAF
    return (tree.node_meta[interior] & 3).astype(np.int64), tree.node_split[interior].astype(np.float64)


def _edges_in_split_planes(tree, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(axis, a, b) of every triangle edge whose two ends lie in one of the tree's split planes."""
    axes, positions = split_planes(tree)
    found = [], [], []
    for k in range(3):
        a, b = corners[:, k], corners[:, (k + 1) % 3]
        for axis in range(3):
            planes = np.unique(positions[axes == axis])
            on = (a[:, axis] == b[:, axis]) & np.isin(a[:, axis], planes)
            found[0].append(np.full(on.sum(), axis))
            found[1].append(a[on])
            found[2].append(b[on])
    return tuple(np.concatenate(part) for part in found)


def scale_directions(rng: np.random.Generator, directions: np.ndarray, factor: float, tiny: float = 0.0) -> np.ndarray:
    """Directions times ``factor``, then every zero component replaced by ``+-tiny`` (when non-zero)."""
    directions = directions * factor
    if tiny:
        zero = directions == 0.0
        directions[zero] = tiny * np.where(rng.random(zero.sum()) < 0.5, -1.0, 1.0)
    return directions


def make_rays(kind: str, scene: Scene, tree, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` rays of one of :data:`RAY_KINDS` (float64 origins and non-zero directions).

    random
        Origins uniform in the enlarged bounding box, directions isotropic.
    axis_parallel
        Like random, with one or two direction components zeroed (+0.0 or -0.0).
    split_plane
        Origins exactly on one or two of the tree's split planes; a third of the
        directions lie in the plane (component ±0), others axis-parallel or random.
    split_plane_edge
        Rays lying exactly in a split plane (direction component ±0 on its axis) through
        a point of a triangle edge lying in that plane (both ends on it: the shared
        edges of grids, terraces and boxes), from either side; scenes without such
        edges get ``split_plane`` rays.
    vertex
        Rays through a vertex: axis-parallel from an exactly shifted origin (the ray
        passes exactly through the float32 vertex), oblique ones aimed at it, and rays
        starting on it.
    edge
        Origins on an edge's line (inside and beyond the edge), going along the edge,
        across it axis-parallel, or in a random direction; plus rays aimed at edge points.
    interior
        Rays aimed at random interior points of triangles (clear hits), half axis-parallel.
    """
    rng = np.random.default_rng(seed)
    lo, hi = _box(scene)
    size = float(np.max(hi - lo))
    origins = rng.uniform(lo, hi, size=(n, 3))
    directions = rng.normal(size=(n, 3))
    corners = _corners(scene)
    if kind == "random":
        pass
    elif kind == "axis_parallel":
        directions = _zero_components(rng, directions)
    elif kind == "split_plane":
        axes, positions = split_planes(tree)
        if len(axes):
            for column in range(2):
                pick = rng.integers(0, len(axes), size=n)
                use = rng.random(n) < (1.0 if column == 0 else 0.4)
                origins[use, axes[pick[use]]] = positions[pick[use]]
                if column == 0:
                    in_plane = rng.random(n) < 0.35
                    directions[in_plane, axes[pick[in_plane]]] = _signed_zero(rng, in_plane.sum())
            directions = _zero_components(rng, directions, fraction=0.3)
    elif kind == "split_plane_edge":
        edges = _edges_in_split_planes(tree, corners)
        if len(edges[0]) == 0:
            return make_rays("split_plane", scene, tree, n, seed)
        axis, a, b = (part[rng.integers(0, len(edges[0]), size=n)] for part in edges)
        rows = np.arange(n)
        s = np.where(rng.random(n) < 0.4, rng.choice([0.0, 0.5, 1.0], size=n), rng.uniform(0.0, 1.0, size=n))
        point = a + s[:, None] * (b - a)
        point[rows, axis] = a[rows, axis]  # exactly in the plane, whatever the rounding of a + s (b - a)
        directions[rows, axis] = _signed_zero(rng, n)
        unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        origins = point - rng.uniform(0.05, 1.0, size=(n, 1)) * size * unit
        origins[rows, axis] = a[rows, axis]
    elif kind == "vertex":
        tri = rng.integers(0, len(corners), size=n)
        vertex = corners[tri, rng.integers(0, 3, size=n)]
        mode = rng.integers(0, 3, size=n)
        axis = rng.integers(0, 3, size=n)
        rows = np.arange(n)
        shift = rng.uniform(0.05, 1.0, size=n) * size * np.where(rng.random(n) < 0.5, -1.0, 1.0)
        axial = mode == 0
        origins[axial] = vertex[axial]
        origins[rows[axial], axis[axial]] += shift[axial]
        directions[axial] = _signed_zero(rng, (axial.sum(), 3))
        directions[rows[axial], axis[axial]] = -np.sign(shift[axial])
        aimed = mode == 1
        origins[aimed] = vertex[aimed] - (rng.uniform(0.1, 1.0, size=(aimed.sum(), 1)) * size * directions[aimed]
                                          / np.linalg.norm(directions[aimed], axis=1, keepdims=True))
        on = mode == 2
        origins[on] = vertex[on]
    elif kind == "edge":
        tri = rng.integers(0, len(corners), size=n)
        k = rng.integers(0, 3, size=n)
        rows = np.arange(n)
        a, b = corners[tri, k], corners[tri, (k + 1) % 3]
        s = np.where(rng.random(n) < 0.3, rng.choice([0.0, 0.5, 1.0], size=n), rng.uniform(-0.5, 1.5, size=n))
        point = a + s[:, None] * (b - a)
        mode = rng.integers(0, 4, size=n)
        origins[mode < 3] = point[mode < 3]
        along = mode == 0
        directions[along] = (b - a)[along] * np.where(rng.random(along.sum()) < 0.5, -1.0, 1.0)[:, None]
        across = mode == 1
        directions[across] = _signed_zero(rng, (across.sum(), 3))
        directions[rows[across], rng.integers(0, 3, size=across.sum())] = np.where(rng.random(across.sum()) < 0.5, -1.0, 1.0)
        aimed = mode == 3
        unit = directions[aimed] / np.linalg.norm(directions[aimed], axis=1, keepdims=True)
        origins[aimed] = point[aimed] - rng.uniform(0.1, 1.0, size=(aimed.sum(), 1)) * size * unit
        # Degenerate (zero-length) directions along collapsed edges: fall back to random.
        bad = ~directions.any(axis=1)
        directions[bad] = rng.normal(size=(bad.sum(), 3))
    elif kind == "interior":
        tri = rng.integers(0, len(corners), size=n)
        w = rng.dirichlet([1.0, 1.0, 1.0], size=n)
        target = np.einsum("ij,ijk->ik", w, corners[tri])
        axis_parallel = rng.random(n) < 0.5
        directions[axis_parallel] = _zero_components(rng, directions[axis_parallel])
        unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        origins = target - rng.uniform(0.05, 1.0, size=(n, 1)) * size * unit
    else:
        raise ValueError(f"unknown ray kind {kind!r}")
    # Every component zeroed (e.g. an in-plane zero plus two more): go along one axis instead.
    dead = np.flatnonzero(~directions.any(axis=1))
    directions[dead, rng.integers(0, 3, size=len(dead))] = np.where(rng.random(len(dead)) < 0.5, -1.0, 1.0)
    return origins, directions
