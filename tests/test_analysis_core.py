"""THS analysis core: loop model, rendered (k, b), calibration, exact stability boundary.

Every check is against something independent: the paper's equations, published limits,
scipy's discretisation, a brute-force spectral-radius search, or the continuous oscillator.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

from hapsim.analysis import (LoopModel, Mode, calibrate, characteristic, closed_loop_poles,
                             damping_limits, grid, modes_from_poles, plant, published_limits, render,
                             rendered_pair, spectral_radius, stability_boundary,
                             stability_limit, zoh_state_space)
from hapsim.cli import main
from hapsim.errors import ConfigError
from tolerance import rel_tol

# ----------------------------------------------------------------------------- helpers


def _monic(p):
    p = np.trim_zeros(np.asarray(p, dtype=float), "f")
    return p / p[0]


def _brentq_kmax(loop, B, k_hi):
    """Independent K_max: numpy's roots of K P + B Q + R, a scan for the first unstable K,
    then brentq on max|z| - 1 (no unit-circle algebra, no polishing)."""
    from scipy.optimize import brentq
    P, Q, R = characteristic(loop)

    def rho(k):
        return float(np.max(np.abs(np.roots(np.polyadd(np.polyadd(k * P, B * Q), R)))))
    ks = np.linspace(0, k_hi, 601)[1:]
    for i, k in enumerate(ks):
        if rho(k) >= 1.0:
            lo = ks[i - 1] if i else 0.0
            return brentq(lambda k: rho(k) - 1.0, lo, k, xtol=1e-300, rtol=1e-15, maxiter=500)
    return math.inf


# ----------------------------------------------------------------------------- loop model

@pytest.mark.parametrize("kw, key", [
    (dict(mass=0.0), "mass"), (dict(mass=-1.0), "mass"), (dict(rate_hz=0.0), "rate_hz"),
    (dict(rate_hz=-5.0), "rate_hz"), (dict(friction=-0.1), "friction"),
    (dict(delay=-1), "delay"), (dict(delay=1.5, hold="ideal"), "delay"),
    (dict(delay=float("nan")), "delay"), (dict(hold="foh"), "hold"),
])
def test_loop_validation_names_the_key(kw, key):
    args = dict(mass=1.0, friction=0.0, rate_hz=1000.0, delay=1, hold="zoh")
    args.update(kw)
    with pytest.raises(ConfigError) as ei:
        LoopModel(**args)
    assert ei.value.key == key
    if key == "hold":
        assert "zoh" in str(ei.value) and "ideal" in str(ei.value)


def test_from_device_reads_the_scene_device():
    class Dev:
        mass, friction, delay, hold = 0.2, 0.3, 2, "ideal"
    loop = LoopModel.from_device(Dev(), 2000.0)
    assert (loop.mass, loop.friction, loop.delay, loop.hold, loop.period) == \
        (0.2, 0.3, 2, "ideal", 0.0005)


@pytest.mark.parametrize("m, b0, T", [(0.1, 0.0, 1e-3), (0.1, 0.5, 1e-3), (2.0, 3.0, 0.01),
                                      (0.05, 1e-7, 5e-5), (1.0, 30.0, 0.1)])
def test_zoh_state_space_matches_expm(m, b0, T):
    A = np.array([[0.0, 1.0], [0.0, -b0 / m]])
    b = np.array([0.0, 1.0 / m])
    M = np.zeros((3, 3))
    M[:2, :2] = A
    M[:2, 2] = b
    E = scipy.linalg.expm(M * T)
    Ad, Bd = zoh_state_space(m, b0, T)
    # measured 2.7e-15 abs, 5.4e-14 rel (generic 2.7e-15, 5.4e-14), margin 56
    np.testing.assert_allclose(Ad, E[:2, :2], rtol=1e-12, atol=1e-12 * max(T, 1e-300))
    # measured 9e-17 abs, 2.8e-15 rel (generic 9e-17, 2.8e-15), margin 29
    np.testing.assert_allclose(Bd, E[:2, 2], rtol=1e-12, atol=1e-14 * T * T / m)


@pytest.mark.parametrize("b0", [0.0, 0.5, 40.0])
def test_zoh_plant_matches_cont2discrete(b0):
    loop = LoopModel(mass=0.1, friction=b0, rate_hz=1000.0, delay=0, hold="zoh")
    A = np.array([[0.0, 1.0], [0.0, -b0 / 0.1]])
    Bc = np.array([[0.0], [10.0]])
    Ad, Bd, Cd, Dd, _ = scipy.signal.cont2discrete((A, Bc, [[1.0, 0.0]], [[0.0]]),
                                                    loop.period, method="zoh")
    num, den = scipy.signal.ss2tf(Ad, Bd, Cd, Dd)
    N, D = plant(loop)
    # measured 5.1e-11 relative (generic 5.1e-11), margin 19
    np.testing.assert_allclose(np.trim_zeros(num[0], "f"), N, rtol=1e-9)
    # measured 2.2e-16 abs, 1.7e-16 rel (generic 2.2e-16, 1.7e-16), margin 3000
    np.testing.assert_allclose(den, D, rtol=1e-12, atol=1e-14)


# ----------------------------------------------------------------------------- the paper

def test_paper_eq2_eq3_eq4_polynomials():
    """With m = T = 1 the ideal hold gives exactly the paper's polynomials (no factor z)."""
    z = np.array([1.0, 0.0])
    for d, R_paper in ((0, np.polymul([1, -1], [1, -1])),                     # eq. (2)
                       (1, np.polymul(z, np.polymul([1, -1], [1, -1])))):     # eq. (3)
        P, Q, R = characteristic(LoopModel(1.0, 0.0, 1.0, d, "ideal"))
        # measured 0 (generic 0): exact on both targets
        np.testing.assert_allclose(P, [1.0, 0.0], atol=1e-15)      # P = z
        # measured 0 (generic 0): exact on both targets
        np.testing.assert_allclose(Q, [1.0, -1.0], atol=1e-15)     # Q = z - 1
        # measured 0 (generic 0): exact on both targets
        np.testing.assert_allclose(R, R_paper, atol=1e-14)
    b0 = 0.5                                                       # eq. (4)
    P, Q, R = characteristic(LoopModel(1.0, b0, 1.0, 1, "ideal"))
    R4 = np.polymul(np.polymul(z, [1.0, -1.0]), [1.0, -math.exp(-b0)]) * b0 / (1 - math.exp(-b0))
    # measured 0 (generic 0): exact on both targets
    np.testing.assert_allclose(P, [1.0, 0.0], atol=1e-15)
    # measured 0 (generic 0): exact on both targets
    np.testing.assert_allclose(Q, [1.0, -1.0], atol=1e-15)
    # measured 1.1e-16 (generic 1.1e-16), margin 7e8
    np.testing.assert_allclose(R, R4, atol=1e-14)


