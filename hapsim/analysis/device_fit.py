"""Identify a 1-DoF device from a recorded force / position stream (``hapsim identify``).

Model (docs/design.md, 'The THS'): ``m x'' + b0 x' = u(t) - fc sign(x')`` with the
commanded force ``u`` applied ``d`` whole samples after the position it answers and held
over the period (zero-order hold) -- or the paper's idealised sampled image (Florens, Voda &
Urma eq. (4));
the encoder rounds to a quantum ``q`` after Gaussian noise of standard deviation ``sigma``.

Method
------
*Output error on the moving stretches.* The velocity's sign is read from the positions
(:func:`_stretches`); inside a stretch where the device clearly moves one way the Coulomb
friction is a constant force and the exact ZOH discretisation is linear. For each hold and
each delay ``d = 0 .. max_delay`` the recorded forces, shifted by ``d`` (a tick the device
reported late holds the force before), drive the model restarted at every stretch from its
own initial state (multiple shooting); for given ``(m, b0)`` the stretch states and
``(fc+, fc-)`` follow by linear least squares, so only ``(ln m, b0)`` are searched
(variable projection: Golub & Pereyra 1973; ``scipy.optimize.least_squares``, started from
the correlation of force steps with acceleration). The two best candidates are then refined
with the nonlinear friction model (stick, reversal) over all parameters, and stretches the
model misses by far (an unseen reversal) are dropped once. Unlike the equation error, whose
regressors carry the sensor noise (errors in variables: biased), the output error is
consistent for white sensor noise, also in closed loop: the forces are known exactly, the
model output given them is the true position, the residual is the sensor error (L. Ljung,
*System Identification*, 2nd ed., 1999, Sec. 4.2, 7.3). The (hold, d) with the least
residual is chosen; every other whose likelihood ratio ``N ln(S_d / S_best)`` is below the
chi-square quantile stays in the delay's interval, and the intervals of m, b0 and fc then
also cover the estimates under those delays. When the delays are tried (no account of the
applied force), ``N`` is the residual's effective samples (:func:`_effective_samples`: a
quantiser's error is correlated, and counted as ``N`` independent samples the ratio told
apart delays the record cannot, the best a wrong one); a record that then cannot tell two
delays apart says so (``delay_certain`` False, the verdict naming both), or is refused
with ``ambiguous_delay="refuse"``.

*Lost STATEs.* With ``seq`` (the device's tick of each row) a gap in the ticks cuts the
record: every stretch of consecutive ticks is fitted from states of its own, none across a
gap, with the mass and frictions shared; the force answering row ``k`` acts from tick
``seq[k] + d`` (:func:`applied_force`).

Intervals
---------
At :data:`LEVEL` (99.9 %: the intervals rest on a linearisation and on a sign detection
that is not perfect, and a blind test over 50 random devices must find every true value
inside them in at least 95 % of the cases). ``cov = (J'J)^-1 S (J'J)^-1`` with the stretch
states partialled out of ``J`` (Frisch-Waugh-Lovell) and ``S`` the Newey-West
(Bartlett-weighted, lag ``L``) estimate of the covariance of the score ``J' r`` (W. K. Newey
& K. D. West, Econometrica 55(3), 1987): quantisation of a slowly moving position is not
white. Positions are never taken as known better than :data:`POSITION_FLOOR` (on exact data
the intervals do not shrink below the optimiser's resolution). The interval of ``m`` is
``m exp(+-z s_ln m)``. On a quantised record that linearisation is not enough (the
quantiser's error is bounded and deterministic, and on a record of few encoder steps its
effect on the estimates is neither small nor unbiased): each interval is then the union of
the linearised one and the bias-corrected prediction interval of :data:`REPLICATES` refits
of the fitted model passed through the same encoder (:func:`_grid_replicates`). A mass not
determined within a factor :data:`MASS_SPAN`, or fewer encoder steps on the stretches than
fitted parameters, is an :class:`~hapsim.errors.IdentificationError`. The quantum is read from the positions (the smallest step between
distinct values, when every value is a whole multiple of it). The noise is the
maximum-likelihood ``sigma`` of the rounded Gaussian ``P(y | x) = Phi((y - x + q/2)/s) -
Phi((y - x - q/2)/s)``, ``s^2 = sigma^2 + delta^2`` (``delta``: the model output's own
error, taken anywhere in ``[0, 2 delta]``), with its profile-likelihood interval. Without a
quantum, the noise is the white part of the residual, from the median absolute second
difference inside the stretches (:func:`_noise_white`): a smooth model error (the Coulomb
model's stick and reversal timing) is no noise, and the residual's variance counted it as
noise (an interval of 8-11 um missing a noise of 0).

Verdict
-------
The 2nd-order model explains the data when the residual's RMS is at most twice what the
sensor explains, ``sqrt(q^2/12 + sigma_w^2)`` (``sigma_w``: white noise from the median
absolute second difference of the residual, which a smooth unmodelled motion -- a
resonance, a compliant transmission -- barely feeds). Otherwise the residual's dominant
frequency is reported.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from hapsim.errors import ConfigError, IdentificationError

__all__ = ["Estimate", "DeviceFit", "fit_device", "applied_force", "POSITION_FLOOR",
           "LEVEL"]

#: Positions are never taken as known better than this [m] (intervals' numerical floor).
POSITION_FLOOR = 1e-10
#: Confidence level of every interval.
LEVEL = 0.999
_HOLDS = {"zoh": 0, "ideal": 1}
#: ln m [kg] the fit searches within (1e-6 .. 1e6 kg: beyond, no device; the basis overflows).
_LM_RANGE = (math.log(1e-6), math.log(1e6))


@dataclass
class Estimate:
    """One identified quantity with its confidence interval.

    Attributes
    ----------
    value : float
        Estimate (unit in ``unit``).
    lo, hi : float
        Interval at :data:`LEVEL`.
    unit : str
        Unit, e.g. ``"kg"``.
    """

    value: float
    lo: float
    hi: float
    unit: str

    def contains(self, truth: float) -> bool:
        """True when ``lo <= truth <= hi``."""
        return bool(self.lo <= truth <= self.hi)


@dataclass
class DeviceFit:
    """What :func:`fit_device` identified.

    Attributes
    ----------
    mass : Estimate
        Moving mass m [kg] (with a hand on the handle: hand + handle, the THS mass).
    friction : Estimate
        Viscous friction b0 [N s/m] (with a hand: the THS damping).
    coulomb_pos, coulomb_neg : Estimate
        Coulomb friction while moving in + / - [N] (zero-width at 0 for hold ``ideal``).
    coulomb : Estimate
        Their mean [N]; ``asymmetry`` = ``fc+ - fc-`` [N].
    asymmetry : Estimate
    delay : int
        Whole samples d between a position and the force answering it being applied.
    delay_range : tuple of int
        Every whole delay the data cannot tell from ``delay`` (its interval).
    delay_estimate : Estimate
        The delay as a real number of periods ``d + frac`` (a sub-sample delay: the split
        hold, :mod:`hapsim.analysis.subsample`) with its interval [periods]; under the
        idealised hold, the whole delay. ``delay`` is its whole part as the fit chose it.
    hold : str
        ``"zoh"`` or ``"ideal"``; ``hold_certain`` False when the other fits as well.
    hold_certain : bool
    position_resolution : Estimate
        Encoder quantum q [m] (0 when the positions are not on a grid).
    noise : Estimate
        Sensor noise standard deviation [m].
    x0 : float
        Fitted position at the first sample [m].
    rms_residual : float
        RMS of ``x_model - x_meas`` [m].
    explained : bool
        The model explains the data (module notes).
    verdict : str
        One sentence for the user.
    residual_peak_hz : float
        Dominant frequency of the residual [Hz].
    period : float
        Sample period T [s].
    n_samples : int
        Samples used.
    level : float
        Confidence level of the intervals.
    motion_counts : int
        Encoder steps seen on the fitted stretches (changes between neighbouring
        samples; -1: positions not on a grid).
    delay_certain : bool
        False when another delay fits as well (``delay_range``; the verdict names it):
        ``delay`` is then the better fit's, not determined.
    candidates : list of dict
        ``hold``, ``delay``, ``rms`` of every model tried.
    model : ndarray
        The model's positions [m], shape (n_samples,).
    """

    mass: Estimate
    friction: Estimate
    coulomb_pos: Estimate
    coulomb_neg: Estimate
    coulomb: Estimate
    asymmetry: Estimate
    delay: int
    delay_range: tuple
    hold: str
    hold_certain: bool
    position_resolution: Estimate
    noise: Estimate
    x0: float
    rms_residual: float
    explained: bool
    verdict: str
    residual_peak_hz: float
    period: float
    n_samples: int
    level: float = LEVEL
    motion_counts: int = -1
    delay_certain: bool = True
    delay_estimate: Estimate = None
    candidates: list = field(default_factory=list)
    model: np.ndarray = field(default=None, repr=False)

    def device(self, force_limit: float = math.inf):
        """The identified device as a :class:`hapsim.scene.Device`.

        Parameters
        ----------
        force_limit : float
            Force limit to put in it [N].

        Returns
        -------
        hapsim.scene.Device
            Negative estimates of friction, Coulomb friction are written as 0 (their
            intervals then hold 0).
        """
        from hapsim.scene import Device
        return Device(mass=self.mass.value, friction=max(self.friction.value, 0.0),
                      delay=self.device_delay(), hold=self.hold, force_limit=force_limit,
                      position_resolution=self.position_resolution.value,
                      coulomb=max(self.coulomb.value, 0.0), noise=self.noise.value)

    def device_delay(self):
        """The delay to write in a device section [periods]: the whole ``delay`` when
        the interval of :attr:`delay_estimate` holds it (a whole delay gives today's
        numbers bit for bit), else the sub-sample estimate rounded to 1e-3 period.

        Returns
        -------
        int or float
        """
        e = self.delay_estimate
        if e is None or e.lo <= self.delay <= e.hi or not math.isfinite(e.value):
            return int(self.delay)
        return round(float(e.value), 3)

    def to_dict(self) -> dict:
        """Plain data (``--json``): every estimate as ``{value, lo, hi, unit}``."""
        d = {k: v for k, v in asdict(self).items() if k != "model"}
        d["delay_range"] = list(self.delay_range)
        return d


def applied_force(force, delay: int, late=None, seq=None) -> np.ndarray:
    """The force the device held over each period, from the forces the host sent.

    Parameters
    ----------
    force : array_like, shape (n,)
        Force sent answering the position of sample ``k`` [N].
    delay : int >= 0
        d: that force acts over ``[(k+d)T, (k+d+1)T)``.
    late : array_like of bool, shape (n,), optional
        Ticks the device reported holding an older force: the force before is held.
    seq : array_like of int, shape (n,), optional
        The device's tick (STATE seq) of each row; rows missing from the record (a STATE
        lost, never answered) are gaps in it. The force answering row ``k`` acts from tick
        ``seq[k] + d``; at a tick whose due force was never sent (its STATE lost) the
        device holds the last one that was. Default: ``seq[k] = k``.

    Returns
    -------
    ndarray, shape (n,)
        ``u[j] = force[k]`` with ``k`` the last row whose ``seq[k] <= seq[j] - d`` (0 when
        none: nothing sent yet), the previous tick's ``u`` where late. A fall of ``seq``
        (the device restarted its ticks) starts the search anew.
    """
    f = np.asarray(force, float)
    n = f.size
    if seq is None:
        u = np.zeros_like(f)
        if delay < f.size:
            u[delay:] = f[:f.size - delay]
    else:
        s = np.asarray(seq, np.int64)
        if s.shape != f.shape:
            raise ConfigError(f"seq must have the forces' shape {f.shape}, got {s.shape}",
                              key="seq")
        u = np.zeros(n)
        for a, b in _runs(s, falls_only=True):
            k = np.searchsorted(s[a:b], s[a:b] - int(delay), side="right") - 1
            u[a:b] = np.where(k >= 0, f[a + np.maximum(k, 0)], 0.0)
    if late is not None:
        lt = np.asarray(late, bool)
        for k in np.flatnonzero(lt):
            if k > 0:
                u[k] = u[k - 1]
    return u


def _true_runs(mask: np.ndarray) -> list:
    """``(a, b)`` ranges where ``mask`` holds throughout."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]]).astype(np.int8)
    e = np.flatnonzero(np.diff(m))
    return [(int(a), int(b)) for a, b in zip(e[0::2], e[1::2])]


