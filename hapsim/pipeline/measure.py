"""Step 5 of a run (:mod:`hapsim.pipeline.runner`): identify the free response the run logged
after its excitation and compare it with the prediction (docs/design.md, 'The THS').

:func:`identify_run` reads the telemetry, accounts for late ticks, clamped forces, a
driver's missing replies and the sensor's step (:mod:`hapsim.analysis.measurement`), fits
the felt pair (:func:`hapsim.analysis.measurement.identify`) and states the verdict
against the prediction, with the notes on why the two may differ."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hapsim.analysis.measurement import (aperture_noise, contact_verdict, identify,
                                         late_accounted, relative_error, verdict,
                                         wire_errors)
from hapsim.analysis.network import device_body
from hapsim.analysis.prediction import has_offset, predict, predicted_poles
from hapsim.pipeline.run_types import PreparedRun
from hapsim.host.telemetry import FLAG_ESTIMATED, Telemetry
from hapsim.errors import ConfigError
from hapsim.scene import Scene

__all__ = ["identify_run", "sensor_step", "informative_s", "contact_replay",
           "measure_record", "MEASURE_KEYS", "timing_verdict", "LATE_SHARE_MAX"]

#: What the page gets of a measurement (:func:`measure_record`).
MEASURE_KEYS = ("k", "b", "k_unc", "b_unc", "verdict", "within", "comparable", "reason",
                "error")


def contact_replay(scene: Scene, cols: dict, skipped=None):
    """Contact states of the run's rows, replayed from its telemetry.

    Parameters
    ----------
    scene : Scene
        The run's (calibrated) scene.
    cols : dict of ndarray
        Telemetry columns (:meth:`hapsim.host.telemetry.Telemetry.columns`), each of
        shape ``(n,)``: ``position`` [m], ``force`` [N], ``seq``, ``flags``...
    skipped : tuple, optional
        The run's skipped STATEs' record (:meth:`hapsim.host.telemetry.Telemetry.skipped`),
        replayed too; None: none kept (a snapshot of the rows).

    Returns
    -------
    ContactReplay or None
        :func:`hapsim.pipeline.contact_replay.replay_contacts`'s result (which contacts are
        closed at each row), or None for a scene without contacts or without a port.
    """
    from hapsim.pipeline.contact_replay import contact_links, replay_contacts
    if not contact_links(scene) or scene.port is None:
        return None
    return replay_contacts(scene, cols, passivity=bool(scene.safety.passivity_controller),
                           skipped=skipped)



def identify_run(prep: PreparedRun, tel: Telemetry, hello=None, driver=None) -> dict:
    """Step 5: identify the free response logged at the start and compare it.

    A driver's board that renders some time after its read, known within bounds
    (``prep.pred["render_latency_s"]``, :func:`hapsim.pipeline.render_latency.
    timed_prediction`): the measurement is made with the loop modelled at the latency
    within the bounds at which the measured and predicted felt damping agree
    (:func:`hapsim.pipeline.render_latency.latency_search`), ``prep.pred`` updated to it.

    The whole record while it fits in memory; the head once the ring has gone round.

    Parameters
    ----------
    prep : PreparedRun
        :func:`hapsim.pipeline.runner.prepare_run`'s result.
    tel : Telemetry
        The run's telemetry.
    hello : firmware_protocol.Hello, optional
        The device's HELLO: its ``position_scale`` is the sensor step when the scene's
        ``device.position_resolution`` does not give one.
    driver : hapsim.drivers.base.Driver, optional
        The run's driver: its wire's number format is in the stated uncertainty
        (:func:`hapsim.analysis.measurement.wire_errors`), and its ``position_scale``
        [m/count] is the sensor step when neither the scene nor a HELLO gives one (the
        quantiser's share, q^2 / 12 through the loop: Widrow & Kollar 2008, ch. 4; with
        its ``force_scale``, the rounding in the loop by draws of its phase:
        :mod:`hapsim.analysis.pair_rounding`).

    Returns
    -------
    dict
        :func:`identify`'s result with ``verdict``, ``within``, ``k_interval``,
        ``b_interval`` (:func:`verdict`), ``note`` (why prediction and measurement may differ),
        ``rel_err`` against the prediction and ``rel_err_target`` (one target only);
        ``comparable`` (True with a measurement; False, with ``reason``,
        ``first_open_sample``, ``open_contact``, ``closed_samples`` and ``needed``, when a
        scene's contacts leave no closed stretch long enough: :func:`contact_verdict`).
    """
    if prep.informative_s is None:
        # (once: every fit of the search and of the fixed point measures the same head)
        prep = dataclasses.replace(prep, informative_s=informative_s(
            prep.scene, predict(prep.scene), driver))
    if prep.pred.get("render_latency_s") and prep.model_scene is not None:
        from hapsim.pipeline.render_latency import latency_search
        return latency_search(prep, lambda p, final: _identify_at(
            p, tel, hello, driver, searching=not final, review=final is True))
    return _identify_at(prep, tel, hello, driver)


def informative_s(scene: Scene, pred: dict, driver) -> float:
    """How long the predicted free response from the scene's start ``x0`` stays worth
    measuring when the position sensor has a step ``q`` (:func:`sensor_step`): until its
    envelope ``x0 exp(-sigma t)`` falls below the level a measurement counts cycles above
    (:data:`hapsim.analysis.identify.MIN_QUANTA` steps), and one cycle more.

    Below that level the record spans a few steps and its quantisation error follows the
    signal (Widrow & Kollar, *Quantization Noise*, 2008, ch. 4-5): no cycle more, a bias
    (``configs/firefader.yaml``: k 15.121-15.213 N/m fitted over 1.5-3.6 s against 15.153,
    docs/drivers.md, "The default record length"). The default run records this long
    (:func:`hapsim.pipeline.runner.prepare_run`), a longer record is measured over it.

    Parameters
    ----------
    scene : hapsim.scene.Scene
    pred : dict
        The prediction: ``f0_hz`` [Hz] and ``damping_ratio`` of the felt pair.
    driver : hapsim.drivers.base.Driver or None

    Returns
    -------
    float
        Seconds from the free response's start [s]; ``inf`` without a step, a start above
        the level or a decay.
    """
    from hapsim.analysis.identify import MIN_QUANTA
    q = sensor_step(scene.device, None, driver)
    x0 = abs(float(scene.excitation.x0))
    f0, zeta = pred.get("f0_hz"), pred.get("damping_ratio")
    if not (q > 0 and x0 > MIN_QUANTA * q and f0 and zeta and 0 < zeta < 1):
        return math.inf
    sigma = 2.0 * math.pi * float(f0) * float(zeta)
    return math.log(x0 / (MIN_QUANTA * q)) / sigma + 1.0 / float(f0)


def _informative_head(prep: PreparedRun, cols: dict) -> tuple:
    """A record's rows worth measuring: ``(cols, dropped)``, its rows up to
    ``prep.informative_s`` after the free response's start (the scene's own prediction,
    the same whatever latency the loop is modelled with) or the default record's length
    (``prep.window``), the longer; ``dropped`` the rows left out (0: the record
    unchanged). A run's ``--duration`` longer than that is logged whole: the tail below
    the sensor's level only biased the fit (:func:`informative_s`)."""
    n = int(cols["seq"].size)
    if n == 0:
        return cols, 0
    keep_s = prep.exc_end + prep.informative_s        # (set by identify_run)
    if not math.isfinite(keep_s):
        return cols, 0
    keep_s = max(keep_s, prep.window)           # (the default record: measured whole)
    last = int(cols["seq"][0]) + max(int(round(keep_s / prep.scene.period)), 1)
    m = int(np.searchsorted(np.asarray(cols["seq"]), last, side="left"))
    if m >= n:
        return cols, 0
    return {k: (v[:m] if isinstance(v, np.ndarray) and v.shape[:1] == (n,) else v)
            for k, v in cols.items()}, n - m


