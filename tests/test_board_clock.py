"""A Hapkit whose oscillator is off the host's clock: its ticks walk across the host's writes.

The WHC2017 sketch takes commands on its own Timer1 tick, 62 counts of 16 us from its
16 MHz source (``Hapkit_arduino.h:59-68``). The host aligns its writes to the middle of
that tick once, at the first arming (:class:`hapsim.drivers.tick_align.TickAligned`), and
then writes a whole number of the nominal 0.992 ms ticks apart. A board whose source is
``e`` off the host's clock (a crystal tens of ppm, a ceramic resonator up to a few
thousand) walks its tick ``per e`` of a tick a period against those writes, ``per`` the
period's ticks: over a record of ``n`` periods the writes cross ``n per |e|`` tick
boundaries, each a command taken a tick early or late, which the host does not see
(:class:`hapsim.emulated.hapkit_serial_board.HapkitSerialDevice`, ``clock_ppm``).

Closed offline on the simulated clock
(:func:`hapsim.emulated.hapkit_serial_board.hapkit_serial_offline_loop`), random paddles
and springs, the board's oscillator 1,000 to 5,000 ppm off, the writes at a random phase:
over seeds 0-15 of the generator below the matching paddle was "within" in 13 and
"differs" in 3 (7, 11 and 13; seed 13 at 1,252 ppm, one boundary crossed). A crossing is
no isolated hold: the handle's read moves for the rest of the record (from the command's
end to the board's tick, or back), a loop whose delay changed, which the unseen holds'
review (:mod:`hapsim.analysis.unseen_holds`) takes for 7-8 holds. The host does not follow
the board's clock: this class is open (issue 29, a wrong verdict), and its seeds are
marked strict ``xfail`` so that a fix shows here. Seeds 8 and 12 stand for the rest: the
matching paddle within, one that differs "differs".
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hapsim.drivers.hapkit_serial import FIRMWARE_TICK_S
from hapsim.emulated.hapkit_serial_board import hapkit_serial_offline_loop
from hapsim.errors import UnstableConfigError
from test_unseen_holds import DURATION, YAML, _measure, _prep   # same directory

OPEN = pytest.mark.xfail(strict=True, reason=(
    "issue 29: the host aligns its writes to the board's tick once; a board whose "
    "oscillator is off the host's clock walks its tick across them and the matching "
    "paddle may be said to differ"))


def _paddle(seed: int, tmp_path):
    """A random Hapkit paddle and spring whose loop is stable (drawn again until it is),
    the board's oscillator offset [ppm], 1,000 to 5,000 either way, and the writes' phase
    in the board's tick at the start [fraction of a tick]."""
    rng = np.random.default_rng(5000 + seed)
    path = tmp_path / f"paddle{seed}.yaml"
    while True:
        m = float(rng.uniform(0.05, 0.15))
        K = float(rng.uniform(60.0, 150.0))
        x0 = min(float(rng.uniform(0.005, 0.015)), 1.5 / K)      # within the 2 N limit
        path.write_text(YAML.format(rate=float(rng.choice([252.016, 201.613])), K=K,
                                    B=float(rng.uniform(0.0, 0.3)), m=m,
                                    b0=float(rng.uniform(0.05, 0.4)), x0=x0))
        try:
            prep = _prep(path)
            break
        except UnstableConfigError:      # beyond the stability limit: another loop
            continue
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


@pytest.mark.parametrize("seed", [pytest.param(7, marks=OPEN), 8,
                                  pytest.param(11, marks=OPEN), 12,
                                  pytest.param(13, marks=OPEN)])
def test_a_board_off_the_hosts_clock_never_makes_a_matching_paddle_differ(seed, tmp_path):
    """The matching paddle on a board 1,000-5,000 ppm off the host's clock is never
    "differs" (within, or not measurable with its reason); one with 30 % more mass (even
    seeds) or 0.3 N s/m of friction the scene does not state (odd ones), on the same
    board, "differs"."""
    prep, ppm, phase = _paddle(seed, tmp_path)
    n = int(round(DURATION * prep.scene.rate_hz))
    cols, drv, board = hapkit_serial_offline_loop(prep.scene, n, clock_ppm=ppm, phase=phase)
    assert board.tick_arrivals["off_period"] >= 1          # the class happened
    m = _measure(prep, cols, drv)
    info = (ppm, phase, m.get("verdict"), m.get("error"), m.get("unseen_holds"),
            {q: (m.get(q), prep.pred[q], m.get(f"{q}_unc")) for q in ("k", "b")})
    assert not str(m.get("verdict")).startswith("measured differs"), info
    assert m.get("within") is True or "k" not in m, info
    dev = prep.scene.device
    wrong = (dataclasses.replace(dev, mass=1.3 * dev.mass) if seed % 2 == 0
             else dataclasses.replace(dev, friction=dev.friction + 0.3))
    cols, drv, _ = hapkit_serial_offline_loop(prep.scene, n, clock_ppm=ppm, phase=phase,
                                              device=wrong)
    m = _measure(prep, cols, drv)
    assert str(m.get("verdict")).startswith("measured differs"), (ppm, m.get("verdict"))


def test_an_oscillator_offset_is_refused_with_its_key():
    """An offset that is no number, or 10 % and more, is refused naming the key."""
    from hapsim.emulated.hapkit_serial_board import HapkitSerialDevice
    from hapsim.errors import ConfigError
    prep = _prep("configs/hapkit_serial.yaml")
    for bad in (float("nan"), 1e5, "fast"):
        with pytest.raises(ConfigError, match="clock_ppm"):
            HapkitSerialDevice(prep.scene.device, prep.scene.rate_hz, clock_ppm=bad)
