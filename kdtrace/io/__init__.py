"""Mesh file loaders (OBJ + MTL, PLY) producing :class:`kdtrace.scene.Scene` objects.

How to use::

    from kdtrace.io import load_mesh
    scene = load_mesh("../shared/scenes/cornell-box/CornellBox-Original.obj")  # cached after the first call

``load_mesh`` dispatches on the suffix to :func:`kdtrace.io.obj.read_obj` or
:func:`kdtrace.io.ply.read_ply` and caches the parsed arrays as ``.npz`` in the cache
directory (``KDTRACE_CACHE`` or ``DEFAULT_CONFIG.cache.directory``, sub-folder
``meshes``), keyed by the SHA-256 of the resolved path, of the source bytes, of every
file it depends on (``.mtl``, material side-car) and of :data:`LOADER_VERSION`. The scenes returned by the
loaders have no camera and no sky; :mod:`kdtrace.scenes` adds those.

Every bad input raises :class:`SceneError` naming the file (and the line, for text
formats); recoverable oddities are reported once per file as :class:`SceneWarning`, and
are re-emitted on a cache hit so a cached load warns exactly like a cold one.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from kdtrace.cache import atomic_write, cache_root, compute_once
from kdtrace.scene import Material, Scene

#: Bumped whenever a loader's output changes, so stale cache entries are never read.
LOADER_VERSION = "kdtrace-io-2"

#: Environment variable overriding the cache directory.


#: Largest finite float32: vertex positions and texture coordinates must lie within it.
FLOAT32_MAX = float(np.finfo(np.float32).max)


class SceneError(ValueError):
    """A scene or mesh file is missing, unreadable or malformed (message names file and line)."""


class SceneWarning(UserWarning):
    """A recoverable oddity in a scene file (unknown key, missing material, degenerate face)."""


def read_source(path: str | Path) -> bytes:
    """Bytes of ``path``, or a :class:`SceneError` naming it when missing or unreadable."""
    path = Path(path)
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise SceneError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise SceneError(f"{path}: is a directory, not a file") from None
    except OSError as error:
        raise SceneError(f"{path}: cannot read file ({error.strerror or error})") from None


def is_file(path: Path) -> bool:
    """``path.is_file()``, but False where the system cannot look the name up (too long a name)."""
    try:
        return path.is_file()
    except (OSError, ValueError):
        return False


def is_dir(path: Path) -> bool:
    """``path.is_dir()``, but False where the system cannot look the name up (too long a name)."""
    try:
        return path.is_dir()
    except (OSError, ValueError):
        return False


def decode_text(data: bytes) -> str:
    """Text of an OBJ or MTL file's bytes, with LF line ends.

    UTF-8, a leading byte order mark dropped; UTF-16 after a UTF-16 byte order mark.
    Bytes that are not UTF-8 (Latin-1 names) are kept as surrogate escapes, so a name
    still finds the file it names.
    """
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        text = data.decode("utf-16", "replace")
    else:
        text = data.decode("utf-8", "surrogateescape").removeprefix("\ufeff")
    return text.replace("\r\n", "\n").replace("\r", "\n")


class WarningLog:
    """Collects warnings of one file, at most one per topic, and emits them.

    The messages are kept so that a cache entry can replay them.
    """

    def __init__(self) -> None:
        self.messages: list[str] = []
        self._topics: set[str] = set()

    def warn(self, topic: str, message: str) -> None:
        """Record and emit ``message`` unless ``topic`` was already reported."""
        if topic in self._topics:
            return
        self._topics.add(topic)
        self.messages.append(message)
        warnings.warn(message, SceneWarning, stacklevel=3)


# ------------------------------------------------------------------------ geometry helpers
def area_weighted_vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Per-vertex sum of the adjacent triangles' area-weighted geometric normals, unit length.

    Vertices touched only by zero-area triangles (or by none) get ``(0, 0, 1)``.

    Parameters
    ----------
    vertices : (V, 3) float array
        Positions (scene units).
    triangles : (T, 3) int array
        Vertex indices, counter-clockwise from the front.

    Returns
    -------
    (V, 3) float64 array of unit normals.
    """
    corners = np.asarray(vertices, dtype=np.float64)[triangles]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    sums = np.zeros((len(vertices), 3))
    for corner in range(3):
        np.add.at(sums, triangles[:, corner], face_normals)
    return normalise_or_default(sums)


