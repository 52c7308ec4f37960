"""Baselines the networks are measured against.

Denoising: the noisy input itself, and Intel Open Image Denoise through ``pyoidn``
(CPU device, filter ``"RT"``, ``hdr=True``, albedo and optional normal auxiliary images,
``quality="high"``, auxiliaries treated as noisy, i.e. ``clean_aux=False``).

Upsampling 2×: bicubic through :func:`reconstruction.models.bicubic_upsample` (torch,
a = −0.75, so the bicubic baseline is exactly the image the superresolution net
refines), Lanczos-3 through Pillow ``Image.resize(..., Resampling.LANCZOS)`` per channel
on 32-bit float ("F") images, and nearest neighbour (the floor any upsampler must beat).
Upsampled images are clamped to [0, 1] (inputs are [0, 1] images).
"""

from __future__ import annotations

import numpy as np
import torch

from reconstruction.models import bicubic_upsample


def _rgb(image, name: str, shape=None) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
        raise ValueError(f"{name} must have shape (H, W, 3), got {image.shape}")
    if shape is not None and image.shape != shape:
        raise ValueError(f"{name} must have the colour's shape {shape}, got {image.shape}")
    if not np.all(np.isfinite(image)):
        raise ValueError(f"{name} contains {int(np.count_nonzero(~np.isfinite(image)))} NaN/inf values")
    return np.ascontiguousarray(image, dtype=np.float32)


def noisy_input(color: np.ndarray) -> np.ndarray:
    """The trivial denoising baseline: the noisy image unchanged (float32 copy, (H, W, 3))."""
    return _rgb(color, "color").copy()


def oidn(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray | None = None) -> np.ndarray:
    """Denoise with Intel Open Image Denoise (``RT`` filter, HDR, CPU).

    Parameters
    ----------
    color : numpy.ndarray
        Shape (H, W, 3), noisy linear radiance ≥ 0 (finite).
    albedo : numpy.ndarray
        Shape (H, W, 3), diffuse map in [0, 1].
    normal : numpy.ndarray, optional
        Shape (H, W, 3), normals in [-1, 1].

    Returns
    -------
    numpy.ndarray
        Shape (H, W, 3), float32 denoised linear radiance.
    """
    import pyoidn

    color = _rgb(color, "color")
    if np.any(color < 0):
        raise ValueError("color must be non-negative radiance for HDR denoising")
    albedo = _rgb(albedo, "albedo", color.shape)
    normal = None if normal is None else _rgb(normal, "normal", color.shape)
    return pyoidn.denoise(color, albedo, normal, hdr=True, quality="high")


def bicubic(image: np.ndarray, factor: int = 2) -> np.ndarray:
    """Bicubic upsampling (torch, as the SR net's input), (H, W, 3) → (fH, fW, 3) in [0, 1]."""
    x = torch.from_numpy(_rgb(image, "image")).permute(2, 0, 1)[None]
    return bicubic_upsample(x, factor).clamp(0.0, 1.0)[0].permute(1, 2, 0).numpy().copy()


def _pillow_resize(image: np.ndarray, factor: int, resample) -> np.ndarray:
    from PIL import Image

    image = _rgb(image, "image")
    size = (image.shape[1] * factor, image.shape[0] * factor)
    channels = [np.asarray(Image.fromarray(np.ascontiguousarray(image[:, :, c])).resize(size, resample)) for c in range(3)]
    return np.clip(np.stack(channels, axis=2), 0.0, 1.0).astype(np.float32)


def lanczos(image: np.ndarray, factor: int = 2) -> np.ndarray:
    """Lanczos-3 upsampling (Pillow, float per channel), (H, W, 3) → (fH, fW, 3) in [0, 1]."""
    from PIL.Image import Resampling

    return _pillow_resize(image, factor, Resampling.LANCZOS)


def nearest(image: np.ndarray, factor: int = 2) -> np.ndarray:
    """Nearest-neighbour upsampling (pixel replication), (H, W, 3) → (fH, fW, 3)."""
    return np.repeat(np.repeat(_rgb(image, "image"), factor, axis=0), factor, axis=1)
