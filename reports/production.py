"""Table 1 at production scale: a generated scene of ten million triangles, against Embree.

The scene is :func:`kdtrace.procedural.instanced_scene` of ``[production]`` in the
configuration (copies of a shipped scan on a displaced terrain, from a seed; generated
every run, never stored). It goes through Table 1's measurements, in stages:

``scene``
    Generation seconds and the scene's size.
``build-naive``, ``build-local``
    Each tree built from scratch (no cache, after a small warm-up build): seconds, the peak
    growth of the process's resident memory during the build (:func:`kdtrace.resources.resident_peak`,
    which sees numba's allocations), the resident memory the finished tree keeps ready to
    trace, and its arrays' bytes (:mod:`reports.table1`'s MB columns; the paper's memory comparison). The build is
    serial, so its one-core and all-core seconds are the same number.
``embree``
    Embree's BVH of the same triangles (``rtcCommitScene`` on all cores, Embree's default):
    seconds, peak and kept resident memory, the same measure as ours.
``rays``
    Mrays/s of both trees and Embree on the profile's primary, incoherent and shadow rays,
    all on the same threads (:func:`reports.table1.ray_speeds`).
``agreement``
    The Embree agreement check (:func:`references.agreement.check_scene`, its disagreements
    judged by the float64 oracle) on ``agreement_rays_per_kind`` rays of each kind, and
    ``oracle_rays`` incoherent rays whose every answer is checked against the oracle.
``scaling``
    Build seconds of nested random subsets from 10 thousand to all the triangles
    (:func:`reports.build_scaling.measure`).

Each stage's record is written as soon as it ends (``rows/production/STAGE.json``, under a
key of the configuration, profile, thread count and code), so an interrupted run resumes at
the next stage; the trees are built again for the later stages then (a 10M-triangle tree is
not kept in the cache). Outputs: ``table1_production.md`` and ``.json``,
``table1_build_production.md`` / ``.csv`` and ``figures/build_scaling_production.png``.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from pathlib import Path

import numba
import numpy as np
from tqdm import tqdm

from kdtrace import oracle, procedural
from kdtrace.cache import atomic_write_bytes, content_key, source_fingerprint
from kdtrace.config import Config
from kdtrace.kdtree import VARIANTS, build_bytes, build_kdtree
from kdtrace.oracle import nearest_hits_fast
from kdtrace.procedural import instanced_scene, instanced_scene_bytes
from kdtrace.provenance import machine, stamp
from kdtrace.rays import random_rays
from kdtrace.render import renderer_fingerprint
from kdtrace.resources import require_memory, resident_peak
from kdtrace.scenes import load_scene
from references import agreement as classification
from references.agreement import AGREE, TIE, UNEXPLAINED, WRONG, TriangleGeometry, check_scene, compare_hits
from references.embree import EmbreeIntersector
from reports import build_scaling, table1

#: Version of the stage records' layout.
RECORD_VERSION = 1
#: The stages, in the order they run.
STAGES = ("scene", "build-naive", "build-local", "embree", "rays", "agreement", "scaling")
#: Bytes per triangle of Embree's BVH and mesh, an upper bound for the memory check.
EMBREE_BYTES_PER_TRIANGLE = 256
#: Bytes per triangle a finished tree keeps ready to trace (arrays, traversal copies, corners,
#: span corners), an upper bound for the memory check.
TREE_BYTES_PER_TRIANGLE = 512


def stage_key(config: Config, profile_name: str, stage: str) -> str:
    """The content key of one stage's record: what it measured with, and the code whose speed and answers
    it measured (the build, the traversal, the scene generator, the oracle and the agreement classes, as
    Table 1's rows are keyed; not the code that writes the tables)."""
    profile = config.profile(profile_name)
    return content_key("production", RECORD_VERSION, stage, config.production.__dict__, config.kdtree.__dict__,
                       {field: getattr(profile, field) for field in table1.PROFILE_FIELDS}, numba.get_num_threads(),
                       renderer_fingerprint(), source_fingerprint(procedural, oracle, classification))


def needed_bytes(triangles: int) -> int:
    """Upper bound of the memory a production run holds at its peak: the scene, one finished tree while the
    other is built, then both trees and Embree's BVH."""
    return (instanced_scene_bytes(triangles) + build_bytes(triangles)
            + (TREE_BYTES_PER_TRIANGLE + EMBREE_BYTES_PER_TRIANGLE) * triangles)


def oracle_sample(scene, trees: dict, rays: int, seed: int) -> dict[str, int]:
    """Every answer of both trees on ``rays`` incoherent rays checked against the float64 oracle.

    The oracle (:func:`kdtrace.oracle.nearest_hits_fast`: every ray against every triangle, in
    float64, watertight) takes the place of Embree in :func:`references.agreement.compare_hits`,
    so ``wrong`` counts rays where a tree missed a nearer hit than the one it returned.

    Returns
    -------
    dict
        ``oracle_rays`` and, per variant, ``oracle_agree_{variant}``, ``oracle_ties_{variant}``,
        ``oracle_wrong_{variant}`` and ``oracle_unexplained_{variant}``.
    """
    origins, directions = random_rays(scene, rays, seed)
    geometry = TriangleGeometry.of(scene)
    t, tri = nearest_hits_fast(scene.vertices, scene.triangles, origins, directions, skip=geometry.degenerate)
    exact = (t, tri, np.zeros(len(t)), np.zeros(len(t)))
    row = {"oracle_rays": rays}
    for variant, tree in trees.items():
        counts = compare_hits(scene, origins, directions, tree.intersect(origins, directions), exact,
                              geometry=geometry).counts()
        for name, label in (("agree", AGREE), ("ties", TIE), ("wrong", WRONG), ("unexplained", UNEXPLAINED)):
            row[f"oracle_{name}_{variant}"] = counts[label]
    return row


def ready_to_trace(tree):
    """``tree`` with everything its queries read made (the span corners are made on first use)."""
    tree.span_corners  # noqa: B018 - a cached property: made now, inside the memory measurement
    return tree


class Run:
    """One production run: the scene, the trees and Embree, made when a stage first needs them."""

    def __init__(self, config: Config, profile_name: str, progress: tqdm):
        self.config, self.profile, self.progress = config, config.profile(profile_name), progress
        self._scene = None
        self.trees: dict = {}
        self._embree = None

    def scene(self):
        if self._scene is None:
            settings = self.config.production
            self.progress.set_postfix_str(f"generating {settings.triangles:,} triangles")
            self._scene = instanced_scene(load_scene(settings.base_scene), settings.triangles, seed=settings.seed,
                                          terrain_cells=settings.terrain_cells)
        return self._scene

    def build(self, variant: str) -> dict:
        scene = self.scene()
        self.progress.set_postfix_str(f"building the {variant} tree")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # zero-area triangles: counted in the scene stage
            # compiled and warm first, so neither compilation nor its memory is measured
            ready_to_trace(build_kdtree(build_scaling.triangle_subset(scene, min(64, len(scene.triangles))), variant,
                                        self.config.kdtree, cache=False))
            tree, memory = resident_peak(lambda: ready_to_trace(build_kdtree(scene, variant, self.config.kdtree,
                                                                             cache=False)))
        self.trees[variant] = tree
        stats = {key: tree.stats[key] for key in ("nodes", "triangle_references", "tree_bytes", "traversal_bytes",
                                                    "span_bytes", "build_seconds", "max_depth", "sah_cost")}
        return {**stats, "peak_bytes": memory["peak_bytes"], "retained_bytes": memory["retained_bytes"],
                "peak_exact": memory["peak_exact"]}

    def tree(self, variant: str):
        if variant not in self.trees:
            self.build(variant)
        return self.trees[variant]

    def embree(self) -> tuple[EmbreeIntersector, dict]:
        self.progress.set_postfix_str("building Embree's BVH")
        intersector, memory = resident_peak(lambda: EmbreeIntersector(self.scene(), threads=numba.get_num_threads()))
        self._embree = intersector
        return intersector, memory

    def stage(self, stage: str) -> dict:
        """Measure one stage; its record's fields (see the module docstring)."""
        settings = self.config.production
        if stage == "scene":
            scene, memory = resident_peak(self.scene)
            return {"name": scene.name, "triangles": len(scene.triangles), "vertices": len(scene.vertices),
                    "zero_area_triangles": int(scene.degenerate_mask().sum()), "generate_seconds": memory["seconds"],
                    "scene_bytes": memory["retained_bytes"]}
        if stage.startswith("build-"):
            return self.build(stage.removeprefix("build-"))
        if stage == "embree":
            _, memory = self.embree()
            return {"commit_seconds": memory["seconds"], "peak_bytes": memory["peak_bytes"],
                    "retained_bytes": memory["retained_bytes"], "peak_exact": memory["peak_exact"]}
        trees = {variant: self.tree(variant) for variant in VARIANTS}
        if stage == "rays":
            embree = self._embree or self.embree()[0]
            return table1.ray_speeds(self.scene(), trees, embree, self.profile, self.progress)
        if stage == "agreement":
            self.progress.set_postfix_str("Embree agreement")
            agreement = check_scene(self.scene(), trees, settings.agreement_rays_per_kind, settings.seed,
                                    progress=False, embree=self._embree or self.embree()[0])
            self.progress.set_postfix_str(f"{settings.oracle_rays} rays against the float64 oracle")
            row = table1.agreement_fields(agreement)
            row.pop("agreement_counts")
            return {**row, **oracle_sample(self.scene(), trees, settings.oracle_rays, settings.seed + 1)}
        if stage == "scaling":
            self.trees.clear()  # the subsets' builds need the memory more
            self.progress.set_postfix_str("build scaling")
            sizes = [size for size in settings.scaling_sizes if size <= len(self.scene().triangles)]
            return build_scaling.measure(self.scene(), self.config, sizes, once_above_seconds=5.0)
        raise ValueError(f"unknown production stage {stage!r}; stages: {', '.join(STAGES)}")


def generate(config: Config, profile_name: str, out_dir: Path, fresh: bool = False, progress: bool = True) -> dict:
    """Run (or resume) every stage and write the production table; returns the stages' records by name.

    Raises
    ------
    kdtrace.resources.InsufficientMemoryError
        Before any work, when the run would not fit in the memory available.
    """
    out_dir = Path(out_dir)
    settings = config.production
    require_memory(needed_bytes(settings.triangles),
                   f"Table 1 at production scale ({settings.triangles:,} triangles: the scene, two KD-trees, "
                   "a build and Embree's BVH)", "lower [production] triangles")
    records: dict[str, dict] = {}
    bar = tqdm(STAGES, desc=f"production scale ({settings.triangles:,} triangles)", unit="stage",
               disable=not progress)
    run = Run(config, profile_name, bar)
    for stage in bar:
        path = out_dir / "rows" / "production" / f"{stage}.json"
        key = stage_key(config, profile_name, stage)
        saved = json.loads(path.read_text()) if path.is_file() and not fresh else None
        if saved is not None and saved.get("key") == key:
            records[stage] = saved
            continue
        measured = run.stage(stage)
        records[stage] = {"key": key, "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"),
                          "threads": numba.get_num_threads(), "load_average": [round(x, 2) for x in os.getloadavg()],
                          "machine": machine(), "row": measured}
        atomic_write_bytes(path, json.dumps(records[stage], indent=1, default=float).encode())
    bar.close()
    write_outputs(records, config, profile_name, out_dir)
    return records


