"""The daemon in-process: mock physics, the mock's protocol duties, the lockstep closed THS.

Precision carried here (lockstep, no bytes): the measured (k, b) of the closed THS equal the
analysis prediction ``render`` to 1e-6 relative over the whole grid of (m, b0, T, K, B, d,
hold) (144 cases), and
calibrated targets are felt as asked to 1e-6. The mock's ZOH step is checked against an
independent formula (scipy.linalg.expm of the augmented matrix) to 1e-12.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

import firmware_protocol as fp
from hapsim.analysis.loop import LoopModel, plant, zoh_state_space
from hapsim.analysis.ths import calibrate, render
from hapsim.analysis.stability import stability_limit
from hapsim.host.loop import HostLoop, LoopConfig, StopFlag
from hapsim.emulated.mock import (MockDevice, MockPhysics, hand_force_samples,
                                ideal_step_coefficients, zoh_step_coefficients)
from hapsim.pipeline.runner import identify, run_scene
from hapsim.host.telemetry import Telemetry, load_telemetry
from hapsim.emulated.links import InProcessTransport
from hapsim.engine import Engine
from hapsim.errors import ConfigError, UnstableConfigError
from hapsim.scene import Device, Excitation, Impulse, parse_scene
from tolerance import rel_tol


def wall_text(K, B, *, m=0.1, b0=0.5, d=1, hold="zoh", rate=1000.0, x0=0.005, extra_dev="",
              excitation=None, target=None, force_limit=10.0):
    link = (f"target: {{k: {target[0]}, b: {target[1]}}}" if target is not None
            else f"stiffness: {K}, damping: {B}")
    exc = excitation if excitation is not None else f"{{x0: {x0}}}"
    return f"""
rate_hz: {rate}
masses:
  - {{name: hand, kind: port}}
  - {{name: wall, kind: ground, x0: 0.0}}
links:
  - {{name: wall, kind: spring_damper, between: [hand, wall], {link}}}
device: {{mass: {m}, friction: {b0}, delay: {d}, hold: {hold},
          force_limit: {force_limit}{extra_dev}}}
