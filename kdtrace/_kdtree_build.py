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
def _best_split_on_axis(lo, hi, planar, n, bmin, bmax, axis, area, k_t, k_i, empty_bonus, candidates):
    """Sweep the sorted triangle bounds along one axis; returns (cost, position).

    The planes tried are every triangle bound (``candidates`` empty: the SAH events of
    pbrt and Wald & Havran) or the sorted positions ``candidates`` (the paper's triangle
    centroids, Algorithm 1's FindPlaneSAH).
    """
    best_cost = np.inf
    best_pos = 0.0
    n_planar = planar.shape[0]
    n_candidates = candidates.shape[0]
    c = 0  # candidates[:c] tried
    i = 0  # lo[:i] < p
    j = 0  # hi[:j] <= p
    q = 0  # planar[:q] < p
    box_lo = bmin[axis]
    box_hi = bmax[axis]
    cmin = np.empty(3)
    cmax = np.empty(3)
    while (c < n_candidates) if n_candidates > 0 else (i < n or j < n):
        if n_candidates > 0:
            p = candidates[c]
            c += 1
            if c < n_candidates and candidates[c] == p:
                continue  # a repeated position is tried once
            while i < n and lo[i] < p:
                i += 1
        elif i < n and (j >= n or lo[i] <= hi[j]):
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
        if n_candidates == 0:
            while i < n and lo[i] <= p:
                i += 1
    return best_cost, best_pos


