"""Run time against error, the presentation: plots, Markdown and CSV of the measured rows.

:func:`write_outputs` writes ``error_time.md`` (the headline table, then per scene its plot,
the reconstructions worse than their own input, the equal-error and equal-time tables),
``error_time.csv`` (every point), ``error_time/SCENE.png`` and ``error_time.provenance.json``
from the rows :mod:`reports.error_time` measures; the numbers come from
:mod:`reports.error_time_curves`.
"""

from __future__ import annotations

import io
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path

import pandas as pd
from tabulate import tabulate

from kdtrace.cache import atomic_write_bytes
from kdtrace.config import Config, ReconstructionProfile
from kdtrace.provenance import stamp
from kdtrace.timing import TIMING_REPEATS
from reports.error_time_curves import (
    DISPLAY_PSNR_THRESHOLDS,
    METHODS,
    PIPELINES,
    PSNR_THRESHOLDS,
    RENDERER,
    all_measured,
    common_seconds,
    denoising_methods,
    equal_error_table,
    equal_time_table,
    headline,
    losses_to_input,
    method_label,
    methods_of,
    plugin_method,
    speedup_cell,
)

#: Load average above the core count by more than this means other processes shared the CPU (the
#: measurement's own threads bring it to about the core count).
LOAD_MARGIN = 0.5


def load_note(rows: Sequence[dict]) -> str:
    """A sentence on the machine's 1-minute load average around the measurements (rows that recorded it)."""
    loads = [value for row in rows for value in row.get("load_average", [])]
    if not loads:
        return ""
    cores = os.cpu_count() or 1
    why = ("above the core count: other processes competed for the CPU and times are inflated, the networks' "
           "multi-threaded torch times most" if max(loads) > cores + LOAD_MARGIN
           else "at most the core count, which the measurement's own threads fill")
    return (f"1-minute load average before/after each scene's measurements: {min(loads):.1f}–{max(loads):.1f} on "
            f"{cores} cores ({why}). ")


def points_frame(rows: Sequence[dict]) -> pd.DataFrame:
    """All measured points of all scenes as one long table (the CSV)."""
    return pd.DataFrame([{"scene": row["scene"], **point} for row in rows for point in row["points"]])


def _format(value: float, digits: str) -> str:
    return "—" if value is None or not math.isfinite(value) else format(value, digits)


