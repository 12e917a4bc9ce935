"""identify designs its own excitation (issue 29 item 4): a short probe, then force levels
that move the device clearly and stay inside the envelope, with no option to tune.

Before: the excitation's level grew while the device moved less than 30 % of the envelope in
100 ms and was cut when the device, at its present velocity, would pass 60 % within the
longest delay; its inertia was not counted, so a 0.237 kg device stopped 0.06 mm beyond the
10 mm envelope in 5 of 6 real-time runs (safety stop, exit 1), and a device with 0.4-0.5 N
of Coulomb friction never broke loose under the 0.4 N the level could reach at the default
2 N force limit ("the device hardly moved").

The records of the property test come from the independent simulation of
``tests/test_identify_gaps.py`` (exact zero-order hold from the matrix exponential, the
first-order Coulomb rule, a device applying the answer to tick ``t`` from ``t + d``), driven
by :class:`hapsim.pipeline.excitation.ExcitationEngine` at the default options.
"""

import math
import os
import subprocess
import sys

import numpy as np
import pytest

from hapsim.analysis.device_fit_stretches import moving_stretches
from hapsim.pipeline.excitation import LEVEL_SHARE, PRBS_SHARE

from intervals import assert_within  # same directory (pytest prepend import mode)
from test_identify_gaps import simulate  # same directory (pytest prepend import mode)
from inproc import hapsim_main  # same directory (pytest prepend import mode)

#: identify's defaults (hapsim/commands/identify.py): force limit [N], envelope [m],
#: duration [s] at 1 kHz.
FORCE_LIMIT, ENVELOPE, N = 2.0, 0.01, 4000


@pytest.mark.parametrize("seed", range(12))
def test_the_excitation_moves_every_device_clearly_inside_the_envelope(seed):
    """Property over the issue's devices (seeded random: m 0.02-2 kg log-uniform, b0 0-5
    N s/m, Coulomb 0-0.5 N, d 0-20, sensor noise 0, 20 or 50 um) at the default options:
    the device never leaves the envelope (what the loop's safety stop checks), the force
    sent never reaches the limit (the other safety stop), and the record holds the 100
    samples of clear motion the fit needs (the fit's own rule,
    :func:`hapsim.analysis.device_fit_stretches.moving_stretches`)."""
    rng = np.random.default_rng(1000 + seed)
    lm, b0, fc = rng.uniform(math.log(0.02), math.log(2.0)), rng.uniform(0, 5), rng.uniform(0, .5)
    d, noise = int(rng.integers(0, 21)), float(rng.choice([0.0, 20e-6, 50e-6]))
    m = math.exp(lm)
    rng = np.random.default_rng(seed)
    _, pos, force, _, _ = simulate(m, b0, fc, d, N, np.zeros(N, bool), rng,
                                     noise=noise, force_limit=FORCE_LIMIT)
    # the true positions are within the sensor noise of the recorded ones: 6 sigma
    assert np.max(np.abs(pos)) < ENVELOPE - 6.0 * noise, (m, b0, fc, d)
    # the excitation's own bound: the square wave's level and the PRBS on it are at most
    # (1 + PRBS_SHARE) LEVEL_SHARE of the limit; the centring force adds to it
    assert np.max(np.abs(force)) < FORCE_LIMIT
    assert (1 + PRBS_SHARE) * LEVEL_SHARE < 1
    st_ = moving_stretches(pos, 0.0)
    assert int(np.sum(st_[1] - st_[0])) >= 100, (m, b0, fc, d)


def _device(rng, **fixed):
    """One of the issue's random devices (module notes), ``fixed`` keys given."""
    dev = {"mass": float(np.exp(rng.uniform(math.log(0.02), math.log(2.0)))),
           "friction": float(rng.uniform(0.0, 5.0)), "coulomb": float(rng.uniform(0, 0.5)),
           "delay": int(rng.integers(0, 21)), "noise": float(rng.uniform(0, 50e-6)),
           "position_resolution": 0.0, "hold": "zoh", "force_limit": 10.0}
    dev.update(fixed)
    return dev


@pytest.mark.parametrize("seed,fixed", [(3, {"coulomb": 0.48, "delay": 20}),
                                        (5, {"mass": 1.9, "noise": 0.0}),
                                        (8, {"mass": 0.021, "coulomb": 0.0})])
def test_random_devices_are_identified_within_their_intervals(seed, fixed):
    """Lockstep (the maths, not the timing): the whole identification at the default
    options of a Coulomb-heavy device behind the longest delay, a heavy one and a light
    one: identified, no safety stop, every truth inside its interval (widened for the
    checks of one run: tests/intervals.py), d exact."""
    from hapsim.commands.identify import identify
    from hapsim.scene import Device
    dev = _device(np.random.default_rng(seed), **fixed)
    fit, rec = identify(device=Device(**dev), transport="inprocess", seed=seed,
                        progress=False, handle_signals=False)
    assert not rec["loop"]["safety_stop"], rec["loop"]["stop_reason"]
    est = {k: v for k, v in fit.to_dict().items() if isinstance(v, dict)}
    assert_within(est, {"mass": dev["mass"], "friction": dev["friction"],
                        "coulomb_pos": dev["coulomb"], "coulomb_neg": dev["coulomb"],
                        "noise": dev["noise"]})
    assert fit.delay == dev["delay"]


