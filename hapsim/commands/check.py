"""``hapsim check``: scene-level closed-loop check (stability and what the hand feels), in any
dimension (a 2-D or 3-D scene: its felt matrices, or its modes without a port)."""

from __future__ import annotations

import argparse
import json
import math
import sys

from hapsim.errors import ConfigError, fixed, plural
from hapsim.option_values import Number

_DESCRIPTION = """\
Check a whole scene felt through its device, before touching the device.

The scene and the device section are turned into ONE linear closed loop, sampled at the
scene rate: the hand + handle mass m with its real friction b0 (integrated exactly over each
period with the force held, or the paper's ideal sampled image with hold: ideal), the
computation delay of d samples, every virtual mass (advanced by the scene's integrator:
centred, symplectic_euler or exact, as the engine runs it), and every link. Contacts are taken as
engaged (acting as spring-dampers, the usual stability-critical case); to check a scene
with a contact released, check a copy without that contact. Its eigenvalues z are the
closed-loop poles. The loop is stable when every |z| < 1 (the spectral radius); poles on
the unit circle belong to lossless virtual parts (marginal) and are accepted.

What the hand feels is read from the least damped pole pair z: with s = ln(z)/T and m the
device mass, the felt stiffness is k = m |s|^2 and the felt damping b = -2 m Re(s) (real +
virtual damping, as deformed by sampling and delay; Florens, Voda & Urma). The other
poles are the parasitic modes.

A scene whose device speaks a board's own protocol (device.protocol) is checked as that
board runs it: at the rate of its own ticks (the Hapkit sketch's whole 0.992 ms ticks), and
with the delay its render after the read adds (the Hapkit sketch: 0.15-0.55 ms, analysed
at the middle, as hapsim run states its prediction); a line says so, with how far the felt
(k, b) move over the latency's bounds (--json: board).

Links given as a felt target {k, b} (a spring_damper between the port and a ground) are
first calibrated: the virtual (K, B) that puts the closed-loop pair on the target is
computed for the device alone, then the whole scene is checked with it.

A 2-D or 3-D scene (dimension: 2 or 3; docs/dimensions.md) is checked the same way as a
MIMO loop: the device's Cartesian mass and friction MATRICES (a pantograph or a delta at
its operating point: J^-T M_q J^-1), the hold, the delay, every virtual mass and link
linearised at rest. Stability comes from the spectral radius of the coupled loop, never
axis by axis. It prints the felt stiffness k [N/m] and damping b [N s/m] as n x n
matrices (the unique pair with the n rendered poles and their mode shapes at the
handle), the principal directions with the (m, k, b) felt along each, and, when every
port link ends on a ground, the stiffness limit K_max along the principal axes of the
device's mass (--json: dof, felt_stiffness, felt_damping, principal_directions,
spectral_radius, stiffness_limits). A scene whose forces do not balance at the positions
it names (where a run starts) gets a line saying so, with the net force and how far the
balance lies (--json: not_at_rest, null at rest). --plot draws the scene over the
device's workspace with the felt stiffness ellipses. A scene without a port (a sounding membrane) gives its
modes instead."""

_EPILOG = """\
examples:
  hapsim check configs/wall.yaml
  hapsim check configs/string.yaml --modes 5
  hapsim check configs/wall.yaml --json | python -m json.tool
  hapsim check configs/pantograph_wall.yaml --plot wall.png     2-D: felt matrices, ellipses
  hapsim check configs/delta_sphere.yaml --json                 3-D
  hapsim check configs/membrane.yaml --modes 6                  no port: the modes

exit codes:
  0  the closed loop is stable
  1  the closed loop is unstable, or a target (k, b) this device cannot render
  2  bad scene file or option"""


def register(sub) -> None:
    """Add the ``check`` parser to ``sub`` (an argparse sub-parsers action).

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-command registry.
    """
    p = sub.add_parser(
        "check", help="closed-loop check of a whole scene: stable? what (k, b) is felt?",
        description=_DESCRIPTION, epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="YAML scene file")
    p.add_argument("--json", action="store_true",
                   help="print the result as one JSON object on stdout")
    p.add_argument("--modes", type=Number(int, low=0), default=8, metavar="N",
                   help="parasitic modes listed in the table (default 8; 0 for none)")
    p.add_argument("--plot", metavar="FIG",
                   help="2-D or 3-D scene: draw it over its device's workspace with the "
                        "felt stiffness ellipses (png, pdf, svg)")
    p.set_defaults(func=run)


