"""n-D CORDIS-ANIMA kernels (n = 1, 2, 3): centred masses and visco-elastic links, laid
out for speed.

Plain arrays and floats only; nothing here imports from the API layer (CONVENTIONS §3).
Units SI.

State (structure of arrays, float64, C order):

``x``, ``xp``, ``f`` (dim, N)
    Positions at sample n and n - 1 [m], force accumulator [N]: one contiguous row per
    axis, so every pass below reads and writes unit-stride rows.
``t2m`` (N,)
    ``T^2 / m`` [s^2/kg] of each mass; 0 for grounds and the port (they do not move under
    the forces: with ``xp = x`` the update ``2 x - xp`` leaves them in place).

Links (one kind per link set):

``linear``
    ``F = k d + z (d - d_prev)`` with ``d = x1 - x2`` (vector), ``z = B / T`` [N/m]: the
    1-D law on every axis (Faust ``mi.lib`` ``spring``), ``-F`` on mass 1, ``+F`` on mass 2.
``euclid``
    ``F = [k (|d| - L) + z (|d| - l_prev)] d / |d|`` with ``l_prev`` the link's length at
    the previous sample, kept per link (``eu_lprev``: one square root per link, not two):
    the Euclidean stretch and the damping along the link (miPhysics ``SpringDamper3D``);
    no force while ``|d| = 0`` (no direction).

Stripes. A mesh's links are grouped (:func:`stripes`, once, at build time) by the index
offset ``s = i2 - i1`` into runs of consecutive ``i1``: a stripe is ``(a, s, c, j0)``, the
``c`` links joining ``a + i`` to ``a + s + i`` whose parameters are ``k[j0 + i]`` etc.
Per sample a stripe is processed in chunks of :data:`CHUNK` links, each in unit-stride
passes: one fused loop computes the chunk's link forces into scratch rows (square roots
and divisions vectorised), then ``f[d, a:a+c] -= W[d]`` and ``f[d, a+s:a+s+c] += W[d]``:
no gather, no scatter, no aliasing between the reads and the writes of one loop, and
unsigned indices (no negative-index wraparound), so LLVM vectorises every loop. A 3-D grid mesh is 3 stripes per
layer of rows; links that form no run fall into stripes of length 1 (the gather/scatter
of a general mesh). Summation order differs from one-link-at-a-time code only in the
order each mass's link forces are added (round-off).

Contacts (few, scattered) run one at a time: sphere contacts (the Euclidean law with rest
length ``threshold`` while ``|d| < threshold``) and plane contacts (``p = offset -
normal . x``, force ``(k p + z (p - p_prev)) normal`` while ``p > 0``).

Scheme: ``x[n+1] = 2 x[n] - x[n-1] + t2m f[n]`` per axis (the 1-D scheme of
:mod:`hapsim.kernels.cordis` on every axis; docs/design.md, 'The scheme').
No kernel allocates.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["stripes", "link_lengths", "step_nd", "run_nd", "CHUNK"]

_jit = nb.njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")


def stripes(i1: np.ndarray, i2: np.ndarray, max_gap: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Group links into stripes (module docstring) and give the link order they need.

    Parameters
    ----------
    i1, i2 : ndarray of int, shape (L,)
        First and second mass of each link (``i1 != i2``).
    max_gap : int, optional
        Runs of the same offset separated by at most this many missing links are joined
        into one stripe, the holes filled with padding links (``order = -1``: give them
        zero stiffness and damping, they add no force): a grid's rows become one long
        stripe per direction instead of one short stripe per row.

    Returns
    -------
    table : ndarray of int64, shape (S, 4)
        ``(a, s, c, j0)`` per stripe: the links ``a + i`` -- ``a + s + i`` for
        ``i < c``, whose parameters are at ``j0 + i`` in the reordered link arrays.
    order : ndarray of int64, shape (L + padding,)
        For each slot of the reordered link arrays, the original link (``k[order]``),
        or -1 for a padding link.
    """
    i1 = np.asarray(i1, np.int64)
    i2 = np.asarray(i2, np.int64)
    s = i2 - i1
    srt = np.lexsort((i1, s))
    rows = []
    slots = []
    j = 0
    L = srt.size
    while j < L:
        a = int(i1[srt[j]])
        off = int(s[srt[j]])
        j0 = len(slots)
        slots.append(int(srt[j]))
        last = a
        j += 1
        while j < L and s[srt[j]] == off and 0 < i1[srt[j]] - last <= max_gap + 1:
            slots.extend([-1] * int(i1[srt[j]] - last - 1))
            slots.append(int(srt[j]))
            last = int(i1[srt[j]])
            j += 1
        rows.append((a, off, last - a + 1, j0))
    table = np.array(rows, dtype=np.int64).reshape(-1, 4)
    return table, np.array(slots, dtype=np.int64)


