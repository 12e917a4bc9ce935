"""Holds a board on its own tick mistimed that no host saw (issue 29, the wrong-verdict
class): found in the record and cut (:mod:`hapsim.analysis.unseen_holds`).

The Hapkit sketch reads the handle and applies a command's force at the command's end or
the tick after its read began (``Hapkit_arduino.ino:96-135``). A board that is itself
late to read a command (a USB-serial bridge's 1 ms frames; the emulated sketch's process
beside two CPU-bound ones) samples it that much late: the reply's position read late, the
force before held longer, which neither the reply nor the host sees. Beside two hogs the emulated sketch took 1 to 8 of
them a run, and one run said "differs" of a matching paddle.

Here the THS is closed on a SIMULATED clock
(:func:`hapsim.emulated.hapkit_serial_board.hapkit_serial_offline_loop`: the board on its
own tick fed the simulated time of each command; deterministic, no pty, no wall clock),
random paddles and loops, 1 to 10 holds of 0.6 to 2.5 ticks of read latency at random rows
that the host does not mark. Before the change (the search off: ``own_tick`` False, as
``identify_run`` was) 4 of these 16 seeds said "differs" of the matching paddle (17, 21,
22, 31: k 0.02-0.03 % or b 0.8-1.6 % off, outside intervals of 0.01-0.03 % and
0.5-1.3 %); over seeds 0-149 of this generator 10 did. Seeds 16-31 are the window that
holds four of them: the suite keeps those four and two more (the even seeds' wrong paddle
is heavier, the odd ones' has hidden friction), CI's soak runs all 16 (tests/seeds.py). A device that truly differs (30 % more mass, or 0.3 N s/m of hidden
friction) must still "differ".
"""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest

from hapsim.emulated.hapkit_serial_board import hapkit_serial_offline_loop
from hapsim.errors import UnstableConfigError
from hapsim.pipeline.options import RunOptions
from hapsim.pipeline.runner import identify_run, prepare_run
from hapsim.scene import load_scene
from seeds import seeds
from tolerance import measured

pytestmark = pytest.mark.xdist_group("test_unseen_holds")

YAML = """rate_hz: {rate}
masses:
  - {{name: handle, kind: port}}
  - {{name: wall, kind: ground, x0: 0.0}}
links:
  - {{name: spring, kind: spring_damper, between: [handle, wall], stiffness: {K},
     damping: {B}}}
device:
  protocol: hapkit-serial
  mass: {m}
  friction: {b0}
  delay: 1
  hold: zoh
  force_limit: 2.0
excitation:
  x0: {x0}
"""
#: The record's length [s]: 4 to 11 cycles of the paddles drawn below.
DURATION = 1.2


def _prep(path):
    """The run's prepared loop; one unstable only with its reading taken a period late
    (``late_reading_periods``: refused by a run) is prepared past that refusal: these
    offline loops take every reading in its period, and the draws stay those the tests
    were written with."""
    opts = dict(driver="hapkit-serial", rt_priority=0, handle_signals=False,
                duration=DURATION)
    try:
        return prepare_run(load_scene(str(path)), RunOptions(**opts))
    except UnstableConfigError as exc:
        if "period late" not in str(exc):
            raise
        prep = prepare_run(load_scene(str(path)), RunOptions(**opts, allow_unstable=True))
        assert prep.pred.get("stable") is not False
        assert prep.pred.get("unstable_latency_s") is None
        return prep


def stable_paddle(rng, path):
    """A random Hapkit paddle and spring drawn from ``rng`` (again until its loop is
    stable), written to ``path``: the run's prepared loop."""
    while True:
        m = float(rng.uniform(0.05, 0.15))
        K = float(rng.uniform(60.0, 150.0))
        x0 = min(float(rng.uniform(0.005, 0.015)), 1.5 / K)      # within the 2 N limit
        path.write_text(YAML.format(rate=float(rng.choice([252.016, 201.613])), K=K,
                                    B=float(rng.uniform(0.0, 0.3)), m=m,
                                    b0=float(rng.uniform(0.05, 0.4)), x0=x0))
        try:
            return _prep(path)
        except UnstableConfigError:      # beyond the stability limit: another loop
            continue


