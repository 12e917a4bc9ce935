"""``hapsim run`` on a 2-D or 3-D scene: the felt matrices measured and compared with the
prediction, and the linearisation bound. ``--lockstep``: the loop closed in-process;
``--port PORT``: over the framed protocol with an n-axis device, in real time (late ticks
accounted per axis, :mod:`hapsim.pipeline.run_nd`); neither: the same over the embedded n-D
mock (``hapsim mock --scene SCENE --once``) in a child process behind a pty."""

from __future__ import annotations

import json
import math
import sys

import numpy as np

from hapsim.errors import ConfigError

#: ``hapsim run``'s own options (not run options) an n-D scene does not take.
_REFUSED = (("device", "--device"), ("auto", "--auto"))


def _refuse_options(args):
    """Refuse ``hapsim run``'s own options an n-D run does not take, then every run option
    it does not take (:func:`hapsim.pipeline.felt_run.refuse_options`), by its flag.

    Returns
    -------
    hapsim.pipeline.options.RunOptions
        The run options of the command line, checked one by one.
    """
    from hapsim.pipeline.felt_run import refuse_options
    from hapsim.pipeline.options import RunOptions
    for attr, flag in _REFUSED:
        if getattr(args, attr, None) is not None and getattr(args, attr) is not False:
            raise ConfigError(f"a 2-D or 3-D scene does not take {flag} yet (1-D scenes "
                              "only)", key=flag)
    opts = RunOptions.from_args(args)
    refuse_options(opts)
    return opts


