"""Property-based numerical stress tests of both KD-trees against the float64 oracle.

Scenes and rays come from ``tests/strategies.py``: scales 1e-4 .. 1e5 and far offsets,
slivers, planar and duplicated triangles, scenes flat along an axis, rays on split
planes, through vertices, along edges and axis-parallel (signed zeros). Every query
is checked for sanity (no NaN; a finite t only with a triangle; tmin < t < tmax;
barycentrics inside the triangle) and compared with
:func:`kdtrace.oracle.intersect_brute_force` by :func:`references.agreement.compare_hits`
/ :func:`~references.agreement.compare_occlusion`: a disagreement must be explained
(edge/vertex, grazing, tmax boundary), never ``unexplained``. On generic scenes with
random rays the triangle must be exactly the oracle's.

All tests are deterministic (``derandomize=True``); the ``slow`` variant draws many
more, larger examples (``pytest -m slow tests/test_kdtree_stress.py``). The soak run
(``.venv/bin/python scripts/soak.py``) sets ``KDTRACE_SOAK_EXAMPLES`` (10,000 there): every property
then draws at least that many examples.

Besides the classifier, the float64 watertight oracle judges every disagreement
(:func:`references.agreement.compare_hits`): a ray on which it finds a nearer hit than
ours is ``wrong`` and fails the test whatever its geometry.
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from kdtrace._kdtree_build import LEAF
from kdtrace.config import KDTreeConfig
from kdtrace.kdtree import VARIANTS, build_kdtree
from kdtrace.oracle import intersect_brute_force
from kdtrace.scene import Material, Scene
from references.agreement import (
    EXPLANATIONS,
    UNEXPLAINED,
    WRONG,
    TriangleGeometry,
    compare_hits,
    compare_occlusion,
    exact_hits,
    position_tolerance,
    t_tolerance,
)
from tests.strategies import (
    GENERIC_KINDS,
    RAY_KINDS,
    StressScene,
    build_scene,
    make_rays,
    scale_directions,
    split_planes,
    stress_scenes,
    tree_configs,
)

# NumPy warnings of the oracle / agreement re-tests on rays parallel to a triangle (inf - inf,
# 1 / det overflowing for subnormal or 1e-20 directions) are expected.
pytestmark = [
    pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning"),
    pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning"),
    pytest.mark.filterwarnings("ignore:divide by zero encountered:RuntimeWarning"),
]

#: Slack on the barycentric range checks (the trees test u, v exactly; this only guards the asserts).
BARY_EPS = 1e-12
#: Examples per property in a soak run (``scripts/soak.py``); 0 in the normal tiers.
SOAK_EXAMPLES = int(os.environ.get("KDTRACE_SOAK_EXAMPLES", "0"))
#: Labels that fail a test: no explanation, or the oracle has a nearer hit.
FAILING = (UNEXPLAINED, WRONG)


def fast(max_examples: int):
    """Deterministic settings for CI; no shrinking (a failure message already names the
    scene parameters and the failing rays, and shrinking costs minutes on 2 cores)."""
    return settings(
        max_examples=max(max_examples, SOAK_EXAMPLES), deadline=None, derandomize=True, database=None,
        phases=[Phase.explicit, Phase.generate],
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


def build_trees(scene: Scene, config) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # zero-area triangles left out (expected here)
        return {variant: build_kdtree(scene, variant, config, cache=False) for variant in VARIANTS}


def oracle(scene: Scene, origins, directions, tmin=0.0, tmax=np.inf):
    return intersect_brute_force(
        scene.vertices, scene.triangles, origins, directions, tmin=tmin, tmax=tmax, skip=scene.degenerate_mask()
    )


def _describe(case: StressScene, variant: str, rays: np.ndarray, origins, directions, ours, theirs, labels=None) -> str:
    lines = [f"{case!r}, variant {variant}: {len(rays)} bad rays, first ones:"]
    for i in rays[:3]:
        lines.append(
            f"  ray {i}: o={origins[i].tolist()!r} d={directions[i].tolist()!r} "
            f"ours=(t={ours[0][i]!r}, tri={int(ours[1][i])}) oracle=(t={theirs[0][i]!r}, tri={int(theirs[1][i])})"
            + (f" label={labels[i]!r}" if labels is not None else "")
        )
    return "\n".join(lines)


def check_sane(scene: Scene, answer, tmin, tmax) -> None:
    """No NaN, hits only with a (non-degenerate) triangle, tmin < t < tmax, u, v inside the triangle."""
    t, tri, u, v = answer
    n = len(t)
    tmin = np.broadcast_to(tmin, (n,))
    tmax = np.broadcast_to(tmax, (n,))
    assert not np.isnan(t).any() and not np.isnan(u).any() and not np.isnan(v).any()
    hit = tri >= 0
    np.testing.assert_array_equal(np.isfinite(t), hit)
    assert np.all(t[~hit] == np.inf)
    assert np.all(tri < len(scene.triangles))
    assert not scene.degenerate_mask()[tri[hit]].any(), "a zero-area triangle was reported"
    assert np.all((t[hit] > tmin[hit]) & (t[hit] < tmax[hit]))
    assert np.all((u[hit] >= -BARY_EPS) & (v[hit] >= -BARY_EPS) & (u[hit] + v[hit] <= 1.0 + BARY_EPS))


def in_plane(geometry: TriangleGeometry, tri: np.ndarray, origins, directions, t) -> np.ndarray:
    """Rays lying in triangle ``tri``'s plane up to float32 noise: parallel to it (|cos| below
    the triangle's grazing threshold) and within the position tolerance of the plane both at
    the origin and at the reported distance ``t`` (0 where not finite)."""
    cos = exact_hits(geometry, tri, origins, directions)["cos"]
    t = np.where(np.isfinite(t), t, 0.0)
    tol = position_tolerance(origins, directions, t, geometry.scale)
    normal = geometry.normal[tri]
    at_origin = np.einsum("ij,ij->i", origins - geometry.v0[tri], normal)
    at_hit = at_origin + t * np.einsum("ij,ij->i", directions, normal)
    return (np.abs(cos) <= geometry.grazing_cos[tri]) & (np.abs(at_origin) <= tol) & (np.abs(at_hit) <= tol)


def check_intersect(case: StressScene, trees: dict, origins, directions, tmin=0.0, tmax=np.inf, exact=False) -> dict:
    """Closest hits of every tree vs the oracle: sane answers, no unexplained disagreement.

    ``exact``: the rays are generic (random rays on triangles in general position), so
    every ray must report the oracle's triangle unless it is explained (edge, grazing,
    tmax); ties at the same distance are not accepted either.
    Returns the oracle's answer.
    """
    scene = case.scene
    theirs = oracle(scene, origins, directions, tmin, tmax)
    geometry = TriangleGeometry.of(scene)
    for variant, tree in trees.items():
        ours = tree.intersect(origins, directions, tmin, tmax)
        check_sane(scene, ours, tmin, tmax)
        labels = compare_hits(scene, origins, directions, ours, theirs, tmax=tmax, geometry=geometry).labels
        bad = np.flatnonzero(np.isin(labels, FAILING))
        assert len(bad) == 0, _describe(case, variant, bad, origins, directions, ours, theirs, labels)
        # Same triangle => the same float64 Möller–Trumbore: the distances agree to float64
        # rounding, i.e. far below the float32 tolerance of compare_hits (2**-29 of it).
        same = np.flatnonzero((ours[1] == theirs[1]) & (ours[1] >= 0))
        same = same[~in_plane(geometry, ours[1][same], origins[same], directions[same], theirs[0][same])]
        cos = exact_hits(geometry, ours[1][same], origins[same], directions[same])["cos"]
        slack = np.maximum(1e-9 * theirs[0][same],
                           1e-6 * t_tolerance(origins[same], directions[same], theirs[0][same], cos, geometry.scale))
        off = same[np.abs(ours[0][same] - theirs[0][same]) > slack]
        assert len(off) == 0, "same triangle, different t: " + _describe(case, variant, off, origins, directions, ours, theirs)
        if exact:
            wrong = np.flatnonzero((ours[1] != theirs[1]) & ~np.isin(labels, EXPLANATIONS))
            assert len(wrong) == 0, _describe(case, variant, wrong, origins, directions, ours, theirs, labels)
    return theirs


def check_occluded(case: StressScene, trees: dict, origins, directions, tmax) -> None:
    """``occluded`` of every tree vs ``isfinite(oracle t)`` for the same tmax; disagreements explained."""
    scene = case.scene
    expected = np.isfinite(oracle(scene, origins, directions, 0.0, tmax)[0])
    geometry = TriangleGeometry.of(scene)
    for variant, tree in trees.items():
        blocked = tree.occluded(origins, directions, tmax)
        assert blocked.dtype == bool and blocked.shape == expected.shape
        labels = compare_occlusion(scene, origins, directions, tmax, blocked, expected, geometry=geometry).labels
        bad = np.flatnonzero(np.isin(labels, FAILING))
        assert len(bad) == 0, (
            f"{case!r}, variant {variant}: occluded disagrees on {len(bad)} rays, first: "
            f"o={origins[bad[0]].tolist()!r} d={directions[bad[0]].tolist()!r} tmax={tmax[bad[0]]!r} "
            f"ours={bool(blocked[bad[0]])} oracle={bool(expected[bad[0]])}"
        )


def shadow_tmax(rng: np.random.Generator, t_oracle: np.ndarray, span: float) -> np.ndarray:
    """Segment lengths around the closest hits: before it, beyond it, exactly at it, or anywhere."""
    n = len(t_oracle)
    t_ref = np.where(np.isfinite(t_oracle), t_oracle, span)
    choice = rng.integers(0, 4, size=n)
    return np.select(
        [choice == 0, choice == 1, choice == 2],
        [t_ref * rng.uniform(0.0, 1.0, n), t_ref * rng.uniform(1.0, 2.0, n), t_ref],
        rng.uniform(0.0, 2.0, n) * span,
    )


def _span(scene: Scene, directions: np.ndarray) -> float:
    lo, hi = scene.bounds
    return float(np.linalg.norm(hi - lo) + np.abs(hi).max() * 1e-6) / float(np.linalg.norm(directions, axis=1).min())


def run_case(case: StressScene, config, ray_kind: str, n_rays: int, seed: int, occlusion: bool = True, exact=False,
             direction_scale: float = 1.0, tiny: float = 0.0) -> None:
    """Build both variants, make ``n_rays`` rays of ``ray_kind`` (directions scaled, zero
    components replaced by +-tiny), check intersect and (optionally) occluded vs the oracle."""
    trees = build_trees(case.scene, config)
    origins, directions = make_rays(ray_kind, case.scene, trees["naive"], n_rays, seed)
    if direction_scale != 1.0 or tiny:
        directions = scale_directions(np.random.default_rng(seed + 3), directions, direction_scale, tiny)
    theirs = check_intersect(case, trees, origins, directions, exact=exact)
    if ray_kind == "interior":  # not vacuous: rays aimed at triangles do hit
        assert np.mean(theirs[1] >= 0) > 0.5
    if occlusion:
        rng = np.random.default_rng(seed + 7)
        tmax = shadow_tmax(rng, theirs[0], _span(case.scene, directions))
        check_occluded(case, trees, origins, directions, tmax)


# ------------------------------------------------------------------ fast properties
@fast(12)
@given(case=stress_scenes(kinds=GENERIC_KINDS, max_triangles=800, allow_duplicates=False), config=tree_configs, seed=st.integers(0, 2**16))
def test_random_rays_on_generic_scenes_report_the_oracles_triangle(case, config, seed):
    """Random rays, triangles in general position, any scale/offset: the very same triangle
    as the oracle on every ray that is not near an edge/vertex/grazing."""
    run_case(case, config, "random", 600, seed, exact=True)


@fast(14)
@given(case=stress_scenes(max_triangles=400), config=tree_configs, seed=st.integers(0, 2**16))
def test_axis_parallel_rays_with_signed_zeros(case, config, seed):
    """One or two direction components exactly +0.0 or -0.0, on every scene kind."""
    run_case(case, config, "axis_parallel", 400, seed)


@fast(14)
@given(case=stress_scenes(max_triangles=400), config=tree_configs, seed=st.integers(0, 2**16))
def test_origins_on_split_planes(case, config, seed):
    """Origins exactly on one or two of the tree's split planes, directions in/along/across them."""
    run_case(case, config, "split_plane", 400, seed)


