"""The compiled host loop's numba code (:mod:`hapsim.host.fastloop` drives it): the
stretch that answers clean STATEs on the port's fd, the per-sample body, the port step of
the engine's kernel, and the layout of the arrays they share with Python.

:func:`answer_stretch` runs, in one ``nogil`` function, for as many samples as it can: wait
for input (``poll``), ``read``, COBS + CRC decode, the port step (the engine's numba
kernel), the safety checks (clamp, non-finite, bounds, passivity observer and controller,
energy), FORCE encode, ``write``, one telemetry row into the preallocated arrays; it returns
a code (``R_*``) when Python must act (:mod:`hapsim.host.fastloop`, module notes). The
per-sample body exists once, :func:`answer_sample`, the numba transcription of
:meth:`hapsim.host.loop.HostLoop._drive`'s body, operation by operation.

numba keys the disk cache of these functions on this file: it holds the digest of the
modules it compiles in (:data:`COMPILED_SOURCES_SHA256`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba.extending import overload

import firmware_protocol as fp
# the compiled I/O primitives, under the names this module's numba code has always used
from hapsim.kernels.compiled_io import (
    POLLERR as _POLLERR, POLLHUP as _POLLHUP, POLLIN as _POLLIN,
    POLLNVAL as _POLLNVAL, POLLOUT as _POLLOUT, c_poll as _c_poll, c_read as _c_read,
    c_write as _c_write, cobs_decode as _cobs_decode,
    crc16 as _crc16, expand_seq as _expand_seq, force_compact_frame as _force_compact_frame,
    force_frame as _force_frame, le as _le, next_frame as _next_frame, now_ns as _now_ns)
from hapsim.kernels.sources import LOOP_SOURCES, source_paths, sources_digest
from hapsim.host.telemetry import FLAG_CLAMPED, FLAG_RAMP, FLAG_SKIPPED
from hapsim.kernels import arguments, cordis, schemes
from hapsim.kernels.ticks import STATUS_FORCE_APPLIED as _FORCE_APPLIED
from hapsim.kernels.ticks import held_force as _held_force
from hapsim.kernels.ticks import named_delay as _named_delay
from hapsim.kernels.ticks import tick_late as _tick_late
from hapsim.kernels.late_growth import GROWTH_MODES as _GROWTH_MODES
from hapsim.kernels.late_growth import GROWTH_POINTS as _GROWTH_POINTS
from hapsim.kernels.late_growth import LATE_GROWTH_STOP as _LATE_GROWTH_STOP
from hapsim.kernels.late_growth import late_growth_step as _late_growth_step
from hapsim.kernels.late_growth import open_hold_growth as _open_hold_growth

#: The sources this module's numba code compiles in (:mod:`hapsim.kernels.sources`).
COMPILED_SOURCES = LOOP_SOURCES

#: SHA-256 of the modules this module's numba code compiles in
#: (:data:`hapsim.kernels.sources.LOOP_SOURCES`, by :func:`~hapsim.kernels.sources.sources_digest`).
#: numba keys its disk cache on this file alone: when those modules change, this constant
#: must change with them (``tests/test_compiled_loop_sources.py`` says so), which edits
#: this file and makes numba recompile. Until then the loop compiles without the cache.
COMPILED_SOURCES_SHA256 = "06e9555bb2419e9055ee99abbe6281ed6454a0039093d6a27e9ae6a7d5432247"

#: Whether numba's disk cache may serve this module's compiled code: only when the modules
#: compiled in are those the digest names (else a cached loop could run an old rule).
CACHE_OK = sources_digest(source_paths(LOOP_SOURCES)) == COMPILED_SOURCES_SHA256

#: The decorator of the compiled loop's functions: nopython, no GIL, cached on disk when
#: :data:`CACHE_OK`.
_jit = numba.njit(nogil=True, cache=CACHE_OK)

__all__ = ["COMPILED_SOURCES", "COMPILED_SOURCES_SHA256", "CACHE_OK", "KERNEL_NAMES",
           "kernel_pack", "kernel_tag", "port_arrays", "answer_sample", "skip_sample",
           "answer_stretch"]

# ----------------------------------------------------------------------------- layout
# iv: int64 state shared by Python and the compiled code
I_K, I_N, I_WSUM, I_RAMP, I_RESTART, I_FAPPLIED, I_LATE, I_CLAMPED, I_PSAMPLES = range(9)
I_LAST_SEQ, I_EXPECT, I_MISSED, I_FRAMES_OK, I_RB_LEN, I_NF_SEQ, I_NMAX, I_SYNC = range(9, 17)
I_HIST, I_ERRNO, I_SAMPLES, I_SKIPPED, I_SKIPFLAG, I_CLAST, I_SKIPN = 17, 18, 19, 20, 21, 22, 23
I_GPREV = 24                # the lateness guard's last FORCE named (-1: none yet)
N_IV = 25
# fv: float64 state
F_ENERGY, F_E0, F_XPREV, F_EMAX, F_XMAX, F_VMAX, F_FMAX, F_LAST_RX = range(8)
F_X, F_V, F_EXCESS = 8, 9, 10
F_GROWTH = 11               # the lateness guard's cumulative growths, one a mode [nepers]
F_GWORST = F_GROWTH + _GROWTH_MODES     # at a stop: the largest, its open hold counted
F_HELD = F_GWORST + 1       # the force the last STATE named as held [N] and which FORCE
N_FV = F_HELD + 2           # (-1: none): held_force's two entries
# pv: float64 parameters
(P_LIM, P_D, P_T, P_RATE, P_POS, P_VLIM, P_ELIM, P_PC, P_BMAX, P_CLAMP_MAX, P_RAMP_N, P_HL,
 P_RL, P_SILENCE, P_POLL, P_NEWEST, P_AHEAD, P_COMPACT, P_CRATE) = range(19)
# the lateness guard (hapsim.kernels.late_growth): its step [ticks] (0: no guard), its
# tables' last index n, their number (modes), and the tables g_k(j * step), j = 0 .. n,
# row after row from P_GTAB on
# and the rest speed below which it does not stop [m/s] (the braking's, LoopConfig.brake_rest)
P_GSTEP, P_GN, P_GK, P_GREST, P_GTAB = 19, 20, 21, 22, 23
N_PV = P_GTAB + _GROWTH_MODES * (_GROWTH_POINTS + 1)

# return codes
R_OK, R_NONFINITE, R_SAFETY, R_IOERR = 0, 1, 2, 3
R_DONE, R_STOP, R_HANDOFF, R_IDLE, R_INTR, R_SYNC, R_PORT = 4, 5, 6, 7, 8, 9, 10

_U32 = 0xFFFFFFFF
_HALF = 0x80000000
_STATE_PACKET = 29          # type + 1-axis STATE body + CRC [bytes]
_VELOCITY_PACKET = 15       # type + 1-axis VELOCITY body + CRC [bytes]
_STATE_C_PACKET = 11        # type + 1-axis STATE_COMPACT body + CRC [bytes]
_MAX_FRAME = fp.MAX_FRAME


# ----------------------------------------------------------------------------- port step
# The engine's kernel is named by a tag among the module-level kernels of hapsim.kernels,
# with its arrays in one tuple (its state arguments, KernelPack.args): numba loads a
# function from its on-disk cache only when no argument is a dispatcher (a first-class
# function argument made the loop compile again at every start, ~8 s). The tag is a tuple
# whose length is the kernel's number + 1, so its numba *type* names the kernel: the loop is
# compiled (and cached) per kernel, with only that kernel in it, instead of all six behind
# a run-time branch (the first run of a spring wall compiled the contact, symplectic and
# exact kernels too). The kernels and their arguments are those of
# hapsim.kernels.arguments.KERNELS (the multi-rate run_periods aside: the compiled loop
# does not run a scene with audio), numbered in its order.
_KERNELS = tuple(name for name, k in arguments.KERNELS.items() if k.module != "audio")
K_MASSES, K_SD, K_CONTACT, K_SD_CONTACT, K_SYMPLECTIC, K_EXACT = (
    _KERNELS.index(name) for name in ("run_masses", "run_sd", "run_contact", "run_sd_contact",
                                      "run_symplectic_euler", "run_exact"))
_MODULES = {"cordis": cordis, "schemes": schemes}
_KINDS = {getattr(_MODULES[arguments.KERNELS[name].module], name): kind
          for kind, name in enumerate(_KERNELS)}
#: The kernels' function names, by kind (the compiled-loop stamps are named after them).
KERNEL_NAMES = dict(enumerate(_KERNELS))


def kernel_pack(engine) -> tuple[tuple, tuple]:
    """The engine's kernel as ``(tag, pack)`` for :func:`_port_step`.

    Parameters
    ----------
    engine : hapsim.engine.Engine
        Its :attr:`~hapsim.engine.Engine.kernel_pack` (the arrays are shared, not copied:
        the kernel updates the engine's state in place).

    Returns
    -------
    tag : tuple
        :func:`kernel_tag` of the kernel (``K_MASSES`` .. ``K_EXACT``): the compiled loop
        is compiled for that kernel alone.
    pack : tuple
        The kernel's state arguments (:attr:`hapsim.engine.KernelPack.args`: the arrays
        and the period ``T`` [s] of :data:`hapsim.kernels.arguments.KERNELS`, in the
        kernel's order): 6 for ``K_MASSES``, 10 ``K_SD``, 11 ``K_CONTACT``, 15
        ``K_SD_CONTACT``, 18 ``K_SYMPLECTIC``, 18 ``K_EXACT``.

    Raises
    ------
    KeyError
        A kernel outside :mod:`hapsim.kernels.cordis` / :mod:`hapsim.kernels.schemes`.
    """
    kp = engine.kernel_pack
    return kernel_tag(_KINDS[kp.kernel]), tuple(kp.args)


def port_arrays(engine, at_least: int = -1) -> tuple:
    """The port's arrays in the engine's kernel pack.

    Parameters
    ----------
    engine : hapsim.engine.Engine
        Its :attr:`~hapsim.engine.Engine.kernel_pack`.
    at_least : int
        Smallest port index returned (a scene without a port: 0 for a throw-away run).

    Returns
    -------
    tuple
        ``(x, f, port)``: the positions [m] and forces [N] (shared, not copied) and the
        port's index.
    """
    kp = engine.kernel_pack
    return kp.state[0], kp.state[2], max(kp.port, at_least)


def _kernel_step(kind, ka, rec, out):
    """One sample of the kernel the tag ``kind`` names, in compiled code only: numba
    replaces each call by that kernel's call (:func:`_kernel_step_for`)."""
    raise NotImplementedError("_kernel_step exists in compiled code only")


def _pack_expression(arg, i, j) -> str:
    """The source of argument ``arg`` of a kernel called on a pack ``ka``
    (:func:`hapsim.kernels.arguments.call_function`): one sample, state argument ``j`` as
    ``ka[j]`` (a constant index), ``rec`` and ``out`` the loop's, the first row 0."""
    if arg.role == arguments.COUNT:
        return "np.int64(1)"
    if arg.role == arguments.ROW:
        return "np.int64(0)"
    if arg.role == arguments.STATE:
        return f"ka[{j}]"
    if arg.role == arguments.CALL and arg.name in ("rec", "out"):
        return arg.name
    raise ValueError(f"the compiled loop has no argument {arg.name!r} ({arg.role})")


@overload(_kernel_step)
def _kernel_step_for(kind, ka, rec, out):
    """The implementation of :func:`_kernel_step` for the kernel tag's type: only that
    kernel is typed and compiled into the loop (a scene pays only for its element kinds,
    the first run included). Its call, every argument written out, is generated from the
    kernel's entry in :data:`hapsim.kernels.arguments.KERNELS` when numba types the loop.

    The sample count and the first row are passed as ``int64`` values (``np.int64``), not
    as the literals ``1`` and ``0``: numba types a literal argument of a call between
    compiled functions as ``Literal[int]`` and compiles the callee once more for that
    signature (~5 CPU-s a kernel into an empty cache), where ``int64`` is the signature
    :meth:`hapsim.engine.Engine.run` and :mod:`hapsim.kernels.step1d` already compile."""
    which = len(kind.types) - 1          # kernel_tag: K + 1 zeros
    if not 0 <= which < len(_KERNELS):
        return None
    name = _KERNELS[which]
    fn = getattr(_MODULES[arguments.KERNELS[name].module], name)
    return arguments.call_function(name, fn, "kind, ka, rec, out", _pack_expression,
                                   {"__name__": __name__, "np": np})


@_jit
def _port_step(kind, ka, rec, out):
    """One sample of the engine's kernel named by the tag ``kind`` on the arrays of ``ka``
    (:func:`kernel_pack`)."""
    _kernel_step(kind, ka, rec, out)


def kernel_tag(kind: int) -> tuple:
    """The tag that names kernel ``kind`` to the compiled loop: ``kind + 1`` zeros, whose
    numba type (a tuple of that length) selects the kernel at compile time.

    Parameters
    ----------
    kind : int
        One of ``K_MASSES`` .. ``K_EXACT``.

    Returns
    -------
    tuple of int
    """
    return (0,) * (int(kind) + 1)


@_jit
def _write_all(fd, buf, n, pfd):
    """Write ``buf[:n]`` (waiting up to 1 s for room); 0, or -1 on an error."""
    done = 0
    tries = 0
    while done < n:
        w = _c_write(fd, buf.ctypes.data + done, n - done)
        if w > 0:
            done += w
            continue
        tries += 1
        if tries > 3:
            return -1
        pfd[0] = fd
        pfd[1] = _POLLOUT
        if _c_poll(pfd.ctypes.data, 1, 1000) <= 0:
            return -1
    return 0


@_jit
def answer_sample(kind, kargs, xs, fs, port, rec, out, iv, fv, pv, fh, win, t_arr, x_arr,
                  f_arr, s_arr, ta_arr, late_arr, fl_arr, fs_arr, st_arr, seq, time_us, status,
                  force_seq, x, t_rx, fd,
                  pkt, f8, u8, table, tx, pfd, ts, f4):
    """One sample of :meth:`HostLoop._drive`, transcribed: late check, port step, observer,
    controller, ramp, clamp, FORCE written, clamp window, telemetry row, maxima, bounds.

    Parameters
    ----------
    kind, kargs : tuple
        The engine kernel's tag and arrays (:func:`kernel_pack`).
    xs, fs : ndarray of float64
        The engine's positions [m] and forces [N] (:func:`port_arrays`; shared).
    port : int
        The port's index in them.
    rec, out : ndarray
        The kernel's recording arguments (empty: nothing recorded).
    iv, fv, pv : ndarray of int64, float64, float64, shapes (N_IV,), (N_FV,), (N_PV,)
        The state shared with Python and the parameters (``I_*``, ``F_*``, ``P_*``).
    fh : ndarray of float64, shape (2, R)
        The FORCEs sent this stretch, by seq: row 0 their seq (-1: none), row 1 their
        force [N] (the energy observer's, :func:`hapsim.kernels.ticks.held_force`).
    win : ndarray of int8
        The clamp window (1: a clamped sample).
    t_arr, x_arr, f_arr, s_arr, ta_arr, late_arr, fl_arr, fs_arr, st_arr : ndarray
        The telemetry's columns (time [s], position [m], force [N], seq, turnaround [us],
        late, flags, force_seq, status), written at the ring's slot of row ``iv[I_N]``.
    seq, time_us, status, force_seq : int
        The STATE's fields (time [us]).
    x : float
        The STATE's position [m].
    t_rx : int
        When its bytes were read [ns, ``CLOCK_MONOTONIC``].
    fd : int
        The port's file descriptor (the FORCE is written there).
    pkt, tx : ndarray of uint8
        Scratch for a decoded frame and the frame written.
    f8, u8, f4 : ndarray
        Views of one 8-byte scratch (float64, bytes, float32).
    table : ndarray of uint16
        The CRC table (:data:`hapsim.kernels.compiled_io.CRC_TABLE`).
    pfd : ndarray of int32, shape (2,)
        ``poll``'s ``struct pollfd``.
    ts : ndarray of int64, shape (2,)
        ``clock_gettime``'s ``struct timespec``.

    Returns
    -------
    int
        R_OK, R_NONFINITE (nothing written; ``iv[I_NF_SEQ]`` = seq), R_SAFETY (row
        logged; ``fv[F_X]``, ``fv[F_V]``, ``fv[F_EXCESS]``, ``fv[F_GWORST]`` say why) or
        R_IOERR (the write failed).
    """
    d = np.int64(pv[P_D])
    lt = 0
    if status & _FORCE_APPLIED and iv[I_FAPPLIED] == 0:
        iv[I_FAPPLIED] = 1
    # the late-tick rule (hapsim.kernels.ticks), as the Python loop and the account read it
    if _tick_late(seq, force_seq, status, d, iv[I_FAPPLIED] != 0):
        lt = 1
        iv[I_LATE] += 1
    g_step = pv[P_GSTEP]
    g_worst = 0.0
    if g_step > 0.0:
        g_n = np.int64(pv[P_GN]) + 1
        g_k = np.int64(pv[P_GK])
        acc = fv[F_GROWTH:F_GROWTH + g_k]
        lag = _named_delay(seq, force_seq, status, iv[I_FAPPLIED] != 0)
        tabs = pv[P_GTAB:P_GTAB + g_k * g_n].reshape((g_k, g_n))
        iv[I_GPREV] = _late_growth_step(acc, iv[I_GPREV], force_seq, lag, tabs, g_step)
        g_worst = _open_hold_growth(acc, iv[I_GPREV], seq, lag, d, tabs, g_step)
    if math.isfinite(x):
        xs[port] = x
        _port_step(kind, kargs, rec, out)
        iv[I_SAMPLES] += 1
        f = fs[port]
    else:
        f = math.nan
    if not math.isfinite(f):
        iv[I_NF_SEQ] = seq
        return R_NONFINITE
    dx = x - fv[F_XPREV]
    fv[F_XPREV] = x
    v = dx * pv[P_RATE]
    k = iv[I_K]
    # the work of the force held over the last period (HostLoop._drive's)
    energy = fv[F_ENERGY] + _held_force(fh, seq, force_seq, status, d, iv[I_FAPPLIED] != 0,
                                        fv[F_HELD:F_HELD + 2]) * dx
    fv[F_ENERGY] = energy
    excess = energy - fv[F_E0]
    if pv[P_PC] != 0.0 and excess > 0.0:
        tvv = pv[P_T] * v * v
        if tvv > 0.0:
            bmax = pv[P_BMAX]
            alpha = excess / tvv if excess < bmax * tvv else bmax
            f -= alpha * v
            iv[I_PSAMPLES] += 1
    rf = 0
    ramp = iv[I_RAMP]
    if ramp > 0:
        ramp_n = np.int64(pv[P_RAMP_N])
        f *= (ramp_n - ramp + 1) / ramp_n
        iv[I_RAMP] = ramp - 1
        rf = FLAG_RAMP
    lim = pv[P_LIM]
    c = 0
    if f > lim:
        f = lim
        c = 1
    elif f < -lim:
        f = -lim
        c = 1
    if pv[P_COMPACT] != 0.0:
        n = _force_compact_frame(seq, f, pkt, f4, u8, table, tx)
    else:
        n = _force_frame(seq, f, pkt, f8, u8, table, tx)
    if _write_all(fd, tx, n, pfd) < 0:
        return R_IOERR
    t_tx = _now_ns(ts)
    iv[I_LAST_SEQ] = seq
    j = seq % fh.shape[1]
    fh[0, j] = seq
    fh[1, j] = f
    iv[I_K] = k + 1
    i = iv[I_N]
    wlen = win.size
    j = i % wlen
    wsum = iv[I_WSUM] + c - win[j]
    iv[I_WSUM] = wsum
    win[j] = c
    iv[I_CLAMPED] += c
    hl = np.int64(pv[P_HL])
    rl = np.int64(pv[P_RL])
    sl = i if i < hl else hl + (i - hl) % rl
    t_arr[sl] = time_us * 1e-6
    x_arr[sl] = x
    f_arr[sl] = f
    s_arr[sl] = seq
    ta_arr[sl] = (t_tx - t_rx) * 1e-3
    late_arr[sl] = lt
    fs_arr[sl] = force_seq
    st_arr[sl] = status
    fl_arr[sl] = lt | rf | iv[I_RESTART] | (FLAG_CLAMPED if c else 0) | iv[I_SKIPFLAG]
    iv[I_RESTART] = 0
    iv[I_SKIPFLAG] = 0
    iv[I_N] = i + 1
    if energy > fv[F_EMAX]:
        fv[F_EMAX] = energy
    if excess > fv[F_XMAX]:
        fv[F_XMAX] = excess
    av = v if v >= 0.0 else -v
    if av > fv[F_VMAX]:
        fv[F_VMAX] = av
    af = f if f >= 0.0 else -f
    if af > fv[F_FMAX]:
        fv[F_FMAX] = af
    pos = pv[P_POS]
    if (wsum >= pv[P_CLAMP_MAX] or x > pos or x < -pos or av > pv[P_VLIM]
            or excess > pv[P_ELIM] or (g_worst > _LATE_GROWTH_STOP and av > pv[P_GREST])):
        fv[F_X] = x
        fv[F_V] = v
        fv[F_EXCESS] = excess
        fv[F_GWORST] = g_worst
        return R_SAFETY
    return R_OK


@_jit
def skip_sample(kind, kargs, xs, port, rec, out, iv, fv, pv, fh, x, sk_row, sk_x, sk_meta,
                seq, force_seq, status, time_us):
    """A STATE the backlog policy skips: the scene steps with its position (the next
    velocity spans one period), nothing is sent; the step goes into the skipped STATEs'
    record (as :meth:`HostLoop._drive`; :mod:`hapsim.host.telemetry`).

    Parameters
    ----------
    kind, kargs : tuple
        The engine kernel's tag and arrays (:func:`kernel_pack`).
    xs, fs : ndarray of float64
        The engine's positions [m] and forces [N] (:func:`port_arrays`; shared).
    port : int
        The port's index in them.
    rec, out : ndarray
        The kernel's recording arguments (empty: nothing recorded).
    iv, fv : ndarray of int64, float64
        The state shared with Python (``I_SAMPLES`` counts the step, ``I_SKIPN`` the
        record's entries, ``F_XPREV`` takes ``x``; ``F_ENERGY`` the work of the force held
        over the period, ``F_HELD`` and the next entry the force this STATE names held
        and which FORCE, as :func:`answer_sample`).
    pv : ndarray of float64
        The parameters (the delay).
    fh : ndarray of float64, shape (2, R)
        The FORCEs sent (:func:`hapsim.kernels.ticks.held_force`).
    x : float
        The skipped STATE's position [m] (not finite: nothing steps, nothing recorded).
    sk_row, sk_x : ndarray of int64, float64, shape (skips,)
        The telemetry's skipped STATEs' record: entry ``iv[I_SKIPN]`` (while it fits)
        takes the row it precedes (``iv[I_N]``) and ``x``.
    sk_meta : ndarray of int64, shape (skips, 4)
        The same entry's ``seq``, ``force_seq``, ``status``, ``time_us``.
    seq, force_seq, status, time_us : int
        The skipped STATE's fields (time [us]).
    """
    if math.isfinite(x):
        xs[port] = x
        _port_step(kind, kargs, rec, out)
        iv[I_SAMPLES] += 1
        d = np.int64(pv[P_D])
        fv[F_ENERGY] += _held_force(fh, seq, force_seq, status, d, iv[I_FAPPLIED] != 0,
                                    fv[F_HELD:F_HELD + 2]) * (x - fv[F_XPREV])
        fv[F_XPREV] = x
        sn = iv[I_SKIPN]
        if sn < sk_row.size:
            sk_row[sn] = iv[I_N]
            sk_x[sn] = x
            sk_meta[sn, 0] = seq
            sk_meta[sn, 1] = force_seq
            sk_meta[sn, 2] = status
            sk_meta[sn, 3] = time_us
        iv[I_SKIPN] = sn + 1


@_jit
def _newer_in(rb, a, n_rb, seq, ahead_max, scratch, table, compact):
    """Whether a complete frame in ``rb[a:n_rb]`` is an armed 1-axis STATE ahead of
    ``seq`` by 1 .. ``ahead_max`` (:func:`hapsim.host.device_clock._newer_waiting`, on bytes).

    ``compact``: the STATE_COMPACTs are expanded in order as the Python decoder's
    :class:`firmware_protocol.CompactExpander` does (from ``seq``, each armed one of any
    number of axes moving the reference)."""
    b = a
    last = seq
    for j in range(a, n_rb):
        if rb[j] != 0:
            continue
        if j > b and j - b <= _MAX_FRAME - 1:
            m = _cobs_decode(rb, b, j, scratch)
            if compact:
                if (scratch[0] == 0x13 and m >= _STATE_C_PACKET and (m - 7) % 4 == 0
                        and (m - 7) // 4 <= fp.MAX_AXES and _crc16(scratch, m, table) == 0
                        and scratch[3] & 0x01):
                    e = _expand_seq(_le(scratch, 1, 2), last)
                    ahead = (e - seq) & _U32
                    if m == _STATE_C_PACKET and 0 < ahead < _HALF and ahead <= ahead_max:
                        return True
                    last = e
            elif (m == _STATE_PACKET and scratch[0] == 0x10 and _crc16(scratch, m, table) == 0
                    and scratch[13] & 0x01):
                ahead = (_le(scratch, 1, 4) - seq) & _U32
                if 0 < ahead < _HALF and ahead <= ahead_max:
                    return True
        b = j + 1
    return False


@_jit
def _keep_frame(rb, a, z, hist, hist_len, iv):
    """A good frame ``rb[a:z]`` the stretch took: into the history ring (the Python
    decoder's ``last_frames`` and ``frames_ok`` get it from there)."""
    h = iv[I_HIST] % hist.shape[0]
    for j in range(z - a):
        hist[h, j] = rb[a + j]
    hist_len[h] = z - a
    iv[I_HIST] += 1


@_jit
def answer_stretch(kind, kargs, xs, fs, port, rec, out, iv, fv, pv, fh, win, t_arr, x_arr,
                   f_arr, s_arr, ta_arr, late_arr, fl_arr, fs_arr, st_arr, fd, rb, stop, pkt,
                   f8, u8, table, tx, pfd, ts, f4, hist, hist_len, sk_row, sk_x, sk_meta):
    """Answer clean STATEs on ``fd`` until something needs Python (the notes of
    :mod:`hapsim.host.fastloop`).

    ``rb[:iv[I_RB_LEN]]`` holds received bytes not yet framed (a partial frame on entry;
    on return with R_HANDOFF or R_PORT, the bytes from the first frame not taken on).

    In a compact session (``pv[P_COMPACT]``) the clean 1-axis STATE_COMPACTs are taken
    instead of STATEs, expanded against ``iv[I_CLAST]`` (the decoder's
    :attr:`firmware_protocol.CompactExpander.last`, -1 for none; moved by each one taken)
    with the time of ``pv[P_CRATE]``, and answered with FORCE_COMPACT.

    Parameters
    ----------
    kind, kargs : tuple
        The engine kernel's tag and arrays (:func:`kernel_pack`).
    xs, fs : ndarray of float64
        The engine's positions [m] and forces [N] (:func:`port_arrays`; shared).
    port : int
        The port's index in them.
    rec, out : ndarray
        The kernel's recording arguments (empty: nothing recorded).
    iv, fv, pv : ndarray of int64, float64, float64, shapes (N_IV,), (N_FV,), (N_PV,)
        The state shared with Python and the parameters (``I_*``, ``F_*``, ``P_*``).
    fh : ndarray of float64, shape (2, R)
        The FORCEs sent this stretch, by seq: row 0 their seq (-1: none), row 1 their
        force [N] (the energy observer's, :func:`hapsim.kernels.ticks.held_force`).
    win : ndarray of int8
        The clamp window (1: a clamped sample).
    t_arr, x_arr, f_arr, s_arr, ta_arr, late_arr, fl_arr, fs_arr, st_arr : ndarray
        The telemetry's columns (time [s], position [m], force [N], seq, turnaround [us],
        late, flags, force_seq, status), written at the ring's slot of row ``iv[I_N]``.
    fd : int
        The port's file descriptor (read, polled and written).
    rb : ndarray of uint8
        The received bytes' buffer (``iv[I_RB_LEN]`` of them held).
    stop : ndarray of int64, shape (1,)
        The stop flag (:attr:`hapsim.spawn.StopFlag.shared`): nonzero, return R_STOP.
    pkt, tx : ndarray of uint8
        Scratch for a decoded frame and the frame written.
    f8, u8, f4 : ndarray
        Views of one 8-byte scratch (float64, bytes, float32).
    table : ndarray of uint16
        The CRC table (:data:`hapsim.kernels.compiled_io.CRC_TABLE`).
    pfd : ndarray of int32, shape (2,)
        ``poll``'s ``struct pollfd``.
    ts : ndarray of int64, shape (2,)
        ``clock_gettime``'s ``struct timespec``.
    hist, hist_len : ndarray
        The ring of the good frames taken and their lengths (the decoder's history).
    sk_row, sk_x, sk_meta : ndarray
        The skipped STATEs' record (:func:`skip_sample`).

    Returns
    -------
    int
        R_DONE (``iv[I_NMAX]`` rows), R_STOP, R_SYNC (``iv[I_SYNC]`` rows), R_HANDOFF (a
        frame for Python), R_IDLE (silence), R_INTR (a signal), R_PORT (a port error),
        or a code of :func:`answer_sample` other than R_OK.
    """
    n_rb = iv[I_RB_LEN]
    silence = pv[P_SILENCE]
    poll_max = pv[P_POLL]
    rate = pv[P_RATE]
    compact = pv[P_COMPACT] != 0.0
    sync_at = iv[I_N] + iv[I_SYNC]
    t_read = _now_ns(ts)            # when the bytes in rb were read (the turnaround's start)
    while True:
        if stop[0] != 0:
            iv[I_RB_LEN] = n_rb
            return R_STOP
        if iv[I_N] >= iv[I_NMAX]:
            iv[I_RB_LEN] = n_rb
            return R_DONE
        if iv[I_N] >= sync_at:
            iv[I_RB_LEN] = n_rb
            return R_SYNC
        # frames complete in the buffer?
        a = np.int64(0)     # int64, not Literal[0]: no specialisation of the helpers
        while True:
            a, z = _next_frame(rb, a, n_rb)
            if z < 0:
                break
            if z - a > _MAX_FRAME - 1:
                break               # overlong: Python counts it
            m = _cobs_decode(rb, a, z, pkt)
            if m == _VELOCITY_PACKET and pkt[0] == 0x12 and _crc16(pkt, m, table) == 0:
                # a clean 1-axis VELOCITY (PROTOCOL.md §4): a good frame, taken (counted and
                # kept in the history as Python's decoder does) and not used: the compiled
                # loop runs no correction (velocity_sensor runs in the Python loop), as
                # the Python loop without one ignores it
                _keep_frame(rb, a, z, hist, hist_len, iv)
                a = z + 1
                continue
            if compact:
                # STATE_COMPACT (PROTOCOL.md §4 "Compact frames"), expanded as
                # firmware_protocol.CompactExpander does: seq after the last armed one,
                # force_seq = seq - lag when FORCE_APPLIED, time of the tick since CONFIG
                if (m != _STATE_C_PACKET or pkt[0] != 0x13
                        or _crc16(pkt, m, table) != 0):
                    break           # not a clean 1-axis STATE_COMPACT: Python's
                seq = _expand_seq(_le(pkt, 1, 2), iv[I_CLAST])
                status = np.int64(pkt[3])
                fseq = (seq - np.int64(pkt[4])) & _U32 if status & _FORCE_APPLIED else 0
                tus = np.int64(round(seq * 1e6 / pv[P_CRATE]))
                for j in range(4):
                    u8[j] = pkt[5 + j]
                x = np.float64(f4[0])
            else:
                if m != _STATE_PACKET or pkt[0] != 0x10 or _crc16(pkt, m, table) != 0:
                    break           # not a clean 1-axis STATE: Python's
                seq = _le(pkt, 1, 4)
                tus = _le(pkt, 5, 8)
                status = _le(pkt, 13, 2)
                fseq = _le(pkt, 15, 4)
                for j in range(8):
                    u8[j] = pkt[19 + j]
                x = f8[0]
            if not status & 0x0001:
                break               # disarmed: Python declares the loss
            expect = iv[I_EXPECT]
            if expect < 0:
                break
            gap = (seq - expect) & _U32
            if gap >= _HALF:
                break               # stale: Python counts it
            t_rx = t_read
            now = _now_ns(ts) * 1e-9
            if gap and gap > (now - fv[F_LAST_RX] + silence) * rate + 2.0:
                break               # implausible: Python counts it
            iv[I_MISSED] += gap
            fv[F_LAST_RX] = now
            iv[I_EXPECT] = (seq + 1) & _U32
            if compact:
                iv[I_CLAST] = seq           # armed: the expansion's reference moves
            iv[I_FRAMES_OK] += 1
            _keep_frame(rb, a, z, hist, hist_len, iv)
            a = z + 1
            if pv[P_NEWEST] != 0.0 and _newer_in(rb, a, n_rb, seq, pv[P_AHEAD], tx, table,
                                                compact):
                iv[I_SKIPPED] += 1          # backlog: answer the newest STATE waiting
                iv[I_SKIPFLAG] = FLAG_SKIPPED
                skip_sample(kind, kargs, xs, port, rec, out, iv, fv, pv, fh, x, sk_row, sk_x,
                            sk_meta, seq, fseq, status, tus)
                continue
            code = answer_sample(kind, kargs, xs, fs, port, rec, out, iv, fv, pv, fh, win, t_arr,
                           x_arr, f_arr, s_arr, ta_arr, late_arr, fl_arr, fs_arr, st_arr,
                           seq, tus, status,
                           fseq, x, t_rx, fd, pkt, f8, u8, table, tx, pfd, ts, f4)
            if code != R_OK or iv[I_N] >= iv[I_NMAX] or stop[0] != 0 or iv[I_N] >= sync_at:
                for j in range(a, n_rb):
                    rb[j - a] = rb[j]
                iv[I_RB_LEN] = n_rb - a
                if code != R_OK:
                    return code
                if stop[0] != 0:
                    return R_STOP
                if iv[I_N] >= iv[I_NMAX]:
                    return R_DONE
                return R_SYNC
        # drop what was taken; hand the rest over if a frame is not ours
        for j in range(a, n_rb):
            rb[j - a] = rb[j]
        n_rb -= a
        if z >= 0 or n_rb > _MAX_FRAME:
            iv[I_RB_LEN] = n_rb
            return R_HANDOFF
        # wait for bytes no longer than the silence still allowed (as the Python loop); once
        # it has run out, still take what is waiting (poll 0 ms), as the Python loop's
        # receive(0) does: after a stall of this thread (a return to Python that waited for
        # the GIL) the device's STATEs are in the port's buffer, the device is not lost
        left = fv[F_LAST_RX] + silence - _now_ns(ts) * 1e-9
        wait = poll_max if left > poll_max else left
        pfd[0] = fd
        pfd[1] = _POLLIN
        ms = np.int32(math.ceil(wait * 1000.0)) if wait > 1e-6 else np.int32(0)
        r = _c_poll(pfd.ctypes.data, 1, ms)
        if r < 0:
            iv[I_RB_LEN] = n_rb
            return R_INTR           # a signal: Python runs its handler
        if r == 0:
            iv[I_RB_LEN] = n_rb
            return R_IDLE
        if (pfd[1] >> 16) & (_POLLERR | _POLLHUP | _POLLNVAL):
            iv[I_RB_LEN] = n_rb
            return R_PORT
        got = _c_read(fd, rb.ctypes.data + n_rb, rb.size - n_rb)
        t_read = _now_ns(ts)
        if got <= 0:
            iv[I_RB_LEN] = n_rb
            return R_PORT
        n_rb += got
