"""The characteristic function's pieces kept on the loop (issue 31 item 2: a grid or a
stability sweep asked :func:`hapsim.analysis.loop.char_parts` for them, and
``loop_poles._char_poly_z`` for their powers of ``z``, at every evaluation, ~150,000 times
for one grid): the kept pieces, ``char_eval`` and the closed-loop poles equal what numpy's
``polyval`` / ``polyder`` and the uncached computation give, bit for bit, over random loops
of every kind (plain, both holds, split delay, hand behind a grip, real spring, each
correction); the kept arrays cannot be written."""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.analysis import loop as lp
from hapsim.analysis import loop_poles
from hapsim.analysis.corrections import Correction
from hapsim.analysis.loop import LoopModel


def _loops(rng):
    out = []
    for _ in range(6):
        m = float(np.exp(rng.uniform(-4, 1)))
        b0 = float(rng.uniform(0, 3))
        rate = float(rng.choice([500.0, 1000.0, 4000.0]))
        d = int(rng.integers(0, 6))
        out += [LoopModel(m, b0, rate, d, hold="zoh"), LoopModel(m, b0, rate, d, hold="ideal"),
                LoopModel(m, b0, rate, d + 0.4, hold="zoh"),
                LoopModel(m, b0, rate, d, stiffness=50.0 * m),
                LoopModel(m, b0, rate, d, hand_mass=0.5 * m, hand_damping=0.5 * b0,
                          grip_stiffness=2000.0, grip_damping=1.0)]
        for corr in (Correction("velocity_filter", cutoff_hz=rate / 8),
                     Correction("prediction", horizon=1.0),
                     Correction("inertia_compensation", mass=0.3 * m),
                     Correction("virtual_coupling", stiffness=3000.0, damping=2.0)):
            out.append(LoopModel(m, b0, rate, d, correction=corr))
    return out


def _polyval_char_eval(P, Q, D, e, kappa, beta, w):
    """char_eval as written before the pieces were kept: numpy's polyval and polyder."""
    z = 1.0 + w
    ze = z ** e
    f = kappa * np.polyval(P, w) + beta * np.polyval(Q, w) + ze * np.polyval(D, w)
    zem1 = z ** (e - 1) if e > 0 else np.zeros_like(z)
    df = (kappa * np.polyval(np.polyder(P), w) + beta * np.polyval(np.polyder(Q), w)
          + e * zem1 * np.polyval(D, w) + ze * np.polyval(np.polyder(D), w))
    return f, df


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True) \
        and np.array_equal(np.signbit(a.real), np.signbit(b.real)) \
        and np.array_equal(np.signbit(np.imag(a)), np.signbit(np.imag(b)))


def test_kept_pieces_and_char_eval_are_the_computation_bit_for_bit():
    rng = np.random.default_rng(31)
    for loop in _loops(rng):
        fresh = lp._char_parts_of(loop)
        kept = lp.char_parts(loop)
        assert lp.char_parts(loop) is kept                       # kept, not recomputed
        assert kept[3] == fresh[3]
        for a, b in zip(kept[:3], fresh[:3]):
            assert _same(a, np.asarray(b)), (loop, a, b)
            assert not a.flags.writeable
            with pytest.raises(ValueError):
                a[0] = 1.0
        kappa, beta = float(rng.uniform(0, 0.5)), float(rng.uniform(-0.2, 0.5))
        w = (rng.normal(size=40) + 1j * rng.normal(size=40)) * rng.choice([1e-6, 1e-2, 1.0])
        for x in (w, w[3]):
            f, df = lp.char_eval(loop, kappa, beta, x, derivative=True)
            rf, rdf = _polyval_char_eval(*fresh, kappa, beta, np.asarray(x, dtype=complex))
            assert _same(f, rf) and _same(df, rdf), loop
            assert _same(lp.char_eval(loop, kappa, beta, x), rf)
        zP, zQ, R = loop_poles._z_parts(loop)
        P, Q, D, e = fresh
        assert _same(zP, lp.w_to_z(P)) and _same(zQ, lp.w_to_z(Q))
        assert _same(R, np.concatenate([lp.w_to_z(D), np.zeros(e)]))