@fast(12)
@given(case=stress_scenes(max_triangles=400), config=tree_configs, seed=st.integers(0, 2**16))
def test_rays_through_vertices(case, config, seed):
    """Axis-parallel rays passing exactly through float32 vertices, rays aimed at and starting on them."""
    run_case(case, config, "vertex", 400, seed)


@fast(12)
@given(case=stress_scenes(max_triangles=400), config=tree_configs, seed=st.integers(0, 2**16))
def test_rays_along_and_across_edges(case, config, seed):
    """Origins on the edges' lines (inside and beyond), along the edge, across it, aimed at it."""
    run_case(case, config, "edge", 400, seed)


@fast(10)
@given(case=stress_scenes(max_triangles=400), config=tree_configs, seed=st.integers(0, 2**16))
def test_rays_aimed_at_triangle_interiors(case, config, seed):
    """Rays aimed at interior points (half axis-parallel): mostly clear hits, plenty of hits to compare."""
    run_case(case, config, "interior", 400, seed)


@fast(10)
@given(
    case=stress_scenes(kinds=("flat_grid", "terraces", "boxes", "coplanar", "flat_soup"), max_triangles=300),
    config=tree_configs,
    seed=st.integers(0, 2**16),
    ray_kind=st.sampled_from(RAY_KINDS),
    tmin_fraction=st.sampled_from([0.0, 1e-3, 0.3]),
)
def test_planar_scenes_with_tmin(case, config, seed, ray_kind, tmin_fraction):
    """Triangles lying in split planes / flat scenes, every ray kind, and a positive tmin."""
    trees = build_trees(case.scene, config)
    origins, directions = make_rays(ray_kind, case.scene, trees["naive"], 300, seed)
    tmin = tmin_fraction * _span(case.scene, directions)
    check_intersect(case, trees, origins, directions, tmin=tmin)