def _fmt_mode(md) -> str:
    def g(v, spec):
        return "-" if not math.isfinite(v) else format(v, spec)
    row = (f"  {fixed(abs(md.z), '<14.10f')} {g(md.f0_hz, '<10.4g')} {g(md.damping_ratio, '<+11.4g')} "
           f"{g(md.k, '<12.6g')} {g(md.b, '<+12.6g')} {md.kind:<5}")
    if md.participation is not None:  # weight at the port (residue, relative)
        from hapsim.analysis.modes import OBSERVABLE_TOL
        row += f" {md.participation:<9.2g}"
        if not md.participation >= OBSERVABLE_TOL:
            row += " not felt (mode of the object)"
    return row.rstrip()


def _object_mode(k: float, static: float, scene) -> bool:
    """Whether the felt pole is a mode of the scene's virtual masses rather than the
    port's spring: there are virtual masses, and its ``k`` is more than twice, or less
    than half, the static stiffness at the port."""
    if not any(m.kind == "mass" for m in scene.masses) or not math.isfinite(k):
        return False
    return not (0.5 * static <= k <= 2.0 * static)


def print_board(bd: dict) -> None:
    """Print the lines on the timing of the board a scene's ``device.protocol`` names
    (:func:`hapsim.api.checking.board_loop`; ``check`` and ``stability --scene``).

    Parameters
    ----------
    bd : dict
        :attr:`hapsim.api.checking.CheckReport.board`.
    """
    name = bd["protocol"]
    if "rate_written_hz" in bd:
        print(f"board ({name}): runs at {bd['rate_hz']:.9g} Hz, the whole ticks the "
              f"file's {bd['rate_written_hz']:g} Hz stands for; the loop is analysed there")
    if "render_latency_s" in bd:
        lo, hi = (1e3 * v for v in bd["render_latency_s"])
        line = (f"board ({name}): renders {lo:g}-{hi:g} ms after its read, so the loop's "
                f"delay is d = {bd['delay_modelled']:.6g} periods at the middle (as hapsim "
                f"run predicts; it searches the latency in its measurement)")
        if "k_spread" in bd:
            line += (f"; over the bounds the felt k moves by up to {bd['k_spread']:.3g} N/m "
                     f"and b by {bd['b_spread']:.3g} N s/m")
        print(line)
    if "refused" in bd:
        print(f"board ({name}): hapsim run refuses this rate: {bd['refused']}")


