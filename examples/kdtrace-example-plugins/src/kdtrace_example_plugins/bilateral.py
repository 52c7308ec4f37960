"""A cross-bilateral denoiser guided by the albedo and normal buffers.

Each output pixel is a weighted mean of the noisy colour over a square window; the
weight of a neighbour falls off with its distance (``sigma_spatial``, pixels) and
with how much its albedo and normal differ from the centre's (``sigma_albedo``,
``sigma_normal``). The guides are nearly noise-free in a path tracer, so noise is
averaged away inside a surface while object and texture edges are kept. Colour is
filtered as albedo-demodulated irradiance and modulated back, so textures stay sharp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Albedo floor for demodulation, so black surfaces do not divide by zero.
ALBEDO_FLOOR = 1e-3


@dataclass(frozen=True)
class CrossBilateral:
    """The filter and its parameters; call it as ``denoise(color, albedo, normal)``.

    Attributes
    ----------
    radius : int
        Half-width of the window (pixels); the window is ``2 radius + 1`` square.
    sigma_spatial : float
        Standard deviation of the spatial Gaussian (pixels).
    sigma_albedo : float
        Standard deviation of the albedo difference (albedo units, RGB distance).
    sigma_normal : float
        Standard deviation of the normal difference (RGB distance of unit normals).
    """

    radius: int = 4
    sigma_spatial: float = 2.5
    sigma_albedo: float = 0.05
    sigma_normal: float = 0.1

    def __call__(self, color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """Denoise one frame.

        Parameters
        ----------
        color : (H, W, 3) float32
            Noisy linear radiance.
        albedo : (H, W, 3) float32
            Albedo in [0, 1].
        normal : (H, W, 3) float32
            Normals in [-1, 1].

        Returns
        -------
        (H, W, 3) float32
            Denoised linear radiance.
        """
        height, width, _ = color.shape
        albedo = albedo.astype(np.float64)
        irradiance = color.astype(np.float64) / np.maximum(albedo, ALBEDO_FLOOR)
        r = self.radius
        pad = ((r, r), (r, r), (0, 0))
        padded = [np.pad(a, pad, mode="edge") for a in (irradiance, albedo, normal.astype(np.float64))]
        total = np.zeros((height, width, 3))
        weight_sum = np.zeros((height, width))
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                window = (slice(r + dy, r + dy + height), slice(r + dx, r + dx + width))
                e_irradiance, e_albedo, e_normal = (a[window] for a in padded)
                exponent = (dx * dx + dy * dy) / (2.0 * self.sigma_spatial**2)
                exponent = exponent + np.sum((e_albedo - albedo) ** 2, axis=2) / (2.0 * self.sigma_albedo**2)
                exponent = exponent + np.sum((e_normal - normal) ** 2, axis=2) / (2.0 * self.sigma_normal**2)
                weight = np.exp(-exponent)
                total += weight[..., None] * e_irradiance
                weight_sum += weight
        return (total / weight_sum[..., None] * np.maximum(albedo, ALBEDO_FLOOR)).astype(np.float32)


def make() -> CrossBilateral:
    """kdtrace denoiser factory: the cross-bilateral filter with its default parameters."""
    return CrossBilateral()
