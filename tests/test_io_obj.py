"""OBJ and MTL readers: real scenes against an independent parse, edge cases, errors, cache."""

from __future__ import annotations

import re
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from kdtrace.io import SceneError, SceneWarning, cache_directory, load_mesh
from kdtrace.io.mtl import read_mtl
from kdtrace.io.obj import read_obj
from kdtrace.scene import Material

#: Small OBJ files modelled on other loaders' bug reports (each cites them at its top).
DATA = Path(__file__).parent / "data" / "obj"

# (file, triangles) from ../shared/scenes/README.md
REAL_OBJS = [
    ("cornell-box/CornellBox-Original.obj", 36),
    ("cornell-box/CornellBox-Mirror.obj", 36),
    ("cornell-box/CornellBox-Sphere.obj", 2188),
    ("cornell-box/CornellBox-Empty-RG.obj", 12),
    ("stanford-dragon-10k/dragon-10k.obj", 10461),
    ("stanford-bunny/bunny.obj", 69451),
    ("dabrovic-sponza/sponza.obj", 66454),
    ("samurai-monastery/samurai_monastry.obj", 124789),
]


def independent_obj_summary(path: Path) -> tuple[int, float, Counter]:
    """Triangle count, float64 area and triangles per usemtl name: a minimal regex parse.

    Written independently of kdtrace.io.obj: only the first index of each corner is
    used, negative indices are resolved against the vertices read so far, polygons are
    fanned, faces with fewer than 3 corners are skipped.
    """
    positions: list[list[float]] = []
    corners: list[tuple[int, int, int]] = []
    per_material: Counter = Counter()
    material = None
    for line in re.split(r"\r\n|\r|\n", path.read_text()):
        words = line.split()
        if not words:
            continue
        if words[0] == "v":
            positions.append([float(w) for w in words[1:4]])
        elif words[0] == "usemtl":
            material = words[1]
        elif words[0] == "f":
            ids = [int(w.split("/")[0]) for w in words[1:]]
            ids = [i - 1 if i > 0 else len(positions) + i for i in ids]
            for k in range(1, len(ids) - 1):
                corners.append((ids[0], ids[k], ids[k + 1]))
                per_material[material] += 1
    a, b, c = np.transpose(np.array(positions, dtype=np.float64)[np.array(corners)], (1, 0, 2))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    return len(corners), float(area), per_material


def write(path: Path, text: str, newline: str = "\n") -> Path:
    path.write_bytes(text.replace("\n", newline).encode())
    return path


def messages(record) -> list[str]:
    return [str(w.message) for w in record]


def quiet_read(path: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SceneWarning)
        return read_obj(path)


# ------------------------------------------------------------------------ real scenes
@pytest.mark.parametrize(("file", "expected_triangles"), REAL_OBJS, ids=[f for f, _ in REAL_OBJS])
def test_real_obj_matches_independent_parse(shared_scenes, file, expected_triangles):
    scene = quiet_read(shared_scenes / file)
    triangles, area, per_material = independent_obj_summary(shared_scenes / file)
    assert len(scene.triangles) == expected_triangles == triangles
    assert scene.triangles.dtype == np.int32 and scene.vertices.dtype == np.float32
    assert scene.material_ids.dtype == np.int32
    assert scene.triangle_areas().sum() == pytest.approx(area, rel=1e-5)
    counts = Counter(scene.materials[i].name for i in scene.material_ids)
    if None in per_material:
        counts[None] = counts.pop("default")
    assert counts == per_material


def test_samurai_monastery_keeps_its_83_zero_area_triangles(shared_scenes):
    with pytest.warns(SceneWarning, match=r"samurai_monastry\.obj:\d+: 201 face\(s\) with 2 vertices") as record:
        scene = read_obj(shared_scenes / "samurai-monastery/samurai_monastry.obj")
    assert len(record) == 1
    assert int(scene.degenerate_mask().sum()) == 83
    assert len(scene.materials) == 81  # 82 in the .mtl, 81 used
    assert scene.normals is None and scene.texcoords is not None


