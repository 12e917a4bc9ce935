"""The devices' presets are the published geometries. tests/test_kinematics.py checks the
forward kinematics against references written there, but those references read the same
preset objects: a wrong constant would pass them. These numbers are typed in from the
publications (libnifalcon ``include/falcon/core/FalconGeometry.h``: Stamper's diagram,
page 30; HaplyHaptics ``src/Haply/Pantograph.cpp``: l = 0.05, L = 0.07, d = 0.02 m), and
the pantograph against Haply's own published forward kinematics and Jacobian (the same
file's method, restated here: the radical line of the two distal circles, then the
larger root of a quadratic) at >= 1,000 random configurations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hapsim.kinematics import DELTA_PRESETS, PANTOGRAPH_PRESETS, Delta, Pantograph
from tolerance import measured, rel_tol

pytestmark = pytest.mark.numerical

#: libnifalcon FalconGeometry.h: a, b, c, d, e (= d), f, r, s [m]; the legs at
#: pi/2, -pi/6, -5 pi/6, each plus OFFSET_ANGLE = pi/12.
FALCON = dict(a=0.060, b=0.1025, c=0.014, d=0.01125, e=0.01125, f=-0.025,
              r=0.037233758, s=-0.027330909)
FALCON_PHI = [math.pi / 2 + math.pi / 12, -math.pi / 6 + math.pi / 12,
              -5 * math.pi / 6 + math.pi / 12]


def test_falcon_preset_is_libnifalcons_geometry():
    g = DELTA_PRESETS["falcon"]
    for key, value in FALCON.items():
        # a published constant, stored or converted by a product at most (2 roundings)
        assert getattr(g, key) == pytest.approx(value, rel=rel_tol(2)), key
    # degrees to radians: a product by pi/180 on each side (3 roundings, angles <= pi)
    assert np.allclose(np.radians(g.phi_deg), FALCON_PHI, rtol=0, atol=rel_tol(3) * math.pi)


def test_haply_preset_is_haplys_geometry():
    g = PANTOGRAPH_PRESETS["haply"]
    assert (g.l1, g.l2, g.L1, g.L2, g.d) == (0.05, 0.05, 0.07, 0.07, 0.02)


def test_falcon_rest_pose_by_hand():
    """Equal thigh angles q put the effector on the z axis at a height in closed form
    from Stamper's leg equations and the published constants alone (no hapsim preset):
    on the axis a leg sees the effector at (u, v) = (-r, -s), so its shin angle is
    cos t3 = (f - s)/b, the knee-to-effector reach L = d + e + b sin t3, and
    z = a sin q + sqrt(L^2 - (c - r - a cos q)^2) (the Falcon's branch); to 2.8e-17 m
    measured (x86-64, OpenBLAS Haswell and Prescott), margin 1000."""
    dev = Delta("falcon")
    G = FALCON
    for q in np.radians([-10.0, 0.0, 15.0, 30.0]):
        # leg i's open chain: u + c = a cos q + L cos t2, v + f = b cos t3,
        # w = a sin q + L sin t2, with (u, v) = (-r, -s) on the axis
        cos_t3 = (-G["s"] + G["f"]) / G["b"]
        L = G["d"] + G["e"] + G["b"] * math.sqrt(1 - cos_t3 ** 2)
        du = -G["r"] + G["c"] - G["a"] * math.cos(q)          # = L cos t2
        z = G["a"] * math.sin(q) + math.sqrt(L * L - du * du)  # the Falcon's branch
        assert np.allclose(dev.forward([q, q, q]), [0.0, 0.0, z], rtol=0,
                           atol=measured(2.8e-17, 1000))


def haply_published(q, l=0.05, L=0.07, d=0.02):
    """Haply's Pantograph::forwardKinematics, restated: the handle (x, y) on the radical
    line x = M y + N of the circles of radius L about the elbows A and B, y the larger
    root of a y^2 + b y + c = 0; and its matrix [[J11, J12], [J21, J22]] from the distal
    angles phi_i = acos((x - x_elbow_i)/L), which maps (F_x, F_y) to the joint torques
    up to its gain; and a bound on the round-off of that (x, y) [m]."""
    t1, t2 = q
    xA, yA = l * math.cos(t1), l * math.sin(t1)
    xB, yB = d + l * math.cos(t2), l * math.sin(t2)
    R, S = xA * xA + yA * yA, xB * xB + yB * yB
    M = (yA - yB) / (xB - xA)
    N = 0.5 * (S - R) / (xB - xA)
    a, b = M * M + 1.0, 2.0 * (M * N - M * xA - yA)
    c = N * N - 2.0 * N * xA + R - L * L
    y = (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    x = M * y + N
    p1 = math.acos((x - xA) / L)
    p2 = math.acos((x - xB) / L)
    s21, s12, s22 = math.sin(p2 - p1), math.sin(t1 - p2), math.sin(t2 - p2)
    J = np.array([[-(math.sin(t1) * s21 + math.sin(p1) * s12) / s21,
                   (math.cos(t1) * s21 + math.cos(p1) * s12) / s21],
                  [math.sin(p1) * s22 / s21, -math.cos(p1) * s22 / s21]])
    # its round-off [m]: ~30 roundings from q to x (cos, the circles' R and S, M, N, the
    # quadratic's a, b, c, its discriminant, sqrt, y, x), amplified by the division by
    # xB - xA (the radical line) and by the quadratic's root condition |b| / sqrt(disc)
    span = l + L + d
    tol = (rel_tol(30) * span * max(1.0, span / abs(xB - xA))
           * max(1.0, abs(b) / math.sqrt(b * b - 4.0 * a * c)))
    return np.array([x, y]), J, min(y - yA, y - yB), tol


def test_pantograph_is_haplys_published_forward_kinematics():
    """At >= 1,000 random joint configurations the handle is Haply's to the published
    method's round-off (1 um asked; it loses digits where the elbows are nearly above
    each other: haply_published's bound). Haply's matrix is l J^T, hapsim's Jacobian
    transposed over the proximal length, where its distal angles are right (acos: the
    handle above both elbows, the 2DIY's workspace), to 1.9e-13 of the largest entry
    measured (x86-64, OpenBLAS Haswell and Prescott), margin 1000."""
    dev = Pantograph("haply")
    rng = np.random.default_rng(23)
    worst_x = worst_j = 0.0
    above = 0
    for q in rng.uniform(-0.5, math.pi + 0.5, (1200, 2)):
        x, Jh, rise, tol = haply_published(q)
        # as a fraction of the bound (hapsim's own error is far below the published one's)
        worst_x = max(worst_x, float(np.max(np.abs(dev.forward(q) - x))) / tol)
        if rise > 1e-3:
            J = dev.jacobian(q)
            worst_j = max(worst_j, float(np.max(np.abs(0.05 * Jh - J.T)) / np.max(np.abs(J))))
            above += 1
    assert worst_x <= 1.0
    assert above >= 1000 and worst_j <= measured(1.9e-13, 1000)
