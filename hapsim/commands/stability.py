"""``hapsim stability``: the exact largest stable virtual stiffness K_max(B)."""

from __future__ import annotations

import argparse
import json
import math
import sys

from hapsim.commands._loop_args import UNITS_HELP, para, add_loop_arguments, fmt, loop_from_args
from hapsim.option_values import declared


def register(sub) -> None:
    """Add the ``stability`` parser to ``sub``.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-parsers.
    """
    p = sub.add_parser(
        "stability", help="exact stiffness limit K_max for a virtual damping B",
        description=para("Compute the exact K_max(B) where the closed loop's spectral radius "
                    "reaches 1, and, for reference, the published first-order limits: "
                    "passivity (Colgate & Schenkel 1997, b0 > K T/2 + |B|), Diolaiti et al. "
                    "2006 (K < (b0 + B)/(T/2 + d T)) and the centred-difference oscillator "
                    "(4 m / T^2). K_max = 0 means no positive K is stable; null (JSON) or "
                    "inf means no finite limit. The limit is certified where exact "
                    "arithmetic proves it (no pole on |z| = 1 for any smaller K, stable "
                    "below and unstable above a guaranteed bracket: JSON K_max_method "
                    "'certified', K_max_interval), else labelled 'sampled (N)' (the scan of "
                    "N points of the circle) with the reason."),
        epilog=UNITS_HELP + "\nexample:\n  hapsim stability --mass 0.1 --friction 0.5 --rate 1000 "
               "--delay 1 --hold zoh --B 0\n"
               "\n2-D and 3-D devices (one K_max per direction, and over the workspace):\n"
               "  hapsim check configs/pantograph_wall.yaml     K_max along the device's "
               "principal mass axes\n"
               "  hapsim kinematics pantograph --joints 130 50 --joint-inertia 2e-4 "
               "--joint-friction 1e-3 \\\n"
               "      --hand-mass 0.05 --B 0.5 --grid 9 --out kmax.png   its map over the "
               "workspace, charted\n",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    add_loop_arguments(p)
    p.add_argument("--B", type=declared("stability", "B"), default=0.0,
                   help="virtual damping B [N s/m] (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args) -> int:
    """Run ``hapsim stability``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``stability`` options.

    Returns
    -------
    int
        0 if some ``K > 0`` is stable (``K_max > 0``), 1 if none is. The spectral radius at
        ``K_max`` is given to the digits double arithmetic knows
        (:func:`hapsim.analysis.loop.spectral_radius_known`; JSON
        ``spectral_radius_error``): a double pole there (the undamped centred-difference
        loop, at ``z = -1``) is uncertain to ~1e-7.

    Raises
    ------
    hapsim.errors.ConfigError
        Bad loop option (key: the option) or a non-finite ``--B``.
    """
    from hapsim.api import known_decimals, stability
    loop = loop_from_args(args)
    rep = stability(loop, args.B)
    d = rep.to_dict()
    kmax = math.inf if rep.K_max is None else rep.K_max
    rho, err = rep.spectral_radius_at_K_max, rep.spectral_radius_error
    if args.json:
        print(json.dumps(d))
    else:
        out = sys.stdout
        print(f"loop: m={loop.mass:g} kg  b0={loop.friction:g} N s/m  {loop.rate_hz:g} Hz  "
              f"d={loop.delay}  hold={loop.hold}   virtual B={args.B:g} N s/m", file=out)
        shown = "-" if rho is None else (
            f"{rho:.{known_decimals(err)}f} +- {err:.1g}" if err > 0
            else f"{rho:.15g}")
        print(f"  exact K_max            {fmt(kmax):>14} N/m  (spectral radius "
              f"{shown} there)", file=out)
        iv, why = rep.K_max_interval, rep.K_max_certificate
        if iv is not None and iv[1] == 0:
            print(f"  certified: K_max = 0 (exact arithmetic: {why})", file=out)
        elif iv is not None and iv[1] is None:
            print(f"  certified: every K > 0 stable (exact arithmetic: {why})", file=out)
        elif iv is not None:
            print(f"  certified: K_max in [{_outward(iv[0], up=False)}, "
                  f"{_outward(iv[1], up=True)}] N/m (exact arithmetic: {why})", file=out)
        else:
            print(f"  {rep.K_max_method}: not certified ({why})", file=out)
        if d["passivity_K"] > 0:
            print(f"  passivity (C&S 1997)   {fmt(d['passivity_K']):>14} N/m  sufficient, "
                  "zoh, d = 0", file=out)
        else:  # b0 > K T/2 + |B| holds for no K >= 0
            print(f"  passivity (C&S 1997)   {'none':>14}      |B| >= b0: no K >= 0 is "
                  "passive (b0 > K T/2 + |B|)", file=out)
        print(f"  Diolaiti et al. 2006   {fmt(d['diolaiti_K']):>14} N/m  first order in "
              "b0 T/m", file=out)
        print(f"  centred difference     {fmt(d['centred_difference_K']):>14} N/m  "
              "ideal, d = 0, b0 = B = 0", file=out)
    return 0 if kmax > 0 else 1


def _outward(v: float, up: bool, digits: int = 10) -> str:
    """``v`` to ``digits`` significant digits, rounded away from the bracket's inside
    (``up``: towards +inf), so the printed bracket still holds what the exact one does."""
    from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal
    if v == 0:
        return "0"
    d = Decimal(v)
    q = Decimal(1).scaleb(d.adjusted() - digits + 1)
    r = d.quantize(q, rounding=ROUND_CEILING if up else ROUND_FLOOR)
    return format(r.normalize(), "f") if abs(d.adjusted()) < 12 else format(r, "g")
