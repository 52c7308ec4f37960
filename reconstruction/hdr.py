"""The HDR transform between linear radiance and the denoiser's input/output space.

Transform: ``encode(x) = log1p(max(x, 0))``, inverse ``decode(z) = expm1(max(z, 0))``.
log1p compresses fireflies (radiance 1000 → 6.9) while staying ≈ linear near 0, so the
network sees bounded, well-scaled values; it is exactly invertible on x ≥ 0. Negative
radiance is clamped to 0 (path-traced radiance is non-negative; negatives can only be
round-off) and ``decode`` clamps negative network outputs to 0 (radiance 0).

Bad input policy: NaN or ±inf radiance is **refused** by :func:`encode` with a
``ValueError`` naming the count. Callers that prefer to continue call :func:`sanitize`
first, which replaces non-finite and negative values by 0 and returns how many it
replaced, so the caller can report it.
"""

from __future__ import annotations

import numpy as np
import torch

_AUXILIARY_RANGE = {"albedo": (0.0, 1.0), "normal": (-1.0, 1.0)}


def _is_tensor(x) -> bool:
    return isinstance(x, torch.Tensor)


def _count_nonfinite(x) -> int:
    return int((~torch.isfinite(x)).sum()) if _is_tensor(x) else int(np.count_nonzero(~np.isfinite(x)))


def sanitize(radiance):
    """Replace NaN, ±inf and negative radiance by 0.

    Parameters
    ----------
    radiance : numpy.ndarray or torch.Tensor
        Linear radiance, any shape.

    Returns
    -------
    clean : same type and shape as ``radiance`` (a copy)
    replaced : dict
        ``{"nonfinite": int, "negative": int}``, the number of values replaced.
    """
    if _is_tensor(radiance):
        finite = torch.isfinite(radiance)
        negative = finite & (radiance < 0)
        clean = torch.where(finite & ~negative, radiance, torch.zeros_like(radiance))
        return clean, {"nonfinite": int((~finite).sum()), "negative": int(negative.sum())}
    radiance = np.asarray(radiance)
    finite = np.isfinite(radiance)
    negative = finite & (radiance < 0)
    clean = np.where(finite & ~negative, radiance, 0).astype(radiance.dtype)
    return clean, {"nonfinite": int(np.count_nonzero(~finite)), "negative": int(np.count_nonzero(negative))}


def encode(radiance):
    """Linear radiance → network space, ``log1p(max(radiance, 0))``.

    Parameters
    ----------
    radiance : numpy.ndarray or torch.Tensor
        Linear radiance (non-negative; negatives are clamped to 0), any shape.

    Returns
    -------
    Same type and shape, values ≥ 0.

    Raises
    ------
    ValueError
        If any value is NaN or ±inf (call :func:`sanitize` first to continue anyway).
    """
    bad = _count_nonfinite(radiance)
    if bad:
        raise ValueError(f"radiance contains {bad} NaN/inf values; call reconstruction.hdr.sanitize() first")
    if _is_tensor(radiance):
        return torch.log1p(radiance.clamp_min(0))
    return np.log1p(np.maximum(radiance, 0))


def decode(encoded):
    """Network space → linear radiance, ``expm1(max(encoded, 0))`` (inverse of :func:`encode`).

    Parameters
    ----------
    encoded : numpy.ndarray or torch.Tensor
        Values in the network's output space, any shape.

    Returns
    -------
    Same type and shape: linear radiance ≥ 0.
    """
    if _is_tensor(encoded):
        return torch.expm1(encoded.clamp_min(0))
    return np.expm1(np.maximum(encoded, 0))


def denoiser_input(color: np.ndarray, albedo: np.ndarray, normal=None, depth=None) -> torch.Tensor:
    """Stack the denoiser's input channels for one image.

    Channel order: ``encode(color)`` (3), albedo (3, as is), then, if given, normal (3,
    as is) and ``encode(depth)`` (1) — the order :class:`reconstruction.models.Denoiser`
    expects for ``auxiliary=("albedo",)`` or ``("albedo", "normal", "depth")``.

    Parameters
    ----------
    color : numpy.ndarray
        Shape (H, W, 3), noisy linear radiance (finite; see :func:`sanitize`).
    albedo : numpy.ndarray
        Shape (H, W, 3), diffuse map in [0, 1].
    normal : numpy.ndarray, optional
        Shape (H, W, 3), unit normals in [-1, 1]; must be given together with ``depth``.
    depth : numpy.ndarray, optional
        Shape (H, W) or (H, W, 1), non-negative distance (scene units; ``inf`` for
        background is refused like any non-finite value).

    Returns
    -------
    torch.Tensor
        Shape (C, H, W), float32, C = 6 or 10.

    Raises
    ------
    ValueError
        On wrong shapes, mismatched sizes, non-finite values or aux values out of range.
    """
    color = np.asarray(color)
    if color.ndim != 3 or color.shape[2] != 3 or 0 in color.shape:
        raise ValueError(f"color must have shape (H, W, 3), got {color.shape}")
    if (normal is None) != (depth is None):
        raise ValueError("normal and depth must be given together (or neither)")
    planes = [encode(color.astype(np.float32, copy=False))]
    buffers = [("albedo", albedo)] + ([("normal", normal)] if normal is not None else [])
    for name, buffer in buffers:
        buffer = np.asarray(buffer, dtype=np.float32)
        if buffer.shape != color.shape:
            raise ValueError(f"{name} must have the colour's shape {color.shape}, got {buffer.shape}")
        if _count_nonfinite(buffer):
            raise ValueError(f"{name} contains NaN/inf values")
        low, high = _AUXILIARY_RANGE[name]
        if buffer.min() < low - 1e-3 or buffer.max() > high + 1e-3:
            raise ValueError(f"{name} must lie in [{low}, {high}], got [{buffer.min()}, {buffer.max()}]")
        planes.append(buffer)
    if depth is not None:
        depth = np.asarray(depth, dtype=np.float32)
        depth = depth[:, :, 0] if depth.ndim == 3 and depth.shape[2] == 1 else depth
        if depth.shape != color.shape[:2]:
            raise ValueError(f"depth must have shape {color.shape[:2]} or (H, W, 1), got {depth.shape}")
        planes.append(encode(depth)[:, :, None])
    stacked = np.concatenate([np.asarray(p, dtype=np.float32) for p in planes], axis=2)
    return torch.from_numpy(np.ascontiguousarray(stacked.transpose(2, 0, 1)))
