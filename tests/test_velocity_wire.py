"""The velocity sensor over the wire (issue 14): SENSORS_REQUEST / SENSORS / VELOCITY
(PROTOCOL.md §4) between the mock, the host loops and ``hapsim run``.

What is checked: the mock offers the velocity and sends, just before each STATE, the exact
velocity of its physics at that sample; the host's ``velocity_sensor`` correction reads
those frames (in-process, lockstep pty, real-time pty) and measures what the analysis
predicts to 1e-6, with a rigid hand and with a grip spring; a device without the sensor (it
says so, or it predates the message) is refused in one line, exit 2; the compiled loop and
the Python loop agree bit for bit on a recorded stream with VELOCITY frames. The Hapkit
firmware's answer is tested on simavr in ``tests/test_firmware.py``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

import firmware_protocol as fp
from from_file import load_module  # same directory
from hapsim.analysis.loop import LoopModel
from hapsim.analysis.ths import render
from hapsim.emulated.mock import MockDevice
from hapsim.scene import Device, Excitation, parse_scene
from tolerance import rel_tol
from pty_device import PtyDevice

HERE = Path(__file__).resolve().parent

RIGID = "mass: 0.1, friction: 0.5"
GRIP = ("mass: 0.05, friction: 0.3, hand: {mass: 0.2, damping: 0.5, grip_stiffness: 2000, "
        "grip_damping: 1.0}")


def scene_text(body: str = RIGID, K: float = 300.0, B: float = 1.5,
               corr: str = "{kind: velocity_sensor}") -> str:
    return f"""
rate_hz: 1000
masses: [{{name: hand, kind: port}}, {{name: wall, kind: ground}}]
links: [{{name: wall, kind: spring_damper, between: [hand, wall], stiffness: {K},
          damping: {B}}}]
