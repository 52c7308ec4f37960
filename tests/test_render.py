"""The path tracer: determinism, agreement with the slow reference, known answers, semantics, aux, bad input."""

from __future__ import annotations

import dataclasses
import importlib
import math
import os
import warnings

import numba
import numpy as np
import pytest

from kdtrace import _render_kernels as kernels
from kdtrace.imageio import read_exr, write_exr, write_png, write_render
from kdtrace.kdtree import build_kdtree
from kdtrace.rays import pinhole_directions
from kdtrace.render import ALL_FEATURES, render, render_stereo, scene_features, stereo_cameras
from kdtrace.scene import Camera, Material, Scene, Sky
from kdtrace.scenes import load_scene
from tests.render_reference import ReferenceTracer

SEED = 20261122


@pytest.fixture(scope="module", autouse=True)
def tree_cache(tmp_path_factory):
    """Keep this module's KD-trees out of the working directory's cache."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("KDTRACE_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


def _load(name: str) -> Scene:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # MTL keys the loader does not use
        return load_scene(name)


@pytest.fixture(scope="module")
def cbox():
    return _load("cbox-original")


def with_material(scene: Scene, name: str, **changes) -> Scene:
    """A copy of ``scene`` with the fields of material ``name`` replaced."""
    materials = [dataclasses.replace(m, **changes) if m.name == name else m for m in scene.materials]
    return dataclasses.replace(scene, materials=materials)


def cube_scene(albedo: float, emission: float) -> Scene:
    """A closed cube [-1, 1]^3 whose 12 triangles all face inwards; camera at the centre."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = []
    for a, b, c, d in faces:
        for tri in ((a, b, c), (a, c, d)):
            p = corners[list(tri)]
            normal = np.cross(p[1] - p[0], p[2] - p[0])
            triangles.append(tri if normal @ -p.mean(0) > 0 else tri[::-1])  # front side inwards
    material = Material("wall", albedo=(albedo,) * 3, emission=(emission,) * 3)
    camera = Camera((0.1, 0.2, 0.3), (0.1, 0.2, -1.0), fov=60.0, width=24, height=24)
    return Scene("furnace", corners, np.array(triangles), np.zeros(12, np.int32), [material], cameras=[camera])


def quad_scene(facing_camera: bool) -> Scene:
    """One emitting unit quad at z = 0 whose front faces +z (towards the camera) or -z."""
    vertices = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    triangles = np.array([[0, 1, 2], [0, 2, 3]] if facing_camera else [[0, 2, 1], [0, 3, 2]])
    camera = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov=30.0, width=16, height=16)
    material = Material("light", albedo=(0.5, 0.5, 0.5), emission=(2.0, 3.0, 4.0))
    return Scene("quad", vertices, triangles, np.zeros(2, np.int32), [material], cameras=[camera])


# ------------------------------------------------------------------ RNG and camera
def test_rng_is_uniform_and_keyed():
    key = np.uint64(kernels.sample_key(np.uint64(SEED), 17, 3))
    values = np.array([kernels.uniform(key, d) for d in range(4000)])
    assert values.min() >= 0.0 and values.max() < 1.0
    assert abs(values.mean() - 0.5) < 0.02 and abs(values.var() - 1 / 12) < 0.01
    others = {kernels.sample_key(np.uint64(s), p, n) for s in (0, 1) for p in (0, 1, 2) for n in (0, 1)}
    assert len(others) == 12
    assert kernels.uniform(key, 5) == kernels.uniform(np.uint64(kernels.sample_key(np.uint64(SEED), 17, 3)), 5)


def test_turn_cos_sin_matches_libm():
    """The path tracer's own cos/sin of 2 pi u against libm, exact at the quarter turns."""
    u = np.concatenate([np.random.default_rng(5).random(20_000), np.arange(16) / 16,
                        [np.nextafter(0.125, 0), np.nextafter(0.125, 1), np.nextafter(1.0, 0)]])
    ours = np.array([kernels.turn_cos_sin(x) for x in u])
    libm = np.stack([np.cos(2 * np.pi * u), np.sin(2 * np.pi * u)], axis=1)
    np.testing.assert_allclose(ours, libm, rtol=0, atol=1e-15)
    for k, exact in enumerate([(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)]):
        assert tuple(kernels.turn_cos_sin(k / 4)) == exact


