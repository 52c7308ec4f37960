"""Table 1's frame timing and gated metrics (reports/table1.py), on a tiny frame."""

from __future__ import annotations

import warnings

import pytest

from kdtrace import timing
from kdtrace.kdtree import VARIANTS, build_kdtree
from reports import table1


@pytest.fixture(scope="module")
def cbox():
    from kdtrace.scenes import load_scene

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = load_scene("cbox-original")
    return scene, {variant: build_kdtree(scene, variant) for variant in VARIANTS}


def test_frame_times_render_both_trees_alike(cbox):
    scene, trees = cbox
    times = table1.frame_times(scene, trees, 24, 16, 2, 3, seed=7, repeats=2)
    assert times["frame_paths"] == 24 * 16 * 2
    assert times["frame_seconds_naive"] > 0 and times["frame_seconds_local"] > 0
    assert times["frame_local_over_naive"] > 0
    # same seed, trees that find the same hits: at most a tie or two changes a path
    assert times["frame_differing_pixels"] <= 2


def test_metrics_of_a_row():
    row = {"scene": "s", "primary_local_over_embree": 0.5, "incoherent_local_over_embree": 0.25,
           "occlusion_local_over_embree": 0.75, "frame_local_over_naive": 1.1, "unexplained": 0, "wrong": 0,
           "agreement_rays": 10, "naive_triangle_references": 12,
           "local_triangle_references": 9}
    metrics = {m.name: m for m in table1.table_metrics([row])}
    assert {name: (m.kind, m.value) for name, m in metrics.items()} == {
        "table1/s/local_over_embree_primary": ("ratio", 0.5),
        "table1/s/local_over_embree_incoherent": ("ratio", 0.25),
        "table1/s/local_over_embree_occlusion": ("ratio", 0.75),
        "table1/s/local_over_naive_frame": ("ratio", 1.1),
        "table1/s/unexplained_disagreements": ("zero", 0),
        "table1/s/wrong_hits": ("zero", 0),
        "table1/s/triangle_references_naive": ("count", 12),
        "table1/s/triangle_references_local": ("count", 9),
    }


class _Recorder:
    """Stands in for an intersector: records the order of full-size calls."""

    def __init__(self, name, calls):
        self.name, self.calls = name, calls

    def intersect(self, origins, directions):
        if len(origins) > 64:
            self.calls.append(self.name)


def test_intersectors_take_turns_in_rotated_order():
    import numpy as np

    calls = []
    rays = np.zeros((100, 3))
    seconds = timing.interleaved_seconds({n: _Recorder(n, calls) for n in "abc"}, rays, rays, rounds=4)
    assert calls == list("abc" "bca" "cab" "abc")
    assert {n: len(s) for n, s in seconds.items()} == {"a": 4, "b": 4, "c": 4}


def test_occlusion_is_timed_with_shadow_rays_and_their_lengths(cbox):
    from types import SimpleNamespace

    import numpy as np

    scene, trees = cbox
    lengths = []

    class Embree:
        def occluded(self, origins, directions, tmax):
            lengths.append(np.asarray(tmax))
            return trees["local"].occluded(origins, directions, tmax)

    row = table1.time_occlusion(scene, trees, Embree(), SimpleNamespace(timing_rays=500, seed=3))
    assert set(row) == {"occlusion_mrays_naive", "occlusion_mrays_local", "occlusion_mrays_embree",
                        "occlusion_local_over_embree"}
    assert all(value > 0 for value in row.values())
    # every timed call gets the segment lengths (a shadow ray without them would hit the light)
    full = [t for t in lengths if t.size == 500]
    assert len(full) == timing.TIMING_ROUNDS and all(np.isfinite(t).all() and (t > 0).all() for t in full)


def test_paired_speedup_is_the_median_of_round_ratios():
    assert timing.paired_speedup([2.0, 9.0, 3.0], [1.0, 1.0, 3.0]) == 2.0
    with pytest.raises(ValueError):
        timing.paired_speedup([1.0], [1.0, 2.0])
