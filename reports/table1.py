"""Table 1 of the paper, regenerated: KD-tree sizes, build times, traversal speed, frame times.

For each scene of a profile: triangles; triangle references of the naive and the
local-branch tree (and the paper's, where the scene stands for one of the paper's);
tree bytes; build seconds; Mrays/s of both trees and of Embree on the same rays with
the same thread count (the primary rays of one frame, and incoherent rays); the
path-traced frame time (profile frame size and spp, warm, same seed) on the naive and
on the local-branch tree, beside the paper's 512x512 4 spp seconds; and the Embree
agreement check (unexplained and wrong disagreements must be 0).

Rows are written per scene as soon as they are done (atomically), so an interrupted
report resumes where it stopped; ``fresh=True`` recomputes. :func:`generate` returns the
gated metrics (:mod:`reports.metrics`) and writes them to ``metrics/table1.json``.

With a Dask scheduler (``kdtrace report --scheduler ADDRESS``, ``$KDTRACE_SCHEDULER`` or
``[distributed] scheduler``) the missing rows are measured as units of
:mod:`kdtrace.distributed`, one scene each, on the workers' own threads (the row records
the worker and its thread count; all ratios stay within one worker); the client writes
the rows, so a rerun skips every scene already measured. Without one, rows are measured
in this process on all its threads.

Plug-in accelerators (``kdtrace report --accelerator SPEC``, :mod:`reports.plugins`) get
a row per scene (:func:`plugin_row`: factory seconds, their optional ``stats``, Mrays/s
beside Embree on the same rays, the agreement check), always measured in this process,
after our rows, and cached apart in ``rows/table1-plugins/`` under a key holding the spec
and a hash of the plug-in's source; our own rows and their keys are the same with or
without plug-ins.
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
from kdtrace.provenance import machine
from kdtrace.rays import shadow_rays
from kdtrace.render import render, renderer_fingerprint
from kdtrace.scenes import load_scene
from kdtrace.timing import TIMING_ROUNDS, interleaved_seconds, paired_speedup, timed, timing_ray_sets
from references.agreement import OURS_EXACT, UNEXPLAINED, WRONG, check_scene, format_table
from references.embree import EmbreeIntersector
from reports import build_scaling, sensitivity
from reports.metrics import Metric, write_metrics
from reports.notes import ReportNote
from reports.paper_figures import TABLE1

#: Version of the row layout; rows measured with another version are measured again.
ROW_VERSION = 9
#: Frame renders per tree, in alternating order (naive-local, local-naive, ...): even, so
#: the order effect of back-to-back renders on a shared machine cancels.
FRAME_REPEATS = 4
#: Profile fields a row depends on (its cache key).
PROFILE_FIELDS = ("agreement_rays_per_kind", "timing_rays", "frame_width", "frame_height", "frame_spp", "seed")
#: The line of table1.md that links the production-scale table (``kdtrace production``) when it is there.
PRODUCTION_LINK = ("\nThe same measurements on a generated scene of ten million triangles (`kdtrace production`): "
                   "[table1_production.md](table1_production.md).\n")
#: Non-numeric columns left out of table1.csv.
TEXT_COLUMNS = ("agreement_table", "agreement_counts", "warnings")



def agreement_fields(agreement) -> dict:
    """A Table 1 row's agreement columns from a :func:`check_scene` table: ray count, unexplained,
    wrong and ours-exact totals, the formatted table and its records."""
    return {"agreement_rays": int(agreement["rays"].sum()), "unexplained": int(agreement[UNEXPLAINED].sum()),
            "wrong": int(agreement[WRONG].sum()), "ours_exact": int(agreement[OURS_EXACT].sum()),
            "agreement_table": format_table(agreement), "agreement_counts": agreement.to_dict("records")}

class CameraPackets:
    """A tree that traces rays as the path tracer traces its camera rays: 16 consecutive rays a packet."""

    def __init__(self, tree):
        self.tree = tree

    def intersect(self, origins, directions):
        return self.tree.intersect(origins, directions, packets=True)

    @property
    def last_counters(self):
        return self.tree.last_counters


def frame_times(scene, trees: dict, width: int, height: int, spp: int, max_depth: int, seed: int,
                repeats: int = FRAME_REPEATS) -> dict[str, float]:
    """Path-traced frame seconds on each tree, and the local-over-naive speed ratio.

    Each tree renders the same frame (same seed) ``repeats`` times, in alternating order;
    :func:`kdtrace.render.render` compiles and warms its kernel before it starts timing.
    The images of the two trees are compared afterwards (a timed render must be right):
    with the same seed they differ only where equally near triangles tie.

    Returns
    -------
    dict
        ``frame_seconds_naive``, ``frame_seconds_local`` (medians), ``frame_local_over_naive``
        (median over the alternating pairs of naive seconds / local seconds: > 1 when the
        local-branch tree renders faster), ``frame_paths`` and ``frame_differing_pixels``.
    """
    seconds: dict[str, list[float]] = {variant: [] for variant in VARIANTS}
    images = {}
    for index in range(repeats):
        for variant in (VARIANTS if index % 2 == 0 else VARIANTS[::-1]):
            result = render(scene, spp=spp, max_depth=max_depth, seed=seed, width=width, height=height,
                            aux=False, tree=trees[variant])
            seconds[variant].append(result.seconds)
            images[variant] = result
    naive, local = images["naive"], images["local"]
    if not (np.isfinite(naive.rgb).all() and np.isfinite(local.rgb).all()):
        raise RuntimeError(f"{scene.name}: a Table 1 frame holds NaN or inf radiance")
    return {"frame_seconds_naive": statistics.median(seconds["naive"]),
            "frame_seconds_local": statistics.median(seconds["local"]),
            "frame_local_over_naive": paired_speedup(seconds["naive"], seconds["local"]),
            "frame_paths": int(local.stats["paths"]),
            "frame_differing_pixels": int((naive.rgb != local.rgb).any(axis=-1).sum())}


def time_occlusion(scene, trees: dict, embree, profile) -> dict[str, float]:
    """Shadow-ray (any-hit) speed of both trees and Embree.

    The rays run from surface points to points on the lights (:func:`kdtrace.rays.shadow_rays`,
    ``timing_rays`` of them); their answers are checked against Embree by the agreement
    columns (the ``shadow`` ray kind of :func:`references.agreement.check_scene`).
    Returns ``occlusion_mrays_{naive,local,embree}`` and ``occlusion_local_over_embree``.
    """
    origins, directions, tmax = shadow_rays(scene, profile.timing_rays, profile.seed + 1)
    seconds = interleaved_seconds({**trees, "embree": embree}, origins, directions, tmax=tmax)
    row = {f"occlusion_mrays_{label}": len(origins) / statistics.median(timings) / 1e6
           for label, timings in seconds.items()}
    row["occlusion_local_over_embree"] = paired_speedup(seconds["embree"], seconds["local"])
    return row


def ray_speeds(scene, trees: dict, embree, profile, progress: tqdm | None = None) -> dict[str, float]:
    """Mrays/s of both trees and Embree on primary, incoherent and shadow rays, with the work per ray.

    Primary rays are one frame at the profile's size and spp, traced by our trees in camera
    packets as the path tracer traces them; incoherent and shadow rays are the profile's
    ``timing_rays`` (:func:`kdtrace.timing.timing_ray_sets`, :func:`time_occlusion`).

    Returns
    -------
    dict
        ``{kind}_mrays_{naive,local,embree}``, ``{kind}_nodes_per_ray_{variant}``,
        ``{kind}_tests_per_ray_{variant}``, ``{kind}_local_over_naive`` and
        ``{kind}_local_over_embree`` for ``kind`` in primary and incoherent, and the
        ``occlusion_*`` fields of :func:`time_occlusion`.
    """
    row: dict[str, float] = {}
    for kind, (origins, directions) in timing_ray_sets(scene, profile).items():
        if progress is not None:
            progress.set_postfix_str(f"{scene.name}: timing {kind} rays")
        # Camera rays in packets, as the path tracer traces them (same hits and counters).
        traced = {variant: CameraPackets(tree) for variant, tree in trees.items()} if kind == "primary" else trees
        seconds = interleaved_seconds({**traced, "embree": embree}, origins, directions)
        for label, timings in seconds.items():
            row[f"{kind}_mrays_{label}"] = len(origins) / statistics.median(timings) / 1e6
        for variant, tree in trees.items():  # the work behind the speed, from the last timed call
            work = tree.last_counters.mean()
            row[f"{kind}_nodes_per_ray_{variant}"] = work["nodes_per_ray"]
            row[f"{kind}_tests_per_ray_{variant}"] = work["tests_per_ray"]
        row[f"{kind}_local_over_naive"] = paired_speedup(seconds["naive"], seconds["local"])
        row[f"{kind}_local_over_embree"] = paired_speedup(seconds["embree"], seconds["local"])
    if progress is not None:
        progress.set_postfix_str(f"{scene.name}: timing occlusion rays")
    row.update(time_occlusion(scene, trees, embree, profile))
    return row


def scene_row(name: str, config: Config, profile_name: str, progress: tqdm) -> dict:
    """Measure one scene: tree statistics, throughput of both trees and Embree, frame times, agreement."""
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
        for key in ("nodes", "triangle_references", "interior_references", "tree_bytes", "traversal_bytes", "span_bytes",
                    "build_seconds", "max_depth", "sah_cost", "cache_hit"):
            row[f"{variant}_{key}"] = tree.stats[key]
    row["reference_reduction"] = 1.0 - row["local_triangle_references"] / row["naive_triangle_references"]
    row["batches_regrouped"] = bool(trees["local"].regroups)

    row.update(ray_speeds(scene, trees, embree, profile, progress))

    progress.set_postfix_str(f"{name}: frame {profile.frame_width}x{profile.frame_height} {profile.frame_spp} spp")
    with warnings.catch_warnings(record=True) as render_warnings:
        warnings.simplefilter("always")
        row.update(frame_times(scene, trees, profile.frame_width, profile.frame_height, profile.frame_spp,
                               config.render.max_depth, profile.seed))
    caught.extend(render_warnings)

    progress.set_postfix_str(f"{name}: Embree agreement")
    agreement = check_scene(scene, trees, profile.agreement_rays_per_kind, profile.seed, progress=False)
    row.update(agreement_fields(agreement))
    row["warnings"] = sorted({str(w.message) for w in caught})
    return row


def _row_key(name: str, config: Config, profile_name: str, threads: int | None = None) -> str:
    profile = config.profile(profile_name)
    return content_key("table1-row", ROW_VERSION, renderer_fingerprint(), name, config.kdtree.__dict__, config.render.__dict__,
                       {field: getattr(profile, field) for field in PROFILE_FIELDS},
                       numba.get_num_threads() if threads is None else threads)


def _row_path(out_dir: Path, name: str) -> Path:
    return Path(out_dir) / "rows" / f"{name}.json"


def _write_record(out_dir: Path, name: str, record: dict) -> None:
    """Save one scene's record atomically, as soon as it is measured (resumable runs)."""
    atomic_write_bytes(_row_path(out_dir, name), json.dumps(record, indent=1).encode())


