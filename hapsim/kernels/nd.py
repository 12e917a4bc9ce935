"""n-D CORDIS-ANIMA kernels (n = 1, 2, 3): centred masses and visco-elastic links, laid
out and scheduled for speed.

Plain arrays and floats only; nothing here imports from the API layer (docs/design.md, rule 3).
Units SI.

State (structure of arrays, C order, always :data:`ROWS` = 3 rows: a 1-D or 2-D scene
leaves the rows past its dimension at zero, where they stay), float64 or, in single
precision, float32: every kernel is written for either (no float64 literal in an
expression, :func:`_zero`), numba compiles one version per type, and :func:`context`
with :func:`run_context` / :func:`run_context32` name the arrays of each. In float64 the
arithmetic is the same operations in the same order as before single precision existed
(``x + x`` for ``2 x``: both exact), so double-precision results are unchanged bit for
bit:

``x``, ``xp``, ``f`` (3, N)
    Positions at sample n and n - 1 [m], force accumulator [N] (zero between samples:
    each block of masses clears its forces once it has advanced).
``t2m`` (N,)
    ``T^2 / m`` [s^2/kg] of each mass; 0 for grounds and the port (they do not move under
    the forces: with ``xp = x`` the update ``2 x - xp`` leaves them in place).

Links (one kind per link set), every link oriented so that its first mass has the lower
index (the laws below are symmetric in the two ends):

``linear``
    ``F = k d + z (d - d_prev)`` with ``d = x1 - x2`` (vector), ``z = B / T`` [N/m]: the
    1-D law on every axis (Faust ``mi.lib`` ``spring``), ``-F`` on mass 1, ``+F`` on mass 2.
``euclid``
    ``F = [k (|d| - L) + z (|d| - l_prev)] d / |d|`` with ``l_prev`` the link's length at
    the previous sample, kept per link (``eu_lprev``): the Euclidean stretch and the
    damping along the link (miPhysics ``SpringDamper3D``); no force while ``|d| = 0``.

Layout and schedule (why it is fast):

* *Stripes.* Links are grouped (:func:`stripes`, once) by the index offset
  ``s = i2 - i1 > 0`` into runs of consecutive ``i1``: the ``c`` links joining ``a + i``
  to ``a + s + i``, parameters at ``j0 + i``. A 3-D grid mesh is three long stripes (its
  +x, +y, +z families); a link that forms no run is a stripe of one.
* *Blocks.* The masses are cut into blocks of :data:`BLOCK` consecutive indices and each
  stripe into *pieces* by the block of their lower mass (:func:`schedule`). A sample
  runs the blocks in order: each piece computes its links' forces in one fused,
  vectorised pass into scratch rows, adds them to the force rows with two unit-stride
  passes (``f[:, a:a+c] -= W``, ``f[:, a+s:a+s+c] += W``: no gather, no scatter, no
  aliasing between one loop's reads and writes), and then the block's masses --- whose
  every link has now been counted (a link is in the block of its lower mass) --- advance
  at once while their rows are still in the L1 cache. Nothing reads a mass's position
  after it has advanced within the sample: a link reads its ends in the block of its
  lower mass, never later than that mass's own block.
* *Families.* A mesh's dense families of Euclidean links (offsets ``s`` whose links
  ``(i, i + s)`` cover a quarter of the masses or more: a grid's +x, +y and +z links;
  :func:`hapsim.kernels.layout.families`, up to three) are not scattered: a block computes
  its families' links into one row per axis and family, ``G[i]`` the force on mass
  ``i + s``, and each mass then *pulls* its forces, ``sum (G[i - s] - G[i])`` over the
  families, as it advances (unit-stride reads of rows already written: the link of
  ``i - s`` is in an earlier block or this one). No read-modify-write of a force row per
  link and no scratch rows for them: 5.6 against 6.9 ns per mass-sample on the 5,808-mass
  grid, same run (``tools/bench_nd.py``); none above
  :data:`hapsim.kernels.layout.FAMILY_MAX_MASSES` masses, where their rows stream from
  memory.
* A Euclidean piece or family whose links share their stiffness, damping and rest
  length (a uniform mesh's) reads them as three numbers instead of three per-link arrays
  (:func:`shared_params`: the pieces' entries, then the families'); its padding links
  (the holes a stripe or family was given) are computed and their forces dropped (a
  family's zeroed in ``G`` per chunk of blocks, found by bisection in its sorted list).
* *Placement.* A load whose address matches a store in flight modulo 4,096 bytes waits
  for it, and the families' loops stream 13 to 17 arrays at once: the engine starts each
  streamed array where in its page few such pairs occur
  (:func:`hapsim.kernels.layout.family_offsets`; where numpy's allocations happened to
  land moved the 5,016-mass grid's sample by 20 %). With the shared family parameters,
  4.45 against 4.73 ns per mass-sample there (same process, 4 fresh allocations each,
  medians; trajectories bit for bit main's).
* Every helper is inlined into :func:`step_nd` and indexes the 2-D arrays directly (no
  row views: a view costs a reference-count update per piece).
* ``fastmath={"contract"}`` only: ``a * b + c`` may become one fused multiply-add
  (round-off); no reassociation, no finite-math assumption. Square roots and divisions
  are the exact IEEE operations (an inverse square root by Newton's method from the
  previous sample's, or from a single-precision estimate, tried, was no faster here: the
  kernel is bound by its loads and stores as much as by its divider;
  ``tools/bench_nd.py`` prints where the time goes).
* One argument per call from Python (:func:`context`, :func:`run_context`): the arrays'
  addresses and shapes in one int64 array, rebuilt in compiled code
  (:mod:`hapsim.kernels.pointers`), so that a real-time loop stepping once per sample
  does not pay numba's type check and unboxing of 38 arguments (microseconds, and a
  transient allocation, per call).

The summation order of each mass's forces differs from one-link-at-a-time code (and a
fused multiply-add may round once where the reference rounds twice): the results agree
with a straightforward implementation to round-off (``tests/test_engine_nd.py``, ``tools/bench_nd.py``).

Contacts (few, scattered) run one at a time, before the blocks: sphere contacts (the
Euclidean law with rest length ``threshold`` while ``|d| < threshold``) and plane contacts
(``p = offset - normal . x``, force ``(k p + z (p - p_prev)) normal`` while ``p > 0``).

Scheme: ``x[n+1] = 2 x[n] - x[n-1] + t2m f[n]`` per axis (the 1-D scheme of
:mod:`hapsim.kernels.cordis` on every axis; docs/design.md, 'The scheme').

In single precision the same scheme is kept in its velocity form: the ``xp`` array holds
the increment ``v = x[n] - x[n-1]`` [m] and a sample is ``v += t2m f``, ``x += v``
(:func:`_vform`; the linear law's damping reads ``v1 - v2``, a plane's previous
penetration ``p + normal . v``). Equal in exact arithmetic; in float32 a position is
rounded to 24 bits every sample, and in the position form that rounding (up to
``ulp(x) / 2``, 4e-9 m at 0.1 m) is a velocity error, integrated twice: on a mesh 1 cm
apart moving 1 mm at 44.1 kHz, the position form's float32 trajectory is 2e-2 of the
motion away from float64's after 200 samples, the velocity form's 2e-5. Double precision
keeps the position form (its results unchanged bit for bit).
No kernel allocates.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba.extending import overload, register_jitable

from hapsim.kernels.layout import (BLOCK, euclid_layout, families, link_lengths,
                                   schedule, shared_params, stripes)
from hapsim.kernels.pointers import address, voidptr
from hapsim.kernels.sources import cache_ok

__all__ = ["stripes", "schedule", "shared_params", "link_lengths", "families",
           "euclid_layout", "step_nd", "run_nd",
           "run_nd_listen", "context", "run_context", "run_context32", "BLOCK", "ROWS"]

#: The sources this module's numba code compiles in (:mod:`hapsim.kernels.sources`).
COMPILED_SOURCES = ("hapsim/kernels/pointers.py", "hapsim/kernels/layout.py")
#: Their SHA-256: numba keys its disk cache on this file alone, so this literal changes
#: with them (``tests/test_compiled_loop_sources.py`` says so); until then, no cache.
COMPILED_SOURCES_SHA256 = "3435790be65a25a406582536897ba487fbb87fa469851f31f020dd86a81e64a0"
#: Whether numba's disk cache may serve this module's compiled code.
CACHE_OK = cache_ok(COMPILED_SOURCES, COMPILED_SOURCES_SHA256)

_jit = nb.njit(cache=CACHE_OK, nogil=True, boundscheck=False, error_model="numpy",
               fastmath={"contract"})
_inline = nb.njit(cache=CACHE_OK, nogil=True, boundscheck=False, error_model="numpy",
                  fastmath={"contract"}, inline="always")
#: The context's accessors (:func:`run_context`): compiled once per signature and called
#: (LLVM inlines them), not inlined into numba's IR at each of the 66 call sites, which
#: translated and typed the accessor again at every site (~3 CPU-s a runner into an empty
#: cache). An overload (``register_jitable``) types the constant index as ``int64``, not
#: ``Literal``, so each accessor compiles once. A view is built, no arithmetic: same code.
_access = register_jitable(boundscheck=False)

#: Blocks advanced at once in a scene with dense families (their links computed over the
#: span first): each vectorised loop then runs 4,096 masses, not 256, and its scalar
#: remainder (a square root and a division each) is paid once, not 16 times: 5.2 against
#: 6.1 ns per mass-sample on the 5,808-mass grid, 5.2 against 6.2 on the 32,000-mass one
#: (same runs; spans of 8 to 32 blocks within 3 % of each other). Scenes without
#: families advance block by block as before.
FAMILY_SPAN = 16
#: Rows of the state arrays (axes): a scene of lower dimension leaves the rest at zero.
ROWS = 3


_U = nb.uint64       # unsigned indices: no negative-index wraparound, so loops vectorise


def _zero(v):
    """A zero of ``v``'s floating type (compiled code only: a literal ``0.0`` is a
    float64, which would promote a single-precision expression to double)."""
    return 0.0


@overload(_zero, inline="always")
def _zero_typed(v):
    if isinstance(v, nb.types.Float) and v.bitwidth == 32:
        return lambda v: np.float32(0.0)
    return lambda v: 0.0


def _vform(x):
    """Whether the state ``x`` is in single precision, whose second row array holds the
    velocity form's increment ``x[n] - x[n-1]`` instead of ``x[n-1]`` (module docstring;
    a constant of the compiled code: each type compiles one branch)."""
    return False


@overload(_vform, inline="always")
def _vform_typed(x):
    if x.dtype == nb.types.float32:
        return lambda x: True
    return lambda x: False


@_inline
def _scatter(f, dim, a, b, c, W):
    """``f[d, a:a+c] -= W[d]``, ``f[d, b:b+c] += W[d]`` per live axis (two loops: no
    aliasing between their reads and writes, even for an offset below the vector width)."""
    for d in range(dim):
        for i in range(c):
            f[d, a + i] -= W[d, i]
        for i in range(c):
            f[d, b + i] += W[d, i]


@_inline
def _linear_piece(x, xp, dim, a, b, c, j0, k, z, W):
    """Linear links ``a + i`` -- ``b + i``: their forces into ``W``."""
    if _vform(x):
        for d in range(dim):
            for i in range(c):
                dd = x[d, a + i] - x[d, b + i]
                W[d, i] = k[j0 + i] * dd + z[j0 + i] * (xp[d, a + i] - xp[d, b + i])
    else:
        for d in range(dim):
            for i in range(c):
                dd = x[d, a + i] - x[d, b + i]
                W[d, i] = k[j0 + i] * dd + z[j0 + i] * (dd - (xp[d, a + i] - xp[d, b + i]))


@_inline
def _euclid_law(dx, dy, dz, k, z, rest, lprev, j):
    """The Euclidean law's factor ``g = [k (|d| - L) + z (|d| - l_prev)] / |d|`` of the
    link ``j`` with ``d = (dx, dy, dz)`` (0 while ``|d| = 0``); its length kept in
    ``lprev[j]`` for the next sample (module docstring, ``euclid``)."""
    ln = np.sqrt(dx * dx + dy * dy + dz * dz)
    lp = lprev[j]
    lprev[j] = ln
    g = (k * (ln - rest) + z * (ln - lp)) / ln
    if not ln > 0.0:
        g = _zero(g)
    return g


@_inline
def _euclid_piece(x, a, b, c, j0, k, z, rest, lprev, W):
    """Euclidean links ``a + i`` -- ``b + i``: their forces into ``W``, their lengths
    into ``lprev`` (all three rows: a lower dimension's extra rows are zero)."""
    for i in range(c):
        j = j0 + i
        dx = x[0, a + i] - x[0, b + i]
        dy = x[1, a + i] - x[1, b + i]
        dz = x[2, a + i] - x[2, b + i]
        g = _euclid_law(dx, dy, dz, k[j], z[j], rest[j], lprev, j)
        W[0, i] = g * dx
        W[1, i] = g * dy
        W[2, i] = g * dz


@_inline
def _euclid_piece_shared(x, a, b, c, j0, k, z, rest, lprev, W):
    """:func:`_euclid_piece` with one ``k``, ``z`` and rest length for the piece."""
    for i in range(c):
        j = j0 + i
        dx = x[0, a + i] - x[0, b + i]
        dy = x[1, a + i] - x[1, b + i]
        dz = x[2, a + i] - x[2, b + i]
        g = _euclid_law(dx, dy, dz, k, z, rest, lprev, j)
        W[0, i] = g * dx
        W[1, i] = g * dy
        W[2, i] = g * dz


@_jit
def _contacts(x, f, i1, i2, k, z, thr, lprev):
    """Sphere contacts, one at a time (few, scattered): the Euclidean law with rest length
    ``thr`` while ``|d| < thr``; every contact's length is kept for its damping."""
    for j in range(i1.size):
        a = _U(i1[j])
        b = _U(i2[j])
        l2 = 0.0
        for d in range(x.shape[0]):
            dd = x[d, a] - x[d, b]
            l2 += dd * dd
        ln = np.sqrt(l2)
        lp = lprev[j]
        lprev[j] = ln
        if ln < thr[j] and ln > 0.0:
            g = (k[j] * (ln - thr[j]) + z[j] * (ln - lp)) / ln
            for d in range(x.shape[0]):
                fd = g * (x[d, a] - x[d, b])
                f[d, a] -= fd
                f[d, b] += fd


@_jit
def _planes(x, xp, f, mass, normal, offset, k, z):
    """Plane contacts, one (plane, mass) pair at a time: with the penetration
    ``p = offset - normal . x``, the force ``(k p + z (p - p_prev)) normal`` while
    ``p > 0``."""
    dim = normal.shape[0]
    for j in range(mass.size):
        m = _U(mass[j])
        p = offset[j]
        pp = offset[j]
        for d in range(dim):
            p -= normal[d, j] * x[d, m]
            pp -= normal[d, j] * xp[d, m]
        if _vform(x):           # xp holds x[n] - x[n-1]: p_prev = p + normal . xp
            pp = p
            for d in range(dim):
                pp += normal[d, j] * xp[d, m]
        if p > 0.0:
            g = k[j] * p + z[j] * (p - pp)
            for d in range(dim):
                f[d, m] += g * normal[d, j]


@_inline
def _family(x, G, r, a, s, c, j0, m0, m1, k, z, rest, lprev):
    """A dense family's links whose lower mass ``i`` is in ``[m0, m1)``: the Euclidean
    law of :func:`_euclid_piece` (parameters and length at slot ``j0 + i - a``), its
    force on the upper mass into ``G[r:r + 3, P + i]`` (``P`` the rows' leading zeros)."""
    P = _U(G.shape[1] - x.shape[1])
    for i in range(max(m0, a), min(m1, a + c)):
        j = j0 - a + i
        dx = x[0, i] - x[0, i + s]
        dy = x[1, i] - x[1, i + s]
        dz = x[2, i] - x[2, i + s]
        g = _euclid_law(dx, dy, dz, k[j], z[j], rest[j], lprev, j)
        G[r, P + i] = g * dx
        G[r + 1, P + i] = g * dy
        G[r + 2, P + i] = g * dz


@_inline
def _family_shared(x, G, r, a, s, c, j0, m0, m1, k, z, rest, lprev, pad, p0, p1):
    """:func:`_family` with one ``k``, ``z`` and rest length for the family (three loads
    fewer per link), then its padding slots' forces (``a + pad[p]``, ``p0 <= p < p1``,
    ascending) in ``[m0, m1)`` zeroed: they were computed with the shared values."""
    P = _U(G.shape[1] - x.shape[1])
    lo = max(m0, a)
    hi = min(m1, a + c)
    for i in range(lo, hi):
        j = j0 - a + i
        dx = x[0, i] - x[0, i + s]
        dy = x[1, i] - x[1, i + s]
        dz = x[2, i] - x[2, i + s]
        g = _euclid_law(dx, dy, dz, k, z, rest, lprev, j)
        G[r, P + i] = g * dx
        G[r + 1, P + i] = g * dy
        G[r + 2, P + i] = g * dz
    # the first padding slot at or after lo (bisection: the chunks run in order, one or
    # two a sample at the sizes families serve, so no pointer is kept between calls)
    end = p1
    while p0 < p1:
        mid = (p0 + p1) // 2
        if _U(pad[mid]) + a < lo:
            p0 = mid + 1
        else:
            p1 = mid
    for p in range(p0, end):
        i = _U(pad[p]) + a
        if i >= hi:
            break
        G[r, P + i] = _zero(k)
        G[r + 1, P + i] = _zero(k)
        G[r + 2, P + i] = _zero(k)


@_inline
def _pulled(G, d, i, P, o0, o1, o2):
    """The force of three families on mass ``i`` along axis ``d`` [N]: ``G[i - s] -
    G[i]`` per family (``o = P - s``; a missing family's rows are zero)."""
    return ((G[d, o0 + i] - G[d, P + i]) + (G[3 + d, o1 + i] - G[3 + d, P + i])) + \
        (G[6 + d, o2 + i] - G[6 + d, P + i])


@_inline
def _advance_pulled(x, xp, f, t2m, dim, m0, m1, port, port_f, G, fam, use_f):
    """:func:`_advance` with the families' forces pulled from ``G`` (:func:`_pulled`)
    added to ``f``'s (read and cleared only when ``use_f``: other links, contacts or
    planes wrote there)."""
    P = _U(G.shape[1] - x.shape[1])
    o0, o1, o2 = P - _U(fam[0, 1]), P - _U(fam[1, 1]), P - _U(fam[2, 1])
    if m0 <= port < m1:
        for d in range(dim):
            port_f[d] = f[d, port] + _pulled(G, d, _U(port), P, o0, o1, o2)
    for d in range(dim):
        if _vform(x):
            for i in range(m0, m1):
                F = _pulled(G, d, i, P, o0, o1, o2)
                if use_f:
                    F = f[d, i] + F
                    f[d, i] = 0.0
                v = xp[d, i] + t2m[i] * F
                xp[d, i] = v
                x[d, i] = x[d, i] + v
        else:
            for i in range(m0, m1):
                F = _pulled(G, d, i, P, o0, o1, o2)
                if use_f:
                    F = f[d, i] + F
                    f[d, i] = 0.0
                xn = x[d, i] + x[d, i] - xp[d, i] + t2m[i] * F
                xp[d, i] = x[d, i]
                x[d, i] = xn


@_inline
def _advance(x, xp, f, t2m, dim, m0, m1, port, port_f):
    """Masses ``m0 <= i < m1`` to the next sample; their forces saved for the port and
    cleared for the next sample."""
    if m0 <= port < m1:
        for d in range(dim):
            port_f[d] = f[d, port]
    if _vform(x):
        for d in range(dim):
            for i in range(m0, m1):
                v = xp[d, i] + t2m[i] * f[d, i]
                xp[d, i] = v
                x[d, i] = x[d, i] + v
                f[d, i] = 0.0
    else:
        for d in range(dim):
            for i in range(m0, m1):
                xn = x[d, i] + x[d, i] - xp[d, i] + t2m[i] * f[d, i]
                xp[d, i] = x[d, i]
                x[d, i] = xn
                f[d, i] = 0.0


@_jit
def step_nd(dim, block, x, xp, f, t2m, lin_pieces, lin_ptr, lin_k, lin_z, eu_pieces,
            eu_ptr, eu_k, eu_z, eu_rest, eu_lprev, eu_sh, eu_sk, eu_sz, eu_srest,
            eu_pad_ptr, eu_pad, W, c_i1, c_i2, c_k, c_z, c_thr, c_lprev, p_mass, p_normal,
            p_offset, p_k, p_z, dn_fam, dn_G, port, port_f):
    """One sample of the n-D scheme (module docstring).

    Parameters
    ----------
    dim : int
        The scene's dimension (1, 2 or 3): rows of ``x`` past it are zero.
    block : int
        Masses per block, as given to :func:`schedule`.
    x, xp, f : ndarray, shape (3, N)
        Positions at n and n - 1 [m] (updated to n + 1 and n), force accumulator [N]
        (zero on entry and on return).
    t2m : ndarray, shape (N,)
        ``T^2 / m`` [s^2/kg] (0: does not move).
    lin_pieces, lin_ptr, eu_pieces, eu_ptr : ndarray of int64
        The linear and Euclidean links' pieces and block pointers (:func:`schedule`).
    lin_k, lin_z : ndarray
        Linear links' ``K`` [N/m] and ``B / T`` [N/m], in stripe order.
    eu_k, eu_z, eu_rest : ndarray
        Euclidean links' ``K`` [N/m], ``B / T`` [N/m] and rest length [m], in stripe
        order (padding links: 0, 0, 0).
    eu_lprev : ndarray
        Each Euclidean link's length at the previous sample [m] (updated; start it from
        ``xp``: :func:`link_lengths`).
    eu_sh, eu_sk, eu_sz, eu_srest, eu_pad_ptr, eu_pad : ndarray
        Per Euclidean piece: its links share ``K``, ``B / T`` and rest length, their
        values, and its padding slots (:func:`shared_params`).
    W : ndarray, shape (3, block)
        Scratch (one piece's link forces).
    c_i1, c_i2, c_k, c_z, c_thr, c_lprev : ndarray, shape (C,)
        Sphere contacts: masses, ``K`` [N/m], ``B / T`` [N/m], threshold [m] and length
        at the previous sample [m] (updated).
    p_mass, p_normal, p_offset, p_k, p_z : ndarray
        Plane contacts per (plane, mass) pair: the mass (P,), the unit normal (dim, P),
        the offset [m], ``K`` [N/m] and ``B / T`` [N/m] (P,).
    dn_fam : ndarray of int64, shape (3, 4) or (0, 4)
        The dense families of Euclidean links (:func:`hapsim.kernels.layout.families`):
        ``(a, s, c, j0)`` each, their parameters and lengths in the ``eu_*`` slot arrays
        from ``j0``; a missing one ``(0, 0, 0, 0)``.
    dn_G : ndarray, shape (9, P + N) or (0, 0)
        Scratch: family ``r``'s force on the upper mass of its link from mass ``i`` in
        rows ``3 r`` to ``3 r + 2``, column ``P + i``; the first ``P >= max s`` columns
        zero (never written).
    port : int
        The mass whose force is saved in ``port_f`` (-1: none).
    port_f : ndarray, shape (3,)
        The force on ``port`` at this sample [N] (written).
    """
    _contacts(x, f, c_i1, c_i2, c_k, c_z, c_thr, c_lprev)
    _planes(x, xp, f, p_mass, p_normal, p_offset, p_k, p_z)
    n = x.shape[1]
    use_f = lin_pieces.shape[0] + eu_pieces.shape[0] + c_i1.size + p_mass.size > 0
    nq = lin_ptr.size - 1
    span = FAMILY_SPAN if dn_fam.shape[0] > 0 else 1    # blocks per advance
    for q in range(nq):
        for r in range(lin_ptr[q], lin_ptr[q + 1]):
            a = _U(lin_pieces[r, 0])
            b = _U(lin_pieces[r, 0] + lin_pieces[r, 1])
            c = _U(lin_pieces[r, 2])
            j0 = _U(lin_pieces[r, 3])
            _linear_piece(x, xp, dim, a, b, c, j0, lin_k, lin_z, W)
            _scatter(f, dim, a, b, c, W)
        for r in range(eu_ptr[q], eu_ptr[q + 1]):
            a = _U(eu_pieces[r, 0])
            b = _U(eu_pieces[r, 0] + eu_pieces[r, 1])
            c = _U(eu_pieces[r, 2])
            j0 = _U(eu_pieces[r, 3])
            if eu_sh[r]:
                _euclid_piece_shared(x, a, b, c, j0, eu_sk[r], eu_sz[r], eu_srest[r],
                                     eu_lprev, W)
                for p in range(eu_pad_ptr[r], eu_pad_ptr[r + 1]):
                    i = eu_pad[p]
                    W[0, i] = 0.0
                    W[1, i] = 0.0
                    W[2, i] = 0.0
            else:
                _euclid_piece(x, a, b, c, j0, eu_k, eu_z, eu_rest, eu_lprev, W)
            _scatter(f, dim, a, b, c, W)
        if (q + 1) % span != 0 and q != nq - 1:
            continue
        m0 = _U((q - q % span) * block)
        m1 = _U(min(n, q * block + block))
        if dn_fam.shape[0] == 0:
            _advance(x, xp, f, t2m, dim, m0, m1, port, port_f)
            continue
        for r in range(dn_fam.shape[0]):
            e = eu_pieces.shape[0] + r      # the family's entry in the shared arrays
            if e < eu_sh.size and eu_sh[e]:
                _family_shared(x, dn_G, 3 * r, _U(dn_fam[r, 0]), _U(dn_fam[r, 1]),
                               _U(dn_fam[r, 2]), _U(dn_fam[r, 3]), m0, m1, eu_sk[e],
                               eu_sz[e], eu_srest[e], eu_lprev, eu_pad, eu_pad_ptr[e],
                               eu_pad_ptr[e + 1])
            else:
                _family(x, dn_G, 3 * r, _U(dn_fam[r, 0]), _U(dn_fam[r, 1]),
                        _U(dn_fam[r, 2]), _U(dn_fam[r, 3]), m0, m1, eu_k, eu_z, eu_rest,
                        eu_lprev)
        _advance_pulled(x, xp, f, t2m, dim, m0, m1, port, port_f, dn_G, dn_fam, use_f)


@_jit
def run_nd(n, dim, block, x, xp, f, t2m, lin_pieces, lin_ptr, lin_k, lin_z, eu_pieces,
           eu_ptr, eu_k, eu_z, eu_rest, eu_lprev, eu_sh, eu_sk, eu_sz, eu_srest,
           eu_pad_ptr, eu_pad, W, c_i1, c_i2, c_k, c_z, c_thr, c_lprev, p_mass, p_normal,
           p_offset, p_k, p_z, dn_fam, dn_G, port, port_f):
    """``n`` samples of :func:`step_nd` (same arguments after ``n``).

    Parameters
    ----------
    n : int
        Samples to run, >= 0 (0: nothing changes).
    dim, block, x, ..., port_f
        As :func:`step_nd`: ``x``, ``xp``, the previous lengths (``eu_lprev``,
        ``c_lprev``) and ``port_f`` updated in place (``port_f``: the last sample's force
        on ``port`` [N]).
    """
    for _ in range(n):
        step_nd(dim, block, x, xp, f, t2m, lin_pieces, lin_ptr, lin_k, lin_z, eu_pieces,
                eu_ptr, eu_k, eu_z, eu_rest, eu_lprev, eu_sh, eu_sk, eu_sz, eu_srest,
                eu_pad_ptr, eu_pad, W, c_i1, c_i2, c_k, c_z, c_thr, c_lprev, p_mass,
                p_normal, p_offset, p_k, p_z, dn_fam, dn_G, port, port_f)


@_jit
def run_nd_listen(out, axis, mass, velocity, gain, dim, block, x, xp, f, t2m, lin_pieces,
                  lin_ptr, lin_k, lin_z, eu_pieces, eu_ptr, eu_k, eu_z, eu_rest, eu_lprev,
                  eu_sh, eu_sk, eu_sz, eu_srest, eu_pad_ptr, eu_pad, W, c_i1, c_i2, c_k,
                  c_z, c_thr, c_lprev, p_mass, p_normal, p_offset, p_k, p_z, dn_fam, dn_G,
                  port, port_f, port_x):
    """``out.shape[0]`` samples of :func:`step_nd`, recording listening points.

    Parameters
    ----------
    out : ndarray, shape (n, C)
        Written: channel ``c`` after sample ``k + 1`` is ``gain[c] * x[axis[c],
        mass[c]]``, minus ``gain[c] * xp[axis[c], mass[c]]`` where ``velocity[c]``
        (give ``gain = g / T`` for a velocity [m/s] times ``g``).
    axis, mass : ndarray of int64, shape (C,)
    velocity : ndarray of bool, shape (C,)
    gain : ndarray, shape (C,)
    port_x : ndarray, shape (3,)
        Where the port is held (set before every sample; ignored when ``port < 0``).
    dim, block, x, ..., port_f
        As :func:`step_nd`.
    """
    for k in range(out.shape[0]):
        if port >= 0:
            for d in range(dim):
                x[d, port] = port_x[d]
                if _vform(x):
                    xp[d, port] = _zero(xp[d, port])
        step_nd(dim, block, x, xp, f, t2m, lin_pieces, lin_ptr, lin_k, lin_z, eu_pieces,
                eu_ptr, eu_k, eu_z, eu_rest, eu_lprev, eu_sh, eu_sk, eu_sz, eu_srest,
                eu_pad_ptr, eu_pad, W, c_i1, c_i2, c_k, c_z, c_thr, c_lprev, p_mass,
                p_normal, p_offset, p_k, p_z, dn_fam, dn_G, port, port_f)
        for c in range(out.shape[1]):
            v = x[axis[c], mass[c]]
            if velocity[c]:
                if _vform(x):
                    v = xp[axis[c], mass[c]]
                else:
                    v -= xp[axis[c], mass[c]]
            out[k, c] = gain[c] * v


# ------------------------------------------------------------------ one-argument calls
#: The arrays of :func:`run_nd` after ``n, dim, block`` (and before ``port, port_f``), in
#: order, with their element type and number of dimensions: a context names them.
CONTEXT_ARRAYS = (
    ("x", np.float64, 2), ("xp", np.float64, 2), ("f", np.float64, 2),
    ("t2m", np.float64, 1), ("lin_pieces", np.int64, 2), ("lin_ptr", np.int64, 1),
    ("lin_k", np.float64, 1), ("lin_z", np.float64, 1), ("eu_pieces", np.int64, 2),
    ("eu_ptr", np.int64, 1), ("eu_k", np.float64, 1), ("eu_z", np.float64, 1),
    ("eu_rest", np.float64, 1), ("eu_lprev", np.float64, 1), ("eu_sh", np.bool_, 1),
    ("eu_sk", np.float64, 1), ("eu_sz", np.float64, 1), ("eu_srest", np.float64, 1),
    ("eu_pad_ptr", np.int64, 1), ("eu_pad", np.int64, 1), ("W", np.float64, 2),
    ("c_i1", np.int64, 1), ("c_i2", np.int64, 1), ("c_k", np.float64, 1),
    ("c_z", np.float64, 1), ("c_thr", np.float64, 1), ("c_lprev", np.float64, 1),
    ("p_mass", np.int64, 1), ("p_normal", np.float64, 2), ("p_offset", np.float64, 1),
    ("p_k", np.float64, 1), ("p_z", np.float64, 1), ("dn_fam", np.int64, 2),
    ("dn_G", np.float64, 2), ("port_f", np.float64, 1))
#: Context slots: samples, dimension, block, port, then (address, rows, columns) per array.
_CTX_HEAD = 4


def context(dim, block, *arrays_and_port, dtype=np.float64) -> np.ndarray:
    """The int64 context of one :func:`run_context` call per step (module
    :mod:`hapsim.kernels.pointers`): the arguments of :func:`run_nd` after ``n``.

    Parameters
    ----------
    dim, block : int
        As :func:`step_nd`.
    *arrays_and_port
        The arrays of :func:`step_nd` from ``x`` to ``dn_G`` (:data:`CONTEXT_ARRAYS`), then
        ``port`` (int) and ``port_f``; kept alive and in place by the caller.
    dtype : numpy dtype, optional
        The floating type of the state and parameters (the arrays :data:`CONTEXT_ARRAYS`
        lists as float64): ``np.float64`` (run by :func:`run_context`) or ``np.float32``
        (single precision, run by :func:`run_context32`).

    Returns
    -------
    ndarray of int64, shape (4 + 3 * 35,)
        Slot 0 the samples to run (set it before each call, 1 here), then ``dim``,
        ``block``, ``port`` and each array's address, rows and columns.

    Raises
    ------
    ValueError
        An array of another element type or number of dimensions than
        :data:`CONTEXT_ARRAYS` says, not C-ordered or not writeable.
    """
    *arrays, port, port_f = arrays_and_port
    arrays = list(arrays) + [port_f]
    if len(arrays) != len(CONTEXT_ARRAYS):
        raise ValueError(f"{len(arrays)} arrays given, {len(CONTEXT_ARRAYS)} expected")
    ctx = np.zeros(_CTX_HEAD + 3 * len(arrays), np.int64)
    ctx[:_CTX_HEAD] = (1, dim, block, port)
    if np.dtype(dtype) not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise ValueError(f"dtype must be float64 or float32, got {np.dtype(dtype)}")
    for i, (a, (name, kind, ndim)) in enumerate(zip(arrays, CONTEXT_ARRAYS)):
        if a.ndim != ndim:
            raise ValueError(f"{name}: {ndim} dimensions expected, got shape {a.shape}")
        ctx[_CTX_HEAD + 3 * i] = address(a, dtype if kind is np.float64 else kind)
        ctx[_CTX_HEAD + 3 * i + 1] = a.shape[0]
        ctx[_CTX_HEAD + 3 * i + 2] = a.shape[1] if ndim == 2 else 0
    return ctx


@_access
def _f1(c, i):
    k = _CTX_HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1],), np.float64)


