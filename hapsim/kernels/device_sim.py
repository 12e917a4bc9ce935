"""Output simulation of the device model ``m x'' + b0 x' = u - Coulomb`` for identification.

Kernels on plain arrays and floats (SI units): :func:`simulate_device`, the position
samples a 1-DoF device would report for a given sequence of *applied* forces, stretch by
stretch, :func:`stretch_basis`, the responses its linear part is a combination of, and
:func:`stretch_projection`, the device fit's variable projection on that basis (the
residual once the stretch states and Coulomb frictions are solved); for the two holds of
docs/design.md, 'The timing convention':

``zoh`` (hold 0)
    The force is held over each period and the motion integrated exactly (closed form of
    the matrix exponential of the 2x2 system, variation of constants), with Coulomb
    friction as a held force ``-fc sign(v)``: ``fc_pos`` while ``v > 0``, ``fc_neg`` while
    ``v < 0``; from rest the force must exceed the friction in its direction to move; a
    velocity that would change sign within the period while the force cannot overcome the
    friction sticks (``v = 0``). This is the same first-order friction model as the mock
    device (:class:`hapsim.emulated.mock.MockPhysics`), written again here from its
    description.
``zoh`` with a sub-sample delay ``frac`` (the split hold, :mod:`hapsim.analysis.subsample`)
    Over ``[kT, (k+1)T)`` the force applied before, ``u[k-1]``, holds for ``frac T``, then
    ``u[k]`` for ``(1 - frac) T``: each piece integrated exactly, Coulomb friction per
    piece, as the mock's :meth:`hapsim.device_model.MockPhysics._advance_split` does
    (``u[-1]`` is 0). ``frac = 0`` is the plain hold, bit for bit.
``ideal`` (hold 1)
    Florens, Voda & Urma eq. (4): ``x[n+1] = (1 + a) x[n] - a x[n-1] + T^2/m psi u[n]``,
    ``a = e^(-b0 T/m)``, ``psi = (1 - a)/(b0 T/m)``; no Coulomb friction.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_jit = nb.njit(cache=True, nogil=True)
#: The binary64 machine epsilon (numpy.finfo(float).eps).
_EPS = 2.220446049250313e-16


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
def _coefficients(m, friction, T):
    """Exact ZOH step ``x' = x + cxv v + cxu u``, ``v' = a v + cvu u`` and the idealised
    image's ``cu = T^2/m psi`` (see :func:`hapsim.emulated.mock.zoh_step_coefficients`)."""
    y = friction * T / m
    psi, phi1 = _psi_phi1(y)
    return math.exp(-y), T * psi, T * T / m * phi1, T / m * psi, T * T / m * psi


@_jit
def _zoh_piece(x, v, f, fc_pos, fc_neg, a, cxv, cxu, cvu):
    """One exact ZOH piece with Coulomb friction (module notes): the new ``(x, v)``."""
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
        return x, v                     # stuck: the force cannot break it loose
    ft = f + fc
    vn = a * v + cvu * ft
    xn = x + cxv * v + cxu * ft
    if v != 0.0 and vn * v < 0.0:
        lim = fc_pos if v > 0.0 else fc_neg
        if abs(f) <= lim:
            vn = 0.0
    return xn, vn


