"""The real-time mock's tick compiled with numba, so that the test rig keeps up above 2 kHz.

:class:`CompiledMock` runs the armed, real-time part of :func:`hapsim.emulated.serve.serve_fd`
in one numba ``nogil`` function, :func:`_stretch`, for as many ticks as it can: sleep until
the tick's absolute deadline (``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)``: no
spinning, also under ``SCHED_FIFO``), take the host's bytes (``poll`` 0 ms + ``read``),
act on each clean FORCE frame (COBS + CRC decode, the delay line), then the tick: the force
due (late, watchdog, clamp), the STATE frame encoded and written, the physics advanced one
period. libc is called by symbol, and the COBS / CRC / clock helpers are those of the
compiled host loop (:mod:`hapsim.host.fastloop`).

It returns to Python, which then does exactly what the reference mock does, for: a frame
that is not a clean, finite FORCE (CONFIG, PING, STOP, HELLO_REQUEST, a bad or non-finite
frame: the bytes from that frame on go to the Python receiver), the port's hang-up or an
error (the Python path reads it and sees EIO / EOF), a signal (its handler runs) and the
stop flag.

The per-message and per-tick bodies are transcriptions of :class:`MockDevice`'s
``_on_force`` (real-time branch), ``_apply_due``, ``_emit`` and :class:`MockPhysics`'s
``sample`` / ``advance``, operation by operation, so the device stream is byte-identical to
the Python mock's for the same host bytes at the same device times
(``tests/test_fastmock.py``). One difference in timing, not in arithmetic: the Python mock
wakes on each host frame and stamps it (watchdog) on arrival, the compiled one reads what
arrived when it wakes for the tick and stamps it with the tick's time.

Not compiled (the Python mock serves; :func:`hapsim.emulated.serve.compiled_reason` says why): lockstep (paced by
the FORCEs, not by a clock), a fault plan (the faults are Python), VELOCITY frames enabled
by the host (a velocity-sensor correction), sensor noise (numpy's
generator), a compliant hand grip (4-state plant), a subclass of the mock (tests), and the
per-tick ``trace`` / ``applied_log`` of the tests.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import types

import firmware_protocol as fp
from hapsim.kernels.compiled_io import (CRC_TABLE, POLLERR, POLLHUP, POLLIN, POLLNVAL, c_poll,
                                       c_read, c_write, cobs_decode, cobs_encode, crc16, le,
                                       next_frame, now_ns)
from hapsim.kernels.sources import MOCK_SOURCES, source_paths, sources_digest

#: The sources this module's numba code compiles in (:mod:`hapsim.kernels.sources`).
COMPILED_SOURCES = MOCK_SOURCES

#: SHA-256 of the modules this module's numba code compiles in
#: (:data:`hapsim.kernels.sources.MOCK_SOURCES`): numba keys its disk cache on this file
#: alone, so this constant changes with them (``tests/test_compiled_loop_sources.py`` says
#: so), which edits this file and makes numba recompile. Until then: no cache.
COMPILED_SOURCES_SHA256 = "72ecec7b635e1b2946cf16411ec06dda70379583221df8ea55c501fe0f13f5c9"

#: Whether numba's disk cache may serve this module's compiled code.
CACHE_OK = sources_digest(source_paths(MOCK_SOURCES)) == COMPILED_SOURCES_SHA256

#: The decorator of the compiled mock's functions: nopython, no GIL, cached on disk when
#: :data:`CACHE_OK`.
jit = numba.njit(nogil=True, cache=CACHE_OK)

__all__ = ["CompiledMock"]

_c_clock_nanosleep = types.ExternalFunction(
    "clock_nanosleep", types.int32(types.int32, types.int32, types.intp, types.intp))
_CLOCK_MONOTONIC = 1
_TIMER_ABSTIME = 1

# iv: int64 state shared by Python and the compiled code
(I_N, I_APPLIED_SEQ, I_STATUS_EXTRA, I_LAST_FORCE_US, I_TICKS, I_FORCES_RX, I_LATE,
 I_WATCHDOG, I_CLAMPED, I_OVERRUNS, I_STALE, I_DELAY, I_WATCHDOG_US, I_T0_NS, I_PERIOD_NS,
 I_DEADLINE_NS, I_FRAMES_OK, I_RB_LEN, I_HOLD, I_NFORCE, I_TICK_US) = range(21)
N_IV = 21
# fv: float64 state
(F_X, F_V, F_XPREV, F_APPLIED, F_U, F_LIMIT, F_A, F_CXV, F_CXU, F_CVU, F_CU, F_Q, F_COULOMB,
 F_PERIOD) = range(14)
N_FV = 14

HOLD_ZOH, HOLD_IDEAL = 0, 1
# return codes of _stretch / _feed
R_STOP, R_INTR, R_PORT, R_HANDOFF, R_FED = 1, 2, 3, 4, 5

_U32 = 0xFFFFFFFF
_FORCE_PACKET = 15          # type + 1-axis FORCE body + CRC [bytes]
_STATE_PACKET = 29
_MAX_FRAME = fp.MAX_FRAME
_RB_SIZE = 1 << 16
_ARMED_CONFIGURED = fp.STATUS_ARMED | fp.STATUS_CONFIGURED
_APPLIED = fp.STATUS_FORCE_APPLIED
_OVERRUN = fp.STATUS_OVERRUN
_WATCHDOG = fp.STATUS_WATCHDOG_TRIPPED
_CLAMPED = fp.STATUS_FORCE_CLAMPED


# ----------------------------------------------------------------------------- physics
@jit
def _round_half_even(v):
    """Python's ``round(v)`` of a float (ties to even), as a float."""
    r = math.floor(v)
    d = v - r
    if d > 0.5 or (d == 0.5 and r != 2.0 * math.floor(0.5 * r)):     # r odd
        r += 1.0
    return r


