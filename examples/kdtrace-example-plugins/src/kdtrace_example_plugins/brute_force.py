"""A brute-force accelerator: every ray against every triangle, in float64 NumPy.

The simplest correct answer to kdtrace's ``Accelerator`` interface, and a template
for a real one: ``make(scene)`` returns an object with ``intersect``, ``occluded``
and ``stats``. It does ``rays x triangles`` work, so keep it to small scenes.
"""

from __future__ import annotations

import time

import numpy as np

#: Ray-triangle pairs tested per NumPy pass (bounds the temporary arrays to ~25 MB each).
PAIRS_PER_PASS = 1 << 20


class BruteForce:
    """Möller–Trumbore in float64 of each ray against all triangles, edges inclusive, double-sided.

    Parameters
    ----------
    vertices : (V, 3) float array
        Vertex positions (scene units).
    triangles : (T, 3) int array
        Vertex indices; hits report rows of this array.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        start = time.perf_counter()
        corners = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)]
        self.v0 = corners[:, 0]
        self.e1 = corners[:, 1] - self.v0
        self.e2 = corners[:, 2] - self.v0
        self.stats = {"references": len(corners), "bytes": 3 * self.v0.nbytes, "nodes": 0,
                      "build_seconds": time.perf_counter() - start}

    def _pass(self, o: np.ndarray, d: np.ndarray, tmin: np.ndarray, tmax: np.ndarray) -> tuple[np.ndarray, ...]:
        """Nearest hit of a few rays: (t, tri, u, v) with ``tmin < t < tmax``, inf / -1 / 0 on a miss."""
        p = np.cross(d[:, None], self.e2[None])
        det = np.einsum("tk,rtk->rt", self.e1, p)
        s = o[:, None] - self.v0[None]
        q = np.cross(s, self.e1[None])
        with np.errstate(divide="ignore", invalid="ignore"):  # parallel rays: det = 0, excluded below
            inv = 1.0 / det
            u = np.einsum("rtk,rtk->rt", s, p) * inv
            v = np.einsum("rk,rtk->rt", d, q) * inv
            t = np.einsum("tk,rtk->rt", self.e2, q) * inv
            inside = (det != 0.0) & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0) & (t > tmin[:, None]) & (t < tmax[:, None])
        t = np.where(inside, t, np.inf)
        best = np.argmin(t, axis=1)
        rows = np.arange(len(o))
        t_best = t[rows, best]
        hit = np.isfinite(t_best)
        tri = np.where(hit, best, -1).astype(np.int32)
        return t_best, tri, np.where(hit, u[rows, best], 0.0), np.where(hit, v[rows, best], 0.0)

    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf):
        """Closest hit of every ray ``o + t d`` with ``tmin < t < tmax``.

        Parameters
        ----------
        origins, directions : (N, 3) float arrays
            Rays (scene units; directions need not be unit).
        tmin, tmax : float or (N,) array
            Accepted range of ``t``, in units of ``|d|``.

        Returns
        -------
        t : (N,) float64, inf on a miss
        tri : (N,) int32, row of the triangle array, -1 on a miss
        u, v : (N,) float64, barycentric weights of vertices 1 and 2 (0 on a miss)
        """
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        n = len(o)
        tmin = np.broadcast_to(np.asarray(tmin, dtype=np.float64), (n,))
        tmax = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (n,))
        step = max(1, PAIRS_PER_PASS // max(1, len(self.v0)))
        passes = [self._pass(o[i:i + step], d[i:i + step], tmin[i:i + step], tmax[i:i + step]) for i in range(0, n, step)]
        if not passes:
            return np.empty(0), np.empty(0, np.int32), np.empty(0), np.empty(0)
        t, tri, u, v = (np.concatenate(part) for part in zip(*passes, strict=True))
        return t, tri, u, v

    def occluded(self, origins, directions, tmax):
        """(N,) bool: whether any triangle is hit with ``0 < t < tmax`` (units of ``|d|``)."""
        return self.intersect(origins, directions, 0.0, tmax)[1] >= 0


def make(scene) -> BruteForce:
    """kdtrace accelerator factory: the brute-force intersector of a ``kdtrace.scene.Scene``."""
    return BruteForce(scene.vertices, scene.triangles)
