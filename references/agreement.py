"""Ray-by-ray agreement between one of our intersectors and Embree.

Two intersectors agree on a ray when both miss, or both hit at distances within a
float32-derived tolerance (a different triangle at the same distance is a *tie*,
e.g. the two sides of a shared edge). Every other ray is a disagreement, and is
explained with float64 arithmetic as one of:

``zero-area triangle``
    a side hit a triangle of zero area (our trees drop them, Embree keeps them);
``origin on surface``
    the hit lies within tolerance of ``t = 0``: the ray starts on a triangle, where
    Embree accepts ``t = 0`` and our trees and the oracle demand ``t > tmin``;
``tmax boundary``
    the hit lies within tolerance of ``tmax`` (shadow rays ending at the light);
``grazing``
    the ray is nearly parallel to the triangle, so the sign of the float32
    determinant is noise (this includes rays lying in the triangle's plane, whose
    barycentrics are undefined);
``edge/vertex``
    the hit lies within float32 precision of an edge or vertex of the triangle,
    where watertightness is decided by rounding;
``unexplained``
    none of the above: a real bug in one of the two.

Before any explanation is tried, the float64 watertight oracle
(:func:`kdtrace.oracle.nearest_hits_fast`, every ray against every triangle) judges
the disagreement: if it finds a hit clear of both ends of the ray (by that hit's
float32 distance tolerance, below, from ``t = 0`` and from ``tmax``) and nearer than
ours by more than that tolerance (or ours misses it; for shadow rays: ours reports no
blocker), the ray is ``wrong``, whatever its geometry, and no class can absorb it. Separately, every disagreement on which our
answer equals the oracle's and Embree's does not is counted as ``ours exact, Embree
not``.

Precision model. A float32 ray-triangle test on operands of magnitude at most
``|o| + |t d| + scale`` (``scale`` the largest vertex coordinate magnitude) is a
chain of about a dozen rounded operations (float32 rounding of the inputs, two
cross products, dot products, one division), each with relative error at most
``u = 2**-24``; the first-order bound on the hit point's position error is
therefore ``delta = C u (|o| + |t d| + scale)`` with ``C = 16`` (the step count
rounded up to a power of two, not fitted to any data). Moving the plane by
``delta`` moves the hit along the ray by ``delta / |cos theta|``, giving the
distance tolerance ``tol_t = delta / max(|cos theta|, 1e-6) / |d|`` in units of
``|d|``, and a barycentric tolerance ``delta / max(|cos theta|, 1e-6) / h_min``
with ``h_min`` the triangle's smallest altitude. The float32 normal's direction is
uncertain by about ``C u l_max / h_min`` radians (``l_max`` the longest edge), so
rays with ``|cos theta|`` below that are *grazing*.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from kdtrace.oracle import as_float64_rays, nearest_hits_fast
from kdtrace.plugins import OUR_ACCELERATORS, load_accelerator
from kdtrace.scene import Scene

#: Unit roundoff of float32.
UNIT_ROUNDOFF = 2.0**-24
#: Bound on the number of rounded float32 operations in a ray-triangle test (see module docstring).
ROUNDING_STEPS = 16.0
#: Floor on |cos theta| so the tolerances stay finite for rays parallel to a triangle.
MIN_COS = 1e-6

AGREE = "agree"
TIE = "tie: same distance"
ZERO_AREA = "zero-area triangle"
TMIN = "origin on surface"
TMAX = "tmax boundary"
GRAZING = "grazing"
EDGE = "edge/vertex"
UNEXPLAINED = "unexplained"
WRONG = "wrong"
#: Count (not a label) of disagreements where ours equals the oracle and Embree does not.
OURS_EXACT = "ours exact, Embree not"
#: Explanations in the order they are tried; the first that applies is the label.
EXPLANATIONS = (ZERO_AREA, TMIN, TMAX, GRAZING, EDGE)
LABELS = (AGREE, TIE, *EXPLANATIONS, UNEXPLAINED, WRONG)
#: The ray kinds of :func:`check_scene`, with the query each uses.
RAY_KINDS = {"primary": "intersect", "random": "intersect", "vertex": "intersect", "edge": "intersect", "shadow": "occluded"}


# ------------------------------------------------------------------ precision model
def position_tolerance(origins: np.ndarray, directions: np.ndarray, t: np.ndarray, scale: float) -> np.ndarray:
    """Bound on the float32 error of a hit point, ``C u (|o| + |t d| + scale)`` (scene units)."""
    o_len = np.linalg.norm(origins, axis=1)
    d_len = np.linalg.norm(directions, axis=1)
    return ROUNDING_STEPS * UNIT_ROUNDOFF * (o_len + np.abs(t) * d_len + scale)


def t_tolerance(origins: np.ndarray, directions: np.ndarray, t: np.ndarray, cos_theta: np.ndarray, scale: float) -> np.ndarray:
    """Distance tolerance of a float32 hit, in units of ``|d|``.

    Parameters
    ----------
    origins, directions : (N, 3) arrays
        The rays.
    t : (N,) array
        Hit distance in units of ``|d|``.
    cos_theta : (N,) array
        Cosine between the ray and the triangle normal.
    scale : float
        Largest vertex coordinate magnitude of the scene (scene units).

    Returns
    -------
    (N,) float64
        ``C u (|o| + |t d| + scale) / max(|cos theta|, 1e-6) / |d|``.
    """
    d_len = np.linalg.norm(directions, axis=1)
    return position_tolerance(origins, directions, t, scale) / np.maximum(np.abs(cos_theta), MIN_COS) / d_len


@dataclass(frozen=True)
class TriangleGeometry:
    """Float64 per-triangle data for classifying disagreements.

    Attributes
    ----------
    v0, e1, e2 : (T, 3) float64
        First vertex and the two edges from it.
    normal : (T, 3) float64
        Unit geometric normal (zero for zero-area triangles).
    h_min : (T,) float64
        Smallest altitude (scene units).
    grazing_cos : (T,) float64
        ``C u l_max / h_min``: |cos theta| below which a ray counts as grazing.
    degenerate : (T,) bool
        Zero-area triangles.
    scale : float
        Largest vertex coordinate magnitude (scene units).
    """

    v0: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    normal: np.ndarray
    h_min: np.ndarray
    grazing_cos: np.ndarray
    degenerate: np.ndarray
    scale: float

    @classmethod
    def of(cls, scene: Scene) -> TriangleGeometry:
        corners = scene.vertices.astype(np.float64)[scene.triangles]
        e1 = corners[:, 1] - corners[:, 0]
        e2 = corners[:, 2] - corners[:, 0]
        cross = np.cross(e1, e2)
        twice_area = np.linalg.norm(cross, axis=1)
        degenerate = twice_area == 0.0
        safe = np.where(degenerate, 1.0, twice_area)
        l_max = np.linalg.norm(np.stack([e1, e2, corners[:, 2] - corners[:, 1]], 1), axis=2).max(1)
        h_min = np.where(degenerate, 0.0, safe / np.maximum(l_max, np.finfo(float).tiny))
        with np.errstate(divide="ignore", invalid="ignore"):  # zero-area rows are masked
            grazing_cos = np.where(degenerate, np.inf, ROUNDING_STEPS * UNIT_ROUNDOFF * l_max / h_min)
        return cls(
            v0=corners[:, 0],
            e1=e1,
            e2=e2,
            normal=np.where(degenerate[:, None], 0.0, cross / safe[:, None]),
            h_min=h_min,
            grazing_cos=grazing_cos,
            degenerate=degenerate,
            scale=float(np.abs(scene.vertices).max()),
        )


def exact_hits(geometry: TriangleGeometry, tri: np.ndarray, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
    """Float64 Möller–Trumbore of ray ``i`` against triangle ``tri[i]``, without the inside test.

    Unlike :func:`kdtrace.oracle.intersect_brute_force` the barycentrics are kept
    when they fall outside the triangle, to measure how far a hit is from an edge.

    Returns
    -------
    dict of (N,) float64
        ``t`` (units of ``|d|``, the ray's distance to the triangle's plane), ``u``,
        ``v``, ``min_bary`` (smallest of ``u, v, 1 - u - v``) and ``cos`` (between
        ray and normal). NaN or inf for zero-area triangles.
    """
    e1, e2, v0 = geometry.e1[tri], geometry.e2[tri], geometry.v0[tri]
    p = np.cross(directions, e2)
    s = origins - v0
    q = np.cross(s, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.einsum("ij,ij->i", e1, p)
        u = np.einsum("ij,ij->i", s, p) * inv
        v = np.einsum("ij,ij->i", directions, q) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        min_bary = np.minimum(np.minimum(u, v), 1.0 - u - v)
    cos = np.einsum("ij,ij->i", directions, geometry.normal[tri]) / np.linalg.norm(directions, axis=1)
    return {"t": t, "u": u, "v": v, "min_bary": min_bary, "cos": cos}


def _reasons(
    geometry: TriangleGeometry, tri: np.ndarray, origins: np.ndarray, directions: np.ndarray, tmax: np.ndarray
) -> dict[str, np.ndarray]:
    """Which explanations apply to ray ``i`` passing near triangle ``tri[i]``.

    Besides the :data:`EXPLANATIONS`, ``"clear"`` marks an unambiguous hit with
    ``tol < t < tmax - tol``, ``"in_range"`` a plane crossing within tolerance
    of ``[0, tmax]`` and ``"in_plane"`` a ray lying in the triangle's plane.
    """
    # Rays parallel to a triangle give inf/NaN plane distances; they fail every test below.
    with np.errstate(invalid="ignore"):
        return _reasons_of(geometry, tri, origins, directions, tmax)


def _reasons_of(
    geometry: TriangleGeometry, tri: np.ndarray, origins: np.ndarray, directions: np.ndarray, tmax: np.ndarray
) -> dict[str, np.ndarray]:
    hit = exact_hits(geometry, tri, origins, directions)
    zero = geometry.degenerate[tri]
    t = np.where(zero, 0.0, hit["t"])
    position = position_tolerance(origins, directions, t, geometry.scale)
    cos = np.maximum(np.abs(hit["cos"]), MIN_COS)
    tol_t = position / cos / np.linalg.norm(directions, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        tol_bary = position / cos / geometry.h_min[tri]
    on_triangle = ~zero & (hit["min_bary"] >= -tol_bary)
    parallel = np.abs(hit["cos"]) <= geometry.grazing_cos[tri]
    # A ray lying in the triangle's plane (e.g. along an edge) has a (near-)zero
    # determinant: its barycentrics are noise, and so is any hit either side reports.
    plane_offset = np.einsum("ij,ij->i", origins - geometry.v0[tri], geometry.normal[tri])
    in_plane = ~zero & parallel & (np.abs(plane_offset) <= position_tolerance(origins, directions, np.zeros(len(tri)), geometry.scale))
    grazing = (on_triangle & parallel) | in_plane
    edge = on_triangle & (hit["min_bary"] <= tol_bary)
    at_tmax = on_triangle & np.isfinite(tmax) & (np.abs(t - tmax) <= tol_t)
    at_tmin = on_triangle & ~grazing & (np.abs(t) <= tol_t)
    clear = on_triangle & ~grazing & ~edge & (t > tol_t) & (t < tmax - tol_t)
    in_range = (t > -tol_t) & (t < tmax + tol_t)
    return {ZERO_AREA: zero, TMIN: at_tmin, TMAX: at_tmax, GRAZING: grazing, EDGE: edge, "clear": clear,
            "in_range": in_range, "in_plane": in_plane}


def _first_label(ray: np.ndarray, reasons: dict[str, np.ndarray], rays: np.ndarray) -> np.ndarray:
    """Label each ray in ``rays`` with the first explanation any of its candidates (``ray``) has."""
    labels = np.full(len(rays), UNEXPLAINED, dtype=object)
    slot = np.searchsorted(rays, ray)
    for name in reversed(EXPLANATIONS):
        applies = np.zeros(len(rays), dtype=bool)
        np.logical_or.at(applies, slot, reasons[name])
        labels[applies] = name
    return labels


@dataclass(frozen=True)
class Comparison:
    """Per-ray outcome of comparing two intersectors.

    Attributes
    ----------
    labels : (N,) object array of str
        One of :data:`LABELS` per ray.
    ours_exact : (N,) bool array
        Disagreements on which our answer is the oracle's and the reference's is not.
    """

    labels: np.ndarray
    ours_exact: np.ndarray

    def counts(self) -> dict[str, int]:
        """Number of rays per label, every label present, and the :data:`OURS_EXACT` count."""
        return {"rays": len(self.labels), **{name: int(np.sum(self.labels == name)) for name in LABELS},
                OURS_EXACT: int(self.ours_exact.sum())}


def _clear_hit_before(scene: Scene, geometry: TriangleGeometry, origins: np.ndarray, directions: np.ndarray,
                      tmax: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """Whether the oracle's nearest hit lies beyond ``t = 0`` and before ``limit`` by more than its tolerance.

    The search starts at the smallest distance tolerance at t = 0 (|cos theta| = 1): a hit on
    the surface a ray starts from would hide any farther one.
    """
    start = t_tolerance(origins, directions, np.zeros(len(origins)), np.ones(len(origins)), geometry.scale)
    t, _, tol = _oracle(scene, geometry, origins, directions, start, tmax)
    return (t - tol > 0.0) & (t + tol < limit)


def _oracle(scene: Scene, geometry: TriangleGeometry, origins: np.ndarray, directions: np.ndarray,
            tmin: float | np.ndarray, tmax: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The watertight oracle's nearest hit ``(t, tri)`` on each ray and its distance tolerance (0 on a miss)."""
    t, tri = nearest_hits_fast(scene.vertices, scene.triangles, origins, directions, tmin, tmax, skip=geometry.degenerate)
    hit = tri >= 0
    tol = np.zeros(len(t))
    if hit.any():
        cos = exact_hits(geometry, tri[hit], origins[hit], directions[hit])["cos"]
        tol[hit] = t_tolerance(origins[hit], directions[hit], t[hit], cos, geometry.scale)
    return t, tri, tol