def run_nd(args) -> int:
    """Measure an n-D scene's felt matrices (``dimension: 2`` or ``3``).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``lockstep``, ``port``, ``amplitude`` [m] (None: 1e-8), ``json``, and
        run's other options (refused when set).

    Returns
    -------
    int
        0 when the loop is stable (the measurement then reported, whatever it finds),
        1 when the check finds it unstable and ``--allow-unstable`` is not given, or the
        device fails (no HELLO, a FAULT, STATEs lost).

    Raises
    ------
    ConfigError
        An option the n-D run does not take; a bad amplitude or scene (file, line, key).

    Notes
    -----
    In-process (``--lockstep`` without ``--port``):
    :func:`hapsim.lockstep.measure_felt_lockstep`: 2n free responses of the loop
    (engine, exact ZOH device of the Cartesian mass at rest, delay line) from the handle
    displaced by ``a`` along each axis and moving along each, minus the response from
    rest. Over a port: :func:`hapsim.pipeline.run_nd.measure_felt_port`, the same records
    from the device's hand, each a CONFIG, with the late ticks' known disturbance
    subtracted. Then the felt matrices by vector linear prediction and the inverse
    quadratic eigenvalue problem (:mod:`hapsim.analysis.identify_nd`), against
    :func:`hapsim.analysis.scene_check.check_scene_nd`; the linearisation bound of
    :mod:`hapsim.analysis.linearisation` at ``a``.
    """
    from hapsim.progress import Progress
    opts = _refuse_options(args)
    driver = getattr(args, "driver", None)
    if getattr(args, "generation", None) is not None and driver != "haply":
        raise ConfigError("goes with --driver haply on a 2-D pantograph scene (the Haply "
                          "2DIY's two wire generations)", key="--generation")
    if driver == "falcon":
        from hapsim.commands.run_falcon import run_falcon_command
        return run_falcon_command(args)
    for flag, attr in (("--firmware", "firmware"), ("--packets", "packets")):
        if getattr(args, attr, None) is not None:
            raise ConfigError(f"{flag} goes with --driver falcon (a delta scene on the "
                              "Novint Falcon)", key=flag)
    if driver not in (None, "haply"):
        raise ConfigError(f"a 2-D or 3-D scene takes --driver haply (a pantograph scene, "
                          f"the Haply 2DIY) or --driver falcon (a delta scene, the Novint "
                          f"Falcon), not {driver!r}", key="--driver")
    if driver == "haply":
        return _run_haply2(args)
    from hapsim.pipeline.felt_run import measure_scene_nd, scene_for_run
    a, scene = scene_for_run(args.scene, getattr(args, "amplitude", None),
                             getattr(args, "rate_hz", None))
    from hapsim.api import stable_prediction_nd
    stable_prediction_nd(scene, args.allow_unstable, "--allow-unstable")
    n = scene.dimension
    in_process = args.lockstep and not args.port
    label = "run (lockstep)" if in_process else "run (over the port)"
    from hapsim.errors import DeviceError, ProtocolError
    with Progress(2 * n if in_process else 2 * n + 1, label, unit="records") as bar:
        try:
            res, port_info = measure_scene_nd(scene, opts, a, progress=bar.update)
        except (DeviceError, ProtocolError) as exc:
            print(f"hapsim run: {exc}", file=sys.stderr)
            return 1
    where = "in-process" if in_process else (
        f"over {port_info['port']}" + (" (embedded mock, real time)"
                                       if port_info["embedded"] else ""))
    fit, chk, dev, bound = res["measured"], res["predicted"], res["deviation"], res["bound"]
    if args.json:
        from hapsim.api import run_report_nd
        out = run_report_nd(scene, res, in_process, port_info).to_dict()
        print(json.dumps(out))
        return 0
    o = sys.stdout
    if in_process:
        print(f"{scene.path}: {n}-D scene in lockstep at {scene.rate_hz:g} Hz, in-process "
              f"(engine, exact ZOH device of the Cartesian mass at rest, delay "
              f"{scene.device.delay})", file=o)
    else:
        print(f"{scene.path}: {n}-D scene {where}, {n} axes on the framed protocol "
              f"(device delay {res['delay'][0] if res['delay'] else 'unknown'} ticks from "
              "seq - force_seq)", file=o)
        c = res["counts"]
        print(f"  late ticks: {res['late']} of {sum(res['rows'])} rows used "
              f"(watchdog {res['watchdog']}), their known disturbance's response "
              f"subtracted per axis; host scheduling: {port_info['scheduling']}", file=o)
        print(f"  rows used per start (rest first): {res['rows']} of {res['samples']}; "
              f"CONFIGs {c['configs']}, records cut short at a lost STATE {c['cut']} "
              f"(STATEs missed {c['missed']}, duplicates {c['stale']}, reordered "
              f"{c['reordered']}, bad frames {res['bad_frames']}), device resets "
              f"{c['resets']}, device lost {c['lost']} / recovered {c['recovered']}"
              + (f"; faults injected: {port_info['faults_injected']}"
                 if port_info.get("faults_injected") else ""), file=o)
        if res.get("stop", "end") != "end":
            print(f"  stopped: {res['stop']} (what was recorded by then is reported)",
                  file=o)
    print(f"  excitation: {res['records']} free responses of {res['samples']} samples, "
          f"amplitude a = {a:g} m (minus the response from rest)", file=o)
    if not chk.stable:
        grow = chk.render.spectral_radius ** res["samples"]
        print(f"  the loop is UNSTABLE (--allow-unstable): its free responses grow by up to "
              f"{grow:.3g} times over a record, so the amplitude and the bound below hold "
              "at its start only", file=o)

    def mat(name, m, unit):
        if m is None:
            print(f"  {name}: none (fewer than {n} rendered pairs)", file=o)
            return
        print(f"  {name} [{unit}]", file=o)
        for row in m:
            print("    " + "  ".join(f"{v:+14.8g}" for v in row), file=o)
    mat("predicted felt stiffness k", chk.render.felt_stiffness, "N/m")
    mat("measured felt stiffness k", fit["felt_stiffness"], "N/m")
    mat("predicted felt damping b", chk.render.felt_damping, "N s/m")
    mat("measured felt damping b", fit["felt_damping"], "N s/m")
    if dev is not None:
        print(f"  measured - predicted (largest entry over the largest predicted): "
              f"k {dev['felt_stiffness']:.2e}, b {dev['felt_damping']:.2e}", file=o)
    bd = bound.to_dict()
    print(f"  linearisation bound at the records' largest excursion {bound.amplitude:.3g} m "
          f"(first order in it; hapsim.analysis.linearisation):", file=o)
    print(f"    device kinematics c_kin = {bound.kinematic:.4g} /m (the Cartesian mass "
          "and the velocity-product terms over a; "
          + ("not in the lockstep device, which holds the mass at rest)" if in_process
             else "carried by a joint-space device, the mock's or a real one)"), file=o)
    print(f"    Euclidean links c_link = {bound.link:.4g} /m"
          + (f" (link {bound.link_name!r})" if bound.link_name else " (none: linear)"),
          file=o)
    if bd["felt_stiffness"] is None:
        print(f"    the excursion reaches the depth of {bound.depth_name!r} "
              f"({bound.depth:.3g} m): "
              "the contact opens, no linear estimate holds", file=o)
    else:
        print(f"    felt stiffness within {bd['felt_stiffness']:.2e}, felt damping within "
              f"{bd['felt_damping']:.2e} (relative) while the excursion < {bound.depth:.3g} m"
              + (f" (depth of {bound.depth_name!r})" if bound.depth_name else ""), file=o)
    from hapsim.pipeline.run_nd import verdict_nd
    v = verdict_nd(res)
    wire = res.get("wire")
    if wire is not None:
        dq = wire["reading_bound_rad"]
        print(f"  device: {port_info.get('device')}", file=o)
        print(f"  the wire's rounding (joint readings within {dq[0]:.2e} / {dq[1]:.2e} rad: "
              f"half a count and a binary32 ulp; torques within {wire['torque_bound_nm']:.2e} "
              "N m: half a PWM step), first-order worst case through the loop and the fit: "
              f"k {wire['felt_stiffness']:.2e}, b {wire['felt_damping']:.2e}; one count at "
              f"the handle {wire['quantum_m']:.2e} m", file=o)
    print_statements(v, o)
    print(f"  verdict: {v['verdict']}: {v['reason']}", file=o)
    return 0