excitation: {exc}
"""


def late_tolerant_wall(directory, late: int = 10) -> str:
    """configs/wall.yaml with a wall that stays stable while the host's FORCEs arrive up
    to ``late`` samples late, written to ``directory``; returns the file's path.

    The device holds the last force it got, so a FORCE ``late`` samples late makes the
    loop's delay ``1 + late`` samples for that stretch. The shipped wall (K = 1000 N/m,
    B = 1.5 N s/m, d = 1) is stable at its own delay only (K_max 1313 N/m at d = 1, 785
    N/m at d = 2): on a loaded machine a real-time run on it grows to the force limit
    and ends on a safety stop (exit 1). Tests of what a real-time run does (journal,
    signals, faults, kill -9) rather than of what it measures take this wall: K at 0.9
    times the stability limit at delay ``1 + late`` (the same B), about 150 N/m for 10
    samples (10 ms at 1 kHz), the rest of the scene unchanged.
    """
    import re
    from pathlib import Path

    from hapsim.analysis.loop import LoopModel
    from hapsim.analysis.stability import stability_limit
    from hapsim.scene import load_scene

    shipped = Path(__file__).resolve().parents[1] / "configs" / "wall.yaml"
    sc = load_scene(shipped)
    dev, link = sc.device, sc.links[0]
    K = 0.9 * stability_limit(LoopModel(mass=dev.mass, friction=dev.friction,
                                        rate_hz=sc.rate_hz, delay=dev.delay + late,
                                        hold=dev.hold), link.damping)
    text, n = re.subn(r"stiffness: [0-9.e+]+", f"stiffness: {K:.6g}", shipped.read_text())
    assert n == 1 and K < link.stiffness, (n, K)
    path = Path(directory) / "late_tolerant_wall.yaml"
    path.write_text(text)
    return str(path)


def lockstep(text, **kw):
    kw.setdefault("duration", 1.0)
    return run_scene(parse_scene(text), transport="inprocess", lockstep=True,
                     handle_signals=False, **kw)


# --------------------------------------------------------------------------- physics

@pytest.mark.numerical
@pytest.mark.parametrize("m,b0,T", [(0.1, 0.5, 1e-3), (1.0, 0.0, 1e-3), (0.05, 3.0, 2e-4),
                                    (0.2, 40.0, 1e-3), (2.0, 1e-4, 5e-5)])
def test_zoh_step_matches_expm_of_augmented_matrix(m, b0, T):
    """Closed form of the mock == expm([[A, B], [0, 0]] T) to 1e-12 (independent formula)."""
    a, cxv, cxu, cvu = zoh_step_coefficients(m, b0, T)
    M = np.zeros((3, 3))
    M[0, 1] = 1.0
    M[1, 1] = -b0 / m
    M[1, 2] = 1.0 / m
    E = scipy.linalg.expm(M * T)
    ours = np.array([[1.0, cxv, cxu], [0.0, a, cvu]])
    # measured 1.3e-14 relative (generic 1.3e-14), margin 270 (worst of 5)
    np.testing.assert_allclose(ours, E[:2], rtol=1e-12, atol=1e-15 * max(T, 1e-3))
    # and the analysis's own closed form agrees
    Ad, Bd = zoh_state_space(m, b0, T)
    # measured 0 (generic 0): exact on both targets
    np.testing.assert_allclose(ours[:, :2], Ad, rtol=1e-12)
    # measured 7.6e-15 relative (generic 7.6e-15), margin 130 (worst of 5)
    np.testing.assert_allclose(ours[:, 2], Bd, rtol=1e-12)


@pytest.mark.numerical
def test_mock_trajectory_matches_expm_propagation():
    """1000 ticks with random held forces: MockPhysics == expm propagation to 1e-12."""
    m, b0, rate = 0.1, 0.5, 1000.0
    T = 1 / rate
    ph = MockPhysics(Device(mass=m, friction=b0), rate, Excitation(x0=0.003, v0=-0.02))
    M = np.zeros((3, 3))
    M[0, 1], M[1, 1], M[1, 2] = 1.0, -b0 / m, 1.0 / m
    E = scipy.linalg.expm(M * T)
    rng = np.random.default_rng(1)
    s = np.array([0.003, -0.02, 0.0])
    xs, ref = [], []
    for _ in range(1000):
        u = float(rng.normal())
        s[2] = u
        s = E @ s
        ph.advance(u)
        xs.append(ph.x)
        ref.append(s[0])
    # measured 1.4e-14 relative (generic 1.9e-16), margin 10000
    np.testing.assert_allclose(xs, ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)))


@pytest.mark.numerical
def test_ideal_hold_is_the_papers_sampled_image():
    """Ideal hold: x follows D(z) X = N(z) U of analysis.plant(hold='ideal') (eq. (4))."""
    m, b0, rate = 0.1, 0.5, 1000.0
    loop = LoopModel(m, b0, rate, 1, "ideal")
    N, D = plant(loop)
    ph = MockPhysics(Device(mass=m, friction=b0, hold="ideal"), rate, Excitation())
    rng = np.random.default_rng(2)
    u = rng.normal(size=500)
    x = []
    for ui in u:
        ph.advance(float(ui))
        x.append(ph.x)
    # X(z)/U(z) = N/D, proper: pad N to D's length so lfilter's z^-1 powers line up;
    # then y[n] = x[n] (x[0] = 0) while the list holds x[1], x[2], ...
    y = scipy.signal.lfilter(np.concatenate([np.zeros(len(D) - len(N)), N]), D, u)
    # measured 1.5e-11 relative (generic 1.5e-11), margin 35
    np.testing.assert_allclose(np.array(x)[:-1], y[1:], rtol=1e-10, atol=1e-14)
    a, cu = ideal_step_coefficients(m, 0.0, 1 / rate)
    # measured 0 (generic 0): exact on both targets
    assert a == 1.0 and cu == pytest.approx((1 / rate) ** 2 / m, rel=1e-15)


def test_impulse_mean_over_period_and_profile(tmp_path):
    T = 1e-3
    h = hand_force_samples(Excitation(impulse=Impulse(2.0, 0.0015, 0.002)), T)
    # measured 0 (generic 0): exact on both targets
    np.testing.assert_allclose(h, [0, 1.0, 2.0, 1.0])
    prof = tmp_path / "hand.csv"
    prof.write_text("time,force\n0.0,0.0\n0.004,4.0\n")
    h = hand_force_samples(Excitation(profile=str(prof)), T)
    # measured 0 (generic 0): exact on both targets
    np.testing.assert_allclose(h, [0.5, 1.5, 2.5, 3.5, 0.0])


def test_quantisation_noise_and_coulomb_only_when_asked():
    dev = Device(mass=0.1, friction=0.5, position_resolution=1e-4, noise=1e-5)
    ph = MockPhysics(dev, 1000.0, Excitation(x0=0.00123), seed=3)
    s = ph.sample()
    q, sigma = 1e-4, 1e-5                # the device's position_resolution and noise [m]
    # s = q round(y / q), so s / q is a whole number to the round-off of a product and a
    # quotient (tests/tolerance.py rel_tol(2)); the bound on s - x0: half a quantum plus
    # 15 sigma of a normal draw (seed 3 draws z = 2.04: measured |s - x0| = 7e-5 m, and
    # |s / q - n| = 1.8e-15 against rel_tol(2) n = 2.9e-14, pure Python on both targets)
    assert abs(s / q - round(s / q)) <= rel_tol(2) * abs(s / q) and \
        abs(s - 0.00123) < 0.5 * q + 15 * sigma
    stuck = MockPhysics(Device(mass=0.1, coulomb=1.0), 1000.0, Excitation(x0=0.001))
    stuck.advance(0.5)          # below the Coulomb level from rest: does not move
    assert stuck.x == 0.001 and stuck.v == 0.0
    plain = MockPhysics(Device(mass=0.1), 1000.0, Excitation(x0=0.001))
    assert plain.sample() == 0.001


# --------------------------------------------------------------------------- protocol duties

def _armed(lockstep=True, d=1, limit=10.0, watchdog_us=5000):
    mock = MockDevice(Device(mass=0.1, friction=0.5, delay=d, force_limit=limit),
                      Excitation(x0=0.001), lockstep=lockstep)
    out = mock.handle(fp.Config(1000.0, watchdog_us, 100.0), 0)
    return mock, out


def test_mock_hello_ping_config_stop():
    mock, out = _armed()
    assert isinstance(out[0], fp.State) and out[0].seq == 0 and out[0].status & fp.STATUS_ARMED
    hello = mock.handle(fp.HelloRequest(), 0)[0]
    assert isinstance(hello, fp.Hello) and hello.n_axes == 1 and hello.force_limit == 10.0
    assert mock.handle(fp.Ping(7, 123), 456) == [fp.Pong(7, 123, 456)]
    # CONFIG's limit 100 N is lowered to the device's 10 N: a 50 N force is clamped
    st = mock.handle(fp.Force(0, (50.0,)), 0)[0]
    assert st.seq == 1 and st.force_seq == 0 and st.status & fp.STATUS_FORCE_CLAMPED
    assert mock.stats.last_applied == 10.0 and mock.stats.clamped == 1
    assert mock.handle(fp.Stop(), 0) == []
    assert mock.stats.saw_stop and mock.stats.last_applied == 0.0 and not mock.armed
    assert mock.handle(fp.Force(1, (1.0,)), 0) == []     # disarmed: ignored
    assert isinstance(mock.handle(fp.Config(0.0, 1, 1.0))[0], fp.Fault)


def test_mock_non_finite_force_faults_and_disarms():
    mock, _ = _armed()
    out = mock.handle(fp.Force(0, (math.nan,)), 0)
    assert out == [fp.Fault(fp.FAULT_NON_FINITE_FORCE, 0)]
    assert not mock.armed and mock.stats.last_applied == 0.0


def test_real_time_late_force_holds_and_watchdog_zeroes():
    mock, out = _armed(lockstep=False, d=1, watchdog_us=5000)
    assert out == []
    s0 = mock.tick(0)
    assert s0.seq == 0
    mock.handle(fp.Force(0, (2.0,)), 500)
    s1 = mock.tick(1000)                       # FORCE 0 due at tick 1: applied
    assert s1.force_seq == 0 and mock.stats.last_applied == 2.0 and mock.stats.late == 0
    s2 = mock.tick(2000)                       # FORCE 1 missing: last force held, counted
    assert s2.status & fp.STATUS_OVERRUN and mock.stats.late == 1
    assert mock.stats.last_applied == 2.0 and s2.force_seq == 0
    mock.handle(fp.Force(1, (3.0,)), 2100)     # late: never applied at tick 3 (wants seq 2)
    mock.tick(3000)
    assert mock.stats.last_applied == 2.0 and mock.stats.late == 2
    for t in range(4000, 12000, 1000):         # silence beyond 5 ms: watchdog zeroes force
        st = mock.tick(t)
    assert st.status & fp.STATUS_WATCHDOG_TRIPPED and mock.stats.last_applied == 0.0
    assert mock.stats.watchdog_trips >= 1


def test_real_time_mock_refuses_zero_delay():
    with pytest.raises(ConfigError, match="lockstep only"):
        MockDevice(Device(mass=0.1, delay=0), lockstep=False)


# --------------------------------------------------------------------------- lockstep THS

def _grid():
    cases = []
    for m, b0, rate, d, hold in itertools.product((0.1, 0.5), (0.0, 0.5, 2.0), (1000.0, 4000.0),
                                                  (0, 1, 2), ("zoh", "ideal")):
        loop = LoopModel(m, b0, rate, d, hold)
        for B in (0.5, 3.0):
            kmax = stability_limit(loop, B)
            if not (kmax > 0):
                continue
            K = 0.5 * min(kmax, 4e4)
            cases.append((m, b0, rate, d, hold, K, B))
    return cases                # 144 cases, ~0.1 s each


GRID = _grid()


@pytest.mark.parametrize("m,b0,rate,d,hold,K,B", GRID,
                         ids=[f"m{c[0]}-b{c[1]}-r{c[2]:g}-d{c[3]}-{c[4]}-K{c[5]:.0f}-B{c[6]}"
                              for c in GRID])
def test_lockstep_measured_equals_render(m, b0, rate, d, hold, K, B):
    """In-process lockstep: measured (k, b) == analysis.render (k, b) to 1e-6 relative.

    No absolute term on b: over the whole grid the worst relative error of b is 2.3e-11
    (b = 0.25 N s/m, m = 0.5 kg, 4 kHz, ideal hold), far inside 1e-6."""
    rep = lockstep(wall_text(K, B, m=m, b0=b0, d=d, hold=hold, rate=rate, force_limit=1e6))
    r = render(LoopModel(m, b0, rate, d, hold), K, B)
    meas = rep["measured"]
    assert "k" in meas, meas
    # measured 9.1e-13 relative (generic 9.9e-13), margin 1e6 (worst of 144)
    assert meas["k"] == pytest.approx(r.k, rel=1e-6)
    # measured 2.1e-11 relative (generic 2.1e-11), margin 46000 (worst of 144)
    assert meas["b"] == pytest.approx(r.b, rel=1e-6)
    # measured 0 (generic 0): exact on both targets
    assert rep["predicted"]["k"] == pytest.approx(r.k, rel=1e-12)
    assert rep["loop"]["late"] == 0 and rep["loop"]["missed"] == 0
    assert rep["loop"]["mock"]["saw_stop"] and rep["loop"]["mock"]["last_applied"] == 0.0


def test_grid_covers_every_dimension():
    assert len(GRID) == 144
    for i, values in enumerate(((0.1, 0.5), (0.0, 0.5, 2.0), (1000.0, 4000.0), (0, 1, 2),
                                ("zoh", "ideal"))):
        assert {c[i] for c in GRID} == set(values)


@pytest.mark.parametrize("k,b,d,hold", [(1000.0, 3.0, 1, "zoh"), (300.0, 1.0, 2, "zoh"),
                                        (2000.0, 4.0, 0, "zoh"), (800.0, 2.0, 1, "ideal")])
def test_calibrated_target_is_felt_as_asked(k, b, d, hold):
    """A link given as target {k, b}: the lockstep THS rings at exactly (k, b) (1e-6)."""
    rep = lockstep(wall_text(0, 0, d=d, hold=hold, target=(k, b)))
    assert rep["target"]["renderable"]
    cal = calibrate(LoopModel(0.1, 0.5, 1000.0, d, hold), k, b)
    # measured 0 (generic 0): exact on both targets
    assert rep["virtual"]["K"] == pytest.approx(cal.K, rel=1e-12)
    # measured 1.6e-14 relative (generic 1.8e-14), margin 5.6e7 (worst of 4)
    assert rep["measured"]["k"] == pytest.approx(k, rel=1e-6)
    # measured 1.4e-13 relative (generic 5.5e-14), margin 6.9e6 (worst of 4)
    assert rep["measured"]["b"] == pytest.approx(b, rel=1e-6)


def test_every_target_link_is_reported_with_its_verdict():
    """Two target links: JSON ``targets`` has both (``target`` keeps the first), the text
    report prints each with its renderability verdict."""
    from hapsim.pipeline.runner import format_report
    text = wall_text(0, 0, target=(300.0, 2.0)) .replace(
        "links:\n", "links:\n  - {name: firm, kind: spring_damper, between: [hand, wall], "
        "target: {k: 200.0, b: 1.5}}\n")
    rep = lockstep(text)
    ts = rep["targets"]
    assert [t["link"] for t in ts] == ["firm", "wall"] and rep["target"] == ts[0]
    assert all(t["renderable"] and t["reason"] for t in ts)
    assert "rel_err_target" not in rep["measured"]      # the felt pair is their sum
    out = format_report(rep)
    for t in ts:
        assert f"link {t['link']}: renderable (" in out
    assert out.count("  target ") == 2
    # one target: the verdict is printed too, and the measurement compared with it
    one = lockstep(wall_text(0, 0, target=(1000.0, 3.0)))
    assert "link wall: renderable (every other pole" in format_report(one)
    assert "rel_err_target" in one["measured"] and len(one["targets"]) == 1


def test_felt_wall_config_is_felt_as_asked():
    from hapsim.scene import load_scene
    rep = run_scene(load_scene("configs/felt_wall.yaml"), transport="inprocess", lockstep=True,
                    handle_signals=False)
    assert rep["target"]["k"] == 1000.0 and rep["target"]["b"] == 3.0
    # measured 2.5e-15 relative (generic 3e-15), margin 3.3e8
    assert rep["measured"]["k"] == pytest.approx(1000.0, rel=1e-6)
    # measured 4.1e-14 relative (generic 4.1e-14), margin 2.4e7
    assert rep["measured"]["b"] == pytest.approx(3.0, rel=1e-6)


def test_unrenderable_target_is_refused():
    # 40 Hz with a tiny damping through one sample of delay and little friction: the
    # analysis finds a parasitic pole or instability; the run refuses with the reason
    text = wall_text(0, 0, b0=0.0, d=2, target=(50000.0, 0.01))
    with pytest.raises(UnstableConfigError, match="not renderable"):
        lockstep(text)


def test_impulse_excitation_is_identified_after_it_ends():
    text = wall_text(1000.0, 1.5, x0=0.0,
                     excitation="{impulse: {force: 2.0, start: 0.002, duration: 0.003}}")
    rep = lockstep(text)
    # measured 0 (generic 0): exact on both targets
    assert rep["loop"]["excitation_end_s"] == pytest.approx(0.005)
    assert rep["measured"]["first_seq"] >= 5 + 1 + 3
    # measured 7.8e-16 relative (generic 1.3e-15), margin 7.4e8
    assert rep["measured"]["k"] == pytest.approx(rep["predicted"]["k"], rel=1e-6)


def test_unstable_scene_refused_with_radius_and_limit():
    with pytest.raises(UnstableConfigError) as ei:
        lockstep(wall_text(3000.0, 1.5))
    e = ei.value
    assert e.spectral_radius > 1 and 1000 < e.stiffness_limit < 3000
    assert "spectral radius" in str(e) and "stiffness limit" in str(e)


def test_allow_unstable_ends_in_safety_stop_with_zero_force():
    rep = lockstep(wall_text(3000.0, 1.5), allow_unstable=True, duration=5.0)
    lp = rep["loop"]
    assert lp["safety_stop"] and lp["stop_reason"].startswith("safety")
    assert lp["ticks"] < 5000
    assert lp["mock"]["saw_stop"] and lp["mock"]["last_applied"] == 0.0
    assert lp["mock"]["last_host_message"] == "Stop"
    assert rep["exit_code"] == 1


def test_a_safety_stop_says_what_came_before_it():
    """The report of a safety stop holds what the device did before it
    (``loop.safety_context``, :func:`hapsim.pipeline.report.safety_context`): a loop that
    grew (in lockstep: the device's time one period a sample exactly, a new FORCE applied
    at each, forces to the limit, no watchdog), and, on a telemetry written here, a host
    that stalled 60 ms while the device held its last FORCE and its watchdog zeroed it
    after 50 (the counts exact)."""
    from hapsim.pipeline.report import format_report, safety_context
    rep = lockstep(wall_text(3000.0, 1.5), allow_unstable=True, duration=5.0)
    sc = rep["loop"]["safety_context"]
    assert sc is not None and sc["rows"] == min(rep["loop"]["ticks"], 300), sc
    t = sc["step_at_s"]
    # (device times are whole microseconds, each divided by 1e6 and rounded: half an ulp
    # of each time, and half an ulp of the difference's rounding, derived at the times
    # the step ended at, the largest in the run)
    assert abs(sc["largest_step_s"] - 1e-3) <= np.spacing(t) + 0.5 * np.spacing(1e-3), sc
    # (the run's first two samples both name FORCE 0: none is applied before it, d = 1)
    assert sc["longest_same_force_rows"] == (2 if sc["from_s"] == 0.0 else 1), sc
    assert sc["watchdog_rows"] == 0, sc
    assert sc["force_abs_max_n"] == 10.0, sc
    assert abs(sc["position_last_m"]) > abs(sc["position_first_m"]), sc
    assert "before the stop (its last" in format_report(rep)
    tel = Telemetry(400)
    n = 300
    tel.time[:n] = np.arange(n) * 1e-3
    tel.force_seq[:n] = np.arange(n) - 1
    tel.force_seq[100:160] = 98                 # the host silent: FORCE 98 held 61 samples
    tel.status[150:160] = fp.STATUS_WATCHDOG_TRIPPED | fp.STATUS_OVERRUN
    tel.force[:n] = 0.5
    tel.force[150:160] = 0.0
    tel.position[:n] = np.linspace(0.0, -0.12, n)
    tel.n = n
    sc = safety_context(tel, rows=250)
    assert sc["rows"] == 250 and sc["from_s"] == tel.time[50], sc
    assert sc["longest_same_force_rows"] == 61, sc      # rows 99..159
    assert sc["watchdog_rows"] == 10 and sc["overrun_rows"] == 10, sc
    assert sc["force_abs_max_n"] == 0.5 and sc["position_last_m"] == -0.12, sc
    assert safety_context(Telemetry(10)) is None
    # a run that did not stop says nothing of it
    assert lockstep(wall_text(1000.0, 1.5), duration=0.2)["loop"]["safety_context"] is None


# --------------------------------------------------------------------------- host safety

class _NanMock(MockDevice):
    """A device whose encoder returns NaN from tick 10 on."""

    def _emit(self, now_us):
        st = super()._emit(now_us)
        if st.seq >= 10:
            return fp.State(st.seq, st.time_us, st.status, st.force_seq, (math.nan,))
        return st


def test_non_finite_position_sends_zero_force_and_stops():
    scene = parse_scene(wall_text(1000.0, 1.5))
    mock = _NanMock(scene.device, scene.excitation, lockstep=True)
    sent = []
    tr = InProcessTransport(mock)
    orig = tr.send
    tr.send = lambda msg: (sent.append(msg), orig(msg))
    tel = Telemetry(100)
    eng = Engine(scene)
    res = HostLoop(eng, tr, LoopConfig(1000.0, 100, force_limit=10.0), tel).run()
    assert res.safety_stop and "non-finite" in res.stop_reason
    forces = [m for m in sent if isinstance(m, fp.Force)]
    assert forces[-1].force == (0.0,) and isinstance(sent[-1], fp.Stop)
    assert mock.stats.saw_stop and mock.stats.last_applied == 0.0
    assert tel.n == 10


def test_stop_flag_ends_loop_cleanly():
    scene = parse_scene(wall_text(1000.0, 1.5))
    mock = MockDevice(scene.device, scene.excitation, lockstep=True)
    flag = StopFlag()

    class Tr(InProcessTransport):
        def receive(self, timeout=0.0):
            if self.mock.stats.ticks >= 50:
                flag.request(15)
            return super().receive(timeout)

    tel = Telemetry(1000)
    res = HostLoop(Engine(scene), Tr(mock), LoopConfig(1000.0, 1000), tel, flag).run()
    assert res.stop_reason == "signal SIGTERM" and not res.safety_stop
    assert 49 <= tel.n <= 51 and mock.stats.saw_stop and mock.stats.last_applied == 0.0


def test_host_clamps_force():
    rep = lockstep(wall_text(1000.0, 1.5, x0=0.02, force_limit=10.0), allow_unstable=False,
                   duration=0.05)
    assert rep["loop"]["clamped"] > 0
    assert rep["loop"]["mock"]["clamped"] == 0        # the host clamped first


# --------------------------------------------------------------------------- telemetry

@pytest.mark.parametrize("ext", [".npz", ".csv"])
def test_telemetry_written_atomically_and_loads(tmp_path, ext):
    path = str(tmp_path / f"t{ext}")
    rep = lockstep(wall_text(1000.0, 1.5), telemetry=path, duration=0.2)
    data = load_telemetry(path)
    assert rep["telemetry"]["samples"] == 200 == data["seq"].size
    np.testing.assert_array_equal(data["seq"], np.arange(200))
    # measured 2.8e-17 abs, 2.1e-16 rel (generic 2.8e-17 abs, 2.1e-16 rel), margin 3.6e10 (worst of 2)
    np.testing.assert_allclose(data["time"], np.arange(200) * 1e-3, atol=1e-6)
    # measured 0 (generic 0): exact on both targets
    assert data["position"][0] == pytest.approx(0.005)
    # measured 0 (generic 0): exact on both targets
    assert data["force"][0] == pytest.approx(-5.0)
    assert not (tmp_path / f"t{ext}.partial").exists()


def test_identify_uses_longest_consecutive_run():
    T, m = 1e-3, 0.1
    n = np.arange(600)
    s = -5 + 100j
    y = np.exp(s.real * n * T) * np.cos(s.imag * n * T)
    seq = n.copy()
    seq[100:] += 3            # a gap: the longest run is after it
    out = identify(y, seq, T, 2, m, 0)
    # measured 1.1e-15 relative (generic 3.4e-16), margin 8.8e5
    assert out["first_seq"] == 103 + 3 and out["k"] == pytest.approx(m * abs(s) ** 2, rel=1e-9)
    # a late tick cuts the record too; with no long clean stretch the whole run is used
    late = np.zeros(600, dtype=np.int8)
    late[300] = 1
    out = identify(y, seq, T, 2, m, 0, late=late, skip=2)
    assert out["first_seq"] == 300 + 3 + 2 and out["late_in_segment"] == 0   # seq 303 late
    late[::50] = 1
    out = identify(y, n, T, 2, m, 0, late=late)
    assert out["samples_used"] == 600 and out["late_in_segment"] == 11


def test_bad_arguments():
    text = wall_text(1000.0, 1.5)
    with pytest.raises(ConfigError):
        lockstep(text, duration=-1.0)
    with pytest.raises(ConfigError):
        run_scene(parse_scene(text), transport="inprocess", lockstep=False, handle_signals=False)
    with pytest.raises(ConfigError):
        lockstep(text, telemetry="x.txt")
    with pytest.raises(ConfigError, match="lockstep"):
        run_scene(parse_scene(wall_text(1000.0, 1.5, d=0)), handle_signals=False)


def test_scene_with_virtual_mass_matches_check_scene():
    """Port - spring - mass - spring - ground: measured == check_scene's rendered pair."""
    from hapsim.analysis.scene_check import check_scene
    text = """
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: bob, kind: mass, mass: 0.05}
  - {name: wall, kind: ground, x0: 0.0}
links:
  - {name: a, kind: spring_damper, between: [hand, bob], stiffness: 800.0, damping: 1.0}
  - {name: b, kind: spring_damper, between: [bob, wall], stiffness: 500.0, damping: 0.5}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10.0}
excitation: {x0: 0.005}
"""
    scene = parse_scene(text)
    rep = lockstep(text, duration=2.0)
    chk = check_scene(scene)
    assert rep["predicted"]["source"] == "check_scene" and rep["predicted"]["order"] == 6
    # measured 1.4e-14 relative (generic 1.2e-14), margin 6.8e7
    assert rep["measured"]["k"] == pytest.approx(chk.rendered.k, rel=1e-6)
    # measured 1.1e-13 relative (generic 4.2e-13), margin 2.3e6
    assert rep["measured"]["b"] == pytest.approx(chk.rendered.b, rel=1e-6)
    assert "virtual masses" in rep["measured"]["note"]