def measure_record(name: str, config: Config, profile_name: str, progress: tqdm) -> dict:
    """Measure one scene's row on this process's threads: ``{key, threads, measured_at, row}``."""
    threads = numba.get_num_threads()
    row = scene_row(name, config, profile_name, progress)
    row["threads"] = threads
    return {"key": _row_key(name, config, profile_name, threads), "threads": threads,
            "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"), "row": row}


def _remote_record(shared: tuple[Config, str], name: str) -> dict:
    """Unit of work on a Dask worker: one scene's record (see :func:`measure_record`)."""
    config, profile_name = shared
    return measure_record(name, config, profile_name, tqdm(disable=True))


def cached_row(name: str, config: Config, profile_name: str, out_dir: Path, any_threads: bool = False) -> dict | None:
    """The saved record (``key``, ``measured_at``, ``row``) of ``name`` if it matches the configuration, else None.

    The thread count is part of the match: this process's, or with ``any_threads`` (rows
    measured on Dask workers) the one the record says it was measured with.
    """
    path = _row_path(out_dir, name)
    if not path.exists():
        return None
    saved = json.loads(path.read_text())
    threads = saved.get("threads") if any_threads else None
    return saved if saved.get("key") == _row_key(name, config, profile_name, threads) else None


def load_rows(config: Config, profile_name: str, out_dir: Path) -> list[dict]:
    """The finished rows of every scene of the profile, for reports built on Table 1.

    Raises
    ------
    FileNotFoundError
        When a scene has no row measured with this configuration (run Table 1 first).
    """
    names = config.profile(profile_name).scenes
    # any thread count: rows measured on Dask workers count too (agreement does not depend on it)
    records = {name: cached_row(name, config, profile_name, out_dir, any_threads=True) for name in names}
    missing = [name for name, record in records.items() if record is None]
    if missing:
        raise FileNotFoundError(f"no Table 1 row for {', '.join(missing)} in {Path(out_dir) / 'rows'} measured with "
                                f"this configuration; run the table1 part first (kdtrace report --parts table1)")
    return [records[name]["row"] for name in names]


