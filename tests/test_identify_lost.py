"""``identify`` whose device is lost during the excitation (a port that fails: unplugged,
its board gone). Before, any loss was the error alone and the record made was lost with
it. Now, as ``hapsim run``'s loss: the record up to the loss is fitted and reported, its
stop "device lost: ...", ``error`` its type and message, then the error on stderr and exit
1; a loss before the first row, or after too few rows to identify the device, is the
error alone, saying so (:func:`hapsim.pipeline.identify_run.record`,
:func:`hapsim.api.identifying.excite_and_fit`)."""

from __future__ import annotations

import json
import math
import random
from pathlib import Path

import pytest

from hapsim.api.identifying import identify
from hapsim.errors import DeviceError
from hapsim.scene import Device
from seeds import seeds  # same directory

#: The excitation's length in these tests [s] (at 1 kHz: 2,000 rows).
DURATION = 2.0


def _lose_from(monkeypatch, cls, at: int, op: str = "receive") -> list:
    """``cls.receive`` (or ``cls.send``: ``op``) fails from its ``at``-th call on, as a
    port unplugged fails (the transport's DeviceError); returns the call count (a
    one-item list)."""
    real = getattr(cls, op)
    calls = [0]

    def failing(self, *a, **k):
        calls[0] += 1
        if calls[0] >= at:
            raise DeviceError(("read" if op == "receive" else "write")
                              + " failed: [Errno 5] Input/output error")
        return real(self, *a, **k)
    monkeypatch.setattr(cls, op, failing)
    return calls


@pytest.mark.parametrize("seed", seeds(range(1, 25), kept=[1, 2, 5]))
def test_a_device_lost_mid_excitation_is_identified_from_its_record(seed, monkeypatch):
    """A random exact device (no noise, no quantum: its record determines it), the
    in-process lockstep mock's port failing at a random read, early (in the handshake or
    the first rows) or anywhere in the excitation. Lost before any row: the error alone.
    Lost after fewer rows than a fit needs: the error, saying how many rows it had and
    why they do not identify it. Later: the report, ``error`` a DeviceError's, the stop
    "device lost: ...", fewer rows than asked for, and the fit of those rows the device
    itself: m to 1e-6 relative and b0 to 1e-6 (the bound of the whole record's fit,
    ``tests/test_identify.py``: measured 2e-14, the optimiser's resolution) -- a record
    cut short is a shorter record, not a wrong one."""
    from hapsim.emulated.links import InProcessTransport
    rng = random.Random(seed)
    m = math.exp(rng.uniform(math.log(0.02), 0.0))
    b = rng.uniform(0.0, 5.0)
    d = rng.randrange(0, 4)
    dev = Device(mass=m, friction=b, delay=d, force_limit=10.0)
    at = rng.randrange(1, 260) if seed % 3 == 2 else rng.randrange(260, 2100)
    calls = _lose_from(monkeypatch, InProcessTransport, at)
    try:
        rep = identify(device=dev, transport="inprocess", duration=DURATION,
                       force_limit=4.0, max_delay=3, seed=seed)
    except DeviceError as exc:
        msg = str(exc)
        assert "Input/output error" in msg, msg
        assert at < 260, ("a loss late in the excitation is reported, not raised", at, msg)
        if "which do not identify it" in msg:
            n = int(msg.split("lost after ")[1].split()[0])
            assert 0 < n < at, (n, at, msg)
        return
    assert calls[0] >= at, "the port never failed"
    loop = rep.loop
    assert rep.error is not None and rep.error["type"] == "DeviceError", rep.error
    assert loop["stop_reason"].startswith("device lost: ") and loop["error"] == rep.error
    assert 0 < loop["samples"] < loop["requested"] == int(DURATION * 1000), loop
    fit = rep.fit
    # measured 2.4e-15 relative (generic 2.2e-15) over the 24 seeds, margin 4e8
    assert abs(fit.mass.value / m - 1) < 1e-6, (seed, m, fit.mass, loop["samples"])
    # measured 6.2e-14 (generic 6.5e-14) over the 24 seeds, margin 1.5e7
    assert abs(fit.friction.value - b) < 1e-6 * max(b, 1.0), (seed, b, fit.friction)
    assert rep.to_dict()["error"] == rep.error


