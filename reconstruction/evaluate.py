"""The quality table: denoiser and superresolution against their baselines on held-out views.

For each scene, on the **test views** of its Precision Graphics dataset (whole views, never
seen in training or model selection):

* **denoising** — the noisy input, our denoiser and Intel Open Image Denoise
  (:func:`reconstruction.baselines.oidn`, with albedo and normal), each against the
  reference render;
* **superresolution 2×** — each reference clipped to [0, 1] is reduced 2x
  (:func:`downsample_2x`, the profile's ``superres_downsample``) and upsampled back by
  bicubic (the net's own input), Lanczos-3 and our Y-channel net
  (:func:`superres_images`); the same on whole photographs, among them the held-out
  photo test set :data:`TEST_PHOTOS`.

Metrics are **pooled over the split**: RMSE is the root of the mean squared error over
every pixel and channel of every test view (linear values clipped to [0, 1], the
convention of :mod:`reconstruction.metrics`), and PSNR = −20·log10(RMSE). The mean of
per-image PSNRs is reported beside it (``psnr_mean``) but not used for comparisons: it is
inflated by flat, nearly error-free images (a crop of a plain wall can reach 50 dB).

The display-referred metrics of an image pair (FLIP and SSIM take about 2 s on a 2-megapixel
photo) are reused by content hash (:func:`cached_display_metrics`): a rerun, or a second
table on the same images (the noisy input and OIDN beside each model), measures them once.

Entry point :func:`main_quality` trains (or reuses, by content key) the per-scene
denoisers and one superresolution net over the given scenes, then writes the table as
Markdown and CSV, each atomically.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import math
from collections.abc import Sequence
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from torch import nn

from kdtrace.cache import atomic_write_bytes, cache_root, content_key, source_fingerprint
from kdtrace.config import ReconstructionProfile
from kdtrace.markdown import markdown_table
from reconstruction.data import resolve_profile

#: Columns of the quality table, in order.
COLUMNS = ("scene", "task", "method", "psnr", "rmse", "psnr_mean", "images", "pixels")


def pooled(predictions: Sequence[np.ndarray], references: Sequence[np.ndarray]) -> dict[str, float]:
    """Pooled metrics of image pairs, linear and (for RGB) display-referred.

    Parameters
    ----------
    predictions, references : sequences of ndarray
        Matching shapes per pair (any layout, e.g. (H, W, 3)); linear radiance.

    Returns
    -------
    dict
        Linear, clipped to [0, 1]: ``rmse`` (over all values of all pairs), ``psnr`` (−20·log10
        of it, ``inf`` if zero), ``psnr_mean`` (mean of the per-image PSNRs, each capped at 100
        dB), ``per_image_psnr`` (those PSNRs, in the order of the pairs). HDR: ``relmse`` and
        ``smape`` (means over all values, :mod:`reconstruction.metrics`). When every pair is
        (H, W, 3), display-referred (each view tonemapped with its reference's exposure,
        :func:`reconstruction.metrics.display_metrics`; a view with an all-black reference with
        the median exposure of the others, counted in ``black_references``): ``display_rmse``
        and ``display_psnr`` pooled over all displayed values, and ``flip``, the pixel-weighted
        mean FLIP. Also
        ``images`` and ``pixels`` (values counted / channels are not separated).
    """
    from reconstruction import metrics

    if len(predictions) == 0 or len(predictions) != len(references):
        raise ValueError(f"need matching, non-empty image lists, got {len(predictions)} and {len(references)}")
    squared, count, per_image = 0.0, 0, []
    relative = {"relmse": 0.0, "smape": 0.0}
    display = {"squared": 0.0, "flip": 0.0} if all(np.ndim(r) == 3 and np.shape(r)[2] == 3 for r in references) else None
    own, exposures = metrics.display_exposures(references) if display is not None else ([], [])
    for index, (prediction, reference) in enumerate(zip(predictions, references, strict=True)):
        prediction, reference = np.asarray(prediction, np.float64), np.asarray(reference, np.float64)
        if prediction.shape != reference.shape:
            raise ValueError(f"prediction {prediction.shape} and reference {reference.shape} differ in shape")
        if not (np.all(np.isfinite(prediction)) and np.all(np.isfinite(reference))):
            raise ValueError("images contain NaN/inf values")
        error = float(np.sum((np.clip(prediction, 0, 1) - np.clip(reference, 0, 1)) ** 2))
        squared += error
        count += prediction.size
        mse = error / prediction.size
        per_image.append(100.0 if mse == 0 else min(100.0, -10.0 * math.log10(mse)))
        relative["relmse"] += metrics.relmse(prediction, reference) * prediction.size
        relative["smape"] += metrics.smape(prediction, reference) * prediction.size
        if display is not None:
            shown = cached_display_metrics(prediction, reference, exposures[index])
            display["squared"] += shown["display_rmse"] ** 2 * prediction.size
            display["flip"] += shown["flip"] * prediction.size
    rmse = math.sqrt(squared / count)
    result = {"psnr": math.inf if rmse == 0 else -20.0 * math.log10(rmse), "rmse": rmse,
              "psnr_mean": float(np.mean(per_image)), "per_image_psnr": per_image, "images": len(per_image),
              "pixels": count, **{name: total / count for name, total in relative.items()}}
    if display is not None:
        result.update(_display_pooled(display["squared"] / count, display["flip"] / count))
        result["black_references"] = sum(exposure is None for exposure in own)
    return result


@functools.cache
def _display_metrics_code() -> tuple[str, str, str]:
    """What the display metrics' values depend on besides the images: the source of
    :mod:`reconstruction.metrics` and the versions of flip-evaluator and scikit-image (read once)."""
    from reconstruction import metrics

    return source_fingerprint(metrics), version("flip-evaluator"), version("scikit-image")


def cached_display_metrics(test: np.ndarray, reference: np.ndarray, exposure: float) -> dict[str, float]:
    """:func:`reconstruction.metrics.display_metrics` of one pair, reused by content hash.

    The key holds both images' bytes, shapes and dtypes, the exposure, the source of
    :mod:`reconstruction.metrics` and the versions of flip-evaluator and scikit-image, so
    any change to what is measured or how measures again. Stored as JSON under
    ``cache_root()/display-metrics``; an unreadable entry is measured again and rewritten.
    """
    from reconstruction import metrics

    digest = hashlib.blake2b(digest_size=32)
    for image in (test, reference):
        image = np.ascontiguousarray(image)
        digest.update(f"{image.dtype.str}{image.shape}".encode())
        digest.update(image.data)
    key = content_key("display-metrics", digest.hexdigest(), float(exposure), _display_metrics_code())
    path = cache_root() / "display-metrics" / f"{key[:32]}.json"
    try:
        return {name: float(value) for name, value in json.loads(path.read_text()).items()}
    except (OSError, ValueError, AttributeError):
        pass
    shown = metrics.display_metrics(test, reference, exposure)
    atomic_write_bytes(path, json.dumps(shown).encode())
    return shown


def _display_pooled(mean_squared: float, flip: float) -> dict[str, float]:
    display_rmse = math.sqrt(mean_squared)
    return {"display_rmse": display_rmse, "display_psnr": math.inf if display_rmse == 0 else -20.0 * math.log10(display_rmse),
            "flip": flip}


def denoise_view(model: nn.Module, view: dict[str, np.ndarray], auxiliary: tuple[str, ...] = ("albedo",)) -> np.ndarray:
    """Denoise one whole view of a dataset with ``model``; (H, W, 3) linear radiance."""
    from reconstruction.hdr import decode
    from reconstruction.train import denoiser_tensors

    planes = {name: view[name].transpose(2, 0, 1)[None] for name in ("noisy", "reference", *auxiliary)}
    inputs, _ = denoiser_tensors(planes, auxiliary)
    was_training = model.training
    model.eval()
    with torch.no_grad():
        output = decode(model(inputs))
    model.train(was_training)
    return output[0].permute(1, 2, 0).numpy()


def beyond_input(outputs: Sequence[np.ndarray], inputs: Sequence[np.ndarray]) -> int:
    """Pixels of the denoised ``outputs`` brighter than anything in their noisy input.

    A denoiser averages samples: no output pixel can be brighter than the brightest value of
    its own noisy frame. A pixel above it (in any channel) is a blown-up network output, not
    a denoising error; its PSNR alone would hide that.

    Parameters
    ----------
    outputs, inputs : sequences of ndarray, (H, W, 3)
        Linear radiance of each view, denoised and noisy.

    Returns
    -------
    int
        Pixels, over all views, with a channel above the view's input maximum.
    """
    return int(sum(np.count_nonzero(np.any(output > float(np.max(noisy)), axis=-1))
                   for output, noisy in zip(outputs, inputs, strict=True)))


def black_where_lit(outputs: Sequence[np.ndarray], inputs: Sequence[np.ndarray]) -> int:
    """Pixels the denoiser made exactly black (every channel 0) where the noisy input has light.

    The decode clamps negative network outputs to radiance 0 (:func:`reconstruction.hdr.decode`),
    so a network pushed far below its input on an unfamiliar scene shows as patches of exact
    black: a collapsed output, not a denoising error.
    """
    return int(sum(np.count_nonzero(np.all(output <= 0.0, axis=-1) & np.any(noisy > 0.0, axis=-1))
                   for output, noisy in zip(outputs, inputs, strict=True)))


def denoiser_quality(model: nn.Module, dataset, split: str | None = "test", auxiliary: tuple[str, ...] = ("albedo",),
                     with_oidn: bool = True) -> dict[str, dict[str, float]]:
    """Pooled metrics of noisy input, ``model`` and (optionally) OIDN on the views of one split.

    ``split=None`` takes every view (e.g. a scene the model never saw).

    Returns
    -------
    dict
        Method (``"noisy"``, ``"ours"``, ``"oidn"``) -> :func:`pooled` metrics; ``"ours"`` also
        has ``beyond_input``, the pixels brighter than their whole noisy frame (:func:`beyond_input`),
        and ``black_where_lit``, the pixels made black where the input has light (:func:`black_where_lit`).
    """
    from reconstruction.baselines import noisy_input, oidn

    outputs: dict[str, list[np.ndarray]] = {"noisy": [], "ours": [], **({"oidn": []} if with_oidn else {})}
    references = []
    for name in dataset.views(split):
        view = dataset.load_view(name)
        references.append(view["reference"])
        outputs["noisy"].append(noisy_input(view["noisy"]))
        outputs["ours"].append(denoise_view(model, view, auxiliary))
        if with_oidn:
            outputs["oidn"].append(oidn(view["noisy"], view["albedo"], view["normal"]))
    quality = {method: pooled(images, references) for method, images in outputs.items()}
    quality["ours"]["beyond_input"] = beyond_input(outputs["ours"], outputs["noisy"])
    quality["ours"]["black_where_lit"] = black_where_lit(outputs["ours"], outputs["noisy"])
    return quality


#: Photographs held out from superresolution training and validation (the photo test set,
#: Table 5), bundled with scikit-image (no download): the left view of the Middlebury
#: motorcycle stereo pair and the Hubble deep field. Chosen for being the remaining
#: bundled colour photographs, before any model was evaluated on them.
TEST_PHOTOS = ("motorcycle_left", "hubble_deep_field")


def held_out_photo(name: str) -> np.ndarray:
    """One photograph of :data:`TEST_PHOTOS` as linear RGB float32 (H, W, 3) in [0, 1]."""
    from kdtrace.imageio import srgb_decode
    from reconstruction.data import photo

    if name not in TEST_PHOTOS:
        raise ValueError(f"unknown test photo {name!r}; known: {', '.join(TEST_PHOTOS)}")
    if name == "motorcycle_left":
        import skimage.data

        return srgb_decode(skimage.data.stereo_motorcycle()[0][..., :3] / 255.0)
    return photo(name)


def downsample_2x(image: np.ndarray, method: str = "area") -> np.ndarray:
    """The half-resolution image the superresolution net is given, (H, W, 3) -> (H/2, W/2, 3).

    ``"area"``: 2x2 box mean; ``"bicubic"``: antialiased bicubic (the two reductions of
    :func:`reconstruction.data.degrade`). H and W must be even.
    """
    import torch.nn.functional as F

    image = np.asarray(image, np.float32)
    if image.ndim != 3 or image.shape[0] % 2 or image.shape[1] % 2:
        raise ValueError(f"image must be (H, W, C) with even H and W, got {image.shape}")
    tensor = torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))[None]
    if method == "area":
        small = F.avg_pool2d(tensor, 2)
    elif method == "bicubic":
        small = F.interpolate(tensor, scale_factor=0.5, mode="bicubic", align_corners=False, antialias=True)
    else:
        raise ValueError(f"unknown downsampling {method!r}; use 'area' or 'bicubic'")
    return small[0].permute(1, 2, 0).numpy().copy()


def superres_images(model: nn.Module, targets: Sequence[np.ndarray], downsample: str = "area",
                    with_lanczos: bool = True) -> dict[str, dict[str, float]]:
    """Pooled metrics of bicubic, Lanczos and ``model`` 2x upsampling of ``targets``.

    Each target (linear RGB, clipped to [0, 1], trimmed to even sides) is reduced 2x
    (:func:`downsample_2x`) and upsampled back: bicubic
    (:func:`reconstruction.baselines.bicubic`, the net's own input), Lanczos-3
    (:func:`reconstruction.baselines.lanczos`) and ours
    (:func:`reconstruction.models.superresolve`: the net refines Y, Cb and Cr stay bicubic).
    A net of the display space (``model.space == "display"``) and its two baselines upsample the
    half-size image as it is shown (:func:`reconstruction.metrics.to_display` with the target's
    display exposure, :func:`reconstruction.metrics.display_exposures`); their outputs are
    measured as the linear images that display as they do (``srgb_decode(shown) / exposure``),
    so both spaces' metrics apply to them.

    Parameters
    ----------
    model : nn.Module
        The superresolution net.
    targets : sequence of ndarray
        (H, W, 3) images of any sizes (at least 2x2).
    downsample : {"area", "bicubic"}
    with_lanczos : bool

    Returns
    -------
    dict
        ``"bicubic"``, ``"lanczos"`` (if asked) and ``"ours"`` -> :func:`pooled` metrics.
    """
    from kdtrace.imageio import srgb_decode
    from reconstruction import metrics
    from reconstruction.baselines import bicubic, lanczos
    from reconstruction.models import superresolve

    methods = {"bicubic": bicubic, **({"lanczos": lanczos} if with_lanczos else {}),
               "ours": lambda low: superresolve(model, low)}
    references, lows = [], []
    for target in targets:
        target = np.clip(np.asarray(target, np.float32), 0.0, 1.0)
        target = target[: target.shape[0] // 2 * 2, : target.shape[1] // 2 * 2]
        references.append(target)
        lows.append(np.clip(downsample_2x(target, downsample), 0.0, 1.0))
    displayed = getattr(model, "space", "linear") == "display"
    exposures = metrics.display_exposures(references)[1] if displayed else [1.0] * len(references)
    outputs: dict[str, list[np.ndarray]] = {name: [] for name in methods}
    was_training = model.training
    model.eval()
    for low, exposure in zip(lows, exposures, strict=True):
        for name, upsample in methods.items():
            if displayed:
                shown = upsample(metrics.to_display(low, exposure).astype(np.float32))
                outputs[name].append(srgb_decode(shown) / np.float32(exposure))  # every upsampler clamps to [0, 1]
            else:
                outputs[name].append(upsample(low))
    model.train(was_training)
    return {name: pooled(images, references) for name, images in outputs.items()}


def superres_quality(model: nn.Module, dataset, split: str | None = "test", downsample: str = "area",
                     with_lanczos: bool = True) -> dict[str, dict[str, float]]:
    """:func:`superres_images` on the references of the views of one split (None: all views)."""
    return superres_images(model, [dataset.load_view(name)["reference"] for name in dataset.views(split)],
                           downsample, with_lanczos)


def combine(results: Sequence[dict[str, float]]) -> dict[str, float]:
    """Pool several :func:`pooled` results (of disjoint image sets) into one.

    RMSE is recombined from the squared errors (``rmse**2 * pixels``), so the result is
    exactly :func:`pooled` over the union; ``psnr_mean`` is the image-weighted mean.
    """
    if not results:
        raise ValueError("nothing to combine")
    pixels = sum(r["pixels"] for r in results)
    images = sum(r["images"] for r in results)
    rmse = math.sqrt(sum(r["rmse"] ** 2 * r["pixels"] for r in results) / pixels)
    combined = {"psnr": math.inf if rmse == 0 else -20.0 * math.log10(rmse), "rmse": rmse,
                "psnr_mean": sum(r["psnr_mean"] * r["images"] for r in results) / images,
                "images": images, "pixels": pixels}
    for name in ("relmse", "smape"):
        if all(name in r for r in results):
            combined[name] = sum(r[name] * r["pixels"] for r in results) / pixels
    if all("black_references" in r for r in results):
        combined["black_references"] = sum(r["black_references"] for r in results)
    if all("display_rmse" in r for r in results):
        combined.update(_display_pooled(sum(r["display_rmse"] ** 2 * r["pixels"] for r in results) / pixels,
                                        sum(r["flip"] * r["pixels"] for r in results) / pixels))
    return combined


def quality_rows(scene: str, denoising: dict[str, dict[str, float]] | None,
                 superres: dict[str, dict[str, float]] | None) -> list[dict]:
    """Rows of the quality table for one scene (see :data:`COLUMNS`)."""
    rows = []
    for task, results in (("denoise", denoising), ("superres", superres)):
        for method, metrics in (results or {}).items():
            rows.append({"scene": scene, "task": task, "method": method,
                         **{name: metrics[name] for name in COLUMNS[3:]}})
    return rows


def to_markdown(table: pd.DataFrame) -> str:
    """A GitHub Markdown table of ``table`` (floats to 3 decimals for dB, 5 for RMSE)."""
    def cell(column: str, value) -> str:
        if isinstance(value, float):
            return f"{value:.5f}" if column == "rmse" else f"{value:.3f}"
        return str(value)

    return markdown_table(list(table.columns), [[cell(c, v) for c, v in zip(table.columns, row, strict=True)]
                                                for row in table.itertuples(index=False)])


def write_table(table: pd.DataFrame, out_dir: str | Path, stem: str = "quality") -> tuple[Path, Path]:
    """Write ``table`` to ``out_dir/<stem>.md`` and ``<stem>.csv``, each atomically."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    text = io.StringIO()
    table.to_csv(text, index=False)
    csv_path = atomic_write_bytes(out_dir / f"{stem}.csv", text.getvalue().encode())
    markdown_path = atomic_write_bytes(out_dir / f"{stem}.md", to_markdown(table).encode())
    return markdown_path, csv_path


def main_quality(scene_names: Sequence[str], profile: str | ReconstructionProfile = "quick",
                 out_dir: str | Path = "quality", with_oidn: bool = True,
                 progress: bool | None = None) -> pd.DataFrame:
    """Train (or reuse) the models and tabulate their quality on every scene's test views.

    Per scene: the per-scene (Precision Graphics) denoiser against the noisy input and
    OIDN; one superresolution net trained on the photos plus the training views of all
    ``scene_names``, against bicubic. Models and datasets are cached by content key
    (:mod:`reconstruction.train`, :mod:`reconstruction.data`), so a rerun only evaluates.

    Parameters
    ----------
    scene_names : sequence of str
    profile : str or ReconstructionProfile
    out_dir : str or Path
        Receives ``quality.md`` and ``quality.csv``.
    with_oidn : bool
        Include the OIDN baseline (needs ``pyoidn``).
    progress : bool, optional
        Progress bars (None: only on a terminal).

    Returns
    -------
    pandas.DataFrame
        Columns :data:`COLUMNS`, one row per scene, task and method.
    """
    from reconstruction.data import generate_dataset
    from reconstruction.train import train_denoiser, train_superres

    profile = resolve_profile(profile)
    scene_names = list(scene_names)
    if not scene_names:
        raise ValueError("no scenes given")
    datasets = {name: generate_dataset(name, profile, progress) for name in scene_names}
    superres_model = train_superres(profile, scene_names, progress=progress).model
    rows = []
    for name, dataset in datasets.items():
        denoiser = train_denoiser([name], profile, progress=progress).model
        rows += quality_rows(name, denoiser_quality(denoiser, dataset, "test", with_oidn=with_oidn),
                             superres_quality(superres_model, dataset, "test", profile.superres_downsample))
    table = pd.DataFrame(rows, columns=list(COLUMNS))
    write_table(table, out_dir)
    return table
