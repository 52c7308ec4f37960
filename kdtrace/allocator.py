"""How the C allocator treats large freed blocks while something is timed.

glibc serves every block above its mmap threshold (at most 32 MiB) with a fresh ``mmap``
and unmaps it on free, so a block that size is page-faulted in again on every use. The
superresolution net's 1024x1024, 32-channel bf16 activations are 64 MiB each: their page
faults were 70 ms of a 0.30 s frame (2 threads, AMD EPYC, idle), more than the
whole of its first layer. PyTorch's CPU performance guide answers this with a caching
allocator preloaded into the process (jemalloc or tcmalloc, ``LD_PRELOAD``); glibc's own
``mallopt`` gives the same reuse from inside the process, with no preload and no extra
package: large blocks come from the heap and freed memory stays there to be reused.

Only timed sections keep freed memory (:func:`freed_memory_retained`). For a whole process
it cost too much: the heap never shrinks, and the standard report, holding it while it
gathered the mixed model's 10 GB of training crops, was killed for lack of memory at 23 GB
of 24; with glibc's defaults the same step fits.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import platform
from collections.abc import Iterator
from contextlib import contextmanager

# glibc's mallopt parameters and their defaults (malloc.h, malloc.c).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_DEFAULT_TRIM_THRESHOLD = 128 * 1024
_DEFAULT_MMAP_MAX = 65536
#: Heap top kept on free (bytes) in a timed section; the largest value mallopt takes (an int).
TRIM_THRESHOLD = 2**31 - 1

_depth = 0  # nesting of freed_memory_retained (the outermost one sets and restores)


@functools.cache  # find_library runs ldconfig: once per process
def _glibc():
    """glibc as a ctypes library, or None on another C library (musl, macOS, Windows)."""
    if platform.libc_ver()[0] != "glibc":
        return None
    name = ctypes.util.find_library("c")
    return ctypes.CDLL(name) if name else None


def _set(libc, mmap_max: int, trim_threshold: int) -> None:
    if not (libc.mallopt(_M_MMAP_MAX, mmap_max) and libc.mallopt(_M_TRIM_THRESHOLD, trim_threshold)):
        raise RuntimeError(f"glibc's mallopt refused mmap_max={mmap_max}, trim_threshold={trim_threshold}")


@contextmanager
def freed_memory_retained() -> Iterator[None]:
    """Inside: large blocks come from the heap and freed memory stays there (glibc only).

    Sets ``M_MMAP_MAX`` to 0 (no block gets its own mapping) and ``M_TRIM_THRESHOLD`` to
    :data:`TRIM_THRESHOLD` (the heap is not shrunk on free), as
    ``GLIBC_TUNABLES=glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=...`` would for a
    whole process. On leaving the outermost section glibc's defaults come back and the free
    heap is returned to the system (``malloc_trim``). Nested sections are part of the
    outermost one. Elsewhere than glibc nothing changes.
    """
    global _depth
    libc = _glibc() if _depth == 0 else None
    if libc is not None:
        _set(libc, 0, TRIM_THRESHOLD)
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if libc is not None:
            _set(libc, _DEFAULT_MMAP_MAX, _DEFAULT_TRIM_THRESHOLD)
            libc.malloc_trim(0)


def allocator_policy() -> str:
    """What timed sections do to the allocator, for provenance records."""
    if _glibc() is None:
        return f"C library default ({platform.libc_ver()[0] or 'not glibc'}), unchanged"
    return f"glibc; timed sections keep freed memory (mmap_max 0, trim_threshold {TRIM_THRESHOLD})"
