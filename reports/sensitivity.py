"""Under which tree do the paper's local-branch claims hold? Table 1 under two build recipes.

The paper reports 27-34% fewer triangle references and 13-40% faster traversal for the
local-branch tree over the naive one. Both depend on the tree the pull-up starts from, so
each scene of the profile's ``sensitivity_scenes`` is built twice over:

``paper``
    The paper's recipe (§2, Algorithm 1): split axis cycled by depth (``axis_selection =
    "cycle"``), planes tried through the triangles' centroids (``split_candidates =
    "centroids"``), no empty-space bonus; its Terminate rule (leaf when the best split
    costs more than ``K_I * T``) and our K_T, K_I and leaf size (the paper tunes them per
    scene and does not give them).
``ours``
    The configured build (``[kdtree]``: full SAH over all three axes at every triangle
    bound, empty bonus).

For each recipe the naive and local-branch trees' references, bytes and speed on the
Table 1 ray sets (one primary frame, the incoherent rays) are measured, the four trees
taking turns in every timed round (:func:`kdtrace.timing.interleaved_seconds`); local/naive
is the median of the per-round ratios. Frames are not path traced here (Table 1 does that
for ``ours``).

Written to ``table1_sensitivity.md`` and ``table1_sensitivity.csv``; rows are cached in
``rows/sensitivity/SCENE.json`` under a key of both recipes, the ray settings and the
source of the builder and traversal.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import time
from pathlib import Path

import pandas as pd
from tabulate import tabulate
from tqdm import tqdm

from kdtrace import _kdtree_build, _kdtree_layout, _kdtree_traverse
from kdtrace.cache import atomic_write_bytes, content_key, source_fingerprint
from kdtrace.config import Config, KDTreeConfig
from kdtrace.kdtree import VARIANTS, build_kdtree
from kdtrace.provenance import machine
from kdtrace.scenes import load_scene
from kdtrace.timing import interleaved_seconds, paired_speedup, timing_ray_sets
from reports.metrics import Metric
from reports.paper_figures import TABLE1

#: Version of the row layout; rows of another version are measured again.
ROW_VERSION = 1
RECIPES = ("paper", "ours")


def recipes(config: Config) -> dict[str, KDTreeConfig]:
    """The two build recipes: the paper's (see the module docstring) and the configured one."""
    paper = dataclasses.replace(config.kdtree, axis_selection="cycle", split_candidates="centroids", empty_bonus=0.0,
                                clip_triangles=False)
    return {"paper": paper, "ours": config.kdtree}


def _key(name: str, config: Config, profile_name: str) -> str:
    profile = config.profile(profile_name)
    return content_key("table1-sensitivity", ROW_VERSION, source_fingerprint(_kdtree_build, _kdtree_layout, _kdtree_traverse), name,
                       {recipe: dataclasses.asdict(c) for recipe, c in recipes(config).items()},
                       [profile.timing_rays, profile.frame_width, profile.frame_height, profile.frame_spp, profile.seed])


def measure_row(name: str, config: Config, profile_name: str) -> dict:
    """Build both recipes' trees for one scene and time them on Table 1's ray sets."""

    profile = config.profile(profile_name)
    scene = load_scene(name)
    trees = {(recipe, variant): build_kdtree(scene, variant, recipe_config)
             for recipe, recipe_config in recipes(config).items() for variant in VARIANTS}
    row: dict[str, object] = {"scene": name, "triangles": len(scene.triangles)}
    for (recipe, variant), tree in trees.items():
        row[f"{recipe}_{variant}_references"] = tree.stats["triangle_references"]
        row[f"{recipe}_{variant}_bytes"] = tree.stats["tree_bytes"]
        row[f"{recipe}_{variant}_nodes"] = tree.stats["nodes"]
    for recipe in RECIPES:
        row[f"{recipe}_reduction"] = 1.0 - row[f"{recipe}_local_references"] / row[f"{recipe}_naive_references"]
        row[f"{recipe}_memory_saving"] = 1.0 - row[f"{recipe}_local_bytes"] / row[f"{recipe}_naive_bytes"]
    labelled = {f"{recipe}/{variant}": tree for (recipe, variant), tree in trees.items()}
    for kind, (origins, directions) in timing_ray_sets(scene, profile).items():
        seconds = interleaved_seconds(labelled, origins, directions)
        for recipe in RECIPES:
            for variant in VARIANTS:
                row[f"{recipe}_{kind}_mrays_{variant}"] = len(origins) / statistics.median(seconds[f"{recipe}/{variant}"]) / 1e6
                work = trees[(recipe, variant)].last_counters.mean()
                row[f"{recipe}_{kind}_nodes_per_ray_{variant}"] = work["nodes_per_ray"]
                row[f"{recipe}_{kind}_tests_per_ray_{variant}"] = work["tests_per_ray"]
            row[f"{recipe}_{kind}_local_over_naive"] = paired_speedup(seconds[f"{recipe}/naive"], seconds[f"{recipe}/local"])
        row[f"{kind}_ours_over_paper_local"] = paired_speedup(seconds["paper/local"], seconds["ours/local"])
    return row


