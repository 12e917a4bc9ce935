"""The mock device: the real side of the THS, behind the device side of the protocol.

Physics (docs/design.md, 'The mock device')
-------------------------------------------
``m x'' + b0 x' = u(t) + f_ext(t)`` with the commanded force ``u`` held constant over each
period (zero-order hold), integrated *exactly* from tick to tick with the closed form of
:func:`zoh_step_coefficients` (written here independently of
:func:`hapsim.analysis.loop.zoh_state_space`; the tests compare both with
``scipy.linalg.expm`` of the augmented matrix). With ``hold: ideal`` the mock is the paper's
idealised sampled image instead, a centred-difference mass with the friction form of
Florens, Voda & Urma eq. (4)::

    x[n+1] = (1 + a) x[n] - a x[n-1] + psi T^2/m u[n],   a = e^(-b0 T/m),
    psi = (1 - a) / (b0 T / m)                            (psi = 1 when b0 = 0)

i.e. ``D(z) X = N(z) U`` with ``N = T^2/m z`` and ``D = (z-1)(z-a)(b0T/m)/(1-a)`` shifted
by one sample, the plant the analysis uses for ``"ideal"``.

Timing convention
-----------------
Tick ``n`` samples ``x(nT)`` and sends STATE ``seq = n``. The FORCE answering STATE ``n``
(``seq = n``) is applied over ``[(n+d)T, (n+d+1)T)``: at tick ``n`` the device applies the
FORCE with ``seq = n - d`` if it has arrived, and otherwise holds the force it applied last
(real-time mode; the tick is counted *late*). ``d = 0`` ("apply at once") exists in lockstep
only, where tick ``n`` waits for FORCE ``n``. STATE ``n`` carries in ``force_seq`` the seq of
the force applied from tick ``n`` on (``seq - force_seq = d`` when on time); with ``d = 0``
it is the one applied over the previous period (FORCE ``n`` is not known yet).

Only what a scene asks for is added: encoder quantisation (``position_resolution``),
Coulomb friction (``coulomb``), Gaussian sensor noise (``noise``, seeded), the velocity
sensor's quantum and noise (``velocity_resolution``, ``velocity_noise``: VELOCITY frames,
sent only when the host asks, PROTOCOL.md §4), the force clamp
(``force_limit``) and the excitation (``x0``, ``v0``, a force ``impulse``, a recorded hand
force ``profile``).
"""

from __future__ import annotations

import gc
import json
import math
import os
import select
import signal
import time
from dataclasses import dataclass, field

import firmware_protocol as fp
from hapsim.spawn import StopFlag
from hapsim.device_model import (DEFAULT_DEVICE, DEFAULT_EXCITATION, MockPhysics,
                                 hand_force_samples, ideal_step_coefficients,
                                 zoh_step_coefficients)
from hapsim.errors import ConfigError
from hapsim.scene import Device, Excitation

__all__ = ["zoh_step_coefficients", "ideal_step_coefficients", "hand_force_samples",
           "MockPhysics", "MockDevice", "MockStats", "serve_fd", "MOCK_DEVICE_ID",
           "DEFAULT_DEVICE", "DEFAULT_EXCITATION", "compiled_reason", "warm_up_mock"]

#: HELLO.device_id of the mock ("MOCK" in ASCII).
MOCK_DEVICE_ID = 0x4D4F434B
#: Real-time ticks: the mock waits in ``select`` until this long before each deadline and
#: reads the host's bytes in a loop for the rest [ns]. 0: no spin (the wait ends at the
#: deadline; select's timeout is exact to the timer under SCHED_FIFO, whose timer slack is
#: 0). A spin to each deadline made the mock, a SCHED_FIFO process, throttled under load.
#: Above this native rate [Hz] ``serve_fd(tick="auto")`` ticks in numba; at and below it in
#: Python (the compiled tick's loading delays the HELLO by 0.5-1 s; 1 kHz runs do not need it).
AUTO_COMPILED_HZ = 2000.0
MOCK_SPIN_NS = 0


# --------------------------------------------------------------------------- physics

# --------------------------------------------------------------------------- protocol side

