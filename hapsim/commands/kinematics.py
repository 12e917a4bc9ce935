"""``hapsim kinematics``: a multi-DoF device's handle position and Jacobian at given joints."""

from __future__ import annotations

import argparse
import json
import math
import sys

from hapsim.errors import ConfigError
from hapsim.option_values import Number, declared
from hapsim.outputs import finite_or_none

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
    p.add_argument("--joints", type=Number(unit="deg"), nargs="+", required=True, metavar="DEG",
                   help="joint angles [deg]: 2 for the pantograph, 3 for the delta")
    p.add_argument("--geometry", default=None, metavar="SPEC",
                   help="a preset name (pantograph: haply; delta: falcon) or the lengths "
                        "[m] comma-separated: pantograph l,L,d; delta a,b,c,d,e,f (leg "
                        "base and angles stay the Falcon's)")
    p.add_argument("--force", type=Number(unit="N"), nargs="+", default=None, metavar="N",
                   help="a Cartesian handle force [N] (2 or 3 components): also print "
                        "the joint torques J^T F [N m]")
    g = p.add_argument_group(
        "stiffness limits (the THS as a matrix at these joints: hapsim.analysis.ths)")
    g.add_argument("--joint-inertia", type=Number(float, low=0, open_low=True, unit="kg m^2"),
                   nargs="+", metavar="KG_M2",
                   help="joint inertia [kg m^2], one per joint (or one for all): computes "
                        "the Cartesian mass and K_max along its principal axes")
    g.add_argument("--joint-friction", type=Number(float, low=0, unit="N m s/rad"),
                   nargs="+", default=[0.0],
                   metavar="N_M_S", help="joint viscous friction [N m s/rad] (default 0)")
    g.add_argument("--hand-mass", type=Number(float, low=0, unit="kg"),
                   default=0.0, help="hand mass [kg] (default 0)")
    g.add_argument("--hand-damping", type=Number(float, low=0, unit="N s/m"), default=0.0,
                   help="hand damping [N s/m] (default 0)")
    g.add_argument("--rate", type=declared("loop", "rate_hz"),
                   default=1000.0, help="sample rate [Hz] (default 1000)")
    g.add_argument("--delay", type=declared("loop", "delay"),
                   default=1, help="delay [periods], a real number (default 1)")
    g.add_argument("--B", type=Number(unit="N s/m"), default=0.0,
                   help="virtual damping [N s/m], isotropic (default 0)")
    g.add_argument("--grid", type=Number(int, low=0, high=40), default=0, metavar="N",
                   help="also map K_max over N points per joint within --span of the joints")
    g.add_argument("--span", type=Number(float, low=0, open_low=True, unit="deg"),
                   default=30.0, metavar="DEG",
                   help="half-width of the --grid map around each joint [deg] (default 30)")
    g.add_argument("--out", metavar="FIG", help="chart the --grid map (png, pdf, svg)")
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
    if args.joint_inertia is not None:
        out.update(_limits(args, dev, q, n))
    elif args.grid or args.out:
        raise ConfigError("the stiffness limits need --joint-inertia", key="--joint-inertia")
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
    if "limits" in out:
        lim = out["limits"]
        print(f"  Cartesian mass [kg] eigenvalues {', '.join(f'{v:.6g}' for v in lim['mass_eigenvalues'])}"
              f"; K_max [N/m] along them (B = {args.B:g} N s/m, {args.rate:g} Hz, d = "
              f"{args.delay}):", file=o)
        for e, k in zip(lim["directions"], lim["K_max"]):
            print("    (" + ", ".join(f"{v:+.4f}" for v in e) + f")  K_max = "
                  f"{'inf' if k is None else format(k, '.6g')}", file=o)
        if any(k == 0 for k in lim["K_max"]):
            print("  K_max = 0 along an axis: no stiffness K > 0 is stable there (the damping, "
                  "--B plus --joint-friction and --hand-damping through J, is too small "
                  "for the delay: raise one of them)", file=o)
    if "workspace" in out:
        w = out["workspace"]
        ks = [v[0] for v, st in zip(w["K_max"], w["status"]) if st == "ok"]
        print(f"  workspace map: {len(w['status'])} configurations, {len(ks)} usable; "
              f"K_max along the lightest axis from {min(ks):.6g} to {max(ks):.6g} N/m"
              if ks else "  workspace map: no usable configuration", file=o)
    return 0


