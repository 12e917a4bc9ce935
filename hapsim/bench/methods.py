"""The methods compared (moved): :mod:`hapsim.analysis.integrators`.

The integrators as linear maps, their closed-form stability limits and
:func:`~hapsim.analysis.integrators.stability_margin` are analysis (the daemon refuses
unstable scenes with them), so they live in :mod:`hapsim.analysis`; this module keeps the old
names for ``hapsim bench`` and its callers.
"""

from hapsim.analysis.integrators import *  # noqa: F401,F403
from hapsim.analysis.integrators import __all__  # noqa: F401
