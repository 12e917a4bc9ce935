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

import numpy as np

import firmware_protocol as fp
from hapsim.daemon.loop import StopFlag
from hapsim.errors import ConfigError
from hapsim.scene import Device, Excitation

__all__ = ["zoh_step_coefficients", "ideal_step_coefficients", "hand_force_samples",
           "MockPhysics", "MockDevice", "MockStats", "serve_fd", "MOCK_DEVICE_ID",
           "DEFAULT_DEVICE", "DEFAULT_EXCITATION"]

#: HELLO.device_id of the mock ("MOCK" in ASCII).
MOCK_DEVICE_ID = 0x4D4F434B
#: Device used by ``hapsim mock`` without ``--scene`` (the device of ``configs/wall.yaml``).
DEFAULT_DEVICE = Device(mass=0.1, friction=0.5, delay=1, hold="zoh", force_limit=10.0)
#: Excitation used by ``hapsim mock`` without ``--scene``: 5 mm initial displacement.
DEFAULT_EXCITATION = Excitation(x0=0.005)
#: Real-time ticks: the mock waits in ``select`` until this long before each deadline and
#: reads the host's bytes in a loop for the rest [ns]. 0: no spin (the wait ends at the
#: deadline; select's timeout is exact to the timer under SCHED_FIFO, whose timer slack is
#: 0). A spin to each deadline made the mock, a SCHED_FIFO process, throttled under load.
#: Above this native rate [Hz] ``serve_fd(tick="auto")`` ticks in numba; at and below it in
#: Python (the compiled tick's loading delays the HELLO by 0.5-1 s; 1 kHz runs do not need it).
AUTO_COMPILED_HZ = 2000.0
MOCK_SPIN_NS = 0


# --------------------------------------------------------------------------- physics

def _series_psi_phi1(y: float) -> tuple[float, float]:
    """``psi = (1 - e^-y)/y`` and ``phi1 = (e^-y - 1 + y)/y^2`` by their Taylor series."""
    psi = 0.0
    phi1 = 0.0
    term = 1.0            # (-y)^j / j!
    for j in range(30):
        psi += term / (j + 1)
        phi1 += term / ((j + 1) * (j + 2))
        term *= -y / (j + 1)
        if abs(term) < 1e-20:
            break
    return psi, phi1


def zoh_step_coefficients(mass: float, friction: float, period: float):
    """Coefficients of one exact ZOH step of ``m x'' + b0 x' = u`` (u held over the period).

    Parameters
    ----------
    mass : float
        Moving mass m [kg], > 0.
    friction : float
        Viscous friction b0 [N s/m], >= 0.
    period : float
        Period T [s], > 0.

    Returns
    -------
    tuple of float
        ``(a, c_xv, c_xu, c_vu)`` such that over one period
        ``x' = x + c_xv v + c_xu u`` and ``v' = a v + c_vu u``, with ``y = b0 T/m``,
        ``a = e^-y`` [-], ``c_xv = T (1 - e^-y)/y`` [s], ``c_xu = T^2/m (e^-y - 1 + y)/y^2``
        [m/N], ``c_vu = T/m (1 - e^-y)/y`` [m/(N s)] (limits ``T``, ``T^2/(2m)``, ``T/m``
        at ``b0 = 0``).

    Raises
    ------
    ConfigError
        On a non-positive mass or period or a negative friction.

    Notes
    -----
    Solution of ``v' = -(b0/m) v + u/m`` and ``x' = v`` with ``u`` constant (variation of
    constants); the small-``y`` branch (``y < 1e-2``) uses the Taylor series of ``psi`` and
    ``phi1`` so no cancellation occurs. Matches ``expm([[A, B], [0, 0]] T)`` to ~1e-15.
    """
    m, b0, T = float(mass), float(friction), float(period)
    if not (m > 0 and T > 0 and b0 >= 0):
        raise ConfigError(f"need mass > 0, friction >= 0, period > 0; got m={mass!r}, "
                          f"b0={friction!r}, T={period!r}")
    y = b0 * T / m
    if y < 1e-2:
        psi, phi1 = _series_psi_phi1(y)
    else:
        em1 = math.expm1(-y)          # e^-y - 1
        psi = -em1 / y
        phi1 = (em1 + y) / (y * y)
    a = math.exp(-y)
    return a, T * psi, T * T / m * phi1, T / m * psi