def _per_joint(values, n, key):
    if len(values) == 1:
        return [values[0]] * n
    if len(values) != n:
        raise ConfigError(f"must be 1 or {n} values, got {len(values)}", key=key)
    return list(values)


def _limits(args, dev, q, n) -> dict:
    """The ``limits`` (and ``workspace``) part of the output."""
    import numpy as np

    from hapsim.analysis.ths import MatrixLoop

    from hapsim.analysis.direction_limits import direction_limits
    Iq = _per_joint(args.joint_inertia, n, "--joint-inertia")
    Bq = _per_joint(args.joint_friction, n, "--joint-friction")
    if args.out:
        from hapsim.plots import check_figure_path
        check_figure_path(args.out)
        if not args.grid:
            raise ConfigError("a chart needs --grid N", key="--out")
    kw = dict(hand_mass=args.hand_mass, hand_damping=args.hand_damping,
              rate_hz=args.rate, delay=args.delay)
    loop = MatrixLoop.from_device(dev, q, Iq, Bq, **kw)
    w, V = np.linalg.eigh(loop.mass)
    K = direction_limits(loop, V, args.B * np.eye(n))

    f = finite_or_none
    out = {"limits": {"mass": loop.mass.tolist(), "friction": loop.friction.tolist(),
                      "mass_eigenvalues": w.tolist(), "directions": V.T.tolist(),
                      "K_max": [f(v) for v in K], "B": args.B}}
    if args.grid:
        out["workspace"] = workspace_map(
            dev, q, Iq, Bq, B=args.B * np.eye(n), grid=args.grid, span=args.span,
            out=args.out, title=(f"{args.device}: K_max over the workspace (B = "
                                 f"{args.B:g} N s/m, {args.rate:g} Hz, d = {args.delay})"),
            **kw)
    return out


def workspace_map(dev, q, joint_inertia, joint_friction, *, B, grid: int, span: float,
                  out: str | None = None, title: str = "", **loop) -> dict:
    """``K_max`` along the principal axes of the Cartesian mass over a grid of joint
    configurations around ``q``, as JSON-ready lists, charted to ``out`` if given
    (``hapsim kinematics --grid`` and ``hapsim stability --scene --grid``).

    Parameters
    ----------
    dev : hapsim.kinematics.Pantograph or hapsim.kinematics.Delta
    q : array_like, shape (n,)
        The grid's centre [rad].
    joint_inertia, joint_friction
        As :meth:`hapsim.analysis.ths.MatrixLoop.from_device`.
    B : ndarray, shape (n, n)
        Virtual damping [N s/m].
    grid : int
        Points per joint, 2 to 40 (``grid ** n`` configurations).
    span : float
        Half-width of the grid around each joint [deg].
    out : str, optional
        Chart path (png, pdf, svg).
    title : str, optional
    **loop
        ``hand_mass``, ``hand_damping``, ``rate_hz``, ``delay``.

    Returns
    -------
    dict
        ``joints_deg``, ``positions`` [m], ``status``, ``mass_eigenvalues`` [kg],
        ``K_max`` [N/m] (:func:`hapsim.analysis.direction_limits.workspace_limits`; None for a
        non-finite value).

    Raises
    ------
    ConfigError
        ``grid`` outside 2..40 (key ``--grid``); a grid point beyond one turn (key
        ``joints``).
    """
    import itertools

    import numpy as np

    from hapsim.analysis.direction_limits import workspace_limits
    from hapsim.progress import Progress
    if not 2 <= grid <= 40:
        raise ConfigError(f"must be between 2 and 40, got {grid}", key="--grid")

    f = finite_or_none
    axes = [np.linspace(v - np.radians(span), v + np.radians(span), grid) for v in q]
    Q = np.array(list(itertools.product(*axes)))
    with Progress(len(Q), "workspace map", unit="configurations") as bar:
        res = workspace_limits(dev, Q, joint_inertia, joint_friction, B=B,
                               progress=bar.update, **loop)
    if out:
        from hapsim.plots import save_figure
        from hapsim.plots.workspace import plot_workspace
        save_figure(plot_workspace(res, title), out)
    return {"joints_deg": np.degrees(res.joints).tolist(),
            "positions": [[f(v) for v in row] for row in res.positions],
            "status": res.status,
            "mass_eigenvalues": [[f(v) for v in row] for row in res.mass_eigenvalues],
            "K_max": [[f(v) for v in row] for row in res.limits]}