def run(args: argparse.Namespace) -> int:
    """Run ``hapsim check``.

    Parameters
    ----------
    args : argparse.Namespace
        ``scene`` (path), ``json`` (bool), ``modes`` (int).

    Returns
    -------
    int
        0 stable, 1 unstable.

    Raises
    ------
    ConfigError
        Bad scene file or option (exit code 2, handled by :mod:`hapsim.cli`).
    UnrenderableTargetError
        A target that is not renderable (a negative verdict: exit code 1).
    """
    from hapsim.scene import scene_dimension, scene_has_ports
    if scene_has_ports(args.scene):            # several ports: the felt matrices across them
        return _run_ports(args)
    if scene_dimension(args.scene) > 1:        # a 2-D or 3-D scene: its felt matrices
        return _run_nd(args)
    if getattr(args, "plot", None) is not None:
        raise ConfigError("draws a 2-D or 3-D scene (dimension: 2 or 3); a 1-D scene's "
                          "charts are hapsim stability/family --plot", key="--plot")
    from hapsim.api import check
    from hapsim.scene import load_scene

    scene = load_scene(args.scene)
    from hapsim.analysis.network import check_size, state_count
    check_size(scene)                   # too large: refused before the cost is announced
    n_states = state_count(scene)
    if n_states > 500:  # say what it costs before it starts (O(n^3), ~20 s at 2000)
        print(f"hapsim check: {n_states} states: every eigenvalue of a dense "
              f"{n_states}-square matrix, about {20 * (n_states / 2000) ** 3:.0f} s",
              file=sys.stderr, flush=True)
    # an unrenderable target raises UnrenderableTargetError: a negative verdict, exit 1
    rep = check(scene)
    chk, scene, cals, static = rep.analysis, rep.calibrated_scene, rep.calibrations_made, rep.static_k
    ok = rep.stable             # (over the board's render latency too: its ``board``)
    verdict = rep.verdict

    if args.json:
        print(json.dumps({**rep.to_dict(), "scene": args.scene}))
        return 0 if ok else 1

    T = scene.period
    print(f"scene {args.scene}: {scene.rate_hz:g} Hz (T = {T * 1e3:g} ms), "
          f"{plural(sum(m.kind == 'mass' for m in scene.masses), 'virtual mass', 'virtual masses')}, "
          f"{plural(len(scene.links), 'link')} (contacts taken as engaged), integrator "
          f"{chk.integrator}")
    if scene.audio is not None:
        a = scene.audio
        print(f"multi-rate: masses at {a.rate_hz:g} Hz ({round(a.rate_hz / scene.rate_hz)} "
              f"sub-steps per device sample), port position {a.port_position}, port force "
              f"{a.port_force}; the matrix is their product over one device period")
    if chk.has_port:
        dv = scene.device
        print(f"device: m = {dv.mass:g} kg, b0 = {dv.friction:g} N s/m, delay d = {dv.delay}, "
              f"hold {dv.hold}")
        if getattr(dv, "hand", None) is not None:
            h = dv.hand
            print(f"hand (nominal member of the family; hapsim family for all of it): mass "
                  f"{h.mass}, damping {h.damping}, grip "
                  f"{'rigid' if h.rigid else h.grip_stiffness} / {h.grip_damping}"
                  + (f", stiffness to ground {h.stiffness}" if h.stiffness else ""))
        if getattr(dv, "correction", None) is not None:
            print(f"correction: {dv.correction}")
        if rep.board is not None:
            print_board(rep.board)
    else:
        print("no port: the virtual network alone is checked (no device in the loop)")
    for c in cals:
        print(f"target {c.link}: (k, b) = ({c.k:g} N/m, {c.b:g} N s/m) -> "
              f"K = {c.result.K:.6g} N/m, B = {c.result.B:.6g} N s/m; renderable")
    tag = f"{verdict.upper()} with the {chk.integrator} integrator"
    if chk.stable and not ok and rep.board.get("unstable_latency_s") is not None:
        bd = rep.board
        tag += (f": the board may render {bd['unstable_latency_s'] * 1e3:.3g} ms after its "
                f"read (within its bounds), where the spectral radius is "
                f"{bd['unstable_spectral_radius']:.9g}; the loop below, at the middle, is "
                f"stable")
    elif chk.stable and not ok:
        lr = rep.board["late_reading_unstable"]
        tag += (f": a host that wakes a little late takes the board's reply "
                f"{lr['periods']} period{'s' if lr['periods'] != 1 else ''} late, and at a "
                f"delay of {lr['delay']:.4g} periods the spectral radius is "
                f"{lr['spectral_radius']:.9g} (hapsim run refuses it); the loop below, at "
                f"the board's own timing, is stable")
    if ok and chk.marginal:
        tag += " (marginal: some poles sit on the unit circle and never decay)"
    print(f"verdict: {tag}")
    if rep.board and rep.board.get("missing_reply_warning"):
        print(f"warning: {rep.board['missing_reply_warning']}")
    print(f"spectral radius: {chk.spectral_radius:.12g}  ({len(chk.eigenvalues)} states)")
    rp = chk.rendered
    if rp is not None:
        print(f"felt at the port: k = {rp.k:.6g} N/m, b = {rp.b:.6g} N s/m "
              f"(f0 = {rp.f0_hz:.6g} Hz, damping ratio {rp.damping_ratio:.4g}; "
              f"m = {chk.reference_mass:g} kg)")
        if static is not None and _object_mode(rp.k, static, scene):
            print(f"  that is a mode of the scene ringing at {rp.f0_hz:.6g} Hz, felt at the "
                  f"port, not a spring: k = m (2 pi f0)^2")
    elif chk.has_port:
        print("felt at the port: no oscillating pole pair (nothing rings)")
    if static is not None and any(m.kind == "mass" for m in scene.masses):
        print(f"static at the port: k = {static:.6g} N/m (what a slow push feels: the "
              f"virtual masses at rest)")
    others = [md for md in chk.modes if md is not rp and md.z != 0]
    deadbeat = sum(1 for md in chk.modes if md.z == 0)
    if args.modes and others:
        label = "parasitic modes" if chk.has_port else "modes"
        print(f"{label} (least damped first; k, b with m = {chk.reference_mass:g} kg):")
        # (in the axis's units here: the rotary words, longer, would shift the columns)
        from hapsim.drivers import run_units
        u = run_units(scene)
        k_head, b_head = f"k [{u['stiffness']}]", f"b [{u['friction']}]"
        print(f"  {'|z|':<14} {'f0 [Hz]':<10} {'zeta':<11} {k_head:<12} "
              f"{b_head:<12} kind" + ("  at port" if chk.has_port else ""))
        for md in others[:args.modes]:
            print(_fmt_mode(md))
        if len(others) > args.modes:
            print(f"  ... and {len(others) - args.modes} more (--modes N, --json)")
    if deadbeat:
        print(f"  + {deadbeat} dead-beat mode(s) at z = 0 (delay line)")
    return 0 if ok else 1


