"""numba kernels of the path tracer: RNG, sampling, BSDFs, the per-pixel path loop.

Everything here is a pure function over flat arrays; validation, scene packing and
timing live in :mod:`kdtrace.render`. The tile kernel :func:`render_tiles` takes seven
feature flags, run-time booleans: a scene skips the work of every feature it lacks at
the cost of a predicted branch, and one compiled kernel serves every scene.

Conventions (Mitsuba 3's ``path`` integrator, so both renderers estimate one image):

- ``depth`` is the number of scattering events before the current hit (0 at the camera
  ray's hit): emission is added at every hit, next-event estimation and BSDF sampling
  only while ``depth + 1 < max_depth`` (max_depth = -1: no limit).
- Diffuse and mirror surfaces are two-sided (the shading normal is flipped to face the
  incoming direction, like Mitsuba's ``twosided``); emitters are one-sided and emit on
  the side of their counter-clockwise geometric normal; dielectrics use the unflipped
  shading normal to tell inside from outside.
- NEE samples emitter triangles power-weighted (area x mean emission) and combines with
  BSDF sampling by the power heuristic; specular bounces and the sky are reached by
  BSDF sampling only (weight 1).
- Russian roulette from ``depth >= rr_depth`` with probability
  ``min(max(throughput) * eta^2, 0.95)``.

Random numbers are counter-based, so an image does not depend on threads or tiling:
``uniform(key, dim)`` hashes (splitmix64 finaliser) the path key
``sample_key(seed, pixel, sample)`` with the dimension ``dim``: 0 and 1 jitter the
pixel position, and bounce ``depth`` uses ``2 + 7 * depth + k`` for k = light pick,
light point (2), dielectric lobe, BSDF direction (2), Russian roulette.
"""

from __future__ import annotations

import math
import sys

import numpy as np
from numba import literally, njit, prange

from kdtrace import _kdtree_build, _kdtree_layout, _kdtree_traverse, _packet_traverse, _stack
from kdtrace._kdtree_traverse import intersect_tree_triangle, ray_scratch, trace_ray, trace_ray_called, triangle_test_setup
from kdtrace._packet_traverse import (
    PACKET_BEST,
    PACKET_SIZE,
    PACKET_TRI,
    PACKET_U,
    PACKET_V,
    occluded_packet,
    packet_scratch,
    trace_packet,
)
from kdtrace._stack import stack_empty
from kdtrace.cache import drop_stale_kernel_cache

KIND_DIFFUSE = 0
KIND_MIRROR = 1
KIND_DIELECTRIC = 2

#: Mitsuba's ``math::RayEpsilon<float>`` (1500 float32 epsilons): relative origin offset.
RAY_EPSILON = 1500.0 * 2.0**-24
#: Mitsuba's ``math::ShadowEpsilon<float>``: shadow rays stop this fraction short.
SHADOW_EPSILON = 10.0 * RAY_EPSILON
#: Random dimensions of one bounce: light pick, light point (2), lobe, direction (2), RR.
DIMS_PER_BOUNCE = 7
#: Dimensions 0 and 1 of every sample are the pixel jitter.
CAMERA_DIMS = 2
#: Counter columns per tile.
COUNT_CAMERA, COUNT_SHADOW, COUNT_BOUNCE, COUNT_PATHS = 0, 1, 2, 3

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MUL1 = np.uint64(0xBF58476D1CE4E5B9)
_MUL2 = np.uint64(0x94D049BB133111EB)
_INV_2_53 = 1.0 / 9007199254740992.0
_INV_PI = 1.0 / math.pi


# ------------------------------------------------------------------ counter-based RNG
@njit(cache=True, inline="always")
def mix64(z):
    """splitmix64 finaliser of ``z + golden gamma`` (uint64 in, uint64 out)."""
    z = z + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _MUL1
    z = (z ^ (z >> np.uint64(27))) * _MUL2
    return z ^ (z >> np.uint64(31))


@njit(cache=True)
def sample_key(seed, pixel, sample):
    """Key of one path: a hash of (seed, pixel index ``row * width + col``, sample index)."""
    return mix64(mix64(mix64(np.uint64(seed)) ^ np.uint64(pixel)) ^ np.uint64(sample))


@njit(cache=True)
def uniform(key, dim):
    """Uniform float64 in [0, 1) for random dimension ``dim`` of the path ``key`` (53 bits)."""
    z = mix64(key ^ (np.uint64(dim) * _MUL2))
    return np.float64(z >> np.uint64(11)) * _INV_2_53


# ------------------------------------------------------------------ camera and sampling
@njit(cache=True, inline="always")
def camera_direction(cam, width, height, x, y):
    """Unit direction through image position (x, y) in pixels, row 0 at the top.

    ``cam`` is float64 ``[position(3), forward(3), right(3), up(3), half_w, half_h]``;
    same arithmetic as :func:`kdtrace.rays.pinhole_directions`.
    """
    sx = (2.0 * x / width - 1.0) * cam[12]
    sy = (1.0 - 2.0 * y / height) * cam[13]
    dx = cam[3] + sx * cam[6] + sy * cam[9]
    dy = cam[4] + sx * cam[7] + sy * cam[10]
    dz = cam[5] + sx * cam[8] + sy * cam[11]
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return dx / norm, dy / norm, dz / norm


#: Taylor coefficients of sin(x) / x and of cos(x) as polynomials in x², highest power first:
#: on |x| <= pi/4 the first terms left out (x^16 / 17! and x^18 / 18!) are below 1e-16.
_SIN_SERIES = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(7, -1, -1))
_COS_SERIES = tuple((-1.0) ** k / math.factorial(2 * k) for k in range(8, -1, -1))


