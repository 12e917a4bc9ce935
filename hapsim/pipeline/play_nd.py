"""``hapsim play`` on a 2-D or 3-D scene with an ``audio`` section: its sound, live,
felt through its device's model, changed over OSC while it plays.

The scene runs from its initial state (a struck membrane rings) and its listening points
go out through JACK (or PortAudio) as they are computed
(:class:`hapsim.audio.live_nd.LiveND`): without changes, the frames played are the ones
``hapsim simulate SCENE --audio F.wav`` writes, paced by the sound card's clock; xruns
(the server's count) and underruns (frames of silence because the producer was late) are
counted and reported. A scene with a port and a device is closed on the device's model
at the scene's rate (the loop ``hapsim check`` analyses); its ``excitation`` (a force on
the device's mass along the scene's direction) plucks it, again every ``--pluck-every``
seconds. ``--osc PORT`` serves the 1-D play's addresses
(:mod:`hapsim.audio.control_nd`): every change is checked by the MIMO criterion before it
is accepted and ramped over ``--ramp`` seconds, sample by sample.
"""

from __future__ import annotations

import sys
import time

import numpy as np


from hapsim.errors import ConfigError

#: ``hapsim play`` options (argparse destinations) a 2-D or 3-D scene's play takes.
TAKES = frozenset({"scene", "duration", "sound", "jack_server", "rt_priority", "json", "osc", "view",
                   "ramp", "pluck_every", "journal"})
#: Options it refuses when given other than their defaults (destination, flag, default).
_REFUSED = (("lockstep", "--lockstep", False), ("telemetry", "--telemetry", None))


def refuse_untaken(args) -> None:
    """Refuse the ``hapsim play`` options an n-D scene's play does not take.

    Parameters
    ----------
    args : argparse.Namespace

    Raises
    ------
    ConfigError
        Naming the first such option given, and the ones taken (exit 2); ``--sound none``
        (an n-D scene's play is its sound).
    """
    takes = ", ".join("--" + d.replace("_", "-") for d in sorted(TAKES - {"scene"}))
    for dest, flag, default in _REFUSED:
        v = getattr(args, dest, default)
        if v is not None and v != default:
            raise ConfigError(f"a 2-D or 3-D scene's play does not take {flag} (its loop "
                              f"runs in the sound's producer, paced by the sound card; it "
                              f"takes {takes})", key=flag)
    if getattr(args, "sound", "auto") == "none":
        raise ConfigError("a 2-D or 3-D scene's play is its sound: --sound auto, jack or "
                          "sounddevice ('hapsim simulate SCENE --audio F.wav' renders it "
                          "offline)", key="--sound")


def hand_of(scene, pluck_every: float):
    """The hand's force profile, direction and pluck period of an n-D scene's play.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
    pluck_every : float
        ``--pluck-every`` [s] (0: once).

    Returns
    -------
    hand : ndarray, shape (H,), or None
        One force per sample [N] (:func:`hapsim.device_model.hand_force_samples`), None
        without an excitation.
    direction : ndarray, shape (n,), or None
    every : int
        Pluck period [samples] (0: once).

    Raises
    ------
    ConfigError
        ``--pluck-every`` on a scene without an excitation (or without a port).
    """
    import os

    from hapsim.device_model import hand_force_samples
    exc = getattr(scene, "excitation", None)
    every = int(round(pluck_every * scene.rate_hz)) if pluck_every > 0 else 0
    if exc is None:
        if every:
            raise ConfigError("--pluck-every repeats the scene's excitation, and this scene "
                              "has none (excitation: {direction: [..], impulse: {force, "
                              "start, duration}} on a scene with a port and a device)",
                              file=scene.path, key="excitation")
        return None, None, 0
    base = os.path.dirname(os.path.abspath(scene.path))
    return hand_force_samples(exc, scene.period, base), exc.direction, every


