"""The Haply M3 board keeps its own time (issue 29 items 1 and 2).

The board's emulation (``hapsim.emulated.driver_mock.HaplyDevice``, ``clock="wall"`` by default) runs
its joint on the wall clock, holding the last torque while the host is silent or late; the
host's driver must survive that: a late reply is a late sample, a host stall is a stall (no
catch-up burst), and a re-synchronisation needs evidence that the board lost its place.
"""

import math
import struct
import subprocess
import sys
import time

import numpy as np
import pytest

from hapsim.device_model import MockPhysics
from hapsim.emulated.driver_mock import HaplyDevice, WallClock
from hapsim.drivers import haply as hp
from hapsim.scene import Device, Excitation
from tolerance import rel_tol

EPS = np.finfo(float).eps


def free_motion(x0, v0, u, m, b, t):
    """m x'' + b x' = u with u constant (b > 0): the closed form, written here
    independently of hapsim's step coefficients."""
    tau = m / b
    vinf = u / b
    e = math.exp(-t / tau)
    return x0 + vinf * t + (v0 - vinf) * tau * (1.0 - e), vinf + (v0 - vinf) * e


@pytest.mark.parametrize("seed", range(5))
def test_a_period_cut_anywhere_is_the_period(seed):
    """The wall clock integrates exactly: a force held over intervals of any lengths
    reaches the closed-form state, and a force change inside a period acts from its time
    on (the split of the interval at the change)."""
    rng = np.random.default_rng(seed)
    m, b = rng.uniform(1e-4, 1e-2), rng.uniform(1e-4, 1e-2)
    rate = float(rng.choice([250.0, 1000.0]))
    x0, v0 = rng.uniform(-0.3, 0.3), rng.uniform(-2, 2)
    ph = MockPhysics(Device(mass=m, friction=b, delay=1), rate, Excitation(x0=x0, v0=v0))
    wc = WallClock(ph)
    u1, u2 = rng.uniform(-0.1, 0.1, 2)
    t_change = rng.uniform(0.1, 3.7) / rate
    t_end = rng.uniform(4.0, 9.0) / rate
    wc.schedule(0.0, u1)
    wc.schedule(t_change, u2)
    for t in np.sort(rng.uniform(0.0, t_end, 7)):
        wc.run_to(float(t))
    wc.run_to(t_end)
    x1, v1 = free_motion(x0, v0, u1, m, b, t_change)
    x2, v2 = free_motion(x1, v1, u2, m, b, t_end - t_change)
    # each interval's exact step is good to a few eps of the state's scale; at most ~20
    # intervals are chained (7 reads, 9 period boundaries, the change): 200 eps of margin
    scale = abs(x0) + abs(v0) * t_end + abs(u1 + u2) / b * t_end + 1e-12
    assert ph.x == pytest.approx(x2, abs=200 * EPS * scale)
    assert ph.v == pytest.approx(v2, abs=200 * EPS * (abs(v0) + abs(u1 + u2) / b))
    assert wc.held == u2 and ph.n == int(t_end * rate)


def _write(tau):
    return hp.write_packet(1, tau)


def _angle(reply):
    return struct.unpack("<f", reply[1:5])[0]


def test_the_board_holds_its_torque_through_a_silence():
    """No watchdog (firmware V1.5): a torque written at t = 0 acts over the whole silence
    the host leaves; the next write's reply carries the angle sampled when it arrives,
    the closed form's to the encoder's count."""
    m, b, cpr = 1e-3, 1e-3, 4880.0
    dev = HaplyDevice(Device(mass=m, friction=b, delay=1, force_limit=0.12), 1000.0,
                      Excitation(), cpr=cpr, resolution=cpr)
    setup = hp.setup_packet(1, resolution=cpr)
    out = dev.feed(setup, 0.0)
    t0 = HaplyDevice.SETUP_S                      # the Encoder's 2 ms before the next pass
    assert out == b""
    out = dev.feed(_write(0.05), 0.0)
    # one sum of positive times at most: derived rel_tol(1)
    assert len(out) == 5 and dev.ready_at == pytest.approx(t0, rel=rel_tol(1))
    silence = 0.05
    out = dev.feed(_write(0.0), t0 + silence)
    x, _ = free_motion(0.0, 0.0, 0.05, m, b, silence)
    count = round(x / (2 * math.pi) * cpr)
    # the count's angle, two double roundings either side, went as binary32 (2^-24 of it):
    # derived; a count's difference is 0.074 degrees
    assert _angle(out) == pytest.approx(360.0 * count / cpr, rel=2.0 ** -24 + rel_tol(4))
    assert count > 40                             # it really moved: 0.05 N m over 50 ms (48)


