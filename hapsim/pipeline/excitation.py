"""The excitation of ``hapsim identify``: designed from what the device shows, safe for it.

The excitation is a scene-less "engine" for :class:`hapsim.host.loop.HostLoop`: so the
identification runs under the very same loop as ``hapsim run`` -- handshake, CONFIG with the
device watchdog armed, host-side force clamp, the safety stops (force at the limit in half
of the last 100 samples, position beyond the envelope, non-finite values), zero force and
STOP at the end, loss recovery.

Force sent answering the position ``x[n]``::

    f[n] = -Kc (x[n] - x_start) - Bc (x[n] - x[n-1]) / T + r[n]

a weak centring spring-damper, stable for every mass in :data:`MASS_RANGE` and every delay
``0 .. d_max`` (:func:`centring_gains`: the largest ``Kc = 0.5 F_lim / envelope / 2^j``,
half the force limit at the envelope's edge at most, for which a ``Bc`` makes every such
loop's spectral radius < 1 -- a delayed spring needs damping ``> Kc (d + 1) T``, and delayed
damping on a light mass is itself unstable beyond ``~(pi/2) m / (d T)``, so a long delay
forces a weak spring) plus ``g r[n]``:
a pseudo-random binary sequence of amplitude ``0.1 F_lim`` whose levels last 1..40
samples at random (a wide band: the mass line above the friction corner, the friction
below), added to a square wave of ``0.1 F_lim`` whose sign flips every 250 ms (slow
constant-force steps: long stretches of one velocity sign, which is what separates Coulomb
from viscous friction), and early when the device is past 30 % of the envelope on the side
it pushes towards (a relay: the steps move the device both ways and keep it centred without
a stiff spring, which a long delay forbids). The gain ``g`` starts at 1/8 and grows by
2^(1/4) every 100 ms (up to 1) while the device moved over less than 30 % of the
envelope (every 25 ms while it has not yet moved 0.5 % of it: held by Coulomb friction at the start),
each time only once the device has felt the present level's full push (the PRBS along the
square wave) for the longest delay (a level raised under the PRBS's weak half broke a light
device loose far above its Coulomb friction, and behind a long delay it left the envelope
before the reversal reached it), and
halves each time the device is about to pass 60 % of the envelope (then 66 %, ...; its
position ``d_max + 1`` samples ahead at its present velocity): a light device behind a long delay (the force reacts
``d`` samples after it moved) never leaves the envelope before the gain has found its
level. The fit (:mod:`hapsim.analysis.device_fit`) uses the forces the device applied
(:mod:`hapsim.applied`), so neither the centring loop nor late ticks bias it.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["ExcitationPlan", "ExcitationEngine", "excitation_plan", "centring_gains",
           "MASS_RANGE", "LEVEL_SHARE", "PRBS_SHARE", "HOST_STALL_PRIOR_S", "PROBE_START",
           "LEVEL_WINDOW_S", "PROBE_S"]


#: Growth of the excitation's gain per calm 100 ms (2^(1/4): a force level at most 19 %
#: above the last one, under which the device moved over less than 30 % of the envelope).
_GROW = 2.0 ** 0.25
#: The probe's first level, a share of the top one (the square wave's level starts there).
PROBE_START = 1.0 / 64.0
#: The window [s] over which the engine judges the motion before it raises the level by
#: :data:`_GROW` (a quarter of it while the device is still held at the start).
LEVEL_WINDOW_S = 0.1
#: The longest the probe takes to reach the top level [s]: from :data:`PROBE_START` by
#: :data:`_GROW` a :data:`LEVEL_WINDOW_S` window, 24 windows (2.4 s), when the device
#: never moves over 40 % of the envelope (``hapsim identify``'s default duration counts it:
#: :func:`hapsim.pipeline.identify_settings.default_duration`).
PROBE_S = round(round(math.log(1.0 / PROBE_START) / math.log(_GROW)) * LEVEL_WINDOW_S, 9)
#: Moving masses [kg] the centring loop is made stable for (a hand on a handle included).
MASS_RANGE = (0.02, 2.0)
#: The square wave's largest force level, a share of the force limit: the PRBS on top
#: (PRBS_SHARE of it) and the centring force stay below the limit (a force at the limit
#: in half of the last 100 samples is a safety stop).
LEVEL_SHARE = 0.4
#: The PRBS's level, a share of the square wave's: below 1, the reversed square wave
#: always brakes with at least (1 - PRBS_SHARE) of its level.
PRBS_SHARE = 0.5
#: Samples of the windows the engine's velocity and acceleration are taken over.
_WINDOW = 16
#: Gain of the engine's position low-pass per sample (its time constant: 8 samples).
_LOWPASS = 1.0 / 8.0
#: Samples at the start whose second differences give the sensor noise (the probe's force
#: is then ~1/64 of its top level, ramped in over 20 ms).
_QUIET = 100
#: Margin on the measured overshoot coefficient (a faster or weaker reversal than those
#: measured: the coefficient of the delay's share falls with the velocity, of the
#: inertia's with the level).
_OVERSHOOT_MARGIN = 1.5
#: Each reversal's overshoot coefficient replaces the last one when larger than this share
#: of it (an old measurement at another level fades out).
_FORGET = 0.7
#: Share of the envelope the halving's threshold grows to at most (it grows by 10 % at each
#: halving; unbounded, it passed the envelope after four and no longer protected it).
_EDGE_TOP = 0.8
#: The excitation's last seconds: it brakes the device to rest while it ramps out.
_END_S = 0.1
#: Share of the envelope where the square wave reverses when the device would stop beyond.
_CALM = 0.4
#: Share of the envelope beyond which a predicted stop halves the level.
_EDGE = 0.7
#: Host stall [s] the stop ahead counts on a real-time port before the run has shown a
#: longer one: the issue's "ordinary" stall of a busy machine (issue 29: 6 ms).
HOST_STALL_PRIOR_S = 0.006


def _rho_mass(m: float, kc: float, bc: float, d: int, T: float) -> float:
    """Spectral radius of a mass ``m`` [kg] (exact ZOH, no friction) under the centring
    force ``-kc x[n-d] - bc (x[n-d] - x[n-d-1]) / T``: the roots of
    ``(z-1)^2 z^(d+1) + T^2/(2m) (z+1) (kc z + bc/T (z-1))`` (the plant
    ``T^2 (z+1) / (2 m (z-1)^2)``, Florens, Voda & Urma eq. (4) with ``b0 = 0``)."""
    a = np.zeros(d + 4)
    a[:3] = (1.0, -2.0, 1.0)
    b = (T * T / (2.0 * m)) * np.polymul([1.0, 1.0], [kc + bc / T, -bc / T])
    a[-3:] += b
    return float(np.max(np.abs(np.roots(a))))


def _rho_masses(ms, kc: float, bcs, d: int, T: float) -> np.ndarray:
    """:func:`_rho_mass` of every pair ``(ms[i], bcs[i])``, bit for bit, the companion
    matrices' eigenvalues in one LAPACK call per matrix as :func:`numpy.roots` forms them
    (one ``numpy.linalg.eigvals`` over the stack, not a Python call per pair).

    Parameters
    ----------
    ms, bcs : sequence of float, length k
        Masses [kg] and centring dampings [N s/m], paired.
    kc : float
        Centring stiffness [N/m].
    d : int >= 0
        Delay [samples].
    T : float
        Sample period [s].

    Returns
    -------
    ndarray, shape (k,)
        The spectral radii [-].
    """
    ms = np.asarray(ms, float)
    bcs = np.asarray(bcs, float)
    k = ms.size
    N = d + 4
    # _rho_mass's coefficients, element by element the same operations:
    # polymul([1, 1], [p, q]) = [p, p + q, q] (products by 1 exact)
    p = kc + bcs / T
    q = -bcs / T
    a = np.zeros((k, N))
    a[:, :3] = (1.0, -2.0, 1.0)
    a[:, -3:] += (T * T / (2.0 * ms))[:, None] * np.stack([p, p + q, q], axis=1)
    # numpy.roots' companion matrix (a[:, 0] is 1: nothing to strip in front)
    A = np.zeros((k, N - 1, N - 1))
    A[:, np.arange(1, N - 1), np.arange(N - 2)] = 1.0
    A[:, 0, :] = -a[:, 1:] / a[:, :1]
    odd = (a[:, -1] == 0.0) | ~np.isfinite(a).all(axis=1)
    rho = np.empty(k)
    if not odd.all():
        rho[~odd] = np.max(np.abs(np.linalg.eigvals(A[~odd])), axis=1)
    for i in np.flatnonzero(odd):
        # a root at 0 numpy.roots strips, or a coefficient not finite: its own way
        rho[i] = _rho_mass(float(ms[i]), kc, float(bcs[i]), d, T)
    return rho


@functools.lru_cache(maxsize=256)
def centring_gains(force_limit: float, envelope: float, rate_hz: float, max_delay: int,
                   masses=MASS_RANGE) -> tuple[float, float]:
    """Centring stiffness and damping stable for every mass and delay (module notes).

    A pure function of its arguments, kept for each (up to 256): its search takes ~40 ms
    (up to 13 stiffnesses, each 168 companion matrices' eigenvalues), and a process
    identifies one device at its one set of these many times (each run, each retry).

    Parameters
    ----------
    force_limit : float > 0
        Largest force sent [N].
    envelope : float > 0
        Half-width of the position envelope [m].
    rate_hz : float > 0
        Sample rate [Hz].
    max_delay : int >= 0
        Largest device delay [samples].
    masses : (float, float)
        Range of moving masses [kg] (7 points on a log grid are checked, and the ends).

    Returns
    -------
    (float, float)
        ``Kc`` [N/m], ``Bc`` [N s/m]: the largest ``Kc = 0.5 F_lim / envelope / 2^j``
        (``j = 0 .. 12``) with a ``Bc`` (24 values on a log grid from ``Kc (d_max + 1) T``
        to ``(pi/2) m_min / ((d_max + 1) T)``) making every loop's spectral radius < 1;
        ``Bc`` the geometric middle of the stable ones found. Without any, the smallest ``Kc`` tried
        and ``Bc = 0`` (the device's own friction must then hold it; the envelope stop
        remains).
    """
    T = 1.0 / rate_hz
    d = int(max_delay)
    grid = np.geomspace(masses[0], masses[1], 7)
    kc0 = 0.5 * force_limit / envelope
    kc = kc0
    for j in range(13):
        kc = kc0 / 2.0 ** j
        lo = kc * (d + 1) * T
        hi = 0.5 * math.pi * masses[0] / ((d + 1) * T)
        if hi <= lo:
            continue
        bcs = np.geomspace(lo, hi, 24)
        # every (damping, mass) pair at once (_rho_masses: np.roots' radii bit for bit)
        rho = _rho_masses(np.tile(grid, bcs.size), kc, np.repeat(bcs, grid.size), d,
                          T).reshape(bcs.size, grid.size)
        ok = [float(bc) for bc, r in zip(bcs, rho) if max(r.tolist()) < 1.0 - 1e-9]
        if not ok:
            continue
        # the middle (geometric) of the stable dampings: as far from either edge as the
        # grid allows, and no more damping than that (it would absorb the excitation)
        bc = math.sqrt(ok[0] * ok[-1])
        # the delay's worst case is not always the longest: check every one
        if all(r < 1.0 for dd in range(d + 1)
               for r in _rho_masses(grid, kc, [bc] * grid.size, dd, T).tolist()):
            return float(kc), bc
    return float(kc), 0.0


class ExcitationPlan:
    """The precomputed excitation of one identification run.

    Parameters
    ----------
    r : ndarray, shape (n,)
        Open-loop part of the force per sample, per unit of the engine's force level [-].
    kc : float
        Centring stiffness [N/m].
    bc : float
        Centring damping [N s/m].
    rate_hz : float
        Sample rate [Hz].
    envelope : float
        Half-width of the position envelope [m]; the open-loop part is halved each time
        the device passes 60 % of it.
    max_delay : int
        Largest device delay [samples] (the gain looks that far ahead).
    square : ndarray, shape (n,), optional
        Envelope of the square wave per sample [-] (its sign is the engine's, its force
        level the engine's).
    level_max : float
        Largest force level of the square wave [N].
    clock : callable, optional
        The host's clock [s] (``time.monotonic``) on a real-time port, where the device
        keeps its own time and a stalled host leaves it its force; None in lockstep (the
        device waits for the host, and the excitation reads no clock).

    Attributes
    ----------
    host_stall : float
        The longest host stall [s] an engine of this plan saw (0 before any): an engine
        rebuilt after a loss starts from it (:class:`ExcitationEngine`).
    """

    def __init__(self, r: np.ndarray, kc: float, bc: float, rate_hz: float,
                 envelope: float, max_delay: int = 0, square=None,
                 level_max: float = math.inf, clock=None) -> None:
        self.clock = clock
        self.host_stall = 0.0
        self.r = np.asarray(r, float)
        self.square = (np.zeros_like(self.r) if square is None
                       else np.asarray(square, float))
        self.max_delay = int(max_delay)
        self.envelope = float(envelope)
        self.kc = float(kc)
        self.bc = float(bc)
        self.rate_hz = float(rate_hz)
        self.level_max = float(level_max)


def excitation_plan(n: int, rate_hz: float, force_limit: float, envelope: float, *,
                    max_delay: int = 5, seed: int = 0) -> ExcitationPlan:
    """Build the excitation (module notes).

    Parameters
    ----------
    n : int > 0
        Samples.
    rate_hz : float > 0
        Sample rate [Hz].
    force_limit : float > 0
        Largest force sent [N].
    envelope : float > 0
        Half-width of the position envelope [m].
    max_delay : int >= 0
        Largest device delay the centring loop must stay stable with [samples].
    seed : int
        Seed of the PRBS.

    Returns
    -------
    ExcitationPlan
        ``r``: the PRBS of unit level times :data:`PRBS_SHARE` (ramped in and out over
        20 ms), ``square``: the square wave's unit envelope (ramped likewise); the engine
        multiplies both by its force level, at most :data:`LEVEL_SHARE` ``force_limit``.

    Raises
    ------
    ConfigError
        Non-positive force limit, envelope, rate or length.
    """
    if not (math.isfinite(force_limit) and force_limit > 0):
        raise ConfigError(f"must be a positive force [N], got {force_limit!r}",
                          key="--force-limit")
    if not (math.isfinite(envelope) and envelope > 0):
        raise ConfigError(f"must be a positive distance [m], got {envelope!r}",
                          key="--envelope")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"must be a positive rate [Hz], got {rate_hz!r}", key="--rate")
    if n < 1:
        raise ConfigError(f"must be > 0 samples, got {n}", key="--duration")
    rng = np.random.default_rng(seed)
    r = np.empty(n)
    i = 0
    level = PRBS_SHARE
    while i < n:
        k = int(rng.integers(1, 41))
        r[i:i + k] = level
        level = -level if rng.random() < 0.5 else level
        i += k
    sq = np.ones(n)
    # ramp in over 20 ms (no step at arming), out over the engine's braking end (zero
    # force at the end)
    nr = min(max(int(0.02 * rate_hz), 1), n // 4 or 1)
    ne = min(max(int(_END_S * rate_hz), 1), n // 4 or 1)
    ramp = np.ones(n)
    ramp[:nr] = np.linspace(0.0, 1.0, nr)
    ramp[n - ne:] = np.minimum(ramp[n - ne:], np.linspace(1.0, 0.0, ne))
    r *= ramp
    sq *= ramp
    kc, bc = centring_gains(force_limit, envelope, rate_hz, max_delay)
    return ExcitationPlan(r, kc, bc, rate_hz, envelope, max_delay, square=sq,
                          level_max=LEVEL_SHARE * force_limit)


class ExcitationEngine:
    """The excitation as an engine of :class:`~hapsim.host.loop.HostLoop`.

    Parameters
    ----------
    scene : ExcitationPlan
        Called ``scene`` because the loop rebuilds an engine after a loss as
        ``type(engine)(engine.scene)`` (the excitation then restarts).

    Notes
    -----
    The force level ``A`` [N] of the square wave (the PRBS is ``PRBS_SHARE A``) is designed
    from what the device shows, with no option to tune (module notes, 'The level'):

    - *probe*: ``A`` starts at ``level_max / 64`` and grows by 2^(1/4) every 25 ms until the
      device moves (its low-passed position spans 0.5 % of the envelope: a device held by
      Coulomb friction reaches its breakaway force within ~0.5 s), then every 100 ms while
      it moves over less than 30 % of the envelope, up to ``level_max``;
    - *apparent mass*: during each push (between two flips of the square wave) that starts
      from rest or against the motion, the force sent is integrated twice; when the device
      has moved 1 % of the envelope (the probe's first clear motion: slow, the force just
      above what breaks it loose), that double integral over the displacement is an
      apparent mass: friction, a delay and a velocity against the push only make it
      larger, so ``M = 2 x`` the smallest seen bounds the mass from above (before the
      first: no inertia term, the device has not yet moved 1 % of the envelope);
    - *stop ahead*: where the device stops if the force reverses now:
      ``s = e + v tau + sign(v) M max(|v| - v_n, 0)^2 / (2 (1 - PRBS_SHARE) A)``
      with ``e`` the low-passed position (8 samples), ``tau = (d_max + 1 + 1.5 W) T`` (the
      longest delay and the filters' lag), ``v`` the velocity over a ``W``-sample window
      (a 50 um sensor noise is ~4 mm/s of it, not 70 as from one difference) and
      ``(1 - PRBS_SHARE) A`` the least braking force the reversed excitation applies
      (friction only helps); ``v_n`` is three standard deviations of the sensor noise's
      share of ``v``, the noise measured from the second differences of the first 100
      samples (the device at rest or nearly: the probe's force is tiny then), and ``M`` is
      at most ``2 MASS_RANGE[1]``. Once the device has turned after a reversal of the square
      wave, its measured overshoot ``o`` beyond the position of the reversal, over the
      square of the velocity ``v_r`` it had then, is a stop coefficient that holds the
      delay, the inertia and the damping as the device shows them: the stop ahead is the
      smaller of the above and ``1.5 max(o / v_r^2, 0.7 x the last)`` ``sign(v) v^2``
      (a heavily damped device stops far sooner than its apparent mass says); on a
      real-time port (the plan's ``clock``) plus ``v t_s``, the distance the device
      travels through a stall of its host (it holds its force meanwhile, and the answers
      queued behind the stall reach it late): ``t_s`` the longest stall seen in this run
      (the host's clock between two answers, less a period), at least
      :data:`HOST_STALL_PRIOR_S`;
    - *end*: over the last 100 ms the level ramps out and only brakes (against ``v``).
      The overshoot coefficient of a reversal at least as fast as the one behind the
      present coefficient replaces it (one measured at a crawl holds the delay's share
      over a tiny velocity squared); a slower one replaces it only when larger, else the
      present one fades by 30 %. On a real-time port the stop ahead is also at least where a
      stall holding the present push leaves the device, ``e + v t_s + a t_s^2 / 2``
      whatever the signs (from a turn the push alone carries it).
      The square wave reverses when ``s`` passes 40 % of the
      envelope on the side it pushes towards (even a push towards the centre: the device
      coming back fast would stop beyond the other side), and every 250 ms unless the
      device is past 40 % on the side the push comes from; when ``s`` passes 70 %
      (then 77 %, ...) ``A`` halves once the device moves the way
      it is pushed again (the braking push keeps the level the stop ahead counted on: halved
      at once, the stop ahead grew and halved it again, down to nothing).

    :meth:`port_step` allocates nothing: a ring of ``W`` positions and a few floats.
    """

    def __init__(self, scene: ExcitationPlan) -> None:
        self.scene = scene
        self._r = scene.r
        self._n = scene.r.size
        self._kc = scene.kc
        self._bc = scene.bc * scene.rate_hz
        self._T = 1.0 / scene.rate_hz
        self._k = 0
        self._xc = 0.0
        self._xp = 0.0
        self._amax = float(scene.level_max)
        self._g = self._amax * PROBE_START
        self._edge = _EDGE * scene.envelope
        self._calm = _CALM * scene.envelope
        self._probe_dist = 0.01 * scene.envelope
        self._win = max(int(LEVEL_WINDOW_S * scene.rate_hz), 1)
        self._sub = max(int(0.025 * scene.rate_hz), 1)
        self._still = 0.005 * scene.envelope
        self._stuck = True
        # the sample where the level's full push (the PRBS along the square wave) was
        # first sent at this level and sign (-1: not yet)
        self._shown = -1
        self._reach = scene.max_delay + 1
        self._hi = -math.inf
        self._lo = math.inf
        self._W = _WINDOW
        self._ring = [0.0] * (2 * _WINDOW + 1)
        self._tau = (scene.max_delay + 1 + 1.5 * _WINDOW) * self._T
        self._mass = 0.0
        self._vf = 0.0
        self._xf = 0.0
        self._e0 = 0.0
        self._measured = False
        self._halve = False
        self._nend = min(max(int(_END_S * scene.rate_hz), 1), self._n // 4 or 1)
        self._n2 = 0.0
        self._cmeas = 0.0
        self._vmeas = 0.0
        self._vf0 = 0.0
        self._xf0 = 0.0
        self._o = 0.0
        self._vdead = 0.0
        self._lp = 0.0
        self._sq = scene.square
        self._sign = 1.0
        self._half = max(int(0.25 * scene.rate_hz), 1)
        self._clock = getattr(scene, "clock", None)
        self._t_last = math.inf
        # the longest stall any engine of this plan saw: the loop rebuilds its engine
        # after a loss (type(engine)(engine.scene)), often right after a long stall
        self._stall = (max(HOST_STALL_PRIOR_S, getattr(scene, "host_stall", 0.0))
                       if self._clock is not None else 0.0)

    @property
    def host_stall(self) -> float:
        """The host stall [s] the stop ahead counts now (class notes; 0 in lockstep)."""
        return self._stall

    @property
    def level(self) -> float:
        """The square wave's force level ``A`` now [N]."""
        return self._g

    def set_port_position(self, position: float, at_rest: bool = False) -> None:
        """Centre the excitation at the device's position ``position`` [m].

        Parameters
        ----------
        position : float
            Device position [m]; the position history is filled with it.
        at_rest : bool, optional
            Taken for the engines' interface (:meth:`hapsim.engine.Engine.set_port_position`)
            and ignored: the history always starts at rest.
        """
        self._xc = float(position)
        self._xp = float(position)
        self._lp = float(position)
        self._ring = [float(position)] * len(self._ring)
        self._e0 = 0.0

    def port_step(self, position: float) -> float:
        """Force [N] answering the position ``position`` [m] (class notes).

        Parameters
        ----------
        position : float
            Device position of this sample [m].

        Returns
        -------
        float
            Force to send [N]: the centring spring-damper, the square wave and the PRBS.
        """
        k = self._k
        T = self._T
        e = position - self._xc
        ring = self._ring
        nr = len(ring)
        W = self._W
        ring[k % nr] = position
        # velocity and acceleration of W-sample windows (x[k] - x[k-W], then its change):
        # a 50 um sensor noise is ~4 mm/s of velocity, not 70 as from one difference
        v = (position - ring[(k - W) % nr]) / (W * T)
        if k < _QUIET:
            # the sensor's noise while the probe's force is still tiny: the second
            # differences of a device at rest (or nearly) are its noise, variance 6 sigma^2
            if k >= 2:
                d2 = position - 2.0 * ring[(k - 1) % nr] + ring[(k - 2) % nr]
                self._n2 += d2 * d2
            if k == _QUIET - 1:
                sig = math.sqrt(self._n2 / (6.0 * (_QUIET - 2)))
                self._vdead = 3.0 * sig * math.sqrt(2.0) / (W * T)
        self._lp += (position - self._lp) * _LOWPASS
        lp = self._lp
        brake = (1.0 - PRBS_SHARE) * self._g
        va = v - self._vdead if v > self._vdead else (
            v + self._vdead if v < -self._vdead else 0.0)
        s = v * self._tau + va * abs(va) * self._mass / (2.0 * brake)
        if self._cmeas > 0.0:
            # the overshoot measured after the last reversals (delay, inertia and damping
            # as the device shows them), with its margin, when it says less
            s2 = _OVERSHOOT_MARGIN * self._cmeas * va * abs(va)
            if abs(s2) < abs(s):
                s = s2
        hold = 0.0
        if self._clock is not None:
            # a stall of the host: the longest seen (or the prior), travelled at v
            now = self._clock()
            gap = now - self._t_last - T
            self._t_last = now
            if gap > self._stall:
                self._stall = self.scene.host_stall = gap
            ts = self._stall
            s += v * ts
            # the push held through it: the acceleration of the last two windows, when it
            # drives the device on (a braking one is not counted on)
            a = (v - (ring[(k - W) % nr] - ring[(k - 2 * W) % nr]) / (W * T)) / (W * T)
            if a * v > 0.0:
                s += 0.5 * a * ts * ts
            # and where a stall holding the present push leaves the device, whatever its
            # velocity's sign: from a turning point (v ~ 0, the push just reversed it) the
            # push alone carries it ``a ts^2 / 2`` the way it pushes -- counted only along
            # v above, a 79 ms stall at a turn carried a 0.7 kg device 7 mm
            hold = lp - self._xc + v * ts + 0.5 * a * ts * ts
        s += lp - self._xc
        if self._clock is not None and abs(hold) > abs(s):
            s = hold
        # the overshoot after the last reversal: how far the device went on the way it
        # moved when the force turned
        if self._vf0 != 0.0:
            o = (lp - self._xf0) * (1.0 if self._vf0 > 0.0 else -1.0)
            if o > self._o:
                self._o = o
            if v * self._vf0 <= 0.0:           # it turned: one measurement
                c = self._o / (self._vf0 * self._vf0)
                if abs(self._vf0) >= self._vmeas:
                    # at least as fast as the one behind the coefficient: it replaces it
                    # (a coefficient measured at a crawl holds the delay's share over a
                    # tiny velocity squared -- 28 s^2/m on a damped 25 g device whose
                    # stops at ten times that speed measured 2.7 -- and, faded by 30 % a
                    # reversal, it halved the level until the device hardly moved)
                    self._cmeas = c
                    self._vmeas = abs(self._vf0)
                else:
                    self._cmeas = max(c, _FORGET * self._cmeas)
                self._vf0 = 0.0
        as_ = s if s >= 0.0 else -s
        if as_ > self._edge and self._g > 1e-3 * self._amax:
            # nearing the envelope: excite less from the push after the braking one (the
            # braking push keeps the level the stop ahead counted on)
            self._halve = True
            self._edge = min(self._edge * 1.1, _EDGE_TOP * self.scene.envelope)
        if lp > self._hi:
            self._hi = lp
        if lp < self._lo:
            self._lo = lp
        if self._stuck and (self._hi - self._lo >= self._still and self._mass > 0.0):
            self._stuck = False            # broke loose: from now on the 100 ms steps only
        if k % self._win == self._win - 1 or (self._stuck and k % self._sub == self._sub - 1):
            if (self._hi - self._lo < self._calm and self._g < self._amax
                    and 0 <= self._shown <= k - self._reach):
                # it moved less than 30 % of the envelope in 100 ms: excite more, by steps
                # small enough that a device held by Coulomb friction breaks loose gently,
                # and only once it has felt the level's full push for the longest delay
                # (a level raised under the PRBS's weak half breaks it loose far above its
                # Coulomb friction, and a light device behind a long delay then leaves the
                # envelope before the reversal reaches it)
                self._g = min(self._g * _GROW, self._amax)
                self._shown = -1
            self._hi = -math.inf
            self._lo = math.inf
        # the square wave: its sign flips each half period (250 ms), and early when the
        # device would stop past 30 % of the envelope on the side it pushes towards
        sg = self._sign
        if sg * s > self._calm or k % self._half == self._half - 1:
            if sg * s > self._calm or not sg * e < -self._calm:
                sg = -sg
                self._sign = sg
                self._shown = -1
                self._vf = self._xf = 0.0
                self._e0 = lp - self._xc
                if self._vf0 == 0.0 and abs(v) > self._vdead and k >= _QUIET:
                    self._vf0, self._xf0, self._o = v, lp, 0.0
                # a push measures the mass only from rest or against the motion (a
                # velocity along it would make the apparent mass too small)
                self._measured = sg * v > 0.0
        if self._halve and sg * v > 0.0:
            self._g *= 0.5                 # the device has turned: the push is weaker
            self._halve = False
        # the apparent mass of this push (class notes)
        if not self._measured:
            dx = (lp - self._xc - self._e0) * sg
            if dx >= self._probe_dist:
                self._measured = True
                if self._xf * sg > 0.0:
                    m2 = max(2.0 * self._xf * sg / dx, MASS_RANGE[0])
                    m2 = min(m2, 2.0 * MASS_RANGE[1])
                    self._mass = m2 if self._mass == 0.0 else min(self._mass, m2)
        if k >= self._n - self._nend:
            # the end: brake to rest as the level ramps out (no push, no PRBS): a device
            # left coasting at the end of a push travels v m / b0 past it
            r = (-self._g * self._sq[k] * (1.0 if va > 0.0 else -1.0 if va < 0.0 else 0.0)
                 if k < self._n else 0.0)
        else:
            r = self._g * (self._r[k] + sg * self._sq[k])
            if self._shown < 0 and self._r[k] * sg > 0.0:
                self._shown = k
        self._k = k + 1
        f = -self._kc * e - self._bc * (position - self._xp) + r
        self._xp = position
        self._xf += self._vf * T + 0.5 * f * T * T
        self._vf += f * T
        return f
