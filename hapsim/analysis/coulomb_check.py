"""A "differs" that a device's declared Coulomb friction could explain is no verdict.

The run's prediction is the linear THS (the device's mass, viscous friction, hold and
delay with the virtual links). A device declared with Coulomb friction ``fc``
(``device.coulomb``: the mock adds it) is not that loop: its friction dissipates per
cycle of amplitude ``a`` at ``w`` what a viscous ``b_eq = 4 fc / (pi a w)`` would (its
describing function; Gelb & Vander Velde 1968, ch. 2; :mod:`hapsim.analysis.zwidth`),
more the smaller the motion. A verdict fuzz of matching devices on hapsim's mock in
lockstep (random spring-dampers, ``fc`` 0.1-5 % of the start's spring force) said
"measured differs" in 23 of 30: the prediction, not the device, was off. Where the
Coulomb friction's equivalent damping at the amplitude the fit weighs (the root mean
square of the window's fitted decay) exceeds the stated damping interval, the departure is one the prediction leaves out: the run says "not
measurable" with that reason (a device that differs more than that still may, but the
record cannot tell it from the declared friction). Where it is below, the verdict
stands.
"""

from __future__ import annotations

import math

__all__ = ["coulomb_verdict", "coulomb_equivalent_damping"]


def coulomb_equivalent_damping(fc: float, amplitude: float, w: float) -> float:
    """The viscous damping that dissipates per cycle what a Coulomb friction does in a
    sinusoidal motion: ``4 fc / (pi a w)`` (its describing function; Gelb & Vander Velde
    1968, ch. 2).

    Parameters
    ----------
    fc : float
        The Coulomb friction's force [N], >= 0.
    amplitude : float
        The motion's amplitude a [m], > 0.
    w : float
        Its angular frequency [rad/s], > 0.

    Returns
    -------
    float
        The equivalent damping [N s/m].
    """
    return 4.0 * fc / (math.pi * amplitude * w)


def coulomb_verdict(measured: dict, device, period: float) -> None:
    """Turn a "differs" the declared Coulomb friction could explain into "not
    measurable" (in place; module notes).

    Parameters
    ----------
    measured : dict
        The run's measurement after :func:`hapsim.analysis.measurement.verdict`
        (``within``, ``amplitude`` [m] at the window's start, ``f0_hz``,
        ``damping_ratio``, ``samples_used``, ``b_interval`` [N s/m]).
    device : hapsim.scene.Device
        Its ``coulomb`` [N].
    period : float
        T [s].
    """
    fc = float(getattr(device, "coulomb", 0.0) or 0.0)
    if not fc > 0 or measured.get("within") is not False:
        return
    a0, f0 = measured.get("amplitude"), measured.get("f0_hz")
    if not (a0 and f0 and a0 > 0 and f0 > 0):
        return
    w = 2.0 * math.pi * f0
    zeta = max(float(measured.get("damping_ratio") or 0.0), 0.0)
    t = float(measured.get("samples_used") or 0) * period
    # the amplitude the fit weighs: the root mean square of the felt oscillation's fitted
    # decay a0 exp(-zeta w t) over the window (a least-squares fit weighs each sample by
    # its square), a0 sqrt((1 - exp(-2 x)) / (2 x)) with x = zeta w t
    x = zeta * w * t
    a_eff = a0 * (math.sqrt(-math.expm1(-2.0 * x) / (2.0 * x)) if x > 1e-12 else 1.0)
    b_eq = coulomb_equivalent_damping(fc, a_eff, w)
    measured["coulomb_b_eq"] = b_eq
    if b_eq <= measured["b_interval"]:
        return
    measured["within"] = None
    measured["verdict"] = (
        f"not measurable: the device's Coulomb friction ({fc:g} N), which the linear "
        f"prediction leaves out, damps like {b_eq:.3g} N s/m at the record's weighted "
        f"amplitude ({a_eff:.3g} m; 4 fc / (pi a w)), more than the stated uncertainty of "
        f"b ({measured['b_interval']:.3g}): the departure measured may be it")
