"""Fuzz tests of the mesh readers and scene descriptions: every input loads or is refused cleanly.

The property, for OBJ + MTL (:mod:`kdtrace.io.obj`, :mod:`kdtrace.io.mtl`), PLY
(:mod:`kdtrace.io.ply`) and scene TOMLs (:mod:`kdtrace.scenes`): every input either

* loads, and the loaded scene passes its own validation (:func:`assert_valid`), or
* raises :class:`kdtrace.io.SceneError` naming the file: ``FILE:LINE:`` for OBJ and MTL
  (except the whole-file refusals in :data:`WHOLE_FILE`), ``FILE:`` for PLY (a binary
  body has no lines; the header's errors give the line) and ``FILE:`` plus the key for
  a TOML description (or the mesh file, for an error inside a mesh),

and never raises another exception type or a warning other than a ``SceneWarning``
(NumPy's cast and overflow warnings are errors here), never runs longer than
:data:`SLOW_SECONDS` of CPU time (and a timer stops it at :data:`HANG_SECONDS`), and never
allocates more than :func:`memory_bound` bytes of traced memory (``tracemalloc`` peak,
which includes NumPy's buffers) while parsing one input.

Inputs are the shipped files damaged by :data:`tests.strategies.mutations` (the small
Cornell boxes of ``../shared/scenes``, ``tests/data/obj``, ``scenes/*.toml``, and small
PLY files written with plyfile from the Cornell box), files from the OBJ and PLY
grammars of :mod:`tests.strategies`, and structured edits of the TOML descriptions.

Example counts: :data:`tests.strategies.FUZZ_DEFAULT_EXAMPLES` per property in the
default run (the whole file takes about 20 s on 2 cores); ``KDTRACE_FUZZ_EXAMPLES=N``
runs ``N`` per property, with a fresh random seed each run (see ``docs/testing.md``).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import re
import shutil
import signal
import sys
import tempfile
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st
from plyfile import PlyData, PlyElement

from kdtrace.io import SceneError, SceneWarning
from kdtrace.io.obj import read_obj
from kdtrace.io.ply import read_ply
from kdtrace.scene import Scene
from kdtrace.scenes import SCENES_DIRECTORY, SHARED_SCENES_DIRECTORY, load_scene
from tests.strategies import GRAMMAR_MTL, ODD_NUMBERS, fuzz, mutate, mutations, obj_files, ply_files, reencode

#: Hard bound on the CPU seconds of one parse: longer is a hang (stopped by a CPU-time timer).
HANG_SECONDS = 20.0
#: CPU seconds one parse may take and still pass: a reader slower than this on a small input is
#: a defect (quadratic parsing and the like). CPU time, not wall-clock time: a parse on a busy
#: machine waits for a core without being slower.
SLOW_SECONDS = 5.0
#: Memory bound of one parse: this much plus :data:`MEMORY_PER_BYTE` per input byte.
MEMORY_BASE = 16 * 2**20
MEMORY_PER_BYTE = 200
#: Refusals of a whole OBJ file, which name the file but no line.
WHOLE_FILE = ("the mesh has no faces", "the mesh has no triangles")

def memory_bound(size: int) -> int:
    """Bytes of traced memory one parse of a ``size``-byte input may peak at."""
    return MEMORY_BASE + MEMORY_PER_BYTE * size


class Hang(AssertionError):
    """The reader did not answer within :data:`HANG_SECONDS` of CPU time (a failure hypothesis reports with its input)."""


def bounded(load, size: int, scene_warnings: str = "ignore"):
    """``load()`` under the time and memory bounds: the scene, or the :class:`SceneError` it raised.

    Any other exception, and any warning but a ``SceneWarning``, propagates; a
    ``SceneWarning`` is handled by the ``scene_warnings`` filter action.
    """
    def alarm(signum, frame):
        raise Hang(f"no answer within {HANG_SECONDS} s of CPU time")

    previous = signal.signal(signal.SIGPROF, alarm)
    signal.setitimer(signal.ITIMER_PROF, HANG_SECONDS)  # counts this process's CPU time only
    tracemalloc.start()
    started = time.process_time()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            warnings.simplefilter(scene_warnings, SceneWarning)
            try:
                result = load()
            except SceneError as error:
                result = error
        seconds = time.process_time() - started
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, previous)
    assert peak <= memory_bound(size), f"a {size}-byte input peaked at {peak / 2**20:.1f} MiB"
    assert seconds <= SLOW_SECONDS, f"a {size}-byte input took {seconds:.1f} s of CPU time"
    return result


def assert_valid(scene: Scene) -> None:
    """The loaded scene passes its own validation, and its materials and normals are usable."""
    dataclasses.replace(scene)  # Scene.__post_init__: shapes, finiteness, index ranges
    assert scene.vertices.dtype == np.float32 and scene.triangles.dtype == np.int32
    if scene.normals is not None:
        np.testing.assert_allclose(np.linalg.norm(scene.normals, axis=1), 1.0, atol=1e-3)
    for material in scene.materials:
        assert material.kind in ("diffuse", "mirror", "dielectric"), material
        assert all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in material.albedo), material
        assert all(math.isfinite(c) and c >= 0.0 for c in material.emission), material
        assert math.isfinite(material.ior) and material.ior > 0.0, material
    for camera in scene.cameras:
        dataclasses.replace(camera)
        assert all(math.isfinite(c) for c in (*camera.position, *camera.look_at, *camera.up)), camera


def assert_names_file(error: SceneError, paths: list[Path], line: bool) -> None:
    """The message starts with one of ``paths``, and with ``PATH:LINE:`` when ``line`` (but :data:`WHOLE_FILE`)."""
    message = str(error)
    assert any(message.startswith(f"{path}:") for path in paths), message
    if line and not any(text in message for text in WHOLE_FILE):
        assert any(re.match(re.escape(str(path)) + r":\d+: ", message) for path in paths), message


def check(load, path: Path, size: int, line: bool, others: tuple[Path, ...] = ()):
    """Run the property on one input: load it or get a clean refusal (see the module docstring)."""
    result = bounded(load, size)
    if isinstance(result, SceneError):
        event("refused")
        assert_names_file(result, [path, *others], line)
    else:
        event("loaded")
        assert_valid(result)
    return result


@pytest.fixture(scope="module", autouse=True)
def private_cache(tmp_path_factory):
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("KDTRACE_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def _fresh_folder(workspace: Path, files: dict[str, bytes]) -> Path:
    folder = Path(tempfile.mkdtemp(dir=workspace))
    for name, content in files.items():
        (folder / name).write_bytes(content)
    return folder


# ---------------------------------------------------------------------------------- seeds
DATA = Path(__file__).parent / "data" / "obj"
CORNELL = SHARED_SCENES_DIRECTORY / "cornell-box"


def _obj_seeds() -> list[tuple[str, dict[str, bytes]]]:
    """(OBJ file name, files of its folder): the small Cornell boxes and every ``tests/data/obj`` file."""
    seeds = []
    for stem in ("CornellBox-Original", "CornellBox-Mirror", "CornellBox-Empty-RG"):
        if (CORNELL / f"{stem}.obj").is_file():
            seeds.append((f"{stem}.obj", {p.name: p.read_bytes() for p in CORNELL.glob(f"{stem}.*")}))
    if (CORNELL / "CornellBox-Original.obj").is_file():  # the sphere box's MTL (dielectric, mirror) under the small box
        obj = (CORNELL / "CornellBox-Original.obj").read_bytes().replace(b"CornellBox-Original.mtl", b"CornellBox-Sphere.mtl")
        seeds.append(("spheres.obj", {"spheres.obj": obj, "CornellBox-Sphere.mtl": (CORNELL / "CornellBox-Sphere.mtl").read_bytes()}))
    folder = {p.name: p.read_bytes() for p in DATA.iterdir() if p.is_file()}
    seeds += [(name, folder) for name in sorted(folder) if name.endswith(".obj")]
    return seeds


OBJ_SEEDS = _obj_seeds()


def _ply_seeds() -> list[bytes]:
    """The Cornell box (or a small soup) as PLY in the three formats, written by plyfile."""
    if (CORNELL / "CornellBox-Original.obj").is_file():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SceneWarning)
            scene = read_obj(CORNELL / "CornellBox-Original.obj")
    else:
        from kdtrace.procedural import random_soup

        scene = random_soup(20, seed=1)
    vertex = np.zeros(len(scene.vertices), [("x", "f4"), ("y", "f4"), ("z", "f4"), ("nx", "f4"), ("ny", "f4"), ("nz", "f4"),
                                              ("u", "f4"), ("v", "f4")])
    for k, axis in enumerate("xyz"):
        vertex[axis] = scene.vertices[:, k]
    vertex["nz"], vertex["u"], vertex["v"] = 1.0, scene.vertices[:, 0], scene.vertices[:, 1]
    face = np.zeros(len(scene.triangles), [("vertex_indices", "i4", (3,)), ("material_id", "i4")])
    face["vertex_indices"], face["material_id"] = scene.triangles, scene.material_ids
    seeds = []
    for text, order in ((True, "="), (False, "<"), (False, ">")):
        ply = PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")], text=text, byte_order=order)
        with tempfile.TemporaryFile() as handle:
            ply.write(handle)
            handle.seek(0)
            seeds.append(handle.read())
    return seeds


PLY_SEEDS = _ply_seeds()
TOML_SEEDS = {p.name: p.read_bytes() for p in sorted(SCENES_DIRECTORY.glob("*.toml"))}
#: Meshes this small are used as they are by the TOML tests; larger ones get a stub.
STUB_ABOVE_BYTES = 10_000


@pytest.fixture(scope="module")
def mesh_stubs(tmp_path_factory) -> Path:
    """A folder with every mesh the shipped descriptions name: small Cornell boxes as they are, stubs for the rest.

    A stub is one triangle per material name any description's ``[materials]`` overrides,
    so the overrides find their material.
    """
    folder = tmp_path_factory.mktemp("meshes")
    names = sorted({name for data in TOML_SEEDS.values() for name in tomllib_loads(data).get("materials", {})})
    for data in TOML_SEEDS.values():
        for mesh in tomllib_loads(data)["mesh"]:
            target = folder / mesh["file"]
            target.parent.mkdir(parents=True, exist_ok=True)
            real = SHARED_SCENES_DIRECTORY / mesh["file"]
            if real.is_file() and real.stat().st_size <= STUB_ABOVE_BYTES:
                for sibling in real.parent.glob(real.stem + ".*"):
                    shutil.copy(sibling, target.parent / sibling.name)
            elif target.suffix == ".ply":
                target.write_bytes(PLY_SEEDS[1])
            else:
                lines = ["v 0 0 0", "v 1 0 0", "v 0 1 0"] + [f"usemtl {name}\nf 1 2 3" for name in ["default", *names]]
                target.write_text("\n".join(lines) + "\n")
    return folder


def tomllib_loads(data: bytes) -> dict:
    import tomllib

    return tomllib.loads(data.decode())


def test_the_bounds_stop_a_hang_and_fail_a_slow_parse_but_not_a_wait(monkeypatch):
    """The guards of every fuzz example can fail: a parse that spins is stopped, one that computes
    too long fails, and one that only waits (a busy machine) passes."""
    monkeypatch.setattr(sys.modules[__name__], "HANG_SECONDS", 0.2)
    with pytest.raises(Hang, match="CPU time"):
        bounded(lambda: [i for i in range(10**12)], 10)
    monkeypatch.setattr(sys.modules[__name__], "HANG_SECONDS", 20.0)
    monkeypatch.setattr(sys.modules[__name__], "SLOW_SECONDS", 0.05)
    with pytest.raises(AssertionError, match="s of CPU time"):
        bounded(lambda: sum(range(10**6)), 10)
    assert bounded(lambda: time.sleep(0.3) or "waited", 10) == "waited"


# ------------------------------------------------------------------------------- OBJ + MTL
@fuzz()
@given(seed=st.integers(0, len(OBJ_SEEDS) - 1), target=st.integers(0, 7), damage=mutations)
def test_mutated_obj_and_mtl_load_or_are_refused_naming_file_and_line(workspace, seed, target, damage):
    name, files = OBJ_SEEDS[seed]
    text_files = sorted(n for n in files if n == name or n.endswith(".mtl"))
    chosen = text_files[target % len(text_files)] if target < 4 else name  # the OBJ half the time
    files = {**files, chosen: mutate(files[chosen], damage)}
    folder = _fresh_folder(workspace, files)
    try:
        others = tuple(folder / n for n in files if n.endswith(".mtl"))
        check(lambda: read_obj(folder / name), folder / name, sum(map(len, files.values())), line=True, others=others)
    finally:
        shutil.rmtree(folder)


@fuzz()
@given(data=obj_files())
def test_obj_grammar_loads_or_is_refused_naming_file_and_line(workspace, data):
    folder = _fresh_folder(workspace, {"a.obj": data, "lib.mtl": GRAMMAR_MTL})
    try:
        check(lambda: read_obj(folder / "a.obj"), folder / "a.obj", len(data), line=True, others=(folder / "lib.mtl",))
    finally:
        shutil.rmtree(folder)


@pytest.mark.parametrize("encoding", ["crlf", "cr", "utf-8-sig", "utf-16", "latin-1"])
@pytest.mark.parametrize("seed", range(len(OBJ_SEEDS)), ids=[name for name, _ in OBJ_SEEDS])
def test_obj_and_mtl_read_alike_in_every_line_end_and_encoding(workspace, seed, encoding):
    """Line ends, a byte order mark (UTF-8 or UTF-16) or Latin-1 text change nothing but the bytes.

    A seed refused as it is must be refused in every encoding too, for the same reason.
    """
    name, files = OBJ_SEEDS[seed]
    encoded = {n: (reencode(d, encoding) if n.endswith((".obj", ".mtl")) and encoding != "latin-1"
                   else d.decode("utf-8").encode("latin-1") if encoding == "latin-1" else d) for n, d in files.items()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SceneWarning)
        try:
            plain = read_obj(_fresh_folder(workspace, files) / name)
        except SceneError as refused:
            with pytest.raises(SceneError) as again:
                read_obj(_fresh_folder(workspace, encoded) / name)
            assert _reason(again.value) == _reason(refused)
            return
        scene = read_obj(_fresh_folder(workspace, encoded) / name)
    np.testing.assert_array_equal(scene.vertices, plain.vertices)
    np.testing.assert_array_equal(scene.triangles, plain.triangles)
    assert scene.materials == plain.materials and np.array_equal(scene.material_ids, plain.material_ids)


def _reason(error: SceneError) -> str:
    """An error's message without its FILE:LINE prefix (the folder differs between two reads)."""
    return str(error).split(": ", 1)[-1]