def _as_tmax(tmax: float | np.ndarray | None, n: int) -> np.ndarray:
    return np.broadcast_to(np.asarray(np.inf if tmax is None else tmax, dtype=np.float64), (n,))


def compare_hits(
    scene: Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    ours: tuple[np.ndarray, ...],
    theirs: tuple[np.ndarray, ...],
    tmax: float | np.ndarray | None = None,
    geometry: TriangleGeometry | None = None,
) -> Comparison:
    """Compare two closest-hit answers on the same rays and label every ray.

    Parameters
    ----------
    scene : Scene
        The geometry both intersectors were built on.
    origins, directions : (N, 3) arrays
        The rays.
    ours, theirs : tuple (t, tri, u, v)
        Answers of ``intersect``: distance in units of ``|d|`` (inf on a miss) and
        triangle index (-1 on a miss); ``u, v`` are not used.
    tmax : float or (N,) array, optional
        The ``tmax`` the rays were traced with.
    geometry : TriangleGeometry, optional
        Precomputed ``TriangleGeometry.of(scene)``.

    Returns
    -------
    Comparison
        :data:`AGREE` or :data:`TIE` for agreeing rays; a disagreement is :data:`WRONG`
        when the oracle's nearest hit (rays traced from ``tmin = 0``) is nearer than
        ours beyond tolerance, else gets the first applicable explanation among the
        triangles either side reported, checked in float64, or :data:`UNEXPLAINED`.
    """
    origins, directions = as_float64_rays(origins, directions)
    n = len(origins)
    geometry = TriangleGeometry.of(scene) if geometry is None else geometry
    tmax = _as_tmax(tmax, n)
    t_o, tri_o = np.asarray(ours[0], dtype=np.float64), np.asarray(ours[1], dtype=np.int64)
    t_t, tri_t = np.asarray(theirs[0], dtype=np.float64), np.asarray(theirs[1], dtype=np.int64)
    if not (t_o.shape == tri_o.shape == t_t.shape == tri_t.shape == (n,)):
        raise ValueError(f"ours and theirs must hold (N,) arrays with N = {n} rays")
    hit_o, hit_t = tri_o >= 0, tri_t >= 0
    both = hit_o & hit_t

    def tolerance(t: np.ndarray, tri: np.ndarray) -> np.ndarray:
        cos = exact_hits(geometry, tri, origins, directions)["cos"]
        return np.where(geometry.degenerate[tri], np.nan, t_tolerance(origins, directions, t, cos, geometry.scale))

    tol = np.fmax(tolerance(np.where(both, t_o, 0.0), np.maximum(tri_o, 0)), tolerance(np.where(both, t_t, 0.0), np.maximum(tri_t, 0)))
    tol = np.where(np.isnan(tol), t_tolerance(origins, directions, np.where(both, t_t, 0.0), np.ones(n), geometry.scale), tol)
    gap = np.subtract(t_o, t_t, out=np.zeros(n), where=both)
    close = both & (np.abs(gap) <= tol)
    labels = np.full(n, UNEXPLAINED, dtype=object)
    labels[(~hit_o & ~hit_t) | (close & (tri_o == tri_t))] = AGREE
    labels[close & (tri_o != tri_t)] = TIE
    rays = np.flatnonzero(labels == UNEXPLAINED)
    ours_exact = np.zeros(n, dtype=bool)
    if len(rays):
        # The oracle judges first: a nearer exact hit makes ours wrong, whatever the geometry.
        o, d, end = origins[rays], directions[rays], tmax[rays]
        t_x, tri_x, tol_x = _oracle(scene, geometry, o, d, 0.0, end)

        def matches(t: np.ndarray, tri: np.ndarray) -> np.ndarray:
            gap = np.subtract(t, t_x, out=np.full(len(t), np.inf), where=(tri >= 0) & (tri_x >= 0))
            return np.where(tri_x >= 0, np.abs(gap) <= tol_x, tri < 0)

        ours_exact[rays] = matches(t_o[rays], tri_o[rays]) & ~matches(t_t[rays], tri_t[rays])
        wrong = _clear_hit_before(scene, geometry, o, d, end, np.minimum(t_o[rays], end))
        labels[rays[wrong]] = WRONG
        rays = rays[~wrong]
    if len(rays):
        ray = np.concatenate([rays[hit_o[rays]], rays[hit_t[rays]]])
        tri = np.concatenate([tri_o[rays][hit_o[rays]], tri_t[rays][hit_t[rays]]])
        order = np.argsort(ray, kind="stable")
        ray, tri = ray[order], tri[order]
        reasons = _reasons(geometry, tri, origins[ray], directions[ray], tmax[ray])
        labels[rays] = _first_label(ray, reasons, rays)
    return Comparison(labels, ours_exact)


