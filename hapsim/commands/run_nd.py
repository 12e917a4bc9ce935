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

#: The run options (:class:`hapsim.pipeline.options.RunOptions` fields) an n-D run takes;
#: every other one set to anything but its default is refused by name, with exit 2
#: (``--driver`` takes ``haply`` on a pantograph scene: the emulated 2DIY board).
ND_TAKES = ("port", "baud", "lockstep", "allow_unstable", "rt_priority", "driver",
            "rate_hz", "faults", "fault_seed")

#: ``hapsim run``'s own options (not run options) an n-D scene does not take.
_REFUSED = (("device", "--device"), ("auto", "--auto"))


def _refuse_options(args) -> None:
    """Refuse every option the n-D run does not take (module constants), by its flag, and
    check the ones it takes by their declarations (:func:`hapsim.pipeline.options.option`)."""
    from hapsim.pipeline.options import command_line_fields
    set_ = [opt for attr, opt in _REFUSED
            if getattr(args, attr, None) is not None and getattr(args, attr) is not False]
    for f in command_line_fields():
        meta = f.metadata["cli"]
        if not hasattr(args, f.name):
            continue
        if f.name in ND_TAKES:
            if meta["check"] is not None and getattr(args, f.name) is not None:
                meta["check"](getattr(args, f.name), meta["flag"])
            continue
        v, d = getattr(args, f.name), meta["cli_default"]
        # (0 == False == 0.0: a value is the default only of the same type)
        if type(v) is not type(d) or v != d:
            set_.append(meta["flag"])
    if set_:
        raise ConfigError(f"a 2-D or 3-D scene does not take {set_[0]} yet (1-D scenes "
                          "only)", key=set_[0])