@dataclass
class MockStats:
    """What the mock saw, for tests and reports (all counts since the last CONFIG).

    Attributes
    ----------
    ticks : int
        STATE messages produced.
    forces_rx : int
        FORCE messages received.
    late : int
        Ticks at which the FORCE due (``seq = n - d``) had not arrived: last force held.
    watchdog_trips : int
        Ticks at which the watchdog zeroed the force.
    clamped : int
        Ticks whose applied force was clamped to the force limit.
    overruns : int
        Real-time ticks more than one period late (the mock's own scheduling).
    unexpected : int
        FORCE messages that were ignored (disarmed, or wrong seq in lockstep).
    stale : int
        Real-time FORCE messages ignored because their ``seq`` is outside
        ``[n - d, n]`` (``n``: the next tick): too late to be applied (duplicated, reordered
        or delayed: the tick they were due at has passed, a newer force may already be
        applied) or answering a STATE not sent yet (a frame from before a CONFIG). They do
        not feed the watchdog.
    saw_stop : bool
        A STOP was received.
    last_applied : float
        Force applied at the last tick, or 0.0 after STOP [N].
    last_host_message : str
        Type name of the last message received from the host.
    faults : list of str
        FAULT names sent.
    """

    ticks: int = 0
    forces_rx: int = 0
    late: int = 0
    watchdog_trips: int = 0
    clamped: int = 0
    overruns: int = 0
    unexpected: int = 0
    stale: int = 0
    saw_stop: bool = False
    last_applied: float = 0.0
    last_host_message: str = ""
    faults: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready copy of the counters.

        Returns
        -------
        dict
            Every attribute of the class by name (``faults`` copied).
        """
        return {"ticks": self.ticks, "forces_rx": self.forces_rx, "late": self.late,
                "watchdog_trips": self.watchdog_trips, "clamped": self.clamped,
                "overruns": self.overruns, "unexpected": self.unexpected,
                "stale": self.stale, "saw_stop": self.saw_stop, "last_applied": self.last_applied,
                "last_host_message": self.last_host_message, "faults": list(self.faults)}


class MockDevice:
    """The device side of the protocol around :class:`MockPhysics`; I/O-free.

    Parameters
    ----------
    device : Device
        Physics and imperfections of the device; ``device.delay`` is ``d``,
        ``device.force_limit`` the device's own clamp (HELLO.force_limit).
    excitation : Excitation, optional
        How the hand starts the motion at each CONFIG.
    native_rate_hz : float
        Rate announced in HELLO [Hz]; CONFIG sets the rate actually used.
    lockstep : bool
        True: one period per FORCE (tick ``n + 1`` is produced when FORCE ``n`` arrives).
        False: :meth:`tick` is called by a clock.
    seed : int
        Sensor-noise seed.
    base_dir : str, optional
        Directory for relative profile paths.

    Raises
    ------
    ConfigError
        When ``d = 0`` is asked for in real-time mode, or on invalid device values.

    Notes
    -----
    Host duties served (see ``firmware_protocol``): HELLO on connect (:meth:`hello`) and on
    HELLO_REQUEST; CONFIG (re)starts the physics from the excitation and arms; STATE each
    tick; FORCE stored in a delay line and applied at tick ``seq + d`` (real-time: only a
    FORCE whose tick is still to come, ``seq`` in ``[n - d, n]``; older or newer ones are
    counted ``stale`` and ignored, so a duplicated or reordered FORCE never replaces a
    newer one), clamped to
    ``min(CONFIG.force_limit, device force limit)``; a non-finite FORCE zeroes the force,
    sends FAULT NON_FINITE_FORCE and disarms; PING -> PONG; STOP zeroes the force at once and
    disarms; watchdog (real-time): no FORCE for ``CONFIG.watchdog_us`` zeroes the force.
    """

    def __init__(self, device: Device, excitation: Excitation | None = None, *,
                 native_rate_hz: float = 1000.0, lockstep: bool = True, seed: int = 0,
                 base_dir: str | None = None) -> None:
        self.device = device
        self.excitation = excitation or Excitation()
        self.native_rate_hz = float(native_rate_hz)
        self.lockstep = bool(lockstep)
        self.seed = seed
        self.base_dir = base_dir
        self.delay = int(device.delay)
        if self.delay == 0 and not self.lockstep:
            raise ConfigError("delay d = 0 (force applied at once) exists in lockstep only; "
                              "a real-time device needs d >= 1", key="device.delay")
        self._hand_cache: dict = {}
        self._init_protocol(float(device.force_limit))

    def _init_protocol(self, force_limit: float) -> None:
        """The protocol side's state before the first CONFIG (``delay``, ``lockstep``,
        ``native_rate_hz`` and ``_zero`` set): delay line, counters, disarmed."""
        self._ring = max(16, 2 * self.delay + 2)
        self._rf = [self._zero] * self._ring
        self._rs = [-1] * self._ring
        self.armed = False
        self.configured = False
        self.physics = None
        self.stats = MockStats()
        self.history: list = []      # the MockStats of each earlier CONFIG (lifetime totals)
        self.trace: list | None = None  # tests: (time_us, applied force [N]) per tick when a list
        #: tests: when a ``collections.deque(maxlen=N)`` (bounded), one
        #: ``(time_us, tick, force_seq, applied force [N], configs)`` per tick, ``configs``
        #: counting the CONFIGs accepted before (the session the tick belongs to)
        self.applied_log = None
        self.rate_hz = self.native_rate_hz
        self.force_limit = force_limit
        self.watchdog_us = 0
        self._applied = self._zero
        self._applied_seq = 0
        self._status_extra = 0
        self._last_force_us = 0
        self._u = self._zero
        #: sensor messages enabled by the host's SENSORS_REQUEST (PROTOCOL.md §4): kept
        #: across CONFIG and STOP, cleared by a reset
        self.sensors = 0
        #: the VELOCITY of the last STATE emitted (None while VELOCITY is not enabled)
        self.velocity_out = None

    # ------------------------------------------------------------------ messages
    def hello(self) -> fp.Hello:
        """HELLO message of this device (sent on connect and on HELLO_REQUEST).

        Returns
        -------
        firmware_protocol.Hello
            Protocol version :data:`firmware_protocol.PROTOCOL_VERSION`, 1 axis, device id
            :data:`MOCK_DEVICE_ID`, position scale ``device.position_resolution`` [m],
            force scale 0, force limit ``device.force_limit`` [N] (1e300 when unlimited),
            native rate [Hz].
        """
        fl = self.device.force_limit
        return fp.Hello(fp.PROTOCOL_VERSION, 1, MOCK_DEVICE_ID,
                        float(self.device.position_resolution or 0.0), 0.0,
                        float(fl) if math.isfinite(fl) else 1e300, self.native_rate_hz)

    def handle(self, msg, now_us: int = 0) -> list:
        """Act on one host message.

        Parameters
        ----------
        msg : firmware_protocol message
            Message from the host.
        now_us : int
            Device clock [us] (real-time mode; PONG and watchdog).

        Returns
        -------
        list of messages
            Replies to send, in order (in lockstep, a FORCE is answered by the next STATE).
        """
        st = self.stats
        st.last_host_message = type(msg).__name__
        if isinstance(msg, fp.Force):
            return self._on_force(msg, now_us)
        if isinstance(msg, fp.HelloRequest):
            return [self.hello()]
        if isinstance(msg, fp.Ping):
            return [fp.Pong(msg.nonce, msg.host_time_us, now_us)]
        if isinstance(msg, fp.SensorsRequest):
            offered = self.sensors_offered
            self.sensors = msg.sensors & offered
            return [fp.Sensors(offered, self.sensors)]
        if isinstance(msg, fp.Config):
            return self._on_config(msg, now_us)
        if isinstance(msg, fp.Stop):
            self.stop()
            st.saw_stop = True
            return []
        return []

    @property
    def sensors_offered(self) -> int:
        """Sensor bits this mock can send (SENSORS.offered): VELOCITY with the ZOH hold
        (its physics has a velocity state), none with the ideal hold (a centred-difference
        mass has no velocity at the sample instant)."""
        return fp.SENSOR_VELOCITY if self.device.hold == "zoh" else 0

    def frames(self, state) -> list:
        """The messages of one tick in wire order: VELOCITY (when enabled), then STATE.

        Parameters
        ----------
        state : firmware_protocol.State
            The STATE :meth:`tick` (or the lockstep answer) just produced.

        Returns
        -------
        list of messages
            ``[Velocity, State]`` while VELOCITY is enabled, else ``[State]``.
        """
        vo = self.velocity_out
        return [state] if vo is None else [vo, state]

    # ------------------------------------------------------------------ the force's axes
    #: The force held when none is due [N]; an n-axis mock (:mod:`hapsim.emulated.mock_nd`)
    #: holds a tuple of n forces and overrides these four.
    _zero = 0.0

    def _force_value(self, msg: fp.Force):
        """The FORCE's force as this device holds it [N], or None when it carries another
        number of axes than the device has (counted ``unexpected``)."""
        return msg.force[0]

    @staticmethod
    def _is_finite(f) -> bool:
        """Every axis of the force finite."""
        return math.isfinite(f)

    @staticmethod
    def _clamp(f, lim: float):
        """``(f clamped to [-lim, lim] on each axis, whether it was)`` [N]."""
        if f > lim or f < -lim:
            return (lim if f > 0 else -lim), True
        return f, False

    @staticmethod
    def _first(f) -> float:
        """The first axis of the force [N] (``stats.last_applied``)."""
        return f

    def _position(self, ph) -> tuple:
        """The STATE's positions: the physics' sample on each axis [m]."""
        return (ph.sample(),)

    def stop(self) -> None:
        """Zero the force at once and disarm (STOP, or the mock shutting down)."""
        self._applied = self._zero
        self._u = self._zero
        self.armed = False
        self.stats.last_applied = 0.0
        self._rs = [-1] * self._ring

    def _on_config(self, msg: fp.Config, now_us: int) -> list:
        if not self._config_ok(msg):
            self.stats.faults.append("BAD_CONFIG")
            return [fp.Fault(fp.FAULT_BAD_CONFIG, 0)]
        self.rate_hz = float(msg.rate_hz)
        self.watchdog_us = int(msg.watchdog_us)
        self.force_limit = min(float(msg.force_limit), float(self.device.force_limit))
        hand = self._hand_cache.get(self.rate_hz)
        if hand is None:      # reading a long profile takes time: once per rate, not per CONFIG
            hand = self._hand_cache[self.rate_hz] = hand_force_samples(
                self.excitation, 1.0 / self.rate_hz, self.base_dir)
        self.physics = MockPhysics(self.device, self.rate_hz, self.excitation,
                                   seed=self.seed, base_dir=self.base_dir, hand=hand)
        return self._armed(now_us)

    @staticmethod
    def _config_ok(msg: fp.Config) -> bool:
        """A CONFIG's rate, watchdog and force limit valid (else FAULT BAD_CONFIG)."""
        return (math.isfinite(msg.rate_hz) and msg.rate_hz > 0 and msg.watchdog_us > 0
                and math.isfinite(msg.force_limit) and msg.force_limit >= 0)

    def _armed(self, now_us: int) -> list:
        """After a CONFIG built the physics: a fresh session (counters, delay line, zero
        force), armed; in lockstep the first STATE."""
        self.history.append(self.stats)
        self.stats = MockStats(last_host_message="Config")
        self._rs = [-1] * self._ring
        self._applied = self._zero
        self._applied_seq = 0
        self._status_extra = 0          # force_seq restarts: FORCE_APPLIED clear until one is
        self._u = self._zero
        self._last_force_us = now_us
        self.armed = self.configured = True
        if self.lockstep:
            return self.frames(self._emit(now_us))
        return []

    def _on_force(self, msg: fp.Force, now_us: int) -> list:
        st = self.stats
        if not self.armed or self.physics is None:
            st.unexpected += 1
            return []
        f = self._force_value(msg)
        if f is None:
            st.unexpected += 1
            return []
        if not self._is_finite(f):
            self.stop()
            st.faults.append("NON_FINITE_FORCE")
            return [fp.Fault(fp.FAULT_NON_FINITE_FORCE, msg.seq)]
        if not self.lockstep:
            # only a FORCE still to be applied is stored: seq in [n - d, n], n the next
            # tick (its STATE not sent yet). Older: its tick has passed (a newer FORCE may
            # be applied already; a duplicate or reordered frame must not replace it).
            # Newer: answers a STATE this session never sent (a frame from before CONFIG).
            lo = self.physics.n - self.delay
            ahead = (msg.seq - lo) & 0xFFFFFFFF
            if ahead > self.delay:
                st.stale += 1
                return []
            seq = lo + ahead                  # unwrapped: the ring compares whole ticks
            st.forces_rx += 1
            self._last_force_us = now_us
            i = seq % self._ring
            self._rf[i] = f
            self._rs[i] = seq
            return []
        st.forces_rx += 1
        self._last_force_us = now_us
        i = msg.seq % self._ring
        self._rf[i] = f
        self._rs[i] = msg.seq
        n = self.physics.n
        if msg.seq != n:
            st.unexpected += 1
            return []
        if self.delay == 0:
            self._apply_due(n, now_us)
        self.physics.advance(self._u)
        return self.frames(self._emit(now_us))

    # ------------------------------------------------------------------ ticks
    def _apply_due(self, n: int, now_us: int) -> None:
        """Choose the force held over ``[nT, (n+1)T)``: FORCE ``n - d`` or the last one."""
        due = n - self.delay
        # FORCE_APPLIED (PROTOCOL.md §4): force_seq names a FORCE applied since CONFIG
        # (kept while a late tick holds it), so force_seq = 0 is not "none yet"
        applied = self._status_extra & fp.STATUS_FORCE_APPLIED
        self._status_extra = 0
        if due < 0:
            f, seq, applied = self._zero, 0, 0
        else:
            i = due % self._ring
            if self._rs[i] == due:
                f, seq, applied = self._rf[i], due, fp.STATUS_FORCE_APPLIED
            else:
                self.stats.late += 1
                self._status_extra |= fp.STATUS_OVERRUN
                f, seq = self._applied, self._applied_seq
        self._status_extra |= applied
        if (not self.lockstep and self.watchdog_us > 0
                and now_us - self._last_force_us > self.watchdog_us):
            f = self._zero
            self.stats.watchdog_trips += 1
            self._status_extra |= fp.STATUS_WATCHDOG_TRIPPED
        f, clamped = self._clamp(f, self.force_limit)
        if clamped:
            self.stats.clamped += 1
            self._status_extra |= fp.STATUS_FORCE_CLAMPED
        self._applied = f
        self._applied_seq = seq
        self._u = f
        self.stats.last_applied = self._first(f)
        if self.trace is not None:
            self.trace.append((now_us, f))
        if self.applied_log is not None:
            self.applied_log.append((now_us, n, seq, f, len(self.history)))

    def _emit(self, now_us: int) -> fp.State:
        """STATE of the current tick (choosing its force first when ``d >= 1``)."""
        ph = self.physics
        n = ph.n
        if self.delay > 0:
            self._apply_due(n, now_us)
        self.stats.ticks += 1
        time_us = int(round(n * 1e6 / self.rate_hz)) if self.lockstep else now_us
        status = fp.STATUS_ARMED | fp.STATUS_CONFIGURED | self._status_extra
        # the velocity sensor reads the same instant as the encoder: v(nT), exact
        self.velocity_out = (fp.Velocity(n & 0xFFFFFFFF, (ph.sample_velocity(),))
                             if self.sensors & fp.SENSOR_VELOCITY else None)
        return fp.State(n & 0xFFFFFFFF, time_us, status, self._applied_seq & 0xFFFFFFFF,
                        self._position(ph))

    def totals(self) -> dict:
        """Counters summed over every CONFIG since start (``stats`` holds the current one).

        Returns
        -------
        dict
            ``ticks``, ``forces_rx``, ``late``, ``watchdog_trips``, ``clamped``,
            ``overruns``, ``unexpected``, ``stale``, ``configs`` (number of CONFIGs accepted).
        """
        keys = ("ticks", "forces_rx", "late", "watchdog_trips", "clamped", "overruns",
                "unexpected", "stale")
        out = {k: sum(getattr(s, k) for s in self.history + [self.stats]) for k in keys}
        out["configs"] = len(self.history)
        return out

    def tick(self, now_us: int) -> fp.State | None:
        """Real-time tick: apply the force due, emit STATE, advance the physics one period.

        Parameters
        ----------
        now_us : int
            Device clock at the tick [us].

        Returns
        -------
        State or None
            The STATE to send; None when disarmed.
        """
        if not self.armed or self.physics is None:
            return None
        state = self._emit(now_us)
        self.physics.advance(self._u)
        return state


