"""Mitsuba 3 reference renders of a :class:`kdtrace.scene.Scene`, with per-pixel variance.

The very same float32 vertex and int32 index arrays become Mitsuba meshes (built in
memory, no file round trip), one mesh per material. Renders are cached on disk by a
hash of everything they depend on; ``main_reference`` regenerates one from a scene name.

Mapping (all facts checked against Mitsuba 3.9.1, see ``tests/test_mitsuba.py``):

- **Meshes.** ``mi.Mesh(name, vertex_count, face_count, props, has_vertex_normals,
  has_vertex_texcoords)`` then ``mi.traverse(mesh)`` to write ``vertex_positions``,
  ``faces`` (and ``vertex_normals`` / ``vertex_texcoords``) and ``params.update()``.
  ``props`` carries the BSDF and the area emitter. Each material's mesh holds its
  triangles in scene order and the vertices they use (in ascending index order), so
  ``vertex_positions[faces]`` equals ``scene.vertices[scene.triangles]`` bit for bit.
  Zero-area triangles (``Scene.degenerate_mask``) are dropped, exactly as our KD-tree
  drops them: they cannot be hit.
- **Normals and texture coordinates.** When the scene has per-vertex normals, Mitsuba
  shades with them (interpolated shading normals; the geometric normal still comes from
  the winding). Texture coordinates are passed as ``(u, 1 - v)``: Mitsuba's OBJ loader
  flips ``v`` the same way, so OBJ coordinates address the bitmap as in OBJ.
- **BSDFs.** diffuse -> ``diffuse`` (reflectance = albedo, or a ``bitmap`` texture when
  ``Material.texture`` names an existing file and the scene has texture coordinates);
  mirror -> ``conductor`` with ``material="none"`` (perfect reflector,
  ``specular_reflectance`` = albedo); dielectric -> ``dielectric`` (``int_ior`` = ior,
  ``ext_ior`` = 1, ``specular_transmittance`` = albedo). Mitsuba's diffuse and
  conductor are black seen from the back, so both are wrapped in ``twosided``: our
  surfaces scatter on both sides and only emission is one-sided.
- **Emitters.** ``area`` emitters are one-sided and emit on the side the face normal
  ``cross(p1 - p0, p2 - p0)`` points to, i.e. the counter-clockwise front of
  :class:`kdtrace.scene.Material` (with vertex normals, Mitsuba tests the side against
  the shading normal). A sky is a ``constant`` emitter.
- **Camera.** ``perspective`` with ``fov_axis="y"`` and
  ``look_at(position, look_at, up)``; Mitsuba puts image column 0 on the viewer's left
  and row 0 at the top, like our pinhole (no mirroring). ``hdrfilm`` with a ``box``
  filter (each sample lands in exactly one pixel), ``independent`` sampler.
- **Integrator.** ``path`` with the same ``max_depth`` (Mitsuba's convention: 1 = only
  emitters seen directly, 2 = direct lighting; Russian roulette from depth 5). The
  built-in ``moment`` integrator records moments of the *XYZ* colour, from which
  per-channel RGB variance cannot be recovered, so a ten-line Python integrator
  (``kdtrace_rgb_moment``) wraps ``path`` and records the RGB first and second moments
  as AOVs instead. It is vectorised in ``llvm_ad_rgb``; in ``scalar_rgb`` Mitsuba calls
  it per sample (correct, about 10x slower).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from kdtrace.cache import cache_root, compute_once, content_key, load_npz, save_npz
from kdtrace.scene import Camera, Material, Scene
from references.llvm import activate_variant

#: Bump when the conversion or the estimator changes: old cached references become misses.
RECIPE_VERSION = 1
#: Samples (pixels x spp) rendered per pass; bounds the memory of a vectorised pass.
PASS_SAMPLES = 1 << 20
#: A partial render is checkpointed to the cache at most this often (seconds).
CHECKPOINT_SECONDS = 30.0
#: Name under which the RGB moment integrator is registered with Mitsuba.
MOMENT_INTEGRATOR = "kdtrace_rgb_moment"
#: Default folder of ``main_reference``'s EXR/PNG images (relative to the working directory).
DEFAULT_OUTPUT_DIR = Path("out/references")

_registered_variants: set[str] = set()


@dataclass(frozen=True)
class Reference:
    """A Mitsuba reference image with the variance of its per-pixel mean.

    Attributes
    ----------
    rgb : ndarray, float32, shape (H, W, 3)
        Linear RGB radiance, the mean of ``spp`` samples per pixel.
    variance : ndarray, float32, shape (H, W, 3)
        Variance of that mean per pixel and channel: the sample variance divided by spp.
    spp : int
        Samples per pixel.
    seconds : float
        Wall-clock render time (of the original render when loaded from the cache).
    variant : str
        Mitsuba variant that rendered it.
    metadata : dict
        Configuration, versions, cache key and conversion statistics.
    """

    rgb: np.ndarray
    variance: np.ndarray
    spp: int
    seconds: float
    variant: str
    metadata: dict[str, Any]


# ------------------------------------------------------------------------ conversion
def _rgb(value: tuple[float, float, float]) -> dict[str, Any]:
    """A Mitsuba ``rgb`` spectrum of linear RGB ``value``."""
    return {"type": "rgb", "value": [float(c) for c in value]}


def bsdf_dict(material: Material, has_texcoords: bool) -> dict[str, Any]:
    """Mitsuba BSDF description of ``material`` (see the module docstring for the mapping).

    Parameters
    ----------
    material : Material
        The material to convert.
    has_texcoords : bool
        Whether the mesh carries texture coordinates (a texture needs them).

    Returns
    -------
    dict
        A ``load_dict`` description.
    """
    if material.kind == "dielectric":
        return {"type": "dielectric", "int_ior": float(material.ior), "ext_ior": 1.0,
                "specular_transmittance": _rgb(material.albedo)}
    if material.kind == "mirror":
        inner = {"type": "conductor", "material": "none", "specular_reflectance": _rgb(material.albedo)}
    elif material.kind == "diffuse":
        inner = {"type": "diffuse", "reflectance": _diffuse_reflectance(material, has_texcoords)}
    else:
        raise ValueError(f"material {material.name!r}: unknown kind {material.kind!r}")
    return {"type": "twosided", "material": inner}


def _diffuse_reflectance(material: Material, has_texcoords: bool) -> dict[str, Any]:
    """A ``bitmap`` texture when the material's texture is usable, else the flat albedo."""
    if material.texture is None:
        return _rgb(material.albedo)
    if not Path(material.texture).is_file():
        warnings.warn(f"material {material.name!r}: texture {material.texture} not found; using its albedo",
                      stacklevel=3)
        return _rgb(material.albedo)
    if not has_texcoords:
        warnings.warn(f"material {material.name!r}: the scene has no texture coordinates; using its albedo",
                      stacklevel=3)
        return _rgb(material.albedo)
    return {"type": "bitmap", "filename": str(material.texture)}


