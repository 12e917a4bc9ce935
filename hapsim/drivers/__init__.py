"""Drivers: the bytes of devices that speak their own protocol, below the host loop, and
the one registry of the device families.

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

:data:`FAMILIES` is the registry: every device family hapsim drives, once, with its name,
dimension, driver class and the route that runs it; :data:`DRIVERS`, :func:`get_driver`,
the scene's ``device.protocol`` choices, ``hapsim run``'s n-D dispatch and the device
table of docs/devices.md are read from it.
"""

from __future__ import annotations

import dataclasses
import importlib
import re

from hapsim.errors import ConfigError

__all__ = ["Family", "FAMILIES", "DEFAULT", "DRIVERS", "family", "get_driver", "device_driver",
           "protocol_of", "axis_units", "in_axis_units", "run_units", "units_of"]


@dataclasses.dataclass(frozen=True)
class Family:
    """One device family of the registry.

    Attributes
    ----------
    name : str
        Its ``--driver`` name (1-D: also a scene's ``device.protocol``).
    dimension : int
        The scenes it drives: 1, 2 or 3 (0: any, the framed protocol).
    driver : str
        Its driver class as ``"module:Class"`` (imported by :meth:`load`; its ``limits``
        say what the protocol cannot do); ``""`` for the framed protocol (the loop's own
        transport, no driver object).
    route : str
        What runs it: ``"loop"``, the host loop (the framed protocol: or its compiled
        twin) through a transport
        (:func:`hapsim.host.transport.open_transport`); else the ``"module:function"``
        taking ``hapsim run``'s arguments (a device whose run is its own).
    transport : str
        The link: ``"framed"`` (:class:`~hapsim.host.transport.SerialTransport`),
        ``"driver"`` (:class:`~hapsim.drivers.transport.DriverTransport`), ``"own"`` (its
        route's: the 2DIY's pyserial link, the Falcon's USB).
    device : str
        The device, as ``--help`` and docs/devices.md name it.
    options : tuple of str
        ``hapsim run``'s flags that go with this family only.
    mock : str
        Its emulated device on the device side, ``"module:Class"`` (a 1-D family's: the
        byte-exact board :mod:`hapsim.emulated.driver_mock` serves on a pty); ``""``: none
        there (the framed protocol's mock is :mod:`hapsim.emulated.mock`; the n-D devices'
        run their own). Named as a string: the drivers stand below the device side and
        never import it.
    """

    name: str
    dimension: int
    driver: str
    route: str
    transport: str
    device: str
    options: tuple = ()
    mock: str = ""

    def load(self):
        """The driver class, its module imported now (None: the framed protocol's).

        Returns
        -------
        type or None
            A :class:`~hapsim.drivers.base.Driver` subclass (the 2DIY's codec,
            :class:`~hapsim.drivers.haply2.Haply2DIY`, and the Falcon's are their own).
        """
        return _resolve(self.driver)

    def load_mock(self):
        """The emulated device's class, its module imported now (None: no driver mock).

        Returns
        -------
        type or None
        """
        return _resolve(self.mock)

    def runner(self):
        """The function that runs this family's ``hapsim run``, its module imported now
        (None: the host loop's route).

        Returns
        -------
        callable or None
            ``hapsim run``'s function of this family (``run_haply2_command``, ...).
        """
        return None if self.route == "loop" else _resolve(self.route)


def _resolve(spec: str):
    """The object a ``"module:name"`` string names (None for ``""``)."""
    if not spec:
        return None
    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


#: The device families, the default (hapsim's own framed protocol) first.
FAMILIES = (
    Family("framed", 0, "", "loop", "framed",
           "hapsim's own protocol (COBS frames, CRC, sequence numbers, watchdog)"),
    Family("firefader", 1, "hapsim.drivers.firefader:FireFader", "loop", "driver",
           "the FireFader (Berdahl), one axis",
           mock="hapsim.emulated.firefader_board:FireFaderDevice"),
    Family("haply", 1, "hapsim.drivers.haply:HaplyM3", "loop", "driver",
           "a Haply M3 board, one joint", mock="hapsim.emulated.haply_board:HaplyDevice"),
    Family("hapkit-serial", 1, "hapsim.drivers.hapkit_serial:HapkitSerial", "loop", "driver",
           "a Hapkit running the WHC2017 sketch",
           mock="hapsim.emulated.hapkit_serial_board:HapkitSerialDevice"),
    Family("haply", 2, "hapsim.drivers.haply2:Haply2DIY",
           "hapsim.commands.run_haply2:run_haply2_command", "own",
           "a pantograph scene, the Haply 2DIY", ("--generation",)),
    Family("falcon", 3, "hapsim.drivers.falcon_usb:FalconUSB",
           "hapsim.commands.run_falcon:run_falcon_command", "own",
           "a delta scene, the Novint Falcon", ("--firmware", "--packets")),
)

#: The default protocol: hapsim's own, framed.
DEFAULT = FAMILIES[0].name

