"""Slow, obvious Python versions of the KD-tree pieces, used as test oracles."""

from __future__ import annotations

from kdtrace._kdtree_build import LEAF


def pull_up_reference(node_meta, node_start, node_count, refs):
    """Algorithm 3's pull-up with Python sets: per node, the triangles it holds."""
    held = [set(refs[s : s + c].tolist()) for s, c in zip(node_start, node_count, strict=True)]
    for node in range(len(node_meta) - 1, -1, -1):
        if node_meta[node] == LEAF:
            continue
        left = node_meta[node] >> 2
        shared = held[left] & held[left + 1]
        held[node] |= shared
        held[left] -= shared
        held[left + 1] -= shared
    return held


def leaves_reached(node_meta, node_start, node_count, refs):
    """For every leaf, the triangles stored on the path from the root to it (inclusive)."""
    result = {}
    stack = [(0, frozenset())]
    while stack:
        node, above = stack.pop()
        here = above | frozenset(refs[node_start[node] : node_start[node] + node_count[node]].tolist())
        if node_meta[node] == LEAF:
            result[node] = here
        else:
            left = node_meta[node] >> 2
            stack += [(left, here), (left + 1, here)]
    return result
