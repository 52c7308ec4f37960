"""Classification of intersector disagreements, on injected faults."""

import numpy as np
import pandas as pd
import pytest

from kdtrace.oracle import intersect_brute_force
from kdtrace.scene import Camera, Material, Scene
from references import agreement as ag


@pytest.fixture(scope="module")
def quad():
    """Unit square at z = 1 (triangles 0, 1 share the diagonal), a zero-area triangle (2), a far wall at z = 3 (3, 4)."""
    vertices = [(0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1), (5, 5, 5), (6, 6, 6), (-2, -2, 3), (3, -2, 3), (3, 3, 3), (-2, 3, 3)]
    triangles = [(0, 1, 2), (0, 2, 3), (4, 5, 5), (6, 7, 8), (6, 8, 9)]
    return Scene("quad", np.array(vertices, float), np.array(triangles), np.zeros(5, int), [Material("white")])


def up_rays(xy):
    xy = np.asarray(xy, float)
    return np.column_stack([xy, np.zeros(len(xy))]), np.tile([0.0, 0.0, 1.0], (len(xy), 1))


def answer(t, tri):
    t = np.asarray(t, float)
    return t, np.asarray(tri), np.zeros_like(t), np.zeros_like(t)


def labels_of(quad, ours, theirs, xy, tmax=None):
    origins, directions = up_rays(xy)
    return list(ag.compare_hits(quad, origins, directions, answer(*ours), answer(*theirs), tmax=tmax).labels)


def test_agree_and_tie(quad):
    xy = [(0.5, 0.5), (0.2, 0.7), (9.0, 9.0), (0.2, 0.7)]
    theirs = ([1.0, 1.0, np.inf, 1.0], [0, 1, -1, 1])
    ours = ([1.0, 1.0 + 1e-7, np.inf, 1.0], [1, 1, -1, 1])
    assert labels_of(quad, ours, theirs, xy) == [ag.TIE, ag.AGREE, ag.AGREE, ag.AGREE]


def test_a_lost_hit_is_wrong_even_on_an_edge(quad):
    """The oracle hits the shared diagonal, an edge and a vertex; a side that went on to
    the far wall (or missed) is wrong, not an edge/vertex case."""
    xy = [(0.5, 0.5), (0.5, 1e-9), (0.0, 0.0), (0.25, 0.6)]
    theirs = ([1.0] * 4, [0, 0, 1, 1])
    ours = ([3.0, 3.0, 3.0, 3.0], [3, 3, 3, 3])  # went through to the far wall
    assert labels_of(quad, ours, theirs, xy) == [ag.WRONG] * 4
    ours = ([np.inf] * 4, [-1] * 4)  # missed altogether
    assert labels_of(quad, ours, theirs, xy) == [ag.WRONG] * 4


def test_a_hit_outside_the_edge_is_explained_and_ours_is_counted_exact(quad):
    """Embree reports the square just outside its edges (float32 rounding); ours goes on to the far
    wall as the oracle does: explained as edge/vertex, and counted as ours exact, Embree not."""
    origins, directions = up_rays([(0.5, -1e-9), (-1e-9, -1e-9), (0.25, 0.6)])
    theirs = answer([1.0, 1.0, 1.0], [0, 0, 1])
    ours = answer([3.0, 3.0, 1.0], [3, 3, 1])
    comparison = ag.compare_hits(quad, origins, directions, ours, theirs)
    assert list(comparison.labels) == [ag.EDGE, ag.EDGE, ag.AGREE]
    assert list(comparison.ours_exact) == [True, True, False]
    assert comparison.counts()[ag.OURS_EXACT] == 2


def test_perturbed_distance(quad):
    xy = [(0.25, 0.6)] * 3
    tol = ag.t_tolerance(*up_rays(xy[:1]), np.array([1.0]), np.array([1.0]), 6.0)[0]
    assert 1e-7 < tol < 1e-4
    theirs = ([1.0] * 3, [1] * 3)
    ours = ([1.0 + 0.5 * tol, 1.0 + 3 * tol, 1.01], [1] * 3)
    assert labels_of(quad, ours, theirs, xy) == [ag.AGREE, ag.WRONG, ag.WRONG]
    # The same distances on Embree's side: ours is the oracle's, Embree's is off.
    assert labels_of(quad, theirs, ours, xy) == [ag.AGREE, ag.UNEXPLAINED, ag.UNEXPLAINED]


