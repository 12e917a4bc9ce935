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

Scheme (docs/design.md, 'The scheme'; Florens, Voda & Urma Fig. 5; Faust ``mi.lib``
``mass``/``spring``/``collision``): a link's force
``F = k (x1 - x2) + z ((x1 - x2) - (x1p - x2p))`` is applied as ``-F`` on mass 1 and
``+F`` on mass 2; a contact applies
``F = k (x1 - x2 + thr) + z ((x1 - x2) - (x1p - x2p))`` only while ``x2 - x1 < thr`` (so its
force is continuous at engagement, as Faust 2.54 ``mi.lib`` ``collision``); then each
mobile mass moves by ``x[n+1] = 2 x[n] - x[n-1] + T^2 F[n] / m``.

One top-level kernel per set of link kinds (``run_masses``, ``run_sd``, ``run_contact``,
``run_sd_contact``): a scene pays only for the kinds it uses and each kernel compiles once
(``cache=True``), whatever the scene. No kernel allocates.

Speed (no per-scene code generation, no ``fastmath``; same operations in the same order,
so the results are bit for bit those of the straightforward loops):

* Indices are converted to unsigned before indexing, so numba emits no negative-index
  wraparound in the inner loops; the helpers are inlined into the kernels.
* Chains: when the spring-dampers form one chain in mass order (link ``j`` joins masses
  ``s + j`` and ``s + j + 1``, the moving masses are exactly its inner masses — a string
  between two grounds, laid out as scenes list it), ``run_sd`` and ``run_sd_contact`` detect
  it once per call (O(n_sd)) and run a fused, branch-free pass per sample: each inner
  mass's force is ``F[j-1] - F[j]`` (what clearing ``f`` and accumulating gives) and the
  mass moves at once, which LLVM vectorises; masses touched by contacts are set aside and
  moved after the contact forces are added, in the original order.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["run_masses", "run_sd", "run_contact", "run_sd_contact", "KERNELS"]

_jit = nb.njit(cache=True, nogil=True, boundscheck=False)
_jit_inline = nb.njit(cache=True, nogil=True, boundscheck=False, inline="always")
_NO_IDX = np.empty(0, dtype=np.int64)   # "no contacts" for the chain helpers
_U = nb.uint64                           # index type without wraparound checks
_ONE = nb.uint64(1)


@_jit_inline
def clear_forces(f):
    """Zero the force accumulator ``f`` (shape (n_masses,)) before a sample's links.

    Parameters
    ----------
    f : ndarray, shape (n_masses,)
        Force accumulator [N], zeroed in place.
    """
    for i in range(f.size):
        f[i] = 0.0


@_jit_inline
def spring_dampers(x, xp, f, i1, i2, k, z):
    """Add every spring-damper's force to ``f`` [N]: ``F = k (x1 - x2) + z ((x1 - x2) -
    (x1p - x2p))`` (``z = B / T``), ``-F`` on the first mass, ``+F`` on the second
    (docs/design.md, 'The scheme').

    Parameters
    ----------
    x, xp : ndarray, shape (n_masses,)
        Positions at samples n and n - 1 [m].
    f : ndarray, shape (n_masses,)
        Force accumulator [N], added to in place.
    i1, i2 : ndarray of int64, shape (n_sd,)
        First and second mass of each link.
    k, z : ndarray, shape (n_sd,)
        Stiffness [N/m] and ``z = B / T`` [N/m] of each link.
    """
    for j in range(i1.size):
        a = _U(i1[j])
        c = _U(i2[j])
        d = x[a] - x[c]
        force = k[j] * d + z[j] * (d - (xp[a] - xp[c]))
        f[a] -= force
        f[c] += force


