"""Packet traversal against the scalar kernel (its oracle): the same hits and counters, ray by ray.

:mod:`kdtrace._packet_traverse` claims that every ray of a packet makes the scalar walk's
decisions in the scalar walk's order, so t, triangle, u, v, nodes visited and triangle
tests are the scalar kernel's bit for bit. Checked on the stress scenes with every ray
kind of :mod:`tests.strategies` (origins on split planes, rays lying in them, zero and
signed-zero direction components, rays through vertices and edges), grouped into
packets that share an origin (the packets camera rays make) and as they come; on real
scenes' camera rays; and through the path tracer, whose images must not change.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from numba import njit

from kdtrace import _kdtree_traverse as scalar_kernels
from kdtrace import _packet_traverse as packet_kernels
from kdtrace.config import KDTreeConfig
from kdtrace.kdtree import VARIANTS, build_kdtree, validate_rays
from kdtrace.rays import camera_rays
from kdtrace.render import ALL_FEATURES, render
from kdtrace.scene import Sky
from kdtrace.scenes import load_scene
from tests.strategies import RAY_KINDS, make_rays, stress_scenes, tree_configs

pytestmark = [
    pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning"),
    pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning"),
]

OUTPUTS = ("t", "triangle", "u", "v", "nodes visited", "triangle tests")


@pytest.fixture(scope="module", autouse=True)
def tree_cache(tmp_path_factory):
    """Keep this module's KD-trees out of the working directory's cache."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("KDTRACE_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


def _outputs(n: int) -> list[np.ndarray]:
    return [np.empty(n), np.empty(n, np.int32), np.empty(n), np.empty(n), np.empty(n, np.int32), np.empty(n, np.int32)]


def trace_both(tree, origins, directions, tmax=np.inf, packet_size=packet_kernels.PACKET_SIZE):
    """(scalar, packet) outputs of the closest-hit queries over (0, tmax)."""
    origins, directions, tmin, tmax = validate_rays(origins, directions, 0.0, tmax)
    n = len(origins)
    chunks = max(1, min(n, 4))
    scalar = _outputs(n)
    scalar_kernels.trace_batch(tree.node_words, tree.node_splits, tree.refs, tree.box, tree.corners,
                               scalar_kernels.no_spans(tree.corners), origins, directions, tmin, tmax, False,
                               tree.watertight, chunks, *scalar)
    packet = _outputs(n)
    packet_kernels.trace_batch_packets(tree.node_words, tree.node_splits, tree.refs, tree.box, tree.corners,
                                       origins, directions, tmax, tree.watertight, packet_size, chunks, *packet)
    return scalar, packet


def assert_same(scalar, packet, context: str) -> None:
    for name, a, b in zip(OUTPUTS, scalar, packet, strict=True):
        differ = np.flatnonzero(~((a == b) | (np.isnan(a) & np.isnan(b))) if a.dtype.kind == "f" else a != b)
        assert len(differ) == 0, f"{context}: {name} differs on {len(differ)} rays, first {differ[:5]}: {a[differ[:5]]} != {b[differ[:5]]}"


