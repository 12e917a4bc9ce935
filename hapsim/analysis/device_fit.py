"""Identify a 1-DoF device from a recorded force / position stream (``hapsim identify``).

Model (docs/design.md, 'The THS'): ``m x'' + b0 x' = u(t) - fc sign(x')`` with the
commanded force ``u`` applied ``d`` whole samples after the position it answers and held
over the period (zero-order hold) -- or the paper's idealised sampled image (Florens, Voda &
Urma eq. (4));
the encoder rounds to a quantum ``q`` after Gaussian noise of standard deviation ``sigma``.

Method
------
*Output error on the moving stretches.* The velocity's sign is read from the positions
(:func:`moving_stretches`); inside a stretch where the device clearly moves one way the Coulomb
friction is a constant force and the exact ZOH discretisation is linear. For each hold and
each delay ``d = 0 .. max_delay`` the recorded forces, shifted by ``d`` (a tick the device
reported late holds the force before), drive the model restarted at every stretch from its
own initial state (multiple shooting); for given ``(m, b0)`` the stretch states and
``(fc+, fc-)`` follow by linear least squares, so only ``(ln m, b0)`` are searched
(variable projection: Golub & Pereyra 1973; ``scipy.optimize.least_squares``, started from
the correlation of force steps with acceleration). The two best candidates are then refined
with the nonlinear friction model (stick, reversal) over all parameters. Stretches the
model misses by far (an unseen reversal) are dropped, before and after the refinement; a
stretch is cut where the model's velocity comes within two periods of reversing (a stop
for an instant the centred difference does not see: :func:`split_at_stops`), up to three
times. The intervals are the wider of the Newey-West and the lag-0 ones (the stretch
states' fit leaves the residual negatively autocorrelated). Unlike the equation error, whose
regressors carry the sensor noise (errors in variables: biased), the output error is
consistent for white sensor noise, also in closed loop: the forces are known exactly, the
model output given them is the true position, the residual is the sensor error (L. Ljung,
*System Identification*, 2nd ed., 1999, Sec. 4.2, 7.3). The (hold, d) with the least
residual is chosen; every other whose likelihood ratio ``N ln(S_d / S_best)`` is below the
chi-square quantile stays in the delay's interval, and the intervals of m, b0 and fc then
also cover the estimates under those delays. When the delays are tried (no account of the
applied force), ``N`` is the residual's effective samples (:func:`effective_samples`: a
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
of the fitted model passed through the same encoder (:func:`grid_replicates`). A mass not
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

Modules
-------
This module is the fit's entry (:func:`fit_device`) and its public names; the parts live
beside it, one job each: :mod:`hapsim.analysis.device_fit_model` (what a fit returns, the
applied force, the record's pieces and quantum), :mod:`hapsim.analysis.device_fit_search`
(the stretches, the variable projection, the search over delays and holds, the nonlinear
refinement) and :mod:`hapsim.analysis.device_fit_intervals` (the delay's interval, the
Newey-West covariance, the noise, the quantised record's replicates, the verdict's test).
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.device_fit_intervals import (
    MASS_SPAN, REPLICATES, ambiguity_sentence, best_residual, chi2_ppf_1, delay_interval,
    effective_samples, explains, grid_replicates, hac_covariance, noise_estimate)
from hapsim.analysis.device_fit_model import (
    HOLDS, LEVEL, POSITION_FLOOR, DeviceFit, Estimate, input_known, encoder_quantum, tick_runs,
    true_runs, applied_force)
from hapsim.analysis.device_fit_search import (
    FRACTION_TOL, correlation_guess, fraction_candidate, refine, search_candidates,
    search_fraction)
from hapsim.analysis.device_fit_stretches import moving_stretches, split_at_stops
from hapsim.errors import ConfigError, IdentificationError

__all__ = ["Estimate", "DeviceFit", "fit_device", "applied_force", "POSITION_FLOOR",
           "LEVEL"]

#: Samples of clear motion (:func:`~hapsim.analysis.device_fit_stretches.moving_stretches`)
#: a record needs before it is fitted.
MIN_MOVING = 100


def _more_motion(moving: int, n: int, T: float) -> str:
    """What to change when a record of ``n`` samples of ``T`` [s] held ``moving`` samples
    of clear motion, fewer than :data:`MIN_MOVING`: the force, the envelope (the
    excitation reverses within it: a coarse encoder's counts over a narrow envelope, the
    Haply joint's 0.01 rad, are few), or the duration that the same pace of motion would
    fill (the record's own rate, 1.5 times over), as a
    coarse encoder at a low rate needs (the FireFader's 0.39 mm counts at 250 Hz: 4 s
    of its default excitation were too few, 8 s identified it)."""
    if moving <= 0:
        return ("no stretch of it moved one way by more than 1.5 sensor steps and the "
                "noise over 10 samples: raise --force-limit, --envelope (the reach it "
                "moves within) or --duration")
    need = math.ceil(1.5 * MIN_MOVING / moving * n * T)
    return (f"{moving} in {n} samples: raise --force-limit, --envelope (the reach it "
            f"moves within), or --duration to about {need} s at this pace")


def _stretches_fitted(r, offs, share=0.0):
    """Which stretches the model fits: ``None`` when every one (or too few would stay),
    else a mask, shape (s,), False for a stretch whose mean square residual exceeds 9
    times the stretches' median (plus :data:`POSITION_FLOOR` squared) -- a reversal or a
    stop the stretch hides. At least 3 stretches, and the ``share`` of the samples, must
    stay: a model that misses more than that is not rescued by dropping (its verdict
    says so)."""
    lens = np.diff(np.append(offs, r.size))
    ss = np.add.reduceat(r * r, offs) / lens
    keep = ss <= 9.0 * float(np.median(ss)) + POSITION_FLOOR ** 2
    if np.all(keep) or np.sum(keep) < 3 or np.sum(lens[keep]) < share * np.sum(lens):
        return None
    return keep


def _refit_on(st, cands, x, f, T, late, holds, max_delay, known, seq):
    """The candidates' search again on the stretches ``st``, started from the best of
    ``cands``: the new candidates (empty when none fits)."""
    b_ = min(cands, key=lambda c: c["cost"])
    return search_candidates(x, f, T, late, holds, max_delay, st, b_["delay"],
                             HOLDS[b_["hold"]], math.exp(b_["_res"].x[0]), known, seq)


def _fraction_and_refine(cands, x, T, late, st, known, seq, f, holds):
    """The sub-sample delays' candidates added (zero-order hold), then the nonlinear
    refinement (:func:`~hapsim.analysis.device_fit_search.refine`) of the two best and of
    the best whole delay's; a refinement is kept where it lowers the cost. Returns the
    candidates, sorted by cost before the refinement."""
    if "zoh" in holds:
        # sub-sample delays d + frac under the zero-order hold (the split hold)
        cands = cands + search_fraction(x, T, late, st, cands, known, seq, f)
    cands.sort(key=lambda c: c["cost"])
    # (and the best whole delay's: a sub-sample candidate the ratio cannot tell from it
    # gives way to it below, refined as it would have been without them)
    whole = [c for c in cands if c.get("frac", 0.0) == 0.0][:2]
    for c in cands[:2] + [c for c in whole if c not in cands[:2]]:
        if "_ref" in c:
            continue                       # refined already (the fraction's profile)
        c["_ref"] = refine(c["_mod"], c["_res"].x) if c["_mod"].coulomb else None
        if c["_ref"] is not None and c["_ref"][4] < c["cost"]:
            c["cost"] = c["_ref"][4]
        else:
            c["_ref"] = None
    return cands


def fit_device(position, force, period: float, *, late=None, max_delay: int = 5,
               holds=("zoh", "ideal"), lag: int = 50, applied=None, seq=None,
               ambiguous_delay: str = "range", length_unit: str = "m") -> DeviceFit:
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
    length_unit : str
        The positions' unit in the messages (``"m"``; ``"rad"`` on a rotary axis,
        :attr:`hapsim.drivers.base.Driver.rotary`): the figures are the same, only said
        in it (micro-units).

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
        if h not in HOLDS:
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
        usable &= input_known(seq, late, int(max_delay))
    ticks = np.arange(n) if seq is None else seq
    pieces = [(a + int(i0), a + int(i1)) for a, b in tick_runs(ticks)
              for i0, i1 in true_runs(usable[a:b])]
    if known is not None:
        # the correlation sees the applied force: its delay is 0 by construction
        _, h0, m0 = correlation_guess(x, u, T, 2, pieces)
        d0 = known[1]
    else:
        d0, h0, m0 = correlation_guess(x, f, T, max_delay, pieces)
    q = encoder_quantum(x)
    st = moving_stretches(x, q.value, pieces=pieces)
    moving = int(np.sum(st[1] - st[0])) if st[0].size else 0
    if moving < MIN_MOVING:
        raise IdentificationError(f"the device hardly moved: fewer than {MIN_MOVING} samples "
                                  f"of clear motion ({_more_motion(moving, n, T)})")
    cands = search_candidates(x, f, T, late, holds, max_delay, st, d0, h0, m0, known, seq)
    if cands:
        # a stretch the best model misses by far hides an unseen reversal of the velocity
        # (Coulomb friction flips there): drop such stretches and fit again
        best = min(cands, key=lambda c: c["cost"])
        keep = _stretches_fitted(best_residual(best), best["_mod"].offs)
        if keep is not None:
            st = tuple(a_[keep] for a_ in st)
            cands = _refit_on(st, cands, x, f, T, late, holds, max_delay, known, seq)
    for _ in range(3):
        # a stretch whose model nearly stops inside it: cut there and fit again (the
        # model after a cut is closer, and may show a stop the first one smoothed over)
        if not cands:
            break
        best = min(cands, key=lambda c: c["cost"])
        mod = best["_mod"]
        cut = split_at_stops(st, best_residual(best) + x[mod.idx])
        if cut is None or cut[0].size < 3:
            break
        again = _refit_on(cut, cands, x, f, T, late, holds, max_delay, known, seq)
        if not again:
            break
        st, cands = cut, again
    if not cands:
        raise IdentificationError("no model could be fitted to the record")
    cands = _fraction_and_refine(cands, x, T, late, st, known, seq, f, holds)
    # the refined model (sticking and reversals inside a stretch modelled) may still miss
    # a stretch by far: a handle that stopped and stuck at a stretch's edge, where the
    # centred difference still saw motion (a noise-free record shows it as exact zero
    # steps): those stretches are dropped and the record fitted again, once
    # (three quarters of the samples stay: a model missing more is not rescued)
    best = min(cands, key=lambda c: c["cost"])
    keep = _stretches_fitted(best_residual(best), best["_mod"].offs, share=0.75)
    if keep is not None:
        st_k = tuple(a_[keep] for a_ in st)
        again = _refit_on(st_k, cands, x, f, T, late, holds, max_delay, known, seq)
        if again:
            st, cands = st_k, _fraction_and_refine(again, x, T, late, st_k, known, seq, f,
                                                   holds)
    best = min(cands, key=lambda c: c["cost"])
    nu = best["_mod"].idx.size
    crit = chi2_ppf_1(LEVEL)
    s_best = max(best["cost"], 0.5 * nu * POSITION_FLOOR ** 2)
    mod = best["_mod"]
    # the likelihood ratio's samples: when the delays are searched, the residual's
    # effective ones (a quantiser's error is correlated: counted as nu independent
    # samples, the ratio told apart delays the record cannot, and the best was a wrong
    # delay); from an account of the applied force (one delay, the holds alone) all
    n_lr = float(nu) if known is not None else effective_samples(
        best_residual(best), mod.offs, lag)

    def close(c):
        return n_lr * math.log(max(c["cost"], 0.5 * nu * POSITION_FLOOR ** 2) / s_best) <= crit

    # the fraction's interval on the residual's effective samples (its error is
    # correlated: a model error, a quantiser; counted as nu independent samples, 2 of 30
    # random sub-sample delays fell outside intervals stated at 99.9 %)
    n_fr = n_lr if known is None else effective_samples(best_residual(best), mod.offs, lag)

    def close_fr(c):
        return n_fr * math.log(max(c["cost"], 0.5 * nu * POSITION_FLOOR ** 2) / s_best) <= crit

    delay_estimate = delay_interval(cands, best, close_fr, n_fr, s_best, crit, nu)
    fractional = any(c.get("frac", 0.0) > 0.0 for c in cands)
    if fractional:
        # the fraction's search resolves it to FRACTION_TOL: on a noise-free record the
        # likelihood's interval is far narrower, and 5 of 120 in-process devices with a
        # sub-sample delay missed their truths by less (tools/identify_blind.py --mode
        # inprocess --fractional, seeds 19, 43, 77)
        # (never below the least whole delay tried: a device's account fixes it)
        e_ = delay_estimate
        floor_d = float(min(c["delay"] for c in cands))
        delay_estimate = Estimate(e_.value, max(min(e_.lo, e_.value - FRACTION_TOL), floor_d),
                                  max(e_.hi, e_.value + FRACTION_TOL), e_.unit)
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
        ambiguity = ambiguity_sentence(best, rival, nu, n_lr, q.value, length_unit)
        if ambiguous_delay == "refuse" and explains(best_residual(best), q.value)[0]:
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
    noise = noise_estimate(xi, ym, q.value, delta, z, p.size + n_nuis, offs=mod.offs)
    n_hi = noise_estimate(xi, ym, q.value, 0.0, z, p.size + n_nuis, offs=mod.offs)
    n_lo = noise_estimate(xi, ym, q.value, 2.0 * delta, z, p.size + n_nuis, offs=mod.offs)
    noise = Estimate(noise.value, min(noise.lo, n_lo.lo), max(noise.hi, n_hi.hi), "m")
    # a quantised record: the quantiser's effect on the estimates, from replicates of the
    # record through the same encoder (grid_replicates, in intervals() below)
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
                f"({q.value * 1e6:.3g} u{length_unit}) on the {mod.starts.size} stretches of clear "
                f"motion, for {n_par} parameters (each stretch's position and velocity, "
                f"the mass and frictions); between steps the encoder only says the "
                f"handle is inside one cell (raise --force-limit, --envelope or "
                f"--duration)")
    t_q = float(stdtrit(max(REPLICATES - 1, 1), 0.5 + LEVEL / 2))   # scipy.stats.t.ppf's

    def intervals(mod_c, ym_c, p_c, J_c, nn_c):
        """(mass, fric, cp, cn, cm, asym) of one candidate: the union of the linearised
        interval and, on a quantised record, the replicates' bias-corrected prediction
        interval ``theta - bias +- t_(R-1) s sqrt(1 + 1/R)`` (the bias itself estimated
        from R replicates: Student's t, R - 1 degrees of freedom)."""
        # the Newey-West covariance, and the heteroskedasticity-robust one (lag 0) as its
        # floor, quantity by quantity: each stretch's fitted state leaves its residual
        # negatively autocorrelated over the stretch, which the Bartlett sum counts
        # against the variance -- on short stretches (a record cut by lost STATEs) the
        # lag-50 estimate fell below the white noise's own: 8 of 300 truths missed their
        # 99.9 % intervals, 1 with this floor (tools/identify_gap_coverage.py --n 100
        # --seed 7 --quantum 0; tests/test_identify_gaps.py holds the class)
        covs = (hac_covariance(J_c, ym_c - x[mod_c.idx], lag, nn_c),
                hac_covariance(J_c, ym_c - x[mod_c.idx], 0, nn_c))
        boot = None
        if q.value > 0:
            boot = grid_replicates(mod_c, ym_c, p_c, q.value, noise.value)
            if boot.shape[0] < REPLICATES // 2:
                raise IdentificationError(
                    f"the record does not determine the device: fitted again through the "
                    f"same {q.value * 1e6:.3g} u{length_unit} encoder, {REPLICATES - boot.shape[0]} of "
                    f"{REPLICATES} replicates of it fail (raise --force-limit or "
                    f"--duration)")

        def interval(pairs, unit, log=False):
            w = np.zeros(p_c.size)
            for j, c in pairs:
                w[j] = c
            v = float(w @ p_c)
            h = z * math.sqrt(max(max(float(w @ c_ @ w) for c_ in covs), 0.0))
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
    f_best = best.get("frac", 0.0)

    def resolved(c):
        # a fraction within the search's resolution of the best's: as good a model
        return (c["hold"] == best["hold"] and c["delay"] == best["delay"]
                and abs(c.get("frac", 0.0) - f_best) <= FRACTION_TOL)
    # the estimates at the delay interval's ends: the mass and frictions move with the
    # fraction, and an interval at the best's fraction alone missed the friction at the
    # true one (1.1645 N s/m against [1.1587, 1.1641], the delay 1.3575 inside [1.331,
    # 1.364]: 8 of 240 devices of tools/identify_subsample.py, seeds 2911, 5, 77, 11-15)
    ends = []
    if best["hold"] == "zoh" and fractional:
        for e_ in (delay_estimate.lo, delay_estimate.hi):
            d_e = int(math.floor(e_))
            fr_e = e_ - d_e
            if not FRACTION_TOL < fr_e < 1.0 - FRACTION_TOL or (
                    known is not None and d_e != known[1]):
                continue
            u_e = known[0] if known is not None else applied_force(f, d_e, late, seq)
            c_e = fraction_candidate(x, u_e, T, st, [best["_res"].x], d_e, fr_e)
            if c_e is not None:
                ends.append(c_e)
    covered = [c for c in cands if c is not best and (close(c) or resolved(c))] + ends
    for c in covered:
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
    explained, rms, floor = explains(resid, q.value)
    spec = np.abs(np.fft.rfft(resid - resid.mean()))
    freqs = np.fft.rfftfreq(resid.size, T)
    peak = float(freqs[1 + int(np.argmax(spec[1:]))]) if spec.size > 1 else 0.0
    if explained:
        verdict = (f"the 2nd-order model explains the data: residual RMS {rms * 1e6:.3g} "
                   f"u{length_unit} against the sensor's {floor * 1e6:.3g} u{length_unit} (quantum and white noise)")
    else:
        verdict = (f"the 2nd-order model does NOT explain the data: residual RMS "
                   f"{rms * 1e6:.3g} u{length_unit} against the sensor's {floor * 1e6:.3g} "
                   f"u{length_unit}; the "
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
