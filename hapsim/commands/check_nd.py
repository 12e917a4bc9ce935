"""``hapsim check`` on a 2-D or 3-D scene: the MIMO closed loop, the felt matrices."""

from __future__ import annotations

import json
import sys


def run_nd(args) -> int:
    """Check an n-D scene (``dimension: 2`` or ``3``; :mod:`hapsim.scene_nd`).

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
        (:func:`hapsim.analysis.modes_nd.scene_modes_nd`), 1 when the scheme diverges.

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
    scene = api.load_scene_nd(args.scene)
    if scene.port is None:
        return _run_modes(args, scene, plot)
    from hapsim.progress import Progress
    with Progress(scene.dimension, "stiffness limits (longer with a longer delay)",
                  unit="directions") as bar:
        rep = api.check_nd(scene, progress=bar.update)
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

    def mat(name, a, unit):
        if a is None:
            return
        print(f"  {name} [{unit}]", file=o)
        for row in a:
            print("    " + "  ".join(f"{v:+14.6g}" for v in row), file=o)
    mat("felt stiffness k", r.felt_stiffness, "N/m")
    mat("felt damping b", r.felt_damping, "N s/m")
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
    return 0 if chk.stable else 1


def _run_modes(args, scene, plot) -> int:
    """``check`` on a scene without a port: its modes (:func:`run_nd`)."""
    from hapsim import api
    rep = api.modes_nd(scene)
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
