"""``hapsim kinematics``: a multi-DoF device's handle position and Jacobian at given joints."""

from __future__ import annotations

import argparse
import json
import math
import sys

from hapsim.errors import ConfigError

#: Parameters of ``--geometry`` per device, in order (lengths [m]).
GEOMETRY_FIELDS = {"pantograph": ("l", "L", "d"), "delta": ("a", "b", "c", "d", "e", "f")}


def register(sub) -> None:
    """Add the ``kinematics`` parser to ``sub``.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-parsers.
    """
    p = sub.add_parser(
        "kinematics", help="handle position and Jacobian of the pantograph or the delta",
        description=(
            "Forward kinematics and Jacobian J = dx/dq of a multi-DoF device at the given "
            "joint angles: the planar five-bar pantograph (Haply 2DIY geometry by "
            "default) or the Novint Falcon's delta (after Stamper, libnifalcon's "
            "constants). Configurations outside the workspace or at a singularity are "
            "refused (exit 2). With --force, also the joint torques tau = J^T F."),
        epilog=("units: joints [deg] in, position [m], Jacobian [m/rad], force [N], "
                "torques [N m]\nexamples:\n"
                "  hapsim kinematics pantograph --joints 130 50 --json\n"
                "  hapsim kinematics pantograph --joints 130 50 --geometry 0.05,0.07,0.02\n"
                "  hapsim kinematics delta --joints 10 20 30 --force 0 0 1\n"),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("device", choices=sorted(GEOMETRY_FIELDS),
                   help="pantograph (2 joints) or delta (3 joints)")
    p.add_argument("--joints", type=float, nargs="+", required=True, metavar="DEG",
                   help="joint angles [deg]: 2 for the pantograph, 3 for the delta")
    p.add_argument("--geometry", default=None, metavar="SPEC",
                   help="a preset name (pantograph: haply; delta: falcon) or the lengths "
                        "[m] comma-separated: pantograph l,L,d; delta a,b,c,d,e,f (leg "
                        "base and angles stay the Falcon's)")
    p.add_argument("--force", type=float, nargs="+", default=None, metavar="N",
                   help="a Cartesian handle force [N] (2 or 3 components): also print "
                        "the joint torques J^T F [N m]")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def _geometry(kind: str, spec: str | None):
    from dataclasses import replace

    from hapsim.kinematics import DELTA_PRESETS, PANTOGRAPH_PRESETS, PantographGeometry
    presets = PANTOGRAPH_PRESETS if kind == "pantograph" else DELTA_PRESETS
    if spec is None:
        return next(iter(presets))
    if spec in presets:
        return spec
    names = GEOMETRY_FIELDS[kind]
    parts = spec.split(",")
    try:
        values = [float(v) for v in parts]
    except ValueError:
        values = None
    if values is None or len(values) != len(names):
        raise ConfigError(f"must be a preset ({', '.join(presets)}) or {len(names)} "
                          f"comma-separated lengths {','.join(names)} [m], got {spec!r}",
                          key="--geometry")
    try:
        if kind == "pantograph":
            return PantographGeometry.symmetric(*values)
        return replace(DELTA_PRESETS["falcon"], **dict(zip(names, values)))
    except ConfigError as exc:
        raise ConfigError(exc.reason, key=f"--geometry {exc.key}") from None


def run(args) -> int:
    """Run ``hapsim kinematics``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``kinematics`` options.

    Returns
    -------
    int
        0 (a refused configuration raises).

    Raises
    ------
    hapsim.errors.ConfigError
        Wrong number of joints or force components, a bad ``--geometry``.
    hapsim.errors.KinematicsError
        Outside the workspace or singular (a ConfigError: exit 2).
    """
    from hapsim.kinematics import device
    dev = device(args.device, _geometry(args.device, args.geometry))
    n = dev.dof
    if len(args.joints) != n:
        raise ConfigError(f"the {args.device} takes {n} joint angles [deg], got "
                          f"{len(args.joints)}", key="--joints")
    q = [math.radians(v) for v in args.joints]
    x = dev.forward(q)
    J = dev.jacobian(q)
    out = {"device": args.device, "joints_deg": list(args.joints),
           "position": x.tolist(), "jacobian": J.tolist(),
           "geometry": dev.geometry.to_dict()}
    if args.force is not None:
        if len(args.force) != n:
            raise ConfigError(f"the {args.device} takes {n} force components [N], got "
                              f"{len(args.force)}", key="--force")
        out["force"] = list(args.force)
        out["torques"] = dev.torques(q, args.force).tolist()
    if args.json:
        print(json.dumps(out))
        return 0
    o = sys.stdout
    axes = "xyz"[:n]
    print(f"{args.device} at joints {', '.join(f'{v:g}' for v in args.joints)} deg", file=o)
    print("  position [m]      " + "  ".join(f"{a}={v:+.9f}" for a, v in zip(axes, x)),
          file=o)
    print("  Jacobian [m/rad]  rows d" + "/d".join(axes) + ", columns dq1..dq" + str(n),
          file=o)
    for row in J:
        print("    " + "  ".join(f"{v:+.9f}" for v in row), file=o)
    if "torques" in out:
        print("  torques J^T F [N m]  " + "  ".join(f"{v:+.9g}" for v in out["torques"]),
              file=o)
    return 0
