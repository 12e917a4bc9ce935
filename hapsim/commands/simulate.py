"""``hapsim simulate``: run a scene of any dimension offline and write the trajectories (or
its sound: ``--audio``)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import TYPE_CHECKING

from hapsim.errors import ConfigError, HapsimError
from hapsim.outputs import check_writable
from hapsim.progress import Progress
from hapsim.option_values import Number

if TYPE_CHECKING:       # the annotations' names (numpy loads lazily)
    import numpy as np


def register(sub) -> None:
    """Add the ``simulate`` sub-command.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The sub-parsers of the ``hapsim`` parser (:func:`hapsim.cli.build_parser`); the new
        parser's ``func`` is :func:`run`.
    """
    p = sub.add_parser(
        "simulate", help="run a scene offline (no device) and write positions to .npz or .csv",
        description=(
            "Run the mass-interaction scene offline with the CORDIS-ANIMA scheme and write "
            "the positions of the recorded masses. No device is involved: the port, if any, "
            "is held at the excitation's initial displacement x0 (so a plucking port starts "
            "pressed into the string); a scene with several ports (devices:) closes each "
            "port through its own device model instead (below). Links given as a felt target {k, b} are first "
            "calibrated for the scene's device, as hapsim run does, and the (K, B) used are "
            "printed."),
        epilog=(
            "output:\n"
            "  time [s] shape (N+1,), position [m] shape (N+1, R), names shape (R,);\n"
            "  row 0 is the initial state at t = 0, row i the state after i samples.\n"
            "  .npz holds the three arrays; .csv has a header 'time,<name>,...'.\n"
            "sound (a scene with an audio section):\n"
            "  --audio FILE.wav renders the listening points (16-bit PCM, one channel each, at\n"
            "  audio.rate_hz). --gesture excitation (default) plays the scene's excitation on\n"
            "  the mock device closed on the scene (the hand's impulse/profile pushes the handle\n"
            "  into the string, the contact throws it back); --gesture FILE drives the port\n"
            "  along a recorded position profile (time [s], position [m]; .csv or .npz).\n"
            "  A 2-D or 3-D scene is heard at its own rate_hz (its audio.listen points name\n"
            "  a mass, an axis and position or velocity; a port is held at rest).\n"
            "several ports (a devices: scene, docs/ports.md):\n"
            "  each port is closed through its own device model, the lockstep run's (mass,\n"
            "  friction, delay, zero-order hold, force_limit); --x0 PORT=M and --v0 PORT=M/S\n"
            "  start a port displaced or moving (default: at rest). .npz: time, position\n"
            "  (N+1, R, 1), names, and ports (P,), port_position [m] and port_force [N]\n"
            "  (N+1, P): the force each device took at each sample.\n"
            "examples:\n"
            "  hapsim simulate configs/string.yaml --steps 2000 --out string.npz --record s25 s10\n"
            "  hapsim simulate configs/audio_string.yaml --steps 2000 --audio pluck.wav\n"
            "  hapsim simulate configs/membrane.yaml --steps 88200 --audio drum.wav\n"
            "  hapsim simulate configs/two_faders.yaml -n 2000 --x0 fader_a=0.004 --out faders.npz"),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="YAML scene file")
    p.add_argument("--steps", "-n", type=Number(int, low=0), required=True, metavar="N",
                   help="number of samples to simulate (>= 0; 2e4 is read as 20000)")
    p.add_argument("--out", "-o", metavar="FILE",
                   help="output file, .npz or .csv (format chosen by extension); required "
                        "unless --audio is given")
    p.add_argument("--audio", metavar="FILE.wav",
                   help="write the scene's sound (its audio.listen points) to this WAV file")
    p.add_argument("--gesture", default="excitation", metavar="excitation|FILE",
                   help="with --audio: the scene's excitation on the mock device (default) "
                        "or a position profile file for the port (time [s], position [m])")
    p.add_argument("--record", nargs="+", metavar="NAME",
                   help="masses to record, in this order (default: all)")
    p.add_argument("--x0", action="append", metavar="PORT=M",
                   help="a scene with several ports: this port's initial displacement [m] "
                        "(repeat per port; default 0)")
    p.add_argument("--v0", action="append", metavar="PORT=M/S",
                   help="a scene with several ports: this port's initial velocity [m/s] "
                        "(repeat per port; default 0)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``hapsim simulate``.

    The trajectory is :func:`hapsim.api.simulate`'s (a 2-D or 3-D scene: :func:`_run_nd`;
    several ports: :func:`_run_ports`).

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options: ``scene`` (path), ``steps`` (N >= 0), ``out`` (``.npz`` or
        ``.csv``), ``record`` (mass names or None for all), ``x0``/``v0`` (several ports'
        ``PORT=VALUE`` items, refused otherwise), ``json`` (bool).

    Returns
    -------
    int
        0, or 1 when a position becomes NaN or infinite (the scene diverged): the rows
        before it are written and the step and the mass are named; the trajectory is
        written to ``args.out`` (time [s] shape (N+1,), position [m]
        shape (N+1, R), names shape (R,)) and a summary printed (one JSON object with
        ``--json``, including ``calibrations``: one dict per target link, see
        :meth:`hapsim.analysis.targets.TargetCalibration.to_dict`).

    Raises
    ------
    ConfigError
        Unknown output extension (key ``--out``), negative ``--steps``, an unknown mass
        in ``--record`` (key ``--record``, with the valid names), an invalid scene file
        (file, line, key), ``--x0``/``--v0`` on a scene without several ports, or a
        target no (K, B) renders (:class:`~hapsim.errors.UnrenderableTargetError`, key
        ``links.NAME.target``).
    """
    from hapsim.blas import preload_numba_blas
    from hapsim.scene import load_scene, scene_dimension, scene_has_ports
    if scene_has_ports(args.scene):            # several ports, each its own device
        return _run_ports(args)
    for opt in ("x0", "v0"):
        if getattr(args, opt, None):
            raise ConfigError(f"names a port of a scene with several ports (devices:); a "
                              f"one-port, 2-D or 3-D scene's port starts at its excitation's "
                              f"{opt} (the scene file)", key=f"--{opt}")
    preload_numba_blas()                # before numba's first kernel (hapsim.blas)
    if scene_dimension(args.scene) > 1:        # a 2-D or 3-D scene: the n-D engine
        return _run_nd(args)
    if args.audio is not None:
        return _run_audio(args)
    if args.out is None:
        raise ConfigError("give an output file (--out FILE.npz|.csv) or --audio FILE.wav",
                          key="--out")
    ext = os.path.splitext(args.out)[1].lower()
    if ext not in (".npz", ".csv"):
        raise ConfigError(f"unknown output format {ext or '(none)'!r}; valid: .npz, .csv",
                          key="--out")
    check_writable(args.out, "--out")
    # what the command line asks is refused before the engine is compiled (seconds on a
    # first run): the columns (the engine's names are the scene's masses, in order) and
    # the memory they need
    from hapsim.api.simulating import line_columns, simulate   # the engine, port at x0
    scene, calibrations, names = line_columns(load_scene(args.scene), args.steps,
                                              args.record, ("--record", "--steps"))
    _announce_compilation(scene)
    t0 = time.perf_counter()
    try:
        with Progress(args.steps, "simulate", unit="samples") as bar:
            rep = simulate(scene, args.steps, record=names, progress=bar.update)
    except ConfigError as exc:
        if exc.key != "record":
            raise
        # the names came from the command line, not from the scene file
        raise ConfigError(exc.reason, key="--record") from None
    elapsed = time.perf_counter() - t0
    t, x, bad = rep.time, rep.position, rep.diverged
    if bad is not None:
        bad = (bad["step"], bad["mass"], bad["recorded"])
    write_trajectory(args.out, t, x, names)
    if bad is not None:
        step, mass, recorded = bad
        message = (f"hapsim simulate: the scene diverged: the position of mass {mass!r}"
                   f"{'' if recorded else ' (not recorded)'} is not finite "
                   f"{'at' if recorded else 'by'} step {step} (t = {step / scene.rate_hz:.6g} s); stopped "
                   f"there and wrote the {step} rows before it (t < {step / scene.rate_hz:.6g} s) "
                   f"to {args.out}")
        print(message, file=sys.stderr)
        if args.json:
            summary = {"scene": args.scene, "out": args.out, "steps": step,
                       "rate_hz": scene.rate_hz, "recorded": len(names),
                       "diverged": {"step": step, "mass": mass}, "exit": 1}
            print(json.dumps(summary))
        return 1
    summary = {"scene": args.scene, "out": args.out, "steps": args.steps,
               "rate_hz": scene.rate_hz, "recorded": len(names), "seconds": elapsed,
               "calibrations": [c.to_dict() for c in calibrations]}
    if args.json:
        print(json.dumps(summary))
    else:
        for c in calibrations:
            print(f"calibrated link {c.link}: felt k = {c.k:g} N/m, b = {c.b:g} N s/m -> "
                  f"virtual K = {c.result.K:.6g} N/m, B = {c.result.B:.6g} N s/m")
        print(f"wrote {args.out}: {args.steps} samples x {len(names)} masses "
              f"({args.steps / scene.rate_hz:g} s simulated in {elapsed:.3f} s)")
    return 0


