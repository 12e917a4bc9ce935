"""Run what a user runs against the independent board models, as a user would, and
tabulate what happened (``docs/testing.md``, "Independent board models").

Usage::

    python tools/independent_boards/run_checks.py [--drivers haply firefader hapkit-serial]
        [--conditions clean loss stall] [--seeds 1 2 ... 10] [--hogs 2] [--duration 1.5]
        [--board-opt DRIVER=--torque-levels=0 ...] [--json PATH]

For each driver, condition and seed: the driver's independent board
(``tools/independent_boards/``: ``haply_m3.py``, ``firefader_ino.py``,
``hapkit_sketch.py``) on a fresh pty, then ``hapsim run configs/<scene> --driver NAME
--port PTY --json`` as a separate process, beside ``--hogs`` CPU-bound processes
(``python3 -c 'while 1: pass'``, started and ended here by their pids). Conditions:
``clean`` (no fault); ``loss`` (1 byte in 200 lost each way, seeded, at the board's end);
``stall`` (the ``hapsim run`` process stopped with SIGSTOP and continued with SIGCONT
``--stalls`` times, 6-60 ms each, at seeded moments of its loop: every thread of the host
stops, its watchdog's process and the board run on); ``lossstall`` both.

Each row: the exit code, the verdict, the measured and predicted (k, b) and the stated
half-widths, the truth's (k, b) (the felt pair of the board's own loop: the scene's
device with the board's true timing, ``true_delay``) and whether it lies in the stated
interval, the safety stop, re-synchronisations and their reasons, the host stalls, the
watchdog, and from the board's truth log: the longest time a non-zero force was held
with no command taking effect, the largest excursion from the spring's rest in the host's
first frame against the run's position limit, the bytes lost each way. A measurement
program (real time on a shared machine; the load average is in the JSON), not a test.

The Haply M3's encoder offset (``offset_deg``, the host frame's angle at arming) is given
in a device file written here, as a user of a real board gives it: the joint's start.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
BOARDS = {
    "haply": ("haply_m3.py", "configs/haply.yaml", ["--x0", "0.2"]),
    "firefader": ("firefader_ino.py", "configs/firefader.yaml", ["--x0", "0.015"]),
    "hapkit-serial": ("hapkit_sketch.py", "configs/hapkit_serial.yaml", ["--x0", "0.01"]),
}
LOSS = 0.005
#: ``hapsim identify``'s options per driver (``--identify``): the scenes' rates and force
#: limits, an envelope inside each board's travel.
IDENTIFY = {
    "haply": ["--rate", "1000", "--duration", "2", "--force-limit", "0.1", "--envelope", "1",
              "--max-delay", "4"],
    "firefader": ["--rate", "250", "--duration", "3", "--force-limit", "0.38", "--envelope",
                  "0.02"],
    "hapkit-serial": ["--rate", "201.613", "--duration", "3", "--force-limit", "1.0",
                      "--envelope", "0.02"],
}


def _hogs(n: int) -> list:
    return [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(n)]


def _device_file(path: str, scene_path: str, options: dict) -> None:
    """A device section from the scene's, with ``protocol_options`` (what a user of a
    real board writes, or ``hapsim identify --out`` gives)."""
    import yaml
    with open(os.path.join(ROOT, scene_path)) as fh:
        dev = dict(yaml.safe_load(fh)["device"])
    dev["protocol_options"] = options
    with open(path, "w") as fh:
        yaml.safe_dump({"device": dev}, fh)


class Staller(threading.Thread):
    """Stops the host's process ``n`` times for 6-60 ms at seeded moments of its loop
    (from the line that says the loop closes, within ``duration`` [s] of it: the run's
    own length is at least 1 s); records what it did."""

    def __init__(self, proc, n: int, duration: float, seed: int, stderr_lines) -> None:
        super().__init__(daemon=True)
        self.proc, self.n, self.duration = proc, n, duration
        self.rng = random.Random(seed * 7 + 3)
        self.lines = stderr_lines
        self.done: list = []

    def run(self) -> None:
        t_end = time.monotonic() + 120
        while time.monotonic() < t_end:
            if any("closing the loop" in ln for ln in list(self.lines)):
                break
            if self.proc.poll() is not None:
                return
            time.sleep(0.005)
        t0 = time.monotonic()
        at = sorted(self.rng.uniform(0.05, self.duration) for _ in range(self.n))
        for a in at:
            ms = self.rng.uniform(6.0, 60.0)
            while time.monotonic() < t0 + a:
                time.sleep(0.001)
            if self.proc.poll() is not None:
                return
            s = time.monotonic()
            try:
                os.kill(self.proc.pid, signal.SIGSTOP)
                time.sleep(ms / 1e3)
            finally:
                os.kill(self.proc.pid, signal.SIGCONT)
            self.done.append({"at_s": round(s - t0, 4), "asked_ms": round(ms, 2),
                              "ms": round((time.monotonic() - s) * 1e3, 2)})


def true_pair(driver: str, truth: dict, run: dict) -> tuple:
    """The felt (k, b) of the board's own loop: the scene's device, the virtual (K, B)
    run, and the board's true delay [periods] (its firmware's timing, module notes)."""
    from hapsim.analysis.loop import LoopModel
    from hapsim.analysis.ths import render
    p = truth.get("params", {})
    rate = 1.0 / run["_period"]
    T = run["_period"]
    if driver == "haply":
        m, b0, d = p["inertia"], p["friction"], 1.0
    elif driver == "firefader":
        m, b0 = p["mass"], p["friction"]
        d = 1.0 - float(truth["pot_read_after_pwm_s"]) / T
    else:
        m, b0 = p["mass"], p["friction"]
        d = 1.0 + (float(p["render_us"]) - 12.0) * 1e-6 / T
    v = run.get("virtual") or {}
    r = render(LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d, hold="zoh"),
               float(v.get("port_K", v.get("K"))), float(v.get("port_B", v.get("B"))))
    return float(r.k), float(r.b), d


def _tail(path: str, n: int = 500) -> str:
    """The last ``n`` characters of a text file ("" if it cannot be read)."""
    try:
        with open(path, errors="replace") as fh:
            return fh.read()[-n:]
    except OSError:
        return ""


def _commit(root: str) -> str:
    """The commit of the hapsim the runs ran (``git rev-parse --short HEAD`` in ``root``),
    "+ changes" when its tree differs from it; "unknown" outside a checkout (an export)."""
    try:
        head = subprocess.run(["git", "-C", root, "rev-parse", "--short=8", "HEAD"],
                              capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "-C", root, "status", "--porcelain", "--",
                                "hapsim"], capture_output=True, text=True, timeout=10)
        return head.stdout.strip() + (" + changes" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def one_run(driver: str, condition: str, seed: int, args, tmp: str) -> dict:
    """One board and one ``hapsim run`` (module notes); the row."""
    script, scene, bopts = BOARDS[driver]
    link = os.path.join(tmp, f"{driver}-{condition}-{seed}.pty")
    truth_path = os.path.join(tmp, f"{driver}-{condition}-{seed}.json")
    ready = os.path.join(tmp, f"{driver}-{condition}-{seed}.ready")
    loss = LOSS if "loss" in condition else 0.0
    extra = [o.replace("=", " ", 1).split(" ") if o.startswith("--") else [o]
             for o in args.board_opt.get(driver, [])]
    if args.identify:
        # identification starts where the hand leaves the handle: the envelope's centre
        # (hapsim identify says why it stops when a device rests off-centre)
        bopts = ["--x0", str(args.identify_x0)]
    cmd = [sys.executable, os.path.join(HERE, script), "--link", link, "--ready", ready,
           "--truth", truth_path, "--seed", str(seed), "--drop-rx", str(loss),
           "--drop-tx", str(loss), "--rt-priority", str(args.board_priority), *bopts]
    for e in extra:
        cmd += e
    # the board's messages in a file of the run's directory (a pipe nobody reads would
    # stop a board that writes more than its buffer), read back when its truth is missing
    board_log = os.path.join(tmp, f"{driver}-{condition}-{seed}.board.txt")
    with open(board_log, "w") as log:
        board = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log, text=True)
    t_end = time.monotonic() + 20
    while not os.path.exists(ready) and time.monotonic() < t_end and board.poll() is None:
        time.sleep(0.01)
    row = {"driver": driver, "condition": condition, "seed": seed,
           "board_opts": args.board_opt.get(driver, [])}
    if not os.path.exists(ready):
        board.kill()
        row["error"] = "board did not start: " + _tail(board_log)
        return row
    hcmd = [sys.executable, "-m", "hapsim", "run", scene, "--driver", driver, "--port", link,
            *(["--duration", str(args.duration)] if args.duration is not None else []),
            *(["--telemetry", os.path.join(args.keep, f"{driver}-{condition}-{seed}.npz")]
              if args.telemetry and args.keep else []),
            "--json"]
    if args.identify:
        hcmd = [sys.executable, "-m", "hapsim", "identify", "--driver", driver, "--port",
                link, "--json", *IDENTIFY[driver]]
    if driver == "haply" and not args.identify:
        dev = os.path.join(tmp, "m3_device.yaml")
        _device_file(dev, scene, {"offset_deg": math.degrees(0.2)})
        hcmd += ["--device", dev]
    lines: list = []
    out_path = os.path.join(tmp, f"{driver}-{condition}-{seed}.out")
    root = args.hapsim_root or ROOT
    env = dict(os.environ)
    if args.hapsim_root:
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    with open(out_path, "w") as out:
        proc = subprocess.Popen(hcmd, cwd=root, stdout=out, stderr=subprocess.PIPE,
                                text=True, env=env)
        reader = threading.Thread(target=lambda: lines.extend(iter(proc.stderr.readline, "")),
                                  daemon=True)
        reader.start()
        staller = None
        if "stall" in condition:
            staller = Staller(proc, args.stalls, args.duration or 1.0, seed, lines)
            staller.start()
        try:
            rc = proc.wait(timeout=args.timeout)
            hung = False
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGCONT)
            proc.terminate()
            try:
                rc = proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                rc = proc.wait()
            hung = True
        reader.join(timeout=5)
        if staller is not None:
            staller.join(timeout=5)
    board.terminate()
    try:
        board.wait(timeout=20)
    except subprocess.TimeoutExpired:
        board.kill()
    # (the run's directory named, not its machine path: the JSON is committed)
    row.update(exit_code=rc, hung=hung,
               stderr_tail="".join(lines[-4:])[-800:].replace(tmp, "<RUN_DIR>"))
    if staller is not None:
        row["stalls"] = staller.done
    try:
        truth = json.load(open(truth_path))
    except (OSError, ValueError) as exc:
        truth = {}
        row["truth_error"] = str(exc).replace(tmp, "<RUN_DIR>")
        row["board_exit"] = board.returncode
        row["board_tail"] = _tail(board_log).replace(tmp, "<RUN_DIR>")
    try:
        run = json.load(open(out_path))
    except (OSError, ValueError) as exc:
        run = {}
        row["run_error"] = f"{type(exc).__name__}: {exc}"
    if args.identify:
        _fill_identify(row, run, truth)
    else:
        _fill(row, driver, run, truth)
    # (the run's directory named, not its machine path, in every field: committed JSON)
    return {k: v.replace(tmp, "<RUN_DIR>") if isinstance(v, str) else v
            for k, v in row.items()}


def _fill_identify(row: dict, rep: dict, truth: dict) -> None:
    """An identification's row: the mass and friction found with their intervals against
    the board's own (the truth log's), the delay, the fit's verdict."""
    p = truth.get("params", {})
    true = {"mass": p.get("inertia", p.get("mass")), "friction": p.get("friction")}
    row.update(verdict=(rep.get("error") or {}).get("message") or rep.get("verdict")
               or rep.get("model_verdict"),
               longest_hold_s=truth.get("longest_hold_s"),
               excursion_true=truth.get("excursion"), lost_in=truth.get("counters", {}).get(
                   "lost_in"), lost_out=truth.get("counters", {}).get("lost_out"))
    dev = rep.get("device") or {}
    for q in ("mass", "friction"):
        est = dev.get(q) or {}
        row[q] = est.get("value")
        row[q + "_true"] = true[q]
        row[q + "_interval"] = [est.get("lo"), est.get("hi")]
        if None not in (est.get("lo"), est.get("hi"), true[q]):
            row[q + "_truth_in_interval"] = bool(est["lo"] <= true[q] <= est["hi"])
    lp = rep.get("loop") or {}
    row.update(delay=dev.get("delay"), model_verdict=dev.get("verdict"),
               safety_stop=lp.get("safety_stop"), stop_reason=lp.get("stop_reason"),
               resyncs=(lp.get("driver") or {}).get("resyncs"))
    row["truth_in_interval"] = bool(row.get("mass_truth_in_interval")
                                    and row.get("friction_truth_in_interval"))