def _random_case(seed: int, tmp_path):
    """A random Hapkit paddle and spring (drawn again until its loop is stable) and its
    unseen holds: ``{command: read latency [ticks]}``."""
    rng = np.random.default_rng(seed)
    prep = stable_paddle(rng, tmp_path / f"paddle{seed}.yaml")
    n = int(round(DURATION * prep.scene.rate_hz))
    rows = rng.choice(np.arange(5, n - 5), size=int(rng.integers(1, 11)), replace=False)
    return prep, n, {int(r): float(rng.uniform(0.6, 2.5)) for r in rows}


def _measure(prep, cols, driver):
    tel = types.SimpleNamespace(wrapped=False, n=cols["seq"].size, head=cols["seq"].size,
                                columns=lambda *a: cols)
    return identify_run(prep, tel, None, driver=driver)


def test_the_signature_is_a_holds_disturbance():
    """One command read late by 0.75, 1, 1.25 and 2 ticks on configs/hapkit_serial.yaml
    (the host's writes mid-tick: the sketch samples at the command's end, so the sample
    is late by the read's latency, no whole number of ticks,
    :class:`hapsim.emulated.hapkit_serial_board.HapkitSerialDevice`): the record less the
    record without it is the hold's signature (:func:`hapsim.analysis.unseen_holds.
    hold_signature`) at that mistiming, computed from the record without it, to a few
    per cent of its norm (the force's error taken as an impulse over the period, the rows
    around the hold interpolated), and five times nearer to it than the signature of the
    quarter ticks either side, a tick early or a period late (so the search, on quarter
    ticks, finds the hold's own). A read 3 ticks late has its bytes read (2.98 ms and the
    command's 1.74 ms on the wire) before the next command is written a period (5 ticks,
    4.96 ms) after the first: one hold. (At 4 ticks, before the rate was bounded by the
    latest answer, that next command was late too.) The board a sketch that applies the
    float at its read
    (``levels=0, render_s=0``, named): the signature is the scene's linear loop's, which
    the sketch's levels and render latency are not."""
    from hapsim.analysis.error_response import force_error_response, sensor_error_response
    from hapsim.analysis.unseen_holds import hold_signature
    from hapsim.emulated.hapkit_serial_board import HapkitSerialDevice
    tick = HapkitSerialDevice.TICK_S
    prep = _prep("configs/hapkit_serial.yaml")
    n = 375
    ideal = {"levels": 0, "render_s": 0.0}
    base, _, _ = hapkit_serial_offline_loop(prep.scene, n, **ideal)
    S = sensor_error_response(prep.scene, n)
    H = force_error_response(prep.scene, n)
    for ticks in (0.75, 1, 1.25, 2):
        cols, _, board = hapkit_serial_offline_loop(prep.scene, n, read_late={100: ticks},
                                                    **ideal)
        assert board.tick_arrivals["off_at"] == [100, 101]     # its hold and the next
        d = cols["position"] - base["position"]
        assert not np.any(d[:100])
        off = {k: np.linalg.norm(d[100:] - hold_signature(
            base["position"], base["force"], 100, n - 100, prep.scene.period, S, H,
            k * tick)) / np.linalg.norm(d[100:])
            for k in (-1, ticks - 0.25, ticks, ticks + 0.25, 4)}
        # measured 4.3 %, 4.1 %, 3.8 % and 3.1 % (0.75, 1, 1.25, 2 ticks, at 5 ticks a
        # period); margin 1.5
        assert off[ticks] <= measured(0.043, 1.5), off
        # the nearest other is 4.06 times as far at least (2 ticks' quarter ticks either
        # side: 0.125 and 0.131 against 0.031), measured; margin 1.35: 3.0 asked
        assert all(v >= 4.06 / 1.35 * off[ticks] for k, v in off.items() if k != ticks), off
    _, _, board = hapkit_serial_offline_loop(prep.scene, n, read_late={100: 3}, **ideal)
    assert board.tick_arrivals["off_at"] == [100, 101]


