"""The cycle budget of the Hapkit pantograph firmware (two emulated ATmega328P on a TWI bus).

The emulated board (``pantograph_board``, lockstep: the emulated time waits for each FORCE,
so the figures are cycle counts of the emulated chips and do not depend on the host
machine's load) runs the leader and the follower on a scene's pantograph; a small host
arms it at ``--rate`` and answers every STATE with joint torques (a joint-space spring
``-K (q - q0)``, 5 N m/rad) for ``--ticks`` ticks. Reported, per tick (between two rising
edges of the leader's D13 probe, which its tick interrupt raises): the cycles each MCU is
not asleep (mean, worst), the slack of the critical path (from the end of the tick's DRIVE
-- the follower's torque on the bus, the last step before both joints can take the next
tick's torques -- to the next tick's SYNC: the cycles to spare, smallest and mean), the
device's delay (``seq - force_seq``), the overruns and the TWI traffic, for the compact
frames (STATE_COMPACT / FORCE_COMPACT, what hapsim asks of this firmware) and the full ones.
``--profile``: the leader's busy cycles by function (the ELF's symbols).

    PYTHONPATH=. python tools/bench_pantograph.py [--ticks 1000] [--frames compact,full]
        [--json FILE] [--profile] [--host-slack]

``--realtime N`` measures instead what a real-time run meets on this machine: N times
``hapsim mock --firmware --scene SCENE`` (the board paced to the wall clock) and
``hapsim run SCENE --port PTY --amplitude A --json`` against it, each run's late ticks
(FORCEs that missed their DRIVE slot, taken as known inputs), verdict, and the board's
time (slips, emulation speed), with the machine's load before and after (a figure
measured beside other work is "loaded": the JSON says so):

    PYTHONPATH=. python tools/bench_pantograph.py --realtime 8 --json FILE
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import firmware_protocol as fp  # noqa: E402
from hapsim.emulated import pantograph_board as pb  # noqa: E402
from hapsim.host.transport import SerialTransport  # noqa: E402
from hapsim.scene import load_scene_nd  # noqa: E402
from provenance import command_line  # noqa: E402  (tools/, beside this file)

#: The host's joint-space spring [N m/rad].
SPRING = 5.0


def _profile(path: Path) -> list:
    """(function, cycles) of the leader's busy cycles, largest first."""
    syms = []
    out = subprocess.run(["avr-nm", "-n", "-S", str(pb.LEADER_ELF)], capture_output=True,
                         text=True).stdout
    for line in out.splitlines():
        p = line.split()
        if len(p) >= 4 and p[2] in "tTwW":
            syms.append((int(p[0], 16), int(p[1], 16), p[3].split(".")[0]))
    tot: collections.Counter = collections.Counter()
    for line in path.read_text().splitlines():
        a, c = line.split()
        a, c = int(a, 16), int(c)
        name = next((n for s, z, n in syms if s <= a < s + z), "?")
        tot[name] += c
    return tot.most_common()


def ask_compact(tr, rate: float) -> None:
    """SENSORS_REQUEST bit COMPACT, and the transport into the compact session once the
    leader enables it (RuntimeError when it does not answer)."""
    tr.send(fp.SensorsRequest(fp.FEATURE_COMPACT))
    end = time.monotonic() + 5
    while time.monotonic() < end:
        for m in tr.receive(0.05):
            if isinstance(m, fp.Sensors):
                if not m.enabled & fp.FEATURE_COMPACT:
                    raise RuntimeError("the leader did not enable the compact frames")
                tr.set_compact(rate)
                return
    raise RuntimeError("no SENSORS from the leader")


