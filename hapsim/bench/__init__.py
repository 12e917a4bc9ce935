"""Speed against accuracy: the methods compared, charts' data, stability margins, advice.

Compute only (plain data); figures are drawn by :mod:`hapsim.plots.bench`.

- :mod:`hapsim.bench.methods`: the old name of :mod:`hapsim.analysis.integrators`
  (integrators as linear maps, closed-form limits, ``stability_margin``).
- :mod:`hapsim.bench.accuracy`: chart 1, felt (k, b) error against rate, naive and calibrated.
- :mod:`hapsim.bench.cost`: chart 2, mode error against CPU cost per integrator.
- :mod:`hapsim.bench.capacity`: chart 3, loop capacity over a real pty.
- :mod:`hapsim.bench.advise`: :func:`~hapsim.bench.advise.advise_scene`, the lowest rate and
  cheapest scheme a scene needs.
"""

from hapsim.analysis.integrators import StabilityMargin, stability_margin

__all__ = ["StabilityMargin", "stability_margin"]
