"""Hypothesis strategies: scenes and rays for the KD-tree stress tests, damaged files for the readers.

Scenes are drawn as *parameters* (kind, size, seed, axis permutation, scale, offset,
duplicates), not as raw arrays, so hypothesis shrinks them to readable cases and a
failure prints everything needed to rebuild the scene (``StressScene.params``).
Rays are made with NumPy from a drawn seed by :func:`make_rays`, aimed at the places
where a KD-tree's floating-point decisions are made: split planes, vertices, edges,
axis-parallel directions (with signed zeros) and planar triangles.

For the reader fuzz tests (``tests/test_fuzz_readers.py``), :data:`mutations` damages
a file's bytes (:func:`mutate`: byte flips, truncation, odd numbers and bytes,
repeated chunks, line shuffles, re-encodings), and :func:`obj_files` and
:func:`ply_files` write files from a small grammar of valid and nearly valid lines.
"""

from __future__ import annotations

import os
import re
import struct

import numpy as np
from hypothesis import HealthCheck, settings
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


# ------------------------------------------------------------------ reader fuzzing
#: Examples per fuzz property in a soak (``KDTRACE_FUZZ_EXAMPLES``); 0 in the default run.
FUZZ_SOAK_EXAMPLES = int(os.environ.get("KDTRACE_FUZZ_EXAMPLES", "0"))
#: Examples per fuzz property in the default run.
FUZZ_DEFAULT_EXAMPLES = 150

settings.register_profile(
    "kdtrace-fuzz",
    # no wall-clock deadline: a soak beside other work waits for a core; the readers' bound is
    # their CPU time (tests/test_fuzz_readers.py), the plug-in checks are single numpy passes
    deadline=None,
    derandomize=not FUZZ_SOAK_EXAMPLES,  # the default run is reproducible, a soak explores
    database=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)


def fuzz(examples: int = FUZZ_DEFAULT_EXAMPLES) -> settings:
    """The ``kdtrace-fuzz`` settings profile with ``examples`` examples (``KDTRACE_FUZZ_EXAMPLES`` in a soak)."""
    return settings(settings.get_profile("kdtrace-fuzz"), max_examples=FUZZ_SOAK_EXAMPLES or examples)


