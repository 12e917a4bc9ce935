"""The device fit's model and record (:mod:`hapsim.analysis.device_fit`): what a fit
returns (:class:`Estimate`, :class:`DeviceFit`), the force a device applied over each
period (:func:`applied_force`), the record's pieces of consecutive ticks and its encoder
quantum.

The model, the method and the intervals are described in :mod:`hapsim.analysis.device_fit`;
the search of the model's parameters is :mod:`hapsim.analysis.device_fit_search`, their
intervals and the noise :mod:`hapsim.analysis.device_fit_intervals`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["Estimate", "DeviceFit", "applied_force", "POSITION_FLOOR", "LEVEL", "HOLDS",
           "true_runs", "tick_runs", "input_known", "encoder_quantum"]

#: Positions are never taken as known better than this [m] (intervals' numerical floor).
POSITION_FLOOR = 1e-10
#: Confidence level of every interval.
LEVEL = 0.999
#: The holds a fit tries, by name: their codes in the compiled device model
#: (:mod:`hapsim.kernels.device_sim`: 0 the zero-order hold, 1 the idealised image).
HOLDS = {"zoh": 0, "ideal": 1}


@dataclass
class Estimate:
    """One identified quantity with its confidence interval.

    Attributes
    ----------
    value : float
        Estimate (unit in ``unit``).
    lo, hi : float
        Interval at :data:`LEVEL`.
    unit : str
        Unit, e.g. ``"kg"``.
    """

    value: float
    lo: float
    hi: float
    unit: str

    def contains(self, truth: float) -> bool:
        """True when ``lo <= truth <= hi``.

        Parameters
        ----------
        truth : float
            The value to test, in :attr:`unit`.

        Returns
        -------
        bool
            False also for a NaN ``truth`` or bound.
        """
        return bool(self.lo <= truth <= self.hi)


@dataclass
class DeviceFit:
    """What :func:`hapsim.analysis.device_fit.fit_device` identified.

    Attributes
    ----------
    mass : Estimate
        Moving mass m [kg] (with a hand on the handle: hand + handle, the THS mass).
    friction : Estimate
        Viscous friction b0 [N s/m] (with a hand: the THS damping).
    coulomb_pos, coulomb_neg : Estimate
        Coulomb friction while moving in + / - [N] (zero-width at 0 for hold ``ideal``).
    coulomb : Estimate
        Their mean [N]; ``asymmetry`` = ``fc+ - fc-`` [N].
    asymmetry : Estimate
    delay : int
        Whole samples d between a position and the force answering it being applied.
    delay_range : tuple of int
        Every whole delay the data cannot tell from ``delay`` (its interval).
    delay_estimate : Estimate
        The delay as a real number of periods ``d + frac`` (a sub-sample delay: the split
        hold, :mod:`hapsim.analysis.subsample`) with its interval [periods]; under the
        idealised hold, the whole delay. ``delay`` is its whole part as the fit chose it.
    hold : str
        ``"zoh"`` or ``"ideal"``; ``hold_certain`` False when the other fits as well.
    hold_certain : bool
    position_resolution : Estimate
        Encoder quantum q [m] (0 when the positions are not on a grid).
    noise : Estimate
        Sensor noise standard deviation [m].
    x0 : float
        Fitted position at the first sample [m].
    rms_residual : float
        RMS of ``x_model - x_meas`` [m].
    explained : bool
        The model explains the data (module notes).
    verdict : str
        One sentence for the user.
    residual_peak_hz : float
        Dominant frequency of the residual [Hz].
    period : float
        Sample period T [s].
    n_samples : int
        Samples used.
    level : float
        Confidence level of the intervals.
    motion_counts : int
        Encoder steps seen on the fitted stretches (changes between neighbouring
        samples; -1: positions not on a grid).
    delay_certain : bool
        False when another delay fits as well (``delay_range``; the verdict names it):
        ``delay`` is then the better fit's, not determined.
    candidates : list of dict
        ``hold``, ``delay``, ``rms`` of every model tried.
    model : ndarray
        The model's positions [m], shape (n_samples,).
    """

    mass: Estimate
    friction: Estimate
    coulomb_pos: Estimate
    coulomb_neg: Estimate
    coulomb: Estimate
    asymmetry: Estimate
    delay: int
    delay_range: tuple
    hold: str
    hold_certain: bool
    position_resolution: Estimate
    noise: Estimate
    x0: float
    rms_residual: float
    explained: bool
    verdict: str
    residual_peak_hz: float
    period: float
    n_samples: int
    level: float = LEVEL
    motion_counts: int = -1
    delay_certain: bool = True
    delay_estimate: Estimate = None
    candidates: list = field(default_factory=list)
    model: np.ndarray = field(default=None, repr=False)

    def device(self, force_limit: float = math.inf):
        """The identified device as a :class:`hapsim.scene.Device`.

        Parameters
        ----------
        force_limit : float
            Force limit to put in it [N].

        Returns
        -------
        hapsim.scene.Device
            Negative estimates of friction, Coulomb friction are written as 0 (their
            intervals then hold 0).
        """
        from hapsim.scene import Device
        return Device(mass=self.mass.value, friction=max(self.friction.value, 0.0),
                      delay=self.device_delay(), hold=self.hold, force_limit=force_limit,
                      position_resolution=self.position_resolution.value,
                      coulomb=max(self.coulomb.value, 0.0), noise=self.noise.value)

    def device_delay(self):
        """The delay to write in a device section [periods]: the whole ``delay`` when
        the interval of :attr:`delay_estimate` holds it (a whole delay gives today's
        numbers bit for bit), else the sub-sample estimate rounded to 1e-3 period.

        Returns
        -------
        int or float
        """
        e = self.delay_estimate
        if e is None or e.lo <= self.delay <= e.hi or not math.isfinite(e.value):
            return int(self.delay)
        return round(float(e.value), 3)

    def to_dict(self) -> dict:
        """Plain data (``--json``): every estimate as ``{value, lo, hi, unit}``.

        Returns
        -------
        dict
            Every attribute but ``model`` by name (:func:`dataclasses.asdict`),
            ``delay_range`` as a list, ``delay_estimate`` None when not identified.
        """
        d = {k: v for k, v in asdict(self).items() if k != "model"}
        d["delay_range"] = list(self.delay_range)
        return d


def applied_force(force, delay: int, late=None, seq=None) -> np.ndarray:
    """The force the device held over each period, from the forces the host sent.

    Parameters
    ----------
    force : array_like, shape (n,)
        Force sent answering the position of sample ``k`` [N].
    delay : int >= 0
        d: that force acts over ``[(k+d)T, (k+d+1)T)``.
    late : array_like of bool, shape (n,), optional
        Ticks the device reported holding an older force: the force before is held.
    seq : array_like of int, shape (n,), optional
        The device's tick (STATE seq) of each row; rows missing from the record (a STATE
        lost, never answered) are gaps in it. The force answering row ``k`` acts from tick
        ``seq[k] + d``; at a tick whose due force was never sent (its STATE lost) the
        device holds the last one that was. Default: ``seq[k] = k``.

    Returns
    -------
    ndarray, shape (n,)
        ``u[j] = force[k]`` with ``k`` the last row whose ``seq[k] <= seq[j] - d`` (0 when
        none: nothing sent yet), the previous tick's ``u`` where late. A fall of ``seq``
        (the device restarted its ticks) starts the search anew.
    """
    f = np.asarray(force, float)
    n = f.size
    if seq is None:
        u = np.zeros_like(f)
        if delay < f.size:
            u[delay:] = f[:f.size - delay]
    else:
        s = np.asarray(seq, np.int64)
        if s.shape != f.shape:
            raise ConfigError(f"seq must have the forces' shape {f.shape}, got {s.shape}",
                              key="seq")
        u = np.zeros(n)
        for a, b in tick_runs(s, falls_only=True):
            k = np.searchsorted(s[a:b], s[a:b] - int(delay), side="right") - 1
            u[a:b] = np.where(k >= 0, f[a + np.maximum(k, 0)], 0.0)
    if late is not None:
        lt = np.asarray(late, bool)
        for k in np.flatnonzero(lt):
            if k > 0:
                u[k] = u[k - 1]
    return u


def true_runs(mask: np.ndarray) -> list:
    """The ranges where a mask holds throughout.

    Parameters
    ----------
    mask : array_like of bool, shape (n,)

    Returns
    -------
    list of (int, int)
        ``(a, b)``: ``mask[a:b]`` all True, ``mask[a - 1]`` and ``mask[b]`` False (or
        outside), in increasing order.
    """
    m = np.concatenate([[False], np.asarray(mask, bool), [False]]).astype(np.int8)
    e = np.flatnonzero(np.diff(m))
    return [(int(a), int(b)) for a, b in zip(e[0::2], e[1::2])]


def tick_runs(seq: np.ndarray, falls_only: bool = False) -> list:
    """The row ranges of a record's stretches of consecutive ticks.

    Parameters
    ----------
    seq : ndarray of int, shape (n,)
        The device's tick (STATE seq) of each row.
    falls_only : bool
        Cut only where ``seq`` falls or stays (the device restarted its ticks), not at a
        gap.

    Returns
    -------
    list of (int, int)
        ``(a, b)`` row ranges covering ``0 .. n``: inside each, ``seq`` rises by 1 from
        row to row (with ``falls_only``: rises).
    """
    d = np.diff(np.asarray(seq, np.int64))
    cut = np.flatnonzero(d <= 0 if falls_only else d != 1) + 1
    e = np.concatenate([[0], cut, [seq.size]]).astype(np.int64)
    return [(int(a), int(b)) for a, b in zip(e[:-1], e[1:])]


def input_known(seq: np.ndarray, late, max_delay: int) -> np.ndarray:
    """The rows whose applied force :func:`applied_force` names for every delay up to
    ``max_delay``.

    Parameters
    ----------
    seq : ndarray of int, shape (n,)
        The device's tick (STATE seq) of each row.
    late : array_like of bool, shape (n,), or None
        Rows the device reported holding an older force.
    max_delay : int >= 0
        Largest delay tried [samples].

    Returns
    -------
    ndarray of bool, shape (n,)
        False at a late row right after a gap (what the device held at the lost tick
        before it is not in the record) and at the first ``max_delay`` ticks after the
        device restarted its ticks (forces sent before the restart may act there).
    """
    n = seq.size
    ok = np.ones(n, bool)
    if late is not None:
        lt = np.asarray(late, bool)
        gap_before = np.zeros(n, bool)
        gap_before[1:] = np.diff(seq) != 1
        ok &= ~(lt & gap_before)
    for i, (a, b) in enumerate(tick_runs(seq, falls_only=True)):
        if i > 0:
            ok[a:b] &= seq[a:b] - seq[a] >= int(max_delay)
    return ok


def encoder_quantum(y: np.ndarray) -> Estimate:
    """Encoder quantum ``q`` [m]: the grid the positions lie on, if they lie on one.

    A device sends ``k q`` rounded to its own number format (float32 on an 8-bit MCU:
    a relative error of 2^-24 of the value), so the step between two neighbouring values
    far from zero differs from ``q`` by that rounding, and the smallest step is not ``q``.
    The grid step is therefore estimated from all values: ``q1``, the median of the steps
    near the smallest, gives each value its whole count ``k = round(y / q1)``; then ``q``
    is the least-squares slope of ``y`` on ``k`` (every value's rounding averages out).
    The values lie on the grid when every ``|y / q - k| < 1e-3``. The interval is the
    larger of ``1e-6 q`` and three times the largest residual ``|y - k q|`` over the
    largest ``|k|`` (the error of the slope through the farthest value).

    Parameters
    ----------
    y : ndarray, shape (n,)
        Positions [m].

    Returns
    -------
    Estimate
        ``q`` with its interval, or ``0`` with the interval ``[0, smallest step]`` when
        the positions are not on a grid (``[0, inf]`` when they never change).
    """
    vals = np.unique(y)
    steps = np.diff(vals)
    steps = steps[steps > 0]
    if steps.size == 0:
        return Estimate(0.0, 0.0, math.inf, "m")
    q0 = float(steps.min())
    if q0 > 1e-9:
        q1 = float(np.median(steps[steps < 1.5 * q0]))
        k = np.round(vals / q1)
        q = float(np.dot(k, vals) / np.dot(k, k)) if np.any(k) else q1
        if np.max(np.abs(vals / q - k)) < 1e-3:
            kmax = float(np.max(np.abs(k)))
            tol = max(1e-6 * q, 3.0 * float(np.max(np.abs(vals - k * q))) / kmax)
            return Estimate(q, q - tol, q + tol, "m")
    return Estimate(0.0, 0.0, q0, "m")
