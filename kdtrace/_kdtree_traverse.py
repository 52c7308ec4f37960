"""numba kernels for ray queries on the KD-trees (paper Algorithms 2 and 4).

One traversal serves both variants: interior nodes of the naive tree hold no
triangles, so the local-branch test (Algorithm 4) costs a single count check there.
Traversal and intersection run in float64 on float32 scene data, front to back with
an explicit stack; a subtree whose entry distance lies beyond the closest hit so far
is skipped (the pruning of Algorithm 4, which is also valid for the naive tree).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from kdtrace._kdtree_build import LEAF

STACK_SIZE = 96


@njit(cache=True, inline="always")
def intersect_triangle(tri, corners, ox, oy, oz, dx, dy, dz, tmin, tmax):
    """Möller–Trumbore, double-sided, edges inclusive; returns (t, u, v), t=inf on a miss.

    ``corners[tri]`` holds the triangle's three float32 vertices; the edges are formed
    in float64, where the difference of two float32 numbers is exact.
    """
    v0x = np.float64(corners[tri, 0])
    v0y = np.float64(corners[tri, 1])
    v0z = np.float64(corners[tri, 2])
    e1x = corners[tri, 3] - v0x
    e1y = corners[tri, 4] - v0y
    e1z = corners[tri, 5] - v0z
    e2x = corners[tri, 6] - v0x
    e2y = corners[tri, 7] - v0y
    e2z = corners[tri, 8] - v0z
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    # Compare unnormalised barycentrics against |det|: one division, only for hits.
    if det > 0.0:
        sign = 1.0
    elif det < 0.0:
        sign = -1.0
    else:
        return np.inf, 0.0, 0.0
    abs_det = det * sign
    sx = ox - v0x
    sy = oy - v0y
    sz = oz - v0z
    u_scaled = (sx * px + sy * py + sz * pz) * sign
    if u_scaled < 0.0 or u_scaled > abs_det:
        return np.inf, 0.0, 0.0
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    v_scaled = (dx * qx + dy * qy + dz * qz) * sign
    if v_scaled < 0.0 or u_scaled + v_scaled > abs_det:
        return np.inf, 0.0, 0.0
    t_scaled = (e2x * qx + e2y * qy + e2z * qz) * sign
    if t_scaled <= tmin * abs_det or t_scaled >= tmax * abs_det:
        return np.inf, 0.0, 0.0
    inv = 1.0 / abs_det
    return t_scaled * inv, u_scaled * inv, v_scaled * inv


@njit(cache=True, inline="always")
def clip_to_box(box, ox, oy, oz, dx, dy, dz, tmin, tmax):
    """Slab test against box = (xmin, ymin, zmin, xmax, ymax, zmax).

    Zero direction components are handled explicitly (no 0 * inf), so axis-parallel
    rays are exact. Returns (t_enter, t_exit); t_enter > t_exit means a miss.
    """
    t0 = tmin
    t1 = tmax
    o = (ox, oy, oz)
    d = (dx, dy, dz)
    for k in range(3):
        lo = box[k]
        hi = box[k + 3]
        if d[k] == 0.0:
            if o[k] < lo or o[k] > hi:
                return 1.0, 0.0
            continue
        inv = 1.0 / d[k]
        ta = (lo - o[k]) * inv
        tb = (hi - o[k]) * inv
        if ta > tb:
            ta, tb = tb, ta
        if ta > t0:
            t0 = ta
        if tb < t1:
            t1 = tb
        if t0 > t1:
            return 1.0, 0.0
    return t0, t1


@njit(cache=True, inline="always")  # inlined: no per-ray call, no reference counting of the arrays
def trace_ray(
    nodes, splits, refs, box, corners,
    ox, oy, oz, dx, dy, dz, tmin, tmax, any_hit, st_node, st_ent, st_ext,
):
    """Closest (or any) hit of one ray; returns (t, triangle, u, v, nodes_visited, tests).

    ``nodes`` is the packed (N, 4) int32 node array ``[meta, split bits, start, count]``
    and ``splits`` its float32 view (column 1 is the split position), so one node is
    16 contiguous bytes. ``st_*`` are caller-owned stack buffers (no allocation per ray).
    """
    best_t = tmax
    best_tri = -1
    best_u = 0.0
    best_v = 0.0
    visited = 0
    tests = 0
    ent, ext = clip_to_box(box, ox, oy, oz, dx, dy, dz, tmin, tmax)
    if ent > ext:
        return np.inf, -1, 0.0, 0.0, visited, tests
    o = (ox, oy, oz)
    d = (dx, dy, dz)
    # Reciprocal directions: a multiply per node instead of a divide (inf where d = 0,
    # a case handled before it is used).
    inv_d = (1.0 / dx if dx != 0.0 else np.inf, 1.0 / dy if dy != 0.0 else np.inf, 1.0 / dz if dz != 0.0 else np.inf)
    node = 0
    sp = 0
    while True:
        visited += 1
        count = nodes[node, 3]
        if count > 0:
            first = nodes[node, 2]
            for k in range(first, first + count):
                tri = refs[k]
                tests += 1
                t, u, v = intersect_triangle(tri, corners, ox, oy, oz, dx, dy, dz, tmin, best_t)
                if t < best_t:
                    best_t = t
                    best_tri = tri
                    best_u = u
                    best_v = v
                    if any_hit:
                        return best_t, best_tri, best_u, best_v, visited, tests
        meta = nodes[node, 0]
        if meta != LEAF:
            axis = meta & 3
            left = meta >> 2
            split = splits[node, 1]
            if o[axis] < split or (o[axis] == split and d[axis] <= 0.0):
                near = left
                far = left + 1
            else:
                near = left + 1
                far = left
            if d[axis] == 0.0 or o[axis] == split:
                # Parallel to the plane, or starting on it heading into `near`: one child.
                # (Also avoids 0 * inf = NaN when 1/d overflows for a subnormal d.)
                node = near
                continue
            t_plane = (split - o[axis]) * inv_d[axis]
            if t_plane > ext or t_plane <= 0.0 or t_plane > best_t:
                node = near
            elif t_plane < ent:
                node = far
            else:
                st_node[sp] = far
                st_ent[sp] = t_plane
                st_ext[sp] = ext
                sp += 1
                node = near
                ext = t_plane
            continue
        # Leaf done: resume with the next subtree unless the closest hit precedes it.
        found = False
        while sp > 0:
            sp -= 1
            if st_ent[sp] <= best_t:
                node = st_node[sp]
                ent = st_ent[sp]
                ext = st_ext[sp]
                found = True
                break
            sp = 0  # entries below are even farther: stop
        if not found:
            break
    if best_tri < 0:
        return np.inf, -1, 0.0, 0.0, visited, tests
    return best_t, best_tri, best_u, best_v, visited, tests


@njit(cache=True, parallel=True)
def trace_batch(
    nodes, splits, refs, box, corners,
    origins, directions, tmin, tmax, any_hit, n_chunks,
    out_t, out_tri, out_u, out_v, out_visited, out_tests,
):
    """Trace every ray, in parallel over chunks of rays (one stack per chunk)."""
    n = origins.shape[0]
    chunk = (n + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        st_node = np.empty(STACK_SIZE, np.int32)
        st_ent = np.empty(STACK_SIZE, np.float64)
        st_ext = np.empty(STACK_SIZE, np.float64)
        for i in range(c * chunk, min(n, (c + 1) * chunk)):
            t, tri, u, v, visited, tests = trace_ray(
                nodes, splits, refs, box, corners,
                origins[i, 0], origins[i, 1], origins[i, 2],
                directions[i, 0], directions[i, 1], directions[i, 2],
                tmin[i], tmax[i], any_hit, st_node, st_ent, st_ext,
            )
            out_t[i] = t
            out_tri[i] = tri
            out_u[i] = u
            out_v[i] = v
            out_visited[i] = visited
            out_tests[i] = tests
