"""Wavefront OBJ reader (own implementation, vectorised with NumPy).

Supported: ``v`` (x y z, an optional w or r g b ignored), ``vt`` (u [v [w]]; w ignored,
a missing v is 0), ``vn``, faces ``f`` in the forms ``v``, ``v/vt``, ``v//vn`` and
``v/vt/vn`` (one form per face), negative indices relative to the elements read so far,
polygons triangulated as fans, ``usemtl``, ``mtllib`` (paths relative to the OBJ),
comments (whole-line and trailing), blank lines, and LF, CRLF or CR line ends. ``o``,
``g``, ``s``, ``l`` and ``p`` are ignored; other keywords warn once per file.

Output conventions:

* Each distinct (v, vt, vn) index triple becomes one vertex, so normals and texture
  coordinates are per vertex. Vertices are ordered by (v, vt, vn) index; vertices no
  face uses are dropped.
* ``normals`` is None when the file has no ``vn``; otherwise unit length, and a vertex
  of a face without ``vn`` (or whose ``vn`` is zero) gets the area-weighted geometric
  normal of its faces (:func:`kdtrace.io.repair_normals`).
* ``texcoords`` is None when the file has no ``vt``; otherwise faces without ``vt``
  get (0, 0).
* A face with 2 vertices (an edge, as Blender writes them) gives no triangle and one
  warning per file; a face with fewer vertices is an error.
* Zero-area triangles are kept.
* Materials: with ``mtllib``, each ``usemtl`` name is looked up in the libraries
  (:mod:`kdtrace.io.mtl`); an unknown name, or faces before any ``usemtl``, get a
  default grey diffuse material and a warning. Without ``mtllib``, each ``usemtl`` name
  gets a default diffuse material of that name and faces without one get ``"default"``.
  The material table lists the materials in order of first use.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NoReturn

import numpy as np

from kdtrace.io import (
    SceneError,
    WarningLog,
    cache_key,
    cached_load,
    fan_triangulate,
    read_source,
    repair_normals,
)
from kdtrace.io.mtl import parse_mtl
from kdtrace.scene import Material, Scene

#: Name of the material given to faces that have none.
DEFAULT_MATERIAL_NAME = "default"

_IGNORED_KEYWORDS = frozenset({"o", "g", "s", "l", "p"})
# Face forms: number of '/'-separated fields and whether vt / vn are present.
_FORM_V, _FORM_V_VT, _FORM_V_VN, _FORM_V_VT_VN = range(4)
_FORM_FIELDS = {_FORM_V: 1, _FORM_V_VT: 2, _FORM_V_VN: 2, _FORM_V_VT_VN: 3}
_FORM_NAMES = {_FORM_V: "v", _FORM_V_VT: "v/vt", _FORM_V_VN: "v//vn", _FORM_V_VT_VN: "v/vt/vn"}
_VALUE_COUNTS = {"v": (3, 4, 6), "vt": (1, 2, 3), "vn": (3,)}
_MTLLIB_LINE = re.compile(rb"^[ \t]*mtllib[ \t]+([^\r\n#]*)", re.MULTILINE)


def _face_form(corner: str) -> int:
    slashes = corner.count("/")
    if slashes == 0:
        return _FORM_V
    if slashes == 1:
        return _FORM_V_VT
    return _FORM_V_VN if "//" in corner else _FORM_V_VT_VN


class _Lines:
    """What the line-by-line pass collects; numbers are 1-based line numbers."""

    def __init__(self) -> None:
        self.tokens = {"v": [], "vt": [], "vn": []}
        self.value_counts = {"v": [], "vt": [], "vn": []}
        self.line_numbers = {"v": [], "vt": [], "vn": []}
        # per face
        self.face_line: list[int] = []
        self.face_corners: list[int] = []
        self.face_form: list[int] = []
        self.face_material: list[int] = []
        self.face_defined: list[tuple[int, int, int]] = []  # v, vt, vn counts so far
        self.form_tokens: dict[int, list[str]] = {form: [] for form in _FORM_FIELDS}
        self.material_names: list[str] = []
        self.material_lines: list[int] = []
        self.mtllibs: list[tuple[str, int]] = []
        self.short_faces: list[int] = []


def _scan(text: str, path: Path, log: WarningLog) -> _Lines:
    """One pass over the lines: dispatch on the keyword, keep tokens for bulk conversion."""
    found = _Lines()
    material_index: dict[str, int] = {}
    material = -1
    for number, line in enumerate(text.split("\n"), 1):
        if "#" in line:
            line = line.split("#", 1)[0]
        parts = line.split(None, 1)
        if not parts:
            continue
        keyword = parts[0]
        rest = parts[1] if len(parts) > 1 else ""
        if keyword in found.tokens:
            values = rest.split()
            if len(values) not in _VALUE_COUNTS[keyword]:
                expected = " or ".join(map(str, _VALUE_COUNTS[keyword]))
                raise SceneError(f"{path}:{number}: '{keyword}' needs {expected} numbers, got {len(values)}")
            found.tokens[keyword].extend(values)
            found.value_counts[keyword].append(len(values))
            found.line_numbers[keyword].append(number)
        elif keyword == "f":
            corners = rest.split()
            if len(corners) < 2:
                raise SceneError(f"{path}:{number}: a face needs at least 3 vertices, got {len(corners)}")
            if len(corners) == 2:
                found.short_faces.append(number)
            form = _face_form(corners[0])
            found.face_line.append(number)
            found.face_corners.append(len(corners))
            found.face_form.append(form)
            found.face_material.append(material)
            found.face_defined.append((len(found.line_numbers["v"]), len(found.line_numbers["vt"]), len(found.line_numbers["vn"])))
            found.form_tokens[form].extend(corners)
        elif keyword == "usemtl":
            name = rest.strip()
            if not name:
                raise SceneError(f"{path}:{number}: 'usemtl' without a material name")
            if name not in material_index:
                material_index[name] = len(found.material_names)
                found.material_names.append(name)
                found.material_lines.append(number)
            material = material_index[name]
        elif keyword == "mtllib":
            if not rest.strip():
                raise SceneError(f"{path}:{number}: 'mtllib' without a file name")
            found.mtllibs.append((rest.strip(), number))
        elif keyword not in _IGNORED_KEYWORDS:
            log.warn(f"keyword {keyword}", f"{path}:{number}: unknown OBJ keyword {keyword!r} ignored")
    return found


def _convert_values(found: _Lines, keyword: str, path: Path) -> np.ndarray:
    """The ``v``/``vt``/``vn`` values as a float64 array of 3 (v, vn) or 2 (vt) columns."""
    tokens, counts = found.tokens[keyword], np.asarray(found.value_counts[keyword], dtype=np.int64)
    width = 2 if keyword == "vt" else 3
    if not len(counts):
        return np.zeros((0, width))
    try:
        flat = np.array(tokens, dtype=np.float64)
    except ValueError:
        for number, start, count in zip(found.line_numbers[keyword], np.cumsum(counts) - counts, counts):
            for token in tokens[start : start + count]:
                try:
                    float(token)
                except ValueError:
                    raise SceneError(f"{path}:{number}: '{keyword}' value {token!r} is not a number") from None
        raise SceneError(f"{path}: malformed '{keyword}' values") from None
    starts = np.cumsum(counts) - counts
    columns = np.arange(width)
    present = columns[None, :] < counts[:, None]
    gathered = flat[np.minimum(starts[:, None] + columns[None, :], len(flat) - 1)]
    values = np.where(present, gathered, 0.0)
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        number = found.line_numbers[keyword][int(np.flatnonzero(~finite)[0])]
        raise SceneError(f"{path}:{number}: '{keyword}' has a NaN or infinite value")
    return values


def _slow_face_check(found: _Lines, form: int, path: Path) -> NoReturn:
    """Find the face line of ``form`` that the bulk conversion rejected, and report it."""
    fields = _FORM_FIELDS[form]
    tokens = found.form_tokens[form]
    offset = 0
    for number, count, face_form in zip(found.face_line, found.face_corners, found.face_form):
        if face_form != form:
            continue
        for corner in tokens[offset : offset + count]:
            if _face_form(corner) != form:
                raise SceneError(f"{path}:{number}: face mixes index forms ({_FORM_NAMES[form]!r} and {corner!r})")
            pieces = corner.split("/")
            if form == _FORM_V_VN:
                pieces = [pieces[0], pieces[2]]
            if len(pieces) != fields:
                raise SceneError(f"{path}:{number}: malformed face vertex {corner!r}")
            for piece in pieces:
                try:
                    int(piece)
                except ValueError:
                    raise SceneError(f"{path}:{number}: face index {piece!r} in {corner!r} is not an integer") from None
        offset += count
    raise SceneError(f"{path}: malformed face indices")


def _convert_faces(found: _Lines, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw (v, vt, vn) OBJ indices of every face corner in file order; 0 where absent."""
    counts = np.asarray(found.face_corners, dtype=np.int64)
    forms = np.asarray(found.face_form, dtype=np.int64)
    first_corner = np.cumsum(counts) - counts
    raw = np.zeros((int(counts.sum()), 3), dtype=np.int64)
    for form, tokens in found.form_tokens.items():
        if not tokens:
            continue
        fields = _FORM_FIELDS[form]
        joined = " ".join(tokens)
        if form == _FORM_V_VN:
            separators_ok = joined.count("//") == len(tokens) and joined.count("/") == 2 * len(tokens)
            joined = joined.replace("//", " ")
        else:
            separators_ok = joined.count("/") == (fields - 1) * len(tokens)
            joined = joined.replace("/", " ")
        pieces = joined.split()
        if not separators_ok or len(pieces) != fields * len(tokens):
            _slow_face_check(found, form, path)
        try:
            values = np.array(pieces, dtype=np.int64).reshape(-1, fields)
        except ValueError:
            _slow_face_check(found, form, path)
        faces = np.flatnonzero(forms == form)
        corner_positions = np.repeat(first_corner[faces], counts[faces]) + (
            np.arange(len(values)) - np.repeat(np.cumsum(counts[faces]) - counts[faces], counts[faces])
        )
        columns = {_FORM_V: [0], _FORM_V_VT: [0, 1], _FORM_V_VN: [0, 2], _FORM_V_VT_VN: [0, 1, 2]}[form]
        raw[corner_positions[:, None], np.array(columns)[None, :]] = values
    return raw, counts, forms