@_access
def _f2(c, i):
    k = _CTX_HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1], c[k + 2]), np.float64)


@_access
def _s1(c, i):
    k = _CTX_HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1],), np.float32)


@_access
def _s2(c, i):
    k = _CTX_HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1], c[k + 2]), np.float32)


@_access
def _i1(c, i):
    k = _CTX_HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1],), np.int64)


@_access
def _i2(c, i):
    k = _CTX_HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1], c[k + 2]), np.int64)


@_access
def _b1(c, i):
    k = _CTX_HEAD + 3 * i
    return nb.carray(voidptr(c[k]), (c[k + 1],), np.bool_)


@_jit
def run_context(ctx):
    """``ctx[0]`` samples of :func:`step_nd` on the arrays a :func:`context` names: one
    argument to type and unbox per call instead of 38 (the per-sample call of a real-time
    loop; no allocation in the compiled code).

    Parameters
    ----------
    ctx : ndarray of int64
        From :func:`context` (its arrays alive and in place).
    """
    run_nd(ctx[0], ctx[1], ctx[2], _f2(ctx, 0), _f2(ctx, 1), _f2(ctx, 2), _f1(ctx, 3),
           _i2(ctx, 4), _i1(ctx, 5), _f1(ctx, 6), _f1(ctx, 7), _i2(ctx, 8), _i1(ctx, 9),
           _f1(ctx, 10), _f1(ctx, 11), _f1(ctx, 12), _f1(ctx, 13), _b1(ctx, 14),
           _f1(ctx, 15), _f1(ctx, 16), _f1(ctx, 17), _i1(ctx, 18), _i1(ctx, 19),
           _f2(ctx, 20), _i1(ctx, 21), _i1(ctx, 22), _f1(ctx, 23), _f1(ctx, 24),
           _f1(ctx, 25), _f1(ctx, 26), _i1(ctx, 27), _f2(ctx, 28), _f1(ctx, 29),
           _f1(ctx, 30), _f1(ctx, 31), _i2(ctx, 32), _f2(ctx, 33), ctx[3],
           _f1(ctx, 34))


