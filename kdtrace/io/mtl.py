"""Wavefront MTL reader: maps each ``newmtl`` block to a :class:`kdtrace.scene.Material`.

Our renderer knows three materials (Lambertian diffuse, perfect mirror, smooth
dielectric) plus emission, so MTL's Phong/Blinn model is mapped, in this order:

1. **Dielectric** -- ``Ni`` differs from 1 *and* the material is transparent (some
   ``Tf`` component < 1, ``d`` < 1 or ``Tr`` > 0): ``kind="dielectric"``, ``ior=Ni``,
   albedo = ``Tf`` (white when ``Tf`` is absent).
2. **Mirror** -- the largest ``Ks`` component is >= :data:`MIRROR_MIN_KS` and
   ``Ns`` >= :data:`MIRROR_MIN_NS`, and the material is opaque: ``kind="mirror"``,
   albedo = ``Ks``.
3. **Diffuse** otherwise, albedo = ``Kd`` (the :class:`Material` default grey when
   ``Kd`` is absent). *Approximation:* a glossy Blinn lobe (``Ks`` with moderate ``Ns``)
   is dropped; only ``Kd`` is kept. ``Ka`` and ``illum`` are ignored (the values decide).
   ``Ni`` of an opaque material is ignored.

Independently of the kind, ``Ke`` with a positive component makes the material an
area emitter of radiance ``Ke``. ``map_Kd`` is kept as a path (resolved relative to the
``.mtl`` file, options before the file name dropped, existence not checked); the other
texture maps are ignored. Colours outside [0, 1] are clipped (with a warning); a single
value ``Kd r`` means grey ``r r r``. Unknown keys are reported once per key per file as
a :class:`kdtrace.io.SceneWarning` naming the file and line.
"""

from __future__ import annotations

from pathlib import Path

from kdtrace.io import SceneError, WarningLog, decode_text, read_source
from kdtrace.scene import Material

#: A specular colour at least this large (max component) with a sharp lobe is a mirror.
MIRROR_MIN_KS = 0.9
#: Phong exponent from which a strong specular lobe is treated as a perfect mirror.
MIRROR_MIN_NS = 500.0

_COLOUR_KEYS = ("Ka", "Kd", "Ks", "Ke", "Tf")
_SCALAR_KEYS = ("Ns", "Ni", "d", "Tr")
# Keys understood and deliberately ignored (ambient term, illumination model, maps we
# do not render).
_IGNORED_KEYS = frozenset(
    {"illum", "map_Ka", "map_Ks", "map_Ns", "map_d", "map_Bump", "map_bump", "bump", "disp", "decal", "refl", "sharpness"}
)


def _colour(values: list[str], key: str, origin: str) -> tuple[float, float, float]:
    if values and values[0] in ("spectral", "xyz"):
        raise SceneError(f"{origin}: '{key} {values[0]}' colours are not supported; give r g b")
    if len(values) not in (1, 3):
        raise SceneError(f"{origin}: '{key}' needs 1 or 3 numbers, got {len(values)}")
    numbers = [_number(v, key, origin) for v in values]
    return (numbers[0],) * 3 if len(numbers) == 1 else tuple(numbers)


def _number(token: str, key: str, origin: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise SceneError(f"{origin}: '{key}' value {token!r} is not a number") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise SceneError(f"{origin}: '{key}' value {token!r} is not finite")
    return value


def _clip(colour: tuple[float, float, float], key: str, origin: str, log: WarningLog) -> tuple[float, float, float]:
    clipped = tuple(min(max(c, 0.0), 1.0) for c in colour)
    if clipped != colour:
        log.warn(f"clip {key}", f"{origin}: '{key}' {colour} outside [0, 1], clipped to {clipped}")
    return clipped


def _to_material(name: str, fields: dict[str, object], where: str, log: WarningLog) -> Material:
    ks = fields.get("Ks", (0.0, 0.0, 0.0))
    tf = fields.get("Tf")
    transparent = (tf is not None and min(tf) < 1.0) or fields.get("d", 1.0) < 1.0 or fields.get("Tr", 0.0) > 0.0
    ior = float(fields.get("Ni", 1.0))
    emission = tuple(max(c, 0.0) for c in fields.get("Ke", (0.0, 0.0, 0.0)))
    texture = fields.get("map_Kd")
    if ior != 1.0 and transparent:
        albedo = _clip(tf if tf is not None else (1.0, 1.0, 1.0), "Tf", where, log)
        return Material(name, "dielectric", albedo, emission, ior, texture)
    if not transparent and max(ks) >= MIRROR_MIN_KS and fields.get("Ns", 0.0) >= MIRROR_MIN_NS:
        return Material(name, "mirror", _clip(ks, "Ks", where, log), emission, 1.0, texture)
    albedo = _clip(fields["Kd"], "Kd", where, log) if "Kd" in fields else Material(name).albedo
    return Material(name, "diffuse", albedo, emission, 1.0, texture)


def parse_mtl(data: bytes, path: Path, log: WarningLog) -> dict[str, Material]:
    """Materials of an MTL file's bytes, by name.

    Parameters
    ----------
    data : bytes
        File content (any of LF, CRLF, CR line ends; UTF-8 or, after a byte order mark,
        UTF-16; see :func:`kdtrace.io.decode_text`).
    path : Path
        The file, for messages and to resolve ``map_Kd``.
    log : WarningLog
        Receives warnings (unknown keys, clipped colours).

    Raises
    ------
    SceneError
        Malformed value, a key before the first ``newmtl``, a duplicate material name.
    """
    text = decode_text(data)
    materials: dict[str, Material] = {}
    name: str | None = None
    start = 0
    fields: dict[str, object] = {}
    for number, line in enumerate(text.split("\n"), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        key, values = parts[0], parts[1:]
        origin = f"{path}:{number}"
        if key == "newmtl":
            if not values:
                raise SceneError(f"{origin}: 'newmtl' without a material name")
            if name is not None:
                materials[name] = _to_material(name, fields, f"{path}:{start}", log)
            name, start, fields = " ".join(values), number, {}
            if name in materials:
                raise SceneError(f"{origin}: material {name!r} is defined twice")
            continue
        if name is None:
            raise SceneError(f"{origin}: '{key}' before the first 'newmtl'")
        if key in _COLOUR_KEYS:
            fields[key] = _colour(values, key, origin)
        elif key in _SCALAR_KEYS:
            if len(values) != 1:
                raise SceneError(f"{origin}: '{key}' needs 1 number, got {len(values)}")
            fields[key] = _number(values[0], key, origin)
        elif key == "map_Kd":
            if not values:
                raise SceneError(f"{origin}: 'map_Kd' without a file name")
            fields[key] = str(path.parent / values[-1])
        elif key not in _IGNORED_KEYS:
            log.warn(f"key {key}", f"{origin}: unknown MTL key {key!r} ignored")
    if name is not None:
        materials[name] = _to_material(name, fields, f"{path}:{start}", log)
    return materials


def read_mtl(path: str | Path, log: WarningLog | None = None) -> dict[str, Material]:
    """Materials of the MTL file at ``path``, by name (see the module docstring for the mapping)."""
    path = Path(path)
    return parse_mtl(read_source(path), path, log if log is not None else WarningLog())