def plot_scene(row: dict, path: Path) -> Path:
    """Error against seconds of one scene, as a PNG (Agg): display-referred PSNR, HDR relMSE (log-log) and
    linear PSNR, one panel each, the legend below the panels so that it covers no data."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = pd.DataFrame(row["points"])
    panels = [(error, label) for error, label in (("display_psnr", "display PSNR (dB)"), ("relmse", "relMSE (HDR)"),
                                                  ("psnr", "linear PSNR (dB, clipped to [0, 1])")) if error in points]
    figure, axes = plt.subplots(1, len(panels), figsize=(5.0 * len(panels), 4.4), constrained_layout=True)
    for method in methods_of(points):
        group = points[points["method"] == method].sort_values("spp")
        if group.empty:
            continue
        style = ("-o" if method in PIPELINES else "--s" if method == "mitsuba" else "-^" if method in METHODS
                 else ":D")
        for axis, (error, _) in zip(axes, panels, strict=True):
            plot = axis.loglog if error == "relmse" else axis.semilogx
            plot(group["seconds"], group[error], style, label=method_label(method), markersize=4)
            first = group.iloc[0]
            axis.annotate(f"{first['spp']}", (first["seconds"], first[error]), fontsize=7, xytext=(3, 3),
                          textcoords="offset points")
    floor = row["reference"]
    for axis, (error, label) in zip(axes, panels, strict=True):
        if error == "relmse":
            axis.axhline(floor["relmse_floor"], color="grey", linewidth=0.8, linestyle=":", label="reference noise")
        elif error == "psnr" and math.isfinite(floor["psnr_ceiling"]):
            axis.axhline(floor["psnr_ceiling"], color="grey", linewidth=0.8, linestyle=":", label="reference noise")
        for threshold in (PSNR_THRESHOLDS if error == "psnr" else DISPLAY_PSNR_THRESHOLDS if error == "display_psnr"
                          else ()):
            axis.axhline(threshold, color="black", linewidth=0.5, alpha=0.4)
        axis.set(xlabel="seconds (render + reconstruction)", ylabel=label, title=f"{row['scene']}: {label}")
        axis.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="outside lower center", ncol=min(5, len(labels)), fontsize=7)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    return atomic_write_bytes(path, buffer.getvalue())


def scene_markdown(row: dict, recon: ReconstructionProfile) -> str:
    """One scene's section: plot link, headline, equal-error and equal-time tables."""
    points = pd.DataFrame(row["points"])
    name = row["scene"]
    reference = row["reference"]
    about = (f"{row['triangles']:,} triangles, {row['width']}x{row['height']}; reference: Mitsuba {reference['spp']} spp "
             f"({reference['variant']}), whose own noise gives relMSE ≈ {reference['relmse_floor']:.2g} and "
             f"PSNR ≈ {reference['psnr_ceiling']:.1f} dB (errors near these measure the reference).")
    lines = [f"## {name}", "", f"![{name}: error against seconds](error_time/{name}.png)", "", about, ""]
    for error, what, unit in (("display_psnr", "display PSNR", " dB"), ("flip", "FLIP", ""), ("psnr", "linear PSNR", " dB")):
        below = losses_to_input(points, error)
        if len(below):
            cells = [f"{method_label(m)} at {spp} spp ({d:+.3g}{unit})"
                     for m, spp, d in zip(below["method"], below["spp"], below["difference"], strict=True)]
            lines += [f"Worse than their own noisy input by {what}: {'; '.join(cells)}.", ""]
        elif f"input_{error}" in points:
            lines += [f"No reconstruction is worse than its own noisy input by {what} at any spp.", ""]
    if "weight" in points:
        blended = points[points["method"] == "kdtrace+denoiser-blend"].sort_values("spp")
        fitted = row.get("blend", {})
        validated = dict(zip(fitted.get("spp", []), fitted.get("weights", []), strict=True))
        limited_by = dict(zip(fitted.get("spp", []), fitted.get("limited_by", []), strict=True))

        def limit(spp: int, weight: float) -> str:
            if spp not in validated:
                return ""
            return " (frame cap)" if weight < validated[spp] else f" ({limited_by[spp]})"

        lines += ["Blend weights of the denoiser, min(w(spp), the frame's cap); w(spp) is fitted on the validation "
                  "views as the smallest of its linear, display and FLIP bounds (what set the weight in brackets): "
                  + ", ".join(f"{spp} spp {w:.2f}{limit(spp, w)}"
                              for spp, w in zip(blended["spp"], blended["weight"], strict=True))
                  + ".", ""]
    failures = {spec: status for spec, status in row.get("plugins", {}).items() if status != "ok"}
    if failures:
        lines += [f"Plug-in {spec}: {status}" + ("" if not len(points[points["method"] == plugin_method(spec)]) else
                                                  " (its points before the failure are shown)") + "."
                  for spec, status in failures.items()] + [""]
    reach = equal_error_table(points)
    mitsuba_max = float(points[points["method"] == "mitsuba"]["seconds"].max())
    # thresholds every method was measured against (a plug-in row may lack the display space)
    keys = [key for key in reach["mitsuba"] if all(key in cells for cells in reach.values())]
    header = ["method", *keys]
    order = methods_of(points)
    body = [[method_label(method), *(reach[method][key].cell() for key in keys)] for method in order]
    for pipeline in denoising_methods(order):
        body.append([f"speed-up of {method_label(pipeline)} over Mitsuba",
                     *(speedup_cell(reach["mitsuba"][key], reach[pipeline][key], mitsuba_max) for key in keys)])
    lines += ["Equal error: seconds to reach each threshold (display-referred PSNR, linear PSNR clipped to [0, 1], "
              "HDR relMSE).", "", tabulate(body, headers=header, tablefmt="github"), ""]
    grid = common_seconds(float(points["seconds"].min()), float(points["seconds"].max()))
    if grid:
        table = equal_time_table(points, grid)
        body = []
        for method in order:
            part = table[table["method"] == method]
            body.append([method_label(method), *(f"{_format(p, '.1f')} / {_format(r, '.2g')}"
                                            for p, r in zip(part["psnr"], part["relmse"], strict=True))])
        lines += ["Equal time: PSNR dB / relMSE at common seconds (interpolated; — outside the measured range).", "",
                  tabulate(body, headers=["method", *(f"{s:g} s" for s in grid)], tablefmt="github"), ""]
    return "\n".join(lines)


