"""The two reconstruction networks of Tang et al.: the denoising autoencoder (§4.1) and
the Y-channel superresolution CNN (§5.1), plus the BT.601 colour conversion and the
bicubic upsampling the superresolution net refines.

Denoiser layer arrangement (95,107 trainable parameters with the diffuse map)
------------------------------------------------------------------------------
Every convolution is 3×3, stride 1, zero padding 1, with bias; ``relu`` is ReLU.

==========  =====================================================  ==========  ==========
name        operation                                               scale       parameters
==========  =====================================================  ==========  ==========
``inc``     relu(conv 6→32)                                         1           1,760
``enc1``    e1 = relu(conv 32→32); then 2×2 max pool                1 → 1/2     9,248
``enc2``    e2 = relu(conv 32→32); then 2×2 max pool                1/2 → 1/4   9,248
``enc3``    e3 = relu(conv 32→32); then 2×2 max pool                1/4 → 1/8   9,248
``enc4``    e4 = relu(conv 32→32); then 2×2 max pool                1/8 → 1/16  9,248
``enc5``    e5 = relu(conv 32→32); then 2×2 max pool                1/16 → 1/32 9,248
``dec5``    2× nearest upsample; relu(conv 32→32) + e5              1/32 → 1/16 9,248
``dec4``    2× nearest upsample; relu(conv 32→32) + e4              1/16 → 1/8  9,248
``dec3``    2× nearest upsample; relu(conv 32→32) + e3              1/8 → 1/4   9,248
``dec2``    2× nearest upsample; relu(conv 32→32) + e2              1/4 → 1/2   9,248
``dec1``    2× nearest upsample; relu(conv 32→32) + e1              1/2 → 1     9,248
``out``     conv 32→3 (linear: the output is in the HDR-encoded      1           867
            space of :mod:`reconstruction.hdr`)
==========  =====================================================  ==========  ==========

Total 1,760 + 10 × 9,248 + 867 = 95,107. Each encoder block's output (before pooling)
is added to the output of the decoder block at the same resolution.

Residual form (default, ``residual=True``): the output is the HDR-encoded noisy colour
plus ``out`` (a parameter-free skip; the count stays 95,107), and ``out`` starts at zero,
so an untrained denoiser returns its noisy input exactly and training departs from there.
The paper's net predicts the clean image directly (``residual=False``). With the optional
auxiliary normal and depth inputs (``auxiliary=("albedo", "normal", "depth")``, 10 input
channels) only ``inc`` grows, to 10·32·9 + 32 = 2,912, giving 96,259 parameters.

Albedo demodulation (``demodulate=True``, a documented variant; off by default, the count
stays 95,107): the same network sees the noisy colour divided by the diffuse map,
``encode(decode(noisy) / s)`` with ``s = ε + (1 − ε)·albedo`` (ε = :data:`DEMODULATION_EPSILON`,
so s ∈ [ε, 1]), and its output is multiplied back, ``encode(decode(out) · s)``
(:func:`remodulate`; negative outputs stay negative there), so input and output stay
in the paper net's encoded space and every caller is unchanged. Texture and wall colour
then pass through the multiplication untouched and the net only smooths the illumination
(the irradiance-demodulation of SVGF and of production denoisers). Where the albedo is
below :data:`DEMODULATION_FLOOR` in every channel (emitters, sky, background, mirrors)
``s = 1``. All parameter-free.

Perceptual transfer (``perceptual=G``, a documented variant; off by default, the count stays
95,107): the network works on ``w = log1p(g·x) / log1p(G)`` of the linear radiance ``x`` instead
of ``log1p(x)``, with ``g = G · e`` and ``e`` the training references' exposure (the display
space's rule, :func:`reconstruction.metrics.auto_exposure`, over every training crop; set by
:meth:`Denoiser.calibrate` and kept with the weights as the buffer ``radiance_gain``). Exposed
radiance between 1/G and 1, what a display shows, spans most of ``[0, 1]`` as the sRGB curve's
does, and values above display white stay logarithmic, as OIDN's HDR transfer is. The input and
output stay in the paper net's ``log1p`` space (:func:`to_perceptual`, :func:`from_perceptual`), so
every caller is unchanged; training takes its loss in ``w`` (:class:`reconstruction.loss.InSpace`).
All parameter-free.

The five poolings need sides divisible by 32: :meth:`Denoiser.forward` pads the bottom
and right edges by edge replication up to the next multiple of 32 and crops the result
back, so any input size works and the pooling grid is anchored at the top-left pixel
(which :mod:`reconstruction.inference` relies on for exact tiling).

Superresolution (37,793 trainable parameters)
---------------------------------------------
relu(conv 9×9 1→32) [2,624] → relu(conv 3×3 32→32) [9,248] → relu(conv 5×5 32→32)
[25,632] → conv 3×3 32→1 [289]; "same" padding by edge replication. The net sees the Y
channel of the bicubic 2×-upsampled image and predicts a correction added to it
(residual form, a parameter-free choice; the last convolution is zero-initialised, so an
untrained net returns its input exactly and starts at bicubic quality).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from reconstruction import hdr

#: Channels of each denoiser input, in stacking order after the noisy RGB.
AUXILIARY_CHANNELS = {"albedo": 3, "normal": 3, "depth": 1}
#: Side multiple the denoiser's five 2×2 poolings need.
POOLING_MULTIPLE = 32
#: Number of encoder (and decoder) blocks.
DEPTH = 5
#: Filters of every hidden layer.
FILTERS = 32
#: The smallest divisor of the colour (``demodulate=True``, ``s = ε + (1 − ε)·albedo``): keeps a
#: dark diffuse albedo of 0.03 finite and well scaled (it divides by 0.04).
DEMODULATION_EPSILON = 0.01
#: Pixels whose largest albedo channel is below this are not demodulated (divided by 1): they
#: show what has no diffuse albedo, emitters, the sky, the background and mirrors. Dividing the
#: sky of crytek-sponza (radiance ~1, albedo 0) by 0.01 made it the whole of the loss and the
#: net failed (27.3 dB on the standard test views, below its 35.9 dB input).
DEMODULATION_FLOOR = 0.02


#: Where :func:`remodulate` switches from ``log1p(s·expm1(o))`` to ``o + log(s + (1 − s)·e^−o)``.
REMODULATE_SWITCH = 20.0


def remodulate(encoded: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Multiply encoded radiance by ``scale`` in linear radiance: ``log1p(expm1(encoded) · scale)``.

    Parameters
    ----------
    encoded : torch.Tensor
        The demodulated network output in the log1p space; any real value.
    scale : torch.Tensor or float
        Positive, broadcastable to ``encoded`` (in (0, 1] for demodulation; the perceptual
        transfer also multiplies by more than 1, when ``s + (1 − s)·e^−o`` stays ≥ 1).

    Returns
    -------
    torch.Tensor
        Same shape, finite for every input. Above o = 20 it is computed as
        ``o + log(s + (1 − s)·e^−o)`` (expm1 overflows float32 above 88). A negative o is
        negative radiance, which :func:`reconstruction.hdr.decode` clamps to 0 anyway; there
        the map continues linearly with its slope at 0, ``s·o``, so the loss always has a
        gradient: a clamp stopped training dead (all outputs negative, no gradient), and a
        straight-through clamp fed the edge loss gradients that did not lower it until the
        weights grew without bound (quick data).
    """
    # up to o = 20 the direct formula (for a large scale the other one cancels: 1 + (s − 1)·o
    # from s + (1 − s)·(1 − o)); beyond, e^−o < 3e-9 and the other one is exact in float32
    near = encoded.clamp(0.0, REMODULATE_SWITCH)
    far = encoded.clamp_min(REMODULATE_SWITCH)
    positive = torch.where(encoded <= REMODULATE_SWITCH, torch.log1p(scale * torch.expm1(near)),
                           far + torch.log(scale + (1.0 - scale) * torch.exp(-far)))
    return torch.where(encoded >= 0, positive, scale * encoded.clamp_max(0.0))


