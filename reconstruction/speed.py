"""Same-run timing of the networks against their baselines (Table 6; bench groups ``denoise``, ``superres``).

A :class:`Frame` is one noisy render of a scene's default camera by our path tracer
(colour, albedo, normal) with a Mitsuba reference of the same view. On it:

* :func:`choose_options` runs :func:`reconstruction.inference.select_fast_inference` for
  the denoiser (PSNR of the decoded output against the reference) and for the
  superresolution net (PSNR of the luma against the reference's luma, input: the
  reference reduced 2x and bicubic-upsampled), accepting a faster execution mode only
  if the PSNR changes by at most 0.05 dB;
* :func:`time_denoise` times our denoiser end to end (HDR encode, network in the chosen
  mode, decode) against Intel Open Image Denoise on the same buffers, and
  :func:`time_superres` our 2x superresolution against bicubic upsampling of the same
  image. Each timing is the median of ``repeats`` calls after ``warmup`` untimed calls,
  and each output is checked afterwards (finite, right shape, PSNR recorded), so a fast
  but wrong result cannot pass unnoticed.

Seconds are wall-clock on this machine; only ratios within one run are meaningful.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from kdtrace.timing import median_seconds
from reconstruction import hdr, metrics
from reconstruction.inference import FastInferenceDecision, denoise, make_runner, select_fast_inference
from reconstruction.models import bicubic_upsample, superresolve, ycbcr_from_rgb


@dataclass(frozen=True)
class Frame:
    """One noisy frame with its auxiliary buffers and reference.

    Attributes
    ----------
    scene : str
    color, albedo, normal : ndarray
        float32 (H, W, 3): noisy linear radiance, albedo (diffuse map), shading normal.
    reference : ndarray
        float32 (H, W, 3), Mitsuba reference of the same view (linear).
    spp, reference_spp : int
        Samples per pixel of the noisy render and of the reference.
    """

    scene: str
    color: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray
    reference: np.ndarray
    spp: int
    reference_spp: int


def render_frame(scene_name: str, width: int, height: int, spp: int, max_depth: int, seed: int,
                 reference_spp: int, cache: bool = True) -> Frame:
    """Render the default view of a scene with our path tracer and Mitsuba (the reference).

    Parameters
    ----------
    scene_name : str
    width, height : int
        Pixels.
    spp, max_depth : int
        Noisy render (max_depth in Mitsuba's convention).
    seed : int
        Seed of the noisy render; the reference uses ``seed + 1``.
    reference_spp : int
        Mitsuba samples per pixel.
    cache : bool
        Reuse / store the Mitsuba reference in the cache (:func:`references.mitsuba.render_reference`).
    """
    from kdtrace.render import render
    from kdtrace.scenes import load_scene
    from references.mitsuba import render_reference

    scene = load_scene(scene_name)
    noisy = render(scene, spp=spp, max_depth=max_depth, seed=seed, width=width, height=height, aux=True)
    reference = render_reference(scene, spp=reference_spp, max_depth=max_depth, seed=seed + 1, width=width,
                                 height=height, cache=cache)
    return Frame(scene_name, *(np.ascontiguousarray(a, np.float32) for a in (noisy.rgb, noisy.albedo, noisy.normal,
                                                                             reference.rgb)), spp, reference_spp)


def superres_input(image: np.ndarray, downsample: str = "area") -> tuple[torch.Tensor, np.ndarray]:
    """Luma input of the superresolution net for ``image`` and the luma it should recover.

    Returns
    -------
    y_input : torch.Tensor, (1, 1, H, W)
        Y of the bicubic 2x upsampling of ``image`` (clipped to [0, 1], even sides) reduced 2x.
    y_target : ndarray, (H, W, 1)
        Y of the clipped ``image``.
    """
    from reconstruction.evaluate import downsample_2x

    target = np.clip(np.asarray(image, np.float32), 0.0, 1.0)
    target = target[: target.shape[0] // 2 * 2, : target.shape[1] // 2 * 2]
    low = torch.from_numpy(downsample_2x(target, downsample).transpose(2, 0, 1).copy())[None]
    y_input = ycbcr_from_rgb(bicubic_upsample(low).clamp(0.0, 1.0), channel_axis=-3)[:, :1].contiguous()
    y_target = ycbcr_from_rgb(target, channel_axis=-1)[..., :1]
    return y_input, np.asarray(y_target, np.float32)


def choose_options(denoiser: nn.Module, superres: nn.Module, frame: Frame, downsample: str = "area",
                   repeats: int = 3) -> dict[str, FastInferenceDecision]:
    """Fast-inference decisions (``"denoise"``, ``"superres"``) of both nets on ``frame``."""
    x = hdr.denoiser_input(frame.color, frame.albedo)[None]
    y_input, y_target = superres_input(frame.reference, downsample)
    return {"denoise": select_fast_inference(denoiser, x, frame.reference, decode=hdr.decode, repeats=repeats),
            "superres": select_fast_inference(superres, y_input, y_target, repeats=repeats)}


def _checked(image: np.ndarray, shape: tuple[int, ...], what: str) -> np.ndarray:
    image = np.asarray(image)
    if image.shape != shape or not np.all(np.isfinite(image)):
        raise ValueError(f"{what}: expected a finite image of shape {shape}, got {image.shape}")
    return image


def time_denoise(model: nn.Module, frame: Frame, option: str = "fp32", repeats: int = 3,
                 warmup: int = 1) -> dict[str, float]:
    """Seconds and PSNR of our denoiser (execution mode ``option``) and of OIDN on ``frame``.

    Returns
    -------
    dict
        ``ours_seconds``, ``oidn_seconds``, ``oidn_over_ours`` (higher: ours faster),
        ``noisy_psnr``, ``ours_psnr``, ``oidn_psnr`` (dB against the reference), ``pixels``.
    """
    from reconstruction.baselines import oidn

    runner = make_runner(model, option)
    ours_seconds, ours = median_seconds(lambda: denoise(model, frame.color, frame.albedo, runner=runner),
                                        repeats, warmup)
    oidn_seconds, theirs = median_seconds(lambda: oidn(frame.color, frame.albedo, frame.normal), repeats, warmup)
    shape = frame.color.shape
    return {"ours_seconds": ours_seconds, "oidn_seconds": oidn_seconds, "oidn_over_ours": oidn_seconds / ours_seconds,
            "noisy_psnr": metrics.psnr(frame.color, frame.reference),
            "ours_psnr": metrics.psnr(_checked(ours, shape, "ours"), frame.reference),
            "oidn_psnr": metrics.psnr(_checked(theirs, shape, "OIDN"), frame.reference),
            "pixels": shape[0] * shape[1]}


def full_resolution_gflop(model: nn.Module, pixels: int) -> float:
    """Arithmetic of a network whose every convolution runs at the output's resolution, GFLOP.

    Each weight is one multiply-add per output pixel (2 FLOP); true for the superresolution
    net of §5.1 (four 'same' convolutions on the upsampled image), not for the denoiser's
    U-Net. Biases and ReLUs are left out (under 0.2% here).
    """
    macs = sum(layer.weight.numel() for layer in model.modules() if isinstance(layer, nn.Conv2d))
    return 2.0 * macs * pixels / 1e9


def matmul_gflops(option: str = "fp32", size: int = 2048, repeats: int = 3) -> float:
    """This machine's dense matrix-multiply rate in GFLOP/s, in the precision of ``option``.

    A ``size``-square ``torch`` matmul (oneDNN/MKL, as near peak as this CPU gets from
    PyTorch) under bf16 autocast when ``option`` uses bf16; the same threads as the networks.
    Used as the attainable rate: a network of G GFLOP cannot run in under G / rate seconds.
    """
    a, b = torch.rand(size, size), torch.rand(size, size)
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled="bf16" in option):
        seconds, _ = median_seconds(lambda: a @ b, repeats)
    return 2.0 * size**3 / seconds / 1e9


def time_superres(model: nn.Module, image: np.ndarray, option: str = "fp32", repeats: int = 3,
                  warmup: int = 1) -> dict[str, float]:
    """Seconds of our 2x superresolution (mode ``option``) and of bicubic upsampling of ``image``.

    ``image`` (H, W, 3) in [0, 1] is upsampled to (2H, 2W). As a check of what was timed,
    both outputs are reduced 2x again (area) and compared with ``image``: a correct 2x
    upsampler reproduces its input closely (``*_consistency_psnr``, dB).

    Returns
    -------
    dict
        ``ours_seconds``, ``bicubic_seconds``, ``bicubic_over_ours`` (higher: ours faster),
        ``ours_consistency_psnr``, ``bicubic_consistency_psnr``, ``output_pixels``;
        ``ours_gflop`` (the network's arithmetic per frame), ``ours_gflops`` (its achieved
        rate), ``matmul_gflops`` (:func:`matmul_gflops` in the same mode, same run) and
        ``floor_seconds`` = ``ours_gflop / matmul_gflops``, the fastest this network can be here.
    """
    from reconstruction.baselines import bicubic
    from reconstruction.evaluate import downsample_2x

    image = np.clip(np.asarray(image, np.float32), 0.0, 1.0)
    runner = make_runner(model, option)
    ours_seconds, ours = median_seconds(lambda: superresolve(model, image, runner=runner), repeats, warmup)
    bicubic_seconds, theirs = median_seconds(lambda: bicubic(image), repeats, warmup)
    shape = (2 * image.shape[0], 2 * image.shape[1], 3)
    gflop, rate = full_resolution_gflop(model, shape[0] * shape[1]), matmul_gflops(option)
    return {"ours_seconds": ours_seconds, "bicubic_seconds": bicubic_seconds,
            "ours_gflop": gflop, "ours_gflops": gflop / ours_seconds, "matmul_gflops": rate,
            "floor_seconds": gflop / rate,
            "bicubic_over_ours": bicubic_seconds / ours_seconds,
            "ours_consistency_psnr": metrics.psnr(downsample_2x(_checked(ours, shape, "ours")), image),
            "bicubic_consistency_psnr": metrics.psnr(downsample_2x(_checked(theirs, shape, "bicubic")), image),
            "output_pixels": shape[0] * shape[1]}