@_jit_inline
def contacts(x, xp, f, i1, i2, k, z, thr):
    """Add every engaged contact's force to ``f`` [N]: the spring-damper law with the spring
    term ``k (x1 - x2 + thr)``, only while ``x2 - x1 < thr``
    (docs/design.md, 'The scheme').

    Parameters
    ----------
    x, xp : ndarray, shape (n_masses,)
        Positions at samples n and n - 1 [m].
    f : ndarray, shape (n_masses,)
        Force accumulator [N], added to in place.
    i1, i2 : ndarray of int64, shape (n_c,)
        First and second mass of each contact.
    k, z, thr : ndarray, shape (n_c,)
        Stiffness [N/m], ``z = B / T`` [N/m] and threshold [m] of each contact.
    """
    for j in range(i1.size):
        a = _U(i1[j])
        c = _U(i2[j])
        d = x[a] - x[c]
        if -d < thr[j]:
            force = k[j] * (d + thr[j]) + z[j] * (d - (xp[a] - xp[c]))
            f[a] -= force
            f[c] += force


@_jit_inline
def advance(x, xp, f, mobile, t2m, fixed):
    """Move the mobile masses one period, ``x[n+1] = 2 x[n] - x[n-1] + T^2 F[n] / m``
    (Florens, Voda & Urma Fig. 5), and carry the port's and grounds' ``x`` into ``xp``.

    Parameters
    ----------
    x, xp : ndarray, shape (n_masses,)
        Positions at samples n and n - 1 [m]; on return at n + 1 and n.
    f : ndarray, shape (n_masses,)
        Forces of sample n [N] (read only).
    mobile : ndarray of int64, shape (n_mobile,)
        Indices of the moving masses.
    t2m : ndarray, shape (n_mobile,)
        ``T^2 / m`` of each moving mass [s^2/kg].
    fixed : ndarray of int64, shape (n_fixed,)
        Indices of the grounds and the port.
    """
    for j in range(mobile.size):
        i = _U(mobile[j])
        xn = 2.0 * x[i] - xp[i] + t2m[j] * f[i]
        xp[i] = x[i]
        x[i] = xn
    for j in range(fixed.size):
        i = fixed[j]
        xp[i] = x[i]


@_jit
def chain_start(x, mobile, fixed, i1, i2):
    """First mass of the spring-damper chain, or -1 when the links are not one.

    A chain (detected once per kernel call, O(n_sd)): link ``j`` joins masses ``s + j`` and
    ``s + j + 1``; the moving masses are exactly ``s + 1 .. s + n_sd - 1`` in order; the two
    ends and every other mass are in ``fixed``. Such scenes (strings) then run without index
    arrays in their inner loops, with the same floating-point operations in the same order.

    Parameters
    ----------
    x : ndarray, shape (n_masses,)
        Positions (only their number is used).
    mobile : ndarray of int64, shape (n_mobile,)
        Indices of the moving masses.
    fixed : ndarray of int64, shape (n_fixed,)
        Indices of the grounds and the port.
    i1, i2 : ndarray of int64, shape (n_sd,)
        First and second mass of each spring-damper.

    Returns
    -------
    int
        ``s``, the chain's first mass, or -1 (also for fewer than two links).
    """
    nl = i1.size
    if nl < 2 or mobile.size != nl - 1 or fixed.size + mobile.size != x.size:
        return -1
    s = i1[0]
    # Branch-free OR reductions (vectorised): this runs on every call, port_step included.
    bad = np.int64(0)
    for j in range(nl):
        bad |= (i1[j] - (s + j)) | (i2[j] - (s + j + 1))
    for j in range(mobile.size):
        bad |= mobile[j] - (s + 1 + j)
    return s if bad == 0 else -1


@_jit_inline
def _next_mark(c_i1, c_i2, a):
    """Smallest index > ``a`` of a mass that a contact touches (2^62 when none)."""
    m = np.int64(1) << 62
    for j in range(c_i1.size):
        if a < c_i1[j] < m:
            m = c_i1[j]
        if a < c_i2[j] < m:
            m = c_i2[j]
    return m