def sensor_dict(camera: Camera, width: int, height: int, bounds: tuple[np.ndarray, np.ndarray],
                spp: int) -> dict[str, Any]:
    """Mitsuba ``perspective`` sensor matching our pinhole ``camera``.

    Parameters
    ----------
    camera : Camera
        Position, target, up vector and vertical fov (degrees).
    width, height : int
        Image resolution in pixels.
    bounds : (ndarray, ndarray)
        Scene bounding box, used to set clip planes that never cut geometry.
    spp : int
        Sample count of the ``independent`` sampler (per pass).

    Returns
    -------
    dict
        A ``load_dict`` description with an ``hdrfilm`` (box filter) and sampler.
    """
    import mitsuba as mi

    corners = np.array(np.meshgrid(*zip(*bounds, strict=True), indexing="ij")).reshape(3, -1).T
    reach = float(np.max(np.linalg.norm(corners - np.asarray(camera.position), axis=1)))
    far_clip = 2.0 * max(reach, 1e-3)
    return {
        "type": "perspective",
        "fov": float(camera.fov),
        "fov_axis": "y",
        "near_clip": 1e-5 * far_clip,
        "far_clip": far_clip,
        "to_world": mi.ScalarTransform4f().look_at(origin=list(map(float, camera.position)),
                                                  target=list(map(float, camera.look_at)),
                                                  up=list(map(float, camera.up))),
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb", "component_format": "float32"},
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }


def material_triangles(scene: Scene) -> list[tuple[int, np.ndarray]]:
    """Per material, the indices of its non-degenerate triangles (materials without any are left out)."""
    keep = ~scene.degenerate_mask()
    groups = []
    for index in range(len(scene.materials)):
        rows = np.flatnonzero((scene.material_ids == index) & keep)
        if len(rows):
            groups.append((index, rows))
    return groups


def build_mesh(scene: Scene, material_index: int, rows: np.ndarray, name: str) -> Any:
    """One Mitsuba mesh holding triangles ``rows`` of ``scene`` with their material.

    Parameters
    ----------
    scene : Scene
        Source of vertices, triangles, normals, texture coordinates and materials.
    material_index : int
        Index of the material of every triangle in ``rows``.
    rows : ndarray of int
        Triangle indices (non-degenerate), kept in this order.
    name : str
        Mesh id in the Mitsuba scene.

    Returns
    -------
    mitsuba.Mesh
    """
    import mitsuba as mi

    material = scene.materials[material_index]
    used, faces = np.unique(scene.triangles[rows], return_inverse=True)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf_dict(material, scene.texcoords is not None))
    if material.is_emitter:
        props["emitter"] = mi.load_dict({"type": "area", "radiance": _rgb(material.emission)})
    mesh = mi.Mesh(name, len(used), len(rows), props=props, has_vertex_normals=scene.normals is not None,
                   has_vertex_texcoords=scene.texcoords is not None)
    params = mi.traverse(mesh)
    params["vertex_positions"] = scene.vertices[used].ravel()
    params["faces"] = faces.astype(np.uint32).ravel()
    if scene.normals is not None:
        params["vertex_normals"] = scene.normals[used].ravel()
    if scene.texcoords is not None:
        uv = scene.texcoords[used]
        params["vertex_texcoords"] = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1).astype(np.float32).ravel()
    params.update()
    return mesh


def _mesh_name(index: int, material: Material) -> str:
    """A Mitsuba-safe mesh id for material ``index``."""
    return f"mesh{index:04d}_" + re.sub(r"[^A-Za-z0-9_]", "_", material.name)


