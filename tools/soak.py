#!/usr/bin/env python3
"""Soak test of the hapsim daemon: N minutes at 1 kHz over a pty with random faults.

Not a test (no assertions): a program that runs ``run_scene`` on the embedded mock (a
child process behind a real pseudo-terminal, real time) with a seeded random fault plan and
a hand force that keeps the loop moving, and prints what happened:

- faults injected (by the mock), losses and recoveries (by the host), reconnect attempts;
- frames lost: STATEs the host never used (gaps, bad frames, stale), ticks the mock made
  while the host had lost it;
- the largest force sent, the energy the scene gave the hand;
- memory: RSS (``VmRSS`` of ``/proc/PID/status``) of the host and of the mock child,
  sampled every 10 s (a quarter of the run when shorter), growth from the first sample
  after one minute (warm-up; the first sample in a shorter run) to the end;
- turnaround percentiles; bad frames recorded, implausible STATEs, telemetry rows the
  journal writer lost, events journaled;
- the git commit (and whether the work tree had changes) it ran at.

Usage::

    PYTHONPATH=. python tools/soak.py --minutes 10 --seed 1 --json docs/soak.json
    PYTHONPATH=. python tools/soak.py --minutes 0.2 --json /tmp/smoke.json   # smoke run
    # issue 13: 30 min of configs/wall.yaml beside two CPU-bound processes, no faults, then
    # the same with the faults (--loop python for the reference loop)
    PYTHONPATH=. python tools/soak.py --minutes 30 --stress 2 --faults none --scene configs/wall.yaml
    PYTHONPATH=. python tools/soak.py --minutes 30 --stress 2 --scene configs/wall.yaml

Default fault SPEC (per frame / per tick at 1 kHz, so about one stall, reset or vanish a
minute; host -> device frames are faulted too, ``rx.*``): see ``DEFAULT_FAULTS``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import threading
import time

import numpy as np

from provenance import portable_path  # tools/, beside this file

#: Faults of the soak: wire faults per frame in both directions (device -> host, and
#: host -> device as ``rx.*``), device faults per tick (1 kHz).
DEFAULT_FAULTS = ("drop=0.002,corrupt=0.001,garbage=0.0005,dup=0.0005,reorder=0.0005,"
                  "spike=0.0005:5ms,"
                  "rx.drop=0.002,rx.corrupt=0.001,rx.garbage=0.0005,rx.dup=0.0005,"
                  "rx.reorder=0.0005,rx.spike=0.0005:5ms,"
                  "stall=0.00002:200ms,reset=0.00002,vanish=0.00001:300ms")

SCENE = """\
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: 0.0}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000.0, damping: 1.5}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10.0}
excitation:
  x0: 0.005
  profile: hand.csv
