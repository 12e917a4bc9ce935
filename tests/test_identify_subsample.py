"""identify states a sub-sample delay with its interval (issue 29 item 3).

A device whose force takes effect ``d = m + f`` periods after the position it answers
(the FireFader's ADC 1.1 ms into a 4 ms period, a USB frame 0.3 ms into a 1 ms one)
holds the previous force over the first ``f T`` of each period: the split hold of
:mod:`hapsim.analysis.subsample`, which the mock's physics runs
(:meth:`hapsim.device_model.MockPhysics._advance_split`). Fitted as a whole delay, a
hidden ``d = 1.3`` gave b0 = 0.428 in [0.362, 0.494] for a true 0.5 (the interval missed
it); the fit now searches the fraction (hapsim.analysis.device_fit_search.search_fraction) and
reports ``delay_estimate`` with its interval; a whole delay keeps today's model.
"""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.commands.identify import identify
from hapsim.kernels.device_sim import simulate_device
from hapsim.scene import Device


def _identify(dev, seed):
    return identify(device=dev, transport="inprocess", duration=2.0, force_limit=4.0,
                    max_delay=5, seed=seed, progress=False, handle_signals=False)


def test_a_hidden_delay_of_1_3_periods_is_stated_within_its_interval():
    """The issue's case: m 0.1 kg, b0 0.5 N s/m, d 1.3, 1 um noise."""
    dev = Device(mass=0.1, friction=0.5, delay=1.3, hold="zoh", force_limit=10.0,
                 noise=1e-6)
    fit, _ = _identify(dev, 1)
    assert fit.delay == 1
    assert fit.delay_estimate.contains(1.3), fit.delay_estimate
    assert fit.delay_estimate.hi - fit.delay_estimate.lo < 0.2
    assert fit.mass.contains(0.1) and fit.friction.contains(0.5), (fit.mass, fit.friction)
    # statistical (1 um noise, seed 1), the interval above being the stated uncertainty:
    # measured 0.011, margin 4.5
    assert fit.device_delay() == pytest.approx(1.3, abs=0.05)


def _random_device(rng):
    """``(d, device)``: m 0.05-1 kg log-uniform, b0 0-3 N s/m, Coulomb 0-0.2 N, d uniform
    in [0, 4) periods, noise 0-3 um (the family of ``tools/identify_subsample.py``, its
    draws in its order)."""
    d = float(rng.uniform(0.0, 4.0))
    return d, Device(mass=float(np.exp(rng.uniform(np.log(0.05), np.log(1.0)))),
                     friction=float(rng.uniform(0.0, 3.0)),
                     coulomb=float(rng.uniform(0.0, 0.2)), delay=d, hold="zoh",
                     noise=float(rng.uniform(0.0, 3e-6)), force_limit=10.0)


def test_intervals_cover_random_sub_sample_delays():
    """Property over seeded random devices (m 0.05-1 kg, b0 0-3 N s/m, Coulomb 0-0.2 N,
    d uniform in [0, 4) periods, noise 0-3 um): the delay, mass and friction intervals
    (99.9 %) hold the truth. 10 devices: with a true coverage of 99.9 % a miss has
    probability ~1 %, so one miss per quantity is allowed (two: ~4e-4)."""
    rng = np.random.default_rng(29)
    miss = {"d": 0, "m": 0, "b0": 0}
    for i in range(10):
        d, dev = _random_device(rng)
        fit, _ = _identify(dev, i)
        assert fit.delay == int(np.floor(d))
        miss["d"] += not fit.delay_estimate.contains(d)
        miss["m"] += not fit.mass.contains(dev.mass)
        miss["b0"] += not fit.friction.contains(dev.friction)
    assert all(v <= 1 for v in miss.values()), miss


@pytest.mark.parametrize("d", [0, 1, 3])
def test_a_whole_delay_stays_whole(d):
    """A whole delay: its interval holds it, the device written has it as an integer
    (the numbers downstream are today's, bit for bit)."""
    dev = Device(mass=0.2, friction=1.0, delay=d, hold="zoh", force_limit=10.0,
                 noise=1e-6)
    fit, _ = _identify(dev, 3)
    assert fit.delay == d and fit.delay_estimate.contains(d)
    got = fit.device_delay()
    assert isinstance(got, int) and got == d


