"""Write the shipped 2-D and 3-D scenes of configs/ (issue 23 item 7).

The ground points that press the handle into a wall, a disc or a sphere sit where the
handle rests (the forward kinematics of the device's joints), so they are computed here
from :mod:`hapsim.kinematics` and written rounded to 0.1 nm (the rest is an equilibrium to about 1e-10 m). Run from the repository root::

    python tools/make_nd_scenes.py          # rewrites configs/{pantograph,delta}_*.yaml
                                            # and configs/membrane.yaml

Each scene presses its handle ``PRESS`` into the object at rest with a soft "press"
spring (length 0) to a ground point behind it: the rest is then (to the rounding) an
equilibrium, the contact stays engaged under a small excitation, and every direction
renders a pair (a frictionless wall, disc or sphere alone has no tangential stiffness, so
the loop would have fewer than n rendered pairs and no felt matrices).
"""

from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from hapsim.kinematics import device  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
PRESS = 0.0005          # the handle's depth into the object at rest [m]


def v(a) -> str:
    return "[" + ", ".join(f"{round(float(x), 10):.10f}".rstrip("0").rstrip(".")
                           if abs(x) > 5e-11 else "0.0" for x in a) + "]"


def unit(a) -> np.ndarray:
    a = np.asarray(a, float)
    return a / np.linalg.norm(a)


def pantograph_device(joints, lengths=None) -> str:
    if lengths is not None:                       # the five-bar's lengths as numbers
        head = (f"device: {{kind: pantograph, joints: {v(joints)},\n"
                "         geometry: {" + ", ".join(f"{k}: {x:g}" for k, x in
                                         zip(("l1", "l2", "L1", "L2", "d"), lengths))
                + "},  # [m]\n")
    else:
        head = f"device: {{kind: pantograph, geometry: haply, joints: {v(joints)},\n"
    return (head +
            "         joint_inertia: [2.0e-4, 2.0e-4],   # [kg m^2]\n"
            "         joint_friction: [1.0e-3, 1.0e-3],  # [N m s/rad]\n"
            "         hand_mass: 0.05, delay: 1}        # [kg], [samples]\n")


def delta_device(joints) -> str:
    return (f"device: {{kind: delta, geometry: falcon, joints: {v(joints)},\n"
            "         joint_inertia: [1.5e-4, 1.5e-4, 1.5e-4],   # [kg m^2]\n"
            "         joint_friction: [1.0e-3, 1.0e-3, 1.0e-3],  # [N m s/rad]\n"
            "         hand_mass: 0.05, delay: 1}                # [kg], [samples]\n")


def wall() -> str:
    q = [130.0, 50.0]
    h = device("pantograph").forward(np.radians(q))
    n = np.array([0.0, 1.0])                      # out of the wall, towards the handle
    K, kp = 1000.0, 200.0
    press = h - (K * PRESS / kp) * n
    return (
        "# A planar wall under the handle of a Haply 2DIY pantograph (five-bar, l = 0.05,\n"
        "# L = 0.07, d = 0.02 m). The wall is the half-plane below y = offset; the handle\n"
        "# rests 0.5 mm into it, held there by a soft press spring to a point behind it\n"
        "# (without it a frictionless wall has no tangential stiffness: no felt matrices).\n"
        "# hapsim check: the felt stiffness and damping matrices, the stiffness limit\n"
        "# along the device's principal mass axes; --plot FIG.png draws them over the\n"
        "# workspace. Written by tools/make_nd_scenes.py.\n"
        "dimension: 2\n"
        "rate_hz: 1000\n"
        "masses:\n"
        "  - {name: hand, kind: port}            # rests at the handle (joints below)\n"
        f"  - {{name: press, kind: ground, x0: {v(press)}}}\n"
        "links:\n"
        "  - {name: press, kind: spring_damper, between: [hand, press], stiffness: "
        f"{kp:g}, damping: 0.5}}\n"
        "planes:\n"
        f"  - {{name: wall, normal: {v(n)}, offset: {h[1] + PRESS:.10f}, stiffness: {K:g}, "
        "damping: 2.0,\n"
        "     masses: [hand]}\n"
        + pantograph_device(q))


