"""numba kernels for ray queries on the KD-trees (paper Algorithms 2 and 4).

One traversal serves both variants: interior nodes of the naive tree hold no
triangles, so the local-branch test (Algorithm 4) costs a single count check there.
Traversal and intersection run in float64 on float32 scene data, front to back with
an explicit stack; a subtree whose entry distance lies beyond the closest hit so far
is skipped (the pruning of Algorithm 4, which is also valid for the naive tree).
Any-hit (shadow) queries walk their segment from its end instead (see :func:`trace_ray`).
"""

from __future__ import annotations

import sys

import numpy as np
from numba import njit, prange
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros

from kdtrace import _kdtree_build, _kdtree_layout, _stack
from kdtrace._kdtree_build import LEAF
from kdtrace._kdtree_layout import HAS_TRIANGLES
from kdtrace._stack import stack_empty
from kdtrace.cache import drop_stale_kernel_cache

STACK_SIZE = 96
#: Length of a traversal's per-ray scratch buffer (origin, direction, 1 / direction).
RAY_SCRATCH = 9
#: Relative widening of every ray interval a box or split plane yields, 1 + 2 gamma(3) in
#: float64 (pbrt-v4's robust slab test): a computed crossing distance is within gamma(3) of
#: the exact one, so a ray through a box corner or along a box face is not clipped away
#: by rounding. Leaves test triangles over (tmin, closest hit), not the node interval, so
#: widening only ever adds visits.
INTERVAL_PAD = 1.0 + 2.0 * (3.0 * 2.0**-53) / (1.0 - 3.0 * 2.0**-53)
#: The float32 grid's finest spacing (the smallest subnormal): a vertex that is not on a
#: split plane or box face is at least this far from it. A ray that starts on the plane and
#: departs from it by less over its interval reaches no vertex off the plane, but the triangle
#: test, whose shear is then subnormal and rounds, can see it on the plane: it lies in it.
FLOAT32_FINEST = 2.0**-149


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
    t = t_scaled * inv
    if not t > tmin:  # a subnormal t_scaled above tmin * abs_det = 0 can round to t = 0
        return np.inf, 0.0, 0.0
    return t, u_scaled * inv, v_scaled * inv


@njit(cache=True, inline="always")
def ray_shear(dx, dy, dz):
    """Per-ray constants of :func:`intersect_triangle_watertight` (Woop et al. 2013, §3).

    ``kz`` is the axis of the largest ``|d|`` component and ``kx, ky`` the other two in
    cyclic order; the shear ``(sx, sy, sz)`` maps the direction to ``(0, 0, 1)``.
    Returns ``(kx, ky, kz, sx, sy, sz)``.
    """
    if abs(dx) >= abs(dy) and abs(dx) >= abs(dz):
        kz = 0
    elif abs(dy) >= abs(dz):
        kz = 1
    else:
        kz = 2
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    d = (dx, dy, dz)
    sz = 1.0 / d[kz]
    return kx, ky, kz, d[kx] * sz, d[ky] * sz, sz


