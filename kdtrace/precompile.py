"""Compile the ray-query kernels ahead of their first use, in a process of their own.

numba compiles a kernel on its first call and keeps the machine code in ``__pycache__`` beside
the source, so only a fresh checkout pays for it. There the path tracer's kernel takes about
3 minutes to compile on one core, and the batch queries (closest hit, any hit, packets,
regrouped rays) and the brute-force oracle about 3 more, one after the other. Run as
``python -m kdtrace.precompile`` beside a job that starts with the path tracer, the query
kernels compile on the other core at the same time; the job then loads them from the cache.
The test suite does this on a cold cache (``tests/conftest.py``). Nothing is measured or
written here except numba's cache.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kdtrace.kdtree import build_kdtree
from kdtrace.oracle import nearest_hits_fast
from kdtrace.procedural import random_soup

#: The kernels' cache index files (``__pycache__/<module>.<function>-*.nbi``) whose absence
#: means a cold cache: the first kernel of each kind of query this module compiles.
INDEX_GLOBS = ("_packet_traverse.trace_batch_packets-*.nbi", "_kdtree_traverse.trace_batch-*.nbi",
               "_oracle_kernels.nearest_hits-*.nbi")


def cache_is_cold(cache: Path | None = None) -> bool:
    """Whether any kernel of :data:`INDEX_GLOBS` has no cached machine code in ``cache`` yet.

    ``cache`` defaults to numba's cache folder of the kernels, ``kdtrace/__pycache__``.
    """
    cache = Path(__file__).resolve().parent / "__pycache__" if cache is None else cache
    return not all(any(cache.glob(pattern)) for pattern in INDEX_GLOBS)


def compile_query_kernels() -> None:
    """Call every batch query of :class:`kdtrace.kdtree.KDTree` and the oracle once, on 64 random triangles.

    The arguments have the dtypes and layouts of every caller's (float64 rays, writable arrays),
    so the compiled signatures are the ones the tests and reports use.
    """
    scene = random_soup(64, seed=0)
    rng = np.random.default_rng(0)
    origins = rng.uniform(-2.0, 2.0, (256, 3))
    directions = -origins + rng.normal(0.0, 0.3, (256, 3))
    for variant in ("local", "naive"):
        tree = build_kdtree(scene, variant, cache=False)
        for vector_spans in (True, False):
            tree.intersect(origins, directions, vector_spans=vector_spans)
        tree.intersect(origins, directions, packets=True)
        tree.intersect(origins, directions, regroup=True)
        tree.occluded(origins, directions, np.full(len(origins), 2.0))
    nearest_hits_fast(scene.vertices, scene.triangles, origins, directions)


if __name__ == "__main__":
    compile_query_kernels()
