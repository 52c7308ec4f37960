"""Procedural test scenes: deterministic from a seed, placeable at any scale and offset.

Every generator returns a :class:`~kdtrace.scene.Scene` with one grey diffuse material,
a default camera (:func:`kdtrace.scenes.default_camera`) and a white sky. Geometry is
built in float64 in a unit-sized frame (about ``[-1, 1]^3``), then mapped to
``base * scale + offset`` and rounded to float32 once, so ``scale`` (1e-4 .. 1e5) and
``offset`` (far from the origin) test the trees' numerical robustness.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from kdtrace.resources import require_memory
from kdtrace.scene import Material, Scene, Sky
from kdtrace.scenes import DEFAULT_SKY_RADIANCE, default_camera


def _scene(name: str, corners: np.ndarray, scale: float, offset: Sequence[float]) -> Scene:
    """Scene of triangle soup ``corners`` (T, 3, 3) placed at ``corners * scale + offset``."""
    if not scale > 0.0:
        raise ValueError(f"scale must be positive, got {scale}")
    placed = corners.reshape(-1, 3) * scale + np.asarray(offset, dtype=np.float64)
    vertices = placed.astype(np.float32)
    return Scene(
        name=name,
        vertices=vertices,
        triangles=np.arange(len(vertices)).reshape(-1, 3),
        material_ids=np.zeros(len(corners)),
        materials=[Material("procedural")],
        cameras=[default_camera(vertices)],
        sky=Sky(DEFAULT_SKY_RADIANCE),
    )


def _unit_vectors(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    vectors = rng.normal(size=(*shape, 3))
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def random_soup(
    n_triangles: int = 1000,
    *,
    seed: int = 0,
    sizes: tuple[float, float] = (0.01, 0.2),
    scale: float = 1.0,
    offset: Sequence[float] = (0.0, 0.0, 0.0),
) -> Scene:
    """Random triangles with centres uniform in ``[-1, 1]^3``.

    Parameters
    ----------
    n_triangles : int
        Number of triangles.
    seed : int
        Seed of the generator.
    sizes : (float, float)
        Range of the triangles' radii (distance of the corners from the centre, before
        ``scale``), sampled log-uniformly.
    scale, offset : float, 3 floats
        Placement of the unit frame (see the module docstring).
    """
    if n_triangles < 1 or not 0.0 < sizes[0] <= sizes[1]:
        raise ValueError("random_soup needs n_triangles >= 1 and 0 < sizes[0] <= sizes[1]")
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1.0, 1.0, size=(n_triangles, 1, 3))
    radii = np.exp(rng.uniform(np.log(sizes[0]), np.log(sizes[1]), size=(n_triangles, 1, 1)))
    return _scene("random-soup", centres + radii * _unit_vectors(rng, (n_triangles, 3)), scale, offset)


def heightfield_grid(
    cells: int = 32,
    *,
    seed: int = 0,
    amplitude: float = 0.2,
    scale: float = 1.0,
    offset: Sequence[float] = (0.0, 0.0, 0.0),
) -> Scene:
    """A regular ``cells x cells`` grid over ``[-1, 1]^2`` (2 triangles per cell), height along z.

    The height is a sum of four random sine waves of total amplitude ``amplitude``
    (0 gives a flat, coplanar grid).
    """
    if cells < 1:
        raise ValueError(f"heightfield_grid needs cells >= 1, got {cells}")
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(-1.0, 1.0, cells + 1), np.linspace(-1.0, 1.0, cells + 1), indexing="ij")
    frequencies = rng.uniform(0.5, 4.0, size=(4, 2))
    phases = rng.uniform(0.0, 2.0 * np.pi, size=4)
    z = sum(np.sin(np.pi * (f[0] * x + f[1] * y) + p) for f, p in zip(frequencies, phases, strict=True)) * amplitude / 4.0
    points = np.stack([x, y, z], axis=-1)
    a, b, c, d = points[:-1, :-1], points[1:, :-1], points[1:, 1:], points[:-1, 1:]
    corners = np.concatenate([np.stack([a, b, c], -2).reshape(-1, 3, 3), np.stack([a, c, d], -2).reshape(-1, 3, 3)])
    return _scene("heightfield-grid", corners, scale, offset)


def slivers(
    n_triangles: int = 1000,
    *,
    seed: int = 0,
    max_aspect: float = 1e6,
    scale: float = 1.0,
    offset: Sequence[float] = (0.0, 0.0, 0.0),
) -> Scene:
    """Long thin triangles: length 0.2 .. 1, aspect ratio (length / width) log-uniform in ``[1, max_aspect]``.

    Centres are uniform in ``[-1, 1]^3``, directions uniformly random.
    """
    if n_triangles < 1 or not max_aspect >= 1.0:
        raise ValueError("slivers needs n_triangles >= 1 and max_aspect >= 1")
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1.0, 1.0, size=(n_triangles, 3))
    lengths = rng.uniform(0.2, 1.0, size=(n_triangles, 1))
    widths = lengths / np.exp(rng.uniform(0.0, np.log(max_aspect), size=(n_triangles, 1)))
    along = _unit_vectors(rng, (n_triangles,))
    across = np.cross(along, _unit_vectors(rng, (n_triangles,)))
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    corners = np.stack(
        [centres - 0.5 * lengths * along, centres + 0.5 * lengths * along, centres + widths * across], axis=1
    )
    return _scene("slivers", corners, scale, offset)


def coplanar_stack(
    n_triangles: int = 1000,
    *,
    seed: int = 0,
    duplicate_fraction: float = 0.25,
    scale: float = 1.0,
    offset: Sequence[float] = (0.0, 0.0, 0.0),
) -> Scene:
    """Many overlapping triangles in the plane z = 0, a fraction of them exact duplicates.

    Corners are uniform in ``[-1, 1]^2``; ``duplicate_fraction`` of the triangles copy an
    other one (same corners, same order), so hits tie exactly.
    """
    if n_triangles < 1 or not 0.0 <= duplicate_fraction < 1.0:
        raise ValueError("coplanar_stack needs n_triangles >= 1 and 0 <= duplicate_fraction < 1")
    rng = np.random.default_rng(seed)
    unique = max(1, int(round(n_triangles * (1.0 - duplicate_fraction))))
    flat = np.zeros((unique, 3, 3))
    flat[:, :, :2] = rng.uniform(-1.0, 1.0, size=(unique, 3, 2))
    copies = flat[rng.integers(0, unique, size=n_triangles - unique)]
    corners = np.concatenate([flat, copies])[rng.permutation(n_triangles)]
    return _scene("coplanar-stack", corners, scale, offset)


#: Upper bound of the bytes :func:`instanced_scene` allocates per triangle at its peak (float64
#: placements, normals and int64 indices before the float32/int32 copies; about 190 for the
#: shipped scans, whose vertices and triangles are about as many).
INSTANCED_BYTES_PER_TRIANGLE = 320


def instanced_scene_bytes(triangles: int) -> int:
    """Upper bound of the memory :func:`instanced_scene` needs for ``triangles`` triangles, in bytes."""
    return triangles * INSTANCED_BYTES_PER_TRIANGLE


def instanced_scene(
    base: Scene,
    min_triangles: int,
    *,
    seed: int = 0,
    terrain_cells: int = 0,
) -> Scene:
    """A production-scale scene: copies of ``base`` on a displaced terrain, at least ``min_triangles``.

    The copies stand on a square grid in the x–z plane (``base``'s up axis is +y, as the shipped
    scans'), spaced 1.25 times ``base``'s largest horizontal extent; each is turned about +y
    by a random angle, scaled by a random factor in [0.8, 1.2] and shifted by up to a tenth of
    the spacing, all drawn from ``seed``. Under them lies a heightfield of ``terrain_cells`` ×
    ``terrain_cells`` cells (two triangles each; 0 for none), a sum of four random sine waves of
    amplitude one tenth of ``base``'s height. The geometry is exact copies (not instances the
    trees would share): every triangle is stored, as in a flattened production scene. Materials,
    normals and texture coordinates of ``base`` are copied with it.

    Parameters
    ----------
    base : Scene
        The scan to copy (e.g. ``load_scene("samurai-monastery")``, 262k triangles).
    min_triangles : int
        The scene has at least this many triangles (copies are added until it does).
    seed : int
        Seed of the placements and of the terrain.
    terrain_cells : int
        Cells per side of the terrain (0: none).

    Returns
    -------
    Scene
        Named ``BASE-xCOPIES-tCELLS-sSEED``; its default camera sees the whole.

    Raises
    ------
    ValueError
        For ``min_triangles < 1`` or ``terrain_cells < 0``.
    kdtrace.resources.InsufficientMemoryError
        Before anything is allocated, when :func:`instanced_scene_bytes` exceed the memory available.
    """
    if min_triangles < 1 or terrain_cells < 0:
        raise ValueError(f"instanced_scene needs min_triangles >= 1 and terrain_cells >= 0, got {min_triangles}, "
                         f"{terrain_cells}")
    require_memory(instanced_scene_bytes(max(min_triangles, 2 * terrain_cells**2)),
                   f"a scene of {min_triangles:,} triangles from copies of {base.name!r}",
                   "ask for fewer triangles")
    terrain_triangles = 2 * terrain_cells**2
    copies = max(1, -(-(min_triangles - terrain_triangles) // len(base.triangles)))
    side = int(np.ceil(np.sqrt(copies)))
    rng = np.random.default_rng(seed)
    vertices = base.vertices.astype(np.float64)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    centre = (low + high) / 2.0  # of the bounding box
    spacing = 1.25 * float(max(high[0] - low[0], high[2] - low[2]))
    angles = rng.uniform(0.0, 2.0 * np.pi, copies)
    scales = rng.uniform(0.8, 1.2, copies)
    jitter = rng.uniform(-0.1, 0.1, (copies, 2)) * spacing
    placed_vertices, placed_normals = [], []
    for index in range(copies):
        cos, sin = np.cos(angles[index]), np.sin(angles[index])
        turn = np.array([[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]])
        row, column = divmod(index, side)
        shift = np.array([(column - (side - 1) / 2) * spacing + jitter[index, 0], 0.0,
                          (row - (side - 1) / 2) * spacing + jitter[index, 1]])
        # centred horizontally, standing on y = 0, turned, scaled, then put on its grid cell
        placed_vertices.append(((vertices - [centre[0], low[1], centre[2]]) @ turn.T) * scales[index] + shift)
        if base.normals is not None:
            placed_normals.append(base.normals.astype(np.float64) @ turn.T)
    count = len(base.vertices)
    triangles = [base.triangles.astype(np.int64) + index * count for index in range(copies)]
    material_ids = [base.material_ids] * copies
    materials = list(base.materials)
    normals = np.concatenate(placed_normals) if base.normals is not None else None
    texcoords = np.concatenate([base.texcoords] * copies) if base.texcoords is not None else None
    if terrain_cells:
        extent = side * spacing / 2.0
        ground = heightfield_grid(terrain_cells, seed=seed, amplitude=0.1 * float(high[1] - low[1]) / extent)
        # heightfield_grid's height is along z over x, y in [-1, 1]: lay it in the x–z plane, height along y
        terrain = ground.vertices.astype(np.float64)[:, [0, 2, 1]] * [extent, extent, extent]
        triangles.append(ground.triangles.astype(np.int64) + copies * count)
        placed_vertices.append(terrain)
        material_ids.append(np.full(len(ground.triangles), len(materials)))
        materials.append(Material("terrain"))
        if normals is not None:  # the terrain has no shading normals: its geometric ones are used
            normals = None
        if texcoords is not None:
            texcoords = np.concatenate([texcoords, np.zeros((len(terrain), 2), np.float32)])
    all_vertices = np.concatenate(placed_vertices).astype(np.float32)
    return Scene(
        name=f"{base.name}-x{copies}-t{terrain_cells}-s{seed}",
        vertices=all_vertices,
        triangles=np.concatenate(triangles).astype(np.int32),
        material_ids=np.concatenate(material_ids).astype(np.int32),
        materials=materials,
        normals=None if normals is None else normals.astype(np.float32),
        texcoords=texcoords,
        cameras=[default_camera(all_vertices)],
        sky=base.sky if base.sky is not None else Sky(DEFAULT_SKY_RADIANCE),
        sources=[*base.sources, f"kdtrace.procedural.instanced_scene(min_triangles={min_triangles}, seed={seed}, "
                 f"terrain_cells={terrain_cells})"],
    )
