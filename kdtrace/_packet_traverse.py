"""numba kernels: closest hits, and occlusion, of a packet of coherent rays traversed together.

A packet (Wald et al. 2001; Wald 2004, ch. 7 for kd-trees) walks the tree once for all
its rays: a node is fetched and decoded once per packet instead of once per ray, and
each ray keeps its own interval, closest hit and active bit. Every ray makes at every
node exactly the decision :func:`kdtrace._kdtree_traverse.trace_ray` makes (same
near/far rule, same interval padding, same pruning by its closest hit), and its nodes
come in the scalar walk's order, so each ray tests the same triangles in the same order
and gets the same hit, bit for bit, with the same node and test counts. The scalar
kernel stays the oracle; the tests compare the two ray by ray.

The packet needs its active rays to agree on which child of a split is near (true for
rays from one origin, e.g. a pinhole camera's, except on a split plane through that
origin). Where they do not, :func:`trace_packet` gives up and returns False, and the
caller traces the packet's rays one by one.

Occlusion queries (:func:`occluded_packet`, the path tracer's shadow rays from the first
hits of a camera packet) need no order, so their rays never leave the packet for
disagreeing: each goes where its own interval reaches. On shadow rays from jittered
camera hits towards the light (8 a pixel, the renderer's order) a packet of 16 visited 9.6
nodes on cbox-original and 19.7 on car, where the 16 rays one by one visit 16 x 8.1 and
16 x 10.6; the packet's lane work (about 700 cycles to load 16 rays, about 150 a split and
90 a triangle for each shear axis in use, measured with the cycle counter) leaves 2.4x
(cbox-original) and 1.6x (car) over one-by-one rays in a batch.
"""

from __future__ import annotations

import sys

import numpy as np
from numba import njit, prange

from kdtrace import _kdtree_build, _kdtree_layout, _kdtree_traverse, _stack
from kdtrace._kdtree_build import LEAF
from kdtrace._kdtree_traverse import (
    FLOAT32_FINEST,
    INTERVAL_PAD,
    STACK_SIZE,
    decode_node,
    intersect_triangle,
    no_spans,
    ray_scratch,
    store_hit,
    trace_ray,
    watertight_decision,
)
from kdtrace._stack import stack_empty
from kdtrace.cache import drop_stale_kernel_cache

#: Most rays in one packet (bits of an int64 mask; 16 = two pixels at 8 spp).
PACKET_SIZE = 16
# Rows of the lane state: ``lanes3[kind, axis, lane]`` ...
_ORIGIN, _DIRECTION, _INVERSE, _PERMUTED = 0, 1, 2, 3
# ... ``lanes[row, lane]`` (float64) ...
_ENT, _EXT, _BEST, _U, _V, _FAR_ENT, _FAR_EXT, _SHEAR_X, _SHEAR_Y, _SHEAR_Z = range(10)
# ... and ``lane_ints[row, lane]``.
_TRI, _VISITED, _TESTS, _KX, _KY, _KZ = range(6)
#: Rows of a packet's results: closest t, u, v in ``lanes``, triangle in ``lane_ints``.
PACKET_BEST, PACKET_U, PACKET_V, PACKET_TRI = _BEST, _U, _V, _TRI


@njit(cache=True, inline="always")
def packet_scratch():
    """Per-thread buffers of :func:`trace_packet`, on the stack of the function it is inlined into.

    Lane state as a structure of arrays, so that a loop over the lanes reads contiguous
    rows: ``lanes3`` (4, 3, :data:`PACKET_SIZE`) float64, ``lanes`` (10, PACKET_SIZE)
    float64, ``lane_ints`` (6, PACKET_SIZE) int64 (rows named by this module's ``_ORIGIN``
    .. ``_KZ``), the stack: (node, rays entering unchecked, rays whose entry is checked) and
    the pushed intervals, and a bool per lane (the triangle test's hits).

    Allocated where the caller's LLVM function sees it (:func:`kdtrace._stack.stack_empty`),
    so LLVM knows the buffers do not alias: from a separate function the returned arrays
    might, and the triangle test's lane loop (which writes the hit flags beside the closest
    hits) was not vectorised, which made camera packets no faster than single rays (0.82x on
    cbox-original's camera rays, 2 threads).
    """
    return (stack_empty((4, 3, PACKET_SIZE), np.float64), stack_empty((10, PACKET_SIZE), np.float64),
            stack_empty((6, PACKET_SIZE), np.int64), stack_empty((STACK_SIZE, 3), np.int64),
            stack_empty((STACK_SIZE, 2, PACKET_SIZE), np.float64), stack_empty(PACKET_SIZE, np.bool_))


