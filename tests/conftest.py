"""Shared fixtures: the shared scene folder, an isolated mesh cache, camera coverage, and the
committed model stores kept out of reach of tests that train."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kdtrace.oracle import intersect_brute_force
from kdtrace.rays import camera_rays
from kdtrace.scenes import SHARED_SCENES_DIRECTORY

#: A session of at least this many tests on a cold numba cache compiles the ray-query kernels
#: in a second process (:mod:`kdtrace.precompile`) while its first tests compile the path tracer.
PRECOMPILE_MIN_TESTS = 100
_PRECOMPILE = pytest.StashKey[subprocess.Popen]()


def pytest_collection_finish(session: pytest.Session) -> None:
    """Start :mod:`kdtrace.precompile` in the background for a large session on a cold cache."""
    from kdtrace import precompile

    if len(session.items) >= PRECOMPILE_MIN_TESTS and precompile.cache_is_cold():
        session.config.stash[_PRECOMPILE] = subprocess.Popen(
            [sys.executable, "-m", "kdtrace.precompile"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Stop the precompiling process if it is still running (numba writes its cache atomically)."""
    process = session.config.stash.get(_PRECOMPILE, None)
    if process is not None and process.poll() is None:
        process.terminate()
        process.wait(timeout=60)


def _private_store(factory: pytest.TempPathFactory):
    from reconstruction import train

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(train, "MODEL_STORE_ROOT", factory.mktemp("model-stores"))
        yield


@pytest.fixture(scope="module", autouse=True)
def private_model_stores_of_module_fixtures(tmp_path_factory):
    """Relative model stores (``models/quick``, ``models/standard``) resolve in a private folder,
    so that a test that trains never publishes into the checkout, nor finds another test's model:
    one folder for a module's fixtures, one for each test (below). A test of the committed networks
    sets ``reconstruction.train.MODEL_STORE_ROOT`` back to ``train.REPOSITORY``."""
    yield from _private_store(tmp_path_factory)


@pytest.fixture(autouse=True)
def private_model_stores(tmp_path_factory):
    """Each test's own private model stores (see :func:`private_model_stores_of_module_fixtures`)."""
    yield from _private_store(tmp_path_factory)


@pytest.fixture(scope="session")
def shared_scenes() -> Path:
    """The shared scene data folder (``../shared/scenes``); skips when it is absent."""
    if not SHARED_SCENES_DIRECTORY.is_dir():
        pytest.skip(f"shared scenes not found at {SHARED_SCENES_DIRECTORY}")
    return SHARED_SCENES_DIRECTORY


@pytest.fixture
def isolated_cache(tmp_path, monkeypatch) -> Path:
    """A fresh, empty mesh cache directory for this test (via ``KDTRACE_CACHE``)."""
    directory = tmp_path / "cache"
    monkeypatch.setenv("KDTRACE_CACHE", str(directory))
    return directory


@pytest.fixture
def camera_coverage():
    """``coverage(scene, rays_per_side=5) -> (central ray hits, fraction of grid rays that hit)``."""

    def coverage(scene, rays_per_side: int = 5) -> tuple[bool, float]:
        origins, directions = camera_rays(scene.camera, rays_per_side, rays_per_side)
        centre_origin, centre_direction = camera_rays(scene.camera, 1, 1)
        _, hits, _, _ = intersect_brute_force(
            scene.vertices, scene.triangles, np.vstack([centre_origin, origins]), np.vstack([centre_direction, directions])
        )
        return bool(hits[0] >= 0), float(np.mean(hits[1:] >= 0))

    return coverage
