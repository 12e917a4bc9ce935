"""Host-side layout of the n-D kernels' links (:mod:`hapsim.kernels.nd`, whose module
docstring says why): stripes of consecutive links, their pieces per block of masses, the
pieces' shared parameters, the dense families of a mesh, and the links' starting lengths.

Plain numpy, run once when an engine is built; nothing here is compiled. Units SI.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BLOCK", "stripes", "schedule", "shared_params", "link_lengths", "families",
           "euclid_layout", "family_offsets", "placed"]

#: Masses per block (and the most links in one piece): the block's rows, the scratch
#: rows and the pieces' link data stay in L1.
BLOCK = 256
#: At most this many dense families (:func:`families`): the kernels' pulled advance sums
#: three, a 3-D grid's +x, +y and +z links.
FAMILIES = 3
#: No families in a mesh of more masses: their force rows (72 bytes per mass) then stream
#: from memory beside the state, and the pieces are faster. Measured on the grid mesh of
#: ``tools/bench_nd.py`` (same runs, AMD EPYC, 1 MB L2 per core): families 5.2 against
#: 7.4 ns per mass-sample at 32,000 masses, 6.5 against 7.6 at 62,500, but 8.6-9.7
#: against 7.7-8.2 at 108,000.
FAMILY_MAX_MASSES = 80_000


def stripes(i1: np.ndarray, i2: np.ndarray, max_gap: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Group links into stripes (module docstring) and give the link order they need.

    Parameters
    ----------
    i1, i2 : ndarray of int, shape (L,)
        First and second mass of each link (``i1 != i2``; the kernels need
        ``i1 < i2``: orient the links first, the laws are symmetric).
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


def schedule(table: np.ndarray, n_masses: int, block: int = BLOCK
             ) -> tuple[np.ndarray, np.ndarray]:
    """Cut stripes into pieces by the block of their lower mass (module docstring).

    Parameters
    ----------
    table : ndarray of int64, shape (S, 4)
        Stripes (:func:`stripes`) with every offset ``s > 0``.
    n_masses : int
        Number of masses N.
    block : int, optional
        Masses per block (:data:`BLOCK`).

    Returns
    -------
    pieces : ndarray of int64, shape (P, 4)
        ``(a, s, c, j0)`` per piece (a stripe's links ``a + i`` for ``i < c``, at most
        ``block`` of them, all with ``a + i`` in one block), ordered by block.
    ptr : ndarray of int64, shape (ceil(N / block) + 1,)
        The pieces of block ``q`` are ``pieces[ptr[q]:ptr[q + 1]]``.

    Raises
    ------
    ValueError
        An offset ``s <= 0`` (a link not oriented lower index first).
    """
    n_blocks = max(1, -(-int(n_masses) // block))
    per = [[] for _ in range(n_blocks)]
    for a, s, c, j0 in np.asarray(table, np.int64).reshape(-1, 4):
        if s <= 0:
            raise ValueError(f"stripe offset {s} <= 0: orient links lower index first")
        i = 0
        while i < c:
            q = (a + i) // block
            m = min(c - i, (q + 1) * block - (a + i))
            per[q].append((a + i, s, m, j0 + i))
            i += m
    ptr = np.zeros(n_blocks + 1, np.int64)
    ptr[1:] = np.cumsum([len(p) for p in per])
    rows = [r for p in per for r in p]
    return np.array(rows, np.int64).reshape(-1, 4), ptr


def shared_params(pieces: np.ndarray, order: np.ndarray, k: np.ndarray, z: np.ndarray,
                  rest: np.ndarray) -> tuple:
    """Which pieces' real links share one stiffness, damping and rest length.

    Parameters
    ----------
    pieces : ndarray of int64, shape (P, 4)
        From :func:`schedule`.
    order : ndarray of int64
        Slot -> original link, -1 for padding (:func:`stripes`).
    k, z, rest : ndarray
        Per slot: ``K`` [N/m], ``B / T`` [N/m], rest length [m].

    Returns
    -------
    shared : ndarray of bool, shape (P,)
        The piece's real links all have the same ``(k, z, rest)`` (compared exactly).
    sk, sz, srest : ndarray, shape (P,)
        That ``k`` [N/m], ``z`` [N/m] and rest length [m] (0 where not shared).
    pad_ptr : ndarray of int64, shape (P + 1,)
        A shared piece's padding slots are ``pad[pad_ptr[r]:pad_ptr[r + 1]]``.
    pad : ndarray of int64
        Their offsets ``i`` within the piece (their forces are dropped).
    """
    P = len(pieces)
    shared = np.zeros(P, np.bool_)
    sk, sz, srest = np.zeros(P), np.zeros(P), np.zeros(P)
    pad_ptr = np.zeros(P + 1, np.int64)
    pad = []
    for r, (a, s, c, j0) in enumerate(np.asarray(pieces, np.int64).reshape(-1, 4)):
        sl = slice(j0, j0 + c)
        real = np.asarray(order[sl]) >= 0
        if real.any():
            kr, zr, rr = k[sl][real], z[sl][real], rest[sl][real]
            if np.all(kr == kr[0]) and np.all(zr == zr[0]) and np.all(rr == rr[0]):
                shared[r] = True
                sk[r], sz[r], srest[r] = kr[0], zr[0], rr[0]
                pad.extend(np.flatnonzero(~real).tolist())
        pad_ptr[r + 1] = len(pad)
    return shared, sk, sz, srest, pad_ptr, np.array(pad, np.int64)


def link_lengths(xp: np.ndarray, table: np.ndarray, n_slots: int) -> np.ndarray:
    """Each stripe slot's link length at ``xp`` [m] (the start of ``eu_lprev``).

    Parameters
    ----------
    xp : ndarray, shape (dim, N)
        Positions at the previous sample [m].
    table : ndarray of int64, shape (S, 4)
        Stripes (:func:`stripes`) or pieces (:func:`schedule`).
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




