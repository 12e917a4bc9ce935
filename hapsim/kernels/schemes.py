"""Alternative integrators of the virtual masses: symplectic Euler and exact (matched) ZOH.

The CORDIS centred difference (:mod:`hapsim.kernels.cordis`) stays the default. This module
adds two schemes a scene selects with ``integrator:`` (``symplectic_euler``, ``exact``).
Same state layout and calling convention as the CORDIS kernels (struct of arrays, SI units;
``kernel(n, *args, rec, out, row0)``), so :class:`hapsim.engine.Engine` drives every scheme
alike: ``x``/``xp`` hold the positions at samples ``n`` and ``n - 1`` [m], ``f`` the forces
computed from sample ``n`` [N] (``f[port]`` is what the device gets), ``mobile``/``t2m`` the
moving masses and ``T^2/m`` [s^2/kg], ``fixed`` the grounds and the port. Link arrays:
``i1``, ``i2`` (int64), ``k`` [N/m], ``z = B / T`` [N/m] and, for contacts, ``thr`` [m].

Schemes (one oscillator ``m x'' = -K x - B x'``; ``kappa = K T^2/m``, ``beta = B T/m``)
------------------------------------------------------------------------------------
centred (reference, :mod:`hapsim.kernels.cordis`)
    ``x[n+1] = 2x[n] - x[n-1] + T^2 F[n]/m``, damping on the backward difference.
    Characteristic ``z^2 + (kappa + beta - 2) z + (1 - beta) = 0``; Jury's criterion
    (Jury, *Theory and Application of the z-Transform Method*, 1964; for a quadratic
    ``z^2 + a1 z + a0``: ``|a0| < 1``, ``1 + a1 + a0 > 0``, ``1 - a1 + a0 > 0``) gives
    ``0 < kappa < 4 - 2 beta`` and ``beta < 2``, i.e. **K < 4 m/T^2 - 2 B/T** and
    **B < 2 m/T** (``B = 0``: Florens-Voda-Urma eq. (2) at ``T sqrt(K/m) = pi``).

symplectic_euler (:func:`run_symplectic_euler`)
    Explicit velocity state ``v``; the damping of each link on a mass's *own* velocity is
    implicit (diagonal), the neighbours' velocities explicit (a Jacobi split):
    ``(m + T c_i) v_i[n+1] = m v_i[n] + T (F_spring,i[n] + sum_links B v_j[n])``, i.e.
    ``v_i[n+1] = v_i[n] + T F_i[n] / (m + T c_i)`` with ``F_i[n]`` the fully explicit force,
    ``c_i`` the sum of the damping B of the links acting on mass ``i`` (engaged contacts
    included), then ``x[n+1] = x[n] + T v[n+1]``. With the damping fully explicit this
    is algebraically the centred scheme (``v[n] = (x[n] - x[n-1]) / T``); the real
    differences are (1) the own damping uses the forward difference, so the
    characteristic becomes ``(1 + beta) z^2 + (kappa - beta - 2) z + 1 = 0`` and Jury gives
    **K < 4 m/T^2 + 2 B/T** with **no bound on B** (damping widens the stable range
    instead of narrowing it; a stiff damper no longer explodes the scheme), and (2) the
    velocity is a state, not the difference of two nearly equal positions, so the damping
    force does not lose ``log10(|x| / (|v| T))`` digits at high rates. Same cost class as
    the centred scheme (one more divide per mass, one more array). Undamped network:
    ``T^2 lambda_max(M^-1 K) < 4``, as centred (the position sequences coincide).

exact (:func:`run_exact`)
    Matched (zero-order-hold) discretisation of the linear network: the port and grounds
    are held inputs ``u`` (piecewise constant positions), the state ``s = [x_m, v_m]`` of
    the moving masses advances by ``s[n+1] = Phi s[n] + Gam u[n] + Psi (u[n] - u[n-1])``
    with ``Phi = expm(A T)``, ``Gam = int_0^T expm(A t) dt Bu`` (both from one augmented
    matrix exponential, Van Loan 1978) and ``Psi`` the momentum impulse ``-M^-1 B_mf du``
    a damper passes on when the held port position jumps, carried over the period. It is
    the exact solution of the continuous network for a staircase port path, so its poles
    are ``exp(lambda T)`` of the continuous eigenvalues: **stable at every rate and
    stiffness for a passive network** (all ``Re lambda <= 0``); the only limit is the
    continuous one (negative damping). Dense cost O(N^2) per sample (N moving masses);
    linear links only (contacts switch the network: refused by the scene/engine).

No kernel allocates; everything is compiled once (``cache=True``). The matrix set-up
(:func:`exact_matrices`, in :mod:`hapsim.kernels.matrices`, re-exported here) uses
numpy/scipy at construction, never in the step. Nothing here
imports from the API layer (docs/design.md, rule 3).
"""

