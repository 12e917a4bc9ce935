"""Drivers: the bytes of devices that speak their own protocol, below the host loop.

The host loop (:mod:`hapsim.host.loop`) sees positions in and forces out, as messages of
the framed protocol. A driver owns the bytes of another protocol and a
:class:`~hapsim.drivers.transport.DriverTransport` turns them into those messages, so the
loop itself is unchanged (and the framed protocol, the default, keeps its own transport
and fast path).

Interface of a driver (:class:`~hapsim.drivers.base.Driver`): its serial settings
(``baud``, ``rtscts``), the units of its one driven axis (``position_scale`` [m/count],
``force_scale`` [N/count], ``force_limit`` [N]), ``encode_force(f)`` -> bytes, a fresh
``decoder()`` whose ``feed(bytes)`` returns the positions [m] of the complete records, and
``limits``: what the protocol cannot do (shown by ``--help`` and docs/devices.md).
"""

from __future__ import annotations

from hapsim.errors import ConfigError
from hapsim.scene_schema import PROTOCOLS

__all__ = ["DRIVERS", "get_driver"]

#: Driver names ``--driver`` accepts (and a scene's ``device.protocol``); ``framed`` is
#: hapsim's own protocol (the default).
DRIVERS = PROTOCOLS


def get_driver(name: str, **options):
    """The driver called ``name``.

    Parameters
    ----------
    name : str
        One of :data:`DRIVERS` other than ``"framed"``.
    **options
        Passed to the driver's constructor (e.g. ``axis``, ``full_scale``).

    Returns
    -------
    hapsim.drivers.base.Driver

    Raises
    ------
    ConfigError
        An unknown name (the message lists the valid ones), or ``"framed"`` (it has no
        driver object: the framed protocol is the loop's own transport).
    """
    if name == "firefader":
        from hapsim.drivers.firefader import FireFader
        return FireFader(**options)
    if name == "haply":
        from hapsim.drivers.haply import HaplyM3
        return HaplyM3(**options)
    if name == "hapkit-serial":
        from hapsim.drivers.hapkit_serial import HapkitSerial
        return HapkitSerial(**options)
    raise ConfigError(f"unknown driver {name!r}; valid: {', '.join(DRIVERS)}"
                      + (" (framed is the default transport, not a driver object)"
                         if name == "framed" else ""), key="--driver")
