"""The host's write timing in the Haply M3's stated uncertainty (issue 29, the wrong-verdict
class): firmware V1.5 sets the torque in the pass that takes a write and holds it until
the next (no watchdog, no tick), so on a board that keeps its own time hold ``k`` lasts
``T + delta_k``, ``delta_k`` the host's write jitter. The record is the loop of exact
periods with the joint's state changed at each sample by the motion over the hold's
excess; the measurement estimates those changes from the host's write times, the readings
and the torques, takes their motion through the loop off the record and states what the
estimate leaves (:func:`hapsim.analysis.write_holds.write_time_terms`, the 2DIY's
functions with n = 1).

On the simulated clock (:func:`hapsim.emulated.haply_board.haply_offline_loop`: the
board's joint integrated exactly over each real hold, the same run on any machine)."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest

from hapsim.emulated.haply_board import haply_offline_loop
from hapsim.errors import UnstableConfigError
from hapsim.pipeline.options import RunOptions
from hapsim.pipeline.runner import identify_run, prepare_run
from hapsim.scene import load_scene
from seeds import seeds
from tolerance import measured

YAML = """rate_hz: {rate}
masses:
  - {{name: joint, kind: port}}
  - {{name: rest, kind: ground, x0: 0.0}}
links:
  - {{name: spring, kind: spring_damper, between: [joint, rest], stiffness: {K},
     damping: {B}}}
device:
  protocol: haply
  mass: {m}
  friction: {b0}
  delay: 1
  hold: zoh
  force_limit: 0.12
excitation:
  x0: {x0}