def link_lengths(xp: np.ndarray, table: np.ndarray, n_slots: int) -> np.ndarray:
    """Each stripe slot's link length at ``xp`` [m] (the start of ``eu_lprev``).

    Parameters
    ----------
    xp : ndarray, shape (dim, N)
        Positions at the previous sample [m].
    table : ndarray of int64, shape (S, 4)
        Stripes (:func:`stripes`).
    n_slots : int
        Length of the reordered link arrays.

    Returns
    -------
    ndarray, shape (n_slots,)
        ``|xp[:, a + i] - xp[:, a + s + i]|`` per slot (padding slots too: harmless).
    """
    out = np.zeros(n_slots)
    for a, s, c, j0 in table:
        d = xp[:, a:a + c] - xp[:, a + s:a + s + c]
        out[j0:j0 + c] = np.sqrt((d * d).sum(axis=0))
    return out


_U = nb.uint64       # unsigned indices: no negative-index wraparound, so loops vectorise

#: Links per chunk of a stripe: the scratch rows stay in L1 (3 x 512 x 8 bytes).
CHUNK = 512


@_jit
def _scatter(f, a, b, c, W):
    """``f[d, a:a+c] -= W[d]``, ``f[d, b:b+c] += W[d]`` per axis (two loops: no
    aliasing between their reads and writes, even for an offset below the vector width)."""
    for d in range(f.shape[0]):
        fd = f[d]
        wd = W[d]
        for i in range(c):
            fd[a + i] -= wd[i]
        for i in range(c):
            fd[b + i] += wd[i]


@_jit
def _linear_chunk(x, xp, f, a, b, c, j0, k, z, W):
    for d in range(x.shape[0]):
        xd = x[d]
        pd = xp[d]
        wd = W[d]
        for i in range(c):
            dd = xd[a + i] - xd[b + i]
            wd[i] = k[j0 + i] * dd + z[j0 + i] * (dd - (pd[a + i] - pd[b + i]))
    _scatter(f, a, b, c, W)


@_jit
def _euclid_chunk3(x, xp, f, a, b, c, j0, k, z, rest, lprev, W):
    x0, x1, x2 = x[0], x[1], x[2]
    w0, w1, w2 = W[0], W[1], W[2]
    for i in range(c):
        dx = x0[a + i] - x0[b + i]
        dy = x1[a + i] - x1[b + i]
        dz = x2[a + i] - x2[b + i]
        ln = np.sqrt(dx * dx + dy * dy + dz * dz)
        j = j0 + i
        g = k[j] * (ln - rest[j]) + z[j] * (ln - lprev[j])
        lprev[j] = ln
        g = g / ln if ln > 0.0 else 0.0
        w0[i] = g * dx
        w1[i] = g * dy
        w2[i] = g * dz
    _scatter(f, a, b, c, W)


@_jit
def _euclid_chunk2(x, xp, f, a, b, c, j0, k, z, rest, lprev, W):
    x0, x1 = x[0], x[1]
    w0, w1 = W[0], W[1]
    for i in range(c):
        dx = x0[a + i] - x0[b + i]
        dy = x1[a + i] - x1[b + i]
        ln = np.sqrt(dx * dx + dy * dy)
        j = j0 + i
        g = k[j] * (ln - rest[j]) + z[j] * (ln - lprev[j])
        lprev[j] = ln
        g = g / ln if ln > 0.0 else 0.0
        w0[i] = g * dx
        w1[i] = g * dy
    _scatter(f, a, b, c, W)


@_jit
def _euclid_chunk1(x, xp, f, a, b, c, j0, k, z, rest, lprev, W):
    x0 = x[0]
    w0 = W[0]
    for i in range(c):
        dx = x0[a + i] - x0[b + i]
        ln = abs(dx)
        j = j0 + i
        g = k[j] * (ln - rest[j]) + z[j] * (ln - lprev[j])
        lprev[j] = ln
        g = g / ln if ln > 0.0 else 0.0
        w0[i] = g * dx
    _scatter(f, a, b, c, W)


@_jit
def _links(x, xp, f, table, k, z, rest, lprev, W, euclid):
    dim = x.shape[0]
    for r in range(table.shape[0]):
        a = _U(table[r, 0])
        c = _U(table[r, 2])
        j0 = _U(table[r, 3])
        b = _U(table[r, 0] + table[r, 1])
        lo = _U(0)
        while lo < c:
            m = min(_U(CHUNK), c - lo)
            if not euclid:
                _linear_chunk(x, xp, f, a + lo, b + lo, m, j0 + lo, k, z, W)
            elif dim == 3:
                _euclid_chunk3(x, xp, f, a + lo, b + lo, m, j0 + lo, k, z, rest, lprev, W)
            elif dim == 2:
                _euclid_chunk2(x, xp, f, a + lo, b + lo, m, j0 + lo, k, z, rest, lprev, W)
            else:
                _euclid_chunk1(x, xp, f, a + lo, b + lo, m, j0 + lo, k, z, rest, lprev, W)
            lo += m