@_jit
def simulate_device(u, mass, friction, fc_pos, fc_neg, starts, ends, xs, vs, period, hold,
                    out, frac=0.0):
    """Positions of the device model driven by the applied forces ``u``, per stretch.

    Parameters
    ----------
    u : ndarray of float64, shape (n,)
        Force applied (held) over ``[kT, (k+1)T)`` [N].
    mass : float
        Moving mass m [kg], > 0.
    friction : float
        Viscous friction b0 [N s/m].
    fc_pos, fc_neg : float
        Coulomb friction [N] while moving in the + and - direction (zoh only).
    starts, ends : ndarray of int64, shape (s,)
        Stretch ``j`` covers samples ``starts[j] <= k < ends[j]`` and starts from position
        ``xs[j]`` [m] and velocity ``vs[j]`` [m/s] (multiple shooting: H. G. Bock &
        K. J. Plitt, IFAC 1984).
    xs, vs : ndarray of float64, shape (s,)
        Stretch initial states.
    period : float
        Sample period T [s].
    hold : int
        0: zero-order hold (exact), 1: the paper's idealised sampled image.
    out : ndarray of float64, shape (n,)
        Filled with ``x[k]`` [m] on the stretches' samples (untouched elsewhere).
    frac : float in [0, 1)
        Sub-sample part of the delay (zoh only): ``u[k-1]`` holds over the first
        ``frac T`` of period ``k`` (module notes).
    """
    T = period
    a, cxv, cxu, cvu, cu = _coefficients(mass, friction, T)
    a1, cxv1, cxu1, cvu1, _ = _coefficients(mass, friction, frac * T)
    a2, cxv2, cxu2, cvu2, _ = _coefficients(mass, friction, (1.0 - frac) * T)
    for j in range(starts.shape[0]):
        x = xs[j]
        v = vs[j]
        xp = x - v * T
        for k in range(starts[j], ends[j]):
            out[k] = x
            f = u[k]
            if hold == 0 and frac > 0.0:
                x, v = _zoh_piece(x, v, u[k - 1] if k >= 1 else 0.0, fc_pos, fc_neg,
                                  a1, cxv1, cxu1, cvu1)
                x, v = _zoh_piece(x, v, f, fc_pos, fc_neg, a2, cxv2, cxu2, cvu2)
            elif hold == 0:
                x, v = _zoh_piece(x, v, f, fc_pos, fc_neg, a, cxv, cxu, cvu)
            else:
                xn = (1.0 + a) * x - a * xp + cu * f
                xp = x
                x = xn


@_jit
def stretch_basis(u, starts, ends, mass, friction, period, hold, yu, g, c, frac=0.0):
    """Responses of the linear device model restarted at the start of each stretch.

    Within a stretch the device moves one way, so Coulomb friction is a constant force and
    the model is linear: the position is ``yu + x_s + v_s g + F_c c`` with ``yu`` the
    response to the applied forces from rest at 0, ``g`` the response to a unit initial
    velocity [m per m/s], ``c`` the response to a unit constant force [m/N] (zero initial
    state), each restarted at every stretch start.

    Parameters
    ----------
    u : ndarray of float64, shape (n,)
        Applied force per period [N].
    starts, ends : ndarray of int64, shape (s,)
        Stretch ``j`` covers samples ``starts[j] <= k < ends[j]``.
    mass, friction, period : float
        m [kg], b0 [N s/m], T [s].
    hold : int
        0 exact ZOH, 1 the idealised image (Florens et al. eq. (4)).
    yu, g, c : ndarray of float64, shape (n,)
        Filled on the stretches' samples (left untouched elsewhere).
    frac : float in [0, 1)
        Sub-sample part of the delay (zoh only, module notes): the applied forces'
        response ``yu`` takes ``u[k-1]`` over the first ``frac T`` of period ``k``; ``g``
        and ``c`` (no input switching) are the plain hold's.
    """
    T = period
    a, cxv, cxu, cvu, cu = _coefficients(mass, friction, T)
    a1, cxv1, cxu1, cvu1, _ = _coefficients(mass, friction, frac * T)
    a2, cxv2, cxu2, cvu2, _ = _coefficients(mass, friction, (1.0 - frac) * T)
    for j in range(starts.shape[0]):
        x1 = 0.0
        v1 = 0.0
        x2 = 0.0
        v2 = 1.0
        x3 = 0.0
        v3 = 0.0
        p1 = 0.0
        p2 = -T
        p3 = 0.0
        for k in range(starts[j], ends[j]):
            yu[k] = x1
            g[k] = x2
            c[k] = x3
            f = u[k]
            if hold == 0 and frac > 0.0:
                fp = u[k - 1] if k >= 1 else 0.0
                x1, v1 = x1 + cxv1 * v1 + cxu1 * fp, a1 * v1 + cvu1 * fp
                x1, v1 = x1 + cxv2 * v1 + cxu2 * f, a2 * v1 + cvu2 * f
                x2, v2 = x2 + cxv * v2, a * v2
                x3, v3 = x3 + cxv * v3 + cxu, a * v3 + cvu
            elif hold == 0:
                x1, v1 = x1 + cxv * v1 + cxu * f, a * v1 + cvu * f
                x2, v2 = x2 + cxv * v2, a * v2
                x3, v3 = x3 + cxv * v3 + cxu, a * v3 + cvu
            else:
                n1 = (1.0 + a) * x1 - a * p1 + cu * f
                p1 = x1
                x1 = n1
                n2 = (1.0 + a) * x2 - a * p2
                p2 = x2
                x2 = n2
                n3 = (1.0 + a) * x3 - a * p3 + cu
                p3 = x3
                x3 = n3


