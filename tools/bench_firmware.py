"""The MCU budget of the Hapkit firmware on the emulated ATmega328P at 1, 2 and 5 kHz.

For each rate the emulated board runs the firmware (fast clock: the emulated time waits for
each FORCE, so the figures are cycle counts of the emulated chip and do not depend on the
host machine's load); a small host arms it and answers every STATE with a spring FORCE
for ``--ticks`` ticks. The board counts, per tick, every cycle the MCU is not asleep between
two rising edges of the D13 probe (the tick interrupt, the codec, the main loop, the UART
interrupts) and reports the mean, the worst case and the idle fraction. The build measured
is ``make bench`` (the firmware without its 1250 Hz CONFIG limit, which this table sets).

    PYTHONPATH=. python tools/bench_firmware.py [--ticks 1000] [--json FILE]

``--realtime N``: instead, the board in real time (``hapsim mock --firmware``) under N runs of
``hapsim run configs/hapkit.yaml --port`` (``--duration`` s each; ``--beside-cpu``: next to
one CPU-bound process): each run's late ticks, then where the board's wall time went
(emulating, the pty/UART bridge, sleeping to hold real time; the emulated MHz per wall
second while armed; the slips of its clock) and the CPU it needed.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import tty
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import firmware_protocol as fp  # noqa: E402
from hapsim.daemon import board  # noqa: E402


BENCH_ELF = board.FIRMWARE_DIR / "hapkit_bench.elf"  # without the firmware's 1250 Hz limit


def _functions(path: str) -> list:
    """(first line, name) of each function defined in a C file (definitions start in
    column 0; ``ISR(X_vect)`` is named ``X_vect``)."""
    import re
    out = []
    try:
        lines = Path(path).read_text().splitlines()
    except OSError:
        return out
    for i, ln in enumerate(lines, 1):
        m = re.match(r"ISR\((\w+)\)", ln) or re.match(
            r"(?:static\s+)?(?:inline\s+)?[A-Za-z_][\w\s\*]*?\b(\w+)\(", ln)
        if m and not ln.rstrip().endswith(";") and not ln.startswith(("typedef", "#")):
            out.append((i, m.group(1)))
    return out


def profile_paths(elf: Path, prof: Path) -> dict:
    """Cycles per path from the board's ``--profile`` dump (cycles at each flash address).

    Each address is mapped by ``avr-addr2line`` to its source line (the ELF carries -g;
    with -flto the functions are inlined, so the line, not the symbol, tells where the
    cycles go), the line to the C function around it, the function to a path of
    :data:`PATHS`; avr-libc's routines (no source here) by their symbol.
    Returns ``{path: cycles}`` summed over the run.
    """
    rows = [ln.split() for ln in prof.read_text().splitlines() if ln.strip()]
    if not rows:
        return {}
    out = subprocess.run(["avr-addr2line", "-a", "-f", "-e", str(elf), *[a for a, _ in rows]],
                         capture_output=True, text=True, check=True).stdout.splitlines()
    # -a: each answer is "0xADDR", the function, "file:line"
    where = {}
    for i in range(0, len(out) - 2, 3):
        where[int(out[i], 16)] = (out[i + 1], out[i + 2])
    # avr-libc's routines carry no line information: named by the symbol at or before
    nm = subprocess.run(["avr-nm", "-n", str(elf)], capture_output=True, text=True,
                        check=True).stdout.split("\n")
    syms = sorted((int(f[0], 16), f[2]) for f in (ln.split() for ln in nm)
                  if len(f) == 3 and f[1] in "tT")
    import bisect
    starts = [a for a, _ in syms]
    funcs_of: dict = {}
    paths: dict = {}
    for a, cyc in rows:
        i = bisect.bisect_right(starts, int(a, 16)) - 1
        lib = syms[i][1] if i >= 0 else "??"
        if lib.startswith("__") and not lib.startswith("__vector"):
            key = next((name for name, pre in LIBRARY if any(p in lib for p in pre)),
                       f"other ({lib})")
            paths[key] = paths.get(key, 0) + int(cyc)
            continue
        sym, loc = where.get(int(a, 16), ("??", "??:0"))
        file, _, line = loc.rpartition(":")
        fn = sym
        if file and file != "??" and line.split()[0].isdigit():
            if file not in funcs_of:
                funcs_of[file] = _functions(file)
            n = int(line.split()[0])
            before = [name for first, name in funcs_of[file] if first <= n]
            if before:
                fn = before[-1]
        key = next((name for name, fns in PATHS if fn in fns), f"other ({fn})")
        paths[key] = paths.get(key, 0) + int(cyc)
    return paths


#: avr-libc / libgcc routines by path (a part of the symbol's name).
LIBRARY = [
    ("soft float (float32 arithmetic, libgcc/avr-libc)", ("sf", "__fp_", "sisf", "sfsi")),
    ("64-bit integer arithmetic (libgcc)", ("di3", "udivmod64", "di2")),
    ("32-bit multiply/divide (libgcc)", ("si4", "hisi3", "__tablejump")),
]

#: Functions by path of the firmware's work per tick.
PATHS = [
    ("tick ISR (Timer1: PWM, watchdog, ADC start)", {"TIMER1_COMPA_vect", "pwm_write"}),
    ("ADC ISR + read + flip counting", {"read_counts", "ADC_vect"}),
    ("UART RX ISR", {"USART_RX_vect"}),
    ("UART TX ISR (UDRE)", {"USART_UDRE_vect"}),
    ("UART ring in main loop", {"uart_frame", "uart_put", "uart_frame_ready", "uart_rx_lost",
                                "uart_frame_done"}),
    ("CRC-16", {"hp_crc16"}),
    ("COBS encode/decode", {"hp_cobs_encode", "hp_cobs_decode"}),
    ("pack/unpack fields", {"pack", "hp_encode", "hp_decode_packet", "hp_decode_frame",
                            "put_u16", "put_u32", "put_u64", "put_f64", "get_u16", "get_u32",
                            "get_u64", "get_f64", "fixed_len"}),
    ("f32 <-> f64 bit conversion", {"hp_b64_from_f32_bits", "hp_f32_bits_from_b64",
                                   "f64_of_float", "float_of_f64", "f64_is_finite"}),
    ("STATE / FORCE handling", {"serve_tick", "on_force", "on_message", "take_frame",
                                "send", "send_fault", "now_us", "latch_fault", "zero_now"}),
    ("main loop + sleep", {"main", "__vectors", "__bad_interrupt"}),
    ("memcpy/memset", {"memcpy", "memset"}),
]


def measure(rate: float, ticks: int, profile: bool = False, compact: bool = False) -> dict:
    """Run ``ticks`` armed ticks at ``rate`` [Hz]; the board's report plus late/overrun
    (and, with ``profile``, the cycles per path: :func:`profile_paths`); ``compact``: the
    host asks for the compact frames (SENSORS_REQUEST bit COMPACT) and answers each
    STATE_COMPACT with a FORCE_COMPACT."""
    import select
    with tempfile.TemporaryDirectory() as d:
        rep = Path(d, "board.json")
        prof = Path(d, "profile.txt")
        extra = ["--profile", str(prof)] if profile else []
        proc = subprocess.Popen([str(board.BOARD), str(BENCH_ELF), "--report",
                                 str(rep), *extra], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, text=True)
        try:
            port = proc.stdout.readline().split()[1]
            fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
            tty.setraw(fd)
            dec = fp.StreamDecoder()
            os.write(fd, b"\x00" + fp.encode(fp.HelloRequest(1)))
            hello = None
            while hello is None:
                select.select([fd], [], [], 0.05)
                for m in dec.feed(os.read(fd, 65536)):
                    if isinstance(m, fp.Hello):
                        hello = m
            if compact:
                os.write(fd, fp.encode(fp.SensorsRequest(fp.FEATURE_COMPACT)))
                sens = None
                while sens is None:
                    select.select([fd], [], [], 0.05)
                    for m in dec.feed(os.read(fd, 65536)):
                        if isinstance(m, fp.Sensors):
                            sens = m
                if not sens.enabled & fp.FEATURE_COMPACT:
                    raise SystemExit("the firmware does not offer the compact frames")
                dec.expander = fp.CompactExpander(rate)
            os.write(fd, fp.encode(fp.Config(rate, int(5e6 / rate), 5.0)))
            n = overrun = 0
            lags: dict = {}     # seq - force_seq -> ticks (from the 5th tick on)
            while n < ticks:
                r, _, _ = select.select([fd], [], [], 1.0)
                if not r:
                    continue
                for m in dec.feed(os.read(fd, 65536)):
                    if isinstance(m, fp.Fault) and m.code == fp.FAULT_BAD_CONFIG:
                        raise SystemExit(f"the firmware refused CONFIG at {rate} Hz "
                                         "(a rate must divide 16 MHz)")
                    if isinstance(m, fp.State) and m.status & fp.STATUS_ARMED:
                        if m.seq >= 4 and m.status & fp.STATUS_FORCE_APPLIED:
                            lag = (m.seq - m.force_seq) & 0xFFFFFFFF
                            lags[lag] = lags.get(lag, 0) + 1
                        overrun += bool(m.status & fp.STATUS_OVERRUN)
                        f = fp.Force(m.seq, (-500.0 * m.position[0],))
                        os.write(fd, fp.encode(fp.compact_force(f) if compact else f))
                        n += 1
            os.close(fd)
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=20)
        out = json.loads(rep.read_text())
        paths = profile_paths(BENCH_ELF, prof) if profile else None
    # the device's delay: the lag of most ticks; late: the ticks with another lag
    delay = max(lags, key=lags.get) if lags else None
    late = sum(v for k, v in lags.items() if k != delay)
    print(f"  lags at {rate:g} Hz: {dict(sorted(lags.items()))}", flush=True)
    b = out["budget"]
    res = {"frames": "compact" if compact else "full", "rate_hz": rate, "period_cycles": b["period_cycles"], "ticks": n,
            "busy_mean_cycles": b["busy_mean_cycles"], "busy_max_cycles": b["busy_max_cycles"],
            "idle_fraction": b["idle_fraction"], "saturated": b["saturated"],
            "delay": delay, "late": late,
            "overrun_states": overrun}
    if paths is not None:
        res["cycles_per_tick_by_path"] = {k: v / max(n, 1) for k, v in
                                          sorted(paths.items(), key=lambda kv: -kv[1])}
    return res


def realtime(runs: int, duration: float, beside_cpu: bool) -> int:
    """The real-time board under ``runs`` runs of ``hapsim run --port``: print each run's
    late ticks and the board's time breakdown (its report's ``time``); 0 when every run has
    at most 1 % of its ticks late (5 % beside a CPU-bound process)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    tmp = Path(tempfile.mkdtemp())
    link, rep = tmp / "port", tmp / "board.json"
    hog = (subprocess.Popen([sys.executable, "-c", "while True: pass"]) if beside_cpu
           else None)
    mock = subprocess.Popen([sys.executable, "-m", "hapsim", "mock", "--firmware", "--link",
                             str(link), "--report", str(rep)], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env=env)
    worst = 0.0
    try:
        line = mock.stdout.readline()
        if not line.startswith("PORT "):
            raise SystemExit(f"the board did not start: {line!r}")
        load = os.getloadavg()
        print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, cores {os.cpu_count()}"
              f"{', beside one CPU-bound process' if beside_cpu else ''}")
        t0 = time.monotonic()
        for i in range(runs):
            r = subprocess.run([sys.executable, "-m", "hapsim", "run",
                                str(ROOT / "configs" / "hapkit.yaml"), "--port", str(link),
                                "--duration", str(duration), "--json"],
                               capture_output=True, text=True, env=env, timeout=300)
            rep_run = json.loads(r.stdout)
            lp = rep_run["loop"]
            frac = lp["late"] / max(lp["ticks"], 1)
            worst = max(worst, frac)
            print(f"  run {i + 1}: late {lp['late']}/{lp['ticks']} ({frac:.2%}), "
                  f"{lp['scheduling']}; {rep_run['measured'].get('verdict')}", flush=True)
        wall = time.monotonic() - t0
    finally:
        mock.send_signal(signal.SIGTERM)
        mock.wait(timeout=30)
        if hog is not None:
            hog.kill()
            hog.wait()
    tm = json.loads(rep.read_text())["time"]
    busy = tm["emulate_s"] + tm["io_s"]
    print(f"board: emulating {tm['emulate_s']:.2f} s, pty/UART bridge {tm['io_s']:.2f} s, "
          f"sleeping {tm['sleep_s']:.2f} s of {wall:.2f} s; {tm['armed_mhz']:.1f} emulated "
          f"MHz per wall second while armed (16 MHz is real time); CPU needed "
          f"{busy / wall:.0%} of a core; clock slips {tm['slips']} "
          f"({tm['slipped_s']:.3f} s, at most {tm['behind_max_ms']:.1f} ms behind)")
    limit = 0.05 if beside_cpu else 0.01
    print(f"worst late fraction {worst:.2%} (target <= {limit:.0%})")
    return 0 if worst <= limit else 1