def headline_table(rows: Sequence[dict], recon: ReconstructionProfile) -> str:
    """Per scene and pipeline at the denoiser's spp: PSNR, seconds, and the speed-up at equal PSNR over
    brute force on the pipeline's own renderer and over brute-force Mitsuba."""
    body = []
    for row in rows:
        points = pd.DataFrame(row["points"])
        for pipeline in denoising_methods(methods_of(points)):
            if not ((points["method"] == pipeline) & (points["spp"] == recon.spp)).any():
                continue
            renderer = RENDERER.get(pipeline, "kdtrace")  # a plug-in denoiser runs after our path tracer
            shown = {error: headline(points, recon.spp, pipeline, error=error) for error in ("display_psnr", "relmse")
                     if all_measured(points, error, pipeline, "mitsuba")}
            own = headline(points, recon.spp, pipeline, renderer,
                           error="display_psnr" if all_measured(points, "display_psnr", pipeline, renderer) else "psnr")
            linear = headline(points, recon.spp, pipeline)
            body.append([row["scene"], method_label(pipeline),
                         f"{shown['display_psnr']['value']:.2f}" if "display_psnr" in shown else "—",
                         f"{linear['seconds']:.3g}", own["speedup"] if renderer == "kdtrace" else "(same)",
                         shown["display_psnr"]["speedup"] if "display_psnr" in shown else "—",
                         shown["relmse"]["speedup"] if "relmse" in shown else "—", linear["speedup"]])
    return tabulate(body, headers=["scene", f"pipeline at {recon.spp} spp", "display PSNR dB", "seconds",
                                   "speed-up over our brute force (display)", "over Mitsuba, equal display PSNR",
                                   "over Mitsuba, equal relMSE", "over Mitsuba, equal linear PSNR"], tablefmt="github")


def write_outputs(rows: Sequence[dict], config: Config, profile_name: str, out_dir: Path) -> None:
    """Write the Markdown, CSV, plots and provenance (each atomically); the gated metrics are :func:`reports.error_time.scene_metrics`'s."""
    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    provenance = stamp(config.to_dict(), profile=profile_name, seed=profile.seed)
    machine = provenance["machine"]
    for row in rows:
        plot_scene(row, out_dir / "error_time" / f"{row['scene']}.png")
    threads = rows[0] if rows else {}
    warned = sorted({w for row in rows for w in row["warnings"]})
    header = (
        f"# Run time against error ({profile_name} profile)\n\n"
        f"Machine: {machine['cpu']}, {machine['cores']} cores; {machine['numba_threads']} numba threads, "
        f"{threads.get('torch_threads', '?')} torch threads, {threads.get('mitsuba_threads', '?')} Dr.Jit threads "
        f"(Mitsuba {threads.get('mitsuba_variant', '?')}); OIDN picks its own thread count; {machine['date']}. "
        f"Frames {profile.sweep_width}x{profile.sweep_height} from each scene's camera, max_depth {recon.max_depth}, "
        f"spp {', '.join(map(str, profile.sweep_spp))}; reference Mitsuba {profile.sweep_reference_spp} spp. "
        f"Networks: reconstruction profile `{profile.reconstruction_profile}` (per-scene denoiser trained on "
        f"{recon.spp} spp inputs at {recon.width}x{recon.height}). Seed {profile.seed}.\n\n"
        "Seconds of a pipeline = render + reconstruction, warm: our render is the kernel's wall time (no scene "
        "packing, no compilation); Mitsuba's is `mi.render` plus the copy to NumPy with the scene already loaded, "
        "after one untimed warm-up render at the same spp; every reconstruction step is timed after a warm-up call. "
        f"Each time is the shortest of {TIMING_REPEATS} runs. {load_note(rows)}Absolute seconds depend on the machine; compare methods "
        "within this table only. PSNR on linear images clipped to [0, 1]; relMSE on HDR images "
        "(the superresolution output is clipped to [0, 1], so its relMSE includes clipping of bright pixels). "
        "Between measured points curves are interpolated (log-log for relMSE, PSNR over log seconds); outside them "
        "nothing is extrapolated: `≤ s` means the fastest measured point already meets the threshold, "
        "`not reached` that no measured point does.\n\n"
        + (f"Warnings during the run: {'; '.join(warned)}\n\n" if warned else "")
    )
    text = (header + f"## Headline: speed-up over brute-force Mitsuba at equal PSNR\n\n"
            f"Each pipeline at {recon.spp} spp (the denoiser's training spp, the paper's operating point) against the "
            f"seconds Mitsuba needs to reach the same PSNR on its measured curve.\n\n" + headline_table(rows, recon)
            + "\n\n" + "\n\n".join(scene_markdown(row, recon) for row in rows) + "\n")
    atomic_write_bytes(out_dir / "error_time.md", text.encode())
    atomic_write_bytes(out_dir / "error_time.csv", points_frame(rows).to_csv(index=False).encode())
    atomic_write_bytes(out_dir / "error_time.provenance.json", json.dumps(provenance, indent=1, default=str).encode())