@njit(cache=True, inline="always")
def watertight_decision(a_x, a_y, a_z, b_x, b_y, b_z, c_x, c_y, c_z, okx, oky, okz, sx, sy, sz, tmin, tmax):
    """The decision of :func:`intersect_triangle_watertight` from a triangle's vertices a, b, c,
    each given in the permuted order ``(kx, ky, kz)`` of :func:`ray_shear`.

    Returns ``(hit, t_scaled, det, w1, w2)``: whether the ray hits in (tmin, tmax), and the
    scaled distance, determinant and barycentric weights of b and c, signed so that
    ``det >= 0`` (t = t_scaled / det, u = w1 / det, v = w2 / det).
    """
    az = a_z - okz
    bz = b_z - okz
    cz = c_z - okz
    ax = (a_x - okx) - sx * az
    ay = (a_y - oky) - sy * az
    bx = (b_x - okx) - sx * bz
    by = (b_y - oky) - sy * bz
    cx = (c_x - okx) - sx * cz
    cy = (c_y - oky) - sy * cz
    # Edge functions: w0 of edge (b, c) weighs vertex a, w1 of (c, a) weighs b, w2 of (a, b) weighs c.
    w0 = cx * by - cy * bx
    w1 = ax * cy - ay * cx
    w2 = bx * ay - by * ax
    # One branch on the combined outcome, not an early out per condition: a random ray's
    # edge signs are unpredictable, and the mispredicted early outs cost more than the
    # arithmetic they skip (incoherent rays 9-12% faster on cbox-original and car, one
    # thread). Same results: the conditions are the same.
    inside = not (((w0 < 0.0) | (w1 < 0.0) | (w2 < 0.0)) & ((w0 > 0.0) | (w1 > 0.0) | (w2 > 0.0)))
    det = w0 + w1 + w2
    t_scaled = (w0 * az + w1 * bz + w2 * cz) * sz
    negative = det < 0.0
    det = -det if negative else det
    t_scaled = -t_scaled if negative else t_scaled
    w1 = -w1 if negative else w1
    w2 = -w2 if negative else w2
    return inside & (det != 0.0) & (t_scaled > tmin * det) & (t_scaled < tmax * det), t_scaled, det, w1, w2


@njit(cache=True, inline="always")
def intersect_triangle_watertight(tri, corners, okx, oky, okz, kx, ky, kz, sx, sy, sz, tmin, tmax):
    """Watertight ray-triangle test (Woop, Benthin, Wald 2013), double-sided, edges inclusive.

    The vertices move into ray space (origin at ``o``, direction sheared onto +z by
    :func:`ray_shear`), where three 2D edge functions decide the hit
    (:func:`watertight_decision`). A vertex shared
    by two triangles gets bit-identical ray-space coordinates in both, and the edge
    function of a shared edge is exactly the negation of the neighbour's
    (``a*b - c*d`` against ``c*d - a*b``), so a ray through an edge is never missed by
    both triangles; Möller–Trumbore gives no such guarantee. Float64 on float32
    vertices. ``okx, oky, okz`` are the origin's components in the permuted order;
    returns ``(t, u, v)``, t = inf on a miss.
    """
    hit, t_scaled, det, w1, w2 = watertight_decision(
        corners[tri, kx], corners[tri, ky], corners[tri, kz], corners[tri, 3 + kx], corners[tri, 3 + ky],
        corners[tri, 3 + kz], corners[tri, 6 + kx], corners[tri, 6 + ky], corners[tri, 6 + kz],
        okx, oky, okz, sx, sy, sz, tmin, tmax)
    if not hit:
        return np.inf, 0.0, 0.0
    # The oracle's divisions (1 / det overflows for a subnormal det), and t in (tmin, tmax) once
    # divided too: a subnormal t_scaled above tmin * det = 0 can round to t = 0.
    t = t_scaled / det
    if not (t > tmin and t < tmax):
        return np.inf, 0.0, 0.0
    return t, w1 / det, w2 / det


@njit(cache=True, inline="always")
def triangle_test_setup(watertight, ox, oy, oz, dx, dy, dz):
    """Per-ray constants of the tree's triangle test, ``(okx, oky, okz, kx, ky, kz, sx, sy, sz)``:
    the origin in the permuted order and the shear of :func:`ray_shear` for the watertight test,
    the plain origin and placeholders for Möller–Trumbore."""
    if watertight:
        kx, ky, kz, sx, sy, sz = ray_shear(dx, dy, dz)
        o = (ox, oy, oz)
        return o[kx], o[ky], o[kz], kx, ky, kz, sx, sy, sz
    return ox, oy, oz, 0, 1, 2, 0.0, 0.0, 0.0