def _announce_compilation(scene) -> None:
    """With numba's cache empty, say on stderr that the engine's kernel is compiled (once)
    before the silence it costs (:mod:`hapsim.pipeline.startup`)."""
    from hapsim.pipeline import startup
    startup.reset_announcements()
    startup.announce_compilation(startup.run_compile_parts(scene, compiled_loop=False),
                                 scene=scene, command="hapsim simulate")


def _write_sound(args, audio, rate_hz: float) -> dict:
    """Write ``--audio``'s WAV (:func:`hapsim.audio.offline.write_wav`'s summary); a sound
    that diverged raises :class:`HapsimError` (exit 1, cli's line and ``--json`` object),
    nothing written."""
    from hapsim.audio.offline import write_wav
    try:
        return write_wav(args.audio, audio, rate_hz)
    except ValueError as exc:
        raise HapsimError(f"{exc}; nothing written (hapsim check {args.scene})") from None


def _run_audio(args: argparse.Namespace) -> int:
    """``simulate --audio``: render a gesture through the multi-rate scene to a WAV file
    (and the device trajectory to ``--out`` when given). Exit 0, 1 when the sound
    diverged (an unstable scene), 2 on bad input."""
    import numpy as np
    from hapsim.audio.offline import closed_loop_pluck, load_gesture, open_loop_gesture
    from hapsim.engine import Engine
    from hapsim.scene import load_scene

    if not args.audio.lower().endswith(".wav"):
        raise ConfigError(f"the sound file must end in .wav, got {args.audio!r}", key="--audio")
    check_writable(args.audio, "--audio")       # (before the work: it failed after it)
    if args.out is not None and os.path.splitext(args.out)[1].lower() not in (".npz", ".csv"):
        raise ConfigError("unknown output format; valid: .npz, .csv", key="--out")
    scene = load_scene(args.scene)
    if scene.audio is None or scene.port is None:
        raise ConfigError("the scene needs an audio section (rate_hz, listen) and a port to "
                          "be heard; see configs/audio_string.yaml", file=scene.path,
                          key="audio")
    calibrations = []
    if scene.unresolved_targets:
        from hapsim.analysis.targets import apply_targets
        scene, calibrations = apply_targets(scene)
    _announce_compilation(scene)
    engine = Engine(scene)
    t0 = time.perf_counter()
    with Progress(args.steps, "simulate", unit="samples") as bar:
        if args.gesture == "excitation":
            audio, xs, fs = closed_loop_pluck(engine, args.steps, progress=bar.update)
        else:
            xs = load_gesture(args.gesture, scene.rate_hz, args.steps)
            audio, fs = open_loop_gesture(engine, xs, progress=bar.update)
    elapsed = time.perf_counter() - t0
    info = _write_sound(args, audio, scene.audio.rate_hz)
    if args.out is not None:
        T = scene.period
        write_trajectory(args.out, np.arange(args.steps) * T,
                         np.column_stack([xs, fs]), ["port.position", "port.force"])
    summary = {"scene": args.scene, "audio": args.audio, "gesture": args.gesture,
               "steps": args.steps, "rate_hz": scene.rate_hz, "substeps": engine.substeps,
               "listen": list(engine.channels), "seconds": elapsed,
               "audio_rate_hz": info["rate_hz"], "frames": info["frames"],
               "peak": info["peak"], "clipped": info["clipped"],
               "calibrations": [c.to_dict() for c in calibrations]}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.audio}: {info['frames']} frames x {info['channels']} channel(s) at "
              f"{info['rate_hz']} Hz ({', '.join(engine.channels)}), peak {info['peak']:.3g}"
              + (f", {info['clipped']} samples clipped: lower the gain" if info["clipped"] else "")
              + f" ({args.steps / scene.rate_hz:g} s simulated in {elapsed:.3f} s)")
    return 0