def _fill(row: dict, driver: str, run: dict, truth: dict) -> None:
    """The row's fields from the run's JSON and the board's truth log."""
    m = run.get("measured") or {}
    lp = run.get("loop") or {}
    dl = lp.get("driver") or {}
    pr = run.get("predicted") or {}
    row.update(
        verdict=(m.get("verdict") or run.get("verdict") or
                 (run.get("error") or {}).get("message")),
        within=m.get("within"), k=m.get("k"), b=m.get("b"),
        k_unc=m.get("k_unc"), b_unc=m.get("b_unc"),
        k_pred=pr.get("k"), b_pred=pr.get("b"),
        safety_stop=lp.get("safety_stop"), stop_reason=lp.get("stop_reason"),
        resyncs=dl.get("resyncs"),
        resync_reasons={k: v for k, v in (dl.get("resync_reasons") or {}).items() if v},
        missing=dl.get("missing"), host_stalls=dl.get("host_stalls", lp.get("overruns")),
        watchdog={k: (dl.get("watchdog") or {}).get(k) for k in ("fired", "robust",
                                                                   "longest_s")},
        workspace=(lp.get("safety") or {}).get("position_limit"),
        tick_probe=dl.get("tick_probe"),
        reason=run.get("reason") if not m.get("verdict") else None,
    )
    if truth:
        ref = truth.get("first_frame_zero") or 0.0
        excursion = truth.get("excursion")
        row.update(longest_hold_s=truth.get("longest_hold_s"),
                   excursion_true=None if excursion is None else excursion + abs(ref),
                   stop_hits=truth.get("stop_hits"),
                   lost_in=truth.get("counters", {}).get("lost_in"),
                   lost_out=truth.get("counters", {}).get("lost_out"),
                   board_counters=truth.get("counters"),
                   board_late_max_s=truth.get("server_late_max_s"),
                   board_scheduling=truth.get("scheduling"),
                   frame_walk=truth.get("frame_walk"),
                   misparsed=truth.get("misparsed_commands"),
                   silence_zeroings=truth.get("silence_zeroings"))
        if run.get("loop") and m.get("k") is not None:
            try:
                run["_period"] = 1.0 / float(_scene_rate(BOARDS[driver][1]))
                kt, bt, d = true_pair(driver, truth, run)
                row.update(k_true=kt, b_true=bt, true_delay=d)
                if m.get("k_unc") is not None:
                    row["truth_in_interval"] = bool(
                        abs(kt - m["k"]) <= m["k_unc"] and abs(bt - m["b"]) <= m["b_unc"])
            except Exception as exc:    # noqa: BLE001 - a row says why, the table goes on
                row["truth_pair_error"] = f"{type(exc).__name__}: {exc}"