@njit(cache=True, inline="always")
def intersect_tree_triangle(watertight, tri, corners, ox, oy, oz, dx, dy, dz, setup, tmin, tmax):
    """``(t, u, v)`` of triangle ``tri`` by the tree's test (watertight or Möller–Trumbore), ``setup``
    from :func:`triangle_test_setup`; t = inf on a miss."""
    okx, oky, okz, kx, ky, kz, sx, sy, sz = setup
    if watertight:
        return intersect_triangle_watertight(tri, corners, okx, oky, okz, kx, ky, kz, sx, sy, sz, tmin, tmax)
    return intersect_triangle(tri, corners, ox, oy, oz, dx, dy, dz, tmin, tmax)


@njit(cache=True, inline="always")
def no_spans(corners):
    """An empty ``span_corners`` for :func:`trace_ray`: test triangles one by one."""
    return corners.reshape(-1)[:0]


#: Lanes of :func:`span_hits`' passes: 8 float64 values fill an AVX-512 register. ``span_corners``
#: ends with ``SPAN_LANES`` zeros, so a pass may read past the last span.
SPAN_LANES = 8


#: Bits of :func:`span_hits`' mask: lanes ``0 .. SPAN_MASK_BITS - 2`` one bit each, the rest the last bit.
SPAN_MASK_BITS = 64


@njit(cache=True, inline="always")
def span_hits(span_corners, first, count, okx, oky, okz, kx, ky, kz, sx, sy, sz, tmin, tmax):
    """Which of the references ``first .. first + count - 1`` (one node's span) are hit in
    (tmin, tmax), as a bit mask: bit ``k`` for reference ``first + k``, and the last bit
    (:data:`SPAN_MASK_BITS` - 1) for any of the references from there on.

    :func:`watertight_decision` for every reference of the span, with no early out and no
    branch per triangle, so the loop runs on vector registers. ``span_corners`` holds each
    span's corners as a block of 9 runs of ``count`` (:attr:`kdtrace.kdtree.KDTree.span_corners`).
    A query then tests one by one only the references from the mask's first set bit to its last
    (for the last bit: to the span's end): no other reference can be found hit one by one, because
    the decision is the same, bit for bit, so the hit and the counters are the one-by-one walk's.
    (Testing only the set bits, in a loop over the mask, rendered max_depth-3 frames 1.03x slower
    than this and the camera-ray-only ones 1.15-1.27x slower: LLVM laid out the path tracer's kernel
    differently, though the camera packets' code is the same.)

    The loop runs to ``count`` rounded up to a multiple of :data:`SPAN_LANES`, and the lanes
    past ``count`` (reading the next run's corners, or the array's zero padding at its end)
    are masked out. With the trip count a known multiple of 8, LLVM tests a span of up to 8
    triangles in one pass of 8 float64 lanes (zmm); with the exact count it took a span of 8
    in two passes of 4 lanes and a span of 1-3 in scalar code. Frames 1.06x faster on
    cbox-original and 1.03x on cbox-sphere, car and Crytek Sponza unchanged (256x256, 8 spp,
    max_depth 3, 2 threads, separate processes, 3 rounds). Same hits.
    """
    mask = np.uint64(0)
    n = np.uint64(count)
    block = np.uint64(9) * np.uint64(first)
    akx = block + np.uint64(kx) * n
    aky = block + np.uint64(ky) * n
    akz = block + np.uint64(kz) * n
    b = np.uint64(3) * n
    c = np.uint64(6) * n
    lanes = np.uint64(SPAN_LANES)
    last_bit = np.uint64(SPAN_MASK_BITS - 1)
    for k in range((n + lanes - np.uint64(1)) & ~(lanes - np.uint64(1))):
        hit = (k < n) & watertight_decision(
            span_corners[akx + k], span_corners[aky + k], span_corners[akz + k], span_corners[b + akx + k],
            span_corners[b + aky + k], span_corners[b + akz + k], span_corners[c + akx + k],
            span_corners[c + aky + k], span_corners[c + akz + k], okx, oky, okz, sx, sy, sz, tmin, tmax)[0]
        mask |= np.uint64(hit) << min(k, last_bit)
    return mask


