"""``hapsim play``: play a scene live: sound out, changes in over OSC, the mock hand plucking."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from hapsim.outputs import json_safe
from hapsim.option_values import Number

_DESCRIPTION = """\
Play a scene live, as an instrument: the embedded mock device (the scene's device section)
is closed on the scene at the device rate in real time, its hand plucking with the scene's
excitation (again every --pluck-every seconds); the sound of the scene's audio section goes
out through JACK (or PortAudio); an OSC server (--osc PORT, localhost) takes changes from
Pd, Max or SuperCollider while it plays. Every change is checked before it is applied (the
changed scene's closed loop must be stable, the check hapsim run makes, also at three points
of the ramp) or refused with the reason sent back; accepted changes are ramped over --ramp
seconds (no step felt, no click) and journaled.

A 2-D or 3-D scene (dimension: 2 or 3) with an audio section plays its sound from its
initial state (a struck membrane rings): without changes, the frames 'hapsim simulate
SCENE --audio F.wav' writes. With a port and a device its loop is closed on the device's
model at the scene's rate (the exact ZOH of its Cartesian mass and friction, its delay:
the loop 'hapsim check' analyses), in the sound's producer, one compiled call per chunk;
the scene's excitation (excitation: {direction: [..], impulse: {force, start, duration}}
or a profile) is the hand's force on the device's mass along that direction, again every
--pluck-every seconds; --osc takes the same addresses, checked by the MIMO criterion of
the n-D check (the whole coupled loop's spectral radius, not axis by axis), and the ramps
run sample by sample. It takes --duration, --sound, --jack-server, --rt-priority, --json,
--osc, --ramp, --pluck-every, --journal (--lockstep, --telemetry and --sound none are
refused by name)."""

_EPILOG = """\
OSC addresses (replies go to the sender's address and port):
  /hapsim/link/stiffness LINK K        /hapsim/link/damping LINK B
  /hapsim/link/kb LINK K B             /hapsim/link/target LINK k b   (felt, calibrated)
  /hapsim/mass MASS m                  /hapsim/gain G                 (sound master gain)
  /hapsim/pause, /hapsim/resume        (force and sound ramped to 0 and back)
      -> /hapsim/ok ADDRESS ramp_s k b   or   /hapsim/refused ADDRESS REASON
  /hapsim/felt  -> /hapsim/felt k b f0 zeta k_measured b_measured
  /hapsim/loop  -> /hapsim/loop sample spectral_radius stable accepted refused xruns underruns
  /hapsim/telemetry HOST PORT [RATE] -> /hapsim/tel t x f k b sent to HOST:PORT at RATE Hz
  2-D/3-D scene: LINK may be a spring_damper, a contact or a plane (K, B on every mass it
  acts on); k b are the felt stiffness along its stiffest principal direction and the
  felt damping along it; /hapsim/felt appends n, the felt stiffness matrix and the felt
  damping matrix (row by row); /hapsim/tel t x1..xn f1..fn k b; /hapsim/link/target is
  refused (a felt target is a 1-D calibration); a scene without a port is checked alone
  (its modes' spectral radius; k b NaN, f0 zeta its lowest mode's).
signals: SIGINT (Ctrl-C) or SIGTERM ends the play early, as it ends hapsim run: the sound
  and the OSC server are closed, the report (stop_reason: signal NAME) is printed, exit 0.
measured (k, b): identified (matrix pencil) from each free response between plucks that no
  change disturbed; NaN until one has been.
late: times the loop fell more than 20 ms behind the clock (it then resynchronises; the
  mock device's physics stays sample-exact).
sound: computed in the sound server's callback, one block ahead of the hand: the force of
  device period n reaches the device lead = ceil(block / N) samples later (N audio
  sub-steps per device period), a pure delay the prediction includes (report: delay =
  device delay + lead), and the loop is paced by the sound card's clock. When the server
  changes its block during the run, the loop is predicted again for the new lead (journal
  event 'delay'), and the run stops (exit 1) if that loop is unstable. Through JACK the
  callback is native code (report: callback native): it never takes Python's lock, so
  nothing else in the process can make it late. xruns (JACK's count, with when: xrun_at_s,
  or PortAudio underflows); underruns: frames of silence, while the loop ran, because the
  next period's position had not arrived (the model waits; the loop stays the predicted
  one), with when the blocks that had them started (underrun_at_s, native callback).
examples:
  jackd -d dummy -r 48000 -p 256 &   # or your audio interface: jackd -d alsa -r 48000
  hapsim play configs/audio_string.yaml --osc 9000 --duration 60
  hapsim play configs/wall.yaml --osc 9000 --sound none --pluck-every 0.5 --json
  hapsim play configs/membrane.yaml --osc 9000 --ramp 0.02   # a 3-D membrane, changed live"""


#: Longest wait for the last identification after the run [s] (a large scene's fit of a
#: record its contacts made nonlinear can take minutes; it is then dropped).
END_WAIT_S = 3.0


def register(sub) -> None:
    """Add the ``play`` sub-command.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The sub-parsers of the ``hapsim`` parser; the new parser's ``func`` is :func:`run`.
    """
    p = sub.add_parser("play", help="play a scene live: sound out (JACK), changes in (OSC)",
                       description=_DESCRIPTION, epilog=_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="YAML scene file with a port and a device")
    p.add_argument("--duration", type=Number(float, low=0, open_low=True, unit="s"),
                   default=10.0, metavar="S",
                   help="play this long [s] (default 10)")
    p.add_argument("--osc", type=Number(int, low=0, high=65535), metavar="PORT",
                   help="serve OSC changes and queries on localhost:PORT (0: any free port)")
    p.add_argument("--view", type=Number(int, low=0, high=65535), nargs="?", const=8765,
                   metavar="PORT",
                   help="serve a live view on http://127.0.0.1:PORT (default port 8765; 0: "
                        "any free port): scene, traces, (k, b) grid, the --osc changes, stop "
                        "(needs pip install 'hapsim[view]')")
    p.add_argument("--sound", default="auto", choices=("auto", "jack", "sounddevice", "none"),
                   help="sound output (default auto: JACK, else PortAudio; scenes without "
                        "an audio section play silently)")
    p.add_argument("--jack-server", metavar="NAME", help="JACK server name (jackd -n NAME)")
    p.add_argument("--ramp", type=Number(float, low=0, unit="s"), default=0.05, metavar="S",
                   help="ramp time of every change [s] (default 0.05)")
    p.add_argument("--pluck-every", type=Number(float, low=0, unit="s"), default=0.0, metavar="S",
                   help="repeat the scene's excitation (hand impulse/profile) every S seconds "
                        "(default 0: once)")
    p.add_argument("--lockstep", action="store_true",
                   help="run as fast as possible instead of in real time (no OSC timing; "
                        "with live sound the sound card sets the pace anyway)")
    p.add_argument("--journal", metavar="FILE.json",
                   help="write the change journal (requests, verdicts, ramps) here")
    p.add_argument("--telemetry", metavar="FILE.npz",
                   help="write time [s], device position [m], port force [N] per sample")
    p.add_argument("--rt-priority", type=Number(int, low=0, high=99), default=None, metavar="N",
                   help="SCHED_FIFO priority of the haptic loop where permitted (0: normal). "
                        "Default: with live sound one below the sound callback's thread (the "
                        "loop feeds it: a haptic thread behind other real-time work starves "
                        "the sound), else 10; never at or above the callback's (it would "
                        "delay it past its deadline, holding the CPU or the GIL)")
    p.add_argument("--json", action="store_true", help="print one JSON report on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``hapsim play``.

    SIGINT and SIGTERM are handled from the start until the report is made (as ``hapsim
    run`` does, :mod:`hapsim.pipeline.runner`): they end the loop at its next sample, and the
    report covers what was played (``stop_reason``: ``signal SIGINT``/``signal SIGTERM``).

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options (see :func:`register`).

    Returns
    -------
    int
        0 after the run (also when a signal ended it); 1 when the scene's closed loop (with live sound: its callback's
        lead added to the device delay) is unstable (refused before playing), no sound
        output could be opened for ``--sound jack|sounddevice``, or the sound server
        stopped calling back (the report then covers what was played);
        2 on bad input (raised as ConfigError).
    """
    import signal
    import threading

    from hapsim.host.loop_types import StopFlag
    stop = StopFlag()
    old = {}
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, lambda signum, frame: stop.request(signum))
    try:
        return _play(args, stop)
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _play(args: argparse.Namespace, stop) -> int:
    """The play itself (:func:`run`, its signal handlers in place); ``stop`` is the
    :class:`~hapsim.host.loop_types.StopFlag` they set. A 2-D or 3-D scene plays its
    sound (:func:`hapsim.commands.play_nd.play_nd`)."""
    from hapsim.scene_nd import scene_dimension
    if getattr(args, "view", None) is not None:     # before anything starts: how to install
        from hapsim.view.server import require_websockets
        require_websockets()
    if scene_dimension(args.scene) > 1:
        from hapsim.commands.play_nd import play_nd
        return play_nd(args, stop)
    from hapsim.audio.control import Controller
    from hapsim.audio.osc import send_telemetry, serve_osc
    from hapsim.audio.journal import write_journal
    from hapsim.device_model import InProcessLoop, MockPhysics, hand_force_samples
    from hapsim.analysis.prediction import prepare_scene
    from hapsim.engine import Engine, warm_up
    from hapsim.errors import DeviceError
    from hapsim.scene import load_scene

    scene, _ = prepare_scene(load_scene(args.scene))
    engine = Engine(scene)
    live = out = None
    if args.sound != "none" and scene.audio is not None:
        from hapsim.audio.live import LiveSound, open_output
        live = LiveSound(engine)
    T = scene.period
    steps = int(round(args.duration * scene.rate_hz))
    dev = scene.device
    base = os.path.dirname(os.path.abspath(scene.path))
    h = hand_force_samples(scene.excitation, T, base)
    P = int(round(args.pluck_every * scene.rate_hz)) if args.pluck_every > 0 else steps + 1
    hand = np.zeros(steps + 1)
    for s0 in range(0, steps, max(P, 1)):
        n = min(h.size, steps - s0)
        hand[s0:s0 + n] = h[:n]
    phys = MockPhysics(dev, scene.rate_hz, scene.excitation, hand=hand, base_dir=base)
    xs = np.zeros(steps)
    fs = np.zeros(steps)
    engine.set_port_position(phys.sample(), at_rest=True)
    from hapsim.blas import limit_blas_threads
    limit_blas_threads(1)        # a threaded BLAS spins for seconds on a small SVD (loaded box)
    warm_up(scene)                                    # kernels loaded before the clock starts
    if live is not None:    # the sound starts after the warm-up (silence until the loop does)
        try:
            out = open_output(live, args.sound, server=args.jack_server)
        except DeviceError as exc:
            if args.sound != "auto":
                print(f"hapsim play: {exc}", file=sys.stderr)
                return 1
            print(f"hapsim play: no sound ({exc}); playing silently", file=sys.stderr)
            live = None
    # the loop played: the device's delay plus, with live sound, the callback's lead
    # (period n's force, computed in the sound server's callback, reaches the device
    # ``lead`` samples after its position left: a pure delay, hapsim.audio.live)
    played = live.coupled_scene(scene) if live is not None else scene
    ctl = Controller(played, engine, live, ramp_s=args.ramp)
    if not ctl.felt["stable"]:
        extra = (f" with the sound server's {out.blocksize}-frame block ({live.lead} device "
                 f"samples of delay added to the device's {dev.delay}; a smaller block, "
                 f"jackd -p, or --sound none may render it)" if live is not None else "")
        print(f"hapsim play: the closed loop of {args.scene}{extra} is unstable (spectral "
              f"radius {ctl.felt['spectral_radius']:.6g}); see hapsim check", file=sys.stderr)
        if out is not None:
            out.close()
        ctl.close()
        return 1
    server = tel = None
    status = (lambda: {"xruns": getattr(out, "xruns", 0),
                       "underruns": live.stats()["underruns"] if live else 0})
    if args.osc is not None:
        server, tel = serve_osc(ctl, args.osc, status=status)
        host, port = server.server_address[:2]
        print(f"hapsim play: OSC on {host}:{port}", file=sys.stderr, flush=True)
    view = None
    if getattr(args, "view", None) is not None:
        from hapsim.view import PlaySource, start_view
        try:
            view = start_view(PlaySource(scene, xs, fs, engine, ctl), ctl, stop, args.view,
                              "play")
        except BaseException:
            if server is not None:
                server.shutdown()
                server.server_close()
            if out is not None:
                out.close()
            ctl.close()
            raise
    loop = InProcessLoop(phys, live.port_step if live is not None else engine.port_step,
                         dev.delay, dev.force_limit)
    clocked = live is None and not args.lockstep     # live sound: the sound card's clock
    late = 0
    quiet_from = 0            # first sample after the last change's ramp ended
    error = None
    from hapsim.host.realtime import RealtimePriority
    prio = 10 if args.rt_priority is None else args.rt_priority
    if out is not None:
        # just below the sound callback's thread: at its priority or above, the haptic
        # thread (and the GIL it holds) delays the callback past its deadline; far below,
        # other real-time work delays the positions the callback needs
        from hapsim.audio.live import wait_priority
        ap = wait_priority(out)
        if ap:
            prio = max(0, ap - 1 if args.rt_priority is None else min(prio, ap - 1))
    rt = RealtimePriority(prio).__enter__()
    t0 = time.perf_counter()
    # the lead the prediction was made for (the block may have changed since)
    lead_now = round(float(played.device.delay) - float(dev.delay))
    done = steps               # samples played (fewer after a signal or a device error)
    stop_reason = "duration"
    try:
        for n in range(steps):
            if stop.set:
                from hapsim.host.loop_types import signame
                done, stop_reason = n, (f"signal {signame(stop.signal)}"
                                        if stop.signal is not None or stop.reason is None
                                        else stop.reason)
                break
            if live is not None and live.lead != lead_now:
                # the sound server changed its block (JACK's buffer-size callback): the
                # loop's delay is now device delay + the new lead; re-predict it, and do not
                # measure a free response that straddles the change
                lead_now = live.lead
                quiet_from = n + 1 + int(dev.delay) + lead_now
                ctl.rebase_delay(dev.delay + lead_now,
                                 f"the sound server's block changed to {out.blocksize} "
                                 f"frames at sample {n} (lead {lead_now})")
            if ctl.unstable is not None:
                raise DeviceError(ctl.unstable)
            ctl.poll()
            if ctl.ramping:
                quiet_from = max(quiet_from, n + 1)
            x, f = loop.step(ctl.force_scale)
            xs[n], fs[n] = x, f
            if tel is not None and n % tel["every"] == 0:
                send_telemetry(tel, n * T, x, f, ctl)
            # (a scene plucked by x0 alone is free from the start, once: its first window)
            if P <= steps and (n + 1) % P == 0 and (h.size or n + 1 == P):
                # end of a free response: measured (on a worker thread) when no change
                # disturbed it
                a = max(n + 1 - P + h.size, quiet_from)
                if n + 1 - a >= 50:
                    ctl.measure(xs[a:n + 1])
            if clocked:
                ahead = t0 + (n + 1) * T - time.perf_counter()
                if ahead > 0:
                    time.sleep(ahead)
                elif ahead < -0.02:       # more than 20 ms behind: count, resynchronise
                    late += 1
                    t0 -= ahead
    except DeviceError as exc:  # the sound server stopped, or its new block made the loop
        # unstable: report what was played
        error = str(exc)
        done, stop_reason = n, "error"
    finally:
        if out is not None:
            out.finish()      # the last position is pushed: what follows is not starvation
        rt.__exit__(None, None, None)
        if server is not None:
            server.shutdown()
            server.server_close()
        if out is not None:
            out.close()
    if done < steps:
        steps = done
        xs, fs = xs[:steps], fs[:steps]
    if P > steps and max(h.size, quiet_from) < steps - 50:   # one free response: now
        ctl.measure(xs[max(h.size, quiet_from):], wait=END_WAIT_S)
    else:
        ctl.finish(END_WAIT_S)
    note = None if ctl.finish(0.0) else (
        f"the last identification ran past {END_WAIT_S:g} s after the run: dropped")
    ctl.close()
    report = {"scene": args.scene, "samples": steps, "rate_hz": scene.rate_hz,
              "stop_reason": stop_reason, "late": late,  # times > 20 ms behind the clock (then resynchronised)
              "paced_by": "sound" if live is not None else ("clock" if clocked else "none"),
              "delay": int(ctl.scene.device.delay),   # device samples, lead included
              "scheduling": rt.note, "accepted": ctl.accepted, "refused": ctl.refused,
              "felt": ctl.felt, "measured": {"k": ctl.measured[0], "b": ctl.measured[1],
                                             "why_not": ctl.unmeasured,
                                             **({} if ctl.measurement is None else {
                                                 q: ctl.measurement.get(q) for q in
                                                 ("k_unc", "b_unc", "method", "samples_used")})},
              "error": error, "note": note,
              "links": {lk.name: [lk.stiffness, lk.damping] for lk in ctl.scene.links},
              "sound": None if live is None else {
                  "backend": type(out).__name__, "callback": out.callback,
                  "xruns": out.xruns, "xrun_at_s": list(out.xrun_at),
                  "active_monotonic_s": out.t_active, "block": out.blocksize,
                  "underrun_at_s": (out.underrun_at() if hasattr(out, "underrun_at")
                                    else []),
                  **live.stats()},
              "journal": ctl.journal}
    if args.journal:
        write_journal(args.journal, ctl.journal)
    if args.telemetry:
        tmp = args.telemetry + ".partial"
        with open(tmp, "wb") as fh:
            np.savez(fh, time=np.arange(steps) * T, position=xs, force=fs)
        os.replace(tmp, args.telemetry)
    if view is not None:
        view.finish(report)
    if args.json:
        print(json.dumps(json_safe(report)))
    else:
        felt = ctl.felt
        print(f"played {args.scene} for {steps * T:g} s ({steps} samples, {late} late); "
              f"{ctl.accepted} changes accepted, {ctl.refused} refused"
              + ("" if stop_reason == "duration" else f"; stopped by {stop_reason}"))
        measured = (f"measured k = {ctl.measured[0]:.6g}, b = {ctl.measured[1]:.6g}"
                    if ctl.unmeasured is None else f"measured: nothing ({ctl.unmeasured})")
        print(f"felt now: k = {_g(felt.get('k'))} N/m, b = {_g(felt.get('b'))} N s/m "
              f"predicted; {measured}")
        if report["sound"]:
            print(sound_line(report["sound"]))
    if error:
        print(f"hapsim play: {error}", file=sys.stderr)
        return 1
    return 0


def _g(v) -> str:
    return f"{v:.6g}" if isinstance(v, (int, float)) else str(v)


def sound_line(sound: dict) -> str:
    """The ``sound:`` line of ``hapsim play``'s text report.

    Parameters
    ----------
    sound : dict
        The report's ``sound`` entry: ``backend``, ``callback``, ``block`` [frames],
        ``xruns``, ``xrun_at_s``, ``underruns`` [frames], ``underrun_at_s``, ``lead``
        [device samples], ``periods``, ``waits``, ...

    Returns
    -------
    str
        One line, e.g. ``sound: JackOutput (native callback), block 256 frames, lead 6
        samples; xruns 0, underruns 0 frames; 3000 periods played, 0 waits``.
    """
    s = sound
    line = (f"sound: {s.get('backend')} ({s.get('callback')} callback), block "
            f"{s.get('block')} frames, lead {s.get('lead')} samples; xruns {s.get('xruns')}")
    if s.get("xrun_at_s"):
        line += f" (at {', '.join(f'{t:.3f}' for t in s['xrun_at_s'][:5])} s)"
    line += f", underruns {s.get('underruns')} frames"
    if s.get("underrun_at_s"):
        line += f" (at {', '.join(f'{t:.3f}' for t in s['underrun_at_s'][:5])} s)"
    return line + f"; {s.get('periods')} periods played, {s.get('waits')} waits"
