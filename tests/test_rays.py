"""Ray generators: determinism, shapes, validity, geometric guarantees."""

import numpy as np
import pytest

from kdtrace import rays
from kdtrace.oracle import intersect_brute_force
from kdtrace.scene import Camera, Material, Scene

KINDS = [rays.primary_rays, rays.random_rays, rays.vertex_rays, rays.edge_rays, rays.shadow_rays]


def box_scene(emitting=True):
    """A closed box [0,2]x[0,1]x[0,1] (12 triangles), a zero-area triangle, and a small light quad under the lid."""
    corners = np.array([[x, y, z] for x in (0, 2) for y in (0, 1) for z in (0, 1)], float)
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = [t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))]
    light = np.array([[0.8, 0.99, 0.4], [1.2, 0.99, 0.4], [1.2, 0.99, 0.6], [0.8, 0.99, 0.6]])
    vertices = np.vstack([corners, light])
    triangles += [(8, 9, 10), (8, 10, 11), (0, 0, 4)]
    material_ids = [0] * 12 + [1 if emitting else 0] * 2 + [0]
    camera = Camera((1.0, 0.5, 0.9), (1.0, 0.5, 0.0), fov=60.0, width=32, height=24)
    materials = [Material("white"), Material("light", emission=(5.0, 5.0, 5.0))]
    return Scene("box", vertices, np.array(triangles), np.array(material_ids), materials, cameras=[camera])


@pytest.fixture(scope="module")
def scene():
    return box_scene()


@pytest.mark.parametrize("make", KINDS)
def test_deterministic_valid_float32(scene, make):
    first, again, other = make(scene, 300, 5), make(scene, 300, 5), make(scene, 300, 6)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(first[1], other[1])
    origins, directions = first[:2]
    for array in first:
        assert array.dtype == np.float32 and np.all(np.isfinite(array))
    assert origins.shape == directions.shape == (300, 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-6)


@pytest.mark.parametrize("make", KINDS)
def test_validation(scene, make):
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="ray count"):
            make(scene, bad, 0)
    with pytest.raises(TypeError, match="Scene"):
        make("cbox", 10, 0)


def test_random_rays_fill_enlarged_box(scene):
    origins, _ = rays.random_rays(scene, 4000, 0)
    assert origins.min(0) == pytest.approx([-0.1, -0.1, -0.1], abs=0.01)
    assert origins.max(0) == pytest.approx([2.1, 1.1, 1.1], abs=0.01)


def distance_to_points(origins, directions, points):
    """(N, P) distance from each ray's line to each point, float64."""
    o, d = origins.astype(np.float64), directions.astype(np.float64)
    rel = points[None, :, :] - o[:, None, :]
    along = np.einsum("npk,nk->np", rel, d) / np.einsum("nk,nk->n", d, d)[:, None]
    return np.linalg.norm(rel - along[..., None] * d[:, None, :], axis=2), along


def test_vertex_rays_pass_through_a_vertex(scene):
    origins, directions = rays.vertex_rays(scene, 400, 1)
    distance, along = distance_to_points(origins, directions, scene.vertices.astype(np.float64))
    nearest = distance.argmin(1)
    assert np.all(distance.min(1) < 1e-6)
    assert np.all(along[np.arange(400), nearest] > 0.0)  # the vertex is ahead of the origin
    # ray origins: half inside the enlarged box, half outside it
    inside = np.all((origins > -0.11) & (origins < [2.11, 1.11, 1.11]), axis=1)
    assert inside[::2].all() and not inside[1::2].any()


def test_edge_rays_pass_through_an_edge_midpoint(scene):
    origins, directions = rays.edge_rays(scene, 300, 3)
    good = scene.triangles[~scene.degenerate_mask()]
    v = scene.vertices.astype(np.float64)
    midpoints = np.vstack([(v[good[:, i]] + v[good[:, (i + 1) % 3]]) / 2 for i in range(3)])
    distance, _ = distance_to_points(origins, directions, midpoints)
    assert np.all(distance.min(1) < 1e-6)


