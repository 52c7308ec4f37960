"""Datasets and units of work on a Dask cluster (kdtrace/distributed.py, reconstruction/data.py).

One 2-worker LocalCluster (worker processes) serves the whole module; the killed-worker
test runs last among its users because the nanny replaces the killed worker.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import os
import signal
import socket
import threading
import time
from pathlib import Path

import pytest

from kdtrace import distributed
from kdtrace.cli import main
from kdtrace.config import DEFAULT_CONFIG, load_config
from kdtrace.kdtree import build_kdtree
from kdtrace.scenes import load_scene
from reconstruction import data

#: The quick profile with 2 camera positions (8 candidate views): enough for identity and fault
#: tests, at half the rendering of the real quick profile (CI time).
QUICK = dataclasses.replace(DEFAULT_CONFIG.reconstruction.profile("quick"), positions=2)
SCENE = "cbox-original"
#: Volatile fields of a view record: who rendered it and how long it took.
VOLATILE = ("worker", "unit_seconds", "noisy_seconds", "reference_seconds")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """(client, cache folder) of a 2-worker LocalCluster whose workers cache trees in a temporary folder."""
    with pytest.MonkeyPatch.context() as patch:
        patch.delenv(distributed.SCHEDULER_ENV, raising=False)
        patch.setenv("KDTRACE_CACHE", str(tmp_path_factory.mktemp("worker-cache")))
        with distributed.connect(workers=2, announce=False) as client:
            client.wait_for_workers(2, timeout=120)
            yield client


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """An empty dataset cache for this test, and no scheduler from the environment."""
    monkeypatch.delenv(distributed.SCHEDULER_ENV, raising=False)
    monkeypatch.setenv("KDTRACE_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _in_cache(directory: Path, monkeypatch, generate):
    monkeypatch.setenv("KDTRACE_CACHE", str(directory))
    return generate()


def _stable(record: dict) -> dict:
    return {name: value for name, value in record.items() if name not in VOLATILE}


def _assert_same_dataset(first: data.Dataset, second: data.Dataset) -> None:
    assert first.key == second.key
    assert first.manifest["splits"] == second.manifest["splits"]
    assert [_stable(v) for v in first.manifest["views"]] == [_stable(v) for v in second.manifest["views"]]
    for name in first.views():
        one, two = first.load_view(name), second.load_view(name)
        for buffer in data.BUFFERS:
            assert one[buffer].tobytes() == two[buffer].tobytes(), (name, buffer)


def _listing(root: Path) -> dict[str, str]:
    return {path.name: hashlib.sha256(path.read_bytes()).hexdigest() for path in sorted(root.iterdir())}


def test_two_workers_make_the_single_process_dataset_bit_for_bit(cluster, tmp_path, monkeypatch):
    single = _in_cache(tmp_path / "single", monkeypatch,
                       lambda: data.generate_dataset(SCENE, QUICK, progress=False))
    spread = _in_cache(tmp_path / "dask", monkeypatch,
                       lambda: data.generate_dataset(SCENE, QUICK, progress=False, client=cluster))
    _assert_same_dataset(single, spread)
    workers = set(cluster.scheduler_info()["workers"])
    assert {view["worker"] for view in spread.manifest["views"]} <= workers
    assert all(view["unit_seconds"] > 0 for view in spread.manifest["views"])
    assert not [path for path in spread.root.iterdir() if path.name.startswith(".")]

    # a rerun after losing the manifest and one view renders only that view
    (spread.root / "manifest.json").unlink()
    lost = spread.root / "view-0001.npz"
    lost.unlink()
    kept = {path.name: path.stat().st_mtime_ns for path in spread.root.iterdir()}
    again = _in_cache(tmp_path / "dask", monkeypatch,
                      lambda: data.generate_dataset(SCENE, QUICK, progress=False, client=cluster))
    _assert_same_dataset(single, again)
    assert {name: (spread.root / name).stat().st_mtime_ns for name in kept} == kept
    assert lost.is_file()


def test_test_references_refined_on_two_workers_are_the_in_process_ones(cluster, tmp_path, monkeypatch):
    from reconstruction.test_references import refine_test_references

    tiny = dataclasses.replace(QUICK, width=32, height=32, reference_spp=16, test_reference_spp_by_scene={SCENE: 48})
    scene = load_scene(SCENE)
    single = _in_cache(tmp_path / "single", monkeypatch, lambda: refine_test_references(
        data.generate_dataset(SCENE, tiny, progress=False), scene, tiny, progress=False))
    spread = _in_cache(tmp_path / "dask", monkeypatch, lambda: refine_test_references(
        data.generate_dataset(SCENE, tiny, progress=False), scene, tiny, progress=False, client=cluster))
    assert spread.views("test") and spread.folder != single.folder
    for name in spread.views("test"):
        assert spread.load_view(name)["reference"].tobytes() == single.load_view(name)["reference"].tobytes()


def test_two_clients_at_once_render_each_view_once(cluster, cache):
    from distributed import Client

    outcome = {}

    def generate(name, client):
        outcome[name] = data.generate_dataset(SCENE, QUICK, progress=False, client=client)

    with Client(cluster.scheduler.address, set_as_default=False) as other:
        threads = [threading.Thread(target=generate, args=(name, client))
                   for name, client in (("first", cluster), ("second", other))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=300)
    first, second = outcome["first"], outcome["second"]
    # the same worker and seconds in both manifests: one rendering per view, shared by
    # task key or read back from its file, never rendered by both
    assert first.manifest["views"] == second.manifest["views"]
    assert not [path for path in first.root.iterdir() if path.name.startswith(".")]


def test_dataset_command_on_an_existing_scheduler(cluster, cache, capsys):
    assert main(["dataset", SCENE, "--scheduler", cluster.scheduler.address]) == 0
    printed = capsys.readouterr().out
    dataset = data.generate_dataset(SCENE, DEFAULT_CONFIG.reconstruction.profile("quick"), progress=False)  # a cache hit now
    assert {view["worker"] for view in dataset.manifest["views"]} <= set(cluster.scheduler_info()["workers"])
    accepted = sum(view["accepted"] for view in dataset.manifest["views"])
    assert f"{accepted} of {len(dataset.manifest['views'])} views accepted" in printed
    assert str(dataset.root) in printed


def test_unreachable_scheduler_is_a_clear_error_within_seconds(cache):
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    config = dataclasses.replace(DEFAULT_CONFIG.distributed, connect_timeout=2.0)
    started = time.perf_counter()
    with pytest.raises(distributed.SchedulerUnreachableError, match=f"127.0.0.1:{port}.*dask scheduler"):
        distributed.run_units([distributed.Unit("a", (1,))], abs, address, config=config)
    assert time.perf_counter() - started < 15.0
    # the command line says the same and exits with 2
    assert main(["dataset", SCENE, "--scheduler", address]) == 2


def test_a_worker_with_other_versions_is_refused(cluster, monkeypatch):
    real = distributed.package_versions()
    fake = {**real, "numpy": "0.0.fake"}
    monkeypatch.setattr(distributed, "package_versions", lambda: fake)
    with pytest.raises(distributed.VersionMismatchError, match=rf"numpy: client 0.0.fake, worker {real['numpy']}"):
        distributed.check_worker_versions(cluster)
    # and inside a unit, for a worker that joined after the check
    with pytest.raises(distributed.UnitError, match="refused: numpy: client 0.0.fake") as caught:
        distributed.run_units([distributed.Unit("versions-check", (-3,))], abs, client=cluster, progress=False)
    assert isinstance(caught.value.__cause__, distributed.VersionMismatchError)
    monkeypatch.setattr(distributed, "package_versions", lambda: real)
    assert [r.value for r in distributed.run_units([distributed.Unit("versions-ok", (-3,))], abs, client=cluster,
                                                   progress=False)] == [3]


def test_run_units_keeps_order_and_reports_worker_and_seconds(cluster):
    units = [distributed.Unit(f"square-{i}", (i, 2)) for i in range(6)]
    results = distributed.run_units(units, pow, client=cluster, progress=False)
    assert [r.value for r in results] == [i * i for i in range(6)]
    assert [r.key for r in results] == [u.key for u in units]
    assert {r.worker for r in results} <= set(cluster.scheduler_info()["workers"])
    assert all(r.seconds >= 0 for r in results)
    with pytest.raises(distributed.UnitError, match="unit bad-1 failed: ValueError"):
        distributed.run_units([distributed.Unit("bad-1", ("x",))], int, client=cluster, progress=False)
    with pytest.raises(ValueError, match="unique"):
        distributed.run_units([distributed.Unit("a"), distributed.Unit("a")], abs, client=cluster)


def _snapshot_partial_dataset(cache: Path) -> tuple[Path, dict[str, str]]:
    """A tiny dataset with its manifest and one view removed (work left to do), and its file listing."""
    tiny = dataclasses.replace(QUICK, width=32, height=32, reference_spp=16)
    dataset = data.generate_dataset(SCENE, tiny, progress=False)
    (dataset.root / "manifest.json").unlink()
    (dataset.root / "view-0002.npz").unlink()
    return dataset.root, _listing(dataset.root)


@pytest.mark.parametrize("code", [errno.EROFS, errno.ENOSPC])
def test_unwritable_output_is_a_clear_error_and_leaves_the_dataset(cache, monkeypatch, code):
    root, before = _snapshot_partial_dataset(cache)
    tiny = dataclasses.replace(QUICK, width=32, height=32, reference_spp=16)

    def refuse(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    # As root, chmod does not stop writes: simulate the file system's answer instead.
    # A read-only folder fails the up-front probe; a full disk fails the view's write.
    target = "tempfile.mkstemp" if code == errno.EROFS else "numpy.savez"
    monkeypatch.setattr(target, refuse)
    with pytest.raises(data.DatasetWriteError, match=os.strerror(code)) as caught:
        data.generate_dataset(SCENE, tiny, progress=False)
    assert str(root) in str(caught.value)
    if code == errno.ENOSPC:  # the view's bytes and the free space are named
        assert f"cannot write {root / 'view-0002.npz'}" in str(caught.value)
        assert "needs" in str(caught.value) and "bytes) free" in str(caught.value)
    assert _listing(root) == before


def test_stale_temporaries_of_dead_writers_are_removed(cache):
    root, before = _snapshot_partial_dataset(cache)
    stale, fresh = root / ".view-0002.dead.npz", root / ".view-0003.live.npz"
    for path in (stale, fresh):
        path.write_bytes(b"PK\x03\x04 half a file")
    old = time.time() - 2 * DEFAULT_CONFIG.distributed.stale_temporary_seconds
    os.utime(stale, (old, old))
    assert data.remove_stale_temporaries(root, DEFAULT_CONFIG.distributed.stale_temporary_seconds) == [stale.name]
    assert fresh.is_file() and _listing(root).keys() == before.keys() | {fresh.name}


def test_table1_rows_measured_on_the_cluster_match_the_in_process_rows(cluster, cache, tmp_path, monkeypatch):
    """The report's per-scene sweep (Table 1) as units: same counts and agreement, each row once."""
    import warnings as warnings_

    from reports import table1
    from reports.notes import ReportNote

    config = load_config()
    small = dataclasses.replace(config.profile("quick"), scenes=("cbox-empty", "cbox-original"),
                                agreement_rays_per_kind=2000, timing_rays=2000, frame_width=16, frame_height=16,
                                frame_spp=1, sensitivity_scenes=())
    config = dataclasses.replace(config, profiles={"tiny": small})
    with warnings_.catch_warnings():
        warnings_.simplefilter("ignore")
        local = {m.name: m.value for m in table1.generate(config, "tiny", tmp_path / "local", progress=False)}
        monkeypatch.setenv(distributed.SCHEDULER_ENV, cluster.scheduler.address)
        remote = {m.name: m.value for m in table1.generate(config, "tiny", tmp_path / "remote", progress=False)}
    assert local.keys() == remote.keys() and len(local) == 2 * 8  # 8 gated metrics per scene
    exact = [name for name in local if not name.endswith(("_primary", "_incoherent", "_occlusion", "_frame"))]
    assert {name: remote[name] for name in exact} == {name: local[name] for name in exact}
    # the worker built the configured tree: the references of an in-process build with the same config
    direct = build_kdtree(load_scene("cbox-original"), "local", config.kdtree, cache=False)
    assert remote["table1/cbox-original/triangle_references_local"] == direct.stats["triangle_references"]
    workers = set(cluster.scheduler_info()["workers"])
    rows = table1.load_rows(config, "tiny", tmp_path / "remote")
    assert all(row["worker"] in workers and row["threads"] == 1 for row in rows)
    with pytest.warns(ReportNote, match="reused 2 of 2 scene rows"):  # a rerun submits no unit
        table1.generate(config, "tiny", tmp_path / "remote", progress=False)


