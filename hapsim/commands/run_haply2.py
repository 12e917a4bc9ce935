"""``hapsim run SCENE --driver haply`` on a 2-D pantograph scene: the felt matrices through
the Haply 2DIY's bytes and its emulated board, in lockstep or in real time (the board in a
child process behind a pty, the host loop on its own clock)."""

from __future__ import annotations

import json
import math
import sys

from hapsim.braking import brake_text
from hapsim.pipeline.felt_run import print_statements, scene_for_run
from hapsim.errors import ConfigError

__all__ = ["run_haply2_command", "prediction_haply2", "designed_start", "HAPLY_AMPLITUDE",
           "HAPLY_CPR"]


#: The smallest amplitude ``--driver haply`` takes by default [m]: the binary32 angles
#: on the wire resolve ~1e-7 m at the handle, so 1e-4 m keeps them below 1e-3 of it. The
#: default is the largest start the scene's linear range allows
#: (:func:`hapsim.lockstep.largest_start`), never below this.
HAPLY_AMPLITUDE = 1e-4
#: The emulated encoders' counts per revolution under ``--driver haply --lockstep``: a
#: fine encoder, so that the run checks the wire and the loop (a real 2DIY's 10752 or 4880
#: counts are tens of micrometres at the handle; the report states what they would be).
HAPLY_CPR = 2.0 ** 22


