"""Shared fixtures: the shared scene folder, an isolated mesh cache, camera coverage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kdtrace.oracle import intersect_brute_force
from kdtrace.scenes import SHARED_SCENES_DIRECTORY


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


def camera_grid_rays(camera, rays_per_side: int) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole rays through a ``rays_per_side`` square grid of the image (row-major, centre included when odd)."""
    position = np.array(camera.position, dtype=np.float64)
    forward = np.subtract(camera.look_at, position)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half_height = np.tan(np.radians(camera.fov) / 2.0)
    half_width = half_height * camera.width / camera.height
    steps = (np.arange(rays_per_side) + 0.5) / rays_per_side * 2.0 - 1.0
    x, y = np.meshgrid(steps, -steps)
    directions = forward + x.reshape(-1, 1) * half_width * right + y.reshape(-1, 1) * half_height * up
    return np.broadcast_to(position, directions.shape).copy(), directions


@pytest.fixture
def camera_coverage():
    """``coverage(scene, rays_per_side=5) -> (central ray hits, fraction of grid rays that hit)``."""

    def coverage(scene, rays_per_side: int = 5) -> tuple[bool, float]:
        origins, directions = camera_grid_rays(scene.camera, rays_per_side)
        centre_origin, centre_direction = camera_grid_rays(scene.camera, 1)
        _, hits, _, _ = intersect_brute_force(
            scene.vertices, scene.triangles, np.vstack([centre_origin, origins]), np.vstack([centre_direction, directions])
        )
        return bool(hits[0] >= 0), float(np.mean(hits[1:] >= 0))

    return coverage