def _resolve(raw: np.ndarray, defined_so_far: np.ndarray, total: int, present: np.ndarray, kind: str, corner_line: np.ndarray, path: Path) -> np.ndarray:
    """0-based indices from OBJ indices (1-based, or negative = relative); -1 where absent."""
    resolved = np.where(raw > 0, raw - 1, defined_so_far + raw)
    bad = present & ((raw == 0) | (resolved < 0) | (resolved >= total))
    if bad.any():
        corner = int(np.flatnonzero(bad)[0])
        index = int(raw[corner])
        if index == 0:
            reason = "index 0 is invalid (OBJ indices start at 1)"
        elif index < 0:
            reason = f"relative index {index} reaches before the first {kind} ({int(defined_so_far[corner])} defined so far)"
        else:
            reason = f"index {index} is out of range (the file has {total} {kind} elements)"
        raise SceneError(f"{path}:{int(corner_line[corner])}: {kind} {reason}")
    return np.where(present, resolved, -1)


def _materials(found: _Lines, face_material: np.ndarray, path: Path, log: WarningLog) -> tuple[list[Material], np.ndarray]:
    """Material table (in order of first use) and each face's index into it."""
    library: dict[str, Material] = {}
    library_names: list[str] = []
    for name, number in found.mtllibs:
        for mtl_path in _mtllib_files(path, name, number):
            library.update(parse_mtl(read_source(mtl_path), mtl_path, log))
            library_names.append(mtl_path.name)
    used = np.unique(face_material)
    table: list[Material] = []
    remap = np.zeros(len(found.material_names) + 1, dtype=np.int64)  # slot -1 -> last
    for slot in used:
        if slot < 0:
            if library_names:
                first = found.face_line[int(np.flatnonzero(face_material < 0)[0])]
                log.warn("no usemtl", f"{path}:{first}: faces without 'usemtl' get a default grey diffuse material")
            material = Material(DEFAULT_MATERIAL_NAME)
        else:
            name = found.material_names[slot]
            material = library.get(name)
            if material is None:
                if library_names:
                    log.warn(
                        f"missing {name}",
                        f"{path}:{found.material_lines[slot]}: material {name!r} is not defined in "
                        f"{', '.join(library_names)}; using a default grey diffuse material",
                    )
                material = Material(name)
        remap[slot] = len(table)
        table.append(material)
    return table, remap[face_material]