@fast(14)
@given(
    case=stress_scenes(kinds=("heightfield", "flat_grid", "terraces", "boxes"), max_triangles=400),
    config=tree_configs,
    seed=st.integers(0, 2**16),
)
def test_rays_in_split_planes_through_shared_edges(case, config, seed):
    """Rays lying exactly in a split plane through edges lying in it: the nearest
    hit may be a triangle that only touches the plane from the side the ray does not start in."""
    run_case(case, config, "split_plane_edge", 400, seed)


def test_split_plane_edge_rays_are_not_vacuous():
    """The grid scenes do have edges in split planes, so the property above traces them."""
    from tests.strategies import _corners, _edges_in_split_planes, build_scene

    scene = build_scene("heightfield", 100, 5)
    tree = build_trees(scene, None)["local"]
    axis, a, b = _edges_in_split_planes(tree, _corners(scene))
    assert len(axis) > 20 and np.all(a[np.arange(len(axis)), axis] == b[np.arange(len(axis)), axis])


def test_split_planes_exist_for_the_split_plane_rays():
    """Guard against a vacuous split-plane test: the strategies' trees do split.

    With leaves of up to 4 triangles, three of the four sizes the strategies draw (with the default 8,
    this 128-triangle scene gets no z split planes).
    """
    from tests.strategies import build_scene

    scene = build_scene("terraces", 8, 3, scale=1e3, offset=(1e5, 0.0, -2e4))
    trees = build_trees(scene, KDTreeConfig(min_leaf_size=4))
    axes, positions = split_planes(trees["local"])
    assert len(axes) > 10 and set(axes.tolist()) == {0, 1, 2}
    # Flat terraces lie exactly in some z split planes.
    z_levels = np.unique(scene.vertices[:, 2].astype(np.float64))
    assert np.isin(positions[axes == 2], z_levels).any()


