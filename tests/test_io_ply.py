"""PLY reader: the Crytek Sponza against plyfile and its side-car, small files of every format, errors."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from kdtrace.io import SceneError, SceneWarning, load_mesh
from kdtrace.io.ply import read_ply

SPONZA = "crytek-sponza/sponza.ply"


def test_crytek_sponza_matches_plyfile_and_its_material_sidecar(shared_scenes):
    scene = read_ply(shared_scenes / SPONZA)
    reference = PlyData.read(str(shared_scenes / SPONZA))  # independent reader
    vertex, face = reference["vertex"], reference["face"]
    assert len(scene.triangles) == 262_267
    np.testing.assert_array_equal(scene.vertices, np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1))
    np.testing.assert_array_equal(scene.triangles, np.stack(face["vertex_indices"]))
    np.testing.assert_array_equal(scene.texcoords, np.stack([vertex["s"], vertex["t"]], axis=1))
    np.testing.assert_array_equal(scene.material_ids, face["material_id"])
    assert scene.material_ids.min() == 0 and scene.material_ids.max() == 24
    assert int(scene.degenerate_mask().sum()) == 428
    assert np.allclose(np.linalg.norm(scene.normals, axis=1), 1.0, atol=1e-6)

    entries = json.loads((shared_scenes / "crytek-sponza/sponza_materials.json").read_text())
    counts = np.bincount(scene.material_ids, minlength=25)
    for entry in entries:
        assert counts[entry["id"]] == entry["triangles"], entry["name"]
        material = scene.materials[entry["id"]]
        assert material.name == entry["name"] and material.kind == "diffuse"
        assert material.albedo == tuple(entry.get("mean_texture_linear_rgb") or entry["mtl_Kd"])  # id 24 has no texture


VERTICES = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32)
FACES = [[0, 1, 2, 3], [0, 1, 4]]  # a quad and a triangle


def write_ply(path: Path, fmt: str, faces=FACES, vertices=VERTICES, extra_header: str = "") -> Path:
    """A PLY with x y z nx ny nz u v per vertex, vertex_indices + material_id per face (3, 1, 1, ...)."""
    materials = [3] + [1] * (len(faces) - 1)
    header = (
        f"ply\nformat {fmt} 1.0\ncomment test\nelement vertex {len(vertices)}\n"
        + "".join(f"property float {p}\n" for p in ("x", "y", "z", "nx", "ny", "nz", "u", "v"))
        + f"element face {len(faces)}\nproperty list uchar int vertex_indices\nproperty int material_id\n"
        + extra_header
        + "end_header\n"
    )
    rows = [(*v, 0.0, 0.0, 2.0, v[0], v[1]) for v in vertices]
    if fmt == "ascii":
        body = "".join(" ".join(f"{x:g}" for x in row) + "\n" for row in rows)
        body += "".join(f"{len(f)} {' '.join(map(str, f))} {m}\n" for f, m in zip(faces, materials, strict=True))
        path.write_bytes((header + body).encode())
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        body = b"".join(struct.pack(order + "8f", *row) for row in rows)
        body += b"".join(struct.pack(f"{order}B{len(f)}ii", len(f), *f, m) for f, m in zip(faces, materials, strict=True))
        path.write_bytes(header.encode() + body)
    return path


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_small_ply_in_every_format(tmp_path, fmt):
    scene = read_ply(write_ply(tmp_path / "small.ply", fmt))
    np.testing.assert_array_equal(scene.vertices, VERTICES)
    assert scene.triangles.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]
    assert scene.material_ids.tolist() == [3, 3, 1]
    assert [m.name for m in scene.materials] == [f"material_{k}" for k in range(4)]
    assert scene.normals.tolist() == [[0, 0, 1]] * 5  # (0, 0, 2) normalised
    np.testing.assert_array_equal(scene.texcoords, VERTICES[:, :2])


def test_binary_all_triangles_fast_path_equals_ascii(tmp_path):
    faces = [[0, 1, 2], [0, 2, 3], [0, 1, 4]]
    binary = read_ply(write_ply(tmp_path / "b.ply", "binary_little_endian", faces))
    text = read_ply(write_ply(tmp_path / "a.ply", "ascii", faces))
    np.testing.assert_array_equal(binary.triangles, text.triangles)
    np.testing.assert_array_equal(binary.vertices, text.vertices)
    np.testing.assert_array_equal(binary.material_ids, [3, 1, 1])


def test_extra_elements_are_skipped_with_a_warning(tmp_path):
    path = write_ply(tmp_path / "e.ply", "ascii", extra_header="element edge 0\nproperty int vertex1\n")
    with pytest.warns(SceneWarning, match="element 'edge' ignored"):
        assert len(read_ply(path).triangles) == 3


def test_cached_ply_is_identical(shared_scenes, isolated_cache):
    cold = load_mesh(shared_scenes / SPONZA)
    hot = load_mesh(shared_scenes / SPONZA)
    assert hot.content_hash() == cold.content_hash() and hot.materials == cold.materials


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p.write_bytes(b"solid nothing\n"), "not a PLY file"),
        (lambda p: p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\n"
                                 b"property float x\nproperty float y\nproperty float z\nend_header\n"), "no 'face' element"),
        (lambda p: p.write_bytes(b"ply\nformat binary_middle_endian 1.0\nend_header\n"), ":2: unsupported PLY format"),
        (lambda p: p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n"), ":4: malformed property"),
        (lambda p: write_ply(p, "ascii", faces=[[0, 1, 9], [0, 1, 4]]), "face 0 has vertex index 9 outside 0..4"),
        (lambda p: write_ply(p, "binary_little_endian", faces=[[0, 1, -1], [0, 1, 4]]), "vertex index -1"),
        (lambda p: write_ply(p, "ascii", faces=[[0, 1], [0, 1, 4]]), "face 0 has 2 vertices"),
        (lambda p: write_ply(p, "ascii", vertices=VERTICES * np.float32(np.nan)), "vertex 0 has a NaN"),
        (lambda p: p.write_bytes(write_ply(p, "binary_little_endian").read_bytes()[:-5]), "file ends inside element 'face'"),
        (lambda p: p.write_bytes(write_ply(p, "ascii").read_bytes().replace(b"\n1 1 0 ", b"\n1 x 0 ")), "non-numeric 'vertex'"),
        (lambda p: p.write_bytes(write_ply(p, "ascii").read_bytes()[:-8]), "malformed 'face' record"),
    ],
    ids=["magic", "no faces", "format", "property type", "index", "negative index", "short face", "nan", "truncated", "non-numeric",
         "short record"],
)
def test_bad_ply_raises_scene_error_naming_the_file(tmp_path, make, message):
    path = tmp_path / "bad.ply"
    make(path)
    with pytest.raises(SceneError, match=re.escape(str(path)) + ".*" + re.escape(message)):
        read_ply(path)


def test_sidecar_missing_an_id_is_an_error(tmp_path):
    path = write_ply(tmp_path / "s.ply", "ascii")
    (tmp_path / "s_materials.json").write_text(json.dumps([{"id": 1, "name": "a", "mtl_Kd": [0.5, 0.5, 0.5]}]))
    with pytest.raises(SceneError, match=r"s_materials\.json: no entry for material id\(s\) \[0, 2, 3\]"):
        read_ply(path)
