"""The felt stiffness and damping matrices measured from records of an n-DoF loop.

The n-D counterpart of :mod:`hapsim.analysis.identify`'s linear prediction: a free
response of a linear loop of state size ``n p`` seen through the ``n`` handle coordinates
obeys a vector linear prediction (multichannel Prony; a vector autoregression of order
``p``) ``y[k] = sum_{j=1..p} C_j y[k-j]``, exactly when the loop is observable from the
handle with observability index ``p``. Its companion matrix has the loop's poles as
eigenvalues and, in the first block of its eigenvectors, the handle mode shapes; the felt
matrices follow from them as for the prediction
(:func:`hapsim.analysis.ths_nd.felt_matrices`, the inverse quadratic eigenvalue problem).
Several records (free responses from different initial states) are fitted together, so
every mode is excited.
"""

from __future__ import annotations

import numpy as np

from hapsim.analysis.ths_nd import continuous_poles, felt_matrices, rendered_pairs_of
from hapsim.errors import ConfigError

__all__ = ["fit_felt_nd", "felt_sensitivity_nd", "worst_case_nd"]


def fit_felt_nd(records, mass, period: float, order: int) -> dict:
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
        a scene of :mod:`hapsim.analysis.scene_nd_check`).

    Returns
    -------
    dict
        ``poles`` (every measured pole, largest ``|z|`` first), ``rendered_poles``,
        ``felt_stiffness`` [N/m] and ``felt_damping`` [N s/m] (n x n, None when fewer
        than n rendered pairs), ``residual`` (largest prediction error over the largest
        position [-]) and ``rank`` of the regression.

    Raises
    ------
    ConfigError
        Records of different widths, too short for the order (fewer equations than
        unknowns), or not finite.
    """
    recs = [np.asarray(r, float) for r in records]
    if not recs or any(r.ndim != 2 for r in recs) or len({r.shape[1] for r in recs}) != 1:
        raise ConfigError("records must be arrays of shape (N, n) with one n", key="records")
    n = recs[0].shape[1]
    p = int(order)
    rows, rhs = [], []
    for r in recs:
        if not np.all(np.isfinite(r)):
            raise ConfigError("records must be finite", key="records")
        for k in range(p, r.shape[0]):
            rows.append(r[k - p:k][::-1].ravel())
            rhs.append(r[k])
    if len(rows) < n * p:
        raise ConfigError(f"{len(rows)} equations for {n * p} unknowns per coordinate: "
                          "longer or more records", key="records")
    R, Y = np.array(rows), np.array(rhs)
    C, _, rank, _ = np.linalg.lstsq(R, Y, rcond=None)
    scale = float(np.max(np.abs(Y))) or 1.0
    residual = float(np.max(np.abs(R @ C - Y))) / scale
    comp = np.zeros((n * p, n * p))
    comp[:n, :] = C.T
    comp[n:, :-n] = np.eye(n * (p - 1))
    zr, U, poles = rendered_pairs_of(comp, n, period)
    out = {"poles": poles, "rendered_poles": zr, "felt_stiffness": None,
           "felt_damping": None, "residual": residual, "rank": int(rank)}
    if zr.size == n:
        z = zr.astype(complex)
        s = continuous_poles(z, period)
        k, b = felt_matrices(np.asarray(mass, float), s, U)
        out["felt_stiffness"], out["felt_damping"] = k, b
    return out


def _felt_of(C, n: int, p: int, mass, period: float):
    """The felt matrices ``(k, b)`` of prediction coefficients ``C`` (shape (n p, n)), or
    None when fewer than n rendered pairs."""
    comp = np.zeros((n * p, n * p))
    comp[:n, :] = C.T
    comp[n:, :-n] = np.eye(n * (p - 1))
    zr, U, _ = rendered_pairs_of(comp, n, period)
    if zr.size != n:
        return None
    try:
        return felt_matrices(np.asarray(mass, float),
                             continuous_poles(zr.astype(complex), period), U)
    except ConfigError:
        return None


def felt_sensitivity_nd(records, mass, period: float, order: int, *,
                        step: float = 1e-7) -> list | None:
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
    fit_felt_nd(recs, mass, period, order)                  # validates
    n = recs[0].shape[1]
    p = int(order)
    R = np.array([r[k - p:k][::-1].ravel() for r in recs for k in range(p, r.shape[0])])
    Y = np.array([r[k] for r in recs for k in range(p, r.shape[0])])
    P = np.linalg.pinv(R)                                   # (n p, rows)
    C = P @ Y
    if _felt_of(C, n, p, mass, period) is None:
        return None
    h = step * max(float(np.max(np.abs(C))), 1.0)
    G = np.empty((2, n, n, n * p, n))
    for a in range(n * p):
        for c in range(n):
            Cp, Cm = C.copy(), C.copy()
            Cp[a, c] += h
            Cm[a, c] -= h
            fp, fm = _felt_of(Cp, n, p, mass, period), _felt_of(Cm, n, p, mass, period)
            if fp is None or fm is None:
                return None
            G[0, :, :, a, c] = (fp[0] - fm[0]) / (2 * h)
            G[1, :, :, a, c] = (fp[1] - fm[1]) / (2 * h)
    W = np.einsum("ar,oac->orc", P, G.reshape(2 * n * n, n * p, n))   # (O, rows, n)
    Cj = C.reshape(p, n, n)                                 # C_j = Cj[j-1]: y[k-j] @ C_j
    out, row = [], 0
    for r in recs:
        N = r.shape[0]
        Wr = np.zeros((W.shape[0], N + p, n))
        Wr[:, p:N] = W[:, row:row + N - p]
        row += N - p
        s = Wr[:, :N].copy()
        for j in range(1, p + 1):
            s -= np.einsum("otc,ic->oti", Wr[:, j:N + j], Cj[j - 1])
        out.append(s.reshape(2, n, n, N, n))
    return out


def worst_case_nd(sensitivity, response, bounds) -> np.ndarray:
    """Worst case, to first order, of the felt entries' change under bounded errors.

    An error ``u_r[t]`` (``|u_r[t, j]| <= bounds_r[t, j]``, any sign, any correlation)
    enters record ``r`` through the impulse response ``response`` (the record's change
    ``sum_{tau <= t} response[t - tau] u_r[tau]``); with the sensitivity ``s_r`` of
    :func:`felt_sensitivity_nd`, the felt entry ``o`` moves by at most
    ``sum_r sum_(tau, j) |(s_r * response)[o, tau, j]| bounds_r[tau, j]`` (Hoelder's
    inequality on the linear map).

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
    from scipy.signal import fftconvolve
    H = np.asarray(response, float)
    out = 0.0
    for s, e in zip(sensitivity, bounds):
        sh = s.shape
        S = s.reshape(-1, sh[-2], sh[-1])                 # (O, N, n)
        N = S.shape[1]
        L = min(N, H.shape[0])
        Su = np.zeros((S.shape[0], N, H.shape[2]))
        rev = S[:, ::-1, :]
        for c in range(S.shape[2]):
            for j in range(H.shape[2]):
                Su[:, :, j] += fftconvolve(rev[:, :, c], H[None, :L, c, j],
                                           axes=1)[:, :N][:, ::-1]
        eb = np.broadcast_to(np.asarray(e, float), (N, H.shape[2]))
        out = out + np.einsum("otj,tj->o", np.abs(Su), eb)
    return np.asarray(out).reshape(sensitivity[0].shape[:3])