def print_statements(v: dict, o) -> None:
    """Print a verdict's statements (:func:`hapsim.analysis.felt_matrices.felt_verdict`), one a line:
    the quantity (a felt matrix as a whole, or along a principal direction: predicted and
    measured [N/m] or [N s/m]), its deviation against its stated uncertainty (the
    linearisation bound plus the wire's term, relative), and what it says.

    Parameters
    ----------
    v : dict
        The verdict, with ``statements``.
    o : file
        Where to print.
    """
    st = v.get("statements") or []
    if not st:
        return
    print("  statements (relative: measured - predicted against the stated uncertainty = "
          "linearisation bound + the wire's term + binary64 round-off):", file=o)
    unit = {"felt_stiffness": "N/m", "felt_damping": "N s/m"}

    def e(x):
        return "-" if x is None else f"{x:.2e}"
    for s in st:
        head = s["name"]
        if s["direction"] is not None:
            head += (f": predicted {s['predicted']:.6g}, measured {s['measured']:.6g} "
                     f"{unit[s['quantity']]}")
        terms = (f"lin {e(s['linearisation'])}"
                 + (f" + wire {e(s['wire'])}" if s["wire"] is not None else "")
                 + (f" + round-off {e(s.get('roundoff'))}" if s.get("roundoff") else ""))
        if s["verdict"] == "not measurable":
            print(f"    {head}: not measurable ({s['reason']})", file=o)
        else:
            print(f"    {head}: {s['verdict']} (deviation {e(s['deviation'])} "
                  + ("<=" if s["within"] else ">") + f" {e(s['uncertainty'])} = {terms})",
                  file=o)


#: ``--driver haply``'s default amplitude [m]: the binary32 angles on the wire resolve
#: ~1e-7 m at the handle, so 1e-4 m keeps them below 1e-3 of it.
HAPLY_AMPLITUDE = 1e-4
#: The emulated encoders' counts per revolution under ``--driver haply --lockstep``: a
#: fine encoder, so that the run checks the wire and the loop (a real 2DIY's 10752 or 4880
#: counts are tens of micrometres at the handle; the report states what they would be).
HAPLY_CPR = 2.0 ** 22