def _scene_rate(scene: str) -> float:
    import yaml
    with open(os.path.join(ROOT, scene)) as fh:
        return float(yaml.safe_load(fh)["rate_hz"])


def _short(v) -> str:
    v = str(v)
    for key in ("within the stated", "differs", "not measurable", "not identified"):
        if key in v:
            return {"within the stated": "within"}.get(key, key)
    return v[:30]


def summarize(rows: list) -> dict:
    """Per driver and condition: runs, exit codes, verdicts, truth in interval, safety
    stops, re-synchronisations, longest hold, largest excursion."""
    out: dict = {}
    for r in rows:
        s = out.setdefault(f"{r['driver']} {r['condition']}", {
            "runs": 0, "exit_codes": {}, "verdicts": {}, "truth_in_interval": 0,
            "truth_checked": 0, "safety_stops": 0, "resyncs_max": 0, "runs_resynced": 0,
            "longest_hold_s_max": 0.0, "excursion_true_max": 0.0, "hung": 0, "errors": 0})
        s["runs"] += 1
        s["exit_codes"][str(r.get("exit_code"))] = s["exit_codes"].get(
            str(r.get("exit_code")), 0) + 1
        v = _short(r.get("verdict"))
        s["verdicts"][v] = s["verdicts"].get(v, 0) + 1
        if r.get("truth_in_interval") is not None:
            s["truth_checked"] += 1
            s["truth_in_interval"] += bool(r["truth_in_interval"])
        s["safety_stops"] += bool(r.get("safety_stop"))
        s["resyncs_max"] = max(s["resyncs_max"], r.get("resyncs") or 0)
        s["runs_resynced"] += bool(r.get("resyncs"))
        s["longest_hold_s_max"] = max(s["longest_hold_s_max"], r.get("longest_hold_s") or 0)
        s["excursion_true_max"] = max(s["excursion_true_max"], r.get("excursion_true") or 0)
        s["hung"] += bool(r.get("hung"))
        s["errors"] += bool(r.get("error") or r.get("run_error"))
        s["workspace"] = r.get("workspace")
    for s in out.values():
        # flat counts for the documentation's tables (docs/testing.md)
        for v in ("within", "differs", "not measurable"):
            s["n_" + v.replace(" ", "_")] = s["verdicts"].get(v, 0)
        s["n_other"] = s["runs"] - sum(s["verdicts"].get(v, 0) for v in (
            "within", "differs", "not measurable"))
        s["exit_0"] = s["exit_codes"].get("0", 0)
        s["exit_1"] = s["exit_codes"].get("1", 0)
        s["exit_other"] = s["runs"] - s["exit_0"] - s["exit_1"]
    return out


