"""The (k, b) grid in the (K, B) plane: Florens, Voda & Urma Fig. 4 (algorithm), Figs. 7-9.

Compute only: :func:`grid` returns arrays; :func:`hapsim.plots.plot_grid` draws them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapsim.analysis.loop import LoopModel
from hapsim.analysis.ths import calibrate_core, log_abs_w
from hapsim.analysis.stability import stability_boundary

__all__ = ["GridResult", "grid", "PAPER_PRESETS", "paper_preset"]

#: Fig. 9 convention: the damping axis is the virtual B *plus* the real friction b0.
B_AXIS_CONVENTION = ("B axis = B + b0 (Florens et al. Fig. 9: the virtual B scale with the "
                     "b0 bias added), so the identity grid is K = k, B + b0 = b")


@dataclass(frozen=True)
class GridResult:
    """Iso-k and iso-b curves of the THS parameter deformation.

    Attributes
    ----------
    loop : LoopModel
        The configuration.
    k_values : ndarray, shape (nk,)
        Target stiffnesses [N/m] (one iso-k curve each).
    b_values : ndarray, shape (nb,)
        Target whole-THS dampings [N s/m] (one iso-b curve each).
    K : ndarray, shape (nk, nb)
        Calibrated virtual stiffness [N/m]; nan where the target is not rendered.
    B : ndarray, shape (nk, nb)
        Calibrated virtual damping [N s/m] (without the b0 bias); nan likewise.
    rendered : ndarray of bool, shape (nk, nb)
        True where the target pair is placed, every other pole is inside the unit circle
        and decays faster than it. The ``b = 0`` column (the stability boundary, paper
        Sec. 6.2) is kept when the other poles are inside.
    b_bias : float
        ``b0`` [N s/m], added to ``B`` on the damping axis (see ``convention``).
    identity_K : ndarray, shape (nk, nb)
        Identity grid ``K = k`` [N/m] (what a perfect simulator would need).
    identity_B : ndarray, shape (nk, nb)
        Identity grid ``B = b - b0`` [N s/m].
    boundary_B : ndarray, shape (nB,)
        Virtual dampings [N s/m] where the stability boundary is evaluated.
    boundary_K : ndarray, shape (nB,)
        Exact ``K_max(B)`` [N/m] (``0`` where no positive K is stable, ``inf`` if unbounded).
    convention : str
        The damping-axis convention, spelled out.
    iso_k_b, iso_k_K, iso_k_B : ndarray, shapes (ns,), (nk, ns), (nk, ns), or None
        Finely sampled iso-k curves: ``K``, ``B`` [virtual units] at ``ns`` values of ``b``
        spanning ``b_values`` (only with ``samples > 0``).
    iso_b_k, iso_b_K, iso_b_B : ndarray, shapes (ns,), (nb, ns), (nb, ns), or None
        Finely sampled iso-b curves at ``ns`` values of ``k`` spanning ``k_values``.
    """

    loop: LoopModel
    k_values: np.ndarray
    b_values: np.ndarray
    K: np.ndarray
    B: np.ndarray
    rendered: np.ndarray
    b_bias: float
    identity_K: np.ndarray
    identity_B: np.ndarray
    boundary_B: np.ndarray
    boundary_K: np.ndarray
    convention: str = B_AXIS_CONVENTION
    iso_k_b: np.ndarray | None = None
    iso_k_K: np.ndarray | None = None
    iso_k_B: np.ndarray | None = None
    iso_b_k: np.ndarray | None = None
    iso_b_K: np.ndarray | None = None
    iso_b_B: np.ndarray | None = None

    @property
    def B_axis(self) -> np.ndarray:
        """``B + b0`` [N s/m], the damping axis of the figures, shape (nk, nb)."""
        return self.B + self.b_bias

    @property
    def boundary_B_axis(self) -> np.ndarray:
        """Stability boundary on the damping axis, ``B + b0`` [N s/m], shape (nB,)."""
        return self.boundary_B + self.b_bias

    def to_dict(self) -> dict:
        """JSON-ready dict; nan/inf become ``None``.

        Returns
        -------
        dict
            Keys ``loop, convention, b_bias, k_values, b_values, K, B, rendered,
            identity_K, identity_B, boundary_B, boundary_K`` (lists; 2-D arrays as lists of
            rows, shape (nk, nb)), SI units as in the attributes.
        """
        def lst(a):
            a = np.asarray(a, dtype=float)
            return [[v if math.isfinite(v) else None for v in row] for row in a.tolist()] \
                if a.ndim == 2 else [v if math.isfinite(v) else None for v in a.tolist()]
        return {"loop": self.loop.to_dict(), "convention": self.convention,
                "b_bias": self.b_bias, "k_values": lst(self.k_values),
                "b_values": lst(self.b_values), "K": lst(self.K), "B": lst(self.B),
                "rendered": np.asarray(self.rendered).tolist(),
                "identity_K": lst(self.identity_K), "identity_B": lst(self.identity_B),
                "boundary_B": lst(self.boundary_B), "boundary_K": lst(self.boundary_K)}


def _grid_point(loop: LoopModel, k: float, b: float):
    m, T = loop.mass, loop.period
    disc = b * b - 4 * m * k
    if b < 0 or (disc < 0 and math.sqrt(-disc) / (2 * m) * T >= math.pi):
        return math.nan, math.nan, False
    core = calibrate_core(loop, k, b)
    if core is None:
        return math.nan, math.nan, False
    kappa, beta, others, w_t, _, _ = core
    log_t = min(log_abs_w(w) for w in w_t)
    ok = all(log_abs_w(w) < min(log_t, 0.0) for w in others)
    if not ok:
        return math.nan, math.nan, False
    return kappa * m / (T * T), beta * m / T, True


def _sweep(loop, kv, bv):
    K = np.full((kv.size, bv.size), np.nan)
    B = np.full_like(K, np.nan)
    ok = np.zeros(K.shape, dtype=bool)
    for i, k in enumerate(kv):
        for j, b in enumerate(bv):
            K[i, j], B[i, j], ok[i, j] = _grid_point(loop, float(k), float(b))
    return K, B, ok


def grid(loop: LoopModel, k_values, b_values, *, boundary_B=None, n_boundary: int = 121,
         samples: int = 0) -> GridResult:
    """Sweep targets ``(k, b)``, calibrate each to ``(K, B)``: the paper's Fig. 4 algorithm.

    Parameters
    ----------
    loop : LoopModel
        The configuration.
    k_values : array_like, shape (nk,)
        Target stiffnesses [N/m], > 0.
    b_values : array_like, shape (nb,)
        Target whole-THS dampings [N s/m], >= 0 (``b = 0`` gives the stability boundary).
    boundary_B : array_like, optional
        Virtual dampings [N s/m] at which to evaluate the exact boundary ``K_max(B)``;
        by default ``n_boundary`` values spanning the grid's B range and the identity's.
    n_boundary : int, optional
        Number of boundary points when ``boundary_B`` is None.
    samples : int, optional
        When > 0, also sample each iso-k curve at ``samples`` values of ``b`` and each iso-b
        curve at ``samples`` values of ``k`` (smooth curves for plotting).

    Returns
    -------
    GridResult
        Row ``i`` of ``K``/``B`` is the iso-k curve ``k_values[i]`` (over b), column ``j``
        the iso-b curve ``b_values[j]`` (over k). Targets that are not rendered (a
        parasitic pole dominates or is unstable, or above Nyquist) are nan.

    Raises
    ------
    hapsim.errors.ConfigError
        If a ``k`` value is not finite or not > 0, or a ``b`` value is not finite
        (key ``k_values``).

    Notes
    -----
    Damping-axis convention (Florens et al. Fig. 9): figures plot ``B + b0``; the identity
    grid is then ``K = k``, ``B + b0 = b`` (``identity_B = b - b0`` in virtual units).
    Each point is the calibration of :func:`hapsim.analysis.calibrate` (Florens et al.
    Sec. 5, Fig. 4: solve ``P K + Q B + R = 0`` at the target's poles ``z = e^(sT)``).
    Plotting is separate: :func:`hapsim.plots.plot_grid`.
    """
    kv = np.asarray(k_values, dtype=float).ravel()
    bv = np.asarray(b_values, dtype=float).ravel()
    if np.any(kv <= 0) or np.any(~np.isfinite(kv)) or np.any(~np.isfinite(bv)):
        from hapsim.errors import ConfigError
        raise ConfigError("k values must be finite and > 0, b values finite", key="k_values")
    K, B, ok = _sweep(loop, kv, bv)
    fine = {}
    if samples and samples > 0:
        fb = np.linspace(bv.min(), bv.max(), int(samples))
        fk = np.linspace(kv.min(), kv.max(), int(samples))
        ikK, ikB, _ = _sweep(loop, kv, fb)
        ibK, ibB, _ = _sweep(loop, fk, bv)
        fine = dict(iso_k_b=fb, iso_k_K=ikK, iso_k_B=ikB, iso_b_k=fk, iso_b_K=ibK.T,
                    iso_b_B=ibB.T)
    b0 = loop.friction
    idK = np.repeat(kv[:, None], bv.size, axis=1)
    idB = np.repeat(bv[None, :], kv.size, axis=0) - b0
    if boundary_B is None:
        allB = [B] + [fine[key] for key in ("iso_k_B", "iso_b_B") if key in fine]
        finite = np.concatenate([a[np.isfinite(a)] for a in allB])
        lo, hi = float(np.min(idB)), float(np.max(idB))
        if finite.size:
            span = max(hi - lo, float(np.ptp(finite)), 1e-300)
            # ignore round-off below the identity's range (e.g. B = -1e-17 for b = b0)
            if finite.min() < lo - 1e-9 * span:
                lo = float(finite.min())
            hi = max(hi, float(finite.max()))
        if hi <= lo:
            hi = lo + 1.0
        boundary_B = np.linspace(lo, hi, n_boundary)
    bB = np.asarray(boundary_B, dtype=float).ravel()
    bK = stability_boundary(loop, bB)
    return GridResult(loop=loop, k_values=kv, b_values=bv, K=K, B=B, rendered=ok,
                      b_bias=b0, identity_K=idK, identity_B=idB, boundary_B=bB,
                      boundary_K=bK, **fine)


#: The paper's Figs. 7-9 (normalised units m = T = 1, ideal hold): loop and target ranges.
PAPER_PRESETS = {
    7: {"loop": dict(mass=1.0, friction=0.0, rate_hz=1.0, delay=0, hold="ideal"),
        "k": (1.0, 9.0), "b": (0.0, 2.0), "zoh_k": (0.1, 2.0), "zoh_b": (0.0, 1.6), "title": "Fig. 7: ideal interface, no delay"},
    8: {"loop": dict(mass=1.0, friction=0.0, rate_hz=1.0, delay=1, hold="ideal"),
        "k": (0.1, 1.0), "b": (0.0, 0.8), "zoh_k": (0.05, 0.6), "zoh_b": (0.0, 0.6), "title": "Fig. 8: one sample of delay"},
    9: {"loop": dict(mass=1.0, friction=0.5, rate_hz=1.0, delay=1, hold="ideal"),
        "k": (0.1, 1.2), "b": (0.0, 1.2),
        "title": "Fig. 9: one sample of delay and real damping b0 = 0.5"},
}


def paper_preset(number: int, hold: str | None = None):
    """Loop and target ranges of the paper's Fig. 7, 8 or 9.

    Parameters
    ----------
    number : {7, 8, 9}
        Figure number.
    hold : {"ideal", "zoh"}, optional
        Override the hold (the paper uses ``"ideal"``).

    Returns
    -------
    loop : LoopModel
    k_range : tuple of float
        ``(k_min, k_max)`` [N/m, normalised] (smaller for ``"zoh"``, whose renderable
        domain is smaller).
    b_range : tuple of float
        ``(b_min, b_max)`` [N s/m, normalised].
    title : str

    Raises
    ------
    hapsim.errors.ConfigError
        For a figure number other than 7, 8 or 9 (key ``number``, the valid choices
        listed), or an unknown ``hold`` (key ``hold``).
    """
    from hapsim.errors import ConfigError
    try:
        n = int(number)
        if n != number:
            raise ValueError
        p = PAPER_PRESETS[n]
    except (TypeError, ValueError, KeyError):
        raise ConfigError(f"no preset for figure {number!r}; valid choices: "
                          f"{', '.join(str(k) for k in sorted(PAPER_PRESETS))}",
                          key="number") from None
    kw = dict(p["loop"])
    if hold is not None:
        kw["hold"] = hold
    loop = LoopModel(**kw)
    if loop.hold == "zoh":  # the ZOH renders a smaller (k, b) domain: zoom on it
        return loop, p.get("zoh_k", p["k"]), p.get("zoh_b", p["b"]), p["title"]
    return loop, p["k"], p["b"], p["title"]