# ------------------------------------------------------------------------------------ PLY
@fuzz()
@given(seed=st.integers(0, len(PLY_SEEDS) - 1), damage=mutations)
def test_mutated_ply_loads_or_is_refused_naming_the_file(workspace, seed, damage):
    data = mutate(PLY_SEEDS[seed], damage)
    folder = _fresh_folder(workspace, {"a.ply": data})
    try:
        check(lambda: read_ply(folder / "a.ply"), folder / "a.ply", len(data), line=False)
    finally:
        shutil.rmtree(folder)


@fuzz()
@given(data=ply_files())
def test_ply_grammar_loads_or_is_refused_naming_the_file(workspace, data):
    folder = _fresh_folder(workspace, {"a.ply": data})
    try:
        check(lambda: read_ply(folder / "a.ply"), folder / "a.ply", len(data), line=False)
    finally:
        shutil.rmtree(folder)


# ----------------------------------------------------------------------------------- TOML
def _dump_toml(value, key: str | None = None) -> str:
    """TOML text of a dict (top level: ``key = value`` lines; below: inline tables and arrays)."""
    if key is None:
        return "".join(f"{json.dumps(k)} = {_dump_toml(v, k)}\n" for k, v in value.items())
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if value != value else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_dump_toml(v, key) for v in value) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {_dump_toml(v, k)}" for k, v in value.items()) + "}"