# ------------------------------------------------------------------ plug-in accelerators
#: Version of the plug-in row layout; plug-in rows measured with another version are measured again.
PLUGIN_ROW_VERSION = 1
#: Keys of a plug-in's optional ``stats`` that Table 1 shows (blank when absent).
PLUGIN_STATS = ("references", "bytes", "nodes", "build_seconds")


def plugin_row(name: str, spec: str, config: Config, profile_name: str, progress: tqdm) -> dict:
    """Measure one plug-in accelerator on one scene, as our trees are measured in :func:`scene_row`.

    The factory's wall time (``load_seconds``), its ``stats`` (:data:`PLUGIN_STATS`),
    Mrays/s on the same primary and incoherent rays as our trees, interleaved round by
    round with Embree on as many threads (``plugin_over_embree``: median of the per-round
    speed ratios; the plug-in's answers are validated on the clock, as in the benchmarks),
    and the Embree agreement check on the same rays and classifier as our trees. A
    :class:`~kdtrace.plugins.PluginError` (the plug-in raised or returned invalid output)
    ends the measurement: the row then holds ``failed`` (``failed: MESSAGE``) and what was
    measured before.
    """
    from kdtrace.plugins import PluginError, load_accelerator
    from reports.plugins import failure

    profile = config.profile(profile_name)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(name)
    row: dict[str, object] = {"scene": name, "plugin": spec, "triangles": len(scene.triangles),
                              "threads": numba.get_num_threads()}
    try:
        progress.set_postfix_str(f"{name}: plug-in {spec}: factory")
        accelerator, row["load_seconds"] = timed(lambda: load_accelerator(spec, scene))
        stats = accelerator.stats
        for key in PLUGIN_STATS:
            value = stats.get(key)
            row[key] = float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None
        embree = EmbreeIntersector(scene, threads=numba.get_num_threads())
        for kind, (origins, directions) in timing_ray_sets(scene, profile).items():
            progress.set_postfix_str(f"{name}: plug-in {spec}: timing {kind} rays")
            seconds = interleaved_seconds({"plugin": accelerator, "embree": embree}, origins, directions)
            row[f"{kind}_mrays_plugin"] = len(origins) / statistics.median(seconds["plugin"]) / 1e6
            row[f"{kind}_mrays_embree"] = len(origins) / statistics.median(seconds["embree"]) / 1e6
            row[f"{kind}_plugin_over_embree"] = paired_speedup(seconds["embree"], seconds["plugin"])
        progress.set_postfix_str(f"{name}: plug-in {spec}: Embree agreement")
        agreement = check_scene(scene, {spec: accelerator}, profile.agreement_rays_per_kind, profile.seed, progress=False)
        row.update(agreement_fields(agreement))
    except PluginError as error:
        row["failed"] = failure(error)
    row["warnings"] = sorted({str(w.message) for w in caught})
    return row