def write_trajectory(path: str, time_s: np.ndarray, position: np.ndarray, names: list[str]) -> None:
    """Write a trajectory atomically (``path.partial``, then renamed to ``path``).

    Parameters
    ----------
    path : str
        ``.npz`` or ``.csv`` file.
    time_s : ndarray, shape (N+1,)
        Time [s].
    position : ndarray, shape (N+1, R)
        Positions [m].
    names : list of str, length R
        Recorded mass names.
    """
    import numpy as np

    from hapsim.outputs import atomic_write
    with atomic_write(path, "wb", "--out") as fh:      # (a failure leaves no .partial)
        if path.lower().endswith(".npz"):
            np.savez(fh, time=time_s, position=position, names=np.array(names))
        else:
            np.savetxt(fh, np.column_stack([time_s, position]), delimiter=",",
                       header=",".join(["time"] + names), comments="", fmt="%.17g")


# ------------------------------------------------- a 2-D or 3-D scene
def _run_nd(args) -> int:
    """Simulate an n-D scene (``dimension: 2`` or ``3``; :func:`hapsim.scene.load_scene_nd`).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``steps``, ``out`` (``.npz``), ``record``, ``json``, ``audio`` (a
        ``.wav`` path: the scene's ``audio`` listening points instead of a trajectory,
        :func:`hapsim.audio.offline.render_nd`).

    Returns
    -------
    int
        0, or 1 when a position becomes NaN or infinite (the rows before it are written).
        The ``.npz`` holds ``time`` [s] shape (N+1,), ``position`` [m] shape (N+1, R, n)
        and ``names`` shape (R,); row 0 is the initial state. The port (if any) is held at
        its rest position, the device's handle position (no device is simulated; the
        closed loop is :class:`hapsim.lockstep.LockstepND`).

    Raises
    ------
    ConfigError
        An output that is not ``.npz`` (``.wav`` with ``--audio``), a scene without an
        ``audio`` section with ``--audio``, negative ``--steps``, an unknown or repeated
        ``--record`` name, an invalid scene (file, line, key).
    """
    import numpy as np
    from hapsim.outputs import check_writable
    from hapsim.progress import Progress
    from hapsim.scene import load_scene_nd
    if args.audio is not None:
        return _run_audio_nd(args)
    if args.out is None:
        raise ConfigError("give an output file (--out FILE.npz: a 2-D or 3-D trajectory, "
                          "time, position (N+1, R, n), names) or --audio FILE.wav",
                          key="--out")
    if os.path.splitext(args.out)[1].lower() != ".npz":
        raise ConfigError(f"a 2-D or 3-D trajectory is written as .npz (time, position "
                          f"(N+1, R, n), names), got {args.out!r}", key="--out")
    check_writable(args.out, "--out")
    scene = load_scene_nd(args.scene)
    from hapsim.api.simulating import simulate     # the engine, its port held at rest
    t0 = time.perf_counter()
    try:
        with Progress(args.steps, "simulate", unit="samples") as bar:
            rep = simulate(scene, args.steps, record=args.record, progress=bar.update)
    except ConfigError as exc:
        if exc.key not in ("record", "steps"):
            raise
        raise ConfigError(exc.reason, key=f"--{exc.key}") from None
    elapsed = time.perf_counter() - t0
    names, n = rep.names, scene.dimension
    bad = None if rep.diverged is None else rep.diverged["step"]
    np.savez(args.out, time=rep.time, position=rep.position, names=np.array(names))
    summary = {"scene": args.scene, "out": args.out, "dimension": n,
               "steps": args.steps if bad is None else bad, "rate_hz": scene.rate_hz,
               "recorded": len(names), "seconds": elapsed}
    if bad is not None:
        summary["diverged"] = {"step": bad}
    return _outcome(args, summary, None if bad is None else (
        f"hapsim simulate: the scene diverged: a position is not finite at step {bad} "
        f"(t = {bad / scene.rate_hz:.6g} s); wrote the {bad} rows before it to "
        f"{args.out}"),
        f"wrote {args.out}: {args.steps} samples x {len(names)} masses x {n} axes "
        f"({args.steps / scene.rate_hz:g} s simulated in {elapsed:.3f} s)")


