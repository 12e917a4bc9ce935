"""A lockstep FireFader mock's record measures the same whatever the host's wall clock did.

The FireFader's firmware zeroes its force after 0.1 s without a byte (the ``.ino``'s
silence rule, :data:`hapsim.drivers.firefader.SILENCE_S`), and the driver's account of the
applied forces (:meth:`hapsim.drivers.firefader.FireFader.account`) looks for such
silences between the rows. On the board's own clock they are the host's wall-clock gaps;
on a lockstep mock, stepped one period per command, they are not: its silence rule counts
commands (``hapsim.emulated.firefader_board``). Before, the account read the rows' wall
times on a lockstep mock too: the same record (identical positions and forces) of
``configs/firefader.yaml`` measured b within on a quiet host and not beside two CPU-bound
processes, where the host's gaps reached the silence's doubt band
(``tests/test_subsample.py``'s lockstep run, 1 of 3). Now the transport names the lockstep
mock's time per command (``Driver.command_period``) and the account uses it.

Checked over seeded records of the lockstep board: host stalls of random length and place
(0.08-0.5 s, as a descheduled host makes) added to the rows' times change nothing with a
command period; without one (a board on its own clock) the same stalls do change the
account, so the rule is still applied where it holds.
"""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.drivers import get_driver
from hapsim.drivers.firefader import SILENCE_DOUBT_S

RATE = 250.0


def _record(seed: int, n: int = 400):
    """A lockstep in-process FireFader board driven by random counts (its rows' positions
    [m] and each row's force [N]): test_drivers' drive, at the default full scale."""
    from test_drivers import ff_lockstep_drive
    return ff_lockstep_drive(0.05, None, n, seed)


def _account(x, force, times, command_period):
    drv = get_driver("firefader")
    drv.loop_delay = 1
    drv.command_period = command_period
    n = x.size
    acc = drv.account({"seq": np.arange(n), "time": times, "position": x,
                       "flags": np.zeros(n, np.int64)}, force)
    return None if acc is None else np.asarray(acc.applied, float)


@pytest.mark.parametrize("seed", range(6))
def test_host_stalls_change_nothing_on_a_lockstep_mock_and_count_on_a_board(seed):
    x, force = _record(seed)
    n = x.size
    rng = np.random.default_rng(100 + seed)
    quiet = np.arange(n) / RATE
    gaps = np.zeros(n)
    at = rng.choice(np.arange(5, n - 5), size=4, replace=False)
    gaps[at] = rng.uniform(SILENCE_DOUBT_S[0], 0.5, at.size)      # descheduled host
    stalled = quiet + np.cumsum(gaps)
    lock_quiet = _account(x, force, quiet, 1.0 / RATE)
    lock_stalled = _account(x, force, stalled, 1.0 / RATE)
    if lock_quiet is None:
        assert lock_stalled is None
    else:
        assert lock_stalled is not None and np.array_equal(lock_quiet, lock_stalled)
    # a board on its own clock: the stalls are its silences, and its force was zeroed
    # (or may have been) over them: the account says so
    own_quiet = _account(x, force, quiet, None)
    own_stalled = _account(x, force, stalled, None)
    assert own_stalled is not None
    base = force if own_quiet is None else own_quiet
    assert not np.array_equal(base, own_stalled)
