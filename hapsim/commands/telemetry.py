"""``hapsim telemetry FILE``: summarise, convert and plot a run's telemetry."""

from __future__ import annotations

import argparse
import json
import math
import os

from hapsim.errors import DAMAGED_FILE_ERRORS, ConfigError
from hapsim.option_values import Number
from hapsim.outputs import finite_or_none as _finite

__all__ = ["register", "run", "read", "described", "summarize", "felt_energy",
           "format_summary"]

_FORMATS = (".hst", ".npz", ".csv")


def register(sub) -> None:
    """Add the ``telemetry`` sub-command.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The sub-parsers of the ``hapsim`` parser; the new parser's ``func`` is :func:`run`.
    """
    p = sub.add_parser(
        "telemetry", help="summarise, convert (.hst/.npz/.csv) and plot a run's telemetry",
        description=(
            "Read the telemetry of a 'hapsim run --telemetry FILE' (the .hst journal, even "
            "one cut short by kill -9, or its .npz/.csv export) and print what happened: "
            "samples, rate and duration, late ticks, device losses and recoveries, the "
            "position, force and turnaround ranges, and the energy the scene gave the hand. "
            "A journal cut by a kill is read up to its last intact chunk and the summary "
            "says what was lost."),
        epilog=(
            "columns: time [s], position [m], force [N], seq, turnaround_us [us], late,\n"
            "  flags (1 late, 2 first sample after a recovery, 4 ramped, 8 clamped),\n"
            "  force_seq (the device's STATE.force_seq: the FORCE it applied), status\n"
            "applied: from force_seq, the force the device held at each tick, its delay\n"
            "  and late ticks, and the felt energy from the applied force (exact with late\n"
            "  ticks)\n"
            "felt energy: E(n) = sum_k f(k - d) (x(k+1) - x(k)) [J], the work the held force\n"
            "  did on the hand (the run's passivity observer), restarted at each recovery\n"
            "examples:\n"
            "  hapsim run configs/wall.yaml --telemetry wall.hst --faults drop=0.01,reset@800\n"
            "  hapsim telemetry wall.hst\n"
            "  hapsim telemetry wall.hst --out wall.csv          # or .npz; and back to .hst\n"
            "  hapsim telemetry wall.hst --plot wall.png --json\n"
            "exit codes: 0 read (a truncated journal included); 2 not a telemetry file,\n"
            "  bad option."),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", metavar="FILE", help="telemetry file: .hst, .npz or .csv")
    p.add_argument("--out", metavar="FILE",
                   help="write the telemetry to FILE in the format of its extension "
                        "(.hst, .npz, .csv; events are kept in .hst and .npz)")
    p.add_argument("--plot", metavar="FIG",
                   help="draw position, force, felt energy and flags over time to FIG (.png, "
                        ".svg, ...; needs matplotlib)")
    p.add_argument("--delay", type=Number(int, low=0), default=None, metavar="D",
                   help="samples d between a position and the force answering it, for the "
                        "felt energy (default: the device.delay the run's file states "
                        "where whole, else 1)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.set_defaults(func=run)


def read(path: str) -> tuple[dict, dict]:
    """Read a telemetry file and what is known about its integrity.

    Parameters
    ----------
    path : str
        ``.hst`` journal, ``.npz`` or ``.csv`` (:mod:`hapsim.host.telemetry`).

    Returns
    -------
    cols : dict of str to ndarray
        The columns of :data:`hapsim.host.telemetry.COLUMNS`, each shape (n,).
    info : dict
        ``format``; ``events`` (list of dict; empty for a ``.csv``); for a journal also
        ``chunks``, ``torn_bytes``, ``torn_rows``, ``gaps`` (:func:`~hapsim.host.telemetry.load`).

    Raises
    ------
    ConfigError
        (key ``FILE``) When the file is missing or unreadable, has another extension, or is
        not telemetry: a non-empty journal without one intact chunk, an ``.npz`` without
        the columns, a ``.csv`` without the header or with non-numbers.
    """
    import numpy as np
    from hapsim.host.telemetry import COLUMNS, load

    ext = os.path.splitext(path)[1].lower()
    if ext not in _FORMATS:
        raise ConfigError(f"unknown telemetry format {ext or '(none)'!r}; valid: "
                          f"{', '.join(_FORMATS)}", file=path, key="FILE")
    if not os.path.isfile(path):
        raise ConfigError("not a regular file (a directory, a device or a pipe)"
                          if os.path.exists(path) else "no such file", file=path, key="FILE")
    info: dict = {"format": ext[1:], "events": []}
    try:
        if ext == ".hst":
            cols = load(path, info=info)
            if info["chunks"] == 0 and info["torn_bytes"] > 0 and info["torn_rows"] is None:
                raise ConfigError("not a hapsim telemetry journal (no intact chunk; a "
                                  "journal starts with b'HSTC')", file=path, key="FILE")
        elif ext == ".npz":
            with np.load(path) as z:
                missing = [c for c in ("time", "position", "force", "seq") if c not in z.files]
                if missing:
                    raise ConfigError(f"not hapsim telemetry: no column {missing[0]!r} "
                                      f"(has: {', '.join(z.files[:10]) or 'nothing'})",
                                      file=path, key="FILE")
                if "events" in z.files:
                    info["events"] = json.loads(str(z["events"]))
            cols = load(path)
        else:
            with open(path, encoding="utf-8", errors="replace") as fh:
                header = fh.readline().strip().split(",")
            missing = [c for c in ("time", "position", "force", "seq") if c not in header]
            if header[:3] != list(COLUMNS[:3]) or missing:   # (a missing seq read as zeros)
                raise ConfigError(f"not hapsim telemetry: the first line must be the header "
                                  f"{','.join(COLUMNS)}", file=path, key="FILE")
            cols = load(path)
    except ConfigError:
        raise
    except DAMAGED_FILE_ERRORS as exc:
        msg = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
        if "pickle" in msg or "context manager" in msg:
            # (numpy's advice to load it unsafely, for a file that is no .npz archive)
            msg = f"not an {ext} archive (another format under its name?)"
        raise ConfigError(f"cannot read telemetry: {msg}", file=path, key="FILE") from None
    if not (isinstance(info.get("events"), list)
            and all(isinstance(e, dict) for e in info["events"])):
        # (an AttributeError in the summary before)
        raise ConfigError("not hapsim telemetry: its events are not a list of objects",
                          file=path, key="FILE")
    from hapsim.host.telemetry import DTYPES
    bad = [c for c in COLUMNS if np.asarray(cols[c]).dtype.kind not in (
        "iu" if np.dtype(DTYPES[c]).kind in "iu" else "iuf")]
    if bad:             # (a string, complex or float-flags column: a TypeError deep in it)
        raise ConfigError(f"not hapsim telemetry: column {bad[0]!r} is not "
                          f"{'whole ' if np.dtype(DTYPES[bad[0]]).kind in 'iu' else ''}"
                          f"numbers ({np.asarray(cols[bad[0]]).dtype})", file=path, key="FILE")
    if not all(np.asarray(cols[c]).ndim == 1 and cols[c].size == cols["seq"].size
               for c in COLUMNS):
        raise ConfigError("not hapsim telemetry: columns of different lengths", file=path,
                          key="FILE")
    if ext == ".hst":
        info["damaged"] = _intact_chunks_after(path, info)
    t = np.asarray(cols["time"], float)
    # rows out of order or written twice (chunks swapped or repeated: their CRCs hold);
    # before, such a file was summarised as intact, its energy doubled
    info["time_back"] = int(np.sum(~(np.diff(t) > 0))) if t.size > 1 else 0
    return cols, info


def _intact_chunks_after(path: str, info: dict) -> int:
    """The intact chunks after the one a journal's reading stopped at: 0 where the
    journal is whole or cut at its end (a kill mid-write); more where a chunk in the
    middle is damaged and the rest was never read (before: said to be a cut tail)."""
    import zlib

    from hapsim.host.telemetry import CHUNK_HEAD, CHUNK_MAGIC
    from hapsim.outputs import read_input
    if not info.get("torn_bytes"):          # read to its end: nothing after (no 2nd read)
        return 0
    data = read_input(path, "FILE", what="telemetry")
    pos, found = len(data) - int(info.get("torn_bytes") or 0) + 1, 0
    while (pos := data.find(CHUNK_MAGIC, pos)) >= 0 and pos + CHUNK_HEAD.size <= len(data):
        _, _, hlen, plen, crc = CHUNK_HEAD.unpack_from(data, pos)
        a = pos + CHUNK_HEAD.size
        whole = a + hlen + plen <= len(data)
        if whole and zlib.crc32(data[a + hlen:a + hlen + plen],
                                zlib.crc32(data[a:a + hlen])) == crc:
            found, pos = found + 1, a + hlen + plen
        else:
            pos += 1
    return found


def felt_energy(position: np.ndarray, force: np.ndarray, flags: np.ndarray,
                delay: int) -> np.ndarray:
    """The energy the held force gave the hand, sample by sample (passivity observer).

    Parameters
    ----------
    position : ndarray, shape (n,)
        Device positions [m].
    force : ndarray, shape (n,)
        Forces sent [N]; the force answering sample ``k`` is held over period ``k + d``.
    flags : ndarray, shape (n,)
        Telemetry flags; a sample with :data:`~hapsim.host.telemetry.FLAG_LOST` restarts
        the sum (the scene restarted there after a recovery).
    delay : int
        d [samples], >= 0.

    Returns
    -------
    ndarray, shape (n,)
        ``E[n] = sum_{k = r + d}^{n - 1} f(k - d) (x(k + 1) - x(k))`` [J], ``r`` the last
        restart at or before ``n`` (Hannaford & Ryu 2002, with the sign of
        :mod:`hapsim.host.loop`: energy out of the scene into the hand).
    """
    import numpy as np
    from hapsim.host.telemetry import FLAG_LOST

    x = np.asarray(position, float)
    f = np.asarray(force, float)
    n = x.size
    e = np.zeros(n)
    starts = [0] + [int(i) for i in np.flatnonzero(np.asarray(flags) & FLAG_LOST) if i > 0]
    for a, b in zip(starts, starts[1:] + [n]):
        if b - a <= delay + 1:
            continue
        inc = f[a:b - 1 - delay] * np.diff(x[a + delay:b])     # k = a + d .. b - 2
        e[a + delay + 1:b] = np.cumsum(inc)
    return e


def _range(a: np.ndarray) -> dict:
    import numpy as np
    a = a[np.isfinite(a)]
    return {"min": float(a.min()), "max": float(a.max())} if a.size else {"min": None,
                                                                          "max": None}


def described(info: dict) -> dict:
    """What the run said of itself in its file (its ``"run"`` event, written first by
    :func:`hapsim.pipeline.runner.run_loop`; empty for a ``.csv`` or an older file).

    Parameters
    ----------
    info : dict
        From :func:`read`.

    Returns
    -------
    dict
        ``units`` (:func:`hapsim.drivers.axis_units`: the columns' units, a rotary
        joint's radians and newton metres; SI when the file does not say), ``delay`` (the
        device's delay [periods], or None) and ``rate_hz`` (or None).
    """
    from hapsim.drivers import axis_units
    ev = next((e for e in info.get("events", []) if e.get("event") == "run"), {})
    units = ev.get("units")
    # the units of an axis hapsim knows, else SI (a damaged description's half set of
    # units was a KeyError out of the summary)
    known = (axis_units(None), axis_units("haply"))
    delay, rate = ev.get("delay"), ev.get("rate_hz")
    return {"units": units if units in known else axis_units(None),
            "delay": delay if isinstance(delay, (int, float)) and not isinstance(delay, bool)
            and 0 <= delay <= 10 ** 6 else None,
            "rate_hz": rate if isinstance(rate, (int, float)) and not isinstance(rate, bool)
            and math.isfinite(rate) and rate > 0 else None}


def summarize(cols: dict, info: dict, delay: int = 1) -> dict:
    """What a run's telemetry says.

    Parameters
    ----------
    cols : dict of str to ndarray
        Columns as returned by :func:`read`.
    info : dict
        Integrity facts from :func:`read`.
    delay : int
        d [samples] for the felt energy.

    Returns
    -------
    dict
        ``samples``; ``duration_s`` (last minus first device time [s]); ``rate_hz`` (the
        inverse of the median time step); ``seq`` (``first``, ``last``, ``jumps``: forward
        steps > 1, ``missing``: sequence numbers they skip that never reached the host,
        ``skipped``: those it received but did not answer, the backlog policy's, counted
        at rows flagged ``FLAG_SKIPPED``); ``late`` (late ticks);
        ``events`` (count per event name: ``lost``, ``recovered``, ...); ``restarts``
        (samples flagged as a restart after a recovery), ``ramped``, ``clamped``;
        ``position_m``, ``force_n``, ``turnaround_us`` (``min``/``max``; turnaround also
        ``p50``/``p99``); ``felt_energy_j`` (``max``, ``end``, ``delay``); ``integrity``
        (``format``, ``intact``, and for a journal ``chunks``, ``torn_bytes``,
        ``lost_rows``: ranges ``[a, b)`` lost to a torn last chunk or to the writer);
        ``applied`` when the rows carry the device's ``force_seq``
        (:func:`hapsim.applied.account_from_force_seq`): ``method``, ``delay`` (the
        delay the device showed), ``late``, ``tick_delay_max``, ``unknown``, and
        ``felt_energy_j`` (``max``, ``end``) from the force the device applied at each tick
        (exact with late ticks; the ``felt_energy_j`` above assumes each force on time).
    """
    import numpy as np
    from hapsim.host.telemetry import FLAG_CLAMPED, FLAG_LOST, FLAG_RAMP, FLAG_SKIPPED

    t, seq = cols["time"], cols["seq"].astype(np.int64)
    flags = cols["flags"]
    n = int(seq.size)
    dt = np.diff(t)
    dt = dt[np.isfinite(dt) & (dt > 0)]
    step = np.diff(seq)
    jumps = step[step > 1]
    # a row flagged FLAG_SKIPPED answered the newest of several waiting STATEs: the jump
    # before it is the backlog policy's, not the wire's
    at_skip = (flags[1:] & FLAG_SKIPPED) != 0 if n > 1 else np.zeros(0, bool)
    skipped = int((step[at_skip & (step > 1)] - 1).sum())
    events: dict[str, int] = {}
    for ev in info.get("events", []):
        name = str(ev.get("event", "?"))
        if name in ("run", "converted"):    # (the run's description; a conversion's note)
            continue
        events[name] = events.get(name, 0) + 1
    e = felt_energy(cols["position"], cols["force"], flags, delay) if n else np.zeros(0)
    ta = cols["turnaround_us"][np.isfinite(cols["turnaround_us"])]
    lost_rows = [list(map(int, g)) for g in info.get("gaps", [])]
    if info.get("torn_rows"):
        lost_rows.append(list(map(int, info["torn_rows"])))
    was = next((ev.get("integrity") for ev in info.get("events", [])
                if ev.get("event") == "converted" and isinstance(ev.get("integrity"), dict)),
               None)                    # a file converted from one that was not intact
    integrity = {"format": info.get("format"),
                 "intact": bool(n) and not info.get("torn_bytes") and not lost_rows
                 and not info.get("time_back") and not info.get("damaged") and not was,
                 "time_back": int(info.get("time_back", 0)), "empty": not n}
    if was:
        integrity["converted_from"] = was
    if info.get("format") == "hst":
        integrity.update(chunks=int(info["chunks"]), torn_bytes=int(info["torn_bytes"]),
                         lost_rows=lost_rows, damaged_after=int(info.get("damaged", 0)))
    applied = None
    fseq = cols.get("force_seq")
    if n and fseq is not None and np.any(fseq >= 0):
        from hapsim.applied import account_from_force_seq
        acc = account_from_force_seq(seq, cols["force"], fseq, cols["status"])
        if acc.delay >= 0:
            ea = felt_energy(cols["position"], acc.applied, flags, 0)
            applied = {**acc.to_dict(), "felt_energy_j": {"max": _finite(np.nanmax(ea)),
                                                          "end": _finite(ea[-1])}}
    return {
        "applied": applied,
        "samples": n,
        "duration_s": (_finite(t[-1] - t[0]) or 0.0) if n else 0.0,
        "rate_hz": float(1.0 / np.median(dt)) if dt.size else None,
        "seq": {"first": int(seq[0]) if n else None, "last": int(seq[-1]) if n else None,
                "jumps": int(jumps.size), "missing": int((jumps - 1).sum()) - skipped,
                "skipped": skipped},
        "late": int(np.count_nonzero(cols["late"])),
        "events": events,
        "restarts": int(np.count_nonzero(flags & FLAG_LOST)),
        "ramped": int(np.count_nonzero(flags & FLAG_RAMP)),
        "clamped": int(np.count_nonzero(flags & FLAG_CLAMPED)),
        "position_m": _range(cols["position"]),
        "force_n": _range(cols["force"]),
        "turnaround_us": {**_range(ta), "p50": float(np.percentile(ta, 50)) if ta.size else None,
                          "p99": float(np.percentile(ta, 99)) if ta.size else None},
        "felt_energy_j": {"max": _finite(np.nanmax(e)) if n else None,
                          "end": _finite(e[-1]) if n else None, "delay": int(delay)},
        "integrity": integrity,
    }


def _g(v, spec: str = ".6g") -> str:
    return "-" if v is None else format(v, spec)


def format_summary(path: str, s: dict) -> str:
    """The summary as text, one fact per line.

    Parameters
    ----------
    path : str
        File name shown.
    s : dict
        Output of :func:`summarize`.

    Returns
    -------
    str
        Lines without a trailing newline.
    """
    sq, ev, ig = s["seq"], s["events"], s["integrity"]
    rate = f"{s['rate_hz']:.6g} Hz" if s["rate_hz"] else "rate unknown"
    lines = [f"{path}: {ig['format']}, {s['samples']} samples over {s['duration_s']:.6g} s "
             f"at {rate} (seq {_g(sq['first'], 'd')}..{_g(sq['last'], 'd')})"]
    other = ", ".join(f"{k} {v}" for k, v in sorted(ev.items())
                      if k not in ("lost", "recovered"))
    lines.append(f"events: lost {ev.get('lost', 0)}, recovered {ev.get('recovered', 0)}"
                 + (f"; {other}" if other else ""))
    lines.append(f"ticks: late {s['late']}, seq jumps {sq['jumps']} ({sq['missing']} missing, {sq['skipped']} skipped), "
                 f"restarts {s['restarts']}, ramped {s['ramped']}, clamped {s['clamped']}")
    p, f, ta, e = s["position_m"], s["force_n"], s["turnaround_us"], s["felt_energy_j"]
    lines.append(f"position [m]: {_g(p['min'])} .. {_g(p['max'])}")
    lines.append(f"force [N]: {_g(f['min'])} .. {_g(f['max'])}")
    lines.append(f"turnaround [us]: p50 {_g(ta['p50'], '.0f')}  p99 {_g(ta['p99'], '.0f')}  "
                 f"max {_g(ta['max'], '.0f')}")
    lines.append(f"felt energy [J] (d = {e['delay']}): max {_g(e['max'])}, end {_g(e['end'])}")
    ap = s.get("applied")
    if ap:
        lines.append(f"applied (force_seq): device delay {ap['delay']}, late {ap['late']} "
                     f"(longest {ap['tick_delay_max']} ticks behind); felt energy [J] from the "
                     f"applied force: max {_g(ap['felt_energy_j']['max'])}, end "
                     f"{_g(ap['felt_energy_j']['end'])}")
    if ig.get("converted_from"):
        lines.append("NOT INTACT: converted from a file that was not ("
                     + ", ".join(f"{k} {v}" for k, v in ig["converted_from"].items()
                                 if k in ("chunks", "torn_bytes", "lost_rows", "time_back",
                                          "damaged_after") and v) + ")")
    if ig.get("empty"):
        lines.append("NOT INTACT: no sample at all (an empty file, or a run stopped before "
                     "its first record)")
    if ig.get("time_back"):
        lines.append(f"NOT INTACT: the time goes back or repeats {ig['time_back']} times "
                     "(rows out of order or written twice: chunks swapped or repeated); "
                     "the figures above count them as they come")
    if ig["format"] == "hst":
        if ig["intact"]:
            lines.append(f"journal: {ig['chunks']} chunks, intact")
        elif ig.get("damaged_after"):
            lines.append(f"journal: {ig['chunks']} intact chunks read, then a damaged "
                         f"chunk with {ig['damaged_after']} intact chunks after it, not "
                         "read: the file is damaged in its middle (not cut by a kill); "
                         "every row after the damage is lost")
        elif ig["torn_bytes"] or ig["lost_rows"]:
            lost = ", ".join(f"rows {a}..{b - 1}" for a, b in ig["lost_rows"])
            torn = (f"; the last {ig['torn_bytes']} bytes are a chunk cut short (a kill "
                    "mid-write), ignored" if ig["torn_bytes"] else "")
            lines.append(f"journal: {ig['chunks']} intact chunks read{torn}; lost: "
                         f"{lost or 'rows of the cut chunk (count unknown)'}")
        else:
            lines.append(f"journal: {ig['chunks']} chunks read")
    elif ig["format"] == "csv":
        lines.append("csv: columns only (the loss/recovery events are kept in .hst and .npz)")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run ``hapsim telemetry``.

    Parameters
    ----------
    args : argparse.Namespace
        ``file``, ``out``, ``plot``, ``delay``, ``json``.

    Returns
    -------
    int
        0 (a truncated journal included: the summary says what was lost).

    Raises
    ------
    ConfigError
        Not a telemetry file (key ``FILE``), a negative ``--delay``, an ``--out`` with
        another extension or in a missing directory, an unwritable ``--plot`` (exit 2).
    """
    from hapsim.host.telemetry import save_columns
    from hapsim.plots import check_output_path

    if args.out:
        if os.path.splitext(args.out)[1].lower() not in _FORMATS:
            raise ConfigError(f"unknown telemetry format in {args.out!r}; valid: "
                              f"{', '.join(_FORMATS)}", key="--out")
        check_output_path(args.out, "--out")
        if os.path.abspath(args.out) == os.path.abspath(args.file):
            raise ConfigError("--out is the file being read; give another name", key="--out")
    if args.plot:
        from hapsim.plots import check_figure_path
        check_figure_path(args.plot, "--plot")
    cols, info = read(args.file)
    run_said = described(info)
    stated = run_said["delay"]
    delay = args.delay if args.delay is not None else (
        int(stated) if isinstance(stated, (int, float)) and float(stated).is_integer()
        and stated >= 0 else 1)
    s = summarize(cols, info, delay)
    s["file"] = args.file
    s["units"] = units = run_said["units"]
    if args.out:
        events = list(info.get("events") or [])
        if not s["integrity"]["intact"]:
            # (before, a torn journal's export said it was intact)
            events.append({"event": "converted", "sample": int(cols["seq"].size),
                           "from": args.file, "integrity": s["integrity"]})
        save_columns(cols, args.out, events, key="--out")
        s["out"] = args.out
    if args.plot:
        from hapsim.plots.telemetry import plot_telemetry
        from hapsim.plots import save_figure
        e = felt_energy(cols["position"], cols["force"], cols["flags"], delay)
        save_figure(plot_telemetry(cols, e, info.get("events", []),
                                   title=os.path.basename(args.file), units=units),
                    args.plot)
        s["plot"] = args.plot
    if args.json:
        print(json.dumps(s, allow_nan=False, default=_json_default))
    else:
        from hapsim.drivers import in_axis_units
        print(in_axis_units(format_summary(args.file, s), units))
        if args.out:
            print(f"wrote {args.out}")
        if args.plot:
            print(f"wrote {args.plot}")
    return 0


def _json_default(v):
    import numpy as np
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return None if not math.isfinite(v) else float(v)
    raise TypeError(type(v).__name__)