def test_cornell_box_materials(shared_scenes):
    original = read_obj(shared_scenes / "cornell-box/CornellBox-Original.obj")
    light = next(m for m in original.materials if m.name == "light")
    assert light.emission == (17.0, 12.0, 4.0)
    emitting = {original.materials[original.material_ids[t]].name for t in original.emitter_triangles}
    assert emitting == {"light"} and len(original.emitter_triangles) == 2
    assert all(m.kind == "diffuse" for m in original.materials)

    with pytest.warns(SceneWarning, match=r"CornellBox-Mirror\.mtl:\d+: unknown MTL key 'Pe'"):
        mirror = read_obj(shared_scenes / "cornell-box/CornellBox-Mirror.obj")
    tall = next(m for m in mirror.materials if m.name == "tallBox")
    assert tall.kind == "mirror" and tall.albedo == (0.95, 0.95, 0.95)

    with pytest.warns(SceneWarning, match="'Pe'"):
        spheres = read_obj(shared_scenes / "cornell-box/CornellBox-Sphere.obj")
    by_name = {m.name: m for m in spheres.materials}
    assert by_name["leftSphere"].kind == "mirror"
    assert by_name["rightSphere"].kind == "dielectric" and by_name["rightSphere"].ior == 1.6
    assert by_name["rightSphere"].albedo == (0.95, 0.95, 0.95)
    assert by_name["light"].is_emitter
    assert spheres.normals is not None and spheres.texcoords is not None
    assert np.allclose(np.linalg.norm(spheres.normals, axis=1), 1.0, atol=1e-6)


def test_dragon_zero_normals_are_repaired(shared_scenes):
    dragon = read_obj(shared_scenes / "stanford-dragon-10k/dragon-10k.obj")  # 41 "vn 0 0 0", CR and CRLF
    assert np.allclose(np.linalg.norm(dragon.normals, axis=1), 1.0, atol=1e-6)
    assert dragon.texcoords is None


# ---------------------------------------------------------------------- syntax coverage
SQUARE = """# a unit square
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
f 1 2 3 4
"""


def test_crlf_cr_and_negative_indices_match_plain_file(tmp_path):
    reference = quiet_read(write(tmp_path / "plain.obj", SQUARE))
    relative = SQUARE.replace("f 1 2 3 4", "f -4 -3 -2 -1   \t")
    for newline in ("\r\n", "\r"):
        scene = quiet_read(write(tmp_path / "relative.obj", relative, newline))
        np.testing.assert_array_equal(scene.vertices, reference.vertices)
        np.testing.assert_array_equal(scene.triangles, reference.triangles)
    assert reference.triangles.tolist() == [[0, 1, 2], [0, 2, 3]]  # fan
    assert reference.triangle_areas().sum() == pytest.approx(1.0)
    assert reference.normals is None and reference.texcoords is None
    assert [m.name for m in reference.materials] == ["default"]


