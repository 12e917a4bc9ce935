"""hapsim zwidth (issue 22): the stiffness limit K_max(B) measured on the mock from short
records (the dominant pole's modulus from the identified felt pair), beside the exact
linear prediction and the describing-function prediction with Coulomb friction."""

from __future__ import annotations

import json

import pytest

from hapsim.cli import main
from seeds import seeds  # same directory

COULOMB = """rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: 0.0}
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000.0, damping: 1.5}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10.0,
         coulomb: 0.05, position_resolution: 1.0e-5}
excitation: {x0: 0.005}
"""


def _one_point(capsys, argv):
    rc = main(["zwidth", *argv, "--json"])
    rep = json.loads(capsys.readouterr().out)
    assert rc == 0
    (p,) = rep["points"]
    return rep, p


def test_lockstep_mock_measures_the_linear_limit(capsys):
    """The lockstep mock is the linear THS: measured = predicted (target 1 %; the records
    give it to ~1e-9), the interval holds it, the records below decay (rho < 1) and the
    first one above grows; the search starts below the limit and raises K."""
    rep, p = _one_point(capsys, ["--lockstep", "--B", "1.5", "--start", "0.9"])
    assert set(p) >= {"B", "K_max_predicted", "K_max_measured", "K_max_measured_interval"}
    Kp, Km, (lo, hi) = p["K_max_predicted"], p["K_max_measured"], \
        p["K_max_measured_interval"]
    # measured 3.9e-11 relative (generic 3.9e-11), margin 25000; the interval is the
    # search's last bracket (tol 2e-3 of K) widened by the records' uncertainty
    assert abs(Km - Kp) <= 1e-6 * Kp and lo <= Kp <= hi and (hi - lo) <= 3e-3 * Kp
    trials = p["trials"]
    assert trials[0]["K"] < Kp and not trials[0]["growing"] and trials[0]["rho"] < 1.0
    for t in trials:
        assert t["growing"] == (t["K"] > Kp) and (t["rho"] > 1.0) == (t["K"] > Kp)
    assert rep["follows"] == "linear"


def test_coulomb_and_quantisation_move_the_limit_as_the_describing_function_says(
        tmp_path, capsys):
    """With Coulomb friction (0.05 N) and a 10 um encoder the device renders stiffer
    walls than the linear limit at the record's amplitude: the measured limit follows the
    describing-function prediction to 1 % and the linear limit lies outside its interval."""
    f = tmp_path / "coulomb.yaml"
    f.write_text(COULOMB)
    rep, p = _one_point(capsys, ["--scene", str(f), "--lockstep", "--B", "1.5",
                                    "--tol", "0.01", "--start", "0.9"])
    assert rep["follows"] == "coulomb"
    assert abs(p["rel_err_coulomb"]) < 1e-2
    lo, hi = p["K_max_measured_interval"]
    assert not lo <= p["K_max_predicted"] <= hi and p["K_max_predicted"] < lo


def test_real_time_mock_measures_the_limit_within_3_percent(capsys):
    """The embedded mock in real time on a pty (late ticks are cut out of the records by
    the run's identification): measured = predicted within the 3 % target, and the
    interval, when the records bracket the limit, holds the prediction (the records are
    exact wherever identified: a disturbance must not decide a record's side)."""
    rep, p = _one_point(capsys, ["--B", "1.5", "--tol", "0.02", "--duration", "0.2",
                                  "--start", "0.9"])
    assert abs(p["rel_err"]) < 0.03
    iv = p["K_max_measured_interval"]
    assert iv is None or iv[0] <= p["K_max_predicted"] <= iv[1]


def _report(b=None, safety=False, ticks=300, late=0):
    """A run's report as run_scene gives it, reduced to what run_measure reads."""
    stop = "safety: force at the limit 10 N in 50 of the last 100 samples" if safety \
        else "duration"
    meas = {"error": "not identified"} if b is None else {"b": b, "k": 1300.0,
                                                         "b_unc": 1e-14}
    return {"measured": meas, "loop": {"stop_reason": stop, "safety_stop": safety,
                                       "ticks": ticks, "late": late, "missed": 0,
                                       "stale": 0, "mock": {"late": late}}}


