"""Brute-force float64 ray-triangle intersection: the slow, obvious oracle for tests.

Every ray is tested against every triangle in float64 (vectorised over triangles with
NumPy, one ray at a time), with the watertight test of Woop, Benthin and Wald (2013)
or with Möller–Trumbore. It is the reference the KD-trees are compared with, and the
judge of :mod:`references.agreement`; never use it on a hot path.
"""

from __future__ import annotations

import numpy as np

from kdtrace.config import TRIANGLE_TESTS


def as_float64_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and directions as float64 arrays, both of shape (N, 3), or a ValueError."""
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
        raise ValueError(f"origins and directions must both have shape (N, 3), got {origins.shape} and {directions.shape}")
    return origins, directions


def _kept_corners(vertices: np.ndarray, triangles: np.ndarray, skip: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(T', 3, 3) float64 corners of the triangles not skipped, and their indices into ``triangles``."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)]
    keep = np.arange(len(corners)) if skip is None else np.flatnonzero(~np.asarray(skip, dtype=bool))
    return corners[keep], keep


def moller_trumbore(corners: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, ...]:
    """One ray against every triangle: (t, u, v, inside), edges inclusive, double-sided.

    ``corners`` is (T, 3, 3) float64; ``t`` is in units of ``|d|`` (NaN or inf where
    the ray is parallel to a triangle, which ``inside`` excludes).
    """
    v0 = corners[:, 0]
    e1 = corners[:, 1] - v0
    e2 = corners[:, 2] - v0
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    inv = 1.0 / det
    s = o - v0
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    inside = (det != 0.0) & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0)
    return t, u, v, inside


def watertight(corners: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, ...]:
    """One ray against every triangle with the watertight test: (t, u, v, inside).

    Woop, Benthin and Wald (2013): translate the vertices to the ray's origin, permute
    the axes so the largest direction component is z, shear the direction onto +z and
    decide the hit by the signs of three 2D edge functions. Edges inclusive (a zero
    edge function is inside), double-sided. ``corners`` is (T, 3, 3) float64.
    """
    kz = int(np.argmax(np.abs(d)))  # the first of equal maxima, as the traversal kernel picks
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    sz = 1.0 / d[kz]
    sx = d[kx] * sz
    sy = d[ky] * sz
    rel = corners - o  # (T, vertex, axis)
    z = rel[:, :, kz]
    x = rel[:, :, kx] - sx * z
    y = rel[:, :, ky] - sy * z
    a, b, c = (0, 1, 2)
    # w[k] is the edge function of the edge opposite vertex k, its barycentric weight.
    w0 = x[:, c] * y[:, b] - y[:, c] * x[:, b]
    w1 = x[:, a] * y[:, c] - y[:, a] * x[:, c]
    w2 = x[:, b] * y[:, a] - y[:, b] * x[:, a]
    det = w0 + w1 + w2
    mixed = ((w0 < 0.0) | (w1 < 0.0) | (w2 < 0.0)) & ((w0 > 0.0) | (w1 > 0.0) | (w2 > 0.0))
    inside = ~mixed & (det != 0.0)
    t = (w0 * z[:, a] + w1 * z[:, b] + w2 * z[:, c]) * sz / det
    return t, w1 / det, w2 / det, inside


def intersect_brute_force(
    vertices: np.ndarray,
    triangles: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: float = 0.0,
    tmax: float | np.ndarray = np.inf,
    skip: np.ndarray | None = None,
    triangle_test: str = "watertight",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closest hit of every ray against every triangle, in float64.

    Parameters
    ----------
    vertices : (V, 3) array
        Vertex positions.
    triangles : (T, 3) int array
        Vertex indices.
    origins, directions : (N, 3) arrays
        Rays ``o + t d``; directions need not be normalised (t is in units of |d|).
    tmin, tmax : float or (N,) array
        Accepted range of t (hits with ``tmin < t < tmax`` count).
    skip : (T,) bool array, optional
        Triangles to ignore (e.g. zero-area ones, as the trees do).
    triangle_test : {"watertight", "moller-trumbore"}
        The float64 ray-triangle test (see :func:`watertight`, :func:`moller_trumbore`).

    Returns
    -------
    t : (N,) float64
        Distance along the ray, ``inf`` on a miss.
    tri : (N,) int64
        Triangle index, -1 on a miss.
    u, v : (N,) float64
        Barycentric coordinates of the hit (weights of vertices 1 and 2).
    """
    if triangle_test not in TRIANGLE_TESTS:
        raise ValueError(f"unknown triangle test {triangle_test!r}; choose one of {TRIANGLE_TESTS}")
    test = watertight if triangle_test == "watertight" else moller_trumbore
    origins, directions = as_float64_rays(origins, directions)
    corners, keep = _kept_corners(vertices, triangles, skip)
    n = len(origins)
    tmax = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (n,))
    t_out = np.full(n, np.inf)
    tri_out = np.full(n, -1, dtype=np.int64)
    u_out = np.zeros(n)
    v_out = np.zeros(n)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for i in range(n):
            t, u, v, inside = test(corners, origins[i], directions[i])
            ok = inside & (t > tmin) & (t < tmax[i])
            if ok.any():
                candidates = np.flatnonzero(ok)
                best = candidates[np.argmin(t[candidates])]
                t_out[i] = t[best]
                tri_out[i] = keep[best]
                u_out[i] = u[best]
                v_out[i] = v[best]
    return t_out, tri_out, u_out, v_out


def nearest_hits_fast(
    vertices: np.ndarray,
    triangles: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: float | np.ndarray = 0.0,
    tmax: float | np.ndarray = np.inf,
    skip: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The watertight oracle's ``(t, tri)`` as :func:`intersect_brute_force`, compiled.

    Still every ray against every triangle (``kdtrace._oracle_kernels``), only
    vectorised and parallel; :func:`intersect_brute_force` is its reference. Used by
    :mod:`references.agreement` to judge disagreements on whole scenes.
    """
    from kdtrace import _oracle_kernels

    origins, directions = as_float64_rays(origins, directions)
    n = len(origins)
    corners, keep = _kept_corners(vertices, triangles, skip)
    t = np.full(n, np.inf)
    tri = np.full(n, -1, dtype=np.int64)
    if n == 0 or len(keep) == 0:
        return t, tri
    soa = np.ascontiguousarray(corners.transpose(1, 2, 0))  # (vertex, axis, triangle)
    # writable copies: a read-only array would be a second compiled signature of the kernel
    tmin = np.array(np.broadcast_to(np.asarray(tmin, dtype=np.float64), (n,)), order="C")
    tmax = np.array(np.broadcast_to(np.asarray(tmax, dtype=np.float64), (n,)), order="C")
    _oracle_kernels.nearest_hits(soa, origins, directions, tmin, tmax, t, tri)
    hit = tri >= 0
    tri[hit] = keep[tri[hit]]
    return t, tri
