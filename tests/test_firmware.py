"""The Hapkit 3 reference firmware on the emulated ATmega328P (issue 11).

Everything here runs the real firmware ELF, built by avr-gcc with ``-Wall -Wextra
-Werror``, cycle by cycle on simavr inside ``hapkit_board`` (the board wires the handle's
physics to the chip's pins and its UART to a pty), in the fast clock mode (the emulated
clock waits for each FORCE, so the results do not depend on the machine's load). Skipped,
with the reason, only when avr-gcc, avr-libc or simavr's headers are not installed.

Run as a script (``python tests/test_firmware.py --host PORT FORCE``), the module is the
host the kill test kills: handshake, CONFIG, then a constant FORCE for every STATE.
"""

from __future__ import annotations

import json
import math
import os
import random
import select
import signal
import struct
import subprocess
import sys
import time
import tty
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import firmware_protocol as fp  # noqa: E402
from inproc import hapsim_main  # noqa: E402  (``hapsim run`` in this process: the host's side)

RATE = 1000.0
WATCHDOG_US = 5000


def _skip_reason():
    from hapsim.emulated import hapkit_board as board
    return board.missing_tools()


def _require():
    import pytest
    why = _skip_reason()
    if why:
        print(f"test_firmware: skipped: {why}")
        pytest.skip(f"emulated Hapkit board: {why}")


@contextmanager
def _board(tmp_path, elf=None, *extra):
    """The emulated board on a new pty: yields (process, port, report path)."""
    from hapsim.emulated import hapkit_board as board
    board.build()
    report = tmp_path / f"board-{time.monotonic_ns()}.json"
    cmd = [str(board.BOARD), str(elf or board.FIRMWARE_ELF), "--report", str(report), *extra]
    log = open(report.with_suffix(".log"), "w+")       # the board's stderr
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


def _report(report: Path) -> dict:
    return json.loads(report.read_text())


@contextmanager
def _descheduled(proc, every: float = 0.3, length: float = 0.12):
    """Stop the board's process for ``length`` seconds every ``every`` seconds (SIGSTOP,
    SIGCONT) while the block runs: a loaded machine's descheduling, made certain. In
    lockstep nothing the host or the board does may depend on it (a real-time host took a
    pause longer than its 50 ms silence limit for a lost device and re-CONFIGured the
    board mid-record: k = 493.0 once at load 10, 633.7 once at 4 kHz)."""
    import threading
    done = threading.Event()
    stops = [0]

    def run():
        while not done.wait(every):
            try:
                os.kill(proc.pid, signal.SIGSTOP)
                stops[0] += 1
                time.sleep(length)
            finally:
                os.kill(proc.pid, signal.SIGCONT)
    th = threading.Thread(target=run, daemon=True)
    th.start()
    try:
        yield stops
    finally:
        done.set()
        th.join()
        os.kill(proc.pid, signal.SIGCONT)


