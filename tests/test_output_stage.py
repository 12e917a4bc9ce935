"""The boards' output stages and the Hapkit sketch's render latency
(:mod:`hapsim.drivers.output_stage`, :mod:`hapsim.pipeline.render_latency`).

Each output stage is compared with a re-implementation written here from the firmware's
text, line by line, in numpy binary32 (not by calling the module): the Hapkit WHC2017
sketch (haphub/WHC2017 ef6028f, ``Hapkit_Kinematics_Simulation.h``, ``forceOutput``):

    Tp = rp/rs * rh * force;              // float rs = 0.073152, rp = 0.004191, rh = 0.075
    if(force > 0) dir HIGH else LOW;
    duty = sqrt(abs(Tp)/0.0183);          // AVR: double is binary32
    if (duty > 1) duty = 1; else if (duty < 0) duty = 0;
    int output = (int)(duty * 255);

its motor model inverted (``0.0183 (n/255)^2`` N m at the pulley); the Haply M3 V1.5
(HaplyHaptics/Haply-Arduino-Firmware-Versions edcf50f, ``Haply_M3_Firmware_V1_5.h``,
``create_torque``):

    if(torque <= 0) dir output else !output;
    torque = abs(torque);
    if(torque > MAX_TORQUE) torque = MAX_TORQUE;     // #define 0.123 (a double)
    duty = PWM_OUTPUT_RESOLUTION * torque / MAX_TORQUE;  // 4095 * float, then / double
    pwm_write_duty(mtr->pwmPin, duty);               // 12 bits at the Due's 8: duty >> 4

of a period of 255 counts. Then the class of runs: the emulated boards (firmware-faithful
by default) measured "within" with their own loop's truth inside the stated interval, on a
simulated clock over random paddles and on the wall clock for the shipped scenes; a board
that differs still "differs"; a driver without a render latency keeps today's prediction
bit for bit.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import types

import numpy as np
import pytest

from hapsim.drivers.output_stage import m3_output, sketch_board_output, sketch_output
from seeds import seeds
from tolerance import rel_tol

f32 = np.float32


def _sketch_reference(force) -> np.ndarray:
    """The Hapkit's motor force [N] for rendered forces, from the sketch's lines above."""
    force = np.asarray(force, np.float64).astype(f32)
    g = f32(f32(f32(0.004191) / f32(0.073152)) * f32(0.075))      # rp/rs * rh, in order
    out = np.empty(force.size)
    for i, f in enumerate(force):
        tp = f32(g * f)
        duty = f32(np.sqrt(f32(f32(abs(tp)) / f32(0.0183))))
        if duty > f32(1):
            duty = f32(1)
        elif duty < f32(0):
            duty = f32(0)
        n = int(math.floor(float(f32(duty * f32(255))))) if np.isfinite(duty) else 0
        torque = 0.0183 * (n / 255.0) ** 2                      # at the motor pulley
        out[i] = (1.0 if f > 0 else -1.0) * torque / (0.004191 / 0.073152 * 0.075)
    return out


def _m3_reference(torque) -> np.ndarray:
    """The M3 motor's torque [N m] for written torques, from ``create_torque`` above."""
    torque = np.asarray(torque, np.float64).astype(f32)
    out = np.empty(torque.size)
    for i, t in enumerate(torque):
        sign = -1.0 if t <= 0 else 1.0
        a = f32(abs(t))
        if float(a) > 0.123:
            a = f32(0.123)
        prod = f32(f32(4095) * a)                  # int * float: binary32
        q = float(prod) / 0.123                    # float / double: binary64
        duty = int(q) if math.isfinite(q) else 0   # (int): toward zero
        out[i] = sign * 0.123 * (duty >> 4) / 255.0
    return out


