"""``hapsim family``: what a whole family of hands feels, and whether all of it is stable."""

from __future__ import annotations

import argparse
import json
import math

from hapsim.errors import ConfigError
from hapsim.option_values import declared

_DESCRIPTION = """\
Judge a scene over the whole family of hands that may hold the device (Florens, Voda &
Urma Sec. 4: "the whole family of possible parameter sets that the THS may get along its
variations").

The device section's hand: block gives the hand mass, its damping, the grip stiffness and
the grip damping, each a value or a range [lo, hi]. The family is every corner of the
ranges, the nominal member (the middle of every range; geometric for the grip stiffness),
and a grid (--grid points per ranged value) or --samples seeded random members. For each
member the whole scene's closed-loop state matrix is built (handle and hand states under
zero-order hold, delay line, virtual network) and its eigenvalues give:

  - the spectral radius: the family is ROBUSTLY STABLE when every member is stable; else
    the member that is not is named (an interior member may fail while every corner holds:
    a grip resonance inside the range). A grid can miss a narrow unstable band between
    two of its members, so the verdict is then certified over the continuous ranges by a
    subdivision of the parameter box (Bauer-Fike bound on each box, hapsim.analysis.
    robust; zero-order hold): it proves every member stable, or finds an unstable member
    between the sampled ones. The report says "certified" (in floating point: the bounds'
    rounding is not bounded) or, when the subdivision gives up (--certify-boxes),
    "sampled (N)": then nothing is claimed between the N members;
  - the felt (k, b) at the port (least damped pair, with m = handle + hand mass), and of
    every spring_damper between the port and a ground alone, with their spread
    (max - min) / nominal over the family.

A scene with two or more spring_dampers between the port and a ground (links in parallel),
or one and the hand's stiffness to ground (device.hand.stiffness: a real spring), is also
checked for consistency (Florens et al. Table 1 generalised, cases IV and V): the felt pair
of the parts together against the sum of what each part alone makes felt (a link on the
member without the real spring; the real spring as it is; real damping counted once); 1
would be consistent.

A correction of the virtual element (the scene's device.correction, or --correction) acts
at the port of every member: its state joins the stacked matrices, so the family stays one
batched eigenvalue call (same verdicts as the per-member loop polynomial).

Target links {k, b} are calibrated on the nominal member first. With --calibrate, each
target link is also calibrated for the whole family (minimax): the virtual (K, B) whose
worst relative error max(|k_i - k|/k, |b_i - b|/b) over the members is least, with the
member that limits it, next to the same figure for the nominal calibration."""

_EPILOG = """\
examples:
  hapsim family configs/hand_wall.yaml
  hapsim family configs/hand_wall.yaml --samples 10000 --json
  hapsim family configs/hand_wall.yaml --plot family.png
  hapsim family my_target_scene.yaml --calibrate
  hapsim family configs/hand_wall.yaml --correction velocity_filter:cutoff_hz=100

exit codes:
  0  no member found unstable (every member when certified; the sampled ones otherwise)
  1  some member is unstable (named in the report)
  2  bad scene file or option"""


def register(sub) -> None:
    """Add the ``family`` parser to ``sub`` (an argparse sub-parsers action).

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-command registry.
    """
    p = sub.add_parser(
        "family", help="a family of hands: robust stability and the spread of what is felt",
        description=_DESCRIPTION, epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="YAML scene file (device.hand with ranges)")
    p.add_argument("--samples", type=declared("family", "samples"), default=None, metavar="N",
                   help="N seeded random members instead of the grid")
    p.add_argument("--grid", type=declared("family", "grid"), default=9, metavar="G",
                   help="grid points per ranged hand value (default 9)")
    p.add_argument("--seed", type=declared("family", "seed"),
                   default=0, help="seed of --samples (default 0)")
    p.add_argument("--certify-boxes", type=declared("family", "certify"), default=4096, metavar="N",
                   help="most boxes of the certified subdivision of the ranges (default "
                        "4096; 0: the sampled verdict only)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument("--calibrate", action="store_true",
                   help="for every target link: the minimax (K, B) over the family (the "
                        "least worst relative error of the felt k and b), against the "
                        "nominal member's calibration")
    p.add_argument("--plot", metavar="FILE", default=None,
                   help="figure: felt (k, b) of every member, coloured by spectral radius")
    p.add_argument("--correction", metavar="SPEC", default=None,
                   help="a correction of the virtual element for the whole family, instead "
                        "of the scene's device.correction: KIND or KIND:PARAM=VALUE,... "
                        "(velocity_sensor | velocity_filter:cutoff_hz=HZ | "
                        "prediction[:horizon=SAMPLES] | inertia_compensation:mass=KG | "
                        "virtual_coupling:stiffness=N_PER_M,damping=NS_PER_M), or none")
    p.set_defaults(func=run)


