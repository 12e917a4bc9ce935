"""Rows after a record's first cut beyond what the undisturbed records do are left out
(:func:`hapsim.analysis.felt_records.within_excursion`): by the motion's norm and along
each engaged contact's opening, checked against the contact laws themselves over random
scenes and records (the laws written here, not taken from the code under test)."""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.analysis.felt_records import within_excursion
from hapsim.lockstep import LockstepND, excitation_starts
from test_bound_at_records import _scene


def _laws(D, normal, centre, threshold):
    """The motion toward each opening [m]: the plane's penetration falls by ``D . n``; the
    ring's distance ``|D - c|`` (the handle rests at the origin) grows past its rest."""
    ring = np.linalg.norm(D - centre, axis=1) - np.linalg.norm(centre)
    return D @ normal, ring


def _case(seed) -> int:
    """One random case, its assertions; returns the rows after a cut the norm alone kept
    and an opening's motion leaves out."""
    rng = np.random.default_rng(seed)
    dim = 2 + seed % 2
    sc, normal, _p0, centre, threshold = _scene(rng, dim)
    N, a = 120, float(rng.uniform(5e-5, 2e-4))
    rest = LockstepND(sc).step(N, record=True)
    clean = [LockstepND(sc, x0=x0, v0=v0).step(N, record=True) - rest
             for x0, v0 in excitation_starts(dim, a, sc.period)[1:]]
    nominal = max(float(np.max(np.linalg.norm(d, axis=1))) for d in clean)
    plane_nom = max(float(np.max(_laws(d, normal, centre, threshold)[0])) for d in clean)
    ring_nom = max(float(np.max(_laws(d, normal, centre, threshold)[1])) for d in clean)
    diffs, usable = [], []
    for d in clean:
        d = d * rng.uniform(0.5, 2.5)
        k0 = int(rng.integers(0, N - 10))
        d[k0:k0 + 10] += rng.normal(size=dim) * nominal * rng.uniform(0.2, 1.5)
        u = rng.uniform(size=N) > 0.05
        u[int(rng.integers(5, N - 5))] = False           # at least one cut
        diffs.append(d)
        usable.append(u)
    out = within_excursion(sc, diffs, usable, a)
    hits = 0
    for d, u, o in zip(diffs, usable, out):
        first = int(np.flatnonzero(~u)[0])
        assert np.array_equal(o[:first + 1], u[:first + 1])
        plane, ring = _laws(d, normal, centre, threshold)
        # the laws' rounding against the code's (the same sums in another order): a few
        # ulps of the 10-30 mm ring radius
        tol = 8 * float(np.spacing(np.linalg.norm(centre)))
        inside = ((np.linalg.norm(d, axis=1) <= nominal) & (plane <= plane_nom + tol)
                  & (ring <= ring_nom + tol))
        sure = ((np.linalg.norm(d, axis=1) <= nominal) & (plane <= plane_nom - tol)
                & (ring <= ring_nom - tol))
        after = np.arange(N) > first
        assert not np.any(o[after] & ~inside[after])             # nothing beyond is kept
        assert np.all(o[after] | ~(u & sure)[after])             # nothing within is lost
        # the rows the norm alone would keep and an opening's motion leaves out
        hits += int(np.sum(after & u & (np.linalg.norm(d, axis=1) <= nominal) & ~inside))
    return hits


@pytest.mark.parametrize("seed", range(30))
def test_rows_after_a_cut_stay_within_the_undisturbed_motion_along_each_opening(seed):
    """Random 2-D and 3-D scenes (a plane and a ring contact on the handle), random records
    (the undisturbed ones scaled by 0.5-2.5 and pushed along random directions over random
    rows) cut at a random row: the rows before the first cut are kept as they were; a row
    after it is kept exactly when it was usable and its motion's norm and its motion
    toward the plane's and the ring's opening are within the undisturbed records'."""
    _case(seed)


def test_the_openings_reach_rows_the_norm_kept():
    """The class the norm alone missed is exercised: in most of the random cases some
    rows after a cut are within the undisturbed norm and beyond an opening's motion
    (measured: 29 of the 30 seeds, 2-108 rows each)."""
    assert sum(_case(seed) > 0 for seed in range(30)) >= 25
