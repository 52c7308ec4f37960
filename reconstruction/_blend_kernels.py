"""numba kernel of :mod:`reconstruction.blend`: a blend's clipped squared error in one pass.

:func:`reconstruction.blend.cross_validated_weight` evaluates this error about 26 times per
call, twice per swept frame. As a NumPy expression each evaluation made six passes over
float64 temporaries (0.13 s a call on a 512x512 frame, 2026-12-04, AVX-512 EPYC); this loop
reads each input once and allocates nothing. ``tests/test_reconstruction_blend.py`` checks
it against the NumPy expression.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, error_model="numpy")
def clipped_blend_error(noisy, change, goal, weight):
    """``sum((clip(noisy + weight * change, 0, 1) - goal) ** 2)``.

    Parameters
    ----------
    noisy, change, goal : 1-D float64 arrays
        Equal length; linear values (``goal`` already clipped to [0, 1]).
    weight : float
        The blend weight.

    Returns
    -------
    float
        The sum in float64 (NaN if any term is NaN, as with NumPy).
    """
    total = 0.0
    for i in range(noisy.size):
        value = min(max(noisy[i] + weight * change[i], 0.0), 1.0)
        difference = value - goal[i]
        total += difference * difference
    return total