def shared_origins(origins: np.ndarray, size: int) -> np.ndarray:
    """Every ray takes the origin of the first ray of its packet (a camera's packets)."""
    first = (np.arange(len(origins)) // size) * size
    return origins[first]


@njit
def _packet_completes(nodes, splits, refs, box, corners, origins, directions, n, watertight):
    return packet_kernels.trace_packet(nodes, splits, refs, box, corners, origins, directions, n, np.inf, watertight,
                                       packet_kernels.packet_scratch())


def packet_runs(tree, origins, directions) -> int:
    """How many packets of ``PACKET_SIZE`` consecutive rays :func:`trace_packet` completes."""
    origins, directions, _, _ = validate_rays(origins, directions, 0.0, np.inf)
    size = packet_kernels.PACKET_SIZE
    done = 0
    for start in range(0, len(origins), size):
        n = min(size, len(origins) - start)
        done += _packet_completes(tree.node_words, tree.node_splits, tree.refs, tree.box, tree.corners,
                                  origins[start:start + n], directions[start:start + n], n, tree.watertight)
    return done


fast = settings(max_examples=12, deadline=None, derandomize=True, database=None, phases=[Phase.explicit, Phase.generate],
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@fast
@given(case=stress_scenes(max_triangles=400), config=tree_configs, seed=st.integers(0, 2**16),
       ray_kind=st.sampled_from(RAY_KINDS), triangle_test=st.sampled_from(["watertight", "moller-trumbore"]))
def test_packets_give_the_scalar_kernels_hits_and_counters(case, config, seed, ray_kind, triangle_test):
    config = dataclasses.replace(config, triangle_test=triangle_test)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # zero-area triangles left out (expected here)
        trees = {variant: build_kdtree(case.scene, variant, config, cache=False) for variant in VARIANTS}
    origins, directions = make_rays(ray_kind, case.scene, trees["naive"], 203, seed)  # 12 full packets and a partial one
    for variant, tree in trees.items():
        for label, o in (("own origins", origins), ("shared origins", shared_origins(origins, packet_kernels.PACKET_SIZE))):
            scalar, packet = trace_both(tree, o, directions)
            assert_same(scalar, packet, f"{case!r}, {variant}, {ray_kind} rays, {label}")


def occluded_both(tree, origins, directions, tmax):
    """(scalar, packet) answers of the occlusion queries over (0, tmax)."""
    origins, directions, tmin, tmax = validate_rays(origins, directions, 0.0, tmax)
    n = len(origins)
    scalar = _outputs(n)
    scalar_kernels.trace_batch(tree.node_words, tree.node_splits, tree.refs, tree.box, tree.corners,
                               scalar_kernels.no_spans(tree.corners), origins, directions, tmin, tmax, True,
                               tree.watertight, 4, *scalar)
    packet = np.empty(n, np.bool_)
    packet_kernels.occluded_batch_packets(tree.node_words, tree.node_splits, tree.refs, tree.box, tree.corners,
                                          origins, directions, tmax, 4, packet)
    return scalar[1] >= 0, packet


@fast
@given(case=stress_scenes(max_triangles=400), config=tree_configs, seed=st.integers(0, 2**16),
       ray_kind=st.sampled_from(RAY_KINDS))
def test_occlusion_packets_block_exactly_the_rays_the_scalar_kernel_blocks(case, config, seed, ray_kind):
    """Rays that disagree on near children stay in an occlusion packet, so this holds for any
    grouping: the rays as they come, and sharing their packet's first origin (shadow rays
    of nearby hits are between the two). Segments of every length, some unbounded."""
    config = dataclasses.replace(config, triangle_test="watertight")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # zero-area triangles left out (expected here)
        trees = {variant: build_kdtree(case.scene, variant, config, cache=False) for variant in VARIANTS}
    origins, directions = make_rays(ray_kind, case.scene, trees["naive"], 203, seed)
    rng = np.random.default_rng(seed)
    extent = float(np.abs(case.scene.vertices).max()) + 1.0
    tmax = np.where(rng.random(len(origins)) < 0.2, np.inf, extent * rng.random(len(origins)) ** 3)
    for variant, tree in trees.items():
        for label, o in (("own origins", origins), ("shared origins", shared_origins(origins, packet_kernels.PACKET_SIZE))):
            scalar, packet = occluded_both(tree, o, directions, tmax)
            differ = np.flatnonzero(scalar != packet)
            assert len(differ) == 0, f"{case!r}, {variant}, {ray_kind} rays, {label}: rays {differ[:5]} differ"


def test_occlusion_packets_on_shadow_rays_of_a_real_scene():
    """Shadow rays from the hits of jittered camera rays (8 a pixel, the renderer's order) to
    points on car's light: the packets' answers are the scalar kernel's, with both answers common."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # MTL keys the loader does not use
        scene = load_scene("car")
    tree = build_kdtree(scene)
    rng = np.random.default_rng(3)
    samples = [camera_rays(scene.camera, 48, 40, jitter=True, rng=rng) for _ in range(8)]
    origins = np.stack([s[0] for s in samples], axis=1).reshape(-1, 3)
    directions = np.stack([s[1] for s in samples], axis=1).reshape(-1, 3)
    t, triangle, _, _ = tree.intersect(origins, directions)
    points = (origins + t[:, None] * directions)[triangle >= 0]
    light = scene.vertices[scene.triangles[scene.emitter_triangles]].astype(np.float64)
    pick = rng.integers(0, len(light), len(points))
    weights = rng.dirichlet(np.ones(3), len(points))
    targets = np.einsum("nk,nkc->nc", weights, light[pick])
    to_light = targets - points
    distance = np.linalg.norm(to_light, axis=1)
    to_light /= distance[:, None]
    scalar, packet = occluded_both(tree, points + 1e-4 * to_light, to_light, distance * (1.0 - 1e-4))
    np.testing.assert_array_equal(scalar, packet)
    assert 0.05 < scalar.mean() < 0.95


def test_packets_split_at_a_plane_through_their_origin_fall_back_to_single_rays():
    """A shared origin on a split plane, directions on both sides of it: the rays disagree
    on the near child, the packet gives up, and the single rays give the scalar answers."""
    scene = load_scene("cbox-original")
    tree = build_kdtree(scene, "local", KDTreeConfig(), cache=False)
    axis = int(tree.node_words[0] & 3)  # the root's split (every ray inside the box meets it)
    assert axis < 3
    origin = (tree.box[:3] + tree.box[3:]).astype(np.float64) / 2
    origin[axis] = tree.node_splits[1]
    rng = np.random.default_rng(5)
    directions = rng.normal(size=(16, 3))
    directions[:, axis] = np.where(np.arange(16) % 2 == 0, 1.0, -1.0) * np.abs(directions[:, axis])
    origins = np.repeat(origin[None], 16, axis=0)
    assert packet_runs(tree, origins, directions) == 0
    scalar, packet = trace_both(tree, origins, directions)
    assert_same(scalar, packet, "origin on a split plane")
    assert (scalar[1] >= 0).any()


def test_packets_with_different_tmax_fall_back_to_single_rays():
    scene = load_scene("cbox-original")
    tree = build_kdtree(scene, "local", KDTreeConfig(), cache=False)
    origins, directions = camera_rays(scene.camera, 8, 4)
    tmax = np.where(np.arange(32) % 3 == 0, 1.0, np.inf)
    scalar, packet = trace_both(tree, origins, directions, tmax)
    assert_same(scalar, packet, "mixed tmax")
    assert np.isinf(scalar[0][::3]).any() and np.isfinite(scalar[0]).any()


@pytest.mark.parametrize("name", ["cbox-sphere", "car"])
def test_camera_ray_packets_on_real_scenes(name):
    """Jittered camera rays, pixel after pixel with 8 samples each (the renderer's order)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # MTL keys the loader does not use
        scene = load_scene(name)
    rng = np.random.default_rng(11)
    samples = [camera_rays(scene.camera, 48, 40, jitter=True, rng=rng) for _ in range(8)]
    origins = np.stack([s[0] for s in samples], axis=1).reshape(-1, 3)
    directions = np.stack([s[1] for s in samples], axis=1).reshape(-1, 3)
    for variant in VARIANTS:
        tree = build_kdtree(scene, variant)
        for size in (1, 5, packet_kernels.PACKET_SIZE):
            scalar, packet = trace_both(tree, origins, directions, packet_size=size)
            assert_same(scalar, packet, f"{name} {variant} camera rays, packets of {size}")
        # Not vacuous: the packets do run (they fall back only on a split plane through the camera).
        assert packet_runs(tree, origins, directions) == -(-len(origins) // packet_kernels.PACKET_SIZE)
        assert (scalar[1] >= 0).mean() > 0.5
        # The public entry point (Table 1's primary rays): the same hits and counters.
        hits = tree.intersect(origins, directions)
        counters = tree.last_counters
        packet_hits = tree.intersect(origins, directions, packets=True)
        for a, b in zip(hits, packet_hits, strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(counters.nodes_visited, tree.last_counters.nodes_visited)
        np.testing.assert_array_equal(counters.triangle_tests, tree.last_counters.triangle_tests)
        with pytest.raises(ValueError, match="tmin must be 0"):
            tree.intersect(origins, directions, tmin=1e-3, packets=True)


@pytest.mark.parametrize(("name", "sky"), [("cbox-original", False), ("cbox-sphere", False), ("car", True)])
def test_renders_with_camera_packets_equal_the_scalar_renders(name, sky):
    """Camera and first shadow rays in packets against one by one: bit for bit, with the aux
    buffers, at a size that leaves partial tiles and an spp that makes packets span pixels;
    mirror and glass (cbox-sphere), textures (car) and a sky."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = load_scene(name)
    if sky:
        scene = dataclasses.replace(scene, sky=Sky((0.3, 0.4, 0.5)),
                                    cameras=[dataclasses.replace(scene.camera, fov=150.0)])
    tree = build_kdtree(scene)
    for max_depth, spp in ((1, 3), (3, 5)):
        images = {}
        for packets in (False, True):
            result = render(scene, spp=spp, max_depth=max_depth, seed=17, width=37, height=21, tile_size=16,
                            tree=tree, features=ALL_FEATURES if sky else None, camera_packets=packets,
                            shadow_packets=packets)
            images[packets] = result
        a, b = images[False], images[True]
        for field in ("rgb", "variance", "albedo", "normal", "depth"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), f"{name}, max_depth {max_depth}: {field}"
        assert a.stats["rays"] == b.stats["rays"]
        assert b.stats["camera_packets"] and not a.stats["camera_packets"]
        assert b.stats["shadow_packets"] and not a.stats["shadow_packets"]
        assert a.rgb.max() > 0.0


@njit(error_model="numpy")
def _loaded_lanes(box, origins, directions, tmax, n):
    """The lane state :func:`kdtrace._packet_traverse._load_lanes` fills, copied out."""
    lanes3, lanes, lane_ints, _, _, _ = packet_kernels.packet_scratch()
    for r in range(n):
        lanes[packet_kernels._BEST, r] = tmax[r]
    active, along_x, along_y, along_z = packet_kernels._load_lanes(box, origins, directions, n, True, lanes3, lanes,
                                                                   lane_ints)
    return active, along_x | (along_y << 16) | (along_z << 32), lanes3.copy(), lanes.copy(), lane_ints.copy()


def test_loaded_lanes_hold_the_scalar_walks_interval_reciprocals_and_shear():
    """Lane for lane, the branch-free load gives what ``clip_to_box``, the reciprocals and
    ``ray_shear`` give one ray at a time: origins on and off the box, zero components of both signs."""
    rng = np.random.default_rng(21)
    box = np.array([-1.0, -2.0, 0.0, 1.0, 2.0, 3.0])
    size = packet_kernels.PACKET_SIZE
    for trial in range(200):
        n = int(rng.integers(1, size + 1))
        origins = rng.uniform(-2.0, 3.5, (n, 3))
        origins[rng.random((n, 3)) < 0.15] = 1.0  # on a face of the box, or in its planes
        directions = rng.normal(size=(n, 3))
        zero = rng.random((n, 3)) < 0.2
        directions[zero] = np.where(rng.random(zero.sum()) < 0.5, 0.0, -0.0)
        directions[~directions.any(axis=1), 2] = 1.0
        tmax = np.where(rng.random(n) < 0.2, np.inf, rng.uniform(0.0, 5.0, n))
        active, along, lanes3, lanes, lane_ints = _loaded_lanes(box, origins, directions, tmax, n)
        for r in range(n):
            o, d = origins[r], directions[r]
            ent, ext = scalar_kernels.clip_to_box(box, *o, *d, 0.0, tmax[r])
            assert (lanes[packet_kernels._ENT, r], lanes[packet_kernels._EXT, r]) == (ent, ext), (trial, r)
            assert bool(active >> r & 1) == (ent <= ext)
            inverse = [1.0 / c if c != 0.0 else np.inf for c in d]
            np.testing.assert_array_equal(lanes3[packet_kernels._INVERSE, :, r], inverse)
            kx, ky, kz, sx, sy, sz = scalar_kernels.ray_shear(*d)
            assert tuple(lane_ints[packet_kernels._KX:packet_kernels._KZ + 1, r]) == (kx, ky, kz)
            assert (along >> (16 * kz + r)) & 1 == 1
            np.testing.assert_array_equal(lanes3[packet_kernels._PERMUTED, :, r], o[[kx, ky, kz]])
            np.testing.assert_array_equal(lanes[[packet_kernels._SHEAR_X, packet_kernels._SHEAR_Y,
                                                 packet_kernels._SHEAR_Z], r], [sx, sy, sz])
        assert active >> n == 0  # lanes past n stay inactive