# --------------------------------------------------------------------------- serving

def _write(fd: int, data: bytes) -> bool:
    """Write ``data`` to a non-blocking fd; False when the peer is gone or the buffer full."""
    if not data:
        return True
    try:
        os.write(fd, data)
        return True
    except BlockingIOError:
        return False
    except OSError:        # EIO: no host has the port open; the next read says so
        return False


def _load_tick(dev):
    """The compiled tick for ``dev`` (numba's cache loaded, or compiled once), before any
    tick; ``(CompiledMock, None)``, or ``(None, reason)`` when it cannot load (the Python
    tick serves). Not in a thread beside the serving loop: a loading thread holding the GIL
    while the scheduler preempts it stalled the serving thread (late ticks, losses)."""
    try:
        from hapsim.emulated import fastmock
        from hapsim.blas import preload_numba_blas
        preload_numba_blas()
        warm_up_mock()
        return fastmock.CompiledMock(dev), None
    except Exception as exc:  # noqa: BLE001 - the Python tick serves instead
        return None, f"{type(exc).__name__}: {exc}"


def serve_fd(fd: int, mock: MockDevice, *, exit_on_stop: bool = True,
             report_path: str | None = None, flag: StopFlag | None = None,
             handle_signals: bool = True, plan=None, reopen=None, persistent: bool = False,
             on_host_gone=None, tick: str = "auto", hello: bool = True) -> dict:
    """Serve the mock device on a byte stream (the master side of a pty).

    Parameters
    ----------
    fd : int
        File descriptor to read host frames from and write device frames to; made
        non-blocking (a full buffer drops the frame rather than stalling the device).
    mock : MockDevice
        The device; its ``lockstep`` selects the serving loop (FORCE-driven or clock-driven).
    exit_on_stop : bool
        Return after a STOP from the host.
    report_path : str, optional
        Write :class:`MockStats` (plus decoder counters) there as JSON on exit (atomic).
    flag : StopFlag, optional
        Polled each iteration; serving ends when its ``set`` becomes true.
    handle_signals : bool
        Install SIGTERM/SIGINT handlers that end serving cleanly (main thread only).
    plan : FaultPlan, optional
        Faults to inject (:mod:`hapsim.emulated.faults`): wire faults on every frame sent
        and (``rx.`` names) on every frame received, stall / reset / vanish at device
        ticks, no HELLO.
    reopen : callable, optional
        ``reopen() -> fd``: a new port after a ``vanish`` (the old ``fd`` is closed when
        the port vanishes); required when the plan can make the port vanish.
    persistent : bool
        Outlive hosts: when the host closes the port (EIO: no slave fd open, e.g. a run
        that ended or was killed) the device zeroes its force, disarms and waits for the
        next host to open the port, instead of returning; waiting also at the start (the
        caller may close its own slave fd). Use with ``exit_on_stop=False``.
    on_host_gone : callable, optional
        ``on_host_gone(stats)`` with :meth:`MockStats.to_dict` of the session that ended,
        called (outside any tick) each time a persistent device loses its host.
    tick : {"auto", "compiled", "python"}
        ``"auto"`` (default): ``"compiled"`` when the device's native rate is above
        :data:`AUTO_COMPILED_HZ`, else ``"python"`` -- loading numba and the compiled tick
        costs the child about 0.5-1 s before its HELLO (``tools/bench_startup.py``), which a
        1 kHz run does not need: the Python tick keeps 1 kHz (``tools/bench_mock.py``).
        ``"compiled"``: while armed in real time, the ticks run in numba
        (:class:`hapsim.emulated.fastmock.CompiledMock`: same bytes, no GIL, absolute-deadline
        sleeps) wherever :func:`compiled_reason` allows (not in
        lockstep, with a fault plan, sensor noise or a compliant grip: then Python);
        ``"python"``: this function's Python loop throughout (the reference).
    hello : bool
        Say ``0x00`` + HELLO at once, as a device does when its port opens (default). False:
        only when asked (HELLO_REQUEST), for a port the host opens *after* this starts
        (``hapsim run``'s embedded mock): pyserial's open flushes the input and could cut
        an early HELLO in half (a bad frame); the host always asks.

    Returns
    -------
    dict
        The final report (same content as the JSON file), with ``faults_injected`` and
        ``fault_events`` when a plan was given, and ``totals`` over every CONFIG.

    Raises
    ------
    ConfigError
        A plan with ``vanish`` but no ``reopen``, or an unknown ``tick``.

    Notes
    -----
    Real-time ticks run on ``time.monotonic_ns``: ``select`` sleeps until the absolute
    deadline (waking for the host's bytes meanwhile), then the tick; no spin (a
    ``SCHED_FIFO`` process spinning to each deadline is throttled under load;
    :data:`MOCK_SPIN_NS` before it, 0 by default). The mock is a process on a
    shared machine, not a microcontroller: when the OS schedules it more than half a period
    late, the tick is counted in ``overruns`` and the next tick is put at least half a period
    later (the schedule slips rather than compressing the host's time to answer, so ``late``
    counts the host's lateness, not the mock's). The physics is per tick, so slips do not
    change it. The garbage collector is disabled while serving.
    Serving ends on EOF/EIO (host side closed; not when ``persistent``), STOP (when
    ``exit_on_stop``), or the flag.
    """
    from hapsim.emulated.faults import FaultyDevice

    flag = flag or StopFlag()
    if tick not in ("auto", "compiled", "python"):
        raise ConfigError(f"unknown tick {tick!r}; valid: auto, compiled, python", key="--tick")
    if tick == "auto":
        tick = "compiled" if mock.native_rate_hz > AUTO_COMPILED_HZ else "python"
    if plan is not None and plan.has_vanish and reopen is None:
        raise ConfigError("a vanish fault needs a port that can come back (--link PATH)",
                          key="--faults")
    if handle_signals:
        def _on_signal(signum, frame):
            flag.request(signum)
        for s in (signal.SIGTERM, signal.SIGINT):
            signal.signal(s, _on_signal)
    os.set_blocking(fd, False)
    dev = FaultyDevice(mock, plan)
    fast = load_error = None
    if tick == "compiled" and not mock.lockstep and (plan is None or plan.empty):
        fast, load_error = _load_tick(dev)       # before HELLO: every tick is compiled
    python_once = False              # the compiled stretch saw the port hang up: Python reads
    t0 = time.monotonic_ns()

    def now_us() -> int:
        return (time.monotonic_ns() - t0) // 1000

    if hello:
        dev.connect(now_us())
        _write(fd, dev.pop_due(now_us()))
    gc_was = gc.isenabled()
    gc.disable()
    deadline = None            # monotonic ns of the next real-time tick
    period_ns = 0
    reason = "flag"
    awaiting_host = persistent      # a persistent device starts with no host (EIO) too
    try:
        while not flag.set:
            now_ns = time.monotonic_ns()
            t_us = (now_ns - t0) // 1000
            if dev.vanish_pending:               # the port disappears: close the master
                dev.vanish_pending = False
                if fd is not None:
                    os.close(fd)
                fd = None
            if fd is None and not dev.vanished(t_us):
                fd = reopen()
                os.set_blocking(fd, False)
                awaiting_host = True             # EIO until the host opens the new port
                dev.poll(t_us)                   # 0x00 + HELLO on the new port
            if not mock.lockstep and mock.armed:
                if deadline is None:
                    period_ns = int(round(1e9 / mock.rate_hz))
                    deadline = now_ns
                wait = (deadline - now_ns - MOCK_SPIN_NS) / 1e9
            else:
                deadline = None
                wait = 0.05
            rel = dev.next_release_us()
            if rel is not None:
                wait = min(wait, max((rel - t_us) * 1e-6, 0.0))
            down = fd is None or dev.link_down(t_us)
            if down:
                end = max(dev.stalled_until_us, dev.vanished_until_us)
                wait = min(wait, max((end - t_us) * 1e-6, 0.0))
            pending = None           # host bytes the compiled stretch handed over
            if (fast is not None and deadline is not None and not down and not python_once
                    and not awaiting_host and not dev._out and not dev.decoder._overflow
                    and compiled_reason(dev.mock, dev.plan) is None):
                code, deadline, pending = fast.serve(fd, t0, deadline, period_ns, flag)
                if code != fast.R_HANDOFF:
                    python_once = code == fast.R_PORT
                    continue
            python_once = False
            r = []
            if pending is not None:
                r = [fd]
            elif wait > 0:
                try:
                    if down:
                        time.sleep(min(wait, 0.05))
                    else:
                        r, _, _ = select.select([fd], [], [], min(wait, 0.05))
                except InterruptedError:
                    continue
            elif not down:
                r = [fd]
            if r:
                try:
                    chunk = pending if pending is not None else os.read(fd, 4096)
                except BlockingIOError:
                    chunk = None
                except OSError:            # EIO: every slave fd closed
                    chunk = b""
                if chunk == b"" and awaiting_host:
                    time.sleep(0.001 if dev.vanished_until_us else 0.005)
                    chunk = None
                elif chunk == b"" and persistent:      # the host went away: wait for the next
                    mock.stop()
                    dev.decoder.reset()
                    awaiting_host = True
                    if on_host_gone is not None:
                        on_host_gone(mock.stats.to_dict())
                    continue
                elif chunk == b"":
                    reason = "host closed"
                    break
                if chunk:
                    awaiting_host = False
                    msgs = dev.feed(chunk, now_us())
                    if exit_on_stop and dev.plan.empty and any(
                            isinstance(m, fp.Stop) for m in msgs):
                        _write(fd, dev.pop_due(now_us()))
                        reason = "stop"
                        break
            if deadline is not None and mock.armed:
                now = time.monotonic_ns()
                if now >= deadline:
                    if now - deadline > period_ns // 2:
                        mock.stats.overruns += 1
                    dev.tick(now_us())
                    # the host always gets at least half a period to answer: a mock
                    # scheduled late slips its schedule (counted) instead of compressing it
                    deadline = max(deadline + period_ns, now + period_ns // 2)
                else:
                    dev.poll(now_us())           # host frames held by rx. faults
            else:
                dev.poll(now_us())
            if fd is not None:
                data = dev.pop_due(now_us())
                if data:
                    _write(fd, data)
    finally:
        if gc_was:
            gc.enable()
        mock.stop()
        report = mock.stats.to_dict()
        if reason == "flag" and flag.signal is not None:
            reason = f"signal {signal.Signals(flag.signal).name}"
        report["end"] = reason
        report["decoder"] = dev.decoder.stats.as_dict()
        report["totals"] = mock.totals()
        report["compiled_ticks"] = fast.ticks if fast is not None else 0
        if load_error is not None:
            report["compiled_note"] = f"compiled tick unavailable: {load_error}"
        if plan is not None:
            report["faults_injected"] = dict(plan.to_dict()["injected"])
            report["fault_events"] = dev.events
        if report_path:
            tmp = report_path + ".partial"
            with open(tmp, "w") as fh:
                json.dump(report, fh)
            os.replace(tmp, report_path)
    return report


# ----------------------------------------------------------------------------- Python side
def compiled_reason(mock, plan=None) -> str | None:
    """Why the compiled tick cannot serve this mock now; None when it can.

    Parameters
    ----------
    mock : MockDevice
        The device (its current CONFIG: physics and mode).
    plan : FaultPlan, optional
        The fault plan of :func:`~hapsim.emulated.mock.serve_fd`.

    Returns
    -------
    str or None
        ``"lockstep"``, ``"faults"``, ``"velocity sensor"`` (VELOCITY frames enabled by
        the host), ``"noise"``, ``"hand grip or arm stiffness (state-space plant)"``,
        ``"sub-sample delay (the split hold)"``, ``"hold"``, ``"subclass"``, ``"trace"`` or
        ``"not configured"``; None: compiled.
    """
    if type(mock) is not MockDevice:
        return "subclass"
    if mock.lockstep:
        return "lockstep"
    if plan is not None and not plan.empty:
        return "faults"
    if getattr(mock, "sensors", 0):
        return "velocity sensor"        # VELOCITY frames before each STATE: Python's
    if mock.trace is not None or mock.applied_log is not None:
        return "trace"
    ph = mock.physics
    if ph is None:
        return "not configured"
    if type(ph) is not MockPhysics:
        return "subclass"
    if ph._rng is not None:
        return "noise"
    if ph._grip is not None:
        return "hand grip or arm stiffness (state-space plant)"
    if ph.split > 0:
        return "sub-sample delay (the split hold)"
    if ph.hold not in ("zoh", "ideal"):
        return "hold"
    return None



def warm_up_mock() -> float:
    """Compile (or load from numba's cache) the compiled tick, on a pipe; seconds taken.

    Returns
    -------
    float
        Wall time [s].
    """
    from hapsim.emulated.faults import FaultyDevice
    from hapsim.spawn import StopFlag
    from hapsim.emulated.fastmock import CompiledMock

    t = time.perf_counter()
    mock = MockDevice(DEFAULT_DEVICE, DEFAULT_EXCITATION, lockstep=False)
    dev = FaultyDevice(mock)
    dev.feed(fp.encode(fp.Config(1000.0, 50_000, 10.0)), 0)
    cm = CompiledMock(dev)
    cm.load()
    cm.feed(fp.encode(fp.Force(0, (0.0,))), 0)
    cm.tick(0)
    cm.store()
    r, w = os.pipe()
    try:
        os.set_blocking(r, False)
        os.write(w, fp.encode(fp.Stop()))
        flag = StopFlag()
        now = time.monotonic_ns()
        cm.serve(r, now, now, 1_000_000, flag)       # reads the STOP: hands it over
    finally:
        os.close(r)
        os.close(w)
    return time.perf_counter() - t