def test_a_disturbance_never_decides_a_records_side(monkeypatch):
    """The class of the real-time misses (docs/zwidth.md): a record whose identified b
    decays and that then stops on a safety limit (a host stall held a stale force) is
    decaying; a disturbed record without identification is repeated, not called growing,
    and undecided if every attempt is disturbed; an undisturbed one that ran into a limit
    after MIN_GROWTH_TICKS grew."""
    import hapsim.pipeline.runner as runner
    from hapsim.analysis.zwidth import MIN_GROWTH_TICKS, RECORD_ATTEMPTS
    from hapsim.commands.zwidth import DEFAULT_DEVICE, run_measure
    from hapsim.scene import parse_scene
    queue = []
    monkeypatch.setattr(runner, "run_scene", lambda *a, **k: queue.pop(0))
    measure = run_measure(parse_scene(DEFAULT_DEVICE, "<d>"), 0.005, duration=0.3)
    queue[:] = [_report(b=0.3, safety=True)]
    t = measure(1000.0, 1.5)
    assert t.growing is False and "disturbance" in t.note
    queue[:] = [_report(safety=True, late=12), _report(b=-0.2)]
    t = measure(1400.0, 1.5)
    assert t.growing is True and t.b == -0.2 and "record 2 of" in t.note and not queue
    queue[:] = [_report(safety=True, late=3) for _ in range(RECORD_ATTEMPTS)]
    t = measure(1400.0, 1.5)
    assert t.growing is None and not queue
    queue[:] = [_report(safety=True, ticks=MIN_GROWTH_TICKS)]
    assert measure(1400.0, 1.5).growing is True
    queue[:] = [_report(safety=True, ticks=MIN_GROWTH_TICKS - 1)]
    assert measure(1400.0, 1.5).growing is None
    # late ticks in the fit: b within their bound plus the interval is repeated, then
    # undecided; beyond it decides; unbounded late ticks never decide
    late_rep = _report(b=-0.01)
    late_rep["measured"].update(late_accounted=3, b_unc=1e-3, b_bound_late=0.02)
    queue[:] = [late_rep] * RECORD_ATTEMPTS
    t = measure(1400.0, 1.5)
    assert t.growing is None and not queue and "not decided" in t.note
    queue[:] = [dict(late_rep, measured=dict(late_rep["measured"], b=-0.05))]
    assert measure(1400.0, 1.5).growing is True
    queue[:] = [dict(late_rep, measured=dict(late_rep["measured"], b=-0.05,
                                             b_bound_late=None))] * RECORD_ATTEMPTS
    assert measure(1400.0, 1.5).growing is None


def _near_limit_record(seed, n_late_max=5):
    """A free response of the default device's wall at K within 1e-4..1e-2 of the linear
    limit (either side), with late ticks whose accounted forces are wrong by a random
    share (up to all) of their known disturbance ``|w|`` (1-10 % of the wall's force)."""
    import numpy as np
    from hapsim.analysis.error_response import disturbance_response, force_error_response
    from hapsim.analysis.prediction import predicted_poles
    from hapsim.analysis.stability import stability_limit
    from hapsim.analysis.zwidth import device_loop, wall_scene
    from hapsim.commands.zwidth import DEFAULT_DEVICE
    from hapsim.scene import parse_scene
    base = parse_scene(DEFAULT_DEVICE, "<d>")
    B, n, m = 1.5, 300, 0.1
    rng = np.random.default_rng(seed)
    K = stability_limit(device_loop(base.device, base.rate_hz), B) * (
        1 + rng.choice([-1, 1]) * 10 ** rng.uniform(-4, -2))
    sc = wall_scene(base, K, B, 0.0)
    poles, felt = predicted_poles(sc)
    b_true = -2 * m * (np.log(complex(felt)) / base.period).real
    kick = np.zeros(n)
    kick[0] = 1.0                                  # a free response after the kick
    x = disturbance_response(sc, kick)
    late = np.zeros(n, bool)
    if n_late_max:
        late[rng.choice(np.arange(10, n), rng.integers(1, n_late_max + 1),
                        replace=False)] = True
    w = np.where(late, rng.uniform(0.01, 0.1, n) * K * np.max(np.abs(x)), 0.0)
    err = np.where(late, rng.uniform(-1.0, 1.0, n) * w, 0.0)
    err[late] = np.where(rng.random(int(late.sum())) < 0.5, np.sign(err[late]) * w[late],
                         err[late])                # half of them at the worst case
    y = x + disturbance_response(sc, err)
    return (y[5:], w[5:], force_error_response(sc, n - 5), base.period, m, poles, felt,
            int(late.sum()), b_true)


