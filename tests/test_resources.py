"""Memory refused before allocation: renders, KD-tree builds, dataset views and training crops name
the bytes they need and the bytes available; what the shipped profiles ask for passes."""

from __future__ import annotations

import pytest
from test_mitsuba import cornell_like

from kdtrace import resources
from kdtrace.config import DEFAULT_CONFIG
from kdtrace.kdtree import BUILD_BYTES_PER_TRIANGLE, build_bytes, build_kdtree
from kdtrace.render import frame_bytes, render
from kdtrace.resources import InsufficientMemoryError, available_memory, require_memory
from reconstruction import data

MEMINFO = "MemTotal:       24684332 kB\nMemFree:        19559252 kB\nMemAvailable:    2097152 kB\n"


@pytest.fixture
def two_gib(tmp_path, monkeypatch):
    """A machine with 2 GiB available (as /proc/meminfo says)."""
    meminfo = tmp_path / "meminfo"
    meminfo.write_text(MEMINFO)
    monkeypatch.setattr(resources, "MEMINFO", meminfo)
    return 2 * 2**30


def _allocating(*args, **kwargs):
    raise AssertionError("the memory check must come before any allocation")


def test_available_memory_reads_memavailable(two_gib, tmp_path, monkeypatch):
    assert available_memory() == two_gib
    require_memory(two_gib, "exactly what is available")
    with pytest.raises(InsufficientMemoryError, match=r"^a job needs up to 2.00 GiB \(2,147,483,649 bytes\) of memory, "
                                                      r"but only 2.00 GiB \(2,147,483,648 bytes\) are available "
                                                      r"\(MemAvailable\); ask for less$"):
        require_memory(two_gib + 1, "a job", "ask for less")
    monkeypatch.setattr(resources, "MEMINFO", tmp_path / "absent")  # not Linux: nothing is refused
    assert available_memory() is None
    require_memory(10**18, "anything")


def test_a_render_too_large_for_the_memory_available_is_refused_before_the_tree(two_gib, monkeypatch):
    import importlib

    monkeypatch.setattr(importlib.import_module("kdtrace.render"), "build_kdtree", _allocating)
    side = 7000  # 49 M pixels x 13 float32 channels, and 438 x 438 tiles x 4 int64 counters
    with pytest.raises(InsufficientMemoryError, match=rf"width x height = {side} x {side} \(49,000,000 pixels\) for the "
                                                      r"rgb, variance, albedo, normal and depth buffers needs up to "
                                                      r"2.38 GiB \(2,554,139,008 bytes\) of memory, but only 2.00 GiB"):
        render(cornell_like(8), width=side, height=side)
    assert frame_bytes(side, side, False, 16) < two_gib  # without the auxiliary buffers it fits


def test_a_kdtree_build_too_large_is_refused_and_a_cache_hit_is_not(two_gib, isolated_cache, monkeypatch):
    from kdtrace import kdtree

    scene = cornell_like(8)
    build_kdtree(scene, "local")  # cached
    monkeypatch.setattr(kdtree, "BUILD_BYTES_PER_TRIANGLE", two_gib)
    assert build_kdtree(scene, "local").stats["cache_hit"]
    monkeypatch.setattr(kdtree.build_kernels, "build_presorted", _allocating)
    with pytest.raises(InsufficientMemoryError, match=rf"the naive KD-tree of scene 'cornell-like' \({len(scene.triangles)} "
                                                      r"triangles\) needs up to .* but only 2.00 GiB"):
        build_kdtree(scene, "naive")


def test_a_dataset_whose_view_does_not_fit_is_refused_before_rendering(two_gib, isolated_cache, monkeypatch):
    import dataclasses

    huge = dataclasses.replace(DEFAULT_CONFIG.reconstruction.profile("quick"), width=4096, height=4096)
    monkeypatch.setattr(data, "make_view", _allocating)
    with pytest.raises(InsufficientMemoryError, match=r"a 4096x4096 view of the dataset in .* needs up to 3.25 GiB"):
        data.generate_dataset(cornell_like(8), huge, progress=False)


def test_crops_of_more_views_than_fit_are_refused_before_loading(two_gib, tmp_path):
    names = [f"view-{index:04d}" for index in range(400)]
    manifest = {"key": "k", "settings": {"width": 512, "height": 512},
                "splits": {"train": names, "validation": [], "test": []}}
    dataset = data.Dataset(tmp_path, manifest)  # no view file: the check comes before any load
    # 400 whole views of 512 x 512 x 13 float32, and 3,200 crops of 64 x 64 x 13 float32
    with pytest.raises(InsufficientMemoryError, match=rf"8 crops of 64x64 from each of the 400 train views of {tmp_path} "
                                                      r"needs up to 5.71 GiB \(6,134,169,600 bytes\)"):
        data.crops(dataset, "train", 64, 8, seed=0)


def test_the_shipped_standard_profile_fits_a_machine_with_2_gib(two_gib):
    standard = DEFAULT_CONFIG.profile("standard")
    assert frame_bytes(standard.frame_width, standard.frame_height, True, DEFAULT_CONFIG.render.tile_size) < two_gib / 100
    assert build_bytes(262_267) < two_gib / 4  # Crytek Sponza
    assert BUILD_BYTES_PER_TRIANGLE >= 3 * 291  # over three times the measured peak
    profile = DEFAULT_CONFIG.reconstruction.profile("standard")
    assert data.view_memory_bytes(profile) < two_gib / 10


def test_resident_peak_sees_a_temporary_allocation_and_what_is_kept():
    import numpy as np

    def temporary_then_kept():
        scratch = np.ones(64 * 2**20 // 8)  # 64 MiB touched, then freed
        total = float(scratch.sum())
        del scratch
        return total, np.ones(16 * 2**20 // 8)  # 16 MiB kept

    (total, kept), measured = resources.resident_peak(temporary_then_kept)
    assert total == 8 * 2**20 and measured["seconds"] > 0
    # what is kept is resident; the freed 64 MiB may be too, when the C allocator keeps it for reuse
    assert measured["retained_bytes"] >= 14 * 2**20
    if measured["peak_exact"]:
        assert 60 * 2**20 <= measured["peak_bytes"] <= 160 * 2**20
        assert measured["retained_bytes"] <= measured["peak_bytes"]
    del kept


def test_resident_memory_without_the_status_fields_is_an_error(tmp_path, monkeypatch):
    status = tmp_path / "status"
    status.write_text("Name:\tpython\nVmRSS:\t  100 kB\n")
    monkeypatch.setattr(resources, "STATUS", status)
    with pytest.raises(OSError, match="VmHWM"):
        resources.resident_memory()


def test_a_production_scene_too_large_is_refused_before_it_is_made(two_gib, monkeypatch):
    from kdtrace import procedural
    from kdtrace.procedural import instanced_scene, instanced_scene_bytes
    from kdtrace.scenes import load_scene

    base = load_scene("cbox-original")
    monkeypatch.setattr(procedural.np, "concatenate", _allocating)
    with pytest.raises(InsufficientMemoryError, match=r"10,000,000 triangles.*GiB"):
        instanced_scene(base, 10_000_000)
    assert instanced_scene_bytes(10_000_000) > two_gib
