"""The device-clocked host loop compiled with numba: the hot path owns the port's fd.

:class:`CompiledHostLoop` is a :class:`~hapsim.host.loop.HostLoop` whose device-clocked
stretch runs in one numba ``nogil`` function, :func:`_stretch`, for as many samples as it
can: wait for input (``poll``), ``read``, COBS + CRC decode, the port step (the engine's
numba kernel), the safety checks (clamp, non-finite, bounds, passivity observer and
controller, energy), FORCE encode, ``write``, one telemetry row into the preallocated
arrays. libc is called from nopython code by symbol (numba ``ExternalFunction``); pyserial still
opens and configures the port.

It returns to Python only for what Python must do, and Python then does exactly what the
reference loop does (:meth:`HostLoop._device_states`, which reads through
:meth:`CompiledHostLoop._receive_hook`):

- a frame it does not take: anything but a clean, armed, 1-axis STATE in sequence order
  (in a compact session, STATE_COMPACT, expanded as the decoder's
  :class:`firmware_protocol.CompactExpander` does, whose reference seq it shares, and
  answered with FORCE_COMPACT) or a clean 1-axis VELOCITY (bad frames, FAULT, HELLO, stale / implausible / unarmed
  STATEs): the bytes from that frame on are fed to the transport's Python decoder and the
  reference code handles them. A VELOCITY it takes is counted and kept in the decoder's
  history, and not used, as the Python loop does without a velocity_sensor correction
  (corrections, the only readers of the measured velocity, run in the Python loop);
- silence (no byte within what the reference loop would wait) or a port error: the
  reference code declares the loss;
- a stop request (:attr:`StopFlag.shared`, set by the signal handler; a signal interrupting
  ``poll`` returns at once so that Python runs the handler), the end of the run, a safety
  stop;
- every ``sync`` rows, so that ``Telemetry.n`` moves on and the journal writer thread
  (which runs meanwhile: the compiled code holds no GIL) drains the ring.

The per-sample body exists once, :func:`_sample`, used by the compiled stretch and by the
samples Python hands over; it is the numba transcription of :meth:`HostLoop._drive`'s
body, operation by operation, so forces and telemetry are bit-identical to the Python loop
on the same device stream (``tests/test_compiled_loop.py``). Backlog
(``LoopConfig.backlog``): with ``"newest"`` a clean STATE followed in the buffer by a newer
one is skipped (counted, flagged on the next row), as the Python loop does within a read.
"""

from __future__ import annotations

import math
import time

import numba
import numpy as np
from numba.extending import overload

import firmware_protocol as fp
# the compiled I/O primitives, under the names this module's numba code has always used
from hapsim.kernels.compiled_io import (
    CRC_TABLE as _CRC, POLLERR as _POLLERR, POLLHUP as _POLLHUP, POLLIN as _POLLIN,
    POLLNVAL as _POLLNVAL, POLLOUT as _POLLOUT, c_poll as _c_poll, c_read as _c_read,
    c_write as _c_write, cobs_decode as _cobs_decode,
    crc16 as _crc16, expand_seq as _expand_seq, force_compact_frame as _force_compact_frame,
    force_frame as _force_frame, le as _le, next_frame as _next_frame, now_ns as _now_ns)
from hapsim.host.loop import HostLoop, LostDevice, safety_reason
from hapsim.kernels.sources import LOOP_SOURCES, source_paths, sources_digest
from hapsim.host.telemetry import FLAG_CLAMPED, FLAG_RAMP, FLAG_SKIPPED
from hapsim.errors import DeviceError
from hapsim.kernels import cordis, schemes
from hapsim.kernels.ticks import STATUS_FORCE_APPLIED as _FORCE_APPLIED
from hapsim.kernels.ticks import tick_late as _tick_late

#: The sources this module's numba code compiles in (:mod:`hapsim.kernels.sources`).
COMPILED_SOURCES = LOOP_SOURCES

#: SHA-256 of the modules this module's numba code compiles in
#: (:data:`hapsim.kernels.sources.LOOP_SOURCES`, by :func:`~hapsim.kernels.sources.sources_digest`).
#: numba keys its disk cache on this file alone: when those modules change, this constant
#: must change with them (``tests/test_compiled_loop_sources.py`` says so), which edits
#: this file and makes numba recompile. Until then the loop compiles without the cache.
COMPILED_SOURCES_SHA256 = "dd8d54c211780984ad193acb72a4974695eb7e9fad700629bf5ab6a6333d7e65"

