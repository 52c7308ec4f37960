"""Unit tests of the KD-tree build, pull-up, cache and ray queries against oracles."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from numba import njit

from kdtrace._kdtree_build import LEAF
from kdtrace._kdtree_layout import HAS_TRIANGLES, LINE_NODES
from kdtrace._kdtree_traverse import (
    SPAN_LANES,
    SPAN_MASK_BITS,
    intersect_triangle_watertight,
    span_hits,
    triangle_test_setup,
)
from kdtrace.config import KDTreeConfig
from kdtrace.kdtree import VARIANTS, build_kdtree, validate_rays
from kdtrace.oracle import intersect_brute_force
from kdtrace.scene import Material, Scene
from references.agreement import UNEXPLAINED, compare_hits
from tests.kdtree_reference import leaves_reached, pull_up_reference


def soup(n: int, seed: int, spread: float = 0.1) -> Scene:
    """Random triangle soup in [-1, 1]^3 with triangles of size ~spread."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1, 1, (n, 1, 3))
    vertices = (centres + rng.normal(0, spread, (n, 3, 3))).reshape(-1, 3)
    return Scene(f"soup{n}-{seed}", vertices, np.arange(3 * n).reshape(n, 3), np.zeros(n), [Material("grey")])


def random_rays(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.5, 1.5, (n, 3)), rng.normal(size=(n, 3))


@pytest.fixture(scope="module")
def big_and_small_triangles() -> Scene:
    """Small triangles plus a few large ones spanning many cells (pull-up candidates)."""
    small = soup(600, 3, 0.05)
    rng = np.random.default_rng(4)
    big = rng.uniform(-1, 1, (20, 3, 3)).reshape(-1, 3)
    vertices = np.concatenate([small.vertices, big])
    triangles = np.concatenate([small.triangles, np.arange(60).reshape(20, 3) + len(small.vertices)])
    return Scene("mixed", vertices, triangles, np.zeros(len(triangles)), [Material("grey")])


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("config", [KDTreeConfig(), KDTreeConfig(clip_triangles=True),
                                    KDTreeConfig(axis_selection="cycle", min_leaf_size=1),
                                    KDTreeConfig(axis_selection="cycle", split_candidates="centroids", empty_bonus=0.0)])
def test_closest_hit_matches_oracle(variant, config, big_and_small_triangles):
    scene = big_and_small_triangles
    tree = build_kdtree(scene, variant, config, cache=False)
    origins, directions = random_rays(3000, 11)
    ours = tree.intersect(origins, directions)
    oracle = intersect_brute_force(scene.vertices, scene.triangles, origins, directions)
    labels = compare_hits(scene, origins, directions, ours, oracle).labels
    assert (labels == UNEXPLAINED).sum() == 0
    # Random rays almost never tie: demand the same triangle on nearly every ray.
    assert np.mean(ours[1] == oracle[1]) > 0.999
    hit = ours[1] >= 0
    np.testing.assert_allclose(ours[0][hit], oracle[0][hit], rtol=1e-9)
    assert hit.mean() > 0.1  # the test is not vacuous


@pytest.mark.parametrize("variant", VARIANTS)
def test_occluded_matches_oracle_with_tmin_tmax(variant, big_and_small_triangles):
    scene = big_and_small_triangles
    tree = build_kdtree(scene, variant, cache=False)
    origins, directions = random_rays(2000, 12)
    rng = np.random.default_rng(5)
    tmin = rng.uniform(0, 0.3, len(origins))
    tmax = tmin + rng.uniform(0, 1.5, len(origins))
    t, _, _, _ = intersect_brute_force(scene.vertices, scene.triangles, origins, directions, tmin=0.0, tmax=tmax)
    blocked = tree.occluded(origins, directions, tmax)
    np.testing.assert_array_equal(blocked, np.isfinite(t))
    t_ours, _, _, _ = tree.intersect(origins, directions, tmin=tmin, tmax=tmax)
    expected = np.array([
        intersect_brute_force(scene.vertices, scene.triangles, origins[i : i + 1], directions[i : i + 1], tmin[i], tmax[i])[0][0]
        for i in range(0, len(origins), 20)
    ])
    np.testing.assert_allclose(t_ours[::20], expected, rtol=1e-9)


