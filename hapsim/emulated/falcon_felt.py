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
command (:data:`hapsim.drivers.falcon.TORQUE_PER_COUNT`). A reading is therefore the
angle to within half a count, a torque the one computed to within half a command count;
each error enters the records through the loop (the reading error through ``J(q0)``, the
torque error through ``J(q0)^-T``: :func:`hapsim.lockstep.error_responses`) and the fit
to first order, and their worst case whatever their signs and correlation, taken over
the errors' box (at the records and at each statement's worst errors within the bounds,
the largest times a margin: :mod:`hapsim.analysis.wire_box`), is the wire's term
(:func:`hapsim.lockstep.wire_terms_nd` with ``box=True``; records cut at missing replies:
:func:`hapsim.analysis.felt_records.wire_terms_records`), as for the 2DIY. The
first-order term at the records alone is no bound here: on configs/falcon_spring.yaml at
its largest start (3.77 mm, the exact records in lockstep) errors within half a count and
half a motor command, each statement's worst signs re-linearised at the records they
moved, moved the stiffness along the heaviest principal direction 2.2 times its
first-order term (0.22 against 0.10, a term that stated it) and one stiffness entry's fit
collapsed (1,800 times; tests/test_wire_box_devices.py). Over the box nothing is stated
on that scene at the Falcon's counts; an encoder 10 times finer states the stiffness.
A rounding of a smooth signal a few counts wide is not white noise, so no statistical
interval is taken for it (Widrow & Kollar's ``q^2 / 12`` per reading is printed beside
it by tools/falcon_felt_figures.py, for comparison only).

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

from hapsim.errors import ConfigError

__all__ = ["measure_felt_falcon", "falcon_felt_verdict", "falcon_usable_rows",
           "quantiser_terms", "felt_feasibility", "COMMAND_CLAMP", "EXCURSION_MARGIN"]

#: The largest motor command a packet carries (int16; :func:`hapsim.drivers.falcon.
#: torque_command` clamps there).
COMMAND_CLAMP = 32767
#: The largest excitation :func:`felt_feasibility` takes is this fraction of the one whose
#: exact records reach the shallowest contact's depth or the legs' envelope (the records'
#: excursion is linear in ``a``; the margin leaves the velocity starts' overshoot and the
#: second-order terms 10 %).
EXCURSION_MARGIN = 0.9


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