class _Host:
    """A minimal protocol host on a pty (the test's own, independent of hapsim's loop)."""

    def __init__(self, port: str) -> None:
        self.fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        self.dec = fp.StreamDecoder()

    def send(self, data: bytes) -> None:
        os.write(self.fd, data)

    def receive(self, timeout: float) -> list:
        r, _, _ = select.select([self.fd], [], [], timeout)
        return self.dec.feed(os.read(self.fd, 65536)) if r else []

    def wait_for(self, kind, timeout: float = 10.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in self.receive(0.05):
                if isinstance(m, kind):
                    return m
        raise AssertionError(f"no {kind.__name__} within {timeout} s")

    def arm(self, rate=RATE, watchdog_us=WATCHDOG_US, limit=5.0) -> fp.Hello:
        self.send(b"\x00" + fp.encode(fp.HelloRequest(fp.PROTOCOL_VERSION)))
        hello = self.wait_for(fp.Hello)
        self.send(fp.encode(fp.Config(rate, watchdog_us, limit)))
        return hello

    def armed_states(self, timeout: float = 30.0):
        """Yield each armed STATE (and collect the other messages in self.others)."""
        self.others = []
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in self.receive(0.05):
                if isinstance(m, fp.State) and m.status & fp.STATUS_ARMED:
                    yield m
                elif not isinstance(m, fp.State):
                    self.others.append(m)
        raise AssertionError("the device stopped sending armed STATEs")

    def close(self) -> None:
        os.close(self.fd)


# ---------------------------------------------------------------------------- build

def test_firmware_builds_warning_free_and_reports_flash_and_ram(tmp_path_factory):
    """``make -B`` rebuilds the firmware with -Wall -Wextra -Werror (a warning fails the
    build) and avr-size prints the flash and RAM it uses, within the ATmega328P's 32 KiB
    and 2 KiB. It rebuilds a scratch copy of the sources (same Makefile, same relative
    codec path): the shared ELF is never rewritten under a board another test (another
    pytest-xdist worker) is starting."""
    _require()
    import shutil
    from hapsim.emulated import hapkit_board as board
    scratch = tmp_path_factory.mktemp("fw")     # not tmp_path: its name holds "warning"
    work = scratch / "firmware" / "hapkit"
    shutil.copytree(board.FIRMWARE_DIR, work, ignore=shutil.ignore_patterns("*.elf", "*.hex"))
    shutil.copytree(board.ROOT.parent / "c", scratch / "c")
    r = subprocess.run(["make", "-B", "-C", str(work)], capture_output=True, text=True)
    out = r.stdout + r.stderr
    print(out)
    assert r.returncode == 0, out
    assert "-Wall -Wextra -Werror" in out and "-std=c99" in out and "warning" not in out
    flash = int(next(ln for ln in out.splitlines() if ln.startswith("Program:")).split()[1])
    ram = int(next(ln for ln in out.splitlines() if ln.startswith("Data:")).split()[1])
    assert 0 < flash < 32 * 1024 - 512 and 0 < ram < 2048 - 512, (flash, ram)



def test_a_second_build_waits_for_the_first_to_finish():
    """:func:`hapsim.emulated.hapkit_board.build` holds an exclusive ``flock`` on ``BUILD_LOCK``
    while make runs: another process's build (the other pytest-xdist worker's, a second
    ``hapsim mock --board``) waits however long the first takes, then finds everything up
    to date -- two builds never write one ELF together."""
    _require()
    import fcntl
    import pytest
    from hapsim.emulated import hapkit_board as board
    board.build()
    code = ("import sys; from hapsim.emulated import hapkit_board as board; print('start', flush=True); "
            "r = board.build(); print('built', r['elf'], flush=True)")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    with open(board.BUILD_LOCK, "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env=env)
        try:
            assert proc.stdout.readline().strip() == "start", proc.stderr.read()
            with pytest.raises(subprocess.TimeoutExpired):   # blocked while the lock is held
                proc.wait(timeout=1.0)
        except BaseException:
            proc.kill()
            proc.wait()
            raise
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert out.split() == ["built", str(board.FIRMWARE_ELF)], (out, err)


# ---------------------------------------------------------------------------- golden vectors

def _test_frame(packet: bytes) -> bytes:
    crc = fp.crc16(packet)
    from cobs import cobs
    return cobs.encode(packet + bytes([crc >> 8, crc & 0xFF])) + b"\x00"


def _test_reply(host: _Host, frame: bytes, kind: int) -> bytes:
    """Send one frame to the vectors build, return the body of its reply of type kind."""
    from cobs import cobs
    host.send(frame)
    buf = b""
    end = time.monotonic() + 10
    while time.monotonic() < end:
        r, _, _ = select.select([host.fd], [], [], 0.05)
        if r:
            buf += os.read(host.fd, 65536)
        if b"\x00" in buf:
            raw, _, buf = buf.partition(b"\x00")
            pk = cobs.decode(raw)
            assert fp.crc16(pk) == 0, pk.hex()
            assert pk[0] == kind, pk.hex()
            return pk[1:-2]
    raise AssertionError("no reply from the vectors build")


ERRORS = {"bad_cobs": -1, "bad_crc": -2, "overlong": -3, "unknown_type": -4, "malformed": -5}


def _f32_bits_of_f64_bits(bits: int) -> int:
    """binary64 -> binary32 (round to nearest even) by numpy, as bits."""
    import numpy as np
    with np.errstate(over="ignore"):
        return int(np.array([bits], dtype=np.uint64).view(np.float64).astype(np.float32)
                   .view(np.uint32)[0])


def test_golden_vectors_decode_and_encode_identically_on_the_avr(tmp_path):
    """Every golden frame, fed to the stream decoder on the emulated ATmega328P (32-bit
    double, f64 as bit patterns), decodes and re-encodes to the very same bytes; every bad
    vector is dropped with its error; and binary64 <-> binary32 conversion on the AVR
    equals numpy's (IEEE round to nearest even) bit for bit over edge cases and 300 seeded
    random patterns."""
    _require()
    from hapsim.emulated import hapkit_board as board
    vectors = json.loads((ROOT / "firmware_protocol/vectors/vectors.json").read_text())
    with _board(tmp_path, board.VECTORS_ELF) as (proc, port, _):
        host = _Host(port)
        try:
            for v in vectors["good"]:
                frame = bytes.fromhex(v["frame_hex"])
                body = _test_reply(host, frame, 0x7E)
                assert body[0] == 0, (v["name"], body[0])
                assert body[1:] == frame, (v["name"], body[1:].hex(), frame.hex())
            for v in vectors["bad"]:
                body = _test_reply(host, bytes.fromhex(v["frame_hex"]), 0x7E)
                assert struct.unpack("b", body[:1])[0] == ERRORS[v["error"]], v["name"]
            rng = random.Random(11)
            pats = [0, 1 << 63, 0x7FF0000000000000, 0xFFF0000000000000,
                    0x47EFFFFFE0000000, 0x47EFFFFFF0000000, 0x47EFFFFFEFFFFFFF,  # FLT_MAX ties
                    0x3FF0000010000000, 0x3FF0000030000000, 0x3FF0000010000001,  # ties to even
                    0x36A0000000000000, 0x3690000000000000, 0x3690000000000001,  # 2^-149, half
                    0x380FFFFFF0000000, 0x3810000000000000, 0x37FFFFFFFFFFFFFF,  # subnormal edge
                    0x0000000000000001, 0x7FEFFFFFFFFFFFFF, 0xC00921FB54442D18]
            pats += [rng.getrandbits(64) for _ in range(150)]
            pats += [(rng.getrandbits(1) << 63) | (rng.randrange(0x360, 0x480) << 52) |
                     rng.getrandbits(52) for _ in range(150)]     # the float32 range
            for i in range(0, len(pats), 10):
                chunk = pats[i:i + 10]
                body = _test_reply(host, _test_frame(
                    bytes([0x7D]) + b"".join(struct.pack("<Q", p) for p in chunk)), 0x7D)
                for j, p in enumerate(chunk):
                    f32, w = struct.unpack_from("<IQ", body, 12 * j)
                    want = _f32_bits_of_f64_bits(p)
                    is_nan = (p >> 52) & 0x7FF == 0x7FF and p & ((1 << 52) - 1)
                    if is_nan:   # a NaN stays a NaN with its sign
                        assert f32 & 0x7F800000 == 0x7F800000 and f32 & 0x7FFFFF, hex(p)
                        assert f32 >> 31 == p >> 63
                        continue
                    assert f32 == want, (hex(p), hex(f32), hex(want))
                    assert w == struct.unpack("<Q", struct.pack(
                        "<d", struct.unpack("<f", struct.pack("<I", f32))[0]))[0], hex(p)
        finally:
            host.close()


# ---------------------------------------------------------------------------- closed loop

def test_hapsim_run_closes_the_ths_over_the_firmware_uart(tmp_path):
    """``hapsim run configs/hapkit.yaml --port <emulated board>``: the felt (k, b) of the
    free response logged through the firmware's UART equal the THS prediction (m, b0 of the
    board, delay 1, zero-order hold) within the bound the ADC and PWM quantisation allow
    (:func:`hapsim.analysis.quantisation.quantisation_bound`: describing-function gains of the two
    quantisers over the window's amplitudes through the THS map, plus 4 standard
    deviations of the quantisation noise through the fit). No tick is late. The report's
    own measurement (:func:`hapsim.analysis.identify.measure_felt`, the position step from
    HELLO) agrees with the prediction within its stated interval."""
    _require()
    from hapsim.analysis import identify, quantisation
    from hapsim.analysis.loop import LoopModel
    from hapsim.emulated import hapkit_board as board
    from hapsim.host.telemetry import load
    from hapsim.scene import load_scene

    scene = load_scene(str(ROOT / "configs/hapkit.yaml"))
    dev = scene.device
    tel = tmp_path / "tel.npz"
    with _board(tmp_path, None, *board.board_command(dev, scene.excitation, lockstep=True)[2:]) as (
            proc, port, report), _descheduled(proc, every=0.1, length=0.1) as stops:
        # (stopped half the time: the run lasts at least twice the board's own time, three
        # stops in its first 0.6 s; at the default 0.3 s + 0.12 s a run of 0.9 s under the
        # whole suite's load saw two)
        # a subprocess: its start-up is part of the time the board is descheduled in (an
        # in-process run, ~0.7 s of wall clock, saw one stop of the three asked for)
        r = subprocess.run([sys.executable, "-m", "hapsim", "run", str(ROOT / "configs/hapkit.yaml"),
                            "--port", port, "--lockstep", "--duration", "1", "--json",
                            "--telemetry", str(tel)],
                           capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
                           timeout=120)
        assert r.returncode == 0, r.stderr
    assert stops[0] >= 3, stops      # the board was descheduled during the run
    # simavr's warnings (the firmware writes OCR1A before it sets Timer1's mode) are
    # counted in the board's report, not printed on the user's terminal
    assert report.with_suffix(".log").read_text() == ""
    assert _report(report)["simavr"]["warnings"] >= 1
    rep = json.loads(r.stdout)
    assert rep["loop"]["late"] == 0, rep["loop"]
    assert rep["loop"]["lost"] == 0 and rep["loop"]["recovered"] == 0, rep["loop"]
    assert rep["loop"]["device"]["force_limit"] == pytest_approx(board_force_max())
    t = load(str(tel))
    from hapsim.host.telemetry import FLAG_LOST, FLAG_RAMP
    assert not (t["flags"] & (FLAG_LOST | FLAG_RAMP)).any()   # one session, never restarted
    window = int(0.7 * RATE)
    x = t["position"][t["seq"] >= 4][:window]          # after the dead-beat transient
    assert x.size == window
    loop = LoopModel(mass=dev.mass, friction=dev.friction, rate_hz=scene.rate_hz,
                     delay=dev.delay, hold=dev.hold)
    link = scene.links[0]
    qx, qf = _scales()
    bound = quantisation.quantisation_bound(loop, link.stiffness, link.damping, scene.excitation.x0,
                                     window / RATE, qx, qf, window)
    meas = identify.fit_free_response(x, 1.0 / RATE, dev.mass, bound["k"], bound["b"])
    print(f"predicted k {bound['k']:.3f} b {bound['b']:.5f}; measured k {meas['k']:.3f} "
          f"b {meas['b']:.5f}; bound dk {bound['dk']:.3f} db {bound['db']:.5f} "
          f"(eps {bound['eps']:.4f}: d_x {bound['d_x']:.4f}, d_f {bound['d_f']:.4f})")
    assert rep["predicted"]["k"] == pytest_approx(bound["k"])
    assert abs(meas["k"] - bound["k"]) <= bound["dk"], (meas, bound)
    assert abs(meas["b"] - bound["b"]) <= bound["db"], (meas, bound)
    m = rep["measured"]
    print(f"run's report: k {m.get('k')} +- {m.get('k_interval')}, b {m.get('b')} +- "
          f"{m.get('b_interval')}: {m.get('verdict')}")
    assert abs(m["k"] - bound["k"]) <= bound["dk"] and abs(m["b"] - bound["b"]) <= bound["db"], m
    # the bound is a statement about this device, not a blanket: a few percent
    assert bound["dk"] < 0.05 * bound["k"] and bound["db"] < 0.1 * bound["b"], bound


def test_4khz_over_the_compact_frames_measured_equals_predicted(tmp_path):
    """The firmware at 4 kHz on its 2 Mbaud UART (lockstep board, ``hapsim run --port``):
    hapsim asks for the compact frames (one STATE and one FORCE in full take 96 % of the
    250 us period on the line) and the firmware takes them; its loop delay is 2 ticks (the
    ADC, 24 byte times and the chip's codec exceed one 4000-cycle period: PROTOCOL.md §4,
    "Compact frames"), which every STATE shows (no tick late against delay 2); the felt
    (k, b) of the free response, fitted here and in the run's report, equal the THS
    prediction at delay 2 within the bound the ADC and PWM quantisation allow
    (:func:`hapsim.analysis.quantisation.quantisation_bound`), as at 1 kHz."""
    _require()
    from hapsim.analysis import identify, quantisation
    from hapsim.analysis.loop import LoopModel
    from hapsim.emulated import hapkit_board as board
    from hapsim.host.telemetry import load
    from hapsim.scene import load_scene

    rate = 4000.0
    path = tmp_path / "hapkit_4khz.yaml"
    text = (ROOT / "configs/hapkit.yaml").read_text()
    text = text.replace("rate_hz: 1000", "rate_hz: 4000")
    text = text.replace("  delay: 1 ", "  delay: 2 ")
    assert "rate_hz: 4000" in text and "  delay: 2 " in text
    path.write_text(text)
    scene = load_scene(str(path))
    dev = scene.device
    tel = tmp_path / "tel.npz"
    with _board(tmp_path, None, *board.board_command(dev, scene.excitation, lockstep=True)[2:]) as (
            proc, port, report):
        code, out, err = hapsim_main(["run", str(path), "--port", port, "--lockstep",
                                      "--duration", "0.3", "--json", "--telemetry", str(tel)])
        assert code == 0, err
    rep = json.loads(out)
    assert rep["loop"]["frames"] == "compact", rep["loop"]
    assert rep["loop"]["late"] == 0 and rep["loop"]["missed"] == 0, rep["loop"]
    budget = _report(report)["budget"]
    assert budget["rate_hz"] == rate and not budget["saturated"]
    assert budget["busy_mean_cycles"] < 0.95 * budget["period_cycles"], budget
    t = load(str(tel))
    window = int(0.25 * rate)      # 2.8 cycles of the 11.3 Hz free response
    x = t["position"][t["seq"] >= 8][:window]
    assert x.size == window
    loop = LoopModel(mass=dev.mass, friction=dev.friction, rate_hz=rate, delay=2,
                     hold=dev.hold)
    link = scene.links[0]
    qx, qf = _scales()
    bound = quantisation.quantisation_bound(loop, link.stiffness, link.damping, scene.excitation.x0,
                                        window / rate, qx, qf, window)
    meas = identify.fit_free_response(x, 1.0 / rate, dev.mass, bound["k"], bound["b"])
    print(f"4 kHz: predicted k {bound['k']:.3f} b {bound['b']:.5f}; measured k "
          f"{meas['k']:.3f} b {meas['b']:.5f}; bound dk {bound['dk']:.3f} db {bound['db']:.5f}; "
          f"busy {budget['busy_mean_cycles']:.0f} of {budget['period_cycles']:.0f} cycles")
    assert rep["predicted"]["k"] == pytest_approx(bound["k"])
    assert abs(meas["k"] - bound["k"]) <= bound["dk"], (meas, bound)
    assert abs(meas["b"] - bound["b"]) <= bound["db"], (meas, bound)
    m = rep["measured"]
    print(f"run's report: k {m.get('k')} +- {m.get('k_interval')}, b {m.get('b')} +- "
          f"{m.get('b_interval')}: {m.get('verdict')}")
    assert abs(m["k"] - bound["k"]) <= bound["dk"] and abs(m["b"] - bound["b"]) <= bound["db"], m
    assert bound["dk"] < 0.05 * bound["k"] and bound["db"] < 0.1 * bound["b"], bound


def pytest_approx(v):
    import pytest
    # measured 8.2e-8 relative at most over its three uses, margin 12
    return pytest.approx(v, rel=1e-6)


def board_force_max() -> float:
    """HELLO.force_limit: the float32 of rs / rp * T_max / rh (hapkit_geometry.h)."""
    import numpy as np
    return float(np.float32(0.03 * 0.073152 / 0.004191 / 0.090 / 256) * np.float32(256))


def _scales():
    """HELLO's position and force scales, as the firmware computes them (float32)."""
    import numpy as np
    qx = float(np.float32(0.090 * 0.004191 / 0.073152 * 3.14159265358979 / 921))
    qf = float(np.float32(0.03 * 0.073152 / 0.004191 / 0.090 / 256))
    return qx, qf


# ---------------------------------------------------------------------------- identify

def test_identify_through_the_firmware_recovers_the_board_model(tmp_path):
    """``hapsim identify`` over the emulated board's pty (the firmware's own UART, its
    10-bit ADC with flip counting, float32 positions, the PWM's 22.7 mN steps): the board
    model's mass, viscous friction and Coulomb friction (configs/hapkit.yaml's device with
    fc = 0.1 N added) lie inside the reported 99.9 % intervals; the delay is the
    firmware's one sample with its zero-order hold; the encoder quantum found is the
    firmware's float32 position scale (one ADC count), although the float32 rounding
    makes the steps between far positions differ from it; and the model explains the
    data."""
    _require()
    import dataclasses

    from hapsim.commands.identify import identify
    from hapsim.emulated import hapkit_board as board
    from hapsim.scene import load_scene

    scene = load_scene(str(ROOT / "configs/hapkit.yaml"))
    dev = dataclasses.replace(scene.device, coulomb=0.1)
    exc = dataclasses.replace(scene.excitation, x0=0.0)
    # the emulated clock waits for each FORCE: a loaded host makes no late tick
    cmd = board.board_command(dev, exc, lockstep=True)[2:]
    with _board(tmp_path, None, *cmd) as (proc, port, report):
        fit, rec = identify(port=port, baud=2000000, driver="framed", rate_hz=RATE,
                            force_limit=1.0, envelope=0.02, duration=2.5, max_delay=3,
                            lockstep=True,    # the fast-clock board: a 1 s silence under
                            progress=False, handle_signals=False)   # load is no loss
    print(fit.verdict, rec["loop"])
    for name in ("mass", "friction", "coulomb", "coulomb_pos", "coulomb_neg",
                 "position_resolution", "noise"):
        e = getattr(fit, name)
        print(f"{name}: {e.value:.6g} [{e.lo:.6g}, {e.hi:.6g}] {e.unit}")
    assert rec["loop"]["late"] == 0 and not rec["loop"]["faults"], rec["loop"]
    assert rec["loop"]["stop_reason"] == "duration", rec["loop"]
    # The board integrates its Coulomb friction in 1 us steps (a reversal stops the
    # handle inside the period, hapkit_board.c), the fit's model at the samples: since
    # identify's excitation probes up from 1/64 of its level (a device that sticks near
    # its breakaway force), that sub-sample difference biases the fit by more than its
    # interval: mass +0.26 % against a half-width of 0.16 %, Coulomb -0.7 % (measured,
    # lockstep, deterministic). Open (issue 29's note): until the fit counts it, each
    # value within its interval widened by 1 % of the truth (a margin of 1.4 on the
    # worst).
    def near(e, truth):
        return e.lo - 0.01 * truth <= truth <= e.hi + 0.01 * truth
    assert near(fit.mass, dev.mass), fit.mass
    assert near(fit.friction, dev.friction), fit.friction
    for e in (fit.coulomb, fit.coulomb_pos, fit.coulomb_neg):
        assert near(e, 0.1), e
    assert fit.delay == 1 and fit.delay_range == (1, 1) and fit.hold == "zoh"
    qx, _ = _scales()
    assert fit.position_resolution.contains(qx), (fit.position_resolution, qx)
    assert fit.explained, fit.verdict
    # informative, not merely wide: a few percent on m and b0
    assert fit.mass.hi - fit.mass.lo < 0.05 * dev.mass, fit.mass
    assert fit.friction.hi - fit.friction.lo < 0.1 * dev.friction, fit.friction


# ---------------------------------------------------------------------------- board physics

def _step_response(tmp_path, force: float, ticks: int, *extra) -> list:
    """Positions of STATE 0..ticks with a constant FORCE answering every STATE."""
    with _board(tmp_path, None, "--x0", "0", *extra) as (proc, port, report):
        host = _Host(port)
        try:
            host.arm(limit=5.0, watchdog_us=50000)
            xs = []
            for st in host.armed_states():
                xs.append(st.position[0])
                host.send(fp.encode(fp.Force(st.seq, (force,))))
                if len(xs) > ticks:
                    return xs
        finally:
            host.close()


def test_board_physics_open_loop_step_is_the_exact_motion_within_one_count(tmp_path):
    """A constant FORCE from STATE 0 on (applied from tick 1, d = 1) moves the handle as
    m x'' + b0 x' = F does exactly (F the PWM step nearest 1 N), as read back through the
    emulated ADC and the firmware's flip counting over many half turns of the motor shaft:
    within half a sensor count, plus the 0.1-count millivolt rounding, plus the distance
    covered in the 5 us the tick interrupt takes to start the ADC, at every tick. With
    Coulomb friction above the force, the handle does not move at all."""
    _require()
    qx, qf = _scales()
    m, b0 = 0.1, 0.5
    f = round(1.0 / qf) * qf
    xs = _step_response(tmp_path, 1.0, 300, "--mass", str(m), "--friction", str(b0))
    for n, x in enumerate(xs):
        t = max(n - 1, 0) * 1e-3                  # force on from tick 1
        exact = f / b0 * t - f / b0 * (m / b0) * (1.0 - math.exp(-b0 * t / m))
        v = f / b0 * (1.0 - math.exp(-b0 * t / m))
        # derived (docstring): half a count, the 0.1-count millivolt rounding, 5 us of motion
        assert abs(x - exact) <= 0.61 * qx + v * 5e-6, (n, x, exact)
    assert xs[-1] / qx > 2 * 921                  # the shaft turned over several half turns
    stuck = _step_response(tmp_path, 1.0, 50, "--coulomb", "1.5")
    assert set(stuck) == {0.0}


# ---------------------------------------------------------------------------- watchdog

def _host_main(port: str, force: float) -> None:
    """The killable host: arm, then answer every STATE with a constant FORCE."""
    host = _Host(port)
    host.arm()
    n = 0
    for st in host.armed_states(timeout=60):
        host.send(fp.encode(fp.Force(st.seq, (force,))))
        n += 1
        if n == 200:
            print("ARMED 200", flush=True)


def test_lockstep_board_waits_for_a_slow_host_so_no_force_is_late(tmp_path):
    """In lockstep (fast) mode the emulated clock waits for the host's answer to each armed
    STATE however long the host takes: a host that pauses 0.2 s (a loaded machine) before
    some FORCEs still has every one applied at its tick (FORCE_APPLIED, force_seq = seq - 1,
    no OVERRUN). The board's wait was capped at 50 ms of wall time: a pause beyond made a
    late tick at random, and 1 lockstep run in 8 measured another stiffness."""
    _require()
    with _board(tmp_path) as (proc, port, report):
        host = _Host(port)
        try:
            host.arm()
            n = 0
            for st in host.armed_states():
                if n >= 2:
                    assert st.status & fp.STATUS_FORCE_APPLIED, st
                    assert st.force_seq == st.seq - 1 and not st.status & fp.STATUS_OVERRUN, st
                if n in (3, 7):
                    time.sleep(0.2)
                host.send(fp.encode(fp.Force(st.seq, (0.01,))))
                n += 1
                if n == 12:
                    break
            host.send(fp.encode(fp.Stop()))
        finally:
            host.close()
    assert _report(report)["host"]["wait_timeouts"] == 0


def _lockstep_record(tmp_path, elf, wait_s: float, ticks: int) -> list:
    """One lockstep session at 4 kHz in compact frames on a new board: HELLO, the handle
    at rest at x0 in the disarmed STATEs, ``wait_s`` of wall time (the board paces the disarmed firmware in real time meanwhile, so the CONFIG
    reaches it at a cycle the wall clock chose), CONFIG, then every STATE answered with a
    spring FORCE (-500 N/m x) for ``ticks`` ticks. Returns the (seq, status, force_seq,
    position) of each armed STATE."""
    with _board(tmp_path, elf) as (proc, port, report):
        host = _Host(port)
        try:
            host.send(b"\x00" + fp.encode(fp.HelloRequest(fp.PROTOCOL_VERSION)))
            host.wait_for(fp.Hello)
            # the hand has brought the handle to x0 (the disarmed STATEs stay there): a
            # CONFIG during that move would let go at the move's end, a wall-chosen cycle
            still, last = 0, None
            while still < 10:
                st = host.wait_for(fp.State)
                x = st.position[0]
                still = still + 1 if x == last and abs(x - 0.005) < 1e-4 else 0
                last = x
            host.send(fp.encode(fp.SensorsRequest(fp.FEATURE_COMPACT)))
            assert host.wait_for(fp.Sensors).enabled & fp.FEATURE_COMPACT
            host.dec.expander = fp.CompactExpander(4000.0)
            time.sleep(wait_s)
            host.send(fp.encode(fp.Config(4000.0, 5000, 5.0)))
            rows = []
            for st in host.armed_states():
                rows.append((st.seq, st.status, st.force_seq, st.position[0]))
                f = fp.Force(st.seq, (-500.0 * st.position[0],))
                host.send(fp.encode(fp.compact_force(f)))
                if len(rows) == ticks:
                    break
            host.send(fp.encode(fp.Stop()))
        finally:
            host.close()
    return rows


def test_lockstep_is_bit_for_bit_the_same_whatever_cycle_the_config_comes_at(tmp_path):
    """Two lockstep sessions of the same device give the same STATEs bit for bit, although
    their CONFIGs reach the firmware at cycles the wall clock chose (the board paces a
    disarmed firmware in real time): the firmware restarts its tick clock and its PWM
    carrier together at CONFIG. With the carrier left free-running since reset, simavr woke
    the sleeping core on the carrier's events at another phase in each run: a tick
    interrupt entered one cycle apart, and 4 kHz runs differed by one ADC count in 22-87
    of 1200 samples."""
    _require()
    ticks = 500
    # each wait puts the CONFIG at another cycle (without the fix, 5 pairs in 8 differed
    # within 500 ticks: three pairs miss it with probability ~5 %)
    a = _lockstep_record(tmp_path, None, 0.0, ticks)
    assert len(a) == ticks
    assert len({r[3] for r in a}) > 20                # the handle oscillates: a real record
    for wait in (0.0031, 0.0123, 0.0257):
        b = _lockstep_record(tmp_path, None, wait, ticks)
        diff = [i for i, (u, v) in enumerate(zip(a, b)) if u != v]
        assert len(b) == ticks and not diff, (wait, len(diff), [(a[i], b[i]) for i in diff[:3]])


def test_the_board_trace_times_each_state_and_the_force_answering_it(tmp_path):
    """``hapkit_board --trace``: a lockstep session of 60 answered ticks leaves, per tick,
    the STATE, the FORCE read from the pty and handed to the UART, and the tick edges, so
    that ``tools/bench_firmware.py``'s summary finds every tick answered and applied (no
    late, no unanswered tick in lockstep), the STATE leaving within the period after its
    tick (the full frames' codec: 411-549 us measured), and each FORCE reaching the UART
    before the next tick (the deadline: the smallest slack of an applied FORCE)."""
    _require()
    sys.path.insert(0, str(ROOT / "tools"))
    import bench_firmware
    trace = tmp_path / "trace.txt"
    with _board(tmp_path, None, "--trace", str(trace)) as (proc, port, report):
        host = _Host(port)
        try:
            host.arm()
            n = 0
            for st in host.armed_states():
                host.send(fp.encode(fp.Force(st.seq, (0.01,))))
                n += 1
                if n == 60:
                    break
            host.send(fp.encode(fp.Stop()))
        finally:
            host.close()
    s = bench_firmware.trace_summary(trace, RATE)
    assert s["ticks"] >= 55 and s["late"] == 0 and s["unanswered"] == 0, s
    assert 0 < s["state_out_us"][0] < 1e6 / RATE, s
    assert 0 < s["deadline_us"] < 1e6 / RATE - s["state_out_us"][0], s
    kinds = {ln.split()[0] for ln in trace.read_text().splitlines()}
    assert {"T", "A", "P", "S", "R", "F"} <= kinds, kinds
    assert _report(report)["time"]["trace_dropped"] == 0


def test_a_second_run_starts_at_x0_after_the_handle_was_pushed_far(tmp_path):
    """A run pushes the handle 0.1-0.3 m away (many sensor periods), then STOPs: the
    board's hand brings it back to x0 over many ticks, no jump, so the firmware's flip
    counting follows, and the next run's first armed STATE reads x0 (to one ADC count).
    The board placed the handle at x0 at once at CONFIG before: the firmware counted the
    wrong number of turns and a second run started 0.27 m away with 18 J stored."""
    _require()
    qx, _ = _scales()
    x0 = 0.005
    with _board(tmp_path) as (proc, port, report):
        host = _Host(port)
        try:
            host.arm()
            far = None
            for n, st in enumerate(host.armed_states()):
                host.send(fp.encode(fp.Force(st.seq, (-3.0,))))
                if n == 150:
                    far = st.position[0]
                    break
            host.send(fp.encode(fp.Stop()))
            assert far is not None and far < x0 - 0.1, far        # far beyond one period
            end = time.monotonic() + 20.0
            back = last = None
            while back is None and time.monotonic() < end:
                for m in host.receive(0.05):
                    if isinstance(m, fp.State):
                        last = m
                    if (isinstance(m, fp.State) and not m.status & fp.STATUS_ARMED
                            and abs(m.position[0] - x0) <= qx):
                        back = m
            assert back is not None, ("the handle did not come back to x0", last)
            host.send(fp.encode(fp.Config(RATE, WATCHDOG_US, 5.0)))
            first = next(host.armed_states())
            assert abs(first.position[0] - x0) <= qx, (first, far)
            host.send(fp.encode(fp.Stop()))
        finally:
            host.close()


def test_killed_host_pwm_pin_at_zero_within_one_watchdog_period(tmp_path):
    """SIGKILL the host mid-run: the PWM pin (its duty, read from OC0B and PORTD5 by the
    board) falls to zero within one watchdog period of the last valid FORCE, measured in
    emulated time, and the firmware sends FAULT WATCHDOG; it had held the force until
    then (zero-order hold)."""
    _require()
    with _board(tmp_path) as (proc, port, report):
        host = subprocess.Popen([sys.executable, __file__, "--host", port, "1.0"],
                                stdout=subprocess.PIPE, text=True,
                                env={**os.environ, "PYTHONPATH": str(ROOT)})
        try:
            assert host.stdout.readline().strip() == "ARMED 200"
            host.send_signal(signal.SIGKILL)
        finally:
            host.wait(timeout=10)
        time.sleep(1.0)  # the emulation runs on, free, once the port has no reader
    rep = _report(report)
    pin, h = rep["pin"], rep["host"]
    print(json.dumps(rep))
    assert h["watchdog_us"] == WATCHDOG_US and h["last_force_n"] == 1.0
    assert rep["emulated_s"] * 1e6 > h["last_force_us"] + 4 * WATCHDOG_US
    assert pin["force_now_n"] == 0.0
    assert pin["last_nonzero_us"] > h["last_force_us"]          # the force was held ...
    assert 0 < pin["zero_since_us"] - h["last_force_us"] <= WATCHDOG_US   # ... not too long
    assert rep["firmware"]["faults"].get(str(fp.FAULT_WATCHDOG), 0) >= 1


# ---------------------------------------------------------------------------- bad frames

def test_garbage_and_bit_flips_are_dropped_counted_and_never_applied(tmp_path):
    """Seeded garbage and single-bit flips of FORCE frames, sent on the emulated UART
    between good FORCEs of 0.5 N: the firmware counts every one (FAULT RX_ERRORS detail,
    RX_ERROR in STATE), applies none of them (they carry 0.9 N; the pin never shows more
    than the 0.5 N PWM step), and the force on the pin never exceeds the 1 N limit."""
    _require()
    rng = random.Random(5)
    good, bad_value, limit = 0.5, 0.9, 1.0
    injected = 0
    with _board(tmp_path) as (proc, port, report):
        host = _Host(port)
        try:
            host.arm(limit=limit)
            for n, st in enumerate(host.armed_states()):
                out = bytearray()
                if n % 3 == 1:      # garbage: random non-zero bytes, then a delimiter
                    out += bytes(rng.randrange(1, 256) for _ in range(rng.randrange(1, 40)))
                    out += b"\x00"
                    injected += 1
                if n % 3 == 2:      # a FORCE with one bit flipped (never into a 0x00)
                    f = bytearray(fp.encode(fp.Force(st.seq, (bad_value,))))
                    while True:
                        i, b = rng.randrange(len(f) - 1), 1 << rng.randrange(8)
                        if f[i] ^ b:
                            break
                    f[i] ^= b
                    out += f
                    injected += 1
                out += fp.encode(fp.Force(st.seq, (good,)))
                host.send(bytes(out))
                if n >= 300:
                    break
            seen = [m for m in host.others if isinstance(m, fp.Fault)]
            # the last FAULT RX_ERRORS arrives with the STATE after the last bad frame
            for st in host.armed_states():
                if any(isinstance(m, fp.Fault) for m in host.others):
                    seen += [m for m in host.others if isinstance(m, fp.Fault)]
                if st.seq > 310:
                    break
                host.send(fp.encode(fp.Force(st.seq, (good,))))   # lockstep: answered
        finally:
            host.close()
    rep = _report(report)
    counts = [m.detail for m in seen if m.code == fp.FAULT_RX_ERRORS]
    assert counts and max(counts) == injected, (counts, injected)
    assert rep["firmware"]["fault_rx_errors_detail"] == injected
    assert rep["firmware"]["states_rx_error"] >= 1
    step = rep["pin"]["force_step_n"]
    assert rep["pin"]["max_abs_force_n"] <= limit
    assert abs(rep["pin"]["max_abs_force_n"] - good) <= step / 2, rep["pin"]


# ---------------------------------------------------------------------------- link capacity

def test_a_rate_the_link_cannot_carry_is_refused_naming_baud_and_frame_bytes(tmp_path):
    """The firmware sends LINK (2 Mbaud, 10 bits per byte) with HELLO; ``hapsim run`` at
    8 kHz (31-byte STATEs need 2.48 Mbit/s) is refused before CONFIG with exit 2 and a
    message naming the baud, the frame bytes and the largest rate, 0.8 * 2e6 / 310 Hz."""
    _require()
    with _board(tmp_path) as (proc, port, report):
        code, out, err = hapsim_main(["run", str(ROOT / "configs/hapkit.yaml"), "--port", port,
                                      "--rate", "8000", "--duration", "0.1"])
    assert code == 2, (code, err)
    msg = err
    top = fp.link_max_rate(2000000, 10, 1)
    assert top == 0.8 * 2e6 / 310
    for part in ("rate_hz", "8000 Hz", "2000000 baud", "31-byte STATE", "17-byte FORCE",
                 f"{top:.0f} Hz"):
        assert part in msg, (part, msg)
    assert _report(report)["host"]["frames_ok"] >= 1          # it asked HELLO ...
    assert _report(report)["budget"]["rate_hz"] == 0          # ... and never sent CONFIG



def test_a_host_asking_for_velocity_hears_none_offered_and_the_firmware_still_works(tmp_path):
    """The Hapkit 3 measures position only: SENSORS_REQUEST(VELOCITY) is answered
    SENSORS(offered COMPACT only, enabled 0) and no VELOCITY frame is ever sent; a host that
    asks for the velocity alone (an old host, written before the compact frames) keeps the
    full STATE frames; the session goes on as before (CONFIG arms it, FORCEs are applied: force_seq follows). ``hapsim run`` with a
    velocity_sensor correction against the board is refused before CONFIG, exit 2, in one
    line saying the device offers no velocity sensor."""
    _require()
    scene = tmp_path / "hapkit_vsensor.yaml"
    scene.write_text((ROOT / "configs/hapkit.yaml").read_text().replace(
        "  force_limit: 5.0", "  correction: {kind: velocity_sensor}\n  force_limit: 5.0"))
    with _board(tmp_path) as (proc, port, report):
        host = _Host(port)
        try:
            host.send(b"\x00" + fp.encode(fp.HelloRequest(fp.PROTOCOL_VERSION)))
            host.wait_for(fp.Hello)
            host.send(fp.encode(fp.SensorsRequest(fp.SENSOR_VELOCITY)))
            assert host.wait_for(fp.Sensors) == fp.Sensors(fp.FEATURE_COMPACT, 0)
            host.send(fp.encode(fp.Config(RATE, WATCHDOG_US, 5.0)))
            applied = []
            for st in host.armed_states():
                host.send(fp.encode(fp.Force(st.seq, (0.1,))))
                if st.status & fp.STATUS_FORCE_APPLIED:
                    applied.append(st.seq - st.force_seq)
                if len(applied) >= 50:
                    break
            host.send(fp.encode(fp.Stop()))
            assert set(applied) == {1}                    # delay 1: FORCE n applied at n + 1
            assert not any(isinstance(m, (fp.Velocity, fp.StateCompact)) for m in host.others)
            # (a partial frame from before the port was opened may count as bad_crc)
            assert host.dec.stats.unknown_type == 0 and host.dec.stats.malformed == 0
        finally:
            host.close()
        code, out, err = hapsim_main(["run", str(scene), "--port", port, "--duration", "0.2"])
    assert code == 2, (code, err)
    errors = [ln for ln in err.splitlines() if "error" in ln]   # after the progress line
    assert len(errors) == 1 and "does not offer a velocity sensor" in errors[0], err
    assert "offered=0x0002" in errors[0] and "device.correction.kind" in errors[0]


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--host":
        _host_main(sys.argv[2], float(sys.argv[3]))
