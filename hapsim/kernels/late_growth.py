"""The lateness guard: how much the host's late FORCEs may have grown the scene's loop.

A device holds each FORCE it takes until the next (firmware_protocol/PROTOCOL.md §10: a
FORCE that comes after its tick is ignored, the force before it held). A host that falls
behind -- a loaded machine answering only every few STATEs, on time but seldom -- leaves
each force held for ``h`` ticks instead of one, so that over that hold the force the device
applies is ``d, d + 1, ..., d + h - 1`` ticks old. A loop stable at its own delay ``d`` but
not at longer ones grows through such holds (the shipped wall, ``configs/wall.yaml``, is
stable at ``d = 1`` only; a test's wall stable to 11 ticks grew from 5 mm to 32 mm at
1.5 m/s in 0.5 s of a host 14-36 ticks late, then a loss let it coast to -0.139 m: stop 78,
``docs/reliability.md``).

The guard reads the holds from the STATEs (their ``force_seq``, :func:`hapsim.kernels.
ticks.named_delay`): when the FORCE named changes from ``f_prev`` to ``f_new``, the force
``f_prev`` was held for ``h = f_new - f_prev`` ticks. Its growth is estimated with the
loop frozen at each of the hold's delays,

``g(h) = sum_{l = 0}^{h - 1} c(d + l)``,  ``c(D) = ln rho(D) - max(ln rho(d), 0)``,

``rho(D)`` the spectral radius of the scene's temporary hybrid system with ``D`` periods
of delay (:func:`hapsim.analysis.prediction.predict`: the paper's THS, Florens, Voda &
Urma, with the delay of the late force): the log of the factor by which one period at
that delay multiplies the loop's slowest mode, beyond what the loop does on time (a loop
already unstable at its own delay is the clamp's and the bounds' business, not the
host's lateness). The holds are summed as a one-sided cumulative sum (Page, "Continuous
inspection schemes", *Biometrika* 41, 1954): ``G <- max(0, G + g(h))``, so that on-time
periods (``h = 1``: ``c(d) <= 0``, the loop's own decay) pay back what a stall put in, and
a host late often enough to outrun that decay makes ``G`` climb. At
``G > LATE_GROWTH_STOP`` (``ln 2``: the lateness alone doubled the loop's amplitude, on the
frozen estimate) the host loop stops and brakes, naming the lateness
(:meth:`hapsim.host.loop.HostLoop._drive`, the compiled loop the same way).

The frozen estimate is not exact for a delay that varies (a hold's sawtooth), but close:
on the reliability tests' wall (0.1 kg on 0.5 N s/m, B = 1.5 N s/m, d = 1), uniform holds
grow a 300 N/m wall -0.75, +0.62 and a 150 N/m one -0.79, -0.07, +0.48 (1e-3 a period,
holds of 10, 12, 22, 24, 26) where the estimate says -0.80, +0.67, -0.70, -0.00, +0.66
(``python tools/late_guard.py --rates``); ``tests/test_late_growth.py`` bounds the guard
by what the records do, over random scenes and hosts, not by the estimate.

``g`` is tabulated once per run (:class:`LateGrowth`, built by
:func:`hapsim.pipeline.render_latency.late_growth`) at ``h = j * step``, ``j = 0 .. n``
(``g(0) = 0``), interpolated linearly between, and held at its last entry beyond (a hold
longer than the watchdog ends at zero force). The per-row update, :func:`late_growth_step`,
is plain arithmetic on that table, compiled into the compiled host loop
(``register_jitable``) and called as it is by the Python loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba.extending import register_jitable

__all__ = ["LATE_GROWTH_STOP", "GROWTH_POINTS", "LateGrowth", "hold_growth",
           "late_growth_step", "late_growth_reason"]

#: The guard's bound on the cumulative growth [nepers]: the lateness doubled the loop.
LATE_GROWTH_STOP = math.log(2.0)
#: Most entries of a growth table beyond ``g(0)`` (the compiled loop keeps them in its
#: parameter vector, a fixed size).
GROWTH_POINTS = 64

_MASK = 0xFFFFFFFF
_HALF = 0x80000000


@dataclass(frozen=True)
class LateGrowth:
    """A scene's growth table for the lateness guard (module notes).

    Attributes
    ----------
    table : tuple of float
        ``g(j * step)`` [nepers], ``j = 0 .. n`` (``n <= GROWTH_POINTS``; ``table[0] = 0``).
    step : float
        Hold length [ticks] between entries (>= 1).
    stable_to : int
        The longest delay [ticks] at which the loop is stable (for the stop's reason).
    delay : int
        The scene's own delay ``d`` [ticks].
    """

    table: tuple
    step: float
    stable_to: int
    delay: int

    def array(self) -> np.ndarray:
        """The table as float64, shape (n + 1,).

        Returns
        -------
        ndarray
        """
        return np.asarray(self.table, dtype=np.float64)


@register_jitable
def hold_growth(h, table, step):
    """The growth of a force held ``h`` ticks, interpolated in the table (module notes).

    Parameters
    ----------
    h : int
        Hold [ticks] (>= 0).
    table : ndarray of float64, shape (n + 1,)
        :attr:`LateGrowth.table`.
    step : float
        :attr:`LateGrowth.step` [ticks].

    Returns
    -------
    float
        ``g(h)`` [nepers]; the last entry for a hold beyond the table.
    """
    n = table.size - 1
    pos = h / step
    if pos >= n:
        return table[n]
    i = int(pos)
    return table[i] + (pos - i) * (table[i + 1] - table[i])


@register_jitable
def late_growth_step(acc, f_prev, force_seq, lag, table, step):
    """One STATE's update of the cumulative growth (module notes).

    Parameters
    ----------
    acc : float
        The cumulative growth so far [nepers] (>= 0).
    f_prev : int
        The FORCE the device named last in this stretch (-1: none yet).
    force_seq : int
        This STATE's ``force_seq``.
    lag : int
        Its :func:`hapsim.kernels.ticks.named_delay` (-1: it names no FORCE).
    table : ndarray of float64
        :attr:`LateGrowth.table`.
    step : float
        :attr:`LateGrowth.step` [ticks].

    Returns
    -------
    (float, int)
        The new ``acc`` and ``f_prev``: a FORCE newer than ``f_prev`` ends its hold,
        ``h = force_seq - f_prev`` ticks (mod 2^32), whose :func:`hold_growth` is added
        (the sum kept >= 0); the same FORCE, an older one or none changes nothing.
    """
    if lag < 0:
        return acc, f_prev
    if f_prev < 0:
        return acc, force_seq
    h = (force_seq - f_prev) & _MASK
    if h == 0 or h >= _HALF:
        return acc, f_prev
    acc += hold_growth(h, table, step)
    if acc < 0.0:
        acc = 0.0
    return acc, force_seq


def late_growth_reason(acc: float, guard: LateGrowth, period: float) -> str:
    """The stop reason of the lateness guard (off the fast path).

    Parameters
    ----------
    acc : float
        The cumulative growth at the stop [nepers].
    guard : LateGrowth
        The run's table (its delays).
    period : float
        The sample period [s].

    Returns
    -------
    str
    """
    return (f"safety: the host's FORCEs came too late for the scene's loop: the device held "
            f"them long enough to grow it x{math.exp(acc):.2g} (the loop is stable up to "
            f"{guard.stable_to} periods of delay, {guard.stable_to * period * 1e3:.3g} ms; "
            f"its own is {guard.delay}); a loaded machine? (docs/reliability.md, "
            f"\"The lateness guard\")")
