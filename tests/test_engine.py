"""The numba engine against closed forms, conservation laws and a plain-Python reference."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from hapsim.engine import Engine
from hapsim.errors import ConfigError
from hapsim.scene import Device, Link, Mass, Scene, load_scene, parse_scene
from tolerance import measured, recurrence_tol, rel_tol

pytestmark = pytest.mark.numerical

# Measured tolerances below: the worst seen with numba's host target and
# NUMBA_CPU_NAME=generic, OpenBLAS Haswell and Prescott kernels (identical here: the
# engine's kernels are compiled without fast-math, so no FMA contraction), margin 1000
# (a wrong scheme or force law moves these by >= 1e-6).

RATE = 1000.0
T = 1.0 / RATE


def oscillator(stiffness: float, mass: float = 0.1, x0: float = 0.01, damping: float = 0.0) -> Scene:
    return Scene(rate_hz=RATE,
                 masses=(Mass("anchor", "ground"), Mass("bob", "mass", mass, x0)),
                 links=(Link("spring", "spring_damper", "bob", "anchor", stiffness, damping),))


def closed_form_oscillator(n: int, stiffness: float, mass: float, x0: float) -> np.ndarray:
    """Exact solution of x[k+1] - 2 x[k] + x[k-1] = -K T^2/m x[k], x[0] = x[-1] = x0.

    With cos(theta) = 1 - K T^2 / (2 m) (Florens-Voda-Urma eq. 2), x[k] = A cos(k theta)
    + C sin(k theta), A = x0, C = x0 (cos theta - 1) / sin theta.
    """
    theta = math.acos(1.0 - stiffness * T * T / (2.0 * mass))
    k = np.arange(n + 1)
    c = x0 * (math.cos(theta) - 1.0) / math.sin(theta)
    return x0 * np.cos(k * theta) + c * np.sin(k * theta)


def closed_form_tol(n: int, stiffness: float, mass: float, amplitude: float) -> float:
    """Round-off bound of the engine's run against :func:`closed_form_oscillator`: the
    recurrence's (tests/tolerance.py recurrence_tol on its 2 x 2 companion map) plus the
    closed form's own: theta = acos(c) is off by rel_tol(3) / sin(theta) (acos near its
    ends), and k theta by k times that: a phase error of n dtheta on the amplitude."""
    c = 1.0 - stiffness * T * T / (2.0 * mass)
    A = np.array([[2.0 * c, -1.0], [1.0, 0.0]])
    theta = math.acos(c)
    # the state (x[k], x[k-1]) is at most sqrt(2) amplitude
    return (recurrence_tol(A, n, math.sqrt(2) * amplitude, ops=3)
            + n * rel_tol(3) / math.sin(theta) * amplitude)


@pytest.mark.parametrize("stiffness", [10.0, 1000.0, 1.0e5, 3.9e5])
def test_oscillator_follows_eq2_closed_form(stiffness):
    mass, x0, n = 0.1, 0.01, 20000
    _, x = Engine(oscillator(stiffness, mass, x0)).run(n, ["bob"])
    expected = closed_form_oscillator(n, stiffness, mass, x0)
    amplitude = np.max(np.abs(expected))
    assert np.max(np.abs(x[:, 0] - expected)) < closed_form_tol(n, stiffness, mass, amplitude)


def test_oscillator_eigenfrequency_eq2_fitted():
    """Fit w from the trajectory (least squares over all samples) and check eq. 2 (to
    3.3e-14 relative measured, margin 1000)."""
    mass, stiffness, n = 0.1, 1000.0, 4000
    _, x = Engine(oscillator(stiffness, mass)).run(n, ["bob"])
    y = x[:, 0]
    # x[k+1] + x[k-1] = 2 cos(wT) x[k] holds for the exact discrete oscillator: least squares
    # over the whole record estimates cos(wT) from thousands of samples.
    c = np.dot(y[2:] + y[:-2], y[1:-1]) / (2.0 * np.dot(y[1:-1], y[1:-1]))
    w_measured = math.acos(c) / T
    w_theory = math.acos(1.0 - stiffness * T * T / (2.0 * mass)) / T
    assert abs(w_measured - w_theory) < measured(3.3e-14, 1000) * w_theory
    # ... and it is not the continuous sqrt(K/m): the scheme's frequency warping is visible.
    assert abs(w_theory - math.sqrt(stiffness / mass)) > 1e-4 * w_theory


def zero_crossings(y: np.ndarray) -> np.ndarray:
    """Times of the sign changes of ``y`` [samples], each found as the root of the cubic
    through the four samples around it (Lagrange interpolation, Newton from the linear
    guess). Uses nothing of the scheme: only that the sampled curve is smooth."""
    k = np.nonzero((y[1:-2] > 0) != (y[2:-1] > 0))[0] + 1     # change between k and k+1
    p = np.stack([y[k - 1], y[k], y[k + 1], y[k + 2]])          # at u = -1, 0, 1, 2
    nodes = np.array([-1.0, 0.0, 1.0, 2.0])
    u = y[k] / (y[k] - y[k + 1])
    for _ in range(8):
        lag = np.ones((4, u.size))
        dlag = np.zeros((4, u.size))
        for i in range(4):
            for j in range(4):
                if j != i:
                    term = (u - nodes[j]) / (nodes[i] - nodes[j])
                    dlag[i] = dlag[i] * term + lag[i] / (nodes[i] - nodes[j])
                    lag[i] = lag[i] * term
        u = u - (lag * p).sum(0) / (dlag * p).sum(0)
    assert np.all((u >= 0) & (u <= 1))
    return k + u


@pytest.mark.parametrize("stiffness", [300.0, 1000.0, 3000.0])
def test_oscillator_eigenfrequency_eq2_from_zero_crossings(stiffness):
    """An independent measurement: the half period is the mean spacing of the zero
    crossings of the simulated trajectory (least-squares slope over ~10^4 of them), not a
    re-fit of the recurrence; w = pi / (half period) must satisfy eq. 2 (to 1.8e-14
    relative measured over the three stiffnesses, margin 1000)."""
    mass, n = 0.1, 200_000
    _, x = Engine(oscillator(stiffness, mass)).run(n, ["bob"])
    tc = zero_crossings(x[:, 0])
    assert tc.size > 1000
    half_period = np.polyfit(np.arange(tc.size), tc, 1)[0] * T
    w_measured = math.pi / half_period
    w_eq2 = math.acos(1.0 - stiffness * T * T / (2.0 * mass)) / T
    assert abs(w_measured - w_eq2) < measured(1.8e-14, 1000) * w_eq2
    # the measurement resolves the scheme's warping: it is not the continuous sqrt(K/m)
    w_cont = math.sqrt(stiffness / mass)
    assert abs(w_measured - w_cont) > 1e3 * abs(w_measured - w_eq2)


@pytest.mark.parametrize("factor,grows", [(0.999, False), (1.001, True)])
def test_centred_difference_limit_4m_over_T2(factor, grows):
    mass, x0 = 0.1, 0.01
    n = 2000 if grows else 20000  # growth of |z| = 1.065 per sample overflows past ~11000
    k_limit = 4.0 * mass / T**2
    _, x = Engine(oscillator(factor * k_limit, mass, x0)).run(n, ["bob"])
    peak = np.max(np.abs(x[:, 0]))
    if grows:
        assert peak > 1e6 * x0
    else:
        # bounded by |A| + |C| of the closed form
        theta = math.acos(1.0 - factor * k_limit * T * T / (2.0 * mass))
        bound = x0 * (1.0 + abs((math.cos(theta) - 1.0) / math.sin(theta)))
        assert peak <= bound + closed_form_tol(n, factor * k_limit, mass, bound)


def test_damped_oscillator_matches_pole_closed_form():
    """x[k] = a p1^k + c p2^k with p1, p2 the roots of
    z^2 - (2 - (K T^2 + B T)/m) z + (1 - B T / m) (the scheme of
    docs/design.md, 'The scheme', in z)."""
    mass, stiffness, damping, x0, n = 0.1, 1000.0, 0.5, 0.01, 3000
    _, x = Engine(oscillator(stiffness, mass, x0, damping)).run(n, ["bob"])
    p1, p2 = np.roots([1.0, -(2.0 - (stiffness * T * T + damping * T) / mass), 1.0 - damping * T / mass])
    # x[0] = x0 and x[-1] = x0 (released at rest)
    a, c = np.linalg.solve(np.array([[1.0, 1.0], [1.0 / p1, 1.0 / p2]]), np.array([x0, x0]))
    k = np.arange(n + 1)
    expected = (a * p1**k + c * p2**k).real
    assert abs(p1) < 1.0
    assert np.max(np.abs(x[:, 0] - expected)) < measured(2.6e-13, 1000) * x0


def random_network(rng: np.random.Generator, n_mass: int = 8, n_links: int = 14,
                   with_fixed: bool = True) -> Scene:
    """Random masses and links of every kind; with ``with_fixed``, also a ground, a port and
    a switching contact that is engaged and released by construction (see below)."""
    masses = [Mass(f"m{i}", "mass", float(rng.uniform(0.01, 1.0)), float(rng.normal(0, 0.01)),
                   float(rng.normal(0, 0.1))) for i in range(n_mass)]
    if with_fixed:
        masses += [Mass("g", "ground", 0.0, float(rng.normal(0, 0.01))), Mass("p", "port")]
    names = [m.name for m in masses]
    links = []
    for j in range(n_links):
        a, b = rng.choice(len(names), 2, replace=False)
        kind = "contact" if j % 3 == 2 else "spring_damper"
        links.append(Link(f"l{j}", kind, names[a], names[b], float(rng.uniform(0, 500.0)),
                          float(rng.uniform(0, 0.5)), float(rng.normal(0, 0.005)) if kind == "contact" else 0.0))
    if with_fixed:
        # A bob released at +1 cm on a spring to its own wall at 0, with a contact to that
        # wall acting while bob < 0: it swings through 0 every half period (~31 samples:
        # w ~ 100 rad/s on the positive side, ~118 on the negative one), so the contact
        # engages and releases several times in any run of 100 samples or more, whatever
        # the seed. Nothing random is linked to it.
        masses += [Mass("wall", "ground", 0.0, 0.0), Mass("bob", "mass", 0.1, 0.01)]
        links += [Link("bob_spring", "spring_damper", "bob", "wall", 1000.0, 0.001),
                  Link("bob_contact", "contact", "wall", "bob", 400.0, 0.002, 0.0)]
    return Scene(rate_hz=RATE, masses=tuple(masses), links=tuple(links),
                 device=Device(mass=0.1) if with_fixed else None)


def contact_switches(scene: Scene, x: np.ndarray) -> dict[str, tuple[int, int]]:
    """(engagements, releases) of each contact, from the gate ``x2 - x1 < threshold``
    recomputed on a trajectory ``x`` (rows: samples, columns: masses in scene order).

    The force of sample s is computed from row s, so rows 0 .. n-1 give the gates used."""
    out = {}
    for lk in scene.links:
        if lk.kind != "contact":
            continue
        i1, i2 = scene.index(lk.m1), scene.index(lk.m2)
        gate = (x[:-1, i2] - x[:-1, i1]) < lk.threshold
        out[lk.name] = (int(np.sum(~gate[:-1] & gate[1:])), int(np.sum(gate[:-1] & ~gate[1:])))
    return out


def reference_run(scene: Scene, n: int, port_positions=None) -> np.ndarray:
    """Plain-Python CORDIS-ANIMA, written from docs/design.md, 'The scheme', independently of
    the kernels."""
    T_ = scene.period
    names = [m.name for m in scene.masses]
    x = {m.name: m.x0 for m in scene.masses}
    xp = {m.name: m.x0 - (m.v0 * T_ if m.kind == "mass" else 0.0) for m in scene.masses}
    rows = [[x[nm] for nm in names]]
    for s in range(n):
        if port_positions is not None:
            for m in scene.masses:
                if m.kind == "port":
                    x[m.name] = port_positions[s]
        force = {nm: 0.0 for nm in names}
        for lk in scene.links:
            x1, x2, x1p, x2p = x[lk.m1], x[lk.m2], xp[lk.m1], xp[lk.m2]
            rest = 0.0
            if lk.kind == "contact":
                if not (x2 - x1 < lk.threshold):
                    continue
                rest = lk.threshold  # spring measured from the threshold: continuous force
            f = lk.stiffness * (x1 - x2 + rest) + lk.damping * ((x1 - x2) - (x1p - x2p)) / T_
            force[lk.m1] -= f
            force[lk.m2] += f
        for m in scene.masses:
            if m.kind == "mass":
                new = 2 * x[m.name] - xp[m.name] + T_ * T_ * force[m.name] / m.mass
                xp[m.name], x[m.name] = x[m.name], new
            else:
                xp[m.name] = x[m.name]
        rows.append([x[nm] for nm in names])
    return np.array(rows)


@pytest.mark.parametrize("seed", range(6))
def test_engine_equals_plain_python_reference(seed):
    rng = np.random.default_rng(seed)
    scene = random_network(rng)
    n = 400
    _, got = Engine(scene).run(n)
    want = reference_run(scene, n)
    scale = np.max(np.abs(want))
    assert np.max(np.abs(got - want)) <= measured(1.4e-14, 1000) * scale
    # contacts really switched during the run, so both branches of the gate were compared:
    # at least one contact engaged and released (the bob's does by construction)
    switches = contact_switches(scene, got)
    assert any(on >= 1 and off >= 1 for on, off in switches.values()), switches
    assert min(switches["bob_contact"]) >= 5, switches      # 400 samples: ~6 cycles


def test_port_step_equals_reference_with_driven_port():
    rng = np.random.default_rng(42)
    scene = random_network(rng)
    n = 300
    drive = 0.01 * np.sin(np.arange(n) * 0.05)
    eng = Engine(scene)
    rows = [eng.x[0].copy()]
    forces = []
    for s in range(n):
        forces.append(eng.port_step(drive[s]))
        rows.append(eng.x[0].copy())
    want = reference_run(scene, n, drive)
    got = np.array(rows)
    assert np.max(np.abs(got - want)) <= measured(5.5e-15, 1000) * np.max(np.abs(want))
    # the port force is the sum of the link forces on the port at that sample
    p = scene.index("p")
    assert got[1:, p] == pytest.approx(drive, abs=0)
    assert np.all(np.isfinite(forces))


def test_port_force_is_minus_K_x_minus_B_v():
    scene = parse_scene("""
