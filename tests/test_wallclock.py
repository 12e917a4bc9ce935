"""Emulated devices keep their own time (issue 29 item 1).

A board does not wait for its host: its motor holds the last force while the wall clock
runs. The driver mocks (:mod:`hapsim.emulated.driver_mock`) therefore integrate their physics over
the real time between the host's bytes (``clock="wall"``, their default), apply each
firmware's own silence rule on that clock and answer as late as the board does; lockstep
(one period per command) is a mode a test asks for by name.

Two kinds of test here. In process, the board is handed the times its bytes come at (its
own clock, chosen by the test): the joint's motion over a host pause equals the closed
form of the held force integrated over that time, written here independently of
:mod:`hapsim.device_model`; the FireFader's silence rule zeroes its force at the instant
its polls run out. Over a pty, in real time, beside two CPU-bound processes: the THS
closed through every driver's bytes on the board's own clock is predicted within the
run's stated uncertainty, and a host pause of known length moves the fader as the held
force over the real time the board saw.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import time

import numpy as np
import pytest

from hapsim.emulated.driver_mock import FireFaderDevice, HapkitSerialDevice
from hapsim.drivers import firefader as ff
from hapsim.drivers import hapkit_serial as hk
from hapsim.scene import Device, Excitation
from tolerance import rel_tol, sum_tol


_SCALE = [0.0]          # the largest term any closed form below summed (its round-off)


def _held(x, v, m, b, f, t):
    """Closed form of ``m x'' + b x' = f`` (``f`` constant) from ``(x, v)`` after ``t`` [s]:
    ``v(t) = f/b + (v - f/b) e^(-a t)``, ``x(t) = x + f t / b + (v - f/b)(1 - e^(-a t))/a``,
    ``a = b/m`` (variation of constants); ``b = 0``: ``x + v t + f t^2 / (2 m)``. The
    largest term summed is kept in ``_SCALE`` (with a small ``b`` the terms ``f t / b``
    cancel: the sum's round-off is relative to them, not to the result)."""
    if b == 0.0:
        terms = (x, v * t, f * t * t / (2 * m))
        out = sum(terms), v + f * t / m
    else:
        a = b / m
        e = math.exp(-a * t)
        terms = (x, f * t / b, (v - f / b) * (1 - e) / a)
        out = sum(terms), f / b + (v - f / b) * e
    _SCALE[0] = max(_SCALE[0], *(abs(u) for u in terms))
    return out


@pytest.fixture(autouse=True)
def _fresh_scale():
    _SCALE[0] = 0.0


def _tol(x, steps):
    """Round-off of the board's exact ZOH steps and of the closed form: each of ``steps``
    steps is a few roundings deep (the coefficients: an expm1, a quotient, two products;
    the update: two products and two sums: 10), on the scale of ``|x|`` or of the largest
    term a closed form summed (``_SCALE``), whichever is larger."""
    return rel_tol(10 * steps) * max(abs(x), _SCALE[0], 1e-12)


# ------------------------------------------------------------------ in process, board times

@pytest.mark.parametrize("seed", range(8))
def test_firefader_pause_integrates_the_held_force_over_the_real_time(seed):
    """Random fader masses and frictions, a packet, then a host pause shorter than the
    silence rule (5-95 ms: lockstep would have advanced one period): at the next read the
    fader is where the force of the first packet, held over the pause from its pass's
    read, then the second packet's force over ``adc_s``, put it (closed form); the record
    says so in whole counts; and the record leaves ``reply_s`` after the packet."""
    rng = np.random.default_rng(seed)
    m, b = rng.uniform(0.02, 0.3), rng.uniform(0.0, 1.0)
    dev = FireFaderDevice(Device(mass=m, friction=b, delay=0.725, force_limit=10.0),
                          250.0, Excitation())
    drv = ff.FireFader()
    t = 0.0
    for _ in range(80):                       # the enable comes up (66 passes)
        dev.feed(drv.encode_force(0.0), now=t)
        t += 4e-3
    assert dev.enable == 129
    c1, c2 = rng.integers(-100, 100, 2)
    dev.feed(ff.encode_packet(int(c1), 0), now=t)
    # measured 0 (generic 0): exact on both targets
    assert dev.ready_at == pytest.approx(t + dev.reply_s, abs=1e-15)
    x0, v0, t0 = dev.physics.x, dev.physics.v, t + dev.adc_s      # at the pot's read
    pause = rng.uniform(5e-3, 95e-3)
    t += pause
    rec = dev.feed(ff.encode_packet(int(c2), 0), now=t)
    f1, f2 = 2 * c1 / 254 * 0.39, 2 * c2 / 254 * 0.39
    x1, v1 = _held(x0, v0, m, b, f1, t - t0)
    x2, v2 = _held(x1, v1, m, b, f2, dev.adc_s)
    steps = int(pause / 4e-3) + 4
    assert abs(dev.physics.x - x2) <= _tol(abs(x2) + abs(x1) + abs(x0), steps)
    assert abs(dev.physics.v - v2) <= _tol(abs(v2) + abs(v1) + abs(v0), steps)
    got = ff.RecordDecoder().feed(rec)
    assert got[-1][0] == min(max(ff.CENTRE + round(x2 / dev.mpc), 0), ff.POSITION_MAX)


def test_firefader_silence_zeroes_the_force_at_the_instant_its_polls_run_out():
    """The .ino's waitForSerialInput: 0.1 s without a byte from the end of a pass zeroes
    the enable and the motor at that instant. A silence the emulator saw last 0.15 s:
    the force held over the first 0.1 s after the record left, nothing after (closed
    form); then 5 passes off. A silence of 0.08 s: the force stays on."""
    m, b = 0.05, 0.1
    drv = ff.FireFader()
    for silent, off in ((0.08, False), (0.15, True)):
        dev = FireFaderDevice(Device(mass=m, friction=b, delay=0.725, force_limit=10.0),
                              250.0, Excitation())
        t = 0.0
        for _ in range(80):
            dev.feed(drv.encode_force(0.0), now=t)
            t += 4e-3
        dev.feed(ff.encode_packet(60, 0), now=t)
        x0, v0, t0 = dev.physics.x, dev.physics.v, t + dev.adc_s
        end = dev.ready_at                         # the record has left: the polls start
        dev.idle(end + silent - dev._last_now)     # serve: the host silent so long, seen
        assert dev.enable == (0 if off else 129)
        assert dev.silences == ([end + ff.SILENCE_S] if off else [])
        t_next = end + silent + 1e-3
        dev.feed(ff.encode_packet(60, 0), now=t_next)
        f = 2 * 60 / 254 * 0.39
        if off:
            x1, v1 = _held(x0, v0, m, b, f, end + ff.SILENCE_S - t0)
            x2, v2 = _held(x1, v1, m, b, 0.0, t_next + dev.adc_s - (end + ff.SILENCE_S))
            assert dev.pwm == 0 and dev.held == 0.0          # the gate: 5 passes off
        else:
            x2, v2 = _held(x0, v0, m, b, f, t_next + dev.adc_s - t0)
            # measured 0 (the generic run did not take this branch): the force as sent, exact
            assert dev.held == pytest.approx(f, rel=1e-15)
        assert abs(dev.physics.x - x2) <= _tol(abs(x2) + abs(x0), 60)


def _sketch_read(now: float, tk: float) -> tuple:
    """When the sketch samples after a command written at ``now`` [s] to an idle board,
    from its ``loop`` (haphub/WHC2017 ``Hapkit_arduino.ino:96-135``): the header byte
    comes 10 bits at 57600 baud after the write, the flag's first tick at or after it
    reads the command, whose 9 more bytes end ``10`` bytes' wire after the write; the
    next flag (a tick passed during the read: at once) samples. Returns ``(t, terms,
    on_tick)``: the sample [s], the terms whose sum it is, and whether it is on a tick."""
    byte = 10 / 57600
    read_tick = math.ceil((now + byte) / tk) * tk
    end = [now] + [byte] * 10
    if sum(end) >= read_tick + tk:
        return sum(end), end, False
    return read_tick + tk, [read_tick, tk], True


@pytest.mark.parametrize("seed", range(6))
def test_hapkit_serial_answers_on_its_own_tick_and_holds_its_force(seed):
    """The sketch's ``loop`` reads a command on the first tick its header byte has come by,
    and reads the handle on the next flag: the tick after, or the command's end when that
    is later (the 10 bytes' 1.74 ms of wire outlast a tick; the flag is one bit): on the
    tick for a header coming in the first 0.42 ms after one, at the command's end for the
    rest (:func:`_sketch_read`; the write's phases here are spread over the tick, seeds
    0-2 on the tick, 3-5 at the end). It applies the force's level (its sqrt output, 256
    levels) from its render's end, :data:`hapsim.drivers.hapkit_serial.RENDER_S` after
    the read, and its reply (the force's ``Tp``) leaves the 9 bytes' wire time after that;
    over a host pause (no silence rule) the handle moves as the held level over the real
    time from the first render to the next read (closed form)."""
    from hapsim.drivers.output_stage import sketch_board_output, sketch_tp
    rng = np.random.default_rng(seed)
    m, b = rng.uniform(0.05, 0.3), rng.uniform(0.0, 1.0)
    tk, rate = hk.FIRMWARE_TICK_S, hk.HapkitSerial.native_rate_hz     # 4 ticks a period
    # the handle read exactly (count_m 0, named): the closed form's position
    dev = HapkitSerialDevice(Device(mass=m, friction=b, delay=1, force_limit=2.0), rate,
                             Excitation(), count_m=0.0)
    drv = hk.HapkitSerial()
    byte = 10 / 57600
    flat = 2 * tk - 9 * byte                          # header phases sampled on the tick
    # the header's phase after a tick: seeds 0-2 within the flat part, 3-5 past it
    x = (seed % 3 + rng.uniform(0.1, 0.9)) / 3 * (flat if seed < 3 else tk - flat)
    x += 0.0 if seed < 3 else flat
    now = 10 * tk + x - byte
    f1 = float(np.float32(rng.uniform(-1, 1)))          # binary32 on the wire
    rep = hk.ReplyDecoder().feed(dev.feed(drv.encode_force(f1), now=now))
    tick, terms, on_tick = _sketch_read(now, tk)
    assert on_tick == (seed < 3)                      # the branch the phase was drawn for
    # the device's sum and this one, of the same terms in any order: each within sum_tol
    # (Higham (4.4)), so the two within twice it
    terms = terms + [hk.RENDER_S, 9 * 10 / 57600]
    assert dev.ready_at == pytest.approx(sum(terms), abs=2 * sum_tol(terms))
    assert rep[-1][0] == 0.0 and rep[-1][1] == float(sketch_tp([f1])[0])
    level = float(sketch_board_output([f1])[0])
    assert 0.0 < abs(level) <= abs(f1) and level * f1 > 0
    pause = rng.uniform(20e-3, 200e-3)
    now2 = now + pause
    rep = hk.ReplyDecoder().feed(dev.feed(drv.encode_force(0.0), now=now2))
    tick2 = _sketch_read(now2, tk)[0]
    x, v = _held(0.0, 0.0, m, b, level, tick2 - tick - hk.RENDER_S)
    assert rep[-1][0] == pytest.approx(x, rel=2.0 ** -23 + _tol(1.0, 60))
    # lockstep (named) would have moved it one period (4 ticks) whatever the pause
    lock = HapkitSerialDevice(Device(mass=m, friction=b, delay=1, force_limit=2.0), rate,
                              Excitation(), clock="lockstep", count_m=0.0)
    lock.feed(drv.encode_force(f1))
    lock.feed(drv.encode_force(0.0))
    assert abs(lock.physics.x - _held(0.0, 0.0, m, b, level, 1.0 / rate)[0]) <= _tol(x, 2)
    assert abs(x) > 2 * abs(lock.physics.x)


@pytest.mark.parametrize("k", [1, 3, 17])
def test_2diy_holds_its_torques_over_a_pause_and_pays_for_its_set_up(k):
    """The 2DIY board on its own clock: torques written, the host silent ``k`` periods,
    the next write: the joints moved as the same plant stepped ``k`` periods with those
    torques held (the same Runge-Kutta steps, to round-off; lockstep would have moved it
    one period); a set-up costs its two encoders' 2 ms each (``new Encoder``) after one
    50 us pass per command before it, and the write after it is answered then."""
    import copy

    from hapsim.emulated.haply2_board import PASS_S, SETUP_S, Haply2DIYBoard
    from hapsim.emulated.haply_firmware import CommandDecoder
    from hapsim.drivers.haply2 import Haply2DIY
    from hapsim.scene import load_scene_nd
    from pathlib import Path
    sc = load_scene_nd(Path(__file__).resolve().parents[1] / "configs" / "pantograph_wall.yaml")
    assert sc.device.delay == 1                      # the board's own: no extra latency
    drv = Haply2DIY("gen3")
    wall = Haply2DIYBoard(sc, "gen3", amplitude=1e-4)
    arm = drv.arm_bytes([math.degrees(v) for v in sc.device.joints])
    wall.feed(arm, now=0.0)
    kinds = [c[0] for c in CommandDecoder().commands(arm)]
    assert kinds[-2:] == ["setup", "write"]
    # measured 5.6e-17 (generic 5.6e-17), margin 18000
    assert wall.ready_at == pytest.approx((len(kinds) - 2) * PASS_S + 2 * SETUP_S,
                                          abs=1e-12)
    t = wall.ready_at + 1e-3
    wall.feed(drv.write_bytes((0.01, -0.02)), now=t)
    ref = copy.deepcopy(wall.plant)                  # at t, the torques just taken
    jt = wall._joint_torques()
    T = sc.period
    wall.feed(drv.write_bytes((0.0, 0.0)), now=t + k * T)
    one = copy.deepcopy(ref)
    one.step_torque(jt)
    for _ in range(k):
        ref.step_torque(jt)
    q_w, q_r, q_1 = wall.plant.joints(), ref.joints(), one.joints()
    moved = float(np.abs(q_r - copy.deepcopy(wall).plant.q0).max())
    # the same steps; the step length k T / n against T / 2 differs by an ulp
    assert np.abs(q_w - q_r).max() <= rel_tol(40 * k) * max(moved, 1.0)
    if k > 1:
        assert np.abs(q_w - q_1).max() > 1e3 * rel_tol(40 * k) * max(moved, 1.0)


def _homed_falcon(clock):
    from hapsim.emulated.falcon_device import FalconDevice, home, load_firmware
    from hapsim.scene import load_scene_nd
    from pathlib import Path
    sc = load_scene_nd(Path(__file__).resolve().parents[1] / "configs" / "delta_sphere.yaml")
    dev = FalconDevice(sc, clock=clock)
    load_firmware(dev, bytes(range(256)))
    return sc, dev, home


@pytest.mark.parametrize("k", [1, 4, 23])
def test_falcon_takes_a_packet_on_its_tick_and_holds_its_commands(k):
    """The emulated Falcon on its own clock: a packet is taken at the firmware's next tick
    (the scene's period), its reply ready then; commands held over a host pause of ``k``
    periods move the legs as the same plant stepped ``k`` periods with them (the same
    Runge-Kutta steps, to round-off)."""
    import copy

    from hapsim.drivers.falcon import host_packet
    sc, dev, home = _homed_falcon("wall")
    T = sc.period
    t = [0.5 * T]

    def feed(b):                     # mid-period: each packet on the tick after it
        t[0] += T
        return dev.feed(b, now=t[0])
    home(feed)
    now = t[0] + 0.8 * T
    dev.feed(host_packet((500, -300, 200), 0x2), now=now)
    tick = (math.floor(now / T) + 1) * T
    # measured 0 (generic 0): exact on both targets
    assert dev.ready_at == pytest.approx(tick, abs=1e-12)
    ref = copy.deepcopy(dev.plant)
    tau = np.array([-c * dev.nm_per_count for c in (500, -300, 200)])
    dev.feed(host_packet((0, 0, 0), 0x2), now=tick + (k - 1) * T + 0.5 * T)
    for _ in range(k):
        ref.step_torque(tau)
    moved = float(np.abs(ref.joints() - ref.q0).max())
    assert moved > 0
    assert np.abs(dev.plant.joints() - ref.joints()).max() <= rel_tol(40 * k) * max(moved, 1.0)


def test_falcon_through_pyftdi_is_paced_by_its_firmware_ticks():
    """The real pyftdi above the emulated FT232R, the Falcon on its own clock: the loop
    cannot run faster than the firmware's ticks (a lockstep device let it run as fast as
    the host could), and the readings are the encoders' true counts at their ticks."""
    from hapsim.pipeline.falcon_run import emulated_falcon, run_falcon
    from hapsim.scene import load_scene_nd
    from pathlib import Path
    sc = load_scene_nd(Path(__file__).resolve().parents[1] / "configs" / "delta_sphere.yaml")
    image = bytes(range(256)) * 2
    link, dev, _ = emulated_falcon(sc, image)
    try:
        res = run_falcon(sc, link, image, 100, truth=dev.counts, timeout=0.01, paced=True)
    finally:
        link.close()
    assert dev.clock == "wall"
    if res["stopped"]:
        # a loaded machine: the host fell behind the firmware's pace by more than the
        # 1-DoF loop's late-stop allows (hapsim.host.loop.LATE_STOP): the loop stopped,
        # zero commands sent, and the verdict says so (never "ok")
        assert res["verdict"] == "degraded" and "safety: the host was" in res["reason"]
        assert dev.commands == (0, 0, 0)
        return
    # 101 packets take at least 100 ticks: the rate is at most the scene's (2 % for the
    # first packet's phase and the loop's own timing of its start)
    assert res["packets_per_s"] <= 1.02 * sc.rate_hz
    t = res["truth"]
    # (the rows the host's watchdog wrote before are not compared: their reply may answer
    # its zero command)
    wd_rows = {r for r in (res["watchdog"] or {}).get("rows", []) if r < 100}
    assert t["compared"] >= 100 - res["missing"] - len(wd_rows), (t, sorted(wd_rows))
    # a reading is the true count at its tick; one a loaded host read an exchange late
    # is an earlier tick's (96 % exact at load 14 on 2 cores: a bound with its margin)
    assert t["exact"] >= 0.8 * t["compared"]


def test_the_named_clocks_and_a_wrong_one():
    """The default is the wall clock; lockstep is asked for by name; another is refused
    with the valid choices."""
    from hapsim.errors import ConfigError
    d = Device(mass=0.05, friction=0.1, delay=1, force_limit=1.0)
    assert FireFaderDevice(d, 250.0).clock == "wall"
    assert HapkitSerialDevice(d, 250.0).clock == "wall"
    assert FireFaderDevice(d, 250.0, clock="lockstep").wall is None
    with pytest.raises(ConfigError, match="valid: wall, lockstep"):
        HapkitSerialDevice(d, 250.0, clock="host")


# ------------------------------------------------------------------ real time, loaded

def _burn(until: float) -> None:
    while time.monotonic() < until:
        pass


@pytest.fixture
def two_cpu_hogs():
    """Two CPU-bound processes for the test's length (each ends by itself within 90 s)."""
    from load import burners_for  # same directory (pytest prepend import mode)
    ctx = mp.get_context("spawn")
    # two busy processes beside the test: the other xdist worker is one of them
    procs = [ctx.Process(target=_burn, args=(time.monotonic() + 90.0,), daemon=True)
             for _ in range(burners_for(2))]
    for p in procs:
        p.start()
    time.sleep(0.2)                      # burning before the loop starts
    try:
        yield procs
    finally:
        for p in procs:
            p.terminate()
            p.join(5.0)


@pytest.mark.parametrize("config, driver", [("firefader", "firefader"),
                                            ("hapkit_serial", "hapkit-serial")])
def test_closed_loop_on_the_boards_own_clock_beside_two_cpu_hogs(two_cpu_hogs, config,
                                                                  driver):
    """The THS closed through each driver's bytes on the board's own clock, two
    CPU-bound processes running: the run ends by its duration (or by the host's own
    lateness where the OS refuses real-time priority, zero torque sent), the board
    on its own clock, the device left at zero force, and a measurement made. The verdict
    is not asserted here: the host's jitter within a period is not yet in the stated
    uncertainty (issue 29 item 2, the drivers' part): at load 13-18 on 2 cores one run in
    two said "differs" for each (FireFader b, Hapkit-serial b), the others "within";
    unloaded, tests/test_drivers.py asserts the FireFader's quantiser bound.
    (The framed mock is real time by default: tests/test_daemon_pty.py; the 2DIY and the
    Falcon on their own clocks: tests/test_haply2_realtime.py, the Falcon tests below.)"""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    from pathlib import Path
    sc = load_scene(str(Path(__file__).resolve().parents[1] / "configs" / f"{config}.yaml"))
    assert all(p.is_alive() for p in two_cpu_hogs)         # they run beside it
    assert len(two_cpu_hogs) + max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
                                   - 1, 0) >= 2
    kw = {"driver": driver} if driver else {}
    # the default scheduling (SCHED_FIFO 10 where the OS permits, as `hapsim run`): a
    # loop at normal priority beside two CPU-bound processes is no real-time loop
    rep = run_scene(sc, handle_signals=False, **kw)
    loop = rep["loop"]
    assert loop["mock"]["clock"] == "wall" and loop["mock"]["held_at_end"] == 0.0
    if driver:
        # a driver's board on its emulated link takes the host's writes at their kernel
        # stamps (hapsim.emulated.stamped_link): all but those written before its process
        # took the connection (the port opened while it started up: the arming and its
        # repeats; the loop's ticks come after its first record)
        assert loop["transport"] == "embedded mock on an emulated link", loop["transport"]
        link, dl = loop["mock"]["link"], loop["driver"]
        assert link["unstamped"] <= 1 + dl["rearms"], (link, dl["rearms"])
        assert link["stamped"] >= dl["commands"] - link["unstamped"], (link, dl["commands"])
    if loop.get("safety_stop"):
        # Where the OS refuses SCHED_FIFO (a container), three CPU-bound processes (the
        # two hogs and the other xdist worker) on 2 cores can starve the loop: the one
        # stop allowed is the host's own lateness, zero torque sent, the board left at
        # zero (asserted above). Seen once in a fresh-clone CI run ("the host was 256 ms
        # late over its last 100 ticks"), FireFader at 250 Hz.
        # Beside one more busy process (the suite under tools/suite_time.py --busy 1), a
        # FireFader run at 250 Hz stopped on the host's force clamp instead ("force at the
        # limit 0.38 N in 50 of the last 100 samples"): a stop too, zero force sent, the
        # fader inside its travel (asserted here, from the board's own record)
        from hapsim.host.link_verdict import CLAMP_STOP
        reason = loop["stop_reason"]
        if reason.startswith("safety: position") and loop["overruns"] > 0:
            # A board without a watchdog (the Hapkit sketch) holds its last force while
            # the host is starved: once in a loaded suite the host woke to read the paddle
            # at -0.232 m, beyond its 0.2 m workspace (issue 29). No host can act while it
            # does not run; what it must do once it runs: stop, brake the handle to rest
            # (hapsim.host.recovery: friction alone would carry it v m / b further), leave
            # zero force (asserted above), and say no "within".
            # (at rest, unless the host was late again while braking: then the braking
            # may run out of its 0.25 s; zero force is still left, asserted above)
            bk = loop["brake"]
            assert bk and (bk["ended"] == "rest" or bk["late"] > 0), bk
            assert (rep.get("measured") or {}).get("within") is not True
            return
        assert ("the host was" in reason and "late" in reason) or \
            reason.startswith(CLAMP_STOP), reason
        limit = loop["safety"]["position_limit"]          # the run's workspace [m]
        if loop["mock"]["true_excursion"] > limit:
            # the same starved host as above, its lateness found first on waking (a
            # fresh-clone CI run: the paddle 0.227 m out on its own record, the stop the
            # host's lateness): out while the host did not run, which no host can act
            # on; once it runs: stopped, braked, zero left (above), no "within"
            assert loop["overruns"] > 0, (reason, loop["mock"]["true_excursion"])
            bk = loop["brake"]
            assert bk and (bk["ended"] == "rest" or bk["late"] > 0), (reason, bk)
            assert (rep.get("measured") or {}).get("within") is not True
        return
    assert loop["stop_reason"] == "duration", loop["stop_reason"]
    m = rep["measured"]
    if "within" not in m:
        # not identified (once in a whole-suite run, FireFader: the loaded machine's
        # late rows left too little to fit): said with its reason, never "within"
        from hapsim.pipeline.report import verdict_summary
        assert m.get("error") and verdict_summary(m)["verdict"] == "not measurable", m
        return
    assert m["within"] in (True, False) and m["b"] > 0, m.get("verdict")


