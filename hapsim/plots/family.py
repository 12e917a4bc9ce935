"""Figures of ``hapsim family`` and ``hapsim compare-corrections``. Imports matplotlib
lazily through :mod:`hapsim.plots`.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.plots import pyplot  # the one place matplotlib is imported (lazily)

__all__ = ["plot_family", "plot_corrections"]


def plot_family(res, title: str | None = None):
    """Felt (k, b) of every member of a family, coloured by spectral radius.

    Parameters
    ----------
    res : hapsim.analysis.family.FamilyResult
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
        Left: felt ``b`` [N s/m] against felt ``k`` [N/m] per member (unstable members
        as red crosses, corners as squares, nominal as a star). Right: spectral radius
        against total moving mass [kg], with the unit line.
    """
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.5))
    ok = res.stable
    sc = a1.scatter(res.k[ok], res.b[ok], c=res.rho[ok], s=6, cmap="viridis")
    a1.scatter(res.k[~ok], res.b[~ok], marker="x", color="red", s=14, label="unstable")
    c = res.corners
    a1.scatter(res.k[:c], res.b[:c], marker="s", facecolor="none", edgecolor="k",
               s=40, label="corners")
    a1.scatter(res.k[c:c + 1], res.b[c:c + 1], marker="*", color="k", s=80, label="nominal")
    a1.set_xlabel("felt k [N/m]")
    a1.set_ylabel("felt b [N s/m]")
    a1.legend(loc="best", fontsize=8)
    fig.colorbar(sc, ax=a1, label="spectral radius")
    a2.scatter(res.mass[ok], res.rho[ok], s=6, color="tab:blue")
    a2.scatter(res.mass[~ok], res.rho[~ok], s=14, marker="x", color="red")
    a2.axhline(1.0, color="k", lw=0.8)
    a2.set_xlabel("moving mass, handle + hand [kg]")
    a2.set_ylabel("spectral radius")
    verdict = (f"robustly stable ({res.robust_method})" if res.robust
               else f"{int((~ok).sum())} members unstable")
    fig.suptitle(f"{title + ': ' if title else ''}{res.members.shape[0]} members, {verdict}")
    fig.tight_layout()
    return fig


def plot_corrections(data: dict):
    """The paper's grid (Figs. 7-9 style) for each correction, on one page.

    Parameters
    ----------
    data : dict
        From :func:`hapsim.analysis.compare.compare_corrections`: ``rows`` (one per
        correction with ``label``, ``grid`` (:class:`hapsim.analysis.grid.GridResult`),
        ``boundary`` (B [N s/m], K_max [N/m]) and the figures of merit), ``loop``.

    Returns
    -------
    matplotlib.figure.Figure
        One panel per correction: iso-k (blue) and iso-b (orange) curves of the felt
        (k, b) in the virtual (K, B) plane, the identity grid (grey), the stability
        boundary (black), and the figures of merit in the title.
    """
    plt = pyplot()
    rows = data["rows"]
    n = len(rows)
    ncol = 3 if n > 4 else 2
    nrow = int(math.ceil(n / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(5.2 * ncol, 4.4 * nrow), squeeze=False)
    kmax, bmax = data["k_range"][1], data["b_range"][1]
    for ax, row in zip(axes.ravel(), rows):
        g = row["grid"]
        for j, k in enumerate(g.k_values):
            ax.plot(g.K[j, :], g.B[j, :], color="tab:blue", lw=0.8)
        for i, b in enumerate(g.b_values):
            ax.plot(g.K[:, i], g.B[:, i], color="tab:orange", lw=0.8)
        for k in g.k_values:
            ax.axvline(k, color="0.85", lw=0.5, zorder=0)
        for b in g.b_values:
            ax.axhline(b - data["b0"], color="0.85", lw=0.5, zorder=0)
        Bs, Ks = row["boundary"]
        ax.plot(np.minimum(Ks, 3 * kmax), Bs, color="k", lw=1.2)
        ax.set_xlim(0, 1.6 * kmax)
        ax.set_ylim(min(0.0, -data["b0"]), 1.6 * bmax)
        ax.set_xlabel("K [N/m]")
        ax.set_ylabel("B [N s/m]")
        ax.set_title(f"{row['label']}\nstable area {row['stable_area']:.3g}, worst "
                     f"distortion {row['worst_distortion']:.2g}, "
                     f"tangent {'yes' if row['tangent'] else 'no'}", fontsize=9)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    lp = data["loop"]
    fig.suptitle(f"corrections compared: m = {lp['mass']:g} kg, b0 = {lp['friction']:g} "
                 f"N s/m, {lp['rate_hz']:g} Hz, d = {lp['delay']}, {lp['hold']} "
                 "(blue iso-k, orange iso-b, black: stability boundary)")
    fig.tight_layout()
    return fig