def families(i1: np.ndarray, i2: np.ndarray, n_masses: int, most: int = FAMILIES,
             fill: float = 0.5) -> tuple[np.ndarray, list]:
    """The dense families of a mesh's links: offsets ``s`` whose links ``(i, i + s)``
    cover at least a quarter of the masses, filling at least ``fill`` of their span (none
    in a mesh of more than :data:`FAMILY_MAX_MASSES` masses).

    A family's links are computed into one force row per axis indexed by their lower mass,
    and each mass's force is then *pulled* from those rows (``G[i - s] - G[i]``) as the
    mass advances: no scatter of the forces into a per-mass accumulator (the module
    docstring of :mod:`hapsim.kernels.nd`, 'Families').

    Parameters
    ----------
    i1, i2 : ndarray of int, shape (L,)
        Lower and upper mass of each link (``i1 < i2``).
    n_masses : int
        Number of masses N.
    most : int, optional
        At most this many families, the largest first (:data:`FAMILIES`).
    fill : float, optional
        Least fraction of real links over the family's span (its holes become padding
        slots with zero parameters).

    Returns
    -------
    table : ndarray of int64, shape (F, 4)
        ``(a, s, c, j0)`` per family, as a stripe: links ``a + i`` -- ``a + s + i`` for
        ``i < c``, slots from ``j0 = 0`` for the first family, one after another.
    members : list of ndarray of int64
        Each family's links (indices into ``i1``), in the order of ``table``.
    """
    i1 = np.asarray(i1, np.int64)
    s = np.asarray(i2, np.int64) - i1
    rows, members, j0 = [], [], 0
    if n_masses > FAMILY_MAX_MASSES or not s.size:
        return np.zeros((0, 4), np.int64), members
    offs, counts = np.unique(s, return_counts=True)
    for off in offs[np.argsort(-counts, kind="stable")]:
        sel = np.flatnonzero(s == off)
        lo = i1[sel]
        a, c = int(lo.min()), int(lo.max() - lo.min() + 1)
        if len(rows) == most or 4 * sel.size < n_masses:
            break
        if sel.size < fill * c or np.unique(lo).size != lo.size:   # sparse, or two
            continue                                               # links on one pair
        rows.append((a, int(off), c, j0))
        members.append(sel[np.argsort(lo)])
        j0 += c
    return np.array(rows, np.int64).reshape(-1, 4), members