def _plugin_key(name: str, spec: str, config: Config, profile_name: str) -> str:
    from kdtrace.plugins import ACCELERATOR_GROUP
    from reports.plugins import fingerprint

    profile = config.profile(profile_name)
    return content_key("table1-plugin-row", PLUGIN_ROW_VERSION, name, spec, fingerprint(spec, ACCELERATOR_GROUP),
                       {field: getattr(profile, field) for field in PROFILE_FIELDS}, numba.get_num_threads())


def _plugin_path(out_dir: Path, name: str, spec: str) -> Path:
    from reports.plugins import slug

    return Path(out_dir) / "rows" / "table1-plugins" / name / f"{slug(spec)}.json"


def cached_plugin_row(name: str, spec: str, config: Config, profile_name: str, out_dir: Path) -> dict | None:
    """The saved record of plug-in ``spec`` on ``name`` if its key matches (spec, plug-in source, profile, threads)."""
    path = _plugin_path(out_dir, name, spec)
    if not path.exists():
        return None
    saved = json.loads(path.read_text())
    return saved if saved.get("key") == _plugin_key(name, spec, config, profile_name) else None


def load_plugin_rows(config: Config, profile_name: str, out_dir: Path, specs: list[str]) -> list[dict]:
    """The Table 1 rows of plug-in accelerators ``specs`` on every scene (for the agreement part).

    A plug-in without a row measured with this configuration gets a ``failed`` row saying
    so (run the table1 part with the same ``--accelerator``), instead of an error that
    would stop our own rows too.
    """
    rows = []
    for spec in specs:
        for name in config.profile(profile_name).scenes:
            record = cached_plugin_row(name, spec, config, profile_name, out_dir)
            rows.append(record["row"] if record is not None else
                        {"scene": name, "plugin": spec, "failed": f"failed: no Table 1 row of plug-in {spec!r} on {name} "
                         "measured with this configuration; run the table1 part with the same --accelerator"})
    return rows


