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
def intersect_triangle(tri, v0, e1, e2, ox, oy, oz, dx, dy, dz, tmin, tmax):
    """Möller–Trumbore, double-sided, edges inclusive; returns (t, u, v), t=inf on a miss."""
    e1x = e1[tri, 0]
    e1y = e1[tri, 1]
    e1z = e1[tri, 2]
    e2x = e2[tri, 0]
    e2y = e2[tri, 1]
    e2z = e2[tri, 2]
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return np.inf, 0.0, 0.0
    inv = 1.0 / det
    sx = ox - v0[tri, 0]
    sy = oy - v0[tri, 1]
    sz = oz - v0[tri, 2]
    u = (sx * px + sy * py + sz * pz) * inv
    if u < 0.0 or u > 1.0:
        return np.inf, 0.0, 0.0
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return np.inf, 0.0, 0.0
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    if t <= tmin or t >= tmax:
        return np.inf, 0.0, 0.0
    return t, u, v


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


@njit(cache=True)
def trace_ray(
    node_meta, node_split, node_start, node_count, refs, box, v0, e1, e2,
    ox, oy, oz, dx, dy, dz, tmin, tmax, any_hit, st_node, st_ent, st_ext,
):
    """Closest (or any) hit of one ray; returns (t, triangle, u, v, nodes_visited, tests).

    ``st_*`` are caller-owned stack buffers (no allocation per ray).
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
    node = 0
    sp = 0
    while True:
        visited += 1
        count = node_count[node]
        if count > 0:
            first = node_start[node]
            for k in range(first, first + count):
                tri = refs[k]
                tests += 1
                t, u, v = intersect_triangle(tri, v0, e1, e2, ox, oy, oz, dx, dy, dz, tmin, best_t)
                if t < best_t:
                    best_t = t
                    best_tri = tri
                    best_u = u
                    best_v = v
                    if any_hit:
                        return best_t, best_tri, best_u, best_v, visited, tests
        meta = node_meta[node]
        if meta != LEAF:
            axis = meta & 3
            left = meta >> 2
            split = node_split[node]
            if o[axis] < split or (o[axis] == split and d[axis] <= 0.0):
                near = left
                far = left + 1
            else:
                near = left + 1
                far = left
            if d[axis] == 0.0:
                node = near
                continue
            t_plane = (split - o[axis]) / d[axis]
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
    node_meta, node_split, node_start, node_count, refs, box, v0, e1, e2,
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
                node_meta, node_split, node_start, node_count, refs, box, v0, e1, e2,
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
