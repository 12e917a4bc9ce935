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

One handle
----------
A real-time mock is one handle in one hand, whatever the host does: a CONFIG restarts the
protocol's session (seq 0, the delay line empty, zero force), not the physics. From the
second CONFIG on (after a STOP, a loss, a reset, a vanished port) the plant carries on
from where its last tick left it, advanced over the idle periods since then at zero force
(the device disarmed ticks nothing; the hand force goes on in its own time,
:meth:`hapsim.device_model.MockPhysics.carry_on`), so a host that recovers a lost device
finds the handle where it coasted, still moving, as a board's would be. Only a new host
(the last one hung up: :meth:`MockDevice.new_hand`, called by the persistent serving
loop) starts the scene's excitation again, as a hand that takes the handle afresh. In
lockstep (no device time) every CONFIG restarts the excitation, as before; so does the
n-D mock, whose hand starts each CONFIG from the next identification start (below).

Only what a scene asks for is added: encoder quantisation (``position_resolution``),
Coulomb friction (``coulomb``), Gaussian sensor noise (``noise``, seeded), the velocity
sensor's quantum and noise (``velocity_resolution``, ``velocity_noise``: VELOCITY frames,
sent only when the host asks, PROTOCOL.md §4), the force clamp
(``force_limit``) and the excitation (``x0``, ``v0``, a force ``impulse``, a recorded hand
force ``profile``).

n degrees of freedom
--------------------
The mock of a 2-D or 3-D scene's device on a port (:class:`MockDeviceND`, its physics
:class:`PhysicsND`). The framed protocol carries n axes as it is
(``firmware_protocol/PROTOCOL.md`` §4: HELLO announces ``n_axes``; STATE and FORCE carry
``f64[n]``, their length implying n; the golden vectors hold 2-, 3- and 8-axis frames),
so nothing new goes on the wire: this device says
``n_axes = n`` in HELLO, sends the handle's Cartesian position [m] in STATE and applies the
FORCE's Cartesian force [N] (a device that does its kinematics itself; a joint-level board
such as the Haply 2DIY is driven through its own driver).

Its physics (:class:`PhysicsND`) is the device of :mod:`hapsim.lockstep`: a pantograph or
a delta integrates its joint-space dynamics (:class:`hapsim.joint_device.LocalJointDeviceND`:
the configuration-dependent inertia, joint friction, the torques ``J^T F`` held over the
period, the kinematics to second order about the operating point, compiled: tens of
microseconds a tick, ``tools/bench_joint_nd.py``),
a cartesian device the exact zero-order hold of its Cartesian mass and friction.
Device duties are the 1-D mock's own code (:class:`MockDevice`, whose
force hooks this device gives n axes, and whose serving loop
:func:`hapsim.emulated.serve.serve_fd` runs it): FORCE ``n`` applied at tick ``n + d`` when it
arrived in time, else the last force held (``late``, STATUS_OVERRUN, ``force_seq`` naming the
force held), the watchdog zeroing it, STOP, PING.

The hand: at the ``k``-th CONFIG since the device's last HELLO (on connect or answering
HELLO_REQUEST) it lets the handle go from start ``k mod (2n + 1)`` of
:func:`hapsim.lockstep.excitation_starts` (rest; displaced by ``a`` along each axis;
moving at ``a / (10 T)`` along each), ``a`` the mock's amplitude. A host identifying the
felt matrices (:mod:`hapsim.pipeline.felt_port`) asks HELLO and then runs ``2n + 1`` CONFIGs.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

import firmware_protocol as fp
from hapsim.device_model import (DEFAULT_DEVICE, DEFAULT_EXCITATION, MockPhysics,
                                 hand_force_samples, ideal_step_coefficients,
                                 zoh_step_coefficients)
from hapsim.errors import ConfigError
from hapsim.scene import Device, Excitation

__all__ = ["zoh_step_coefficients", "ideal_step_coefficients", "hand_force_samples",
           "MockPhysics", "MockDevice", "MockStats", "MOCK_DEVICE_ID", "DEFAULT_DEVICE",
           "DEFAULT_EXCITATION", "PhysicsND", "MockDeviceND", "DEFAULT_AMPLITUDE",
           "require_whole_delay"]

