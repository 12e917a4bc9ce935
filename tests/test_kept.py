"""The analysis's kept answers (:class:`hapsim.analysis.kept.Kept`): the same key's answer
given again without computing it, the least recently asked dropped first, an answer
named by an object's identity given to that object only, a failed computation not kept."""

from __future__ import annotations

import pytest

from hapsim.analysis.kept import Kept


def test_answers_kept_newest_first_by_key_and_owner():
    calls = []

    def compute(v):
        def f():
            calls.append(v)
            return [v]
        return f

    k = Kept(2)
    a = k.get("a", compute("a"))
    assert k.get("a", compute("a!")) is a and calls == ["a"]
    k.get("b", compute("b"))
    k.get("a", compute("a!"))              # a asked last: b is the oldest
    k.get("c", compute("c"))               # b dropped
    assert k.get("a", compute("a!")) is a
    k.get("b", compute("b2"))
    assert calls == ["a", "b", "c", "b2"]
    one, other = object(), object()
    x = k.get(("id", 1), compute("x"), owner=one)
    assert k.get(("id", 1), compute("y"), owner=other) == ["y"]   # another object
    assert k.get(("id", 1), compute("z"), owner=other) == ["y"]
    assert x == ["x"]


def test_a_failed_computation_is_not_kept():
    k = Kept(4)

    def fail():
        raise ValueError("no")
    with pytest.raises(ValueError):
        k.get("a", fail)
    assert k.get("a", lambda: 1) == 1
