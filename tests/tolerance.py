"""Derived round-off tolerances for the tests: bounds, not numbers tuned on one CPU.

A test that compares two floating-point computations of one quantity (the 1-D analysis and
the n-D one, hapsim and an independent reference written in the test, a compiled kernel and
numpy) may differ by the round-off of each path. How much depends on the BLAS kernel, the
compiler's use of fused multiply-add and the summation order, so a literal such as ``1e-13``
that holds on the developer's CPU can fail on another (issue 31: poles ``1.62e-13`` apart
against ``1e-13`` on an AMD EPYC without AVX-512). The functions here turn the conditioning
of the problem and a published bound on the algorithm's backward error into the tolerance.

Every bound is stated with its source. ``u = eps/2`` is the unit round-off of IEEE double
(Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed., SIAM 2002, Sec. 2.1).
Where a bound carries a "modestly growing function p(N)" of the size (LAPACK's wording), the
tests take ``p(N) = N``, which covers the rounding of an ``N``-term inner product (Higham
eq. (3.4)) and is the factor every routine used here stays within in practice; the factor
``SAFETY`` below is the only free constant and is stated once.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg

#: Machine epsilon of IEEE double, ``2**-52`` [-].
EPS = float(np.finfo(float).eps)
#: Unit round-off ``u = eps / 2`` (Higham Sec. 2.1) [-].
U = EPS / 2.0
#: One free factor over the first-order bounds below (they drop O(u^2) terms and the
#: "p(N)" of LAPACK is not a proven constant): 10 keeps every bound a bound while it stays
#: orders of magnitude under the errors the tests are written to catch (a wrong formula
#: moves a pole by >= 1e-6 relative).
SAFETY = 10.0


def gamma(n: int) -> float:
    """Higham's ``gamma_n = n u / (1 - n u)`` [-].

    Parameters
    ----------
    n : int
        Number of rounded operations in the longest chain (>= 0, ``n u < 1``).

    Returns
    -------
    float
        The bound on ``|prod (1 + delta_i)^(+-1) - 1|`` over ``n`` roundings
        (Higham, Lemma 3.1).

    Raises
    ------
    ValueError
        When ``n u >= 1`` (the lemma does not hold).
    """
    nu = n * U
    if nu >= 1.0:
        raise ValueError(f"gamma({n}): n u >= 1")
    return nu / (1.0 - nu)


def sum_tol(values) -> float:
    """Absolute bound on the round-off of a floating-point sum of ``values`` [their unit].

    Parameters
    ----------
    values : array_like
        The terms, any shape (flattened).

    Returns
    -------
    float
        ``gamma(n - 1) * sum |x_i|`` (Higham eq. (4.4), any summation order, so numpy's
        pairwise and a compiled loop's sequential sum alike), times :data:`SAFETY`.
    """
    x = np.abs(np.asarray(values, dtype=float).ravel())
    return SAFETY * gamma(max(x.size - 1, 1)) * float(np.sum(x))


def dot_tol(a, b) -> float:
    """Absolute bound on the round-off of the inner product ``a . b`` [their unit].

    Parameters
    ----------
    a, b : array_like
        Vectors of one length ``n``.

    Returns
    -------
    float
        ``gamma(n) * sum |a_i b_i|`` (Higham eq. (3.5)), times :data:`SAFETY`; covers a
        fused multiply-add kernel too (each FMA rounds once, fewer than the bound counts).
    """
    a = np.asarray(a, dtype=float).ravel()
    b = np.asarray(b, dtype=float).ravel()
    return SAFETY * gamma(max(a.size, 1)) * float(np.sum(np.abs(a * b)))


def rel_tol(ops: int, cond: float = 1.0) -> float:
    """Relative bound for a result ``ops`` roundings deep with condition number ``cond`` [-].

    Parameters
    ----------
    ops : int
        Length of the longest chain of rounded operations the result depends on; count it
        beside the call (e.g. "exp, two products, one sum: 4").
    cond : float, optional
        Relative condition number of the quantity with respect to its inputs (1 for a
        product or a quotient, ``sum |x| / |sum x|`` for a sum, ...).

    Returns
    -------
    float
        ``SAFETY * cond * gamma(ops)``: forward error <= condition number x backward error
        (Higham Sec. 1.6), the backward error of ``ops`` roundings being ``gamma(ops)``
        (Lemma 3.1); library functions (exp, log, sin, sqrt) count as one rounding each
        (correctly rounded or within 1 ulp in glibc, the bound their manual states).
    """
    return SAFETY * float(cond) * gamma(int(ops))


def eig_bounds(A, err: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues of ``A`` and an absolute bound on each one's round-off [unit of A].

    Parameters
    ----------
    A : array_like, shape (N, N)
        A real or complex square matrix.
    err : float, optional
        A bound on the 2-norm of the error already in ``A``'s entries (e.g. the round-off
        of the matrix exponential that built them, :func:`expm_tol` times its norm); it
        moves eigenvalue ``i`` by at most ``err / s_i`` (condition numbers of ``A`` itself,
        unbalanced, since that error is in ``A``'s coordinates).

    Returns
    -------
    w : ndarray of complex, shape (N,)
        Eigenvalues (scipy.linalg.eig of the balanced matrix, LAPACK xGEEV).
    bound : ndarray of float, shape (N,)
        ``SAFETY * p(N) * eps * ||A_b||_F / s_i`` with ``A_b`` the balanced matrix (xGEBAL
        'B', exactly what numpy.linalg.eigvals and scipy run first: a permutation and
        power-of-two scaling, exact in floating point) and ``s_i = |y_i^H x_i|`` for unit
        right and left eigenvectors ``x_i``, ``y_i`` (the reciprocal condition number
        RCONDE of xGEEVX). Source: the LAPACK Users' Guide, 3rd ed., Sec. 4.8.1 (the
        computed eigenvalues are exact for ``A + E``, ``||E|| <= p(N) eps ||A||``;
        ``|lambda_i - lambda'_i| <= ||E|| / s_i``, Wilkinson's first-order bound,
        *The Algebraic Eigenvalue Problem* 1965, Sec. 2.9), ``p(N) = N``.

        Where that first-order bound exceeds half the distance to the nearest other
        eigenvalue (a cluster: the linearisation is not valid) the bound is replaced by
        the Bauer-Fike bound of the whole matrix, ``kappa_2(V) ||E||`` (Bauer & Fike 1960;
        rigorous for a diagonalisable matrix, whatever the size of the perturbation), and
        where ``V`` is numerically singular (a defective eigenvalue of multiplicity ``m``)
        by the Hoelder bound ``(||E|| ||A_b||^(m - 1))^(1/m)`` of a Jordan block (Moro,
        Burke & Overton, SIAM J. Matrix Anal. Appl. 18 (1997), Theorem 2.1, to first order).
    """
    A = np.asarray(A)
    N = A.shape[0]
    if N == 0:
        return np.zeros(0, complex), np.zeros(0)
    Ab, _ = scipy.linalg.matrix_balance(A, permute=True, scale=True)
    w, vl, vr = scipy.linalg.eig(Ab, left=True, right=True)
    norm = float(np.linalg.norm(Ab, "fro"))
    E = SAFETY * N * EPS * max(norm, np.finfo(float).tiny)
    vr = vr / np.linalg.norm(vr, axis=0)
    vl = vl / np.linalg.norm(vl, axis=0)
    s = np.abs(np.sum(vl.conj() * vr, axis=0))
    with np.errstate(divide="ignore"):
        bound = np.where(s > 0, E / np.maximum(s, np.finfo(float).tiny), np.inf)
    if err > 0:
        # the same eigenvalues in A's own coordinates: pair them up by nearness
        wa, al, ar = scipy.linalg.eig(A, left=True, right=True)
        sa = np.abs(np.sum((al / np.linalg.norm(al, axis=0)).conj()
                           * (ar / np.linalg.norm(ar, axis=0)), axis=0))
        j = np.argmin(np.abs(w[:, None] - wa[None, :]), axis=1)
        with np.errstate(divide="ignore"):
            bound = bound + np.where(sa[j] > 0, err / np.maximum(sa[j], np.finfo(float).tiny),
                                     np.inf)
    if N > 1:
        gap = np.abs(w[:, None] - w[None, :])
        np.fill_diagonal(gap, np.inf)
        gap = gap.min(axis=1)
        bad = ~(bound < gap / 2)
        if np.any(bad):
            kv = np.linalg.cond(vr)
            if np.isfinite(kv) and kv * EPS < 1e-2:
                bound[bad] = np.maximum(bound[bad], kv * E)
            else:
                # the cluster's size m: eigenvalues within twice the largest bound
                near = np.abs(w[:, None] - w[None, :]) <= 2 * np.max(bound[bad][np.isfinite(
                    bound[bad])], initial=E)
                m = int(np.max(np.sum(near, axis=1)))
                bound[bad] = (E * norm ** (m - 1)) ** (1.0 / m) if m > 1 else E
    return w, bound


def eig_tol(A, err: float = 0.0) -> float:
    """Largest :func:`eig_bounds` of ``A`` [unit of A]: the distance within which any
    backward-stable eigensolver's set of eigenvalues of ``A`` lies from the exact set.

    Parameters
    ----------
    A : array_like, shape (N, N)
    err : float, optional
        Error already in ``A``'s entries (2-norm), as in :func:`eig_bounds`.

    Returns
    -------
    float
        ``max_i bound_i`` (0 for an empty matrix).
    """
    _, b = eig_bounds(A, err)
    return float(np.max(b)) if b.size else 0.0


def companion(c) -> np.ndarray:
    """Companion matrix of the polynomial ``c`` (highest power first), the matrix whose
    eigenvalues numpy.roots returns (after trimming leading zeros).

    Parameters
    ----------
    c : array_like, shape (n + 1,)

    Returns
    -------
    ndarray, shape (n, n)
    """
    c = np.trim_zeros(np.asarray(c, dtype=complex if np.iscomplexobj(c) else float), "f")
    n = c.size - 1
    A = np.zeros((n, n), dtype=c.dtype)
    if n:
        A[0, :] = -c[1:] / c[0]
        A[1:, :-1] += np.eye(n - 1, dtype=c.dtype)
    return A


def roots_tol(c) -> float:
    """Round-off bound on the roots of the polynomial ``c`` as numpy.roots computes them
    (eigenvalues of :func:`companion`, Edelman & Murakami, Math. Comp. 64 (1995)): the
    :func:`eig_tol` of that matrix [unit of z].

    Parameters
    ----------
    c : array_like
        Coefficients, highest power first.

    Returns
    -------
    float
    """
    return eig_tol(companion(c))


def solve_tol(A) -> float:
    """Relative normwise bound on the round-off of ``x = solve(A, b)`` (LU with partial
    pivoting) [-].

    Parameters
    ----------
    A : array_like, shape (n, n)
        Non-singular.

    Returns
    -------
    float
        ``SAFETY * kappa_inf(A) * gamma(3n) || |L||U| ||_inf / ||A||_inf``: Higham
        Theorem 9.4 (``(A + dA) x' = b`` with ``|dA| <= gamma(3n) |L||U|``) into
        Theorem 7.2 (forward error <= condition x relative backward error), with the
        computed factors' own ``|L||U|`` (so the growth factor is measured, not assumed).
    """
    A = np.asarray(A, dtype=float)
    n = A.shape[0]
    _, L, Uf = scipy.linalg.lu(A)
    growth = np.linalg.norm(np.abs(L) @ np.abs(Uf), np.inf) / np.linalg.norm(A, np.inf)
    return SAFETY * float(np.linalg.cond(A, np.inf)) * gamma(3 * n) * float(growth)


def expm_tol(A) -> float:
    """Relative normwise bound on the round-off of ``scipy.linalg.expm(A)`` [-].

    Parameters
    ----------
    A : array_like, shape (n, n)

    Returns
    -------
    float
        ``SAFETY * n * eps * kappa`` with ``kappa = max(1, m^2 ||A|| / ||e^A||)`` and
        ``m = max_{0 <= s <= 1} ||e^(sA)||_2``: the Frechet derivative
        ``L(A, E) = int_0^1 e^((1-s)A) E e^(sA) ds`` is at most ``m^2 ||E||``, so ``kappa``
        bounds the exponential's relative condition number (Higham, *Functions of
        Matrices*, SIAM 2008, eq. (10.15) and Sec. 3.1); scaling and squaring (Al-Mohy &
        Higham 2009, scipy's algorithm) is forward stable to that conditioning, ``n eps``
        being its products' backward error. ``m`` is taken over ``s = j/k``,
        ``k >= ||A||``, as ``||e^(A/k)^j||`` times ``e^(||A||/k) <= e`` for the steps between
        (``||e^((s + h)A)|| <= ||e^(sA)|| e^(h ||A||)``): an upper bound, not a sample.
    """
    A = np.asarray(A, dtype=float)
    n = A.shape[0]
    a = float(np.linalg.norm(A, 2))
    k = max(16, int(math.ceil(a)))
    P1 = scipy.linalg.expm(A / k)
    P = np.eye(n)
    m = 1.0
    for _ in range(k):
        P = P1 @ P
        m = max(m, float(np.linalg.norm(P, 2)))
    m *= math.exp(a / k)
    eA = max(float(np.linalg.norm(P, 2)), np.finfo(float).tiny)
    kappa = max(1.0, m * m * a / eA)
    return SAFETY * n * EPS * kappa


def measured(worst: float, margin: float) -> float:
    """A tolerance measured rather than derived: the worst value seen times a margin.

    For quantities no closed bound covers (a fit's residual, a time-domain simulation of
    thousands of steps), the test states beside the call where ``worst`` was measured (the
    command, the CPU or BLAS kernels tried) and why ``margin`` is enough.

    Parameters
    ----------
    worst : float
        The largest deviation measured [unit of the quantity].
    margin : float
        Factor over it (>= 1).

    Returns
    -------
    float
        ``worst * margin``.

    Raises
    ------
    ValueError
        When ``margin < 1``.
    """
    if margin < 1.0:
        raise ValueError("a margin below 1 is not a margin")
    return float(worst) * float(margin)


def power_bound(A, steps: int) -> float:
    """``max_{0 <= k <= steps} ||A^k||_2`` [-], computed by multiplying out (exact up to a
    relative round-off of ``steps * gamma(N)``, negligible beside the factor it gives).

    Parameters
    ----------
    A : array_like, shape (N, N)
        A one-step map.
    steps : int
        Number of steps (>= 0).

    Returns
    -------
    float
        The largest amplification of a perturbation over at most ``steps`` steps.
    """
    A = np.asarray(A)
    P = np.eye(A.shape[0], dtype=A.dtype)
    worst = 1.0
    # the powers in blocks, each block's 2-norms in one batched SVD: the same products and
    # the same LAPACK singular values as one norm per power (numpy's norm(P, 2) is the
    # largest of svd(P, compute_uv=False)), without ~0.1 ms of Python per power
    left = int(steps)
    while left > 0:
        block = np.empty((min(left, 4096),) + A.shape, dtype=A.dtype)
        for i in range(block.shape[0]):
            P = A @ P
            block[i] = P
        worst = max(worst, float(np.linalg.svd(block, compute_uv=False)[:, 0].max()))
        left -= block.shape[0]
    return worst


def recurrence_tol(A, steps: int, scale: float, ops: int | None = None) -> float:
    """Absolute bound on the round-off of ``x[k+1] = A x[k]`` iterated ``steps`` times,
    for states of size at most ``scale`` [unit of x].

    Parameters
    ----------
    A : array_like, shape (N, N)
        The exact one-step map the computation implements (in whatever form: a compiled
        kernel, a matrix product).
    steps : int
        Number of steps.
    scale : float
        ``max_k ||x[k]||`` (the largest state along the run).
    ops : int, optional
        Roundings per state entry and step; default ``N + 2`` (one row of ``A`` as an
        inner product, Higham eq. (3.4), plus the update's own add and store; a kernel
        that computes a row by fewer operations is covered).

    Returns
    -------
    float
        ``SAFETY * steps * P * gamma(ops) * ||A||_2 * scale`` with
        ``P = max_k ||A^k||`` (:func:`power_bound`): the error made at step ``k`` is at
        most ``gamma(ops) ||A|| ||x[k]||`` and is carried to the end by ``A^(steps-k)``
        (Higham Sec. 18 on powers of matrices, first order).
    """
    A = np.asarray(A)
    N = A.shape[0]
    ops = N + 2 if ops is None else int(ops)
    return (SAFETY * steps * power_bound(A, steps) * gamma(ops)
            * float(np.linalg.norm(A, 2)) * float(scale))


#: Brent's tolerances hapsim passes to scipy.optimize.brentq for the angle ``theta`` of a
#: pole on the unit circle (hapsim.analysis.ths, its matrix loop): ``xtol + rtol * pi`` [rad].
BRENT_THETA = 1e-15 + 1e-14 * math.pi


def crossing_tol(f, x: float, dy: float, h_rel: float = 1e-4) -> float:
    """Bound on the error of a computed crossing ``x`` of a level by ``f`` [unit of x].

    Parameters
    ----------
    f : callable
        The function whose level crossing ``x`` is (e.g. the spectral radius as a function
        of the stiffness, crossing 1 at the stiffness limit).
    x : float
        The crossing.
    dy : float
        How well ``f`` near ``x`` is known to the method that found ``x`` (its round-off
        plus the root finder's tolerance, mapped to ``f``'s unit).
    h_rel : float, optional
        Relative step of the centred difference that measures ``f'(x)``; its error is
        ``O(h^2 f''')``, second order, and it only scales the bound.

    Returns
    -------
    float
        ``dy / |f'(x)|``: first-order inverse error analysis of a root (Higham Sec. 1.6;
        a simple crossing, ``f'(x) != 0``).
    """
    h = h_rel * abs(x) if x != 0 else h_rel
    slope = abs(f(x + h) - f(x - h)) / (2 * h)
    return float(dy) / slope if slope > 0 else math.inf
