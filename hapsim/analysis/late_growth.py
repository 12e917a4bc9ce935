"""The scene's growth tables for the host loop's lateness guard
(:mod:`hapsim.kernels.late_growth`, whose notes give the rule): the poles of the scene's
temporary hybrid system at each delay a late force is held over, each mode followed from
its pole on time. One rule for every dimension: a 1-D scene's poles are its THS's as the
port's record shows them, a 2-D or 3-D scene's the eigenvalues of its closed loop
(:func:`hapsim.analysis.scene_check.closed_loop_nd`).
"""

from __future__ import annotations

import numpy as np

import dataclasses

from hapsim.analysis.prediction import predicted_poles, timed_scene
from hapsim.kernels.late_growth import (GROWTH_MODES, GROWTH_POINTS, LATE_GROWTH_SLACK,
                                        LateGrowth)

__all__ = ["late_growth", "min_cost_assignment"]


def late_growth(scene, watchdog_s: float, latest_s: float = 0.0,
                points: int = 24):
    """The scene's growth tables for the host loop's lateness guard
    (:mod:`hapsim.kernels.late_growth`: ``g_k(h)``, the growth of mode ``k`` over a force
    held ``h`` ticks, from the loop frozen at each delay of the hold).

    The loop's poles that the port's record shows
    (:func:`hapsim.analysis.prediction.predicted_poles`, the scene's THS with ``D``
    periods of delay; for a 2-D or 3-D scene the non-zero eigenvalues of its closed loop,
    :func:`hapsim.analysis.scene_check.closed_loop_nd`, with ``D`` periods) are predicted at ``points`` delays spread evenly over ``d .. d + H``
    (``H`` the watchdog's periods: a longer hold ends at zero force), one of each conjugate
    pair, as ``s = ln z`` [per period]. Each mode is followed from its pole on time as the
    delay grows: at each next delay, each followed mode takes a pole, each pole once, the
    distances in the ``s`` plane least in sum (a pole the delay line adds starts near
    ``z = 0``, far from every followed mode). Its growth a period, ``Re s``, is
    interpolated linearly between the delays: it is smooth in ``D``
    (``configs/wall.yaml``: 2.7e-3, 7.7e-3, 12.3e-3 a period at 2, 3, 4 periods). The
    modes that grow at some delay are kept, at most
    :data:`~hapsim.kernels.late_growth.GROWTH_MODES`, those that grow the most first.

    Parameters
    ----------
    scene : hapsim.scene.Scene or hapsim.scene.SceneND
        The run's calibrated scene (its own delay ``d``, a whole number of periods for the
        framed protocol's tick bookkeeping).
    watchdog_s : float
        The device's watchdog [s] (> 0).
    latest_s : float
        A board's render latency after its read [s], added to every delay (0: the framed
        protocol's devices).
    points : int
        Delays predicted (>= 2).

    Returns
    -------
    hapsim.kernels.late_growth.LateGrowth or None
        None where the scene has no device or the prediction fails at some delay (the
        guard is then off; the run's own prediction says why).
    """
    if scene.device is None:
        return None
    T = scene.period
    d = int(round(float(scene.device.delay)))
    H = max(int(np.ceil(float(watchdog_s) / T - 1e-9)), 1)
    lags = np.unique(np.round(np.linspace(0, H, max(int(points), 2))).astype(int))
    grid = []
    try:
        for l in lags:
            z = _poles(scene, float(latest_s) + l * T)
            z = z[(np.abs(z) > 0.0) & (z.imag >= 0.0)]
            if z.size == 0:
                return None
            grid.append(np.log(z))
    except Exception:  # an advisory table: no guard where the scene cannot be predicted
        return None
    rates = _follow_modes(grid)                             # (modes, lags): Re s
    every = np.array([np.interp(np.arange(H + 1), lags, r) for r in rates])
    # c_k(d + l), l = 0 .. H, less the slack
    c = every - np.maximum(every[:, :1], 0.0) - LATE_GROWTH_SLACK * T
    # the modes that can grow under lateness, the most first (at least one row: a loop
    # stable at every delay of the table keeps its least stable mode, never above zero)
    order = np.argsort(-c.max(axis=1), kind="stable")
    grows = int(np.count_nonzero(c.max(axis=1) > 0.0))
    c = c[order[:min(max(grows, 1), GROWTH_MODES)]]
    prefix = np.concatenate((np.zeros((c.shape[0], 1)), np.cumsum(c, axis=1)), axis=1)
    n = min(H + 1, GROWTH_POINTS)
    step = (H + 1) / n
    table = np.array([np.interp(np.arange(n + 1) * step, np.arange(H + 2), p)
                      for p in prefix])
    stable = np.flatnonzero(every.max(axis=0) >= 0.0)       # a mode growing at d + l
    stable_to = d + (int(stable[0]) - 1 if stable.size else H)
    return LateGrowth(tuple(tuple(float(v) for v in row) for row in table), float(step),
                      int(stable_to), d)


