"""Excite a device safely and record its STATE / FORCE stream (``hapsim identify``).

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
envelope (every 25 ms while it has not yet moved 0.5 % of it: held by Coulomb friction at the start), and
halves each time the device is about to pass 60 % of the envelope (then 66 %, ...; its
position ``d_max + 1`` samples ahead at its present velocity): a light device behind a long delay (the force reacts
``d`` samples after it moved) never leaves the envelope before the gain has found its
level. The fit (:mod:`hapsim.analysis.device_fit`) uses the forces the device applied
(:mod:`hapsim.applied`), so neither the centring loop nor late ticks bias it.
"""

from __future__ import annotations

import math
import signal
import threading

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["ExcitationPlan", "ExcitationEngine", "excitation_plan", "record",
           "centring_gains", "MASS_RANGE"]

#: Growth of the excitation's gain per calm 100 ms (2^(1/4): a force level at most 19 %
#: above the last one, under which the device moved over less than 30 % of the envelope).
_GROW = 2.0 ** 0.25
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


def centring_gains(force_limit: float, envelope: float, rate_hz: float, max_delay: int,
                   masses=MASS_RANGE) -> tuple[float, float]:
    """Centring stiffness and damping stable for every mass and delay (module notes).

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
    """

    def __init__(self, r: np.ndarray, kc: float, bc: float, rate_hz: float,
                 envelope: float, max_delay: int = 0, square=None,
                 level_max: float = math.inf) -> None:
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
      (a heavily damped device stops far sooner than its apparent mass says);
    - *end*: over the last 100 ms the level ramps out and only brakes (against ``v``).
      The square wave reverses when ``s`` passes 40 % of the
      envelope on the side it pushes towards, and every 250 ms; when ``s`` passes 70 %
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
        self._g = self._amax / 64.0
        self._edge = _EDGE * scene.envelope
        self._calm = _CALM * scene.envelope
        self._probe_dist = 0.01 * scene.envelope
        self._win = max(int(0.1 * scene.rate_hz), 1)
        self._sub = max(int(0.025 * scene.rate_hz), 1)
        self._still = 0.005 * scene.envelope
        self._stuck = True
        self._hi = -math.inf
        self._lo = math.inf
        self._W = _WINDOW
        self._ring = [0.0] * (_WINDOW + 1)
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
        self._vf0 = 0.0
        self._xf0 = 0.0
        self._o = 0.0
        self._vdead = 0.0
        self._lp = 0.0
        self._sq = scene.square
        self._sign = 1.0
        self._half = max(int(0.25 * scene.rate_hz), 1)

    @property
    def level(self) -> float:
        """The square wave's force level ``A`` now [N]."""
        return self._g

    def set_port_position(self, position: float, at_rest: bool = False) -> None:
        """Centre the excitation at the device's position ``position`` [m]."""
        self._xc = float(position)
        self._xp = float(position)
        self._lp = float(position)
        self._ring = [float(position)] * len(self._ring)
        self._e0 = 0.0

    def port_step(self, position: float) -> float:
        """Force [N] answering the position ``position`` [m] (class notes)."""
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
        s += lp - self._xc
        # the overshoot after the last reversal: how far the device went on the way it
        # moved when the force turned
        if self._vf0 != 0.0:
            o = (lp - self._xf0) * (1.0 if self._vf0 > 0.0 else -1.0)
            if o > self._o:
                self._o = o
            if v * self._vf0 <= 0.0:           # it turned: one measurement
                c = self._o / (self._vf0 * self._vf0)
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
            if self._hi - self._lo < self._calm and self._g < self._amax:
                # it moved less than 30 % of the envelope in 100 ms: excite more, by steps
                # small enough that a device held by Coulomb friction breaks loose gently
                self._g = min(self._g * _GROW, self._amax)
            self._hi = -math.inf
            self._lo = math.inf
        # the square wave: its sign flips each half period (250 ms), and early when the
        # device would stop past 30 % of the envelope on the side it pushes towards
        sg = self._sign
        if k % self._half == self._half - 1 or sg * s > self._calm:
            if not sg * e < -self._calm:
                sg = -sg
                self._sign = sg
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
        self._k = k + 1
        f = -self._kc * e - self._bc * (position - self._xp) + r
        self._xp = position
        self._xf += self._vf * T + 0.5 * f * T * T
        self._vf += f * T
        return f


