"""The MCU budget of the Hapkit firmware on the emulated ATmega328P at 1, 2 and 5 kHz.

For each rate the emulated board runs the firmware (fast clock: the emulated time waits for
each FORCE, so the figures are cycle counts of the emulated chip and do not depend on the
host machine's load); a small host arms it and answers every STATE with a spring FORCE
for ``--ticks`` ticks. The board counts, per tick, every cycle the MCU is not asleep between
two rising edges of the D13 probe (the tick interrupt, the codec, the main loop, the UART
interrupts) and reports the mean, the worst case and the idle fraction. The build measured
is ``make bench`` (the firmware without its 1250 Hz CONFIG limit, which this table sets).

    PYTHONPATH=. python tools/bench_firmware.py [--ticks 1000] [--json FILE]
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


def measure(rate: float, ticks: int) -> dict:
    """Run ``ticks`` armed ticks at ``rate`` [Hz]; the board's report plus late/overrun."""
    import select
    with tempfile.TemporaryDirectory() as d:
        rep = Path(d, "board.json")
        proc = subprocess.Popen([str(board.BOARD), str(BENCH_ELF), "--report",
                                 str(rep)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                text=True)
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
            os.write(fd, fp.encode(fp.Config(rate, int(5e6 / rate), 5.0)))
            n = late = overrun = 0
            while n < ticks:
                r, _, _ = select.select([fd], [], [], 1.0)
                if not r:
                    continue
                for m in dec.feed(os.read(fd, 65536)):
                    if isinstance(m, fp.State) and m.status & fp.STATUS_ARMED:
                        if m.seq >= 2 and (m.seq - m.force_seq) & 0xFFFFFFFF != 1:
                            late += 1
                        overrun += bool(m.status & fp.STATUS_OVERRUN)
                        os.write(fd, fp.encode(fp.Force(m.seq, (-500.0 * m.position[0],))))
                        n += 1
            os.close(fd)
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=20)
        out = json.loads(rep.read_text())
    b = out["budget"]
    return {"rate_hz": rate, "period_cycles": b["period_cycles"], "ticks": n,
            "busy_mean_cycles": b["busy_mean_cycles"], "busy_max_cycles": b["busy_max_cycles"],
            "idle_fraction": b["idle_fraction"], "saturated": b["saturated"], "late": late,
            "overrun_states": overrun}


def main(argv=None) -> int:
    """Print the budget table (and write it as JSON with ``--json``)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=1000)
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)
    board.build()
    subprocess.run(["make", "-s", "-C", str(board.FIRMWARE_DIR), "bench"], check=True,
                   stdout=subprocess.DEVNULL)
    rows = []
    print("rate [Hz]  period [cycles]  busy mean  busy worst  idle    late  overrun")
    for rate in (1000.0, 2000.0, 5000.0):
        t0 = time.monotonic()
        r = measure(rate, args.ticks)
        rows.append(r)
        worst = "saturated" if r["saturated"] else f"{r['busy_max_cycles']:d}"
        print(f"{rate:9.0f}  {r['period_cycles']:15.0f}  {r['busy_mean_cycles']:9.0f}  "
              f"{worst:>10s}  {r['idle_fraction']:5.1%}  {r['late']:5d}  "
              f"{r['overrun_states']:7d}   ({time.monotonic() - t0:.1f} s)", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