@fast(30)
@given(
    case=stress_scenes(max_triangles=300),
    config=tree_configs,
    seed=st.integers(0, 2**16),
    ray_kind=st.sampled_from(RAY_KINDS),
    exponent=st.sampled_from([0, -20, -6, 6, 20]),
    tiny=st.sampled_from([0.0, 1e-300, 1e-310, 5e-324]),
)
def test_direction_magnitudes_and_tiny_components(case, config, seed, ray_kind, exponent, tiny):
    """Non-unit directions (|d| = 1e-20 .. 1e20; t scales as 1/|d|) and zero components
    replaced by +-tiny, down to the smallest subnormal (1 / d overflows to inf there)."""
    run_case(case, config, ray_kind, 300, seed, direction_scale=10.0**exponent, tiny=tiny)


# ------------------------------------------------------------------ known problems (reproducers)
def fin_scene() -> Scene:
    """A fin standing on the plane y = 1 (its edge (0,1,-1)-(0,1,1) lies in the plane), a wall
    behind it at x = 3, and a layer of small triangles on each side of y = 1 that makes y = 1
    the tree's split plane (the nearest hit once lost for rays lying in a split plane)."""
    triangles = [[[0, 1, -1], [0, 1, 1], [0, 2, 0]], [[3, 0, -2], [3, 0, 2], [3, 3, 0]]]
    for i in range(6):
        for k in range(6):
            low = np.array([-4.0 + 1.5 * i, 0.0, -4.0 + 1.5 * k])
            high = low + [0.0, 2.0, 0.0]
            triangles += [[low, low + [0.5, 1.0, 0], low + [0, 1.0, 0.5]], [high, high + [0.5, -1.0, 0], high + [0, -1.0, 0.5]]]
    vertices = np.array(triangles, np.float32).reshape(-1, 3)
    return Scene("fin", vertices, np.arange(len(vertices)).reshape(-1, 3), np.zeros(len(triangles), np.int32), [Material("m")])


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("min_leaf_size", [1, 2])
def test_ray_lying_in_a_split_plane_finds_the_hit_on_the_other_side(variant, min_leaf_size):
    """The ray y = 1 along +x starts in the plane, heading into the lower child; the fin is only
    in the upper one and is hit on its edge in the plane at t = 5. Visiting one child gave the
    wall at t = 8."""
    scene = fin_scene()
    tree = build_kdtree(scene, variant, KDTreeConfig(min_leaf_size=min_leaf_size), cache=False)
    y_splits = tree.node_split[(tree.node_meta != LEAF) & ((tree.node_meta & 3) == 1)]
    assert 1.0 in y_splits.astype(np.float64)
    origins = np.array([[-5.0, 1.0, 0.0], [-5.0, 1.0, 0.0], [-5.0, 1.0, 0.5]])
    directions = np.array([[1.0, 0.0, 0.0], [1.0, -0.0, 0.0], [1.0, 0.0, -0.1]])
    expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions)
    np.testing.assert_array_equal(expected[1], [0, 0, 0])
    t, tri, _, _ = tree.intersect(origins, directions)
    np.testing.assert_array_equal(tri, expected[1])
    np.testing.assert_allclose(t, expected[0], rtol=1e-12)
    assert tree.occluded(origins, directions, 6.0).all()


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("tiny", [5e-324, -5e-324])
def test_ray_that_never_leaves_a_split_plane_in_float64_finds_the_hit_on_the_other_side(variant, tiny):
    """As above, with the plane's direction component a tiny nonzero number instead of 0 and a long
    direction: over the ray's interval ``o + t d`` stays at y = 1 in float64, and so does the triangle
    test's shear (``d_y / d_x`` underflows to 0), which hits the fin at t = 5e-6. The traversal took
    the one child the sign of ``d_y`` points into and returned the wall at t = 8e-6 (found by the
    soak of the direction-magnitude property). With ``|d| = 1`` the shear keeps a subnormal and the
    test sees the ray pass just off the fin's edge: the wall, as the oracle says."""
    scene = fin_scene()
    tree = build_kdtree(scene, variant, KDTreeConfig(min_leaf_size=1), cache=False)
    origins = np.array([[-5.0, 1.0, 0.0], [-5.0, 1.0, 0.5], [-5.0, 1.0, 0.0]])
    directions = np.array([[1e6, tiny, 0.0], [1e6, tiny, -1e5], [1.0, tiny, 0.0]])
    expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions)
    assert expected[1][0] == 0 and expected[1][1] == 0  # the fin, on the plane's other side for tiny < 0
    t, tri, _, _ = tree.intersect(origins, directions)
    np.testing.assert_array_equal(tri, expected[1])
    np.testing.assert_allclose(t, expected[0], rtol=1e-12)
    assert tree.occluded(origins, directions, expected[0] * 1.5).all()
    assert (tree.occluded(origins, directions, expected[0] * 0.999) == [False, False, False]).all()
    packets = tree.intersect(origins, directions, packets=True)  # the camera rays' traversal
    np.testing.assert_array_equal(packets[1], expected[1])


