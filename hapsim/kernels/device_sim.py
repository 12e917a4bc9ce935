"""Output simulation of the device model ``m x'' + b0 x' = u - Coulomb`` for identification.

One kernel, :func:`simulate_device`, on plain arrays and floats (SI units): the position
samples a 1-DoF device would report for a given sequence of *applied* forces, for the two
holds of DESIGN.md Sec. 4:

``zoh`` (hold 0)
    The force is held over each period and the motion integrated exactly (closed form of
    the matrix exponential of the 2x2 system, variation of constants), with Coulomb
    friction as a held force ``-fc sign(v)``: ``fc_pos`` while ``v > 0``, ``fc_neg`` while
    ``v < 0``; from rest the force must exceed the friction in its direction to move; a
    velocity that would change sign within the period while the force cannot overcome the
    friction sticks (``v = 0``). This is the same first-order friction model as the mock
    device (:class:`hapsim.daemon.mock.MockPhysics`), written again here from its
    description.
``ideal`` (hold 1)
    Florens, Voda & Urma eq. (4): ``x[n+1] = (1 + a) x[n] - a x[n-1] + T^2/m psi u[n]``,
    ``a = e^(-b0 T/m)``, ``psi = (1 - a)/(b0 T/m)``; no Coulomb friction.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_jit = nb.njit(cache=True, nogil=True)


@_jit
def _psi_phi1(y):
    """``(1 - e^-y)/y`` and ``(e^-y - 1 + y)/y^2``, by series for small ``y``."""
    if abs(y) < 1e-2:
        psi = 0.0
        phi1 = 0.0
        term = 1.0
        for j in range(30):
            psi += term / (j + 1)
            phi1 += term / ((j + 1) * (j + 2))
            term *= -y / (j + 1)
        return psi, phi1
    em1 = math.expm1(-y)
    return -em1 / y, (em1 + y) / (y * y)


@_jit
def simulate_device(u, mass, friction, fc_pos, fc_neg, seg_len, xs, vs, period, hold, out):
    """Positions of the device model driven by the applied forces ``u``.

    Parameters
    ----------
    u : ndarray of float64, shape (n,)
        Force applied (held) over ``[kT, (k+1)T)`` [N].
    mass : float
        Moving mass m [kg], > 0.
    friction : float
        Viscous friction b0 [N s/m], >= 0 (a negative value is integrated as given).
    fc_pos, fc_neg : float
        Coulomb friction [N] while moving in the + and - direction (zoh only).
    seg_len : int > 0
        The record is simulated in segments of this many samples (multiple shooting:
        H. G. Bock & K. J. Plitt, IFAC 1984), segment ``j`` starting at sample
        ``j seg_len`` from position ``xs[j]`` [m] and velocity ``vs[j]`` [m/s].
    xs, vs : ndarray of float64, shape (ceil(n / seg_len),)
        Segment initial states.
    period : float
        Sample period T [s].
    hold : int
        0: zero-order hold (exact), 1: the paper's idealised sampled image.
    out : ndarray of float64, shape (n,)
        Filled with ``x[k]`` [m], the position at sample ``k`` (before ``u[k]`` acts).
    """
    n = u.shape[0]
    T = period
    m = mass
    y = friction * T / m
    a = math.exp(-y)
    psi, phi1 = _psi_phi1(y)
    cxv = T * psi
    cxu = T * T / m * phi1
    cvu = T / m * psi
    cu = T * T / m * psi
    seg = seg_len
    x = 0.0
    v = 0.0
    xp = 0.0
    for k in range(n):
        if k % seg == 0:
            j = k // seg
            x = xs[j]
            v = vs[j]
            xp = x - v * T
        out[k] = x
        f = u[k]
        if hold == 0:
            fc = 0.0
            if v > 0.0:
                fc = -fc_pos
            elif v < 0.0:
                fc = fc_neg
            elif f > fc_pos:
                fc = -fc_pos
            elif f < -fc_neg:
                fc = fc_neg
            else:
                continue                    # stuck: the force cannot break it loose
            ft = f + fc
            vn = a * v + cvu * ft
            xn = x + cxv * v + cxu * ft
            if v != 0.0 and vn * v < 0.0:
                lim = fc_pos if v > 0.0 else fc_neg
                if abs(f) <= lim:
                    vn = 0.0
            x = xn
            v = vn
        else:
            xn = (1.0 + a) * x - a * xp + cu * f
            xp = x
            x = xn


