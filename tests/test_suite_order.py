"""The order the README's test command hands its tests out in (tests/suite_order.py):
every collected test exactly once, each ``xdist_group`` whole and in its own order, the
longest scopes first, and the rest in collection order."""

from __future__ import annotations

import json
import types

import numpy as np
import pytest

import conftest
from suite_order import DURATIONS, base_nodeid, load_durations, longest_first


def _random_collection(rng):
    """Node ids (some with parameters holding an ``@``), their groups and measured
    seconds for a random suite: a few groups, many ungrouped tests, a third measured."""
    n = int(rng.integers(1, 300))
    names = [f"tests/test_m{rng.integers(0, 20)}.py::test_{i}"
             + (f"[a@b-{i}]" if rng.random() < 0.1 else "") for i in range(n)]
    pool = [None] * 6 + [f"g{k}" for k in range(int(rng.integers(0, 6)))]
    groups = [pool[int(rng.integers(0, len(pool)))] for _ in range(n)]
    seconds = {name: float(rng.exponential(5.0)) for name in names if rng.random() < 0.35}
    return names, groups, seconds


@pytest.mark.parametrize("seed", range(40))
def test_every_test_once_groups_whole_longest_scope_first(seed):
    """Over random suites: a permutation; each group's tests adjacent and in collection
    order; scope lengths (a group's sum, a test's own) never increase along the order;
    equal lengths (the unmeasured tests among them) in order of first appearance."""
    rng = np.random.default_rng(seed)
    names, groups, seconds = _random_collection(rng)
    order = longest_first(names, groups, seconds)
    assert sorted(order) == list(range(len(names)))
    scopes = []                                     # (key, length, first index) per scope
    seen = set()
    for pos, i in enumerate(order):
        key = groups[i] if groups[i] is not None else ("test", i)
        if key in seen:
            assert scopes[-1][0] == key, f"group {key} split at position {pos}"
            continue
        seen.add(key)
        members = [j for j in range(len(names))
                   if (groups[j] if groups[j] is not None else ("test", j)) == key]
        assert order[pos:pos + len(members)] == members      # whole, in collection order
        scopes.append((key, sum(seconds.get(names[j], 0.0) for j in members), members[0]))
    for (_, a, fa), (_, b, fb) in zip(scopes, scopes[1:]):
        assert a > b or (a == b and fa < fb), (a, fa, b, fb)


def test_nothing_measured_keeps_the_collection_order():
    """Without durations (a missing table) the order is the collection's, groups gathered
    at their first test."""
    names = ["a::t0", "a::t1@x", "b::t2", "b::t3", "c::t4"]
    groups = [None, "x", None, "x", None]
    assert longest_first(names, groups, {}) == [0, 1, 3, 2, 4]
    with pytest.raises(ValueError):
        longest_first(names, groups[:-1], {})


def test_group_suffix_is_not_part_of_the_key():
    """The durations are keyed without pytest-xdist's ``@group``; an ``@`` inside the
    parameters stays."""
    assert base_nodeid("t.py::f[1]@sound") == "t.py::f[1]"
    assert base_nodeid("t.py::f[a@b]") == "t.py::f[a@b]"
    assert base_nodeid("t.py::f@g") == "t.py::f"


def test_the_committed_table_reads_and_a_missing_one_is_empty(tmp_path):
    """``tests/durations.json`` holds positive seconds by node id (no group suffix); a
    missing or broken file gives no durations, so the collection order is kept."""
    table = load_durations()
    assert table and all(v > 0 for v in table.values())
    assert all(base_nodeid(k) == k and k.startswith("tests/") for k in table)
    assert json.loads(DURATIONS.read_text())["measured_by"].startswith("python tools/")
    assert load_durations(tmp_path / "none.json") == {}
    (tmp_path / "bad.json").write_text("{")
    assert load_durations(tmp_path / "bad.json") == {}


class _Item:
    """What the conftest hook reads of a collected test."""

    def __init__(self, nodeid, group):
        self.nodeid = nodeid
        self._id = nodeid
        self._group = group

    def iter_markers(self, name):
        if name == "xdist_group" and self._group is not None:
            yield types.SimpleNamespace(args=(self._group,), kwargs={})


@pytest.mark.parametrize("loadgroup", [True, False])
def test_a_worker_hands_out_the_longest_first_a_serial_run_keeps_its_order(loadgroup):
    """The conftest hook on a pytest-xdist worker (``loadgroup`` set) puts the suite's
    longest measured test before the others and suffixes the grouped ones; without it
    (``-n 0``) the items stay as collected."""
    table = load_durations()
    longest = max(table, key=table.get)
    items = [_Item("tests/test_zz.py::test_short", None), _Item(longest, None),
             _Item("tests/test_zz.py::test_grouped", "g")]
    before = list(items)
    config = types.SimpleNamespace(option=types.SimpleNamespace(loadgroup=loadgroup))
    conftest.pytest_collection_modifyitems(config, items)
    if loadgroup:
        assert items[0] is before[1]
        assert str(before[2]._id).endswith("@g")
    else:
        assert items == before and before[2]._id == "tests/test_zz.py::test_grouped"
