"""numba kernels that build the SAH KD-tree (paper Algorithms 1 and 3).

Pure functions over flat arrays; validation, caching and statistics live in
``kdtrace.kdtree``. Node layout (both variants, 16 bytes per node):

``node_meta``  int32  ``(left_child << 2) | axis`` for an interior node, ``LEAF`` (3) for a leaf;
                      the right child is ``left_child + 1``.
``node_split`` float32 split-plane position (interior nodes).
``node_start`` int32  first entry of this node's triangles in ``refs``.
``node_count`` int32  number of triangles held by the node (leaf triangles; for the
                      local-branch tree also the pulled-up triangles of interior nodes).
"""

from __future__ import annotations

import numpy as np
from numba import njit

LEAF = 3


@njit(cache=True)
def _surface_area(bmin, bmax):
    dx = bmax[0] - bmin[0]
    dy = bmax[1] - bmin[1]
    dz = bmax[2] - bmin[2]
    return 2.0 * (dx * dy + dy * dz + dz * dx)


@njit(cache=True)
def _clip_polygon_axis(src, n_src, dst, axis, plane, keep_above):
    """Sutherland–Hodgman against one axis-aligned plane; returns the new vertex count."""
    n_dst = 0
    for i in range(n_src):
        j = (i + 1) % n_src
        a = src[i, axis]
        b = src[j, axis]
        a_in = a >= plane if keep_above else a <= plane
        b_in = b >= plane if keep_above else b <= plane
        if a_in:
            for k in range(3):
                dst[n_dst, k] = src[i, k]
            n_dst += 1
        if a_in != b_in:
            s = (plane - a) / (b - a)
            for k in range(3):
                dst[n_dst, k] = src[i, k] + s * (src[j, k] - src[i, k])
            dst[n_dst, axis] = plane  # exactly on the plane, whatever the rounding
            n_dst += 1
    return n_dst


@njit(cache=True)
def clipped_bounds(v0, v1, v2, bmin, bmax, poly_a, poly_b, out_min, out_max):
    """Bounds of triangle ∩ box (perfect splits); False if they do not meet.

    The bounds are never larger than the triangle's own bounds nor the box, so a
    triangle lying in a plane keeps zero thickness along that axis.
    """
    inside = True
    for k in range(3):
        lo = min(v0[k], v1[k], v2[k])
        hi = max(v0[k], v1[k], v2[k])
        if hi < bmin[k] or lo > bmax[k]:
            return False
        out_min[k] = lo
        out_max[k] = hi
        if lo < bmin[k] or hi > bmax[k]:
            inside = False
    if inside:
        return True
    for k in range(3):
        poly_a[0, k] = v0[k]
        poly_a[1, k] = v1[k]
        poly_a[2, k] = v2[k]
    n = 3
    for axis in range(3):
        n = _clip_polygon_axis(poly_a, n, poly_b, axis, bmin[axis], True)
        if n == 0:
            return False
        n = _clip_polygon_axis(poly_b, n, poly_a, axis, bmax[axis], False)
        if n == 0:
            return False
    for k in range(3):
        lo = np.inf
        hi = -np.inf
        for i in range(n):
            lo = min(lo, poly_a[i, k])
            hi = max(hi, poly_a[i, k])
        # Never shrink below the box or grow beyond the triangle: keeps the result conservative.
        out_min[k] = max(out_min[k], max(lo, bmin[k]))
        out_max[k] = min(out_max[k], min(hi, bmax[k]))
        if out_min[k] > out_max[k]:
            return False
    return True


