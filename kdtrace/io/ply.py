"""PLY reader (own implementation with NumPy structured dtypes).

Formats ``ascii``, ``binary_little_endian`` and ``binary_big_endian``; any elements and
scalar or list properties.
Used: vertex ``x y z``, optional ``nx ny nz`` (normalised; zero or non-finite ones replaced by the
area-weighted geometric normal) and ``s t`` / ``u v`` / ``texture_u texture_v``; face
``vertex_indices`` (or ``vertex_index``) lists, polygons triangulated as fans, and an
optional integer per-face ``material_id``. Zero-area triangles are kept. Other
elements are skipped with a warning.

Materials: when a side-car ``<stem>_materials.json`` lies beside the file (a JSON list
of ``{"id", "name", "mean_texture_linear_rgb" or "mtl_Kd"}``, as the Crytek Sponza ships
it), material ``id`` becomes a diffuse material of that flat colour: the mean linear
colour of its texture when known (the textures themselves are not used), else ``mtl_Kd``.
Without a side-car, every material id ``k`` in ``0 .. max`` gets a default diffuse
material ``"material_k"`` (one ``"default"`` material without ``material_id``). Ids far
beyond the number of faces are renumbered (see :func:`_materials`).

Refused (:class:`kdtrace.io.SceneError` naming the file, and the line in the header and
in ascii records): a malformed header, an element or property named twice, a body
shorter than its header says (so an enormous element count is refused before anything
is allocated), a negative or fractional list length, an integer property whose ascii
value is not a whole number of its type, a coordinate that is NaN, infinite or beyond
the float32 range, a face with fewer than 3 vertices or a vertex index out of range.

Binary faces are read in one block when every face has the same corner count (the
common all-triangle case); otherwise face by face.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from kdtrace.io import (
    FLOAT32_MAX,
    SceneError,
    WarningLog,
    cache_key,
    cached_load,
    fan_triangulate,
    is_file,
    read_source,
    repair_normals,
)
from kdtrace.scene import Material, Scene

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_TEXCOORD_NAMES = (("s", "t"), ("u", "v"), ("texture_u", "texture_v"))
_FACE_LIST_NAMES = ("vertex_indices", "vertex_index")
#: Side-car material file next to ``name.ply``: ``name`` + this suffix.
MATERIALS_SUFFIX = "_materials.json"
#: Material ids below this always get a table entry each, used or not (see :func:`_materials`).
DENSE_MATERIAL_IDS = 1024


class _Property:
    def __init__(self, name: str, dtype: str, count_dtype: str | None = None) -> None:
        self.name, self.dtype, self.count_dtype = name, dtype, count_dtype

    @property
    def is_list(self) -> bool:
        return self.count_dtype is not None


class _Element:
    def __init__(self, name: str, count: int) -> None:
        self.name, self.count = name, count
        self.properties: list[_Property] = []


def _parse_header(data: bytes, path: Path) -> tuple[str, list[_Element], int]:
    """Format, elements and byte offset of the body."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise SceneError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    body = data.index(b"\n", end) + 1 if b"\n" in data[end:] else len(data)
    lines = data[:end].decode("ascii", "replace").replace("\r\n", "\n").replace("\r", "\n").split("\n")
    file_format: str | None = None
    elements: list[_Element] = []
    for number, line in enumerate(lines[1:], 2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        where = f"{path}:{number}"
        if words[0] == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise SceneError(f"{where}: unsupported PLY format line {line.strip()!r}")
            file_format = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise SceneError(f"{where}: malformed element line {line.strip()!r}")
            if any(e.name == words[1] for e in elements):
                raise SceneError(f"{where}: element {words[1]!r} appears twice")
            elements.append(_Element(words[1], int(words[2])))
        elif words[0] == "property":
            if not elements:
                raise SceneError(f"{where}: property before any element")
            if len(words) == 3 and words[1] in _TYPES:
                prop = _Property(words[2], _TYPES[words[1]])
            elif len(words) == 5 and words[1] == "list" and words[2] in _TYPES and words[3] in _TYPES:
                prop = _Property(words[4], _TYPES[words[3]], _TYPES[words[2]])
            else:
                raise SceneError(f"{where}: malformed property line {line.strip()!r}")
            if any(p.name == prop.name for p in elements[-1].properties):
                raise SceneError(f"{where}: property {prop.name!r} appears twice in element {elements[-1].name!r}")
            elements[-1].properties.append(prop)
        else:
            raise SceneError(f"{where}: unknown PLY header keyword {words[0]!r}")
    if file_format is None:
        raise SceneError(f"{path}: PLY header has no format line")
    return file_format, elements, body


def _read_binary(data: bytes, offset: int, element: _Element, order: str, path: Path) -> tuple[dict[str, np.ndarray], int]:
    """Properties of one binary element (lists as (count, L) arrays or lists of arrays)."""
    def scalar_dtype(props: list[_Property], list_length: int) -> np.dtype:
        fields = []
        for prop in props:
            if prop.is_list:
                fields.append((prop.name + "#count", order + prop.count_dtype))
                fields.append((prop.name, order + prop.dtype, (list_length,)))
            else:
                fields.append((prop.name, order + prop.dtype))
        return np.dtype(fields)

    lists = [p for p in element.properties if p.is_list]
    if element.count == 0:
        return {p.name: np.zeros((0, 3) if p.is_list else 0) for p in element.properties}, offset
    # Guess a constant list length from the first record (exact when there is one list,
    # which comes first or after fixed-size scalars), then verify every record.
    list_length = 0
    if len(lists) == 1:
        head = scalar_dtype(element.properties[: element.properties.index(lists[0])], 0).itemsize
        if offset + head + np.dtype(lists[0].count_dtype).itemsize > len(data):
            raise SceneError(f"{path}: file ends inside element {element.name!r}")
        list_length = int(np.frombuffer(data, order + lists[0].count_dtype, 1, offset + head)[0])
    if len(lists) <= 1 and 0 <= list_length <= len(data):
        dtype = scalar_dtype(element.properties, list_length)
        if offset + dtype.itemsize * element.count <= len(data):
            records = np.frombuffer(data, dtype, element.count, offset)
            if not lists or np.all(records[lists[0].name + "#count"] == list_length):
                return {p.name: records[p.name] for p in element.properties}, offset + dtype.itemsize * element.count
        elif not lists:
            raise SceneError(f"{path}: file ends inside element {element.name!r}")
    # Variable-length lists: record by record.
    columns: dict[str, list] = {p.name: [] for p in element.properties}
    for row in range(element.count):
        for prop in element.properties:
            dtype = np.dtype(order + (prop.count_dtype or prop.dtype))
            if offset + dtype.itemsize > len(data):
                raise SceneError(f"{path}: file ends inside element {element.name!r}")
            value = np.frombuffer(data, dtype, 1, offset)[0]
            offset += dtype.itemsize
            if prop.is_list:
                if not (np.isfinite(value) and value >= 0 and value == int(value)):
                    raise SceneError(f"{path}: element {element.name!r} record {row}: list {prop.name!r} has length {value}")
                items = np.dtype(order + prop.dtype)
                if offset + items.itemsize * int(value) > len(data):
                    raise SceneError(f"{path}: file ends inside element {element.name!r}")
                value = np.frombuffer(data, items, int(value), offset)
                offset += items.itemsize * len(value)
            columns[prop.name].append(value)
    return {name: (values if _is_list(element, name) else np.array(values)) for name, values in columns.items()}, offset


def _is_list(element: _Element, name: str) -> bool:
    return next(p for p in element.properties if p.name == name).is_list


def _read_ascii(lines: list[str], start: int, element: _Element, path: Path, first_line: int) -> dict[str, object]:
    """Properties of one ascii element, one record per line, starting at ``lines[start]``."""
    columns: dict[str, list] = {p.name: [] for p in element.properties}
    for row in range(element.count):
        number = first_line + start + row
        if start + row >= len(lines):
            raise SceneError(f"{path}: file ends inside element {element.name!r} (record {row})")
        words = lines[start + row].split()
        try:
            position = 0
            for prop in element.properties:
                if prop.is_list:
                    count = int(words[position])
                    values = words[position + 1 : position + 1 + count]
                    if len(values) != count:
                        raise IndexError
                    with np.errstate(over="ignore"):  # beyond float32: inf, refused where it matters
                        columns[prop.name].append(np.array(values, dtype=prop.dtype))
                    position += 1 + count
                else:
                    columns[prop.name].append(words[position])
                    position += 1
        except (IndexError, ValueError, OverflowError):
            raise SceneError(f"{path}:{number}: malformed {element.name!r} record {lines[start + row].strip()!r}") from None
        if position != len(words):
            raise SceneError(f"{path}:{number}: {element.name!r} record has {len(words) - position} extra value(s)")
    result: dict[str, object] = {}
    for prop in element.properties:
        if prop.is_list:
            result[prop.name] = columns[prop.name]
        else:
            result[prop.name] = _ascii_scalars(columns[prop.name], prop, element, path, first_line + start)
    return result


def _ascii_scalars(tokens: list[str], prop: _Property, element: _Element, path: Path, first_line: int) -> np.ndarray:
    """The values of one scalar property of an ascii element, as its type.

    Float values beyond the type's range become infinite (the callers refuse those where
    they matter); integer values must be whole and fit the type.

    Raises
    ------
    SceneError
        Naming the line of the first value that is not a number or does not fit.
    """
    dtype = np.dtype(prop.dtype)
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        row = next((i for i, token in enumerate(tokens) if not _is_number(token)), 0)
        raise SceneError(f"{path}:{first_line + row}: non-numeric {element.name!r} property {prop.name!r} value "
                         f"{tokens[row]!r}") from None
    if dtype.kind == "f":
        with np.errstate(over="ignore"):
            return values.astype(dtype)
    limits = np.iinfo(dtype)
    bad = ~(np.isfinite(values) & (values == np.round(values)) & (values >= limits.min) & (values <= limits.max))
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise SceneError(f"{path}:{first_line + row}: {element.name!r} property {prop.name!r} value {tokens[row]!r} "
                         f"is not an integer in {limits.min}..{limits.max}")
    return values.astype(dtype)


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _faces(lists: object, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Flat corner indices and per-face corner counts from a list property."""
    if isinstance(lists, np.ndarray):
        counts = np.full(len(lists), lists.shape[1], dtype=np.int64)
    else:
        counts = np.array([len(face) for face in lists], dtype=np.int64)
    if np.any(counts < 3):
        bad = int(np.flatnonzero(counts < 3)[0])
        raise SceneError(f"{path}: face {bad} has {counts[bad]} vertices (a face needs at least 3)")
    corners = lists.reshape(-1) if isinstance(lists, np.ndarray) else np.concatenate(lists) if len(lists) else np.zeros(0, np.int64)
    if corners.dtype.kind == "f":  # a float index list: whole numbers only
        whole = np.isfinite(corners) & (corners == np.round(corners))
        if not whole.all():
            bad = int(np.flatnonzero(~whole)[0])
            face = int(np.searchsorted(np.cumsum(counts), bad, side="right"))
            raise SceneError(f"{path}: face {face} has vertex index {corners[bad]}, not a whole number")
        corners = np.clip(corners, -(2.0**62), 2.0**62)  # beyond: out of range either way
    return corners.astype(np.int64), counts


def _materials(path: Path, material_ids: np.ndarray | None, log: WarningLog) -> tuple[list[Material], np.ndarray | None]:
    """Material table (side-car colours or defaults) and each face's index into it.

    The table is indexed by material id, 0 .. the largest id, unless the largest id is at
    least :data:`DENSE_MATERIAL_IDS` and the number of faces (most ids unused, as in a
    small file with ``material_id 4000000000``): then only the ids in use get a
    material, in increasing order, and a warning says so.
    """
    sidecar = path.with_name(path.stem + MATERIALS_SUFFIX)
    needed = 1 if material_ids is None else int(material_ids.max()) + 1
    ids = range(needed)
    if material_ids is not None and needed > max(len(material_ids), DENSE_MATERIAL_IDS):
        used, material_ids = np.unique(material_ids, return_inverse=True)
        ids = used.tolist()
        log.warn("sparse material ids", f"{path}: material ids up to {needed - 1} on {len(material_ids)} faces; "
                 f"the {len(ids)} ids in use get materials 0..{len(ids) - 1}")
    if not is_file(sidecar):
        if material_ids is None:
            return [Material("default")], None
        return [Material(f"material_{k}") for k in ids], material_ids
    try:
        entries = json.loads(read_source(sidecar))
        table: dict[int, Material] = {}
        for entry in entries:
            colour = entry.get("mean_texture_linear_rgb") or entry.get("mtl_Kd")
            albedo = tuple(float(c) for c in colour) if colour else Material(entry["name"]).albedo
            if len(albedo) != 3:
                raise ValueError(f"material {entry['id']}: colour needs 3 components")
            table[int(entry["id"])] = Material(str(entry["name"]), "diffuse", albedo)
    except (ValueError, KeyError, TypeError, AttributeError) as error:
        raise SceneError(f"{sidecar}: malformed material side-car ({error})") from None
    missing = [k for k in ids if k not in table]
    if missing:
        raise SceneError(f"{sidecar}: no entry for material id(s) {missing[:10]} used by {path}")
    return [table[k] for k in ids], material_ids


def parse_ply(data: bytes, path: Path, log: WarningLog | None = None) -> Scene:
    """Scene (no camera, no sky) from the bytes of a PLY file (see the module docstring).

    Raises
    ------
    SceneError
        Malformed header or body, missing ``x y z`` or faces, indices out of range,
        non-finite coordinates, an empty mesh.
    """
    log = log if log is not None else WarningLog()
    file_format, elements, body = _parse_header(data, path)
    order = _FORMATS[file_format]
    values: dict[str, dict[str, object]] = {}
    if order is None:
        lines = data[body:].decode("ascii", "replace").replace("\r\n", "\n").replace("\r", "\n").split("\n")
        header_lines = data[:body].count(b"\n")
        cursor = 0
        for element in elements:
            values[element.name] = _read_ascii(lines, cursor, element, path, header_lines + 1)
            cursor += element.count
    else:
        offset = body
        for element in elements:
            values[element.name], offset = _read_binary(data, offset, element, order, path)
    for name in values.keys() - {"vertex", "face"}:
        log.warn(f"element {name}", f"{path}: PLY element {name!r} ignored")
    vertex, face = values.get("vertex"), values.get("face")
    if vertex is None or not all(axis in vertex for axis in "xyz"):
        raise SceneError(f"{path}: no 'vertex' element with x, y, z properties")
    if face is None or not any(name in face for name in _FACE_LIST_NAMES):
        raise SceneError(f"{path}: no 'face' element with a vertex_indices list: the mesh has no faces")
    vertices = np.stack([np.asarray(vertex[axis], dtype=np.float64) for axis in "xyz"], axis=1)
    finite = (np.abs(vertices) <= FLOAT32_MAX).all(axis=1)  # False for NaN and infinities too
    if not finite.all():
        raise SceneError(f"{path}: vertex {int(np.flatnonzero(~finite)[0])} has a NaN, infinite or beyond-float32 coordinate")
    corners, counts = _faces(face[next(n for n in _FACE_LIST_NAMES if n in face)], path)
    if len(counts) == 0:
        raise SceneError(f"{path}: the mesh has no faces")
    if corners.min() < 0 or corners.max() >= len(vertices):
        bad = int(np.flatnonzero((corners < 0) | (corners >= len(vertices)))[0])
        face_index = int(np.searchsorted(np.cumsum(counts), bad, side="right"))
        raise SceneError(f"{path}: face {face_index} has vertex index {corners[bad]} outside 0..{len(vertices) - 1}")
    corner_triangles, face_of_triangle = fan_triangulate(counts)
    triangles = corners[corner_triangles]
    material_ids = None
    if "material_id" in face:
        material_ids = np.asarray(face["material_id"])
        if material_ids.dtype.kind == "f":
            whole = np.isfinite(material_ids) & (material_ids == np.round(material_ids))
            if not whole.all():
                raise SceneError(f"{path}: face {int(np.flatnonzero(~whole)[0])} has material_id "
                                 f"{material_ids[~whole][0]}, not a whole number")
            material_ids = np.clip(material_ids, -(2.0**62), 2.0**62)  # fits int64
        material_ids = material_ids.astype(np.int64)
        if material_ids.min() < 0:
            raise SceneError(f"{path}: negative material_id {material_ids.min()}")
    normals = None
    if all(axis in vertex for axis in ("nx", "ny", "nz")):
        given = np.stack([np.asarray(vertex[axis], dtype=np.float64) for axis in ("nx", "ny", "nz")], axis=1)
        normals = repair_normals(vertices, triangles, np.nan_to_num(given, nan=0.0, posinf=0.0, neginf=0.0), np.zeros(len(vertices), bool))
    texcoords = None
    for u, v in _TEXCOORD_NAMES:
        if u in vertex and v in vertex:
            with np.errstate(over="ignore"):  # beyond float32: infinite, refused below
                texcoords = np.stack([np.asarray(vertex[u], dtype=np.float32), np.asarray(vertex[v], dtype=np.float32)], axis=1)
            if not np.isfinite(texcoords).all():
                raise SceneError(f"{path}: texture coordinates contain NaN or infinite values")
            break
    materials, material_ids = _materials(path, material_ids, log)
    return Scene(
        name=path.stem,
        vertices=vertices.astype(np.float32),
        triangles=triangles.astype(np.int32),
        material_ids=np.zeros(len(triangles), np.int32) if material_ids is None else material_ids[face_of_triangle],
        materials=materials,
        normals=normals,
        texcoords=texcoords,
        sources=[str(path)],
    )


def read_ply(path: str | Path) -> Scene:
    """Parse the PLY file at ``path`` (and its material side-car) without the cache."""
    path = Path(path)
    return parse_ply(read_source(path), path)


def load_ply(path: str | Path, *, use_cache: bool = True) -> Scene:
    """Parse the PLY file at ``path`` through the ``.npz`` cache (see :mod:`kdtrace.io`)."""
    path = Path(path)
    data = read_source(path)
    sidecar = path.with_name(path.stem + MATERIALS_SUFFIX)
    sources = [
        ("path", str(path.resolve()).encode()),
        ("ply", data),
        ("materials", sidecar.read_bytes() if is_file(sidecar) else None),
    ]
    return cached_load(cache_key(sources), lambda log: parse_ply(data, path, log), use_cache)