@pytest.mark.parametrize("variant", VARIANTS)
def test_rays_departing_from_a_split_plane_by_subnormal_steps_find_the_oracles_hit(variant):
    """Terraces with levels at z = 0 (a split plane); two rays start on it with ``d_z = +-5e-324``.
    At 0, float64 resolves such steps (``0 + d_z t`` is ``+-5e-324`` for t > 0.5), so the rays
    leave the plane over their interval and the traversal took one child; but the triangle test,
    whose shear rounds at that scale, hits edges lying in the plane on the other side (tri 50 at
    t = 0.152 and tri 82 at t = 0.430). A ray that departs from the plane by less than the float32
    grid's finest spacing visits both children (found by the soak of the direction-magnitude property)."""
    scene = build_scene("terraces", 8, 1310, duplicates=0.1)
    origins = np.array([[0.05242981775402539, 1.1563954152792624, 0.0], [0.027089371289944375, -0.8367347534765842, 0.0]])
    directions = np.array([[-0.3441800034850191, -1.0528418462791622, -5e-324], [1.10011811694352, 0.04097834569776373, 5e-324]])
    expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions)
    np.testing.assert_array_equal(expected[1], [50, 82])
    tree = build_kdtree(scene, variant, KDTreeConfig(clip_triangles=False, axis_selection="all", min_leaf_size=2), cache=False)
    assert 0.0 in tree.node_split[(tree.node_meta != LEAF) & ((tree.node_meta & 3) == 2)]
    for packets in (False, True):
        t, tri, _, _ = tree.intersect(origins, directions, packets=packets)
        np.testing.assert_array_equal(tri, expected[1])
        np.testing.assert_array_equal(t, expected[0])
    assert tree.occluded(origins, directions, expected[0] * 1.001).all()


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("triangle_test", ["watertight", "moller-trumbore"])
def test_a_hit_whose_distance_rounds_to_zero_is_not_reported(variant, triangle_test):
    """Two rays along a terrace's edge at 1.6e9 from the origin, with ``5e-324`` for their zero
    components, start on the triangle: the scaled distance is a subnormal above ``tmin * det = 0``,
    but divided by ``det`` it rounds to t = 0, which is not in (tmin, tmax); the oracle misses. The
    trees reported triangle 0 at t = 0 (found by the soak of the direction-magnitude property)."""
    scene = build_scene("terraces", 2, 18795, permutation=(2, 0, 1), scale=15848.93192461114,
                        offset=(1502327605.974392, -15848931.92461114, 1584893192.4611142), duplicates=0.1)
    origins = np.array([[1502324110.301798, -15848932.0, 1584895289.2071924],
                        [1502326748.5833116, -15848932.0, 1584905842.3332462]])
    directions = np.array([[5e-324, 5e-324, -1.0], [1.0, 5e-324, 5e-324]])
    expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions, triangle_test=triangle_test)
    np.testing.assert_array_equal(expected[1], [-1, -1])
    config = KDTreeConfig(clip_triangles=True, axis_selection="cycle", min_leaf_size=2, triangle_test=triangle_test)
    tree = build_kdtree(scene, variant, config, cache=False)
    for packets in (False, True):
        np.testing.assert_array_equal(tree.intersect(origins, directions, packets=packets)[1], [-1, -1])
    np.testing.assert_array_equal(tree.occluded(origins, directions, 1.0), [False, False])


