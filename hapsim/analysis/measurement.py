"""The felt pair measured from a run's logged positions, and its verdict against the
prediction.

:func:`identify` cuts the record at gaps, open contacts and (unless the late ticks were
accounted for, :func:`late_accounted`) late ticks, and fits the longest clean stretch of
free response (:func:`hapsim.analysis.identify.measure_felt`, or the full order matrix
pencil); :func:`verdict` states the interval and whether it holds the
prediction (:mod:`hapsim.analysis.prediction`); :func:`contact_verdict` says why a run with
contacts is not comparable. :func:`late_accounted` takes the response to the late ticks'
known disturbance out of the record (the device names the force it applied), and
:func:`wire_errors` gives the wire's number-format errors the stated uncertainty covers.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["identify", "verdict", "contact_verdict", "relative_error", "late_accounted",
           "aperture_noise",
           "late_force_bound",
           "estimated_bounds",
           "wire_errors"]


#: The stated interval's floor on an exact record, relative to the felt pole [-]: the
#: worst error of a lockstep record's dominant felt pair over 150 random 1-D loops was
#: 4.4e-12 relative on k, 2e4 eps (masses 0.02-2 kg, frictions 0-3 N s/m, rates 250-5000
#: Hz, delays 1-3 and fractional, K 0.05-0.9 of its limit, B 0-5 N s/m: the draws of
#: tests/test_weak_felt_pair.py); margin 227.
ROUNDOFF_FLOOR = 1e-9
#: Up to this ratio of the record's amplitude to the felt pair's, the floor stands as it
#: is; beyond, it grows with the ratio [-]. A record's round-off is absolute, eps times
#: its largest amplitude, so a pair ``ratio`` times weaker carries it ``ratio`` times
#: larger relative: the worst error above at ratio 100 is 4.4e-10, under the floor with a
#: margin of 2.27. (An over-damped wall whose only complex pair is a delay mode 1.5e5
#: times weaker than the record: k 9.5e-10 and b 1.1e-9 relative off, "differs" against
#: the plain floor; tests/test_weak_felt_pair.py.)
ROUNDOFF_FREE_RATIO = 100.0


def identify(position: np.ndarray, seq: np.ndarray, period: float, order: int, mass: float,
             start: int, *, offset: bool = False, late: np.ndarray | None = None,
             skip: int = 3, predicted=None, felt: complex | None = None,
             quantum: float = 0.0, noise: float = 0.0, sensor_response=None,
             closed: np.ndarray | None = None, wire=None, bounds=None,
             exclude: np.ndarray | None = None, late_bounds=None, fit=None) -> dict:
    """Measure the rendered oscillator from logged positions.

    Parameters
    ----------
    position : ndarray, shape (n,)
        Logged device positions [m].
    seq : ndarray of int, shape (n,)
        Their STATE sequence numbers.
    period : float
        Sample period T [s].
    order : int
        Identification order (number of non-zero closed-loop poles).
    mass : float
        Device mass m [kg] (k = m |s|^2, b = -2 m Re s).
    start : int
        First sequence number of the free response (after the excitation and the
        dead-beat transient).
    offset : bool
        Difference the signal first (constant equilibrium offset).
    late : ndarray of int, shape (n,), optional
        1 where the device held an older force (a late FORCE). Such a tick is a disturbance,
        not part of the linear THS: the record is cut there as at a gap of seq; the
        response after a disturbance is again a free response, minus ``skip`` samples of
        dead-beat transient. Without a clean segment of at least ``max(4 order + 10,
        100)`` samples the runs of consecutive seq are used as they are
        (``late_in_segment`` says how many disturbances they hold).

        With ``predicted`` and without ``closed``, every stretch is measured: the longest
        and each other of at least ``2 (order + 1) + 10`` samples, each a free response
        of the same loop from its own initial state (:func:`hapsim.analysis.identify.
        measure_felt` with ``lens``), so a run with gaps, late ticks cut out or a
        recovery uses all its data. With ``closed`` (contacts) or without a prediction
        (the pencil alone), the longest stretch only.
    skip : int
        Samples dropped at the start of a segment that follows a disturbance or a gap
        (``d + 2`` is enough: the dead-beat states of the delay line).
    predicted : array_like of complex, optional
        Predicted non-zero closed-loop poles seen at the port; with ``felt`` (the predicted
        felt pole) the measurement is :func:`hapsim.analysis.identify.measure_felt`
        (robust to a quantised or noisy sensor, with standard errors); without, the full
        order matrix pencil alone.
    quantum, noise : float
        Position sensor step [m] and noise standard deviation [m] (0: none).
    sensor_response : ndarray, optional
        Impulse response of the sensor error to the logged position
        (:func:`hapsim.analysis.error_response.sensor_error_response`); default: observed only.
    closed : ndarray of bool, shape (n,), optional
        Per row: every contact engaged (the state the prediction assumes;
        :func:`hapsim.pipeline.contact_replay.replay_contacts`). Rows that are not are cut out
        as late ticks are, and only a stretch of closed rows is identified: when the
        longest is shorter than the fit needs, the result has ``comparable`` False,
        ``closed_samples`` (the longest stretch) and ``needed`` and no measurement.
    exclude : ndarray of bool, shape (n,), optional
        Rows where the loop is not the linear THS for a reason the record does not
        carry as a known input (the force ramp after a recovery: the logged force is the
        loop law's scaled down, the law's own value is not logged): left out, the record
        cut there (a stretch after them is a free response from its own initial state).
    wire : sequence of (float, ndarray), optional
        The wire's number-format errors (:func:`hapsim.analysis.identify.measure_felt`).
    bounds : sequence of (ndarray, ndarray), optional
        Errors bounded at given rows, each ``(e, response)``: ``e`` shape (n,), aligned
        with ``position``, the largest error of each row (0 elsewhere; a position that is
        no reading [m], :func:`estimated_bounds`, through the sensor's response; a force
        the account cannot name [N], through the force response); their worst case is
        added to the stated uncertainty (``measure_felt``'s ``bounded``).
    late_bounds : sequence of (ndarray, ndarray), optional
        As ``bounds``, for the late ticks' accounted forces (:func:`late_accounted`'s
        bound [N], through the force response): their worst case is returned apart
        (``k_bound_late``, ``b_bound_late``; ``measure_felt``'s ``late_bounded``).
    fit : dict, optional
        Filled, when the fit is variable projection, with its modes (``spec``, as
        :func:`~hapsim.analysis.identify.measure_felt`'s ``fit``), ``offset`` and ``rows``:
        one int array per stretch fitted, the indices into ``position`` of its samples
        (what :func:`hapsim.analysis.unseen_holds.fit_residual` needs).

    Returns
    -------
    dict
        ``k``, ``b``, ``f0_hz``, ``damping_ratio``, ``samples_used``, ``first_seq``
        (of the first stretch used), ``order``, ``pencil``, ``late_in_segment``,
        ``stretches`` (of the free response) and ``stretches_used``; with ``predicted`` also ``k_sd``,
        ``b_sd``, ``k_unc``, ``b_unc``, ``method``, ``cycles``... of
        :func:`~hapsim.analysis.identify.measure_felt`; or ``error`` (str) when nothing can
        be identified or the record cannot support a measurement.
    """
    from hapsim.analysis.pencil import fit_rendered

    seq = np.asarray(seq, dtype=np.int64)
    pos = np.asarray(position, dtype=float)
    lt = np.zeros(seq.size, dtype=bool) if late is None else np.asarray(late).astype(bool)
    sel = seq >= start
    y, s, lt = pos[sel], seq[sel], lt[sel]
    eb = [(np.asarray(e, float)[sel], r) for e, r in (bounds or ())]
    elb = [(np.asarray(e, float)[sel], r) for e, r in (late_bounds or ())]
    cl = None if closed is None else np.asarray(closed, dtype=bool)[sel]
    ex = None if exclude is None else np.asarray(exclude, dtype=bool)[sel]

    def segments(cut_late: bool):
        """(begin, end) index ranges of the runs of consecutive seq, cut at late ticks and
        at rows with a contact open or excluded (those rows left out)."""
        cut = np.diff(s) != 1
        if cut_late:
            cut = cut | lt[1:]
        if cl is not None:
            cut = cut | (cl[1:] != cl[:-1])
        if ex is not None:
            cut = cut | (ex[1:] != ex[:-1])
        edges = np.concatenate([[0], np.flatnonzero(cut) + 1, [y.size]])
        out = []
        for a, b in zip(edges[:-1], edges[1:]):
            if cl is not None and not cl[a]:
                continue
            if ex is not None and ex[a]:
                continue
            a2 = a if a == 0 else min(a + skip, b)
            out.append((a2, b))
        return out or [(0, 0)]

    need = max(4 * int(order) + 10, 100)
    # a further stretch is fitted with the longest when it holds more samples than its
    # own initial condition's coefficients (order + offset) by a margin
    extra = 2 * (int(order) + 1) + 10
    a = b = 0
    segs = [(0, 0)]
    if y.size:
        segs = segments(True)
        a, b = max(segs, key=lambda ab: ab[1] - ab[0])
        if b - a < need:
            segs = segments(False)
            a, b = max(segs, key=lambda ab: ab[1] - ab[0])
    late_in = int(np.count_nonzero(lt[a + 1:b])) if b > a else 0
    if cl is None and predicted is not None and felt is not None:
        # every stretch (each from its own initial state, the loop's poles shared): a run
        # with gaps or a recovery is measured on all its data, not its longest stretch
        use = [(a, b)] + [(p, q) for p, q in segs if (p, q) != (a, b) and q - p >= extra]
        use.sort()
    else:
        use = [(a, b)]
    late_in = sum(int(np.count_nonzero(lt[p + 1:q])) for p, q in use if q > p)
    y = np.concatenate([y[p:q] for p, q in use])
    first = s[use[0][0]:use[0][1]]
    lens = [q - p for p, q in use]
    out = {"samples_used": int(y.size), "first_seq": int(first[0]) if first.size else None,
           "order": int(order), "late_in_segment": late_in, "stretches_used": len(use),
           "stretches": len([1 for p, q in segs if q > p])}
    if cl is not None:
        out["comparable"] = bool(b - a >= need)
        if not out["comparable"]:
            out.update(closed_samples=int(b - a), needed=int(need),
                       error=f"the longest stretch with every contact closed is {b - a} "
                             f"samples, fewer than the {need} the fit needs")
            return out
    from hapsim.analysis.pencil import thin_pencil
    pencil = thin_pencil(order, int(b - a) - (1 if offset else 0))
    out["pencil"] = pencil
    if predicted is not None and felt is not None and y.size:
        from hapsim.analysis.identify import measure_felt
        try:
            be = [(np.concatenate([e[p:q] for p, q in use]), r) for e, r in eb]
            bounded = [(e, r) for e, r in be if np.any(e > 0)] or None
            lb = [(np.concatenate([np.asarray(e, float)[p:q] for p, q in use]), r)
                  for e, r in elb]
            lb = [(e, r) for e, r in lb if np.any(e > 0)] or None
            got = {} if fit is not None else None
            res = measure_felt(y, period, mass, predicted, felt, offset=offset,
                               quantum=quantum, noise=noise, order=int(order), pencil=pencil,
                               sensor_response=sensor_response, wire=wire, lens=lens,
                               bounded=bounded, late_bounded=lb, fit=got)
            if got:
                idx = np.flatnonzero(sel)[np.concatenate(
                    [np.arange(p, q) for p, q in use])]
                fit.update(spec=got["spec"], offset=bool(offset),
                           rows=[idx[p:q] for p, q in got["kept"]])
            if late_bounds is not None and "b" in res and lb is None:
                res["k_bound_late"] = res["b_bound_late"] = 0.0
        except (ConfigError, np.linalg.LinAlgError) as exc:
            # (a fit's linear algebra that fails on a record is the record's "not
            # measurable", never a traceback out of the run)
            out["error"] = exc.reason if hasattr(exc, "reason") else f"the fit failed: {exc}"
            return out
        out.update(res)
        if "error" in res:
            for q in ("k", "b", "f0_hz", "damping_ratio"):
                out.pop(q, None)
        return out
    try:
        md = fit_rendered(y, period, int(order), mass, offset=offset, pencil=pencil)
    except (ConfigError, np.linalg.LinAlgError) as exc:
        out["error"] = exc.reason if hasattr(exc, "reason") else f"the fit failed: {exc}"
        if "identically zero" in out["error"]:
            out["error"] += ("; the loop never moved: give the scene an excitation "
                             "(x0, v0, impulse or profile)")
        return out
    out.update(k=float(md.k), b=float(md.b), f0_hz=float(md.f0_hz),
               damping_ratio=float(md.damping_ratio))
    return out



def relative_error(a, b):
    """``(a - b) / |b|``, or None when either is None or not finite, or ``b`` is 0.

    Parameters
    ----------
    a, b : float or None
        Measured and reference value (same unit).

    Returns
    -------
    float or None
    """
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b == 0:
        return None
    return (a - b) / abs(b)



def verdict(pred: dict, measured: dict) -> None:
    """Add ``k_interval``, ``b_interval`` (the stated half-widths), ``within`` and
    ``verdict`` to an identification result (in place).

    The interval is the fit's: :data:`hapsim.analysis.identify.COVERAGE` standard errors,
    the residual's or the sensor's (its error fed back through the loop), the larger; never
    below the round-off of an exact record: 1e-9 relative on k, and on b the same error of
    the felt pole, ``1e-9 k / (2 pi f0)`` (= ``1e-9 sqrt(k m)``), or 1e-9 relative if larger;
    for a felt pair far weaker than the record (:data:`ROUNDOFF_FREE_RATIO`), that floor
    times the ratio of their amplitudes. Where the sensor or the actuator rounds (a
    driver's counts and force steps), the rounding in the loop, its loop gain included,
    is stated by draws of its phase (``k_rounding``, ``b_rounding``:
    :mod:`hapsim.analysis.pair_rounding`), and the interval is the larger of the two. (The
    quantiser's describing-function gain bounded by its worst amplitude,
    :func:`hapsim.analysis.quantisation.quantiser_gain_bound`, widened the interval 2 to 70
    times beyond the errors observed over random loops: tests/test_identify_quantised.py.)

    Parameters
    ----------
    pred : dict
        The prediction (:func:`hapsim.analysis.prediction.predict`): ``k`` [N/m], ``b``
        [N s/m].
    measured : dict
        :func:`identify`'s result, completed in place.
    """
    if "k" not in measured or "k_unc" not in measured or pred.get("k") is None:
        return
    dk, db = measured["k_unc"], measured["b_unc"]
    rel = ROUNDOFF_FLOOR * max(1.0, float(measured.get("record_amplitude") or 0.0)
                               / max(float(measured.get("amplitude") or 0.0), 1e-300)
                               / ROUNDOFF_FREE_RATIO)
    dk = max(dk, rel * abs(pred["k"]))
    # the round-off of an exact record is in the felt pole s, not in b alone: k = m |s|^2
    # and b = -2 m Re(s), so the error that moves k by 1e-9 k moves |s| by 5e-10 |s| and,
    # in Re(s), b by up to m |s| 1e-9 = 1e-9 k / |s| (|s| = 2 pi f0). Relative to a lightly
    # damped pair's b that is 1 / (2 zeta) times more: configs/string.yaml (zeta 1.3e-4)
    # measured b 2e-9 to 4e-9 relative off (5.7e-12 N s/m, k 4e-13) on stretches of
    # 500-600 exact samples, "differs" against the 1e-9 |b| floor before
    f0 = pred.get("f0_hz")
    pole = rel * abs(pred["k"]) / (2.0 * math.pi * f0) if f0 and f0 > 0 else 0.0
    db = max(db, rel * abs(pred["b"]), pole)
    # the sensor's and the actuator's rounding in the loop (draws of its phase:
    # hapsim.analysis.pair_rounding), where it exceeds the fit's interval
    rk, rb = measured.get("k_rounding", 0.0), measured.get("b_rounding", 0.0)
    dk, db = max(dk, rk), max(db, rb)
    measured["k_interval"], measured["b_interval"] = dk, db
    from hapsim.analysis.identify import COVERAGE
    if measured.get("method") == "varpro":
        measured["interval_note"] = (f"stated uncertainty: {COVERAGE:g} standard errors of "
                                     f"the fit, residual or sensor, the larger")
    if "k_sd_wire" in measured:
        measured["interval_note"] = (f"stated uncertainty: {COVERAGE:g} standard errors of "
                                     f"the fit, residual, sensor or the wire's number "
                                     f"format, the largest")
    if "k_rounding" in measured:
        from hapsim.analysis.pair_rounding import PAIR_DRAWS, PAIR_MARGIN
        measured["interval_note"] = (
            f"stated uncertainty: {COVERAGE:g} standard errors of the fit, residual, "
            f"sensor or the wire's number format, or {PAIR_MARGIN:g} times the largest "
            f"change of {PAIR_DRAWS} draws of the rounding in the loop, the largest")
    ok = abs(measured["k"] - pred["k"]) <= dk and abs(measured["b"] - pred["b"]) <= db
    measured["within"] = bool(ok)
    measured["verdict"] = ("measured = predicted within the stated uncertainty" if ok else
                           "measured differs from predicted by more than the stated "
                           "uncertainty")



def contact_verdict(measured: dict, replay, seq: np.ndarray, start: int, T: float) -> None:
    """Say why a run with contacts is not comparable with the prediction (in place).

    ``measured`` is :func:`identify`'s result with ``comparable``; when False, ``reason``
    and ``verdict`` name the first row of the free response (sequence number >= ``start``)
    with a contact open (``first_open_sample``, the telemetry row, and ``open_contact``), or
    why the replay stops knowing, and the longest closed stretch against the samples the
    fit needs. Not comparable is no device fault: the run's exit code is unchanged.

    Parameters
    ----------
    measured : dict
        :func:`identify`'s result (with ``comparable``), completed in place.
    replay : object
        The contact replay (:func:`hapsim.pipeline.contact_replay.replay_contacts`):
        ``closed``, ``known``, ``open_link`` per row and ``reason``.
    seq : ndarray of int, shape (n,)
        The rows' sequence numbers.
    start : int
        First sequence number of the free response.
    T : float
        Sample period [s].
    """
    if measured.get("comparable", True):
        return
    seq = np.asarray(seq, dtype=np.int64)
    rows = np.flatnonzero(seq >= start)
    bad = rows[~replay.closed[rows]] if rows.size else rows
    measured["first_open_sample"] = measured["open_contact"] = None
    if bad.size == 0:
        what = "the free response is too short"
    else:
        i = int(bad[0])
        measured["first_open_sample"] = i
        measured["open_contact"] = replay.open_link[i]
        if replay.known[i]:
            verb = "is open at" if i == int(rows[0]) else "opened at"
            what = (f"contact {replay.open_link[i]!r} {verb} sample {i} / t = {i * T:.6g} s")
        else:
            what = replay.reason or f"the contact states are unknown from sample {i}"
    reason = (f"{what}; the prediction holds while every contact is closed; the longest "
              f"closed stretch is {measured['closed_samples']} samples, fewer than the "
              f"{measured['needed']} the fit needs")
    measured["reason"] = reason
    measured["error"] = "not comparable: " + reason
    measured["verdict"] = "not comparable: " + reason
    measured["within"] = None


def late_accounted(scene, cols: dict, hello=None, driver=None, *, restarts=None,
                   computed=None):
    """The logged positions with the response to the late ticks' known disturbance taken
    out, when the device names the force it applied (framed protocol, ``force_seq``).

    A late tick is a known input of the linear loop (:mod:`hapsim.applied`): the
    position minus the loop's response to ``w = applied - F[n-d]``
    (:func:`hapsim.analysis.error_response.disturbance_response`) is the undisturbed loop's,
    so the whole record is measured, not only the longest stretch without a late tick.
    So is an actuator's rounding: a framed device whose HELLO states a ``force_scale``
    (the Hapkit firmware's PWM step, to which it rounds every FORCE to the nearest) applies
    that step's multiple, and ``w`` holds the rounding at every tick (left in, the 22.7 mN
    steps biased the measured k of the emulated Hapkit in real time: -0.336 +- 0.286 N/m
    from the prediction in one record, +0.027 with the rounding taken out).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene (its device: delay, force limit).
    cols : dict of str to ndarray
        Telemetry columns (``seq``, ``position``, ``force``, ``late``, ``force_seq``,
        ``status``), each shape (n,).
    hello : firmware_protocol.Hello, optional
        The device's HELLO (its force limit).
    driver : hapsim.drivers.base.Driver, optional
        The run's driver: its :meth:`~hapsim.drivers.base.Driver.account`, if any, instead
        of ``force_seq``.
    restarts : ndarray of bool, shape (n,), optional
        Rows where the scene restarted (after a recovery).
    computed : ndarray, shape (n,), optional
        The force the loop's law computed at each row before the host clamped it at the
        force limit [N] (:func:`hapsim.pipeline.contact_replay.computed_forces`). The
        clamp is then a known input as a late tick is: ``w`` is the applied force minus
        the computed one (without it, a record that reached the limit is the clamped,
        nonlinear loop's, and is not identified).

    Returns
    -------
    (ndarray, ndarray or None, dict)
        Positions [m] to measure, the late flags to cut at (None when accounted for; a
        driver's run keeps its host-late rows, whose hold time no account names) and
        the report's ``late_accounted`` / ``device_delay`` / ``clamped_accounted`` (rows
        whose clamp was taken out) (empty when nothing was done); with a driver whose
        account does not know some rows' force (``AppliedAccount.known`` False:
        :meth:`~hapsim.drivers.base.Driver.unknown_force_rows`), ``_unknown_rows`` (bool,
        shape (n,)), the rows the measurement must leave out.
    """
    from hapsim.applied import account_from_force_seq

    pos, late = cols["position"], cols["late"]
    fseq = cols.get("force_seq")
    n_clamped = 0 if computed is None else int(np.count_nonzero(
        np.asarray(computed, float) != np.asarray(cols["force"], float)))
    dev = scene.device
    hook = getattr(driver, "account", None) if driver is not None else None
    stage = None
    if driver is not None:
        # a driver's STATEs name no applied force (force_seq = seq - d): its account is
        # its own timing's (Driver.account -> hapsim.applied.account_from_timing)
        acc = hook(cols, cols["force"]) if hook is not None else None
        # a board whose firmware quantises the force on its way to the motor
        # (Driver.output_stage): the account's forces are the motor's, and the on-time
        # ones (the forces sent, through the stage) are the reference of the timing's
        # doubts; the stage's own departure is a known input at every row
        fn = getattr(driver, "output_stage", None)
        stage = fn(np.asarray(cols["force"], float)) if fn is not None else None
        d_drv = getattr(driver, "loop_delay", None)
        if acc is None and stage is not None and d_drv is not None:
            from hapsim.applied import account_from_timing
            acc = account_from_timing(stage[0], int(d_drv), stage_half_width=stage[1])
        if acc is None:
            return pos, late, {}
        # rows whose force the account cannot name at all (an unframed board's parser out
        # of step: Driver.unknown_force_rows), which the measurement cuts out
        kn = np.asarray(acc.known, bool)
        unknown = {"_unknown_rows": ~kn} if kn.shape == np.shape(pos) and not kn.all() \
            else {}
        ref = cols["force"] if stage is None else stage[0]
        if not np.any(acc.late) and not n_clamped:
            # nothing taken out (but the output stage's departure, below), but the forces
            # it cannot order (a command whose answer never came: sent, or the one
            # before) are in the stated uncertainty. The record is measured against the
            # on-time force, so the bound at such a row is the account's distance from it
            # plus its half-width (the middle of the two and half their step, 2x the
            # half-width: the half-width alone, stated before, left the other case
            # outside by as much again)
            hw = np.asarray(acc.half_width, float)
            info = dict(unknown)
            if stage is not None:
                pos, info = _stage_taken_out(scene, cols, pos, stage[0], acc.delay,
                                             restarts, info)
            if np.any(hw > 0):
                w = acc.disturbance(ref, cols["seq"])
                info["_force_half_width"] = hw + np.where(hw > 0, np.abs(w), 0.0)
            return pos, late, info
    else:
        # an actuator with steps (HELLO.force_scale: the Hapkit's 256-step PWM) applies
        # the nearest step of every force (the firmware rounds so): a known input at every
        # tick, late or not, taken out as a late tick's is
        step = float(getattr(hello, "force_scale", 0.0) or 0.0) if hello is not None else 0.0
        step = step if math.isfinite(step) and step > 0 else 0.0
        if fseq is None or not np.any(fseq >= 0) or not (np.any(late) or step > 0
                                                         or n_clamped):
            return pos, late, {}
        lim = float(dev.force_limit)
        if hello is not None and math.isfinite(getattr(hello, "force_limit", math.inf)):
            lim = min(lim, float(hello.force_limit))
        acc = account_from_force_seq(cols["seq"], cols["force"], fseq, cols["status"],
                                     zero_delay=int(dev.delay) == 0, force_limit=lim,
                                     force_scale=step)
    info = {"device_delay": int(acc.delay), "account": acc.method}
    if driver is not None:
        info.update(unknown)
    if driver is None and step > 0:
        info["force_step"] = step
    if acc.delay != int(dev.delay):     # whole ticks: a fraction is the physics'
        # the model of the loop would be the wrong one: measure as recorded, and say so
        info["late_accounted"] = 0
        info["late_note"] = (f"the device shows a delay of {acc.delay} samples, the scene "
                             f"states {dev.delay}: late ticks are not taken out")
        return pos, late, info
    from hapsim.analysis.error_response import disturbance_response
    # the force the linear loop computed (the host's clamp at the force limit, when
    # given, is then part of the known input)
    w = acc.disturbance(cols["force"] if computed is None else computed, cols["seq"])
    # the response sums within each stretch of consecutive STATEs that the scene did not
    # restart in: before a stretch, whatever happened is its initial state
    seq = np.asarray(cols["seq"], np.int64)
    cut = np.diff(seq) != 1
    if restarts is not None:
        cut |= np.asarray(restarts, bool)[1:]
    starts = np.flatnonzero(cut) + 1
    try:
        xw = disturbance_response(scene, w, starts=starts)
    except ConfigError:
        return pos, late, info
    info["late_accounted"] = acc.n_late
    if n_clamped:
        info["clamped_accounted"] = n_clamped
    # what the account leaves uncertain (a driver's timing): a force error per sample
    info["_force_half_width"] = np.asarray(acc.half_width, float)
    if stage is not None:
        # a late tick's doubt is its distance from the on-time force as the motor got it
        # (the stage's own departure, taken out at every row, is no doubt)
        lim_ref = ref if computed is None else np.asarray(computed, float) + (ref - cols[
            "force"])
        info["_late_force_bound"] = late_force_bound(acc, acc.disturbance(lim_ref,
                                                                          cols["seq"]))
        info["output_stage"] = int(np.count_nonzero(ref != np.asarray(cols["force"],
                                                                      float)))
    else:
        info["_late_force_bound"] = late_force_bound(acc, w)
    if driver is not None and late is not None and np.any(late):
        # a driver's account names which force each row applied, not for how long: a
        # host tick that went out late (the row's late flag) held the force before it
        # over more than a period, a disturbance no account takes out; the record is still
        # cut there (before, an account dropped these cuts: the late rows were measured
        # as on time)
        return pos - xw, np.asarray(late, bool), info
    return pos - xw, None, info


def _stage_taken_out(scene, cols: dict, pos, out, delay: int, restarts, info: dict):
    """:func:`late_accounted`'s positions with the response to a board's output stage
    taken out: ``w[k] = out[k - d] - force[k - d]`` on each stretch of consecutive
    ``seq`` (:meth:`hapsim.applied.AppliedAccount.disturbance` of the on-time forces as
    the motor got them), through :func:`hapsim.analysis.error_response.
    disturbance_response`; ``info`` gains ``output_stage`` (the rows whose force the stage
    changed). Unchanged when the loop's model cannot be built."""
    from hapsim.applied import account_from_timing
    from hapsim.analysis.error_response import disturbance_response
    f = np.asarray(cols["force"], float)
    w = account_from_timing(out, max(int(delay), 0)).disturbance(f, cols["seq"])
    seq = np.asarray(cols["seq"], np.int64)
    cut = np.diff(seq) != 1
    if restarts is not None:
        cut |= np.asarray(restarts, bool)[1:]
    try:
        xw = disturbance_response(scene, w, starts=np.flatnonzero(cut) + 1)
    except ConfigError:
        return pos, info
    info = dict(info, output_stage=int(np.count_nonzero(out != f)))
    return pos - xw, info


def late_force_bound(acc, w) -> np.ndarray:
    """The largest error of the force a late tick's account takes out [N], per row.

    At a late tick the device held the force the account names (``applied``) instead of
    the one due (``applied - w``); the record is measured with ``w`` taken out through the
    loop's response. If the account is wrong at that tick the force truly held lies
    between the two (a FORCE arriving within the period is held for part of it: the
    zero-order hold's impulse over the period is a convex combination of both), so the
    error of the taken-out input is at most the whole disturbance, ``|w|``, plus the
    account's own ``half_width``. On every other row the account's input is its
    ``half_width`` (0 from ``force_seq``) and the on-time force, not a late one.

    Parameters
    ----------
    acc : hapsim.applied.AppliedAccount
        The account (its ``late``, ``half_width``), shape (n,).
    w : array_like, shape (n,)
        The disturbance taken out, ``applied - F[k - d]`` [N]
        (:meth:`hapsim.applied.AppliedAccount.disturbance`).

    Returns
    -------
    ndarray, shape (n,)
        ``|w| + half_width`` [N] at late rows, 0 elsewhere.
    """
    late = np.asarray(acc.late, bool)
    return np.where(late, np.abs(np.asarray(w, float)) + np.asarray(acc.half_width, float),
                    0.0)


def estimated_bounds(cols: dict, period: float, mass: float, friction: float,
                     quantum: float, noise: float = 0.0, rel: float = 0.0,
                     estimated_flag: int = 32, coulomb: float = 0.0) -> np.ndarray:
    """The largest error of each estimated sample's position (a driver's missing reply).

    The loop steps a tick whose reply never came with the position extrapolated linearly
    from the last two records (:meth:`hapsim.drivers.transport.DriverTransport.estimate`):
    records ``j`` and ``j - g`` (``g`` ticks apart: 1, or more when a reply between them
    was missing too), the estimate for tick ``j + r`` (``r`` = 1, 2: the ``r``-th in a
    row) is ``x_e = x[j] + r/g (x[j] - x[j-g])``. The reading it stands for, ``x[j+r]``,
    differs from it by the device's motion and the readings' errors: with ``p`` the true
    position and ``x = p + eps``, ``|eps| <= q/2`` (the sensor step q, plus ``3 noise`` and
    the wire's relative rounding), ``x_e - x[j+r] = -(p[j+r] - L(j+r)) + (1 + r/g) eps[j]
    - r/g eps[j-g] - eps[j+r]`` with ``L`` the line through the two records; the error of
    linear interpolation (Taylor's theorem, the remainder of the Lagrange interpolant
    through ``j - g`` and ``j``) bounds the first term by ``r (r+g)/2 T^2 a_max``, the
    rest by ``(1 + r/g) q``. During the missing reply the device applied the force sent or
    the one before (the account's ambiguity): ``a_max = (max|F| + b0 v_max + F_c) / m``
    over the record (no hand on the device in a free response; ``F_c`` its Coulomb
    friction), ``v_max`` from its largest step.

    Parameters
    ----------
    cols : dict of str to ndarray
        Telemetry columns (``position``, ``force``, ``flags``), shape (n,).
    period : float
        Sample period T [s].
    mass, friction : float
        The device's mass m [kg] and viscous friction b0 [N s/m].
    quantum, noise, rel : float
        Sensor step [m], noise standard deviation [m], the wire's relative rounding.
    estimated_flag : int
        The ``flags`` bit of an estimated row (``FLAG_ESTIMATED``).
    coulomb : float
        The device's Coulomb friction F_c [N].

    Returns
    -------
    ndarray, shape (n,)
        The bound [m] at each estimated row, 0 elsewhere.
    """
    flags = np.asarray(cols["flags"])
    est = (flags & estimated_flag) != 0
    out = np.zeros(est.size)
    if not est.any():
        return out
    x = np.asarray(cols["position"], float)
    f = np.asarray(cols["force"], float)
    v = float(np.max(np.abs(np.diff(x)))) / period + quantum / period if x.size > 1 else 0.0
    a = ((float(np.max(np.abs(f))) + abs(friction) * v + abs(coulomb)) / mass
         if mass > 0 else math.inf)
    eps = 0.5 * quantum + 3.0 * noise + rel * float(np.max(np.abs(x)))
    seq = np.asarray(cols["seq"], np.int64) if "seq" in cols else np.arange(est.size)
    last = prev = None                     # the seqs of the last two records
    for k in range(est.size):
        if not est[k]:
            last, prev = int(seq[k]), last
            continue
        r = int(seq[k]) - last if last is not None else 1
        g = last - prev if prev is not None and last > prev else 1
        out[k] = r * (r + g) / 2 * period * period * a + (2 + 2 * r / g) * eps
    return out


def aperture_noise(cols: dict, period: float, estimated_flag: int = 32,
                   use=None, late_flag: int = 1) -> float:
    """The position error's standard deviation [m] of a board that reads its sensor as
    late as the host's write comes (the Hapkit sketch for most write phases,
    ``Hapkit_arduino.ino:96-135``): each reading is off its place on the grid by its
    write's departure ``delta_k``, an error ``v_k delta_k`` (aperture jitter: Kester,
    *Data Conversion Handbook*, 2005, sec. 2.4: the error of a sample taken ``dt`` late
    is the signal's slope times ``dt``), its rms over the readings the fit uses.

    ``delta_k`` is the host's write time less the least-squares line of the write times
    over ``seq``, one line per run of consecutive ``seq`` with no late tick (a constant
    latency shifts nothing; a host stall is a gap in ``seq``, or a row the host marked
    late where it could not skip one, after which the host's deadlines start again where
    it woke, another grid: one line through a run whose deadlines restarted after stalls
    made the departures of a throttled CI host milliseconds, and its floor 4 mm; the late
    row and the next, on neither grid, are left out), the line through the rows used, 0
    under half a microsecond (the time stamps' resolution); ``v_k`` the central
    difference. The force switched after the reading is as late, an error through the
    loop ``(omega T)^2`` times smaller (0.8 % on configs/hapkit_serial.yaml): left out.

    Parameters
    ----------
    cols : dict of str to ndarray
        Telemetry columns (``time`` [s], ``position`` [m], ``seq``, ``flags``), shape (n,).
    period : float
        Sample period T [s].
    estimated_flag : int
        The ``flags`` bit of an estimated row (no reading: left out).
    use : ndarray of bool, shape (n,), optional
        The rows the fit uses (its window, less the rows it leaves out); None: all. A row
        cut (a host's late write marked, a hold no host saw) or before the window is no
        reading of the fit's: its departure is not the fit's noise.
    late_flag : int
        The ``flags`` bit of a row the host was late at
        (:data:`hapsim.host.telemetry.FLAG_LATE`).

    Returns
    -------
    float
        >= 0 [m]; 0 with no run of three readings used or no time column.
    """
    if "time" not in cols:
        return 0.0
    seq = np.asarray(cols["seq"], np.int64)
    read = (np.asarray(cols["flags"]) & estimated_flag) == 0
    used = read if use is None else read & np.asarray(use, bool)
    t = np.asarray(cols["time"], float)
    v = np.gradient(np.asarray(cols["position"], float), period)
    late = (np.asarray(cols["flags"]) & late_flag) != 0
    # the late row and the one after it (written when the host woke, before its deadline
    # was put on the tick again) are on neither grid: each a run of its own, left out
    off = late.copy()
    off[1:] |= late[:-1]
    cuts = np.flatnonzero((np.diff(seq) != 1) | off[1:] | off[:-1]) + 1
    total, count = 0.0, 0
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, seq.size]):
        u = used[a:b]
        if np.count_nonzero(u) < 3:
            continue
        # the line through the rows used alone (a row cut, late by half a tick or more,
        # would tilt it)
        s, tt = seq[a:b][u].astype(float), t[a:b][u]
        A = np.column_stack([s - s.mean(), np.ones(s.size)])
        delta = tt - A @ np.linalg.lstsq(A, tt, rcond=None)[0]
        delta[np.abs(delta) < 0.5e-6] = 0.0
        total += float(np.sum((v[a:b][u] * delta) ** 2))
        count += int(s.size)
    return math.sqrt(total / count) if count else 0.0


def wire_errors(scene, cols: dict, start: int, driver) -> list:
    """The wire's number-format errors of a driver's run, for the stated uncertainty.

    A driver declares ``position_rel`` / ``force_rel`` (the relative rounding of a float32
    field: at most ``2^-24``) and ``force_scale`` (an actuator step: the FireFader's 8-bit
    PWM). Each is a bounded error per sample; taken as uniform, its standard deviation is
    ``u |v|_max / sqrt(3)`` (``|v|_max`` over the free response) or ``s / sqrt(12)``. The
    position's rounding reaches the record as the sensor's does
    (:func:`hapsim.analysis.error_response.sensor_error_response`: observed, and fed back through
    the virtual links), the force's as a force error at the device
    (:func:`hapsim.analysis.error_response.force_error_response`).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene.
    cols : dict of str to ndarray
        Telemetry columns (``seq``, ``position``, ``force``).
    start : int
        First sequence number of the free response.
    driver : hapsim.drivers.base.Driver or None
        The run's driver (None: hapsim's own protocol).

    Returns
    -------
    list of (float, ndarray)
        ``(sd, response)`` pairs; empty for hapsim's own protocol (float64 fields).
    """
    if driver is None:
        return []
    from hapsim.analysis.error_response import force_error_response, sensor_error_response
    sel = cols["seq"] >= start
    x, f = cols["position"][sel], cols["force"][sel]
    n = int(x.size)
    if n == 0:
        return []
    out = []
    pr = float(getattr(driver, "position_rel", 0.0) or 0.0)
    fr = float(getattr(driver, "force_rel", 0.0) or 0.0)
    fs = float(getattr(driver, "force_scale", 0.0) or 0.0)
    try:
        if pr > 0:
            out.append((pr * float(np.max(np.abs(x))) / math.sqrt(3.0),
                        sensor_error_response(scene, n)))
        sd_f = math.sqrt((fr * float(np.max(np.abs(f)))) ** 2 / 3.0 + fs * fs / 12.0)
        if sd_f > 0:
            out.append((sd_f, force_error_response(scene, n)))
    except ConfigError:
        return []
    return out