def run_haply2_command(args) -> int:
    """``hapsim run SCENE --driver haply [--lockstep]``: the felt matrices through the
    2DIY's bytes and its emulated board, in lockstep
    (:func:`hapsim.emulated.haply2_lockstep.measure_felt_haply2`) or in real time, the board in
    a child process behind a pty and the host on its clock, missing replies estimated
    samples (:func:`hapsim.pipeline.haply2_host.measure_felt_haply2_port`).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``port`` (must be None), ``lockstep``, ``generation`` (``"gen2"`` or
        ``"gen3"``, default gen3), ``amplitude`` [m] (None: the designed start),
        ``rate_hz`` [Hz], ``rt_priority``, ``json``.

    Returns
    -------
    int
        0 (the measurement and its verdict reported, whatever it finds: "within",
        "differs" or "not measurable"); 1 when the joints left the envelope in a real-time
        record (braked, then zero torque: a safety stop, as every run's, reported first),
        or when the board was lost after the first record
        (the records made reported, "stopped: device lost: ...", then the error on
        stderr; ``--json``: one object with ``stop`` and ``error``).

    Raises
    ------
    ConfigError
        With ``--port`` (a real board has no hand to start each record), a scene that is
        not a 2-D pantograph, a bad amplitude.
    DeviceError
        The board lost before its first record (its port failed, a reply lost): exit 1,
        cli's error line and ``--json`` error object.
    """
    import gc

    from hapsim.emulated.haply2_lockstep import measure_felt_haply2
    from hapsim.progress import Progress
    if args.port:
        raise ConfigError("--driver haply on a 2-D scene runs against the emulated board, "
                          "whose hand starts each record (a real 2DIY has none): no --port",
                          key="--port")
    realtime = not args.lockstep
    gen = getattr(args, "generation", None) or "gen3"
    a, scene = scene_for_run(args.scene, getattr(args, "amplitude", None),
                             getattr(args, "rate_hz", None), HAPLY_AMPLITUDE)
    designed = None
    if getattr(args, "amplitude", None) is None:
        a, designed = designed_start(scene)
    excluded = said = None
    if realtime:
        # before the loop: what the emulated board's counts and binary32 let this run
        # state (the same records in lockstep, the board on its lockstep clock, asked
        # for by name; ~1.5 s of CPU): what will not be stated is said first, and the
        # real-time records (cut, estimated) never state it
        with Progress(5, "run (2DIY bytes: what its records can state, in lockstep)",
                      unit="records") as bar:
            pre = measure_felt_haply2(scene, gen, amplitude=a, cpr=HAPLY_CPR,
                                      progress=bar.update)
        excluded, said = prediction_haply2(pre, a)
        if said is not None:
            print(f"hapsim run: {scene.path}: {said}; the run goes on (exit code 0: not a "
                  "device fault)", file=sys.stderr, flush=True)
    # a board lost (its port failing) before the first record raises DeviceError: exit 1
    # with cli's error line and, with --json, its error object; after it, the records
    # made are reported, then the error (exit 1)
    with Progress(5, "run (2DIY bytes, " + ("real time)" if realtime else "lockstep)"),
                  unit="records") as bar:
        if realtime:
            from hapsim.pipeline.haply2_embedded import Embedded2DIY
            from hapsim.pipeline.haply2_host import measure_felt_haply2_port
            from hapsim.host.realtime import RealtimePriority
            prio = max(int(getattr(args, "rt_priority", 0) or 0), 0)
            # the board takes SCHED_FIFO itself once started (a real board's MCU is
            # never descheduled), the host loop here: as the 1-D run's loop and mock
            child = Embedded2DIY(args.scene, gen, amplitude=a, cpr=HAPLY_CPR,
                                 rate_hz=scene.rate_hz, rt_priority=prio)
            gc_was = gc.isenabled()
            rt = RealtimePriority(prio)
            try:
                gc.disable()                 # no collection while the clock runs
                # the emulated board advances one period per write unless it
                # says it keeps the wall clock: a host stall costs its record
                # nothing then
                with rt:
                    res = measure_felt_haply2_port(
                        child.port, scene, gen, amplitude=a, resolution=HAPLY_CPR,
                        progress=bar.update,
                        lockstep_board=getattr(child, "clock", "lockstep") == "lockstep",
                        excluded=excluded)
                res["scheduling"] = rt.note
            finally:
                if gc_was:
                    gc.enable()
                child.close()
        else:
            res = measure_felt_haply2(scene, gen, amplitude=a, cpr=HAPLY_CPR,
                                      progress=bar.update)
    from hapsim.api.common import matrix_list as mat
    from hapsim.outputs import finite_or_none as num
    chk = res["predicted"]
    if res.get("error") is not None:
        return _report_lost(args, scene, res, gen, a, designed, said, excluded)
    fit, dev = res["measured"], res["deviation"]
    bound, wire = res["bound"], res["wire"]
    real = res["quantum_encoders"]
    # the joints out of the envelope in a record (braked, then zero torque): a safety
    # stop, exit 1 after the report, as every run's
    code = 1 if realtime and any(v >= 0 for v in res["left"]) else 0
    if args.json:
        print(json.dumps({
            "scene": scene.path, "dof": 2, "driver": "haply", "generation": gen,
            "lockstep": not realtime, "rate_hz": scene.rate_hz, "amplitude": a,
            "amplitude_limited_by": designed,
            "emulated_cpr": HAPLY_CPR,
            **(_realtime_json(res) if realtime else {}),
            "direction_probe": res.get("direction_probe"),
            "predicted": {"felt_stiffness": mat(chk.render.felt_stiffness),
                          "felt_damping": mat(chk.render.felt_damping)},
            "measured": {"felt_stiffness": mat(fit["felt_stiffness"]),
                         "felt_damping": mat(fit["felt_damping"]),
                         "residual": fit["residual"], "rank": fit["rank"]},
            "deviation": dev, "linearisation_bound": bound.to_dict(),
            "wire": {"felt_stiffness": num(wire["felt_stiffness"]),
                     "felt_damping": num(wire["felt_damping"]),
                     "reading_bound_rad": wire["reading_bound_rad"],
                     "torque_rel": wire["torque_rel"],
                     # the same terms at the records alone, first order, where the
                     # box was sampled (hapsim.analysis.wire_box: the errors that are
                     # no rounding); the rounding's by draws of its phase
                     # (hapsim.analysis.wire_rounding): how the term was taken and the
                     # draws' figures
                     "first_order": None if not wire.get("first_order") else {
                         q: num(wire["first_order"][q])
                         for q in ("felt_stiffness", "felt_damping")},
                     "how": wire.get("how"),
                     "rounding": None if not wire.get("rounding") else {
                         k: wire["rounding"][k] for k in ("draws", "lost", "noise",
                                                          "margin")},
                     # the host's write timing on a board on its own clock: the largest
                     # hold's departure from a period, corrected (None: exact periods)
                     "hold_s": wire.get("hold_s")},
            "link_uncertainty": res.get("link_uncertainty"),
            "uncertainty": res["uncertainty"], "statements": res["statements"],
            "not_stated": res["not_stated"], "verdict": res["verdict"],
            "within": res["within"], "reason": res["reason"], "clamped": res["clamped"],
            "quantum": res["quantum"], "quantum_real_encoders": real,
            "records": res["records"], "samples": res["samples"],
            **({"stated_before_run": said, "not_stated_before_run": list(excluded)}
               if said is not None else {})}))
        return code
    o = sys.stdout
    _print_head(scene, res, gen, realtime, o)
    print(f"  excitation: {res['records']} free responses of {res['samples']} writes, "
          f"a = {a:.3g} m (minus the response from rest"
          + ("" if designed is None else f"; the largest start the scene's linear range "
             f"allows, limited by {_limit_text(designed)}") + ")", file=o)
    for name, m in (("predicted felt stiffness k [N/m]", chk.render.felt_stiffness),
                    ("measured felt stiffness k [N/m]", fit["felt_stiffness"]),
                    ("predicted felt damping b [N s/m]", chk.render.felt_damping),
                    ("measured felt damping b [N s/m]", fit["felt_damping"])):
        print(f"  {name}", file=o)
        for row in ([] if m is None else m):
            print("    " + "  ".join(f"{v:+14.8g}" for v in row), file=o)
    bd = bound.to_dict()
    if dev is not None:
        print(f"  measured - predicted (largest entry over the largest predicted): "
              f"k {dev['felt_stiffness']:.2e}, b {dev['felt_damping']:.2e}", file=o)
    if bd["felt_stiffness"] is not None:
        print(f"  linearisation bound at the records' largest excursion "
              f"{bound.amplitude:.3g} m (never below a: the hand's moving starts go past "
              f"it): k "
              f"{bd['felt_stiffness']:.2e}, "
              f"b {bd['felt_damping']:.2e}", file=o)
    if math.isfinite(wire["felt_stiffness"]):
        dq = wire["reading_bound_rad"]
        print(f"  the wire's rounding (readings within {dq[0]:.2e} / {dq[1]:.2e} rad: half "
              "a count and a binary32 ulp; torques 2^-24)"
              + (" and the estimated samples' error bounds" if realtime
                 and sum(res["estimated"]) else "")
              + f", first-order worst case through the loop and the fit: k "
              f"{wire['felt_stiffness']:.2e}, "
              f"b {wire['felt_damping']:.2e}", file=o)
    if wire.get("hold_s") is not None:
        print(f"  the host's write timing (the board on its own clock): holds up to "
              f"{wire['hold_s'] * 1e6:.0f} us off a period, corrected from the host's "
              "write times; what the correction leaves is in the wire's term above",
              file=o)
    print_statements(res, o)
    if said is not None:
        print(f"  stated before the run: {said}", file=o)
    print(f"  verdict: {res['verdict']}: {res['reason']}", file=o)
    print(f"  one reading step at the handle over a: {res['quantum']:.2e} (one count of the "
          f"emulated encoders or a binary32 ulp, the larger); a real 2DIY's encoders: gen2 "
          f"{real['gen2']:.2e}, gen3 {real['gen3']:.2e} of a", file=o)
    return code