_toml_values = st.deferred(lambda: st.one_of(
    st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 1e-320, 0, -1, 0.0, 2**63 - 1, -(2**63),
                     1e38, 4e9, True, "", "x", "nan", "\u00e9", "../../etc", "cornell-box/CornellBox-Original.obj"]),
    st.floats(), st.integers(-10, 10), st.text(max_size=5),
    st.lists(st.sampled_from([0, 1, -1, float("nan"), 1e308, "a"]), max_size=5),
    st.just({}), st.just([]), st.just([[]]), st.just({"axis": [0, 1, 0]}),
).map(copy.deepcopy))  # edits change the drawn tables in place


def _leaves(value, path=()):
    yield path
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _leaves(v, (*path, i))


@st.composite
def toml_edits(draw) -> bytes:
    """A shipped description with a few values replaced, keys added, or deep nesting (as TOML text)."""
    description = tomllib_loads(draw(st.sampled_from(sorted(TOML_SEEDS.values()))))
    for _ in range(draw(st.integers(1, 3))):
        paths = [p for p in _leaves(description) if p]
        if not paths:
            break
        kind = draw(st.sampled_from(["replace", "replace", "replace", "add", "delete", "nest", "transform", "override"]))
        meshes = [m for m in description.get("mesh", []) if isinstance(m, dict)] if isinstance(description.get("mesh"), list) else []
        if kind in ("transform", "override") and not meshes:
            continue
        if kind == "transform":  # the parts where numbers meet arithmetic
            mesh = draw(st.sampled_from(meshes))
            mesh["transform"] = {key: draw(st.one_of(_toml_values, st.lists(_toml_values, min_size=3, max_size=3)))
                                 for key in draw(st.lists(st.sampled_from(["scale", "translate"]), max_size=2, unique=True))}
            if draw(st.booleans()):
                axis = draw(st.lists(st.one_of(st.integers(-1, 1), _toml_values), min_size=3, max_size=3))
                mesh["transform"]["rotate"] = draw(st.sampled_from([{"axis": axis, "degrees": draw(_toml_values)},
                                                                    {"euler": axis}]))
            continue
        if kind == "override":
            name = draw(st.sampled_from(["light", "dragon", "default", "x"]))
            if not isinstance(description.setdefault("materials", {}), dict):
                continue
            description["materials"][name] = {key: draw(_toml_values) for key in draw(
                st.lists(st.sampled_from(["kind", "albedo", "emission", "ior"]), max_size=3, unique=True))}
            draw(st.sampled_from(meshes))["material_override"] = draw(st.sampled_from([name, [name], 3]))
            continue
        path = draw(st.sampled_from(paths))
        parent = description
        for step in path[:-1]:
            parent = parent[step]
        if kind == "replace":
            parent[path[-1]] = draw(_toml_values)
        elif kind == "delete":
            del parent[path[-1]]
        elif kind == "add" and isinstance(parent, dict):
            parent[draw(st.sampled_from(["colour", "file", "transform", "rotate", "scale", "euler", "degrees", "fov",
                                         "width", "material_override", "ior", "kind", "emission"]))] = draw(_toml_values)
        elif kind == "nest":
            depth = draw(st.sampled_from([2, 10, 100, 1000, 5000]))
            nested: object = 1
            for _ in range(min(depth, 50)):
                nested = [nested]
            parent[path[-1]] = nested
            if depth > 50:
                return (_dump_toml(description) + "deep = " + "[" * depth + "]" * depth + "\n").encode()
    return _dump_toml(description).encode()