@_jit_inline
def chain_fused(x, xp, f, t2m, fixed, s, k, z, c_i1, c_i2):
    """Forces of a chain and the move of its masses that no contact touches, in one pass.

    ``f`` receives exactly what clearing it and running :func:`spring_dampers` gives:
    ``(0 + F[j-1]) - F[j]`` == ``F[j-1] - F[j]`` on inner mass ``s + j``, ``0 - F[0]`` and
    ``0 + F[-1]`` on the ends, 0 on the other fixed masses. A moving mass no contact touches
    has its final force then and moves at once, with :func:`advance`'s operations (its
    old position is kept in registers for the next link). Masses that contacts touch keep
    their position so that the caller adds the contact forces (:func:`contacts`) and moves
    them (:func:`move_marked`). The inner loop runs between such masses and has no branch,
    which lets LLVM vectorise it.

    Parameters
    ----------
    x, xp : ndarray, shape (n_masses,)
        Positions at samples n and n - 1 [m] (the moved masses' advanced in place).
    f : ndarray, shape (n_masses,)
        Force accumulator [N], overwritten on the chain's masses and the fixed ones.
    t2m : ndarray, shape (n_sd - 1,)
        ``T^2 / m`` of the inner masses ``s + 1 ..`` in order [s^2/kg].
    fixed : ndarray of int64, shape (n_fixed,)
        Indices of the grounds and the port.
    s : int
        The chain's first mass (:func:`chain_start`, >= 0).
    k, z : ndarray, shape (n_sd,)
        Stiffness [N/m] and ``z = B / T`` [N/m] of each link.
    c_i1, c_i2 : ndarray of int64, shape (n_c,)
        The contacts' masses (empty for none).
    """
    for j in range(fixed.size):
        f[fixed[j]] = 0.0
    nl = k.size
    xb = x[s + 1]
    xpb = xp[s + 1]
    d = x[s] - xb
    prev = k[0] * d + z[0] * (d - (xp[s] - xpb))
    f[s] = 0.0 - prev
    mark = _next_mark(c_i1, c_i2, s)
    us = _U(s)
    j = 1
    while j < nl:
        stop = min(mark - s, nl)
        # Unsigned indices: numba then emits no negative-index wraparound, and the loop
        # vectorises (about 4x faster on strings).
        for jj in range(_U(j), _U(stop)):
            a = us + jj
            xa = xb
            xpa = xpb
            xb = x[a + _ONE]
            xpb = xp[a + _ONE]
            d = xa - xb
            force = k[jj] * d + z[jj] * (d - (xpa - xpb))
            fa = prev - force
            f[a] = fa
            prev = force
            x[a] = 2.0 * xa - xpa + t2m[jj - _ONE] * fa
            xp[a] = xa
        j = stop
        if j < nl:
            a = s + j
            xa = xb
            xpa = xpb
            xb = x[a + 1]
            xpb = xp[a + 1]
            d = xa - xb
            force = k[j] * d + z[j] * (d - (xpa - xpb))
            f[a] = prev - force
            prev = force
            mark = _next_mark(c_i1, c_i2, a)
            j += 1
    f[s + nl] = 0.0 + prev


@_jit_inline
def move_marked(x, xp, f, t2m, fixed, s, nl, c_i1, c_i2):
    """Move the moving chain masses that are contact ends, then the fixed masses' ``xp``.

    Parameters
    ----------
    x, xp : ndarray, shape (n_masses,)
        Positions at samples n and n - 1 [m], advanced in place.
    f : ndarray, shape (n_masses,)
        Forces of sample n [N], contacts included (read only).
    t2m : ndarray, shape (nl - 1,)
        ``T^2 / m`` of the inner masses ``s + 1 ..`` in order [s^2/kg].
    fixed : ndarray of int64, shape (n_fixed,)
        Indices of the grounds and the port.
    s : int
        The chain's first mass (:func:`chain_start`).
    nl : int
        Links in the chain (``n_sd``).
    c_i1, c_i2 : ndarray of int64, shape (n_c,)
        The contacts' masses (empty for none).
    """
    a = s
    while True:
        a = _next_mark(c_i1, c_i2, a)
        if a >= s + nl:
            break
        xn = 2.0 * x[a] - xp[a] + t2m[a - s - 1] * f[a]
        xp[a] = x[a]
        x[a] = xn
    for j in range(fixed.size):
        i = fixed[j]
        xp[i] = x[i]


