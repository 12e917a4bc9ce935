"""The device-clocked host loop compiled with numba: the hot path owns the port's fd.

:class:`CompiledHostLoop` is a :class:`~hapsim.host.loop.HostLoop` whose device-clocked
stretch runs in one numba ``nogil`` function,
:func:`~hapsim.host.fastloop_kernels.answer_stretch`, for as many samples as it can: wait
for input (``poll``), ``read``, COBS + CRC decode, the port step (the engine's numba
kernel), the safety checks (clamp, non-finite, bounds, passivity observer and controller,
energy), FORCE encode, ``write``, one telemetry row into the preallocated arrays. libc is
called from nopython code by symbol (numba ``ExternalFunction``); pyserial still opens and
configures the port.

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

The per-sample body exists once, :func:`~hapsim.host.fastloop_kernels.answer_sample`, used
by the compiled stretch and by the samples Python hands over; it is the numba transcription
of :meth:`HostLoop._drive`'s body, operation by operation, so forces and telemetry are
bit-identical to the Python loop on the same device stream
(``tests/test_compiled_loop.py``). Backlog (``LoopConfig.backlog``): with ``"newest"`` a
clean STATE followed in the buffer by a newer one is skipped (counted, flagged on the next row), as the Python loop does within a read;
the scene steps with it and the step goes into the telemetry's skipped STATEs' record (the
row it precedes, its position: :mod:`hapsim.host.telemetry`), the same entries as the
Python loop's.

The numba code itself, the layout of the arrays it shares with Python and the packing of
the engine's kernel for it are :mod:`hapsim.host.fastloop_kernels` (numba keys its disk
cache on that file, which holds the digest of what it compiles in); this module drives it.
"""

from __future__ import annotations

import math
import time

import numpy as np

import firmware_protocol as fp
from hapsim.errors import DeviceError
from hapsim.host.fastloop_kernels import (
    CACHE_OK, F_E0, F_EMAX, F_ENERGY, F_EXCESS, F_FMAX, F_GWORST, F_HELD, F_LAST_RX, F_V,
    F_VMAX, F_X, F_XMAX, F_XPREV, I_CLAMPED, I_CLAST, I_EXPECT, I_FAPPLIED, I_FRAMES_OK,
    I_GPREV, I_HIST,
    I_LAST_SEQ, I_LATE, I_MISSED, I_N, I_NF_SEQ, I_NMAX, I_PSAMPLES, I_RAMP, I_RB_LEN,
    I_RESTART, I_SAMPLES, I_SKIPFLAG, I_SKIPN, I_SKIPPED, I_SYNC, I_WSUM, KERNEL_NAMES, N_FV,
    N_IV, N_PV, P_AHEAD, P_BMAX, P_CLAMP_MAX, P_COMPACT, P_CRATE, P_D, P_ELIM, P_GK, P_GN,
    P_GREST, P_GSTEP, P_GTAB, P_HL, P_LIM, P_NEWEST, P_PC, P_POLL, P_POS, P_RAMP_N, P_RATE,
    P_RL, P_SILENCE, P_T, P_VLIM, R_DONE, R_HANDOFF, R_IDLE, R_INTR, R_IOERR, R_NONFINITE,
    R_OK, R_PORT, R_STOP, R_SYNC, answer_sample, answer_stretch, kernel_pack, port_arrays,
    skip_sample)
from hapsim.host.loop import HostLoop, LostDevice, safety_reason
from hapsim.kernels.compiled_io import CRC_TABLE as _CRC
from hapsim.kernels.compiled_io import force_compact_frame as _force_compact_frame
from hapsim.kernels.compiled_io import force_frame as _force_frame
from hapsim.kernels.ticks import sent_ring_size

__all__ = ["CompiledHostLoop", "compiled_available", "encode_force", "warm_up"]

_MAX_FRAME = fp.MAX_FRAME
_RB_SIZE = 1 << 16
#: The compiled stretch returns to Python at least this often [s of samples] to publish
#: ``Telemetry.n`` (the journal writer drains up to there).
SYNC_SECONDS = 0.02
_HIST = 16


