"""The THS as a matrix (hapsim.analysis.ths) against an independent MIMO reference
written here (continuous system, scipy.linalg.expm ZOH, a *force* delay line instead of
hapsim's position delay line, eigenvalues; felt matrices by least squares on the quadratic
eigen-equations), the 1-D prediction of hapsim.analysis.ths/loop, the 1-D answer per axis
of a decoupled loop, and coupling that axis-by-axis checks miss; the entries of
hapsim.analysis.ths (render, calibrate, state_matrix, closed_loop_poles, rendered_pairs)
taking a 1-D loop and a matrix loop alike, and refusing by name what the matrix loop does
not model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.optimize import linear_sum_assignment

from hapsim.analysis.loop import LoopModel, characteristic
from hapsim.analysis.loop_poles import spectral_radius
from hapsim.analysis.stability import stability_limit
from hapsim.analysis.direction_limits import direction_limit, direction_limits, workspace_limits
from hapsim.analysis.ths import (MatrixLoop, as_matrix_loop, calibrate, closed_loop_poles,
                                rendered_pairs, render, state_matrix)
from hapsim.errors import ConfigError
from hapsim.kinematics import Pantograph
from tolerance import (BRENT_THETA, crossing_tol, eig_tol, expm_tol, measured, rel_tol,
                       roots_tol, solve_tol)

pytestmark = pytest.mark.numerical


# --------------------------------------------------------------------------- reference

def reference_state_matrix(M, B0, T, d, K, B):
    """Independent closed loop: x' = v, M v' = -B0 v + F; ZOH by expm of the augmented
    continuous system; the force computed from the current position and delayed by d
    samples through a force delay line. State (x, v, x[n-1], F[n-1], ..., F[n-d])."""
    n = M.shape[0]
    Minv = np.linalg.inv(M)
    Ac = np.zeros((2 * n, 2 * n))
    Ac[:n, n:] = np.eye(n)
    Ac[n:, n:] = -Minv @ B0
    Bc = np.vstack([np.zeros((n, n)), Minv])
    aug = np.zeros((3 * n, 3 * n))
    aug[:2 * n, :2 * n] = Ac * T
    aug[:2 * n, 2 * n:] = Bc * T
    E = expm(aug)
    Ad, Bd = E[:2 * n, :2 * n], E[:2 * n, 2 * n:]
    # controller output now: Fc = -(K + B/T) x + (B/T) x[n-1]
    Cx, Cxp = -(K + B / T), B / T
    N = n * (3 + d)
    A = np.zeros((N, N))
    X, V, XP = slice(0, n), slice(n, 2 * n), slice(2 * n, 3 * n)

    def Fd(k):              # F[n-k], k = 1..d
        return slice((2 + k) * n, (3 + k) * n)
    # plant driven by F[n] = Fc[n - d]
    if d == 0:
        A[:2 * n, X] += Bd @ Cx
        A[:2 * n, XP] += Bd @ Cxp
    else:
        A[:2 * n, Fd(d)] += Bd
    A[:2 * n, :2 * n] += Ad
    A[XP, X] = np.eye(n)
    if d >= 1:
        A[Fd(1), X] = Cx             # F[n] (new, delayed by one) = Fc[n]
        A[Fd(1), XP] = Cxp
        for k in range(2, d + 1):
            A[Fd(k), Fd(k - 1)] = np.eye(n)
    return A


def match(a, b):
    """Largest distance between two eigenvalue sets, optimally paired."""
    cost = np.abs(a[:, None] - b[None, :])
    r, c = linear_sum_assignment(cost)
    return float(cost[r, c].max())


def pole_tol_1d_nd(l1, ln, K, B):
    """Bound on the distance between the 1-D poles (numpy.roots of ``P K + Q B + R``,
    Newton-polished) and the n-D ones (eigenvalues of the state matrix): the sum of each
    path's eigenvalue round-off bound (tests/tolerance.py, LAPACK Users' Guide 4.8.1)."""
    P, Q, R = characteristic(l1)
    c = np.polyadd(np.polyadd(P * K, Q * B), R)
    return roots_tol(c) + eig_tol(state_matrix(ln, K, B))


def felt_tols(z, dz, m, T):
    """Round-off of the felt (k, b) of pole ``z`` known to ``dz``: ``s = ln(z) / T`` moves
    by ``dz / (|z| T)`` (first order), ``k = m |s|^2`` by ``2 m |s| ds``, ``b = -2 m Re s``
    by ``2 m ds``; returns (dk, db) [N/m, N s/m]."""
    s = np.log(z) / T
    ds = dz / (abs(z) * T)
    return 2 * m * abs(s) * ds, 2 * m * ds


def limit_tol(l1, K, B, dz):
    """Bound on the distance between two computations of the stiffness limit ``K`` [N/m]:
    each one puts a pole on ``|z| = 1`` to within the pole's round-off ``dz`` plus Brent's
    tolerance on the angle, so each is off by at most that over ``|d rho / d K|``
    (tests/tolerance.py crossing_tol)."""
    return 2 * crossing_tol(lambda k: spectral_radius(l1, k, B), K, dz + BRENT_THETA)


def limit_tol_1d(m, b0, rate, d, K, B):
    """:func:`limit_tol` of the 1-D loop (m, b0) with both paths' pole round-off."""
    l1 = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d)
    ln = MatrixLoop(mass=[[m]], friction=[[b0]], rate_hz=rate, delay=d)
    return limit_tol(l1, K, B, pole_tol_1d_nd(l1, ln, K, B))


