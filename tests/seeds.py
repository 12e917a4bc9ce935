"""The seeds of a property test over random scenes and loops: a kept few in the suite, the
whole window in CI's soak (docs/testing.md, "Seeds").

A property test draws its scenes, loops and faults from a seed, over a window of seeds.
The README's test command runs the seeds ``kept``: those that found a failure once, and
enough more to take each branch the test takes by the seed's parity. The rest of the
window carries the ``soak`` mark, which the suite deselects (``-m "not soak"`` in
``pyproject.toml``'s ``addopts``) and CI's second pass runs (``-m "numerical or soak"``,
``.ci/run``), on every push, beside the first at the lowest priority. Locally:
``python -m pytest -m soak`` (the soak alone) or ``-m ""`` (everything).
"""

from __future__ import annotations

import pytest


def seeds(window, kept) -> list:
    """The ``parametrize`` values of a seeded property test.

    Parameters
    ----------
    window : iterable of int
        Every seed the property is claimed over.
    kept : iterable of int
        The seeds the suite runs (a subset of ``window``).

    Returns
    -------
    list
        ``window`` in its order: a kept seed as it is, any other as a ``pytest.param``
        with the ``soak`` mark.

    Raises
    ------
    ValueError
        A kept seed outside the window.
    """
    window, kept = list(window), set(kept)
    if not kept <= set(window):
        raise ValueError(f"kept seeds {sorted(kept - set(window))} are not in the window")
    return [s if s in kept else pytest.param(s, marks=pytest.mark.soak) for s in window]
