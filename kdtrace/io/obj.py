"""Wavefront OBJ reader (own implementation, vectorised with NumPy).

Supported: ``v`` (x y z, an optional w or r g b ignored), ``vt`` (u [v [w]]; w ignored,
a missing v is 0), ``vn``, faces ``f`` in the forms ``v``, ``v/vt``, ``v//vn`` and
``v/vt/vn`` (one form per face), negative indices relative to the elements read so far,
polygons triangulated as fans, ``usemtl``, ``mtllib`` (see below), comments (whole-line
and trailing), blank lines, LF, CRLF or CR line ends, and UTF-8 (a byte order mark is
dropped) or UTF-16 text after a byte order mark. ``o``, ``g``, ``s``, ``l`` and
``p`` are ignored; other keywords warn once per file.

Lenient where the data is usable, as tinyobjloader, trimesh and Blender are (each case
warns once per file, naming file and line):

* ``mtllib`` lists one or more file names, relative to the OBJ, separated by blanks;
  ``\\ `` escapes a blank inside a name. When those files do not all exist but the whole
  rest of the line names one that does (``mtllib Peaches Castle.mtl``, as Blender 2.79
  writes it), that file is read. Files that are not found are reported and skipped:
  their materials get the default grey diffuse.
* A face whose ``vt`` (or ``vn``) index is 0, out of range or refers to an element the
  file does not define loses its texture coordinates (or normals), not its triangles;
  one warning counts such faces.

Refused (:class:`kdtrace.io.SceneError` naming file and line): a malformed line, a NaN
or infinite value, a ``v`` or ``vt`` value beyond the float32 range, a vertex index out
of range (indices beyond int64 count as out of range), a file without faces or triangles.

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
* Materials: when a material library was read, each ``usemtl`` name is looked up in the
  libraries in the order of the ``mtllib`` lines and names (the first definition wins;
  :mod:`kdtrace.io.mtl`); an unknown name, or faces before any ``usemtl``, get a default
  grey diffuse material and a warning. When none was read (no ``mtllib``, or none of its
  files found), each ``usemtl`` name gets a default diffuse material of that name and
  faces without one get ``"default"``. The material table lists the materials in order
  of first use.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NoReturn

import numpy as np

from kdtrace.io import (
    FLOAT32_MAX,
    SceneError,
    WarningLog,
    cache_key,
    cached_load,
    decode_text,
    fan_triangulate,
    is_file,
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
_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
_MTLLIB_LINE = re.compile(rb"^[ \t]*mtllib[ \t]+([^\r\n#]*)", re.MULTILINE)
_UNESCAPED_BLANKS = re.compile(r"(?<!\\)[ \t]+")


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
        for number, start, count in zip(found.line_numbers[keyword], np.cumsum(counts) - counts, counts, strict=True):
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
    if keyword != "vn" and not np.all(np.abs(values) <= FLOAT32_MAX):  # kept as float32; normals are normalised first
        number = found.line_numbers[keyword][int(np.flatnonzero(~np.all(np.abs(values) <= FLOAT32_MAX, axis=1))[0])]
        raise SceneError(f"{path}:{number}: '{keyword}' has a value beyond the float32 range")
    return values


def _slow_face_check(found: _Lines, form: int, path: Path) -> NoReturn:
    """Find the face line of ``form`` that the bulk conversion rejected, and report it."""
    fields = _FORM_FIELDS[form]
    tokens = found.form_tokens[form]
    offset = 0
    for number, count, face_form in zip(found.face_line, found.face_corners, found.face_form, strict=True):
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
        except OverflowError:  # beyond int64: out of range whatever the file holds, so clamped
            values = np.array([min(max(int(piece), _INT64_MIN), _INT64_MAX) for piece in pieces]).reshape(-1, fields)
        faces = np.flatnonzero(forms == form)
        corner_positions = np.repeat(first_corner[faces], counts[faces]) + (
            np.arange(len(values)) - np.repeat(np.cumsum(counts[faces]) - counts[faces], counts[faces])
        )
        columns = {_FORM_V: [0], _FORM_V_VT: [0, 1], _FORM_V_VN: [0, 2], _FORM_V_VT_VN: [0, 1, 2]}[form]
        raw[corner_positions[:, None], np.array(columns)[None, :]] = values
    return raw, counts, forms


def _zero_based_indices(
    raw: np.ndarray, defined_so_far: np.ndarray, total: int, present: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """0-based indices from OBJ indices (1-based, or negative = relative).

    Returns the indices (-1 where absent or invalid) and the mask of the corners whose
    index is present but 0 or outside the ``total`` elements.
    """
    resolved = np.where(raw > 0, raw - 1, defined_so_far + raw)
    bad = present & ((raw == 0) | (resolved < 0) | (resolved >= total))
    return np.where(present & ~bad, resolved, -1), bad


def _index_problem(index: int, defined_so_far: int, total: int, kind: str) -> str:
    """What is wrong with the OBJ ``index`` of a ``kind`` element, for a message."""
    if index == 0:
        return f"{kind} index 0 is invalid (OBJ indices start at 1)"
    if index < 0:
        return f"{kind} relative index {index} reaches before the first {kind} ({defined_so_far} defined so far)"
    return f"{kind} index {index} is out of range (the file has {total or 'no'} {kind} elements)"


def _drop_invalid_attributes(
    attributes: dict[str, tuple[np.ndarray, np.ndarray, int]],
    raw: np.ndarray,
    defined: np.ndarray,
    corner_face: np.ndarray,
    face_line: np.ndarray,
    path: Path,
    log: WarningLog,
) -> dict[str, np.ndarray]:
    """Texture coordinate / normal indices with every face that has an invalid one dropped.

    Parameters
    ----------
    attributes : dict
        ``{"texture coordinate": (indices, bad, total), "normal": ...}`` from
        :func:`_zero_based_indices`, in the column order of ``raw`` (1, 2).
    raw, defined : (C, 3) int arrays
        OBJ indices of each corner and the element counts read before its face.
    corner_face : (C,) int array
        The face of each corner.
    face_line : (F,) int array
        The line of each face.

    Returns
    -------
    The indices by kind, -1 on every corner of a face that had an invalid index of that
    kind. One warning per file names the first invalid index and counts the faces.
    """
    kept: dict[str, np.ndarray] = {}
    dropped: list[str] = []
    first: tuple[int, str] | None = None
    for column, (kind, (indices, bad, total)) in enumerate(attributes.items(), 1):
        bad_face = np.zeros(len(face_line), dtype=bool)
        bad_face[corner_face[bad]] = True
        kept[kind] = np.where(bad_face[corner_face], -1, indices)
        if not bad.any():
            continue
        dropped.append(f"the {kind}s of {int(bad_face.sum())} face(s)")
        corner = int(np.flatnonzero(bad)[0])
        line = int(face_line[corner_face[corner]])
        if first is None or line < first[0]:
            first = (line, _index_problem(int(raw[corner, column]), int(defined[corner, column]), total, kind))
    if first is not None:
        log.warn(
            "invalid attribute indices",
            f"{path}:{first[0]}: {first[1]}; dropped {' and '.join(dropped)} with invalid indices, "
            "kept their triangles",
        )
    return kept


def _materials(found: _Lines, face_material: np.ndarray, path: Path, log: WarningLog) -> tuple[list[Material], np.ndarray]:
    """Material table (in order of first use) and each face's index into it."""
    library: dict[str, Material] = {}
    library_names: list[str] = []
    read: set[Path] = set()
    for rest, number in found.mtllibs:
        for mtl_path in _mtllib_files(path, rest, number, log):
            if mtl_path.resolve() in read:
                continue  # some exporters repeat the same mtllib line for every object
            read.add(mtl_path.resolve())
            for name, material in parse_mtl(read_source(mtl_path), mtl_path, log).items():
                library.setdefault(name, material)
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


