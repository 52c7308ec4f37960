"""Procedural generators: determinism, counts, placement at extreme scales, special shapes."""

from __future__ import annotations

import numpy as np
import pytest

from kdtrace.procedural import coplanar_stack, heightfield_grid, random_soup, slivers

GENERATORS = {
    "random_soup": lambda **kw: random_soup(200, **kw),
    "heightfield_grid": lambda **kw: heightfield_grid(10, **kw),
    "slivers": lambda **kw: slivers(200, **kw),
    "coplanar_stack": lambda **kw: coplanar_stack(200, **kw),
}


@pytest.mark.parametrize("name", GENERATORS)
def test_deterministic_from_the_seed(name):
    make = GENERATORS[name]
    assert make(seed=3).geometry_hash() == make(seed=3).geometry_hash()
    assert make(seed=3).geometry_hash() != make(seed=4).geometry_hash()


@pytest.mark.parametrize("name", GENERATORS)
@pytest.mark.parametrize(("scale", "offset"), [(1.0, (0, 0, 0)), (1e-4, (0, 0, 0)), (1e5, (0, 0, 0)), (1e-2, (1e3, -2e3, 5e2)),
                                               (10.0, (1e5, 1e5, 1e5))])
def test_placement_camera_and_sky(name, scale, offset, camera_coverage):
    scene = GENERATORS[name](seed=1, scale=scale, offset=offset)
    unit = GENERATORS[name](seed=1)
    expected = unit.vertices.astype(np.float64) * scale + np.asarray(offset, dtype=np.float64)
    np.testing.assert_allclose(scene.vertices, expected, rtol=1e-6, atol=1e-6 * scale)
    assert scene.sky is not None and scene.materials[0].kind == "diffuse"
    central_hit, fraction = camera_coverage(scene, rays_per_side=7)
    assert central_hit or fraction > 0.0  # a sparse soup may leave the centre empty


def test_counts():
    assert len(random_soup(123).triangles) == 123
    assert len(heightfield_grid(7).triangles) == 2 * 7 * 7
    assert len(slivers(50).triangles) == 50
    assert len(coplanar_stack(80).triangles) == 80


def test_slivers_reach_the_requested_aspect_ratio():
    scene = slivers(2000, seed=2, max_aspect=1e6)
    corners = scene.vertices.astype(np.float64)[scene.triangles]
    longest = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)
    height = 2.0 * scene.triangle_areas() / longest
    aspect = longest / np.maximum(height, 1e-300)
    assert aspect.max() > 1e5 and aspect.min() >= 0.5
    some = np.array([1999, 0, 7, 7])
    assert np.array_equal(scene.triangle_areas(some), scene.triangle_areas()[some])  # only those triangles


def test_coplanar_stack_is_flat_with_exact_duplicates():
    scene = coplanar_stack(400, seed=5, duplicate_fraction=0.25, offset=(0, 0, 3))
    assert np.all(scene.vertices[:, 2] == 3.0)
    corners = scene.vertices[scene.triangles].reshape(len(scene.triangles), -1)
    assert len(np.unique(corners, axis=0)) < len(corners) * 0.8


def test_flat_heightfield_and_bad_arguments():
    assert np.all(heightfield_grid(4, amplitude=0.0).vertices[:, 2] == 0.0)
    with pytest.raises(ValueError):
        random_soup(0)
    with pytest.raises(ValueError):
        slivers(10, max_aspect=0.5)
    with pytest.raises(ValueError):
        heightfield_grid(5, scale=0.0)


def test_instanced_scene_reaches_its_triangle_count_reproducibly(shared_scenes):
    from kdtrace.procedural import instanced_scene
    from kdtrace.scenes import load_scene

    base = load_scene("bunny")
    scene = instanced_scene(base, 300_000, seed=1, terrain_cells=64)
    copies = -(-(300_000 - 2 * 64**2) // len(base.triangles))
    assert len(scene.triangles) == copies * len(base.triangles) + 2 * 64**2 >= 300_000
    assert scene.name == f"bunny-x{copies}-t64-s1" and scene.materials[-1].name == "terrain"
    again = instanced_scene(base, 300_000, seed=1, terrain_cells=64)
    assert np.array_equal(scene.vertices, again.vertices) and np.array_equal(scene.triangles, again.triangles)
    other = instanced_scene(base, 300_000, seed=2, terrain_cells=64)
    assert not np.array_equal(scene.vertices, other.vertices)
    # every copy stands on y = 0 and is the base turned about +y and scaled: its edge lengths scale together
    first = scene.vertices[: len(base.vertices)].astype(np.float64)
    assert first[:, 1].min() == pytest.approx(0.0, abs=1e-6)
    ratio = np.linalg.norm(first[1] - first[0]) / np.linalg.norm(base.vertices[1].astype(np.float64) - base.vertices[0])
    assert 0.8 - 1e-6 <= ratio <= 1.2 + 1e-6
    with pytest.raises(ValueError, match="min_triangles"):
        instanced_scene(base, 0)
