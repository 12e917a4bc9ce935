"""The samples the device fit (:mod:`hapsim.analysis.device_fit`) explains: the stretches
where the device clearly moves one way (Coulomb friction a constant force there, the model
linear), and their cuts where the fitted model nearly stops inside one.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["moving_stretches", "split_at_stops"]


def moving_stretches(x, q, W=5, margin=8, min_len=12, pieces=None):
    """Stretches of samples where the device clearly moves one way.

    The velocity sign is read from ``x[n+W] - x[n-W]``, trusted when that exceeds the
    sensor's reach ``1.5 q + 4 sigma_w`` (``sigma_w``: white noise from the median
    absolute second difference); ``margin`` (> W: the centred difference sees W samples
    ahead and behind) samples are dropped at each end. Inside a stretch the Coulomb
    friction is a constant force (no sticking: the velocity keeps its sign), so the model
    is linear there.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Positions [m].
    q : float >= 0
        Encoder quantum [m] (0: none).
    W, margin, min_len : int
        Half-width of the centred difference, samples dropped at each end, shortest
        stretch kept [samples].
    pieces : list of (int, int), optional
        Row ranges of consecutive ticks with a known input (default: the whole record); a
        stretch never leaves its piece (a lost STATE, a force not known: the model
        restarts from a state of its own).

    Returns
    -------
    tuple of ndarray of int64, each shape (s,)
        ``(starts, ends, dirs)``: the stretches' rows ``starts[i] .. ends[i] - 1`` and
        their directions (+1, -1).
    """
    n = x.size
    if pieces is None:
        pieces = [(0, n)]
    d2 = np.concatenate([np.diff(x[a:b], 2) for a, b in pieces if b - a > 2] or [[0.0]])
    sig = 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / math.sqrt(6.0)
    thr = 1.5 * q + 4.0 * sig + 1e-12
    starts, ends, dirs = [], [], []
    for p0, p1 in pieces:
        xp = x[p0:p1]
        m_ = xp.size
        if m_ <= 2 * W:
            continue
        dv = np.zeros(m_)
        dv[W:m_ - W] = xp[2 * W:] - xp[:m_ - 2 * W]
        sgn = np.where(dv > thr, 1, np.where(dv < -thr, -1, 0))
        k = 0
        while k < m_:
            if sgn[k] == 0:
                k += 1
                continue
            j = k
            while j < m_ and sgn[j] == sgn[k]:
                j += 1
            a_, b_ = k + margin, j - margin
            if b_ - a_ >= min_len:
                starts.append(p0 + a_)
                ends.append(p0 + b_)
                dirs.append(int(sgn[k]))
            k = j
    return (np.array(starts, np.int64), np.array(ends, np.int64), np.array(dirs, np.int64))


def split_at_stops(st, y, min_len=12, ratio=2.0):
    """The stretches cut where the model's velocity comes within ``ratio`` periods of
    reversing: where the device may have stopped for an instant inside a stretch.

    A stretch's linear model holds the Coulomb friction at one sign throughout, but the
    device's own model (:func:`hapsim.kernels.device_sim.simulate_device`, the mock's
    rule) stops a velocity that would reverse within a period while the force cannot
    break the handle loose: the positions still move one way (the centred difference of
    :func:`moving_stretches` sees motion), the linear model cannot follow the stop, and
    its residual there is far above a noise-free sensor's. Such a sample is one where
    the model decelerates (``y[k+1] - 2 y[k] + y[k-1]`` against the motion) and its step
    ``y[k+1] - y[k]`` is less than ``ratio`` times that deceleration -- at the current
    deceleration the velocity reaches zero within ``ratio`` periods (one for the period
    itself, one for the model's own error there). The model positions are smooth whatever
    the sensor's noise or quantum, so a noisy or quantised record is not cut by them.

    Parameters
    ----------
    st : tuple of ndarray of int64, each shape (s,)
        ``(starts, ends, dirs)`` (:func:`moving_stretches`).
    y : ndarray, shape (n_s,)
        The fitted model's positions on the stretches, in their order [m].
    min_len : int
        Shortest piece kept [samples].
    ratio : float > 0
        Periods within which a reversal counts [periods].

    Returns
    -------
    tuple of ndarray or None
        The new ``(starts, ends, dirs)``; the samples ``k - 1 .. k + 2`` around each stop
        ``k`` are left out. None when no stretch is cut.
    """
    starts, ends, dirs = st
    out_s, out_e, out_d = [], [], []
    cut = False
    off = 0
    for a, b, d in zip(starts, ends, dirs):
        L = int(b - a)
        seg = y[off:off + L]
        off += L
        stops = []
        if L >= 3:
            step = d * (seg[2:] - seg[1:-1])            # rows 1 .. L-2
            dec = -d * (seg[2:] - 2.0 * seg[1:-1] + seg[:-2])
            stops = list(np.nonzero((dec > 0) & (step < ratio * dec))[0] + 1)
        if not stops:
            out_s.append(a)
            out_e.append(b)
            out_d.append(d)
            continue
        cut = True
        lo = 0
        for k in stops + [L + 1]:
            hi = min(k - 1, L)
            if hi - lo >= min_len:
                out_s.append(a + lo)
                out_e.append(a + hi)
                out_d.append(d)
            lo = max(lo, k + 3)
    if not cut:
        return None
    return (np.array(out_s, np.int64), np.array(out_e, np.int64), np.array(out_d, np.int64))
