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

``g_k(h) = sum_{l = 0}^{h - 1} c_k(d + l)``,
``c_k(D) = ln |z_k(D)| - max(ln |z_k(d)|, 0) - delta T``,

per mode ``k`` of the loop: ``z_k(D)`` its pole in the scene's temporary hybrid system
with ``D`` periods of delay (the paper's THS, Florens, Voda & Urma, with the delay of the
late force; the poles the port's record shows, :func:`hapsim.analysis.prediction.
predicted_poles`: a mode the port neither sees nor drives is one the device's lateness
cannot pump), followed from ``D = d`` on as the delay grows: the log of the factor by which
one period at that delay multiplies that mode, beyond what it does on time (a loop already
unstable at its own delay is the clamp's and the bounds' business, not the host's
lateness), less a slack ``delta`` (:data:`LATE_GROWTH_SLACK`, Page's reference value: a
growth slower than the estimate's own error is not counted, and left to the bounds).
Each mode's holds are summed as a one-sided cumulative sum (Page, "Continuous
inspection schemes", *Biometrika* 41, 1954): ``G_k <- max(0, G_k + g_k(h))``, so that
on-time periods (``h = 1``: ``c_k(d) <= 0``, the mode's own decay) pay back what a stall
put in, and a host late often enough to outrun that decay makes ``G_k`` climb. The hold
a STATE is in is counted too, as if it ended at the next tick (:func:`open_hold_growth`):
a link that makes every answer late never ends its first hold (the device names one FORCE
until its watchdog; ``docs/reliability.md``, "A hold that never ends"), and is stopped as
soon as that hold has grown the loop as far as an ended one would have. At
``max_k G_k > LATE_GROWTH_STOP`` (``ln 2``: the lateness alone doubled a mode's amplitude,
on the frozen estimate) the host loop stops and brakes, naming the lateness
(:meth:`hapsim.host.loop.HostLoop._drive`, the compiled loop the same way), once the
handle moves faster than the braking's rest speed (``LoopConfig.brake_rest``: a handle
slower is at rest, and a growth from rest, of micrometres, is no danger until it moves). Per mode, not
with the spectral radius alone: on ``configs/string.yaml`` the mode that grows under
lateness (10.9 Hz, the handle on the string) decays on time at 5.6e-3 a period, while the
slowest mode on time (8.8 Hz, 7e-6 a period) hardly moves with the delay; summed as one,
the stalls of a loaded host (``spike`` faults, 2.5 % of the STATEs held 8 ms) stopped a
loop whose handle was decaying, "grown x2".

The frozen estimate is not exact for a delay that varies (a hold's sawtooth), but close:
on the reliability tests' wall (0.1 kg on 0.5 N s/m, B = 1.5 N s/m, d = 1), uniform holds
grow a 300 N/m wall -0.75, +0.62 and a 150 N/m one -0.79, -0.07, +0.48 (1e-3 a period,
holds of 10, 12, 22, 24, 26) where the estimate says -0.80, +0.67, -0.70, -0.00, +0.66
(``python tools/late_guard.py --rates``); ``tests/test_late_growth.py`` bounds the guard
by what the records do, over random scenes and hosts, not by the estimate.

Each ``g_k`` is tabulated once per run (:class:`LateGrowth`, built by
:func:`hapsim.analysis.late_growth.late_growth`, the modes that can grow, at most
:data:`GROWTH_MODES`) at ``h = j * step``, ``j = 0 .. n`` (``g_k(0) = 0``), interpolated
linearly between, and held at its last entry beyond (a hold longer than the watchdog ends
at zero force). The per-row update, :func:`late_growth_step`, is plain arithmetic on those
tables, compiled into the compiled host loop (``register_jitable``) and called as it is by
the Python loop (on lists there: ``len`` and indexing only).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba.extending import register_jitable

__all__ = ["LATE_GROWTH_STOP", "LATE_GROWTH_SLACK", "GROWTH_POINTS", "GROWTH_MODES",
           "LateGrowth", "hold_growth", "late_growth_step", "open_hold_growth",
           "late_growth_reason"]

#: The guard's bound on the cumulative growth [nepers]: the lateness doubled the loop.
LATE_GROWTH_STOP = math.log(2.0)
#: The slack ``delta`` [1/s] taken off every period's growth (module notes): the frozen
#: estimate's error, measured up to 0.32 /s at 1 kHz (a 231 N/m wall held 25 periods at a
#: time: estimated +0.17e-3 a period, its record -0.15e-3; ``python tools/late_guard.py
#: --rates`` has it and others), with a margin of 1.5. A loop that grows slower (doubling in
#: more than 1.4 s) is left to the bounds.
LATE_GROWTH_SLACK = 0.5
#: Most entries of a growth table beyond ``g(0)`` (the compiled loop keeps them in its
#: parameter vector, a fixed size).
GROWTH_POINTS = 64
#: Most modes a growth table follows (the compiled loop keeps their sums and tables in its
#: fixed-size vectors): those that grow the most under lateness.
GROWTH_MODES = 4

_MASK = 0xFFFFFFFF
_HALF = 0x80000000


@dataclass(frozen=True)
class LateGrowth:
    """A scene's growth table for the lateness guard (module notes).

    Attributes
    ----------
    table : tuple of tuple of float
        Per mode ``k`` (at most :data:`GROWTH_MODES`), ``g_k(j * step)`` [nepers],
        ``j = 0 .. n`` (``n <= GROWTH_POINTS``; ``g_k(0) = 0``).
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
        """The tables as float64, shape (modes, n + 1).

        Returns
        -------
        ndarray
        """
        return np.asarray(self.table, dtype=np.float64)

    def lists(self) -> list:
        """The tables as lists of floats (the Python loop's: a list is indexed faster).

        Returns
        -------
        list of list of float
        """
        return [list(row) for row in self.table]


@register_jitable
def hold_growth(h, table, step):
    """The growth of a force held ``h`` ticks, interpolated in the table (module notes).

    Parameters
    ----------
    h : int
        Hold [ticks] (>= 0).
    table : sequence of float, length n + 1
        One mode's row of :attr:`LateGrowth.table` (an array, or a list).
    step : float
        :attr:`LateGrowth.step` [ticks].

    Returns
    -------
    float
        ``g_k(h)`` [nepers]; the last entry for a hold beyond the table.
    """
    n = len(table) - 1
    pos = h / step
    if pos >= n:
        return table[n]
    i = int(pos)
    return table[i] + (pos - i) * (table[i + 1] - table[i])


@register_jitable
def late_growth_step(acc, f_prev, force_seq, lag, tables, step):
    """One STATE's update of the modes' cumulative growths (module notes).

    Parameters
    ----------
    acc : sequence of float, length modes
        Each mode's cumulative growth so far [nepers] (>= 0); updated in place.
    f_prev : int
        The FORCE the device named last in this stretch (-1: none yet).
    force_seq : int
        This STATE's ``force_seq``.
    lag : int
        Its :func:`hapsim.kernels.ticks.named_delay` (-1: it names no FORCE).
    tables : sequence of sequence of float, shape (modes, n + 1)
        :attr:`LateGrowth.table` (an array, or lists).
    step : float
        :attr:`LateGrowth.step` [ticks].

    Returns
    -------
    int
        The new ``f_prev``: a FORCE newer than ``f_prev`` ends its hold,
        ``h = force_seq - f_prev`` ticks (mod 2^32), whose :func:`hold_growth` is added to
        each mode's sum (kept >= 0); the same FORCE, an older one or none changes nothing.
    """
    if lag < 0:
        return f_prev
    if f_prev < 0:
        return force_seq
    h = (force_seq - f_prev) & _MASK
    if h == 0 or h >= _HALF:
        return f_prev
    for k in range(len(acc)):
        a = acc[k] + hold_growth(h, tables[k], step)
        acc[k] = a if a > 0.0 else 0.0
    return force_seq


@register_jitable
def open_hold_growth(acc, f_prev, seq, lag, d, tables, step):
    """The largest mode's cumulative growth with the hold still open counted (module notes).

    A hold is added to the sums when it ends (:func:`late_growth_step`); a link that makes
    every answer late never ends it, and the device holds one force until its watchdog
    (``docs/reliability.md``, "A hold that never ends"). So each STATE also counts the hold
    it is in as if it ended at the next tick: the FORCE ``f_prev`` still named at tick
    ``seq`` has been held ``h = seq - f_prev - d + 1`` ticks, and each mode's sum is read
    as ``acc_k + g_k(h)``. On time (``h = 1``: ``g_k(1) = c_k(d) <= 0``) that is no more
    than ``acc_k``; a hold that stops the run once ended stops it as soon as it has grown
    the loop that far, not when (if ever) the device names a newer FORCE.

    Parameters
    ----------
    acc : sequence of float, length modes
        Each mode's cumulative growth [nepers], as :func:`late_growth_step` left it for
        this STATE (not changed).
    f_prev : int
        The FORCE named last, as :func:`late_growth_step` returned it for this STATE
        (-1: none yet).
    seq : int
        This STATE's ``seq``.
    lag : int
        Its :func:`hapsim.kernels.ticks.named_delay` (-1: it names no FORCE; then no open
        hold is counted).
    d : int
        The scene's delay [ticks].
    tables : sequence of sequence of float, shape (modes, n + 1)
        :attr:`LateGrowth.table`.
    step : float
        :attr:`LateGrowth.step` [ticks].

    Returns
    -------
    float
        ``max(max_k acc_k, max_k (acc_k + g_k(h)))`` [nepers] (the first alone when the
        STATE names no FORCE or the hold is one tick or less).
    """
    worst = 0.0
    for k in range(len(acc)):
        if acc[k] > worst:
            worst = acc[k]
    if lag < 0 or f_prev < 0:
        return worst
    h = ((seq - f_prev) & _MASK) + 1 - d
    if h <= 1 or h >= _HALF:
        return worst
    for k in range(len(acc)):
        a = acc[k] + hold_growth(h, tables[k], step)
        if a > worst:
            worst = a
    return worst


def late_growth_reason(acc: float, guard: LateGrowth, period: float) -> str:
    """The stop reason of the lateness guard (off the fast path).

    Parameters
    ----------
    acc : float
        The largest mode's cumulative growth at the stop [nepers].
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
