"""Scene descriptions: TOML files naming meshes, transforms, materials, lights and cameras.

How to use::

    from kdtrace.scenes import list_scenes, load_scene
    list_scenes()                     # ['bunny', 'car', 'cbox-empty', ...]
    scene = load_scene("cbox-sphere") # scenes/cbox-sphere.toml of the repository
    scene = load_scene("my/scene.toml")
    scene = load_scene("stanford-bunny/bunny.obj")  # bare mesh: default camera, sky if unlit

A description (all keys optional except ``mesh``)::

    name = "car"                      # default: the file stem
    description = "free text"

    [[mesh]]
    file = "cornell-box/CornellBox-Empty-RG.obj"   # found on the search path
    transform = { scale = 0.6, rotate = { axis = [0, 1, 0], degrees = -30 }, translate = [0, 0.42, 0] }
    # rotate = { euler = [x, y, z] } in degrees, applied about x, then y, then z.
    # Order: scale (scalar or 3 values), then rotate, then translate.
    material_override = "dragon"      # every triangle of this mesh gets [materials.dragon]

    [materials.light]                 # overrides fields of every material of that name,
    emission = [17, 12, 4]            # or defines one for material_override
    # keys: kind ("diffuse" | "mirror" | "dielectric"), albedo, emission, ior

    [sky]
    radiance = [1, 1, 1]

    [[light]]                         # extra area light: a quad, corners counter-clockwise
    corners = [[x, y, z], ...]        # seen from the lit side; 4 corners
    emission = [r, g, b]

    [[camera]]                        # the first is the default camera
    position = [0, 1, 3.9]
    look_at = [0, 1, 0]
    up = [0, 1, 0]                    # default +y
    fov = 39.3                        # vertical, degrees (default 40)
    width = 512
    height = 512

Meshes are concatenated into one scene; identical materials are shared. When some meshes
have shading normals (texture coordinates) and others not, the others get area-weighted
vertex normals (zero texture coordinates). A scene without any camera gets
:func:`default_camera`; a scene without any emitter and without a sky gets a constant
white sky (:data:`DEFAULT_SKY_RADIANCE`) so it is lit.

Mesh files are looked up (:func:`scene_search_path`) in: the folders passed as
``search_path``, the description's own folder, the repository's ``scenes/``, each folder
of ``$KDTRACE_SCENES`` (``os.pathsep``-separated), ``../shared/scenes`` beside the
repository, and the current directory.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import kdtrace
from kdtrace.io import SceneError, area_weighted_vertex_normals, is_dir, is_file, load_mesh
from kdtrace.scene import Camera, Material, Scene, Sky

REPOSITORY_ROOT = Path(kdtrace.__file__).resolve().parents[1]
#: Folder of the scene descriptions shipped with the repository.
SCENES_DIRECTORY = REPOSITORY_ROOT / "scenes"
#: Shared data folder beside the repository (``../shared/scenes``).
SHARED_SCENES_DIRECTORY = REPOSITORY_ROOT.parent / "shared" / "scenes"
#: Environment variable with extra mesh folders, separated by ``os.pathsep``.
SCENES_ENV = "KDTRACE_SCENES"
#: Radiance of the sky added to scenes that have no light at all.
DEFAULT_SKY_RADIANCE = (1.0, 1.0, 1.0)
MESH_SUFFIXES = (".obj", ".ply")
#: Largest magnitude of a number in a description: scenes are float32.
FLOAT32_MAX = float(np.finfo(np.float32).max)

_TOP_KEYS = {"name", "description", "mesh", "materials", "sky", "light", "camera"}
_MESH_KEYS = {"file", "transform", "material_override"}
_TRANSFORM_KEYS = {"scale", "rotate", "translate"}
_MATERIAL_KEYS = {"kind", "albedo", "emission", "ior"}
_LIGHT_KEYS = {"corners", "emission"}
_CAMERA_KEYS = {f.name for f in dataclasses.fields(Camera)}


# ------------------------------------------------------------------------- search path
def scene_search_path(search_path: Sequence[str | Path] | None = None) -> list[Path]:
    """Folders searched for mesh files, in order (see the module docstring)."""
    folders = [Path(p) for p in search_path or ()]
    folders.append(SCENES_DIRECTORY)
    folders += [Path(p) for p in os.environ.get(SCENES_ENV, "").split(os.pathsep) if p]
    if SHARED_SCENES_DIRECTORY.is_dir():
        folders.append(SHARED_SCENES_DIRECTORY)
    folders.append(Path.cwd())
    return folders


def find_file(name: str | Path, search_path: Sequence[str | Path] | None = None) -> Path:
    """Path of ``name``: itself when absolute, else the first hit on :func:`scene_search_path`.

    Raises
    ------
    SceneError
        Naming every place looked.
    """
    name = Path(name)
    candidates = [name] if name.is_absolute() else [folder / name for folder in scene_search_path(search_path)]
    for candidate in candidates:
        if is_file(candidate):
            return candidate
    places = "\n  ".join(str(c) for c in candidates)
    raise SceneError(f"{name}: file not found; looked in:\n  {places}")


def list_scenes() -> list[str]:
    """Names of the scene descriptions in the repository's ``scenes/`` folder."""
    return sorted(p.stem for p in SCENES_DIRECTORY.glob("*.toml"))