@pytest.mark.parametrize("variant", VARIANTS)
def test_any_hit_walks_the_segment_from_its_end(variant):
    """Any-hit queries visit the far child of a split first: of the occluders along a shadow
    segment, the kernel reports one in the leaf reached first from tmax, not from the
    origin. The answer (blocked or not) cannot depend on the order: that is
    test_occluded_matches_oracle_with_tmin_tmax; here the order itself is checked."""
    from kdtrace import _kdtree_traverse as kernels

    # Eight small squares across the x axis at x = 1..8 (two triangles each); rays along +x
    # from x = 0.5 through all of them.
    squares = []
    for x in range(1, 9):
        squares.append([[x, -0.5, -0.5], [x, 0.5, -0.5], [x, 0.5, 0.5]])
        squares.append([[x, -0.5, -0.5], [x, 0.5, 0.5], [x, -0.5, 0.5]])
    vertices = np.array(squares, float).reshape(-1, 3)
    scene = Scene("squares", vertices, np.arange(len(vertices)).reshape(-1, 3), np.zeros(16), [Material("grey")])
    # Leaves of at most 4 triangles (two squares), whatever the default: the order is seen
    # only when the squares are spread over several leaves.
    tree = build_kdtree(scene, variant, KDTreeConfig(min_leaf_size=4), cache=False)
    rng = np.random.default_rng(3)
    n = 200
    origins = np.column_stack([np.full(n, 0.5), rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n)])
    directions = np.tile([1.0, 0.0, 0.0], (n, 1))
    out = [np.empty(n), np.empty(n, np.int32), np.empty(n), np.empty(n), np.empty(n, np.int32), np.empty(n, np.int32)]
    for tmax, last_square in ((9.0, 8), (5.2, 5)):  # the segments end at x = 9.5 and 5.7
        for any_hit in (False, True):
            kernels.trace_batch(tree.node_words, tree.node_splits, tree.refs, tree.box, tree.corners,
                                tree.span_corners, origins, directions, np.zeros(n), np.full(n, tmax), any_hit, True, 4,
                                *out)
            square = out[1] // 2 + 1  # triangles 2k and 2k+1 make square k + 1
            if not any_hit:
                np.testing.assert_array_equal(square, 1)  # closest hit: the first square
            else:
                # The last leaf before tmax: a square lies in its split plane, so it is in the
                # leaves on both sides, and the leaf reached first from tmax holds the last
                # square and the one before it. From the origin it would be square 1 or 2.
                assert np.isin(square, [last_square - 1, last_square]).all(), np.unique(square)


@pytest.mark.parametrize("variant", VARIANTS)
def test_span_corners_hold_each_span_as_one_block(big_and_small_triangles, variant):
    """Every node's span of references (leaves and local-branch interior nodes) is one block of
    ``span_corners``: 9 runs of ``count``, each a coordinate of the span's triangles in order,
    and the zero padding the vector test's last pass may read."""
    tree = build_kdtree(big_and_small_triangles, variant, KDTreeConfig(min_leaf_size=4), cache=False)
    blocks = tree.span_corners
    assert blocks.dtype == np.float32 and blocks.shape == (9 * len(tree.refs) + SPAN_LANES,)
    assert not blocks[9 * len(tree.refs):].any()
    spans = np.flatnonzero(tree.node_count > 0)
    assert len(spans) > 1 and (tree.node_count[spans] > 1).any()
    for node in spans:
        first, count = int(tree.node_start[node]), int(tree.node_count[node])
        expected = tree.corners[tree.refs[first:first + count]].T.reshape(-1)
        np.testing.assert_array_equal(blocks[9 * first:9 * (first + count)], expected)


def test_local_branch_is_the_naive_tree_with_pull_up(big_and_small_triangles):
    scene = big_and_small_triangles
    naive = build_kdtree(scene, "naive", cache=False)
    local = build_kdtree(scene, "local", cache=False)
    # Same split decisions.
    np.testing.assert_array_equal(naive.node_meta, local.node_meta)
    np.testing.assert_array_equal(naive.node_split, local.node_split)
    # Pull-up equals the slow set-based reference, node by node.
    expected = pull_up_reference(naive.node_meta, naive.node_start, naive.node_count, naive.refs)
    for node, triangles in enumerate(expected):
        got = set(local.refs[local.node_start[node] : local.node_start[node] + local.node_count[node]].tolist())
        assert got == triangles, f"node {node}"
    # Every leaf still "sees" the same triangles along its root path.
    before = leaves_reached(naive.node_meta, naive.node_start, naive.node_count, naive.refs)
    after = leaves_reached(local.node_meta, local.node_start, local.node_count, local.refs)
    assert before == after
    assert local.stats["interior_references"] > 0
    assert local.stats["triangle_references"] < naive.stats["triangle_references"]


