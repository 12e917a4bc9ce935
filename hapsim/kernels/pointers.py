"""Arrays handed to compiled code as addresses in one int64 *context* array.

Calling a numba function from Python costs a type check and an unboxing per argument
(about 0.1 us each, and a small allocation: the arguments' tuple and each array's
descriptor), so a kernel with tens of array arguments called once per sample spends
microseconds and allocates kilobytes per call outside its own work. Packing the arrays'
addresses and shapes into one int64 array, built once, makes the call a single argument:
the compiled side rebuilds each array with :func:`numba.carray` on its address (no copy,
no allocation). Used by the n-D engine's per-sample step
(:func:`hapsim.kernels.nd.step_context`) and the JACK process callback
(:mod:`hapsim.audio.jack_native`, whose context libjack hands back as a ``void *``).

The arrays must stay alive and in place (never rebound or resized) while a context that
names them is used: the owner keeps them as attributes and updates them in place.
"""

from __future__ import annotations

import numpy as np
from numba import types
from numba.extending import intrinsic

__all__ = ["voidptr", "address"]


@intrinsic
def voidptr(typingctx, addr):
    """An integer address as a ``void *`` (for :func:`numba.carray`), in compiled code.

    Parameters
    ----------
    addr : int64
        The address (``ndarray.ctypes.data``).

    Returns
    -------
    voidptr
    """
    sig = types.voidptr(types.int64)

    def codegen(context, builder, sig, args):
        return builder.inttoptr(args[0], context.get_value_type(types.voidptr))
    return sig, codegen


def address(a: np.ndarray, dtype) -> int:
    """The address of ``a``'s data, after checking it can be rebuilt as a C-ordered
    array of ``dtype`` from that address and its shape.

    Parameters
    ----------
    a : ndarray
    dtype : numpy dtype
        The element type the compiled side reads.

    Returns
    -------
    int
        ``a.ctypes.data``.

    Raises
    ------
    ValueError
        ``a`` is not C-contiguous, not of ``dtype`` or not writeable.
    """
    if a.dtype != np.dtype(dtype) or not a.flags.c_contiguous or not a.flags.writeable:
        raise ValueError(f"a context array must be a writeable C-ordered {np.dtype(dtype)} "
                         f"array, got {a.dtype} {a.shape} (flags {a.flags.c_contiguous}, "
                         f"{a.flags.writeable})")
    return int(a.ctypes.data)
