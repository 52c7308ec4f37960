"""The allocator setting of measuring processes (:mod:`kdtrace.allocator`), checked in fresh processes."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

# malloc, touch and free a 64 MiB block twice; print the page faults of the second time
# (ru_minflt) and the allocator state. Through ctypes, as torch allocates (numpy would
# madvise huge pages).
_PROGRAM = """
import ctypes, ctypes.util, resource, sys
from kdtrace import allocator
if sys.argv[1] == "retain":
    allocator.retain_freed_memory()
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
def use_block():
    block = libc.malloc(64 << 20)
    ctypes.memset(block, 1, 64 << 20)
    libc.free(block)
use_block()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
use_block()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before, allocator.allocator_state(), sep="|")
"""

PAGES = (64 << 20) // 4096


def _faults_and_state(mode: str) -> tuple[int, str]:
    done = subprocess.run([sys.executable, "-c", _PROGRAM, mode], capture_output=True, text=True, check=True)
    faults, state = done.stdout.strip().split("|")
    return int(faults), state


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_retained_memory_is_reused_without_page_faults():
    default_faults, default_state = _faults_and_state("default")
    retained_faults, retained_state = _faults_and_state("retain")
    assert default_state == "C library default"
    assert retained_state.startswith("glibc, freed memory retained")
    # The default maps a fresh block (one fault per 4 KiB page, fewer with huge pages);
    # retained, the freed block is reused from the heap.
    assert default_faults > PAGES // 4
    assert retained_faults < PAGES // 50


def test_provenance_records_the_allocator():
    from kdtrace.provenance import machine

    assert machine()["allocator"].startswith(("C library default", "glibc"))
