"""Sub-sample delay (issue 29 item 3): the split hold against independent models.

Independent references written here, never hapsim's code:
- the hold integrated on a fine sub-grid of the period with ``scipy.linalg.expm`` of the
  augmented continuous system (Van Loan's block form), the force switching on a grid point;
- the closed loop's one-period state matrix built from the two sub-interval exponentials
  (actuator side: the force switches ``f T`` into the sample period);
- the FireFader's own timing (sensor side: the force switches at the period's start, the
  position is read ``alpha T`` later, the next packet applies the force computed from it),
  whose poles must equal the actuator-side model's with ``d = packets - alpha`` (the
  one-period maps from two phases of the period are similar matrices).

Tolerances: an eigenvalue ``z`` of a matrix ``M`` computed in double precision moves by at
most ``kappa(z) ||dM||`` with ``kappa`` its condition number (``||x|| ||y|| / |y^H x|``,
right and left eigenvectors: Wilkinson, *The Algebraic Eigenvalue Problem*, 1965, ch. 2)
and ``||dM|| <= c p eps ||M||`` for the ``p``-square matrices built from a few
exponentials and products (each an ``O(p eps)`` backward-stable step). ``c = 64`` covers
the exponentials, the products and hapsim's own root finder (whose Newton polish only
lowers its error); both sides are within that bound of the exact pole, hence the factor 2.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tolerance import measured
import scipy.linalg as sl

from hapsim.analysis import LoopModel, calibrate, render, stability_limit
from hapsim.analysis.loop_poles import closed_loop_poles
from hapsim.analysis.subsample import (held_plant, split_delay, split_hold, split_hold_body,
                                       split_numerator_w)
from hapsim.errors import ConfigError

pytestmark = pytest.mark.numerical

EPS = np.finfo(float).eps
C_BACKWARD = 64.0


def _body(m, b0):
    return np.array([[0.0, 1.0], [0.0, -b0 / m]]), np.array([0.0, 1.0 / m])


def _van_loan(A, b, tau):
    """``(e^(A tau), int_0^tau e^(As) ds b)`` from one block exponential."""
    p = A.shape[0]
    M = np.zeros((p + 1, p + 1))
    M[:p, :p], M[:p, p] = A, b
    E = sl.expm(M * tau)
    return E[:p, :p], E[:p, p]


def _random_loop(rng, whole_max=5):
    m = float(10 ** rng.uniform(math.log10(0.02), math.log10(2.0)))
    b0 = float(rng.uniform(0.0, 5.0)) * (rng.random() < 0.8)
    rate = float(10 ** rng.uniform(math.log10(250.0), math.log10(10000.0)))
    d = float(rng.integers(0, whole_max + 1) + rng.uniform(0.0, 1.0))
    return m, b0, rate, d


def _actuator_matrix(m, b0, T, d, K, B):
    """Closed-loop one-period matrix, written here: state ``[x, v, x_s[n-1], F[n-1],
    ..., F[n-M-1]]`` with ``F[n] = -K x[n] - B (x[n] - x[n-1]) / T`` held from
    ``(n + d) T``: over ``[nT, (n+1)T)`` the plant holds ``F[n-M-1]`` for ``f T`` then
    ``F[n-M]``."""
    M = int(math.floor(d))
    f = d - M
    A, b = _body(m, b0)
    Phi, _ = _van_loan(A, b, T)
    Ea, g_late = _van_loan(A, b, (1.0 - f) * T)
    _, g_early = _van_loan(A, b, f * T)
    g_early = Ea @ g_early
    L = M + 1                                  # F[n-1] .. F[n-M-1]
    n = 3 + L
    F = np.zeros(n)
    F[0], F[2] = -K - B / T, B / T

    def force(k):                              # row giving F[n-k]
        return F if k == 0 else np.eye(n)[3 + k - 1]
    Acl = np.zeros((n, n))
    Acl[:2, :2] = Phi
    Acl[:2] += np.outer(g_late, force(M)) + np.outer(g_early, force(M + 1))
    Acl[2, 0] = 1.0
    Acl[3] = F
    for j in range(1, L):
        Acl[3 + j, 3 + j - 1] = 1.0
    return Acl


def _sensor_matrix(m, b0, T, packets, alpha, K, B):
    """The FireFader's timing, written here: the force of packet ``n`` acts from the
    period's start ``t_n``; the position is read at ``t_n + alpha T``; the force computed
    from it goes out in packet ``n + packets``. State at ``t_n``: ``[x, v, y[n-1],
    F[n-1], ..., F[n-packets]]`` (``F[j]`` computed from the reading ``y[j]``)."""
    A, b = _body(m, b0)
    Phi, G = _van_loan(A, b, T)
    Ea, Ga = _van_loan(A, b, alpha * T)
    P = int(packets)
    n = 3 + P
    # u[n] = F[n-P] = state row 3 + P - 1; y[n] = Ea[0] s + Ga[0] u[n]
    y = np.zeros(n)
    y[:2] = Ea[0]
    y[3 + P - 1] += Ga[0]
    F = (-K - B / T) * y
    F[2] += B / T
    Acl = np.zeros((n, n))
    Acl[:2, :2] = Phi
    Acl[:2, 3 + P - 1] += G
    Acl[2] = y
    Acl[3] = F
    for j in range(1, P):
        Acl[3 + j, 3 + j - 1] = 1.0
    return Acl


def _eig_tol(Acl):
    """Per-eigenvalue bound ``2 c p eps ||M|| kappa(z)`` (module notes)."""
    w, vl, vr = sl.eig(Acl, left=True, right=True)
    kappa = (np.linalg.norm(vl, axis=0) * np.linalg.norm(vr, axis=0)
             / np.abs(np.sum(vl.conj() * vr, axis=0)))
    return w, 2.0 * C_BACKWARD * Acl.shape[0] * EPS * np.linalg.norm(Acl) * kappa


def _felt(z, m, T):
    s = np.log(z) / T
    return m * abs(s) ** 2, -2.0 * m * s.real


def _match(z_ref, tol, z_got):
    """Each reference eigenvalue (not a dead-beat zero) has a computed pole within its
    bound."""
    for zr, t in zip(z_ref, tol):
        if abs(zr) <= t:
            continue                            # a pole at 0 (dead-beat delay state)
        assert np.min(np.abs(z_got - zr)) <= t, (zr, t, z_got)


# --------------------------------------------------------------------------- the hold


@pytest.mark.parametrize("seed", range(6))
def test_split_hold_equals_the_subgrid_integration(seed):
    """Gamma0, Gamma1 = the response of [x, v] to the new and the old force, integrated
    over a sub-grid of N steps with the force switching at grid point j = f N."""
    rng = np.random.default_rng(seed)
    m, b0, rate, _ = _random_loop(rng)
    T, N = 1.0 / rate, 40
    j = int(rng.integers(1, N))
    f = j / N
    A, b = _body(m, b0)
    E, g = _van_loan(A, b, T / N)
    old, new = np.zeros(2), np.zeros(2)
    for k in range(N):                          # unit old force for j steps, then new
        old = E @ old + (g if k < j else 0.0)
        new = E @ new + (g if k >= j else 0.0)
    Phi, G0, G1 = split_hold(A, b, T, f)
    Pb, G0b, G1b = split_hold_body(m, b0, T, f)
    # N products of O(eps) steps: error <= c N eps times the vector's size
    for ref, got in ((new, G0), (old, G1), (new, G0b), (old, G1b)):
        scale = np.abs(ref) + np.abs(got)
        # derived: N products, each C_BACKWARD eps (a zero scale: both exact, 0 <= 0)
        assert np.all(np.abs(ref - got) <= C_BACKWARD * N * EPS * scale)
    assert np.allclose(Phi, Pb, rtol=C_BACKWARD * EPS, atol=0.0)


def test_split_hold_limits_are_the_plain_hold():
    """f = 0: Gamma1 = 0 and Gamma0 = Gamma; f -> 1: Gamma0 -> 0, Gamma1 -> Gamma."""
    from hapsim.analysis.loop import zoh_state_space
    Ad, G = zoh_state_space(0.1, 0.5, 1e-3)
    P, G0, G1 = split_hold_body(0.1, 0.5, 1e-3, 0.0)
    assert not np.any(G1)       # two exact forms of the same hold: a few eps apart
    assert np.allclose(P, Ad, rtol=C_BACKWARD * EPS, atol=0.0)
    assert np.allclose(G0, G, rtol=C_BACKWARD * EPS, atol=0.0)
    _, G0, G1 = split_hold_body(0.1, 0.5, 1e-3, 1.0 - 2 ** -40)
    # measured 9.1e-13 relative (generic 9.1e-13), margin 1e6
    # (the hold's split at 1 - 2^-40 moves G by 2^-40 ~ 9.1e-13 relative: margin 10)
    assert np.allclose(G1, G, rtol=measured(9.1e-13, 10)) and \
        np.all(np.abs(G0) <= measured(9.1e-13, 10) * np.abs(G))


def test_held_plant_and_numerator_are_the_same_transfer():
    """The augmented state space and the numerator give one pulse transfer: at random
    points z, c (zI - Ad)^-1 Bd = Nf(w) / (z D(w))."""
    rng = np.random.default_rng(3)
    A, b = _body(0.3, 1.2)
    T, f = 2e-3, 0.37
    Phi, G0, G1 = split_hold(A, b, T, f)
    Ad, Bd = held_plant(Phi, G0, G1)
    Nf = split_numerator_w(Phi - np.eye(2), G0, G1, [1.0, 0.0])
    D = np.poly(Phi - np.eye(2))
    for z in np.exp(1j * rng.uniform(0, math.pi, 5)) * rng.uniform(0.5, 1.5, 5):
        lhs = (np.linalg.solve(z * np.eye(3) - Ad, Bd))[0]
        rhs = np.polyval(Nf, z - 1) / (z * np.polyval(D, z - 1))
        # Nf comes from det(M + g c) - det(M): O(1) coefficients minus O(1) ones leave
        # O(|g|) ones, so its relative error is eps sum|D| / max|Nf| per operation
        loss = np.sum(np.abs(D)) / np.max(np.abs(Nf))
        assert abs(lhs - rhs) <= C_BACKWARD * 3 * EPS * loss * abs(lhs)


@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf, "x", True, None])
def test_split_delay_refuses(bad):
    with pytest.raises(ConfigError, match=r"real number >= 0"):
        split_delay(bad)


# --------------------------------------------------------------------------- the loop


def _gains(rng, loop):
    """A stable (K, B) well inside this loop's region (a fraction of K_max at B)."""
    T, m = loop.period, loop.mass
    B = float(rng.uniform(0.0, 0.3)) * m / T / (1.0 + loop.delay)
    kmax = stability_limit(loop, B)
    kmax = min(kmax, 4.0 * m / (T * T)) if math.isfinite(kmax) else 4.0 * m / (T * T)
    return float(rng.uniform(0.05, 0.9)) * kmax, B


