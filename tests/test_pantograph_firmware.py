"""The Hapkit pantograph: our firmware on two emulated ATmega328P joined on a TWI bus
(issue 23, item 6).

Everything here runs the real firmware ELFs (``firmware_protocol/firmware/pantograph``, the
leader and follower roles of one source, ``-Wall -Wextra -Werror``) cycle by cycle on two
simavr cores inside ``pantograph_board`` (lockstep: the emulated clock waits for each
FORCE, so the results do not depend on the machine's load). Skipped, with the reason,
only when avr-gcc, avr-libc or simavr's headers are not installed. The build is cached by
make (only what is older than its sources is rebuilt).
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import firmware_protocol as fp  # noqa: E402

SCENE = ROOT / "configs" / "pantograph_wall.yaml"
pytestmark = pytest.mark.xdist_group("pantograph_firmware")


@pytest.fixture(scope="module")
def built():
    from hapsim.emulated import hapkit_board as board, pantograph_board
    why = board.missing_tools()
    if why:
        pytest.skip(f"emulated Hapkit pantograph: {why}")
    return pantograph_board.build()


@pytest.fixture(scope="module")
def scene():
    from hapsim.scene import load_scene_nd
    return load_scene_nd(str(SCENE))


@contextmanager
def _board(tmp_path, scene, amplitude=2e-4, **kw):
    """The emulated pantograph on a new pty: yields (process, port, report path)."""
    from hapsim.emulated.pantograph_board import board_command
    report = tmp_path / f"board-{time.monotonic_ns()}.json"
    cmd = board_command(scene, amplitude, report=str(report), **kw)
    log = open(report.with_suffix(".log"), "w+")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith("PORT "), (line, log.seek(0) or log.read())
        yield proc, line.split()[1], report
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
        log.close()


def _plant(scene, torques, period):
    """``pantograph_board --plant-test``: the C plant from the home at rest, each row of
    ``torques`` (N, 2) [N m] held over one period; returns (N, 6): q1 q2 qd1 qd2 x y."""
    from hapsim.emulated.pantograph_board import BOARD, board_command
    cmd = [str(BOARD), "--plant-test"] + board_command(scene, 1e-8)[3:]
    text = "".join(f"{float(t1)!r} {float(t2)!r} {float(period)!r}\n" for t1, t2 in torques)
    r = subprocess.run(cmd, input=text, capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    return np.array([[float(v) for v in line.split()] for line in r.stdout.splitlines()])


def _hello(tr):
    tr.send(fp.HelloRequest(fp.PROTOCOL_VERSION))
    end = time.monotonic() + 5
    while time.monotonic() < end:
        for m in tr.receive(0.05):
            if isinstance(m, fp.Hello):
                return m
    raise AssertionError("no HELLO")


def _compact(tr, rate_hz=1000.0):
    """Ask the leader for the compact frames (SENSORS_REQUEST bit COMPACT) and enter the
    compact session on ``tr``; the leader must offer and enable them."""
    tr.send(fp.SensorsRequest(fp.FEATURE_COMPACT))
    end = time.monotonic() + 5
    while time.monotonic() < end:
        for m in tr.receive(0.05):
            if isinstance(m, fp.Sensors):
                assert m.offered == fp.FEATURE_COMPACT and m.enabled == fp.FEATURE_COMPACT
                tr.set_compact(rate_hz)
                return
    raise AssertionError("no SENSORS")


def _named(states, forces):
    """The torques each STATE says were held over its period: the FORCE its ``force_seq``
    names (zero before any was applied), from the STATEs alone (PROTOCOL.md §4)."""
    out = []
    for m in states:
        if m.status & fp.STATUS_FORCE_APPLIED:
            out.append(forces[m.force_seq])
        else:
            out.append((0.0, 0.0))
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_plant_matches_the_python_joint_space_model(built, scene, seed):
    """The board's five-bar dynamics (C) against hapsim.joint_device.JointDeviceND (Python,
    the model it transcribes) over random held torques: the same joints to 1e-9 rad over
    300 periods of motion of more than 0.01 rad."""
    from hapsim.joint_device import JointDeviceND
    rng = np.random.default_rng(seed)
    T = scene.period
    # a random bias and random changes of the held torques each period
    tau = rng.uniform(-1e-3, 1e-3, 2) + rng.uniform(-1.5e-3, 1.5e-3, (300, 2))
    c = _plant(scene, tau, T)
    ref = JointDeviceND(scene, np.asarray(scene.device.position, float), np.zeros(2),
                        substeps=2)
    q = np.empty((300, 2))
    qd = np.empty((300, 2))
    for k in range(300):
        J = ref.kin.jacobian(ref.q)
        ref.step(np.linalg.solve(J.T, tau[k]))      # J^T u = tau
        q[k], qd[k] = ref.q, ref.qd
    motion = np.max(np.abs(q - np.asarray(scene.device.joints)))
    assert motion > 1e-2
    # measured 4e-13 (generic 4e-13), margin 2500
    assert np.max(np.abs(c[:, :2] - q)) < 1e-9
    # measured 1.7e-11 (generic 1.7e-11), margin 5900
    assert np.max(np.abs(c[:, 2:4] - qd)) < 1e-7 * max(1.0, np.max(np.abs(qd)))
    x = np.array([ref.kin.forward(qq) for qq in q])
    # measured 2.3e-14 (generic 2.3e-14), margin 43000
    assert np.max(np.abs(c[:, 4:] - x)) < 1e-9


@pytest.mark.parametrize("frames", ["compact", "full"])
def test_follower_samples_reach_the_leader_in_order(built, scene, tmp_path, frames):
    """The follower's sensor samples cross the emulated TWI bus to the leader every tick and
    in order: each STATE's joint angles equal the plant's (the C plant driven by the
    PWM-exact torques each STATE names as held, force_seq) to within one sensor count,
    while the follower's joint sweeps hundreds of counts, several a tick; the follower's
    torque crosses the bus the other way (it moves that joint). Compact frames: every
    FORCE is applied one tick late (d = 1). Full frames: the 64 bytes and the binary64
    codec take the FORCE past the tick's DRIVE slot in most ticks (lockstep: the host
    answers at once), so it is applied a tick later, and the STATE says so (seq -
    force_seq = 2): the plant driven by what the STATEs name is still the one read."""
    from hapsim.host.transport import SerialTransport
    step = None
    states, q_read = [], []
    with _board(tmp_path, scene) as (proc, port, report):
        tr = SerialTransport(port)
        try:
            hello = _hello(tr)
            if frames == "compact":
                _compact(tr)
            step, c = hello.force_scale, hello.position_scale
            torque = [(0.0, 3 * step) if k < 60 else (0.0, -3 * step) for k in range(121)]
            tr.send(fp.Config(1000.0, 20000, 10.0))
            k = 0
            end = time.monotonic() + 20
            while k < 121 and time.monotonic() < end:
                for m in tr.receive(0.05):
                    if isinstance(m, fp.State) and m.status & fp.STATUS_ARMED and m.seq == k:
                        states.append(m)
                        q_read.append(m.position)
                        tr.send(fp.Force(m.seq, torque[k]))
                        k += 1
            tr.send(fp.Stop())
            time.sleep(0.1)
        finally:
            tr.close()
    rep = json.loads(report.read_text())
    assert [m.seq for m in states] == list(range(121))
    lags = {m.seq - m.force_seq for m in states if m.status & fp.STATUS_FORCE_APPLIED}
    if frames == "compact":
        assert lags == {1}
    else:
        assert lags <= {1, 2} and 2 in lags, lags
    assert rep["firmware"]["overrun"] == 0              # no tick moved by a DRIVE
    # the torques held over period k are the FORCE STATE k names; the plant's joints at
    # tick k + 1 are the ones read in STATE k + 1
    applied = _named(states, torque)[:120]
    q_read = q_read[:120]
    plant = _plant(scene, applied, scene.period)
    q_plant = np.vstack([np.asarray(scene.device.joints, float), plant[:119, :2]])
    err = np.abs(np.asarray(q_read) - q_plant)
    assert np.max(err) <= 1.01 * c, np.max(err) / c
    sweep = np.max(np.abs(q_plant[:, 1] - q_plant[0, 1])) / c
    assert sweep > 100
    assert np.max(np.abs(np.diff(q_plant[:, 1]))) / c > 3
    assert rep["twi"]["late_bytes"] == 0 and rep["twi"]["overflow"] == 0
    assert rep["twi"]["nack_address"] == 0 and rep["twi"]["nack_data"] == 0
    assert rep["firmware"]["faults"] == {} and rep["firmware"]["bad_frames"] == 0


def test_follower_nack_is_refused_cleanly(built, scene, tmp_path):
    """A follower gone from the bus (the board withholds its acknowledge from the 40th
    transaction after CONFIG on) is refused cleanly: the leader sends FAULT SENSOR once,
    naming the transaction NACKed, sends no armed STATE after it, and both motors stop (the
    leader's at once, the follower's by its own watchdog: nobody can reach it)."""
    from hapsim.emulated.pantograph_board import DEVICE_ID
    from hapsim.host.transport import SerialTransport
    faults, armed_after = [], 0
    with _board(tmp_path, scene, nack_after=40) as (proc, port, report):
        tr = SerialTransport(port)
        try:
            assert _hello(tr).device_id == DEVICE_ID
            tr.send(fp.Config(1000.0, 20000, 10.0))
            end = time.monotonic() + 10
            while time.monotonic() < end and not faults:
                for m in tr.receive(0.05):
                    if isinstance(m, fp.Fault):
                        faults.append(m)
                    elif isinstance(m, fp.State) and m.status & fp.STATUS_ARMED:
                        tr.send(fp.Force(m.seq, (0.004, -0.004)))
            t = time.monotonic()
            while time.monotonic() - t < 0.3:               # >= 30 ms of emulated time
                for m in tr.receive(0.05):
                    if isinstance(m, fp.Fault):
                        faults.append(m)
                    elif isinstance(m, fp.State) and m.status & fp.STATUS_ARMED:
                        armed_after += 1
        finally:
            tr.close()
    rep = json.loads(report.read_text())
    assert [f.code for f in faults] == [fp.FAULT_SENSOR], (faults, rep["firmware"],
                                                           rep["host"])
    assert faults[0].detail & 0xFF in (1, 2, 3)         # SYNC, READ or DRIVE NACKed
    assert armed_after == 0
    assert rep["twi"]["nack_address"] >= 1
    assert rep["drive"]["leader_steps"] == 0 and rep["drive"]["follower_steps"] == 0
    assert rep["emulated_s"] > 0


@pytest.mark.parametrize("frames", ["auto", "full"])
def test_lockstep_run_felt_matrices_against_the_stated_uncertainty(built, scene, tmp_path,
                                                                    frames):
    """hapsim run's measurement over the leader's UART (joint-level pantograph turned into
    the Cartesian device), lockstep, on configs/pantograph_wall.yaml with a = 0.2 mm. With
    the compact frames (what the host asks for) the delay is one tick and no tick is late;
    with the full ones every FORCE misses its DRIVE slot (the 1 kHz budget) and is applied
    a tick later, every tick: 149 late rows a record, each the known input its STATE names,
    and the measurement is as good (the account of late ticks against the firmware, every
    tick). Either way the measured felt matrices are within the stated
    uncertainty (the linearisation bound plus the wire's worst case: half a sensor count,
    half a PWM step) of the prediction, and the verdict says what the Hapkit's 10-bit
    sensor and 8-bit PWM allow: "not measurable" (the wire's term is above 0.25: one
    PWM step is ~0.035 N at the handle against ~0.04 N of force at this amplitude).
    Deterministic: the same deviation bit for bit run after run."""
    from hapsim.analysis.linearisation import linearisation_bound
    from hapsim.emulated.pantograph_board import JointLevelTransport, wire_term
    from hapsim.pipeline.felt_port import measure_felt_port
    from hapsim.host.transport import SerialTransport
    from hapsim.analysis.felt_matrices import felt_verdict
    a = 2e-4
    with _board(tmp_path, scene, a) as (proc, port, report):
        tr = JointLevelTransport(SerialTransport(port), scene)
        try:
            res = measure_felt_port(tr, scene, samples=150, frames=frames)
        finally:
            tr.close()
    assert tr.joint_level and tr.clamped == 0 and res["lost"] == 0
    if frames == "auto":
        assert res["frames"] == "compact"
        assert res["delay"] == [1] * 5 and res["late"] == 0
    else:
        assert res["frames"] == "full"
        assert res["delay"] == [2] * 5 and res["late"] == 5 * 149
    res["torque_max"] = tr.torque_max
    assert 0 < tr.torque_max < 0.5                       # a live loop, never full duty
    wire = wire_term(scene, res, tr.hello.position_scale, tr.hello.force_scale)
    bound = linearisation_bound(scene, max(a, res["excursion"]),
                                res["predicted"].render.rendered_poles)
    lin = bound.to_dict()
    dev = res["deviation"]
    for key in ("felt_stiffness", "felt_damping"):
        assert math.isfinite(wire[key])
        assert dev[key] <= lin[key] + wire[key], (key, dev, lin, wire)
    v = felt_verdict(dev, bound, wire)
    assert v["verdict"] == "not measurable"
    assert "too small for the wire's resolution" in v["reason"]
    assert res["excursion"] < scene_depth()


def scene_depth() -> float:
    """configs/pantograph_wall.yaml's handle depth into its wall [m] (the contact opens
    beyond it)."""
    return 5e-4


def test_mock_firmware_on_a_2d_scene_runs_in_real_time(built, tmp_path):
    """hapsim mock --firmware on a 2-D scene without --lockstep serves the emulated
    pantograph in real time (it was refused, exit 2, before the board had a real-time
    mode): HELLO, the compact frames, armed STATEs answered; its report says "realtime"
    and how the emulated clock held to the wall clock. --spin-us with --lockstep is
    refused (exit 2)."""
    from hapsim.host.transport import SerialTransport
    report = tmp_path / "mock.json"
    proc = subprocess.Popen([sys.executable, "-m", "hapsim", "mock", "--firmware", "--scene",
                             str(SCENE), "--report", str(report), "--rt-priority", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    armed = 0
    try:
        line = proc.stdout.readline()
        assert line.startswith("PORT "), (line, proc.stderr.read() if proc.poll() else "")
        tr = SerialTransport(line.split()[1])
        try:
            assert _hello(tr).n_axes == 2
            _compact(tr)
            tr.send(fp.Config(1000.0, 20000, 10.0))
            end = time.monotonic() + 10
            while armed < 50 and time.monotonic() < end:
                for m in tr.receive(0.05):
                    if isinstance(m, fp.State) and m.status & fp.STATUS_ARMED:
                        tr.send(fp.Force(m.seq, (0.0, 0.0)))
                        armed += 1
            tr.send(fp.Stop())
        finally:
            tr.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    assert armed >= 50
    rep = json.loads(report.read_text())
    assert rep["mode"] == "realtime" and rep["time"]["spin_us"] == 0   # the default
    # a host descheduled for 20 periods (a loaded machine) meets the leader's watchdog:
    # FAULT WATCHDOG (code 1) is the device's answer to it; nothing else may come
    assert set(rep["firmware"]["faults"]) <= {"1"} and rep["firmware"]["bad_frames"] == 0
    from inproc import hapsim_main        # refused before it starts anything: in this process
    code, _, err = hapsim_main(["mock", "--firmware", "--scene", str(SCENE), "--lockstep",
                                "--spin-us", "100"])
    assert code == 2 and "--spin-us" in err, err


def test_hostile_bytes_to_the_leader_are_dropped_counted_and_never_acted_on(built, scene,
                                                                           tmp_path):
    """Garbage, a corrupted FORCE_COMPACT (one bit flipped: its CRC fails) and an
    over-long frame sent to the leader between good FORCEs (a compact session) are dropped and counted (FAULT RX_ERRORS with
    the count, STATE's RX_ERROR), never applied: the torques stay the good FORCEs' (the
    follower's joint keeps its constant torque's motion, read as the plant's to one count;
    the corrupted FORCE's 0.3 N m, 146 PWM steps, would throw it off). The hostile bytes
    hold the wire longer than the tick's slack: the good FORCE behind them comes late and
    the torque held meanwhile is the same, its lag (seq - force_seq) above one."""
    import random
    from hapsim.host.transport import SerialTransport
    rng = random.Random(5)
    faults, q_read, lags, rx_err = [], [], set(), 0
    with _board(tmp_path, scene) as (proc, port, report):
        tr = SerialTransport(port)
        try:
            hello = _hello(tr)
            _compact(tr)                     # the session's frames: the hostile ones below
            c, tau = hello.position_scale, (0.0, 2 * hello.force_scale)
            tr.send(fp.Config(1000.0, 20000, 10.0))
            k = 0
            end = time.monotonic() + 20
            while k < 80 and time.monotonic() < end:
                for m in tr.receive(0.05):
                    if isinstance(m, fp.Fault):
                        faults.append(m)
                    elif isinstance(m, fp.State) and m.status & fp.STATUS_ARMED and m.seq == k:
                        q_read.append(m.position)
                        rx_err += bool(m.status & fp.STATUS_RX_ERROR)
                        if m.status & fp.STATUS_FORCE_APPLIED:
                            lags.add(m.seq - m.force_seq)
                        if k % 10 == 5:       # hostile bytes before this tick's FORCE
                            bad = bytearray(fp.encode(fp.compact_force(
                                fp.Force(m.seq, (0.3, -0.3)))))
                            bad[4] ^= 0x10
                            tr._ser.write(bytes(rng.randrange(1, 256) for _ in range(20))
                                          + b"\x00" + bytes(bad) + b"\x01" * 200 + b"\x00")
                        tr.send(fp.Force(m.seq, tau))
                        k += 1
            tr.send(fp.Stop())
            time.sleep(0.1)
        finally:
            tr.close()
    rep = json.loads(report.read_text())
    rx = [f for f in faults if f.code == fp.FAULT_RX_ERRORS]
    assert rx and rx_err > 0 and all(f.code == fp.FAULT_RX_ERRORS for f in faults)
    assert rx[-1].detail >= 8 * 2                       # >= 2 bad frames per burst, 8 bursts
    assert 1 in lags and max(lags) > 1                  # on time, and late behind the bytes
    applied = [(0.0, 0.0)] + [tau] * 79
    plant = _plant(scene, applied, scene.period)
    q_plant = np.vstack([np.asarray(scene.device.joints, float), plant[:79, :2]])
    assert np.max(np.abs(np.asarray(q_read) - q_plant)) <= 1.01 * c
    assert rep["drive"]["leader_steps"] == 0                # STOP zeroed it


def test_joint_level_transport_turns_angles_and_torques_into_the_cartesian_device(scene):
    """:class:`JointLevelTransport` against the kinematics: after the pantograph's HELLO a
    STATE's joint angles come out as f(q), a FORCE F answering it goes out as J(q)^T F;
    before that HELLO (or for another device) nothing is changed; a FORCE for a STATE not
    seen is an error, not a guess."""
    from hapsim.emulated.pantograph_board import DEVICE_ID, JointLevelTransport
    from hapsim.errors import DeviceError
    from hapsim.kinematics import device

    class Fake:
        def __init__(self):
            self.inbox, self.sent = [], []

        def receive(self, timeout=0.0):
            out, self.inbox = self.inbox, []
            return out

        def send(self, msg):
            self.sent.append(msg)

    kin = device("pantograph", scene.device.geometry)
    rng = np.random.default_rng(7)
    f = Fake()
    tr = JointLevelTransport(f, scene)
    q = tuple(float(v) for v in np.asarray(scene.device.joints) + rng.normal(0, 0.05, 2))
    f.inbox = [fp.State(3, 0, 1, 2, q)]
    assert tr.receive()[0].position == q                  # no HELLO yet: unchanged
    f.inbox = [fp.Hello(1, 2, DEVICE_ID, 1e-4, 2e-3, 1e30, 1000.0), fp.State(4, 0, 1, 3, q)]
    out = tr.receive()
    assert tr.joint_level
    # measured 0 (generic 0): exact on both targets
    assert np.allclose(out[1].position, kin.forward(np.array(q)), rtol=0, atol=1e-15)
    F = (0.7, -1.3)
    tr.send(fp.Force(4, F))
    tau = kin.jacobian(np.array(q)).T @ np.array(F)
    # measured 0 (generic 0): exact on both targets
    assert np.allclose(f.sent[-1].force, tau, rtol=1e-14, atol=0)
    with pytest.raises(DeviceError, match="answers no STATE"):
        tr.send(fp.Force(5, F))
    f.inbox = [fp.Hello(1, 2, 0x12345678, 0, 0, 1e300, 1000.0), fp.State(6, 0, 1, 5, q)]
    assert tr.receive()[1].position == q and not tr.joint_level


class QuantisedPantograph:
    """The Hapkit pantograph as a model, behind the transport interface (lockstep): the
    joint-space plant (:class:`hapsim.joint_device.JointDeviceND`), the sensors as the board
    and simavr quantise them (sensor voltage in millivolts, ``floor(mV 1023 / 5000)``) and
    the firmware reads them (flip counting, ``home + n c`` in binary32), the torques as the
    firmware quantises them (binary32, nearest PWM step) and the board applies them, FORCE n
    at tick n + 1, the hand's starts. No code of the firmware or the board: an independent
    statement of what they should do."""

    def __init__(self, scene, amplitude, hello):
        from hapsim.lockstep import excitation_starts
        self.scene, self.hello = scene, hello
        self.home = np.asarray(scene.device.joints, float)
        self.c = np.float32(hello.position_scale)
        tau_max = np.float32(np.float32(np.float32(0.03) * np.float32(0.073152))
                             / np.float32(0.004191))
        self.steps_per_nm = np.float32(np.float32(256.0) / tau_max)
        self.starts = excitation_starts(2, amplitude, scene.period)
        self.configs = 0
        self.out = []
        self.raw0 = self._raw(self.home)       # the firmware's zero: its first samples, home

    def _raw(self, q):
        theta = (q - self.home) * (0.073152 / 0.004191) + math.pi * 460 / 921
        phi = np.mod(theta, math.pi)
        counts = 51 + 921 * phi / math.pi
        mv = np.floor((counts + 0.5) * 5000 / 1023 + 0.5)
        return np.floor(mv * 1023 / 5000).astype(int)

    def _state(self):
        n = (self._raw(self.dev.q) - self.raw0).astype(np.float32)  # no flips: small records
        q = np.float32(self.home.astype(np.float32)) + n * self.c
        self.out.append(fp.State(self.k, 0, fp.STATUS_ARMED | fp.STATUS_CONFIGURED
                                 | (fp.STATUS_FORCE_APPLIED if self.k else 0),
                                 max(self.k - 1, 0), tuple(float(v) for v in q)))

    def send(self, msg):
        from hapsim.joint_device import JointDeviceND
        if isinstance(msg, fp.HelloRequest):
            self.configs = 0
            self.out.append(self.hello)
        elif isinstance(msg, fp.Config):
            x0, v0 = self.starts[self.configs % len(self.starts)]
            self.configs += 1
            rest = np.asarray(self.scene.device.position, float)
            self.dev = JointDeviceND(self.scene, rest + x0, v0, substeps=2)
            self.k, self.tau = 0, np.zeros(2)
            self._state()
        elif isinstance(msg, fp.Force):
            t = np.asarray(msg.force, float).astype(np.float32)
            a = np.abs(t) * self.steps_per_nm
            n = np.where(a >= 256, 256, (a + np.float32(0.5)).astype(np.int64))
            tau = np.where(t > 0, 1.0, -1.0) * n / 256 * 0.03 * 0.073152 / 0.004191
            J = self.dev.kin.jacobian(self.dev.q)
            # the torques of FORCE k - 1 held over period k (delay 1), J^T u = tau
            self.dev.step(np.linalg.solve(J.T, self.tau))
            self.tau = tau
            self.k += 1
            self._state()

    def receive(self, timeout=0.0):
        out, self.out = self.out, []
        return out

    def last_frames(self):
        return ""


def test_the_firmware_loop_is_the_quantised_model_loop(built, scene, tmp_path):
    """The 2-DoF loop closed over the firmware (two emulated ATmega328P on the TWI bus, the
    board's plant) and the same loop closed over :class:`QuantisedPantograph` (the model of
    the sensors, the firmware's arithmetic and the PWM, written from their specification):
    the same records, sample for sample, up to a sensor count where the model leaves out
    the few cycles between a PWM change and its ADC start and the hand's release (a
    rounding that falls the other way: from there the two quantised loops go their own
    ways): 85 % of the samples or more bit for bit (91 % here), and the same felt stiffness to 1 % (0.4 % here; the
    felt damping, which the readings' rounding alone may move by 39 times itself, differs
    by 12 % after one record's rounding went the other way). What the firmware renders is what the
    quantised model renders: the stated uncertainty is the quantisers', not the firmware's."""
    from hapsim.emulated.pantograph_board import JointLevelTransport
    from hapsim.pipeline.felt_port import measure_felt_port
    from hapsim.host.transport import SerialTransport
    a = 2e-4
    with _board(tmp_path, scene, a) as (proc, port, report):
        tr = JointLevelTransport(SerialTransport(port), scene)
        try:
            fw = measure_felt_port(tr, scene, samples=150)
        finally:
            tr.close()
    model = JointLevelTransport(QuantisedPantograph(scene, a, tr.hello), scene)
    md = measure_felt_port(model, scene, samples=150)
    c_handle = np.linalg.norm(model.kin.jacobian(np.asarray(scene.device.joints)), 2) \
        * tr.hello.position_scale
    same = 0
    for rf, rm in zip(fw["responses"], md["responses"]):
        d = np.max(np.abs(rf - rm), axis=1)
        first = np.flatnonzero(d > 1e-12)
        # identical up to a first difference of at most one count (a rounding that fell
        # the other way); from there the two quantised loops go their own ways
        if first.size:
            assert d[first[0]] <= 1.01 * c_handle, (first[0], d[first[0]] / c_handle)
        same += int(np.count_nonzero(d <= 1e-12))
    assert same >= 0.85 * 5 * 150, same                 # 685 of 750 here
    m1, m2 = fw["measured"]["felt_stiffness"], md["measured"]["felt_stiffness"]
    # not round-off: the quantised loops part where a rounding falls the other way;
    # measured 0.42 % of the largest entry (generic the same), margin 2.4
    assert np.max(np.abs(m1 - m2)) <= 0.01 * np.max(np.abs(m2)), (m1, m2)


def test_realtime_run_felt_verdict_holds_whatever_the_load(built, scene, tmp_path):
    """hapsim run's measurement against the emulated pantograph in real time (the board's
    clock locked to the wall clock, the host answering as it can: on a loaded machine
    some FORCEs miss their tick): every late tick is taken as the known input its STATE
    names (force_seq), so the verdict is the lockstep one's: never "differs" (the felt
    matrices within the stated uncertainty, or "not measurable" for the stated reason:
    here the Hapkit's sensor and PWM, as in lockstep). The compact frames are used (the
    leader offers them, the host asks a device whose HELLO gives a force step).

    The lateness guard is off here: this is the account's test, and the shipped wall is
    stable only at its own delay (1 period), so on a loaded machine the guard stops it
    as it stops a run ("the host's FORCEs came too late ...: a loaded machine?"; seen
    once in CI, "grow it x2.4"); its stops are tests/test_record_guard.py's."""
    from hapsim.analysis.linearisation import linearisation_bound
    from hapsim.emulated.pantograph_board import JointLevelTransport, wire_term
    from hapsim.pipeline.felt_port import measure_felt_port
    from hapsim.host.transport import SerialTransport
    from hapsim.analysis.felt_matrices import felt_verdict
    a = 2e-4
    with _board(tmp_path, scene, a, realtime=True) as (proc, port, report):
        tr = JointLevelTransport(SerialTransport(port), scene)
        try:
            res = measure_felt_port(tr, scene, samples=150, late_guard=False)
        finally:
            tr.close()
    rep = json.loads(report.read_text())
    assert rep["mode"] == "realtime"
    assert res["frames"] == "compact" and res["incomplete"] is None, res["incomplete"]
    # never before it is due; -1: a record in which no FORCE made its tick (a host starved
    # past the watchdog throughout it, seen once in a fresh-clone suite beside helpers'
    # work): the device held zero, every row past the delay a known input
    # (hapsim.pipeline.felt_port.measure_felt_port's docstring)
    assert all(d >= 1 or d == -1 for d in res["delay"]), res["delay"]
    res["torque_max"] = tr.torque_max
    wire = wire_term(scene, res, tr.hello.position_scale, tr.hello.force_scale)
    bound = linearisation_bound(scene, max(a, res["excursion"]),
                                res["predicted"].render.rendered_poles)
    v = felt_verdict(res["deviation"], bound, wire)
    assert v["verdict"] in ("within", "partly within", "not measurable"), \
        (v, res["late"], res["delay"])
    lin = bound.to_dict()
    for key in ("felt_stiffness", "felt_damping"):
        if lin[key] is not None:                 # None: beyond the bound's validity
            assert res["deviation"][key] <= lin[key] + wire[key], (key, res["late"])


def _replay(scene, hello, torques):
    """The joint readings of the Hapkit pantograph from rest under ``torques`` (N, 2) [N m]
    held over periods 0 .. N - 1, by the independent model of :class:`QuantisedPantograph`
    (joint-space plant, sensor and binary32 readings; the torques already whole PWM
    steps): readings at ticks 0 .. N, shape (N + 1, 2) [rad]."""
    from hapsim.joint_device import JointDeviceND
    qp = QuantisedPantograph(scene, 1e-8, hello)
    dev = JointDeviceND(scene, np.asarray(scene.device.position, float), np.zeros(2),
                        substeps=2)

    raws = [qp._raw(dev.q)]
    for tau in torques:
        J = dev.kin.jacobian(dev.q)
        dev.step(np.linalg.solve(J.T, np.asarray(tau, float)))
        raws.append(qp._raw(dev.q))
    # the firmware's flip counting: a step of more than half the span is a wrap
    raws = np.array(raws)
    step = np.diff(raws, axis=0)
    wraps = np.cumsum(np.where(step > 460, -921, np.where(step < -460, 921, 0)), axis=0)
    n = (raws - qp.raw0 + np.vstack([np.zeros((1, 2), int), wraps])).astype(np.float32)
    return (np.float32(qp.home.astype(np.float32)) + n * qp.c).astype(float)


def test_late_ticks_in_real_time_are_the_torques_the_states_name(built, scene, tmp_path):
    """A real-time host that answers some STATEs late on purpose (a 3 ms pause before
    every 12th FORCE, so that it and the ones queued behind it miss their DRIVE slot),
    never answers others, and sends hostile bytes before every 17th FORCE (garbage, a
    FORCE_COMPACT of 0.3 N m with one bit flipped, an over-long frame: dropped and counted,
    FAULT RX_ERRORS, never applied): the leader holds the older torques over those
    periods and each STATE names what it held (force_seq; zero under WATCHDOG_TRIPPED). The joint readings
    are those of an independent model (:class:`QuantisedPantograph`'s plant, sensor and
    binary32 readings) driven by the torques the STATEs name, to one count at every sample
    (a rounding that falls the other way) and exactly at half of them or more (five times as
    many as the on-time model); the same
    model driven by the on-time assumption (FORCE k over period k + 1) is off by more
    than two counts. The
    account (:func:`hapsim.applied.account_from_force_seq`) counts as late exactly the
    ticks whose named FORCE is not the one before."""
    from hapsim.applied import account_from_force_seq
    from hapsim.host.transport import SerialTransport
    import random
    rng = random.Random(11)
    N = 240
    states, faults = {}, []
    with _board(tmp_path, scene, realtime=True) as (proc, port, report):
        tr = SerialTransport(port)
        try:
            hello = _hello(tr)
            _compact(tr)
            s = hello.force_scale
            torque = [(s * (2 + k % 3), -s * (3 - k % 2)) if (k // 40) % 2 == 0 else
                      (-s * (2 + k % 3), s * (3 - k % 2)) for k in range(N + 5)]
            tr.send(fp.Config(1000.0, 20000, 10.0))
            end = time.monotonic() + 20
            while len(states) < N and time.monotonic() < end:
                for m in tr.receive(0.02):
                    if isinstance(m, fp.Fault):
                        faults.append(m)
                    if isinstance(m, fp.State) and m.status & fp.STATUS_ARMED \
                            and m.seq not in states and m.seq < N:
                        states[m.seq] = m
                        if m.seq % 12 == 5:
                            time.sleep(0.003)           # late on purpose
                        if m.seq % 17 == 3:             # hostile bytes
                            bad = bytearray(fp.encode(fp.compact_force(
                                fp.Force(m.seq, (0.3, -0.3)))))
                            bad[4] ^= 0x10
                            tr._ser.write(bytes(rng.randrange(1, 256) for _ in range(20))
                                          + b"\x00" + bytes(bad) + b"\x01" * 200 + b"\x00")
                        if m.seq % 29 != 13:            # never answered
                            tr.send(fp.Force(m.seq, torque[m.seq]))
            tr.send(fp.Stop())
            end = time.monotonic() + 0.1
            while time.monotonic() < end:
                faults += [m for m in tr.receive(0.02) if isinstance(m, fp.Fault)]
        finally:
            tr.close()
    rep = json.loads(report.read_text())
    rx = [f for f in faults if f.code == fp.FAULT_RX_ERRORS]
    assert rx and rx[-1].detail >= 2 * 10                # >= 2 bad frames a burst, 14 bursts
    assert {f.code for f in faults} <= {fp.FAULT_RX_ERRORS, fp.FAULT_WATCHDOG}
    seqs = sorted(states)
    assert seqs == list(range(len(seqs))) and len(seqs) >= 200, len(seqs)
    st = [states[k] for k in seqs]
    c = hello.position_scale
    named = [(0.0, 0.0) if (m.status & fp.STATUS_WATCHDOG_TRIPPED
                            or not m.status & fp.STATUS_FORCE_APPLIED)
             else torque[m.force_seq] for m in st]
    lag = np.array([m.seq - m.force_seq if m.status & fp.STATUS_FORCE_APPLIED else -1
                    for m in st])
    assert np.count_nonzero(lag >= 2) >= 10                # the late ones are named late
    assert rep["plant"]["bad_kinematics"] == 0
    # (no claim on OVERRUN here: a flood of hostile bytes after the board caught up with
    # the wall clock can keep the main loop from serving a tick in time, which the STATE
    # says; once in the full suite under load: what the torques did is the replay below)
    read = np.array([m.position for m in st])
    K = len(st)

    def compare(applied):
        model = _replay(scene, hello, applied[:K - 1])
        d = np.max(np.abs(read - model), axis=1)
        first = np.flatnonzero(d > 1e-12)
        return d, (first[0] if first.size else K)

    # the torques are not fed back: a period held with other torques than the ones named
    # moves the joints off for good (a growing difference), a rounding that falls the
    # other way (the model leaves out the cycles between a PWM change and its ADC start)
    # is one count at that sample only
    d, first = compare(named)
    assert np.max(d) <= 1.01 * c, (np.argmax(d), np.max(d) / c)
    # the on-time assumption, FORCE k - 1 over period k, is another motion
    naive = [(0.0, 0.0)] + [torque[k] for k in range(K - 1)]
    d_naive, _ = compare(naive)
    assert np.max(d_naive) > 2 * c, np.max(d_naive) / c
    # exact at most samples: how many roundings fall the other way depends on when in its
    # period each FORCE is served, so on the machine's load. Measured: 0.89 to 0.97 of the
    # samples quiet and beside two busy processes, 0.73 once in the full suite on 2 cores;
    # the on-time model 0.04 to 0.07 (exact only before the first late tick). The bound,
    # half, keeps a margin of 0.23 under the worst seen and is 7 times the on-time model's
    # (a reading is a whole number of counts c from home in both: a difference below half
    # a count is none)
    exact = np.count_nonzero(d < 0.5 * c)
    exact_naive = np.count_nonzero(d_naive < 0.5 * c)
    assert exact >= 0.5 * K and exact > 5 * exact_naive, (exact, exact_naive, K)
    # the account: late = a due tick whose named FORCE is not the one before it
    acc = account_from_force_seq(np.array(seqs), np.array([t[0] for t in torque[:K]]),
                                 np.array([m.force_seq for m in st]),
                                 np.array([m.status for m in st]))
    assert acc.delay == 1
    mine = np.array([k >= 1 and (lag[k] != 1 or bool(st[k].status
                                                      & fp.STATUS_WATCHDOG_TRIPPED))
                     for k in range(K)])
    assert np.array_equal(acc.late, mine)