@njit(cache=True, inline="always")
def _lane_mask(flags):
    """Bit mask of the true entries of ``flags``."""
    mask = 0
    for r in range(PACKET_SIZE):
        mask |= np.int64(flags[r]) << r
    return mask


@njit(cache=True, inline="always")
def _lane_slab(lo, hi, o, d, ent, ext):
    """:func:`kdtrace._kdtree_traverse.clip_to_slab` with selects instead of a branch (lane loops)."""
    ta = (lo - o) / d
    tb = (hi - o) / d
    near = (tb if ta > tb else ta) / INTERVAL_PAD
    far = (ta if ta > tb else tb) * INTERVAL_PAD
    return (near if near > ent else ent), (far if far < ext else ext)


@njit(cache=True, inline="always")
def _load_lanes(box, origins, directions, n, watertight, lanes3, lanes, lane_ints):
    """Fill the lane state of rays ``0 .. n-1``, each over ``(0, lanes[_BEST, r])``.

    The caller has put each ray's tmax in ``lanes[_BEST]`` (lanes past ``n`` copy ray 0
    and stay inactive). Returns ``(active, along_x, along_y, along_z)``: the mask of rays
    that meet the scene box, and for each axis the mask of the lanes whose watertight
    shear is along it.

    Each lane gets the arithmetic of :func:`kdtrace._kdtree_traverse.clip_to_box`, of the
    scalar walk's reciprocals and of :func:`kdtrace._kdtree_traverse.ray_shear`, operation
    for operation (the same values bit for bit), but in lane loops without branches: their
    13 divisions a ray then run on vector registers. With one loop over the lanes calling
    those functions, loading a packet took about 700 cycles, most of them divisions
    (cycle counter).
    """
    origin = lanes3[_ORIGIN]
    direction = lanes3[_DIRECTION]
    inverse = lanes3[_INVERSE]
    ent_l = lanes[_ENT]
    ext_l = lanes[_EXT]
    best = lanes[_BEST]
    missed = lane_ints[_VISITED]  # scratch until the end: 1 where the ray misses the box
    for r in range(PACKET_SIZE):
        q = r if r < n else 0
        for axis in range(3):
            origin[axis, r] = origins[q, axis]
            direction[axis, r] = directions[q, axis]
        best[r] = best[q]
    for r in range(PACKET_SIZE):
        ent_l[r] = 0.0
        ext_l[r] = best[r]
        missed[r] = 0
    for axis in range(3):
        lo = box[axis]
        hi = box[axis + 3]
        o_row = origin[axis]
        d_row = direction[axis]
        inv_row = inverse[axis]
        for r in range(PACKET_SIZE):
            o = o_row[r]
            d = d_row[r]
            parallel = d == 0.0
            inv_row[r] = np.inf if parallel else 1.0 / d
            t0, t1 = _lane_slab(lo, hi, o, d, ent_l[r], ext_l[r])
            outside = (o < lo) | (o > hi)
            skipped = parallel | ((o == lo) & (d < 0.0)) | ((o == hi) & (d > 0.0))
            missed[r] |= np.int64((parallel & outside) | ((not skipped) & (t0 > t1)))
            ent_l[r] = ent_l[r] if skipped else t0
            ext_l[r] = ext_l[r] if skipped else t1
    for axis in range(3):  # rays leaving through a face they start on, as clip_to_box
        lo = box[axis]
        hi = box[axis + 3]
        o_row = origin[axis]
        d_row = direction[axis]
        for r in range(PACKET_SIZE):
            o = o_row[r]
            d = d_row[r]
            leaving = ((o == lo) & (d < 0.0)) | ((o == hi) & (d > 0.0))
            moves = leaving & (abs(d) * ext_l[r] >= FLOAT32_FINEST)
            t0, t1 = _lane_slab(lo, hi, o, d, ent_l[r], ext_l[r])
            missed[r] |= np.int64(moves & (t0 > t1))
            ent_l[r] = t0 if moves else ent_l[r]
            ext_l[r] = t1 if moves else ext_l[r]
    active = 0
    for r in range(PACKET_SIZE):
        lost = missed[r] != 0
        ent_l[r] = 1.0 if lost else ent_l[r]
        ext_l[r] = 0.0 if lost else ext_l[r]
        lanes[_U, r] = 0.0
        lanes[_V, r] = 0.0
        lane_ints[_TRI, r] = -1
        lane_ints[_VISITED, r] = 0
        lane_ints[_TESTS, r] = 0
        active |= np.int64((ent_l[r] <= ext_l[r]) & (r < n)) << r
    along_x = 0
    along_y = 0
    along_z = 0
    if watertight:
        for r in range(PACKET_SIZE):
            dx, dy, dz = direction[0, r], direction[1, r], direction[2, r]
            ax, ay, az = abs(dx), abs(dy), abs(dz)
            x_largest = (ax >= ay) & (ax >= az)
            kz = 0 if x_largest else (1 if ay >= az else 2)
            kx = 1 if kz == 0 else (2 if kz == 1 else 0)
            ky = 2 if kz == 0 else (0 if kz == 1 else 1)
            d_kz = dx if kz == 0 else (dy if kz == 1 else dz)
            d_kx = dy if kz == 0 else (dz if kz == 1 else dx)
            d_ky = dz if kz == 0 else (dx if kz == 1 else dy)
            sz = 1.0 / d_kz
            lane_ints[_KX, r] = kx
            lane_ints[_KY, r] = ky
            lane_ints[_KZ, r] = kz
            ox, oy, oz = origin[0, r], origin[1, r], origin[2, r]
            lanes3[_PERMUTED, 0, r] = oy if kz == 0 else (oz if kz == 1 else ox)
            lanes3[_PERMUTED, 1, r] = oz if kz == 0 else (ox if kz == 1 else oy)
            lanes3[_PERMUTED, 2, r] = ox if kz == 0 else (oy if kz == 1 else oz)
            lanes[_SHEAR_X, r] = d_kx * sz
            lanes[_SHEAR_Y, r] = d_ky * sz
            lanes[_SHEAR_Z, r] = sz
            along_x |= np.int64(kz == 0) << r
            along_y |= np.int64(kz == 1) << r
            along_z |= np.int64(kz == 2) << r
    return active, along_x, along_y, along_z


