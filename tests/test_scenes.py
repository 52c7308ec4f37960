"""Scene descriptions: every shipped scene loads and its camera sees geometry; TOML features; search path."""

from __future__ import annotations

import os
import re
import warnings

import numpy as np
import pytest

from kdtrace.io import SceneError, SceneWarning
from kdtrace.scenes import DEFAULT_SKY_RADIANCE, SCENES_ENV, list_scenes, load_scene

# Triangle counts from ../shared/scenes/README.md (car = 12 + 10,461).
EXPECTED_TRIANGLES = {
    "cbox-original": 36,
    "cbox-mirror": 36,
    "cbox-sphere": 2188,
    "cbox-empty": 12,
    "car": 12 + 10461,
    "bunny": 69451,
    "dabrovic-sponza": 66454,
    "samurai-monastery": 124789,
    "crytek-sponza": 262267,
    "pine": 12 + 2 + 69451,
}


def quiet_load(*args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SceneWarning)
        return load_scene(*args, **kwargs)


def test_every_shared_scene_has_a_description():
    assert set(EXPECTED_TRIANGLES) <= set(list_scenes())


@pytest.mark.parametrize("name", list_scenes())
def test_scene_loads_is_lit_and_its_camera_sees_geometry(shared_scenes, name, camera_coverage):
    scene = quiet_load(name)
    if name in EXPECTED_TRIANGLES:
        assert len(scene.triangles) == EXPECTED_TRIANGLES[name]
    assert scene.sky is not None or len(scene.emitter_triangles) > 0
    central_hit, fraction = camera_coverage(scene)
    assert central_hit and fraction >= 0.25, (central_hit, fraction)


def test_car_dragon_stands_on_the_floor_inside_the_box(shared_scenes):
    scene = quiet_load("car")
    dragon = np.flatnonzero(scene.material_ids == [m.name for m in scene.materials].index("dragon"))
    assert len(dragon) == 10461
    corners = scene.vertices[scene.triangles[dragon]].reshape(-1, 3)
    box = scene.vertices[scene.triangles[np.setdiff1d(np.arange(len(scene.triangles)), dragon)]].reshape(-1, 3)
    assert corners[:, 1].min() == pytest.approx(0.0, abs=1e-3)
    assert np.all(corners.min(0) > box.min(0)) and np.all(corners.max(0) < box.max(0))


def test_pine_is_the_bunny_in_a_recoloured_box_with_two_stronger_lights(shared_scenes):
    """Table 3's near unseen scene (the paper's Pine): other object, wall colours and lights than the car's box."""
    pine, car = quiet_load("pine"), quiet_load("car")
    colours = {m.name: m.albedo for m in pine.materials}
    assert colours["leftWall"] != {m.name: m.albedo for m in car.materials}["leftWall"]
    assert pine.bounds[0][1] == pytest.approx(0.0, abs=1e-3)  # the bunny stands on the floor

    def power(scene):
        emitting = [m for m in scene.materials if max(m.emission) > 0]
        return len(emitting), max(max(m.emission) for m in emitting)
    (lights, strongest), (car_lights, car_strongest) = power(pine), power(car)
    assert lights == car_lights + 1 and strongest > car_strongest


def test_cbox_sphere_materials(shared_scenes):
    scene = quiet_load("cbox-sphere")
    kinds = {m.name: m.kind for m in scene.materials}
    assert kinds["leftSphere"] == "mirror" and kinds["rightSphere"] == "dielectric"
    assert scene.sky is None and len(scene.emitter_triangles) == 2


def test_bare_mesh_gets_default_camera_and_sky(shared_scenes, camera_coverage):
    scene = quiet_load("stanford-dragon-10k/dragon-10k.obj")
    camera = scene.camera
    centre = 0.5 * (scene.bounds[0] + scene.bounds[1])
    assert np.allclose(camera.look_at, centre) and camera.position[2] > scene.bounds[1][2]
    assert camera.up == (0.0, 1.0, 0.0) and camera.fov == 40.0 and (camera.width, camera.height) == (512, 512)
    assert scene.sky is not None and scene.sky.radiance == DEFAULT_SKY_RADIANCE
    assert camera_coverage(scene)[0]
    lit = quiet_load("cornell-box/CornellBox-Original.obj")
    assert lit.sky is None  # has an area light


