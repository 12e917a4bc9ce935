"""THS analysis of Florens, Voda & Urma: loop model, rendered (k, b), calibration,
stability boundary and the (k, b) grid in the (K, B) plane (docs/design.md, 'The THS').
``render``, ``calibrate`` and ``closed_loop_poles`` take a loop of any dimension (a 1-D
:class:`LoopModel` or a :class:`MatrixLoop`: :mod:`hapsim.analysis.ths`).

Compute functions here return plain data; drawing lives in :mod:`hapsim.plots`.
"""

from hapsim.analysis.modes import Mode, modes_from_poles, rendered_pair
from hapsim.analysis.loop import (HOLDS, STABILITY_TOL, LoopModel, characteristic, plant,
                                  zoh_state_space)
from hapsim.analysis.loop_poles import spectral_radius
from hapsim.analysis.stability import (damping_limits, published_limits, stability_boundary,
                                       stability_limit)
from hapsim.analysis.ths import (CalibrationResult, MatrixLoop, MatrixRenderResult,
                                 RenderResult, calibrate, closed_loop_poles, render,
                                 state_matrix)
from hapsim.analysis.grid import PAPER_PRESETS, GridResult, grid, paper_preset
from hapsim.analysis.pencil import fit_modes, fit_rendered, pencil_poles
from hapsim.analysis.scene_check import SceneCheck, check_scene, scene_state_matrix
from hapsim.analysis.table1 import table1_experiment
from hapsim.analysis.network import closed_loop

__all__ = [
    "Mode", "modes_from_poles", "rendered_pair",
    "HOLDS", "STABILITY_TOL", "LoopModel", "characteristic", "closed_loop_poles", "plant",
    "spectral_radius", "zoh_state_space",
    "CalibrationResult", "RenderResult", "calibrate", "damping_limits", "published_limits",
    "render", "stability_boundary", "stability_limit",
    "MatrixLoop", "MatrixRenderResult", "state_matrix",
    "PAPER_PRESETS", "GridResult", "grid", "paper_preset",
    "fit_modes", "fit_rendered", "pencil_poles",
    "SceneCheck", "check_scene", "scene_state_matrix",
    "table1_experiment",
    "closed_loop",
]
