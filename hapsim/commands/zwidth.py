"""``hapsim zwidth``: the stiffness limit K_max(B) measured on the device, beside the
predicted one."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys

from hapsim.errors import ConfigError
from hapsim.option_values import Number

_DESCRIPTION = """\
Measure the device's Z-width (Colgate & Brown 1994): for each virtual damping B, the
largest wall stiffness K it renders stably, located from the records themselves.

For each B a one-link wall (K, B) is run on the device, released from x0, for a short
record; hapsim run's identification gives the felt pair, whose damping b sets the dominant
pole's modulus rho = exp(-b T / 2m): < 1 the record decays, > 1 it grows (on the boundary
b = 0). K starts below the predicted limit and is raised by 15 % per record until a record
grows (the run's safety limits stay armed; x0 is reduced so that K x0 stays under 30 % of
the force limit), then the crossing is refined by regula falsi on the measured b(K) to
--tol. K_max measured is the root of b(K); its interval is the last bracket (a decaying
and a growing record), widened by the stated uncertainty of b.

Predicted beside it: the exact linear limit (hapsim stability), and, for a device with
Coulomb friction fc, the limit at the record's amplitude a by the describing function of
friction (b_eq = 4 fc / (pi a w) added to b0): the device follows one or the other, and
the report says which."""

_EPILOG = """\
examples:
  hapsim zwidth --lockstep --B 0 1.5 4 --json
  hapsim zwidth --B 0 2 4 8 --plot zwidth.png          (embedded mock, real time)
  hapsim zwidth --scene configs/wall.yaml --port /dev/ttyACM0 --baud 2000000
  hapsim zwidth --firmware --B 1.5                      (the emulated Hapkit board)
  hapsim zwidth --firmware --lockstep --B 0 1.5 4       (the board, host-paced)

exit codes: 0 every point measured, 1 some point not measured (no bracket), 2 bad input"""

#: The device measured when no --scene is given: configs/wall.yaml's.
DEFAULT_DEVICE = """rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: 0.0}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000.0, damping: 1.5}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10.0}
excitation: {x0: 0.005}
"""


def register(sub) -> None:
    """Add the ``zwidth`` parser to ``sub``.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-parsers.
    """
    p = sub.add_parser("zwidth", help="the stiffness limit K_max(B) measured on the device",
                       description=_DESCRIPTION, epilog=_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", metavar="SCENE", default=None,
                   help="scene whose device, rate and safety limits are measured (default: "
                        "configs/wall.yaml's device: 0.1 kg, b0 0.5 N s/m, d = 1, zoh, 1 kHz; "
                        "with --firmware configs/hapkit.yaml, the device the board models); "
                        "a 2-D or 3-D scene with --lockstep: an isotropic wall's Z-width")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--port", default=None, help="serial port of a device (or hapsim mock)")
    where.add_argument("--firmware", action="store_true",
                       help="the Hapkit 3 reference firmware on the emulated board (simavr), "
                            "started here")
    p.add_argument("--baud", type=Number(int, low=1), default=115200, help="baud rate of --port")
    p.add_argument("--lockstep", action="store_true",
                   help="the embedded mock in lockstep, in process (deterministic); with "
                        "--firmware, the emulated board's clock paced by the host")
    p.add_argument("--B", type=Number(unit="N s/m"),
                   nargs="+", default=None, metavar="B",
                   help="virtual dampings [N s/m] (default 0 1.5 4 on a device of 0.1 kg "
                        "at 1 kHz or heavier and faster; on a lighter or slower one the "
                        "same B T/m: scaled by mass x rate / 100 kg Hz)")
    p.add_argument("--x0", type=Number(unit="m"), default=None,
                   help="release position [m] (default the scene's excitation x0, or 5 mm)")
    p.add_argument("--duration", type=Number(float, low=0, high=600, open_low=True, unit="s"),
                   default=0.3, help="record length per trial [s] (default 0.3; at most 600: "
                                     "a trial per K, a dozen K per B)")
    p.add_argument("--tol", type=Number(float, low=0, high=0.5, open_low=True, open_high=True),
                   default=2e-3,
                   help="relative width of the final bracket (default 0.002)")
    p.add_argument("--start", type=Number(float, low=0, high=1, open_low=True, open_high=True),
                   default=0.7,
                   help="first K as a fraction of the predicted limit (default 0.7; K is "
                        "raised by 15 %% per record from there)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument("--plot", metavar="FILE", default=None,
                   help="chart: predicted boundary and measured points with their intervals")
    p.set_defaults(func=run)


def _base(args):
    from hapsim.scene import parse_scene
    from hapsim.commands.dimension import load_one_d_scene
    if args.scene is None and args.firmware:      # the board models this device
        from hapsim.emulated import hapkit_board as board
        args.scene = board.shipped_scene("hapkit.yaml")
    if args.scene is None:
        return parse_scene(DEFAULT_DEVICE, "<default device>")
    sc = load_one_d_scene(args.scene, "zwidth", "--scene")
    if sc.port is None or sc.device is None:
        raise ConfigError("zwidth needs a scene with a port and a device section",
                          file=sc.path, key="device")
    return sc


def _start_firmware(base, realtime: bool = True):
    """Start the emulated board behind a pty (``hapsim mock --firmware``); (proc, port).
    ``realtime`` False: the board's clock advances as the host answers (lockstep)."""
    import subprocess
    from hapsim.emulated import hapkit_board as board
    why = board.missing_tools()
    if why:
        raise ConfigError(f"the emulated board cannot be built here: {why}", key="--firmware")
    board.build()
    cmd = board.board_command(base.device, base.excitation, realtime=realtime)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for line in proc.stdout:
        if line.startswith("PORT "):
            return proc, line.split()[1]
    proc.kill()
    raise ConfigError("the emulated board printed no PORT line", key="--firmware")