device: {{{body}, delay: 1, force_limit: 1000000.0, correction: {corr}}}
excitation: {{x0: 0.005}}
"""


# --------------------------------------------------------------------------- the mock

def test_mock_offers_velocity_and_sends_it_before_each_state_with_its_seq():
    """SENSORS answers requested & offered; then every STATE is preceded by the VELOCITY
    of the same seq whose value is the physics' velocity at that sample (the state the
    position is sampled from); a host that never asks gets none; a reset forgets it."""
    dev = Device(mass=0.1, friction=0.5, delay=1, hold="zoh", force_limit=100.0)
    m = MockDevice(dev, Excitation(x0=0.004, v0=-0.3), lockstep=False)
    m.handle(fp.Config(1000.0, 5000, 10.0), 0)
    st = m.tick(0)
    assert m.frames(st) == [st]                       # not asked: STATE only
    assert m.handle(fp.SensorsRequest(0xFFFF), 0) == [fp.Sensors(fp.SENSOR_VELOCITY,
                                                                 fp.SENSOR_VELOCITY)]
    for n in range(1, 40):
        v_at_sample = m.physics.v                     # before the tick advances it
        st = m.tick(1000 * n)
        vel, st2 = m.frames(st)
        assert st2 is st and vel == fp.Velocity(st.seq, (v_at_sample,))
        m.handle(fp.Force(st.seq, (-50.0 * st.position[0],)), 1000 * n + 100)
    assert m.handle(fp.SensorsRequest(0), 0) == [fp.Sensors(fp.SENSOR_VELOCITY, 0)]
    st = m.tick(50_000)
    assert m.frames(st) == [st]                       # turned off: STATE only again
    # the ideal hold has no velocity at the sample instant: not offered
    ideal = MockDevice(Device(mass=0.1, friction=0.5, delay=1, hold="ideal"), lockstep=True)
    assert ideal.handle(fp.SensorsRequest(fp.SENSOR_VELOCITY), 0) == [fp.Sensors(0, 0)]


def test_mock_velocity_sensor_model_quantum_and_noise():
    """``device.velocity_resolution`` rounds the sent velocity to its multiples (within half
    a quantum of the physics); ``device.velocity_noise`` adds seeded Gaussian noise of that
    standard deviation (sample std within 10 % over 4000 ticks), drawn apart from the
    position noise: the positions of a seed are the same with or without it."""
    def run(**kw):
        dev = Device(mass=0.1, friction=0.5, delay=1, hold="zoh", force_limit=100.0,
                     noise=1e-6, **kw)
        m = MockDevice(dev, Excitation(x0=0.004, v0=0.2), lockstep=False, seed=3)
        m.handle(fp.Config(1000.0, 5000, 10.0), 0)
        m.handle(fp.SensorsRequest(fp.SENSOR_VELOCITY), 0)
        xs, vs, true = [], [], []
        for n in range(4000):
            true.append(m.physics.v)
            st = m.tick(1000 * n)
            vel, _ = m.frames(st)
            xs.append(st.position[0])
            vs.append(vel.velocity[0])
            m.handle(fp.Force(st.seq, (-30.0 * st.position[0],)), 1000 * n + 100)
        return np.array(xs), np.array(vs), np.array(true)
    x0, v0, t0 = run()
    assert np.array_equal(v0, t0)                       # exact by default
    q = 1e-3
    xq, vq, tq = run(velocity_resolution=q)
    assert np.array_equal(xq, x0)
    # q round(v / q): half a quantum, plus the quotient's and the product's roundings
    # (derived; measured: half a quantum to 2 digits, the bound is reached)
    assert np.all(np.abs(vq - tq) <= q / 2 + rel_tol(2) * (np.abs(tq) + np.abs(vq)))
    # whole quanta to the product's and this quotient's roundings: derived
    n_max = float(np.max(np.abs(vq / q)))
    assert np.allclose(vq / q, np.round(vq / q), rtol=0, atol=rel_tol(2) * n_max) \
        and np.any(vq != tq)
    xn, vn, tn = run(velocity_noise=2e-3)
    assert np.array_equal(xn, x0)                       # position noise stream untouched
    # statistical: the sample deviation of 4000 normal draws has a relative standard
    # error of 1 / sqrt(2 x 3999) = 1.1 %, so 10 % is 8.9 of them (seed 3: measured
    # 0.023 %, margin 430)
    assert np.std(vn - tn) == pytest.approx(2e-3, rel=0.1)


def test_a_reset_device_forgets_the_request():
    from hapsim.emulated.faults import FaultPlan, FaultyDevice
    dev = Device(mass=0.1, friction=0.5, delay=1, hold="zoh", force_limit=100.0)
    m = MockDevice(dev, Excitation(x0=0.004), lockstep=False)
    fd = FaultyDevice(m, FaultPlan())
    fd.feed(fp.encode(fp.SensorsRequest(1)) + fp.encode(fp.Config(1000.0, 5000, 10.0)), 0)
    fd.tick(1000)
    host = fp.StreamDecoder()
    kinds = [type(x) for x in host.feed(fd.pop_due(2000))]
    assert kinds == [fp.Sensors, fp.Velocity, fp.State]
    fd.reset(3000)
    fd.feed(fp.encode(fp.Config(1000.0, 5000, 10.0)), 3000)
    fd.tick(4000)
    kinds = [type(x) for x in host.feed(fd.pop_due(5000))]
    assert kinds == [fp.Hello, fp.State]


# --------------------------------------------------------------------------- hapsim run

@pytest.mark.parametrize("body", [RIGID, GRIP], ids=["rigid", "grip"])
@pytest.mark.parametrize("transport", ["inprocess", "pty"])
def test_lockstep_velocity_sensor_over_the_wire_measured_equals_predicted(body, transport):
    """Lockstep, the correction fed by the VELOCITY frames only (no in-process shortcut:
    over the pty the mock is another process): measured (k, b) == render to 1e-6, one
    VELOCITY per STATE, none missing, no unknown frame."""
    from hapsim.pipeline.runner import run_scene
    sc = parse_scene(scene_text(body))
    rep = run_scene(sc, transport=transport, lockstep=True, handle_signals=False,
                    duration=1.0)
    r = render(LoopModel.from_device(sc.device, sc.rate_hz), 300.0, 1.5)
    assert r.stable
    # measured 3.3e-13 relative (generic 1.3e-13), margin 3e6
    assert rep["measured"]["k"] == pytest.approx(r.k, rel=1e-6)
    # measured 4.5e-13 relative (generic 7.7e-14), margin 2.2e6
    assert rep["measured"]["b"] == pytest.approx(r.b, rel=1e-6)
    vs = rep["loop"]["velocity_sensor"]
    assert vs["missing"] == 0 and vs["frames"] >= rep["loop"]["ticks"] > 0
    if transport == "pty":
        assert rep["loop"]["decoder"]["unknown_type"] == 0


def test_the_wire_velocity_is_what_the_correction_uses(monkeypatch):
    """A mock whose velocity sensor reads 0 makes the velocity_sensor wall a pure spring:
    the damping felt drops far below the prediction (the value on the wire is used)."""
    from hapsim.pipeline.runner import run_scene
    orig = MockDevice.frames

    def zero_velocity(self, state):
        out = orig(self, state)
        return [fp.Velocity(m.seq, (0.0,)) if type(m) is fp.Velocity else m for m in out]

    monkeypatch.setattr(MockDevice, "frames", zero_velocity)
    sc = parse_scene(scene_text(RIGID, B=3.0))
    rep = run_scene(sc, transport="inprocess", lockstep=True, handle_signals=False,
                    duration=1.0)
    r = render(LoopModel.from_device(sc.device, sc.rate_hz), 300.0, 3.0)
    assert rep["measured"]["b"] < 0.5 * r.b


def test_real_time_pty_run_reads_the_velocity_frames():
    """Real time over the pty (the mock ticks on its clock): every STATE answered had its
    VELOCITY (a pty loses nothing), and the loop ran to its end. No timing asserted."""
    from hapsim.pipeline.runner import run_scene
    sc = parse_scene(scene_text(RIGID))
    rep = run_scene(sc, transport="pty", lockstep=False, handle_signals=False, duration=0.5,
                    rt_priority=0)
    lp = rep["loop"]
    assert lp["ticks"] > 0 and lp["velocity_sensor"]["missing"] == 0
    assert lp["velocity_sensor"]["frames"] >= lp["ticks"]
    assert lp["decoder"]["unknown_type"] == 0


def test_a_reset_device_is_asked_again_when_the_loop_recovers():
    """A device reset mid-run (virtual clock, fault ``reset@400``) forgets the request; the
    loop's recovery asks again before CONFIG, so every STATE answered after it has its
    VELOCITY too (none missing) and the run goes to its end."""
    from hapsim.pipeline.runner import run_scene
    sc = parse_scene(scene_text(RIGID))
    rep = run_scene(sc, transport="sim", lockstep=False, handle_signals=False, duration=1.0,
                    faults="reset@400")
    lp = rep["loop"]
    assert lp["lost"] == lp["recovered"] == 1 and lp["ticks"] == 1000
    assert lp["velocity_sensor"]["missing"] == 0
    assert lp["velocity_sensor"]["frames"] >= lp["ticks"]


def test_link_check_counts_the_velocity_frame():
    """LINK rule with VELOCITY enabled: a STATE (31 bytes) and a VELOCITY (17 bytes) go up
    each tick, so at 115200 baud 8N1 250 Hz (under the 297 Hz of STATE alone) is refused for
    a velocity_sensor loop, naming the 48 bytes and 192 Hz, and accepted for a plain one."""
    from hapsim.host.loop import HostLoop, LoopConfig, MeasuredVelocity
    from hapsim.errors import ConfigError

    class _Tr:
        info = {"port": "/dev/null"}

    hello = fp.Hello(1, 1, 9, 1e-6, 1e-3, 10.0, 1000.0)
    for measured in (None, MeasuredVelocity()):
        loop = HostLoop(None, _Tr(), LoopConfig(rate_hz=250.0, n_samples=10), None, measured=measured)
        loop._link = fp.Link(115200, 10)
        if measured is None:
            loop._check_hello(hello)
            continue
        with pytest.raises(ConfigError) as info:
            loop._check_hello(hello)
        msg = str(info.value)
        assert "48-byte STATE + VELOCITY" in msg and "192 Hz" in msg and "115200 baud" in msg


class _OldDevice(PtyDevice):
    """A device on a pty master that answers HELLO_REQUEST and PING only (written before
    SENSORS_REQUEST), or, with ``answer``, also SENSORS(offered=0, enabled=0)."""

    def __init__(self, master: int, answer: bool) -> None:
        super().__init__(master, fp.encode(fp.Hello(1, 1, 9, 1e-6, 1e-3, 10.0, 1e3)))
        self.answer = answer
        self.requests = self.configs = 0

    def on_message(self, msg) -> None:
        t = type(msg)
        if t is fp.SensorsRequest:
            self.requests += 1
            if self.answer:
                os.write(self.master, fp.encode(fp.Sensors(0, 0)))
        elif t is fp.Config:
            self.configs += 1


@pytest.mark.parametrize("answer,why", [(True, "it answers SENSORS offered=0x0000"),
                                        (False, "no SENSORS answer to 3 requests")])
def test_run_refuses_velocity_sensor_on_a_device_without_it(tmp_path, capsys, answer, why):
    """``hapsim run --port`` with a velocity_sensor scene, against a device that says it has
    no velocity sensor or never answers (older firmware): exit 2, one error line naming the
    key and the reason, and no CONFIG was sent."""
    from hapsim.cli import main
    path = tmp_path / "vs.yaml"
    path.write_text(scene_text(RIGID))
    master, slave = os.openpty()
    dev = _OldDevice(master, answer)
    dev.start()
    try:
        code = main(["run", str(path), "--port", os.ttyname(slave), "--duration", "0.1"])
    finally:
        dev.done = True
        dev.join(2.0)
        os.close(slave)
        os.close(master)
    err = capsys.readouterr().err
    errors = [ln for ln in err.splitlines() if "error" in ln]
    assert code == 2, err
    assert len(errors) == 1 and "device.correction.kind" in errors[0], err
    assert "does not offer a velocity sensor" in errors[0] and why in errors[0]
    assert dev.requests == (1 if answer else 3) and dev.configs == 0


# --------------------------------------------------------------------------- compiled loop

def _compiled_helpers():
    return load_module(HERE / "test_compiled_loop.py", "_compiled_loop_helpers")


@pytest.mark.parametrize("seed", [1, 2])
def test_compiled_equals_python_on_a_recorded_stream_with_velocity(seed):
    """The recorded faulty stream of tests/test_compiled_loop.py with a VELOCITY before
    every STATE (some corrupted, some of 2 axes: handed to Python): the compiled loop takes
    the clean ones in its stretch and both loops send the same forces, log the same
    telemetry and report the same counters, bit for bit; the compiled count of samples is
    not inflated by the VELOCITY frames."""
    from hapsim.host.fastloop import warm_up
    h = _compiled_helpers()
    warm_up(h.Engine(h.prepare_scene(h.load_scene(h.WALL))[0]))   # compiled before the run
    rng = np.random.default_rng(seed)
    frames, usable = h.faulty_segment(rng, 100, 500)
    with_v = []
    for s, b in frames:
        if s >= 0:
            v = 0.01 * math.cos(s / 40.0)
            r = rng.random()
            vel = fp.encode(fp.Velocity(s, (v,) if r > 0.02 else (v, v)))
            if 0.02 <= r < 0.04:
                vel = bytearray(vel)
                vel[7] ^= 0x08                               # CRC catches it
                vel = bytes(vel)
            with_v.append((-1, vel))
        with_v.append((s, b))
    n = usable - 5
    a, b = h.both([h.chunked(with_v, rng)], n, passivity_controller=True, energy_limit=1.0)
    h.assert_same(a, b)
    res, loop = b[0], b[3]
    assert res.samples == n and loop.compiled_samples <= n
    assert res.decoder["bad_crc"] >= 1 and res.decoder["unknown_type"] == 0
