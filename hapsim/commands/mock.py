"""``hapsim mock``: a mock force-feedback device on a new pseudo-terminal."""

from __future__ import annotations

import argparse
import json
import math
import os
import pty
import tty

from hapsim.errors import ConfigError


def register(sub) -> None:
    """Add the ``mock`` parser to ``sub`` (an argparse sub-parsers action)."""
    p = sub.add_parser(
        "mock", help="serve a mock device (exact THS physics) on a new pseudo-terminal",
        description=(
            "Start a mock 1-DoF force-feedback device on a new pseudo-terminal and print its "
            "path as the first line of stdout ('PORT /dev/pts/N'). The mock speaks the "
            "framed protocol exactly like hardware (HELLO, CONFIG, STATE every tick, FORCE, "
            "PING/PONG, watchdog, force clamp, STOP) and integrates m x'' + b0 x' = f "
            "exactly over each period with the force held (zero-order hold), applying the "
            "FORCE answering STATE n at tick n + d. Its device and excitation come from the "
            "scene's 'device' and 'excitation' sections (default: the device of "
            "configs/wall.yaml, m = 0.1 kg, b0 = 0.5 N s/m, d = 1, 10 N, with x0 = 5 mm). "
            "It serves until SIGINT/SIGTERM or until the host sends STOP."),
        epilog=(
            "modes:\n"
            "  real-time (default)  ticks on the monotonic clock at the host's CONFIG rate;\n"
            "                       a late FORCE leaves the last force held (counted)\n"
            "  --lockstep           one period per FORCE: deterministic, any host speed\n"
            "example (two terminals):\n"
            "  $ hapsim mock --scene configs/wall.yaml\n"
            "  PORT /dev/pts/7\n"
            "  $ hapsim run configs/wall.yaml --port /dev/pts/7\n"
            "exit codes: 0 stopped by STOP or a signal; 2 bad arguments or scene."),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", metavar="SCENE", help="scene whose device/excitation to model")
    p.add_argument("--lockstep", action="store_true",
                   help="advance one period per FORCE instead of on the clock")
    p.add_argument("--rate", type=float, metavar="HZ",
                   help="native rate announced in HELLO [Hz] (default: the scene's)")
    p.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default 0)")
    p.add_argument("--report", metavar="FILE",
                   help="write what the mock saw (ticks, late, last force, STOP) as JSON on exit")
    p.add_argument("--fd", type=int, help=argparse.SUPPRESS)    # embedded: pty master fd
    p.add_argument("--spec", help=argparse.SUPPRESS)            # embedded: device JSON
    p.set_defaults(func=run)


def _from_spec(text: str):
    from hapsim.scene import Device, Excitation, Impulse
    spec = json.loads(text)
    d = dict(spec["device"])
    if d.get("force_limit") is None:
        d["force_limit"] = math.inf
    e = dict(spec["excitation"])
    if e.get("impulse") is not None:
        e["impulse"] = Impulse(**e["impulse"])
    return Device(**d), Excitation(**e), spec.get("base_dir")


def run(args) -> int:
    """Run ``hapsim mock``; returns the exit code."""
    from hapsim.daemon.mock import DEFAULT_DEVICE, DEFAULT_EXCITATION, MockDevice, serve_fd

    rate = 1000.0
    if args.spec:
        device, excitation, base_dir = _from_spec(args.spec)
    elif args.scene:
        from hapsim.scene import load_scene
        scene = load_scene(args.scene)
        if scene.device is None:
            raise ConfigError("the scene has no device section", file=scene.path, key="device")
        device, excitation = scene.device, scene.excitation
        base_dir = os.path.dirname(os.path.abspath(args.scene))
        rate = scene.rate_hz
    else:
        device, excitation, base_dir = DEFAULT_DEVICE, DEFAULT_EXCITATION, None
    if args.rate is not None:
        if not (math.isfinite(args.rate) and args.rate > 0):
            raise ConfigError(f"must be a positive number [Hz], got {args.rate}", key="--rate")
        rate = args.rate
    mock = MockDevice(device, excitation, native_rate_hz=rate, lockstep=args.lockstep,
                      seed=args.seed, base_dir=base_dir)
    if args.fd is not None:
        # embedded in hapsim run: the host owns the terminal; end on STOP, EOF or SIGTERM
        import signal

        from hapsim.daemon.loop import StopFlag
        flag = StopFlag()
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, lambda signum, frame: flag.request(signum))
        serve_fd(args.fd, mock, exit_on_stop=True, report_path=args.report, flag=flag,
                 handle_signals=False)
        return 0
    master, slave = pty.openpty()
    tty.setraw(slave)
    print(f"PORT {os.ttyname(slave)}", flush=True)
    try:
        serve_fd(master, mock, exit_on_stop=True, report_path=args.report)
    finally:
        os.close(master)
        os.close(slave)
    return 0