def plugin_rows(config: Config, profile_name: str, out_dir: Path, specs: list[str], fresh: bool,
                progress: bool) -> list[dict]:
    """Measure (or reuse) every plug-in's row on every scene, in this process; cached under ``rows/table1-plugins/``.

    A failed row is saved too (the agreement part shows it) but measured again on the next run.
    """
    names = list(config.profile(profile_name).scenes)
    pairs = [(spec, name) for spec in specs for name in names]
    rows, reused = [], []
    bar = tqdm(pairs, unit="row", desc=f"Table 1 plug-ins ({profile_name})", disable=not progress)
    for spec, name in bar:
        saved = None if fresh else cached_plugin_row(name, spec, config, profile_name, out_dir)
        if saved is not None and not saved["row"].get("failed"):
            reused.append(f"{spec} on {name} ({saved['measured_at']})")
            rows.append(saved["row"])
            continue
        row = plugin_row(name, spec, config, profile_name, bar)
        atomic_write_bytes(_plugin_path(out_dir, name, spec), json.dumps(
            {"key": _plugin_key(name, spec, config, profile_name), "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"),
             "row": row}, indent=1).encode())
        rows.append(row)
    if reused:
        warnings.warn(f"Table 1: reused {len(reused)} of {len(pairs)} plug-in rows measured earlier: {', '.join(reused)}"
                      " (--fresh measures again)", ReportNote, stacklevel=2)
    for row in rows:
        if row.get("failed"):
            warnings.warn(f"Table 1: plug-in {row['plugin']!r} on {row['scene']}: {row['failed']}", ReportNote, stacklevel=2)
    return rows


def plugin_metrics(rows: list[dict]) -> list[Metric]:
    """Gated metrics of plug-in rows: speed over Embree (``ratio``), wrong and unexplained hits, ``failed`` (``zero``).

    Named ``table1/SCENE/plugin:SPEC/...``; never part of a baseline (:mod:`reports.plugins`).
    """
    from reports.plugins import metric_name

    metrics = []
    for row in rows:
        def name(quantity: str, row=row) -> str:
            return metric_name("table1", row["scene"], row["plugin"], quantity)

        metrics.append(Metric(name("failed"), "zero", int(bool(row.get("failed"))), row.get("failed") or "ran"))
        if row.get("failed"):
            continue
        metrics += [
            Metric(name("over_embree_primary"), "ratio", float(row["primary_plugin_over_embree"]),
                   "Mrays/s plug-in / Embree, primary rays of one frame"),
            Metric(name("over_embree_incoherent"), "ratio", float(row["incoherent_plugin_over_embree"]),
                   "Mrays/s plug-in / Embree, random rays"),
            Metric(name("unexplained_disagreements"), "zero", int(row["unexplained"]),
                   f"of {row['agreement_rays']:,} ray comparisons with Embree"),
            Metric(name("wrong_hits"), "zero", int(row["wrong"]),
                   f"of {row['agreement_rays']:,} rays: the float64 oracle finds a nearer hit than the plug-in"),
        ]
    return metrics


def _cell(value, digits: int = 2, scale: float = 1.0) -> str:
    return "" if value is None or (isinstance(value, float) and not np.isfinite(value)) else f"{value / scale:,.{digits}f}"


def _seconds(value) -> str:
    return "" if value is None else f"{value:.3g}"


def plugin_markdown(rows: list[dict]) -> str:
    """The plug-in accelerators' rows of Table 1 as Markdown (blank where a plug-in's ``stats`` say nothing)."""
    lines = []
    for row in rows:
        failed = row.get("failed")
        lines.append({
            "scene": row["scene"], "plug-in": row["plugin"], "triangles": row.get("triangles", ""),
            "factory s": _seconds(row.get("load_seconds")), "build s (stats)": _seconds(row.get("build_seconds")),
            "references": _cell(row.get("references"), 0), "MB": _cell(row.get("bytes"), 2, 1e6),
            "nodes": _cell(row.get("nodes"), 0),
            "primary Mrays/s plug-in/Embree": ("" if "primary_mrays_plugin" not in row else
                                               f"{row['primary_mrays_plugin']:.3g} / {row['primary_mrays_embree']:.3g}"),
            "plug-in/Embree primary": _cell(row.get("primary_plugin_over_embree"), 3),
            "incoherent Mrays/s plug-in/Embree": ("" if "incoherent_mrays_plugin" not in row else
                                                  f"{row['incoherent_mrays_plugin']:.3g} / "
                                                  f"{row['incoherent_mrays_embree']:.3g}"),
            "plug-in/Embree incoherent": _cell(row.get("incoherent_plugin_over_embree"), 3),
            "unexplained / wrong vs Embree": ("" if "unexplained" not in row else
                                              f"{row['unexplained']} / {row['wrong']} of {row['agreement_rays']:,} ray comparisons"),
            "plug-in exact, Embree not": "" if "ours_exact" not in row else f"{row['ours_exact']:,}",
            "status": failed or "ok",
        })
    return tabulate(lines, headers="keys", tablefmt="github", disable_numparse=True)


