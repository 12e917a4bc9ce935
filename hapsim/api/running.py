"""``run``: the loop closed on a device or its mock and what is felt measured, in any
dimension (a 1-D scene's felt pair, :mod:`hapsim.pipeline.runner`; a 2-D or 3-D scene's
felt matrices, :mod:`hapsim.pipeline.felt_run`)."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np

from hapsim.errors import ConfigError
from hapsim.option_values import check_values
from hapsim.outputs import json_safe
from hapsim.api.common import (Charted, MeasuredPair, load_scene, matrix_list,
                               matrix_or_nan, n_d_scene, scene_given)
from hapsim.results import Report


# ---------------------------------------------------------------------------- run
@dataclasses.dataclass(frozen=True)
class RunReport(Charted, MeasuredPair, Report):
    """What ``hapsim run SCENE --json`` says: the loop closed, what was felt, how it ran.

    Attributes
    ----------
    scene : str
    target : dict or None
        The first target link's (k, b) and renderability (``targets``: all of them).
    targets : list of dict
    virtual : dict
        The (K, B) simulated.
    predicted : dict
        ``k`` [N/m], ``b`` [N s/m], ``f0_hz``, ``damping_ratio``, ``stable``, ...
    measured : dict
        The same figures identified from the logged free response, with their
        uncertainty and the verdict (``error`` when nothing could be measured).
    loop : dict
        Rate, ticks, late, missed, turnaround, stop reason, the device's protocol, ...
    telemetry, osc, sound : dict or None
    error : dict or None
        ``type`` and ``message`` of the device error that ended the run (the device lost
        beyond recovery); None when it ran to its end.
    advice : dict or None
        What ``auto`` chose (rate and integrator).
    verdict : str
        ``"within"``, ``"differs"`` or ``"not measurable"``: ``measured``'s verdict in the
        word a 2-D/3-D run's report has at its top level (:class:`RunReportND`;
        :func:`hapsim.pipeline.report.verdict_summary`).
    within : bool or None
        Measured = predicted within the stated uncertainty (None: not measurable).
    reason : str
        The verdict in words (``measured``'s sentence).
    units : dict or None
        The units of the axis's figures (:func:`hapsim.drivers.axis_units`: SI, or a
        rotary joint's, in which ``predicted`` and ``measured`` are then said).

    Other attributes: ``exit_code``, what ``hapsim run`` exits with (0, or 1 after a
    safety stop or a device fault).
    """

    _OPTIONAL = ("error", "advice")

    scene: str
    target: dict | None
    targets: list
    virtual: dict
    predicted: dict
    measured: dict
    loop: dict
    telemetry: dict | None
    osc: dict | None
    sound: dict | None
    error: dict | None = None
    advice: dict | None = None
    verdict: str | None = None
    within: bool | None = None
    reason: str | None = None
    units: dict | None = None

    def exit_rule(self) -> bool:
        """Whether ``hapsim run`` exited 0, from the report's content: no device lost
        (``error``), no safety stop, no fault, a link that kept the loop it measured
        (:func:`hapsim.pipeline.report.build_report`'s rule).

        Returns
        -------
        bool
        """
        import copy

        from hapsim.host.link_verdict import link_verdict
        from hapsim.pipeline.report import run_failed
        loop = self.loop or {}
        unfit = link_verdict(copy.deepcopy(self.measured or {}), copy.deepcopy(loop))
        return not (self.error or run_failed(loop, unfit))

    _chart = "plot_felt"

    def text(self) -> str:
        """The human report ``hapsim run`` prints (:func:`hapsim.pipeline.report.format_report`).

        Returns
        -------
        str
            Several aligned lines, no trailing newline.
        """
        from hapsim.pipeline.report import format_report
        return format_report(self.to_dict())


#: RunOptions fields that are the run's own bookkeeping, not options of :func:`run`.
_RUN_INTERNAL = ("plan", "embedded")


def run_options() -> tuple:
    """The options :func:`run` takes: the fields of
    :class:`hapsim.pipeline.options.RunOptions` (what ``hapsim run``'s options become).

    Returns
    -------
    tuple of str
    """
    from hapsim.pipeline.options import RunOptions
    return tuple(f.name for f in dataclasses.fields(RunOptions)
                 if f.name not in _RUN_INTERNAL)


def run(scene, options=None, *, amplitude: float | None = None, **changes: Any):
    """Close the loop of a scene on a device (``port``) or on its mock, and measure it.

    A scene of any dimension: a 2-D or 3-D one measures its felt matrices
    (:func:`hapsim.api.run_scene_nd`, a :class:`RunReportND`), one with several ports
    the felt matrices across them in lockstep (:func:`run_scene_ports`, a
    :class:`RunReportND`), a 1-D one its felt pair (below).

    ``hapsim run`` is this function with the options of its command line
    (:meth:`hapsim.pipeline.options.RunOptions.from_args`); it prints the result.

    Parameters
    ----------
    scene : hapsim.scene.Scene, hapsim.scene.SceneND, hapsim.scene.ScenePorts or str
    options : hapsim.pipeline.options.RunOptions, optional
        All the options at once (default: ``RunOptions(handle_signals=False)``: a library
        leaves SIGINT to its caller).
    amplitude : float, optional
        A 2-D or 3-D scene's or several ports' excitation [m] (default 1e-8); a 1-D
        scene refuses it (its hand's start is the scene's ``excitation``).
    **changes
        Options by name, over ``options`` (:func:`run_options`): ``port`` (None: the
        embedded mock on a pseudo-terminal), ``duration`` [s], ``lockstep`` (deterministic
        mock), ``driver`` (default: the scene's ``device.protocol``), ``telemetry`` (a
        file), ``transport`` (``"inprocess"``: the lockstep mock called directly, no child
        process), ``handle_signals``, ...

    Returns
    -------
    RunReport or RunReportND
        Also when the run ended on a safety stop or a device fault (``ok`` False; a device
        lost beyond recovery: ``error``). A 2-D/3-D scene's, or several ports',
        :class:`RunReportND`.

    Raises
    ------
    ConfigError
        An invalid scene or option (an unknown option names the valid ones).
    UnstableConfigError
        An unstable loop without ``allow_unstable``, an unrenderable target.
    DeviceError, ProtocolError
        The port failed or the device was lost beyond recovery before anything ran.

    Notes
    -----
    The measured (k, b) are identified from the free response by the matrix pencil
    method (Hua & Sarkar 1990) beside the THS prediction (Florens, Voda & Urma).
    """
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import run_scene
    from hapsim.errors import DeviceError, ProtocolError

    valid = run_options()
    unknown = sorted(set(changes) - set(valid))
    if unknown:
        raise ConfigError(f"unknown option(s) {', '.join(unknown)}; valid: "
                          f"{', '.join(valid)}", key=unknown[0])
    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)               # in the dimension it declares
    scene_given(scene)
    if options is not None and not isinstance(options, RunOptions):
        raise ConfigError(f"must be a RunOptions (hapsim.api.run_options names its fields), "
                          f"got {options!r}", key="options")
    opts = dataclasses.replace(options if options is not None
                               else RunOptions(handle_signals=False), **changes)
    from hapsim.scene import ScenePorts
    if isinstance(scene, ScenePorts):
        return run_scene_ports(scene, opts, amplitude)
    if getattr(scene, "dimension", 1) != 1:
        return run_scene_nd(scene, opts, amplitude)
    if amplitude is not None:
        raise ConfigError("a 1-D scene's hand starts where its excitation says (x0, v0): "
                          "amplitude is for a 2-D or 3-D scene", key="amplitude")
    driver = opts.driver
    if driver is None and scene.device is not None:
        driver = scene.device.protocol
    try:
        rep = run_scene(scene, dataclasses.replace(opts, driver=driver))
    except (DeviceError, ProtocolError) as exc:
        rep = getattr(exc, "report", None)
        if rep is None:
            raise
    code = rep.pop("exit_code")
    return RunReport.from_dict(json_safe(rep), exit_code=code)


@dataclasses.dataclass(frozen=True)
class RunReportND(Report):
    """What ``hapsim run SCENE --json`` says of a 2-D or 3-D scene: the felt matrices
    measured from free responses beside the prediction, and the linearisation bound.

    Attributes
    ----------
    scene : str
    dof : int
    lockstep : bool
        In-process lockstep (True) or over a port.
    stable : bool
        The check's verdict.
    predicted, measured : dict
        ``felt_stiffness`` [N/m], ``felt_damping`` [N s/m] (n x n lists or None),
        ``rendered_poles`` ([re, im] of z); ``measured`` also ``residual`` and ``rank``
        of the fit.
    deviation : dict or None
        ``felt_stiffness``, ``felt_damping``: the largest |measured - predicted| over the
        largest predicted entry.
    linearisation_bound : dict
        :meth:`hapsim.analysis.linearisation.LinearisationBound.to_dict`.
    records, samples, order : int
        Free responses, samples each, the fit's order.
    verdict : str
        ``"within"``, ``"differs"`` or ``"not measurable"``: the deviation against the
        linearisation bound (:func:`hapsim.analysis.felt_matrices.felt_verdict`; the framed
        protocol carries binary64 positions and forces, so the wire adds no term).
    within : bool or None
        The deviation is inside the bound (None: not measurable).
    reason : str
        The verdict in words, as ``hapsim run`` prints it.
    statements : list of dict
        What was stated, per quantity (the felt stiffness and damping matrices as a
        whole) and per principal direction of the prediction (the felt stiffness and
        damping along it): each ``quantity``, ``direction`` (unit vector, None for a
        matrix), ``name``, ``predicted`` and ``measured`` (along the direction [N/m] or
        [N s/m]; None for a matrix), ``deviation``, ``linearisation``, ``wire``,
        ``uncertainty`` [-], ``verdict``, ``within``, ``reason``
        (:func:`hapsim.analysis.felt_matrices.felt_verdict`). ``verdict`` is their conjunction.
    not_stated : list of str
        The names of the statements that were not measurable.
    port, late, watchdog, delay, lost
        Over a port only: the port (with the embedded mock's ``faults``, ``fault_seed``
        and ``faults_injected``), the late ticks, watchdog trips, the device delay per
        record used and the device losses (the port failed).
    rows, counts, bad_frames, incomplete
        Over a port only: rows used per start (the record from rest first); what the
        records met (:func:`hapsim.pipeline.felt_port.measure_felt_port`: STATEs missed,
        duplicates, reordered, records cut short, device resets, losses and recoveries,
        CONFIGs sent); bad frames the host's decoder dropped; why nothing was fitted
        (None when the matrices were measured).
    stop : str or None
        Over a port only: what ended the measurement, ``"end"`` or, when a stop was
        requested, ``"signal SIGINT"`` / ``"signal SIGTERM"`` (Ctrl-C, a service manager),
        or a safety stop's ``"safety: ..."``: what was recorded by then is reported, as
        the 1-D run's ``loop.stop_reason``.
    safety : dict or None
        Over a port only: the records' bounds and what a breach did
        (:meth:`hapsim.pipeline.record_guard.RecordGuard.to_dict`: ``position_limit``
        [m], ``stop``, ``brake``, ``brake_damping``, ``late_guard``).
    error : dict or None
        ``type`` and ``message`` of the device error that ended the run (the device lost
        beyond recovery, ``stop`` "device lost"), as :class:`RunReport`'s; None when it
        ran to its end.

    Other attributes: ``exit_code``, what ``hapsim run`` exits with (0, or 1 after a
    safety stop or a device lost for good).
    """

    _OPTIONAL = ("port", "late", "watchdog", "delay", "lost", "rows", "counts",
                 "bad_frames", "incomplete", "stop", "safety", "error")

    scene: str
    dof: int
    lockstep: bool
    stable: bool
    predicted: dict
    measured: dict
    deviation: dict | None
    linearisation_bound: dict
    records: int
    samples: int
    order: int
    verdict: str
    within: bool | None
    reason: str
    statements: Any = None
    not_stated: Any = None
    port: dict | None = None
    late: Any = None
    watchdog: Any = None
    delay: Any = None
    lost: Any = None
    rows: Any = None
    counts: Any = None
    bad_frames: Any = None
    incomplete: Any = None
    stop: Any = None
    safety: Any = None
    error: dict | None = None

    @property
    def ok(self) -> bool:
        """Ran to its end, or was stopped by a signal, with no safety stop and no device
        error: what exit code 0 means. A report read back from its JSON (no
        ``exit_code``) is judged by the same rule on what it says (before: always True,
        a device lost included)."""
        code = getattr(self, "exit_code", None)
        if code is not None:
            return code == 0
        return not _nd_failed(self.error, self.safety, self.extra.get("realtime"))

    @property
    def k(self) -> np.ndarray:
        """Measured felt stiffness matrix [N/m], shape (n, n) (NaN without one)."""
        return matrix_or_nan(self.measured.get("felt_stiffness"), self.dof)

    @property
    def b(self) -> np.ndarray:
        """Measured felt damping matrix [N s/m], shape (n, n) (NaN without one)."""
        return matrix_or_nan(self.measured.get("felt_damping"), self.dof)


def run_report_nd(scene, res: dict, lockstep: bool, port_info: dict | None = None
                  ) -> RunReportND:
    """The report of an n-D measurement (what ``hapsim run --json`` prints).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    res : dict
        :func:`hapsim.lockstep.measure_felt_lockstep`'s or
        :func:`hapsim.pipeline.felt_port.measure_felt_port`'s result, with ``bound`` (and
        ``wire``, the readings' and torques' term of a quantised device such as the
        emulated Hapkit pantograph, :func:`hapsim.emulated.pantograph_board.wire_term`).
    lockstep : bool
        Measured in-process.
    port_info : dict, optional
        Over a port: ``port``, ``embedded``, ``mock``.

    Returns
    -------
    RunReportND

    Raises
    ------
    ConfigError
        A scene that is no scene, a result that is no measurement's (its keys named), a
        ``lockstep`` that is no bool, a ``port_info`` that is no mapping (before: an
        AttributeError, a KeyError, or a list taken as True).
    """
    from hapsim.analysis.felt_matrices import felt_directions, felt_verdict
    from hapsim.option_values import check_kind
    scene_given(scene)
    need = ("measured", "predicted", "deviation", "bound", "records", "samples", "order")
    if not isinstance(res, dict) or not set(need) <= set(res):
        raise ConfigError(f"must be a measurement's result with {', '.join(need)}, got "
                          f"{type(res).__name__}", key="res")
    check_kind("lockstep", lockstep, "True or False", required=True)
    check_kind("port_info", port_info, "a mapping of options")
    fit, chk = res["measured"], res["predicted"]
    if port_info is not None:
        from hapsim.pipeline.felt_port import verdict_nd
        v = verdict_nd(res)
    else:
        v = felt_verdict(res["deviation"], res["bound"], res.get("wire"),
                         directions=felt_directions(fit, chk))
    d = {"scene": scene.path, "dof": chk.render.dof, "lockstep": bool(lockstep),
         "stable": bool(chk.stable),
         "predicted": {"felt_stiffness": matrix_list(chk.render.felt_stiffness),
                       "felt_damping": matrix_list(chk.render.felt_damping),
                       "rendered_poles": [[float(z.real), float(z.imag)]
                                          for z in chk.render.rendered_poles]},
         "measured": {"felt_stiffness": matrix_list(fit["felt_stiffness"]),
                      "felt_damping": matrix_list(fit["felt_damping"]),
                      "rendered_poles": [[float(z.real), float(z.imag)]
                                         for z in fit["rendered_poles"]],
                      "residual": fit["residual"], "rank": fit["rank"]},
         "deviation": res["deviation"], "linearisation_bound": res["bound"].to_dict(),
         "records": res["records"], "samples": res["samples"], "order": res["order"],
         "verdict": v["verdict"], "within": v["within"], "reason": v["reason"],
         "statements": v["statements"], "not_stated": v["not_stated"]}
    if port_info is not None:
        d.update(port=port_info, late=res["late"], watchdog=res["watchdog"],
                 delay=res["delay"], lost=res["lost"], rows=res["rows"],
                 counts=res["counts"], bad_frames=res["bad_frames"],
                 incomplete=res["incomplete"], stop=res.get("stop", "end"),
                 safety=res.get("safety"), error=res.get("error"))
    if res.get("wire") is not None:
        d.update(wire=res["wire"], uncertainty=v["uncertainty"])
    failed = _nd_failed(res.get("error"), res.get("safety"))
    return RunReportND.from_dict(d, exit_code=1 if failed else 0)


def _nd_failed(error, safety=None, realtime=None) -> bool:
    """An n-D run's exit rule: it failed (exit 1) after a device lost (``error``) or a
    safety stop (``safety["stop"]``, or a real-time record stopped by ``safety ...``);
    the reports of a run, of a run over several ports and of one read back from JSON
    all apply it.

    Parameters
    ----------
    error : dict or None
    safety : dict or None
    realtime : dict or None
        A run over ports' real-time record (its ``stop``).

    Returns
    -------
    bool
    """
    stop = str((realtime or {}).get("stop") or "")
    return bool(error or (safety or {}).get("stop") or stop.startswith("safety"))


#: What a run of a scene with several ports takes (every other option refused by name).
PORTS_TAKES = ("lockstep", "allow_unstable")


def run_scene_ports(scene, options, amplitude: float | None = None,
                    by: str = "field") -> RunReportND:
    """:func:`hapsim.api.run` of a scene with several ports: the felt matrices across the
    ports measured in lockstep, in-process, each port its own device model
    (:func:`hapsim.lockstep_ports.measure_felt_ports`; ``hapsim run SCENE --lockstep``), or,
    without ``lockstep`` or with a ``port`` or a ``driver``, the FireFader's two faders in
    real time (:func:`hapsim.pipeline.faders_run.run_faders`).

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
    options : hapsim.pipeline.options.RunOptions
        ``lockstep`` and ``allow_unstable`` (in real time:
        :data:`hapsim.pipeline.faders_run.FADERS_TAKES`); any other option set is refused
        by name.
    amplitude : float, optional
        The excitation ``a`` [m] (default
        :data:`hapsim.pipeline.felt_run.DEFAULT_AMPLITUDE`, 1e-8).
    by : {"field", "flag"}
        Name a refused option by its field (the API) or its flag (``hapsim run``).

    Returns
    -------
    RunReportND
        ``dof`` the number of ports; ``ports`` and ``delays`` [periods] beside the
        fields (rows and columns of the matrices in port order). In real time also
        after a safety stop or a board lost in the middle of the run (``realtime.stop``,
        ``error``; ``exit_code`` 1, ``ok`` False).

    Raises
    ------
    ConfigError
        In real time, ports that are not the two faders of one FireFader (several boards,
        other protocols: :func:`hapsim.pipeline.faders_run.faders_refusal`); another
        option set.
    UnstableConfigError
        The coupled loop is unstable and ``allow_unstable`` is false.
    """
    from hapsim.analysis.ports import stable_ports_check
    from hapsim.lockstep_ports import measure_felt_ports
    from hapsim.pipeline.felt_run import DEFAULT_AMPLITUDE, refuse_options
    opts = options.check_values()
    if not opts.lockstep or opts.port or opts.driver is not None:
        # in real time: the FireFader's two faders (refused by name otherwise)
        from hapsim.pipeline.faders_run import run_faders
        res = run_faders(scene, opts, amplitude, by=by)
        v = res["verdict"]
        rep = run_report_nd(scene, res, False).to_dict()
        # the verdict of the records (a stopped run's says why it is not measurable)
        rep.update({k: v[k] for k in ("verdict", "within", "reason", "statements",
                                      "not_stated")})
        # a safety stop or the board lost in the middle: exit 1, as every run's
        failed = _nd_failed(res.get("error"), realtime=res["realtime"])
        return RunReportND.from_dict({**rep, "ports": list(res["predicted"].ports),
                                      "delays": [float(d) for d in res["predicted"].delays],
                                      "realtime": res["realtime"],
                                      "error": res.get("error"),
                                      "amplitude": res["amplitude"],
                                      # said before the run: what it cannot state, or None
                                      "stated_before_run": res.get("stated_before_run")},
                                     exit_code=1 if failed else 0)
    name = (lambda f: "--" + f.replace("_", "-")) if by == "flag" else (lambda f: f)
    refuse_options(opts, by, PORTS_TAKES, "a scene with several ports",
                   f"it takes {', '.join(name(f) for f in PORTS_TAKES + ('amplitude',))}")
    chk = stable_ports_check(scene, opts.allow_unstable, name("allow_unstable"))
    res = measure_felt_ports(scene, DEFAULT_AMPLITUDE if amplitude is None else amplitude)
    return RunReportND.from_dict({**run_report_nd(scene, res, True).to_dict(),
                                  "ports": list(chk.ports),
                                  "delays": [float(d) for d in chk.delays]})


def run_nd(scene, amplitude: float = 1e-8, *, allow_unstable: bool = False
           ) -> RunReportND:
    """Measure a 2-D or 3-D scene's felt matrices in lockstep, in-process
    (``hapsim run SCENE --lockstep``).

    Parameters
    ----------
    scene : hapsim.scene.SceneND or str
        An n-D scene with a port and a device, or its path.
    amplitude : float, optional
        The excitation ``a`` [m] (> 0): the handle displaced by ``a`` along each axis,
        then moving along each.
    allow_unstable : bool, optional
        Run an unstable loop anyway.

    Returns
    -------
    RunReportND

    Raises
    ------
    ConfigError
        An invalid scene or amplitude, a scene without a port.
    UnstableConfigError
        The check finds the loop unstable and ``allow_unstable`` is False.

    Notes
    -----
    2n free responses of the loop (engine, exact ZOH device of the Cartesian mass at rest,
    delay line) minus the response from rest; the felt matrices by vector linear
    prediction and the inverse quadratic eigenvalue problem
    (:func:`hapsim.analysis.pencil.fit_felt_nd`), against :func:`check_nd`'s prediction; the
    first-order linearisation bound at ``a`` (:mod:`hapsim.analysis.linearisation`).
    """
    from hapsim.lockstep import measure_felt_lockstep
    check_values("run_nd", required=True, amplitude=amplitude)
    scene = n_d_scene(scene)
    a = float(amplitude)
    from hapsim.analysis.prediction import require_device
    require_device(scene)      # (the 1-D run's refusal: the same message, file and line)
    stable_prediction_nd(scene, allow_unstable)
    return run_report_nd(scene, measure_felt_lockstep(scene, a), True)


def run_scene_nd(scene, options, amplitude: float | None = None) -> RunReportND:
    """:func:`hapsim.api.run` of a 2-D or 3-D scene: its felt matrices measured in
    lockstep in-process, or over a port (``options.port``, or an embedded n-D mock in real
    time): :func:`hapsim.pipeline.felt_run.measure_scene_nd`.

    Parameters
    ----------
    scene : hapsim.scene.SceneND or str
        A scene with a port and a device, or its path (the embedded mock loads this file).
    options : hapsim.pipeline.options.RunOptions
        ``port``, ``baud``, ``lockstep``, ``allow_unstable``, ``rt_priority``,
        ``rate_hz``, ``faults``, ``fault_seed``, ``frames``, ``reconnect``,
        ``reconnect_time``, ``reconnect_attempts``, ``lost_timeout``, ``stop``,
        ``handle_signals``; any other option set is refused by name.
    amplitude : float, optional
        The excitation ``a`` [m] (default
        :data:`hapsim.pipeline.felt_run.DEFAULT_AMPLITUDE`, 1e-8).

    Returns
    -------
    RunReportND
        Also when a stop was requested (``stop`` names it; "not measurable" unless every
        start was recorded), after a safety stop, and when the device was lost for good
        after its first record (``stop`` "device lost", ``error``; ``exit_code`` 1 for
        either, ``ok`` False).

    Raises
    ------
    ConfigError
        An option not taken (``driver`` included: the 2DIY's and the Falcon's runs are
        ``hapsim run``'s), a bad value, a scene without a port.
    UnstableConfigError
        The check finds the loop unstable and ``allow_unstable`` is false.
    DeviceError, ProtocolError
        The device failed before its first record (no HELLO, a wrong one, a FAULT).
    """
    import os

    from hapsim.pipeline.felt_run import measure_scene_nd, refuse_options, scene_for_run
    from hapsim.pipeline.options import RunOptions
    from hapsim.scene import SceneND
    if not isinstance(scene, (str, os.PathLike)) and not isinstance(scene_given(scene),
                                                                     SceneND):
        # (before: a 1-D scene was an AttributeError deep in the run)
        raise ConfigError("must be a 2-D or 3-D scene (hapsim.run takes any)", key="scene")
    if not isinstance(options, RunOptions):
        raise ConfigError(f"must be a hapsim.pipeline.options.RunOptions, got {options!r}",
                          key="options")
    opts = options.check_values()
    if opts.driver is not None:
        raise ConfigError(f"driver {opts.driver!r} on a 2-D or 3-D scene runs from the "
                          f"command line only (hapsim run SCENE --driver {opts.driver})",
                          key="driver")
    refuse_options(opts, "field")
    a, scene = scene_for_run(scene, amplitude, opts.rate_hz)
    stable_prediction_nd(scene, opts.allow_unstable)
    res, info = measure_scene_nd(scene, opts, a, by="field")
    return run_report_nd(scene, res, bool(opts.lockstep and not opts.port), info)


def stable_prediction_nd(scene, allow_unstable: bool = False,
                         override: str = "allow_unstable"):
    """The scene's check (:func:`hapsim.analysis.scene_check.check_scene_nd`), refused
    when its closed loop is unstable unless ``allow_unstable`` (every n-D run: the API's,
    ``hapsim run``'s and the Falcon's).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A scene with a port and a device.
    allow_unstable : bool, optional
        Return the check of an unstable loop instead of refusing it.
    override : str, optional
        How the caller's user says ``allow_unstable`` (named in the refusal).

    Returns
    -------
    hapsim.analysis.scene_check.SceneCheckND

    Raises
    ------
    UnstableConfigError
        The closed loop's spectral radius is 1 or more and ``allow_unstable`` is false.
    """
    from hapsim.analysis.scene_check import check_scene_nd
    from hapsim.errors import UnstableConfigError
    pred = check_scene_nd(scene)
    if not pred.stable and not allow_unstable:
        raise UnstableConfigError(
            f"{scene.path}: the closed loop is unstable (spectral radius "
            f"{pred.render.spectral_radius:.9f}); hapsim check for the felt matrices, "
            f"{override} to run it anyway")
    return pred
