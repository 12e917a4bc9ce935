"""CORDIS-ANIMA kernels: centred-difference masses and visco-elastic links.

State layout (struct of arrays, all float64 unless stated):

``x`` (n_masses,)
    Positions at sample n [m].
``xp`` (n_masses,)
    Positions at sample n - 1 [m].
``f`` (n_masses,)
    Force accumulator of the current sample [N]; after a step it holds the forces
    computed from ``x[n]``, ``xp[n]`` (so ``f[port]`` is the force sent to the device).
``mobile`` (n_mobile,) int64, ``t2m`` (n_mobile,)
    Indices of the masses that move and their ``T^2 / m`` [s^2/kg].
``fixed`` (n_fixed,) int64
    Indices of grounds and the port: their previous position follows the current one.
Link arrays (one set per kind): ``i1``, ``i2`` int64 (first and second mass), ``k`` [N/m],
``z`` = B / T [N/m] (damping per sample, Faust ``mi.lib``'s physical ``z``), and for
contacts ``thr`` [m].

Scheme (DESIGN §3; Florens, Voda & Urma Fig. 5; Faust ``mi.lib`` ``mass``/``spring``/
``collision``): a link's force ``F = k (x1 - x2) + z ((x1 - x2) - (x1p - x2p))`` is applied
as ``-F`` on mass 1 and ``+F`` on mass 2; a contact applies
``F = k (x1 - x2 + thr) + z ((x1 - x2) - (x1p - x2p))`` only while ``x2 - x1 < thr`` (so its
force is continuous at engagement, as Faust 2.54 ``mi.lib`` ``collision``); then each
mobile mass moves by ``x[n+1] = 2 x[n] - x[n-1] + T^2 F[n] / m``.

One top-level kernel per set of link kinds (``run_masses``, ``run_sd``, ``run_contact``,
``run_sd_contact``): a scene pays only for the kinds it uses and each kernel compiles once
(``cache=True``), whatever the scene. No kernel allocates.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["run_masses", "run_sd", "run_contact", "run_sd_contact", "KERNELS"]

_jit = nb.njit(cache=True, nogil=True, boundscheck=False)


@_jit
def _clear(f):
    for i in range(f.size):
        f[i] = 0.0


@_jit
def _spring_dampers(x, xp, f, i1, i2, k, z):
    for j in range(i1.size):
        a = i1[j]
        c = i2[j]
        d = x[a] - x[c]
        force = k[j] * d + z[j] * (d - (xp[a] - xp[c]))
        f[a] -= force
        f[c] += force


@_jit
def _contacts(x, xp, f, i1, i2, k, z, thr):
    for j in range(i1.size):
        a = i1[j]
        c = i2[j]
        d = x[a] - x[c]
        if -d < thr[j]:
            force = k[j] * (d + thr[j]) + z[j] * (d - (xp[a] - xp[c]))
            f[a] -= force
            f[c] += force


@_jit
def _advance(x, xp, f, mobile, t2m, fixed):
    for j in range(mobile.size):
        i = mobile[j]
        xn = 2.0 * x[i] - xp[i] + t2m[j] * f[i]
        xp[i] = x[i]
        x[i] = xn
    for j in range(fixed.size):
        i = fixed[j]
        xp[i] = x[i]


@_jit
def _record(x, rec, out, row):
    for r in range(rec.size):
        out[row, r] = x[rec[r]]


@_jit
def run_masses(n, x, xp, f, mobile, t2m, fixed, rec, out, row0):
    """Advance ``n`` samples of a scene without links.

    Parameters
    ----------
    n : int
        Samples to advance, >= 0.
    x, xp, f : ndarray, shape (n_masses,)
        Positions at n and n - 1 [m] and the force accumulator [N] (updated in place).
    mobile : ndarray of int64, shape (n_mobile,)
        Indices of moving masses.
    t2m : ndarray, shape (n_mobile,)
        ``T^2 / m`` of each moving mass [s^2/kg].
    fixed : ndarray of int64, shape (n_fixed,)
        Indices of grounds and port.
    rec : ndarray of int64, shape (R,)
        Indices of the masses to record (may be empty).
    out : ndarray, shape (>= row0 + n, R)
        Recorded positions; row ``row0 + s`` receives the positions after sample s + 1.
    row0 : int
        First row of ``out`` to write.
    """
    for s in range(n):
        _clear(f)
        _advance(x, xp, f, mobile, t2m, fixed)
        _record(x, rec, out, row0 + s)


@_jit
def run_sd(n, x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z, rec, out, row0):
    """Advance ``n`` samples of a scene with spring-dampers only.

    Parameters as :func:`run_masses`, plus the spring-damper arrays ``sd_i1``, ``sd_i2``
    (int64, shape (n_sd,)), ``sd_k`` [N/m] and ``sd_z`` = B / T [N/m].
    """
    for s in range(n):
        _clear(f)
        _spring_dampers(x, xp, f, sd_i1, sd_i2, sd_k, sd_z)
        _advance(x, xp, f, mobile, t2m, fixed)
        _record(x, rec, out, row0 + s)


@_jit
def run_contact(n, x, xp, f, mobile, t2m, fixed, c_i1, c_i2, c_k, c_z, c_thr, rec, out, row0):
    """Advance ``n`` samples of a scene with contacts only.

    Parameters as :func:`run_masses`, plus the contact arrays ``c_i1``, ``c_i2`` (int64),
    ``c_k`` [N/m], ``c_z`` = B / T [N/m] and ``c_thr`` [m].
    """
    for s in range(n):
        _clear(f)
        _contacts(x, xp, f, c_i1, c_i2, c_k, c_z, c_thr)
        _advance(x, xp, f, mobile, t2m, fixed)
        _record(x, rec, out, row0 + s)


@_jit
def run_sd_contact(n, x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z,
                   c_i1, c_i2, c_k, c_z, c_thr, rec, out, row0):
    """Advance ``n`` samples of a scene with spring-dampers and contacts.

    Parameters as :func:`run_sd` followed by those of :func:`run_contact`.
    """
    for s in range(n):
        _clear(f)
        _spring_dampers(x, xp, f, sd_i1, sd_i2, sd_k, sd_z)
        _contacts(x, xp, f, c_i1, c_i2, c_k, c_z, c_thr)
        _advance(x, xp, f, mobile, t2m, fixed)
        _record(x, rec, out, row0 + s)


#: Kernel for each set of link kinds a scene uses.
KERNELS = {
    frozenset(): run_masses,
    frozenset({"spring_damper"}): run_sd,
    frozenset({"contact"}): run_contact,
    frozenset({"spring_damper", "contact"}): run_sd_contact,
}
