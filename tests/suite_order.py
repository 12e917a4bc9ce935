"""The order in which the README's test command hands tests to its pytest-xdist workers:
longest first (issue 31 item 2).

pytest-xdist's ``--dist loadgroup`` hands each worker one *scope* at a time (an
``xdist_group``, run whole on one worker, or a test alone) in the order of the workers'
collection, a new one when the worker has two tests or fewer left. In collection order a
test of a minute can be handed out last and run alone while the other workers have
finished: the suite then waits for it. Handing the longest scopes out first (the LPT rule
of list scheduling, Graham 1969: the finish is at most 4/3 of the optimum, against 2 for
an arbitrary order) leaves the short tests for the end, where they fill the workers'
gaps.

The durations are measured, not guessed: ``tests/durations.json`` holds the wall seconds of
the tests that took :data:`MIN_SECONDS` or more in a full run of the README's command
beside one busy process, written by ``python tools/suite_time.py --durations
tests/durations.json``. A test it does not name (a new one, or a short one) counts as 0
and keeps its place in collection order after the measured ones; a stale figure only moves
a test in the order, never changes what runs (every collected test runs exactly once:
``tests/test_suite_order.py``).
"""

from __future__ import annotations

import json
from pathlib import Path

#: The measured durations' file (tools/suite_time.py --durations writes it).
DURATIONS = Path(__file__).with_name("durations.json")

#: Tests shorter than this [s of wall clock] are not listed: handed out in collection order
#: after the listed ones, they are the short work that fills the workers' ends.
MIN_SECONDS = 2.0


def base_nodeid(nodeid: str) -> str:
    """A node id without pytest-xdist's ``@group`` suffix (the key of the durations).

    Parameters
    ----------
    nodeid : str
        ``path::name[params]`` or ``path::name[params]@group``.

    Returns
    -------
    str
        The id without the suffix (an ``@`` inside the parameters is kept).
    """
    at = nodeid.rfind("@")
    return nodeid[:at] if at > nodeid.rfind("]") else nodeid


def load_durations(path: str | Path = DURATIONS) -> dict[str, float]:
    """The measured wall seconds by node id (without the group suffix).

    Parameters
    ----------
    path : str or Path, optional
        The JSON file: ``{"seconds": {nodeid: seconds, ...}, ...}``.

    Returns
    -------
    dict
        Empty when the file is missing or unreadable (the collection order is then kept).
    """
    try:
        with open(path) as f:
            seconds = json.load(f)["seconds"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    return {str(k): float(v) for k, v in seconds.items()}


def longest_first(nodeids: list[str], groups: list[str | None],
                  seconds: dict[str, float]) -> list[int]:
    """The order of the tests, longest scope first.

    A scope is an ``xdist_group`` (all its tests) or an ungrouped test alone; its length
    is the sum of its tests' measured seconds (0 for a test not measured). Scopes are
    ordered by decreasing length, ties (the unmeasured ones among them) in the order in
    which they first appear; a group's tests stay together in their collection order.

    Parameters
    ----------
    nodeids : list of str
        The collected tests' node ids, in collection order.
    groups : list of str or None
        Each test's ``xdist_group`` name, None for an ungrouped test.
    seconds : dict
        Measured wall seconds by node id without the group suffix (:func:`base_nodeid`).

    Returns
    -------
    list of int
        A permutation of ``range(len(nodeids))``: the indices in the new order.
    """
    if len(nodeids) != len(groups):
        raise ValueError(f"{len(nodeids)} node ids but {len(groups)} groups")
    members: dict[tuple, list[int]] = {}
    for i, (nodeid, group) in enumerate(zip(nodeids, groups)):
        key = ("group", group) if group is not None else ("test", i)
        members.setdefault(key, []).append(i)
    length = {key: sum(seconds.get(base_nodeid(nodeids[i]), 0.0) for i in idx)
              for key, idx in members.items()}
    first = {key: idx[0] for key, idx in members.items()}
    order = sorted(members, key=lambda key: (-length[key], first[key]))
    return [i for key in order for i in members[key]]