def to_perceptual(encoded: torch.Tensor, gain: torch.Tensor, perceptual: float) -> torch.Tensor:
    """``log1p`` space → the perceptual space ``w = log1p(g·expm1(z)) / log1p(G)``.

    Parameters
    ----------
    encoded : torch.Tensor
        ``z = log1p(x)`` of linear radiance ``x``; negative values (negative radiance, only a
        network output can have them) continue linearly with slope ``g / log1p(G)``.
    gain : torch.Tensor
        ``g`` (> 0), radiance units⁻¹: the radiance that shows at 1/G of display white is 1/g.
    perceptual : float
        ``G`` (> 0), the transfer's gain on exposed radiance.

    Returns
    -------
    torch.Tensor
        Same shape, finite for every finite input (see :func:`remodulate`).
    """
    return remodulate(encoded, gain) / math.log1p(perceptual)


def from_perceptual(transferred: torch.Tensor, gain: torch.Tensor, perceptual: float) -> torch.Tensor:
    """The inverse of :func:`to_perceptual`: perceptual space → ``log1p`` space."""
    return remodulate(transferred * math.log1p(perceptual), 1.0 / gain)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters of ``model``."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def _check_batch(x: torch.Tensor, channels: int, name: str) -> None:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} input must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim != 4 or x.shape[1] != channels:
        raise ValueError(f"{name} input must have shape (N, {channels}, H, W), got {tuple(x.shape)}")
    if x.shape[2] == 0 or x.shape[3] == 0:
        raise ValueError(f"{name} input must be non-empty, got {tuple(x.shape)}")


