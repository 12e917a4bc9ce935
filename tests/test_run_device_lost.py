"""A run whose device goes away for good still prints its report (text and JSON), keeps its
telemetry, then names the error on stderr and exits 1."""

from __future__ import annotations

import json
import re

import pytest

from hapsim.cli import main
from hapsim.pipeline.runner import run_scene
from hapsim.host.telemetry import load
from hapsim.errors import DeviceError
from hapsim.scene import load_scene
from test_daemon import late_tolerant_wall  # same directory (pytest prepend import mode)

# the port vanishes at tick 300 for 5 s; the host gives up reconnecting after 0.3 s
LOSE = ["--faults", "vanish@300:5s", "--reconnect-time", "0.3", "--rt-priority", "0",
        "--duration", "1"]         # 1000 ticks (the late-tolerant wall rings slower)


# The runs are real-time runs of what a run does when its device is lost, not of what it
# measures: they take the late-tolerant wall (test_daemon.late_tolerant_wall). On the
# shipped wall (stable at its own delay only) a loaded machine's late FORCEs could end a
# run on a safety stop before the port vanished (seen: 'force at the limit').


def test_json_report_of_a_run_that_lost_its_device(tmp_path, capsys):
    tel = str(tmp_path / "lost.npz")
    assert main(["run", late_tolerant_wall(tmp_path), *LOSE, "--telemetry", tel, "--json"]) == 1
    cap = capsys.readouterr()
    rep = json.loads(cap.out)
    lp = rep["loop"]
    why = (lp["stop_reason"], lp["faults"], lp["safety_stop"], lp["events"][-3:])
    assert "error" in rep, why
    assert rep["error"]["type"] == "DeviceError" and "device lost" in rep["error"]["message"]
    # (a loaded machine may add a loss it recovers from: the last one is for good)
    assert lp["lost"] >= 1 and lp["recovered"] == lp["lost"] - 1
    assert lp["reconnect_attempts"] >= 1 and lp["state"] in ("lost", "recovering")
    assert lp["stop_reason"].startswith("DeviceError: device lost")
    assert 0 < lp["ticks"] <= 300 and lp["ticks"] == rep["telemetry"]["samples"]
    assert [e["event"] for e in lp["events"]][-1] in ("lost", "attempt")
    assert lp["mock"] is not None                       # the mock's own counters too
    assert load(tel)["seq"].size == lp["ticks"]         # nothing recorded was lost
    assert "DeviceError: device lost" in cap.err and cap.err.index("closing the loop") < \
        cap.err.index("DeviceError")


def test_text_report_of_a_run_that_lost_its_device(tmp_path, capsys):
    assert main(["run", late_tolerant_wall(tmp_path), *LOSE]) == 1
    cap = capsys.readouterr()
    assert "predicted" in cap.out and re.search(r"\d+/1000 ticks", cap.out)
    assert "stop: DeviceError: device lost" in cap.out and re.search(r"faults: lost \d+", cap.out)
    assert "hapsim run: DeviceError: device lost" in cap.err


def test_library_callers_still_get_the_error_with_the_report_attached(tmp_path):
    with pytest.raises(DeviceError, match="device lost") as ei:
        run_scene(load_scene(late_tolerant_wall(tmp_path)), faults="vanish@300:5s",
                  reconnect_time=0.3, duration=1.0, rt_priority=0, handle_signals=False)
    rep = ei.value.report
    assert rep["exit_code"] == 1 and 0 < rep["loop"]["ticks"] <= 300
    assert rep["error"]["message"] == str(ei.value)
