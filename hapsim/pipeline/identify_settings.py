"""What ``hapsim identify`` runs with when an option is not given: the protocol, the rate,
the duration, the force limit and the envelope, from the scene (``--mock-scene``) and the
fit's needs.

One resolver for the command and the API (:func:`identify_settings`): ``hapsim identify
--mock-scene SCENE`` and ``hapsim.api.identify(scene=SCENE)`` identify the same device
the same way.

The defaults (docs/identify.md, "The defaults"):

- the protocol: ``--driver``, else the scene's ``device.protocol``, as ``hapsim run``
  takes it (:func:`hapsim.drivers.protocol_of`: one rule), with the scene's
  ``device.protocol_options`` when the protocol is the scene's;
- the rate: ``--rate``, else the scene's ``rate_hz``, else 1000 Hz or, through a board
  that cannot hold it, the highest rate of :data:`RATE_LADDER` it holds
  (:func:`default_rate`: the FireFader's 250 Hz, the Hapkit sketch's 201.613 Hz);
- without a scene, the embedded mock's device and the envelope the protocol's own where
  it has them (:attr:`hapsim.drivers.base.Driver.identify_device`: the Haply joint's);
- the duration (:func:`default_duration`): the probe's longest time plus 16 times the
  fit's samples of clear motion, and never less than 4 s;
- the force limit (:func:`default_force_limit`): 2 N, or less where the scene's device or
  its protocol allows less;
- the envelope (:func:`default_envelope`): 0.01 (the protocol's own where it has one),
  or the scene's own start ``|x0|`` where it is larger (in the scene's units: a rotary
  axis's radians).
"""

from __future__ import annotations

import dataclasses
import math

from hapsim.errors import ConfigError

__all__ = ["IdentifySettings", "identify_settings", "default_duration",
           "default_force_limit", "default_envelope", "default_rate", "DEFAULT_RATE_HZ",
           "RATE_LADDER",
           "DEFAULT_FORCE_LIMIT", "DEFAULT_ENVELOPE", "DURATION_FLOOR_S", "MOVING_FACTOR"]

#: The loop rate without ``--rate`` or a scene [Hz].
DEFAULT_RATE_HZ = 1000.0
#: The rates a board that cannot hold :data:`DEFAULT_RATE_HZ` is offered, increasing [Hz]
#: (its highest held is the default: :func:`default_rate`).
RATE_LADDER = (100.0, 200.0, 250.0, 500.0, 1000.0)
#: The largest force sent without ``--force-limit`` [N], where neither the scene's device
#: nor its protocol allows less.
DEFAULT_FORCE_LIMIT = 2.0
#: The envelope without ``--envelope`` [m], where the scene's start is not farther out.
DEFAULT_ENVELOPE = 0.01
#: The shortest default duration [s]: at 1 kHz and above, the duration that identified
#: every device of the blind tests (docs/identify.md): after the probe (2.4 s), 1.6 s, six
#: of the square wave's 250-ms pushes, three each way.
DURATION_FLOOR_S = 4.0
#: Samples recorded after the probe, in units of the fit's
#: :data:`~hapsim.analysis.device_fit.MIN_MOVING` samples of clear motion: 16 (1,600
#: samples, what 4 s gives at 1 kHz after the probe). Measured on the FireFader's scene
#: at 250 Hz (its defaults, seed 0): no clear motion before 2.2 s (547 samples; in the
#: old fixed 4 s none at all), 536 samples of it in the 8.8 s, 521 of them in the 1,600
#: after the probe: 5.4 times MIN_MOVING.
MOVING_FACTOR = 16


@dataclasses.dataclass(frozen=True)
class IdentifySettings:
    """What an identification runs with, each value given or its default.

    Attributes
    ----------
    device : hapsim.scene.Device or None
        The scene's device (what the embedded mock models), without the scene's hand
        unless ``hand``; without a scene the protocol's
        (:attr:`hapsim.drivers.base.Driver.identify_device`), else None (hapsim's
        default mock device).
    driver : str
        The protocol (:data:`hapsim.drivers.DRIVERS`).
    said : str
        Where the protocol comes from (:func:`hapsim.drivers.protocol_of`).
    driver_options : dict or None
        The driver's device parameters (the scene's ``device.protocol_options`` when it
        names this protocol, updated by those given); None on the framed protocol.
    rate_hz : float
        Loop rate [Hz].
    duration : float
        Excitation length [s].
    force_limit : float
        Largest force sent [N] (the scene's units: [N m] on a rotary axis).
    envelope : float
        Position envelope around the start [m] (the scene's units: [rad] on a rotary axis).
    """

    device: object
    driver: str
    said: str
    driver_options: dict | None
    rate_hz: float
    duration: float
    force_limit: float
    envelope: float


