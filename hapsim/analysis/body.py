"""The device's moving body seen by the analysis: mass and friction of the handle with the
hand on it, the hand's stiffness to ground, the ideal hold's shift row.

Below :mod:`hapsim.analysis.network` and :mod:`hapsim.analysis.corrections`, which both
build the closed loop's plant rows from it (Florens, Voda & Urma eq. (4); the hand model of
:mod:`hapsim.analysis.hand`).
"""

from __future__ import annotations

import math

__all__ = ["device_body", "body_stiffness"]


def device_body(dev, member=None) -> tuple[float, float]:
    """Total moving mass [kg] and friction [N s/m] of a device (handle + hand).

    Parameters
    ----------
    dev : hapsim.scene.Device
    member : array_like, shape (4,) or (5,), optional
        Hand member ``(mh, bh, kg, bg[, kh])``; default the nominal member of ``dev.hand``.

    Returns
    -------
    (float, float)
        ``(m + mh, b0 + bh)`` (``(m, b0)`` without a hand): the mass the felt
        ``k = m |s|^2``, ``b = -2 m Re s`` are expressed with.
    """
    from hapsim.analysis.hand import nominal_member

    m, b0 = float(dev.mass), float(dev.friction)
    hand = getattr(dev, "hand", None)
    if member is None and hand is None:
        return m, b0
    mh, bh = (member if member is not None else nominal_member(hand))[:2]
    return m + float(mh), b0 + float(bh)



def body_stiffness(dev, member=None) -> float:
    """Real stiffness to ground of a device's hand (``device.hand.stiffness``) [N/m].

    Parameters
    ----------
    dev : hapsim.scene.Device
    member : array_like, shape (4,) or (5,), optional
        Hand member; default the nominal member of ``dev.hand``.

    Returns
    -------
    float
        ``kh`` (0 without a hand or for a 4-column member).
    """
    from hapsim.analysis.hand import hand_stiffness, nominal_member

    hand = getattr(dev, "hand", None)
    if member is None and hand is None:
        return 0.0
    return float(hand_stiffness(member if member is not None else nominal_member(hand)))



def ideal_shift(dev, T: float, member=None) -> tuple[float, float, float]:
    """``(tr, det, g)`` of the ideal hold's ``x[n+1] = tr x[n] - det x[n-1] + g f[n]``
    (Florens et al. eq. (4); with the hand's stiffness the impulse-invariant image,
    :func:`hapsim.analysis.hand.ideal_rows`).

    Parameters
    ----------
    dev : hapsim.scene.Device
        The device (mass [kg], friction [N s/m], hand).
    T : float
        Sample period [s].
    member : array_like, shape (4,) or (5,), optional
        Hand member ``(mh, bh, kg, bg[, kh])``; None: the nominal ``dev.hand``.

    Returns
    -------
    tr, det : float
        ``1 + a`` and ``a`` [-], ``a = exp(-b T / m)`` of the body ``(m, b)``
        (:func:`device_body`), without a hand stiffness.
    g : float
        ``T^2 / (m c)`` [m/N], ``c = (b T / m) / (1 - a)`` (1 for ``b = 0``); with a hand
        stiffness all three are :func:`hapsim.analysis.hand.ideal_rows`'.
    """
    mass, b0 = device_body(dev, member)
    kh = body_stiffness(dev, member)
    if kh > 0:
        from hapsim.analysis.hand import ideal_rows
        return tuple(float(v) for v in ideal_rows(mass, b0, kh, T))
    x = b0 * T / mass
    a = math.exp(-x)
    c = x / -math.expm1(-x) if x > 0 else 1.0
    return 1.0 + a, a, T * T / (mass * c)



def is_compliant(dev, member) -> bool:
    """Whether the hand holds the handle through a compliant grip (finite grip stiffness).

    Parameters
    ----------
    dev : hapsim.scene.Device
    member : array_like, shape (4,) or (5,), or None
        Hand member ``(mh, bh, kg, bg[, kh])``; None: the nominal ``dev.hand``.

    Returns
    -------
    bool
        True when ``kg`` is finite (4 plant states), False for a rigid grip or no hand.
    """
    hand = getattr(dev, "hand", None)
    if member is not None:
        return math.isfinite(float(member[2]))
    return hand is not None and not hand.rigid