def _progress_thread(tel, total: int, stop_evt: threading.Event, label: str):
    from hapsim.progress import Progress

    def run():
        with Progress(total, label, "samples", delay=0.5) as bar:
            while not stop_evt.wait(0.25):
                bar.update(min(tel.n, total))
            bar.update(min(tel.n, total))
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def record(device=None, *, port: str | None = None, baud: int = 115200,
           rate_hz: float = 1000.0, duration: float = 4.0, force_limit: float = 2.0,
           envelope: float = 0.01, max_delay: int = 5, seed: int = 0, noise_seed: int = 0,
           transport: str | None = None, lockstep: bool = False, progress: bool = True,
           handle_signals: bool = True, stop=None, driver: str | None = None,
           driver_options: dict | None = None, mock_options: dict | None = None,
           travel: float | None = None, rt_priority: int = 10):
    """Run the excitation on a device (or the mock of ``device``) and return the record.

    Parameters
    ----------
    device : hapsim.scene.Device, optional
        The device the mock models (ignored with ``port``); default: the mock's default.
    port : str, optional
        Serial port of a device speaking the framed protocol.
    baud : int
        Baud rate for ``port``.
    rate_hz : float
        Loop rate [Hz].
    duration : float
        Excitation length [s].
    force_limit : float
        Largest force sent [N] (also the CONFIG force limit).
    envelope : float
        Position envelope [m]: the loop stops (zero force, STOP) beyond it.
    max_delay : int
        Largest delay the centring loop is made stable for [samples].
    seed : int
        Seed of the excitation.
    noise_seed : int
        Seed of the mock's sensor noise.
    transport : {"inprocess", "pty", "serial"}, optional
        Default: ``"serial"`` with ``port``, ``"pty"`` (embedded mock) otherwise.
    lockstep : bool
        Lockstep mock (``"inprocess"`` implies it).
    progress : bool
        Show a progress bar on a terminal (stderr).
    handle_signals : bool
        SIGINT/SIGTERM end the excitation cleanly (zero force, STOP; main thread only).
    stop : StopFlag, optional
        External stop flag.
    driver : str, optional
        A protocol of :mod:`hapsim.drivers` (host-clocked; without ``port``, that
        driver's mock of ``device``); None or ``"framed"``: hapsim's own.
    driver_options : dict, optional
        The driver's device parameters (``device.protocol_options``).
    mock_options : dict, optional
        The driver mock's hardware (default: the device the driver describes).
    travel : float, optional
        The FireFader's travel between its end stops [m]: before the excitation, a sweep
        between the stops finds its position scale
        (:func:`hapsim.drivers.firefader_travel.find_travel`), which the excitation and
        ``protocol_options`` then use.
    rt_priority : int
        ``SCHED_FIFO`` priority of the loop on a real-time port (pty or serial, not
        lockstep) where the OS permits it, as ``hapsim run``'s (0: normal scheduling;
        :class:`hapsim.host.realtime.RealtimePriority`): a host preempted mid-push leaves
        the device its force for the preemption, beyond the excitation's plan.

    Returns
    -------
    dict
        ``position``, ``force``, ``late``, ``time``, ``seq`` (arrays), ``period`` [s], ``loop``
        (stop reason, safety stop, late, clamped, samples, transport, ``force_scale``,
        ``direction_probe``: what a driver that finds its motor direction first found,
        :class:`hapsim.drivers.haply_probe.DirectionProbe`, else None; ``travel_sweep``:
        :class:`hapsim.drivers.firefader_travel.TravelSweep` as a dict, or None),
        ``protocol_options`` (the driver's parameters, the direction found included).
        ``force`` is the force the device applied for each sample: what the host sent,
        on the actuator's grid when the device reports one (a driver's protocol
        resolution, or a framed device's ``HELLO.force_scale`` > 0 [N], the nearest
        step: a PWM of 256 steps rounds every force, and a fit of the force sent would
        see that rounding's gain on the excitation as a wrong mass).

    Raises
    ------
    ConfigError
        Bad values (:func:`excitation_plan`), an unknown transport.
    DeviceError, ProtocolError
        As :meth:`hapsim.host.loop.HostLoop.run`.
    IdentificationError
        The Haply joint's motor direction cannot be found (it does not move under the
        probe's torque pulses, or moves the same way under both signs); the FireFader's
        sweep found no end stop it can take as one (``travel``).
    """
    from hapsim.drivers import DEFAULT, family
    from hapsim.host.loop import HostLoop, LoopConfig, StopFlag
    from hapsim.emulated.mock import DEFAULT_DEVICE, MockDevice
    from hapsim.host.telemetry import Telemetry
    from hapsim.scene import Excitation

    if travel is not None and not getattr(family(driver or DEFAULT).load(), "travel_sweep",
                                          False):
        raise ConfigError(f"a travel sweep finds the FireFader's position scale; the "
                          f"{driver or DEFAULT} protocol has none to find (valid with "
                          f"--travel: --driver firefader)", key="--travel")
    if not (math.isfinite(duration) and duration > 0):
        raise ConfigError(f"must be a positive number of seconds, got {duration!r}",
                          key="--duration")
    n = max(int(round(duration * rate_hz)), 1)
    plan = excitation_plan(n, rate_hz, force_limit, envelope, max_delay=max_delay, seed=seed)
    if transport is None:
        transport = "serial" if port else "pty"
    if transport not in ("inprocess", "pty", "serial"):
        raise ConfigError(f"unknown transport {transport!r}; valid: inprocess, pty, serial",
                          key="transport")
    dev = device or DEFAULT_DEVICE
    stop = stop or StopFlag()
    old = {}
    if handle_signals and threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, lambda signum, frame: stop.request(signum))
    embedded = None
    lock = lockstep or transport == "inprocess"
    use_driver = driver not in (None, DEFAULT)
    if use_driver:
        from hapsim.drivers import get_driver
        drv = get_driver(driver, **(driver_options or {}))
        drv.check_rate(rate_hz)             # a rate the device cannot hold is refused
        lock = lock or port is None
    probe = None
    sweep = None
    try:
        if use_driver:
            from hapsim.drivers.transport import DriverTransport
            if port is None:
                from hapsim.emulated.driver_mock import WALL_CLOCK_MOCKS, EmbeddedDriverMock
                hardware = dict(mock_options if mock_options is not None
                                else drv.mock_hardware())
                if driver in WALL_CLOCK_MOCKS:
                    # the board's clock follows the host's pacing: an identification over
                    # a driver's embedded mock is still lockstep (named here), its probes
                    # and excitation paced by the commands
                    hardware.setdefault("clock", "lockstep" if lock else "wall")
                embedded = EmbeddedDriverMock(driver, dev, Excitation(), rate_hz, seed=noise_seed,
                                              options=hardware)
            if getattr(drv, "probes_direction", False) and \
                    "motor_direction" not in (driver_options or {}):
                # a wrong motor direction makes the excitation run away: find it first
                # (unless it is given: a device file's, or --protocol-option)
                drv, probe = _probe_direction(drv, port or embedded.port, force_limit,
                                              envelope, rate_hz, port is None)
            if travel is not None:
                # the position scale first: the excitation and its fit are in its units
                drv, sweep = _sweep_travel(drv, port or embedded.port, travel, force_limit,
                                           rate_hz, port is None)
            if port is None:
                # paced by the commands: asked again only when its account says it is
                # quiet (a slow mock process is no lost answer, whatever the time)
                acct = embedded.handled
                tr = DriverTransport(drv, embedded.port, delay=int(dev.delay),
                                     reply_deadline=0.02,
                                     board_period=None if acct is None else 1.0 / rate_hz,
                                     handled=None if acct is None else acct.totals)
                embedded.release_slave()
            else:
                tr = DriverTransport(drv, port, delay=1, delay_known=False)
        elif transport == "inprocess":
            from hapsim.emulated.links import InProcessTransport
            mock = MockDevice(dev, Excitation(), native_rate_hz=rate_hz, lockstep=True,
                              seed=noise_seed)
            tr = InProcessTransport(mock)
        elif transport == "pty":
            from hapsim.emulated.links import EmbeddedMock
            from hapsim.host.transport import SerialTransport
            embedded = EmbeddedMock(dev, Excitation(), rate_hz, lockstep=lock, seed=noise_seed)
            tr = SerialTransport(embedded.port, baud)
            embedded.release_slave()
        else:
            from hapsim.host.transport import SerialTransport
            tr = SerialTransport(port, baud)
        d_expect = int(dev.delay) if port is None else 1     # whole ticks (force_seq)
        cfg = LoopConfig(rate_hz=rate_hz, n_samples=n, delay=d_expect, force_limit=force_limit,
                         lockstep=lock, host_clocked=use_driver,
                         state_timeout=(0.5 if transport == "inprocess" else 10.0) if lock
                         else 1.0,
                         hello_timeout=30.0 if transport == "pty" else 5.0,
                         position_bound=envelope, reconnect=False,
                         # every STATE answered and logged: a late answer is a known
                         # input (its force_seq), a skipped STATE a hole in the record
                         backlog="all")
        tel = Telemetry(n)
        from hapsim.host.realtime import RealtimePriority
        loop = HostLoop(ExcitationEngine(plan), tr, cfg, tel, stop)
        evt = threading.Event()
        th = None
        if progress:
            th = _progress_thread(tel, n, evt, "hapsim identify: exciting")
        try:
            # the loop's thread at SCHED_FIFO where permitted, as hapsim run's: preempted
            # for a few ms mid-push (a suite beside a CPU-bound process), the device held
            # its force and passed the envelope the excitation had planned within
            with RealtimePriority(rt_priority if transport in ("pty", "serial") and not lock
                                  else 0) as rt:
                res = loop.run()
        finally:
            evt.set()
            if th is not None:
                th.join(1.0)
            tr.close()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if embedded is not None:
            embedded.report()
            embedded.close()
    cols = tel.columns()
    force = cols["force"].copy()
    fs = 0.0
    account = None
    if use_driver:          # what the device was sent: the protocol's quantised force
        force = np.array([drv.applied_force(v) for v in force])
        # a driver's protocol names no applied force: its own timing may (issue 20)
        hook = getattr(drv, "account", None)
        account = hook(cols, force) if hook is not None else None
        late = cols["late"].astype(bool) if account is None else account.late
    else:                   # a framed device's actuator grid, as its HELLO reports it
        from hapsim.applied import account_from_force_seq
        hello = getattr(res, "hello", None)
        fs = float(getattr(hello, "force_scale", 0.0) or 0.0)
        if not (math.isfinite(fs) and fs > 0):
            fs = 0.0
        hl = float(getattr(hello, "force_limit", math.inf) or math.inf)
        # the force the device applied at every tick, from its STATEs' force_seq: the
        # delay is the one the device shows, late ticks are known inputs
        account = account_from_force_seq(cols["seq"], force, cols["force_seq"],
                                         cols["status"], zero_delay=lock and d_expect == 0,
                                         force_limit=min(force_limit, hl), force_scale=fs)
        force = np.round(force / fs) * fs if fs else force
        late = account.late
    return {"position": cols["position"].copy(), "force": force,
            "late": late, "time": cols["time"].copy(),
            "seq": cols["seq"].copy(), "account": account,
            "period": 1.0 / rate_hz,
            "loop": {"samples": int(res.samples), "requested": n,
                     "stop_reason": res.stop_reason, "safety_stop": bool(res.safety_stop),
                     "late": int(np.count_nonzero(late)), "clamped": int(res.clamped),
                     "device_delay": None if account is None else int(account.delay),
                     "transport": transport, "lockstep": bool(lock), "scheduling": rt.note,
                     "port": tr.info.get("port"), "faults": list(res.faults),
                     "f_max": float(res.f_max), "v_max": float(res.v_max),
                     "centring": {"K": plan.kc, "B": plan.bc}, "force_scale": fs,
                     "driver": tr.report() if use_driver else None,
                     "direction_probe": None if probe is None else probe.to_dict(),
                     "travel_sweep": None if sweep is None else sweep.to_dict()},
            "protocol_options": drv.options() if use_driver else None}