@jit
def _sample(fv):
    """:meth:`MockPhysics.sample` without noise: the position, quantised when asked."""
    y = fv[F_X]
    q = fv[F_Q]
    if q > 0:
        y = q * _round_half_even(y / q)
    return y


@jit
def _advance(iv, fv, hand, u):
    """:meth:`MockPhysics.advance` (rigid body: ZOH with Coulomb friction, or ideal)."""
    n = iv[I_N]
    f = u + (hand[n] if n < hand.size else 0.0)
    if iv[I_HOLD] == HOLD_ZOH:
        x = fv[F_X]
        v = fv[F_V]
        fc = 0.0
        c = fv[F_COULOMB]
        if c > 0:
            if v != 0.0:
                fc = -c if v > 0 else c
            elif abs(f) > c:
                fc = -c if f > 0 else c
            else:                         # stuck and the force cannot break it loose
                iv[I_N] = n + 1
                return
        ft = f + fc
        vn = fv[F_A] * v + fv[F_CVU] * ft
        xn = x + fv[F_CXV] * v + fv[F_CXU] * ft
        if c > 0 and v != 0.0 and vn * v < 0 and abs(f) <= c:
            vn = 0.0
        fv[F_X] = xn
        fv[F_V] = vn
    else:
        x = fv[F_X]
        xp = fv[F_XPREV]
        a = fv[F_A]
        xn = (1.0 + a) * x - a * xp + fv[F_CU] * f
        fv[F_XPREV] = x
        fv[F_X] = xn
        fv[F_V] = (xn - x) / fv[F_PERIOD]
    iv[I_N] = n + 1


# ----------------------------------------------------------------------------- device
@jit
def _on_force(iv, rf, rs, seq, f, now_us):
    """:meth:`MockDevice._on_force`, real-time branch, for a finite force."""
    d = iv[I_DELAY]
    lo = iv[I_N] - d
    ahead = (seq - lo) & _U32
    if ahead > d:
        iv[I_STALE] += 1
        return
    s = lo + ahead
    iv[I_FORCES_RX] += 1
    iv[I_LAST_FORCE_US] = now_us
    i = s % rf.size
    rf[i] = f
    rs[i] = s


@jit
def _apply_due(iv, fv, rf, rs, n, now_us):
    """:meth:`MockDevice._apply_due` (real time: the watchdog applies)."""
    due = n - iv[I_DELAY]
    applied = iv[I_STATUS_EXTRA] & _APPLIED
    extra = 0
    if due < 0:
        f = 0.0
        seq = 0
        applied = 0
    else:
        i = due % rf.size
        if rs[i] == due:
            f = rf[i]
            seq = due
            applied = _APPLIED
        else:
            iv[I_LATE] += 1
            extra |= _OVERRUN
            f = fv[F_APPLIED]
            seq = iv[I_APPLIED_SEQ]
    extra |= applied
    wd = iv[I_WATCHDOG_US]
    if wd > 0 and now_us - iv[I_LAST_FORCE_US] > wd:
        f = 0.0
        iv[I_WATCHDOG] += 1
        extra |= _WATCHDOG
    lim = fv[F_LIMIT]
    if f > lim or f < -lim:
        f = lim if f > 0 else -lim
        iv[I_CLAMPED] += 1
        extra |= _CLAMPED
    iv[I_STATUS_EXTRA] = extra
    fv[F_APPLIED] = f
    iv[I_APPLIED_SEQ] = seq
    fv[F_U] = f