def _near_degenerate(
    geometry: TriangleGeometry, origin: np.ndarray, direction: np.ndarray, tmax: float, tol: float
) -> bool:
    """Whether the segment ``o + t d, 0 <= t <= tmax`` passes within ``tol`` of a zero-area triangle's longest edge."""
    index = np.flatnonzero(geometry.degenerate)
    if len(index) == 0:
        return False
    v0, e1, e2 = geometry.v0[index], geometry.e1[index], geometry.e2[index]
    starts = np.stack([v0, v0, v0 + e1], 1)
    edges = np.stack([e1, e2, e2 - e1], 1)
    longest = np.argmax(np.einsum("ijk,ijk->ij", edges, edges), axis=1)
    rows = np.arange(len(index))
    a, edge = starts[rows, longest], edges[rows, longest]
    edge_len2 = np.einsum("ij,ij->i", edge, edge)
    # closest points of the two lines, clamped to the edge, then to the ray's range
    dd = direction @ direction
    de = edge @ direction
    w = origin - a
    denom = dd * edge_len2 - de**2
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 0.0, (dd * np.einsum("ij,ij->i", edge, w) - de * (w @ direction)) / denom, 0.0)
    point = a + np.clip(np.nan_to_num(s), 0.0, 1.0)[:, None] * edge
    t = np.clip((point - origin) @ direction / dd, 0.0, tmax)
    gap = np.linalg.norm(origin + t[:, None] * direction - point, axis=1)
    return bool((gap <= tol).any())