#: Driver names ``--driver`` accepts on a 1-D scene (and a scene's ``device.protocol``);
#: ``framed`` is hapsim's own protocol (the default).
DRIVERS = tuple(f.name for f in FAMILIES if f.dimension <= 1)


def family(name: str, dimension: int = 1) -> Family:
    """The registered family called ``name`` for a scene of ``dimension``.

    Parameters
    ----------
    name : str
    dimension : int
        1, or 2 and 3 (an n-D scene: a family of either, as ``hapsim run`` dispatches).

    Returns
    -------
    Family

    Raises
    ------
    ConfigError
        No such family for that dimension (the message lists the valid ones).
    """
    found = [f for f in FAMILIES if f.name == name and (f.dimension <= 1) == (dimension <= 1)]
    if found:
        return found[0]
    if dimension <= 1:
        raise ConfigError(f"unknown driver {name!r}; valid: {', '.join(DRIVERS)}",
                          key="--driver")
    raise ConfigError("a 2-D or 3-D scene takes " + " or ".join(
        f"--driver {f.name} ({f.device})" for f in FAMILIES if f.dimension > 1)
        + f", not {name!r}", key="--driver")


def axis_units(driver) -> dict:
    """The units a protocol's values are in: a rotary axis's
    (:attr:`hapsim.drivers.base.Driver.rotary`: the Haply joint) or the SI ones of a
    linear axis. The one place they are chosen (identify's device file and fit's words).

    Parameters
    ----------
    driver : hapsim.drivers.base.Driver or str or None
        A driver, or its class, or its name (:data:`DRIVERS`); None or ``"framed"``: the
        framed protocol's (SI).

    Returns
    -------
    dict
        ``mass``, ``friction``, ``force``, ``position``, ``stiffness``, ``speed``:
        ``"kg"``, ``"N s/m"``, ``"N"``, ``"m"``, ``"N/m"``, ``"m/s"``, or ``"kg m^2"``,
        ``"N m s/rad"``, ``"N m"``, ``"rad"``, ``"N m/rad"``, ``"rad/s"``.

    Raises
    ------
    ConfigError
        An unknown driver name (the valid ones listed).
    """
    if isinstance(driver, str):
        driver = family(driver).load()
    if getattr(driver, "rotary", False):
        return {"mass": "kg m^2", "friction": "N m s/rad", "force": "N m", "position": "rad",
                "stiffness": "N m/rad", "speed": "rad/s"}
    return {"mass": "kg", "friction": "N s/m", "force": "N", "position": "m",
            "stiffness": "N/m", "speed": "m/s"}


def run_units(scene, driver: str | None = None) -> dict:
    """The units a 1-D run's figures are in: ``--driver``'s axis, or the scene's
    ``device.protocol``'s where no driver or the framed protocol (which names no axis)
    is given; SI for an n-D scene (Cartesian) or without a scene.

    Parameters
    ----------
    scene : hapsim.scene.Scene or hapsim.scene.SceneND or None
    driver : str or None
        ``--driver`` (one of :data:`DRIVERS`), or None.

    Returns
    -------
    dict
        :func:`axis_units`'s.
    """
    return units_of(int(getattr(scene, "dimension", 1) or 1),
                    getattr(getattr(scene, "device", None), "protocol", None), driver)


def units_of(dimension: int, protocol: str | None, driver: str | None = None) -> dict:
    """:func:`run_units`'s rule on what it reads of a scene: its ``dimension`` and its
    ``device.protocol`` (the command line peeks them from the file,
    :func:`hapsim.scene.scene_dimension`, :func:`hapsim.scene.scene_protocol`).

    Parameters
    ----------
    dimension : int
        1, 2 or 3.
    protocol : str or None
        The scene's ``device.protocol``.
    driver : str or None
        ``--driver``.

    Returns
    -------
    dict
        :func:`axis_units`'s.
    """
    if dimension > 1:
        return axis_units(None)
    if driver is None or driver == DEFAULT:
        driver = protocol
    return axis_units(driver if driver in DRIVERS else None)


#: An SI unit of a linear axis after a number or in brackets (:func:`in_axis_units`):
#: the longest first ("N s/m" before "N"), not one already followed by " m" ("N m").
_SI_UNIT = re.compile(r"(?:(?<=\d )|(?<=\[))(N s/m|N/m|m/s|kg|mm|um|m|N)"
                      r"(?![\w/^]| m\b| s/)")


