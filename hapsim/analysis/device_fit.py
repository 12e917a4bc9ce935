"""Identify a 1-DoF device from a recorded force / position stream (``hapsim identify``).

Model (DESIGN.md Sec. 4-5): ``m x'' + b0 x' = u(t) - fc sign(x')`` with the commanded force
``u`` applied ``d`` whole samples after the position it answers and held over the period
(zero-order hold) -- or the paper's idealised sampled image (Florens, Voda & Urma eq. (4));
the encoder rounds to a quantum ``q`` after Gaussian noise of standard deviation ``sigma``.

Method
------
*Output error*: for each hold and each delay ``d = 0 .. max_delay`` the recorded forces,
shifted by ``d`` (a tick the device reported late holds the force before), drive the exact
discretisation (:func:`hapsim.kernels.device_sim.simulate_device`) from rest, and
``theta = (ln m, b0, fc+, fc-, x0)`` minimises ``sum (x_model[n] - x_meas[n])^2``
(``scipy.optimize.least_squares``, started from the equation-error least squares of the
exact ZOH recurrence ``dx[n+1] = a dx[n] + beta1 F[n+1] + beta0 F[n]``). Unlike the equation
error, whose regressor ``dx[n]`` carries the sensor noise (errors in variables: biased), the
output error is consistent for white sensor noise, also in closed loop: the forces are
known exactly (they are what was sent), the model output given them is the true position,
and the residual is the sensor error alone (L. Ljung, *System Identification*, 2nd ed.,
1999, Sec. 4.2, 7.3). The (hold, d) with the least residual is chosen; every other whose
likelihood ratio ``N ln(S_d / S_best)`` is below the chi-square quantile stays in the
delay's interval.

Intervals
---------
``cov = (J'J)^-1 S (J'J)^-1`` with ``S`` the Newey-West (Bartlett-weighted, lag ``L``)
estimate of the covariance of the score ``J' r`` (W. K. Newey & K. D. West, Econometrica
55(3), 1987): quantisation of a slowly moving position is not white, and this keeps the
intervals honest for it. Positions are taken as known to no better than
:data:`POSITION_FLOOR` (a numerical floor: on exact data the intervals do not shrink below
the optimiser's resolution). The interval of ``m`` is ``m exp(+-z s_ln m)``.
The quantum is read from the positions (the smallest step between distinct values, when
every value is a whole multiple of it). The noise is the maximum-likelihood ``sigma`` of the
rounded Gaussian ``P(y | x) = Phi((y - x + q/2)/s) - Phi((y - x - q/2)/s)``,
``s^2 = sigma^2 + delta^2`` (``delta``: the model output's own uncertainty), with its
profile-likelihood interval.

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

from hapsim.errors import ConfigError

__all__ = ["Estimate", "DeviceFit", "fit_device", "applied_force", "POSITION_FLOOR",
           "LEVEL"]

#: Positions are never taken as known better than this [m] (intervals' numerical floor).
POSITION_FLOOR = 1e-10
#: Confidence level of every interval.
LEVEL = 0.99
_HOLDS = {"zoh": 0, "ideal": 1}


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
        Every delay the data cannot tell from ``delay`` (its interval).
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
                      delay=int(self.delay), hold=self.hold, force_limit=force_limit,
                      position_resolution=self.position_resolution.value,
                      coulomb=max(self.coulomb.value, 0.0), noise=self.noise.value)

    def to_dict(self) -> dict:
        """Plain data (``--json``): every estimate as ``{value, lo, hi, unit}``."""
        d = {k: v for k, v in asdict(self).items() if k != "model"}
        d["delay_range"] = list(self.delay_range)
        return d


def applied_force(force, delay: int, late=None) -> np.ndarray:
    """The force the device held over each period, from the forces the host sent.

    Parameters
    ----------
    force : array_like, shape (n,)
        Force sent answering the position of sample ``k`` [N].
    delay : int >= 0
        d: that force acts over ``[(k+d)T, (k+d+1)T)``.
    late : array_like of bool, shape (n,), optional
        Ticks the device reported holding an older force: the force before is held.

    Returns
    -------
    ndarray, shape (n,)
        ``u[k] = force[k - d]`` (0 for ``k < d``), the previous ``u`` where late.
    """
    f = np.asarray(force, float)
    u = np.zeros_like(f)
    if delay < f.size:
        u[delay:] = f[:f.size - delay]
    if late is not None:
        lt = np.asarray(late, bool)
        for k in np.flatnonzero(lt):
            if k > 0:
                u[k] = u[k - 1]
    return u


def _quantum(y: np.ndarray) -> Estimate:
    """Encoder quantum: the smallest step between distinct positions, if they lie on it."""
    vals = np.unique(y)
    steps = np.diff(vals)
    steps = steps[steps > 0]
    if steps.size == 0:
        return Estimate(0.0, 0.0, math.inf, "m")
    q = float(steps.min())
    if q > 1e-9:
        k = y / q
        if np.max(np.abs(k - np.round(k))) < 1e-3:
            # all on the grid; the grid step is q to the values' float resolution
            tol = 1e-6 * q
            return Estimate(q, q - tol, q + tol, "m")
    return Estimate(0.0, 0.0, q, "m")


def _correlation(x, f, T, max_delay):
    """Delay, hold and mass from the correlation of force steps with acceleration.

    The PRBS makes the force increments ``df[n]`` nearly white and much larger than the
    smooth centring part, so ``c_j = sum d2x[n+j] df[n] / sum df^2`` (``d2x[n] =
    x[n+1] - 2 x[n] + x[n-1]``) is the impulse response of ``df -> d2x``: for the exact ZOH
    with delay d, ``c_{d+1} ~ c_{d+2} ~ T^2/(2m)``; for the idealised image ``c_{d+1} ~
    T^2/m`` alone (correlation analysis, Ljung 1999 Sec. 6.1). Sensor noise is uncorrelated
    with past force steps. Returns ``(d, hold, m)``.
    """
    d2 = np.zeros_like(x)
    d2[1:-1] = x[2:] - 2 * x[1:-1] + x[:-2]
    df = np.zeros_like(f)
    df[1:] = np.diff(f)
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


class _Model:
    """Residual function of one (hold, delay) candidate, by multiple shooting."""

    def __init__(self, x, u, T, hold, seg):
        from hapsim.kernels.device_sim import simulate_device
        self.x, self.u, self.T, self.hold, self.seg = x, u, T, hold, int(seg)
        self._sim = simulate_device
        self._out = np.empty_like(x)
        self.coulomb = hold == 0
        self.k = 5 if self.coulomb else 3     # ln m, b0, (fc+, fc-), then segment states
        self.nseg = -(-x.size // self.seg)

    def unpack(self, p):
        k, ns = self.k, self.nseg
        xs = np.ascontiguousarray(p[k - 1:k - 1 + ns])
        vs = np.ascontiguousarray(p[k - 1 + ns:k - 1 + 2 * ns])
        if self.coulomb:
            return math.exp(p[0]), p[1], p[2], p[3], xs, vs
        return math.exp(p[0]), p[1], 0.0, 0.0, xs, vs

    def output(self, p):
        m, b, fp_, fn, xs, vs = self.unpack(p)
        out = np.empty_like(self.x)
        self._sim(self.u, m, b, fp_, fn, self.seg, xs, vs, self.T, self.hold, out)
        return out

    def residual(self, p):
        m, b, fp_, fn, xs, vs = self.unpack(p)
        self._sim(self.u, m, b, fp_, fn, self.seg, xs, vs, self.T, self.hold, self._out)
        return self._out - self.x

    def start_states(self):
        """Segment states from the positions: x at the start, velocity over 5 samples."""
        x, T, seg = self.x, self.T, self.seg
        i = np.arange(self.nseg) * seg
        j = np.minimum(i + 5, x.size - 1)
        return x[i].astype(float), (x[j] - x[i]) / ((j - i) * T)

    def sparsity(self):
        from scipy.sparse import lil_matrix
        n, k, ns = self.x.size, self.k, self.nseg
        S = lil_matrix((n, k - 1 + 2 * ns), dtype=int)
        S[:, :k - 1] = 1
        rows = np.arange(n)
        S[rows, k - 1 + rows // self.seg] = 1
        S[rows, k - 1 + ns + rows // self.seg] = 1
        return S


def _fit_candidate(x, u, T, hold, start, seg, nfev=200, start_p=None):
    from scipy.optimize import least_squares
    mod = _Model(x, u, T, hold, seg)
    m0, b0, fcp, fcn = start
    xs, vs = mod.start_states()
    p0 = np.concatenate([[math.log(m0), b0] + ([fcp, fcn] if mod.coulomb else []), xs, vs])
    if start_p is not None:
        p0 = np.asarray(start_p, float)
    try:
        r = least_squares(mod.residual, p0, method="trf", x_scale="jac",
                          jac_sparsity=mod.sparsity(), xtol=1e-12, ftol=1e-12, gtol=1e-12,
                          max_nfev=nfev)
    except (ValueError, FloatingPointError):
        return mod, None
    if not np.all(np.isfinite(r.fun)):
        return mod, None
    return mod, r


def _hac(J, r, lag):
    """Newey-West covariance of the least-squares parameters."""
    n, p = J.shape
    JtJ = J.T @ J
    bread = np.linalg.pinv(JtJ)
    g = J * r[:, None]
    S = g.T @ g
    for lg in range(1, min(lag, n - 1) + 1):
        w = 1.0 - lg / (lag + 1.0)
        G = g[lg:].T @ g[:-lg]
        S += w * (G + G.T)
    cov = bread @ S @ bread * n / max(n - p, 1)
    cov += POSITION_FLOOR ** 2 * bread
    return cov


def _noise(y, xm, q, delta, z, dof):
    """ML estimate and profile interval of the sensor noise (module notes)."""
    from scipy.special import log_ndtr
    from scipy.stats import chi2
    r = y - xm
    crit = 0.5 * chi2.ppf(LEVEL, 1)
    floor2 = delta ** 2 + POSITION_FLOOR ** 2
    grid = np.concatenate([[0.0], np.geomspace(1e-10, max(1e-6, 50 * float(np.std(r)) + 1e-9), 400)])
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
    ll = np.array([loglik(s) for s in grid])
    i = int(np.nanargmax(ll))
    ok = grid[ll >= ll[i] - crit]
    return Estimate(float(grid[i]), float(ok.min()), float(ok.max()), "m")


def _estimate(value, sd, z, unit, floor=0.0):
    h = z * sd + floor
    return Estimate(float(value), float(value - h), float(value + h), unit)


def fit_device(position, force, period: float, *, late=None, max_delay: int = 5,
               holds=("zoh", "ideal"), lag: int = 50, seg: int = 100) -> DeviceFit:
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
    seg : int >= 10
        Multiple-shooting segment length [samples] (module notes).

    Returns
    -------
    DeviceFit

    Raises
    ------
    ConfigError
        Arrays of different lengths, fewer than 200 samples, non-finite values, a force
        that never acts (all zero), an invalid period, delay or hold.
    """
    from scipy.stats import chi2, norm
    x = np.asarray(position, float)
    f = np.asarray(force, float)
    if x.ndim != 1 or x.shape != f.shape:
        raise ConfigError(f"position and force must be 1-D of one length, got {x.shape} "
                          f"and {f.shape}", key="position")
    if x.size < 200:
        raise ConfigError(f"too short a record: {x.size} samples, at least 200 are needed",
                          key="position")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(f))):
        raise ConfigError("the record holds non-finite samples", key="position")
    if not np.any(f):
        raise ConfigError("the force is zero throughout: nothing excites the device",
                          key="force")
    if not (math.isfinite(period) and period > 0):
        raise ConfigError(f"must be a positive number [s], got {period!r}", key="period")
    if isinstance(max_delay, bool) or int(max_delay) != max_delay or max_delay < 0:
        raise ConfigError(f"must be a whole number >= 0, got {max_delay!r}", key="max_delay")
    for h in holds:
        if h not in _HOLDS:
            raise ConfigError(f"unknown hold {h!r}; valid: zoh, ideal", key="hold")
    T = float(period)
    n = x.size
    z = float(norm.ppf(0.5 + LEVEL / 2))
    cands = []
    d0, h0, m0 = _correlation(x, f, T, max_delay)
    inv = {v: k for k, v in _HOLDS.items()}
    # every delay and hold briefly, then the two best to convergence
    quick = []
    for hname in holds:
        for d in range(int(max_delay) + 1):
            u = applied_force(f, d, late)
            mod, res = _fit_candidate(x, u, T, _HOLDS[hname], (m0, 1.0, 0.05, 0.05), seg, 12)
            if res is not None:
                quick.append((float(res.cost), hname, d, res))
    quick.sort(key=lambda c: c[0])
    for _, hname, d, r0 in quick[:2]:
        u = applied_force(f, d, late)
        mod, res = _fit_candidate(x, u, T, _HOLDS[hname], (m0, 1.0, 0.05, 0.05), seg,
                                  start_p=r0.x)
        if res is not None:
            cands.append({"hold": hname, "delay": d, "cost": float(res.cost),
                          "_mod": mod, "_res": res})
    for c, hname, d, r0 in quick[2:]:
        cands.append({"hold": hname, "delay": d, "cost": c, "_mod": None, "_res": r0})
    if not cands:
        raise ConfigError("no model could be fitted to the record", key="position")
    best = min((c for c in cands if c["_mod"] is not None), key=lambda c: c["cost"])
    crit = chi2.ppf(LEVEL, 1)
    s_best = max(best["cost"], 0.5 * n * POSITION_FLOOR ** 2)

    def close(c):
        return n * math.log(max(c["cost"], 0.5 * n * POSITION_FLOOR ** 2) / s_best) <= crit

    same = [c["delay"] for c in cands if c["hold"] == best["hold"] and close(c)]
    other_hold = any(c["hold"] != best["hold"] and close(c) for c in cands)
    mod, res = best["_mod"], best["_res"]
    p = res.x
    r = res.fun
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    cov = _hac(J, r, lag)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    m = math.exp(p[0])
    mass = Estimate(m, m * math.exp(-z * sd[0]), m * math.exp(z * sd[0]), "kg")
    fric = _estimate(p[1], sd[1], z, "N s/m")
    if mod.coulomb:
        cp = _estimate(p[2], sd[2], z, "N")
        cn = _estimate(p[3], sd[3], z, "N")
        v = np.zeros(p.size)
        v[2:4] = 0.5
        w = np.zeros(p.size)
        w[2], w[3] = 1.0, -1.0
        cm = _estimate(0.5 * (p[2] + p[3]), math.sqrt(max(v @ cov @ v, 0)), z, "N")
        asym = _estimate(p[2] - p[3], math.sqrt(max(w @ cov @ w, 0)), z, "N")
        x0 = p[4]
    else:
        cp = cn = cm = asym = Estimate(0.0, 0.0, 0.0, "N")
        x0 = p[2]
    xm = mod.output(p)
    # the model output's own uncertainty per sample: RMS of diag(J cov J')
    delta = float(math.sqrt(max(np.mean(np.einsum("ij,jk,ik->i", J, cov, J)), 0.0)))
    q = _quantum(x)
    noise = _noise(x, xm, q.value, delta, z, p.size)
    resid = xm - x
    rms = float(math.sqrt(np.mean(resid ** 2)))
    d2 = np.diff(resid, 2)
    sig_w = float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))
    floor = math.sqrt(q.value ** 2 / 12.0 + sig_w ** 2)
    explained = rms <= 2.0 * floor + 3 * POSITION_FLOOR
    spec = np.abs(np.fft.rfft(resid - resid.mean()))
    freqs = np.fft.rfftfreq(n, T)
    peak = float(freqs[1 + int(np.argmax(spec[1:]))]) if spec.size > 1 else 0.0
    if explained:
        verdict = (f"the 2nd-order model explains the data: residual RMS {rms * 1e6:.3g} um "
                   f"against the sensor's {floor * 1e6:.3g} um (quantum and white noise)")
    else:
        verdict = (f"the 2nd-order model does NOT explain the data: residual RMS "
                   f"{rms * 1e6:.3g} um against the sensor's {floor * 1e6:.3g} um; the "
                   f"residual peaks near {peak:.3g} Hz (a resonance or a compliant "
                   f"transmission the mass-friction model cannot fit, or a nonlinearity)")
    return DeviceFit(mass=mass, friction=fric, coulomb_pos=cp, coulomb_neg=cn, coulomb=cm,
                     asymmetry=asym, delay=int(best["delay"]),
                     delay_range=(min(same), max(same)), hold=best["hold"],
                     hold_certain=not other_hold, position_resolution=q, noise=noise,
                     x0=float(x0), rms_residual=rms, explained=bool(explained),
                     verdict=verdict, residual_peak_hz=peak, period=T, n_samples=n,
                     candidates=[{"hold": c["hold"], "delay": c["delay"],
                                  "rms": math.sqrt(2 * c["cost"] / n)} for c in cands],
                     model=xm)