def sensor_step(device, hello=None, driver=None) -> float:
    """The position sensor's step ``q`` [m] a run's record is read with: the device's
    ``position_resolution``, else the device's HELLO ``position_scale``, else the
    driver's own count (a driver's positions are its wire's counts, FireFader 0.39 mm,
    whether or not a HELLO relayed it: an offline record has none; without it the
    sensor's share of the stated uncertainty was 0); 0 when none is known.

    Parameters
    ----------
    device : hapsim.scene.Device
    hello : firmware_protocol.Hello, optional
    driver : hapsim.drivers.base.Driver, optional

    Returns
    -------
    float
        ``q`` >= 0 [m].
    """
    quantum = float(device.position_resolution or 0.0)
    if not quantum and hello is not None and math.isfinite(hello.position_scale):
        quantum = max(float(hello.position_scale), 0.0)
    if not quantum and driver is not None:
        ds = float(getattr(driver, "position_scale", 0.0) or 0.0)
        quantum = ds if math.isfinite(ds) and ds > 0 else 0.0
    return quantum


def _identify_at(prep: PreparedRun, tel: Telemetry, hello=None, driver=None, *,
                 searching: bool = False, review: bool = True) -> dict:
    """:func:`identify_run` with the loop modelled as ``prep`` states it
    (:attr:`PreparedRun.model`: a driver's render latency in its delay). ``searching``:
    a measurement of :func:`hapsim.pipeline.render_latency.latency_search`'s search, the
    review of a "differs" on a board's unseen holds left out (a test of the record that
    the run makes once, at the latency found: made at each latency tried, it had as many
    chances to explain a device that differs away), and the known inputs taken out
    through the predicted loop. ``review`` False: the loop the record measures found
    (not ``searching``), the review left out (the pair at a latency's bound, whose
    verdict is not the run's)."""
    scene = prep.model
    dev, pred, targets = scene.device, prep.pred, prep.targets
    measured, late_info, cols, known = _fit_record(prep, tel, hello, driver)
    if known and not searching and "k" in measured:
        # the known inputs were taken out through the predicted loop: again through the
        # loop the record measured (hapsim.pipeline.loop_refit). A "differs"'s review asks
        # whether the PREDICTED loop explains the record: its state stays this fit's, the
        # known inputs taken out through that loop (through the measured one, a misfit of
        # that correction, 5 % of the record on the sketch's levels, was left in every
        # row with the predicted poles, and no break could explain it)
        tested = measured.get("_unseen")
        measured = _through_loop(prep, tel, hello, driver, measured)
        if tested is not None and "_unseen" in measured:
            found = _refit_device(scene, measured)
            if found is not None:
                # the review's alternative: the loop the record measured, its record
                loop = dataclasses.replace(scene, device=found)
                tested = {**tested, "alternative": {
                    "poles": predicted_poles(loop)[0],
                    "position": measured["_unseen"]["position"]}}
            measured["_unseen"] = tested
    measured.pop("_hold_rows", None)
    notes = []
    if any(lk.kind == "contact" for lk in scene.links) and measured.get("comparable"):
        notes.append("the scene has contacts: the prediction takes them engaged, so only the "
                     "longest stretch with every contact closed (replayed from the "
                     "telemetry) is identified")
    if any(m.kind == "mass" for m in scene.masses) and "k" in measured:
        notes.append("virtual masses add modes: the identified pair is the one at the "
                     "predicted felt pole, which the excitation may barely excite")
    sensor = (dev.correction or {}).get("kind") == "velocity_sensor"
    if (dev.coulomb > 0 or dev.noise > 0 or dev.position_resolution > 0
            or sensor and (dev.velocity_noise > 0 or dev.velocity_resolution > 0)):
        notes.append("the mock adds Coulomb friction, noise or quantisation: the measured "
                     "loop is not the linear THS exactly")
    if late_info:
        measured.update(late_info)
    n_est = int(np.count_nonzero(cols["flags"] & FLAG_ESTIMATED)) if "flags" in cols else 0
    if n_est and "k" in measured:
        # a driver's missing replies: the scene stepped through them with an extrapolated
        # position, wrong by at most estimated_bounds; its worst case through the loop is
        # in the stated uncertainty (k_bound_rows, b_bound_rows)
        measured["estimated_samples"] = n_est
        notes.append(f"{n_est} samples had no reply (a driver's lossy link) and were "
                     f"stepped through with an extrapolated position: the stated "
                     f"uncertainty covers the worst case of their error (k +-"
                     f"{measured.get('k_bound_rows', 0.0):.3g}, b +-"
                     f"{measured.get('b_bound_rows', 0.0):.3g} of it)")
    tail = measured.get("tail_left_out", 0)
    if tail and "k" in measured:
        from hapsim.analysis.identify import MIN_QUANTA
        notes.append(f"the record's last {tail} samples were left out: the predicted "
                     f"oscillation there is below {MIN_QUANTA:g} sensor steps, where "
                     f"the sensor's rounding follows the signal and biases the fit "
                     f"(informative_s; the telemetry keeps them)")
    n_unseen = measured.get("unseen_holds", 0)
    if n_unseen:
        notes.append(f"{n_unseen} holds the board took off the period, which the host "
                     f"did not see (its own read latency), were found in the record and "
                     f"cut (unseen_hold_seqs)")
    late_in = measured.get("late_in_segment", 0)
    if late_in:
        notes.append(f"no stretch of 100 samples without late ticks: the identified record "
                     f"holds {late_in} late ticks (the device held an older force), so the "
                     f"measured pair is a disturbed loop, not the THS alone; rerun on a "
                     f"quieter machine, at a lower rate, or with --lockstep")
    if notes:
        measured["note"] = "; ".join(notes)
    rounding = measured.pop("_rounding", None)
    if rounding is not None and not searching and "k" in measured:
        # the sensor's and the actuator's rounding in the loop, by draws of their phase
        from hapsim.analysis.pair_rounding import state_rounding
        state_rounding(measured, scene, *rounding,
                       float(getattr(driver, "force_scale", 0.0) or 0.0))
    verdict(prep.pred, measured)
    from hapsim.analysis.coulomb_check import coulomb_verdict
    coulomb_verdict(measured, dev, scene.period)     # the linear prediction's blind spot
    link_within = measured.pop("_link_within", None)
    if link_within and measured.get("within") is False:
        # beyond the stated uncertainty, but within it with the link's unseen latency
        # varying by LINK_JITTER_S between writes too: not told from the write timing
        from hapsim.pipeline.haply2_host import LINK_JITTER_S
        measured["within"] = False
        measured["verdict"] = (
            "not measurable: the board keeps its own time and the departure from the "
            "prediction is within what the link's latency, unseen by the host, varying "
            f"by up to {LINK_JITTER_S * 1e6:.0f} us between writes could make (k +-"
            f"{measured['link_k_unc']:.3g}, b +-{measured['link_b_unc']:.3g}); rerun "
            "with the board in lockstep to measure the loop")
    review_differs_too, review = review, measured.pop("_unseen", None)
    if searching and review is not None:
        # the record's test at this latency, for the search's review of a "differs"
        # (hapsim.pipeline.render_latency.latency_search)
        measured["_tested"] = review
    if (review is not None and measured.get("within") is False and not searching
            and review_differs_too):
        # a board on its own tick: the "differs" stands only where the predicted loop,
        # broken where its unseen holds may have struck, does not explain the record
        from hapsim.pipeline.unseen_review import review_differs
        measured = review_differs(pred, measured, review)
    if not searching and getattr(driver, "tick_moved", None) is not None:
        from hapsim.pipeline.unseen_review import review_tick_walk
        review_tick_walk(measured, driver)     # (a board's tick that walked)
    if "k" in measured:
        measured.setdefault("comparable", True)
        measured["rel_err"] = {q: relative_error(measured[q], pred.get(q))
                               for q in ("k", "b", "f0_hz", "damping_ratio")}
        if len(targets) == 1:     # with several targets the felt pair is their sum
            t0 = targets[0]
            measured["rel_err_target"] = {q: relative_error(measured[q], t0[q])
                                          for q in ("k", "b", "f0_hz", "damping_ratio")}
    return measured