def test_late_ticks_never_decide_a_near_limit_record_on_the_wrong_side():
    """Property over 30 seeds: a record near the limit whose late ticks' accounted forces
    are wrong by up to the whole disturbance is never decided on the wrong side: its side
    needs |b| beyond the worst case of that error through the fit's first-order
    sensitivity (b_bound_late) plus the fit's interval. The former rule (3 stated
    half-intervals, no bound on the disturbance) decides some of the same records wrong,
    so the property is not vacuous; and enough are decided to be useful."""
    from hapsim.analysis.identify import measure_felt
    from hapsim.analysis.zwidth import record_side
    wrong = decided = wrong_old = 0
    for seed in range(30):
        y, w, resp, T, m, poles, felt, n_late, b_true = _near_limit_record(seed)
        r = measure_felt(y, T, m, poles, felt, late_bounded=[(w, resp)])
        assert r["b_bound_late"] > 0
        assert abs(r["b"] - b_true) <= r["b_bound_late"] + r["b_unc"]
        side, margin = record_side(r["b"], r["b_unc"], n_late, r["b_bound_late"])
        assert margin == r["b_bound_late"] + r["b_unc"]
        if side is not None:
            decided += 1
            wrong += side != (b_true < 0)
        old = None if abs(r["b"]) <= 3.0 * r["b_unc"] else r["b"] < 0
        wrong_old += old is not None and old != (b_true < 0)
    assert wrong == 0 and decided >= 5 and wrong_old >= 1     # 8 and 4 of 30 here


def test_without_late_ticks_the_sign_decides():
    """No late ticks: the bound is 0 and the sign of b decides, as before (the record is
    the loop's own, exact: the side is right even within 1e-4 of the limit); late ticks
    without a bound (not accounted) never decide."""
    from hapsim.analysis.identify import measure_felt
    from hapsim.analysis.zwidth import record_side
    for seed in range(4):
        y, w, resp, T, m, poles, felt, n_late, b_true = _near_limit_record(seed, 0)
        r = measure_felt(y, T, m, poles, felt, late_bounded=[(w, resp)])
        assert n_late == 0 and r.get("b_bound_late", 0.0) == 0.0
        side, margin = record_side(r["b"], r["b_unc"], 0, r.get("b_bound_late", 0.0))
        assert margin == 0.0 and side == (b_true < 0) == (r["b"] < 0)
        assert record_side(r["b"], r["b_unc"], 2, None) == (None, float("inf"))