def test_negative_index_is_relative_to_the_vertices_read_so_far(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 5 5 5\nv 6 5 5\nv 5 6 5\nf -3 -2 -1\n"
    scene = quiet_read(write(tmp_path / "a.obj", text))
    corners = scene.vertices[scene.triangles]
    assert corners[0].tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    assert corners[1].tolist() == [[5, 5, 5], [6, 5, 5], [5, 6, 5]]


def test_all_face_forms_and_vertex_splitting(tmp_path):
    text = (
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\nvn 0 0 -1\n"
        "f 1/1/1 2/2/1 3/3/1\n"  # v/vt/vn
        "f 1/1/2 3/3/2 2/2/2\n"  # same positions, other normal: split vertices
        "f 1//1 2//1 3//1\n"  # v//vn: no texcoord -> (0, 0)
        "f 1/2 2/3 3/1\n"  # v/vt: no normal -> geometric
        "f 1 2 3\n"
    )
    scene = quiet_read(write(tmp_path / "forms.obj", text))
    assert len(scene.triangles) == 5
    corners = scene.vertices[scene.triangles].tolist()
    triangle, reversed_triangle = [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 0], [0, 1, 0], [1, 0, 0]]
    assert corners == [triangle, reversed_triangle, triangle, triangle, triangle]
    normals = scene.normals[scene.triangles]
    assert normals[0].tolist() == [[0, 0, 1]] * 3 and normals[1].tolist() == [[0, 0, -1]] * 3
    assert normals[3].tolist() == [[0, 0, 1]] * 3  # geometric normal of a CCW triangle in z = 0
    assert scene.texcoords[scene.triangles[2]].tolist() == [[0, 0]] * 3
    assert scene.texcoords[scene.triangles[3]].tolist() == [[1, 0], [0, 1], [0, 0]]
    assert len(np.unique(scene.triangles)) == len(scene.vertices)


def test_comments_blank_lines_groups_and_unknown_keywords(tmp_path):
    text = "\n  # indented comment\no thing\ng a b\ns 1\nv 0 0 0 # trailing comment\nv 1 0 0\nv 0 1 0\n\ncurv 0 1\nf 1 2 3\n"
    with pytest.warns(SceneWarning, match=r"odd\.obj:10: unknown OBJ keyword 'curv'"):
        scene = read_obj(write(tmp_path / "odd.obj", text))
    assert len(scene.triangles) == 1