def _grid_with_planar_triangles() -> Scene:
    """Axis-aligned quads on a coarse grid: many triangles lying in split planes, shared bounds."""
    quads = []
    for x in range(4):
        for y in range(4):
            quads.append([[x, y, 0], [x + 1, y, 0], [x + 1, y + 1, 0], [x, y, 0], [x + 1, y + 1, 0], [x, y + 1, 0]])
            quads.append([[x, 0, y], [x + 1, 0, y], [x + 1, 0, y + 1], [x, 0, y], [x + 1, 0, y + 1], [x, 0, y + 1]])
    vertices = np.array(quads, float).reshape(-1, 3)
    return Scene("grid", vertices, np.arange(len(vertices)).reshape(-1, 3), np.zeros(len(vertices) // 3),
                 [Material("grey")])


@pytest.mark.parametrize("axis_selection", ["all", "cycle"])
@pytest.mark.parametrize("scene_kind", ["soup", "mixed", "planar grid"])
def test_presorted_build_is_the_per_node_sorting_build(scene_kind, axis_selection, big_and_small_triangles):
    """The O(N log N) builder gives the O(N log^2 N) reference's tree, array for array."""
    from kdtrace import _kdtree_build as kernels
    from kdtrace.kdtree import max_depth_for

    scene = {"soup": soup(3000, 7, 0.05), "mixed": big_and_small_triangles,
             "planar grid": _grid_with_planar_triangles()}[scene_kind]
    config = KDTreeConfig(axis_selection=axis_selection, min_leaf_size=1)
    corners = scene.vertices.astype(np.float64)[scene.triangles]
    ids = np.arange(len(scene.triangles), dtype=np.int32)
    lo, hi = scene.bounds
    args = (*(np.ascontiguousarray(corners[:, k]) for k in range(3)), ids, lo, hi, config.traversal_cost,
            config.intersection_cost, config.min_leaf_size, max_depth_for(len(ids), config),
            axis_selection == "cycle", config.empty_bonus)
    unlimited = 2**40
    reference = kernels.build_naive(*args, False, False, unlimited)
    fast = kernels.build_presorted(*args, unlimited)
    assert len(reference[0]) > 15  # a tree, not a single leaf
    for expected, got in zip(reference[:6], fast[:6], strict=True):
        np.testing.assert_array_equal(got, expected)
    assert fast[6] == reference[6] and not fast[7] and not reference[7]
    # A reference budget below the tree's references caps both builds at the same nodes (a budget
    # is at least the triangle count: the root alone holds that many).
    total = len(reference[4])
    budget = max(len(ids), total * 3 // 4)
    reference = kernels.build_naive(*args, False, False, budget)
    fast = kernels.build_presorted(*args, budget)
    assert reference[7] == fast[7] == (budget < total) and len(fast[4]) <= budget
    for expected, got in zip(reference[:6], fast[:6], strict=True):
        np.testing.assert_array_equal(got, expected)


def test_centroid_candidates_split_at_centroids_on_the_cycled_axis(big_and_small_triangles):
    """The paper's recipe (FindPlaneSAH): axis = depth % 3, every plane through a triangle centroid."""
    from kdtrace._kdtree_build import LEAF

    scene = big_and_small_triangles
    tree = build_kdtree(scene, "naive", KDTreeConfig(axis_selection="cycle", split_candidates="centroids"), cache=False)
    centroids = scene.vertices.astype(np.float64)[scene.triangles].mean(axis=1)
    interior = np.flatnonzero(tree.node_meta != LEAF)
    assert len(interior) > 10
    depth = np.zeros(len(tree.node_meta), int)
    for node in interior:  # children follow their parent in the node array
        left = tree.node_meta[node] >> 2
        depth[left] = depth[left + 1] = depth[node] + 1
        axis = tree.node_meta[node] & 3
        assert axis == depth[node] % 3
        assert np.float32(tree.node_split[node]) in set(np.float32(centroids[:, axis]).tolist())
    bounds = build_kdtree(scene, "naive", KDTreeConfig(axis_selection="cycle"), cache=False)
    assert not np.array_equal(bounds.node_split, tree.node_split)  # the candidates make a difference


def test_unknown_split_candidates_are_refused():
    with pytest.raises(ValueError, match="split_candidates"):
        KDTreeConfig(split_candidates="median")


@pytest.mark.parametrize("variant", VARIANTS)
def test_statistics_are_consistent(variant, big_and_small_triangles):
    tree = build_kdtree(big_and_small_triangles, variant, cache=False)
    stats = tree.stats
    assert stats["nodes"] == 2 * stats["leaves"] - 1
    assert stats["triangle_references"] == len(tree.refs) == stats["leaf_references"] + stats["interior_references"]
    assert stats["tree_bytes"] == sum(a.nbytes for a in (tree.node_meta, tree.node_split, tree.node_start, tree.node_count, tree.refs))
    # Traversal: 8-byte nodes plus a cold half of the same size, padded to whole 64-byte blocks.
    slots = len(tree.packed_nodes) // 2
    assert slots >= stats["nodes"] and slots % 8 == 0
    assert stats["traversal_bytes"] == 16 * slots + 4 * len(tree.refs)
    assert stats["span_bytes"] == tree.span_corners.nbytes  # the vector test's copy of the corners
    assert 0 < stats["max_depth"] <= 8 + 1.3 * np.log2(len(big_and_small_triangles.triangles)) + 1
    # Every non-degenerate triangle is referenced somewhere.
    assert set(tree.refs.tolist()) == set(range(len(big_and_small_triangles.triangles)))
    if variant == "naive":
        assert stats["interior_references"] == 0


@pytest.mark.parametrize("variant", VARIANTS)
def test_traversal_layout_is_the_built_tree_in_cache_line_blocks(variant, big_and_small_triangles):
    """The 8-byte blocked traversal array decodes to the build's tree, node for node."""
    tree = build_kdtree(big_and_small_triangles, variant, cache=False)
    packed = tree.packed_nodes
    assert packed.ctypes.data % 64 == 0 and packed.shape[0] % (2 * LINE_NODES) == 0
    n_slots = packed.shape[0] // 2
    word, second = packed[:n_slots, 0], packed[:n_slots, 1]
    # Walk both trees together from the roots: same splits, same triangles, same shape.
    slot_of = {0: 0}
    paths = []  # (distinct cache lines, nodes) of every root-to-leaf path
    stack = [(0, 0, frozenset(), 0)]
    while stack:
        node, slot, lines, depth = stack.pop()
        lines, depth = lines | {slot // LINE_NODES}, depth + 1
        start, count = tree.node_start[node], tree.node_count[node]
        if tree.node_meta[node] == LEAF:
            assert word[slot] & 3 == LEAF and word[slot] >> 2 == count and (count == 0 or second[slot] == start)
            paths.append((len(lines), depth))
            continue
        assert word[slot] & 3 == tree.node_meta[node] & 3
        assert second[slot:slot + 1].view(np.float32)[0] == tree.node_split[node]
        assert bool(word[slot] & HAS_TRIANGLES) == (count > 0)
        if count:
            assert tuple(packed[n_slots + slot]) == (start, count)
        left, left_slot = tree.node_meta[node] >> 2, word[slot] >> 3
        assert left_slot % 2 == 0  # a sibling pair is 16 aligned bytes
        slot_of[left], slot_of[left + 1] = left_slot, left_slot + 1
        stack += [(left, left_slot, lines, depth), (left + 1, left_slot + 1, lines, depth)]
    assert sorted(slot_of) == list(range(len(tree.node_meta)))
    assert len(set(slot_of.values())) == len(slot_of)  # one slot per node
    padding = np.setdiff1d(np.arange(n_slots), list(slot_of.values()))
    assert np.all(word[padding] == LEAF)  # empty leaves
    # Locality: a root-to-leaf path reads about one cache line per two levels.
    lines, depths = np.array(paths).T
    assert depths.mean() > 6 and lines.mean() <= 0.6 * depths.mean()


def test_cache_hit_returns_identical_tree(tmp_path, monkeypatch):
    monkeypatch.setenv("KDTRACE_CACHE", str(tmp_path))
    scene = soup(300, 8)
    first = build_kdtree(scene, "local")
    second = build_kdtree(scene, "local")
    assert not first.stats["cache_hit"] and second.stats["cache_hit"]
    for name in ("node_meta", "node_split", "node_start", "node_count", "refs"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    other = build_kdtree(scene, "local", KDTreeConfig(intersection_cost=3.0))
    assert not other.stats["cache_hit"]
    assert len(list((tmp_path / "kdtrees").glob("*.npz"))) == 2
    assert not list((tmp_path / "kdtrees").glob(".*tmp*"))  # no temporary files left


def test_zero_area_triangles_are_left_out_and_counted():
    scene = soup(200, 9)
    vertices = scene.vertices.copy()
    vertices[3 * 7 + 2] = vertices[3 * 7 + 1]  # triangle 7: repeated vertex
    vertices[3 * 8 + 2] = 2 * vertices[3 * 8 + 1] - vertices[3 * 8]  # triangle 8: collinear
    degenerate = Scene("degenerate", vertices, scene.triangles, scene.material_ids, scene.materials)
    assert degenerate.degenerate_mask().sum() >= 1
    with pytest.warns(UserWarning, match="zero-area triangles left out"):
        tree = build_kdtree(degenerate, "local", cache=False)
    assert 7 not in set(tree.refs.tolist())
    assert tree.stats["zero_area_triangles"] == degenerate.degenerate_mask().sum()


def test_bad_rays_and_arguments_are_clear_errors():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tree = build_kdtree(soup(50, 1), "naive", cache=False)
    good = np.zeros((4, 3))
    with pytest.raises(ValueError, match="shape"):
        tree.intersect(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="shape"):
        tree.intersect(good, np.ones((5, 3)))
    with pytest.raises(ValueError, match="finite"):
        tree.intersect(np.full((4, 3), np.nan), np.ones((4, 3)))
    with pytest.raises(ValueError, match="non-zero"):
        tree.intersect(good, good)
    with pytest.raises(ValueError, match=r"tmin must be <= tmax; ray 0 has tmin = 2.0 > tmax = 1.0 \(4 of 4"):
        tree.intersect(good, np.ones((4, 3)), tmin=2.0, tmax=1.0)
    with pytest.raises(ValueError, match="tmax must be a number, got NaN for ray 2"):
        tree.intersect(good, np.ones((4, 3)), tmax=[1.0, 1.0, np.nan, 1.0])
    with pytest.raises(ValueError, match="variant"):
        build_kdtree(soup(10, 1), "bvh")
    with pytest.raises(ValueError, match="axis_selection"):
        KDTreeConfig(axis_selection="diagonal")
    collapsed = Scene("flat", np.zeros((3, 3)), [[0, 1, 2]], [0], [Material("m")])
    with pytest.raises(ValueError, match="zero area"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            build_kdtree(collapsed, cache=False)


def test_missing_or_mis_sized_tmin_tmax_are_clear_errors():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tree = build_kdtree(soup(50, 1), "naive", cache=False)
    origins, directions = np.zeros((4, 3)), np.ones((4, 3))
    with pytest.raises(TypeError, match=r"tmax is required: a float or an array of shape \(4,\).*got None.*np\.inf"):
        tree.occluded(origins, directions, None)
    with pytest.raises(TypeError, match="tmin is required.*got None"):
        tree.intersect(origins, directions, tmin=None)
    with pytest.raises(TypeError, match=r"tmax must be a float or an array of shape \(4,\).*got str 'far'"):
        tree.occluded(origins, directions, "far")
    with pytest.raises(ValueError, match=r"tmax has shape \(3,\) but there are 4 rays"):
        tree.occluded(origins, directions, np.ones(3))
    with pytest.raises(ValueError, match=r"tmin has shape \(4, 1\) but there are 4 rays"):
        tree.intersect(origins, directions, tmin=np.zeros((4, 1)))
    assert tree.occluded(origins, directions, np.full(4, np.inf)).shape == (4,)


def test_ray_bounds_reach_the_kernels_as_one_compiled_signature():
    """A scalar, an array and a read-only array bound all become writable C float64 arrays:
    numba compiles a read-only array as another signature of every traversal kernel (about a
    minute of compilation each time), so the wrapper must not let one through."""
    origins, directions = np.zeros((4, 3)), np.ones((4, 3))
    read_only = np.full(4, np.inf)
    read_only.flags.writeable = False
    for tmax in (np.inf, np.full(4, np.inf), read_only, np.broadcast_to(np.inf, (4,))):
        *_, tmin, tmax_out = validate_rays(origins, directions, 0.0, tmax)
        for bound in (tmin, tmax_out):
            assert bound.dtype == np.float64 and bound.flags.c_contiguous and bound.flags.writeable


@pytest.mark.parametrize("variant", VARIANTS)
def test_axis_parallel_rays_on_a_grid_hit_exactly(variant):
    """A flat grid in z=0 split along x and y: rays along -z through cell corners and
    split planes, and rays travelling inside the plane (which must miss)."""
    n = 8
    xs, ys = np.meshgrid(np.arange(n + 1, dtype=np.float32), np.arange(n + 1, dtype=np.float32), indexing="ij")
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size, np.float32)], 1)
    index = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]], -1).reshape(-1, 4)
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    scene = Scene("grid", vertices, triangles, np.zeros(len(triangles)), [Material("m")])
    tree = build_kdtree(scene, variant, KDTreeConfig(min_leaf_size=1), cache=False)
    gx, gy = np.meshgrid(np.linspace(0, n, 4 * n + 1), np.linspace(0, n, 4 * n + 1), indexing="ij")
    origins = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, 5.0)], 1)
    directions = np.tile([0.0, 0.0, -1.0], (len(origins), 1))
    t, tri, _, _ = tree.intersect(origins, directions)
    assert np.all(tri >= 0), "every ray through the closed grid (edges included) must hit"
    np.testing.assert_array_equal(t, 5.0)
    in_plane = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    t, tri, _, _ = tree.intersect(in_plane - [1.0, 0.0, 0.0], np.tile([1.0, 0.0, 0.0], (len(origins), 1)))
    assert np.all(tri == -1), "rays inside the triangles' plane are parallel to them"