#: Number-like tokens that readers get wrong: NaN/inf spellings, values beyond float32 /
#: float64, indices beyond int32 / int64 / uint32, negative and zero indices, and tokens
#: Python parses and C does not (or the reverse).
ODD_NUMBERS = (
    b"nan", b"NaN", b"-nan", b"inf", b"-inf", b"Infinity", b"1e39", b"-1e39", b"1e309", b"-1e309", b"1e-320",
    b"0", b"-0", b"-1", b"-2", b"-7", b"1", b"2", b"255", b"256", b"-129", b"65536",
    b"2147483647", b"2147483648", b"-2147483649", b"4294967295", b"4294967296", b"4000000000",
    b"9223372036854775807", b"9223372036854775808", b"-9223372036854775809", b"99999999999999999999999",
    b"1_0", b"+1", b"0x1F", b"1.5", b"1e3", b"--1", b".", b"",
)  # fmt: skip
#: Byte sequences of odd encodings and separators.
ODD_BYTES = (
    b"\x00", b"\xff", b"\xff\xfe", b"\xfe\xff", b"\xef\xbb\xbf", b"\xc3\xa9", b"\xe9", b"\xed\xa0\x80", b"\xc3",
    b"\r", b"\r\n", b"\n", b"\t", b" ", b"/", b"//", b"///", b"#", b"\\", b"\\ ", b'"', b"'", b"[", b"]", b"{", b"}",
    b"=", b",", b"\n[[mesh]]\n", b"\nf 1 2 3\n", b"\nend_header\n", b"\nelement vertex 4000000000\n",
)  # fmt: skip
#: Whole-file re-encodings: an encoding, a byte order mark or other line ends.
ENCODINGS = ("latin-1", "utf-8-sig", "utf-16", "utf-16-le", "crlf", "cr", "invalid-utf-8")
_NUMBER = re.compile(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def reencode(data: bytes, encoding: str) -> bytes:
    """``data`` (UTF-8 text) re-encoded as one of :data:`ENCODINGS`."""
    if encoding == "crlf":
        return data.replace(b"\r\n", b"\n").replace(b"\n", b"\r\n")
    if encoding == "cr":
        return data.replace(b"\r\n", b"\n").replace(b"\n", b"\r")
    if encoding == "invalid-utf-8":
        return data.replace(b" ", b" \xff", 1)
    text = data.decode("utf-8", "replace")
    if encoding == "latin-1":
        return text.replace(" ", " \u00e9", 1).encode("latin-1", "replace")
    return text.encode(encoding)


def mutate(data: bytes, mutations: list[tuple]) -> bytes:
    """``data`` after each of ``mutations`` (as drawn by :func:`mutations`), in order.

    Positions are taken modulo the current length, so every drawn mutation applies to
    every file and hypothesis shrinks positions towards the start of the file.
    """
    for kind, *args in mutations:
        n = len(data)
        if kind == "flip":
            position, mask = args
            if n:
                position %= n
                data = data[:position] + bytes([data[position] ^ mask]) + data[position + 1 :]
        elif kind == "truncate":
            data = data[: args[0] % (n + 1)]
        elif kind == "insert":
            position, token = args
            position %= n + 1
            data = data[:position] + token + data[position:]
        elif kind == "number":
            index, token = args
            matches = list(_NUMBER.finditer(data))
            if matches:
                match = matches[index % len(matches)]
                data = data[: match.start()] + token + data[match.end() :]
        elif kind == "repeat":
            position, length, times = args
            position %= n + 1
            chunk = data[position : position + length]
            data = data[:position] + chunk * times + data[position:]
        elif kind in ("delete_line", "duplicate_line", "swap_lines"):
            lines = data.split(b"\n")
            i, j = (a % len(lines) for a in args)
            if kind == "delete_line":
                del lines[i]
            elif kind == "duplicate_line":
                lines.insert(i, lines[i])
            else:
                lines[i], lines[j] = lines[j], lines[i]
            data = b"\n".join(lines)
        elif kind == "encode":
            data = reencode(data, args[0])
        else:
            raise ValueError(f"unknown mutation {kind!r}")
    return data


_positions = st.integers(0, 2**20)
_one_mutation = st.one_of(
    st.tuples(st.just("flip"), _positions, st.sampled_from([1, 2, 4, 8, 16, 32, 64, 128, 255])),
    st.tuples(st.just("truncate"), _positions),
    st.tuples(st.just("insert"), _positions, st.sampled_from(ODD_NUMBERS + ODD_BYTES)),
    st.tuples(st.just("number"), _positions, st.sampled_from(ODD_NUMBERS)),
    st.tuples(st.just("number"), _positions, st.sampled_from(ODD_NUMBERS)),
    st.tuples(st.just("repeat"), _positions, st.integers(1, 64), st.integers(2, 40)),
    st.tuples(st.sampled_from(["delete_line", "duplicate_line", "swap_lines"]), _positions, _positions),
    st.tuples(st.just("encode"), st.sampled_from(ENCODINGS)),
)
#: One to four mutations (see :func:`mutate`).
mutations = st.lists(_one_mutation, min_size=1, max_size=4)


# OBJ grammar: valid and nearly valid lines.
_obj_numbers = st.integers(0, 9).flatmap(lambda k: st.sampled_from([token.decode() for token in ODD_NUMBERS]) if k == 0 else st.one_of(
    st.floats(-1e3, 1e3, allow_nan=False, width=32).map(lambda x: repr(float(x))), st.integers(-5, 5).map(str)))
_obj_indices = st.integers(0, 9).flatmap(lambda k: st.sampled_from([0, 2**31, -(2**31) - 1, 2**63, -(2**63) - 1, 10**20]) if k == 0
                                         else st.one_of(st.integers(1, 4), st.integers(-4, -1), st.integers(-8, 8)))
_blank = st.sampled_from([" ", "  ", "\t", " \t "])


@st.composite
def _obj_corner(draw, form: str) -> str:
    v = draw(_obj_indices)
    if form == "v":
        return str(v)
    vt, vn = draw(_obj_indices), draw(_obj_indices)
    return {"v/vt": f"{v}/{vt}", "v//vn": f"{v}//{vn}", "v/vt/vn": f"{v}/{vt}/{vn}", "v/": f"{v}/", "v//": f"{v}//"}[form]


_valid_obj_lines = st.one_of(
    st.tuples(st.integers(-4, 4), st.integers(-4, 4), st.integers(-4, 4)).map(lambda v: "v {} {} {}".format(*v)),
    st.lists(st.integers(1, 4), min_size=3, max_size=5).map(lambda f: "f " + " ".join(map(str, f))),
    st.lists(st.integers(-4, -1), min_size=3, max_size=4).map(lambda f: "f " + " ".join(f"{i}//1" for i in f)),
    st.sampled_from(["vn 0 0 1", "vt 0.5 0.5", "usemtl white", "usemtl light", "usemtl red", "mtllib lib.mtl", "g part", "# note", ""]),
)


@st.composite
def _obj_line(draw) -> str:
    kind = draw(st.sampled_from(["v", "v", "v", "vt", "vn", "f", "f", "f", "usemtl", "mtllib", "group", "comment", "blank", "odd"]))
    blank = draw(_blank)
    if kind in ("v", "vt", "vn"):
        usual = st.sampled_from({"v": [3, 4, 6], "vt": [1, 2, 3], "vn": [3]}[kind])
        count = draw(st.integers(0, 7) if draw(st.integers(0, 9)) == 0 else usual)
        return kind + blank + blank.join(draw(_obj_numbers) for _ in range(count))
    if kind == "f":
        forms = ["v", "v/vt", "v//vn", "v/vt/vn"]
        form = draw(st.sampled_from(forms + ["v/", "v//"]))
        count = draw(st.integers(1, 6))
        corners = [draw(_obj_corner(form if draw(st.integers(0, 19)) else draw(st.sampled_from(forms)))) for _ in range(count)]
        return "f" + blank + blank.join(corners)
    if kind == "usemtl":
        return "usemtl" + blank + draw(st.sampled_from(["", "white", "light", "red", "caf\u00e9", "a b"]))
    if kind == "mtllib":
        return "mtllib" + blank + draw(st.sampled_from(["", "lib.mtl", "missing.mtl", "lib.mtl lib.mtl", "my\\ lib.mtl", ".", "/"]))
    if kind == "group":
        return draw(st.sampled_from(["o thing", "g a b", "s 1", "s off", "l 1 2", "p 1"]))
    if kind == "comment":
        return "# " + draw(st.text(max_size=8))
    if kind == "blank":
        return draw(st.sampled_from(["", " ", "\t"]))
    return draw(st.sampled_from(["curv 0 1", "vp 0.5", "f", "v", "\u00e9", "\x00", "cstype bspline", "usemtl\t"]))


#: MTL library written beside grammar-made OBJ files (as ``lib.mtl``).
GRAMMAR_MTL = b"newmtl white\nKd 0.8 0.8 0.8\nnewmtl light\nKd 0 0 0\nKe 10 10 10\nnewmtl red\nKd 0.9 0.1 0.1\n"


@st.composite
def obj_files(draw) -> bytes:
    """An OBJ file from a small grammar: mostly valid lines, some nearly valid ones.

    Starts with a few valid vertices so that most drawn faces index something.
    """
    valid = draw(st.booleans())  # only valid lines (vertex indices may still be out of range)
    head = ["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 1 1 0", "vn 0 0 1"][: 5 if valid else draw(st.integers(0, 4))]
    lines = head + draw(st.lists(_valid_obj_lines if valid else _obj_line(), min_size=1, max_size=24))
    newline = draw(st.sampled_from(["\n", "\n", "\r\n", "\r"]))
    return newline.join(lines).encode("utf-8", "surrogateescape") + newline.encode() * draw(st.integers(0, 1))


# PLY grammar: headers with any element count, property type, list type and format, and
# bodies of the right or a wrong length.
_PLY_TYPES = ("char", "uchar", "short", "ushort", "int", "uint", "float", "double", "int8", "uint8", "int32", "uint32", "float32")
_PLY_STRUCT = {"char": "b", "uchar": "B", "short": "h", "ushort": "H", "int": "i", "uint": "I", "float": "f", "double": "d",
               "int8": "b", "uint8": "B", "int32": "i", "uint32": "I", "float32": "f"}  # fmt: skip
_ply_counts = st.one_of(st.integers(0, 6), st.sampled_from([4000000000, 2**31, 2**32 - 1, 10**6]))


@st.composite
def _ply_element(draw, name: str) -> tuple[str, int, list[tuple]]:
    count = draw(st.integers(3, 6) if draw(st.integers(0, 2)) else _ply_counts)
    if name == "vertex":
        names = ["x", "y", "z"] + draw(st.sampled_from([[], [], ["nx", "ny", "nz"], ["u", "v"], ["s", "t"], ["x"]]))
        properties = [(draw(st.sampled_from(["float", "float", "double", "uchar", "int"])), n) for n in names]
    elif name == "face":
        properties = [("list", draw(st.sampled_from(["uchar", "uchar", "int", "char", "uint", "float"])),
                       draw(st.sampled_from(["int", "int", "uint", "uchar", "short", "float"])),
                       draw(st.sampled_from(["vertex_indices", "vertex_indices", "vertex_index"])))]
        if draw(st.booleans()):
            properties.append((draw(st.sampled_from(["int", "uint", "uchar", "float"])), "material_id"))
    else:
        properties = [(draw(st.sampled_from(_PLY_TYPES)), f"p{k}") for k in range(draw(st.integers(0, 2)))]
        if draw(st.booleans()):
            properties.append(("list", "uchar", draw(st.sampled_from(_PLY_TYPES)), "items"))
    return name, count, properties


def _ply_value(draw, type_name: str, index_like: bool) -> float | int:
    if draw(st.integers(0, 3)):  # mostly a usable value
        return draw(st.integers(0, 2)) if index_like or type_name not in ("float", "double", "float32") else draw(
            st.floats(-10, 10, width=32))
    if type_name in ("float", "double", "float32"):
        special = st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e39, -0.0])
        return draw(st.one_of(st.integers(-2, 6).map(float), st.floats(-10, 10, width=32), special) if index_like
                    else st.one_of(st.floats(-10, 10, width=32), special))
    code = _PLY_STRUCT[type_name]
    lo, hi = {"b": (-128, 127), "B": (0, 255), "h": (-(2**15), 2**15 - 1), "H": (0, 2**16 - 1),
              "i": (-(2**31), 2**31 - 1), "I": (0, 2**32 - 1)}[code]  # fmt: skip
    return draw(st.one_of(st.integers(max(lo, -2), min(hi, 6)), st.sampled_from([lo, hi])))


