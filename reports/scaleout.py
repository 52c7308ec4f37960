"""Scale-out: dataset throughput on 1 and 2 local Dask workers, and the ``paper`` datasets' projected wall time.

How to use::

    from reports import scaleout
    metrics = scaleout.generate(config, "quick", Path("results/quick"))   # writes scaleout.md

Two measurements, in one run:

1. **Throughput.** The first reconstruction scene's dataset under the profile's
   reconstruction profile, with enough camera positions for ``[distributed]
   scaleout_views`` candidate views, is generated on an embedded LocalCluster of 1 and
   then of 2 worker processes (one compute thread each), each time into an empty folder.
   Workers are warmed first (KD-tree, numba kernels, Mitsuba variant), so the timed
   part is rendering and writing views. Views/s and their ratio are reported, and the
   two datasets are checked to be identical bit for bit.
2. **Projection.** For every scene the ``paper`` profile makes a dataset of (its
   ``reconstruction_scenes`` and ``unseen_scene``), single-thread seconds per view are
   modelled from frames of the scene's default camera at ``calibration_size``, timed in
   CPU seconds (one thread each, so a shared machine's load does not inflate them):
   the noisy render at the profile's spp at that side and twice it (fixed + per-pixel
   cost), and the Mitsuba reference at the two ``calibration_spp`` (fixed + per-sample
   cost). The model is evaluated at the ``paper`` reconstruction profile's size, spp and
   reference spp, times its positions x views, assuming every view is accepted (an
   upper bound). Wall time on N cores divides the core-seconds by N (ideal) and by N
   times the measured 2-worker efficiency (ratio / 2), never below one view's time.
   Network and shared-storage costs are not modelled.

Speed is only a ratio within this run; seconds appear as the projection's unit.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from kdtrace.cache import atomic_write_bytes, cache_root, content_key
from kdtrace.config import (
    DEFAULT_CONFIG,
    Config,
    DistributedConfig,
    ReconstructionProfile,
)
from kdtrace.markdown import markdown_table
from kdtrace.provenance import stamp
from kdtrace.timing import timed
from reports.metrics import Metric, write_metrics
from reports.notes import ReportNote

#: Metric names (stable).
THROUGHPUT_METRIC = "scaleout/dataset/two_over_one_worker_throughput"
CONCURRENCY_METRIC = "scaleout/dataset/two_worker_concurrency"
#: Bump when what ``scaleout.json`` holds changes: older files are measured again.
RESULT_VERSION = 2


def _warm(scene: Any, profile: ReconstructionProfile) -> None:
    """Render one view without writing it: loads kernels, the KD-tree and the Mitsuba variant (on a worker)."""
    from reconstruction.data import _render_view, candidate_views

    _render_view(scene, candidate_views(scene, profile)[0], profile)


def throughput_profile(profile: ReconstructionProfile, views: int) -> ReconstructionProfile:
    """``profile`` with enough positions for at least ``views`` candidate views."""
    return dataclasses.replace(profile, positions=max(1, math.ceil(views / profile.views_per_position)))


def measure_throughput(scene_name: str, profile: ReconstructionProfile, workers: tuple[int, ...] = (1, 2),
                       progress: bool = False, config: DistributedConfig | None = None) -> dict[str, Any]:
    """Time dataset generation on LocalClusters of each size in ``workers``.

    Parameters
    ----------
    scene_name : str
    profile : ReconstructionProfile
        The dataset made each time (into a fresh temporary cache).
    workers : tuple of int
        Cluster sizes (worker processes, one compute thread each).
    progress : bool
        Progress bars.
    config : DistributedConfig, optional
        Timeouts and retries (default ``[distributed]``); the clusters always run one
        compute thread per worker and no dashboard.

    Returns
    -------
    dict
        ``views`` (candidate views per run), ``runs`` (per size: workers, seconds,
        views_per_second, distinct workers used, the 1-minute load average just before, and
        concurrency: the units' summed wall seconds over the run's, which stays near the
        worker count when scheduling costs little even if other load slows every unit) and ``identical`` (every run produced
        the same arrays as the first, bit for bit).

    Notes
    -----
    Environment: ``KDTRACE_CACHE`` points to a temporary folder during each run (workers
    inherit it when they start) and is restored afterwards.
    """
    from kdtrace.distributed import connect
    from kdtrace.scenes import load_scene
    from reconstruction.data import BUFFERS, generate_dataset

    scene = load_scene(scene_name)
    config = dataclasses.replace(config or DEFAULT_CONFIG.distributed, threads_per_worker=1, dashboard_address="")
    runs, datasets = [], []
    previous = os.environ.get("KDTRACE_CACHE")
    with tempfile.TemporaryDirectory(prefix="kdtrace-scaleout-") as scratch:
        try:
            for count in workers:
                os.environ["KDTRACE_CACHE"] = str(Path(scratch) / f"workers-{count}")
                with connect("local", workers=count, config=config, announce=progress) as client:
                    client.wait_for_workers(count, timeout=120)
                    client.run(_warm, scene, profile)
                    load = os.getloadavg()[0]
                    dataset, seconds = timed(lambda client=client: generate_dataset(scene, profile, progress=progress,
                                                                                    client=client, config=config))
                views = len(dataset.manifest["views"])
                busy = sum(view["unit_seconds"] for view in dataset.manifest["views"])
                runs.append({"workers": count, "seconds": seconds, "views_per_second": views / seconds,
                             "load_average_before": load, "concurrency": busy / seconds,
                             "workers_used": len({view["worker"] for view in dataset.manifest["views"]})})
                datasets.append({name: dataset.load_view(name) for name in dataset.views()})
        finally:
            if previous is None:
                os.environ.pop("KDTRACE_CACHE", None)
            else:
                os.environ["KDTRACE_CACHE"] = previous
    identical = all(other.keys() == datasets[0].keys()
                    and all(np.array_equal(other[name][b], datasets[0][name][b]) for name in other for b in BUFFERS)
                    for other in datasets[1:])
    return {"scene": scene_name, "views": len(dataset.manifest["views"]), "runs": runs, "identical": identical}


def _fit(x: tuple[float, float], y: tuple[float, float]) -> tuple[float, float]:
    """Intercept and slope of the line through two points (intercept clamped at 0)."""
    slope = max((y[1] - y[0]) / (x[1] - x[0]), 0.0)
    return max(y[0] - slope * x[0], 0.0), slope


def calibrate_scene(scene_name: str, target: ReconstructionProfile, size: int, spp: tuple[int, int]) -> dict[str, Any]:
    """Single-thread seconds of one ``target`` view of ``scene_name``, from timed small frames.

    Frames are timed in CPU seconds of this process (numba and Dr.Jit on one thread
    each): on a machine shared with other jobs that estimates what a free core takes
    better than wall seconds, which include waiting for the core.

    Parameters
    ----------
    scene_name : str
    target : ReconstructionProfile
        Supplies spp, max_depth, reference_spp and the frame size being projected to.
    size : int
        Side of the timed frames, pixels (the noisy render is also timed at ``2 * size``).
    spp : (int, int)
        Reference samples per pixel of the two timed references.

    Returns
    -------
    dict
        The fitted models (``noisy_fixed_s``, ``noisy_per_pixel_s``, ``reference_fixed_s``,
        ``reference_per_sample_s``: per pixel-sample) and ``noisy_s`` / ``reference_s``
        per projected view, seconds on one thread.
    """
    import numba

    from kdtrace.render import render
    from kdtrace.scenes import load_scene
    from reconstruction.data import _one_jit_thread, reference_variant
    from references.llvm import activate_variant
    from references.mitsuba import render_reference

    scene = load_scene(scene_name)
    previous = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        noisy = []
        for side in (size, size, 2 * size):  # the first call loads the kernels and the tree
            _, cpu_seconds = timed(lambda side=side: render(scene, spp=target.spp, max_depth=target.max_depth, seed=1,
                                                            width=side, height=side, aux=True), clock=time.process_time)
            noisy.append(cpu_seconds)
        variant = activate_variant(reference_variant(None))
        reference = []
        with _one_jit_thread():
            for count in (spp[0], *spp):
                _, cpu_seconds = timed(lambda count=count: render_reference(scene, spp=count, max_depth=target.max_depth, seed=1,
                                                                            width=size, height=size, cache=False,
                                                                            variant=variant), clock=time.process_time)
                reference.append(cpu_seconds)
    finally:
        numba.set_num_threads(previous)
    noisy_fixed, noisy_per_pixel = _fit((size * size, 4 * size * size), (noisy[1], noisy[2]))
    reference_fixed, per_spp = _fit(spp, (reference[1], reference[2]))
    per_sample = per_spp / (size * size)
    pixels = target.width * target.height
    return {"scene": scene_name, "variant": variant, "noisy_fixed_s": noisy_fixed, "noisy_per_pixel_s": noisy_per_pixel,
            "reference_fixed_s": reference_fixed, "reference_per_sample_s": per_sample,
            "noisy_s": noisy_fixed + noisy_per_pixel * pixels,
            "reference_s": reference_fixed + per_sample * pixels * target.reference_spp}


def project(calibration: list[dict[str, Any]], target: ReconstructionProfile, cores: tuple[int, ...],
            efficiency: float) -> list[dict[str, Any]]:
    """Projected wall time of every scene's ``target`` dataset on each core count.

    Returns
    -------
    list of dict
        Per core count: ``cores``, ``core_hours`` (all scenes), ``ideal_hours`` and
        ``measured_efficiency_hours`` (wall time, hours).
    """
    views = target.positions * target.views_per_position
    per_view = [row["noisy_s"] + row["reference_s"] for row in calibration]
    total = views * sum(per_view)
    longest = max(per_view)
    return [{"cores": n, "core_hours": total / 3600.0,
             "ideal_hours": max(total / n, longest) / 3600.0,
             "measured_efficiency_hours": max(total / (n * efficiency), longest) / 3600.0} for n in cores]


def _markdown(result: dict[str, Any], provenance: dict[str, Any]) -> str:
    throughput, target, made = result["throughput"], result["target"], result["dataset_profile"]
    machine = provenance["machine"]
    header = (f"# Scale-out ({result['profile']} profile)\n\n"
              f"Machine: {machine['cpu']}, {machine['cores']} cores, shared with other jobs (timings are noisy); "
              f"{machine['date']}. Speed is a ratio within this run.\n")
    measured = (f"## Dataset throughput, 1 and 2 local Dask workers\n\n"
                f"{throughput['views']} candidate views of `{throughput['scene']}` ({made['width']}x{made['height']}, "
                f"{made['spp']} spp, references {made['reference']} at {made['reference_spp']} spp), each run into "
                f"an empty folder after warming the workers; one compute thread per worker. Datasets identical bit "
                f"for bit: {'yes' if throughput['identical'] else 'NO'}. Concurrency: the views' summed seconds "
                f"over the run's wall seconds (near the worker count when the cluster keeps every worker busy; "
                f"the throughput ratio falls below it when other jobs take the cores).\n")
    runs = markdown_table(["workers", "views/s", "workers used", "concurrency", "load average before"],
                          [[str(run["workers"]), f"{run['views_per_second']:.2f}", str(run["workers_used"]),
                            f"{run['concurrency']:.2f}", f"{run['load_average_before']:.1f}"] for run in throughput["runs"]],
                          right_aligned=[True] * 5)
    projected = (f"## Projected wall time of the `paper` datasets\n\n"
                 f"Scenes: {', '.join(row['scene'] for row in result['calibration'])}; each "
                 f"{target['positions']} x {target['views_per_position']} views at {target['width']}x"
                 f"{target['height']}, {target['spp']} spp input, Mitsuba references at {target['reference_spp']} "
                 f"spp, every view assumed accepted. Per-view single-thread CPU seconds modelled from frames timed at "
                 f"{result['calibration_size']}x{result['calibration_size']} (see `reports/scaleout.py`).\n")
    per_scene = markdown_table(["scene", "Mitsuba variant", "noisy s/view", "reference s/view"],
                               [[row["scene"], row["variant"], f"{row['noisy_s']:.2f}", f"{row['reference_s']:.1f}"]
                                for row in result["calibration"]], right_aligned=[False, False, True, True])
    wall = markdown_table(["cores", "core-hours", "wall hours, ideal",
                           f"wall hours at the measured 2-worker efficiency ({result['efficiency']:.2f})"],
                          [[str(row["cores"]), f"{row['core_hours']:.1f}", f"{row['ideal_hours']:.2f}",
                            f"{row['measured_efficiency_hours']:.2f}"] for row in result["projection"]],
                          right_aligned=[True] * 4)
    caveat = ("Not modelled: scheduler and network overhead, shared-storage writes, views rejected for low "
              "coverage (which skip their reference), and the difference between the default camera and the "
              "sampled views.")
    lines = [header, measured, *runs.splitlines(), f"\n2 workers / 1 worker throughput: **{result['ratio']:.2f}**\n",
             projected, *per_scene.splitlines(), "", *wall.splitlines(), "", caveat]
    return "\n".join(lines) + "\n"


def generate(config: Config, profile_name: str, out_dir: str | Path, fresh: bool = False,
             progress: bool = True) -> list[Metric]:
    """Measure (or reuse) throughput and projection and write ``scaleout.md``.

    Parameters
    ----------
    config : Config
        Resolved configuration (``[distributed]`` settings, the profiles).
    profile_name : str
        Report profile: its reconstruction profile and first reconstruction scene are timed.
        The projection is always of the ``paper`` profile.
    out_dir : str or Path
        Writes ``scaleout.md``, ``scaleout.json`` (all figures, with provenance) and
        ``metrics/scaleout.json``.
    fresh : bool
        Measure again even when the cache holds a result of the same settings
        (``cache_root()/reports/scaleout-KEY.json``; reuse is noted in the report).
    progress : bool
        Progress bars and the cluster announcements.

    Returns
    -------
    list of Metric
        ``scaleout/dataset/two_over_one_worker_throughput`` (ratio: views/s on 2 workers over
        1) and ``scaleout/dataset/two_worker_concurrency`` (ratio: how busy the 2-worker
        cluster was kept, which other jobs on the machine do not lower).
    """
    out_dir = Path(out_dir)
    report = config.profile(profile_name)
    dataset_profile = throughput_profile(config.reconstruction.profile(report.reconstruction_profile),
                                         config.distributed.scaleout_views)
    paper = config.profile("paper")
    target = config.reconstruction.profile(paper.reconstruction_profile)
    scenes = list(dict.fromkeys([*paper.reconstruction_scenes, *([paper.unseen_scene] if paper.unseen_scene else [])]))
    settings = {"dataset_profile": dataclasses.asdict(dataset_profile), "target": dataclasses.asdict(target),
                "scenes": scenes, "scene": report.reconstruction_scenes[0],
                "distributed": dataclasses.asdict(config.distributed)}
    key = content_key("scaleout", RESULT_VERSION, settings)
    # The measurement is cached under the cache root, not in the (committed) report folder:
    # a fresh clone, such as CI's, measures again instead of gating a committed number.
    cached = cache_root() / "reports" / f"scaleout-{key[:24]}.json"
    result = None
    if not fresh and cached.is_file():
        result = json.loads(cached.read_text())
        warnings.warn(f"scale-out: reused the measurement of {result['provenance']['machine']['date']} "
                      f"({cached}; --fresh measures again)", ReportNote, stacklevel=2)
    if result is None:
        throughput = measure_throughput(settings["scene"], dataset_profile, (1, 2), progress, config.distributed)
        one, two = (run["views_per_second"] for run in throughput["runs"])
        ratio = two / one
        distributed = config.distributed
        calibration = [calibrate_scene(name, target, distributed.calibration_size, distributed.calibration_spp)
                       for name in scenes]
        efficiency = min(1.0, ratio / 2.0)
        result = {"key": key, "profile": profile_name, **settings, "throughput": throughput, "ratio": ratio,
                  "efficiency": efficiency, "calibration": calibration,
                  "calibration_size": distributed.calibration_size,
                  "projection": project(calibration, target, distributed.projection_cores, efficiency),
                  "provenance": stamp(config.to_dict(), profile=profile_name)}
        atomic_write_bytes(cached, json.dumps(result, indent=1, default=str).encode())
    atomic_write_bytes(out_dir / "scaleout.json", json.dumps(result, indent=1, default=str).encode())
    atomic_write_bytes(out_dir / "scaleout.md", _markdown(result, result["provenance"]).encode())
    if not result["throughput"]["identical"]:
        raise RuntimeError("the 1- and 2-worker datasets differ: the distributed path is not reproducible")
    scene = result["throughput"]["scene"]
    metrics = [Metric(THROUGHPUT_METRIC, "ratio", float(result["ratio"]),
                      f"views/s of {scene} dataset generation, 2 local workers over 1 (depends on other load)"),
               Metric(CONCURRENCY_METRIC, "ratio", float(result["throughput"]["runs"][1]["concurrency"]),
                      f"summed view seconds over wall seconds of the 2-worker {scene} run (at most 2)")]
    write_metrics(out_dir, "scaleout", metrics)
    return metrics