def _run_haply2(args) -> int:
    """``hapsim run SCENE --driver haply [--lockstep]``: the felt matrices through the
    2DIY's bytes and its emulated board, in lockstep
    (:func:`hapsim.emulated.haply2_board.measure_felt_haply2`) or in real time, the board in
    a child process behind a pty and the host on its clock, missing replies estimated
    samples (:func:`hapsim.pipeline.haply2_host.measure_felt_haply2_port`).

    Returns
    -------
    int
        0 (the measurement and its verdict reported, whatever it finds: "within",
        "differs" or "not measurable"); 1 when the board lost a reply.

    Raises
    ------
    ConfigError
        With ``--port`` (a real board has no hand to start each record), a scene that is
        not a 2-D pantograph, a bad amplitude.
    """
    import gc

    from hapsim.emulated.haply2_board import measure_felt_haply2
    from hapsim.errors import DeviceError
    from hapsim.progress import Progress
    if args.port:
        raise ConfigError("--driver haply on a 2-D scene runs against the emulated board, "
                          "whose hand starts each record (a real 2DIY has none): no --port",
                          key="--port")
    realtime = not args.lockstep
    gen = getattr(args, "generation", None) or "gen3"
    a, scene = _amplitude_and_scene(args, HAPLY_AMPLITUDE)
    with Progress(5, "run (2DIY bytes, " + ("real time)" if realtime else "lockstep)"),
                  unit="records") as bar:
        try:
            if realtime:
                from hapsim.pipeline.haply2_host import Embedded2DIY, measure_felt_haply2_port
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
                            lockstep_board=getattr(child, "clock", "lockstep") == "lockstep")
                    res["scheduling"] = rt.note
                finally:
                    if gc_was:
                        gc.enable()
                    child.close()
            else:
                res = measure_felt_haply2(scene, gen, amplitude=a, cpr=HAPLY_CPR,
                                          progress=bar.update)
        except DeviceError as exc:
            print(f"hapsim run: {exc}", file=sys.stderr)
            return 1
    chk, fit, dev = res["predicted"], res["measured"], res["deviation"]
    bound, wire = res["bound"], res["wire"]
    real = res["quantum_encoders"]

    def num(x):
        return float(x) if math.isfinite(x) else None
    if args.json:
        def mat(x):
            return None if x is None else np.asarray(x, float).tolist()
        print(json.dumps({
            "scene": scene.path, "dof": 2, "driver": "haply", "generation": gen,
            "lockstep": not realtime, "rate_hz": scene.rate_hz, "amplitude": a,
            "emulated_cpr": HAPLY_CPR,
            **({"estimated": res["estimated"], "late_ticks": res["late_ticks"],
                "replies": res["replies"], "writes": res["writes"],
                "resyncs": res["resyncs"], "skipped": res["skipped"],
                "scheduling": res.get("scheduling")} if realtime else {}),
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
                     "torque_rel": wire["torque_rel"]},
            "uncertainty": res["uncertainty"], "statements": res["statements"],
            "not_stated": res["not_stated"], "verdict": res["verdict"],
            "within": res["within"], "reason": res["reason"], "clamped": res["clamped"],
            "quantum": res["quantum"], "quantum_real_encoders": real,
            "records": res["records"], "samples": res["samples"]}))
        return 0
    o = sys.stdout
    print(f"{scene.path}: the Haply 2DIY's bytes ({gen} set-up, firmware V1.5 board "
          f"emulated, encoders of {HAPLY_CPR:.0f} counts/rev), "
          + ("in real time (the board in a child process behind a pty)" if realtime
             else "in lockstep"), file=o)
    if realtime:
        print(f"  estimated samples (replies not read by their tick) per record: "
              f"{res['estimated']}; ticks the host began a period late: "
              f"{res['late_ticks']}; replies read {res['replies']} of {res['writes']}; "
              f"host loop scheduling: {res.get('scheduling')}", file=o)
    print(f"  excitation: {res['records']} free responses of {res['samples']} writes, "
          f"a = {a:g} m (minus the response from rest)", file=o)
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
        print(f"  linearisation bound at a: k {bd['felt_stiffness']:.2e}, "
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
    print_statements(res, o)
    print(f"  verdict: {res['verdict']}: {res['reason']}", file=o)
    print(f"  one reading step at the handle over a: {res['quantum']:.2e} (one count of the "
          f"emulated encoders or a binary32 ulp, the larger); a real 2DIY's encoders: gen2 "
          f"{real['gen2']:.2e}, gen3 {real['gen3']:.2e} of a", file=o)
    return 0


def _amplitude_and_scene(args, default: float):
    """``--amplitude`` (``default`` when absent) checked, and the scene with its port, at
    ``--rate`` when given (:func:`hapsim.pipeline.felt_run.scene_for_run`)."""
    from hapsim.pipeline.felt_run import scene_for_run
    return scene_for_run(args.scene, getattr(args, "amplitude", None),
                         getattr(args, "rate_hz", None), default)
