"""What goes into the host loop and what comes out: :class:`LoopConfig` (the run's
parameters), :class:`LoopResult` (its counters, events and figures), :class:`StopFlag`
(how a signal or a caller ends it), :class:`MeasuredVelocity` (the device's velocity
sensor, for a correction that reads it), :class:`LostDevice` (a loss, raised inside the
loop and handled by its recovery) and the protocol constants the loop's rooms share
(:mod:`hapsim.host.loop`, :mod:`hapsim.host.handshake`,
:mod:`hapsim.host.recovery`, :mod:`hapsim.host.bad_frames`)."""

from __future__ import annotations

import math
import signal
from dataclasses import dataclass, field

import numpy as np

import firmware_protocol as fp
from hapsim.spawn import StopFlag  # noqa: F401 - the host loop's stop flag, named here too

__all__ = ["LoopConfig", "LoopResult", "StopFlag", "MeasuredVelocity", "LostDevice",
           "EstimatedState",
           "percentiles_us", "signame", "LATCHED_FAULTS", "BAD_FRAME_RECORDS",
           "BAD_FRAME_CONTEXT", "SENSORS_TRIES", "SENSORS_WAIT", "QUIESCE_TRIES",
           "QUIESCE_WAIT", "QUIESCE_NONCE", "SEQ_MASK", "SEQ_HALF",
           "OPEN_ENDED"]

#: Sequence numbers are 32-bit and wrap (PROTOCOL.md §3): differences are taken modulo
#: ``SEQ_MASK + 1``; one at or above ``SEQ_HALF`` is negative (older).
SEQ_MASK = 0xFFFFFFFF
SEQ_HALF = 0x80000000
#: Rows of a run without a sample count (ended by a stop).
OPEN_ENDED = 1 << 62


#: Bad-frame incidents kept in :attr:`LoopResult.bad_frames` (the latest ones).
BAD_FRAME_RECORDS = 32
#: Frames received before a bad one that its record shows (at most).
BAD_FRAME_CONTEXT = 8


#: SENSORS_REQUEST attempts before a device is taken to offer no sensor (it was written
#: before the message and drops it, PROTOCOL.md §4), and the wait after each [s].
SENSORS_TRIES = 3
SENSORS_WAIT = 0.1

#: Before every CONFIG the host sends STOP then a PING and waits for its PONG, at most this
#: many times, this long each [s] (:meth:`hapsim.host.handshake.Handshake._quiesce`); then
#: it arms anyway.
QUIESCE_TRIES = 3
QUIESCE_WAIT = 0.1
#: Nonce of the quiescing PINGs (+ the try): apart from the round-trip PINGs' 0..15.
QUIESCE_NONCE = 0x51E7_0000


#: Fault codes that latch on the device (PROTOCOL.md §4): they end the run.
LATCHED_FAULTS = frozenset((fp.FAULT_BAD_CONFIG, fp.FAULT_SENSOR, fp.FAULT_AMPLIFIER,
                            fp.FAULT_NON_FINITE_FORCE, fp.FAULT_VERSION_MISMATCH))


class LostDevice(Exception):
    """The device is lost (silence, port error, reset): raised inside the host loop (and
    the compiled one) and handled by its recovery; never leaves :meth:`HostLoop.run`.

    Parameters
    ----------
    reason : str
        What was seen, for the report's events.
    port_error : bool
        True when the port itself failed (reopened on recovery).
    """

    def __init__(self, reason: str, port_error: bool = False) -> None:
        super().__init__(reason)
        self.port_error = port_error


