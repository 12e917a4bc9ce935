"""Robust stability certified over the continuous ranges of a hand family (issue 22): a
grid cannot miss a narrow unstable band, and a certified verdict is true between samples.

The reference is an independent model: the handle + hand written out here, its ZOH by
``scipy.linalg.expm`` of the augmented matrix, the delayed virtual spring-damper as a
shift register, and numpy's eigenvalues (no hapsim code)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.linalg as sl

from hapsim.cli import main

T = 1e-3

SCENE = """rate_hz: 1000
masses:
  - {{name: hand, kind: port}}
  - {{name: wall, kind: ground, x0: 0.0}}
links:
  - {{name: wall, kind: spring_damper, between: [hand, wall], stiffness: {K!r}, damping: {B!r}}}
device:
  mass: {mc!r}
  friction: {bc!r}
  delay: 1
  hold: zoh
  force_limit: 10.0
  hand:
    mass: {mh!r}
    damping: {bh!r}
    grip_stiffness: [{lo!r}, {hi!r}]
    grip_damping: 0.0
excitation:
  x0: 0.005
"""


def independent_rho(mc, bc, mh, bh, kg, K, B, d=1):
    """Spectral radius of the closed loop, built without hapsim: plant [xh, vh, xm, vm]
    (grip damping 0), exact ZOH, F[n] = -K x[n-d] - B (x[n-d] - x[n-d-1]) / T."""
    A = np.array([[0, 1, 0, 0], [-kg / mc, -bc / mc, kg / mc, 0],
                  [0, 0, 0, 1], [kg / mh, 0, -kg / mh, -bh / mh]], float)
    M = np.zeros((5, 5))
    M[:4, :4], M[1, 4] = A, 1.0 / mc
    E = sl.expm(M * T)
    n = 4 + d + 1
    S = np.zeros((n, n))
    f = np.zeros(n)
    f[4 + d - 1], f[4 + d] = -(K + B / T), B / T
    S[:4, :4] = E[:4, :4]
    S[:4, :] += np.outer(E[:4, 4], f)
    S[4, 0] = 1.0
    for i in range(1, d + 1):
        S[4 + i, 3 + i] = 1.0
    return float(np.abs(np.linalg.eigvals(S)).max())


def _banded_families(count, seed=0):
    """Random devices and hands whose grip range has one narrow unstable band strictly
    between two points of the 9-point geometric grid: located on a scan (hapsim's batched
    poles, for speed), then the grid points and the band's edges checked with the
    independent model."""
    from hapsim.analysis.family import family_poles
    from hapsim.scene import parse_scene
    rng = np.random.default_rng(seed)
    out = []
    scan = np.geomspace(2e3, 4e5, 400)
    for _ in range(100):
        p = dict(mc=float(rng.uniform(0.045, 0.06)), bc=float(rng.uniform(0.52, 0.57)),
                 mh=float(rng.uniform(0.045, 0.06)), bh=float(rng.uniform(0.9, 1.1)),
                 K=float(rng.uniform(950.0, 1050.0)), B=float(rng.uniform(1.15, 1.25)))
        sc = parse_scene(SCENE.format(lo=2e3, hi=4e5, **p))
        mem = np.zeros((scan.size, 5))
        mem[:, 0], mem[:, 1], mem[:, 2] = p["mh"], p["bh"], scan
        rho = np.abs(family_poles(sc, mem)).max(axis=1)
        bad = np.flatnonzero(rho > 1.0)
        if not bad.size or bad[-1] - bad[0] + 1 != bad.size or bad[0] == 0 \
                or bad[-1] == scan.size - 1:
            continue
        b1, b2 = scan[bad[0] - 1], scan[bad[-1] + 1]    # stable just outside
        mid = math.sqrt(scan[bad[0]] * scan[bad[-1]])
        r = 3.0 * b2 / b1
        i = int(rng.integers(1, 7))
        lo = math.sqrt(b1 * b2 / r) / r ** i
        grid = lo * r ** np.arange(9)
        ind = [independent_rho(p["mc"], p["bc"], p["mh"], p["bh"], g, p["K"], p["B"])
               for g in list(grid) + [b1, b2, mid]]
        if max(ind[:11]) >= 1.0 or ind[11] <= 1.0:
            continue
        out.append(dict(p, lo=float(grid[0]), hi=float(grid[-1]), band=(b1, b2)))
        if len(out) == count:
            return out
    raise AssertionError("no banded family found")


def test_a_band_between_grid_points_is_never_robustly_stable(tmp_path, capsys):
    """Every sampled member of these families is stable (independently checked), the
    unstable band lies between two of them: the verdict is NOT robustly stable, certified,
    with an unstable member the independent model confirms inside the band."""
    from hapsim.analysis.family import family
    from hapsim.scene import parse_scene
    for k, p in enumerate(_banded_families(4)):
        text = SCENE.format(**p)
        res = family(parse_scene(text), certify=4096)
        assert np.all(res.stable)                      # the grid alone would say robust
        assert not res.robust and res.robust_method == "certified"
        ce = res.certificate.counterexample
        assert p["band"][0] < ce[2] < p["band"][1]
        assert independent_rho(p["mc"], p["bc"], p["mh"], p["bh"], ce[2], p["K"],
                               p["B"]) > 1.0
        if k == 0:
            f = tmp_path / "band.yaml"
            f.write_text(text)
            assert main(["family", str(f), "--json"]) == 1
            rep = json.loads(capsys.readouterr().out)
            # what is proven: the bounds in floating point, their rounding not bounded
            assert rep["verdict"] == ("not robustly stable (certified in floating point: "
                                      "rounding not bounded)")
            assert rep["certificate"]["arithmetic"] == "floating point: rounding not bounded"
            assert rep["unstable"] == 0 and rep["certificate"]["counterexample"]
            assert main(["family", str(f), "--certify-boxes", "0"]) == 0
            out = capsys.readouterr().out
            assert "sampled (12)" in out and "not certified" in out


@pytest.mark.parametrize("seed", range(3))
def test_a_certified_stable_family_is_stable_between_its_samples(seed):
    """Narrow random ranges that the subdivision proves stable are stable at 200 members
    between the samples, by the independent model."""
    from hapsim.analysis.family import family
    from hapsim.scene import parse_scene
    rng = np.random.default_rng(100 + seed)
    p = dict(mc=float(rng.uniform(0.05, 0.1)), bc=float(rng.uniform(0.5, 1.0)),
             mh=float(rng.uniform(0.05, 0.3)), bh=float(rng.uniform(0.5, 1.5)),
             K=float(rng.uniform(300.0, 800.0)), B=float(rng.uniform(0.5, 1.5)))
    lo = float(rng.uniform(500.0, 3000.0))
    p.update(lo=lo, hi=lo * 1.2)
    res = family(parse_scene(SCENE.format(**p)), certify=4096)
    assert res.robust and res.robust_method == "certified", res.certificate
    for kg in np.linspace(p["lo"], p["hi"], 200):
        assert independent_rho(p["mc"], p["bc"], p["mh"], p["bh"], kg, p["K"], p["B"]) < 1.0
