"""Feasibility figures of issue 29 for the Novint Falcon: can the felt matrices of a delta
scene be measured through the emulated Falcon's packets, whose encoder count is 27-47 um
at the handle and whose motor command is an integer count of 1e-4 N m?

For each amplitude ``a``: the identification's ``2n + 1`` records taken by the driver's
loop over the emulated Falcon on its lockstep clock (named: deterministic), for the
scene's own device ("match") and for one with ``--heavier`` times the leg inertia,
fitted and stated by :func:`hapsim.emulated.falcon_felt.measure_felt_falcon`: the fit's
deviation, the linearisation bound and the wire's term (worst case of half a count per
reading and half a command count per torque, as the 2DIY's) and the verdict; beside them
:func:`hapsim.emulated.falcon_felt.quantiser_terms` about the exact records (the fit with
no rounding; the worst case; Widrow & Kollar's ``q^2 / 12`` per reading and per command,
for comparison) and, last, :func:`hapsim.emulated.falcon_felt.felt_feasibility` (the
statement ``hapsim run --driver falcon`` prints).

Run: ``python tools/falcon_felt_figures.py [SCENE] [--amplitudes 1e-4,3e-4] [--heavier 1.3]``
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace


def main(argv=None) -> int:
    """Print the figures (module notes); 0."""
    from hapsim.emulated.falcon_felt import (felt_feasibility, measure_felt_falcon,
                                             quantiser_terms)
    from hapsim.lockstep import identification_plan
    from hapsim.scene import load_scene_nd
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", default="configs/delta_sphere.yaml")
    p.add_argument("--amplitudes", default="1e-4,2e-4,3e-4")
    p.add_argument("--heavier", type=float, default=1.3,
                   help="the hidden leg inertia's factor of the differing device")
    a = p.parse_args(argv)
    scene = load_scene_nd(a.scene)
    plan = identification_plan(scene)
    dev = scene.device
    heavy = replace(scene, device=replace(dev, joint_inertia=dev.joint_inertia * a.heavier))
    print(f"{a.scene}: prediction order {plan[1]}, {plan[2]} samples a record")
    print(f"{'a [m]':>8} {'device':>8} {'dev k':>9} {'dev b':>9} {'lin k':>8} {'lin b':>8} "
          f"{'wire k':>8} {'wire b':>8}  verdict")
    for amp in [float(v) for v in a.amplitudes.split(",")]:
        for name, plant in (("match", None), (f"x{a.heavier:g} Mq", heavy)):
            r = measure_felt_falcon(scene, amp, plant=plant, plan=plan)
            dv = r["deviation"] or {}
            lin = r["bound"].to_dict()
            print(f"{amp:8.1e} {name:>8} {dv.get('felt_stiffness', math.nan):9.2e} "
                  f"{dv.get('felt_damping', math.nan):9.2e} "
                  f"{(lin['felt_stiffness'] or math.nan):8.2e} "
                  f"{(lin['felt_damping'] or math.nan):8.2e} "
                  f"{r['wire']['felt_stiffness']:8.2e} {r['wire']['felt_damping']:8.2e}  "
                  f"{r['verdict']} (records' excursion {r['excursion'] * 1e3:.3f} mm, legs "
                  f"{r['excursion_rad']:.3g} rad)")
        t = quantiser_terms(scene, amp, plan)
        print(f"{'':8} exact records: fit off by {t['fit_exact']['felt_stiffness']:.2e} / "
              f"{t['fit_exact']['felt_damping']:.2e}; about them, worst case "
              f"{t['worst']['felt_stiffness']:.3g} / {t['worst']['felt_damping']:.3g} "
              f"(readings {t['worst_reading']['felt_stiffness']:.3g} / "
              f"{t['worst_reading']['felt_damping']:.3g}, commands "
              f"{t['worst_command']['felt_stiffness']:.3g} / "
              f"{t['worst_command']['felt_damping']:.3g}); Widrow & Kollar s.d. "
              f"{t['widrow_kollar']['felt_stiffness']:.3g} / "
              f"{t['widrow_kollar']['felt_damping']:.3g}")
    f = felt_feasibility(scene, plan)
    print(f"feasibility: {f['verdict']}: {f['reason']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