rate_hz: 1000
masses: [{name: hand, kind: port}, {name: wall, kind: ground}]
links: [{kind: spring_damper, between: [hand, wall], stiffness: 2000, damping: 3}]
device: {mass: 0.1}
""")
    eng = Engine(scene)
    eng.port_step(0.001)
    f = eng.port_step(0.003)
    # K x + B (x - x_prev) / T: 5 roundings on each side, condition 1 (same signs)
    assert f == pytest.approx(-2000 * 0.003 - 3 * (0.003 - 0.001) / 1e-3, rel=2 * rel_tol(5))


def test_internal_links_conserve_momentum():
    rng = np.random.default_rng(7)
    scene = random_network(rng, n_mass=12, n_links=30, with_fixed=False)
    n = 2000
    _, x = Engine(scene).run(n)
    m = np.array([ms.mass for ms in scene.masses])
    momentum = (x[1:] - x[:-1]) @ m / scene.period
    assert np.ptp(momentum) <= measured(1.5e-16, 1000) * np.max(np.abs(x)) * m.sum() / \
        scene.period


def test_undamped_string_keeps_discrete_energy():
    base = load_scene("configs/string.yaml")
    links = tuple(Link(lk.name, lk.kind, lk.m1, lk.m2, lk.stiffness, 0.0, lk.threshold)
                  for lk in base.links if lk.kind == "spring_damper"
                  # the string alone: not the finger's hold spring on the port (issue 31)
                  and "hand" not in (lk.m1, lk.m2))
    masses = tuple(Mass(m.name, m.kind, m.mass, 0.001 * math.sin(math.pi * i / 51) if m.kind == "mass" else 0.0,
                        0.0) for i, m in enumerate(base.masses) if m.kind != "port")
    eng = Engine(Scene(rate_hz=base.rate_hz, masses=masses, links=links))
    e0 = eng.energy()
    energies = []
    for _ in range(50):
        eng.step(2000)
        energies.append(eng.energy())
    assert e0 > 0
    assert max(abs(e - e0) for e in energies) <= measured(1.8e-13, 1000) * e0


def test_target_link_must_be_calibrated_first():
    scene = parse_scene("""