def compare_occlusion(
    scene: Scene,
    origins: np.ndarray,
    directions: np.ndarray,
    tmax: float | np.ndarray,
    ours: np.ndarray,
    theirs: np.ndarray,
    geometry: TriangleGeometry | None = None,
) -> Comparison:
    """Compare two ``occluded`` answers on the same rays and label every ray.

    A disagreement is explained from the float64 view of every triangle along the
    segment: the closest occluder as the brute-force oracle would find it, plus
    every triangle missed or hit only within tolerance. If any triangle is hit
    unambiguously (inside, away from edges, ``tmax``, grazing) or none is near at
    all, one side is simply wrong: :data:`UNEXPLAINED`. Otherwise the label is the
    first explanation any near triangle has. Costs O(T) per disagreeing ray.

    Parameters
    ----------
    scene : Scene
        The geometry.
    origins, directions : (N, 3) arrays
        The shadow rays.
    tmax : float or (N,) array
        Segment length in units of ``|d|``.
    ours, theirs : (N,) bool arrays
        Answers of ``occluded``.
    geometry : TriangleGeometry, optional
        Precomputed ``TriangleGeometry.of(scene)``.

    Returns
    -------
    Comparison
    """
    origins, directions = as_float64_rays(origins, directions)
    n = len(origins)
    geometry = TriangleGeometry.of(scene) if geometry is None else geometry
    tmax = _as_tmax(tmax, n)
    ours, theirs = np.asarray(ours, dtype=bool), np.asarray(theirs, dtype=bool)
    if ours.shape != (n,) or theirs.shape != (n,):
        raise ValueError(f"ours and theirs must have shape ({n},)")
    labels = np.full(n, AGREE, dtype=object)
    ours_exact = np.zeros(n, dtype=bool)
    differ = np.flatnonzero(ours != theirs)
    if len(differ):
        o, d, end = origins[differ], directions[differ], tmax[differ]
        blocked = _oracle(scene, geometry, o, d, 0.0, end)[1] >= 0
        ours_exact[differ] = ours[differ] == blocked
        # A blocker that ours missed, clear of both ends by its own distance tolerance.
        wrong = ~ours[differ] & _clear_hit_before(scene, geometry, o, d, end, end)
        labels[differ[wrong]] = WRONG
        differ = differ[~wrong]
    solid = np.flatnonzero(~geometry.degenerate)
    for i in differ:
        o = np.broadcast_to(origins[i], (len(solid), 3))
        d = np.broadcast_to(directions[i], (len(solid), 3))
        reasons = _reasons(geometry, solid, o, d, np.full(len(solid), tmax[i]))
        # A ray lying in a triangle's plane has no defined plane distance (NaN): near wherever it is.
        near = (reasons["in_range"] | reasons["in_plane"]) & (reasons[TMIN] | reasons[TMAX] | reasons[GRAZING] | reasons[EDGE])
        far_end = tmax[i] if np.isfinite(tmax[i]) else 0.0
        position = position_tolerance(origins[i : i + 1], directions[i : i + 1], far_end, geometry.scale)[0]
        if reasons["clear"].any():
            labels[i] = UNEXPLAINED
        elif _near_degenerate(geometry, origins[i], directions[i], tmax[i], position):
            labels[i] = ZERO_AREA
        else:
            labels[i] = next((name for name in EXPLANATIONS[1:] if reasons[name][near].any()), UNEXPLAINED)
    return Comparison(labels, ours_exact)