def ideal_step_coefficients(mass: float, friction: float, period: float):
    """Coefficients of the paper's idealised sampled mass (Florens et al. eqs. (2)-(4)).

    Parameters
    ----------
    mass, friction, period : float
        m [kg] > 0, b0 [N s/m] >= 0, T [s] > 0.

    Returns
    -------
    tuple of float
        ``(a, c_u)`` with ``x[n+1] = (1 + a) x[n] - a x[n-1] + c_u u[n]``, ``a = e^-y``,
        ``c_u = T^2/m (1 - e^-y)/y`` [m/N], ``y = b0 T / m``.

    Raises
    ------
    ConfigError
        As :func:`zoh_step_coefficients`.
    """
    m, b0, T = float(mass), float(friction), float(period)
    if not (m > 0 and T > 0 and b0 >= 0):
        raise ConfigError(f"need mass > 0, friction >= 0, period > 0; got m={mass!r}, "
                          f"b0={friction!r}, T={period!r}")
    y = b0 * T / m
    psi = _series_psi_phi1(y)[0] if y < 1e-2 else -math.expm1(-y) / y
    return math.exp(-y), T * T / m * psi


def _load_profile(path: str, column: str = "force", unit: str = "N",
                  key: str = "excitation.profile") -> tuple[np.ndarray, np.ndarray]:
    """Time [s] and ``column`` columns of a ``.csv`` (header allowed) or ``.npz`` profile
    (a 2-D ``.npz`` array: its first column); errors name ``key``."""
    what = f"time [s], {column} [{unit}]"
    try:
        if path.lower().endswith(".npz"):
            with np.load(path) as z:
                t, f = np.asarray(z["time"], float), np.asarray(z[column], float)
            f = f[:, 0] if f.ndim == 2 else f
        else:
            data = np.genfromtxt(path, delimiter=",", comments="#")
            if data.ndim == 2 and not np.all(np.isfinite(data[0])):
                data = data[1:]          # header line
            data = np.atleast_2d(data)
            t, f = data[:, 0], data[:, 1]
    except (OSError, KeyError, ValueError, IndexError) as exc:
        raise ConfigError(f"cannot read the {column} profile {path}: {exc}; expected "
                          f"columns {what}", key=key) from None
    if t.size < 1 or t.shape != f.shape or not (np.all(np.isfinite(t)) and np.all(np.isfinite(f))):
        raise ConfigError(f"profile needs finite columns {what}", key=key)
    if np.any(np.diff(t) <= 0):
        raise ConfigError("profile times must increase strictly", key=key)
    return t, f


def hand_force_samples(excitation: Excitation, period: float,
                       base_dir: str | None = None) -> np.ndarray:
    """The hand force of the excitation, one value per period [N].

    Parameters
    ----------
    excitation : Excitation
        The scene's excitation (``impulse`` and ``profile`` are used here).
    period : float
        Tick period T [s].
    base_dir : str, optional
        Directory a relative ``profile`` path is resolved against.

    Returns
    -------
    ndarray, shape (n_ticks,)
        Element ``n`` is the force held over ``[nT, (n+1)T)``: for the impulse, its mean over
        the period (exact when ``start`` and ``duration`` are multiples of T); for the
        profile, the profile linearly interpolated at the middle of the period (zero after
        its last time). Empty when there is no hand force.

    Raises
    ------
    ConfigError
        When the profile cannot be read.
    """
    T = float(period)
    n = 0
    imp = excitation.impulse
    prof = None
    if imp is not None and imp.duration > 0 and imp.force != 0:
        n = max(n, int(math.ceil((imp.start + imp.duration) / T - 1e-9)))
    if excitation.profile:
        path = excitation.profile
        if base_dir and not os.path.isabs(path):
            path = os.path.join(base_dir, path)
        prof = _load_profile(path)
        n = max(n, int(math.ceil(prof[0][-1] / T - 1e-9)) + 1)
    out = np.zeros(n)
    if imp is not None and imp.duration > 0 and imp.force != 0:
        a, b = imp.start, imp.start + imp.duration
        for i in range(n):
            lo, hi = max(a, i * T), min(b, (i + 1) * T)
            if hi > lo:
                out[i] += imp.force * (hi - lo) / T
    if prof is not None:
        mid = (np.arange(n) + 0.5) * T
        out += np.interp(mid, prof[0], prof[1], left=0.0, right=0.0)
    return out