@njit(cache=True, inline="always")
def turn_cos_sin(u):
    """``(cos 2 pi u, sin 2 pi u)`` for ``u`` in [0, 1), within 1e-15 of libm's.

    Written out instead of calling ``math.cos`` and ``math.sin`` (which LLVM merges into
    one libm ``sincos``): that call in the middle of the inlined path loop made the
    path tracer's frames slower, measured 1.025x on cbox-original and 1.01x on car (256x256,
    8 spp, max_depth 3, separate processes, 5 rounds). ``u`` is reduced to the nearest quarter turn
    exactly (``4 u`` and its distance to an integer are exact in floating point), the
    remainder ``x`` in [-pi/4, pi/4] goes through the Taylor series, and the quarter turns
    swap and negate the pair without a branch.
    """
    turns = 4.0 * u
    quarter = math.floor(turns + 0.5)
    x = (turns - quarter) * (0.5 * math.pi)
    x2 = x * x
    sin_x = 0.0
    for coefficient in _SIN_SERIES:
        sin_x = sin_x * x2 + coefficient
    sin_x *= x
    cos_x = 0.0
    for coefficient in _COS_SERIES:
        cos_x = cos_x * x2 + coefficient
    k = np.int64(quarter) & 3  # quarter turns: (c, s) -> (-s, c) -> (-c, -s) -> (s, -c)
    odd = k & 1
    cos_sign = 1.0 - 2.0 * (((k + 1) >> 1) & 1)
    sin_sign = 1.0 - 2.0 * (k >> 1)
    return cos_sign * (sin_x if odd else cos_x), sin_sign * (cos_x if odd else sin_x)


@njit(cache=True, inline="always")
def cosine_hemisphere(u1, u2, nx, ny, nz):
    """Cosine-weighted unit direction about the unit normal n (pdf cos/pi per steradian)."""
    r = math.sqrt(u1)
    c, s = turn_cos_sin(u2)
    lx = r * c
    ly = r * s
    lz = math.sqrt(max(0.0, 1.0 - u1))
    # Duff et al. 2017 orthonormal basis.
    sign = 1.0 if nz >= 0.0 else -1.0
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    tx, ty, tz = 1.0 + sign * nx * nx * a, sign * b, -sign * nx
    bx, by, bz = b, sign + ny * ny * a, -ny
    return (lx * tx + ly * bx + lz * nx, lx * ty + ly * by + lz * ny, lx * tz + ly * bz + lz * nz)


@njit(cache=True, inline="always")
def fresnel_dielectric(cos_i, eta):
    """Mitsuba's ``fresnel``: (reflectance, signed cos_t, eta_it, eta_ti) for relative IOR ``eta``."""
    outside = cos_i >= 0.0
    eta_it = eta if outside else 1.0 / eta
    eta_ti = 1.0 / eta if outside else eta
    cos_t_sqr = 1.0 - eta_ti * eta_ti * (1.0 - cos_i * cos_i)
    cos_i_abs = abs(cos_i)
    cos_t_abs = math.sqrt(max(cos_t_sqr, 0.0))
    if eta == 1.0:
        r = 0.0
    elif cos_i_abs == 0.0 or cos_t_sqr <= 0.0:
        r = 1.0
    else:
        a_s = (cos_i_abs - eta_it * cos_t_abs) / (cos_i_abs + eta_it * cos_t_abs)
        a_p = (cos_t_abs - eta_it * cos_i_abs) / (cos_t_abs + eta_it * cos_i_abs)
        r = 0.5 * (a_s * a_s + a_p * a_p)
    cos_t = -cos_t_abs if cos_i >= 0.0 else cos_t_abs
    return r, cos_t, eta_it, eta_ti


@njit(cache=True, inline="always")
def power_heuristic(a, b):
    """MIS weight a^2 / (a^2 + b^2) of the strategy with pdf ``a``."""
    a2 = a * a
    return a2 / (a2 + b * b)


@njit(cache=True)
def texture_lookup(tex_pixels, tex_info, k, s, t):
    """Bilinear, wrapping lookup of texture ``k`` at (s, t); row = (1 - t) * height (OBJ's v up).

    ``tex_info[k] = (first pixel, width, height)`` into the row-major ``tex_pixels`` (N, 3).
    """
    first, w, h = tex_info[k, 0], tex_info[k, 1], tex_info[k, 2]
    x = s * w - 0.5
    y = (1.0 - t) * h - 0.5
    x0 = math.floor(x)
    y0 = math.floor(y)
    fx = x - x0
    fy = y - y0
    ix0 = int(x0) % w
    iy0 = int(y0) % h
    ix1 = (ix0 + 1) % w
    iy1 = (iy0 + 1) % h
    a = first + iy0 * w + ix0
    b = first + iy0 * w + ix1
    c = first + iy1 * w + ix0
    d = first + iy1 * w + ix1
    return (_bilinear(tex_pixels, 0, a, b, c, d, fx, fy), _bilinear(tex_pixels, 1, a, b, c, d, fx, fy),
            _bilinear(tex_pixels, 2, a, b, c, d, fx, fy))


@njit(cache=True, inline="always")
def _bilinear(pixels, channel, a, b, c, d, fx, fy):
    """Channel ``channel`` of pixels a, b (top row) and c, d (bottom row) mixed by (fx, fy)."""
    top = (1.0 - fx) * pixels[a, channel] + fx * pixels[b, channel]
    bottom = (1.0 - fx) * pixels[c, channel] + fx * pixels[d, channel]
    return (1.0 - fy) * top + fy * bottom