def _check_toml(workspace: Path, mesh_stubs: Path, data: bytes) -> None:
    folder = _fresh_folder(workspace, {"scene.toml": data})
    path = folder / "scene.toml"
    try:
        result = bounded(lambda: load_scene(path, search_path=[mesh_stubs], use_cache=False), len(data))
        event("refused" if isinstance(result, SceneError) else "loaded")
        if isinstance(result, SceneError):
            message = str(result)
            names_mesh = str(mesh_stubs) in message.split(":", 1)[0] or "file not found; looked in:" in message
            assert message.startswith((f"{path}:", f"{path} [[")) or names_mesh, message  # FILE: or FILE [[table]] N:
        else:
            assert_valid(result)
    finally:
        shutil.rmtree(folder)


_deep_nesting = st.sampled_from([100, 1000, 5000]).map(lambda n: ("insert", 0, b"x = " + b"[" * n + b"]" * n + b"\n"))


@fuzz()
@given(seed=st.sampled_from(sorted(TOML_SEEDS)), damage=st.one_of(mutations, st.tuples(_deep_nesting).map(list)))
def test_mutated_scene_description_loads_or_is_refused_naming_the_file(workspace, mesh_stubs, seed, damage):
    _check_toml(workspace, mesh_stubs, mutate(TOML_SEEDS[seed], damage))


