#!/usr/bin/env python3
"""How late a pseudo-terminal delivers bytes on this machine now, beside a pipe (a program,
not a test): is the machine fit for a real-time run or a soak over the embedded mock?

A ``SCHED_FIFO`` writer process sends one 16-byte frame per period on absolute deadlines,
each stamped with its send time (``CLOCK_MONOTONIC``); a ``SCHED_FIFO`` reader polls the
other end and logs every frame's delivery latency (read returned - stamp) and its own time
runnable but not running (``/proc/self/task/TID/schedstat``, second field) across the
read of the latest frame. The same is done over a pipe.

Linux moves the bytes written to a pty master to the slave's reader in a kernel worker
thread (the tty flip buffer's work, normal scheduling), a pipe wakes the reader from the
writer's own call. So under CPU load, and above all while other real-time processes hold
the cores, a pty delivers in bursts however high the reader's priority: frames late by
tens of ms while the reader sat idle in ``poll`` (runnable-not-running ~0). A host loop
over the pty then sees the device's STATEs in bursts (skipped, all but the newest) and a
silence over the loss timeout (50 ms) as a lost device, whichever loop it is.

Usage::

    python tools/pty_latency.py [--seconds 10] [--rate 1000] [--json FILE]

Exit code 0 (2 on bad arguments; 1 when SCHED_FIFO is not permitted: the figures would
measure the reader's own scheduling, not the pty).
"""

from __future__ import annotations

import argparse
import json
import os
import pty
import select
import struct
import sys
import threading
import time
import tty
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hapsim.host.realtime import sleep_until_ns  # noqa: E402

FRAME = 16      # 8-byte stamp + 7 bytes + 0x00 [bytes]


def _writer(fd: int, seconds: float, period_ns: int) -> None:
    t = time.monotonic_ns()
    end = t + int(seconds * 1e9)
    while t < end:
        t += period_ns
        sleep_until_ns(t)
        os.write(fd, struct.pack("<q", time.monotonic_ns()) + b"\x01" * 7 + b"\x00")


def measure(kind: str, seconds: float, rate: float) -> dict:
    """Delivery latency of ``kind`` ("pty" or "pipe") for ``seconds`` at ``rate`` frames/s.

    Parameters
    ----------
    kind : {"pty", "pipe"}
        The channel between the writer (child process) and the reader (this thread).
    seconds : float
        Writing time [s].
    rate : float
        Frames per second [Hz].

    Returns
    -------
    dict
        ``frames``; ``latency_ms`` with ``p50``, ``p99``, ``p999``, ``max`` [ms];
        ``over_10ms``, ``over_50ms`` (frames); ``silences_50ms`` (reader polls of 50 ms
        that saw nothing while the writer wrote); ``worst_runnable_ms``: the reader's time
        runnable but not running across the read of the latest frame [ms].

    Raises
    ------
    PermissionError
        When SCHED_FIFO is refused.
    """
    if kind == "pipe":
        rfd, wfd = os.pipe()
    else:
        wfd, rfd = pty.openpty()
        tty.setraw(rfd)
    pid = os.fork()
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))   # both sides
    if pid == 0:                                                   # pragma: no cover
        try:
            os.close(rfd)
            _writer(wfd, seconds, int(round(1e9 / rate)))
            time.sleep(0.2)
        finally:
            os._exit(0)
    os.close(wfd)
    tid = threading.get_native_id()

    def runnable_ns() -> int:
        with open(f"/proc/self/task/{tid}/schedstat") as fh:
            return int(fh.read().split()[1])

    lat, buf, silences, worst = [], b"", 0, (0.0, 0.0)
    end = time.monotonic() + seconds
    p = select.poll()
    p.register(rfd, select.POLLIN)
    try:
        while True:
            r0 = runnable_ns()
            if not p.poll(50):
                if time.monotonic() > end + 0.5:
                    break
                silences += time.monotonic() < end
                continue
            try:
                data = os.read(rfd, 65536)
            except OSError:
                break
            if not data:
                break
            now = time.monotonic_ns()
            r1 = runnable_ns()
            buf += data
            while len(buf) >= FRAME:
                ms = (now - struct.unpack("<q", buf[:8])[0]) / 1e6
                buf = buf[FRAME:]
                lat.append(ms)
                if ms > worst[0]:
                    worst = (ms, (r1 - r0) / 1e6)
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.close(rfd)
        os.waitpid(pid, 0)
    a = np.asarray(lat) if lat else np.zeros(1)
    return {"kind": kind, "frames": len(lat),
            "latency_ms": {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
                           "p999": float(np.percentile(a, 99.9)), "max": float(a.max())},
            "over_10ms": int((a > 10).sum()), "over_50ms": int((a > 50).sum()),
            "silences_50ms": silences, "worst_runnable_ms": worst[1]}


def main(argv=None) -> int:
    """Measure the pty and the pipe, print one line each (and the JSON with ``--json``)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="per channel (default 10)")
    ap.add_argument("--rate", type=float, default=1000.0, help="frames per second (1000)")
    ap.add_argument("--json", metavar="FILE", help="also write the figures there")
    args = ap.parse_args(argv)
    if not (args.seconds > 0 and 0 < args.rate <= 100_000):
        ap.error("--seconds must be > 0 and --rate in (0, 100000]")
    out = {}
    for kind in ("pty", "pipe"):
        try:
            r = out[kind] = measure(kind, args.seconds, args.rate)
        except PermissionError as exc:
            print(f"pty_latency: SCHED_FIFO refused ({exc}); nothing measured", file=sys.stderr)
            return 1
        la = r["latency_ms"]
        print(f"{kind:4}: {r['frames']} frames, latency p50 {la['p50']:.3f} p99 {la['p99']:.2f} "
              f"p99.9 {la['p999']:.1f} max {la['max']:.1f} ms; > 10 ms {r['over_10ms']}, "
              f"> 50 ms {r['over_50ms']}; 50 ms silences {r['silences_50ms']}; the reader was "
              f"runnable-not-running {r['worst_runnable_ms']:.2f} ms around the worst frame")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