def _sweep_travel(drv, port: str, travel: float, force_limit: float, rate_hz: float,
                  mock: bool):
    """The FireFader driver with the position scale a sweep between its end stops found
    (:func:`hapsim.drivers.firefader_travel.sweep_port`), and what was found."""
    from hapsim.drivers import get_driver
    from hapsim.drivers.firefader_travel import sweep_port
    # a mock advances one period per packet, however slowly it runs: wait for it, unpaced
    found = sweep_port(drv, port, travel=travel, force=force_limit, rate_hz=rate_hz,
                       timeout=0.5 if mock else 0.05, pace=not mock)
    return get_driver(drv.name, **{**drv.options(),
                                   "metres_per_count": found.metres_per_count}), found


def _probe_direction(drv, port: str, force_limit: float, envelope: float, rate_hz: float,
                     mock: bool):
    """The driver with the motor direction found by a torque pulse of each sign
    (:func:`hapsim.drivers.haply_probe.probe_port`), and what was found."""
    from hapsim.drivers import get_driver
    from hapsim.drivers.haply_probe import probe_port
    # a mock advances one period per write, however slowly it runs: wait for it, unpaced
    found = probe_port(drv, port, force_limit=force_limit, envelope=envelope,
                       rate_hz=rate_hz, timeout=0.5 if mock else 0.05, pace=not mock)
    return get_driver(drv.name, **{**drv.options(),
                                   "motor_direction": found.motor_direction}), found