@_jit
def _stretch_fit(z, g, starts, ends, L, Sg, Sgg, det, out, cx, cv):
    """``z`` minus its least-squares fit by ``[1, g]`` on each stretch (compact rows).

    ``out`` [rows] gets the projection; ``cx``, ``cv`` [stretches] the fit's coefficients
    (the normal equations of the two columns, Cramer's rule; ``det`` nonzero).
    """
    o = 0
    for j in range(starts.shape[0]):
        n = ends[j] - starts[j]
        sz = 0.0
        sgz = 0.0
        for i in range(o, o + n):
            sz += z[i]
            sgz += g[i] * z[i]
        a = (Sgg[j] * sz - Sg[j] * sgz) / det[j]
        b = (L[j] * sgz - Sg[j] * sz) / det[j]
        cx[j] = a
        cv[j] = b
        for i in range(o, o + n):
            out[i] = z[i] - a - b * g[i]
        o += n


@_jit
def stretch_projection(u, starts, ends, dirs, mass, friction, period, hold, frac, coulomb,
                       xi, yu, g, c, r, phi, cx, cv):
    """The variable projection of the stretch model at ``(m, b0)``: the residual left when
    the stretch states (and, with ``coulomb``, the Coulomb frictions) are solved by linear
    least squares (G. H. Golub & V. Pereyra, SIAM J. Numer. Anal. 10(2), 1973).

    The positions on the stretches are ``yu + x_s + v_s g - fc+ c`` (moving +) or ``...
    + fc- c`` (moving -) (:func:`stretch_basis`). The stretch states are eliminated
    stretch by stretch (the projection on the orthogonal complement of ``[1, g]``); the
    two Coulomb columns, nonzero on disjoint stretches, stay orthogonal once projected, so
    their least squares is one quotient per column, a column whose norm is at most
    ``eps * rows`` times the larger one's taken as zero (``numpy.linalg.lstsq``'s default
    cut-off, ``rcond = eps max(M, N)``, on the singular values: these norms).

    Parameters
    ----------
    u : ndarray of float64, shape (n,)
        Applied force per period [N].
    starts, ends, dirs : ndarray of int64, shape (s,)
        The stretches (samples ``starts[j] <= k < ends[j]``) and their directions (+1, -1).
    mass, friction, period : float
        m [kg], b0 [N s/m], T [s].
    hold : int
        0 exact ZOH, 1 the idealised image.
    frac : float in [0, 1)
        Sub-sample part of the delay (:func:`stretch_basis`).
    coulomb : bool
        Fit the Coulomb frictions ``(fc+, fc-)`` too.
    xi : ndarray of float64, shape (rows,)
        The positions on the stretches [m], stretch after stretch (``rows`` = the
        stretches' total length).
    yu, g, c : ndarray of float64, shape (n,)
        Work arrays, filled as :func:`stretch_basis` fills them.
    r : ndarray of float64, shape (rows,)
        Out: the residual, positions minus model [m].
    phi : ndarray of float64, shape (2,)
        Out: ``(fc+, fc-)`` [N] (zeros without ``coulomb``).
    cx, cv : ndarray of float64, shape (s,)
        Out: the stretches' initial positions [m] and velocities [m/s].

    Returns
    -------
    bool
        False when the basis is not finite on the stretches (``r`` etc. then undefined).
    """
    stretch_basis(u, starts, ends, mass, friction, period, hold, yu, g, c, frac)
    ns = starts.shape[0]
    rows = xi.shape[0]
    gi = np.empty(rows)
    t = np.empty(rows)
    ci = np.empty(rows)
    L = np.empty(ns)
    Sg = np.empty(ns)
    Sgg = np.empty(ns)
    det = np.empty(ns)
    o = 0
    for j in range(ns):
        sg = 0.0
        sgg = 0.0
        for k in range(starts[j], ends[j]):
            if not (math.isfinite(g[k]) and math.isfinite(yu[k]) and math.isfinite(c[k])):
                return False
            gi[o] = g[k]
            ci[o] = c[k]
            t[o] = xi[o] - yu[k]
            sg += g[k]
            sgg += g[k] * g[k]
            o += 1
        n = float(ends[j] - starts[j])
        L[j] = n
        Sg[j] = sg
        Sgg[j] = sgg
        d = n * sgg - sg * sg
        det[j] = d if abs(d) > 0.0 else 1.0
    phi[0] = 0.0
    phi[1] = 0.0
    if coulomb:
        pt = np.empty(rows)
        _stretch_fit(t, gi, starts, ends, L, Sg, Sgg, det, pt, cx, cv)
        # the Coulomb column of each stretch: -c moving + (fc+), +c moving - (fc-)
        col = np.empty(rows)
        o = 0
        for j in range(ns):
            s_ = -1.0 if dirs[j] > 0 else 1.0
            for i in range(o, o + ends[j] - starts[j]):
                col[i] = s_ * ci[i]
            o += ends[j] - starts[j]
        pc = np.empty(rows)
        _stretch_fit(col, gi, starts, ends, L, Sg, Sgg, det, pc, cx, cv)
        ss = np.zeros(2)
        sd = np.zeros(2)
        o = 0
        for j in range(ns):
            w = 0 if dirs[j] > 0 else 1
            for i in range(o, o + ends[j] - starts[j]):
                ss[w] += pc[i] * pc[i]
                sd[w] += pc[i] * pt[i]
            o += ends[j] - starts[j]
        top = math.sqrt(max(ss[0], ss[1]))
        cut = _EPS * rows * top
        for w in range(2):
            if ss[w] > 0.0 and math.sqrt(ss[w]) > cut:
                phi[w] = sd[w] / ss[w]
        o = 0
        for j in range(ns):
            p_ = phi[0] if dirs[j] > 0 else phi[1]
            for i in range(o, o + ends[j] - starts[j]):
                t[i] = t[i] - col[i] * p_
            o += ends[j] - starts[j]
    _stretch_fit(t, gi, starts, ends, L, Sg, Sgg, det, r, cx, cv)
    return True