#: Whether numba's disk cache may serve this module's compiled code: only when the modules
#: compiled in are those the digest names (else a cached loop could run an old rule).
CACHE_OK = sources_digest(source_paths(LOOP_SOURCES)) == COMPILED_SOURCES_SHA256

#: The decorator of the compiled loop's functions: nopython, no GIL, cached on disk when
#: :data:`CACHE_OK`.
_jit = numba.njit(nogil=True, cache=CACHE_OK)

__all__ = ["CompiledHostLoop", "compiled_available", "encode_force", "warm_up"]

# ----------------------------------------------------------------------------- layout
# iv: int64 state shared by Python and the compiled code
I_K, I_N, I_WSUM, I_RAMP, I_RESTART, I_FAPPLIED, I_LATE, I_CLAMPED, I_PSAMPLES = range(9)
I_LAST_SEQ, I_EXPECT, I_MISSED, I_FRAMES_OK, I_RB_LEN, I_NF_SEQ, I_NMAX, I_SYNC = range(9, 17)
I_HIST, I_ERRNO, I_SAMPLES, I_SKIPPED, I_SKIPFLAG, I_CLAST = 17, 18, 19, 20, 21, 22
N_IV = 23
# fv: float64 state
F_ENERGY, F_E0, F_XPREV, F_EMAX, F_XMAX, F_VMAX, F_FMAX, F_LAST_RX = range(8)
F_X, F_V, F_EXCESS = 8, 9, 10
N_FV = 11
# pv: float64 parameters
(P_LIM, P_D, P_T, P_RATE, P_POS, P_VLIM, P_ELIM, P_PC, P_BMAX, P_CLAMP_MAX, P_RAMP_N, P_HL,
 P_RL, P_SILENCE, P_POLL, P_NEWEST, P_AHEAD, P_COMPACT, P_CRATE) = range(19)
N_PV = 19

# return codes
R_OK, R_NONFINITE, R_SAFETY, R_IOERR = 0, 1, 2, 3
R_DONE, R_STOP, R_HANDOFF, R_IDLE, R_INTR, R_SYNC, R_PORT = 4, 5, 6, 7, 8, 9, 10

_U32 = 0xFFFFFFFF
_HALF = 0x80000000
_STATE_PACKET = 29          # type + 1-axis STATE body + CRC [bytes]
_VELOCITY_PACKET = 15       # type + 1-axis VELOCITY body + CRC [bytes]
_STATE_C_PACKET = 11        # type + 1-axis STATE_COMPACT body + CRC [bytes]
_MAX_FRAME = fp.MAX_FRAME
_RB_SIZE = 1 << 16
#: The compiled stretch returns to Python at least this often [s of samples] to publish
#: ``Telemetry.n`` (the journal writer drains up to there).
SYNC_SECONDS = 0.02
_HIST = 16


# ----------------------------------------------------------------------------- port step
# The engine's kernel is named by a tag among the module-level kernels of hapsim.kernels,
# with its arrays in one tuple of fixed types (unused slots empty): numba loads a function
# from its on-disk cache only when no argument is a dispatcher (a first-class function
# argument made the loop compile again at every start, ~8 s). The tag is a tuple whose
# length is the kernel's number + 1, so its numba *type* names the kernel: the loop is
# compiled (and cached) per kernel, with only that kernel in it, instead of all six behind
# a run-time branch (the first run of a spring wall compiled the contact, symplectic and
# exact kernels too).
K_MASSES, K_SD, K_CONTACT, K_SD_CONTACT, K_SYMPLECTIC, K_EXACT = range(6)
_KINDS = {cordis.run_masses: K_MASSES, cordis.run_sd: K_SD, cordis.run_contact: K_CONTACT,
          cordis.run_sd_contact: K_SD_CONTACT, schemes.run_symplectic_euler: K_SYMPLECTIC,
          schemes.run_exact: K_EXACT}
