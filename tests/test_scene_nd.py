"""2-D and 3-D scenes (hapsim.scene.SceneND) and their closed-loop check
(hapsim.analysis.scene_check): the n-D check of a scene whose links are linear is the
1-D check per axis; a port held by grounds and planes is the THS matrix of
hapsim.analysis.ths; Euclidean links linearise to the finite-difference Jacobian of
their law; every rule is refused with file, line and key; `check --json` reports the
felt matrices."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from hapsim.analysis import check_scene
from hapsim.analysis.scene_check import check_scene_nd
from hapsim.analysis.virtual_network import link_blocks
from hapsim.analysis.ths import MatrixLoop, render
from hapsim.cli import main
from hapsim.errors import ConfigError
from hapsim.kinematics import Pantograph, cartesian_mass
from hapsim.scene import parse_scene
from hapsim.scene import parse_scene_nd
from tolerance import BRENT_THETA, crossing_tol, eig_tol, measured, recurrence_tol, rel_tol, solve_tol

pytestmark = pytest.mark.numerical

STRING_1D = """\
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: left, kind: ground}
  - {name: bead, kind: mass, mass: 0.01}
  - {name: right, kind: ground}
links:
  - {kind: spring_damper, between: [left, bead], stiffness: 200, damping: 0.01}
  - {kind: spring_damper, between: [bead, right], stiffness: 200, damping: 0.01}
  - {kind: spring_damper, between: [hand, bead], stiffness: 500, damping: 0.1}
device: {mass: 0.1, friction: 0.5, delay: DELAY}
"""


def match(a, b):
    cost = np.abs(np.asarray(a)[:, None] - np.asarray(b)[None, :])
    r, c = linear_sum_assignment(cost)
    return float(cost[r, c].max())


@pytest.mark.parametrize("dim, delay", [(2, 0), (2, 2), (3, 1)])
def test_linear_links_are_the_1d_scene_per_axis(dim, delay):
    """A scene whose links are all `length: 0` spring_dampers and whose device is
    isotropic is n copies of the 1-D scene: its poles are the 1-D check's, each n times
    (1e-12), its felt stiffness is the 1-D felt k times I."""
    from hapsim.analysis.network import closed_loop
    from hapsim.analysis.scene_check import closed_loop_nd
    one = STRING_1D.replace("DELAY", str(delay))
    s1, sn = parse_scene(one), parse_scene_nd(f"dimension: {dim}\n" + one)
    c1, cn = check_scene(s1), check_scene_nd(sn)
    # each path's eigenvalue round-off (tests/tolerance.py: LAPACK UG 4.8.1)
    dz = eig_tol(closed_loop(s1)[0]) + eig_tol(closed_loop_nd(sn)[0])
    assert match(np.concatenate([c1.eigenvalues] * dim), cn.render.poles) <= dz
    assert cn.render.spectral_radius == pytest.approx(c1.spectral_radius, rel=0, abs=dz)
    assert cn.stable == c1.stable
    # felt (k, b) = m |s|^2, -2 m Re s with s = ln(z)/T: moved by 2 m |s| ds, 2 m ds,
    # ds = dz / (|z| T) (first order), m the device mass (0.1 kg)
    z = cn.render.rendered_poles[0]
    ds = dz / (abs(z) * s1.period)
    s = np.log(z) / s1.period
    k = cn.render.felt_stiffness
    # derived: 2 m |s| ds with m = 0.1 kg (the comment above); measured 8.6e-11 (generic
    # 3.7e-11), 1/4000 of it
    assert np.allclose(k, c1.rendered.k * np.eye(dim), rtol=0, atol=2 * 0.1 * abs(s) * ds)
    # derived: 2 m ds; measured 1.3e-12 (generic 4.4e-13), 1/3900 of it
    assert np.allclose(cn.render.felt_damping, c1.rendered.b * np.eye(dim), rtol=0,
                       atol=2 * 0.1 * ds)


def test_port_held_by_grounds_and_planes_is_the_ths_matrix():
    """A port tied to grounds (linear and Euclidean links) and pressed on planes: the
    scene's closed loop has the poles and felt matrices of render with the summed
    link blocks as (K, B) (two independent layouts: force delay line here, position delay
    line there)."""
    text = """\
dimension: 2
rate_hz: 2000
masses:
  - {name: hand, kind: port}
  - {name: a, kind: ground, x0: [0.03, 0.01]}
  - {name: b, kind: ground, x0: [-0.01, 0.02]}