def _runs(seq: np.ndarray, falls_only: bool = False) -> list:
    """``(a, b)`` row ranges of a record's stretches of consecutive ticks (``seq`` rising
    by 1 from row to row), or with ``falls_only`` of its runs of rising ``seq`` (a fall:
    the device restarted its ticks)."""
    d = np.diff(np.asarray(seq, np.int64))
    cut = np.flatnonzero(d <= 0 if falls_only else d != 1) + 1
    e = np.concatenate([[0], cut, [seq.size]]).astype(np.int64)
    return [(int(a), int(b)) for a, b in zip(e[:-1], e[1:])]


def _input_known(seq: np.ndarray, late, max_delay: int) -> np.ndarray:
    """Rows whose applied force :func:`applied_force` names for every delay up to
    ``max_delay``: not a late row right after a gap (what the device held at the lost
    tick before it is not in the record), not one of the first ``max_delay`` ticks after
    the device restarted its ticks (forces sent before the restart may act there)."""
    n = seq.size
    ok = np.ones(n, bool)
    if late is not None:
        lt = np.asarray(late, bool)
        gap_before = np.zeros(n, bool)
        gap_before[1:] = np.diff(seq) != 1
        ok &= ~(lt & gap_before)
    for i, (a, b) in enumerate(_runs(seq, falls_only=True)):
        if i > 0:
            ok[a:b] &= seq[a:b] - seq[a] >= int(max_delay)
    return ok


def _quantum(y: np.ndarray) -> Estimate:
    """Encoder quantum ``q`` [m]: the grid the positions lie on, if they lie on one.

    A device sends ``k q`` rounded to its own number format (float32 on an 8-bit MCU:
    a relative error of 2^-24 of the value), so the step between two neighbouring values
    far from zero differs from ``q`` by that rounding, and the smallest step is not ``q``.
    The grid step is therefore estimated from all values: ``q1``, the median of the steps
    near the smallest, gives each value its whole count ``k = round(y / q1)``; then ``q``
    is the least-squares slope of ``y`` on ``k`` (every value's rounding averages out).
    The values lie on the grid when every ``|y / q - k| < 1e-3``. The interval is the
    larger of ``1e-6 q`` and three times the largest residual ``|y - k q|`` over the
    largest ``|k|`` (the error of the slope through the farthest value).

    Parameters
    ----------
    y : ndarray, shape (n,)
        Positions [m].

    Returns
    -------
    Estimate
        ``q`` with its interval, or ``0`` with the interval ``[0, smallest step]`` when
        the positions are not on a grid (``[0, inf]`` when they never change).
    """
    vals = np.unique(y)
    steps = np.diff(vals)
    steps = steps[steps > 0]
    if steps.size == 0:
        return Estimate(0.0, 0.0, math.inf, "m")
    q0 = float(steps.min())
    if q0 > 1e-9:
        q1 = float(np.median(steps[steps < 1.5 * q0]))
        k = np.round(vals / q1)
        q = float(np.dot(k, vals) / np.dot(k, k)) if np.any(k) else q1
        if np.max(np.abs(vals / q - k)) < 1e-3:
            kmax = float(np.max(np.abs(k)))
            tol = max(1e-6 * q, 3.0 * float(np.max(np.abs(vals - k * q))) / kmax)
            return Estimate(q, q - tol, q + tol, "m")
    return Estimate(0.0, 0.0, q0, "m")


def _correlation(x, f, T, max_delay, pieces=None):
    """Delay, hold and mass from the correlation of force steps with acceleration.

    The PRBS makes the force increments ``df[n]`` nearly white and much larger than the
    smooth centring part, so ``c_j = sum d2x[n+j] df[n] / sum df^2`` (``d2x[n] =
    x[n+1] - 2 x[n] + x[n-1]``) is the impulse response of ``df -> d2x``: for the exact ZOH
    with delay d, ``c_{d+1} ~ c_{d+2} ~ T^2/(2m)``; for the idealised image ``c_{d+1} ~
    T^2/m`` alone (correlation analysis, Ljung 1999 Sec. 6.1). Sensor noise is uncorrelated
    with past force steps. ``pieces``: row ranges of consecutive ticks (a difference
    across a lost STATE is left out). Returns ``(d, hold, m)``.
    """
    d2 = np.zeros_like(x)
    d2[1:-1] = x[2:] - 2 * x[1:-1] + x[:-2]
    df = np.zeros_like(f)
    df[1:] = np.diff(f)
    if pieces is not None and len(pieces) > 1:
        inside = np.zeros(x.size, bool)
        for a, b in pieces:
            inside[a + 1:b - 1] = True
        d2 = np.where(inside, d2, 0.0)
        df[[a for a, _ in pieces]] = 0.0
    D = int(max_delay) + 3
    n = x.size
    den = float(np.dot(df[:n - D], df[:n - D])) or 1.0
    c = np.array([float(np.dot(d2[j:n - D + j], df[:n - D])) / den for j in range(D)])
    j = int(np.argmax(c[1:])) + 1
    # the first of two equal taps: the earlier one if it is comparable
    if j >= 2 and c[j - 1] > 0.6 * c[j]:
        j -= 1
    nxt = c[j + 1] if j + 1 < D else 0.0
    zoh = nxt > 0.4 * c[j]
    s = c[j] + (nxt if zoh else 0.0)
    m = T * T / s if s > 0 else 0.1
    return max(min(j - 1, int(max_delay)), 0), (0 if zoh else 1), float(m)


