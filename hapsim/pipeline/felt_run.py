"""One 2-D or 3-D run (``dimension: 2`` or ``3``): the felt matrices measured, what
:func:`hapsim.api.run` and ``hapsim run`` do with such a scene, as
:mod:`hapsim.pipeline.runner` does with a 1-D one.

``lockstep`` without a ``port``: the loop closed in-process
(:func:`hapsim.lockstep.measure_felt_lockstep`). Otherwise over the framed protocol
with an n-axis device (:func:`hapsim.pipeline.felt_port.measure_felt_port`): the ``port``
given, or an embedded n-D mock (``hapsim mock --scene SCENE --once``) in a child process
of its own session behind a pty, real time unless ``lockstep``. Over a port a stop
requested (Ctrl-C or SIGTERM when ``handle_signals``, or ``RunOptions.stop``) ends the
record under way and the measurement reports what it had.

The 2DIY (``driver="haply"``) and the Falcon (``driver="falcon"``) take their own routes
(``hapsim run``'s, :mod:`hapsim.commands.run`).
"""

from __future__ import annotations

import dataclasses
import math

from hapsim.errors import ConfigError

__all__ = ["ND_TAKES", "ND_REFUSED_WHY", "DEFAULT_AMPLITUDE", "refuse_options", "scene_for_run",
           "measure_scene_nd", "print_statements"]

#: The run options (:class:`hapsim.pipeline.options.RunOptions` fields) an n-D run takes;
#: every other one set to anything but its default is refused by name (its flag)
#: (``driver`` takes ``haply`` on a pantograph scene and ``falcon`` on a delta scene:
#: the command's own routes).
ND_TAKES = ("port", "baud", "lockstep", "allow_unstable", "rt_priority", "driver",
            "rate_hz", "faults", "fault_seed", "frames", "reconnect", "reconnect_attempts",
            "reconnect_time", "lost_timeout")

#: Why an n-D run does not take each run option it refuses (said with the refusal; an
#: option not named here: "1-D scenes only").
ND_REFUSED_WHY = {
    "duration": "it measures 2n + 1 records whose length the fit sets",
    "host_clocked": "the n-axis device keeps its own clock, a STATE every tick",
    "loop": "its record loop is the Python one; the compiled host loop is 1-D",
    "telemetry": "its records are kept in memory, for the fit only",
    "seed": "the n-axis mock has no sensor noise",
    "osc": "a 2-D or 3-D scene is played live by 'hapsim play SCENE --osc PORT'",
    "osc_ramp": "a 2-D or 3-D scene is played live by 'hapsim play SCENE --osc PORT'",
    "sound": "a 2-D or 3-D scene is heard live through 'hapsim play SCENE'",
    "jack_server": "a 2-D or 3-D scene is heard live through 'hapsim play SCENE'",
    "view": "a 2-D or 3-D scene's live view is 'hapsim play SCENE --view'",
}

#: Default excitation amplitude [m]: small enough that the scenes' Euclidean links depart
#: from their linearisation by ~1e-7 (c_link ~ 30 /m), large enough against the round-off
#: of positions ~0.1 m (1e-17 m, 1e-9 relative).
DEFAULT_AMPLITUDE = 1e-8


def refuse_options(opts, by: str = "flag", takes: tuple = ND_TAKES,
                   what: str = "a 2-D or 3-D scene", why: str = "1-D scenes only") -> None:
    """Refuse every run option an n-D run does not take (:data:`ND_TAKES`), by name.

    Parameters
    ----------
    opts : hapsim.pipeline.options.RunOptions
        A value is taken as not given when it equals its command line's default (``by``
        "flag") or the field's (``by`` "field"), of the same type (``0 == False`` is not
        a float's default).
    by : {"flag", "field"}
        Name an option by its command-line flag (``--duration``: ``hapsim run``) or its
        field (``duration``: :func:`hapsim.api.run`).
    takes : tuple of str, optional
        The fields the run takes (a scene with several ports takes fewer).
    what, why : str, optional
        The run's scene and what takes the option instead, for the message.

    Returns
    -------
    None
        When every option not in ``takes`` has its default.

    Raises
    ------
    ConfigError
        Keyed by the first such option's flag (``--duration``, ``--telemetry``, ...).
    """
    from hapsim.pipeline.options import command_line_fields

    def same(v, d) -> bool:
        return type(v) is type(d) and v == d
    given = []
    fields = {}                             # what is named -> the field's name
    for f in command_line_fields():
        if f.name in takes:
            continue
        v = getattr(opts, f.name)
        # the command line's default (--loop auto) or the field's (a Python caller's)
        if not same(v, f.metadata["cli"]["cli_default"] if by == "flag" else f.default):
            given.append(f.metadata["cli"]["flag"] if by == "flag" else f.name)
            fields[given[-1]] = f.name
    if given:
        if takes is ND_TAKES:               # the n-D run's own reason per option
            why = ND_REFUSED_WHY.get(fields[given[0]], why)
        raise ConfigError(f"{what} does not take {given[0]} yet ({why})", key=given[0])