def test_lockstep_is_asked_by_name():
    dev = HaplyDevice(Device(mass=1e-3, friction=1e-3, delay=1), 1000.0)
    assert dev.clock == "wall"
    with pytest.raises(ValueError, match="time of each packet"):
        dev.feed(hp.setup_packet(1) + _write(0.01))
    with pytest.raises(Exception, match="valid: wall, lockstep"):
        HaplyDevice(Device(mass=1e-3, friction=1e-3, delay=1), 1000.0, clock="host")


@pytest.mark.parametrize("seed", range(20))
def test_late_and_bunched_replies_are_samples(seed):
    """A joint sampled when the writes of a jittery host arrive (gaps of 0.2 to 40
    periods, replies read one by one or several in one read): the reply decoder takes
    every reply, with no byte skipped (before: a reply off the per-reply linear prediction
    by 2 deg was dropped, a run of them counted as a desync, and the host re-synchronised
    a board that had lost nothing). A flipped exponent bit on a moving joint is still no
    reply."""
    rng = np.random.default_rng(seed)
    w, amp, zeta = rng.uniform(5, 60), rng.uniform(0.05, 1.0), rng.uniform(0, 0.2)
    res = 4880.0
    now = [0.0]
    dec = hp.ReplyDecoder(1, resolution=res, clock=lambda: now[0])
    t, taken, sent = 0.0, 0, 0
    while t < 1.0:
        batch = int(rng.choice([1, 1, 1, 2, 3]))
        data = b""
        for _ in range(batch):
            t += float(rng.choice([rng.uniform(0.2e-3, 2e-3), rng.uniform(2e-3, 40e-3)],
                                  p=[0.9, 0.1])) if batch == 1 else rng.uniform(0, 0.3e-3)
            theta = amp * math.exp(-zeta * w * t) * math.cos(w * t)
            count = round(theta / (2 * math.pi) * res)
            data += hp.reply_packet(1, 360.0 * count / res)
            sent += 1
        now[0] = t
        taken += len(dec.feed(data))
    assert taken == sent and dec.stats["skipped"] == 0 and dec.stats["desync"] == 0
    # a corrupted exponent on a joint well away from zero, within one period of the last
    # two replies: 2^k times the angle is no motion
    dec2 = hp.ReplyDecoder(1, resolution=res, clock=lambda: now[0])
    for k, a in enumerate((30.0, 30.2, 30.4)):
        now[0] = k * 1e-3
        assert dec2.feed(hp.reply_packet(1, 360.0 * round(a / 360 * res) / res))
    now[0] = 3e-3
    assert dec2.feed(hp.reply_packet(1, 2 * 360.0 * round(30.6 / 360 * res) / res)) == []


def _burners(n):
    return [subprocess.Popen([sys.executable, "-c", "import time\nend = time.time() + 60\n"
                              "while time.time() < end: pass"]) for _ in range(n)]


@pytest.mark.xdist_group("haply_wallclock")
def test_a_host_stall_is_a_stall_beside_two_busy_processes(monkeypatch):
    """configs/haply.yaml on the wall-clock board, beside two CPU-bound processes, with a
    6 ms host stall injected (the issue's trigger): no re-synchronisation, the joint
    never beyond where the hand let it go (x0 = 0.2 rad: the loop is stable and passive
    at K = 0.5 N m/rad, K_max 1.33), zero torque left; or, on a machine too loaded to
    hold 1 kHz, the lateness safety stop before the joint goes far."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.drivers import transport
    from hapsim.scene import load_scene
    sent = {"n": 0}
    send = transport.DriverTransport.send

    def stalling_send(self, msg):
        sent["n"] += 1
        if sent["n"] == 700:
            time.sleep(0.006)
        return send(self, msg)

    monkeypatch.setattr(transport.DriverTransport, "send", stalling_send)
    from load import burners_for  # same directory (pytest prepend import mode)
    procs = _burners(burners_for(2))   # the other xdist worker is one of the two
    try:
        # the product's default scheduling (SCHED_FIFO where permitted, as hapsim run)
        rep = run_scene(load_scene("configs/haply.yaml"), driver="haply",
                        handle_signals=False)
    finally:
        for p in procs:
            p.kill()
    lp, m = rep["loop"], rep["measured"]
    assert lp["mock"]["clock"] == "wall"
    assert lp["driver"]["resyncs"] == 0, lp["driver"]
    assert lp["driver"]["decoder"]["desync"] == 0
    assert lp["mock"]["held_at_end"] == 0.0
    if lp["safety_stop"]:
        # a machine too loaded to hold 1 kHz without real-time priority: the loop stops
        # itself before the joint goes far (the lateness rule), and says so
        assert "the host was" in lp["stop_reason"], lp["stop_reason"]
        assert lp["mock"]["true_excursion"] <= 2 * 0.2, lp["mock"]["true_excursion"]
        return
    assert lp["mock"]["true_excursion"] <= 0.2 * (1 + 1e-9), (
        {k: lp[k] for k in ("ticks", "missed", "estimated", "overruns", "stop_reason")})
    # never "differs" of the matching joint: the host's write jitter within a period
    # (before: one run in three at load 15-18 said 'differs' with under 2 % late ticks)
    # is corrected, its remainder stated (hapsim.analysis.write_holds, measure's
    # write_hold_s), and a "differs" stands only beyond the link's unseen 50 us too
    assert m.get("verdict") or m.get("error")
    assert not str(m.get("verdict", "")).startswith("measured differs"), (
        {q: m.get(q) for q in ("verdict", "k", "b", "k_unc", "b_unc", "write_hold_s")})


def test_a_late_run_is_not_called_within():
    """The run's verdict is withdrawn when the host was late in more than 2 % of the ticks
    or the board's re-synchronisations may have moved the device out of its workspace
    (the host's largest reading plus their summed frame bound beyond the position bound;
    a transport that states no bound: unbounded), however many there were otherwise (on
    the wall clock; a lockstep run's host paces the device, so lateness costs nothing
    there)."""
    from types import SimpleNamespace

    from hapsim.pipeline.runner import LATE_SHARE_MAX, timing_verdict
    base = {"k": 1.0, "b": 0.1, "within": True, "verdict": "measured = predicted"}
    m = dict(base)
    timing_verdict(m, SimpleNamespace(samples=1000, overruns=int(LATE_SHARE_MAX * 1000)),
                   {"resyncs": 9, "frame_bound": 0.5}, workspace=(0.2, 4.0))
    assert m["within"]
    m = dict(base)
    timing_verdict(m, SimpleNamespace(samples=1000, overruns=int(LATE_SHARE_MAX * 1000) + 1),
                   {"resyncs": 0})
    assert not m["within"] and m["verdict"].startswith("not measurable: the host missed")
    for link, ws in (({"resyncs": 3, "frame_bound": 0.5}, (3.6, 4.0)),
                     ({"resyncs": 1}, (0.2, 4.0))):
        m = dict(base)
        timing_verdict(m, SimpleNamespace(samples=1000, overruns=0), link, workspace=ws)
        assert not m["within"] and "beyond the workspace" in m["verdict"], link
        assert f"re-synchronised {link['resyncs']} times" in m["verdict"]
    m = dict(base)
    timing_verdict(m, SimpleNamespace(samples=1000, overruns=500), {"resyncs": 9}, wall=False,
                   workspace=(3.9, 4.0))
    assert m["within"]
