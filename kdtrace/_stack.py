"""Scratch arrays on a numba kernel's stack, for kernels compiled without numba's runtime (NRT).

numba counts references to every array that crosses an inlined call, with an atomic
``NRT_incref``/``NRT_decref`` call pair that LLVM cannot remove: the path tracer made about
two dozen such calls per sample and per bounce (a camera ray that missed the scene cost
101 ns, 64 of them in reference counting; AVX-512 EPYC, one thread). A kernel
compiled with ``_nrt=False`` makes none, but then cannot allocate with ``np.empty``;
:func:`stack_empty` gives it C-contiguous arrays in its own stack frame instead (no
reference count, freed on return, and LLVM knows they alias nothing else, so loops over
them vectorise as over fresh allocations).
"""

from __future__ import annotations

import math

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic
from numba.np.arrayobj import populate_array


def _literal_shape(shape) -> tuple[int, ...] | None:
    if isinstance(shape, types.IntegerLiteral):
        return (shape.literal_value,)
    if isinstance(shape, types.BaseTuple) and all(isinstance(t, types.IntegerLiteral) for t in shape.types):
        return tuple(t.literal_value for t in shape.types)
    return None


@intrinsic
def stack_empty(typingctx, shape, dtype):
    """An uninitialised C-contiguous array of ``shape`` (int constants) and ``dtype`` on the stack.

    Call it only from jitted code, with a constant shape (e.g. ``stack_empty((16, 3),
    np.float64)``); the array lives until the function that called it returns, so never
    return it or keep it beyond that function (an inlined helper's arrays live in the
    function it is inlined into). Its memory is in the function's entry block: calling it
    in a loop reuses the same memory.
    """
    dims = _literal_shape(shape)
    if dims is None or not isinstance(dtype, (types.NumberClass, types.DType)) or min(dims) < 1:
        return None
    element = dtype.dtype
    array_type = types.Array(element, len(dims), "C")

    def codegen(context, builder, signature, args):
        element_type = context.get_data_type(element)
        data = cgutils.alloca_once(builder, element_type, size=math.prod(dims))
        itemsize = context.get_abi_sizeof(element_type)
        intp = context.get_value_type(types.intp)
        strides = [itemsize * math.prod(dims[k + 1:]) for k in range(len(dims))]
        array = context.make_array(array_type)(context, builder)
        populate_array(array, data=data, shape=[ir.Constant(intp, d) for d in dims],
                       strides=[ir.Constant(intp, s) for s in strides], itemsize=ir.Constant(intp, itemsize),
                       meminfo=None)
        return array._getvalue()

    return array_type(shape, dtype), codegen