# ------------------------------------------------------------------ whole-scene check
def _ray_sets(scene: Scene, rays_per_kind: int, seed: int) -> dict[str, tuple[np.ndarray, ...]]:
    """The five ray kinds (``primary`` only when the scene has a camera), with distinct seeds."""
    from kdtrace import rays

    seeds = np.random.SeedSequence(seed).generate_state(len(RAY_KINDS))
    makers = {
        "primary": rays.primary_rays,
        "random": rays.random_rays,
        "vertex": rays.vertex_rays,
        "edge": rays.edge_rays,
        "shadow": rays.shadow_rays,
    }
    return {
        kind: makers[kind](scene, rays_per_kind, int(kind_seed))
        for kind, kind_seed in zip(RAY_KINDS, seeds, strict=True)
        if kind != "primary" or scene.cameras
    }


def check_scene(
    scene: Scene, intersectors: dict[str, object], rays_per_kind: int, seed: int, progress: bool = True,
    embree: object | None = None,
) -> pd.DataFrame:
    """Compare each intersector with Embree on every ray kind of :data:`RAY_KINDS`.

    Parameters
    ----------
    scene : Scene
        The scene (``primary`` rays are skipped when it has no camera).
    intersectors : dict of name -> object
        Objects with ``intersect(origins, directions, tmin, tmax)`` and
        ``occluded(origins, directions, tmax)``, e.g. our KD-trees.
    rays_per_kind : int
        Rays generated per kind.
    seed : int
        Seed of the ray generators.
    progress : bool
        Show a tqdm bar over the stages (ray generation, Embree, each intersector).
    embree : references.embree.EmbreeIntersector, optional
        Embree's intersector of ``scene`` when the caller has built one already (a second
        BVH of a large scene costs its build time and memory); built here otherwise.

    Returns
    -------
    pandas.DataFrame
        One row per (intersector, kind): ``rays``, ``agree``, ``ties``, one column per
        explanation and ``unexplained``.
    """
    from tqdm import tqdm

    from references.embree import EmbreeIntersector

    if not intersectors:
        raise ValueError("no intersector to compare with Embree")
    stages = tqdm(total=2 + len(RAY_KINDS) * (1 + len(intersectors)), disable=not progress, unit="stage")
    stages.set_description("rays")
    ray_sets = _ray_sets(scene, rays_per_kind, seed)
    geometry = TriangleGeometry.of(scene)
    stages.update()
    stages.set_description("embree build")
    embree = EmbreeIntersector(scene) if embree is None else embree
    stages.update()
    rows = []
    for kind, ray_set in ray_sets.items():
        stages.set_description(f"{kind}: embree")
        if RAY_KINDS[kind] == "occluded":
            reference = embree.occluded(*ray_set)
        else:
            reference = embree.intersect(*ray_set)
        stages.update()
        for name, intersector in intersectors.items():
            stages.set_description(f"{kind}: {name}")
            if RAY_KINDS[kind] == "occluded":
                answer = intersector.occluded(*ray_set)
                comparison = compare_occlusion(scene, *ray_set, answer, reference, geometry=geometry)
            else:
                answer = intersector.intersect(*ray_set)
                comparison = compare_hits(scene, *ray_set, answer, reference, geometry=geometry)
            counts = comparison.counts()
            rows.append({"intersector": name, "kind": kind, "rays": counts.pop("rays"),
                         "agree": counts.pop(AGREE), "ties": counts.pop(TIE), **counts})
            stages.update()
    stages.close()
    return pd.DataFrame(rows)


