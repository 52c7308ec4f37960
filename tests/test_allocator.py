"""Timed sections keep freed memory (:mod:`kdtrace.allocator`), checked in a fresh process."""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

# Page faults (ru_minflt) of a second malloc + touch + free of a 64 MiB block (the first one
# maps it), by glibc's defaults, inside a timed section, inside a nested one after the inner
# one has ended, and after the outermost one has ended. Through ctypes, as torch allocates
# (numpy would madvise huge pages).
_PROGRAM = """
import ctypes, ctypes.util, json, resource
from kdtrace.allocator import freed_memory_retained
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
def use_block():
    block = libc.malloc(64 << 20)
    ctypes.memset(block, 1, 64 << 20)
    libc.free(block)
def faults():
    use_block()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    use_block()
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
counts = {"default": faults()}
with freed_memory_retained():
    counts["retained"] = faults()
    with freed_memory_retained():
        pass
    counts["after a nested section"] = faults()
counts["after"] = faults()
print(json.dumps(counts))
"""

PAGES = (64 << 20) // 4096


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_timed_sections_reuse_freed_memory_and_restore_the_defaults():
    done = subprocess.run([sys.executable, "-c", _PROGRAM], capture_output=True, text=True, check=True)
    faults = json.loads(done.stdout)
    # by default a fresh mapping (one fault per 4 KiB page, fewer with huge pages); retained,
    # the freed block is reused from the heap, also after a nested section has ended
    assert faults["default"] > PAGES // 4 and faults["after"] > PAGES // 4
    assert faults["retained"] < PAGES // 50 and faults["after a nested section"] < PAGES // 50


def test_provenance_records_the_allocator_policy():
    from kdtrace.provenance import machine

    assert machine()["allocator"].startswith(("C library default", "glibc; timed sections keep freed memory"))