def test_poles_of_a_fresh_loop_equal_those_of_a_used_one():
    """roots_w on a loop whose pieces are kept (asked many times) equals roots_w on an
    equal loop asked for the first time: nothing of one call leaks into the next."""
    rng = np.random.default_rng(7)
    for loop in _loops(rng)[:24]:
        gains = [(float(rng.uniform(0, 0.3)), float(rng.uniform(0, 0.3))) for _ in range(4)]
        used = [loop_poles.roots_w(loop, k, b) for k, b in gains]
        for (k, b), got in zip(gains, used):
            twin = LoopModel(**{f: getattr(loop, f) for f in loop.__dataclass_fields__})
            assert twin == loop and "_char_parts" not in twin.__dict__
            assert _same(loop_poles.roots_w(twin, k, b), got), (loop, k, b)


def test_horner_is_numpys_polyval_bit_for_bit():
    """loop._horner (the stability sweeps' evaluations) against np.polyval on what they
    pass: Python and numpy complex scalars, 0-d and 1-d arrays, real and complex."""
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 5):
        p = rng.normal(size=n) * 10.0 ** rng.uniform(-8, 8, size=n)
        v = rng.normal(size=30) + 1j * rng.normal(size=30)
        for x in (complex(v[0]), v[1], np.asarray(v[2]), v, v.real, float(v.real[0]),
                  -2.0 + 0j):
            assert _same(lp._horner(p, x), np.polyval(p, x)), (p, x)


def test_roots_w_kept_by_the_loop_and_gains_bits():
    """roots_w keeps its answers by the loop's repr and the gains' bits: a repeated call
    is the computation's poles bit for bit, a caller writing into them changes no later
    answer, and a loop or a gain one bit apart gets its own poles."""
    import math
    rng = np.random.default_rng(11)
    for loop in _loops(rng)[:18]:
        kappa, beta = float(rng.uniform(0.01, 0.3)), float(rng.uniform(0.0, 0.3))
        first = loop_poles.roots_w(loop, kappa, beta)
        first[:] = np.nan                                  # the caller's own copy
        again = loop_poles.roots_w(loop, kappa, beta)
        assert _same(again, loop_poles._roots_w(loop, kappa, beta)), loop
        k2 = math.nextafter(kappa, 1.0)
        assert _same(loop_poles.roots_w(loop, k2, beta), loop_poles._roots_w(loop, k2, beta))
        fields = {f: getattr(loop, f) for f in loop.__dataclass_fields__}
        fields["mass"] = math.nextafter(loop.mass, 0.0)
        other = LoopModel(**fields)
        assert _same(loop_poles.roots_w(other, kappa, beta),
                     loop_poles._roots_w(other, kappa, beta))


def test_w_to_z_is_numpys_polymul_and_polyadd_bit_for_bit():
    """w_to_z convolves without np.polymul's poly1d: the same coefficients as Horner's
    scheme through np.polyadd(np.polymul(out, [1, -1]), [c]), byte for byte (signed zeros
    too), on random polynomials of 1-9 coefficients over 40 decades, with zeros."""
    rng = np.random.default_rng(5)

    def numpys(p):
        out = np.array([0.0])
        for c in p:
            out = np.polyadd(np.polymul(out, np.array([1.0, -1.0])), [c])
        return np.trim_zeros(out, "f") if np.any(out) else np.array([0.0])

    for _ in range(3000):
        n = int(rng.integers(1, 10))
        p = rng.standard_normal(n) * 10.0 ** rng.integers(-20, 20, n)
        p[rng.random(n) < 0.3] = 0.0
        p[rng.random(n) < 0.1] = -0.0
        got, want = lp.w_to_z(p), numpys(p)
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes(), p


def test_a_kept_split_hold_is_the_computation_and_each_caller_gets_its_own():
    """split_hold_body kept by its arguments' bits: a repeated call is split_hold's
    answer bit for bit, and writing into one answer changes no later one."""
    from hapsim.analysis.hand import rigid_matrices
    from hapsim.analysis.subsample import split_hold, split_hold_body
    rng = np.random.default_rng(9)
    for _ in range(40):
        args = (float(np.exp(rng.uniform(-4, 1))), float(rng.uniform(0, 3)),
                1.0 / float(rng.choice([500.0, 1000.0, 4000.0])), float(rng.uniform(0, 1)))
        first = split_hold_body(*args)
        for a in first:
            a[...] = np.nan
        want = split_hold(*rigid_matrices(args[0], args[1], 0.0), *args[2:])
        again = split_hold_body(*args)
        assert all(_same(g, w) for g, w in zip(again, want)), args