def test_precomputed_geometric_normals_are_the_ones_computed_at_a_hit():
    """The path tracer reads each triangle's unit normal from ``geometric_normals``: the same
    numbers as :func:`geometric_normal` at a hit, bit for bit, and numpy's cross product to
    rounding; NaN for a zero-area triangle."""
    scene = load_scene("crytek-sponza")
    corners = np.ascontiguousarray(scene.vertices[scene.triangles].reshape(-1, 9))
    table = kernels.geometric_normals(corners)
    v = scene.vertices[scene.triangles].astype(np.float64)
    cross = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = np.linalg.norm(cross, axis=1)
    assert (area == 0).any() and np.isnan(table[area == 0]).all()
    picked = np.random.default_rng(5).choice(np.flatnonzero(area > 0), 500, replace=False)
    at_hit = np.array([kernels.geometric_normal(corners, int(tri)) for tri in picked])
    assert np.array_equal(table[picked], at_hit)
    np.testing.assert_allclose(table[area > 0], cross[area > 0] / area[area > 0, None], rtol=0, atol=1e-12)


def test_camera_matches_numpy_pinhole(cbox):
    from kdtrace.render import _camera_array

    camera = dataclasses.replace(cbox.camera, up=(0.1, 1.0, 0.2))
    cam = _camera_array(camera, 40, 30)
    x, y = np.array([0.0, 13.25, 39.9]), np.array([0.0, 7.5, 29.99])
    ours = np.array([kernels.camera_direction(cam, 40, 30, a, b) for a, b in zip(x, y, strict=True)])
    np.testing.assert_allclose(ours, pinhole_directions(camera, x, y, 40, 30), rtol=0, atol=1e-15)


# ------------------------------------------------------------------ determinism
def test_image_independent_of_threads_and_tiles(cbox):
    tree = build_kdtree(cbox)
    images = []
    threads = numba.get_num_threads()
    try:
        for n_threads, tile in ((1, 16), (min(2, numba.config.NUMBA_NUM_THREADS), 16), (min(2, numba.config.NUMBA_NUM_THREADS), 7)):
            numba.set_num_threads(n_threads)
            result = render(cbox, spp=2, max_depth=3, seed=SEED, width=24, height=20, tile_size=tile, tree=tree)
            images.append((result.rgb, result.variance, result.albedo, result.normal, result.depth))
    finally:
        numba.set_num_threads(threads)
    for other in images[1:]:
        for a, b in zip(images[0], other, strict=True):
            assert np.array_equal(a, b)
    again = render(cbox, spp=2, max_depth=3, seed=SEED + 1, width=24, height=20, tree=tree)
    assert not np.array_equal(again.rgb, images[0][0])


def test_adjacent_sample_ranges_average_to_the_render_of_their_union(cbox):
    tree = build_kdtree(cbox)
    whole = render(cbox, spp=5, max_depth=3, seed=SEED, width=24, height=20, tree=tree)
    first = render(cbox, spp=2, max_depth=3, seed=SEED, width=24, height=20, tree=tree)
    rest = render(cbox, spp=3, max_depth=3, seed=SEED, width=24, height=20, tree=tree, first_sample=2)
    assert rest.stats["first_sample"] == 2 and not np.array_equal(first.rgb, rest.rgb)
    for buffer in ("rgb", "albedo"):
        mean = (2 * getattr(first, buffer).astype(np.float64) + 3 * getattr(rest, buffer)) / 5
        np.testing.assert_allclose(mean, getattr(whole, buffer), rtol=1e-6, atol=1e-7)