from __future__ import annotations

import numba as nb
import numpy as np

# the matrix set-up is numpy/scipy only: kept in its own module so that the analysis
# (hapsim check) builds the network's Laplacians without loading numba
from hapsim.kernels.matrices import exact_matrices, laplacians

__all__ = ["INTEGRATORS", "run_symplectic_euler", "run_exact", "exact_matrices",
           "laplacians", "build"]

#: Integrators a scene may select (the first is the default).
INTEGRATORS = ("centred", "symplectic_euler", "exact")

_jit = nb.njit(cache=True, nogil=True, boundscheck=False)
_jit_inline = nb.njit(cache=True, nogil=True, boundscheck=False, inline="always")
_U = nb.uint64   # unsigned indices: no negative-index wraparound code in the inner loops


@_jit_inline
def _se_spring_dampers(x, v, f, c, i1, i2, k, z, T):
    for j in range(i1.size):
        a = _U(i1[j])
        b = _U(i2[j])
        bb = z[j] * T
        force = k[j] * (x[a] - x[b]) + bb * (v[a] - v[b])
        f[a] -= force
        f[b] += force
        c[a] += bb
        c[b] += bb


@_jit_inline
def _se_contacts(x, v, f, c, i1, i2, k, z, thr, T):
    for j in range(i1.size):
        a = _U(i1[j])
        b = _U(i2[j])
        d = x[a] - x[b]
        if -d < thr[j]:
            bb = z[j] * T
            force = k[j] * (d + thr[j]) + bb * (v[a] - v[b])
            f[a] -= force
            f[b] += force
            c[a] += bb
            c[b] += bb


@_jit
def run_symplectic_euler(n, x, xp, f, mobile, t2m, fixed, v, c, T,
                         sd_i1, sd_i2, sd_k, sd_z, c_i1, c_i2, c_k, c_z, c_thr,
                         rec, out, row0):
    """Advance ``n`` samples with symplectic Euler, own damping implicit (module docstring).

    Parameters
    ----------
    n : int
        Samples to advance, >= 0.
    x, xp, f : ndarray, shape (n_masses,)
        Positions at n and n - 1 [m], forces of sample n [N] (updated in place).
    mobile : ndarray of int64, shape (n_mobile,)
        Indices of moving masses.
    t2m : ndarray, shape (n_mobile,)
        ``T^2 / m`` [s^2/kg].
    fixed : ndarray of int64, shape (n_fixed,)
        Grounds and port; their velocity is the backward difference ``(x - xp) / T``.
    v : ndarray, shape (n_masses,)
        Velocity state [m/s] (mobile entries are the scheme's state).
    c : ndarray, shape (n_masses,)
        Work array: sum of the damping B [N s/m] acting on each mass this sample.
    T : float
        Period [s].
    sd_i1, sd_i2, sd_k, sd_z : ndarray
        Spring-dampers (may be empty): int64 ends, K [N/m], B/T [N/m].
    c_i1, c_i2, c_k, c_z, c_thr : ndarray
        Contacts (may be empty), as above plus the threshold [m].
    rec, out, row0
        Recording, as :func:`hapsim.kernels.cordis.run_sd`.

    Notes
    -----
    ``(m + T c_i) v_i[n+1] = m v_i[n] + T (F_i[n] + c_i v_i[n])`` with ``F_i[n]`` the explicit
    link force, then ``x_i[n+1] = x_i[n] + T v_i[n+1]``. Limit (one oscillator, Jury):
    ``K < 4 m / T^2 + 2 B / T``.
    """
    for s in range(n):
        for j in range(fixed.size):
            i = fixed[j]
            v[i] = (x[i] - xp[i]) / T
        for i in range(f.size):
            f[i] = 0.0
            c[i] = 0.0
        _se_spring_dampers(x, v, f, c, sd_i1, sd_i2, sd_k, sd_z, T)
        _se_contacts(x, v, f, c, c_i1, c_i2, c_k, c_z, c_thr, T)
        for j in range(mobile.size):
            i = _U(mobile[j])
            h = t2m[j] / T  # T / m
            vn = v[i] + h * f[i] / (1.0 + h * c[i])
            xp[i] = x[i]
            x[i] = x[i] + T * vn
            v[i] = vn
        for j in range(fixed.size):
            i = fixed[j]
            xp[i] = x[i]
        for r in range(rec.size):
            out[row0 + s, r] = x[rec[r]]