def _through_loop(prep: PreparedRun, tel: Telemetry, hello, driver, measured: dict) -> dict:
    """:func:`_identify_at`'s measurement with its known inputs taken out through the loop
    it measures (:func:`hapsim.pipeline.loop_refit.through_measured_loop`).

    A board on its own tick (a search for the holds it mistimed unseen): the fixed point
    is found with the holds the search found through the predicted loop cut as they are
    (a hold "found" where that loop's correction left its own error is no hold, and its
    cut loses rows, never biases: 2-9 such on records that held none), the search is made
    again through the loop found, and where it finds other holds the fixed point is found
    again with those cut.
    """
    from hapsim.pipeline.loop_refit import through_measured_loop
    scene = prep.model
    rows = measured.get("_hold_rows")

    def fit(d, given):
        return _fit_record(prep, tel, hello, driver, loop_device=d, unseen=given)[0]

    at = through_measured_loop(scene, measured, lambda d: fit(d, rows))
    found = _refit_device(scene, at)
    if rows is None or "k" not in at or found is None:
        return at
    searched = fit(found, None)
    again = searched.get("_hold_rows", ([], []))
    if "k" not in searched:
        return searched
    if sorted(again[0]) == sorted(rows[0]):
        return at
    return through_measured_loop(scene, searched, lambda d: fit(d, again), start=found)