@pytest.mark.parametrize("seed", range(40))
def test_poles_and_felt_pair_equal_the_independent_loop(seed):
    """Random loops, random real delays: every closed-loop pole, hence the felt (k, b),
    equals the eigenvalues of the one-period matrix built here, within the eigenvalue's
    own bound."""
    rng = np.random.default_rng(1000 + seed)
    m, b0, rate, d = _random_loop(rng)
    loop = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d)
    K, B = _gains(rng, loop)
    T = loop.period
    z_ref, tol = _eig_tol(_actuator_matrix(m, b0, T, d, K, B))
    z = closed_loop_poles(loop, K, B)
    assert z.size == int(math.floor(d)) + 4
    _match(z_ref, tol, z)
    r = render(loop, K, B)
    if r.rendered is not None:
        i = int(np.argmin(np.abs(z_ref - complex(r.rendered.z))))
        zr, t = z_ref[i], tol[i]
        k_ref, b_ref = _felt(zr if zr.imag > 0 else zr.conjugate(), m, T)
        # k = m |s|^2, b = -2 m Re s, s = ln z / T: |ds| <= |dz| / (|z| T)
        ds = t / (abs(zr) * T)
        s_abs = math.sqrt(k_ref / m)
        assert abs(r.k - k_ref) <= 2.0 * m * s_abs * ds + m * ds * ds
        assert abs(r.b - b_ref) <= 2.0 * m * ds


