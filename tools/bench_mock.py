#!/usr/bin/env python3
"""Benchmark of the mock device's tick rate: the Python mock against the compiled one (a
program, not a test).

The mock runs as in ``hapsim run`` (:class:`hapsim.emulated.links.EmbeddedMock`: a
child process on a pty master, ``SCHED_FIFO`` 10 where permitted), once with
``--tick python`` and once with ``--tick compiled``, at each rate. The host is trivial and
compiled (numba, no GIL, the COBS / CRC / FORCE encoder of :mod:`hapsim.host.fastloop`):
it answers every STATE at once with ``FORCE(seq, 0)``, so what is measured is the mock.
Printed per rate and mock: ticks served in the run's seconds against those asked, the
mock's own late ticks (``overruns``: woken more than half a period after its deadline),
ticks whose FORCE had not arrived (``late``), STATE gaps the host saw, and the ratio of
the Python mock's overruns to the compiled one's. The machine's load is printed with the
figures: on a shared machine say "loaded machine" beside them.

Usage::

    PYTHONPATH=$PWD python tools/bench_mock.py [--seconds 5] [--rates 1000 2000 5000 10000 20000]
"""

from __future__ import annotations

import argparse
import json
import os
import select
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import firmware_protocol as fp  # noqa: E402
from hapsim.host.fastloop_kernels import (_POLLIN, _c_poll, _c_read,  # noqa: E402
                                            _c_write, _cobs_decode, _crc16, _force_frame, _jit)
from hapsim.kernels.compiled_io import CRC_TABLE as _CRC  # noqa: E402
from hapsim.host.realtime import RealtimePriority  # noqa: E402
from hapsim.emulated.links import EmbeddedMock  # noqa: E402
from hapsim.scene import Device, Excitation  # noqa: E402
from provenance import command_line  # noqa: E402  (tools/, beside this file)


@_jit
def _answer_states(fd, n_states, timeout_ms, rb, pkt, f8, u8, table, tx, pfd, seen):
    """Answer each STATE on ``fd`` with FORCE(seq, 0) until ``n_states`` were seen or
    ``timeout_ms`` of silence; ``seen`` gets [states, gaps]. Returns 0, or -1 on a port
    error."""
    n_rb = 0
    expect = -1
    while seen[0] < n_states:
        pfd[0] = fd
        pfd[1] = _POLLIN
        if _c_poll(pfd.ctypes.data, 1, timeout_ms) <= 0:
            return 0
        got = _c_read(fd, rb.ctypes.data + n_rb, rb.size - n_rb)
        if got <= 0:
            return -1
        n_rb += got
        a = 0
        for z in range(n_rb):
            if rb[z] != 0:
                continue
            if z > a:
                m = _cobs_decode(rb, a, z, pkt)
                if m == 29 and pkt[0] == 0x10 and _crc16(pkt, m, table) == 0:
                    seq = np.int64(0)
                    for j in range(4):
                        seq |= np.int64(pkt[1 + j]) << (8 * j)
                    if expect >= 0 and seq != expect:
                        seen[1] += (seq - expect) & 0xFFFFFFFF
                    expect = (seq + 1) & 0xFFFFFFFF
                    seen[0] += 1
                    k = _force_frame(seq, 0.0, pkt, f8, u8, table, tx)
                    _c_write(fd, tx.ctypes.data, k)
            a = z + 1
        for j in range(a, n_rb):
            rb[j - a] = rb[j]
        n_rb -= a
    return 0


