"""The closed-loop poles of the sampled THS loop (:mod:`hapsim.analysis.loop`) and its
spectral radius.

The characteristic polynomial in ``z`` (:func:`hapsim.analysis.loop.char_parts`: ``z^(d+1)
D(z)`` is three O(1) coefficients and ``d + 1`` zeros) gives the poles as the eigenvalues of
its companion matrix; each is Newton-polished in ``w = z - 1`` on the unexpanded
characteristic function (:func:`hapsim.analysis.loop.char_eval`), conjugate pairs made
exact; the spectral radius carries the precision double arithmetic knows it to (Wilkinson
1963). The numerics are in the notes of :mod:`hapsim.analysis.loop`.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.kept import Kept
from hapsim.analysis.loop import LoopModel, char_eval, char_parts, check_delay, w_to_z
from hapsim.scene_schema import check_product

__all__ = ["roots_w", "scaled_gains", "closed_loop_poles", "spectral_radius",
           "spectral_radius_known"]


def _char_poly_z(loop: LoopModel, kappa: float, beta: float) -> np.ndarray:
    """The dimensionless characteristic polynomial in ``z`` (highest first).

    ``z^e D(z)`` is ``D``'s three coefficients followed by ``e`` zeros: every coefficient is
    O(1) whatever the delay, so its companion matrix (plant states + delay line) is well
    conditioned, unlike the expanded polynomial in ``w``.
    """
    zP, zQ, R = _z_parts(loop)
    low = np.polyadd(kappa * zP, beta * zQ)
    return np.polyadd(R, low)


def _z_parts(loop: LoopModel):
    """``w_to_z(P~)``, ``w_to_z(Q~)`` and ``z^e D`` of :func:`char_parts`, read-only, kept
    in the loop's ``__dict__`` as ``char_parts`` keeps its pieces (the same arrays every
    call: a grid recomputed them per point, a third of its time)."""
    got = loop.__dict__.get("_char_parts_z")
    if got is None:
        P, Q, D, e = char_parts(loop)
        got = (w_to_z(P), w_to_z(Q), np.concatenate([w_to_z(D), np.zeros(e)]))
        for a in got:
            a.setflags(write=False)
        loop.__dict__["_char_parts_z"] = got
    return got


def _polish_w(loop: LoopModel, kappa: float, beta: float, w: np.ndarray,
              iters: int = 6) -> np.ndarray:
    """Newton-polish roots ``w`` on :func:`char_eval` (structured, any delay).

    A step is kept only while it lowers ``|f|`` and stays well inside the gap to the
    nearest other root (so a root of a cluster never jumps onto its neighbour).
    """
    w = np.array(w, dtype=complex)
    if w.size == 0:
        return w
    if w.size > 1:
        gap = np.abs(w[:, None] - w[None, :])
        np.fill_diagonal(gap, np.inf)
        reach = 0.25 * gap.min(axis=1)
    else:
        reach = np.full(1, np.inf)
    x0 = w.copy()
    best = w.copy()
    fbest = np.abs(char_eval(loop, kappa, beta, w))
    x = w.copy()
    for _ in range(iters):
        f, df = char_eval(loop, kappa, beta, x, derivative=True)
        ok = df != 0
        step = np.where(ok, f / np.where(ok, df, 1.0), 0.0)
        x = x - step
        fx = np.abs(char_eval(loop, kappa, beta, x))
        better = (fx < fbest) & (np.abs(x - x0) < reach) & np.isfinite(fx)
        best = np.where(better, x, best)
        fbest = np.where(better, fx, fbest)
        x = np.where(better, x, best)
    return best


def _pair_up(r: np.ndarray) -> np.ndarray:
    """Re-impose exact conjugate pairs on the roots of a real polynomial."""
    out = []
    used = np.zeros(r.size, bool)
    for i in range(r.size):
        if used[i]:
            continue
        used[i] = True
        if abs(r[i].imag) <= 1e-14 * max(abs(r[i]), 1e-300):
            out.append(complex(r[i].real, 0.0))
            continue
        cand = np.flatnonzero(~used)
        if cand.size == 0:
            out.append(r[i])
            continue
        j = cand[np.argmin(np.abs(r[cand] - np.conj(r[i])))]
        used[j] = True
        zr = complex(0.5 * (r[i].real + r[j].real), 0.5 * (abs(r[i].imag) + abs(r[j].imag)))
        out.extend([zr, zr.conjugate()])
    return np.array(out, dtype=complex)


def roots_w(loop: LoopModel, kappa: float, beta: float) -> np.ndarray:
    """Closed-loop poles as ``w = z - 1``.

    Eigenvalues of the companion matrix of the characteristic polynomial *in z* (its
    coefficients are O(1) at any delay: the plant and the delay line as one state matrix),
    then Newton-polished in ``w`` on the unexpanded characteristic function
    (:func:`char_eval`), which restores the relative precision of the poles near ``z = 1``
    lost by the subtraction ``w = z - 1``.

    Parameters
    ----------
    loop : LoopModel
    kappa, beta : float
        Dimensionless gains ``K T^2 / m``, ``B T / m`` (:func:`scaled_gains`).

    Returns
    -------
    ndarray of complex, shape (n_poles,)
        ``z - 1`` of every closed-loop pole.

    Raises
    ------
    ConfigError
        A delay beyond :data:`MAX_DELAY`.
    """
    check_delay(loop.delay_whole)
    key = (repr(loop), float(kappa).hex(), float(beta).hex())
    return _ROOTS.get(key, lambda: _roots_w(loop, kappa, beta)).copy()


#: :func:`roots_w`'s answers by the loop's repr (every field, floats to the bit) and the
#: gains' bits: render, check, the run's prediction and the stability limit's interval
#: tests ask for the same poles of the same loop again (40 % of the calls in
#: test_long_delay's random loops); the same inputs, the same poles.
_ROOTS = Kept(512)


def _roots_w(loop: LoopModel, kappa: float, beta: float) -> np.ndarray:
    """:func:`roots_w` computed (its delay already checked)."""
    c = _char_poly_z(loop, kappa, beta)
    c = np.trim_zeros(c, "f")
    z = np.roots(c) if c.size > 1 else np.zeros(0, complex)
    # roots np.roots drops (trailing zero coefficients) are exact poles at z = 0
    if loop.generic:
        nz = c.size - 1 - z.size
    elif loop.delay_fraction > 0:
        nz = loop.delay_whole + 4 - z.size     # split hold: one more state
    else:
        nz = (loop.delay + (3 if loop.hold == "zoh" else 2)) - z.size
    if nz > 0:
        z = np.concatenate([z, np.zeros(nz, complex)])
    w = _polish_w(loop, kappa, beta, z.astype(complex) - 1.0)
    return _pair_up(w)


def scaled_gains(loop: LoopModel, K: float, B: float, keys=("K", "B")) -> tuple[float, float]:
    """The dimensionless gains ``(K T^2 / m, B T / m)`` of the characteristic equation
    (Florens, Voda & Urma eq. (4)).

    Parameters
    ----------
    loop : LoopModel
    K, B : float
        Virtual stiffness [N/m] and damping [N s/m].
    keys : tuple of str
        The keys an error names for K and B.

    Returns
    -------
    (float, float)

    Raises
    ------
    ConfigError
        A product beyond :data:`MAX_PRODUCT`.
    """
    T, m = loop.period, loop.mass
    check_product(float(K), T * T / m, keys[0], "N/m", "K T^2/m")
    check_product(float(B), T / m, keys[1], "N s/m", "B T/m")
    return float(K) * T * T / m, float(B) * T / m


def closed_loop_poles(loop: LoopModel, K: float, B: float = 0.0) -> np.ndarray:
    """Poles of the closed loop for a virtual spring ``K`` and damper ``B``.

    Parameters
    ----------
    loop : LoopModel
    K : float
        Virtual stiffness [N/m].
    B : float, optional
        Virtual damping [N s/m] (backward difference of the delayed position).

    Returns
    -------
    ndarray of complex, shape (d + 3,) for ``"zoh"``, (d + 2,) for ``"ideal"``
        Roots of ``P K + Q B + R`` (see :func:`characteristic`): eigenvalues of its
        companion matrix in ``z``, Newton-polished in ``w = z - 1`` on the unexpanded
        characteristic function (module docstring); conjugate pairs are exact.

    Raises
    ------
    ConfigError
        When ``|K| T^2/m`` or ``|B| T/m`` exceeds :data:`MAX_PRODUCT`.
    """
    kappa, beta = scaled_gains(loop, K, B)
    return 1.0 + roots_w(loop, kappa, beta)


def spectral_radius(loop: LoopModel, K: float, B: float = 0.0) -> float:
    """Largest closed-loop pole modulus of the THS loop.

    Parameters
    ----------
    loop : LoopModel
        The configuration (mass, friction, rate, delay, hold).
    K : float
        Virtual stiffness [N/m].
    B : float, optional
        Virtual damping [N s/m].

    Returns
    -------
    float
        ``max |z|`` [-] over the roots of ``P K + Q B + R`` (:func:`closed_loop_poles`,
        Florens et al. Sec. 6 eq. (1)): ``< 1`` asymptotically stable, ``> 1`` unstable;
        within :data:`STABILITY_TOL` of 1 the verdicts call the loop marginal.
    """
    return float(np.max(np.abs(closed_loop_poles(loop, K, B))))


def spectral_radius_known(loop: LoopModel, K: float, B: float = 0.0) -> tuple[float, float]:
    """Spectral radius with the precision to which double arithmetic knows it.

    A pole of multiplicity ``m`` moves by ``~ (eta)^(1/m)`` under a relative perturbation
    ``eta`` of the coefficients: at the stiffness limit of the undamped centred-difference
    loop (ideal hold, ``d = 0``, ``K = 4 m / T^2``) the poles are a double root at
    ``z = -1`` and any double-precision computation of their modulus is uncertain to
    ~1e-7, so "1.0000000298" carries two digits of noise.

    Parameters
    ----------
    loop : LoopModel
    K : float
        Virtual stiffness [N/m].
    B : float, optional
        Virtual damping [N s/m].

    Returns
    -------
    rho : float
        ``max |z|`` (:func:`spectral_radius`) [-].
    error : float
        First-order bound on its error [-]: for the dominant pole ``z0`` and the smallest
        ``m`` such that at most ``m`` computed poles lie within ``2 e_m`` of it,
        ``e_m = (m! eta(z0) / |p^(m)(z0)|)^(1/m)`` with the backward error
        ``eta(z) = 4 n eps sum_j |c_j| |z|^j`` of the degree-``n`` characteristic
        polynomial in ``z`` (coefficients ``c_j``; Wilkinson, *Rounding Errors in
        Algebraic Processes*, 1963, ch. 2: the perturbation of a multiple root).

    Raises
    ------
    ConfigError
        As :func:`closed_loop_poles`.
    """
    kappa, beta = scaled_gains(loop, K, B)
    c = np.trim_zeros(_char_poly_z(loop, kappa, beta), "f")
    z = closed_loop_poles(loop, K, B)
    mod = np.abs(z)
    i0 = int(np.argmax(mod))
    z0, rho = complex(z[i0]), float(mod[i0])
    n = c.size - 1
    if n < 1:
        return rho, 0.0
    eps = np.finfo(float).eps
    eta = 4.0 * n * eps * float(np.polyval(np.abs(c), abs(z0)))
    dist = np.abs(z - z0)
    der = c.astype(float)
    err = math.inf
    for m in range(1, n + 1):
        der = np.polyder(der)
        dm = abs(complex(np.polyval(der, z0)))
        if dm == 0.0:
            continue
        e = (math.factorial(m) * eta / dm) ** (1.0 / m)
        if np.count_nonzero(dist <= 2.0 * e) <= m:
            err = e
            break
    return rho, float(err)