links:
  - {name: s1, kind: spring_damper, between: [hand, a], stiffness: 400, damping: 0.8,
     length: 0.02}
  - {name: s2, kind: spring_damper, between: [b, hand], stiffness: 250, damping: 0.3}
planes:
  - {name: floor, normal: [0.3, 1], offset: -0.001, stiffness: 700, damping: 1.2}
device: {mass: [[0.12, 0.03], [0.03, 0.2]], friction: [0.4, 0.6], delay: 2}
"""
    scene = parse_scene_nd(text, "s.yaml")
    chk = check_scene_nd(scene)
    loop = MatrixLoop(mass=scene.device.mass, friction=scene.device.friction,
                      rate_hz=2000.0, delay=2)
    ref = render(loop, chk.port_stiffness, chk.port_damping)
    from hapsim.analysis.scene_check import closed_loop_nd
    from hapsim.analysis.ths import state_matrix
    dz = (eig_tol(closed_loop_nd(scene)[0])
          + eig_tol(state_matrix(loop, chk.port_stiffness, chk.port_damping)))
    # the force delay line here has poles at z = 0 the position delay line has not: the
    # non-zero poles are compared (|z| > 1e-6; the loop's smallest non-zero one is ~0.1)
    assert match(chk.render.poles[np.abs(chk.render.poles) > 1e-6],
                 ref.poles[np.abs(ref.poles) > 1e-6]) <= dz
    # felt matrices from the rendered pairs: each pair's s moves by dz / (|z| T); k, b
    # by 2 |M| |s| ds and 2 |M| ds (first order; the pairs are well separated, gap >> dz,
    # so their eigenvectors move by the same order)
    T = scene.period
    zr = chk.render.rendered_poles
    ds = dz / (np.min(np.abs(zr)) * T)
    s_max = np.max(np.abs(np.log(zr))) / T
    Mn = np.linalg.norm(scene.device.mass, 2)
    assert np.allclose(chk.render.felt_stiffness, ref.felt_stiffness, rtol=0,
                       atol=2 * Mn * s_max * ds)
    assert np.allclose(chk.render.felt_damping, ref.felt_damping, rtol=0, atol=2 * Mn * ds)
    # the summed blocks themselves: K e e^T + K (1 - L/l0)(I - e e^T), K I, K u u^T
    d0 = np.array([0.0, 0.0]) - np.array([0.03, 0.01])
    e = d0 / np.linalg.norm(d0)
    u = np.array([0.3, 1.0]) / np.hypot(0.3, 1.0)
    P = np.outer(e, e)
    K = (400 * P + 400 * (1 - 0.02 / np.linalg.norm(d0)) * (np.eye(2) - P)
         + 250 * np.eye(2) + 700 * np.outer(u, u))
    # a sum of four 2 x 2 blocks, each a few products: 8 roundings deep, condition 1
    # against the largest entry
    assert np.allclose(chk.port_stiffness, K, rtol=0, atol=rel_tol(8) * np.max(np.abs(K)))


def euclid_force(xa, xb, K, L):
    """The Euclidean spring's force on mass b (written here): +K (|d| - L) d/|d|."""
    d = xa - xb
    return K * (np.linalg.norm(d) - L) * d / np.linalg.norm(d)


@pytest.mark.parametrize("dim", [2, 3])
def test_euclidean_link_blocks_are_the_jacobian_of_the_law(dim):
    """The stiffness block of a Euclidean spring (and of a contact, L = threshold) at
    random rest configurations equals the central-difference Jacobian of its force law:
    d(force on b)/d(x_a) = Kl."""
    rng = np.random.default_rng(dim)
    for _ in range(30):
        xa, xb = rng.normal(size=dim) * 0.02, rng.normal(size=dim) * 0.02
        K, L = rng.uniform(10, 1000), rng.uniform(0.0, 0.05)
        kind = "contact" if rng.random() < 0.5 else "spring_damper"
        extra = f"threshold: {L!r}" if kind == "contact" else f"length: {L!r}"
        text = (f"dimension: {dim}\nrate_hz: 1000\nmasses:\n"
                f"  - {{name: a, kind: mass, mass: 0.01, x0: {xa.tolist()}}}\n"
                f"  - {{name: b, kind: mass, mass: 0.01, x0: {xb.tolist()}}}\n"
                f"links:\n  - {{kind: {kind}, between: [a, b], stiffness: {K!r}, "
                f"damping: 1.0, {extra}}}\n")
        (_, _, _, Kl, Bl), = link_blocks(parse_scene_nd(text))
        h = 1e-7
        J = np.column_stack([(euclid_force(xa + h * ei, xb, K, L)
                              - euclid_force(xa - h * ei, xb, K, L)) / (2 * h)
                             for ei in np.eye(dim)])
        # central difference: truncation h^2/6 max|f^(3)| with |f^(3)| <= 15 K L / r^3
        # (third derivatives of K (r - L) d/r), plus the force's round-off (10 roundings
        # relative to |f| <= K (r + L)) over h
        r = np.linalg.norm(xa - xb)
        trunc = h * h / 6 * 15 * K * L / r ** 3
        noise = rel_tol(10) * K * (r + L) / h
        assert np.allclose(Kl, J, rtol=0, atol=trunc + noise)
        e = (xa - xb) / np.linalg.norm(xa - xb)
        # e e^T of a normalised difference: a norm (dim + 1 roundings), a quotient, a product
        assert np.allclose(Bl, np.outer(e, e), rtol=0, atol=rel_tol(dim + 3))