@pytest.mark.parametrize("seed", range(12))
def test_sensor_side_timing_has_the_same_poles(seed):
    """The FireFader's timing (force at the packet, position read alpha T later, the
    reply's force in the next packet or later) has the poles of d = packets - alpha."""
    rng = np.random.default_rng(2000 + seed)
    m, b0, rate, _ = _random_loop(rng)
    packets = int(rng.integers(1, 4))
    alpha = float(rng.uniform(0.01, 0.99))
    loop = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=packets - alpha)
    K, B = _gains(rng, loop)
    z_ref, tol = _eig_tol(_sensor_matrix(m, b0, loop.period, packets, alpha, K, B))
    _match(z_ref, tol, closed_loop_poles(loop, K, B))


def test_firefader_timing_felt_damping():
    """configs/firefader.yaml's loop with the board's timing (ADC 1.1 ms after the packet
    at 250 Hz): d = 1 - 1.1/4 = 0.725 felt b = 0.1271 N s/m against 0.1103 at d = 1 (the
    +11 to +16 % the emulated board measured, issue 29)."""
    one = render(LoopModel(mass=0.05, friction=0.1, rate_hz=250, delay=1), 15.0, 0.1)
    real = render(LoopModel(mass=0.05, friction=0.1, rate_hz=250, delay=0.725), 15.0, 0.1)
    z_ref, tol = _eig_tol(_sensor_matrix(0.05, 0.1, 4e-3, 1, 0.275, 15.0, 0.1))
    i = int(np.argmax(np.where(np.abs(z_ref.imag) > 0, np.abs(z_ref), -1.0)))
    k_ref, b_ref = _felt(z_ref[i], 0.05, 4e-3)
    ds = tol[i] / (abs(z_ref[i]) * 4e-3)          # as in the random loops' test
    # derived from the poles' round-off bound (m = 0.05 kg, T = 4 ms), as there
    assert abs(real.b - b_ref) <= 2 * 0.05 * ds
    # derived, the same bound: |dk| <= 2 m |s| |ds| + m |ds|^2
    assert abs(real.k - k_ref) <= 2 * 0.05 * math.sqrt(k_ref / 0.05) * ds + 0.05 * ds * ds
    assert 0.122 <= real.b <= 0.128 and one.b < 0.111