def test_coulomb_stops_a_free_mass_at_the_physical_distance():
    """Free mass, v0, Coulomb C: stops after v0^2 m / (2 C) (to one tick of motion)."""
    ph = MockPhysics(Device(mass=0.1, coulomb=0.01), 1000.0, Excitation(v0=0.01))
    for _ in range(300):
        ph.advance(0.0)
    # bound: a tick whose velocity crosses zero ends at v = 0 but moves x the whole tick
    # under the deceleration C/m, short of the true stop by (C/m) (T - t_stop)^2 / 2 <=
    # (C/m) T^2 / 2 = 5e-8 m (measured exactly that: v0 / (C/m) = 100 ticks, the stop at a
    # tick's start); the tolerance (C/m) T^2 is twice it, for the 100 steps' round-off
    C, m, T, v0 = 0.01, 0.1, 1e-3, 0.01
    assert ph.v == 0.0 and ph.x == pytest.approx(v0 ** 2 * m / (2 * C), abs=C / m * T ** 2)


@pytest.mark.parametrize("extra", [", noise: 1.0e-7", ", position_resolution: 1.0e-6"])
def test_noise_and_quantisation_only_perturb_the_measurement_slightly(extra):
    """Seeded noise / encoder quantum: deterministic, measured within 1e-3 of render."""
    rep = lockstep(wall_text(1000.0, 1.5, extra_dev=extra))
    assert "quantisation" in rep["measured"]["note"]
    # not round-off: the seeded noise's and the quantum's effect on the fit, deterministic;
    # measured 3.5e-6 relative (generic 3.5e-6), margin 280 (worst of 2)
    assert rep["measured"]["k"] == pytest.approx(rep["predicted"]["k"], rel=1e-3)
    # measured 4.7e-5 relative (generic 4.7e-5), margin 210 (worst of 2)
    assert rep["measured"]["b"] == pytest.approx(rep["predicted"]["b"], rel=1e-2)
    assert rep["measured"]["k"] != rep["predicted"]["k"]