@nb.njit(cache=True, nogil=True, error_model="numpy")
def refine_jacobian(u, masses, X, dX, coulomb, starts, ends, period, hold, frac, idx, xi, f0,
                    cx, cv, out, data):
    """The device fit refinement's forward-difference Jacobian in one call: what
    :meth:`hapsim.analysis.device_fit_search._BlockDifference.data` computes on the
    refinement's residual ``simulate_device(...)[idx] - xi``, the same operations in the
    same order (bit for bit; division by zero as numpy's, not an exception).

    Parameters
    ----------
    u : ndarray, shape (n,)
        Applied force [N].
    masses : ndarray, shape (w,)
        ``exp(X[g, 0])`` per group, as Python's ``math.exp`` gives it [kg].
    X : ndarray, shape (w, k + 2 ns)
        The stepped points, one per column group (``w = k + 2``: the ``k`` shared
        parameters ``(ln m, b0[, fc+, fc-])`` alone, then every stretch's initial position
        at once, then every initial velocity).
    dX : ndarray, shape (w, k + 2 ns)
        ``X - x0``: the steps as represented.
    coulomb : bool
        ``k == 4`` (the frictions are parameters 2 and 3) or ``k == 2``.
    starts, ends : ndarray of int64, shape (ns,)
    period, hold, frac
        As :func:`simulate_device`.
    idx : ndarray of int, shape (m,)
        The stretches' rows of the record.
    xi : ndarray, shape (m,)
        The positions there [m].
    f0 : ndarray, shape (m,)
        The residual at ``x0`` [m].
    cx, cv : ndarray of int, shape (m,)
        Each row's initial-position and initial-velocity columns (``k + sid``,
        ``k + ns + sid``).
    out : ndarray, shape (n,)
        Scratch for the positions.
    data : ndarray, shape (m, w)
        Written: ``(f(X[g]) - f0) / dX[g, column]`` in column ``g``.
    """
    w = X.shape[0]
    k = w - 2
    ns = starts.shape[0]
    for g in range(w):
        fp = X[g, 2] if coulomb else 0.0
        fn = X[g, 3] if coulomb else 0.0
        simulate_device(u, masses[g], X[g, 1], fp, fn, starts, ends,
                        np.ascontiguousarray(X[g, k:k + ns]),
                        np.ascontiguousarray(X[g, k + ns:k + 2 * ns]), period, hold, out, frac)
        for r in range(idx.shape[0]):
            if g < k:
                col = g
            elif g == k:
                col = cx[r]
            else:
                col = cv[r]
            data[r, g] = ((out[idx[r]] - xi[r]) - f0[r]) / dX[g, col]
