"""A 2-D or 3-D run whose device goes away for good: as the 1-D run
(``tests/test_run_device_lost.py``), the measurement ends there with what was recorded,
says "device lost" and why, and exits 1 after its report; a device that never said HELLO is
the error alone. The 1-D run's recovery options (``--no-reconnect``, ``--reconnect-time``,
``--reconnect-attempts``) mean the same over an n-axis port.

The property runs the n-axis mock on a virtual clock (:class:`SimTransport`, seeded: never
timed) with its port vanishing, or its link stalling (the device silent: no frame at all),
at a random tick for a random time, against random recovery options, and sorts each case by
what the options allow: a vanish shorter than the first backoff step is always recovered, a
stall shorter than the silence that makes a loss (0.25 s) is no loss at all, and an outage
longer than every wait the options allow (and, for a stall, the HELLO's 3 s) is never
recovered.
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from hapsim.analysis.linearisation import linearisation_bound
from hapsim.emulated.faults import parse_faults
from hapsim.emulated.mock import MockDeviceND
from hapsim.emulated.links import SimTransport
from hapsim.errors import DeviceError
from hapsim.pipeline.felt_port import measure_felt_port, verdict_nd
from hapsim.scene import load_scene_nd

from seeds import seeds  # same directory (pytest prepend import mode)

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
SCENES = ("pantograph_wall.yaml", "pantograph_spring.yaml", "delta_sphere.yaml")
N = 150                         # STATEs per record: 5 or 7 records of 0.15 s


def _waits(attempts: int, backoff: float = 0.05, backoff_max: float = 1.0) -> float:
    """The time the first ``attempts`` reopening attempts have waited by their end [s]
    (:func:`hapsim.pipeline.port_session.reopen_port`'s doubling backoff)."""
    w, total = backoff, 0.0
    for _ in range(attempts):
        total += w
        w = min(2 * w, backoff_max)
    return total


def _case(seed: int):
    rng = random.Random(seed)
    name = rng.choice(SCENES)
    kind = rng.choice(["vanish", "stall"])
    tick = rng.randrange(50, 600)                        # inside the records
    outage = rng.choice([0.02, 0.3, 1.5, 4.0, 30.0] if kind == "vanish"
                        else [0.02, 0.1, 0.6, 4.0, 30.0])   # [s]
    reconnect = rng.random() < 0.8
    time_allowed = rng.choice([0.5, 2.0, 10.0])
    attempts = rng.choice([None, 1, 3, 8])
    return name, kind, tick, outage, reconnect, time_allowed, attempts


@pytest.mark.parametrize("seed", seeds(range(1, 41), kept=[1, 2, 3, 4, 8, 12, 35]))
def test_a_device_lost_for_good_ends_with_what_was_recorded_never_a_wrong_verdict(seed):
    """Random 2-D / 3-D scene, vanish or stall, tick, outage and recovery options.
    Always: a result (never an exception once the device said HELLO), ``stop`` "device
    lost" with ``error`` exactly when the device was not recovered, and then never a
    "within" verdict from rows the device did not send. A stall shorter than the silence
    is no loss; a vanish shorter than the first wait (0.05 s) is recovered whenever
    reconnect is on; an outage longer than every wait the options allow never is, and its
    attempts are no more than allowed; ``--no-reconnect`` tries none."""
    name, kind, tick, outage, reconnect, time_allowed, attempts = _case(seed)
    sc = load_scene_nd(CONFIGS / name)
    plan = parse_faults(f"{kind}@{tick}:{int(outage * 1000)}ms", seed)
    tr = SimTransport(MockDeviceND(sc, lockstep=False), plan)
    res = measure_felt_port(tr, sc, samples=N, reconnect=reconnect,
                            reconnect_time=time_allowed, reconnect_attempts=attempts)
    assert tr.device.plan.injected.get(kind) == 1
    lost = res["stop"] == "device lost"
    assert lost == (res["error"] is not None) == (res["counts"]["recovered"] < res["lost"])
    if kind == "stall" and outage < 0.25:
        assert res["lost"] == 0 and not lost, res["counts"]     # a pause, not a loss
    else:
        assert res["lost"] >= 1
    most = time_allowed if attempts is None else min(time_allowed, _waits(attempts))
    if kind == "stall":
        most = time_allowed + 3.0           # each HELLO asked waits 3 s for its answer
    if kind == "stall" and outage < 0.25:
        pass
    elif not reconnect:
        assert lost and res["counts"]["reconnect_attempts"] == 0
        assert "reconnect is off" in res["error"]["message"]
    elif outage < 0.05:
        assert not lost, res["error"]
    elif outage > most + 1.0:       # (+ the HELLO's and the port's own waits)
        assert lost, res["counts"]
        assert res["error"]["type"] == "DeviceError"
        assert "did not come back" in res["error"]["message"]
        if attempts is not None:
            assert res["counts"]["reconnect_attempts"] <= attempts
    res["bound"] = linearisation_bound(sc, max(1e-8, res["excursion"]),
                                       res["predicted"].render.rendered_poles)
    v = verdict_nd(res)
    if lost:
        assert v["verdict"] in ("not measurable", "within"), v
        if v["verdict"] == "not measurable":
            assert "device lost" in v["reason"], v["reason"]
    if v["verdict"] == "within":         # the rows kept are the device's own: exact
        assert max(res["deviation"].values()) < 1e-6, res["deviation"]
    else:
        assert res["deviation"] is None or lost


def test_a_device_that_never_said_hello_is_the_error_alone():
    """nohello with reconnect off: the DeviceError at once (after the HELLO's three
    requests), no result; with reconnect on, after the time allowed."""
    sc = load_scene_nd(CONFIGS / "pantograph_wall.yaml")
    for reconnect in (False, True):
        tr = SimTransport(MockDeviceND(sc, lockstep=False), parse_faults("nohello", 0))
        with pytest.raises(DeviceError, match="no HELLO"):
            measure_felt_port(tr, sc, samples=N, reconnect=reconnect, reconnect_time=1.0)
        assert tr.now_us < (4.5e6 if not reconnect else 9e6), tr.now_us


def _cli(argv, capsys):
    from hapsim.cli import main
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.xdist_group("realtime")
def test_hapsim_run_reports_a_2d_device_lost_then_exits_1(capsys):
    """Real time, the embedded mock's port gone at tick 300 for 30 s, the host allowed
    0.3 s: the report of what was recorded, "device lost", exit 1, then the error line on
    stderr; ``--no-reconnect --json`` the report's object with the error and no attempt
    (a device that never said HELLO raises: the error object, as every command's,
    ``tests/test_json_failures.py``); a stalled link past ``--lost-timeout`` is a loss
    too."""
    scene = str(CONFIGS / "pantograph_wall.yaml")
    lose = ["--faults", "vanish@300:30s", "--reconnect-time", "0.3"]
    code, out, err = _cli(["run", scene, *lose], capsys)
    assert code == 1, err
    assert "stopped: device lost" in out and "verdict: not measurable" in out, out
    assert "hapsim run: DeviceError: device lost" in err, err
    code, out, err = _cli(["run", scene, "--faults", "vanish@300:30s", "--no-reconnect",
                           "--json"], capsys)
    assert code == 1, err
    rep = json.loads(out)
    assert rep["stop"] == "device lost" and rep["verdict"] == "not measurable"
    assert rep["error"]["type"] == "DeviceError" and rep["lost"] == 1
    assert rep["counts"]["recovered"] == 0 and rep["counts"]["reconnect_attempts"] == 0
    assert "reconnect is off" in rep["error"]["message"]
    assert rep["port"]["faults_injected"] == {"vanish": 1}     # the mock asked to end
    # the device silent (its link stalled) for longer than --lost-timeout: a loss
    code, out, err = _cli(["run", scene, "--faults", "stall@300:30s", "--lost-timeout", "0.1",
                           "--no-reconnect", "--json"], capsys)
    assert code == 1, err
    rep = json.loads(out)
    assert rep["stop"] == "device lost" and "fell silent" in rep["error"]["message"]


@pytest.mark.xdist_group("realtime")
def test_the_api_returns_the_report_of_a_lost_device():
    """``hapsim.run`` of a 2-D scene whose device is lost for good: the RunReportND (not an
    exception), ``ok`` False, ``exit_code`` 1, ``error`` and ``stop`` set; a run to its end
    is ``ok``."""
    import hapsim
    scene = CONFIGS / "pantograph_wall.yaml"
    rep = hapsim.run(str(scene), faults="vanish@300:30s", reconnect_time=0.3)
    assert isinstance(rep, hapsim.RunReportND)
    assert not rep.ok and rep.exit_code == 1 and rep.stop == "device lost"
    assert rep.error["type"] == "DeviceError" and rep.verdict == "not measurable"
    rep = hapsim.run(str(scene), lockstep=True)
    assert rep.ok and rep.exit_code == 0 and rep.error is None


class _HostStalls(SimTransport):
    """A host descheduled once: before its ``at``-th read it does nothing for ``stall``
    seconds of the virtual clock while the device ticks on (its frames wait)."""

    def __init__(self, mock, at: int, stall: float) -> None:
        super().__init__(mock)
        self.at, self.stall, self.reads = at, stall, 0

    def receive(self, timeout):
        self.reads += 1
        if self.reads == self.at:
            self.sleep(self.stall)
        return super().receive(timeout)


@pytest.mark.parametrize("seed", seeds(range(1, 13), kept=[1, 2]))
def test_a_host_that_stalled_did_not_lose_its_device(seed):
    """The host stalls 0.3-2 s at a random read (the device's frames wait for it): a
    record may end there, but the device said something all along, so no loss is
    counted, HELLO is not asked again, and the run ends with every start recorded and
    measured = predicted to 1e-6 (the mock is exact)."""
    rng = random.Random(seed)
    sc = load_scene_nd(CONFIGS / rng.choice(SCENES))
    tr = _HostStalls(MockDeviceND(sc, lockstep=False), at=rng.randrange(20, 400),
                     stall=rng.choice([0.3, 0.6, 2.0]))
    res = measure_felt_port(tr, sc, samples=N, late_guard=False)
    assert tr.reads > tr.at                      # it stalled
    assert res["lost"] == 0 and res["stop"] == "end", res["counts"]
    assert res["counts"]["hellos"] == 0
    assert max(res["deviation"].values()) < 1e-6, res["deviation"]


class _Called(Exception):
    """The measurement's keyword arguments, raised by the spy below."""


@pytest.mark.parametrize("flags, want", [
    ([], {"frames": "auto", "reconnect": True, "reconnect_time": 10.0,
          "reconnect_attempts": 8, "lost_timeout": None, "late_guard": True}),
    (["--frames", "full", "--no-reconnect", "--reconnect-time", "2.5",
      "--reconnect-attempts", "3", "--lost-timeout", "0.4"],
     {"frames": "full", "reconnect": False, "reconnect_time": 2.5, "reconnect_attempts": 3,
      "lost_timeout": 0.4, "late_guard": True}),
    (["--frames", "compact"], {"frames": "auto"})], ids=["defaults", "given", "compact"])
def test_the_run_options_reach_the_measurement(monkeypatch, flags, want):
    """What ``hapsim run SCENE`` (2-D, over the embedded mock) hands
    :func:`measure_felt_port` for its frames and recovery options: the 1-D defaults, each
    option given, and ``--frames compact`` as ``auto`` (both the compact frames whenever
    offered). The spy stops the run at once; the mock's child is gone after it."""
    import hapsim.pipeline.felt_port as fp_mod
    from hapsim.cli import main

    def spy(transport, scene, **kw):
        raise _Called(kw)
    monkeypatch.setattr(fp_mod, "measure_felt_port", spy)
    with pytest.raises(_Called) as got:
        main(["run", str(CONFIGS / "pantograph_wall.yaml"), "--rt-priority", "0", *flags])
    kw = got.value.args[0]
    assert {k: kw[k] for k in want} == want, kw
