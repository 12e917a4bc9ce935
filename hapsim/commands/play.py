"""``hapsim play``: play a scene live: sound out, changes in over OSC, the mock hand plucking."""

from __future__ import annotations

import argparse
import json
import sys

from hapsim.outputs import json_safe
from hapsim.option_values import declared

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
  one), with when the blocks that had them started (underrun_at_s, native callback;
  loop_begin_s: when the loop's first position came, the same clock).
examples:
  jackd -d dummy -r 48000 -p 256 &   # or your audio interface: jackd -d alsa -r 48000
  hapsim play configs/audio_string.yaml --osc 9000 --duration 60
  hapsim play configs/wall.yaml --osc 9000 --sound none --pluck-every 0.5 --json
  hapsim play configs/membrane.yaml --osc 9000 --ramp 0.02   # a 3-D membrane, changed live"""


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
    p.add_argument("--duration", type=declared("play", "duration"),
                   default=10.0, metavar="S",
                   help="play this long [s] (default 10)")
    p.add_argument("--osc", type=declared("play", "osc"), metavar="PORT",
                   help="serve OSC changes and queries on localhost:PORT (0: any free port)")
    p.add_argument("--view", type=declared("play", "view"), nargs="?", const=8765,
                   metavar="PORT",
                   help="serve a live view on http://127.0.0.1:PORT (default port 8765; 0: "
                        "any free port): scene, traces, (k, b) grid, the --osc changes, stop "
                        "(needs pip install 'hapsim[view]')")
    p.add_argument("--sound", default="auto", choices=("auto", "jack", "sounddevice", "none"),
                   help="sound output (default auto: JACK, else PortAudio; scenes without "
                        "an audio section play silently)")
    p.add_argument("--jack-server", metavar="NAME", help="JACK server name (jackd -n NAME)")
    p.add_argument("--ramp", type=declared("play", "ramp"), default=None, metavar="S",
                   help="ramp time of every change that comes in through --osc or --view "
                        "[s] (default 0.05)")
    p.add_argument("--pluck-every", type=declared("play", "pluck_every"), default=0.0,
                   metavar="S",
                   help="repeat the scene's excitation (hand impulse/profile) every S seconds "
                        "(default 0: once)")
    p.add_argument("--lockstep", action="store_true",
                   help="run as fast as possible instead of in real time (no OSC timing; "
                        "with live sound the sound card sets the pace anyway)")
    p.add_argument("--journal", metavar="FILE.json",
                   help="write the change journal (requests, verdicts, ramps) here")
    p.add_argument("--telemetry", metavar="FILE.npz",
                   help="write time [s], device position [m], port force [N] per sample")
    p.add_argument("--rt-priority", type=declared("play", "rt_priority"), default=None,
                   metavar="N",
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
    from hapsim.blas import preload_numba_blas
    from hapsim.host.loop_types import StopFlag
    from hapsim.pipeline.play import stop_on_signals
    preload_numba_blas()                # before numba's first kernel (hapsim.blas)
    stop = StopFlag()
    with stop_on_signals(stop):
        return _play(args, stop)


def _play(args: argparse.Namespace, stop) -> int:
    """The play itself (:func:`run`, its signal handlers in place); ``stop`` is the
    :class:`~hapsim.host.loop_types.StopFlag` they set:
    :func:`hapsim.pipeline.play.play_scene`, its report printed (``--json``: one object;
    else :func:`hapsim.pipeline.play.play_text`); a refusal before playing raised (exit 1,
    cli's error line and ``--json`` error object)."""
    from hapsim.api.playing import PLAY_OPTIONS
    from hapsim.commands.dimension import refuse_ports_scene
    from hapsim.pipeline.options import check_ramp
    from hapsim.pipeline.play import play_scene, play_text
    refuse_ports_scene(args.scene, "play")        # several ports: nothing to hear
    check_ramp(args.ramp is not None, args.osc, args.view)
    if args.ramp is None:
        args.ramp = PLAY_OPTIONS["ramp"]
    # a refusal before playing (an unstable loop, a device that failed) raises: exit 1,
    # cli's error line and, with --json, its error object
    code, report = play_scene(args, stop)
    if args.json:
        print(json.dumps(json_safe(report)))
    else:
        print(play_text(report))
    if report.get("error"):
        print(f"hapsim play: {report['error']}", file=sys.stderr)
    return code