def reference_pole_tol(loop, M, B0, T, d, K, B):
    """Bound on |reference poles - hapsim's|: each eigenproblem's round-off, the reference
    matrix's entries carrying expm's error (tests/tolerance.py expm_tol) through the
    products with the controller gains."""
    n = M.shape[0]
    Minv = np.linalg.inv(M)
    aug = np.zeros((3 * n, 3 * n))
    aug[:n, n:2 * n] = np.eye(n) * T
    aug[n:2 * n, n:2 * n] = -Minv @ B0 * T
    aug[n:2 * n, 2 * n:] = Minv * T
    E = expm(aug)
    gain = max(1.0, np.linalg.norm(K + B / T, 2), np.linalg.norm(B / T, 2))
    err = expm_tol(aug) * np.linalg.norm(E, 2) * gain
    A = reference_state_matrix(M, B0, T, d, K, B)
    return eig_tol(A, err) + eig_tol(state_matrix(loop, K, B))


def random_spd(rng, n, lo, hi):
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return Q @ np.diag(rng.uniform(lo, hi, n)) @ Q.T


def random_loop(rng, n):
    M = random_spd(rng, n, 0.05, 0.5)
    B0 = random_spd(rng, n, 0.0, 2.0)
    rate = float(rng.choice([500.0, 1000.0, 4000.0]))
    d = int(rng.choice([0, 1, 2, 4]))
    K = random_spd(rng, n, 0.0, 800.0)
    B = random_spd(rng, n, 0.0, 3.0)
    return M, B0, rate, d, K, B


def reference_felt(M, T, z, V, n):
    """Felt (k, b) by least squares on (M s^2 + b s + k) u = 0 over the n least damped
    complex pairs of the reference (real and imaginary parts, 2n^2 unknowns)."""
    up = np.flatnonzero(z.imag > 0)       # LAPACK: a real eigenvalue has imag exactly 0
    up = up[np.argsort(-np.abs(z[up]))][:n]
    rows, rhs = [], []
    for i in up:
        s = np.log(z[i]) / T
        u = V[:n, i] / np.linalg.norm(V[:n, i])
        # unknown vector: vec(k) row-major then vec(b): (k u)_r = sum_c k[r, c] u[c]
        for r in range(n):
            row = np.zeros(2 * n * n, complex)
            row[r * n:(r + 1) * n] = u
            row[n * n + r * n:n * n + (r + 1) * n] = s * u
            val = -(M @ u)[r] * s * s
            rows += [row.real, row.imag]
            rhs += [val.real, val.imag]
    x = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    return x[:n * n].reshape(n, n), x[n * n:].reshape(n, n)