def generate(config: Config, profile_name: str, out_dir: Path, fresh: bool = False, progress: bool = True,
             accelerators: list[str] | tuple[str, ...] = ()) -> list[Metric]:
    """Run (or resume) Table 1 for a profile; write table1.md, table1.csv and metrics/table1.json.

    Parameters
    ----------
    config : Config
        Resolved configuration; the profile's ``scenes`` are the rows.
    profile_name : str
        Profile from ``[profiles.*]`` of the configuration.
    out_dir : Path
        Output folder; rows are kept in ``out_dir / "rows"`` for resuming.
    fresh : bool
        Ignore finished rows and measure again.
    progress : bool
        Show a progress bar and print the table at the end.
    accelerators : sequence of str
        Plug-in accelerator specs (``kdtrace report --accelerator``): a row per plug-in
        and scene (:func:`plugin_row`), under "Plug-in accelerators" in table1.md and in
        ``table1_plugins.csv``. They are measured in this process after our rows, also
        when our rows go to Dask workers; their rows are cached apart
        (``rows/table1-plugins/``), so our rows' keys do not depend on them.

    Returns
    -------
    list of Metric
        Per scene: local/Embree speed on primary and incoherent rays and local/naive frame
        speed (``ratio``), unexplained and wrong Embree disagreements (``zero``), triangle references
        of both trees (``count``); and per plug-in :func:`plugin_metrics`.
    """
    from kdtrace.distributed import Unit, run_units, scheduler_address

    out_dir = Path(out_dir)
    names = list(config.profile(profile_name).scenes)
    address = scheduler_address(config=config.distributed)
    records, reused = {}, []
    for name in names:
        saved = None if fresh else cached_row(name, config, profile_name, out_dir, any_threads=address is not None)
        if saved is not None:
            reused.append(f"{name} ({saved['measured_at']})")
            records[name] = saved
    missing = [name for name in names if name not in records]
    if address is not None and missing:
        units = [Unit(f"table1-row-{name}-{_row_key(name, config, profile_name)[:16]}", (name,)) for name in missing]
        for name, result in zip(missing, run_units(units, _remote_record, address, shared=(config, profile_name),
                                                   progress=progress, description=f"Table 1 ({profile_name})",
                                                   config=config.distributed), strict=True):
            records[name] = result.value
            records[name]["row"]["worker"] = result.worker
            _write_record(out_dir, name, records[name])
    else:
        bar = tqdm(missing, unit="scene", desc=f"Table 1 ({profile_name})", disable=not progress)
        for name in bar:
            records[name] = measure_record(name, config, profile_name, bar)
            _write_record(out_dir, name, records[name])
    rows = [records[name]["row"] for name in names]
    if reused:
        message = f"Table 1: reused {len(reused)} of {len(names)} scene rows measured earlier: {', '.join(reused)} (--fresh measures again)"
        warnings.warn(message, ReportNote, stacklevel=2)
    table = pd.DataFrame(rows)
    extra = plugin_rows(config, profile_name, out_dir, list(accelerators), fresh, progress) if accelerators else []
    scaling = []
    scaling_scene = config.profile(profile_name).build_scaling_scene
    scaling_scene = scaling_scene if scaling_scene in names else ""  # --scenes without it: skipped
    if scaling_scene:
        record, scaling_reused = build_scaling.generate(config, scaling_scene, out_dir, fresh)
        if scaling_reused:
            warnings.warn(f"Table 1: reused the build scaling of {scaling_scene} measured {record['measured_at']} "
                          "(--fresh measures again)", ReportNote, stacklevel=2)
        scaling = build_scaling.metrics_of(record)
    sensitivity_rows, sensitivity_reused = sensitivity.generate(config, profile_name, out_dir, fresh, progress)
    if sensitivity_reused:
        warnings.warn(f"Table 1: reused the build-recipe rows of {', '.join(sensitivity_reused)} (--fresh measures again)",
                      ReportNote, stacklevel=2)
    write_outputs(table, config, profile_name, out_dir, extra, build_scaling_scene=scaling_scene,
                  sensitivity=bool(sensitivity_rows))
    if progress:
        print(table1_markdown(table))
        if extra:
            print(plugin_markdown(extra))
    metrics = table_metrics(rows) + plugin_metrics(extra) + scaling + sensitivity.metrics_of(sensitivity_rows)
    write_metrics(out_dir, "table1", metrics)
    return metrics


