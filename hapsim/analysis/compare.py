"""Correction means compared on the paper's grid (Florens, Voda & Urma Figs. 7-9, Sec. 7).

For one device (mass, friction, rate, delay, hold) and each correction of
:mod:`hapsim.analysis.corrections` (and the plain element), three figures say which
correction is best:

stable area
    ``int_0^Bw min(K_max(B), Kw) dB`` over a window ``[0, Kw] x [0, Bw]`` of the virtual
    (K, B) plane, with the exact boundary ``K_max(B)`` (:func:`hapsim.analysis.stability_limit`),
    reported as a ratio to the plain element's area.
worst distortion
    Over a stated usable region of targets ``k in [k_lo, k_hi]``, ``b in [b_lo, b_hi]``
    (a ``n x n`` grid), the worst ``max(|K - k| / k, |B + b0 - b| / b)`` of the calibrated
    ``(K, B)`` (:func:`hapsim.analysis.calibrate`): 0 for a simulator that renders what it
    simulates; ``inf`` when some target of the region is not renderable.
tangency at low (K, B)
    The Jacobian ``J = d(k, b)/d(K, B)`` of the felt pair in the paper's normalised units
    (``K T^2/m``, ``B T/m``) at a small ``(K, B)``; the grid is tangent to the identity when
    ``max |J - I| < TANGENT_TOL``. The delay makes it not tangent (paper's remark on Fig.
    8): ``db/dK = -(d + 1/2) T`` (ZOH), i.e. ``-(d + 1/2)`` in normalised units whatever
    the rate, so raising the rate does not help.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.corrections import Correction
from hapsim.analysis.grid import grid
from hapsim.analysis.loop import LoopModel
from hapsim.analysis.ths import check_target, render
from hapsim.analysis.stability import stability_limit
from hapsim.errors import ConfigError

__all__ = ["compare_corrections", "default_corrections", "tangency", "tangency_limit",
           "TANGENT_TOL", "TANGENCY_AT"]

#: ``max |J - I|`` below which the grid counts as tangent to the identity at the origin.
TANGENT_TOL = 0.05

#: Normalised ``K T^2/m = B T/m`` at which :func:`tangency` takes its finite Jacobian (the
#: report states it beside the limit of :func:`tangency_limit`).
TANGENCY_AT = 1e-3


def default_corrections(loop: LoopModel) -> list:
    """The corrections compared by default, with parameters scaled to the loop.

    Parameters
    ----------
    loop : LoopModel

    Returns
    -------
    list of (Correction or None)
        None (the plain element), velocity sensor, velocity filter at a tenth of the rate,
        prediction ``d`` and ``d + 1/2`` samples ahead (the hold's half sample),
        inertia compensation of half the mass, virtual coupling ``Kc = 0.9 x 2 (b0 + ...)``
        at Colgate's passivity bound ``Kc = 2 (b0 - Bc) / T`` (``Bc = 0``; a stiffer
        coupling if ``b0 = 0``: ``m / T^2``).
    """
    T = loop.period
    kc = 0.9 * 2.0 * loop.friction / T if loop.friction > 0 else loop.mass / (T * T)
    return [None, Correction("velocity_sensor"),
            Correction("velocity_filter", cutoff_hz=0.1 * loop.rate_hz),
            Correction("prediction"), Correction("prediction", horizon=loop.delay + 0.5),
            Correction("inertia_compensation", mass=0.5 * loop.mass),
            Correction("virtual_coupling", stiffness=kc, damping=0.0)]


def _with(loop: LoopModel, corr) -> LoopModel:
    d = loop.to_dict()
    d.pop("correction", None)
    return LoopModel(**d, correction=corr)


def tangency(loop: LoopModel, *, at: float = 1e-3, step: float = 1e-6) -> np.ndarray:
    """Jacobian of the felt (k, b) against the virtual (K, B) near the origin, normalised.

    Parameters
    ----------
    loop : LoopModel
    at : float, optional
        Normalised point ``K T^2/m = at``, ``B T/m = at`` (small: the low (K, B) corner).
    step : float, optional
        Central-difference step in normalised units.

    Returns
    -------
    ndarray, shape (2, 2)
        ``[[dk/dK, dk/dB], [db/dK, db/dB]]`` in normalised units (identity for a perfect
        simulator); nan where no pair is rendered.
    """
    T, m = loop.period, loop.mass
    sK, sB = m / (T * T), m / T

    def felt(kn, bn):
        r = render(loop, kn * sK, bn * sB)
        return np.array([r.k / sK, r.b / sB])
    J = np.empty((2, 2))
    for j, (dk, db) in enumerate(((step, 0.0), (0.0, step))):
        J[:, j] = (felt(at + dk, at + db) - felt(at - dk, at - db)) / (2 * step)
    return J


def tangency_limit(loop: LoopModel) -> np.ndarray:
    """Jacobian of the felt (k, b) against the virtual (K, B) *at* ``K = B = 0``, normalised.

    The finite-difference :func:`tangency` at ``K T^2/m = B T/m = 1e-3`` is not the limit:
    a virtual coupling's ``dk/dK`` is 0.81 there and 1.00 in the limit. The limit is exact:
    at ``K = B = 0`` the felt pair is the integrator pole ``w1 = 0`` and the friction pole
    ``w2 = -(1 - e^(-b0 T/m))`` (``w = z - 1``; a double root at 0 when ``b0 = 0``), and the
    symmetric functions of the pair, ``k T^2/m = sigma1 sigma2`` and ``b T/m = -(sigma1 +
    sigma2)`` with ``sigma = ln(1 + w)`` (``k = m |s|^2``, ``b = -2 m Re s``, ``s = sigma /
    T``), stay analytic through the over-damped range where the pair is real.

    Parameters
    ----------
    loop : LoopModel
        With or without a correction.

    Returns
    -------
    ndarray, shape (2, 2)
        ``[[dk/dK, dk/dB], [db/dK, db/dB]]`` in normalised units at the origin.

    Raises
    ------
    ConfigError
        The characteristic at ``K = B = 0`` has no integrator pole at ``w = 0`` (the felt
        pair is then not the limit's).

    Notes
    -----
    The pair is the monic factor ``q = w^2 + c1 w + c0`` of ``F = kappa P~ + beta Q~ + R~``
    (:func:`hapsim.analysis.loop.char_eval`, Florens et al. Sec. 6 eq. (1) in the delta
    variable), ``F = q G``. Differentiating at ``kappa = beta = 0``: ``P~ = dq G (mod q)``
    (and ``Q~`` for ``beta``), a 2-by-2 linear system for ``dq = dc1 w + dc0``, with
    ``G mod q`` and ``P~ mod q`` the linear interpolants at the roots of ``q`` (Hermite at a
    double root). Then, with ``w1 = 0``: ``d(k T^2/m) = ln(1 + w2)/w2 dc0`` and ``d(b T/m)
    = (dc1 - dc0)/(1 + w2)``.
    """
    from hapsim.analysis.loop import char_parts

    P, Q, D, e = char_parts(loop)
    P, Q, D = (np.asarray(v, float) for v in (P, Q, D))
    if e:                         # plain loop: R~ = (1 + w)^e D, D = lead w (w - w2)
        lead = D[0]
        if D.size != 3 or D[2] != 0.0:
            raise ConfigError("no integrator pole at K = B = 0", key="loop")
        w2 = -D[1] / lead

        def G(w, der=False):
            return lead * (e * (1 + w) ** (e - 1) if der else (1 + w) ** e)
    else:                         # a correction, a hand: R~ expanded
        r = np.roots(np.trim_zeros(D, "f"))
        r = r[np.argsort(np.abs(r))]
        if r.size < 2 or abs(r[0]) > 1e-9:
            raise ConfigError("no integrator pole at K = B = 0", key="loop")
        w2 = float(r[1].real) if abs(r[1]) > 1e-7 else 0.0
        Gp = np.polydiv(D, np.poly([0.0, w2]))[0]

        def G(w, der=False):
            return np.polyval(np.polyder(Gp) if der else Gp, w)

    def lin(f, df):            # f mod q as (slope, intercept)
        if w2 != 0.0:
            g1 = (f(0.0) - f(w2)) / (0.0 - w2)
        else:
            g1 = df(0.0)
        return g1, f(0.0)
    c1, c0 = -w2, 0.0
    g1, g0 = lin(G, lambda w: G(w, True))
    A = np.array([[g0 - g1 * c1, g1], [-g1 * c0, g0]])
    lam = math.log1p(w2) / w2 if w2 != 0.0 else 1.0
    J = np.empty((2, 2))
    for j, poly in enumerate((P, Q)):
        r1, r0 = lin(lambda w: np.polyval(poly, w), lambda w: np.polyval(np.polyder(poly), w))
        dc1, dc0 = np.linalg.solve(A, [r1, r0])
        J[0, j] = lam * dc0
        J[1, j] = (dc1 - dc0) / (1.0 + w2)
    return J


def compare_corrections(loop: LoopModel, corrections=None, *, k_range=None, b_range=None,
                        n: int = 6, window=None, n_boundary: int = 61,
                        progress=None) -> dict:
    """Grid, stable area, worst distortion and tangency for each correction.

    Parameters
    ----------
    loop : LoopModel
        The device (its own ``correction`` is ignored).
    corrections : list of (Correction or None), optional
        Default :func:`default_corrections`.
    k_range, b_range : (float, float), optional
        Usable region of targets [N/m], [N s/m]. Default ``k`` from 5 % to 50 % of the
        plain loop's ``K_max`` at ``B = 2 b0`` (at least 1 % of ``m/T^2`` if that is 0),
        ``b`` from ``b0 + 0.5 sqrt(k_lo m) ...`` i.e. damping ratios 0.05 .. 0.5 at the
        middle ``k``.
    n : int, optional
        Points per axis of the usable region (and of the drawn grid).
    window : (float, float), optional
        ``(Kw, Bw)`` of the stable-area window; default 10 ``k_hi`` and 3 ``b_hi``.
    n_boundary : int, optional
        Points of the boundary ``K_max(B)`` over ``[0, Bw]``.
    progress : callable, optional
        ``progress(i, total, label)`` after each correction.

    Returns
    -------
    dict
        ``loop`` (dict), ``k_range``, ``b_range``, ``window``, ``b0``, ``tangent_tol``,
        ``rows``: per correction ``label``, ``correction`` (dict or None), ``grid``
        (:class:`GridResult`), ``boundary`` ((B, K_max) arrays), ``stable_area``
        [N^2 s/m^2], ``stable_area_ratio`` (to the plain element), ``worst_distortion``,
        ``unrenderable`` (count in the usable region), ``jacobian`` (2x2 list: the limit
        at ``K = B = 0``, :func:`tangency_limit`), ``jacobian_finite`` (:func:`tangency`
        at ``K T^2/m = B T/m =`` :data:`TANGENCY_AT`), ``off_identity`` (``max |J - I|``
        of the limit), ``tangent`` (bool); ``stable_area_method``: ``"sampled (N)"``, the
        trapezoid over ``N = n_boundary`` exact ``K_max(B)`` (an area between samples is
        not certified); ``jacobian_at``: where the two Jacobians are taken.
    """
    base = _with(loop, None)
    T, m, b0 = base.period, base.mass, base.friction
    if corrections is None:
        corrections = default_corrections(base)
    if k_range is None:
        kp = stability_limit(base, 2.0 * b0)
        if not (kp > 0 and math.isfinite(kp)):
            kp = 0.02 * m / (T * T)
        k_range = (0.05 * kp, 0.5 * kp)
    k_lo, k_hi = (float(v) for v in k_range)
    if b_range is None:
        kmid = math.sqrt(k_lo * k_hi)
        crit = 2.0 * math.sqrt(kmid) * math.sqrt(m)
        b_range = (max(b0 * 1.2, 0.05 * crit), max(b0 * 1.5, 0.5 * crit))
    b_lo, b_hi = (float(v) for v in b_range)
    Kw, Bw = window if window is not None else (10.0 * k_hi, 3.0 * b_hi)
    ks = np.linspace(k_lo, k_hi, n)
    bs = np.linspace(b_lo, b_hi, n)
    Bgrid = np.linspace(0.0, Bw, n_boundary)
    rows = []
    total = len(corrections)
    for i, corr in enumerate(corrections):
        lp = _with(base, corr)
        label = "plain (backward difference)" if corr is None else corr.label()
        for k in ks:
            for b in bs:
                check_target(lp, k, b)          # calibrate's checks, before the grid's
        # The grid calibrates each (k, b) of the usable region as calibrate does
        # (calibrate_core; K = kappa m / T^2, B = beta m / T) and renders it exactly when
        # calibrate would for b > 0 (every other pole inside the unit circle and decaying
        # faster than the target); its exact boundary is K_max at each B of Bgrid (the same
        # stability_limit calls). Its numbers serve here, instead of each computed twice.
        g = grid(lp, ks, bs, boundary_B=Bgrid)
        Kmax = g.boundary_K
        area = float(np.trapezoid(np.minimum(Kmax, Kw), Bgrid))
        worst, bad = 0.0, 0
        for i, k in enumerate(ks):
            for j, b in enumerate(bs):
                if b <= 0 or not g.rendered[i, j]:      # calibrate: b <= 0 never renders
                    bad += 1
                    continue
                K, B = float(g.K[i, j]), float(g.B[i, j])
                worst = max(worst, abs(K - k) / k, abs(B + b0 - b) / b)
        J_at = tangency(lp, at=TANGENCY_AT)
        try:
            J = tangency_limit(lp)
        except ConfigError:       # no integrator pole at the origin: the finite one
            J = J_at
        off = float(np.max(np.abs(J - np.eye(2))))
        rows.append({"label": label, "correction": None if corr is None else corr.to_dict(),
                     "grid": g, "boundary": (Bgrid, Kmax), "stable_area": area,
                     "worst_distortion": math.inf if bad else worst,
                     "worst_distortion_renderable": worst, "unrenderable": bad,
                     "jacobian": J.tolist(), "jacobian_finite": J_at.tolist(),
                     "off_identity": off,
                     "tangent": bool(off < TANGENT_TOL)})
        if progress is not None:
            progress(i + 1, total, label)
    a0 = rows[0]["stable_area"] if corrections[0] is None else None
    for r in rows:
        r["stable_area_ratio"] = (r["stable_area"] / a0) if a0 else None
    return {"loop": base.to_dict(), "k_range": (k_lo, k_hi), "b_range": (b_lo, b_hi),
            "stable_area_method": f"sampled ({n_boundary})",
            "jacobian_at": {"limit": "K, B -> 0", "finite_normalised": TANGENCY_AT},
            "window": (float(Kw), float(Bw)), "b0": b0, "tangent_tol": TANGENT_TOL,
            "n": n, "rows": rows}


