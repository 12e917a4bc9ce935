"""hapsim's Python API: the commands as functions that return typed results.

Flat, in python-control's style: load a scene, then ask what it feels like::

    import hapsim
    scene = hapsim.load_scene("configs/wall.yaml")
    r = hapsim.check(scene)          # CheckReport: r.k [N/m], r.b [N s/m], r.stable, ...
    fig = r.plot()                   # the closed-loop poles (needs the plot extra)

Each function returns a frozen dataclass whose fields are exactly the keys of the matching
command's ``--json`` object (``to_dict()`` gives that object back), so what a script reads
is what a program reading ``hapsim COMMAND --json`` reads:

============================  ==========================  ===========================
function                      result                      command
============================  ==========================  ===========================
:func:`check`                 :class:`CheckReport`        ``hapsim check SCENE``
:func:`render`                :class:`RenderReport`       ``hapsim render``
:func:`calibrate`             :class:`CalibrateReport`    ``hapsim calibrate``
:func:`stability`             :class:`StabilityReport`    ``hapsim stability``
:func:`family`                :class:`FamilyReport`       ``hapsim family SCENE``
:func:`identify`              :class:`IdentifyReport`     ``hapsim identify``
:func:`run`                   :class:`RunReport`          ``hapsim run SCENE``
:func:`play`                  :class:`PlayReport`,        ``hapsim play SCENE`` (any
                              :class:`PlayReportND`       dimension)
:func:`check_nd`              :class:`CheckReportND`      ``hapsim check SCENE`` (n-D)
:func:`modes_nd`              :class:`ModesReportND`      ``hapsim check SCENE`` (n-D,
                                                          no port)
:func:`run_nd`                :class:`RunReportND`        ``hapsim run SCENE
                                                          --lockstep`` (n-D)
:func:`simulate`              :class:`SimulateReport`     ``hapsim simulate SCENE``
                              (``...ND``, ``...Ports``)   (any dimension, ports)
============================  ==========================  ===========================

A 2-D or 3-D scene (``dimension: 2`` or ``3``) is read by :func:`load_scene` too (a
:class:`~hapsim.scene.SceneND`, whose ``dimension`` says which) or
:func:`load_scene_nd`; :func:`check`, :func:`run` and :func:`play` take a scene of any
dimension (``check_nd``, ``modes_nd`` and ``run_nd`` are the same computations by their
n-D names); :func:`family` and :func:`identify` are 1-D yet and say so. A scene with
several ports (``devices:``, a :class:`~hapsim.scene.ScenePorts`) is taken by
:func:`check`, :func:`run` and :func:`simulate` (its trajectory, each port closed
through its own device model); :func:`simulate` takes every dimension too (the
trajectory ``hapsim simulate SCENE --out FILE`` writes).

The package is split by capability, each module holding every dimension's report and
function: :mod:`~hapsim.api.checking` (check), :mod:`~hapsim.api.loops` (render,
calibrate, stability), :mod:`~hapsim.api.families`, :mod:`~hapsim.api.identifying`,
:mod:`~hapsim.api.running`, :mod:`~hapsim.api.playing`, :mod:`~hapsim.api.simulating`, and :mod:`~hapsim.api.common`
(reading a scene, what the others share).

``render``, ``calibrate`` and ``stability`` take a :class:`LoopModel` (the real side of
the loop: mass, friction, rate, delay, hold). Errors are those of the commands: a
:class:`~hapsim.errors.ConfigError` names the file, line and key; an
:class:`~hapsim.errors.UnstableConfigError` is a negative verdict. Compute and drawing are
apart: the ``plot()`` methods call :mod:`hapsim.plots`, the only module importing
matplotlib (the ``plot`` extra).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from hapsim.api.checking import (CheckReport, CheckReportND, ModesReportND, check,
                                 check_nd, modes_nd)
from hapsim.api.common import known_decimals, known_digits, load_scene, load_scene_nd
from hapsim.api.families import FamilyReport, family
from hapsim.api.identifying import IdentifyReport, calibrate_scale, excite_and_fit, identify
from hapsim.api.loops import (CalibrateReport, RenderReport, StabilityReport, calibrate,
                              render, stability)
from hapsim.api.playing import PLAY_OPTIONS, PlayReport, PlayReportND, play
from hapsim.api.running import (RunReport, RunReportND, run, run_nd, run_options,
                                run_report_nd, run_scene_nd, stable_prediction_nd)
from hapsim.api.simulating import (SimulateReport, SimulateReportND, SimulateReportPorts,
                                   simulate)
from hapsim.results import Report

if TYPE_CHECKING:     # bound for readers and checkers; at run time by __getattr__
    from hapsim.analysis.loop import LoopModel

__all__ = ["load_scene", "LoopModel", "check", "render", "calibrate", "stability", "family",
           "identify", "calibrate_scale", "run", "play", "excite_and_fit", "known_digits",
           "known_decimals", "run_options", "CheckReport", "RenderReport", "CalibrateReport",
           "StabilityReport", "FamilyReport", "IdentifyReport", "RunReport", "PlayReport",
           "PLAY_OPTIONS", "Report", "load_scene_nd", "check_nd", "modes_nd", "run_nd",
           "run_report_nd", "run_scene_nd", "stable_prediction_nd", "CheckReportND",
           "ModesReportND", "RunReportND", "PlayReportND", "simulate", "SimulateReport",
           "SimulateReportND", "SimulateReportPorts"]


#: Public names provided on first use (PEP 562), with the module that defines them:
#: importing the analysis costs more than the rest of this package together.
_LAZY = {"LoopModel": "hapsim.analysis.loop"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value            # once: the next reads find it directly
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