def parse_correction(spec: str) -> dict | None:
    """A ``--correction`` option as a ``device.correction`` mapping.

    Parameters
    ----------
    spec : str
        ``KIND`` or ``KIND:PARAM=VALUE,...`` (:data:`hapsim.scene.CORRECTIONS`), or
        ``none``.

    Returns
    -------
    dict or None
        ``{"kind": KIND, PARAM: float}``; None for ``none``.

    Raises
    ------
    ConfigError
        Unknown kind or parameter, a value that is not a number or out of range (key
        ``--correction``, with the valid choices).
    """
    from hapsim.analysis.corrections import Correction
    from hapsim.scene import CORRECTIONS

    if spec.strip().lower() == "none":
        return None
    kind, _, rest = spec.partition(":")
    kind = kind.strip()
    if kind not in CORRECTIONS:
        raise ConfigError(f"unknown correction {kind!r}; valid: none, "
                          + ", ".join(CORRECTIONS), key="--correction")
    out: dict = {"kind": kind}
    for item in filter(None, (t.strip() for t in rest.split(","))):
        name, eq, value = item.partition("=")
        if not eq or name.strip() not in CORRECTIONS[kind]:
            raise ConfigError(f"bad parameter {item!r} for {kind}; valid: "
                              + (", ".join(f"{q}=VALUE" for q in CORRECTIONS[kind])
                                 or "none"), key="--correction")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise ConfigError(f"{name.strip()} must be a number, got {value!r}",
                              key="--correction") from None
    try:
        Correction.from_dict(out)
    except ConfigError as exc:
        raise ConfigError(f"{exc.reason} ({exc.key})", key="--correction") from None
    return out


def _g(v, spec=".6g"):
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) \
        else format(v, spec)


def _member_line(md: dict) -> str:
    kg = md["grip_stiffness"]
    return (f"hand {_g(md['mass'], 'g')} kg, damping {_g(md['damping'], 'g')} N s/m, grip "
            f"{kg if isinstance(kg, str) else _g(kg, '.6g') + ' N/m'} / "
            f"{_g(md['grip_damping'], 'g')} N s/m"
            + (f", arm stiffness {_g(md['stiffness'], 'g')} N/m" if md.get("stiffness") else "")
            + f"{' (a corner)' if md['corner'] else ''}: spectral radius "
            f"{_g(md['spectral_radius'], '.9g')}")