def test_kinematic_device_is_its_cartesian_mass_at_the_operating_point():
    """A pantograph device: the scene's mass and friction are J^-T M_q J^-1 (+ hand) at
    the joints, and the port rests at the forward kinematics."""
    text = """\
dimension: 2
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: [0.0, 0.1]}
links:
  - {name: w, kind: spring_damper, between: [hand, wall], stiffness: 300, damping: 1}
device: {kind: pantograph, geometry: haply, joints: [120, 40],
         joint_inertia: [2.0e-4, 3.0e-4], joint_friction: [1.0e-3, 2.0e-3],
         hand_mass: 0.05, hand_damping: 0.2, delay: 1}
"""
    scene = parse_scene_nd(text)
    dev = Pantograph("haply")
    q = np.radians([120, 40])
    J = dev.jacobian(q)
    # the reader forms J^-T M_q J^-1 + m_h I from the same kinematics: the two differ by
    # at most the round-off of the inverse of J (a solve's bound) on each side
    tol = 2 * solve_tol(J)
    Mref = cartesian_mass(J, [2e-4, 3e-4]) + 0.05 * np.eye(2)
    Bref = cartesian_mass(J, [1e-3, 2e-3]) + 0.2 * np.eye(2)
    assert np.allclose(scene.device.mass, Mref, rtol=0, atol=tol * np.max(np.abs(Mref)))
    assert np.allclose(scene.device.friction, Bref, rtol=0, atol=tol * np.max(np.abs(Bref)))
    assert np.array_equal(scene.port.x0, dev.forward(q))
    assert check_scene_nd(scene).stable


BASE = """\
dimension: 2
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: [0.0, 0.01]}
  - {name: bob, kind: mass, mass: 0.01, x0: [0.01, 0.0]}
links:
  - {name: w, kind: spring_damper, between: [hand, wall], stiffness: 300, damping: 1}
device: {mass: 0.1, friction: 0.5}
"""

BAD = [
    # (replace, by, line, key, says)
    ("rate_hz: 1000", "rate_hz: 1000\ncolour: red", 3, "colour", "valid keys"),
    ("dimension: 2", "dimension: 4", 1, "dimension", "between 1 and 3"),
    ("x0: [0.0, 0.01]", "x0: [0.0, 0.01, 0.0]", 5, "masses[1].x0", "list of 2 numbers"),
    ("x0: [0.0, 0.01]", "x0: 0.01", 5, "masses[1].x0", "list of 2 numbers"),
    ("mass: 0.01,", "mass: -1,", 6, "masses[2].mass", "> 0"),
    ("{name: bob,", "{name: wall,", 6, "masses[2].name", "duplicate"),
    ("between: [hand, wall]", "between: [hand, nowhere]", 8, "links[0].between",
     "no mass named"),
    ("between: [hand, wall]", "between: [hand, hand]", 8, "links[0].between",
     "two different"),
    ("damping: 1}", "damping: 1, threshold: 0.01}", 8, "links[0].threshold",
     "valid keys"),
    ("kind: spring_damper, between", "kind: contact, between", 8, "links[0].threshold",
     "missing required"),
    ("stiffness: 300,", "stiffness: -300,", 8, "links[0].stiffness", ">= 0"),
    ("device: {mass: 0.1,", "device: {mass: [[0.1, 0.2], [0.2, 0.1]],", 9, "device.mass",
     "positive definite"),
    ("device: {mass: 0.1,", "device: {kind: delta, joints: [0, 0, 0], "
     "joint_inertia: 1.0e-4, mass: 0.1,", 9, "device.mass", "valid keys"),
    ("device: {mass: 0.1, friction: 0.5}", "device: {kind: delta, joints: [0, 0, 0], "
     "joint_inertia: 1.0e-4}", 9, "device.kind", "3 degrees of freedom"),
    ("device: {mass: 0.1, friction: 0.5}", "device: {kind: pantograph, joints: "
     "[90, 113.578], joint_inertia: 1.0e-4}", 9, "device.joints", "ambiguous assembly"),
    ("device: {mass: 0.1, friction: 0.5}", "device: {mass: 0.1, hold: ideal}", 9,
     "device.hold", "valid choices: zoh"),
    ("device: {mass: 0.1, friction: 0.5}\n", "", 2, "device", "needs a device"),
]