def test_zero_area_and_tmax(quad):
    xy = [(5.5, 5.5), (0.25, 0.6), (0.25, 0.6)]
    theirs = ([np.inf, 1.0, np.inf], [-1, 1, -1])
    ours = ([4.5, np.inf, 1.0], [2, -1, 1])
    tmax = np.array([np.inf, 1.0 + 1e-7, 1.0 - 1e-7])
    assert labels_of(quad, ours, theirs, xy, tmax) == [ag.ZERO_AREA, ag.TMAX, ag.TMAX]
    # Well inside the segment: the lost hit is wrong; the extra one unexplained.
    assert labels_of(quad, ours, theirs, xy, np.array([np.inf, 2.0, 2.0]))[1:] == [ag.WRONG, ag.UNEXPLAINED]


def test_grazing(quad):
    origins = np.array([[-1.0, 0.3, 1.0 - 1e-9]])
    directions = np.array([[1.0, 0.0, 1e-9]])
    labels = ag.compare_hits(quad, origins, directions, answer([1.3], [1]), answer([np.inf], [-1])).labels
    assert list(labels) == [ag.GRAZING]


def test_occlusion(quad):
    xy = [(0.25, 0.6), (0.5, 0.5), (0.25, 0.6), (9.0, 9.0), (5.5, 5.5), (0.25, 0.6)]
    origins, directions = up_rays(xy)
    tmax = np.array([2.0, 2.0, 1.0, 2.0, 6.0, 0.5])
    ours = np.array([False, False, True, True, True, False])
    theirs = np.array([True, True, False, False, False, False])
    comparison = ag.compare_occlusion(quad, origins, directions, tmax, ours, theirs)
    # Ours misses the quad's interior and its shared diagonal: wrong. Ours blocks at tmax: explained.
    assert list(comparison.labels) == [ag.WRONG, ag.WRONG, ag.TMAX, ag.UNEXPLAINED, ag.ZERO_AREA, ag.AGREE]
    # Segment ending exactly at the quad: the oracle's t > tmin, t < tmax says unblocked, as Embree does.
    assert list(comparison.ours_exact) == [False] * 6


def test_tolerance_is_scale_invariant():
    rng = np.random.default_rng(0)
    o, d = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    t, cos = rng.uniform(0, 5, 50), rng.uniform(-1, 1, 50)
    base = ag.t_tolerance(o, d, t, cos, 3.0)
    for s in (1e-3, 7.0, 1e4):
        np.testing.assert_allclose(ag.t_tolerance(s * o, d, s * t, cos, s * 3.0), s * base, rtol=1e-12)
        np.testing.assert_allclose(ag.t_tolerance(o, s * d, t / s, cos, 3.0), base / s, rtol=1e-12)
    assert np.all(ag.t_tolerance(o, d, t, cos * 0.5, 3.0) >= base)  # grows towards grazing


def test_classification_is_scale_invariant(quad):
    xy = np.array([(0.5, 0.5), (0.25, 0.6)])
    for s in (1e-3, 1e3):
        scaled = Scene("scaled", quad.vertices * s, quad.triangles, quad.material_ids, quad.materials)
        origins, directions = up_rays(xy * s)
        hits, misses = answer([s, s], [0, 1]), answer([np.inf] * 2, [-1] * 2)
        # Ours exact, Embree missing the diagonal (explained) and the interior (not).
        assert list(ag.compare_hits(scaled, origins, directions, hits, misses).labels) == [ag.EDGE, ag.UNEXPLAINED]
        # Ours missing both: wrong.
        assert list(ag.compare_hits(scaled, origins, directions, misses, hits).labels) == [ag.WRONG, ag.WRONG]


def test_input_errors(quad):
    origins, directions = up_rays([(0.5, 0.5)])
    with pytest.raises(ValueError, match="shape"):
        ag.compare_hits(quad, origins[:, :2], directions, answer([1.0], [0]), answer([1.0], [0]))
    with pytest.raises(ValueError, match="N = 1"):
        ag.compare_hits(quad, origins, directions, answer([1.0, 1.0], [0, 0]), answer([1.0], [0]))
    with pytest.raises(ValueError, match="shape"):
        ag.compare_occlusion(quad, origins, directions, 1.0, [True, False], [True])


