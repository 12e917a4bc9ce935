"""The FireFader's position scale from a sweep between its end stops (issue 20): the
sweep (hapsim.drivers.firefader_travel.find_travel) against the firmware's own loop
(hapsim.emulated.driver_mock.FireFaderDevice with end stops), in-process, over random true scales;
its refusals; and the full scale from an added mass once the position scale is right."""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.emulated.driver_mock import FireFaderDevice
from hapsim.drivers import firefader as ff
from hapsim.drivers.firefader_travel import find_travel
from hapsim.errors import ConfigError, IdentificationError
from hapsim.scene import Device, Excitation


class _Wire:
    """The host's port wired to the mock firmware in this process (no pty, no time)."""

    def __init__(self, dev) -> None:
        self.dev = dev
        self.buf = b""

    def write(self, data: bytes) -> None:
        self.buf += self.dev.feed(data)

    def read(self, timeout: float) -> bytes:
        out, self.buf = self.buf, b""
        return out


def _fader(mpc, travel, stop_low, *, mass=0.05, friction=0.5, coulomb=0.0, touch=True,
           full_scale=0.39, seed=0):
    dev = Device(mass=mass, friction=friction, delay=1, force_limit=10.0, coulomb=coulomb)
    # lockstep by name: the sweep's logic against the firmware's, in-process, no time
    return FireFaderDevice(dev, 250.0, Excitation(), full_scale=full_scale,
                           metres_per_count=mpc, travel=travel, stop_low=stop_low,
                           touch=touch, seed=seed, clock="lockstep")


def _sweep(dev, drv=None, force=0.3):
    return find_travel(drv or ff.FireFader(), _Wire(dev), travel=dev.stops[1] - dev.stops[0],
                       force=force, rate_hz=250.0, pace=False, timeout=0.0)


@pytest.mark.parametrize("seed", range(20))
def test_the_sweep_finds_the_true_position_scale(seed):
    """Random true position scales (0.3-0.5 mm per count), travels and stop positions
    that the pot reads inside its rails, random full scales and masses: the position scale
    found is within its stated interval, the interval is the stops' counts to at most +-1 count each
    (under 1 % of a ~250-count span), and the fader ends near the middle at zero force."""
    rng = np.random.default_rng(seed)
    mpc = rng.uniform(0.3e-3, 0.5e-3)
    span = rng.uniform(120, 245)                   # counts between the stops
    low = rng.uniform(3, 250 - span)               # the low stop's count, off the rails
    travel = span * mpc
    dev = _fader(mpc, travel, (low - ff.CENTRE) * mpc, mass=rng.uniform(0.03, 0.2),
                 full_scale=rng.uniform(0.2, 2.0), seed=seed)
    got = _sweep(dev)
    assert got.lo <= mpc <= got.hi, (mpc, got)
    assert (got.hi - got.lo) / mpc < 4.1 / span
    # the counts the mock's pot reads at its stops (an independent reading of the truth)
    assert abs(got.counts[0] - round(low)) <= 1
    assert abs(got.counts[1] - round(low + span)) <= 1
    assert dev.held == 0.0 or dev.settles_on() == 0.0
    mid = 0.5 * (got.counts[0] + got.counts[1])
    # not round-off: "near the middle" as a quarter of the span; measured 2.9 % of that
    # bound at worst over the 20 seeds (1.5 counts at most), margin 34
    assert abs(dev.position_count() - mid) <= 0.25 * span


def test_the_sweep_refuses_what_is_no_length_reference():
    """A stop beyond the pot's rail, no stops at all, an untouched fader (the firmware's
    force never comes on), a fader whose friction exceeds the force: each refused with
    its reason, never a scale."""
    mpc = ff.METRES_PER_COUNT
    rail = _fader(mpc, 0.1, -0.0505)                # the low stop reads below count 0
    with pytest.raises(IdentificationError, match="rail"):
        _sweep(rail)
    nostop = _fader(mpc, None, None)
    nostop.stops = None
    with pytest.raises(IdentificationError, match="rail|did not reach"):
        find_travel(ff.FireFader(), _Wire(nostop), travel=0.09, force=0.3, pace=False,
                    timeout=0.0)
    cold = _fader(mpc, 0.09, -0.045, touch=False)
    with pytest.raises(IdentificationError, match="did not move"):
        _sweep(cold)
    stuck = _fader(mpc, 0.09, -0.045, coulomb=0.5)
    with pytest.raises(IdentificationError, match="did not move"):
        _sweep(stuck, force=0.3)
    with pytest.raises(ConfigError, match="--travel"):
        find_travel(ff.FireFader(), _Wire(stuck), travel=-1.0, force=0.3)


@pytest.mark.parametrize("argv,msg", [
    (["--travel", "98"], "--travel.*framed protocol has none.*--driver firefader"),
    (["--driver", "haply", "--travel", "98"], "--travel.*haply protocol.*--driver firefader"),
    (["--driver", "firefader", "--travel", "0"], r"--travel: must be a finite number > 0 \[mm\]"),
])
def test_identify_travel_is_checked(argv, msg, capsys):
    """hapsim identify --travel: refused before anything runs (exit 2) for a protocol
    without a position scale to find, and for a travel that is not a positive length;
    the message names the option and the valid choice."""
    import re

    from hapsim.cli import main
    assert main(["identify", *argv]) == 2
    assert re.search(msg, capsys.readouterr().err, re.S)