@njit(cache=True)
def _best_split_on_axis(lo, hi, planar, n, bmin, bmax, axis, area, k_t, k_i, empty_bonus):
    """Sweep the sorted triangle bounds along one axis; returns (cost, position)."""
    best_cost = np.inf
    best_pos = 0.0
    n_planar = planar.shape[0]
    i = 0  # lo[:i] < p
    j = 0  # hi[:j] <= p
    q = 0  # planar[:q] < p
    box_lo = bmin[axis]
    box_hi = bmax[axis]
    cmin = np.empty(3)
    cmax = np.empty(3)
    while i < n or j < n:
        if i < n and (j >= n or lo[i] <= hi[j]):
            p = lo[i]
        else:
            p = hi[j]
        while j < n and hi[j] <= p:
            j += 1
        while q < n_planar and planar[q] < p:
            q += 1
        on_plane = 0
        while q + on_plane < n_planar and planar[q + on_plane] == p:
            on_plane += 1
        if box_lo < p < box_hi:
            n_left = i + on_plane
            n_right = n - j + on_plane
            for k in range(3):
                cmin[k] = bmin[k]
                cmax[k] = bmax[k]
            cmax[axis] = p
            area_left = _surface_area(bmin, cmax)
            cmin[axis] = p
            area_right = _surface_area(cmin, bmax)
            bonus = 1.0 - empty_bonus if (n_left == 0 or n_right == 0) else 1.0
            cost = k_t + k_i * bonus * (area_left / area * n_left + area_right / area * n_right)
            if cost < best_cost:
                best_cost = cost
                best_pos = p
        while i < n and lo[i] <= p:
            i += 1
    return best_cost, best_pos


