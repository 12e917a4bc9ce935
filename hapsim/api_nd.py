"""The 2-D and 3-D API: read an n-D scene, its felt matrices and modes, a lockstep run.

The same style as :mod:`hapsim.api` (typed results whose fields are the command's
``--json`` keys, :class:`hapsim.results.Report`), for scenes with ``dimension: 2`` or ``3``
(docs/dimensions.md). :mod:`hapsim.api` provides these names too, loading this module on
first use.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any

import numpy as np

from hapsim.errors import ConfigError
from hapsim.option_values import check_values
from hapsim.results import Report

__all__ = ["load_scene_nd", "check_nd", "modes_nd", "run_nd", "run_report_nd", "stable_prediction_nd",
           "CheckReportND", "ModesReportND", "RunReportND", "PlayReportND"]

def load_scene_nd(path: str | os.PathLike):
    """Read and validate a 2-D or 3-D scene file (docs/dimensions.md).

    Parameters
    ----------
    path : str or path-like
        A YAML scene with ``dimension: 2`` or ``3``.

    Returns
    -------
    hapsim.scene_nd.SceneND

    Raises
    ------
    ConfigError
        An unreadable or invalid file (file, line and key named), or a 1-D scene (read
        it with :func:`load_scene`).
    """
    from hapsim.scene_nd import load_scene_nd as _load
    return _load(os.fspath(path))


def _scene_nd(scene):
    """A SceneND from a SceneND or a path."""
    if isinstance(scene, (str, os.PathLike)):
        return load_scene_nd(scene)
    return scene


def _mat(x):
    return None if x is None else np.asarray(x, float).tolist()


@dataclasses.dataclass(frozen=True)
class CheckReportND(Report):
    """What ``hapsim check SCENE --json`` says of a 2-D or 3-D scene felt through its
    device: the MIMO closed loop's stability and the felt matrices.

    Attributes
    ----------
    dof : int
        n, the scene's dimension.
    stable : bool
        Spectral radius within 1e-9 of 1 or below (the MIMO characteristic).
    verdict : {"stable", "unstable"}
    spectral_radius : float
    felt_stiffness, felt_damping : list of list of float or None
        The n x n felt matrices k [N/m], b [N s/m] (None with fewer than n rendered
        pairs; ``note`` says why).
    principal_directions : list of list of float or None
        Unit vectors (columns), least damped first.
    direction_stiffness, direction_damping, direction_mass : list of float or None
        The felt pair and the modal mass [kg] along each.
    port_stiffness, port_damping : list of list of float
        The port's links linearised at rest [N/m], [N s/m].
    states : int
    rendered_poles : list of [float, float]
        The n rendered discrete poles z (real, imaginary).
    stiffness_limits : list of dict or None
        ``direction``, ``K_max`` [N/m] along the device's principal mass axes (when every
        port link ends on a ground).
    note : str or None
    scene : str
    device : dict
        ``kind``, ``mass`` [kg], ``friction`` [N s/m], ``position`` [m], ``delay``,
        ``hold``.

    Other attribute (not in ``--json``): ``analysis``, the
    :class:`~hapsim.analysis.scene_nd_check.SceneCheckND`; ``scene_nd``, the scene.
    """

    dof: int
    stable: bool
    verdict: str
    spectral_radius: float
    felt_stiffness: list | None
    felt_damping: list | None
    principal_directions: list | None
    direction_stiffness: list | None
    direction_damping: list | None
    direction_mass: list | None
    port_stiffness: list
    port_damping: list
    states: int
    rendered_poles: list
    stiffness_limits: list | None
    note: str | None
    scene: str
    device: dict

    @property
    def k(self) -> np.ndarray:
        """Felt stiffness matrix k [N/m], shape (n, n) (NaN without one)."""
        return _matrix_or_nan(self.felt_stiffness, self.dof)

    @property
    def b(self) -> np.ndarray:
        """Felt damping matrix b [N s/m], shape (n, n) (NaN without one)."""
        return _matrix_or_nan(self.felt_damping, self.dof)

    def plot(self, path=None, title: str | None = None):
        """The scene over its device's workspace with the felt stiffness ellipses
        (:func:`hapsim.plots.workspace.plot_scene_nd`; for a pantograph or a delta also the
        ellipses felt at other configurations, :func:`felt_over_workspace`).

        Parameters
        ----------
        path : str or path-like, optional
            A figure file to write (its extension picks the format); None: only return it.
        title : str, optional
            Default: the scene's file name, device, rate and delay.

        Returns
        -------
        matplotlib.figure.Figure

        Raises
        ------
        ConfigError
            matplotlib missing, or a path that cannot be written (key ``plot``).
        """
        from hapsim.analysis.scene_nd_check import felt_over_workspace
        from hapsim.plots import save_figure
        from hapsim.plots.workspace import plot_scene_nd
        scene = self.scene_nd
        felt = felt_over_workspace(scene) if scene.device.joints is not None else None
        if title is None:
            note = "\nfelt at the handle only (a port link ends on a moving mass)" \
                if felt is not None and felt.note else ""
            title = (f"{os.path.basename(scene.path)}: {scene.device.kind}, "
                     f"{scene.rate_hz:g} Hz, delay {scene.device.delay}" + note)
        fig = plot_scene_nd(scene, self.analysis, felt, title=title)
        if path is not None:
            save_figure(fig, os.fspath(path))
        return fig


def _matrix_or_nan(m, n: int) -> np.ndarray:
    return np.full((n, n), math.nan) if m is None else np.array(m, float)


def check_nd(scene, progress=None) -> CheckReportND:
    """Check a 2-D or 3-D scene felt through its device: the MIMO loop and the felt
    matrices.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND or str
        A loaded n-D scene with a port and a device, or the path of one.
    progress : callable, optional
        ``progress(done, total)`` after each direction's stiffness limit
        (:func:`hapsim.analysis.scene_nd_check.check_scene_nd`).

    Returns
    -------
    CheckReportND

    Raises
    ------
    ConfigError
        An invalid scene, one without a port (its modes: :func:`modes_nd`), or one too
        large to analyse.

    Notes
    -----
    The eigenvalues of the closed loop's state matrix (the device's exact ZOH, the delay
    line, the virtual masses, the links linearised at rest); the felt matrices solve the
    inverse quadratic eigenvalue problem on the n rendered pairs (Lancaster 2007;
    :mod:`hapsim.analysis.scene_nd_check`, docs/dimensions.md).
    """
    from hapsim.analysis.scene_nd_check import check_scene_nd
    scene = _scene_nd(scene)
    if scene.port is None:
        raise ConfigError("an n-D scene is felt through its device: it needs a mass of "
                          "kind 'port' and a device section (a scene without one: "
                          "hapsim.modes_nd)", file=scene.path, key="masses")
    chk = check_scene_nd(scene, progress=progress)
    dev = scene.device
    d = {**chk.to_dict(), "scene": scene.path,
         "device": {"kind": dev.kind, "mass": dev.mass.tolist(),
                    "friction": dev.friction.tolist(), "position": dev.position.tolist(),
                    "delay": dev.delay, "hold": dev.hold}}
    return CheckReportND.from_dict(d, analysis=chk, scene_nd=scene)


@dataclasses.dataclass(frozen=True)
class ModesReportND(Report):
    """What ``hapsim check SCENE --json`` says of a 2-D or 3-D scene without a port: the
    modes of its centred scheme linearised at rest (:mod:`hapsim.analysis.modes_nd`).

    Attributes
    ----------
    scene : str
    dof : int
        n, the scene's dimension.
    masses : int
        Moving masses.
    states : int
        Size of the one-step map.
    stable : bool
        Spectral radius within 1e-9 of 1 or below.
    verdict : {"stable", "unstable"}
        The same, as every ``check --json`` says it (1-D, n-D, with or without a port).
    spectral_radius : float
    modes : list of dict
        ``frequency_hz`` [Hz], ``damping_ratio`` [-], ``axis`` (0..n-1: the one its shape
        moves most along), lowest frequency first.

    Other attribute (not in ``--json``): ``analysis``, the
    :class:`~hapsim.analysis.modes_nd.SceneModesND` (with the mode shapes).
    """

    scene: str
    dof: int
    masses: int
    states: int
    stable: bool
    verdict: str
    spectral_radius: float
    modes: list

    @property
    def frequencies(self) -> np.ndarray:
        """Every mode's eigenfrequency [Hz], lowest first."""
        return np.array([m["frequency_hz"] for m in self.modes], float)

    def plot(self, path=None, title: str | None = None, count: int = 6):
        """The lowest modes along the last axis over the rest positions
        (:func:`hapsim.plots.workspace.plot_modes_nd`).

        Parameters
        ----------
        path : str or path-like, optional
            A figure file to write; None: only return it.
        title : str, optional
        count : int, optional
            Panels (distinct eigenfrequencies).

        Returns
        -------
        matplotlib.figure.Figure

        Raises
        ------
        ConfigError
            matplotlib missing, or a path that cannot be written (key ``plot``).
        """
        from hapsim.plots import save_figure
        from hapsim.plots.workspace import plot_modes_nd
        scene = self.scene_nd
        if title is None:
            title = f"{os.path.basename(scene.path)}: modes at {scene.rate_hz:g} Hz"
        fig = plot_modes_nd(scene, self.analysis, title=title, count=count)
        if path is not None:
            save_figure(fig, os.fspath(path))
        return fig