rate_hz: 1000
masses: [{name: hand, kind: port}, {name: wall, kind: ground}]
links: [{name: felt, kind: spring_damper, between: [hand, wall], target: {k: 1000, b: 3}}]
device: {mass: 0.1}
""", "felt.yaml")
    with pytest.raises(ConfigError, match=r"felt.yaml:4: links.felt: .*calibrate"):
        Engine(scene)
    eng = Engine(scene.with_link("felt", stiffness=900.0, damping=2.0))
    # measured 0 (generic 0): exact on both targets
    assert eng.port_step(0.001) == pytest.approx(-0.9 - 2.0)


def test_kernel_chosen_by_link_kinds():
    from hapsim.kernels import cordis
    assert Engine(oscillator(10.0))._kernel is cordis.run_sd
    string = Engine(load_scene("configs/string.yaml"))
    assert string._kernel is cordis.run_sd_contact


def test_record_unknown_name_lists_masses():
    with pytest.raises(ConfigError, match="no mass named 'nope'; masses are: anchor, bob"):
        Engine(oscillator(10.0)).run(3, ["nope"])


def test_port_step_without_port_is_an_error_and_changes_nothing():
    """Without a port there is no device position to set: refuse, never write x[-1]."""
    eng = Engine(oscillator(1000.0))
    before = eng.x[0].copy()
    with pytest.raises(ConfigError, match=r"masses: the scene has no port"):
        eng.port_step(0.5)
    np.testing.assert_array_equal(eng.x[0].copy(), before)   # the bob (last mass) untouched
    assert eng.sample == 0
    with pytest.raises(ConfigError, match="no port"):
        eng.set_port_position(0.5)
    assert np.array_equal(eng.port_force, [0.0])          # (n,) = (1,) zeros without a port


# ---------------------------------------------------------------- compile once, kernels apart

def _exercise(eng: Engine) -> None:
    """Every way the engine calls its kernel: step, run with and without a record, port_step."""
    eng.step(3)
    eng.run(5)
    eng.run(4, [eng.names[-1]])
    if eng.scene.port is not None:
        eng.port_step(0.0005)


@pytest.mark.parametrize("integrator", ["centred", "symplectic_euler", "exact"])
def test_kernels_compile_once_per_set_of_link_kinds_not_per_scene(integrator):
    """Two different scenes (sizes, values, topology, chain or not) with the same link kinds
    share one compiled kernel: the numba dispatcher's signature count does not grow."""
    import dataclasses

    from hapsim.bench.cost import string_scene

    def scheme(sc):
        return dataclasses.replace(sc, integrator=integrator)

    pairs = [(oscillator(1000.0), string_scene(n=37, K=1500.0))]        # spring_dampers only
    if integrator != "exact":                                           # exact: no contacts
        pairs.append((load_scene("configs/string.yaml"),                # springs + contacts
                      random_network(np.random.default_rng(3))))
        only = lambda sc: dataclasses.replace(                          # noqa: E731
            sc, links=tuple(lk for lk in sc.links if lk.kind == "contact"))
        pairs.append((only(load_scene("configs/string.yaml")),         # contacts only
                      only(random_network(np.random.default_rng(4)))))
    for first, second in pairs:
        a, b = Engine(scheme(first)), Engine(scheme(second))
        assert a.scene.kinds == b.scene.kinds and len(a.names) != len(b.names)
        assert a._kernel is b._kernel
        _exercise(a)                      # compiles (or loads from the cache) if needed
        compiled = len(a._kernel.signatures)
        assert compiled >= 1
        _exercise(b)
        assert len(b._kernel.signatures) == compiled, b._kernel.signatures