def test_a_device_never_lost_reports_no_error():
    """The control: the same identification with no loss has no ``error`` in its report
    (the key left out of ``--json``) and the whole record."""
    rep = identify(device=Device(mass=0.1, friction=0.5, delay=1, force_limit=10.0),
                   transport="inprocess", duration=DURATION, force_limit=4.0, max_delay=3)
    assert rep.error is None and "error" not in rep.to_dict()
    assert rep.loop["samples"] == rep.loop["requested"] and rep.loop["error"] is None


@pytest.mark.parametrize("as_json", [False, True], ids=["text", "json"])
def test_hapsim_identify_reports_the_record_up_to_the_loss_then_the_error(as_json,
                                                                          monkeypatch):
    """``hapsim identify --lockstep`` (the embedded mock behind a pty), its port failing
    at the 1,200th read: the device file of the record up to the loss and its excitation
    line ("stop: device lost: ..., the fit is of the record up to the loss"), or the
    ``--json`` report with ``error``; then the error on stderr; exit 1."""
    from hapsim.host.transport import SerialTransport
    from inproc import hapsim_main
    _lose_from(monkeypatch, SerialTransport, 1200)
    args = ["identify", "--lockstep", "--duration", str(DURATION)]
    code, out, err = hapsim_main(args + (["--json"] if as_json else []))
    assert code == 1, (out, err)
    line = [ln for ln in err.splitlines() if ln.startswith("hapsim identify: ")]
    assert line and line[-1].startswith("hapsim identify: DeviceError: port failed: "
                                        "read failed: [Errno 5]"), err
    if as_json:
        rep = json.loads(out)
        assert rep["error"]["type"] == "DeviceError", rep.get("error")
        assert rep["loop"]["stop_reason"].startswith("device lost: ")
        assert 0 < rep["loop"]["samples"] < rep["loop"]["requested"]
        # the default mock's mass (0.1 kg) inside the interval the record up to the loss
        # states
        mass = rep["device"]["mass"]
        assert mass["lo"] <= 0.1 <= mass["hi"], mass
    else:
        assert "mass:" in out, out
        assert "stop: device lost: port failed" in out, out
        assert "the fit is of the record up to the loss" in out, out


def test_a_device_lost_with_the_added_mass_on_takes_no_scale(monkeypatch, capsys):
    """``hapsim identify --added-mass`` whose device is lost in the second identification
    (the mass on): the first identification is the report, no ``scale`` is taken from a
    record cut short, ``error`` is the loss's, then the error on stderr, exit 1 (the
    FireFader's driver mock in lockstep, its port failing at the second identification's
    900th write: its arming's 72 and the excitation's 1,000 ticks, lockstep, whatever
    the host's timing)."""
    import hapsim.api
    from hapsim.cli import main
    from hapsim.drivers.transport import DriverTransport
    real, calls, send = hapsim.api.identify, [], DriverTransport.send

    def second_lost(*a, **k):
        calls.append(1)
        if len(calls) == 1:
            monkeypatch.setattr(DriverTransport, "send", send)     # (a run before)
        else:
            _lose_from(monkeypatch, DriverTransport, 900, "send")
        return real(*a, **k)
    monkeypatch.setattr(hapsim.api, "identify", second_lost)
    argv = ["identify", "--driver", "firefader", "--mock-option", "full_scale=1.56",
            "--added-mass", "0.05", "--rate", "250", "--duration", "4", "--force-limit",
            "0.38", "--envelope", "0.02", "--lockstep", "--mock-scene",
            str(Path(__file__).resolve().parents[1] / "configs" / "firefader.yaml")]
    code = main(argv + ["--json"])
    out, err = capsys.readouterr()
    rep = json.loads(out)
    assert code == 1 and len(calls) == 2 and "loop" in rep, (code, out, err)
    assert "scale" not in rep and rep["error"]["type"] == "DeviceError", rep.get("error")
    assert rep["loop"]["stop_reason"] == "duration"     # (the first identification's)
    assert "hapsim identify: DeviceError: " in err, err