def test_run_states_the_late_forces_bound_that_zwidth_decides_on():
    """End to end on the lockstep mock made late at scripted ticks (it holds the force it
    applied before and names it by force_seq): ``run``'s measurement takes the late
    forces out (exact here), states their worst case through the fit apart
    (``b_bound_late`` > 0, holding the exact b), and a record 0.3 % above the limit with
    10 late ticks is then not decided (|b| = 0.006 against a bound of 0.075 N s/m)."""
    import pytest as _pytest

    from hapsim.analysis.stability import stability_limit
    from hapsim.analysis.zwidth import device_loop, record_side, wall_scene
    from hapsim.commands.zwidth import DEFAULT_DEVICE
    from hapsim.emulated import mock as mock_mod
    from hapsim.pipeline import runner
    from hapsim.scene import parse_scene

    late = frozenset(range(77, 84)) | frozenset(range(231, 234))

    class LateMock(mock_mod.MockDevice):
        def _apply_due(self, n, now_us):
            due = n - self.delay
            if due in late and due >= 1 and self._rs[due % self._ring] == due:
                self._rs[due % self._ring] = -1     # the FORCE missed its tick
            super()._apply_due(n, now_us)

    base = parse_scene(DEFAULT_DEVICE, "<d>")
    K = stability_limit(device_loop(base.device, base.rate_hz), 1.5) * 1.003
    with _pytest.MonkeyPatch.context() as mp:
        mp.setattr(runner, "MockDevice", LateMock)
        rep = runner.run_scene(wall_scene(base, K, 1.5, 0.005), lockstep=True,
                               transport="inprocess", handle_signals=False, duration=0.3,
                               allow_unstable=True)
    meas, pred = rep["measured"], rep["predicted"]
    assert meas["late_accounted"] == len(late) == rep["loop"]["late"]
    # measured 7.6e-14 (generic 6.1e-14), margin 13000
    assert meas["b"] == _pytest.approx(pred["b"], abs=1e-9) and pred["b"] < 0
    assert abs(meas["b"]) < meas["b_bound_late"]
    assert record_side(meas["b"], meas["b_unc"], meas["late_accounted"],
                       meas["b_bound_late"])[0] is None


def test_emulated_firmware_measures_the_limit_within_10_percent(capsys):
    """Over the Hapkit reference firmware on the emulated ATmega328P (simavr; its clock
    paced by the host, so the test does not depend on the machine's load): the measured
    limit is within the 10 % target of the linear prediction and the device is said to follow
    it. Not to round-off: the firmware computes the force in its own fixed point, drives a
    PWM and reads a 17.6 um encoder (docs/zwidth.md)."""
    from hapsim.emulated import hapkit_board as board
    why = board.missing_tools()
    if why:
        print(f"test_zwidth: skipped: {why}")
        pytest.skip(f"emulated Hapkit board: {why}")
    # --tol 0.05: the 10 % claim needs a bracket within 5 %, not the default 0.2 %
    # (4 records instead of 6)
    rep, p = _one_point(capsys, ["--firmware", "--lockstep", "--B", "1.5", "--start", "0.9",
                                  "--tol", "0.05"])
    assert abs(p["rel_err"]) < 0.10
    assert rep["follows"] == "linear"
    # the records below the limit decay and the search crossed it from below
    trials = [t for t in p["trials"] if t.get("growing") is not None]
    assert not trials[0]["growing"] and any(t["growing"] for t in trials)


def test_zwidth_refuses_bad_options(capsys):
    assert main(["zwidth", "--lockstep", "--tol", "0"]) == 2
    assert main(["zwidth", "--lockstep", "--start", "1.5"]) == 2
    assert main(["zwidth", "--lockstep", "--port", "/dev/null"]) == 2
    assert main(["zwidth", "--lockstep", "--B", "nan"]) == 2
    assert "--B" in capsys.readouterr().err