def _body(device: Device, member=None):
    """``(mass, friction, A_grip)`` of the mock's plant: handle + hand as one body, and the
    continuous matrix of a compliant grip (4x4) or of the one body with the hand's
    stiffness to ground (2x2, ``[x, v]``); None when neither. ``mass`` is the body the
    force acts on (the handle alone behind a compliant grip). Without a hand nothing is
    imported: a mock restarted by CONFIG must answer at once."""
    hand = getattr(device, "hand", None)
    if hand is None and member is None:
        return float(device.mass), float(device.friction), None
    from hapsim.analysis.hand import hand_matrices, hand_stiffness, nominal_member
    mem = np.asarray(member if member is not None else nominal_member(hand), float)
    if np.isfinite(mem[2]):
        A, _ = hand_matrices(float(device.mass), float(device.friction), mem)
        return float(device.mass), float(device.friction), A
    m, b = float(device.mass + mem[0]), float(device.friction + mem[1])
    kh = float(hand_stiffness(mem))
    if kh > 0:                                  # m x'' + b x' + kh x = f
        return m, b, np.array([[0.0, 1.0], [-kh / m, -b / m]])
    return m, b, None


class MockPhysics:
    """The real side of the THS, advanced one period at a time.

    Parameters
    ----------
    device : Device
        Mass, friction, hold and the optional imperfections (quantisation, Coulomb, noise).
    rate_hz : float
        Tick rate [Hz], > 0.
    excitation : Excitation, optional
        Initial displacement/velocity and hand force.
    seed : int, optional
        Seed of the sensor-noise generator (numpy ``default_rng``).
    base_dir : str, optional
        Directory relative profile paths are resolved against.
    hand : ndarray, optional
        Precomputed :func:`hand_force_samples` (a device restarted by CONFIG reuses it).
    member : array_like, shape (4,), optional
        The member ``(mh, bh, kg, bg[, kh])`` of ``device.hand`` to simulate (default its nominal
        member, :func:`hapsim.analysis.hand.nominal_member`). A rigid grip adds the hand's
        mass and damping to the handle's; a compliant one makes the plant
        ``[xh, vh, xm, vm]``, advanced exactly by ``expm([[A, b], [0, 0]] T)``; the hand's
        stiffness to ground (``kh``) puts a real spring on the hand (on the one body when
        rigid: ``[x, v]`` by the same exponential, or ``e^(AT)`` and ``T e^(AT) b`` for
        the ideal hold). Coulomb friction is not modelled on those paths; noise and
        quantisation are.

    Attributes
    ----------
    x : float
        True position at the current tick [m].
    v : float
        Velocity at the current tick [m/s] (``"zoh"``; backward difference for ``"ideal"``).
    n : int
        Current tick.
    hand : ndarray
        Hand force per period [N] (see :func:`hand_force_samples`).

    Raises
    ------
    ConfigError
        On invalid device values or an unreadable profile.
    """

    def __init__(self, device: Device, rate_hz: float, excitation: Excitation | None = None,
                 *, seed: int = 0, base_dir: str | None = None,
                 hand: np.ndarray | None = None, member=None) -> None:
        exc = excitation or Excitation()
        self.device = device
        self.period = T = 1.0 / float(rate_hz)
        self.hold = device.hold
        mass, friction, self._grip = _body(device, member)
        if self._grip is not None:         # compliant grip or the arm's spring: state space
            import scipy.linalg
            p = self._grip.shape[0]
            A = np.zeros((p + 1, p + 1))
            A[:p, :p], A[1, p] = self._grip, 1.0 / mass
            E = scipy.linalg.expm(A * T)
            self._Ad, self._Bd = E[:p, :p], E[:p, p]
            if self.hold == "ideal":       # impulses T f at nT: Bd = T e^(AT) b
                self._Bd = T * self._Ad[:, 1] / mass
            self._s = np.tile(np.array([exc.x0, exc.v0], dtype=float), p // 2)
        if self.hold == "zoh":
            self._a, self._cxv, self._cxu, self._cvu = zoh_step_coefficients(
                mass, friction, T)
        elif self.hold == "ideal":
            self._a, self._cu = ideal_step_coefficients(mass, friction, T)
        else:
            raise ConfigError(f"unknown hold {device.hold!r}; valid: zoh, ideal", key="device.hold")
        self.x = float(exc.x0)
        self.v = float(exc.v0)
        self._xprev = self.x - self.v * T          # ideal hold: x[-1]
        self.n = 0
        self.hand = hand if hand is not None else hand_force_samples(exc, T, base_dir)
        self._q = float(device.position_resolution or 0.0)
        self._coulomb = float(device.coulomb or 0.0)
        self._noise = float(device.noise or 0.0)
        self._rng = np.random.default_rng(seed) if self._noise > 0 else None
        self._vq = float(getattr(device, "velocity_resolution", 0.0) or 0.0)
        self._vnoise = float(getattr(device, "velocity_noise", 0.0) or 0.0)
        # its own stream: the position noise of a seed is the same with or without it
        self._vrng = (np.random.default_rng([seed, 1]) if self._vnoise > 0 else None)

    @property
    def excitation_end(self) -> float:
        """Time after which no hand force acts [s] (0.0 without impulse or profile)."""
        return self.hand.size * self.period

    def sample(self) -> float:
        """Position the encoder reports at the current tick.

        Returns
        -------
        float
            ``x`` [m] plus Gaussian noise of standard deviation ``device.noise`` (seeded),
            then rounded to a multiple of ``device.position_resolution`` when > 0.
        """
        y = self.x
        if self._rng is not None:
            y += self._noise * float(self._rng.standard_normal())
        if self._q > 0:
            y = self._q * round(y / self._q)
        return y

    def sample_velocity(self) -> float:
        """Velocity the velocity sensor reports at the current tick (VELOCITY frames).

        Returns
        -------
        float
            ``v``, the exact velocity at the sample instant [m/s] (the handle's with a
            compliant grip), plus Gaussian noise of standard deviation
            ``device.velocity_noise`` (seeded, its own stream), then rounded to a multiple
            of ``device.velocity_resolution`` when > 0.
        """
        y = self.v
        if self._vrng is not None:
            y += self._vnoise * float(self._vrng.standard_normal())
        if self._vq > 0:
            y = self._vq * round(y / self._vq)
        return y

    def advance(self, u: float) -> None:
        """Advance one period with the force ``u`` [N] held (plus the hand force of this tick).

        Parameters
        ----------
        u : float
            Commanded force held over ``[nT, (n+1)T)`` [N].

        Notes
        -----
        Coulomb friction ``C`` (when asked for) is added as the held force
        ``-C sign(v)`` (``-C sign(u_total)`` from rest); if the velocity would change sign
        within the period while ``|u_total| <= C`` the mass sticks (v = 0). This is a
        first-order model, exact only while the sign of ``v`` does not change in the period.
        """
        n = self.n
        f = u + (self.hand[n] if n < self.hand.size else 0.0)
        if self._grip is not None:
            s = self._Ad @ self._s + self._Bd * f
            self._s = s
            self.x, self.v = float(s[0]), float(s[1])
        elif self.hold == "zoh":
            x, v = self.x, self.v
            fc = 0.0
            if self._coulomb > 0:
                C = self._coulomb
                if v != 0.0:
                    fc = -C if v > 0 else C
                elif abs(f) > C:
                    fc = -C if f > 0 else C
                else:                         # stuck and the force cannot break it loose
                    self.n = n + 1
                    return
            ft = f + fc
            vn = self._a * v + self._cvu * ft
            xn = x + self._cxv * v + self._cxu * ft
            if self._coulomb > 0 and v != 0.0 and vn * v < 0 and abs(f) <= self._coulomb:
                vn = 0.0
            self.x, self.v = xn, vn
        else:
            x, xp = self.x, self._xprev
            xn = (1.0 + self._a) * x - self._a * xp + self._cu * f
            self._xprev = x
            self.x = xn
            self.v = (xn - x) / self.period
        self.n = n + 1


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
        self._ring = max(16, 2 * self.delay + 2)
        self._rf = [0.0] * self._ring
        self._rs = [-1] * self._ring
        self.armed = False
        self.configured = False
        self.physics: MockPhysics | None = None
        self.stats = MockStats()
        self.history: list = []      # the MockStats of each earlier CONFIG (lifetime totals)
        self._hand_cache: dict = {}
        self.trace: list | None = None  # tests: (time_us, applied force [N]) per tick when a list
        #: tests: when a ``collections.deque(maxlen=N)`` (bounded), one
        #: ``(time_us, tick, force_seq, applied force [N], configs)`` per tick, ``configs``
        #: counting the CONFIGs accepted before (the session the tick belongs to)
        self.applied_log = None
        self.rate_hz = self.native_rate_hz
        self.force_limit = float(device.force_limit)
        self.watchdog_us = 0
        self._applied = 0.0
        self._applied_seq = 0
        self._status_extra = 0
        self._last_force_us = 0
        self._u = 0.0
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

    def stop(self) -> None:
        """Zero the force at once and disarm (STOP, or the mock shutting down)."""
        self._applied = 0.0
        self._u = 0.0
        self.armed = False
        self.stats.last_applied = 0.0
        self._rs = [-1] * self._ring

    def _on_config(self, msg: fp.Config, now_us: int) -> list:
        ok = (math.isfinite(msg.rate_hz) and msg.rate_hz > 0 and msg.watchdog_us > 0
              and math.isfinite(msg.force_limit) and msg.force_limit >= 0)
        if not ok:
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
        self.history.append(self.stats)
        self.stats = MockStats(last_host_message="Config")
        self._rs = [-1] * self._ring
        self._applied = 0.0
        self._applied_seq = 0
        self._status_extra = 0          # force_seq restarts: FORCE_APPLIED clear until one is
        self._u = 0.0
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
        f = msg.force[0]
        if not math.isfinite(f):
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
            f, seq, applied = 0.0, 0, 0
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
            f = 0.0
            self.stats.watchdog_trips += 1
            self._status_extra |= fp.STATUS_WATCHDOG_TRIPPED
        lim = self.force_limit
        if f > lim or f < -lim:
            f = lim if f > 0 else -lim
            self.stats.clamped += 1
            self._status_extra |= fp.STATUS_FORCE_CLAMPED
        self._applied = f
        self._applied_seq = seq
        self._u = f
        self.stats.last_applied = f
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
                        (ph.sample(),))

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
        from hapsim.daemon import fastmock
        from hapsim.daemon.startup import preload_numba_blas
        preload_numba_blas()
        fastmock.warm_up_mock()
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
        Faults to inject (:mod:`hapsim.daemon.faults`): wire faults on every frame sent
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
        (:class:`hapsim.daemon.fastmock.CompiledMock`: same bytes, no GIL, absolute-deadline
        sleeps) wherever :func:`~hapsim.daemon.fastmock.compiled_reason` allows (not in
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
    from hapsim.daemon.faults import FaultyDevice

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
                    and fast.reason() is None):
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