def _forces(rng, n: int, top: float) -> np.ndarray:
    """Random forces of both signs, half uniform up to ``top``, half log-uniform from
    1e-6 of it (the small forces, where the square-root levels are coarsest)."""
    u = rng.uniform(-top, top, n // 2)
    s = rng.choice([-1.0, 1.0], n - n // 2) * top * 10.0 ** rng.uniform(-6, 0, n - n // 2)
    return np.concatenate([u, s, [0.0, -0.0]])


@pytest.mark.parametrize("seed", range(4))
def test_the_sketch_stage_is_its_firmware_lines(seed):
    """Random forces (past the duty's clamp at 4.26 N): the board's level is the
    firmware's exactly; the driver's account holds it within its stated half-width,
    which is non-zero only where a level's edge is within a few units in the last place
    (measured: none or a few of 4000 here)."""
    rng = np.random.default_rng(seed)
    f = _forces(rng, 4000, 5.0)
    ref = _sketch_reference(f)
    # the same level: the motor model's force, 0.0183 (n/255)^2 over the gearing, computed
    # in another order of binary64 operations (6 roundings each side at most: rel_tol(12))
    assert np.all(np.abs(sketch_board_output(f) - ref) <= rel_tol(12) * np.abs(ref))
    out, hw = sketch_output(f)
    assert np.all(np.abs(out - ref) <= hw + rel_tol(12) * np.abs(ref))
    assert np.count_nonzero(hw) <= 0.01 * f.size
    # the level is below the force (truncation), the sign the force's
    assert np.all(np.abs(ref) <= np.abs(f.astype(f32).astype(float)) + 0.0)
    assert np.all(ref * f >= 0.0)


@pytest.mark.parametrize("seed", range(4))
def test_the_m3_stage_is_its_firmware_lines(seed):
    """Random torques (past the 0.123 N m clamp): the module's torque is the firmware's,
    exactly, and stated exact (half-width 0)."""
    rng = np.random.default_rng(100 + seed)
    t = _forces(rng, 4000, 0.2)
    out, hw = m3_output(t)
    assert np.array_equal(out, _m3_reference(t))
    assert not np.any(hw)
    assert np.all(np.abs(out) <= 0.123)
    assert set(np.unique(np.rint(np.abs(out) / 0.123 * 255))) <= set(range(256))


def test_the_drivers_stages_clamp_then_quantise():
    """The drivers' ``output_stage``: the limit's clamp (a non-finite force: 0), then the
    firmware's stage; ``levels``/``torque_levels`` 0 (named): no stage."""
    from hapsim.drivers import get_driver
    f = np.array([-3.0, -2.0, -0.5, 0.0, 0.3, 2.5, np.nan, np.inf])
    def clamped(v, lim):
        return np.where(np.isfinite(v), np.clip(v, -lim, lim), 0.0)   # as encode_force
    hk = get_driver("hapkit-serial")
    out, hw = hk.output_stage(f)
    ref = _sketch_reference(clamped(f, 2.0))
    # rel_tol(12): the motor model's arithmetic in another order (above)
    assert np.all(np.abs(out - ref) <= hw + rel_tol(12) * np.abs(ref))
    m3 = get_driver("haply")
    out, _ = m3.output_stage(f * 0.06)
    from hapsim.drivers.haply import MAX_TORQUE          # the driver's clamp: 0.123 N m
    assert np.array_equal(out, _m3_reference(clamped(f * 0.06, MAX_TORQUE)))
    assert get_driver("hapkit-serial", levels=0).output_stage(f) is None
    assert get_driver("haply", torque_levels=0).output_stage(f) is None


def _prepare(path, driver, **kw):
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    return prepare_run(load_scene(str(path)),
                       RunOptions(driver=driver, rt_priority=0, handle_signals=False, **kw))


@pytest.mark.parametrize("config,driver,kw", [
    ("configs/haply.yaml", "haply", {}),
    ("configs/firefader.yaml", "firefader", {}),
    ("configs/hapkit.yaml", None, {}),
    ("configs/hapkit_serial.yaml", "hapkit-serial", {"lockstep": True}),
    ("configs/hapkit_serial.yaml", "hapkit-serial",
     {"driver_options": {"render_latency_s": [0.0, 0.0]}}),
])
def test_no_render_latency_keeps_todays_prediction(config, driver, kw):
    """A driver whose board renders at its read (no ``render_latency_s``), no driver, a
    lockstep board (no time of its own) or bounds of 0: the run's prediction is
    ``predict(scene)``, bit for bit, and the loop is modelled with the scene itself."""
    from hapsim.analysis.prediction import predict
    from hapsim.pipeline.render_latency import timed_prediction
    prep = _prepare(config, driver, **kw)
    assert prep.model_scene is None and prep.model is prep.scene
    plain = predict(prep.scene)
    assert prep.pred.keys() == plain.keys()
    for key in plain:
        assert repr(prep.pred[key]) == repr(plain[key]), key
    model, pred = timed_prediction(prep.scene, None)
    assert model is prep.scene and repr(pred) == repr(plain)


def test_the_sketch_s_latency_is_predicted_at_the_range_s_middle():
    """configs/hapkit_serial.yaml with its driver in real time: the loop is modelled with
    the scene's delay and the middle of the sketch's render latency (periods), the
    prediction that scene's."""
    from hapsim.analysis.prediction import predict
    from hapsim.drivers.hapkit_serial import RENDER_LATENCY_S
    prep = _prepare("configs/hapkit_serial.yaml", "hapkit-serial")
    mid = 0.5 * sum(RENDER_LATENCY_S)
    assert prep.model.device.delay == prep.scene.device.delay + mid * prep.scene.rate_hz
    assert prep.pred["k"] == predict(prep.model)["k"]
    assert prep.pred["render_latency_s"] == list(RENDER_LATENCY_S)


def _truth(scene, latency_s: float, device=None) -> dict:
    """The felt pair of the board's own loop [N/m, N s/m]: the scene's device (or
    ``device``), its delay and the board's render latency (linear: the levels not in it,
    as the independent models' truth, docs/testing.md)."""
    from hapsim.analysis.prediction import predict
    from hapsim.pipeline.render_latency import timed_scene
    sc = scene if device is None else dataclasses.replace(scene, device=device)
    return predict(timed_scene(sc, latency_s))


def _inside(m, truth) -> bool:
    return (abs(m["k"] - truth["k"]) <= m["k_interval"]
            and abs(m["b"] - truth["b"]) <= m["b_interval"])


@pytest.mark.parametrize("seed", seeds(range(6), kept=(0, 1, 2)))
def test_random_paddles_on_the_sketch_s_board_are_within_with_the_truth_inside(
        seed, tmp_path):
    """Random paddles and springs (tests/test_unseen_holds.py's generator, no hold), the
    sketch's board on a simulated clock (its 256 levels, its render 0.45 ms after the
    read, its Tp replies): "within", the latency found within the bounds, and the board's
    own loop's felt pair inside the stated interval; the same paddle with 30 % more mass
    or 0.3 N s/m more friction than the scene states "differs" (the latency does not
    explain a device away)."""
    from hapsim.drivers.hapkit_serial import RENDER_LATENCY_S, RENDER_S
    from hapsim.emulated.hapkit_serial_board import hapkit_serial_offline_loop
    from hapsim.pipeline.runner import identify_run
    from test_unseen_holds import _random_case
    prep, n, _ = _random_case(seed, tmp_path)

    def measure(device=None):
        p = dataclasses.replace(prep, pred=dict(prep.pred))
        cols, drv, _ = hapkit_serial_offline_loop(prep.scene, n, device=device)
        tel = types.SimpleNamespace(wrapped=False, n=n, head=n, columns=lambda *a: cols)
        return identify_run(p, tel, None, driver=drv)
    m = measure()
    info = (m.get("verdict"), m.get("render_latency_s"), m.get("k"), m.get("k_interval"),
            m.get("b"), m.get("b_interval"))
    assert m.get("within") is True, info
    assert RENDER_LATENCY_S[0] <= m["render_latency_s"] <= RENDER_LATENCY_S[1]
    assert _inside(m, _truth(prep.scene, RENDER_S)), (info, _truth(prep.scene, RENDER_S))
    dev = prep.scene.device
    wrong = (dataclasses.replace(dev, mass=1.3 * dev.mass) if seed % 2 else
             dataclasses.replace(dev, friction=dev.friction + 0.3))
    w = measure(wrong)
    assert str(w.get("verdict")).startswith("measured differs"), (
        w.get("verdict"), w.get("render_latency_s"), w.get("b"), w.get("b_interval"))


def _wall_run(config: str, driver: str, seed: int) -> dict:
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    root = pathlib.Path(__file__).resolve().parents[1]
    return run_scene(load_scene(str(root / config)), driver=driver, duration=1.5,
                     handle_signals=False, seed=seed,
                     driver_faults={"drop_tx": 0.0, "drop_rx": 0.0, "seed": seed})


#: The share of its commands a board on its own tick may take off its period (its own
#: report, ``tick_arrivals``) in a run that must say "within"; a run beyond it was not the
#: sketch's loop (:func:`_wall_runs_within`). Measured on the CI machine kind, idle, 15
#: runs of the Hapkit scene: 0.09-0.21 in the 9 within, 0.26-0.65 in the 6 not
#: measurable; below 0.15 every run was within (6 of 6), the nearest not measurable run
#: 1.7 times above.
OFF_PERIOD_SHARE = 0.15


def _wall_runs_within(config: str, driver: str, truth, seeds=(1, 2, 3)) -> list:
    """Runs of ``config`` on the driver's emulated board on its own clock, seed by seed
    until one says "within": none says "differs"; each "within" holds ``truth`` (the
    board's own loop's felt pair) inside its stated interval; each other outcome is "not
    measurable" with its reason (on a loaded machine, the suite's other workers beside: a
    safety stop on the host's own lateness, the board's unseen holds cutting the record
    short). Returns the outcomes; at least one "within" is asserted, unless every run's
    board says it did not run the loop modelled: a board on its own tick that took
    :data:`OFF_PERIOD_SHARE` or more of its commands at another number of ticks than the
    period. Over a pty that was mostly its emulating process woken late on a virtual
    machine that halts idle CPUs (0.3-1 ms at the median, a pty's delivery 1-2 ms at
    times, measured), which a board on its own processor does not do; over the emulated
    link the board takes each write when it was made (hapsim.emulated.stamped_link), and
    its count is the host's own writes made late (marked, the record cut there: a host
    that cannot keep the sketch's tick on this machine). Each such run must still say no "differs" and "not measurable" with its
    reason; the outcomes are said in pytest's warnings summary."""
    outcomes = []
    excused = 0
    for seed in seeds:
        rep = _wall_run(config, driver, seed)
        m = rep["measured"]
        assert rep["loop"]["mock"]["clock"] == "wall"
        verdict = str(m.get("verdict") or m.get("error"))
        # what a failure needs to be read: the record's cuts and the host's lateness
        outcomes.append((seed, verdict[:60], {q: m.get(q) for q in (
            "samples_used", "stretches_used", "mistimed_rows", "unseen_holds", "cycles")},
            {q: rep["loop"].get(q) for q in ("overruns", "missed", "estimated", "scheduling")},
            {q: rep["loop"]["driver"].get(q) for q in ("read_late", "mispaired", "missing")},
            # the board's own truth: the commands it took off its period (its process
            # late on a loaded or virtual machine, or the host's writes near its boundary)
            (rep["loop"]["mock"].get("tick_arrivals") or {}).get("off_period")))
        assert not verdict.startswith("measured differs"), (seed, verdict, m.get("k"),
                                                             m.get("b"), truth)
        if m.get("within") is True:
            assert _inside(m, truth), (seed, m["k"], m["k_interval"], m["b"],
                                       m["b_interval"], truth)
            if driver == "hapkit-serial":
                assert rep["predicted"]["render_latency_found_s"] == m["render_latency_s"]
            else:
                assert m.get("output_stage", 0) > 0         # the levels were taken out
            return outcomes
        assert m.get("error") or "not measurable" in verdict, (seed, verdict)
        arr = rep["loop"]["mock"].get("tick_arrivals") or {}
        if arr.get("commands") and arr["off_period"] >= OFF_PERIOD_SHARE * arr["commands"]:
            excused += 1
    if excused == len(seeds):
        # said in pytest's summary, not passed over in silence
        import warnings
        warnings.warn(f"{config}: no run within: the emulated board took "
                      f"{OFF_PERIOD_SHARE:g} or more of its commands off its period in every "
                      f"run (not the loop modelled): {outcomes}", stacklevel=2)
        return outcomes
    raise AssertionError(f"no run said within: {outcomes}")


def test_the_hapkit_serial_scene_on_the_sketch_s_board_is_within():
    """``hapsim run configs/hapkit_serial.yaml --driver hapkit-serial`` against the
    emulated sketch on its own (wall) clock: "within", and the felt pair of the board's
    own loop (its render 0.45 ms after its read) inside the stated interval (before, on
    the board that applied the float at its read, the scene's loop; the independent
    model's runs said "differs" every time, docs/testing.md)."""
    from hapsim.drivers.hapkit_serial import RENDER_S, HapkitSerial
    from hapsim.scene import load_scene
    sc = load_scene("configs/hapkit_serial.yaml")
    # the board's loop: its period 4 of the sketch's ticks (252.016 Hz stands for them)
    sc = sc.with_rate(HapkitSerial().board_rate_hz(sc.rate_hz))
    _wall_runs_within("configs/hapkit_serial.yaml", "hapkit-serial", _truth(sc, RENDER_S))


def test_the_haply_scene_on_the_m3_board_is_within():
    """``hapsim run configs/haply.yaml --driver haply`` against the emulated M3 (its 256
    torque levels) on its own clock: "within", the board's own loop's felt pair (its
    delay one period: no render latency) inside the stated interval."""
    from hapsim.scene import load_scene
    _wall_runs_within("configs/haply.yaml", "haply",
                      _truth(load_scene("configs/haply.yaml"), 0.0))


def test_the_sketch_reads_the_handle_in_whole_counts_and_the_driver_states_them():
    """The sketch's position is ``rh (m updatedPos + b)``: whole counts of 17.19 um at the
    handle (``Hapkit_Kinematics_Simulation.h:130-138``, its calibration ``m`` at sim.h:23,
    ``rh`` at :38-40). The emulated board replies with whole counts (to the reply's
    binary32), a scene's own resolution kept; the driver states the count as the sensor
    step the measurement takes (a host stall's record against the independent sketch
    said "differs" of a matching paddle with the step unstated); 0 is a sketch that reads
    the handle exactly, and a negative step is refused."""
    from hapsim.drivers import hapkit_serial as hk
    from hapsim.emulated.hapkit_serial_board import HapkitSerialDevice
    from hapsim.errors import ConfigError
    from hapsim.scene import Device, Excitation
    q = hk.SKETCH_COUNT_M
    assert q == 0.075 * 0.0002292
    drv = hk.HapkitSerial()
    assert drv.position_scale == q and drv.mock_hardware() == {"count_m": q}
    assert hk.HapkitSerial(count_m=0.0).position_scale == 0.0
    with pytest.raises(ConfigError, match="count_m"):
        hk.HapkitSerial(count_m=-1e-6)
    rng = np.random.default_rng(3)
    dev = Device(mass=0.1, friction=0.3, delay=1, force_limit=2.0)
    for count, want in ((None, q), (0.0, 0.0), (None, 5e-6)):
        d = dataclasses.replace(dev, position_resolution=5e-6) if want == 5e-6 else dev
        board = HapkitSerialDevice(d, drv.native_rate_hz, Excitation(x0=0.01), count_m=count)
        xs, now = [], 0.0
        for _ in range(60):
            now += 4 * hk.FIRMWARE_TICK_S
            f = float(rng.uniform(-1.0, 1.0))
            xs.append(hk.ReplyDecoder().feed(board.feed(drv.encode_force(f), now=now))[-1][0])
        x = np.asarray(xs)
        if want:
            # whole counts, to the reply's binary32: the bound derived from its round-off,
            # half an ulp (2^-24 of |x|), and the float64 product N q and quotient x / q
            # (2^-53 each)
            n = x / want
            assert np.all(np.abs(n - np.round(n)) <= (2.0 ** -24 + 2.0 ** -51) * np.abs(n)), n
            assert len(np.unique(np.round(n))) > 5             # it moved
        else:
            n = x / q                                           # read exactly: between counts
            assert np.any(np.abs(n - np.round(n)) > 1e-3)
