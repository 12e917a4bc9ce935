"""Figures of ``hapsim bench`` (charts 1-3). Imports matplotlib lazily, as :mod:`hapsim.plots`.

Each function takes the plain data returned by :mod:`hapsim.bench` and returns a figure;
:func:`hapsim.plots.save_figure` writes it.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.plots import pyplot  # the one place matplotlib is imported (lazily)

__all__ = ["plot_accuracy_vs_rate", "plot_accuracy_vs_cost", "plot_capacity"]

_D_COLORS = {0: "tab:blue", 1: "tab:orange", 2: "tab:red"}
_I_COLORS = {"centred": "tab:blue", "symplectic_euler": "tab:green", "exact": "tab:purple"}
_FLOOR = 1e-16
#: Floor of chart 1's error axis: the calibrated loops sit at round-off (~1e-15) and are
#: drawn on it, so the axis spans the naive errors (1e-4 ... 1e3) instead of 19 decades.
_RATE_FLOOR = 1e-7


def _arr(v):
    return np.array([np.nan if x is None else float(x) for x in v])


def plot_accuracy_vs_rate(data: dict):
    """Chart 1: felt-(k, b) error against rate, one panel per target.

    Parameters
    ----------
    data : dict
        :func:`hapsim.bench.accuracy.accuracy_vs_rate` output.

    Returns
    -------
    matplotlib.figure.Figure
        Log-log error [-] against rate [Hz]: naive curves solid (colour = delay d, circle =
        ZOH, square = ideal hold), calibrated dashed (round-off, ~1e-15: drawn on the axis
        floor 1e-7, so the axis spans the naive errors). On the rate axis, a filled triangle marks each naive loop's stability
        boundary (spectral radius 1, unstable below) and an open one the rate below which
        the calibrated target is not renderable. Rates where the naive loop is stable but
        has no felt pair (its slowest mode is real) are gaps in the curve, marked by crosses
        (ZOH) or pluses (ideal) in the top band, one row per curve.

    Raises
    ------
    hapsim.errors.ConfigError
        If matplotlib is missing.
    """
    plt = pyplot()
    tg = data["targets"]
    fig, axes = plt.subplots(1, len(tg), figsize=(5.2 * len(tg), 5.4), dpi=110, squeeze=False)
    rates = np.array(data["rates"])
    band = {}  # (hold, delay) -> y of its "no felt pair" row
    unstable_above = False
    for ax, t in zip(axes[0], tg):
        for c in t["curves"]:
            e = _arr(c["err"])
            naive = c["method"] == "naive"
            col = _D_COLORS.get(c["delay"], "k")
            mk = "o" if c["hold"] == "zoh" else "s"
            y = np.maximum(e, _RATE_FLOOR) if not naive else e
            ax.plot(rates, y, ls="-" if naive else "--", marker=mk, ms=3.5, color=col,
                    lw=1.4 if naive else 0.9, alpha=1.0 if naive else 0.6,
                    mfc=col if c["hold"] == "zoh" else "white")
            if naive:
                for x in c.get("stability_boundary_hz", []):
                    unstable_above |= not x["stable_above"]
                    ax.plot([x["rate_hz"]], [_RATE_FLOOR / 3], marker="^" if x["stable_above"]
                            else "v",
                            ms=8, color=col, clip_on=False, zorder=5)
                gap = [r for r, st in zip(rates, c.get("status", [])) if st == "no felt pair"]
                if gap:
                    yb = band.setdefault((c["hold"], c["delay"]),
                                         30.0 * 2.1 ** (c["delay"] + 3 * (c["hold"] != "zoh")))
                    ax.plot(gap, [yb] * len(gap), ls="", marker="x" if c["hold"] == "zoh"
                            else "+", ms=5, mew=1.3, color=col)
            else:
                b = c.get("works_from_hz")
                if b is not None and b > rates[0] * 1.001:
                    ax.plot([b], [_RATE_FLOOR / 3], marker="v", ms=8, color=col, mfc="white",
                            clip_on=False, zorder=5)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(_RATE_FLOOR / 5, 5e3)
        ax.axhline(0.01, color="0.5", lw=0.8, ls=":")
        ax.axhline(14.0, color="0.8", lw=0.6)
        ax.text(rates[0] * 1.05, 0.013, "1 %", color="0.4", fontsize=8)
        ax.text(rates[-1] / 1.05, 12.0, "above: no felt pair", color="0.4", fontsize=7,
                va="top", ha="right")
        ax.set_xlabel("sample rate [Hz]")
        ax.set_title(f"{t['name']}: k = {t['k']:g} N/m, b = {t['b']:g} N s/m", fontsize=10)
        ax.grid(True, which="major", alpha=0.3)
    axes[0][0].set_ylabel("relative error of felt (k, b)  [max of the two]")
    # legend built by hand
    h = []
    for d, col in _D_COLORS.items():
        h.append(plt.Line2D([], [], color=col, lw=2, label=f"delay d = {d}"))
    h += [plt.Line2D([], [], color="k", marker="o", ls="", label="ZOH hold"),
          plt.Line2D([], [], color="k", marker="s", mfc="white", ls="", label="ideal hold"),
          plt.Line2D([], [], color="k", ls="-", label="naive K = k, B = b - b0"),
          plt.Line2D([], [], color="k", ls="--", alpha=0.6,
                     label=f"calibrated (round-off ~1e-15, drawn at {_RATE_FLOOR:.0e})"),
          plt.Line2D([], [], color="k", marker="^", ls="",
                     label="naive: stability boundary, |z| = 1 (unstable below)"),
          plt.Line2D([], [], color="k", marker="v", mfc="white", ls="",
                     label="calibrated: not renderable below"),
          plt.Line2D([], [], color="k", marker="x", ls="",
                     label="naive: stable, no felt pair (slowest mode real; ZOH x, ideal +)")]
    if unstable_above:
        h.append(plt.Line2D([], [], color="k", marker="v", ls="",
                            label="naive: stability boundary (unstable above)"))
    dev = data["device"]
    fig.suptitle(f"Felt (k, b) error against sample rate - device m = {dev['mass']:g} kg, "
                 f"b0 = {dev['friction']:g} N s/m", fontsize=11)
    fig.legend(handles=h, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.11, 1, 0.96))
    return fig


def plot_accuracy_vs_cost(data: dict):
    """Chart 2: mode error against CPU time per simulated second, per integrator.

    Parameters
    ----------
    data : dict
        :func:`hapsim.bench.cost.accuracy_vs_cost` output.

    Returns
    -------
    matplotlib.figure.Figure
        One panel per network; x: CPU time per simulated second [ms] (ns/sample x rate),
        y: max relative error; solid = eigenfrequency, dotted = damping; points labelled with
        the rate; unstable points drawn as crosses at the top; the Pareto front (frequency
        error) in grey.
    """
    plt = pyplot()
    nets = data["networks"]
    fig, axes = plt.subplots(1, len(nets), figsize=(6.4 * len(nets), 5.2), dpi=110,
                             squeeze=False)
    for ax, net in zip(axes[0], nets):
        top = 3.0
        allpts = []
        for integ, col in _I_COLORS.items():
            pts = [p for p in net["points"] if p["integrator"] == integ]
            if not pts:
                continue
            x = np.array([p["cpu_ms_per_simulated_s"] for p in pts])
            fe = _arr([p["freq_err"] for p in pts])
            de = _arr([p["damp_err"] for p in pts])
            ns = net["ns_per_sample"][integ]
            ax.plot(x, np.maximum(fe, _FLOOR), "-o", color=col, ms=4,
                    label=f"{integ} ({ns:.0f} ns/sample, x{net['ratio_to_centred'][integ]:.1f})")
            ax.plot(x, np.maximum(de, _FLOOR), ":", marker=".", color=col, ms=4)
            for p, xi, yi in zip(pts, x, fe):
                if p["stable"] and math.isfinite(yi):
                    ax.annotate(f"{p['rate_hz'] / 1000:g}k", (xi, max(yi, _FLOOR)), fontsize=6.5,
                                color=col, xytext=(3, 3), textcoords="offset points")
                    allpts.append((xi, max(yi, _FLOOR)))
                elif not p["stable"]:
                    ax.plot([xi], [top], "x", color=col, ms=9, mew=2)
                    ax.annotate(f"{p['rate_hz'] / 1000:g}k unstable", (xi, top), fontsize=6.5,
                                color=col, xytext=(3, -10), textcoords="offset points")
        if allpts:  # Pareto front: lower error at no higher cost
            allpts.sort()
            front, best = [], math.inf
            for xi, yi in allpts:
                if yi < best:
                    front.append((xi, yi))
                    best = yi
            fx, fy = zip(*front)
            ax.step(fx, fy, where="post", color="0.6", lw=3, alpha=0.35, zorder=0,
                    label="Pareto front (frequency)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(1e-17, 10)
        ax.set_xlabel("CPU time per simulated second [ms]  (= ns/sample x rate)")
        ax.set_title(f"{net['name']}: {net['description']}", fontsize=9.5)
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7.5, loc="center right")
    axes[0][0].set_ylabel("max relative error of modes (solid: frequency, dotted: damping)")
    fig.suptitle("Virtual modes: accuracy against cost per integrator "
                 "(vs continuous eigenvalues)", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return fig


def plot_capacity(data: dict):
    """Chart 3: loop capacity over a real pty, daemon against the raw echo floor.

    Parameters
    ----------
    data : dict
        :func:`hapsim.bench.capacity.loop_capacity` output.

    Returns
    -------
    matplotlib.figure.Figure
        Left: host turnaround p50/p99/p999 [us] against rate for the raw echo and the
        daemon, and the period. Right: missed deadlines [%] of each. A note replaces the daemon
        curves when it is not available.
    """
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12.5, 5.8), dpi=110)
    rates = np.array(data["rates"])
    sources = []
    styles = {"p50": ("-", "o"), "p99": ("--", "s"), "p999": (":", "^")}
    for key, col, lab in (("echo", "tab:gray", "raw pty echo (floor)"),
                          ("daemon", "tab:blue", "hapsim daemon + mock")):
        rows = data.get(key) or []
        if not rows:
            continue
        for q, (ls, mk) in styles.items():
            y = _arr([r.get("turnaround_us", {}).get(q) for r in rows])
            a1.plot(rates[:len(y)], y, ls=ls, marker=mk, ms=4, color=col)
        sources.append(plt.Line2D([], [], color=col, lw=2.5, label=lab))
        miss = _arr([r.get("missed_pct") for r in rows])
        a2.plot(rates[:len(miss)], np.maximum(miss, 1e-3), "-o", color=col, label=lab)
    a1.plot(rates, 1e6 / rates, color="k", lw=1.2)
    quantiles = [plt.Line2D([], [], color="0.3", ls=ls, marker=mk, ms=5, lw=1.4, label=q)
                 for q, (ls, mk) in styles.items()]
    if data.get("daemon_note"):
        a1.text(0.03, 0.03, data["daemon_note"], transform=a1.transAxes, fontsize=8,
                color="tab:red", va="bottom", wrap=True)
    a1.set_xscale("log")
    a1.set_yscale("log")
    a1.set_xlabel("loop rate [Hz]")
    a1.set_ylabel("turnaround [us]")
    a1.set_title("host turnaround: message read -> reply written", fontsize=10)
    a1.grid(True, which="both", alpha=0.3)
    a1.legend(handles=sources + quantiles + [plt.Line2D([], [], color="k", lw=1.2,
                                                        label="period 1/rate")],
              fontsize=7.5, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.13),
              handlelength=4.5)
    a2.set_xscale("log")
    a2.set_yscale("log")
    a2.set_xlabel("loop rate [Hz]")
    a2.set_ylabel("missed deadlines [% of samples] (0 drawn at 1e-3)")
    a2.set_title("missed deadlines", fontsize=10)
    a2.grid(True, which="both", alpha=0.3)
    a2.legend(fontsize=8)
    fig.suptitle(f"Loop capacity over a real pty ({data.get('machine', '')})", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return fig
