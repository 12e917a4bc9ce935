"""How long a free response stays above a floor, and what would make a record that is too
short for a measurement long enough (:func:`seconds_above`, :func:`more_cycles`).

A measurement of the felt pair (:func:`hapsim.analysis.identify.measure_felt`) counts the
oscillation cycles of its record above a floor (a few sensor steps, or the fit's residual):
each stretch of the record holds a damped oscillation of amplitude ``a_j`` at its start,
``a_j exp(-sigma t)`` later (``sigma = -Re s`` of the felt pole, 1/s), which stays above
the level ``L`` for ``log(a_j / L) / sigma`` seconds, at most the stretch's length. When the
cycles fall short, two things add some: a longer record, when the last stretch ended with
the oscillation still above the level; or a larger start, which adds ``log(g) / sigma``
seconds to each stretch that decays below the level within its length (the same closed
form, solved for ``g``).
"""

from __future__ import annotations

import math

__all__ = ["seconds_above", "more_cycles", "more_cycles_hint"]


def seconds_above(amps, lens, sigma: float, level: float, period: float,
                  scale: float = 1.0) -> list:
    """The time each stretch's oscillation stays above ``level`` (module notes).

    Parameters
    ----------
    amps : sequence of float
        Each stretch's oscillation amplitude at its start [m] (>= 0).
    lens : sequence of float
        Each stretch's length [samples].
    sigma : float
        Decay rate ``-Re s`` of the felt pole [1/s]; <= 0: no decay.
    level : float
        The floor [m] (> 0).
    period : float
        Sample period T [s].
    scale : float, optional
        A factor on every amplitude (a larger start, :func:`more_cycles`; > 0).

    Returns
    -------
    list of float
        Seconds per stretch [s]: ``min(log(scale a_j / level) / sigma, n_j T)``, 0 where
        ``scale a_j <= level``, ``n_j T`` where ``sigma <= 0``.
    """
    return _seconds(amps, lens, sigma, level, period, math.log(scale))


def _seconds(amps, lens, sigma, level, period, log_scale) -> list:
    """:func:`seconds_above` with the scale as its logarithm (no overflow however large
    the scale a bisection tries)."""
    out = []
    for a, n in zip(amps, lens):
        a = float(a)
        up = math.log(a / level) + log_scale if a > 0 else -math.inf
        if not up > 0:
            out.append(0.0)
            continue
        t = up / sigma if sigma > 0 else math.inf
        out.append(min(t, float(n) * period))
    return out


def more_cycles(amps, lens, sigma: float, level: float, period: float, cycle_hz: float,
                need: float, *, ends_record: bool = True) -> tuple:
    """What gives a record ``need`` oscillation cycles above ``level``: a longer record, a
    larger start, or neither (module notes).

    Parameters
    ----------
    amps, lens, sigma, level, period
        As :func:`seconds_above`.
    cycle_hz : float
        Cycles per second of the oscillation, ``f0 sqrt(1 - zeta^2)`` [Hz].
    need : float
        The cycles a measurement needs.
    ends_record : bool, optional
        The last stretch ends where the record does (a longer run extends it); False
        when it ends at a disturbance.

    Returns
    -------
    tuple
        ``("enough", 0.0)`` when the record already holds ``need`` cycles;
        ``("none", 0.0)`` when the pair does not oscillate (``cycle_hz <= 0``);
        ``("longer", s)``: the last stretch ended the record still above the level, and
        ``s`` more seconds of it give ``need`` cycles [s]; ``("larger", g)``: a start
        ``g`` times larger (every amplitude scaled) gives ``need`` cycles, the stretches'
        lengths allowing it; ``("stretches", t)``: neither does, the stretches being too
        short at any start (``t`` the longest [s]).
    """
    if not cycle_hz > 0:
        return ("none", 0.0)
    have = cycle_hz * sum(_seconds(amps, lens, sigma, level, period, 0.0))
    if have >= need:
        return ("enough", 0.0)
    short = (need - have) / cycle_hz
    a_l, n_l = float(amps[-1]), float(lens[-1])
    if ends_record and a_l > level:
        tail = math.inf if sigma <= 0 else math.log(a_l / level) / sigma - n_l * period
        if tail >= short:
            return ("longer", short)
    live = [(float(a), float(n)) for a, n in zip(amps, lens) if a > 0]
    if not live or cycle_hz * period * sum(n for _, n in live) < need:
        return ("stretches", period * max(float(n) for n in lens))
    # the log-scale at which every stretch is above the level over its whole length
    hi = max(math.log(level / a) + (sigma * n * period if sigma > 0 else 0.0)
             for a, n in live)
    lo, hi = 0.0, max(hi, 0.0) + 1e-9
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if cycle_hz * sum(_seconds(amps, lens, sigma, level, period, mid)) >= need:
            hi = mid
        else:
            lo = mid
        if hi - lo <= 1e-12 * max(1.0, hi):
            break
    return ("larger", math.exp(hi) if hi < 700.0 else math.inf)


def _up(v: float, digits: int) -> float:
    """``v`` rounded up to ``digits`` significant digits: a remedy shown is never short of
    what it gives (a factor of 1.0004 read "1 times larger")."""
    if not (math.isfinite(v) and v > 0.0):
        return v
    unit = 10.0 ** (math.floor(math.log10(v)) - digits + 1)
    return float(f"{math.ceil(v / unit - 1e-9) * unit:.{digits + 1}g}")


def more_cycles_hint(amps, lens, sigma: float, level: float, period: float,
                     cycle_hz: float, need: float, sensor: bool, *,
                     ends_record: bool = True) -> str:
    """The clause a "too few cycles" error ends with: what would give ``need`` cycles
    (:func:`more_cycles`), said to the user.

    Parameters
    ----------
    amps, lens, sigma, level, period, cycle_hz, need, ends_record
        As :func:`more_cycles`.
    sensor : bool
        The level is the sensor's (its step or noise), not the fit's residual: a finer
        sensor helps as much as a larger start.

    Returns
    -------
    str
        ``"; ..."``, or ``""`` when the record already holds ``need`` cycles or the pair
        does not oscillate.
    """
    how, v = more_cycles(amps, lens, sigma, level, period, cycle_hz, need,
                         ends_record=ends_record)
    if how in ("enough", "none"):
        return ""
    if how == "longer":
        return (f"; the record ended with the oscillation still above that level: about "
                f"{_up(v, 2):g} s more of undisturbed free response (a longer run) would give "
                f"{need:g}")
    if how == "larger":
        return (f"; a start about {_up(v, 3):g} times larger"
                + (" (or a sensor step that much finer)" if sensor else
                   " (the residual staying as it is)")
                + f" would give {need:g}")
    return (f"; its undisturbed stretches are too short for {need:g} at any start (the "
            f"longest {v:.2g} s): fewer disturbances are needed")