@njit(cache=True, inline="always")
def triangle_point(corners, tri, b1, b2):
    """Point with barycentrics (1 - b1 - b2, b1, b2) on triangle ``tri`` (float64)."""
    b0 = 1.0 - b1 - b2
    return (
        b0 * corners[tri, 0] + b1 * corners[tri, 3] + b2 * corners[tri, 6],
        b0 * corners[tri, 1] + b1 * corners[tri, 4] + b2 * corners[tri, 7],
        b0 * corners[tri, 2] + b1 * corners[tri, 5] + b2 * corners[tri, 8],
    )


@njit(cache=True, inline="always")
def geometric_normal(corners, tri):
    """Unit normal of the counter-clockwise winding (the emitting side)."""
    e1x = corners[tri, 3] - np.float64(corners[tri, 0])
    e1y = corners[tri, 4] - np.float64(corners[tri, 1])
    e1z = corners[tri, 5] - np.float64(corners[tri, 2])
    e2x = corners[tri, 6] - np.float64(corners[tri, 0])
    e2y = corners[tri, 7] - np.float64(corners[tri, 1])
    e2z = corners[tri, 8] - np.float64(corners[tri, 2])
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    return nx / norm, ny / norm, nz / norm


@njit(cache=True, error_model="numpy")
def geometric_normals(corners):
    """(T, 3) float64 :func:`geometric_normal` of every triangle, bit for bit (the path tracer
    reads them instead of computing a cross product, a square root and three divisions per hit
    and per light sample: frames 1.03-1.05x faster on car, cbox-original and cbox-sphere at
    max_depth 3, Crytek Sponza, lit by its sky only, 0.96-1.00x; separate processes, 3 rounds).
    NaN for a zero-area triangle, as computed at a hit (the tree holds none).
    24 bytes a triangle, 1.7 ms for Crytek Sponza's 262k, before a render's clock starts."""
    out = np.empty((corners.shape[0], 3))
    for tri in range(corners.shape[0]):
        out[tri, 0], out[tri, 1], out[tri, 2] = geometric_normal(corners, tri)
    return out


@njit(cache=True)
def sample_emitter(emit_tri, emit_cdf, corners, select, u1, u2, pick):
    """Pick an emitter triangle (by the CDF when ``select``, else the only one) and a uniform point.

    Returns (triangle, point x, y, z) with the point area-uniform on the triangle.
    """
    k = 0
    if select:
        k = np.searchsorted(emit_cdf, pick, side="right")
        k = min(k, len(emit_tri) - 1)
    tri = emit_tri[k]
    root = math.sqrt(u1)
    b1 = root * (1.0 - u2)
    b2 = root * u2
    px, py, pz = triangle_point(corners, tri, b1, b2)
    return tri, px, py, pz


@njit(cache=True, inline="always")
def offset_origin(px, py, pz, nx, ny, nz, dx, dy, dz):
    """Mitsuba's ``offset_p``: move p off its surface along the normal, to the side of d."""
    mag = (1.0 + max(abs(px), abs(py), abs(pz))) * RAY_EPSILON
    if nx * dx + ny * dy + nz * dz < 0.0:
        mag = -mag
    return px + mag * nx, py + mag * ny, pz + mag * nz


#: ``tri`` of :func:`last_ray_hit` for a last ray whose closest hit carries no radiance.
NO_RADIANCE = -2


@njit(cache=True, inline="always")
def last_ray_hit(emitters, sky, watertight, tree, emit_tri, tri_gnormal, ox, oy, oz, dx, dy, dz, scratch):
    """The closest hit of a path's last ray, as far as the radiance it brings back needs it.

    The last ray (``depth + 1 == max_depth``) only adds the emission of a front-facing
    emitter it hits first, or the sky if it leaves the scene; nothing is shaded at its hit.
    So the emitter triangles are tested first, one by one (:func:`kdtrace.render.render`
    allows this for scenes with few of them), and the tree is asked only an any-hit
    question: is anything in front of the nearest emitter hit, or (with a sky) does the ray
    hit anything at all? A ray that meets no emitter in a scene without sky, or meets the
    back of one, needs no traversal. Any hit stops at the first occluder, walking from the
    segment's far end, so it is also cheaper than the closest-hit walk it replaces.
    ``tri_gnormal`` holds the triangles' unit normals (:func:`geometric_normals`).

    The triangle tests are those of :func:`kdtrace._kdtree_traverse.trace_ray`, so the
    emitter's ``t`` is bit for bit the closest-hit walk's. Returns ``(t, tri)`` with ``tri``
    the emitter triangle when it is the closest hit, ``-1`` (t = inf) when the ray leaves
    the scene, and :data:`NO_RADIANCE` otherwise; only a hit of exactly equal ``t`` on an
    occluder (a tie the closest-hit walk breaks by its visiting order) can differ from it.
    """
    nodes, splits, refs, box, corners, span_corners = tree
    st_node, st_ent, st_ext, ray = scratch
    best_t = np.inf
    best_tri = -1
    if emitters:
        setup = triangle_test_setup(watertight, ox, oy, oz, dx, dy, dz)
        for k in range(emit_tri.shape[0]):
            tri = emit_tri[k]
            t, _, _ = intersect_tree_triangle(watertight, tri, corners, ox, oy, oz, dx, dy, dz, setup, 0.0, best_t)
            if t < best_t:
                best_t = t
                best_tri = tri
    if best_tri >= 0:
        gx, gy, gz = tri_gnormal[best_tri, 0], tri_gnormal[best_tri, 1], tri_gnormal[best_tri, 2]
        if -(gx * dx + gy * dy + gz * dz) <= 0.0:
            return best_t, NO_RADIANCE  # the back of an emitter: no emission, whatever lies before it
    elif not sky:
        return best_t, NO_RADIANCE
    # The escape query (no emitter hit, a sky) uses the vector test as well since its mask of hits
    # (Crytek Sponza's max_depth-3 frames 1.02x, car and cbox-original 0.99-1.00x, separate processes,
    # 4 rounds); with the "any hit?" test of before they had been 4-5% slower.
    _, blocker, _, _, _, _ = trace_ray(nodes, splits, refs, box, corners, span_corners, ox, oy, oz, dx, dy, dz, 0.0,
                                       best_t, True, watertight, st_node, st_ent, st_ext, ray)
    if blocker >= 0:
        return best_t, NO_RADIANCE
    return best_t, best_tri