# --------------------------------------------------------------------------- continuity


@pytest.mark.parametrize("seed", range(6))
def test_integer_limits_and_continuity(seed):
    """d -> m+ and d -> (m+1)-: render, calibrate and K_max tend to the whole delay's.
    Every quantity is differentiable in d (the split hold is smooth in f, and
    f = 1 is d = m + 1 plus a pole at z = 0), so a step eps in d moves it by O(eps):
    the bound below is eps times a slope measured on the same loop over a step 1e-3."""
    rng = np.random.default_rng(3000 + seed)
    m, b0, rate, d = _random_loop(rng, whole_max=3)
    b0 = max(b0, 0.5)
    M = int(math.floor(d))
    eps = 1e-9
    base = dict(mass=m, friction=b0, rate_hz=rate)

    def quantities(dd):
        lp = LoopModel(delay=dd, **base)
        km = stability_limit(lp, 0.0)
        r = render(lp, 0.3 * km, 0.0)
        return np.array([km, r.k, r.b])
    for whole, side in ((M, +1), (M + 1, -1)):
        at = quantities(whole)
        near = quantities(whole + side * eps)
        far = quantities(whole + side * 1e-3)
        slope = np.abs(far - at) / 1e-3
        # O(eps) move plus the solvers' relative precision (Brent's 1e-12 on K_max)
        assert np.all(np.abs(near - at) <= 10.0 * slope * eps + 1e-11 * np.abs(at)), \
            (whole, side, near, at)
    ks = [stability_limit(LoopModel(delay=M + t, **base), 0.0)
          for t in np.linspace(0.0, 1.0, 9)]
    assert all(a > b for a, b in zip(ks, ks[1:])), ks   # more delay, less stiffness