@njit(cache=True, inline="always")
def _lane_shears(lanes3, lanes):
    """The lanes' rows the watertight test reads: permuted origins, shears and closest hits (or tmax)."""
    ok = lanes3[_PERMUTED]
    return ok[0], ok[1], ok[2], lanes[_SHEAR_X], lanes[_SHEAR_Y], lanes[_SHEAR_Z], lanes[_BEST]


@njit(cache=True, inline="always")
def _permuted_corners(tri, corners, kx, ky, kz):
    """Triangle ``tri``'s vertices a, b, c as float64, each in the permuted order ``(kx, ky, kz)``."""
    return (np.float64(corners[tri, kx]), np.float64(corners[tri, ky]), np.float64(corners[tri, kz]),
            np.float64(corners[tri, 3 + kx]), np.float64(corners[tri, 3 + ky]), np.float64(corners[tri, 3 + kz]),
            np.float64(corners[tri, 6 + kx]), np.float64(corners[tri, 6 + ky]), np.float64(corners[tri, 6 + kz]))


@njit(cache=True, inline="always")
def _test_triangle_uniform(tri, corners, kx, ky, kz, n, active, lanes3, lanes, lane_ints, hit):
    """:func:`kdtrace._kdtree_traverse.intersect_triangle_watertight` for every lane at once.

    The lanes in ``active`` share the shear's axes ``kx, ky, kz``, so the corners are read
    once and the lane loop is branch-free (selects, no early outs); each lane's arithmetic is the
    scalar test's, operation for operation, so its result is the same bit for bit. A first lane
    loop takes every lane's decision without the division (``watertight_decision``) and the
    triangle is done when no lane passes it: camera-ray frames 1.07-1.13x faster with leaves of 16
    (car, the Cornell boxes, Crytek Sponza; separate processes, 3 rounds).
    """
    okx, oky, okz, shx, shy, shz, best = _lane_shears(lanes3, lanes)
    cax, cay, caz, cbx, cby, cbz, ccx, ccy, ccz = _permuted_corners(tri, corners, kx, ky, kz)
    u_out = lanes[_U]
    v_out = lanes[_V]
    tests = lane_ints[_TESTS]
    # First every lane's decision without the division (most triangles of a leaf are missed by
    # every ray); the lanes that pass it are the only ones the full test below can accept.
    any_lane = False
    for r in range(n):
        on = (active >> r) & 1
        tests[r] += on
        hit[r] = (on == 1) & watertight_decision(cax, cay, caz, cbx, cby, cbz, ccx, ccy, ccz, okx[r], oky[r], okz[r],
                                                 shx[r], shy[r], shz[r], 0.0, best[r])[0]
        any_lane |= hit[r]
    if not any_lane:
        return
    for r in range(n):
        b = best[r]
        _, t_scaled, det, w1, w2 = watertight_decision(cax, cay, caz, cbx, cby, cbz, ccx, ccy, ccz, okx[r], oky[r],
                                                       okz[r], shx[r], shy[r], shz[r], 0.0, b)
        t = t_scaled / det
        good = hit[r] & (t > 0.0) & (t < b)  # hit[r]: this lane's decision of the first loop, on the same values
        hit[r] = good
        best[r] = t if good else b
        u_out[r] = w1 / det if good else u_out[r]
        v_out[r] = w2 / det if good else v_out[r]
    tri_out = lane_ints[_TRI]
    for r in range(n):
        tri_out[r] = tri if hit[r] else tri_out[r]


