"""Fast evaluation of the networks: tiled parallel inference (§6.4) and measured speed-ups.

Tiling
------
The frame is split into rectangles ("cores") and every core is evaluated on its own
crop extended by a halo, by a thread pool (one tile per worker at a time, torch
intra-op threads set to 1 meanwhile so the workers do not oversubscribe the cores).
Unlike the paper's split without overlap (RMSE 0.0023 against the whole frame), the halo
makes the tiled result equal to the whole-frame result up to float round-off:

* Denoiser: the frame is first padded (bottom/right, edge replication — the padding
  :meth:`~reconstruction.models.Denoiser.forward` applies) to a multiple of 32, and tile
  corners and sizes are multiples of 32, so every tile sees the whole frame's pooling
  grid. The zero padding of a 3×3 conv at a tile edge corrupts at most 64 pixels
  inward (1 + 1 at full scale, then one coarse pixel per encoder level, doubled back
  through five nearest upsamplings and convolutions: measured 64 on a random network),
  so :data:`DENOISER_HALO` = 64 (itself a multiple of 32). Tile edges on the frame edge
  are the frame edge, so padding there is identical.
* Superresolution: no pooling; the receptive-field radius is 4 + 1 + 2 + 1 = 8, so
  :data:`SUPERRESOLUTION_HALO` = 8 and alignment 1.

Faster inference
----------------
:func:`select_fast_inference` times the candidate execution modes of :data:`OPTIONS` on
a sample and accepts the fastest one that is at least :data:`MIN_SPEEDUP` times faster
than plain float32 and whose PSNR against a reference image changes by at most
:data:`MAX_PSNR_CHANGE` dB (else it keeps ``"fp32"``). Every mode runs under
``torch.inference_mode`` with the model in eval mode. ``torch.compile`` is not offered:
it needs a C++ toolchain at run time and compiles for tens of seconds per input shape.
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from kdtrace.timing import median_seconds
from reconstruction import hdr, metrics
from reconstruction.models import POOLING_MULTIPLE, Denoiser

#: Halo (pixels) making denoiser tiles exact; a multiple of :data:`POOLING_MULTIPLE`.
DENOISER_HALO = 64
#: Halo (pixels) making superresolution tiles exact (receptive-field radius).
SUPERRESOLUTION_HALO = 8
#: Largest accepted PSNR change (dB) of a faster mode against plain float32.
MAX_PSNR_CHANGE = 0.05
#: Smallest speed-up a faster mode must bring to be chosen.
MIN_SPEEDUP = 1.05
#: Execution modes :func:`make_runner` offers (bf16 modes only where supported).
OPTIONS = ("fp32", "channels_last", "bf16", "channels_last_bf16", "jit_freeze")


def tile_grid(height: int, width: int, tile: int, align: int = 1) -> list[tuple[int, int, int, int]]:
    """Split a frame into core rectangles.

    Parameters
    ----------
    height, width : int
        Frame size in pixels (already a multiple of ``align``).
    tile : int
        Core side in pixels, rounded up to a multiple of ``align``; edge tiles are smaller.
    align : int
        Corner alignment in pixels.

    Returns
    -------
    list of (y0, y1, x0, x1)
        Half-open pixel ranges covering the frame exactly once.
    """
    if tile < 1 or align < 1:
        raise ValueError(f"tile and align must be positive, got tile={tile}, align={align}")
    step = math.ceil(tile / align) * align
    return [
        (y, min(y + step, height), x, min(x + step, width))
        for y in range(0, height, step)
        for x in range(0, width, step)
    ]


@contextmanager
def _intra_op_threads(count: int):
    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def run_tiled(
    model: nn.Module,
    x: torch.Tensor,
    *,
    tile: int,
    halo: int,
    align: int = 1,
    workers: int | None = None,
) -> torch.Tensor:
    """Evaluate a fully convolutional, size-preserving model tile by tile.

    Parameters
    ----------
    model : torch.nn.Module
        Maps (1, C, h, w) to (1, C', h, w) for any h, w (evaluated under inference mode).
    x : torch.Tensor
        Shape (1, C, H, W).
    tile : int
        Core tile side in pixels (rounded up to a multiple of ``align``).
    halo : int
        Context added on every side of a core (a multiple of ``align``).
    align : int
        Pooling grid of the model: the frame is padded to a multiple of it by edge
        replication (bottom/right) and tile corners lie on it.
    workers : int, optional
        Threads evaluating tiles concurrently (default: ``torch.get_num_threads()``).
        With 1 worker the tiles run in turn with torch's own intra-op threading.

    Returns
    -------
    torch.Tensor
        Shape (1, C', H, W), equal to ``model(x)`` up to round-off when ``halo`` is at
        least the model's edge-contamination depth (:data:`DENOISER_HALO`,
        :data:`SUPERRESOLUTION_HALO`).
    """
    if x.ndim != 4 or x.shape[0] != 1:
        raise ValueError(f"x must have shape (1, C, H, W), got {tuple(x.shape)}")
    if halo < 0 or halo % align:
        raise ValueError(f"halo must be a non-negative multiple of align={align}, got {halo}")
    workers = workers or torch.get_num_threads()
    height, width = x.shape[-2:]
    pad_h, pad_w = (-height) % align, (-width) % align
    padded = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate") if pad_h or pad_w else x
    full_h, full_w = padded.shape[-2:]
    cores = tile_grid(full_h, full_w, tile, align)

    def evaluate(core):
        y0, y1, x0, x1 = core
        ey0, ey1, ex0, ex1 = max(y0 - halo, 0), min(y1 + halo, full_h), max(x0 - halo, 0), min(x1 + halo, full_w)
        with torch.inference_mode():
            result = model(padded[..., ey0:ey1, ex0:ex1])
        return result[..., y0 - ey0 : y1 - ey0, x0 - ex0 : x1 - ex0]

    if workers == 1:
        results = [evaluate(core) for core in cores]
    else:
        with _intra_op_threads(1), ThreadPoolExecutor(workers) as pool:
            results = list(pool.map(evaluate, cores))
    output = results[0].new_empty((1, results[0].shape[1], full_h, full_w))
    for (y0, y1, x0, x1), result in zip(cores, results, strict=True):
        output[..., y0:y1, x0:x1] = result
    return output[..., :height, :width]


def denoise(
    model: Denoiser,
    color: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    *,
    tile: int | None = None,
    workers: int | None = None,
    runner: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> np.ndarray:
    """Denoise one frame end to end: HDR encode, network (tiled if asked), decode.

    Parameters
    ----------
    model : Denoiser
        Network; normal and depth must be given iff it was built with them.
    color, albedo, normal, depth : numpy.ndarray
        See :func:`reconstruction.hdr.denoiser_input` (non-finite colour is refused).
    tile : int, optional
        Core tile side (multiple of 32); ``None`` evaluates the whole frame at once.
    workers : int, optional
        Tile threads (see :func:`run_tiled`).
    runner : callable, optional
        Evaluates the network on the whole frame instead of ``model`` itself, e.g. a
        faster execution mode from :func:`make_runner` (ignored when ``tile`` is given).

    Returns
    -------
    numpy.ndarray
        Shape (H, W, 3), float32 denoised linear radiance.
    """
    x = hdr.denoiser_input(color, albedo, normal, depth)[None]
    if x.shape[1] != model.in_channels:
        raise ValueError(f"model expects {model.in_channels} input channels, the buffers give {x.shape[1]}")
    model.eval()
    if tile is None:
        with torch.inference_mode():
            encoded = model(x) if runner is None else runner(x)
    else:
        encoded = run_tiled(model, x, tile=tile, halo=DENOISER_HALO, align=POOLING_MULTIPLE, workers=workers)
    return hdr.decode(encoded[0].permute(1, 2, 0).numpy()).astype(np.float32)


def _bf16_supported() -> bool:
    return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())


def make_runner(model: nn.Module, option: str) -> Callable[[torch.Tensor], torch.Tensor]:
    """A callable evaluating ``model`` in one execution mode of :data:`OPTIONS`.

    Parameters
    ----------
    model : torch.nn.Module
        Network (put in eval mode; for ``"channels_last"`` a channels-last copy is made).
    option : str
        ``"fp32"``: plain float32. ``"channels_last"``: NHWC memory format (oneDNN's
        native layout). ``"bf16"``: ``torch.autocast("cpu", torch.bfloat16)``, output cast
        back to float32 (only on CPUs with AVX512-BF16 or AMX); a model whose
        ``casts_to_weight_dtype`` is true gets a bfloat16 copy of its weights instead. ``"channels_last_bf16"``:
        both. ``"jit_freeze"``:
        ``torch.jit.trace`` + ``torch.jit.freeze`` (folded weights, fused conv+ReLU),
        traced once per input shape.

    Returns
    -------
    callable
        (N, C, H, W) float32 tensor → float32 output tensor, under inference mode.
    """
    if option not in OPTIONS:
        raise ValueError(f"unknown option {option!r}; choose from {OPTIONS}")
    model.eval()
    bf16 = "bf16" in option
    channels_last = option.startswith("channels_last")
    if bf16 and not _bf16_supported():
        raise RuntimeError("this CPU has neither AVX512-BF16 nor AMX; bfloat16 autocast would be emulated")
    # A net that convolves in its weights' dtype gets bf16 weights once; autocast would cast
    # every activation on every call (1024x1024 superresolution: 0.62 s against 0.36 s).
    bf16_weights = bf16 and getattr(model, "casts_to_weight_dtype", False)
    if channels_last or bf16_weights:
        model = copy.deepcopy(model)
    if bf16_weights:
        model = model.to(torch.bfloat16)
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    traced: dict[tuple[int, ...], torch.jit.ScriptModule] = {}

    def forward(x: torch.Tensor) -> torch.Tensor:
        if option != "jit_freeze":
            return model(x)
        if tuple(x.shape) not in traced:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", torch.jit.TracerWarning)  # shape branches: traced per shape
                warnings.simplefilter("ignore", DeprecationWarning)  # TorchScript is deprecated in 2.x
                traced[tuple(x.shape)] = torch.jit.freeze(torch.jit.trace(model, x, check_trace=False))
        return traced[tuple(x.shape)](x)

    def run(x: torch.Tensor) -> torch.Tensor:
        with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16 and not bf16_weights):
            if channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            return forward(x).float().contiguous()

    return run


@dataclass(frozen=True)
class OptionResult:
    """Timing and quality of one execution mode.

    Attributes
    ----------
    option : str
    seconds : float
        Median wall time of one forward pass (s).
    speedup : float
        fp32 seconds / these seconds.
    psnr : float
        PSNR (dB) of the decoded output against the reference image.
    psnr_change : float
        ``psnr`` − fp32 PSNR (dB).
    max_abs_difference : float
        Largest absolute output difference from fp32 (network space).
    accepted : bool
        ``|psnr_change| ≤ MAX_PSNR_CHANGE`` and ``speedup ≥ MIN_SPEEDUP``.
    """

    option: str
    seconds: float
    speedup: float
    psnr: float
    psnr_change: float
    max_abs_difference: float
    accepted: bool


@dataclass(frozen=True)
class FastInferenceDecision:
    """Outcome of :func:`select_fast_inference`: the chosen option and all measurements."""

    chosen: str
    results: tuple[OptionResult, ...]


def select_fast_inference(
    model: nn.Module,
    x: torch.Tensor,
    reference: np.ndarray,
    *,
    decode: Callable[[np.ndarray], np.ndarray] = lambda image: image,
    repeats: int = 3,
    max_psnr_change: float = MAX_PSNR_CHANGE,
    min_speedup: float = MIN_SPEEDUP,
) -> FastInferenceDecision:
    """Time every supported mode of :data:`OPTIONS` and choose the fastest that keeps quality.

    Parameters
    ----------
    model : torch.nn.Module
        Network to evaluate.
    x : torch.Tensor
        Shape (1, C, H, W), a representative input (e.g. 512×512).
    reference : numpy.ndarray
        Shape (H, W, C'), the image the decoded output is compared with (the
        noise-free reference, or any fixed target for an untrained model).
    decode : callable
        Maps the output (H, W, C') from network space to image space
        (:func:`reconstruction.hdr.decode` for the denoiser; identity by default).
    repeats : int
        Timed runs per mode after one warm-up run; the median is used.
    max_psnr_change, min_speedup : float
        Acceptance thresholds (dB, ratio).

    Returns
    -------
    FastInferenceDecision
        ``chosen`` is ``"fp32"`` when no mode is accepted.
    """
    options = [option for option in OPTIONS if "bf16" not in option or _bf16_supported()]
    measured = []
    for option in options:
        run = make_runner(model, option)
        measured.append((option, *median_seconds(lambda run=run: run(x), repeats)))  # one warm-up (and trace)
    base_seconds, base_output = measured[0][1], measured[0][2]

    def quality(output) -> float:
        return metrics.psnr(decode(output[0].permute(1, 2, 0).numpy()), reference)

    base_psnr = quality(base_output)
    results = []
    for option, seconds, output in measured:
        score = quality(output)
        change = 0.0 if score == base_psnr else score - base_psnr
        speedup = base_seconds / seconds
        results.append(
            OptionResult(
                option=option,
                seconds=seconds,
                speedup=speedup,
                psnr=score,
                psnr_change=change,
                max_abs_difference=float((output - base_output).abs().max()),
                accepted=option != "fp32" and abs(change) <= max_psnr_change and speedup >= min_speedup,
            )
        )
    accepted = [result for result in results if result.accepted]
    chosen = min(accepted, key=lambda result: result.seconds).option if accepted else "fp32"
    return FastInferenceDecision(chosen=chosen, results=tuple(results))
