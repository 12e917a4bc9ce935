"""``hapsim play`` on a 2-D or 3-D scene with an ``audio`` section: its sound, live.

The scene runs from its initial state (a struck membrane rings) and its listening points
go out through JACK (or PortAudio) as they are computed
(:class:`hapsim.audio.live_nd.LiveND`): the frames played are the ones ``hapsim simulate
SCENE --audio F.wav`` writes, paced by the sound card's clock; xruns (the server's count)
and underruns (frames of silence because the producer was late) are counted and reported.
An n-D scene is not played by a hand or changed over OSC (yet): those options are refused
by name.
"""

from __future__ import annotations

import json
import sys
import time

from hapsim.errors import ConfigError

#: ``hapsim play`` options (argparse destinations) a 2-D or 3-D scene's play takes.
TAKES = frozenset({"scene", "duration", "sound", "jack_server", "rt_priority", "json"})
#: Options it refuses when given other than their defaults (destination, flag, default).
_REFUSED = (("osc", "--osc", None), ("ramp", "--ramp", 0.05),
            ("pluck_every", "--pluck-every", 0.0), ("lockstep", "--lockstep", False),
            ("journal", "--journal", None), ("telemetry", "--telemetry", None))


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
            raise ConfigError(f"a 2-D or 3-D scene's play does not take {flag} (it plays "
                              f"the scene's sound from its initial state; it takes {takes})",
                              key=flag)
    if getattr(args, "sound", "auto") == "none":
        raise ConfigError("a 2-D or 3-D scene's play is its sound: --sound auto, jack or "
                          "sounddevice ('hapsim simulate SCENE --audio F.wav' renders it "
                          "offline)", key="--sound")


def play_nd(args, stop) -> int:
    """Play an n-D scene's sound live (module notes).

    Parameters
    ----------
    args : argparse.Namespace
        ``hapsim play``'s options (``scene``, ``duration`` [s], ``sound``,
        ``jack_server``, ``rt_priority``, ``json``).
    stop : hapsim.daemon.loop_types.StopFlag
        Set by SIGINT/SIGTERM: ends the play at the next chunk.

    Returns
    -------
    int
        0 after the play (also when a signal ended it); 1 when no sound output opens.

    Raises
    ------
    ConfigError
        An option not taken; a scene without an ``audio`` section (exit 2).
    """
    from hapsim.audio.live import open_output, wait_priority
    from hapsim.audio.live_nd import LiveND
    from hapsim.daemon.loop_types import signame
    from hapsim.daemon.realtime import RealtimePriority
    from hapsim.engine_nd import EngineND
    from hapsim.errors import DeviceError
    from hapsim.scene_nd import load_scene_nd
    refuse_untaken(args)
    scene = load_scene_nd(args.scene)
    if not scene.audio:
        raise ConfigError("the scene has no audio section (listen: [{mass, axis, quantity, "
                          "gain}]): nothing to play; see configs/membrane.yaml",
                          file=scene.path, key="audio")
    live = LiveND(EngineND(scene))
    total = int(round(args.duration * scene.rate_hz))
    live.produce(0)                   # the compiled kernels loaded before the sound starts
    live.run(min(total, live.ahead))  # the first frames ready before the callback reads
    try:
        out = open_output(live.ring, args.sound, server=args.jack_server)
    except DeviceError as exc:
        print(f"hapsim play: {exc}", file=sys.stderr)
        return 1
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
            done = live.run(total, stop)
        if done < total:
            stop_reason = f"signal {signame(stop.signal)}"
        live.finish()
    finally:
        out.finish()
        out.close()
    st = live.stats()
    report = {"scene": scene.path, "dof": scene.dimension, "rate_hz": scene.rate_hz,
              "frames": st["written"], "seconds": st["written"] / scene.rate_hz,
              "wall_s": round(time.monotonic() - t0, 3), "stop_reason": stop_reason,
              "scheduling": rt.note,
              "sound": {"backend": type(out).__name__, "callback": out.callback,
                        "block": out.blocksize, "channels": list(live.ring.channels),
                        "xruns": out.xruns, "xrun_at_s": list(out.xrun_at), **st}}
    if args.json:
        print(json.dumps(report))
        return 0
    s = report["sound"]
    print(f"played {scene.path} ({scene.dimension}-D) for {report['seconds']:g} s "
          f"({st['written']} frames at {scene.rate_hz:g} Hz)"
          + ("" if stop_reason == "duration" else f"; stopped by {stop_reason}"))
    print(f"sound: {s['backend']} ({s['callback']} callback), block {s['block']} frames, "
          f"{st['ahead']} frames ahead; xruns {s['xruns']}, underruns {st['underruns']} "
          f"frames, skipped {st['skipped']}")
    return 0
