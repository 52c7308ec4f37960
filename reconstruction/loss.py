"""Training loss of §4.3: ``0.7·MSE + 0.3·MSE(edge(P), edge(T))``.

Edge map ``edge(X)``: the Laplacian of Gaussian (LoG) of each channel of X, then min–max
normalised **per image and per channel** to [0, 1] with the *target's* range:
``(L − min L_T) / max(max L_T − min L_T, EDGE_RANGE_FLOOR)``, computed on the *signed* LoG
response. The target's edge map is exactly in [0, 1] and the prediction's goes through
the same affine map, so the edge term is a scaled MSE of the LoG responses: zero only
when they agree, and an error in intensity counts as one. Normalising each map by its
own range (a literal reading of the paper) makes the term blind to intensity and, at
weight 0.3 against pixel errors 10-50 times smaller, it dominated training: measured
(quick data with 4 camera positions, residual denoiser, test views), Sponza
41.3 dB noisy -> 41.3 dB denoised with independent maps, 47.2 dB with the target's
range; the Cornell box 37.2 -> 40.2 and 42.5 dB. The floor keeps constant or nearly
constant targets safe: gradients stay finite, and (:data:`DENOISER_RANGE_FLOOR`) flat dark
crops do not turn the leftover noise into most of the loss. min/max are differentiable almost
everywhere, so the loss trains with autograd.

LoG filter: the same discrete kernel as ``scipy.ndimage.gaussian_laplace``, i.e. the sum
of the two separable second-derivative-of-Gaussian filters, each tap sampled from the
Gaussian normalised to unit sum times the polynomial (x²/σ⁴ − 1/σ²), radius
``int(4σ + 0.5)`` (6 for σ = 1.4, 4 for σ = 1); boundaries by edge replication (scipy
``mode="nearest"``). The kernel sum is −5.4e-5 (σ = 1.4) / −1.4e-4 (σ = 1), not exactly 0:
a constant image gives a constant response, which the normalisation maps to 0.
σ = 1.4 for the denoiser, σ = 1 for superresolution.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

#: σ of the LoG in the denoiser's loss (§4.3).
DENOISER_SIGMA = 1.4
#: σ of the LoG in the superresolution loss (§5.2).
SUPERRESOLUTION_SIGMA = 1.0
#: Weight of the pixel MSE; the edge MSE has weight 1 − MSE_WEIGHT.
MSE_WEIGHT = 0.7
#: Smallest LoG range used as the min–max denominator (superresolution: images in [0, 1]).
EDGE_RANGE_FLOOR = 1e-4
#: The same for the denoiser, whose targets are HDR-encoded radiance. With 1e-4, dark and flat
#: crops (Crytek Sponza: 10% of its standard validation crops have a target range of 0, half
#: below 0.005) multiplied any noise left in the prediction by up to 10⁴ in the edge term, and
#: an all-black image scored 57× lower than the 4-spp input: the nets learned to darken (the
#: demodulated net's lit Sponza surfaces came out at 17–29% of the reference). Chosen on the
#: quick profile's validation views of cbox-original, car, crytek-sponza and cbox-sphere
#: (floors 1e-4, 0.01, 0.03, 0.1, 0.3): mean gain over the noisy input 1.89, 3.55,
#: 3.52, 3.71, 3.57 dB for the paper net and 1.32, 3.84, 3.91, 4.08 dB for the demodulated one.
#: The profiles set it (``denoiser_edge_range_floor``); this is the value the standard and paper
#: profiles use, and a test keeps the two in step.
DENOISER_RANGE_FLOOR = 0.1


def log_kernel_1d(sigma: float, truncate: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """The 1-D factors of :func:`log_kernel`: the normalised Gaussian and its second derivative.

    Parameters
    ----------
    sigma : float
        Gaussian standard deviation in pixels (> 0).
    truncate : float
        Radius in standard deviations; radius = ``int(truncate·sigma + 0.5)``.

    Returns
    -------
    gauss, second : numpy.ndarray
        Shape (2r + 1,), float64; the 2-D kernel is ``outer(second, gauss) + outer(gauss, second)``.
    """
    if not sigma > 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    radius = int(truncate * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    gauss = np.exp(-0.5 * x**2 / sigma**2)
    gauss /= gauss.sum()
    return gauss, gauss * (x**2 / sigma**4 - 1.0 / sigma**2)


def log_kernel(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """Discrete 2-D LoG kernel, identical to the one ``scipy.ndimage.gaussian_laplace`` applies.

    ``sigma`` and ``truncate`` as for :func:`log_kernel_1d`; returns a (2r + 1, 2r + 1) float64 array.
    """
    gauss, second = log_kernel_1d(sigma, truncate)
    return np.outer(second, gauss) + np.outer(gauss, second)


def _banded(kernel: torch.Tensor, length: int) -> torch.Tensor:
    """(length + 2r, length) matrix ``T`` with ``T[j + t, j] = kernel[t]``: ``padded @ T`` correlates rows."""
    taps = kernel.shape[0]
    band = kernel.new_zeros(length + taps - 1, length)
    columns = torch.arange(length)
    for t in range(taps):
        band[columns + t, columns] = kernel[t]
    return band


class LaplacianOfGaussian(nn.Module):
    """Depthwise LoG of every channel, edge-replicated, as matrix products (fixed, not trainable).

    The kernel is :func:`log_kernel`, the sum of two separable ones, so the LoG is four 1-D
    correlations; each is a product with a banded matrix. A direct 13x13 single-channel
    convolution ran at a few GFLOP/s in oneDNN: its backward took 0.67 s of a 1.26 s bf16 training
    step of the denoiser (32 crops of 128x128, 2 threads, EPYC). The tests compare this with the
    direct convolution and with SciPy.

    Parameters
    ----------
    sigma : float
        Gaussian standard deviation in pixels.
    """

    def __init__(self, sigma: float) -> None:
        super().__init__()
        self.sigma = float(sigma)
        gauss, second = log_kernel_1d(sigma)
        # float64 so that float64 inputs get the exact kernel; cast to the input's dtype on use
        self.register_buffer("gauss", torch.from_numpy(gauss), persistent=False)
        self.register_buffer("second", torch.from_numpy(second), persistent=False)
        self._bands: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def _bands_for(self, length: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The Gaussian's and the second derivative's banded matrices for ``length``, cached."""
        key = (length, like.dtype, like.device)
        if key not in self._bands:
            self._bands[key] = tuple(_banded(k, length).to(like) for k in (self.gauss, self.second))
        return self._bands[key]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """LoG of x, shape (N, C, H, W) → (N, C, H, W), edge-replicated boundaries."""
        if x.ndim != 4:
            raise ValueError(f"expected shape (N, C, H, W), got {tuple(x.shape)}")
        n, c, h, w = x.shape
        radius = self.gauss.shape[0] // 2
        padded = F.pad(x.reshape(n * c, 1, h, w), (radius,) * 4, mode="replicate")[:, 0]
        row_gauss, row_second = self._bands_for(w, x)
        column_gauss, column_second = self._bands_for(h, x)
        # sum over u, t of (second[u] gauss[t] + gauss[u] second[t]) · padded[i + u, j + t]
        response = column_second.mT @ (padded @ row_gauss) + column_gauss.mT @ (padded @ row_second)
        return response.reshape(n, c, h, w)


