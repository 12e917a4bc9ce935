"""The devices' presets are the published geometries. tests/test_kinematics.py checks the
forward kinematics against references written there, but those references read the same
preset objects: a wrong constant would pass them. These numbers are typed in from the
publications (libnifalcon ``include/falcon/core/FalconGeometry.h``: Stamper's diagram,
page 30; HaplyHaptics ``src/Haply/Pantograph.cpp``: l = 0.05, L = 0.07, d = 0.02 m)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hapsim.kinematics import DELTA_PRESETS, PANTOGRAPH_PRESETS, Delta, Pantograph

#: libnifalcon FalconGeometry.h: a, b, c, d, e (= d), f, r, s [m]; the legs at
#: pi/2, -pi/6, -5 pi/6, each plus OFFSET_ANGLE = pi/12.
FALCON = dict(a=0.060, b=0.1025, c=0.014, d=0.01125, e=0.01125, f=-0.025,
              r=0.037233758, s=-0.027330909)
FALCON_PHI = [math.pi / 2 + math.pi / 12, -math.pi / 6 + math.pi / 12,
              -5 * math.pi / 6 + math.pi / 12]


def test_falcon_preset_is_libnifalcons_geometry():
    g = DELTA_PRESETS["falcon"]
    for key, value in FALCON.items():
        assert getattr(g, key) == pytest.approx(value, rel=1e-12), key
    assert np.allclose(np.radians(g.phi_deg), FALCON_PHI, rtol=0, atol=1e-12)


def test_haply_preset_is_haplys_geometry():
    g = PANTOGRAPH_PRESETS["haply"]
    assert (g.l1, g.l2, g.L1, g.L2, g.d) == (0.05, 0.05, 0.07, 0.07, 0.02)


def test_falcon_rest_pose_by_hand():
    """Equal thigh angles q put the effector on the z axis at a height in closed form
    from Stamper's leg equations and the published constants alone (no hapsim preset):
    on the axis a leg sees the effector at (u, v) = (-r, -s), so its shin angle is
    cos t3 = (f - s)/b, the knee-to-effector reach L = d + e + b sin t3, and
    z = a sin q + sqrt(L^2 - (c - r - a cos q)^2) (the Falcon's branch); to 1e-9 m."""
    dev = Delta("falcon")
    G = FALCON
    for q in np.radians([-10.0, 0.0, 15.0, 30.0]):
        # leg i's open chain: u + c = a cos q + L cos t2, v + f = b cos t3,
        # w = a sin q + L sin t2, with (u, v) = (-r, -s) on the axis
        cos_t3 = (-G["s"] + G["f"]) / G["b"]
        L = G["d"] + G["e"] + G["b"] * math.sqrt(1 - cos_t3 ** 2)
        du = -G["r"] + G["c"] - G["a"] * math.cos(q)          # = L cos t2
        z = G["a"] * math.sin(q) + math.sqrt(L * L - du * du)  # the Falcon's branch
        assert np.allclose(dev.forward([q, q, q]), [0.0, 0.0, z], rtol=0, atol=1e-9)