@jit
def _tick(iv, fv, rf, rs, hand, now_us, pkt, f8, u8, table, tx):
    """:meth:`MockDevice.tick`: the force due, STATE encoded into ``tx`` (its length
    returned), the physics advanced one period."""
    n = iv[I_N]
    _apply_due(iv, fv, rf, rs, n, now_us)
    iv[I_TICKS] += 1
    status = _ARMED_CONFIGURED | iv[I_STATUS_EXTRA]
    seq = n & _U32
    fseq = iv[I_APPLIED_SEQ] & _U32
    pkt[0] = 0x10
    for j in range(4):
        pkt[1 + j] = (seq >> (8 * j)) & 0xFF
    for j in range(8):
        pkt[5 + j] = (now_us >> (8 * j)) & 0xFF
    pkt[13] = status & 0xFF
    pkt[14] = (status >> 8) & 0xFF
    for j in range(4):
        pkt[15 + j] = (fseq >> (8 * j)) & 0xFF
    f8[0] = _sample(fv)
    for j in range(8):
        pkt[19 + j] = u8[j]
    c = crc16(pkt, 27, table)
    pkt[27] = (c >> 8) & 0xFF
    pkt[28] = c & 0xFF
    _advance(iv, fv, hand, fv[F_U])
    iv[I_TICK_US] = now_us               # MockDevice._plant_us: the plant's last tick
    return cobs_encode(pkt, _STATE_PACKET, tx)


@jit
def _feed(iv, rf, rs, rb, now_us, pkt, f8, u8, table):
    """Act on the complete frames in ``rb[:iv[I_RB_LEN]]`` that are clean, finite FORCEs.

    Returns R_FED (all taken; a partial frame left at the front of ``rb``) or R_HANDOFF
    (``rb`` starts at the first frame that is not one, for the Python receiver)."""
    n_rb = iv[I_RB_LEN]
    a = np.int64(0)         # int64, not Literal[0]: no specialisation of the helpers
    code = R_FED
    while True:
        a, z = next_frame(rb, a, n_rb)
        if z < 0:
            if n_rb - a > _MAX_FRAME - 1:
                code = R_HANDOFF       # overlong: the Python receiver counts it
            break
        if z - a > _MAX_FRAME - 1:
            code = R_HANDOFF
            break
        m = cobs_decode(rb, a, z, pkt)
        if m != _FORCE_PACKET or pkt[0] != 0x11 or crc16(pkt, m, table) != 0:
            code = R_HANDOFF
            break
        seq = le(pkt, 1, 4)
        for j in range(8):
            u8[j] = pkt[5 + j]
        f = f8[0]
        if not math.isfinite(f):
            code = R_HANDOFF           # the Python mock faults and disarms
            break
        _on_force(iv, rf, rs, seq, f, now_us)
        iv[I_FRAMES_OK] += 1
        iv[I_NFORCE] += 1
        a = z + 1
    for j in range(a, n_rb):
        rb[j - a] = rb[j]
    iv[I_RB_LEN] = n_rb - a
    return code


@jit
def _stretch(fd, stop, iv, fv, rf, rs, hand, rb, pkt, f8, u8, table, tx, ts, pfd):
    """Serve real-time ticks on ``fd`` until something needs Python (module notes)."""
    t0 = iv[I_T0_NS]
    period = iv[I_PERIOD_NS]
    while True:
        if stop[0] != 0:
            return R_STOP
        dl = iv[I_DEADLINE_NS]
        ts[0] = dl // 1_000_000_000
        ts[1] = dl % 1_000_000_000
        if _c_clock_nanosleep(_CLOCK_MONOTONIC, _TIMER_ABSTIME, ts.ctypes.data, 0) != 0:
            return R_INTR              # a signal: Python runs its handler
        now = now_ns(ts)
        now_us = (now - t0) // 1000
        pfd[0] = fd
        pfd[1] = POLLIN
        r = c_poll(pfd.ctypes.data, 1, 0)
        if r > 0:
            rev = pfd[1] >> 16
            if rev & POLLIN:
                n_rb = iv[I_RB_LEN]
                got = c_read(fd, rb.ctypes.data + n_rb, rb.size - n_rb)
                if got <= 0:
                    return R_PORT      # EOF / EIO: the Python path reads it again
                iv[I_RB_LEN] = n_rb + got
                if _feed(iv, rf, rs, rb, now_us, pkt, f8, u8, table) == R_HANDOFF:
                    return R_HANDOFF   # the tick of this deadline is Python's
            elif rev & (POLLERR | POLLHUP | POLLNVAL):
                return R_PORT          # the host closed the port: Python reads the EIO
        if now - dl > period // 2:
            iv[I_OVERRUNS] += 1
        k = _tick(iv, fv, rf, rs, hand, now_us, pkt, f8, u8, table, tx)
        c_write(fd, tx.ctypes.data, k)     # non-blocking: a full buffer drops the frame
        nxt = dl + period
        late = now + period // 2
        iv[I_DEADLINE_NS] = nxt if nxt > late else late