def test_stats_count_rays_and_record_features(cbox):
    result = render(cbox, spp=2, max_depth=3, width=16, height=12)
    assert result.stats["rays"]["camera"] == result.stats["paths"] == 16 * 12 * 2
    assert 0 < result.stats["rays"]["shadow"] <= 2 * result.stats["paths"]
    assert 0 < result.stats["rays"]["bounce"] <= 2 * result.stats["paths"]
    assert result.stats["features"] == ["aux", "emitter_selection", "emitters"]
    assert result.stats["kernel"] == "specialised" and result.seconds > 0
    for buffer in (result.rgb, result.variance, result.albedo, result.normal, result.depth):
        assert buffer.dtype == np.float32
    assert scene_features(_load("cbox-sphere")) == {"aux", "emitter_selection", "emitters", "normals", "specular"}


# ------------------------------------------------------------------ agreement with the reference
@pytest.mark.parametrize("kind", ["diffuse", "mirror", "dielectric"])
def test_kernel_agrees_with_reference_tracer(cbox, kind):
    """Same RNG keys: the brute-force reference follows the same paths, so pixels agree to rounding."""
    scene = with_material(cbox, "tallBox", kind=kind, ior=1.5 if kind == "dielectric" else 1.0)
    width, height, spp, max_depth = 24, 24, 4, 4
    result = render(scene, spp=spp, max_depth=max_depth, seed=SEED, width=width, height=height, aux=False)
    reference = ReferenceTracer(scene, max_depth, SEED)
    pixels = [(12, 12), (15, 14), (9, 16), (5, 20), (18, 8), (12, 2), (3, 11), (16, 19)]
    agree = 0
    for i, j in pixels:
        expected = reference.pixel(i, j, spp, width, height)
        agree += np.allclose(result.rgb[j, i], expected, rtol=1e-4, atol=1e-6)
    # A path may rarely branch differently on a rounding difference (a grazing hit).
    assert agree >= len(pixels) - 1


# ------------------------------------------------------------------ known answers
@pytest.mark.parametrize("max_depth", [1, 2, 3, -1])
def test_furnace_radiance(max_depth):
    """Inside a closed box of albedo rho emitting E everywhere: L = E (1 + rho + ... + rho^(k-1))."""
    rho, emission = 0.5, 0.8
    scene = cube_scene(rho, emission)
    result = render(scene, spp=4, max_depth=max_depth, seed=SEED, aux=False)
    expected = emission / (1 - rho) if max_depth == -1 else emission * sum(rho**k for k in range(max_depth))
    pixels = result.rgb.shape[0] * result.rgb.shape[1]
    mean = result.rgb.mean(axis=(0, 1))
    standard_error = np.sqrt(result.variance.sum(axis=(0, 1))) / pixels
    if max_depth == 1:
        np.testing.assert_allclose(result.rgb, emission, rtol=1e-6)
    else:
        assert np.all(np.abs(mean - expected) <= 3 * standard_error + 1e-9)


def test_emitters_are_one_sided():
    front = render(quad_scene(True), spp=2, max_depth=1)
    back = render(quad_scene(False), spp=2, max_depth=1)
    hit = front.depth > 0
    assert hit.mean() > 0.3 and np.array_equal(hit, back.depth > 0)
    centre = front.rgb[6:10, 6:10]
    np.testing.assert_allclose(centre, np.broadcast_to([2.0, 3.0, 4.0], centre.shape), rtol=1e-6)
    assert np.all(back.rgb == 0.0)


def test_max_depth_one_shows_only_the_light(cbox):
    result = render(cbox, spp=2, max_depth=1, width=32, height=32)
    lit = result.rgb.max(axis=2) > 0
    assert 0 < lit.mean() < 0.1
    ratio = result.rgb[lit] / np.array([17.0, 12.0, 4.0])
    np.testing.assert_allclose(ratio, np.repeat(ratio[:, :1], 3, axis=1), rtol=1e-5)


