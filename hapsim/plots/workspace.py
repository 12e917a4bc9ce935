"""Charts of a multi-DoF device's workspace: the stiffness limit over it (``hapsim
kinematics --grid --out``) and an n-D scene with its felt stiffness ellipses (``hapsim
check --plot`` on a 2-D or 3-D scene). Imports matplotlib lazily through :mod:`hapsim.plots`.
"""

from __future__ import annotations

import numpy as np

from hapsim.plots import pyplot  # the one place matplotlib is imported (lazily)

__all__ = ["plot_workspace", "plot_scene_nd"]


def plot_workspace(res, title: str | None = None):
    """``K_max`` along the lightest principal axis of the Cartesian mass, over the
    configurations of a :class:`hapsim.analysis.direction_limits.WorkspaceLimits`.

    Parameters
    ----------
    res : hapsim.analysis.direction_limits.WorkspaceLimits
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
        Handle positions [m] (x, y; for a 3-D device the x-z projection) coloured by
        ``K_max`` [N/m] along the lightest axis; the refused configurations as grey
        crosses. Right: ``K_max`` along the lightest axis against its mass eigenvalue
        [kg] (the configuration-dependent mass sets the limit).
    """
    plt = pyplot()
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


def _ellipse_points(k2: np.ndarray, centre: np.ndarray, scale: float) -> np.ndarray:
    """Outline (100, 2) of the stiffness ellipse of a 2 x 2 block: semi-axes along the
    eigenvectors of its symmetric part, ``scale`` [m per N/m] times the eigenvalues."""
    w, V = np.linalg.eigh(0.5 * (k2 + k2.T))
    t = np.linspace(0.0, 2.0 * np.pi, 100)
    pts = (V * (scale * np.maximum(w, 0.0))) @ np.vstack([np.cos(t), np.sin(t)])
    return centre[:, None] + pts