# ------------------------------------------------------------------------ TOML features
TRIANGLE_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nvn 0 0 1\nvn 0 0 1\nf 1//1 2//2 3//3\n"


@pytest.fixture
def mesh_folder(tmp_path):
    (tmp_path / "tri.obj").write_text(TRIANGLE_OBJ)
    (tmp_path / "m.mtl").write_text("newmtl paint\nKd 0.2 0.3 0.4\n")
    (tmp_path / "painted.obj").write_text("mtllib m.mtl\nv 0 0 5\nv 1 0 5\nv 0 1 5\nusemtl paint\nf 1 2 3\n")
    return tmp_path


def write_toml(folder, text, name="scene.toml"):
    path = folder / name
    path.write_text(text)
    return path


def test_transform_scale_then_rotate_then_translate(mesh_folder):
    path = write_toml(
        mesh_folder,
        '[[mesh]]\nfile = "tri.obj"\n'
        "transform = { scale = [2, 3, 1], rotate = { axis = [0, 0, 1], degrees = 90 }, translate = [10, 0, 0] }\n",
    )
    scene = load_scene(path)
    corners = scene.vertices[scene.triangles[0]]
    # (1,0,0) -> scale (2,0,0) -> rotate (0,2,0) -> translate (10,2,0); (0,1,0) -> (0,3,0) -> (-3,0,0) -> (7,0,0)
    np.testing.assert_allclose(corners, [[10, 0, 0], [10, 2, 0], [7, 0, 0]], atol=1e-5)
    np.testing.assert_allclose(scene.normals, [[0, 0, 1]] * 3, atol=1e-6)
    assert scene.sky is not None  # nothing emits