def table_metrics(rows: list[dict]) -> list[Metric]:
    """The gated metrics of Table 1 rows (see :func:`generate`)."""
    metrics = []
    for row in rows:
        prefix = f"table1/{row['scene']}"
        metrics += [
            Metric(f"{prefix}/local_over_embree_primary", "ratio", float(row["primary_local_over_embree"]),
                   "Mrays/s local-branch tree / Embree, primary rays of one frame"),
            Metric(f"{prefix}/local_over_embree_incoherent", "ratio", float(row["incoherent_local_over_embree"]),
                   "Mrays/s local-branch tree / Embree, random rays"),
            Metric(f"{prefix}/local_over_embree_occlusion", "ratio", float(row["occlusion_local_over_embree"]),
                   "Mrays/s local-branch tree / Embree, shadow rays (any hit) from surfaces to the lights"),
            Metric(f"{prefix}/local_over_naive_frame", "ratio", float(row["frame_local_over_naive"]),
                   "path-traced frame seconds naive / local-branch"),
            Metric(f"{prefix}/unexplained_disagreements", "zero", int(row["unexplained"]),
                   f"of {row['agreement_rays']:,} ray comparisons with Embree"),
            Metric(f"{prefix}/wrong_hits", "zero", int(row["wrong"]),
                   f"of {row['agreement_rays']:,} rays: the float64 oracle finds a nearer hit than ours"),
            Metric(f"{prefix}/triangle_references_naive", "count", int(row["naive_triangle_references"]),
                   "deterministic build"),
            Metric(f"{prefix}/triangle_references_local", "count", int(row["local_triangle_references"]),
                   "deterministic build"),
        ]
    return metrics


def _pair(a: float, b: float, digits: int = 2) -> str:
    return f"{a:.{digits}f} / {b:.{digits}f}"


def _work(row: dict, kind: str) -> str:
    """``nodes / tests`` per ray of the local-branch tree on one ray set (blank for rows without them)."""
    nodes, tests = row.get(f"{kind}_nodes_per_ray_local"), row.get(f"{kind}_tests_per_ray_local")
    return "" if nodes is None or tests is None else f"{nodes:.1f} / {tests:.1f}"


def table1_markdown(table: pd.DataFrame) -> str:
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
            "MB naive/local": _pair(row["naive_tree_bytes"] / 1e6, row["local_tree_bytes"] / 1e6, 1),
            "traversal MB naive/local": _pair(row["naive_traversal_bytes"] / 1e6, row["local_traversal_bytes"] / 1e6, 1),
            "span-corner MB naive/local": _pair(row["naive_span_bytes"] / 1e6, row["local_span_bytes"] / 1e6, 1),
            "build s naive/local": (_pair(row["naive_build_seconds"], row["local_build_seconds"])
                                    + (" (cached)" if row["local_cache_hit"] else "")),
            "primary Mrays/s naive/local/Embree": f"{row['primary_mrays_naive']:.2f} / {row['primary_mrays_local']:.2f} / "
                                                  f"{row['primary_mrays_embree']:.2f}",
            "incoherent Mrays/s naive/local/Embree": f"{row['incoherent_mrays_naive']:.2f} / {row['incoherent_mrays_local']:.2f} / "
                                                     f"{row['incoherent_mrays_embree']:.2f}",
            "shadow Mrays/s naive/local/Embree": (f"{row['occlusion_mrays_naive']:.2f} / {row['occlusion_mrays_local']:.2f} / "
                                                  f"{row['occlusion_mrays_embree']:.2f}"),
            "regrouped": "yes" if row.get("batches_regrouped") else "no",
            "local nodes / tests per ray, primary": _work(row, "primary"),
            "incoherent": _work(row, "incoherent"),
            "frame s naive/local": _pair(row["frame_seconds_naive"], row["frame_seconds_local"], 3),
            "paper frame s naive/local": _pair(paper["naive_frame_seconds"], paper["local_frame_seconds"]) if paper else "",
            "local/naive frame speed": f"{row['frame_local_over_naive']:.2f}",
            "paper local/naive speed": f"{paper['naive_frame_seconds'] / paper['local_frame_seconds']:.2f}" if paper else "",
            "unexplained / wrong vs Embree": f"{row['unexplained']} / {row['wrong']} of {row['agreement_rays']:,} ray comparisons",
            "ours exact, Embree not": f"{row['ours_exact']:,}",
        })
    return tabulate(lines, headers="keys", tablefmt="github")