def circle() -> str:
    q = [140.0, 60.0]
    h = device("pantograph").forward(np.radians(q))
    R = 0.02
    n = unit([-0.6, 0.8])                         # from the disc's centre to the handle
    c = h - (R - PRESS) * n
    K, kp = 1000.0, 200.0
    press = h - (K * PRESS / kp) * n
    return (
        "# A disc (a circle of radius 0.02 m) touched by the handle of a Haply 2DIY\n"
        "# pantograph, from its upper left, off the workspace's centre line (the device's\n"
        "# Cartesian mass is not diagonal there). The handle rests 0.5 mm into the disc,\n"
        "# held by a soft press spring; the contact is the sphere law (Euclidean, acting\n"
        "# while the distance is below the threshold, the disc's radius).\n"
        "# Written by tools/make_nd_scenes.py.\n"
        "dimension: 2\n"
        "rate_hz: 1000\n"
        "masses:\n"
        "  - {name: hand, kind: port}\n"
        f"  - {{name: disc, kind: ground, x0: {v(c)}}}\n"
        f"  - {{name: press, kind: ground, x0: {v(press)}}}\n"
        "links:\n"
        f"  - {{name: disc, kind: contact, between: [hand, disc], stiffness: {K:g}, "
        f"damping: 2.0, threshold: {R:g}}}\n"
        "  - {name: press, kind: spring_damper, between: [hand, press], stiffness: "
        f"{kp:g}, damping: 0.5}}\n"
        + pantograph_device(q))


#: The planar spring's stiffness [N/m] and damping [N s/m], and the excitation the
#: emulated Hapkit pantograph is measured at [m] (docs/pantograph.md, 'What the loop
#: measures').
SPRING_K, SPRING_B, SPRING_AMPLITUDE = 800.0, 6.0, 5e-3


def spring() -> str:
    q = [130.0, 50.0]
    h = device("pantograph").forward(np.radians(q))
    return (
        "# A planar spring: the handle of a pantograph held at its workspace's centre by a\n"
        "# spring-damper of rest length 0 (the same law on both axes) to a ground there.\n"
        "# No contact to open, so the hand may move millimetres: large against the Hapkit\n"
        "# pantograph's resolution (one sensor count is about 11 um at the handle, one PWM\n"
        "# step about 0.036 N), which its firmware then measures (docs/pantograph.md; over\n"
        "# the wire's error box nothing is stated in lockstep at 5 mm):\n"
        f"#   hapsim mock --firmware --scene configs/pantograph_spring.yaml --lockstep "
        f"--amplitude {SPRING_AMPLITUDE:g}\n"
        f"#   hapsim run configs/pantograph_spring.yaml --port PTY --lockstep "
        f"--amplitude {SPRING_AMPLITUDE:g}\n"
        "# The geometry is given as numbers, the five-bar's lengths [m] (here the Haply\n"
        "# 2DIY's; write your device's). Written by tools/make_nd_scenes.py.\n"
        "dimension: 2\n"
        "rate_hz: 1000\n"
        "masses:\n"
        "  - {name: hand, kind: port}\n"
        f"  - {{name: centre, kind: ground, x0: {v(h)}}}\n"
        "links:\n"
        "  - {name: spring, kind: spring_damper, between: [hand, centre], stiffness: "
        f"{SPRING_K:g}, damping: {SPRING_B:g}}}\n"
        + pantograph_device(q, (0.05, 0.05, 0.07, 0.07, 0.02)))


#: The Falcon's spring field: stiffness [N/m] and damping [N s/m] (configs/falcon_spring.yaml;
#: the figures in its comments are tools/falcon_felt_figures.py's, pinned by
#: tests/test_falcon_spring.py).
FALCON_K, FALCON_B = 1000.0, 3.0


def falcon_spring() -> str:
    q = [20.0, 25.0, 15.0]
    h = device("delta", "falcon").forward(np.radians(q))
    return (
        "# A spring field felt through a Novint Falcon (delta, libnifalcon's geometry): the\n"
        "# handle held where it rests by a 3-D spring-damper of rest length 0 to an anchor\n"
        "# there (the same law along every axis). No contact to open, so a hand start may be\n"
        "# millimetres, up to the run's envelope of 0.1 rad at a leg (3.8 mm here, about 95\n"
        "# encoder counts of 27-47 um). There the counts' rounding, drawn at 100 phases of\n"
        "# the encoders' zero through the loop and refitted by the run's fit, moves the felt\n"
        "# stiffness by 0.083 of itself at most; the run states 1.5 times that, 0.12, below\n"
        "# the 0.25 a statement allows ('hapsim run --driver falcon' measures and states the\n"
        "# felt stiffness, as a matrix and along each principal direction). The worst case\n"
        "# over every sign of the roundings, 0.19 at first order, was 1.3 and more over the\n"
        "# errors' box. The damping is not measurable at any start: the draws move it by\n"
        "# 0.93 (python tools/rounding_figures.py falcon).\n"
        "# 1000 N/m is 0.5 of the stiffness limit along the device's lightest mass axis\n"
        "# (2029 N/m); 3 N s/m keeps the loop stable with one period more of delay (a packet\n"
        "# lost on the link: the firmware holds the last command), and no more: a larger\n"
        "# damping lets the records fade into the counts, which then state less.\n"
        "# Written by tools/make_nd_scenes.py.\n"
        "dimension: 3\n"
        "rate_hz: 1000\n"
        "masses:\n"
        "  - {name: hand, kind: port}\n"
        f"  - {{name: anchor, kind: ground, x0: {v(h)}}}\n"
        "links:\n"
        "  - {name: field, kind: spring_damper, between: [hand, anchor], stiffness: "
        f"{FALCON_K:g}, damping: {FALCON_B:g}}}\n"
        + delta_device(q))


