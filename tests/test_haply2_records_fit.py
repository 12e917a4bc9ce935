"""The 2DIY's records cut at their disturbances fitted each on its own stretches about a
fitted equilibrium (issue 29: 1 byte in 200 lost each way), not as differences against
the record from rest, whose cuts a difference took on as its own
(:mod:`hapsim.analysis.felt_records`, :func:`hapsim.analysis.pencil.fit_felt_nd`'s
``offset``).

Closed forms on the loop's own free responses (predicted in lockstep,
:class:`hapsim.lockstep.LockstepND`) over seeded random loops and cut patterns; the
fit's first-order sensitivity against refits; the whole measurement on the emulated
board, on its own clock in simulated time (``test_haply2_stalls``'s ``SimClock``: the
same run on any machine at any load) or in lockstep (named in the test's name)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hapsim.analysis.felt_matrices import felt_deviation
from hapsim.analysis.pencil import _equations, fit_felt_nd
from hapsim.kinematics import cartesian_mass, device
from hapsim.lockstep import LockstepND, identification_plan
from hapsim.scene import load_scene_nd
from test_haply2_cuts import _measure
from test_haply2_stalls import WALL
from seeds import seeds
from tolerance import measured


def _random_loop(seed):
    """configs/pantograph_wall.yaml with each joint's inertia and friction scaled by a
    seeded random factor (0.5-2 and 0.2-5): another loop, its own prediction. The
    device's Cartesian mass and friction (what the loop and the prediction use) are
    mapped again from the new joint values, ``J^-T M_q J^-1`` plus the hand's (as the
    scene's reader does): replacing the joint values alone left them the scene's, so
    every seed was the same loop."""
    rng = np.random.default_rng(seed)
    sc = load_scene_nd(WALL)
    dev = sc.device
    Mq = dev.joint_inertia * rng.uniform(0.5, 2.0, 2)
    Bq = dev.joint_friction * rng.uniform(0.2, 5.0, 2)
    J = device("pantograph", dev.geometry).jacobian(np.asarray(dev.joints))
    eye = np.eye(2)
    return dataclasses.replace(sc, device=dataclasses.replace(
        dev, joint_inertia=Mq, joint_friction=Bq,
        mass=cartesian_mass(J, Mq) + dev.hand_mass * eye,
        friction=cartesian_mass(J, Bq) + dev.hand_damping * eye)), rng


def test_the_random_loops_are_different_loops():
    """Each seed's loop has its own Cartesian mass (the stale one made them equal)."""
    masses = [_random_loop(s)[0].device.mass for s in range(4)]
    for i in range(4):
        for j in range(i):
            # the joint values differ by random factors 0.5-2: the Cartesian masses by
            # far more than a per cent (measured: 13 % at the closest pair of seeds)
            gap = np.max(np.abs(masses[i] - masses[j])) / np.max(np.abs(masses[j]))
            assert gap > 0.01, (i, j, gap)


def _cut_records(sc, rng, N, a=1e-4):
    """Five records of absolute handle positions [m] (the operating point's plus the
    loop's free responses, the first from rest), each restarted 2-6 times from another
    random start (a re-synchronisation: the hand lets the handle go again) with 1-4 rows
    cut there, as the host's cuts do; and their usable rows."""
    x_eq = device("pantograph", sc.device.geometry).forward(np.asarray(sc.device.joints))

    def free(rest=False):
        if rest:
            return LockstepND(sc).step(N, record=True)
        return LockstepND(sc, x0=rng.uniform(-a, a, 2),
                          v0=rng.uniform(-a, a, 2) / (10 * sc.period)).step(N, record=True)
    recs, usable = [], []
    for j in range(5):
        r, u = free(rest=j == 0), np.ones(N, bool)
        for c in np.sort(rng.choice(np.arange(10, N - 10), size=int(rng.integers(2, 7)),
                                    replace=False)):
            r[c:] = free()[:N - c]
            u[c - 1:c + int(rng.integers(1, 5))] = False
        recs.append(r + x_eq)
        usable.append(u)
    return recs, usable


@pytest.mark.parametrize("seed", range(4))
def test_cut_records_fitted_on_their_own_stretches_give_the_loop_to_round_off(seed):
    """Closed form: random loops, five records each restarted at random rows (the rest
    record too), absolute positions: the affine fit of every record's own stretches gives
    the prediction's felt matrices to round-off; without the equilibrium (offset False)
    it is far off, and the differences against the record from rest hold fewer
    equations (only the rows usable in both)."""
    sc, rng = _random_loop(seed)
    chk, p, N = identification_plan(sc, 200)
    recs, usable = _cut_records(sc, rng, N)
    fit = fit_felt_nd(recs, sc.device.mass, sc.period, p, usable=usable, offset=True)
    # worst measured over seeds 0-5 (numpy's LAPACK, x86-64): 7.6e-10 (the records are
    # absolute positions, 0.094 m, moving 1e-4 m: three digits of the differences' 5.8e-13
    # go to the equilibrium); a margin of 100 for another BLAS, still 8 orders of
    # magnitude under the fit without the equilibrium
    tol = measured(7.6e-10, 100.0)
    dev = felt_deviation(fit, chk)
    assert max(dev.values()) <= tol, dev
    # the loop's equilibrium, where its force is zero: the operating point's within the
    # scene's ten digits (3.8e-11 m measured), far under the motion (1e-4 m)
    x_eq = device("pantograph", sc.device.geometry).forward(np.asarray(sc.device.joints))
    assert np.max(np.abs(fit["equilibrium"] - x_eq)) <= measured(3.8e-11, 100.0)
    plain = felt_deviation(fit_felt_nd(recs, sc.device.mass, sc.period, p, usable=usable),
                           chk)
    assert max(plain.values()) > 1e3 * tol, plain
    both = [usable[0] & u for u in usable[1:]]
    own = sum(k.size for k in _equations(recs, p, usable))
    diff = sum(k.size for k in _equations(recs[1:], p, both))
    assert diff < own


@pytest.mark.parametrize("seed", seeds(range(1, 9), kept=(3, 4, 5, 8)))
def test_lossy_matching_board_on_its_own_clock_states_the_stiffness_simulated_time(
        monkeypatch, seed):
    """1 byte in 200 lost each way, the board on its own clock (simulated time), seeds
    1-8: as differences against the record from rest, seeds 3, 4 and 8 were "not
    measurable" (15, 13 and 4 equations left of the 234, 266 and 247 the records' own
    stretches hold; their fits off by 4e3 to 4e4 % in the felt stiffness). Fitted on their own
    stretches: never "differs"; the felt stiffness stated and within, unless the run is
    "not measurable" for a reason of its own (seed 5: the joints left the measurement's
    envelope, no fit stated). At a = 2e-4 m: the records move 0.44 mm, about what 1e-4 m
    moved when the board coasted through its set-up before the hand let go (at 1e-4 m now
    seed 8 leaves the stiffness unstated; at 3e-4 m seeds 3 and 4 are "not measurable",
    a lost byte's torque taking the handle out of the wall, named)."""
    r = _measure(monkeypatch, seed, loss=1 / 200, amplitude=2e-4)
    assert sum(r["resyncs"]) > 0 and min(r["usable"]) < 200
    assert r["verdict"] != "differs", (r["reason"], r["deviation"], r["uncertainty"])
    if r["verdict"] == "not measurable":
        assert "envelope" in r["reason"], r["reason"]
        return
    st = [s for s in r["statements"] if s["quantity"] == "felt_stiffness"
          and s["direction"] is None]
    assert st and st[0]["verdict"] == "within", (r["verdict"], r["reason"])
    assert r["deviation"]["felt_stiffness"] <= r["uncertainty"]["felt_stiffness"]
    # equations fitted per record (the one from rest first): 97 at the fewest (seed 8)
    assert len(r["fitted_rows"]) == 5 and sum(r["fitted_rows"]) > 4 * 15


@pytest.mark.parametrize("seed", [1, 4])
def test_lossy_hidden_friction_never_within_lockstep(monkeypatch, seed):
    """1 byte in 200 lost each way, the board in lockstep with each joint's friction 30
    times the scene's (the felt damping 13 times the prediction): the run never says
    "within", and a damping it states is "differs" (the stiffness barely moves: a
    "partly within" names the damping as not stated)."""
    r = _measure(monkeypatch, seed, loss=1 / 200, clock="lockstep", friction=30.0)
    # (the loss reached the loop: the board re-synchronised, or the count of replies
    # realigned after a write it swallowed)
    assert sum(r["resyncs"]) + sum(r["realigned"]) > 0
    assert r["verdict"] != "within", (r["reason"], r["deviation"])
    assert r["deviation"]["felt_damping"] > 1.0
    for s in r["statements"]:
        if s["quantity"] == "felt_damping":
            assert s["verdict"] != "within", s
    if r["verdict"] == "partly within":
        assert "felt damping" in r["not_stated"]

