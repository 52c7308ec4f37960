"""Deterministic ray sets for benchmarks and intersector validation.

Every generator takes a :class:`~kdtrace.scene.Scene`, a ray count and a seed
(``np.random.default_rng(seed)``) and returns float32 ``origins, directions`` of
shape (N, 3) with unit-length directions, plus ``tmax`` (N,) for shadow rays. The
kinds stress different things: ``primary_rays`` are coherent camera rays,
``random_rays`` are incoherent, ``vertex_rays`` and ``edge_rays`` aim at the
places where watertightness is decided, ``shadow_rays`` test occlusion queries.

The pinhole camera model lives in :func:`camera_basis` and :func:`pinhole_directions`
so the path tracer shares it.
"""

from __future__ import annotations

import numpy as np

from kdtrace.scene import Camera, Scene

#: Offset of a shadow-ray origin off its surface, relative to the scene's coordinate
#: scale: about 170 float32 ulps, clear of the surface's own rounding.
SURFACE_OFFSET = 1e-5
#: Shadow rays stop this fraction short of the light, so the light is not an occluder.
SHADOW_TMAX_SHORTEN = 1e-4
#: Bounding-box enlargement (total, split over both sides) for random-ray origins.
BOX_MARGIN = 0.10


# ------------------------------------------------------------------ pinhole camera
def camera_basis(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal camera frame, float64.

    Returns
    -------
    forward, right, up : (3,) float64
        Unit viewing direction, ``normalize(cross(forward, camera.up))`` and
        ``cross(right, forward)`` (right-handed).
    """
    forward = np.subtract(camera.look_at, camera.position).astype(np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(camera.up, dtype=np.float64))
    right /= np.linalg.norm(right)
    return forward, right, np.cross(right, forward)


def pinhole_directions(
    camera: Camera, x: np.ndarray, y: np.ndarray, width: int | None = None, height: int | None = None
) -> np.ndarray:
    """Unit directions through continuous image positions of a pinhole camera.

    Parameters
    ----------
    camera : Camera
        Position, orientation and vertical field of view (degrees).
    x, y : (N,) arrays
        Image-plane positions in pixels: ``x`` in [0, width) from the left, ``y`` in
        [0, height) from the top; pixel ``(i, j)`` has its centre at ``(i + 0.5, j + 0.5)``.
    width, height : int, optional
        Image resolution in pixels (default: the camera's).

    Returns
    -------
    (N, 3) float64
        Unit world-space directions.
    """
    width = camera.width if width is None else width
    height = camera.height if height is None else height
    forward, right, up = camera_basis(camera)
    half_h = np.tan(np.radians(camera.fov) / 2.0)
    half_w = half_h * width / height
    sx = (2.0 * np.asarray(x, dtype=np.float64) / width - 1.0) * half_w
    sy = (1.0 - 2.0 * np.asarray(y, dtype=np.float64) / height) * half_h
    d = forward + sx[:, None] * right + sy[:, None] * up
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def camera_rays(
    camera: Camera,
    width: int | None = None,
    height: int | None = None,
    jitter: bool = False,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One primary ray per pixel, in row-major order with row 0 at the top.

    Parameters
    ----------
    camera : Camera
        The pinhole camera.
    width, height : int, optional
        Resolution in pixels (default: the camera's).
    jitter : bool
        Uniform random position inside each pixel instead of its centre.
    rng : numpy.random.Generator
        Random source; required when ``jitter``.

    Returns
    -------
    origins, directions : (width * height, 3) float32
    """
    width = camera.width if width is None else int(width)
    height = camera.height if height is None else int(height)
    if width < 1 or height < 1:
        raise ValueError(f"resolution must be positive, got {width}x{height}")
    if jitter and rng is None:
        raise ValueError("jittered camera rays need an rng")
    j, i = np.divmod(np.arange(width * height), width)
    offset = rng.random((2, width * height)) if jitter else np.full((2, width * height), 0.5)
    directions = pinhole_directions(camera, i + offset[0], j + offset[1], width, height)
    origins = np.broadcast_to(np.asarray(camera.position, dtype=np.float32), directions.shape)
    return np.ascontiguousarray(origins), directions.astype(np.float32)


# ------------------------------------------------------------------ helpers
def _check_count(n: int) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"ray count must be a positive integer, got {n!r}")
    return int(n)


def _check_scene(scene: Scene) -> np.ndarray:
    """Validate the scene; return the indices of its triangles of non-zero area."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a kdtrace Scene, got {type(scene).__name__}")
    good = np.flatnonzero(~scene.degenerate_mask())
    if len(good) == 0:
        raise ValueError(f"scene {scene.name!r} has no triangle of non-zero area")
    return good


def _box(scene: Scene, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Scene bounds grown by ``margin`` times the largest extent in total (float64)."""
    lo, hi = scene.bounds
    pad = 0.5 * margin * max(float((hi - lo).max()), 1e-6 * max(float(np.abs(lo).max()), float(np.abs(hi).max()), 1.0))
    return lo - pad, hi + pad


def _scale(scene: Scene) -> float:
    """Coordinate magnitude that float32 rounding errors scale with (scene units)."""
    lo, hi = scene.bounds
    return max(float(np.abs(lo).max()), float(np.abs(hi).max()), float((hi - lo).max()))


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    """Directions uniform on the unit sphere, float64 (N, 3)."""
    d = rng.standard_normal((n, 3))
    norm = np.linalg.norm(d, axis=1)
    while (small := norm < 1e-9).any():
        d[small] = rng.standard_normal((int(small.sum()), 3))
        norm = np.linalg.norm(d, axis=1)
    return d / norm[:, None]


def _surface_points(scene: Scene, tris: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted uniform points on the triangles ``tris`` (float64 (N, 3)) and the triangle of each."""
    areas = scene.triangle_areas(tris)
    chosen = tris[rng.choice(len(tris), size=n, p=areas / areas.sum())]
    corners = scene.vertices.astype(np.float64)[scene.triangles[chosen]]
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    w1 = r1 * (1.0 - r2)
    w2 = r1 * r2
    points = corners[:, 0] + w1[:, None] * (corners[:, 1] - corners[:, 0]) + w2[:, None] * (corners[:, 2] - corners[:, 0])
    return points, chosen


def _aim(origins: np.ndarray, targets: np.ndarray, min_length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Float32 rays from ``origins`` towards ``targets``; rows closer than ``min_length`` are flagged.

    Returns
    -------
    origins, directions : (N, 3) float32
        Directions are unit length (computed in float64 from the float32 origins).
    length : (N,) float64
        Distance from the float32 origin to the target.
    """
    origins = origins.astype(np.float32)
    delta = targets - origins.astype(np.float64)
    length = np.linalg.norm(delta, axis=1)
    directions = delta / np.maximum(length, min_length)[:, None]
    return origins, directions.astype(np.float32), length


def _aimed_rays(scene: Scene, targets: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Rays through ``targets`` from origins alternately inside the bounds and on a sphere around them."""
    lo, hi = _box(scene, BOX_MARGIN)
    centre, radius = (lo + hi) / 2.0, float(np.linalg.norm(hi - lo))
    n = len(targets)
    min_length = 1e-4 * radius
    origins = np.empty((n, 3))
    redo = np.ones(n, dtype=bool)
    while redo.any():
        k = np.flatnonzero(redo)
        inside = k % 2 == 0
        origins[k[inside]] = rng.uniform(lo, hi, (int(inside.sum()), 3))
        origins[k[~inside]] = centre + radius * _unit_vectors(rng, int((~inside).sum()))
        o32, directions, length = _aim(origins, targets, min_length)
        redo = length < min_length
    return o32, directions


# ------------------------------------------------------------------ ray kinds
def primary_rays(scene: Scene, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` jittered camera rays spread evenly over the image of the scene's first camera.

    Ray ``k`` goes through pixel ``floor((k + U_k) P / n)`` of the ``P`` pixels in
    row-major order, so small ``n`` samples the whole image and large ``n`` tiles it
    repeatedly; rays stay in image order (coherent).

    Returns
    -------
    origins, directions : (n, 3) float32
    """
    n = _check_count(n)
    _check_scene(scene)
    camera = scene.camera
    rng = np.random.default_rng(seed)
    pixels = camera.width * camera.height
    index = np.minimum(((np.arange(n) + rng.random(n)) * pixels / n).astype(np.int64), pixels - 1)
    row, col = np.divmod(index, camera.width)
    directions = pinhole_directions(camera, col + rng.random(n), row + rng.random(n))
    origins = np.broadcast_to(np.asarray(camera.position, dtype=np.float32), directions.shape)
    return np.ascontiguousarray(origins), directions.astype(np.float32)


def random_rays(scene: Scene, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Incoherent rays: origins uniform in the bounds enlarged by 10 %, directions uniform on the sphere.

    Returns
    -------
    origins, directions : (n, 3) float32
    """
    n = _check_count(n)
    _check_scene(scene)
    rng = np.random.default_rng(seed)
    lo, hi = _box(scene, BOX_MARGIN)
    origins = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    return origins, _unit_vectors(rng, n).astype(np.float32)


def vertex_rays(scene: Scene, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays aimed exactly at vertices of non-degenerate triangles.

    Even-numbered rays start uniformly inside the (10 % enlarged) bounds, odd ones on
    a sphere around them of radius the box diagonal. Targets are the float32 vertex
    positions, so the ray passes through the vertex up to direction rounding.

    Returns
    -------
    origins, directions : (n, 3) float32
    """
    n = _check_count(n)
    good = _check_scene(scene)
    rng = np.random.default_rng(seed)
    used = np.unique(scene.triangles[good])
    targets = scene.vertices[used[rng.integers(0, len(used), n)]].astype(np.float64)
    return _aimed_rays(scene, targets, rng)


def edge_rays(scene: Scene, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays aimed at edge midpoints of non-degenerate triangles (origins as in :func:`vertex_rays`).

    Returns
    -------
    origins, directions : (n, 3) float32
    """
    n = _check_count(n)
    good = _check_scene(scene)
    rng = np.random.default_rng(seed)
    tris = scene.triangles[good[rng.integers(0, len(good), n)]]
    edge = rng.integers(0, 3, n)
    rows = np.arange(n)
    a = scene.vertices[tris[rows, edge]].astype(np.float64)
    b = scene.vertices[tris[rows, (edge + 1) % 3]].astype(np.float64)
    return _aimed_rays(scene, 0.5 * (a + b), rng)


def shadow_rays(scene: Scene, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shadow rays from surface points to points on the lights.

    Origins are area-weighted uniform points on non-degenerate, non-emitting
    triangles (all triangles if every one emits), moved off the surface by
    ``SURFACE_OFFSET`` times the scene's coordinate scale along the geometric
    normal, towards the light. Targets are area-weighted uniform points on emitting
    triangles; a scene without emitters stands the sky in with uniform points on
    a sphere of radius twice the bounds' diagonal around their centre.

    Returns
    -------
    origins, directions : (n, 3) float32
        Unit directions towards the light point.
    tmax : (n,) float32
        Distance to the light point times ``1 - SHADOW_TMAX_SHORTEN``, scene units.
    """
    n = _check_count(n)
    good = _check_scene(scene)
    rng = np.random.default_rng(seed)
    emitters = np.intersect1d(scene.emitter_triangles, good)
    receivers = np.setdiff1d(good, emitters) if len(emitters) < len(good) else good
    lo, hi = scene.bounds
    centre, radius = (lo + hi) / 2.0, 2.0 * max(float(np.linalg.norm(hi - lo)), 1e-6)
    offset = SURFACE_OFFSET * _scale(scene)
    origins = np.empty((n, 3))
    targets = np.empty((n, 3))
    redo = np.ones(n, dtype=bool)
    while redo.any():
        k = np.flatnonzero(redo)
        points, tri = _surface_points(scene, receivers, len(k), rng)
        if len(emitters):
            targets[k], _ = _surface_points(scene, emitters, len(k), rng)
        else:
            targets[k] = centre + radius * _unit_vectors(rng, len(k))
        corners = scene.vertices.astype(np.float64)[scene.triangles[tri]]
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        side = np.where(np.einsum("ij,ij->i", normal, targets[k] - points) < 0.0, -1.0, 1.0)
        origins[k] = points + (side * offset)[:, None] * normal
        o32, directions, length = _aim(origins, targets, 4.0 * offset)
        redo = length < 4.0 * offset
    tmax = (length * (1.0 - SHADOW_TMAX_SHORTEN)).astype(np.float32)
    return o32, directions, tmax