@pytest.mark.parametrize("seed", range(6))
def test_fractions_down_to_the_subnormal_range_are_the_whole_delay(seed):
    """A delay ``M + f`` with ``f`` from 1e-12 down to the smallest double (5e-324): the
    split hold's share ``f T`` is subnormal there. Before, the hold's balancing divided
    by it (``inf``, then ``nan``): ``hapsim stability --delay 1e-308`` ended in a
    ``LinAlgError`` traceback, found by a fuzz of the command line. Each quantity is
    finite and within ``f`` times the slope of the whole delay's (the bound of
    :func:`test_integer_limits_and_continuity`), and the hold over ``f T`` is ``(A f T,
    b f T)`` to first order (bound below)."""
    from hapsim.analysis.hand import rigid_matrices, zoh_matrices
    rng = np.random.default_rng(5000 + seed)
    m, b0, rate, d = _random_loop(rng, whole_max=3)
    M = int(math.floor(d))
    base = dict(mass=m, friction=max(b0, 0.5), rate_hz=rate)

    def quantities(dd):
        lp = LoopModel(delay=dd, **base)
        km = stability_limit(lp, 0.0)
        r = render(lp, 0.3 * km, 0.0)
        return np.array([km, r.k, r.b])
    at = quantities(M)
    slope = np.abs(quantities(M + 1e-3) - at) / 1e-3
    A, b = rigid_matrices(m, base["friction"], 0.0)
    T = 1.0 / rate
    for f in (1e-12, 1e-100, 1e-300, 1e-308, 1e-320, 5e-324):
        got = quantities(M + f)
        assert np.all(np.isfinite(got)), (f, got)
        # bound: an O(f) move (f times the slope, derived above) plus the round-off
        # between two computations of one loop (the split hold's and the plain hold's
        # poles, K_max to Brent's rtol 1e-15 on the circle's crossings): beyond the slope
        # term measured 1.7e-15 relative at most (8 eps) over seeds 5000-5039 and every f
        # here, margin 128 for another CPU's or BLAS's rounding
        assert np.all(np.abs(got - at) <= 10.0 * slope * f + 1000 * EPS * np.abs(at)), (
            f, got, at)
        tau = f * T
        Aw, Bd = zoh_matrices(A, b, tau)
        # e^X - I - X and (Gamma - tau I) b are at most ||X||^2 and tau ||X|| ||b|| for
        # ||X|| = ||A tau|| <= 1e-12 (the series' remainder); 4 eps of the largest entry
        # for their sums' rounding; a subnormal carries its own absolute rounding, 2**-1074
        X = np.linalg.norm(A * tau, 2)
        tiny = np.finfo(float).smallest_subnormal
        assert np.all(np.abs(Aw - A * tau)
                      <= 4 * EPS * np.max(np.abs(A * tau)) + X * X + tiny), (f, Aw)
        assert np.all(np.abs(Bd - b * tau)
                      <= 4 * EPS * np.max(np.abs(b * tau)) + tau * X * np.max(np.abs(b))
                      + tiny), (f, Bd)


def test_calibrate_hits_the_target_at_fractional_delays():
    """calibrate's (K, B) renders the target back, at fractional delays."""
    for d in (0.25, 1.3, 2.75):
        lp = LoopModel(mass=0.1, friction=0.5, rate_hz=1000, delay=d)
        c = calibrate(lp, 2000.0, 3.0)
        assert c.renderable
        r = render(lp, c.K, c.B)
        # measured 1.3e-15 relative at most (generic 1.3e-15), margin 7.7e5
        # margin 1e4: the root finders stop at ~1e-12 relative on other targets
        assert abs(r.k - 2000.0) <= measured(1.3e-15, 1e4) * 2000.0 and \
            abs(r.b - 3.0) <= measured(1.3e-15, 1e4) * 3.0


def test_whole_delays_take_the_plain_path_bit_for_bit():
    """A whole delay given as a float (the CLI parses --delay 2 as 2.0) is the int path:
    the same numbers bit for bit."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        m, b0, rate, d = _random_loop(rng)
        d = int(d)
        a = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d)
        b = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=float(d))
        assert isinstance(b.delay, int) and b.delay_fraction == 0.0
        K, B = _gains(rng, a)
        assert np.array_equal(closed_loop_poles(a, K, B), closed_loop_poles(b, K, B))
        assert stability_limit(a, B) == stability_limit(b, B)


def test_ideal_hold_refuses_a_fractional_delay():
    with pytest.raises(ConfigError, match="zoh") as e:
        LoopModel(mass=1.0, rate_hz=1.0, delay=0.5, hold="ideal")
    assert e.value.key == "delay"


# --------------------------------------------------------------------------- scenes

WALL = """rate_hz: {rate!r}
masses:
  - {{name: hand, kind: port}}
  - {{name: wall, kind: ground}}