def test_shadow_rays_end_short_of_the_light(scene):
    origins, directions, tmax = rays.shadow_rays(scene, 500, 4)
    lights = scene.emitter_triangles
    skip = np.ones(len(scene.triangles), bool)
    skip[lights] = False
    t, tri, _, _ = intersect_brute_force(scene.vertices, scene.triangles, origins, directions, skip=skip)
    assert np.all(np.isin(tri, lights))
    np.testing.assert_allclose(tmax, t * (1 - rays.SHADOW_TMAX_SHORTEN), rtol=1e-5)
    # origins lie on non-emitting surfaces, offset towards the light (inside the box)
    assert np.all((origins > 0.0) & (origins < [2.0, 1.0, 1.0]))
    t_all, _, _, _ = intersect_brute_force(scene.vertices, scene.triangles, origins, directions, tmax=tmax)
    assert np.all(np.isinf(t_all))  # nothing inside the empty box blocks the light


def test_shadow_rays_without_emitters_aim_at_the_sky():
    scene = box_scene(emitting=False)
    origins, directions, tmax = rays.shadow_rays(scene, 200, 0)
    assert np.all(np.isfinite(tmax)) and tmax.min() > 1.0
    outside = np.any((origins < 0.0) | (origins > [2.0, 1.0, 1.0]), axis=1)
    assert outside.any() and (~outside).any()  # both faces of the walls are used, facing the sky point


def test_camera_rays_centre_and_fov():
    camera = Camera((1.0, 2.0, 3.0), (4.0, 0.0, -1.0), up=(0.0, 1.0, 0.0), fov=50.0, width=5, height=3)
    origins, directions = rays.camera_rays(camera)
    assert origins.shape == directions.shape == (15, 3)
    np.testing.assert_array_equal(origins, np.tile(np.float32(camera.position), (15, 1)))
    forward, right, up = rays.camera_basis(camera)
    np.testing.assert_allclose(directions[7], forward, atol=1e-6)  # pixel (2, 1) is the centre
    assert np.cross(forward, camera.up) @ right > 0.0 and up[1] > 0.0
    top, bottom, corner = rays.pinhole_directions(camera, np.array([2.5, 2.5, 0.0]), np.array([0.0, 3.0, 0.0]))
    assert np.degrees(np.arccos(top @ forward)) == pytest.approx(25.0)
    assert np.degrees(np.arccos(top @ bottom)) == pytest.approx(50.0)
    assert top @ up > 0.0 and corner @ right < 0.0  # row 0 at the top, column 0 at the left
    half_w = np.tan(np.radians(25.0)) * 5 / 3
    expected = forward - half_w * right + np.tan(np.radians(25.0)) * up
    np.testing.assert_allclose(corner, expected / np.linalg.norm(expected), atol=1e-12)


def test_camera_rays_jitter_and_resolution():
    camera = Camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    _, plain = rays.camera_rays(camera, 8, 4)
    _, jittered = rays.camera_rays(camera, 8, 4, jitter=True, rng=np.random.default_rng(0))
    assert plain.shape == (32, 3) and not np.array_equal(plain, jittered)
    assert np.abs(plain - jittered).max() < 2.0 * np.tan(np.radians(20.0)) / 4  # within a pixel
    with pytest.raises(ValueError, match="rng"):
        rays.camera_rays(camera, jitter=True)
    with pytest.raises(ValueError, match="resolution"):
        rays.camera_rays(camera, 0, 4)


def test_primary_rays_cover_the_image(scene):
    origins, directions = rays.primary_rays(scene, 2000, 0)
    camera = scene.camera
    forward, right, up = rays.camera_basis(camera)
    d = directions.astype(np.float64)
    x = (d @ right) / (d @ forward) / np.tan(np.radians(30.0)) / (32 / 24)
    y = (d @ up) / (d @ forward) / np.tan(np.radians(30.0))
    assert x.min() < -0.95 and x.max() > 0.95 and y.min() < -0.95 and y.max() > 0.95
    assert np.all(np.abs(x) <= 1.0) and np.all(np.abs(y) <= 1.0)
    assert y[0] > 0.9 and y[-1] < -0.9  # image order, top row first
