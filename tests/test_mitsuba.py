"""Mitsuba 3 references: variant choice, exact conversion, conventions, statistics, cache.

Scenes are built by hand (tiny, 32x32 or 64x64, a few spp) so the whole file runs in
well under a minute on a shared 2-core machine.
"""

from __future__ import annotations

import numpy as np
import pytest

from kdtrace.scene import Camera, Material, Scene, Sky
from references import llvm
from references import mitsuba as mref

# ---------------------------------------------------------------- scene builders


def quad(corner, u, v) -> list[np.ndarray]:
    """Corners of the parallelogram corner, corner+u, corner+u+v, corner+v (front = u x v)."""
    corner, u, v = (np.asarray(x, dtype=np.float64) for x in (corner, u, v))
    return [corner, corner + u, corner + u + v, corner + v]


def scene_of(quads: list[tuple[list[np.ndarray], int]], materials: list[Material], camera: Camera,
             sky: Sky | None = None, name: str = "test") -> Scene:
    """A Scene of two counter-clockwise triangles per quad."""
    vertices, triangles, ids = [], [], []
    for corners, material in quads:
        base = len(vertices)
        vertices.extend(corners)
        triangles += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
        ids += [material, material]
    return Scene(name, np.array(vertices, np.float32), np.array(triangles), np.array(ids), materials,
                 cameras=[camera], sky=sky)


def cornell_like(size: int = 32) -> Scene:
    """Open box [-1, 1]^3 seen from +z: red left wall (x = -1), green right wall, ceiling light."""
    materials = [Material("white", albedo=(0.7, 0.7, 0.7)), Material("red", albedo=(0.7, 0.1, 0.1)),
                 Material("green", albedo=(0.1, 0.7, 0.1)),
                 Material("light", albedo=(0.5, 0.5, 0.5), emission=(15.0, 15.0, 15.0))]
    quads = [
        (quad((-1, -1, -1), (2, 0, 0), (0, 2, 0)), 0),  # back wall, front +z
        (quad((-1, -1, 1), (2, 0, 0), (0, 0, -2)), 0),  # floor, front +y
        (quad((-1, 1, -1), (2, 0, 0), (0, 0, 2)), 0),  # ceiling, front -y
        (quad((-1, -1, 1), (0, 0, -2), (0, 2, 0)), 1),  # left wall, front +x
        (quad((1, -1, -1), (0, 0, 2), (0, 2, 0)), 2),  # right wall, front -x
        (quad((-0.3, 0.99, -0.3), (0.6, 0, 0), (0, 0, 0.6)), 3),  # light, front -y
    ]
    camera = Camera((0.0, 0.0, 3.5), (0.0, 0.0, 0.0), fov=40.0, width=size, height=size)
    return scene_of(quads, materials, camera, name="cornell-like")


def emitter_scene(facing_camera: bool, corner=(-0.5, -0.5, 0.0), side: float = 1.0, size: int = 32) -> Scene:
    """One emissive square in the z = 0 plane, camera on +z; front toward the camera or away."""
    u, v = (side, 0, 0), (0, side, 0)
    corners = quad(corner, u, v) if facing_camera else quad(corner, v, u)
    camera = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov=40.0, width=size, height=size)
    light = Material("light", albedo=(0.5, 0.5, 0.5), emission=(2.0, 3.0, 4.0))
    return scene_of([(corners, 0)], [light], camera, name="emitter")


@pytest.fixture(scope="module", params=[None, "scalar_rgb"], ids=["default", "scalar"])
def variant(request) -> str:
    """Each rendering test runs with the default variant (llvm_ad_rgb when usable) and scalar_rgb."""
    return llvm.activate_variant(request.param)


# ------------------------------------------------------------------ variant choice


def test_find_llvm_reads_the_given_directories(tmp_path):
    assert llvm.find_llvm((tmp_path,)) is None
    (tmp_path / "libLLVM.so.19.1").write_bytes(b"")
    assert llvm.find_llvm((tmp_path / "missing", tmp_path)) == tmp_path / "libLLVM.so.19.1"


