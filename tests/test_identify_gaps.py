"""identify fits every stretch of consecutive STATEs, not only the longest (issue 19).

A record over a real port loses STATEs now and then; the host answers none of them, so the
device holds the force it applied before at the ticks their answers were due. Each stretch
of consecutive ticks is fitted from its own initial state with the mass and frictions
shared (multiple shooting), as ``run``'s measurement does (``measure_felt(lens=)``).

The records here come from an independent simulation written in this file: the exact
zero-order-hold step of ``m x'' + b0 x' = u - fc sign(x')`` from the matrix exponential
(``scipy.linalg.expm`` of the augmented 3x3 system, not the series of
``hapsim.kernels.device_sim``), with the first-order Coulomb rule of the mock's description
(``hapsim.device_model.MockPhysics.advance``: held ``-fc sign(v)``, from rest only a force
beyond ``fc`` moves, a sign change of ``v`` under ``|u| <= fc`` sticks), a host that answers
only the STATEs it received, and a device that applies the answer to tick ``t`` from tick
``t + d`` until a newer one is due.
"""

import math
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from hapsim.analysis.device_fit import applied_force, fit_device
from hapsim.applied import STATUS_FORCE_APPLIED, account_from_force_seq

T = 1e-3


def _lost(rng, n: int, frac: float) -> np.ndarray:
    """Ticks whose STATE never reaches the host: bursts of 1-6, about ``frac`` of them."""
    lost = np.zeros(n, bool)
    k = 30
    while k < n:
        if rng.random() < frac:
            b = int(rng.integers(1, 7))
            lost[k:k + b] = True
            k += b
        k += int(rng.integers(20, 200))
    return lost


def simulate(m, b0, fc, d, n, lost, rng, *, quantum=0.0, noise=0.0, force_limit=4.0,
             prbs=False):
    """The record a host keeps of a device behind a lossy link (module notes), excited as
    ``hapsim identify`` excites (its :class:`~hapsim.pipeline.excitation.ExcitationEngine`,
    answering only the STATEs received, the force clamped to ``force_limit`` [N]).

    Returns ``(seq, position, force, force_seq, status)`` of the received rows: the ticks,
    the positions reported [m], the forces sent answering them [N], and each STATE's
    ``force_seq`` (the tick whose answer the device held) and status bits. ``prbs``: a
    plain binary force of ``0.1 force_limit`` (random holds of 1-40 ticks) on a 1 Hz
    centring spring instead, free of the envelope (many encoder steps on a coarse one).
    """
    from hapsim.pipeline.excitation import ExcitationEngine, excitation_plan
    eng = ExcitationEngine(excitation_plan(n, 1.0 / T, force_limit, 0.01, max_delay=20,
                                           seed=int(rng.integers(1 << 30))))
    eng.set_port_position(0.0)
    E = expm(np.array([[0.0, 1.0, 0.0], [0.0, -b0 / m, 1.0 / m], [0.0, 0.0, 0.0]]) * T)
    x = v = 0.0
    sent = {}                        # tick answered -> force sent
    held, held_seq = 0.0, -1
    rows = []
    level, left = 0.1 * force_limit, 0
    for k in range(n):
        due = k - d
        if due in sent:              # the answer to tick k - d acts from now on
            held, held_seq = sent[due], due
        y = x + (noise * rng.standard_normal() if noise else 0.0)
        if quantum:
            y = quantum * round(y / quantum)
        if not lost[k]:
            if prbs:
                if left == 0:
                    level = -level if rng.random() < 0.5 else level
                    left = int(rng.integers(1, 41))
                left -= 1
                f = level - 40.0 * m * y
            else:
                f = float(np.clip(eng.port_step(y), -force_limit, force_limit))
            sent[k] = f
            rows.append((k, y, f, max(held_seq, 0), STATUS_FORCE_APPLIED if held_seq >= 0
                         else 0))
            if d == 0:               # applied at once (its STATE named the one before)
                held, held_seq = f, k
        # one period with ``held`` (the mock's first-order Coulomb rule)
        c = 0.0
        if fc > 0:
            if v != 0.0:
                c = -fc if v > 0 else fc
            elif abs(held) > fc:
                c = -fc if held > 0 else fc
            else:
                continue
        xn, vn, _ = E @ np.array([x, v, held + c])
        if fc > 0 and v != 0.0 and vn * v < 0 and abs(held) <= fc:
            vn = 0.0
        x, v = float(xn), float(vn)
    seq, pos, force, fseq, status = (np.array(c_) for c_ in zip(*rows))
    return seq.astype(np.int64), pos, force, fseq.astype(np.int64), status.astype(np.int64)