@pytest.mark.parametrize("old, new, line, key, says", BAD, ids=[b[3] for b in BAD])
def test_every_rule_is_refused_with_file_line_and_key(old, new, line, key, says):
    assert old in BASE
    text = BASE.replace(old, new, 1)
    with pytest.raises(ConfigError) as err:
        parse_scene_nd(text, "bad.yaml")
    e = err.value
    assert (e.file, e.key) == ("bad.yaml", key), str(e)
    assert says in str(e), str(e)
    if key != "device":
        assert e.line == line, str(e)


def test_planes_and_euclidean_links_refuse_what_has_no_direction():
    """A zero plane normal; a Euclidean link whose masses coincide at rest (the check
    names the link)."""
    with pytest.raises(ConfigError) as err:
        parse_scene_nd(BASE + "planes: [{normal: [0, 0], stiffness: 10}]\n", "p.yaml")
    assert err.value.key == "planes[0].normal"
    text = BASE.replace("damping: 1}", "damping: 1, length: 0.01}").replace(
        "x0: [0.0, 0.01]", "x0: [0.0, 0.0]")
    with pytest.raises(ConfigError) as err:
        check_scene_nd(parse_scene_nd(text, "c.yaml"))
    assert err.value.key == "links.w" and err.value.line == 8


def test_check_cli_dispatches_on_dimension(tmp_path, capsys):
    """`hapsim check` on a 2-D scene: one JSON object with dof, felt_stiffness,
    felt_damping (n x n), principal directions, spectral radius; exit 0 stable, 1
    unstable; 1-D files (no key or dimension: 1) keep the 1-D check; the 1-D reader
    refuses dimension 2 saying who reads it."""
    f = tmp_path / "s2.yaml"
    f.write_text(BASE)
    assert main(["check", str(f), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["dof"] == 2 and d["stable"] is True
    assert np.shape(d["felt_stiffness"]) == (2, 2) and np.shape(d["felt_damping"]) == (2, 2)
    assert np.shape(d["principal_directions"]) == (2, 2)
    chk = check_scene_nd(parse_scene_nd(BASE))
    assert d["spectral_radius"] == chk.render.spectral_radius
    assert np.array_equal(d["felt_stiffness"], chk.render.felt_stiffness.tolist())
    f.write_text(BASE.replace("stiffness: 300", "stiffness: 90000"))
    assert main(["check", str(f), "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["verdict"] == "unstable"
    one = tmp_path / "s1.yaml"
    one.write_text("dimension: 1\n" + STRING_1D.replace("DELAY", "1"))
    assert main(["check", str(one), "--json"]) == 0          # the 1-D check
    assert "dof" not in json.loads(capsys.readouterr().out)
    with pytest.raises(ConfigError) as err:
        parse_scene(BASE, "s2.yaml")
    assert err.value.key == "dimension" and "hapsim check" in str(err.value)
    f.write_text(BASE.replace("x0: [0.0, 0.01]", "x0: [0.0]"))
    assert main(["check", str(f), "--json"]) == 2
    assert json.loads(capsys.readouterr().out)["error"]["key"] == "masses[1].x0"


def test_stiffness_limits_along_the_mass_axes_are_the_1d_limits_when_decoupled():
    """A cartesian device with a diagonal mass and friction, the port on grounds and an
    axis-aligned plane: K_max along each axis is the 1-D exact limit of that axis's mass,
    friction and virtual damping (the other axis's stiffness kept: decoupled); with a
    virtual mass on a port link there is no such limit (None)."""
    from hapsim.analysis.loop import LoopModel
    from hapsim.analysis.stability import stability_limit
    text = """\
dimension: 2
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground}
links:
  - {name: w, kind: spring_damper, between: [hand, wall], stiffness: 200, damping: 0.8}
planes:
  - {name: p, normal: [0, 1], offset: 0.0, stiffness: 300, damping: 0.4}
device: {mass: [0.08, 0.2], friction: [0.3, 0.6], delay: 1}
"""
    chk = check_scene_nd(parse_scene_nd(text))
    m, b0, B = [0.08, 0.2], [0.3, 0.6], [0.8, 1.2]
    for i in range(2):
        e = chk.limit_directions[:, i]
        j = int(np.argmax(np.abs(e)))
        ref = stability_limit(LoopModel(mass=m[j], friction=b0[j], rate_hz=1000.0,
                                        delay=1), B[j])
        # each method puts a pole on |z| = 1 to within its eigenvalue round-off and
        # Brent's angle tolerance: the two limits differ by that over d rho / d K, twice
        from hapsim.analysis.loop_poles import spectral_radius
        from hapsim.analysis.ths import state_matrix
        l1 = LoopModel(mass=m[j], friction=b0[j], rate_hz=1000.0, delay=1)
        ln = MatrixLoop(mass=[[m[j]]], friction=[[b0[j]]], rate_hz=1000.0, delay=1)
        dz = eig_tol(state_matrix(ln, ref, B[j])) + BRENT_THETA
        tol = 2 * crossing_tol(lambda K: spectral_radius(l1, K, B[j]), ref, dz)
        assert chk.stiffness_limits[i] == pytest.approx(ref, rel=0, abs=tol)
    virt = text.replace("  - {name: wall, kind: ground}",
                        "  - {name: wall, kind: mass, mass: 0.01}")
    assert check_scene_nd(parse_scene_nd(virt)).stiffness_limits is None


def test_lockstep_loop_is_the_analysed_state_matrix():
    """The in-process loop (n-D engine + exact ZOH device + delay line) started from a
    displaced, moving handle follows the analysis's state matrix A^k s0 to round-off over
    300 samples, for a 2-D scene with a virtual mass at equilibrium at rest and linear
    links (the analysis is the engine's exact linear image there; Euclidean links are
    linearised, tested against their Jacobian above)."""
    from hapsim.analysis.scene_check import closed_loop_nd
    from hapsim.lockstep import LockstepND
    text = """\
dimension: 2
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: [0.0, 0.0]}
  - {name: bob, kind: mass, mass: 0.02, x0: [0.0, 0.0]}
links:
  - {name: w, kind: spring_damper, between: [hand, wall], stiffness: 150, damping: 0.6}
  - {name: e, kind: spring_damper, between: [hand, bob], stiffness: 120, damping: 0.05}
  - {name: g, kind: spring_damper, between: [bob, wall], stiffness: 60, damping: 0.02}
device: {mass: [[0.1, 0.02], [0.02, 0.15]], friction: [0.4, 0.3], delay: 2}
"""
    scene = parse_scene_nd(text)
    A, names = closed_loop_nd(scene)
    x0, v0 = np.array([0.002, -0.001]), np.array([0.01, 0.03])
    loop = LockstepND(scene, x0=x0, v0=v0)
    rec = loop.step(300, record=True)
    # the same start as a state of A: device (x, v), x_port[n-1], F delay line, the
    # virtual mass at rest (x[n], x[n-1] deviations 0)
    s = np.zeros(A.shape[0])
    s[:2], s[2:4] = x0, v0
    s[4:6] = x0 - v0 * scene.period
    lin, scale = [], 0.0
    for _ in range(300):
        lin.append(s[:2].copy())
        scale = max(scale, float(np.linalg.norm(s)))
        s = A @ s
    lin = np.array(lin)
    assert np.max(np.abs(lin)) > 1e-3
    # both paths iterate the same linear map 300 times, each with its own round-off
    # (tests/tolerance.py recurrence_tol: each step's error carried by the powers of A)
    assert np.max(np.abs(rec - lin)) <= 2 * recurrence_tol(A, 300, scale)


def _balanced_plane_scene(dim):
    """A port pressed on a tilted plane (always engaged for small motion) and held there
    by a spring to a ground placed so that the rest position is an equilibrium: a linear
    loop with anisotropic felt matrices."""
    u = np.ones(dim)
    u[0] = 0.3
    u /= np.linalg.norm(u)
    g = (-400 * 0.005 * u / 150).tolist()
    M = np.eye(dim) * 0.12 + 0.02
    return f"""\
dimension: {dim}
rate_hz: 1000
masses:
  - {{name: hand, kind: port}}
  - {{name: wall, kind: ground, x0: {g}}}
links:
  - {{name: w, kind: spring_damper, between: [hand, wall], stiffness: 150, damping: 0.6}}
planes:
  - {{name: p, normal: {u.tolist()}, offset: 0.005, stiffness: 400, damping: 0.2}}
device: {{mass: {M.tolist()}, friction: {[0.4, 0.3, 0.5][:dim]}, delay: 2}}
"""


@pytest.mark.parametrize("dim", [2, 3])
def test_lockstep_measured_felt_matrices_equal_the_prediction(dim):
    """Free responses of the lockstep loop (n records from n initial handle states),
    fitted by vector linear prediction (hapsim.analysis.pencil.fit_felt_nd): the measured felt
    stiffness and damping matrices equal check's prediction, and the measured poles the
    predicted ones. Measured tolerances (no closed bound covers the fit's least squares):
    the worst of dim 2 and 3 on x86-64 with OpenBLAS Haswell, Sandybridge and Prescott
    kernels and numba's generic target, times 1000 (round-off moves between CPUs by a
    few ulps times the problem's condition; a wrong prediction moves these by >= 1e-4)."""
    from hapsim.analysis.pencil import fit_felt_nd
    from hapsim.analysis.scene_check import closed_loop_nd
    from hapsim.lockstep import LockstepND
    scene = parse_scene_nd(_balanced_plane_scene(dim))
    # at rest: the ground is placed by a product of three numbers (the equilibrium up to
    # its round-off, ~1e-18 m measured), margin 1000
    assert np.max(np.abs(LockstepND(scene).step(200, record=True))) < measured(1.8e-18,
                                                                               1000)
    chk = check_scene_nd(scene)
    A, _ = closed_loop_nd(scene)
    rng = np.random.default_rng(dim)
    recs = [LockstepND(scene, x0=rng.uniform(-2e-3, 2e-3, dim),
                       v0=rng.uniform(-0.03, 0.03, dim)).step(300, record=True)
            for _ in range(dim)]
    fit = fit_felt_nd(recs, scene.device.mass, scene.period, A.shape[0] // dim)
    assert fit["residual"] < measured(1.1e-14, 1000)
    k, b = chk.render.felt_stiffness, chk.render.felt_damping
    assert np.max(np.abs(fit["felt_stiffness"] - k)) <= measured(1.2e-12, 1000) * np.max(
        np.abs(k))
    assert np.max(np.abs(fit["felt_damping"] - b)) <= measured(3.7e-12, 1000) * np.max(
        np.abs(b))
    assert np.max(np.abs(np.sort_complex(fit["rendered_poles"])
                         - np.sort_complex(chk.render.rendered_poles))) <= measured(1.8e-14,
                                                                                    1000)


@pytest.mark.parametrize("encoding", ["utf-8", "utf-8-sig", "utf-16", "utf-32"])
def test_an_nd_scene_file_is_read_as_the_1d_reader_reads_files(encoding, tmp_path):
    """The n-D reader takes a file through the 1-D reader's text and lines: any encoding
    the 1-D reader decodes is found to be 2-D (the dimension probe once looked for the
    bytes b'dimension', which a UTF-16 file does not hold) and reads to the same scene;
    an unknown key is named at its line as the 1-D reader names it."""
    from pathlib import Path

    from hapsim.scene import load_scene_nd, scene_dimension
    src = Path(__file__).resolve().parents[1] / "configs" / "pantograph_circle.yaml"
    text = src.read_text(encoding="utf-8")
    f = tmp_path / "scene.yaml"
    f.write_bytes(text.encode(encoding))
    assert scene_dimension(f) == 2
    got, want = load_scene_nd(f), load_scene_nd(src)
    assert (got.rate_hz, [m.name for m in got.masses]) == (want.rate_hz,
                                                          [m.name for m in want.masses])
    f.write_text("dimension: 2\nrate_hz: 1000\nmasses: []\n\"odd key\": 1\n", encoding="utf-8")
    with pytest.raises(ConfigError) as nd:
        load_scene_nd(f)
    g = tmp_path / "one.yaml"
    g.write_text("rate_hz: 1000\nmasses: []\n\"odd key\": 1\n", encoding="utf-8")
    with pytest.raises(ConfigError) as one:
        parse_scene(g.read_text(), str(g))
    assert (nd.value.line, nd.value.key) == (4, one.value.key) and one.value.line == 3