def scene_for_run(scene, amplitude: float | None, rate_hz: float | None,
                  default: float = DEFAULT_AMPLITUDE):
    """The amplitude checked and the scene at ``rate_hz`` when given (the loop's rate
    overridden, as for a 1-D scene: the prediction, the engine, the device and its mock
    all at that rate).

    Parameters
    ----------
    scene : hapsim.scene.SceneND or str or path-like
    amplitude : float or None
        The excitation's amplitude [m] (None: ``default``).
    rate_hz : float or None
        [Hz].
    default : float
        [m].

    Returns
    -------
    (float, hapsim.scene.SceneND)

    Raises
    ------
    ConfigError
        A non-positive amplitude or rate (keys ``--amplitude``, ``--rate``); a scene
        without a port (file, key ``masses``).
    """
    import os

    from hapsim.scene import load_scene_nd
    from hapsim.option_values import check_values
    a = default if amplitude is None else amplitude
    # (its declaration: before, True was taken as 1 m)
    check_values("run_nd", required=True, amplitude=a)
    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene_nd(scene)
    if rate_hz is not None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ConfigError(f"must be a positive number [Hz], got {rate_hz}",
                              key="--rate")
        scene = dataclasses.replace(scene, rate_hz=float(rate_hz))
    from hapsim.analysis.prediction import require_device
    require_device(scene)      # (the 1-D run's refusal: the same message, file and line)
    return float(a), scene


def measure_scene_nd(scene, opts, amplitude: float, progress=None, by: str = "flag"):
    """Measure a 2-D or 3-D scene's felt matrices (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        With a port (:func:`scene_for_run`); its file is what the embedded mock loads
        (at the scene's rate).
    opts : hapsim.pipeline.options.RunOptions
        ``port``, ``baud``, ``lockstep``, ``rt_priority``, ``faults``, ``fault_seed``,
        ``stop``, ``handle_signals`` (the others refused: :func:`refuse_options`).
    amplitude : float
        The excitation's amplitude [m].
    progress : callable, optional
        ``progress(done, total)`` per whole record.
    by : {"flag", "field"}
        How a refused option is named (:func:`refuse_options`).

    Returns
    -------
    (dict, dict or None)
        The measurement (:func:`hapsim.lockstep.measure_felt_lockstep`'s or
        :func:`hapsim.pipeline.felt_port.measure_felt_port`'s, with ``bound`` at the records'
        largest excursion) and, over a port, ``{"port", "embedded", "mock",
        "scheduling", "faults", "fault_seed", "faults_injected"}`` (and ``device``,
        ``clamped`` for a joint-level pantograph); None in-process.

    Raises
    ------
    ConfigError
        An option not taken; ``faults`` with a ``port``, or in lockstep.
    DeviceError, ProtocolError
        The device failed (no HELLO, a FAULT, lost beyond recovery).
    """
    refuse_options(opts, by)
    if opts.lockstep and not opts.port:
        if opts.faults:
            # (before, taken and ignored: "within", nothing injected, nothing said)
            raise ConfigError("the lockstep run of a 2-D or 3-D scene closes its loop in "
                              "this process, with no wire to fault: its n-axis mock takes "
                              "faults on its own clock (without --lockstep)",
                              key="--faults" if by == "flag" else "faults")
        from hapsim.lockstep import measure_felt_lockstep
        return measure_felt_lockstep(scene, amplitude, progress=progress), None
    from hapsim.analysis.linearisation import bound_at_records, linearisation_bound
    res, info = _over_port(scene, opts, amplitude, progress)
    # the bound at the largest excursion the records reached: a late tick's held force
    # moves the handle past the nominal amplitude, and the departure from the linear
    # loop grows with the motion (hapsim.analysis.linearisation)
    poles = res["predicted"].render.rendered_poles
    res["bound"] = (bound_at_records(scene, amplitude, res["moved"], poles,
                                     free=res.get("responses"))[0]
                    if res.get("moved") else
                    linearisation_bound(scene, max(amplitude, res["excursion"]), poles))
    return res, info


