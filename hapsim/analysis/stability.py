"""The exact stability boundary of the THS: the largest stiffness K_max at a damping B,
the damping interval at a stiffness K, the boundary over a range of B, and the published
limits beside them.

Florens, Voda & Urma, Sec. 6; docs/design.md, 'The THS'. As :mod:`hapsim.analysis.ths`
(the rendered (k, b) and the calibration), every computation uses the dimensionless pieces
of :mod:`hapsim.analysis.loop` in ``w = z - 1``, never expanded: the roots outside the unit
circle counted on the companion matrix in ``z``, the boundary's crossings found by a scan
of the unit circle and refined by Brent's method.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.loop import LoopModel, char_eval, char_parts
from hapsim.analysis.loop_poles import roots_w, scaled_gains
from hapsim.errors import ConfigError

__all__ = ["stability_limit", "damping_limits", "circle_scan_points", "stability_boundary",
           "published_limits", "brent_root", "brake_loop_matrix"]


def _log_rho(w: np.ndarray) -> float:
    """``ln max |1 + w|``, accurate near the unit circle."""
    wr, wi = w.real, w.imag
    arg = 2.0 * wr + wr * wr + wi * wi
    with np.errstate(divide="ignore"):
        return float(np.max(0.5 * np.log1p(np.maximum(arg, -1.0))))


def _roots_outside(loop: LoopModel, kappa: float, beta: float) -> int | None:
    """Number of closed-loop poles outside the unit circle by the argument principle.

    The winding of ``f(e^{i theta})`` (:func:`hapsim.analysis.loop.char_eval`, unexpanded)
    round the circle counts the poles inside; ``f`` has real coefficients, so half a turn
    (``theta`` in ``[0, pi]``) gives half the count. O(d) evaluations (64 points per turn of
    ``z^e`` plus a geometric grid down to 1e-9 for the poles near ``z = 1``; every step that
    turns by more than pi/4 is bisected, up to 40 times), against O(d^3) for the
    eigenvalues. Returns None when it cannot be trusted (a pole on or within ~1e-12 of the
    circle: the caller then takes the eigenvalues).
    """
    P, Q, D, e = char_parts(loop)
    # degree of the characteristic polynomial: e + 2 for the plain loop, deg R for a
    # hand or a correction (e = 0 there, R expanded)
    deg = max(len(np.trim_zeros(np.asarray(D, float), "f")) - 1 + e,
              len(np.trim_zeros(np.asarray(P, float), "f")) - 1,
              len(np.trim_zeros(np.asarray(Q, float), "f")) - 1)
    n = max(2048, 64 * (e + 1))
    th = np.unique(np.concatenate([[0.0], np.geomspace(1e-9, math.pi, n // 2),
                                   np.linspace(0.0, math.pi, n + 1)]))

    def ev(t):
        return char_eval(loop, kappa, beta, -2.0 * np.sin(0.5 * t) ** 2 + 1j * np.sin(t))

    f = ev(th)
    for _ in range(40):
        if not np.all(np.isfinite(f)) or np.any(f == 0):
            return None
        step = np.angle(f[1:] / f[:-1])
        big = np.flatnonzero(np.abs(step) > 0.25 * math.pi)
        if big.size == 0:
            inside = float(np.sum(step)) / math.pi
            k = round(inside)
            return None if abs(inside - k) > 1e-6 else deg - k
        mid = 0.5 * (th[big] + th[big + 1])
        if np.any(mid - th[big] < 1e-13):
            return None
        th = np.insert(th, big + 1, mid)
        f = np.insert(f, big + 1, ev(mid))
    return None


def _stable_at(loop: LoopModel, kappa: float, beta: float) -> bool:
    """Every pole strictly inside the unit circle (argument principle, else eigenvalues)."""
    out = _roots_outside(loop, kappa, beta)
    if out is not None:
        return out == 0
    return _log_rho(roots_w(loop, kappa, beta)) < 0.0


def brent_root(f, a: float, b: float, *, xtol: float = 1e-12, rtol: float = 1e-15,
               maxiter: int = 200) -> float:
    """A root of ``f`` in ``[a, b]`` by Brent's method (bisection, secant and inverse
    quadratic interpolation).

    Written here so that the stability limit, which every ``hapsim run`` reports, needs no
    ``scipy.optimize`` (its import costs ~0.3 s of start-up).

    Parameters
    ----------
    f : callable
        ``f(x) -> float``, continuous on ``[a, b]``.
    a, b : float
        Bracket; ``f(a)`` and ``f(b)`` of opposite signs (or one of them 0).
    xtol, rtol : float
        The root is returned once the bracket is below ``xtol + rtol |x|`` [units of x].
    maxiter : int
        Most evaluations of ``f`` after the two at the ends.

    Returns
    -------
    float
        ``x`` in ``[a, b]`` with ``f(x) = 0`` or within the tolerance of a sign change.

    Raises
    ------
    ValueError
        ``f(a)`` and ``f(b)`` have the same sign (no bracket).
    RuntimeError
        Not converged within ``maxiter`` evaluations.

    Notes
    -----
    R. P. Brent, *Algorithms for Minimization without Derivatives* (Prentice-Hall, 1973),
    ch. 4 (procedure *zero*): each step takes the interpolated point when it falls inside
    the bracket and shrinks the step faster than bisection would, else bisects; the
    bracket always holds the sign change.
    """
    fa, fb = float(f(a)), float(f(b))
    if fa == 0.0:
        return float(a)
    if fb == 0.0:
        return float(b)
    if (fa > 0.0) == (fb > 0.0):
        raise ValueError("f(a) and f(b) must have opposite signs")
    c, fc = a, fa
    d = e = b - a
    for _ in range(int(maxiter)):
        if (fb > 0.0) == (fc > 0.0):          # keep the sign change between b and c
            c, fc = a, fa
            d = e = b - a
        if abs(fc) < abs(fb):                 # b: the best estimate so far
            a, b, c = b, c, b
            fa, fb, fc = fb, fc, fb
        tol = 0.5 * (xtol + rtol * abs(b))
        xm = 0.5 * (c - b)
        if abs(xm) <= tol or fb == 0.0:
            return float(b)
        if abs(e) >= tol and abs(fa) > abs(fb):
            s = fb / fa
            if a == c:                        # secant
                p, q = 2.0 * xm * s, 1.0 - s
            else:                             # inverse quadratic interpolation
                q, r = fa / fc, fb / fc
                p = s * (2.0 * xm * q * (q - r) - (b - a) * (r - 1.0))
                q = (q - 1.0) * (r - 1.0) * (s - 1.0)
            if p > 0.0:
                q = -q
            p = abs(p)
            if 2.0 * p < min(3.0 * xm * q - abs(tol * q), abs(e * q)):
                e, d = d, p / q               # interpolation accepted
            else:
                d = e = xm                    # bisection
        else:
            d = e = xm
        a, fa = b, fb
        b += d if abs(d) > tol else math.copysign(tol, xm)
        fb = float(f(b))
    raise RuntimeError(f"Brent's method did not converge in {maxiter} evaluations")


def _circle_thetas(e: int) -> np.ndarray:
    """The scan of the upper unit circle by :func:`_circle_values`: 4000 angles spaced
    geometrically from 1e-9 and at least 64 per turn of ``z^e``, linearly, up to pi."""
    n_lin = max(4000, 32 * (e + 1))
    return np.unique(np.concatenate([np.geomspace(1e-9, math.pi, 4000),
                                     np.linspace(0.0, math.pi, n_lin + 1)[1:]]))


def circle_scan_points(loop: LoopModel) -> int:
    """Angles of the unit circle :func:`stability_limit` scans for crossings.

    Parameters
    ----------
    loop : LoopModel

    Returns
    -------
    int
        The ``N`` of a limit labelled ``"sampled (N)"``: the scan finds every crossing
        whose neighbours on the circle are at least one scan step apart.
    """
    return int(_circle_thetas(char_parts(loop)[3]).size)


def _circle_values(A, C, e: int):
    """Real ``x`` for which ``x A(w) + C(w)`` has a root on the unit circle.

    ``A``, ``C``: vectorised functions of ``w = z - 1`` (evaluated unexpanded, see
    :func:`hapsim.analysis.loop.char_eval`); ``e``: the delay exponent, which sets how fast
    they turn round the circle. On ``z = e^{i theta}`` the root condition is ``x = -C/A``,
    real iff ``Im[C conj(A)] = 0``; that is solved for ``theta`` in ``(0, pi]`` (dense scan
    with at least 64 points per turn of ``z^e``, then Brent to ~1e-15). Returns ``(values,
    lossless, x_pi)``: the candidate values (unsorted, finite), whether ``-C/A`` is real all
    round the circle (a lossless loop: the scan finds no sign change), and ``-C/A`` at
    ``z = -1`` (nan where ``A(-1) = 0``).
    """
    def wof(theta):
        return -2.0 * np.sin(0.5 * theta) ** 2 + 1j * np.sin(theta)  # e^{i theta} - 1

    def g(theta):
        w = wof(theta)
        a, c = complex(A(w)), complex(C(w))
        return (c * np.conj(a)).imag / max(abs(c) * abs(a), 1e-300)

    thetas = _circle_thetas(e)
    wv = wof(thetas)
    av = A(wv)
    cv = C(wv)
    gv = (cv * np.conj(av)).imag / np.maximum(np.abs(cv) * np.abs(av), 1e-300)
    a, c = complex(A(-2.0 + 0j)), complex(C(-2.0 + 0j))
    x_pi = (-(c / a)).real if abs(a) > 1e-14 * max(abs(c), 1.0) else math.nan
    if np.max(np.abs(gv[thetas >= 1e-3])) < 1e-9:  # (tiny theta: cancellation noise)
        return [], True, x_pi
    vals = []
    for i in np.flatnonzero((gv[:-1] == 0.0) | (gv[:-1] * gv[1:] < 0)):
        if gv[i] == 0.0:
            th = thetas[i]
        else:
            try:
                th = brent_root(g, thetas[i], thetas[i + 1], xtol=1e-300, rtol=1e-15,
                                maxiter=200)
            except ValueError:  # scalar and vector rounding disagree on a tiny |g|
                th = 0.5 * (thetas[i] + thetas[i + 1])
        w = wof(th)
        a, c = complex(A(w)), complex(C(w))
        if abs(a) > 0:
            vals.append((-(c / a)).real)
    if math.isfinite(x_pi):
        vals.append(x_pi)
    return [v for v in vals if math.isfinite(v)], False, x_pi


def _kappa_max(loop: LoopModel, beta: float) -> float:
    """Dimensionless ``K_max T^2 / m`` for dimensionless ``beta = B T / m``."""
    P, Q, D, e = char_parts(loop)
    vals, lossless, k_pi = _circle_values(
        lambda w: np.polyval(P, w),
        lambda w: beta * np.polyval(Q, w) + (1.0 + w) ** e * np.polyval(D, w), e)
    if lossless:
        # Lossless loop (e.g. ideal hold, d = 0, B = -b0: the centred-difference
        # oscillator): K(theta) is real all round the circle, the poles sit on it for small
        # K (marginal stability) and leave it at z = -1.
        return k_pi if k_pi > 0 else 0.0
    cands = sorted({c for c in vals if c > 0})
    # stability is constant between consecutive crossings: test each interval's middle
    edges = [0.0] + cands
    for i, lo in enumerate(edges):
        hi = edges[i + 1] if i + 1 < len(edges) else (2.0 * lo if lo > 0 else 1.0)
        mid = math.sqrt(lo * hi) if lo > 0 else 0.5 * hi
        if not _stable_at(loop, mid, beta):
            return lo
    return math.inf


def stability_limit(loop: LoopModel, B: float = 0.0) -> float:
    """Exact largest stable virtual stiffness ``K_max(B)`` [N/m].

    Parameters
    ----------
    loop : LoopModel
    B : float, optional
        Virtual damping [N s/m].

    Returns
    -------
    float
        ``sup {K : the loop is stable for every K' in (0, K)}``, where the spectral radius
        reaches 1. ``0.0`` when no small positive ``K`` is stable (e.g. ZOH with
        ``b0 = B = 0``, or a delay without damping); ``inf`` when every ``K > 0`` is stable
        (no finite crossing, e.g. the ideal hold with large damping ratio; rare).
        For a lossless loop (``"ideal"``, ``d = 0``, ``B = -b0``; e.g. ``b0 = B = 0``) the
        poles stay on the unit circle (marginal stability) up to where they leave it at
        ``z = -1``: for ``b0 = B = 0`` the centred-difference limit ``4 m / T^2``.

    Notes
    -----
    On the boundary a pole is ``z = e^{i theta}`` and ``K(theta) = -(Q B + R)/P`` must be
    real: ``Im[(QB + R) conj(P)] = 0`` is solved for ``theta`` in ``(0, pi]`` (dense scan
    then Brent, relative precision ~1e-15), each root gives a candidate ``K``; between
    consecutive candidates stability cannot change, so each interval is classified by the
    spectral radius at one interior point. The boundary is the ``b = 0`` curve of the grid
    (Florens et al. Sec. 6.2).

    Raises
    ------
    ConfigError
        If ``B`` is not finite or ``|B| T/m`` exceeds
        :data:`hapsim.analysis.loop.MAX_PRODUCT` (key ``B``).
    """
    if not math.isfinite(float(B)):
        raise ConfigError(f"must be finite, got {B!r}", key="B")
    T, m = loop.period, loop.mass
    _, beta = scaled_gains(loop, 0.0, B)
    return _kappa_max(loop, beta) * m / (T * T)


def damping_limits(loop: LoopModel, K: float) -> list:
    """Exact range(s) of virtual damping ``B`` keeping the loop stable at a fixed ``K``.

    Parameters
    ----------
    loop : LoopModel
    K : float
        Virtual stiffness [N/m], finite.

    Returns
    -------
    list of (float, float)
        The maximal intervals ``(B_min, B_max)`` [N s/m] of ``B`` for which every closed-loop
        pole has ``|z| < 1``, in increasing order; bounds may be ``-inf`` / ``inf``; empty
        when no ``B`` stabilises this ``K``. For a delayed loop the set is bounded on both
        sides: too little damping and too much (the delayed backward-difference damper
        pumps energy near the Nyquist frequency) are both unstable, the lens of Florens
        et al. Fig. 8. Ideal hold, ``d = 0``, ``b0 = 0``: ``(0, (4 m/T^2 - K) T/2)``.

    Raises
    ------
    ConfigError
        If ``K`` is not finite or ``|K| T^2/m`` exceeds
        :data:`hapsim.analysis.loop.MAX_PRODUCT`.

    Notes
    -----
    Same method as :func:`stability_limit` with the roles of ``K`` and ``B`` exchanged: on
    the boundary a pole is ``z = e^{i theta}`` and ``B(theta) = -(P K + R)/Q`` must be real;
    each root of ``Im[(P K + R) conj(Q)] = 0`` in ``(0, pi]`` gives a candidate ``B``
    (relative precision ~1e-15 in ``theta``); stability is constant between consecutive
    candidates and is classified by the spectral radius at one interior point of each.
    """
    if not math.isfinite(float(K)):
        raise ConfigError(f"must be finite, got {K!r}", key="K")
    T, m = loop.period, loop.mass
    kappa, _ = scaled_gains(loop, K, 0.0)
    P, Q, D, e = char_parts(loop)
    vals, lossless, b_pi = _circle_values(
        lambda w: np.polyval(Q, w),
        lambda w: kappa * np.polyval(P, w) + (1.0 + w) ** e * np.polyval(D, w), e)
    if lossless:
        vals = [b_pi] if math.isfinite(b_pi) else []
    cands = sorted(set(vals))
    if not cands:
        return [(-math.inf, math.inf)] if _stable_at(loop, kappa, 0.0) else []
    edges = [-math.inf] + cands + [math.inf]
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        if math.isinf(lo):
            mid = hi - max(1.0, abs(hi))
        elif math.isinf(hi):
            mid = lo + max(1.0, abs(lo))
        else:
            mid = 0.5 * (lo + hi)
        if _stable_at(loop, kappa, mid):
            if out and out[-1][1] == lo:
                out[-1] = (out[-1][0], hi)
            else:
                out.append((lo, hi))
    scale = m / T
    return [(float(lo * scale), float(hi * scale)) for lo, hi in out]


def stability_boundary(loop: LoopModel, B_values) -> np.ndarray:
    """``K_max(B)`` [N/m] for each virtual damping in ``B_values`` [N s/m].

    Parameters
    ----------
    loop : LoopModel
    B_values : array_like, shape (n,)

    Returns
    -------
    ndarray, shape (n,)
        :func:`stability_limit` at each ``B`` (``0.0`` / ``inf`` as documented there).
    """
    return np.array([stability_limit(loop, float(B)) for B in np.ravel(B_values)])


def published_limits(loop: LoopModel, B: float = 0.0) -> dict:
    """First-order stiffness limits from the literature, for reference [N/m].

    Parameters
    ----------
    loop : LoopModel
    B : float, optional
        Virtual damping [N s/m].

    Returns
    -------
    dict
        ``passivity_K``: Colgate & Schenkel (1997), ``b0 > K T/2 + |B|`` i.e.
        ``K < 2 (b0 - |B|) / T`` (sufficient, ZOH, no delay; may be <= 0).
        ``diolaiti_K``: Diolaiti et al. (2006), ``K < (b0 + B) / (T/2 + d T)`` (first order
        in ``b0 T / m``). ``centred_difference_K``: ``4 m / T^2`` (ideal hold, d = 0,
        Florens et al. eq. (2) at ``T sqrt(k/m) = pi``).
    """
    T, m, b0, d = loop.period, loop.mass, loop.friction, loop.delay
    return {"passivity_K": 2.0 * (b0 - abs(B)) / T,
            "diolaiti_K": (b0 + B) / (T / 2.0 + d * T),
            "centred_difference_K": 4.0 * m / (T * T)}


def brake_loop_matrix(mass, friction, damping, period: float, delay: int) -> np.ndarray:
    """The exact sampled loop of a device braked by ``tau = -B y``: the state matrix of
    ``(v[k], e_0, ..., e_d)``, ``e_j = x[k-j] - x[k-j-1]``.

    The plant ``M x'' + B_f x' = tau`` (any dimension ``n``) with ``tau`` held over each
    period (zero-order hold, exact: the matrix exponential), the host's velocity the
    backward difference ``y[k] = e_0 / T`` and ``tau[k] = -B y[k-d] = -(B / T) e_d``.
    Positions enter only through their differences (a braking has no position to go
    to: the translation mode, at ``z = 1`` exactly, is left out).

    Parameters
    ----------
    mass, friction, damping : array_like, shape (n, n) (or scalars)
        ``M`` [kg], ``B_f`` and ``B`` [N s/m] (or joint-space [kg m^2], [N m s/rad]).
    period : float
        ``T`` [s].
    delay : int
        ``d`` >= 0 [periods].

    Returns
    -------
    ndarray, shape (n (d + 2), n (d + 2))
        Its eigenvalues are the loop's poles: stable while all are inside the unit
        circle. With ``B_f = 0`` and ``B = g M / T`` they are the roots of
        :func:`hapsim.braking.brake_mode_polynomial` at ``g``, each ``n`` times.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``M`` singular.
    """
    from hapsim.analysis.ths import zoh_blocks
    M = np.atleast_2d(np.asarray(mass, float))
    n = M.shape[0]
    Bf, B = (float(a) * np.eye(n) if np.ndim(a) == 0 else np.asarray(a, float)
             for a in (friction, damping))
    T, d = float(period), int(delay)
    # the exact hold of M x'' + B_f x' = tau (the n-D THS's own, phi-functions)
    Ad, Bd = zoh_blocks(M, Bf, T)
    Pxv, Pvv = Ad[:n, n:], Ad[n:, n:]
    Gx, Gv = Bd[:n], Bd[n:]
    K = -B / T                                   # tau = K e_d
    S = n * (d + 2)
    out = np.zeros((S, S))
    ed = slice(n * (d + 1), n * (d + 2))
    out[:n, :n] = Pvv
    out[:n, ed] += Gv @ K
    out[n:2 * n, :n] = Pxv
    out[n:2 * n, ed] += Gx @ K
    for j in range(1, d + 1):
        out[n * (j + 1):n * (j + 2), n * j:n * (j + 1)] = np.eye(n)
    return out