#: Eigenvalues of an n-D closed loop at most this far from ``z = 0`` are the delay line's
#: (exact zeros up to round-off: its shift blocks are nilpotent), as
#: :func:`hapsim.analysis.prediction.predicted_poles` leaves out ``|z| <= 1e-9``.
_ZERO_POLE = 1e-9


def _poles(scene, latency_s: float) -> np.ndarray:
    """The loop's non-zero poles with ``latency_s`` [s] added to the device's delay: a 1-D
    scene's as its port's record shows them (:func:`predicted_poles`), a 2-D or 3-D
    scene's the eigenvalues of its closed loop (shape (m,), complex)."""
    if getattr(scene, "dimension", 1) == 1:
        return np.asarray(predicted_poles(timed_scene(scene, latency_s))[0], dtype=complex)
    from hapsim.analysis.scene_check import closed_loop_nd
    dev = scene.device
    delay = dev.delay + latency_s / scene.period
    if float(delay).is_integer():
        delay = int(round(delay))
    A = closed_loop_nd(dataclasses.replace(scene, device=dataclasses.replace(
        dev, delay=delay)))[0]
    z = np.linalg.eigvals(A)
    return z[np.abs(z) > _ZERO_POLE]


def _follow_modes(grid: list) -> np.ndarray:
    """Each mode of ``grid[0]`` followed through the next delays (:func:`late_growth`):
    at each, each followed mode takes a pole, each pole once, the pairs' distances in the
    ``s`` plane least in sum (the assignment problem: :func:`min_cost_assignment`). Where
    a delay shows fewer poles than modes are followed, its poles are offered as many
    times as it takes (a double pole of a symmetric device, split by round-off into a
    conjugate pair of which one half is kept, stands for two modes; a real pair merging
    into a complex one, counted once, for two).

    Parameters
    ----------
    grid : list of ndarray of complex
        ``s = ln z`` [per period] of the poles at each delay (one of each conjugate pair;
        none empty).

    Returns
    -------
    ndarray of float, shape (modes, delays)
        ``Re s`` of each followed mode at each delay.
    """
    s = np.array(grid[0], dtype=complex)
    out = [s.real.copy()]
    for nxt in grid[1:]:
        nxt = np.tile(nxt, -(-s.size // nxt.size))
        s = nxt[min_cost_assignment(np.abs(s[:, None] - nxt[None, :]))]
        out.append(s.real.copy())
    return np.array(out).T


def min_cost_assignment(cost: np.ndarray) -> np.ndarray:
    """The rows' columns, each column once, whose costs are least in sum: the Hungarian
    method with potentials (Kuhn 1955, Munkres 1957; the O(n^2 m) shortest-augmenting-path
    form, Jonker & Volgenant 1987), a row added at a time, each scan vectorised over the
    columns. The optimum :func:`scipy.optimize.linear_sum_assignment` finds, without
    importing ``scipy.optimize`` on a run's way to its first sample (~0.3 s of start-up,
    docs/startup.md); of two assignments of equal sum, either may be returned.

    Parameters
    ----------
    cost : ndarray of float, shape (n, m), n <= m
        Finite costs.

    Returns
    -------
    ndarray of int, shape (n,)
        The column of each row.

    Raises
    ------
    ValueError
        More rows than columns, or a cost not finite.
    """
    c = np.asarray(cost, dtype=float)
    n, m = c.shape
    if n > m or not np.isfinite(c).all():
        raise ValueError(f"needs finite costs of shape (n, m), n <= m; got {c.shape}")
    u = np.zeros(n + 1)
    v = np.zeros(m + 1)
    row = np.zeros(m + 1, dtype=np.int64)     # the row (1-based) of each column; 0: none
    way = np.zeros(m + 1, dtype=np.int64)
    for i in range(1, n + 1):
        row[0] = i
        j0 = 0
        minv = np.full(m + 1, np.inf)
        used = np.zeros(m + 1, dtype=bool)
        while True:
            used[j0] = True
            i0 = row[j0]
            cur = c[i0 - 1] - u[i0] - v[1:]
            free = ~used[1:]
            better = free & (cur < minv[1:])
            minv[1:][better] = cur[better]
            way[1:][better] = j0
            cand = np.where(free, minv[1:], np.inf)
            j1 = int(np.argmin(cand)) + 1
            delta = cand[j1 - 1]
            u[row[used]] += delta
            v[used] -= delta
            minv[~used] -= delta
            j0 = j1
            if row[j0] == 0:
                break
        while j0:
            j1 = way[j0]
            row[j0] = row[j1]
            j0 = j1
    out = np.empty(n, dtype=np.int64)
    assigned = np.flatnonzero(row[1:])
    out[row[1:][assigned] - 1] = assigned
    return out
