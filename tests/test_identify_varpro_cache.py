"""The variable projection's column cache (hapsim.analysis.identify._ColumnCache, issue 31
item 2: string.yaml's felt-pair fit recomputed every mode's columns for each of the
finite-difference Jacobian's ~100 columns) changes no bit of the fit: the refined poles and
the cost with the cache equal those without it, on records of several modes, one stretch
or several, with an offset or a real pole."""

from __future__ import annotations

import numpy as np
import pytest

import hapsim.analysis.identify as ident


class _NoCache(ident._ColumnCache):
    """Never hits: every column recomputed, as before the cache."""

    def get(self, key):
        return None


def _record(rng, pairs, n, real=None, offset=0.0):
    t = np.arange(n, dtype=float)
    y = np.full(n, offset)
    spec = []
    for _ in range(pairs):
        a, w = rng.uniform(0.002, 0.02), rng.uniform(0.05, 2.5)
        y += rng.normal() * np.exp(-a * t) * np.cos(w * t + rng.uniform(0, 6.3))
        # the start a little off the truth: the optimiser has work to do
        spec.append(["pair", a * (1 + 0.05 * rng.normal()), w * (1 + 0.002 * rng.normal())])
    if real is not None:
        y += 0.5 * real ** t
        spec.append(["real", real * 0.99])
    return y + 1e-4 * rng.standard_normal(n), spec


@pytest.mark.parametrize("case", [
    {"pairs": 6, "n": 600},
    {"pairs": 4, "n": 500, "lens": [180, 170, 150]},
    {"pairs": 3, "n": 400, "real": 0.97, "offset": 0.3},
])
def test_varpro_column_cache_changes_no_bit(case, monkeypatch):
    rng = np.random.default_rng(31)
    y, spec = _record(rng, case["pairs"], case["n"], case.get("real"), case.get("offset", 0.0))
    offset = "offset" in case
    lens = case.get("lens")
    got = ident._varpro([list(s) for s in spec], y, offset, lens)
    monkeypatch.setattr(ident, "_ColumnCache", _NoCache)
    want = ident._varpro([list(s) for s in spec], y, offset, lens)
    assert got[1] == want[1]                                  # the cost, bit for bit
    assert got[0] == want[0]                                  # every refined pole
    assert want[0] != spec                                    # it did refine them


def test_basis_without_derivatives_or_from_the_cache_is_the_same_matrix():
    spec = [["pair", 0.01, 0.3], ["pair", 0.0, 1.1], ["real", 0.95], ["real", -0.0]]
    theta = ident._theta(spec)
    phi, dcols = ident._basis(spec, theta, 300, True)
    cache = ident._ColumnCache(20)
    for _ in range(2):           # the second time every column comes from the cache
        phi2, none = ident._basis(spec, theta, 300, True, derivatives=False, cache=cache)
        assert none is None
        assert np.array_equal(phi, phi2) and np.array_equal(np.signbit(phi), np.signbit(phi2))
    phi3, dcols3 = ident._basis(spec, theta, 300, True, cache=cache)
    assert np.array_equal(phi, phi3) and len(dcols3) == len(dcols) == theta.size
    for p1, p3 in zip(dcols, dcols3):
        for (i1, d1), (i3, d3) in zip(p1, p3):
            assert i1 == i3 and np.array_equal(d1, d3)
    # a mode whose parameters differ by one bit is not taken from the cache
    th = theta.copy()
    th[0] = np.nextafter(th[0], 1.0)
    fresh, _ = ident._basis(spec, th, 300, True)
    cached, _ = ident._basis(spec, th, 300, True, derivatives=False, cache=cache)
    assert np.array_equal(fresh, cached) and not np.array_equal(fresh[:, 0], phi[:, 0])