def _packable(code: str, value: float | int) -> float | int:
    """``value`` as ``struct`` packs it with ``code``: an int, or a float beyond float32 as infinity."""
    if code not in "fd":
        return int(value)
    return float(np.copysign(np.inf, value)) if code == "f" and np.isfinite(value) and abs(value) > 3.4e38 else value


@st.composite
def ply_files(draw) -> bytes:
    """A PLY file from a small grammar: header, body matching it (mostly), then damage.

    Element counts are small, or huge (``element vertex 4000000000``) with a small body;
    list lengths mostly 3 or 4, sometimes 0, 255 or negative; the body may lose or gain
    bytes at the end (binary formats: wrong lengths).
    """
    file_format = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian", "binary_little_endian"]))
    if draw(st.booleans()):  # a valid file
        vertices = draw(st.lists(st.tuples(*[st.floats(-10, 10, width=32)] * 3), min_size=3, max_size=6))
        faces = draw(st.lists(st.lists(st.integers(0, len(vertices) - 1), min_size=3, max_size=5), min_size=1, max_size=6))
        elements = [("vertex", len(vertices), [("float", "x"), ("float", "y"), ("float", "z")]),
                    ("face", len(faces), [("list", "uchar", "int", "vertex_indices")])]
        records = [[("float", c) for c in v] for v in vertices] + [[("uchar", len(f))] + [("int", i) for i in f] for f in faces]
        return _ply_bytes(file_format, elements, records)
    elements = [draw(_ply_element("vertex"))]
    if draw(st.integers(0, 7)):
        elements.append(draw(_ply_element("face")))
    if draw(st.integers(0, 3)) == 0:
        elements.insert(draw(st.integers(0, len(elements))), draw(_ply_element(draw(st.sampled_from(["edge", "vertex", "face"])))))
    records: list[list[tuple[str, float | int]]] = []
    for _name, count, properties in elements:
        for _ in range(count if count <= 6 and draw(st.integers(0, 3)) else min(count, draw(st.integers(0, 6)))):
            record: list[tuple[str, float | int]] = []
            for prop in properties:
                if prop[0] == "list":
                    length = draw(st.sampled_from([3, 3, 3, 3, 3, 3, 4, 4, 0, 1, 2, 255, -1]))
                    if length < 0 and _PLY_STRUCT[prop[1]] in "BHI":
                        length = 255
                    elif _PLY_STRUCT[prop[1]] == "b":
                        length = min(length, 127)
                    record.append((prop[1], length))
                    record += [(prop[2], _ply_value(draw, prop[2], True)) for _ in range(min(max(length, 0), 8))]
                else:
                    record.append((prop[0], _ply_value(draw, prop[0], prop[1] == "material_id")))
            records.append(record)
    data = _ply_bytes(file_format, elements, records)
    damage = draw(st.integers(-8, 8)) if draw(st.integers(0, 2)) == 0 else 0
    return data[: len(data) + damage] if damage < 0 else data + bytes(draw(st.binary(min_size=damage, max_size=damage)))


def _ply_bytes(file_format: str, elements: list[tuple], records: list[list[tuple]]) -> bytes:
    """A PLY file of ``elements`` (name, count, properties) whose body holds ``records`` of (type, value)."""
    header = ["ply", f"format {file_format} 1.0", "comment fuzz"]
    for name, count, properties in elements:
        header.append(f"element {name} {count}")
        header += [" ".join(("property", *p)) for p in properties]
    header.append("end_header")
    order = "<" if file_format == "binary_little_endian" else ">"
    data = "\n".join(header).encode() + b"\n"
    if file_format == "ascii":
        data += "".join(" ".join(repr(v) if isinstance(v, float) else str(v) for _, v in record) + "\n"
                        for record in records).encode()
    else:
        data += b"".join(struct.pack(order + _PLY_STRUCT[t], _packable(_PLY_STRUCT[t], v)) for record in records for t, v in record)
    return data