@_jit
def _contacts(x, f, i1, i2, k, z, thr, lprev):
    """Sphere contacts, one at a time (few, scattered): the Euclidean law with rest length
    ``thr`` while ``|d| < thr``; every contact's length is kept for its damping."""
    dim = x.shape[0]
    for j in range(i1.size):
        a = _U(i1[j])
        b = _U(i2[j])
        l2 = 0.0
        for d in range(dim):
            dd = x[d, a] - x[d, b]
            l2 += dd * dd
        ln = np.sqrt(l2)
        lp = lprev[j]
        lprev[j] = ln
        if ln < thr[j] and ln > 0.0:
            g = (k[j] * (ln - thr[j]) + z[j] * (ln - lp)) / ln
            for d in range(dim):
                fd = g * (x[d, a] - x[d, b])
                f[d, a] -= fd
                f[d, b] += fd


@_jit
def _planes(x, xp, f, mass, normal, offset, k, z):
    """Plane contacts, one (plane, mass) pair at a time: with the penetration
    ``p = offset - normal . x``, the force ``(k p + z (p - p_prev)) normal`` while
    ``p > 0``."""
    dim = x.shape[0]
    for j in range(mass.size):
        m = _U(mass[j])
        p = offset[j]
        pp = offset[j]
        for d in range(dim):
            p -= normal[d, j] * x[d, m]
            pp -= normal[d, j] * xp[d, m]
        if p > 0.0:
            g = k[j] * p + z[j] * (p - pp)
            for d in range(dim):
                f[d, m] += g * normal[d, j]


@_jit
def _advance(x, xp, f, t2m):
    n = _U(x.shape[1])
    for d in range(x.shape[0]):
        xd = x[d]
        xpd = xp[d]
        fd = f[d]
        for i in range(n):
            xn = 2.0 * xd[i] - xpd[i] + t2m[i] * fd[i]
            xpd[i] = xd[i]
            xd[i] = xn


@_jit
def step_nd(x, xp, f, t2m, lin_table, lin_k, lin_z, eu_table, eu_k, eu_z, eu_rest,
            eu_lprev, W, c_i1, c_i2, c_k, c_z, c_thr, c_lprev, p_mass, p_normal,
            p_offset, p_k, p_z):
    """One sample of the n-D scheme (module docstring).

    Parameters
    ----------
    x, xp, f : ndarray, shape (dim, N)
        Positions at n and n - 1 [m] (updated to n + 1 and n), force accumulator [N]
        (left holding the forces of sample n).
    t2m : ndarray, shape (N,)
        ``T^2 / m`` [s^2/kg] (0: does not move).
    lin_table, eu_table : ndarray of int64, shape (S, 4)
        Stripes of the linear and Euclidean links (:func:`stripes`).
    lin_k, lin_z : ndarray
        Linear links' ``K`` [N/m] and ``B / T`` [N/m], in stripe order.
    eu_k, eu_z, eu_rest : ndarray
        Euclidean links' ``K`` [N/m], ``B / T`` [N/m] and rest length [m], in stripe
        order (padding links: 0, 0, 0).
    eu_lprev : ndarray
        Each Euclidean link's length at the previous sample [m] (updated; start it at
        the lengths of ``xp``: :func:`link_lengths`).
    W : ndarray, shape (dim, CHUNK)
        Scratch (the link forces of one chunk).
    c_i1, c_i2, c_k, c_z, c_thr, c_lprev : ndarray, shape (C,)
        Sphere contacts: masses, ``K`` [N/m], ``B / T`` [N/m], threshold [m] and length
        at the previous sample [m] (updated).
    p_mass, p_normal, p_offset, p_k, p_z : ndarray
        Plane contacts per (plane, mass) pair: the mass (P,), the unit normal (dim, P),
        the offset [m], ``K`` [N/m] and ``B / T`` [N/m] (P,).
    """
    for d in range(f.shape[0]):
        fd = f[d]
        for i in range(_U(fd.size)):
            fd[i] = 0.0
    _links(x, xp, f, lin_table, lin_k, lin_z, lin_z, lin_z, W, False)
    _links(x, xp, f, eu_table, eu_k, eu_z, eu_rest, eu_lprev, W, True)
    _contacts(x, f, c_i1, c_i2, c_k, c_z, c_thr, c_lprev)
    _planes(x, xp, f, p_mass, p_normal, p_offset, p_k, p_z)
    _advance(x, xp, f, t2m)


@_jit
def run_nd(n, x, xp, f, t2m, lin_table, lin_k, lin_z, eu_table, eu_k, eu_z, eu_rest,
           eu_lprev, W, c_i1, c_i2, c_k, c_z, c_thr, c_lprev, p_mass, p_normal, p_offset,
           p_k, p_z):
    """``n`` samples of :func:`step_nd` (same arguments after ``n``)."""
    for _ in range(n):
        step_nd(x, xp, f, t2m, lin_table, lin_k, lin_z, eu_table, eu_k, eu_z, eu_rest,
                eu_lprev, W, c_i1, c_i2, c_k, c_z, c_thr, c_lprev, p_mass, p_normal,
                p_offset, p_k, p_z)
