"""``hapsim bench``: speed against accuracy, charted (PNG + JSON)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

_DESCRIPTION = """\
Measure and chart speed against accuracy. Writes into --out:

  accuracy_vs_rate.png/.json  felt (k, b) error against rate (250 Hz - 20 kHz), naive
                              (K = k, B = b - b0) and calibrated rendering, d = 0, 1, 2,
                              ZOH and ideal hold, three targets; boundary rates marked
  accuracy_vs_cost.png/.json  eigenfrequency/damping error of a virtual oscillator and a
                              50-mass string per integrator (centred, symplectic_euler,
                              exact) against CPU time measured in the same run
  loop_capacity.png/.json     missed deadlines and turnaround p50/p99/p999 of the daemon
                              with the mock over a real pty at 1, 2, 5, 10 kHz, next to a
                              raw os.read/os.write pty echo (the machine's floor)

--quick uses a few rates and short timings (seconds, for tests). --from-json re-reads the
JSON already in --out and re-derives what is computed from the measurements (loop_capacity:
the daemon/echo ratios) without measuring again. --only NAME (repeatable)
regenerates just the named charts and leaves the others' files untouched."""

#: Chart names, in the order they are computed (also the JSON / PNG file stems).
CHARTS = ("accuracy_vs_rate", "accuracy_vs_cost", "loop_capacity")

_EPILOG = """\
examples:
  hapsim bench --out docs/bench
  hapsim bench --quick --out /tmp/bench
  hapsim bench --only accuracy_vs_rate --out docs/bench
  hapsim bench --only loop_capacity --from-json --no-plot --out docs/bench

exit codes: 0 written; 2 bad option or output directory"""


def register(sub) -> None:
    """Add the ``bench`` parser to ``sub`` (an argparse sub-parsers action).

    Parameters
    ----------
    sub : argparse._SubParsersAction
    """
    p = sub.add_parser("bench", help="chart speed against accuracy (PNG + JSON)",
                       description=_DESCRIPTION, epilog=_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--quick", action="store_true", help="tiny grids and short timings")
    p.add_argument("--no-daemon", action="store_true",
                   help="skip the daemon run of the loop-capacity chart (echo floor only)")
    p.add_argument("--no-plot", action="store_true", help="JSON only")
    p.add_argument("--from-json", action="store_true",
                   help="re-derive from the JSON in --out instead of measuring")
    p.add_argument("--only", action="append", choices=CHARTS, metavar="CHART",
                   help="regenerate only this chart (repeatable; one of "
                        f"{', '.join(CHARTS)}); default: all three")
    p.set_defaults(func=run)


def run(args) -> int:
    """Compute the charts' data (all three, or those of ``--only``), write JSON and PNG.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``bench`` options (``out``, ``quick``, ``no_daemon``, ``no_plot``, ``only``).

    Returns
    -------
    int
        Exit code 0.

    Raises
    ------
    hapsim.errors.ConfigError
        When the output directory cannot be created, ``--from-json`` is combined with
        ``--quick``, or a JSON to re-derive from is missing or unreadable.
    """
    from hapsim.bench import accuracy, capacity, cost
    from hapsim.errors import ConfigError

    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create output directory: {exc}", key="--out") from exc
    q = args.quick
    jobs = [
        ("accuracy_vs_rate", lambda: accuracy.accuracy_vs_rate(
            accuracy.QUICK_RATES if q else accuracy.FULL_RATES)),
        ("accuracy_vs_cost", lambda: cost.accuracy_vs_cost(
            cost.QUICK_RATES if q else cost.FULL_RATES, samples=2000 if q else 20000,
            repeats=3 if q else 7)),
        ("loop_capacity", lambda: capacity.loop_capacity(
            capacity.QUICK_RATES if q else capacity.RATES, 0.2 if q else 1.0,
            daemon=not args.no_daemon)),
    ]
    if args.from_json and args.quick:
        raise ConfigError("--from-json re-reads data, it does not measure: drop --quick",
                          key="--from-json")
    plots = {"accuracy_vs_rate": "plot_accuracy_vs_rate",
             "accuracy_vs_cost": "plot_accuracy_vs_cost", "loop_capacity": "plot_capacity"}
    only = set(args.only or CHARTS)
    for name, fn in jobs:
        if name not in only:
            continue
        t0 = time.perf_counter()
        path = os.path.join(args.out, name + ".json")
        if args.from_json:
            data = _rederive(name, path)
        else:
            data = fn()
            data["generated_by"] = "hapsim bench" + (" --quick" if q else "")
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=1, allow_nan=False)
        msg = f"{path} ({time.perf_counter() - t0:.1f} s)"
        if not args.no_plot:
            from hapsim.plots import bench as plot_bench
            from hapsim.plots import save_figure
            png = os.path.join(args.out, name + ".png")
            save_figure(getattr(plot_bench, plots[name])(data), png)
            msg += f", {png}"
        print(msg, file=sys.stderr)
    return 0


def _rederive(name: str, path: str) -> dict:
    """Load a chart's JSON and recompute the fields derived from its measurements.

    Parameters
    ----------
    name : str
        One of :data:`CHARTS`.
    path : str
        The chart's JSON file.

    Returns
    -------
    dict
        The data, with ``loop_capacity``'s ``ratios`` recomputed by
        :func:`hapsim.bench.capacity.capacity_ratios` (other charts: as read).

    Raises
    ------
    hapsim.errors.ConfigError
        When the file is missing, not JSON, or not the chart's measurements (key
        ``--from-json``).
    """
    from hapsim.bench import capacity
    from hapsim.errors import ConfigError
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"cannot re-read {path}: {exc}", key="--from-json") from None
    if not isinstance(data, dict) or (name == "loop_capacity" and not (
            isinstance(data.get("echo"), list) and isinstance(data.get("daemon"), list))):
        # (a list was an AttributeError; {} was rewritten as {"ratios": []}, exit 0)
        raise ConfigError(f"cannot re-read {path}: not the {name} chart's measurements "
                          "(a JSON object with its rows)", key="--from-json")
    if name == "loop_capacity":
        data["ratios"] = capacity.capacity_ratios(data.get("echo"), data.get("daemon"))
    return data