def play_nd_report(args, stop, scene=None) -> tuple[int, dict]:
    """Play an n-D scene live (module notes); ``hapsim play``'s report, not printed.

    Parameters
    ----------
    args : argparse.Namespace or types.SimpleNamespace
        ``hapsim play``'s options (``scene``, ``duration`` [s], ``sound``,
        ``jack_server``, ``rt_priority``, ``osc``, ``view``, ``ramp`` [s],
        ``pluck_every`` [s], ``journal``).
    stop : hapsim.host.loop_types.StopFlag
        Set by SIGINT/SIGTERM or the view's stop button: ends the play at the next chunk.
    scene : hapsim.scene_nd.SceneND, optional
        The scene already loaded (default: read from ``args.scene``).

    Returns
    -------
    code : int
        0 (after the play, also when stopped early).
    report : dict
        ``hapsim play --json``'s object (``dof``, ``frames``, ``stop_reason``, ``sound``,
        with a checked loop ``felt``, ``journal``, ...).

    Raises
    ------
    ConfigError
        An option not taken; a scene without an ``audio`` section; ``--pluck-every``
        without an excitation; ``--osc`` on a scene too large to check (exit 2).
    UnstableConfigError
        The scene's loop (or, without a port, the scene alone) is unstable: refused
        before playing (``before_play`` True; ``hapsim play`` exits 1).
    DeviceError
        No sound output opens: refused before playing (``before_play`` True; exit 1).
    """
    from hapsim.errors import UnstableConfigError
    from hapsim.audio.osc import send_telemetry, serve_osc
    from hapsim.audio.control_nd import ControllerND
    from hapsim.audio.live import open_output, wait_priority
    from hapsim.audio.live_nd import LiveND
    from hapsim.host.loop_types import signame
    from hapsim.host.realtime import RealtimePriority
    from hapsim.engine_nd import EngineND
    from hapsim.errors import DeviceError
    from hapsim.scene_nd import load_scene_nd
    refuse_untaken(args)
    if scene is None:
        scene = load_scene_nd(args.scene)
    if not scene.audio:
        raise ConfigError("the scene has no audio section (listen: [{mass, axis, quantity, "
                          "gain}]): nothing to play; see configs/membrane.yaml",
                          file=scene.path, key="audio")
    hand, direction, every = hand_of(scene, getattr(args, "pluck_every", 0.0) or 0.0)
    engine = EngineND(scene)
    ctl = None
    note = None
    try:
        ctl = ControllerND(scene, engine, ramp_s=getattr(args, "ramp", 0.05),
                           background=getattr(args, "osc", None) is not None
                           or getattr(args, "view", None) is not None)
    except ConfigError as exc:
        if getattr(args, "osc", None) is not None:
            raise ConfigError(f"--osc checks every change on the scene's loop, and this "
                              f"scene cannot be analysed: {exc}", file=scene.path,
                              key="--osc") from None
        note = f"the loop was not checked before playing: {exc}"
    if ctl is not None and not ctl.felt["stable"]:
        ctl.close()
        exc = UnstableConfigError(
            f"the {'closed loop' if ctl.felt['loop'] == 'closed' else 'scene'} of "
            f"{args.scene} is unstable (spectral radius "
            f"{ctl.felt['spectral_radius']:.6g}); see hapsim check",
            spectral_radius=ctl.felt["spectral_radius"])
        exc.before_play = True
        raise exc
    live = LiveND(engine, hand=hand, direction=direction, every=every, control=ctl)
    if ctl is not None:
        ctl.live = live
        ctl.sample_of = lambda: live.written
    total = int(round(args.duration * scene.rate_hz))
    live.produce(0)                   # the compiled kernels loaded before the sound starts
    live.run(min(total, live.ahead))  # the first frames ready before the callback reads
    try:
        out = open_output(live.ring, args.sound, server=args.jack_server)
    except DeviceError as exc:
        if ctl is not None:
            ctl.close()
        exc.before_play = True
        raise
    server = tel = None
    if getattr(args, "osc", None) is not None:
        server, tel = serve_osc(ctl, args.osc, status=lambda: {
            "xruns": out.xruns, "underruns": live.stats()["underruns"]})
        host, port = server.server_address[:2]
        print(f"hapsim play: OSC on {host}:{port}", file=sys.stderr, flush=True)
    T = scene.period
    last = [0]
    view = None
    if getattr(args, "view", None) is not None:
        from hapsim.view import ChunkSource, start_view
        src = ChunkSource(scene, engine, ctl)
        try:
            view = start_view(src, ctl, stop, args.view, "play")
        except BaseException:
            if server is not None:
                server.shutdown()
                server.server_close()
            out.close()
            if ctl is not None:
                ctl.close()
            raise

    def on_chunk(lv):
        if ctl is not None:
            ctl.sample = lv.written
        if view is not None:                    # a bounded deque: never waits
            if lv.closed:
                src.push(lv.written - 1, lv.port_position(), lv.port_force())
            else:                               # a free scene: its listened mass
                src.push(lv.written - 1, src.probe(), np.zeros(scene.dimension))
        if tel is not None and tel["client"] is not None \
                and lv.written // tel["every"] != last[0]:
            last[0] = lv.written // tel["every"]
            send_telemetry(tel, lv.written * T, lv.port_position(), lv.port_force(), ctl)
    # just below the callback's thread (the producer feeds it), as the 1-D play
    ap = wait_priority(out)
    prio = 10 if args.rt_priority is None else args.rt_priority
    if ap:
        prio = max(0, min(prio, ap - 1))
    rt = RealtimePriority(prio)
    t0 = time.monotonic()
    stop_reason = "duration"
    try:
        with rt:
            done = live.run(total, stop, on_chunk=on_chunk if server is not None
                            or view is not None else None)
        if done < total:
            stop_reason = (f"signal {signame(stop.signal)}" if stop.signal is not None
                           or stop.reason is None else stop.reason)
        live.finish()
    except BaseException:     # a KeyboardInterrupt in a caller that left SIGINT as it is
        if view is not None:  # (hapsim.api.play): the view's server closed too
            view.close()
        raise
    finally:
        if server is not None:
            server.shutdown()
            server.server_close()
        out.finish()
        out.close()
        if ctl is not None:
            ctl.finish(0.0)
            ctl.close()
    st = live.stats()
    report = {"scene": scene.path, "dof": scene.dimension, "rate_hz": scene.rate_hz,
              "frames": st["written"], "seconds": st["written"] / scene.rate_hz,
              "wall_s": round(time.monotonic() - t0, 3), "stop_reason": stop_reason,
              "scheduling": rt.note, "note": note,
              "loop": "closed" if live.closed else "free",
              "delay": int(scene.device.delay) if live.closed else None,
              "plucks": ({"every_samples": every, "samples": int(hand.size),
                          "direction": [float(v) for v in direction]}
                         if hand is not None else None),
              "sound": {"backend": type(out).__name__, "callback": out.callback,
                        "block": out.blocksize, "channels": list(live.ring.channels),
                        "xruns": out.xruns, "xrun_at_s": list(out.xrun_at), **st}}
    if ctl is not None:
        sc = ctl.scene
        report.update({"accepted": ctl.accepted, "refused": ctl.refused, "felt": ctl.felt,
                       "links": {e.name: [e.stiffness, e.damping]
                                 for e in (*sc.links, *sc.planes)},
                       "masses": {m.name: m.mass for m in sc.masses if m.kind == "mass"},
                       "journal": ctl.journal})
        if getattr(args, "journal", None):
            from hapsim.audio.journal import write_journal
            write_journal(args.journal, ctl.journal)
    if view is not None:
        view.finish(report)
    return 0, report


def play_nd_text(report: dict) -> str:
    """The text report ``hapsim play`` prints of a 2-D or 3-D play (without ``--json``).

    Parameters
    ----------
    report : dict
        :func:`play_nd_report`'s report.

    Returns
    -------
    str
        Two or three lines, no trailing newline.
    """
    s, st = report["sound"], report["sound"]
    lines = [f"played {report['scene']} ({report['dof']}-D, loop {report['loop']}) for "
             f"{report['seconds']:g} s ({report['frames']} frames at {report['rate_hz']:g} Hz)"
             + ("" if report["stop_reason"] == "duration"
                else f"; stopped by {report['stop_reason']}")]
    if "felt" in report:
        lines.append(f"{report['accepted']} changes accepted, {report['refused']} refused; "
                     f"spectral radius now {report['felt']['spectral_radius']:.6g}")
    lines.append(f"sound: {s['backend']} ({s['callback']} callback), block {s['block']} "
                 f"frames, {st['ahead']} frames ahead; xruns {s['xruns']}, underruns "
                 f"{st['underruns']} frames, skipped {st['skipped']}")
    return "\n".join(lines)
