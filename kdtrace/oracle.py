"""Brute-force float64 ray-triangle intersection: the slow, obvious oracle for tests.

Every ray is tested against every triangle with the Möller–Trumbore algorithm in
float64 (vectorised over triangles with NumPy, looping over rays in chunks). It is
the reference the KD-trees are compared with; never use it on a hot path.
"""

from __future__ import annotations

import numpy as np


def as_float64_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and directions as float64 arrays, both of shape (N, 3), or a ValueError."""
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
        raise ValueError(f"origins and directions must both have shape (N, 3), got {origins.shape} and {directions.shape}")
    return origins, directions


def intersect_brute_force(
    vertices: np.ndarray,
    triangles: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    tmin: float = 0.0,
    tmax: float | np.ndarray = np.inf,
    skip: np.ndarray | None = None,
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

    Returns
    -------
    t : (N,) float64
        Distance along the ray, ``inf`` on a miss.
    tri : (N,) int64
        Triangle index, -1 on a miss.
    u, v : (N,) float64
        Barycentric coordinates of the hit (weights of vertices 1 and 2).
    """
    origins, directions = as_float64_rays(origins, directions)
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)]
    if skip is not None:
        keep = np.flatnonzero(~np.asarray(skip, dtype=bool))
    else:
        keep = np.arange(len(corners))
    corners = corners[keep]
    v0 = corners[:, 0]
    e1 = corners[:, 1] - v0
    e2 = corners[:, 2] - v0
    n = len(origins)
    tmax = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (n,))
    t_out = np.full(n, np.inf)
    tri_out = np.full(n, -1, dtype=np.int64)
    u_out = np.zeros(n)
    v_out = np.zeros(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(n):
            o, d = origins[i], directions[i]
            p = np.cross(d, e2)
            det = np.einsum("ij,ij->i", e1, p)
            inv = 1.0 / det
            s = o - v0
            u = np.einsum("ij,ij->i", s, p) * inv
            q = np.cross(s, e1)
            v = (q @ d) * inv
            t = np.einsum("ij,ij->i", e2, q) * inv
            ok = (det != 0.0) & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0) & (t > tmin) & (t < tmax[i])
            if ok.any():
                candidates = np.flatnonzero(ok)
                best = candidates[np.argmin(t[candidates])]
                t_out[i] = t[best]
                tri_out[i] = keep[best]
                u_out[i] = u[best]
                v_out[i] = v[best]
    return t_out, tri_out, u_out, v_out