@njit(cache=True, inline="always")
def _test_triangle(tri, corners, watertight, along, active, lanes3, lanes, lane_ints, hit):
    """Test triangle ``tri`` against the active lanes; returns the mask of lanes it is the new closest hit of.

    Watertight: branch-free over the lanes (:func:`_test_triangle_uniform`), once per
    shear axis the active lanes use (a camera packet's rays mostly share one).
    Möller–Trumbore: lane by lane with the scalar test.
    """
    hits = 0
    if watertight:
        along_x, along_y, along_z = along
        if active & along_x:
            _test_triangle_uniform(tri, corners, 1, 2, 0, PACKET_SIZE, active & along_x, lanes3, lanes, lane_ints, hit)
            hits |= _lane_mask(hit)
        if active & along_y:
            _test_triangle_uniform(tri, corners, 2, 0, 1, PACKET_SIZE, active & along_y, lanes3, lanes, lane_ints, hit)
            hits |= _lane_mask(hit)
        if active & along_z:
            _test_triangle_uniform(tri, corners, 0, 1, 2, PACKET_SIZE, active & along_z, lanes3, lanes, lane_ints, hit)
            hits |= _lane_mask(hit)
        return hits
    for r in range(PACKET_SIZE):
        if not (active >> r) & 1:
            continue
        lane_ints[_TESTS, r] += 1
        t, u, v = intersect_triangle(tri, corners, lanes3[_ORIGIN, 0, r], lanes3[_ORIGIN, 1, r],
                                     lanes3[_ORIGIN, 2, r], lanes3[_DIRECTION, 0, r], lanes3[_DIRECTION, 1, r],
                                     lanes3[_DIRECTION, 2, r], 0.0, lanes[_BEST, r])
        if t < lanes[_BEST, r]:
            hits |= 1 << r
            lanes[_BEST, r] = t
            lanes[_U, r] = u
            lanes[_V, r] = v
            lane_ints[_TRI, r] = tri
    return hits


