"""Multi-rate kernel: the virtual network at the audio rate, the port at the device rate.

State layout as :mod:`hapsim.kernels.cordis` (``x``, ``xp``, ``f``, ``mobile``, ``t2m``,
``fixed`` and the link arrays), with ``t2m = Ta^2 / m`` and ``z = B / Ta`` at the audio
period ``Ta = T / N``. One device period is ``N`` audio sub-steps of the CORDIS-ANIMA
scheme (the same helpers, in the same order, as ``run_sd_contact``); within device period
``n`` the port position at sub-step ``j`` is

* ``hold``:   ``q[j] = p[n]``,
* ``linear``: ``q[j] = p[n-1] + (j + 1) / N (p[n] - p[n-1])`` (miPhysics smooths the haptic
  input up to the audio rate this way),

where ``p[n-1]`` is the port position the state holds on entry; the force sent to the
device is the mean of the N sub-step port forces (a boxcar decimator) or the last one.
The linear model of the same map is :func:`hapsim.analysis.virtual_network.multirate_blocks`.

Listening points write one audio frame per sub-step: ``gain * x[i]`` (position),
``gain * (x[i] - xp[i]) / Ta`` (velocity, after the sub-step's move) or ``gain * f[i]``
(the force computed in that sub-step).

No allocation, no Python objects: the kernel is called once per device sample by the
haptic loop (``n = 1``), per block by the JACK process callback and once for a whole
offline gesture.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from hapsim.kernels.cordis import (advance, chain_fused, chain_start, clear_forces, contacts,
                                   move_marked, spring_dampers)
from hapsim.kernels.sources import cache_ok

__all__ = ["run_periods", "run_frames", "ring_write", "ring_read", "LISTEN_CODES", "LIVE_STATE"]

#: Kernel code of each listened quantity (``hapsim.scene.LISTEN_QUANTITIES``).
LISTEN_CODES = {"position": 0, "velocity": 1, "force": 2}

#: The sources this module's numba code compiles in (:mod:`hapsim.kernels.sources`).
COMPILED_SOURCES = ("hapsim/kernels/cordis.py",)
#: Their SHA-256: numba keys its disk cache on this file alone, so this literal changes
#: with them (``tests/test_compiled_loop_sources.py`` says so); until then, no cache.
COMPILED_SOURCES_SHA256 = "83886cfafdc1e236acf79fddfdaddee29626f970e47bdd5b176e8b47f73bdc76"
#: Whether numba's disk cache may serve this module's compiled code.
CACHE_OK = cache_ok(COMPILED_SOURCES, COMPILED_SOURCES_SHA256)

_jit = nb.njit(cache=CACHE_OK, nogil=True, boundscheck=False)
_jit_inline = nb.njit(cache=CACHE_OK, nogil=True, boundscheck=False, inline="always")


@_jit_inline
def _substep(chain, x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z,
             c_i1, c_i2, c_k, c_z, c_thr, l_idx, l_code, l_gain, inv_ta, audio, row):
    """One audio sub-step (the port already placed) and its listened frame ``audio[row]``."""
    if chain >= 0:
        chain_fused(x, xp, f, t2m, fixed, chain, sd_k, sd_z, c_i1, c_i2)
        contacts(x, xp, f, c_i1, c_i2, c_k, c_z, c_thr)
        move_marked(x, xp, f, t2m, fixed, chain, sd_k.size, c_i1, c_i2)
    else:
        clear_forces(f)
        spring_dampers(x, xp, f, sd_i1, sd_i2, sd_k, sd_z)
        contacts(x, xp, f, c_i1, c_i2, c_k, c_z, c_thr)
        advance(x, xp, f, mobile, t2m, fixed)
    for c in range(l_idx.size):
        k = l_idx[c]
        code = l_code[c]
        if code == 0:
            v = x[k]
        elif code == 1:
            v = (x[k] - xp[k]) * inv_ta
        else:
            v = f[k]
        audio[row, c] = l_gain[c] * v


@_jit
def run_periods(n, nsub, linear, last, port, pos, x, xp, f, mobile, t2m, fixed,
                sd_i1, sd_i2, sd_k, sd_z, c_i1, c_i2, c_k, c_z, c_thr,
                l_idx, l_code, l_gain, inv_ta, audio, arow0, force, rec, out, row0):
    """Advance ``n`` device periods of ``nsub`` audio sub-steps each.

    Parameters
    ----------
    n : int
        Device periods to advance, >= 0.
    nsub : int
        Audio sub-steps per device period N, >= 1.
    linear : bool
        Port position up to the audio rate by linear interpolation (else held).
    last : bool
        Port force down to the device rate: last sub-step's (else the mean).
    port : int
        Index of the port (-1 without one: ``pos`` is ignored).
    pos : ndarray, shape (>= n,)
        Port position of each device period [m].
    x, xp, f, mobile, t2m, fixed
        Engine state at the audio period (:mod:`hapsim.kernels.cordis`), in place.
    sd_i1, sd_i2, sd_k, sd_z : ndarray, shape (n_sd,)
        Spring-damper arrays (may be empty).
    c_i1, c_i2, c_k, c_z, c_thr : ndarray, shape (n_c,)
        Contact arrays (may be empty).
    l_idx, l_code : ndarray of int64, shape (C,)
        Listened mass and quantity code (:data:`LISTEN_CODES`) of each channel.
    l_gain : ndarray, shape (C,)
        Gain of each channel.
    inv_ta : float
        1 / Ta [1/s].
    audio : ndarray, shape (>= arow0 + n * nsub, C)
        Audio frames out; frame ``arow0 + i * nsub + j`` is sub-step j of period i.
    arow0 : int
        First frame of ``audio`` to write.
    force : ndarray, shape (>= n,)
        Port force of each period out [N] (0 without a port).
    rec : ndarray of int64, shape (R,)
        Masses to record once per device period (may be empty).
    out : ndarray, shape (>= row0 + n, R)
        Recorded positions; row ``row0 + i`` after period i.
    row0 : int
        First row of ``out`` to write.
    """
    chain = chain_start(x, mobile, fixed, sd_i1, sd_i2)
    inv_n = 1.0 / nsub
    for i in range(n):
        p1 = pos[i] if port >= 0 else 0.0
        p0 = x[port] if port >= 0 else 0.0
        acc = 0.0
        fl = 0.0
        for j in range(nsub):
            if port >= 0:
                if linear:
                    x[port] = p0 + (j + 1) * inv_n * (p1 - p0)
                else:
                    x[port] = p1
            _substep(chain, x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z,
                     c_i1, c_i2, c_k, c_z, c_thr, l_idx, l_code, l_gain, inv_ta, audio,
                     arow0 + i * nsub + j)
            if port >= 0:
                fl = f[port]
                acc += fl
        force[i] = fl if last else acc * inv_n
        for r in range(rec.size):
            out[row0 + i, r] = x[rec[r]]


#: Slots of the live state array ``st`` of :func:`run_frames` (int64 counters kept as
#: float64 whole numbers, exact below 2^53): sub-step phase j, positions read, frames
#: starved (silence: no position for the next device period yet; counted once the first
#: has arrived), forces written, the period's start and end port positions, the force
#: accumulator, the gain.
LIVE_STATE = {"phase": 0, "read": 1, "starved": 2, "written": 3, "p0": 4, "p1": 5,
              "acc": 6, "gain": 7, "gain_target": 8, "gain_step": 9}


@_jit
def run_frames(nframes, nsub, linear, last, port, ring, wr, st, fring,
               x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z,
               c_i1, c_i2, c_k, c_z, c_thr, l_idx, l_code, l_gain, inv_ta, audio):
    """Advance ``nframes`` audio sub-steps for a live sound server (the JACK callback).

    The same sub-step as :func:`run_periods`; the device period boundaries fall wherever
    they fall in the block (``st`` carries the phase across calls). At the start of each
    device period the next port position is taken from the ring the haptic thread fills
    (``ring[read % R]`` while ``read < wr[0]``); when none has arrived the model does not
    advance: the frame is silence and, once the first position has arrived, counted as
    starved (``st[2]``), and the period starts at the first frame that finds its position.
    Period n therefore always runs on the haptic thread's n-th position, whatever the block
    size and the threads' timing: the coupling is a pure delay, which the analysis models
    (:class:`hapsim.audio.live.LiveSound`). At the end of each period the port force (mean or last) is
    written to ``fring[written % R]`` for the haptic thread. A master gain ramps linearly
    toward its target (no click on a gain change).

    Parameters
    ----------
    nframes : int
        Frames to compute (the server's block size).
    nsub, linear, last, port
        As :func:`run_periods`.
    ring : ndarray, shape (R,)
        Port positions from the haptic thread [m].
    wr : ndarray of int64, shape (1,)
        Positions written so far (the haptic thread increments it after writing).
    st : ndarray, shape (10,)
        Live state (:data:`LIVE_STATE`), in place.
    fring : ndarray, shape (R,)
        Port forces to the haptic thread [N].
    x ... inv_ta
        As :func:`run_periods`.
    audio : ndarray, shape (>= nframes, C)
        Frames out (float32 or float64).
    """
    chain = chain_start(x, mobile, fixed, sd_i1, sd_i2)
    R = ring.size
    inv_n = 1.0 / nsub
    for r in range(nframes):
        j = int(st[0])
        if j == 0:
            if port >= 0:
                rd = int(st[1])
                if rd >= wr[0]:
                    # no position for this period yet: the model waits (silence out), so
                    # period n always runs on p[n] and the loop stays the analysed one
                    for c in range(l_idx.size):
                        audio[r, c] = 0.0
                    if rd > 0:
                        st[2] += 1
                    continue
                st[4] = x[port]
                st[5] = ring[rd % R]
                st[1] = rd + 1
            st[6] = 0.0
        if port >= 0:
            if linear:
                x[port] = st[4] + (j + 1) * inv_n * (st[5] - st[4])
            else:
                x[port] = st[5]
        _substep(chain, x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z,
                 c_i1, c_i2, c_k, c_z, c_thr, l_idx, l_code, l_gain, inv_ta, audio, r)
        g = st[7]
        if g != st[8]:
            g += st[9]
            if (st[9] > 0 and g > st[8]) or (st[9] < 0 and g < st[8]):
                g = st[8]
            st[7] = g
        for c in range(l_idx.size):
            audio[r, c] *= g
        if port >= 0:
            st[6] += f[port]
        j += 1
        if j == nsub:
            j = 0
            w = int(st[3])
            fring[w % R] = (f[port] if last else st[6] * inv_n) if port >= 0 else 0.0
            st[3] = w + 1
        st[0] = j


@_jit
def ring_write(frames, ring, wr):
    """Append ``frames`` (shape (F, C)) to the frame ring (shape (R, C)); ``wr[0]`` counts
    frames written (the producer publishes after copying).

    Parameters
    ----------
    frames : ndarray, shape (F, C)
        The frames to append (F may be 0).
    ring : ndarray of float32, shape (R, C)
        The ring, written at ``(wr[0] + i) % R``.
    wr : ndarray of int64, shape (1,)
        Frames written so far, advanced by F.
    """
    R = ring.shape[0]
    w = wr[0]
    for i in range(frames.shape[0]):
        for c in range(frames.shape[1]):
            ring[(w + i) % R, c] = frames[i, c]
    wr[0] = w + frames.shape[0]


@_jit
def ring_read(nframes, ring, wr, st, out):
    """Copy the next ``nframes`` frames of the ring into ``out`` for the sound server.

    ``st[0]`` frames read, ``st[1]`` frames missing (the ring was empty: silence written,
    counted), ``st[2]`` frames skipped (the writer was more than half a ring ahead: the
    reader jumps to a quarter ring behind it, so that clock drift between the device and
    the sound card never grows the latency).

    Parameters
    ----------
    nframes : int
        Frames to copy, at most ``out.shape[0]``.
    ring : ndarray of float32, shape (R, C)
        The ring.
    wr : ndarray of int64, shape (1,)
        Frames written (read only).
    st : ndarray of int64, shape (3,)
        Read, missing and skipped counts, updated in place.
    out : ndarray of float32, shape (>= nframes, C)
        Receives the frames (0.0 where the ring ran empty).
    """
    R = ring.shape[0]
    rd = st[0]
    w = wr[0]
    if w - rd > R // 2:
        st[2] += w - R // 4 - rd
        rd = w - R // 4
    for i in range(nframes):
        if rd < w:
            for c in range(out.shape[1]):
                out[i, c] = ring[rd % R, c]
            rd += 1
        else:
            for c in range(out.shape[1]):
                out[i, c] = 0.0
            st[1] += 1
    st[0] = rd