def _stretches(x, q, W=5, margin=8, min_len=12, pieces=None):
    """Stretches of samples where the device clearly moves one way.

    The velocity sign is read from ``x[n+W] - x[n-W]``, trusted when that exceeds the
    sensor's reach ``q + 4 sigma_w`` (``sigma_w``: white noise from the median absolute
    second difference); ``margin`` (> W: the centred difference sees W samples ahead and
    behind) samples are dropped at each end. Inside a stretch
    the Coulomb friction is a constant force (no sticking: the velocity keeps its sign),
    so the model is linear there. ``pieces``: ``(a, b)`` row ranges of consecutive ticks
    with a known input (default: the whole record); a stretch never leaves its piece (a
    lost STATE, a force not known: the model restarts from a state of its own). Returns
    ``(starts, ends, dirs)`` (int64 arrays, dirs +-1).
    """
    n = x.size
    if pieces is None:
        pieces = [(0, n)]
    d2 = np.concatenate([np.diff(x[a:b], 2) for a, b in pieces if b - a > 2] or [[0.0]])
    sig = 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / math.sqrt(6.0)
    thr = 1.5 * q + 4.0 * sig + 1e-12
    starts, ends, dirs = [], [], []
    for p0, p1 in pieces:
        xp = x[p0:p1]
        m_ = xp.size
        if m_ <= 2 * W:
            continue
        dv = np.zeros(m_)
        dv[W:m_ - W] = xp[2 * W:] - xp[:m_ - 2 * W]
        sgn = np.where(dv > thr, 1, np.where(dv < -thr, -1, 0))
        k = 0
        while k < m_:
            if sgn[k] == 0:
                k += 1
                continue
            j = k
            while j < m_ and sgn[j] == sgn[k]:
                j += 1
            a_, b_ = k + margin, j - margin
            if b_ - a_ >= min_len:
                starts.append(p0 + a_)
                ends.append(p0 + b_)
                dirs.append(int(sgn[k]))
            k = j
    return (np.array(starts, np.int64), np.array(ends, np.int64), np.array(dirs, np.int64))


class _Stretched:
    """Variable-projection model of one (hold, delay) candidate on the moving stretches.

    For given ``(m, b0)`` the positions are linear in the stretch states ``(x_s, v_s)``
    and, for the ZOH, in ``(fc+, fc-)``: those are solved by linear least squares
    (the stretch states eliminated stretch by stretch), and only ``(ln m, b0)`` are
    searched (G. H. Golub & V. Pereyra, SIAM J. Numer. Anal. 10(2), 1973).
    """

    def __init__(self, x, u, T, hold, st, frac=0.0):
        from hapsim.kernels.device_sim import stretch_basis
        self.x, self.u, self.T, self.hold = x, u, T, hold
        self.frac = float(frac)
        self.starts, self.ends, self.dirs = st
        self.coulomb = hold == 0
        self._basis = stretch_basis
        n = x.size
        self._yu, self._g, self._c = np.zeros(n), np.zeros(n), np.zeros(n)
        self.idx = np.concatenate([np.arange(a, b) for a, b in zip(self.starts, self.ends)])
        lens = self.ends - self.starts
        self.sid = np.repeat(np.arange(self.starts.size), lens)
        self.offs = np.concatenate([[0], np.cumsum(lens)[:-1]])
        self.dir_i = self.dirs[self.sid]
        self._longest = int(lens.max()) if lens.size else 1
        self._bad = np.ones(self.idx.size)
        # what every _solve used to form again: the positions on the stretches and each
        # stretch's sample count (np.add.reduceat of ones: whole numbers, exact)
        self._xi = self.x[self.idx]
        self._L = np.add.reduceat(np.ones(self.idx.size), self.offs) if self.idx.size else \
            np.zeros(0)

    def _solve(self, lm, b0):
        i = self.idx
        # outside the physical range the basis overflows (a negative b0 on a light mass
        # grows as exp(|b0| t / m)) and the least squares below would get NaN (LAPACK's
        # "DLASCL illegal value" on stdout): the optimiser gets a residual far worse than
        # any physical model's instead (1 m per sample), so it steps back
        if not (_LM_RANGE[0] < lm < _LM_RANGE[1] and math.isfinite(b0)
                and abs(b0) * self.T * self._longest < 50.0 * math.exp(lm)):
            return self._bad, np.zeros(2), np.zeros(self.starts.size), np.zeros(
                self.starts.size)
        m = math.exp(lm)
        self._basis(self.u, self.starts, self.ends, m, b0, self.T, self.hold,
                    self._yu, self._g, self._c, self.frac)
        g, yu, c = self._g[i], self._yu[i], self._c[i]
        if not (np.isfinite(g).all() and np.isfinite(yu).all() and np.isfinite(c).all()):
            return self._bad, np.zeros(2), np.zeros(self.starts.size), np.zeros(
                self.starts.size)
        t = self._xi - yu
        off = self.offs
        L = self._L
        Sg = np.add.reduceat(g, off)
        Sgg = np.add.reduceat(g * g, off)
        det = L * Sgg - Sg * Sg
        det = np.where(np.abs(det) > 0, det, 1.0)

        def project(z):
            """z minus its least-squares fit by [1, g] on each stretch."""
            Sz = np.add.reduceat(z, off)
            Sgz = np.add.reduceat(g * z, off)
            cx = (Sgg * Sz - Sg * Sgz) / det
            cv = (L * Sgz - Sg * Sz) / det
            return z - cx[self.sid] - cv[self.sid] * g, cx, cv
        self._project = project
        pt, _, _ = project(t)
        phi = np.zeros(2)
        cols = []
        if self.coulomb:
            cp = np.where(self.dir_i > 0, -c, 0.0)       # -fc+ while moving +
            cn = np.where(self.dir_i < 0, c, 0.0)        # +fc- while moving -
            P = np.column_stack([project(cp)[0], project(cn)[0]])
            used = [k for k in range(2) if np.any(P[:, k])]
            if used:
                sol = np.linalg.lstsq(P[:, used], pt, rcond=None)[0]
                phi[used] = sol
            cols = [cp, cn]
        resid_t = t - (cols[0] * phi[0] + cols[1] * phi[1] if cols else 0.0)
        r, cx, cv = project(resid_t)
        return r, phi, cx, cv

    def residual(self, p):
        return -self._solve(p[0], p[1])[0]

    def full(self, p):
        """Model positions on the stretches, all parameters, and the full Jacobian."""
        lm, b0 = p
        r, phi, cx, cv = self._solve(lm, b0)
        i = self.idx
        g = self._g[i].copy()
        c = self._c[i].copy()

        def model(lm_, b0_):
            m = math.exp(lm_)
            yu, gg, cc = np.zeros_like(self.x), np.zeros_like(self.x), np.zeros_like(self.x)
            self._basis(self.u, self.starts, self.ends, m, b0_, self.T, self.hold, yu, gg, cc,
                        self.frac)
            y = yu[i] + cx[self.sid] + cv[self.sid] * gg[i]
            if self.coulomb:
                y = y + np.where(self.dir_i > 0, -cc[i] * phi[0], cc[i] * phi[1])
            return y
        y0 = model(lm, b0)
        hl, hb = 1e-6, 1e-6 * max(abs(b0), 1e-2)
        jl = (model(lm + hl, b0) - model(lm - hl, b0)) / (2 * hl)
        jb = (model(lm, b0 + hb) - model(lm, b0 - hb)) / (2 * hb)
        cols = [jl, jb]
        if self.coulomb:
            cols += [np.where(self.dir_i > 0, -c, 0.0), np.where(self.dir_i < 0, c, 0.0)]
        # Frisch-Waugh-Lovell: the stretch states partialled out of the Jacobian leave the
        # marginal covariance of (ln m, b0, fc+, fc-) (the projector of the last _solve)
        self._solve(lm, b0)
        Jr = np.column_stack([self._project(cc)[0] for cc in cols])
        params = np.concatenate([[lm, b0], phi if self.coulomb else []])
        return y0, params, Jr, 2 * self.starts.size


def _fit_stretched(x, u, T, hold, st, starts, frac=0.0):
    from scipy.optimize import least_squares
    mod = _Stretched(x, u, T, hold, st, frac)
    best = None
    for p0 in starts:
        try:
            r = least_squares(mod.residual, np.asarray(p0, float), method="lm",
                              x_scale="jac", xtol=1e-11, ftol=1e-11, gtol=1e-11, max_nfev=200)
        except (ValueError, FloatingPointError, OverflowError, np.linalg.LinAlgError):
            continue
        if np.all(np.isfinite(r.fun)) and (best is None or r.cost < best.cost):
            best = r
    return mod, best


def _search(x, f, T, late, holds, max_delay, st, d0, h0, m0, known=None, seq=None):
    """Fit every (hold, delay): the correlation's guess from three starts, then the others
    warm-started from it. With ``known = (u, d)`` (the force the device applied, from its
    account) only the holds are tried, at the device's delay ``d``; ``seq``: the rows'
    ticks (:func:`applied_force`)."""
    inv = {v: k for k, v in _HOLDS.items()}
    delays = range(int(max_delay) + 1) if known is None else (known[1],)
    if known is not None:
        d0 = known[1]
    first = (inv[h0] if inv[h0] in holds else holds[0], d0)
    order = [first] + [(h, d) for h in holds for d in delays if (h, d) != first]
    starts = [(math.log(m0), b) for b in (1.0, 0.1, 4.0)]
    cands = []
    for hname, d in order:
        u = applied_force(f, d, late, seq) if known is None else known[0]
        mod, res = _fit_stretched(x, u, T, _HOLDS[hname], st, starts)
        if res is None:
            continue
        cands.append({"hold": hname, "delay": d, "frac": 0.0, "cost": float(res.cost),
                      "_mod": mod, "_res": res})
        if len(cands) == 1:
            starts = [res.x]
    return cands


#: Grid of the sub-sample delay's fraction searched first (then refined around the best).
FRACTION_GRID = (0.25, 0.5, 0.75)
#: Half-width of the bounded search around the grid's best [periods]: one grid step.
_FRACTION_STEP = 0.25