@pytest.mark.parametrize("d", [0, 1, 2])
def test_ideal_loop_has_no_spurious_pole_at_zero(d, capsys):
    """Eq. (1) at d = 0 is a quadratic: two poles, none at z = 0, and render lists no
    parasitic mode; with delay d the order is d + 2 (ideal), d + 3 (ZOH)."""
    ideal = closed_loop_poles(LoopModel(1.0, 0.0, 1.0, d, "ideal"), 0.5, 0.1)
    zoh = closed_loop_poles(LoopModel(1.0, 0.0, 1.0, d, "zoh"), 0.05, 0.3)
    assert ideal.size == d + 2 and zoh.size == d + 3
    if d == 0:
        assert np.min(np.abs(ideal)) > 0.5
        assert main(["render", "--mass", "1", "--rate", "1", "--delay", "0", "--hold", "ideal",
                     "--K", "0.5", "--B", "0.1", "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["modes"] == []


def test_zoh_characteristic_is_z_N_and_z_pow_d_plus_1_D():
    """ZOH keeps the general form P = z N, Q = (z - 1) N / T, R = z^(d+1) D (no factor to
    remove: N(0) = T^2/m phi0 != 0), with N, D from scipy's cont2discrete."""
    for d in (0, 2):
        loop = LoopModel(mass=0.1, friction=0.5, rate_hz=1000.0, delay=d, hold="zoh")
        A = np.array([[0.0, 1.0], [0.0, -5.0]])
        Ad, Bd, Cd, Dd, _ = scipy.signal.cont2discrete(
            (A, np.array([[0.0], [10.0]]), [[1.0, 0.0]], [[0.0]]), loop.period, method="zoh")
        num, den = scipy.signal.ss2tf(Ad, Bd, Cd, Dd)
        N = np.trim_zeros(num[0], "f")
        P, Q, R = characteristic(loop)
        P_ref = np.polymul([1.0, 0.0], N)
        Q_ref = np.polymul([1.0, -1.0], N) / loop.period
        # measured 2e-16 abs, 4e-11 rel (generic 2e-16, 4e-11), margin 24
        np.testing.assert_allclose(P, P_ref, rtol=1e-9, atol=1e-14 * np.max(np.abs(P_ref)))
        # measured 3.3e-13 abs, 4e-8 rel (generic 3.3e-13, 4e-8), margin 15
        np.testing.assert_allclose(Q, Q_ref, rtol=1e-9, atol=1e-9 * np.max(np.abs(Q_ref)))
        zd1 = np.zeros(d + 2)
        zd1[0] = 1.0
        # measured 0 (generic 0): exact on both targets
        np.testing.assert_allclose(R, np.polymul(zd1, den), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("m, rate", [(1.0, 1.0), (0.1, 1000.0), (2.0, 20000.0)])
def test_paper_eq1_poles(m, rate):
    """Closed-loop poles (ideal, d = 0, B = 0) are the roots of (m/T^2)(1 - z)^2 + K z."""
    T = 1 / rate
    loop = LoopModel(m, 0.0, rate, 0, "ideal")
    for frac in (0.01, 0.3, 0.9):
        K = frac * 4 * m / T**2
        ref = np.sort_complex(np.roots([m / T**2, K - 2 * m / T**2, m / T**2]))
        got = closed_loop_poles(loop, K, 0.0)
        got = np.sort_complex(got[np.abs(got) > 1e-6])
        # measured 6.5e-16 abs, 6.5e-16 rel (generic 6.5e-16, 6.5e-16), margin 2e5
        np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("m, rate", [(1.0, 1.0), (0.1, 1000.0), (3.0, 20000.0)])
def test_paper_eq2_tuning_relation(m, rate):
    """K = (m/T^2)(2 - 2 cos(T sqrt(k/m))) for ideal, d = 0, b = 0 (Florens et al. eq. 2)."""
    T = 1 / rate
    loop = LoopModel(m, 0.0, rate, 0, "ideal")
    for wT in (0.01, 0.3, 1.0, 2.5):
        k = m * (wT / T) ** 2
        c = calibrate(loop, k, 0.0)
        K_ref = m / T**2 * (2 - 2 * math.cos(T * math.sqrt(k / m)))
        # K_ref's 2 - 2 cos(wT) cancels: condition number (2 + 2|cos|) / |2 - 2 cos| (2e4
        # at wT = 0.01), six roundings (sqrt, /, *, cos, -, *) (derived; measured worst
        # 2.9e-13 relative, generic the same, 1/100 of this bound)
        cs = math.cos(T * math.sqrt(k / m))
        assert c.K == pytest.approx(K_ref, rel=rel_tol(6, (2 + 2 * abs(cs)) / abs(2 - 2 * cs)))
        # B = 0 exactly in exact arithmetic: measured 1.4e-17 m/T (generic the same),
        # margin 7e4
        assert abs(c.B) <= 1e-12 * m / T
        assert not c.renderable and "not positive" in c.reason  # undamped: marginal


# ----------------------------------------------------------------------------- modes

def test_modes_from_continuous_oscillator():
    m, T = 0.2, 1e-3
    k, b = 900.0, 1.5
    s = complex(-b / (2 * m), math.sqrt(k / m - (b / (2 * m)) ** 2))
    z = np.exp(np.array([s, s.conjugate()]) * T)
    poles = np.concatenate([z, [0.3, -0.2, 0.0]])
    modes = modes_from_poles(poles, m, T)
    assert [md.kind for md in modes] == ["pair", "real", "real", "real"]
    pair = rendered_pair(modes)
    assert pair is modes[0] and pair.z.imag > 0
    # measured 1.3e-14 relative (generic 1.3e-14), margin 75000
    assert pair.k == pytest.approx(k, rel=1e-9) and pair.b == pytest.approx(b, rel=1e-9)
    # measured 0 (generic 0): exact on both targets
    assert pair.f0_hz == pytest.approx(math.sqrt(k / m) / (2 * math.pi), rel=1e-12)
    # measured 1.3e-14 relative (generic 1.3e-14), margin 74000
    assert pair.damping_ratio == pytest.approx(b / (2 * math.sqrt(k * m)), rel=1e-9)
    assert modes[1].s.imag == 0 and modes[1].damping_ratio == 1.0
    # measured 0 (generic 0): exact on both targets
    assert modes[2].s.imag == pytest.approx(math.pi / T)  # negative real: Nyquist
    assert modes[3].k == math.inf and modes[3].to_dict()["k"] is None
    assert rendered_pair(modes[1:]) is None
    with pytest.raises(ValueError):
        modes_from_poles([1 + 1j], m, T)
    assert isinstance(pair, Mode)


# ----------------------------------------------------------------------------- round trip

CONFIGS = [LoopModel(m, b0, rate, d, hold)
           for hold in ("zoh", "ideal") for d in (0, 1, 2, 3)
           for (m, b0, rate) in ((1.0, 0.0, 1.0), (1.0, 0.5, 1.0), (0.1, 0.5, 1000.0),
                                 (0.05, 0.0, 1000.0), (0.5, 2.0, 20000.0))]


@pytest.mark.parametrize("loop", CONFIGS, ids=lambda L: f"{L.hold}-d{L.delay}-m{L.mass}-"
                         f"b{L.friction}-{L.rate_hz:g}Hz")
def test_calibrate_render_round_trip(loop):
    m, T = loop.mass, loop.period
    n_ok = 0
    for fT in (0.002, 0.01, 0.03, 0.08):
        w = 2 * math.pi * fT / T
        k = m * w * w
        for zeta in (0.02, 0.2, 0.5, 0.9):
            b = 2 * zeta * math.sqrt(k * m)
            c = calibrate(loop, k, b)
            if not c.renderable:
                assert c.reason and "renderable:" not in c.reason
                continue
            n_ok += 1
            r = render(loop, c.K, c.B)
            assert r.stable and r.spectral_radius < 1
            # measured 2.3e-13 relative (generic 2.3e-13), margin 27000
            assert r.k == pytest.approx(k, rel=1e-9)
            # measured 1.4e-13 relative (generic 1.4e-13), margin 13000
            assert r.b == pytest.approx(b, rel=1e-9)
            # measured 3e-15 relative (generic 3e-15), margin 3e5
            assert r.spectral_radius == pytest.approx(c.spectral_radius, rel=1e-9)
            # every parasitic mode decays faster than the rendered pair
            assert all(abs(md.z) < abs(r.rendered.z) for md in r.modes)
    assert n_ok >= 3, "the round trip must not pass vacuously"


def test_calibrate_over_and_critically_damped_place_real_poles():
    loop = LoopModel(0.1, 0.5, 1000.0, 1, "zoh")
    m, T = loop.mass, loop.period
    for k, b in ((400.0, 20.0), (400.0, 2 * math.sqrt(400.0 * 0.1))):  # over, critical
        c = calibrate(loop, k, b)
        assert c.renderable, c.reason
        disc = max(b * b - 4 * m * k, 0.0)
        for s in ((-b + math.sqrt(disc)) / (2 * m), (-b - math.sqrt(disc)) / (2 * m)):
            poles = closed_loop_poles(loop, c.K, c.B)
            assert np.min(np.abs(poles - math.exp(s * T))) < 1e-6  # double root: ~sqrt(eps)
        r = render(loop, c.K, c.B)
        assert r.stable and math.isnan(r.k) and r.note  # nothing oscillates: said


def test_unrenderable_targets_say_why():
    loop = LoopModel(0.1, 0.0, 1000.0, 2, "zoh")
    c = calibrate(loop, 1e5, 0.5)  # stiff and lightly damped with 2 samples of delay
    assert not c.renderable
    assert ("unstable" in c.reason or "less damped" in c.reason) and "spectral radius" in c.reason
    c = calibrate(LoopModel(1, 0, 1, 0, "ideal"), 1000.0, 1.0)  # above Nyquist
    assert not c.renderable and "Nyquist" in c.reason
    with pytest.raises(ConfigError):
        calibrate(loop, -1.0, 1.0)


def test_a_refused_calibration_is_truly_not_renderable():
    """Each refusal naming a parasitic pole is checked on numpy's roots of K P + B Q + R
    for the refused (K, B): the named pole is a root, the target's poles exp(s T) (from the
    continuous target, closed form) are roots, and the named pole is on/outside the unit
    circle ("unstable") or decays no faster than the target ("less damped")."""
    import re
    kinds = {"unstable": 0, "less damped": 0}
    for loop in (LoopModel(0.1, 0.5, 1000.0, 1, "zoh"), LoopModel(0.1, 0.5, 1000.0, 2, "ideal"),
                 LoopModel(0.1, 0.5, 250.0, 1, "zoh"), LoopModel(1.0, 0.0, 1.0, 1, "ideal")):
        m, T = loop.mass, loop.period
        for k in np.geomspace(1e-3, 2.0, 12) * m / T ** 2:
            for b in np.array([0.005, 0.03, 0.1, 0.3, 1.0]) * m / T:
                c = calibrate(loop, k, b)
                if c.renderable or "parasitic pole" not in c.reason:
                    continue
                kind = "unstable" if c.reason.startswith("unstable") else "less damped"
                kinds[kind] += 1
                re_, im_ = map(float, re.search(r"z = ([-+0-9.e]+)([-+][0-9.e]+)j",
                                                c.reason).groups())
                z_named = complex(re_, im_)
                P, Q, R = characteristic(loop)
                roots = np.roots(np.polyadd(np.polyadd(c.K * P, c.B * Q), R))
                scale = max(1.0, np.max(np.abs(roots)))
                # the reason prints z to 6 significant digits: measured 4.3e-9 * scale
                # (generic the same), margin 230
                assert np.min(np.abs(roots - z_named)) < 1e-6 * scale
                s_t = np.roots([m, b, k])                          # continuous target
                z_t = np.exp(s_t * T)
                for zt in z_t:
                    # measured 1.7e-14 (generic the same), margin 6e7: a wrong calibration
                    # moves a target pole by far more than 1e-6
                    assert np.min(np.abs(roots - zt)) < 1e-6
                if kind == "unstable":
                    assert abs(z_named) >= 1.0 - 1e-9
                else:
                    assert abs(z_named) >= np.min(np.abs(z_t)) * (1 - 1e-9)
                    assert abs(z_named) < 1.0
    assert kinds["unstable"] >= 3 and kinds["less damped"] >= 3, kinds


# ----------------------------------------------------------------------------- stability

def test_centred_difference_limit():
    for m, rate in ((1.0, 1.0), (0.1, 1000.0), (0.3, 20000.0)):
        loop = LoopModel(m, 0.0, rate, 0, "ideal")
        kmax = stability_limit(loop, 0.0)
        # measured 1.5e-16 relative (generic 1.5e-16), margin 6800
        assert kmax == pytest.approx(4 * m * rate**2, rel=1e-12)
        assert spectral_radius(loop, 0.999 * kmax) <= 1 + 1e-9
        assert spectral_radius(loop, 1.001 * kmax) > 1 + 1e-6
        # measured 1.5e-16 relative (generic 1.5e-16), margin 7e9
        assert published_limits(loop)["centred_difference_K"] == pytest.approx(4 * m * rate**2)
    # lossless again with friction cancelled by B = -b0 (eq. 4): the poles leave the circle
    # at z = -1, where K = (m/T^2)(2x + 2(1 + e^-x) x/(1 - e^-x)), x = b0 T/m
    m, b0, rate = 0.2, 0.5, 1000.0
    x = b0 / (m * rate)
    loop = LoopModel(m, b0, rate, 0, "ideal")
    kmax = stability_limit(loop, -b0)
    ref = m * rate**2 * (2 * x + 2 * (1 + math.exp(-x)) * x / -math.expm1(-x))
    # measured 1.5e-16 relative (generic 1.5e-16), margin 7e6
    assert kmax == pytest.approx(ref, rel=1e-9)
    assert spectral_radius(loop, 0.999 * kmax, -b0) <= 1 + 1e-9
    assert spectral_radius(loop, 1.001 * kmax, -b0) > 1 + 1e-6


BOUNDARY_CASES = [(LoopModel(0.1, 0.5, 1000.0, d, h), B) for h in ("zoh", "ideal")
                  for d in (0, 1, 3) for B in (0.0, 1.0, -0.2)] + \
                 [(LoopModel(1.0, 0.0, 1.0, 1, "ideal"), B) for B in (0.1, 0.5, 0.9)] + \
                 [(LoopModel(0.5, 2.0, 20000.0, 1, "zoh"), 3.0)]


@pytest.mark.parametrize("loop, B", BOUNDARY_CASES)
def test_exact_boundary_is_where_spectral_radius_reaches_one(loop, B):
    kmax = stability_limit(loop, B)
    assert 0 < kmax < math.inf
    assert spectral_radius(loop, 0.999 * kmax, B) < 1.0
    assert spectral_radius(loop, 1.001 * kmax, B) > 1.0
    # stable all the way from 0 (sampled), and the same as an independent brute-force search
    for f in (0.01, 0.3, 0.7, 0.99):
        assert spectral_radius(loop, f * kmax, B) < 1.0
    # 1e-9 relative precision: the radius is 1 to first order at K_max
    rho_lo = spectral_radius(loop, kmax * (1 - 1e-8), B)
    rho_hi = spectral_radius(loop, kmax * (1 + 1e-8), B)
    assert rho_lo < 1.0 < rho_hi


@pytest.mark.parametrize("loop, B", BOUNDARY_CASES + [
    (LoopModel(1.0, 0.5, 1.0, 2, "ideal"), 0.2), (LoopModel(1.0, 0.0, 1.0, 1, "ideal"), 0.3)])
def test_exact_boundary_against_brentq(loop, B):
    """K_max to relative 1e-9 (issue 3) against an independent brentq solve of spectral
    radius 1 on numpy's roots (they agree to ~1e-12 here; the reference's own round-off)."""
    kmax = stability_limit(loop, B)
    ref = _brentq_kmax(loop, B, 3 * kmax)
    # measured 1.8e-12 relative (generic 1.8e-12), margin 560
    assert kmax == pytest.approx(ref, rel=1e-9)


def _rho_numpy(loop, K, B):
    """Spectral radius from numpy's roots of K P + B Q + R alone (independent path)."""
    P, Q, R = characteristic(loop)
    return float(np.max(np.abs(np.roots(np.polyadd(np.polyadd(K * P, B * Q), R)))))


def test_damping_limits_closed_form_centred_difference():
    """Ideal hold, d = 0, b0 = 0 (m = T = 1): z^2 + (K + B - 2) z + 1 - B = 0; Jury:
    stable iff 0 < B and K + 2 B < 4, i.e. B in (0, 2 - K/2)."""
    loop = LoopModel(1.0, 0.0, 1.0, 0, "ideal")
    for K in (0.1, 1.0, 3.0, 3.9):
        ((lo, hi),) = damping_limits(loop, K)
        # lo: measured 4.5e-16 (generic the same), margin 2200; hi: measured 0 (generic 0)
        assert abs(lo) < 1e-12 and hi == pytest.approx(2.0 - K / 2.0, rel=1e-12)
    assert damping_limits(loop, 4.5) == []          # beyond 4 m/T^2 no damping helps
    with pytest.raises(ConfigError):
        damping_limits(loop, math.inf)


@pytest.mark.parametrize("loop", [LoopModel(0.1, 0.5, 1000.0, 1, "zoh"),
                                  LoopModel(0.1, 0.5, 1000.0, 2, "ideal"),
                                  LoopModel(0.5, 2.0, 20000.0, 1, "zoh"),
                                  LoopModel(1.0, 0.0, 1.0, 1, "ideal")])
def test_damping_limits_against_brentq_on_numpy_roots(loop):
    """Both ends of the stable B interval at fixed K equal an independent brentq solve of
    max|roots| = 1 (numpy roots of K P + B Q + R) to 1e-9; the lens of Fig. 8 is closed on
    both sides."""
    from scipy.optimize import brentq
    K = 0.5 * stability_limit(loop, 0.5 * loop.mass / loop.period * 0.5)
    ((lo, hi),) = damping_limits(loop, K)
    assert -math.inf < lo < hi < math.inf
    mid = 0.5 * (lo + hi)
    assert _rho_numpy(loop, K, mid) < 1.0
    for edge, out in ((lo, lo - 0.5 * (hi - lo)), (hi, hi + 0.5 * (hi - lo))):
        assert _rho_numpy(loop, K, out) > 1.0
        ref = brentq(lambda B: _rho_numpy(loop, K, B) - 1.0, mid, out, xtol=1e-15,
                     rtol=1e-14, maxiter=300)
        # measured 1.5e-11 abs, 1.5e-14 rel (generic 1.5e-11, 1.5e-14), margin 68000
        assert edge == pytest.approx(ref, rel=1e-9, abs=1e-12 * loop.mass / loop.period)


def test_passivity_is_sufficient():
    """Colgate & Schenkel 1997: b0 > K T/2 + |B| => stable (ZOH, no delay)."""
    rng = np.random.default_rng(1)
    n = 0
    for m, b0, rate in ((0.1, 0.5, 1000.0), (1.0, 2.0, 100.0), (0.02, 0.1, 20000.0),
                        (1.0, 0.5, 1.0)):
        loop = LoopModel(m, b0, rate, 0, "zoh")
        T = loop.period
        for _ in range(40):
            B = rng.uniform(-b0, b0) * 0.999
            K = rng.uniform(0, 1) * 2 * (b0 - abs(B)) / T
            assert b0 > K * T / 2 + abs(B)
            assert spectral_radius(loop, K, B) < 1.0
            n += 1
        # the condition is sufficient only: the exact limit is larger (or equal)
        assert stability_limit(loop, 0.0) >= published_limits(loop)["passivity_K"] * (1 - 1e-12)
    assert n == 160


@pytest.mark.parametrize("d", [0, 1, 2])
@pytest.mark.parametrize("B_over_b0", [0.0, 1.0])
def test_diolaiti_limit_is_first_order_in_b0T_over_m(d, B_over_b0):
    """Diolaiti et al. 2006: K < (b0 + B)/(T/2 + dT), exact to O(b0 T/m)."""
    m, rate = 1.0, 1000.0
    T = 1 / rate
    errs = []
    xs = (1e-2, 1e-3, 1e-4)
    for x in xs:
        b0 = x * m / T
        loop = LoopModel(m, b0, rate, d, "zoh")
        B = B_over_b0 * b0
        exact = stability_limit(loop, B)
        dio = published_limits(loop, B)["diolaiti_K"]
        errs.append(abs(exact / dio - 1))
    assert errs[0] < 0.1
    for e, x in zip(errs, xs):
        assert e < 5 * (1 + B_over_b0) * (1 + d) * x  # O(b0 T / m)
    # and shrinks proportionally: each decade of b0 T/m is ~ a decade of error
    for a, b in zip(errs, errs[1:]):
        assert 0.05 < b / a < 0.2


def test_stability_boundary_vector_and_extremes():
    loop = LoopModel(1.0, 0.0, 1.0, 1, "ideal")
    Bs = np.array([0.0, 0.5, 1.5])
    K = stability_boundary(loop, Bs)
    assert K.shape == (3,)
    assert K[0] == 0.0 and K[2] == 0.0  # no stable K without damping / with too much
    # measured 3.3e-16 relative (generic 3.3e-16), margin 3e6
    assert K[1] == pytest.approx(0.25, rel=1e-9)  # Jury: peak of the Fig. 8 boundary
    assert stability_limit(LoopModel(1.0, 0.0, 1.0, 0, "zoh")) == 0.0  # ZOH, no loss


# ----------------------------------------------------------------------------- grid

def test_grid_fig7_shapes_identity_and_b_scale():
    loop = LoopModel(1.0, 0.0, 1.0, 0, "ideal")
    kv, bv = np.array([1.0, 2.0, 4.0]), np.array([0.0, 0.2, 0.6])
    g = grid(loop, kv, bv, samples=5)
    assert g.K.shape == (3, 3) and g.iso_k_K.shape == (3, 5) and g.iso_b_K.shape == (3, 5)
    # Fig. 7: the B scale is not influenced by K: B = (m/T)(1 - e^(-bT/m)) for every k
    # measured 2.2e-16 (generic 2.2e-16), margin 4500
    np.testing.assert_allclose(g.B, np.tile(1 - np.exp(-bv), (3, 1)), atol=1e-12)
    # measured 0 (generic 0): exact on both targets
    np.testing.assert_allclose(g.identity_K[:, 0], kv)
    assert g.rendered[:, 0].all()  # b = 0: the marginal boundary, still drawn
    # measured 1.3e-16 relative (generic 1.3e-16), margin 7600
    np.testing.assert_allclose(g.K[:, 0], 2 - 2 * np.cos(np.sqrt(kv)), rtol=1e-12)
    json.dumps(g.to_dict())


def test_grid_fig9_b0_bias_convention():
    loop = LoopModel(1.0, 0.5, 1.0, 1, "ideal")
    g = grid(loop, [0.3], [0.4, 0.8])
    # measured 2.8e-16 relative (generic 2.8e-16), margin 2e8
    np.testing.assert_allclose(g.identity_B, [[-0.1, 0.3]])
    # measured 0 (generic 0): exact on both targets
    np.testing.assert_allclose(g.B_axis, g.B + 0.5)
    assert "b0" in g.convention
    for j, b in enumerate((0.4, 0.8)):
        r = render(loop, g.K[0, j], g.B[0, j])
        # measured 5.6e-16 relative (generic 5.6e-16), margin 2e6
        assert r.b == pytest.approx(b, rel=1e-9) and r.k == pytest.approx(0.3, rel=1e-9)


# ----------------------------------------------------------------------------- CLI

LOOP = ["--mass", "0.1", "--friction", "0.5", "--rate", "1000", "--delay", "1", "--hold", "zoh"]


def test_cli_render_calibrate_round_trip(capsys):
    assert main(["calibrate", *LOOP, "--k", "2000", "--b", "3", "--json"]) == 0
    c = json.loads(capsys.readouterr().out)
    assert c["renderable"] is True and set(c) >= {"K", "B", "reason", "spectral_radius", "modes"}
    assert main(["render", *LOOP, "--K", repr(c["K"]), "--B", repr(c["B"]), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    # measured 7.4e-16 relative (generic 7.4e-16), margin 1e6
    assert r["k"] == pytest.approx(2000, rel=1e-9) and r["b"] == pytest.approx(3, rel=1e-9)
    assert r["stable"] is True and isinstance(r["modes"], list)
    assert main(["render", *LOOP, "--K", "3000"]) == 1  # unstable: negative verdict
    assert "UNSTABLE" in capsys.readouterr().out
    assert main(["calibrate", *LOOP, "--k", "1e6", "--b", "0.1", "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["renderable"] is False


def test_cli_stability_json(capsys):
    assert main(["stability", *LOOP, "--B", "0", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    loop = LoopModel(0.1, 0.5, 1000.0, 1, "zoh")
    # measured 0 (generic 0): exact on both targets
    assert d["K_max"] == pytest.approx(stability_limit(loop), rel=1e-12)
    # measured 0 (generic 0): exact on both targets
    assert d["spectral_radius_at_K_max"] == pytest.approx(1.0, abs=1e-9)
    # measured 0 (generic 0): exact on both targets
    assert d["diolaiti_K"] == pytest.approx(0.5 / 0.0015)
    # measured 0 (generic 0): exact on both targets
    assert d["passivity_K"] == pytest.approx(1000.0)
    # measured 1.5e-16 relative (generic 1.5e-16), margin 7e9
    assert d["centred_difference_K"] == pytest.approx(4e5)


def test_cli_map_paper_preset(tmp_path, capsys):
    out, data = tmp_path / "f8.png", tmp_path / "f8.json"
    assert main(["map", "--paper", "8", "--n", "4", "--samples", "10", "--out", str(out),
                 "--data", str(data)]) == 0
    assert out.stat().st_size > 10_000 and out.read_bytes()[:4] == b"\x89PNG"
    d = json.loads(data.read_text())
    assert d["loop"]["delay"] == 1 and d["loop"]["hold"] == "ideal"
    # measured 1.6e-5 relative (generic 1.6e-5), margin 62
    assert max(v for v in d["boundary_K"] if v is not None) == pytest.approx(0.25, rel=1e-3)


@pytest.mark.parametrize("opt, name, expect", [
    ("--out", "fig.foo", "unsupported figure format '.foo'"),
    ("--out", "fig", "no file extension"),
    ("--out", "missing/fig.png", "does not exist"),
    ("--out", "adir.png", "is a directory"),
    ("--data", "missing/grid.json", "does not exist"),
    ("--data", ".", "is a directory"),
    ("--data", "grid.txt", "give a file ending in .json"),
])
def test_cli_map_bad_output_paths_exit_2_naming_the_option(opt, name, expect, tmp_path,
                                                           monkeypatch, capsys):
    """A bad --out / --data is a one-line error naming the option (exit 2), found before
    the grid is computed, and nothing is written."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "adir.png").mkdir()
    import sys
    grid_mod = sys.modules["hapsim.analysis.grid"]   # (the package re-exports grid())

    def no_grid(*a, **k):
        raise AssertionError("the grid was computed before the paths were checked")
    monkeypatch.setattr(grid_mod, "grid", no_grid)
    assert main(["map", "--paper", "8", "--n", "3", "--samples", "4", opt, name]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"error: {opt}: " in err and expect in err
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir.png"]
    if expect.startswith(("unsupported", "no file")):
        assert ".png" in err and ".svg" in err      # the valid choices are listed


@pytest.mark.parametrize("argv, option", [
    (["render", "--mass", "0", "--rate", "1000", "--K", "1"], "--mass"),
    (["render", "--mass", "1", "--rate", "-1", "--K", "1"], "--rate"),
    (["calibrate", "--mass", "1", "--rate", "1000", "--delay", "-1", "--k", "1", "--b", "1"],
     "--delay"),
    (["stability", "--mass", "1", "--rate", "1000", "--hold", "foh"], "--hold"),
    (["stability", "--mass", "1", "--rate", "1000", "--friction", "-2"], "--friction"),
    (["map", "--mass", "1", "--rate", "1000"], "--k-range"),
])
def test_cli_bad_arguments_exit_2(argv, option, capsys):
    assert main(argv) == 2
    assert option in capsys.readouterr().err


def test_paper_preset_unknown_figure_is_a_config_error_listing_the_choices():
    from hapsim.analysis import paper_preset
    loop, k_range, b_range, title = paper_preset(9)
    assert (loop.friction, loop.delay, loop.hold) == (0.5, 1, "ideal") and "Fig. 9" in title
    for bad in (6, 10, "8", 8.5, None):
        with pytest.raises(ConfigError) as ei:
            paper_preset(bad)
        assert ei.value.key == "number" and "7, 8, 9" in str(ei.value)
        assert not isinstance(ei.value, KeyError)
    with pytest.raises(ConfigError) as ei:
        paper_preset(8, hold="foh")
    assert ei.value.key == "hold"


def test_grid_and_stability_limit_raise_config_error():
    loop = LoopModel(1.0, 0.0, 1.0, 1, "ideal")
    for kv, bv in (([0.0, 0.5], [0.1]), ([0.5], [math.nan]), ([math.inf], [0.1])):
        with pytest.raises(ConfigError):
            grid(loop, kv, bv)
    with pytest.raises(ConfigError):
        stability_limit(loop, math.nan)
