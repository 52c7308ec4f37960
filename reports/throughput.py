"""Renderer throughput: our path tracer's paths/s against Mitsuba 3's, in one run.

For each reconstruction scene of a profile (the scenes of the run-time-against-error sweep)
and each max_depth of :data:`DEPTHS`, both renderers render the scene's camera view at
:data:`SIZE` x :data:`SIZE` pixels and :data:`SPP` spp: Mitsuba's ``path`` integrator in its
vectorised LLVM backend on the scene :func:`references.mitsuba.to_mitsuba` builds
(:class:`reports.error_time.MitsubaTimer`), and our path tracer (local-branch tree, no
auxiliary buffers, the kernel's wall time). After one untimed render of each, :data:`ROUNDS`
rounds alternate the two (Mitsuba first in even rounds, ours first in odd ones, with a pause
after Mitsuba's render so that its worker threads are idle before ours start); the ratio of a
scene is the median over rounds of Mitsuba's seconds over ours, so the machine's drift between
rounds cancels. The project's targets (:data:`TARGETS`) stand beside the ratios.

Both renderers estimate the same image: each row records the mean radiance of both frames and
their difference in standard errors of ours (from our per-pixel variance, doubled for two
independent estimates); a difference beyond :data:`MEAN_SIGMAS` is a failed ``zero`` metric.

Rows are cached in ``OUT_DIR/rows/throughput/SCENE.json`` under the renderer's source
fingerprint (:func:`reports.error_time.scene_rows`); ``fresh=True`` measures again.
"""

from __future__ import annotations

import json
import statistics
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from tabulate import tabulate

from kdtrace.cache import atomic_write_bytes
from kdtrace.config import Config
from kdtrace.provenance import stamp
from kdtrace.timing import alternating_seconds, timed
from reports.error_time import MitsubaTimer, scene_rows
from reports.error_time_present import load_note
from reports.metrics import Metric, write_metrics
from reports.notes import ReportNote

#: The issue's frame (256x256, 8 spp, as its table of Mitsuba against ours).
SIZE, SPP = 256, 8
#: max_depth 1: camera rays and the emission they see; 3: one indirect bounce, the paper's setting.
DEPTHS = (1, 3)
#: The project's targets for ours / Mitsuba paths/s, per max_depth.
TARGETS = {1: 0.25, 3: 0.5}
ROUNDS = 5
#: Seconds to wait after a Mitsuba render before timing ours (Dr.Jit's threads spin briefly when idle).
PAUSE_SECONDS = 0.3
#: Largest allowed difference of the two frames' mean radiances, in standard errors.
MEAN_SIGMAS = 5.0
ROW_VERSION = 1


def measure_depth(scene, tree, depth: int, seed: int) -> dict:
    """Both renderers at one max_depth: Mpaths/s, the ratio over rounds and the image check."""
    from kdtrace.render import render

    mitsuba = MitsubaTimer(scene, depth, SIZE, SIZE)
    frames = {}

    def ours() -> float:
        frames["ours"] = render(scene, spp=SPP, max_depth=depth, seed=seed, width=SIZE, height=SIZE, tree=tree,
                                aux=False)
        return frames["ours"].seconds

    def theirs() -> float:
        frames["mitsuba"], seconds = timed(lambda: mitsuba.image(SPP, seed))
        return seconds

    theirs()  # compiles Mitsuba's kernels (ours were compiled by the scene's first render), untimed
    ours()
    their_seconds, ours_seconds = alternating_seconds(theirs, ours, ROUNDS, pause_after_first=PAUSE_SECONDS)
    ratios = [t / o for o, t in zip(ours_seconds, their_seconds, strict=True)]
    ours_frame, their_rgb = frames["ours"], frames["mitsuba"]
    pixels = ours_frame.rgb.shape[0] * ours_frame.rgb.shape[1]
    standard_error = np.sqrt(2.0 * ours_frame.variance.sum(axis=(0, 1))) / pixels
    difference = np.abs(ours_frame.rgb.mean(axis=(0, 1)) - their_rgb.mean(axis=(0, 1)))
    paths = SIZE * SIZE * SPP
    return {
        "ours_mpaths_per_second": paths / statistics.median(ours_seconds) / 1e6,
        "mitsuba_mpaths_per_second": paths / statistics.median(their_seconds) / 1e6,
        "ratio": statistics.median(ratios), "ratio_min": min(ratios), "ratio_max": max(ratios),
        "mean_difference_sigmas": float(np.max(difference / np.maximum(standard_error, 1e-12))),
        "last_ray_shortcut": ours_frame.stats["last_ray_shortcut"],
        "threads": ours_frame.stats["threads"], "mitsuba_threads": mitsuba.threads, "mitsuba_variant": mitsuba.variant,
    }


