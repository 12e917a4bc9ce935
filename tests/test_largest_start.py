"""The largest hand start a scene's linear range allows (:func:`hapsim.lockstep.largest_start`)
and the 2DIY run's default start built on it (:func:`hapsim.commands.run_haply2.designed_start`).

Checked against the records themselves: at the start it returns, the exact records' motion
toward the limiting contact's opening (:func:`hapsim.analysis.linearisation.bound_at_records`,
itself checked against the contact laws in tests/test_bound_at_records.py) is
:data:`~hapsim.lockstep.START_MARGIN` of the depth, or their excursion that of the joints'
envelope at the handle; over random wall depths the start follows the depth.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from hapsim.analysis.linearisation import bound_at_records
from hapsim.kinematics import device
from hapsim.lockstep import (START_MARGIN, LockstepND, excitation_starts,
                             identification_plan, largest_start)
from hapsim.scene import load_scene_nd
from tolerance import measured, rel_tol

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _records(scene, a, N):
    recs = [LockstepND(scene, x0=x0, v0=v0).step(N, record=True)
            for x0, v0 in excitation_starts(scene.dimension, a, scene.period)]
    return [r - recs[0] for r in recs[1:]]


@pytest.mark.parametrize("name, env", [("pantograph_wall", 0.03), ("pantograph_circle", 0.03),
                                       ("pantograph_spring", 0.03), ("delta_sphere", 0.1),
                                       ("falcon_spring", 0.1)])
def test_the_start_puts_the_records_at_the_margin_of_what_limits_it(name, env):
    """At the returned start the exact records reach 0.9 of the limiting contact's depth
    (toward its opening) or of the joints' envelope at the handle: the records are linear
    in ``a`` to first order (the contacts' curvature: the disc 1.0e-2 off 0.9, the sphere
    4.1e-3, the wall 2e-14; the envelope-limited loops, linear, 3e-14). The Falcon's spring field is limited by its legs'
    envelope at 3.77 mm, the figure its feasibility states (docs/devices.md)."""
    sc = load_scene_nd(CONFIGS / f"{name}.yaml")
    N = identification_plan(sc)[2]
    a, by, limit = largest_start(sc, N, env)
    bound, ex = bound_at_records(sc, a, _records(sc, a, N))
    if by.startswith("contact"):
        assert by == f"contact {bound.opening_name}" and bound.opening_name is not None
        assert limit == bound.depth                   # one contact in each of these
        # measured 1.0e-2 (the disc), margin 2
        assert abs(bound.opening - START_MARGIN) < measured(1.0e-2, 2.0), (name, bound.opening)
    else:
        J = device(sc.device.kind, sc.device.geometry).jacobian(np.asarray(sc.device.joints))
        reach = env * np.linalg.svd(J, compute_uv=False)[-1]
        # the same product of the same singular value, one rounding each side (the
        # envelope's float() and the product): derived, rel_tol(2)
        assert abs(limit - reach) <= rel_tol(2) * reach
        # with the record from rest's own drift (the rest positions' ten digits: 1e-10 m
        # on falcon_spring, 2.7e-8 of the envelope), counted first by largest_start;
        # measured 3.2e-14 (a linear loop: round-off only), margin 3e5
        drift = float(np.max(np.linalg.norm(_full(sc, a, N)[0], axis=1)))
        assert abs((ex + drift) / reach - START_MARGIN) < measured(3.2e-14, 3e5), (
            name, ex / reach, drift / reach)
        assert not bound.opening >= START_MARGIN      # (nan: no contact engaged)
    if name == "falcon_spring":
        # derived: the docs' 3.77 mm to its printed digits (half a unit in the last one)
        assert by == "envelope" and abs(a - 3.77e-3) < 5e-6


def _deeper(sc, shift):
    """configs/pantograph_wall.yaml's handle ``shift`` [m] deeper into its wall at the same
    rest: the wall moved out by ``shift`` and the press point back by the stiffnesses'
    ratio times it (the wall's force ``K_w d`` balanced by the press spring's ``K_s L``),
    as docs/pantograph_deep_wall.yaml is built."""
    ratio = sc.planes[0].stiffness / sc.links[0].stiffness
    return dataclasses.replace(
        sc, planes=[dataclasses.replace(p, offset=p.offset + shift) for p in sc.planes],
        masses=[dataclasses.replace(m, x0=np.asarray(m.x0) - [0.0, ratio * shift])
                if m.kind == "ground" else m for m in sc.masses])


@pytest.mark.parametrize("seed", range(6))
def test_the_start_follows_the_walls_depth_at_random_depths(seed):
    """configs/pantograph_wall.yaml with the handle resting 0.15-2 mm into the wall (the
    press point moved with it, so the loop is the same): the start is proportional to the
    depth while the wall limits it (the records' motion toward the wall is the same loop's
    at every depth), and the joints' envelope takes over past it (0.54 mm of start at
    0.03 rad, about 0.6 mm of depth)."""
    rng = np.random.default_rng(seed)
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    N = identification_plan(sc)[2]
    a0, by0, d0 = largest_start(sc, N, 0.03)
    # the shipped wall's depth at rest [m]: the scene's ten digits (measured 3.8e-11),
    # margin 26
    assert abs(d0 - 5e-4) < measured(3.8e-11, 26.0)
    depth = float(np.exp(rng.uniform(np.log(1.5e-4), np.log(2e-3))))   # log-uniform
    shift = depth - d0
    a, by, limit = largest_start(_deeper(sc, shift), N, 0.03)
    # the same loop 20 mm into the wall: the joints' envelope alone limits it
    a_env, by_env, _ = largest_start(_deeper(sc, 0.02), N, 0.03)
    assert by0 == "contact wall" and by_env == "envelope"
    want = a0 * depth / d0
    if want < 0.98 * a_env:
        # measured 1.3e-7 off proportional (the wall's records are the same loop's at
        # every depth, to the loop's second order), margin 77
        assert by == "contact wall" and abs(a / want - 1.0) < measured(1.3e-7, 77.0), (
            depth, a, want)
        # the scene's ten digits (measured 3.8e-11), margin 26
        assert abs(limit - depth) < measured(3.8e-11, 26.0)
    elif want > 1.02 * a_env:
        # the same envelope-limited loop (measured 0): only the rest positions' round-off
        # differs, 1e-16 of 0.1 m against 1e-4 m of motion, a 1e-12 bound per step
        assert by == "envelope" and abs(a / a_env - 1.0) < 1e-9, (depth, a, a_env)
    assert a <= min(want, a_env) * 1.02


def test_the_2diy_run_takes_the_designed_start_and_states_everything(capsys):
    """``hapsim run configs/pantograph_wall.yaml --driver haply --lockstep`` without
    ``--amplitude`` takes the largest start the wall allows (0.42 mm), names what limits
    it, and states every quantity within (its own JSON); a start of 0.01 mm leaves the
    felt damping unstated (the old default of 0.1 mm did over the errors' box; with the
    wire's rounding term, hapsim.analysis.wire_rounding, 0.1 mm states it too)."""
    from hapsim.cli import main
    assert main(["run", str(CONFIGS / "pantograph_wall.yaml"), "--driver", "haply",
                 "--lockstep", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["amplitude_limited_by"] == "contact wall"
    assert 4.0e-4 < out["amplitude"] < 4.4e-4
    assert out["verdict"] == "within" and not out["not_stated"], out["reason"]
    assert main(["run", str(CONFIGS / "pantograph_wall.yaml"), "--driver", "haply",
                 "--lockstep", "--amplitude", "1e-5", "--json"]) == 0
    small = json.loads(capsys.readouterr().out)
    assert small["amplitude_limited_by"] is None and small["amplitude"] == 1e-5
    assert small["verdict"] == "partly within" and small["not_stated"]


def _not_at_rest(seed):
    """configs/pantograph_wall.yaml with its press spring and its wall stiffer or softer
    (their rest positions kept): the forces no longer balance at the joints, and the
    record from rest drifts to the new equilibrium (0.1-2 mm)."""
    rng = np.random.default_rng(100 + seed)
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    return dataclasses.replace(
        sc, links=[dataclasses.replace(lk, stiffness=lk.stiffness
                                       * float(np.exp(rng.uniform(-0.5, 0.6))))
                   for lk in sc.links],
        planes=[dataclasses.replace(p, stiffness=p.stiffness
                                    * float(np.exp(rng.uniform(-1.0, 0.7))))
                for p in sc.planes])


def _full(sc, a, N):
    """The exact records about the operating point, the one from rest included."""
    return [LockstepND(sc, x0=x0, v0=v0).step(N, record=True)
            for x0, v0 in excitation_starts(sc.dimension, a, sc.period)]


@pytest.mark.parametrize("seed", range(8))
def test_a_scene_not_at_rest_counts_its_drift_before_the_start(seed):
    """A scene whose forces do not balance at its joints drifts from every start, the one
    from rest too: the start leaves room for that drift, so that the whole records (not
    only their differences from the one from rest) stay within the margin of the joints'
    envelope and of the wall's depth; when the drift alone reaches it, the start is 0 and
    the run's default names why. (Before, the drift was not counted: on these scenes the
    whole records at the start reached up to 1.6 times the envelope's margin, or went
    past the wall's; a wall-clock run of such a scene left the envelope in 3 of its 5
    records and measured nothing.)"""
    from hapsim.analysis.linearisation import opening_motions, records_excursion
    from hapsim.analysis.static_balance import not_at_rest
    from hapsim.commands.run_haply2 import designed_start
    sc = _not_at_rest(seed)
    N = identification_plan(sc)[2]
    env_rad = 0.03
    J = device(sc.device.kind, sc.device.geometry).jacobian(np.asarray(sc.device.joints))
    env = env_rad * np.linalg.svd(J, compute_uv=False)[-1]
    a, by, limit = largest_start(sc, N, env_rad)
    rest = _full(sc, 1e-4, N)[0]
    drift = records_excursion([rest])
    assert drift > 1e-4, drift                        # these scenes are not at rest
    # and hapsim check says so before any run (hapsim.analysis.static_balance), its
    # linearised balance within the record's excursion (0.41-0.57 of it on these eight:
    # the record overshoots the balance)
    said = not_at_rest(sc)
    assert said is not None and 0 < said["balance_m"] <= drift, (said, drift)
    if a == 0.0:
        # the drift alone reaches the margin of what limits it
        toward = {nm: t for nm, _, t in opening_motions(sc, [rest], drift)}
        reached = (drift >= START_MARGIN * env if by == "envelope"
                   else toward[by.split(" ", 1)[1]] >= START_MARGIN * limit)
        assert reached, (by, drift, env, limit)
        assert "not at rest at its joints" in designed_start(sc)[1]
        return
    recs = _full(sc, a, N)
    # the whole records are sums of the drift and the start's share, linear in a for
    # this plane (round-off only: measured 3e-14 on the shipped scene's loop, margin 3e5)
    tol = measured(3.2e-14, 3e5)
    assert records_excursion(recs) <= START_MARGIN * env * (1 + tol)
    for nm, dep, toward in opening_motions(sc, recs, records_excursion(recs)):
        assert toward <= START_MARGIN * dep * (1 + tol), (nm, toward, dep)


def test_the_scenes_not_at_rest_reach_both_outcomes():
    """Of the eight scenes above, some leave room for a start and some do not (a test of
    the test: both branches are taken)."""
    outcomes = set()
    for seed in range(8):
        sc = _not_at_rest(seed)
        outcomes.add(largest_start(sc, identification_plan(sc)[2], 0.03)[0] > 0.0)
    assert outcomes == {True, False}


def test_a_plane_on_several_masses_counts_each_ones_drift():
    """A plane holding a virtual mass and the handle is two engaged entries under one
    name, each with its own depth and its own motion toward opening: the start leaves
    each entry's own drift its room. The record from rest drifts along the wall (its
    tangent: none of it toward the handle's opening), the virtual mass, 0.2 mm deep, is
    credited with the records' whole excursion (the port's records do not say how it
    moves). Fails on the code that kept one drift per name (the handle's, 0, listed
    last): the start then took the virtual mass's whole margin and its drift beside."""
    from hapsim.analysis.linearisation import opening_motions, records_excursion
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    wall = sc.planes[0]
    m = dataclasses.replace(sc.masses[1], name="m", kind="mass", mass=0.01,
                            x0=np.array([0.01, wall.offset - 2e-4]))
    g = dataclasses.replace(sc.masses[1], name="g", x0=np.array([0.01, wall.offset - 2e-4]))
    spring = dataclasses.replace(sc.links[0], name="m_g", m1="m", m2="g")
    sc = dataclasses.replace(sc, masses=[*sc.masses, m, g], links=[*sc.links, spring],
                             planes=[dataclasses.replace(wall, masses=("m", "hand"))])
    N, ref = 50, 1e-4
    t = np.linspace(0.0, 1.0, N)[:, None]
    rest = np.hstack([1.5e-4 * t, 0.0 * t])                  # along the wall
    recs = [rest] + [rest + ref * np.hstack([s * np.sin(7 * t), c * t])
                     for s, c in ((0.1, 0.5), (0.3, -0.2), (-0.2, 0.4), (0.0, 1.0))]
    a, by, limit = largest_start(sc, N, 0.03, reference=ref, records=recs)
    assert a > 0.0, (a, by)
    # each entry: its drift and the start's share, within the margin of its own depth
    # (the share is linear in a here by construction; round-off only)
    diffs = [r - rest for r in recs[1:]]
    drift = records_excursion([rest])
    rest_t = opening_motions(sc, [rest], drift)
    entries = opening_motions(sc, diffs, records_excursion(diffs))
    assert [e[0] for e in entries] == ["wall", "wall"]
    for (nm, dep, toward), (_, _, r_t) in zip(entries, rest_t):
        # (derived: a few roundings of quantities of the depth's size)
        assert r_t + a / ref * toward <= START_MARGIN * dep * (1 + 16 * rel_tol(1)), (
            nm, dep, r_t, toward, a)
