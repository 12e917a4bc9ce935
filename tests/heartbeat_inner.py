"""The inner test of ``tests/test_heartbeat.py`` (not collected by the suite: its name is
not ``test_*.py``): it waits ``HAPSIM_HEARTBEAT_WAIT`` seconds of wall clock."""

import os
import time


def test_waits_on_the_wall_clock():
    time.sleep(float(os.environ.get("HAPSIM_HEARTBEAT_WAIT", "0")))