def test_max_depth_two_has_no_indirect_light(cbox):
    """The ceiling sees only the back of the light: black with direct light only, lit with one bounce."""
    tree = build_kdtree(cbox)
    direct = render(cbox, spp=2, max_depth=2, width=32, height=32, tree=tree)
    ceiling_albedo = next(m.albedo for m in cbox.materials if m.name == "ceiling")
    ceiling = (direct.normal[:, :, 1] < -0.999) & np.all(np.abs(direct.albedo - ceiling_albedo) < 1e-6, axis=2)
    assert ceiling.sum() >= 20
    assert np.all(direct.rgb[ceiling] == 0.0)
    indirect = render(cbox, spp=4, max_depth=3, width=32, height=32, tree=tree)
    assert np.mean(indirect.rgb[ceiling].max(axis=1) > 0) > 0.75


def test_mirror_and_glass_render_finite():
    scene = _load("cbox-sphere")
    for max_depth in (3, -1):
        result = render(scene, spp=2, max_depth=max_depth, width=24, height=24, features=ALL_FEATURES)
        assert np.all(np.isfinite(result.rgb)) and np.all(result.rgb >= 0.0)
        assert np.all(np.isfinite(result.variance))
        assert result.rgb.mean() > 0.0


# ------------------------------------------------------------------ aux buffers
def test_aux_buffers_are_sane(cbox):
    result = render(cbox, spp=1, max_depth=2, width=32, height=32)  # one sample: no mixed pixels
    hit = result.depth > 0
    assert hit.mean() > 0.9  # the box fills nearly all the view
    lengths = np.linalg.norm(result.normal, axis=2)
    np.testing.assert_allclose(lengths[hit], 1.0, atol=1e-5)
    assert np.all(lengths[~hit] == 0.0) and np.all(result.albedo[~hit] == 0.0)
    assert result.depth[hit].min() > 3.0  # the camera is 3.9 in front of the box's open side
    for name, axis, sign in (("backWall", 2, 1.0), ("leftWall", 0, 1.0)):
        albedo = next(m.albedo for m in cbox.materials if m.name == name)
        facing = result.normal[:, :, axis] * sign > 0.9999
        assert facing.sum() > 10
        close = np.all(np.abs(result.albedo[facing] - albedo) < 1e-6, axis=1)
        assert close.all()
    no_aux = render(cbox, spp=1, max_depth=2, width=32, height=32, aux=False)
    assert no_aux.albedo is None and no_aux.normal is None and no_aux.depth is None
    assert np.array_equal(no_aux.rgb, result.rgb)


def test_specialised_and_general_kernels_agree(cbox):
    tree = build_kdtree(cbox)
    special = render(cbox, spp=2, max_depth=3, width=24, height=24, tree=tree)
    general = render(cbox, spp=2, max_depth=3, width=24, height=24, tree=tree, features=ALL_FEATURES)
    assert special.stats["kernel"] == "specialised" and general.stats["kernel"] == "general"
    assert np.array_equal(special.rgb, general.rgb)
    assert np.array_equal(special.normal, general.normal)