#: HELLO.device_id of the mock ("MOCK" in ASCII).
MOCK_DEVICE_ID = 0x4D4F434B

#: The longest idle time [s] a re-configured handle is advanced over (module notes, 'One
#: handle'): a host silent for longer finds it where a minute took it.
_IDLE_MAX_S = 60.0

# the protocol's status bits, read once per tick (module constants: no lookup in fp)
_APPLIED = fp.STATUS_FORCE_APPLIED
_OVERRUN = fp.STATUS_OVERRUN
_WATCHDOG = fp.STATUS_WATCHDOG_TRIPPED
_CLAMPED = fp.STATUS_FORCE_CLAMPED
_ARMED_CONFIGURED = fp.STATUS_ARMED | fp.STATUS_CONFIGURED
_SENSOR_VELOCITY = fp.SENSOR_VELOCITY


def require_whole_delay(delay: float, *, file: str | None = None, command: str = "run"
                        ) -> None:
    """Refuse a device delay the real-time mock cannot give: its delay line is whole
    periods (each FORCE applied at a tick after the one it answers), so ``d < 1`` would
    need a force before its tick. Said before the mock starts (the mock refuses it too,
    in its own process, where the host saw only its port close).

    Parameters
    ----------
    delay : float
        The device's delay ``d`` [periods].
    file : str, optional
        The scene it came from (named in the error).
    command : str
        The command refused (``"run"``, ``"identify"``), for what to give instead.

    Raises
    ------
    ConfigError
        ``d < 1`` (``d = 0``: "exists in lockstep only"), keyed ``device.delay``.
    """
    if float(delay) == 0:
        raise ConfigError("device delay d = 0 (force applied at once) exists in lockstep "
                          f"only; a real-time {command} needs d >= 1", file=file,
                          key="device.delay")
    if float(delay) < 1:
        # (--driver only where the command takes it: zwidth measures hapsim's mock)
        board = ("; a driver's board such as the FireFader's takes d < 1 from its own "
                 "timing: --driver" if command in ("run", "identify") else "")
        raise ConfigError(f"device delay d = {float(delay):g} < 1 period: hapsim's mock "
                          "applies each FORCE at a tick after the one it answers, so a "
                          f"real-time {command} needs d >= 1 (or --lockstep{board})",
                          file=file, key="device.delay")


# --------------------------------------------------------------------------- physics

#: The hand's default amplitude ``a`` [m] (as ``hapsim run --lockstep`` on n-D scenes:
#: the scenes' Euclidean links depart from their linearisation by ~1e-7 there).
DEFAULT_AMPLITUDE = 1e-8


def _nd_models():
    """The models an n-DoF mock runs on (:mod:`hapsim.analysis.ths`,
    :mod:`hapsim.joint_device`, :mod:`hapsim.lockstep`), imported on first use: a 1-D
    mock's process does not load them (the n-D engine and its kernels come with them)."""
    from hapsim import joint_device, lockstep
    from hapsim.analysis import ths
    return ths, joint_device, lockstep


