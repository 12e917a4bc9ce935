"""``hapsim play --osc`` on a 2-D scene, against real parts: the real JACK dummy server
(its own, at the scene's 8 kHz), a python-osc client and Pd run headless. The sound a
client of ours records through a real JACK connection is the independent rendering of
tests/test_play_nd.py with the change ramped from the sample the journal names, to
float32 round-off; the unstable change is refused with the reason; Pd's changes (a plane's
stiffness: one stable, one not) get their verdicts."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from recording import assert_periods_match
from test_audio_live import Recorder, dummy_jackd, without_xrun_periods
from test_osc import PATCH, Client, Sink, play_daemon, run_patch, stop, wait_for
from test_play_nd import (F32_OF_SCALE, SCENE, assert_float32_roundoff, hand_of_scene,
                          reference)
from tolerance import rel_tol

#: pytest-xdist: a private jackd and OSC clients, serialised with the other live tests.
pytestmark = pytest.mark.xdist_group("sound")

RATE = 8000


@pytest.fixture(scope="module")
def jack8k():
    """A private ``jackd -d dummy -r 8000 -p 128`` (the test scene's rate); its name."""
    yield from dummy_jackd(RATE, 128)


def start_play(server, *extra):
    """``hapsim play SCENE --osc 0`` through ``server``; the process and its OSC port."""
    return play_daemon(SCENE, server, *extra)


def assert_heard(got, i0, j, length, ref, sound):
    """The recording ``got`` is the rendering ``ref`` (shape (r,)) to float32 round-off,
    from its first sound (at ``i0``, the rendering's ``j``: :func:`aligned`) for
    ``length`` frames, but for what the xruns the server reported (``sound``: the
    report's) may do: with every period recorded, :func:`recording.assert_periods_match`
    (a late recording client garbles a period and loses the next, measured); where the
    producer was late (underruns), its silences dropped and one period off per xrun
    (:func:`test_audio_live.without_xrun_periods`; seen once in a fresh-clone suite: 128
    frames of one period off, every later frame in order)."""
    atol = F32_OF_SCALE * np.max(np.abs(ref))
    if not sound["underruns"]:
        seen = assert_periods_match(got[:i0 + length], ref, sound["block"], sound["xruns"],
                                    atol)
        assert seen["compared"] > length - 2000, seen
        return
    seg = got[i0:i0 + length]
    seg = seg[seg != 0]                  # silences where the producer was late
    m = min(seg.size, ref.size - j)
    assert m > length - 2000
    seg, want = seg[:m], ref[j:j + m]
    bad = np.flatnonzero(np.abs(seg - want) > atol)
    keep = without_xrun_periods(bad, seg.size, sound["xruns"], sound["block"])
    assert_float32_roundoff(seg[keep, None], want[keep, None])


def aligned(got, ref, window=400):
    """Where the recording's first sound is in the reference: the offset whose window
    matches best (the recorder connects after the sound started)."""
    i0 = int(np.flatnonzero(got)[0])
    w = got[i0:i0 + window].astype(float)
    views = np.lib.stride_tricks.sliding_window_view(ref, window)
    j = int(np.argmin(np.max(np.abs(views - w), axis=1)))
    return i0, j


def test_python_osc_changes_the_2d_scene_and_the_recorded_sound_follows(jack8k):
    """A stable /hapsim/link/kb is accepted (ok, ramp time, felt k b), an unstable one is
    refused with 'unstable', /hapsim/felt carries n and the felt matrices, /hapsim/loop the
    sample and the verdict; the recorded sound from the first frame heard to 0.4 s after
    the ramp is the independent rendering with that ramp, to float32 round-off."""
    rec = Recorder(jack8k, seconds=30.0)
    rec.armed = False                 # from the connection on (a loaded start is slow)
    proc, port = start_play(jack8k, "--ramp", "0.01")
    try:
        src = rec.client.get_ports("hapsim.*:out_m2_y_velocity")
        assert src, rec.client.get_ports()
        rec.client.connect(src[0], rec.inp.name)
        rec.armed = True
        c = Client(port, proc)
        sink = Sink()
        addr, p = c.ask("/hapsim/telemetry", "127.0.0.1", sink.port, 100.0)
        assert addr == "/hapsim/ok", p
        addr, felt = c.ask("/hapsim/felt")
        assert addr == "/hapsim/felt" and len(felt) == 6 + 1 + 8 and felt[6] == 2
        addr, p = c.ask("/hapsim/link/kb", "chain", 900.0, 0.25)
        assert addr == "/hapsim/ok" and p[0] == "/hapsim/link/kb", p
        # OSC's binary32 of the double: 2^-24 relative (derived; IEEE 754 round to nearest)
        assert p[1] == pytest.approx(0.01, rel=2.0 ** -24 + rel_tol(1))
        addr, p = c.ask("/hapsim/link/kb", "chain", 1e8, 0.0)
        assert addr == "/hapsim/refused" and "unstable" in p[1], p
        addr, p = c.ask("/hapsim/loop")
        assert addr == "/hapsim/loop" and p[2] == 1 and (p[3], p[4]) == (1, 1)
        wait_for(c, "/hapsim/loop", lambda q: q[0] > p[0] + 8000, "0.5 s after the ramp")
    finally:
        rep = stop(proc)
        rec.close()
    assert rep["links"]["chain"] == [900.0, 0.25] and rep["loop"] == "closed"
    start = [e["sample"] for e in rep["journal"] if e["event"] == "ramp_start"]
    end = [e["sample"] for e in rep["journal"] if e["event"] == "ramp_end"]
    assert len(start) == 1 and end == [start[0] + 80]
    got = rec.buf[:rec.n]
    assert np.any(got), "the recording is silent"
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(SCENE)

    def chain(par, a):
        par["K"]["chain"] = 500 + a * 400
        par["B"]["chain"] = 0.1 + a * 0.15
    n = end[0] + int(0.4 * RATE)
    h, e = hand_of_scene(sc)                      # the scene's excitation, once
    track = []
    ref = reference(sc, n, [(start[0], 80, chain)], hand=h, direction=e,
                    track=track)[:, :1]
    # every /hapsim/tel t x y fx fy k b: the device's position at sample t * rate
    from pythonosc.osc_message import OscMessage
    tel = [m.params for m in map(OscMessage, sink.close()) if m.address == "/hapsim/tel"]
    # 100 Hz at most; how many come is the loop's pace (a loop catching up after a
    # preemption sends one for its whole stretch): 16 over the run in a fresh-clone suite
    # beside a CPU-bound process, >20 unloaded. What is asserted of each is its content
    assert len(tel) >= 8 and all(len(p) == 7 for p in tel), len(tel)
    k = np.array([round(p[0] * RATE) for p in tel])
    assert np.all(np.diff(k) >= 80)               # 100 Hz at most
    k_in = k <= n
    assert k_in.sum() >= 5, k
    # OSC's binary32 of each double: 2^-24 relative (derived; measured 3.7e-8); the atol a
    # floor for an exact 0, far below any position
    np.testing.assert_allclose(np.array([p[1:3] for p in tel])[k_in],
                               np.array(track)[k[k_in]], rtol=2.0 ** -24 + rel_tol(2),
                               atol=1e-15)
    i0, j = aligned(got, ref[:, 0])
    assert j < start[0], "the recording began after the change"
    assert_heard(got, i0, j, n - j, ref[:, 0], rep["sound"])


def test_plucks_every_quarter_second_are_recorded_at_their_samples(jack8k):
    """``hapsim play SCENE --pluck-every 0.25``: the scene's impulse again every 2000
    samples; the recorded sound is the independent rendering with the plucks at samples
    2000 k + 80 .. 2000 k + 120, to float32 round-off, over the first second heard."""
    rec = Recorder(jack8k, seconds=30.0)
    rec.armed = False
    proc, port = start_play(jack8k, "--pluck-every", "0.25")
    try:
        rec.client.connect(rec.client.get_ports("hapsim.*:out_m2_y_velocity")[0],
                           rec.inp.name)
        rec.armed = True
        c = Client(port, proc)
        wait_for(c, "/hapsim/loop", lambda q: q[0] > 20000, "2.5 s of sound")
    finally:
        rep = stop(proc)
        rec.close()
    assert rep["plucks"]["every_samples"] == 2000
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(SCENE)
    h, e = hand_of_scene(sc)
    got = rec.buf[:rec.n]
    ref = reference(sc, 20000, hand=h, direction=e, every=2000)[:, :1]
    i0, j = aligned(got, ref[:, 0])
    length = min(8000, 20000 - j)
    assert length > 4000 and (j + length) // 2000 > j // 2000 + 1   # two plucks heard
    assert_heard(got, i0, j, length, ref[:, 0], rep["sound"])


def test_pd_patch_changes_a_plane_of_the_2d_scene(jack8k, tmp_path):
    """tests/test_osc.py's Pd patch, run headless (pd -nogui -nosound) against the 2-D
    scene: /hapsim/link/stiffness wall 600 (the plane under the handle) is accepted and
    applied, wall 1e6 is refused (the MIMO loop would be unstable)."""
    if shutil.which("pd") is None:
        pytest.skip("pd not installed: apt-get install puredata")
    proc, port = start_play(jack8k)
    try:
        run_patch(PATCH, port, tmp_path)
        c = Client(port, proc)
        wait_for(c, "/hapsim/loop", lambda p: (p[3], p[4]) == (1, 1), "Pd's two changes")
    finally:
        rep = stop(proc)
    assert rep["links"]["wall"] == [600.0, 1.0]
    got = [(e["event"], e["args"], e.get("reason", "")) for e in rep["journal"]
           if e["event"] in ("accepted", "refused")]
    assert [g[:2] for g in got] == [("accepted", ["wall", 600.0]), ("refused", ["wall", 1e6])]
    assert "unstable" in got[1][2]