def test_device_falling_silent_raises_device_error_and_keeps_telemetry(tmp_path, monkeypatch):
    """A device that stops answering: DeviceError with the last frames; telemetry kept."""
    import hapsim.pipeline.runner as runner_mod
    from hapsim.errors import DeviceError

    class Silent(MockDevice):
        def _on_force(self, msg, now_us):
            return [] if msg.seq >= 20 else super()._on_force(msg, now_us)

    scene = parse_scene(wall_text(1000.0, 1.5))
    path = str(tmp_path / "t.npz")
    monkeypatch.setattr(runner_mod, "MockDevice", Silent)
    with pytest.raises(DeviceError, match="no STATE"):
        run_scene(scene, transport="inprocess", lockstep=True, handle_signals=False,
                  telemetry=path)
    assert load_telemetry(path)["seq"].size == 21


def test_force_seq_read_only_when_the_device_says_it_is_valid():
    """PROTOCOL.md §4: force_seq names the FORCE applied only with STATUS_FORCE_APPLIED.
    After CONFIG, STATE seq 0 is answered by FORCE seq 0, so force_seq = 0 alone cannot
    tell "FORCE 0 applied" from "none applied yet"; the bit can."""
    from hapsim.kernels.ticks import named_delay, tick_late
    A = fp.STATUS_FORCE_APPLIED
    d = 1
    # a device that sets the bit: FORCE 0 applied at tick 1 is on time ...
    assert not tick_late(1, 0, A, d, True)
    # ... and at tick 1 with no FORCE applied yet (bit clear, force_seq 0) it is late,
    # which the bare force_seq comparison (1 - 0 == d) would have missed
    assert tick_late(1, 0, 0, d, True)
    assert tick_late(5, 3, A, d, True)           # an older FORCE held
    # a device that never sets the bit is read by force_seq alone, as before
    assert not tick_late(1, 0, 0, d, False)
    assert tick_late(5, 3, 0, d, False)
    assert named_delay(0, 0xFFFFFFFF, A, True) == 1          # mod 2^32


