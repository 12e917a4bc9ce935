"""The device model: the real side of the THS, one period at a time.

``m x'' + b0 x' = u(t) + f_ext(t)`` with the commanded force ``u`` held constant over each
period (zero-order hold), integrated *exactly* from tick to tick with the closed form of
:func:`zoh_step_coefficients` (written here independently of
:func:`hapsim.analysis.loop.zoh_state_space`; the tests compare both with
``scipy.linalg.expm`` of the augmented matrix). With ``hold: ideal`` the model is the
paper's idealised sampled image instead, a centred-difference mass with the friction form of
Florens, Voda & Urma eq. (4)::

    x[n+1] = (1 + a) x[n] - a x[n-1] + psi T^2/m u[n],   a = e^(-b0 T/m),
    psi = (1 - a) / (b0 T / m)                            (psi = 1 when b0 = 0)

Only what a scene asks for is added: encoder quantisation, Coulomb friction, Gaussian sensor
noise, the hand on the handle and the excitation (``x0``, ``v0``, a force ``impulse``, a
recorded hand force ``profile``).

Below the daemon, the drivers and the sound: the protocol mock
(:mod:`hapsim.emulated.mock`), the vendor drivers' mocks (:mod:`hapsim.emulated.driver_mock`), the
offline renderer (:mod:`hapsim.audio.offline`) and ``hapsim play`` all advance this one
model.
"""

from __future__ import annotations

import math
import os
from collections import deque
from typing import Callable

import numpy as np

from hapsim.errors import DAMAGED_FILE_ERRORS, ConfigError
from hapsim.scene import Device, Excitation

__all__ = ["zoh_step_coefficients", "ideal_step_coefficients", "hand_force_samples",
           "load_profile", "MockPhysics", "InProcessLoop", "DEFAULT_DEVICE",
           "DEFAULT_EXCITATION"]


#: Device used by ``hapsim mock`` without ``--scene`` (the device of ``configs/wall.yaml``).
DEFAULT_DEVICE = Device(mass=0.1, friction=0.5, delay=1, hold="zoh", force_limit=10.0)



#: Excitation used by ``hapsim mock`` without ``--scene``: 5 mm initial displacement.
DEFAULT_EXCITATION = Excitation(x0=0.005)



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



def load_profile(path: str, column: str = "force", unit: str = "N",
                  key: str = "excitation.profile") -> tuple[np.ndarray, np.ndarray]:
    """Time [s] and ``column`` columns of a ``.csv`` (header allowed) or ``.npz`` profile
    (a 2-D ``.npz`` array: its first column); errors name ``key``.

    Parameters
    ----------
    path : str
        ``.npz`` file with arrays ``time`` and ``column``, or ``.csv`` whose first two
        columns are time [s] and the value (an optional header line, ``#`` comments).
    column : str
        Name of the value (the ``.npz`` array; the messages).
    unit : str
        Unit of the value, for the messages (``"N"``).
    key : str
        Scene key the messages name.

    Returns
    -------
    t : ndarray, shape (n,)
        Sample times [s], strictly increasing.
    f : ndarray, shape (n,)
        The values [``unit``].

    Raises
    ------
    ConfigError
        The file cannot be read or lacks the columns, a value is not finite, or the
        times do not increase strictly (key ``key``).
    """
    import io

    from hapsim.outputs import read_input
    what = f"time [s], {column} [{unit}]"
    # (a FIFO or /dev/zero: refused, not read)
    raw = io.BytesIO(read_input(path, key, what=f"the {column} profile"))
    try:
        if path.lower().endswith(".npz"):
            with np.load(raw) as z:
                t, f = np.asarray(z["time"], float), np.asarray(z[column], float)
            f = f[:, 0] if f.ndim == 2 else f
        else:
            data = np.genfromtxt(raw, delimiter=",", comments="#", ndmin=2)
            if data.shape[0] and not np.all(np.isfinite(data[0])):
                data = data[1:]          # header line
            if data.shape[1] < 2:       # (one column was read as one sample: t, x)
                raise ValueError(f"{data.shape[1]} column(s)")
            t, f = data[:, 0], data[:, 1]
    except DAMAGED_FILE_ERRORS as exc:
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
        prof = load_profile(path)
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