# ------------------------------------------------------------------ stereo
@pytest.mark.parametrize("case", ["emitters", "glass", "emitters and sky", "sky only", "textures and sky"])
def test_last_ray_shortcut_and_vector_spans_give_the_oracles_image(cbox, case):
    """Bit for bit, at max_depth 2 and 3: the last ray tested against the emitters and then for
    occlusion (or escape) gives the image of its full closest-hit walk, and ray queries (closest
    hit and occlusion) that test a node's triangles all at once give that of testing them one by
    one, each alone and together. The Cornell box's ceiling sees the back of the light, its open front lets rays
    reach the sky, and its glass box makes last rays follow specular bounces."""
    scene, features = cbox, None
    if case == "glass":
        scene = with_material(cbox, "tallBox", kind="dielectric", ior=1.5)
    elif case == "textures and sky":
        scene, features = _load("car"), ALL_FEATURES
    if "sky" in case:
        scene = dataclasses.replace(scene, sky=Sky((0.3, 0.4, 0.5)),
                                    cameras=[dataclasses.replace(scene.camera, fov=150.0)])
    if case == "sky only":
        scene = with_material(scene, "light", emission=(0.0, 0.0, 0.0))
        assert scene.emitter_triangles.size == 0
    tree = build_kdtree(scene)
    for max_depth in (2, 3):
        oracle, *fast = (render(scene, spp=3, max_depth=max_depth, seed=SEED, width=37, height=21, tree=tree,
                                features=features, last_ray_shortcut=shortcut, vector_spans=vector)
                         for shortcut, vector in ((False, False), (True, False), (False, True), (True, True)))
        for result in fast:
            for field in ("rgb", "variance", "albedo", "normal", "depth"):
                assert np.array_equal(getattr(oracle, field), getattr(result, field)), f"max_depth {max_depth}: {field}"
            assert oracle.stats["rays"] == result.stats["rays"]
        assert not oracle.stats["last_ray_shortcut"] and not oracle.stats["vector_spans"]
        assert fast[-1].stats["last_ray_shortcut"] and fast[-1].stats["vector_spans"]
        assert oracle.rgb.max() > 0.0
    # Both on by default for a scene with few emitter triangles.
    stats = render(scene, spp=1, width=8, height=8, tree=tree, features=features).stats
    assert stats["last_ray_shortcut"] and stats["vector_spans"]


