"""Two processes on one cache: every artefact is computed once, nobody reads a partial file.

The processes are real (``subprocess``), started together on an empty cache folder; a
barrier file makes them miss the cache at the same moment.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from kdtrace.cache import ClaimWarning, atomic_write_bytes, claim, compute_once

REPOSITORY = Path(__file__).resolve().parents[1]

# One contender: waits for the barrier, then compute_once on a slow artefact, logging each computation.
_CONTENDER = textwrap.dedent("""
    import json, os, sys, time
    from pathlib import Path
    from kdtrace.cache import atomic_write_bytes, compute_once
    artefact, log, barrier = map(Path, sys.argv[1:4])
    while not barrier.exists():
        time.sleep(0.01)

    def compute():
        with open(log, "a") as handle:
            handle.write(f"{os.getpid()}\\n")
        time.sleep(1.0)  # long enough that the other process misses the cache meanwhile
        atomic_write_bytes(artefact, json.dumps({"by": os.getpid()}).encode())
        return artefact.read_text()

    def load():
        return artefact.read_text() if artefact.exists() else None

    print(compute_once(artefact, load, compute))
""")


def _start(script: str, *args: str, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", script, *args], cwd=REPOSITORY, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})})


def _finish(process: subprocess.Popen, timeout: float = 600) -> str:
    out, err = process.communicate(timeout=timeout)
    assert process.returncode == 0, err
    return out


def test_two_processes_compute_an_artefact_once_and_both_get_it(tmp_path):
    cache = {"KDTRACE_CACHE": str(tmp_path / "cache")}
    artefact, log, barrier = tmp_path / "artefact.json", tmp_path / "computed.log", tmp_path / "go"
    processes = [_start(_CONTENDER, str(artefact), str(log), str(barrier), env=cache) for _ in range(2)]
    barrier.touch()
    outputs = [_finish(process) for process in processes]
    assert len(log.read_text().split()) == 1  # computed once
    assert outputs[0] == outputs[1] == artefact.read_text() + "\n"  # the other one loaded the same file


def test_a_killed_holder_releases_its_claim_at_once(tmp_path):
    artefact = tmp_path / "artefact.npz"
    holder = _start("import sys, time; from kdtrace.cache import claim\n"
                    "with claim(sys.argv[1]):\n    print('held', flush=True); time.sleep(600)", str(artefact))
    assert holder.stdout.readline().strip() == "held"
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    started = time.perf_counter()
    with claim(artefact, timeout=30) as held:
        assert held
    assert time.perf_counter() - started < 5


def test_a_hung_holder_is_given_up_on_after_the_timeout_with_a_warning(tmp_path):
    artefact = tmp_path / "artefact.json"
    holder = _start("import sys, time; from kdtrace.cache import claim\n"
                    "with claim(sys.argv[1]):\n    print('held', flush=True); time.sleep(600)", str(artefact))
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.warns(ClaimWarning, match="computing it here as well"):
            value = compute_once(artefact, lambda: None,
                                 lambda: atomic_write_bytes(artefact, b"mine") and artefact.read_bytes(), timeout=0.5)
        assert value == b"mine"
    finally:
        holder.kill()
        holder.wait()


def test_an_unwritable_cache_runs_the_block_without_a_claim(tmp_path, monkeypatch):
    not_a_folder = tmp_path / "cache"
    not_a_folder.write_text("a file where the cache folder should be")  # unwritable even for root
    monkeypatch.setenv("KDTRACE_CACHE", str(not_a_folder))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with claim(not_a_folder / "artefact.npz") as held:
            assert not held


_TREE = textwrap.dedent("""
    import json, sys, time
    from pathlib import Path
    from kdtrace.kdtree import build_kdtree
    from kdtrace.scenes import load_scene
    barrier = Path(sys.argv[1])
    scene = load_scene("cbox-original")  # parsed before the barrier: the race is on the tree
    while not barrier.exists():
        time.sleep(0.01)
    tree = build_kdtree(scene, "local")
    print(json.dumps({"cache_hit": tree.stats["cache_hit"], "nodes": int(tree.node_meta.shape[0]),
                      "digest": __import__("hashlib").sha256(tree.refs.tobytes()).hexdigest()}))
""")


def _race(script: str, cache: Path, barrier: Path) -> list[dict]:
    """Start two processes of ``script`` on ``cache``, release them together, and return their last JSON lines."""
    processes = [_start(script, str(barrier), env={"KDTRACE_CACHE": str(cache)}) for _ in range(2)]
    time.sleep(0.5)
    barrier.touch()
    return [json.loads(_finish(process).strip().splitlines()[-1]) for process in processes]


def test_two_processes_building_one_kdtree_build_it_once(tmp_path):
    cache = tmp_path / "cache"
    results = _race(_TREE, cache, tmp_path / "go")
    assert sorted(result["cache_hit"] for result in results) == [False, True]  # one built, one loaded
    assert results[0]["digest"] == results[1]["digest"] and results[0]["nodes"] > 1
    assert len(list((cache / "kdtrees").glob("*.npz"))) == 1
    assert not list((cache / "kdtrees").glob(".*"))  # no temporary left behind


_DATASET = textwrap.dedent("""
    import dataclasses, json, sys, time
    from pathlib import Path
    from kdtrace.config import DEFAULT_CONFIG
    from reconstruction.data import generate_dataset
    barrier = Path(sys.argv[1])
    profile = dataclasses.replace(DEFAULT_CONFIG.reconstruction.profile("quick"), positions=2, width=32, height=32,
                                  reference_spp=16, test_reference_spp_by_scene={})
    while not barrier.exists():
        time.sleep(0.01)
    dataset = generate_dataset("cbox-original", profile, progress=False)
    print(json.dumps({view["name"]: view["worker"] for view in dataset.manifest["views"]}))
""")


def test_two_processes_generating_one_dataset_share_its_views(tmp_path):
    cache = tmp_path / "cache"
    made_by = _race(_DATASET, cache, tmp_path / "go")
    # each view was rendered by one process and read by the other: a view both had rendered would
    # carry each process's own identity in its own manifest
    assert made_by[0] == made_by[1] and len(made_by[0]) > 1
    views = sorted((next((cache / "datasets").iterdir())).glob("view-*.npz"))
    assert len(views) == len(made_by[0])
    for path in views:
        with np.load(path) as data:
            assert "__metadata__" in data.files  # complete files only