@fuzz()
@given(data=toml_edits())
def test_edited_scene_description_loads_or_is_refused_naming_the_file(workspace, mesh_stubs, data):
    _check_toml(workspace, mesh_stubs, data)


def test_odd_numbers_cover_the_integer_limits():
    """The mutations reach past int32, uint32 and int64 both ways (what overflowed readers before)."""
    values = {int(token) for token in ODD_NUMBERS if re.fullmatch(rb"[-+]?\d+", token)}
    assert {2**31, -(2**31) - 1, 2**32, 2**63, -(2**63) - 1} <= values


# ------------------------------------------------------------ regressions: what the fuzzing found
TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"


def assert_refused(result, pattern: str) -> None:
    """``result`` (of :func:`bounded`) is a :class:`SceneError` whose message matches ``pattern``."""
    assert isinstance(result, SceneError), result
    assert re.match(pattern, str(result)), str(result)
PLY_HEAD = b"ply\nformat binary_little_endian 1.0\ncomment fuzz\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
ASCII_TRIANGLE = (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                  b"element face 1\nproperty list uchar int vertex_indices\nproperty int material_id\nend_header\n"
                  b"0 0 0\n1 0 0\n0 1 0\n")


@pytest.mark.parametrize(("text", "message"), [
    ("v 0.0 0.0 0.0\nf 0 9223372036854775808", ":2: vertex index 0 is invalid"),  # OverflowError before
    (TRIANGLE + "f 1 2 99999999999999999999\n", ":4: vertex index 9223372036854775807 is out of range"),
    (TRIANGLE + "v 1e39 0 0\nf 1 2 3\n", ":4: 'v' has a value beyond the float32 range"),  # a cast warning and ValueError before
    (TRIANGLE + "vt 0 1e39\nf 1/1 2/1 3/1\n", ":4: 'vt' has a value beyond the float32 range"),
], ids=["index beyond int64", "index beyond int64, in range of nothing", "v beyond float32", "vt beyond float32"])
def test_regression_obj_numbers_beyond_int64_and_float32_are_refused_naming_the_line(tmp_path, text, message):
    path = tmp_path / "a.obj"
    path.write_text(text)
    assert_refused(bounded(lambda: read_obj(path), len(text)), re.escape(f"{path}{message}"))


