"""One engine for every dimension (issue 30 item 1): :class:`hapsim.engine.Engine` takes a
1-D, 2-D or 3-D scene and answers one API, each dimension on its own kernels.

Held here: the API's shapes on every shipped dimension, the ``n = 1`` float shorthand
against the array form (bit for bit, over seeded random 1-D networks), live changes
through :meth:`Engine.cells` against an engine built with the changed values (every
dimension, seeded random networks), the same wall felt through a 1-D and a 2-D scene
within the derived round-off of the link law, and no ``engine_nd`` module left."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from hapsim.engine import Engine
from hapsim.errors import ConfigError
from hapsim.scene import load_scene, load_scene_nd, parse_scene, parse_scene_nd
from test_engine import random_network
from test_engine_nd import random_scene
from tolerance import rel_tol

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"


@pytest.mark.parametrize("name", ["wall.yaml", "audio_string.yaml", "oscillator.yaml",
                                  "pantograph_wall.yaml", "delta_sphere.yaml"])
def test_one_api_on_every_dimension(name):
    """``Engine(scene)`` of a shipped 1-D, 2-D and 3-D scene: an :class:`Engine` whose
    positions are ``(n, N)`` (``positions`` their transpose), the port's position and
    force ``(n,)``, ``position(name)`` a column of ``x``, ``sample`` counting steps."""
    path = CONFIGS / name
    scene = load_scene_nd(path) if "dimension" in path.read_text() else load_scene(path)
    eng = Engine(scene)
    n, N = scene.dimension, len(scene.masses)
    assert isinstance(eng, Engine) and eng.dim == n and len(eng.names) == N
    assert eng.x.shape == eng.xp.shape == (n, N)
    assert np.array_equal(eng.positions, eng.x.T) and eng.positions.shape == (N, n)
    assert np.array_equal(eng.previous_positions, eng.xp.T)
    for i, nm in enumerate(eng.names):
        assert np.array_equal(eng.position(nm), eng.x[:, i])
    assert eng.port_force.shape == (n,)
    if eng.port is None:
        assert eng.port_index == -1 and np.array_equal(eng.port_force, np.zeros(n))
        eng.step(3)
    else:
        p = eng.x[:, eng.port_index] + 1e-3
        eng.set_port_position(p, at_rest=True)
        assert np.array_equal(eng.xp[:, eng.port_index], p)      # at rest: no velocity
        f = eng.port_step(p)
        assert f.shape == (n,) and np.array_equal(f, eng.port_force)
        eng.step(2)
    assert eng.sample == 3


@pytest.mark.parametrize("seed", range(6))
def test_the_float_shorthand_is_the_array_form(seed):
    """For n = 1 a float position in gives a float force out, bit for bit the ``(1,)``
    array form's, over 120 samples of a random network with contacts and a port."""
    rng = np.random.default_rng(seed)
    scene = random_network(rng)
    a, b = Engine(scene), Engine(scene)
    drive = 0.01 * np.sin(np.arange(120) * rng.uniform(0.01, 0.2))
    for x in drive:
        fa = a.port_step(float(x))
        fb = b.port_step(np.array([x]))
        assert type(fa) is float and fb.shape == (1,) and fb[0] == fa
    assert np.array_equal(a.x, b.x) and np.array_equal(a.xp, b.xp)


@pytest.mark.parametrize("seed", range(4))
def test_port_step_after_a_multi_sample_step_advances_one_sample(seed):
    """``step(n)`` then ``port_step`` advances n + 1 samples, as n single steps and the
    port set then stepped once do (the 1-D step leaves its context at one sample), bit for
    bit, over random networks and step counts."""
    rng = np.random.default_rng(300 + seed)
    scene = random_network(rng)
    a, b = Engine(scene), Engine(scene)
    for _ in range(5):
        n, x = int(rng.integers(0, 40)), float(rng.normal(0, 0.005))
        a.step(n)
        f = a.port_step(x)
        for _ in range(n):
            b.step(1)
        b.set_port_position(x)
        b.step(1)
        assert f == b.port_force[0] and np.array_equal(a.x, b.x) and a.sample == b.sample


def _one_d_changed(scene, link, K, B):
    """``scene`` with ``link``'s (K, B) replaced (1-D)."""
    return scene.with_link(link, stiffness=K, damping=B)


@pytest.mark.parametrize("seed", range(4))
def test_live_changes_equal_an_engine_built_with_them_1d(seed):
    """``set_link`` and ``set_mass`` between samples (through :meth:`Engine.cells`) give,
    bit for bit, the engine built with the new values from the start (random networks)."""
    rng = np.random.default_rng(100 + seed)
    scene = random_network(rng, with_fixed=False)
    lk = scene.links[int(rng.integers(len(scene.links)))]
    K, B = float(rng.uniform(1, 400)), float(rng.uniform(0, 0.4))
    m = float(rng.uniform(0.05, 2.0))
    live = Engine(scene)
    live.set_link(lk.name, K, B)
    live.set_mass("m0", m)
    masses = tuple(dataclasses.replace(x, mass=m) if x.name == "m0" else x
                   for x in scene.masses)
    built = Engine(dataclasses.replace(_one_d_changed(scene, lk.name, K, B), masses=masses))
    live.step(150)
    built.step(150)
    assert np.array_equal(live.x, built.x)