def measure(scene_path: str, rate: float, ticks: int, profile: bool = False,
            frames: str = "compact", host_latency_us: float | None = None) -> dict:
    """Run the board and the host; returns the board's report with the host's figures.

    Parameters
    ----------
    scene_path : str
        A 2-D pantograph scene (its geometry, home and dynamics).
    rate : float
        CONFIG rate [Hz] (the firmware takes 250..1000 Hz dividing 16 MHz).
    ticks : int
        Armed ticks answered.
    profile : bool
        Add the leader's busy cycles by function.
    frames : {"compact", "full"}
        The session's STATE and FORCE frames.
    host_latency_us : float, optional
        The emulated host answers each STATE this long after its last byte [us].

    Returns
    -------
    dict
        ``rate_hz``, ``frames``, ``ticks``, ``delay`` (the most common ``seq - force_seq``),
        ``late`` (STATEs whose lag is not that), ``budget``, ``twi``, ``firmware`` (the
        board's report sections) and ``profile`` when asked.
    """
    pb.build()
    scene = load_scene_nd(scene_path)
    q0 = [float(v) for v in scene.device.joints]
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "board.json"
        prof = Path(tmp) / "profile.txt"
        cmd = pb.board_command(scene, 1e-8, report=str(report),
                               profile=str(prof) if profile else None,
                               host_latency_us=host_latency_us)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
        lags = collections.Counter()
        try:
            port = proc.stdout.readline().split()[1]
            tr = SerialTransport(port)
            tr.send(fp.HelloRequest(fp.PROTOCOL_VERSION))
            if frames == "compact":
                ask_compact(tr, float(rate))
            tr.send(fp.Config(float(rate), int(20e6 / rate), 10.0))
            n = 0
            end = time.monotonic() + 60 + ticks / 100
            while n < ticks and time.monotonic() < end:
                for m in tr.receive(0.05):
                    if isinstance(m, fp.State) and m.status & fp.STATUS_ARMED:
                        q = m.position
                        tr.send(fp.Force(m.seq, tuple(-SPRING * (q[i] - q0[i])
                                                      for i in range(2))))
                        if m.status & fp.STATUS_FORCE_APPLIED:
                            lags[m.seq - m.force_seq] += 1
                        n += 1
            tr.send(fp.Stop())
            time.sleep(0.05)
            tr.close()
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=20)
        rep = json.loads(report.read_text())
        delay, count = lags.most_common(1)[0] if lags else (None, 0)
        out = {"rate_hz": rate, "frames": frames, "ticks": n, "delay": delay,
               "late": sum(lags.values()) - count, "budget": rep["budget"], "twi": rep["twi"],
               "firmware": rep["firmware"]}
        if profile:
            out["profile"] = _profile(prof)
    return out


def host_slack(scene_path: str, rate: float, frames: str, ticks: int = 300) -> dict:
    """The longest a host may take to answer (from the STATE's last byte leaving the leader
    to its FORCE's first byte reaching it) with every tick at one tick of delay: bisected
    to 1 us over the emulated host latency (lockstep: emulated cycles, load-independent).

    Returns
    -------
    dict
        ``frames``, ``rate_hz``, ``host_slack_us`` (-1 when even an instant answer misses
        the slot: the delay is 2 at this rate), ``ticks``.
    """
    def ok(lat):
        r = measure(scene_path, rate, ticks, frames=frames, host_latency_us=lat)
        return r["delay"] == 1 and r["late"] == 0 and r["firmware"]["overrun"] == 0
    if not ok(0.0):
        return {"frames": frames, "rate_hz": rate, "host_slack_us": -1, "ticks": ticks}
    lo, hi = 0.0, 1e6 / rate
    while hi - lo > 1.0:
        mid = round((lo + hi) / 2, 1)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return {"frames": frames, "rate_hz": rate, "host_slack_us": lo, "ticks": ticks}