def test_zero_area_triangles_are_kept(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 3\nf 1 1 4\nf 1 2 4\n"
    scene = quiet_read(write(tmp_path / "flat.obj", text))
    assert len(scene.triangles) == 3 and scene.degenerate_mask().tolist() == [True, True, False]


# --------------------------------------------------------------------------- materials
MTL = """newmtl white
Kd 0.8 0.8 0.8
newmtl lamp
Kd 0.5 0.5 0.5
Ke 10 10 10
newmtl chrome
Ks 0.95 0.95 0.95
Ns 800
newmtl glossy
Kd 0.3 0.2 0.1
Ks 0.5 0.5 0.5
Ns 96
newmtl glass
Ni 1.5
d 0.2
newmtl tinted
Ni 1.33
Tf 0.9 1 0.8
newmtl opaque_ior
Kd 0.1 0.2 0.3
Ni 1.5
newmtl textured
Kd 0.9
map_Kd -s 1 1 1 textures/wood.png
"""


def test_mtl_mapping_rules(tmp_path):
    materials = read_mtl(write(tmp_path / "m.mtl", MTL))
    assert materials["white"].kind == "diffuse" and materials["white"].albedo == (0.8, 0.8, 0.8)
    assert materials["lamp"].emission == (10.0, 10.0, 10.0) and materials["lamp"].kind == "diffuse"
    assert materials["chrome"].kind == "mirror" and materials["chrome"].albedo == (0.95, 0.95, 0.95)
    assert materials["glossy"].kind == "diffuse" and materials["glossy"].albedo == (0.3, 0.2, 0.1)
    assert materials["glass"].kind == "dielectric" and materials["glass"].ior == 1.5
    assert materials["glass"].albedo == (1.0, 1.0, 1.0)
    assert materials["tinted"].kind == "dielectric" and materials["tinted"].albedo == (0.9, 1.0, 0.8)
    assert materials["opaque_ior"].kind == "diffuse"
    assert materials["textured"].albedo == (0.9, 0.9, 0.9)
    assert materials["textured"].texture == str(tmp_path / "textures/wood.png")


def test_mtl_unknown_key_warns_once_with_file_and_line(tmp_path):
    path = write(tmp_path / "u.mtl", "newmtl a\nKd 1 1 1\nfoo 1\nnewmtl b\nfoo 2\nbar\n")
    with pytest.warns(SceneWarning) as record:
        read_mtl(path)
    messages = [str(w.message) for w in record]
    assert len(messages) == 2
    assert f"{path}:3: unknown MTL key 'foo'" in messages[0] and f"{path}:6: unknown MTL key 'bar'" in messages[1]


def test_obj_material_assignment_and_missing_materials(tmp_path):
    write(tmp_path / "m.mtl", MTL)
    text = "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nusemtl lamp\nf 1 2 3\nusemtl nowhere\nf 1 2 3\nusemtl lamp\nf 1 2 3\n"
    with pytest.warns(SceneWarning) as record:
        scene = read_obj(write(tmp_path / "a.obj", text))
    messages = " | ".join(str(w.message) for w in record)
    assert f"{tmp_path / 'a.obj'}:5: faces without 'usemtl'" in messages
    assert f"{tmp_path / 'a.obj'}:8: material 'nowhere' is not defined in m.mtl" in messages
    names = [scene.materials[i].name for i in scene.material_ids]
    assert names == ["default", "lamp", "nowhere", "lamp"]
    assert scene.materials[scene.material_ids[2]].albedo == (0.5, 0.5, 0.5)
    assert scene.emitter_triangles.tolist() == [1, 3]


def test_obj_without_mtllib_gets_one_default_material_per_usemtl(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl a\nf 1 2 3\nusemtl b\nf 1 2 3\nusemtl a\nf 1 2 3\n"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = read_obj(write(tmp_path / "a.obj", text))
    assert [m.name for m in scene.materials] == ["a", "b"] and scene.material_ids.tolist() == [0, 1, 0]
    assert all(m.kind == "diffuse" and not m.is_emitter for m in scene.materials)


# ------------------------------------------- files other loaders read: load with a warning
def test_missing_mtl_file_warns_and_gives_default_materials():
    path = DATA / "missing_mtl.obj"
    with pytest.warns(SceneWarning) as record:
        scene = read_obj(path)
    assert messages(record) == [
        f"{path}:7: material library 'missing_mtl.mtl' not found in {DATA}; its materials get a default grey diffuse"
    ]
    assert len(scene.triangles) == 3
    assert [scene.materials[i].name for i in scene.material_ids] == ["wood", "wood", "metal"]
    assert scene.materials == [Material("wood"), Material("metal")]


def test_several_mtllibs_load_those_found_first_definition_wins():
    path = DATA / "several_mtllibs.obj"
    with pytest.warns(SceneWarning) as record:
        scene = read_obj(path)
    assert messages(record) == [  # the repeated mtllib line neither warns again nor reads the files again
        f"{path}:10: material library 'several_c.mtl' not found in {DATA}; its materials get a default grey diffuse",
        f"{DATA / 'several_b.mtl'}:5: unknown MTL key 'Pe' ignored",
        f"{path}:21: material 'nowhere' is not defined in several_a.mtl, several_b.mtl; "
        "using a default grey diffuse material",
    ]
    by_triangle = [scene.materials[i] for i in scene.material_ids]
    assert [m.name for m in by_triangle] == ["red", "lamp", "shared", "nowhere"]
    assert by_triangle[0].albedo == (0.8, 0.1, 0.1)  # several_a.mtl
    assert by_triangle[1].emission == (10.0, 10.0, 10.0)  # several_b.mtl
    assert by_triangle[2].albedo == (0.1, 0.8, 0.1)  # several_a.mtl's, not several_b.mtl's (0.1, 0.1, 0.8)
    assert by_triangle[3] == Material("nowhere")


@pytest.mark.parametrize("file", ["mtllib_name_with_space.obj", "mtllib_name_escaped.obj"])
def test_mtl_file_name_with_a_space(file):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = read_obj(DATA / file)
    assert [m.name for m in scene.materials] == ["stone"] and scene.materials[0].albedo == (0.6, 0.6, 0.5)


def test_mtl_name_with_spaces_found_under_no_reading_warns_naming_both(tmp_path):
    path = write(tmp_path / "a.obj", "mtllib my lib.mtl\n" + TRIANGLE + "usemtl x\nf 1 2 3\n")
    with pytest.warns(SceneWarning) as record:
        scene = read_obj(path)
    assert messages(record) == [
        f"{path}:1: material library 'my', 'lib.mtl' not found in {tmp_path} (nor 'my lib.mtl' as one name); "
        "its materials get a default grey diffuse"
    ]
    assert scene.materials == [Material("x")]


def test_texture_coordinates_the_file_does_not_define_are_dropped():
    path = DATA / "vt_undefined.obj"
    with pytest.warns(SceneWarning) as record:
        scene = read_obj(path)
    assert messages(record) == [
        f"{path}:9: texture coordinate index 1 is out of range (the file has no texture coordinate elements); "
        "dropped the texture coordinates of 2 face(s) with invalid indices, kept their triangles"
    ]
    assert len(scene.triangles) == 2 and scene.texcoords is None
    np.testing.assert_array_equal(scene.normals, [[0, 0, 1]] * len(scene.vertices))


def test_normals_the_file_does_not_define_are_dropped():
    path = DATA / "vn_undefined.obj"
    with pytest.warns(SceneWarning, match=re.escape(f"{path}:14: normal index 1 is out of range")) as record:
        scene = read_obj(path)
    assert len(record) == 1 and "dropped the normals of 1 face(s)" in messages(record)[0]
    assert len(scene.triangles) == 2 and scene.normals is None
    np.testing.assert_array_equal(scene.texcoords, [[0, 0], [1, 0], [1, 1], [0, 1]])


def test_out_of_range_attribute_indices_drop_that_attribute_of_the_whole_face():
    path = DATA / "attribute_index_out_of_range.obj"
    with pytest.warns(SceneWarning) as record:
        scene = read_obj(path)
    assert messages(record) == [
        f"{path}:20: texture coordinate index 100 is out of range (the file has 3 texture coordinate elements); "
        "dropped the texture coordinates of 1 face(s) and the normals of 1 face(s) with invalid indices, "
        "kept their triangles"
    ]
    assert len(scene.triangles) == 3
    texcoords, normals = scene.texcoords[scene.triangles], scene.normals[scene.triangles]
    assert texcoords[0].tolist() == [[0, 0], [1, 0], [0, 1]]
    assert texcoords[1].tolist() == [[0, 0]] * 3  # not vt 1 and vt 3 on the valid corners
    assert texcoords[2].tolist() == [[0, 0], [1, 0], [0, 1]]
    np.testing.assert_allclose(normals[1], [[0, 0.6, 0.8]] * 3, atol=1e-6)
    assert normals[2].tolist() == [[0, 0, 1]] * 3  # geometric, not vn 2 on the two valid corners


def test_index_zero_of_a_normal_is_dropped_with_the_reason(tmp_path):
    path = write(tmp_path / "a.obj", TRIANGLE + "vn 0 1 0\nf 1//1 2//0 3//1\n")
    with pytest.warns(SceneWarning, match=re.escape(f"{path}:5: normal index 0 is invalid (OBJ indices start at 1)")):
        scene = read_obj(path)
    assert len(scene.triangles) == 1 and scene.normals is None


# ----------------------------------------------------- files broken beyond use: refused
@pytest.mark.parametrize(
    ("file", "message"),
    [
        ("nan_vertex.obj", ":6: 'v' has a NaN or infinite value"),
        ("vertex_index_out_of_range.obj", ":11: vertex index 999999 is out of range (the file has 3 vertex"),
        ("no_faces.obj", ": the mesh has no faces"),
    ],
)
def test_broken_files_are_refused_naming_file_and_line(file, message):
    path = DATA / file
    with pytest.raises(SceneError, match=re.escape(f"{path}{message}")):
        quiet_read(path)


# ------------------------------------------------------------------------------ errors
TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"
BAD_OBJS = {
    "short vertex": (TRIANGLE + "v 1 2\nf 1 2 3\n", 4, "'v' needs 3"),
    "non-numeric vertex": (TRIANGLE + "v 1 x 2\nf 1 2 3\n", 4, "'x' is not a number"),
    "nan vertex": (TRIANGLE + "v 1 nan 2\nf 1 2 3\n", 4, "NaN or infinite"),
    "inf vertex": ("v inf 0 0\n" + TRIANGLE + "f 1 2 3\n", 1, "NaN or infinite"),
    "one-vertex face": (TRIANGLE + "f 1\n", 4, "at least 3 vertices"),
    "non-numeric face": (TRIANGLE + "f 1 2 3\nf 1 b 3\n", 5, "'b'"),
    "float face index": (TRIANGLE + "f 1 2.5 3\n", 4, "not an integer"),
    "mixed face forms": (TRIANGLE + "vn 0 0 1\nf 1//1 2//1 3//1\nf 1//1 2 3//1\n", 6, "mixes index forms"),
    "index zero": (TRIANGLE + "f 0 1 2\n", 4, "index 0"),
    "index too large": (TRIANGLE + "f 1 2 3\nf 1 2 4\n", 5, "index 4 is out of range"),
    "relative index too far": (TRIANGLE + "f -1 -2 -4\n", 4, "relative index -4"),
    "bad normal": (TRIANGLE + "vn 0 0\nf 1 2 3\n", 4, "'vn' needs 3"),
    "usemtl without name": (TRIANGLE + "usemtl\nf 1 2 3\n", 4, "'usemtl' without"),
}


@pytest.mark.parametrize("case", BAD_OBJS, ids=list(BAD_OBJS))
def test_bad_obj_raises_scene_error_with_file_and_line(tmp_path, case):
    text, line, message = BAD_OBJS[case]
    path = write(tmp_path / "bad.obj", text)
    with pytest.raises(SceneError, match=re.escape(f"{path}:{line}:") + ".*" + re.escape(message)):
        quiet_read(path)


@pytest.mark.parametrize(
    ("text", "message"),
    [("# nothing\nv 0 0 0\n", "no faces"), (TRIANGLE + "f 1 2\n", "no triangles")],
    ids=["no faces", "only 2-vertex faces"],
)
def test_empty_mesh_raises(tmp_path, text, message):
    path = write(tmp_path / "empty.obj", text)
    with pytest.raises(SceneError, match=re.escape(str(path)) + ".*" + message):
        quiet_read(path)


def test_missing_and_unreadable_files_raise(tmp_path):
    with pytest.raises(SceneError, match=re.escape(f"{tmp_path / 'none.obj'}: file not found")):
        read_obj(tmp_path / "none.obj")
    with pytest.raises(SceneError, match="is a directory"):
        read_obj(tmp_path)
    with pytest.raises(SceneError, match="unknown mesh format"):
        load_mesh(write(tmp_path / "a.stl", "solid"))


@pytest.mark.parametrize(
    ("text", "line", "message"),
    [
        ("newmtl a\nKd 1 x 1\n", 2, "'x' is not a number"),
        ("newmtl a\nKd 1 1\n", 2, "needs 1 or 3 numbers"),
        ("Kd 1 1 1\n", 1, "before the first 'newmtl'"),
        ("newmtl a\nNs\n", 2, "'Ns' needs 1 number"),
        ("newmtl a\nnewmtl a\n", 2, "defined twice"),
        ("newmtl a\nKe inf 0 0\n", 2, "not finite"),
    ],
)
def test_bad_mtl_raises_scene_error_with_file_and_line(tmp_path, text, line, message):
    path = write(tmp_path / "bad.mtl", text)
    with pytest.raises(SceneError, match=re.escape(f"{path}:{line}:") + ".*" + re.escape(message)):
        read_mtl(path)


# ------------------------------------------------------------------------------- cache
def test_cache_hit_returns_identical_arrays_and_replays_warnings(tmp_path, isolated_cache):
    write(tmp_path / "m.mtl", MTL + "Pe 3\n")
    text = "mtllib m.mtl\nvt 0 0\nvn 0 0 1\n" + TRIANGLE + "usemtl glass\nf 1/1/1 2/1/1 3/1/1 2/1/1\n"
    path = write(tmp_path / "a.obj", text)
    with pytest.warns(SceneWarning, match="'Pe'"):
        cold = load_mesh(path)
    assert len(list(cache_directory().glob("*.npz"))) == 1
    with pytest.warns(SceneWarning, match="'Pe'"):
        hot = load_mesh(path)
    for name in ("vertices", "triangles", "material_ids", "normals", "texcoords"):
        np.testing.assert_array_equal(getattr(hot, name), getattr(cold, name))
        assert getattr(hot, name).dtype == getattr(cold, name).dtype
    assert hot.materials == cold.materials and hot.name == cold.name and hot.sources == cold.sources
    assert hot.content_hash() == cold.content_hash()


def test_cache_key_follows_a_missing_mtl_file_named_with_a_space(tmp_path, isolated_cache):
    path = write(tmp_path / "a.obj", "mtllib my lib.mtl\n" + TRIANGLE + "usemtl a\nf 1 2 3\n")
    with pytest.warns(SceneWarning, match="not found"):
        assert load_mesh(path).materials == [Material("a")]
    write(tmp_path / "my lib.mtl", "newmtl a\nKd 0.7 0.7 0.7\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_mesh(path).materials[0].albedo == (0.7, 0.7, 0.7)


def test_cache_key_follows_the_mtl_file(tmp_path, isolated_cache):
    write(tmp_path / "m.mtl", "newmtl a\nKd 0.1 0.1 0.1\n")
    path = write(tmp_path / "a.obj", "mtllib m.mtl\n" + TRIANGLE + "usemtl a\nf 1 2 3\n")
    assert load_mesh(path).materials[0].albedo == (0.1, 0.1, 0.1)
    write(tmp_path / "m.mtl", "newmtl a\nKd 0.7 0.7 0.7\n")
    assert load_mesh(path).materials[0].albedo == (0.7, 0.7, 0.7)
    assert len(list(cache_directory().glob("*.npz"))) == 2
    assert not list(cache_directory().glob("*.tmp*"))


# ------------------------------------------------------------------------ command line
def test_cli_prints_each_warning_once_as_one_line_and_quiet_silences_them(tmp_path, isolated_cache, capsys):
    from kdtrace.cli import main

    obj = DATA / "several_mtllibs.obj"
    scene = write(tmp_path / "twice.toml", f'[[mesh]]\nfile = "{obj}"\n[[mesh]]\nfile = "{obj}"\n')  # 2nd: cache hit
    assert main(["build", str(scene), "--variant", "naive"]) == 0
    err = capsys.readouterr().err
    assert [line for line in err.splitlines() if "warning" in line.lower()] == [
        f"warning: {obj}:10: material library 'several_c.mtl' not found in {DATA}; "
        "its materials get a default grey diffuse",
        f"warning: {DATA / 'several_b.mtl'}:5: unknown MTL key 'Pe' ignored",
        f"warning: {obj}:21: material 'nowhere' is not defined in several_a.mtl, several_b.mtl; "
        "using a default grey diffuse material",
    ]
    assert "SceneWarning" not in err and "warnings.warn" not in err  # not Python's two-line format
    assert main(["--quiet", "build", str(scene), "--variant", "naive"]) == 0
    assert "warning" not in capsys.readouterr().err.lower()
