"""The real-time mock is one handle: a CONFIG restarts the protocol's session, not the
physics (hapsim.emulated.mock, 'One handle').

Before, every CONFIG rebuilt the plant at the scene's x0 at rest: a host that lost the
device and re-configured it found the handle back at 5 mm, wherever the force it held
through the silence had taken it. A board's handle stays where it went.
"""

from __future__ import annotations


import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.emulated.mock import MockDevice
from hapsim.scene import Device, Excitation
from test_haply_wallclock import free_motion    # the closed form, written independently

EPS = np.finfo(float).eps


def _pushed(rng, rate=1000.0):
    """A random device configured at t = 0 and pushed by random FORCEs for a while; the
    mock, its period [us] and the time of its last tick [us]."""
    dev = Device(mass=float(rng.uniform(0.05, 0.5)), friction=float(rng.uniform(0.1, 2.0)),
                 delay=1, hold="zoh", force_limit=10.0)
    mock = MockDevice(dev, Excitation(x0=float(rng.uniform(-0.01, 0.01))),
                      native_rate_hz=rate, lockstep=False)
    T_us = int(round(1e6 / rate))
    mock.handle(fp.Config(rate, 50_000, 10.0), 0)
    t = 0
    for _ in range(int(rng.integers(20, 200))):
        st = mock.tick(t)
        mock.handle(fp.Force(st.seq, (float(rng.normal(0.0, 2.0)),)), t + T_us // 3)
        t += T_us
    return mock, T_us, t - T_us


@pytest.mark.parametrize("seed", range(8))
def test_a_reconfigured_handle_is_where_it_coasted(seed):
    """STOP, then CONFIG some whole periods later: the new session's first STATE is the
    free coast of the handle the last tick left (its position and velocity, zero force over
    every period from the end of that tick's period to the CONFIG), not the scene's x0."""
    rng = np.random.default_rng(900 + seed)
    mock, T_us, t_last = _pushed(rng)
    ph = mock.physics
    x1, v1 = ph.x, ph.v                     # the plant at the end of the last tick's period
    dev = mock.device
    idle = int(rng.integers(0, 600))        # whole periods left alone
    t_stop = t_last + T_us // 2
    mock.handle(fp.Stop(), t_stop)
    t_cfg = t_last + (idle + 1) * T_us
    mock.handle(fp.Config(1000.0, 50_000, 10.0), t_cfg)
    st = mock.tick(t_cfg)
    assert st.seq == 0                       # the protocol's session restarted
    want, _ = free_motion(x1, v1, 0.0, dev.mass, dev.friction, idle * T_us * 1e-6)
    # the ZOH recursion, idle steps each rounding a few times (relative eps each), against
    # the closed form: 16 eps per step on the scale of the motion, with a margin
    scale = abs(x1) + abs(v1) * dev.mass / dev.friction
    assert st.position[0] == pytest.approx(want, rel=0, abs=16 * (idle + 1) * EPS * scale)
    assert st.position[0] != mock.excitation.x0 or v1 == 0.0


def test_the_hand_goes_on_in_its_own_time():
    """A hand force profile is not restarted by a CONFIG: the re-configured plant's hand is
    the old one's from the instant reached (idle periods included)."""
    dev = Device(mass=0.1, friction=0.5, delay=1, hold="zoh", force_limit=10.0)
    mock = MockDevice(dev, Excitation(x0=0.0), native_rate_hz=1000.0, lockstep=False)
    mock.handle(fp.Config(1000.0, 50_000, 10.0), 0)
    hand = np.linspace(0.0, 1.0, 400)
    mock.physics.hand = hand
    for k in range(30):
        mock.tick(1000 * k)
    mock.handle(fp.Stop(), 29_500)
    mock.handle(fp.Config(1000.0, 50_000, 10.0), 29_000 + 11 * 1000)   # 10 idle periods
    assert np.array_equal(mock.physics.hand, hand[40:])


def test_a_new_hand_and_lockstep_start_the_excitation_again():
    """After new_hand() (a new host: the persistent serving loop calls it when one hangs
    up), and in lockstep at every CONFIG, the plant starts at the scene's x0 at rest."""
    rng = np.random.default_rng(5)
    mock, T_us, t_last = _pushed(rng)
    mock.handle(fp.Stop(), t_last + T_us)
    mock.new_hand()
    mock.handle(fp.Config(1000.0, 50_000, 10.0), t_last + 5 * T_us)
    assert mock.tick(t_last + 5 * T_us).position[0] == mock.excitation.x0
    dev = Device(mass=0.1, friction=0.5, delay=1, hold="zoh", force_limit=10.0)
    lock = MockDevice(dev, Excitation(x0=0.004), native_rate_hz=1000.0, lockstep=True)
    (s,) = lock.handle(fp.Config(1000.0, 50_000, 10.0), 0)
    for _ in range(50):
        (s,) = lock.handle(fp.Force(s.seq, (3.0,)), 0)
    assert s.position[0] != 0.004
    (s,) = lock.handle(fp.Config(1000.0, 50_000, 10.0), 0)
    assert s.seq == 0 and s.position[0] == 0.004