def _mtllib_readings(rest: str) -> list[list[str]]:
    """The ways to read the file names of an ``mtllib`` line, most likely first.

    First the names separated by blanks (``\\ `` is a blank inside a name), then, when
    that gives several names, the whole rest of the line as one name.
    """
    rest = rest.strip()
    names = [name.replace("\\ ", " ") for name in _UNESCAPED_BLANKS.split(rest)]
    return [names, [rest.replace("\\ ", " ")]] if len(names) > 1 else [names]


def _mtllib_files(path: Path, rest: str, number: int, log: WarningLog) -> list[Path]:
    """The existing MTL files of the ``mtllib`` line ``number``; the missing ones are reported.

    The first reading of :func:`_mtllib_readings` whose files all exist is used; when
    none does, the files of the first reading that exist, with a warning naming the
    others.
    """
    readings = _mtllib_readings(rest)
    for names in readings:
        files = [path.parent / name for name in names]
        if all(is_file(f) for f in files):
            return files
    found = [path.parent / name for name in readings[0] if is_file(path.parent / name)]
    missing = ", ".join(repr(name) for name in readings[0] if not is_file(path.parent / name))
    tried = f" (nor {readings[1][0]!r} as one name)" if len(readings) > 1 and not found else ""
    log.warn(
        f"mtllib {missing}",
        f"{path}:{number}: material library {missing} not found in {path.parent}{tried}; "
        "its materials get a default grey diffuse",
    )
    return found


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
        Any malformed line, bad vertex index, non-finite value or a file without
        faces; the message names the file and line.
    """
    log = log if log is not None else WarningLog()
    found = _scan(decode_text(data), path, log)
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
    face_line = np.asarray(found.face_line, dtype=np.int64)
    corner_line = face_line[corner_face]
    defined = np.asarray(found.face_defined, dtype=np.int64)[corner_face]
    corner_form = forms[corner_face]
    v, bad_v = _zero_based_indices(raw[:, 0], defined[:, 0], len(positions), np.ones(len(raw), bool))
    if bad_v.any():
        corner = int(np.flatnonzero(bad_v)[0])
        problem = _index_problem(int(raw[corner, 0]), int(defined[corner, 0]), len(positions), "vertex")
        raise SceneError(f"{path}:{int(corner_line[corner])}: {problem}")
    has_vt = (corner_form == _FORM_V_VT) | (corner_form == _FORM_V_VT_VN)
    has_vn = (corner_form == _FORM_V_VN) | (corner_form == _FORM_V_VT_VN)
    attributes = {
        "texture coordinate": (*_zero_based_indices(raw[:, 1], defined[:, 1], len(texcoords), has_vt), len(texcoords)),
        "normal": (*_zero_based_indices(raw[:, 2], defined[:, 2], len(normals), has_vn), len(normals)),
    }
    kept = _drop_invalid_attributes(attributes, raw, defined, corner_face, face_line, path, log)
    vt, vn = kept["texture coordinate"], kept["normal"]

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
    if (vn >= 0).any():
        vn_first = vn[first]
        given = np.where(vn_first[:, None] >= 0, normals[np.maximum(vn_first, 0)], 0.0)
        vertex_normals = repair_normals(vertices, triangles, given, vn_first < 0)
    vertex_texcoords = None
    if (vt >= 0).any():
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
    for match in _MTLLIB_LINE.finditer(decode_text(data).encode("utf-8", "surrogateescape")):
        for names in _mtllib_readings(match.group(1).decode("utf-8", "surrogateescape")):
            for name in names:
                candidate = path.parent / name
                sources.append((f"mtl {name}", candidate.read_bytes() if is_file(candidate) else None))
    return cached_load(cache_key(sources), lambda log: parse_obj(data, path, log), use_cache)
