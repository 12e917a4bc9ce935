"""The wire's term of the n-D felt matrices beyond first order: the first-order worst
case taken at the records and at the worst errors of every statement within the errors'
bounds, the largest with a margin stated (:func:`box_worst_case`).

Why. The felt matrices are fitted by a vector linear prediction
(:func:`hapsim.analysis.pencil.fit_felt_nd`) whose regression is nearly rank deficient:
the loop's fast modes (the hold's, the delay's) die out within a few samples, so its
smallest singular values are 1e-10 to 1e-9 m against readings rounded to 5e-8 m. Errors
within the bounds then move the fit far outside the region where its first-order
sensitivity (:func:`hapsim.analysis.pencil.felt_sensitivity_nd`) holds: measured on the
2DIY's wall with random joint inertia, friction, wall and delay (``tests/test_wire_box.py``,
seeded loops, reading errors of half a count at 2^20 to 2^22 counts per revolution), the
sensitivity at a point of the error box was up to 13 times the one at the records, and
errors found by re-linearising at the perturbed records moved a stated felt damping entry
1.5 times the first-order worst case stated at the records (0.33 against 0.22 relative,
inside the measurable limit of 0.25): a "differs" could be wrong.

What is stated. For a felt entry ``o(x)`` of the records ``x`` and errors ``u`` in the box
``|u| <= bounds`` entering through the loop's responses ``H`` (``x + H u``), the mean
value theorem on the segment from ``x`` to ``x + H u`` gives
``|o(x + H u) - o(x)| <= sup_{v in box} sum |(s(x + H v) * H)[o]| bounds``: the first-order
worst case (Hoelder's, :func:`hapsim.analysis.pencil.worst_case_nd`) taken at the worst
point of the box, not at the records alone (the truth is the records less errors inside
the same box, so the same bound holds from the records back to it). The supremum is not
computed exactly; it is sampled at the records and at each statement's worst errors for
the first-order map at the records, ``u_o = bounds sign((s * H)[o])`` (the point where
that statement's change is largest to first order), and the largest, times
:data:`BOX_MARGIN`, is stated: a sample of the supremum is no bound on it.

The fit's branch (issue 29: the term 3e4 to 1.4e5 relative on the 2DIY's wall-clock
records kept in time). The fit renders the first ``n`` complex pairs of its ``n p``
poles; those of the loop's fast modes carry nothing the records hold above their errors
(their RMS amplitude at the handle at most 1.42 times the readings' bound on the 2DIY's
records, :func:`hapsim.analysis.pencil.mode_amplitudes`), so the errors alone place them,
anywhere. Taken by ``|z|`` alone, such a noise pair was rendered wherever it outranked a
pair of the loop, and the felt matrices there were no mode's: captured beside two busy
processes (records cut at host stalls to 18-39 rows a record), at the records the fit was
right (the first-order term 0.15) while at one entry's worst errors in the box (moved at
most 2.4e-7 m) a noise pair went to ``z = -0.975 + 0.284j`` (``|z| = 1.016``, near the
Nyquist frequency) and outranked the slow pair (``|z| = 0.996``): the felt stiffness's
(2, 2) entry there 2.8e5 N/m against 1.2e3, a term of 5.6e3; in another run the slow pair
was missing from the stretches at the records already (three singular values of the
regression above its noise, not four: the first-order term 4.5e4). Neither the
regression's conditioning, the write-timing correction's ``H`` nor the units: the term was
the real sensitivity of a selection that jumps. Now a pair whose size in the records is
within :data:`hapsim.analysis.pencil.MODE_FLOOR` times the readings' bound is never
rendered (``floor``, at the records and at every point sampled): the first run's term
falls to 0.62 (the stiffness along one direction stated), and where a point of the box
leaves fewer than ``n`` pairs of the loop (a pair turned real, 1.052 and 0.899, or below
the floor) nothing is stated (term inf): the records, within their errors, do not
determine that pair, which is what the cut stretches of a loaded host give.

Where it is taken. The box is an adversary's errors: every sign pattern within the
bounds. For errors that are no rounding (the 2DIY's estimated samples, its write timing)
that is the term; a device's rounding is not chosen so, and the Falcon's and the 2DIY's
verdicts take it by draws of its phase through the loop instead
(:mod:`hapsim.analysis.wire_rounding`: on configs/falcon_spring.yaml the box's term is
hundreds of times what rounding does). The Hapkit pantograph firmware's and the two
faders' verdicts still take their rounding over the box.
"""

