"""The felt matrices of a Falcon's records and their verdict against the stated
uncertainty (:func:`falcon_felt_verdict`), and the records themselves taken through the
emulated Falcon's packets (:func:`measure_felt_falcon`).

The records are the identification's: ``2n + 1`` of them (``n = 3``), the one from rest
first, the others from the hand's starts (:func:`hapsim.lockstep.excitation_starts` at
the amplitude ``a``: the handle displaced by ``a`` along each axis, then moving at
``a / (10 T)`` along each), each driven by the driver's loop
(:func:`hapsim.emulated.falcon_device.drive_falcon`); the records minus the one from rest
are free responses of the loop, fitted jointly by the n-D fit
(:func:`hapsim.analysis.pencil.fit_felt_nd`) and stated as the 2DIY's are
(:func:`hapsim.emulated.haply2_verdict.felt_verdict_of_runs`).

**The wire's term** of the stated uncertainty: the Falcon's packets carry each leg's
angle as a whole encoder count (:data:`hapsim.drivers.falcon.DEG_PER_TICK`, 6.35e-4 rad;
27-47 um at the handle of configs/delta_sphere.yaml) and each torque as a whole motor
command (:data:`hapsim.drivers.falcon.TORQUE_PER_COUNT`). Where a count's edge falls
relative to the motion is set by the encoder's zero, an unknown fraction of a count: the
wire's term is the spread of the run's own fit over draws of that phase
(:func:`hapsim.analysis.wire_rounding.rounding_term`: the predicted loop's records at the
run's starts with the counts and the motor commands rounding inside the loop, at uniform
phases, each refitted by the run's fit; :data:`hapsim.analysis.wire_rounding.
ROUNDING_MARGIN` times the largest change of each statement over
:data:`hapsim.analysis.wire_rounding.ROUNDING_DRAWS` draws), the rounding's observation
share and its loop gain both in it; a draw that loses a pair of the loop or renders a
noise pair leaves nothing stated. Before, the term was the first-order worst case over
the errors' box (:mod:`hapsim.analysis.wire_box`: every sign pattern of the roundings,
to first order up to ``sqrt(3 N)`` times the standard deviation of what rounding does),
which stated nothing at the Falcon's counts: on configs/falcon_spring.yaml at its largest
start (3.77 mm) 40 times the stiffness matrix's largest entry at the exact records and
1.1-1.5 at the wall-clock runs' records, where 400 draws of the rounding moved it at
most 0.093 (docs/dimensions.md, "The wire's rounding term"). The first-order figures
(:func:`quantiser_terms`: the worst case and Widrow & Kollar's ``q^2 / 12``) are
printed beside it, for comparison.

A fit that renders a pair nearer one of the loop's fast poles than any rendered pair
(a noise pair outranking a loop pair) states nothing either (the run's own records, as
each draw's: :func:`hapsim.analysis.wire_rounding.noise_pair`).

**Missing samples.** A reply that did not come (lost or mangled bytes; the engine held
the last reading) leaves its row out with the rows its stale force acted on: rows
``r0 - 1 .. r1 + d + 1`` of a run ``r0 .. r1`` of missing rows (:func:`falcon_usable_rows`,
the 2DIY's rule of :func:`hapsim.pipeline.haply2_host.usable_rows` for estimated rows).
Records so cut are not differenced against the record from rest (a difference would take
on that record's cuts as its own): each record, the one from rest too, is fitted on its
own stretches about the fitted equilibrium, every stretch jointly
(:func:`hapsim.analysis.pencil.fit_felt_nd`'s ``offset``; the wire's term
:func:`hapsim.analysis.felt_records.wire_terms_records`), its rows after its first cut
that lie farther from rest than the undisturbed records go left out
(:func:`hapsim.analysis.felt_records.within_excursion`), as the 2DIY's
(:mod:`hapsim.emulated.haply2_verdict`); too few rows left is "not measurable" with the
reason. A command at the int16 clamp in a row fitted is "not
measurable" too (the loop not the linear one).
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError, DeviceError

__all__ = ["measure_felt_falcon", "falcon_felt_verdict", "falcon_usable_rows",
           "quantiser_terms", "felt_feasibility", "COMMAND_CLAMP", "NOT_AT_REST_M"]

#: The record from rest's own motion [m] beyond which :func:`felt_feasibility` says the
#: scene is not at rest at its joints (a micrometre: a 25th of one of the Falcon's counts
#: at the handle; the shipped scenes' ten-digit rest positions drift 1e-10 m).
NOT_AT_REST_M = 1e-6
#: The largest motor command a packet carries (int16; :func:`hapsim.drivers.falcon.
#: torque_command` clamps there).
COMMAND_CLAMP = 32767


def falcon_usable_rows(joints, delay: int) -> np.ndarray:
    """The rows of a Falcon record in its undisturbed stretches (module notes).

    Parameters
    ----------
    joints : array_like, shape (N, 3)
        The legs' readings [rad], NaN where the reply was missing.
    delay : int >= 0
        The scene's delay ``d`` [periods].

    Returns
    -------
    ndarray of bool, shape (N,)
        False on rows ``r0 - 1 .. r1 + d + 1`` of each run ``r0 .. r1`` of missing rows.
    """
    miss = ~np.isfinite(np.asarray(joints, float)).all(axis=1)
    N = miss.size
    d = max(int(delay), 0)
    bad = np.zeros(N + 1, np.int64)
    edge = np.diff(np.concatenate(([0], miss.astype(np.int8), [0])))
    for r0, r1 in zip(np.flatnonzero(edge == 1), np.flatnonzero(edge == -1) - 1):
        a, b = max(r0 - 1, 0), min(r1 + d + 1, N - 1)
        bad[a] += 1
        bad[b + 1] -= 1
    return np.cumsum(bad[:N]) == 0


def falcon_felt_verdict(scene, runs, plan, amplitude: float, *, excluded=None,
                        progress=None) -> dict:
    """The felt matrices of a Falcon's ``2n + 1`` records and their verdict (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        The 3-D delta scene the host ran.
    runs : list of dict
        The records, the one from rest first: ``position`` (N, 3) [m] and ``joints``
        (N, 3) [rad] read (NaN where missing), ``commands`` (N, 3) sent [counts].
    plan : tuple
        :func:`hapsim.lockstep.identification_plan`'s ``(check, order, N)``.
    amplitude : float
        The hand's ``a`` [m].
    excluded : dict, optional
        :func:`hapsim.analysis.felt_matrices.felt_verdict`'s: statements the prediction
        before the run excluded (:func:`felt_feasibility`), never made here.
    progress : callable, optional
        ``progress(done, total)`` over the rounding's draws.

    Returns
    -------
    dict
        ``measured`` (the fit), ``predicted``, ``deviation``, ``bound`` (the
        linearisation bound at ``a``), ``wire`` (``felt_stiffness``, ``felt_damping``,
        ``directions``: the wire's relative terms; ``reading_bound_rad``,
        ``torque_bound_nm``: half a count and half a command count), ``verdict``,
        ``within``, ``uncertainty``, ``reason``, ``statements``, ``not_stated``
        (:func:`hapsim.analysis.felt_matrices.felt_verdict`), ``clamped`` (commands at
        the clamp in rows fitted), ``missing`` (rows missing over the records),
        ``fitted_rows`` (records cut at missing replies: per record, the one from rest
        first, the equations its own stretches gave the fit; None for whole records),
        ``quantum`` (one count at the handle over ``a``, ``|J(q0)| q / a`` [-]),
        ``excursion`` (the largest distance of a record's fitted rows from the operating
        point, the record from rest's included [m]: the linearisation bound's amplitude
        when above ``amplitude``).

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.pencil.fit_felt_nd` for whole records.
    """
    from hapsim.analysis.felt_matrices import (felt_deviation, felt_directions, felt_verdict,
                                               noise_pair_verdict)
    from hapsim.analysis.felt_records import window_rows, within_excursion, wire_terms_records
    from hapsim.analysis.linearisation import bound_at_records
    from hapsim.analysis.pencil import fit_felt_nd
    from hapsim.analysis.wire_rounding import (Rounding, exact_loop, noise_pair,
                                               rounding_applies, rounding_term,
                                               rounding_wire, stretch_loop)
    from hapsim.drivers.falcon import DEG_PER_TICK, TORQUE_PER_COUNT
    from hapsim.kinematics import device
    from hapsim.lockstep import wire_terms_nd
    chk, order, N = plan
    n = 3
    pos = [np.asarray(r["position"], float)[:N] for r in runs]
    rest = pos[0]
    ok = [falcon_usable_rows(np.asarray(r["joints"], float)[:N], scene.device.delay)
          for r in runs]
    missing = int(sum(np.count_nonzero(~np.isfinite(np.asarray(r["joints"], float)[:N])
                                       .all(axis=1)) for r in runs))
    usable = None if all(u.all() for u in ok) else [ok[0] & u for u in ok[1:]]
    # a missing row's position is NaN: the fit never reads it (cut), held at 0 here
    diffs = [np.where(np.isfinite(p - rest), p - rest, 0.0) for p in pos[1:]]
    q0 = np.asarray(scene.device.joints, float)
    kin = device("delta", scene.device.geometry)
    J = kin.jacobian(q0)
    x_eq = kin.forward(q0)
    # records cut at their missing replies: each record (the one from rest too) fitted
    # on its own stretches about the fitted equilibrium (module notes), its rows beyond
    # the undisturbed records' excursion after its first cut left out
    own = None
    if usable is not None:
        held = [np.where(np.isfinite(p), p, x_eq) for p in pos]
        own = within_excursion(scene, [p - x_eq for p in held], ok, amplitude)
    short = None
    try:
        if own is not None:
            fit = fit_felt_nd(held, scene.device.mass, scene.period, order, usable=own,
                              offset=True)
        else:
            fit = fit_felt_nd(diffs, scene.device.mass, scene.period, order)
    except ConfigError as exc:
        if usable is None:
            raise
        short = (f"the records cut at their missing replies leave too few undisturbed "
                 f"stretches of more than {order} rows for the fit ({exc})")
        usable, own, fit = None, None, None
    delta = math.radians(DEG_PER_TICK) / 2.0
    tq = TORQUE_PER_COUNT / 2.0
    # the bound at the motion the fitted rows reached: each record's own about the
    # operating point, the one from rest too (as the 2DIY's: a difference would cancel
    # or miss the record from rest's own motion, a scene not at rest at its joints
    # drifting in every record)
    bound, excursion = bound_at_records(scene, amplitude, held if own is not None else pos,
                                        chk.render.rendered_poles, origin=x_eq,
                                        usable=own)
    wire = {"felt_stiffness": math.inf, "felt_damping": math.inf,
            "reading_bound_rad": delta, "torque_bound_nm": tq}
    cmds = [np.asarray(r["commands"])[:N] for r in runs]
    fitted = own if own is not None else [np.ones(N, bool)] * len(runs)
    clamped = int(sum(np.count_nonzero((np.abs(c) >= COMMAND_CLAMP) & u[:, None])
                      for c, u in zip(cmds, fitted)))
    if fit is None:
        dev, v = None, {"verdict": "not measurable", "within": None, "uncertainty": None,
                        "statements": [], "not_stated": ["felt stiffness", "felt damping"],
                        "reason": short}
    else:
        dev = felt_deviation(fit, chk)
        # the rounding's term: the run's own fit over draws of the counts' and the
        # commands' phases, the quantisers in the predicted loop (module notes)
        rounding = Rounding(J, q0, 2.0 * delta, command=2.0 * tq)
        if own is not None:
            def refit(recs):
                return fit_felt_nd([x_eq + r for r in recs], scene.device.mass,
                                   scene.period, order, usable=own, offset=True)
        else:
            def refit(recs):
                return fit_felt_nd([r - recs[0] for r in recs[1:]], scene.device.mass,
                                   scene.period, order)
        base = None
        if own is not None:
            # the stretches between the cuts: the predicted loop's free responses that
            # fit them, rounded in the draws (hapsim.analysis.wire_rounding.stretch_loop)
            eq = fit.get("equilibrium")
            base = stretch_loop(scene, [p - x_eq for p in held], own, order,
                                exact_loop(scene, amplitude, N),
                                equilibrium=None if eq is None else eq - x_eq)
        if rounding_applies(N):
            term = rounding_term(scene, chk, rounding, amplitude, N, refit, exact=base,
                                 progress=progress)
            wire.update(rounding_wire(chk, term))
        else:
            # records shorter than the draws' margin was measured at: the rounding's
            # worst case over the errors' box (hapsim.analysis.wire_rounding.
            # ROUNDING_MIN_ROWS; hapsim.analysis.wire_box)
            term = None
            errors = [("reading", J, np.full(n, delta)),
                      ("force", np.linalg.inv(J).T, np.full(n, tq))]
            if own is not None:
                errors = [(kind, G, [np.where(u[:, None], np.broadcast_to(b, (N, n)), 0.0)
                                     for u in own]) for kind, G, b in errors]
                wire.update(wire_terms_records(scene, held, chk, order, errors, usable=own))
            else:
                wire.update(wire_terms_nd(scene, diffs, chk, order, errors, box=True))
        # the records' own fit rendering a noise pair: no felt matrices of the loop
        wire["noise_pair"] = bool(term is not None and noise_pair(fit, term["reference"]))
        v = felt_verdict(dev, bound, wire, estimated=0,
                         directions=felt_directions(fit, chk), excluded=excluded)
        if wire.get("noise_pair") and v["verdict"] != "not measurable":
            # (a verdict that states nothing keeps its own reason)
            v = noise_pair_verdict("the rounding")
        if usable is not None:
            v["reason"] += (f"; {missing} missing replies: the records cut there, each "
                            "fitted on its own undisturbed stretches about the fitted "
                            "equilibrium, every stretch jointly")
    if clamped:
        v = {"verdict": "not measurable", "within": None, "uncertainty": None,
             "statements": [], "not_stated": ["felt stiffness", "felt damping"],
             "reason": f"a motor command at the packets' clamp ({COMMAND_CLAMP} counts) in "
                       f"{clamped} rows fitted: the loop was not the linear one predicted"}
    return {"measured": fit, "predicted": chk, "deviation": dev, "bound": bound,
            "wire": wire, **v, "clamped": clamped, "missing": missing,
            "fitted_rows": (None if own is None
                            else [int(np.count_nonzero(window_rows(u, order))) for u in own]),
            "quantum": float(np.linalg.norm(J, 2)) * 2.0 * delta / amplitude,
            "excursion": excursion}


def measure_felt_falcon(scene, amplitude: float = 2e-4, *, plant=None, plan=None,
                        samples: int | None = None, max_step: int = 8,
                        faults=None, progress=None, encoder_offset=(0.0, 0.0, 0.0)) -> dict:
    """The felt matrices of a delta scene measured through the emulated Falcon's packets
    on its lockstep clock (named: deterministic), and their verdict (module notes).

    Each record: a :class:`hapsim.emulated.falcon_device.FalconDevice` loaded and homed,
    the hand's start (:meth:`~hapsim.emulated.falcon_device.FalconDevice.let_go`), then
    ``N`` packets of the driver's loop (:func:`hapsim.emulated.falcon_device.drive_falcon`).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D scene with a delta device (the host's).
    amplitude : float
        The hand's ``a`` [m]; the default 0.2 mm is 4-7 counts of configs/delta_sphere.yaml
        at the handle, its records reaching 0.4 mm, below its sphere's depth of 0.5 mm
        (the contact stays engaged).
    plant : hapsim.scene.SceneND, optional
        The scene whose device the emulated Falcon carries (default ``scene``): a device
        that is not the one the scene states (a test of the verdict).
    plan : tuple, optional
        :func:`hapsim.lockstep.identification_plan` of ``scene``, already computed.
    samples : int, optional
        Packets per record (default the plan's).
    max_step : int, optional
        The reply decoder's plausible step [counts]
        (:class:`hapsim.drivers.falcon.DevicePacketDecoder`; an encoder finer than the
        Falcon's scales it).
    faults : hapsim.emulated.driver_mock.ByteFaults, optional
        Byte faults on the records' packets, both ways (the homing clean): a reply lost
        is a missing sample, cut (module notes).
    progress : callable, optional
        :func:`falcon_felt_verdict`'s.
    encoder_offset : sequence of 3 float, optional
        The emulated encoders' index off nominal [counts]
        (:class:`hapsim.emulated.falcon_device.FalconDevice`'s: where the counts' edges
        fall along the motion).

    Returns
    -------
    dict
        :func:`falcon_felt_verdict`'s, and ``excursion_rad`` (the largest leg
        displacement from the operating point, the emulator's truth).

    Raises
    ------
    hapsim.errors.DeviceError
        The emulated Falcon did not home.
    """
    from hapsim.drivers.falcon import DevicePacketDecoder, LED_BLUE, LED_GREEN
    from hapsim.emulated.falcon_device import FalconDevice, drive_falcon, home, load_firmware
    from hapsim.lockstep import excitation_starts, identification_plan
    if plan is None:
        plan = identification_plan(scene, samples)
    chk, order, N = plan
    runs = []
    excursion = 0.0
    for x0, v0 in excitation_starts(3, amplitude, scene.period):
        dev = FalconDevice(plant if plant is not None else scene, clock="lockstep",
                           encoder_offset=encoder_offset)
        load_firmware(dev, b"\x00" * 16)
        dec = DevicePacketDecoder()
        home(dev.feed, LED_BLUE, decoder=dec)
        dev.let_go(x0, v0)
        # a fresh decoder: the hand's start is a jump from the homing's last counts (its
        # first reply taken unchecked, the steps after it checked)
        r = drive_falcon(dev.feed, scene, N, leds=LED_GREEN,
                         decoder=DevicePacketDecoder(max_step), faults=faults)
        if r["error"] is not None:          # (a record cut short measures nothing here)
            raise DeviceError(r["error"]["message"])
        runs.append(r)
        q = np.asarray(r["joints"], float)
        excursion = max(excursion, float(np.nanmax(np.abs(q - scene.device.joints))))
    out = falcon_felt_verdict(scene, runs, plan, amplitude, progress=progress)
    out["excursion_rad"] = excursion
    return out


def quantiser_terms(scene, amplitude: float, plan) -> dict:
    """The Falcon's quantisers' effect on the felt matrices to first order, about the
    exact records (:class:`hapsim.lockstep.LockstepND` from the hand's starts at
    ``amplitude``: what the fit would see with no rounding).

    Two figures, carried by the same loop responses (:func:`hapsim.lockstep.
    error_responses`) and fit sensitivities (:func:`hapsim.analysis.pencil.
    felt_sensitivity_nd`): the stated term's worst case (:func:`hapsim.lockstep.
    wire_terms_nd`: half a count per reading, half a command count per torque, whatever
    their signs and correlation), and Widrow & Kollar's standard deviation (each reading's
    and each command's rounding a white error of variance ``q^2 / 12``, Widrow & Kollar,
    *Quantization Noise*, 2008, Sec. 4.3 and 5.1: the variance of a felt entry is
    ``sum (s * H)^2 q^2 / 12``), for comparison only (module notes: not stated).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D delta scene.
    amplitude : float
        The hand's ``a`` [m].
    plan : tuple
        :func:`hapsim.lockstep.identification_plan`'s ``(check, order, N)``.

    Returns
    -------
    dict
        ``worst`` (:func:`hapsim.lockstep.wire_terms_nd`'s, both quantisers),
        ``worst_reading`` and ``worst_command`` (each quantiser alone: ``felt_stiffness``,
        ``felt_damping`` [-]), ``widrow_kollar`` (``felt_stiffness``, ``felt_damping``:
        the largest entry's standard deviation over the predicted matrix's largest entry
        [-]), ``fit_exact`` (:func:`hapsim.analysis.felt_matrices.felt_deviation` of the
        exact records' fit), ``excursion`` (the exact records' largest distance from the
        rest record [m]). Every figure inf when the exact records give no sensitivity.
    """
    from hapsim.analysis.felt_matrices import felt_deviation
    from hapsim.analysis.fftconv import fftconvolve
    from hapsim.analysis.pencil import felt_sensitivity_nd, fit_felt_nd
    from hapsim.drivers.falcon import DEG_PER_TICK, TORQUE_PER_COUNT
    from hapsim.kinematics import device
    from hapsim.lockstep import error_responses, exact_differences, wire_terms_nd
    chk, order, N = plan
    diffs = exact_differences(scene, amplitude, N)
    J = device("delta", scene.device.geometry).jacobian(np.asarray(scene.device.joints))
    G = [("reading", J, math.radians(DEG_PER_TICK)),
         ("force", np.linalg.inv(J).T, TORQUE_PER_COUNT)]
    keys = ("felt_stiffness", "felt_damping")
    # the loop's responses and the fit's sensitivity at the records, once for every
    # figure below (each the same call on the same records)
    resp = error_responses(scene, N)
    sens = felt_sensitivity_nd(diffs, scene.device.mass, scene.period, order)
    each = [wire_terms_nd(scene, diffs, chk, order, [(k, g, np.full(3, c / 2.0))],
                          responses=resp, sensitivity=sens)
            for k, g, c in G]
    out = {"worst": {k: each[0][k] + each[1][k] for k in keys},
           "worst_reading": {k: each[0][k] for k in keys},
           "worst_command": {k: each[1][k] for k in keys},
           "widrow_kollar": {k: math.inf for k in keys},
           "excursion": float(max(np.max(np.linalg.norm(d_, axis=1)) for d_ in diffs))}
    fit = fit_felt_nd(diffs, scene.device.mass, scene.period, order)
    out["fit_exact"] = felt_deviation(fit, chk)
    if sens is None:
        return out
    sens = list(sens) + [-sum(sens)]                 # the rest record's, in each
    resp = dict(zip(("reading", "force"), resp))
    var = 0.0
    for kind, g, c in G:
        H = resp[kind] @ g
        for s in sens:
            S = s.reshape(-1, N, 3)
            Su = np.zeros((S.shape[0], N, 3))
            for a in range(3):
                for j in range(3):
                    Su[:, :, j] += fftconvolve(S[:, ::-1, a], H[None, :, a, j],
                                               axes=1)[:, :N][:, ::-1]
            var = var + np.sum(Su ** 2, axis=(1, 2)) * c * c / 12.0
    sd = np.sqrt(var).reshape(2, 9)
    for i, k in enumerate(keys):
        out["widrow_kollar"][k] = float(sd[i].max()
                                        / np.abs(np.asarray(getattr(chk.render, k))).max())
    return out


def felt_feasibility(scene, plan=None, *, max_step: int = 8, progress=None) -> dict:
    """What a run can state of the felt matrices of a delta scene through the Falcon's
    counts, predicted before it: the run's own records and statement
    (:func:`measure_felt_falcon`: the emulated Falcon, its packets' whole counts and motor
    commands, :func:`falcon_felt_verdict`'s rounding term) taken in lockstep
    (named: the counts' and the commands' rounding alone, no host timing) at the largest
    excitation the scene's linear range allows, the start the run takes.

    The largest excitation ``a_max`` is :func:`hapsim.lockstep.largest_start`'s, the
    2DIY run's: :data:`hapsim.lockstep.START_MARGIN` of the start whose exact records'
    motion toward a contact's opening reaches its depth at rest (beyond it the contact
    opens, no linear estimate holds) or carries a leg beyond
    :data:`hapsim.drivers.falcon.ENVELOPE_RAD` (through ``J(q0)``'s smallest singular
    value), whichever is smaller, less what the record from rest's own drift takes of it
    (a scene not at rest at its joints; said in the reason beyond
    :data:`NOT_AT_REST_M`); the records' motion is linear in ``a`` to first order
    (8e-4 off from 0.1 to 0.2 mm on configs/delta_sphere.yaml). Before, the motion's
    norm against the shallowest depth: on configs/delta_sphere.yaml 0.24 mm where the
    motion toward the sphere's opening allows 0.55 mm.

    **Why the lockstep records.** The run's statement is a function of its records and
    of the predicted loop (its wire's term, :func:`hapsim.analysis.wire_rounding.
    rounding_term`, is drawn with a fixed seed), so the lockstep records give the
    lockstep run's statements exactly; a run on the Falcon's own clock takes the same
    records unless the host is late (its rows cut, fitted otherwise), and it never makes
    a statement excluded here (:func:`hapsim.pipeline.falcon_run.felt_statement` passes
    them on). Before, the prediction was the first-order term about the exact records
    (:func:`quantiser_terms`), which said "measurable" on configs/falcon_spring.yaml
    (0.19) where the run, over the errors' box, stated nothing; then the run's statement
    over the box, which stated nothing there either (1.3 and more on the stiffness,
    where 400 draws of the rounding's phase moved it at most 0.093). ~1 s of CPU on
    configs/falcon_spring.yaml (the records 0.4 s, the rounding's draws 1 s), with
    ``progress`` over the draws.

    The first-order figures about the exact records (:func:`quantiser_terms`: the worst
    case, Widrow & Kollar's, the excitation and the count their extrapolations would
    need) are kept beside it, for the reason's numbers only.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D delta scene.
    plan : tuple, optional
        :func:`hapsim.lockstep.identification_plan` of ``scene``.
    max_step : int, optional
        The reply decoder's plausible step [counts] (:func:`measure_felt_falcon`'s: an
        encoder finer than the Falcon's scales it).
    progress : callable, optional
        ``progress(done, total)`` over the rounding's draws.

    Returns
    -------
    dict
        ``verdict`` (``"not measurable"``: nothing can be stated; ``"measurable"``: the
        lockstep records state something), ``stated`` and ``not_stated`` (the
        statements' names), ``statement`` (None when every statement is made, else the
        sentence a run says before it starts), ``lockstep`` (the lockstep records'
        verdict: ``verdict``, ``wire`` relative terms, ``rounding``: the draws' figures,
        :func:`hapsim.analysis.wire_rounding.rounding_wire`), ``reason`` (str,
        with the numbers), ``amplitude_m`` (``a_max``), ``limited_by`` (a contact's depth
        or the envelope), ``count_at_handle_m`` (one count through ``J(q0)``: its
        smallest and largest singular values times the count [m]), ``worst``,
        ``worst_reading``, ``worst_command``, ``widrow_kollar`` (:func:`quantiser_terms`
        at ``a_max``), ``limit``, ``needed_amplitude_m`` and ``needed_count_rad`` (their
        first-order extrapolations to the limit, the least that could do). A contact
        open at rest, or a scene not at rest at its joints whose drift alone reaches the
        margin (no start left): ``verdict`` ("not measurable"), ``stated``,
        ``not_stated``, ``statement``, ``reason``, ``amplitude_m`` (0), ``limited_by``
        and ``count_at_handle_m`` only.

    Raises
    ------
    hapsim.errors.DeviceError
        The emulated Falcon did not home (:func:`measure_felt_falcon`).
    """
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.drivers.falcon import DEG_PER_TICK, ENVELOPE_RAD
    from hapsim.kinematics import device
    from hapsim.lockstep import (START_MARGIN, exact_records, identification_plan,
                                 largest_start)
    if plan is None:
        plan = identification_plan(scene)
    J = device("delta", scene.device.geometry).jacobian(np.asarray(scene.device.joints))
    q = math.radians(DEG_PER_TICK)
    # the records' excursion is linear in ``a`` to first order (the loop linearised at
    # rest; measured on configs/delta_sphere.yaml: 8e-4 relative from 0.1 to 0.2 mm)
    a_ref = 1e-4
    recs = exact_records(scene, a_ref, plan[2])
    unit = max(float(np.max(np.linalg.norm(d_ - recs[0], axis=1)))
               for d_ in recs[1:]) / a_ref
    # the record from rest's own motion: a scene not at rest at its joints drifts in
    # every record, and largest_start leaves the start only what the drift leaves
    drift = float(np.max(np.linalg.norm(recs[0], axis=1)))
    col = np.linalg.svd(J, compute_uv=False)[::-1] * q      # a count along the axes of J
    every = ["felt stiffness", "felt damping"]

    def no_start(why: str, limited_by: str) -> dict:
        return {"verdict": "not measurable", "stated": [], "not_stated": every,
                "statement": _before_run(0.0, [], every, why), "amplitude_m": 0.0,
                "limited_by": limited_by,
                "count_at_handle_m": [float(col.min()), float(col.max())], "reason": why}
    # the largest start, the 2DIY run's rule (the motion toward each contact's opening,
    # the legs' envelope through J(q0)), on the records just taken: before, the motion's
    # norm against the shallowest depth, conservative along a contact's tangent
    a_max, lim, depth = largest_start(scene, plan[2], ENVELOPE_RAD, reference=a_ref,
                                      records=recs)
    if a_max <= 0.0 and depth <= 0.0:
        name = lim.split(" ", 1)[1]
        return no_start(f"the contact {name!r} is open at rest: no hand start keeps the "
                        "loop linear", f"contact {name!r}")
    by = (f"the legs' envelope of {ENVELOPE_RAD:g} rad" if lim == "envelope" else
          f"the depth {depth * 1e3:.2f} mm of the contact {lim.split(' ', 1)[1]!r} toward "
          "its opening")
    if a_max <= 0.0:
        # the record from rest's own drift reaches the margin (largest_start's notes)
        return no_start(f"the scene is not at rest at its joints: left alone from rest, "
                        f"the handle reaches {START_MARGIN:g} of {by}"
                        + (" at the handle" if lim == "envelope" else "")
                        + ", and no hand start is left", by)
    t = quantiser_terms(scene, a_max, plan)
    keys = ("felt_stiffness", "felt_damping")
    need_a = {k: a_max * t["worst"][k] / MEASURABLE_WIRE for k in keys}
    need_q = {k: q * MEASURABLE_WIRE / t["worst_reading"][k]
              if t["worst_reading"][k] > 0 else math.inf for k in keys}
    # the run's own records and statement, in lockstep (class notes)
    m = measure_felt_falcon(scene, a_max, plan=plan, max_step=max_step, progress=progress)
    stated = [st["name"] for st in m["statements"] if st["verdict"] != "not measurable"]
    not_stated = list(m["not_stated"])
    w = m["wire"]
    wk, wb = w["felt_stiffness"], w["felt_damping"]
    rd = w.get("rounding")
    said = (f"on the emulated Falcon's own records in lockstep at that start (what the run "
            f"fits), the counts' and commands' rounding may move the felt stiffness by "
            f"{wk:.2g} and the damping by {wb:.2g} (relative, {w.get('how', 'first order')}"
            + ("" if not rd else
               f"; the draws' largest {rd['largest']['felt_stiffness']:.2g} and "
               f"{rd['largest']['felt_damping']:.2g}, their median "
               f"{rd['median']['felt_stiffness']:.2g} and "
               f"{rd['median']['felt_damping']:.2g}") + ")")
    if rd and (rd["lost"] or rd["noise"]):
        said += (f"; in {rd['lost'] + rd['noise']} of {rd['draws']} draws of the rounding "
                 f"the fit lost a pair of the loop ({rd['lost']}) or rendered a noise pair "
                 f"({rd['noise']}): the records do not determine every rendered pair")
    reason = (f"one encoder count is {col.min() * 1e6:.0f}-{col.max() * 1e6:.0f} um at the "
              f"handle; the largest hand start the scene's linear range allows is "
              f"{a_max * 1e3:.2f} mm, about {a_max / col.mean():.0f} counts (the records "
              f"reach {unit:.2f} a; the start is {START_MARGIN:g} of the one at which they "
              f"reach {by}" + (f", less the record from rest's own drift of "
                               f"{drift * 1e3:.2g} mm: the scene is not at rest at its "
                               "joints" if drift > NOT_AT_REST_M else "")
              + f"); {said}, against the limit {MEASURABLE_WIRE:g} of a statement: "
              + (("stated: " + ", ".join(stated)
                  + ("; not stated: " + ", ".join(not_stated) if not_stated else ""))
                 if stated else "nothing stated")
              + f" (for comparison, the first-order worst case about the exact records "
              f"over every sign of the roundings: {t['worst']['felt_stiffness']:.3g} and "
              f"{t['worst']['felt_damping']:.3g}; Widrow & Kollar's standard deviation "
              f"{t['widrow_kollar']['felt_stiffness']:.2g} and "
              f"{t['widrow_kollar']['felt_damping']:.2g})")
    return {"verdict": "measurable" if stated else "not measurable", "reason": reason,
            "stated": stated, "not_stated": not_stated,
            "statement": _before_run(a_max, stated, not_stated, reason),
            "lockstep": {"verdict": m["verdict"],
                         "wire": {k: w[k] for k in ("felt_stiffness", "felt_damping",
                                                    "directions")},
                         "rounding": rd},
            "amplitude_m": a_max, "limited_by": by,
            "count_at_handle_m": [float(col.min()), float(col.max())],
            "worst": t["worst"], "worst_reading": t["worst_reading"],
            "worst_command": t["worst_command"], "widrow_kollar": t["widrow_kollar"],
            "limit": MEASURABLE_WIRE, "needed_amplitude_m": need_a,
            "needed_count_rad": need_q}


def _before_run(a: float, stated: list, not_stated: list, reason: str) -> str | None:
    """The sentence a run says before it starts (None: every statement will be made)."""
    from hapsim.analysis.felt_matrices import said_before_run
    return said_before_run(f"the emulated Falcon's records in lockstep at a = {a:g} m, the "
                           "counts' and the commands' rounding alone", stated, not_stated,
                           reason)