def _refit_device(scene: Scene, measured: dict):
    """The device of the loop the record measured: the scene's with the mass and friction
    :mod:`hapsim.pipeline.loop_refit` found (``measured["loop_refit"]["device"]``); None
    without a refit."""
    got = (measured.get("loop_refit") or {}).get("device")
    return (None if got is None else
            dataclasses.replace(scene.device, mass=got[0], friction=got[1]))


def _fit_record(prep: PreparedRun, tel: Telemetry, hello=None, driver=None, *,
                loop_device=None, unseen=None):
    """:func:`_identify_at`'s fit of the record, before its verdict.

    ``loop_device``: the device of the loop the known inputs (late ticks, an output
    stage, a board's write holds) and the errors' responses are taken through
    (:mod:`hapsim.pipeline.loop_refit`); default the model's. The law's replays, the
    fit's starting poles and the mass the felt pair is expressed with stay the model's.
    ``unseen``: a board on its own tick, the holds to cut without a search
    (:func:`hapsim.pipeline.unseen_review.cut_unseen_holds`' ``given``); default: searched.

    Returns
    -------
    (dict, dict, dict, bool)
        The measurement, the late ticks' report (:func:`late_accounted`), the telemetry
        columns, and whether a known input was taken out through the loop (the record
        measured is not the record logged).
    """
    scene = prep.model
    dev, pred = scene.device, prep.pred
    loop = scene if loop_device is None else dataclasses.replace(scene, device=loop_device)
    known = False
    T = scene.period
    cols = tel.columns((0, min(tel.n, tel.head))) if tel.wrapped else tel.columns()
    tail = 0
    measured = {"error": "not identified"}
    late_info = {}
    quantum = sensor_step(dev, hello, driver)
    if pred["order"]:
        start = int(math.ceil(prep.exc_end / T - 1e-9)) + math.ceil(float(dev.delay)) + 3
        if cols["seq"].size:
            start += int(cols["seq"][0])
        offset = has_offset(scene)
        poles, felt = predicted_poles(scene)
        response = None
        if quantum > 0 or dev.noise > 0:
            from hapsim.analysis.error_response import sensor_error_response
            try:
                response = sensor_error_response(loop, int(cols["seq"].size))
            except ConfigError:
                response = None
        # the skipped STATEs the loop stepped the scene with (a backlog), kept beside the
        # rows: replayed too, so a backlog does not end what the replay knows
        skipped = tel.skipped() if hasattr(tel, "skipped") else None
        put_back = 0
        if skipped is not None and skipped[0].size:
            # and they are samples of the device: put back in the record as the rows they
            # would have been (their law forces replayed), a backlog leaves no gap in seq
            from hapsim.pipeline.contact_replay import fill_skipped
            filled = fill_skipped(scene, cols, skipped, tel.skipped_ticks(),
                                  int(math.ceil(float(dev.delay))),
                                  bool(scene.safety.passivity_controller))
            if filled is not None:
                put_back = int(filled[0]["seq"].size - cols["seq"].size)
                cols, skipped = filled
        if skipped is None or not skipped[0].size:
            # (a skipped STATE not put back names its row: the record kept whole then)
            cols, tail = _informative_head(prep, cols)
        replay = contact_replay(scene, cols, skipped)
        from hapsim.host.telemetry import FLAG_LOST, FLAG_RAMP
        from hapsim.host.telemetry import FLAG_CLAMPED
        computed = None
        if np.any(cols["flags"] & FLAG_CLAMPED) and not scene.safety.passivity_controller:
            # the host's clamp at the force limit: a known input (the law's force
            # replayed from the logged positions), taken out with the late ticks'
            from hapsim.pipeline.contact_replay import computed_forces
            # (an empty record replays as none)
            computed = computed_forces(
                scene, cols, skipped=skipped if skipped is not None and skipped[0].size
                else None)
        # rows the host clamped at the force limit whose law force the replay cannot give
        # (skipped STATEs past the skipped STATEs' record: their positions, which the law
        # stepped through, are not kept;
        # a live change; the passivity controller): the force the device held there is
        # the clamped one, not the linear loop's, an input the account does not know. Left
        # out, the record cut there: the stretch after them is a free response from its
        # own initial state (the clamped forces still in flight are part of it; the fit
        # drops each stretch's first delay + 2 rows), so the measurement stays exact
        clamp_unknown = (cols["flags"] & FLAG_CLAMPED) != 0 if computed is None else None
        position, late, late_info = late_accounted(
            loop, cols, hello, driver, restarts=(cols["flags"] & FLAG_LOST) != 0,
            computed=computed)
        # rows whose applied force the driver's account cannot name (an unframed board's
        # parser out of step: hapsim.drivers.base.Driver.unknown_force_rows), cut as those
        unknown = late_info.pop("_unknown_rows", None)
        if unknown is not None:
            clamp_unknown = unknown if clamp_unknown is None else clamp_unknown | unknown
        # rows whose force a board on its own tick held a tick longer or shorter than the
        # period, or whose reading the transport found paired with another command
        # (hapsim.drivers.base.Driver.mistimed_rows), cut as those
        rows_of = getattr(driver, "mistimed_rows", None)
        mistimed = None if rows_of is None else rows_of(cols)
        if mistimed is not None:
            clamp_unknown = mistimed if clamp_unknown is None else clamp_unknown | mistimed
        # a board on its own clock holding each force from its write's arrival: the holds'
        # departures from a period corrected (the host's write times), the far ones cut
        holds = _write_holds(loop, cols, driver, quantum)
        if holds is not None:
            position = position - holds[0]["motion"]
            cut = holds[0]["cut"]
            clamp_unknown = cut if clamp_unknown is None else clamp_unknown | cut
        wire = wire_errors(loop, cols, start, driver)
        if holds is not None:
            wire = wire + holds[0]["wire"]
        hw = late_info.pop("_force_half_width", None)
        lfb = late_info.pop("_late_force_bound", None)
        late_bounds = None if lfb is None else []
        if lfb is not None and np.any(lfb > 0):
            # the late ticks' accounted forces, wrong by at most the disturbance taken out:
            # their worst case through the fit, apart (a side decided on b adds it)
            from hapsim.analysis.error_response import force_error_response
            late_bounds = [(lfb, force_error_response(loop, int(cols["seq"].size)))]
        bounds = []
        if hw is not None and np.any(hw > 0):
            # the forces the account cannot name (a command whose answer never came: sent
            # or the one before), bounded at their rows, through the loop's force
            # response: their worst case is in the stated uncertainty
            from hapsim.analysis.error_response import force_error_response
            bounds.append((hw, force_error_response(loop, int(cols["seq"].size))))
        if "flags" in cols and np.any(cols["flags"] & FLAG_ESTIMATED):
            # a driver's missing replies: the positions the loop stepped through them with
            # are extrapolations, wrong by at most what the device can have done meanwhile
            from hapsim.analysis.measurement import estimated_bounds
            if response is None:
                from hapsim.analysis.error_response import sensor_error_response
                try:
                    response = sensor_error_response(loop, int(cols["seq"].size))
                except ConfigError:
                    response = None
            if response is not None:
                bounds.append((estimated_bounds(
                    cols, T, *device_body(dev), quantum, dev.noise,
                    float(getattr(driver, "position_rel", 0.0) or 0.0), FLAG_ESTIMATED,
                    coulomb=dev.coulomb), response))
        exclude = (cols["flags"] & FLAG_RAMP) != 0
        exclude = exclude if clamp_unknown is None else exclude | clamp_unknown
        if holds is not None:
            bounds += holds[0]["bounds"]
        # a board reading as late as the writes come: their jitter (on the rows the fit
        # uses) is its sensor's noise
        jit = getattr(driver, "samples_at_write", False) and driver.own_tick
        noise = math.hypot(dev.noise, aperture_noise(
            cols, T, FLAG_ESTIMATED, (cols["seq"] >= start) & ~exclude) if jit else 0.0)

        last: dict = {}

        def fitted(ex, fit=None):
            last["fit"] = {} if fit is None else fit      # (its windows: the rounding's)
            return identify(position, cols["seq"], T, pred["order"], device_body(dev)[0],
                            start, offset=offset, late=late,
                            skip=math.ceil(float(dev.delay)) + 2, predicted=poles,
                            felt=felt, quantum=quantum, noise=noise,
                            sensor_response=response,
                            closed=None if replay is None else replay.closed, exclude=ex,
                            wire=wire, bounds=bounds or None, late_bounds=late_bounds,
                            fit=last["fit"])
        if getattr(driver, "own_tick", False) and float(getattr(driver, "tick_s", 0.0)) > 0:
            # a board on its own tick and clock: the holds it mistimed that the host did
            # not see, found in the record and cut as the marked ones
            # (hapsim.analysis.unseen_holds); a lockstep mock has no tick to mistime
            # rows with an error the stated uncertainty bounds already (an estimated
            # position, a force the account cannot name or a late tick's): no hold there
            unread = (cols["flags"] & FLAG_ESTIMATED) != 0
            for b in (hw, lfb):
                if b is not None:
                    unread = unread | (np.asarray(b, float) > 0)
            from hapsim.pipeline.unseen_review import cut_unseen_holds
            measured = cut_unseen_holds(loop, fitted, exclude, position, cols, quantum,
                                         driver, unread, poles, given=unseen)
        else:
            measured = fitted(exclude)
        if "k" in measured and last["fit"].get("rows"):
            measured["_rounding"] = (position, last["fit"], quantum, poles, felt)
        if holds is not None and "k" in measured:
            _link_check(prep.pred, measured, fitted, exclude, bounds, holds)
        if mistimed is not None:
            measured["mistimed_rows"] = int(np.count_nonzero(mistimed))
        if replay is not None:
            contact_verdict(measured, replay, cols["seq"], start, T)
        if measured.get("first_seq") is not None and cols["seq"].size:
            # the identified stretch's first row of the run (live changes are journaled
            # by row: hapsim.audio.journal.revise_measurement)
            measured["first_row"] = int(measured["first_seq"] - cols["seq"][0])
        if put_back:
            measured["skipped_put_back"] = put_back   # rows of skipped STATEs measured too
        known = not np.array_equal(position, cols["position"])
        if known and "k" in measured:
            from hapsim.analysis.identify import sensor_sd
            _own_motion(measured, cols["position"], position, exclude,
                        sensor_sd(quantum, dev.noise))
    if tail:
        measured["tail_left_out"] = tail
    return measured, late_info, cols, known