def _over_port(scene, opts, a: float, progress):
    """:func:`hapsim.pipeline.felt_port.measure_felt_port` over ``opts.port`` or an embedded
    mock; the child and its temporary folder are gone whatever the way this ends."""
    import gc
    import json
    import os
    import shutil
    import signal
    import subprocess
    import sys
    import tempfile
    import threading

    from hapsim.emulated.faults import parse_faults
    from hapsim.errors import DeviceError
    from hapsim.host.realtime import RealtimePriority
    from hapsim.host.transport import SerialTransport
    from hapsim.pipeline.felt_port import measure_felt_port
    from hapsim.spawn import StopFlag, at_stop, child_env, done
    child = None
    port = opts.port
    faults = opts.faults
    plan = parse_faults(faults, int(opts.fault_seed or 0)) if faults else None
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
    try:
        if port is None:
            if not opts.lockstep:           # refused here, not by the child's mock
                from hapsim.emulated.mock import require_whole_delay
                require_whole_delay(scene.device.delay, file=scene.path)
            cmd = [sys.executable, "-m", "hapsim", "mock", "--scene", str(scene.path),
                   "--once", "--amplitude", repr(a), "--rt-priority",
                   str(int(opts.rt_priority or 0)), "--rate", repr(float(scene.rate_hz)),
                   "--report", report]
            if opts.lockstep:
                cmd.append("--lockstep")
            if plan is not None:
                cmd += ["--faults", plan.spec, "--fault-seed", str(plan.seed)]
                if plan.has_vanish:
                    # the pty closes and a new one comes: the host opens the link kept at it
                    cmd += ["--link", os.path.join(tmp, "port")]
            # in a session of its own, as the 1-D run's mock (hapsim.spawn.PtyChild.start):
            # a Ctrl-C at the terminal reaches only the host, which stops the device itself
            child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     env=child_env(), text=True, start_new_session=True)
            started.append(child)
            line = child.stdout.readline()
            if not line.startswith("PORT "):
                child.kill()
                raise DeviceError("the embedded n-D mock did not start: "
                                  + (child.stderr.read() or line).strip()[-500:])
            port = line.split()[1]
        tr = SerialTransport(port, opts.baud)
    except BaseException:
        undo()
        done(stop_token)
        raise
    joint = None
    if scene.dimension == 2 and scene.device.kind == "pantograph":
        # a joint-level pantograph (the Hapkit pantograph's firmware) says so in HELLO:
        # then its joint angles and torques are turned into the Cartesian device's
        from hapsim.emulated.pantograph_board import JointLevelTransport
        tr = joint = JointLevelTransport(tr, scene)
    gc_was = gc.isenabled()
    rt = RealtimePriority(int(opts.rt_priority or 0))
    stop = opts.stop or StopFlag()
    lost = False            # the device lost for good, or the measurement raised
    old = {}
    if opts.handle_signals and threading.current_thread() is threading.main_thread():
        # Ctrl-C and SIGTERM end the record under way and report what was measured, as
        # the 1-D run does (hapsim.pipeline.runner)
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, lambda signum, frame: stop.request(signum))
    try:
        # as the 1-D loop: SCHED_FIFO where permitted, no collection while it runs
        with rt:
            gc.disable()
            # the 1-D run's recovery options; the compact frames whenever the device
            # offers them ("auto" and "compact" alike: the n-D frames are the larger)
            lost = True                         # until the measurement returns
            res = measure_felt_port(
                tr, scene, progress=progress, amplitude=a, stop=stop,
                late_guard=not opts.lockstep,
                reconnect=(not opts.lockstep) if opts.reconnect is None else opts.reconnect,
                reconnect_time=opts.reconnect_time,
                reconnect_attempts=opts.reconnect_attempts, lost_timeout=opts.lost_timeout,
                frames="full" if opts.frames == "full" else "auto")
            lost = res.get("error") is not None
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if gc_was:
            gc.enable()
        tr.close()
        note = None
        if child is not None:
            if lost:
                # a mock whose port is gone (vanish) never sees the host leave: it
                # is asked to end (SIGTERM: it writes its report), not waited for
                child.terminate()
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


def print_statements(v: dict, o) -> None:
    """Print a verdict's statements (:func:`hapsim.analysis.felt_matrices.felt_verdict`), one a
    line: the quantity (a felt matrix as a whole, or along a principal direction: predicted
    and measured [N/m] or [N s/m]), its deviation against its stated uncertainty (the
    linearisation bound plus the wire's term, relative), and what it says.

    Parameters
    ----------
    v : dict
        The verdict, with ``statements``.
    o : file
        Where to print.

    Returns
    -------
    None
        Nothing is printed when the verdict has no statements.
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