links:
  - {{name: wall, kind: spring_damper, between: [hand, wall], stiffness: {K!r}, damping: {B!r}}}
device: {{mass: {m!r}, friction: {b0!r}, delay: {d!r}, hold: zoh{extra}}}
excitation: {{x0: 0.001}}
"""

EXTRAS = ["", ", correction: {kind: prediction}", ", correction: {kind: velocity_sensor}",
          ", hand: {mass: 0.05, damping: 0.2, grip_stiffness: 4000, grip_damping: 3}"]


@pytest.mark.parametrize("seed", range(16))
def test_check_scene_equals_render_at_fractional_delays(seed):
    """check (the scene's state matrix, the held force one more state) and render (the
    characteristic polynomial) are two independent builds of the split-hold loop: the same
    spectral radius and felt (k, b), with a correction or a hand behind a grip too."""
    from hapsim.analysis import check_scene
    from hapsim.scene import parse_scene
    rng = np.random.default_rng(4000 + seed)
    m, b0, rate, d = _random_loop(rng, whole_max=4)
    m = max(m, 0.1)
    extra = EXTRAS[seed % len(EXTRAS)]
    sc = parse_scene(WALL.format(rate=rate, K=1.0, B=0.0, m=m, b0=b0, d=d, extra=extra))
    loop = LoopModel.from_device(sc.device, rate)
    K, B = _gains(rng, loop)
    sc = parse_scene(WALL.format(rate=rate, K=K, B=B, m=m, b0=b0, d=d, extra=extra))
    chk = check_scene(sc)
    r = render(loop, K, B)
    z = closed_loop_poles(loop, K, B)
    # the state matrix's dominant eigenvalue, its bound as in the loops' test
    from hapsim.analysis.network import closed_loop
    A, _ = closed_loop(sc)
    zr, tol = _eig_tol(A)
    i = int(np.argmax(np.abs(zr)))
    assert abs(chk.spectral_radius - r.spectral_radius) <= tol[i] + C_BACKWARD * EPS
    _match(zr[np.abs(zr) > 1e-3], tol[np.abs(zr) > 1e-3], z)
    if r.rendered is not None and chk.rendered is not None:
        j = int(np.argmin(np.abs(zr - complex(r.rendered.z))))
        ds = tol[j] / (abs(zr[j]) * loop.period)
        M = loop.mass
        assert abs(chk.rendered.b - r.b) <= 4.0 * M * ds
        assert abs(chk.rendered.k - r.k) <= 4.0 * M * math.sqrt(r.k / M) * ds + 2 * M * ds * ds


@pytest.mark.parametrize("d", [0.4, 1.3, 2.75])
def test_lockstep_run_measures_the_split_hold(d):
    """run --lockstep closes the loop on the mock device, whose physics applies each force
    f T into the period (hapsim.device_model.MockPhysics, integrated sub-interval by
    sub-interval, not from the analysis): measured = render's (k, b)."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import parse_scene
    m, b0, rate = 0.05, 0.1, 250.0
    loop = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d)
    K, B = 15.0, 0.1
    r = render(loop, K, B)
    rep = run_scene(parse_scene(WALL.format(rate=rate, K=K, B=B, m=m, b0=b0, d=d, extra="")),
                    transport="inprocess", lockstep=True, handle_signals=False)
    assert rep["predicted"]["b"] == r.b and rep["predicted"]["k"] == r.k
    # the run's own verdict: measured within the interval it states
    assert rep["measured"]["within"] is True, rep["measured"]["verdict"]
    assert abs(rep["measured"]["b"] - r.b) <= rep["measured"]["b_interval"]
    assert abs(rep["measured"]["k"] - r.k) <= rep["measured"]["k_interval"]