def _own_motion(measured: dict, raw, position, exclude, floor: float) -> None:
    """A measurement of a record with known inputs taken out through the predicted loop,
    refused (in place: ``error``, the pair removed) where the handle did not move over
    the rows measured.

    The known inputs' response (an output stage's levels, late ticks' forces, a clamp)
    is the model's: on a handle that stopped (held by a Coulomb friction the scene does
    not state, 0.03 N on a 21 N/m paddle: the record constant from its second cycle on)
    the record measured was that response alone, the predicted loop's free response,
    and the pair came out as predicted to 1e-14 with "within"
    (tests/test_unseen_accepted.py). The record logged must move over those rows by more
    than its sensor's noise could: its norm about its mean above ``2 sigma sqrt(N)``
    (``N`` rows, ``sigma`` the sensor's deviation; white noise alone gives
    ``sigma sqrt(N - 1)``, within ``sigma / sqrt(2)`` of it). A response taken out as
    large as the motion is no fault (a record driven into the force limit, clamped, still
    measures the prediction to 1e-6: tests/test_identify_late.py).

    Parameters
    ----------
    measured : dict
        The fit's result (``first_row``; the rows from it on, not ``exclude``d, are the
        ones measured).
    raw, position : ndarray, shape (n,)
        The record logged and the record measured [m].
    exclude : ndarray of bool, shape (n,)
        Rows the fit left out.
    floor : float
        The sensor's standard deviation [m] (0: read exactly).
    """
    first = int(measured.get("first_row") or 0)
    keep = np.zeros(len(raw), bool)
    keep[first:] = True
    keep &= ~np.asarray(exclude, bool)
    x = np.asarray(raw, float)[keep]
    if not x.size:
        return
    own = float(np.linalg.norm(x - x.mean()))
    if own > 2.0 * float(floor) * math.sqrt(x.size):
        return
    c = (np.asarray(raw, float) - position)[keep]
    for q in [q for q in measured if q in ("k", "b", "f0_hz", "damping_ratio")
              or q.startswith(("k_", "b_"))]:
        measured.pop(q)
    measured["error"] = (
        f"not identified: the handle did not move over the {x.size} rows measured "
        f"({own:.3g} m about its mean, within its sensor's noise): the oscillation "
        f"there ({float(np.linalg.norm(c - c.mean())):.3g} m) was the known inputs' "
        f"response taken out of the record (an output stage's levels, late or clamped "
        f"forces) through the predicted loop, the model's, not the device's (a handle "
        f"stopped, held by friction the scene does not state?)")