def _outcome(args, summary: dict, diverged: str | None, written: str) -> int:
    """Say how a trajectory ended: ``diverged`` (the message, or None) on stderr, with
    ``exit: 1`` added to ``summary``; then the summary as one JSON object with ``--json``,
    else ``written`` when it did not diverge. Returns the exit code (0, or 1 diverged)."""
    if diverged is not None:
        summary["exit"] = 1
        print(diverged, file=sys.stderr)
    if args.json:
        print(json.dumps(summary))
    elif diverged is None:
        print(written)
    return 0 if diverged is None else 1


def _run_audio_nd(args) -> int:
    """``simulate --audio`` on an n-D scene: its listening points to a WAV file."""
    from hapsim.audio.offline import render_nd
    from hapsim.engine import Engine
    from hapsim.outputs import check_writable
    from hapsim.progress import Progress
    from hapsim.scene import load_scene_nd
    if not args.audio.lower().endswith(".wav"):
        raise ConfigError(f"the sound file must end in .wav, got {args.audio!r}",
                          key="--audio")
    if getattr(args, "gesture", "excitation") != "excitation":
        raise ConfigError("a 2-D or 3-D scene is heard from its initial state (no gesture "
                          "drives its port yet): leave --gesture out", key="--gesture")
    for opt, val in (("--out", args.out), ("--record", args.record)):
        if val:
            raise ConfigError(f"--audio writes the sound only: {opt} is not taken with it",
                              key=opt)
    check_writable(args.audio, "--audio")
    scene = load_scene_nd(args.scene)
    if not scene.audio:
        raise ConfigError("the scene needs an audio section (listen: [{mass, axis, "
                          "quantity, gain}]) to be heard; see configs/membrane.yaml",
                          file=scene.path, key="audio")
    if scene.rate_hz != int(scene.rate_hz):
        raise ConfigError(f"a sound's rate is a whole number of Hz, got {scene.rate_hz:g}",
                          file=scene.path, key="rate_hz")
    t0 = time.perf_counter()
    with Progress(args.steps, "simulate", unit="samples") as bar:
        audio = render_nd(Engine(scene), args.steps, progress=bar.update)
    elapsed = time.perf_counter() - t0
    info = _write_sound(args, audio, scene.rate_hz)
    summary = {"scene": args.scene, "audio": args.audio, "dimension": scene.dimension,
               "steps": args.steps, "rate_hz": scene.rate_hz, "frames": info["frames"],
               "channels": info["channels"], "peak": info["peak"],
               "clipped": info["clipped"], "seconds": elapsed}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.audio}: {info['frames']} frames x {info['channels']} "
              f"channel(s) at {scene.rate_hz:g} Hz, peak {info['peak']:.3g}"
              + (f", {info['clipped']} samples clipped" if info["clipped"] else "")
              + f" ({elapsed:.2f} s)")
    return 0