def _coulomb_zoh(x, v, f, C, a, cxv, cxu, cvu):
    """One exact ZOH piece of the mass under the held force ``f`` [N] and Coulomb friction
    ``C`` [N] (0: none), from ``(x, v)`` [m, m/s], with the step's coefficients
    (:func:`zoh_step_coefficients`).

    Returns
    -------
    tuple of float
        The new ``(x, v)``: unchanged when the mass is at rest and ``|f| <= C`` (stuck:
        the force cannot break it loose).

    Notes
    -----
    The friction is held as ``-C sign(v)`` (``-C sign(f)`` from rest); a velocity that
    would change sign within the piece while ``|f| <= C`` sticks (v = 0): first order,
    exact only while the sign of ``v`` does not change (as
    :func:`hapsim.kernels.device_sim._zoh_piece`, its compiled twin).
    """
    fc = 0.0
    if C > 0:
        if v != 0.0:
            fc = -C if v > 0 else C
        elif abs(f) > C:
            fc = -C if f > 0 else C
        else:
            return x, v
    ft = f + fc
    vn = a * v + cvu * ft
    xn = x + cxv * v + cxu * ft
    if C > 0 and v != 0.0 and vn * v < 0 and abs(f) <= C:
        vn = 0.0
    return xn, vn


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
    split : float
        The fraction ``f`` of a sub-sample ``device.delay = m + f`` (0 for a whole delay):
        :meth:`advance` holds the previous force over the first ``f T`` of the period and
        the new one over the rest (the split hold, :mod:`hapsim.analysis.subsample`); the
        whole ``m`` is the protocol's delay line.

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
        self._mass, self._friction = mass, friction     # advance_interval's own steps
        if self._grip is not None:         # compliant grip or the arm's spring: state space
            import scipy.linalg
            p = self._grip.shape[0]
            A = np.zeros((p + 1, p + 1))
            A[:p, :p], A[1, p] = self._grip, 1.0 / mass
            E = scipy.linalg.expm(A * T)
            self._Ad, self._Bd = E[:p, :p], E[:p, p]
            self._A = A
            if self.hold == "ideal":       # impulses T f at nT: Bd = T e^(AT) b
                self._Bd = T * self._Ad[:, 1] / mass
            self._s = np.tile(np.array([exc.x0, exc.v0], dtype=float), p // 2)
        # a sub-sample delay m + f (hapsim.analysis.subsample): the device applies each
        # force f T into the period, after holding the previous one; the whole m is the
        # protocol's delay line (int(device.delay)), the fraction is the physics'
        self.split = float(getattr(device, "delay", 0)) % 1.0
        self._held = 0.0
        if self.split > 0:
            if self.hold != "zoh":
                raise ConfigError("a fractional delay needs hold: zoh", key="device.delay")
            if self._grip is not None:
                self._sub = []
                for tau in (self.split * T, (1.0 - self.split) * T):
                    E = scipy.linalg.expm(A * tau)
                    self._sub.append((E[:p, :p], E[:p, p]))
            else:
                self._sub = [zoh_step_coefficients(mass, friction, tau)
                             for tau in (self.split * T, (1.0 - self.split) * T)]
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
    def hand(self) -> np.ndarray:
        """Hand force per period [N], shape ``(n_ticks,)`` (:func:`hand_force_samples`).

        Set it as a whole (not element by element): the per-tick paths read a copy as
        Python floats, kept with it. An element of the array is a numpy scalar, and a
        numpy scalar added to the held force made the whole state (``x``, ``v``, the
        encoder's sample, the STATE's position, the host's arithmetic on it) numpy scalars
        from the first tick with a hand force on, ~10x slower per operation than floats
        for the same IEEE-754 binary64 operations (the same bits)."""
        return self._hand

    @hand.setter
    def hand(self, value) -> None:
        self._hand = value
        self._hand_f = [float(h) for h in value]

    @property
    def step_coefficients(self) -> dict:
        """The one-body step's coefficients by name, for a compiled twin of :meth:`advance`.

        Returns
        -------
        dict of str to float
            ``"zoh"`` hold: ``a``, ``cxv``, ``cxu``, ``cvu`` of
            ``v' = a v + cvu f``, ``x' = x + cxv v + cxu f``
            (:func:`zoh_step_coefficients`); ``"ideal"``: ``a``, ``cu`` of
            ``x' = (1 + a) x - a x_prev + cu f`` (:func:`ideal_step_coefficients`). With
            a compliant grip or an arm spring (:attr:`state_space`) :meth:`advance` steps
            the state-space plant instead and these are not used.
        """
        if self.hold == "zoh":
            return {"a": self._a, "cxv": self._cxv, "cxu": self._cxu, "cvu": self._cvu}
        return {"a": self._a, "cu": self._cu}

    @property
    def position_resolution(self) -> float:
        """The encoder's step [m] the sampled position is rounded to (0.0: none)."""
        return self._q

    @property
    def coulomb(self) -> float:
        """Coulomb friction force [N] on the one-body zoh path (0.0: none)."""
        return self._coulomb

    @property
    def noisy(self) -> bool:
        """Whether the sampled position carries sensor noise (a random stream)."""
        return self._rng is not None

    @property
    def state_space(self) -> bool:
        """Whether the plant is the hand grip's or the arm spring's state space rather than
        the one body."""
        return self._grip is not None

    @property
    def previous_position(self) -> float:
        """The position one period ago, ``x[n-1]`` [m] (the ideal hold's recurrence); a
        compiled twin that advanced the plant sets it back with :attr:`x` and :attr:`v`."""
        return self._xprev

    @previous_position.setter
    def previous_position(self, value: float) -> None:
        self._xprev = float(value)

    def carry_on(self, prev: "MockPhysics", idle: int) -> None:
        """Take over the plant of ``prev``, a handle that was left alone for ``idle`` whole
        periods (zero commanded force) since its last tick: a device re-configured keeps
        its handle where its physics took it, moving as it moved, and its hand where the
        hand is in its own time (this object's rate may differ from ``prev``'s).

        ``prev`` advances ``idle`` periods at zero force (the hand force of its own
        periods added, :meth:`advance`), then this plant takes its state (position,
        velocity, the previous position of the ideal hold, a grip's or arm spring's state,
        the split hold's held force, the sensor-noise streams) and its hand from the same
        instant: ``prev``'s own hand from its tick ``prev.n`` on at the same rate; at
        another, this plant's hand (the scene's, sampled at its rate) from
        ``round(t / T)``, ``t = prev.n prev.period`` the time ``prev`` reached, ``T`` this
        plant's period. Its tick counter stays at 0 (a CONFIG restarts
        the protocol's seq, PROTOCOL.md §10).

        Parameters
        ----------
        prev : MockPhysics
            The plant until now (it is advanced in place).
        idle : int
            Whole periods of ``prev`` the handle was left alone (>= 0).

        Raises
        ------
        ValueError
            ``idle`` negative, or ``prev`` and this plant of different kinds (one with a
            grip's state space, the other without).
        """
        if idle < 0:
            raise ValueError(f"idle must be >= 0 periods, got {idle}")
        if (prev._grip is None) != (self._grip is None):
            raise ValueError("the plants differ in kind (a grip's state space in one only)")
        for _ in range(idle):
            prev.advance(0.0)
        self.x, self.v, self._xprev = prev.x, prev.v, prev._xprev
        if prev._grip is not None:
            self._s = prev._s.copy()
        self._held = prev._held
        self._rng, self._vrng = prev._rng, prev._vrng
        if prev.period == self.period:          # the same hand, from where it is
            self.hand = np.asarray(prev.hand)[prev.n:]
        else:                                   # the scene's hand at this rate, same instant
            self.hand = np.asarray(self.hand)[int(round(prev.n * prev.period / self.period)):]

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
        if self.split > 0:
            self._advance_split(u)
            return
        n = self.n
        hand = self._hand_f
        f = u + (hand[n] if n < len(hand) else 0.0)
        if self._grip is not None:
            s = self._Ad @ self._s + self._Bd * f
            self._s = s
            self.x, self.v = float(s[0]), float(s[1])
        elif self.hold == "zoh":
            self.x, self.v = _coulomb_zoh(self.x, self.v, f, self._coulomb, self._a,
                                          self._cxv, self._cxu, self._cvu)
        else:
            x, xp = self.x, self._xprev
            xn = (1.0 + self._a) * x - self._a * xp + self._cu * f
            self._xprev = x
            self.x = xn
            self.v = (xn - x) / self.period
        self.n = n + 1


    def advance_interval(self, tau: float, u: float) -> None:
        """Advance ``tau`` seconds (any length within the current period) with the force
        ``u`` [N] held: a device on the wall clock, whose force changes when a packet
        arrives, not at a period boundary (:class:`hapsim.emulated.driver_mock.WallClock`).

        Parameters
        ----------
        tau : float
            Interval [s], ``0 <= tau``; the caller splits intervals at period boundaries
            (the hand force is the current period's, ``hand[n]``) and ends a period with
            :meth:`end_period`.
        u : float
            Force held over the interval [N].

        Raises
        ------
        ConfigError
            With the ideal hold (impulses at the sample instants have no meaning between
            them).

        Notes
        -----
        The exact ZOH solution over ``tau`` (:func:`zoh_step_coefficients` with the period
        ``tau``; ``expm`` of the augmented state-space plant with a grip or an arm spring),
        Coulomb friction per interval as in :meth:`advance`. A period cut into intervals
        equals one :meth:`advance` of the whole period with the same held force to round-off
        (the semigroup property of the exact solution).
        """
        if tau <= 0.0:
            return
        if self.hold != "zoh":
            raise ConfigError("a device on the wall clock needs hold: zoh (the ideal hold's "
                              "impulses act at sample instants only)", key="device.hold")
        n = self.n
        hand = self._hand_f
        f = u + (hand[n] if n < len(hand) else 0.0)
        if self._grip is not None:
            import scipy.linalg
            p = self._grip.shape[0]
            E = scipy.linalg.expm(self._A * tau)
            self._s = E[:p, :p] @ self._s + E[:p, p] * f
            self.x, self.v = float(self._s[0]), float(self._s[1])
            return
        self.x, self.v = _coulomb_zoh(self.x, self.v, f, self._coulomb,
                                      *zoh_step_coefficients(self._mass, self._friction, tau))

    def end_period(self) -> None:
        """A period boundary passed on the wall clock (:meth:`advance_interval`): the next
        period's hand force applies."""
        self.n += 1

    def hold_now(self, u: float) -> None:
        """The device sets the force it holds itself, now (a firmware's silence rule).

        Parameters
        ----------
        u : float
            The force held from now [N]: with a sub-sample delay the next period's first
            ``f T`` holds it too (nothing changes for a whole delay).
        """
        self._held = float(u)

    def _advance_split(self, u: float) -> None:
        """:meth:`advance` for a sub-sample delay ``m + f``: the force held before (the
        previous ``u``) over the first ``f T``, then ``u`` over the last ``(1 - f) T``,
        each sub-interval integrated exactly (Coulomb friction as in :meth:`advance`, per
        sub-interval); the hand force of the tick acts over the whole period."""
        n = self.n
        hand = self._hand_f
        h = hand[n] if n < len(hand) else 0.0
        for (co, force) in zip(self._sub, (self._held, u)):
            f = force + h
            if self._grip is not None:
                Ad, Bd = co
                self._s = Ad @ self._s + Bd * f
                self.x, self.v = float(self._s[0]), float(self._s[1])
                continue
            self.x, self.v = _coulomb_zoh(self.x, self.v, f, self._coulomb, *co)
        self._held = u
        self.n = n + 1


class InProcessLoop:
    """The device model closed on a force law in this process, one sample at a time: the
    THS without a protocol (``hapsim play``, the offline pluck of
    :func:`hapsim.audio.offline.closed_loop_pluck`).

    Each :meth:`step` samples the device's position ``x[n]``, asks ``force_of(x[n])`` for
    the port force (an :meth:`hapsim.engine.Engine.port_step`, or a live sound source's),
    and has the device apply the force computed ``d`` samples earlier, clamped to
    ``force_limit``, over the coming period: FORCE ``n`` is applied over
    ``[(n+d)T, (n+d+1)T)``, zeros before the first ``d`` forces
    (docs/design.md, 'The timing convention').

    Parameters
    ----------
    physics : MockPhysics
        The device model (its excitation and hand force included).
    force_of : callable
        ``force_of(position [m]) -> force [N]``, called once per sample.
    delay : int
        ``d`` [samples], >= 0.
    force_limit : float
        Clamp of the applied force [N] (inf: none).
    """

    def __init__(self, physics: MockPhysics, force_of: Callable[[float], float], delay: int,
                 force_limit: float) -> None:
        self.physics = physics
        self.force_of = force_of
        self._line = deque([0.0] * int(delay))
        self._limit = float(force_limit)

    def step(self, scale: float = 1.0) -> tuple[float, float]:
        """One sample of the closed loop.

        Parameters
        ----------
        scale : float
            Factor on the computed force (a ramp of live changes); 1 by default.

        Returns
        -------
        x : float
            The device position sampled [m].
        f : float
            The port force computed from it [N] (scaled, before the delay and the clamp).
        """
        x = self.physics.sample()
        f = self.force_of(x) * scale
        self._line.append(f)
        u = self._line.popleft()
        lim = self._limit
        self.physics.advance(min(lim, max(-lim, u)))
        return x, f