def in_axis_units(obj, units: dict):
    """``obj`` with the SI units of a linear axis in its sentences said in ``units``
    (:func:`axis_units`'s): a 1-D run's measurement and notes are made by the same code
    for every protocol, in metres and newtons, which on a rotary axis are radians and
    newton metres.

    A unit is rewritten where it follows a number (``"0.00129 m"`` -> ``"0.00129 rad"``)
    or stands in brackets (``"[N/m]"``): ``N s/m``, ``N/m``, ``m/s``, ``kg``, ``mm``,
    ``um``, ``m`` and ``N``. Other words are left as they are.

    Parameters
    ----------
    obj : str or dict or list or tuple or object
        A sentence, or a structure of them (dict values, list and plain tuple items,
        recursively); anything else is returned as it is.
    units : dict
        :func:`axis_units`'s; SI (``position`` ``"m"``) returns ``obj`` itself.

    Returns
    -------
    Same type as ``obj``
        A new structure where something was rewritten (dict keys unchanged).
    """
    if units.get("position", "m") == "m":
        return obj
    if isinstance(obj, dict):
        return {k: in_axis_units(v, units) for k, v in obj.items()}
    if type(obj) in (list, tuple):
        return type(obj)(in_axis_units(v, units) for v in obj)
    if not isinstance(obj, str):
        return obj
    say = {"N s/m": units["friction"], "N/m": units["stiffness"], "m/s": units["speed"],
           "kg": units["mass"], "mm": "m" + units["position"], "um": "u" + units["position"],
           "m": units["position"], "N": units["force"]}
    return _SI_UNIT.sub(lambda mt: say[mt.group(1)], obj)


def protocol_of(scene, driver: str | None) -> tuple[str, str]:
    """The protocol a 1-D run or identification speaks, and where that choice comes from:
    ``--driver`` when given, else the scene's ``device.protocol`` (``hapsim run`` and
    ``hapsim identify --mock-scene`` both take it here: one rule).

    Parameters
    ----------
    scene : hapsim.scene.Scene or None
        The scene (its ``device.protocol``); ``"framed"`` without a scene or a device.
    driver : str or None
        ``--driver`` (None when not given).

    Returns
    -------
    name : str
        One of :data:`DRIVERS` (not checked here: :func:`family` refuses an unknown one).
    said : str
        The name with its source, for the start-up line: ``"the framed protocol"``,
        ``"the firefader protocol (the scene's device.protocol)"``, ``"the hapkit-serial
        protocol (--driver; the scene's device.protocol is firefader)"``.

    Raises
    ------
    ConfigError
        ``--driver`` drives a rotary axis where the scene names a linear one, or the
        reverse (key ``--driver``): the scene's figures are in its own axis's units, and
        read in the other's they are another device (the FireFader's 0.05 kg fader read
        as a 0.05 kg m^2 joint, 50 times the Haply's). The framed protocol names no axis
        (its HELLO says the device's scales): its scenes take any driver, and any scene
        runs on its mock in the scene's own units.
    """
    device = getattr(scene, "device", None)
    named = getattr(device, "protocol", None) or DEFAULT
    if driver is None:
        return named, (f"the {named} protocol" + ("" if named == DEFAULT
                                                   else " (the scene's device.protocol)"))
    if driver != named:
        if device is None:          # no scene (or none with a device): nothing to contrast
            return driver, f"the {driver} protocol (--driver)"
        if DEFAULT not in (named, driver) and driver in DRIVERS and named in DRIVERS:
            ours, theirs = axis_units(driver), axis_units(named)
            if ours["position"] != theirs["position"]:
                def kind(u):
                    return ("a rotary joint" if u["position"] == "rad" else "a linear axis")
                raise ConfigError(
                    f"{driver} drives {kind(ours)} ({ours['mass']}, "
                    f"{ours['stiffness']}, {ours['position']}), but the scene's "
                    f"device.protocol is {named}, {kind(theirs)}: its figures are in "
                    f"{theirs['mass']}, {theirs['stiffness']} and {theirs['position']}, "
                    f"and read in the other's units they are another device. Give a scene "
                    f"written for {driver} (device.protocol: {driver}), or leave --driver "
                    f"out", key="--driver")
        return driver, (f"the {driver} protocol (--driver; the scene's device.protocol "
                        f"is {named})")
    return driver, f"the {driver} protocol"


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
    cls = family(name).load()
    if cls is None:
        raise ConfigError(f"unknown driver {name!r}; valid: {', '.join(DRIVERS)} (framed is "
                          "the default transport, not a driver object)", key="--driver")
    return cls(**options)


def device_driver(device):
    """The driver a 1-D scene's device section names (``device.protocol``), configured
    with its ``device.protocol_options``; None on hapsim's framed protocol.

    What a board does that the scene's numbers do not say is the driver's: its own tick
    (:meth:`~hapsim.drivers.base.Driver.board_rate_hz`,
    :meth:`~hapsim.drivers.base.Driver.board_rates`) and its render after its read
    (``render_latency_s``). ``hapsim check``, ``advise`` and ``run`` take them from here.

    Parameters
    ----------
    device : hapsim.scene.Device or None
        A 1-D scene's device section.

    Returns
    -------
    hapsim.drivers.base.Driver or None

    Raises
    ------
    ConfigError
        Options the driver refuses (its message names the option).
    """
    name = getattr(device, "protocol", None)
    if device is None or name in (None, DEFAULT):
        return None
    return get_driver(name, **(getattr(device, "protocol_options", None) or {}))