@njit(cache=True)
def build_naive(v0, v1, v2, triangle_ids, root_min, root_max, k_t, k_i, min_leaf, max_depth, cycle_axes, empty_bonus, clip):
    """Build the naive SAH KD-tree (Algorithm 1): only leaves hold triangles.

    Parameters
    ----------
    v0, v1, v2 : (T, 3) float64
        Triangle corners.
    triangle_ids : (M,) int32
        Triangles to insert (zero-area ones already removed).
    root_min, root_max : (3,) float64
        Scene bounds.
    k_t, k_i : float
        Traversal and intersection cost (SAH, eq. 1).
    min_leaf : int
        Nodes with at most this many triangles become leaves.
    max_depth : int
        Depth limit.
    cycle_axes : bool
        True: split axis = depth % 3 (paper); False: best of all three axes.
    empty_bonus : float
        SAH bonus for splits with an empty child.
    clip : bool
        True: classify triangles by their exact overlap with each node ("perfect
        splits"); False: by their bounding box against the split plane (the paper's
        naive build, which duplicates more).

    Returns
    -------
    node_meta, node_split, node_start, node_count, refs, node_area, max_depth_reached
    """
    capacity = 1024
    node_meta = np.empty(capacity, np.int32)
    node_split = np.zeros(capacity, np.float32)
    node_start = np.zeros(capacity, np.int32)
    node_count = np.zeros(capacity, np.int32)
    node_area = np.zeros(capacity, np.float64)
    n_nodes = 1

    ref_capacity = max(16, 4 * triangle_ids.shape[0])
    refs = np.empty(ref_capacity, np.int32)
    n_refs = 0

    # Working buffer of triangle lists; children are appended above their parent's
    # slice and the buffer top is reset to the popped node's end (LIFO discipline).
    work = np.empty(max(16, 3 * triangle_ids.shape[0]), np.int32)
    work[: triangle_ids.shape[0]] = triangle_ids

    stack_depth_cap = max_depth + 4
    st_node = np.empty(stack_depth_cap, np.int64)
    st_depth = np.empty(stack_depth_cap, np.int64)
    st_start = np.empty(stack_depth_cap, np.int64)
    st_end = np.empty(stack_depth_cap, np.int64)
    st_bounds = np.empty((stack_depth_cap, 6), np.float64)
    sp = 0
    st_node[0] = 0
    st_depth[0] = 0
    st_start[0] = 0
    st_end[0] = triangle_ids.shape[0]
    st_bounds[0, :3] = root_min
    st_bounds[0, 3:] = root_max
    sp = 1

    poly_a = np.empty((12, 3))
    poly_b = np.empty((12, 3))
    bmin = np.empty(3)
    bmax = np.empty(3)
    depth_reached = 0

    while sp > 0:
        sp -= 1
        node = st_node[sp]
        depth = st_depth[sp]
        start = st_start[sp]
        end = st_end[sp]
        bmin[:] = st_bounds[sp, :3]
        bmax[:] = st_bounds[sp, 3:]
        depth_reached = max(depth_reached, depth)
        area = _surface_area(bmin, bmax)
        node_area[node] = area

        # Bounds of every triangle within this node's box (clipped: exact; else its bbox).
        n_in = end - start
        tri_min = np.empty((n_in, 3))
        tri_max = np.empty((n_in, 3))
        n = 0
        for idx in range(start, end):
            t = work[idx]
            if clip:
                if clipped_bounds(v0[t], v1[t], v2[t], bmin, bmax, poly_a, poly_b, tri_min[n], tri_max[n]):
                    work[start + n] = t
                    n += 1
            else:
                for k in range(3):
                    tri_min[n, k] = max(bmin[k], min(v0[t, k], v1[t, k], v2[t, k]))
                    tri_max[n, k] = min(bmax[k], max(v0[t, k], v1[t, k], v2[t, k]))
                work[start + n] = t
                n += 1
        end = start + n

        best_cost = np.inf
        best_axis = -1
        best_pos = 0.0
        if n > min_leaf and depth < max_depth and area > 0.0:
            for axis in range(3):
                if cycle_axes and axis != depth % 3:
                    continue
                if bmax[axis] <= bmin[axis]:
                    continue
                lo = np.sort(tri_min[:n, axis])
                hi = np.sort(tri_max[:n, axis])
                flat = tri_min[:n, axis] == tri_max[:n, axis]
                planar = np.sort(tri_min[:n, axis][flat])
                cost, pos = _best_split_on_axis(lo, hi, planar, n, bmin, bmax, axis, area, k_t, k_i, empty_bonus)
                if cost < best_cost:
                    best_cost = cost
                    best_axis = axis
                    best_pos = pos
        if best_axis >= 0:
            # Store the plane exactly as the traversal will see it (float32).
            best_pos = np.float64(np.float32(best_pos))
            if not (bmin[best_axis] < best_pos < bmax[best_axis]):
                best_axis = -1
        # Paper's Terminate(V): leaf when the best split costs more than intersecting all.
        if best_axis < 0 or best_cost > k_i * n:
            if n_refs + n > ref_capacity:
                ref_capacity = max(2 * ref_capacity, n_refs + n)
                grown = np.empty(ref_capacity, np.int32)
                grown[:n_refs] = refs[:n_refs]
                refs = grown
            node_meta[node] = LEAF
            node_start[node] = n_refs
            node_count[node] = n
            refs[n_refs : n_refs + n] = np.sort(work[start:end])
            n_refs += n
            continue

        # Interior node: allocate both children next to each other.
        if n_nodes + 2 > capacity:
            capacity *= 2
            node_meta = _grow_i32(node_meta, capacity)
            node_start = _grow_i32(node_start, capacity)
            node_count = _grow_i32(node_count, capacity)
            grown_split = np.zeros(capacity, np.float32)
            grown_split[:n_nodes] = node_split[:n_nodes]
            node_split = grown_split
            grown_area = np.zeros(capacity, np.float64)
            grown_area[:n_nodes] = node_area[:n_nodes]
            node_area = grown_area
        left = n_nodes
        n_nodes += 2
        node_meta[node] = (left << 2) | best_axis
        node_split[node] = np.float32(best_pos)
        node_start[node] = 0
        node_count[node] = 0

        # Partition: right list first (it is processed last), then the left list above it.
        n_right = 0
        n_left = 0
        for k in range(n):
            lo_k = tri_min[k, best_axis]
            hi_k = tri_max[k, best_axis]
            planar_here = lo_k == best_pos and hi_k == best_pos
            if hi_k > best_pos or planar_here:
                n_right += 1
            if lo_k < best_pos or planar_here:
                n_left += 1
        needed = end + n_right + n_left
        if needed > work.shape[0]:
            grown_work = np.empty(max(2 * work.shape[0], needed), np.int32)
            grown_work[:end] = work[:end]
            work = grown_work
        write_right = end
        write_left = end + n_right
        for k in range(n):
            t = work[start + k]
            lo_k = tri_min[k, best_axis]
            hi_k = tri_max[k, best_axis]
            planar_here = lo_k == best_pos and hi_k == best_pos
            if hi_k > best_pos or planar_here:
                work[write_right] = t
                write_right += 1
            if lo_k < best_pos or planar_here:
                work[write_left] = t
                write_left += 1
        # Push right (bottom) then left (top).
        st_node[sp] = left + 1
        st_depth[sp] = depth + 1
        st_start[sp] = end
        st_end[sp] = end + n_right
        st_bounds[sp, :3] = bmin
        st_bounds[sp, 3:] = bmax
        st_bounds[sp, best_axis] = best_pos
        sp += 1
        st_node[sp] = left
        st_depth[sp] = depth + 1
        st_start[sp] = end + n_right
        st_end[sp] = end + n_right + n_left
        st_bounds[sp, :3] = bmin
        st_bounds[sp, 3:] = bmax
        st_bounds[sp, 3 + best_axis] = best_pos
        sp += 1

    return (
        node_meta[:n_nodes].copy(),
        node_split[:n_nodes].copy(),
        node_start[:n_nodes].copy(),
        node_count[:n_nodes].copy(),
        refs[:n_refs].copy(),
        node_area[:n_nodes].copy(),
        depth_reached,
    )