@pytest.mark.xdist_group("realtime")     # (its two runs in real time: tests/conftest.py)
def test_a_real_time_run_says_when_a_force_a_period_late_runs_its_loop_away(tmp_path):
    """A device holds the last force it got, so a FORCE a host sends a period late makes
    the loop's delay a period longer for that stretch: a loop stable at its own delay but
    not at that one grows on a host that falls behind (configs/wall.yaml: K_max 1313 N/m
    at d = 1, 785 at d = 2, its wall 1000 N/m; ``late_tolerant_wall`` above was written
    for that). Random devices and walls on the framed protocol, 6 seeded draws, the
    limits from the loop model itself at d and d + 1: a wall between them is prepared
    for a real-time run with the warning, naming d + 1, and not refused; below the d + 1
    limit, and in lockstep (the device waits for each FORCE), without it. A real-time run
    of the shipped wall (0.3 s, the embedded mock) reports it among its warnings; the
    README's first wall (stable at d = 3) reports none."""
    import json

    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    from inproc import hapsim_main  # same directory (pytest prepend import mode)
    from hapsim.analysis.stability import stability_limit
    rng = np.random.default_rng(11)
    for i in range(6):
        m, b0, B = (float(rng.uniform(0.05, 0.5)), float(rng.uniform(0.0, 1.0)),
                    float(rng.uniform(0.5, 3.0)))
        d = int(rng.integers(1, 4))
        k1, k2 = (stability_limit(LoopModel(mass=m, friction=b0, rate_hz=1000.0, delay=dd,
                                            hold="zoh"), B) for dd in (d, d + 1))
        assert k2 < k1
        for K, warned in ((0.5 * (k1 + k2), True), (0.95 * k2, False)):
            path = tmp_path / f"w{i}{warned}.yaml"
            path.write_text(wall_text(K, B, m=m, b0=b0, d=d, x0=0.001))
            for lock in (False, True):
                prep = prepare_run(load_scene(str(path)), RunOptions(
                    handle_signals=False, lockstep=lock))
                said = prep.pred.get("late_force_warning")
                assert (said is not None) is (warned and not lock), (i, K, lock, said)
                if said:
                    assert prep.pred["late_force_unstable"]["delay"] == d + 1
                    assert f"d = {d + 1}:" in said
    for scene, warned in (("configs/wall.yaml", True), ("configs/first_wall.yaml", False)):
        code, out, err = hapsim_main(["run", scene, "--duration", "0.3", "--json"])
        assert out, (code, err)
        lp = json.loads(out)["loop"]
        # the shipped wall is what its warning says: a host a period behind can run it to
        # its safety stop (exit 1, the report written: once in a whole suite on a slow,
        # loaded machine); the wall without the warning is never stopped by a host a
        # period behind: only by the lateness guard, on a host so far behind that the
        # device held a force older than every delay its loop is stable at (once in a
        # fresh clone's CI, beside the second pass: "the loop is stable up to 5 periods
        # of delay"; the guard counts nothing else), its late ticks in the record (one at
        # least: a stall's backlog answered at its newest STATE counts one)
        assert code == 0 or (code == 1 and lp["safety_stop"]), (code, err, lp["stop_reason"])
        if code == 1 and not warned:
            assert "FORCEs came too late" in lp["stop_reason"], lp["stop_reason"]
            assert lp["late"] >= 1 and lp["safety"]["late_guard"]["stable_to_periods"] > 1
        ws = lp["warnings"]
        assert any("a FORCE a period late" in w for w in ws) is warned, ws