from __future__ import annotations

import numpy as np

__all__ = ["box_worst_case", "moved_records", "statement_terms", "BOX_MARGIN"]

#: The factor over the sampled supremum that is stated [-]. Measured over 40 seeded loops
#: (the 2DIY's wall with its joint inertia, friction, wall, press spring and delay drawn,
#: ``tests/test_wire_box.py``'s ``_loop`` family, seeds 0-9, ``a`` 2e-5 to 1e-4 m, 150 or
#: 300 samples, half a count at 2^20 to 2^22 counts per revolution): the largest change
#: that refits found (each statement's worst errors re-linearised three times at the
#: records they moved, random errors uniform and at the box's corners) was 1.27 times the
#: sampled supremum of a component it stated (seed 9, 1e-4 m, 300 samples, 2^20: a term of
#: 0.2, near the measurable limit, where the fit is least linear; 0.54 for terms under
#: 0.1). Times 2 the worst is 0.40 of what is stated, a margin of 2.5 over the search;
#: 171 of the 262 components the first-order term stated are then stated.
BOX_MARGIN = 2.0


def moved_records(records, inputs, *, rest_last: bool = False) -> list:
    """The records moved by error inputs through the loop.

    Parameters
    ----------
    records : list of ndarray, each shape (N, n)
        The records as fitted [m]: free responses, or their differences against the
        record from rest (``rest_last``).
    inputs : list of (ndarray, list of ndarray)
        Per error kind ``(H, u)``: ``H`` shape (L, n, m) the records' response to a unit
        error [m per unit], ``u`` one (N, m) array per record of the errors [unit] (with
        ``rest_last``, one more: the record from rest's, whose change enters every
        difference with a minus sign).
    rest_last : bool, optional
        ``records`` are differences against a record from rest.

    Returns
    -------
    list of ndarray, each shape (N, n)
        ``records[r] + sum_kinds (H * u_r)`` (causal convolution), less the rest record's
        change with ``rest_last``.
    """
    from hapsim.analysis.fftconv import fast_length
    N, n = records[0].shape
    count = len(records) + int(rest_last)
    dx = [np.zeros((N, n)) for _ in range(count)]
    for H, us in inputs:
        H = np.asarray(H, float)
        L = min(N, H.shape[0])
        m = H.shape[2]
        # hapsim.analysis.fftconv.fftconvolve(u_r[:, j], H[:L, c, j])[:N] for every r, c
        # and j, its steps on the same lines: each transform, product and inverse is
        # taken line by line (pocketfft's transforms, numpy's product), so one call over
        # the stacked lines gives the same bits as one call per line
        F = [fast_length(N + L - 1)]
        U = np.fft.rfftn(np.stack([np.broadcast_to(np.asarray(u, float), (N, m)).T
                                   for u in us]), F, axes=[2])          # (R, m, F/2+1)
        Hf = np.fft.rfftn(H[:L].transpose(1, 2, 0), F, axes=[2])        # (n, m, F/2+1)
        conv = np.fft.irfftn(U[:, None] * Hf[None], F, axes=[3])        # (R, n, m, F)
        for r in range(len(us)):
            for c in range(n):
                for j in range(m):
                    dx[r][:, c] += conv[r, c, j, :N]
    if rest_last:
        return [x + d - dx[-1] for x, d in zip(records, dx[:-1])]
    return [x + d for x, d in zip(records, dx)]


