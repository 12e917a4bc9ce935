#!/usr/bin/env python3
"""Benchmark of the hapsim protocol codec (a program, not a test).

Measures encode + decode of one STATE and one FORCE (1 axis by default) through
``firmware_protocol``, three ways: ``encode`` + ``decode_frame``, ``encode`` +
``StreamDecoder.feed``, and the baseline measured in the same run, a bare precompiled
``struct.Struct.pack`` + ``unpack`` of the same body (no CRC, no COBS, no message object),
so the framing overhead is visible. Prints microseconds per round trip, the fraction of a
1 ms period (1 kHz loop) and the ratio to the baseline.

Usage::

    PYTHONPATH=. python tools/bench_protocol.py [--axes N] [--repeat R] [--number K]
"""

from __future__ import annotations

import argparse
import struct
import sys
import timeit

import firmware_protocol as fp
from provenance import command_line  # tools/, beside this file


def best_us(stmt, number: int, repeat: int) -> float:
    """Best time per call over ``repeat`` runs of ``number`` calls.

    Parameters
    ----------
    stmt : callable
        What to time (no arguments).
    number : int
        Calls per run.
    repeat : int
        Runs; the best is kept (least disturbed by other load).

    Returns
    -------
    float
        Time per call [us].
    """
    return min(timeit.repeat(stmt, number=number, repeat=repeat)) / number * 1e6


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (``sys.argv[1:]`` when None): ``--axes``, ``--repeat``, ``--number``.

    Returns
    -------
    int
        Exit code: 0.
    """
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--axes", type=int, default=1, help="axes per STATE/FORCE (1..8)")
    ap.add_argument("--repeat", type=int, default=7, help="timing runs, best is kept")
    ap.add_argument("--number", type=int, default=20000, help="calls per timing run")
    args = ap.parse_args(argv)
    n = args.axes

    state = fp.State(123456, 987654321, fp.STATUS_ARMED, 123455,
                     tuple(0.01 * (k + 1) for k in range(n)))
    force = fp.Force(123456, tuple(-0.5 * (k + 1) for k in range(n)))
    s_frame, f_frame = fp.encode(state), fp.encode(force)
    dec = fp.StreamDecoder()
    assert fp.decode_frame(s_frame) == state and dec.feed(f_frame) == [force]

    s_struct = struct.Struct(f"<IQHI{n}d")
    f_struct = struct.Struct(f"<I{n}d")
    pos, frc = state.position, force.force

    def base_state():
        s_struct.unpack(s_struct.pack(123456, 987654321, 1, 123455, *pos))

    def base_force():
        f_struct.unpack(f_struct.pack(123456, *frc))

    enc, decf, feed = fp.encode, fp.decode_frame, dec.feed
    cases = [
        ("STATE", "struct pack+unpack (baseline)", base_state, None),
        ("STATE", "encode + decode_frame", lambda: decf(enc(state)), "STATE"),
        ("STATE", "encode + StreamDecoder.feed", lambda: feed(enc(state)), "STATE"),
        ("FORCE", "struct pack+unpack (baseline)", base_force, None),
        ("FORCE", "encode + decode_frame", lambda: decf(enc(force)), "FORCE"),
        ("FORCE", "encode + StreamDecoder.feed", lambda: feed(enc(force)), "FORCE"),
        ("STATE", "encode only", lambda: enc(state), "STATE"),
        ("STATE", "decode_frame only", lambda: decf(s_frame), "STATE"),
        ("FORCE", "encode only", lambda: enc(force), "FORCE"),
        ("FORCE", "decode_frame only", lambda: decf(f_frame), "FORCE"),
    ]
    print("command: " + command_line("tools/bench_protocol.py", argv))
    print(f"python {sys.version.split()[0]}, axes={n}, frames: STATE {len(s_frame)} B, "
          f"FORCE {len(f_frame)} B, best of {args.repeat} x {args.number}")
    print(f"{'msg':6} {'operation':32} {'us':>8} {'of 1 ms':>9} {'x baseline':>11}")
    base = {}
    for msg, label, fn, ref in cases:
        us = best_us(fn, args.number, args.repeat)
        if ref is None:
            base[msg] = us
        ratio = f"{us / base[msg]:10.1f}x" if ref else f"{1.0:10.1f}x"
        print(f"{msg:6} {label:32} {us:8.3f} {us / 1000:9.2%} {ratio:>11}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