@pytest.mark.parametrize("variant", VARIANTS)
def test_hits_with_a_subnormal_determinant_have_the_oracles_barycentrics(variant):
    """Rays lying in a stack of coplanar triangles 3162 from the origin, ``|d| = 1e6`` with
    components of 1e-310 across the plane: the determinant of their hits is subnormal, so
    ``1 / det`` overflows. With ``t`` divided as the oracle does, the barycentrics were
    ``w * (1 / det) = inf``; divided too, they are the oracle's (found by the soak of the
    direction-magnitude property)."""
    scene = build_scene("coplanar", 290, 425, flips=(False, True, False), scale=3162.2776601683795,
                        offset=(0.0, 0.0, 3162.2776601683795), duplicates=0.5)
    origins = np.array([[-2073.7491799681366, -2032.5415986720127, 3162.277587890625],
                        [-976.141184556699, -139.19969741576483, 3162.277587890625]])
    directions = np.array([[-1e-310, 1e6, 1e-310], [1e6, -1e-310, 1e-310]])
    expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions)
    np.testing.assert_array_equal(expected[1], [56, 191])
    tree = build_kdtree(scene, variant, KDTreeConfig(clip_triangles=True, axis_selection="all", min_leaf_size=8),
                        cache=False)
    for packets in (False, True):
        t, tri, u, v = tree.intersect(origins, directions, packets=packets)
        assert (tri >= 0).all() and np.isfinite(u).all() and np.isfinite(v).all()
        assert ((u >= 0.0) & (v >= 0.0) & (u + v <= 1.0 + BARY_EPS)).all()
        # The second ray's hit is a tie among coplanar duplicates, which the local tree breaks otherwise.
        assert (tri[0], t[0], u[0], v[0]) == (expected[1][0], expected[0][0], expected[2][0], expected[3][0])


@pytest.mark.parametrize("clip_triangles", [False, True])
def test_a_stack_of_overlapping_coplanar_triangles_stays_within_the_reference_budget(clip_triangles):
    """1,599 overlapping triangles in one plane: the SAH found every split worth it while each one
    kept most triangles on both sides, so the references doubled at every level until the depth
    limit (over 6 GB at depth 22; found by the soak of test_stress_many_examples, killed by the
    kernel at 24 GB). The budget makes the rest leaves, with a warning, and the tree still gives
    the oracle's hits."""
    from kdtrace.kdtree import MAX_REFERENCES_PER_TRIANGLE, MIN_REFERENCE_BUDGET

    scene = build_scene("coplanar", 1599, 457, permutation=(2, 1, 0), scale=7943.282347242814,
                        offset=(-23829.84704172844, 0.0, 7943.282347242814))
    config = KDTreeConfig(min_leaf_size=2, clip_triangles=clip_triangles)
    budget = max(MAX_REFERENCES_PER_TRIANGLE * len(scene.triangles), MIN_REFERENCE_BUDGET)
    for variant in VARIANTS:
        with pytest.warns(RuntimeWarning, match="reached its budget"):
            tree = build_kdtree(scene, variant, config, cache=False)
        assert tree.stats["triangle_references"] <= budget
        rng = np.random.default_rng(5)
        lo, hi = scene.bounds
        origins = np.column_stack([np.full(200, lo[0] - 100.0), rng.uniform(lo[1], hi[1], 200), rng.uniform(lo[2], hi[2], 200)])
        directions = np.column_stack([np.ones(200), rng.normal(0, 0.01, 200), rng.normal(0, 0.01, 200)])
        expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions)
        t, tri, _, _ = tree.intersect(origins, directions)
        assert (tri >= 0).mean() > 0.5
        # The stack's triangles tie up to rounding: the oracle's distance, from any of them.
        np.testing.assert_array_equal(tri >= 0, expected[1] >= 0)
        np.testing.assert_allclose(t, expected[0], rtol=1e-12)


