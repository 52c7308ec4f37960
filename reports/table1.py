"""Table 1 of the paper, regenerated: KD-tree sizes, build times, traversal speed.

For each scene of a profile: triangles; triangle references of the naive and the
local-branch tree (and the paper's, where the scene stands for one of the paper's);
tree bytes; build seconds; Mrays/s of both trees and of Embree on the same rays with
the same thread count (the primary rays of one frame, and incoherent rays); and the
Embree agreement check (unexplained disagreements must be 0).

Rows are written per scene as soon as they are done (atomically), so an interrupted
report resumes where it stopped; ``fresh=True`` recomputes.
"""

from __future__ import annotations

import json
import statistics
import time
import warnings
from pathlib import Path

import numba
import numpy as np
import pandas as pd
from tabulate import tabulate
from tqdm import tqdm

from kdtrace.cache import atomic_write_bytes, content_key
from kdtrace.config import Config
from kdtrace.kdtree import VARIANTS, build_kdtree
from kdtrace.provenance import stamp
from kdtrace.rays import camera_rays, random_rays
from kdtrace.scenes import load_scene
from references.agreement import UNEXPLAINED, check_scene, format_table
from references.embree import EmbreeIntersector
from reports.paper_figures import TABLE1

ROW_VERSION = 1


def mrays_per_second(intersector, origins, directions, repeats: int = 3) -> float:
    """Median throughput of ``intersect`` over ``repeats`` runs, after one warm-up call."""
    intersector.intersect(origins[:64], directions[:64])  # compile / commit, never timed
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        intersector.intersect(origins, directions)
        seconds.append(time.perf_counter() - started)
    return len(origins) / statistics.median(seconds) / 1e6


def scene_row(name: str, config: Config, profile_name: str, progress: tqdm) -> dict:
    """Measure one scene: tree statistics, throughput of both trees and Embree, agreement."""
    profile = config.profile(profile_name)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(name)
        progress.set_postfix_str(f"{name}: trees")
        trees = {variant: build_kdtree(scene, variant, config.kdtree) for variant in VARIANTS}
    embree = EmbreeIntersector(scene, threads=numba.get_num_threads())
    row: dict[str, object] = {"scene": name, "triangles": len(scene.triangles),
                              "zero_area_triangles": int(scene.degenerate_mask().sum())}
    for variant, tree in trees.items():
        for key in ("triangle_references", "interior_references", "tree_bytes", "build_seconds", "max_depth", "sah_cost", "cache_hit"):
            row[f"{variant}_{key}"] = tree.stats[key]
    row["reference_reduction"] = 1.0 - row["local_triangle_references"] / row["naive_triangle_references"]

    camera = scene.camera
    frame = [camera_rays(camera, profile.frame_width, profile.frame_height, jitter=True, rng=np.random.default_rng(profile.seed + s))
             for s in range(profile.frame_spp)]
    ray_sets = {
        "primary": tuple(np.concatenate([f[i] for f in frame]) for i in range(2)),
        "incoherent": random_rays(scene, profile.timing_rays, profile.seed),
    }
    for kind, (origins, directions) in ray_sets.items():
        progress.set_postfix_str(f"{name}: timing {kind} rays")
        for label, intersector in (*trees.items(), ("embree", embree)):
            row[f"{kind}_mrays_{label}"] = mrays_per_second(intersector, origins, directions)
        row[f"{kind}_local_over_naive"] = row[f"{kind}_mrays_local"] / row[f"{kind}_mrays_naive"]
        row[f"{kind}_local_over_embree"] = row[f"{kind}_mrays_local"] / row[f"{kind}_mrays_embree"]
    row["frame_seconds_naive"] = len(ray_sets["primary"][0]) / row["primary_mrays_naive"] / 1e6
    row["frame_seconds_local"] = len(ray_sets["primary"][0]) / row["primary_mrays_local"] / 1e6

    progress.set_postfix_str(f"{name}: Embree agreement")
    agreement = check_scene(scene, trees, profile.agreement_rays_per_kind, profile.seed, progress=False)
    row["agreement_rays"] = int(agreement["rays"].sum())
    row["unexplained"] = int(agreement[UNEXPLAINED].sum())
    row["agreement_table"] = format_table(agreement)
    row["warnings"] = sorted({str(w.message) for w in caught})
    return row


def _row_key(name: str, config: Config, profile_name: str) -> str:
    return content_key("table1-row", ROW_VERSION, name, config.kdtree.__dict__, config.profile(profile_name).__dict__)


