"""A Hapkit whose oscillator is off the host's clock: its ticks walk across the host's writes.

The WHC2017 sketch takes commands on its own Timer1 tick, 62 counts of 16 us from its
16 MHz source (``Hapkit_arduino.h:59-68``). The host aligns its writes to the middle of
that tick once, at the first arming (:class:`hapsim.drivers.tick_align.TickAligned`), and
then writes a whole number of the nominal 0.992 ms ticks apart. A board whose source is
``e`` off the host's clock (a crystal tens of ppm, a ceramic resonator up to a few
thousand) walks its tick ``per e`` of a tick a period against those writes, ``per`` the
period's ticks: over a record of ``n`` periods the writes cross ``n per |e|`` tick
boundaries (:class:`hapsim.emulated.hapkit_serial_board.HapkitSerialDevice`,
``clock_ppm``). A crossing is no isolated hold: the handle's read moves for the rest of
the record (from the command's end to the board's tick, or back), a loop whose delay
changed, which the unseen holds' review (:mod:`hapsim.analysis.unseen_holds`) takes for
7-8 holds.

Closed offline on the simulated clock
(:func:`hapsim.emulated.hapkit_serial_board.hapkit_serial_offline_loop`), random paddles
and springs, the board 1,000 to 5,000 ppm off, the writes at a random phase: over seeds
0-15 of the generator below the matching paddle was "within" in 13 and "differs" in 3
(7, 11 and 13; seed 13 at 1,252 ppm, one boundary crossed). The host now probes the tick
again at the run's stop (:meth:`~hapsim.drivers.tick_align.TickAligned.end_probe`) and a
"differs" with the tick moved is "not measurable" with the reason
(:func:`hapsim.pipeline.unseen_review.review_tick_walk`). The guard is partial: a walk
within 0.15 of a whole number of ticks looks like none to the probe, and in 12 such walks
the matching paddle was still said to differ in 4 (strict ``xfail`` below: the class
stays open, issue 29).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hapsim.drivers.hapkit_serial import FIRMWARE_TICK_S
from hapsim.emulated.hapkit_serial_board import hapkit_serial_offline_loop
from test_unseen_holds import DURATION, _measure, _prep, stable_paddle  # same directory

OPEN = pytest.mark.xfail(strict=True, reason=(
    "issue 29: a board whose oscillator is off the host's clock walks its tick across "
    "writes aligned once; a walk within 0.15 of a whole number of ticks looks like none "
    "to the stop's probe, and the matching paddle may be said to differ"))


def _paddle(seed: int, tmp_path):
    """A random Hapkit paddle and spring whose loop is stable (drawn again until it is),
    the board's oscillator offset [ppm], 1,000 to 5,000 either way, and the writes' phase
    in the board's tick at the start [fraction of a tick]."""
    rng = np.random.default_rng(5000 + seed)
    prep = stable_paddle(rng, tmp_path / f"paddle{seed}.yaml")
    ppm = float(rng.choice([-1.0, 1.0]) * rng.uniform(1000.0, 5000.0))
    return prep, ppm, float(rng.uniform(0.2, 0.8))


@pytest.mark.parametrize("ppm", [0.0, 800.0, -2500.0, 5000.0])
def test_the_boards_tick_walks_across_the_writes_by_its_offset(ppm):
    """Writes a whole number of nominal ticks apart, from the middle of the board's tick:
    the board takes them at ticks ``per`` apart except where its tick crossed a write,
    ``n per |e|`` times over ``n`` periods (to the one crossing the start's phase may add
    or save); none with the host's clock."""
    prep = _prep("configs/hapkit_serial.yaml")
    n = 600
    _, _, board = hapkit_serial_offline_loop(prep.scene, n, clock_ppm=ppm, levels=0,
                                             render_s=0.0)
    per = round(prep.scene.period / FIRMWARE_TICK_S)
    walk = n * per * abs(ppm) * 1e-6                 # boundaries crossed [ticks]
    got = board.tick_arrivals["off_period"]
    assert abs(got - walk) <= 1.0, (got, walk)
    assert (got == 0) == (ppm == 0.0)
    assert board.TICK_S == FIRMWARE_TICK_S * (1.0 + ppm * 1e-6)