def test_whole_delays_never_touch_the_split_hold(monkeypatch):
    """Integer delays take today's code path: with every split-hold function made to fail,
    check (1-D and n-D), render, calibrate, stability and a lockstep run of every shipped
    scene still answer (so their numbers are the plain hold's, bit for bit; compared
    against the code before this change: 300 random loops and every configs/*.yaml
    check --json identical, docs/stability.md)."""
    import pathlib

    import hapsim.analysis.network as network
    import hapsim.analysis.scene_check as scene_check
    import hapsim.analysis.subsample as subsample
    import hapsim.analysis.ths.holds as holds
    from hapsim.scene import load_scene
    from hapsim.scene import load_scene_nd

    def boom(*a, **k):
        raise AssertionError("the split hold was used for a whole delay")
    for mod, names in ((subsample, ("split_hold", "split_hold_body", "split_numerator_w",
                                    "held_plant")),
                       (network, ("split_plant_rows",)),
                       (holds, ("split_hold_matrices",)),
                       (scene_check, ("split_hold_matrices",))):
        for name in names:
            monkeypatch.setattr(mod, name, boom)
    import hapsim.analysis.loop as loop_mod
    for name in ("split_hold_body", "split_numerator_w"):
        monkeypatch.setattr(loop_mod, name, boom)
    # poles another test of this worker computed are kept (loop_poles.roots_w): start
    # empty, so every pole here is computed under the patches
    import hapsim.analysis.loop_poles as loop_poles
    from hapsim.analysis.kept import Kept
    monkeypatch.setattr(loop_poles, "_ROOTS", Kept(loop_poles._ROOTS.size))
    from hapsim.cli import main
    configs = sorted((pathlib.Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))
    seen = 0
    for path in configs:
        text = path.read_text()
        if "dimension: 2" in text or "dimension: 3" in text:
            dev = load_scene_nd(str(path)).device
            assert dev is None or isinstance(dev.delay, int)
        elif "devices:" in text:          # several ports (two_faders.yaml: the
            from hapsim.scene import load_scene_ports   # FireFader's real delay, 0.725)
            if any(d.delay % 1 for _, d in load_scene_ports(str(path)).devices):
                continue
        else:
            sc = load_scene(str(path))
            if sc.device is None or sc.port is None or sc.device.delay % 1:
                continue          # (firefader.yaml states its real delay, 0.725)
            from hapsim.drivers import device_driver
            if getattr(device_driver(sc.device), "render_latency_s", None) is not None:
                continue          # (hapkit_serial.yaml: check adds its board's render
                #                    latency after the read, a fraction of a period)
            lp = LoopModel.from_device(sc.device, sc.rate_hz)
            r = render(lp, 100.0, 0.1)
            stability_limit(lp, 0.1)
            if r.rendered is not None:
                calibrate(lp, r.k, r.b)
        assert main(["check", str(path), "--json"]) in (0, 1), path   # (1: unstable)
        seen += 1
    assert seen >= 10
    # and the patches bite: a fractional delay does go through them
    with pytest.raises(AssertionError, match="split hold"):
        render(LoopModel(mass=0.1, friction=0.5, rate_hz=1000.0, delay=1.5), 100.0)


def test_firefader_with_its_own_adc_timing_is_predicted_by_the_real_delay():
    """configs/firefader.yaml run through the FireFader's bytes on its driver mock, the
    board keeping its own pass timing (the .ino sets the PWM at the packet and reads the
    fader 1.1 ms later: hapsim.emulated.driver_mock.FireFaderDevice(adc_s=1.1e-3), which ignores the
    scene's delay): the scene's d = 1 - 1.1/4 = 0.725 predicts the measured (k, b) within
    the run's stated uncertainty, and the measured b lies outside that uncertainty of the
    whole delay's prediction (the issue's +11 to +16 %)."""
    import dataclasses

    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    import pathlib
    sc = load_scene(str(pathlib.Path(__file__).resolve().parents[1] / "configs"
                        / "firefader.yaml"))
    assert sc.device.delay == 0.725
    # lockstep by name: the split hold's arithmetic, bit-exact timing (the same board on
    # the wall clock: tests/test_wallclock.py)
    rep = run_scene(sc, driver="firefader", mock_options={"adc_s": 1.1e-3}, lockstep=True,
                    handle_signals=False, rt_priority=0)
    m = rep["measured"]
    assert m["within"] is True, m["verdict"]
    whole = render(LoopModel.from_device(dataclasses.replace(sc.device, delay=1),
                                         sc.rate_hz), *_spring(sc))
    assert m["b"] - whole.b > m["b_interval"] and m["b"] > 1.1 * whole.b