def generate(config: Config, profile_name: str, out_dir: Path, scenes: list[str] | None = None, fresh: bool = False) -> pd.DataFrame:
    """Run (or resume) Table 1 for a profile and write Markdown, CSV and provenance.

    Parameters
    ----------
    config : Config
        Resolved configuration.
    profile_name : str
        Profile from ``[profiles.*]`` of the configuration.
    out_dir : Path
        Output folder; rows are kept in ``out_dir / "rows"`` for resuming.
    scenes : list of str, optional
        Subset of the profile's scenes.
    fresh : bool
        Ignore finished rows and measure again.
    """
    profile = config.profile(profile_name)
    names = list(scenes or profile.scenes)
    rows = []
    progress = tqdm(names, unit="scene", desc=f"Table 1 ({profile_name})")
    for name in progress:
        path = out_dir / "rows" / f"{name}.json"
        key = _row_key(name, config, profile_name)
        if not fresh and path.exists():
            saved = json.loads(path.read_text())
            if saved.get("key") == key:
                progress.write(f"{name}: reusing the row measured {saved['measured_at']} (pass --fresh to measure again)")
                rows.append(saved["row"])
                continue
        row = scene_row(name, config, profile_name, progress)
        record = {"key": key, "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"), "row": row}
        atomic_write_bytes(path, json.dumps(record, indent=1).encode())
        rows.append(row)
    table = pd.DataFrame(rows)
    write_outputs(table, config, profile_name, out_dir)
    return table


def markdown_table(table: pd.DataFrame) -> str:
    """Table 1 as Markdown: ours beside the paper's, with ratios."""
    lines = []
    for row in table.to_dict("records"):
        paper = TABLE1.get(row["scene"], {})
        lines.append({
            "scene": row["scene"] + (f" ({paper['paper_scene']})" if paper else ""),
            "triangles": row["triangles"],
            "paper triangles": paper.get("triangles", ""),
            "refs naive": row["naive_triangle_references"],
            "refs local": row["local_triangle_references"],
            "reduction": f"{100 * row['reference_reduction']:.1f}%",
            "paper reduction": f"{100 * (1 - paper['local_references'] / paper['naive_references']):.1f}%" if paper else "",
            "MB naive/local": f"{row['naive_tree_bytes'] / 1e6:.1f} / {row['local_tree_bytes'] / 1e6:.1f}",
            "build s naive/local": f"{row['naive_build_seconds']:.2f} / {row['local_build_seconds']:.2f}" + (" (cached)" if row["local_cache_hit"] else ""),
            "primary Mrays/s naive/local/Embree": f"{row['primary_mrays_naive']:.2f} / {row['primary_mrays_local']:.2f} / {row['primary_mrays_embree']:.2f}",
            "incoherent Mrays/s naive/local/Embree": f"{row['incoherent_mrays_naive']:.2f} / {row['incoherent_mrays_local']:.2f} / {row['incoherent_mrays_embree']:.2f}",
            "local/naive speed": f"{row['incoherent_local_over_naive']:.2f}",
            "paper local/naive speed": f"{paper['naive_frame_seconds'] / paper['local_frame_seconds']:.2f}" if paper else "",
            "unexplained vs Embree": f"{row['unexplained']} of {row['agreement_rays']:,} ray comparisons",
        })
    return tabulate(lines, headers="keys", tablefmt="github")


def write_outputs(table: pd.DataFrame, config: Config, profile_name: str, out_dir: Path) -> None:
    """Write table1.md, table1.csv, agreement.md and provenance.json atomically."""
    profile = config.profile(profile_name)
    provenance = stamp(config.to_dict(), profile=profile_name, seed=profile.seed)
    header = (
        f"# Table 1 — KD-tree size and speed ({profile_name} profile)\n\n"
        f"Machine: {provenance['machine']['cpu']}, {provenance['machine']['cores']} cores, "
        f"{provenance['machine']['numba_threads']} numba threads (Embree gets as many Python threads); "
        f"{provenance['machine']['date']}. Primary rays: one {profile.frame_width}x{profile.frame_height} "
        f"frame at {profile.frame_spp} spp (ray casting only, no shading); incoherent rays: "
        f"{profile.timing_rays:,} random rays. Speeds are medians of 3 runs after a warm-up; "
        f"ratios are within one run. Seed {profile.seed}. Versions: "
        + ", ".join(f"{k} {v}" for k, v in provenance["versions"].items()) + ".\n\n"
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out_dir / "table1.md", (header + markdown_table(table) + "\n").encode())
    atomic_write_bytes(out_dir / "table1.csv", table.drop(columns=["agreement_table", "warnings"]).to_csv(index=False).encode())
    agreement = "\n\n".join(f"## {row['scene']}\n\n{row['agreement_table']}" for row in table.to_dict("records"))
    atomic_write_bytes(out_dir / "agreement.md", f"# Agreement with Embree ({profile_name})\n\n{agreement}\n".encode())
    atomic_write_bytes(out_dir / "provenance.json", json.dumps(provenance, indent=1, default=str).encode())
