"""One sample period of a kinematic device's joint-space dynamics, compiled (the real-time
n-DoF mock's tick: :class:`hapsim.joint_device.LocalJointDeviceND`).

Quadratic kinematics about the operating point ``q0``: ``f(q0 + s) = f0 + J0 s + H(s, s)/2``,
``J(s) = J0 + H s``; Lagrange's equations of the joint inertia ``Mq``, joint friction
``Bq`` and a Cartesian point mass ``mh`` with damping ``bh`` at the handle (Khatib 1987)::

    (Mq + mh J^T J) s'' = tau - Bq s' - bh J^T J s' - mh J^T H(s', s')

with the torques ``tau`` held over the period; classical fourth-order Runge-Kutta. Plain
arrays and floats in SI units (rad, rad/s, N m, kg m^2); ``n <= 3`` axes (a Gaussian
elimination with partial pivoting solves the n x n system).
"""

from __future__ import annotations

import numba as nb

__all__ = ["joint_step"]

_jit = nb.njit(cache=True, nogil=True)


@_jit
def _accel(s, sd, tau, J0, H, Mq, Bq, mh, bh, out, J, A, b):
    n = s.size
    for i in range(n):
        for j in range(n):
            v = J0[i, j]
            for k in range(n):
                v += H[i, j, k] * s[k]
            J[i, j] = v
    # bias_i = H[i, j, k] sd_j sd_k ; rhs = tau - Bq sd - bh JtJ sd - mh J^T bias
    for r in range(n):
        acc = tau[r]
        for c in range(n):
            acc -= Bq[r, c] * sd[c]
        b[r] = acc
    for i in range(n):
        bias = 0.0
        Jsd = 0.0
        for j in range(n):
            Jsd += J[i, j] * sd[j]
            for k in range(n):
                bias += H[i, j, k] * sd[j] * sd[k]
        for r in range(n):
            b[r] -= J[i, r] * (bh * Jsd + mh * bias)
    for r in range(n):
        for c in range(n):
            jtj = 0.0
            for i in range(n):
                jtj += J[i, r] * J[i, c]
            A[r, c] = Mq[r, c] + mh * jtj
    # Gaussian elimination, partial pivoting
    for c in range(n):
        p = c
        for r in range(c + 1, n):
            if abs(A[r, c]) > abs(A[p, c]):
                p = r
        if p != c:
            for k in range(n):
                A[c, k], A[p, k] = A[p, k], A[c, k]
            b[c], b[p] = b[p], b[c]
        for r in range(c + 1, n):
            f = A[r, c] / A[c, c]
            for k in range(c, n):
                A[r, k] -= f * A[c, k]
            b[r] -= f * b[c]
    for r in range(n - 1, -1, -1):
        v = b[r]
        for k in range(r + 1, n):
            v -= A[r, k] * out[k]
        out[r] = v / A[r, r]


@_jit
def joint_step(s, sd, tau, J0, H, Mq, Bq, mh, bh, h, substeps, wv, wm):
    """Advance ``s``, ``sd`` in place over one period holding the joint torques ``tau``.

    Parameters
    ----------
    s, sd : ndarray, shape (n,)
        Joint displacement from ``q0`` [rad] and joint velocity [rad/s] (updated).
    tau : ndarray, shape (n,)
        Joint torques [N m], held over the period.
    J0 : ndarray, shape (n, n)
        Jacobian at ``q0`` [m/rad].
    H : ndarray, shape (n, n, n)
        ``d J[:, j] / d q_k`` [m/rad^2], symmetric in ``j, k``.
    Mq, Bq : ndarray, shape (n, n)
        Joint inertia [kg m^2] and friction [N m s/rad].
    mh, bh : float
        Hand mass [kg] and damping [N s/m] at the handle.
    h : float
        Runge-Kutta step [s] (the period over ``substeps``).
    substeps : int
    wv : ndarray, shape (10, n)
        Work space (no allocation per tick).
    wm : ndarray, shape (2, n, n)
        Work space.

    Returns
    -------
    None
    """
    n = s.size
    J = wm[0]
    A = wm[1]
    b, k1, k2, k3, k4, qt, vt, v2, v3 = (wv[0], wv[2], wv[3], wv[4], wv[5], wv[6], wv[7],
                                         wv[8], wv[9])
    for _ in range(substeps):
        _accel(s, sd, tau, J0, H, Mq, Bq, mh, bh, k1, J, A, b)
        for i in range(n):
            qt[i] = s[i] + 0.5 * h * sd[i]
            v2[i] = sd[i] + 0.5 * h * k1[i]
        _accel(qt, v2, tau, J0, H, Mq, Bq, mh, bh, k2, J, A, b)
        for i in range(n):
            qt[i] = s[i] + 0.5 * h * v2[i]
            v3[i] = sd[i] + 0.5 * h * k2[i]
        _accel(qt, v3, tau, J0, H, Mq, Bq, mh, bh, k3, J, A, b)
        for i in range(n):
            qt[i] = s[i] + h * v3[i]
            vt[i] = sd[i] + h * k3[i]
        _accel(qt, vt, tau, J0, H, Mq, Bq, mh, bh, k4, J, A, b)
        for i in range(n):
            s[i] += h / 6.0 * (sd[i] + 2.0 * v2[i] + 2.0 * v3[i] + vt[i])
            sd[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