def plot_scene_nd(scene, chk, felt=None, title: str | None = None):
    """A 2-D or 3-D scene over its device's workspace, with the felt stiffness ellipses.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    chk : hapsim.analysis.scene_check.SceneCheckND
        Its check (the felt matrices at the handle's rest position).
    felt : hapsim.analysis.scene_check.WorkspaceFelt, optional
        The workspace and the felt matrices over it (a kinematic device).
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
        The plane (x, y), or for a 3-D scene the projection on (x, z): the workspace
        (grey points), grounds (black), masses (blue), planes (lines along their surface),
        contacts (circles of their threshold about their ground), the felt stiffness
        ellipse at the handle (red: semi-axes along the eigenvectors of the symmetric
        part of ``k``, proportional to its eigenvalues [N/m]) and, over the workspace,
        the felt ellipses of the same port links at other configurations (grey; an
        unstable configuration as a red cross).
    """
    plt = pyplot()
    n = scene.dimension
    ax_i = (0, 1) if n == 2 else (0, 2)
    lab = ("x [m]", "y [m]") if n == 2 else ("x [m]", "z [m]")
    fig, ax = plt.subplots(figsize=(7, 6.5))
    if felt is not None and felt.workspace.size:
        W = felt.workspace[:, ax_i]
        ax.scatter(W[:, 0], W[:, 1], s=3, color="0.85", label=f"workspace (joints "
                   f"\u00b1{felt.span_deg:g} deg)", zorder=0)
    pos = {m.name: m.x0 for m in scene.masses}
    g = np.array([m.x0[list(ax_i)] for m in scene.masses if m.kind == "ground"])
    v = np.array([m.x0[list(ax_i)] for m in scene.masses if m.kind == "mass"])
    if len(g):
        ax.scatter(g[:, 0], g[:, 1], s=8, color="k", label="grounds", zorder=2)
    if len(v):
        ax.scatter(v[:, 0], v[:, 1], s=10, color="tab:blue", label="masses", zorder=2)
    hand = scene.device.position[list(ax_i)]
    for lk in scene.links:
        a, b = pos[lk.m1][list(ax_i)], pos[lk.m2][list(ax_i)]
        ax.plot([a[0], b[0]], [a[1], b[1]], color="tab:blue", lw=0.5, alpha=0.5, zorder=1)
        if lk.kind == "contact":
            other = lk.m2 if lk.m1 == scene.port.name else lk.m1
            c = pos[other][list(ax_i)]
            t = np.linspace(0, 2 * np.pi, 200)
            ax.plot(c[0] + lk.threshold * np.cos(t), c[1] + lk.threshold * np.sin(t),
                    color="k", lw=1.2, zorder=1)
    span = 0.05
    for pl in scene.planes:
        u = pl.normal[list(ax_i)]
        if np.linalg.norm(u) < 1e-9:
            continue
        x = scene.device.position
        p0 = (x - (pl.normal @ x - pl.offset) * pl.normal)[list(ax_i)]  # nearest point
        t = np.array([-u[1], u[0]]) / np.linalg.norm(u)
        ax.plot([p0[0] - span * t[0], p0[0] + span * t[0]],
                [p0[1] - span * t[1], p0[1] + span * t[1]], color="k", lw=2, zorder=1)
        ax.annotate("", p0 + 0.01 * u / np.linalg.norm(u), p0,
                    arrowprops=dict(arrowstyle="->", color="k"))
    ks = [chk.render.felt_stiffness] if chk.render.felt_stiffness is not None else []
    if felt is not None:
        ks += [k for k in felt.felt_stiffness if np.all(np.isfinite(k))]
    kmax = max([float(np.max(np.abs(np.linalg.eigvalsh(0.5 * (k + k.T))))) for k in ks]
               or [1.0])
    extent = felt.workspace[:, ax_i] if felt is not None and felt.workspace.size \
        else np.vstack([hand] + ([g] if len(g) else []))
    size = float(np.max(np.ptp(extent, axis=0))) if len(extent) > 1 else 0.05
    scale = 0.06 * max(size, 0.02) / kmax
    sel = np.ix_(ax_i, ax_i)
    if felt is not None:
        for x, k, ok in zip(felt.positions, felt.felt_stiffness, felt.stable):
            c = x[list(ax_i)]
            if not ok or not np.all(np.isfinite(k)):
                ax.plot(c[0], c[1], "x", color="tab:red", ms=6)
                continue
            e = _ellipse_points(k[sel], c, scale)
            ax.plot(e[0], e[1], color="0.4", lw=0.8)
    if chk.render.felt_stiffness is not None:
        e = _ellipse_points(chk.render.felt_stiffness[sel], hand, scale)
        ax.plot(e[0], e[1], color="tab:red", lw=2,
                label=f"felt stiffness at the handle ({kmax:.4g} N/m = "
                      f"{1e3 * scale * kmax:.3g} mm)")
    ax.plot(hand[0], hand[1], "o", color="tab:red", ms=5, label="handle at rest")
    ax.set_xlabel(lab[0])
    ax.set_ylabel(lab[1])
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def plot_modes_nd(scene, res, title: str | None = None, count: int = 6):
    """The lowest modes of a scene without a port, drawn over its rest positions.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    res : hapsim.analysis.modes.SceneModesND
        Its modes (lowest frequency first).
    title : str, optional
    count : int, optional
        Panels: the lowest modes moving along the scene's last axis (the membrane's
        transverse one), one per frequency (a degenerate pair is drawn once).

    Returns
    -------
    matplotlib.figure.Figure
        One panel per mode: the masses at rest in the first two axes (m), coloured by the
        mode shape's component along the last axis (red up, blue down), the grounds grey;
        the panel's title gives the eigenfrequency [Hz] and the damping ratio.
    """
    plt = pyplot()
    n = scene.dimension
    pos = {m.name: np.asarray(m.x0, float) for m in scene.masses}
    grounds = np.array([pos[m.name] for m in scene.masses if m.kind != "mass"]).reshape(-1, n)
    moving = np.array([pos[nm] for nm in res.names]).reshape(-1, n)
    picked = []
    for md in res.modes:
        if md.axis != n - 1:
            continue
        if picked and abs(md.frequency_hz - picked[-1].frequency_hz) <= \
                1e-9 * md.frequency_hz:
            continue
        picked.append(md)
        if len(picked) == count:
            break
    cols = min(3, max(1, len(picked)))
    rows = max(1, -(-len(picked) // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.ravel()[len(picked):]:
        ax.set_axis_off()
    for ax, md in zip(axes.ravel(), picked):
        w = md.shape[:, n - 1]
        lim = float(np.max(np.abs(w))) or 1.0
        if grounds.size:
            ax.scatter(grounds[:, 0], grounds[:, 1], s=8, color="0.7")
        ax.scatter(moving[:, 0], moving[:, 1], c=w, cmap="coolwarm", vmin=-lim, vmax=lim,
                   s=28)
        ax.set_title(f"{md.frequency_hz:.2f} Hz, zeta {md.damping_ratio:.2g}", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]", fontsize=8)
        ax.set_ylabel("y [m]", fontsize=8)
        ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig
