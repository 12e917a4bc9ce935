"""An n-D scene played live: the loop closed on its device, the changes ramped and the
listening points written to the sound ring, one compiled call with one argument per chunk.

One sample ``n`` (the timing of :mod:`hapsim.lockstep` and of the n-D check,
:mod:`hapsim.analysis.scene_check`, so the loop played is the one analysed):

1. every ramp under way takes its next value (``v = c (s + a (e - s))`` or, for a mass,
   ``v = c / (s + a (e - s))``, ``a = done / steps`` after ``done`` is counted: the first
   sample of a change already moves, the ``steps``-th reaches the end), written into the
   engine's (or this loop's) parameter cell;
2. with a device: the port is at the device sample ``rest + x_dev[n]``;
3. the engine advances one sample (:func:`hapsim.kernels.nd.run_context`), computing the
   force on the port ``F[n]``;
4. ``scale F[n]`` enters the delay line and the device holds ``u[n] = scale F[n-d] + h[n]
   e`` over the period (``h`` the hand's force profile [N], repeated every ``every``
   samples when ``every > 0``, ``e`` its unit direction): ``[x, v][n+1] = Ad [x, v][n] +
   Bd u[n]`` (the exact zero-order hold of the Cartesian mass and friction,
   :func:`hapsim.analysis.ths.zoh_matrices`);
5. each listening point is recorded, ``master gain [c] x[axis, mass]`` (minus its previous
   value for a velocity).

The chunk's frames are then appended to the frame ring
(:func:`hapsim.kernels.audio.ring_write`). All arrays are named by address in one int64
context (:mod:`hapsim.kernels.pointers`): the call unboxes one argument and allocates
nothing.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba.extending import register_jitable

from hapsim.kernels import audio as audio_kernel
from hapsim.kernels import nd as nd_kernel
from hapsim.kernels.pointers import address, voidptr
from hapsim.kernels.sources import cache_ok

__all__ = ["play_context", "play_chunk", "play_chunk32", "HEAD", "PLAY_ARRAYS", "FRAMES",
           "RAMPS", "SAMPLE", "RAMP_COLUMNS", "ENGINE_ARRAYS"]

#: The sources this module's numba code compiles in (:mod:`hapsim.kernels.sources`).
COMPILED_SOURCES = ("hapsim/kernels/nd.py", "hapsim/kernels/audio.py",
                    "hapsim/kernels/cordis.py", "hapsim/kernels/pointers.py",
                    "hapsim/kernels/layout.py")
#: Their SHA-256 (``tests/test_play_nd.py`` says when to update it).
COMPILED_SOURCES_SHA256 = "3573dcef48a54d071ded057a3c6009225a6bded29863b7e9cd3eff74350bd61d"
#: Whether numba's disk cache may serve this module's compiled code.
CACHE_OK = cache_ok(COMPILED_SOURCES, COMPILED_SOURCES_SHA256)

_jit = nb.njit(cache=CACHE_OK, nogil=True, boundscheck=False, error_model="numpy")

#: Context head slots: frames to run, dimension, delay [samples], port index (-1: no
#: device loop), ramps in the table, hand profile length, samples run so far, pluck
#: period [samples] (0: once).
FRAMES, DIM, DELAY, PORT, RAMPS, HAND, SAMPLE, EVERY = range(8)
HEAD = 8
#: The arrays a context names, in the order :func:`play_chunk` reads them.
PLAY_ARRAYS = ("engine", "out", "axis", "mass", "velocity", "gain", "ring", "wr", "x", "xp",
               "port_f", "Ad", "Bd", "state", "rest", "line", "hand", "direction",
               "params", "cells", "ramps")
#: Their element types and dimensions: int64 vectors (the engine's context, listening
#: points' axes, masses and velocity flags, the ring's write count), float64 vectors,
#: float64 matrices, the ramp table's cells (int64: address, index), the ring (float32).
_KINDS = {**dict.fromkeys(("engine", "axis", "mass", "velocity", "wr"), (np.int64, 1)),
          **dict.fromkeys(("gain", "port_f", "state", "rest", "hand", "direction",
                           "params"), (np.float64, 1)),
          **dict.fromkeys(("out", "x", "xp", "Ad", "Bd", "line", "ramps"), (np.float64, 2)),
          "cells": (np.int64, 2), "ring": (np.float32, 2)}
#: The arrays held in the engine's precision (float32 for a single-precision engine,
#: whose ``xp`` rows hold the last step ``x[n] - x[n-1]``: the velocity form).
ENGINE_ARRAYS = ("x", "xp", "port_f")
#: Columns of the ramp table: law (0: ``c v``, 1: ``c / v``), c, start, end, steps, done.
RAMP_COLUMNS = 6


def play_context(dim: int, delay: int, port: int, every: int, arrays: dict,
                 dtype=np.float64) -> np.ndarray:
    """The int64 context of :func:`play_chunk` (or, with ``dtype`` float32, of
    :func:`play_chunk32`).

    Parameters
    ----------
    dim : int
        The scene's dimension (2 or 3).
    delay : int
        The device's delay [samples] (>= 0).
    port : int
        The port's mass index, or -1 (no device: the scene runs on its own).
    every : int
        Pluck period [samples] (0: the hand's profile once).
    arrays : dict
        Every array of :data:`PLAY_ARRAYS` by name, kept alive and in place by the
        caller (``engine`` is the engine's own context,
        :func:`hapsim.kernels.nd.context`).
    dtype : numpy dtype, optional
        The engine's precision: the type of :data:`ENGINE_ARRAYS` (float32: a
        single-precision engine, ``port`` then -1).

    Returns
    -------
    ndarray of int64, shape (HEAD + 3 len(PLAY_ARRAYS),)
        Slot :data:`FRAMES` is set before each call, :data:`RAMPS` when the ramp table
        changes; :data:`SAMPLE` counts the samples run.

    Raises
    ------
    ValueError
        An array missing, of another element type or number of dimensions, not
        C-ordered or not writeable.
    """
    if np.dtype(dtype) != np.float64 and port >= 0:
        raise ValueError("a single-precision engine plays without a device (port -1)")
    ctx = np.zeros(HEAD + 3 * len(PLAY_ARRAYS), np.int64)
    ctx[DIM], ctx[DELAY], ctx[PORT], ctx[EVERY] = dim, delay, port, every
    ctx[HAND] = arrays["hand"].shape[0]
    for i, name in enumerate(PLAY_ARRAYS):
        kind, ndim = _KINDS[name]
        if name in ENGINE_ARRAYS:
            kind = dtype
        a = arrays[name]
        if a.ndim != ndim:
            raise ValueError(f"{name}: {ndim} dimensions expected, got shape {a.shape}")
        ctx[HEAD + 3 * i:HEAD + 3 * i + 3] = (address(a, kind), a.shape[0],
                                              a.shape[-1] if ndim == 2 else 0)
    return ctx


_inline = nb.njit(cache=CACHE_OK, nogil=True, inline="always")
#: The context's accessors: compiled once per signature and called (LLVM inlines them),
#: not inlined into numba's IR at each call site (which translated and typed the accessor
#: again at every site); an overload (``register_jitable``) types the constant index as
#: ``int64``, not ``Literal``, so each compiles once per dtype. A view, no arithmetic.
_access = register_jitable


@_access
def _v1(c, i, dtype):
    """Array ``i`` of the context, 1-D, of ``dtype`` (no copy)."""
    k = HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1],), dtype)


@_access
def _v2(c, i, dtype):
    """Array ``i`` of the context, 2-D, of ``dtype`` (no copy)."""
    k = HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1], c[k + 2]), dtype)


@_jit
def play_chunk(ctx):
    """Run ``ctx[FRAMES]`` samples of the played loop (module docstring) and append their
    frames to the ring.

    Parameters
    ----------
    ctx : ndarray of int64
        From :func:`play_context` (its arrays alive and in place); ``ctx[FRAMES]`` at most
        the rows of its ``out`` array.
    """
    eng = _v1(ctx, 0, np.int64)
    out = _v2(ctx, 1, np.float64)
    axis = _v1(ctx, 2, np.int64)
    mass = _v1(ctx, 3, np.int64)
    vel = _v1(ctx, 4, np.int64)
    gain = _v1(ctx, 5, np.float64)
    ring = _v2(ctx, 6, np.float32)
    wr = _v1(ctx, 7, np.int64)
    x = _v2(ctx, 8, np.float64)
    xp = _v2(ctx, 9, np.float64)
    port_f = _v1(ctx, 10, np.float64)
    Ad = _v2(ctx, 11, np.float64)
    Bd = _v2(ctx, 12, np.float64)
    state = _v1(ctx, 13, np.float64)
    rest = _v1(ctx, 14, np.float64)
    line = _v2(ctx, 15, np.float64)
    hand = _v1(ctx, 16, np.float64)
    direction = _v1(ctx, 17, np.float64)
    params = _v1(ctx, 18, np.float64)
    cells = _v2(ctx, 19, np.int64)
    ramps = _v2(ctx, 20, np.float64)
    frames = ctx[FRAMES]
    dim = ctx[DIM]
    d = ctx[DELAY]
    port = ctx[PORT]
    H = ctx[HAND]
    every = ctx[EVERY]
    m2 = 2 * dim
    for k in range(frames):
        s = ctx[SAMPLE]
        _ramp(ctx[RAMPS], ramps, cells, np.float64)
        if port >= 0:
            for i in range(dim):
                x[i, port] = rest[i] + state[i]
        eng[0] = 1
        nd_kernel.run_context(eng)
        if port >= 0:
            h = 0.0
            j = s % every if every > 0 else s
            if j < H:
                h = hand[j]
            # u = scale F[n - d] + h e (F[n] enters the line), kept in state[2n:3n]
            for i in range(dim):
                f = params[0] * port_f[i]
                if d > 0:
                    u = line[s % d, i]
                    line[s % d, i] = f
                else:
                    u = f
                state[m2 + i] = u + h * direction[i]
            # [x, v] <- Ad [x, v] + Bd u, through state[3n:5n]
            for i in range(m2):
                acc = 0.0
                for j2 in range(m2):
                    acc += Ad[i, j2] * state[j2]
                for j2 in range(dim):
                    acc += Bd[i, j2] * state[m2 + j2]
                state[m2 + dim + i] = acc
            for i in range(m2):
                state[i] = state[m2 + dim + i]
        _listen(out, k, x, xp, axis, mass, vel, gain, params[1], False)
        ctx[SAMPLE] = s + 1
    audio_kernel.ring_write(out[:frames], ring, wr)


@_jit
def play_chunk32(ctx):
    """:func:`play_chunk` for a single-precision engine (its state float32, in the
    scheme's velocity form: ``xp`` holds ``x[n] - x[n-1]``), which plays without a device
    (a port's scene runs the double-precision engine): each sample the ramps advance
    (written to the engine's float32 cells), the engine steps
    (:func:`hapsim.kernels.nd.run_context32`) and the listening points are recorded.

    Parameters
    ----------
    ctx : ndarray of int64
        From :func:`play_context` with ``dtype=np.float32`` and port -1.
    """
    eng = _v1(ctx, 0, np.int64)
    out = _v2(ctx, 1, np.float64)
    axis = _v1(ctx, 2, np.int64)
    mass = _v1(ctx, 3, np.int64)
    vel = _v1(ctx, 4, np.int64)
    gain = _v1(ctx, 5, np.float64)
    ring = _v2(ctx, 6, np.float32)
    wr = _v1(ctx, 7, np.int64)
    x = _v2(ctx, 8, np.float32)
    v = _v2(ctx, 9, np.float32)
    params = _v1(ctx, 18, np.float64)
    cells = _v2(ctx, 19, np.int64)
    ramps = _v2(ctx, 20, np.float64)
    frames = ctx[FRAMES]
    for k in range(frames):
        _ramp(ctx[RAMPS], ramps, cells, np.float32)
        eng[0] = 1
        nd_kernel.run_context32(eng)
        _listen(out, k, x, v, axis, mass, vel, gain, params[1], True)
        ctx[SAMPLE] += 1
    audio_kernel.ring_write(out[:frames], ring, wr)


@_inline
def _ramp(count, ramps, cells, dtype):
    """Every ramp under way takes its next value (module docstring, step 1), written into
    its cell, an array of ``dtype`` (the engine's precision, or this loop's float64)."""
    for r in range(count):
        if ramps[r, 5] < ramps[r, 4]:
            ramps[r, 5] += 1.0
            a = ramps[r, 5] / ramps[r, 4]
            v = ramps[r, 2] + a * (ramps[r, 3] - ramps[r, 2])
            v = ramps[r, 1] / v if ramps[r, 0] == 1.0 else ramps[r, 1] * v
            cell = nb.carray(voidptr(cells[r, 0]), (cells[r, 1] + 1,), dtype)
            cell[cells[r, 1]] = v


@_inline
def _listen(out, k, x, xp, axis, mass, vel, gain, g, step_form):
    """Frame ``k``: each listening point, ``g gain[c] x[axis, mass]`` or, for a velocity,
    its last step (``x - xp``, or ``xp`` itself in the velocity form: ``step_form``)."""
    for c in range(out.shape[1]):
        v = float(x[axis[c], mass[c]])
        if vel[c] != 0:
            v = float(xp[axis[c], mass[c]]) if step_form else v - xp[axis[c], mass[c]]
        out[k, c] = g * gain[c] * v