#: The kernels' function names, by kind (the compiled-loop stamps are named after them).
_KERNEL_NAMES = {k: f.__name__ for f, k in _KINDS.items()}
_EI = np.empty(0, dtype=np.int64)
_EF = np.empty(0, dtype=np.float64)
_EF2 = np.empty((0, 0), dtype=np.float64)


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
        ``(x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z, c_i1, c_i2, c_k, c_z,
        c_thr, v, c, T, phi, gam, psi, snew, sold, uold)``; the slots the kernel does not
        take are empty arrays (``T`` 0.0).

    Raises
    ------
    KeyError
        A kernel outside :mod:`hapsim.kernels.cordis` / :mod:`hapsim.kernels.schemes`.
    """
    kp = engine.kernel_pack
    kind = _KINDS[kp.kernel]
    sd = kp.sd if kp.sd is not None else (_EI, _EI, _EF, _EF)
    ct = kp.contact if kp.contact is not None else (_EI, _EI, _EF, _EF, _EF)
    sc = kp.scheme
    extras = tuple(sc.get(name, _EF) for name in ("v", "c")) + (float(sc.get("T", 0.0)),) \
        + tuple(sc.get(name, _EF2) for name in ("phi", "gam", "psi")) \
        + tuple(sc.get(name, _EF) for name in ("snew", "sold", "uold"))
    return kernel_tag(kind), tuple(kp.state) + tuple(sd) + tuple(ct) + extras


def _port_arrays(engine, at_least: int = -1) -> tuple:
    """``(x, f, port)`` of the engine's kernel pack: its positions and forces (shared) and
    the port's index (at least ``at_least``)."""
    kp = engine.kernel_pack
    return kp.state[0], kp.state[2], max(kp.port, at_least)


def _kernel_step(kind, ka, rec, out):
    """One sample of the kernel the tag ``kind`` names, in compiled code only: numba
    replaces each call by that kernel's call (:func:`_kernel_step_for`)."""
    raise NotImplementedError("_kernel_step exists in compiled code only")


@overload(_kernel_step)
def _kernel_step_for(kind, ka, rec, out):
    """The implementation of :func:`_kernel_step` for the kernel tag's type: only that
    kernel is typed and compiled into the loop (a scene pays only for its element kinds,
    the first run included).

    The sample count and the first row are passed as ``int64`` values (``np.int64``), not
    as the literals ``1`` and ``0``: numba types a literal argument of a call between
    compiled functions as ``Literal[int]`` and compiles the callee once more for that
    signature (~5 CPU-s a kernel into an empty cache), where ``int64`` is the signature
    :meth:`hapsim.engine.Engine.run` and :mod:`hapsim.kernels.step1d` already compile."""
    which = len(kind.types) - 1          # kernel_tag: K + 1 zeros
    if which == K_MASSES:
        def step(kind, ka, rec, out):
            n, row0 = np.int64(1), np.int64(0)
            x, xp, f, mobile, t2m, fixed = ka[:6]
            cordis.run_masses(n, x, xp, f, mobile, t2m, fixed, rec, out, row0)
    elif which == K_SD:
        def step(kind, ka, rec, out):
            n, row0 = np.int64(1), np.int64(0)
            x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z = ka[:10]
            cordis.run_sd(n, x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z, rec,
                          out, row0)
    elif which == K_CONTACT:
        def step(kind, ka, rec, out):
            n, row0 = np.int64(1), np.int64(0)
            x, xp, f, mobile, t2m, fixed = ka[:6]
            c_i1, c_i2, c_k, c_z, c_thr = ka[10:15]
            cordis.run_contact(n, x, xp, f, mobile, t2m, fixed, c_i1, c_i2, c_k, c_z, c_thr,
                               rec, out, row0)
    elif which == K_SD_CONTACT:
        def step(kind, ka, rec, out):
            n, row0 = np.int64(1), np.int64(0)
            (x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z, c_i1, c_i2, c_k, c_z,
             c_thr) = ka[:15]
            cordis.run_sd_contact(n, x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z,
                                  c_i1, c_i2, c_k, c_z, c_thr, rec, out, row0)
    elif which == K_SYMPLECTIC:
        def step(kind, ka, rec, out):
            n, row0 = np.int64(1), np.int64(0)
            (x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z, c_i1, c_i2, c_k, c_z,
             c_thr, v, c, T) = ka[:18]
            schemes.run_symplectic_euler(n, x, xp, f, mobile, t2m, fixed, v, c, T, sd_i1,
                                         sd_i2, sd_k, sd_z, c_i1, c_i2, c_k, c_z, c_thr, rec,
                                         out, row0)
    elif which == K_EXACT:
        def step(kind, ka, rec, out):
            n, row0 = np.int64(1), np.int64(0)
            (x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z, c_i1, c_i2, c_k, c_z,
             c_thr, v, c, T, phi, gam, psi, snew, sold, uold) = ka
            schemes.run_exact(n, x, xp, f, mobile, t2m, fixed, v, T, phi, gam, psi, snew,
                              sold, uold, sd_i1, sd_i2, sd_k, sd_z, rec, out, row0)
    else:
        return None
    return step


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
def _sample(kind, kargs, xs, fs, port, rec, out, iv, fv, pv, fh, win, t_arr, x_arr, f_arr,
            s_arr, ta_arr, late_arr, fl_arr, fs_arr, st_arr, seq, time_us, status, force_seq,
            x, t_rx, fd,
            pkt, f8, u8, table, tx, pfd, ts, f4):
    """One sample of :meth:`HostLoop._drive`, transcribed: late check, port step, observer,
    controller, ramp, clamp, FORCE written, clamp window, telemetry row, maxima, bounds.

    Returns R_OK, R_NONFINITE (nothing written; ``iv[I_NF_SEQ]`` = seq), R_SAFETY (row
    logged) or R_IOERR (the write failed)."""
    d = np.int64(pv[P_D])
    lt = 0
    if status & _FORCE_APPLIED and iv[I_FAPPLIED] == 0:
        iv[I_FAPPLIED] = 1
    # the late-tick rule (hapsim.kernels.ticks), as the Python loop and the account read it
    if _tick_late(seq, force_seq, status, d, iv[I_FAPPLIED] != 0):
        lt = 1
        iv[I_LATE] += 1
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
    fhl = fh.size
    energy = fv[F_ENERGY]
    if k > d:
        energy += fh[(k - 1 - d) % fhl] * dx
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
    fh[k % fhl] = f
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
            or excess > pv[P_ELIM]):
        fv[F_X] = x
        fv[F_V] = v
        fv[F_EXCESS] = excess
        return R_SAFETY
    return R_OK


