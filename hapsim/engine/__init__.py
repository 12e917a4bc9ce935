"""The mass-interaction engine: a validated scene of any dimension turned into arrays and
numba kernels (issue 30 item 1: one engine, compiled per dimension).

:class:`Engine` is the API layer: it takes a :class:`~hapsim.scene.Scene` (1-D) or a
:class:`~hapsim.scene.SceneND` (2-D, 3-D), never raw YAML, and answers one API for both
(positions ``(n, N)``, the port's position and force ``(n,)``; the ``n = 1`` float
shorthand of :meth:`Engine.port_step`). Each dimension keeps its own layout and kernels, in
the package's private modules:

- :mod:`hapsim.engine._line`: a 1-D scene as one array per field, advanced by the kernel
  of :mod:`hapsim.kernels.cordis` (or :mod:`~hapsim.kernels.schemes`) matching its link
  kinds, multi-rate with :mod:`hapsim.kernels.audio`; its compiled callers take its arrays
  by name (:class:`KernelPack`, :class:`MultiRatePack`);
- :mod:`hapsim.engine._space`: a 2-D or 3-D scene as a ``(3, N)`` state on the kernels of
  :mod:`hapsim.kernels.nd`, in double or single precision (:data:`PRECISIONS`);
- :mod:`hapsim.engine._api`: :class:`Engine` itself, :func:`mass_indices` and
  :func:`warm_up`.
"""

from __future__ import annotations

from hapsim.engine._api import LAYOUTS, PRECISIONS, Engine, mass_indices, warm_up
from hapsim.engine._line import KernelPack, Line, MultiRatePack


def _space() -> type:
    """The n-D layout, imported on the first 2-D or 3-D engine (a 1-D run does not load
    the n-D kernels' module)."""
    from hapsim.engine._space import Space
    return Space


LAYOUTS.update({1: lambda: Line, 2: _space, 3: _space})

__all__ = ["Engine", "KernelPack", "MultiRatePack", "PRECISIONS", "mass_indices", "warm_up"]