def test_euler_rotation_and_mirroring_keep_the_front_side(mesh_folder):
    path = write_toml(mesh_folder, '[[mesh]]\nfile = "tri.obj"\ntransform = { rotate = { euler = [90, 0, 0] } }\n')
    rotated = load_scene(path)
    corners = rotated.vertices[rotated.triangles[0]].astype(np.float64)
    np.testing.assert_allclose(corners, [[0, 0, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)  # y -> z about x
    mirrored = load_scene(write_toml(mesh_folder, '[[mesh]]\nfile = "tri.obj"\ntransform = { scale = [1, 1, -1] }\n'))
    corners = mirrored.vertices[mirrored.triangles[0]].astype(np.float64)
    geometric = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    assert np.dot(geometric, mirrored.normals[0]) > 0  # winding flipped with the normals


def test_materials_override_light_sky_and_cameras(mesh_folder):
    text = """
name = "custom"
[[mesh]]
file = "painted.obj"
[[mesh]]
file = "tri.obj"
material_override = "gold"
[materials.paint]
emission = [5, 5, 5]
[materials.gold]
kind = "mirror"
albedo = [1.0, 0.8, 0.3]
[sky]
radiance = [0.1, 0.2, 0.3]
[[light]]
corners = [[0, 2, 0], [1, 2, 0], [1, 2, 1], [0, 2, 1]]
emission = [10, 10, 10]
[[camera]]
position = [0, 0, 10]
look_at = [0, 0, 0]
[[camera]]
position = [0, 10, 0.5]
look_at = [0, 0, 0.5]
up = [0, 0, 1]
fov = 30
width = 64
height = 32
"""
    scene = load_scene(write_toml(mesh_folder, text), search_path=[mesh_folder])
    assert scene.name == "custom" and len(scene.triangles) == 4
    by_name = {m.name: m for m in scene.materials}
    assert by_name["paint"].albedo == (0.2, 0.3, 0.4) and by_name["paint"].emission == (5.0, 5.0, 5.0)
    assert by_name["gold"].kind == "mirror" and by_name["gold"].albedo == (1.0, 0.8, 0.3)
    assert by_name["light_0"].emission == (10.0, 10.0, 10.0)
    assert [scene.materials[i].name for i in scene.material_ids] == ["paint", "gold", "light_0", "light_0"]
    assert scene.sky.radiance == (0.1, 0.2, 0.3)
    assert len(scene.cameras) == 2 and scene.cameras[1].up == (0.0, 0.0, 1.0) and scene.cameras[1].width == 64
    assert scene.normals is not None  # painted.obj and the light got geometric normals
    light = scene.vertices[scene.triangles[2]].astype(np.float64)
    assert np.cross(light[1] - light[0], light[2] - light[0])[1] < 0  # faces down, towards the meshes


def test_mesh_found_through_environment_variable(tmp_path, mesh_folder, monkeypatch):
    (tmp_path / "elsewhere").mkdir()
    path = write_toml(tmp_path / "elsewhere", '[[mesh]]\nfile = "sub/tri.obj"\n')
    (mesh_folder / "sub").mkdir()
    (mesh_folder / "sub" / "tri.obj").write_text(TRIANGLE_OBJ)
    with pytest.raises(SceneError, match="sub/tri.obj: file not found; looked in:"):
        load_scene(path)
    monkeypatch.setenv(SCENES_ENV, f"{tmp_path / 'nothing'}{os.pathsep}{mesh_folder}")
    assert len(load_scene(path).triangles) == 1


def test_missing_mesh_error_names_every_place_looked(tmp_path, monkeypatch):
    monkeypatch.setenv(SCENES_ENV, str(tmp_path / "extra"))
    path = write_toml(tmp_path, '[[mesh]]\nfile = "no/such.obj"\n')
    with pytest.raises(SceneError) as error:
        load_scene(path, search_path=[tmp_path / "first"])
    message = str(error.value)
    for folder in (tmp_path / "first", tmp_path, tmp_path / "extra"):
        assert str(folder / "no/such.obj") in message


def test_unknown_scene_name_lists_the_available_ones():
    with pytest.raises(SceneError, match=re.escape("unknown scene 'nope'; available: ") + ".*cbox-original"):
        load_scene("nope")


def test_directory_is_refused_naming_what_is_accepted_and_its_mesh_files(tmp_path, mesh_folder):
    message = r"is a directory .*, not a scene; load_scene takes a scene name \(.*cbox-original.*\), a \.toml description"
    with pytest.raises(SceneError, match=message + ".*" + re.escape(f"in it: {mesh_folder / 'painted.obj'}, "
                                                                    f"{mesh_folder / 'tri.obj'}")):
        load_scene(mesh_folder)
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneError, match=message + ".*it holds no .toml, .obj or .ply file"):
        load_scene(tmp_path / "empty")
    with pytest.raises(SceneError, match=re.escape(f"'empty' is a directory ({tmp_path / 'empty'})")):
        load_scene("empty", search_path=[tmp_path])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "needs at least one [[mesh]]"),
        ('[[mesh]]\nfile = "tri.obj"\ncolour = 1\n', "unknown key(s) ['colour'] in [[mesh]] 0"),
        ('[[mesh]]\nfile = "tri.obj"\n[materials.nothing]\nkind = "diffuse"\n', "['nothing'] match no material"),
        ('[[mesh]]\nfile = "tri.obj"\nmaterial_override = "x"\n', "material_override 'x' is not defined"),
        ('[[mesh]]\nfile = "tri.obj"\n[materials.default]\nkind = "plastic"\n', "kind must be diffuse"),
        ('[[mesh]]\nfile = "tri.obj"\ntransform = { scale = 0 }\n', "scale must not be zero"),
        ('[[mesh]]\nfile = "tri.obj"\ntransform = { rotate = { axis = [0, 1, 0] } }\n', "needs either 'axis' and 'degrees'"),
        ('[[mesh]]\nfile = "tri.obj"\n[sky]\nradiance = [1, 1]\n', "radiance must be a list of 3 numbers"),
        ('[[mesh]]\nfile = "tri.obj"\n[[camera]]\nposition = [0, 0, 1]\nlook_at = [0, 0, 1]\n', "look_at must differ"),
        ('[[mesh]]\nfile = "tri.obj"\n[[light]]\ncorners = [[0, 0, 0]]\nemission = [1, 1, 1]\n', "corners must be a list of 4"),
        ("[[mesh]\n", "invalid TOML"),
    ],
)
def test_bad_description_raises_scene_error_naming_the_file(mesh_folder, text, message):
    path = write_toml(mesh_folder, text)
    with pytest.raises(SceneError, match=re.escape(str(path)) + ".*" + re.escape(message)):
        load_scene(path)
