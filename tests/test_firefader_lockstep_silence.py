"""A lockstep FireFader mock's silence rule counts periods, not the wall clock (issue 29).

The ``.ino`` zeroes its enable and motor after about 0.1 s without a byte
(:data:`hapsim.drivers.firefader.SILENCE_S`). On its own clock the mock runs that rule on
the wall clock, as the board does. Named lockstep (a test device), the device's time is
the host's commands: one period per host write. Before, :func:`hapsim.emulated.
driver_mock.serve` still called the device's ``idle`` with the wall clock's silence, so a
lockstep mock whose host was descheduled for 0.1 s (a loaded machine) zeroed its force
and the record was another. Now the rule counts host writes of which no byte arrived,
SILENCE_S of periods of them, and the wall clock is nobody's time in lockstep.
"""

from __future__ import annotations

import math
import socket
import threading
import time

import pytest

from hapsim.drivers import firefader as ff
from hapsim.emulated.driver_mock import FireFaderDevice, serve
from hapsim.scene import Device, Excitation

RATE = 250.0
#: Writes of which no byte arrived that make SILENCE_S at RATE: 25 (0.1 s / 4 ms).
QUIET = math.ceil(ff.SILENCE_S * RATE - 1e-9)


def _device():
    return FireFaderDevice(Device(mass=0.05, friction=0.1, delay=1, force_limit=0.39), RATE,
                           Excitation(x0=0.0), clock="lockstep", pass_time=False)


def _armed(dev, passes=20):
    pk = ff.FireFader().encode_force(0.1)
    for _ in range(passes):
        dev.feed(pk, writes=[b"", pk])
    assert dev.enable >= 20               # the enable filter is full: the force is on
    return pk


@pytest.mark.parametrize("quiet", [QUIET - 1, QUIET])
def test_lockstep_silence_is_counted_in_periods(quiet):
    """Closed form: ``quiet`` host writes lost whole (each one period of the device's
    time): one fewer than SILENCE_S worth leaves the enable as it was; SILENCE_S worth
    zeroes it and the motor at that tick, and the next passes restart the filter."""
    dev = _device()
    pk = _armed(dev)
    e = dev.enable
    ticks = dev.host_ticks
    dev.feed(b"", writes=[b""] + [b""] * quiet)      # writes whose bytes were all lost
    assert dev.host_ticks == ticks + quiet and dev.silent_ticks == quiet
    tripped = quiet * dev.physics.period >= ff.SILENCE_S - 1e-12
    assert dev.enable == (0 if tripped else e)
    assert dev.silences == ([(ticks + quiet) * dev.physics.period] if tripped else [])
    dev.feed(pk, writes=[b"", pk])                    # a byte came: the count restarts
    assert dev.silent_ticks == 0
    assert (dev.enables[-1] == 0) == tripped          # the pass ran with the enable zeroed


def test_a_slow_host_is_no_silence_for_a_lockstep_mock():
    """Through :func:`serve` (a socket pair as the port): the host arms the mock, then is
    silent for 0.15 s of wall time (a descheduled host), then goes on. The lockstep
    mock's time did not go on: no silence, the enable goes on rising from where it was.
    (The test's sleep is the slow host; nothing here measures time.)"""
    dev = _device()
    host, board = socket.socketpair()
    stop = threading.Event()
    th = threading.Thread(target=serve, args=(board.fileno(), dev),
                          kwargs={"stop": stop.is_set, "poll": 0.005}, daemon=True)
    th.start()
    pk = ff.FireFader().encode_force(0.1)
    host.settimeout(5.0)

    def ask():
        host.sendall(pk)
        got = b""
        while len(got) < 7:                              # one record per packet
            got += host.recv(7 - len(got))
        return got

    try:
        for _ in range(12):
            ask()
        before = dev.enable
        assert before >= 20
        time.sleep(1.5 * ff.SILENCE_S)                   # the host is silent (slow)
        ask()
    finally:
        stop.set()
        th.join(5.0)
        host.close()
        board.close()
    assert dev.silences == [] and dev.silent_ticks == 0
    assert dev.enables[-1] == before                     # the pass after the wait: as before
