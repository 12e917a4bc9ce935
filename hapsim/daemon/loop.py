"""The host loop: handshake, fixed-rate device- or host-clocked loop, safety.

Hot path (CONVENTIONS §4): per sample it decodes the STATE, steps the engine (numba), clamps,
encodes and writes the FORCE and writes one telemetry row *by index* into preallocated
arrays (a head kept whole, then a ring that a writer thread drains to the journal: the data
leaves through a ring buffer, and a run can be open-ended). No logging, no file I/O, no
allocation beyond the protocol's message objects and byte strings (unavoidable in Python).
Counters (late, missed, clamped, overruns) are kept as integers and reported at the end.

Timing convention: STATE ``n`` (``x(nT)``) is answered by FORCE ``seq = n`` computed from
``x[n]`` and ``x[n-1]``; the device applies it over ``[(n+d)T, (n+d+1)T)``.

Safety (from the first version): host-side clamp at the force limit; a non-finite position
or force sends zero force and stops; a stop flag (set by SIGINT/SIGTERM handlers) ends the
loop; safety stops end it with zero force: force at the limit in at least ``clamp_max`` of the
last ``clamp_window`` samples, ``|x|`` beyond ``position_bound``, ``|v|`` beyond
``velocity_limit``, or the energy the virtual environment gave the hand beyond
``energy_limit``. Every end sends a zero FORCE then STOP.

Reliability (both loops): bad frames are dropped by the decoder and never acted on, and
each is recorded (CONVENTIONS §11: sample, time, what the decoder found, its bytes and the
frames before it; the last ``BAD_FRAME_RECORDS``): the loop compares the decoder's bad-frame
count after each read (five integer reads) and only when it changed copies the references
of the decoder's last frames, formatted at the end of the run;
a STATE older than the last one (duplicated, reordered) is ignored (``stale``), one with the
wrong number of axes too (``bad_axes``); silence for ``lost_timeout`` (default: the
watchdog period, so the host sends zero force and STOP when the device's own watchdog
zeroes it), a port error, an unarmed STATE after arming, or a HELLO after the first armed
STATE (the device reset: it says HELLO when it restarts) make the device *lost* at once:
zero FORCE and STOP are sent (best effort), then, when ``reconnect`` is on, the host re-opens
the port if it failed, asks for HELLO and sends CONFIG again, with exponential backoff, at
most ``reconnect_attempts`` times and ``reconnect_time`` seconds per loss; the scene restarts
from its initial state with the port at the device's position at rest, the force ramped up
over ``ramp_samples``. A recovery's CONFIG follows a STOP and the PONG of a PING sent
after it (:meth:`HostLoop._quiesce`; without that PONG, the first armed STATE after the
CONFIG must not report a FORCE applied, as the host sent none yet): the scene restarts at
the handle of the new session, never at a STATE the device sent before it took the CONFIG. The loop's state (:attr:`HostLoop.state`: ``idle``, ``handshake``,
``armed``, ``lost``, ``recovering``, ``stopped``) is kept and reported. Non-latched device
FAULTs (WATCHDOG, RX_ERRORS, OVERRUN, AXES_MISMATCH) are counted; latched ones end the
run. The host-clocked loop uses the same machinery (one driver,
:meth:`HostLoop._run_stretches`, runs either loop's stretch and recovers its losses;
:meth:`HostLoop._resume` restarts the scene) and the same per-sample work
(:meth:`HostLoop._drive`, fed by either clock's source of STATEs): it answers the latest
STATE at each host deadline, and silence longer than ``lost_timeout`` is a loss like in the
device-clocked loop. Without ``reconnect`` a loss raises :class:`DeviceError`.

Passivity observer (Hannaford & Ryu, "Time-domain passivity control of haptic interfaces",
IEEE Trans. Robot. Autom. 18(1), 2002): ``E(n) = sum_k f_held(k) (x(k+1) - x(k))`` [J], i.e.
``T sum f v`` with ``v`` the backward-difference velocity, where ``f_held(k)`` is the force
the device held over ``[kT, (k+1)T)`` (the FORCE answering STATE ``k - d``). Sign convention:
``E`` is the energy that flowed **out of the virtual environment into the hand** (work done
by the actuator on the hand); Hannaford & Ryu's ``E_obs`` (energy *into* the one-port) is
``-E``. A passive environment holding the energy ``E0`` when it starts can give at most
``E0`` (their condition ``E_obs(n) + E0 >= 0``), so the observer's baseline is ``E0``, the
scene's stored energy (:meth:`hapsim.engine.Engine.energy`) at each (re)start, with the port
at rest at the device's position; ``E`` restarts from 0 at each (re)start (a recovery
restarts the scene, whose stored energy is ``E0`` again). What the scene gave **beyond** it,
the *excess* ``E - E0``, is what the energy safety stop (``excess > energy_limit``) and the
optional passivity controller act on: the controller adds the damping
``alpha = (E - E0) / (T v^2)`` (their ``alpha = -(E_obs + E0) / (T v^2)``) while the excess
is positive, capped at ``max_damping``: ``f <- f - alpha v``. With d samples of delay the
damping acts d samples late; the observer still measures the work really done (the force
held, not the force sent). A sampled wall is not exactly passive (the hold and the delay
lag its spring, Colgate & Schenkel 1997): when its damping B does not cover that lag the
excess grows a little above 0 even though the loop is stable, and the controller acts.
"""

from __future__ import annotations

import gc
import math
import time
from collections import deque
from dataclasses import dataclass, field
from itertools import chain

import numpy as np

import firmware_protocol as fp
from hapsim.daemon.realtime import sleep_until_ns
from hapsim.daemon.telemetry import (FLAG_CLAMPED, FLAG_ESTIMATED, FLAG_LOST, FLAG_RAMP,
                                     FLAG_SKIPPED)
from hapsim.errors import ConfigError, DeviceError, ProtocolError

__all__ = ["LoopConfig", "LoopResult", "StopFlag", "HostLoop", "MeasuredVelocity",
           "percentiles_us", "LATCHED_FAULTS", "BAD_FRAME_RECORDS", "SENSORS_TRIES",
           "SENSORS_WAIT"]

_U32 = 0xFFFFFFFF
_OPEN_ENDED = 1 << 62       # rows of a run without a sample count (ended by a stop)
_HALF = 0x80000000

#: Missing samples in a row a driver's loop steps the scene through with an extrapolated
#: position (beyond, ticks are skipped): :meth:`HostLoop._host_states`.
ESTIMATED_MAX = 2

#: Bad-frame incidents kept in :attr:`LoopResult.bad_frames` (the latest ones).
BAD_FRAME_RECORDS = 32
#: Frames received before a bad one that its record shows (at most).
BAD_FRAME_CONTEXT = 8

#: SENSORS_REQUEST attempts before a device is taken to offer no sensor (it was written
#: before the message and drops it, PROTOCOL.md §4), and the wait after each [s].
SENSORS_TRIES = 3
SENSORS_WAIT = 0.1

#: Before every CONFIG the host sends STOP then a PING and waits for its PONG, at most this
#: many times, this long each [s] (:meth:`HostLoop._quiesce`); then it arms anyway.
QUIESCE_TRIES = 3
QUIESCE_WAIT = 0.1
#: Nonce of the quiescing PINGs (+ the try): apart from the round-trip PINGs' 0..15.
QUIESCE_NONCE = 0x51E7_0000

#: Fault codes that latch on the device (PROTOCOL.md §4): they end the run.
LATCHED_FAULTS = frozenset((fp.FAULT_BAD_CONFIG, fp.FAULT_SENSOR, fp.FAULT_AMPLIFIER,
                            fp.FAULT_NON_FINITE_FORCE, fp.FAULT_VERSION_MISMATCH))


class _Lost(Exception):
    """Internal: the device is lost (silence, port error, reset); carries the reason."""

    def __init__(self, reason: str, port_error: bool = False) -> None:
        super().__init__(reason)
        self.port_error = port_error


class MeasuredVelocity:
    """The device's measured velocity over the wire (VELOCITY frames, PROTOCOL.md §4).

    The loop keeps the last VELOCITY received (:meth:`put`) and, for each STATE it
    answers, :meth:`take` makes :attr:`value` that STATE's velocity: the VELOCITY with the
    same ``seq`` (the device sends it just before the STATE), or, when it was lost, the
    last value held (counted in :attr:`missing`). An engine that uses the measured velocity
    (:func:`hapsim.daemon.correction.corrected_engine`) calls the object.

    Attributes
    ----------
    value : float
        Velocity of the STATE being answered [m/s] (0.0 before any).
    frames : int
        VELOCITY messages received with one axis.
    missing : int
        STATEs taken without their VELOCITY (the last value held).
    """

    __slots__ = ("value", "frames", "missing", "_seq", "_v")

    def __init__(self) -> None:
        self.value = 0.0
        self.frames = 0
        self.missing = 0
        self._seq = -1
        self._v = 0.0

    def __call__(self) -> float:
        """The measured velocity of the STATE being answered [m/s]."""
        return self.value

    def put(self, msg) -> None:
        """Keep a VELOCITY message (one axis; others are ignored).

        Parameters
        ----------
        msg : firmware_protocol.Velocity
        """
        if len(msg.velocity) == 1:
            self.frames += 1
            self._seq = msg.seq
            self._v = msg.velocity[0]

    def take(self, seq: int) -> None:
        """A STATE with ``seq`` is answered next: its velocity becomes :attr:`value`.

        Parameters
        ----------
        seq : int
            The STATE's ``seq``.
        """
        if self._seq == seq:
            self.value = self._v
        else:
            self.missing += 1

    def as_dict(self) -> dict:
        """``frames`` and ``missing`` as a dict (the run's report)."""
        return {"frames": self.frames, "missing": self.missing}