def normalise_or_default(vectors: np.ndarray, default: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Unit-length copies of ``vectors`` (float64); zero or non-finite rows become ``default``."""
    vectors = np.asarray(vectors, dtype=np.float64)
    lengths = np.linalg.norm(vectors, axis=1)
    usable = np.isfinite(lengths) & (lengths > 0.0)
    result = np.empty_like(vectors)
    result[usable] = vectors[usable] / lengths[usable, None]
    result[~usable] = default
    return result


def repair_normals(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray, missing: np.ndarray) -> np.ndarray:
    """Shading normals made valid: given ones normalised, missing or zero ones replaced.

    Parameters
    ----------
    vertices, triangles : arrays
        The mesh.
    normals : (V, 3) float array
        Normals from the file (any length; rows flagged ``missing`` are ignored).
    missing : (V,) bool array
        Vertices whose normal the file did not give.

    Returns
    -------
    (V, 3) float32 array of unit normals; a missing or zero-length normal is replaced
    by the area-weighted geometric vertex normal (:func:`area_weighted_vertex_normals`).
    """
    normals = np.asarray(normals, dtype=np.float64)
    largest = np.abs(normals).max(axis=1, keepdims=True) if len(normals) else np.zeros((0, 1))
    extreme = (largest > 1e150) | ((largest > 0.0) & (largest < 1e-150))  # whose norm would overflow or underflow
    normals = np.divide(normals, largest, out=normals.copy(), where=extreme)
    lengths = np.linalg.norm(normals, axis=1)
    replace = missing | ~(lengths > 0.0)
    result = np.empty_like(normals)
    keep = ~replace
    result[keep] = normals[keep] / lengths[keep, None]
    if replace.any():
        result[replace] = area_weighted_vertex_normals(vertices, triangles)[replace]
    return result.astype(np.float32)


def fan_triangulate(corner_counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangulation of polygons stored one after another.

    Parameters
    ----------
    corner_counts : (F,) int array
        Number of corners of each polygon (>= 2; a 2-corner polygon gives no triangle).

    Returns
    -------
    corners : (T, 3) int64 array
        Indices into the concatenated corner list: polygon ``f`` with first corner ``s``
        and ``n`` corners gives ``(s, s+k, s+k+1)`` for ``k = 1 .. n-2``.
    polygon_of_triangle : (T,) int64 array
        The polygon each triangle comes from.
    """
    corner_counts = np.asarray(corner_counts, dtype=np.int64)
    first_corner = np.concatenate(([0], np.cumsum(corner_counts)[:-1]))
    triangles_per_polygon = np.maximum(corner_counts - 2, 0)
    polygon_of_triangle = np.repeat(np.arange(len(corner_counts)), triangles_per_polygon)
    first_triangle = np.concatenate(([0], np.cumsum(triangles_per_polygon)[:-1]))
    k = np.arange(len(polygon_of_triangle)) - first_triangle[polygon_of_triangle] + 1
    start = first_corner[polygon_of_triangle]
    return np.stack([start, start + k, start + k + 1], axis=1), polygon_of_triangle


# ------------------------------------------------------------------------------- caching
def cache_directory() -> Path:
    """Folder of the mesh cache: ``meshes`` under :func:`kdtrace.cache.cache_root`."""
    return cache_root() / "meshes"


def cache_key(sources: Sequence[tuple[str, bytes | None]]) -> str:
    """SHA-256 over the loader version and each (role, bytes) pair; None marks a missing file."""
    digest = hashlib.sha256(LOADER_VERSION.encode())
    for role, content in sources:
        digest.update(role.encode() + b"\0")
        digest.update(b"<missing>" if content is None else hashlib.sha256(content).digest())
    return digest.hexdigest()


_ARRAYS = ("vertices", "triangles", "material_ids", "normals", "texcoords")


def _save_cached(path: Path, scene: Scene, messages: list[str]) -> None:
    arrays = {name: getattr(scene, name) for name in _ARRAYS if getattr(scene, name) is not None}
    meta = {
        "name": scene.name,
        "sources": scene.sources,
        "materials": [dataclasses.asdict(m) for m in scene.materials],
        "warnings": messages,
    }
    atomic_write(path, lambda temporary: np.savez(temporary, meta=np.array(json.dumps(meta)), **arrays))


def _load_cached(path: Path) -> Scene | None:
    try:
        with np.load(path, allow_pickle=False) as archive:
            meta = json.loads(str(archive["meta"]))
            arrays = {name: archive[name] if name in archive else None for name in _ARRAYS}
    except (OSError, ValueError, KeyError, json.JSONDecodeError):
        return None  # unreadable or foreign entry: treated as a miss and overwritten
    for message in meta["warnings"]:
        warnings.warn(message, SceneWarning, stacklevel=3)
    materials = [
        Material(**{**m, "albedo": tuple(m["albedo"]), "emission": tuple(m["emission"])}) for m in meta["materials"]
    ]
    return Scene(name=meta["name"], materials=materials, sources=meta["sources"], **arrays)


def cached_load(key: str, parse: Callable[[WarningLog], Scene], use_cache: bool) -> Scene:
    """Return the cached scene of ``key``, or ``parse`` it and store it.

    Parameters
    ----------
    key : str
        From :func:`cache_key`.
    parse : callable
        Parses the mesh, reporting warnings through the given :class:`WarningLog`.
    use_cache : bool
        False parses without reading or writing the cache.
    """
    log = WarningLog()
    if not use_cache:
        return parse(log)
    entry = cache_directory() / f"{key}.npz"

    def parse_and_save() -> Scene:
        scene = parse(log)
        try:
            _save_cached(entry, scene, log.messages)
        except OSError as error:
            warnings.warn(f"mesh cache not written to {entry}: {error}", SceneWarning, stacklevel=4)
        return scene

    return compute_once(entry, lambda: _load_cached(entry) if entry.exists() else None, parse_and_save)


def load_mesh(path: str | Path, *, use_cache: bool = True) -> Scene:
    """Load an ``.obj`` (with its ``.mtl``) or ``.ply`` mesh, through the cache.

    Parameters
    ----------
    path : str or Path
        Mesh file; the suffix (case-insensitive) selects the reader.
    use_cache : bool
        Read and write the ``.npz`` cache (default True).

    Returns
    -------
    Scene
        Geometry and materials, without cameras or sky.

    Raises
    ------
    SceneError
        Unknown suffix, missing or malformed file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".obj":
        return obj.load_obj(path, use_cache=use_cache)
    if suffix == ".ply":
        return ply.load_ply(path, use_cache=use_cache)
    raise SceneError(f"{path}: unknown mesh format {path.suffix!r}; expected .obj or .ply")


# The readers import the helpers above, so they are imported last.
from kdtrace.io import obj, ply  # noqa: E402

__all__ = ["LOADER_VERSION", "SceneError", "SceneWarning", "load_mesh", "obj", "ply"]