def run(args: argparse.Namespace) -> int:
    """Run ``hapsim family``.

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``samples``, ``grid``, ``seed``, ``json``, ``plot``, ``calibrate``,
        ``correction``.

    Returns
    -------
    int
        0 robustly stable, 1 some member unstable.

    Raises
    ------
    ConfigError
        Bad scene or option (exit 2 via :mod:`hapsim.cli`).
    """
    from hapsim.api import family
    from hapsim.commands.dimension import load_one_d_scene

    if args.plot:
        from hapsim.plots import check_figure_path
        check_figure_path(args.plot, "--plot")
    scene = load_one_d_scene(args.scene, "family")
    if args.correction is not None:
        import dataclasses
        corr = parse_correction(args.correction)
        scene = dataclasses.replace(scene, device=dataclasses.replace(scene.device,
                                                                      correction=corr))
    fam = family(scene, args.samples, grid=args.grid, seed=args.seed,
                 certify=args.certify_boxes, calibrate=args.calibrate)
    res, rep = fam.analysis, fam.to_dict()
    cons, cals = fam.consistency, fam.family_calibrations or []
    if args.plot:
        fam.plot(args.plot, title=args.scene)
    if args.json:
        print(json.dumps({**rep, "scene": args.scene}))
        return 0 if res.robust else 1
    if getattr(scene.device, "hand", None) is None:
        print("no device.hand section: the family is the device alone (one member)")
    else:
        print(f"family of {rep['members']} members ({rep['corners']} corners, nominal, "
              + (f"{args.samples} samples" if args.samples else f"grid {args.grid}") + ")")
    if getattr(scene.device, "correction", None) is not None:
        from hapsim.analysis.corrections import Correction
        print("correction: " + Correction.from_dict(scene.device.correction).label())
    bd = rep.get("board")
    if bd is not None and "render_latency_s" in bd:
        lo, hi = (1e3 * v for v in bd["render_latency_s"])
        at = bd.get("unstable_latency_s")
        print(f"board ({bd['protocol']}, {bd['rate_hz']:.9g} Hz): renders {lo:g}-{hi:g} ms "
              f"after its read; the family is analysed with d = {bd['delay_modelled']:.6g} "
              + (f"periods, at {at * 1e3:g} ms, where it is not robustly stable (at the "
                 f"middle it is)" if at is not None else
                 "periods (the middle) and held stable at both bounds"))
    lr = (bd or {}).get("late_reading_unstable")
    if lr is not None:
        print(f"  with the board's reply taken {lr['periods']} period(s) late, as a host "
              f"that wakes a little late takes it (d = {lr['delay']:.6g}), the family is not "
              f"robustly stable: the members below are there (hapsim run holds the scene's "
              f"own loop to the same delay)")
    for name, (K, B) in rep["calibrated"].items():
        print(f"target {name}: calibrated on the nominal member: K = {K:.6g} N/m, "
              f"B = {B:.6g} N s/m")
    cert = res.certificate
    if res.robust and res.robust_method == "certified":
        print(f"verdict: ROBUSTLY STABLE (every member of the ranges: certified in "
              f"{cert.arithmetic}; {cert.boxes} boxes)")
    elif res.robust:
        why = cert.method if cert is not None else "not asked (--certify-boxes 0)"
        print(f"verdict: ROBUSTLY STABLE on the sampled members only ({res.robust_method}); "
              f"not certified between them: {why}")
    elif rep["unstable"]:
        print(f"verdict: NOT ROBUSTLY STABLE (certified): {rep['unstable']} of "
              f"{rep['members']} members unstable"
              + ("" if not rep["corners_stable"] else
                 " (every corner is stable: the failure is inside the range)"))
        print("  first unstable member: " + _member_line(rep["first_unstable"]))
    else:
        ce = rep["certificate"]["counterexample"]
        print(f"verdict: NOT ROBUSTLY STABLE (certified in {cert.arithmetic}): every one "
              f"of the {rep['members']} sampled members is stable, but the subdivision of "
              f"the ranges found an unstable member between them ({cert.boxes} boxes)")
        print(f"  unstable member: hand {ce['mass']:g} kg, damping {ce['damping']:g} N s/m, "
              f"grip {ce['grip_stiffness']:.6g} N/m / {ce['grip_damping']:g} N s/m"
              + (f", arm stiffness {ce['stiffness']:g} N/m" if ce["stiffness"] else "")
              + f": spectral radius {ce['spectral_radius']:.9g}")
    print("  worst member: " + _member_line(rep["worst"]))
    print("felt at the port over the family (m = handle + hand of each member):")
    for q, unit in (("k", "N/m"), ("b", "N s/m")):
        st = rep["felt"][q]
        print(f"  {q}: {_g(st['min'])} .. {_g(st['max'])} {unit} (nominal {_g(st['nominal'])}, "
              f"spread {_g(st['spread'], '.3g')})")
    for name, d in rep["links"].items():
        print(f"link {name} alone (K = {d['K']:.6g}, B = {d['B']:.6g}): "
              f"k {_g(d['k']['min'])} .. {_g(d['k']['max'])} N/m, "
              f"b {_g(d['b']['min'])} .. {_g(d['b']['max'])} N s/m")
    if cons is not None:
        kr, br = cons["k_ratio"], cons["b_ratio"]
        parts = (f"links {', '.join(cons['links'])}"
                 + (" and the hand's real spring (device.hand.stiffness)"
                    if cons["real_spring"] else ""))
        print(f"consistency (Table 1 generalised): {parts} together feel "
              f"k / (sum of the parts) = {_g(kr['min'], '.4g')} .. "
              f"{_g(kr['max'], '.4g')} (nominal {_g(kr['nominal'], '.4g')}), b / (sum) = "
              f"{_g(br['min'], '.4g')} .. {_g(br['max'], '.4g')}; 1 would be consistent")
    for c in cals:
        lim = c["limiting"]
        print(f"minimax calibration of {c['link']} for (k, b) = ({c['k']:g}, {c['b']:g}): "
              f"K = {c['K']:.6g} N/m, B = {c['B']:.6g} N s/m, worst relative error "
              f"{_g(c['error'], '.4g')} (limited by hand {lim['mass']:g} kg, grip "
              f"{_g(lim['grip_stiffness'], 'g')} N/m); nominal calibration K = "
              f"{c['nominal']['K']:.6g}, B = {c['nominal']['B']:.6g}: worst "
              f"{_g(c['nominal']['error'], '.4g')}; "
              + ("every member stable" if c["stable"] else "SOME MEMBER UNSTABLE"))
    if args.plot:
        print(f"figure: {args.plot}")
    return 0 if res.robust else 1
