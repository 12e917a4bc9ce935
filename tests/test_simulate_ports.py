"""``hapsim simulate`` and ``hapsim.simulate`` of a scene with several ports (issue 30):
each port closed through its own device model, checked against an independent state space
(tests/test_ports.py's ``reference_state_matrix``: each device's own ``expm`` hold and force
FIFO, the links' law one link at a time; it shares no code with
``hapsim.lockstep_ports``, which simulate runs), the force limit's clip, divergence, the
file and the refusals."""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.cli import main
from hapsim.errors import ConfigError
from hapsim.scene import Device, Link, ScenePorts, parse_scene_ports
from test_ports import TWO, _force_law, random_ports, reference_state_matrix
from tolerance import measured, rel_tol

import hapsim


def _reference_run(scene, x0, v0, steps):
    """The reference loop from ``(x0, v0)``: ports' positions and the links' forces on
    them, rows ``0..steps`` (a port's previous position one period back at its initial
    velocity, every force before the start zero, as a device at rest holds)."""
    A = reference_state_matrix(scene)
    P, T = len(scene.devices), scene.period
    s = np.zeros(A.shape[0])
    s[:P], s[P:2 * P], s[2 * P:3 * P] = x0, v0, x0 - v0 * T
    xs, xps = np.empty((steps + 1, P)), np.empty((steps + 1, P))
    for n in range(steps + 1):
        xs[n], xps[n] = s[:P], s[2 * P:3 * P]
        s = A @ s
    Cx, Cxp = _force_law(scene)
    return xs, xs @ Cx.T + xps @ Cxp.T


#: The trajectories' deviation from the reference, relative to the run's largest port
#: position (or force): measured worst 9.3e-15 over the 26 stable ones of 60 random
#: scenes (seeds 100-129, whole and own delays, 400 samples; x86-64, numpy's OpenBLAS)
#: and 3.5e-15 over this file's 12; the margin of 100 covers other CPUs' fused multiply-adds and BLAS kernels
#: (each step's roundings change, not their number) and stays under the derived bound
#: where it was computed (tests/tolerance.py's recurrence_tol on the state scaled to
#: metres, velocity times T and forces over the links' gain: 3e-10 on seed 30's first
#: scene, its powers amplifying by 38), while a modelling error (a delay, a hold, a
#: link's law) moves the trajectory by 1e-3 and more.
TRAJECTORY_REL = measured(1e-14, 100.0)


@pytest.mark.parametrize("own", [False, True])
def test_simulate_equals_the_independent_state_space(own):
    """Random stable scenes of 2 and 3 ports (each its own whole delay, or, with ``own``,
    its own delay whole or sub-sample; random devices, links to ground and across ports),
    each started displaced and moving at random: ``hapsim.simulate``'s port positions and
    forces equal the reference loop's over 400 samples, to :data:`TRAJECTORY_REL` of the
    run's largest position (force)."""
    rng = np.random.default_rng(30 + own)
    steps, done = 400, 0
    while done < 6:
        scene = random_ports(rng, coupled=True, whole=True, own=own)
        P = len(scene.devices)
        if max(abs(np.linalg.eigvals(reference_state_matrix(scene)))) >= 0.999:
            continue                                      # stable ones: bounded runs
        x0, v0 = rng.uniform(-1e-2, 1e-2, P), rng.uniform(-0.1, 0.1, P)
        rep = hapsim.simulate(scene, steps, x0=list(x0), v0=list(v0))
        xs, fs = _reference_run(scene, x0, v0, steps)
        assert rep.exit_code == 0 and rep.diverged is None
        assert rep.port_position.shape == (steps + 1, P) == rep.port_force.shape
        np.testing.assert_allclose(rep.port_position, xs, rtol=0,
                                   atol=TRAJECTORY_REL * float(np.max(np.abs(xs))))
        np.testing.assert_allclose(rep.port_force, fs, rtol=0,
                                   atol=TRAJECTORY_REL * float(np.max(np.abs(fs))))
        # the trajectory's port columns are the ports' positions, the ground's its x0
        names = list(rep.names)
        for i, p in enumerate(scene.ports):
            assert np.array_equal(rep.position[:, names.index(p), 0], rep.port_position[:, i])
        assert np.all(rep.position[:, names.index("g"), 0] == 0.0)
        done += 1