# --------------------------------------------------------------------------- tests

@pytest.mark.parametrize("n", [2, 3])
def test_eigenvalues_and_felt_matrices_equal_the_independent_reference(n):
    """Over random n-D loops (random SPD mass and friction, rate, delay, SPD K and B):
    the poles equal the reference's to both eigenproblems' round-off, and the felt
    matrices the reference's least-squares ones (measured: 7.0e-12 relative at worst on
    x86-64 with the OpenBLAS Haswell, Sandybridge, Prescott kernels, margin 1000; a
    wrong felt formula moves them by >= 1e-3) when the reference's n least damped pairs
    are the rendered ones."""
    rng = np.random.default_rng(100 + n)
    felt_checked = 0
    for _ in range(24):
        M, B0, rate, d, K, B = random_loop(rng, n)
        loop = MatrixLoop(mass=M, friction=B0, rate_hz=rate, delay=d)
        A = reference_state_matrix(M, B0, 1.0 / rate, d, K, B)
        z_ref, V = np.linalg.eig(A)
        z = closed_loop_poles(loop, K, B)
        assert z.size == z_ref.size == n * (d + 3)
        dz = reference_pole_tol(loop, M, B0, 1.0 / rate, d, K, B)
        assert match(z, z_ref) <= dz
        r = render(loop, K, B)
        assert r.spectral_radius == pytest.approx(np.max(np.abs(z_ref)), rel=0, abs=dz)
        if r.felt_stiffness is None:
            continue
        up = np.sort(np.abs(z_ref[z_ref.imag > 0]))[::-1][:n]
        if not np.allclose(np.sort(np.abs(r.rendered_poles))[::-1], up, rtol=0, atol=dz):
            continue          # a shape-dependent pick: not the same n pairs
        k_ref, b_ref = reference_felt(M, 1.0 / rate, z_ref, V, n)
        scale_k = np.max(np.abs(k_ref))
        scale_b = max(np.max(np.abs(b_ref)), 1e-3)
        assert np.max(np.abs(r.felt_stiffness - k_ref)) <= measured(7.0e-12, 1000) * scale_k
        assert np.max(np.abs(r.felt_damping - b_ref)) <= measured(7.1e-12, 1000) * scale_b
        felt_checked += 1
    assert felt_checked >= 12


def test_felt_system_has_the_rendered_poles_and_shapes():
    """M x'' + b x' + k x = 0 with the felt matrices has the rendered s_i = ln(z_i)/T as
    eigenvalues (the definition, checked on its continuous state matrix; measured:
    1.0e-15 of max |s| at worst on the kernels listed above, margin 1000)."""
    rng = np.random.default_rng(7)
    for n in (2, 3):
        M, B0, rate, d, K, B = random_loop(rng, n)
        loop = MatrixLoop(mass=M, friction=B0, rate_hz=rate, delay=min(d, 1))
        r = render(loop, K, B)
        Minv = np.linalg.inv(M)
        Ac = np.block([[np.zeros((n, n)), np.eye(n)],
                       [-Minv @ r.felt_stiffness, -Minv @ r.felt_damping]])
        s = np.linalg.eigvals(Ac)
        s_ren = np.log(r.rendered_poles) * rate
        assert match(s, np.concatenate([s_ren, s_ren.conj()])) <= measured(1.0e-15, 1000) * \
            np.max(np.abs(s))


