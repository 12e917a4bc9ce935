"""A record with too few oscillation cycles above its floor says what would give enough
(hapsim.analysis.cycles), and following what it says gives a measurement.

The closed forms of hapsim.analysis.cycles are checked against an independent count: the
decaying envelope sampled on a grid 50 times finer than the period, the time above the
level counted sample by sample (no logarithm). Then measure_felt on quantised records of
a damped oscillation: the record it refuses for too few cycles, changed as its error says
(a start g times larger, or s more seconds), is measured.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from hapsim.analysis.cycles import more_cycles, seconds_above
from hapsim.analysis.identify import MIN_CYCLES, measure_felt
from tolerance import measured

T = 1e-3
#: The grid of the independent count: the period over this.
FINE = 50


def _counted(amps, lens, sigma, level, scale=1.0):
    """Seconds above ``level``, summed over the stretches, by counting grid points."""
    total = 0.0
    dt = T / FINE
    for a, n in zip(amps, lens):
        t = np.arange(int(n) * FINE) * dt
        total += dt * np.count_nonzero(scale * a * np.exp(-sigma * t) > level)
    return total


def _case(rng):
    k = int(rng.integers(1, 6))
    lens = rng.integers(50, 2000, size=k)
    level = 1e-4
    amps = level * np.exp(rng.uniform(-0.5, 3.0, size=k))
    sigma = float(np.exp(rng.uniform(math.log(0.3), math.log(30.0))))
    hz = float(rng.uniform(1.0, 20.0))
    return amps, lens, sigma, level, hz


@pytest.mark.parametrize("seed", range(40))
def test_the_closed_forms_match_a_sampled_envelope_and_the_remedy_is_the_least(seed):
    rng = np.random.default_rng(seed)
    amps, lens, sigma, level, hz = _case(rng)
    # the grid count is off by at most one grid step per stretch (derived)
    tol = len(lens) * T / FINE
    assert sum(seconds_above(amps, lens, sigma, level, T)) == pytest.approx(
        _counted(amps, lens, sigma, level), abs=tol)
    have = hz * sum(seconds_above(amps, lens, sigma, level, T))
    need = have + float(rng.uniform(0.1, 2.0))
    how, v = more_cycles(amps, lens, sigma, level, T, hz, need)
    if how == "longer":
        # the last stretch v seconds longer gives need, and no less than v does
        grown = list(lens[:-1]) + [lens[-1] + v / T]
        # the same sums in another order: measured 2.0e-16 over the 40 cases, margin 50
        assert hz * sum(seconds_above(amps, grown, sigma, level, T)) == pytest.approx(
            need, rel=measured(2.0e-16, 50.0))
    elif how == "larger":
        # g times every amplitude gives need (by the independent count, to its grid), and
        # a start 1 % smaller does not reach it
        assert hz * _counted(amps, lens, sigma, level, v) >= need - hz * tol
        assert hz * sum(seconds_above(amps, lens, sigma, level, T, v * 0.99)) < need
    else:
        assert how == "stretches"
        # even every stretch above the level over its whole length falls short
        assert hz * T * sum(int(n) for a, n in zip(amps, lens) if a > 0) < need


def test_every_remedy_is_reached_over_the_cases():
    """The cases above exercise both remedies and the refusal (a test of the test)."""
    seen = set()
    for seed in range(40):
        rng = np.random.default_rng(seed)
        amps, lens, sigma, level, hz = _case(rng)
        have = hz * sum(seconds_above(amps, lens, sigma, level, T))
        seen.add(more_cycles(amps, lens, sigma, level, T, hz,
                             have + float(rng.uniform(0.1, 2.0)))[0])
    assert seen == {"longer", "larger", "stretches"}


def _measure(A, n, sigma, f_hz, q=1e-4, mass=0.05):
    """measure_felt of a quantised damped oscillation ``A exp(-sigma t) cos(2 pi f t)``."""
    s = complex(-sigma, 2.0 * math.pi * f_hz)
    z = complex(np.exp(s * T))
    t = np.arange(n) * T
    y = q * np.round(A * np.exp(-sigma * t) * np.cos(2.0 * math.pi * f_hz * t) / q)
    return measure_felt(y, T, mass, [z, z.conjugate()], z, quantum=q)


@pytest.mark.parametrize("sigma, f_hz, A, n, remedy", [
    (6.0, 5.0, 1.2e-3, 3000, "larger"),    # decays below 5 steps within the record
    (12.0, 8.0, 1.0e-3, 3000, "larger"),
    (0.5, 5.0, 3.0e-3, 200, "longer"),     # light damping, a record cut short
    (1.0, 3.0, 2.0e-3, 300, "longer"),
])
def test_a_record_changed_as_its_error_says_is_measured(sigma, f_hz, A, n, remedy):
    r = _measure(A, n, sigma, f_hz)
    assert r["cycles"] < MIN_CYCLES and "too few for a measurement" in r["error"]
    if remedy == "larger":
        g = float(re.search(r"a start about ([0-9.e+-]+) times larger", r["error"]).group(1))
        # 10 % over the printed factor (three digits): at the factor itself the refit of
        # the new record counted 1.491-1.547 cycles (its own rounding and fit), with 10 %
        # 1.570-1.611 (measured)
        again = _measure(A * g * 1.1, n, sigma, f_hz)
    else:
        s = float(re.search(r"about ([0-9.e+-]+) s more", r["error"]).group(1))
        # 10 % over the printed seconds (two digits): at them the refit counted
        # 1.49998-1.50003 cycles, with 10 % 1.555-1.563 (measured)
        again = _measure(A, n + int(math.ceil(1.1 * s / T)), sigma, f_hz)
    assert "error" not in again, again.get("error")
    assert again["cycles"] >= MIN_CYCLES


def test_the_edges_answer_without_an_exception():
    """A heavily damped pair over a long record (the bisection's bound far beyond the
    answer: exp of it overflowed), a pair that does not oscillate, no decay with a stretch
    under the floor, and a last stretch ending at a disturbance."""
    from hapsim.analysis.cycles import more_cycles_hint
    # sigma n T = 3000: the whole-length scale is e^3000; the answer, one stretch decaying
    # within its length, is the closed form (level / a) exp(sigma need / f)
    how, g = more_cycles([1e-3], [60000], 50.0, 4e-4, T, 5.0, 1.5)
    # the bisection stops at 1e-12 of log g (15 here): derived, 2e-11 relative in g
    assert how == "larger" and g == pytest.approx(0.4 * math.exp(15.0), rel=1e-10)
    assert more_cycles([1e-3], [100], 5.0, 1e-5, T, 0.0, 3.0) == ("none", 0.0)
    assert more_cycles_hint([1e-3], [100], 5.0, 1e-5, T, 0.0, 3.0, True) == ""
    # no decay: the second stretch (5 s, under the floor) needs only to be lifted above it
    how, g = more_cycles([1e-3, 1e-6], [100, 5000], -1.0, 1e-5, T, 10.0, 3.0)
    assert how == "larger" and 10.0 < g < 10.0 * (1 + 1e-9)
    # the same short record, its last stretch ending at a disturbance: not "longer"
    args = ([3e-3], [200], 0.5, 5e-4, T, 5.0, 1.5)
    assert more_cycles(*args)[0] == "longer"
    assert more_cycles(*args, ends_record=False)[0] != "longer"


def test_a_count_short_of_the_need_never_reads_as_the_need():
    """Records cut one sample apart around the need: every refusal's printed count is
    below :data:`MIN_CYCLES` and the count to its second digit (two digits of 1.47 read
    "1.5", the count needed: said by the verdict fuzz on the wall clock, a FireFader's
    "only 1.5 oscillation cycles ... would give 1.5"), the records just short of it
    included."""
    shown = []
    for n in range(280, 320):
        r = _measure(3e-3, n, 0.5, 5.0)
        if "error" not in r:
            continue
        got = float(re.search(r"only ([0-9.e+-]+) oscillation cycles", r["error"]).group(1))
        # (rounded to two digits, or down: within one unit of the second)
        unit = 10.0 ** (math.floor(math.log10(r["cycles"])) - 1)
        assert got < MIN_CYCLES and abs(got - r["cycles"]) <= unit, (n, got, r["cycles"])
        shown.append(r["cycles"])
    # (the test's test: records whose two digits round up to the need were among them)
    assert any(float(f"{c:.2g}") >= MIN_CYCLES for c in shown), shown


@pytest.mark.parametrize("seed", range(40))
def test_the_remedy_printed_is_never_short_of_the_one_computed(seed):
    """The factor and the seconds the hint prints are the computed remedy rounded up to
    their digits (three, two): following the words gives the cycles (a factor of 1.0004
    printed "1" would give none)."""
    from hapsim.analysis.cycles import more_cycles_hint
    rng = np.random.default_rng(seed)
    amps, lens, sigma, level, hz = _case(rng)
    need = hz * sum(seconds_above(amps, lens, sigma, level, T)) + float(
        rng.uniform(0.1, 2.0))
    how, v = more_cycles(amps, lens, sigma, level, T, hz, need)
    text = more_cycles_hint(amps, lens, sigma, level, T, hz, need, True)
    if how == "larger":
        got, digits = float(re.search(r"about ([0-9.e+-]+) times", text).group(1)), 3
    elif how == "longer":
        got, digits = float(re.search(r"about ([0-9.e+-]+) s more", text).group(1)), 2
    else:
        return
    unit = 10.0 ** (math.floor(math.log10(v)) - digits + 1)
    # (up by less than one unit of the last digit; the 1e-9 units the rounding forgives)
    assert v - 1e-9 * unit <= got < v + unit, (how, v, got)
