"""The results of a run's steps (:mod:`hapsim.pipeline.runner`): :class:`PreparedRun` (steps 1-2,
:func:`~hapsim.pipeline.runner.prepare_run`), :class:`Connection` (step 3,
:func:`~hapsim.pipeline.runner.connect`) and :class:`LoopRun` (step 4,
:func:`~hapsim.pipeline.runner.run_loop`), which the identification
(:func:`hapsim.pipeline.measure.identify_run`) and the report
(:func:`hapsim.pipeline.report.build_report`) read. Records only: nothing here runs."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hapsim.host.loop import LoopConfig, StopFlag
    from hapsim.host.realtime import RealtimePriority
    from hapsim.host.telemetry import Telemetry
    from hapsim.scene import Scene

__all__ = ["PreparedRun", "Connection", "LoopRun"]


@dataclass
class PreparedRun:
    """Step 1-2 of a run: the calibrated scene, its prediction and the run's sizes.

    Attributes
    ----------
    scene : Scene
        Calibrated scene (rate override applied).
    targets : list of dict
        :func:`~hapsim.analysis.prediction.prepare_scene`'s target links.
    pred : dict
        :func:`~hapsim.analysis.prediction.predict`'s closed loop.
    exc_end : float
        End of the excitation [s].
    window : float
        Identification window [s] (excitation + 10 periods of the predicted pair, >= 1 s).
    n_samples : int
        Samples to run (0: open-ended).
    n_window, n_ring : int
        Telemetry head (identification window) and ring [samples].
    base_dir : str or None
        Directory of the scene file (profiles are relative to it).
    model_scene : Scene or None
        The scene the loop is predicted and measured with when it is not ``scene``: a
        driver's board that renders a command after it read the handle adds that latency
        to the delay (:func:`hapsim.pipeline.render_latency.timed_prediction`); None:
        ``scene``.
    informative_s : float or None
        How long after the excitation the record is measured when longer
        (:func:`hapsim.pipeline.measure.informative_s`) [s]; None until a measurement
        computes it (once: :func:`hapsim.pipeline.measure.identify_run`).
    """

    scene: Scene
    targets: list
    pred: dict
    exc_end: float
    window: float
    n_samples: int
    n_window: int
    n_ring: int
    base_dir: str | None
    model_scene: Scene | None = None
    informative_s: float | None = None

    @property
    def model(self) -> Scene:
        """The scene the loop is predicted and measured with (:attr:`model_scene`, else
        :attr:`scene`)."""
        return self.scene if self.model_scene is None else self.model_scene


@dataclass
class Connection:
    """Step 3: what :func:`~hapsim.pipeline.runner.connect` set up for the loop (closed by :func:`~hapsim.pipeline.runner.run_loop`).

    Attributes
    ----------
    engine : Engine
        Warmed-up engine of the scene.
    tel : Telemetry
        Preallocated telemetry (whole run, or head + ring).
    cfg : LoopConfig
        Loop configuration.
    stop : StopFlag
        Stop flag the signal handlers set.
    tr : object
        Transport (serial, in-process or sim).
    rt : RealtimePriority
        Entered real-time scheduling (left by :func:`~hapsim.pipeline.runner.run_loop`).
    embedded : EmbeddedMock or None
        Mock child on a pty.
    mock : MockDevice or None
        In-process mock (``inprocess`` and ``sim``).
    old_signals : dict
        ``{signum: handler}`` replaced, put back by :func:`~hapsim.pipeline.runner.run_scene` once the report is
        made.
    measured : MeasuredVelocity or None
        The device's velocity over the wire (VELOCITY frames) for a ``velocity_sensor``
        correction: the loop asks the device for it and the engine reads it.
    warm : thread or None
        The numba warm-up, still running: :func:`~hapsim.pipeline.runner.run_loop` waits for it
        (``finish()``) after the device's HELLO, before CONFIG arms it.
    view : hapsim.view.ViewServer or None
        The live view (``--view``), handed the report once it is made.
    """

    engine: object
    tel: Telemetry
    cfg: LoopConfig
    stop: StopFlag
    tr: object
    rt: RealtimePriority
    embedded: object = None
    mock: object = None
    old_signals: dict = field(default_factory=dict)
    measured: object = None
    warm: object = None
    view: object = None


@dataclass
class LoopRun:
    """Step 4: the loop's result and what the run left behind.

    Attributes
    ----------
    res : LoopResult
        :meth:`hapsim.host.loop.HostLoop.run`'s result.
    mock_report : dict or None
        The mock's own counters.
    writer_info : dict or None
        Journal writer's ``lost_rows``, ``chunks``, ``events``, ``error``.
    journal : str or None
        Journal path (``.hst``).
    error : DeviceError or ProtocolError or None
        What ended the loop when the device was lost beyond recovery (``res`` then holds
        the run up to the loss); :func:`~hapsim.pipeline.runner.run_scene` raises it with the report attached.
    loop : HostLoop or CompiledHostLoop
        The loop that ran.
    ended_at : float or None
        When the loop ended, on ``time.monotonic`` [s] (its start: ``loop.armed_at``).
    """

    res: object
    mock_report: dict | None
    writer_info: dict | None
    journal: str | None
    control: object = None
    sound: dict | None = None
    error: Exception | None = None
    loop: object = None
    ended_at: float | None = None