def _verdicts(prep, n, ppm, phase, seed):
    """The matching paddle's measurement and one that differs (30 % more mass on even
    seeds, 0.3 N s/m of friction the scene does not state on odd ones) on the board
    ``ppm`` off, and the matching record's board."""
    cols, drv, board = hapkit_serial_offline_loop(prep.scene, n, clock_ppm=ppm, phase=phase)
    m = _measure(prep, cols, drv)
    dev = prep.scene.device
    wrong = (dataclasses.replace(dev, mass=1.3 * dev.mass) if seed % 2 == 0
             else dataclasses.replace(dev, friction=dev.friction + 0.3))
    cols, drv, _ = hapkit_serial_offline_loop(prep.scene, n, clock_ppm=ppm, phase=phase,
                                              device=wrong)
    return m, _measure(prep, cols, drv), board, drv.tick_moved


def _walked(m) -> bool:
    """A verdict left unsaid for the board's tick's walk."""
    return str(m.get("verdict")).startswith("not measurable: the board's tick moved")


@pytest.mark.parametrize("seed", [7, 8, 11, 12, 13])
def test_a_board_off_the_hosts_clock_never_makes_a_matching_paddle_differ(seed, tmp_path):
    """Seeds 7-13 of the generator (7, 11 and 13 said "differs" of the matching paddle
    before the stop's probe): the matching paddle on a board 1,000-5,000 ppm off is never
    "differs" (within, or not measurable with its reason: the tick's walk); the paddle
    that differs is never within: "differs", or not measurable for the walk the stop's
    probe found (more than :data:`~hapsim.pipeline.unseen_review.TICK_MOVED_MAX`: the
    guard's cost), or with no pair measured and its reason (seeds 7 and 11, before the
    guard too)."""
    from hapsim.pipeline.unseen_review import TICK_MOVED_MAX
    prep, ppm, phase = _paddle(seed, tmp_path)
    n = int(round(DURATION * prep.scene.rate_hz))
    m, w, board, moved = _verdicts(prep, n, ppm, phase, seed)
    assert board.tick_arrivals["off_period"] >= 1          # the class happened
    info = (ppm, phase, moved, m.get("verdict"), m.get("unseen_holds"),
            {q: (m.get(q), prep.pred[q], m.get(f"{q}_unc")) for q in ("k", "b")})
    assert not str(m.get("verdict")).startswith("measured differs"), info
    assert m.get("within") is True or "k" not in m or _walked(m), info
    if seed in (7, 11, 13):
        assert _walked(m) and abs(moved["moved"]) > TICK_MOVED_MAX, info
    assert (str(w.get("verdict")).startswith("measured differs") or "k" not in w
            or (_walked(w) and abs(moved["moved"]) > TICK_MOVED_MAX)), (ppm, w.get("verdict"))
    assert w.get("within") is not True, (ppm, w.get("verdict"))


def _hole(seed: int, tmp_path):
    """A random paddle on a board whose walk over the record is within 0.1 of a whole
    number (1-5) of ticks, either way: where the stop's probe sees none."""
    prep, _, phase = _paddle(seed, tmp_path)
    n = int(round(DURATION * prep.scene.rate_hz))
    rng = np.random.default_rng(9000 + seed)
    walk = float(rng.choice([-1.0, 1.0]) * (rng.integers(1, 6) + rng.uniform(-0.1, 0.1)))
    per = round(prep.scene.period / FIRMWARE_TICK_S)
    return prep, n, walk / (n * per) * 1e6, phase


@pytest.mark.parametrize("seed", [2, pytest.param(7, marks=OPEN),
                                  pytest.param(10, marks=OPEN)])
def test_a_walk_of_whole_ticks_is_the_guards_hole(seed, tmp_path):
    """Walks within 0.1 of a whole number of ticks (seeds 0-11 of :func:`_hole`): the
    stop's probe finds the tick moved by less than the guard's limit, so a "differs" is
    not reviewed; the matching paddle was within in 7 of 12 and "differs" in 4 (1, 7, 9
    and 10). Seed 2 stands for the first; 7 and 10 are strict ``xfail``, the hole open."""
    from hapsim.pipeline.unseen_review import TICK_MOVED_MAX
    prep, n, ppm, phase = _hole(seed, tmp_path)
    cols, drv, board = hapkit_serial_offline_loop(prep.scene, n, clock_ppm=ppm, phase=phase)
    assert board.tick_arrivals["off_period"] >= 1          # the class happened
    assert abs(drv.tick_moved["moved"]) <= TICK_MOVED_MAX   # and the probe saw none
    m = _measure(prep, cols, drv)
    assert not str(m.get("verdict")).startswith("measured differs"), (ppm, m.get("verdict"))