def test_regression_obj_lenient_cases_load(tmp_path):
    """A vt index beyond int64 drops the face's texture coordinates; huge normals are normalised; a
    ``mtllib`` name too long for the file system is a missing library (OSError before)."""
    (tmp_path / "a.obj").write_text(TRIANGLE + "vt 0 0\nvn 1e300 1e300 0\nf 1/99999999999999999999 2/1 3/1\nf 1//1 2//1 3//1\n")
    (tmp_path / "b.obj").write_text("mtllib " + "mtllib " * 60 + "x.mtl\n" + TRIANGLE + "usemtl a\nf 1 2 3\n")
    with pytest.warns(SceneWarning) as record:
        scene = bounded(lambda: read_obj(tmp_path / "a.obj"), 200, "always")
        assert_valid(scene)
        assert_valid(bounded(lambda: read_obj(tmp_path / "b.obj"), 600, "always"))
    np.testing.assert_allclose(scene.normals[scene.triangles[1]], [[2**-0.5, 2**-0.5, 0]] * 3, rtol=1e-6)
    assert any("texture coordinate index 9223372036854775807 is out of range" in str(w.message) for w in record)
    assert any("not found" in str(w.message) for w in record)


@pytest.mark.parametrize("bom", [b"\xef\xbb\xbf", b"\xff\xfe"], ids=["utf-8", "utf-16"])
def test_regression_byte_order_marks_are_read_not_taken_for_a_keyword(tmp_path, bom):
    """``'\\ufeff' before the first 'newmtl'`` before; the OBJ lost its first line."""
    def encoded(text: str) -> bytes:
        return bom + text.encode("utf-16-le" if bom == b"\xff\xfe" else "utf-8")
    (tmp_path / "m.mtl").write_bytes(encoded("newmtl lamp\nKe 1 1 1\n"))
    (tmp_path / "a.obj").write_bytes(encoded("v 0 0 0\nmtllib m.mtl\nv 1 0 0\nv 0 1 0\nusemtl lamp\nf 1 2 3\n"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = read_obj(tmp_path / "a.obj")
    assert scene.vertices.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0]] and scene.materials[0].emission == (1.0, 1.0, 1.0)


