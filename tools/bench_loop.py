#!/usr/bin/env python3
"""Benchmark of the host loop's per-sample cost, both clocks (a program, not a test).

Runs :class:`hapsim.daemon.loop.HostLoop` on the in-process virtual-clock transport
(:class:`~hapsim.daemon.transport.SimTransport` around the real-time mock, no faults) for
N samples of the wall scene of the reliability tests, device-clocked and host-clocked,
and prints the wall time per sample [us], best of R runs. Measured in the same run, as
baselines:

* ``round trip``: the same mock and transport driven by a bare loop that answers each
  STATE with a zero FORCE (codec, mock physics, virtual clock; no engine, no host-loop
  bookkeeping);
* ``port_step``: the engine's ``port_step`` alone, N calls.

``own`` is the loop minus both baselines: what the host loop itself adds per sample
(checks, passivity observer, clamp, telemetry row, safety bounds); ``x rt`` is the loop
over the round trip. With ``--ref REV`` the ``hapsim/daemon/loop.py`` of git revision REV
is loaded as a second module and timed in the same run, interleaved with the current one,
and the ratios current / REV are printed (the figure a refactor of the loop is judged by).

The machine may be shared: each figure is the best of R runs (least disturbed), and the
runs of the variants are interleaved so drift hits them alike. The handshake (16 PINGs,
CONFIG) is inside the timed ``run()``; it is under 0.5 % of N = 20000 samples.

Usage::

    python tools/bench_loop.py [--n N] [--repeat R] [--ref REV] [--json FILE]

Exit code 0, or 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import gc
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import firmware_protocol as fp  # noqa: E402
from hapsim.daemon import loop as loop_mod  # noqa: E402
from hapsim.daemon.mock import MockDevice  # noqa: E402
from hapsim.daemon.telemetry import Telemetry  # noqa: E402
from hapsim.daemon.transport import SimTransport  # noqa: E402
from hapsim.engine import Engine  # noqa: E402
from hapsim.scene import load_scene  # noqa: E402

#: The shipped wall (K = 1000 N/m, B = 1.5 N s/m, 1 kHz, d = 1, 10 N force limit).
WALL = REPO / "configs" / "wall.yaml"


def load_ref(rev: str):
    """``hapsim/daemon/loop.py`` at git revision ``rev``, imported as its own module.

    Parameters
    ----------
    rev : str
        A git revision of this repository.

    Returns
    -------
    module
        The old loop module (its ``HostLoop``, ``LoopConfig``).
    """
    src = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:hapsim/daemon/loop.py"],
                         check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp(prefix="bench_loop_")) / "loop_ref.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("hapsim.daemon._loop_ref", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod          # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def time_loop(mod, scene, n: int, host_clocked: bool) -> float:
    """One run of ``mod.HostLoop`` for ``n`` samples; wall time per sample [us]."""
    mock = MockDevice(scene.device, scene.excitation, native_rate_hz=1000.0, lockstep=False)
    tr = SimTransport(mock)
    cfg = mod.LoopConfig(rate_hz=1000.0, n_samples=n, delay=1, force_limit=scene.device.force_limit,
                         reconnect=True, watchdog_us=50_000, position_bound=0.1,
                         host_clocked=host_clocked)
    tel = Telemetry(n)
    loop = mod.HostLoop(Engine(scene), tr, cfg, tel)
    t0 = time.perf_counter_ns()
    res = loop.run()
    dt = time.perf_counter_ns() - t0
    if res.samples != n or res.stop_reason != "duration":
        raise SystemExit(f"benchmark run ended early: {res.samples} samples, {res.stop_reason}")
    return dt * 1e-3 / n


def time_round_trip(scene, n: int) -> float:
    """The mock and transport alone: answer each STATE with a zero FORCE; us per sample."""
    mock = MockDevice(scene.device, scene.excitation, native_rate_hz=1000.0, lockstep=False)
    tr = SimTransport(mock)
    tr.send(fp.HelloRequest(fp.PROTOCOL_VERSION))
    tr.receive(0.1)
    gc.collect()
    gc.disable()                   # as HostLoop.run
    try:
        t0 = time.perf_counter_ns()
        tr.send(fp.Config(1000.0, 50_000, scene.device.force_limit))
        State, Force, receive, send = fp.State, fp.Force, tr.receive, tr.send
        i = 0
        while i < n:
            for msg in receive(0.1):
                if type(msg) is State:
                    send(Force(msg.seq, (0.0,)))
                    i += 1
        dt = time.perf_counter_ns() - t0
    finally:
        gc.enable()
    return dt * 1e-3 / n


def time_port_step(scene, n: int) -> float:
    """The engine's ``port_step`` alone, on a 1 Hz, 5 mm sine; us per sample."""
    import math
    eng = Engine(scene)
    eng.set_port_position(0.0, at_rest=True)
    xs = [0.005 * math.sin(2 * math.pi * k / 1000.0) for k in range(n)]
    step = eng.port_step
    gc.collect()
    gc.disable()
    try:
        t0 = time.perf_counter_ns()
        for x in xs:
            step(x)
        dt = time.perf_counter_ns() - t0
    finally:
        gc.enable()
    return dt * 1e-3 / n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=20_000, help="samples per run (default 20000)")
    ap.add_argument("--repeat", type=int, default=5, help="runs, best kept (default 5)")
    ap.add_argument("--ref", help="git revision whose loop.py is timed alongside")
    ap.add_argument("--json", help="also write the figures to this file")
    args = ap.parse_args(argv)
    if args.n < 100 or args.repeat < 1:
        ap.error("--n must be >= 100 and --repeat >= 1")
    scene = load_scene(WALL)
    variants = {"current": loop_mod}
    if args.ref:
        variants[f"ref {args.ref}"] = load_ref(args.ref)
    # warm up: numba compiles or loads the kernel, the first run pays the imports
    for mod in variants.values():
        for hc in (False, True):
            time_loop(mod, scene, 200, hc)
    time_round_trip(scene, 200)
    time_port_step(scene, 200)

    best: dict = {}

    def keep(key, us):
        best[key] = min(best.get(key, float("inf")), us)

    for _ in range(args.repeat):          # interleaved: drift hits every variant alike
        keep("round trip", time_round_trip(scene, args.n))
        keep("port_step", time_port_step(scene, args.n))
        for name, mod in variants.items():
            for hc, clock in ((False, "device"), (True, "host")):
                keep((name, clock), time_loop(mod, scene, args.n, hc))

    rt, ps = best["round trip"], best["port_step"]
    print("command: " + " ".join([sys.executable, *sys.argv]))
    print(f"python {sys.version.split()[0]}, N = {args.n} samples, best of {args.repeat}")
    print(f"{'what':26} {'us/sample':>10} {'x rt':>7} {'own us':>8}")
    print(f"{'round trip (baseline)':26} {rt:10.3f} {1.0:7.3f} {'':>8}")
    print(f"{'port_step (baseline)':26} {ps:10.3f} {ps / rt:7.3f} {'':>8}")
    out = {"n": args.n, "repeat": args.repeat, "round_trip_us": rt, "port_step_us": ps,
           "loops": {}}
    for name in variants:
        for clock in ("device", "host"):
            us = best[(name, clock)]
            print(f"{name + ', ' + clock + '-clocked':26} {us:10.3f} {us / rt:7.3f} "
                  f"{us - rt - ps:8.3f}")
            out["loops"][f"{name}, {clock}"] = {"us": us, "x_round_trip": us / rt,
                                                "own_us": us - rt - ps}
    if args.ref:
        ref = f"ref {args.ref}"
        for clock in ("device", "host"):
            cur, old = best[("current", clock)], best[(ref, clock)]
            print(f"{clock}-clocked: current / {args.ref} = {cur / old:.4f} per sample, "
                  f"own work {(cur - rt - ps) / (old - rt - ps):.4f}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