def _run_nd(args) -> int:
    """Check an n-D scene (``dimension: 2`` or ``3``; :func:`hapsim.scene.load_scene_nd`).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene`` (path), ``json`` (bool), ``modes`` (int), ``plot`` (figure path or
        None: the scene over its device's workspace with the felt stiffness ellipses,
        :func:`hapsim.plots.workspace.plot_scene_nd`).

    Returns
    -------
    int
        0 stable, 1 unstable (the MIMO characteristic's spectral radius). A scene without
        a port (nothing to feel: a sounding object) is checked on its own: the
        eigenfrequencies and damping ratios of its modes
        (:func:`hapsim.analysis.modes.scene_modes_nd`), 1 when the scheme diverges.

    Raises
    ------
    ConfigError
        Bad scene file or option (exit 2).
    """
    from hapsim import api
    plot = getattr(args, "plot", None)
    if plot is not None:
        from hapsim.plots import check_figure_path
        check_figure_path(plot, "--plot")
    scene = api.load_scene(args.scene)
    if scene.port is None:
        return _run_modes(args, scene, plot)
    from hapsim.progress import Progress
    with Progress(scene.dimension, "stiffness limits (longer with a longer delay)",
                  unit="directions") as bar:
        rep = api.check(scene, progress=bar.update)
    chk = rep.analysis
    if plot is not None:
        rep.plot(plot)
    if args.json:
        print(json.dumps(rep.to_dict()))
        return 0 if chk.stable else 1
    o = sys.stdout
    r = chk.render
    n = chk.dof
    print(f"{scene.path}: {n}-D scene, {chk.states} states, device {scene.device.kind} "
          f"(delay {scene.device.delay}, hold {scene.device.hold})", file=o)
    print(f"  verdict: {'stable' if chk.stable else 'UNSTABLE'} (spectral radius "
          f"{r.spectral_radius:.9f}, MIMO characteristic)", file=o)

    _print_matrix("felt stiffness k", r.felt_stiffness, "N/m", o)
    _print_matrix("felt damping b", r.felt_damping, "N s/m", o)
    if r.directions is not None:
        print("  principal directions (least damped first):", file=o)
        for i in range(n):
            e = "(" + ", ".join(f"{v:+.4f}" for v in r.directions[:, i]) + ")"
            print(f"    {e}  m = {r.direction_mass[i]:.6g} kg  k = "
                  f"{r.direction_stiffness[i]:.6g} N/m  b = {r.direction_damping[i]:.6g} "
                  "N s/m", file=o)
    if chk.stiffness_limits is not None:
        print("  stiffness limit K_max along the device's principal mass axes (the port "
              "links as port-ground springs):", file=o)
        for i in range(n):
            e = "(" + ", ".join(f"{v:+.4f}" for v in chk.limit_directions[:, i]) + ")"
            print(f"    {e}  K_max = {chk.stiffness_limits[i]:.6g} N/m", file=o)
    if r.note:
        print(f"  {r.note}", file=o)
    if rep.not_at_rest is not None:
        print(f"  {rep.not_at_rest['note']}", file=o)
    return 0 if chk.stable else 1


def _print_matrix(name: str, a, unit: str, o) -> None:
    """Print matrix ``a`` under its name and unit, one row a line (nothing when None)."""
    if a is None:
        return
    print(f"  {name} [{unit}]", file=o)
    for row in a:
        print("    " + "  ".join(f"{v:+14.6g}" for v in row), file=o)