@pytest.mark.parametrize("frac", [0.0, 0.25, 0.7])
def test_the_split_hold_kernel_is_the_mocks(frac):
    """simulate_device's split hold against an independent integration: the same
    device stepped on a grid 100 times finer with the force switching at ``frac T``
    (forces on the fine grid: a plain exact ZOH there), no Coulomb friction; equal to
    the round-off of the fine run's exact steps (the bound derived below)."""
    rng = np.random.default_rng(7)
    n, T, m, b = 200, 1e-3, 0.15, 0.8
    u = rng.normal(0.0, 1.0, n)
    out = np.zeros(n)
    simulate_device(u, m, b, 0.0, 0.0, np.array([0]), np.array([n]), np.zeros(1),
                    np.zeros(1), T, 0, out, frac)
    K = 100
    j = int(round(frac * K))
    # measured 0 (generic 0): exact on both targets
    # (a correctly rounded quotient of two exact integers is the literal's own double)
    assert j / K == frac
    uf = np.empty(n * K)
    for k in range(n):
        uf[k * K:k * K + j] = u[k - 1] if k >= 1 else 0.0
        uf[k * K + j:(k + 1) * K] = u[k]
    fine = np.zeros(n * K)
    simulate_device(uf, m, b, 0.0, 0.0, np.array([0]), np.array([n * K]), np.zeros(1),
                    np.zeros(1), T / K, 0, fine, 0.0)
    scale = np.abs(out).max()
    # derived bound: each exact step rounds its state by a few eps (4: the products and
    # sums of x' = x + cxv v + cxu u), the velocity map is contracting (a = e^(-bT/m) < 1)
    # and the position adds the errors up, so the fine run's N K steps are off by at most
    # N K 4 eps of the motion (1.8e-11 here; measured 1e-15)
    assert np.abs(out - fine[::K]).max() <= n * K * 4 * np.finfo(float).eps * scale


@pytest.mark.parametrize("seed", range(16))
def test_a_noise_free_sub_sample_delay_and_its_estimates_hold_their_truths(seed):
    """Property over random noise-free devices with a sub-sample delay (m 0.02-2 kg, b0
    0-5 N s/m, Coulomb 0-0.5 N, d 1-20 to 1e-3 period; lockstep, identify's defaults):
    m, b0, fc (each way) and the delay inside their intervals. The fraction is searched
    to a resolution of ``FRACTION_TOL`` (2e-3 period); a noise-free record's likelihood
    interval is far narrower, and the estimates at the search's last point missed their
    truths by less than the search resolves: 14 of these 16 devices (21 of seeds 0-23:
    b0, fc, m at 1e-4), 0 after the intervals covered the candidates within that
    resolution."""
    import math

    from hapsim.api import excite_and_fit
    rng = np.random.default_rng(9000 + seed)
    dev = {"mass": float(np.exp(rng.uniform(math.log(0.02), math.log(2.0)))),
           "friction": float(rng.uniform(0.0, 5.0)), "coulomb": float(rng.uniform(0.0, 0.5)),
           "delay": round(float(rng.uniform(1.0, 20.0)), 3), "position_resolution": 0.0,
           "noise": 0.0, "hold": "zoh", "force_limit": 10.0}
    fit, rec = excite_and_fit(device=Device(**dev), transport="inprocess", seed=seed,
                              progress=False, handle_signals=False, max_delay=20)
    assert not rec["loop"]["safety_stop"], rec["loop"]["stop_reason"]
    for name, truth in (("mass", dev["mass"]), ("friction", dev["friction"]),
                        ("coulomb_pos", dev["coulomb"]), ("coulomb_neg", dev["coulomb"]),
                        ("delay_estimate", dev["delay"])):
        e = getattr(fit, name)
        assert e.lo <= truth <= e.hi, (name, truth, e, dev)


def test_the_frictions_interval_holds_the_fractions_uncertainty():
    """Coverage over 30 random devices with a delay of 0-4 periods (the family of
    ``tools/identify_subsample.py``, its seed 77: m 0.05-1 kg, b0 0-3 N s/m, Coulomb 0-0.2
    N, noise 0-3 um; 2 s at 4 N, lockstep): the friction moves with the fraction, and an
    interval taken at the best fraction alone missed the friction at the true one (b0
    1.1645 against [1.1587, 1.1641] with the delay 1.3575 inside [1.331, 1.364]): 3 of
    these 30 (8 of 240 over eight seeds). The intervals now also cover the estimates at
    the delay interval's two ends: 0 of these 30 (1 of 240). At most 1 miss of the 90
    truths (m, b0, d) is allowed."""
    rng = np.random.default_rng(77)
    misses = []
    for i in range(30):
        d, dev = _random_device(rng)
        fit, _ = _identify(dev, i)
        for name, ok in (("d", fit.delay_estimate.contains(d)),
                         ("m", fit.mass.contains(dev.mass)),
                         ("b0", fit.friction.contains(dev.friction))):
            if not ok:
                misses.append((i, name, d, fit.delay_estimate, fit.friction))
    assert len(misses) <= 1, misses