"""
ROWS = 2000
#: The property test's encoder: 16 bits per revolution (the M3's set-up takes any
#: resolution), so that the host's jitter stands above the rounding in the fit.
RESOLUTION = 2.0 ** 16
#: The host's write delays: up to 0.4 ms after each tick, uniform (a loaded host).
LATE_S = 4e-4


def _random_case(seed: int, tmp_path, rate: float = 1000.0):
    """A random M3 joint and spring (drawn again until its loop is stable) and the host's
    write delays [s], one per command."""
    rng = np.random.default_rng(seed)
    path = tmp_path / f"m3_{seed}.yaml"
    while True:
        K = float(rng.uniform(0.4, 1.0))
        path.write_text(YAML.format(rate=rate, K=K, B=float(rng.uniform(0.0, 5e-4)),
                                    m=float(rng.uniform(0.5e-3, 2e-3)),
                                    b0=float(rng.uniform(2e-4, 6e-4)),
                                    x0=min(float(rng.uniform(0.1, 0.3)), 0.1 / K)))
        try:
            prep = prepare_run(load_scene(str(path)),
                               RunOptions(driver="haply", rt_priority=0, handle_signals=False,
                                          duration=ROWS / rate))
            break
        except UnstableConfigError:
            continue
    return prep, rng.uniform(0.0, LATE_S, ROWS + 1)


def _measure(prep, cols, driver):
    tel = types.SimpleNamespace(wrapped=False, n=cols["seq"].size, head=cols["seq"].size,
                                columns=lambda *a: cols)
    return identify_run(prep, tel, None, driver=driver)


@pytest.mark.parametrize("seed", seeds(range(12), kept=range(6)))
def test_a_jittered_host_never_makes_a_matching_m3_differ(seed, tmp_path):
    """Random M3 loops, the host writing each command up to 0.4 ms late (random), 2,000
    rows read to 2^16 counts per revolution: the matching joint is never "differs", and
    within (before, on main: 3 of these 12 said 'differs', k or b 1.3 to 2.1 stated
    uncertainties off); the same loop with 30 % more joint inertia, the same writes, still
    "differs" (every third seed: each measurement costs CPU), and with 2 % more, which the
    link's unseen latency could explain, "not measurable" with that reason (never
    "within")."""
    prep, late = _random_case(seed, tmp_path)
    cols, drv, _ = haply_offline_loop(prep.scene, ROWS, write_late=late,
                                      resolution=RESOLUTION)
    m = _measure(prep, cols, drv)
    info = (m.get("verdict"), m.get("error"),
            {q: (m.get(q), prep.pred[q], m.get(f"{q}_unc")) for q in ("k", "b")})
    # the class happened: holds up to 0.3-0.4 ms off a period
    assert np.max(np.abs(np.diff(cols["time"]) - prep.scene.period)) > 0.3e-3
    assert m.get("within") is True, info
    if seed % 3 == 2:
        return
    dev = prep.scene.device
    heavier = 1.3 if seed % 3 == 0 else 1.02
    cols, drv, _ = haply_offline_loop(prep.scene, ROWS, write_late=late, resolution=RESOLUTION,
                                      device=dataclasses.replace(dev, mass=heavier * dev.mass))
    w = _measure(prep, cols, drv)
    info = (w.get("verdict"), w.get("error"), w.get("k"), prep.pred["k"], w.get("k_unc"),
            w.get("link_k_unc"))
    if heavier == 1.3:
        assert str(w.get("verdict")).startswith("measured differs"), info
    else:
        # 2 % more: beyond the stated uncertainty, but within what the link's unseen
        # latency (50 us between writes, worst case) could make: never "within"
        assert w.get("within") is False and "link's latency" in str(w.get("verdict")), info


@pytest.mark.parametrize("seed", range(3))
def test_the_correction_removes_the_holds_motion(seed, tmp_path):
    """The record with the host's jitter, less the estimated motion of its holds
    (:func:`hapsim.analysis.write_holds.write_time_terms`), is the record of the same loop
    with writes exactly a period apart, to a small part of what the jitter did. An
    encoder of 2^22 counts per revolution, so that the jitter's effect (400 to 1,300
    counts) stands far above the rounding (the M3's 4880 counts: about one count, the
    rounding's own size). The board applies the torque's float exactly (named,
    ``torque_levels=0``): its firmware's 256 levels would let the two loops take other
    levels once apart, a difference that is not the holds' (the measurement takes the
    levels out as a known input: tests/test_haply_writetime.py's verdicts above). The
    host's delays are whole passes of the firmware's loop: the board takes a write at its
    first pass after it came (:func:`hapsim.emulated.haply_firmware.pass_at`), by a phase
    the host does not see, which no correction from the host's write times removes (the
    verdicts above bound it: the link's latency); whole passes leave the holds the host's."""
    from hapsim.analysis.write_holds import write_time_terms
    from hapsim.emulated.haply_firmware import PASS_S
    from hapsim.host.telemetry import FLAG_ESTIMATED
    prep, late = _random_case(seed, tmp_path)
    late = PASS_S * np.round(late / PASS_S)
    exact, _, _ = haply_offline_loop(prep.scene, ROWS, resolution=2.0 ** 22, torque_levels=0)
    cols, drv, _ = haply_offline_loop(prep.scene, ROWS, write_late=late, resolution=2.0 ** 22,
                                      torque_levels=0)
    q = drv.position_scale
    terms = write_time_terms(prep.scene, cols, quantum=q, position_rel=drv.position_rel,
                             flag_estimated=FLAG_ESTIMATED)
    assert not terms["cut"].any() and terms["corrected"][2:].all()
    raw = cols["position"] - exact["position"]
    left = raw - terms["motion"]
    assert np.max(np.abs(raw)) > 300 * q
    # measured over seeds 0-5: 0.12 to 0.50 % of the jitter's effect left (the second
    # order of the holds' departures, the rounding through the estimate); margin 2
    assert np.linalg.norm(left) <= measured(0.0050, 2.0) * np.linalg.norm(raw)


def test_exact_periods_change_nothing(tmp_path):
    """Writes exactly a period apart (a host with no jitter; at 1024 Hz the write times
    are exact in binary64) and a lockstep board (no clock of its own: no correction
    sought): the measurement is today's, bit for bit."""
    prep, _ = _random_case(5, tmp_path, rate=1024.0)
    cols, drv, _ = haply_offline_loop(prep.scene, ROWS)
    assert not np.any(np.diff(cols["time"]) - prep.scene.period)
    m = _measure(prep, cols, drv)
    drv.own_clock = False
    plain = _measure(prep, cols, drv)
    assert "write_hold_s" not in plain
    for q in ("k", "b", "k_unc", "b_unc", "samples_used", "verdict"):
        assert m[q] == plain[q], q
