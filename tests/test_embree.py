"""EmbreeIntersector against the float64 oracle, its conventions and its errors."""

import numpy as np
import pytest

from kdtrace.oracle import intersect_brute_force
from kdtrace.scene import Material, Scene
from references import embree as embree_module
from references.agreement import UNEXPLAINED, compare_hits
from references.embree import EmbreeIntersector

#: Embree's float32 t is within a few ulps of the exact distance, and which ulp depends on the
#: ISA kernel it picks: exact on the AVX-512 machines, 1 - 2**-24 for t = 1 on an AVX2-only
#: AMD EPYC. Exact expectations would test the CPU, not the wrapper.
EMBREE_T_RTOL = 4 * 2.0**-24


def make_scene(vertices, triangles, name="test"):
    triangles = np.asarray(triangles)
    return Scene(name, np.asarray(vertices), triangles, np.zeros(len(triangles), int), [Material("white")])


@pytest.fixture(scope="module")
def soup():
    rng = np.random.default_rng(7)
    centres = rng.uniform(0.0, 1.0, (400, 1, 3))
    vertices = (centres + rng.normal(0.0, 0.08, (400, 3, 3))).reshape(-1, 3)
    return make_scene(vertices, np.arange(1200).reshape(-1, 3), "soup")


@pytest.fixture(scope="module")
def soup_rays():
    rng = np.random.default_rng(8)
    origins = rng.uniform(-0.2, 1.2, (3000, 3)).astype(np.float32)
    directions = rng.normal(size=(3000, 3)).astype(np.float32)
    return origins, directions


@pytest.fixture(scope="module")
def stacked_planes():
    """Unit squares (two triangles each) at z = 1, 2, 3."""
    vertices, triangles = [], []
    for z in (1.0, 2.0, 3.0):
        base = len(vertices)
        vertices += [(0, 0, z), (1, 0, z), (1, 1, z), (0, 1, z)]
        triangles += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return make_scene(vertices, triangles, "planes")


