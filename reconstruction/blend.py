"""The denoiser blended with its noisy input, one weight per spp fitted on validation views.

A denoiser trained at one input spp (the paper's 4) over-smooths inputs that are already
clean: at 64 spp our quick per-scene denoisers lose 1-8 dB to their own input.
The paper's network stays the measured object; this is the documented variant beside it,
``ours + denoiser, blended``:

    output = w(spp) * denoised + (1 - w(spp)) * noisy,   w in [0, 1],

with 95,107 network parameters plus one weight per fitted spp. ``w(spp)`` is fitted on the
references of the scene's **validation** views (never the test views or the sweep's frame),
each rendered by our path tracer at that spp with its own seed, in every space the suite
judges images in (:data:`SPACES`):

``linear``
    the squared error of the linear images clipped to [0, 1] (our linear PSNR);
``display``
    the squared error of the displayed images (each view's exposure and the sRGB curve,
    :func:`reconstruction.metrics.to_display`; our display PSNR);
``flip``
    the LDR-FLIP error map of the displayed images (our FLIP).

For each space the blend's error is evaluated at the weights of :data:`FIT_GRID` and summed
per :data:`BLOCK` x :data:`BLOCK` pixel block of every validation view
(:func:`view_error_curves`). The reference's own noise is independent of ``n`` and ``d``: in
the squared errors it adds the same amount at every weight, so a noisy reference moves the
minimiser only by chance. An over-estimated weight is what loses to the input (in squared
error any weight up to twice the optimum still beats it), and few validation pixels (the
quick profile has two 64x64 views) make the minimiser uncertain. So each space's weight is a
lower confidence bound: the :data:`BOUND_QUANTILE` quantile of the minimising weight over
:data:`BOOTSTRAP_SAMPLES` bootstrap resamplings of the blocks (blocks, since neighbouring
pixels' errors are correlated after denoising; :func:`lower_bound_weight`). ``w(spp)`` is the
smallest of the three, so on the validation views the blend is no worse than its input in
any of them. Between fitted spp the weight is interpolated linearly in log2(spp), and held
constant outside.

Fitted weights are cached by content key (dataset, weights of the model, spp list, path
length, seed) under ``cache_root()/blend``.

The frame's own cap
-------------------
A weight fitted on a few validation views can still be too large for a frame that looks
different (the quick Crytek Sponza sweep frame lost 0.46 dB to its input at 64 spp with
the validated weight). So, at spp >= 2, the frame is rendered as two halves of its samples
(:func:`combine_halves` gives the frame back) and each half, denoised, is blended against
the *other* half as a noisy but independent target, in the clipped squared error of our
PSNR. No reference is involved. For a denoised error independent of the input's noise, the
half's optimum ``w_h = 2 s / (2 s + e)`` (input variance ``s`` at the frame's spp, denoised
error ``e``) gives the frame's as ``w_h / (2 - w_h)`` (:func:`frame_weight_cap`); where the
denoiser also improves with more samples this is an under-estimate, so as a cap it only
moves the blend towards the input. A single frame's estimate is noisy, and an over-estimate
is what loses to the input (the quick car sweep frame at 32 spp: cap 0.18 where
the frame's optimum was 0.08, 0.07 dB below the input), so the cap is the same
:data:`BOUND_QUANTILE` lower bound as the validated weight: ``w_h`` is the weight on a grid of
:data:`CAP_GRID` values minimising the error of :data:`BOOTSTRAP_SAMPLES` resamplings of the
frame's :data:`BLOCK` x :data:`BLOCK` blocks. The weight used is ``min(w(spp), cap)``. The
cap costs two more denoiser passes and the error curves (timed in the sweep). It is in the
linear space only: against a noisy target, the display curve's minimiser is biased by the
sRGB curve's bend over the target's noise, and FLIP counts the target's noise as error.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from kdtrace.cache import atomic_write_bytes, cache_root, content_key
from reconstruction._blend_kernels import clipped_blend_block_errors

#: Bump when the fit changes: cached weights become stale.
BLEND_VERSION = 2
#: The spaces a weight is fitted in (the module docstring); the weight used is their smallest.
SPACES = ("linear", "display", "flip")
#: Blend weights at which :func:`view_error_curves` evaluates the validation views (steps of
#: 0.05: FLIP, the costly space, takes 0.05 s per 256x256 view and weight).
FIT_GRID = np.linspace(0.0, 1.0, 21)
#: Side of the pixel blocks resampled by the bootstrap, pixels.
BLOCK = 8
#: Bootstrap resamplings of the blocks.
BOOTSTRAP_SAMPLES = 400
#: The weight used is this quantile of the bootstrap distribution of w* (a one-sided 90% lower bound).
BOUND_QUANTILE = 0.1
#: Blend weights at which :func:`frame_weight_cap` evaluates the halves' error (steps of 0.005).
CAP_GRID = np.linspace(0.0, 1.0, 201)


@dataclass(frozen=True)
class BlendWeights:
    """Blend weight of the denoiser per input spp.

    Attributes
    ----------
    spp : tuple of int
        The fitted spp, increasing.
    weights : tuple of float
        ``w(spp)`` in [0, 1] for each.
    views : int
        Validation views the weights were fitted on.

    by_space : dict of str -> tuple of float
        Each space's own bound per spp (:data:`SPACES`), whose smallest is ``weights``;
        empty when not recorded.
    """

    spp: tuple[int, ...]
    weights: tuple[float, ...]
    views: int
    by_space: dict[str, tuple[float, ...]] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.spp or len(self.spp) != len(self.weights) or list(self.spp) != sorted(set(self.spp)):
            raise ValueError("blend weights need one weight per distinct, increasing spp")
        if min(self.spp) < 1 or not all(0.0 <= w <= 1.0 for w in self.weights):
            raise ValueError("blend spp must be >= 1 and weights in [0, 1]")
        for space, bounds in self.by_space.items():
            if len(bounds) != len(self.spp):
                raise ValueError(f"blend bounds of {space!r} need one value per spp")

    def limiting_space(self, spp: int) -> str:
        """The space whose bound set ``w(spp)`` at a fitted ``spp`` ("" when not recorded)."""
        index = self.spp.index(spp)
        limits = [space for space, bounds in self.by_space.items() if bounds[index] == self.weights[index]]
        return "/".join(limits)

    def weight(self, spp: int, cap: float = 1.0) -> float:
        """``min(w(spp), cap)``: ``w`` linear in log2(spp) between fitted spp, constant outside them.

        ``cap`` is a frame's own bound (:func:`frame_weight_cap`), in [0, 1].
        """
        if spp < 1:
            raise ValueError(f"spp must be >= 1, got {spp}")
        if not 0.0 <= cap <= 1.0:
            raise ValueError(f"the weight cap must lie in [0, 1], got {cap}")
        return min(float(np.interp(math.log2(spp), np.log2(self.spp), self.weights)), cap)

    def apply(self, noisy: np.ndarray, denoised: np.ndarray, spp: int, cap: float = 1.0) -> np.ndarray:
        """The blend of a denoised image with its noisy input at ``spp`` (float32, same shape)."""
        if noisy.shape != denoised.shape:
            raise ValueError(f"noisy {noisy.shape} and denoised {denoised.shape} differ in shape")
        w = self.weight(spp, cap)
        return (w * denoised + (1.0 - w) * noisy).astype(np.float32)


def _block_sums(values: np.ndarray, block: int) -> np.ndarray:
    """Sums of an (H, W, C) array over ``block`` x ``block`` tiles (edge tiles smaller), flattened."""
    height, width = values.shape[:2]
    rows = np.add.reduceat(values.sum(axis=2), np.arange(0, height, block), axis=0)
    return np.add.reduceat(rows, np.arange(0, width, block), axis=1).ravel()


def _bootstrap_counts(blocks: int, seed: int) -> np.ndarray:
    """How often each of ``blocks`` blocks is drawn in each of :data:`BOOTSTRAP_SAMPLES` resamplings.

    Returns
    -------
    numpy.ndarray
        Shape (BOOTSTRAP_SAMPLES, blocks), float64: a resampling's sum of per-block values is
        ``counts @ values``.
    """
    picks = np.random.default_rng(seed).integers(0, blocks, size=(BOOTSTRAP_SAMPLES, blocks))
    offsets = np.arange(BOOTSTRAP_SAMPLES)[:, None] * blocks
    return np.bincount((picks + offsets).ravel(), minlength=BOOTSTRAP_SAMPLES * blocks).reshape(
        BOOTSTRAP_SAMPLES, blocks).astype(np.float64)


def lower_bound_weight(curves: np.ndarray, weights: np.ndarray, quantile: float | None = BOUND_QUANTILE,
                       seed: int = 0) -> float:
    """The weight minimising summed block errors, as a bootstrap lower bound.

    Parameters
    ----------
    curves : (len(weights), blocks) array
        Each block's error at each weight (:func:`view_error_curves`, :func:`block_error_curves`).
    weights : 1-D array
        The weights, increasing.
    quantile : float, optional
        The ``quantile`` of the minimiser over :data:`BOOTSTRAP_SAMPLES` resamplings of the
        blocks (default :data:`BOUND_QUANTILE`, a lower bound); None: the minimiser of the sum.
    seed : int
        Seed of the bootstrap.

    Returns
    -------
    float
        One of ``weights`` (ties: the smallest), or its quantile in between.
    """
    curves = np.asarray(curves, np.float64)
    if curves.ndim != 2 or curves.shape[0] != len(weights):
        raise ValueError(f"curves must have shape (len(weights)={len(weights)}, blocks), got {curves.shape}")
    if not np.all(np.isfinite(curves)):
        raise ValueError("the blend's errors are not finite")
    if quantile is None:
        return float(weights[int(np.argmin(curves.sum(axis=1)))])
    counts = _bootstrap_counts(curves.shape[1], seed)
    return float(np.quantile(np.asarray(weights)[np.argmin(counts @ curves.T, axis=1)], quantile))


def view_error_curves(noisy: np.ndarray, denoised: np.ndarray, reference: np.ndarray, exposure: float,
                      weights: np.ndarray = FIT_GRID) -> dict[str, np.ndarray]:
    """Per block and weight, the error of ``noisy + w (denoised - noisy)`` in each of :data:`SPACES`.

    Parameters
    ----------
    noisy, denoised, reference : (H, W, 3) arrays
        Linear radiance of one view.
    exposure : float
        The view's display exposure (:func:`reconstruction.metrics.display_exposures`).
    weights : 1-D array
        Blend weights in [0, 1] (default :data:`FIT_GRID`).

    Returns
    -------
    dict of str -> numpy.ndarray
        Per space, shape (len(weights), blocks), float64: ``linear`` the clipped squared
        error, ``display`` the displayed images' squared error, ``flip`` the sum of the
        LDR-FLIP error map, each over a :data:`BLOCK` x :data:`BLOCK` block.
    """
    from reconstruction.metrics import displayed_flip, to_display

    noisy, denoised, reference = (np.asarray(x, np.float64) for x in (noisy, denoised, reference))
    curves = {"linear": block_error_curves(noisy, denoised, reference, weights)}
    shown_reference = to_display(reference, exposure)
    display, flip = [], []
    for w in weights:
        shown = to_display(noisy + w * (denoised - noisy), exposure)
        display.append(_block_sums((shown - shown_reference) ** 2, BLOCK))
        flip.append(_block_sums(displayed_flip(shown, shown_reference)[0][..., None], BLOCK))
    curves["display"], curves["flip"] = np.array(display), np.array(flip)
    return curves


def block_error_curves(noisy: np.ndarray, denoised: np.ndarray, target: np.ndarray,
                       weights: np.ndarray = CAP_GRID) -> np.ndarray:
    """Per :data:`BLOCK`-pixel block, ``sum((clip(noisy + w (denoised - noisy)) - clip(target))^2)`` at each ``w``.

    Clipping to [0, 1] is our PSNR's. ``target`` is an independent noisy estimate (the other
    half of the frame's samples): its noise adds the same amount at every ``w`` in the
    unclipped case, so the minimising ``w`` is unbiased.

    Parameters
    ----------
    noisy, denoised, target : (H, W, 3) arrays
        Linear radiance.
    weights : 1-D array
        The blend weights (default :data:`CAP_GRID`).

    Returns
    -------
    numpy.ndarray
        Shape (len(weights), blocks), float64; blocks in :func:`_block_sums` order.
    """
    noisy, denoised, target = (np.asarray(x, np.float64) for x in (noisy, denoised, target))
    if not noisy.shape == denoised.shape == target.shape or noisy.ndim != 3:
        raise ValueError(f"shapes differ or are not (H, W, C): noisy {noisy.shape}, denoised {denoised.shape}, "
                         f"target {target.shape}")
    weights = np.asarray(weights, np.float64)
    if not np.all((weights >= 0.0) & (weights <= 1.0)):
        raise ValueError("blend weights must lie in [0, 1]")
    return clipped_blend_block_errors(np.ascontiguousarray(noisy), np.ascontiguousarray(denoised - noisy),
                                      np.ascontiguousarray(np.clip(target, 0.0, 1.0)), BLOCK, weights)


def combine_halves(first, second) -> tuple[np.ndarray, np.ndarray]:
    """The frame's ``rgb`` and ``albedo`` from two renders of adjacent sample ranges (float32).

    ``first`` and ``second`` are :class:`~kdtrace.render.RenderResult` with albedo, the
    second rendered with ``first_sample`` = the first's spp: their spp-weighted means are
    the buffers of the render of all their samples, up to float rounding.
    """
    n1, n2 = first.stats["spp"], second.stats["spp"]
    if second.stats["first_sample"] != first.stats["first_sample"] + n1:
        raise ValueError("the halves are not adjacent sample ranges")
    if first.albedo is None or second.albedo is None:
        raise ValueError("the halves need their albedo buffers (render with aux=True)")
    rgb = (n1 * first.rgb.astype(np.float64) + n2 * second.rgb) / (n1 + n2)
    albedo = (n1 * first.albedo.astype(np.float64) + n2 * second.albedo) / (n1 + n2)
    return rgb.astype(np.float32), albedo.astype(np.float32)


def frame_weight_cap(denoise: Callable[[np.ndarray, np.ndarray], np.ndarray], first, second,
                     quantile: float = BOUND_QUANTILE, seed: int = 0) -> float:
    """A frame's own bound on the blend weight, from two halves of its samples (see the module docstring).

    Each half is denoised and blended against the other (:func:`block_error_curves`); the
    blocks of both pairings are resampled together :data:`BOOTSTRAP_SAMPLES` times, each
    resampling's summed error is minimised over :data:`CAP_GRID`, and the ``quantile`` of those
    minimisers, ``w_h``, is the half's weight; ``w_h / (2 - w_h)`` the frame's.

    Parameters
    ----------
    denoise : callable
        ``denoise(rgb, albedo)`` -> denoised rgb, e.g. ``lambda c, a: inference.denoise(model, c, a)``.
    first, second : RenderResult
        Renders of two halves of the frame's samples, with albedo, equal spp.
    quantile : float
        Of the bootstrap distribution (default :data:`BOUND_QUANTILE`, a lower bound; 0.5 its median).
    seed : int
        Seed of the bootstrap.

    Returns
    -------
    float
        In [0, 1].
    """
    if first.stats["spp"] != second.stats["spp"]:
        raise ValueError(f"the halves differ in spp: {first.stats['spp']} and {second.stats['spp']}")
    curves = sum(block_error_curves(a.rgb, denoise(a.rgb, a.albedo), b.rgb) for a, b in ((first, second), (second, first)))
    if not np.all(np.isfinite(curves)):
        raise ValueError("the halves or their denoised images are not finite")
    half = lower_bound_weight(curves, CAP_GRID, quantile, seed)
    return half / (2.0 - half)


def _weights_digest(model: nn.Module) -> str:
    digest = hashlib.sha256()
    for name, tensor in model.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def view_seed(seed: int, view_index: int, spp: int) -> int:
    """Render seed of a validation view at ``spp`` (independent of the dataset's own seeds)."""
    return int(np.random.SeedSequence([seed, 5, view_index, spp]).generate_state(1)[0])


def fit_blend_weights(model: nn.Module, dataset, scene, spp_list: Sequence[int], max_depth: int, seed: int,
                      split: str = "validation", progress: bool | None = None) -> BlendWeights:
    """Fit ``w(spp)`` for ``model`` on the ``split`` views of ``dataset`` (cached by content key).

    Parameters
    ----------
    model : nn.Module
        A denoiser taking noisy RGB and albedo (:class:`reconstruction.models.Denoiser`).
    dataset : reconstruction.data.Dataset
        The scene's dataset; its ``split`` views give the cameras and references.
    scene : Scene
        The scene the dataset was rendered from.
    spp_list : sequence of int
        Input spp to fit a weight at (e.g. the sweep's).
    max_depth, seed : int
        Path length of the renders and seed of their view seeds (:func:`view_seed`).
    split : str
        Which views to fit on; ``"validation"`` for every reported number.
    progress : bool, optional

    Returns
    -------
    BlendWeights
    """
    from kdtrace.render import render
    from reconstruction.data import view_camera
    from reconstruction.evaluate import denoise_view
    from reconstruction.metrics import display_exposures

    spp_list = sorted({int(s) for s in spp_list})
    names = dataset.views(split)
    if not names:
        raise ValueError(f"the dataset has no {split} views to fit blend weights on")
    key = content_key("denoiser-blend", BLEND_VERSION, dataset.key, _weights_digest(model), spp_list, max_depth,
                      seed, split)
    path = cache_root() / "blend" / f"{key[:24]}.json"
    if path.is_file():
        stored = json.loads(path.read_text())
        return BlendWeights(tuple(stored["spp"]), tuple(stored["weights"]), stored["views"],
                            {space: tuple(bounds) for space, bounds in stored["by_space"].items()})
    records = {view["name"]: view for view in dataset.manifest["views"]}
    views = [dataset.load_view(name) for name in names]
    _, exposures = display_exposures([view["reference"] for view in views])
    bounds: dict[str, list[float]] = {space: [] for space in SPACES}
    bar = tqdm(total=len(spp_list) * len(names), desc="blend weights", unit="render",
               disable=None if progress is None else not progress, leave=False)
    for spp in spp_list:
        curves: dict[str, list[np.ndarray]] = {space: [] for space in SPACES}
        for name, view, exposure in zip(names, views, exposures, strict=True):
            record = records[name]
            camera = view_camera(record)
            frame = render(scene, spp=spp, max_depth=max_depth, seed=view_seed(seed, record["index"], spp),
                           width=camera.width, height=camera.height, aux=True, camera=camera)
            with torch.no_grad():
                output = denoise_view(model, {"noisy": frame.rgb, "albedo": frame.albedo,
                                              "reference": view["reference"]})
            for space, curve in view_error_curves(frame.rgb, output, view["reference"], exposure).items():
                curves[space].append(curve)
            bar.update()
        for space in SPACES:
            bounds[space].append(lower_bound_weight(np.concatenate(curves[space], axis=1), FIT_GRID,
                                                    seed=seed + spp))
    bar.close()
    result = BlendWeights(tuple(spp_list), tuple(min(values) for values in zip(*bounds.values(), strict=True)),
                          len(names), {space: tuple(values) for space, values in bounds.items()})
    atomic_write_bytes(path, json.dumps({**dataclasses.asdict(result), "key": key}, indent=1).encode())
    return result