def _search_fraction(x, T, late, st, cands, known=None, seq=None, f=None):
    """Sub-sample delays ``d + frac`` for the zero-order hold (issue 29 item 3): the
    split hold (:mod:`hapsim.analysis.subsample`) fitted at ``frac`` on
    :data:`FRACTION_GRID`, then refined around the best by a bounded scalar search of
    the cost (Brent's method, R. P. Brent, *Algorithms for Minimization without
    Derivatives*, 1973, ch. 5); every fit a candidate (``frac`` > 0) beside the whole
    delays'. The whole part: the account's delay (a device that names the force it
    applied), else the best whole delay's and the one below it (the truth lies between
    two whole delays the plain hold tried). Returns the new candidates."""
    from scipy.optimize import minimize_scalar
    zoh = [c for c in cands if c["hold"] == "zoh"]
    if not zoh:
        return []
    best = min(zoh, key=lambda c: c["cost"])
    bases = ([known[1]] if known is not None
             else sorted({best["delay"], max(best["delay"] - 1, 0)}))
    new = []
    for d in bases:
        u = known[0] if known is not None else applied_force(f, d, late, seq)
        start = [c["_res"].x for c in zoh if c["delay"] == d] or [best["_res"].x]
        seen = {}

        def fit(fr, d=d, u=u, start=start, seen=seen):
            fr = float(fr)
            if fr in seen:
                return seen[fr]
            mod, res = _fit_stretched(x, u, T, _HOLDS["zoh"], st, start, fr)
            c = None if res is None else {"hold": "zoh", "delay": d, "frac": fr,
                                          "cost": float(res.cost), "_mod": mod,
                                          "_res": res}
            if c is not None and mod.coulomb:
                # the profile over the fraction on the refined cost (Coulomb reversals
                # inside a stretch), as the best whole delay's is: a refined best beside
                # unrefined neighbours made every neighbour "ruled out" (intervals of
                # zero width that missed the truth, 6 of 30 devices)
                ref = _refine(mod, res.x)
                c["_ref"] = ref if ref is not None and ref[4] < c["cost"] else None
                if c["_ref"] is not None:
                    c["cost"] = c["_ref"][4]
            seen[fr] = c
            if c is not None:
                new.append(c)
            return c
        grid = [(fr, fit(fr)) for fr in FRACTION_GRID]
        base = [c for c in zoh if c["delay"] == d]
        pts = [(0.0, base[0] if base else None)] + grid
        ok = [(fr, c) for fr, c in pts if c is not None]
        if not ok:
            continue
        fb = min(ok, key=lambda t: t[1]["cost"])[0]
        lo, hi = max(fb - _FRACTION_STEP, 0.0), min(fb + _FRACTION_STEP, 0.999)
        if hi - lo > 1e-3:
            minimize_scalar(lambda fr: (fit(fr) or {"cost": math.inf})["cost"],
                            bounds=(lo, hi), method="bounded",
                            options={"xatol": 2e-3, "maxiter": 10})
    # the whole delays beside them on the same (refined) cost: the profile's ends
    near = set(bases) | {b + 1 for b in bases}
    for c in zoh:
        if c["delay"] in near and "_ref" not in c and c["_mod"].coulomb:
            ref = _refine(c["_mod"], c["_res"].x)
            c["_ref"] = ref if ref is not None and ref[4] < c["cost"] else None
            if c["_ref"] is not None:
                c["cost"] = c["_ref"][4]
    return new


def _delay_interval(cands, best, close, n_lr, s_best, crit, nu):
    """The delay ``d + frac`` [periods] as an :class:`Estimate`: the best candidate's, its
    interval the set the likelihood ratio does not rule out among the zero-order hold's
    candidates (whole and sub-sample), each end interpolated to where the ratio crosses
    its bound between the last candidate inside and the first outside (linear in the
    ratio's signed root, exact for a quadratic profile); an end with no candidate outside beyond it stays at the last one inside.
    Under the idealised hold: the whole delay, its interval ``delay_range``."""
    def total(c):
        return c["delay"] + c.get("frac", 0.0)
    zoh = sorted((c for c in cands if c["hold"] == "zoh"), key=total)
    if best["hold"] != "zoh" or not zoh:
        d = [c["delay"] for c in cands if close(c)] or [best["delay"]]
        return Estimate(float(best["delay"]), float(min(d)), float(max(d)), "periods")

    def h(c):
        # the signed root of the likelihood ratio: linear in the delay where the cost is
        # quadratic about its minimum (a chord of the ratio itself, convex, crossed its
        # bound too early: an interval 0.427..0.433 for a true 0.4345)
        return math.sqrt(max(n_lr * math.log(max(c["cost"], 0.5 * nu * POSITION_FLOOR ** 2)
                                             / s_best), 0.0))
    bound = math.sqrt(crit)
    inside = [i for i, c in enumerate(zoh) if close(c)]
    if not inside:
        v = total(best)
        return Estimate(v, v, v, "periods")
    i0, i1 = inside[0], inside[-1]

    def cross(i_in, i_out):
        a, b = zoh[i_in], zoh[i_out]
        ha, hb = h(a), h(b)
        t = 0.0 if not hb > ha else min(max((bound - ha) / (hb - ha), 0.0), 1.0)
        return total(a) + t * (total(b) - total(a))
    lo = cross(i0, i0 - 1) if i0 > 0 else total(zoh[i0])
    hi = cross(i1, i1 + 1) if i1 + 1 < len(zoh) else total(zoh[i1])
    v = total(best)
    return Estimate(v, min(lo, v), max(hi, v), "periods")


class _BlockDifference:
    """The refinement's Jacobian by forward differences, as scipy's sparse finite difference
    forms it, in ``k + 2`` evaluations.

    The residual of row ``r`` depends on the ``k`` shared parameters and on its own
    stretch's two states only (``k + sid[r]``, ``k + ns + sid[r]``): every shared
    parameter is stepped alone, every stretch's initial position at once, then every
    initial velocity at once (A. R. Curtis, M. J. D. Powell & J. K. Reid, J. Inst. Math.
    Appl. 13, 1974). Each entry is ``(f(x + h_j e_j)_r - f(x)_r) / ((x_j + h_j) - x_j)``
    with scipy's step ``h_j = sqrt(eps) sign(x_j) max(1, |x_j|)``
    (``scipy.optimize.approx_derivative``, ``method='2-point'``): the same numbers, bit
    for bit, as ``least_squares(..., jac_sparsity=S)`` computes (its column groups stepped
    together too, the structure exact), returned in the same canonical CSR layout, without
    the sparse indexing it repeats at every call (two thirds of a fit's time).
    ``tests/test_device_fit_jacobian.py`` compares the two.

    Parameters
    ----------
    fun : callable
        ``fun(p) -> ndarray, shape (n_rows,)``, the residual; a new array each call.
    k : int
        Shared parameters (columns ``0 .. k-1``, dense).
    sid : ndarray of int, shape (n_rows,)
        Each row's stretch.
    ns : int
        Stretches (columns ``k .. k+ns-1``: initial positions; ``k+ns .. k+2ns-1``:
        initial velocities).
    """

    def __init__(self, fun, k, sid, ns):
        self._fun, self.k, self.sid, self.ns = fun, int(k), np.asarray(sid), int(ns)
        m = self.sid.size
        n = self.k + 2 * self.ns
        self.shape = (m, n)
        w = self.k + 2
        self._cols = np.empty((m, w), np.int32)
        self._cols[:, :self.k] = np.arange(self.k)
        self._cols[:, self.k] = self.k + self.sid
        self._cols[:, self.k + 1] = self.k + self.ns + self.sid
        self._indices = self._cols.ravel()
        self._indptr = np.arange(0, m * w + 1, w, dtype=np.int32)
        self._groups = [np.arange(n) == j for j in range(self.k)]
        self._groups += [(np.arange(n) >= self.k) & (np.arange(n) < self.k + self.ns),
                         np.arange(n) >= self.k + self.ns]
        self._last = None

    def fun(self, p):
        """The residual at ``p``, remembered for the Jacobian at the same point."""
        f = np.atleast_1d(self._fun(p))
        self._last = (np.array(p, float), f.copy())
        return f

    def __call__(self, p):
        """The Jacobian at ``p``: a ``scipy.sparse.csr_array`` of shape ``(n_rows, n)``."""
        from scipy.sparse import csr_array
        x0 = np.asarray(p, float)
        if self._last is not None and np.array_equal(self._last[0], x0):
            f0 = self._last[1]
        else:
            f0 = np.atleast_1d(self._fun(x0.copy()))
        # scipy's _compute_absolute_step for '2-point' (sign 1 at 0)
        sign = (x0 >= 0).astype(float) * 2 - 1
        h = np.finfo(np.float64).eps ** 0.5 * sign * np.maximum(1.0, np.abs(x0))
        m = self.shape[0]
        data = np.empty((m, self.k + 2))
        for g, e in enumerate(self._groups):
            x = x0 + h * e
            dx = x - x0
            df = np.atleast_1d(self._fun(x)) - f0
            data[:, g] = df / dx[self._cols[:, g]]
        return csr_array((data.ravel(), self._indices, self._indptr), shape=self.shape)