@njit(error_model="numpy")
def _span_hits_along(span_corners, first, count, origin, direction, tmax):
    """:func:`span_hits` for one ray, with the ray's setup as :func:`trace_ray` makes it."""
    okx, oky, okz, kx, ky, kz, sx, sy, sz = triangle_test_setup(True, origin[0], origin[1], origin[2], direction[0],
                                                                direction[1], direction[2])
    return span_hits(span_corners, first, count, okx, oky, okz, kx, ky, kz, sx, sy, sz, 0.0, tmax)


@njit(error_model="numpy")
def _hit_one_by_one(corners, origin, direction, tmax):
    """Whether each triangle is hit in (0, tmax) by the scalar watertight test, as the queries test."""
    okx, oky, okz, kx, ky, kz, sx, sy, sz = triangle_test_setup(True, origin[0], origin[1], origin[2], direction[0],
                                                                direction[1], direction[2])
    hit = np.zeros(corners.shape[0], np.bool_)
    for tri in range(corners.shape[0]):
        t, _, _ = intersect_triangle_watertight(tri, corners, okx, oky, okz, kx, ky, kz, sx, sy, sz, 0.0, tmax)
        hit[tri] = t < np.inf
    return hit


def test_span_mask_is_the_one_by_one_answer_for_the_span_alone():
    """The vector span test reads whole passes of lanes past a span's end (into the next span,
    or the padding): whatever lies there, its mask holds exactly the span's triangles the scalar
    test finds hit (the last bit: any from there on), and it is non-zero exactly when the
    brute-force oracle finds a hit. Random triangles and rays, so that the lanes past the end
    often hold a hit; spans of up to 80 triangles, past the mask's 64 bits."""
    rng = np.random.default_rng(7)
    answers = []
    last = SPAN_MASK_BITS - 1
    for case in range(3000):
        count = int(rng.integers(1, 12)) if case % 10 else int(rng.integers(SPAN_MASK_BITS - 8, 81))
        corners = rng.uniform(-1.0, 1.0, (count, 9)).astype(np.float32)
        after = rng.uniform(-1.0, 1.0, int(rng.integers(0, 30)) + SPAN_LANES).astype(np.float32)
        blocks = np.concatenate([corners.T.reshape(-1), after])
        origin = rng.uniform(-1.0, 1.0, 3) + np.array([0.0, 0.0, -3.0])
        direction = rng.normal(size=3) * 0.3 + np.array([0.0, 0.0, 1.0])
        direction /= np.linalg.norm(direction)
        _, hits, _, _ = intersect_brute_force(corners.reshape(-1, 3).astype(np.float64), np.arange(3 * count).reshape(-1, 3),
                                              origin[None], direction[None], tmax=10.0)
        answers.append(hits[0] >= 0)
        mask = int(_span_hits_along(blocks, 0, count, origin, direction, 10.0))
        one_by_one = _hit_one_by_one(corners, origin, direction, 10.0)
        expected = sum(1 << k for k in range(min(count, last)) if one_by_one[k]) | (int(one_by_one[last:].any()) << last)
        assert mask == expected
        assert (mask != 0) == (hits[0] >= 0)
    assert 0.1 < np.mean(answers) < 0.9  # both answers were put to the test