def format_table(df: pd.DataFrame) -> str:
    """The agreement table as GitHub markdown."""
    from tabulate import tabulate

    return tabulate(df, headers="keys", tablefmt="github", showindex=False)


def main_check_embree(
    scene_name: str, rays_per_kind: int, seed: int, accelerators: tuple[str, ...] = OUR_ACCELERATORS
) -> tuple[pd.DataFrame, str]:
    """Load a scene, build the accelerators named and compare them with Embree.

    Parameters
    ----------
    accelerators : tuple of str
        Plug-in specs (:func:`kdtrace.plugins.load_accelerator`): short names such as
        our KD-trees ``local`` and ``naive``, or ``package.module:factory``.

    Returns
    -------
    df : pandas.DataFrame
        The table of :func:`check_scene`.
    text : str
        A heading line and the markdown table, for ``kdtrace check-embree``.
    """
    from kdtrace.scenes import load_scene

    scene = load_scene(scene_name)
    trees = {spec: load_accelerator(spec, scene) for spec in accelerators}
    df = check_scene(scene, trees, rays_per_kind, seed)
    heading = (f"Agreement with Embree on {scene.name} ({len(scene.triangles)} triangles), "
               f"{rays_per_kind} rays per kind, seed {seed}")
    return df, f"{heading}\n\n{format_table(df)}\n"