def default_duration(rate_hz: float) -> float:
    """The excitation's length when none is given [s].

    ``max(DURATION_FLOOR_S, PROBE_S + MOVING_FACTOR * MIN_MOVING / rate_hz)``, rounded up
    to 0.1 s: the probe's longest time to reach its top level
    (:data:`hapsim.pipeline.excitation.PROBE_S`, 2.4 s: from 1/64 of the level by 2^(1/4)
    every 100 ms) plus :data:`MOVING_FACTOR` times the fit's
    :data:`~hapsim.analysis.device_fit.MIN_MOVING` samples of clear motion (the fit refuses
    fewer: "hardly moved"). The probe's time is in seconds, the fit's need in samples: at
    1 kHz and above this is 4 s, as before; at a board's lower rate it grows (250 Hz, the
    FireFader's: 8.8 s; 201.613 Hz, the Hapkit sketch's: 10.4 s), where a fixed 4 s left
    the FireFader's scene no sample of clear motion.

    Parameters
    ----------
    rate_hz : float > 0
        Loop rate [Hz].

    Returns
    -------
    float
        Duration [s], at least :data:`DURATION_FLOOR_S`.

    Raises
    ------
    ConfigError
        A rate that is not a positive finite number (key ``--rate``).
    """
    from hapsim.analysis.device_fit import MIN_MOVING
    from hapsim.pipeline.excitation import PROBE_S
    if isinstance(rate_hz, bool) or not (isinstance(rate_hz, (int, float))
                                         and math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"must be a positive rate [Hz], got {rate_hz!r}", key="--rate")
    need = PROBE_S + MOVING_FACTOR * MIN_MOVING / float(rate_hz)
    return max(DURATION_FLOOR_S, math.ceil(round(need * 10.0, 6)) / 10.0)


def default_rate(driver=None) -> float:
    """The loop rate when neither ``--rate`` nor a scene gives one [Hz]:
    :data:`DEFAULT_RATE_HZ`, or through a board that cannot hold it the highest rate of
    :data:`RATE_LADDER` it holds (:meth:`hapsim.drivers.base.Driver.board_rates`: its
    round trip, and the Hapkit sketch's whole ticks).

    Before, 1000 Hz was refused on the FireFader (a 2.99 ms round trip) and the Hapkit
    sketch (4.27 ms): ``hapsim identify --driver firefader`` failed with its defaults.

    Parameters
    ----------
    driver : hapsim.drivers.base.Driver, optional
        The protocol's driver; None: hapsim's framed protocol (no bound of its own).

    Returns
    -------
    float
        Rate [Hz]: 1000 where the board holds it; the FireFader's 250, the Hapkit
        sketch's 201.613 (5 of its 0.992 ms ticks); 1000 where it holds none of the
        ladder (its own refusal then says why).
    """
    if driver is None:
        return DEFAULT_RATE_HZ
    held = driver.board_rates(RATE_LADDER)
    if not held or held[-1] >= DEFAULT_RATE_HZ:
        return DEFAULT_RATE_HZ
    return float(held[-1])


def default_force_limit(device=None, driver=None) -> float:
    """The largest force sent when none is given [N]: :data:`DEFAULT_FORCE_LIMIT`, or the
    scene's ``device.force_limit`` or the protocol's own limit where smaller.

    An excitation designed for a force the device cannot apply is clipped by its board
    (the Haply board's 0.123 N m against the 2 N default: a force at the limit half the
    time, a safety stop), and one beyond the scene's limit asks more of the device than its
    scene does.

    Parameters
    ----------
    device : hapsim.scene.Device, optional
        The scene's device (its ``force_limit`` [N], infinite when the scene states none).
    driver : hapsim.drivers.base.Driver, optional
        The protocol's driver (its ``force_limit`` [N]).

    Returns
    -------
    float
        Force [N] (the scene's units).
    """
    limits = [DEFAULT_FORCE_LIMIT]
    for obj in (device, driver):
        v = getattr(obj, "force_limit", None)
        if v is not None and math.isfinite(v) and v > 0:
            limits.append(float(v))
    return min(limits)


