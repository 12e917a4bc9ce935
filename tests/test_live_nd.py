"""The live sound of a 2-D/3-D scene without a sound server (issue 23 item 7; the real
JACK server's test is in test_audio_live.py): the producer's frames are the offline
rendering's whatever the chunk, it never runs more than ``ahead`` frames beyond the
reader, it makes no array per chunk, and ``hapsim play`` refuses by name what an n-D
scene's play does not take."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from hapsim.audio.live import LiveND
from hapsim.audio.offline import render_nd
from hapsim.engine import Engine
from hapsim.scene import load_scene_nd

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


class _Reader:
    """A sound server's reader on a virtual clock: ``block`` frames read per call of the
    producer's sleep, the largest lead of the writer over it recorded."""

    def __init__(self, live, block):
        self.live, self.block, self.lead = live, block, 0
        self.frames = []

    def sleep(self, _):
        self.lead = max(self.lead, self.live.written - self.live.read)
        self.frames.append(self.live.ring.render(self.block).copy())


@pytest.mark.parametrize("chunk,block", [(256, 256), (100, 333)])
def test_ring_frames_are_the_offline_rendering_and_the_lead_is_bounded(chunk, block,
                                                                       monkeypatch):
    """The membrane, 5,000 frames in chunks of any size (a last partial one) read in
    blocks of any size: what the reader gets, in order, is render_nd's float64 frames
    rounded to float32, bit for bit; the writer is never more than ``ahead`` frames
    beyond the reader; no silence between the first and the last frame."""
    import hapsim.audio.live as ln
    sc = load_scene_nd(CONFIGS / "membrane.yaml")
    total = 5000
    ref = render_nd(Engine(sc), total)[:, 0].astype(np.float32)
    live = LiveND(Engine(sc), chunk=chunk, ring=4096, ahead=1024)
    rd = _Reader(live, block)
    monkeypatch.setattr(ln.time, "sleep", rd.sleep)
    assert live.run(total) == total
    while live.read < total:
        rd.sleep(0)
    got = np.concatenate(rd.frames)[:, 0]
    np.testing.assert_array_equal(got[:total], ref)
    assert rd.lead <= live.ahead
    st = live.stats()
    assert st["underruns"] == 0 and st["skipped"] == 0 and st["read"] >= total


def test_a_late_producer_underruns_are_counted_and_the_sound_resumes():
    """The reader reads 3 blocks before the producer starts and 2 while it is silent
    mid-way: the silence before the first frame is not an underrun, the mid-way one is
    (its frames counted), and the frames read are the offline ones in order."""
    sc = load_scene_nd(CONFIGS / "membrane.yaml")
    ref = render_nd(Engine(sc), 1024)[:, 0].astype(np.float32)
    live = LiveND(Engine(sc), chunk=256, ring=4096, ahead=1024)
    ring = live.ring
    before = [ring.render(128).copy() for _ in range(3)]   # not started yet
    live.produce()
    a = ring.render(256).copy()
    gap = [ring.render(128).copy() for _ in range(2)]       # the producer is late
    live.produce()
    live.produce()
    live.produce()
    b = np.concatenate([ring.render(256).copy() for _ in range(3)])
    live._missing_end = int(ring.callback_pack.st[1])       # as run() ends
    assert not np.any(np.concatenate(before)) and not np.any(np.concatenate(gap))
    assert live.stats()["underruns"] == 256
    np.testing.assert_array_equal(np.concatenate([a, b])[:, 0], ref)


def test_a_chunk_makes_no_array(monkeypatch):
    """The producer's chunk (engine, ring) makes no array: its transient memory, with the
    two compiled calls replaced by no-ops (their numba dispatch is the one cost Python
    cannot avoid; the native JACK callback allocates nothing), is below one small
    array's."""
    import hapsim.audio.sources as src
    sc = load_scene_nd(CONFIGS / "membrane.yaml")
    monkeypatch.setattr(src.audio_kernel, "ring_write", lambda f, r, w: None)
    live = LiveND(Engine(sc), chunk=256)
    live._listen = lambda out: None
    live.produce()
    tracemalloc.start()
    try:
        peaks = []
        for _ in range(5):
            tracemalloc.reset_peak()
            c0 = tracemalloc.get_traced_memory()[0]
            live.produce()
            peaks.append(tracemalloc.get_traced_memory()[1] - c0)
        tracemalloc.reset_peak()
        c0 = tracemalloc.get_traced_memory()[0]
        np.empty(1)
        one = tracemalloc.get_traced_memory()[1] - c0
    finally:
        tracemalloc.stop()
    assert max(peaks[1:]) < one, (peaks, one)


@pytest.mark.parametrize("argv,flag", [(["--telemetry", "t.npz"], "--telemetry"),
                                       (["--pluck-every", "0.5"], "--pluck-every"),
                                       (["--lockstep"], "--lockstep"),
                                       (["--sound", "none"], "--sound")])
def test_play_nd_refuses_what_it_does_not_take(argv, flag, capsys):
    """``hapsim play MEMBRANE`` with an option an n-D scene's play does not take (or
    --pluck-every, on a scene without an excitation): exit 2, the flag named, before any
    sound opens."""
    from hapsim.cli import main
    assert main(["play", str(CONFIGS / "membrane.yaml"), *argv]) == 2
    assert flag in capsys.readouterr().err


def test_play_nd_needs_an_audio_section(capsys):
    """A 2-D scene without an audio section: exit 2 naming the key."""
    from hapsim.cli import main
    assert main(["play", str(CONFIGS / "pantograph_wall.yaml"), "--sound", "jack"]) == 2
    assert "audio" in capsys.readouterr().err
