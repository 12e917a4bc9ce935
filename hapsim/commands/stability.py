"""``hapsim stability``: the exact largest stable virtual stiffness K_max(B)."""

from __future__ import annotations

import json
import math
import sys

from hapsim.commands._loop_args import fmt, loop_from_args, loop_line, loop_parser
from hapsim.errors import ConfigError
from hapsim.option_values import Number, declared
from hapsim.outputs import finite_or_none


def register(sub) -> None:
    """Add the ``stability`` parser to ``sub``.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-parsers.
    """
    p = loop_parser(
        sub, "stability", "exact stiffness limit K_max for a virtual damping B",
        "Compute the exact K_max(B) where the closed loop's spectral radius "
        "reaches 1, and, for reference, the published first-order limits: "
        "passivity (Colgate & Schenkel 1997, b0 > K T/2 + |B|), Diolaiti et al. "
        "2006 (K < (b0 + B)/(T/2 + d T)) and the centred-difference oscillator "
        "(4 m / T^2). K_max = 0 means no positive K is stable; null (JSON) or "
        "inf means no finite limit. The limit is certified where exact "
        "arithmetic proves it (no pole on |z| = 1 for any smaller K, stable "
        "below and unstable above a guaranteed bracket: JSON K_max_method "
        "'certified', K_max_interval), else labelled 'sampled (N)' (the scan of "
        "N points of the circle) with the reason.",
        "\nexample:\n  hapsim stability --mass 0.1 --friction 0.5 --rate 1000 "
        "--delay 1 --hold zoh --B 0\n"
        "\na scene's own loop (one K_max per direction; a 1-D scene has one):\n"
        "  hapsim stability --scene configs/wall.yaml\n"
        "  hapsim stability --scene configs/pantograph_wall.yaml   K_max along the "
        "device's principal mass axes\n"
        "  hapsim stability --scene configs/pantograph_wall.yaml --grid 9 --out "
        "kmax.png   and its map over the workspace\n"
        "  hapsim check configs/pantograph_wall.yaml     the same limits beside the "
        "felt matrices\n"
        "  hapsim kinematics pantograph --joints 130 50 --joint-inertia 2e-4 "
        "--joint-friction 1e-3 \\\n"
        "      --hand-mass 0.05 --B 0.5 --grid 9 --out kmax.png   its map over the "
        "workspace, charted\n", require=False)
    p.add_argument("--B", type=declared("stability", "B"), default=0.0,
                   help="virtual damping B [N s/m] (default %(default)s)")
    g = p.add_argument_group(
        "a scene (instead of --mass/--rate: the loop is the scene's)")
    g.add_argument("--scene", metavar="SCENE.yaml",
                   help="K_max along each principal axis of the scene's device's Cartesian "
                        "mass at its operating point (the port links' damping and the rest "
                        "of their stiffness held; the MIMO loop, not axis by axis; a 1-D "
                        "scene: its one axis)")
    g.add_argument("--grid", type=Number(int, low=0, high=40), default=0, metavar="N",
                   help="also map K_max over N points per joint within --span of the "
                        "device's joints (a pantograph or delta; the port damping held)")
    g.add_argument("--span", type=Number(float, low=0, open_low=True, unit="deg"),
                   default=30.0, metavar="DEG",
                   help="half-width of the --grid map around each joint [deg] (default 30)")
    g.add_argument("--out", metavar="FIG", help="chart the --grid map (png, pdf, svg)")
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
        (:func:`hapsim.analysis.loop_poles.spectral_radius_known`; JSON
        ``spectral_radius_error``): a double pole there (the undamped centred-difference
        loop, at ``z = -1``) is uncertain to ~1e-7.

    Raises
    ------
    hapsim.errors.ConfigError
        Bad loop option (key: the option), a non-finite ``--B``, neither the loop nor
        ``--scene``, or a bad scene (:func:`_run_scene`).
    """
    from hapsim.api import known_decimals, stability
    if args.scene is not None:
        return _run_scene(args)
    for flag in ("--grid", "--span", "--out"):
        dest = flag[2:]
        if getattr(args, dest) not in (None, 0, 30.0):
            raise ConfigError("a workspace map needs a 2-D or 3-D scene: --scene FILE",
                              key=flag)
    missing = [f for f, v in (("--mass", args.mass), ("--rate", args.rate)) if v is None]
    if missing:
        raise ConfigError(f"the loop needs {' and '.join(missing)} (or --scene FILE: the "
                          "loop of a scene's device)", key=missing[0])
    loop = loop_from_args(args)
    rep = stability(loop, args.B)
    d = rep.to_dict()
    kmax = math.inf if rep.K_max is None else rep.K_max
    rho, err = rep.spectral_radius_at_K_max, rep.spectral_radius_error
    if args.json:
        print(json.dumps(d))
    else:
        out = sys.stdout
        print(f"{loop_line(loop)}   virtual B={args.B:g} N s/m", file=out)
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


#: The loop options a scene gives itself (flag, destination, default).
_LOOP_FLAGS = (("--mass", "mass", None), ("--friction", "friction", 0.0),
               ("--rate", "rate", None), ("--delay", "delay", 1), ("--hold", "hold", "zoh"),
               ("--B", "B", 0.0))


def _run_scene(args) -> int:
    """``hapsim stability --scene``: ``K_max`` per principal direction of a scene's
    device (a 1-D scene is n = 1: :func:`_run_scene_line`; several ports:
    :func:`_run_scene_ports`) (:func:`hapsim.analysis.scene_check.check_scene_nd`, the MIMO loop's
    spectral radius through :func:`hapsim.analysis.direction_limits.direction_limit`; issue 23
    item 4) and, with ``--grid``, its map over the workspace
    (:func:`hapsim.commands.kinematics.workspace_map`).

    Returns
    -------
    int
        0 when every direction has a positive limit, 1 when one has none or the scene's
        port links end on moving masses (no port-to-ground limit to state).

    Raises
    ------
    hapsim.errors.ConfigError
        A loop option given with a scene (the scene gives them), a scene without a
        port, ``--grid`` on a Cartesian or 1-DoF device, ``--out`` without ``--grid``,
        a bad scene file.
    """
    import numpy as np

    from hapsim import api
    from hapsim.progress import Progress
    given = [f for f, dest, default in _LOOP_FLAGS if getattr(args, dest) != default]
    if given:
        raise ConfigError("a scene gives its own loop (device mass, friction, rate, delay, "
                          "hold) and its port links' damping: leave out "
                          + ", ".join(given), key=given[0])
    if args.out:
        from hapsim.plots import check_figure_path
        check_figure_path(args.out)
        if not args.grid:
            raise ConfigError("a chart needs --grid N", key="--out")
    scene = api.load_scene(args.scene)
    from hapsim.scene import ScenePorts
    if isinstance(scene, ScenePorts):
        return _run_scene_ports(args, scene)
    if scene.port is None:
        raise ConfigError("the scene has no port (nothing felt, no loop): 'hapsim check "
                          "SCENE' gives its modes", key="--scene")
    if getattr(scene, "dimension", 1) == 1:
        return _run_scene_line(args, scene)
    dev = scene.device
    if args.grid and dev.kind not in ("pantograph", "delta"):
        raise ConfigError(f"a {dev.kind} device's mass is the same over the workspace: the "
                          "limits above hold everywhere (a map needs a pantograph or a "
                          "delta)", key="--grid")
    with Progress(scene.dimension, "stiffness limits (longer with a longer delay)",
                  unit="directions") as bar:
        rep = api.check_nd(scene, progress=bar.update)
    chk = rep.analysis
    n = scene.dimension
    lim = chk.stiffness_limits
    E = chk.limit_directions

    f = finite_or_none
    w = np.linalg.eigvalsh(dev.mass)
    d = {"scene": str(args.scene), "dof": n, "device": dev.kind, "rate_hz": scene.rate_hz,
         "delay": dev.delay, "port_stiffness": chk.port_stiffness.tolist(),
         "port_damping": chk.port_damping.tolist(),
         "mass_eigenvalues": w.tolist(),
         "directions": None if E is None else E.T.tolist(),
         "K_max": None if lim is None else [f(v) for v in lim],
         "port_stiffness_along": None if E is None else [
             float(E[:, i] @ chk.port_stiffness @ E[:, i]) for i in range(n)]}
    if args.grid:
        from hapsim.commands.kinematics import workspace_map
        from hapsim.kinematics import device as kin_device
        d["workspace"] = workspace_map(
            kin_device(dev.kind, dev.geometry), dev.joints, dev.joint_inertia,
            dev.joint_friction, B=chk.port_damping, grid=args.grid, span=args.span,
            out=args.out, title=(f"{args.scene}: K_max over the workspace ({scene.rate_hz:g}"
                                 f" Hz, d = {dev.delay}, the port damping)"),
            hand_mass=dev.hand_mass, hand_damping=dev.hand_damping,
            rate_hz=scene.rate_hz, delay=dev.delay)
    code = 1 if lim is None or not np.all(lim > 0) else 0
    if args.json:
        print(json.dumps(d))
        return code
    o = sys.stdout
    print(f"scene: {args.scene}  ({n}-D {dev.kind}, {scene.rate_hz:g} Hz, d={dev.delay})",
          file=o)
    if lim is None:
        print("  no per-direction limit: a port link ends on a moving mass, so the limit "
              "of a port-to-ground spring says nothing about what is felt (as in 1-D)",
              file=o)
        return code
    print("  K_max along the principal axes of the device's Cartesian mass (the MIMO "
          "loop's spectral radius; the port damping and the rest of its stiffness held):",
          file=o)
    for i in range(n):
        e = "(" + ", ".join(f"{v:+.4f}" for v in E[:, i]) + ")"
        print(f"    {e}  mass {w[i]:.4g} kg  K_max = {fmt(lim[i])} N/m   (the scene's "
              f"port stiffness along it: {d['port_stiffness_along'][i]:.6g} N/m)", file=o)
    if args.grid:
        ws = d["workspace"]
        ok = [min(v for v in row if v is not None) for row, st in zip(ws["K_max"],
                                                                       ws["status"])
              if st == "ok" and any(v is not None for v in row)]
        print(f"  over the workspace ({args.grid} points per joint, +-{args.span:g} deg): "
              f"{len(ok)} of {len(ws['status'])} configurations assembled; lowest K_max "
              + (f"{fmt(min(ok))} N/m" if ok else "-")
              + (f"; chart: {args.out}" if args.out else ""), file=o)
    return code


def _run_scene_line(args, scene) -> int:
    """``hapsim stability --scene`` of a 1-D scene: n = 1 of the per-direction limit.

    The loop is the scene's device (:meth:`hapsim.analysis.loop.LoopModel.from_device`:
    its hand and correction included), ``B`` the damping of the links at the port (a
    ``target`` calibrated first, contacts taken as engaged, as ``hapsim check``), and
    ``K_max`` the exact limit of the port-to-ground stiffness for that ``B``
    (:func:`hapsim.api.stability`: the closed loop's spectral radius 1, Florens, Voda &
    Urma sec. 6.2). In 1-D the principal direction is the axis and the rest of the port
    stiffness is nothing, so this is the 2-D/3-D limit along one direction
    (:func:`hapsim.analysis.direction_limits.direction_limit`) with n = 1.

    Returns
    -------
    int
        0 when ``K_max > 0``, 1 when no positive stiffness is stable or a port link ends
        on a moving mass (no port-to-ground limit to state, as in 2-D/3-D).

    Raises
    ------
    hapsim.errors.ConfigError
        ``--grid`` (a 1-DoF device has no workspace map), a target the device cannot
        render, link values that are not finite.
    """
    from hapsim import api
    from hapsim.analysis.loop import LoopModel
    from hapsim.analysis.virtual_network import link_values
    if args.grid:
        raise ConfigError("a 1-DoF device's mass is the same everywhere: the limit holds "
                          "over its whole travel (a map needs a pantograph or a delta)",
                          key="--grid")
    # the loop the board the scene's device.protocol names runs (its rate of whole ticks,
    # its render latency after the read in the delay), as check and run analyse it
    from hapsim.api.checking import board_loop
    scene, _, model, board = board_loop(scene)
    dev, port = model.device, scene.port.name
    kinds = {m.name: m.kind for m in scene.masses}
    K = B = 0.0
    grounded = True
    for lk, Kl, Bl in link_values(scene):
        if port in (lk.m1, lk.m2):
            K, B = K + Kl, B + Bl
            grounded = grounded and kinds[lk.m2 if lk.m1 == port else lk.m1] == "ground"
    loop = LoopModel.from_device(dev, scene.rate_hz)
    rep = api.stability(loop, B) if grounded else None
    kmax = None if rep is None else (math.inf if rep.K_max is None else rep.K_max)
    if board is not None and "render_latency_s" in board and kmax is not None:
        # the board renders anywhere within its bounds after its read: the limit is the
        # least over them (the middle's is the loop check and run predict)
        import numpy as np

        from hapsim.analysis.prediction import timed_scene
        from hapsim.pipeline.render_latency import SPREAD_POINTS
        board["K_max_middle"] = None if math.isinf(kmax) else kmax
        for r in np.linspace(*board["render_latency_s"], SPREAD_POINTS):
            at = api.stability(LoopModel.from_device(timed_scene(scene, float(r)).device,
                                                     scene.rate_hz), B)
            k_at = math.inf if at.K_max is None else at.K_max
            if k_at < kmax:
                kmax, rep = k_at, at
                board["K_max_latency_s"] = float(r)
                board["K_max_latency"] = k_at
    if board is not None and board.get("late_reading_periods") and kmax is not None:
        # a host that wakes a little late takes the reply that many periods late:
        # the run refuses a loop unstable so (hapsim.pipeline.render_latency.late_reading)
        late_s = (board.get("render_latency_s") or [0.0, 0.0])[1] \
            + board["late_reading_periods"] * scene.period
        from hapsim.analysis.prediction import timed_scene
        at = api.stability(LoopModel.from_device(timed_scene(scene, late_s).device,
                                                 scene.rate_hz), B)
        k_at = math.inf if at.K_max is None else at.K_max
        board["K_max_late_reading"] = None if math.isinf(k_at) else k_at
        if k_at < kmax:
            kmax, rep = k_at, at
    d = {"scene": str(args.scene), "dof": 1, "device": "1-DoF", "rate_hz": scene.rate_hz,
         "delay": dev.delay, "port_stiffness": [[K]], "port_damping": [[B]],
         "mass_eigenvalues": [loop.mass], "directions": [[1.0]] if grounded else None,
         "K_max": None if kmax is None else [None if math.isinf(kmax) else kmax],
         "port_stiffness_along": [K] if grounded else None,
         "stability": None if rep is None else rep.to_dict(), "board": board}
    code = 1 if kmax is None or not kmax > 0 else 0
    if args.json:
        print(json.dumps(d))
        return code
    o = sys.stdout
    print(f"scene: {args.scene}  (1-D, {scene.rate_hz:g} Hz, d={dev.delay:.6g})", file=o)
    if board is not None:
        from hapsim.commands.check import print_board
        print_board(board)
    if kmax is None:
        print("  no limit: a port link ends on a moving mass, so the limit of a "
              "port-to-ground spring says nothing about what is felt", file=o)
        return code
    print(f"  K_max along the device's axis (the closed loop's spectral radius; the port "
          f"damping B = {B:g} N s/m held):", file=o)
    print(f"    (+1.0000)  mass {loop.mass:.4g} kg  K_max = {fmt(kmax)} N/m   (the "
          f"scene's port stiffness: {K:.6g} N/m; {rep.K_max_method})", file=o)
    if board is not None and "K_max_latency_s" in board:
        print(f"    the least over the board's render latency: {fmt(board['K_max_latency'])} "
              f"N/m at {board['K_max_latency_s'] * 1e3:.3g} ms after its read (at the "
              f"middle: {fmt(board['K_max_middle'])} N/m)", file=o)
    if board is not None and board.get("K_max_late_reading") == kmax:
        n = board["late_reading_periods"]
        print(f"    the least with the board's reply taken {n} period{'s' if n != 1 else ''} "
              f"late, as a host that wakes a little late takes it: {fmt(kmax)} N/m "
              f"(hapsim run refuses a spring beyond it)", file=o)
    return code


def _run_scene_ports(args, scene) -> int:
    """``hapsim stability --scene`` of a scene with several ports: ``K_max`` along each
    port's axis of the coupled loop, the rest of the port stiffness and the port damping
    held (:func:`hapsim.analysis.direction_limits.direction_limit` with each port's own
    delay, the loop of :func:`hapsim.analysis.ports.port_loop`; the MIMO loop's spectral
    radius, not port by port).

    Returns
    -------
    int
        0 when every port has a positive limit, else 1.

    Raises
    ------
    hapsim.errors.ConfigError
        ``--grid`` (the ports' masses are the same everywhere).
    """
    import numpy as np

    from hapsim.analysis.direction_limits import direction_limit
    from hapsim.analysis.ports import port_loop, port_matrices
    from hapsim.progress import Progress
    if args.grid:
        raise ConfigError("the ports' devices have the same mass everywhere: the limits "
                          "hold over their whole travel (a map needs a pantograph or a "
                          "delta)", key="--grid")
    loop, delays = port_loop(scene)
    K, B = port_matrices(scene)
    P = loop.dof
    E = np.eye(P)
    lim = np.empty(P)
    with Progress(P, "stiffness limits", unit="ports") as bar:
        for i in range(P):
            lim[i] = direction_limit(loop, E[:, i], B, K - K[i, i] * np.outer(E[:, i],
                                                                               E[:, i]),
                                     delays=delays)
            bar.update(i + 1, P)
    per = [float(d.delay) for _, d in scene.devices]
    d = {"scene": str(args.scene), "dof": P, "device": "ports", "ports": list(scene.ports),
         "rate_hz": scene.rate_hz, "delay": per, "port_stiffness": K.tolist(),
         "port_damping": B.tolist(), "mass_eigenvalues": np.diag(loop.mass).tolist(),
         "directions": E.tolist(),
         "K_max": [float(v) if np.isfinite(v) else None for v in lim],
         "port_stiffness_along": np.diag(K).tolist()}
    code = 0 if np.all(lim > 0) else 1
    if args.json:
        print(json.dumps(d))
        return code
    o = sys.stdout
    print(f"scene: {args.scene}  ({P} ports, {scene.rate_hz:g} Hz, delays "
          + ", ".join(f"{x:g}" for x in per) + ")", file=o)
    print("  K_max along each port's axis (the coupled loop's spectral radius; the port "
          "damping and the rest of the port stiffness held):", file=o)
    for i, name in enumerate(scene.ports):
        print(f"    {name:<10} mass {loop.mass[i, i]:.4g} kg  K_max = {fmt(lim[i])} N/m   "
              f"(the scene's port stiffness along it: {K[i, i]:.6g} N/m)", file=o)
    return code