KERNEL_DIR = Path(__file__).resolve().parents[1] / "hapsim" / "kernels"


def imported_modules(source: str, module: str, tree=None) -> set[str]:
    """Absolute names of every module ``source`` (the module ``module``) imports, at any
    depth (function-level imports included), relative imports resolved; ``tree``, when
    given, is ``ast.parse(source)`` already made."""
    package = module.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(source) if tree is None else tree):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module
            out.add(stem)
            out.update(f"{stem}.{alias.name}" for alias in node.names)
    return out


def _api_imports(names: set[str]) -> set[str]:
    return {n for n in names if (n == "hapsim" or n.startswith("hapsim."))
            and not (n == "hapsim.kernels" or n.startswith("hapsim.kernels."))}


def test_import_contract_scanner_catches_api_imports():
    """The scanner below would see a kernel importing the API layer, in any spelling."""
    for bad in ("from hapsim.scene import Scene", "import hapsim.engine",
                "from .. import engine", "from ..commands import simulate",
                "def f():\n    from hapsim.host import loop\n", "import hapsim"):
        assert _api_imports(imported_modules(bad, "hapsim.kernels.cordis")), bad
    assert not _api_imports(imported_modules("from . import cordis\nimport numba",
                                             "hapsim.kernels.schemes"))