@_jit
def _skip_step(kind, kargs, xs, port, rec, out, iv, fv, x):
    """A STATE the backlog policy skips: the scene steps with its position (the next
    velocity spans one period), nothing is sent or logged (as :meth:`HostLoop._drive`)."""
    if math.isfinite(x):
        xs[port] = x
        _port_step(kind, kargs, rec, out)
        iv[I_SAMPLES] += 1
        fv[F_XPREV] = x


@_jit
def _newer_in(rb, a, n_rb, seq, ahead_max, scratch, table, compact):
    """Whether a complete frame in ``rb[a:n_rb]`` is an armed 1-axis STATE ahead of
    ``seq`` by 1 .. ``ahead_max`` (:func:`hapsim.host.loop._newer_waiting`, on bytes).

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
def _stretch(kind, kargs, xs, fs, port, rec, out, iv, fv, pv, fh, win, t_arr, x_arr, f_arr,
             s_arr, ta_arr, late_arr, fl_arr, fs_arr, st_arr, fd, rb, stop, pkt, f8, u8, table,
             tx, pfd, ts, f4, hist, hist_len):
    """Answer clean STATEs on ``fd`` until something needs Python (module notes).

    ``rb[:iv[I_RB_LEN]]`` holds received bytes not yet framed (a partial frame on entry;
    on return with R_HANDOFF or R_PORT, the bytes from the first frame not taken on).

    In a compact session (``pv[P_COMPACT]``) the clean 1-axis STATE_COMPACTs are taken
    instead of STATEs, expanded against ``iv[I_CLAST]`` (the decoder's
    :attr:`firmware_protocol.CompactExpander.last`, -1 for none; moved by each one taken)
    with the time of ``pv[P_CRATE]``, and answered with FORCE_COMPACT."""
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
        handled = False
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
            handled = True
            if pv[P_NEWEST] != 0.0 and _newer_in(rb, a, n_rb, seq, pv[P_AHEAD], tx, table,
                                                compact):
                iv[I_SKIPPED] += 1          # backlog: answer the newest STATE waiting
                iv[I_SKIPFLAG] = FLAG_SKIPPED
                _skip_step(kind, kargs, xs, port, rec, out, iv, fv, x)
                continue
            code = _sample(kind, kargs, xs, fs, port, rec, out, iv, fv, pv, fh, win, t_arr,
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


def compiled_available(transport) -> bool:
    """Whether the compiled loop can own this transport's port (a pyserial port with a
    file descriptor: hardware, or the mock's pty)."""
    ser = getattr(transport, "serial_port", None)
    return isinstance(getattr(ser, "fd", None), int)