def box_worst_case(terms_at, records, *, rest_last: bool = False, settled=None):
    """The first-order worst case of every felt statement, at the records and at each
    statement's worst errors, the largest per statement times :data:`BOX_MARGIN`
    (module notes: the mean value theorem's bound, its supremum over the error box
    sampled).

    With ``settled`` the sampling may stop early: the stated term of a statement only
    grows as points are added (a maximum), so once every statement's term already exceeds
    what its caller asks about (a statement beyond the limit of a statement is not made,
    whatever the points not sampled), the rest cannot change that answer. The points of
    the statements not yet settled are sampled first. Without an early stop the result
    is the same maximum over the same points (bit for bit: ``np.maximum`` is exact).

    Parameters
    ----------
    terms_at : callable
        ``terms_at(records) -> (wc, kinds)`` or None: at the given records, ``wc``
        shape (O,) the first-order worst case of each of the ``O`` statements (felt
        entries and directional forms, their own units), and ``kinds`` a list of
        ``(H, filtered, bounds)`` per error kind: ``H`` shape (L, n, m), ``filtered`` per
        record the (O, N, m) sensitivity through the loop
        (:func:`hapsim.analysis.pencil.filtered_sensitivity_nd`), ``bounds`` per record
        (N, m) or (m,); None when the records give no felt matrices.
    records : list of ndarray, each shape (N, n)
        The records as fitted [m].
    rest_last : bool, optional
        As :func:`moved_records` (``filtered`` and ``bounds`` then hold the rest record
        last).
    settled : callable, optional
        ``settled(stated) -> ndarray of bool, shape (O,)``: per statement, whether the
        stated term so far (:data:`BOX_MARGIN` times the sampled supremum, shape (O,))
        already answers its caller's question (e.g. beyond the limit of a statement).
        The sampling stops once every statement is settled.

    Returns
    -------
    (ndarray, ndarray) or None
        The first-order worst case at the records and the largest over the sampled
        points times :data:`BOX_MARGIN` (what is stated), each shape (O,); None when the
        records (or a moved copy of them) give no felt matrices: nothing can be stated.
        With ``settled``, a third item: ``complete`` (bool, every point sampled; False:
        stopped early, the terms lower bounds of the full sampling's).
    """
    got = terms_at(records)
    if got is None:
        return None
    wc0, kinds = got
    wc0 = np.asarray(wc0, float)
    sup = wc0.copy()
    left = list(range(wc0.size))
    complete = True
    sampled = set()
    while left:
        o = left[0]
        if settled is not None:
            done = np.asarray(settled(BOX_MARGIN * sup), bool)
            if done.all():
                complete = False
                break
            o = next((i for i in left if not done[i]), o)
        left.remove(o)
        inputs = [(H, [np.broadcast_to(np.asarray(b, float), S[o].shape) * np.sign(S[o])
                       for S, b in zip(fil, bounds)]) for H, fil, bounds in kinds]
        # a point already sampled (two statements whose worst errors are the same, e.g.
        # the two off-diagonal entries of a symmetric felt matrix): the same terms again,
        # and np.maximum with them changes nothing
        point = tuple(u.tobytes() for _, us in inputs for u in us)
        if point in sampled:
            continue
        sampled.add(point)
        moved = terms_at(moved_records(records, inputs, rest_last=rest_last))
        if moved is None:
            return None
        sup = np.maximum(sup, np.asarray(moved[0], float))
    if settled is None:
        return wc0, BOX_MARGIN * sup
    return wc0, BOX_MARGIN * sup, complete


def statement_terms(sens, directions, plan):
    """The first-order worst case of every felt statement and each error kind's filtered
    sensitivity: what :func:`box_worst_case`'s ``terms_at`` returns.

    Parameters
    ----------
    sens : list of ndarray, each shape (2, n, n, N, n)
        Per record, :func:`hapsim.analysis.pencil.felt_sensitivity_nd`'s (the rest
        record's appended by a caller fitting differences).
    directions : ndarray, shape (n, n)
        The principal directions ``e_i`` (columns).
    plan : list of (ndarray, list)
        Per error kind ``(H, bounds)``: the response (L, n, m) and per record its bounds,
        (N, m) or (m,).

    Returns
    -------
    (ndarray, list)
        ``wc`` shape (2 n^2 + 2 n,): Hoelder's worst case of the felt entries [N/m],
        [N s/m], then of ``e_i^T k e_i`` and ``e_i^T b e_i``
        (:func:`hapsim.analysis.pencil.worst_case_nd`); and per kind ``(H, filtered,
        bounds)``, ``filtered`` per record the (O, N, m) sensitivity through the loop.
    """
    from hapsim.analysis.pencil import filtered_sensitivity_nd
    E = np.asarray(directions, float)
    n = E.shape[0]
    N = sens[0].shape[-2]
    # the entries, then the directional forms: one worst case over all of them
    comb = [np.concatenate([s.reshape(2 * n * n, N, n),
                            np.einsum("ai,bi,qabtc->qitc", E, E, s).reshape(2 * n, N, n)])
            for s in sens]
    wc, out = 0.0, []
    for H, b in plan:
        fil = filtered_sensitivity_nd(comb, H)
        wc = wc + sum(np.einsum("otj,tj->o", np.abs(S), np.broadcast_to(
            np.asarray(e, float), S.shape[1:])) for S, e in zip(fil, b))
        out.append((H, fil, b))
    return wc, out
