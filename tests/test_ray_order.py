"""Regrouped batch queries (``kdtrace._ray_order``): the keys against their definition, and the
same answers and counters as the batch traced as given, on the stress scenes and every ray kind;
likewise the vector span test against one-by-one tests."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from kdtrace import _ray_order as ray_order
from kdtrace.config import KDTreeConfig
from kdtrace.kdtree import VARIANTS, build_kdtree
from kdtrace.scene import Material, Scene
from tests.strategies import RAY_KINDS, make_rays, stress_scenes, tree_configs


def keys_by_definition(origins, directions, box, bits=ray_order.ORIGIN_BITS):
    """Octant above the Morton code of the origin's cell, one ray at a time in plain Python."""
    cells = 1 << bits
    keys = []
    for origin, direction in zip(origins, directions, strict=True):
        code = 0
        for axis in range(3):
            extent = box[axis + 3] - box[axis]
            position = (origin[axis] - box[axis]) * (cells / extent) if extent > 0 else 0.0
            cell = int(min(max(position, 0.0), cells - 1.0))
            for bit in range(bits):
                code |= ((cell >> bit) & 1) << (3 * bit + axis)
        octant = sum(int(direction[axis] < 0.0) << axis for axis in range(3))
        keys.append(octant << (3 * bits) | code)
    return np.array(keys)


def test_keys_are_the_octant_above_the_origin_cells_morton_code():
    rng = np.random.default_rng(11)
    box = np.array([-1.0, 0.0, 2.0, 1.0, 0.0, 6.0])  # flat along y: every origin in cell 0 there
    origins = rng.uniform([-1.5, -1.0, 1.0], [1.5, 1.0, 7.0], (2000, 3))  # some outside the box
    origins[:10] = box[:3]  # on the lower faces
    origins[10:20] = box[3:]  # on the upper faces (the last cell)
    origins[20] = [1e300, -1e300, 0.0]  # far outside: clamped, not an undefined conversion
    directions = rng.normal(size=(2000, 3))
    directions[:50, 0] = -0.0  # a negative zero is not negative
    directions[50:100, 2] = 0.0
    keys = ray_order.regroup_keys(origins, directions, box)
    assert keys.dtype == np.int16
    np.testing.assert_array_equal(keys, keys_by_definition(origins, directions, box))
    assert len(np.unique(keys)) > 100


def test_order_is_a_stable_sort_of_the_keys():
    rng = np.random.default_rng(12)
    origins = rng.uniform(0.0, 1.0, (5000, 3))
    directions = rng.normal(size=(5000, 3))
    box = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0])
    order = ray_order.regroup_order(origins, directions, box)
    keys = ray_order.regroup_keys(origins, directions, box)
    np.testing.assert_array_equal(np.sort(order), np.arange(5000))
    assert (np.diff(keys[order]) >= 0).all()
    same = np.diff(keys[order]) == 0
    assert (np.diff(order)[same] > 0).all()  # rays of one group keep their order


def test_gathered_rays_are_the_rays_in_that_order():
    rng = np.random.default_rng(13)
    origins, directions = rng.normal(size=(2, 300, 3))
    tmin, tmax = rng.uniform(0, 1, 300), rng.uniform(1, 2, 300)
    order = rng.permutation(300)
    for ours, theirs in zip(ray_order.gather_rays(order, origins, directions, tmin, tmax),
                            (origins, directions, tmin, tmax), strict=True):
        np.testing.assert_array_equal(ours, theirs[order])


@settings(max_examples=12, deadline=None, derandomize=True, database=None, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(case=stress_scenes(max_triangles=300), config=tree_configs, seed=st.integers(0, 2**16),
       ray_kind=st.sampled_from(RAY_KINDS), tmax_fraction=st.sampled_from([np.inf, 0.5]))
@pytest.mark.parametrize("option", ["regroup", "vector_spans"])
def test_fast_batch_queries_answer_exactly_as_the_oracle(option, case, config, seed, ray_kind, tmax_fraction):
    """Regrouped rays against the batch as given, and a node's triangles found hit all at once
    (``vector_spans``) against one by one: closest hits, occlusion answers and both counters, ray
    for ray, bit for bit."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # zero-area triangles left out (expected here)
        trees = {variant: build_kdtree(case.scene, variant, config, cache=False) for variant in VARIANTS}
    origins, directions = make_rays(ray_kind, case.scene, trees["naive"], 300, seed)
    lo, hi = case.scene.bounds
    tmax = tmax_fraction * float(np.linalg.norm(np.subtract(hi, lo)) + 1.0)
    for tree in trees.values():
        given_hits = tree.intersect(origins, directions, tmax=tmax, **{option: False})
        given_counters = tree.last_counters
        fast_hits = tree.intersect(origins, directions, tmax=tmax, **{option: True})
        for ours, theirs in zip(fast_hits, given_hits, strict=True):
            np.testing.assert_array_equal(ours, theirs)
        np.testing.assert_array_equal(tree.last_counters.nodes_visited, given_counters.nodes_visited)
        np.testing.assert_array_equal(tree.last_counters.triangle_tests, given_counters.triangle_tests)
        blocked = tree.occluded(origins, directions, tmax, **{option: False})
        blocked_counters = tree.last_counters
        np.testing.assert_array_equal(tree.occluded(origins, directions, tmax, **{option: True}), blocked)
        np.testing.assert_array_equal(tree.last_counters.nodes_visited, blocked_counters.nodes_visited)
        np.testing.assert_array_equal(tree.last_counters.triangle_tests, blocked_counters.triangle_tests)
        assert blocked.any() or not np.isfinite(given_hits[0]).any()


def _two_triangles() -> Scene:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float32)
    return Scene("two", vertices, np.arange(6).reshape(2, 3), np.zeros(2), [Material("grey")])


def test_trees_regroup_by_their_size_and_never_packets():
    scene = _two_triangles()
    always = build_kdtree(scene, config=KDTreeConfig(regroup_min_bytes=0), cache=False)
    assert always.regroups
    small = build_kdtree(scene, config=KDTreeConfig(), cache=False)  # a few hundred bytes, below the default
    assert not small.regroups
    origins = np.tile([0.2, 0.2, -1.0], (20, 1))
    directions = np.tile([0.0, 0.0, 1.0], (20, 1))
    t, tri, _, _ = always.intersect(origins, directions, packets=True)  # packets: the batch's own order
    np.testing.assert_array_equal(tri, 0)
    np.testing.assert_allclose(t, 1.0)
    with pytest.raises(ValueError, match="packets or regroup"):
        always.intersect(origins, directions, packets=True, regroup=True)