def test_stereo_pair_differs_by_horizontal_parallax_only(cbox):
    left_camera, right_camera = stereo_cameras(cbox.camera, 0.3)
    offset = np.subtract(right_camera.position, left_camera.position)
    np.testing.assert_allclose(offset, [0.3, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.subtract(right_camera.look_at, right_camera.position),
                               np.subtract(cbox.camera.look_at, cbox.camera.position), atol=1e-12)
    left, right = render_stereo(cbox, eye_separation=0.3, spp=2, max_depth=1, width=48, height=48)
    assert not np.array_equal(left.albedo, right.albedo)
    errors = {}
    for dy in range(-3, 4):
        for dx in range(-6, 7):
            a = left.albedo[8:40, 8:40]
            b = right.albedo[8 + dy:40 + dy, 8 + dx:40 + dx]
            errors[dx, dy] = float(np.abs(a - b).mean())
    best_dx, best_dy = min(errors, key=errors.get)
    assert best_dy == 0 and best_dx < 0  # scene points move left in the right eye
    with pytest.raises(ValueError, match="eye_separation"):
        stereo_cameras(cbox.camera, 0.0)


# ------------------------------------------------------------------ bad input
def test_bad_arguments_are_clear_errors(cbox):
    for kwargs, match in (({"spp": 0}, "spp"), ({"width": 0}, "width"), ({"height": -2}, "height"),
                          ({"max_depth": 0}, "max_depth"), ({"seed": -1}, "seed"), ({"tile_size": 0}, "tile_size"),
                          ({"first_sample": -1}, "first_sample"), ({"first_sample": 1.5}, "first_sample"),
                          ({"features": {"emitters"}}, "needs features"), ({"features": {"bogus"}}, "unknown")):
        with pytest.raises(ValueError, match=match):
            render(cbox, **kwargs)
    with pytest.raises(ValueError, match="NaN"):
        render(cbox, camera=dataclasses.replace(cbox.camera, up=(math.nan, 1.0, 0.0)))
    with pytest.raises(ValueError, match="floor"):
        render(with_material(cbox, "floor", albedo=(math.nan, 0.5, 0.5)))


@pytest.mark.parametrize(("aux", "gib", "buffers"), [(True, "48,545.19", "rgb, variance, albedo, normal and depth"),
                                                     (False, "22,468.16", "rgb and variance")])
def test_resolution_too_large_for_memory_is_refused_before_any_work(cbox, aux, gib, buffers, monkeypatch):
    def no_tree(*args, **kwargs):
        raise AssertionError("the size check must come before the tree is built")

    monkeypatch.setattr(importlib.import_module("kdtrace.render"), "build_kdtree", no_tree)  # the module, not the function
    with pytest.raises(ValueError, match=rf"width x height = 1000000 x 1000000 \(1,000,000,000,000 pixels\) "
                                         rf"for the {buffers} buffers needs up to {gib} GiB"):
        render(cbox, width=10**6, height=10**6, aux=aux)


def test_scene_without_light_is_black_with_warning(cbox):
    dark = dataclasses.replace(cbox, materials=[dataclasses.replace(m, emission=(0.0, 0.0, 0.0)) for m in cbox.materials])
    with pytest.warns(UserWarning, match="no emitter and no sky"):
        result = render(dark, spp=1, width=8, height=8, features=ALL_FEATURES)
    assert np.all(result.rgb == 0.0) and np.mean(result.depth > 0) > 0.5


def test_camera_inside_geometry_and_sky_render(cbox):
    inside = dataclasses.replace(cbox.camera, position=(0.3, 0.5, 0.3), look_at=(0.3, 0.5, -1.0))
    result = render(cbox, camera=inside, spp=1, width=8, height=8)
    assert np.all(np.isfinite(result.rgb))
    sky = quad_scene(True)
    sky = dataclasses.replace(sky, sky=Sky((0.25, 0.5, 1.0)), cameras=[dataclasses.replace(sky.camera, fov=90.0)])
    result = render(sky, spp=1, max_depth=1, features=ALL_FEATURES)
    np.testing.assert_allclose(result.rgb[0, 0], [0.25, 0.5, 1.0])  # the corner pixel misses the quad


def test_camera_looking_at_nothing_warns(cbox):
    away = dataclasses.replace(cbox.camera, look_at=(0.0, 1.0, 10.0))
    with pytest.warns(UserWarning, match="looks at nothing"):
        result = render(cbox, camera=away, spp=1, width=8, height=8)
    assert np.all(result.rgb == 0.0)


def test_missing_texture_warns_and_uses_flat_albedo(tmp_path):
    scene = quad_scene(True)
    scene = dataclasses.replace(
        scene, texcoords=np.zeros((4, 2), np.float32),
        materials=[dataclasses.replace(scene.materials[0], texture=str(tmp_path / "missing.png"))])
    with pytest.warns(UserWarning, match="missing.png"):
        result = render(scene, spp=1, max_depth=1, features=ALL_FEATURES)
    np.testing.assert_allclose(result.albedo[8, 8], [0.5, 0.5, 0.5])


def test_texture_is_looked_up(tmp_path):
    from PIL import Image

    path = tmp_path / "red.png"
    Image.fromarray(np.full((2, 2, 3), [255, 0, 0], np.uint8)).save(path)
    scene = quad_scene(True)
    scene = dataclasses.replace(
        scene, texcoords=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32),
        materials=[dataclasses.replace(scene.materials[0], texture=str(path))])
    result = render(scene, spp=1, max_depth=1, features=ALL_FEATURES)
    np.testing.assert_allclose(result.albedo[8, 8], [1.0, 0.0, 0.0], atol=1e-6)


# ------------------------------------------------------------------ image files
def test_exr_and_png_writes_are_atomic_and_round_trip(tmp_path, cbox):
    image = np.random.default_rng(SEED).random((5, 7, 3)).astype(np.float32) * 10
    path = write_exr(tmp_path / "a.exr", image)
    assert np.array_equal(read_exr(path), image)
    write_exr(tmp_path / "d.exr", image[:, :, 0])
    assert read_exr(tmp_path / "d.exr").shape == (5, 7)
    write_png(tmp_path / "a.png", image)
    result = render(cbox, spp=1, width=8, height=8)
    written = write_render(result, tmp_path / "out", "cbox")
    assert set(written) == {"png", "rgb", "variance", "albedo", "normal", "depth"}
    assert not [name for name in os.listdir(tmp_path / "out") if ".tmp" in name]
    with pytest.raises(ValueError, match="shape"):
        write_exr(tmp_path / "bad.exr", np.zeros((2, 2, 2)))
    assert not (tmp_path / "bad.exr").exists()