# ------------------------------------------------------------------------------ pieces
def default_camera(vertices: np.ndarray) -> Camera:
    """Camera on the +z side of the bounding box, looking at its centre, up +y.

    The bounding sphere of ``vertices`` fits the :class:`Camera` default field of view.
    """
    lower = np.min(vertices, axis=0).astype(np.float64)
    upper = np.max(vertices, axis=0).astype(np.float64)
    centre = 0.5 * (lower + upper)
    radius = 0.5 * float(np.linalg.norm(upper - lower)) or 1.0
    fov = Camera.__dataclass_fields__["fov"].default
    distance = radius / math.sin(math.radians(fov) / 2.0)
    position = centre + np.array([0.0, 0.0, distance])
    return Camera(position=tuple(map(float, position)), look_at=tuple(map(float, centre)))


def _vector(value: object, length: int, what: str, origin: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != length or not all(isinstance(v, int | float) for v in value):
        raise SceneError(f"{origin}: {what} must be a list of {length} numbers, got {value!r}")
    if not all(math.isfinite(v) and abs(v) <= FLOAT32_MAX for v in value):
        raise SceneError(f"{origin}: {what} must be finite (and within the float32 range), got {value!r}")
    return tuple(float(v) for v in value)


def _number(value: object, what: str, origin: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not (math.isfinite(value) and abs(value) <= FLOAT32_MAX):
        raise SceneError(f"{origin}: {what} must be a finite number, got {value!r}")
    return float(value)


def _check_keys(table: object, allowed: set[str], what: str, origin: str) -> dict:
    if not isinstance(table, dict):
        raise SceneError(f"{origin}: {what} must be a table, got {table!r}")
    unknown = set(table) - allowed
    if unknown:
        raise SceneError(f"{origin}: unknown key(s) {sorted(unknown)} in {what}; known: {sorted(allowed)}")
    return table


def _rotation(spec: object, origin: str) -> np.ndarray:
    """3x3 rotation from ``{axis, degrees}`` or ``{euler = [x, y, z]}`` (degrees)."""
    spec = _check_keys(spec, {"axis", "degrees", "euler"}, "transform.rotate", origin)
    if "euler" in spec and spec.keys() == {"euler"}:
        matrix = np.eye(3)
        for axis, degrees in zip(np.eye(3), _vector(spec["euler"], 3, "rotate.euler", origin), strict=True):
            matrix = _axis_angle(axis, degrees) @ matrix
        return matrix
    if spec.keys() == {"axis", "degrees"}:
        axis = np.array(_vector(spec["axis"], 3, "rotate.axis", origin))
        if not np.abs(axis).max() > 0.0:
            raise SceneError(f"{origin}: rotate.axis must not be zero")
        with np.errstate(over="ignore", under="ignore"):
            if not 0.0 < np.linalg.norm(axis) < np.inf:
                axis /= np.abs(axis).max()  # the norm over- or underflowed
        return _axis_angle(axis / np.linalg.norm(axis), _number(spec["degrees"], "rotate.degrees", origin))
    raise SceneError(f"{origin}: transform.rotate needs either 'axis' and 'degrees', or 'euler'")


def _axis_angle(axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rodrigues rotation matrix about a unit ``axis``."""
    angle = math.radians(degrees)
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross


def _transformed(scene: Scene, spec: object, origin: str) -> Scene:
    """``scene`` scaled, then rotated, then translated (normals and winding kept consistent)."""
    spec = _check_keys(spec, _TRANSFORM_KEYS, "transform", origin)
    scale = spec.get("scale", 1.0)
    scale = np.array(_vector([scale] * 3, 3, "transform.scale", origin) if isinstance(scale, int | float)
                     else _vector(scale, 3, "transform.scale", origin))
    if np.any(scale == 0.0):
        raise SceneError(f"{origin}: transform.scale must not be zero")
    rotation = _rotation(spec["rotate"], origin) if "rotate" in spec else np.eye(3)
    translate = np.array(_vector(spec.get("translate", [0, 0, 0]), 3, "transform.translate", origin))
    vertices = (scene.vertices.astype(np.float64) * scale) @ rotation.T + translate
    if not np.all(np.abs(vertices) <= FLOAT32_MAX):
        raise SceneError(f"{origin}: transform moves vertices beyond the float32 range (scale {scale.tolist()}, "
                         f"translate {translate.tolist()})")
    normals = None
    if scene.normals is not None:
        with np.errstate(over="ignore"):
            normals = scene.normals.astype(np.float64) / scale
        if not np.all(np.isfinite(normals)):  # a tiny scale: the same directions without the overflow
            normals = scene.normals.astype(np.float64) * (np.abs(scale).min() / scale)
        normals = normals @ rotation.T
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    triangles = scene.triangles[:, [0, 2, 1]] if np.prod(scale) < 0 else scene.triangles  # mirrored: keep CCW front
    return dataclasses.replace(scene, vertices=vertices, triangles=triangles, normals=normals)


def _material_fields(entry: object, name: str, origin: str) -> dict[str, object]:
    entry = _check_keys(entry, _MATERIAL_KEYS, f"[materials.{name}]", origin)
    fields: dict[str, object] = {}
    if "kind" in entry:
        if entry["kind"] not in ("diffuse", "mirror", "dielectric"):
            raise SceneError(f"{origin}: [materials.{name}] kind must be diffuse, mirror or dielectric")
        fields["kind"] = entry["kind"]
    for key in ("albedo", "emission"):
        if key in entry:
            fields[key] = _vector(entry[key], 3, f"[materials.{name}] {key}", origin)
    if "albedo" in fields and not all(0.0 <= c <= 1.0 for c in fields["albedo"]):
        raise SceneError(f"{origin}: [materials.{name}] albedo must lie in [0, 1]")
    if "emission" in fields and min(fields["emission"]) < 0.0:
        raise SceneError(f"{origin}: [materials.{name}] emission must not be negative")
    if "ior" in entry:
        if not isinstance(entry["ior"], int | float) or not 0.0 < entry["ior"] <= FLOAT32_MAX:
            raise SceneError(f"{origin}: [materials.{name}] ior must be a positive finite number")
        fields["ior"] = float(entry["ior"])
    return fields


def _light_quad(entry: object, index: int, origin: str) -> Scene:
    entry = _check_keys(entry, _LIGHT_KEYS, f"[[light]] {index}", origin)
    if set(entry) != _LIGHT_KEYS:
        raise SceneError(f"{origin}: [[light]] {index} needs 'corners' and 'emission'")
    corners = entry["corners"]
    if not isinstance(corners, list) or len(corners) != 4:
        raise SceneError(f"{origin}: [[light]] {index} corners must be a list of 4 points")
    vertices = np.array([_vector(c, 3, f"[[light]] {index} corner", origin) for c in corners])
    emission = _vector(entry["emission"], 3, f"[[light]] {index} emission", origin)
    if min(emission) < 0.0 or max(emission) <= 0.0:
        raise SceneError(f"{origin}: [[light]] {index} emission must be non-negative and not all zero")
    material = Material(f"light_{index}", albedo=(0.0, 0.0, 0.0), emission=emission)
    return Scene(
        name=f"light_{index}",
        vertices=vertices,
        triangles=np.array([[0, 1, 2], [0, 2, 3]]),
        material_ids=np.zeros(2),
        materials=[material],
        sources=[origin],
    )


def _camera(entry: object, index: int, origin: str) -> Camera:
    entry = _check_keys(entry, _CAMERA_KEYS, f"[[camera]] {index}", origin)
    values = dict(entry)
    for key in ("position", "look_at", "up"):
        if key in values:
            values[key] = _vector(values[key], 3, f"[[camera]] {index} {key}", origin)
    try:
        return Camera(**values)
    except (TypeError, ValueError) as error:
        raise SceneError(f"{origin}: [[camera]] {index}: {error}") from None


def merge(parts: Sequence[Scene], name: str) -> Scene:
    """One scene holding the triangles of all ``parts`` (no cameras, no sky).

    Identical materials are shared; missing normals / texture coordinates are filled as
    described in the module docstring.
    """
    index: dict[Material, int] = {}
    vertices, triangles, material_ids, normals, texcoords = [], [], [], [], []
    with_normals = any(p.normals is not None for p in parts)
    with_texcoords = any(p.texcoords is not None for p in parts)
    offset = 0
    for part in parts:
        remap = np.array([index.setdefault(m, len(index)) for m in part.materials])
        vertices.append(part.vertices)
        triangles.append(part.triangles.astype(np.int64) + offset)
        material_ids.append(remap[part.material_ids])
        if with_normals:
            normals.append(part.normals if part.normals is not None else area_weighted_vertex_normals(part.vertices, part.triangles))
        if with_texcoords:
            texcoords.append(part.texcoords if part.texcoords is not None else np.zeros((len(part.vertices), 2)))
        offset += len(part.vertices)
    return Scene(
        name=name,
        vertices=np.concatenate(vertices),
        triangles=np.concatenate(triangles),
        material_ids=np.concatenate(material_ids),
        materials=list(index),
        normals=np.concatenate(normals) if with_normals else None,
        texcoords=np.concatenate(texcoords) if with_texcoords else None,
        sources=[source for part in parts for source in part.sources],
    )


def _finish(scene: Scene, cameras: list[Camera], sky: Sky | None) -> Scene:
    """Add the default camera and sky where the scene has none (see the module docstring)."""
    scene.cameras = cameras or [default_camera(scene.vertices)]
    scene.sky = sky if sky is not None or len(scene.emitter_triangles) else Sky(DEFAULT_SKY_RADIANCE)
    return scene


# --------------------------------------------------------------------------- load scene
def _load_description(path: Path, search_path: Sequence[str | Path] | None, use_cache: bool) -> Scene:
    origin = str(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise SceneError(f"{path}: cannot read scene description ({error.strerror or error})") from None
    try:
        description = tomllib.loads(data.decode("utf-8-sig"))  # a byte order mark is dropped
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        raise SceneError(f"{path}:{line}: invalid TOML (not UTF-8: {error.reason} at byte {error.start})") from None
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: invalid TOML ({error})") from None
    except RecursionError:
        raise SceneError(f"{path}: invalid TOML (arrays or tables nested too deeply)") from None
    _check_keys(description, _TOP_KEYS, "the scene description", origin)
    meshes = description.get("mesh")
    if not isinstance(meshes, list) or not meshes:
        raise SceneError(f"{path}: a scene needs at least one [[mesh]] with a 'file'")
    material_entries = description.get("materials", {})
    if not isinstance(material_entries, dict):
        raise SceneError(f"{path}: [materials] must be a table of [materials.NAME] tables")
    overrides = {name: _material_fields(entry, name, origin) for name, entry in material_entries.items()}
    used_overrides: set[str] = set()
    folders = [*(search_path or ()), path.parent]
    parts = []
    for number, entry in enumerate(meshes):
        entry = _check_keys(entry, _MESH_KEYS, f"[[mesh]] {number}", origin)
        if not isinstance(entry.get("file"), str):
            raise SceneError(f"{path}: [[mesh]] {number} needs a 'file' string")
        part = load_mesh(find_file(entry["file"], folders), use_cache=use_cache)
        if "transform" in entry:
            part = _transformed(part, entry["transform"], f"{origin} [[mesh]] {number}")
        override = entry.get("material_override")
        if override is not None:
            if not isinstance(override, str) or override not in overrides:
                raise SceneError(f"{path}: [[mesh]] {number} material_override {override!r} is not defined in [materials]")
            used_overrides.add(override)
            material = Material(override, **overrides[override])
            part = dataclasses.replace(part, materials=[material], material_ids=np.zeros(len(part.triangles)))
        else:
            renamed = [dataclasses.replace(m, **overrides[m.name]) if m.name in overrides else m for m in part.materials]
            used_overrides.update(m.name for m in part.materials if m.name in overrides)
            part = dataclasses.replace(part, materials=renamed)
        parts.append(part)
    unused = sorted(set(overrides) - used_overrides)
    if unused:
        raise SceneError(f"{path}: [materials] {unused} match no material of the meshes and no material_override")
    lights = description.get("light", [])
    if not isinstance(lights, list):
        raise SceneError(f"{path}: 'light' must be an array of tables ([[light]])")
    parts += [_light_quad(entry, number, origin) for number, entry in enumerate(lights)]
    name = description.get("name", path.stem)
    if not isinstance(name, str):
        raise SceneError(f"{path}: name must be a string")
    scene = merge(parts, name)
    scene.sources.insert(0, str(path))
    sky = None
    if "sky" in description:
        sky_entry = _check_keys(description["sky"], {"radiance"}, "[sky]", origin)
        radiance = _vector(sky_entry.get("radiance"), 3, "[sky] radiance", origin)
        if min(radiance) < 0.0:
            raise SceneError(f"{path}: [sky] radiance must not be negative")
        sky = Sky(radiance)
    camera_entries = description.get("camera", [])
    if not isinstance(camera_entries, list):
        raise SceneError(f"{path}: 'camera' must be an array of tables ([[camera]])")
    cameras = [_camera(entry, number, origin) for number, entry in enumerate(camera_entries)]
    return _finish(scene, cameras, sky)


def load_scene(
    name_or_path: str | Path,
    *,
    search_path: Sequence[str | Path] | None = None,
    use_cache: bool = True,
) -> Scene:
    """Load a scene by name, from a ``.toml`` description, or from a bare ``.obj``/``.ply``.

    Parameters
    ----------
    name_or_path : str or Path
        A name from :func:`list_scenes`, a path to a ``.toml`` description, or a mesh
        file (found directly or on the search path).
    search_path : sequence of paths, optional
        Folders searched for mesh files before the default ones.
    use_cache : bool
        Use the parsed-mesh cache of :mod:`kdtrace.io` (default True).

    Returns
    -------
    Scene
        With at least one camera; lit by its emitters and/or a sky.

    Raises
    ------
    SceneError
        Unknown name (the message lists the available ones), a directory (the message
        lists the scene and mesh files inside it), missing or malformed files.
    """
    path = Path(name_or_path)
    suffix = path.suffix.lower()
    if suffix == ".toml":
        return _load_description(path, search_path, use_cache)
    if suffix in MESH_SUFFIXES:
        mesh = load_mesh(find_file(path, search_path), use_cache=use_cache)
        return _finish(mesh, [], None)
    description = SCENES_DIRECTORY / f"{name_or_path}.toml"
    if is_file(description):
        return _load_description(description, search_path, use_cache)
    candidates = [path] if path.is_absolute() else [folder / path for folder in scene_search_path(search_path)]
    folder = next((c for c in candidates if is_dir(c)), None)
    if folder is not None:
        raise SceneError(_directory_message(path, folder))
    raise SceneError(f"unknown scene {str(name_or_path)!r}; available: {', '.join(list_scenes())}")


def _directory_message(path: Path, folder: Path) -> str:
    """Why a directory is not a scene, with the loadable files directly inside it as a hint."""
    accepted = f"a scene name ({', '.join(list_scenes())}), a .toml description or an .obj/.ply mesh file"
    files = sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in (".toml", *MESH_SUFFIXES))
    if not files:
        hint = "it holds no .toml, .obj or .ply file"
    else:
        base = path if path.is_dir() else folder  # a name that loads from where the caller is
        shown = ", ".join(str(base / name) for name in files[:10])
        hint = f"files in it: {shown}" + (f" and {len(files) - 10} more" if len(files) > 10 else "")
    return f"{str(path)!r} is a directory ({folder.resolve()}), not a scene; load_scene takes {accepted}; {hint}"
