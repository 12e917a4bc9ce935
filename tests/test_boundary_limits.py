"""Figures given to the precision they are known, and where they are taken (issue 22):
the spectral radius at K_max, and the compare-corrections slopes in the limit K, B -> 0."""

from __future__ import annotations

import json
import math
from fractions import Fraction

import numpy as np
import pytest

from hapsim.analysis.compare import default_corrections, tangency, tangency_limit
from hapsim.analysis.loop import LoopModel
from hapsim.analysis.loop_poles import spectral_radius_known
from hapsim.analysis.stability import stability_limit
from hapsim.cli import main


def test_stability_reports_a_double_pole_radius_to_the_digits_known(capsys):
    """Ideal hold, d = 0, no damping: K_max = 4 m/T^2 puts a double pole at z = -1, whose
    modulus double arithmetic knows to ~1e-7; the report rounds to that and states the
    error, which covers the true modulus at the float K_max (closed form: z^2 + (kappa -
    2) z + 1, radius (|kappa - 2| + sqrt((kappa - 2)^2 - 4)) / 2, kappa exact as a
    fraction)."""
    assert main(["stability", "--mass", "0.1", "--friction", "0", "--rate", "1000",
                 "--delay", "0", "--hold", "ideal", "--B", "0", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    err = d["spectral_radius_error"]
    assert 1e-9 < err < 1e-6
    assert d["spectral_radius_at_K_max"] == 1.0
    kappa = Fraction(d["K_max"]) * Fraction(1, 1000) ** 2 / Fraction(0.1)
    disc = (kappa - 2) ** 2 - 4
    true = (abs(float(kappa - 2)) + math.sqrt(max(float(disc), 0.0))) / 2
    loop = LoopModel(0.1, 0.0, 1000.0, 0, "ideal")
    rho, err2 = spectral_radius_known(loop, d["K_max"])
    assert abs(rho - true) <= err2 and err2 == err


@pytest.mark.parametrize("seed", range(8))
def test_radius_at_simple_crossings_is_known_to_round_off(seed):
    """A simple pole on the circle at K_max (delay, friction): the error bound is tiny and
    the radius is 1 within it."""
    rng = np.random.default_rng(seed)
    loop = LoopModel(float(rng.uniform(0.05, 1.0)), float(rng.uniform(0.1, 2.0)), 1000.0,
                     int(rng.integers(1, 6)), str(rng.choice(["zoh", "ideal"])))
    B = float(rng.uniform(0.0, 1.0))
    rho, err = spectral_radius_known(loop, stability_limit(loop, B), B)
    # err is spectral_radius_known's derived bound; the floor 1e-12 where err is below the
    # radius's own rounding: measured 1.1e-16 (generic 1.1e-16), margin 9000
    assert err < 1e-9 and abs(rho - 1.0) <= max(err, 1e-12)


@pytest.mark.parametrize("d", [0, 1, 3])
@pytest.mark.parametrize("hold,half", [("zoh", 0.5), ("ideal", 0.0)])
def test_slopes_in_the_limit_are_the_closed_form(d, hold, half):
    """Without friction the limit Jacobian is exactly [[1, 0], [-(d + 1/2), 1]] (ZOH) or
    [[1, 0], [-d, 1]] (ideal hold): the delay's tilt (Diolaiti et al. 2006 at b0 = 0)."""
    J = tangency_limit(LoopModel(0.1, 0.0, 1000.0, d, hold))
    # measured 0 (generic 0): exact on both targets
    assert np.allclose(J, [[1.0, 0.0], [-(d + half), 1.0]], atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_slopes_in_the_limit_are_where_the_finite_ones_converge(seed):
    """Each correction's limit equals the central differences taken 100 and 200 times
    closer to the origin (K T^2/m = B T/m = 1e-5, 5e-6), extrapolated (Richardson: the
    error is linear there), to 2e-3, while at compare-corrections' finite point (1e-3) a
    virtual coupling is 0.19 off."""
    rng = np.random.default_rng(seed)
    loop = LoopModel(float(rng.uniform(0.05, 0.5)), float(rng.uniform(0.1, 1.0)), 1000.0,
                     int(rng.integers(0, 3)), "zoh")
    for corr in default_corrections(loop):
        if corr is not None and corr.kind == "inertia_compensation":
            continue   # the finite difference follows another pair there
        lp = LoopModel(**{k: v for k, v in loop.to_dict().items()}, correction=corr)
        rich = 2.0 * tangency(lp, at=5e-6, step=5e-9) - tangency(lp, at=1e-5, step=1e-8)
        # not round-off: Richardson's leftover second-order term; measured 6.6e-5
        # (generic 6.6e-5), margin 30
        assert np.allclose(tangency_limit(lp), rich, atol=2e-3), corr
    vc = LoopModel(0.1, 0.5, 1000.0, 1, correction=default_corrections(
        LoopModel(0.1, 0.5, 1000.0, 1))[-1])
    assert abs(tangency(vc)[0, 0] - tangency_limit(vc)[0, 0]) > 0.1