@njit(cache=True, inline="always")
def _split_lanes(split, axis, active, lanes3, lanes):
    """Every active lane's decision at a split, branch-free: the scalar walk's cases in its order.

    Lying in the plane: both children over the same interval; parallel to it or starting
    on it: near only; the plane outside the interval or past the closest hit: near only;
    before the entry: far only; else both, split at the plane. Leaves each lane's near
    interval in ``lanes[_ENT]``, ``lanes[_EXT]`` and its far one in ``lanes[_FAR_ENT]``,
    ``lanes[_FAR_EXT]``; returns the lane masks ``(left_near, go_near, go_far,
    far_checked)``, the last of the lanes whose far entry must still be checked against
    their closest hit when it is popped.
    """
    o_row = lanes3[_ORIGIN, axis]
    d_row = lanes3[_DIRECTION, axis]
    i_row = lanes3[_INVERSE, axis]
    ent_l = lanes[_ENT]
    ext_l = lanes[_EXT]
    best = lanes[_BEST]
    far_ent = lanes[_FAR_ENT]
    far_ext = lanes[_FAR_EXT]
    left_near = 0
    go_near = 0
    go_far = 0
    far_checked = 0
    for r in range(PACKET_SIZE):
        o_axis = o_row[r]
        d_axis = d_row[r]
        ent = ent_l[r]
        ext = ext_l[r]
        t_plane = (split - o_axis) * i_row[r]
        on_plane = o_axis == split
        parallel = d_axis == 0.0
        # in the plane over the whole interval (see trace_ray)
        lying = on_plane & (parallel | (abs(d_axis) * ext < FLOAT32_FINEST))
        one_child = parallel | on_plane
        near_only = (not one_child) & ((t_plane > ext * INTERVAL_PAD) | (t_plane <= 0.0) | (t_plane > best[r]))
        decided = one_child | near_only
        far_only = (not decided) & (t_plane * INTERVAL_PAD < ent)
        both = (not decided) & (not far_only)
        on = np.int64((active >> r) & 1)
        left_near |= (np.int64((o_axis < split) | (on_plane & (d_axis <= 0.0))) & on) << r
        go_near |= (np.int64(not far_only) & on) << r
        go_far |= (np.int64(lying | far_only | both) & on) << r
        far_checked |= (np.int64(lying | both) & on) << r
        far_ent[r] = t_plane if both else ent
        far_ext[r] = ext
        ext_l[r] = t_plane if both else ext
    return left_near, go_near, go_far, far_checked


@njit(cache=True, inline="always")
def trace_packet(nodes, splits, refs, box, corners, origins, directions, n, tmax, watertight, scratch):
    """Closest hits of rays ``0 .. n-1`` (n <= :data:`PACKET_SIZE`) over ``(0, tmax)``.

    Inline it into a function with ``error_model="numpy"`` that gets ``scratch`` from
    :func:`packet_scratch` itself: the lane loops divide by zero on lanes they then
    discard (numba's Python error model would check every division, and it ran 1.8x
    slower), and with the buffers passed in from a caller LLVM must assume they alias
    (1.8x slower again; Crytek Sponza's camera rays, one thread). Best in a
    function compiled with ``_nrt=False`` (see :mod:`kdtrace._stack`).

    ``origins`` and ``directions`` are (n, 3) float64; the tree arrays are those of
    :func:`kdtrace._kdtree_traverse.trace_ray`; ``scratch`` comes from :func:`packet_scratch`.
    On success returns True, with each ray's t
    (inf on a miss), u, v in ``lanes[_BEST]``, ``lanes[_U]``, ``lanes[_V]`` and its
    triangle (-1 on a miss), nodes visited and triangle tests in ``lane_ints[_TRI]``,
    ``lane_ints[_VISITED]`` and ``lane_ints[_TESTS]``. Returns False, with nothing usable,
    when two active rays disagree on a split's near child.
    """
    lanes3, lanes, lane_ints, st_head, st_span, flags = scratch
    ent_l = lanes[_ENT]
    ext_l = lanes[_EXT]
    best = lanes[_BEST]
    far_ent = lanes[_FAR_ENT]
    far_ext = lanes[_FAR_EXT]
    visited = lane_ints[_VISITED]
    for r in range(PACKET_SIZE):
        best[r] = tmax
    active, along_x, along_y, along_z = _load_lanes(box, origins, directions, n, watertight, lanes3, lanes, lane_ints)
    along = (along_x, along_y, along_z)
    spans = np.uint64(nodes.shape[0] >> 2)
    node = np.uint64(0)
    sp = 0
    while active != 0:
        word, axis, first, count = decode_node(nodes, node, spans)
        for r in range(PACKET_SIZE):
            visited[r] += (active >> r) & 1
        # Triangle-major: one triangle's corners are read once for every active ray.
        for k in range(first, first + count):
            _test_triangle(refs[np.uint64(k)], corners, watertight, along, active, lanes3, lanes, lane_ints, flags)
        if axis != LEAF:
            left = np.uint64(word >> 3)
            split = np.float64(splits[np.uint64(2) * node + np.uint64(1)])
            left_near, go_near, go_far, far_checked = _split_lanes(split, axis, active, lanes3, lanes)
            if left_near != 0 and left_near != active:
                return False
            near = left if left_near != 0 else left + np.uint64(1)
            far = left + np.uint64(1) if left_near != 0 else left
            if go_far != 0:
                # Pushed before the near child is walked: each ray meets its far child after its
                # near subtree, as in the scalar walk (a far-only ray waits, doing nothing).
                st_head[sp, 0] = np.int64(far)
                st_head[sp, 1] = go_far & ~far_checked
                st_head[sp, 2] = far_checked
                pushed_ent = st_span[sp, 0]
                pushed_ext = st_span[sp, 1]
                for r in range(PACKET_SIZE):
                    pushed_ent[r] = far_ent[r]
                    pushed_ext[r] = far_ext[r]
                sp += 1
            if go_near != 0:
                node = near
                active = go_near
                continue
        # Resume with the next entry that has a ray left: a ray the scalar walk would have
        # pushed stays only if its closest hit does not precede the entry.
        active = 0
        while sp > 0:
            sp -= 1
            pushed_ent = st_span[sp, 0]
            pushed_ext = st_span[sp, 1]
            checked = st_head[sp, 2]
            mask = st_head[sp, 1]
            for r in range(PACKET_SIZE):
                mask |= (np.int64(pushed_ent[r] <= best[r]) & ((checked >> r) & 1)) << r
            if mask != 0:
                node = np.uint64(st_head[sp, 0])
                active = mask
                for r in range(PACKET_SIZE):
                    on = (mask >> r) & 1 == 1
                    ent_l[r] = pushed_ent[r] if on else ent_l[r]
                    ext_l[r] = pushed_ext[r] if on else ext_l[r]
                break
    for r in range(PACKET_SIZE):
        if lane_ints[_TRI, r] < 0:
            best[r] = np.inf
            lanes[_U, r] = 0.0
            lanes[_V, r] = 0.0
    return True