@njit(cache=True)
def _grow_i32(array, capacity):
    grown = np.zeros(capacity, np.int32)
    grown[: array.shape[0]] = array
    return grown


@njit(cache=True)
def pull_up(node_meta, node_start, node_count, refs):
    """Algorithm 3's pull-up: a triangle held by both children moves to the parent.

    Works bottom-up (children always have larger indices than their parent), on
    sorted per-node lists, so a triangle spanning a whole subtree ends up stored once
    at the subtree's root.

    Returns
    -------
    new_start, new_count, new_refs : arrays in the same layout as the input.
    """
    n_nodes = node_meta.shape[0]
    pool = np.empty(2 * refs.shape[0] + 16, np.int32)
    pool[: refs.shape[0]] = refs
    top = refs.shape[0]
    start = node_start.copy()
    count = node_count.copy()
    for node in range(n_nodes - 1, -1, -1):
        meta = node_meta[node]
        if meta == LEAF:
            continue
        left = meta >> 2
        right = left + 1
        a0 = start[left]
        na = count[left]
        b0 = start[right]
        nb = count[right]
        # Sorted-list intersection, written to the pool top.
        i = 0
        j = 0
        shared = 0
        while i < na and j < nb:
            x = pool[a0 + i]
            y = pool[b0 + j]
            if x == y:
                pool[top + shared] = x
                shared += 1
                i += 1
                j += 1
            elif x < y:
                i += 1
            else:
                j += 1
        start[node] = top
        count[node] = shared
        if shared > 0:
            count[left] = _remove_sorted(pool, a0, na, top, shared)
            count[right] = _remove_sorted(pool, b0, nb, top, shared)
        top += shared
    # Compact into node order.
    total = 0
    for node in range(n_nodes):
        total += count[node]
    new_refs = np.empty(total, np.int32)
    new_start = np.empty(n_nodes, np.int32)
    offset = 0
    for node in range(n_nodes):
        new_start[node] = offset
        new_refs[offset : offset + count[node]] = pool[start[node] : start[node] + count[node]]
        offset += count[node]
    return new_start, count.astype(np.int32), new_refs


@njit(cache=True)
def _remove_sorted(pool, list_start, list_count, removed_start, removed_count):
    """Remove the sorted entries pool[removed...] from the sorted list in place; new count."""
    write = list_start
    r = 0
    for k in range(list_start, list_start + list_count):
        x = pool[k]
        while r < removed_count and pool[removed_start + r] < x:
            r += 1
        if r < removed_count and pool[removed_start + r] == x:
            continue
        pool[write] = x
        write += 1
    return write - list_start
