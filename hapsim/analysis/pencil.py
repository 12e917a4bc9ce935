"""The poles of sampled free responses and what they give: one coordinate by the matrix
pencil (its modes, its rendered pair), n coordinates by vector linear prediction (the felt
stiffness and damping matrices).

Method: the total-least-squares matrix pencil of Y. Hua and T. K. Sarkar, "Matrix pencil
method for estimating parameters of exponentially damped/undamped sinusoids in noise",
IEEE Trans. ASSP 38(5), 1990. For ``y[n] = sum_i c_i z_i^n`` (``n = 0 .. N-1``, ``M``
poles) the Hankel matrix ``Y[r, j] = y[r + j]`` (``N - L`` rows, ``L + 1`` columns, pencil
parameter ``L``) has rank ``M``; its ``M`` dominant right singular vectors ``V`` span the
Vandermonde columns ``[z_i^j]_j``, so with ``V1 = V[:-1]`` and ``V2 = V[1:]`` the
eigenvalues of ``pinv(V1) V2`` are the ``z_i``. On exact data of a linear system of
order ``M`` the poles are recovered to round-off; with noise the SVD truncation is a
least-squares filter.

Constant offsets
----------------
A constant in ``y`` (e.g. an equilibrium that is not at 0, or an encoder offset) is a pole
at ``z = 1``. With ``offset=True`` the signal is first *differenced*,
``dy[n] = y[n+1] - y[n] = sum_i c_i (z_i - 1) z_i^n``: every pole ``z_i != 1`` keeps its
value exactly and the constant disappears exactly. Removing the mean instead would not
be exact (the mean of a finite decaying record is not the offset, so a residual constant
would remain as a spurious pole), which is why it is not used. A genuine mode at
``z = 1`` (a free rigid-body drift) cannot be identified with ``offset=True``.

n coordinates: the felt matrices
--------------------------------
The n-D counterpart (:func:`fit_felt_nd`): a free response of a linear loop of state size
``n p`` seen through the ``n`` handle coordinates obeys a vector linear prediction
(multichannel Prony; a vector autoregression of order ``p``)
``y[k] = sum_{j=1..p} C_j y[k-j]``, exactly when the loop is observable from the handle
with observability index ``p``. Its companion matrix has the loop's poles as eigenvalues
and, in the first block of its eigenvectors, the handle mode shapes; the felt matrices
follow from them as for the prediction (:func:`hapsim.analysis.ths.felt_matrices`, the
inverse quadratic eigenvalue problem). Several records (free responses from different
initial states) are fitted together, so every mode is excited. The fit's first-order
sensitivity to the records (:func:`felt_sensitivity_nd`) and its worst case under bounded
errors (:func:`worst_case_nd`) bound what the wire's errors can do to the measurement.

A common equilibrium ``c`` (records of absolute handle positions, not differences against
a record from rest) is taken by an affine prediction, ``offset=True``:
``y[k] - c = sum_j C_j (y[k-j] - c)``, i.e. ``y[k] = sum_j C_j y[k-j] + g`` with
``g = (I - sum_j C_j) c`` one more unknown per coordinate, shared by every record and
stretch (the vector autoregression with intercept, whose mean is
``(I - sum_j C_j)^-1 g``: H. Luetkepohl, *New Introduction to Multiple Time Series
Analysis*, 2005, Sec. 2.1.1 and 3.2). On exact data of the loop it holds exactly (as
the differencing of the 1-D fit does), and it costs no row of a stretch: a first
difference would cost each stretch one equation, and subtracting a record from rest
would leave only the rows usable in both records (each record's cuts made the other's
too).
:mod:`hapsim.analysis.ths` is imported on call (importing :mod:`hapsim.analysis` does
not load it).
"""

from __future__ import annotations

import numpy as np

from hapsim.analysis.modes import Mode, modes_from_poles, rendered_pair
from hapsim.errors import ConfigError

__all__ = ["pencil_poles", "fit_modes", "fit_rendered", "thin_pencil", "RANK_TOL",
           "fit_felt_nd", "felt_sensitivity_nd", "worst_case_nd",
           "filtered_sensitivity_nd", "companion", "ar_poles", "mode_amplitudes",
           "MODE_FLOOR"]