def run_one(tick: str, rate: float, seconds: float, settle: float = 0.0) -> dict:
    """One run of the mock (``tick``: "python" or "compiled") at ``rate`` [Hz], CONFIG
    sent ``settle`` seconds after HELLO."""
    dev = Device(mass=0.1, friction=0.5, delay=1, force_limit=10.0)
    rt = RealtimePriority(10)
    rt.__enter__()
    mock = EmbeddedMock(dev, Excitation(x0=0.005), rate, tick=tick, rt_priority=10)
    fd = os.open(mock.port, os.O_RDWR | os.O_NOCTTY)
    mock.release_slave()
    try:
        dec = fp.StreamDecoder()
        t_end = time.monotonic() + 30.0
        while time.monotonic() < t_end:            # the child's start-up: wait for HELLO
            os.write(fd, fp.encode(fp.HelloRequest(fp.PROTOCOL_VERSION)))
            if select.select([fd], [], [], 0.2)[0] and any(
                    isinstance(m, fp.Hello) for m in dec.feed(os.read(fd, 4096))):
                break
        time.sleep(settle)
        os.write(fd, fp.encode(fp.Config(rate, 50_000, 10.0)))
        n = int(rate * seconds)
        u8 = np.zeros(8, dtype=np.uint8)
        seen = np.zeros(2, dtype=np.int64)
        t0 = time.monotonic()
        _answer_states(fd, n, 1000, np.zeros(1 << 16, dtype=np.uint8),
                       np.zeros(64, dtype=np.uint8), u8.view(np.float64), u8, _CRC,
                       np.zeros(64, dtype=np.uint8), np.zeros(2, dtype=np.int32), seen)
        elapsed = time.monotonic() - t0
        os.write(fd, fp.encode(fp.Stop()))
    finally:
        os.close(fd)
        rep = mock.report(10.0) or {}
        mock.close()
        rt.__exit__(None, None, None)
    return {"tick": tick, "rate_hz": rate, "asked": n, "states": int(seen[0]),
            "gaps": int(seen[1]), "elapsed_s": elapsed, "ticks": rep.get("ticks"),
            "overruns": rep.get("overruns"), "late": rep.get("late"),
            "compiled_ticks": rep.get("compiled_ticks"), "scheduling": rt.note}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="seconds per run (default 5)")
    ap.add_argument("--rates", type=float, nargs="+",
                    default=[1000.0, 2000.0, 5000.0, 10000.0, 20000.0])
    ap.add_argument("--settle", type=float, default=0.0,
                    help="seconds between the mock's HELLO and CONFIG (default 0: at once, "
                         "as hapsim run; the compiled tick loads before HELLO)")
    ap.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    args = ap.parse_args(argv)
    from hapsim.emulated.serve import warm_up_mock
    warm_up_mock()                    # numba's cache filled before the children load it
    _answer_states(-1, 1, 0, np.zeros(8, dtype=np.uint8), np.zeros(64, dtype=np.uint8),
                   np.zeros(1), np.zeros(8, dtype=np.uint8), _CRC,
                   np.zeros(64, dtype=np.uint8), np.zeros(2, dtype=np.int32),
                   np.zeros(2, dtype=np.int64))
    print("command: " + command_line("tools/bench_mock.py", argv))
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}; {args.seconds:g} s per run, "
          f"CONFIG {args.settle:g} s after HELLO")
    rows = []
    print(f"{'rate [Hz]':>9} {'mock':>9} {'ticks/asked':>13} {'rate got':>9} {'overruns':>9} "
          f"{'late':>7} {'gaps':>6} {'py/compiled overruns':>21}")
    for rate in args.rates:
        pair = {t: run_one(t, rate, args.seconds, args.settle) for t in ("python", "compiled")}
        rows += pair.values()
        for t, r in pair.items():
            ratio = ""
            if t == "compiled":
                ratio = f"{pair['python']['overruns'] / max(r['overruns'], 1):21.1f}"
            got = r["states"] / r["elapsed_s"] if r["elapsed_s"] > 0 else 0.0
            print(f"{rate:9g} {t:>9} {r['states']:>6}/{r['asked']:<6} {got:9.0f} "
                  f"{r['overruns']:9} {r['late']:7} {r['gaps']:6} {ratio}", flush=True)
    print(f"scheduling: {rows[0]['scheduling']}; load average now "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