def write_outputs(table: pd.DataFrame, config: Config, profile_name: str, out_dir: Path,
                  plugins: list[dict] | None = None, build_scaling_scene: str = "", sensitivity: bool = False) -> None:
    """Write table1.md and table1.csv atomically (and with plug-in rows, their section and table1_plugins.csv)."""
    profile = config.profile(profile_name)
    host = machine()
    header = (
        f"# Table 1 — KD-tree size and speed ({profile_name} profile)\n\n"
        f"Machine: {host['cpu']}, {host['cores']} cores, {host['numba_threads']} numba threads (Embree gets as "
        f"many threads); {host['date']}. Primary rays: one {profile.frame_width}x{profile.frame_height} frame at "
        f"{profile.frame_spp} spp (ray casting only, no shading; our trees trace them as the path tracer traces its "
        f"camera rays, pixel after pixel with each pixel's samples together, in packets of 16 consecutive "
        f"rays); incoherent rays: {profile.timing_rays:,} random "
        f"rays; shadow rays: {profile.timing_rays:,} any-hit rays from surface points to points on the lights. "
        f"Our trees trace the incoherent and shadow rays grouped by origin cell and direction octant on the scenes "
        f"marked \"regrouped\" (trees of at least {config.kdtree.regroup_min_bytes / 1e6:g} MB of traversal data and "
        f"triangle corners; the grouping's key, sort and copies are in the timed call; Embree traces the rays as "
        f"given). "
        f"Mrays/s are medians of {TIMING_ROUNDS} rounds after a warm-up, the three intersectors taking turns in each "
        f"round; local/Embree is the median of the per-round ratios. Frame seconds: the path tracer "
        f"(max_depth {config.render.max_depth}, no auxiliary buffers) renders the same "
        f"{profile.frame_width}x{profile.frame_height} {profile.frame_spp} spp frame on each tree, {FRAME_REPEATS} "
        f"times in alternating order after compilation and warm-up (medians); local/naive frame speed is the "
        f"median over those pairs of naive seconds / local seconds. The paper's seconds are 512x512 at 4 spp on "
        f"one core of its machine, so only the ratios compare. MB: the build's arrays (17 bytes a node, 4 a "
        f"reference), the measure of the paper's memory comparison; traversal MB: what the queries read (8-byte "
        f"nodes in cache-line blocks with a cold half of the same size for local-branch interior spans, padding "
        f"slots included, and the references); span-corner MB: the references' corners stored again in node "
        f"order (36 bytes a reference), which the vector triangle test reads (the scene's own triangle corners, "
        f"36 bytes a triangle, are in neither). Speeds are ratios within one run; seed "
        f"{profile.seed}. Provenance: provenance.json.\n\n"
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    text = header + table1_markdown(table) + "\n"
    if build_scaling_scene:
        text += (f"\nBuild seconds against triangle count, with the fitted slope ({build_scaling_scene}): "
                 "[table1_build.md](table1_build.md).\n")
    if sensitivity:
        text += ("\nThe local-branch tree under the paper's build recipe and under ours (reference reduction, memory, "
                 "local/naive speed): [table1_sensitivity.md](table1_sensitivity.md).\n")
    if (out_dir / "table1_production.md").is_file():  # written by `kdtrace production`, kept between runs
        text += PRODUCTION_LINK
    if plugins:
        text += ("\n## Plug-in accelerators\n\n"
                 "Each plug-in (`kdtrace report --accelerator SPEC`) on the same primary and incoherent rays as our "
                 f"trees, interleaved round by round with Embree ({TIMING_ROUNDS} rounds, medians; its answers are "
                 "validated on the clock, as in the benchmarks), measured in this process (not on Dask workers); "
                 "factory s: wall time of its factory on the scene; build s, references, MB, nodes: from its optional "
                 "`stats` (blank when it gives none); the agreement check uses the same rays, classifier and float64 "
                 "oracle as our trees. A plug-in that raised or returned invalid output shows `failed: ...`.\n\n"
                 + plugin_markdown(plugins) + "\n")
    atomic_write_bytes(out_dir / "table1.md", text.encode())
    columns = [column for column in TEXT_COLUMNS if column in table.columns]
    atomic_write_bytes(out_dir / "table1.csv", table.drop(columns=columns).to_csv(index=False).encode())
    if plugins:
        extra = pd.DataFrame(plugins)
        extra = extra.drop(columns=[column for column in TEXT_COLUMNS if column in extra.columns])
        atomic_write_bytes(out_dir / "table1_plugins.csv", extra.to_csv(index=False).encode())