def _refine(mod, p_lin):
    """Nonlinear output error on the stretches (Coulomb friction with the mock's stick and
    reversal rules), from the variable-projection solution: a velocity that reverses for a
    sample inside a stretch (too briefly for the positions to show) is then modelled.

    Returns ``(y, theta, J_theta_partialled, n_nuisance, cost)`` or None.
    """
    from scipy.optimize import least_squares

    from hapsim.kernels.device_sim import simulate_device
    _, phi, cx, cv = mod._solve(p_lin[0], p_lin[1])
    k = 4 if mod.coulomb else 2
    ns = mod.starts.size
    i = mod.idx
    out = np.zeros_like(mod.x)
    xi = mod.x[i]

    def resid(p):
        fp_, fn = (p[2], p[3]) if mod.coulomb else (0.0, 0.0)
        simulate_device(mod.u, math.exp(p[0]), p[1], fp_, fn, mod.starts, mod.ends,
                        np.ascontiguousarray(p[k:k + ns]),
                        np.ascontiguousarray(p[k + ns:k + 2 * ns]), mod.T, mod.hold, out,
                        mod.frac)
        return out[i] - xi
    p0 = np.concatenate([[p_lin[0], p_lin[1]], phi if mod.coulomb else [], cx, cv])
    rows = np.arange(i.size)
    jac = _BlockDifference(resid, k, mod.sid, ns)
    try:
        r = least_squares(jac.fun, p0, method="trf", x_scale="jac", jac=jac,
                          xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=60)
    except (ValueError, FloatingPointError, OverflowError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(r.fun)):
        return None
    J = r.jac.toarray() if hasattr(r.jac, "toarray") else np.asarray(r.jac)
    # Frisch-Waugh-Lovell: partial the stretch states out, stretch by stretch
    off = mod.offs
    a1 = J[rows, k + mod.sid]
    a2 = J[rows, k + ns + mod.sid]
    s11 = np.add.reduceat(a1 * a1, off)
    s12 = np.add.reduceat(a1 * a2, off)
    s22 = np.add.reduceat(a2 * a2, off)
    det = s11 * s22 - s12 * s12
    det = np.where(np.abs(det) > 0, det, 1.0)
    cols = []
    for c in range(k):
        zc = J[:, c]
        t1 = np.add.reduceat(a1 * zc, off)
        t2 = np.add.reduceat(a2 * zc, off)
        c1 = (s22 * t1 - s12 * t2) / det
        c2 = (s11 * t2 - s12 * t1) / det
        cols.append(zc - c1[mod.sid] * a1 - c2[mod.sid] * a2)
    y = r.fun + xi
    return y, r.x[:k], np.column_stack(cols), 2 * ns, float(r.cost)


def _explains(resid, q: float) -> tuple[bool, float, float]:
    """The verdict's test (module notes): ``(explained, rms, floor)``, the residual's RMS
    against the sensor's ``floor = sqrt(q^2/12 + sigma_w^2)`` [m]."""
    resid = np.asarray(resid, float)
    rms = float(math.sqrt(np.mean(resid ** 2)))
    d2 = np.diff(resid, 2)
    sig_w = float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))
    floor = math.sqrt(q ** 2 / 12.0 + sig_w ** 2)
    return bool(rms <= 2.0 * floor + 3 * POSITION_FLOOR), rms, floor


def _effective_samples(r, offs, lag: int) -> float:
    """Independent samples a residual is worth: ``N / tau`` with ``tau = 1 + 2 sum_k
    (1 - k/(L+1)) rho_k`` (``k = 1 .. L``, Bartlett weights, ``rho_k`` the residual's
    autocorrelation pooled over the stretches, never across two), at least 1 sample and
    at most ``N``. The integrated autocorrelation time of a stationary series (M. B.
    Priestley, *Spectral Analysis and Time Series*, 1981, Sec. 5.3; the Newey-West weights
    of :func:`_hac`): a quantiser's error on a slow motion is a sawtooth correlated over
    many samples, and a likelihood ratio that counts its ``N`` samples as independent
    tells candidates apart that the record cannot."""
    r = np.asarray(r, float)
    n = r.size
    den = float(np.dot(r, r))
    if n < 2 or den <= 0:
        return float(max(n, 1))
    bounds = list(zip(offs, list(offs[1:]) + [n]))
    tau = 1.0
    for k in range(1, int(lag) + 1):
        num = sum(float(np.dot(r[a:b - k], r[a + k:b])) for a, b in bounds if b - a > k)
        tau += 2.0 * (1.0 - k / (lag + 1.0)) * num / den
    return float(min(max(n / max(tau, 1.0), 1.0), n))


def _best_residual(best) -> np.ndarray:
    """The best candidate's residual on its stretches [m] (its refinement's when kept)."""
    mod = best["_mod"]
    if best.get("_ref") is not None:
        return best["_ref"][0] - mod.x[mod.idx]
    return mod.residual(best["_res"].x)


def _ambiguity(best, rival, nu, n_eff, q) -> str:
    """The sentence naming two delays a record cannot tell apart."""
    def said(c_):
        return (f"d = {c_['delay']} ({c_['hold']} hold, residual RMS "
                f"{math.sqrt(2.0 * c_['cost'] / nu) * 1e6:.3g} um)")
    enc = f"a {q * 1e6:.3g} um encoder" if q > 0 else "the sensor's noise"
    return (f"the delay is ambiguous: {said(best)} and {said(rival)} explain the record "
            f"alike (likelihood ratio within the {LEVEL:.1%} chi-square bound over "
            f"{n_eff:.0f} effective samples of {nu}: the residual of {enc} is correlated)")


#: Variance given to a parameter the record does not determine (its Jacobian column is
#: zero, or lies in the span of the others', after scaling): finite, so that weighted sums
#: of the covariance stay numbers, and so large that any interval through it is the whole
#: line (a mass interval of exp(1e150): refused as not determined).
UNDETERMINED_VARIANCE = 1e300


def _bread(JtJ):
    """The inverse of the normal matrix, column-scaled, and which parameters it leaves
    undetermined.

    ``np.linalg.pinv(JtJ)`` cuts singular values below 1e-15 of the largest: a parameter
    whose sensitivity is tiny beside another's (a mass of 6.5e11 kg fitted to a record
    of straight stretches, beside the Coulomb terms) got variance ZERO, a narrow interval
    around a wrong value. Scaling every column to unit norm first (the covariance is
    invariant to it: Jacobi scaling) leaves only the collinearity the record really has;
    the directions of the scaled matrix below the rank tolerance of
    ``numpy.linalg.matrix_rank`` (largest eigenvalue times size times the machine
    epsilon) are not determined: every parameter with weight on them beyond
    ``sqrt(eps)`` is marked undetermined.

    Returns ``(bread, undetermined)``: ndarray (p, p) and a bool mask (p,).
    """
    p = JtJ.shape[0]
    d = np.sqrt(np.maximum(np.diag(JtJ), 0.0))
    ok = np.isfinite(d) & (d > 0.0)
    s = np.where(ok, d, 1.0)
    A = JtJ / np.outer(s, s)
    A[~ok, :] = 0.0
    A[:, ~ok] = 0.0
    lam, V = np.linalg.eigh(A)
    eps = np.finfo(float).eps
    tol = max(float(lam.max(initial=0.0)), 0.0) * p * eps
    keep = lam > tol
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    bread = (V * inv) @ V.T / np.outer(s, s)
    null = V[:, ~keep]
    undetermined = ~ok | (np.abs(null).max(axis=1, initial=0.0) > math.sqrt(eps))
    return bread, undetermined


def _hac(J, r, lag, extra=0):
    """Newey-West covariance of the least-squares parameters (Newey & West 1987); a
    parameter the record does not determine (:func:`_bread`) has variance
    :data:`UNDETERMINED_VARIANCE` and no covariance with the others."""
    n, p = J.shape
    JtJ = J.T @ J
    bread, undetermined = _bread(JtJ)
    g = J * r[:, None]
    S = g.T @ g
    for lg in range(1, min(lag, n - 1) + 1):
        w = 1.0 - lg / (lag + 1.0)
        G = g[lg:].T @ g[:-lg]
        S += w * (G + G.T)
    cov = bread @ S @ bread * n / max(n - p - extra, 1)
    cov += POSITION_FLOOR ** 2 * bread
    if np.any(undetermined):
        cov[undetermined, :] = 0.0
        cov[:, undetermined] = 0.0
        cov[undetermined, undetermined] = UNDETERMINED_VARIANCE
    return cov


#: Asymptotic efficiency of the median absolute deviation as a Gaussian scale estimator
#: (P. J. Huber & E. M. Ronchetti, *Robust Statistics*, 2nd ed., 2009, Sec. 5.5: 36.7 %).
MAD_EFFICIENCY = 0.367
#: Integrated autocorrelation time of the second differences of white noise: their
#: autocorrelation is -4/6 at lag 1 and 1/6 at lag 2, so ``1 + 2 (16 + 1) / 36``.
_D2_TAU = 1.0 + 2.0 * (16.0 + 1.0) / 36.0


