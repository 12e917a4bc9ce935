"""Separating a driver's force (or position) scale from the moving mass (a known added
mass).

A device identified through a driver's protocol (``hapsim identify --driver``) is seen
only through the force-to-acceleration gain: the host sends forces in the units of the
full scale it *assumes* (``device.protocol_options``), the motor pushes with the full scale
it *has*. With ``g = full_scale_true / full_scale_assumed`` the device obeys
``m x'' + b0 x' = g u``, i.e. ``(m / g) x'' + (b0 / g) x' = u``: identification finds
``m / g`` and ``b0 / g`` and cannot tell ``g`` from ``m`` (a wrong position scale enters the
same way). The closed loop the host runs is then predicted right in the host's units, but
the hand feels ``g`` times the forces hapsim reports.

A known mass ``dm`` clamped to the handle separates them: two identifications give
``m1 = m / g`` and ``m2 = (m + dm) / g``, hence ``g = dm / (m2 - m1)``, the true full scale
``g * full_scale_assumed`` and the true mass ``g * m1`` (a spring of known stiffness at the
handle would do as well: its felt stiffness is scaled by ``g``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hapsim.errors import ConfigError

__all__ = ["ForceScale", "full_scale_from_added_mass", "rescale_fit"]


@dataclass(frozen=True)
class ForceScale:
    """The force scale found with an added mass.

    Attributes
    ----------
    gain : float
        ``g = full_scale_true / full_scale_assumed`` [-].
    gain_lo, gain_hi : float
        Its interval, from the two masses' intervals (the extreme combinations).
    full_scale : float
        ``g * full_scale_assumed`` [N].
    full_scale_lo, full_scale_hi : float
        Its interval [N].
    mass : float
        The moving mass without the added one, ``g * m1`` [kg].
    """

    gain: float
    gain_lo: float
    gain_hi: float
    full_scale: float
    full_scale_lo: float
    full_scale_hi: float
    mass: float


def full_scale_from_added_mass(m1, m2, added_mass: float,
                               assumed_full_scale: float) -> ForceScale:
    """The true force scale of a device identified twice, without and with a known mass.

    Parameters
    ----------
    m1, m2 : Estimate
        The identified masses (``value``, ``lo``, ``hi`` [kg]; e.g.
        ``DeviceFit.mass``) without and with the added mass, in the units the host assumed.
    added_mass : float > 0
        The mass clamped to the handle for the second record [kg].
    assumed_full_scale : float > 0
        The full scale the host used (``device.protocol_options``) [N].

    Returns
    -------
    ForceScale
        ``g = dm / (m2 - m1)`` (module notes); its interval spans ``dm / (m2.hi - m1.lo)``
        to ``dm / (m2.lo - m1.hi)``.

    Raises
    ------
    ConfigError
        A non-positive added mass or full scale, ``m2`` below ``m1`` beyond their
        intervals (swapped records), or not above it beyond them (the added mass is not
        resolved: add more, or record longer).
    """
    if not (math.isfinite(added_mass) and added_mass > 0):
        raise ConfigError(f"must be a positive mass [kg], got {added_mass!r}", key="added_mass")
    if not (math.isfinite(assumed_full_scale) and assumed_full_scale > 0):
        raise ConfigError(f"must be a positive force [N], got {assumed_full_scale!r}",
                          key="full_scale")
    dm = float(added_mass)
    lo_den = m2.lo - m1.hi
    if m2.hi < m1.lo:
        # (before: said to overlap; the loaded record is lighter beyond both intervals)
        raise ConfigError(f"the mass identified with the added mass ([{m2.lo:.4g}, "
                          f"{m2.hi:.4g}] kg) is below the one without it ([{m1.lo:.4g}, "
                          f"{m1.hi:.4g}] kg): the two records are swapped, or the mass was "
                          "not on the handle", key="added_mass")
    if not lo_den > 0:
        raise ConfigError(f"the added mass is not resolved: the masses identified with and "
                          f"without it overlap ([{m1.lo:.4g}, {m1.hi:.4g}] and [{m2.lo:.4g}, "
                          f"{m2.hi:.4g}] kg); add more mass or record longer",
                          key="added_mass")
    g = dm / (m2.value - m1.value)
    g_lo, g_hi = dm / (m2.hi - m1.lo), dm / lo_den
    fs = float(assumed_full_scale)
    return ForceScale(g, g_lo, g_hi, g * fs, g_lo * fs, g_hi * fs, g * m1.value)


def rescale_fit(fit, scale: ForceScale, kind: str = "force"):
    """The device identified in the host's assumed units, in the device's own.

    With ``g`` the gain :func:`full_scale_from_added_mass` found, the identified mass and
    viscous friction are ``m / g`` and ``b0 / g`` (module notes): the device's are ``g``
    times them, their intervals spanning the gain's too (``[g_lo lo, g_hi hi]``). A wrong
    *force* scale (``kind="force"``: the FireFader's ``full_scale``) scales the Coulomb
    friction the same way; a wrong *position* scale (``kind="position"``: the Haply board's
    counts per revolution) leaves forces as they are and scales positions by ``g``: the
    encoder step, the noise and the rest position are ``1 / g`` times the identified ones.

    Parameters
    ----------
    fit : hapsim.analysis.device_fit.DeviceFit
        The identification without the added mass.
    scale : ForceScale
        The gain found with the added mass (``gain``, ``gain_lo``, ``gain_hi`` > 0).
    kind : {"force", "position"}
        Which scale the host assumed wrongly.

    Returns
    -------
    DeviceFit
        A copy in the device's units.

    Raises
    ------
    ConfigError
        An unknown ``kind`` or a gain interval that is not positive.
    """
    import dataclasses
    if kind not in ("force", "position"):
        raise ConfigError(f"must be 'force' or 'position', got {kind!r}", key="kind")
    g, lo, hi = scale.gain, scale.gain_lo, scale.gain_hi
    if not (g > 0 and lo > 0 and hi >= lo):
        raise ConfigError(f"the gain must be positive, got {g:g} [{lo:g}, {hi:g}]",
                          key="added_mass")

    def times(e):
        return dataclasses.replace(e, value=e.value * g, lo=min(e.lo * lo, e.lo * hi),
                                   hi=max(e.hi * hi, e.hi * lo))

    def over(e):
        return dataclasses.replace(e, value=e.value / g, lo=min(e.lo / hi, e.lo / lo),
                                   hi=max(e.hi / lo, e.hi / hi))
    ch = {"mass": times(fit.mass), "friction": times(fit.friction)}
    if kind == "force":
        ch.update(coulomb=times(fit.coulomb), coulomb_pos=times(fit.coulomb_pos),
                  coulomb_neg=times(fit.coulomb_neg))
    else:
        ch.update(position_resolution=over(fit.position_resolution), noise=over(fit.noise),
                  x0=fit.x0 / g)
    return dataclasses.replace(fit, **ch)
