"""The matrix pencil: the poles of a sampled free response, and its modes.

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
"""

from __future__ import annotations

import numpy as np

from hapsim.analysis.modes import Mode, modes_from_poles, rendered_pair
from hapsim.errors import ConfigError

__all__ = ["pencil_poles", "fit_modes", "fit_rendered", "thin_pencil", "RANK_TOL"]


#: Singular values of the Hankel matrix below ``RANK_TOL`` times the largest are round-off:
#: the model order is cut to the numerical rank (Sarkar & Pereira, "Using the matrix pencil
#: method to estimate the parameters of a sum of complex exponentials", IEEE Antennas Prop.
#: Mag. 37(1), 1995: keep the singular values above ``10^-p`` of the largest, ``p`` the
#: significant digits of the data; double-precision records hold ~15). A long record of a
#: slow mode whose fast companions died out in its first samples has rank 2, not the loop's
#: ``d + 3``: the extra singular vectors are noise and their pencil eigenvalues spurious
#: poles, some outside the unit circle, taken for the least damped pair.
RANK_TOL = 1e-12


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
