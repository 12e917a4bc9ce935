"""The figure of a run's telemetry (``hapsim telemetry FILE --plot FIG``).

matplotlib is imported lazily through :func:`hapsim.plots.pyplot` (Agg backend).
"""

from __future__ import annotations

import numpy as np

__all__ = ["plot_telemetry"]

# flags bits drawn as rows of the lowest panel: (bit, label, colour)
_FLAG_ROWS = ((1, "late", "tab:orange"), (2, "restart", "tab:red"),
              (4, "ramp", "tab:purple"), (8, "clamped", "tab:brown"))


def plot_telemetry(cols: dict, energy: np.ndarray, events: list, title: str = "",
                   units: dict | None = None):
    """Position, force, felt energy and flags of a run over time, on one time axis.

    Parameters
    ----------
    cols : dict of str to ndarray
        Telemetry columns (:data:`hapsim.host.telemetry.COLUMNS`), each shape (n,):
        ``time`` [s], ``position`` [m], ``force`` [N], ``flags``.
    energy : ndarray, shape (n,)
        Felt energy per sample [J] (:func:`hapsim.commands.telemetry.felt_energy`).
    events : list of dict
        Loop events (``event``, ``t`` [s] device time when known, ``sample``); ``lost`` and
        ``recovered`` are drawn as vertical lines on every panel.
    title : str
        Figure title (the file name).
    units : dict, optional
        :func:`hapsim.drivers.axis_units` of the run's axis (default SI; a rotary
        joint's: position [mrad], torque [N m]).

    Returns
    -------
    matplotlib.figure.Figure
        Four panels sharing the time axis [s] (time from the first sample): position [mm],
        force [N], felt energy [mJ], and one row of ticks per flag (late, restart after a
        recovery, ramp, clamped).

    Raises
    ------
    ConfigError
        If matplotlib is missing (message: install the plot extra).
    """
    from hapsim.drivers import axis_units, in_axis_units
    from hapsim.plots import pyplot

    plt = pyplot()
    u = units or axis_units(None)
    t = np.asarray(cols["time"], float)
    t0 = t[0] if t.size else 0.0
    tt = t - t0
    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(8.0, 7.5), dpi=110,
                             gridspec_kw={"height_ratios": [3, 3, 2, 1.4]})
    ax_x, ax_f, ax_e, ax_flags = axes
    tb = _break_gaps(tt)          # no line drawn across a stretch without samples
    ax_x.plot(tb, _break_gaps(tt, 1e3 * np.asarray(cols["position"], float)), lw=0.9,
              color="tab:blue")
    ax_x.set_ylabel(in_axis_units("position [mm]", u))
    ax_f.plot(tb, _break_gaps(tt, np.asarray(cols["force"], float)), lw=0.9, color="tab:green")
    ax_f.set_ylabel(in_axis_units("force [N]", u))
    ax_e.plot(tb, _break_gaps(tt, 1e3 * np.asarray(energy, float)), lw=0.9, color="tab:red")
    ax_e.set_ylabel("felt energy [mJ]")
    flags = np.asarray(cols["flags"])
    for row, (bit, label, colour) in enumerate(_FLAG_ROWS):
        on = np.flatnonzero(flags & bit)
        if on.size:
            ax_flags.plot(tt[on], np.full(on.size, row), "|", color=colour, ms=8)
    ax_flags.set_yticks(range(len(_FLAG_ROWS)))
    ax_flags.set_yticklabels([r[1] for r in _FLAG_ROWS], fontsize=8)
    ax_flags.set_ylim(-0.7, len(_FLAG_ROWS) - 0.3)
    ax_flags.set_xlabel("time [s]")
    spans = _lost_spans(events, tt)
    for i, (a, b) in enumerate(spans):
        for ax in axes:
            ax.axvspan(a, b, color="0.6", alpha=0.35, lw=0,
                       label="device lost" if (ax is ax_x and i == 0) else None)
    if spans:
        ax_x.legend(loc="upper right", fontsize=8)
    for ax in axes[:3]:
        ax.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def _break_gaps(t: np.ndarray, y: np.ndarray | None = None) -> np.ndarray:
    """``y`` (or ``t``) with a NaN inserted where time jumps by more than 3 median steps."""
    y = t if y is None else y
    if t.size < 3:
        return y
    dt = np.diff(t)
    med = np.median(dt[dt > 0]) if np.any(dt > 0) else 0.0
    cut = np.flatnonzero(dt > 3 * med) + 1 if med > 0 else np.zeros(0, int)
    return np.insert(y.astype(float), cut, np.nan)


def _lost_spans(events: list, tt: np.ndarray) -> list:
    """Time spans ``(a, b)`` [s] from the last sample before each loss to the first sample
    after its recovery (events carry ``sample``, the row index where they happened)."""
    spans, start = [], None
    n = tt.size
    for ev in events:
        k = ev.get("sample")
        if not isinstance(k, (int, float)) or n == 0:
            continue
        k = int(k)
        if ev.get("event") == "lost" and start is None:
            start = float(tt[min(max(k - 1, 0), n - 1)])
        elif ev.get("event") == "recovered" and start is not None:
            spans.append((start, float(tt[min(k, n - 1)])))
            start = None
    if start is not None:
        spans.append((start, float(tt[-1])))
    return spans
