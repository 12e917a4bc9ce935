"""Chart of the stiffness limit over a device's workspace (``hapsim kinematics --grid
--out``). Imports matplotlib lazily through :mod:`hapsim.plot`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["plot_workspace"]


def _mpl():
    from hapsim.plot import _mpl as mpl  # the one place matplotlib is imported
    return mpl()


def plot_workspace(res, title: str | None = None):
    """``K_max`` along the lightest principal axis of the Cartesian mass, over the
    configurations of a :class:`hapsim.analysis.ths_nd.WorkspaceLimits`.

    Parameters
    ----------
    res : hapsim.analysis.ths_nd.WorkspaceLimits
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
        Handle positions [m] (x, y; for a 3-D device the x-z projection) coloured by
        ``K_max`` [N/m] along the lightest axis; the refused configurations as grey
        crosses. Right: ``K_max`` along the lightest axis against its mass eigenvalue
        [kg] (the configuration-dependent mass sets the limit).
    """
    plt = _mpl()
    ok = np.array([s == "ok" for s in res.status])
    P = res.positions
    j = 1 if P.shape[1] == 2 else 2
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.5))
    k = res.limits[:, 0]
    fin = ok & np.isfinite(k)
    sc = a1.scatter(P[fin, 0], P[fin, j], c=k[fin], s=14, cmap="viridis")
    if np.any(~ok):
        a1.scatter(P[~ok, 0], P[~ok, j], marker="x", color="grey", s=10, label="refused")
        a1.legend(loc="best", fontsize=8)
    a1.set_xlabel("x [m]")
    a1.set_ylabel("y [m]" if j == 1 else "z [m]")
    a1.set_aspect("equal", adjustable="datalim")
    fig.colorbar(sc, ax=a1, label="K_max along the lightest axis [N/m]")
    a2.scatter(res.mass_eigenvalues[fin, 0], k[fin], s=10)
    a2.set_xlabel("lightest Cartesian mass eigenvalue [kg]")
    a2.set_ylabel("K_max [N/m]")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig
