"""numba brute force of the float64 oracle: every ray against every triangle.

The same watertight test as :func:`kdtrace.oracle.watertight` (Woop, Benthin, Wald
2013), written as a branch-free loop over triangles that LLVM vectorises, so that
:mod:`references.agreement` can ask the oracle about hundreds of thousands of
disagreeing rays on scenes of 10^5 triangles. No acceleration structure: nothing a
traversal bug could share. ``tests/test_oracle.py`` checks it against the NumPy oracle.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


# error_model="numpy": a division by a zero determinant gives inf/NaN (masked) instead of
# a Python exception check, which would keep LLVM from vectorising the loop.
@njit(cache=True, error_model="numpy")
def _ray_distances(corners, start, stop, ox, oy, oz, dx, dy, dz, tmin, tmax, out):
    """``out[k - start]``: distance of the watertight hit on triangle k in (tmin, tmax), else inf.

    ``corners`` is (3 vertices, 3 axes, T) float64, so each vertex coordinate is one
    contiguous row.
    """
    ad = (abs(dx), abs(dy), abs(dz))
    kz = 0 if ad[0] >= ad[1] and ad[0] >= ad[2] else (1 if ad[1] >= ad[2] else 2)
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    o = (ox, oy, oz)
    d = (dx, dy, dz)
    sz = 1.0 / d[kz]
    sx = d[kx] * sz
    sy = d[ky] * sz
    okx, oky, okz = o[kx], o[ky], o[kz]
    ax_, ay_, az_ = corners[0, kx], corners[0, ky], corners[0, kz]
    bx_, by_, bz_ = corners[1, kx], corners[1, ky], corners[1, kz]
    cx_, cy_, cz_ = corners[2, kx], corners[2, ky], corners[2, kz]
    for k in range(start, stop):
        az = az_[k] - okz
        bz = bz_[k] - okz
        cz = cz_[k] - okz
        ax = (ax_[k] - okx) - sx * az
        ay = (ay_[k] - oky) - sy * az
        bx = (bx_[k] - okx) - sx * bz
        by = (by_[k] - oky) - sy * bz
        cx = (cx_[k] - okx) - sx * cz
        cy = (cy_[k] - oky) - sy * cz
        w0 = cx * by - cy * bx
        w1 = ax * cy - ay * cx
        w2 = bx * ay - by * ax
        det = w0 + w1 + w2
        # Bitwise & and |, not `and`/`or`: no branches, so the loop vectorises.
        inside = ~(((w0 < 0.0) | (w1 < 0.0) | (w2 < 0.0)) & ((w0 > 0.0) | (w1 > 0.0) | (w2 > 0.0)))
        t = (w0 * az + w1 * bz + w2 * cz) * sz / det
        out[k - start] = t if inside & (det != 0.0) & (t > tmin) & (t < tmax) else np.inf


#: Triangles per block: a block's 9 coordinate rows (72 bytes a triangle) stay in L2
#: while every ray of a chunk is tested against it.
BLOCK = 4096
#: Rays per chunk (one parallel task).
RAYS_PER_CHUNK = 16


@njit(cache=True, parallel=True, error_model="numpy")
def nearest_hits(corners, origins, directions, tmin, tmax, out_t, out_tri):
    """Nearest watertight hit of every ray (t = inf, tri = -1 on a miss), parallel over rays."""
    n = origins.shape[0]
    n_triangles = corners.shape[2]
    n_chunks = (n + RAYS_PER_CHUNK - 1) // RAYS_PER_CHUNK
    for c in prange(n_chunks):
        distances = np.empty(BLOCK)
        first = c * RAYS_PER_CHUNK
        last = min(n, first + RAYS_PER_CHUNK)
        for i in range(first, last):
            out_t[i] = np.inf
            out_tri[i] = -1
        for start in range(0, n_triangles, BLOCK):
            stop = min(n_triangles, start + BLOCK)
            for i in range(first, last):
                _ray_distances(corners, start, stop, origins[i, 0], origins[i, 1], origins[i, 2],
                               directions[i, 0], directions[i, 1], directions[i, 2], tmin[i], tmax[i], distances)
                # Strictly smaller: the lowest index wins among equal distances, as np.argmin.
                best_t = out_t[i]
                best_k = -1
                for k in range(stop - start):
                    if distances[k] < best_t:
                        best_t = distances[k]
                        best_k = k
                if best_k >= 0:
                    out_t[i] = best_t
                    out_tri[i] = start + best_k