@njit(cache=True)
def build_naive(v0, v1, v2, triangle_ids, root_min, root_max, k_t, k_i, min_leaf, max_depth, cycle_axes, empty_bonus, clip,
                centroids, max_refs):
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
    centroids : bool
        True: try the planes through the node's triangle centroids (the paper's
        FindPlaneSAH); False: through every triangle bound (the exact SAH sweep).
    max_refs : int
        Reference budget: a node whose split would bring the references of the leaves and of
        the nodes still to build above it becomes a leaf. SAH and the depth limit alone let a
        stack of overlapping coplanar triangles double its references at every level (1,599
        triangles asked for over 6 GB).

    Returns
    -------
    node_meta, node_split, node_start, node_count, refs, node_area, max_depth_reached, capped
        ``capped``: the budget made at least one leaf.
    """
    meta, split, start_of, count_of, area_of = _grow_nodes(np.empty(0, np.int32), np.empty(0, np.float32),
                                                          np.empty(0, np.int32), np.empty(0, np.int32),
                                                          np.empty(0), 1024)
    n_nodes = 1
    refs = np.empty(max(16, 4 * triangle_ids.shape[0]), np.int32)
    n_refs = 0

    # Working buffer of triangle lists; children are appended above their parent's
    # slice and the buffer top is reset to the popped node's end (LIFO discipline).
    work = np.empty(max(16, 3 * triangle_ids.shape[0]), np.int32)
    work[: triangle_ids.shape[0]] = triangle_ids
    st_node, st_depth, st_start, st_end, st_bounds = _build_stack(max_depth, triangle_ids.shape[0], root_min, root_max)
    sp = 1

    poly_a = np.empty((12, 3))
    poly_b = np.empty((12, 3))
    bmin = np.empty(3)
    bmax = np.empty(3)
    # Every triangle's centroid, once (the paper's split candidates), not per node and axis.
    centroid = (v0 + v1 + v2) / 3.0 if centroids else np.empty((0, 3))
    depth_reached = 0

    pending = triangle_ids.shape[0]  # references of the nodes on the stack
    capped = False
    while sp > 0:
        sp -= 1
        node, depth, start, end = st_node[sp], st_depth[sp], st_start[sp], st_end[sp]
        pending -= end - start
        bmin[:] = st_bounds[sp, :3]
        bmax[:] = st_bounds[sp, 3:]
        depth_reached = max(depth_reached, depth)
        area = _surface_area(bmin, bmax)
        area_of[node] = area

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
                if (cycle_axes and axis != depth % 3) or bmax[axis] <= bmin[axis]:
                    continue
                lo = np.sort(tri_min[:n, axis])
                hi = np.sort(tri_max[:n, axis])
                flat = tri_min[:n, axis] == tri_max[:n, axis]
                planar = np.sort(tri_min[:n, axis][flat])
                candidates = np.empty(0)
                if centroids:
                    candidates = np.sort(centroid[work[start:end], axis])
                cost, pos = _best_split_on_axis(lo, hi, planar, n, bmin, bmax, axis, area, k_t, k_i, empty_bonus,
                                                candidates)
                if cost < best_cost:
                    best_cost = cost
                    best_axis = axis
                    best_pos = pos
        best_axis, best_pos = _representable_split(best_axis, best_pos, bmin, bmax)
        # Paper's Terminate(V): leaf when the best split costs more than intersecting all.
        if best_axis < 0 or best_cost > k_i * n:
            refs, n_refs = _write_leaf(meta, start_of, count_of, node, refs, n_refs, work[start:end])
            continue

        # Partition: right list first (it is processed last), then the left list above it.
        # Clipped bounds decide (perfect splits); on the unclipped path they decide as the
        # raw ones would, the split lying inside the box.
        n_right = 0
        n_left = 0
        for k in range(n):
            goes_right, goes_left = _sides(tri_min[k, best_axis], tri_max[k, best_axis], best_pos)
            n_right += goes_right
            n_left += goes_left
        if n_refs + pending + n_right + n_left > max_refs:
            capped = True
            refs, n_refs = _write_leaf(meta, start_of, count_of, node, refs, n_refs, work[start:end])
            continue
        pending += n_right + n_left
        meta, split, start_of, count_of, area_of, left = _add_children(meta, split, start_of, count_of, area_of,
                                                                       n_nodes, node, best_axis, best_pos)
        n_nodes += 2
        work = _ensure_capacity(work, end + n_right + n_left)
        write_right = end
        write_left = end + n_right
        for k in range(n):
            t = work[start + k]
            goes_right, goes_left = _sides(tri_min[k, best_axis], tri_max[k, best_axis], best_pos)
            if goes_right:
                work[write_right] = t
                write_right += 1
            if goes_left:
                work[write_left] = t
                write_left += 1
        sp = _push_children(st_node, st_depth, st_start, st_end, st_bounds, sp, left, depth + 1, best_axis, best_pos,
                            bmin, bmax, end, end + n_right, end + n_right + n_left)

    return (meta[:n_nodes].copy(), split[:n_nodes].copy(), start_of[:n_nodes].copy(), count_of[:n_nodes].copy(),
            refs[:n_refs].copy(), area_of[:n_nodes].copy(), depth_reached, capped)


@njit(cache=True)
def build_presorted(v0, v1, v2, triangle_ids, root_min, root_max, k_t, k_i, min_leaf, max_depth, cycle_axes, empty_bonus,
                     max_refs):
    """:func:`build_naive` with ``clip=False`` in O(N log N): the same tree, sorted once.

    :func:`build_naive` sorts every node's triangle bounds along each axis, O(n log n) per
    node and O(N log^2 N) in all. Here the root's triangles are sorted once per axis, by
    their lower and by their upper bound (six lists), and every child inherits its lists by
    a stable partition of its parent's (Wald & Havran 2006). Clipping a bound to a child's
    box is monotone, so an inherited list stays sorted by the child's clipped bounds, and
    the sweep sees exactly the values :func:`build_naive` sorts: same splits, same tree
    (tests/test_kdtree.py compares the two). Perfect splits (``clip=True``) change a
    triangle's bounds along every axis, so they stay with :func:`build_naive`.

    Parameters and returns as :func:`build_naive` (without ``clip`` and ``centroids``: the
    sweep tries every triangle bound). The budget is checked in the same order, so the tree is
    the same with it too.
    """
    n_tris = v0.shape[0]
    # Axis-major bounds: a node's sweep gathers along one axis, from one 8-byte-per-triangle array.
    raw_lo = np.empty((3, n_tris))
    raw_hi = np.empty((3, n_tris))
    for t in range(n_tris):
        for k in range(3):
            raw_lo[k, t] = min(v0[t, k], v1[t, k], v2[t, k])
            raw_hi[k, t] = max(v0[t, k], v1[t, k], v2[t, k])
    m = triangle_ids.shape[0]
    meta, split, start_of, count_of, area_of = _grow_nodes(np.empty(0, np.int32), np.empty(0, np.float32),
                                                          np.empty(0, np.int32), np.empty(0, np.int32),
                                                          np.empty(0), 1024)
    n_nodes = 1
    refs = np.empty(max(16, 4 * m), np.int32)
    n_refs = 0
    # A node's six lists lie back to back in ``work``: list 2 * axis holds its triangles by
    # lower bound along ``axis``, list 2 * axis + 1 by upper bound. Children are appended
    # above their parent and the top is reset to the popped node's start (LIFO).
    work = np.empty(max(96, 18 * m), np.int32)
    for axis in range(3):
        work[2 * axis * m:(2 * axis + 1) * m] = triangle_ids[np.argsort(raw_lo[axis, triangle_ids])]
        work[(2 * axis + 1) * m:(2 * axis + 2) * m] = triangle_ids[np.argsort(raw_hi[axis, triangle_ids])]
    st_node, st_depth, st_start, st_end, st_bounds = _build_stack(max_depth, 6 * m, root_min, root_max)
    sp = 1
    bmin = np.empty(3)
    bmax = np.empty(3)
    lo = np.empty(m)
    hi = np.empty(m)
    planar = np.empty(m)
    side = np.zeros(n_tris, np.uint8)  # bit 0: goes right, bit 1: goes left, of the node being split
    no_candidates = np.empty(0)
    depth_reached = 0
    pending = m  # references of the nodes on the stack
    capped = False
    while sp > 0:
        sp -= 1
        node, depth, start, end = st_node[sp], st_depth[sp], st_start[sp], st_end[sp]
        bmin[:] = st_bounds[sp, :3]
        bmax[:] = st_bounds[sp, 3:]
        n = (end - start) // 6
        pending -= n
        depth_reached = max(depth_reached, depth)
        area = _surface_area(bmin, bmax)
        area_of[node] = area
        best_cost = np.inf
        best_axis = -1
        best_pos = 0.0
        if n > min_leaf and depth < max_depth and area > 0.0:
            for axis in range(3):
                if (cycle_axes and axis != depth % 3) or bmax[axis] <= bmin[axis]:
                    continue
                by_lo = start + 2 * axis * n
                by_hi = by_lo + n
                n_planar = 0
                for i in range(n):
                    t = work[by_lo + i]
                    lo[i] = max(bmin[axis], raw_lo[axis, t])
                    if lo[i] == min(bmax[axis], raw_hi[axis, t]):
                        planar[n_planar] = lo[i]
                        n_planar += 1
                    hi[i] = min(bmax[axis], raw_hi[axis, work[by_hi + i]])
                cost, pos = _best_split_on_axis(lo[:n], hi[:n], planar[:n_planar], n, bmin, bmax, axis, area,
                                                k_t, k_i, empty_bonus, no_candidates)
                if cost < best_cost:
                    best_cost = cost
                    best_axis = axis
                    best_pos = pos
        best_axis, best_pos = _representable_split(best_axis, best_pos, bmin, bmax)
        if best_axis < 0 or best_cost > k_i * n:
            refs, n_refs = _write_leaf(meta, start_of, count_of, node, refs, n_refs, work[start:start + n])
            continue
        # Stable partition of each list: the right child's lists first (processed last).
        # Each triangle's side is decided once, from the first list, and looked up by the
        # six list passes (one byte per triangle instead of two gathered bounds).
        n_right = 0
        n_left = 0
        for i in range(start, start + n):
            t = work[i]
            goes_right, goes_left = _sides(raw_lo[best_axis, t], raw_hi[best_axis, t], best_pos)
            n_right += goes_right
            n_left += goes_left
            side[t] = goes_right | (goes_left << 1)
        if n_refs + pending + n_right + n_left > max_refs:
            capped = True
            refs, n_refs = _write_leaf(meta, start_of, count_of, node, refs, n_refs, work[start:start + n])
            continue
        pending += n_right + n_left
        meta, split, start_of, count_of, area_of, left = _add_children(meta, split, start_of, count_of, area_of,
                                                                       n_nodes, node, best_axis, best_pos)
        n_nodes += 2
        # One slot of slack: a list's unconditional store past its last entry lands on the
        # next list's first slot (written later) or, for the last left list, on the slack.
        work = _ensure_capacity(work, end + 6 * (n_right + n_left) + 1)
        right_start = end
        left_start = end + 6 * n_right
        for bit, child_start, child_n in ((1, right_start, n_right), (2, left_start, n_left)):
            for list_index in range(6):
                write = child_start + list_index * child_n
                for i in range(start + list_index * n, start + (list_index + 1) * n):
                    t = work[i]
                    # Store unconditionally, advance by the side bit: no unpredictable branch.
                    work[write] = t
                    write += (side[t] & bit) != 0
        sp = _push_children(st_node, st_depth, st_start, st_end, st_bounds, sp, left, depth + 1, best_axis, best_pos,
                            bmin, bmax, right_start, left_start, left_start + 6 * n_left)
    return (meta[:n_nodes].copy(), split[:n_nodes].copy(), start_of[:n_nodes].copy(), count_of[:n_nodes].copy(),
            refs[:n_refs].copy(), area_of[:n_nodes].copy(), depth_reached, capped)


@njit(cache=True, inline="always")
def _sides(lo, hi, pos):
    """(goes right, goes left) of a triangle with unclipped bounds [lo, hi] along the split axis.

    Either side its bounds reach; one lying in the plane goes to both.
    """
    planar_here = lo == pos and hi == pos
    return hi > pos or planar_here, lo < pos or planar_here


@njit(cache=True)
def _representable_split(axis, pos, bmin, bmax):
    """The split stored exactly as traversal sees it (float32); axis -1 if it leaves the open box."""
    if axis < 0:
        return axis, pos
    pos = np.float64(np.float32(pos))
    if not (bmin[axis] < pos < bmax[axis]):
        return -1, pos
    return axis, pos


@njit(cache=True)
def _ensure_capacity(work, needed):
    """``work`` itself, or a copy at least twice as large when ``needed`` entries do not fit."""
    if needed <= work.shape[0]:
        return work
    grown = np.empty(max(2 * work.shape[0], needed), work.dtype)
    grown[: work.shape[0]] = work
    return grown


@njit(cache=True)
def _write_leaf(meta, start_of, count_of, node, refs, n_refs, triangles):
    """Make ``node`` a leaf of ``triangles`` (stored sorted); returns (refs, n_refs)."""
    n = triangles.shape[0]
    refs = _ensure_capacity(refs, n_refs + n)
    meta[node] = LEAF
    start_of[node] = n_refs
    count_of[node] = n
    refs[n_refs:n_refs + n] = np.sort(triangles)
    return refs, n_refs + n


@njit(cache=True)
def _grow_nodes(meta, split, start_of, count_of, area_of, capacity):
    """Node arrays with room for ``capacity`` nodes, the existing ones copied."""
    used = meta.shape[0]
    grown_split = np.zeros(capacity, np.float32)
    grown_split[:used] = split
    grown_area = np.zeros(capacity)
    grown_area[:used] = area_of
    return (_grow_i32(meta, capacity), grown_split, _grow_i32(start_of, capacity), _grow_i32(count_of, capacity),
            grown_area)


@njit(cache=True)
def _add_children(meta, split, start_of, count_of, area_of, n_nodes, node, axis, pos):
    """Make ``node`` interior (split at ``pos`` along ``axis``) with two new children next to each other.

    The children are nodes ``n_nodes`` and ``n_nodes + 1``; the arrays grow (doubling)
    when they are full. Returns the (possibly new) arrays and the left child's index.
    """
    if n_nodes + 2 > meta.shape[0]:
        meta, split, start_of, count_of, area_of = _grow_nodes(meta, split, start_of, count_of, area_of,
                                                              2 * meta.shape[0])
    meta[node] = (n_nodes << 2) | axis
    split[node] = np.float32(pos)
    start_of[node] = 0
    count_of[node] = 0
    return meta, split, start_of, count_of, area_of, n_nodes


@njit(cache=True)
def _build_stack(max_depth, root_end, root_min, root_max):
    """The build's node stack (node, depth, work start, work end, bounds), holding the root."""
    cap = max_depth + 4
    st_node = np.empty(cap, np.int64)
    st_depth = np.empty(cap, np.int64)
    st_start = np.empty(cap, np.int64)
    st_end = np.empty(cap, np.int64)
    st_bounds = np.empty((cap, 6))
    st_node[0] = 0
    st_depth[0] = 0
    st_start[0] = 0
    st_end[0] = root_end
    st_bounds[0, :3] = root_min
    st_bounds[0, 3:] = root_max
    return st_node, st_depth, st_start, st_end, st_bounds


@njit(cache=True)
def _push_children(st_node, st_depth, st_start, st_end, st_bounds, sp, left, depth, axis, pos, bmin, bmax,
                   right_start, left_start, left_end):
    """Push the right child (work ``[right_start, left_start)``) then the left one; returns sp."""
    for child, lo_end, hi_end, bound in ((left + 1, right_start, left_start, axis),
                                         (left, left_start, left_end, 3 + axis)):
        st_node[sp] = child
        st_depth[sp] = depth
        st_start[sp] = lo_end
        st_end[sp] = hi_end
        st_bounds[sp, :3] = bmin
        st_bounds[sp, 3:] = bmax
        st_bounds[sp, bound] = pos
        sp += 1
    return sp


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