def _noise_white(r, offs, delta, z):
    """The white sensor noise of an unquantised record from its residual's second
    differences (module notes): ``sigma = 1.4826 median|D2 r| / sqrt(6)``, the differences
    taken inside each stretch (``offs``: their first rows), never across two.

    A model error is smooth between the device's events (a stick, a reversal) and its
    second differences are ~0 but for a few samples there, which the median ignores: the
    residual's own variance counted it as noise (a device with no noise got an interval
    of 8-11 um, the model's Coulomb mismatch). The interval is the median absolute
    deviation's normal one, ``sigma (1 +- z / sqrt(2 MAD_EFFICIENCY N / _D2_TAU))``, its
    lower end less the model output's own share ``delta`` and POSITION_FLOOR (in
    quadrature), at least 0."""
    r = np.asarray(r, float)
    edges = list(np.asarray(offs, np.int64)) + [r.size]
    d2 = np.concatenate([np.diff(r[a:b], 2) for a, b in zip(edges[:-1], edges[1:])
                         if b - a >= 3] or [np.zeros(0)])
    if d2.size < 8:
        return Estimate(0.0, 0.0, math.inf, "m")
    sig = float(1.4826 * np.median(np.abs(d2)) / math.sqrt(6.0))
    h = z / math.sqrt(2.0 * MAD_EFFICIENCY * d2.size / _D2_TAU)
    lo2 = (sig * max(1.0 - h, 0.0)) ** 2 - (delta ** 2 + POSITION_FLOOR ** 2)
    hi = sig * (1.0 + h) + POSITION_FLOOR
    return Estimate(sig, math.sqrt(lo2) if lo2 > 0 else 0.0, hi, "m")


def _chi2_ppf_1(p: float) -> float:
    """The quantile ``p`` of the chi-square distribution with one degree of freedom.

    Parameters
    ----------
    p : float
        Probability, in (0, 1).

    Returns
    -------
    float
        ``2 gammaincinv(1/2, p)``: the formula of ``scipy.stats.chi2.ppf(p, 1)``, the same
        number bit for bit (scipy 1.1x), without importing ``scipy.stats`` (~1 CPU-s in
        each process that fits a device; the quantiles here are of ``norm``, ``t`` and
        ``chi2`` only, taken from ``scipy.special`` as ``scipy.stats`` takes them).
    """
    from scipy.special import gammaincinv
    return float(2 * gammaincinv(0.5, p))


def _noise(y, xm, q, delta, z, dof, offs=None):
    """ML estimate and profile interval of the sensor noise (module notes); an
    unquantised record's from its second differences (:func:`_noise_white`)."""
    from scipy.special import log_ndtr
    r = y - xm
    if q <= 0 and offs is not None:
        return _noise_white(r, offs, delta, z)
    crit = 0.5 * _chi2_ppf_1(LEVEL)
    floor2 = delta ** 2 + POSITION_FLOOR ** 2
    if q > 0:
        def loglik(sig):
            s = np.sqrt(sig * sig + floor2)
            hi = (r + q / 2) / s
            lo = (r - q / 2) / s
            # log(Phi(hi) - Phi(lo)) computed stably
            la, lb = log_ndtr(hi), log_ndtr(lo)
            return float(np.sum(la + np.log1p(-np.exp(np.minimum(lb - la, -1e-300)))))
    else:
        ss = float(np.sum(r * r)) * r.size / max(r.size - dof, 1)
        n = r.size

        def loglik(sig):
            s2 = sig * sig + floor2
            return -0.5 * (ss / s2 + n * math.log(s2))
    from scipy.optimize import brentq, minimize_scalar
    with np.errstate(divide="ignore", invalid="ignore"):
        return _noise_interval(loglik, r, crit)


def _noise_interval(loglik, r, crit):
    from scipy.optimize import brentq, minimize_scalar
    top = max(1e-6, 20.0 * float(np.std(r)) + 1e-9)
    res = minimize_scalar(lambda ls: -loglik(math.exp(ls)), bounds=(math.log(1e-11),
                          math.log(top)), method="bounded", options={"xatol": 1e-6})
    s_hat = math.exp(res.x)
    l_hat = -res.fun
    if loglik(0.0) > l_hat:
        s_hat, l_hat = 0.0, loglik(0.0)

    def g(sig):
        return loglik(sig) - (l_hat - crit)
    lo = 0.0 if g(0.0) >= 0 else brentq(g, 0.0, max(s_hat, 1e-12), xtol=1e-13)
    hi = brentq(g, max(s_hat, 1e-12), top * 10, xtol=1e-13) if g(top * 10) < 0 else top * 10
    return Estimate(float(s_hat), float(lo), float(hi), "m")


#: A mass interval wider than this ratio hi / lo is "not identified".
MASS_SPAN = 100.0
#: Replicates of the quantised record (:func:`_grid_replicates`).
REPLICATES = 24


def _grid_replicates(mod, ym, theta, q, sigma, reps=REPLICATES, seed=0):
    """Estimates from records the fitted model would give through the same encoder.

    A quantiser's error is a deterministic, bounded function of the true position: on a
    slow motion it is a sawtooth correlated over many samples, and its effect on the
    estimates is neither white nor, on a record of few counts, small or unbiased (the
    estimator is nonlinear in the data). Its only unknown is where the grid lies relative
    to the motion. So the fitted model's positions ``ym`` (stretch states, forces and all)
    are passed ``reps`` times through the encoder with a random grid phase ``U(-q/2,
    q/2)`` after Gaussian noise ``sigma`` (the model of the module notes), and refitted
    exactly as the record was (same stretches, hold and delay, the variable projection
    from ``theta``, then the nonlinear refinement): a parametric bootstrap (B. Efron &
    R. Tibshirani, *An Introduction to the Bootstrap*, 1993, Sec. 6.5 and 10.2 for the
    bias). The spread and mean shift of the replicates are the quantisation's effect on
    the estimates at the fitted device.

    Parameters
    ----------
    mod : _Stretched
        The chosen candidate's model (its stretches, hold, applied force).
    ym : ndarray, shape (n_s,)
        The fitted model's positions on the stretches [m].
    theta : ndarray, shape (k,)
        Fitted ``(ln m, b0[, fc+, fc-])``.
    q, sigma : float
        Encoder quantum [m] (> 0) and noise standard deviation [m].
    reps : int
        Replicates.
    seed : int
        Seed of the grid phases and noise (the fit is deterministic).

    Returns
    -------
    ndarray, shape (r, k)
        The replicates' estimates (``r <= reps``: those whose fit converged).
    """
    rng = np.random.default_rng(seed)
    st = (mod.starts, mod.ends, mod.dirs)
    out = []
    y = mod.x.copy()
    for _ in range(reps):
        ph = rng.uniform(-0.5, 0.5)
        e = sigma * rng.standard_normal(ym.size) if sigma > 0 else 0.0
        y[mod.idx] = q * (np.round((ym + e) / q + ph) - ph)
        m2, res = _fit_stretched(y, mod.u, mod.T, mod.hold, st, [theta[:2]], mod.frac)
        if res is None:
            continue
        th = None
        if mod.coulomb:
            ref = _refine(m2, res.x)
            if ref is not None and ref[4] < res.cost:
                th = ref[1]
        if th is None:
            th = m2.full(res.x)[1]
        if np.all(np.isfinite(th)):
            out.append(np.asarray(th, float)[:theta.size])
    return np.array(out).reshape(-1, theta.size)


def _estimate(value, sd, z, unit, floor=0.0):
    h = z * sd + floor
    return Estimate(float(value), float(value - h), float(value + h), unit)