def test_a_differs_is_reviewed_only_for_a_walk_the_probe_saw():
    """:func:`~hapsim.pipeline.unseen_review.review_tick_walk`: a "differs" with the tick
    moved more than the limit, or not placed again, becomes "not measurable" naming the
    walk and the lower bound on the oscillator's offset; within the limit, a "within", or
    no probe, nothing changes."""
    import types

    from hapsim.pipeline.unseen_review import TICK_MOVED_MAX, review_tick_walk
    differs = "measured differs from predicted by more than the stated uncertainty"

    def run(moved, verdict=differs, within=False):
        drv = types.SimpleNamespace(tick_moved=moved)
        return review_tick_walk({"verdict": verdict, "within": within}, drv)

    m = run({"moved": -0.3, "seconds": 1.5, "found": True})
    assert _walked(m) and m["within"] is False and m["tick_walk"]["moved"] == -0.3
    # at least 0.3 of 0.992 ms in 1.5 s: 198 ppm
    assert "at least 198 ppm" in m["verdict"], m["verdict"]
    m = run({"moved": 0.0, "seconds": 1.5, "found": False})
    assert m["verdict"].startswith("not measurable: the board's tick could not be placed")
    for moved in ({"moved": TICK_MOVED_MAX, "seconds": 1.0, "found": True}, None):
        assert run(moved)["verdict"] == differs
    within = "measured = predicted within the stated uncertainty"
    assert run({"moved": 0.4, "seconds": 1.0, "found": True}, within, True)["verdict"] == within


def test_the_stop_probe_finds_how_far_the_boards_tick_walked(monkeypatch):
    """In process, the sketch's loop on a tick of its own and the host on one simulated
    clock (:class:`test_hapkit_serial_tick.TickingPort`, ``SimClock``): the board's
    oscillator 350 ppm off either way, the stop's probe 1 s after the arming's finds the
    tick moved by ``fold(1 s e / tick)``, 0.35 of a tick, and none on the host's clock;
    to the two probes' placements (each to half their spacing of a sixteenth of a tick:
    a thirty-second) and what the tick walked during each (16 probes spaced 7 ticks and
    a sixteenth apart, 0.11 s: 0.04 of a tick at 350 ppm)."""
    from test_hapkit_serial_tick import TICK_NS, TickingPort, _transport
    from hapsim.drivers import tick_align
    for ppm in (350.0, -350.0, 0.0):
        port = TickingPort(300_000, 200_000, sketch=True, tick_ns=TICK_NS * (1 + ppm * 1e-6))
        tr = _transport(monkeypatch, port)
        assert tr.tick_phase() is not None, tr.tick_probe
        t0 = tick_align.time.monotonic_ns()
        tick_align.time.sleep(1.0 - (tick_align.time.monotonic_ns() - tr._write_at) * 1e-9)
        got = tr.end_probe()
        span = (tick_align.time.monotonic_ns() - t0) * 1e-9 - 1.0 + 0.11   # one probe [s]
        assert got["found"], tr.tick_probe
        want = (got["seconds"] * ppm * 1e-6 * 1e9 / TICK_NS + 0.5) % 1.0 - 0.5
        tol = 2 / 32 + 2 * span * abs(ppm) * 1e-6 * 1e9 / TICK_NS
        assert abs(got["moved"] - want) <= tol, (ppm, got, want, tol)
        assert tr.driver.tick_moved is got and tr.report()["tick_moved"] is got


def test_an_oscillator_offset_is_refused_with_its_key():
    """An offset that is no number, or 10 % and more, is refused naming the key."""
    from hapsim.emulated.hapkit_serial_board import HapkitSerialDevice
    from hapsim.errors import ConfigError
    prep = _prep("configs/hapkit_serial.yaml")
    for bad in (float("nan"), 1e5, "fast"):
        with pytest.raises(ConfigError, match="clock_ppm"):
            HapkitSerialDevice(prep.scene.device, prep.scene.rate_hz, clock_ppm=bad)