@pytest.mark.parametrize("root,power", [(1000.0, 1.0), (437.0, 2.0), (5169.0, 0.5)])
def test_onset_search_on_synthetic_records(root, power):
    """The search alone, on records whose b(K) = 1 - (K/root)^p is known: it starts below
    the guess, brackets the root between a decaying and a growing record and ends within
    the tolerance (the guess 20 % off); a device whose every record grows gives no
    limit."""
    from hapsim.analysis.zwidth import Trial, locate_onset

    def measure(K, B):
        b = 1.0 - (K / root) ** power
        return Trial(K, B, b, K, 0.0, None, b < 0)
    tol = 1e-3
    Km, (lo, hi), trials, note = locate_onset(measure, 0.0, 1.2 * root, tol=tol)
    # derived: the search stops with hi - lo <= tol lo, and Km (the secant's zero) and the
    # root both lie in that bracket
    assert abs(Km - root) <= tol * root and lo <= root <= hi and not note
    assert trials[0].K < root and not trials[0].growing
    Km, iv, trials, note = locate_onset(
        lambda K, B: Trial(K, B, -1.0, K, 0.0, None, True, "safety: position"), 0.0, root)
    assert Km is None and iv is None and "no decaying record" in note

    def close_to_call(K, B):          # undecided within 1 % of the root
        t = measure(K, B)
        return t if abs(K - root) > 0.01 * root else Trial(K, B, t.b, K, 0.0, None, None,
                                                             "too close")
    Km, (lo, hi), trials, note = locate_onset(close_to_call, 0.0, 1.2 * root, tol=1e-3)
    assert lo <= root <= hi and "undecided: too close" in note and trials[-1].growing is None


@pytest.mark.parametrize("seed", seeds(range(1, 13), kept=[1, 5]))
def test_a_device_lost_mid_sweep_reports_the_points_measured(seed, capsys, monkeypatch):
    """The device lost (its run raises DeviceError, as ``hapsim run`` does past its
    recovery) at a random record of a three-point sweep: lost in the first point, the
    error alone (exit 1 by the cli); later, the points measured before it, each as a
    whole sweep measures it, ``stop`` "device lost: ... (after i of 3 B values)" and
    ``error``, then the error on stderr, exit 1. Before, every loss was the error alone,
    the points measured lost with it."""
    import random

    import hapsim.pipeline.runner as runner
    from hapsim.errors import DeviceError
    real, calls = runner.run_scene, [0]
    argv = ["zwidth", "--lockstep", "--B", "1.5", "3.0", "4.5", "--start", "0.9", "--json"]
    assert main(argv) == 0
    whole = json.loads(capsys.readouterr().out)["points"]

    def counted(*a, **k):
        calls[0] += 1
        return real(*a, **k)
    monkeypatch.setattr(runner, "run_scene", counted)
    main(argv[:4] + argv[6:])                           # the first point alone
    first, calls[0] = calls[0], 0
    main(argv)
    capsys.readouterr()
    at = random.Random(seed).randrange(1, calls[0] + 1)
    calls[0] = 0

    def lost_at(*a, **k):
        calls[0] += 1
        if calls[0] >= at:
            raise DeviceError("device lost (port failed: read failed); 3 reconnect "
                              "attempts in 10 s failed")
        return real(*a, **k)
    monkeypatch.setattr(runner, "run_scene", lost_at)
    code = main(argv)
    out, err = capsys.readouterr()
    rep = json.loads(out)
    if "points" not in rep:                             # the cli's error object
        assert code == 1 and rep["error"]["type"] == "DeviceError", rep
        assert at <= first, ("the error alone after the first point", at, first)
        return
    n = len(rep["points"])
    assert code == 1 and 1 <= n < 3, (code, n)
    assert rep["stop"] == (f"device lost: device lost (port failed: read failed); 3 reconnect"
                           f" attempts in 10 s failed (after {n} of 3 B values)")
    assert rep["error"]["type"] == "DeviceError"
    assert rep["points"] == whole[:n]                   # (lockstep: the same records)
    assert err.strip().splitlines()[-1].startswith("hapsim zwidth: DeviceError: device lost")


def _shipped_one_d_devices():
    """Every shipped one-device 1-D scene of configs/ (path, scene)."""
    import pathlib

    from hapsim.scene import load_scene, scene_dimension, scene_has_ports
    root = pathlib.Path(__file__).resolve().parents[1] / "configs"
    out = []
    for p in sorted(root.glob("*.yaml")):
        if scene_has_ports(str(p)) or scene_dimension(str(p)) > 1:
            continue
        sc = load_scene(str(p))
        if sc.device is not None:
            out.append((p.name, sc))
    return out


