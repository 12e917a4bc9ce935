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
port``; unused slots 0); then ``(address, rows, columns)`` per array, in the kernel's
order: its state and call arguments as :data:`hapsim.kernels.arguments.KERNELS` declares
them (``rec`` and ``out`` last). A float argument (``T``, ``1 / Ta``) is a 1-element
float64 array. The runners' kernel calls are generated from that table (:func:`_call`), so
the order is written once.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba.extending import register_jitable

from hapsim.kernels import arguments, audio, cordis, schemes
from hapsim.kernels.pointers import address, voidptr
from hapsim.kernels.sources import cache_ok

__all__ = ["HEAD", "context", "RUNNERS"]

#: The sources this module's numba code compiles in (:mod:`hapsim.kernels.sources`).
COMPILED_SOURCES = ("hapsim/kernels/audio.py", "hapsim/kernels/cordis.py",
                    "hapsim/kernels/schemes.py", "hapsim/kernels/pointers.py",
                    "hapsim/kernels/arguments.py")
#: Their SHA-256: numba keys its disk cache on this file alone, so this literal changes
#: with them (``tests/test_compiled_loop_sources.py`` says so); until then, no cache.
COMPILED_SOURCES_SHA256 = "bf2cc549a32680a092a60d107a50ef6709281552dbd6deae202398b81e77e9d4"
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


def _context_expression(arg, i, j) -> str:
    """The source of argument ``arg`` of a kernel called from a context ``c``
    (:func:`hapsim.kernels.arguments.call_function`): the count ``n``; a head integer
    ``c[1 + i]`` (a flag ``!= 0``); array ``i`` rebuilt by its type's accessor (a float as
    its 1-element array's ``[0]``); a first row ``np.int64(0)`` (a step records nothing).

    The zeros are ``np.int64(0)``, not the literal 0: numba would type a literal as
    ``Literal[int](0)`` and compile the kernel once more for it (~5 CPU-s a kernel into an
    empty cache) besides the ``int64`` signature :meth:`hapsim.engine.Engine.run` compiles.
    """
    role, typ = arg.role, arg.type
    if role == arguments.COUNT:
        return "n"
    if role == arguments.HEAD:
        return f"c[{1 + i}] != 0" if typ == arguments.BOOL else f"c[{1 + i}]"
    if role == arguments.ROW:
        return "np.int64(0)"
    return {arguments.F: f"_f(c, {i})", arguments.I: f"_i(c, {i})",
            arguments.F2: f"_f2(c, {i})", arguments.FLOAT: f"_f(c, {i})[0]"}[typ]


#: The calls' decorator: numba inlines each into its runner's IR before typing, so the
#: runner is the call written out by hand (same typing, one LLVM module: a called layer,
#: a function or an ``@overload``, cost ~0.4-1 CPU-s a runner into an empty cache, measured
#: with tools/numba_compiles.py), and the runner, in this file, is what numba caches.
_inline = nb.njit(inline="always", nogil=True, boundscheck=False)


def _call(kernel: str):
    """``call(c, n)``: ``n`` samples of the kernel named ``kernel`` on the arrays of the
    context ``c``, its arguments written out from its entry in
    :data:`hapsim.kernels.arguments.KERNELS` (a numba function inlined where it is called).

    Parameters
    ----------
    kernel : str
        A key of :data:`hapsim.kernels.arguments.KERNELS`.

    Returns
    -------
    numba dispatcher
    """
    fn = getattr(_MODULES[arguments.KERNELS[kernel].module], kernel)
    return _inline(arguments.call_function(
        kernel, fn, "c, n", _context_expression,
        {"__name__": __name__, "np": np, "_f": _f, "_f2": _f2, "_i": _i}))


def _slot(kernel: str, name: str) -> int:
    """The context slot of argument ``name`` of ``kernel``: ``1 + i`` for head integer
    ``i``, else its index among the context's arrays (its state and call arguments)."""
    args = arguments.KERNELS[kernel].args
    heads = [a.name for a in args if a.role == arguments.HEAD]
    if name in heads:
        return 1 + heads.index(name)
    return [a.name for a in args if a.role in (arguments.STATE, arguments.CALL)].index(name)


_MODULES = {"cordis": cordis, "schemes": schemes, "audio": audio}
_run_masses, _run_sd, _run_contact, _run_sd_contact = (
    _call(k) for k in ("run_masses", "run_sd", "run_contact", "run_sd_contact"))
_run_symplectic_euler, _run_exact, _run_periods = (
    _call(k) for k in ("run_symplectic_euler", "run_exact", "run_periods"))


# The runners: ctx[0] samples of one kernel, its arguments in the context in its order
# (hapsim.kernels.arguments.KERNELS: the head integers, then its state and call arrays,
# rec and out last); its first rows are 0. Each is documented by its kernel's docstring.

@_jit
def step_masses(c):
    """``c[0]`` samples of ``run_masses`` (its docstring), its arguments in the context
    ``c`` (:data:`hapsim.kernels.arguments.KERNELS`).

    Parameters
    ----------
    c : ndarray of int64
        The context of :func:`context`: ``c[0]`` the samples to advance, then each
        array's address and shape (the arrays advance in place, as by the direct call).
    """
    _run_masses(c, c[0])


@_jit
def step_sd(c):
    """``c[0]`` samples of ``run_sd`` (its docstring), its arguments in the context
    ``c`` (:data:`hapsim.kernels.arguments.KERNELS`).

    Parameters
    ----------
    c : ndarray of int64
        The context of :func:`context`: ``c[0]`` the samples to advance, then each
        array's address and shape (the arrays advance in place, as by the direct call).
    """
    _run_sd(c, c[0])


@_jit
def step_contact(c):
    """``c[0]`` samples of ``run_contact`` (its docstring), its arguments in the context
    ``c`` (:data:`hapsim.kernels.arguments.KERNELS`).

    Parameters
    ----------
    c : ndarray of int64
        The context of :func:`context`: ``c[0]`` the samples to advance, then each
        array's address and shape (the arrays advance in place, as by the direct call).
    """
    _run_contact(c, c[0])


@_jit
def step_sd_contact(c):
    """``c[0]`` samples of ``run_sd_contact`` (its docstring), its arguments in the context
    ``c`` (:data:`hapsim.kernels.arguments.KERNELS`).

    Parameters
    ----------
    c : ndarray of int64
        The context of :func:`context`: ``c[0]`` the samples to advance, then each
        array's address and shape (the arrays advance in place, as by the direct call).
    """
    _run_sd_contact(c, c[0])


@_jit
def step_symplectic_euler(c):
    """``c[0]`` samples of ``run_symplectic_euler`` (its docstring), its arguments in the context
    ``c`` (:data:`hapsim.kernels.arguments.KERNELS`).

    Parameters
    ----------
    c : ndarray of int64
        The context of :func:`context`: ``c[0]`` the samples to advance, then each
        array's address and shape (the arrays advance in place, as by the direct call).
    """
    _run_symplectic_euler(c, c[0])


@_jit
def step_exact(c):
    """``c[0]`` samples of ``run_exact`` (its docstring), its arguments in the context
    ``c`` (:data:`hapsim.kernels.arguments.KERNELS`).

    Parameters
    ----------
    c : ndarray of int64
        The context of :func:`context`: ``c[0]`` the samples to advance, then each
        array's address and shape (the arrays advance in place, as by the direct call).
    """
    _run_exact(c, c[0])


#: :func:`step_periods`' slots: the port positions and the positions (arrays), the port's
#: index (a head integer) and the runner's own mode, after the kernel's head integers.
_P_POS, _P_X = _slot("run_periods", "pos"), _slot("run_periods", "x")
_P_PORT = _slot("run_periods", "port")
_P_MODE = 1 + sum(a.role == arguments.HEAD for a in arguments.KERNELS["run_periods"].args)


@_jit
def step_periods(c):
    """``ctx[0]`` device periods of :func:`hapsim.kernels.audio.run_periods` (head ``nsub,
    linear, last, port, mode``). Mode 0 (``Engine.step``): the port held where it is, one
    period per call on its own position (the ``pos`` array is a 1-element scratch), frames
    and forces dropped into scratch; mode 1 (``Engine.port_step``): the periods on the
    positions of ``pos``, frames and forces kept in the ``audio`` and ``force`` arrays.

    Parameters
    ----------
    c : ndarray of int64
        The context of :func:`context` with the head ``nsub, linear, last, port`` and the
        mode (0 or 1) after it; ``c[0]`` the device periods to advance.
    """
    pos, x = _f(c, _P_POS), _f(c, _P_X)
    port = c[_P_PORT]
    held = c[_P_MODE] == 0
    calls, periods = (c[0], 1) if held else (1, c[0])
    for _ in range(calls):
        if held:
            pos[0] = x[port] if port >= 0 else 0.0
        _run_periods(c, periods)


#: The runner of each kernel (called as ``runner(ctx)``), by the kernel function; kernel
#: ``run_X`` has the runner ``step_X`` (:func:`hapsim.pipeline.startup.part_is_fresh` finds
#: a runner in numba's cache by that name, without importing numba).
RUNNERS = {getattr(_MODULES[k.module], name): globals()["step_" + name[len("run_"):]]
           for name, k in arguments.KERNELS.items()}