class Denoiser(nn.Module):
    """Denoising autoencoder of §4.1 (see the module docstring for the layer table).

    Parameters
    ----------
    auxiliary : tuple of str
        Auxiliary buffers stacked after the noisy RGB, in this order; a subset of
        ``("albedo", "normal", "depth")`` with ``"albedo"`` (the paper's diffuse map).
        ``("albedo",)`` gives the paper's 6-channel, 95,107-parameter network;
        ``("albedo", "normal", "depth")`` the 10-channel, 96,259-parameter variant.
    residual : bool
        Predict a correction added to the encoded noisy colour, starting from the
        identity (default), or the clean image directly as the paper does.
    demodulate : bool
        Denoise the colour divided by ``albedo + ε`` and multiply the result back (see the
        module docstring); the input and output spaces are unchanged.
    perceptual : float
        ``G`` of the perceptual transfer (see the module docstring), 0 for the paper's ``log1p``
        space. Such a net is calibrated (:meth:`calibrate`) before training.
    """

    def __init__(self, auxiliary: tuple[str, ...] = ("albedo",), residual: bool = True,
                 demodulate: bool = False, perceptual: float = 0.0) -> None:
        super().__init__()
        perceptual = float(perceptual)
        if not (perceptual == 0 or (math.isfinite(perceptual) and perceptual > 0)):
            raise ValueError(f"perceptual must be 0 (off) or a positive finite gain, got {perceptual!r}")
        if perceptual and demodulate:
            raise ValueError("the perceptual transfer and albedo demodulation are separate variants; choose one")
        self.perceptual = perceptual
        if perceptual:  # a buffer, so the calibrated gain travels with the weights
            self.register_buffer("radiance_gain", torch.tensor(perceptual, dtype=torch.float32))
        auxiliary = tuple(auxiliary)
        order = tuple(name for name in AUXILIARY_CHANNELS if name in auxiliary)
        if "albedo" not in auxiliary or set(auxiliary) - set(AUXILIARY_CHANNELS) or order != auxiliary:
            raise ValueError(
                f"auxiliary must contain 'albedo' and be an ordered subset of {tuple(AUXILIARY_CHANNELS)}, got {auxiliary}"
            )
        self.auxiliary = auxiliary
        self.in_channels = 3 + sum(AUXILIARY_CHANNELS[name] for name in auxiliary)
        self.inc = nn.Conv2d(self.in_channels, FILTERS, 3, padding=1)
        self.encoders = nn.ModuleList(nn.Conv2d(FILTERS, FILTERS, 3, padding=1) for _ in range(DEPTH))
        self.decoders = nn.ModuleList(nn.Conv2d(FILTERS, FILTERS, 3, padding=1) for _ in range(DEPTH))
        self.out = nn.Conv2d(FILTERS, 3, 3, padding=1)
        self.residual = bool(residual)
        self.demodulate = bool(demodulate)
        if self.residual:
            nn.init.zeros_(self.out.weight)
            nn.init.zeros_(self.out.bias)

    @property
    def config(self) -> dict:
        """Constructor arguments and identity, for checkpoints: ``Denoiser(**config["kwargs"])``."""
        config = {"architecture": "Denoiser", "kwargs": {"auxiliary": list(self.auxiliary), "residual": self.residual}}
        if self.demodulate:  # only when set, so the paper net's cache keys and checkpoints stay valid
            config["kwargs"]["demodulate"] = True
            # what the cache key needs beyond the constructor: earlier clamps and scales were other models
            config.update(output="unclamped", scale="eps+(1-eps)*albedo", floor=DEMODULATION_FLOOR,
                          epsilon=DEMODULATION_EPSILON)
        if self.perceptual:
            config["kwargs"]["perceptual"] = self.perceptual
            config.update(transfer="log1p(g*x)/log1p(G), g = G * exposure of the training references")
        return config

    def calibrate(self, targets: torch.Tensor) -> float:
        """Set the perceptual transfer's ``g = G · exposure`` from the training targets.

        Parameters
        ----------
        targets : torch.Tensor
            Shape (N, 3, H, W), the training targets in the ``log1p`` space.

        Returns
        -------
        float
            ``g`` in radiance units⁻¹.

        Raises
        ------
        ValueError
            When the net has no perceptual transfer, or the targets have no exposure (all black).
        """
        from reconstruction.metrics import auto_exposure

        if not self.perceptual:
            raise ValueError("only a perceptual denoiser (perceptual=G) is calibrated")
        radiance = hdr.decode(targets.detach().float()).permute(0, 2, 3, 1).reshape(-1, targets.shape[-1], 3)
        gain = self.perceptual * auto_exposure(radiance.numpy(), "the training targets")
        self.radiance_gain.fill_(gain)
        return gain

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Denoise a batch.

        Parameters
        ----------
        x : torch.Tensor
            Shape (N, ``in_channels``, H, W), any H, W ≥ 1: HDR-encoded noisy RGB then the
            auxiliary buffers (see :func:`reconstruction.hdr.denoiser_input`).

        Returns
        -------
        torch.Tensor
            Shape (N, 3, H, W): the denoised RGB in the HDR-encoded space.
        """
        _check_batch(x, self.in_channels, "Denoiser")
        height, width = x.shape[-2:]
        if self.demodulate:
            # fp32 whatever the autocast: expm1/log1p of bf16 values would lose the low bits
            albedo = x[:, 3:6].float()
            # what has no albedo (emitters, sky, background, mirrors) passes through undemodulated
            scale = torch.where(albedo.amax(dim=1, keepdim=True) < DEMODULATION_FLOOR, 1.0,
                                DEMODULATION_EPSILON + (1.0 - DEMODULATION_EPSILON) * albedo)
            x = torch.cat([torch.log1p(hdr.decode(x[:, :3].float()) / scale), x[:, 3:].float()], dim=1)
        if self.perceptual:
            x = torch.cat([to_perceptual(x[:, :3].float(), self.radiance_gain, self.perceptual), x[:, 3:].float()],
                          dim=1)
        noisy = x[:, :3]
        pad_h, pad_w = (-height) % POOLING_MULTIPLE, (-width) % POOLING_MULTIPLE
        if pad_h or pad_w:
            x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
        x = F.relu(self.inc(x))
        skips = []
        for conv in self.encoders:
            x = F.relu(conv(x))
            skips.append(x)
            x = F.max_pool2d(x, 2)
        for conv, skip in zip(reversed(self.decoders), reversed(skips), strict=True):
            x = F.relu(conv(F.interpolate(x, scale_factor=2, mode="nearest"))) + skip
        correction = self.out(x)[..., :height, :width]
        output = noisy + correction if self.residual else correction
        if self.demodulate:
            output = remodulate(output.float(), scale)
        if self.perceptual:
            output = from_perceptual(output.float(), self.radiance_gain, self.perceptual)
        return output


#: Image spaces a :class:`Superresolution` net can be trained in.
SUPERRES_SPACES = ("linear", "display")


class Superresolution(nn.Module):
    """Y-channel superresolution CNN of §5.1 (9-3-5-3 kernels, 32 filters, 37,793 parameters).

    The input is the Y channel of the bicubic 2×-upsampled image; the output is that Y
    plus the predicted correction (same size as the input).

    Parameters
    ----------
    space : {"linear", "display"}
        The image space the net was trained in, which its caller must feed it: ``"linear"``
        (the paper's: radiance clipped to [0, 1]) or ``"display"`` (the documented variant: each
        image exposed and sRGB-encoded, :func:`reconstruction.metrics.to_display`, before the
        bicubic upsampling). The layers are the same; the space is part of the model's identity.
    """

    #: bf16 inference converts this net's weights once instead of autocasting every call
    #: (:func:`reconstruction.inference.make_runner`): :meth:`forward` convolves in the weights'
    #: dtype and adds the correction to its input in the input's own precision, as autocast does.
    casts_to_weight_dtype = True

    def __init__(self, space: str = "linear") -> None:
        super().__init__()
        if space not in SUPERRES_SPACES:
            raise ValueError(f"unknown superresolution space {space!r}; use one of {', '.join(SUPERRES_SPACES)}")
        self.space = space
        self.layers = nn.ModuleList(
            nn.Conv2d(c_in, c_out, k, padding=k // 2, padding_mode="replicate")
            for c_in, c_out, k in ((1, FILTERS, 9), (FILTERS, FILTERS, 3), (FILTERS, FILTERS, 5), (FILTERS, 1, 3))
        )
        # The correction layer starts at zero so the untrained net returns its input exactly
        # (bicubic quality) and training departs from there; with PyTorch's default random
        # init it would start below bicubic and a short training may not climb back.
        nn.init.zeros_(self.layers[-1].weight)
        nn.init.zeros_(self.layers[-1].bias)

    @property
    def config(self) -> dict:
        """Constructor arguments and identity, for checkpoints."""
        # the linear net keeps the empty kwargs of before, so that its stored weights keep their key
        return {"architecture": "Superresolution", "kwargs": {} if self.space == "linear" else {"space": self.space}}

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        """Refine a bicubic-upsampled luma batch.

        Parameters
        ----------
        y : torch.Tensor
            Shape (N, 1, H, W), BT.601 luma in [0, 1] of the bicubic-upsampled image.

        Returns
        -------
        torch.Tensor
            Shape (N, 1, H, W): refined luma (not clamped; :func:`superresolve` clamps).
        """
        _check_batch(y, 1, "Superresolution")
        # Without gradients the border strips are convolved apart (exact, and cheaper than a
        # padded copy of every activation); training keeps the plain padded convolution.
        convolve = replicate_padded_conv if not torch.is_grad_enabled() else lambda x, conv: conv(x)
        x = y.to(self.layers[0].weight.dtype)
        for layer in self.layers[:-1]:
            x = F.relu(convolve(x, layer), inplace=True)
        return y + convolve(x, self.layers[-1]).to(y.dtype)


def replicate_padded_conv(x: torch.Tensor, conv: nn.Conv2d) -> torch.Tensor:
    """``conv(x)`` for a stride-1 'same' convolution with replicate padding, without padding ``x``.

    The convolution runs with zero padding, which oneDNN applies on the fly, and the strips
    within the kernel radius of the border, the only outputs on which zero and replicate
    padding differ, are computed again from replicate-padded slices of ``x``. A padded copy
    of each 32-channel activation cost 52 ms of a 1024x1024 bf16 frame (2 threads, EPYC).

    Parameters
    ----------
    x : torch.Tensor
        Shape (N, C, H, W).
    conv : torch.nn.Conv2d
        Odd square kernel, stride 1, dilation 1, ``padding=k // 2``, ``padding_mode="replicate"``.

    Returns
    -------
    torch.Tensor
        Equal to ``conv(x)`` (same arithmetic per output pixel).
    """
    radius = conv.kernel_size[0] // 2
    height, width = x.shape[-2:]
    if min(height, width) <= 2 * radius:
        return conv(x)
    out = F.conv2d(x, conv.weight, conv.bias, padding=radius)

    def strip(part: torch.Tensor, left: int, right: int, top: int, bottom: int) -> torch.Tensor:
        return F.conv2d(F.pad(part, (left, right, top, bottom), mode="replicate"), conv.weight, conv.bias)

    r, band = radius, 2 * radius
    out[..., :r, :] = strip(x[..., :band, :], r, r, r, 0)
    out[..., height - r :, :] = strip(x[..., height - band :, :], r, r, 0, r)
    out[..., :, :r] = strip(x[..., :, :band], r, 0, r, r)
    out[..., :, width - r :] = strip(x[..., :, width - band :], 0, r, r, r)
    return out


# Full-range BT.601 (JFIF) for values in [0, 1]: Y in [0, 1], Cb and Cr centred on 0.5.
_RGB_TO_YCBCR = np.array(
    [[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]], dtype=np.float64
)
_YCBCR_TO_RGB = np.linalg.inv(_RGB_TO_YCBCR)
_CHROMA_OFFSET = np.array([0.0, 0.5, 0.5])


def _apply_colour_matrix(image, matrix: np.ndarray, before: np.ndarray, after: np.ndarray, channel_axis: int):
    if image.shape[channel_axis] != 3:
        raise ValueError(f"expected 3 channels on axis {channel_axis}, got shape {tuple(image.shape)}")
    if isinstance(image, torch.Tensor):
        moved = torch.movedim(image, channel_axis, -1)
        m = torch.as_tensor(matrix, dtype=image.dtype, device=image.device)
        b = torch.as_tensor(before, dtype=image.dtype, device=image.device)
        a = torch.as_tensor(after, dtype=image.dtype, device=image.device)
        return torch.movedim((moved - b) @ m.T + a, -1, channel_axis)
    image = np.asarray(image)
    dtype = image.dtype if np.issubdtype(image.dtype, np.floating) else np.float64
    moved = np.moveaxis(image.astype(np.float64, copy=False), channel_axis, -1)
    return np.moveaxis((moved - before) @ matrix.T + after, -1, channel_axis).astype(dtype)


def ycbcr_from_rgb(rgb, channel_axis: int = -1):
    """Full-range BT.601 YCbCr of RGB in [0, 1] (JFIF convention, no 16–235 studio range).

    Parameters
    ----------
    rgb : numpy.ndarray or torch.Tensor
        RGB values (nominally [0, 1]) with 3 channels on ``channel_axis``.
    channel_axis : int
        Channel axis: -1 for (H, W, 3) arrays, -3 for (N, 3, H, W) tensors.

    Returns
    -------
    Same type and shape: Y = 0.299 R + 0.587 G + 0.114 B in [0, 1], Cb and Cr in [0, 1]
    with neutral grey at 0.5.
    """
    return _apply_colour_matrix(rgb, _RGB_TO_YCBCR, np.zeros(3), _CHROMA_OFFSET, channel_axis)


def rgb_from_ycbcr(ycbcr, channel_axis: int = -1):
    """Inverse of :func:`ycbcr_from_rgb` (exact matrix inverse; no clamping)."""
    return _apply_colour_matrix(ycbcr, _YCBCR_TO_RGB, _CHROMA_OFFSET, np.zeros(3), channel_axis)


def bicubic_upsample(x: torch.Tensor, factor: int = 2) -> torch.Tensor:
    """Bicubic upsampling used everywhere in the project (SR input and bicubic baseline).

    ``torch.nn.functional.interpolate(mode="bicubic", align_corners=False)``: Keys cubic
    with a = -0.75, pixel-centre aligned, edge-clamped; not clamped to [0, 1].

    Parameters
    ----------
    x : torch.Tensor
        Shape (N, C, H, W).
    factor : int
        Integer scale factor.

    Returns
    -------
    torch.Tensor
        Shape (N, C, factor·H, factor·W).
    """
    return F.interpolate(x, scale_factor=factor, mode="bicubic", align_corners=False)


def superresolve(model: Superresolution, low_res_rgb: np.ndarray, runner=None) -> np.ndarray:
    """2× superresolution of an RGB image in [0, 1], end to end (§5.1).

    Bicubic 2× upsampling (:func:`bicubic_upsample`), clamped to [0, 1]; BT.601 YCbCr;
    the network refines Y; Cb and Cr stay bicubic; back to RGB, clamped to [0, 1].

    Parameters
    ----------
    model : Superresolution
        The network (evaluated without gradients, in its current train/eval mode).
    low_res_rgb : numpy.ndarray
        Shape (H, W, 3), float values in [0, 1] (the caller chooses linear or sRGB).
    runner : callable, optional
        Evaluates the network on the (1, 1, 2H, 2W) luma instead of ``model`` itself,
        e.g. a faster execution mode of :func:`reconstruction.inference.make_runner`.

    Returns
    -------
    numpy.ndarray
        Shape (2H, 2W, 3), float32 in [0, 1].
    """
    low_res_rgb = np.asarray(low_res_rgb)
    if low_res_rgb.ndim != 3 or low_res_rgb.shape[2] != 3 or 0 in low_res_rgb.shape:
        raise ValueError(f"low_res_rgb must have shape (H, W, 3), got {low_res_rgb.shape}")
    if not np.all(np.isfinite(low_res_rgb)):
        raise ValueError("low_res_rgb contains NaN or infinite values")
    x = torch.from_numpy(np.ascontiguousarray(low_res_rgb, dtype=np.float32)).permute(2, 0, 1)[None]
    with torch.inference_mode():
        upsampled = bicubic_upsample(x).clamp(0.0, 1.0)
        luma = sum(float(weight) * upsampled[:, c : c + 1] for c, weight in enumerate(_RGB_TO_YCBCR[0]))
        refined = model(luma) if runner is None else runner(luma)
        # Every RGB channel carries Y with weight 1 (the first column of the inverse matrix), so
        # keeping Cb and Cr and replacing Y adds the change of Y to each channel: the round trip
        # through YCbCr without its two 3x3 colour products (about 25 ms of a 1024x1024 frame).
        rgb = (upsampled + (refined - luma)).clamp(0.0, 1.0)
    return rgb[0].permute(1, 2, 0).numpy().copy()