# ------------------------------------------------------------------ feature flags
# The seven feature flags (specular, textures, normals, sky, emitters, emitter_selection,
# aux) are run-time booleans:
#   specular           mirror and dielectric branches (else every material is diffuse)
#   textures           texture-coordinate interpolation and texture lookups
#   normals            interpolated per-vertex shading normals (else the geometric one)
#   sky                constant environment radiance for rays leaving the scene
#   emitters           emission at hits and next-event estimation
#   emitter_selection  pick among several emitter triangles by a CDF (else emitter 0)
#   aux                albedo, normal and depth of the first hit
# They were numba literals (one machine code per combination, absent branches pruned) until
# Kernels for all features and for each scene's own ran at the same speed
# (paired general/specialised seconds: medians 0.86-1.07, every round 0.63-1.23, on cbox-original,
# cbox-sphere, car, Crytek Sponza and bunny, 256x256, 8 spp, max_depth 1 and 3), while each
# combination cost 45-60 s of compilation on first use (13 of them in one CI run).
# ``watertight`` (the triangle test of the tree, :func:`kdtrace._kdtree_traverse.trace_ray`)
# stays a literal (``literally``), so only one ray-triangle test is compiled in.


@njit(cache=True, error_model="numpy", inline="always")
def path_sample(
    specular, textures, normals, sky, emitters, emitter_selection, aux, watertight,
    tree, shading, ox, oy, oz, dx, dy, dz, first_hit, key, max_depth, rr_depth, last_ray_shortcut, scratch, deferred,
):
    """One path from the camera ray (o, d), whose hit ``first_hit`` = (t, triangle, u, v) is
    already traced, for the feature flags given first.

    ``last_ray_shortcut`` traces the last ray with :func:`last_ray_hit` (the same image).
    ``tree`` is ``(nodes, splits, refs, box, corners, span_corners)`` (an empty ``span_corners``:
    its ray queries test triangles one by one), ``shading`` the per-triangle,
    material, texture, emitter and sky arrays in :func:`render_tiles`' order (``tri_mat``
    to ``sky_rgb``), and ``scratch`` the traversal's ``(st_node, st_ent, st_ext, ray)``.
    They are tuples because CPython compiles a call of more than 30 arguments into
    ``f(*args)``, which numba cannot inline. Inlined into :func:`render_tile`, cbox-original
    rendered 1.4x faster at max_depth 1 and 1.3x at 3 (2 threads).

    The first hit's shadow ray is not traced here: it goes to row ``slot`` of ``deferred`` =
    ``(origins, directions, extra, slot)`` (origin, unit direction, and tmax followed by the
    rgb it brings if nothing blocks it), so that :func:`render_tile` can trace a camera
    packet's first shadow rays together; that rgb is not in the L returned. Shadow rays of
    later hits are traced here, one by one.

    Returns (L rgb, first-hit albedo rgb, first-hit normal xyz, first-hit distance
    (0 on a miss), shadow rays, bounce rays, whether a first shadow ray went to ``deferred``).
    """
    shadow_origins, shadow_directions, shadow_extra, slot = deferred
    first_shadow = False
    nodes, splits, refs, box, corners, span_corners = tree
    (tri_mat, tri_gnormal, tri_normals, tri_uv, mat_kind, mat_albedo, mat_emission, mat_ior, mat_tex, tex_pixels,
     tex_info, emit_tri, emit_cdf, tri_emit_pdf, sky_rgb) = shading
    st_node, st_ent, st_ext, ray = scratch
    lr = 0.0  # radiance gathered so far
    lg = 0.0
    lb = 0.0
    br = 1.0  # path throughput
    bg = 1.0
    bb = 1.0
    eta = 1.0  # product of relative IORs crossed (for Russian roulette)
    prev_pdf = 0.0  # solid-angle pdf of the last BSDF sample
    prev_delta = True  # last bounce was specular (or the camera)
    ar = ag = ab = 0.0
    anx = any_ = anz = 0.0
    first_t = 0.0
    n_shadow = 0
    n_bounce = 0
    depth = 0
    t, tri, u, v = first_hit
    while True:
        if depth > 0:
            n_bounce += 1
            if last_ray_shortcut and depth + 1 == max_depth:
                t, tri = last_ray_hit(emitters, sky, watertight, tree, emit_tri, tri_gnormal, ox, oy, oz, dx, dy, dz,
                                      scratch)
                if tri == NO_RADIANCE:
                    break
                u = v = 0.0  # unused: nothing is shaded at the last hit
            else:
                t, tri, u, v, _, _ = trace_ray(nodes, splits, refs, box, corners, span_corners, ox, oy, oz, dx, dy,
                                               dz, 0.0, np.inf, False, watertight, st_node, st_ent, st_ext, ray)
        if tri < 0:
            if sky:
                lr += br * sky_rgb[0]
                lg += bg * sky_rgb[1]
                lb += bb * sky_rgb[2]
            break
        m = tri_mat[tri]
        gx, gy, gz = tri_gnormal[tri, 0], tri_gnormal[tri, 1], tri_gnormal[tri, 2]
        wx, wy, wz = -dx, -dy, -dz
        # ---- emission seen by this ray (one-sided)
        if emitters and tri_emit_pdf[tri] > 0.0:
            cos_l = gx * wx + gy * wy + gz * wz
            if cos_l > 0.0:
                w = 1.0
                if not prev_delta:
                    w = power_heuristic(prev_pdf, tri_emit_pdf[tri] * t * t / cos_l)
                lr += br * w * mat_emission[m, 0]
                lg += bg * w * mat_emission[m, 1]
                lb += bb * w * mat_emission[m, 2]
        last = max_depth >= 0 and depth + 1 >= max_depth
        if last and not (aux and depth == 0):
            # The path ends here and no buffer needs this hit's attributes: skip the shading
            # normal and the texture lookup (one hit in three at max_depth 3).
            break
        px, py, pz = triangle_point(corners, tri, u, v)
        # ---- surface attributes
        sx, sy, sz = gx, gy, gz
        if normals and tri_normals.shape[0] == corners.shape[0]:  # the general kernel may get none
            w0 = 1.0 - u - v
            sx = w0 * tri_normals[tri, 0] + u * tri_normals[tri, 3] + v * tri_normals[tri, 6]
            sy = w0 * tri_normals[tri, 1] + u * tri_normals[tri, 4] + v * tri_normals[tri, 7]
            sz = w0 * tri_normals[tri, 2] + u * tri_normals[tri, 5] + v * tri_normals[tri, 8]
            norm = math.sqrt(sx * sx + sy * sy + sz * sz)
            if norm > 0.0:
                inv_norm = 1.0 / norm
                sx, sy, sz = sx * inv_norm, sy * inv_norm, sz * inv_norm
            else:
                sx, sy, sz = gx, gy, gz
        kr, kg, kb = mat_albedo[m, 0], mat_albedo[m, 1], mat_albedo[m, 2]
        if textures and mat_tex[m] >= 0:
            w0 = 1.0 - u - v
            s = w0 * tri_uv[tri, 0] + u * tri_uv[tri, 2] + v * tri_uv[tri, 4]
            tt = w0 * tri_uv[tri, 1] + u * tri_uv[tri, 3] + v * tri_uv[tri, 5]
            kr, kg, kb = texture_lookup(tex_pixels, tex_info, mat_tex[m], s, tt)
        cos_i = sx * wx + sy * wy + sz * wz
        if aux and depth == 0:
            ar, ag, ab = kr, kg, kb
            flip = 1.0 if cos_i >= 0.0 else -1.0
            anx, any_, anz = flip * sx, flip * sy, flip * sz
            first_t = t
        if last:
            break
        base = CAMERA_DIMS + depth * DIMS_PER_BOUNCE
        kind = mat_kind[m] if specular else KIND_DIFFUSE
        if kind == KIND_DIFFUSE:
            if cos_i < 0.0:  # two-sided: work on the side the ray came from
                sx, sy, sz, cos_i = -sx, -sy, -sz, -cos_i
            # ---- next-event estimation
            if emitters:
                ltri, qx, qy, qz = sample_emitter(emit_tri, emit_cdf, corners, emitter_selection,
                                                  uniform(key, base + 1), uniform(key, base + 2),
                                                  uniform(key, base))
                ex, ey, ez = qx - px, qy - py, qz - pz
                dist = math.sqrt(ex * ex + ey * ey + ez * ez)
                if dist > 0.0:
                    inv_dist = 1.0 / dist
                    ex, ey, ez = ex * inv_dist, ey * inv_dist, ez * inv_dist
                    nlx, nly, nlz = tri_gnormal[ltri, 0], tri_gnormal[ltri, 1], tri_gnormal[ltri, 2]
                    cos_l = -(nlx * ex + nly * ey + nlz * ez)
                    cos_o = sx * ex + sy * ey + sz * ez
                    if cos_l > 0.0 and cos_o > 0.0 and tri_emit_pdf[ltri] > 0.0:
                        sox, soy, soz = offset_origin(px, py, pz, gx, gy, gz, ex, ey, ez)
                        hx, hy, hz = qx - sox, qy - soy, qz - soz
                        hdist = math.sqrt(hx * hx + hy * hy + hz * hz)
                        n_shadow += 1
                        inv_hdist = 1.0 / hdist
                        sdx, sdy, sdz = hx * inv_hdist, hy * inv_hdist, hz * inv_hdist
                        shadow_tmax = hdist * (1.0 - SHADOW_EPSILON)
                        # f = power_heuristic(pdf_light, pdf_bsdf) * pdf_bsdf / pdf_light with
                        # pdf_light = area pdf * d^2 / cos_l, rewritten with one division
                        # (cbox-original 1.004-1.01x with the reciprocals above).
                        area = tri_emit_pdf[ltri] * dist * dist
                        pdf_bsdf = cos_o * _INV_PI
                        bsdf_cos = pdf_bsdf * cos_l
                        f = area * bsdf_cos / (area * area + bsdf_cos * bsdf_cos)
                        lm = tri_mat[ltri]
                        cr = br * kr * f * mat_emission[lm, 0]
                        cg = bg * kg * f * mat_emission[lm, 1]
                        cb = bb * kb * f * mat_emission[lm, 2]
                        if depth == 0:
                            shadow_origins[slot, 0], shadow_origins[slot, 1], shadow_origins[slot, 2] = sox, soy, soz
                            shadow_directions[slot, 0], shadow_directions[slot, 1], shadow_directions[slot, 2] = (
                                sdx, sdy, sdz)
                            shadow_extra[slot, 0] = shadow_tmax
                            shadow_extra[slot, 1], shadow_extra[slot, 2], shadow_extra[slot, 3] = cr, cg, cb
                            first_shadow = True
                        else:
                            _, blocker, _, _, _, _ = trace_ray(
                                nodes, splits, refs, box, corners, span_corners, sox, soy, soz, sdx, sdy, sdz, 0.0,
                                shadow_tmax, True, watertight, st_node, st_ent, st_ext, ray)
                            if blocker < 0:
                                lr += cr
                                lg += cg
                                lb += cb
            # ---- BSDF sampling
            dx, dy, dz = cosine_hemisphere(uniform(key, base + 4), uniform(key, base + 5), sx, sy, sz)
            cos_o = sx * dx + sy * dy + sz * dz
            if cos_o <= 0.0:
                break
            br *= kr
            bg *= kg
            bb *= kb
            prev_pdf = cos_o * _INV_PI
            prev_delta = False
        elif kind == KIND_MIRROR:
            if cos_i < 0.0:
                sx, sy, sz, cos_i = -sx, -sy, -sz, -cos_i
            dx, dy, dz = -wx + 2.0 * cos_i * sx, -wy + 2.0 * cos_i * sy, -wz + 2.0 * cos_i * sz
            br *= kr
            bg *= kg
            bb *= kb
            prev_delta = True
        else:
            r, cos_t, eta_it, eta_ti = fresnel_dielectric(cos_i, mat_ior[m])
            if uniform(key, base + 3) <= r:
                dx, dy, dz = -wx + 2.0 * cos_i * sx, -wy + 2.0 * cos_i * sy, -wz + 2.0 * cos_i * sz
            else:
                c = eta_ti * cos_i + cos_t
                dx, dy, dz = -eta_ti * wx + c * sx, -eta_ti * wy + c * sy, -eta_ti * wz + c * sz
                scale = eta_ti * eta_ti  # radiance is compressed into the denser medium
                br *= kr * scale
                bg *= kg * scale
                bb *= kb * scale
                eta *= eta_it
            prev_delta = True
        ox, oy, oz = offset_origin(px, py, pz, gx, gy, gz, dx, dy, dz)
        depth += 1
        b_max = max(br, bg, bb)
        if b_max <= 0.0:
            break
        if depth >= rr_depth:
            q = min(b_max * eta * eta, 0.95)
            if uniform(key, base + 6) >= q:
                break
            br /= q
            bg /= q
            bb /= q
    return lr, lg, lb, ar, ag, ab, anx, any_, anz, first_t, n_shadow, n_bounce, first_shadow