def _write_holds(scene, cols: dict, driver, quantum: float):
    """The host's write timing of a run whose board holds each force from its write's
    arrival, on its own clock (:attr:`hapsim.drivers.base.Driver.holds_from_write`,
    ``own_clock``), with the scene's delay the board's one period: the record's
    correction and its remainder, without and with the link's unseen latency variation.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene.
    cols : dict of ndarray
        The telemetry columns (``time`` [s], ``position``, ``force``, ``seq``,
        ``flags``), shape (n,).
    driver : hapsim.drivers.base.Driver or None
    quantum : float
        The sensor's step [m].

    Returns
    -------
    tuple or None
        :func:`hapsim.analysis.write_holds.write_time_terms` with ``latency_s`` 0 (a
        dict), and a callable giving it with :data:`hapsim.pipeline.haply2_host.
        LINK_JITTER_S` (the firmware's pass; computed only for a "differs"); None when it
        does not apply (another board, a lockstep mock, another delay, no times).
    """
    if not (getattr(driver, "holds_from_write", False) and getattr(driver, "own_clock", False)
            and float(scene.device.delay) == 1.0 and "time" in cols and cols["time"].size):
        return None
    from hapsim.analysis.write_holds import state_change_responses, write_time_terms
    from hapsim.host.telemetry import FLAG_ESTIMATED
    from hapsim.pipeline.haply2_host import LINK_JITTER_S
    try:
        resp = state_change_responses(scene, int(cols["seq"].size))
    except ConfigError:
        return None
    pr = float(getattr(driver, "position_rel", 0.0) or 0.0)

    def terms(L):
        return write_time_terms(scene, cols, quantum=quantum, position_rel=pr, latency_s=L,
                                flag_estimated=FLAG_ESTIMATED, responses=resp)
    return terms(0.0), lambda: terms(LINK_JITTER_S)