def realtime_run(scene_path: str, amplitude: float = 2e-4, timeout: float = 300.0,
                 mock_args: tuple = ()) -> dict:
    """One real-time run: ``hapsim mock --firmware`` (real time) and ``hapsim run --port
    --json`` against it, as a user types them.

    Returns
    -------
    dict
        ``verdict``, ``reason``, ``late`` (rows whose FORCE missed its tick), ``rows``
        (rows used), ``late_fraction``, ``delay`` (per record), ``watchdog``, ``frames``,
        ``run_exit`` and ``run_error`` (the run's exit code, its last stderr line),
        ``board`` (the board's report: ``time``, ``firmware``, ``twi`` sections).
        ``mock_args``: more options of ``hapsim mock`` (``--spin-us``, ``--rt-priority``).
    """
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "board.json"
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        mock = subprocess.Popen([sys.executable, "-m", "hapsim", "mock", "--firmware",
                                 "--scene", scene_path, "--report", str(report),
                                 "--amplitude", repr(amplitude), *mock_args],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=env)
        try:
            line = mock.stdout.readline()
            if not line.startswith("PORT "):
                raise RuntimeError("the emulated board did not start: "
                                   + (mock.stderr.read() or line)[-300:])
            r = subprocess.run([sys.executable, "-m", "hapsim", "run", scene_path, "--port",
                                line.split()[1], "--amplitude", repr(amplitude), "--json"],
                               capture_output=True, text=True, timeout=timeout, env=env)
        finally:
            mock.send_signal(signal.SIGTERM)
            try:
                mock.wait(timeout=20)
            except subprocess.TimeoutExpired:
                mock.kill()
                mock.wait()
        board = json.loads(report.read_text()) if report.exists() else {}
    out = {"run_exit": r.returncode,
           "run_error": (r.stderr.strip().splitlines() or [""])[-1] if r.returncode else None,
           "board": {k: board.get(k) for k in ("time", "firmware", "twi")}}
    if r.returncode == 0:
        d = json.loads(r.stdout)
        rows = sum(d.get("rows") or [])
        dev = (d.get("port") or {}).get("device") or ""
        out.update(verdict=d["verdict"], reason=d["reason"], late=d["late"], rows=rows,
                   late_fraction=d["late"] / rows if rows else None, delay=d["delay"],
                   watchdog=d["watchdog"],
                   frames="compact" if "compact frames" in dev else "full")
    return out


