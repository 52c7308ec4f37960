"""Intel Embree (through ``embreex``) as the reference intersector.

:class:`EmbreeIntersector` answers the same two queries as our KD-trees,
``intersect`` and ``occluded``, with the same signatures and miss conventions, so
the two can be compared ray by ray (``references.agreement``).

Facts about ``embreex`` 4.4 this wrapper relies on (checked against the installed
wheel, see ``tests/test_embree.py``):

- ``EmbreeScene(robust=True)`` sets ``RTC_SCENE_FLAG_ROBUST`` (watertight
  traversal); we pass it explicitly rather than rely on the default.
- ``TriangleMesh(scene, vertices, indices)`` copies every triangle in order, so
  Embree's ``primID`` is the row index into the index array. Nothing is dropped:
  zero-area triangles stay in the BVH and *can* be reported as hits (their float32
  normal is rounding noise, not zero).
- ``run`` always sets ``tnear = 0`` and accepts hits with ``0 <= t <= tfar``
  (both ends inclusive); ``dists`` is the per-ray ``tfar`` and is overwritten in
  place with the hit distance. A miss leaves ``tfar`` unchanged and reports
  ``primID = -1``. ``query='OCCLUDED'`` returns 0 for an occluded ray and -1 otherwise.
- The scene is committed lazily by the first ``run``; ``run`` requires float32
  arrays, traces one ray at a time on the calling thread and releases the GIL, so
  threads over disjoint chunks scale.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from kdtrace.scene import Scene

#: Rays per ``run`` call when splitting work across threads; large enough to make
#: the per-call Python overhead negligible, small enough to balance the threads.
CHUNK_RAYS = 16384


def _validate_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Check ray arrays and return them as float32 C-contiguous (N, 3) arrays."""
    origins = np.asarray(origins)
    directions = np.asarray(directions)
    for name, array in (("origins", origins), ("directions", directions)):
        if array.ndim != 2 or array.shape[1] != 3:
            raise ValueError(f"{name} must have shape (N, 3), got {array.shape}")
        if not np.issubdtype(array.dtype, np.floating):
            raise TypeError(f"{name} must be a floating-point array, got dtype {array.dtype}")
    if origins.shape != directions.shape:
        raise ValueError(f"origins and directions must have the same shape, got {origins.shape} and {directions.shape}")
    with np.errstate(over="ignore"):  # overflow to inf is reported below
        origins = np.ascontiguousarray(origins, dtype=np.float32)
        directions = np.ascontiguousarray(directions, dtype=np.float32)
    for name, array in (("origins", origins), ("directions", directions)):
        if not np.all(np.isfinite(array)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(array), axis=1))[0])
            raise ValueError(f"{name}[{bad}] has a NaN or infinite component (after conversion to float32)")
    zero = ~np.any(directions != 0.0, axis=1)
    if zero.any():
        raise ValueError(f"directions[{int(np.flatnonzero(zero)[0])}] has zero length")
    return origins, directions


def _validate_range(tmin: float, tmax: float | np.ndarray, n: int) -> tuple[float, np.ndarray]:
    """Check the accepted ray interval and return ``tmin`` and ``tmax`` as an (N,) float64 array."""
    tmin = float(tmin)
    if not np.isfinite(tmin) or tmin < 0.0:
        raise ValueError(f"tmin must be finite and >= 0, got {tmin}")
    tmax_arr = np.asarray(tmax, dtype=np.float64)
    if tmax_arr.ndim > 1 or (tmax_arr.ndim == 1 and tmax_arr.shape != (n,)):
        raise ValueError(f"tmax must be a scalar or have shape ({n},), got {tmax_arr.shape}")
    tmax_arr = np.broadcast_to(tmax_arr, (n,))
    if np.isnan(tmax_arr).any():
        raise ValueError("tmax contains NaN")
    if (tmax_arr < tmin).any():
        raise ValueError(f"tmax must be >= tmin ({tmin}) for every ray")
    return tmin, tmax_arr


def _exclusive_tfar(length: np.ndarray) -> np.ndarray:
    """Embree ``tfar`` making its inclusive test ``t <= tfar`` equal ``t < length`` in float32."""
    length32 = length.astype(np.float32)
    finite = np.isfinite(length32)
    return np.where(finite, np.nextafter(length32, np.float32(-np.inf)), length32).astype(np.float32)


