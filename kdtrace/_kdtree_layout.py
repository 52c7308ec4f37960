"""numba kernel that packs a built KD-tree into the compact, cache-line-clustered node array.

The builder's arrays (``kdtrace._kdtree_build``: meta, split, start, count, 16 bytes per
node in build order) are what the statistics, the pull-up and the cache keep. Traversal
reads a second copy made here, because a random ray's traversal is bound by memory
latency, not arithmetic (measured on bunny, 2026-12-02: the same 100 rays repeated run
4.6x faster than 100,000 different ones):

- **8 bytes per node** (as pbrt's): word 0 = ``(payload << 3) | (has_refs << 2) | axis``
  with axis 3 for a leaf; word 1 = the float32 split (interior) or the first reference
  (leaf). ``payload`` is the left child's index (interior; the right child is next to
  it) or the reference count (leaf). An interior node that holds pulled-up triangles
  (the local-branch tree) sets ``has_refs`` and keeps its (start, count) in a side table
  read only then.
- **Treelets**: sibling pairs are laid out so that a pair and its descendants' pairs down
  to ``treelet_pairs`` pairs share one aligned block (8 pairs = 128 bytes: the two cache
  lines the L2 spatial prefetcher fetches together), filled breadth first; the pairs
  left over start their own blocks, depth first. A ray then crosses three levels per
  block fetched instead of about one.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from kdtrace._kdtree_build import LEAF

#: Bit set in word 0 of an interior node that holds triangles itself (local-branch tree).
HAS_REFS = 4
#: Bits of word 0 below the payload (axis or leaf in bits 0-1, HAS_REFS in bit 2).
PAYLOAD_SHIFT = 3
#: Largest payload (child index or reference count) word 0 can hold.
MAX_PAYLOAD = (1 << (31 - PAYLOAD_SHIFT)) - 1


@njit(cache=True)
def treelet_order(node_meta, treelet_pairs):
    """New slot of every node: pairs stay adjacent, treelets fill aligned blocks.

    Parameters
    ----------
    node_meta : (N,) int32
        Builder metadata (``(left << 2) | axis``, or ``LEAF``).
    treelet_pairs : int
        Sibling pairs per block (the root occupies the first pair's place of block 0).

    Returns
    -------
    slot : (N,) int64
        New index of each node; ``slot.max() + 1`` slots are needed (padding included).
    """
    n = node_meta.shape[0]
    slot = np.full(n, -1, np.int64)
    slot[0] = 0
    # Units: the root (as a pair with an empty second slot) and every sibling pair, named by
    # its first node (the root: 0). A stack of block roots, and a per-block breadth-first queue.
    stack = np.empty(n + 1, np.int64)
    queue = np.empty(n + 1, np.int64)
    sp = 0
    stack[sp] = 0
    sp += 1
    next_slot = 0
    while sp > 0:
        sp -= 1
        head = 0
        tail = 0
        queue[tail] = stack[sp]
        tail += 1
        base = next_slot
        placed = 0
        while head < tail:
            first = queue[head]
            head += 1
            if placed == treelet_pairs:
                # The block is full: the rest of the queue start blocks of their own.
                stack[sp] = first
                sp += 1
                continue
            members = 1 if first == 0 else 2
            for k in range(members):
                slot[first + k] = base + 2 * placed + k
                meta = node_meta[first + k]
                if meta != LEAF:
                    queue[tail] = meta >> 2
                    tail += 1
            placed += 1
        next_slot = base + 2 * treelet_pairs
    return slot


@njit(cache=True)
def pack_nodes(node_meta, node_split, node_start, node_count, slot, n_slots):
    """The 8-byte node array and the side table of interior nodes' own triangles, in ``slot`` order.

    Returns
    -------
    nodes : (n_slots, 2) int32
        Word 0 and word 1 (see the module docstring); padding slots are empty leaves.
    node_refs : (n_slots, 2) int32
        (start, count) of interior nodes with ``HAS_REFS``; zero elsewhere.
    """
    nodes = np.zeros((n_slots, 2), np.int32)
    nodes[:, 0] = LEAF
    node_refs = np.zeros((n_slots, 2), np.int32)
    split_bits = node_split.view(np.int32)
    for i in range(node_meta.shape[0]):
        s = slot[i]
        meta = node_meta[i]
        if meta == LEAF:
            nodes[s, 0] = (node_count[i] << PAYLOAD_SHIFT) | LEAF
            nodes[s, 1] = node_start[i]
        else:
            flag = HAS_REFS if node_count[i] > 0 else 0
            nodes[s, 0] = (np.int32(slot[meta >> 2]) << PAYLOAD_SHIFT) | flag | (meta & 3)
            nodes[s, 1] = split_bits[i]
            node_refs[s, 0] = node_start[i]
            node_refs[s, 1] = node_count[i]
    return nodes, node_refs
