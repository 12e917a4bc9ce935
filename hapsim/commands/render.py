"""``hapsim render``: what the user feels, (K, B) -> (k, b)."""

from __future__ import annotations

import json
import sys

from hapsim.errors import fixed

from hapsim.commands._loop_args import fmt, loop_from_args, loop_line, loop_parser, print_modes
from hapsim.option_values import declared


def register(sub) -> None:
    """Add the ``render`` parser to ``sub``.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-parsers.
    """
    p = loop_parser(
        sub, "render", "predict the stiffness k and damping b felt for a virtual K, B",
        "Close the THS loop (real mass + friction, hold, delay, virtual spring K "
        "and damper B) and report the oscillator the user feels: the least "
        "damped closed-loop pole pair as k, b, f0, damping ratio; the other "
        "poles are listed as parasitic modes. A spectral radius within 1e-9 of 1 is "
        "reported as marginal and counted as stable (as 'hapsim check' does). "
        "Exit 1 when the loop is unstable.",
        "\nexample:\n  hapsim render --mass 0.1 --friction 0.5 --rate 1000 "
        "--delay 1 --hold zoh --K 2000 --B 2\n")
    p.add_argument("--K", type=declared("render", "K"), required=True, help="virtual stiffness K [N/m]")
    p.add_argument("--B", type=declared("render", "B"), default=0.0, help="virtual damping B [N s/m] "
                   "(default %(default)s)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args) -> int:
    """Run ``hapsim render``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``render`` options.

    Returns
    -------
    int
        0 if the loop is stable (marginal included), 1 if not.

    Raises
    ------
    hapsim.errors.ConfigError
        Bad loop option (key: the option) or a non-finite ``--K`` / ``--B``.
    """
    from hapsim.api import render
    loop = loop_from_args(args)
    rep = render(loop, args.K, args.B)
    r = rep.analysis
    if args.json:
        print(json.dumps(rep.to_dict()))
    else:
        out = sys.stdout
        print(f"{loop_line(loop)}   virtual K={args.K:g} N/m  B={args.B:g} N s/m", file=out)
        print(f"  felt k        {fmt(r.k):>12} N/m", file=out)
        print(f"  felt b        {fmt(r.b):>12} N s/m  (real + virtual)", file=out)
        print(f"  f0            {fmt(r.f0_hz):>12} Hz", file=out)
        print(f"  damping ratio {fmt(r.damping_ratio):>12}", file=out)
        verdict = ("stable, marginal: a mode on the unit circle never decays" if r.marginal
                   else "stable" if r.stable else "UNSTABLE")
        print(f"  spectral rad. {fixed(r.spectral_radius, '>12.9f')}  ({verdict})", file=out)
        if r.note:
            print(f"  note: {r.note}", file=out)
        print("parasitic modes:", file=out)
        print_modes(r.modes, out)
    return 0 if r.stable else 1