def _realtime_json(res: dict) -> dict:
    """A real-time run's own entries of ``--json``: per record, what the host's loop
    counted, its watchdog and scheduling, the tick the joints left the envelope (-1:
    none) and the braking after it (:mod:`hapsim.braking`; None: none)."""
    return {k: res.get(k) for k in ("estimated", "late_ticks", "replies", "writes",
                                    "resyncs", "skipped", "watchdog", "scheduling",
                                    "left", "brake")}


def _print_head(scene, res: dict, gen: str, realtime: bool, o) -> None:
    """The report's first lines: the run, and in real time what the host's loop counted
    per record, its watchdog's writes and each braking."""
    print(f"{scene.path}: the Haply 2DIY's bytes ({gen} set-up, firmware V1.5 board "
          f"emulated, encoders of {HAPLY_CPR:.0f} counts/rev), "
          + ("in real time (the board in a child process behind a pty)" if realtime
             else "in lockstep"), file=o)
    if not realtime:
        return
    print(f"  estimated samples (replies not read by their tick) per record: "
          f"{res['estimated']}; ticks the host began a period late: "
          f"{res['late_ticks']}; replies read {res['replies']} of {res['writes']}; "
          f"host loop scheduling: {res.get('scheduling')}", file=o)
    wd = res.get("watchdog")
    if wd is not None:
        # the host's watchdog (the board has none), as the 1-DoF report words it; its
        # robust writes each followed by the host's re-arming, the record cut there
        from hapsim.drivers.torque_watchdog import watchdog_text
        again = sum(wd.get("resyncs") or ())
        print("  " + watchdog_text(wd, "the zero command")
              + (f"; the host re-armed the board after {again} of them (records cut "
                 "there)" if again else ""), file=o)
    for j, bk in enumerate(res["brake"]):
        if bk:
            print(f"  record {j + 1}, the joints out of the envelope at tick "
                  f"{res['left'][j]}: " + brake_text(bk, "N m s/rad", "rad/s"), file=o)


