"""``identify``: a device's mass, friction and delay from its own response."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hapsim.drivers import DEFAULT, axis_units
from hapsim.errors import ConfigError, DeviceError, HapsimError, IdentificationError
from hapsim.option_values import check_values
from hapsim.outputs import json_safe
from hapsim.results import Report


# ---------------------------------------------------------------------------- devices
@dataclasses.dataclass(frozen=True)
class IdentifyReport(Report):
    """What ``hapsim identify --json`` says: a device's mass, friction, delay and hold.

    Attributes
    ----------
    device : dict
        The fit (:meth:`hapsim.analysis.device_fit.DeviceFit.to_dict`): each quantity with
        its confidence interval, ``explained``, the residual.
    loop : dict
        The excitation run (samples, stop reason, late, clamped, ...).
    hand : bool
        Whether a hand held the handle (then mass and friction are the THS's).
    out, plot : str or None
        The files the command wrote (None from the API).
    note : str or None
    error : dict or None
        The device lost during the excitation, its record fitted up to the loss: the
        error's ``type`` and ``message`` (``hapsim identify`` then exits 1, the report
        first); None otherwise.

    Other attributes: ``fit`` (the :class:`~hapsim.analysis.device_fit.DeviceFit`) and
    ``record`` (the excitation's columns and loop facts). Its chart (``plot`` is the
    command's file field here): :func:`hapsim.plots.plot_identify` ``(report)``.
    """

    _OPTIONAL = ("note", "error")

    device: dict
    loop: dict
    hand: bool
    out: str | None
    plot: str | None
    note: str | None = None
    error: dict | None = None

    def found_driver(self):
        """The driver the identification went through, as its record found it: its
        ``loop.settings.driver`` with the record's ``protocol_options`` (every parameter,
        the Haply motor direction probed first included).

        Returns
        -------
        hapsim.drivers.base.Driver or None
            None on the framed protocol, or for a report without its record (read back
            from JSON).
        """
        name = (self.loop.get("settings") or {}).get("driver")
        opts = (getattr(self, "record", None) or {}).get("protocol_options")
        if name is None or name == DEFAULT or opts is None:
            return None
        from hapsim.drivers import get_driver
        return get_driver(name, **opts)

    def device_yaml(self, force_limit: float | None = None, driver=None) -> str:
        """The ``device:`` section for a scene or ``hapsim run --device`` (as ``--out``).

        Parameters
        ----------
        force_limit : float, optional
            The excitation's force limit (its comment) [N] ([N m] on a rotary axis), a
            finite number > 0; default the report's own (``loop.settings.force_limit``;
            before: 2 whatever the excitation's was).
        driver : hapsim.drivers.base.Driver, optional
            The driver whose protocol and units it names; default :meth:`found_driver`
            (a Haply joint's file then says [kg m^2]), the framed protocol's SI units
            where the report has none.

        Returns
        -------
        str
            YAML text (:func:`hapsim.device_file.device_yaml`).

        Raises
        ------
        ConfigError
            ``force_limit`` not a finite number > 0, or none given to a report that
            states none; ``driver`` not a driver (keyed by the argument).
        """
        import math

        from hapsim.device_file import device_yaml
        from hapsim.drivers.base import Driver
        from hapsim.option_values import check_kind
        if force_limit is None:
            force_limit = (self.loop.get("settings") or {}).get("force_limit")
        check_kind("force_limit", force_limit, "a number", required=True)
        if not (math.isfinite(force_limit) and force_limit > 0):
            raise ConfigError(f"must be a finite number > 0 [N], got {force_limit!r}",
                              key="force_limit")
        if driver is not None and not isinstance(driver, Driver):
            raise ConfigError(f"must be a driver (hapsim.drivers.get_driver), got "
                              f"{driver!r}", key="driver")
        return device_yaml(self.fit, force_limit, hand=self.hand,
                           driver=self.found_driver() if driver is None else driver)


def identify(port: str | None = None, *, scene=None, driver: str | None = None,
             baud: int = 115200, device=None, force_limit: float | None = None,
             envelope: float | None = None, duration: float | None = None,
             rate_hz: float | None = None, max_delay: int = 20,
             lockstep: bool = False, seed: int = 0, hand: bool = False,
             transport: str | None = None, progress: bool = False,
             handle_signals: bool = False,
             driver_options: dict | None = None,
             mock_options: dict | None = None,
             travel: float | None = None, rt_priority: int = 10) -> IdentifyReport:
    """Excite a device (or its mock) and identify its mass, friction, delay and hold.

    Parameters
    ----------
    port : str, optional
        Serial port of the device; None: the embedded mock of ``device``.
    scene : hapsim.scene.Scene or str, optional
        A 1-D scene (or its file) whose device the mock models, as ``hapsim identify
        --mock-scene``: its ``device.protocol`` (unless ``driver`` is given) with its
        ``protocol_options``, its rate, and the defaults it sets
        (:func:`hapsim.pipeline.identify_settings.identify_settings`). Not with ``device``.
    driver : str, optional
        Its protocol (:data:`hapsim.drivers.DRIVERS`); default the scene's
        ``device.protocol``, else ``"framed"``.
    baud : int
    device : hapsim.scene.Device, optional
        What the mock models (default the protocol's
        :attr:`~hapsim.drivers.base.Driver.identify_device`, else m = 0.1 kg,
        b0 = 0.5 N s/m, d = 1).
    force_limit : float, optional
        Largest force sent [N]; default 2, or the scene's device or protocol limit where
        smaller (:func:`~hapsim.pipeline.identify_settings.default_force_limit`).
    envelope : float, optional
        Position envelope [m] around the start; beyond it the excitation stops. Default
        0.01 (the protocol's own where it has one), or the scene's ``|excitation.x0|``
        where larger
        (:func:`~hapsim.pipeline.identify_settings.default_envelope`).
    duration : float, optional
        Excitation length [s]; default from the rate
        (:func:`~hapsim.pipeline.identify_settings.default_duration`: 4 s at 1 kHz).
    rate_hz : float, optional
        Loop rate [Hz]; default the scene's ``rate_hz``, else 1000 or the highest rate
        of a ladder the board holds (:func:`~hapsim.pipeline.identify_settings.default_rate`).
    max_delay : int
        Largest device delay tried [samples].
    lockstep : bool
        Lockstep embedded mock (deterministic).
    seed : int
    hand : bool
        A hand holds the handle (the result is the THS's mass and damping).
    transport : {"inprocess", "pty", "serial"}, optional
        ``"inprocess"``: the lockstep mock called directly (no child process); default
        ``"serial"`` with a port, else the embedded mock on a pseudo-terminal.
    progress : bool
        A progress bar on stderr when it is a terminal.
    handle_signals : bool
        Stop cleanly on SIGINT/SIGTERM (a library leaves them to its caller by default).
    driver_options : dict, optional
        The driver's device parameters (``device.protocol_options``, e.g. the FireFader's
        ``full_scale``; over the scene's when the protocol is the scene's); the mass and
        friction found are in the units they set.
    mock_options : dict, optional
        A driver mock's hardware (e.g. ``{"full_scale": 1.56}``: a fader other than the
        one ``driver_options`` describe); default the driver's own.
    travel : float, optional
        The FireFader's travel between its end stops [m] (its datasheet's): a sweep between
        the stops finds its position scale first (``loop.travel_sweep``; the
        record's ``protocol_options`` carry it).
    rt_priority : int
        ``SCHED_FIFO`` priority of the excitation's loop on a real-time port where the OS
        permits it (0: normal scheduling; ``loop.scheduling`` says what it got), as
        ``hapsim run``'s ``--rt-priority``.

    Returns
    -------
    IdentifyReport

    Raises
    ------
    ConfigError
        Bad values (keyed by the flag of ``hapsim identify``:
        :data:`hapsim.option_values.API_OPTIONS`), a keyword of the wrong kind (a
        ``device`` that is no :class:`hapsim.scene.Device`, a flag that is no bool, options
        that are no mapping), an unknown driver, both ``scene`` and ``device``, a 2-D or 3-D
        scene or one without a device section (a file: its reading's errors).
    IdentificationError
        A record too short or that the fit cannot explain.
    DeviceError, ProtocolError
        As :func:`run`, before the excitation's first row; a device lost after it whose
        record up to the loss does not identify it (a DeviceError saying why). A record
        that does is returned, with ``error`` set.

    Notes
    -----
    :func:`hapsim.analysis.device_fit.fit_device`: least squares of the sampled plant
    (mass, friction, Coulomb friction, delay, hold) on the recorded positions and forces.
    """
    from hapsim.drivers import family
    from hapsim.pipeline.identify_settings import identify_settings
    if driver is not None:
        try:
            family(driver)              # an unknown name: the valid ones listed
        except ConfigError as exc:      # named by this function's keyword
            raise ConfigError(exc.reason, key="driver") from None
    check_values("identify", baud=baud, force_limit=force_limit, envelope=envelope,
                 duration=duration, rate_hz=rate_hz, max_delay=max_delay, seed=seed,
                 rt_priority=rt_priority)
    _kinds(device=device, lockstep=lockstep, hand=hand, driver_options=driver_options,
           mock_options=mock_options)
    if scene is not None:
        if device is not None:
            raise ConfigError("give a scene or a device, not both", key="device")
        scene = _one_d_scene(scene)
    st = identify_settings(scene, driver=driver, rate_hz=rate_hz, duration=duration,
                           force_limit=force_limit, envelope=envelope, hand=hand,
                           driver_options=driver_options if driver is not None or
                           scene is not None else None)
    if device is None:              # the scene's, or the protocol's where no scene says
        device = st.device
    if st.driver_options is not None:       # a driver's: the scene's, updated by those given
        driver_options = st.driver_options
    driver, rate_hz, duration = st.driver, st.rate_hz, st.duration
    force_limit, envelope = st.force_limit, st.envelope
    fit, rec = excite_and_fit(port=port, baud=baud, device=device, force_limit=force_limit,
                         envelope=envelope, duration=duration, rate_hz=rate_hz,
                         max_delay=max_delay, lockstep=lockstep, seed=seed,
                         driver=None if driver == DEFAULT else driver, progress=progress,
                         transport=transport, handle_signals=handle_signals,
                         driver_options=driver_options, mock_options=mock_options,
                         travel=travel, rt_priority=rt_priority)
    # what it ran with, each value given or its default (hapsim.pipeline.identify_settings)
    rec["loop"]["settings"] = {"protocol": st.said, "driver": driver,
                               "rate_hz": rate_hz, "duration": duration,
                               "force_limit": force_limit, "envelope": envelope}
    d = {"device": fit.to_dict(), "loop": rec["loop"], "hand": bool(hand), "out": None,
         "plot": None, "error": rec["loop"].get("error")}
    if hand:
        d["note"] = "mass and friction are the THS's: hand + handle, for this grip"
    return IdentifyReport.from_dict(json_safe(d), fit=fit, record=rec)


def _one_d_scene(scene):
    """A 1-D scene with a device, from a :class:`~hapsim.scene.Scene` or its file.

    Raises
    ------
    ConfigError
        A 2-D or 3-D scene (``hapsim identify --mock-scene SCENE --lockstep`` identifies
        those), a scene without a device section, the file's own errors.
    """
    if isinstance(scene, (str, bytes)) or hasattr(scene, "__fspath__"):
        from hapsim.scene import load_scene
        scene = load_scene(scene)
    if getattr(scene, "dimension", 1) > 1:
        raise ConfigError(f"a {scene.dimension}-D scene: identify(scene=) takes 1-D scenes "
                          f"('hapsim identify --mock-scene SCENE --lockstep' identifies a "
                          f"2-D or 3-D scene's device)", key="scene")
    if getattr(scene, "device", None) is None:
        raise ConfigError("the scene has no device section: nothing to identify",
                          file=getattr(scene, "path", None), key="device")
    return scene


def excite_and_fit(*, port=None, baud=115200, device=None, force_limit=2.0, envelope=0.01,
             duration=4.0, rate_hz=1000.0, max_delay=20, lockstep=False, seed=0,
             transport=None, progress=True, handle_signals=True, driver=None,
             driver_options=None, mock_options=None, travel=None, rt_priority=10):
    """Excite, record and fit: what ``hapsim identify`` and :func:`identify` run.

    Parameters
    ----------
    port, baud : str, int
        Device port (None: a mock of ``device``) and baud rate.
    device : hapsim.scene.Device, optional
        What the mock models.
    force_limit, envelope, duration, rate_hz, max_delay, lockstep, seed
        As the options of the same names ([N], [m], [s], [Hz], [samples]).
    transport : {"inprocess", "pty", "serial"}, optional
        As :func:`hapsim.pipeline.identify_run.record`.
    progress, handle_signals : bool
        Progress bar on a terminal; clean stop on SIGINT/SIGTERM.
    driver : str, optional
        Device protocol (:data:`hapsim.drivers.DRIVERS`); default hapsim's own.
    driver_options : dict, optional
        The driver's device parameters (``device.protocol_options``: e.g. the FireFader's
        ``full_scale``); the mass and friction found are in the units they set.
    mock_options : dict, optional
        The driver mock's hardware (:func:`hapsim.pipeline.identify_run.record`).
    travel : float, optional
        The FireFader's travel between its end stops [m]
        (:func:`hapsim.pipeline.identify_run.record`).
    rt_priority : int
        As :func:`hapsim.pipeline.identify_run.record`.

    Returns
    -------
    (DeviceFit, dict)
        The fit and the record (:func:`hapsim.pipeline.identify_run.record`).

    Raises
    ------
    ConfigError
        Bad values; a record too short to fit (a safety stop at once).
    DeviceError, ProtocolError
        As ``hapsim run``, before the excitation's first row; a device lost after it
        whose record up to the loss does not identify it. A record that does is fitted
        and returned, ``rec["lost"]`` the DeviceError.
    """
    from hapsim.analysis.device_fit import fit_device
    from hapsim.option_values import check_kind
    from hapsim.outputs import check_fits
    from hapsim.pipeline.identify_run import record
    # every keyword, as identify checks its own (before: only max_delay; a word or None
    # for a number was a TypeError deep in the excitation, a bool taken as 1)
    check_values("identify", required=True, baud=baud, force_limit=force_limit,
                 envelope=envelope, duration=duration, rate_hz=rate_hz,
                 max_delay=max_delay, seed=seed)
    check_values("identify", rt_priority=rt_priority)
    _kinds(device=device, lockstep=lockstep, hand=False, driver_options=driver_options,
           mock_options=mock_options)
    for key, value in (("progress", progress), ("handle_signals", handle_signals)):
        check_kind(key, value, "True or False", required=True)
    check_kind("--port", port, "a path")
    check_kind("--travel", travel, "a number")
    check_kind("transport", transport, "a text")
    if driver is None and (driver_options or mock_options):
        raise ConfigError("options of a driver's protocol or board, and no driver is given",
                          key="--protocol-option" if driver_options else "--mock-option")
    samples = duration * rate_hz
    check_fits(64.0 * samples, f"{samples:.3g} samples of the excitation's record",
               "--duration")
    import signal
    import threading

    from hapsim.host.loop_types import StopFlag
    stop, old = None, {}
    if handle_signals and threading.current_thread() is threading.main_thread():
        # the handlers stay until the fit is made, as hapsim run's stay until its report:
        # a SIGINT/SIGTERM while the mock reports or the fit runs (seconds on a loaded
        # machine) asks for a stop already under way; with the default handler back
        # there it killed the process (-15), the record and the fit lost
        stop = StopFlag()
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, lambda signum, frame: stop.request(signum))
    try:
        rec = record(device, port=port, baud=baud, rate_hz=rate_hz, duration=duration,
                     force_limit=force_limit, envelope=envelope, max_delay=max_delay, seed=seed,
                     noise_seed=seed, transport=transport, lockstep=lockstep, progress=progress,
                     handle_signals=False, stop=stop, driver=driver,
                     driver_options=driver_options, mock_options=mock_options,
                     travel=travel, rt_priority=rt_priority)
        # the whole record: every stretch of consecutive STATEs is fitted, each from its
        # own initial state (a lost STATE is a gap, the mass and frictions are shared)
        seq = rec["seq"]
        a, b = 0, int(seq.size)
        rec["loop"]["fitted_rows"] = [a, b]
        rec["loop"]["gaps"] = int(np.count_nonzero(np.diff(seq) != 1))
        acc = rec.get("account")
        if acc is not None:
            rec["loop"]["account"] = acc.to_dict()
        try:
            try:
                fit = fit_device(rec["position"], rec["force"], rec["period"],
                                 late=rec["late"], max_delay=max_delay + 1, applied=acc,
                                 seq=seq, length_unit=axis_units(driver)["position"])
            except IdentificationError as exc:
                raise IdentificationError(f"{exc}{_safety_note(rec, envelope)}") from None
            except (ArithmeticError, np.linalg.LinAlgError, ValueError) as exc:
                if isinstance(exc, HapsimError):
                    raise
                # the fit failed numerically: the record does not carry what the model
                # needs
                raise IdentificationError(f"the record cannot be identified: the fit "
                                          f"failed ({type(exc).__name__}: {exc}); "
                                          f"{_record_summary(rec, a, b)}") from None
        except (IdentificationError, ConfigError) as exc:
            lost = rec.get("lost")
            if lost is None:
                raise
            # a device lost before its record could identify it: the loss is the error,
            # what the record lacked said with it
            raise DeviceError(f"the device was lost after {b} samples, which do not "
                              f"identify it ({str(exc).splitlines()[0]}): {lost}") from None
        return fit, rec
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def calibrate_scale(bare: IdentifyReport, loaded: IdentifyReport, added_mass: float,
                    driver):
    """A driver's scale parameter from two identifications, without and with a known
    mass clamped to the handle (``hapsim identify --added-mass``).

    Parameters
    ----------
    bare, loaded : IdentifyReport
        :func:`identify` without and with ``added_mass`` on the handle, through ``driver``.
    added_mass : float > 0
        The clamped mass [kg] (an inertia [kg m^2] for a rotary axis).
    driver : hapsim.drivers.base.Driver
        The driver both records were taken through: its ``scale_option`` (the FireFader's
        ``full_scale``, the Haply board's ``resolution``) is the value assumed.

    Returns
    -------
    (ForceScale, DeviceFit, Driver)
        The gain and the parameter found (:func:`hapsim.analysis.calibration.
        full_scale_from_added_mass`: ``full_scale`` is the parameter whatever it is),
        ``bare``'s fit in the device's own units
        (:func:`~hapsim.analysis.calibration.rescale_fit`) and the driver with the
        parameter found (its :meth:`~hapsim.drivers.base.Driver.options` are what the
        device file's ``protocol_options`` then hold).

    Raises
    ------
    ConfigError
        A report that is no identification's with its fit (one read back from JSON has
        none), a driver that is no driver or not the one the reports name
        (``loop.settings.driver``), a driver whose protocol carries SI units (nothing to
        calibrate), a bad mass, or the added mass not resolved by the two fits.
    """
    from hapsim.analysis.calibration import full_scale_from_added_mass, rescale_fit
    from hapsim.drivers import get_driver
    from hapsim.drivers.base import Driver
    check_values("identify", required=True, added_mass=added_mass)
    for key, rep in (("bare", bare), ("loaded", loaded)):
        if getattr(rep, "fit", None) is None:
            raise ConfigError(f"must be identify()'s report, with its fit (one read back "
                              f"from JSON has none), got {type(rep).__name__}", key=key)
    if not isinstance(driver, Driver):
        raise ConfigError(f"must be a driver (hapsim.drivers.get_driver), got {driver!r}",
                          key="driver")
    for key, rep in (("bare", bare), ("loaded", loaded)):
        # (before: a Haply driver took two FireFader records and rescaled its resolution
        # by the fader's gain)
        named = ((getattr(rep, "loop", None) or {}).get("settings") or {}).get("driver")
        if named is not None and named != driver.name:
            raise ConfigError(f"the {key} record went through the {named} driver, not "
                              f"{driver.name}: the scale is the driver's the records were "
                              "taken through", key="driver")
    opt = driver.scale_option
    if opt is None:
        raise ConfigError(f"the {driver.name} protocol carries SI units: no scale to "
                          f"calibrate (valid with --added-mass: the drivers firefader and "
                          f"haply)", key="--added-mass")
    sc = full_scale_from_added_mass(bare.fit.mass, loaded.fit.mass, added_mass,
                                    float(getattr(driver, opt)))
    fit = rescale_fit(bare.fit, sc, driver.scale_kind)
    opts = driver.options()
    opts[opt] = sc.full_scale
    return sc, fit, get_driver(driver.name, **opts)


def _safety_note(rec: dict, envelope: float) -> str:
    """Why a record that could not be fitted ended, when it ended on a safety stop: the
    stop, and where the device started against the envelope (the excitation moves it
    about its start, up to 0.7-0.8 of ``envelope``, while the stop is at ``|x| >
    envelope``: a device resting off-centre leaves the envelope early). ``""`` otherwise.

    Before, such a record said only "too short a record" (the independent FireFader model
    of ``tools/independent_boards`` resting at 15 mm, ``--envelope 0.02``: stopped at
    sample 177 of 750, three runs of three).

    Parameters
    ----------
    rec : dict
        The record (:func:`hapsim.pipeline.identify_run.record`): ``loop``'s
        ``safety_stop``, ``stop_reason`` and ``samples``, and ``position`` [m].
    envelope : float
        ``--envelope`` [m].

    Returns
    -------
    str
        ``"; the excitation ended on a safety stop ..."`` or ``""``.
    """
    loop = rec.get("loop") or {}
    if not loop.get("safety_stop"):
        return ""
    pos = np.asarray(rec.get("position", ()), float)
    note = (f"; the excitation ended on a safety stop at sample {loop.get('samples')}: "
            f"{loop.get('stop_reason')}")
    if pos.size and math.isfinite(pos[0]):
        x0 = float(pos[0])
        room = float(envelope) - abs(x0)
        note += (f"; the device started at {x0:.4g}, {room:.3g} inside the envelope of "
                 f"+-{envelope:g} (the excitation moves it up to 0.8 x that about its "
                 f"start): start it near the envelope's centre (0), or widen --envelope")
    return note


def _record_summary(rec, a: int, b: int) -> str:
    """One phrase on a record: rows fitted, late ticks, the device's delay, its stop."""
    loop = rec["loop"]
    dd = loop.get("device_delay")
    return (f"rows {a}..{b}, {int(np.count_nonzero(rec['late'][a:b]))} late, device delay "
            f"{'not shown' if dd is None or dd < 0 else dd}, stop: {loop['stop_reason']}")


def _kinds(device, lockstep, hand, driver_options, mock_options) -> None:
    """Refuse :func:`identify`'s keywords of the wrong kind, by their flag (before: a
    ``device`` of 1.0 was a TypeError from ``dataclasses.asdict``; ``lockstep="x"`` was
    taken as True, ``driver_options="x"`` without a driver ignored)."""
    from hapsim.option_values import check_kind
    from hapsim.scene import Device
    if device is not None and not isinstance(device, Device):
        raise ConfigError(f"must be a hapsim.scene.Device, got {device!r}", key="device")
    check_kind("--lockstep", lockstep, "True or False", required=True)
    check_kind("--hand", hand, "True or False", required=True)
    check_kind("--protocol-option", driver_options, "a mapping of options")
    check_kind("--mock-option", mock_options, "a mapping of options")