@pytest.mark.parametrize("seed", range(6))
def test_one_dof_reproduces_the_1d_prediction(seed):
    """n = 1: poles, felt (k, b), spectral radius and the stiffness limit equal
    hapsim.analysis.loop/ths's to round-off."""
    rng = np.random.default_rng(seed)
    m, b0 = rng.uniform(0.02, 1.0), rng.uniform(0.0, 3.0)
    rate, d = float(rng.choice([500.0, 1000.0, 10000.0])), int(rng.integers(0, 6))
    K, B = rng.uniform(10.0, 1500.0), rng.uniform(0.0, 3.0)
    l1 = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d)
    ln = MatrixLoop(mass=[[m]], friction=[[b0]], rate_hz=rate, delay=d)
    dz = pole_tol_1d_nd(l1, ln, K, B)
    assert match(closed_loop_poles(l1, K, B), closed_loop_poles(ln, K, B)) <= dz
    r1, rn = render(l1, K, B), render(ln, K, B)
    assert rn.spectral_radius == pytest.approx(r1.spectral_radius, rel=0, abs=dz)
    assert rn.stable == r1.stable
    if math.isfinite(r1.k):
        dk, db = felt_tols(rn.rendered_poles[0], dz, m, 1.0 / rate)
        assert rn.felt_stiffness[0, 0] == pytest.approx(r1.k, rel=0, abs=dk)
        assert rn.felt_damping[0, 0] == pytest.approx(r1.b, rel=0, abs=db)
        assert rn.direction_stiffness[0] == pytest.approx(r1.k, rel=0, abs=dk)
    k1 = stability_limit(l1, B)
    dz1 = pole_tol_1d_nd(l1, ln, k1, B)
    assert direction_limit(ln, [1.0], B) == pytest.approx(k1, rel=0,
                                                          abs=limit_tol(l1, k1, B, dz1))


@pytest.mark.parametrize("n", [2, 3])
def test_decoupled_loop_is_the_1d_answer_per_axis(n):
    """Diagonal mass, friction, K and B: the felt matrices are diagonal with the 1-D
    (k, b) of each axis on the diagonal; the limit along each axis is its 1-D limit."""
    rng = np.random.default_rng(20 + n)
    m, b0 = rng.uniform(0.05, 0.4, n), rng.uniform(0.1, 1.0, n)
    K, B = rng.uniform(100.0, 800.0, n), rng.uniform(0.5, 2.0, n)
    loop = MatrixLoop(mass=m, friction=b0, rate_hz=1000.0, delay=1)
    r = render(loop, K, B)
    assert r.stable
    for i in range(n):
        l1 = LoopModel(mass=m[i], friction=b0[i], rate_hz=1000.0, delay=1)
        r1 = render(l1, K[i], B[i])
        P, Q, R = characteristic(l1)
        dz = (roots_tol(np.polyadd(np.polyadd(P * K[i], Q * B[i]), R))
              + eig_tol(state_matrix(loop, np.diag(K), np.diag(B))))
        dk, db = np.max([felt_tols(z, dz, m[i], 1e-3) for z in r.rendered_poles], axis=0)
        assert r.felt_stiffness[i, i] == pytest.approx(r1.k, rel=0, abs=dk)
        assert r.felt_damping[i, i] == pytest.approx(r1.b, rel=0, abs=db)
        e = np.eye(n)[i]
        k1 = stability_limit(l1, B[i])
        assert direction_limit(loop, e, B) == pytest.approx(
            k1, rel=0, abs=limit_tol_1d(m[i], b0[i], 1000.0, 1, k1, B[i]))
    off = r.felt_stiffness - np.diag(np.diag(r.felt_stiffness))
    assert np.max(np.abs(off)) <= max(felt_tols(z, dz, np.max(m), 1e-3)[0]
                                      for z in r.rendered_poles)


