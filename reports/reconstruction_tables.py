"""Tables 2, 3, 5 and 6 of the paper, regenerated: denoising, the mixed model, superresolution, speed.

For a report profile (``[profiles.NAME]``) and its reconstruction profile
(``[reconstruction.profiles.*]``), :func:`generate`

1. generates or reuses the Precision Graphics dataset of every ``reconstruction_scenes``
   scene and of the ``unseen_scene`` (:func:`reconstruction.data.generate_dataset`);
2. trains or reuses one denoiser per scene, one **mixed** denoiser over all of them and
   one superresolution net (photos plus the training views of all scenes)
   (:mod:`reconstruction.train`; all content-addressed in the cache);
3. measures, pooled over whole views (:func:`reconstruction.evaluate.pooled`):

   * Table 2 — per scene, the per-scene and the mixed model on the train, validation
     and test views; the mixed model pooled over all scenes;
   * Table 3 — the mixed model on each scene's test views and on **all** views of the
     unseen scene (none of which it saw: using every view gives the figure more
     pixels), with the noisy input and OIDN beside it;
   * Table 5 — superresolution 2x against bicubic and Lanczos: on the training and
     validation photos, on the held-out photo test set
     (:data:`reconstruction.evaluate.TEST_PHOTOS`) and per scene on the test views;
   * Table 6 — per scene, at the report profile's frame size, a noisy render of the
     default view with a Mitsuba reference (:func:`reconstruction.speed.render_frame`):
     the fast-inference decision of both nets (a faster mode only if PSNR changes by at
     most 0.05 dB), then seconds of our denoiser against OIDN on the same buffers, and of
     superresolution to twice the frame size against bicubic (medians after a warm-up;
     only the ratios mean anything across machines);

4. writes ``table2``, ``table3``, ``table5``, ``table6`` and ``quality`` as Markdown and
   CSV, ``reconstruction_provenance.json`` and the gated metrics
   (``metrics/reconstruction.json``), every file atomically.

The paper's published figures stand beside ours (:mod:`reports.paper_figures`), on the
stand-in scenes of Table 1. Tables say which datasets and models were reused from the
cache; a rerun only evaluates.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from tabulate import tabulate
from tqdm import tqdm

from kdtrace.cache import atomic_write_bytes
from kdtrace.config import Config, ReconstructionProfile
from kdtrace.provenance import stamp
from reports.metrics import Metric, write_metrics
from reports.notes import ReportNote
from reports.paper_figures import TABLE2, TABLE3, TABLE5, TABLE6


@dataclasses.dataclass(frozen=True)
class DenoiserVariant:
    """A documented variant of the per-scene denoiser, trained and measured beside the paper's net (Table 2).

    Attributes
    ----------
    key : str
        Its key in the measurements and gated metric names (``table2/SCENE/KEY_test_psnr``).
    label : str
        What its stage, epochs and history are called (``"LABEL denoiser SCENE"``, ``"SCENE LABEL"``).
    row : str
        Its Table 2 model column.
    scenes_field : str
        The report profile's field listing the scenes that get it.
    auxiliary : tuple of str
        Its auxiliary input buffers.
    demodulate : bool
        Albedo demodulation (:class:`reconstruction.models.Denoiser`).
    perceptual : bool
        Trained in the perceptual transfer with the reconstruction profile's
        ``denoiser_perceptual_gain`` (:class:`reconstruction.models.Denoiser`).
    warmup_field : str
        The reconstruction profile's field giving its learning-rate warm-up steps ("": none).
    """

    key: str
    label: str
    row: str
    scenes_field: str
    auxiliary: tuple[str, ...]
    demodulate: bool = False
    perceptual: bool = False
    warmup_field: str = ""

    def train_options(self, recon: ReconstructionProfile) -> dict[str, Any]:
        """The :func:`reconstruction.train.train_denoiser` arguments of this variant under ``recon``."""
        return {"auxiliary": self.auxiliary, "demodulate": self.demodulate,
                "perceptual": recon.denoiser_perceptual_gain if self.perceptual else 0.0,
                "warmup_steps": getattr(recon, self.warmup_field) if self.warmup_field else 0}


#: The documented variants: the paper's network fed albedo, normal and depth (10 input channels
#: instead of 6, its parameter count reported), the paper's network on albedo-demodulated
#: colour, and the paper's network trained in a display-like transfer (both with the same 95,107
#: parameters).
DENOISER_VARIANTS = (
    DenoiserVariant("normal_depth", "normal+depth", "per-scene +normal+depth", "variant_scenes",
                    ("albedo", "normal", "depth"), warmup_field="normal_depth_warmup_steps"),
    DenoiserVariant("demodulated", "demodulated", "per-scene demodulated", "demodulated_scenes", ("albedo",), True),
    DenoiserVariant("perceptual", "perceptual", "per-scene perceptual", "perceptual_scenes", ("albedo",),
                    perceptual=True),
)

#: Output stems, each written as ``.md`` and ``.csv``.
TABLES = ("table2", "table3", "table5", "table6", "quality")


# ------------------------------------------------------------------ stages
@dataclasses.dataclass
class Stage:
    """One dataset or training run: its seconds, whether the cache already held it and, for a
    model, the seconds of its training epochs (summed from its history, also when reused)."""

    name: str
    seconds: float
    reused: bool
    training_seconds: float | None = None


def _run_stage(stages: list[Stage], name: str, started: float, work: Callable[[], Any],
               was_made: Callable[[Any], float], training_seconds: Callable[[Any], float] | None = None) -> Any:
    """Run ``work``, record its seconds, whether its artefact predates ``started`` (reused) and
    ``training_seconds(result)`` when given."""
    begin = time.perf_counter()
    result = work()
    stages.append(Stage(name, time.perf_counter() - begin, was_made(result) < started,
                        training_seconds(result) if training_seconds else None))
    return result


def _dataset_made(dataset) -> float:
    return (dataset.root / "manifest.json").stat().st_mtime  # written last, once, when the dataset is complete


def _model_made(result) -> float:
    # best.pt: written in the cache by every epoch that improved, and the file a stored model has
    return (result.directory / "best.pt").stat().st_mtime


def _references_made(refined) -> float:
    return max(path.stat().st_mtime for path in refined.folder.glob("view-*.npz"))  # each written once, atomically


def _training_seconds(result) -> float:
    return sum(epoch["seconds"] for epoch in result.history)


# ------------------------------------------------------------------ measurement
def reference_noise(dataset, split: str, spp: int, reference_spp: int) -> dict[str, float]:
    """Each view's reference noise, as a PSNR, estimated from the noisy input's error.

    Noisy input and reference are independent estimates of the same image whose variance
    falls as 1/spp (the same integrator; our path tracer passes per-pixel Z-tests against
    Mitsuba), so ``MSE(noisy, reference) = v/spp + v/reference_spp`` and the reference's own
    squared error is that MSE times ``spp / (spp + reference_spp)``; clipped to [0, 1] as
    every PSNR here. ``reference_spp`` is that of the ``split``'s references (a refined test
    split's, :meth:`reconstruction.test_references.RefinedDataset.reference_spp`). Returns each
    view's PSNR (``psnrs``, in the order of ``dataset.views(split)``), the lowest and the median,
    and the pooled PSNR of all of them (from their mean squared error, as the tables' PSNRs are
    pooled), dB, with ``reference_spp``.
    """
    share = spp / (spp + reference_spp)
    errors = []
    for name in dataset.views(split):
        view = dataset.load_view(name)
        errors.append(float(np.mean((np.clip(view["noisy"], 0, 1) - np.clip(view["reference"], 0, 1)) ** 2)) * share)
    def to_psnr(mse: float) -> float:
        return math.inf if mse == 0 else -10.0 * math.log10(mse)

    values = [to_psnr(error) for error in errors]
    return {"psnrs": values, "reference_spp": reference_spp,
            "lowest_psnr": float(min(values)), "median_psnr": float(np.median(values)),
            # every view has the same pixel count, so the pooled error is the views' mean
            "pooled_psnr": to_psnr(float(np.mean(errors))), "views": len(values)}


def measure_plugin_denoisers(specs: list[str], scenes: list[str], datasets: dict[str, Any], frames: dict[str, Any],
                             timing: dict[str, Any]) -> dict[str, dict[str, dict]]:
    """Each plug-in denoiser on the same test views as ours and OIDN, and timed on Table 6's frame.

    Parameters
    ----------
    specs : list of str
        Plug-in specs (:func:`kdtrace.plugins.load_denoiser`).
    scenes : list of str
    datasets : dict
        Scene -> dataset (``views(split)``, ``load_view(name)``).
    frames : dict
        Scene -> :class:`reconstruction.speed.Frame` of Table 6.
    timing : dict
        Scene -> Table 6's timing record (its OIDN seconds on the same frame).

    Returns
    -------
    dict
        Spec -> scene -> ``test`` (:func:`reconstruction.evaluate.pooled` over the test
        views, fed noisy colour, albedo and normal as float32), ``views``, ``seconds``
        (median of 3 calls after a warm-up on the frame), ``oidn_seconds`` (Table 6's),
        ``oidn_over_plugin`` and ``psnr`` (of the timed output against the frame's
        reference); or ``failed`` (``failed: MESSAGE``) when the plug-in's factory or a call
        raised or returned invalid output (:class:`kdtrace.plugins.PluginError`).
    """
    from kdtrace.plugins import PluginError, load_denoiser
    from reconstruction import evaluate, metrics, speed
    from reports.plugins import failure

    def buffers(view: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        return tuple(np.ascontiguousarray(view[key], np.float32) for key in ("noisy", "albedo", "normal"))

    results: dict[str, dict[str, dict]] = {}
    for spec in specs:
        try:
            denoiser = load_denoiser(spec)
        except PluginError as error:
            results[spec] = {name: {"failed": failure(error)} for name in scenes}
            continue
        results[spec] = {}
        for name in scenes:
            try:
                outputs, references = [], []
                for view_name in datasets[name].views("test"):
                    view = datasets[name].load_view(view_name)
                    outputs.append(denoiser(*buffers(view)))
                    references.append(view["reference"])
                frame = frames[name]
                seconds, image = speed.median_seconds(
                    lambda denoiser=denoiser, frame=frame: denoiser(frame.color, frame.albedo, frame.normal))
                oidn_seconds = timing[name]["denoise"]["oidn_seconds"]
                results[spec][name] = {"test": evaluate.pooled(outputs, references), "views": len(outputs),
                                       "seconds": seconds, "oidn_seconds": oidn_seconds,
                                       "oidn_over_plugin": oidn_seconds / seconds,
                                       "psnr": metrics.psnr(image, frame.reference)}
            except PluginError as error:
                results[spec][name] = {"failed": failure(error)}
    return results


def _measure(config: Config, profile_name: str, fresh: bool, progress: bool,
             denoisers: list[str] | tuple[str, ...] = ()) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train or reuse everything and measure every number of the tables.

    Returns the measurements (JSON-ready) and the objects the figures are drawn from
    (datasets, per-scene models, mixed model, superresolution model).
    """
    from kdtrace.scenes import load_scene
    from reconstruction import evaluate, speed
    from reconstruction.data import TRAIN_PHOTOS, VALIDATION_PHOTOS, generate_dataset, photo
    from reconstruction.test_references import refine_test_references
    from reconstruction.train import parameter_count, train_denoiser, train_superres

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    scenes = list(profile.reconstruction_scenes)
    if not scenes:
        raise ValueError(f"profile {profile_name!r} names no reconstruction_scenes")
    unseen = profile.unseen_scene
    far = profile.far_unseen_scene
    started = time.time() - 1.0  # file times have coarse resolution on some systems
    stages: list[Stage] = []
    variants = {variant: list(getattr(profile, variant.scenes_field)) for variant in DENOISER_VARIANTS}
    # datasets; per-scene, mixed, variant and superresolution models; refined references; quality
    # per scene and per unseen scene; photos; a frame and its timing per scene
    steps = (len(scenes) + bool(unseen) + bool(far) + len(scenes) + 1 + sum(map(len, variants.values())) + 1
             + profile.perceptual_mixed + profile.superres_display
             + sum(recon.test_reference_spp(name) > recon.reference_spp for name in scenes)
             + len(scenes) + bool(unseen) + bool(far) + 1 + 2 * len(scenes))
    bar = tqdm(total=steps, unit="step", desc=f"reconstruction ({profile_name})", disable=not progress)

    def step(label: str) -> None:
        bar.set_postfix_str(label)

    def stage(label: str, work: Callable[[], Any], was_made: Callable[[Any], float] = _model_made,
              training_seconds: Callable[[Any], float] | None = _training_seconds) -> Any:
        """One dataset, model or refinement: named on the bar, timed and recorded in ``stages``."""
        step(label)
        result = _run_stage(stages, label, started, work, was_made, training_seconds)
        bar.update()
        return result

    datasets = {name: stage(f"dataset {name}", lambda name=name: generate_dataset(name, recon, progress=False),
                            _dataset_made, None)
                for name in scenes + [n for n in (unseen, far) if n]}
    models = {name: stage(f"denoiser {name}", lambda name=name: train_denoiser([name], recon, progress=False))
              for name in scenes}
    # the paper's models (per-scene, then mixed) before the documented variants: an interrupted
    # run has the measured objects first
    mixed = stage("mixed denoiser", lambda: train_denoiser(scenes, recon.mixed, progress=False))
    variant_models: dict[DenoiserVariant, dict[str, Any]] = {
        variant: {name: stage(f"{variant.label} denoiser {name}", lambda name=name, variant=variant: train_denoiser(
            [name], recon, progress=False, **variant.train_options(recon))) for name in names}
        for variant, names in variants.items()}
    mixed_perceptual = (stage("perceptual mixed denoiser", lambda: train_denoiser(
        scenes, recon.mixed, perceptual=recon.denoiser_perceptual_gain, progress=False))
        if profile.perceptual_mixed else None)
    superres = stage("superresolution", lambda: train_superres(recon, scenes, progress=False))
    superres_display = (stage("display superresolution", lambda: train_superres(recon, scenes, progress=False,
                                                                                space="display"))
                        if profile.superres_display else None)
    for name in scenes:  # more reference samples for the test views of the scenes that need them, only
        refine = functools.partial(refine_test_references, datasets[name], load_scene(name), recon, progress=False)
        needed = recon.test_reference_spp(name) > recon.reference_spp
        # nothing rendered where not needed: the dataset's own references
        datasets[name] = stage(f"test references {name}", refine, _references_made, None) if needed else refine()
    quality: dict[str, Any] = {}
    for name in scenes:
        step(f"quality {name}")
        dataset = datasets[name]
        quality[name] = {
            "views": {split: len(dataset.views(split)) for split in ("train", "validation", "test")},
            "ours": {split: evaluate.denoiser_quality(models[name].model, dataset, split, with_oidn=split == "test")
                     for split in ("train", "validation", "test")},
            "mixed": {split: evaluate.denoiser_quality(mixed.model, dataset, split, with_oidn=False)["ours"]
                      for split in ("train", "validation", "test")},
            "superres": evaluate.superres_quality(superres.model, dataset, "test", recon.superres_downsample),
            "reference_noise": reference_noise(dataset, "test", recon.spp, dataset.reference_spp("test")),
        }
        if mixed_perceptual is not None:
            quality[name]["mixed_perceptual"] = {"test": evaluate.denoiser_quality(
                mixed_perceptual.model, dataset, "test", with_oidn=False)["ours"]}
        if superres_display is not None:
            quality[name]["superres_display"] = evaluate.superres_quality(superres_display.model, dataset, "test",
                                                                          recon.superres_downsample)
        for variant, trained in variant_models.items():
            if name in trained:
                quality[name][variant.key] = {
                    split: evaluate.denoiser_quality(trained[name].model, dataset, split, variant.auxiliary,
                                                     with_oidn=False)["ours"] for split in ("train", "validation", "test")}
        bar.update()
    unseen_quality = {}
    for role, name in (("unseen", unseen), ("far", far)):
        if name:
            step(f"unseen {name}")
            unseen_quality[role] = {"scene": name, "views": len(datasets[name].views()),
                                    **evaluate.denoiser_quality(mixed.model, datasets[name], None, with_oidn=True)}
            if mixed_perceptual is not None:
                unseen_quality[role]["mixed_perceptual"] = evaluate.denoiser_quality(
                    mixed_perceptual.model, datasets[name], None, with_oidn=False)["ours"]
            bar.update()
    step("photos")
    photo_sets = {"train": [photo(n) for n in TRAIN_PHOTOS], "validation": [photo(n) for n in VALIDATION_PHOTOS],
                  "test": [evaluate.held_out_photo(n) for n in evaluate.TEST_PHOTOS]}
    photos = {split: evaluate.superres_images(superres.model, images, recon.superres_downsample)
              for split, images in photo_sets.items()}
    photos_display = ({split: evaluate.superres_images(superres_display.model, images, recon.superres_downsample)
                       for split, images in photo_sets.items()} if superres_display is not None else None)
    bar.update()

    timing, frames = {}, {}
    for name in scenes:
        step(f"frame {name}")
        frames[name] = frame = speed.render_frame(name, profile.frame_width, profile.frame_height, profile.frame_spp,
                                   recon.max_depth, profile.seed, recon.reference_spp, cache=not fresh)
        bar.update()
        step(f"timing {name}")
        decisions = speed.choose_options(models[name].model, superres.model, frame, recon.superres_downsample)
        timing[name] = {
            "threads": torch.get_num_threads(),
            "denoise_option": decisions["denoise"].chosen,
            "superres_option": decisions["superres"].chosen,
            "decisions": {kind: [dataclasses.asdict(r) for r in decision.results]
                          for kind, decision in decisions.items()},
            "denoise": speed.time_denoise(models[name].model, frame, decisions["denoise"].chosen),
            "superres": speed.time_superres(superres.model, frame.reference, decisions["superres"].chosen),
        }
        bar.update()
    bar.close()
    plugins = {}
    if denoisers:
        plugins["plugin_denoisers"] = measure_plugin_denoisers(list(denoisers), scenes, datasets, frames, timing)
    return {
        **plugins,
        "profile": profile_name, "reconstruction_profile": profile.reconstruction_profile, "scenes": scenes,
        "unseen": unseen, "frame": [profile.frame_width, profile.frame_height], "frame_spp": profile.frame_spp,
        "stages": [dataclasses.asdict(s) for s in stages],
        "best_epochs": {**{name: models[name].best_epoch for name in scenes}, "mixed": mixed.best_epoch,
                        **({"mixed perceptual": mixed_perceptual.best_epoch} if mixed_perceptual is not None else {}),
                        **({"superres display": superres_display.best_epoch} if superres_display is not None else {}),
                        **{f"{name} {variant.label}": result.best_epoch
                           for variant, trained in variant_models.items() for name, result in trained.items()},
                        "superres": superres.best_epoch},
        "epochs": {"per-scene denoisers": recon.denoiser.epochs, "mixed": recon.mixed.epochs,
                   "superresolution": recon.epochs},
        "parameters": {"denoiser": parameter_count(mixed.model), "superres": parameter_count(superres.model),
                       **{f"{variant.key}_denoiser": parameter_count(next(iter(trained.values())).model)
                          for variant, trained in variant_models.items() if trained}},
        **{variant.scenes_field: variants[variant] for variant in DENOISER_VARIANTS},
        "quality": quality, "unseen_quality": unseen_quality.get("unseen"), "photos": photos, "timing": timing,
        "photos_display": photos_display,
        "far": far, "far_quality": unseen_quality.get("far"),
        "histories": {**{name: models[name].history for name in scenes}, "mixed": mixed.history,
                      **({"mixed perceptual": mixed_perceptual.history} if mixed_perceptual is not None else {}),
                      **({"superres display": superres_display.history} if superres_display is not None else {}),
                      **{f"{name} {variant.label}": result.history
                         for variant, trained in variant_models.items() for name, result in trained.items()},
                      "superres": superres.history},
    }, {"datasets": datasets, "models": {name: models[name].model for name in scenes}, "mixed": mixed.model,
        "superres": superres.model,
        "variants": {variant.key: {name: result.model for name, result in trained.items()}
                     for variant, trained in variant_models.items()}}


# ------------------------------------------------------------------ tables
def _f(value: float | None, digits: int = 2) -> str:
    return "" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _paper_name(scene: str) -> str:
    paper = TABLE2.get(scene) or TABLE3.get(scene) or {}
    return scene + (f" ({paper['paper_scene']})" if paper else "")


def _reused(stages: list[dict], name: str) -> str:
    """How a model came: "trained N s" in this run, else "reused (trained N s)"; N sums its
    training epochs (the stage's wall time, or a bare "reused", in measurements made before it was recorded)."""
    stage = next(s for s in stages if s["name"] == name)
    trained = stage.get("training_seconds")
    if not stage["reused"]:
        return f"trained {stage['seconds'] if trained is None else trained:.0f} s"
    return "reused" if trained is None else f"reused (trained {trained:.0f} s)"


def _per_view_margin(noise: dict, *results: dict | None) -> float | None:
    """Smallest, over the test views, of a view's reference PSNR minus the best PSNR measured on it.

    ``results`` are :func:`reconstruction.evaluate.pooled` results on the same views (the row's
    model, OIDN, the noisy input; None: not measured). None when a per-view list is missing
    (measurements made before they were kept).
    """
    lists = [result.get("per_image_psnr") for result in results if result is not None]
    if not noise.get("psnrs") or not lists or any(values is None for values in lists):
        return None
    return min(reference - max(measured) for reference, *measured in zip(noise["psnrs"], *lists, strict=True))


def _spaces(model: dict, noisy: dict | None = None, oidn: dict | None = None) -> dict:
    """Display-referred and HDR columns of one row: the model's, and the noisy input's and OIDN's beside them."""
    columns = {}
    for prefix, result in (("", model), ("noisy_", noisy), ("oidn_", oidn)):
        for key in ("display_psnr", "flip", "relmse", "smape"):
            columns[f"{prefix}{key}"] = None if result is None else result.get(key)
    if columns["oidn_display_psnr"] is not None and columns["display_psnr"] is not None:
        columns["minus_oidn_display"] = columns["display_psnr"] - columns["oidn_display_psnr"]
    return columns


def _test_columns(quality: dict, model_test: dict) -> dict:
    """Table 2's test-view columns of one row: the model, the noisy input, OIDN and the references' noise.

    ``quality`` is the scene's evaluation (``ours.test`` holds the noisy input's and OIDN's
    results, ``reference_noise`` the references' own PSNRs, empty when not measured),
    ``model_test`` the row model's pooled test result. Every reference margin is over the best
    of the row's model, OIDN and the noisy input, so all rows of a scene are judged against the
    same references.
    """
    test, noise = quality["ours"]["test"], quality.get("reference_noise", {})
    psnr, noisy, oidn = model_test["psnr"], test["noisy"]["psnr"], test.get("oidn", {}).get("psnr")
    best = max(p for p in (psnr, oidn, noisy) if p is not None)
    return {**_spaces(model_test, test["noisy"], test.get("oidn")),
            "test_psnr": psnr, "test_rmse": model_test["rmse"], "noisy_test_psnr": noisy,
            "gain_over_noisy": psnr - noisy, "oidn_test_psnr": oidn, "minus_oidn": None if oidn is None else psnr - oidn,
            "reference_psnr_lowest": noise.get("lowest_psnr"),
            "reference_margin_db": None if not noise else noise["lowest_psnr"] - best,
            "reference_psnr_pooled": noise.get("pooled_psnr"),
            "reference_margin_pooled_db": None if not noise else noise["pooled_psnr"] - best,
            "reference_margin_per_view_db": _per_view_margin(noise, model_test, test.get("oidn"), test["noisy"]),
            "test_reference_spp": noise.get("reference_spp"),
            "black_test_views": model_test.get("black_references")}


def _table2(m: dict) -> list[dict]:
    rows = []
    for name in m["scenes"]:
        q, paper = m["quality"][name], TABLE2.get(name, {})
        for model in ("ours", "mixed"):
            metrics = {split: (q[model][split]["ours"] if model == "ours" else q[model][split])
                       for split in ("train", "validation", "test")}
            rows.append({"scene": name, "model": "per-scene" if model == "ours" else "mixed",
                         "train_psnr": metrics["train"]["psnr"], "validation_psnr": metrics["validation"]["psnr"],
                         **_test_columns(q, metrics["test"]),
                         "test_views": q["views"]["test"],
                         "paper_test_psnr": paper.get("test_psnr") if model == "ours" else None,
                         "paper_test_rmse": paper.get("test_rmse") if model == "ours" else None,
                         "model_source": _reused(m["stages"], f"denoiser {name}" if model == "ours" else "mixed denoiser")})
        for kind in (v for v in DENOISER_VARIANTS if v.key in q):
            variant = q[kind.key]
            rows.append({"scene": name, "model": kind.row, "train_psnr": variant["train"]["psnr"],
                         "validation_psnr": variant["validation"]["psnr"], **_test_columns(q, variant["test"]),
                         "test_views": q["views"]["test"],
                         "model_source": _reused(m["stages"], f"{kind.label} denoiser {name}")})
    from reconstruction.evaluate import combine

    pooled = {split: combine([m["quality"][n]["mixed"][split] for n in m["scenes"]]) for split in ("train", "validation", "test")}
    per_scene = combine([m["quality"][n]["ours"]["test"]["ours"] for n in m["scenes"]])
    rows.append({"scene": "all scenes", "model": "mixed", **_spaces(pooled["test"]), "train_psnr": pooled["train"]["psnr"],
                 "validation_psnr": pooled["validation"]["psnr"], "test_psnr": pooled["test"]["psnr"],
                 "test_rmse": pooled["test"]["rmse"], "test_views": pooled["test"]["images"],
                 "paper_test_psnr": TABLE2["mixed"]["test_psnr"], "paper_test_rmse": TABLE2["mixed"]["test_rmse"],
                 "model_source": _reused(m["stages"], "mixed denoiser")})
    rows.append({"scene": "all scenes", "model": "per-scene", **_spaces(per_scene), "train_psnr": None, "validation_psnr": None,
                 "test_psnr": per_scene["psnr"], "test_rmse": per_scene["rmse"], "test_views": per_scene["images"],
                 "paper_test_psnr": None, "paper_test_rmse": None, "model_source": "each scene's own model"})
    return rows + _table2_plugins(m)


def _table2_plugins(m: dict) -> list[dict]:
    """Table 2's rows of the plug-in denoisers (model ``plug-in SPEC``): per scene, and pooled when none failed."""
    from reconstruction.evaluate import combine

    rows = []
    for spec, by_scene in m.get("plugin_denoisers", {}).items():
        for name in m["scenes"]:
            result, test = by_scene[name], m["quality"][name]["ours"]["test"]
            oidn = test.get("oidn", {}).get("psnr")
            if result.get("failed"):
                rows.append({"scene": name, "model": f"plug-in {spec}", "model_source": result["failed"]})
                continue
            psnr = result["test"]["psnr"]
            rows.append({"scene": name, "model": f"plug-in {spec}", **_spaces(result["test"], test["noisy"], test.get("oidn")),
                         "test_psnr": psnr, "test_rmse": result["test"]["rmse"],
                         "noisy_test_psnr": test["noisy"]["psnr"], "gain_over_noisy": psnr - test["noisy"]["psnr"],
                         "oidn_test_psnr": oidn, "minus_oidn": None if oidn is None else psnr - oidn,
                         "test_views": result["views"], "model_source": "plug-in"})
        if all(not by_scene[name].get("failed") for name in m["scenes"]):
            pooled = combine([by_scene[name]["test"] for name in m["scenes"]])
            rows.append({"scene": "all scenes", "model": f"plug-in {spec}", "test_psnr": pooled["psnr"],
                         "test_rmse": pooled["rmse"], "test_views": pooled["images"], "model_source": "plug-in"})
    return rows


def _table3(m: dict) -> list[dict]:
    rows = []
    for name in m["scenes"]:
        q, paper = m["quality"][name], TABLE3.get(name, {})
        rows.append({"scene": name, "views": f"test ({q['views']['test']})",
                     **_spaces(q["mixed"]["test"], q["ours"]["test"]["noisy"], q["ours"]["test"].get("oidn")),
                     "per_scene_display_psnr": q["ours"]["test"]["ours"].get("display_psnr"),
                     "mixed_psnr": q["mixed"]["test"]["psnr"],
                     "mixed_rmse": q["mixed"]["test"]["rmse"],
                     "mixed_pixels_beyond_input": q["mixed"]["test"].get("beyond_input"),
                     "mixed_pixels_black_where_lit": q["mixed"]["test"].get("black_where_lit"),
                     "per_scene_psnr": q["ours"]["test"]["ours"]["psnr"],
                     "psnr_difference": q["ours"]["test"]["ours"]["psnr"] - q["mixed"]["test"]["psnr"],
                     "noisy_psnr": q["ours"]["test"]["noisy"]["psnr"],
                     "oidn_psnr": q["ours"]["test"].get("oidn", {}).get("psnr"),
                     "paper_mixed_psnr": paper.get("test_psnr"), "paper_mixed_rmse": paper.get("test_rmse"),
                     "paper_psnr_difference": paper.get("psnr_difference"),
                     **_mixed_perceptual_columns(q.get("mixed_perceptual", {}).get("test"))})
    if m["unseen_quality"]:
        u, paper = m["unseen_quality"], TABLE3["unseen"]
        rows.append({"scene": f"{m['unseen']} (never seen)", "views": f"all ({u['views']})",
                     **_spaces(u["ours"], u["noisy"], u.get("oidn")),
                     "mixed_psnr": u["ours"]["psnr"], "mixed_rmse": u["ours"]["rmse"],
                     "mixed_pixels_beyond_input": u["ours"].get("beyond_input"),
                     "mixed_pixels_black_where_lit": u["ours"].get("black_where_lit"), "per_scene_psnr": None,
                     "psnr_difference": None, "noisy_psnr": u["noisy"]["psnr"],
                     "oidn_psnr": u.get("oidn", {}).get("psnr"),
                     "paper_mixed_psnr": paper["test_psnr"], "paper_mixed_rmse": paper["test_rmse"],
                     "paper_psnr_difference": None, **_mixed_perceptual_columns(u.get("mixed_perceptual"))})
    if m.get("far_quality"):
        u = m["far_quality"]
        rows.append({"scene": f"{m['far']} (never seen, far)", "views": f"all ({u['views']})",
                     **_spaces(u["ours"], u["noisy"], u.get("oidn")),
                     "mixed_psnr": u["ours"]["psnr"], "mixed_rmse": u["ours"]["rmse"],
                     "mixed_pixels_beyond_input": u["ours"].get("beyond_input"),
                     "mixed_pixels_black_where_lit": u["ours"].get("black_where_lit"), "per_scene_psnr": None,
                     "psnr_difference": None, "noisy_psnr": u["noisy"]["psnr"],
                     "oidn_psnr": u.get("oidn", {}).get("psnr"), "paper_mixed_psnr": None, "paper_mixed_rmse": None,
                     "paper_psnr_difference": None, **_mixed_perceptual_columns(u.get("mixed_perceptual"))})
    return rows


def _mixed_perceptual_columns(result: dict | None) -> dict:
    """Table 3's columns of the perceptual mixed model on a row's views (empty: not trained)."""
    if result is None:
        return {}
    return {"mixed_perceptual_display_psnr": result.get("display_psnr"), "mixed_perceptual_flip": result.get("flip"),
            "mixed_perceptual_relmse": result.get("relmse"), "mixed_perceptual_psnr": result["psnr"],
            "mixed_perceptual_pixels_beyond_input": result.get("beyond_input")}


def _sr_row(label: str, split: str, results: dict, paper: dict | None = None, displayed: dict | None = None) -> dict:
    """One Table 5 row: the linear net and its baselines, and (``displayed``) the display-space net and its own."""
    row = {"data": label, "split": split, "images": results["ours"]["images"],
           **{f"{method}_{key}": results[method].get(key) for method in ("bicubic", "lanczos", "ours")
              for key in ("psnr", "rmse", "display_psnr", "flip")},
           "gain_over_bicubic": results["ours"]["psnr"] - results["bicubic"]["psnr"],
           "display_gain_over_bicubic": (None if results["ours"].get("display_psnr") is None
                                         else results["ours"]["display_psnr"] - results["bicubic"]["display_psnr"]),
           "paper_psnr": (paper or {}).get(f"{split}_psnr"), "paper_rmse": (paper or {}).get(f"{split}_rmse")}
    if displayed is not None:
        row.update({f"displayed_{method}_{key}": displayed[method].get(key) for method in ("bicubic", "ours")
                    for key in ("psnr", "display_psnr", "flip")})
        row["displayed_gain_over_bicubic"] = displayed["ours"]["display_psnr"] - displayed["bicubic"]["display_psnr"]
    return row


def _table5(m: dict) -> list[dict]:
    from reconstruction.evaluate import combine

    shown = m.get("photos_display")
    rows = [_sr_row("photos", split, m["photos"][split], TABLE5["photos"], shown and shown[split])
            for split in ("train", "validation", "test")]
    rows += [_sr_row(name, "test", m["quality"][name]["superres"], None, m["quality"][name].get("superres_display"))
             for name in m["scenes"]]
    pooled = {method: combine([m["quality"][n]["superres"][method] for n in m["scenes"]])
              for method in ("bicubic", "lanczos", "ours")}
    pooled_shown = ({method: combine([m["quality"][n]["superres_display"][method] for n in m["scenes"]])
                     for method in ("bicubic", "ours")} if shown else None)
    rows.append(_sr_row("all scenes", "test", pooled, None, pooled_shown))
    return rows


def _table6(m: dict) -> list[dict]:
    rows = []
    width, height = m["frame"]
    for name in m["scenes"]:
        t, paper = m["timing"][name], TABLE6.get(name, {})
        rows.append({"scene": name, "frame": f"{width}x{height}", "denoise_option": t["denoise_option"],
                     "ours_denoise_s": t["denoise"]["ours_seconds"], "oidn_s": t["denoise"]["oidn_seconds"],
                     "oidn_over_ours": t["denoise"]["oidn_over_ours"], "noisy_psnr": t["denoise"]["noisy_psnr"],
                     "ours_psnr": t["denoise"]["ours_psnr"], "oidn_psnr": t["denoise"]["oidn_psnr"],
                     "superres_option": t["superres_option"], "superres_output": f"{2 * width}x{2 * height}",
                     "ours_superres_s": t["superres"]["ours_seconds"], "bicubic_s": t["superres"]["bicubic_seconds"],
                     "bicubic_over_ours": t["superres"]["bicubic_over_ours"],
                     "superres_gflop": t["superres"]["ours_gflop"], "superres_gflops": t["superres"]["ours_gflops"],
                     "matmul_gflops": t["superres"]["matmul_gflops"], "superres_floor_s": t["superres"]["floor_seconds"],
                     "paper_denoise_s": paper.get("denoise_seconds"), "paper_superres_s": paper.get("superres_seconds"),
                     "threads": t["threads"]})
    return rows


def _table6_plugins(m: dict) -> list[dict]:
    """Table 6's plug-in denoisers: seconds on the same frame beside Table 6's OIDN seconds."""
    rows = []
    width, height = m["frame"]
    for spec, by_scene in m.get("plugin_denoisers", {}).items():
        for name in m["scenes"]:
            result = by_scene[name]
            row = {"scene": name, "plug-in": spec, "frame": f"{width}x{height}"}
            if result.get("failed"):
                rows.append({**row, "status": result["failed"]})
                continue
            rows.append({**row, "plugin_denoise_s": result["seconds"], "oidn_s": result["oidn_seconds"],
                         "oidn_over_plugin": result["oidn_over_plugin"], "plugin_psnr": result["psnr"],
                         "oidn_psnr": m["timing"][name]["denoise"]["oidn_psnr"], "status": "ok"})
    return rows


def _quality(m: dict) -> list[dict]:
    rows = []
    for name in m["scenes"]:
        q = m["quality"][name]
        test = q["ours"]["test"]
        rows.append({"scene": name, "noisy_display": test["noisy"].get("display_psnr"),
                     "ours_display": test["ours"].get("display_psnr"), "mixed_display": q["mixed"]["test"].get("display_psnr"),
                     "oidn_display": test.get("oidn", {}).get("display_psnr"),
                     "paper_ours": TABLE2.get(name, {}).get("test_psnr"),
                     "paper_mixed": TABLE3.get(name, {}).get("test_psnr"),
                     "bicubic_display": q["superres"]["bicubic"].get("display_psnr"),
                     "ours_superres_display": q["superres"]["ours"].get("display_psnr"),
                     "noisy": test["noisy"]["psnr"], "ours": test["ours"]["psnr"],
                     "mixed": q["mixed"]["test"]["psnr"], "oidn": test.get("oidn", {}).get("psnr"),
                     "bicubic": q["superres"]["bicubic"]["psnr"], "lanczos": q["superres"]["lanczos"]["psnr"],
                     "ours_superres": q["superres"]["ours"]["psnr"]})
    if m["unseen_quality"]:
        u = m["unseen_quality"]
        rows.append({"scene": f"{m['unseen']} (never seen)", "noisy_display": u["noisy"].get("display_psnr"),
                     "mixed_display": u["ours"].get("display_psnr"), "oidn_display": u.get("oidn", {}).get("display_psnr"),
                     "paper_mixed": TABLE3["unseen"]["test_psnr"], "noisy": u["noisy"]["psnr"],
                     "mixed": u["ours"]["psnr"], "oidn": u.get("oidn", {}).get("psnr")})
    return rows


def _cell(column: str, value: Any) -> str:
    """A table cell: seconds (``*_s``) with 4 decimals, RMSE with 4, FLIP with 3, relMSE and SMAPE with 3
    significant digits, other floats with 2."""
    if isinstance(value, float) and ("relmse" in column or "smape" in column) and math.isfinite(value):
        return f"{value:.3g}"
    if isinstance(value, float):
        return _f(value, 4 if column.endswith("_s") or "rmse" in column else 3 if "flip" in column else 2)
    return "" if value is None else str(value)


def _markdown(rows: list[dict], scene_columns: tuple[str, ...] = ("scene",)) -> str:
    shown = [{column: (_paper_name(value) if column in scene_columns and isinstance(value, str) else _cell(column, value))
              for column, value in row.items()} for row in rows]
    return tabulate(shown, headers="keys", tablefmt="github", disable_numparse=True)


def _joined(row: dict, form: str, *keys: str) -> str:
    """Several values of one row as ``a / b / c`` in ``form`` (``-`` where not measured; empty when none is)."""
    values = [row.get(key) for key in keys]
    return "" if all(v is None for v in values) else " / ".join("-" if v is None else form.format(v) for v in values)


#: A compact view of a table: (heading, [(column or callable, header)]); the CSV keeps every column.
#: A view may end with the column it is about: without a value in any row (a variant not trained) it is left out.
View = tuple[str, list[tuple[Any, str]]] | tuple[str, list[tuple[Any, str]], str]

_DISPLAY = ("Display-referred (the paper's space: each view exposed so that its reference's 99th-percentile "
            "luminance is white, clipped, sRGB); PSNR in dB, FLIP lower is better")
_LINEAR = "Linear radiance clipped to [0, 1] (PSNR dB) and HDR (relMSE, unclipped)"

_VIEWS: dict[str, list[View]] = {
    "table2": [
        (_DISPLAY, [("scene", "scene"), ("model", "model"), ("paper_test_psnr", "paper PSNR"),
                    ("noisy_display_psnr", "noisy"), ("display_psnr", "ours"), ("oidn_display_psnr", "OIDN"),
                    ("minus_oidn_display", "ours − OIDN"),
                    (lambda r: _joined(r, "{:.3f}", "noisy_flip", "flip", "oidn_flip"), "FLIP noisy / ours / OIDN")]),
        (_LINEAR, [("scene", "scene"), ("model", "model"), ("noisy_test_psnr", "noisy"), ("test_psnr", "ours"),
                   ("oidn_test_psnr", "OIDN"), ("relmse", "relMSE ours"), ("oidn_relmse", "relMSE OIDN"),
                   ("reference_margin_per_view_db", "reference margin per view (dB)")]),
        ("Splits, references and models (linear PSNR, dB)",
         [("scene", "scene"), ("model", "model"), ("train_psnr", "train"), ("validation_psnr", "validation"),
          ("test_views", "test views"), ("black_test_views", "of which black"), ("test_reference_spp", "reference spp"),
          ("model_source", "trained")]),
    ],
    "table3": [
        (_DISPLAY, [("scene", "scene"), ("views", "views"), ("paper_mixed_psnr", "paper mixed PSNR"),
                    ("noisy_display_psnr", "noisy"), ("display_psnr", "mixed"), ("per_scene_display_psnr", "per-scene"),
                    ("oidn_display_psnr", "OIDN"), (lambda r: _joined(r, "{:.3f}", "noisy_flip", "flip", "oidn_flip"),
                                                    "FLIP noisy / mixed / OIDN")]),
        ("The perceptual mixed model (profile `perceptual_mixed`), display-referred PSNR in dB, FLIP and HDR relMSE "
         "lower is better",
         [("scene", "scene"), ("views", "views"), ("noisy_display_psnr", "noisy"),
          ("mixed_perceptual_display_psnr", "mixed perceptual"), ("oidn_display_psnr", "OIDN"),
          (lambda r: _joined(r, "{:.3f}", "noisy_flip", "mixed_perceptual_flip", "oidn_flip"), "FLIP noisy / mixed perceptual / OIDN"),
          (lambda r: _joined(r, "{:.3g}", "mixed_perceptual_relmse", "oidn_relmse"), "relMSE mixed perceptual / OIDN")],
         "mixed_perceptual_display_psnr"),
        (_LINEAR, [("scene", "scene"), ("noisy_psnr", "noisy"), ("mixed_psnr", "mixed"), ("per_scene_psnr", "per-scene"),
                   ("oidn_psnr", "OIDN"), ("relmse", "relMSE mixed"),
                   ("mixed_pixels_beyond_input", "pixels beyond input"),
                   ("mixed_pixels_black_where_lit", "pixels black where lit")]),
    ],
    "table5": [
        (_DISPLAY, [("data", "data"), ("split", "split"), ("images", "images"), ("paper_psnr", "paper PSNR"),
                    ("bicubic_display_psnr", "bicubic"), ("lanczos_display_psnr", "Lanczos"), ("ours_display_psnr", "ours"),
                    ("display_gain_over_bicubic", "ours − bicubic")]),
        ("The display-trained net (profile `superres_display`) against bicubic of the same displayed image; "
         "display-referred PSNR in dB, FLIP lower is better",
         [("data", "data"), ("split", "split"), ("displayed_bicubic_display_psnr", "bicubic of the displayed image"),
          ("displayed_ours_display_psnr", "ours, display-trained"),
          ("displayed_gain_over_bicubic", "display-trained − its bicubic"),
          (lambda r: _joined(r, "{:.3f}", "displayed_bicubic_flip", "displayed_ours_flip"), "FLIP bicubic / display-trained")],
         "displayed_ours_display_psnr"),
        (_LINEAR, [("data", "data"), ("split", "split"), ("bicubic_psnr", "bicubic"), ("lanczos_psnr", "Lanczos"),
                   ("ours_psnr", "ours"), ("gain_over_bicubic", "ours − bicubic")]),
    ],
    "table6": [
        ("Denoising one frame (seconds; only the ratio compares across machines)",
         [("scene", "scene"), ("frame", "frame"), ("denoise_option", "mode"), ("ours_denoise_s", "ours s"),
          ("oidn_s", "OIDN s"), ("oidn_over_ours", "OIDN / ours"), ("paper_denoise_s", "paper s")]),
        ("Superresolution 2x of one frame (seconds)",
         [("scene", "scene"), ("superres_output", "output"), ("superres_option", "mode"), ("ours_superres_s", "ours s"),
          ("bicubic_s", "bicubic s"), ("bicubic_over_ours", "bicubic / ours"), ("paper_superres_s", "paper s")]),
        ("What was timed, checked (linear PSNR in dB against the frame's reference) and the arithmetic",
         [("scene", "scene"), ("noisy_psnr", "noisy"), ("ours_psnr", "ours"), ("oidn_psnr", "OIDN"),
          ("superres_gflops", "SR GFLOP/s"), ("matmul_gflops", "matmul GFLOP/s"), ("threads", "threads")]),
    ],
    "quality": [
        (_DISPLAY + "; the paper's PSNRs are of its display images",
         [("scene", "scene"), ("paper_ours", "paper per-scene"), ("noisy_display", "noisy"), ("ours_display", "ours"),
          ("mixed_display", "mixed"), ("paper_mixed", "paper mixed"), ("oidn_display", "OIDN"),
          ("ours_superres_display", "SR ours (bicubic)")]),
    ],
}


def _view_markdown(rows: list[dict], columns: list[tuple[Any, str]], scene_columns: tuple[str, ...]) -> str:
    shown = []
    for row in rows:
        cells = {}
        for column, header in columns:
            if callable(column):
                cells[header] = column(row)
            elif column in scene_columns and isinstance(row.get(column), str):
                cells[header] = _paper_name(row[column])
            else:
                cells[header] = _cell(column, row.get(column))
        if any(list(cells.values())[2:]):  # a row with nothing measured in this view is left out of it
            shown.append(cells)
    return tabulate(shown, headers="keys", tablefmt="github", disable_numparse=True)


def _views_markdown(stem: str, rows: list[dict], scene_columns: tuple[str, ...], csv_name: str) -> str:
    """Every compact view of a table, each under its heading, and where the full table is."""
    parts = [f"### {heading}\n\n{_view_markdown(rows, columns, scene_columns)}"
             for heading, columns, *about in _VIEWS[stem]
             if not about or any(row.get(about[0]) is not None for row in rows)]
    return "\n\n".join(parts) + f"\n\nEvery column, both spaces: [{csv_name}]({csv_name}).\n"


_TITLES = {
    "table2": ("Table 2 — denoiser quality per scene (per-scene and mixed models)",
               "Metrics pooled over whole views of each split, in two spaces (reconstruction/metrics.py): "
               "display-referred, the space of the paper's PSNRs and of what a person sees, and linear radiance "
               "clipped to [0, 1] with HDR relMSE beside it. A test view whose reference is entirely black (no light "
               "reaches what its camera sees; `of which black`) has no exposure of its own and is displayed with the "
               "median exposure of the others; in linear PSNR such a view only rewards black output. "
               "`all scenes`: pooled over every scene's views (the paper's Mixed row is the mixed model on its own "
               "test set). Paper figures beside ours where the paper has the scene. `per-scene +normal+depth` "
               "(profile `variant_scenes`): the documented variant fed albedo, normal and depth ({variant_parameters} "
               "parameters against the paper network's {parameters}), trained and measured like the per-scene model "
               "on the same views, with a linear learning-rate warm-up over its first Adam steps (the reconstruction "
               "profile's `normal_depth_warmup_steps`, in the provenance). `per-scene demodulated` (profile "
               "`demodulated_scenes`): the paper's network "
               "({demodulated_parameters} parameters) denoising the noisy colour divided by the albedo and "
               "multiplying its output back (`reconstruction.models.Denoiser(demodulate=True)`), trained and measured "
               "the same way. `per-scene perceptual` (profile `perceptual_scenes`): the paper's network working on "
               "`log1p(g·x)/log1p(G)` of the radiance x instead of `log1p(x)`, g = G times the exposure of its "
               "training references, and trained with the paper's loss in that space "
               "(`reconstruction.models.Denoiser(perceptual=G)`, G the reconstruction profile's "
               "`denoiser_perceptual_gain`): errors weighted roughly as the display weights them. "
               "The references' own noise, as PSNRs estimated from the noisy input's error and the spp "
               "ratio: `reference_psnr_lowest` on the worst test view and `reference_psnr_pooled` over all of them; "
               "each `reference_margin` is that minus the best pooled PSNR of the row (ours, OIDN or noisy). The pooled "
               "margin says how far reference noise can move the row's pooled PSNRs (6 dB: at most 1 dB). "
               "`reference_margin_per_view_db`: the smallest, over the test views, of a view's own reference PSNR "
               "minus the best PSNR of the row's model, OIDN and the noisy input on that view. `test_reference_spp`: "
               "samples per pixel of the test views' references (the dataset's, or refined: "
               "`reconstruction.test_references`, the profile's `test_reference_spp_by_scene`)."),
    "table3": ("Table 3 — the mixed model on each scene and on a scene it never saw",
               "`psnr_difference` = per-scene model minus mixed model on the same test views (positive: the "
               "per-scene model is better, as in the paper). The unseen scene is measured on all its views, none "
               "of which the mixed model saw; the paper's unseen scene is Pine, ours differs. "
               "`mixed_pixels_beyond_input`: pixels of the mixed model's output brighter than anything in their own "
               "noisy frame (a denoiser averages samples, so such a pixel is a blown-up output, not a denoising error; "
               "`reconstruction.evaluate.beyond_input`); `mixed_pixels_black_where_lit`: pixels it made exactly black "
               "where the noisy input has light (negative network outputs are clamped to 0, so a collapsed output shows "
               "as black patches; `reconstruction.evaluate.black_where_lit`). Both are failures of a different kind from "
               "a low PSNR and are counted apart. `mixed perceptual` (profile `perceptual_mixed`): the mixed model "
               "trained in the perceptual transfer of Table 2's `per-scene perceptual` variant, on the same crops."),
    "table5": ("Table 5 — superresolution 2x against bicubic and Lanczos",
               "Each target is reduced 2x ({downsample}) and upsampled back; PSNR/RMSE pooled, clipped to [0, 1], "
               "linear. Photos: whole images (train and validation photos were used in training / model choice; the "
               "test photos never). Scenes: reference renders of the test views. The paper's per-scene rows repeat "
               "its Table 2 (a typesetting error) and are not shown. `ours, display-trained` (profile "
               "`superres_display`): the same network trained on display-encoded images "
               "(`reconstruction.models.Superresolution(space=\"display\")`): the half-size image is reduced in linear "
               "radiance, shown with the target's exposure and sRGB curve, and upsampled there; `bicubic of the "
               "displayed image` is its own input, bicubic upsampling in that space. Its linear columns are of the "
               "linear image that displays as its output does."),
    "table6": ("Table 6 — network evaluation seconds, ours against OIDN and bicubic in the same run",
               "Per scene: the default view at the report frame size, {spp} spp (our path tracer) with a Mitsuba "
               "reference; seconds are medians of 3 calls after a warm-up, torch threads as listed, OIDN on its own "
               "threads; PSNR against the reference checks what was timed. Options: the fast-inference mode chosen "
               "(a faster mode only if PSNR changes by at most 0.05 dB). Paper seconds: Keras on the paper's CPU, "
               "512 -> 1024; only ratios compare across machines. Superresolution arithmetic: superres_gflop is "
               "the network's work per output frame (2 FLOP per weight and output pixel), superres_gflops its "
               "achieved rate, matmul_gflops this machine's dense matmul rate in the same mode and run, and "
               "superres_floor_s their quotient, the network's time at that rate. Timed calls keep freed memory "
               "for reuse (the allocator in the provenance's machine record), as the sweep's timings do."),
    "quality": ("Reconstruction quality on the test views (PSNR, dB)",
                "Denoising: noisy input / our per-scene model / the mixed model / OIDN (albedo and normal); "
                "superresolution 2x: bicubic / Lanczos / ours. Paper figures from Tables 2 and 3."),
}


def _schedule(reconstruction: Any) -> str:
    """The denoisers' learning-rate schedule in words."""
    warmup = (f", a {reconstruction.denoiser_warmup_steps}-step linear warm-up"
              if reconstruction.denoiser_warmup_steps else "")
    return (f"denoisers trained with Adam at {reconstruction.denoiser_rate:g}, {reconstruction.denoiser_decay} "
            f"learning rate{warmup}")


def _header(stem: str, m: dict, provenance: dict, reconstruction: Any) -> str:
    title, note = _TITLES[stem]
    note = note.format(downsample=reconstruction.superres_downsample, spp=m["frame_spp"],
                       parameters=m["parameters"]["denoiser"],
                       variant_parameters=m["parameters"].get("normal_depth_denoiser", "no"),
                       demodulated_parameters=m["parameters"].get("demodulated_denoiser", "no"))
    machine = provenance["machine"]
    from reconstruction.train import resolve_precision

    precision, why = resolve_precision(reconstruction.precision)
    reused = [s for s in m["stages"] if s["reused"]]
    made = [s for s in m["stages"] if not s["reused"]]
    made_list = ", ".join(f"{s['name']} ({s['seconds']:.0f} s)" for s in made)
    cache = (f"Reused from the cache: {len(reused)} of {len(m['stages'])} datasets and models"
             + (f"; made in this run: {made_list}" if made else "") + ".")
    return (f"# {title} ({m['profile']} profile)\n\n{note}\n\n"
            f"Reconstruction profile `{m['reconstruction_profile']}` ({reconstruction.width}x{reconstruction.height} "
            f"views, {reconstruction.spp} spp input, {reconstruction.reference} references at "
            f"{reconstruction.reference_spp} spp; epochs: "
            + ", ".join(f"{k} {v}" for k, v in m["epochs"].items()) + f"; {_schedule(reconstruction)}; kept epochs: "
            + ", ".join(f"{k} {v}" for k, v in m["best_epochs"].items()) + "). "
            f"Training arithmetic on this machine: {why or precision}. "
            f"Machine: {machine['cpu']}, {machine['cores']} cores; {machine['date']}. {cache}\n\n")


def write_outputs(m: dict, config: Config, out_dir: Path) -> dict[str, pd.DataFrame]:
    """Write every table (Markdown and CSV) and the provenance record, atomically."""
    reconstruction = config.reconstruction.profile(m["reconstruction_profile"])
    provenance = stamp(config.to_dict(), profile=m["profile"], seed=config.profile(m["profile"]).seed,
                       stages=m["stages"], best_epochs=m["best_epochs"], parameters=m["parameters"],
                       fast_inference={name: t["decisions"] for name, t in m["timing"].items()})
    tables = {"table2": _table2(m), "table3": _table3(m), "table5": _table5(m), "table6": _table6(m),
              "quality": _quality(m)}
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = {}
    for stem, rows in tables.items():
        frames[stem] = pd.DataFrame(rows)
        scene_columns = ("scene", "data")
        text = _header(stem, m, provenance, reconstruction) + _views_markdown(stem, rows, scene_columns, f"{stem}.csv")
        if stem == "table6" and m.get("plugin_denoisers"):
            plugins = _table6_plugins(m)
            text += ("\n## Plug-in denoisers\n\nEach plug-in (`kdtrace report --denoiser SPEC`) on the same frame: "
                     "noisy colour, albedo and normal in, medians of 3 calls after a warm-up (its output validated "
                     "on the clock); OIDN's seconds and PSNR are the table's above. A plug-in that raised or returned "
                     "invalid output shows `failed: ...`.\n\n" + _markdown(plugins) + "\n")
            atomic_write_bytes(out_dir / "table6_plugins.csv", pd.DataFrame(plugins).to_csv(index=False).encode())
        atomic_write_bytes(out_dir / f"{stem}.md", text.encode())
        atomic_write_bytes(out_dir / f"{stem}.csv", frames[stem].to_csv(index=False).encode())
    atomic_write_bytes(out_dir / "reconstruction_provenance.json",
                       json.dumps({**provenance, "measurements": m}, indent=1, default=str).encode())
    return frames


def write_figures(m: dict, objects: dict[str, Any], config: Config, out_dir: Path) -> list[Path]:
    """The paper's Figures 4, 5-6 and 7 as PNGs in ``out_dir/figures`` and their index ``figures.md``.

    Figure 4: every model's training curves. Per reconstruction scene, one test view
    (:func:`reports.figures.scene_figures`: the first in name order): noisy / per-scene /
    mixed / (demodulated and perceptual variants, where trained) / OIDN / reference, and bicubic / ours / reference superresolution; per
    never-seen scene, noisy / mixed / OIDN / reference on its first view. For the verdict page, the
    linear images of each scene's strip (noisy / per-scene / mixed / OIDN / reference; never-seen
    scenes without the per-scene model) as EXR (:func:`reports.figures.write_linear_strip`).
    """
    from reports.figures import markdown_links, scene_figures, training_curves, write_linear_strip

    recon = config.reconstruction.profile(m["reconstruction_profile"])
    paths = {"training": training_curves(m["histories"], out_dir / "figures" / "training.png")}
    variants = objects.get("variants", {})
    for name in m["scenes"]:
        panels = {"ours": objects["models"][name], "mixed": objects["mixed"],
                  **{f"ours {key}": variants[key][name] for key in ("demodulated", "perceptual")
                     if name in variants.get(key, {})}}
        paths.update(scene_figures(name, objects["datasets"][name], panels, objects["superres"], out_dir,
                                   downsample=recon.superres_downsample))
    for role in ("unseen", "far"):
        name = m["unseen"] if role == "unseen" else m.get("far")
        if name:
            dataset = objects["datasets"][name]
            found = scene_figures(name, dataset, {"mixed": objects["mixed"]}, objects["superres"], out_dir,
                                  view=dataset.views()[0], downsample=recon.superres_downsample)
            paths.update({key: path for key, path in found.items() if "denoising" in key})
            write_linear_strip(name, dataset, {"mixed": objects["mixed"]}, out_dir, split=None)
    for name in m["scenes"]:
        write_linear_strip(name, objects["datasets"][name], {"ours": objects["models"][name], "mixed": objects["mixed"]},
                           out_dir)
    text = (f"# Figures ({m['profile']} profile)\n\nThe paper's Figure 4 (training curves: solid train, dashed "
            "validation, a dot at each kept epoch) and, per scene, Figures 5-7 on one test view (the first in name "
            "order, not the best-looking one; never-seen scenes: their first view) with each panel's PSNR under it "
            "and an enlarged crop (the window with the most detail in the reference). Display: linear values "
            "clipped to [0, 1], sRGB curve.\n\n" + markdown_links(paths, out_dir) + "\n")
    atomic_write_bytes(out_dir / "figures.md", text.encode())
    return list(paths.values())


def metrics_of(m: dict) -> list[Metric]:
    """The gated metrics of one run (see :mod:`reports.metrics`)."""
    out = [Metric("table2/denoiser/parameters", "count", m["parameters"]["denoiser"], "trainable parameters"),
           Metric("table5/superres/parameters", "count", m["parameters"]["superres"], "trainable parameters")]
    for name in m["scenes"]:
        q = m["quality"][name]
        out += [Metric(f"table2/{name}/ours_test_psnr", "psnr", q["ours"]["test"]["ours"]["psnr"],
                       "per-scene denoiser, test views, dB"),
                Metric(f"table2/{name}/mixed_test_psnr", "psnr", q["mixed"]["test"]["psnr"],
                       "mixed denoiser, this scene's test views, dB"),
                Metric(f"table5/{name}/ours_test_psnr", "psnr", q["superres"]["ours"]["psnr"],
                       "superresolution 2x, test views, dB")]
        out += _display_metrics(f"table2/{name}/ours", q["ours"]["test"]["ours"], "per-scene denoiser, test views")
        out += _display_metrics(f"table2/{name}/mixed", q["mixed"]["test"], "mixed denoiser, this scene's test views")
        out += _display_metrics(f"table5/{name}/ours", q["superres"]["ours"], "superresolution 2x, test views",
                                with_flip=False)
        if "superres_display" in q:
            out += _display_metrics(f"table5/{name}/display_trained", q["superres_display"]["ours"],
                                    "display-trained superresolution 2x, test views", with_flip=False)
        if "mixed_perceptual" in q:
            out += _display_metrics(f"table3/{name}/mixed_perceptual", q["mixed_perceptual"]["test"],
                                    "perceptual mixed denoiser, this scene's test views")
        for variant in (v for v in DENOISER_VARIANTS if v.key in q):
            out.append(Metric(f"table2/{name}/{variant.key}_test_psnr", "psnr", q[variant.key]["test"]["psnr"],
                              f"per-scene {variant.label} variant, test views, dB"))
        t = m["timing"][name]
        out += [Metric(f"table6/{name}/oidn_over_ours_seconds", "ratio", t["denoise"]["oidn_over_ours"],
                       f"OIDN seconds / ours ({t['denoise_option']}), same frame"),
                Metric(f"table6/{name}/bicubic_over_ours_seconds", "ratio", t["superres"]["bicubic_over_ours"],
                       f"bicubic seconds / our superresolution ({t['superres_option']}), same frame")]
    if m["unseen_quality"]:
        out.append(Metric(f"table3/{m['unseen']}/mixed_psnr", "psnr", m["unseen_quality"]["ours"]["psnr"],
                          "mixed denoiser on the never-seen scene, all views, dB"))
        out += _display_metrics(f"table3/{m['unseen']}/mixed", m["unseen_quality"]["ours"],
                                "mixed denoiser on the never-seen scene, all views")
        if "mixed_perceptual" in m["unseen_quality"]:
            out += _display_metrics(f"table3/{m['unseen']}/mixed_perceptual", m["unseen_quality"]["mixed_perceptual"],
                                    "perceptual mixed denoiser on the never-seen scene, all views")
    if m.get("far_quality"):
        out.append(Metric(f"table3/{m['far']}/mixed_psnr", "psnr", m["far_quality"]["ours"]["psnr"],
                          "mixed denoiser on the far never-seen scene, all views, dB"))
    out.append(Metric("table5/photos/ours_test_psnr", "psnr", m["photos"]["test"]["ours"]["psnr"],
                      "superresolution 2x, held-out photos, dB"))
    out += _display_metrics("table5/photos/ours", m["photos"]["test"]["ours"], "superresolution 2x, held-out photos",
                            with_flip=False)
    if m.get("photos_display"):
        out += _display_metrics("table5/photos/display_trained", m["photos_display"]["test"]["ours"],
                                "display-trained superresolution 2x, held-out photos", with_flip=False)
    return out + plugin_metrics(m)


def _display_metrics(prefix: str, result: dict, what: str, with_flip: bool = True) -> list[Metric]:
    """``PREFIX_display_psnr`` (and ``PREFIX_flip``) of one pooled result, where it has them."""
    out = []
    if math.isfinite(result.get("display_psnr", math.nan)):
        out.append(Metric(f"{prefix}_display_psnr", "psnr", result["display_psnr"], f"{what}, display-referred dB"))
    if with_flip and "flip" in result:
        out.append(Metric(f"{prefix}_flip", "flip", result["flip"], f"{what}, mean LDR-FLIP of the displayed images"))
    return out


def plugin_metrics(m: dict) -> list[Metric]:
    """The plug-in denoisers' metrics: ``table2/SCENE/plugin:SPEC/{failed,test_psnr}``, ``table6/.../oidn_over_plugin_seconds``.

    Never part of a baseline (:mod:`reports.plugins`); ``failed`` (``zero``) fails the run.
    """
    from reports.plugins import metric_name

    out = []
    for spec, by_scene in m.get("plugin_denoisers", {}).items():
        for name in m["scenes"]:
            result = by_scene[name]
            out.append(Metric(metric_name("table2", name, spec, "failed"), "zero", int(bool(result.get("failed"))),
                              result.get("failed") or "ran"))
            if result.get("failed"):
                continue
            if math.isfinite(result["test"]["psnr"]):
                out.append(Metric(metric_name("table2", name, spec, "test_psnr"), "psnr", result["test"]["psnr"],
                                  "plug-in denoiser, test views, dB"))
            out.append(Metric(metric_name("table6", name, spec, "oidn_over_plugin_seconds"), "ratio",
                              result["oidn_over_plugin"], "OIDN seconds / plug-in seconds, same frame"))
    return out


def generate(config: Config, profile_name: str, out_dir: str | Path, fresh: bool = False,
             progress: bool = True, denoisers: list[str] | tuple[str, ...] = ()) -> list[Metric]:
    """Run (or reuse) the reconstruction experiments of a profile and write Tables 2, 3, 5, 6.

    Parameters
    ----------
    config : Config
        Resolved configuration.
    profile_name : str
        A report profile (``[profiles.NAME]``); its ``reconstruction_profile``,
        ``reconstruction_scenes``, ``unseen_scene`` and frame size are used.
    out_dir : str or Path
        Receives ``table2``, ``table3``, ``table5``, ``table6``, ``quality`` (``.md`` and
        ``.csv``), ``reconstruction_provenance.json`` and ``metrics/reconstruction.json``.
    fresh : bool
        Render the Mitsuba references of the timed frames again instead of loading them
        from the cache. Datasets and models are keyed by content and deterministic, so
        they are always reused; point ``KDTRACE_CACHE`` elsewhere to rebuild them.
    progress : bool
        Show a tqdm bar over the steps.
    denoisers : sequence of str
        Plug-in denoiser specs (``kdtrace report --denoiser``): each measured on the same
        test views (Table 2 rows ``plug-in SPEC``) and timed on the same frame (a section
        of table6.md and ``table6_plugins.csv``), :func:`measure_plugin_denoisers`. Not in
        the figures.

    Returns
    -------
    list of Metric
        PSNRs (dB) of every per-scene, mixed and superresolution test result, the two
        parameter counts, and per scene the same-run speed ratios OIDN/ours and
        bicubic/ours superresolution seconds (higher is better for us); per plug-in
        :func:`plugin_metrics`.
    """
    out_dir = Path(out_dir)
    if not config.profile(profile_name).reconstruction_scenes:
        warnings.warn(f"reconstruction tables skipped: profile {profile_name!r} has no reconstruction scenes "
                      "(left out by --scenes?)", ReportNote, stacklevel=2)
        return []
    measurements, objects = _measure(config, profile_name, fresh, progress, denoisers)
    for spec, by_scene in measurements.get("plugin_denoisers", {}).items():
        for name, result in by_scene.items():
            if result.get("failed"):
                warnings.warn(f"reconstruction: plug-in {spec!r} on {name}: {result['failed']}", ReportNote, stacklevel=2)
    reused = [stage["name"] for stage in measurements["stages"] if stage["reused"]]
    if reused:
        warnings.warn(f"reconstruction: reused {len(reused)} of {len(measurements['stages'])} datasets and models "
                      "from the cache", ReportNote, stacklevel=2)
    write_outputs(measurements, config, out_dir)
    write_figures(measurements, objects, config, out_dir)
    metrics = metrics_of(measurements)
    write_metrics(out_dir, "reconstruction", metrics)
    return metrics