def test_a_killed_worker_s_view_is_rendered_elsewhere(cluster, tmp_path, monkeypatch):
    """SIGKILL a worker while it renders a view: the dataset still completes, identical and without duplicates."""
    slow = dataclasses.replace(QUICK, positions=3, width=96, height=96, reference_spp=128)
    pids = cluster.run(os.getpid)
    monkeypatch.setenv("KDTRACE_CACHE", str(tmp_path / "dask"))
    outcome: dict[str, object] = {}

    def generate():
        try:
            outcome["dataset"] = data.generate_dataset(SCENE, slow, progress=False, client=cluster)
        except Exception as error:  # noqa: BLE001 (reported by the assertion below)
            outcome["error"] = error

    root = data.dataset_dir(load_scene(SCENE), slow)
    thread = threading.Thread(target=generate)
    thread.start()
    victim = None
    deadline = time.monotonic() + 180
    while victim is None and thread.is_alive() and time.monotonic() < deadline:
        busy = {address: keys for address, keys in cluster.processing().items() if keys}
        if any(root.glob("view-*.npz")) and busy:  # workers warm, one of them rendering
            victim = min(busy)
            os.kill(pids[victim], signal.SIGKILL)
        time.sleep(0.01)
    thread.join(timeout=300)
    assert victim is not None, "no view was in progress to kill"
    assert not thread.is_alive() and "error" not in outcome, outcome.get("error")
    with pytest.raises(ProcessLookupError):
        os.kill(pids[victim], 0)
    spread = outcome["dataset"]
    candidates = slow.positions * slow.views_per_position
    assert sorted(path.name for path in root.iterdir()) == sorted(
        [f"view-{i:04d}.npz" for i in range(candidates)] + ["manifest.json"])
    assert [view["name"] for view in spread.manifest["views"]] == [f"view-{i:04d}" for i in range(candidates)]
    single = _in_cache(tmp_path / "single", monkeypatch, lambda: data.generate_dataset(SCENE, slow, progress=False))
    _assert_same_dataset(single, spread)


def test_local_cluster_is_sized_to_the_cores_and_config_is_validated(tmp_path, monkeypatch):
    monkeypatch.delenv(distributed.SCHEDULER_ENV, raising=False)
    cores = os.cpu_count() or 1
    config = dataclasses.replace(DEFAULT_CONFIG.distributed, workers=0, threads_per_worker=1)
    assert distributed.local_cluster_size(None, config) == (cores, 1)
    workers, threads = distributed.local_cluster_size(2, config)
    assert workers == 2 and threads == max(1, cores // 2)
    with pytest.raises(ValueError, match="workers"):
        distributed.local_cluster_size(-1, config)
    user = tmp_path / "user.toml"
    user.write_text('[distributed]\nworkers = 3\nscheduler = "tcp://head:8786"\n')
    loaded = load_config(user).distributed
    assert (loaded.workers, loaded.scheduler, loaded.threads_per_worker) == (3, "tcp://head:8786", 1)
    assert distributed.scheduler_address(None, loaded) == "tcp://head:8786"
    assert distributed.scheduler_address("local", loaded) is None
    user.write_text("[distributed]\ncalibration_spp = [64, 16]\n")
    with pytest.raises(ValueError, match="calibration_spp"):
        load_config(user)