class CompiledMock:
    """The compiled tick around a :class:`~hapsim.emulated.faults.FaultyDevice` without
    faults (module notes); the Python objects stay the reference state between stretches.

    Parameters
    ----------
    dev : FaultyDevice
        The device as :func:`~hapsim.emulated.serve.serve_fd` wraps it (its ``mock``, its
        receiver ``decoder``).
    """

    def __init__(self, dev) -> None:
        self.dev = dev
        self.iv = np.zeros(N_IV, dtype=np.int64)
        self.fv = np.zeros(N_FV, dtype=np.float64)
        self.rb = np.zeros(_RB_SIZE, dtype=np.uint8)
        u8 = np.zeros(8, dtype=np.uint8)
        self.io = (np.zeros(64, dtype=np.uint8), u8.view(np.float64), u8, CRC_TABLE,
                   np.zeros(64, dtype=np.uint8))
        self.ts = np.zeros(2, dtype=np.int64)
        self.pfd = np.zeros(2, dtype=np.int32)
        self.rf = self.rs = None
        self.hand = None
        #: Ticks the compiled code served (the others were Python's).
        self.ticks = 0
        self._plan = dev.plan

    R_HANDOFF, R_PORT = R_HANDOFF, R_PORT       # the codes serve_fd acts on

    # ---------------------------------------------------------------- state in and out
    def load(self) -> None:
        """Copy the Python mock's state into the arrays (the partial frame its receiver
        holds included)."""
        mock = self.dev.mock
        ph = mock.physics
        iv, fv = self.iv, self.fv
        iv[:] = 0
        iv[I_N] = ph.n
        iv[I_APPLIED_SEQ] = mock._applied_seq
        iv[I_STATUS_EXTRA] = mock._status_extra
        iv[I_LAST_FORCE_US] = mock._last_force_us
        iv[I_TICK_US] = mock._plant_us
        iv[I_DELAY] = mock.delay
        iv[I_WATCHDOG_US] = mock.watchdog_us
        iv[I_HOLD] = HOLD_ZOH if ph.hold == "zoh" else HOLD_IDEAL
        fv[F_X], fv[F_V], fv[F_XPREV] = ph.x, ph.v, ph.previous_position
        fv[F_APPLIED], fv[F_U], fv[F_LIMIT] = mock._applied, mock._u, mock.force_limit
        co = ph.step_coefficients
        fv[F_A] = co["a"]
        if ph.hold == "zoh":
            fv[F_CXV], fv[F_CXU], fv[F_CVU] = co["cxv"], co["cxu"], co["cvu"]
        else:
            fv[F_CU] = co["cu"]
        fv[F_Q], fv[F_COULOMB], fv[F_PERIOD] = ph.position_resolution, ph.coulomb, ph.period
        self.rf = np.array(mock._rf, dtype=np.float64)
        self.rs = np.array(mock._rs, dtype=np.int64)
        self.hand = np.ascontiguousarray(ph.hand, dtype=np.float64)
        dec = self.dev.decoder
        pre = dec.take_partial()
        if pre:
            self.rb[:len(pre)] = np.frombuffer(pre, dtype=np.uint8)
        iv[I_RB_LEN] = len(pre)

    def store(self) -> bytes:
        """Copy the arrays back into the Python mock; the bytes it has not taken.

        Returns
        -------
        bytes
            After a hand-off, the host's bytes from the first frame the compiled code left
            (for :meth:`FaultyDevice.feed`); else the partial frame, put back into the
            receiver, and ``b""``.
        """
        mock = self.dev.mock
        ph = mock.physics
        iv, fv = self.iv, self.fv
        ph.n = int(iv[I_N])
        ph.x, ph.v = float(fv[F_X]), float(fv[F_V])
        ph.previous_position = float(fv[F_XPREV])
        mock._applied_seq = int(iv[I_APPLIED_SEQ])
        mock._status_extra = int(iv[I_STATUS_EXTRA])
        mock._last_force_us = int(iv[I_LAST_FORCE_US])
        mock._plant_us = int(iv[I_TICK_US])
        mock._applied = mock.stats.last_applied = float(fv[F_APPLIED])
        mock._u = float(fv[F_U])
        mock.velocity_out = None            # no VELOCITY while compiled (hapsim.emulated.serve.compiled_reason)
        mock._rf = self.rf.tolist()
        mock._rs = self.rs.tolist()
        st = mock.stats
        st.ticks += int(iv[I_TICKS])
        self.ticks += int(iv[I_TICKS])
        st.forces_rx += int(iv[I_FORCES_RX])
        st.late += int(iv[I_LATE])
        st.watchdog_trips += int(iv[I_WATCHDOG])
        st.clamped += int(iv[I_CLAMPED])
        st.overruns += int(iv[I_OVERRUNS])
        st.stale += int(iv[I_STALE])
        if iv[I_NFORCE]:
            st.last_host_message = "Force"
        self.dev.decoder.stats.frames_ok += int(iv[I_FRAMES_OK])
        for k in (I_TICKS, I_FORCES_RX, I_LATE, I_WATCHDOG, I_CLAMPED, I_OVERRUNS, I_STALE,
                  I_NFORCE, I_FRAMES_OK):
            iv[k] = 0
        rest = bytes(self.rb[:int(iv[I_RB_LEN])])
        iv[I_RB_LEN] = 0
        if rest and rest.find(b"\x00") < 0 and len(rest) <= _MAX_FRAME - 1:
            self.dev.decoder.put_partial(rest)    # a partial frame: the receiver's again
            return b""
        return rest

    # ---------------------------------------------------------------- without I/O
    def feed(self, data: bytes, now_us: int) -> bytes:
        """The host's ``data`` at device time ``now_us`` [us], as :meth:`_stretch` takes it
        (between :meth:`load` and :meth:`store`).

        Returns
        -------
        bytes
            Empty, or from the first frame left to Python on (a hand-off): what
            :meth:`FaultyDevice.feed` must get next.
        """
        n0 = int(self.iv[I_RB_LEN])
        b = np.frombuffer(data, dtype=np.uint8)
        self.rb[n0:n0 + b.size] = b
        self.iv[I_RB_LEN] = n0 + b.size
        pkt, f8, u8, table, _ = self.io
        code = _feed(self.iv, self.rf, self.rs, self.rb, np.int64(now_us), pkt, f8, u8, table)
        if code == R_HANDOFF:
            n = int(self.iv[I_RB_LEN])
            self.iv[I_RB_LEN] = 0
            return bytes(self.rb[:n])
        return b""

    def tick(self, now_us: int) -> bytes:
        """One tick at device time ``now_us`` [us] (between :meth:`load` and :meth:`store`).

        Returns
        -------
        bytes
            The STATE frame (0x00-delimited), as :meth:`FaultyDevice.pop_due` gives it.
        """
        pkt, f8, u8, table, tx = self.io
        k = _tick(self.iv, self.fv, self.rf, self.rs, self.hand, np.int64(now_us), pkt, f8,
                  u8, table, tx)
        return bytes(tx[:k])

    # ---------------------------------------------------------------- with I/O
    def serve(self, fd: int, t0_ns: int, deadline_ns: int, period_ns: int, flag):
        """Run :func:`_stretch` on ``fd`` from the tick due at ``deadline_ns``.

        Parameters
        ----------
        fd : int
            The non-blocking port (pty master).
        t0_ns : int
            ``time.monotonic_ns`` of device time 0 [ns].
        deadline_ns : int
            The next tick's deadline [ns, time.monotonic_ns].
        period_ns : int
            Tick period [ns].
        flag : StopFlag
            Its ``shared`` array ends the stretch when set.

        Returns
        -------
        code : int
            ``R_STOP``, ``R_INTR``, ``R_PORT`` or ``R_HANDOFF``.
        deadline_ns : int
            The next tick's deadline.
        rest : bytes
            With ``R_HANDOFF``, the host's bytes for :meth:`FaultyDevice.feed`.
        """
        self.load()
        iv = self.iv
        iv[I_T0_NS] = t0_ns
        iv[I_PERIOD_NS] = period_ns
        iv[I_DEADLINE_NS] = deadline_ns
        pkt, f8, u8, table, tx = self.io
        try:
            code = _stretch(fd, flag.shared, iv, self.fv, self.rf, self.rs, self.hand,
                            self.rb, pkt, f8, u8, table, tx, self.ts, self.pfd)
        finally:
            deadline_ns = int(iv[I_DEADLINE_NS])
            rest = self.store()
        return code, deadline_ns, rest