def _mb(count: float) -> str:
    return f"{count / 1e6:,.0f}"


def table_markdown(records: dict[str, dict], config: Config, profile_name: str) -> str:
    """``table1_production.md``: the scene, memory, build, speed and correctness, each a short table."""
    scene, embree = records["scene"]["row"], records["embree"]["row"]
    builds = {variant: records[f"build-{variant}"]["row"] for variant in VARIANTS}
    rays, agreement = records["rays"]["row"], records["agreement"]["row"]
    profile = config.profile(profile_name)
    n = scene["triangles"]
    host = records["rays"]["machine"]
    lines = [
        f"# Table 1 at production scale: {n:,} triangles", "",
        f"`kdtrace production`: {scene['name']}, {config.production.triangles:,} triangles asked for "
        f"({scene['vertices']:,} vertices, {scene['zero_area_triangles']:,} of zero area), generated in "
        f"{scene['generate_seconds']:.1f} s from seed {config.production.seed} "
        f"(copies of {config.production.base_scene} on a {config.production.terrain_cells}² terrain; "
        "see docs/scenes.md). Machine: "
        f"{host['cpu']}, {records['rays']['threads']} threads on each side; load average before the ray timing "
        f"{records['rays']['load_average'][0]:.2f}. Measured {records['rays']['measured_at']}.", "",
        "## Memory and build", "",
        "Peak: the growth of the process's peak resident memory while the structure was built; kept: what it "
        "still holds after, ready to trace (ours: the tree, its traversal copies, the triangles' corners and the "
        "span corners; Embree: its BVH and its copy of the mesh). Arrays: the tree's own arrays (the paper's "
        "measure, Table 1's MB column). "
        "Our build is serial (one core); Embree builds on all cores, as it does by default.", "",
        "| structure | build s | peak MB | kept MB | kept bytes/triangle | arrays MB | triangle references |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for variant in VARIANTS:
        b = builds[variant]
        lines.append(f"| KD-tree, {variant} | {b['build_seconds']:.1f} | {_mb(b['peak_bytes'])} | "
                     f"{_mb(b['retained_bytes'])} | {b['retained_bytes'] / n:.0f} | {_mb(b['tree_bytes'])} | "
                     f"{b['triangle_references']:,} |")
    lines.append(f"| Embree BVH | {embree['commit_seconds']:.1f} | {_mb(embree['peak_bytes'])} | "
                 f"{_mb(embree['retained_bytes'])} | {embree['retained_bytes'] / n:.0f} | | |")
    saving = 1.0 - builds["local"]["tree_bytes"] / builds["naive"]["tree_bytes"]
    lines += ["", f"The local-branch tree's arrays are {saving:.1%} smaller than the naive tree's "
              f"(the paper: about 30%); it holds {1 - builds['local']['triangle_references'] / builds['naive']['triangle_references']:.1%} "
              "fewer triangle references.", "",
              "## Speed", "",
              f"Mrays/s, medians of interleaved rounds after a warm-up (Table 1's method): primary = one "
              f"{profile.frame_width}x{profile.frame_height} frame at {profile.frame_spp} spp; incoherent and "
              f"shadow = {profile.timing_rays:,} rays each.", "",
              "| rays | naive | local | Embree | local / Embree |", "|---|---:|---:|---:|---:|"]
    for kind, prefix in (("primary", "primary"), ("incoherent", "incoherent"), ("shadow (any hit)", "occlusion")):
        lines.append(f"| {kind} | {rays[f'{prefix}_mrays_naive']:.2f} | {rays[f'{prefix}_mrays_local']:.2f} | "
                     f"{rays[f'{prefix}_mrays_embree']:.2f} | {rays[f'{prefix}_local_over_embree']:.2f} |")
    lines += ["", "## Correctness", "",
              f"Embree agreement on {agreement['agreement_rays']:,} ray comparisons "
              f"({config.production.agreement_rays_per_kind:,} rays of each kind, each tree): "
              f"**{agreement['unexplained']} unexplained, {agreement['wrong']} wrong**; ours exact where Embree is "
              f"not: {agreement['ours_exact']:,}.", "",
              agreement["agreement_table"], "",
              f"Every answer on {agreement['oracle_rays']:,} incoherent rays against the float64 oracle (every ray "
              "against every triangle):", "",
              "| tree | agree | ties | wrong | unexplained |", "|---|---:|---:|---:|---:|"]
    for variant in VARIANTS:
        lines.append(f"| {variant} | {agreement[f'oracle_agree_{variant}']:,} | {agreement[f'oracle_ties_{variant}']:,} | "
                     f"**{agreement[f'oracle_wrong_{variant}']}** | {agreement[f'oracle_unexplained_{variant}']} |")
    sizes = [row["triangles"] for row in records["scaling"]["row"]["rows"]]
    lines += ["", f"Build seconds from {sizes[0]:,} triangles to {sizes[-1]:,}: "
              "[table1_build_production.md](table1_build_production.md).", ""]
    return "\n".join(lines)


def write_outputs(records: dict[str, dict], config: Config, profile_name: str, out_dir: Path) -> None:
    """``table1_production.md`` / ``.json`` and the build-scaling table and figure, atomically."""
    scaling = records["scaling"]
    build_scaling.write_outputs({**scaling["row"], "measured_at": scaling["measured_at"], "machine": scaling["machine"]},
                                out_dir, stem="table1_build_production", figure="build_scaling_production")
    atomic_write_bytes(out_dir / "table1_production.md", table_markdown(records, config, profile_name).encode())
    summary = stamp(config.to_dict(), profile=profile_name,
                    stages={stage: record["row"] for stage, record in records.items() if stage != "scaling"})
    atomic_write_bytes(out_dir / "table1_production.json", json.dumps(summary, indent=1, default=float).encode())