@_jit
def run_exact(n, x, xp, f, mobile, t2m, fixed, v, T, phi, gam, psi, snew, sold, uold,
              sd_i1, sd_i2, sd_k, sd_z, rec, out, row0):
    """Advance ``n`` samples with the exact ZOH state transition (module docstring).

    Parameters
    ----------
    n : int
        Samples to advance, >= 0.
    x, xp, f : ndarray, shape (n_masses,)
        Positions at n and n - 1 [m], forces of sample n [N] (updated in place).
    mobile : ndarray of int64, shape (N,)
        Indices of moving masses.
    t2m : ndarray, shape (N,)
        ``T^2 / m`` [s^2/kg] (unused by the update; kept for the common layout).
    fixed : ndarray of int64, shape (n_fixed,)
        Grounds and port (held inputs).
    v : ndarray, shape (n_masses,)
        Velocity state [m/s]; fixed entries are backward differences.
    T : float
        Period [s].
    phi : ndarray, shape (2N, 2N)
        ``expm(A T)`` on ``[x_m, v_m]``.
    gam : ndarray, shape (2N, n_fixed)
        Response to held fixed positions [-, 1/s].
    psi : ndarray, shape (2N, n_fixed)
        Response to a jump of the fixed positions through the dampers [-, 1/s].
    snew, sold : ndarray, shape (2N,)
        Work arrays (new and gathered old state).
    uold : ndarray, shape (2 n_fixed,)
        Work array (fixed positions and their jumps).
    sd_i1, sd_i2, sd_k, sd_z : ndarray
        Spring-dampers (for the force sent to the port): int64 ends, K [N/m], B/T [N/m].
    rec, out, row0
        Recording, as :func:`hapsim.kernels.cordis.run_sd`.
    """
    nm = mobile.size
    nf = fixed.size
    for s in range(n):
        for j in range(nf):
            i = fixed[j]
            v[i] = (x[i] - xp[i]) / T
        for i in range(f.size):
            f[i] = 0.0
        for j in range(sd_i1.size):
            a = sd_i1[j]
            b = sd_i2[j]
            force = sd_k[j] * (x[a] - x[b]) + sd_z[j] * T * (v[a] - v[b])
            f[a] -= force
            f[b] += force
        for j in range(nm):  # gather the state contiguously: the product then vectorises
            i = _U(mobile[j])
            sold[j] = x[i]
            sold[nm + j] = v[i]
        for j in range(nf):
            i = _U(fixed[j])
            uold[j] = x[i]
            uold[nf + j] = x[i] - xp[i]
        if nm >= 8:
            np.dot(phi, sold, snew)  # BLAS gemv into the work array (no allocation)
        else:                        # small: a plain loop beats the BLAS call overhead
            for r in range(2 * nm):
                acc = 0.0
                for j in range(2 * nm):
                    acc += phi[r, j] * sold[j]
                snew[r] = acc
        for r in range(2 * nm):
            acc = snew[r]
            for j in range(nf):
                acc += gam[r, j] * uold[j] + psi[r, j] * uold[nf + j]
            snew[r] = acc
        for j in range(nm):
            i = mobile[j]
            xp[i] = x[i]
            x[i] = snew[j]
            v[i] = snew[nm + j]
        for j in range(nf):
            i = fixed[j]
            xp[i] = x[i]
        for r in range(rec.size):
            out[row0 + s, r] = x[rec[r]]