def test_bogus_llvm_falls_back_to_scalar_with_a_warning(monkeypatch):
    monkeypatch.setenv(llvm.LLVM_ENV, "/nonexistent/libLLVM.so.19.1")
    with pytest.warns(llvm.LLVMFallbackWarning, match="nonexistent"):
        chosen, library = llvm.select_variant()
    assert (chosen, library) == ("scalar_rgb", None)


def test_missing_llvm_falls_back_to_scalar_with_a_warning(monkeypatch):
    monkeypatch.delenv(llvm.LLVM_ENV, raising=False)
    monkeypatch.setattr(llvm, "find_llvm", lambda directories=llvm.LLVM_DIRECTORIES: None)
    with pytest.warns(llvm.LLVMFallbackWarning, match="setup-llvm.sh"):
        assert llvm.select_variant("llvm_ad_rgb") == ("scalar_rgb", None)


def test_unsupported_variant_is_an_error():
    with pytest.raises(ValueError, match="cuda_ad_rgb"):
        llvm.select_variant("cuda_ad_rgb")


@pytest.mark.skipif(llvm.find_llvm() is None, reason="LLVM 19 not installed (scripts/setup-llvm.sh)")
def test_llvm_variant_really_renders():
    assert llvm.activate_variant() == "llvm_ad_rgb"
    reference = mref.render_reference(cornell_like(16), spp=4, max_depth=3, seed=0, variant="llvm_ad_rgb",
                                      cache=False)
    assert reference.variant == "llvm_ad_rgb"
    assert reference.metadata["libllvm"] and "19" in reference.metadata["libllvm"]
    assert np.all(np.isfinite(reference.rgb)) and reference.rgb.mean() > 0


# ---------------------------------------------------------------------- conversion


def test_conversion_keeps_the_exact_arrays_per_material(variant):
    import mitsuba as mi

    scene = cornell_like()
    rng = np.random.default_rng(7)
    scene.vertices += rng.normal(scale=1e-3, size=scene.vertices.shape).astype(np.float32)
    normals = rng.normal(size=scene.vertices.shape)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    texcoords = rng.random((len(scene.vertices), 2))
    # A zero-area triangle (repeated vertex) in material 1: dropped, like the KD-tree drops it.
    triangles = np.vstack([scene.triangles, [[0, 0, 1]]])
    scene = Scene("exact", scene.vertices, triangles, np.append(scene.material_ids, 1), scene.materials,
                  normals=normals, texcoords=texcoords, cameras=scene.cameras)
    mitsuba_scene, counts = mref.to_mitsuba(scene, max_depth=2, width=8, height=8, spp=2)
    assert counts["zero_area_dropped"] == 1 and counts["meshes"] == len(scene.materials)
    shapes = {shape.id(): shape for shape in mitsuba_scene.shapes()}
    for index, rows in mref.material_triangles(scene):
        params = mi.traverse(shapes[mref._mesh_name(index, scene.materials[index])])
        positions = np.array(params["vertex_positions"], dtype=np.float32).reshape(-1, 3)
        faces = np.array(params["faces"]).reshape(-1, 3)
        expected = scene.triangles[rows]
        assert np.array_equal(positions[faces].view(np.uint32), scene.vertices[expected].view(np.uint32))
        mesh_normals = np.array(params["vertex_normals"], dtype=np.float32).reshape(-1, 3)
        assert np.array_equal(mesh_normals[faces], scene.normals[expected])
        uv = np.array(params["vertex_texcoords"], dtype=np.float32).reshape(-1, 2)[faces]
        assert np.array_equal(uv[..., 0], scene.texcoords[expected][..., 0])
        assert np.array_equal(uv[..., 1], (1.0 - scene.texcoords[expected][..., 1]).astype(np.float32))