class EmbreeIntersector:
    """Embree BVH over a :class:`~kdtrace.scene.Scene`, queried from a thread pool.

    Parameters
    ----------
    scene : Scene
        The geometry. Every triangle is given to Embree (zero-area ones included,
        unless ``exclude_degenerate``), so hit indices are rows of ``scene.triangles``.
    threads : int, optional
        Worker threads per query; default ``os.cpu_count()`` (the thread count our
        numba kernels use).
    exclude_degenerate : bool
        Leave zero-area triangles out of the BVH, as our KD-trees do.

    Notes
    -----
    Accepted hits satisfy ``tmin <= t < tmax`` with ``t`` in units of ``|d|``:
    Embree's far test is inclusive, so it is given the largest float32 below
    ``tmax``. Embree has no near distance in ``embreex``; ``tmin > 0`` is emulated by
    moving the origin to ``o + tmin d`` (rounded to float32), tracing up to
    ``tmax - tmin`` and adding ``tmin`` back, which perturbs ``t`` by about one
    float32 ulp of ``|o| + tmin |d|``.
    """

    def __init__(self, scene: Scene, threads: int | None = None, exclude_degenerate: bool = False) -> None:
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a kdtrace Scene, got {type(scene).__name__}")
        if threads is None:
            threads = os.cpu_count() or 1
        if not isinstance(threads, (int, np.integer)) or threads < 1:
            raise ValueError(f"threads must be a positive integer, got {threads!r}")
        self.threads = int(threads)
        keep = ~scene.degenerate_mask() if exclude_degenerate else np.ones(len(scene.triangles), dtype=bool)
        if not keep.any():
            raise ValueError(f"scene {scene.name!r} has no triangle of non-zero area")
        self._tri_index = np.flatnonzero(keep).astype(np.int32)
        self._scene = rtcs.EmbreeScene(robust=True)
        self._mesh = TriangleMesh(self._scene, scene.vertices, np.ascontiguousarray(scene.triangles[keep]))
        # Commit now, on one thread: run() commits lazily and is not safe to race.
        self._scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))

    def _map(self, fn, n: int) -> list:
        """Call ``fn(slice)`` over chunks of ``range(n)``, on the pool when it helps."""
        chunks = [slice(i, min(i + CHUNK_RAYS, n)) for i in range(0, n, CHUNK_RAYS)]
        if self.threads == 1 or len(chunks) <= 1:
            return [fn(chunk) for chunk in chunks]
        with ThreadPoolExecutor(max_workers=self.threads) as pool:
            return list(pool.map(fn, chunks))

    def intersect(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        tmin: float = 0.0,
        tmax: float | np.ndarray = np.inf,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest hit of every ray.

        Parameters
        ----------
        origins, directions : (N, 3) float arrays
            Rays ``o + t d`` in scene units; directions need not be normalised.
            Converted to float32.
        tmin : float
            Near end of the accepted interval (inclusive), in units of ``|d|``.
        tmax : float or (N,) array
            Far end of the accepted interval (exclusive), in units of ``|d|``.

        Returns
        -------
        t : (N,) float32
            Hit distance in units of ``|d|``, ``inf`` on a miss.
        tri : (N,) int32
            Row of ``scene.triangles`` hit, -1 on a miss.
        u, v : (N,) float32
            Barycentric weights of triangle vertices 1 and 2 (0 on a miss).
        """
        origins, directions = _validate_rays(origins, directions)
        n = len(origins)
        tmin, tmax = _validate_range(tmin, tmax, n)
        if tmin > 0.0:
            origins = (origins + tmin * directions.astype(np.float64)).astype(np.float32)
        tfar = _exclusive_tfar(tmax - tmin)
        t = np.full(n, np.inf, dtype=np.float32)
        tri = np.full(n, -1, dtype=np.int32)
        u = np.zeros(n, dtype=np.float32)
        v = np.zeros(n, dtype=np.float32)

        def trace(chunk: slice) -> None:
            result = self._scene.run(origins[chunk], directions[chunk], dists=tfar[chunk].copy(), output=1)
            hit = result["primID"] >= 0
            t[chunk][hit] = result["tfar"][hit]
            tri[chunk][hit] = self._tri_index[result["primID"][hit]]
            u[chunk][hit] = result["u"][hit]
            v[chunk][hit] = result["v"][hit]

        self._map(trace, n)
        if tmin > 0.0:
            t = (t.astype(np.float64) + tmin).astype(np.float32)
        return t, tri, u, v

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tmax: float | np.ndarray) -> np.ndarray:
        """Whether anything is hit with ``0 <= t < tmax``.

        Parameters
        ----------
        origins, directions : (N, 3) float arrays
            Rays ``o + t d`` in scene units, converted to float32.
        tmax : float or (N,) array
            Distance to the point being tested for visibility, in units of ``|d|``.

        Returns
        -------
        (N,) bool
            True where the segment is blocked.
        """
        origins, directions = _validate_rays(origins, directions)
        n = len(origins)
        _, tmax = _validate_range(0.0, tmax, n)
        tfar = _exclusive_tfar(tmax)
        blocked = np.zeros(n, dtype=bool)

        def trace(chunk: slice) -> None:
            ids = self._scene.run(origins[chunk], directions[chunk], dists=tfar[chunk].copy(), query="OCCLUDED")
            blocked[chunk] = ids >= 0

        self._map(trace, n)
        return blocked