@pytest.mark.parametrize("name,scene", _shipped_one_d_devices(),
                         ids=[n for n, _ in _shipped_one_d_devices()])
def test_every_default_damping_leaves_a_stable_stiffness_on_every_shipped_device(name,
                                                                                  scene):
    """``hapsim zwidth --scene SCENE`` without ``--B``: each default damping has a
    positive, finite predicted limit (the exact linear one, hapsim stability) on every
    shipped 1-D device, so each point can be measured. Before, the fixed 0, 1.5, 4 N s/m
    on the Haply joint (0.001 kg m^2 at 1 kHz: B T / m = 1.5) had K_max = 0 at 1.5 and 4:
    nothing to measure, exit 1. The reference device keeps the old dampings, and a
    scaled list keeps their B T / m."""
    from hapsim.analysis.stability import stability_limit
    from hapsim.analysis.zwidth import DEFAULT_DAMPINGS, default_dampings, device_loop
    Bs = default_dampings(scene.device.mass, scene.rate_hz)
    loop = device_loop(scene.device, scene.rate_hz)
    for B in Bs:
        K = stability_limit(loop, B)
        assert 0.0 < K < float("inf"), (name, B, K)
    m_rate = scene.device.mass * scene.rate_hz
    if m_rate >= 100.0:
        assert Bs == list(DEFAULT_DAMPINGS)
    else:                                       # the same B T / m as the reference's
        for B, B0 in zip(Bs, DEFAULT_DAMPINGS):
            # kept to 6 significant digits, the rounding's bound: half a unit of the 6th, a
            # relative 5e-6 of a leading digit of 1
            assert B / m_rate == pytest.approx(B0 / 100.0, rel=5e-6)


def test_the_haply_scenes_z_width_is_measured_with_the_defaults(capsys):
    """The shipped Haply scene, lockstep, nothing else: every point measured, in the
    joint's units (1.4 CPU-s)."""
    rc = main(["zwidth", "--scene", "configs/haply.yaml", "--lockstep"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "B [N m s/rad]" in out and "kg m^2" in out, out


def test_a_damping_that_leaves_no_stable_stiffness_is_named_so():
    """A predicted limit of 0 (the virtual damping alone destabilises the sampled loop)
    is said as such, not as a limit that is not finite, and nothing is recorded."""
    from hapsim.analysis.zwidth import locate_onset

    def measure(K, B):
        raise AssertionError("no record is made")
    Km, iv, trials, note = locate_onset(measure, 4.0, 0.0)
    assert Km is None and iv is None and trials == []
    assert "K_max = 0" in note and "smaller B" in note, note


@pytest.mark.parametrize("name,scene", [(n, s) for n, s in _shipped_one_d_devices()
                                        if (s.device.protocol or "framed") != "framed"],
                         ids=[n for n, s in _shipped_one_d_devices()
                              if (s.device.protocol or "framed") != "framed"])
def test_a_scene_whose_board_speaks_its_own_protocol_is_never_sent_framed_bytes(
        name, scene, capsys):
    """zwidth's records go over hapsim's framed protocol: with ``--port`` on a scene whose
    device speaks its own (the FireFader's, the Haply's, the Hapkit sketch's) it refuses
    before opening the port, naming the protocol (a board would take the framed bytes for
    its own commands); without a port it says it measures hapsim's model of the device.
    A delay under a period in real time names --lockstep, not the --driver it lacks."""
    path = f"configs/{name}"
    assert main(["zwidth", "--scene", path, "--port", "/dev/null"]) == 2
    err = capsys.readouterr().err
    assert f"speaks the {scene.device.protocol} protocol" in err and "--port" in err, err
    if float(scene.device.delay) < 1:
        assert main(["zwidth", "--scene", path]) == 2
        err = capsys.readouterr().err
        assert "(or --lockstep)" in err and "--driver" not in err, err