def measure_scene(name: str, config: Config, profile_name: str, models, bar) -> dict:
    """One scene's row (``models`` is unused: this part needs no network)."""
    from kdtrace.kdtree import build_kdtree
    from kdtrace.scenes import load_scene

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # loader remarks are the other parts' to report
        scene = load_scene(name)
    tree = build_kdtree(scene, "local")
    depths = {}
    for depth in DEPTHS:
        bar.set_postfix_str(f"{name}: max_depth {depth}")
        depths[str(depth)] = measure_depth(scene, tree, depth, config.profile(profile_name).seed)
    last = depths[str(DEPTHS[-1])]
    return {"scene": name, "width": SIZE, "height": SIZE, "spp": SPP, "rounds": ROUNDS, "depths": depths,
            "threads": last["threads"], "mitsuba_threads": last["mitsuba_threads"],
            "mitsuba_variant": last["mitsuba_variant"]}


def table(rows: list[dict]) -> pd.DataFrame:
    """One line per scene and max_depth."""
    lines = []
    for row in rows:
        for depth, cell in row["depths"].items():
            target = TARGETS[int(depth)]
            lines.append({
                "scene": row["scene"], "max_depth": int(depth),
                "ours Mpaths/s": round(cell["ours_mpaths_per_second"], 2),
                "Mitsuba Mpaths/s": round(cell["mitsuba_mpaths_per_second"], 2),
                "ours / Mitsuba": round(cell["ratio"], 3),
                "rounds' range": f"{cell['ratio_min']:.3f}–{cell['ratio_max']:.3f}",
                "target": target, "met": "yes" if cell["ratio"] >= target else "no",
                "mean radiance difference (σ)": round(cell["mean_difference_sigmas"], 2),
            })
    return pd.DataFrame(lines)


def generate(config: Config, profile_name: str, out_dir: str | Path, fresh: bool = False,
             progress: bool = True) -> list[Metric]:
    """Measure (or reuse) the throughput rows and write ``throughput.md``, ``throughput.csv``.

    Returns
    -------
    list of Metric
        Per scene and max_depth ``D``: ``throughput/SCENE/max_depth_D_kdtrace_over_mitsuba_paths_per_second``
        (ratio) and ``throughput/SCENE/max_depth_D_mean_radiance_mismatch`` (zero: 1 when the
        two frames' mean radiances differ by more than :data:`MEAN_SIGMAS` standard errors).
    """
    out_dir = Path(out_dir)
    rows = scene_rows("throughput", ROW_VERSION, measure_scene, config, profile_name, out_dir, fresh, progress,
                      networks=False)
    frame = table(rows)
    metrics = []
    for row in rows:
        for depth, cell in row["depths"].items():
            prefix = f"throughput/{row['scene']}/max_depth_{depth}"
            metrics.append(Metric(f"{prefix}_kdtrace_over_mitsuba_paths_per_second", "ratio", float(cell["ratio"]),
                                  f"median of {ROUNDS} alternating rounds, {SIZE}x{SIZE}, {SPP} spp"))
            mismatch = cell["mean_difference_sigmas"] > MEAN_SIGMAS
            metrics.append(Metric(f"{prefix}_mean_radiance_mismatch", "zero", int(mismatch),
                                  f"{cell['mean_difference_sigmas']:.2f} standard errors (limit {MEAN_SIGMAS})"))
            if mismatch:
                warnings.warn(f"throughput: {row['scene']} at max_depth {depth}: the two frames' mean radiances differ "
                              f"by {cell['mean_difference_sigmas']:.1f} standard errors", ReportNote, stacklevel=2)
    profile = config.profile(profile_name)
    provenance = stamp(config.to_dict(), profile=profile_name, seed=profile.seed)
    machine = provenance["machine"]
    first = rows[0] if rows else {}
    text = (f"# Renderer throughput: ours against Mitsuba 3 ({profile_name} profile)\n\n"
            f"Machine: {machine['cpu']}, {machine['cores']} cores; {first.get('threads', '?')} numba threads, "
            f"{first.get('mitsuba_threads', '?')} Dr.Jit threads (Mitsuba {first.get('mitsuba_variant', '?')}); "
            f"{machine['date']}. Each scene's camera view at {SIZE}x{SIZE}, {SPP} spp: our path tracer (local-branch "
            f"tree, no auxiliary buffers, the kernel's wall time) against Mitsuba's `path` integrator on the same scene "
            f"(`mi.render` and the copy to NumPy). After one untimed render of each, {ROUNDS} rounds alternate the two; "
            f"ours / Mitsuba is the median of the rounds' ratios of paths per second. Targets: the project's (at least "
            f"{TARGETS[1]} at max_depth 1, {TARGETS[3]} at max_depth 3). The last column checks that both estimate the "
            f"same image: the difference of their mean radiances in standard errors (limit {MEAN_SIGMAS}). Seed "
            f"{profile.seed}. {load_note(rows)}\n\n"
            + tabulate(frame, headers="keys", tablefmt="github", showindex=False) + "\n")
    atomic_write_bytes(out_dir / "throughput.md", text.encode())
    atomic_write_bytes(out_dir / "throughput.csv", frame.to_csv(index=False).encode())
    atomic_write_bytes(out_dir / "throughput.provenance.json", json.dumps(provenance, indent=1, default=str).encode())
    write_metrics(out_dir, "throughput", metrics)
    return metrics