def modes_nd(scene) -> ModesReportND:
    """The modes of a 2-D or 3-D scene on its own (grounds and a port held still).

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND or str

    Returns
    -------
    ModesReportND

    Raises
    ------
    ConfigError
        An invalid scene, no moving mass, or too many states.

    Notes
    -----
    The eigenvalues ``z`` of the centred scheme's one-step map: frequency
    ``arg(z) / (2 pi T)``, damping ratio ``-Re(s)/|s|`` with ``s = ln(z) / T``
    (:mod:`hapsim.analysis.modes_nd`; a square membrane's closed form is in its tests).
    """
    from hapsim.analysis.modes_nd import scene_modes_nd
    scene = _scene_nd(scene)
    res = scene_modes_nd(scene)
    d = {"scene": scene.path, "dof": scene.dimension, "masses": len(res.names),
         "states": res.states, "stable": res.stable,
         "verdict": "stable" if res.stable else "unstable",
         "spectral_radius": res.spectral_radius,
         "modes": [md.to_dict() for md in res.modes]}
    return ModesReportND.from_dict(d, analysis=res, scene_nd=scene)


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
        :meth:`hapsim.analysis.linearisation_nd.LinearisationBound.to_dict`.
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
        records met (:func:`hapsim.pipeline.run_nd.measure_felt_port`: STATEs missed,
        duplicates, reordered, records cut short, device resets, losses and recoveries,
        CONFIGs sent); bad frames the host's decoder dropped; why nothing was fitted
        (None when the matrices were measured).
    stop : str or None
        Over a port only: what ended the measurement, ``"end"`` or, when a stop was
        requested, ``"signal SIGINT"`` / ``"signal SIGTERM"`` (Ctrl-C, a service manager):
        what was recorded by then is reported, as the 1-D run's ``loop.stop_reason``.
    """

    _OPTIONAL = ("port", "late", "watchdog", "delay", "lost", "rows", "counts",
                 "bad_frames", "incomplete", "stop")

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

    @property
    def k(self) -> np.ndarray:
        """Measured felt stiffness matrix [N/m], shape (n, n) (NaN without one)."""
        return _matrix_or_nan(self.measured.get("felt_stiffness"), self.dof)

    @property
    def b(self) -> np.ndarray:
        """Measured felt damping matrix [N s/m], shape (n, n) (NaN without one)."""
        return _matrix_or_nan(self.measured.get("felt_damping"), self.dof)


def run_report_nd(scene, res: dict, lockstep: bool, port_info: dict | None = None
                  ) -> RunReportND:
    """The report of an n-D measurement (what ``hapsim run --json`` prints).

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
    res : dict
        :func:`hapsim.lockstep_nd.measure_felt_lockstep`'s or
        :func:`hapsim.pipeline.run_nd.measure_felt_port`'s result, with ``bound`` (and
        ``wire``, the readings' and torques' term of a quantised device such as the
        emulated Hapkit pantograph, :func:`hapsim.emulated.pantograph_board.wire_term`).
    lockstep : bool
        Measured in-process.
    port_info : dict, optional
        Over a port: ``port``, ``embedded``, ``mock``.

    Returns
    -------
    RunReportND
    """
    from hapsim.analysis.felt_matrices import felt_directions, felt_verdict
    fit, chk = res["measured"], res["predicted"]
    if port_info is not None:
        from hapsim.pipeline.run_nd import verdict_nd
        v = verdict_nd(res)
    else:
        v = felt_verdict(res["deviation"], res["bound"], res.get("wire"),
                         directions=felt_directions(fit, chk))
    d = {"scene": scene.path, "dof": scene.dimension, "lockstep": bool(lockstep),
         "stable": bool(chk.stable),
         "predicted": {"felt_stiffness": _mat(chk.render.felt_stiffness),
                       "felt_damping": _mat(chk.render.felt_damping),
                       "rendered_poles": [[float(z.real), float(z.imag)]
                                          for z in chk.render.rendered_poles]},
         "measured": {"felt_stiffness": _mat(fit["felt_stiffness"]),
                      "felt_damping": _mat(fit["felt_damping"]),
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
                 incomplete=res["incomplete"], stop=res.get("stop", "end"))
    if res.get("wire") is not None:
        d.update(wire=res["wire"], uncertainty=v["uncertainty"])
    return RunReportND.from_dict(d)


def run_nd(scene, amplitude: float = 1e-8, *, allow_unstable: bool = False
           ) -> RunReportND:
    """Measure a 2-D or 3-D scene's felt matrices in lockstep, in-process
    (``hapsim run SCENE --lockstep``).

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND or str
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
    (:mod:`hapsim.analysis.identify_nd`), against :func:`check_nd`'s prediction; the
    first-order linearisation bound at ``a`` (:mod:`hapsim.analysis.linearisation_nd`).
    """
    from hapsim.lockstep_nd import measure_felt_lockstep
    check_values("run_nd", amplitude=amplitude)
    scene = _scene_nd(scene)
    a = float(amplitude)
    if scene.port is None:
        raise ConfigError("a run needs a mass of kind 'port' and a device section",
                          file=scene.path, key="masses")
    stable_prediction_nd(scene, allow_unstable)
    return run_report_nd(scene, measure_felt_lockstep(scene, a), True)


@dataclasses.dataclass(frozen=True)
class PlayReportND(Report):
    """What ``hapsim play SCENE --json`` says of a 2-D or 3-D scene (:func:`hapsim.api.play`
    returns it for such a scene): its sound played live, its loop closed on the device's
    model, the changes taken.

    Attributes
    ----------
    scene : str
    dof : int
        The scene's dimension.
    rate_hz : float
    frames : int
        Frames (samples) played.
    seconds : float
        ``frames / rate_hz`` [s].
    wall_s : float
        Wall-clock time of the play [s].
    stop_reason : str
        ``"duration"``, ``"signal SIGINT"``, ``"view: stop button"``, ...
    scheduling : str
    note : str or None
        Why the loop was not checked before playing (a scene too large to analyse).
    loop : str
        ``"closed"`` (a port and a device) or ``"free"``.
    delay : int or None
        The device's delay [samples] of a closed loop.
    plucks : dict or None
        ``every_samples``, ``samples`` (the hand's profile) and ``direction``.
    sound : dict
        Backend, callback, block, channels, xruns, underruns, frames ahead, ...
    accepted, refused, felt, links, masses, journal
        With a checked loop only: live changes accepted and refused, the prediction now
        (``spectral_radius``, ``stable``, the felt matrices), each link's and plane's
        (K, B), each mass's mass [kg], the changes' journal.

    Other attributes: ``exit_code`` (0).
    """

    _OPTIONAL = ("accepted", "refused", "felt", "links", "masses", "journal")

    scene: str
    dof: int
    rate_hz: float
    frames: int
    seconds: float
    wall_s: float
    stop_reason: str
    scheduling: str
    note: str | None
    loop: str
    delay: int | None
    plucks: dict | None
    sound: dict
    accepted: int | None = None
    refused: int | None = None
    felt: dict | None = None
    links: dict | None = None
    masses: dict | None = None
    journal: list | None = None

    def text(self) -> str:
        """The human report ``hapsim play`` prints
        (:func:`hapsim.pipeline.play_nd.play_nd_text`).

        Returns
        -------
        str
            Two or three lines, no trailing newline.
        """
        from hapsim.pipeline.play_nd import play_nd_text
        return play_nd_text(self.to_dict())


def run_scene_nd(scene, options, amplitude: float | None = None) -> RunReportND:
    """:func:`hapsim.api.run` of a 2-D or 3-D scene: its felt matrices measured in
    lockstep in-process, or over a port (``options.port``, or an embedded n-D mock in real
    time): :func:`hapsim.pipeline.felt_run.measure_scene_nd`.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND or str
        A scene with a port and a device, or its path (the embedded mock loads this file).
    options : hapsim.pipeline.options.RunOptions
        ``port``, ``baud``, ``lockstep``, ``allow_unstable``, ``rt_priority``,
        ``rate_hz``, ``faults``, ``fault_seed``, ``stop``, ``handle_signals``; any other
        option set is refused by name.
    amplitude : float, optional
        The excitation ``a`` [m] (default
        :data:`hapsim.pipeline.felt_run.DEFAULT_AMPLITUDE`, 1e-8).

    Returns
    -------
    RunReportND
        Also when a stop was requested (``stop`` names it; "not measurable" unless every
        start was recorded).

    Raises
    ------
    ConfigError
        An option not taken (``driver`` included: the 2DIY's and the Falcon's runs are
        ``hapsim run``'s), a bad value, a scene without a port.
    UnstableConfigError
        The check finds the loop unstable and ``allow_unstable`` is false.
    DeviceError, ProtocolError
        The device failed (no HELLO, a FAULT, lost beyond recovery).
    """
    from hapsim.pipeline.felt_run import measure_scene_nd, refuse_options, scene_for_run
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
    """The scene's check (:func:`hapsim.analysis.scene_nd_check.check_scene_nd`), refused
    when its closed loop is unstable unless ``allow_unstable`` (every n-D run: the API's,
    ``hapsim run``'s and the Falcon's).

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A scene with a port and a device.
    allow_unstable : bool, optional
        Return the check of an unstable loop instead of refusing it.
    override : str, optional
        How the caller's user says ``allow_unstable`` (named in the refusal).

    Returns
    -------
    hapsim.analysis.scene_nd_check.SceneCheckND

    Raises
    ------
    UnstableConfigError
        The closed loop's spectral radius is 1 or more and ``allow_unstable`` is false.
    """
    from hapsim.analysis.scene_nd_check import check_scene_nd
    from hapsim.errors import UnstableConfigError
    pred = check_scene_nd(scene)
    if not pred.stable and not allow_unstable:
        raise UnstableConfigError(
            f"{scene.path}: the closed loop is unstable (spectral radius "
            f"{pred.render.spectral_radius:.9f}); hapsim check for the felt matrices, "
            f"{override} to run it anyway")
    return pred