def _mtllib_files(path: Path, name: str, number: int) -> list[Path]:
    """The MTL files of an ``mtllib`` line: the whole name if it exists, else each word."""
    whole = path.parent / name
    if whole.is_file():
        return [whole]
    files = [path.parent / word for word in name.split()]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise SceneError(f"{path}:{number}: material library not found: {', '.join(missing)}")
    return files


def parse_obj(data: bytes, path: Path, log: WarningLog | None = None) -> Scene:
    """Scene (no camera, no sky) from the bytes of an OBJ file.

    Parameters
    ----------
    data : bytes
        File content.
    path : Path
        The file: named in messages, and the folder of ``mtllib`` files.
    log : WarningLog, optional
        Receives warnings.

    Raises
    ------
    SceneError
        Any malformed line, bad index, non-finite value, missing ``.mtl`` or a file
        without faces; the message names the file and line.
    """
    log = log if log is not None else WarningLog()
    text = data.decode("utf-8", "surrogateescape").replace("\r\n", "\n").replace("\r", "\n")
    found = _scan(text, path, log)
    if not found.face_line:
        raise SceneError(f"{path}: the mesh has no faces")
    if found.short_faces:
        log.warn(
            "two-vertex faces",
            f"{path}:{found.short_faces[0]}: {len(found.short_faces)} face(s) with 2 vertices give no triangle",
        )
    positions = _convert_values(found, "v", path)
    texcoords = _convert_values(found, "vt", path)
    normals = _convert_values(found, "vn", path)
    raw, counts, forms = _convert_faces(found, path)

    corner_face = np.repeat(np.arange(len(counts)), counts)
    corner_line = np.asarray(found.face_line, dtype=np.int64)[corner_face]
    defined = np.asarray(found.face_defined, dtype=np.int64)[corner_face]
    corner_form = forms[corner_face]
    has_vt = (corner_form == _FORM_V_VT) | (corner_form == _FORM_V_VT_VN)
    has_vn = (corner_form == _FORM_V_VN) | (corner_form == _FORM_V_VT_VN)
    v = _resolve(raw[:, 0], defined[:, 0], len(positions), np.ones(len(raw), bool), "vertex", corner_line, path)
    vt = _resolve(raw[:, 1], defined[:, 1], len(texcoords), has_vt, "texture coordinate", corner_line, path)
    vn = _resolve(raw[:, 2], defined[:, 2], len(normals), has_vn, "normal", corner_line, path)

    corners_of_triangle, face_of_triangle = fan_triangulate(counts)
    if len(face_of_triangle) == 0:
        raise SceneError(f"{path}: the mesh has no triangles (every face has 2 vertices)")
    # One vertex per distinct (v, vt, vn) triple.
    radix_vt, radix_vn = len(texcoords) + 1, len(normals) + 1
    if len(positions) * radix_vt * radix_vn < 2**62:
        keys = (v * radix_vt + vt + 1) * radix_vn + vn + 1
        _, first, vertex_of_corner = np.unique(keys, return_index=True, return_inverse=True)
    else:
        _, first, vertex_of_corner = np.unique(np.stack([v, vt, vn], 1), axis=0, return_index=True, return_inverse=True)
    vertex_of_corner = vertex_of_corner.reshape(-1)
    vertices = positions[v[first]]
    triangles = vertex_of_corner[corners_of_triangle]

    vertex_normals = None
    if len(normals) and has_vn.any():
        vn_first = vn[first]
        given = np.where(vn_first[:, None] >= 0, normals[np.maximum(vn_first, 0)], 0.0)
        vertex_normals = repair_normals(vertices, triangles, given, vn_first < 0)
    vertex_texcoords = None
    if len(texcoords) and has_vt.any():
        vt_first = vt[first]
        vertex_texcoords = np.where(vt_first[:, None] >= 0, texcoords[np.maximum(vt_first, 0)], 0.0)

    face_material = np.asarray(found.face_material, dtype=np.int64)
    materials, face_material_id = _materials(found, face_material, path, log)
    return Scene(
        name=path.stem,
        vertices=vertices.astype(np.float32),
        triangles=triangles.astype(np.int32),
        material_ids=face_material_id[face_of_triangle].astype(np.int32),
        materials=materials,
        normals=vertex_normals,
        texcoords=None if vertex_texcoords is None else vertex_texcoords.astype(np.float32),
        sources=[str(path)],
    )


def read_obj(path: str | Path) -> Scene:
    """Parse the OBJ file at ``path`` (and its ``.mtl`` files) without the cache."""
    path = Path(path)
    return parse_obj(read_source(path), path)


def load_obj(path: str | Path, *, use_cache: bool = True) -> Scene:
    """Parse the OBJ file at ``path`` through the ``.npz`` cache (see :mod:`kdtrace.io`)."""
    path = Path(path)
    data = read_source(path)
    sources: list[tuple[str, bytes | None]] = [("path", str(path.resolve()).encode()), ("obj", data)]
    for match in _MTLLIB_LINE.finditer(data):
        name = match.group(1).decode("utf-8", "surrogateescape").strip()
        for word in [name, *name.split()]:
            candidate = path.parent / word
            sources.append((f"mtl {word}", candidate.read_bytes() if candidate.is_file() else None))
    return cached_load(cache_key(sources), lambda log: parse_obj(data, path, log), use_cache)
