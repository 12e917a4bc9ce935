"""The variable projection of a sum of sampled modes, compiled: the residual and its
Jacobian in the modes' parameters, every stretch of a record in one call.

The model of one stretch of ``L`` samples, ``t = 0 .. L-1``: columns ``e^(-a t) cos(w t)``,
``e^(-a t) sin(w t)`` per damped pair (``kinds`` 0, parameters ``a, w``), ``p^t`` per real
pole (``kinds`` 1, parameter ``p``), and a constant column with ``offset``; the linear
coefficients ``c`` of each stretch are eliminated by least squares (its own initial
condition). :mod:`hapsim.analysis.identify` refines the poles with these (Levenberg-Marquardt
in ``scipy.optimize.least_squares``); its Python ``_solve`` is the residual's mathematics
on numpy (``tests/test_varpro_jacobian.py`` compares the two, and this Jacobian with the
complex step).

The least squares is taken through the thin SVD with ``numpy.linalg.lstsq``'s default
cut-off (singular values under ``eps * max(L, columns) * s_max`` dropped); the Jacobian
is Golub & Pereyra's ("The differentiation of pseudo-inverses and nonlinear least squares
problems whose variables separate", SIAM J. Numer. Anal. 10(2), 1973)::

    dr/dtheta_k = P_perp D_k c - (Phi^+)^T D_k^T r,     D_k = dPhi/dtheta_k
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["projected"]

_jit = nb.njit(cache=True, nogil=True)
#: The binary64 machine epsilon (numpy.finfo(float).eps).
_EPS = 2.220446049250313e-16


@_jit
def _columns(kinds, theta, L, offset):
    """The model's columns on one stretch of ``L`` samples, shape (L, columns), and
    whether every entry is finite."""
    ncol = 1 if offset else 0
    for q in kinds:
        ncol += 2 if q == 0 else 1
    phi = np.empty((L, ncol))
    i = 0
    j = 0
    for q in kinds:
        if q == 0:
            a = theta[i]
            w = theta[i + 1]
            for n in range(L):
                e = math.exp(-a * n)
                phi[n, j] = e * math.cos(w * n)
                phi[n, j + 1] = e * math.sin(w * n)
            i += 2
            j += 2
        else:
            p = theta[i]
            for n in range(L):
                phi[n, j] = p ** float(n)
            i += 1
            j += 1
    if offset:
        for n in range(L):
            phi[n, j] = 1.0
    ok = True
    for n in range(L):
        for k in range(ncol):
            if not math.isfinite(phi[n, k]):
                ok = False
    return phi, ok


@_jit
def _fit(phi, y):
    """Thin SVD of ``phi`` cut as ``numpy.linalg.lstsq(rcond=None)``: ``(U, S, Vt, keep,
    c, r)`` with the first ``keep`` singular triplets kept, ``c`` the least-squares
    coefficients and ``r = phi c - y`` (plain loops: small matrices, and one compiled
    form whatever the layouts)."""
    U, S, Vt = np.linalg.svd(phi, full_matrices=False)
    L, ncol = phi.shape
    cut = _EPS * max(L, ncol) * S[0]
    keep = 0
    for s in S:
        if s > cut:
            keep += 1
    uy = np.zeros(keep)
    for k in range(keep):
        acc = 0.0
        for n in range(L):
            acc += U[n, k] * y[n]
        uy[k] = acc / S[k]
    c = np.zeros(ncol)
    for j in range(ncol):
        acc = 0.0
        for k in range(keep):
            acc += Vt[k, j] * uy[k]
        c[j] = acc
    r = np.empty(L)
    for n in range(L):
        acc = 0.0
        for j in range(ncol):
            acc += phi[n, j] * c[j]
        r[n] = acc - y[n]
    return U, S, Vt, keep, c, r


@_jit
def projected(kinds, theta, y, starts, ends, offset, jacobian, out):
    """The projected residual ``Phi c - y`` of every stretch, one after the other, or its
    Jacobian in ``theta`` in closed form (module notes): one kernel, compiled once.

    Parameters
    ----------
    kinds : ndarray of int64, shape (modes,)
        0 a damped pair (two parameters ``a, w``), 1 a real pole (one, ``p``).
    theta : ndarray of float64, shape (p,)
        The modes' parameters in order.
    y : ndarray of float64, shape (n,)
        The record, its stretches one after the other.
    starts, ends : ndarray of int64, shape (stretches,)
        Each stretch's samples ``starts[j] <= i < ends[j]``.
    offset : bool
        A constant column in every stretch.
    jacobian : bool
        False: the residual, into ``out[:, 0]``; True: the Jacobian, into ``out``.
    out : ndarray of float64, shape (n, 1) or (n, p)
        Out.

    Returns
    -------
    bool
        False where a column or the record is not finite (``out`` then undefined): what
        ``numpy.linalg.lstsq`` refuses.
    """
    p = theta.size
    for s in range(starts.size):
        a, b = starts[s], ends[s]
        L = b - a
        yb = y[a:b]
        phi, ok = _columns(kinds, theta, L, offset)
        if not ok:
            return False
        for v in yb:
            if not math.isfinite(v):
                return False
        U, S, Vt, keep, c, r = _fit(phi, yb)
        if not jacobian:
            for n in range(L):
                out[a + n, 0] = r[n]
            continue
        ncol = phi.shape[1]
        Dc = np.zeros((L, p))            # D_k c, column k
        Dr = np.zeros((ncol, p))         # D_k^T r, column k
        i = 0
        j = 0
        for q in kinds:
            if q == 0:
                for n in range(L):
                    C = phi[n, j]
                    Sn = phi[n, j + 1]
                    da_c = -n * C            # d/da of the cos and sin columns
                    da_s = -n * Sn
                    dw_c = -n * Sn           # d/dw
                    dw_s = n * C
                    Dc[n, i] = c[j] * da_c + c[j + 1] * da_s
                    Dc[n, i + 1] = c[j] * dw_c + c[j + 1] * dw_s
                    Dr[j, i] += da_c * r[n]
                    Dr[j + 1, i] += da_s * r[n]
                    Dr[j, i + 1] += dw_c * r[n]
                    Dr[j + 1, i + 1] += dw_s * r[n]
                i += 2
                j += 2
            else:
                pp = theta[i]
                for n in range(1, L):
                    d = n * pp ** float(n - 1) if pp != 0.0 else 0.0
                    Dc[n, i] = c[j] * d
                    Dr[j, i] += d * r[n]
                i += 1
                j += 1
        # Dc - U (U' Dc) - U (S^-1 Vt Dr): the projector's complement and the
        # pseudo-inverse's transpose
        W = np.zeros((keep, p))
        for k in range(keep):
            for m in range(p):
                acc = 0.0
                for n in range(L):
                    acc += U[n, k] * Dc[n, m]
                acc2 = 0.0
                for jj in range(ncol):
                    acc2 += Vt[k, jj] * Dr[jj, m]
                W[k, m] = acc + acc2 / S[k]
        for n in range(L):
            for m in range(p):
                acc = 0.0
                for k in range(keep):
                    acc += U[n, k] * W[k, m]
                out[a + n, m] = Dc[n, m] - acc
    return True