#: Default excitation amplitude [m]: small enough that the scenes' Euclidean links depart
#: from their linearisation by ~1e-7 (c_link ~ 30 /m), large enough against the round-off
#: of positions ~0.1 m (1e-17 m, 1e-9 relative).
DEFAULT_AMPLITUDE = 1e-8


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
    :func:`hapsim.lockstep_nd.measure_felt_lockstep`: 2n free responses of the loop
    (engine, exact ZOH device of the Cartesian mass at rest, delay line) from the handle
    displaced by ``a`` along each axis and moving along each, minus the response from
    rest. Over a port: :func:`hapsim.pipeline.run_nd.measure_felt_port`, the same records
    from the device's hand, each a CONFIG, with the late ticks' known disturbance
    subtracted. Then the felt matrices by vector linear prediction and the inverse
    quadratic eigenvalue problem (:mod:`hapsim.analysis.identify_nd`), against
    :func:`hapsim.analysis.scene_nd_check.check_scene_nd`; the linearisation bound of
    :mod:`hapsim.analysis.linearisation_nd` at ``a``.
    """
    from hapsim.lockstep_nd import measure_felt_lockstep
    from hapsim.progress import Progress
    _refuse_options(args)
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
    a, scene = _amplitude_and_scene(args, DEFAULT_AMPLITUDE)
    from hapsim.analysis.linearisation_nd import linearisation_bound
    from hapsim.api_nd import stable_prediction_nd
    pred = stable_prediction_nd(scene, args.allow_unstable, "--allow-unstable")
    n = scene.dimension
    in_process = args.lockstep and not args.port
    where = "in-process"
    port_info = None
    if in_process:
        with Progress(2 * n, "run (lockstep)", unit="records") as bar:
            res = measure_felt_lockstep(scene, a, progress=bar.update)
    else:
        from hapsim.errors import DeviceError, ProtocolError
        try:
            res, port_info = _measure_over_port(args, scene, a, n)
        except (DeviceError, ProtocolError) as exc:
            print(f"hapsim run: {exc}", file=sys.stderr)
            return 1
        # the bound at the largest excursion the records reached: a late tick's held force
        # moves the handle past the nominal amplitude, and the departure from the linear
        # loop grows with the motion (hapsim.analysis.linearisation_nd)
        res["bound"] = linearisation_bound(scene, max(a, res["excursion"]),
                                           pred.render.rendered_poles)
        where = (f"over {port_info['port']}" + (" (embedded mock, real time)"
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
          f"(first order in it; hapsim.analysis.linearisation_nd):", file=o)
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


def _measure_over_port(args, scene, a: float, n: int):
    """:func:`hapsim.pipeline.run_nd.measure_felt_port` over ``--port`` or an embedded mock.

    Returns
    -------
    (dict, dict)
        The measurement and ``{"port", "embedded", "mock", "scheduling"}`` (the embedded
        mock's last line on stderr, or None; what the host's SCHED_FIFO request obtained).
    """
    import gc
    import signal
    import subprocess
    import threading

    from hapsim.host.realtime import RealtimePriority
    from hapsim.pipeline.run_nd import measure_felt_port
    from hapsim.host.transport import SerialTransport
    from hapsim.errors import DeviceError
    from hapsim.progress import Progress
    from hapsim.spawn import StopFlag, at_stop, child_env, done
    import os
    import shutil
    import tempfile

    from hapsim.emulated.faults import parse_faults
    child = None
    port = args.port
    faults = getattr(args, "faults", None)
    plan = parse_faults(faults, int(getattr(args, "fault_seed", 0) or 0)) if faults else None
    if plan is not None and port is not None:
        raise ConfigError("--faults are injected by the embedded mock: not with --port "
                          "(give them to 'hapsim mock --faults' serving that port)",
                          key="--faults")
    tmp = tempfile.mkdtemp(prefix="hapsim-nd-")
    report = os.path.join(tmp, "mock.json")
    started: list = []      # the child, once started: a stop at any moment ends it first

    def undo() -> None:
        for proc in started:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        shutil.rmtree(tmp, ignore_errors=True)
    stop_token = at_stop(undo)
    if port is None:
        cmd = [sys.executable, "-m", "hapsim", "mock", "--scene", args.scene, "--once",
               "--amplitude", repr(a), "--rt-priority", str(int(args.rt_priority or 0)),
               "--rate", repr(float(scene.rate_hz)), "--report", report]
        if args.lockstep:
            cmd.append("--lockstep")
        if plan is not None:
            cmd += ["--faults", plan.spec, "--fault-seed", str(plan.seed)]
            if plan.has_vanish:
                # the pty closes and a new one comes: the host opens the link kept at it
                cmd += ["--link", os.path.join(tmp, "port")]
        # in a session of its own, as the 1-D run's mock (hapsim.spawn.PtyChild.start): a
        # Ctrl-C at the terminal reaches only the host, which stops the device itself
        child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 env=child_env(), text=True, start_new_session=True)
        started.append(child)
        line = child.stdout.readline()
        if not line.startswith("PORT "):
            child.kill()
            raise DeviceError("the embedded n-D mock did not start: "
                              + (child.stderr.read() or line).strip()[-500:])
        port = line.split()[1]
    tr = SerialTransport(port, getattr(args, "baud", 115200))
    joint = None
    if scene.dimension == 2 and scene.device.kind == "pantograph":
        # a joint-level pantograph (the Hapkit pantograph's firmware) says so in HELLO:
        # then its joint angles and torques are turned into the Cartesian device's
        from hapsim.emulated.pantograph_board import JointLevelTransport
        tr = joint = JointLevelTransport(tr, scene)
    gc_was = gc.isenabled()
    rt = RealtimePriority(int(args.rt_priority or 0))
    stop = StopFlag()
    old = {}
    if threading.current_thread() is threading.main_thread():
        # Ctrl-C and SIGTERM end the record under way and report what was measured, as
        # the 1-D run does (hapsim.pipeline.runner), instead of an exit 130 with nothing
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, lambda signum, frame: stop.request(signum))
    try:
        with Progress(2 * n + 1, "run (over the port)", unit="records") as bar:
            # as the 1-D loop: SCHED_FIFO where permitted, no collection while it runs
            with rt:
                gc.disable()
                res = measure_felt_port(tr, scene, progress=bar.update, amplitude=a,
                                        stop=stop)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if gc_was:
            gc.enable()
        tr.close()
        note = None
        if child is not None:
            try:
                _, err = child.communicate(timeout=5)
                note = (err or "").strip().splitlines()[-1:] or None
            except subprocess.TimeoutExpired:
                child.kill()
                child.communicate()
        injected = None
        try:
            with open(report) as fh:
                injected = json.load(fh).get("faults_injected")
        except (OSError, ValueError):
            pass
        shutil.rmtree(tmp, ignore_errors=True)
        done(stop_token)
    info = {"port": port, "embedded": child is not None,
            "mock": note[0] if note else None, "scheduling": rt.note,
            "faults": None if plan is None else plan.spec,
            "fault_seed": None if plan is None else plan.seed,
            "faults_injected": injected}
    if joint is not None and joint.joint_level:
        from hapsim.emulated.pantograph_board import wire_term
        h = joint.hello
        res["torque_max"] = joint.torque_max
        if not res.get("incomplete"):      # an incomplete record has no responses to weigh
            res["wire"] = wire_term(scene, res, h.position_scale, h.force_scale)
        info["device"] = ("Hapkit pantograph, joint level (HELLO device id "
                          f"{h.device_id:#x}: angles {h.position_scale:.6g} rad/count, "
                          f"torques {h.force_scale:.6g} N m/step; "
                          f"{res.get('frames', 'full')} frames)")
        info["clamped"] = joint.clamped
    return res, info


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
                child = Embedded2DIY(args.scene, gen, amplitude=a, cpr=HAPLY_CPR,
                                     rate_hz=scene.rate_hz)
                gc_was = gc.isenabled()
                try:
                    gc.disable()                 # no collection while the clock runs
                    # the emulated board advances one period per write unless it
                    # says it keeps the wall clock: a host stall costs its record
                    # nothing then
                    res = measure_felt_haply2_port(
                        child.port, scene, gen, amplitude=a, resolution=HAPLY_CPR,
                        progress=bar.update,
                        lockstep_board=getattr(child, "clock", "lockstep") == "lockstep")
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
                "resyncs": res["resyncs"], "skipped": res["skipped"]} if realtime else {}),
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
              f"{res['late_ticks']}; replies read {res['replies']} of {res['writes']}",
              file=o)
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
    ``--rate`` when given (the loop's rate overridden, as for a 1-D scene: the prediction,
    the engine, the device and its mock all at that rate).

    Raises
    ------
    ConfigError
        A non-positive amplitude or rate; a scene without a port (file, key).
    """
    from hapsim.scene_nd import load_scene_nd
    a = default if getattr(args, "amplitude", None) is None else args.amplitude
    if not (math.isfinite(a) and a > 0):
        raise ConfigError(f"must be a positive number [m], got {a}", key="--amplitude")
    scene = load_scene_nd(args.scene)
    rate = getattr(args, "rate_hz", None)
    if rate is not None:
        if not (math.isfinite(rate) and rate > 0):
            raise ConfigError(f"must be a positive number [Hz], got {rate}", key="--rate")
        import dataclasses
        scene = dataclasses.replace(scene, rate_hz=float(rate))
    if scene.port is None:
        raise ConfigError("a run needs a mass of kind 'port' and a device section",
                          file=scene.path, key="masses")
    return a, scene