def test_rotation_moves_the_felt_matrices_not_the_poles():
    """A rotated device and coupling: same poles, felt matrices R k R^T, directions R e."""
    rng = np.random.default_rng(8)
    M, B0, rate, d, K, B = random_loop(rng, 3)
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    a = render(MatrixLoop(mass=M, friction=B0, rate_hz=rate, delay=1), K, B)
    b = render(MatrixLoop(mass=R @ M @ R.T, friction=R @ B0 @ R.T, rate_hz=rate,
                          delay=1), R @ K @ R.T, R @ B @ R.T)
    # the rotated inputs carry a product's round-off (R X R^T: 2 x 3 terms, rel_tol(6))
    # into the state matrix, amplified by M^-1 (cond(M)); plus each eigenproblem's own
    Ab = state_matrix(MatrixLoop(mass=R @ M @ R.T, friction=R @ B0 @ R.T, rate_hz=rate,
                                 delay=1), R @ K @ R.T, R @ B @ R.T)
    err = rel_tol(6) * np.linalg.cond(M) * np.linalg.norm(Ab, 2)
    dz = eig_tol(Ab, err) + eig_tol(state_matrix(MatrixLoop(mass=M, friction=B0,
                                                            rate_hz=rate, delay=1), K, B))
    assert match(a.poles, b.poles) <= dz
    # felt matrices and directions: measured (4.9e-13, 8.9e-13 relative, 4.4e-16 on the
    # directions' cosines, on the kernels listed above), margin 1000
    assert np.allclose(R @ a.felt_stiffness @ R.T, b.felt_stiffness, rtol=0,
                       atol=measured(4.9e-13, 1000) * np.max(np.abs(a.felt_stiffness)))
    # 1e-3 N s/m floors the scale where the felt damping is ~0: measured 1.9e-12 (generic
    # 2.1e-12), margin 910 on the whole atol
    assert np.allclose(R @ a.felt_damping @ R.T, b.felt_damping, rtol=0,
                       atol=measured(8.9e-13, 1000) * max(np.max(np.abs(a.felt_damping)),
                                                          1e-3))
    for i in range(3):
        assert abs(abs((R @ a.directions[:, i]) @ b.directions[:, i]) - 1) <= measured(
            4.5e-16, 1000)


def test_axis_by_axis_stable_but_coupled_loop_unstable():
    """Li, Tavakoli & Huang 2014: a non-diagonal Cartesian mass (light along a diagonal
    direction) with K = kappa I: each axis's 1-D check (mass M_ii) is stable, the MIMO
    characteristic is not; the limit along M's light axis is the 1-D limit of its
    eigenvalue (isotropic friction and damping commute with M: decoupled there)."""
    th = math.radians(35)
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    lam = np.array([0.02, 0.3])
    M = R @ np.diag(lam) @ R.T
    b0, beta = 2.0, 10.0          # damping-heavy: the limit depends on the mass here
    loop = MatrixLoop(mass=M, friction=b0 * np.eye(2), rate_hz=1000.0, delay=1)
    light = LoopModel(mass=lam[0], friction=b0, rate_hz=1000.0, delay=1)
    k_light = stability_limit(light, beta)
    k_axes = [stability_limit(LoopModel(mass=M[i, i], friction=b0, rate_hz=1000.0,
                                        delay=1), beta) for i in range(2)]
    assert min(k_axes) > 1.2 * k_light
    kappa = 0.5 * (k_light + min(k_axes))
    for i in range(2):
        assert render(LoopModel(mass=M[i, i], friction=b0, rate_hz=1000.0, delay=1),
                      kappa, beta).stable
    r = render(loop, kappa * np.eye(2), beta * np.eye(2))
    assert not r.stable and r.spectral_radius > 1.0
    limits = direction_limits(loop, None, beta * np.eye(2))
    # M = R diag(lam) R^T in floating point: its eigenvalues carry eig_tol(M), which
    # moves a limit proportional to the mass by K dm / m; plus each method's own
    dm = eig_tol(M)
    k_heavy = stability_limit(LoopModel(mass=lam[1], friction=b0, rate_hz=1000.0,
                                        delay=1), beta)
    for k, mass in ((k_light, lam[0]), (k_heavy, lam[1])):
        tol = limit_tol_1d(mass, b0, 1000.0, 1, k, beta) + k * dm / mass
        assert limits[list((k_light, k_heavy)).index(k)] == pytest.approx(k, rel=0, abs=tol)