def encode_force(seq: int, force: float, compact: bool = False) -> bytes:
    """The compiled encoder's frame of ``FORCE(seq, (force,))``.

    Parameters
    ----------
    seq : int
        The STATE's seq answered (u32).
    force : float
        Force [N].
    compact : bool
        FORCE_COMPACT (PROTOCOL.md §4 "Compact frames") instead of FORCE.

    Returns
    -------
    bytes
        The COBS frame with its delimiter: equals :func:`firmware_protocol.encode` of the
        FORCE, or of :func:`firmware_protocol.compact_force` of it (checked by the tests).
    """
    out = np.zeros(32, dtype=np.uint8)
    u8 = np.zeros(8, dtype=np.uint8)
    if compact:
        n = _force_compact_frame(np.int64(seq), float(force), np.zeros(32, dtype=np.uint8),
                                 u8.view(np.float32), u8, _CRC, out)
    else:
        n = _force_frame(np.int64(seq), float(force), np.zeros(32, dtype=np.uint8),
                         u8.view(np.float64), u8, _CRC, out)
    return bytes(out[:n])


class CompiledHostLoop(HostLoop):
    """:class:`HostLoop` with the device-clocked hot path compiled (module notes).

    Same parameters, attributes, results and errors as :class:`HostLoop`; falls back to
    the Python loop when the transport has no file descriptor (in-process or virtual-clock
    transports) or the loop is host-clocked.

    Parameters
    ----------
    engine, transport, config, telemetry, stop
        As :class:`HostLoop`.
    sync : int
        Most rows the compiled stretch runs before returning so that ``Telemetry.n`` is
        published to the journal writer; default :data:`SYNC_SECONDS` of samples.
    """

    def __init__(self, engine, transport, config, telemetry, stop=None, sync: int | None = None):
        super().__init__(engine, transport, config, telemetry, stop)
        # a loop that is not real-time drains the journal itself at half laps (Python)
        self.compiled = (compiled_available(transport) and not config.host_clocked
                         and not (telemetry.drain is not None and telemetry.ring))
        # rows published every 20 ms: the journal writer (every 50 ms) never waits longer
        # for them than the Python loop makes it wait (a kill -9 loses <= 100 ms)
        self._sync = int(sync) if sync else max(int(config.rate_hz * SYNC_SECONDS), 1)
        self._fast = None
        #: Samples the compiled stretch answered itself (the others went through Python's
        #: source of STATEs: first after a CONFIG, after a frame it hands over).
        self.compiled_samples = 0

    # ---------------------------------------------------------------- shared state
    def _setup(self, first_x: float) -> None:
        """Arrays of the stretch that starts now (after :meth:`_resume`)."""
        cfg, tel, res = self.config, self.tel, self.result
        eng = self.engine
        d = cfg.delay
        iv = np.zeros(N_IV, dtype=np.int64)
        fv = np.zeros(N_FV, dtype=np.float64)
        pv = np.zeros(N_PV, dtype=np.float64)
        iv[I_N] = tel.n
        iv[I_RAMP] = self._ramp
        iv[I_RESTART] = self._restart_flag
        iv[I_FAPPLIED] = 1 if self._applied_seen else 0
        iv[I_LAST_SEQ] = self._last_seq
        iv[I_SYNC] = self._sync
        fv[F_ENERGY] = self._energy
        fv[F_E0] = self._e0
        fv[F_XPREV] = first_x
        fv[F_EMAX] = res.energy_max
        fv[F_XMAX] = res.energy_excess_max
        fv[F_VMAX] = res.v_max
        fv[F_FMAX] = res.f_max
        pv[P_LIM] = self.force_limit
        pv[P_D] = d
        pv[P_T] = 1.0 / cfg.rate_hz
        pv[P_RATE] = float(cfg.rate_hz)
        pv[P_POS] = cfg.position_bound
        pv[P_VLIM] = cfg.velocity_limit
        pv[P_ELIM] = cfg.energy_limit
        pv[P_PC] = 1.0 if cfg.passivity_controller else 0.0
        pv[P_BMAX] = float(cfg.max_damping)
        pv[P_CLAMP_MAX] = cfg.clamp_max
        pv[P_RAMP_N] = max(int(cfg.ramp_samples), 1)
        pv[P_HL] = tel.head
        pv[P_RL] = tel.ring
        pv[P_SILENCE] = self._silence()
        pv[P_POLL] = min(0.1, pv[P_SILENCE])
        pv[P_NEWEST] = 1.0 if cfg.backlog == "newest" else 0.0
        pv[P_AHEAD] = pv[P_SILENCE] * float(cfg.rate_hz) + 2.0
        self._compact_params(pv, iv)
        u8 = np.zeros(8, dtype=np.uint8)
        fd = self.transport.serial_port.fd if self.compiled else -1
        self._fast = {
            "iv": iv, "fv": fv, "pv": pv,
            "fh": np.zeros(d + 2, dtype=np.float64),
            "win": np.zeros(max(cfg.clamp_window, 1), dtype=np.int8),
            "eng": (*kernel_pack(eng), *_port_arrays(eng), _REC, _OUT),
            "tel": (tel.time, tel.position, tel.force, tel.seq, tel.turnaround_us, tel.late,
                    tel.flags, tel.force_seq, tel.status),
            "io": (fd, np.zeros(64, dtype=np.uint8), u8.view(np.float64), u8, _CRC,
                   np.zeros(32, dtype=np.uint8), np.zeros(2, dtype=np.int32),
                   np.zeros(2, dtype=np.int64), u8.view(np.float32)),
            "rb": np.zeros(_RB_SIZE, dtype=np.uint8),
            "hist": np.zeros((_HIST, _MAX_FRAME), dtype=np.uint8),
            "hist_len": np.zeros(_HIST, dtype=np.int64),
            "hist_seen": 0, "samples_seen": 0, "states_seen": 0,
        }

    def _compact_params(self, pv, iv) -> None:
        """The compact session's parameters from the transport (PROTOCOL.md §4 "Compact
        frames"): whether it is one, the expander's tick rate and its reference seq (-1:
        none) into ``pv`` / ``iv``."""
        exp = getattr(getattr(self.transport, "decoder", None), "expander", None)
        compact = bool(getattr(self.transport, "compact", False)) and exp is not None
        pv[P_COMPACT] = 1.0 if compact else 0.0
        pv[P_CRATE] = exp.rate_hz if compact else 0.0
        last = exp.last if compact else None
        iv[I_CLAST] = -1 if last is None else last

    def _publish(self) -> None:
        """Copy the compiled state back into the loop and its result (Python's view)."""
        fst = self._fast
        iv, fv = fst["iv"], fst["fv"]
        res = self.result
        self.tel.n = int(iv[I_N])
        self._ramp = int(iv[I_RAMP])
        self._restart_flag = int(iv[I_RESTART])
        self._applied_seen = bool(iv[I_FAPPLIED])
        self._last_seq = int(iv[I_LAST_SEQ])
        res.late += int(iv[I_LATE])
        res.clamped += int(iv[I_CLAMPED])
        res.passivity_samples += int(iv[I_PSAMPLES])
        res.missed += int(iv[I_MISSED])
        res.skipped += int(iv[I_SKIPPED])
        iv[I_LATE] = iv[I_CLAMPED] = iv[I_PSAMPLES] = iv[I_MISSED] = iv[I_SKIPPED] = 0
        self._skip_flag = int(iv[I_SKIPFLAG])
        self._energy = float(fv[F_ENERGY])
        res.energy_max = float(fv[F_EMAX])
        res.energy_excess_max = float(fv[F_XMAX])
        res.v_max = float(fv[F_VMAX])
        res.f_max = float(fv[F_FMAX])
        n = int(iv[I_SAMPLES])
        self.engine.sample += n - fst["samples_seen"]
        fst["samples_seen"] = n

    def _frames_to_decoder(self) -> None:
        """The good frames the compiled code took go into the decoder's counters and its
        history of last frames (for the diagnostics of a later bad frame or loss)."""
        fst = self._fast
        iv = fst["iv"]
        dec = self.transport.decoder
        total = int(iv[I_HIST])
        new = total - fst["hist_seen"]
        if new <= 0:
            return
        dec.stats.frames_ok += new
        states = int(iv[I_FRAMES_OK])       # of which STATEs (the others: VELOCITY)
        self.compiled_samples += states - fst["states_seen"]
        fst["states_seen"] = states
        hist, hl = fst["hist"], fst["hist_len"]
        for j in range(max(total - min(new, _HIST), 0), total):
            h = j % _HIST
            dec.last_frames.append((bytes(hist[h, :hl[h]]), "ok"))
        fst["hist_seen"] = total

    # ---------------------------------------------------------------- per sample
    def _one(self, msg, x: float, t_rx: int) -> int:
        """A sample Python's source yielded, through the compiled body."""
        fst = self._fast
        kind, kargs, xs, fs, port, rec, out = fst["eng"]
        io = fst["io"]
        fst["iv"][I_SKIPFLAG] = self._skip_flag
        return _sample(kind, kargs, xs, fs, port, rec, out, fst["iv"], fst["fv"], fst["pv"],
                       fst["fh"], fst["win"], *fst["tel"], msg.seq, msg.time_us, msg.status,
                       msg.force_seq, float(x), t_rx, io[0], *io[1:])

    def _device_clocked_stretch(self, n_max: int) -> None:
        if self.poll is not None:   # a per-sample Python hook (live changes): Python's loop
            self.compiled = False
        if not self.compiled:
            return super()._device_clocked_stretch(n_max)
        states = self._device_states(n_max)
        self._fast = None
        first = None
        try:
            first = next(states, None)
            if first is None:
                return
            self._setup(first[1])
            self._fast["iv"][I_NMAX] = n_max
            for msg, x, t_rx in _chain1(first, states):
                if t_rx < 0:                # skipped (backlog): the scene steps only
                    self._fast["iv"][I_SKIPFLAG] = self._skip_flag
                    kind, kargs, xs, fs, port, rec, out = self._fast["eng"]
                    _skip_step(kind, kargs, xs, port, rec, out, self._fast["iv"],
                               self._fast["fv"], float(x))
                    self._publish()
                    continue
                code = self._one(msg, x, t_rx)
                self._publish()
                if self._finish(code, msg.seq):
                    break
        except DeviceError as exc:        # a read or write failed: the port is gone
            raise LostDevice(f"port failed: {str(exc).splitlines()[0]}", True) from None
        finally:
            if self._fast is not None:
                self._publish()
            self._fast = None
            self.result.energy = self._energy

    def _finish(self, code: int, seq: int) -> bool:
        """Act on a sample's code as :meth:`HostLoop._drive` does; True: the stretch ends."""
        res = self.result
        if code == R_OK:
            return False
        if code == R_NONFINITE:
            self._non_finite_stop(seq)
            self._fast["iv"][I_LAST_SEQ] = seq      # the zero FORCE answered it
            return True
        if code == R_IOERR:
            raise LostDevice("port failed: write failed", True)
        fv, pv, iv = self._fast["fv"], self._fast["pv"], self._fast["iv"]
        res.stop_reason = safety_reason(int(iv[I_WSUM]), self.config.clamp_max,
                                         self._fast["win"].size, self.force_limit,
                                         float(fv[F_X]), self.config.position_bound,
                                         float(fv[F_V]), self.config.velocity_limit,
                                         float(fv[F_EXCESS]), self.config.energy_limit,
                                         self._e0)
        res.safety_stop = True
        self.stop.set = True
        return True

    def _receive_hook(self):
        """``receive(timeout)`` for :meth:`HostLoop._device_states`: once the stretch is
        armed, the compiled code answers every clean STATE first and only what it leaves
        (or nothing) comes back to the reference code."""
        tr = self.transport
        base = tr.receive
        if not self.compiled:
            return base
        dec = tr.decoder

        def receive(timeout: float):
            fst = self._fast
            if fst is None or self._fresh or dec.overflow:
                return base(timeout)
            iv, fv = fst["iv"], fst["fv"]
            rb = fst["rb"]
            pre = dec.take_partial()        # a partial frame the decoder holds: ours now
            if pre:
                n0 = int(iv[I_RB_LEN])
                rb[n0:n0 + len(pre)] = np.frombuffer(pre, dtype=np.uint8)
                iv[I_RB_LEN] = n0 + len(pre)
            kind, kargs, xs, fs, port, rec, out = fst["eng"]
            exp = dec.expander
            while True:
                iv[I_SKIPFLAG] = self._skip_flag
                iv[I_EXPECT] = self._expect
                fv[F_LAST_RX] = self._last_rx
                self._compact_params(fst["pv"], iv)     # the decoder's expansion, ours now
                code = _stretch(kind, kargs, xs, fs, port, rec, out, iv, fv, fst["pv"],
                                fst["fh"], fst["win"], *fst["tel"], fst["io"][0], rb,
                                self.stop.shared, *fst["io"][1:], fst["hist"],
                                fst["hist_len"])
                self._expect = int(iv[I_EXPECT])
                self._last_rx = float(fv[F_LAST_RX])
                if exp is not None and fst["pv"][P_COMPACT] != 0.0:
                    last = int(iv[I_CLAST])       # the STATE_COMPACTs taken moved it
                    exp.last = None if last < 0 else last
                self._publish()
                self._frames_to_decoder()
                if code in (R_SYNC, R_INTR):
                    continue                # Python runs signal handlers; writer sees n
                if code in (R_HANDOFF, R_PORT):
                    n = int(iv[I_RB_LEN])
                    rest = bytes(rb[:n])
                    iv[I_RB_LEN] = 0
                    msgs = dec.feed(rest)
                    if code == R_PORT and not msgs:
                        return base(timeout)    # pyserial reports the error (or reads)
                    return msgs
                if code in (R_DONE, R_STOP, R_IDLE):
                    return []
                self._finish(code, int(iv[I_NF_SEQ]))
                return []

        return receive


