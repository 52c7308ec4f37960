"""A disk that fills up during each kind of write: nothing half-written is left (the old file or none,
no temporaries), the error names the file, the bytes it needs and the bytes free, and long jobs
(training, Mitsuba references) resume from their last complete checkpoint."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from kdtrace import cache
from kdtrace.cache import DiskFullError, atomic_write, atomic_write_bytes, npz_bytes, save_npz

#: What the simulated file system reports as free, in bytes.
FREE_BYTES = 1234


class FullDisk:
    """Makes writes of temporaries under ``folder`` fail with ``code`` once ``files_allowed`` files were written.

    Both low-level paths are covered: ``os.write`` (:func:`kdtrace.cache.atomic_write_bytes`) and
    ``numpy.savez`` (:func:`kdtrace.cache.save_npz`). The failing write first leaves half of its bytes in
    the temporary, as a real disk that fills up mid-file does. Only temporaries whose name contains
    ``name`` count (``""``: all).
    """

    def __init__(self, monkeypatch: pytest.MonkeyPatch, folder: Path, name: str = "", files_allowed: int = 0,
                 code: int = errno.ENOSPC) -> None:
        self.folder, self.name, self.files_allowed, self.code = Path(folder).resolve(), name, files_allowed, code
        self.files_seen: set[str] = set()
        self.full = True
        real_write, real_savez = os.write, np.savez

        def write(handle, data):
            target = os.readlink(f"/proc/self/fd/{handle}")
            if self._fails(target):
                real_write(handle, bytes(data)[:len(data) // 2])
                raise OSError(self.code, os.strerror(self.code))
            return real_write(handle, data)

        def savez(file, *args, **kwargs):
            if isinstance(file, (str, Path)) and self._fails(str(Path(file).resolve())):
                Path(file).write_bytes(b"PK\x03\x04 half of an archive")
                raise OSError(self.code, os.strerror(self.code))
            return real_savez(file, *args, **kwargs)

        monkeypatch.setattr(os, "write", write)
        monkeypatch.setattr(np, "savez", savez)
        monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10**9, 10**9, FREE_BYTES))

    def _fails(self, target: str) -> bool:
        if not (self.full and target.startswith(f"{self.folder}/") and self.name in Path(target).name):
            return False
        self.files_seen.add(target)
        return len(self.files_seen) > self.files_allowed

    def free(self) -> None:
        """Space is available again: every write succeeds."""
        self.full = False


def _files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (but the claims' lock files) with its bytes."""
    return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*"))
            if path.is_file() and ".locks" not in path.parts}


def _assert_no_temporaries(folder: Path) -> None:
    assert not [name for name in _files(folder) if Path(name).name.startswith(".")]


def _assert_names_the_shortage(error: pytest.ExceptionInfo, path: Path, bytes_needed: int | None) -> None:
    text = str(error.value)
    assert f"cannot write {path}: No space left on device" in text
    assert f"({FREE_BYTES:,} bytes) free" in text
    if bytes_needed is not None:
        assert f"needs {bytes_needed / 1e6:.1f} MB ({bytes_needed:,} bytes)" in text
    assert "\n" not in text


@pytest.fixture
def cache_folder(tmp_path, monkeypatch) -> Path:
    folder = tmp_path / "cache"
    monkeypatch.setenv("KDTRACE_CACHE", str(folder))
    return folder


# ------------------------------------------------------------------ the shared writers
def test_bytes_on_a_full_disk_keep_the_old_file_and_name_path_size_and_free_space(tmp_path, monkeypatch):
    target = tmp_path / "out" / "table.md"
    atomic_write_bytes(target, b"old table")
    before = _files(tmp_path)
    disk = FullDisk(monkeypatch, tmp_path)
    with pytest.raises(DiskFullError) as error:
        atomic_write_bytes(target, b"x" * 5000)
    _assert_names_the_shortage(error, target, 5000)
    assert error.value.errno == errno.ENOSPC and error.value.filename == str(target)
    assert error.value.bytes_written == 2500  # the half the disk took, deleted since
    assert _files(tmp_path) == before
    disk.free()
    atomic_write_bytes(target, b"new table")
    assert target.read_bytes() == b"new table"
    # a Dask worker's error reaches the client whole
    copy = pickle.loads(pickle.dumps(error.value))
    assert (str(copy), copy.bytes_needed, copy.bytes_free) == (str(error.value), 5000, FREE_BYTES)


def test_a_spent_quota_and_a_file_of_unknown_size(tmp_path, monkeypatch):
    FullDisk(monkeypatch, tmp_path, code=errno.EDQUOT)
    with pytest.raises(DiskFullError, match=f"cannot write {tmp_path / 'new.json'}: Disk quota exceeded"):
        atomic_write_bytes(tmp_path / "new.json", b"{}")

    def draw(temporary: str) -> None:  # a writer of unknown size (a plot): the message gives what it managed
        with open(temporary, "wb") as file:
            file.write(b"\x89PNG" + bytes(96))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(DiskFullError) as error:
        atomic_write(tmp_path / "plot.png", draw)
    assert "needs more than the 0.0 MB (100 bytes) written before the failure" in str(error.value)
    assert _files(tmp_path) == {}