@pytest.mark.parametrize("dim,seed", [(2, 0), (2, 1), (3, 2), (3, 3)])
def test_live_changes_equal_an_engine_built_with_them_nd(dim, seed):
    """The same on random n-D meshes: a linear link's (K, B) and a mass changed live
    equal, bit for bit, the scene written with them (its text edited)."""
    rng = np.random.default_rng(200 + seed)
    text, links = random_scene(rng, dim, 12, 20)
    j = next(i for i, lk in enumerate(links) if not lk[5])           # a linear link
    K, B = float(rng.uniform(10, 300)), float(rng.uniform(0, 0.05))
    live = Engine(parse_scene_nd(text))
    live.set_link(f"link{j}", K, B)
    live.set_mass("m1", 0.004)
    lines = text.splitlines()
    row = lines.index("links:") + 1 + j
    a, b, K0, B0 = links[j][:4]
    lines[row] = lines[row].replace(f"stiffness: {K0!r}", f"stiffness: {K!r}").replace(
        f"damping: {B0!r}", f"damping: {B!r}")
    m1 = next(i for i, ln in enumerate(lines) if ln.startswith("  - {name: m1,"))
    old = lines[m1].split("mass: ")[1].split(",")[0]
    lines[m1] = lines[m1].replace(f"mass: {old}", "mass: 0.004")
    built = Engine(parse_scene_nd("\n".join(lines) + "\n"))
    assert built.scene.links[j].stiffness == K and built.scene.masses[1].mass == 0.004
    live.step(150)
    built.step(150)
    assert np.array_equal(live.x, built.x)


def test_unknown_names_and_wrong_scenes_are_refused():
    """A live change of an unknown link or a non-moving mass, a 1-D scene in single
    precision, a dimension without a layout and a non-scene are refused by name."""
    eng = Engine(load_scene(CONFIGS / "wall.yaml"))
    with pytest.raises(ConfigError, match="no link named 'nope'; links are: wall"):
        eng.set_link("nope", 1.0, 0.0)
    with pytest.raises(ConfigError, match="not a moving mass"):
        eng.set_mass("hand", 1.0)
    with pytest.raises(ConfigError, match="engine.precision"):
        Engine(load_scene(CONFIGS / "wall.yaml"), precision="single")
    eng3 = Engine(load_scene_nd(CONFIGS / "delta_sphere.yaml"))
    with pytest.raises(ConfigError, match="no link named 'nope'"):
        eng3.set_link("nope", 1.0, 0.0)
    with pytest.raises(ValueError, match="dimension 1, 2 or 3"):
        Engine.layout(4)
    with pytest.raises(TypeError, match="validated hapsim.scene.Scene"):
        Engine(object())


def test_one_dimension_s_capabilities_are_refused_by_name_in_the_other():
    """What one layout has and the other lacks is a :class:`ConfigError` naming the
    capability, the dimension and what to use instead, never an AttributeError."""
    e1 = Engine(load_scene(CONFIGS / "wall.yaml"))
    e3 = Engine(load_scene_nd(CONFIGS / "delta_sphere.yaml"))
    one = np.zeros(1, np.int64)
    for call, dim in ((lambda: e3.run(3), 3), (lambda: e3.play(np.zeros(3)), 3),
                      (e3.energy, 3),
                      (lambda: e1.listen(np.zeros((2, 1)), one, one, one.astype(bool),
                                         np.ones(1)), 1),
                      (lambda: e1.listener(one, one, one.astype(bool), np.ones(1)), 1)):
        with pytest.raises(ConfigError, match=rf"dimension: \w+ is not built for a "
                                              rf"{dim}-D engine: .+"):
            call()
    assert e3.sample == 0 and e1.sample == 0


WALL_1D = """rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: 0.0}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000, damping: 1.5}
device: {mass: 0.1, friction: 0.5, delay: 1}
"""
WALL_2D = """dimension: 2
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: [0.0, 0.0]}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000, damping: 1.5}
device: {kind: cartesian, mass: 0.1, friction: 0.5, position: [0.0, 0.0], delay: 1}
"""


@pytest.mark.numerical
@pytest.mark.parametrize("seed", range(3))
def test_a_wall_felt_in_one_and_two_dimensions(seed):
    """The same spring-damper wall through a 1-D and a 2-D scene, the 2-D port driven
    along x by the 1-D port's seeded trajectory: the forces agree sample by sample within
    the round-off of ``F = K d + (B / T)(d - d_prev)`` and the 2-D one has no y part."""
    rng = np.random.default_rng(seed)
    e1, e2 = Engine(parse_scene(WALL_1D)), Engine(parse_scene_nd(WALL_2D))
    K, z = 1000.0, 1.5 * 1000.0
    xs = np.cumsum(rng.normal(0, 1e-4, 200))
    prev = 0.0
    for x in xs:
        f1 = e1.port_step(float(x))
        f2 = e2.port_step(np.array([x, 0.0]))
        # the law's roundings: d, d_prev, their difference, two products, the sum, the
        # sign: 7, relative to sum |terms| (the sum's condition)
        assert abs(f2[0] - f1) <= rel_tol(7) * (K * abs(x) + z * abs(x - prev)), (x, f1, f2)
        assert f2[1] == 0.0
        prev = x


def test_no_engine_nd_module_is_left():
    """The n-D engine is the package's, not a twin module: no ``hapsim.engine_nd``, no
    ``*_nd`` module in the engine package."""
    assert importlib.util.find_spec("hapsim.engine_nd") is None
    assert not list((ROOT / "hapsim" / "engine").glob("*_nd.py"))