def run(args) -> int:
    """Run ``hapsim zwidth``.

    Parameters
    ----------
    args : argparse.Namespace

    Returns
    -------
    int
        0 every point measured, 1 some point without a bracket, or the device lost
        after the first point (the points measured reported, with ``stop`` "device lost:
        ..." and ``error``, then the error on stderr).

    Raises
    ------
    ConfigError
        Bad option or scene (exit 2).
    DeviceError
        The device lost before the first point was measured (exit 1).
    """
    from hapsim.errors import DeviceError, error_record
    from hapsim.outputs import say_error_after
    from hapsim.analysis.stability import stability_limit
    from hapsim.analysis.zwidth import (ZPoint, default_dampings, device_loop, locate_onset,
                                        predicted_coulomb, release)
    from hapsim.progress import Progress

    if args.lockstep and args.port:
        raise ConfigError("--lockstep is the embedded mock's or the emulated board's; drop "
                          "it with --port", key="--lockstep")
    if args.scene is not None:
        from hapsim.scene import scene_dimension
        if scene_dimension(args.scene) > 1:
            return _run_space(args)
    if args.plot:
        from hapsim.plots import check_figure_path
        check_figure_path(args.plot, "--plot")
    base = _base(args)
    x0 = args.x0 if args.x0 is not None else (abs(base.excitation.x0) or 0.005)
    if not (math.isfinite(x0) and x0 > 0):
        raise ConfigError(f"must be > 0 [m], got {x0!r}", key="--x0")
    flim = float(base.device.force_limit or math.inf)
    from hapsim.drivers import DEFAULT
    protocol = getattr(base.device, "protocol", None) or DEFAULT
    if args.port and protocol != DEFAULT:
        # zwidth's records go over hapsim's framed protocol: a board that speaks its own
        # would take those bytes for something else
        raise ConfigError(f"the scene's device speaks the {protocol} protocol; zwidth "
                          f"measures over hapsim's framed protocol only (a board's own "
                          f"protocol, its 0.3 s records at the board's rate, is not built "
                          f"yet): without --port it measures hapsim's mock of the scene's "
                          f"device", file=getattr(base, "path", None), key="--port")
    if not (args.lockstep or args.port or args.firmware):
        # hapsim's mock on a pty (the scene's model of its device, whatever protocol the
        # scene names): its delay line is whole periods, said before anything starts
        from hapsim.emulated.mock import require_whole_delay
        require_whole_delay(base.device.delay, file=getattr(base, "path", None),
                            command="zwidth")
    if args.B is None:
        args.B = default_dampings(base.device.mass, base.rate_hz)
    loop = device_loop(base.device, base.rate_hz)
    proc = None
    if args.firmware:
        # the board places the handle at its own x0 at every CONFIG: one release for all
        # the walls, small enough for the stiffest one the search may reach (130 % of the
        # largest predicted limit) to stay clear of the force limit
        kmax = max(stability_limit(loop, B) for B in args.B)
        if math.isfinite(kmax) and kmax > 0:
            x0 = release(x0, flim, 1.3 * kmax)
        base = dataclasses.replace(base, excitation=dataclasses.replace(base.excitation,
                                                                        x0=x0))
        proc, port = _start_firmware(base, realtime=not args.lockstep)
        opts = dict(port=port, lockstep=bool(args.lockstep))
        where = ("the emulated Hapkit board (simavr, " + ("lockstep" if args.lockstep
                                                          else "real time") + ")")
    elif args.port:
        opts = dict(port=args.port, baud=args.baud)
        where = f"the device on {args.port}"
    elif args.lockstep:
        opts = dict(transport="inprocess", lockstep=True)
        where = "the embedded mock (lockstep, in process)"
    else:
        opts = {}
        where = "the embedded mock (real time, on a pty)"
    if protocol != DEFAULT and not args.firmware:
        where += (f", hapsim's model of the scene's device (the {protocol} board's own "
                  f"protocol is not spoken)")
    measure = run_measure(base, x0, duration=args.duration, **opts)
    fc = float(base.device.coulomb or 0.0)
    points = []
    lost = None             # the DeviceError that ended the sweep after its first point
    try:
        with Progress(len(args.B), "measuring K_max(B)", "B values") as bar:
            for i, B in enumerate(args.B):
                Kp = stability_limit(loop, B)
                Kc = (predicted_coulomb(base.device, base.rate_hz, B,
                                        lambda K: release(x0, flim, K)) if fc > 0 else None)
                try:
                    Km, iv, trials, note = locate_onset(measure, B, Kc or Kp, tol=args.tol,
                                                        start=args.start)
                except DeviceError as exc:
                    if not points:
                        raise               # nothing measured: the error alone
                    lost = exc              # the points measured are reported, as a
                    break                   # run's records up to a loss are
                points.append(ZPoint(B=float(B), K_max_predicted=Kp,
                                     K_max_predicted_coulomb=Kc, K_max_measured=Km,
                                     K_max_measured_interval=iv, trials=trials, note=note))
                bar.update(i + 1)
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(timeout=10)
    rep = report(points, base, where, x0, fc)
    if lost is not None:
        rep.update(stop=f"device lost: {str(lost).splitlines()[0]} (after {len(points)} of "
                        f"{len(args.B)} B values)", error=error_record(lost))
    if args.plot:
        from hapsim.plots import save_figure
        from hapsim.plots.zwidth import plot_zwidth
        save_figure(plot_zwidth(rep, loop, base.device, base.rate_hz, x0), args.plot)
    if args.json:
        print(json.dumps(rep))
    else:
        print(format_report(rep))
        if lost is not None:
            print(f"stopped: {rep['stop']}")
        if args.plot:
            print(f"figure: {args.plot}")
    if lost is not None:                # the report first, then why the sweep ended
        say_error_after("zwidth", rep["error"])
        return 1
    return 0 if all(p.K_max_measured is not None for p in points) else 1