class MeasuredVelocity:
    """The device's measured velocity over the wire (VELOCITY frames, PROTOCOL.md §4).

    The loop keeps the last VELOCITY received (:meth:`put`) and, for each STATE it
    answers, :meth:`take` makes :attr:`value` that STATE's velocity: the VELOCITY with the
    same ``seq`` (the device sends it just before the STATE), or, when it was lost, the
    last value held (counted in :attr:`missing`). An engine that uses the measured velocity
    (:func:`hapsim.host.correction.corrected_engine`) calls the object.

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
        """``frames`` and ``missing`` as a dict (the run's report).

        Returns
        -------
        dict
            ``frames`` (VELOCITY messages kept) and ``missing`` (STATEs answered without
            their velocity), ints.
        """
        return {"frames": self.frames, "missing": self.missing}


@dataclass
class LoopConfig:
    """Parameters of one host-loop run.

    Parameters
    ----------
    rate_hz : float
        Loop rate [Hz] sent in CONFIG.
    n_samples : int
        Samples to run; 0: open-ended (until a stop: signal, safety, device). A telemetry
        buffer without a ring (:class:`~hapsim.host.telemetry.Telemetry`) also caps it.
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
    compact : {"auto", "on", "off"}
        The compact frames (STATE_COMPACT / FORCE_COMPACT, PROTOCOL.md §4): ``"auto"`` asks
        a device for them when its LINK shows a UART on which one STATE and one FORCE take
        more than half a period (:func:`firmware_protocol.wants_compact`: 4 kHz at 2 Mbaud)
        or more than the full frames' LINK rule allows; ``"on"`` always asks; ``"off"``
        never. Asked only while the watchdog is at most 250 periods (the compact lag is
        exact up to 254 ticks); a device that does not offer them keeps the full frames.
    brake_damping : float
        After a safety stop on the device's motion (clamp, position, velocity, energy, the
        host's lateness), the damping ``B`` [N s/m] the host brakes the device with before
        its zero force (:meth:`hapsim.host.recovery.Recovery._brake`); 0: no braking.
    brake_rest : float
        The speed [m/s] below which the braking ends (three estimates in a row).
    late_growth : hapsim.kernels.late_growth.LateGrowth or None
        The lateness guard's growth table (:mod:`hapsim.kernels.late_growth`): the loop
        stops (safety, then the braking) once the forces the device held over the host's
        lateness grew the scene's loop by the guard's bound, on the frozen estimate, and the
        handle moves faster than ``brake_rest`` (0: at any speed). None: no guard
        (lockstep, a driver's board with its own rules, a test).
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
    compact: str = "auto"
    brake_damping: float = 0.0
    brake_rest: float = 0.0
    late_growth: object = None


class EstimatedState:
    """The STATE fields of an estimated sample (a driver's missing reply), one object per
    loop, filled in place by the transport's ``estimate`` (no allocation per sample).

    Attributes
    ----------
    seq, time_us, status, force_seq : int
        As :class:`firmware_protocol.State`: the command whose answer is missing, the
        host time it was sent [us], the transport's status bits, ``seq - d``.
    """

    __slots__ = ("seq", "time_us", "status", "force_seq")

    def __init__(self) -> None:
        self.seq = self.time_us = self.status = self.force_seq = 0


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
        the row answered after them has :data:`~hapsim.host.telemetry.FLAG_SKIPPED`, and
        the scene's steps with them are in the telemetry's skipped STATEs' record
        (:meth:`~hapsim.host.telemetry.Telemetry.skipped`).
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
        CONFIG (:meth:`hapsim.host.handshake.Handshake._quiesce`); False: no recovery, or
        it re-armed without that barrier.
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
    frames : str
        ``"compact"`` when the device took the compact frames (PROTOCOL.md §4), else
        ``"full"``.
    brake : dict
        The braking after a safety stop (:meth:`hapsim.host.recovery.Recovery._brake`):
        ``damping`` [N s/m], ``periods`` (forces sent), ``seconds``, ``v_start`` and
        ``v_end`` [m/s] (the first and last speed estimated, None without two STATEs),
        ``ended`` (``"rest"``, ``"time"`` or ``"port"``), ``late`` (its periods that took
        the host more than two: a loaded host's); empty when it did not brake.
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
    frames: str = "full"
    brake: dict = field(default_factory=dict)


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


def signame(signum: int) -> str:
    """The name of a signal (``"SIGINT"``), or its number as text when it has none.

    Parameters
    ----------
    signum : int

    Returns
    -------
    str
    """
    try:
        return signal.Signals(signum).name
    except ValueError:
        return str(signum)
