"""The float64 oracle: watertight and Möller–Trumbore brute force, and its compiled twin."""

from __future__ import annotations

import numpy as np
import pytest

from kdtrace import rays
from kdtrace.oracle import intersect_brute_force, nearest_hits_fast
from kdtrace.procedural import random_soup
from kdtrace.scene import Material, Scene


def grid_mesh(n: int = 8) -> Scene:
    """A closed-off height field: n x n quads, two triangles each, every inner edge shared."""
    rng = np.random.default_rng(3)
    x, y = np.meshgrid(np.linspace(0.0, 1.0, n + 1), np.linspace(0.0, 1.0, n + 1))
    z = 0.02 * rng.standard_normal(x.shape)  # slopes well below the rays': no silhouette edges
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()]).astype(np.float32)
    index = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel(), index[1:, :-1].ravel()
    triangles = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return Scene("grid", vertices, triangles, np.zeros(len(triangles), np.int32), [Material("m")])


def edge_rays(scene: Scene, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from above aimed at points of inner edges (both endpoints inner-grid vertices)."""
    rng = np.random.default_rng(seed)
    corners = scene.vertices.astype(np.float64)[scene.triangles]
    tri = rng.integers(0, len(corners), n)
    k = rng.integers(0, 3, n)
    s = rng.uniform(0.05, 0.95, n)
    a, b = corners[tri, k], corners[tri, (k + 1) % 3]
    target = a + s[:, None] * (b - a)
    directions = rng.uniform(-0.3, 0.3, size=(n, 3)) * [1.0, 1.0, 0.0] + [0.0, 0.0, -1.0]
    return target - 2.0 * directions, directions


def test_watertight_never_misses_a_shared_edge():
    """Every ray aimed at an inner edge of the height field hits it with the watertight test;
    Möller–Trumbore lets some of the same rays through the crack (about 7 % here)."""
    scene = grid_mesh()
    origins, directions = edge_rays(scene, 3000, 1)
    target = origins + 2.0 * directions
    inner = np.all((target[:, :2] > 0.0) & (target[:, :2] < 1.0), axis=1)
    origins, directions = origins[inner], directions[inner]
    t, tri, _, _ = intersect_brute_force(scene.vertices, scene.triangles, origins, directions)
    assert len(tri) > 2000 and np.all(tri >= 0)
    np.testing.assert_allclose(t, 2.0, rtol=1e-9)
    _, tri_mt, _, _ = intersect_brute_force(scene.vertices, scene.triangles, origins, directions, triangle_test="moller-trumbore")
    assert np.mean(tri_mt < 0) > 0.01


@pytest.mark.parametrize("test", ["watertight", "moller-trumbore"])
def test_the_two_tests_agree_away_from_edges(test):
    scene = random_soup(2000, seed=5, sizes=(0.1, 0.4))
    origins, directions = rays.random_rays(scene, 500, 4)[:2]
    reference = intersect_brute_force(scene.vertices, scene.triangles, origins, directions, triangle_test="watertight")
    t, tri, u, v = intersect_brute_force(scene.vertices, scene.triangles, origins, directions, triangle_test=test)
    np.testing.assert_array_equal(tri, reference[1])
    hit = tri >= 0
    assert hit.mean() > 0.3
    np.testing.assert_allclose(t[hit], reference[0][hit], rtol=1e-12)
    # Barycentrics reproduce the hit point.
    corners = scene.vertices.astype(np.float64)[scene.triangles[tri[hit]]]
    point = (1 - u[hit] - v[hit])[:, None] * corners[:, 0] + u[hit][:, None] * corners[:, 1] + v[hit][:, None] * corners[:, 2]
    np.testing.assert_allclose(point, origins[hit] + t[hit][:, None] * directions[hit], atol=1e-9)


@pytest.mark.parametrize("kind", ["random", "vertex", "edge"])
def test_compiled_oracle_equals_the_numpy_oracle(kind):
    """:func:`nearest_hits_fast` (blocked, vectorised) gives the NumPy oracle's (t, tri) on rays
    through vertices and edges, with tmin > 0 and a finite tmax for some rays; more triangles than
    one block (4096) so the block boundary is crossed."""
    base = grid_mesh(48)  # 4608 triangles
    scene = Scene("grid", base.vertices, np.vstack([base.triangles, base.triangles[:5, [0, 0, 1]]]),  # + 5 zero-area
                  np.zeros(len(base.triangles) + 5, np.int32), [Material("m")])
    makers = {"random": rays.random_rays, "vertex": rays.vertex_rays, "edge": rays.edge_rays}
    origins, directions = makers[kind](scene, 300, 2)[:2]
    tmax = np.where(np.arange(300) % 3 == 0, 1.5, np.inf)
    skip = scene.degenerate_mask()
    expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions, 1e-3, tmax, skip=skip)
    t, tri = nearest_hits_fast(scene.vertices, scene.triangles, origins, directions, 1e-3, tmax, skip=skip)
    assert np.mean(expected[1] >= 0) > 0.3
    np.testing.assert_array_equal(tri, expected[1])
    np.testing.assert_array_equal(t, expected[0])


def test_unknown_triangle_test_is_an_error():
    scene = grid_mesh(2)
    with pytest.raises(ValueError, match="unknown triangle test 'exact'"):
        intersect_brute_force(scene.vertices, scene.triangles, np.zeros((1, 3)), np.ones((1, 3)), triangle_test="exact")