class StopFlag:
    """A flag a signal handler sets to end the loop cleanly (zero force, STOP, flush).

    Attributes
    ----------
    set : bool
        True once a stop was requested (stored in :attr:`shared`).
    signal : int or None
        Number of the signal that set it, if any.
    shared : ndarray of int64, shape (1,)
        The flag itself (1: stop requested), read by the compiled loop
        (:mod:`hapsim.daemon.fastloop`) while it runs without the GIL.
    """

    def __init__(self) -> None:
        self.shared = np.zeros(1, dtype=np.int64)
        self.signal = None

    @property
    def set(self) -> bool:
        """True once a stop was requested."""
        return bool(self.shared[0])

    @set.setter
    def set(self, value: bool) -> None:
        self.shared[0] = 1 if value else 0

    def request(self, signum: int | None = None) -> None:
        """Request a stop (safe to call from a signal handler: two attribute stores).

        Parameters
        ----------
        signum : int, optional
            Number of the signal that asked (``signal.SIGINT``, ``signal.SIGTERM``); the
            loop reports ``"signal NAME"`` as the stop reason. None: another caller.
        """
        self.set = True
        self.signal = signum


@dataclass
class LoopConfig:
    """Parameters of one host-loop run.

    Parameters
    ----------
    rate_hz : float
        Loop rate [Hz] sent in CONFIG.
    n_samples : int
        Samples to run; 0: open-ended (until a stop: signal, safety, device). A telemetry
        buffer without a ring (:class:`~hapsim.daemon.telemetry.Telemetry`) also caps it.
    delay : int
        Expected device delay d [samples] (for the late count from ``force_seq``).
    force_limit : float
        Host-side clamp and CONFIG.force_limit [N]; ``inf``: the device's HELLO limit.
    lockstep : bool
        The device is a lockstep mock: generous timeouts, no real-time expectations.
    host_clocked : bool
        Use the host's monotonic clock (sleep, then spin to each deadline) instead of
        answering each STATE: at each deadline the latest STATE is answered. With a
        lockstep device the host's clock paces the device (exact THS in real time); with
        a real-time device two clocks run side by side (host ticks a third of a period
        after the device's; ticks without a new STATE are skipped and counted as missed).
    watchdog_us : int
        CONFIG.watchdog_us [us].
    state_timeout : float
        Longest wait for a STATE before :class:`DeviceError` [s].
    hello_timeout : float
        Longest wait for HELLO [s].
    clamp_window, clamp_max : int
        Safety stop when the force was clamped in ``clamp_max`` of the last
        ``clamp_window`` samples.
    position_bound : float
        Safety stop when ``|x|`` exceeds it [m].
    velocity_limit : float
        Safety stop when the backward-difference velocity ``|v|`` exceeds it [m/s].
    energy_limit : float
        Safety stop when the energy the scene gave the hand beyond what it stored at its
        (re)start, ``E - E0``, exceeds it [J] (module notes).
    passivity_controller : bool
        Add the adaptive damping of Hannaford & Ryu while ``E - E0 > 0``.
    max_damping : float
        Cap of that damping [N s/m].
    reconnect : bool
        Recover a lost device (re-open, HELLO, CONFIG) instead of raising
        :class:`DeviceError` (device- and host-clocked loops).
    lost_timeout : float or None
        Silence after which the device is lost [s]; None: the watchdog period
        ``watchdog_us``. After that long without a FORCE the device zeroes its force by
        itself (PROTOCOL §5.2); the host sends zero force and STOP at the same moment, so
        both sides agree the device is stopped, and starts recovering. A shorter timeout
        would turn a delay spike that the device rides through (holding its force) into a
        loss; a longer one only leaves the host believing it drives a device that has
        already stopped. Without ``reconnect`` the silence allowed is ``state_timeout``;
        the first STATE after a CONFIG may take up to ``state_timeout`` (a device
        restarting).
    reconnect_attempts : int
        Most HELLO + CONFIG attempts per loss.
    reconnect_time : float
        Most time spent recovering one loss [s].
    backoff : float
        First wait between attempts [s]; doubled each time up to ``backoff_max``.
    backoff_max : float
        Longest wait between attempts [s].
    attempt_timeout : float
        Wait for HELLO per attempt [s].
    ramp_samples : int
        After a recovery the force is scaled by ``k / ramp_samples`` for its first samples.
    backlog : {"newest", "all"}
        Device-clocked: when more than one STATE is waiting (a burst after a stall), answer
        only the newest and count the others as ``skipped`` (``"newest"``, the default: the
        device holds a fresh force at once instead of a queue of stale ones), or answer
        every one in order (``"all"``). A STATE counts as newer when it is armed, has one
        axis and is ahead by 1 .. ``silence * rate + 2`` samples.
    """

    rate_hz: float
    n_samples: int
    delay: int = 1
    force_limit: float = math.inf
    lockstep: bool = False
    host_clocked: bool = False
    watchdog_us: int = 50_000
    state_timeout: float = 1.0
    hello_timeout: float = 3.0
    clamp_window: int = 100
    clamp_max: int = 50
    position_bound: float = math.inf
    velocity_limit: float = math.inf
    energy_limit: float = math.inf
    passivity_controller: bool = False
    max_damping: float = 50.0
    reconnect: bool = False
    lost_timeout: float | None = None
    reconnect_attempts: int = 8
    reconnect_time: float = 10.0
    backoff: float = 0.05
    backoff_max: float = 1.0
    attempt_timeout: float = 0.25
    ramp_samples: int = 50
    backlog: str = "newest"