@pytest.mark.parametrize(("data", "message"), [
    (PLY_HEAD + b"element face 4000000000\nproperty list int int vertex_indices\nend_header\n\x00\x00\x00\x00\xff\xff\xff\xff\x00",
     "record 1: list 'vertex_indices' has length -1"),  # ValueError: zero-size array before
    (PLY_HEAD + b"element face 1\nproperty list int int vertex_indices\nend_header\n\x00\x00\x00 ",
     "file ends inside element 'face'"),  # ValueError: dtype size must fit into a C int before
    (PLY_HEAD + b"element face 1\nproperty list int int vertex_indices\nend_header\n\xff\xff\xff\xff\x00\x00\x00\x00",
     "list 'vertex_indices' has length -1"),  # read the rest of the file as the list before
    (PLY_HEAD + b"element face 1\nproperty list uchar int vertex_indices\nend_header\n\x00", "face 0 has 0 vertices"),
    (PLY_HEAD + b"property float x\nelement face 0\nend_header\n", ":8: property 'x' appears twice"),
    (PLY_HEAD + b"element vertex 1\nend_header\n", ":8: element 'vertex' appears twice"),  # the second silently won
    (ASCII_TRIANGLE + b"3 0 1 2 nan\n", ":14: 'face' property 'material_id' value 'nan' is not an integer"),
    (ASCII_TRIANGLE.replace(b"uchar int vertex", b"uchar float vertex") + b"3 0 nan 2 0\n", "face 0 has vertex index nan"),
    (ASCII_TRIANGLE.replace(b"uchar int vertex", b"uchar float vertex") + b"3 0 1 1e+39 0\n", "face 0 has vertex index inf"),
    (ASCII_TRIANGLE.replace(b"int material_id", b"float material_id") + b"3 0 1 2 0.5\n", "material_id 0.5, not a whole number"),
    (ASCII_TRIANGLE.replace(b"float x", b"double x").replace(b"\n1 0 0", b"\n1e300 0 0") + b"3 0 1 2 0\n",
     "vertex 1 has a NaN, infinite or beyond-float32 coordinate"),
], ids=["zero corners, huge count", "list length beyond the file", "negative list length", "zero corners", "property twice",
        "element twice", "nan material id", "nan float index", "float index beyond float32", "fractional material id",
        "double beyond float32"])
def test_regression_ply_inputs_are_refused_naming_the_file(tmp_path, data, message):
    path = tmp_path / "a.ply"
    path.write_bytes(data)
    assert_refused(bounded(lambda: read_ply(path), len(data)), re.escape(str(path)) + ".*" + re.escape(message))


def test_regression_ply_huge_material_id_loads_without_a_huge_table(tmp_path):
    """``material_id 2000000000`` on one face made two billion materials (a hang, then out of memory)."""
    path = tmp_path / "a.ply"
    path.write_bytes(ASCII_TRIANGLE + b"3 0 1 2 2000000000\n")
    with pytest.warns(SceneWarning, match="material ids up to 2000000000 on 1 faces; the 1 ids in use get materials 0..0"):
        scene = bounded(lambda: read_ply(path), len(path.read_bytes()), "always")
    assert [m.name for m in scene.materials] == ["material_2000000000"] and scene.material_ids.tolist() == [0]