def test_matches_oracle_on_random_soup(soup, soup_rays):
    origins, directions = soup_rays
    t, tri, u, v = EmbreeIntersector(soup).intersect(origins, directions)
    t64, tri64, u64, v64 = intersect_brute_force(soup.vertices, soup.triangles, origins, directions)
    same = tri == tri64
    assert same.mean() > 0.99
    assert (tri >= 0).sum() > 500
    hit = same & (tri >= 0)
    np.testing.assert_allclose(t[hit], t64[hit], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(u[hit], u64[hit], atol=1e-4)
    np.testing.assert_allclose(v[hit], v64[hit], atol=1e-4)
    assert np.all(np.isinf(t[tri < 0])) and t.dtype == np.float32 and tri.dtype == np.int32
    labels = compare_hits(soup, origins, directions, (t, tri, u, v), (t64, tri64, u64, v64)).labels
    assert UNEXPLAINED not in set(labels)


def test_axis_aligned_rays_hit_shared_edge(stacked_planes):
    embree = EmbreeIntersector(stacked_planes)
    origins = np.array([[0.25, 0.75, 0.0], [0.75, 0.25, 0.0], [0.5, 0.5, 0.0], [2.0, 2.0, 0.0]])
    directions = np.tile([0.0, 0.0, 1.0], (4, 1))
    t, tri, _, _ = embree.intersect(origins, directions)
    # (0.5, 0.5) lies on the diagonal shared by the two triangles: watertight means a hit
    np.testing.assert_allclose(t, [1.0, 1.0, 1.0, np.inf], rtol=EMBREE_T_RTOL, atol=0)
    np.testing.assert_array_equal(tri[[0, 1, 3]], [1, 0, -1])
    assert tri[2] in (0, 1)
    t, tri, _, _ = embree.intersect(origins[:1] + [0, 0, 4], -directions[:1])
    assert t[0] == pytest.approx(1.0, rel=EMBREE_T_RTOL) and tri[0] == 5


def test_rays_through_interior_vertex_hit():
    """A fan of six triangles around (0, 0, 0); rays from everywhere through the centre."""
    angles = np.linspace(0.0, 2.0 * np.pi, 7)[:-1]
    ring = np.stack([np.cos(angles), np.sin(angles), 0.3 * np.sin(3 * angles)], 1)
    scene = make_scene(np.vstack([[0.0, 0.0, 0.0], ring]), [(0, 1 + i, 1 + (i + 1) % 6) for i in range(6)])
    origins = np.random.default_rng(3).normal(size=(500, 3)).astype(np.float32)
    t, tri, _, _ = EmbreeIntersector(scene).intersect(origins, -origins)
    assert np.all(tri >= 0)
    np.testing.assert_allclose(t, 1.0, rtol=1e-6)


def test_tmin_tmax_semantics(stacked_planes):
    embree = EmbreeIntersector(stacked_planes)
    o = np.array([[0.3, 0.6, 0.0]])
    d = np.array([[0.0, 0.0, 2.0]])  # t in units of |d|: planes at t = 0.5, 1, 1.5
    assert embree.intersect(o, d, tmax=0.75)[0][0] == pytest.approx(0.5, rel=EMBREE_T_RTOL)
    # tmax is exclusive: a hit is reported only below it (Embree's t for the plane at 0.5 is
    # 0.5 or an ulp below, by ISA), and a plane beyond tmax by more than that is not hit
    t_at, tri_at, _, _ = embree.intersect(o, d, tmax=0.5)
    assert tri_at[0] == -1 or t_at[0] < 0.5
    assert embree.intersect(o, d, tmax=0.5 * (1.0 - EMBREE_T_RTOL))[1][0] == -1
    assert embree.intersect(o, d, tmin=0.6)[0][0] == pytest.approx(1.0)
    assert embree.intersect(o, d, tmin=0.5)[0][0] == pytest.approx(0.5)  # tmin is inclusive
    assert embree.intersect(o, d, tmin=1.2, tmax=1.4)[1][0] == -1
    tmax = np.array([0.75, 0.25], np.float32)
    t, _, _, _ = embree.intersect(np.repeat(o, 2, 0), np.repeat(d, 2, 0), tmax=tmax)
    np.testing.assert_allclose(t, [0.5, np.inf], rtol=EMBREE_T_RTOL, atol=0)
    np.testing.assert_array_equal(tmax, [0.75, 0.25])  # embreex writes into dists; ours must not change
    shadow_tmax = [0.5 * (1.0 - EMBREE_T_RTOL), 0.5001, 3.0]
    np.testing.assert_array_equal(embree.occluded(np.repeat(o, 3, 0), np.repeat(d, 3, 0), shadow_tmax), [False, True, True])


def test_occluded_consistent_with_intersect(soup, soup_rays):
    origins, directions = soup_rays
    embree = EmbreeIntersector(soup)
    tmax = np.random.default_rng(1).uniform(0.0, 1.5, len(origins))
    t, _, _, _ = embree.intersect(origins, directions, tmax=tmax)
    np.testing.assert_array_equal(embree.occluded(origins, directions, tmax), np.isfinite(t))


def test_thread_count_does_not_change_results(soup, soup_rays, monkeypatch):
    monkeypatch.setattr(embree_module, "CHUNK_RAYS", 97)
    origins, directions = soup_rays
    one = EmbreeIntersector(soup, threads=1)
    four = EmbreeIntersector(soup, threads=4)
    for a, b in zip(one.intersect(origins, directions), four.intersect(origins, directions), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(one.occluded(origins, directions, 0.5), four.occluded(origins, directions, 0.5))


def test_zero_area_triangles_kept_or_excluded():
    # triangle 0 is a point, 1 is a real triangle: indices must refer to scene rows either way
    scene = make_scene([(0, 0, 1), (0, 0, 2), (1, 0, 2), (0, 1, 2)], [(0, 0, 0), (1, 2, 3)])
    o, d = np.array([[0.2, 0.2, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    for exclude in (False, True):
        t, tri, _, _ = EmbreeIntersector(scene, exclude_degenerate=exclude).intersect(o, d)
        assert tri[0] == 1 and t[0] == pytest.approx(2.0, rel=EMBREE_T_RTOL)
    with pytest.raises(ValueError, match="non-zero area"):
        EmbreeIntersector(make_scene([(0, 0, 0), (1, 1, 1)], [(0, 1, 1)]), exclude_degenerate=True)


@pytest.mark.parametrize(
    ("origins", "directions", "kwargs", "error", "match"),
    [
        (np.zeros((2, 2)), np.ones((2, 2)), {}, ValueError, "shape"),
        (np.zeros((2, 3)), np.ones((3, 3)), {}, ValueError, "same shape"),
        (np.zeros((2, 3), int), np.ones((2, 3)), {}, TypeError, "floating"),
        (np.array([[0.0, np.nan, 0.0]]), np.ones((1, 3)), {}, ValueError, "NaN"),
        (np.zeros((1, 3)), np.array([[1.0, 1e39, 0.0]]), {}, ValueError, "infinite"),
        (np.zeros((1, 3)), np.zeros((1, 3)), {}, ValueError, "zero length"),
        (np.zeros((2, 3)), np.ones((2, 3)), {"tmax": np.ones(3)}, ValueError, "tmax"),
        (np.zeros((2, 3)), np.ones((2, 3)), {"tmax": np.nan}, ValueError, "NaN"),
        (np.zeros((2, 3)), np.ones((2, 3)), {"tmin": -1.0}, ValueError, "tmin"),
        (np.zeros((2, 3)), np.ones((2, 3)), {"tmin": 2.0, "tmax": 1.0}, ValueError, "tmax"),
    ],
)
def test_input_errors(stacked_planes, origins, directions, kwargs, error, match):
    with pytest.raises(error, match=match):
        EmbreeIntersector(stacked_planes).intersect(origins, directions, **kwargs)


def test_constructor_errors(stacked_planes):
    with pytest.raises(TypeError, match="Scene"):
        EmbreeIntersector(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="threads"):
        EmbreeIntersector(stacked_planes, threads=0)

