"""Sub-sample delay: a device delay of a real number of periods, ``d = m + f``.

A force computed from the position sampled at ``nT`` is held from ``(n + d) T`` to
``(n + d + 1) T``. With ``d = m + f`` (``m`` whole, ``0 <= f < 1``) the force switches
*inside* the sample period: over ``[nT, (n+1)T)`` the plant holds ``u[n-m-1]`` for ``fT``,
then ``u[n-m]`` for ``(1 - f) T``. Integrating ``x' = A x + b u`` over the two pieces
(the *split hold*)::

    x[n+1] = Phi x[n] + Gamma1 u[n-m-1] + Gamma0 u[n-m]
    Phi    = e^(A T)
    Gamma0 = int_0^((1-f)T) e^(A s) ds b
    Gamma1 = e^(A (1-f) T) int_0^(fT) e^(A s) ds b

This is the modified z-transform of the hold-plus-plant (E. I. Jury, *Theory and
Application of the z-Transform Method*, 1964; G. F. Franklin, J. D. Powell & M. L.
Workman, *Digital Control of Dynamic Systems*, 3rd ed., 1998, ch. 4, sec. 4.3: the
continuous time delay and the state-space model of a system with delay; K. J. Astrom &
B. Wittenmark, *Computer-Controlled Systems*, 3rd ed., 1997, sec. 2.3, "Systems with time
delay", there with ``tau = (d - 1) h + tau'``). ``f = 0`` gives
``Gamma1 = 0``, ``Gamma0 = Gamma`` (the plain hold: today's model exactly); ``f -> 1``
gives ``Gamma0 -> 0``, ``Gamma1 -> Gamma``: the hold of delay ``m + 1``. The loop is
continuous in ``d`` across the integers.

As one state space: the force held from the previous period is one more plant state
(:func:`held_plant`)::

    [x; h][n+1] = [[Phi, Gamma1], [0, 0]] [x; h][n] + [Gamma0; 1] u[n-m],   h[n] = u[n-m-1]

so a fractional delay is an integer delay ``m`` in front of a plant of order ``p + 1``;
the pulse transfer is ``c (zI - Phi)^-1 (Gamma0 + Gamma1 / z) z^-m``
(:func:`split_numerator_w`).

A *sensor-side* delay, the position sampled ``alpha T`` after the force switches (the
FireFader's ADC reads ~1.1 ms after the packet that sets its PWM, then the host's next
packet sets the force ``T - alpha T`` after that reading), is the same loop seen from
another phase of the period: the closed loop is a linear periodic system whose poles are
the eigenvalues of its one-period transition matrix, and that matrix taken from one
instant is similar to the one taken from any other (``Psi(t0 + T, t0)`` and
``Psi(t1 + T, t1)`` are conjugate by ``Psi(t1, t0)``). Poles, hence the felt ``(k, b)``,
depend only on the time from a sample to the force computed from it taking effect:
``d = (packets of delay) - alpha`` (FireFader at 250 Hz, one packet, ADC at 1.1 ms:
``d = 1 - 1.1 / 4 = 0.725``). What the sample instants see (the recorded positions) is the
same modes.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.hand import rigid_matrices, zoh_matrices
from hapsim.analysis.kept import Kept
from hapsim.errors import ConfigError

__all__ = ["split_delay", "split_hold", "split_hold_body", "held_plant",
           "split_numerator_w"]


def split_delay(delay, key: str = "delay") -> tuple[int, float]:
    """Whole and fractional parts of a delay ``d = m + f``.

    Parameters
    ----------
    delay : float >= 0
        Delay [periods] (a real number; whole numbers are the plain hold's delays).
    key : str, optional
        Name of the option or scene key, for the message.

    Returns
    -------
    m : int
        ``floor(d)`` [periods].
    f : float
        ``d - m`` in ``[0, 1)`` [-]; exactly ``0.0`` for a whole ``d``.

    Raises
    ------
    ConfigError
        ``delay`` not a finite real number >= 0 (``key`` named, with the valid range).
    """
    if isinstance(delay, bool):
        raise ConfigError(f"must be a real number >= 0 [periods], got {delay!r}", key=key)
    try:
        d = float(delay)
    except (TypeError, ValueError):
        raise ConfigError(f"must be a real number >= 0 [periods], got {delay!r}",
                          key=key) from None
    if not (math.isfinite(d) and d >= 0.0):
        raise ConfigError(f"must be a real number >= 0 [periods], got {delay!r}", key=key)
    m = int(math.floor(d))
    return m, d - m


def split_hold(A, b, period: float, fraction: float):
    """The split hold of ``x' = A x + b u`` when the held force switches ``fraction T``
    into the period.

    Parameters
    ----------
    A : array_like, shape (p, p)
        Continuous state matrix [1/s].
    b : array_like, shape (p,)
        Continuous input column [state units / (N s)].
    period : float > 0
        Sample period ``T`` [s].
    fraction : float in [0, 1)
        ``f``: the fractional part of the delay [-].

    Returns
    -------
    Phi : ndarray, shape (p, p)
        ``e^(A T)`` [-].
    Gamma0 : ndarray, shape (p,)
        ``int_0^((1-f)T) e^(As) ds b``: response to the force computed ``m`` periods back,
        held over the last ``(1 - f) T`` [state units / N].
    Gamma1 : ndarray, shape (p,)
        ``e^(A(1-f)T) int_0^(fT) e^(As) ds b``: response to the force before it, held over
        the first ``f T`` [state units / N].

    Raises
    ------
    ConfigError
        ``fraction`` outside ``[0, 1)`` or a non-positive period.

    Notes
    -----
    Franklin, Powell & Workman ch. 4, sec. 4.3; Astrom & Wittenmark sec. 2.3 (module notes).
    Each piece by Van Loan's block exponential (C. F. Van Loan, "Computing integrals
    involving the matrix exponential", IEEE TAC 23, 1978), through the accurate ``phi1``
    of :func:`hapsim.analysis.hand.zoh_matrices` on balanced coordinates.
    """
    f, T = float(fraction), float(period)
    if not 0.0 <= f < 1.0:
        raise ConfigError(f"must be in [0, 1), got {fraction!r}", key="fraction")
    if not (math.isfinite(T) and T > 0):
        raise ConfigError(f"must be > 0 [s], got {period!r}", key="period")
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float)
    eye = np.eye(A.shape[0])
    W, G = zoh_matrices(A, b, T)
    W0, G0 = zoh_matrices(A, b, (1.0 - f) * T)
    if f == 0.0:
        return eye + W, G0, np.zeros_like(G0)
    _, Gf = zoh_matrices(A, b, f * T)
    return eye + W, G0, Gf + W0 @ Gf


def split_hold_body(mass: float, friction: float, period: float, fraction: float):
    """The split hold of the rigid device body ``m x'' + b0 x' = f``.

    Parameters
    ----------
    mass : float > 0
        ``m`` [kg].
    friction : float >= 0
        ``b0`` [N s/m].
    period : float > 0
        ``T`` [s].
    fraction : float in [0, 1)
        ``f`` [-].

    Returns
    -------
    Phi : ndarray, shape (2, 2)
        State transition of ``[x, v]`` over the period.
    Gamma0, Gamma1 : ndarray, shape (2,)
        As :func:`split_hold` [m/N, m/(N s)].

    Raises
    ------
    ConfigError
        A non-positive mass or period, a negative friction, ``fraction`` outside [0, 1).

    Notes
    -----
    :func:`split_hold` on ``A = [[0, 1], [0, -b0/m]]``, ``b = [0, 1/m]`` (the hold's
    series is accurate at any ``b0 tau / m``).
    """
    if not (float(mass) > 0 and float(friction) >= 0):
        raise ConfigError(f"need mass > 0 and friction >= 0, got mass={mass!r}, "
                          f"friction={friction!r}", key="device")
    args = (float(mass), float(friction), float(period), float(fraction))

    def made():
        A, b = rigid_matrices(*args[:2], 0.0)
        return split_hold(A, b, *args[2:])
    # a loop's poles ask for it twice (its characteristic polynomial and its state
    # space), a measurement's searches for the same body many times: kept by the exact
    # bits of its arguments (float.hex tells -0.0 from 0.0), copies handed out
    kept = _BODIES.get(tuple(v.hex() for v in args), made)
    return tuple(a.copy() for a in kept)


#: The rigid bodies' split holds asked for lately (:func:`split_hold_body`).
_BODIES = Kept(256)


def held_plant(Phi, Gamma0, Gamma1):
    """The split-hold plant as one state space with the previous force as a state.

    Parameters
    ----------
    Phi : array_like, shape (p, p)
    Gamma0, Gamma1 : array_like, shape (p,) or (p, q)
        As :func:`split_hold` (``q`` inputs: a column each).

    Returns
    -------
    Ad : ndarray, shape (p + q, p + q)
        ``[[Phi, Gamma1], [0, 0]]``.
    Bd : ndarray, shape (p + q,) or (p + q, q)
        ``[Gamma0; I]``: the input is ``u[n-m]``, the extra states hold it one period
        (``h[n+1] = u[n-m]``).

    Notes
    -----
    Astrom & Wittenmark sec. 2.3 (the delayed input as an extra state of the sampled
    system). The output rows of the original plant are padded with ``q`` zeros.
    """
    Phi = np.atleast_2d(np.asarray(Phi, float))
    G0 = np.asarray(Gamma0, float)
    G1 = np.asarray(Gamma1, float)
    vec = G0.ndim == 1
    G0 = G0.reshape(Phi.shape[0], -1)
    G1 = G1.reshape(Phi.shape[0], -1)
    p, q = G0.shape
    Ad = np.zeros((p + q, p + q))
    Ad[:p, :p] = Phi
    Ad[:p, p:] = G1
    Bd = np.zeros((p + q, q))
    Bd[:p] = G0
    Bd[p:] = np.eye(q)
    return Ad, (Bd[:, 0] if vec else Bd)


def split_numerator_w(Aw, Gamma0, Gamma1, c):
    """Numerator in ``w = z - 1`` of the split-hold pulse transfer, times ``z``.

    Parameters
    ----------
    Aw : array_like, shape (p, p)
        ``Phi - I`` (the delta-operator matrix).
    Gamma0, Gamma1 : array_like, shape (p,)
        As :func:`split_hold`.
    c : array_like, shape (p,)
        Output row (position: ``[1, 0, ...]``).

    Returns
    -------
    ndarray, shape (p + 1,)
        ``Nf(w)`` (highest power first) with
        ``c (zI - Phi)^-1 (Gamma0 + Gamma1 / z) = Nf(w) / (z det(wI - Aw))``, i.e.
        ``Nf = z c adj(wI - Aw) Gamma0 + c adj(wI - Aw) Gamma1``.

    Notes
    -----
    ``c adj(M) g = det(M + g c) - det(M)`` (the matrix determinant lemma), on
    ``M = wI - Aw``. With ``f = 0`` (``Gamma1 = 0``) this is ``z`` times the plain hold's
    numerator: the loop gains one pole at ``z = 0`` and nothing else.
    """
    Aw = np.atleast_2d(np.asarray(Aw, float))
    c = np.asarray(c, float)
    D = np.poly(Aw)

    def num(g):
        return np.polysub(np.poly(Aw - np.outer(np.asarray(g, float), c)), D)[1:]
    n0, n1 = num(Gamma0), num(Gamma1)
    return np.polyadd(np.convolve([1.0, 1.0], n0), n1)