class PhysicsND:
    """The device of an n-D scene advanced one sample period at a time.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a device.
    x0, v0 : array_like, shape (n,)
        Initial displacement from the rest position [m] and velocity [m/s].
    joint_space : bool
        A pantograph or delta integrates its joint-space dynamics
        (:class:`hapsim.joint_device.LocalJointDeviceND`); False, or a cartesian device: the
        exact ZOH of the Cartesian mass at rest (:func:`hapsim.analysis.ths.zoh_matrices`).

    Attributes
    ----------
    n : int
        Ticks advanced since the start (the next STATE's seq).
    """

    def __init__(self, scene, x0, v0, joint_space: bool = True) -> None:
        dev = scene.device
        self.dim = scene.dimension
        self.rest = np.asarray(dev.position, float).copy()
        self.n = 0
        x0 = np.asarray(x0, float)
        v0 = np.asarray(v0, float)
        ths, joint_device, _ = _nd_models()
        self.joint = None
        self.split = float(dev.delay) % 1.0
        if joint_space and dev.joints is not None:
            if self.split > 0:
                raise ConfigError(f"a sub-sample delay ({float(dev.delay):g} periods) is "
                                  "modelled on the Cartesian device; the joint-space model "
                                  "applies whole periods: use a whole delay or the "
                                  "Cartesian model", file=scene.path, key="device.delay")
            self.joint = joint_device.LocalJointDeviceND(scene, x0, v0)
        else:
            lm = ths.MatrixLoop(mass=dev.mass, friction=dev.friction,
                                rate_hz=scene.rate_hz, delay=dev.delay)
            self.Ad, self.Bd = ths.zoh_matrices(lm)
            if self.split > 0:        # the split hold (ths.split_hold_matrices)
                _, self._G0, self._G1 = ths.split_hold_matrices(lm)
                self._held = np.zeros(self.dim)
        self.state = np.concatenate([x0, v0])

    def sample(self) -> tuple:
        """The handle's position [m] at the current tick, as a tuple of n floats."""
        if self.joint is not None:
            return tuple(float(v) for v in self.joint.position())
        return tuple(float(v) for v in self.rest + self.state[:self.dim])

    def advance(self, u) -> None:
        """Hold the force ``u`` [N] (shape (n,)) over one period and advance."""
        if self.joint is not None:
            self.joint.step(u)
        elif self.split > 0:      # the previous force over the first f T, then u
            u = np.asarray(u, float)
            self.state = self.Ad @ self.state + self._G0 @ u + self._G1 @ self._held
            self._held = u
        else:
            self.state = self.Ad @ self.state + self.Bd @ np.asarray(u, float)
        self.n += 1


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
            Every attribute of the class by name, in their order (``faults`` copied).
        """
        return dataclasses.asdict(self)


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
        if not self.lockstep:
            require_whole_delay(device.delay, command="mock")
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
        # the handle's plant across CONFIGs (module notes, 'One handle'): the last plant
        # configured and the device time [us] of its last tick; None until a first CONFIG
        # and after new_hand()
        self._plant = None
        self._plant_us = 0
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
    #: The force held when none is due [N]; an n-axis mock (:class:`MockDeviceND`)
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
        plant = MockPhysics(self.device, self.rate_hz, self.excitation,
                            seed=self.seed, base_dir=self.base_dir, hand=hand)
        prev = self._plant
        if prev is not None and not self.lockstep:
            # the same handle: where it went while no tick ran (disarmed by STOP, a reset,
            # a vanished port) at zero force, whole periods from the end of its last tick
            idle = round((now_us - self._plant_us) * 1e-6 / prev.period) - 1
            plant.carry_on(prev, min(max(idle, 0), int(_IDLE_MAX_S / prev.period)))
        self.physics = self._plant = plant
        self._plant_us = now_us
        return self._armed(now_us)

    def new_hand(self) -> None:
        """A new host's hand takes the handle: the next CONFIG starts the scene's
        excitation again (``x0``, ``v0``, the hand force from ``t = 0``) instead of carrying
        on the plant (module notes, 'One handle'). The serving loop calls it when a host
        hangs up (:func:`hapsim.emulated.serve.serve_fd`, ``persistent``)."""
        self._plant = None

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
        # the tick's status bits, gathered here and stored once (_status_extra)
        applied = self._status_extra & _APPLIED
        extra = 0
        if due < 0:
            f, seq, applied = self._zero, 0, 0
        else:
            i = due % self._ring
            if self._rs[i] == due:
                f, seq, applied = self._rf[i], due, _APPLIED
            else:
                self.stats.late += 1
                extra = _OVERRUN
                f, seq = self._applied, self._applied_seq
        extra |= applied
        if (not self.lockstep and self.watchdog_us > 0
                and now_us - self._last_force_us > self.watchdog_us):
            f = self._zero
            self.stats.watchdog_trips += 1
            extra |= _WATCHDOG
        f, clamped = self._clamp(f, self.force_limit)
        if clamped:
            self.stats.clamped += 1
            extra |= _CLAMPED
        self._status_extra = extra
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
        status = _ARMED_CONFIGURED | self._status_extra
        # the velocity sensor reads the same instant as the encoder: v(nT), exact
        self.velocity_out = (fp.Velocity(n & 0xFFFFFFFF, (ph.sample_velocity(),))
                             if self.sensors & _SENSOR_VELOCITY else None)
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
        self._plant_us = now_us
        return state


# ------------------------------------------------------------------- an n-DoF device
class MockDeviceND(MockDevice):
    """The framed protocol's device side for an n-D scene (module notes); I/O-free.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device (``device.delay`` is ``d``).
    amplitude : float
        The hand's amplitude ``a`` [m] (> 0).
    native_rate_hz : float, optional
        Rate announced in HELLO [Hz] (default the scene's).
    lockstep : bool
        One period per FORCE (True) or ticks on a clock (:meth:`tick`).
    joint_space : bool
        :class:`PhysicsND`'s choice.

    Raises
    ------
    ConfigError
        No device; ``d = 0`` in real time; a bad amplitude.
    """

    def __init__(self, scene, amplitude: float = DEFAULT_AMPLITUDE, *,
                 native_rate_hz: float | None = None, lockstep: bool = False,
                 joint_space: bool = True) -> None:
        if scene.device is None or scene.port is None:
            raise ConfigError("the n-D mock needs a port and a device section",
                              file=scene.path, key="device")
        if not (math.isfinite(amplitude) and amplitude > 0):
            raise ConfigError(f"must be a positive number [m], got {amplitude}",
                              key="--amplitude")
        self.scene = scene
        self.dim = scene.dimension
        self.amplitude = float(amplitude)
        self.joint_space = bool(joint_space)
        self.native_rate_hz = float(native_rate_hz or scene.rate_hz)
        self.lockstep = bool(lockstep)
        self.delay = int(scene.device.delay)
        if not self.lockstep:
            require_whole_delay(scene.device.delay, file=scene.path, command="mock")
        self._zero = (0.0,) * self.dim
        _nd_models()          # imported now, not while the first CONFIG waits for its answer
        self._init_protocol(math.inf)
        #: CONFIGs accepted since the last HELLO (which start the hand takes)
        self.configs_since_hello = 0

    def hello(self) -> fp.Hello:
        """HELLO: version 1, ``n_axes = n``, device id :data:`MOCK_DEVICE_ID`, scales 0,
        no force limit (1e300), the native rate. Restarts the hand's cycle."""
        self.configs_since_hello = 0
        return fp.Hello(fp.PROTOCOL_VERSION, self.dim, MOCK_DEVICE_ID, 0.0, 0.0, 1e300,
                        self.native_rate_hz)

    @property
    def sensors_offered(self) -> int:
        """No extra sensors (0)."""
        return 0

    # the force's axes: a tuple of n forces [N] (MockDevice's hooks)
    def _force_value(self, msg: fp.Force):
        f = tuple(msg.force)
        return f if len(f) == self.dim else None

    @staticmethod
    def _is_finite(f) -> bool:
        return all(math.isfinite(v) for v in f)

    @staticmethod
    def _clamp(f, lim: float):
        if any(v > lim or v < -lim for v in f):
            return tuple(max(-lim, min(lim, v)) for v in f), True
        return f, False

    @staticmethod
    def _first(f) -> float:
        return float(f[0])

    def _position(self, ph) -> tuple:
        return ph.sample()

    def _on_config(self, msg: fp.Config, now_us: int) -> list:
        if not self._config_ok(msg):
            self.stats.faults.append("BAD_CONFIG")
            return [fp.Fault(fp.FAULT_BAD_CONFIG, 0)]
        self.rate_hz = float(msg.rate_hz)
        # the physics at the CONFIG's period (the host's rate, which may be another than
        # the scene's: hapsim run --rate)
        scene = (self.scene if self.rate_hz == self.scene.rate_hz
                 else dataclasses.replace(self.scene, rate_hz=self.rate_hz))
        self.watchdog_us = int(msg.watchdog_us)
        self.force_limit = float(msg.force_limit)
        starts = _nd_models()[2].excitation_starts(self.dim, self.amplitude,
                                                   1.0 / self.rate_hz)
        x0, v0 = starts[self.configs_since_hello % len(starts)]
        self.configs_since_hello += 1
        self.physics = PhysicsND(scene, x0, v0, joint_space=self.joint_space)
        return self._armed(now_us)
