"""The in-memory scene model shared by every consumer (our trees, Embree, Mitsuba).

One :class:`Scene` holds float32 vertices, int32 triangle indices, a per-triangle
material id, optional per-vertex shading normals and texture coordinates, a material
table, lights and cameras. Loaders (``kdtrace.io``) and scene descriptions
(``kdtrace.scenes``) produce it; nothing downstream reads files.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

MaterialKind = Literal["diffuse", "mirror", "dielectric"]


@dataclass(frozen=True)
class Material:
    """A surface material, mapped from MTL (see ``kdtrace.io.mtl`` for the rules).

    Attributes
    ----------
    name : str
        Material name as in the source file.
    kind : {"diffuse", "mirror", "dielectric"}
        Lambertian diffuse, perfect mirror, or smooth dielectric.
    albedo : tuple of 3 floats
        Linear RGB reflectance in [0, 1] (diffuse colour, mirror tint or glass
        transmittance).
    emission : tuple of 3 floats
        Linear RGB radiance emitted from the front side (W sr^-1 m^-2, arbitrary scale);
        all zeros for a non-emitter.
    ior : float
        Index of refraction of a dielectric (1.0 otherwise).
    texture : str or None
        Path of the diffuse texture (``map_Kd``), when there is one.
    """

    name: str
    kind: MaterialKind = "diffuse"
    albedo: tuple[float, float, float] = (0.5, 0.5, 0.5)
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ior: float = 1.0
    texture: str | None = None

    @property
    def is_emitter(self) -> bool:
        return any(c > 0.0 for c in self.emission)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Attributes
    ----------
    position, look_at, up : tuple of 3 floats
        World-space eye point, target point and up vector (scene units).
    fov : float
        Vertical field of view in degrees.
    width, height : int
        Image resolution in pixels.
    """

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov: float = 40.0
    width: int = 512
    height: int = 512

    def __post_init__(self) -> None:
        if not 0.0 < self.fov < 180.0:
            raise ValueError(f"camera fov must be in (0, 180) degrees, got {self.fov}")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera resolution must be positive, got {self.width}x{self.height}")
        forward = np.subtract(self.look_at, self.position)
        if not np.all(np.isfinite(forward)) or np.linalg.norm(forward) == 0.0:
            raise ValueError("camera look_at must differ from position")
        if np.linalg.norm(np.cross(forward, self.up)) == 0.0:
            raise ValueError("camera up must not be parallel to the viewing direction")


@dataclass(frozen=True)
class Sky:
    """A constant environment light of linear RGB radiance."""

    radiance: tuple[float, float, float]