def _spring(sc):
    lk = sc.links[0]
    return lk.stiffness, lk.damping


@pytest.mark.parametrize("kg", ["[500, 5000]", "rigid"])
def test_family_matrices_equal_closed_loop_per_member_at_a_fractional_delay(kg):
    """The hand family's stacked split hold (family_loops) equals the scene matrix built
    member by member (network.closed_loop), each entry to a few roundings of its size
    (the stacked and the single exponentials differ in the order of their products)."""
    from hapsim.analysis.family import family_members, family_matrices
    from hapsim.analysis.network import closed_loop
    from hapsim.scene import parse_scene
    text = f"""
rate_hz: 1000
masses: [{{name: hand, kind: port}}, {{name: wall, kind: ground}}]
links: [{{name: wall, kind: spring_damper, between: [hand, wall], stiffness: 100,
          damping: 2}}]
device: {{mass: 0.02, friction: 1.0, delay: 1.35, force_limit: 1000000.0,
          hand: {{mass: [0.05, 0.5], damping: 1.0, grip_stiffness: {kg}, grip_damping: 0.0}}}}
excitation: {{x0: 0.002}}
"""
    sc = parse_scene(text)
    mem = family_members(sc, 5)
    A, names = family_matrices(sc, mem)
    assert names[-1].startswith("F[n-2]")
    for i in range(mem.shape[0]):
        Ai, ni = closed_loop(sc, member=mem[i])
        assert ni == names
        scale = np.abs(Ai) + np.abs(A[i])
        # (absolute below 1: the poles see errors against ||A|| >= 1, its identity blocks)
        assert np.all(np.abs(A[i] - Ai) <= C_BACKWARD * EPS * np.maximum(scale, 1.0))


CHAIN = """rate_hz: {rate!r}
masses:
  - {{name: hand, kind: port}}
  - {{name: bead, kind: mass, mass: {mv!r}}}
  - {{name: wall, kind: ground}}
links:
  - {{name: a, kind: spring_damper, between: [hand, bead], stiffness: {K1!r}, damping: {B1!r}}}
  - {{name: b, kind: spring_damper, between: [bead, wall], stiffness: {K2!r}, damping: {B2!r}}}
device: {{mass: {m!r}, friction: {b0!r}, delay: {d!r}, hold: zoh}}
excitation: {{x0: 0.001}}
"""


@pytest.mark.parametrize("seed", range(3))
def test_lockstep_scenes_with_a_virtual_mass_are_predicted(seed):
    """Random scenes with a virtual mass between the port and a wall, random fractional
    delays: the lockstep run (the numba engine and the mock device's split hold, sample by
    sample) measures what check's scene matrix predicts, within the run's own interval."""
    from hapsim.analysis import check_scene
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import parse_scene
    rng = np.random.default_rng(7000 + seed)
    for _ in range(50):
        kw = dict(rate=float(rng.choice([500.0, 1000.0, 2000.0])),
                  m=float(rng.uniform(0.05, 0.3)), b0=float(rng.uniform(0.2, 2.0)),
                  d=float(rng.integers(0, 3) + rng.uniform(0.05, 0.95)),
                  mv=float(rng.uniform(0.01, 0.1)), K1=float(rng.uniform(50, 500)),
                  B1=float(rng.uniform(0.0, 1.0)), K2=float(rng.uniform(50, 500)),
                  B2=float(rng.uniform(0.0, 1.0)))
        sc = parse_scene(CHAIN.format(**kw))
        chk = check_scene(sc)
        if chk.stable and chk.spectral_radius < 0.9999 and chk.rendered is not None:
            break
    rep = run_scene(sc, transport="inprocess", lockstep=True, handle_signals=False)
    m = rep["measured"]
    assert m["within"] is True, (kw, m["verdict"])
    assert abs(m["b"] - chk.rendered.b) <= m["b_interval"]
    assert abs(m["k"] - chk.rendered.k) <= m["k_interval"]