@_jit_inline
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
        clear_forces(f)
        advance(x, xp, f, mobile, t2m, fixed)
        _record(x, rec, out, row0 + s)


@_jit
def run_sd(n, x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z, rec, out, row0):
    """Advance ``n`` samples of a scene with spring-dampers only.

    Parameters as :func:`run_masses`, plus the spring-damper arrays ``sd_i1``, ``sd_i2``
    (int64, shape (n_sd,)), ``sd_k`` [N/m] and ``sd_z`` = B / T [N/m].
    """
    c = chain_start(x, mobile, fixed, sd_i1, sd_i2)
    if c >= 0:
        for s in range(n):
            chain_fused(x, xp, f, t2m, fixed, c, sd_k, sd_z, _NO_IDX, _NO_IDX)
            move_marked(x, xp, f, t2m, fixed, c, sd_k.size, _NO_IDX, _NO_IDX)
            _record(x, rec, out, row0 + s)
        return
    for s in range(n):
        clear_forces(f)
        spring_dampers(x, xp, f, sd_i1, sd_i2, sd_k, sd_z)
        advance(x, xp, f, mobile, t2m, fixed)
        _record(x, rec, out, row0 + s)


@_jit
def run_contact(n, x, xp, f, mobile, t2m, fixed, c_i1, c_i2, c_k, c_z, c_thr, rec, out, row0):
    """Advance ``n`` samples of a scene with contacts only.

    Parameters as :func:`run_masses`, plus the contact arrays ``c_i1``, ``c_i2`` (int64),
    ``c_k`` [N/m], ``c_z`` = B / T [N/m] and ``c_thr`` [m].
    """
    for s in range(n):
        clear_forces(f)
        contacts(x, xp, f, c_i1, c_i2, c_k, c_z, c_thr)
        advance(x, xp, f, mobile, t2m, fixed)
        _record(x, rec, out, row0 + s)


@_jit
def run_sd_contact(n, x, xp, f, mobile, t2m, fixed, sd_i1, sd_i2, sd_k, sd_z,
                   c_i1, c_i2, c_k, c_z, c_thr, rec, out, row0):
    """Advance ``n`` samples of a scene with spring-dampers and contacts.

    Parameters as :func:`run_sd` followed by those of :func:`run_contact`.
    """
    c = chain_start(x, mobile, fixed, sd_i1, sd_i2)
    if c >= 0:
        for s in range(n):
            chain_fused(x, xp, f, t2m, fixed, c, sd_k, sd_z, c_i1, c_i2)
            contacts(x, xp, f, c_i1, c_i2, c_k, c_z, c_thr)
            move_marked(x, xp, f, t2m, fixed, c, sd_k.size, c_i1, c_i2)
            _record(x, rec, out, row0 + s)
        return
    for s in range(n):
        clear_forces(f)
        spring_dampers(x, xp, f, sd_i1, sd_i2, sd_k, sd_z)
        contacts(x, xp, f, c_i1, c_i2, c_k, c_z, c_thr)
        advance(x, xp, f, mobile, t2m, fixed)
        _record(x, rec, out, row0 + s)


#: Kernel for each set of link kinds a scene uses.
KERNELS = {
    frozenset(): run_masses,
    frozenset({"spring_damper"}): run_sd,
    frozenset({"contact"}): run_contact,
    frozenset({"spring_damper", "contact"}): run_sd_contact,
}