def _chain1(first, rest):
    yield first
    yield from rest


_REC = np.zeros(0, dtype=np.int64)
_OUT = np.zeros((0, 0), dtype=np.float64)


def _scratch(engine, fd: int) -> dict:
    """The compiled stretch's arrays for a throw-away run on ``fd`` (1 kHz, delay 1, no
    bounds, silence 0): :func:`warm_up` and the tests."""
    iv = np.zeros(N_IV, dtype=np.int64)
    fv = np.zeros(N_FV)
    pv = np.zeros(N_PV)
    pv[P_LIM] = 1.0
    pv[P_D] = 1
    pv[P_RATE] = 1000.0
    pv[P_T] = 1e-3
    pv[P_POS] = pv[P_VLIM] = pv[P_ELIM] = math.inf
    pv[P_RAMP_N] = 1
    pv[P_HL] = 4
    pv[P_SILENCE] = pv[P_POLL] = 0.0
    iv[I_NMAX] = 4
    iv[I_SYNC] = 4
    iv[I_EXPECT] = 0
    tel = tuple(np.zeros(4, dtype=dt) for dt in (np.float64, np.float64, np.float64,
                                                  np.int64, np.float64, np.int8, np.uint8,
                                                  np.int64, np.uint16))
    u8 = np.zeros(8, dtype=np.uint8)
    io = (fd, np.zeros(64, dtype=np.uint8), u8.view(np.float64), u8, _CRC,
          np.zeros(32, dtype=np.uint8), np.zeros(2, dtype=np.int32), np.zeros(2, dtype=np.int64),
          u8.view(np.float32))
    eng = (*kernel_pack(engine), *_port_arrays(engine, at_least=0), _REC, _OUT)
    return {"eng": eng, "iv": iv, "fv": fv, "pv": pv, "fh": np.zeros(3),
            "win": np.zeros(4, dtype=np.int8), "tel": tel, "io": io,
            "stop": np.zeros(1, dtype=np.int64), "rb": np.zeros(256, dtype=np.uint8),
            "hist": np.zeros((_HIST, _MAX_FRAME), dtype=np.uint8),
            "hist_len": np.zeros(_HIST, dtype=np.int64)}