def _run_space(args) -> int:
    """``hapsim zwidth --scene SCENE --lockstep`` of a 2-D or 3-D scene: ``K_max(B)`` of an
    isotropic wall, measured from lockstep records
    (:func:`hapsim.pipeline.zwidth_lockstep.lockstep_measure`) beside the exact limit
    (:func:`hapsim.analysis.direction_limits.isotropic_limit`).

    Returns
    -------
    int
        0 every point measured, 1 some point without a bracket.

    Raises
    ------
    ConfigError
        ``--port``, ``--firmware`` or ``--plot`` (not built for 2-D or 3-D), no
        ``--lockstep``, a bad scene.
    """
    import numpy as np

    from hapsim.analysis.direction_limits import isotropic_limit
    from hapsim.analysis.ths import MatrixLoop
    from hapsim.analysis.zwidth import ZPoint, locate_onset
    from hapsim.pipeline.zwidth_lockstep import isotropic_wall, lockstep_measure
    from hapsim.progress import Progress
    for flag, given in (("--port", args.port), ("--firmware", args.firmware),
                        ("--plot", args.plot)):
        if given:
            raise ConfigError("the Z-width of a 2-D or 3-D device over a port, on the "
                              "emulated board or charted is not built yet: --lockstep "
                              "measures it on the scene's own device model", key=flag)
    if not args.lockstep:
        raise ConfigError("the Z-width of a 2-D or 3-D device in real time is not built "
                          "yet: give --lockstep (the scene's own device model, in "
                          "process)", key="--lockstep")
    base = isotropic_wall(args.scene, 1.0, 0.0)
    dev = base.device
    if args.B is None:
        from hapsim.analysis.zwidth import default_dampings
        args.B = default_dampings(dev.mass, base.rate_hz)
    x0 = args.x0 if args.x0 is not None else 0.001
    if not (math.isfinite(x0) and x0 > 0):
        raise ConfigError(f"must be > 0 [m], got {x0!r}", key="--x0")
    loop = MatrixLoop(mass=dev.mass, friction=dev.friction, rate_hz=base.rate_hz,
                      delay=dev.delay)
    measure = lockstep_measure(args.scene, x0, args.duration)
    points = []
    with Progress(len(args.B), "measuring K_max(B) of an isotropic wall", "B values") as bar:
        for i, B in enumerate(args.B):
            Kp = isotropic_limit(loop, B)
            Km, iv, trials, note = locate_onset(measure, B, Kp, tol=args.tol,
                                                start=args.start)
            points.append(ZPoint(B=float(B), K_max_predicted=Kp, K_max_predicted_coulomb=None,
                                 K_max_measured=Km, K_max_measured_interval=iv,
                                 trials=trials, note=note))
            bar.update(i + 1)
    pts, follows, worst = _points(points)
    where = (f"{args.scene}'s {dev.kind} (lockstep, in process"
             + (", at its operating point" if dev.kind != "cartesian" else "") + ")")
    rep = {"where": where, "x0": x0, "wall": "isotropic", "dof": base.dimension,
           "device": {"kind": dev.kind, "mass": np.asarray(dev.mass).tolist(),
                      "friction": np.asarray(dev.friction).tolist(), "coulomb": 0.0,
                      "delay": dev.delay, "hold": dev.hold, "rate_hz": base.rate_hz},
           "points": pts, "follows": follows, "worst_rel_err": worst}
    if args.json:
        print(json.dumps(rep))
    else:
        print(f"Z-width of {where} for an isotropic wall (a spring-damper of rest length 0 "
              f"to a ground at the handle's rest: (K, B) on every axis), d = {dev.delay}, "
              f"{base.rate_hz:g} Hz; records released {x0 * 1e3:g} mm from rest")
        print("\n".join(_table(rep)))
    return 0 if all(p.K_max_measured is not None for p in points) else 1