def _link_check(pred, measured, fitted, exclude, bounds, holds) -> None:
    """A "differs" of a board on its own clock stands only beyond the uncertainty with the
    link's unseen latency varying too (as :func:`hapsim.pipeline.haply2_host.
    measure_felt_haply2_port`): the fit again with the remainder's bounds at
    ``holds[1]()``'s latency; ``measured`` gets ``write_hold_s`` (the largest hold off a
    period kept, corrected), ``link_k_unc``, ``link_b_unc`` and ``_link_within`` (that
    fit's verdict), which :func:`identify_run` reads after its own."""
    measured["write_hold_s"] = holds[0]["hold_s"]
    probe = dict(measured)
    verdict(pred, probe)
    if probe.get("within") is not False:
        return
    n0 = len(bounds) - len(holds[0]["bounds"])
    bounds[n0:] = holds[1]()["bounds"]
    link = fitted(exclude)
    verdict(pred, link)
    measured["link_k_unc"] = link.get("k_interval", math.nan)
    measured["link_b_unc"] = link.get("b_interval", math.nan)
    measured["_link_within"] = link.get("within") is True


class _Record:
    """A snapshot of a run's first rows, read as :func:`identify_run`
    reads the run's :class:`~hapsim.host.telemetry.Telemetry` (nothing wrapped)."""

    wrapped = False

    def __init__(self, cols: dict) -> None:
        from hapsim.host.telemetry import COLUMNS
        # the columns only (an .npz's ``events``, a run's description, is no row)
        self._cols = {c: cols[c] for c in COLUMNS if c in cols}
        self.n = self.head = int(cols["seq"].size)

    def columns(self, rows=None) -> dict:
        a, b = rows if rows is not None else (0, self.n)
        return {c: v[a:b] for c, v in self._cols.items()}


