"""Cost of the watertight ray-triangle test against Möller–Trumbore, same tree, same rays.

Run: ``.venv/bin/python bench/compare_triangle_tests.py SCENE [SCENE ...]`` on an idle
machine. For each scene the local-branch tree answers 400,000 random and 400,000 camera
rays with each test (``KDTree.watertight`` switched on the same object, so the tree and
the rays are identical), after a warm-up that compiles both, in 7 rounds that alternate
which test goes first; then 11 rounds of a 256x256, 4 spp path-traced frame. It prints
the medians and watertight/MT speed (above 1: watertight faster), with the load average
before and after. Its figures are in ``bench/README.md``.
"""

from __future__ import annotations

import os
import statistics
import sys
import warnings

from kdtrace import rays
from kdtrace.kdtree import build_kdtree
from kdtrace.render import render
from kdtrace.scenes import load_scene
from kdtrace.timing import alternating_seconds, timed


def alternating_medians(run, rounds: int) -> tuple[float, float]:
    """Median wall seconds of ``run(watertight)`` for True and False, the order alternating per round."""
    for watertight in (True, False):
        run(watertight, warm_up=True)
    moller_trumbore, watertight = alternating_seconds(lambda: timed(lambda: run(False, warm_up=False))[1],
                                                      lambda: timed(lambda: run(True, warm_up=False))[1], rounds)
    return statistics.median(watertight), statistics.median(moller_trumbore)


def main(scene_names: list[str]) -> None:
    warnings.simplefilter("ignore")
    print(f"load average {os.getloadavg()}")
    for name in scene_names:
        scene = load_scene(name)
        tree = build_kdtree(scene, "local")
        ray_sets = {"random": rays.random_rays(scene, 400_000, 1)[:2]}
        if scene.cameras:
            ray_sets["primary"] = rays.primary_rays(scene, 400_000, 2)[:2]
        for kind, (origins, directions) in ray_sets.items():
            def trace(watertight, warm_up, tree=tree, origins=origins, directions=directions):
                tree.watertight = watertight
                count = 1000 if warm_up else len(origins)
                tree.intersect(origins[:count], directions[:count])

            wt, mt = alternating_medians(trace, 7)
            print(f"{name:18s} {kind:8s} watertight {len(origins) / wt / 1e6:6.2f} Mrays/s, "
                  f"MT {len(origins) / mt / 1e6:6.2f} Mrays/s, watertight/MT speed {mt / wt:.3f}")
        if scene.cameras:
            def frame(watertight, warm_up, tree=tree, scene=scene):
                tree.watertight = watertight
                size = 16 if warm_up else 256
                render(scene, spp=1 if warm_up else 4, width=size, height=size, seed=1, tree=tree)

            wt, mt = alternating_medians(frame, 11)
            print(f"{name:18s} frame    watertight {wt:.3f} s, MT {mt:.3f} s, watertight/MT speed {mt / wt:.3f}")
    print(f"load average {os.getloadavg()}")


if __name__ == "__main__":
    main(sys.argv[1:] or ["cbox-original", "cbox-sphere", "bunny", "crytek-sponza"])