def falcon_felt_verdict(scene, runs, plan, amplitude: float) -> dict:
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
        ``excursion`` (the largest distance of a record from the rest record [m]).

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.pencil.fit_felt_nd` for whole records.
    """
    from hapsim.analysis.felt_matrices import felt_deviation, felt_directions, felt_verdict
    from hapsim.analysis.felt_records import window_rows, wire_terms_records, within_excursion
    from hapsim.analysis.linearisation import linearisation_bound
    from hapsim.analysis.pencil import fit_felt_nd
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
    excursion = float(max(np.nanmax(np.linalg.norm(d_, axis=1)) for d_ in diffs))
    bound = linearisation_bound(scene, amplitude, chk.render.rendered_poles)
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
        errors = [("reading", J, np.full(n, delta)),
                  ("force", np.linalg.inv(J).T, np.full(n, tq))]
        if own is not None:
            # a row no stretch holds changes only the initial state of the stretches
            # after it (a free response the fit does not see to first order): its errors
            # are left out, each record's own rows kept (hapsim.emulated.haply2_verdict)
            errors = [(kind, G, [np.where(u[:, None], np.broadcast_to(b, (N, n)), 0.0)
                                 for u in own]) for kind, G, b in errors]
            wire.update(wire_terms_records(scene, held, chk, order, errors, usable=own))
        else:
            # over the error box (hapsim.analysis.wire_box; module notes): the
            # first-order term at the records alone was exceeded 2.7 times by errors
            # within the counts' bounds on configs/falcon_spring.yaml
            wire.update(wire_terms_nd(scene, diffs, chk, order, errors, box=True))
        v = felt_verdict(dev, bound, wire, estimated=0,
                         directions=felt_directions(fit, chk))
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
                        faults=None) -> dict:
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
        dev = FalconDevice(plant if plant is not None else scene, clock="lockstep")
        load_firmware(dev, b"\x00" * 16)
        dec = DevicePacketDecoder()
        home(dev.feed, LED_BLUE, decoder=dec)
        dev.let_go(x0, v0)
        # a fresh decoder: the hand's start is a jump from the homing's last counts (its
        # first reply taken unchecked, the steps after it checked)
        r = drive_falcon(dev.feed, scene, N, leds=LED_GREEN, decoder=DevicePacketDecoder(max_step), faults=faults)
        runs.append(r)
        q = np.asarray(r["joints"], float)
        excursion = max(excursion, float(np.nanmax(np.abs(q - scene.device.joints))))
    out = falcon_felt_verdict(scene, runs, plan, amplitude)
    out["excursion_rad"] = excursion
    return out


def _exact_differences(scene, amplitude: float, N: int) -> list:
    """The exact records (:class:`hapsim.lockstep.LockstepND`, no rounding) from the
    hand's starts at ``amplitude``, minus the one from rest: 2n arrays (N, n) [m]."""
    from hapsim.lockstep import LockstepND, excitation_starts
    recs = [LockstepND(scene, x0=x0, v0=v0).step(N, record=True)
            for x0, v0 in excitation_starts(scene.dimension, amplitude, scene.period)]
    return [r - recs[0] for r in recs[1:]]


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
    from hapsim.lockstep import error_responses, wire_terms_nd
    chk, order, N = plan
    diffs = _exact_differences(scene, amplitude, N)
    J = device("delta", scene.device.geometry).jacobian(np.asarray(scene.device.joints))
    G = [("reading", J, math.radians(DEG_PER_TICK)),
         ("force", np.linalg.inv(J).T, TORQUE_PER_COUNT)]
    keys = ("felt_stiffness", "felt_damping")
    each = [wire_terms_nd(scene, diffs, chk, order, [(k, g, np.full(3, c / 2.0))])
            for k, g, c in G]
    out = {"worst": {k: each[0][k] + each[1][k] for k in keys},
           "worst_reading": {k: each[0][k] for k in keys},
           "worst_command": {k: each[1][k] for k in keys},
           "widrow_kollar": {k: math.inf for k in keys},
           "excursion": float(max(np.max(np.linalg.norm(d_, axis=1)) for d_ in diffs))}
    fit = fit_felt_nd(diffs, scene.device.mass, scene.period, order)
    out["fit_exact"] = felt_deviation(fit, chk)
    sens = felt_sensitivity_nd(diffs, scene.device.mass, scene.period, order)
    if sens is None:
        return out
    sens = list(sens) + [-sum(sens)]                 # the rest record's, in each
    resp = dict(zip(("reading", "force"), error_responses(scene, N)))
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


def felt_feasibility(scene, plan=None) -> dict:
    """Whether the felt matrices of a delta scene can be measured through the Falcon's
    counts at all: the readings' and commands' rounding (:func:`quantiser_terms`) at the
    largest excitation the scene's linear range allows, against the limit of a statement
    (:data:`hapsim.analysis.felt_matrices.MEASURABLE_WIRE`).

    The largest excitation ``a_max`` is :data:`EXCURSION_MARGIN` times the one whose exact
    records reach the shallowest contact's depth at rest
    (:func:`hapsim.analysis.linearisation.linearisation_bound`: beyond it the contact
    opens, no linear estimate holds) or carry a leg beyond
    :data:`hapsim.drivers.falcon.ENVELOPE_RAD` (through ``J(q0)``'s smallest singular
    value), whichever is smaller; the records' excursion is linear in ``a`` to first
    order (8e-4 off from 0.1 to 0.2 mm on configs/delta_sphere.yaml). The figures are
    computed at ``a_max`` itself; the excitation and the count that would bring them to
    the limit are their first-order extrapolations (the wire's term inverse in ``a``,
    linear in the count: measured 1.5 % off from 0.1 to 0.2 mm on the sphere, the
    contact's curvature; below ~10 um the exact records' round-off moves the
    sensitivities of the poorly excited modes by tens of per cent).

    Why first order here, when the run's statement takes the wire's term over the
    errors' box (:func:`falcon_felt_verdict`): this is no verdict on the felt matrices,
    only whether a run could state them, and the first-order term at the records is
    never above the box's (the box's supremum is sampled at the records among its
    points, times a margin of at least 1: :func:`hapsim.analysis.wire_box.box_worst_case`).
    So "not measurable" here is certain, the box's term being beyond the limit too, and
    "measurable" means only that the run is not excluded: its records' term over the box
    then decides what is stated (on configs/falcon_spring.yaml, "measurable" at first
    order, 0.19, the box's term at the same exact records is 240 and the run states
    nothing). Likewise the excitation and the count the extrapolations give are the least
    that could do, never enough by themselves. The box's term is not extrapolated: it is
    not linear in the count or the excitation (its sampled points leave the fit's linear
    region), and at ~5 s of CPU per evaluation on a 3-D loop a run does not search for it.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D delta scene.
    plan : tuple, optional
        :func:`hapsim.lockstep.identification_plan` of ``scene``.

    Returns
    -------
    dict
        ``verdict`` (``"not measurable"``, or ``"measurable"``: the stiffness at least
        could be stated), ``reason`` (str, with the numbers), ``amplitude_m``
        (``a_max``), ``limited_by`` (what limits it: a contact's depth or the envelope),
        ``count_at_handle_m`` (one count through ``J(q0)``: its smallest and largest
        singular values times the count [m]),
        ``worst``, ``worst_reading``, ``worst_command``, ``widrow_kollar`` (at ``a_max``,
        :func:`quantiser_terms`), ``limit``, ``needed_amplitude_m`` and
        ``needed_count_rad`` (each for the stiffness and the damping: the excitation, or
        the count, whose worst case is the limit). A contact open at rest: only
        ``verdict`` ("not measurable"), ``reason``, ``amplitude_m`` (0), ``limited_by``
        and ``count_at_handle_m``.
    """
    from hapsim.analysis.felt_matrices import MEASURABLE_WIRE
    from hapsim.analysis.linearisation import linearisation_bound
    from hapsim.drivers.falcon import DEG_PER_TICK, ENVELOPE_RAD
    from hapsim.kinematics import device
    from hapsim.lockstep import identification_plan
    if plan is None:
        plan = identification_plan(scene)
    chk = plan[0]
    J = device("delta", scene.device.geometry).jacobian(np.asarray(scene.device.joints))
    q = math.radians(DEG_PER_TICK)
    # the records' excursion is linear in ``a`` to first order (the loop linearised at
    # rest; measured on configs/delta_sphere.yaml: 8e-4 relative from 0.1 to 0.2 mm)
    a_ref = 1e-4
    unit = max(float(np.max(np.linalg.norm(d_, axis=1)))
               for d_ in _exact_differences(scene, a_ref, plan[2])) / a_ref
    bound = linearisation_bound(scene, 1e-9, chk.render.rendered_poles)
    depth = float(bound.depth)
    env = ENVELOPE_RAD * float(np.linalg.svd(J, compute_uv=False)[-1])
    col = np.linalg.svd(J, compute_uv=False)[::-1] * q      # a count along the axes of J
    if depth <= 0.0:
        return {"verdict": "not measurable", "amplitude_m": 0.0,
                "limited_by": f"contact {bound.depth_name!r}",
                "count_at_handle_m": [float(col.min()), float(col.max())],
                "reason": f"the contact {bound.depth_name!r} is open at rest: no hand start "
                          "keeps the loop linear"}
    if depth < env:
        a_max = EXCURSION_MARGIN * depth / unit
        by = f"the depth {depth * 1e3:.2f} mm of the contact {bound.depth_name!r}"
    else:
        a_max = EXCURSION_MARGIN * env / unit
        by = f"the legs' envelope of {ENVELOPE_RAD:g} rad"
    t = quantiser_terms(scene, a_max, plan)
    keys = ("felt_stiffness", "felt_damping")
    need_a = {k: a_max * t["worst"][k] / MEASURABLE_WIRE for k in keys}
    need_q = {k: q * MEASURABLE_WIRE / t["worst_reading"][k]
              if t["worst_reading"][k] > 0 else math.inf for k in keys}
    ok = t["worst"]["felt_stiffness"] <= MEASURABLE_WIRE
    wk, wb = t["worst"]["felt_stiffness"], t["worst"]["felt_damping"]
    reason = (f"one encoder count is {col.min() * 1e6:.0f}-{col.max() * 1e6:.0f} um at the "
              f"handle; the largest hand start the scene's linear range allows is "
              f"{a_max * 1e3:.2f} mm, about {a_max / col.mean():.0f} counts (the records "
              f"reach {unit:.2f} a: {EXCURSION_MARGIN:g} of the start at which they reach "
              f"{by}); there the "
              f"readings' and commands' rounding alone may move the felt stiffness by "
              f"{wk:.3g} and the damping by {wb:.3g} (relative, first-order worst case, "
              f"the least the run's term over the errors' bounds can be; "
              f"Widrow & Kollar's standard deviation {t['widrow_kollar']['felt_stiffness']:.2g}"
              f" and {t['widrow_kollar']['felt_damping']:.2g}), against the limit "
              f"{MEASURABLE_WIRE:g} of a statement: a count "
              f"{q / need_q['felt_stiffness']:.3g} times finer (or a start of "
              f"{need_a['felt_stiffness'] * 1e3:.3g} mm) would be needed for the stiffness, "
              f"{q / need_q['felt_damping']:.3g} times finer for the damping")
    return {"verdict": "measurable" if ok else "not measurable", "reason": reason,
            "amplitude_m": a_max, "limited_by": by,
            "count_at_handle_m": [float(col.min()), float(col.max())],
            "worst": t["worst"], "worst_reading": t["worst_reading"],
            "worst_command": t["worst_command"], "widrow_kollar": t["widrow_kollar"],
            "limit": MEASURABLE_WIRE, "needed_amplitude_m": need_a,
            "needed_count_rad": need_q}