def measure_record(prep, cols: dict, hello=None) -> dict:
    """The felt (k, b) of a run's record so far, measured as its report will measure it.

    :func:`identify_run` (the matrix pencil of the free response,
    Hua & Sarkar 1990, with the run's late ticks, clamps, contacts and sensor accounted)
    on the rows recorded so far: the same function on the same rows as the report's
    ``measured`` once the record is whole. Run in the controller's analysis process.

    Parameters
    ----------
    prep : hapsim.pipeline.run_types.PreparedRun
        The run's calibrated scene, prediction and targets.
    cols : dict of ndarray
        The telemetry columns (:data:`hapsim.host.telemetry.COLUMNS`) of rows
        ``0 .. n - 1``, each shape (n,) (other keys, an ``.npz``'s ``events``, are not
        read).
    hello : firmware_protocol.Hello, optional
        The device's HELLO (its position scale is the sensor step when the scene gives none).

    Returns
    -------
    dict
        The keys of :data:`MEASURE_KEYS` that the measurement has (``k`` [N/m], ``b``
        [N s/m], ``k_unc``, ``b_unc``: the stated half-widths; or ``error`` / ``reason``),
        and ``rows``: ``n``.
    """
    rec = _Record(cols)
    try:
        m = identify_run(prep, rec, hello)
    except Exception as exc:          # a record too short to carry a measurement yet
        m = {"error": f"{type(exc).__name__}: {exc}"}
    out = {q: m[q] for q in MEASURE_KEYS if q in m}
    out["rows"] = rec.n
    return out


#: A driver's run (host-clocked) whose host missed its deadline in more than this share
#: of its ticks is not the THS the prediction describes: the device held older forces for
#: varying times (a late or stalled host), so its record does not state the felt pair.
LATE_SHARE_MAX = 0.02


def timing_verdict(measured: dict, res, link: dict, *, wall: bool = True,
                   workspace: tuple[float, float] | None = None) -> None:
    """Withdraw a driver's run's verdict when its timing or its link leaves the record
    outside the THS (in place): more than :data:`LATE_SHARE_MAX` of the ticks late by a
    period or more (``res.overruns``), or re-synchronisations whose frame errors may have
    taken the device out of its workspace. The verdict becomes ``not measurable`` with
    the reason; the fit stays in the record for who wants to see it.

    A re-synchronisation sets the board's count to the host's estimate of the angle, so
    the board's frame moves by that estimate's error, at most the transport's
    ``frame_bound`` summed over the run
    (:meth:`hapsim.drivers.resync.Resynchronising._frame_error_bound`). The host closes
    its loop in its own frame, and the law there does not depend on where that frame
    sits (a spring's rest moves with it, in the joint's real frame): the record is cut
    at each re-synchronisation (``seq`` skips), and each stretch is a free response of
    the same loop from its own initial state, so a frame's error does not enter the fit
    (issue 29: 80 lossy runs of a matching joint on the simulated clock, 0 to 4
    re-synchronisations, all within; 60 of a joint 30 % heavier, none within,
    ``tests/test_haply_lossy_verdict.py``). What it does move is the joint's real
    position: up to the summed bound from the host's readings, and a joint beyond its
    workspace (the run's position bound: its end stops, the hand's reach) is not the THS.
    Before, a fixed count (more than two) withdrew it whatever they cost.

    Parameters
    ----------
    measured : dict
        :func:`hapsim.pipeline.measure.identify_run`'s result.
    res : hapsim.host.loop_types.LoopResult
        The loop's counters (``overruns``, ``samples``).
    link : dict
        The driver transport's ``stats`` (``resyncs``, ``frame_bound`` [m or rad]; a
        transport without it: an unbounded frame).
    wall : bool
        The device kept its own time (not a lockstep run, where the host paces the device:
        lateness costs nothing and a re-synchronised board has not moved meanwhile).
    workspace : (float, float), optional
        The host's largest reading's magnitude and the run's position bound [m or rad];
        None: no workspace stated, the frame's errors not checked.
    """
    if not wall:
        return
    ticks = max(int(res.samples), 1)
    late = int(getattr(res, "overruns", 0) or 0)
    resyncs = int(link.get("resyncs", 0))
    why = []
    if late > LATE_SHARE_MAX * ticks:
        why.append(f"the host missed its deadline in {late} of {ticks} ticks "
                   f"({100.0 * late / ticks:.1f} % > {100 * LATE_SHARE_MAX:g} %): the device "
                   f"held older forces for varying times, so the record is not the THS; "
                   f"rerun on a quieter machine, at a lower rate, or with --lockstep")
    if resyncs and workspace is not None:
        bound = float(link.get("frame_bound", math.inf))
        reading, limit = (float(v) for v in workspace)
        if not reading + bound <= limit:
            why.append(f"the board was re-synchronised {resyncs} times, each setting its "
                       f"count to an estimate: the device may be {bound:.4g} from the host's "
                       f"readings (largest {reading:.4g}), beyond the workspace's {limit:.4g}")
    if not why or "k" not in measured:
        return
    measured["within"] = False
    measured["comparable"] = False
    measured["verdict"] = "not measurable: " + "; ".join(why)
