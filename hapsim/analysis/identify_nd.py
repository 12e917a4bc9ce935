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

__all__ = ["fit_felt_nd"]


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