def _run_stretch(sc: dict) -> int:
    """:func:`_stretch` on the arrays of :func:`_scratch`; its return code."""
    io = sc["io"]
    return _stretch(*sc["eng"], sc["iv"], sc["fv"], sc["pv"], sc["fh"], sc["win"], *sc["tel"],
                    io[0], sc["rb"], sc["stop"], *io[1:], sc["hist"], sc["hist_len"])


def warm_up(engine) -> float:
    """Compile (or load from numba's cache) the compiled loop for this engine's kernel,
    on a pipe, before the real-time loop; returns the seconds it took.

    Parameters
    ----------
    engine : hapsim.engine.Engine
        A throw-away engine of the scene (it is stepped).

    Returns
    -------
    float
        Wall time [s].
    """
    import os
    t0 = time.perf_counter()
    r, w = os.pipe()
    try:
        sc = _scratch(engine, w)
        frame = np.frombuffer(fp.encode(fp.State(0, 0, fp.STATUS_ARMED, 0, (0.0,))),
                              dtype=np.uint8)
        sc["rb"][:frame.size] = frame
        sc["iv"][I_RB_LEN] = frame.size
        _run_stretch(sc)
        iv, fv, pv, io = sc["iv"], sc["fv"], sc["pv"], sc["io"]
        _sample(*sc["eng"], iv, fv, pv, sc["fh"], sc["win"], *sc["tel"], 1, 0,
                fp.STATUS_ARMED, 0, 0.0, 0, w, *io[1:])
        kind, kargs, xs, _, port, rec, out = sc["eng"]
        _skip_step(kind, kargs, xs, port, rec, out, iv, fv, 0.0)
    finally:
        os.close(r)
        os.close(w)
    _mark_compiled(len(kind) - 1)
    return time.perf_counter() - t0


def _mark_compiled(kind: int) -> None:
    """Leave the stamp that says the loop for kernel ``kind`` is in numba's cache
    (:func:`hapsim.pipeline.startup.loop_is_fresh` reads it without numba); best effort."""
    import os

    from hapsim.kernels.sources import loop_stamp
    if not CACHE_OK:        # compiled without the cache: nothing for a later start to load
        return
    path = loop_stamp(_KERNEL_NAMES[kind])
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w"):
            pass
    except OSError:
        pass