@njit(cache=True, inline="always")
def leaves_through_face(lo, hi, o, d):
    """Whether a ray starts on a face of the slab ``lo <= x <= hi`` and heads out of it."""
    return (o == lo and d < 0.0) or (o == hi and d > 0.0)


@njit(cache=True, inline="always")
def clip_to_slab(lo, hi, o, d, t0, t1):
    """``(t0, t1)`` narrowed to where ``o + t d`` is in the slab ``lo <= x <= hi`` (``d != 0``),
    widened by :data:`INTERVAL_PAD` at both ends."""
    # Divide (once per ray): 1 / d overflows for a subnormal d, and 0 * inf is NaN
    # for an origin on the slab's face.
    ta = (lo - o) / d
    tb = (hi - o) / d
    if ta > tb:
        ta, tb = tb, ta
    ta = ta / INTERVAL_PAD
    tb = tb * INTERVAL_PAD
    return (ta if ta > t0 else t0), (tb if tb < t1 else t1)


@njit(cache=True, inline="always")
def clip_to_box(box, ox, oy, oz, dx, dy, dz, tmin, tmax):
    """Slab test against box = (xmin, ymin, zmin, xmax, ymax, zmax).

    Zero direction components are handled explicitly (no 0 * inf), so axis-parallel
    rays are exact; the interval is widened by :data:`INTERVAL_PAD` at both ends.
    A ray that starts on a face and heads out through it is clipped by that face only
    if it departs from the face by at least :data:`FLOAT32_FINEST` within the other
    axes' interval; closer, it lies in the face, where the triangle test can find hits
    (as :func:`trace_ray` treats split planes).
    Returns (t_enter, t_exit); t_enter > t_exit means a miss.
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
        if leaves_through_face(lo, hi, o[k], d[k]):
            continue
        t0, t1 = clip_to_slab(lo, hi, o[k], d[k], t0, t1)
        if t0 > t1:
            return 1.0, 0.0
    for k in range(3):
        lo = box[k]
        hi = box[k + 3]
        if leaves_through_face(lo, hi, o[k], d[k]) and abs(d[k]) * t1 >= FLOAT32_FINEST:
            t0, t1 = clip_to_slab(lo, hi, o[k], d[k], t0, t1)
            if t0 > t1:
                return 1.0, 0.0
    return t0, t1


@njit(cache=True, inline="always")
def decode_node(nodes, node, spans):
    """``(word, axis, first, count)`` of node ``node`` of :func:`trace_ray`'s flat ``nodes``.

    ``axis`` is the split axis (:data:`LEAF` for a leaf) and ``first, count`` the node's
    span of ``refs``: a leaf's triangles, a local-branch interior node's pulled-up ones
    (in its cold half, rows ``spans + node``), or none. ``spans`` is the node count.
    """
    word = nodes[np.uint64(2) * node]
    axis = word & 3
    if axis == LEAF:
        return word, axis, nodes[np.uint64(2) * node + np.uint64(1)], word >> 2
    if word & HAS_TRIANGLES:
        return word, axis, nodes[np.uint64(2) * (spans + node)], nodes[np.uint64(2) * (spans + node) + np.uint64(1)]
    return word, axis, 0, 0


@njit(cache=True, inline="always")  # inlined: no per-ray call, no reference counting of the arrays
def trace_ray(
    nodes, splits, refs, box, corners, span_corners,
    ox, oy, oz, dx, dy, dz, tmin, tmax, any_hit, watertight, st_node, st_ent, st_ext, ray,
):
    """Closest (or any) hit of one ray; returns (t, triangle, u, v, nodes_visited, tests).

    ``nodes`` is the (2 n, 2) int32 array of :func:`kdtrace._kdtree_layout.pack_nodes`
    (8-byte nodes in cache-line blocks, interior triangle spans in rows ``n + node``),
    flattened, and ``splits`` its float32 view: node ``i`` is words ``2 i`` and ``2 i + 1``.
    Node indices are unsigned and the array flat, so an index costs no negative-index
    wraparound and no multiply by a run-time row stride (measured 11-21% faster on bunny,
    Sponza and cbox-sphere, incoherent and shadow rays, 2 threads).
    ``watertight`` picks :func:`intersect_triangle_watertight` over Möller–Trumbore.
    ``st_*`` are caller-owned stack buffers (no allocation per ray), and ``ray`` (float64,
    :data:`RAY_SCRATCH`) holds origin, direction and reciprocal direction, indexed by a
    node's axis (measured 9-12% faster than indexing tuples by the axis at run time,
    bunny's random rays, one thread). With ``any_hit`` the segment is walked
    from its end (the far child of a split first): the answer, hit or no hit, is the same,
    and the triangle returned is any one in (tmin, tmax).

    With the watertight test and a non-empty ``span_corners`` (each node's span of references
    as a block, :attr:`kdtrace.kdtree.KDTree.span_corners`), a query first asks
    :func:`span_hits` which of a node's triangles are hit in (tmin, closest hit so far), all
    of them at once, and tests one by one only from the first of those to the last: the same hit,
    the same counters, and a span without a hit (most of them on a shadow ray's way to a light, all but
    the last on a closest-hit walk) costs no branch per triangle. Measured against one-by-one
    tests in separate processes (256x256, 8 spp, max_depth 3, 2 threads): frames
    1.08-1.09x faster with it for occlusion queries (car, cbox-original, cbox-sphere), and
    1.06x more on car and cbox-sphere with it for closest hits as well (cbox-original 1.01x,
    Crytek Sponza 1.02x). With the mask, a span of 16 costs about what one of 8 did, so the trees
    have leaves of 16 (``[kdtree] min_leaf_size``): frames against the commit before both
    (separate processes, 3 rounds) 1.07-1.08x faster at max_depth 3 on car,
    the Cornell boxes and Crytek Sponza, 0.90-0.95x at max_depth 1 (camera packets, which test a
    leaf's triangles lane by lane); Table 1's batch queries, which tested one by one, now use it
    too. Pass an empty array to test one by one.
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
    ray[0] = ox
    ray[1] = oy
    ray[2] = oz
    ray[3] = dx
    ray[4] = dy
    ray[5] = dz
    # Reciprocal directions: a multiply per node instead of a divide (inf where d = 0,
    # a case handled before it is used).
    ray[6] = 1.0 / dx if dx != 0.0 else np.inf
    ray[7] = 1.0 / dy if dy != 0.0 else np.inf
    ray[8] = 1.0 / dz if dz != 0.0 else np.inf
    setup = triangle_test_setup(watertight, ox, oy, oz, dx, dy, dz)
    okx, oky, okz, kx, ky, kz, sx, sy, sz = setup
    spans = np.uint64(nodes.shape[0] >> 2)
    vector_spans = watertight and span_corners.shape[0] > 0
    node = np.uint64(0)
    sp = 0
    while True:
        visited += 1
        word, axis, first, count = decode_node(nodes, node, spans)
        if count > 0:
            if vector_spans:
                may_hit = span_hits(span_corners, first, count, okx, oky, okz, kx, ky, kz, sx, sy, sz, tmin, best_t)
                if may_hit == 0:
                    tests += count  # what testing them one by one counts
                    count = 0
                else:
                    # One by one from the mask's first bit (an any-hit query's hit) to its last (the
                    # closest hit lies between; the last bit of the mask: to the span's end).
                    lead = np.int64(trailing_zeros(may_hit))
                    end = np.int64(count)
                    if may_hit >> np.uint64(SPAN_MASK_BITS - 1) == 0:
                        end = np.int64(SPAN_MASK_BITS) - np.int64(leading_zeros(may_hit))
                    tests += lead if any_hit else lead + count - end
                    first += lead
                    count = end - lead
            for k in range(first, first + count):
                tri = refs[np.uint64(k)]
                tests += 1
                t, u, v = intersect_tree_triangle(watertight, tri, corners, ox, oy, oz, dx, dy, dz, setup, tmin, best_t)
                if t < best_t:
                    best_t = t
                    best_tri = tri
                    best_u = u
                    best_v = v
                    if any_hit:
                        return best_t, best_tri, best_u, best_v, visited, tests
        if axis != LEAF:
            left = np.uint64(word >> 3)
            split = splits[np.uint64(2) * node + np.uint64(1)]
            o_axis = ray[axis]
            d_axis = ray[3 + axis]
            if o_axis < split or (o_axis == split and d_axis <= 0.0):
                near = left
                far = left + np.uint64(1)
            else:
                near = left + np.uint64(1)
                far = left
            if o_axis == split and (d_axis == 0.0 or abs(d_axis) * ext < FLOAT32_FINEST):
                # Lying in the plane: triangles of both children can touch the ray along
                # their edges in the plane (a triangle reaching the plane from one side is
                # stored on that side only), so visit both over the same interval. A ray
                # that departs from the plane by less than FLOAT32_FINEST (a subnormal
                # component) lies in it as well: the triangle test sees it there.
                st_node[sp] = far
                st_ent[sp] = ent
                st_ext[sp] = ext
                sp += 1
                node = near
                continue
            if d_axis == 0.0 or o_axis == split:
                # Parallel to the plane, or starting on it heading into `near`: one child.
                # (Also avoids 0 * inf = NaN when 1/d overflows for a subnormal d.)
                node = near
                continue
            t_plane = (split - o_axis) * ray[6 + axis]
            # Skip a child only if the plane is beyond the interval by more than rounding.
            if t_plane > ext * INTERVAL_PAD or t_plane <= 0.0 or t_plane > best_t:
                node = near
            elif t_plane * INTERVAL_PAD < ent:
                node = far
            else:
                # Both children: visit one, push the other with its part of the interval.
                # Closest hit goes front to back (near first). Any hit takes the far child
                # first, so the segment is walked from its end: any hit answers the query,
                # so the answer is the same in either order, but a shadow ray runs from a
                # surface, where the tree is deepest, to a light in open space, and an
                # occluder is met sooner from the light's side (measured on Table 1's shadow
                # rays, 2 threads: 0.88x on cbox-original, 1.04-1.25x on
                # cbox-sphere, car and samurai, 1.5x on bunny, 2.0x on Crytek Sponza, 2.8x
                # on dabrovic; nodes per ray 82 -> 55 on bunny, 24 -> 11.5 on dabrovic).
                # ``any_hit`` is a constant in every inlined copy, so this folds away.
                st_node[sp] = near if any_hit else far
                st_ent[sp] = ent if any_hit else t_plane
                st_ext[sp] = t_plane if any_hit else ext
                sp += 1
                node = far if any_hit else near
                if any_hit:
                    ent = t_plane
                else:
                    ext = t_plane
            continue
        # Leaf done: resume with the next subtree unless the closest hit precedes it. Entries
        # are not sorted by distance (a child of a plane the ray lies in is pushed with the
        # parent's entry), so a skipped entry says nothing about the ones below it.
        found = False
        while sp > 0:
            sp -= 1
            if st_ent[sp] <= best_t:
                node = np.uint64(st_node[sp])
                ent = st_ent[sp]
                ext = st_ext[sp]
                found = True
                break
        if not found:
            break
    if best_tri < 0:
        return np.inf, -1, 0.0, 0.0, visited, tests
    return best_t, best_tri, best_u, best_v, visited, tests


#: :func:`trace_ray` compiled once and called instead of inlined, for the path tracer's one-by-one
#: fallbacks of its camera and first-hit shadow packets: off the hot path, and each inlined copy cost
#: about 25 s of compilation (the path tracer's kernel compiled in 214 s instead of 267 s, idle; frames
#: as fast within the machine's noise).
trace_ray_called = njit(cache=True)(trace_ray.py_func)


@njit(cache=True, inline="always")
def ray_scratch():
    """:func:`trace_ray`'s per-thread buffers ``(st_node, st_ent, st_ext, ray)``, on the stack of
    the function it is inlined into (:func:`kdtrace._stack.stack_empty`)."""
    return (stack_empty(STACK_SIZE, np.int32), stack_empty(STACK_SIZE, np.float64),
            stack_empty(STACK_SIZE, np.float64), stack_empty(RAY_SCRATCH, np.float64))


@njit(cache=True, inline="always")
def store_hit(outputs, i, t, tri, u, v, visited, tests):
    """Write ray ``i``'s result into the batch outputs ``(t, tri, u, v, visited, tests)``."""
    out_t, out_tri, out_u, out_v, out_visited, out_tests = outputs
    out_t[i] = t
    out_tri[i] = tri
    out_u[i] = u
    out_v[i] = v
    out_visited[i] = visited
    out_tests[i] = tests


@njit(cache=True, _nrt=False)
def _trace_rays(nodes, splits, refs, box, corners, span_corners, origins, directions, tmin, tmax, any_hit, watertight,
                first, end, out_t, out_tri, out_u, out_v, out_visited, out_tests):
    """Rays ``first .. end - 1`` of :func:`trace_batch` (one parallel chunk).

    :func:`trace_ray` is inlined once with ``any_hit`` a constant True and once False, so
    closest-hit rays run without the any-hit branches (with ``any_hit`` passed through,
    they ran 2-8% slower once any-hit traversal differed). ``numba.literally``
    would do the same but dispatched every call anew (about 7 s per call). Compiled
    without numba's runtime: the traversal stack is in its stack frame and no reference to an
    array is counted (see :mod:`kdtrace._stack`).
    """
    st_node, st_ent, st_ext, ray = ray_scratch()
    outputs = (out_t, out_tri, out_u, out_v, out_visited, out_tests)
    for i in range(first, end):
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        if any_hit:
            t, tri, u, v, visited, tests = trace_ray(nodes, splits, refs, box, corners, span_corners, ox, oy, oz,
                                                     dx, dy, dz, tmin[i], tmax[i], True, watertight, st_node, st_ent,
                                                     st_ext, ray)
        else:
            t, tri, u, v, visited, tests = trace_ray(nodes, splits, refs, box, corners, span_corners, ox, oy, oz,
                                                     dx, dy, dz, tmin[i], tmax[i], False, watertight, st_node, st_ent,
                                                     st_ext, ray)
        store_hit(outputs, i, t, tri, u, v, visited, tests)


@njit(cache=True, parallel=True)
def trace_batch(
    nodes, splits, refs, box, corners, span_corners,
    origins, directions, tmin, tmax, any_hit, watertight, n_chunks,
    out_t, out_tri, out_u, out_v, out_visited, out_tests,
):
    """Trace every ray, in parallel over chunks of rays (one stack per chunk, :func:`_trace_rays`)."""
    n = origins.shape[0]
    chunk = (n + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        _trace_rays(nodes, splits, refs, box, corners, span_corners, origins, directions, tmin, tmax, any_hit,
                    watertight, c * chunk, min(n, (c + 1) * chunk), out_t, out_tri, out_u, out_v, out_visited, out_tests)


# numba's cache checks this file only; recompile when a module inlined from here changes.
drop_stale_kernel_cache(sys.modules[__name__], _kdtree_build, _kdtree_layout, _stack)