def default_envelope(scene=None, driver=None) -> float:
    """The position envelope when none is given: :data:`DEFAULT_ENVELOPE` (the protocol's
    own, :attr:`hapsim.drivers.base.Driver.identify_envelope`, where it has one), or the
    scene's own start ``|excitation.x0|`` where it is larger.

    The scene's start is an excursion its device is already asked to make, in the scene's
    units: 0.01 is metres, and on a rotary axis (the Haply joint of ``configs/haply.yaml``,
    0.2 rad) 0.01 rad spans 8 of its encoder's counts, too few for the fit to see clear
    motion ("hardly moved").

    Parameters
    ----------
    scene : hapsim.scene.Scene, optional
        A 1-D scene (its ``excitation.x0``).
    driver : hapsim.drivers.base.Driver, optional
        The protocol's driver (its ``identify_envelope``).

    Returns
    -------
    float
        The envelope's half-width [m] (the scene's units).
    """
    base = getattr(driver, "identify_envelope", None) or DEFAULT_ENVELOPE
    x0 = getattr(getattr(scene, "excitation", None), "x0", 0.0)
    try:
        x0 = abs(float(x0))
    except (TypeError, ValueError):
        x0 = 0.0
    return max(base, x0) if math.isfinite(x0) else base


def identify_settings(scene=None, *, driver: str | None = None,
                      driver_options: dict | None = None, rate_hz: float | None = None,
                      duration: float | None = None, force_limit: float | None = None,
                      envelope: float | None = None, hand: bool = False) -> IdentifySettings:
    """What an identification of ``scene``'s device runs with: each value given, else its
    default (module notes).

    Parameters
    ----------
    scene : hapsim.scene.Scene, optional
        A 1-D scene with a device (``--mock-scene``); None: hapsim's default mock device.
    driver : str, optional
        ``--driver``; None: the scene's ``device.protocol`` (framed without one).
    driver_options : dict, optional
        ``--protocol-option``: over the scene's ``device.protocol_options`` when the
        protocol is the scene's.
    rate_hz, duration, force_limit, envelope : float, optional
        As given ([Hz], [s], [N], [m]); None: the default.
    hand : bool
        ``--hand``: the scene's hand (``device.hand``) stays on the mock's handle. Without
        it the mock is the device alone, as ``identify`` without ``--hand`` asks of a
        real one (the scene's ``mass`` and ``friction`` are then the handle's alone:
        :class:`hapsim.scene.Device`); with the hand on, configs/hand_wall.yaml's grip
        spring made the rigid model fail ("does NOT explain", 0.39 kg for its 0.05).

    Returns
    -------
    IdentifySettings

    Raises
    ------
    ConfigError
        An unknown driver (the valid ones listed, key ``--driver``), options the driver
        refuses (key ``--protocol-option``), options given on the framed protocol, a scene
        without a device section (key ``device``), a bad rate.
    """
    from hapsim.drivers import DEFAULT, family, get_driver, protocol_of
    device = None
    if scene is not None:
        device = getattr(scene, "device", None)
        if device is None:
            raise ConfigError("the scene has no device section: nothing to identify",
                              file=getattr(scene, "path", None), key="device")
        if not hand and getattr(device, "hand", None) is not None:
            device = dataclasses.replace(device, hand=None)
    name, said = protocol_of(scene, driver)
    family(name)                        # an unknown name: the valid ones listed
    drv = None
    opts = None
    if name != DEFAULT:
        opts = dict(device.protocol_options or {}) if (
            device is not None and device.protocol == name) else {}
        opts.update(driver_options or {})
        try:
            drv = get_driver(name, **opts)
        except TypeError as exc:
            raise ConfigError(f"{exc}", key="--protocol-option") from None
    elif driver_options:
        raise ConfigError("the framed protocol takes no options (its device says its units "
                          "in HELLO); give --driver", key="--protocol-option")
    if scene is None and getattr(drv, "identify_device", None):
        from hapsim.device_model import DEFAULT_DEVICE
        device = dataclasses.replace(DEFAULT_DEVICE, **drv.identify_device)
    if rate_hz is None:
        rate_hz = float(scene.rate_hz) if scene is not None else default_rate(drv)
    return IdentifySettings(
        device=device, driver=name, said=said, driver_options=opts, rate_hz=float(rate_hz),
        duration=default_duration(rate_hz) if duration is None else duration,
        force_limit=default_force_limit(device, drv) if force_limit is None else force_limit,
        envelope=default_envelope(scene, drv) if envelope is None else envelope)
