"""Figures. The only hapsim module that imports matplotlib (lazily, Agg backend).

Install the extra with :data:`PLOT_INSTALL` (the command the README gives).
"""

from __future__ import annotations

import os

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["PLOT_INSTALL", "plot_grid", "plot_poles", "plot_felt", "plot_identify", "save_figure", "figure_formats", "check_figure_path",
           "check_output_path", "is_axes"]


#: How to install the plot extra (matplotlib): the README's command, in hapsim's checkout.
PLOT_INSTALL = "python -m pip install -e '.[plot]'"


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend, imported here only (lazily).

    Returns
    -------
    module
        ``matplotlib.pyplot``.

    Raises
    ------
    ConfigError
        matplotlib is not installed (names the extra to install).
    """
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ConfigError(f"matplotlib is not installed; install the plot extra in "
                          f"hapsim's checkout: {PLOT_INSTALL}", key="plot") from exc
    return plt


def plot_grid(result, ax=None, title: str | None = None, *, label_every: int = 1):
    """Draw a :class:`hapsim.analysis.GridResult` in the (K, B + b0) plane.

    Parameters
    ----------
    result : hapsim.analysis.GridResult
        Output of :func:`hapsim.analysis.grid` (use ``samples > 0`` for smooth curves).
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when None.
    title : str, optional
        Axes title; a description of the loop by default.
    label_every : int, optional
        Label every n-th iso curve.

    Returns
    -------
    matplotlib.figure.Figure
        Iso-k curves (solid blue, labelled ``k=``), iso-b curves (solid red, ``b=``), the
        identity grid ``K = k``, ``B + b0 = b`` (dashed grey), the exact stability boundary
        ``K_max(B)`` (bold black). Axes: ``K`` [N/m] and ``B + b0`` [N s/m] (Florens et al.
        Fig. 9 convention).

    Raises
    ------
    ConfigError
        If matplotlib is missing (message: install the plot extra).
    """
    fig, ax = _figure(ax, (7.5, 6.0))
    g = result
    b0 = g.b_bias
    loop = g.loop
    # identity grid
    kv, bv = g.k_values, g.b_values
    Bid = bv  # on the B + b0 axis, the identity is b itself
    for k in kv:
        ax.plot([k, k], [Bid.min(), Bid.max()], ls="--", color="0.6", lw=0.8, zorder=1)
    for b in bv:
        ax.plot([kv.min(), kv.max()], [b, b], ls="--", color="0.6", lw=0.8, zorder=1)
    # iso curves
    if g.iso_k_K is not None:
        ikK, ikB = g.iso_k_K, g.iso_k_B + b0
        ibK, ibB = g.iso_b_K, g.iso_b_B + b0
    else:
        ikK, ikB = g.K, g.B_axis
        ibK, ibB = g.K.T, g.B_axis.T

    labels = []   # (x, y, text, colour, from_start), placed once the limits are known
    for i, k in enumerate(kv):
        ax.plot(ikK[i], ikB[i], color="tab:blue", lw=1.2, zorder=3,
                label="iso-k (felt stiffness k)" if i == 0 else None)
        if i % label_every == 0:
            labels.append((ikK[i], ikB[i], f"k={k:.3g}", "tab:blue", True))
    for j, b in enumerate(bv):
        ax.plot(ibK[j], ibB[j], color="tab:red", lw=1.2, zorder=3,
                label="iso-b (felt damping b)" if j == 0 else None)
        if j % label_every == 0:
            labels.append((ibK[j], ibB[j], f"b={b:.3g}", "tab:red", False))
    ax.plot([], [], ls="--", color="0.6", lw=0.8, label="identity (K = k, B + b0 = b)")
    # boundary
    bK = np.where(np.isfinite(g.boundary_K), g.boundary_K, np.nan)
    ax.plot(bK, g.boundary_B_axis, color="black", lw=2.6, zorder=4,
            label="stability boundary (spectral radius 1)")
    # limits: the grid, with a margin
    xs = np.concatenate([np.ravel(ikK), np.ravel(ibK)])
    ys = np.concatenate([np.ravel(ikB), np.ravel(ibB)])
    xs, ys = xs[np.isfinite(xs)], ys[np.isfinite(ys)]
    if xs.size and ys.size:
        xr = max(xs.max(), 1e-12)
        ax.set_xlim(min(0.0, xs.min()), xr * 1.12)
        yr = ys.max() - min(0.0, ys.min())
        ax.set_ylim(min(0.0, ys.min()) - 0.03 * yr, ys.max() + 0.08 * max(yr, 1e-12))
    _place_labels(ax, labels)
    if loop.mass == 1 and loop.rate_hz == 1:   # the paper's normalised units, m = T = 1
        ax.set_xlabel("virtual stiffness K T²/m (normalised, m = T = 1)")
        ax.set_ylabel("virtual damping (B + b0) T/m (normalised)" if b0
                      else "virtual damping B T/m (normalised, m = T = 1)")
    else:
        ax.set_xlabel("virtual stiffness K [N/m]")
        ax.set_ylabel("virtual damping B + b0 [N s/m]" if b0 else "virtual damping B [N s/m]")
    if title is None:
        title = (f"m = {loop.mass:g} kg, b0 = {loop.friction:g} N s/m, "
                 f"{loop.rate_hz:g} Hz, d = {loop.delay}, hold = {loop.hold}")
    ax.set_title(title, fontsize=10)
    ax.grid(False)
    ax.legend(fontsize=7, loc="upper right", framealpha=0.9)
    fig.tight_layout()
    return fig


def _figure(ax, size: tuple):
    """The figure and axes a chart draws into: ``ax`` and its figure, or a new figure of
    ``size`` (width, height) [in] at 110 dpi (:func:`pyplot`, so a missing matplotlib
    raises its ConfigError either way)."""
    plt = pyplot()
    if ax is None:
        return plt.subplots(figsize=size, dpi=110)
    return ax.figure, ax


def _place_labels(ax, labels, fontsize: float = 7.0) -> None:
    """Write each curve's label where it overlaps no label already placed.

    Each label is tried at its preferred end of its curve (iso-k: the start, iso-b: the
    end), then at points moving along the curve, in display coordinates; a label that
    finds no free place is left out rather than drawn over another.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
        Axes whose limits are final.
    labels : list of (x, y, text, colour, from_start)
        Curve points (arrays, data units), the text, its colour and which end to prefer.
    fontsize : float
        Label size [pt].
    """
    fig = ax.figure
    px = fig.dpi / 72.0 * fontsize          # one character's height [pixels]
    taken = []                               # boxes (x0, y0, x1, y1) [pixels]
    box = ax.get_window_extent()
    for x, y, text, color, from_start in labels:
        ok = np.flatnonzero(np.isfinite(x) & np.isfinite(y))
        if not ok.size:
            continue
        order = ok if from_start else ok[::-1]
        pts = ax.transData.transform(np.column_stack([x[order], y[order]]))
        w, h = 0.62 * px * len(text) + 5.0, 1.15 * px + 1.0   # with a margin
        step = max(1, len(order) // 40)
        for n in range(0, len(order), step):
            x0, y0 = pts[n] + 2.0
            cand = (x0, y0, x0 + w, y0 + h)
            inside = (box.x0 <= cand[0] and cand[2] <= box.x1 + 20 and box.y0 <= cand[1]
                      and cand[3] <= box.y1)
            if inside and not any(c[0] < t[2] and t[0] < c[2] and c[1] < t[3] and t[1] < c[3]
                                  for c in (cand,) for t in taken):
                taken.append(cand)
                i = order[n]
                ax.annotate(text, (x[i], y[i]), color=color, fontsize=fontsize,
                            xytext=(2, 2), textcoords="offset points")
                break


def figure_formats() -> tuple:
    """File extensions matplotlib can write here (without the dot).

    Returns
    -------
    tuple of str
        Sorted, e.g. ``("eps", "jpeg", ..., "png", "svg")``.

    Raises
    ------
    ConfigError
        If matplotlib is missing.
    """
    plt = pyplot()
    fig = plt.figure()
    try:
        return tuple(sorted(fig.canvas.get_supported_filetypes()))
    finally:
        plt.close(fig)


def is_axes(obj) -> bool:
    """Whether ``obj`` is matplotlib axes (a chart's target; the API imports no
    matplotlib of its own).

    Parameters
    ----------
    obj : object

    Returns
    -------
    bool
        False too where matplotlib is not installed (no axes can exist then).
    """
    try:
        from matplotlib.axes import Axes
    except ImportError:  # pragma: no cover - depends on the environment
        return False
    return isinstance(obj, Axes)


def check_figure_path(path: str, key: str = "--out") -> None:
    """Refuse, before any work, a figure path that :func:`save_figure` could not write.

    Parameters
    ----------
    path : str
        Output file; its extension picks the format.
    key : str, optional
        Option or key named in the error.

    Raises
    ------
    ConfigError
        With ``key``: no or an unsupported extension (the message lists the supported
        ones), a directory that does not exist, or a path that is a directory; or
        matplotlib missing.
    """
    ext = os.path.splitext(path)[1].lower().lstrip(".")
    fmts = figure_formats()
    if ext not in fmts:
        what = f"unsupported figure format '.{ext}'" if ext else "no file extension"
        raise ConfigError(f"{what} in {path!r}; valid: {', '.join('.' + f for f in fmts)}",
                          key=key)
    check_output_path(path, key)


def check_output_path(path: str, key: str) -> None:
    """Refuse an output file that cannot be written (:func:`hapsim.outputs.check_writable`).

    Parameters
    ----------
    path : str
        Output file.
    key : str
        Option or key named in the error.

    Raises
    ------
    ConfigError
        With ``key``.
    """
    from hapsim.outputs import check_writable   # one check for every command's outputs
    check_writable(path, key)


def plot_poles(report, ax=None, title: str | None = None):
    """The closed-loop poles of a checked scene or a rendered loop in the z-plane.

    Parameters
    ----------
    report : hapsim.api.CheckReport or hapsim.api.RenderReport
        Its ``eigenvalues`` (list of [re, im]) and ``rendered`` (the felt mode: ``z_re``,
        ``z_im``, ``k`` [N/m], ``b`` [N s/m], ``f0_hz``).
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when None.
    title : str, optional
        Default: the scene's path (a check) or the felt (k, b).

    Returns
    -------
    matplotlib.figure.Figure
        The unit circle (the stability boundary of a sampled system), every pole (x) and
        the felt pair (o, labelled with k, b and f0). Axes: Re z, Im z.

    Raises
    ------
    ConfigError
        If matplotlib is missing.
    """
    fig, ax = _figure(ax, (5.5, 5.5))
    t = np.linspace(0.0, 2.0 * np.pi, 400)
    ax.plot(np.cos(t), np.sin(t), color="0.6", lw=1.0, label="|z| = 1 (stability boundary)")
    z = np.array([[np.nan if v is None else v for v in e] for e in report.eigenvalues],
                 dtype=float).reshape(-1, 2)
    ax.plot(z[:, 0], z[:, 1], "x", color="C0", label="closed-loop poles")
    r = report.rendered
    if r is not None:
        zr = np.array([r["z_re"], r["z_re"]]), np.array([r["z_im"], -r["z_im"]])
        ax.plot(*zr, "o", mfc="none", color="C3", ms=10,
                label=f"felt: k = {r['k']:.4g} N/m, b = {r['b']:.3g} N s/m, "
                      f"f0 = {r['f0_hz']:.3g} Hz")
    ax.set_aspect("equal")
    ax.set_xlabel("Re z")
    ax.set_ylabel("Im z")
    ax.axhline(0.0, color="0.85", lw=0.8)
    ax.axvline(0.0, color="0.85", lw=0.8)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), fontsize=8, frameon=False)
    ax.set_title(title or getattr(report, "scene", None) or "closed-loop poles")
    fig.tight_layout()
    return fig


def plot_felt(report, ax=None, title: str | None = None):
    """A run's felt (k, b): what was simulated, predicted, measured and asked for, in the
    (k, b) plane.

    Parameters
    ----------
    report : hapsim.api.RunReport
        Its ``virtual`` (``K`` [N/m], ``B`` [N s/m] of the port link, when one), its
        ``predicted`` and ``measured`` (``k`` [N/m], ``b`` [N s/m]; the measured
        ``k_unc``, ``b_unc``: the stated uncertainty) and its ``targets``.
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; a new figure is made when None.
    title : str, optional
        Default: the scene's path.

    Returns
    -------
    matplotlib.figure.Figure
        Axes: k [N/m] (x), b [N s/m] (y), or a rotary joint's units (the report's
        ``units``). The simulated (K, B) (square), the predicted
        felt pair (circle; the least damped closed-loop pole pair read as m s^2 + b s + k,
        Florens, Voda & Urma), the measured pair with its stated uncertainty (cross with
        error bars; matrix pencil, Hua & Sarkar 1990) and each target (star).

    Raises
    ------
    ConfigError
        If matplotlib is missing.
    """
    fig, ax = _figure(ax, (6.0, 4.5))
    from hapsim.drivers import axis_units, in_axis_units
    u = getattr(report, "units", None) or axis_units(None)

    def say(text):          # (a rotary joint's run: its units)
        return in_axis_units(text, u)

    def pair(d, k="k", b="b"):
        if not d or d.get(k) is None or d.get(b) is None:
            return None
        return float(d[k]), float(d[b])

    v = pair(report.virtual, "K", "B")
    if v is not None:
        ax.plot(*v, "s", mfc="none", color="0.5", ms=9,
                label=say(f"simulated K = {v[0]:.4g} N/m, B = {v[1]:.3g} N s/m"))
    p = pair(report.predicted)
    if p is not None:
        ax.plot(*p, "o", mfc="none", color="C0", ms=12,
                label=say(f"predicted k = {p[0]:.4g} N/m, b = {p[1]:.3g} N s/m"))
    m = pair(report.measured)
    if m is not None:
        unc = report.measured
        ax.errorbar(*m, xerr=unc.get("k_unc") or 0.0, yerr=unc.get("b_unc") or 0.0,
                    fmt="x", color="C3", ms=9, capsize=3,
                    label=say(f"measured k = {m[0]:.4g} N/m, b = {m[1]:.3g} N s/m"))
    for t in report.targets or []:
        tp = pair(t)
        if tp is not None:
            ax.plot(*tp, "*", color="C2", ms=12,
                    label=say(f"target ({t.get('link')}): k = {tp[0]:.4g} N/m, b = "
                              f"{tp[1]:.3g} N s/m"))
    ax.set_xlabel(say("k [N/m]"))
    ax.set_ylabel(say("b [N s/m]"))
    ax.margins(0.25)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.15), fontsize=8, frameon=False)
    ax.set_title(title or getattr(report, "scene", None) or "felt (k, b)")
    fig.tight_layout()
    return fig


def plot_identify(fit, record=None, units=None):
    """A device identification: the measured response against the fitted model.

    Parameters
    ----------
    fit : hapsim.analysis.device_fit.DeviceFit or hapsim.api.IdentifyReport
        The fit (``model`` [m], shape (n,), ``period`` [s], ``mass``, ``friction``,
        ``coulomb``, ``delay``, ``hold``), or the API's report (its ``fit`` and
        ``record``).
    record : dict, optional
        The excitation record (``position`` [m], shape (N,); ``loop.fitted_rows``: the rows
        fitted); taken from the report when ``fit`` is one.
    units : dict, optional
        :func:`hapsim.drivers.axis_units` of the device's axis (default SI; a rotary
        joint's: mrad, urad, kg m^2, N m s/rad, N m).

    Returns
    -------
    matplotlib.figure.Figure
        Top: measured and model positions [mm] against time [s]; bottom: model - measured
        [um].

    Raises
    ------
    ConfigError
        If matplotlib is missing.
    """
    if record is None:
        fit, record = fit.fit, fit.record
    plt = pyplot()
    # the fit covers the rows it was given (the whole record: every stretch of
    # consecutive STATEs), drawn at their ticks (a lost STATE leaves a gap in time)
    a, _ = record["loop"].get("fitted_rows", (0, fit.n_samples))
    x = record["position"][a:a + fit.n_samples]
    seq = record.get("seq")
    ticks = (np.asarray(seq[a:a + fit.n_samples], float) if seq is not None
             and len(seq) >= a + fit.n_samples else a + np.arange(fit.n_samples))
    t = ticks * fit.period
    fig, (a1, a2) = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
    a1.plot(t, x * 1e3, lw=0.8, label="measured")
    a1.plot(t, fit.model * 1e3, lw=0.8, ls="--", label="model")
    from hapsim.drivers import axis_units, in_axis_units
    u = units or axis_units(None)
    a1.set_ylabel(in_axis_units("position [mm]", u))
    a1.legend(loc="upper right")
    a1.set_title(in_axis_units(f"m = {fit.mass.value:.4g} kg, b0 = {fit.friction.value:.4g} "
                               f"N s/m, fc = {fit.coulomb.value:.3g} N, d = {fit.delay}, "
                               f"{fit.hold}", u))
    a2.plot(t, (fit.model - x) * 1e6, lw=0.6)
    a2.set_ylabel(in_axis_units("model - measured [um]", u))
    a2.set_xlabel("time [s]")
    return fig


def save_figure(fig, path: str) -> None:
    """Write ``fig`` to ``path`` (format from the extension) and close it.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    path : str
        Output file, e.g. ``docs/fig8_ideal.png``.

    Raises
    ------
    ConfigError
        If matplotlib is missing, or the file cannot be written (format or OS error; key
        ``path``).
    """
    plt = pyplot()
    try:
        fig.savefig(path)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"cannot write figure {path!r}: {exc}", key="path") from None
    finally:
        plt.close(fig)