def test_identify_over_a_real_time_port_ends_without_a_safety_stop(tmp_path):
    """The issue's run, on the wall clock: ``hapsim mock --scene`` of a hidden device
    (m 0.237 kg, b0 1.31 N s/m, d 2) and ``hapsim identify --port`` with its default
    options: exit 0, no safety stop, m and b0 inside their intervals."""
    import json
    scene = tmp_path / "dev.yaml"
    scene.write_text("rate_hz: 1000\nmasses:\n  - {name: hand, kind: port}\nlinks: []\n"
                     "device: {mass: 0.237, friction: 1.31, delay: 2, hold: zoh, "
                     "force_limit: 10.0}\n")
    env = dict(os.environ)
    mock = subprocess.Popen([sys.executable, "-m", "hapsim", "mock", "--scene", str(scene)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    try:
        line = mock.stdout.readline()
        assert line.startswith("PORT"), line + mock.stderr.read()
        # the host side in this process (tests/inproc.py): what is tested is its report
        code, stdout, stderr = hapsim_main(["identify", "--port", line.split()[1], "--json"],
                                           timeout=300)
    finally:
        mock.terminate()
        mock.wait(10)
    out = json.loads(stdout)
    # (a run that identified nothing has no loop section: its reason and exit are shown)
    assert "loop" in out, (code, out, stderr[-2000:])
    # the loop at SCHED_FIFO where permitted, as hapsim run's (preempted mid-push beside a
    # CPU-bound process, it held its force and passed the envelope: -0.0100663 m, a
    # fresh-clone suite at normal scheduling), or the reason it was refused
    sched = out["loop"]["scheduling"]
    assert sched == "SCHED_FIFO 10" or sched.startswith("normal (SCHED_FIFO"), sched
    # (seen once in CI, stop 80: "position -0.0100248 m beyond +-0.01 m", 0.25 % past the
    # envelope; the stop ahead counts a host stall of 6 ms, or the longest this run has
    # shown: what came before is said with it)
    lp = out["loop"]
    assert not lp["safety_stop"], (lp["stop_reason"], {k: lp.get(k) for k in (
        "host_stall_s", "late", "clamped", "samples", "f_max", "v_max")})
    assert code == 0, stderr[-2000:]
    assert_within(out["device"], {"mass": 0.237, "friction": 1.31})


def test_the_centring_gains_radii_are_numpy_roots_bit_for_bit():
    """The centring gains' stability check takes the spectral radii of all its (mass,
    damping) loops from one stack of companion matrices (``_rho_masses``, issue 31 item 2:
    ~200 ``numpy.roots`` calls were 53 ms of every identification, 5 now): each radius is
    ``_rho_mass``'s (``numpy.roots`` of the same characteristic polynomial) bit for bit, a
    damping of 0 (a root at 0, which ``numpy.roots`` strips) included; so the gains are
    the same numbers."""
    from hapsim.pipeline.excitation import (MASS_RANGE, _rho_mass, _rho_masses,
                                              centring_gains)
    rng = np.random.default_rng(31)
    for i in range(200):
        d = int(rng.integers(0, 9))
        T = float(10.0 ** rng.uniform(-4, -2))
        kc = float(10.0 ** rng.uniform(-1, 4))
        ms = 10.0 ** rng.uniform(-3, 1, 7)
        bcs = 10.0 ** rng.uniform(-4, 2, 7)
        if i % 10 == 0:
            bcs[0] = 0.0
        got = _rho_masses(ms, kc, bcs, d, T)
        ref = [_rho_mass(float(m), kc, float(bc), d, T) for m, bc in zip(ms, bcs)]
        assert got.tolist() == ref, (d, T, kc)
    # the gains found with them: stable for every mass of the range and every delay
    kc, bc = centring_gains(4.0, 0.01, 1000.0, 3)
    grid = np.geomspace(MASS_RANGE[0], MASS_RANGE[1], 7)
    assert kc > 0 and bc > 0
    assert all(_rho_mass(float(m), kc, bc, d, 1e-3) < 1.0 for d in range(4) for m in grid)


@pytest.mark.parametrize("seed", range(24))
def test_a_light_device_held_by_coulomb_friction_behind_a_long_delay_stays_inside(seed):
    """Property over the issue's hardest corner (seeded random: m 0.02-0.06 kg, b0 0-0.3
    N s/m, Coulomb 0.3-0.5 N, d 8-20, noise 0-50 um) at the default options, on the
    independent simulation: the device never leaves the envelope. Before the excitation
    raised its level only once the device had felt the present level's full push for the
    longest delay, a level raised under the PRBS's weak half broke the device loose far
    above its Coulomb friction and it left the envelope before the reversal reached it:
    3 of these seeds (10, 18, 20: 13.8, 11.7 and 16.9 mm against the 10; 5 of seeds
    0-39), 0 after. (Seed 1, 26 g held by 0.31 N behind 14 samples, still moves too
    little for the fit: "the device hardly moved", a refusal, not a runaway.)"""
    rng = np.random.default_rng(5000 + seed)
    m = math.exp(rng.uniform(math.log(0.02), math.log(0.06)))
    b0, fc = rng.uniform(0, 0.3), rng.uniform(0.3, 0.5)
    d, noise = int(rng.integers(8, 21)), float(rng.uniform(0, 50e-6))
    _, pos, force, _, _ = simulate(m, b0, fc, d, N, np.zeros(N, bool),
                                     np.random.default_rng(seed), noise=noise,
                                     force_limit=FORCE_LIMIT)
    assert np.max(np.abs(pos)) < ENVELOPE - 6.0 * noise, (m, b0, fc, d)
    assert np.max(np.abs(force)) < FORCE_LIMIT