def _register_moment_integrator(variant: str) -> None:
    """Register ``kdtrace_rgb_moment`` (RGB mean and second moment as AOVs) for ``variant``."""
    import mitsuba as mi

    if variant in _registered_variants:
        return

    class RGBMomentIntegrator(mi.SamplingIntegrator):
        """Wraps a nested integrator; AOVs: the sample's R, G, B and R², G², B²."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.nested = props["nested"]

        def sample(self, scene, sampler, ray, medium=None, active=True):  # noqa: ANN001, ANN201
            radiance, valid, _ = self.nested.sample(scene, sampler, ray, medium, active)
            moments = [radiance.x, radiance.y, radiance.z]
            return radiance, valid, moments + [value * value for value in moments]

        def aov_names(self) -> list[str]:
            return ["m1.R", "m1.G", "m1.B", "m2.R", "m2.G", "m2.B"]

    mi.register_integrator(MOMENT_INTEGRATOR, lambda props: RGBMomentIntegrator(props))
    _registered_variants.add(variant)


def to_mitsuba(scene: Scene, max_depth: int, width: int, height: int, spp: int) -> tuple[Any, dict[str, int]]:
    """Build the Mitsuba scene of ``scene`` in the active variant.

    Parameters
    ----------
    scene : Scene
        The scene (its first camera is used).
    max_depth : int
        Longest path in segments, Mitsuba's ``max_depth`` (>= 1).
    width, height : int
        Image resolution in pixels.
    spp : int
        Samples per pixel of the sampler (per pass).

    Returns
    -------
    (mitsuba.Scene, dict)
        The scene, and conversion counts: meshes, triangles, dropped zero-area triangles.
    """
    import mitsuba as mi

    _register_moment_integrator(mi.variant())
    description: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": MOMENT_INTEGRATOR, "nested": {"type": "path", "max_depth": int(max_depth)}},
        "sensor": sensor_dict(scene.camera, width, height, scene.bounds, spp),
    }
    if scene.sky is not None:
        description["sky"] = {"type": "constant", "radiance": _rgb(scene.sky.radiance)}
    groups = material_triangles(scene)
    for index, rows in groups:
        name = _mesh_name(index, scene.materials[index])
        description[name] = build_mesh(scene, index, rows, name)
    kept = sum(len(rows) for _, rows in groups)
    counts = {"meshes": len(groups), "triangles": kept, "zero_area_dropped": int(len(scene.triangles) - kept)}
    return mi.load_dict(description), counts


# ------------------------------------------------------------------------- rendering
def _pass_plan(spp: int, pixels: int) -> list[int]:
    """Samples per pixel of each pass: at most :data:`PASS_SAMPLES` samples per pass."""
    per_pass = max(1, min(spp, PASS_SAMPLES // pixels))
    plan = [per_pass] * (spp // per_pass)
    if spp % per_pass:
        plan.append(spp % per_pass)
    return plan


def _pass_seed(seed: int, index: int) -> int:
    """A 32-bit sampler seed for pass ``index`` of a render seeded with ``seed`` (hashed, so streams differ)."""
    return int(content_key("mitsuba-pass", seed, index)[:8], 16)


def _render_pass(mitsuba_scene: Any, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One pass: per-pixel mean and mean square of the RGB samples, float64 (H, W, 3) each."""
    import mitsuba as mi

    image = np.array(mi.render(mitsuba_scene, spp=spp, seed=seed), dtype=np.float64)
    if image.shape[-1] != 9:
        raise RuntimeError(f"Mitsuba returned {image.shape[-1]} channels, expected RGB + 6 moment AOVs")
    return image[..., 3:6], image[..., 6:9]


def reference_key(scene: Scene, spp: int, max_depth: int, seed: int, width: int, height: int,
                  variant: str) -> str:
    """Cache key of a reference: SHA-256 of everything that changes it (see module docstring)."""
    import mitsuba as mi

    return content_key("mitsuba-reference", RECIPE_VERSION, scene.content_hash(),
                       dataclasses.asdict(scene.camera), [width, height], spp, max_depth, seed,
                       mi.__version__, variant)