def test_kernels_import_nothing_from_the_api_layer():
    """docs/design.md, rule 3 (poliastro's core/ import contract): hapsim/kernels/* import only
    the standard library, numpy, numba, scipy and each other, never hapsim.engine,
    hapsim.scene, hapsim.commands, hapsim.host, hapsim.analysis, ..."""
    files = sorted(KERNEL_DIR.glob("*.py"))
    assert {f.name for f in files} >= {"__init__.py", "cordis.py", "schemes.py"}
    for f in files:
        module = "hapsim.kernels" + ("" if f.stem == "__init__" else f".{f.stem}")
        if f.stem == "__init__":
            module += ".__init__"
        bad = _api_imports(imported_modules(f.read_text(), module))
        assert not bad, f"{f.name} imports the API layer: {sorted(bad)}"


def test_public_read_accessors_share_the_engines_arrays():
    """What the live sound and the contact replay read of an engine is public and is the
    engine's own state: the multi-rate pack's positions are the kernel pack's, a step seen
    through one is seen through the other and through ``positions``; the port index is the
    scene's; a plain engine is not a corrected one."""
    root = Path(__file__).resolve().parents[1]
    eng = Engine(load_scene(root / "configs" / "audio_string.yaml"))
    pack = eng.multirate_pack
    assert pack is not None and len(pack.args) == 19
    assert pack.args[0] is eng.kernel_pack.state[0] and pack.args[1] is eng.kernel_pack.state[1]
    assert pack.head[0] == eng.substeps and pack.head[3] == eng.port_index
    assert eng.port_index == eng.scene.index(eng.scene.port.name)
    before = eng.x[0].copy()
    eng.port_step(1e-3)
    assert np.array_equal(pack.args[0], eng.x[0].copy())
    assert not np.array_equal(before, eng.x[0].copy())
    assert np.array_equal(pack.args[1], eng.xp[0].copy())   # one audio sub-step ago
    assert not eng.corrected
    plain = Engine(load_scene(root / "configs" / "wall.yaml"))
    assert plain.multirate_pack is None and plain.port_index == 0
