"""Stack-allocated scratch arrays (kdtrace._stack) in kernels compiled without numba's runtime."""

import numpy as np
import pytest
from numba import njit
from numba.core.errors import TypingError

from kdtrace._stack import stack_empty


@njit(_nrt=False)
def _fill_and_reduce(values):
    grid = stack_empty((3, 4), np.float64)
    flags = stack_empty(5, np.bool_)
    counts = stack_empty((2, 3, 4), np.int64)
    for i in range(3):
        for j in range(4):
            grid[i, j] = values[i * 4 + j]
            counts[1, i, j] = i * 4 + j
    for k in range(5):
        flags[k] = k % 2 == 0
    total = 0.0
    for i in range(3):
        for j in range(4):
            total += grid[i, j] * counts[1, i, j]
    return total, grid.shape[0], grid.shape[1], counts.strides[0], flags[4], flags[3]


@njit(_nrt=False)
def _reused_in_a_loop(n):
    total = 0
    for i in range(n):
        scratch = stack_empty(8, np.int64)  # allocated once, in the function's entry block
        for k in range(8):
            scratch[k] = i + k
        total += scratch[7]
    return total


def test_stack_arrays_hold_what_is_written_with_c_strides():
    values = np.arange(12, dtype=np.float64) * 0.5
    total, rows, cols, stride, even, odd = _fill_and_reduce(values)
    assert total == pytest.approx(float((values * np.arange(12)).sum()))
    assert (rows, cols) == (3, 4)
    assert stride == 3 * 4 * 8  # C order, int64
    assert even and not odd


def test_a_stack_array_allocated_in_a_loop_holds_each_iterations_values():
    assert _reused_in_a_loop(10_000) == sum(i + 7 for i in range(10_000))


def test_a_shape_that_is_not_a_constant_is_refused():
    @njit(_nrt=False)
    def dynamic(n):
        return stack_empty(n, np.float64)[0]

    with pytest.raises(TypingError):
        dynamic(np.int64(4) + np.int64(np.random.default_rng(0).integers(1, 2)))
