"""A live change asked from the view is checked while the view's measurement of the growing
record is still running (:meth:`hapsim.view.server.ViewServer.submit_measurement`): the
measurements have an analysis process of their own, so the change's stability checks
(four predictions in the controller's analysis process) never queue behind one. Before,
both shared the controller's one process; on a loaded machine (that process at nice 10)
a change once waited over 60 s for its reply (tests/test_view.py).

The measurement here waits for a file the test writes only after the change was answered:
with one shared process the change's checks would wait behind it until the controller's
timeout and the change would be refused, so the order alone decides (no timing)."""

from __future__ import annotations

import os
import time
import types

from hapsim.audio.control import Controller
from hapsim.engine import Engine
from hapsim.scene import parse_scene

WALL = """
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: 0.0}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000.0, damping: 1.5}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10.0}
excitation: {x0: 0.005}
"""


#: How long the controller waits for its checks [s] (a refusal after it: the test fails).
CHECK_TIMEOUT_S = 60.0


def wait_for_file(path: str, limit_s: float = 120.0) -> str:
    """Stand in for a long measurement: return once ``path`` exists (at most ``limit_s``).
    Module-level, so that the analysis child can import it."""
    end = time.monotonic() + limit_s
    while not os.path.exists(path) and time.monotonic() < end:
        time.sleep(0.01)
    return "released" if os.path.exists(path) else "timed out"


def test_a_live_change_is_answered_while_the_views_measurement_runs(tmp_path):
    from hapsim.spawn import StopFlag
    from hapsim.view.server import ViewServer
    sc = parse_scene(WALL)
    ctl = Controller(sc, Engine(sc), ramp_s=0.01)           # its own analysis child
    assert ctl.analyst.background
    ctl.analyst.timeout_s = CHECK_TIMEOUT_S
    server = ViewServer(types.SimpleNamespace(scene=sc), ctl, StopFlag())
    go = tmp_path / "go"
    got = []
    try:
        handle = server.submit_measurement(wait_for_file, (str(go),), got.append)
        assert server._measurer is not ctl.analyst
        ok, info = ctl.request("/hapsim/link/stiffness", "wall", 1100.0)
        assert ok, info
        assert not handle.ready()          # the measurement was still waiting meanwhile
        go.touch()
        handle.wait(60.0)
        assert got == ["released"]
    finally:
        go.touch()
        if server._measurer is not None:
            server._measurer.close()
        ctl.close()