def euclid_layout(i1: np.ndarray, i2: np.ndarray, n_masses: int, block: int = BLOCK,
                  dense: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                np.ndarray]:
    """The Euclidean links' layout: dense families (:func:`families`) and the rest as
    stripes cut into pieces per block (:func:`stripes`, :func:`schedule`).

    Parameters
    ----------
    i1, i2, n_masses
        As :func:`families`.
    block : int, optional
        Masses per block.
    dense : bool, optional
        Look for dense families (False: every link in pieces, the layout before them).

    Returns
    -------
    pieces, ptr : ndarray of int64
        The non-family links' pieces and block pointers (:func:`schedule`).
    fam : ndarray of int64, shape (F, 4)
        ``(a, s, c, j0)`` per family, ``j0`` in the slot arrays (after the pieces' slots).
    order : ndarray of int64
        Slot -> link (index into ``i1``), -1 for a padding slot.
    """
    i1 = np.asarray(i1, np.int64)
    i2 = np.asarray(i2, np.int64)
    fam, members = families(i1, i2, n_masses) if dense else (np.zeros((0, 4), np.int64), [])
    rest = np.ones(i1.size, bool)
    for sel in members:
        rest[sel] = False
    idx = np.flatnonzero(rest)
    if idx.size:
        table, order = stripes(i1[idx], i2[idx])
        order = np.where(order >= 0, idx[np.maximum(order, 0)], -1)
    else:
        table, order = np.zeros((0, 4), np.int64), np.zeros(0, np.int64)
    pieces, ptr = schedule(table, n_masses, block)
    slots = [order]
    for (a, _, c, _), sel in zip(fam, members):
        o = np.full(c, -1, np.int64)
        o[i1[sel] - a] = sel
        slots.append(o)
    fam = fam.copy()
    fam[:, 3] += order.size
    return pieces, ptr, fam, np.concatenate(slots)


#: Bytes of a page: a load is compared with the stores in flight by its address modulo this
#: (the low 12 bits) before its full address is known ("4K aliasing").
PAGE = 4096
#: A store this many bytes or fewer ahead of a load, modulo :data:`PAGE`, in the same
#: loop, makes the load wait as if it depended on the store (four 512-bit vectors). Fitted
#: on the grid mesh of ``tools/bench_nd.py`` (5,016 masses, 80 random placements of the
#: state, families' force rows and lengths, each timed twice, pass-to-pass correlation
#: 0.96): placements with at most 3 such (load, store) pairs ran 4.42 to 4.48 ns per
#: mass-sample, with 10 or more 4.66 to 5.59.
ALIAS_WINDOW = 256
#: The arrays :func:`family_offsets` places, as the families' loops stream them.
PLACED = ("x", "xp", "t2m", "G", "lprev", "k", "z", "rest")