def test_applied_force_follows_the_ticks_not_the_rows():
    """Closed form: rows 0, 1, 2, 5, 6 (ticks 3 and 4 lost), d = 2. Tick 5 is due the
    answer to tick 3, never sent: the device holds the answer to tick 2; tick 6 holds the
    answer to tick 4, never sent either: still tick 2's."""
    seq = np.array([0, 1, 2, 5, 6])
    f = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(applied_force(f, 2, seq=seq), [0, 0, 1, 3, 3])
    np.testing.assert_array_equal(applied_force(f, 2), [0, 0, 1, 2, 3])


def _pieces(seq):
    cut = np.flatnonzero(np.diff(seq) != 1) + 1
    return np.split(np.arange(seq.size), cut)


@settings(max_examples=3, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), frac=st.floats(0.0, 0.6), d=st.integers(1, 20),
       m=st.floats(0.02, 2.0), b0=st.floats(0.0, 5.0), fc=st.floats(0.0, 0.3))
def test_every_stretch_is_fitted_exactly_from_the_applied_force(seed, frac, d, m, b0, fc):
    """Property: a noise-free device behind a link that loses seeded random bursts of
    STATEs is identified from its account (force_seq) to 1e-6 (m, b0, fc), d exact, and
    the model covers more than one stretch of consecutive ticks (the longest alone was
    fitted before)."""
    rng = np.random.default_rng(seed)
    n = 1200
    lost = _lost(rng, n, frac)
    seq, x, f, fseq, status = simulate(m, b0, fc, d, n, lost, rng)
    acc = account_from_force_seq(seq, f, fseq, status)
    fit = fit_device(x, f, T, applied=acc, seq=seq)
    assert acc.delay == d and fit.delay == d and fit.delay_range == (d, d)
    # measured 1.8e-15 relative (generic 8.7e-16), margin 6e8
    assert fit.mass.value == pytest.approx(m, rel=1e-6)
    # measured 5.4e-14 abs, inf rel (generic 1e-13, inf), margin 1e7
    assert fit.friction.value == pytest.approx(b0, rel=1e-6, abs=1e-6)
    # measured 5.6e-17 abs, 1.7e-15 rel (generic 3.1e-16, 3.1e-15), margin 3e9
    assert fit.coulomb.value == pytest.approx(fc, rel=1e-6, abs=1e-6)
    assert fit.mass.contains(m) and fit.friction.contains(b0)
    fitted = [p for p in _pieces(seq) if np.any(np.isfinite(fit.model[p]))]
    assert len(fitted) >= min(2, len(_pieces(seq))), (len(fitted), len(_pieces(seq)))


@settings(max_examples=2, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), frac=st.floats(0.1, 0.6), d=st.integers(0, 4),
       m=st.floats(0.05, 1.0), b0=st.floats(0.0, 3.0))
def test_without_an_account_the_delay_is_found_across_lost_states(seed, frac, d, m, b0):
    """Property: a protocol that names no applied force (the delays 0 .. d + 2 tried on the
    forces sent, shifted in ticks, not rows): the same exactness, d exact."""
    rng = np.random.default_rng(seed)
    lost = _lost(rng, 1200, frac)
    seq, x, f, _, _ = simulate(m, b0, 0.0, d, 1200, lost, rng)
    fit = fit_device(x, f, T, max_delay=d + 2, seq=seq)
    assert fit.delay == d and fit.delay_range == (d, d)
    # measured 4.2e-16 relative (generic 8.4e-16), margin 1e9
    assert fit.mass.value == pytest.approx(m, rel=1e-6)
    # measured 3.1e-15 abs, 1.6e-15 rel (generic 2.7e-15, 1.4e-15), margin 6e8
    assert fit.friction.value == pytest.approx(b0, rel=1e-6, abs=1e-6)


