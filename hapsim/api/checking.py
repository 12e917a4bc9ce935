"""``check``: a scene's closed loop and what is felt at its port, in any dimension
(a 1-D scene's felt pair, a 2-D or 3-D scene's felt matrices, or its modes without a
port)."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from hapsim.errors import ConfigError
from hapsim.api.common import (Charted, draw_report, figure, load_scene, matrix_or_nan,
                               n_d_scene)
from hapsim.results import Report


# ---------------------------------------------------------------------------- check
@dataclasses.dataclass(frozen=True)
class CheckReport(Charted, Report):
    """What ``hapsim check SCENE --json`` says: stability and the (k, b) felt at the port.

    Attributes
    ----------
    scene : str
        The scene's path.
    verdict : {"stable", "unstable"}
    rate_hz : float
        Device rate [Hz].
    device : dict or None
        ``mass`` [kg], ``friction`` [N s/m], ``delay`` [samples], ``hold``, ``correction``.
    calibrations : list of dict
        The (K, B) calibrated for each ``target`` link.
    stable, marginal : bool
        Spectral radius < 1 (marginal: within 1e-9 of 1, counted stable).
    spectral_radius : float
        Of the closed-loop state matrix.
    has_port : bool
    period : float
        T [s].
    reference_mass : float
        m [kg] the felt k, b are expressed with.
    integrator : str
    rendered : dict or None
        The felt mode: ``k`` [N/m], ``b`` [N s/m], ``f0_hz``, ``damping_ratio``, ``z_re``,
        ``z_im``, ``kind``, ``participation``.
    modes : list of dict
        Every mode, least damped first (same keys).
    eigenvalues : list of [float, float]
        Closed-loop eigenvalues z (real, imaginary).
    state_names : list of str
    calibrated : dict
        ``{link: [K, B]}``.
    static_k : float or None
        Stiffness a slow push feels at the port [N/m] (virtual masses at rest;
        :func:`hapsim.analysis.virtual_network.static_stiffness`).
    board : dict or None
        The timing of the board the scene's ``device.protocol`` names, where it is not the
        scene's own (:func:`board_timing`): ``protocol``, ``rate_hz`` (the rate the board
        runs [Hz]), ``render_latency_s`` (the bounds [s] of its render after its read),
        ``delay_modelled`` [periods] (the scene's delay and the bounds' middle, the delay
        the loop above is analysed with), ``k_spread`` [N/m] and ``b_spread`` [N s/m] (how
        far the felt pair moves over the bounds); ``unstable_latency_s`` [s] and
        ``unstable_spectral_radius`` where the loop is stable at the middle but not at
        that latency of the bounds (then ``stable`` is False and ``verdict``
        "unstable": the board may render that late); ``late_reading_unstable``
        (``periods``, ``delay`` [periods], ``spectral_radius``) where the loop is stable
        at the board's timing but not with its reading taken that many periods late, as a
        host waking a little late may take it (:func:`hapsim.pipeline.render_latency.
        late_reading`; then too ``stable`` is False), beside ``late_reading_periods`` (the
        driver's, where it has some); ``missing_reply_unstable`` (``growth_per_tick``,
        ``pattern``) and ``missing_reply_warning`` where replies that go missing now and
        then, stepped with the host's estimates, grow a loop stable on time (a warning, as
        ``hapsim run`` gives it: :func:`hapsim.pipeline.render_latency.
        missing_reply_warning`; ``stable`` unchanged); ``rate_written_hz`` where the
        board's rate is not the file's, ``refused`` where ``hapsim run`` refuses the
        rate. None: the board runs the scene as it is written (the framed protocol, or a
        driver with no timing of its own).

    Other attributes (not in ``--json``): ``analysis`` (the
    :class:`~hapsim.analysis.scene_check.SceneCheck`), ``calibrated_scene`` (the scene
    with its targets calibrated), ``calibrations_made`` (their calibration results).
    """

    scene: str
    verdict: str
    rate_hz: float
    device: dict | None
    calibrations: list
    stable: bool
    marginal: bool
    spectral_radius: float
    has_port: bool
    period: float
    reference_mass: float
    integrator: str
    rendered: dict | None
    modes: list
    eigenvalues: list
    state_names: list
    calibrated: dict
    static_k: float | None
    board: dict | None = None

    @property
    def k(self) -> float:
        """Felt stiffness k [N/m] (NaN when nothing rings at the port)."""
        return figure(self.rendered, "k")

    @property
    def b(self) -> float:
        """Felt damping b [N s/m] (NaN when nothing rings at the port)."""
        return figure(self.rendered, "b")


def check(scene, progress=None):
    """Check a scene: stability of its closed loop and what is felt at its port.

    A scene of any dimension: a 2-D or 3-D one with a port gives its felt matrices
    (:func:`hapsim.api.check_nd`, a :class:`CheckReportND`), one without a port its
    modes (:func:`hapsim.api.modes_nd`, a :class:`ModesReportND`), as ``hapsim check``
    does.

    Parameters
    ----------
    scene : hapsim.scene.Scene, hapsim.scene.SceneND or str
        A loaded scene, or the path of one.
    progress : callable, optional
        A 2-D or 3-D scene with a port: ``progress(done, total)`` after each direction's
        stiffness limit (:func:`check_nd`); unused otherwise.

    Returns
    -------
    CheckReport, CheckReportND, ModesReportND or hapsim.analysis.ports.PortsCheck
        The last for a scene with several ports (its ``to_dict`` is ``hapsim check
        --json``'s, without the devices).

    Raises
    ------
    ConfigError
        An invalid scene, or one too large to analyse.
    UnrenderableTargetError
        A ``target`` link the device cannot render (a negative verdict).

    Notes
    -----
    The eigenvalues of the closed-loop state matrix of the temporary hybrid system
    (Florens, Voda & Urma; docs/design.md, 'The THS'); the felt (k, b) are those of the
    least damped pole pair seen at the port, ``k = m |s|^2``, ``b = -2 m Re(s)``.
    """
    from hapsim.analysis.network import check_size
    from hapsim.analysis.virtual_network import static_stiffness
    from hapsim.analysis.scene_check import check_scene
    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)               # in the dimension it declares
    from hapsim.scene import ScenePorts
    if isinstance(scene, ScenePorts):           # several ports: the felt matrices across
        from hapsim.analysis.ports import check_ports
        return check_ports(scene)
    if getattr(scene, "dimension", 1) != 1:
        return check_nd(scene, progress) if scene.port is not None else modes_nd(scene)
    scene, cals, model, board = board_loop(scene)
    check_size(scene)
    chk = check_scene(model)
    dev = scene.device
    # stable at the latency's middle but not over the board's whole range, or not with
    # a reading taken late: unstable
    stable = (chk.stable and (board or {}).get("unstable_latency_s") is None
              and (board or {}).get("late_reading_unstable") is None)
    d = {"scene": scene.path, "verdict": "stable" if stable else "unstable",
         "rate_hz": scene.rate_hz, "board": board,
         "device": None if dev is None else {
             "mass": dev.mass, "friction": dev.friction, "delay": dev.delay,
             "hold": dev.hold, "correction": getattr(dev, "correction", None)},
         "calibrations": [c.to_dict() for c in cals], **chk.to_dict(),
         "static_k": static_stiffness(scene) if chk.has_port else None}
    d["stable"] = stable
    return CheckReport.from_dict(d, analysis=chk, calibrated_scene=scene, calibrations_made=cals)


def at_board_rate(scene) -> tuple:
    """A 1-D scene at the rate the board its ``device.protocol`` names runs (a board on
    its own tick: whole ticks, :meth:`hapsim.drivers.base.Driver.board_rate_hz`), and
    that board's driver (:func:`hapsim.drivers.device_driver`; None on hapsim's framed
    protocol, the scene then as it is).

    Parameters
    ----------
    scene : hapsim.scene.Scene

    Returns
    -------
    tuple
        ``(scene, driver)``.

    Raises
    ------
    ConfigError
        Driver options the driver refuses.
    """
    from hapsim.drivers import device_driver
    drv = device_driver(scene.device)
    if drv is not None:
        rate = drv.board_rate_hz(scene.rate_hz)
        if rate != scene.rate_hz:
            scene = scene.with_rate(rate)
    return scene, drv


def board_scene(scene) -> tuple:
    """A 1-D scene at the rate the board its ``device.protocol`` names runs (whole ticks:
    :meth:`hapsim.drivers.base.Driver.board_rate_hz`), its targets calibrated for the loop
    with the board's render latency after its read in the delay (the bounds' middle), as
    ``hapsim run`` calibrates them (:func:`hapsim.pipeline.runner.prepare_run`); the
    scene's own device (delay as written) kept. ``check``, ``stability --scene`` and
    ``simulate`` take the targets so.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A loaded 1-D scene.

    Returns
    -------
    tuple
        ``(scene, calibrations, driver, written_hz)``: the scene, the
        :class:`~hapsim.analysis.targets.TargetCalibration` list, the board's driver
        (:func:`hapsim.drivers.device_driver`, None on hapsim's framed protocol) and the
        rate the file states [Hz].

    Raises
    ------
    ConfigError
        Driver options the driver refuses.
    UnrenderableTargetError
        A target the device cannot render in that loop.
    """
    from hapsim.analysis.prediction import timed_scene
    from hapsim.analysis.targets import apply_targets
    from hapsim.pipeline.render_latency import latency_middle
    written_hz = scene.rate_hz
    scene, drv = at_board_rate(scene)
    lat = latency_middle(scene, drv) if scene.port is not None else 0.0
    if lat:
        # the targets calibrated for the loop the board runs, as hapsim run's
        # (hapsim.analysis.prediction.prepare_scene); the scene keeps its own delay
        timed, cals = apply_targets(timed_scene(scene, lat))
        scene = dataclasses.replace(timed, device=scene.device)
    else:
        scene, cals = apply_targets(scene)
    return scene, cals, drv, written_hz


def board_loop(scene) -> tuple:
    """A 1-D scene as the board its ``device.protocol`` names runs it
    (:func:`board_scene`), and the loop analysed: ``check`` and ``stability --scene``
    analyse this loop, as ``hapsim run`` states its prediction.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A loaded 1-D scene.

    Returns
    -------
    tuple
        ``(scene, calibrations, model, board)``: :func:`board_scene`'s scene and
        calibrations, the scene the loop is analysed with (``scene`` with the latency in
        its delay, or ``scene`` itself) and :attr:`CheckReport.board` (None on hapsim's
        framed protocol or where the board runs the scene as written).

    Raises
    ------
    ConfigError, UnrenderableTargetError
        As :func:`board_scene`; a scene too large to analyse.
    """
    from hapsim.analysis.network import check_size
    scene, cals, drv, written_hz = board_scene(scene)
    if drv is not None:
        check_size(scene)       # too large: refused before the board's loops are analysed
    model, board = board_timing(scene, drv, written_hz)
    return scene, cals, model, board


def board_timing(scene, driver, written_hz=None):
    """The scene analysed as its board runs it: the loop's delay is the scene's whole
    periods and the board's render latency after its read, as ``hapsim run`` predicts it.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A calibrated 1-D scene, at the board's own rate (``driver.board_rate_hz``).
    driver : hapsim.drivers.base.Driver or None
        :func:`hapsim.drivers.device_driver`'s.
    written_hz : float, optional
        The rate the scene file states [Hz], where the board runs another (whole ticks).

    Returns
    -------
    tuple
        ``(model, board)``: the scene the loop is analysed with (``scene`` itself without
        a latency: :func:`hapsim.pipeline.render_latency.timed_prediction`) and the
        :attr:`CheckReport.board` dict (None where the board runs the scene as written);
        with ``rate_written_hz`` where the board's rate is not the file's, and
        ``refused``, the reason the driver refuses the rate (``hapsim run`` stops there),
        where it does.

    Notes
    -----
    The delay is real-valued, modelled exactly (modified z-transform: Jury, *Theory and
    Application of the z-Transform Method*, 1964; :mod:`hapsim.analysis.subsample`), at the
    middle of the driver's bounds, as the run states its prediction before it runs
    (:func:`hapsim.pipeline.render_latency.timed_prediction`).
    """
    if driver is None or scene.device is None or scene.port is None:
        return scene, None
    from hapsim.pipeline.render_latency import timed_prediction
    model, pred = timed_prediction(scene, driver)
    board = {"protocol": scene.device.protocol, "rate_hz": scene.rate_hz}
    moved = written_hz is not None and written_hz != scene.rate_hz
    if moved:
        board["rate_written_hz"] = float(written_hz)
    try:
        driver.check_rate(scene.rate_hz)
    except ConfigError as e:
        board["refused"] = str(e)
    late = int(getattr(driver, "late_reading_periods", 0) or 0)
    from hapsim.pipeline.render_latency import missing_reply_warning
    missing = missing_reply_warning(model, driver, pred)
    if model is scene and "refused" not in board and not moved and not late and not missing:
        return scene, None
    if missing:
        board["missing_reply_unstable"] = pred["missing_reply_unstable"]
        board["missing_reply_warning"] = missing
    for key in ("render_latency_s", "delay_modelled", "k_spread", "b_spread",
                "unstable_latency_s", "unstable_spectral_radius", "late_reading_unstable"):
        if key in pred:
            board[key] = pred[key]
    if late:
        board["late_reading_periods"] = late
    return model, board


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
    not_at_rest : dict or None
        None when the scene is at rest at the positions it names; else the net force,
        the linearised balance's distance and a sentence
        (:func:`hapsim.analysis.static_balance.not_at_rest`).

    Other attribute (not in ``--json``): ``analysis``, the
    :class:`~hapsim.analysis.scene_check.SceneCheckND`; ``scene_nd``, the scene.
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
    not_at_rest: dict | None = None

    @property
    def k(self) -> np.ndarray:
        """Felt stiffness matrix k [N/m], shape (n, n) (NaN without one)."""
        return matrix_or_nan(self.felt_stiffness, self.dof)

    @property
    def b(self) -> np.ndarray:
        """Felt damping matrix b [N s/m], shape (n, n) (NaN without one)."""
        return matrix_or_nan(self.felt_damping, self.dof)

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
        from hapsim.analysis.scene_check import felt_over_workspace
        from hapsim.plots.workspace import plot_scene_nd
        scene = self.scene_nd
        felt = felt_over_workspace(scene) if scene.device.joints is not None else None
        if title is None:
            note = "\nfelt at the handle only (a port link ends on a moving mass)" \
                if felt is not None and felt.note else ""
            title = (f"{os.path.basename(scene.path)}: {scene.device.kind}, "
                     f"{scene.rate_hz:g} Hz, delay {scene.device.delay}" + note)
        return draw_report(self, lambda rep, ax=None: plot_scene_nd(
            scene, self.analysis, felt, title=title), path, axes=False)


def check_nd(scene, progress=None) -> CheckReportND:
    """Check a 2-D or 3-D scene felt through its device: the MIMO loop and the felt
    matrices.

    Parameters
    ----------
    scene : hapsim.scene.SceneND or str
        A loaded n-D scene with a port and a device, or the path of one.
    progress : callable, optional
        ``progress(done, total)`` after each direction's stiffness limit
        (:func:`hapsim.analysis.scene_check.check_scene_nd`).

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
    :mod:`hapsim.analysis.scene_check`, docs/dimensions.md).
    """
    from hapsim.analysis.scene_check import check_scene_nd
    scene = n_d_scene(scene)
    if scene.port is None:
        raise ConfigError("an n-D scene is felt through its device: it needs a mass of "
                          "kind 'port' and a device section (a scene without one: "
                          "hapsim.modes_nd)", file=scene.path, key="masses")
    if progress is not None and not callable(progress):
        raise ConfigError(f"must be a function progress(done, total), got {progress!r}",
                          key="progress")
    chk = check_scene_nd(scene, progress=progress)
    from hapsim.analysis.static_balance import not_at_rest
    dev = scene.device
    d = {**chk.to_dict(), "scene": scene.path, "not_at_rest": not_at_rest(scene),
         "device": {"kind": dev.kind, "mass": dev.mass.tolist(),
                    "friction": dev.friction.tolist(), "position": dev.position.tolist(),
                    "delay": dev.delay, "hold": dev.hold}}
    return CheckReportND.from_dict(d, analysis=chk, scene_nd=scene)


@dataclasses.dataclass(frozen=True)
class ModesReportND(Report):
    """What ``hapsim check SCENE --json`` says of a 2-D or 3-D scene without a port: the
    modes of its centred scheme linearised at rest (:mod:`hapsim.analysis.modes`).

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
    :class:`~hapsim.analysis.modes.SceneModesND` (with the mode shapes).
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
        from hapsim.plots.workspace import plot_modes_nd
        scene = self.scene_nd
        if title is None:
            title = f"{os.path.basename(scene.path)}: modes at {scene.rate_hz:g} Hz"
        return draw_report(self, lambda rep, ax=None: plot_modes_nd(
            scene, self.analysis, title=title, count=count), path, axes=False)


def modes_nd(scene) -> ModesReportND:
    """The modes of a 2-D or 3-D scene on its own (grounds and a port held still).

    Parameters
    ----------
    scene : hapsim.scene.SceneND or str

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
    (:mod:`hapsim.analysis.modes`; a square membrane's closed form is in its tests).
    """
    from hapsim.analysis.modes import scene_modes_nd
    scene = n_d_scene(scene)
    res = scene_modes_nd(scene)
    d = {"scene": scene.path, "dof": scene.dimension, "masses": len(res.names),
         "states": res.states, "stable": res.stable,
         "verdict": "stable" if res.stable else "unstable",
         "spectral_radius": res.spectral_radius,
         "modes": [md.to_dict() for md in res.modes]}
    return ModesReportND.from_dict(d, analysis=res, scene_nd=scene)