def test_workspace_limits_follow_the_configuration_dependent_mass():
    """Over Haply pantograph configurations (isotropic joint friction mapped, hand
    damping, virtual damping beta I): the limit along each principal axis of M(q) is
    the 1-D limit of that principal mass with that axis's friction, where the mapped
    friction shares M's axes (joint inertia and friction proportional); it varies across
    the workspace."""
    dev = Pantograph("haply")
    Iq, c = 2e-4, 500.0                     # joint inertia [kg m^2]; B_q = Iq / c ...
    qs = np.radians([[130, 50], [150, 60], [120, 30], [140, 20]])
    beta = 1.0
    w = workspace_limits(dev, qs, [Iq, Iq], [Iq * c, Iq * c], rate_hz=1000.0, delay=1,
                         B=beta * np.eye(2))
    assert w.status == ["ok"] * 4
    for i in range(4):
        for j in range(2):
            m = w.mass_eigenvalues[i, j]
            ref = stability_limit(LoopModel(mass=m, friction=c * m, rate_hz=1000.0,
                                            delay=1), beta)
            # the principal mass is an eigenvalue of J^-T M_q J^-1 (its round-off: a
            # solve's bound on J, then eig_tol); the limit moves by K dm / m with it
            J = dev.jacobian(qs[i])
            dm = m * 2 * solve_tol(J) + eig_tol(w.mass_eigenvalues[i, j] * np.eye(1))
            tol = limit_tol_1d(m, c * m, 1000.0, 1, ref, beta) + ref * dm / m
            assert w.limits[i, j] == pytest.approx(ref, rel=0, abs=tol)
    assert np.ptp(w.limits[:, 0]) > 0.05 * np.mean(w.limits[:, 0])


def test_matrix_loop_refuses_bad_input():
    """Key-named refusals: a mass not SPD, friction not PSD, shapes, hold, delay."""
    for kw, key in [(dict(mass=[[1.0, 2.0], [2.0, 1.0]]), "mass"),
                    (dict(mass=[[1.0, 0.5], [0.0, 1.0]]), "mass"),
                    (dict(mass=np.eye(2), friction=-np.eye(2)), "friction"),
                    (dict(mass=np.eye(2), friction=np.eye(3)), "friction"),
                    (dict(mass=np.eye(2), hold="ideal"), "hold"),
                    (dict(mass=np.eye(2), delay=-0.5), "delay"),
                    (dict(mass=np.eye(4)), "dof"),
                    (dict(mass=0.1), "dof")]:
        with pytest.raises(ConfigError) as err:
            MatrixLoop(**kw)
        assert err.value.key == key, (kw, err.value)
    loop = MatrixLoop(mass=np.eye(2) * 0.1)
    with pytest.raises(ConfigError) as err:
        render(loop, np.ones((3, 3)))
    assert err.value.key == "K"
    with pytest.raises(ConfigError) as err:
        direction_limit(loop, [0.0, 0.0])
    assert err.value.key == "direction"


# ------------------------------------------------------------- one entry, any dimension