def compiled_available(transport) -> bool:
    """Whether the compiled loop can own this transport's port (a pyserial port with a
    file descriptor: hardware, or the mock's pty).

    Parameters
    ----------
    transport : object
        A host transport (:class:`hapsim.host.transport.Transport`).

    Returns
    -------
    bool
        Whether its ``serial_port`` has an int ``fd``.
    """
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
        iv[I_SKIPN] = tel.skip_n
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
        iv[I_GPREV] = -1            # the lateness guard starts again with the stretch
        fv[F_HELD + 1] = -1.0       # and the observer's force held names none (held_force)
        guard = cfg.late_growth
        if guard is not None:
            table = guard.array()
            pv[P_GSTEP] = guard.step
            pv[P_GN] = table.shape[1] - 1
            pv[P_GK] = table.shape[0]
            pv[P_GREST] = float(cfg.brake_rest)
            pv[P_GTAB:P_GTAB + table.size] = table.ravel()
        self._compact_params(pv, iv)
        u8 = np.zeros(8, dtype=np.uint8)
        fd = self.transport.serial_port.fd if self.compiled else -1
        self._fast = {
            "iv": iv, "fv": fv, "pv": pv,
            "fh": _sent_ring(cfg, d),
            "win": np.zeros(max(cfg.clamp_window, 1), dtype=np.int8),
            "eng": (*kernel_pack(eng), *port_arrays(eng), _REC, _OUT),
            "tel": (tel.time, tel.position, tel.force, tel.seq, tel.turnaround_us, tel.late,
                    tel.flags, tel.force_seq, tel.status),
            "io": (fd, np.zeros(64, dtype=np.uint8), u8.view(np.float64), u8, _CRC,
                   np.zeros(32, dtype=np.uint8), np.zeros(2, dtype=np.int32),
                   np.zeros(2, dtype=np.int64), u8.view(np.float32)),
            "rb": np.zeros(_RB_SIZE, dtype=np.uint8),
            "hist": np.zeros((_HIST, _MAX_FRAME), dtype=np.uint8),
            "hist_len": np.zeros(_HIST, dtype=np.int64),
            "skips": (tel.skip_row, tel.skip_x, tel.skip_meta),
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
        self.tel.skip_n = int(iv[I_SKIPN])
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
        return answer_sample(kind, kargs, xs, fs, port, rec, out, fst["iv"], fst["fv"], fst["pv"],
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
                    skip_sample(kind, kargs, xs, port, rec, out, self._fast["iv"],
                                self._fast["fv"], self._fast["pv"], self._fast["fh"],
                                float(x), *self._fast["skips"], msg.seq, msg.force_seq,
                                msg.status, msg.time_us)
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
        fv, iv = self._fast["fv"], self._fast["iv"]
        res.stop_reason = safety_reason(int(iv[I_WSUM]), self.config.clamp_max,
                                         self._fast["win"].size, self.force_limit,
                                         float(fv[F_X]), self.config.position_bound,
                                         float(fv[F_V]), self.config.velocity_limit,
                                         float(fv[F_EXCESS]), self.config.energy_limit,
                                         self._e0, float(fv[F_GWORST]),
                                         self.config.late_growth, 1.0 / self.config.rate_hz)
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
                code = answer_stretch(kind, kargs, xs, fs, port, rec, out, iv, fv, fst["pv"],
                                fst["fh"], fst["win"], *fst["tel"], fst["io"][0], rb,
                                self.stop.shared, *fst["io"][1:], fst["hist"],
                                fst["hist_len"], *fst["skips"])
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
    eng = (*kernel_pack(engine), *port_arrays(engine, at_least=0), _REC, _OUT)
    return {"eng": eng, "iv": iv, "fv": fv, "pv": pv, "fh": _sent_ring(None, 1),
            "win": np.zeros(4, dtype=np.int8), "tel": tel, "io": io,
            "stop": np.zeros(1, dtype=np.int64), "rb": np.zeros(256, dtype=np.uint8),
            "hist": np.zeros((_HIST, _MAX_FRAME), dtype=np.uint8),
            "hist_len": np.zeros(_HIST, dtype=np.int64),
            "skips": (np.zeros(4, dtype=np.int64), np.zeros(4),
                      np.zeros((4, 4), dtype=np.int64))}


def _sent_ring(cfg, d: int) -> np.ndarray:
    """The ring of FORCEs sent, shape (2, R) (:func:`hapsim.kernels.ticks.held_force`):
    row 0 their seq, -1 while empty; R for ``cfg``'s watchdog and delay (None: the
    smallest, for the warm-up)."""
    n = sent_ring_size(cfg.watchdog_us, cfg.rate_hz, d) if cfg is not None else 64
    ring = np.zeros((2, n), dtype=np.float64)
    ring[0] = -1.0
    return ring


def _run_stretch(sc: dict) -> int:
    """:func:`answer_stretch` on the arrays of :func:`_scratch`; its return code."""
    io = sc["io"]
    return answer_stretch(*sc["eng"], sc["iv"], sc["fv"], sc["pv"], sc["fh"], sc["win"], *sc["tel"],
                    io[0], sc["rb"], sc["stop"], *io[1:], sc["hist"], sc["hist_len"],
                    *sc["skips"])


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
        answer_sample(*sc["eng"], iv, fv, pv, sc["fh"], sc["win"], *sc["tel"], 1, 0,
                fp.STATUS_ARMED, 0, 0.0, 0, w, *io[1:])
        kind, kargs, xs, _, port, rec, out = sc["eng"]
        skip_sample(kind, kargs, xs, port, rec, out, iv, fv, pv, sc["fh"], 0.0, *sc["skips"],
                    2, 1, fp.STATUS_ARMED, 0)
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
    path = loop_stamp(KERNEL_NAMES[kind])
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w"):
            pass
    except OSError:
        pass