def generate(config: Config, profile_name: str, out_dir: Path, fresh: bool = False,
             progress: bool = True) -> tuple[list[dict], list[str]]:
    """Measure (or reuse) the rows of the profile's ``sensitivity_scenes`` that are among its
    ``scenes``, and write table1_sensitivity.md / .csv.

    Returns
    -------
    rows : list of dict
    reused : list of str
        ``"scene (measured at)"`` of the rows taken from ``rows/sensitivity/``.
    """
    profile = config.profile(profile_name)
    names = [name for name in profile.sensitivity_scenes if name in profile.scenes]
    out_dir = Path(out_dir)
    rows, reused = [], []
    for name in tqdm(names, unit="scene", desc=f"Table 1 sensitivity ({profile_name})", disable=not progress):
        path = out_dir / "rows" / "sensitivity" / f"{name}.json"
        key = _key(name, config, profile_name)
        saved = json.loads(path.read_text()) if path.exists() and not fresh else None
        if saved is not None and saved.get("key") == key:
            reused.append(f"{name} ({saved['measured_at']})")
            rows.append(saved["row"])
            continue
        row = measure_row(name, config, profile_name)
        record = {"key": key, "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": machine(), "row": row}
        atomic_write_bytes(path, json.dumps(record, indent=1).encode())
        rows.append(row)
    if rows:
        write_outputs(rows, config, out_dir)
    return rows, reused


def _percent(value: float) -> str:
    return f"{100 * value:.1f}%"


def sensitivity_markdown(rows: list[dict]) -> str:
    """One line per scene and recipe, the paper's claim beside them."""
    lines = []
    for row in rows:
        paper = TABLE1.get(row["scene"], {})
        for recipe in RECIPES:
            lines.append({
                "scene": row["scene"], "recipe": recipe,
                "refs naive / local": f"{row[f'{recipe}_naive_references']:,} / {row[f'{recipe}_local_references']:,}",
                "reduction": _percent(row[f"{recipe}_reduction"]),
                "paper reduction": (_percent(1 - paper["local_references"] / paper["naive_references"])
                                    if paper and recipe == "paper" else ""),
                "MB naive / local": f"{row[f'{recipe}_naive_bytes'] / 1e6:.2f} / {row[f'{recipe}_local_bytes'] / 1e6:.2f}",
                "memory saving": _percent(row[f"{recipe}_memory_saving"]),
                "local/naive primary": f"{row[f'{recipe}_primary_local_over_naive']:.2f}",
                "local/naive incoherent": f"{row[f'{recipe}_incoherent_local_over_naive']:.2f}",
                "paper local/naive frame": (f"{paper['naive_frame_seconds'] / paper['local_frame_seconds']:.2f}"
                                            if paper and recipe == "paper" else ""),
                "local Mrays/s primary / incoherent": (f"{row[f'{recipe}_primary_mrays_local']:.2f} / "
                                                       f"{row[f'{recipe}_incoherent_mrays_local']:.2f}"),
                "local nodes / tests per ray, incoherent": (f"{row[f'{recipe}_incoherent_nodes_per_ray_local']:.1f} / "
                                                            f"{row[f'{recipe}_incoherent_tests_per_ray_local']:.1f}"),
            })
    return tabulate(lines, headers="keys", tablefmt="github", disable_numparse=True)


def write_outputs(rows: list[dict], config: Config, out_dir: Path) -> None:
    """table1_sensitivity.md and table1_sensitivity.csv, atomically."""
    paper = recipes(config)["paper"]
    ours = config.kdtree
    text = ("# Table 1 — sensitivity to the build recipe\n\n"
            "Reference reduction, memory saving and local/naive traversal speed of the local-branch tree under the "
            f"paper's build recipe (axis = depth % 3, planes through triangle centroids, no empty bonus, leaf when "
            f"the best split costs more than K_I T; K_T = {paper.traversal_cost:g}, K_I = {paper.intersection_cost:g}, "
            f"leaves of <= {paper.min_leaf_size}) and under ours (SAH over {ours.axis_selection} axes at every "
            f"triangle bound, empty bonus {ours.empty_bonus:g}, the same K_T, K_I and leaf size). Speeds: Table 1's "
            "primary frame and incoherent rays, the four trees taking turns in each of its timed rounds; local/naive "
            "is the median of the per-round ratios (> 1: local faster). The paper's local/naive figure is its frame "
            "speed (Table 1 of the paper). Machine: "
            f"{machine()['cpu']}.\n\n" + sensitivity_markdown(rows) + "\n")
    atomic_write_bytes(out_dir / "table1_sensitivity.md", text.encode())
    atomic_write_bytes(out_dir / "table1_sensitivity.csv", pd.DataFrame(rows).to_csv(index=False).encode())


def metrics_of(rows: list[dict]) -> list[Metric]:
    """Per scene and recipe: both trees' references (``count``: deterministic builds) and
    local/naive speed on incoherent rays (``ratio``)."""
    metrics = []
    for row in rows:
        for recipe in RECIPES:
            prefix = f"table1_sensitivity/{row['scene']}/{recipe}"
            metrics += [Metric(f"{prefix}/triangle_references_{variant}", "count", int(row[f"{recipe}_{variant}_references"]),
                               "deterministic build") for variant in VARIANTS]
            metrics.append(Metric(f"{prefix}/local_over_naive_incoherent", "ratio",
                                  float(row[f"{recipe}_incoherent_local_over_naive"]),
                                  "Mrays/s local-branch / naive tree of the same recipe, random rays"))
    return metrics