@pytest.mark.parametrize("seed", seeds(range(16, 32), kept=(16, 17, 21, 22, 28, 31)))
def test_unseen_holds_never_make_a_matching_paddle_differ(seed, tmp_path):
    """Random paddles and loops on the simulated board's tick, 1 to 10 holds the host does
    not see: the matching paddle is never "differs" (within, or not measurable with its
    reason); the same loop against a paddle with 30 % more mass (even seeds) or
    0.3 N s/m of friction the scene does not state (odd ones), the same holds, still
    "differs"."""
    prep, n, late = _random_case(seed, tmp_path)
    cols, drv, board = hapkit_serial_offline_loop(prep.scene, n, read_late=late)
    assert board.tick_arrivals["off_period"] >= 1          # the class happened
    m = _measure(prep, cols, drv)
    info = (m.get("verdict"), m.get("error"), m.get("unseen_hold_seqs"), sorted(late),
            {q: (m.get(q), prep.pred[q], m.get(f"{q}_unc")) for q in ("k", "b")})
    assert not str(m.get("verdict")).startswith("measured differs"), info
    assert m.get("within") is True or "k" not in m, info
    dev = prep.scene.device
    wrong = (dataclasses.replace(dev, mass=1.3 * dev.mass) if seed % 2 == 0
             else dataclasses.replace(dev, friction=dev.friction + 0.3))
    cols, drv, _ = hapkit_serial_offline_loop(prep.scene, n, read_late=late, device=wrong)
    m = _measure(prep, cols, drv)
    assert str(m.get("verdict")).startswith("measured differs"), (
        m.get("verdict"), m.get("error"), m.get("unseen_hold_seqs"))


@pytest.mark.parametrize("seed", [0, 5])
def test_with_no_hold_the_measurement_is_unchanged(seed, tmp_path):
    """No hold: nothing is found, and the measurement is the one made without the search
    (a driver with no tick), bit for bit."""
    prep, n, _ = _random_case(seed, tmp_path)
    cols, drv, board = hapkit_serial_offline_loop(prep.scene, n)
    assert board.tick_arrivals["off_period"] == 0
    m = _measure(prep, cols, drv)
    drv.own_tick = False                     # the search is for boards on their own tick
    plain = _measure(prep, cols, drv)
    assert m.pop("unseen_holds") == 0 and "unseen_holds" not in plain
    assert m.keys() == plain.keys()
    for q in ("k", "b", "k_unc", "b_unc", "samples_used"):
        assert m[q] == plain[q], q



@pytest.mark.parametrize("seed", seeds(range(40, 48), kept=(40, 41, 42, 43)))
def test_lost_replies_are_not_taken_for_holds(seed, tmp_path):
    """Random paddles with 2 % to 6 % of their replies lost (the rows stepped through with
    an extrapolated position, as a lossy link leaves them), and on odd seeds the random
    unseen holds too: the search finds at most one hold more than the board took (the
    estimated rows' errors, through the loop, are nuisances it projects off: before, 5 of
    these 8 seeds failed, two records cut into stretches too short to measure, two with
    11 and 18 holds found, and "differs" said of the matching paddle in one; on the wall
    clock 2 of 10 lossy Hapkit-serial runs were "not measurable" so), the matching paddle is never
    "differs" (within; or, with holds, not measurable with its reason), and one with 30 %
    more mass still differs."""
    prep, n, late = _random_case(seed, tmp_path)
    late = late if seed % 2 else {}
    rng = np.random.default_rng(1000 + seed)
    lost = {int(j) for j in rng.choice(np.arange(8, n - 2),
                                       size=int(rng.uniform(0.02, 0.06) * n), replace=False)}
    cols, drv, board = hapkit_serial_offline_loop(prep.scene, n, read_late=late,
                                                  lost_replies=lost)
    m = _measure(prep, cols, drv)
    info = (m.get("verdict"), m.get("error"), m.get("unseen_holds"), sorted(late),
            m.get("cycles"))
    assert m.get("unseen_holds", 0) <= board.tick_arrivals["off_period"] + 1, info
    assert not str(m.get("verdict")).startswith("measured differs"), info
    assert m.get("within") is True or (late and "k" not in m), info
    dev = prep.scene.device
    cols, drv, _ = hapkit_serial_offline_loop(
        prep.scene, n, read_late=late, lost_replies=lost,
        device=dataclasses.replace(dev, mass=1.3 * dev.mass))
    m = _measure(prep, cols, drv)
    assert str(m.get("verdict")).startswith("measured differs"), (
        m.get("verdict"), m.get("error"), m.get("unseen_holds"))