def _report_lost(args, scene, res: dict, gen: str, a: float, designed, said,
                 excluded) -> int:
    """Report a real-time run whose board was lost after its first record
    (:func:`hapsim.pipeline.haply2_host.measure_felt_haply2_port`'s ``error``): what the
    records made counted, the prediction, "not measurable" and why, text or one
    ``--json`` object with ``stop`` and ``error``; then the error on stderr. Returns 1."""
    from hapsim.api.common import matrix_list as mat
    chk = res["predicted"]
    if args.json:
        print(json.dumps({
            "scene": scene.path, "dof": 2, "driver": "haply", "generation": gen,
            "lockstep": False, "rate_hz": scene.rate_hz, "amplitude": a,
            "amplitude_limited_by": designed, "emulated_cpr": HAPLY_CPR,
            **_realtime_json(res), "direction_probe": res.get("direction_probe"),
            "predicted": {"felt_stiffness": mat(chk.render.felt_stiffness),
                          "felt_damping": mat(chk.render.felt_damping)},
            "measured": None, "statements": [], "not_stated": res["not_stated"],
            "verdict": res["verdict"], "within": None, "reason": res["reason"],
            "records": res["records"], "stop": res["stop"], "error": res["error"],
            **({"stated_before_run": said, "not_stated_before_run": list(excluded)}
               if said is not None else {})}))
    else:
        o = sys.stdout
        _print_head(scene, res, gen, True, o)
        print(f"  stopped: {res['stop']}", file=o)
        for name, m in (("predicted felt stiffness k [N/m]", chk.render.felt_stiffness),
                        ("predicted felt damping b [N s/m]", chk.render.felt_damping)):
            print(f"  {name}", file=o)
            for row in m:
                print("    " + "  ".join(f"{v:+14.8g}" for v in row), file=o)
        if said is not None:
            print(f"  stated before the run: {said}", file=o)
        print(f"  verdict: {res['verdict']}: {res['reason']}", file=o)
    from hapsim.outputs import say_error_after
    say_error_after("run", res["error"])
    return 1