@_jit
def run_context32(ctx):
    """:func:`run_context` on a single-precision context (``context(..., dtype=
    np.float32)``: the state and parameters float32, the same kernels compiled for them).

    Parameters
    ----------
    ctx : ndarray of int64
        From :func:`context` with ``dtype=np.float32`` (its arrays alive and in place).
    """
    run_nd(ctx[0], ctx[1], ctx[2], _s2(ctx, 0), _s2(ctx, 1), _s2(ctx, 2), _s1(ctx, 3),
           _i2(ctx, 4), _i1(ctx, 5), _s1(ctx, 6), _s1(ctx, 7), _i2(ctx, 8), _i1(ctx, 9),
           _s1(ctx, 10), _s1(ctx, 11), _s1(ctx, 12), _s1(ctx, 13), _b1(ctx, 14),
           _s1(ctx, 15), _s1(ctx, 16), _s1(ctx, 17), _i1(ctx, 18), _i1(ctx, 19),
           _s2(ctx, 20), _i1(ctx, 21), _i1(ctx, 22), _s1(ctx, 23), _s1(ctx, 24),
           _s1(ctx, 25), _s1(ctx, 26), _i1(ctx, 27), _s2(ctx, 28), _s1(ctx, 29),
           _s1(ctx, 30), _s1(ctx, 31), _i2(ctx, 32), _s2(ctx, 33), ctx[3],
           _s1(ctx, 34))