def sphere() -> str:
    q = [20.0, 25.0, 15.0]
    h = device("delta").forward(np.radians(q))
    R = 0.025
    n = unit([0.2, 0.1, -1.0])                    # the sphere is deeper (larger z)
    c = h - (R - PRESS) * n
    K, kp = 800.0, 200.0
    press = h - (K * PRESS / kp) * n
    return (
        "# A sphere of radius 0.025 m touched by the handle of a Novint Falcon (delta,\n"
        "# libnifalcon's geometry; z is the depth away from the user). The handle rests\n"
        "# 0.5 mm into the sphere, held by a soft press spring; the contact is the\n"
        "# Euclidean sphere law. Written by tools/make_nd_scenes.py.\n"
        "dimension: 3\n"
        "rate_hz: 1000\n"
        "masses:\n"
        "  - {name: hand, kind: port}\n"
        f"  - {{name: sphere, kind: ground, x0: {v(c)}}}\n"
        f"  - {{name: press, kind: ground, x0: {v(press)}}}\n"
        "links:\n"
        f"  - {{name: sphere, kind: contact, between: [hand, sphere], stiffness: {K:g}, "
        f"damping: 2.0, threshold: {R:g}}}\n"
        "  - {name: press, kind: spring_damper, between: [hand, press], stiffness: "
        f"{kp:g}, damping: 0.5}}\n"
        + delta_device(q))


def mesh() -> str:
    q = [20.0, 20.0, 20.0]
    h = device("delta").forward(np.radians(q))
    N, step, rest = 7, 0.008, 0.0064              # 7 x 7 points, 20 % pre-tension
    lines = [
        "# A 3-D mesh: a taut square membrane of 7 x 7 points 8 mm apart in the plane\n"
        "# z = const through the handle of a Novint Falcon (delta); the border is fixed,\n"
        "# the 25 inner points are masses, the links are Euclidean springs at 80 % of their\n"
        "# length (pre-tension: without it the membrane has no stiffness across its plane).\n"
        "# The handle holds the centre point through a grip spring, so it feels the\n"
        "# membrane's modes. Written by tools/make_nd_scenes.py.\n",
        "dimension: 3\n", "rate_hz: 1000\n", "masses:\n",
        "  - {name: hand, kind: port}\n"]
    c = (N - 1) // 2
    names = {}
    for i in range(N):
        for j in range(N):
            p = h + np.array([(i - c) * step, (j - c) * step, 0.0])
            nm = f"m{i}{j}"
            names[i, j] = nm
            if i in (0, N - 1) or j in (0, N - 1):
                lines.append(f"  - {{name: {nm}, kind: ground, x0: {v(p)}}}\n")
            else:
                lines.append(f"  - {{name: {nm}, kind: mass, mass: 0.005, x0: {v(p)}}}\n")
    lines.append("links:\n")
    lines.append(f"  - {{name: grip, kind: spring_damper, between: [hand, {names[c, c]}], "
                 "stiffness: 300, damping: 0.5}\n")
    for i in range(N):
        for j in range(N):
            for di, dj in ((1, 0), (0, 1)):
                a, b = (i, j), (i + di, j + dj)
                if b[0] >= N or b[1] >= N:
                    continue
                border = [x in (0, N - 1) for x in (a[0], a[1], b[0], b[1])]
                if (border[0] or border[1]) and (border[2] or border[3]):
                    continue                       # ground to ground: no force
                lines.append(f"  - {{name: s{i}{j}{'x' if di else 'y'}, kind: spring_damper, "
                             f"between: [{names[a]}, {names[b]}], stiffness: 300, "
                             f"damping: 0.05, length: {rest:g}}}\n")
    inner = [names[i, j] for i in range(1, N - 1) for j in range(1, N - 1)]
    lines.append("planes:   # air: a damping-only plane the membrane lies 5 cm inside, so its\n"
                 "          # motion across its plane is damped (the links damp along them)\n"
                 f"  - {{name: air, normal: [0, 0, 1], offset: {h[2] + 0.05:.10f}, "
                 "stiffness: 0, damping: 0.02,\n"
                 f"     masses: [{', '.join(inner)}]}}\n")
    lines.append(delta_device(q))
    return "".join(lines)