@njit(cache=True, error_model="numpy", _nrt=False)
def render_tile(
    specular, textures, normals, sky, emitters, emitter_selection, aux,
    nodes, splits, refs, box, corners, span_corners, watertight, tri_mat, tri_gnormal, tri_normals, tri_uv,
    mat_kind, mat_albedo, mat_emission, mat_ior, mat_tex, tex_pixels, tex_info,
    emit_tri, emit_cdf, tri_emit_pdf, sky_rgb, cam,
    width, height, spp, max_depth, rr_depth, seed, first_sample, tile_size, tile, tiles_x, camera_packets,
    shadow_packets, last_ray_shortcut, out_rgb, out_var, out_albedo, out_normal, out_depth, counts,
):
    """Render one tile (index ``tile`` of a row of ``tiles_x``) into the ``out_*`` buffers.

    The tile's pixel loops and :func:`path_sample` (inlined) are one function, compiled per
    triangle test (``watertight``); the parallel loop of :func:`render_tiles` calls it once per tile
    (numba cannot inline into a ``prange`` body). A pixel takes the samples
    ``first_sample .. first_sample + spp - 1`` of its sequence.

    The tile's camera rays, pixel after pixel and sample after sample, are traced in
    packets of :data:`kdtrace._packet_traverse.PACKET_SIZE` (``camera_packets``; the same
    hits as one by one, see :mod:`kdtrace._packet_traverse`), or one by one with
    :func:`kdtrace._kdtree_traverse.trace_ray` (the oracle). The packet's paths are traced
    one after the other, each leaving its first hit's shadow ray and the light it would bring;
    those shadow rays are then traced together (``shadow_packets``,
    :func:`kdtrace._packet_traverse.occluded_packet`) or one by one, and the light of the
    unblocked ones is added to their paths: the same images either way. Frames with the
    shadow packets against without, separate processes, 3 rounds (256x256, 8 spp, max_depth 3,
    2 threads): cbox-original and cbox-mirror 1.05x, car 1.02x, cbox-sphere 1.00x. The packet's buffers are
    allocated here: with them passed in from the caller, LLVM must assume they alias and
    the packet ran 1.8x slower (Crytek Sponza's camera rays).

    Compiled without numba's runtime (``_nrt=False``), so every buffer is on its stack
    (:func:`kdtrace._stack.stack_empty`) and no reference to an array is counted: the
    inlined :func:`path_sample` and traversals had made about two dozen atomic reference
    count calls per sample and per bounce, and without them the path tracer renders 1.86-2.10x
    faster at max_depth 1 and 1.13-1.17x at max_depth 3 on the Cornell boxes and car
    (Crytek Sponza 1.21x and 1.08x; 256x256, 8 spp, 2 threads, alternating processes).
    Same images.
    """
    literally(watertight)
    tree = (nodes, splits, refs, box, corners, span_corners)
    shading = (tri_mat, tri_gnormal, tri_normals, tri_uv, mat_kind, mat_albedo, mat_emission, mat_ior, mat_tex, tex_pixels, tex_info,
               emit_tri, emit_cdf, tri_emit_pdf, sky_rgb)
    scratch = ray_scratch()
    st_node, st_ent, st_ext, ray = scratch
    lane_scratch = packet_scratch()
    lanes = lane_scratch[1]
    lane_ints = lane_scratch[2]
    origins = stack_empty((PACKET_SIZE, 3), np.float64)
    directions = stack_empty((PACKET_SIZE, 3), np.float64)
    keys = stack_empty(PACKET_SIZE, np.uint64)
    lane_pixels = stack_empty((3, PACKET_SIZE), np.int64)  # column, row, sample
    # Each lane's path: L rgb without its first shadow ray's, albedo, normal, first-hit distance;
    # the row of its first shadow ray in the shadow_* buffers (-1: none).
    lane_paths = stack_empty((PACKET_SIZE, 10), np.float64)
    lane_shadow = stack_empty(PACKET_SIZE, np.int64)
    shadow_origins = stack_empty((PACKET_SIZE, 3), np.float64)
    shadow_directions = stack_empty((PACKET_SIZE, 3), np.float64)
    shadow_extra = stack_empty((PACKET_SIZE, 4), np.float64)  # tmax, rgb if not blocked
    ty0 = (tile // tiles_x) * tile_size
    tx0 = (tile % tiles_x) * tile_size
    tile_w = min(tx0 + tile_size, width) - tx0
    tile_h = min(ty0 + tile_size, height) - ty0
    n_shadow = 0
    n_bounce = 0
    # Per-pixel sums, allocated once per tile and zeroed for each pixel: the same images,
    # and cbox-original at 1 spp, max_depth 3 rendered 1.05-1.07 instead of 0.88-0.97
    # Mpaths/s with four allocations per pixel (8 spp and Sponza: within noise).
    sum_l = stack_empty(3, np.float64)
    sum_l2 = stack_empty(3, np.float64)
    sum_a = stack_empty(3, np.float64)
    sum_n = stack_empty(3, np.float64)
    sum_t = 0.0
    hits = 0
    total = tile_w * tile_h * spp
    # The next sample's pixel and index, advanced by counting: three integer divisions per
    # sample had made the packets' renders 3-10% slower than one-by-one.
    i = tx0
    j = ty0
    s = 0
    for start in range(0, total, PACKET_SIZE):
        lanes_used = min(PACKET_SIZE, total - start)
        for r in range(lanes_used):
            key = sample_key(seed, j * width + i, first_sample + s)
            keys[r] = key
            lane_pixels[0, r] = i
            lane_pixels[1, r] = j
            lane_pixels[2, r] = s
            dx, dy, dz = camera_direction(cam, width, height, i + uniform(key, 0), j + uniform(key, 1))
            origins[r, 0], origins[r, 1], origins[r, 2] = cam[0], cam[1], cam[2]
            directions[r, 0], directions[r, 1], directions[r, 2] = dx, dy, dz
            s += 1
            if s == spp:
                s = 0
                i += 1
                if i == tx0 + tile_w:
                    i = tx0
                    j += 1
        if not (camera_packets and trace_packet(nodes, splits, refs, box, corners, origins, directions, lanes_used,
                                                np.inf, watertight, lane_scratch)):
            for r in range(lanes_used):
                t, tri, u, v, _, _ = trace_ray_called(nodes, splits, refs, box, corners, span_corners, cam[0], cam[1], cam[2],
                                               directions[r, 0], directions[r, 1], directions[r, 2], 0.0, np.inf,
                                               False, watertight, st_node, st_ent, st_ext, ray)
                lanes[PACKET_BEST, r] = t
                lanes[PACKET_U, r] = u
                lanes[PACKET_V, r] = v
                lane_ints[PACKET_TRI, r] = tri
        shadows = 0
        for r in range(lanes_used):
            first_hit = (lanes[PACKET_BEST, r], lane_ints[PACKET_TRI, r], lanes[PACKET_U, r], lanes[PACKET_V, r])
            lr, lg, lb, ar, ag, ab, nx, ny, nz, t, shadow, bounce, first_shadow = path_sample(
                specular, textures, normals, sky, emitters, emitter_selection, aux, watertight,
                tree, shading, cam[0], cam[1], cam[2], directions[r, 0], directions[r, 1], directions[r, 2],
                first_hit, keys[r], max_depth, rr_depth, last_ray_shortcut, scratch,
                (shadow_origins, shadow_directions, shadow_extra, shadows),
            )
            lane_paths[r, 0], lane_paths[r, 1], lane_paths[r, 2] = lr, lg, lb
            lane_paths[r, 3], lane_paths[r, 4], lane_paths[r, 5] = ar, ag, ab
            lane_paths[r, 6], lane_paths[r, 7], lane_paths[r, 8] = nx, ny, nz
            lane_paths[r, 9] = t
            lane_shadow[r] = shadows if first_shadow else -1
            shadows += first_shadow
            n_shadow += shadow
            n_bounce += bounce
        # The first hits' shadow rays, together (all start near one another and head for the
        # same emitters), or one by one.
        blocked = 0
        if shadow_packets and shadows > 1:
            for q in range(shadows):
                lanes[PACKET_BEST, q] = shadow_extra[q, 0]
            blocked = occluded_packet(nodes, splits, refs, box, corners, shadow_origins, shadow_directions, shadows,
                                      lane_scratch)
        else:
            for q in range(shadows):
                _, blocker, _, _, _, _ = trace_ray_called(
                    nodes, splits, refs, box, corners, span_corners, shadow_origins[q, 0], shadow_origins[q, 1],
                    shadow_origins[q, 2], shadow_directions[q, 0], shadow_directions[q, 1], shadow_directions[q, 2],
                    0.0, shadow_extra[q, 0], True, watertight, st_node, st_ent, st_ext, ray)
                blocked |= np.int64(blocker >= 0) << q
        for r in range(lanes_used):
            px = lane_pixels[0, r]
            py = lane_pixels[1, r]
            sample = lane_pixels[2, r]
            if sample == 0:
                for c in range(3):
                    sum_l[c] = 0.0
                    sum_l2[c] = 0.0
                    sum_a[c] = 0.0
                    sum_n[c] = 0.0
                sum_t = 0.0
                hits = 0
            lr, lg, lb = lane_paths[r, 0], lane_paths[r, 1], lane_paths[r, 2]
            q = lane_shadow[r]
            if q >= 0 and (blocked >> q) & 1 == 0:
                lr += shadow_extra[q, 1]
                lg += shadow_extra[q, 2]
                lb += shadow_extra[q, 3]
            ar, ag, ab = lane_paths[r, 3], lane_paths[r, 4], lane_paths[r, 5]
            nx, ny, nz = lane_paths[r, 6], lane_paths[r, 7], lane_paths[r, 8]
            t = lane_paths[r, 9]
            sum_l[0] += lr
            sum_l[1] += lg
            sum_l[2] += lb
            sum_l2[0] += lr * lr
            sum_l2[1] += lg * lg
            sum_l2[2] += lb * lb
            if aux:
                sum_a[0] += ar
                sum_a[1] += ag
                sum_a[2] += ab
                sum_n[0] += nx
                sum_n[1] += ny
                sum_n[2] += nz
                if t > 0.0:
                    sum_t += t
                    hits += 1
            if sample < spp - 1:
                continue
            for c in range(3):
                mean = sum_l[c] / spp
                out_rgb[py, px, c] = mean
                if spp > 1:
                    out_var[py, px, c] = max(sum_l2[c] - sum_l[c] * mean, 0.0) / (spp - 1) / spp
                else:
                    out_var[py, px, c] = np.inf
            if aux:
                norm = math.sqrt(sum_n[0] ** 2 + sum_n[1] ** 2 + sum_n[2] ** 2)
                for c in range(3):
                    out_albedo[py, px, c] = sum_a[c] / spp
                    out_normal[py, px, c] = sum_n[c] / norm if norm > 0.0 else 0.0
                out_depth[py, px] = sum_t / hits if hits > 0 else 0.0
    pixels = tile_w * tile_h
    counts[tile, COUNT_CAMERA] = pixels * spp
    counts[tile, COUNT_SHADOW] = n_shadow
    counts[tile, COUNT_BOUNCE] = n_bounce
    counts[tile, COUNT_PATHS] = pixels * spp


@njit(cache=True, parallel=True, error_model="numpy")
def render_tiles(
    specular, textures, normals, sky, emitters, emitter_selection, aux,
    nodes, splits, refs, box, corners, span_corners, watertight, tri_mat, tri_gnormal, tri_normals, tri_uv,
    mat_kind, mat_albedo, mat_emission, mat_ior, mat_tex, tex_pixels, tex_info,
    emit_tri, emit_cdf, tri_emit_pdf, sky_rgb, cam,
    width, height, spp, max_depth, rr_depth, seed, first_sample, tile_size, tile_stride, camera_packets,
    shadow_packets, last_ray_shortcut, out_rgb, out_var, out_albedo, out_normal, out_depth, counts,
):
    """Render every pixel into the ``out_*`` buffers, in parallel over tiles.

    numba hands each thread one contiguous range of the ``prange`` loop, so the loop
    visits tile ``(k * tile_stride) % tiles``: with a stride coprime to the tile count
    and near its golden-ratio fraction (:func:`kdtrace.render.tile_stride`) every thread's
    range is spread over the whole image, not one band of it (a band holding the light
    or the sky costs more than the others).

    ``out_var`` receives the variance of the pixel mean per channel,
    ``s^2 / spp`` with the unbiased sample variance ``s^2`` (inf when spp = 1).
    ``counts[tile]`` = (camera rays, shadow rays, bounce rays, paths).
    """
    literally(watertight)
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    tiles = tiles_x * tiles_y
    for k in prange(tiles):
        render_tile(
            specular, textures, normals, sky, emitters, emitter_selection, aux,
            nodes, splits, refs, box, corners, span_corners, watertight, tri_mat, tri_gnormal, tri_normals, tri_uv,
            mat_kind, mat_albedo, mat_emission, mat_ior, mat_tex, tex_pixels, tex_info,
            emit_tri, emit_cdf, tri_emit_pdf, sky_rgb, cam,
            width, height, spp, max_depth, rr_depth, seed, first_sample, tile_size, (k * tile_stride) % tiles, tiles_x,
            camera_packets, shadow_packets, last_ray_shortcut, out_rgb, out_var, out_albedo, out_normal, out_depth, counts,
        )


# numba's cache checks this file only; recompile when a module inlined from here changes.
drop_stale_kernel_cache(sys.modules[__name__], _kdtree_build, _kdtree_layout, _kdtree_traverse, _packet_traverse, _stack)