@dataclass
class LoopResult:
    """What a host-loop run did.

    Attributes
    ----------
    samples : int
        Samples answered (telemetry rows).
    stop_reason : str
        ``"duration"``, ``"signal SIGTERM"``/``"signal SIGINT"``, ``"safety: ..."`` or
        ``"device: ..."``.
    safety_stop : bool
        True when a safety rule ended the run.
    late : int
        Ticks the device reported holding an older force (``seq - force_seq != d`` or
        STATUS_OVERRUN).
    missed : int
        STATE sequence numbers never seen (gaps); host-clocked: host ticks without a new
        STATE (skipped: no engine step, no FORCE; or, with a driver, ``estimated``).
    estimated : int
        Host-clocked with a driver: missed ticks the scene was stepped through with an
        extrapolated position (their rows have ``FLAG_ESTIMATED``).
    overruns : int
        Host-clocked deadlines missed by more than one period.
    clamped : int
        Samples whose force the host clamped.
    skipped : int
        STATEs not answered because a newer one was waiting (backlog policy ``newest``);
        the row answered after them has :data:`~hapsim.daemon.telemetry.FLAG_SKIPPED`.
    turnaround_us : dict
        ``p50``, ``p99``, ``p999``, ``max`` of STATE-read to FORCE-written [us].
    hello : Hello or None
        The device's HELLO.
    faults : list of str
        FAULT names received.
    decoder : dict
        Stream decoder counters (serial transports).
    bad_frames : list of dict
        The last :data:`BAD_FRAME_RECORDS` bad frames the decoder dropped, oldest first:
        ``sample`` (rows logged before it), ``t`` [s since arming, when the loop read it],
        ``kind`` (the decoder counter it fed: ``bad_crc``, ``bad_cobs``, ``overlong``,
        ``unknown_type``, ``malformed``), ``hex`` (its COBS bytes), ``before`` (the frames
        received before it, at most :data:`BAD_FRAME_CONTEXT`, ``"outcome: hex"``, oldest
        first), ``outcome`` (``"dropped"``,
        or ``"dropped; then lost: REASON"`` when the device was lost before another sample).
        ``kind`` is ``"unrecorded"`` for frames that left the decoder's history before the
        loop read it (more than its 16 frames in one read).
    bad_frames_seen : int
        Bad frames counted while the loop ran (all of them, recorded or not).
    ping_rtt_us : dict
        PING -> PONG round trip before arming [us]: ``p50``, ``p99``, ``p999``, ``max``,
        ``answered``, ``sent``.
    stale : int
        STATEs older than the last one used (duplicated or reordered): ignored.
    bad_axes : int
        STATEs with another number of axes than HELLO's: ignored.
    implausible : int
        STATEs whose seq is further ahead of the last one used than the time since then
        allows (more than ``(elapsed + lost_timeout) rate + 2``): forged, or corrupted
        beyond what the CRC catches; ignored (accepting one would make every real STATE
        after it look stale).
    unarmed : int
        STATEs without STATUS_ARMED (before the first armed one after CONFIG): ignored.
    earlier_session : int
        Armed STATEs that arrived after a recovery's CONFIG not preceded by a confirmed
        quiescence (``quiesced`` False), before the first one the loop resumed at, with
        STATUS_FORCE_APPLIED set: that bit names a FORCE applied since the last CONFIG
        (PROTOCOL.md §4), and the host had sent none since this one, so they were sent
        before the device took it (an earlier session's handle): ignored.
    quiesced : bool
        The device answered the PING sent after the STOP that preceded the last recovery's
        CONFIG (:meth:`HostLoop._quiesce`); False: no recovery, or it re-armed without
        that barrier.
    hello_mid_run : int
        HELLO messages received after the handshake: before the first armed STATE after a
        CONFIG they answer HELLO requests and are ignored; after it, the device reset and
        is lost at once.
    device_faults : dict of str to int
        Non-latched FAULTs received, by name (the run goes on).
    lost : int
        Times the device was lost (silence, port error, reset).
    recovered : int
        Times it came back (re-handshake and a first armed STATE).
    reconnect_attempts : int
        HELLO + CONFIG attempts made in all.
    events : list of dict
        ``{"event": "lost"|"lost again"|"attempt"|"recovered", "t": [s since arming],
        "sample", "state", ...}`` (off the hot path: only on faults); ``state`` is the
        loop's state once the event happened; ``recovered`` adds ``x``, the device
        position [m] the scene restarted at.
    state : str
        The loop's state when the run ended, before the final zero FORCE and STOP:
        ``armed`` (ran to its end or was stopped while driving the device), ``lost`` or
        ``recovering`` (stopped while recovering), ``handshake`` (stopped before the
        device answered).
    energy : float
        Energy the virtual environment gave the hand since its last (re)start, ``E``, at
        the end [J] (module notes).
    energy_max : float
        Largest ``E`` of any stretch [J].
    energy_stored : float
        The observer's baseline ``E0`` at the last (re)start: the scene's stored energy
        with the port at rest at the device's position [J].
    energy_excess_max : float
        Largest ``E - E0`` over the run, 0.0 when the scene never gave more than it
        stored [J]; what ``energy_limit`` and the passivity controller act on.
    passivity_samples : int
        Samples where the passivity controller added damping.
    v_max : float
        Largest ``|v|`` seen [m/s].
    f_max : float
        Largest ``|f|`` sent [N].
    velocity : dict
        The device's velocity sensor over the wire, when the loop asked for it
        (:class:`MeasuredVelocity`): ``frames`` VELOCITY received, ``missing`` STATEs
        answered without theirs (last value held); empty otherwise.
    """

    samples: int = 0
    stop_reason: str = "duration"
    safety_stop: bool = False
    late: int = 0
    missed: int = 0
    estimated: int = 0
    overruns: int = 0
    clamped: int = 0
    skipped: int = 0
    turnaround_us: dict = field(default_factory=dict)
    hello: object = None
    faults: list = field(default_factory=list)
    decoder: dict = field(default_factory=dict)
    bad_frames: list = field(default_factory=list)
    bad_frames_seen: int = 0
    ping_rtt_us: dict = field(default_factory=dict)
    stale: int = 0
    bad_axes: int = 0
    implausible: int = 0
    unarmed: int = 0
    earlier_session: int = 0
    quiesced: bool = False
    hello_mid_run: int = 0
    device_faults: dict = field(default_factory=dict)
    lost: int = 0
    recovered: int = 0
    reconnect_attempts: int = 0
    events: list = field(default_factory=list)
    state: str = "idle"
    energy: float = 0.0
    energy_max: float = 0.0
    energy_stored: float = 0.0
    energy_excess_max: float = 0.0
    passivity_samples: int = 0
    v_max: float = 0.0
    f_max: float = 0.0
    velocity: dict = field(default_factory=dict)


def percentiles_us(values: np.ndarray) -> dict:
    """Percentiles of a set of durations, for the loop report.

    Parameters
    ----------
    values : array_like of float, shape (n,)
        Durations [us] (turnaround, ping round trips); any order, n >= 0.

    Returns
    -------
    dict
        ``p50``, ``p99``, ``p999`` (``numpy.percentile`` with linear interpolation) and
        ``max`` [us], as floats; each None when ``values`` is empty.
    """
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"p50": None, "p99": None, "p999": None, "max": None}
    p = np.percentile(v, [50, 99, 99.9])
    return {"p50": float(p[0]), "p99": float(p[1]), "p999": float(p[2]), "max": float(v.max())}


