#!/usr/bin/env python3
"""Cost of one tick of the n-DoF mock's joint-space device (a program, not a test).

For each shipped pantograph and delta scene: the time per period of
:class:`hapsim.joint_device.LocalJointDeviceND` (the real-time mock's device: quadratic
kinematics about the operating point, compiled Runge-Kutta) and of
:class:`hapsim.joint_device.JointDeviceND` (the exact kinematics: closed-form pantograph,
Newton-solved delta), both driven by the same random forces in the same run, their ratio,
and the largest distance between the two handles over the run [m] against the motion's
size (the third-order Taylor term the quadratic model leaves out). The 1 kHz deadline is
1000 us; the machine's load is printed beside the figures.

Usage::

    PYTHONPATH=$PWD python tools/bench_joint_nd.py [--steps 400]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hapsim.joint_device import JointDeviceND, LocalJointDeviceND  # noqa: E402
from hapsim.scene import load_scene_nd  # noqa: E402


def _per_step(dev, forces) -> tuple:
    t = time.perf_counter()
    pos = []
    for u in forces:
        dev.step(u)
        pos.append(dev.position())
    return (time.perf_counter() - t) / len(forces), np.array(pos)


def main() -> int:
    """Print the table (module notes). Returns 0."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=400, help="periods per device (400)")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f} (2 cores shared: 'loaded machine' above 2)")
    print(f"{'scene':24s} {'local [us]':>11s} {'exact [us]':>11s} {'ratio':>7s} "
          f"{'motion [m]':>11s} {'local-exact [m]':>16s}")
    for name in ("pantograph_wall", "pantograph_circle", "delta_sphere", "delta_mesh"):
        sc = load_scene_nd(REPO / "configs" / f"{name}.yaml")
        n = sc.dimension
        rng = np.random.default_rng(0)
        steps = args.steps if n == 2 else max(args.steps // 10, 20)   # the exact delta: ms
        forces = 0.02 * rng.normal(size=(steps, n))
        x0, v0 = 1e-4 * np.ones(n), np.zeros(n)
        local = LocalJointDeviceND(sc, x0, v0)
        local.step(np.zeros(n))                      # compiled before timing
        local = LocalJointDeviceND(sc, x0, v0)
        exact = JointDeviceND(sc, sc.device.position + x0, v0)
        tl, pl = _per_step(local, forces)
        te, pe = _per_step(exact, forces)
        motion = float(np.abs(pe - sc.device.position).max())
        print(f"{name:24s} {tl * 1e6:11.1f} {te * 1e6:11.1f} {te / tl:7.0f} "
              f"{motion:11.2e} {float(np.abs(pl - pe).max()):16.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