def main(argv=None) -> int:
    """Run the table (module notes); exit status 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--drivers", nargs="+", default=list(BOARDS), choices=list(BOARDS))
    p.add_argument("--conditions", nargs="+", default=["clean", "loss", "stall"],
                   choices=["clean", "loss", "stall", "lossstall"])
    p.add_argument("--seeds", nargs="+", type=int, default=list(range(1, 11)))
    p.add_argument("--hogs", type=int, default=2)
    p.add_argument("--duration", type=float, default=None,
                   help="hapsim run's --duration [s] (default: none given, the run's own "
                        "length, as a user's run)")
    p.add_argument("--stalls", type=int, default=3, help="host stalls a 'stall' run")
    p.add_argument("--timeout", type=float, default=90.0, help="a run's hang limit [s]")
    p.add_argument("--board-priority", type=int, default=20)
    p.add_argument("--board-opt", action="append", default=[],
                   help="DRIVER=--option=value, passed to that driver's board")
    p.add_argument("--json", help="write every row and the summary here")
    p.add_argument("--identify", action="store_true",
                   help="run 'hapsim identify --driver NAME --port PTY' on each board "
                        "instead of the scene (the mass and friction found against the "
                        "board's own)")
    p.add_argument("--identify-x0", type=float, default=0.0,
                   help="--identify: where the handle rests when it starts [m or rad]")
    p.add_argument("--hapsim-root",
                   help="run the hapsim of this source tree (its configs too), e.g. an "
                        "export of an older commit, for a before/after table")
    p.add_argument("--telemetry", action="store_true",
                   help="with --keep: each run's record there too (hapsim run --telemetry "
                        "DRIVER-CONDITION-SEED.npz), to measure again offline")
    p.add_argument("--keep", help="keep the boards' truth logs and the runs' JSON in this "
                                  "directory (default: a temporary one, removed)")
    args = p.parse_args(argv)
    bo: dict = {}
    for o in args.board_opt:
        d, _, rest = o.partition("=")
        bo.setdefault(d, []).append(rest)
    args.board_opt = bo
    hogs = _hogs(args.hogs)
    rows = []
    load0 = os.getloadavg()[0]
    try:
        with tempfile.TemporaryDirectory(prefix="indep-") as tmp:
            if args.keep:
                os.makedirs(args.keep, exist_ok=True)
                tmp = args.keep
            for driver in args.drivers:
                for cond in args.conditions:
                    for seed in args.seeds:
                        r = one_run(driver, cond, seed, args, tmp)
                        rows.append(r)
                        brief = {k: r.get(k) for k in (
                            "driver", "condition", "seed", "exit_code", "hung", "verdict",
                            "truth_in_interval", "safety_stop", "stop_reason", "resyncs",
                            "longest_hold_s", "excursion_true", "k", "k_pred", "k_true",
                            "k_unc", "b", "b_pred", "b_true", "b_unc")}
                        brief["verdict"] = str(brief["verdict"])[:160]
                        print(json.dumps(brief, default=str), flush=True)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    summary = summarize(rows)
    sys.path.insert(0, os.path.dirname(HERE))
    from provenance import command_line   # tools/: portable paths in committed files
    doc = {"command": command_line(__file__, argv),
           "hapsim_commit": _commit(args.hapsim_root or ROOT),
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "load_before": load0, "load_after": os.getloadavg()[0], "cpus": os.cpu_count(),
           "rows": rows, "summary": summary}
    print(json.dumps(summary, indent=1))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(doc, fh, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
