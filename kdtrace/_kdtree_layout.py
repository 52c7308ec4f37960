"""numba kernels that lay a built KD-tree out for traversal: 8-byte nodes in cache-line blocks.

On large trees much of a node visit's cost is memory latency (bunny's incoherent rays, one
thread: 79 ns per node visit over 200,000 distinct rays, 17 ns when the same 200
rays repeat and their nodes stay cached; beyond the 1 MB L2 a dependent load costs about
190 ns on these VMs). Two changes cut the cache lines a ray touches:

* **8-byte nodes** (as pbrt's): word 0 holds the axis (bits 0-1, 3 for a leaf) and either a
  leaf's triangle count (bits 2-31) or an interior node's flag "holds triangles" (bit 2,
  local-branch trees only) and left child index (bits 3-31); word 1 is the split position
  (float32 bits) or a leaf's first reference. Interior triangle spans live in a second half
  of the same array, row ``n + node``, read only when the flag is set, so the half a ray
  walks holds nothing else.
* **Blocked order**: a sibling pair and, breadth first, up to three pairs below it share
  one 64-byte line (eight nodes), so a ray descending through a block reads one line for
  about two levels; blocks follow each other depth first, and a block that would straddle
  a line boundary starts on the next line.

The layout is the build's tree node for node (``tests/test_kdtree.py`` decodes it back), so
the traversal visits the same nodes in the same order: hits and counters are unchanged.
Measured: distinct node lines per incoherent ray 25 -> 14 on bunny and Sponza; one thread on
bunny 2,246 -> 1,957 ns per ray; with two threads the gain is within the run-to-run noise.
"""

from __future__ import annotations

import sys

import numpy as np
from numba import njit

from kdtrace import _kdtree_build
from kdtrace._kdtree_build import LEAF
from kdtrace.cache import drop_stale_kernel_cache

#: Nodes per 64-byte cache line at 8 bytes per node.
LINE_NODES = 8
#: Bounds of word 0 (a signed int32): child index in bits 3-31, leaf count in bits 2-31.
MAX_NODES = 1 << 28
MAX_COUNT = 1 << 29
HAS_TRIANGLES = 4


@njit(cache=True)
def blocked_order(node_meta):
    """New index of every node: sibling pairs in cache-line blocks, blocks depth first.

    Slot 0 holds the root and slot 1 stays empty, so every pair starts at an even slot and
    a line holds the root and three pairs, or four pairs. Returns ``(new_index, n_slots)``
    with ``n_slots`` a multiple of :data:`LINE_NODES`; slots no node maps to are padding.
    """
    n = node_meta.shape[0]
    new_index = np.full(n, -1, np.int64)
    new_index[0] = 0
    next_slot = 2
    stack = np.empty(n + 1, np.int64)  # left children of pairs still to place
    sp = 0
    if node_meta[0] != LEAF:
        stack[0] = node_meta[0] >> 2
        sp = 1
    block = np.empty(LINE_NODES // 2, np.int64)
    frontier = np.empty(LINE_NODES, np.int64)
    while sp > 0:
        sp -= 1
        block[0] = stack[sp]
        capacity = (LINE_NODES - next_slot % LINE_NODES) // 2
        taken = 1
        head = 0
        n_frontier = 0
        while head < taken:
            pair = block[head]
            head += 1
            for child in (pair, pair + 1):
                if node_meta[child] != LEAF:
                    left = node_meta[child] >> 2
                    if taken < capacity:
                        block[taken] = left
                        taken += 1
                    else:
                        frontier[n_frontier] = left
                        n_frontier += 1
        for k in range(taken):
            new_index[block[k]] = next_slot
            new_index[block[k] + 1] = next_slot + 1
            next_slot += 2
        # Place the next block on a fresh line unless a full block still fits in this one.
        if (next_slot % LINE_NODES) + LINE_NODES // 2 > LINE_NODES:
            next_slot += (LINE_NODES - next_slot % LINE_NODES) % LINE_NODES
        for k in range(n_frontier - 1, -1, -1):  # the first frontier pair is placed next
            stack[sp] = frontier[k]
            sp += 1
    n_slots = next_slot + (LINE_NODES - next_slot % LINE_NODES) % LINE_NODES
    return new_index, n_slots


@njit(cache=True)
def pack_nodes(node_meta, split_bits, node_start, node_count, new_index, n_slots):
    """The (2 * n_slots, 2) int32 traversal array of the blocked layout (module docstring).

    ``split_bits`` is the float32 split array viewed as int32. Padding slots are empty
    leaves. Rows ``n_slots + slot`` hold ``(start, count)`` of interior nodes with triangles.
    """
    packed = np.zeros((2 * n_slots, 2), np.int32)
    packed[:n_slots, 0] = LEAF  # padding: empty leaves, never reached
    for node in range(node_meta.shape[0]):
        slot = new_index[node]
        meta = node_meta[node]
        if meta == LEAF:
            packed[slot, 0] = (node_count[node] << 2) | LEAF
            packed[slot, 1] = node_start[node]
        else:
            flag = HAS_TRIANGLES if node_count[node] > 0 else 0
            packed[slot, 0] = (new_index[meta >> 2] << 3) | flag | (meta & 3)
            packed[slot, 1] = split_bits[node]
            packed[n_slots + slot, 0] = node_start[node]
            packed[n_slots + slot, 1] = node_count[node]
    return packed


# numba's cache checks this file only; recompile when a module inlined from here changes.
drop_stale_kernel_cache(sys.modules[__name__], _kdtree_build)