def report(points, base, where: str, x0: float, fc: float) -> dict:
    """The JSON report: device, points, and which prediction the measurements follow.

    Parameters
    ----------
    points : list of hapsim.analysis.zwidth.ZPoint
    base : hapsim.scene.Scene
    where : str
    x0 : float
    fc : float

    Returns
    -------
    dict
        ``device`` (mass, friction, coulomb, delay, hold, rate_hz, force_limit), ``where``,
        ``x0``, ``points`` (:meth:`ZPoint.to_dict` plus ``rel_err`` against the linear and,
        with Coulomb friction, the describing-function prediction), ``follows``
        (``"linear"``, ``"coulomb"`` or None), ``worst_rel_err`` (against the one followed).
    """
    pts, follows, worst = _points(points)
    dev = base.device
    return {"where": where, "x0": x0,
            "device": {"mass": dev.mass, "friction": dev.friction, "coulomb": fc,
                       "delay": dev.delay, "hold": dev.hold, "rate_hz": base.rate_hz,
                       "force_limit": dev.force_limit,
                       "protocol": getattr(dev, "protocol", None)},
            "points": pts, "follows": follows, "worst_rel_err": worst}


def _points(points) -> tuple:
    """The points as :func:`report` gives them (``rel_err`` against the linear and, with
    Coulomb friction, the describing-function prediction), which prediction they follow
    and the worst relative error against it."""
    pts = []
    for p in points:
        d = p.to_dict()
        km = d["K_max_measured"]
        d["rel_err"] = None if km is None else (km - p.K_max_predicted) / p.K_max_predicted
        d["rel_err_coulomb"] = (None if km is None or p.K_max_predicted_coulomb is None
                                else (km - p.K_max_predicted_coulomb)
                                / p.K_max_predicted_coulomb)
        pts.append(d)
    lin = [abs(d["rel_err"]) for d in pts if d["rel_err"] is not None]
    cou = [abs(d["rel_err_coulomb"]) for d in pts if d["rel_err_coulomb"] is not None]
    follows, worst = None, None
    if lin:
        follows, worst = "linear", max(lin)
        if cou and max(cou) < max(lin):
            follows, worst = "coulomb", max(cou)
    return pts, follows, worst


