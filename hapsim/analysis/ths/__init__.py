"""The THS of Florens, Voda & Urma for a loop of any dimension: what is felt for a virtual
``(K, B)`` and the ``(K, B)`` that renders a felt ``(k, b)`` (docs/design.md, 'The THS';
docs/dimensions.md, 'The THS as a matrix').

One entry per concept, each taking a 1-D :class:`~hapsim.analysis.loop.LoopModel` or a
:class:`MatrixLoop` of n axes (n = 1, 2, 3 Cartesian directions of a handle, or n ports):

- :func:`render` (the inverse map: a :class:`RenderResult` for a 1-D loop, by the scalar
  closed forms; a :class:`MatrixRenderResult`, the felt matrices, for a matrix loop);
- :func:`calibrate` (the forward map; a matrix loop of one axis as its 1-D loop, more axes
  refused by name) and :func:`check_target`;
- :func:`state_matrix`, :func:`closed_loop_poles`, :func:`rendered_pairs` (a rigid 1-D loop
  with the zero-order hold is the matrix loop's case n = 1).

Four rooms, each importing only the ones before it: :mod:`~hapsim.analysis.ths.matrix_loop`
(the loop with matrices), :mod:`~hapsim.analysis.ths.holds` (the hold and delay as matrices:
the exact zero-order hold, the state matrix, the poles), :mod:`~hapsim.analysis.ths.felt`
(the rendered pairs and the felt matrices) and :mod:`~hapsim.analysis.ths.render` (render
and calibrate).
"""

from hapsim.analysis.ths.matrix_loop import MATRIX_HOLDS, MatrixLoop, as_matrix_loop, gain_matrices
from hapsim.analysis.ths.holds import (closed_loop_poles, split_hold_matrices, state_matrix,
                                       zoh_blocks, zoh_matrices)
from hapsim.analysis.ths.felt import (MatrixRenderResult, continuous_poles, felt_matrices,
                                      render_state, rendered_pairs, rendered_pairs_of,
                                      rendered_pairs_of_many)
from hapsim.analysis.ths.render import (CalibrationResult, RenderResult, calibrate,
                                        calibrate_core, check_target, log_abs_w, render)

__all__ = ["MATRIX_HOLDS", "MatrixLoop", "as_matrix_loop", "gain_matrices",
           "closed_loop_poles", "split_hold_matrices", "state_matrix", "zoh_blocks",
           "zoh_matrices",
           "MatrixRenderResult", "continuous_poles", "felt_matrices", "render_state",
           "rendered_pairs", "rendered_pairs_of", "rendered_pairs_of_many",
           "CalibrationResult", "RenderResult", "calibrate", "calibrate_core", "check_target",
           "log_abs_w", "render"]