def test_a_host_pause_moves_the_fader_as_the_held_force_over_real_time():
    """The FireFader on a pty, served in real time: the host sends a force, pauses 30 ms
    (its own clock), sends zero. The board's two passes are at least the pause apart on
    its clock, and between them the fader moved as the first force held over that real
    time (closed form); lockstep would have moved it 4 ms' worth."""
    import socket
    import threading

    from hapsim.emulated.driver_mock import serve
    m, b = 0.05, 0.1
    dev = FireFaderDevice(Device(mass=m, friction=b, delay=0.725, force_limit=10.0),
                          250.0, Excitation())
    drv = ff.FireFader()
    starts = []
    orig = dev._pass

    def spy(count, ticks, start=None, **kw):      # (kw: fader B's count)
        starts.append(start)
        return orig(count, ticks, start, **kw)
    dev._pass = spy
    host, board = socket.socketpair()
    stop = threading.Event()
    th = threading.Thread(target=serve, args=(board.fileno(), dev),
                          kwargs={"stop": stop.is_set, "poll": 0.005}, daemon=True)
    th.start()
    try:
        def exchange(pk):
            host.sendall(pk)
            got = b""
            while len(got) < 7:
                got += host.recv(7 - len(got))
        # armed: the enable climbs to its gate in ~80 passes; a silence over 0.1 s (this
        # thread descheduled on a loaded machine) is the .ino's silence rule and restarts
        # the climb, so the host writes on until the board is armed (at most 400)
        for _ in range(400):
            exchange(drv.encode_force(0.0))
            time.sleep(2e-3)
            if dev.enable == 129:
                break
        assert dev.enable == 129
        exchange(ff.encode_packet(80, 0))
        after = (dev.physics.x, dev.physics.v, dev.wall.t)     # at the pot's read
        t_host = time.monotonic()
        time.sleep(0.03)
        paused = time.monotonic() - t_host
        exchange(ff.encode_packet(0, 0))
        final = (dev.physics.x, dev.wall.t)
    finally:
        stop.set()
        th.join(2.0)
        host.close()
        board.close()
    s1, s2 = starts[-2], starts[-1]
    assert s2 - s1 >= paused                           # the board's clock ran the pause
    assert final[1] == s2 + dev.adc_s and after[2] == s1 + dev.adc_s
    f = 2 * 80 / 254 * 0.39
    x, v = _held(after[0], after[1], m, b, f, s2 - after[2])
    x, v = _held(x, v, m, b, 0.0, dev.adc_s)          # the zero packet's pass to its read
    assert abs(final[0] - x) <= _tol(abs(x) + abs(after[0]), 20)
    lock_x = _held(after[0], after[1], m, b, f, 4e-3)[0]
    assert abs(x - after[0]) > 5 * abs(lock_x - after[0])


