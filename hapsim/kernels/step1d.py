"""The 1-D engine's per-sample step as one compiled call with one argument.

A 1-D kernel (:mod:`hapsim.kernels.cordis`, :mod:`hapsim.kernels.schemes`,
:func:`hapsim.kernels.audio.run_periods`) takes 14 to 32 arguments; called from Python once
per sample it spends microseconds typing and unboxing them and allocates ~0.6-0.85 KB per
call (the arguments' tuple and each array's descriptor). Here the arguments are packed once,
as addresses and shapes in one int64 *context* array (:mod:`hapsim.kernels.pointers`, as
:func:`hapsim.kernels.nd.run_context` does for the n-D engine), and one runner per kernel
rebuilds them with :func:`numba.carray` (no copy, no allocation) and calls the kernel: the
same kernel on the same arrays, so the results are bit for bit those of the direct call.

Context layout: ``ctx[0]`` the samples (device periods) to advance, set before each call;
``ctx[1:HEAD]`` the kernel's integer parameters (the multi-rate head ``nsub, linear, last,
port``; unused slots 0); then ``(address, rows, columns)`` per argument, in the kernel's
order. A float argument (``T``, ``1 / Ta``) is a 1-element float64 array.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba.extending import register_jitable

from hapsim.kernels import audio, cordis, schemes
from hapsim.kernels.pointers import address, voidptr
from hapsim.kernels.sources import cache_ok

__all__ = ["HEAD", "context", "RUNNERS"]

#: The sources this module's numba code compiles in (:mod:`hapsim.kernels.sources`).
COMPILED_SOURCES = ("hapsim/kernels/audio.py", "hapsim/kernels/cordis.py",
                    "hapsim/kernels/schemes.py", "hapsim/kernels/pointers.py")
#: Their SHA-256: numba keys its disk cache on this file alone, so this literal changes
#: with them (``tests/test_compiled_loop_sources.py`` says so); until then, no cache.
COMPILED_SOURCES_SHA256 = "fe6e341892785be0ceedc9d70253f1776c495b1e22a5e61f2a8991b49c737589"
#: Whether numba's disk cache may serve this module's compiled code.
CACHE_OK = cache_ok(COMPILED_SOURCES, COMPILED_SOURCES_SHA256)

_jit = nb.njit(cache=CACHE_OK, nogil=True, boundscheck=False)
#: The context's accessors: compiled once per signature and called (LLVM inlines them),
#: not inlined into numba's IR at each of the runners' ~150 call sites (which re-translated
#: and re-typed the helper at every site: ~1-2 CPU-s a runner into an empty cache). An
#: overload (``register_jitable``) types its constant index as ``int64``, not ``Literal``.
_access = register_jitable(boundscheck=False)

#: Integer slots before the arrays: the count to advance and up to 7 kernel parameters.
HEAD = 8


def context(arrays, head=()) -> tuple[np.ndarray, list]:
    """The int64 context of one runner call (module docstring).

    Parameters
    ----------
    arrays : sequence of ndarray or float
        The kernel's arguments after its integer head, in its order: C-ordered writeable
        float64 or int64 arrays of 1 or 2 dimensions (shared, not copied: keep them alive
        and in place), or floats (each becomes a 1-element float64 array).
    head : sequence of int
        The kernel's integer parameters (at most ``HEAD - 1``; booleans as 0/1).

    Returns
    -------
    ctx : ndarray of int64, shape (HEAD + 3 * len(arrays),)
        ``ctx[0]`` = 1 (set it before each call), the head, each argument's address, rows
        and columns (0 for one dimension).
    keep : list of ndarray
        The 1-element arrays made for float arguments: the caller keeps them alive.

    Raises
    ------
    ValueError
        A head longer than ``HEAD - 1``, an array of another element type than float64 or
        int64, of more than two dimensions, not C-ordered or not writeable.
    """
    if len(head) > HEAD - 1:
        raise ValueError(f"at most {HEAD - 1} head integers, got {len(head)}")
    ctx = np.zeros(HEAD + 3 * len(arrays), np.int64)
    ctx[0] = 1
    ctx[1:1 + len(head)] = [int(h) for h in head]
    keep = []
    for i, a in enumerate(arrays):
        if not isinstance(a, np.ndarray):
            a = np.array([float(a)])
            keep.append(a)
        if a.ndim not in (1, 2):
            raise ValueError(f"argument {i}: 1 or 2 dimensions expected, got shape {a.shape}")
        dtype = np.int64 if a.dtype.kind in "iu" else np.float64
        k = HEAD + 3 * i
        ctx[k] = address(a, dtype)
        ctx[k + 1] = a.shape[0]
        ctx[k + 2] = a.shape[1] if a.ndim == 2 else 0
    return ctx, keep


@_access
def _f(c, i):
    k = HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1],), np.float64)


@_access
def _f2(c, i):
    k = HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1], c[k + 2]), np.float64)


@_access
def _i(c, i):
    k = HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1],), np.int64)


# The runners: ctx[0] samples of one kernel, its arguments in the context in its order,
# then rec (int64), out (2-D); row0 is 0 (a step records nothing). Each is documented by
# its kernel's docstring. The zeros are passed as np.int64(0), not the literal 0: numba
# would type a literal as Literal[int](0) and compile the kernel once more for it (~5 CPU-s
# a kernel into an empty cache) besides the int64 signature Engine.run compiles.

@_jit
def step_masses(c):
    cordis.run_masses(c[0], _f(c, 0), _f(c, 1), _f(c, 2), _i(c, 3), _f(c, 4), _i(c, 5),
                      _i(c, 6), _f2(c, 7), np.int64(0))


@_jit
def step_sd(c):
    cordis.run_sd(c[0], _f(c, 0), _f(c, 1), _f(c, 2), _i(c, 3), _f(c, 4), _i(c, 5),
                  _i(c, 6), _i(c, 7), _f(c, 8), _f(c, 9), _i(c, 10), _f2(c, 11), np.int64(0))


@_jit
def step_contact(c):
    cordis.run_contact(c[0], _f(c, 0), _f(c, 1), _f(c, 2), _i(c, 3), _f(c, 4), _i(c, 5),
                       _i(c, 6), _i(c, 7), _f(c, 8), _f(c, 9), _f(c, 10), _i(c, 11),
                       _f2(c, 12), np.int64(0))


@_jit
def step_sd_contact(c):
    cordis.run_sd_contact(c[0], _f(c, 0), _f(c, 1), _f(c, 2), _i(c, 3), _f(c, 4), _i(c, 5),
                          _i(c, 6), _i(c, 7), _f(c, 8), _f(c, 9), _i(c, 10), _i(c, 11),
                          _f(c, 12), _f(c, 13), _f(c, 14), _i(c, 15), _f2(c, 16), np.int64(0))


@_jit
def step_symplectic_euler(c):
    schemes.run_symplectic_euler(
        c[0], _f(c, 0), _f(c, 1), _f(c, 2), _i(c, 3), _f(c, 4), _i(c, 5), _f(c, 6),
        _f(c, 7), _f(c, 8)[0], _i(c, 9), _i(c, 10), _f(c, 11), _f(c, 12), _i(c, 13),
        _i(c, 14), _f(c, 15), _f(c, 16), _f(c, 17), _i(c, 18), _f2(c, 19), np.int64(0))


@_jit
def step_exact(c):
    schemes.run_exact(
        c[0], _f(c, 0), _f(c, 1), _f(c, 2), _i(c, 3), _f(c, 4), _i(c, 5), _f(c, 6),
        _f(c, 7)[0], _f2(c, 8), _f2(c, 9), _f2(c, 10), _f(c, 11), _f(c, 12), _f(c, 13),
        _i(c, 14), _i(c, 15), _f(c, 16), _f(c, 17), _i(c, 18), _f2(c, 19), np.int64(0))


@_jit
def step_periods(c):
    """``ctx[0]`` device periods of :func:`hapsim.kernels.audio.run_periods` (head ``nsub,
    linear, last, port, mode``). Mode 0 (``Engine.step``): the port held where it is, one
    period per call on its own position (argument 0 is a 1-element scratch), frames and
    forces dropped into scratch; mode 1 (``Engine.port_step``): the periods on the positions
    of argument 0, frames and forces kept in arguments 20 and 21.
    """
    pos, x, frames, force = _f(c, 0), _f(c, 1), _f2(c, 20), _f(c, 21)
    nsub, linear, last, port = c[1], c[2] != 0, c[3] != 0, c[4]
    held = c[5] == 0
    calls, periods = (c[0], 1) if held else (1, c[0])
    for _ in range(calls):
        if held:
            pos[0] = x[port] if port >= 0 else 0.0
        audio.run_periods(periods, nsub, linear, last, port, pos, x, _f(c, 2),
                          _f(c, 3), _i(c, 4), _f(c, 5), _i(c, 6), _i(c, 7), _i(c, 8),
                          _f(c, 9), _f(c, 10), _i(c, 11), _i(c, 12), _f(c, 13), _f(c, 14),
                          _f(c, 15), _i(c, 16), _i(c, 17), _f(c, 18), _f(c, 19)[0], frames,
                          np.int64(0), force, _i(c, 22), _f2(c, 23), np.int64(0))


#: The runner of each kernel (called as ``runner(ctx)``), by the kernel function; kernel
#: ``run_X`` has the runner ``step_X`` (:func:`hapsim.pipeline.startup.part_is_fresh` finds
#: a runner in numba's cache by that name, without importing numba).
RUNNERS = {cordis.run_masses: step_masses, cordis.run_sd: step_sd,
           cordis.run_contact: step_contact, cordis.run_sd_contact: step_sd_contact,
           schemes.run_symplectic_euler: step_symplectic_euler, schemes.run_exact: step_exact,
           audio.run_periods: step_periods}