safety: {position_limit: 0.1, velocity_limit: 5.0, energy_limit: 5.0}
"""


def rss_kb(pid: int | str = "self") -> int | None:
    """Resident memory of a process.

    Parameters
    ----------
    pid : int or str
        Process id, or ``"self"``.

    Returns
    -------
    int or None
        ``VmRSS`` [kB] from ``/proc/PID/status``; None when the process is gone (or no
        ``/proc``).
    """
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def mock_children() -> list[int]:
    """The embedded mock devices this process started.

    Returns
    -------
    list of int
        PIDs of this process's children whose command line contains ``mock`` (from
        ``/proc``; empty without it).
    """
    me = os.getpid()
    out = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
            if ppid != me:
                continue
            with open(f"/proc/{d}/cmdline", "rb") as fh:
                if b"mock" in fh.read():
                    out.append(int(d))
        except (OSError, ValueError, IndexError):
            continue
    return out


def git_commit() -> dict:
    """The git commit this tool runs at.

    Returns
    -------
    dict
        ``commit`` (40 hex digits, or None outside a git work tree / without git) and
        ``dirty`` (True when tracked files differ from the commit; None when unknown).
    """
    import subprocess
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                                text=True, timeout=10, check=True).stdout.strip()
        dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                                    cwd=root, capture_output=True, text=True, timeout=10,
                                    check=True).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": commit, "dirty": dirty}


def start_stress(n: int, seconds: float) -> list:
    """Start ``n`` CPU-bound processes (``stress-ng --cpu n``, else ``n`` Python busy
    loops) for at most ``seconds``; their ``Popen`` objects (terminated by the caller)."""
    import shutil
    import subprocess
    if n <= 0:
        return []
    if shutil.which("stress-ng"):
        return [subprocess.Popen(["stress-ng", "--cpu", str(n), "--timeout", f"{int(seconds)}s",
                                  "--quiet"])]
    return [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(n)]


def main(argv=None) -> int:
    """Run the soak and print (and optionally write) its figures as JSON.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (default ``sys.argv[1:]``): ``--minutes``, ``--seed``,
        ``--faults``, ``--json FILE``, ``--telemetry FILE.hst``.

    Returns
    -------
    int
        0 when the run ended without an exception, 1 otherwise (the figures are printed
        either way).
    """
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--faults", default=DEFAULT_FAULTS)
    ap.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    ap.add_argument("--telemetry", metavar="FILE.hst", help="keep the telemetry journal")
    ap.add_argument("--stress", type=int, default=0, metavar="N",
                    help="run N CPU-bound processes beside it (stress-ng --cpu N, else "
                         "python busy loops)")
    ap.add_argument("--loop", choices=("compiled", "python"), default="compiled",
                    help="host loop (default compiled)")
    ap.add_argument("--keep-going", action="store_true",
                    help="after a safety stop or an error, start the next run for the time "
                         "left, and report every run and the totals (the figures of a whole "
                         "soak on a loaded machine)")
    ap.add_argument("--scene", metavar="FILE.yaml",
                    help="run this scene (e.g. configs/wall.yaml) instead of the built-in wall "
                         "with a moving hand")
    args = ap.parse_args(argv)
    if args.faults in ("none", ""):
        args.faults = None

    from hapsim.pipeline.runner import run_scene
    from hapsim.host.telemetry import load
    from hapsim.scene import load_scene

    tmp = tempfile.mkdtemp(prefix="hapsim-soak-")
    duration = args.minutes * 60.0
    t = np.arange(0.0, duration + 1.0, 0.01)
    hand = 0.3 * np.sin(2 * math.pi * 0.7 * t) + 0.2 * np.sin(2 * math.pi * 3.1 * t)
    np.savetxt(os.path.join(tmp, "hand.csv"), np.column_stack([t, hand]), delimiter=",",
               header="time,force", comments="")
    with open(os.path.join(tmp, "soak.yaml"), "w") as fh:
        fh.write(SCENE)
    scene = load_scene(args.scene or os.path.join(tmp, "soak.yaml"))
    tel_path = args.telemetry or os.path.join(tmp, "soak.hst")
    tel_base = tel_path[:-4] if tel_path.endswith(".hst") else tel_path

    samples = []          # (t [s], host RSS [kB], mock RSS [kB])
    segments = []         # --keep-going: one entry per run
    done = threading.Event()
    t0 = time.monotonic()

    every = min(10.0, max(duration / 4.0, 1.0))

    def sampler():
        shown = 0.0
        while not done.wait(every):
            kids = mock_children()
            now = time.monotonic() - t0
            samples.append((now, rss_kb(), rss_kb(kids[0]) if kids else None))
            if now - shown >= 60.0:        # progress, once a minute, on stderr
                shown = now
                print(f"soak: {now / 60:.1f} of {args.minutes:g} min, host RSS "
                      f"{samples[-1][1]} kB, runs so far {len(segments) + 1}",
                      file=sys.stderr, flush=True)

    th = threading.Thread(target=sampler, daemon=True)
    th.start()
    rev = git_commit()
    print(f"soak: {args.minutes:g} min at 1 kHz over a pty, faults {args.faults} "
          f"(seed {args.seed}) at commit {rev['commit']}"
          f"{' (with local changes)' if rev['dirty'] else ''}", file=sys.stderr, flush=True)
    error = None
    rep = None
    hogs = start_stress(args.stress, duration + 120.0)
    try:
        while True:
            left = duration - (time.monotonic() - t0)
            if segments:
                tel_path = f"{tel_base}.{len(segments)}.hst"
            error, rep = None, None
            try:
                rep = run_scene(scene, duration=left, faults=args.faults,
                                fault_seed=args.seed + len(segments), telemetry=tel_path,
                                handle_signals=True, reconnect_attempts=20,
                                reconnect_time=30.0, loop=args.loop)
            except Exception as exc:  # the soak reports whatever ended it
                error = f"{type(exc).__name__}: {exc}"
            lp = (rep or {}).get("loop") or {}
            segments.append({"at_s": round(time.monotonic() - t0, 1),
                             "samples": lp.get("ticks"), "stop_reason": lp.get("stop_reason",
                                                                                error),
                             "lost": lp.get("lost"), "recovered": lp.get("recovered"),
                             "late": lp.get("late"), "skipped": lp.get("skipped"),
                             # the journal's path as a clone reads it; None when it was
                             # this run's temporary directory (--telemetry not given)
                             "telemetry": portable_path(tel_path) if args.telemetry else None})
            if not args.keep_going or lp.get("stop_reason") == "duration" \
                    or duration - (time.monotonic() - t0) < 10.0:
                break
    finally:
        for h in hogs:
            h.terminate()
            h.wait()
    done.set()
    wall = time.monotonic() - t0
    info: dict = {}
    cols = load(tel_path, info=info)
    f = cols["force"]
    out = {"git_commit": rev["commit"], "git_dirty": rev["dirty"],
           "scene": portable_path(args.scene) if args.scene else "built-in wall with a moving hand",
           "minutes": args.minutes, "wall_s": round(wall, 1), "faults_spec": args.faults,
           "seed": args.seed, "error": error, "telemetry_rows": int(cols["seq"].size),
           "stress_processes": args.stress, "loop": args.loop,
           "telemetry_chunks": info.get("chunks"),
           "telemetry_events": len(info.get("events") or []),
           "telemetry_gaps": info.get("gaps"),
           "max_abs_force_logged_n": float(np.max(np.abs(f))) if f.size else None}
    if rep is not None:
        lp = rep["loop"]
        mk = lp.get("mock") or {}
        dec = lp.get("decoder") or {}
        bad = sum(v for k, v in dec.items() if k != "frames_ok")
        out.update({
            "samples": lp["ticks"], "requested": lp["requested"],
            "stop_reason": lp["stop_reason"],
            "faults_injected": (lp.get("fault_plan") or {}).get("injected"),
            "lost": lp["lost"], "recovered": lp["recovered"],
            "reconnect_attempts": lp["reconnect_attempts"],
            "missed_states": lp["missed"], "stale_states": lp["stale"],
            "bad_frames": bad, "decoder": dec, "late": lp["late"],
            "skipped": lp.get("skipped"), "safety_stop": lp.get("safety_stop"),
            "compiled_samples": lp.get("compiled_samples"),
            "late_rows_logged": int(np.count_nonzero(cols["late"])) if "late" in cols else None,
            "mock_ticks_total": (mk.get("totals") or {}).get("ticks"),
            "mock_configs": (mk.get("totals") or {}).get("configs"),
            "mock_watchdog_trips_total": (mk.get("totals") or {}).get("watchdog_trips"),
            "max_force_n": lp["f_max"], "force_limit_n": scene.device.force_limit,
            "energy_max_j": lp["energy_max_j"],
            "energy_excess_max_j": lp.get("energy_excess_max_j"), "v_max": lp["v_max"],
            "turnaround_us": lp["turnaround_us"],
            "bad_frames_recorded": len(lp.get("bad_frames") or []),
            "implausible_states": lp.get("implausible"),
            "device_rx_decoder": mk.get("decoder"),
            "telemetry_lost_rows": (rep.get("telemetry") or {}).get("lost_rows"),
            "state_at_end": lp.get("state"),
        })
        if out["mock_ticks_total"] is not None:
            out["frames_lost"] = int(out["mock_ticks_total"] - lp["ticks"])
        # the criteria: no loss and no safety stop without faults, every loss
        # recovered with them, every late tick counted (the report's count = the late
        # rows of the telemetry)
        out["verdict"] = {"no_loss": lp["lost"] == 0,
                          "no_safety_stop": not lp.get("safety_stop"),
                          "every_loss_recovered": lp["lost"] == lp["recovered"],
                          "every_late_tick_logged": lp["late"] == out["late_rows_logged"],
                          "ran_to_the_end": lp["ticks"] == lp["requested"]}
    warm = [s for s in samples if s[0] >= 60.0] or samples
    if warm:
        first, last = warm[0], samples[-1]
        out["rss_host_kb"] = {"first_after_warmup": first[1], "end": last[1],
                              "growth": (last[1] - first[1]) if first[1] and last[1] else None,
                              "max": max(s[1] for s in samples if s[1])}
        ms = [s for s in warm if s[2]]
        if ms:
            out["rss_mock_kb"] = {"first_after_warmup": ms[0][2], "end": ms[-1][2],
                                  "growth": ms[-1][2] - ms[0][2],
                                  "max": max(s[2] for s in ms)}
    out["rss_samples"] = samples
    if args.keep_going:
        # every run of the soak (a safety stop or an error ends one; the next one starts)
        out["runs"] = segments
        out["totals"] = {k: sum(g[k] or 0 for g in segments)
                         for k in ("samples", "lost", "recovered", "late", "skipped")}
        out["totals"]["runs"] = len(segments)
        out["totals"]["safety_stops"] = sum(1 for g in segments
                                            if str(g["stop_reason"]).startswith("safety"))
    text = json.dumps(out, indent=1)
    print(text)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text + "\n")
    return 0 if error is None else 1


if __name__ == "__main__":
    sys.exit(main())