@njit(cache=True, inline="always")
def occluded_packet(nodes, splits, refs, box, corners, origins, directions, n, scratch):
    """Which of the rays ``0 .. n-1`` (n <= :data:`PACKET_SIZE`) hit a triangle in ``(0, tmax)``:
    the mask of the blocked ones. Watertight trees only.

    The caller puts each ray's tmax in ``lanes[_BEST]`` of ``scratch`` (from :func:`packet_scratch`;
    inline it as :func:`trace_packet`). An occlusion query's answer does not depend on the
    order in which the tree is walked, so, unlike :func:`trace_packet`, rays that disagree
    on a near child stay in the packet: at a split each ray goes to the children its own
    interval reaches, by the scalar walk's rules (:func:`_split_lanes`), and the packet
    visits a child if any of its rays does. So each ray visits every node the scalar walk
    would visit without a hit, tests its triangles with the scalar test's arithmetic, and is
    blocked exactly when :func:`kdtrace._kdtree_traverse.trace_ray` with ``any_hit`` says
    so. A ray leaves the packet at its first hit. The child most rays meet last is walked
    first (the scalar any-hit walk's far-first order, by majority).
    """
    lanes3, lanes, lane_ints, st_head, st_span, flags = scratch
    ent_l = lanes[_ENT]
    ext_l = lanes[_EXT]
    far_ent = lanes[_FAR_ENT]
    far_ext = lanes[_FAR_EXT]
    active, along_x, along_y, along_z = _load_lanes(box, origins, directions, n, True, lanes3, lanes, lane_ints)
    along = (along_x, along_y, along_z)
    spans = np.uint64(nodes.shape[0] >> 2)
    node = np.uint64(0)
    sp = 0
    blocked = 0
    while active != 0:
        word, axis, first, count = decode_node(nodes, node, spans)
        for k in range(first, first + count):
            hits = _lanes_blocked(refs[np.uint64(k)], corners, along, active, lanes3, lanes, flags)
            blocked |= hits
            active &= ~hits
            if active == 0:
                break
        if axis != LEAF and active != 0:
            left = np.uint64(word >> 3)
            split = np.float64(splits[np.uint64(2) * node + np.uint64(1)])
            left_near, go_near, go_far, _ = _split_lanes(split, axis, active, lanes3, lanes)
            # Walk first the child that is the far one of most rays; ``near_first`` holds the
            # rays for which that child is their near one.
            right_first = 2 * _popcount(left_near) >= _popcount(active)
            near_first = (active & ~left_near) if right_first else left_near
            first_rays = (go_near & near_first) | (go_far & ~near_first)
            second_rays = (go_far & near_first) | (go_near & ~near_first)
            if second_rays != 0:
                st_head[sp, 0] = np.int64(left if right_first else left + np.uint64(1))
                st_head[sp, 1] = second_rays
                pushed_ent = st_span[sp, 0]
                pushed_ext = st_span[sp, 1]
                for r in range(PACKET_SIZE):
                    near = (near_first >> r) & 1 == 1
                    pushed_ent[r] = far_ent[r] if near else ent_l[r]
                    pushed_ext[r] = far_ext[r] if near else ext_l[r]
                sp += 1
            if first_rays != 0:
                for r in range(PACKET_SIZE):
                    near = (near_first >> r) & 1 == 1
                    ent_l[r] = ent_l[r] if near else far_ent[r]
                    ext_l[r] = ext_l[r] if near else far_ext[r]
                node = left + np.uint64(1) if right_first else left
                active = first_rays
                continue
        active = 0
        while sp > 0:
            sp -= 1
            mask = st_head[sp, 1] & ~blocked
            if mask != 0:
                node = np.uint64(st_head[sp, 0])
                active = mask
                pushed_ent = st_span[sp, 0]
                pushed_ext = st_span[sp, 1]
                for r in range(PACKET_SIZE):
                    ent_l[r] = pushed_ent[r]
                    ext_l[r] = pushed_ext[r]
                break
    return blocked