@pytest.mark.parametrize("seed", [1, 3, 8, 9])
def test_haply_m3_losing_host_bytes_never_says_differs(two_cpu_hogs, seed):
    """The Haply M3 joint's loop on its board's own clock, 1 host byte in 200 lost on its
    way to the board (seeded), two CPU-bound processes running: a write that lost a byte
    is parsed from the wrong bytes (firmware V1.5: no start byte, no checksum), an
    arbitrary torque no reply names. The verdict is "within" or "not measurable" with its
    reason, never "differs": the rows around each missing reply are left out of the
    measurement (:meth:`hapsim.drivers.haply.HaplyM3.unknown_force_rows`). Before, with
    those torques measured as the ones sent, 3 of these 4 seeds said "differs" (k 0.4-3.6 %
    off against a stated 0.3-0.5 %, ``tools/driver_timing.py`` at SCHED_FIFO); the
    replies' bytes lost instead were within in 4 of 4."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    from pathlib import Path
    sc = load_scene(str(Path(__file__).resolve().parents[1] / "configs" / "haply.yaml"))
    assert all(p.is_alive() for p in two_cpu_hogs)
    rep = run_scene(sc, driver="haply", duration=1.5, handle_signals=False, seed=seed,
                    driver_faults={"drop_tx": 0.0, "drop_rx": 0.005, "seed": seed})
    loop, m = rep["loop"], rep["measured"]
    assert loop["mock"]["clock"] == "wall"
    if loop.get("safety_stop") and "the host was" in loop["stop_reason"]:
        # a loaded machine can starve the loop before its first lost byte (seed 9 loses
        # a byte of the 49th write; a fresh clone's suite beside a CPU-bound process once
        # ended this run with no byte lost): the one stop allowed is the host's own
        # lateness, zero torque sent, the joint within the run's workspace; nothing is
        # measured, so nothing differs
        assert loop["mock"]["held_at_end"] == 0.0, loop["mock"]
        # (the board's longest hold and the watchdog's report say why, if it fails: once,
        # beside two CPU-bound processes, 151 rad, when the watchdog's zero command could
        # not reach a board that had lost its motor's address; its robust write since)
        assert loop["mock"]["true_excursion"] <= loop["safety"]["position_limit"], (
            loop["mock"].get("longest_hold_s"), loop["driver"].get("watchdog"),
            loop["driver"].get("resync_reasons"))
        return
    # host bytes were lost
    assert sum(loop["mock"]["faults"].values()) > 0, (loop["stop_reason"], loop["mock"])
    verdict = str(m.get("verdict"))
    assert not verdict.startswith("measured differs"), (verdict, m.get("rel_err"),
                                                        m.get("k_unc"), m.get("k"))
    assert m.get("within") is True or verdict.startswith("not measurable") or \
        m.get("error"), verdict


def test_haply_m3_unknown_force_rows_are_each_missing_replys_window():
    """Closed form: each run of estimated rows [r0, r1] leaves out rows r0 - 1 .. r1 + d
    (clipped to the record), overlapping windows merged; no estimated row, None."""
    from hapsim.drivers.base import FLAG_ESTIMATED
    from hapsim.drivers.haply import HaplyM3
    drv = HaplyM3()
    for d in (0, 1, 3):
        drv.loop_delay = d
        rng = np.random.default_rng(d)
        for _ in range(50):
            n = int(rng.integers(1, 60))
            est = rng.random(n) < 0.08
            flags = np.where(est, FLAG_ESTIMATED | 1, 1).astype(np.uint8)
            got = drv.unknown_force_rows({"flags": flags})
            if not est.any():
                assert got is None
                continue
            want = np.zeros(n, bool)
            for r in np.flatnonzero(est):         # a row at a time: windows merge
                want[max(r - 1, 0):min(r + d + 1, n)] = True
            assert np.array_equal(got, want), (d, est, got, want)
    assert drv.unknown_force_rows({}) is None


def test_haply_m3_unknown_force_rows_count_a_gap_in_seq_as_a_missing_reply():
    """Closed form in host ticks: a tick the record has no row for (a gap in ``seq``: a
    lockstep mock's command asked again, a re-synchronisation's skipped number) is a
    missing reply as an estimated row is, so the window t0 - 1 .. t1 + d around each run
    of missing ticks [t0, t1] leaves out the rows whose tick is in it. The oracle marks
    tick by tick on a dense tick line (the driver uses runs and a difference array)."""
    from hapsim.drivers.base import FLAG_ESTIMATED
    from hapsim.drivers.haply import HaplyM3
    drv = HaplyM3()
    for d in (0, 1, 3):
        drv.loop_delay = d
        rng = np.random.default_rng(10 + d)
        for _ in range(50):
            span = int(rng.integers(2, 80))
            logged = rng.random(span) >= 0.1
            logged[0] = logged[-1] = True
            ticks = np.flatnonzero(logged)
            est = rng.random(ticks.size) < 0.05
            flags = np.where(est, FLAG_ESTIMATED | 1, 1).astype(np.uint8)
            got = drv.unknown_force_rows({"flags": flags, "seq": ticks + 1000})
            missing = ~logged
            missing[ticks[est]] = True
            if not missing.any():
                assert got is None
                continue
            bad = np.zeros(span, bool)
            for t in np.flatnonzero(missing):
                bad[max(t - 1, 0):min(t + d + 1, span)] = True
            assert np.array_equal(got, bad[ticks]), (d, ticks, est, got)
    # a seq that is not increasing (no ticks to count in) falls back to rows
    drv.loop_delay = 1
    got = drv.unknown_force_rows({"flags": np.array([1, FLAG_ESTIMATED, 1, 1], np.uint8),
                                  "seq": np.array([5, 3, 4, 9])})
    assert got.tolist() == [True, True, True, False]


def test_haply_m3_account_does_not_know_the_unknown_force_rows():
    """The rule lives in the driver's account (:meth:`hapsim.drivers.base.Driver.account`):
    its ``known`` is False exactly at :meth:`~hapsim.drivers.haply.HaplyM3.unknown_force_rows`,
    which both ``identify``'s fit and ``run``'s measurement leave out
    (:func:`hapsim.analysis.measurement.late_accounted` names them); a driver whose rows
    are all nameable (the FireFader) keeps them all known."""
    from hapsim.drivers.base import FLAG_ESTIMATED
    from hapsim.drivers.haply import HaplyM3
    rng = np.random.default_rng(4)
    n = 400
    flags = np.where(rng.random(n) < 0.03, FLAG_ESTIMATED, 0).astype(np.uint8)
    seq = np.cumsum(1 + (rng.random(n) < 0.03)).astype(np.int64)
    force = rng.uniform(-0.1, 0.1, n)
    cols = {"flags": flags, "seq": seq, "time": seq * 1e-3, "position": np.zeros(n)}
    m3 = HaplyM3()
    m3.loop_delay = 1
    acc = m3.account(cols, force)
    unknown = m3.unknown_force_rows(cols)
    assert unknown.any() and np.array_equal(acc.known, ~unknown)
    assert acc.to_dict()["unknown"] == int(np.count_nonzero(unknown))
    ffd = ff.FireFader()
    ffd.loop_delay = 1
    fa = ffd.account(cols, force)
    assert fa is not None and fa.known.all()


def test_identify_over_an_m3_losing_host_bytes_finds_the_hidden_joint():
    """``hapsim identify`` over the M3 mock (lockstep, as identify always runs a mock),
    1 host byte in 200 lost on its way to the board: the account leaves the rows around
    each missing reply out of the fit (``known`` False: the torques the board may have
    parsed from the wrong bytes, and the extrapolated positions of the estimated rows),
    and the joint's inertia and viscous friction are inside their stated intervals.
    Measured (seeds 1-5, 2 s): with the rule switched off the same fits were within
    too -- in a lockstep record each missing reply is a gap in seq, where the fit
    restarts from a fitted initial state, which absorbs most of the one tick of torque
    parsed wrong; what this asserts is that the rows are left out and the fit stays
    honest without them."""
    import dataclasses

    import hapsim.emulated.driver_mock as dm
    from hapsim.analysis.device_fit import fit_device
    from hapsim.api.identifying import excite_and_fit
    from hapsim.scene import Device

    init = dm.EmbeddedDriverMock.__init__
    m, b = 1e-3, 1e-3
    for seed in (2, 3):
        def lossy(self, *a, **k):
            init(self, *a, **{**k, "faults": {"drop_rx": 0.005, "drop_tx": 0.0,
                                              "seed": seed}})
        dm.EmbeddedDriverMock.__init__ = lossy
        try:
            fit, rec = excite_and_fit(device=Device(mass=m, friction=b, delay=1),
                                      driver="haply", force_limit=0.1, envelope=1.0,
                                      duration=2.0, max_delay=4, lockstep=True, seed=seed,
                                      progress=False, handle_signals=False,
                                      driver_options={"motor_direction": 0})
        finally:
            dm.EmbeddedDriverMock.__init__ = init
        acc = rec["account"]
        unknown = int(np.count_nonzero(~acc.known))
        assert unknown > 0 and rec["loop"]["driver"]["missing"] > 0, seed
        # the rows are left out of the fit: with them in (known throughout), another fit
        full = dataclasses.replace(acc, known=np.ones_like(acc.known))
        again = fit_device(rec["position"], rec["force"], rec["period"], late=rec["late"],
                           max_delay=5, applied=full, seq=rec["seq"])
        assert again.mass.value != fit.mass.value, seed
        assert fit.delay == 1, seed
        assert fit.mass.lo <= m <= fit.mass.hi, (seed, fit.mass)
        assert fit.friction.lo <= b <= fit.friction.hi, (seed, fit.friction)


def test_haply_m3_losing_host_bytes_still_sees_a_device_that_differs(monkeypatch):
    """The same lossy link (1 host byte in 200 lost, seeds 1-3) against a joint with a hidden
    viscous friction of 0.001 N m s/rad more than the scene states (the felt b, predicted
    0.00126 N m s/rad, about doubles): "differs", the measured b above the prediction by
    more than its stated uncertainty -- the rows left out around the missing replies do
    not blind the measurement. The board stepped one period per write (lockstep, named:
    deterministic; on the wall clock a loaded machine's re-synchronisations make some runs
    "not measurable" instead, 12 of them once in the full suite), its missing replies left
    out as on the wall clock."""
    import dataclasses

    import hapsim.emulated.driver_mock as dm
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    from pathlib import Path
    init = dm.EmbeddedDriverMock.__init__

    def hidden(self, driver, device, *a, **k):
        init(self, driver, dataclasses.replace(device, friction=device.friction + 0.001),
             *a, **k)
    monkeypatch.setattr(dm.EmbeddedDriverMock, "__init__", hidden)
    sc = load_scene(str(Path(__file__).resolve().parents[1] / "configs" / "haply.yaml"))
    for seed in (1, 2, 3):
        rep = run_scene(sc, driver="haply", duration=1.5, lockstep=True,
                        handle_signals=False, rt_priority=0, seed=seed,
                        driver_faults={"drop_tx": 0.0, "drop_rx": 0.005, "seed": seed})
        m = rep["measured"]
        assert rep["loop"]["estimated"] > 0                # rows were left out
        assert str(m.get("verdict")).startswith("measured differs"), (seed, m.get("verdict"))
        assert m["b"] - rep["predicted"]["b"] > m["b_unc"], (seed, m["b"],
                                                            rep["predicted"]["b"], m["b_unc"])