@pytest.mark.parametrize("file_format", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("element", ["vertex", "face", "edge"])
def test_enormous_element_counts_are_refused_before_allocating(tmp_path, file_format, element):
    """``element vertex 4000000000`` in a small file: refused within :func:`memory_bound` of its size."""
    properties = {"vertex": "property float x\nproperty float y\nproperty float z\n",
                  "face": "property list uchar int vertex_indices\n", "edge": "property int a\n"}
    header = [f"ply\nformat {file_format} 1.0\n"]
    for name in ("vertex", "face", "edge"):
        header.append(f"element {name} {4000000000 if name == element else 1}\n{properties[name]}")
    body = b"0 0 0\n3 0 0 0\n1\n" if file_format == "ascii" else b"\x00" * 12 + b"\x03" + b"\x00" * 12 + b"\x00" * 4
    path = tmp_path / "huge.ply"
    path.write_bytes("".join(header).encode() + b"end_header\n" + body * 3)
    result = bounded(lambda: read_ply(path), len(path.read_bytes()))
    assert isinstance(result, SceneError) and str(result).startswith(f"{path}:"), result


@pytest.mark.parametrize(("text", "message"), [
    ("x = " + "[" * 5000 + "]" * 5000 + "\n", ": invalid TOML (arrays or tables nested too deeply)"),  # RecursionError before
    ('description = "caf\xe9"\n', ":1: invalid TOML (not UTF-8"),  # UnicodeDecodeError before
    ('[[mesh]]\nfile = "tri.obj"\ntransform = { scale = 1e308 }\n', " [[mesh]] 0: transform.scale must be finite"),
    ('[[mesh]]\nfile = "tri.obj"\ntransform = { scale = 3e38, translate = [3e38, 0, 0] }\n',
     " [[mesh]] 0: transform moves vertices beyond the float32 range"),  # ValueError from Scene before
    ('[[mesh]]\nfile = "tri.obj"\ntransform = { rotate = { axis = [0, 1, 0], degrees = [1] } }\n',
     " [[mesh]] 0: rotate.degrees must be a finite number, got [1]"),  # TypeError before
    ('[[mesh]]\nfile = "tri.obj"\ntransform = { rotate = { axis = [0, 1, 0], degrees = "x" } }\n', "degrees must be a finite number"),
    ('[[mesh]]\nfile = "tri.obj"\ntransform = { rotate = { axis = [0, 1, 0], degrees = nan } }\n', "degrees must be a finite number"),
    ('[[mesh]]\nfile = "tri.obj"\ntransform = { rotate = { axis = [1e308, 1e308, 0], degrees = 3 } }\n',
     "rotate.axis must be finite"),  # an overflow, then no rotation at all, before
    ('[[mesh]]\nfile = "tri.obj"\nmaterial_override = [1]\n', ": [[mesh]] 0 material_override [1] is not defined"),  # TypeError
    ('[[mesh]]\nfile = "tri.obj"\n[materials.default]\nkind = "dielectric"\nior = inf\n', "ior must be a positive finite number"),
    ('[[mesh]]\nfile = "' + "a" * 300 + '.obj"\n', "file not found; looked in"),  # OSError: file name too long before
], ids=["deep nesting", "latin-1", "huge scale", "beyond float32", "degrees list", "degrees string", "degrees nan", "huge axis",
        "override list", "infinite ior", "long file name"])
def test_regression_scene_descriptions_are_refused_naming_file_and_key(tmp_path, text, message):
    (tmp_path / "tri.obj").write_text(TRIANGLE + "vn 0 0 1\nf 1//1 2//1 3//1\n")
    path = tmp_path / "scene.toml"
    path.write_bytes(text.encode("latin-1"))
    result = bounded(lambda: load_scene(path, use_cache=False), len(text))
    assert isinstance(result, SceneError), result
    assert message in str(result) and (str(result).startswith(str(path)) or "a" * 300 in str(result)), result


def test_regression_scene_description_with_a_byte_order_mark_loads(tmp_path):
    (tmp_path / "tri.obj").write_text(TRIANGLE + "f 1 2 3\n")
    path = tmp_path / "scene.toml"
    path.write_bytes(b'\xef\xbb\xbf[[mesh]]\nfile = "tri.obj"\ntransform = { scale = 1e-30 }\n')
    assert_valid(bounded(lambda: load_scene(path, use_cache=False), 60))
