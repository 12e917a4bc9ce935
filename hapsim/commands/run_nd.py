"""``hapsim run --lockstep`` on a 2-D or 3-D scene: the loop closed in-process, the felt
matrices measured and compared with the prediction, and the linearisation bound."""

from __future__ import annotations

import json
import math
import sys

import numpy as np

from hapsim.errors import ConfigError

#: run's options an n-D scene does not take yet (no n-axis protocol, mock behind a port,
#: driver or live input): each refused by name, with exit 2.
_REFUSED = (("port", "--port"), ("driver", "--driver"), ("device", "--device"),
            ("osc", "--osc"), ("sound", "--sound"), ("telemetry", "--telemetry"),
            ("faults", "--faults"), ("auto", "--auto"), ("rate", "--rate"),
            ("host_clocked", "--host-clocked"), ("duration", "--duration"))

#: Default excitation amplitude [m]: small enough that the scenes' Euclidean links depart
#: from their linearisation by ~1e-7 (c_link ~ 30 /m), large enough against the round-off
#: of positions ~0.1 m (1e-17 m, 1e-9 relative).
DEFAULT_AMPLITUDE = 1e-8


def run_nd(args) -> int:
    """Measure an n-D scene's felt matrices in lockstep (``dimension: 2`` or ``3``).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``lockstep`` (required), ``amplitude`` [m] (None: 1e-8), ``json``, and
        run's other options (refused when set: the n-D run is in-process only).

    Returns
    -------
    int
        0 when the loop is stable (the measurement then reported, whatever it finds),
        1 when the check finds it unstable and ``--allow-unstable`` is not given.

    Raises
    ------
    ConfigError
        Without ``--lockstep``; an option the n-D run does not take; a bad amplitude or
        scene (file, line, key).

    Notes
    -----
    :func:`hapsim.lockstep_nd.measure_felt_lockstep`: 2n free responses of the loop
    (engine, exact ZOH device of the Cartesian mass at rest, delay line) from the handle
    displaced by ``a`` along each axis and moving along each, minus the response from
    rest; the felt matrices by vector linear prediction and the inverse quadratic
    eigenvalue problem (:mod:`hapsim.analysis.identify_nd`), against
    :func:`hapsim.analysis.scene_nd_check.check_scene_nd`; the linearisation bound of
    :mod:`hapsim.analysis.linearisation_nd` at ``a``.
    """
    from hapsim.errors import UnstableConfigError
    from hapsim.lockstep_nd import measure_felt_lockstep
    from hapsim.progress import Progress
    from hapsim.scene_nd import load_scene_nd
    if not args.lockstep:
        raise ConfigError("a 2-D or 3-D scene runs in lockstep only, in-process (no n-axis "
                          "protocol or mock behind a port yet): add --lockstep",
                          key="--lockstep")
    for attr, opt in _REFUSED:
        if getattr(args, attr, None) not in (None, False):
            raise ConfigError(f"a 2-D or 3-D scene runs in lockstep, in-process: {opt} "
                              "takes 1-D scenes", key=opt)
    a = DEFAULT_AMPLITUDE if getattr(args, "amplitude", None) is None else args.amplitude
    if not (math.isfinite(a) and a > 0):
        raise ConfigError(f"must be a positive number [m], got {a}", key="--amplitude")
    scene = load_scene_nd(args.scene)
    if scene.port is None:
        raise ConfigError("a run needs a mass of kind 'port' and a device section",
                          file=scene.path, key="masses")
    from hapsim.analysis.scene_nd_check import check_scene_nd
    pred = check_scene_nd(scene)
    if not pred.stable and not args.allow_unstable:
        raise UnstableConfigError(
            f"{scene.path}: the closed loop is unstable (spectral radius "
            f"{pred.render.spectral_radius:.9f}); hapsim check for the felt matrices, "
            "--allow-unstable to run it anyway")
    n = scene.dimension
    with Progress(2 * n, "run (lockstep)", unit="records") as bar:
        res = measure_felt_lockstep(scene, a, progress=bar.update)
    fit, chk, dev, bound = res["measured"], res["predicted"], res["deviation"], res["bound"]
    if args.json:
        def mat(x):
            return None if x is None else np.asarray(x, float).tolist()
        out = {"scene": scene.path, "dof": n, "lockstep": True, "stable": bool(chk.stable),
               "predicted": {"felt_stiffness": mat(chk.render.felt_stiffness),
                             "felt_damping": mat(chk.render.felt_damping),
                             "rendered_poles": [[float(z.real), float(z.imag)]
                                                for z in chk.render.rendered_poles]},
               "measured": {"felt_stiffness": mat(fit["felt_stiffness"]),
                            "felt_damping": mat(fit["felt_damping"]),
                            "rendered_poles": [[float(z.real), float(z.imag)]
                                               for z in fit["rendered_poles"]],
                            "residual": fit["residual"], "rank": fit["rank"]},
               "deviation": dev, "linearisation_bound": bound.to_dict(),
               "records": res["records"], "samples": res["samples"],
               "order": res["order"]}
        print(json.dumps(out))
        return 0
    o = sys.stdout
    print(f"{scene.path}: {n}-D scene in lockstep, in-process (engine, exact ZOH device "
          f"of the Cartesian mass at rest, delay {scene.device.delay})", file=o)
    print(f"  excitation: {res['records']} free responses of {res['samples']} samples, "
          f"amplitude a = {a:g} m (minus the response from rest)", file=o)
    if not chk.stable:
        grow = chk.render.spectral_radius ** res["samples"]
        print(f"  the loop is UNSTABLE (--allow-unstable): its free responses grow by up to "
              f"{grow:.3g} times over a record, so the amplitude and the bound below hold "
              "at its start only", file=o)

    def mat(name, m, unit):
        if m is None:
            print(f"  {name}: none (fewer than {n} rendered pairs)", file=o)
            return
        print(f"  {name} [{unit}]", file=o)
        for row in m:
            print("    " + "  ".join(f"{v:+14.8g}" for v in row), file=o)
    mat("predicted felt stiffness k", chk.render.felt_stiffness, "N/m")
    mat("measured felt stiffness k", fit["felt_stiffness"], "N/m")
    mat("predicted felt damping b", chk.render.felt_damping, "N s/m")
    mat("measured felt damping b", fit["felt_damping"], "N s/m")
    if dev is not None:
        print(f"  measured - predicted (largest entry over the largest predicted): "
              f"k {dev['felt_stiffness']:.2e}, b {dev['felt_damping']:.2e}", file=o)
    bd = bound.to_dict()
    print(f"  linearisation bound at a = {a:g} m (first order in a; "
          "hapsim.analysis.linearisation_nd):", file=o)
    print(f"    device kinematics c_kin = {bound.kinematic:.4g} /m (the Cartesian mass "
          "and the velocity-product terms over a; not in the lockstep device, which "
          "holds the mass at rest)", file=o)
    print(f"    Euclidean links c_link = {bound.link:.4g} /m"
          + (f" (link {bound.link_name!r})" if bound.link_name else " (none: linear)"),
          file=o)
    if bd["felt_stiffness"] is None:
        print(f"    a reaches the depth of {bound.depth_name!r} ({bound.depth:.3g} m): "
              "the contact opens, no linear estimate holds", file=o)
    else:
        print(f"    felt stiffness within {bd['felt_stiffness']:.2e}, felt damping within "
              f"{bd['felt_damping']:.2e} (relative) while a < {bound.depth:.3g} m"
              + (f" (depth of {bound.depth_name!r})" if bound.depth_name else ""), file=o)
    return 0