def format_report(rep: dict) -> str:
    """The human table of :func:`report`.

    Parameters
    ----------
    rep : dict

    Returns
    -------
    str
    """
    d = rep["device"]
    u = _units(d)
    lines = [f"Z-width of {rep['where']}: m = {d['mass']:g} {u['mass']}, b0 = "
             f"{d['friction']:g} {u['friction']}"
             + (f", Coulomb {d['coulomb']:g} {u['force']}" if d["coulomb"] else "")
             + f", d = {d['delay']}, {d['hold']}, {d['rate_hz']:g} Hz; records released "
             f"from x0 = {rep['x0'] * 1e3:g} m{u['position']}"]
    return "\n".join(lines + _table(rep))


def _units(d: dict) -> dict:
    """The units of a report's device: its protocol's (a rotary joint's, the Haply's:
    :func:`hapsim.drivers.axis_units`), SI without one."""
    from hapsim.drivers import axis_units
    return axis_units(d.get("protocol"))


def _table(rep: dict) -> list:
    """The rows of :func:`format_report` after its first line."""
    d = rep["device"]
    lines = []
    head = (f"   B [{_units(d)['friction']}]   K_max predicted"
            + ("   with Coulomb" if d["coulomb"] else "")
            + "   measured   interval                  rel. err   records")
    lines.append(head)
    for p in rep["points"]:
        iv = p["K_max_measured_interval"]
        km = p["K_max_measured"]
        err = p["rel_err_coulomb"] if rep["follows"] == "coulomb" else p["rel_err"]
        lines.append(
            f"  {p['B']:9.4g}   {_g(p['K_max_predicted']):>15}"
            + (f"   {_g(p['K_max_predicted_coulomb']):>12}" if d["coulomb"] else "")
            + f"   {_g(km):>8}   "
            + (f"[{_g(iv[0])}, {_g(iv[1])}]" if iv else "-").ljust(24)
            + f"  {'-' if err is None else format(err, '+.2e'):>9}   {len(p['trials'])}"
            + (f"  ({p['note']})" if p["note"] else ""))
    if rep["follows"]:
        lines.append(f"the device follows the {rep['follows']} prediction"
                     + (" (describing function of Coulomb friction at the record's amplitude)"
                        if rep["follows"] == "coulomb" else "")
                     + f": worst relative error {rep['worst_rel_err']:.2e}")
    return lines


def _g(v) -> str:
    return "-" if v is None else format(v, ".6g")