class HostLoop:
    """The fixed-rate host loop between an engine and a device transport.

    Parameters
    ----------
    engine : hapsim.engine.Engine
        The scene (warmed up: its kernel already compiled/loaded).
    transport : object
        A transport of :mod:`hapsim.daemon.transport`. When it has ``clock()`` and
        ``sleep(s)`` (the virtual-clock :class:`~hapsim.daemon.transport.SimTransport`) the
        loop's timeouts use them; ``reopen()`` is used to recover a failed port.
    config : LoopConfig
        Run parameters.
    telemetry : Telemetry
        Preallocated buffer: its head rows, then its ring (the loop writes row ``i`` in
        slot ``i`` or ``head + (i - head) % ring``, then raises ``n``; a writer thread may
        drain it); without a ring, at most ``head`` samples are run.
    stop : StopFlag, optional
        Polled every sample.
    measured : MeasuredVelocity, optional
        Ask the device for its velocity sensor (SENSORS_REQUEST before CONFIG, refused with
        :class:`~hapsim.errors.ConfigError` when it offers none) and keep each STATE's
        VELOCITY there, for an engine that reads it.

    Attributes
    ----------
    state : str
        ``"idle"`` (not started), ``"handshake"`` (asking HELLO, sending CONFIG),
        ``"armed"`` (CONFIG sent: driving the device, or waiting for its first STATE),
        ``"lost"`` (silence, port error or reset seen: zero force and STOP sent),
        ``"recovering"`` (re-opening, HELLO, CONFIG with backoff), ``"stopped"`` (zero
        force and STOP sent at the end).
    """

    def __init__(self, engine, transport, config: LoopConfig, telemetry,
                 stop: StopFlag | None = None, measured: MeasuredVelocity | None = None):
        self.engine = engine
        self.measured = measured
        #: Called between two samples, before the engine steps (live changes: the
        #: mailbox of :class:`hapsim.audio.control.Controller`); None: nothing.
        self.poll = None
        #: Called once the device's HELLO is checked, before PING and CONFIG (``hapsim
        #: run``: waits for the numba warm-up that ran while the device started); None:
        #: nothing.
        self.before_arm = None
        #: :attr:`_clock` time of the first armed STATE (start-up figure); None before.
        self.first_state_at = None
        self.transport = transport
        self.config = config
        self.tel = telemetry
        self.stop = stop or StopFlag()
        self.result = LoopResult()
        self._last_seq = -1
        self._clock = getattr(transport, "clock", time.monotonic)
        self._sleep = getattr(transport, "sleep", time.sleep)
        self._fresh = True          # next armed STATE (re)starts the scene at rest
        self._ramp = 0              # samples left in the force ramp after a recovery
        self._restart_flag = 0      # FLAG_LOST for the first row after a recovery
        self._skip_flag = 0         # FLAG_SKIPPED for the next row (older STATEs skipped)
        self._expect = -1           # next STATE seq expected (device-clocked source)
        self._last_rx = 0.0         # clock time of the last STATE used [s]
        self._lost_since = None     # clock time of the current loss, None when healthy
        self._attempts = 0
        self._t0 = 0.0
        self._energy = 0.0          # passivity observer E since the last (re)start [J]
        self._e0 = 0.0              # its baseline: stored energy at that (re)start [J]
        self._applied_seen = False  # the device sets STATUS_FORCE_APPLIED (PROTOCOL.md §4)
        self._check_applied = False  # skip STATEs with FORCE_APPLIED until the scene resumes
        self.force_limit = math.inf
        self.state = "idle"
        dec = getattr(transport, "decoder", None)
        self._dstats = dec.stats if dec is not None else None
        self._nbad = _bad_count(self._dstats) if dec is not None else 0
        self._nbad0 = self._nbad
        self._bad_snaps: deque = deque(maxlen=BAD_FRAME_RECORDS)

    # ------------------------------------------------------------------ handshake
    def _ask_hello(self, timeout: float):
        """Send HELLO_REQUEST (every 0.5 s) until a HELLO arrives; None after ``timeout``."""
        tr = self.transport
        clock = self._clock
        end = clock() + timeout
        next_ask = -math.inf
        while True:
            if self.stop.set:
                return None
            now = clock()
            if now >= end:
                return None
            if now >= next_ask:
                tr.send(fp.HelloRequest(fp.PROTOCOL_VERSION))
                next_ask = now + 0.5
            for msg in tr.receive(min(0.05, max(end - now, 0.0))):
                if isinstance(msg, fp.Link):
                    self._link = msg  # the device sends it just before HELLO
                if isinstance(msg, fp.Hello):
                    return msg

    def _check_hello(self, hello) -> None:
        """Check a HELLO and set the force limit from it.

        Parameters
        ----------
        hello : firmware_protocol.Hello
            The device's HELLO.

        Raises
        ------
        ProtocolError
            The device speaks another protocol version, or has another number of axes
            than 1 (the message carries the last frames received, CONVENTIONS §11).
        ConfigError
            The device's LINK (sent with HELLO) shows that its serial line cannot carry a
            STATE and a FORCE frame per tick at the configured rate
            (:func:`firmware_protocol.link_max_rate`).
        """
        cfg = self.config
        if hello.protocol_version != fp.PROTOCOL_VERSION:
            raise ProtocolError(f"device speaks protocol {hello.protocol_version}, "
                                f"hapsim speaks {fp.PROTOCOL_VERSION} (port "
                                f"{self.transport.info.get('port')}); last frames:\n"
                                f"{self.transport.last_frames() or '(none received)'}")
        if hello.n_axes != 1:
            raise ProtocolError(f"device has {hello.n_axes} axes; hapsim run drives 1-DoF "
                                f"devices (port {self.transport.info.get('port')}); last "
                                f"frames:\n{self.transport.last_frames() or '(none received)'}")
        link = getattr(self, "_link", None)
        if link is not None:
            vel = self.measured is not None
            top = fp.link_max_rate(link.baud, link.bits_per_byte, hello.n_axes,
                                   velocity=vel)
            if cfg.rate_hz > top:
                up = fp.state_frame_bytes(hello.n_axes) + (
                    fp.velocity_frame_bytes(hello.n_axes) if vel else 0)
                raise ConfigError(
                    f"{cfg.rate_hz:g} Hz is more than the device's link carries: at "
                    f"{link.baud} baud ({link.bits_per_byte} bits per byte) a "
                    f"{up}-byte STATE{' + VELOCITY' if vel else ''} up and a "
                    f"{fp.force_frame_bytes(hello.n_axes)}-byte FORCE down per tick fit "
                    f"{top:.0f} Hz at most ({fp.LINK_LOAD:.0%} of the line); choose "
                    f"rate_hz <= {int(top)}", key="rate_hz")
        limit = cfg.force_limit if math.isfinite(cfg.force_limit) else hello.force_limit
        self.force_limit = min(float(limit), float(hello.force_limit))

    def _ask_sensors(self) -> None:
        """Enable the device's velocity sensor (SENSORS_REQUEST, PROTOCOL.md §4), when the
        loop has a :attr:`measured` velocity to fill; nothing otherwise.

        Raises
        ------
        ConfigError
            The device answers that it has no velocity sensor, or does not answer
            (written before SENSORS_REQUEST) within ``SENSORS_TRIES * SENSORS_WAIT``.
        """
        if self.measured is None:
            return
        tr = self.transport
        clock = self._clock
        answer = None
        for _ in range(SENSORS_TRIES):
            tr.send(fp.SensorsRequest(fp.SENSOR_VELOCITY))
            end = clock() + SENSORS_WAIT
            while answer is None and clock() < end and not self.stop.set:
                for msg in tr.receive(0.02):
                    if type(msg) is fp.Sensors:
                        answer = msg
            if answer is not None or self.stop.set:
                break
        if answer is not None and answer.enabled & fp.SENSOR_VELOCITY:
            self.result.velocity = self.measured.as_dict()
            return
        if self.stop.set:
            return
        why = (f"it answers SENSORS offered=0x{answer.offered:04X}" if answer is not None
               else f"no SENSORS answer to {SENSORS_TRIES} requests: a device written "
                    f"before the velocity message")
        where = tr.info.get("port") or tr.info.get("kind", "the transport")
        raise ConfigError(f"velocity_sensor: the device on {where} does not offer a "
                          f"velocity sensor ({why}); choose "
                          f"another correction, or a device that measures its velocity",
                          key="device.correction.kind")

    def _quiesce(self) -> bool:
        """Disarm the device and read everything it sent before: STOP, then PING, until
        its PONG (PROTOCOL.md §4: STOP disarms; a device answers PING in order).

        A device keeps ticking armed STATEs of the session it had (a port that vanished and
        came back, a host that died without STOP) until it takes the next CONFIG. Those
        STATEs carry the handle of that session, not the one the CONFIG (re)starts: a host
        that resumed the scene at one would start from the wrong position (the real-time
        mock restarts its plant at CONFIG; the state after a reconnect showed a handle
        0.105 m out, beyond the position bound). The byte stream is in order, so once the
        PONG of a PING sent after the STOP is read, every STATE sent before the STOP has
        been read too (and dropped here), and the device, disarmed, sends no armed STATE
        until CONFIG arms it: the first armed STATE after CONFIG is of the new session. An
        armed STATE within two periods after the PONG shows that the STOP was lost on the
        way (a lossy link): STOP and PING again.

        Returns
        -------
        bool
            True when the PONG came (:attr:`LoopResult.quiesced`); False after
            :data:`QUIESCE_TRIES` waits of :data:`QUIESCE_WAIT` without it (a lossy link or
            a device that does not answer PING: the loop then skips, before it resumes, a
            STATE that shows an earlier session, :attr:`LoopResult.earlier_session`), or on
            a stop.
        """
        tr = self.transport
        clock = self._clock
        settle = 2.0 / self.config.rate_hz
        for k in range(QUIESCE_TRIES):
            nonce = QUIESCE_NONCE + k
            tr.send(fp.Stop())
            tr.send(fp.Ping(nonce, 0))
            end = clock() + QUIESCE_WAIT
            pong = None
            armed = False
            while not armed and clock() < (end if pong is None else pong + settle):
                if self.stop.set:
                    return False
                for msg in tr.receive(0.02 if pong is None else settle):
                    if type(msg) is fp.Pong and msg.nonce == nonce:
                        pong = clock()
                    elif (pong is not None and type(msg) is fp.State
                          and msg.status & fp.STATUS_ARMED):
                        armed = True    # the STOP was lost on the way: send it again
            if pong is not None and not armed:
                return True
        return False

    def _send_config(self) -> None:
        cfg = self.config
        self.transport.receive(0.0)  # drop anything stale before arming
        self.transport.send(fp.Config(float(cfg.rate_hz), int(cfg.watchdog_us),
                                      float(self.force_limit)))
        self._fresh = True

    def handshake(self) -> fp.Hello:
        """Ask for HELLO, check it, send CONFIG (arms the device).

        Returns
        -------
        Hello or None
            None when the stop flag was set before the device answered.

        Raises
        ------
        DeviceError
            No HELLO within ``hello_timeout``.
        ProtocolError
            A protocol version mismatch, or not 1 axis.
        """
        cfg = self.config
        tr = self.transport
        self.state = "handshake"
        hello = self._ask_hello(cfg.hello_timeout)
        if hello is None:
            if self.stop.set:
                return None
            raise DeviceError(f"no HELLO from the device within {cfg.hello_timeout:g} s "
                              f"(port {tr.info.get('port')}); last frames:\n"
                              f"{tr.last_frames() or '(none received)'}")
        self._check_hello(hello)
        if self.before_arm is not None:
            self.before_arm()
            if self.stop.set:       # a signal during the warm-up: the device is not armed
                return None
        self._ask_sensors()
        self._measure_ping()
        self._send_config()
        self.state = "armed"
        self.result.hello = hello
        self._t0 = self._clock()
        return hello

    def _measure_ping(self, count: int = 16) -> None:
        """Round-trip PING -> PONG before arming [us] (transport + device answer time)."""
        tr = self.transport
        clock = self._clock
        rtts = []
        for nonce in range(count):
            t0 = time.perf_counter_ns()
            tr.send(fp.Ping(nonce, t0 // 1000))
            end = clock() + 0.2
            got = False
            while not got and clock() < end:
                for msg in tr.receive(0.02):
                    if isinstance(msg, fp.Pong) and msg.nonce == nonce:
                        got = True
            if got:
                rtts.append((time.perf_counter_ns() - t0) * 1e-3)
        self.result.ping_rtt_us = percentiles_us(np.array(rtts))
        self.result.ping_rtt_us["answered"] = len(rtts)
        self.result.ping_rtt_us["sent"] = count

    # ------------------------------------------------------------------ run
    def run(self) -> LoopResult:
        """Handshake, run the loop, then always send zero force and STOP.

        Returns
        -------
        LoopResult

        Raises
        ------
        DeviceError
            Device silent or lost beyond recovery, port failure, or no HELLO (zero force +
            STOP are still attempted).
        ProtocolError
            The device (at the handshake or when it came back after a loss) speaks another
            protocol version or has another number of axes than 1 (zero force + STOP are
            still attempted).
        """
        gc_was = gc.isenabled()
        gc.collect()             # before CONFIG arms the device: a real-time device ticks
        gc.disable()             # from then on; no collector pauses in the hot loop (§4)
        try:
            hello = self.handshake()
        except BaseException:
            if gc_was:
                gc.enable()
            raise
        try:
            if hello is None:
                pass
            elif self.config.host_clocked:
                self._run_stretches(self._host_clocked_stretch)
            else:
                self._run_stretches(self._device_clocked_stretch)
        finally:
            self.result.state = self.state
            self._shutdown()
            self.state = "stopped"
            if gc_was:
                gc.enable()
        return self.finish()

    def finish(self) -> LoopResult:
        """Fill the result from what was recorded: samples, turnaround, decoder counters.

        :meth:`run` ends with it; a caller that caught :meth:`run`'s DeviceError or
        ProtocolError calls it to report the run up to the loss.

        Returns
        -------
        LoopResult
            :attr:`result`, completed.
        """
        res = self.result
        if self.stop.set and res.stop_reason == "duration" and self.stop.signal is not None:
            res.stop_reason = f"signal {_signame(self.stop.signal)}"
        res.samples = self.tel.n
        if self.measured is not None and res.velocity:
            res.velocity = self.measured.as_dict()
        ta = self.tel.columns()["turnaround_us"]       # the rows still in memory
        res.turnaround_us = percentiles_us(ta)
        res.turnaround_us["samples"] = int(ta.size)
        dec = getattr(self.transport, "decoder", None)
        if dec is not None:
            res.decoder = dec.stats.as_dict()
            self._check_bad()
            res.bad_frames_seen = self._nbad - self._nbad0
            res.bad_frames = self._bad_frame_records()
        return res

    # ------------------------------------------------------------------ bad frames
    def _check_bad(self) -> None:
        """Snapshot the decoder's last frames if its bad-frame count changed (rare: only
        on a fault, so the copy is not paid per sample)."""
        ds = self._dstats
        if ds is None:
            return
        n = _bad_count(ds)
        if n != self._nbad:
            self._snap_bad(n)

    def _snap_bad(self, n: int) -> int:
        """Record that the bad-frame count is now ``n``: sample, time and the references of
        the decoder's last frames (formatted later by :meth:`_bad_frame_records`).

        Parameters
        ----------
        n : int
            The decoder's bad-frame count now.

        Returns
        -------
        int
            ``n``.
        """
        delta = n - self._nbad
        self._nbad = n
        self._bad_snaps.append((self.tel.n, self._clock() - self._t0, delta,
                                tuple(self.transport.decoder.last_frames)))
        return n

    def _bad_frame_records(self) -> list:
        """The recorded bad frames as dicts (see :attr:`LoopResult.bad_frames`)."""
        out = []
        lost = {}
        for ev in self.result.events:
            if ev["event"] in ("lost", "lost again"):
                lost.setdefault(ev["sample"], ev.get("reason", ""))
        for sample, t, delta, frames in self._bad_snaps:
            bad = [j for j, (_, oc) in enumerate(frames) if oc != "ok"][-delta:]
            outcome = "dropped" if sample not in lost else f"dropped; then lost: {lost[sample]}"
            for _ in range(delta - len(bad)):
                out.append({"sample": sample, "t": round(t, 6), "kind": "unrecorded",
                            "hex": "", "before": [], "outcome": outcome})
            for j in bad:
                raw, oc = frames[j]
                out.append({"sample": sample, "t": round(t, 6), "kind": oc,
                            "hex": raw.hex(" "),
                            "before": [f"{o}: {r.hex(' ')}"
                                       for r, o in frames[max(j - BAD_FRAME_CONTEXT, 0):j]],
                            "outcome": outcome})
        return out[-BAD_FRAME_RECORDS:]

    def _shutdown(self) -> None:
        tr = self.transport
        try:
            tr.send(fp.Force((self._last_seq + 1) & _U32, (0.0,)))
            tr.send(fp.Stop())
        except DeviceError:
            pass

    def _state_timeout(self) -> None:
        tr = self.transport
        raise DeviceError(f"no STATE from the device for {self.config.state_timeout:g} s "
                          f"(port {tr.info.get('port')}); last frames:\n"
                          f"{tr.last_frames() or '(none received)'}")

    # ------------------------------------------------------------------ recovery
    def _event(self, event: str, **kw) -> None:
        self.result.events.append({"event": event, "t": round(self._clock() - self._t0, 6),
                                   "sample": self.tel.n, "state": self.state, **kw})

    def _recover(self, lost: _Lost) -> bool:
        """Zero force and STOP, then re-open / HELLO / CONFIG with backoff.

        Returns
        -------
        bool
            True when CONFIG was sent again (the loop resumes at the next armed STATE);
            False when the stop flag was set meanwhile.

        Raises
        ------
        DeviceError
            ``reconnect`` is off, or the attempts / time allowed for this loss are used up.
        ProtocolError
            The device that answered is not one hapsim can drive (version, axes).
        """
        cfg = self.config
        tr = self.transport
        res = self.result
        clock = self._clock
        reason = str(lost)
        frames = tr.last_frames() or "(none received)"      # CONVENTIONS §11
        self._check_bad()
        self.state = "lost"
        if self._lost_since is None:
            self._lost_since = clock()
            self._attempts = 0
            res.lost += 1
            self._event("lost", reason=reason, last_frames=frames)
        else:
            self._event("lost again", reason=reason, last_frames=frames)
        try:                                   # the device's own watchdog zeroes it anyway
            tr.send(fp.Force((self._last_seq + 1) & _U32, (0.0,)))
            tr.send(fp.Stop())
        except DeviceError:
            lost.port_error = True
        if not cfg.reconnect:
            if "no STATE" in reason:
                self._state_timeout()
            raise DeviceError(f"{reason} (port {tr.info.get('port')}); last frames:\n"
                              f"{tr.last_frames() or '(none received)'}")
        port_error = lost.port_error
        delay = cfg.backoff
        last_err = reason
        while not self.stop.set:
            spent = clock() - self._lost_since
            if self._attempts >= cfg.reconnect_attempts or spent > cfg.reconnect_time:
                raise DeviceError(
                    f"device lost ({reason}); {self._attempts} reconnect attempts in "
                    f"{spent:.3g} s failed (last: {last_err}); port {tr.info.get('port')}; "
                    f"last frames:\n{tr.last_frames() or '(none received)'}")
            self._attempts += 1
            res.reconnect_attempts += 1
            self.state = "recovering"
            self._event("attempt", n=self._attempts)
            try:
                if port_error and hasattr(tr, "reopen"):
                    tr.reopen()
                    port_error = False
                hello = self._ask_hello(cfg.attempt_timeout)
                if hello is not None:
                    self._check_hello(hello)
                    self._ask_sensors()        # a reset device forgot the request
                    # the device may still tick armed STATEs of the lost session
                    res.quiesced = self._quiesce()
                    self._check_applied = not res.quiesced
                    self._send_config()
                    self.state = "armed"
                    return True
                last_err = f"no HELLO within {cfg.attempt_timeout:g} s"
            except DeviceError as exc:        # ProtocolError (not a DeviceError) ends it
                last_err = str(exc).split("\n")[0]
                port_error = True
            if self.stop.set:
                break
            self._sleep(delay)
            delay = min(2 * delay, cfg.backoff_max)
        return False

    # ------------------------------------------------------------------ shared
    def _run_stretches(self, stretch) -> None:
        """Run ``stretch(n_max)`` until the end; after each loss, recover and run it again.

        Both loops (device- and host-clocked) go through here: a stretch runs from the next
        armed STATE after a CONFIG until the end, a stop, or a loss (:class:`_Lost`); the loss
        is handled by :meth:`_recover` (zero FORCE, STOP, re-open, HELLO, CONFIG, backoff),
        and the next stretch restarts the scene through :meth:`_resume`.
        """
        res = self.result
        stop = self.stop
        n_max = self.config.n_samples if self.config.n_samples > 0 else _OPEN_ENDED
        if self.tel.max_rows is not None:
            n_max = min(n_max, self.tel.max_rows)
        self._energy = 0.0
        while self.tel.n < n_max and not stop.set:
            try:
                stretch(n_max)
            except _Lost as lost:
                if not self._recover(lost):
                    break
        if stop.set and res.stop_reason == "duration" and stop.signal is not None:
            res.stop_reason = f"signal {_signame(stop.signal)}"

    def _silence(self) -> float:
        """Silence after which the device is lost [s]: ``lost_timeout`` (default: the
        watchdog) when reconnecting, else ``state_timeout``."""
        cfg = self.config
        if cfg.reconnect:
            return cfg.lost_timeout if cfg.lost_timeout is not None else cfg.watchdog_us * 1e-6
        return cfg.state_timeout

    def _resume(self, x: float):
        """First armed STATE after a (re)CONFIG: restart the scene at rest at ``x`` [m].

        After a loss the engine is rebuilt from the scene (its initial state), the force
        ramp is armed and the recovery is recorded. The passivity observer restarts: ``E``
        from 0, its baseline ``E0`` the scene's stored energy now (module notes).

        Parameters
        ----------
        x : float
            Device position of the first armed STATE [m].

        Returns
        -------
        Engine
            The engine to step.
        """
        self._restart_flag = 0
        if self.first_state_at is None:
            self.first_state_at = self._clock()
        if self._lost_since is not None:
            self._restart_flag = FLAG_LOST          # telemetry: the scene restarts here
            self.engine = type(self.engine)(self.engine.scene)
            self._ramp = max(int(self.config.ramp_samples), 1)
            self.result.recovered += 1
            self._event("recovered", attempts=self._attempts,
                        after_s=round(self._clock() - self._lost_since, 6), x=x)
            self._lost_since = None
        self.engine.set_port_position(x, at_rest=True)
        # passivity observer: the scene (re)starts holding E0; E counts from 0 again
        self._e0 = _stored_energy(self.engine)
        self._energy = 0.0
        self.result.energy_stored = self._e0
        self._fresh = False
        self._check_applied = False
        return self.engine

    def _note_other(self, msg) -> bool:
        """A message other than STATE during the loop: count non-latched FAULTs and HELLOs.

        A latched FAULT ends the run (returns True, stop flag set). A HELLO after the first
        armed STATE since the last CONFIG means the device reset (it says HELLO when it
        restarts): the device is lost at once (:class:`_Lost`) rather than after
        ``lost_timeout`` of silence. Before that STATE a HELLO may answer one of the
        handshake's HELLO requests and is only counted.

        Raises
        ------
        _Lost
            On a HELLO after arming.
        """
        res = self.result
        tm = type(msg)
        if tm is fp.Fault:
            name = fp.FAULT_NAMES.get(msg.code, f"0x{msg.code:04X}")
            if msg.code in LATCHED_FAULTS:
                res.faults.append(name)
                res.stop_reason = f"device: FAULT {name} (detail {msg.detail})"
                self.stop.set = True
                return True
            res.device_faults[name] = res.device_faults.get(name, 0) + 1
        elif tm is fp.Velocity:
            if self.measured is not None:
                self.measured.put(msg)
        elif tm is fp.Hello:
            res.hello_mid_run += 1
            if not self._fresh:
                raise _Lost("device reset: HELLO after arming")
        return False

    # ------------------------------------------------------------------ per sample (both)
    def _non_finite_stop(self, seq: int) -> None:
        """Safety stop on a non-finite position or force: zero force for ``seq``, then stop."""
        self.transport.send(fp.Force(seq, (0.0,)))
        self._last_seq = seq
        self.result.stop_reason = "safety: non-finite position or force"
        self.result.safety_stop = True
        self.stop.set = True

    def _drive(self, n_max: int, states) -> None:
        """The hot loop of both clocks: answer each sample ``states`` yields, until it ends,
        a stop, or a loss.

        The per-sample work exists here only: late check, engine step (non-finite stop),
        passivity observer and controller, force ramp after a recovery, clamp, FORCE,
        clamp window, telemetry row (head + ring, drained at half laps), maxima, safety
        bounds. The clocks differ only in which STATE is answered when, and that is the
        source's business (:meth:`_device_states`, :meth:`_host_states`); the source is a
        generator, so this loop keeps its state in local variables (no attribute access
        per sample beyond what the two loops did before).

        Parameters
        ----------
        n_max : int
            Rows to reach (the sources stop there).
        states : generator
            Yields ``(msg, x, t_rx)`` per sample to answer: the STATE, its position [m]
            and ``perf_counter_ns()`` when it was read; ``t_rx = -1`` for a STATE the
            backlog policy skips (the engine steps with it, nothing is sent or logged). It (re)starts the scene
            (:meth:`_resume`) at its first usable STATE, before yielding anything; it ends
            at ``n_max`` rows, on a stop, and raises :class:`_Lost` on a loss.
        """
        cfg = self.config
        tel = self.tel
        stop = self.stop
        res = self.result
        lim = self.force_limit
        d = cfg.delay
        T = 1.0 / cfg.rate_hz
        rate = float(cfg.rate_hz)
        pos_bound = cfg.position_bound
        vlim = cfg.velocity_limit
        elim = cfg.energy_limit
        pc_on = bool(cfg.passivity_controller)
        bmax = float(cfg.max_damping)
        win = np.zeros(max(cfg.clamp_window, 1), dtype=np.int8)
        wlen = win.size
        wsum = 0
        clamp_max = cfg.clamp_max
        fh = [0.0] * (d + 2)                # forces sent, by local sample index
        fhl = len(fh)
        Force = fp.Force
        overrun_bit = fp.STATUS_OVERRUN
        applied_bit = fp.STATUS_FORCE_APPLIED
        flags_applied = self._applied_seen
        isfinite = math.isfinite
        perf = time.perf_counter_ns
        send = self.transport.send
        ramp_n = max(int(cfg.ramp_samples), 1)
        e_max = res.energy_max
        x_max = res.energy_excess_max
        v_max = res.v_max
        f_max = res.f_max
        first = None
        try:
            # the source (re)starts the scene (engine, observer baseline, restart flag)
            # at its first usable STATE, before its first yield: device-clocked, that
            # STATE is the one it yields; host-clocked, the latest STATE at its first
            # deadline. Read what the restart set only now.
            first = next(states, None)
            if first is None:
                return
            eng = self.engine
            restart = self._restart_flag
            energy = self._energy
            e0 = self._e0
            t_arr, x_arr, f_arr, s_arr, ta_arr, late_arr, fl_arr, fs_arr, st_arr = (
                tel.time, tel.position, tel.force, tel.seq, tel.turnaround_us, tel.late,
                tel.flags, tel.force_seq, tel.status)
            hl, rl = tel.head, tel.ring      # row i is in slot i, or hl + (i - hl) % rl
            # a loop that is not real-time lets the journal writer catch up each half lap
            drain = tel.drain if rl else None
            lap_a, lap_b = (hl, hl + rl // 2) if drain is not None else (-1, -1)
            # the scene restarts at rest at the first sample: dx = 0 there, for both clocks
            # (device-clocked: at the STATE it resumed at; host-clocked: at the latest
            # STATE at its first deadline, maybe newer than the one it resumed at)
            x_prev = first[1]
            poll = self.poll
            k = 0                           # samples since this stretch (re)started
            i = tel.n
            for msg, x, t_rx in chain((first,), states):
                if t_rx < 0:
                    # a skipped STATE (backlog policy): not answered, but the scene takes
                    # its position, so that the next velocity spans one period
                    if isfinite(x):
                        eng.port_step(x)
                        x_prev = x
                    continue
                seq = msg.seq
                lt = 0
                st = msg.status
                if st & applied_bit and not flags_applied:
                    flags_applied = self._applied_seen = True
                # with d = 0 (lockstep only) force_seq names the force of the previous
                # period (FORCE n is not known yet, mock notes), so it says nothing about
                # lateness: only STATUS_OVERRUN (the device held an older force) counts
                if seq >= d and (st & overrun_bit or _force_seq_late(
                        seq, msg.force_seq, st, d, flags_applied)):
                    if d > 0 or st & overrun_bit:
                        lt = 1
                        res.late += 1
                if poll is not None:
                    poll()
                f = eng.port_step(x) if isfinite(x) else math.nan
                if not isfinite(f):
                    self._non_finite_stop(seq)
                    break
                # passivity observer: work of the force held over the last period
                dx = x - x_prev
                x_prev = x
                v = dx * rate
                if k > d:                   # held over the last period: FORCE k - 1 - d
                    energy += fh[(k - 1 - d) % fhl] * dx
                excess = energy - e0
                if pc_on and excess > 0.0:
                    tvv = T * v * v
                    if tvv > 0.0:
                        # alpha = (E - E0) / (T v^2), capped (compared without dividing:
                        # no overflow for a tiny v)
                        alpha = excess / tvv if excess < bmax * tvv else bmax
                        f -= alpha * v
                        res.passivity_samples += 1
                rf = 0
                if self._ramp > 0:
                    f *= (ramp_n - self._ramp + 1) / ramp_n
                    self._ramp -= 1
                    rf = FLAG_RAMP
                c = 0
                if f > lim:
                    f = lim
                    c = 1
                elif f < -lim:
                    f = -lim
                    c = 1
                send(Force(seq, (f,)))
                t_tx = perf()
                self._last_seq = seq
                fh[k % fhl] = f
                k += 1
                j = i % wlen
                wsum += c - win[j]
                win[j] = c
                res.clamped += c
                sl = i if i < hl else hl + (i - hl) % rl
                t_arr[sl] = msg.time_us * 1e-6
                x_arr[sl] = x
                f_arr[sl] = f
                s_arr[sl] = seq
                ta_arr[sl] = (t_tx - t_rx) * 1e-3
                late_arr[sl] = lt
                fs_arr[sl] = msg.force_seq
                st_arr[sl] = st
                fl_arr[sl] = lt | rf | restart | (FLAG_CLAMPED if c else 0) | self._skip_flag
                self._skip_flag = 0
                restart = 0
                i += 1
                tel.n = i
                if sl == lap_a or sl == lap_b:
                    drain()
                if energy > e_max:
                    e_max = energy
                if excess > x_max:
                    x_max = excess
                av = v if v >= 0.0 else -v
                if av > v_max:
                    v_max = av
                af = f if f >= 0.0 else -f
                if af > f_max:
                    f_max = af
                if (wsum >= clamp_max or x > pos_bound or x < -pos_bound or av > vlim
                        or excess > elim):
                    res.stop_reason = _safety_reason(wsum, clamp_max, wlen, lim, x, pos_bound,
                                                     v, vlim, excess, elim, e0)
                    res.safety_stop = True
                    stop.set = True
                    break
        except DeviceError as exc:        # a read or write failed: the port is gone
            raise _Lost(f"port failed: {str(exc).splitlines()[0]}", True) from None
        finally:
            if first is not None:
                self._energy = energy
                res.energy_max = e_max
                res.energy_excess_max = x_max
                res.v_max = v_max
                res.f_max = f_max
            # without a sample, E is what the source left: 0 when it (re)started the scene
            res.energy = self._energy

    # ------------------------------------------------------------------ device-clocked
    def _device_clocked_stretch(self, n_max: int) -> None:
        """The hot loop, from the next armed STATE until the end, a stop, or a loss: each
        STATE is answered as it arrives (:meth:`_device_states`, :meth:`_drive`)."""
        self._drive(n_max, self._device_states(n_max))

    def _receive_hook(self):
        """The ``receive(timeout)`` the device-clocked source reads messages with: the
        transport's (a subclass may run samples before returning what is left,
        :mod:`hapsim.daemon.fastloop`)."""
        return self.transport.receive

    def _device_states(self, n_max: int):
        """The device-clocked source of :meth:`_drive`: every usable STATE, as it arrives.

        Drops stale, implausible, wrong-axes and (before the first armed one) unarmed
        STATEs, notes FAULTs and HELLOs, records bad frames, restarts the scene at the
        first armed STATE after a CONFIG, and raises :class:`_Lost` on silence (no usable
        STATE for :meth:`_silence`; ``state_timeout`` for the first after a CONFIG) or a
        disarmed STATE after arming.

        Yields
        ------
        (State, float, int)
            The STATE, its position [m] (NaN for a non-finite first one), and
            ``perf_counter_ns()`` when its frame was read.
        """
        cfg = self.config
        tel = self.tel
        stop = self.stop
        res = self.result
        rate = float(cfg.rate_hz)
        State = fp.State
        armed_bit = fp.STATUS_ARMED
        applied_bit = fp.STATUS_FORCE_APPLIED
        isfinite = math.isfinite
        perf = time.perf_counter_ns
        clock = self._clock
        receive = self._receive_hook()
        self._expect = -1
        silence = self._silence()
        # a device (re)starting after CONFIG gets state_timeout for its first STATE
        first_wait = max(silence, cfg.state_timeout)
        poll = min(0.1, silence)
        newest = cfg.backlog == "newest"
        ahead_max = silence * rate + 2.0
        self._last_rx = clock()
        ds = self._dstats
        nbad = self._nbad
        mv = self.measured
        while tel.n < n_max and not stop.set:
            # wait no longer than the silence still allowed: the loss is declared when it
            # runs out (to 1 us), not a poll later
            allowed = first_wait if self._fresh else silence
            left = self._last_rx + allowed - clock()
            msgs = receive(poll if left > poll else (left if left > 1e-6 else 0.0))
            t_rx = perf()
            if ds is not None and (ds.bad_crc + ds.bad_cobs + ds.overlong + ds.malformed
                                   + ds.unknown_type) != nbad:
                nbad = self._snap_bad(ds.bad_crc + ds.bad_cobs + ds.overlong
                                      + ds.malformed + ds.unknown_type)
            if not msgs:
                if clock() - self._last_rx >= allowed - 1e-6:
                    raise _Lost(f"no STATE from the device for {allowed:g} s")
                continue
            used = False
            for j, msg in enumerate(msgs):
                tm = type(msg)
                if tm is not State:
                    if self._note_other(msg):
                        break
                    continue
                if len(msg.position) != 1:
                    res.bad_axes += 1
                    continue
                seq = msg.seq
                if not msg.status & armed_bit:
                    if self._fresh:
                        res.unarmed += 1
                        continue
                    raise _Lost("the device reports itself disarmed (reset?)")
                x = msg.position[0]
                resumes = self._fresh
                if self._fresh:
                    if self._check_applied and msg.status & applied_bit:
                        res.earlier_session += 1  # a FORCE applied since CONFIG: none sent
                        continue
                    if not isfinite(x):
                        x = math.nan          # _drive stops on it (non-finite position)
                    else:
                        self._resume(x)
                        self._expect = seq
                if self._expect >= 0:
                    gap = (seq - self._expect) & _U32
                    if gap >= _HALF:
                        res.stale += 1            # duplicated or reordered: older
                        continue
                    if gap and gap > (clock() - self._last_rx + silence) * rate + 2.0:
                        res.implausible += 1      # further ahead than time allows
                        continue
                    res.missed += gap
                # only a STATE used keeps the device alive: a host ignoring every STATE
                # (stale, implausible) is as good as deaf, and loses it
                self._last_rx = clock()
                self._expect = (seq + 1) & _U32
                used = True
                if mv is not None:
                    mv.take(seq)                  # its VELOCITY came just before it
                if newest and not resumes and _newer_waiting(msgs, j, seq, ahead_max):
                    res.skipped += 1              # backlog: a newer STATE is waiting
                    self._skip_flag = FLAG_SKIPPED
                    yield msg, x, -1              # not answered; the scene still steps
                    continue
                yield msg, x, t_rx            # _drive answers it (or stops: no resume)
                if tel.n >= n_max:
                    break
            if (not used and not stop.set
                    and clock() - self._last_rx >= (first_wait if self._fresh else silence) - 1e-6):
                # frames came, but no STATE the loop could use for the silence allowed
                raise _Lost(f"no usable STATE from the device for "
                            f"{first_wait if self._fresh else silence:g} s")

    # ------------------------------------------------------------------ host-clocked
    def _host_clocked_stretch(self, n_max: int) -> None:
        """Host-clocked loop from the next armed STATE until the end, a stop, or a loss:
        at each host deadline the latest STATE is answered (:meth:`_host_states`,
        :meth:`_drive`)."""
        self._drive(n_max, self._host_states(n_max))

    def _host_states(self, n_max: int):
        """The host-clocked source of :meth:`_drive`: the latest STATE at each deadline.

        Ticks without a new STATE are skipped (``missed``). Silence longer than
        :meth:`_silence`, or a disarmed STATE after arming, raise :class:`_Lost`
        (recovered by :meth:`_run_stretches`, as in the device-clocked loop). On a
        virtual-clock transport (``clock()``/``sleep()``) the deadlines are on that clock;
        deadlines missed by more than a period are counted (``overruns``).

        Yields
        ------
        (State, float, int)
            The STATE, its position [m], and ``perf_counter_ns()`` at the deadline.
        """
        cfg = self.config
        tr = self.transport
        tel = self.tel
        stop = self.stop
        res = self.result
        rate = float(cfg.rate_hz)
        silence = self._silence()
        State = fp.State
        armed_bit = fp.STATUS_ARMED
        applied_bit = fp.STATUS_FORCE_APPLIED
        perf = time.perf_counter_ns
        clock = self._clock
        sleep = self._sleep
        virtual = hasattr(tr, "clock")
        if virtual:
            def mono_ns() -> int:
                return int(round(clock() * 1e9))
        else:
            mono_ns = time.monotonic_ns
        receive = tr.receive
        # a request-reply device (a driver's) answers only what it is asked. A tick whose
        # answer is overdue (the transport's deadline) is a missing sample, not a silence
        # that grows into a loss: the scene steps with the position extrapolated from the
        # two before and its FORCE goes out (asking the device again), so the scene's clock
        # stays the device's (row flagged FLAG_ESTIMATED); more than ESTIMATED_MAX in a row,
        # the tick is skipped and the last force asked again (hold)
        hold = getattr(tr, "hold", None)
        overdue = getattr(tr, "overdue", None)
        run_est = 0
        x_1 = x_2 = None            # the two positions answered last
        period_ns = int(round(1e9 / cfg.rate_hz))
        latest = None
        t_latest = 0.0              # clock time the latest STATE was taken [s]

        ds = self._dstats
        mv = self.measured

        def take(msgs) -> None:
            """Keep the newest armed 1-axis STATE; count the others; FAULT/HELLO noted;
            a change of the decoder's bad-frame count is recorded."""
            nonlocal latest, t_latest
            if ds is not None and (ds.bad_crc + ds.bad_cobs + ds.overlong + ds.malformed
                                   + ds.unknown_type) != self._nbad:
                self._snap_bad(_bad_count(ds))
            for msg in msgs:
                if type(msg) is not State:
                    self._note_other(msg)
                    continue
                if len(msg.position) != 1:
                    res.bad_axes += 1
                    continue
                if not msg.status & armed_bit:
                    if latest is None:
                        res.unarmed += 1
                        continue
                    raise _Lost("the device reports itself disarmed (reset?)")
                if latest is None and self._check_applied and msg.status & applied_bit:
                    res.earlier_session += 1      # a FORCE applied since CONFIG: none sent
                    continue
                if latest is not None:
                    ahead = (msg.seq - latest.seq) & _U32
                    if ahead >= _HALF:
                        res.stale += 1            # duplicated or reordered: older
                        continue
                    if ahead > 1 and ahead > (clock() - t_latest + silence) * rate + 2.0:
                        res.implausible += 1      # further ahead than time allows
                        continue
                latest = msg
                t_latest = clock()
                if mv is not None:
                    mv.take(msg.seq)              # its VELOCITY came just before it

        # wait for the first armed STATE (a device (re)starting gets state_timeout)
        end = clock() + cfg.state_timeout
        while latest is None and not stop.set:
            take(receive(0.05))
            if latest is None and clock() > end:
                raise _Lost(f"no STATE from the device for {cfg.state_timeout:g} s")
        if latest is None or stop.set:
            return
        self._resume(latest.position[0])
        used_seq = -1
        last_new = clock()
        # a real-time device ticks on the same clock: tick a third of a period after its
        # STATE arrives, so the STATE is in and the FORCE is back before its next tick
        # (ticking in phase with the device would race it every period)
        deadline = mono_ns() + (0 if cfg.lockstep else period_ns // 3)
        while tel.n < n_max and not stop.set:
            remaining = deadline - mono_ns()
            if virtual:
                while remaining > 0:
                    sleep(max(remaining, 1000) * 1e-9)
                    remaining = deadline - mono_ns()
            elif remaining > 0:
                # an absolute-deadline sleep, no spin: a SCHED_FIFO thread spinning to each
                # deadline is throttled by the kernel (sched_rt_runtime_us) under load
                sleep_until_ns(deadline)
            take(receive(0.0))
            if stop.set:
                break
            t_rx = perf()
            if (latest.seq - used_seq) & _U32 >= _HALF or latest.seq == used_seq:
                # no new sample since the last tick (or only one older than an estimated
                # tick already stepped through): stepping the engine with a stale
                # position would corrupt its velocity; skip this tick (counted), or, for a
                # driver whose answer is overdue, step it with an estimate (notes above)
                res.missed += 1
                if clock() - last_new >= silence - 1e-6:
                    raise _Lost(f"no STATE from the device for {silence:g} s")
                if (overdue is not None and run_est < ESTIMATED_MAX and x_2 is not None
                        and overdue()):
                    run_est += 1
                    res.estimated += 1
                    used_seq = (used_seq + 1) & _U32
                    x_e = 2.0 * x_1 - x_2
                    x_2, x_1 = x_1, x_e
                    self._skip_flag |= FLAG_ESTIMATED
                    t_e = latest.time_us + int(round(((used_seq - latest.seq) & _U32)
                                                     * 1e6 / rate))
                    yield (State(used_seq, t_e & 0xFFFFFFFFFFFFFFFF, latest.status,
                                 (used_seq - cfg.delay) & _U32, (x_e,)), x_e, t_rx)
                    deadline += period_ns
                    continue
                if hold is not None:
                    hold()
                deadline += period_ns
                continue
            last_new = clock()
            used_seq = latest.seq
            run_est = 0
            x_2, x_1 = x_1, latest.position[0]
            yield latest, latest.position[0], t_rx   # _drive answers it (or stops)
            deadline += period_ns
            now = mono_ns()
            if now - deadline > period_ns:
                res.overruns += 1
                deadline = now


def _force_seq_late(seq: int, force_seq: int, status: int, d: int,
                    flags_applied: bool) -> bool:
    """Whether a STATE at or after tick ``d`` shows the device holding an older force.

    PROTOCOL.md §4: ``force_seq`` names the FORCE applied only when ``STATUS_FORCE_APPLIED``
    is set; a device known to set that bit (``flags_applied``) and not setting it now has
    applied no FORCE although one was due (late). A device that never sets the bit (written
    before it existed) is read as before: ``force_seq`` compared with ``seq - d``.

    Parameters
    ----------
    seq, force_seq : int
        STATE fields (u32).
    status : int
        STATE status bits.
    d : int
        Expected loop delay [samples], >= 0.
    flags_applied : bool
        The device has set ``STATUS_FORCE_APPLIED`` at least once.

    Returns
    -------
    bool
        True when the force held is not the FORCE answering STATE ``seq - d``.
    """
    if status & fp.STATUS_FORCE_APPLIED or not flags_applied:
        return (seq - force_seq) & _U32 != d
    return True


def _newer_waiting(msgs, j: int, seq: int, ahead_max: float) -> bool:
    """Whether a STATE newer than ``seq`` waits after ``msgs[j]`` (the backlog policy).

    Parameters
    ----------
    msgs : list
        Messages of one read, in arrival order.
    j : int
        Index of the STATE ``seq`` in it.
    seq : int
        Its sequence number (u32).
    ahead_max : float
        Most samples a newer STATE may be ahead (``silence * rate + 2``: a STATE further
        ahead is implausible and does not count).

    Returns
    -------
    bool
        True when a later armed 1-axis STATE is ahead by 1 .. ``ahead_max``.
    """
    State = fp.State
    for m in msgs[j + 1:]:
        if type(m) is State and len(m.position) == 1 and m.status & fp.STATUS_ARMED:
            ahead = (m.seq - seq) & _U32
            if 0 < ahead < _HALF and ahead <= ahead_max:
                return True
    return False


def _bad_count(ds) -> int:
    """Frames a decoder dropped so far (its :class:`~firmware_protocol.DecoderStats`)."""
    return ds.bad_crc + ds.bad_cobs + ds.overlong + ds.malformed + ds.unknown_type


def _stored_energy(engine) -> float:
    """Energy the scene stores now [J] (:meth:`hapsim.engine.Engine.energy`); 0.0 for an
    engine without that method or a non-finite value (the observer's baseline, module notes)."""
    fn = getattr(engine, "energy", None)
    if fn is None:
        return 0.0
    e = float(fn())
    return e if math.isfinite(e) else 0.0


def _signame(signum: int) -> str:
    import signal
    try:
        return signal.Signals(signum).name
    except ValueError:
        return str(signum)


def _safety_reason(wsum: int, clamp_max: int, wlen: int, limit: float, x: float,
                   position_bound: float, v: float, velocity_limit: float, excess: float,
                   energy_limit: float, stored: float = 0.0) -> str:
    """Why a safety stop is due (called only once a bound is breached, off the fast path).

    Parameters
    ----------
    wsum, clamp_max, wlen : int
        Samples at the force limit in the last ``wlen``, and how many stop the run.
    limit : float
        Force limit [N].
    x, position_bound : float
        Device position and its bound [m].
    v, velocity_limit : float
        Device velocity and its bound [m/s].
    excess, energy_limit : float
        Energy given to the hand by the scene beyond what it stored at its (re)start, and
        its bound [J] (passivity observer, Hannaford & Ryu 2002).
    stored : float
        The scene's stored energy at that (re)start, the observer's baseline [J].

    Returns
    -------
    str
        The stop reason for the report, the first breached bound first.
    """
    if wsum >= clamp_max:
        return f"safety: force at the limit {limit:g} N in {wsum} of the last {wlen} samples"
    if x > position_bound or x < -position_bound:
        return f"safety: position {x:.6g} m beyond +-{position_bound:g} m"
    if abs(v) > velocity_limit:
        return f"safety: velocity {v:.6g} m/s beyond +-{velocity_limit:g} m/s"
    return (f"safety: the scene gave the hand {excess:.6g} J more than the {stored:.6g} J "
            f"it stored at its start, beyond the energy limit {energy_limit:g} J")