def _family_streams(n, fam, P, itemsize, off, shared):
    """The (loads, stores) byte addresses at ``i = 0`` of each loop of the families'
    kernels (:func:`hapsim.kernels.nd.step_nd`: one link loop per family, one advance
    loop per axis) for array start offsets ``off`` (a missing name is not counted)."""
    rx, rg = itemsize * n, itemsize * (P + n)
    loops = []

    def at(name, d):
        return None if name not in off else off[name] + d

    for r, (a, s, _, j0) in enumerate(fam):
        j = itemsize * (j0 - a)
        loads = [at("x", q * rx) for q in range(3)] + \
            [at("x", q * rx + itemsize * s) for q in range(3)] + [at("lprev", j)]
        if not shared:
            loads += [at(name, j) for name in ("k", "z", "rest")]
        stores = [at("lprev", j)] + [at("G", (3 * r + q) * rg + itemsize * P)
                                     for q in range(3)]
        loops.append((loads, stores))
    for d in range(3):
        loads = [at("x", d * rx), at("xp", d * rx), at("t2m", 0)]
        for r, (_, s, _, _) in enumerate(fam):
            loads += [at("G", (3 * r + d) * rg + itemsize * P),
                      at("G", (3 * r + d) * rg + itemsize * (P - s))]
        loops.append((loads, [at("xp", d * rx), at("x", d * rx)]))
    return loops


def _aliases(loops) -> int:
    """(load, store) pairs of one loop whose store is 1 to :data:`ALIAS_WINDOW` bytes
    ahead of the load modulo :data:`PAGE`."""
    count = 0
    for loads, stores in loops:
        for ld in loads:
            for st in stores:
                if ld is not None and st is not None and \
                        0 < (st - ld) % PAGE <= ALIAS_WINDOW:
                    count += 1
    return count


def family_offsets(n_masses: int, fam: np.ndarray, P: int, itemsize: int = 8,
                   shared: bool = True) -> dict:
    """Where in a page each array the dense families stream should start, so that few of
    their loops' loads alias a store in flight (:data:`ALIAS_WINDOW`).

    A load whose address matches an earlier store's modulo 4,096 bytes waits for it even
    when the addresses differ (the processor compares the low 12 bits first): with the
    families' 13 to 17 streams per loop, where the arrays happen to start in their pages
    moved the grid mesh's sample time by 20 % (``tools/bench_nd.py``'s 5,016-mass mesh,
    4.43 to 5.44 ns per mass-sample over 40 placements, each reproduced within 1 %).
    The offsets are chosen greedily, in :data:`PLACED` order from ``x`` at 0, each the
    first multiple of 64 bytes with the fewest aliasing pairs among the arrays placed so
    far (:func:`_aliases`); deterministic, a few milliseconds.

    Parameters
    ----------
    n_masses : int
        Columns N of the state rows (3, N).
    fam : ndarray of int64, shape (F, 4)
        The families ``(a, s, c, j0)`` (:func:`families`, ``j0`` in the slot arrays).
    P : int
        Leading columns of the families' force rows (shape (9, P + N)).
    itemsize : int, optional
        Bytes per element (8 in double precision, 4 in single).
    shared : bool, optional
        The families read one stiffness, damping and rest length each (no per-link
        ``k``, ``z``, ``rest`` streams).

    Returns
    -------
    dict
        Byte offset from a page boundary (a multiple of 64, below :data:`PAGE`) per name
        of :data:`PLACED`.
    """
    fam = np.asarray(fam, np.int64).reshape(-1, 4).tolist()
    off = {"x": 0}
    for name in PLACED[1:]:
        best = None
        for o in range(0, PAGE, 64):
            c = _aliases(_family_streams(n_masses, fam, P, itemsize, {**off, name: o},
                                         shared))
            if best is None or c < best[0]:
                best = (c, o)
        off[name] = best[1]
    return off


def placed(a: np.ndarray, offset: int) -> np.ndarray:
    """A C-contiguous copy of ``a`` starting ``offset`` bytes after a page boundary.

    Parameters
    ----------
    a : ndarray
        The values (any shape and type).
    offset : int
        Bytes, ``0 <= offset < PAGE`` (:func:`family_offsets`).

    Returns
    -------
    ndarray
        Same shape, type and values; a view into a buffer one page longer (kept alive by
        the view's ``base``).
    """
    a = np.asarray(a)
    buf = np.empty(a.nbytes + PAGE + offset, np.uint8)
    start = (-buf.ctypes.data) % PAGE + offset
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out