#: Singular values of the Hankel matrix below ``RANK_TOL`` times the largest are round-off:
#: the model order is cut to the numerical rank (Sarkar & Pereira, "Using the matrix pencil
#: method to estimate the parameters of a sum of complex exponentials", IEEE Antennas Prop.
#: Mag. 37(1), 1995: keep the singular values above ``10^-p`` of the largest, ``p`` the
#: significant digits of the data; double-precision records hold ~15). A long record of a
#: slow mode whose fast companions died out in its first samples has rank 2, not the loop's
#: ``d + 3``: the extra singular vectors are noise and their pencil eigenvalues spurious
#: poles, some outside the unit circle, taken for the least damped pair.
RANK_TOL = 1e-12

#: The factor over the records' error bound [-] at or below which a fitted mode's size in
#: the records (its RMS amplitude at the handle over the rows fitted,
#: :func:`mode_amplitudes`) is taken as not determined by them: such a pair is never taken
#: for a rendered one (:func:`fit_felt_nd`'s ``floor``). A vector prediction of order
#: ``p`` has ``n p`` poles; the loop's fast ones (the hold's, the delay's) die out within
#: a few samples, so some of the fit's poles are set by the readings' errors alone and may
#: lie anywhere, outside the unit circle too (issue 29: a noise pair moved to
#: ``|z| = 1.016`` near the Nyquist frequency by errors within half a count outranked the
#: true rendered pair by ``|z|`` and made the 2DIY's box term 5.6e3 relative). Measured,
#: in units of the bound at the handle (half a count through ``|J|``, twice in a
#: difference): on 85 records of the 2DIY's wall (``configs/pantograph_wall.yaml``, 2^22
#: counts per revolution, on the wall clock beside busy processes and on a simulated
#: clock with write jitter) the noise pairs at most 1.42, the rendered pairs at least 73;
#: on the seeded loops of ``tests/test_wire_box.py`` at each entry's worst errors (25
#: rows, a = 2e-5 m, 2^20 to 2^22 counts) the noise pairs at most 0.60, the loop's pairs
#: at least 9.2 (150 rows at 1e-4 m: 0.18 and 27). 3.5 leaves a factor 2.5 over the
#: largest noise pair and 2.6 under the smallest pair of the loop. A pair of the loop
#: under it leaves fewer than n pairs: no felt matrices, "not measurable", never a wrong
#: statement.
MODE_FLOOR = 3.5


def mode_amplitudes(z, V, states, n: int) -> np.ndarray:
    """Each mode's size in the records: the RMS over the rows fitted of its modal
    coordinate times the norm of its handle shape [m].

    The states ``s_k`` (the lagged samples of each equation, about the equilibrium) are
    decomposed on the eigenvectors, ``s_k = sum_i w_ik v_i``; mode ``i`` contributes
    ``w_ik v_i[:n]`` to the handle's position, whose RMS over ``k`` is returned: the
    modal amplitude a mode indicator of the eigensystem realisation ranks modes by
    (J.-N. Juang and R. S. Pappa, "An eigensystem realization algorithm for modal
    parameter identification and model reduction", J. Guidance 8(5), 1985, Sec. IV:
    noise modes carry no amplitude the records hold above their errors).

    Parameters
    ----------
    z : ndarray of complex, shape (B, N)
        The poles of each of ``B`` companion matrices (unused but for the shape).
    V : ndarray of complex, shape (B, N, N)
        Their eigenvectors (columns), the handle's ``n`` coordinates first.
    states : ndarray, shape (K, N)
        The ``K`` states of the rows fitted [m].
    n : int
        Handle coordinates.

    Returns
    -------
    ndarray, shape (B, N)
        [m]; a matrix whose eigenvectors are singular gets inf (every mode kept).
    """
    V = np.asarray(V)
    X = np.asarray(states, float).T
    out = np.full(np.asarray(z).shape, np.inf)
    for b in range(V.shape[0]):
        try:
            W = np.linalg.solve(V[b], X)                         # (N, K)
        except np.linalg.LinAlgError:
            continue
        out[b] = np.linalg.norm(V[b, :n], axis=0) * np.sqrt(np.mean(np.abs(W) ** 2, axis=1))
    return out


def _determined(states, n: int, floor):
    """``keep`` for :func:`hapsim.analysis.ths.rendered_pairs_of`: the poles whose
    :func:`mode_amplitudes` exceed ``floor`` [m] (None: every pole)."""
    if floor is None:
        return None
    return lambda z, V: mode_amplitudes(z, V, states, n) > float(floor)


def _states(R, Ca, n: int, p: int, offset: bool):
    """The fitted rows' states about the fitted equilibrium (the regression's lagged
    samples, less the equilibrium relative to the reference with ``offset``)."""
    X = R[:, :n * p]
    if not offset:
        return X
    A = np.eye(n) - Ca[:n * p].reshape(p, n, n).sum(axis=0).T
    try:
        c = np.linalg.solve(A, Ca[n * p])
    except np.linalg.LinAlgError:
        return X
    return X - np.tile(c, p)