def fit_device(position, force, period: float, *, late=None, max_delay: int = 5,
               holds=("zoh", "ideal"), lag: int = 50, applied=None, seq=None,
               ambiguous_delay: str = "range") -> DeviceFit:
    """Identify mass, friction, Coulomb friction, delay, hold, quantum and noise.

    Parameters
    ----------
    position : array_like, shape (n,)
        Positions the device reported, one per sample [m]; the device at rest at sample 0.
    force : array_like, shape (n,)
        Forces the host sent answering each sample [N] (after its clamp).
    period : float > 0
        Sample period T [s].
    late : array_like of bool, shape (n,), optional
        Samples the device reported holding an older force.
    max_delay : int >= 0
        Largest delay tried [samples].
    holds : sequence of {"zoh", "ideal"}
        Holds tried.
    lag : int >= 1
        Newey-West lag [samples].
    applied : hapsim.applied.AppliedAccount, optional
        The account of the force the device applied per sample (its ``force_seq``): the
        fit is then driven by ``applied.applied``, the delay is the one the device showed
        (``applied.delay``, exact: ``delay_range`` is that one value) and ``late`` and
        ``max_delay`` are not used. Without it, the delays ``0 .. max_delay`` are tried
        on ``force`` (a device that names no applied force); a row whose applied force
        the account does not know (``applied.known`` False) is left out of the fit.
    seq : array_like of int, shape (n,), optional
        The device's tick (STATE seq) of each row. Rows lost from the record (a STATE that
        never arrived) are gaps: every stretch of consecutive ticks is fitted, each
        from its own initial state with the mass and frictions shared (multiple shooting),
        and without an account the force answering row ``k`` acts from tick
        ``seq[k] + d`` (:func:`applied_force`). Default: no row lost.
    ambiguous_delay : {"range", "refuse"}
        When the delays are searched and another delay than the best's fits the record as
        well (the likelihood ratio, counted on the residual's effective samples, within
        the chi-square bound): ``"range"`` returns the fit with ``delay_certain`` False,
        ``delay_range`` holding every such delay, the intervals covering their estimates
        and the verdict naming two of them; ``"refuse"`` raises (a model that explains
        the data; one that does not says so in its verdict either way).

    Returns
    -------
    DeviceFit

    Raises
    ------
    ConfigError
        Arrays of different lengths, an invalid period, delay or hold.
    IdentificationError
        A record that cannot be identified: fewer than 200 samples, non-finite values, a
        force that never acts (all zero), too little motion, no model fitted, a fit that
        fails numerically; with ``ambiguous_delay="refuse"``, a delay it cannot tell.
    """
    from scipy.special import ndtri, stdtrit
    x = np.asarray(position, float)
    f = np.asarray(force, float)
    if x.ndim != 1 or x.shape != f.shape:
        raise ConfigError(f"position and force must be 1-D of one length, got {x.shape} "
                          f"and {f.shape}", key="position")
    if x.size < 200:
        raise IdentificationError(f"too short a record: {x.size} samples, at least 200 are "
                                  f"needed")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(f))):
        raise IdentificationError("the record holds non-finite samples")
    if not np.any(f):
        raise IdentificationError("the force is zero throughout: nothing excites the "
                                  "device")
    if not (math.isfinite(period) and period > 0):
        raise ConfigError(f"must be a positive number [s], got {period!r}", key="period")
    if isinstance(max_delay, bool) or int(max_delay) != max_delay or max_delay < 0:
        raise ConfigError(f"must be a whole number >= 0, got {max_delay!r}", key="max_delay")
    if ambiguous_delay not in ("range", "refuse"):
        raise ConfigError(f"unknown choice {ambiguous_delay!r}; valid: range, refuse",
                          key="ambiguous_delay")
    for h in holds:
        if h not in _HOLDS:
            raise ConfigError(f"unknown hold {h!r}; valid: zoh, ideal", key="hold")
    T = float(period)
    n = x.size
    if seq is not None:
        seq = np.asarray(seq, np.int64)
        if seq.shape != x.shape:
            raise ConfigError(f"seq must have the positions' shape {x.shape}, got "
                              f"{seq.shape}", key="seq")
    z = float(ndtri(0.5 + LEVEL / 2))          # scipy.stats.norm.ppf's own formula
    cands = []
    known = None
    # the pieces of the record a model may run through: consecutive ticks whose input is
    # known (a lost STATE, a force the account cannot name, restart the model)
    usable = np.ones(n, bool)
    if applied is not None:
        u = np.asarray(applied.applied, float)
        if u.shape != x.shape or not np.all(np.isfinite(u)):
            raise ConfigError(f"the applied force must be finite, of the positions' length "
                              f"{x.shape}, got {u.shape}", key="applied")
        if applied.delay < 0:
            raise IdentificationError("the device never reported applying a force (no "
                                      "STATE with FORCE_APPLIED): nothing to fit")
        if not np.any(u):
            raise IdentificationError("the applied force is zero throughout: nothing "
                                      "excited the device")
        known = (u, int(applied.delay))
        kn = getattr(applied, "known", None)
        if kn is not None and np.shape(kn) == x.shape:
            usable &= np.asarray(kn, bool)
    elif seq is not None:
        usable &= _input_known(seq, late, int(max_delay))
    ticks = np.arange(n) if seq is None else seq
    pieces = [(a + int(i0), a + int(i1)) for a, b in _runs(ticks)
              for i0, i1 in _true_runs(usable[a:b])]
    if known is not None:
        # the correlation sees the applied force: its delay is 0 by construction
        _, h0, m0 = _correlation(x, u, T, 2, pieces)
        d0 = known[1]
    else:
        d0, h0, m0 = _correlation(x, f, T, max_delay, pieces)
    q = _quantum(x)
    st = _stretches(x, q.value, pieces=pieces)
    if st[0].size == 0 or int(np.sum(st[1] - st[0])) < 100:
        raise IdentificationError("the device hardly moved: fewer than 100 samples of "
                                  "clear motion (raise --force-limit or --duration)")
    cands = _search(x, f, T, late, holds, max_delay, st, d0, h0, m0, known, seq)
    if cands:
        # a stretch the best model misses by far hides an unseen reversal of the velocity
        # (Coulomb friction flips there): drop such stretches and fit again
        best = min(cands, key=lambda c: c["cost"])
        mod = best["_mod"]
        r = mod.residual(best["_res"].x)
        ss = np.add.reduceat(r * r, mod.offs) / np.diff(np.append(mod.offs, r.size))
        keep = ss <= 9.0 * float(np.median(ss)) + POSITION_FLOOR ** 2
        if not np.all(keep) and np.sum(keep) >= 3:
            st = tuple(a_[keep] for a_ in st)
            b_ = best
            cands = _search(x, f, T, late, holds, max_delay, st, b_["delay"],
                            _HOLDS[b_["hold"]], math.exp(b_["_res"].x[0]), known, seq)
    if not cands:
        raise IdentificationError("no model could be fitted to the record")
    if "zoh" in holds:
        # sub-sample delays d + frac under the zero-order hold (the split hold)
        cands += _search_fraction(x, T, late, st, cands, known, seq, f)
    # the nonlinear refinement (Coulomb reversals inside a stretch) for the two best
    cands.sort(key=lambda c: c["cost"])
    # (and the best whole delay's: a sub-sample candidate the ratio cannot tell from it
    # gives way to it below, refined as it would have been without them)
    whole = [c for c in cands if c.get("frac", 0.0) == 0.0][:2]
    for c in cands[:2] + [c for c in whole if c not in cands[:2]]:
        if "_ref" in c:
            continue                       # refined already (the fraction's profile)
        c["_ref"] = _refine(c["_mod"], c["_res"].x) if c["_mod"].coulomb else None
        if c["_ref"] is not None and c["_ref"][4] < c["cost"]:
            c["cost"] = c["_ref"][4]
        else:
            c["_ref"] = None
    best = min(cands, key=lambda c: c["cost"])
    nu = best["_mod"].idx.size
    crit = _chi2_ppf_1(LEVEL)
    s_best = max(best["cost"], 0.5 * nu * POSITION_FLOOR ** 2)
    mod = best["_mod"]
    # the likelihood ratio's samples: when the delays are searched, the residual's
    # effective ones (a quantiser's error is correlated: counted as nu independent
    # samples, the ratio told apart delays the record cannot, and the best was a wrong
    # delay); from an account of the applied force (one delay, the holds alone) all
    n_lr = float(nu) if known is not None else _effective_samples(
        _best_residual(best), mod.offs, lag)

    def close(c):
        return n_lr * math.log(max(c["cost"], 0.5 * nu * POSITION_FLOOR ** 2) / s_best) <= crit

    # the fraction's interval on the residual's effective samples (its error is
    # correlated: a model error, a quantiser; counted as nu independent samples, 2 of 30
    # random sub-sample delays fell outside intervals stated at 99.9 %)
    n_fr = n_lr if known is None else _effective_samples(_best_residual(best), mod.offs, lag)

    def close_fr(c):
        return n_fr * math.log(max(c["cost"], 0.5 * nu * POSITION_FLOOR ** 2) / s_best) <= crit

    delay_estimate = _delay_interval(cands, best, close_fr, n_fr, s_best, crit, nu)
    if best.get("frac", 0.0) > 0.0:
        # a whole delay the ratio does not rule out is the model kept (the simpler one:
        # a whole delay gives today's estimates bit for bit); its interval stays
        whole = [c for c in cands if c["hold"] == best["hold"] and c.get("frac", 0.0) == 0.0
                 and close(c) and delay_estimate.lo <= c["delay"] <= delay_estimate.hi]
        if whole:
            best = min(whole, key=lambda c: c["cost"])
            mod = best["_mod"]
    # every whole delay not ruled out, under either hold (a sub-sample delay's whole part
    # is in delay_estimate, not here: d + 0.999 is no ambiguity between d and d + 1)
    same = sorted({c["delay"] for c in cands if close(c) and c.get("frac", 0.0) == 0.0}
                  or {best["delay"]})
    other_hold = any(c["hold"] != best["hold"] and close(c) for c in cands)
    ambiguity = None
    if len(same) > 1:
        rival = min((c for c in cands if c["delay"] != best["delay"] and close(c)),
                    key=lambda c_: c_["cost"])
        ambiguity = _ambiguity(best, rival, nu, n_lr, q.value)
        if ambiguous_delay == "refuse" and _explains(_best_residual(best), q.value)[0]:
            raise IdentificationError(
                f"{ambiguity}; no delay is chosen -- raise --force-limit or --duration for "
                f"more motion, or use a protocol whose device reports the force it applied")
    if best.get("_ref") is not None:
        ym, p, J, n_nuis, _ = best["_ref"]
    else:
        ym, p, J, n_nuis = mod.full(best["_res"].x)
    xi = x[mod.idx]
    r = ym - xi
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r)) and np.all(np.isfinite(p))):
        # never hand LAPACK a non-finite matrix (it prints "DLASCL illegal value" on stdout)
        raise IdentificationError("the fit diverged (non-finite model): the record does "
                                  "not determine the device (raise --force-limit or "
                                  "--duration, or check the device's delay)")
    # the model output's own uncertainty per sample: a fitted linear model of k
    # parameters carries k/N of the error variance on average
    delta = float(np.sqrt(np.mean(r * r) * (p.size + n_nuis) / max(r.size, 1)))
    # the fit's own error at the samples is somewhere between 0 and ~2 delta (it is
    # correlated with the noise it partly absorbed): the interval spans both ends
    noise = _noise(xi, ym, q.value, delta, z, p.size + n_nuis, offs=mod.offs)
    n_hi = _noise(xi, ym, q.value, 0.0, z, p.size + n_nuis, offs=mod.offs)
    n_lo = _noise(xi, ym, q.value, 2.0 * delta, z, p.size + n_nuis, offs=mod.offs)
    noise = Estimate(noise.value, min(noise.lo, n_lo.lo), max(noise.hi, n_hi.hi), "m")
    # a quantised record: the quantiser's effect on the estimates, from replicates of the
    # record through the same encoder (_grid_replicates, in intervals() below)
    # encoder steps on the fitted stretches: between two steps a quantised record only
    # says the device is inside one cell
    counts = -1
    if q.value > 0:
        steps = np.diff(xi) != 0
        steps[mod.offs[1:] - 1] = False               # not across two stretches
        counts = int(np.sum(steps))
        n_par = p.size + n_nuis
        if counts <= n_par:
            raise IdentificationError(
                f"the record does not determine the device: {counts} encoder steps "
                f"({q.value * 1e6:.3g} um) on the {mod.starts.size} stretches of clear "
                f"motion, for {n_par} parameters (each stretch's position and velocity, "
                f"the mass and frictions); between steps the encoder only says the "
                f"handle is inside one cell (raise --force-limit or --duration)")
    t_q = float(stdtrit(max(REPLICATES - 1, 1), 0.5 + LEVEL / 2))   # scipy.stats.t.ppf's

    def intervals(mod_c, ym_c, p_c, J_c, nn_c):
        """(mass, fric, cp, cn, cm, asym) of one candidate: the union of the linearised
        interval and, on a quantised record, the replicates' bias-corrected prediction
        interval ``theta - bias +- t_(R-1) s sqrt(1 + 1/R)`` (the bias itself estimated
        from R replicates: Student's t, R - 1 degrees of freedom)."""
        cov_c = _hac(J_c, ym_c - x[mod_c.idx], lag, nn_c)
        boot = None
        if q.value > 0:
            boot = _grid_replicates(mod_c, ym_c, p_c, q.value, noise.value)
            if boot.shape[0] < REPLICATES // 2:
                raise IdentificationError(
                    f"the record does not determine the device: fitted again through the "
                    f"same {q.value * 1e6:.3g} um encoder, {REPLICATES - boot.shape[0]} of "
                    f"{REPLICATES} replicates of it fail (raise --force-limit or "
                    f"--duration)")

        def interval(pairs, unit, log=False):
            w = np.zeros(p_c.size)
            for j, c in pairs:
                w[j] = c
            v = float(w @ p_c)
            h = z * math.sqrt(max(float(w @ cov_c @ w), 0.0))
            lo, hi = v - h, v + h
            if boot is not None and boot.shape[0] >= 2:
                bb = boot @ w
                bias = float(np.mean(bb)) - v
                hb = t_q * float(np.std(bb, ddof=1)) * math.sqrt(1.0 + 1.0 / bb.size)
                lo, hi = min(lo, v - bias - hb), max(hi, v - bias + hb)
            if log:
                # an interval of ln m beyond the float range is a mass not determined
                # (refused below), not an OverflowError
                return Estimate(*(math.exp(t_) if t_ < 709.0 else math.inf
                                  for t_ in (v, lo, hi)), unit)
            return Estimate(v, lo, hi, unit)
        out = [interval([(0, 1.0)], "kg", log=True), interval([(1, 1.0)], "N s/m")]
        if mod_c.coulomb:
            out += [interval([(2, 1.0)], "N"), interval([(3, 1.0)], "N"),
                    interval([(2, 0.5), (3, 0.5)], "N"), interval([(2, 1.0), (3, -1.0)], "N")]
        else:
            out += [Estimate(0.0, 0.0, 0.0, "N")] * 4
        return out
    m = math.exp(p[0])
    mass, fric, cp, cn, cm, asym = intervals(mod, ym, p, J, n_nuis)
    # a hold the data cannot rule out: its own intervals (its model confounds the
    # frictions differently: the idealised image has no Coulomb term, which its b0
    # absorbs) join the best's
    rival = [c for c in cands if c["hold"] != best["hold"] and close(c)]
    if rival:
        c = min(rival, key=lambda c_: c_["cost"])
        if c.get("_ref") is not None:
            ym_r, p_r, J_r, nn_r, _ = c["_ref"]
        else:
            ym_r, p_r, J_r, nn_r = c["_mod"].full(c["_res"].x)
        if (np.all(np.isfinite(J_r)) and np.all(np.isfinite(ym_r))
                and np.all(np.isfinite(p_r))):
            try:
                o = intervals(c["_mod"], ym_r, p_r, J_r, nn_r)
            except IdentificationError:
                o = None
            if o is not None:
                mass = Estimate(mass.value, min(mass.lo, o[0].lo), max(mass.hi, o[0].hi),
                                "kg")
                fric = Estimate(fric.value, min(fric.lo, o[1].lo), max(fric.hi, o[1].hi),
                                "N s/m")
                if mod.coulomb:
                    cp, cn, cm, asym = (
                        Estimate(e.value, min(e.lo, f_.lo), max(e.hi, f_.hi), "N")
                        for e, f_ in zip((cp, cn, cm, asym), o[2:]))
    if not mass.hi < MASS_SPAN * mass.lo:
        # every prediction rests on the mass: one not known within a factor MASS_SPAN
        # (under the holds the data cannot tell apart) is not a device to write down
        raise IdentificationError(
            f"the record does not determine the mass: {mass.value:.3g} kg, interval "
            f"[{mass.lo:.3g}, {mass.hi:.3g}] kg at {LEVEL:.1%} (more than a factor "
            f"{MASS_SPAN:g}{f'; {counts} encoder steps of motion' if counts >= 0 else ''})"
            f" -- raise --force-limit or --duration")
    x0 = float(x[0])
    # a delay or a hold the data cannot rule out moves the estimates: the intervals cover
    # the estimates under every such candidate (each widened by the best fit's lower and
    # upper half-widths)
    def cover(e, v):
        return Estimate(e.value, min(e.lo, v - (e.value - e.lo)), max(e.hi, v + (e.hi - e.value)),
                        e.unit)
    coulomb_free = False
    for c in cands:
        if c is best or not close(c):
            continue
        pc = c["_ref"][1] if c.get("_ref") is not None else c["_mod"].full(c["_res"].x)[1]
        mc = math.exp(pc[0])
        mass = Estimate(m, min(mass.lo, mc * mass.lo / m), max(mass.hi, mc * mass.hi / m), "kg")
        fric = cover(fric, pc[1])
        if mod.coulomb and len(pc) >= 4:
            cp, cn = cover(cp, pc[2]), cover(cn, pc[3])
            cm, asym = cover(cm, 0.5 * (pc[2] + pc[3])), cover(asym, pc[2] - pc[3])
        elif not mod.coulomb and len(pc) >= 4:
            coulomb_free = True
    if coulomb_free:
        # the idealised image (no Coulomb term) fits best, but the zero-order hold with
        # Coulomb friction is not ruled out: the record does not determine the friction
        cp = cn = cm = Estimate(0.0, 0.0, math.inf, "N")
        asym = Estimate(0.0, -math.inf, math.inf, "N")
    if mod.coulomb:
        # a direction the device never clearly moved in says nothing of its Coulomb
        # friction: [0, inf) (its value: the other direction's), and the mean is as
        # unknown above
        seen = (bool(np.any(mod.dir_i > 0)), bool(np.any(mod.dir_i < 0)))
        if not all(seen):
            known_e = cp if seen[0] else cn
            free = Estimate(known_e.value, 0.0, math.inf, "N")
            cp, cn = (known_e, free) if seen[0] else (free, known_e)
            cm = Estimate(known_e.value, min(0.5 * known_e.lo, known_e.lo), math.inf, "N")
            asym = Estimate(0.0, -math.inf, math.inf, "N")
    xm = np.full(n, np.nan)
    xm[mod.idx] = ym
    resid = ym - xi
    explained, rms, floor = _explains(resid, q.value)
    spec = np.abs(np.fft.rfft(resid - resid.mean()))
    freqs = np.fft.rfftfreq(resid.size, T)
    peak = float(freqs[1 + int(np.argmax(spec[1:]))]) if spec.size > 1 else 0.0
    if explained:
        verdict = (f"the 2nd-order model explains the data: residual RMS {rms * 1e6:.3g} um "
                   f"against the sensor's {floor * 1e6:.3g} um (quantum and white noise)")
    else:
        verdict = (f"the 2nd-order model does NOT explain the data: residual RMS "
                   f"{rms * 1e6:.3g} um against the sensor's {floor * 1e6:.3g} um; the "
                   f"residual peaks near {peak:.3g} Hz (a resonance or a compliant "
                   f"transmission the mass-friction model cannot fit, or a nonlinearity)")
    if ambiguity is not None:
        verdict += (f"; {ambiguity}: d = {int(best['delay'])} is the better fit's, not "
                    f"determined")
    return DeviceFit(mass=mass, friction=fric, coulomb_pos=cp, coulomb_neg=cn, coulomb=cm,
                     asymmetry=asym, delay=int(best["delay"]),
                     delay_range=(min(same), max(same)), hold=best["hold"],
                     delay_estimate=delay_estimate,
                     hold_certain=not other_hold, position_resolution=q, noise=noise,
                     x0=float(x0), rms_residual=rms, explained=bool(explained),
                     verdict=verdict, residual_peak_hz=peak, period=T, n_samples=n,
                     motion_counts=counts, delay_certain=ambiguity is None,
                     candidates=[{"hold": c["hold"], "delay": c["delay"],
                                  "frac": c.get("frac", 0.0),
                                  "rms": math.sqrt(2 * c["cost"] / nu)} for c in cands],
                     model=xm)
