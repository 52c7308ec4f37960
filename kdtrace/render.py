"""The path tracer's public API: ``render`` and ``render_stereo``.

How to use::

    from kdtrace.render import render, render_stereo
    from kdtrace.scenes import load_scene
    scene = load_scene("cbox-original")
    result = render(scene, spp=4, max_depth=3, width=128, height=128)
    result.rgb, result.variance, result.albedo, result.normal, result.depth, result.stats
    left, right = render_stereo(scene, eye_separation=0.065, spp=4)

This module validates input, packs the scene into flat arrays, sets the kernel's feature
flags to what the scene needs (see :func:`scene_features`), warms the kernel up and times
the render; the numba kernels
live in :mod:`kdtrace._render_kernels`. ``max_depth`` follows Mitsuba 3's ``path``
integrator (1: emitters seen directly; 2: direct light; 3: one indirect bounce; -1:
unbounded with Russian roulette from depth ``rr_depth``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from kdtrace import _kdtree_build, _kdtree_layout, _kdtree_traverse, _packet_traverse
from kdtrace import _render_kernels as kernels
from kdtrace.cache import source_fingerprint
from kdtrace.config import DEFAULT_CONFIG
from kdtrace.imageio import srgb_decode
from kdtrace.kdtree import KDTree, build_kdtree
from kdtrace.rays import camera_basis
from kdtrace.resources import require_memory
from kdtrace.scene import Camera, Scene

#: Kernel features, in the order of the flags of :func:`kdtrace._render_kernels.render_tiles`.
FEATURES: tuple[str, ...] = ("specular", "textures", "normals", "sky", "emitters", "emitter_selection", "aux")
#: Pass as ``features`` to turn every feature flag on (the "general" kernel stats report).
ALL_FEATURES = frozenset(FEATURES)
#: Positions of :func:`kdtrace._render_kernels.render_tiles`' compile-time (``literally``)
#: arguments: ``watertight``, after the feature flags and the six tree arrays.
_LITERAL_ARGS = frozenset({len(FEATURES) + 6})
_KINDS = {"diffuse": kernels.KIND_DIFFUSE, "mirror": kernels.KIND_MIRROR, "dielectric": kernels.KIND_DIELECTRIC}


@dataclass
class RenderResult:
    """One rendered image and its auxiliary buffers (all float32, linear).

    Attributes
    ----------
    rgb : (H, W, 3) ndarray
        Mean radiance per pixel (linear HDR, the scene's emission units).
    variance : (H, W, 3) ndarray
        Variance of the pixel mean per channel: unbiased sample variance over the
        pixel's samples divided by spp (inf when spp = 1).
    albedo : (H, W, 3) ndarray or None
        Mean albedo of the first visible surface (texture or flat colour; the tint of a
        mirror or glass; 0 where the camera ray leaves the scene). None unless ``aux``.
    normal : (H, W, 3) ndarray or None
        Mean world-space shading normal of the first hit, flipped to face the camera
        and renormalised (0 where every sample missed). None unless ``aux``.
    depth : (H, W) ndarray or None
        Mean distance from the pinhole to the first hit along the (unit) camera ray,
        over the samples that hit, scene units (0 where all missed). None unless ``aux``.
    seconds : float
        Wall time of the render kernel (compilation and warm-up excluded).
    stats : dict
        ``rays`` (camera, shadow, bounce), ``paths``, ``paths_per_second``,
        ``rays_per_second``, ``features``, ``kernel`` ("specialised": the scene's
        features only, or "general": every feature flag on),
        ``compile_seconds`` and the render settings.
    """

    rgb: np.ndarray
    variance: np.ndarray
    albedo: np.ndarray | None
    normal: np.ndarray | None
    depth: np.ndarray | None
    seconds: float
    stats: dict


# ------------------------------------------------------------------ validation
def _positive_int(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def frame_bytes(width: int, height: int, aux: bool, tile_size: int) -> int:
    """Upper bound of the bytes a render allocates for its frame: every output buffer as float32.

    rgb and variance (3 channels each), with ``aux`` albedo, normal (3 each) and depth (1),
    plus 4 int64 counters per tile. Samples accumulate in place, so the bound does not grow
    with spp; the scene and its tree exist before the render (:func:`kdtrace.kdtree.build_kdtree`
    checks its own).
    """
    channels = 3 + 3 + (3 + 3 + 1 if aux else 0)
    tiles = -(-width // tile_size) * -(-height // tile_size)
    return width * height * channels * np.dtype(np.float32).itemsize + tiles * 4 * np.dtype(np.int64).itemsize


def _check_image_size(width: int, height: int, aux: bool, tile_size: int) -> None:
    """Refuse a resolution whose frame buffers (:func:`frame_bytes`) would not fit in the memory available."""
    buffers = "rgb, variance, albedo, normal and depth" if aux else "rgb and variance"
    require_memory(frame_bytes(width, height, aux, tile_size),
                   f"width x height = {width} x {height} ({width * height:,} pixels) for the {buffers} buffers",
                   "choose a smaller resolution")


def _check_camera(camera: Camera) -> None:
    values = [*camera.position, *camera.look_at, *camera.up, camera.fov]
    if not all(math.isfinite(float(x)) for x in values):
        raise ValueError(f"camera has a NaN or infinite value: {camera}")


def _check_materials(scene: Scene) -> None:
    for material in scene.materials:
        values = [*material.albedo, *material.emission, material.ior]
        if not all(math.isfinite(float(x)) for x in values):
            raise ValueError(f"material {material.name!r} has a NaN or infinite value: {material}")
        if min(*material.albedo, *material.emission) < 0.0:
            raise ValueError(f"material {material.name!r} has a negative albedo or emission")
        if material.kind not in _KINDS:
            raise ValueError(f"material {material.name!r} has unknown kind {material.kind!r}")
        if material.kind == "dielectric" and not material.ior > 0.0:
            raise ValueError(f"dielectric {material.name!r} needs ior > 0, got {material.ior}")
    if scene.sky is not None and not all(math.isfinite(x) and x >= 0.0 for x in scene.sky.radiance):
        raise ValueError(f"sky radiance must be finite and non-negative, got {scene.sky.radiance}")


# ------------------------------------------------------------------ scene packing
@functools.lru_cache(maxsize=32)
def _load_texture(path: str) -> np.ndarray | None:
    """Linear RGB float32 (H, W, 3) of an sRGB image file, or None (with a warning) if unreadable."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            srgb = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0
    except (OSError, ValueError) as error:
        warnings.warn(f"texture {path!r} cannot be read ({error}); using the flat albedo", stacklevel=4)
        return None
    return srgb_decode(srgb)


def _textures(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(material texture index or -1, texel array (N, 3), per-texture (first, width, height))."""
    mat_tex = np.full(len(scene.materials), -1, np.int32)
    pixels, info, first = [], [], 0
    for m, material in enumerate(scene.materials):
        if material.texture is None or material.kind != "diffuse":
            continue
        if scene.texcoords is None:
            warnings.warn(f"material {material.name!r} has a texture but the mesh has no texture coordinates; "
                          "using the flat albedo", stacklevel=3)
            continue
        image = _load_texture(str(Path(material.texture)))
        if image is None:
            continue
        mat_tex[m] = len(info)
        info.append((first, image.shape[1], image.shape[0]))
        pixels.append(image.reshape(-1, 3))
        first += image.shape[0] * image.shape[1]
    texels = np.concatenate(pixels) if pixels else np.zeros((1, 3), np.float32)
    return mat_tex, texels, np.array(info if info else [(0, 1, 1)], dtype=np.int64)


def _emitters(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Power-weighted emitter triangles: (indices, CDF, per-triangle selection pdf / area)."""
    tri_emit_pdf = np.zeros(len(scene.triangles))
    candidates = scene.emitter_triangles
    areas = scene.triangle_areas(candidates)  # not every triangle's: this runs before every render
    emission = np.array([m.emission for m in scene.materials])[scene.material_ids[candidates]]
    power = areas * emission.mean(axis=1)
    keep = power > 0.0
    candidates, areas, power = candidates[keep], areas[keep], power[keep]
    if len(candidates) == 0:
        return np.zeros(1, np.int32), np.ones(1), tri_emit_pdf
    probability = power / power.sum()
    tri_emit_pdf[candidates] = probability / areas
    cdf = np.cumsum(probability)
    cdf[-1] = 1.0
    return candidates.astype(np.int32), cdf, tri_emit_pdf


def scene_features(scene: Scene, aux: bool = True) -> frozenset[str]:
    """The kernel features a scene needs (see :data:`FEATURES`)."""
    kinds = {m.kind for m in scene.materials}
    needed = set()
    if kinds & {"mirror", "dielectric"}:
        needed.add("specular")
    if scene.texcoords is not None and any(m.texture is not None and m.kind == "diffuse" for m in scene.materials):
        needed.add("textures")
    if scene.normals is not None:
        needed.add("normals")
    if scene.sky is not None and any(c > 0.0 for c in scene.sky.radiance):
        needed.add("sky")
    emitters, _, tri_emit_pdf = _emitters(scene)
    if tri_emit_pdf.any():
        needed.add("emitters")
        if len(emitters) > 1:
            needed.add("emitter_selection")
    if aux:
        needed.add("aux")
    return frozenset(needed)


def _camera_array(camera: Camera, width: int, height: int) -> np.ndarray:
    forward, right, up = camera_basis(camera)
    half_h = np.tan(np.radians(camera.fov) / 2.0)
    return np.concatenate([np.asarray(camera.position, np.float64), forward, right, up, [half_h * width / height, half_h]])


def _pack(scene: Scene, tree: KDTree, vector_spans: bool) -> dict[str, np.ndarray]:
    """The kernel's scene arguments, in order (``span_corners`` empty unless ``vector_spans``)."""
    mat_tex, texels, tex_info = _textures(scene)
    emit_tri, emit_cdf, tri_emit_pdf = _emitters(scene)
    tri_normals = (scene.normals[scene.triangles].reshape(-1, 9) if scene.normals is not None
                   else np.zeros((1, 9), np.float32))
    tri_uv = (scene.texcoords[scene.triangles].reshape(-1, 6) if scene.texcoords is not None
              else np.zeros((1, 6), np.float32))
    return {
        "nodes": tree.node_words, "splits": tree.node_splits, "refs": tree.refs,
        "box": tree.box, "corners": tree.corners,
        "span_corners": tree.span_corners if vector_spans else np.zeros(0, np.float32),
        "watertight": tree.watertight, "tri_mat": scene.material_ids,
        "tri_gnormal": kernels.geometric_normals(tree.corners),
        "tri_normals": np.ascontiguousarray(tri_normals), "tri_uv": np.ascontiguousarray(tri_uv),
        "mat_kind": np.array([_KINDS[m.kind] for m in scene.materials], np.int32),
        "mat_albedo": np.array([m.albedo for m in scene.materials], np.float64),
        "mat_emission": np.array([m.emission for m in scene.materials], np.float64),
        "mat_ior": np.array([m.ior for m in scene.materials], np.float64),
        "mat_tex": mat_tex, "tex_pixels": texels, "tex_info": tex_info,
        "emit_tri": emit_tri, "emit_cdf": emit_cdf, "tri_emit_pdf": tri_emit_pdf,
        "sky_rgb": np.asarray(scene.sky.radiance if scene.sky is not None else (0.0, 0.0, 0.0), np.float64),
    }


def renderer_fingerprint() -> str:
    """Digest of the source of the tree builder, the traversal, the path tracer and this
    module: part of the key of every cached timing of them (:func:`kdtrace.cache.source_fingerprint`)."""
    return source_fingerprint(_kdtree_build, _kdtree_layout, _kdtree_traverse, _packet_traverse, kernels,
                              sys.modules[__name__])


def tile_stride(tiles: int) -> int:
    """The step through the tile indices of :func:`kdtrace._render_kernels.render_tiles`.

    The integer nearest ``0.618 * tiles`` (the golden ratio's fraction) that is coprime
    to ``tiles``, so ``k -> (k * stride) % tiles`` is a permutation whose contiguous
    ranges of ``k`` scatter over the image.
    """
    stride = max(1, round(0.6180339887 * tiles))
    while math.gcd(stride, tiles) != 1:
        stride += 1
    return stride


def _run(flags, packed, cam, width, height, spp, max_depth, rr_depth, seed, first_sample, tile_size, aux, camera_packets,
         shadow_packets, last_ray_shortcut):
    rgb = np.zeros((height, width, 3), np.float32)
    variance = np.zeros((height, width, 3), np.float32)
    shape = (height, width) if aux else (0, 0)
    albedo = np.zeros((*shape, 3), np.float32)
    normal = np.zeros((*shape, 3), np.float32)
    depth = np.zeros(shape, np.float32)
    tiles = -(-width // tile_size) * -(-height // tile_size)
    counts = np.zeros((tiles, 4), np.int64)
    args = (*flags, *packed.values(), cam, width, height, spp, max_depth, rr_depth, np.uint64(seed), first_sample, tile_size,
            tile_stride(tiles), camera_packets, shadow_packets, last_ray_shortcut, rgb, variance, albedo, normal, depth, counts)
    # numba resolves a ``literally`` kernel's argument types anew on every call: 70-100 ms
    # per call, measured on cbox-original (more than a whole 256x256 frame at
    # 1 spp). Once a specialisation exists, its machine code is called directly.
    signature = tuple(numba.types.literal(a) if i in _LITERAL_ARGS else numba.typeof(a) for i, a in enumerate(args))
    compiled = kernels.render_tiles.overloads.get(signature)
    if compiled is None:
        kernels.render_tiles(*args)  # compiles, or loads from numba's cache
    else:
        compiled.entry_point(*args)
    return rgb, variance, albedo, normal, depth, counts.sum(axis=0)


# ------------------------------------------------------------------ public API
def render(
    scene: Scene,
    spp: int | None = None,
    max_depth: int | None = None,
    seed: int | None = None,
    width: int | None = None,
    height: int | None = None,
    variant: str = "local",
    aux: bool = True,
    features: frozenset[str] | set[str] | None = None,
    tile_size: int | None = None,
    camera: Camera | None = None,
    tree: KDTree | None = None,
    first_sample: int = 0,
    camera_packets: bool | None = None,
    shadow_packets: bool | None = None,
    last_ray_shortcut: bool | None = None,
    vector_spans: bool | None = None,
) -> RenderResult:
    """Path trace ``scene`` from its camera on a KD-tree.

    Parameters
    ----------
    scene : Scene
    spp : int, optional
        Samples per pixel (default ``[render] spp``).
    max_depth : int, optional
        Longest path in segments, Mitsuba 3's convention (>= 1, or -1 for unbounded with
        Russian roulette); default ``[render] max_depth``.
    seed : int, optional
        Non-negative key of the counter-based RNG (default ``[render] seed``).
    width, height : int, optional
        Resolution in pixels (default: the camera's).
    variant : {"local", "naive"}
        KD-tree variant (ignored when ``tree`` is given).
    aux : bool
        Also produce the albedo, normal and depth buffers.
    features : set of str, optional
        Kernel features (:data:`FEATURES`); None derives the minimal set from the scene.
        An explicit set must contain every feature the scene needs; ``ALL_FEATURES``
        forces the general kernel. ``"aux"`` is added when ``aux`` is true.
    tile_size : int, optional
        Side of the parallel tiles in pixels (default ``[render] tile_size``); the image
        does not depend on it.
    camera : Camera, optional
        Overrides ``scene.camera`` (used by :func:`render_stereo`).
    tree : KDTree, optional
        A tree already built for ``scene`` (saves the build or cache load).
    first_sample : int
        Index of the first of the ``spp`` samples every pixel takes from its sequence
        (default 0). Renders of disjoint sample ranges are independent, and the
        spp-weighted mean of the ``rgb`` (and ``albedo``) of adjacent ranges is that of
        the render of their union, up to float rounding.
    camera_packets : bool, optional
        Trace camera rays in packets (default ``[render] camera_packets``); False traces
        them one by one, the oracle. The image is the same bit for bit.
    shadow_packets : bool, optional
        Trace the shadow rays from the first hits of a camera packet's rays as one packet of
        occlusion queries (default ``[render] shadow_packets``; watertight trees only). False
        traces them one by one, the oracle. The image is the same bit for bit.
    last_ray_shortcut : bool, optional
        Trace each path's last ray only as far as its radiance needs: the emitter triangles
        one by one, then an any-hit query for what lies before the nearest (or, with a sky,
        for anything), see :func:`kdtrace._render_kernels.last_ray_hit`. Default: on when
        the scene has at most ``[render] last_ray_max_emitters`` emitter triangles. False
        traces the last ray's closest hit, the oracle; the image is the same.
    vector_spans : bool, optional
        Occlusion and closest-hit queries find a node's triangles hit all at once before testing
        those one by one (:func:`kdtrace._kdtree_traverse.span_hits`; watertight trees only); default: the
        tree's (``[kdtree] vector_spans``). False tests them one by one, the oracle; the
        image is the same.

    Returns
    -------
    RenderResult

    Raises
    ------
    ValueError
        Non-positive spp, resolution or tile size, a resolution whose frame buffers
        (:func:`frame_bytes`) do not fit in the memory available (an InsufficientMemoryError),
        bad max_depth, seed or first_sample, NaN in the camera or a material, or
        ``features`` missing something the scene needs.

    Warns
    -----
    UserWarning
        The scene has no emitter and no sky (the image is black), a texture is missing,
        or (with ``aux``) no camera ray hits the scene.
    """
    config = DEFAULT_CONFIG.render
    spp = _positive_int("spp", config.spp if spp is None else spp)
    max_depth = config.max_depth if max_depth is None else max_depth
    if isinstance(max_depth, bool) or not isinstance(max_depth, (int, np.integer)) or (max_depth < 1 and max_depth != -1):
        raise ValueError(f"max_depth must be >= 1 or -1 (unbounded), got {max_depth!r}")
    seed = config.seed if seed is None else seed
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**64:
        raise ValueError(f"seed must be an integer in [0, 2^64), got {seed!r}")
    tile_size = _positive_int("tile_size", config.tile_size if tile_size is None else tile_size)
    if isinstance(first_sample, bool) or not isinstance(first_sample, (int, np.integer)) or not 0 <= first_sample < 2**62:
        raise ValueError(f"first_sample must be an integer in [0, 2^62), got {first_sample!r}")
    first_sample = int(first_sample)
    camera_packets = bool(config.camera_packets if camera_packets is None else camera_packets)
    shadow_packets = bool(config.shadow_packets if shadow_packets is None else shadow_packets)
    if last_ray_shortcut is None:
        last_ray_shortcut = int(scene.emitter_triangles.size) <= config.last_ray_max_emitters
    last_ray_shortcut = bool(last_ray_shortcut)
    camera = scene.camera if camera is None else camera
    _check_camera(camera)
    width = _positive_int("width", camera.width if width is None else width)
    height = _positive_int("height", camera.height if height is None else height)
    _check_materials(scene)

    needed = scene_features(scene, aux)
    if "emitters" not in needed and "sky" not in needed:
        warnings.warn(f"scene {scene.name!r} has no emitter and no sky: the image is black", stacklevel=2)
    if features is None:
        chosen = needed
    else:
        chosen = frozenset(features) | ({"aux"} if aux else set())
        unknown = chosen - ALL_FEATURES
        if unknown:
            raise ValueError(f"unknown features {sorted(unknown)}; known: {list(FEATURES)}")
        if not needed <= chosen:
            raise ValueError(f"scene {scene.name!r} needs features {sorted(needed - chosen)}")
    aux = "aux" in chosen
    _check_image_size(width, height, aux, tile_size)
    tree = build_kdtree(scene, variant) if tree is None else tree
    vector_spans = tree.vector_spans if vector_spans is None else bool(vector_spans) and tree.watertight
    shadow_packets = shadow_packets and tree.watertight
    packed = _pack(scene, tree, vector_spans)
    cam = _camera_array(camera, width, height)
    flags = tuple(name in chosen for name in FEATURES)
    depth_limit = int(max_depth)
    rr_depth = config.rr_depth

    started = time.perf_counter()  # first call compiles (or loads from numba's cache)
    _run(flags, packed, cam, 1, 1, 1, depth_limit, rr_depth, seed, 0, 1, aux, camera_packets, shadow_packets,
         last_ray_shortcut)
    compile_seconds = time.perf_counter() - started
    started = time.perf_counter()
    rgb, variance, albedo, normal, depth, counts = _run(
        flags, packed, cam, width, height, spp, depth_limit, rr_depth, seed, first_sample, tile_size, aux, camera_packets,
        shadow_packets, last_ray_shortcut)
    seconds = time.perf_counter() - started
    if aux and not (depth > 0).any():
        warnings.warn(f"scene {scene.name!r}: no camera ray hits geometry (the camera looks at nothing)",
                      stacklevel=2)

    rays = {"camera": int(counts[kernels.COUNT_CAMERA]), "shadow": int(counts[kernels.COUNT_SHADOW]),
            "bounce": int(counts[kernels.COUNT_BOUNCE])}
    paths = int(counts[kernels.COUNT_PATHS])
    stats = {
        "rays": rays,
        "paths": paths,
        "paths_per_second": paths / seconds if seconds > 0 else float("inf"),
        "rays_per_second": sum(rays.values()) / seconds if seconds > 0 else float("inf"),
        "features": sorted(chosen),
        "kernel": "general" if chosen == ALL_FEATURES else "specialised",
        "compile_seconds": compile_seconds,
        "spp": spp, "first_sample": first_sample, "max_depth": depth_limit, "rr_depth": rr_depth, "seed": int(seed),
        "width": width, "height": height, "tile_size": tile_size, "variant": tree.variant, "camera_packets": camera_packets,
        "shadow_packets": shadow_packets, "last_ray_shortcut": last_ray_shortcut, "vector_spans": vector_spans,
        "threads": numba.get_num_threads(),
    }
    return RenderResult(
        rgb=rgb, variance=variance,
        albedo=albedo if aux else None, normal=normal if aux else None, depth=depth if aux else None,
        seconds=seconds, stats=stats,
    )


def stereo_cameras(camera: Camera, eye_separation: float) -> tuple[Camera, Camera]:
    """Left and right pinholes of a parallel stereo rig (paper appendix).

    Both eyes keep the camera's orientation, fov and resolution and move by half the
    eye separation along the camera's right vector, so the two images differ by a
    horizontal parallax only.
    """
    if not (isinstance(eye_separation, (int, float)) and math.isfinite(eye_separation) and eye_separation > 0.0):
        raise ValueError(f"eye_separation must be a positive number, got {eye_separation!r}")
    _check_camera(camera)
    _, right, _ = camera_basis(camera)
    shift = 0.5 * eye_separation * right

    def moved(sign: float) -> Camera:
        return dataclasses.replace(
            camera,
            position=tuple(float(x) for x in np.asarray(camera.position) + sign * shift),
            look_at=tuple(float(x) for x in np.asarray(camera.look_at) + sign * shift),
        )

    return moved(-1.0), moved(1.0)


def render_stereo(scene: Scene, eye_separation: float | None = None, **kwargs) -> tuple[RenderResult, RenderResult]:
    """Render the left and right images of a stereo pair for a VR headset.

    Parameters
    ----------
    scene : Scene
    eye_separation : float, optional
        Distance between the pinholes, scene units (default ``[render] eye_separation``).
    **kwargs
        Passed to :func:`render` (not ``camera``); both eyes share the seed, so their
        noise is correlated.

    Returns
    -------
    left, right : RenderResult
    """
    if "camera" in kwargs:
        raise ValueError("render_stereo derives both cameras from scene.camera; do not pass camera")
    eye_separation = DEFAULT_CONFIG.render.eye_separation if eye_separation is None else eye_separation
    left_camera, right_camera = stereo_cameras(scene.camera, eye_separation)
    if kwargs.get("tree") is None:
        kwargs["tree"] = build_kdtree(scene, kwargs.pop("variant", "local"))
    return render(scene, camera=left_camera, **kwargs), render(scene, camera=right_camera, **kwargs)
