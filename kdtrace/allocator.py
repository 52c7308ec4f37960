"""How the C allocator treats large freed blocks, set once per measuring process.

glibc serves every block above its mmap threshold (at most 32 MiB) with a fresh ``mmap``
and unmaps it on free, so a block that size is page-faulted in again on every use. The
superresolution net's 1024x1024, 32-channel bf16 activations are 64 MiB each: their page
faults were 70 ms of a 0.30 s frame (2 threads, AMD EPYC, idle, 2026-12-06), more than the
whole of its first layer. PyTorch's CPU performance guide answers this with a caching
allocator preloaded into the process (jemalloc or tcmalloc, ``LD_PRELOAD``); glibc's own
``mallopt`` gives the same reuse from inside the process, with no preload and no extra
package: large blocks come from the heap and freed memory stays there to be reused.
The price is that the process keeps its peak heap until it exits.

:func:`retain_freed_memory` is called by the command line and the benchmarks before they
measure anything, so every timing of a run (ours and its peers) sees the same allocator;
:func:`allocator_state` is recorded in every result's provenance.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

# glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
#: Heap top kept on free (bytes); the largest value mallopt takes (an int).
TRIM_THRESHOLD = 2**31 - 1

_state = "C library default"


def _glibc():
    """glibc as a ctypes library, or None on another C library (musl, macOS, Windows)."""
    if platform.libc_ver()[0] != "glibc":
        return None
    name = ctypes.util.find_library("c")
    return ctypes.CDLL(name) if name else None


def retain_freed_memory() -> str:
    """Serve large blocks from the heap and keep freed memory for reuse (glibc only).

    Sets ``M_MMAP_MAX`` to 0 (no block is given its own mapping) and ``M_TRIM_THRESHOLD``
    to :data:`TRIM_THRESHOLD` (the heap is not shrunk on free): the effect of
    ``GLIBC_TUNABLES=glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=...`` for a process
    already running. Idempotent. Elsewhere nothing changes.

    Returns
    -------
    str
        The allocator state afterwards (:func:`allocator_state`).
    """
    global _state
    libc = _glibc()
    if libc is None:
        _state = f"C library default ({platform.libc_ver()[0] or 'not glibc'}; not changed)"
    elif libc.mallopt(_M_MMAP_MAX, 0) and libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD):
        _state = f"glibc, freed memory retained (mmap_max 0, trim_threshold {TRIM_THRESHOLD})"
    else:
        raise RuntimeError("glibc's mallopt refused mmap_max=0 or the trim threshold")
    return _state


def allocator_state() -> str:
    """How this process's allocator treats large freed blocks, for provenance records."""
    return _state