def run_measure(base, x0: float, *, duration: float, **run_options):
    """A measuring function for :func:`hapsim.analysis.zwidth.locate_onset`: one ``hapsim
    run`` per trial (it runs the daemon, so it stands with the command, not the analysis).

    Parameters
    ----------
    base : hapsim.scene.Scene
        The device (and rate, safety limits).
    x0 : float
        Release position [m] (reduced by :func:`hapsim.analysis.zwidth.release` for a stiff wall).
    duration : float
        Record length [s].
    **run_options
        Passed to :func:`hapsim.pipeline.runner.run_scene` (``port``, ``lockstep``,
        ``transport``, ...); ``allow_unstable`` is set (the safety limits stay armed).

    Returns
    -------
    callable
        ``measure(K, B) -> Trial``.
    """
    from hapsim.analysis.network import device_body
    from hapsim.analysis.zwidth import (MIN_GROWTH_TICKS, RECORD_ATTEMPTS, Trial,
                                        record_side, release, wall_scene)
    from hapsim.pipeline.runner import run_scene

    m = device_body(base.device)[0]
    T = base.period

    flim = float(getattr(base.device, "force_limit", math.inf) or math.inf)

    def once(K: float, B: float):
        rep = run_scene(wall_scene(base, K, B, release(x0, flim, K)), duration=duration,
                        allow_unstable=True, handle_signals=False, **run_options)
        meas = rep.get("measured") or {}
        lp = rep.get("loop") or {}
        mock = lp.get("mock") or {}
        # ticks whose force was not the loop's (late, missed, stale on either side): a
        # disturbance of the record, not the THS
        disturbed = sum(int(d.get(k) or 0) for d in (lp, mock)
                        for k in ("late", "missed", "stale"))
        stop = str(lp.get("stop_reason") or "")
        safety = bool(lp.get("safety_stop")) or stop.startswith("safety")
        b = meas.get("b")
        if b is None or not math.isfinite(b):
            # a safety stop after a while is growth from x0 (well inside the limits) to a
            # limit; one within the first periods, or in a disturbed record, says nothing
            # of the loop (a device out of place, a clamped start, a host late by tens of
            # ms holding a stale force): undecided
            grew = (safety and int(lp.get("ticks") or 0) >= MIN_GROWTH_TICKS
                    and not disturbed)
            why = (f"{stop} after {lp.get('ticks')} ticks" if safety
                   else stop or str(meas.get("error", "not identified")))
            if disturbed:
                why += f" ({disturbed} late/missed/stale ticks)"
            return Trial(K, B, None, None, 0.0, None, True if grew else None,
                         note=why), disturbed
        unc = float(meas.get("b_unc") or 0.0)
        late_fit = int(meas.get("late_accounted") or 0) + int(meas.get("late_in_segment") or 0)
        lb = meas.get("b_bound_late")
        side, margin = record_side(float(b), unc, late_fit,
                                   None if lb is None else float(lb))
        if side is None:
            # late ticks inside the identified stretch, b within the worst case of their
            # accounted forces' error (plus the fit's interval) of 0: too close to tell
            # the side: repeated, then undecided
            return Trial(K, B, float(b), float(meas.get("k", math.nan)), unc,
                         math.exp(-b * T / (2.0 * m)), None,
                         note=(f"b = {b:.3g} +- {unc:.2g} N s/m from a stretch with "
                               f"{late_fit} late ticks: within {margin:.2g} N s/m of 0 "
                               "(their accounted forces' worst case through the fit, "
                               "plus the fit's interval), side not decided")), late_fit
        # the identified pole decides, not a safety stop: a record whose identified stretch
        # decays (b > 0) and that then stops on a limit was disturbed after it (in real
        # time, a host late by tens of ms holds a stale force: the handle flies into the
        # force or position limit), it did not grow; calling it growing put the upper end
        # of the bracket below the limit (2 of 4 points in a real-time run on the mock)
        note = stop if not (safety and b > 0) else (
            f"{stop} after a decaying stretch (a disturbance: the identified b decides)")
        return Trial(K, B, float(b), float(meas.get("k", math.nan)), unc,
                     math.exp(-b * T / (2.0 * m)), side, note=note), disturbed

    def measure(K: float, B: float) -> Trial:
        # a disturbed record that could not be decided is repeated: in real time the
        # host's stalls are rare events, independent from record to record, so a record
        # with a clean stretch comes within a few (RECORD_ATTEMPTS)
        for attempt in range(1, RECORD_ATTEMPTS + 1):
            t, disturbed = once(K, B)
            if t.growing is not None or not disturbed:
                break
        if attempt > 1:
            t = dataclasses.replace(t, note=f"{t.note} (record {attempt} of "
                                            f"{RECORD_ATTEMPTS}: the earlier ones disturbed "
                                            "and undecided)")
        return t
    return measure


if __name__ == "__main__":  # pragma: no cover
    sys.exit("run it as: hapsim zwidth")