@njit(cache=True, inline="always")
def _popcount(mask):
    """Number of set bits of a lane mask."""
    count = 0
    while mask != 0:
        mask &= mask - 1
        count += 1
    return count


@njit(cache=True, inline="always")
def _lanes_blocked_along(tri, corners, kx, ky, kz, group, lanes3, lanes, flags):
    """Mask of the lanes whose ray hits triangle ``tri`` in (0, lanes[_BEST]), for shear axes
    ``kx, ky, kz``: the scalar test's decision and its ``t < tmax``, branch-free over the lanes."""
    okx, oky, okz, shx, shy, shz, best = _lane_shears(lanes3, lanes)
    cax, cay, caz, cbx, cby, cbz, ccx, ccy, ccz = _permuted_corners(tri, corners, kx, ky, kz)
    for r in range(PACKET_SIZE):
        hit, t_scaled, det, _, _ = watertight_decision(cax, cay, caz, cbx, cby, cbz, ccx, ccy, ccz, okx[r], oky[r],
                                                       okz[r], shx[r], shy[r], shz[r], 0.0, best[r])
        t = t_scaled / det
        flags[r] = hit & (t > 0.0) & (t < best[r])
    return _lane_mask(flags) & group


@njit(cache=True, inline="always")
def _lanes_blocked(tri, corners, along, active, lanes3, lanes, flags):
    """Mask of the active lanes whose ray hits triangle ``tri`` in (0, lanes[_BEST]) (once per
    shear axis the active lanes use)."""
    along_x, along_y, along_z = along
    hits = 0
    if active & along_x:
        hits |= _lanes_blocked_along(tri, corners, 1, 2, 0, active & along_x, lanes3, lanes, flags)
    if active & along_y:
        hits |= _lanes_blocked_along(tri, corners, 2, 0, 1, active & along_y, lanes3, lanes, flags)
    if active & along_z:
        hits |= _lanes_blocked_along(tri, corners, 0, 1, 2, active & along_z, lanes3, lanes, flags)
    return hits


@njit(cache=True, inline="always")
def _copy_packet_rays(origins, directions, start, m, org, dirs):
    """Rays ``start .. start + m - 1`` of a batch into a packet's ``org`` and ``dirs`` rows ``0 .. m - 1``."""
    for r in range(m):
        for k in range(3):
            org[r, k] = origins[start + r, k]
            dirs[r, k] = directions[start + r, k]


@njit(cache=True, error_model="numpy", _nrt=False)
def _occluded_packets(nodes, splits, refs, box, corners, origins, directions, tmax, first_packet, end_packet, out):
    """Packets ``first_packet .. end_packet - 1`` of :func:`occluded_batch_packets` (one parallel chunk)."""
    scratch = packet_scratch()
    lanes = scratch[1]
    org = stack_empty((PACKET_SIZE, 3), np.float64)
    dirs = stack_empty((PACKET_SIZE, 3), np.float64)
    n = origins.shape[0]
    for p in range(first_packet, end_packet):
        start = p * PACKET_SIZE
        m = min(PACKET_SIZE, n - start)
        _copy_packet_rays(origins, directions, start, m, org, dirs)
        for r in range(m):  # _load_lanes fills the lanes past m from ray 0
            lanes[_BEST, r] = tmax[start + r]
        blocked = occluded_packet(nodes, splits, refs, box, corners, org, dirs, m, scratch)
        for r in range(m):
            out[start + r] = (blocked >> r) & 1 == 1