def test_no_inode_left_for_the_temporary(tmp_path, monkeypatch):
    def no_inode(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(cache.tempfile, "mkstemp", no_inode)
    with pytest.raises(DiskFullError, match="needs 0.0 MB \\(3 bytes\\)"):
        atomic_write_bytes(tmp_path / "a" / "b.txt", b"abc")


def test_arrays_on_a_full_disk(tmp_path, monkeypatch):
    arrays = {"rgb": np.ones((16, 16, 3), np.float32)}
    FullDisk(monkeypatch, tmp_path)
    with pytest.raises(DiskFullError) as error:
        save_npz(tmp_path / "view.npz", arrays, {"key": "k"})
    encoded = np.frombuffer(json.dumps({"key": "k"}).encode(), np.uint8)
    _assert_names_the_shortage(error, tmp_path / "view.npz", npz_bytes({"__metadata__": encoded, **arrays}))
    assert _files(tmp_path) == {}


# ------------------------------------------------------------------ training, model store
def _tiny_data(seed: int) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    generator = torch.Generator().manual_seed(seed)
    return {split: (torch.rand(count, 3, 8, 8, generator=generator), torch.rand(count, 3, 8, 8, generator=generator))
            for split, count in (("train", 16), ("validation", 4))}


def _fit(directory: Path, epochs: int):
    from reconstruction import train

    torch.manual_seed(0)
    model = nn.Conv2d(3, 3, 3, padding=1)
    return train.fit(model, nn.MSELoss(), _tiny_data(1), directory, "data-hash", epochs=epochs, batch_size=4,
                     learning_rate=1e-2, seed=0, psnr=lambda test, reference: 0.0, progress=False)


def test_training_stopped_by_a_full_disk_resumes_from_its_last_checkpoint(tmp_path, monkeypatch):
    from reconstruction import train

    monkeypatch.setattr(train, "PLOT_EVERY", 10**6)  # no plot: the checkpoints are what is tested
    uninterrupted = _fit(tmp_path / "uninterrupted", epochs=3)
    directory = tmp_path / "interrupted"
    _fit(directory, epochs=1)
    after_first_epoch = _files(directory)
    disk = FullDisk(monkeypatch, directory, name="checkpoint")
    with pytest.raises(DiskFullError) as error:
        _fit(directory, epochs=3)
    _assert_names_the_shortage(error, directory / "checkpoint.pt", None)
    assert error.value.bytes_needed > 0
    _assert_no_temporaries(directory)
    assert _files(directory)["checkpoint.pt"] == after_first_epoch["checkpoint.pt"]
    assert train.read_checkpoint(directory / "checkpoint.pt")["epoch"] == 1
    disk.free()
    resumed = _fit(directory, epochs=3)
    assert [row["epoch"] for row in resumed.history] == [1, 2, 3]
    for row, reference in zip(resumed.history, uninterrupted.history, strict=True):
        assert row["validation_loss"] == pytest.approx(reference["validation_loss"], rel=1e-5)


def test_publishing_to_a_full_model_store_leaves_no_finished_copy_and_is_done_again(tmp_path, monkeypatch):
    from kdtrace.config import DEFAULT_CONFIG
    from reconstruction import train

    monkeypatch.setattr(train, "PLOT_EVERY", 1)
    result = _fit(tmp_path / "cache" / "denoiser-key", epochs=1)
    atomic_write_bytes(result.directory / "result.json", b'{"test": {}}')
    profile = dataclasses.replace(DEFAULT_CONFIG.reconstruction.profile("quick"), model_store=str(tmp_path / "store"))
    store = tmp_path / "store" / "denoiser-key"
    disk = FullDisk(monkeypatch, tmp_path / "store", files_allowed=2)  # best.pt and history.json fit
    with pytest.raises(DiskFullError) as error:
        train._publish(result, profile)
    _assert_names_the_shortage(error, store / "history.csv", len((result.directory / "history.csv").read_bytes()))
    assert sorted(_files(store)) == ["best.pt", "history.json"]  # no result.json: not a finished copy
    disk.free()
    train._publish(result, profile)
    assert _files(store) == {name: (result.directory / name).read_bytes() for name in train.PUBLISHED_FILES}


# ------------------------------------------------------------------ reports and gate baselines
def test_report_files_on_a_full_disk(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    from reports.figures import write_figure
    from reports.metrics import Metric, write_metrics
    from reports.verdict_page import VERDICT_HTML, VERDICT_MARKDOWN, link_from_index, write_verdict

    out = tmp_path / "results"
    write_metrics(out, "table1", [Metric("table1/car/refs", "count", 10)])
    atomic_write_bytes(out / "README.md", b"# Results\n\nthe index\n")
    write_verdict(out, "quick")
    before = _files(out)
    FullDisk(monkeypatch, out)
    cases = [(lambda: write_metrics(out, "table1", [Metric("table1/car/refs", "count", 11)]),
              out / "metrics" / "table1.json"),
             (lambda: write_figure(Figure(figsize=(2, 1)), out / "plots" / "curve.png"), out / "plots" / "curve.png"),
             (lambda: link_from_index(out), out / "README.md"),
             (lambda: write_verdict(out, "quick"), out / VERDICT_MARKDOWN)]
    for write, path in cases:
        with pytest.raises(DiskFullError) as error:
            write()
        _assert_names_the_shortage(error, path, None)
        assert error.value.bytes_needed > 0
        assert _files(out) == before
    assert (out / VERDICT_HTML).is_file()


def test_gate_baseline_on_a_full_disk(tmp_path, monkeypatch):
    from reports import gate
    from reports.metrics import Metric, write_metrics

    out, baselines = tmp_path / "results", tmp_path / "baseline"
    write_metrics(out, "table1", [Metric("table1/car/refs", "count", 10)])
    gate.update_baseline(out, "quick", directory=baselines)
    before = _files(baselines)
    write_metrics(out, "table1", [Metric("table1/car/refs", "count", 12)])
    disk = FullDisk(monkeypatch, baselines)
    with pytest.raises(DiskFullError) as error:
        gate.update_baseline(out, "quick", directory=baselines)
    _assert_names_the_shortage(error, baselines / "quick.json", None)
    assert _files(baselines) == before
    disk.free()
    gate.update_baseline(out, "quick", directory=baselines)
    assert gate.read_baseline(baselines / "quick.json")["table1/car/refs"].value == 12


# ------------------------------------------------------------------ cached artefacts
def test_kdtree_cache_on_a_full_disk(cache_folder, monkeypatch):
    from test_mitsuba import cornell_like

    from kdtrace.kdtree import build_kdtree

    scene = cornell_like(8)
    disk = FullDisk(monkeypatch, cache_folder)
    with pytest.raises(DiskFullError) as error:
        build_kdtree(scene, "local")
    path = Path(error.value.filename)
    assert path.parent == cache_folder / "kdtrees" and path.suffix == ".npz"
    _assert_names_the_shortage(error, path, error.value.bytes_needed)
    assert error.value.bytes_needed > 0
    assert _files(cache_folder) == {}
    disk.free()
    assert not build_kdtree(scene, "local").stats["cache_hit"]
    assert build_kdtree(scene, "local").stats["cache_hit"]


def test_mitsuba_reference_stopped_by_a_full_disk_resumes_from_its_checkpoint(cache_folder, monkeypatch):
    from test_mitsuba import cornell_like

    from references import llvm
    from references import mitsuba as mref

    variant = llvm.activate_variant("scalar_rgb")
    scene = cornell_like(16)
    monkeypatch.setattr(mref, "PASS_SAMPLES", 16 * 16 * 2)  # 2 spp per pass: 4 passes
    monkeypatch.setattr(mref, "CHECKPOINT_SECONDS", -1.0)  # a checkpoint after every pass but the last
    disk = FullDisk(monkeypatch, cache_folder / "mitsuba", files_allowed=2)  # the third checkpoint fails
    with pytest.raises(DiskFullError) as error:
        mref.render_reference(scene, spp=8, max_depth=3, seed=0, variant=variant)
    assert error.value.filename.endswith(".partial.npz")
    _assert_names_the_shortage(error, Path(error.value.filename), error.value.bytes_needed)
    assert error.value.bytes_needed > 16 * 16 * 3 * 8 * 2  # the two float64 running sums
    _assert_no_temporaries(cache_folder)
    (checkpoint,) = (cache_folder / "mitsuba").glob("*.partial.npz")
    assert mref.load_npz(checkpoint)[1]["passes"] == 2
    disk.free()
    resumed = mref.render_reference(scene, spp=8, max_depth=3, seed=0, variant=variant)
    assert not list((cache_folder / "mitsuba").glob("*.partial.npz"))
    fresh = mref.render_reference(scene, spp=8, max_depth=3, seed=0, variant=variant, cache=False)
    assert np.allclose(resumed.rgb, fresh.rgb, rtol=1e-5, atol=1e-6)

    # the finished reference itself (no checkpoint this time): no file
    FullDisk(monkeypatch, cache_folder / "mitsuba")
    monkeypatch.setattr(mref, "CHECKPOINT_SECONDS", 10**9)
    with pytest.raises(DiskFullError) as error:
        mref.render_reference(scene, spp=8, max_depth=3, seed=1, variant=variant)
    assert not error.value.filename.endswith(".partial.npz")
    _assert_no_temporaries(cache_folder)
    assert not Path(error.value.filename).exists()
