"""numba kernel of :mod:`reconstruction.blend`: a blend's clipped squared error per pixel block and weight.

:func:`reconstruction.blend.frame_weight_cap` needs, for a grid of blend weights, the clipped
squared error of every 8x8 block of a frame, to resample the blocks (bootstrap) without
evaluating the error again. Evaluated weight by weight that is 201 passes over a 512x512
frame (0.27 s in numba, AVX-512 EPYC); most pixels never clip and contribute an
exact quadratic in the weight, so the kernel keeps three sums per block for them and
evaluates only the clipped pixels weight by weight (0.04 s). ``tests/test_reconstruction_blend.py``
checks it against the NumPy expression, clipped pixels included.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(parallel=True, cache=True, error_model="numpy")
def clipped_blend_block_errors(noisy, change, goal, block, weights):
    """``out[k, b] = sum over block b of (clip(noisy + weights[k] * change, 0, 1) - goal) ** 2``.

    A pixel whose blend stays in [0, 1] for every weight in [0, 1] (``noisy`` and
    ``noisy + change`` both in [0, 1]) contributes an exact quadratic in the weight, summed
    into three coefficients per block; only the others are evaluated weight by weight.

    Parameters
    ----------
    noisy, change, goal : (H, W, C) float64 arrays
        Linear values (``goal`` already clipped to [0, 1]).
    block : int
        Side of the square pixel blocks; blocks are numbered row by row, the last row and
        column of blocks smaller when ``block`` does not divide H or W.
    weights : 1-D float64 array
        The blend weights, in [0, 1].

    Returns
    -------
    numpy.ndarray
        Shape (len(weights), blocks), float64 (NaN where a term is NaN, as with NumPy).
    """
    height, width, channels = noisy.shape
    rows, columns = -(-height // block), -(-width // block)
    out = np.zeros((rows * columns, weights.size))
    for row in prange(rows):  # one row of blocks per thread: no shared writes
        for column in range(columns):
            b = row * columns + column
            constant, linear, quadratic = 0.0, 0.0, 0.0
            for y in range(row * block, min(height, (row + 1) * block)):
                for x in range(column * block, min(width, (column + 1) * block)):
                    for c in range(channels):
                        n, d, g = noisy[y, x, c], change[y, x, c], goal[y, x, c]
                        if 0.0 <= n <= 1.0 and 0.0 <= n + d <= 1.0:
                            constant += (n - g) * (n - g)
                            linear += 2.0 * d * (n - g)
                            quadratic += d * d
                        else:  # clipped somewhere in [0, 1], or NaN
                            for k in range(weights.size):
                                difference = min(max(n + weights[k] * d, 0.0), 1.0) - g
                                out[b, k] += difference * difference
            for k in range(weights.size):
                w = weights[k]
                out[b, k] += constant + w * (linear + w * quadratic)
    return out.T.copy()
