"""The paper's §6.4 combined pipeline, regenerated: render at half size, denoise, superresolve 2x.

For each reconstruction scene of a profile: our path tracer renders the scene's camera at
``combined_width/2 x combined_height/2`` with the denoiser's training spp (4, the
paper's), the scene's own denoiser removes the noise and the superresolution net brings
the frame to ``combined_width x combined_height``. The final frame is compared with a
Mitsuba reference of ``combined_reference_spp`` samples per pixel at the final size (PSNR
and RMSE on linear images clipped to [0, 1], the paper's §6 metrics).

Beside the final figures, each stage on its own, to test the paper's estimate ("adding
the RMSE of the denoising and superresolution RMSE's ... and solving for PSNR"):

* denoising: the denoised half-size frame against the reference reduced 2x (2x2 mean);
* superresolution: the net applied to the reduced *reference* against the reference;
* our estimate by the paper's rule, ``-20 log10(RMSE_denoise + RMSE_superres)``;
* bicubic upsampling instead of the net, for scale.

Seconds per stage are warm and the shortest of
:data:`kdtrace.timing.TIMING_REPEATS` runs (the render: the kernel's wall time; each
network: after a warm-up call on the same input). The paper's estimated PSNR and its
one-core total seconds (512x512 render from Table 1 + Table 6 network times) are printed
beside ours where our scene stands in for one of the paper's.

Rows are cached in ``OUT_DIR/rows/combined/SCENE.json`` by a content key and reused.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tabulate import tabulate
from tqdm import tqdm

from kdtrace.cache import atomic_write_bytes
from kdtrace.config import Config
from kdtrace.provenance import stamp
from kdtrace.timing import TIMING_REPEATS, shortest
from reports.error_time import (
    Reconstruction,
    denoise_frame,
    run_cli,
    scene_rows,
    superresolve_frame,
    timed_reconstruction,
)
from reports.error_time_present import load_note
from reports.metrics import Metric, write_metrics
from reports.paper_figures import (
    COMBINED_CBOX_MEASURED,
    COMBINED_ESTIMATES,
    COMBINED_SPP,
)

#: Bump when what a row measures changes: cached rows become stale.
ROW_VERSION = 2


def reduce2x(image: np.ndarray) -> np.ndarray:
    """2x2 box mean of an (H, W, C) image with even H and W (what a half-size render with a box filter sees)."""
    height, width = image.shape[:2]
    if height % 2 or width % 2:
        raise ValueError(f"reduce2x needs even sides, got {height}x{width}")
    return image.reshape(height // 2, 2, width // 2, 2, -1).mean(axis=(1, 3)).astype(np.float32)


def estimated_psnr(*rmses: float) -> float:
    """The paper's rough estimate of a chain's PSNR: ``-20 log10`` of the summed stage RMSEs (dB)."""
    total = float(sum(rmses))
    return math.inf if total == 0 else -20.0 * math.log10(total)


def quality(image: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """``psnr`` (dB) and ``rmse`` of the linear images clipped to [0, 1], and ``display_psnr``, ``display_rmse``
    and ``flip`` of the displayed images (the reference's exposure; :mod:`reconstruction.metrics`)."""
    from reconstruction.metrics import display_metrics, psnr, rmse

    shown = display_metrics(image, reference, name="the §6.4 reference")
    return {"psnr": psnr(image, reference), "rmse": rmse(image, reference), "display_psnr": shown["display_psnr"],
            "display_rmse": shown["display_rmse"], "flip": shown["flip"]}


def measure_scene(name: str, config: Config, profile_name: str, models: Reconstruction,
                  progress: tqdm | None = None) -> dict[str, Any]:
    """Run the pipeline on one scene and measure every stage (see the module docstring).

    Returns
    -------
    dict
        ``scene``, sizes, ``spp``, ``seconds`` (render, denoise, superres, total),
        ``final`` / ``bicubic`` / ``denoise_stage`` / ``superres_stage`` quality
        (``psnr`` dB, ``rmse``), ``estimated_psnr`` (the paper's rule), reference
        provenance and warnings.
    """
    from reconstruction.baselines import bicubic

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene, reference, half_frame, settings = _pipeline_inputs(name, config, profile_name, progress)
        width, height, spp, depth = settings
        if progress is not None:
            progress.set_postfix_str(f"{name}: pipeline")
        frame, render_seconds = shortest(half_frame, warmup=0, seconds_of=lambda result: result.seconds)
        denoiser, superres = models.denoisers[name], models.superres
        final, (denoise_seconds, superres_seconds) = timed_reconstruction(
            [lambda f: denoise_frame(denoiser, f), lambda d: superresolve_frame(superres, d)], frame)
        denoised = denoise_frame(denoiser, frame)
        reduced = reduce2x(reference.rgb)
        denoise_stage = quality(denoised, reduced)
        superres_stage = quality(superresolve_frame(superres, reduced), reference.rgb)
    return {
        "scene": name, "triangles": len(scene.triangles), "render_width": width // 2,
        "render_height": height // 2, "width": width, "height": height, "spp": spp, "max_depth": depth,
        "seconds": {"render": render_seconds, "denoise": denoise_seconds, "superres": superres_seconds,
                    "total": render_seconds + denoise_seconds + superres_seconds},
        "final": quality(final, reference.rgb),
        "bicubic": quality(bicubic(np.clip(denoised, 0.0, 1.0)), reference.rgb),
        "noisy_bicubic": quality(bicubic(np.clip(frame.rgb, 0.0, 1.0)), reference.rgb),
        "denoise_stage": denoise_stage, "superres_stage": superres_stage,
        "estimated_psnr": estimated_psnr(denoise_stage["rmse"], superres_stage["rmse"]),
        "estimated_display_psnr": estimated_psnr(denoise_stage["display_rmse"], superres_stage["display_rmse"]),
        "reference": {"spp": reference.spp, "variant": reference.variant, "seconds": reference.seconds},
        "warnings": sorted({str(w.message) for w in caught}),
    }


def _pipeline_inputs(name: str, config: Config, profile_name: str, progress: tqdm | None = None):
    """The scene, its Mitsuba reference at the final size and a half-size render of it (a callable).

    Returns ``(scene, reference, render_half_frame, (width, height, spp, max_depth))``;
    ``render_half_frame()`` renders the half-size 4-spp frame with auxiliary buffers
    (fixed seed: the same frame every call).
    """
    from kdtrace.kdtree import build_kdtree
    from kdtrace.render import render
    from kdtrace.scenes import load_scene
    from references.mitsuba import render_reference

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    width, height, spp, depth = profile.combined_width, profile.combined_height, recon.spp, recon.max_depth
    scene = load_scene(name)
    tree = build_kdtree(scene, "local", config.kdtree)
    if progress is not None:
        progress.set_postfix_str(f"{name}: reference {profile.combined_reference_spp} spp")
    reference = render_reference(scene, profile.combined_reference_spp, depth, profile.seed % 2**32, width, height)

    def render_half_frame():
        return render(scene, spp=spp, max_depth=depth, seed=profile.seed, width=width // 2, height=height // 2,
                      aux=True, tree=tree)

    return scene, reference, render_half_frame, (width, height, spp, depth)


#: Core tile side of the tiled denoising shown against the whole-frame result (Figure 8).
FIGURE_TILE = 64


def write_pipeline_figures(config: Config, profile_name: str, out_dir: Path) -> list[Path]:
    """Figure 8 per reconstruction scene: ``figures/SCENE-pipeline.png``, drawn by every run.

    Drawn again each time (a few seconds a scene), so that a figure never shows the networks
    of an earlier run beside this run's numbers.

    The stages of the pipeline at the final size (the half-size noisy render and the
    denoised frame, each upsampled bicubically; denoised + superresolved) beside the
    reference, and the denoiser evaluated in :data:`FIGURE_TILE`-pixel tiles minus the
    whole-frame evaluation (:func:`reports.figures.pipeline_panel`). The frame is
    re-rendered with the rows' seed (the same frame the rows measured).
    """
    from reconstruction.baselines import bicubic
    from reconstruction.inference import denoise
    from reports.figures import pipeline_panel

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    names = list(profile.reconstruction_scenes)
    paths, models = [], None
    for name in names:
        path = out_dir / "figures" / f"{name}-pipeline.png"
        if models is None:
            models = Reconstruction.load(names, recon, names, False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the rows record the run's warnings
            _, reference, half_frame, _ = _pipeline_inputs(name, config, profile_name)
            frame = half_frame()
        denoiser = models.denoisers[name]
        whole = denoise_frame(denoiser, frame)
        tiled = denoise(denoiser, frame.rgb, frame.albedo, tile=FIGURE_TILE)
        images = {"noisy, bicubic 2x": bicubic(np.clip(frame.rgb, 0.0, 1.0)),
                  "denoised, bicubic 2x": bicubic(np.clip(whole, 0.0, 1.0)),
                  "denoised + our SR": superresolve_frame(models.superres, whole)}
        pipeline_panel(images, reference.rgb, path, difference=(tiled, whole),
                       title=f"{name}: {frame.rgb.shape[1]}x{frame.rgb.shape[0]} {recon.spp} spp -> "
                             f"{reference.rgb.shape[1]}x{reference.rgb.shape[0]}",
                       reference_label=f"Mitsuba {reference.spp} spp")
        paths.append(path)
    return paths


def generate(config: Config, profile_name: str, out_dir: str | Path, fresh: bool = False,
             progress: bool = True) -> list[Metric]:
    """Run (or reuse) the §6.4 combined pipeline per scene and write its report.

    Arguments as for :func:`reports.error_time.generate`. Writes ``combined.md``,
    ``combined.csv``, ``combined.provenance.json`` and ``metrics/combined.json`` into
    ``out_dir``, rows into ``out_dir/rows/combined/``.

    Returns
    -------
    list of Metric
        Per scene, psnr kind (fixed seeds): ``combined/SCENE/psnr`` (the final frame) and
        ``combined/SCENE/denoise_stage_psnr``. No ratio: the pipeline has no same-run
        speed comparison (its speed against Mitsuba is gated by ``error_time``).
    """
    out_dir = Path(out_dir)
    rows = scene_rows("combined", ROW_VERSION, measure_scene, config, profile_name, out_dir, fresh, progress)
    figures = write_pipeline_figures(config, profile_name, out_dir)
    write_outputs(rows, config, profile_name, out_dir, figures)
    metrics = []
    for row in rows:
        metrics.append(Metric(f"combined/{row['scene']}/psnr", "psnr", row["final"]["psnr"],
                              f"dB, {row['render_width']}x{row['render_height']} {row['spp']} spp -> denoise -> SR "
                              f"{row['width']}x{row['height']} vs Mitsuba {row['reference']['spp']} spp"))
        metrics.append(Metric(f"combined/{row['scene']}/denoise_stage_psnr", "psnr", row["denoise_stage"]["psnr"],
                              "dB, denoised half-size frame vs the reference reduced 2x"))
        metrics.append(Metric(f"combined/{row['scene']}/display_psnr", "psnr", row["final"]["display_psnr"],
                              "display-referred dB of the final frame"))
    write_metrics(out_dir, "combined", metrics)
    return metrics


def table(rows: Sequence[dict]) -> pd.DataFrame:
    """One flat record per scene (the CSV)."""
    records = []
    for row in rows:
        paper = COMBINED_ESTIMATES.get(row["scene"], {})
        records.append({
            "scene": row["scene"], "paper_scene": paper.get("paper_scene", ""), "triangles": row["triangles"],
            "render_size": f"{row['render_width']}x{row['render_height']}", "final_size": f"{row['width']}x{row['height']}",
            "spp": row["spp"],
            **{f"{stage}_seconds": value for stage, value in row["seconds"].items()},
            "display_psnr": row["final"].get("display_psnr", math.nan), "flip": row["final"].get("flip", math.nan),
            "estimated_display_psnr": row.get("estimated_display_psnr", math.nan),
            "bicubic_display_psnr": row["bicubic"].get("display_psnr", math.nan),
            "psnr": row["final"]["psnr"], "rmse": row["final"]["rmse"],
            "estimated_psnr": row["estimated_psnr"],
            "denoise_stage_psnr": row["denoise_stage"]["psnr"], "denoise_stage_rmse": row["denoise_stage"]["rmse"],
            "superres_stage_psnr": row["superres_stage"]["psnr"], "superres_stage_rmse": row["superres_stage"]["rmse"],
            "bicubic_psnr": row["bicubic"]["psnr"], "noisy_bicubic_psnr": row["noisy_bicubic"]["psnr"],
            "paper_estimated_psnr": paper.get("estimated_psnr", math.nan),
            "paper_total_seconds_one_core": paper.get("total_seconds_one_core", math.nan),
        })
    return pd.DataFrame(records)


def combined_markdown(frame: pd.DataFrame) -> str:
    """The combined tables: display-referred beside the paper's estimates, then seconds, then linear."""
    def cell(value: float, digits: str) -> str:
        return "" if not math.isfinite(value) else format(value, digits)

    records = frame.to_dict("records")
    names = [record["scene"] + (f" ({record['paper_scene']})" if record["paper_scene"] else "") for record in records]
    display = tabulate([[name, cell(r["display_psnr"], ".2f"), cell(r["estimated_display_psnr"], ".2f"),
                         cell(r["paper_estimated_psnr"], ".2f"), cell(r["bicubic_display_psnr"], ".2f"),
                         cell(r["flip"], ".3f")] for name, r in zip(names, records, strict=True)],
                       headers=["scene (paper's)", "PSNR", "estimate (paper's rule)", "paper estimate",
                                "denoised + bicubic", "FLIP"], tablefmt="github")
    seconds = tabulate([[name, f"{r['render_size']} → {r['final_size']}", f"{r['render_seconds']:.3f}",
                         f"{r['denoise_seconds']:.3f}", f"{r['superres_seconds']:.3f}", f"{r['total_seconds']:.3f}",
                         cell(r["paper_total_seconds_one_core"], ".2f")] for name, r in zip(names, records, strict=True)],
                       headers=["scene (paper's)", "render → final", "render s", "denoise s", "SR s", "total s",
                                "paper total s (1 core, 1024²)"], tablefmt="github")
    linear = tabulate([[name, f"{r['psnr']:.2f}", f"{r['rmse']:.4f}", f"{r['estimated_psnr']:.2f}",
                        f"{r['denoise_stage_psnr']:.2f}", f"{r['superres_stage_psnr']:.2f}", f"{r['bicubic_psnr']:.2f}",
                        f"{r['noisy_bicubic_psnr']:.2f}"] for name, r in zip(names, records, strict=True)],
                      headers=["scene (paper's)", "PSNR", "RMSE", "estimate", "stage: denoise", "stage: SR",
                               "denoised + bicubic", "noisy + bicubic"], tablefmt="github")
    return (f"### Display-referred (the paper's space; PSNR dB, FLIP lower is better)\n\n{display}\n\n"
            f"### Seconds (this machine, all cores; the paper's on one core, for reference only)\n\n{seconds}\n\n"
            f"### Linear radiance clipped to [0, 1] (PSNR dB)\n\n{linear}")


def write_outputs(rows: Sequence[dict], config: Config, profile_name: str, out_dir: Path,
                  figures: Sequence[Path] = ()) -> None:
    """Write combined.md (linking ``figures``), combined.csv and combined.provenance.json atomically."""
    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    provenance = stamp(config.to_dict(), profile=profile_name, seed=profile.seed)
    machine = provenance["machine"]
    frame = table(rows)
    warned = sorted({w for row in rows for w in row["warnings"]})
    note_spp = "" if recon.spp == COMBINED_SPP else f" (the paper uses {COMBINED_SPP} spp)"
    text = (
        f"# §6.4 combined pipeline ({profile_name} profile)\n\n"
        f"Machine: {machine['cpu']}, {machine['cores']} cores, {machine['numba_threads']} numba threads; "
        f"{machine['date']}. Each scene's camera rendered by our path tracer at "
        f"{profile.combined_width // 2}x{profile.combined_height // 2}, {recon.spp} spp{note_spp}, max_depth "
        f"{recon.max_depth}; denoised by the scene's own denoiser and superresolved 2x to "
        f"{profile.combined_width}x{profile.combined_height} (networks of reconstruction profile "
        f"`{profile.reconstruction_profile}`), then compared with Mitsuba at {profile.combined_reference_spp} spp "
        f"(display-referred PSNR and FLIP: each reference exposed so that its 99th-percentile luminance is white, "
        f"clipped, sRGB; linear PSNR/RMSE on images clipped to [0, 1]). Seconds are warm, the shortest of {TIMING_REPEATS} runs "
        f"(render: kernel wall time; networks: after a warm-up call, whole frame, float32, all cores). "
        f"{load_note(rows)}Absolute "
        f"seconds depend on the machine and the paper's were on one core at 1024x1024, so they are printed for "
        f"reference only, never compared. Seed {profile.seed}.\n\n"
        "Stage PSNRs: the denoised half-size frame against the reference reduced 2x (2x2 mean), and the "
        "superresolution net applied to that reduced reference against the reference. \"Estimate (paper's rule)\" "
        "adds the two stage RMSEs (display-referred in the first table) and converts to PSNR, as the paper does for "
        "its estimates; the paper measured "
        f"{COMBINED_CBOX_MEASURED['psnr']} dB (RMSE {COMBINED_CBOX_MEASURED['rmse']}) on four Cornell box renderings.\n\n"
        + (f"Warnings during the run: {'; '.join(warned)}\n\n" if warned else "")
        + combined_markdown(frame) + "\n"
        + ("\n## Figure 8: the pipeline's stages and the tiled-minus-whole denoiser difference\n\n"
           + "".join(f"![{Path(p).stem}](figures/{Path(p).name})\n\n" for p in figures) if figures else "")
    )
    atomic_write_bytes(out_dir / "combined.md", text.encode())
    atomic_write_bytes(out_dir / "combined.csv", frame.to_csv(index=False).encode())
    atomic_write_bytes(out_dir / "combined.provenance.json", json.dumps(provenance, indent=1, default=str).encode())


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m reports.combined [--profile quick] [--out DIR] [--fresh] [--config FILE]``."""
    return run_cli(generate, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