def _limit_text(designed: str) -> str:
    """:func:`designed_start`'s limit in words: "contact wall" -> "the contact 'wall'"."""
    if designed.startswith("contact "):
        return f"the contact {designed.split(' ', 1)[1]!r}"
    if designed == "envelope":
        from hapsim.pipeline.haply2_record import ENVELOPE_RAD
        return f"the joints' envelope of {ENVELOPE_RAD:g} rad"
    return designed


def designed_start(scene) -> tuple:
    """The hand's start a run takes when none is given: the largest the scene's linear
    range allows (:func:`hapsim.lockstep.largest_start`: every engaged contact closed, the
    joints within :data:`hapsim.pipeline.haply2_record.ENVELOPE_RAD`), never below
    :data:`HAPLY_AMPLITUDE`. A larger start moves the records over more of the wire's
    resolution: on configs/pantograph_wall.yaml 0.42 mm (limited by the wall's 0.5 mm)
    states the felt damping that 0.1 mm left unstated, in lockstep and in real time
    (docs/drivers.md).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 2-D pantograph scene with a port.

    Returns
    -------
    (float, str)
        ``a`` [m] and what limits it (``"contact NAME"``, ``"envelope"``, or ``"the
        smallest start (...)"`` saying what the scene allowed: a contact open at rest, a
        scene not at rest at its joints whose drift alone reaches the limit, or a start
        below the smallest).

    Raises
    ------
    ConfigError
        As :func:`hapsim.lockstep.identification_plan`.
    """
    from hapsim.lockstep import START_MARGIN, identification_plan, largest_start
    from hapsim.pipeline.haply2_record import ENVELOPE_RAD
    a, by, limit = largest_start(scene, identification_plan(scene)[2], ENVELOPE_RAD)
    if a <= 0.0 and limit <= 0.0:
        # the verdict then says the contact opens, by name
        return HAPLY_AMPLITUDE, f"the smallest start ({by} is open at rest)"
    if a <= 0.0:
        what = ("the joints' envelope at the handle" if by == "envelope" else
                f"the {by}'s depth")
        return HAPLY_AMPLITUDE, (f"the smallest start (the scene is not at rest at its "
                                 f"joints: left alone from rest, the handle reaches "
                                 f"{START_MARGIN:g} of {what})")
    if a < HAPLY_AMPLITUDE:
        return HAPLY_AMPLITUDE, f"the smallest start ({by} allows {a:.2g} m)"
    return a, by


def prediction_haply2(pre: dict, amplitude: float):
    """What a real-time 2DIY run will not state, from its records' verdict in lockstep
    (:func:`hapsim.emulated.haply2_lockstep.measure_felt_haply2`: the same board, counts
    and binary32 rounding, no host timing; the statement depends on the records alone,
    its rounding's draws seeded: :mod:`hapsim.analysis.wire_rounding`).

    Parameters
    ----------
    pre : dict
        The lockstep measurement's result.
    amplitude : float
        ``a`` [m].

    Returns
    -------
    (dict, str or None)
        ``excluded`` (``{statement name: reason}``: never stated by the real-time run,
        :func:`hapsim.pipeline.haply2_host.measure_felt_haply2_port`) and the sentence
        said before the run (None: every statement will be made).
    """
    from hapsim.analysis.felt_matrices import said_before_run
    stated = [s["name"] for s in pre["statements"] if s["verdict"] != "not measurable"]
    not_stated = list(pre["not_stated"])
    why = ("not stated, predicted before the run: the wire's term on the same records in "
           "lockstep is beyond the limit")
    reasons = {s["name"]: s["reason"] for s in pre["statements"]}
    detail = "; ".join(f"{n}: {reasons[n]}" for n in not_stated if reasons.get(n))
    return ({n: why for n in not_stated},
            said_before_run(f"the emulated 2DIY's records in lockstep at a = {amplitude:g} "
                            "m, its counts' and binary32 rounding alone", stated, not_stated,
                            detail or pre["reason"]))

