"""The work of ``hapsim play`` (:mod:`hapsim.pipeline.play`) without its printing, for the
command line and :func:`hapsim.api.play`: a 1-D scene's loop played live on its embedded
mock device (sound out through JACK or PortAudio, changes in over OSC and the live view),
a 2-D or 3-D scene's sound (below).

A 2-D or 3-D scene with an ``audio`` section runs from its initial state (a struck
membrane rings) and its listening points go out through JACK (or PortAudio) as they are computed
(:class:`hapsim.audio.live.LiveND`): without changes, the frames played are the ones
``hapsim simulate SCENE --audio F.wav`` writes, paced by the sound card's clock; xruns
(the server's count) and underruns (frames of silence because the producer was late) are
counted and reported. A scene with a port and a device is closed on the device's model
at the scene's rate (the loop ``hapsim check`` analyses); its ``excitation`` (a force on
the device's mass along the scene's direction) plucks it, again every ``--pluck-every``
seconds. ``--osc PORT`` serves the 1-D play's addresses
(:class:`hapsim.audio.control.ControllerND`): every change is checked by the MIMO criterion before it
is accepted and ramped over ``--ramp`` seconds, sample by sample.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import time

import numpy as np

from hapsim.errors import ConfigError

#: Longest wait for the last identification after the run [s] (a large scene's fit of a
#: record its contacts made nonlinear can take minutes; it is then dropped).
END_WAIT_S = 3.0


@contextlib.contextmanager
def stop_on_signals(stop):
    """SIGINT and SIGTERM request ``stop`` (instead of raising) while in the block; the
    previous handlers back after it. Nothing is installed outside the main thread (where
    Python runs no signal handler).

    Parameters
    ----------
    stop : hapsim.host.loop_types.StopFlag
    """
    import signal
    import threading

    old = {}
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, lambda signum, frame: stop.request(signum))
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _refusal(exc):
    """``exc`` marked as a refusal before anything played (``hapsim play`` exits 1 with its
    message alone, as it always has; :func:`hapsim.api.play` raises it)."""
    exc.before_play = True
    return exc


def play_scene(args, stop, scene=None) -> tuple[int, dict]:
    """Play a scene live (``hapsim play``'s work, without its printing): the 1-D loop here,
    a 2-D or 3-D scene's sound by :func:`play_nd_report`.

    Parameters
    ----------
    args : argparse.Namespace or types.SimpleNamespace
        ``hapsim play``'s options by destination (:func:`hapsim.commands.play.register`):
        ``scene`` (the path,
        the report's ``scene`` of a 1-D play), ``duration`` [s], ``osc``, ``view``,
        ``sound``, ``jack_server``, ``ramp`` [s], ``pluck_every`` [s], ``lockstep``,
        ``journal``, ``telemetry``, ``rt_priority``.
    stop : hapsim.host.loop_types.StopFlag
        Ends the play at its next sample (a signal's handler, the view's stop button).
    scene : hapsim.scene.Scene or hapsim.scene.SceneND, optional
        The scene already loaded (default: read from ``args.scene``).

    Returns
    -------
    code : int
        What ``hapsim play`` exits with: 0 after the play (also when stopped early), 1
        when the sound server stopped calling back or its new block made the loop
        unstable (the report then covers what was played, its ``error`` says why).
    report : dict
        ``hapsim play --json``'s object.

    Raises
    ------
    UnstableConfigError
        The scene's closed loop (with live sound, the callback's lead added to the
        device's delay) is unstable: refused before playing (``before_play`` True).
    DeviceError
        No sound output could be opened for ``sound`` ``jack`` or ``sounddevice`` (an
        n-D play: for any ``sound``): refused before playing (``before_play`` True).
    ConfigError
        Bad input (an option an n-D play does not take, a scene without a device, a
        ``jack_server`` without JACK's sound, ...).
    """
    from hapsim.outputs import check_writable
    from hapsim.pipeline.options import check_jack_server
    check_jack_server(getattr(args, "jack_server", None), getattr(args, "sound", "auto"))
    for key in ("journal", "telemetry"):        # (before the play: they failed after it)
        if getattr(args, key, None):
            check_writable(getattr(args, key), "--" + key)
    if getattr(args, "telemetry", None) and not args.telemetry.lower().endswith(".npz"):
        raise ConfigError(f"a play's telemetry is an .npz archive: give a file ending in "
                          f".npz, got {args.telemetry!r}", key="--telemetry")
    if getattr(args, "view", None) is not None:     # before anything starts: how to install
        from hapsim.view.server import require_websockets
        require_websockets()
    if scene is None:
        from hapsim.scene import scene_dimension
        if scene_dimension(args.scene) > 1:
                        return play_nd_report(args, stop)
    elif getattr(scene, "dimension", 1) > 1:
                return play_nd_report(args, stop, scene)
    from hapsim.audio.control import Controller
    from hapsim.audio.journal import write_journal
    from hapsim.audio.osc import send_telemetry, serve_osc
    from hapsim.device_model import InProcessLoop, MockPhysics, hand_force_samples
    from hapsim.analysis.prediction import prepare_scene
    from hapsim.engine import Engine, warm_up
    from hapsim.errors import DeviceError, UnstableConfigError
    from hapsim.scene import load_scene

    scene, _ = prepare_scene(load_scene(args.scene) if scene is None else scene)
    engine = Engine(scene)
    live = out = None
    if args.sound != "none" and scene.audio is not None:
        from hapsim.audio.live import LiveSound, open_output
        live = LiveSound(engine)
    T = scene.period
    n = args.duration * scene.rate_hz
    # the play's records (the hand's force, positions, forces, and the loop's own): about
    # 48 bytes a sample, checked before anything is allocated (before: --duration 1e8
    # asked numpy for 745 GiB and printed its traceback)
    from hapsim.outputs import check_fits
    if not math.isfinite(n):
        raise ConfigError(f"{args.duration:.6g} s at {scene.rate_hz:.6g} Hz is no count of "
                          "samples", key="--duration")
    check_fits(48.0 * n, f"{n:.3g} samples of a play ({scene.rate_hz:.6g} Hz)", "--duration")
    steps = int(round(n))
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
                raise _refusal(exc) from None
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
        if out is not None:
            out.close()
        ctl.close()
        raise _refusal(UnstableConfigError(
            f"the closed loop of {args.scene}{extra} is unstable (spectral radius "
            f"{ctl.felt['spectral_radius']:.6g}); see hapsim check",
            spectral_radius=ctl.felt["spectral_radius"]))
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
    # the journal's sample: the index of the sample being computed (its telemetry row), as
    # hapsim run's journal says it; the controller's own count (ctl.sample, /hapsim/loop)
    # is one more once the sample's poll has run, which named the row after the one a
    # change first acted on
    at = [0]
    ctl.sample_of = lambda: at[0]
    if hasattr(out, "begin"):
        out.begin()       # the callbacks so far played the start (the loop's start-up)
    try:
        for n in range(steps):
            at[0] = n
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
    except BaseException:     # a KeyboardInterrupt in a caller that left SIGINT as it is
        # (hapsim.api.play): nothing is left running (the view's server, the analysis)
        if view is not None:
            view.close()
        ctl.close()
        raise
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
                  "loop_begin_s": getattr(out, "begin_s", None),
                  **live.stats()},
              "journal": ctl.journal}
    if args.journal:
        write_journal(args.journal, ctl.journal)
    if args.telemetry:
        from hapsim.outputs import atomic_write
        with atomic_write(args.telemetry, "wb", "--telemetry") as fh:
            np.savez(fh, time=np.arange(steps) * T, position=xs, force=fs)
    if view is not None:
        view.finish(report)
    return (1 if error else 0), report


def play_text(report: dict) -> str:
    """The text report ``hapsim play`` prints (without ``--json``).

    Parameters
    ----------
    report : dict
        :func:`play_scene`'s report (a 2-D or 3-D play's has ``dof``).

    Returns
    -------
    str
        Two or three lines, no trailing newline.
    """
    if "dof" in report:
                return play_nd_text(report)
    steps, late = report["samples"], report["late"]
    stop_reason = report["stop_reason"]
    felt, m = report["felt"], report["measured"]
    lines = [f"played {report['scene']} for {steps / report['rate_hz']:g} s ({steps} "
             f"samples, {late} late); {report['accepted']} changes accepted, "
             f"{report['refused']} refused"
             + ("" if stop_reason == "duration" else f"; stopped by {stop_reason}")]
    measured = (f"measured k = {m['k']:.6g}, b = {m['b']:.6g}"
                if m["why_not"] is None else f"measured: nothing ({m['why_not']})")
    lines.append(f"felt now: k = {_g(felt.get('k'))} N/m, b = {_g(felt.get('b'))} N s/m "
                 f"predicted; {measured}")
    if report["sound"]:
        lines.append(sound_line(report["sound"]))
    return "\n".join(lines)


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


# ------------------------------------------------ a 2-D or 3-D scene's sound
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
    scene : hapsim.scene.SceneND
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
    scene : hapsim.scene.SceneND, optional
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
    from hapsim.audio.control import ControllerND
    from hapsim.audio.live import LiveND, open_output, wait_priority
    from hapsim.host.loop_types import signame
    from hapsim.host.realtime import RealtimePriority
    from hapsim.engine import Engine
    from hapsim.errors import DeviceError
    from hapsim.scene import load_scene_nd
    refuse_untaken(args)
    if scene is None:
        scene = load_scene_nd(args.scene)
    if not scene.audio:
        raise ConfigError("the scene has no audio section (listen: [{mass, axis, quantity, "
                          "gain}]): nothing to play; see configs/membrane.yaml",
                          file=scene.path, key="audio")
    hand, direction, every = hand_of(scene, getattr(args, "pluck_every", 0.0) or 0.0)
    engine = Engine(scene)
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