def _cache_path(scene: Scene, key: str, suffix: str = "") -> Path:
    """Where the reference with ``key`` is cached (``suffix`` for the partial checkpoint)."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", scene.name)
    return cache_root() / "mitsuba" / f"{stem}-{key[:24]}{suffix}.npz"


def _from_cache(path: Path, key: str) -> Reference | None:
    """The cached reference at ``path`` when it exists and carries ``key``; else None."""
    loaded = load_npz(path)
    if loaded is None or loaded[1].get("key") != key:
        return None
    arrays, metadata = loaded
    return Reference(arrays["rgb"], arrays["variance"], int(metadata["spp"]), float(metadata["seconds"]),
                     metadata["variant"], metadata)


def _validate(spp: int, max_depth: int, seed: int, width: int, height: int) -> None:
    """Raise ValueError for settings Mitsuba cannot render or that leave no variance."""
    if spp < 2:
        raise ValueError(f"spp must be >= 2 (a variance needs two samples), got {spp}")
    if max_depth < 1:
        raise ValueError(f"max_depth must be >= 1 (Mitsuba's convention), got {max_depth}")
    if not 0 <= seed < 2**32:
        raise ValueError(f"seed must be in [0, 2**32), got {seed}")
    if width < 1 or height < 1:
        raise ValueError(f"resolution must be positive, got {width}x{height}")


def render_reference(scene: Scene, spp: int, max_depth: int, seed: int, width: int | None = None,
                     height: int | None = None, variant: str | None = None, cache: bool = True) -> Reference:
    """Render (or load from the cache) the Mitsuba reference of ``scene``'s first camera.

    Parameters
    ----------
    scene : Scene
        The scene; its first camera is used.
    spp : int
        Samples per pixel (>= 2).
    max_depth : int
        Longest path in segments, Mitsuba's convention (2 = direct lighting only).
    seed : int
        Base seed in [0, 2**32); each pass derives its own sampler seed from it.
    width, height : int, optional
        Resolution in pixels; default the camera's. The vertical fov is kept.
    variant : {"llvm_ad_rgb", "scalar_rgb"}, optional
        Default: ``llvm_ad_rgb`` when usable, else ``scalar_rgb`` with a warning.
    cache : bool
        Load from / save to ``cache_root() / "mitsuba"`` (default True). False renders
        afresh and writes nothing.

    Returns
    -------
    Reference
        Mean image and variance of the mean (linear RGB), with provenance.

    Notes
    -----
    The render runs in passes of at most :data:`PASS_SAMPLES` samples, with a tqdm
    progress bar in samples per pixel. With ``cache=True`` the running sums are
    checkpointed every :data:`CHECKPOINT_SECONDS` seconds, so an interrupted render
    resumes where it stopped (same pass seeds, same result).
    """
    width = scene.camera.width if width is None else int(width)
    height = scene.camera.height if height is None else int(height)
    _validate(spp, max_depth, seed, width, height)
    variant = activate_variant(variant)
    key = reference_key(scene, spp, max_depth, seed, width, height, variant)
    path = _cache_path(scene, key)
    if not cache:
        return _render(scene, spp, max_depth, seed, width, height, variant, key, None)

    def render_and_save() -> Reference:
        reference = _render(scene, spp, max_depth, seed, width, height, variant, key,
                            _cache_path(scene, key, ".partial"))
        save_npz(path, {"rgb": reference.rgb, "variance": reference.variance}, reference.metadata)
        _cache_path(scene, key, ".partial").unlink(missing_ok=True)
        return reference

    # claimed: a second process waits for the render (and its checkpoint) instead of doing it again
    return compute_once(path, lambda: _from_cache(path, key), render_and_save)


def _render(scene: Scene, spp: int, max_depth: int, seed: int, width: int, height: int, variant: str,
            key: str, checkpoint: Path | None) -> Reference:
    """Render all passes (resuming from ``checkpoint`` when present) and build the Reference."""
    import drjit as dr
    import mitsuba as mi

    plan = _pass_plan(spp, width * height)
    mitsuba_scene, counts = to_mitsuba(scene, max_depth, width, height, plan[0])
    state = _resume(checkpoint, key, (height, width, 3))
    start = time.perf_counter() - state["seconds"]
    last_save = time.perf_counter()
    with tqdm(total=spp, initial=sum(plan[: state["passes"]]), unit="spp", desc=f"mitsuba {scene.name}",
              disable=None, leave=False) as progress:
        for index in range(state["passes"], len(plan)):
            mean, square = _render_pass(mitsuba_scene, plan[index], _pass_seed(seed, index))
            state["sum"] += plan[index] * mean
            state["sum_sq"] += plan[index] * square
            state["passes"] = index + 1
            progress.update(plan[index])
            due = time.perf_counter() - last_save > CHECKPOINT_SECONDS
            if checkpoint is not None and index + 1 < len(plan) and due:
                state["seconds"] = time.perf_counter() - start
                _save_checkpoint(checkpoint, key, state)
                last_save = time.perf_counter()
    seconds = time.perf_counter() - start
    rgb, variance = _mean_and_variance(state["sum"], state["sum_sq"], spp)
    metadata = {
        "key": key, "recipe_version": RECIPE_VERSION, "scene": scene.name, "scene_hash": scene.content_hash(),
        "camera": dataclasses.asdict(scene.camera), "width": width, "height": height, "spp": spp,
        "max_depth": max_depth, "seed": seed, "passes": len(plan), "seconds": seconds,
        "variant": variant, "mitsuba_version": mi.__version__, "drjit_version": dr.__version__,
        "libllvm": os.environ.get("DRJIT_LIBLLVM_PATH") if variant.startswith("llvm") else None,
        **counts,
    }
    metadata = json.loads(json.dumps(metadata))  # the form the cache returns (tuples become lists)
    return Reference(rgb, variance, spp, seconds, variant, metadata)


def _mean_and_variance(total: np.ndarray, total_sq: np.ndarray, spp: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of the mean (unbiased sample variance / spp) from sums over ``spp`` samples."""
    mean = total / spp
    variance = np.maximum(total_sq / spp - mean * mean, 0.0) / (spp - 1)
    return mean.astype(np.float32), variance.astype(np.float32)


