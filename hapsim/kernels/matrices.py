"""The matrices of a link network, for the integrators and the analysis: numpy and scipy
only, no numba.

:func:`laplacians` (stiffness and damping Laplacians) and :func:`exact_matrices` (the exact
scheme's ``Phi``, ``Gam``, ``Psi``: :mod:`hapsim.kernels.schemes`'s notes, where they are
re-exported). They live apart from the compiled kernels so that a process that only
analyses a scene (``hapsim check``: :mod:`hapsim.analysis.virtual_network`) does not import
numba (a third of a second of CPU) to build them.
"""

from __future__ import annotations

import numpy as np

__all__ = ["laplacians", "exact_matrices"]


def laplacians(n_masses: int, i1, i2, k, b):
    """Stiffness and damping Laplacians of a link network.

    Parameters
    ----------
    n_masses : int
        Number of points.
    i1, i2 : array_like of int, shape (L,)
        Ends of each link.
    k : array_like, shape (L,)
        Stiffness K [N/m].
    b : array_like, shape (L,)
        Damping B [N s/m].

    Returns
    -------
    LK, LB : ndarray, shape (n_masses, n_masses)
        ``F = -LK x - LB v`` is the force on every point [N] (link law, docs/design.md,
        'The scheme').
    """
    LK = np.zeros((n_masses, n_masses))
    LB = np.zeros((n_masses, n_masses))
    for a, c, kk, bb in zip(np.asarray(i1), np.asarray(i2), np.asarray(k), np.asarray(b)):
        for L, g in ((LK, kk), (LB, bb)):
            L[a, a] += g
            L[c, c] += g
            L[a, c] -= g
            L[c, a] -= g
    return LK, LB


def exact_matrices(n_masses: int, mobile, masses, fixed, i1, i2, k, b, T: float):
    """``Phi``, ``Gam``, ``Psi`` of the exact scheme (module docstring).

    Parameters
    ----------
    n_masses : int
        Number of points.
    mobile : array_like of int, shape (N,)
        Moving masses.
    masses : array_like, shape (N,)
        Their inertia [kg], > 0.
    fixed : array_like of int, shape (n_fixed,)
        Grounds and port.
    i1, i2, k, b : array_like, shape (L,)
        Linear links: ends, K [N/m], B [N s/m].
    T : float
        Period [s].

    Returns
    -------
    phi : ndarray, shape (2N, 2N)
    gam, psi : ndarray, shape (2N, n_fixed)

    Notes
    -----
    Continuous model ``M x'' = -LK_mm x - LB_mm x' - LK_mf u - LB_mf u'`` with ``u`` the
    fixed positions. ``expm([[A, Bu], [0, 0]] T) = [[Phi, Gam], [0, I]]`` (Van Loan, "Computing
    integrals involving the matrix exponential", IEEE TAC 23, 1978); ``Psi = Phi[:, N:]
    (-M^-1 LB_mf)`` is the velocity jump ``-M^-1 LB_mf du`` at the start of the period
    carried to its end.
    """
    from scipy.linalg import expm

    mobile = np.asarray(mobile, dtype=np.int64)
    fixed = np.asarray(fixed, dtype=np.int64)
    N, nf = mobile.size, fixed.size
    LK, LB = laplacians(n_masses, i1, i2, k, b)
    Minv = 1.0 / np.asarray(masses, dtype=float)
    A = np.zeros((2 * N, 2 * N))
    A[:N, N:] = np.eye(N)
    A[N:, :N] = -Minv[:, None] * LK[np.ix_(mobile, mobile)]
    A[N:, N:] = -Minv[:, None] * LB[np.ix_(mobile, mobile)]
    Bu = np.zeros((2 * N, nf))
    Bu[N:, :] = -Minv[:, None] * LK[np.ix_(mobile, fixed)]
    aug = np.zeros((2 * N + nf, 2 * N + nf))
    aug[:2 * N, :2 * N] = A
    aug[:2 * N, 2 * N:] = Bu
    E = expm(aug * T)
    phi = np.ascontiguousarray(E[:2 * N, :2 * N])
    gam = np.ascontiguousarray(E[:2 * N, 2 * N:])
    jump = -Minv[:, None] * LB[np.ix_(mobile, fixed)]
    psi = np.ascontiguousarray(phi[:, N:] @ jump) if N else np.zeros((0, nf))
    return phi, gam, psi
