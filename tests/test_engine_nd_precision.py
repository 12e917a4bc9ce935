"""The n-D engine in single precision (``engine: {precision: single}``): the scene key,
the float32 state, and its accuracy over long renders against independent
implementations: the shipped membrane's closed-form modal solution, and a plain numpy
float64 step on a pretensioned membrane of Euclidean links and on a 3-D grid mesh."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from hapsim.engine import Engine
from hapsim.errors import ConfigError
from hapsim.scene import parse_scene_nd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))

import make_nd_scenes as gen  # noqa: E402
from precision_nd import modal_membrane  # noqa: E402

BASE = "dimension: 2\nrate_hz: 1000\nmasses:\n  - {name: a, kind: mass, mass: 0.1}\n"


def test_precision_key_is_read_and_checked():
    """``engine: {precision: ...}``: double by default, single on request; a wrong value,
    an odd key or a non-mapping is refused naming the file, the line and the key."""
    assert parse_scene_nd(BASE).precision == "double"
    assert parse_scene_nd(BASE + "engine: {precision: single}\n").precision == "single"
    for extra, key, words in (("engine: {precision: half}\n", "engine.precision",
                               "valid choices: double, single"),
                              ("engine: {precison: single}\n", "engine.precison",
                               "valid keys: precision"),
                              ("engine: single\n", "engine", "must be a mapping")):
        with pytest.raises(ConfigError) as e:
            parse_scene_nd(BASE + extra, "s.yaml")
        msg = str(e.value)
        assert msg.startswith("s.yaml:5: ") and key in msg and words in msg, msg


def test_single_precision_is_refused_for_a_felt_scene():
    """A scene with a port (felt through a device) runs the exact double engine: single
    precision there is refused by the reader (file, line, key) and by the engine."""
    text = ("dimension: 2\nrate_hz: 1000\nmasses:\n  - {name: h, kind: port}\n"
            "  - {name: g, kind: ground}\nlinks:\n"
            "  - {kind: spring_damper, between: [h, g], stiffness: 100}\n"
            "device: {kind: cartesian, mass: 0.1}\n")
    with pytest.raises(ConfigError) as e:
        parse_scene_nd(text + "engine:\n  precision: single\n", "felt.yaml")
    assert str(e.value).startswith("felt.yaml:10: engine.precision: ") and \
        "without a port" in str(e.value)
    with pytest.raises(ConfigError, match="without a port"):
        Engine(parse_scene_nd(text), precision="single")


def test_the_engine_state_is_in_the_chosen_precision():
    """The state and parameters are float64 by default (the haptic loops' exact engine)
    and float32 in single precision; the argument overrides the scene; a port's force is
    given as float64 either way."""
    text = BASE + ("  - {name: g, kind: ground, x0: [0.01, 0]}\nlinks:\n"
                   "  - {kind: spring_damper, between: [a, g], stiffness: 10, length: 0.005}\n")
    assert Engine(parse_scene_nd(text)).x.dtype == np.float64
    single = parse_scene_nd(text + "engine: {precision: single}\n")
    eng = Engine(single)
    assert eng.precision == "single"
    for name in ("_X", "_XP", "f", "t2m", "eu_k", "eu_z", "eu_rest", "eu_lprev", "W"):
        assert getattr(eng, name).dtype == np.float32, name
    assert Engine(single, precision="double").x.dtype == np.float64
    with pytest.raises(ConfigError, match="valid choices: double, single"):
        Engine(single, precision="half")
    eng.step(100)
    assert 0 < abs(eng.x[0, 0]) < 0.01 and eng.x.dtype == np.float32
    # the live loop names the float32 rows in its context only as float32 (a context
    # built for the double engine refuses them, never misreads them)
    from hapsim.kernels.pointers import address
    x, v = eng.step_rows
    assert x.dtype == v.dtype == np.float32 and x.shape == v.shape == (2, 2)
    with pytest.raises(ValueError):
        address(x, np.float64)
    assert address(x, np.float32) == x.ctypes.data


def test_single_precision_membrane_follows_the_closed_form():
    """The shipped membrane (length-0 links) for 0.5 s at 44.1 kHz: the listened mass's
    position across the plane equals the closed-form modal solution to 2e-5 of its
    largest value in single precision (measured 4.8e-6 over 1 s: tools/precision_nd.py)
    and to 1e-10 in double; listening in single precision (the compiled loop) gives the
    same samples as stepping."""
    scene = parse_scene_nd(gen.membrane())
    n = 22050
    ref = modal_membrane(n)
    li, lj = gen.MEMBRANE_LISTEN
    k = [m.name for m in scene.masses].index(f"m{li}_{lj}")
    for prec, tol in (("double", 1e-10), ("single", 2e-5)):
        eng = Engine(scene, precision=prec)
        z = np.empty(n)
        for s in range(n):
            eng.step()
            z[s] = eng.x[2, k]
        assert np.max(np.abs(z - ref)) <= tol * np.max(np.abs(ref)), prec
    out = np.zeros((400, 1))
    Engine(scene, precision="single").listen(out, [2], [k], [False], [1.0])
    assert np.array_equal(out[:, 0], z[:400].astype(np.float64))


def _plain_steps(X, XP, t2m, i1, i2, K, z, L, n, listen):
    """Plain numpy float64, every link at once: the Euclidean law, forces summed with
    np.add.at; returns ``X[listen]`` after each sample."""
    X, XP = X.copy(), XP.copy()
    out = []
    for s in range(n):
        d, dp = X[:, i1] - X[:, i2], XP[:, i1] - XP[:, i2]
        ln, lp = np.sqrt((d * d).sum(0)), np.sqrt((dp * dp).sum(0))
        F = (K * (ln - L) + z * (ln - lp)) / ln * d
        f = np.zeros_like(X)
        for ax in range(3):
            np.add.at(f[ax], i1, -F[ax])
            np.add.at(f[ax], i2, F[ax])
        X, XP = 2 * X - XP + t2m * f, X
        out.append(X[listen])
    return np.array(out)


def test_single_precision_euclidean_mesh_against_a_plain_double_step():
    """The membrane with Euclidean links of rest length h / 2 (pretensioned; the links'
    lengths computed from absolute in-plane positions up to 0.13 m, where float32 keeps
    ~1e-8 m) for 0.2 s: the listened mass's transverse position agrees with a plain
    numpy double-precision step to 1e-3 of its largest value in single precision
    (measured 2.2e-4 over 1 s against the double engine) and to 1e-9 in double."""
    text = gen.membrane().replace(f"damping: {gen.MEMBRANE_B:g}}}",
                                  f"damping: {gen.MEMBRANE_B:g}, length: "
                                  f"{gen.MEMBRANE_H / 2:g}}}")
    scene = parse_scene_nd(text)
    names = [m.name for m in scene.masses]
    i1 = np.array([names.index(lk.m1) for lk in scene.links])
    i2 = np.array([names.index(lk.m2) for lk in scene.links])
    T = scene.period
    K = np.array([lk.stiffness for lk in scene.links])
    z = np.array([lk.damping / T for lk in scene.links])
    L = np.array([lk.length for lk in scene.links])
    t2m = np.array([T * T / m.mass if m.kind == "mass" else 0.0 for m in scene.masses])
    X0 = np.array([m.x0 for m in scene.masses]).T
    V0 = np.array([m.v0 for m in scene.masses]).T
    li, lj = gen.MEMBRANE_LISTEN
    k = names.index(f"m{li}_{lj}")
    n = 8820
    ref = _plain_steps(X0, X0 - T * V0, t2m, i1, i2, K, z, L, n, (2, k))
    for prec, tol in (("double", 1e-9), ("single", 1e-3)):
        eng = Engine(scene, precision=prec)
        got = np.empty(n)
        for s in range(n):
            eng.step()
            got[s] = eng.x[2, k]
        assert np.max(np.abs(got - ref)) <= tol * np.max(np.abs(ref)), prec


def _grid_scene(nx, ny, nz, seed=0):
    """A 3-D grid of 1 g masses 1 cm apart joined to their +x, +y, +z neighbours by
    Euclidean links (K = 100 N/m, B = 0.001 N s/m, rest 1 cm), the face z = 0 held,
    every other mass displaced at random by up to 1 mm; at 44.1 kHz, in single
    precision."""
    rng = np.random.default_rng(seed)
    lines = ["dimension: 3", "rate_hz: 44100", "engine: {precision: single}", "masses:"]
    idx = {}
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                x = np.array([i, j, k]) * 0.01
                if k:
                    x = x + rng.uniform(-1e-3, 1e-3, 3)
                    lines.append(f"  - {{name: m{len(idx)}, kind: mass, mass: 0.001, "
                                 f"x0: {x.tolist()}}}")
                else:
                    lines.append(f"  - {{name: m{len(idx)}, kind: ground, x0: {x.tolist()}}}")
                idx[i, j, k] = len(idx)
    lines.append("links:")
    for (i, j, k), a in idx.items():
        for d in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
            b = idx.get((i + d[0], j + d[1], k + d[2]))
            if b is not None:
                lines.append(f"  - {{kind: spring_damper, between: [m{a}, m{b}], "
                             "stiffness: 100, damping: 0.001, length: 0.01}")
    return parse_scene_nd("\n".join(lines) + "\n")


def test_single_precision_grid_mesh_keeps_the_velocity_form_accuracy():
    """The benchmark's kind of mesh (a 6 x 6 x 4 grid, absolute coordinates up to 0.05
    m, motion ~1 mm per 200 samples at 44.1 kHz): after 200 samples every single-
    precision position is within 1e-3 of the motion of a plain numpy double-precision
    step. (Measured 2e-5; the position form ``x+ = 2 x - x- + t2m f`` rounded to float32
    every sample, which the kernels do not use in single precision, is 2e-2 away: the
    rounding of a position is a velocity error there, integrated twice.)"""
    scene = _grid_scene(6, 6, 4)
    names = [m.name for m in scene.masses]
    i1 = np.array([names.index(lk.m1) for lk in scene.links])
    i2 = np.array([names.index(lk.m2) for lk in scene.links])
    T = scene.period
    t2m = np.array([T * T / m.mass if m.kind == "mass" else 0.0 for m in scene.masses])
    X0 = np.array([m.x0 for m in scene.masses]).T
    n = 200
    K = np.full(i1.size, 100.0)
    ref = _plain_steps(X0, X0, t2m, i1, i2, K, np.full(i1.size, 0.001 / T),
                       np.full(i1.size, 0.01), n, (slice(None), slice(None)))[-1]
    eng = Engine(scene)
    assert eng.precision == "single"
    eng.step(n)
    motion = np.max(np.abs(ref - X0))
    assert motion > 5e-4
    # float32 round-off integrated 200 samples: measured 1.6e-5 * motion (generic the
    # same), margin 62
    assert np.max(np.abs(eng.x - ref)) <= 1e-3 * motion
