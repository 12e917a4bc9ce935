"""``hapsim advise``: the lowest rate and the cheapest method a scene needs."""

from __future__ import annotations

import argparse
import json

from hapsim.option_values import Number

_DESCRIPTION = """\
Model no more than a scene needs. For each link to the port and for the scene as a whole,
find the lowest sample rate (R10 ladder 250 Hz ... 20 kHz) and the cheapest method that

  - keep the felt (k, b) within --tolerance (relative, on k and on b) of what is asked:
    a target {k, b}; for a plain link its (K, B + b0); for the whole scene the felt pair
    of the continuous-time loop (device + network, no sampling, no delay);
  - keep the closed loop stable with margin: still stable when every (K, B) is divided
    by --margin (0.95: a 5 % gain margin; a bound on the spectral radius itself would
    forbid high rates, since |z| -> 1 as the rate grows).

Methods, cheapest first: per port link naive (K, B as written) then calibrated; per scene
the integrators centred, symplectic_euler, exact (not with contacts)."""

_EPILOG = """\
examples:
  hapsim advise configs/wall.yaml
  hapsim advise configs/wall.yaml --tolerance 0.05 --json

exit codes: 0 advice found; 1 nothing on the ladder meets tolerance and margin;
2 bad scene or option"""


def register(sub) -> None:
    """Add the ``advise`` parser to ``sub`` (an argparse sub-parsers action).

    Parameters
    ----------
    sub : argparse._SubParsersAction
    """
    p = sub.add_parser("advise", help="lowest rate and cheapest method a scene needs",
                       description=_DESCRIPTION, epilog=_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="YAML scene file")
    p.add_argument("--tolerance", type=Number(float, low=0, open_low=True), default=0.01,
                   help="relative error allowed on felt k and b (default 0.01)")
    p.add_argument("--margin", type=Number(float, low=0, high=1, open_low=True), default=0.95,
                   help="gain margin: stable with (K, B) / margin (default 0.95)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args) -> int:
    """Print the advice of :func:`hapsim.bench.advise.advise_scene`.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``advise`` options (``scene``, ``tolerance``, ``margin``, ``json``).

    Returns
    -------
    int
        0 when an advice was found, 1 otherwise.

    Raises
    ------
    hapsim.errors.ConfigError
        Bad scene file, tolerance or margin.
    """
    from hapsim import load_scene
    from hapsim.bench.advise import advise_scene
    from hapsim.commands.dimension import load_one_d_scene

    scene = load_scene(args.scene)
    if getattr(scene, "dimension", 1) == 1:
        scene = load_one_d_scene(args.scene, "advise")
    adv = advise_scene(scene, args.tolerance, margin=args.margin)
    if args.json:
        d = adv.to_dict()
        d["scene"] = scene.path
        print(json.dumps(d, indent=1))
        return 0 if adv.ok else 1
    print(f"scene {scene.path} (now {scene.rate_hz:g} Hz, {scene.integrator}); "
          f"tolerance {args.tolerance:g}, gain margin {args.margin:g}")
    if adv.board is not None:
        bd = adv.board
        lat = (f"; its render {bd['render_latency_s'] * 1e3:g} ms after the read (the "
               f"middle of its bounds) added to the delay, the margin held at "
               f"{bd['render_latency_end_s'] * 1e3:g} ms too" if bd["render_latency_s"]
               else "")
        n = bd.get("late_reading_periods") or 0
        lat += (f", and with its reply taken {n} period{'s' if n != 1 else ''} late" if n
                else "")
        print(f"  board ({bd['protocol']}): the ladder's rates it holds: "
              f"{', '.join(f'{r:g}' for r in bd['rates']) or 'none'} Hz{lat}")
    for la in adv.links:
        where = (f"{la.rate_hz:g} Hz, {la.method}, send K = {la.K:.6g} N/m, B = {la.B:.6g} N s/m"
                 if la.rate_hz else "none")
        print(f"  link {la.link}: wants (k, b) = ({la.wanted[0]:g}, {la.wanted[1]:g}): {where}")
        print(f"    because {la.reason}")
    if adv.ok:
        print(f"  scene: {adv.rate_hz:g} Hz, integrator {adv.integrator}")
    else:
        print("  scene: no advice")
    print(f"    because {adv.reason}")
    return 0 if adv.ok else 1