def test_material_mapping():
    mirror = mref.bsdf_dict(Material("m", "mirror", albedo=(0.9, 0.8, 0.7)), has_texcoords=False)
    assert mirror["type"] == "twosided" and mirror["material"]["material"] == "none"
    glass = mref.bsdf_dict(Material("g", "dielectric", albedo=(1.0, 1.0, 0.9), ior=1.5), has_texcoords=False)
    assert (glass["type"], glass["int_ior"], glass["ext_ior"]) == ("dielectric", 1.5, 1.0)
    with pytest.warns(UserWarning, match="not found"):
        diffuse = mref.bsdf_dict(Material("d", texture="/nonexistent.png"), has_texcoords=True)
    assert diffuse["material"]["reflectance"]["type"] == "rgb"


# ----------------------------------------------------------------- known answers


@pytest.mark.statistical
def test_plane_under_a_constant_sky_reflects_albedo_times_radiance(variant):
    """Lambertian plane, albedo rho, sky L, max_depth 2 (direct only): radiance rho * L everywhere."""
    albedo, radiance = np.array([0.2, 0.5, 0.8]), np.array([1.0, 2.0, 0.5])
    camera = Camera((0.0, 1.0, 0.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, -1.0), fov=30.0, width=32, height=32)
    plane = quad((-5, 0, 5), (10, 0, 0), (0, 0, -10))  # front +y, toward the camera
    scene = scene_of([(plane, 0)], [Material("plane", albedo=tuple(albedo))], camera, sky=Sky(tuple(radiance)))
    reference = mref.render_reference(scene, spp=16, max_depth=2, seed=3, variant=variant, cache=False)
    pixels = reference.rgb.shape[0] * reference.rgb.shape[1]
    mean = reference.rgb.mean(axis=(0, 1))
    standard_error = np.sqrt(reference.variance.sum(axis=(0, 1))) / pixels
    assert np.all(np.abs(mean - albedo * radiance) < 5 * standard_error + 1e-6)


def test_emitters_are_one_sided_toward_the_counter_clockwise_front(variant):
    front = mref.render_reference(emitter_scene(True), spp=2, max_depth=1, seed=0, variant=variant, cache=False)
    back = mref.render_reference(emitter_scene(False), spp=2, max_depth=1, seed=0, variant=variant, cache=False)
    centre = front.rgb[12:20, 12:20].reshape(-1, 3)
    assert np.allclose(centre, [2.0, 3.0, 4.0])
    assert back.rgb.max() == 0.0


def test_camera_keeps_left_on_the_left_and_up_at_the_top(variant):
    # Small emitter at x < 0 (viewer's left: right = forward x up = +x) and y > 0 (up).
    scene = emitter_scene(True, corner=(-0.8, 0.4, 0.0), side=0.3)
    image = mref.render_reference(scene, spp=2, max_depth=1, seed=0, variant=variant, cache=False).rgb
    rows, columns = np.nonzero(image.sum(axis=2) > 0)
    assert len(rows) > 0
    assert columns.max() < image.shape[1] // 2, "emitter on the viewer's left must be in the left half"
    assert rows.max() < image.shape[0] // 2, "emitter above the centre must be in the top half (row 0 = top)"


def test_cornell_like_red_wall_is_on_the_left(variant):
    image = mref.render_reference(cornell_like(), spp=4, max_depth=3, seed=0, variant=variant, cache=False).rgb
    left, right = image[8:24, :3].mean(axis=(0, 1)), image[8:24, -3:].mean(axis=(0, 1))
    assert left[0] > 2 * left[1] and right[1] > 2 * right[0]


# ---------------------------------------------------------------- variance, cache


