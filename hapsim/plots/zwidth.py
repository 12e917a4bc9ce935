"""Figure of ``hapsim zwidth``: the predicted stiffness boundary and the measured points.
Imports matplotlib lazily through :mod:`hapsim.plots`."""

from __future__ import annotations

import numpy as np

__all__ = ["plot_zwidth"]


def plot_zwidth(rep: dict, loop, device, rate_hz: float, x0: float):
    """The Z-width chart.

    Parameters
    ----------
    rep : dict
        :func:`hapsim.commands.zwidth.report`.
    loop : hapsim.analysis.loop.LoopModel
        The device's linear loop.
    device : hapsim.scene.Device
    rate_hz : float
        [Hz].
    x0 : float
        Release position [m] (the Coulomb prediction's amplitude).

    Returns
    -------
    matplotlib.figure.Figure
        ``K_max`` [N/m] against ``B`` [N s/m]: the exact linear boundary (solid), the
        boundary with Coulomb friction by its describing function (dashed, when the device
        has some), the measured points with their intervals (error bars).
    """
    from hapsim.analysis.stability import stability_limit
    from hapsim.analysis.zwidth import predicted_coulomb, release
    from hapsim.plots import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    Bs = [p["B"] for p in rep["points"]]
    hi = max(max(Bs) * 1.15, 1.0)
    grid = np.linspace(min(0.0, min(Bs)), hi, 60)
    ax.plot(grid, [stability_limit(loop, float(b)) for b in grid], "k-",
            label="predicted, linear (exact)")
    flim = float(device.force_limit or np.inf)
    if rep["device"]["coulomb"]:
        ax.plot(grid, [predicted_coulomb(device, rate_hz, float(b),
                                         lambda K: release(x0, flim, K)) for b in grid],
                "k--", label="predicted, Coulomb friction (describing function)")
    for p in rep["points"]:
        km, iv = p["K_max_measured"], p["K_max_measured_interval"]
        if km is None:
            continue
        ax.errorbar([p["B"]], [km], yerr=[[km - iv[0]], [iv[1] - km]], fmt="o", color="C3",
                    capsize=4, label="measured" if p is rep["points"][0] else None)
    ax.set_xlabel("virtual damping B [N s/m]")
    ax.set_ylabel("largest stable stiffness K_max [N/m]")
    ax.set_title(f"Z-width: {rep['where']}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