@pytest.mark.parametrize("variant", VARIANTS)
def test_vertex_ray_with_a_subnormal_shear_finds_the_oracles_hit(variant):
    """A ray along +z with ``|d| = 1e20`` through a triangle's vertex, whose x and y components
    of -1e-300 point out of the triangle's box: it starts on the box's faces x = max and
    y = min. In float64 ``o + t d == o`` in x and y over the box's z range, and the shear
    ``d_x / d_z = -1e-320`` leaves the edge functions of that vertex at 0: the oracle hits
    the vertex at t = 1.85e-22. The box clip cut the interval to t <= 0 on those faces, and
    the trees missed (found by the soak of test_stress_many_examples)."""
    vertices = np.array([[0.27005592, -0.45781592, -0.90863824], [0.27967513, -0.46470046, -0.92573804],
                         [0.27120304, -0.4602462, -0.9282007]], np.float32)
    scene = Scene("vertex-ray", vertices, np.arange(3).reshape(1, 3), np.zeros(1, np.int32), [Material("m")])
    origins = np.array([[float(vertices[1, 0]), float(vertices[1, 1]), -0.9442419892850934]] * 2)
    directions = np.array([[-1e-300, -1e-300, 1e20], [-1e-300, -1e-300, 1.0]])
    expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions)
    # With |d_z| = 1 the shear is 1e-300 and the ray moves off the faces: both miss.
    np.testing.assert_array_equal(expected[1], [0, -1])
    tree = build_kdtree(scene, variant, KDTreeConfig(), cache=False)
    for packets in (False, True):
        t, tri, _, _ = tree.intersect(origins, directions, packets=packets)
        np.testing.assert_array_equal(tri, expected[1])
        assert t[0] == expected[0][0]
    np.testing.assert_array_equal(tree.occluded(origins, directions, 1e-21), [True, False])


@pytest.mark.parametrize("variant", VARIANTS)
def test_negative_tmin_is_honoured_or_rejected(variant):
    """Two slanted triangles split apart at z = 1; a ray from z = 5 along +z with tmin = -10.
    The oracle's closest hit is triangle 0 at t = -4.75 (behind the origin); the trees must
    find it too or refuse tmin < 0 with a ValueError. They return triangle 1 at t = 4.25."""
    vertices = np.array([[0, 0, 0], [1, 0, 1], [0, 1, 0], [0, 0, 9], [1, 0, 10], [0, 1, 9]], np.float32)
    scene = Scene("neg-tmin", vertices, np.arange(6).reshape(2, 3), np.zeros(2), [Material("m")])
    origins = np.array([[0.25, 0.25, 5.0]])
    directions = np.array([[0.0, 0.0, 1.0]])
    expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions, tmin=-10.0)
    assert expected[1][0] == 0 and expected[0][0] == -4.75
    tree = build_kdtree(scene, variant, KDTreeConfig(min_leaf_size=1), cache=False)
    assert tree.node_meta[0] != LEAF and tree.node_split[0] == 1.0  # the split the ray starts beyond
    try:
        t, tri, _, _ = tree.intersect(origins, directions, tmin=-10.0)
    except ValueError:
        return
    assert (tri[0], t[0]) == (0, -4.75)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("dz", [5e-324, -5e-324, 1e-310])
def test_subnormal_direction_component_with_origin_on_split_plane(variant, dz):
    """A ray starting exactly on a z split plane with a subnormal d_z (|d_z| < 1/DBL_MAX).

    The root split (x = -1) pushes the wall's subtree; deeper, the ray's origin lies on the
    z = -0.8 split. ``inv_d = 1 / d_z`` overflows to +-inf, so ``t_plane = (split - o_z) * inv_d``
    is ``0 * inf = NaN``: every comparison is false, the NaN lands on the stack and as ``ext``,
    and the pop test ``st_ent <= best_t`` (False for NaN) then empties the stack, dropping the
    wall. Expected: triangle 0 (the wall) at t = 2.5, a clear hit in the middle of it.
    """
    vertices = np.array([
        [1, -1, -1], [1, 1, -1], [1, 0, 1],                          # 0: wall at x = 1
        [-1.2, -0.1, -1], [-1.0, 0.1, -1], [-1.1, 0.0, -0.8],        # 1, 2: small triangles that
        [-1.2, -0.1, 0.8], [-1.0, 0.1, 0.8], [-1.1, 0.0, 1.0],       #   make z splits at x < -1
    ], np.float32)
    scene = Scene("subnormal-dz", vertices, np.arange(9).reshape(3, 3), np.zeros(3), [Material("m")])
    tree = build_kdtree(scene, variant, KDTreeConfig(min_leaf_size=1), cache=False)
    z_split = float(np.float32(-0.8))
    assert z_split in tree.node_split[(tree.node_meta != LEAF) & ((tree.node_meta & 3) == 2)].astype(np.float64)
    origins = np.array([[-1.5, 0.05, z_split]])
    directions = np.array([[1.0, 0.0, dz]])
    expected = intersect_brute_force(scene.vertices, scene.triangles, origins, directions)
    assert (expected[1][0], expected[0][0]) == (0, 2.5)
    t, tri, _, _ = tree.intersect(origins, directions)
    assert (tri[0], t[0]) == (0, 2.5), f"got t={t[0]}, tri={tri[0]}"
    assert tree.occluded(origins, directions, 3.0)[0]


# ------------------------------------------------------------------ slow variant
@pytest.mark.slow
@settings(max_examples=max(200, SOAK_EXAMPLES), deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(
    case=stress_scenes(max_triangles=2000),
    config=tree_configs,
    seed=st.integers(0, 2**16),
    ray_kind=st.sampled_from(RAY_KINDS),
    exponent=st.sampled_from([0, 0, 0, -20, -6, 6, 20]),
    tiny=st.sampled_from([0.0, 0.0, 0.0, 1e-300, 1e-310, 5e-324]),
)
def test_stress_many_examples(case, config, seed, ray_kind, exponent, tiny):
    """Every scene kind x every ray kind x direction magnitudes, larger scenes, many more examples."""
    exact = ray_kind == "random" and case.params["kind"] in GENERIC_KINDS and not case.params.get("duplicates")
    run_case(case, config, ray_kind, 1500, seed, exact=exact, direction_scale=10.0**exponent, tiny=tiny)


@fast(12)
@given(case=stress_scenes(kinds=("soup", "slivers", "heightfield", "big_and_small"), max_triangles=300,
                          allow_duplicates=False),
       config=tree_configs, seed=st.integers(0, 2**16), sky=st.booleans())
def test_last_ray_shortcut_and_vector_spans_render_the_oracles_image(case, config, seed, sky):
    """The path tracer's last ray against the emitters, then an any-hit query
    (:func:`kdtrace._render_kernels.last_ray_hit`), and ray queries testing a node's
    triangles all at once (:func:`kdtrace._kdtree_traverse.span_blocked`) give the image of the
    full closest-hit walk and one-by-one tests bit for bit: random emitting triangles (front and
    back faces), with and without a sky, any scale and offset, every tree configuration.
    Triangles are in general position, so no occluder ties an emitter's distance (the one case
    the last-ray shortcut may break differently)."""
    from kdtrace.render import render
    from kdtrace.scene import Camera, Sky

    scene = case.scene
    rng = np.random.default_rng(seed)
    emitting = rng.random(len(scene.triangles)) < 0.2
    emitting[rng.integers(len(scene.triangles))] = True
    lo, hi = scene.vertices.min(axis=0).astype(np.float64), scene.vertices.max(axis=0).astype(np.float64)
    centre, extent = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    direction = rng.normal(size=3)
    camera = Camera(tuple(centre + 0.4 * extent * direction / np.linalg.norm(direction)), tuple(centre),
                    up=tuple(rng.normal(size=3)), fov=100.0, width=12, height=10)
    scene = Scene(scene.name, scene.vertices, scene.triangles, emitting.astype(np.int32),
                  [Material("grey", albedo=(0.6, 0.5, 0.4)), Material("light", emission=(3.0, 2.0, 1.0))],
                  cameras=[camera], sky=Sky((0.2, 0.3, 0.4)) if sky else None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # zero-area triangles, cameras that see nothing
        tree = build_kdtree(scene, "local", config=config)
        for max_depth in (2, 3):
            full, shortcut = (render(scene, spp=2, max_depth=max_depth, seed=seed, tree=tree, last_ray_shortcut=flag,
                                     vector_spans=flag) for flag in (False, True))
            assert np.array_equal(full.rgb, shortcut.rgb), f"{case}, max_depth {max_depth}"
            assert np.array_equal(full.variance, shortcut.variance), f"{case}, max_depth {max_depth}"