def _resume(checkpoint: Path | None, key: str, shape: tuple[int, int, int]) -> dict[str, Any]:
    """Running sums from a checkpoint of the render ``key``, or fresh zeros."""
    fresh = {"sum": np.zeros(shape), "sum_sq": np.zeros(shape), "passes": 0, "seconds": 0.0}
    loaded = None if checkpoint is None else load_npz(checkpoint)
    if loaded is None or loaded[1].get("key") != key or loaded[0]["sum"].shape != shape:
        return fresh
    arrays, metadata = loaded
    return {"sum": arrays["sum"], "sum_sq": arrays["sum_sq"], "passes": int(metadata["passes"]),
            "seconds": float(metadata["seconds"])}


def _save_checkpoint(path: Path, key: str, state: dict[str, Any]) -> None:
    """Atomically save the running sums of an unfinished render."""
    save_npz(path, {"sum": state["sum"], "sum_sq": state["sum_sq"]},
             {"key": key, "passes": state["passes"], "seconds": state["seconds"]})


# ---------------------------------------------------------------------- images, CLI
def write_images(reference: Reference, stem: Path) -> list[Path]:
    """Write ``stem.exr`` (linear RGB), ``stem.variance.exr`` and ``stem.png`` (sRGB preview).

    Parameters
    ----------
    reference : Reference
        The render to write.
    stem : Path
        Output path without suffix.

    Returns
    -------
    list of Path
        The files written (each atomically).
    """
    from kdtrace.imageio import write_exr, write_png

    paths = [stem.with_name(stem.name + suffix) for suffix in (".exr", ".variance.exr", ".png")]
    write_exr(paths[0], reference.rgb)
    write_exr(paths[1], reference.variance)
    write_png(paths[2], reference.rgb)
    return paths


def main_reference(scene_name: str, spp: int, max_depth: int, seed: int, width: int | None = None,
                   height: int | None = None, force: bool = False,
                   output_dir: str | Path = DEFAULT_OUTPUT_DIR) -> Reference:
    """Load a scene by name, render or fetch its reference, and write EXR + PNG images.

    Parameters
    ----------
    scene_name : str
        A name for :func:`kdtrace.scenes.load_scene` (e.g. ``"cbox-original"``).
    spp, max_depth, seed, width, height
        As in :func:`render_reference`.
    force : bool
        Re-render even when the cache holds this reference (and overwrite it).
    output_dir : str or Path
        Folder of the images, named ``<scene>-<W>x<H>-<spp>spp-d<depth>-s<seed>``.

    Returns
    -------
    Reference
    """
    from kdtrace.scenes import load_scene

    scene = load_scene(scene_name)
    reference = render_reference(scene, spp, max_depth, seed, width, height, cache=not force)
    if force:
        key = reference.metadata["key"]
        save_npz(_cache_path(scene, key), {"rgb": reference.rgb, "variance": reference.variance},
                 reference.metadata)
    height_px, width_px = reference.rgb.shape[:2]
    stem = Path(output_dir) / f"{scene.name}-{width_px}x{height_px}-{spp}spp-d{max_depth}-s{seed}"
    write_images(reference, stem)
    return reference