class Oracle:
    """The float64 brute force behind the intersector interface (zero-area triangles skipped, as our trees do)."""

    def __init__(self, scene):
        self.scene = scene

    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf):
        s = self.scene
        return intersect_brute_force(s.vertices, s.triangles, origins, directions, tmin, tmax, skip=s.degenerate_mask())

    def occluded(self, origins, directions, tmax):
        return self.intersect(origins, directions, tmax=tmax)[1] >= 0


def test_check_scene_oracle_against_embree():
    rng = np.random.default_rng(2)
    vertices = (rng.uniform(0, 1, (150, 1, 3)) + rng.normal(0, 0.1, (150, 3, 3))).reshape(-1, 3)
    triangles = np.arange(450).reshape(-1, 3)
    triangles[0] = (0, 0, 1)  # one zero-area triangle
    material_ids = (np.arange(150) < 4).astype(int)
    materials = [Material("white"), Material("light", emission=(1.0, 1.0, 1.0))]
    camera = Camera((0.5, 0.5, -2.0), (0.5, 0.5, 0.5), width=16, height=16)
    scene = Scene("soup", vertices, triangles, material_ids, materials, cameras=[camera])
    df = ag.check_scene(scene, {"oracle": Oracle(scene)}, 300, seed=0, progress=False)
    assert list(df["kind"]) == list(ag.RAY_KINDS)
    assert (df["rays"] == 300).all() and (df["unexplained"] == 0).all() and (df[ag.WRONG] == 0).all()
    assert (df["agree"] > 200).all()
    counted = df[["agree", "ties", *ag.EXPLANATIONS, "unexplained", ag.WRONG]].sum(axis=1)
    assert (counted == df["rays"]).all()
    text = ag.format_table(df)
    assert text.splitlines()[0].startswith("| intersector") and "edge/vertex" in text
    # An Embree intersector the caller built is used instead of a second BVH, with the same table.
    from references.embree import EmbreeIntersector

    class Counted(EmbreeIntersector):
        calls = 0

        def intersect(self, *args, **kwargs):
            Counted.calls += 1
            return super().intersect(*args, **kwargs)

    given = ag.check_scene(scene, {"oracle": Oracle(scene)}, 300, seed=0, progress=False, embree=Counted(scene))
    assert Counted.calls > 0
    pd.testing.assert_frame_equal(given, df)


def test_check_scene_finds_a_broken_intersector():
    rng = np.random.default_rng(4)
    vertices = (rng.uniform(0, 1, (100, 1, 3)) + rng.normal(0, 0.1, (100, 3, 3))).reshape(-1, 3)
    scene = Scene("soup", vertices, np.arange(300).reshape(-1, 3), np.zeros(100, int), [Material("white")])

    class DropsTriangleSeven(Oracle):
        def intersect(self, origins, directions, tmin=0.0, tmax=np.inf):
            skip = np.zeros(len(self.scene.triangles), bool)
            skip[7] = True
            s = self.scene
            return intersect_brute_force(s.vertices, s.triangles, origins, directions, tmin, tmax, skip=skip)

    df = ag.check_scene(scene, {"broken": DropsTriangleSeven(scene)}, 2000, seed=1, progress=False).set_index("kind")
    assert df.loc["random", ag.WRONG] > 0 and "primary" not in df.index  # no camera


def test_origin_on_surface_is_explained_only_at_t_zero(quad):
    """Embree accepts t = 0 for a ray starting on a triangle; we demand t > tmin."""
    origins = np.array([[0.25, 0.6, 1.0], [0.25, 0.6, 0.5]])
    directions = np.tile([0.0, 0.0, 1.0], (2, 1))
    theirs = answer([0.0, 0.5], [1, 1])
    ours = answer([2.0, 2.5], [3, 3])  # went on to the far wall
    labels = ag.compare_hits(quad, origins, directions, ours, theirs).labels
    assert list(labels) == [ag.TMIN, ag.WRONG]


def test_ray_in_the_triangle_plane_is_grazing(quad):
    """A ray lying in the quad's plane (along the shared diagonal's plane z = 1): any hit is noise."""
    origins = np.array([[-1.0, 0.5, 1.0], [-1.0, 0.5, 1.5]])
    directions = np.tile([1.0, 0.0, 0.0], (2, 1))
    theirs = answer([1.5, 1.5], [1, 1])
    ours = answer([np.inf, np.inf], [-1, -1])
    labels = ag.compare_hits(quad, origins, directions, ours, theirs).labels
    assert list(labels) == [ag.GRAZING, ag.UNEXPLAINED]  # the second ray is half a unit above the plane