def test_force_limit_clips_each_device_and_nothing_else():
    """Random two-port scenes with a force limit on one port between the smallest and the
    largest force its free run asks: the force that device takes never exceeds it, equals
    it (signed) wherever the links ask more, and until the first such sample the run is the
    unclipped one to the bit (the same operations)."""
    rng = np.random.default_rng(7)
    for _ in range(6):
        scene = random_ports(rng, coupled=True, whole=bool(rng.integers(2)))
        P = len(scene.devices)
        x0 = np.zeros(P)
        x0[0] = 5e-3
        free = hapsim.simulate(scene, 200, x0=list(x0))
        limit = 0.5 * float(np.max(np.abs(free.port_force[:, 0])))
        devs = list(scene.devices)
        devs[0] = (devs[0][0], Device(mass=devs[0][1].mass, friction=devs[0][1].friction,
                                      delay=devs[0][1].delay, force_limit=limit))
        clipped_scene = ScenePorts(rate_hz=scene.rate_hz, masses=scene.masses,
                                   links=scene.links, devices=tuple(devs))
        rep = hapsim.simulate(clipped_scene, 200, x0=list(x0))
        f = rep.port_force[:, 0]
        assert np.all(np.abs(f) <= limit)
        first = int(np.flatnonzero(np.abs(free.port_force[:, 0]) > limit)[0])
        assert np.array_equal(rep.port_position[:first + 1], free.port_position[:first + 1])
        assert f[first] == np.sign(free.port_force[first, 0]) * limit


