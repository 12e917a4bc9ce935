"""Real-time scheduling of the loop: obtained where permitted, restored after, reported."""

from __future__ import annotations

import os

import pytest

from hapsim.daemon.realtime import RealtimePriority
from hapsim.errors import ConfigError

linux = pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="no sched_setscheduler")


def _fifo_permitted() -> bool:
    try:
        saved = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        return False
    os.sched_setscheduler(0, *saved)
    return True


@linux
def test_policy_is_restored_and_reported():
    before = os.sched_getscheduler(0)
    with RealtimePriority(10) as rt:
        inside = os.sched_getscheduler(0)
        if rt.active:
            assert inside == os.SCHED_FIFO and os.sched_getparam(0).sched_priority == 10
            assert rt.note == "SCHED_FIFO 10"
        else:
            assert inside == before and "refused" in rt.note
    assert os.sched_getscheduler(0) == before
    assert rt.active == _fifo_permitted()


def test_zero_leaves_scheduling_alone():
    with RealtimePriority(0) as rt:
        assert not rt.active and rt.note.startswith("normal")


@pytest.mark.parametrize("bad", [-1, 100])
def test_out_of_range_priority_is_a_config_error(bad):
    with pytest.raises(ConfigError, match="--rt-priority"):
        RealtimePriority(bad)


@linux
def test_run_reports_scheduling_and_restores_it():
    from hapsim.daemon.runner import run_scene
    from hapsim.scene import load_scene
    before = os.sched_getscheduler(0)
    rep = run_scene(load_scene("configs/wall.yaml"), transport="pty", lockstep=True,
                    duration=0.2, handle_signals=False, rt_priority=5)
    assert os.sched_getscheduler(0) == before
    expected = "SCHED_FIFO 5" if _fifo_permitted() else "normal"
    assert rep["loop"]["scheduling"].startswith(expected)