@dataclass
class Scene:
    """Triangle mesh, materials, lights and cameras of one scene.

    Attributes
    ----------
    name : str
        Scene name (description file stem or mesh file stem).
    vertices : ndarray, float32, shape (V, 3)
        Vertex positions in scene units.
    triangles : ndarray, int32, shape (T, 3)
        Vertex indices of each triangle, counter-clockwise seen from the front.
    material_ids : ndarray, int32, shape (T,)
        Index into ``materials`` per triangle.
    materials : list of Material
        The material table.
    normals : ndarray, float32, shape (V, 3), optional
        Per-vertex shading normals (unit length), or None.
    texcoords : ndarray, float32, shape (V, 2), optional
        Per-vertex texture coordinates, or None.
    cameras : list of Camera
        At least one camera; ``camera`` is the first.
    sky : Sky or None
        Constant environment light, or None for a black background.
    sources : list of str
        The files the scene was made from, for error messages and provenance.
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    material_ids: np.ndarray
    materials: list[Material]
    normals: np.ndarray | None = None
    texcoords: np.ndarray | None = None
    cameras: list[Camera] = field(default_factory=list)
    sky: Sky | None = None
    sources: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int32)
        self.material_ids = np.ascontiguousarray(self.material_ids, dtype=np.int32)
        origin = self.sources[0] if self.sources else self.name
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"{origin}: vertices must have shape (V, 3), got {self.vertices.shape}")
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3:
            raise ValueError(f"{origin}: triangles must have shape (T, 3), got {self.triangles.shape}")
        if len(self.triangles) == 0:
            raise ValueError(f"{origin}: the mesh has no triangles")
        if not np.all(np.isfinite(self.vertices)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(self.vertices), axis=1))[0])
            raise ValueError(f"{origin}: vertex {bad} has a NaN or infinite coordinate")
        if self.triangles.min() < 0 or self.triangles.max() >= len(self.vertices):
            bad = int(np.flatnonzero((self.triangles < 0).any(1) | (self.triangles >= len(self.vertices)).any(1))[0])
            raise ValueError(
                f"{origin}: triangle {bad} has a vertex index outside 0..{len(self.vertices) - 1}"
            )
        if self.material_ids.shape != (len(self.triangles),):
            raise ValueError(f"{origin}: material_ids must have shape ({len(self.triangles)},)")
        if len(self.materials) == 0 or self.material_ids.min() < 0 or self.material_ids.max() >= len(self.materials):
            raise ValueError(f"{origin}: material ids must index the {len(self.materials)} materials")
        for attr, width in (("normals", 3), ("texcoords", 2)):
            value = getattr(self, attr)
            if value is not None:
                value = np.ascontiguousarray(value, dtype=np.float32)
                if value.shape != (len(self.vertices), width):
                    raise ValueError(f"{origin}: {attr} must have shape ({len(self.vertices)}, {width})")
                if not np.all(np.isfinite(value)):
                    raise ValueError(f"{origin}: {attr} contain NaN or infinite values")
                setattr(self, attr, value)

    # ----------------------------------------------------------------- geometry
    @property
    def camera(self) -> Camera:
        """The first (default) camera."""
        if not self.cameras:
            raise ValueError(f"scene {self.name!r} has no camera")
        return self.cameras[0]

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lower, upper corner), float64."""
        return self.vertices.min(0).astype(np.float64), self.vertices.max(0).astype(np.float64)

    def triangle_areas(self, indices: np.ndarray | None = None) -> np.ndarray:
        """Area of every triangle (or of the triangles ``indices``) in squared scene units, in float64."""
        triangles = self.triangles if indices is None else self.triangles[indices]
        corners = self.vertices.astype(np.float64)[triangles]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        return 0.5 * np.linalg.norm(cross, axis=1)

    def degenerate_mask(self) -> np.ndarray:
        """True for triangles with zero area (collinear or repeated vertices)."""
        return self.triangle_areas() == 0.0

    @property
    def emitter_triangles(self) -> np.ndarray:
        """Indices of the triangles whose material emits light."""
        emissive = np.array([m.is_emitter for m in self.materials])
        return np.flatnonzero(emissive[self.material_ids])

    # ----------------------------------------------------------------- identity
    def geometry_hash(self) -> str:
        """SHA-256 of the vertex and index arrays (what a KD-tree depends on)."""
        digest = hashlib.sha256()
        for array in (self.vertices, self.triangles):
            digest.update(str(array.shape).encode())
            digest.update(np.ascontiguousarray(array).tobytes())
        return digest.hexdigest()

    def content_hash(self) -> str:
        """SHA-256 of everything that changes an image: geometry, attributes, materials, lights, cameras."""
        digest = hashlib.sha256(self.geometry_hash().encode())
        for array in (self.material_ids, self.normals, self.texcoords):
            if array is not None:
                digest.update(np.ascontiguousarray(array).tobytes())
        digest.update(repr((self.materials, self.cameras, self.sky)).encode())
        return digest.hexdigest()

    def summary(self) -> dict[str, object]:
        """Counts for reports: triangles, vertices, materials, emitters, zero-area triangles, area."""
        areas = self.triangle_areas()
        return {
            "name": self.name,
            "triangles": int(len(self.triangles)),
            "vertices": int(len(self.vertices)),
            "materials": len(self.materials),
            "emitter_triangles": int(len(self.emitter_triangles)),
            "zero_area_triangles": int((areas == 0.0).sum()),
            "surface_area": float(areas.sum()),
        }
