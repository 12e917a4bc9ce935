"""Real-time scheduling of the loop: obtained where permitted, restored after, reported."""

from __future__ import annotations

import os

import pytest

from hapsim.host.realtime import RealtimePriority
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
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    before = os.sched_getscheduler(0)
    rep = run_scene(load_scene("configs/wall.yaml"), transport="pty", duration=0.2,
                    handle_signals=False, rt_priority=5)
    assert os.sched_getscheduler(0) == before
    expected = "SCHED_FIFO 5" if _fifo_permitted() else "normal"
    assert rep["loop"]["scheduling"].startswith(expected)


@linux
def test_a_lockstep_run_is_not_real_time():
    """A lockstep mock waits for each FORCE: host and mock ping-pong as fast as they can, so
    under SCHED_FIFO they would own the cores at the priority of every real-time loop of the
    machine. Neither takes it; the report says why."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    rep = run_scene(load_scene("configs/wall.yaml"), transport="pty", lockstep=True,
                    duration=0.2, handle_signals=False, rt_priority=5)
    assert rep["loop"]["scheduling"] == ("normal (lockstep: paced by the device's answers, "
                                         "not by the clock)")


def _policy(pid: int) -> int:
    """Scheduling policy of a process's main thread (field 41 of /proc/PID/stat)."""
    with open(f"/proc/{pid}/stat") as fh:
        return int(fh.read().rsplit(")", 1)[1].split()[38])


@linux
@pytest.mark.parametrize("loop", ["compiled", "python"])
def test_the_mock_starts_under_normal_scheduling_and_takes_fifo_itself(monkeypatch, loop):
    """The embedded mock is spawned from a thread under normal scheduling (its start-up,
    ~0.5 s of CPU, would otherwise run as a real-time process that no real-time loop of
    the same priority can preempt), is asked for the priority on its command line, and
    runs its tick loop under SCHED_FIFO; the host loop runs under SCHED_FIFO."""
    if not _fifo_permitted():
        pytest.skip("SCHED_FIFO not permitted here: nothing to check")
    from hapsim.host import loop as loop_mod
    from hapsim.emulated import links as transport
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    seen = {}
    init = transport.EmbeddedMock.__init__

    def spawn(self, *a, **kw):
        seen["spawned_under"] = os.sched_getscheduler(0)
        init(self, *a, **kw)
        seen["pid"], seen["cmd"] = self.proc.pid, self.proc.args

    states = loop_mod.HostLoop._device_states       # the source of both loops

    def running(self, n_max):
        seen.setdefault("loop_under", os.sched_getscheduler(0))
        seen.setdefault("mock_under", _policy(seen["pid"]))    # it answered: it serves
        return states(self, n_max)

    monkeypatch.setattr(transport.EmbeddedMock, "__init__", spawn)
    monkeypatch.setattr(loop_mod.HostLoop, "_device_states", running)
    run_scene(load_scene("configs/wall.yaml"), transport="pty", duration=0.2,
              handle_signals=False, rt_priority=7, loop=loop)
    assert seen["spawned_under"] == os.SCHED_OTHER
    assert seen["cmd"][seen["cmd"].index("--rt-priority") + 1] == "7"
    assert seen["loop_under"] == os.SCHED_FIFO and seen["mock_under"] == os.SCHED_FIFO