# ------------------------------------------------- a scene with several ports
def _port_values(given, flag: str) -> dict:
    """``--x0``/``--v0``'s ``PORT=VALUE`` items as a mapping (each port once)."""
    out = {}
    for item in given or ():
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ConfigError(f"give PORT=VALUE, got {item!r}", key=flag)
        if name in out:
            raise ConfigError(f"names port {name!r} twice; each once", key=flag)
        out[name] = value
    return out


def _run_ports(args) -> int:
    """Simulate a scene with several ports (``devices:``; :func:`hapsim.api.simulate`),
    each port closed through its own device model.

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``steps``, ``out`` (``.npz``), ``record``, ``x0``/``v0`` (``PORT=VALUE``
        items), ``json``; ``audio`` and ``gesture`` refused.

    Returns
    -------
    int
        0, or 1 when a port's position becomes non-finite (an unstable loop without a
        force limit; the rows before it are written). The ``.npz`` holds ``time`` [s]
        (N+1,), ``position`` [m] (N+1, R, 1), ``names`` (R,), ``ports`` (P,),
        ``port_position`` [m] and ``port_force`` [N] (N+1, P).

    Raises
    ------
    ConfigError
        ``--audio`` or ``--gesture`` (no sound of several ports), an output that is not
        ``.npz``, an unknown or repeated ``--record`` name or ``--x0``/``--v0`` port, a
        value that is not a finite number, an invalid scene (file, line, key).
    """
    import numpy as np
    from hapsim.api.simulating import simulate
    from hapsim.scene import load_scene_ports
    if args.audio is not None or args.gesture != "excitation":
        flag = "--audio" if args.audio is not None else "--gesture"
        raise ConfigError("a scene with several ports has no sound: its reader takes no "
                          "audio: section and no virtual mass to hear (the ports couple "
                          "through spring-dampers only); --out FILE.npz gives the ports' "
                          "motion", key=flag)
    if args.out is None or os.path.splitext(args.out)[1].lower() != ".npz":
        raise ConfigError(f"a scene with several ports is written as .npz (time, position "
                          f"(N+1, R, 1), names, ports, port_position, port_force), got "
                          f"{args.out!r}", key="--out")
    check_writable(args.out, "--out")
    scene = load_scene_ports(args.scene)
    x0, v0 = _port_values(args.x0, "--x0"), _port_values(args.v0, "--v0")
    t0 = time.perf_counter()
    try:
        with Progress(args.steps, "simulate", unit="samples") as bar:
            rep = simulate(scene, args.steps, record=args.record, x0=x0, v0=v0,
                           progress=bar.update)
    except ConfigError as exc:
        if exc.key not in ("record", "x0", "v0"):
            raise
        raise ConfigError(exc.reason, key=f"--{exc.key}") from None
    elapsed = time.perf_counter() - t0
    from hapsim.outputs import atomic_write
    with atomic_write(args.out, "wb", "--out") as fh:
        np.savez(fh, time=rep.time, position=rep.position, names=np.array(rep.names),
                 ports=np.array(rep.ports), port_position=rep.port_position,
                 port_force=rep.port_force)
    summary = {**rep.to_dict(), "out": args.out, "seconds": elapsed}
    bad = rep.diverged
    return _outcome(args, summary, None if bad is None else (
        f"hapsim simulate: the loop diverged: port {bad['port']!r}'s position is not "
        f"finite at step {bad['step']} (t = {bad['step'] / scene.rate_hz:.6g} s; "
        f"hapsim check {args.scene}); wrote the {bad['step']} rows before it to "
        f"{args.out}"),
        f"wrote {args.out}: {args.steps} samples x {len(rep.names)} masses, "
        f"{len(rep.ports)} ports each closed through its own device (delays "
        f"{', '.join(f'{d:g}' for d in rep.delays)}; {args.steps / scene.rate_hz:g} s "
        f"simulated in {elapsed:.3f} s)")