def _validate(y, period: float, order: int, offset: bool, pencil: int | None):
    y = np.asarray(y, dtype=float)
    if y.ndim != 1:
        raise ConfigError(f"the signal must be one-dimensional, got shape {y.shape}", key="y")
    if not np.all(np.isfinite(y)):
        raise ConfigError("the signal contains NaN or infinite samples", key="y")
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1:
        raise ConfigError(f"must be a whole number >= 1, got {order!r}", key="order")
    if not (np.isfinite(period) and period > 0):
        raise ConfigError(f"must be a positive number [s], got {period!r}", key="period")
    if offset:
        y = np.diff(y)
    n = y.size
    need = 2 * int(order) + 2
    if n < need:
        raise ConfigError(
            f"signal too short: {n} usable samples for a model of order {order}; "
            f"at least {need} are needed (2 * order + 2"
            f"{', after differencing for offset=True' if offset else ''})", key="y")
    if pencil is None:
        # Hua & Sarkar: N/3 <= L <= N/2 is the low-variance range for noisy data.
        pencil = max(int(order), n // 3)
    if not (order <= pencil <= n - order - 1):
        raise ConfigError(f"pencil parameter must satisfy order <= L <= N - order - 1 = "
                          f"{n - order - 1}, got {pencil}", key="pencil")
    if not np.any(y):
        raise ConfigError("the signal is identically zero (nothing to identify)", key="y")
    return y, int(pencil)


def thin_pencil(order: int, n: int) -> int:
    """Pencil parameter for long records: ``min(max(order, n // 3), max(10 order, 60))``.

    Hua & Sarkar's ``N/3`` is the low-variance choice for noisy data but makes the Hankel
    matrix square-ish (an SVD of seconds on a loaded machine for ``N = 1000``); a thin
    Hankel with ``max(10 order, 60)`` columns is exact on noise-free data and cheap, and
    the noisy case is refined by least squares (:func:`measure_felt`) anyway.

    Parameters
    ----------
    order : int
        Model order.
    n : int
        Usable samples (after differencing).

    Returns
    -------
    int
        The pencil parameter L.
    """
    return min(max(int(order), n // 3), max(10 * int(order), 60))


def pencil_poles(y, order: int, *, offset: bool = False, pencil: int | None = None,
                 period: float = 1.0) -> np.ndarray:
    """Discrete poles of a sampled signal by the matrix pencil method (Hua & Sarkar 1990).

    Parameters
    ----------
    y : array_like of float, shape (n,)
        Uniformly sampled free response (any unit).
    order : int >= 1
        Model order ``M``: the number of poles (a complex pair counts 2).
    offset : bool, default False
        Difference the signal first so that a constant offset drops out exactly (see the
        module docstring).
    pencil : int, optional
        Pencil parameter ``L`` with ``order <= L <= N - order - 1``; default
        ``max(order, N // 3)``.
    period : float > 0, default 1.0
        Only validated here [s] (kept for a uniform signature).

    Returns
    -------
    ndarray of complex, shape (M,)
        The identified poles ``z_i`` (closed under conjugation: the pencil matrix is real),
        ``M = min(order, numerical rank)``: singular values below :data:`RANK_TOL` of the
        largest do not count (modes the record holds only at round-off).

    Raises
    ------
    ConfigError
        If the signal is not 1-D or not finite, identically zero, shorter than
        ``2 * order + 2`` usable samples, or ``order`` / ``pencil`` are invalid.
    """
    y, L = _validate(y, period, order, offset, pencil)
    n = y.size
    # Hankel matrix, (n - L) x (L + 1): row r is y[r : r + L + 1].
    idx = np.arange(n - L)[:, None] + np.arange(L + 1)[None, :]
    Y = y[idx]
    _, sv, vh = np.linalg.svd(Y, full_matrices=False)
    order = max(1, min(int(order), int(np.count_nonzero(sv > RANK_TOL * sv[0]))))
    V = vh[:order, :].T                     # (L + 1) x M, dominant right singular vectors
    V1, V2 = V[:-1, :], V[1:, :]
    A = np.linalg.lstsq(V1, V2, rcond=None)[0]   # pinv(V1) @ V2, M x M, real
    return np.linalg.eigvals(A).astype(complex)


def fit_modes(y, period: float, order: int, mass: float, *, offset: bool = False,
              pencil: int | None = None) -> list[Mode]:
    """Identify the modes of a sampled free response.

    Parameters
    ----------
    y : array_like of float, shape (n,)
        Position samples ``x[n] = x(nT)`` of the free (unforced) closed loop [m]; skip the
        first samples if the loop has dead-beat (``z = 0``) states excited at the start.
    period : float > 0
        Sample period ``T`` [s].
    order : int >= 1
        Model order: number of non-zero poles excited in ``y`` (a pair counts 2).
    mass : float > 0
        Real mass ``m`` [kg] used to express each pole as ``k = m |s|^2`` [N/m] and
        ``b = -2 m Re(s)`` [N s/m] (docs/design.md, 'The inverse map').
    offset : bool, default False
        The signal has a constant offset: difference it first (exact, module docstring).
    pencil : int, optional
        Pencil parameter (see :func:`pencil_poles`).

    Returns
    -------
    list of Mode
        As :func:`hapsim.analysis.modes.modes_from_poles`: least damped first.

    Raises
    ------
    ConfigError
        On a too short, empty, non-finite or zero signal, or invalid ``order``,
        ``period``, ``mass`` or ``pencil``.

    Notes
    -----
    On noise-free data of a linear system with exactly ``order`` non-zero poles, the poles
    are recovered to about 1e-12 relative (tests: synthetic damped sinusoids).
    """
    if not (np.isfinite(mass) and mass > 0):
        raise ConfigError(f"must be a positive number [kg], got {mass!r}", key="mass")
    z = pencil_poles(y, order, offset=offset, pencil=pencil, period=period)
    return modes_from_poles(z, mass, period)


def fit_rendered(y, period: float, order: int, mass: float, *, offset: bool = False,
                 pencil: int | None = None) -> Mode:
    """The rendered oscillator of a sampled free response: its least damped complex pair.

    Parameters
    ----------
    y, period, order, mass, offset, pencil
        As :func:`fit_modes`.

    Returns
    -------
    Mode
        The ``"pair"`` mode with the largest ``|z|``; its ``k`` [N/m] and ``b`` [N s/m] are
        the felt stiffness and whole THS damping (Florens et al. Sec. 5).

    Raises
    ------
    ConfigError
        As :func:`fit_modes`, and when no complex pair is found (an over-damped or purely
        real response has no rendered oscillator).
    """
    modes = fit_modes(y, period, order, mass, offset=offset, pencil=pencil)
    best = rendered_pair(modes)
    if best is None:
        raise ConfigError(f"no oscillating (complex pair) mode among the {order} identified "
                          "poles: the response is over-damped or the order is too small",
                          key="y")
    return best


# ------------------------------------------------------------------- n coordinates
def _equations(recs, p: int, usable):
    """Per record, the rows ``k`` whose prediction equation is formed: ``k >= p`` and,
    given ``usable``, rows ``k - p .. k`` all usable (one stretch of the loop's free
    response: the equation ``y[k] = sum_j y[k-j] C_j`` holds only when no disturbance
    acted from row ``k - p`` to row ``k``)."""
    if usable is not None and len(usable) != len(recs):
        raise ConfigError(f"usable must have one mask per record ({len(recs)}), got "
                          f"{len(usable)}", key="usable")
    out = []
    for i, r in enumerate(recs):
        N = r.shape[0]
        if usable is None or usable[i] is None:
            out.append(np.arange(p, N))
            continue
        u = np.asarray(usable[i], bool)
        if u.shape != (N,):
            raise ConfigError(f"usable[{i}] must have shape ({N},), got {u.shape}",
                              key="usable")
        # rows k whose window k - p .. k holds no unusable row
        bad = np.concatenate(([0], np.cumsum(~u)))
        k = np.arange(p, N)
        out.append(k[bad[k + 1] - bad[k - p] == 0])
    return out


def _regression(recs, p: int, usable, offset: bool):
    """The prediction's regression: rows ``R`` (the ``p`` lagged samples, newest first,
    then a 1 with ``offset``), right-hand sides ``Y``, the equations per record and the
    samples' reference (0 without ``offset``).

    With ``offset`` every sample is taken relative to the mean of the right-hand sides
    (the affine prediction's ``C`` does not depend on a common shift: only ``g`` does),
    so that the column of ones is not nearly collinear with records of absolute
    positions far from 0."""
    eqs = _equations(recs, p, usable)
    ref = 0.0
    if offset:
        ys = [r[ks] for r, ks in zip(recs, eqs) if ks.size]
        ref = np.mean(np.concatenate(ys), axis=0) if ys else 0.0
    # row k: r[k-1], r[k-2], ..., r[k-p] (newest first) less ref, then the 1; gathered
    # for every k of a record at once (the same values as row by row, to the bit)
    n = recs[0].shape[1] if recs else 0
    cols = n * p + int(bool(offset))
    rows, rhs = [np.zeros((0, cols))], [np.zeros((0, n))]
    for r, ks in zip(recs, eqs):
        if not ks.size:
            continue
        X = (r[ks[:, None] - 1 - np.arange(p)[None, :]] - ref).reshape(ks.size, n * p)
        rows.append(np.hstack([X, np.ones((ks.size, 1))]) if offset else X)
        rhs.append(r[ks] - ref)
    return np.concatenate(rows), np.concatenate(rhs), eqs, ref


def companion(C: np.ndarray, n: int, p: int) -> np.ndarray:
    """The block companion matrix of a vector prediction ``y[k] = sum_j y[k-j] C_j``.

    Parameters
    ----------
    C : ndarray, shape (..., n p, n)
        The coefficients, newest lag first (``C_j`` = rows ``(j-1) n .. j n``); leading
        axes: a stack of predictions.
    n, p : int
        Coordinates and lags.

    Returns
    -------
    ndarray, shape (..., n p, n p)
        Its eigenvalues are the prediction's poles (Lutkepohl, *New Introduction to
        Multiple Time Series Analysis*, 2005, sec. 2.1.1).
    """
    C = np.asarray(C)
    comp = np.zeros(C.shape[:-2] + (n * p, n * p))
    comp[..., :n, :] = np.swapaxes(C, -1, -2)
    comp[..., n:, :-n] = np.eye(n * (p - 1))
    return comp


def ar_poles(record, order: int) -> np.ndarray:
    """The poles of a vector autoregression of ``order`` lags fitted to one record by
    least squares (the prediction of :func:`fit_felt_nd`, without its felt matrices).

    Parameters
    ----------
    record : array_like, shape (N, n)
    order : int

    Returns
    -------
    ndarray of complex, shape (n order,)
        The eigenvalues of :func:`companion` of the fitted coefficients.
    """
    rec = np.asarray(record, float)
    n, p = rec.shape[1], int(order)
    R, Y, _, _ = _regression([rec], p, None, False)
    C, *_ = np.linalg.lstsq(R, Y, rcond=None)
    return np.linalg.eigvals(companion(C, n, p))


def fit_felt_nd(records, mass, period: float, order: int, *, usable=None,
                offset: bool = False, floor: float | None = None) -> dict:
    """Measured poles and felt matrices from free responses at the handle.

    Parameters
    ----------
    records : sequence of array_like, each shape (N_i, n)
        Handle positions [m] of free responses of one loop (deviations from rest).
    mass : array_like, shape (n, n)
        Cartesian mass of hand + handle [kg] (the felt matrices' mass, as predicted).
    period : float
        Sample period ``T`` [s].
    order : int
        Prediction order ``p`` (the loop's state size over n: ``d + 3 + 2 N_virtual`` for
        a scene of :mod:`hapsim.analysis.scene_check`).
    usable : sequence of (array_like of bool, shape (N_i,), or None), optional
        Per record, the rows that belong to an undisturbed stretch of the loop (a record
        cut where a disturbance acted: a host stall, a re-synchronisation). A record's
        stretches are fitted jointly with every other's, each a free response of the
        same loop from its own initial state: row ``k``'s equation is formed only when
        rows ``k - p .. k`` are all usable, so a stretch shorter than ``p + 1`` rows
        gives none. Default: every row.
    offset : bool, optional
        The records are positions about a common equilibrium ``c`` not at 0 (module
        notes: the affine prediction, one more unknown per coordinate): e.g. every
        record of a run taken whole, the record from rest among them, instead of the
        differences against that record. Default False: free responses about 0.
    floor : float, optional
        The records' error bound times :data:`MODE_FLOOR` [m]: a complex pair whose size
        in the records (:func:`mode_amplitudes`) is at most this is not determined by
        them and never taken for a rendered pair (fewer than n pairs above it: no felt
        matrices). Default: every pair a candidate, largest ``|z|`` first (exact
        records).

    Returns
    -------
    dict
        ``poles`` (every measured pole, largest ``|z|`` first), ``rendered_poles``,
        ``felt_stiffness`` [N/m] and ``felt_damping`` [N s/m] (n x n, None when fewer
        than n rendered pairs), ``residual`` (largest prediction error over the largest
        position [-]; with ``offset``, over the largest departure from the mean of the
        rows predicted) and ``rank`` of the regression; with ``offset``, ``equilibrium``
        (shape (n,), [m]: ``c``, None when ``I - sum_j C_j`` is singular).

    Raises
    ------
    ConfigError
        Records of different widths, too short for the order (fewer equations than
        unknowns), or not finite; ``usable`` of the wrong length or shape.
    """
    recs = [np.asarray(r, float) for r in records]
    if not recs or any(r.ndim != 2 for r in recs) or len({r.shape[1] for r in recs}) != 1:
        raise ConfigError("records must be arrays of shape (N, n) with one n", key="records")
    n = recs[0].shape[1]
    p = int(order)
    if not all(np.all(np.isfinite(r)) for r in recs):
        raise ConfigError("records must be finite", key="records")
    rows, rhs, _, ref = _regression(recs, p, usable, offset)
    unknowns = n * p + int(bool(offset))
    if len(rows) < unknowns:
        raise ConfigError(f"{len(rows)} equations for {unknowns} unknowns per coordinate: "
                          "longer or more records"
                          + ("" if usable is None else " (or longer undisturbed stretches)"),
                          key="records")
    R, Y = np.array(rows), np.array(rhs)
    Ca, _, rank, _ = np.linalg.lstsq(R, Y, rcond=None)
    C = Ca[:n * p]
    scale = float(np.max(np.abs(Y))) or 1.0
    residual = float(np.max(np.abs(R @ Ca - Y))) / scale
    comp = companion(C, n, p)
    from hapsim.analysis.ths import continuous_poles, felt_matrices, rendered_pairs_of
    zr, U, poles = rendered_pairs_of(comp, n, period, keep=_determined(
        _states(R, Ca, n, p, offset), n, floor))
    out = {"poles": poles, "rendered_poles": zr, "felt_stiffness": None,
           "felt_damping": None, "residual": residual, "rank": int(rank)}
    if offset:
        # c = (I - sum_j C_j)^-1 g, back in the records' coordinates
        A = np.eye(n) - C.reshape(p, n, n).sum(axis=0).T
        try:
            out["equilibrium"] = ref + np.linalg.solve(A, Ca[n * p])
        except np.linalg.LinAlgError:
            out["equilibrium"] = None
    if zr.size == n:
        z = zr.astype(complex)
        s = continuous_poles(z, period)
        k, b = felt_matrices(np.asarray(mass, float), s, U)
        out["felt_stiffness"], out["felt_damping"] = k, b
    return out


def _felt_of(C, n: int, p: int, mass, period: float, keep=None) -> list:
    """The felt matrices ``(k, b)`` of each of a stack of prediction coefficients ``C``
    (shape (B, n p, n)), or None where fewer than n rendered pairs: one eigen
    decomposition call for the stack (:func:`hapsim.analysis.ths.rendered_pairs_of_many`,
    each the same bits as alone; ``keep`` its)."""
    from hapsim.analysis.ths import continuous_poles, felt_matrices, rendered_pairs_of_many
    M = np.asarray(mass, float)
    out = []
    for zr, U, _ in rendered_pairs_of_many(companion(C, n, p), n, period, keep=keep):
        try:
            out.append(None if zr.size != n else felt_matrices(
                M, continuous_poles(zr.astype(complex), period), U))
        except ConfigError:
            out.append(None)
    return out


def felt_sensitivity_nd(records, mass, period: float, order: int, *,
                        step: float = 1e-7, usable=None, offset: bool = False,
                        floor: float | None = None) -> list | None:
    """First-order sensitivity of the measured felt matrices to each sample of the records.

    The fit (:func:`fit_felt_nd`) is ``C = R^+ Y`` (``R`` the lagged samples, ``Y`` the
    current ones), then the felt matrices of the companion matrix of ``C``. An error
    ``e_r[t]`` on the samples moves the prediction error of row ``k`` by
    ``eps[k] = e[k] - sum_j e[k-j] C_j`` and the coefficients by ``dC = R^+ eps`` (the
    least-squares estimate's first-order perturbation; Seber & Wild, *Nonlinear
    Regression*, 1989, Sec. 2.1); the felt matrices move by ``G dC`` with ``G`` their
    gradient over ``C`` (central differences of step ``step`` times ``max|C|``). The
    chain gives, per felt entry ``o``, ``d o / d e_r[t, i]``.

    Parameters
    ----------
    records : sequence of array_like, each shape (N_i, n)
        The records :func:`fit_felt_nd` fits [m].
    mass, period, order
        As :func:`fit_felt_nd`.
    step : float, optional
        Relative step of the central differences over ``C``.
    usable : optional
        As :func:`fit_felt_nd`: the equations fitted; a row no equation uses has
        sensitivity 0.
    offset : bool, optional
        As :func:`fit_felt_nd`: the affine prediction, ``C`` the first ``n p`` rows of
        ``R^+ Y`` with ``R`` holding the column of ones (an error of the samples does not
        enter that column: ``eps[k]`` as above, ``dC`` the first ``n p`` rows of
        ``R^+ eps``).
    floor : float, optional
        As :func:`fit_felt_nd`: the pairs taken for rendered ones, at ``C`` and at each
        difference's point, only those whose size in the records (about the equilibrium
        fitted at ``C``) exceeds it.

    Returns
    -------
    list of ndarray or None
        Per record, shape ``(2, n, n, N_i, n)``: the derivative of the felt stiffness
        (index 0) [N/m per m] and damping (index 1) [N s/m per m] entries over each
        sample; None when the records give no felt matrices.

    Raises
    ------
    ConfigError
        As :func:`fit_felt_nd`.
    """
    recs = [np.asarray(r, float) for r in records]
    fit_felt_nd(recs, mass, period, order, usable=usable, offset=offset)   # validates
    n = recs[0].shape[1]
    p = int(order)
    rows, rhs, eqs, _ = _regression(recs, p, usable, offset)
    R, Y = np.array(rows), np.array(rhs)
    Pa = np.linalg.pinv(R)
    P = Pa[:n * p]                                          # (n p, rows)
    C = P @ Y
    keep = _determined(_states(R, Pa @ Y, n, p, offset), n, floor)
    h = step * max(float(np.max(np.abs(C))), 1.0)
    # C itself, then C with each coefficient (a, c) moved by +h and by -h: one stack
    cs = np.repeat(C[None], 1 + 2 * n * p * n, axis=0)
    a_, c_ = np.divmod(np.arange(n * p * n), n)
    k_ = 1 + 2 * np.arange(n * p * n)
    cs[k_, a_, c_] = C[a_, c_] + h
    cs[k_ + 1, a_, c_] = C[a_, c_] - h
    felt = _felt_of(cs, n, p, mass, period, keep)
    if any(f is None for f in felt):
        return None
    G = np.empty((2, n, n, n * p, n))
    for a, c, k in zip(a_, c_, k_):
        fp, fm = felt[k], felt[k + 1]
        G[0, :, :, a, c] = (fp[0] - fm[0]) / (2 * h)
        G[1, :, :, a, c] = (fp[1] - fm[1]) / (2 * h)
    # W[o, r, c] = sum_a P[a, r] G[o, a, c] (O, rows, n), the sum over a in order from
    # 0 (einsum("ar,oac->orc")'s order, the same bits: checked), laid out (O, n, rows)
    # so that each step runs along the rows
    Gr = G.reshape(2 * n * n, n * p, n)
    W = np.zeros((Gr.shape[0], n, P.shape[1]))
    for a in range(n * p):
        W = W + Gr[:, a, :, None] * P[a]
    Cj = C.reshape(p, n, n)                                 # C_j = Cj[j-1]: y[k-j] @ C_j
    out, row = [], 0
    for r, ks in zip(recs, eqs):
        N = r.shape[0]
        Wr = np.zeros((W.shape[0], n, N + p))
        Wr[:, :, ks] = W[:, :, row:row + ks.size]
        row += ks.size
        s = Wr[:, :, :N].copy()
        lags = _lag_terms(np.stack([Wr[:, :, j:N + j] for j in range(1, p + 1)]), Cj)
        for j in range(p):
            s -= lags[j]                   # s -= einsum("otc,ic->oti", X_j, C_j), in order
        out.append(s.transpose(0, 2, 1).reshape(2, n, n, N, n))
    return out


def _lag_terms(X, Cj) -> np.ndarray:
    """``sum_c X[j, o, c, t] Cj[j, i, c]`` for every lag ``j`` (X shape (p, O, n, N), Cj
    (p, n, n); result (p, O, n, N), index ``i`` in place of ``c``), the sum over ``c``
    associated as ``np.einsum("otc,ic->oti")`` associates it on x86-64 (a two-lane dot:
    the even terms, the odd terms, their sum, from 0; the same bits there, checked for
    n = 1, 2, 3 with signed zeros; elsewhere within the round-off of an n-term sum), in
    whole-array steps along the samples instead of a kernel call per element."""
    n = X.shape[2]
    q = [X[:, :, c, None, :] * Cj[:, None, :, c, None] for c in range(n)]
    lanes = [q[0], q[1] if n > 1 else None]
    for c in range(2, n):
        lanes[c % 2] = lanes[c % 2] + q[c]
    return (lanes[0] if n == 1 else lanes[0] + lanes[1]) + 0.0


def filtered_sensitivity_nd(sensitivity, response) -> list:
    """The felt entries' sensitivity to each error input, through the loop: per record,
    ``(s_r * response)[o, tau, j] = sum_t sum_c s_r[o, t, c] response[t - tau, c, j]``,
    the first-order change of felt entry ``o`` per unit error ``u_r[tau, j]``
    (superposition of the records' impulse responses, causal: ``response[t] = 0`` for
    ``t < 0``).

    Parameters
    ----------
    sensitivity : list of ndarray, each shape (..., N_r, n)
        :func:`felt_sensitivity_nd`'s result (any leading shape of felt entries).
    response : ndarray, shape (L, n, m)
        The records' response to a unit error of each of the ``m`` inputs.

    Returns
    -------
    list of ndarray, each shape (O, N_r, m)
        Per record, ``O`` the leading entries flattened.
    """
    from hapsim.analysis.fftconv import fast_length
    H = np.asarray(response, float)
    out, spectra = [], {}
    for s in sensitivity:
        sh = s.shape
        S = s.reshape(-1, sh[-2], sh[-1])                 # (O, N, n)
        N = S.shape[1]
        L = min(N, H.shape[0])
        Su = np.zeros((S.shape[0], N, H.shape[2]))
        rev = S[:, ::-1, :]
        # hapsim.analysis.fftconv.fftconvolve(rev[:, :, c], H[None, :L, c, j], axes=1)
        # step by step, the same calls on the same arrays (the same bits), with the
        # transform of each rev[:, :, c] taken once for every input j instead of once
        # each, and the response's once for every record of the same length
        F = [fast_length(N + L - 1)]
        if (F[0], L) not in spectra:
            spectra[F[0], L] = [[np.fft.rfftn(np.asarray(H[None, :L, c, j], dtype=float),
                                              F, axes=[1]) for j in range(H.shape[2])]
                                for c in range(S.shape[2])]
        B = spectra[F[0], L]
        for c in range(S.shape[2]):
            A = np.fft.rfftn(np.asarray(rev[:, :, c], dtype=float), F, axes=[1])
            for j in range(H.shape[2]):
                full = np.fft.irfftn(A * B[c][j], F, axes=[1])[:, :N + L - 1]
                Su[:, :, j] += full[:, :N][:, ::-1]
        out.append(Su)
    return out


def worst_case_nd(sensitivity, response, bounds) -> np.ndarray:
    """Worst case, to first order, of the felt entries' change under bounded errors.

    An error ``u_r[t]`` (``|u_r[t, j]| <= bounds_r[t, j]``, any sign, any correlation)
    enters record ``r`` through the impulse response ``response`` (the record's change
    ``sum_{tau <= t} response[t - tau] u_r[tau]``); with the sensitivity ``s_r`` of
    :func:`felt_sensitivity_nd`, the felt entry ``o`` moves by at most
    ``sum_r sum_(tau, j) |(s_r * response)[o, tau, j]| bounds_r[tau, j]`` (Hoelder's
    inequality on the linear map; :func:`filtered_sensitivity_nd`). The errors that
    reach it are ``bounds_r * sign((s_r * response)[o])``.

    Parameters
    ----------
    sensitivity : list of ndarray, each shape (2, n, n, N_r, n)
        :func:`felt_sensitivity_nd`'s result.
    response : ndarray, shape (L, n, m)
        The records' response to a unit error of each of the ``m`` inputs.
    bounds : list of array_like, each shape (N_r, m) or (m,)
        The errors' bounds per record and sample.

    Returns
    -------
    ndarray, shape (2, n, n)
        The worst-case change of each felt stiffness [N/m] and damping [N s/m] entry.
    """
    m = np.asarray(response).shape[2]
    out = 0.0
    for Su, e in zip(filtered_sensitivity_nd(sensitivity, response), bounds):
        eb = np.broadcast_to(np.asarray(e, float), (Su.shape[1], m))
        out = out + np.einsum("otj,tj->o", np.abs(Su), eb)
    return np.asarray(out).reshape(sensitivity[0].shape[:3])