@pytest.mark.parametrize("seed", range(8))
def test_one_entry_takes_a_1d_loop_as_the_case_n_equals_1(seed):
    """The entries of hapsim.analysis.ths take a 1-D LoopModel where they take a matrix
    loop: state_matrix and rendered_pairs see it as the matrix loop n = 1 (bit for bit the
    same matrix), whose eigenvalues are the 1-D closed_loop_poles' to both paths' round-off;
    calibrate of the matrix loop n = 1 is the 1-D calibration, exactly, and its (K, B)
    render through the matrix form the felt target (k, b) to the poles' round-off."""
    rng = np.random.default_rng(100 + seed)
    m, b0 = rng.uniform(0.02, 1.0), rng.uniform(0.0, 3.0)
    rate, d = float(rng.choice([500.0, 1000.0, 10000.0])), int(rng.integers(0, 6))
    l1 = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d)
    ln = MatrixLoop(mass=[[m]], friction=[[b0]], rate_hz=rate, delay=d)
    assert as_matrix_loop(l1) == ln and as_matrix_loop(ln) is ln
    assert ln.to_loop_model() == l1
    T = 1.0 / rate
    # a target the loop can render: a fraction of the loop's own first-order limits
    k = rng.uniform(0.05, 0.3) * m / (T * T * (1 + d) ** 2)
    b = b0 + rng.uniform(0.05, 0.3) * m / (T * (1 + d))
    K, B = rng.uniform(0.1, 0.5) * stability_limit(l1, 0.0), 0.0
    A = state_matrix(l1, K, B)
    assert np.array_equal(A, state_matrix(ln, K, B))
    dz = pole_tol_1d_nd(l1, ln, K, B)
    assert match(np.linalg.eigvals(A), closed_loop_poles(l1, K, B)) <= dz
    zr, U, _ = rendered_pairs(l1, K, B)
    r1 = render(l1, K, B)
    assert zr.size == 1 and r1.rendered is not None
    assert abs(zr[0] - r1.rendered.z) <= dz
    # the one shape is u / |u| turned real positive: a norm, a division, an abs and a
    # product deep (4), unit to that
    assert U.shape == (1, 1) and abs(U[0, 0] - 1.0) <= rel_tol(4)
    c1, cn = calibrate(l1, k, b), calibrate(ln, k, b)
    assert cn.to_dict() == c1.to_dict()
    assert c1.renderable, c1.reason      # every seed's target is within the limits
    rn, r1 = render(ln, c1.K, c1.B), render(l1, c1.K, c1.B)
    # the 1-D render of the calibrated gains is at the target to its own round-off,
    # measured here; the matrix form is within dz of the 1-D render (the two paths)
    dz_c = pole_tol_1d_nd(l1, ln, c1.K, c1.B) + abs(r1.rendered.z - c1.target.z)
    dk, db = felt_tols(rn.rendered_poles[0], dz_c, m, T)
    assert rn.felt_stiffness[0, 0] == pytest.approx(k, rel=0, abs=dk)
    assert rn.felt_damping[0, 0] == pytest.approx(b, rel=0, abs=db)


def test_the_matrix_loop_refuses_by_name_what_it_does_not_model():
    """A 1-D loop the matrix loop does not model (the paper's ideal hold, a compliant grip,
    a real stiffness, a correction) is refused with the key named, never approximated;
    calibrating felt matrices (more than one axis) is refused by name; the 1-D entries
    still take such a loop by its closed forms."""
    from hapsim.analysis.corrections import Correction
    base = dict(mass=0.1, friction=0.5, rate_hz=1000.0, delay=1)
    for kw, key in [(dict(hold="ideal"), "hold"),
                    (dict(mass=0.1, hand_mass=0.05, grip_stiffness=2000.0), "loop"),
                    (dict(stiffness=50.0), "loop"),
                    (dict(correction=Correction(kind="velocity_sensor")), "loop")]:
        lp = LoopModel(**{**base, **kw})
        for call in (lambda: MatrixLoop.from_loop(lp), lambda: state_matrix(lp, 100.0),
                     lambda: rendered_pairs(lp, 100.0)):
            with pytest.raises(ConfigError) as err:
                call()
            assert err.value.key == key, (kw, err.value)
        assert math.isfinite(render(lp, 100.0, 1.0).spectral_radius)
        assert closed_loop_poles(lp, 100.0, 1.0).size >= 3
    loop2 = MatrixLoop(mass=np.eye(2) * 0.1, friction=0.5, rate_hz=1000.0, delay=1)
    for call in (lambda: calibrate(loop2, 500.0, 3.0), loop2.to_loop_model):
        with pytest.raises(ConfigError) as err:
            call()
        assert err.value.key == "dof"
    with pytest.raises(ConfigError) as err:
        as_matrix_loop(object())
    assert err.value.key == "loop"