def normalise_edges(response: torch.Tensor, reference: torch.Tensor | None = None,
                    floor: float = EDGE_RANGE_FLOOR) -> torch.Tensor:
    """Min–max normalise a LoG response per image and channel, by its own range or a reference's.

    Parameters
    ----------
    response : torch.Tensor
        Shape (N, C, H, W), signed LoG response.
    reference : torch.Tensor, optional
        Same shape: the response whose min and range are used (the target's, in the
        loss); default ``response`` itself, which maps it to [0, 1].
    floor : float
        Smallest range used as the denominator.

    Returns
    -------
    torch.Tensor
        Same shape; in [0, 1] when normalised by itself, ≈ 0 where the range is below
        ``floor``.
    """
    low, scale = edge_range(response if reference is None else reference, floor)
    return (response - low) / scale


def edge_range(reference: torch.Tensor, floor: float = EDGE_RANGE_FLOOR) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image and channel minimum of ``reference`` and its range, at least ``floor`` (shape (N, C, 1, 1))."""
    low = reference.amin(dim=(-2, -1), keepdim=True)
    return low, (reference.amax(dim=(-2, -1), keepdim=True) - low).clamp_min(floor)


class EdgeAwareLoss(nn.Module):
    """``0.7·MSE(P, T) + 0.3·MSE(edge(P), edge(T))`` of §4.3.

    Parameters
    ----------
    sigma : float
        LoG σ: :data:`DENOISER_SIGMA` (1.4) or :data:`SUPERRESOLUTION_SIGMA` (1.0).
    range_floor : float
        Smallest target LoG range the edge maps are normalised by.
    """

    def __init__(self, sigma: float = DENOISER_SIGMA, range_floor: float = EDGE_RANGE_FLOOR) -> None:
        super().__init__()
        self.log = LaplacianOfGaussian(sigma)
        self.range_floor = float(range_floor)

    @property
    def config(self) -> dict:
        """What defines this loss, for the cache key of models trained with it."""
        return {"loss": "EdgeAwareLoss", "sigma": self.log.sigma, "mse_weight": MSE_WEIGHT,
                "edge_normalisation": "target range", "range_floor": self.range_floor,
                # the same LoG as the direct convolution, rounded otherwise: trained weights differ
                "log": "separable matrix products"}

    def forward(self, prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Scalar loss of batches shaped (N, C, H, W) (same shape, finite)."""
        if prediction.shape != target.shape:
            raise ValueError(f"prediction {tuple(prediction.shape)} and target {tuple(target.shape)} differ in shape")
        pixel = F.mse_loss(prediction, target)
        target_edges = self.log(target)
        low, scale = edge_range(target_edges, self.range_floor)  # once for both maps
        edges = F.mse_loss((self.log(prediction) - low) / scale, (target_edges - low) / scale)
        return MSE_WEIGHT * pixel + (1.0 - MSE_WEIGHT) * edges


class InSpace(nn.Module):
    """A loss taken in another image space: ``loss(transfer(P), transfer(T))``.

    Parameters
    ----------
    loss : nn.Module
        The loss, e.g. :class:`EdgeAwareLoss`.
    transfer : callable
        Maps a batch (N, C, H, W) to the space the loss is taken in (differentiable).
    space : str
        What the space is, for the cache key of models trained with it.
    """

    def __init__(self, loss: nn.Module, transfer, space: str) -> None:
        super().__init__()
        self.loss = loss
        self.transfer = transfer
        self.space = space

    @property
    def config(self) -> dict:
        """The wrapped loss's configuration and the space."""
        return {**getattr(self.loss, "config", {"loss": type(self.loss).__name__}), "space": self.space}

    def forward(self, prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Scalar loss of the transferred batches."""
        return self.loss(self.transfer(prediction), self.transfer(target))