def _gapped_noisy_fit(rng):
    """One seeded random device (m 0.02-2 kg log-uniform, b0 0-5 N s/m, fc 0-0.3 N, d
    1-20, sensor noise 0.5-5 um) behind a link losing bursts of 30 % of its STATEs,
    simulated and fitted from its force_seq account: ``((m, b0, fc, d, noise), seq,
    fit)``."""
    m = float(np.exp(rng.uniform(math.log(0.02), math.log(2.0))))
    b0, fc, d = float(rng.uniform(0, 5)), float(rng.uniform(0, 0.3)), int(rng.integers(1, 21))
    s = float(rng.uniform(0.5e-6, 5e-6))
    lost = _lost(rng, 2000, 0.3)
    seq, x, f, fseq, status = simulate(m, b0, fc, d, 2000, lost, rng, noise=s)
    fit = fit_device(x, f, T, applied=account_from_force_seq(seq, f, fseq, status), seq=seq)
    return (m, b0, fc, d, s), seq, fit


def test_with_noise_every_truth_is_in_its_interval():
    """Seeded random devices (m 0.02-2 kg, b0 0-5, fc 0-0.3 N, d 1-20, sensor noise
    0.5-5 um) behind a link losing bursts of its STATEs: every truth inside its 99.9 %
    interval (3 devices x 4 quantities). (A quantised record's intervals rest on replicates
    through the encoder, tests/test_identify_coarse.py.)"""
    rng = np.random.default_rng(1919)
    for _ in range(3):
        case, seq, fit = _gapped_noisy_fit(rng)
        m, b0, fc, d, _ = case
        assert len(_pieces(seq)) >= 3
        assert fit.delay == d, case
        assert fit.mass.contains(m), (case, fit.mass)
        assert fit.friction.contains(b0), (case, fit.friction)
        assert fit.coulomb_pos.contains(fc), (case, fit.coulomb_pos)
        assert fit.coulomb_neg.contains(fc), (case, fit.coulomb_neg)


# ------------------------------------------------------------- the delay on a coarse encoder
def _coarse_device(rng):
    m = float(np.exp(rng.uniform(math.log(0.02), math.log(2.0))))
    return (m, float(rng.uniform(0, 5)), float(rng.uniform(0, 0.3)), int(rng.integers(0, 21)),
            float(rng.uniform(0, 400e-6)), float(rng.uniform(0, 5e-6)))


def test_on_a_coarse_encoder_the_delay_is_exact_or_said_ambiguous_never_wrong():
    """Property over seeded random devices (m 0.02-2 kg, b0 0-5 N s/m, fc 0-0.3 N, d 0-20,
    encoder quantum 0-400 um, noise 0-5 um) whose protocol names no applied force (the
    delays 0-20 tried): the delay returned as certain is the true one; otherwise the fit
    says it is not determined (``delay_certain`` False, the verdict naming two delays,
    the true one inside ``delay_range``), and with ``ambiguous_delay="refuse"`` it refuses
    naming both. Before, the best delay was returned whatever its rivals (6 wrong delays of
    37 devices fitted over 40 such, ``tools/identify_delay_class.py --white``, e.g. d = 2
    for 4 on a 228 um encoder, the first device here; now 0 returned as determined; 3
    devices here for time, the 40 with the tool)."""
    from hapsim.errors import IdentificationError
    said = {"exact": 0, "ambiguous": 0}
    for i in range(3):               # the first devices of tools/identify_delay_class.py
        rng = np.random.default_rng(7000 + i)
        m, b0, fc, d, q, s = _coarse_device(rng)
        seq, x, f, _, _ = simulate(m, b0, fc, d, 1500, np.zeros(1500, bool), rng, quantum=q,
                                   noise=s, force_limit=float(np.clip(40 * m, 4.0, 40.0)),
                                   prbs=True)
        case = (m, b0, fc, d, q, s)
        try:
            fit = fit_device(x, f, T, max_delay=20)
        except IdentificationError as exc:
            assert "hardly moved" in str(exc) or "does not determine" in str(exc), exc
            continue
        if fit.delay_certain:
            assert fit.delay == d and fit.delay_range == (d, d), (case, fit.delay)
            said["exact"] += 1
            continue
        lo, hi = fit.delay_range
        assert lo <= d <= hi and lo < hi, (case, fit.delay_range)
        # the intervals cover every delay not ruled out, the true one's values included
        assert fit.mass.contains(m) and fit.friction.contains(b0), (case, fit.mass,
                                                                    fit.friction)
        named = [int(v) for v in re.findall(r"d = (\d+) \(", fit.verdict)]
        assert len(named) == 2 and named[0] != named[1], fit.verdict
        assert "not determined" in fit.verdict
        if fit.explained and not said["ambiguous"]:
            with pytest.raises(IdentificationError, match=r"the delay is ambiguous: d = \d+ "
                                                          r".* and d = \d+ .*no delay is chosen"):
                fit_device(x, f, T, max_delay=20, ambiguous_delay="refuse")
        said["ambiguous"] += 1
    assert said["exact"] >= 1 and said["ambiguous"] >= 1, said