@pytest.mark.statistical
def test_variance_of_the_mean_scales_as_one_over_spp(variant):
    scene = cornell_like()
    low = mref.render_reference(scene, spp=8, max_depth=3, seed=1, variant=variant, cache=False)
    high = mref.render_reference(scene, spp=32, max_depth=3, seed=2, variant=variant, cache=False)
    assert (low.variance > 0).mean() > 0.9
    ratio = low.variance.mean() / high.variance.mean()
    assert 3.0 < ratio < 5.3, ratio
    # Two independent estimates differ by as much as their variances say.
    other = mref.render_reference(scene, spp=32, max_depth=3, seed=5, variant=variant, cache=False)
    noisy = (high.variance + other.variance) > 0
    z2 = (high.rgb - other.rgb)[noisy] ** 2 / (high.variance + other.variance)[noisy]
    assert 0.7 < z2.mean() < 1.3, z2.mean()


def test_cache_hit_returns_identical_arrays_and_spp_changes_the_key(isolated_cache, variant, monkeypatch):
    scene = cornell_like(16)
    first = mref.render_reference(scene, spp=4, max_depth=3, seed=0, variant=variant)
    assert len(list((isolated_cache / "mitsuba").glob("*.npz"))) == 1

    def no_render(*args, **kwargs):
        raise AssertionError("expected a cache hit")

    monkeypatch.setattr(mref, "_render", no_render)
    second = mref.render_reference(scene, spp=4, max_depth=3, seed=0, variant=variant)
    assert np.array_equal(first.rgb, second.rgb) and np.array_equal(first.variance, second.variance)
    assert second.metadata == first.metadata and second.seconds == first.seconds
    keys = {mref.reference_key(scene, spp, 3, 0, 16, 16, variant) for spp in (4, 8)}
    keys.add(mref.reference_key(scene, 4, 3, 1, 16, 16, variant))
    assert len(keys) == 3


def test_interrupted_render_resumes_from_its_checkpoint(isolated_cache, variant, monkeypatch):
    scene = cornell_like(16)
    monkeypatch.setattr(mref, "PASS_SAMPLES", 16 * 16 * 2)  # 2 spp per pass: 4 passes
    monkeypatch.setattr(mref, "CHECKPOINT_SECONDS", -1.0)  # checkpoint after every pass
    original, calls = mref._render_pass, []

    def failing_pass(*args):
        calls.append(args)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return original(*args)

    monkeypatch.setattr(mref, "_render_pass", failing_pass)
    with pytest.raises(KeyboardInterrupt):
        mref.render_reference(scene, spp=8, max_depth=3, seed=0, variant=variant)
    assert len(list((isolated_cache / "mitsuba").glob("*.partial.npz"))) == 1
    resumed = mref.render_reference(scene, spp=8, max_depth=3, seed=0, variant=variant)
    assert len(calls) == 5  # two passes before the interruption, two after it
    assert not list((isolated_cache / "mitsuba").glob("*.partial.npz"))
    monkeypatch.setattr(mref, "_render_pass", original)
    fresh = mref.render_reference(scene, spp=8, max_depth=3, seed=0, variant=variant, cache=False)
    assert np.allclose(resumed.rgb, fresh.rgb, rtol=1e-5, atol=1e-6)


def test_invalid_settings_are_errors():
    with pytest.raises(ValueError, match="spp"):
        mref.render_reference(cornell_like(8), spp=1, max_depth=3, seed=0)
    with pytest.raises(ValueError, match="max_depth"):
        mref.render_reference(cornell_like(8), spp=4, max_depth=0, seed=0)


def test_write_images(tmp_path, variant):
    reference = mref.render_reference(cornell_like(8), spp=2, max_depth=2, seed=0, variant=variant, cache=False)
    paths = mref.write_images(reference, tmp_path / "cbox")
    assert [path.name for path in paths] == ["cbox.exr", "cbox.variance.exr", "cbox.png"]
    import mitsuba as mi

    assert np.allclose(np.array(mi.Bitmap(str(paths[0]))), reference.rgb)
    assert all(path.stat().st_size > 0 for path in paths)
    assert not list(tmp_path.glob(".*"))