#: The membrane: MEMBRANE_N x MEMBRANE_N masses, spacing [m], mass [kg], link K [N/m] and
#: B [N s/m], sample rate [Hz] (tests/test_membrane.py reads them).
MEMBRANE_N, MEMBRANE_H, MEMBRANE_M, MEMBRANE_K, MEMBRANE_B = 12, 0.01, 0.001, 16000.0, 0.05
MEMBRANE_RATE = 44100
MEMBRANE_STRIKE, MEMBRANE_LISTEN = (4, 5), (9, 3)


def membrane() -> str:
    """A square membrane of masses and length-0 springs, its edge held, struck and heard."""
    n, h = MEMBRANE_N, MEMBRANE_H
    mu11 = 8 * np.sin(np.pi / (2 * (n + 1))) ** 2
    f11 = np.sqrt(mu11 * MEMBRANE_K / MEMBRANE_M) / (2 * np.pi)
    zeta11 = MEMBRANE_B * 2 * np.pi * f11 / (2 * MEMBRANE_K)

    def name(i, j):
        return f"m{i}_{j}" if 1 <= i <= n and 1 <= j <= n else f"g{i}_{j}"
    si, sj = MEMBRANE_STRIKE
    li, lj = MEMBRANE_LISTEN
    lines = [
        f"# A square membrane: {n} x {n} masses of {MEMBRANE_M * 1e3:g} g on a "
        f"{h * 100:g} cm grid, each joined to its\n",
        f"# four neighbours by a length-0 spring-damper (K = {MEMBRANE_K:g} N/m, "
        f"B = {MEMBRANE_B:g} N s/m: the 1-D law on\n",
        "# every axis, so its motion across its plane (z) is the discrete membrane), its "
        "edge held by grounds.\n",
        f"# Struck at {name(si, sj)} (v0 = 0.5 m/s along z), heard at {name(li, lj)} "
        "(its z velocity).\n",
        "# Modes: f_pq ~ sqrt(mu_pq K / m) / (2 pi) with mu_pq = 4 [sin^2(p pi / 26) + "
        "sin^2(q pi / 26)]\n",
        f"# (the centred scheme at 44.1 kHz warps them slightly): f_11 = {f11:.1f} Hz "
        f"(damping ratio {zeta11:.2g}),\n",
        "# f_12 = f_21, f_22, ... (inharmonic, as a drum's).\n",
        "#   hapsim check configs/membrane.yaml [--json] [--plot FIG.png]   (the modes)\n",
        "#   hapsim simulate configs/membrane.yaml --audio membrane.wav --steps 88200\n",
        "# Written by tools/make_nd_scenes.py.\n",
        "dimension: 3\n",
        f"rate_hz: {MEMBRANE_RATE}\n",
        "masses:\n"]
    for i in range(0, n + 2):
        for j in range(0, n + 2):
            if (i in (0, n + 1)) and (j in (0, n + 1)):
                continue                                  # corners join nothing
            x0 = v([i * h, j * h, 0.0])
            if 1 <= i <= n and 1 <= j <= n:
                v0 = ", v0: [0, 0, 0.5]" if (i, j) == (si, sj) else ""
                lines.append(f"  - {{name: {name(i, j)}, kind: mass, mass: {MEMBRANE_M:g}, "
                             f"x0: {x0}{v0}}}\n")
            else:
                lines.append(f"  - {{name: {name(i, j)}, kind: ground, x0: {x0}}}\n")
    lines.append("links:\n")
    for i in range(0, n + 2):
        for j in range(0, n + 2):
            for di, dj in ((1, 0), (0, 1)):
                a, b = (i, j), (i + di, j + dj)
                if b[0] > n + 1 or b[1] > n + 1:
                    continue
                if not any(1 <= p <= n and 1 <= q <= n for p, q in (a, b)):
                    continue
                lines.append(f"  - {{kind: spring_damper, between: [{name(*a)}, "
                             f"{name(*b)}], stiffness: {MEMBRANE_K:g}, damping: "
                             f"{MEMBRANE_B:g}}}\n")
    lines += ["audio:\n", "  listen:\n",
              f"    - {{mass: {name(li, lj)}, axis: z, quantity: velocity, gain: 12.0}}\n"]
    return "".join(lines)


SCENES = {"pantograph_wall.yaml": wall, "pantograph_circle.yaml": circle,
          "pantograph_spring.yaml": spring,
          "delta_sphere.yaml": sphere, "delta_mesh.yaml": mesh,
          "falcon_spring.yaml": falcon_spring, "membrane.yaml": membrane}

if __name__ == "__main__":
    for name, make in SCENES.items():
        path = os.path.join(ROOT, "configs", name)
        with open(path, "w") as fh:
            fh.write(make())
        print(path)