def main(argv=None) -> int:
    """Print the budget table (and write it as JSON with ``--json``)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=1000)
    ap.add_argument("--rates", type=float, nargs="+", default=[1000.0, 1600.0, 2000.0, 5000.0],
                    metavar="HZ", help="tick rates to measure (default 1000 1600 2000 5000; each must divide 16 MHz)")
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--compact", action="store_true",
                    help="the compact frames (STATE_COMPACT / FORCE_COMPACT) instead of "
                         "STATE / FORCE")
    ap.add_argument("--profile", action="store_true",
                    help="also the cycles per tick by path (ISR, ADC, codec, UART, ...)")
    ap.add_argument("--realtime", type=int, default=0, metavar="N",
                    help="instead: N real-time runs over the board, late ticks and where "
                         "the board's time goes")
    ap.add_argument("--duration", type=float, default=3.0, help="each run [s] (3)")
    ap.add_argument("--beside-cpu", action="store_true",
                    help="with --realtime: next to one CPU-bound process")
    args = ap.parse_args(argv)
    board.build()
    if args.realtime:
        return realtime(args.realtime, args.duration, args.beside_cpu)
    subprocess.run(["make", "-s", "-C", str(board.FIRMWARE_DIR), "bench"], check=True,
                   stdout=subprocess.DEVNULL)
    rows = []
    print("rate [Hz]  period [cycles]  busy mean  busy worst  idle   delay  late  overrun")
    for rate in args.rates:
        t0 = time.monotonic()
        r = measure(rate, args.ticks, args.profile, args.compact)
        rows.append(r)
        worst = "saturated" if r["saturated"] else f"{r['busy_max_cycles']:d}"
        print(f"{rate:9.0f}  {r['period_cycles']:15.0f}  {r['busy_mean_cycles']:9.0f}  "
              f"{worst:>10s}  {r['idle_fraction']:5.1%}  {r['delay'] or 0:5d}  {r['late']:5d}  "
              f"{r['overrun_states']:7d}   ({time.monotonic() - t0:.1f} s)", flush=True)
    for r in rows:
        if "cycles_per_tick_by_path" in r:
            print(f"\ncycles per tick by path at {r['rate_hz']:.0f} Hz:")
            for k, v in r["cycles_per_tick_by_path"].items():
                print(f"  {v:8.0f}  {k}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