def _run_ports(args) -> int:
    """``check`` on a scene with several ports: the felt matrices across them and the
    coupled loop's verdict (:func:`hapsim.analysis.ports.check_ports`)."""
    if getattr(args, "plot", None) is not None:
        raise ConfigError("draws a 2-D or 3-D scene; a scene with several ports has no "
                          "chart yet", key="--plot")
    from hapsim.analysis.ports import check_ports
    from hapsim.scene import load_scene_ports
    scene = load_scene_ports(args.scene)
    chk = check_ports(scene)
    if args.json:
        devices = [{"port": n, "mass": d.mass, "friction": d.friction,
                    "delay": float(d.delay), "hold": d.hold, "protocol": d.protocol}
                   for n, d in scene.devices]
        print(json.dumps({**chk.to_dict(), "rate_hz": scene.rate_hz, "devices": devices,
                          "scene": args.scene}))
        return 0 if chk.stable else 1
    o = sys.stdout
    r = chk.render
    print(f"scene {args.scene}: {scene.rate_hz:g} Hz, {len(chk.ports)} ports, "
          f"{plural(len(scene.links), 'link')}, {chk.states} states", file=o)
    for n, d in scene.devices:
        print(f"  port {n}: device m = {d.mass:g} kg, b0 = {d.friction:g} N s/m, delay "
              f"d = {d.delay}, hold {d.hold}, protocol {d.protocol}", file=o)
    print(f"  verdict: {'stable' if chk.stable else 'UNSTABLE'} (spectral radius "
          f"{r.spectral_radius:.9f}, the coupled loop's MIMO characteristic)", file=o)
    print(f"  rows and columns: {', '.join(chk.ports)}", file=o)
    _print_matrix("port stiffness K", chk.port_stiffness, "N/m", o)
    _print_matrix("port damping B", chk.port_damping, "N s/m", o)
    _print_matrix("felt stiffness k", r.felt_stiffness, "N/m", o)
    _print_matrix("felt damping b", r.felt_damping, "N s/m", o)
    if r.directions is not None:
        print("  principal directions across the ports (least damped first):", file=o)
        for i in range(len(chk.ports)):
            e = "(" + ", ".join(f"{v:+.4f}" for v in r.directions[:, i]) + ")"
            print(f"    {e}  m = {r.direction_mass[i]:.6g} kg  k = "
                  f"{r.direction_stiffness[i]:.6g} N/m  b = {r.direction_damping[i]:.6g} "
                  "N s/m", file=o)
    if r.note:
        print(f"  {r.note}", file=o)
    return 0 if chk.stable else 1


def _run_modes(args, scene, plot) -> int:
    """``check`` on a 2-D or 3-D scene without a port: its modes (:func:`_run_nd`)."""
    from hapsim import api
    rep = api.check(scene)
    res = rep.analysis
    if plot is not None:
        rep.plot(plot)
    if args.json:
        print(json.dumps(rep.to_dict()))
        return 0 if res.stable else 1
    # one line per eigenfrequency (a mode repeated along several axes, or a degenerate
    # pair of a symmetric mesh, within 1e-9 relative)
    lines = []
    for md in res.modes:
        if lines and abs(md.frequency_hz - lines[-1][0].frequency_hz) <= \
                1e-9 * md.frequency_hz:
            lines[-1][1].append(md)
        else:
            lines.append((md, [md]))
    o = sys.stdout
    print(f"{scene.path}: {scene.dimension}-D scene without a port, {len(res.names)} "
          f"moving masses, {res.states} states (the centred scheme linearised at rest, "
          "grounds held)", file=o)
    print(f"  verdict: {'stable' if res.stable else 'UNSTABLE'} (spectral radius "
          f"{res.spectral_radius:.9f})", file=o)
    print(f"  {len(res.modes)} oscillating modes at {len(lines)} eigenfrequencies; the "
          f"lowest {min(args.modes, len(lines))}:", file=o)
    print(f"    {'f [Hz]':>12} {'damping ratio':>14}  modes (along)", file=o)
    for md, same in lines[:args.modes]:
        axes = " ".join(sorted({"xyz"[m.axis] for m in same}))
        print(f"    {md.frequency_hz:12.4f} {md.damping_ratio:14.6g}  {len(same)} ({axes})",
              file=o)
    return 0 if res.stable else 1