def realtime(scene_path: str, runs: int, amplitude: float = 2e-4,
             mock_args: tuple = ()) -> dict:
    """``runs`` real-time runs (:func:`realtime_run`) and their summary, with the
    machine's conditions (``tools/bench_firmware.py``'s :func:`machine`, the load
    average before and after: ``loaded`` when above half a core per core)."""
    sys.path.insert(0, str(ROOT / "tools"))
    from bench_firmware import machine
    load0 = os.getloadavg()
    rows = []
    for i in range(runs):
        rows.append(realtime_run(scene_path, amplitude, mock_args=mock_args))
        r = rows[-1]
        print(f"run {i + 1}/{runs}: " + (f"{r['verdict']}, late {r['late']} of {r['rows']} "
              f"rows, board slips {r['board']['time']['slips']}, emulation "
              f"{r['board']['time']['armed_mhz']:.0f} MHz" if r["run_exit"] == 0
              else f"run failed (exit {r['run_exit']}): {r['run_error']}"), flush=True)
    load1 = os.getloadavg()
    fr = [r["late_fraction"] for r in rows if r.get("late_fraction") is not None]
    verdicts = collections.Counter(r.get("verdict", "failed") for r in rows)
    cores = os.cpu_count() or 1
    return {"runs": rows, "verdicts": dict(verdicts), "mock_args": list(mock_args),
            "late_fraction": {"median": sorted(fr)[len(fr) // 2] if fr else None,
                              "max": max(fr) if fr else None},
            "load_before": load0, "load_after": load1,
            "loaded": max(load0[0], load1[0]) > 0.5 * cores,
            "machine": machine()}


def main(argv=None) -> int:
    """Print the budget table (and write ``--json``); exit 1 when a tick was late or the
    delay is not one tick."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=str(ROOT / "configs" / "pantograph_wall.yaml"))
    p.add_argument("--rates", default="1000,500", help="CONFIG rates [Hz], comma-separated")
    p.add_argument("--ticks", type=int, default=1000)
    p.add_argument("--frames", default="compact,full",
                   help="compact and/or full, comma-separated (default both)")
    p.add_argument("--json", metavar="FILE")
    p.add_argument("--profile", action="store_true")
    p.add_argument("--host-slack", action="store_true",
                   help="also bisect the host's time to answer that keeps one tick of delay")
    p.add_argument("--realtime", type=int, metavar="N",
                   help="instead: N real-time runs (hapsim mock --firmware, hapsim run "
                        "--port) and their late ticks and verdicts")
    p.add_argument("--amplitude", type=float, default=2e-4,
                   help="--realtime: the hand's and the run's amplitude [m]")
    p.add_argument("--mock-args", default="",
                   help="--realtime: more options of hapsim mock, e.g. '--spin-us 0'")
    args = p.parse_args(argv)
    if args.realtime:
        pb.build()
        res = realtime(args.scene, args.realtime, args.amplitude,
                       tuple(args.mock_args.split()))
        print(f"verdicts {res['verdicts']}; late fraction median "
              f"{res['late_fraction']['median']}, max {res['late_fraction']['max']}; load "
              f"{res['load_before'][0]:.1f} -> {res['load_after'][0]:.1f} on "
              f"{res['machine']['cores']} cores" + (" (loaded)" if res["loaded"] else ""))
        if args.json:
            command = "PYTHONPATH=. python tools/bench_pantograph.py " + " ".join(
                argv if argv is not None else sys.argv[1:])
            Path(args.json).write_text(json.dumps({"command": command, **res}, indent=1)
                                       + "\n")
        # a verdict "differs" in real time is a wrong one (the lockstep run is within or
        # not measurable): the account of the late ticks failed
        return 1 if res["verdicts"].get("differs") or res["verdicts"].get("failed") else 0
    rows = [measure(args.scene, float(r), args.ticks, args.profile, f)
            for f in args.frames.split(",") for r in args.rates.split(",")]
    print("| frames | rate | period | leader busy mean / max | follower busy mean / max | "
          "slack min / mean | delay | late | overruns |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    bad = False
    for r in rows:
        b, t = r["budget"], r["twi"]
        print(f"| {r['frames']} | {r['rate_hz']:g} Hz | {b['period_cycles']:.0f} | "
              f"{b['leader_busy_mean_cycles']:.0f} / {b['leader_busy_max_cycles']} | "
              f"{b['follower_busy_mean_cycles']:.0f} / {b['follower_busy_max_cycles']} | "
              f"{t['slack_min_cycles']} / {t['slack_mean_cycles']:.0f} | {r['delay']} | "
              f"{r['late']} | {r['firmware']['overrun']} |")
        # the compact frames must keep one tick of delay; the full ones at 1 kHz miss
        # the DRIVE slot (their delay is what it is: reported, not a failure)
        bad = bad or r["firmware"]["overrun"] > 0 or (
            r["frames"] == "compact" and (r["late"] > 0 or r["delay"] != 1))
        if args.profile:
            tot = sum(c for _, c in r["profile"])
            for name, c in r["profile"][:12]:
                print(f"    {name:32s} {c / max(r['ticks'], 1):8.0f} cycles/tick "
                      f"{c / tot:6.1%}")
    slack = []
    if args.host_slack:
        for f in args.frames.split(","):
            for r in args.rates.split(","):
                h = host_slack(args.scene, float(r), f)
                slack.append(h)
                print(f"host slack, {f} frames at {float(r):g} Hz: {h['host_slack_us']:g} us")
    if args.json:
        # paths as the command takes them in a clone (relative to it), not this machine's
        scene = Path(args.scene).resolve()
        scene = str(scene.relative_to(ROOT)) if scene.is_relative_to(ROOT) else args.scene
        command = command_line("tools/bench_pantograph.py", argv,
                               prefix="PYTHONPATH=. python")
        Path(args.json).write_text(json.dumps({"command": command, "scene": scene,
                                               "rows": rows, "host_slack": slack},
                                              indent=1) + "\n")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