@njit(cache=True, parallel=True)
def occluded_batch_packets(nodes, splits, refs, box, corners, origins, directions, tmax, n_chunks, out):
    """Occlusion of every ray over ``(0, tmax[i])`` into ``out`` (bool), consecutive rays in packets of
    :data:`PACKET_SIZE` (:func:`occluded_packet`; watertight trees). For the tests."""
    packets = (origins.shape[0] + PACKET_SIZE - 1) // PACKET_SIZE
    per_chunk = (packets + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        _occluded_packets(nodes, splits, refs, box, corners, origins, directions, tmax, c * per_chunk,
                          min(packets, (c + 1) * per_chunk), out)


@njit(cache=True, error_model="numpy", _nrt=False)
def _trace_packets(nodes, splits, refs, box, corners, origins, directions, tmax, watertight, packet_size,
                   first_packet, end_packet, out_t, out_tri, out_u, out_v, out_visited, out_tests):
    """Packets ``first_packet .. end_packet - 1`` of :func:`trace_batch_packets` (one parallel chunk).

    Compiled without numba's runtime: its scratch is on its stack and no reference to an
    array is counted (see :mod:`kdtrace._stack`).
    """
    scratch = packet_scratch()
    lanes = scratch[1]
    lane_ints = scratch[2]
    s_node, s_ent, s_ext, ray = ray_scratch()
    org = stack_empty((PACKET_SIZE, 3), np.float64)
    dirs = stack_empty((PACKET_SIZE, 3), np.float64)
    outputs = (out_t, out_tri, out_u, out_v, out_visited, out_tests)
    n = origins.shape[0]
    for p in range(first_packet, end_packet):
        start = p * packet_size
        m = min(packet_size, n - start)
        _copy_packet_rays(origins, directions, start, m, org, dirs)
        same_tmax = True
        for r in range(m):
            same_tmax = same_tmax and tmax[start + r] == tmax[start]
        if same_tmax and trace_packet(nodes, splits, refs, box, corners, org, dirs, m, tmax[start], watertight,
                                      scratch):
            for r in range(m):
                store_hit(outputs, start + r, lanes[_BEST, r], lane_ints[_TRI, r], lanes[_U, r], lanes[_V, r],
                          lane_ints[_VISITED, r], lane_ints[_TESTS, r])
            continue
        for r in range(m):
            i = start + r
            t, tri, u, v, visited, tests = trace_ray(
                nodes, splits, refs, box, corners, no_spans(corners), org[r, 0], org[r, 1], org[r, 2],
                dirs[r, 0], dirs[r, 1], dirs[r, 2], 0.0, tmax[i], False, watertight, s_node, s_ent, s_ext, ray)
            store_hit(outputs, i, t, tri, u, v, visited, tests)


@njit(cache=True, parallel=True)
def trace_batch_packets(
    nodes, splits, refs, box, corners, origins, directions, tmax, watertight, packet_size, n_chunks,
    out_t, out_tri, out_u, out_v, out_visited, out_tests,
):
    """Closest hits of every ray over ``(0, tmax[i])``, consecutive rays in packets of ``packet_size``.

    The outputs are those of :func:`kdtrace._kdtree_traverse.trace_batch` with
    ``any_hit=False`` and ``tmin = 0``; a packet whose rays disagree on a near child, or
    whose rays have different ``tmax``, is traced ray by ray by
    :func:`kdtrace._kdtree_traverse.trace_ray`. ``packet_size`` is 1 to :data:`PACKET_SIZE`.
    """
    if packet_size < 1 or packet_size > PACKET_SIZE:
        raise ValueError("packet_size must be 1 to PACKET_SIZE")
    packets = (origins.shape[0] + packet_size - 1) // packet_size
    per_chunk = (packets + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        _trace_packets(nodes, splits, refs, box, corners, origins, directions, tmax, watertight, packet_size,
                       c * per_chunk, min(packets, (c + 1) * per_chunk), out_t, out_tri, out_u, out_v, out_visited,
                       out_tests)


# numba's cache checks this file only; recompile when a module inlined from here changes.
drop_stale_kernel_cache(sys.modules[__name__], _kdtree_build, _kdtree_layout, _kdtree_traverse, _stack)