_EMPTY_I = np.empty(0, dtype=np.int64)
_EMPTY_F = np.empty(0, dtype=np.float64)


def build(integrator: str, T: float, x, xp, f, mobile, t2m, fixed, sd=None, contact=None):
    """Kernel, argument tuple and named extras for a non-default integrator.

    Parameters
    ----------
    integrator : {"symplectic_euler", "exact"}
        Scheme.
    T : float
        Period [s].
    x, xp, f : ndarray, shape (n_masses,)
        State arrays of the engine (shared, updated in place by the kernel).
    mobile, t2m, fixed : ndarray
        As the CORDIS layout.
    sd : tuple of ndarray, optional
        ``(i1, i2, k, z)`` of the spring-dampers.
    contact : tuple of ndarray, optional
        ``(i1, i2, k, z, thr)`` of the contacts.

    Returns
    -------
    kernel : callable
        Called as ``kernel(n, *args, rec, out, row0)``.
    args : tuple
        Arrays and floats the kernel needs, in its argument order.
    extras : dict
        The scheme's own state and coefficients by name, in their argument order between
        ``fixed`` and the links: ``v``, ``c``, ``T`` (``symplectic_euler``); ``v``, ``T``,
        ``phi``, ``gam``, ``psi``, ``snew``, ``sold``, ``uold`` (``exact``). ``v`` is the
        velocity state [m/s]. The same objects as in ``args``.

    Raises
    ------
    ValueError
        Unknown integrator, or contacts with ``"exact"`` (the API layer reports it as a
        ConfigError naming the key before calling).
    """
    sd = sd if sd is not None else (_EMPTY_I, _EMPTY_I, _EMPTY_F, _EMPTY_F)
    contact = contact if contact is not None else (_EMPTY_I, _EMPTY_I, _EMPTY_F, _EMPTY_F,
                                                   _EMPTY_F)
    T = float(T)
    v = ((x - xp) / T).astype(np.float64)
    if integrator == "symplectic_euler":
        extras = {"v": v, "c": np.zeros_like(x), "T": T}
        return run_symplectic_euler, ((x, xp, f, mobile, t2m, fixed) + tuple(extras.values())
                                      + tuple(sd) + tuple(contact)), extras
    if integrator == "exact":
        if contact[0].size:
            raise ValueError("the exact integrator takes linear links only (no contacts)")
        masses = T * T / t2m if t2m.size else t2m
        phi, gam, psi = exact_matrices(x.size, mobile, masses, fixed, sd[0], sd[1], sd[2],
                                       np.asarray(sd[3]) * T, T)
        extras = {"v": v, "T": T, "phi": phi, "gam": gam, "psi": psi,
                  "snew": np.zeros(2 * mobile.size), "sold": np.zeros(2 * mobile.size),
                  "uold": np.zeros(2 * fixed.size)}
        return run_exact, ((x, xp, f, mobile, t2m, fixed) + tuple(extras.values())
                           + tuple(sd)), extras
    raise ValueError(f"unknown integrator {integrator!r}; valid: {', '.join(INTEGRATORS[1:])}")