def test_intervals_hold_their_level_on_records_cut_into_short_stretches():
    """Coverage, the class behind the test above: 40 seeded random devices (its ranges)
    behind a link losing bursts of 30 % of its STATEs, 200 truths (m, b0, fc+, fc-, d).
    Each stretch's fitted state leaves its residual negatively autocorrelated, which the
    Newey-West sum at lag 50 counted against the variance on the short stretches: before
    the heteroskedasticity-robust floor (``hapsim.analysis.device_fit``, ``intervals``)
    3 of these 200 truths fell outside their 99.9 % intervals (and 15 of 750 of 150 more
    devices of the family, seed 7), after it 0 (and 0 of 750). At the intervals' level
    0.2 misses are expected of 200; at most 1 is allowed (the chance of 2 or more at the
    stated level: 1.7 %; at the earlier 2 % miss rate, 91 %)."""
    rng = np.random.default_rng(2929)
    misses = []
    for i in range(40):
        case, _, fit = _gapped_noisy_fit(rng)
        m, b0, fc, d, _ = case
        for name, ok in (("m", fit.mass.contains(m)), ("b0", fit.friction.contains(b0)),
                         ("fc+", fit.coulomb_pos.contains(fc)),
                         ("fc-", fit.coulomb_neg.contains(fc)), ("d", fit.delay == d)):
            if not ok:
                misses.append((i, name, case))
    assert len(misses) <= 1, misses


def test_a_noise_of_twice_the_quantum_or_more_is_inside_its_interval():
    """Coverage of the sensor noise on a quantised record whose noise dominates (noise
    5-50 um, quantum 5-50 % of it: at least twice the quantum), 24 seeded random devices
    of the ranges above, no STATE lost, 72 truths (noise, m, b0). The fitted stretch
    states take a share of the noise out of the residual, which the quantised likelihood
    read: its interval fell below the truth in 2 of these 24 devices (4 of 40 of this
    draw; 8 of 480 blind devices, ``tools/identify_blind.py --mode inprocess``, seeds
    101-112). Where the noise is at least twice the quantum the quantiser's error is
    white and uniform (Widrow & Kollar 2008), and the noise is read from the residual's
    second differences less ``q^2/12``: 0 of 40 miss. At most 1 miss is allowed (at the
    intervals' 99.9 %, 0.07 expected)."""
    rng = np.random.default_rng(6)
    misses = []
    for i in range(24):
        m = float(np.exp(rng.uniform(math.log(0.02), math.log(2.0))))
        b0, fc, d = float(rng.uniform(0, 5)), float(rng.uniform(0, 0.3)), int(rng.integers(1, 21))
        s = float(rng.uniform(5e-6, 50e-6))
        q = float(rng.uniform(0.05, 0.5)) * s
        seq, x, f, fseq, status = simulate(m, b0, fc, d, 4000, np.zeros(4000, bool), rng,
                                           noise=s, quantum=q)
        fit = fit_device(x, f, T, applied=account_from_force_seq(seq, f, fseq, status),
                         seq=seq)
        for name, ok in (("noise", fit.noise.contains(s)), ("m", fit.mass.contains(m)),
                         ("b0", fit.friction.contains(b0))):
            if not ok:
                misses.append((i, name, (m, b0, fc, d, s, q), fit.noise))
    assert len(misses) <= 1, misses
