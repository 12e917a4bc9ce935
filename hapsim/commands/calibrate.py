"""``hapsim calibrate``: virtual (K, B) that make the user feel a target (k, b)."""

from __future__ import annotations

import json
import sys

from hapsim.commands._loop_args import fmt, loop_from_args, loop_line, loop_parser, print_modes
from hapsim.option_values import declared


def register(sub) -> None:
    """Add the ``calibrate`` parser to ``sub``.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-parsers.
    """
    p = loop_parser(
        sub, "calibrate", "find the virtual K, B that render a target k, b",
        "Place two closed-loop poles on those of the target oscillator "
        "m s^2 + b s + k = 0 and solve for the virtual K and B. Then check every "
        "other pole: if one is unstable or less damped than the target, the "
        "target is not renderable with this configuration and the command says "
        "why (exit 1).",
        "\nexample:\n  hapsim calibrate --mass 0.1 --friction 0.5 --rate 1000 "
        "--delay 1 --hold zoh --k 2000 --b 3\n")
    p.add_argument("--k", type=declared("calibrate", "k"),
                   required=True, help="target felt stiffness k [N/m], > 0")
    p.add_argument("--b", type=declared("calibrate", "b"), required=True,
                   help="target felt damping b [N s/m] (whole: real b0 + virtual)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args) -> int:
    """Run ``hapsim calibrate``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``calibrate`` options.

    Returns
    -------
    int
        0 if the target is renderable, 1 if not.

    Raises
    ------
    hapsim.errors.ConfigError
        Bad loop option (key: the option), ``--k <= 0`` or a non-finite target.
    """
    from hapsim.api import calibrate
    loop = loop_from_args(args)
    rep = calibrate(loop, args.k, args.b)
    c = rep.analysis
    if args.json:
        print(json.dumps(rep.to_dict()))
    else:
        out = sys.stdout
        print(f"{loop_line(loop)}   target k={args.k:g} N/m  b={args.b:g} N s/m", file=out)
        print(f"  virtual K     {fmt(c.K):>14} N/m", file=out)
        print(f"  virtual B     {fmt(c.B):>14} N s/m", file=out)
        print(f"  renderable    {'yes' if c.renderable else 'NO':>14}", file=out)
        print(f"  spectral rad. {fmt(c.spectral_radius):>14}", file=out)
        print(f"  {c.reason}", file=out)
        print("other (parasitic) modes:", file=out)
        print_modes(c.modes, out)
    return 0 if c.renderable else 1