def test_an_unstable_loop_without_a_limit_stops_at_its_first_non_finite_sample(tmp_path,
                                                                              capsys):
    """A port on a wall far above its K_max (its device with no force limit) grows until
    its position is not finite: the command exits 1, names the step and the port, and the
    file holds exactly the finite rows before it."""
    scene = parse_scene_ports(TWO)
    links = tuple(Link(lk.name, lk.kind, lk.m1, lk.m2, 1e7, lk.damping)
                  for lk in scene.links)
    wild = ScenePorts(rate_hz=scene.rate_hz, masses=scene.masses, links=links,
                      devices=scene.devices)
    rep = hapsim.simulate(wild, 20000, x0=[1e-3, 0.0])
    assert rep.exit_code == 1 and rep.diverged is not None
    k = rep.diverged["step"]
    assert 0 < k < 20000 and rep.port_position.shape[0] == k
    assert np.isfinite(rep.port_position).all() and rep.time.shape == (k,)
    f = tmp_path / "wild.yaml"
    f.write_text(TWO.replace("links:", "links:\n  - {name: wild, kind: spring_damper, "
                             "between: [a, g], stiffness: 1.0e+7, damping: 0.0}", 1))
    out = tmp_path / "w.npz"
    code = main(["simulate", str(f), "-n", "20000", "--x0", "a=1e-3", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and "diverged" in err and "port 'a'" in err
    data = np.load(out)
    assert np.isfinite(data["port_position"]).all()


def test_the_file_and_the_summary(tmp_path, capsys):
    """The shipped two faders, fader A displaced: the .npz holds time (N+1,), position
    (N+1, R, 1) in --record's order, names, ports, port_position and port_force (N+1, P),
    equal to the API's; --json says steps, ports, delays, x0 and v0."""
    import json
    out = tmp_path / "f.npz"
    assert main(["simulate", "configs/two_faders.yaml", "-n", "300", "--x0", "fader_a=0.004",
                 "--v0", "fader_b=-0.01", "--record", "fader_b", "anchor", "--out", str(out),
                 "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["ports"] == ["fader_a", "fader_b"] and d["delays"] == [0.725, 0.7625]
    assert d["x0"] == [0.004, 0.0] and d["v0"] == [0.0, -0.01] and d["steps"] == 300
    data = np.load(out)
    assert data["time"].shape == (301,) and data["position"].shape == (301, 2, 1)
    assert list(data["names"]) == ["fader_b", "anchor"]
    assert list(data["ports"]) == ["fader_a", "fader_b"]
    rep = hapsim.simulate("configs/two_faders.yaml", 300, x0={"fader_a": 0.004},
                          v0={"fader_b": -0.01})
    assert np.array_equal(data["port_position"], rep.port_position)
    assert np.array_equal(data["port_force"], rep.port_force)
    assert np.array_equal(data["position"][:, 0, 0], rep.port_position[:, 1])
    # row 0 on fader A: its springs (30 + 15 N/m) at 4 mm and the coupling's damper
    # (0.1 N s/m) at B's 0.01 m/s; the backward difference cancels 0.004 against 0.00396
    # (condition 100 on that term), 8 roundings
    assert data["port_force"][0, 0] == pytest.approx(-45 * 0.004 - 0.1 * 0.01,
                                                     rel=rel_tol(8, cond=100))


@pytest.mark.parametrize("argv, key", [
    (["--x0", "c=1", "--out", "{t}/x.npz"], "--x0"),
    (["--x0", "a=1", "--x0", "a=2", "--out", "{t}/x.npz"], "--x0"),
    (["--v0", "a=inf", "--out", "{t}/x.npz"], "--v0"),
    (["--x0", "a", "--out", "{t}/x.npz"], "--x0"),
    (["--record", "zz", "--out", "{t}/x.npz"], "--record"),
    (["--out", "{t}/x.csv"], "--out"),
    (["--audio", "{t}/x.wav"], "--audio"),
])
def test_bad_options_name_their_flag(tmp_path, capsys, argv, key):
    """Each bad option of a several-port simulate is exit 2, one line naming the flag."""
    f = tmp_path / "two.yaml"
    f.write_text(TWO)
    code = main(["simulate", str(f), "-n", "10"] + [a.format(t=tmp_path) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"error: {key}:" in err[0], err


def test_port_options_on_a_one_port_scene_are_refused(tmp_path, capsys):
    """--x0 on a one-port scene names the flag (its port starts at its excitation's x0),
    and hapsim.simulate's x0 the keyword."""
    assert main(["simulate", "configs/wall.yaml", "-n", "10", "--x0", "a=1", "--out",
                 str(tmp_path / "w.npz")]) == 2
    assert "error: --x0:" in capsys.readouterr().err
    with pytest.raises(ConfigError) as e:
        hapsim.simulate("configs/wall.yaml", 10, x0=[1.0])
    assert e.value.key == "x0" and "several ports" in str(e.value)


@pytest.mark.parametrize("config, report", [
    ("configs/oscillator.yaml", "SimulateReport"),
    ("configs/felt_wall.yaml", "SimulateReport"),
    ("configs/pantograph_wall.yaml", "SimulateReportND"),
    ("configs/two_faders.yaml", "SimulateReportPorts"),
])
def test_one_function_and_one_command_for_every_kind_of_scene(tmp_path, config, report):
    """``hapsim.simulate`` takes a 1-D (a felt target calibrated first), a 2-D and a
    several-port scene, and ``hapsim simulate`` writes the very arrays it returns (the
    command calls it)."""
    rep = hapsim.simulate(config, 120)
    assert type(rep).__name__ == report and rep.exit_code == 0 and rep.steps == 120
    out = tmp_path / "x.npz"
    assert main(["simulate", config, "-n", "120", "--out", str(out)]) == 0
    data = np.load(out)
    assert np.array_equal(data["time"], rep.time)
    assert np.array_equal(data["position"], rep.position)
    assert list(data["names"]) == list(rep.names)
    if report == "SimulateReport":
        assert rep.calibrations == ([] if "oscillator" in config
                                    else [c.to_dict() for c in rep.calibrated])
        assert "felt_wall" not in config or len(rep.calibrations) == 1
