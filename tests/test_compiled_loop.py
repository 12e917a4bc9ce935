"""The compiled host loop (hapsim.host.fastloop) against the Python loop (the reference).

A scripted device on a real pseudo-terminal answers HELLO_REQUEST and PING, and after each
CONFIG streams the next segment of a recorded byte stream (STATEs with faults: corrupted,
truncated and garbage frames, duplicates, reordering, gaps, an implausible jump, unarmed
STATEs, FAULTs, a HELLO after arming, late force_seq) in seeded random chunks that split
frames anywhere. The device stream does not depend on the forces, so both loops see the
same STATEs and must send the same FORCEs bit for bit, log the same telemetry (all
columns but the turnaround, a time measurement) and report the same counters, stops and
flags. No timing is asserted.

The same in a compact session (PROTOCOL.md §4 "Compact frames": the device offers COMPACT
at SENSORS_REQUEST and streams STATE_COMPACTs whose 16-bit seq wraps past 65535; the host
answers FORCE_COMPACT): both loops expand the same seqs, force_seqs and times and send the
same binary32 forces.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.host.fastloop import CompiledHostLoop, encode_force
from hapsim.host.loop import HostLoop, LoopConfig, StopFlag
from hapsim.analysis.late_growth import late_growth
from hapsim.pipeline.runner import prepare_scene
from hapsim.host.telemetry import Telemetry
from hapsim.host.transport import SerialTransport
from hapsim.engine import Engine
from hapsim.scene import load_scene
from pty_device import PtyDevice

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WALL = os.path.join(ROOT, "configs", "wall.yaml")
ARMED = fp.STATUS_ARMED | fp.STATUS_FORCE_APPLIED
D = 1


class ScriptedDevice(PtyDevice):
    """A device on a pty master: HELLO for HELLO_REQUEST, PONG for PING, and after the
    i-th CONFIG the chunks of ``segments[i]``; records every FORCE and STOP.

    ``stop_at``: (seq, StopFlag): request the stop just before writing the chunk that
    holds the STATE ``seq`` (for the stop-latency test)."""

    def __init__(self, master: int, segments, stop_at=None, compact=False):
        super().__init__(master, fp.encode(fp.Hello(fp.PROTOCOL_VERSION, 1, 7, 1e-6, 1e-3,
                                                    10.0, 1000.0)))
        self.segments = list(segments)
        self.forces: list = []
        self.stops = 0
        self.configs = 0
        self.stop_at = stop_at
        self.pending: list = []
        self.compact = compact

    def on_message(self, msg):
        t = type(msg)
        if t is fp.SensorsRequest and self.compact:
            os.write(self.master, fp.encode(fp.Sensors(fp.FEATURE_COMPACT,
                                                       msg.sensors & fp.FEATURE_COMPACT)))
        elif t is fp.ForceCompact:
            self.forces.append((msg.seq, msg.force[0]))
        elif t is fp.Config:
            self.pending = list(self.segments[self.configs]) \
                if self.configs < len(self.segments) else []
            self.configs += 1
        elif t is fp.Force:
            self.forces.append((msg.seq, msg.force[0]))
        elif t is fp.Stop:
            self.stops += 1

    def tick(self):
        pending = self.pending
        if pending and isinstance(pending[0], int):   # a burst waits for its answer
            if self.forces and (self.forces[-1][0] == pending[0] & 0xFFFF if self.compact
                                else self.forces[-1][0] >= pending[0]):
                pending.pop(0)
        elif pending:
            seqs, chunk = pending.pop(0)
            if self.stop_at is not None and self.stop_at[0] in seqs:
                self.stop_at[1].request()
            os.write(self.master, chunk)
        return 0.0005 if pending else 0.01


def state(seq, x, *, status=ARMED, fseq=None):
    return fp.encode(fp.State(seq & 0xFFFFFFFF, 1000 * seq + 17, status,
                              ((seq - D) if fseq is None else fseq) & 0xFFFFFFFF, (x,)))


def cstate(seq, x, *, status=ARMED, lag=D):
    """A 1-axis STATE_COMPACT of the 32-bit ``seq`` (its low 16 bits on the wire)."""
    return fp.encode(fp.StateCompact(seq & 0xFFFF, status, lag, (x,)))


def chunked(frames, rng, pause_every=1, most=120):
    """Join ``(seq, bytes)`` frames and cut the stream at random places (1..``most``
    bytes)."""
    data = b"".join(b for _, b in frames)
    owner = []
    for s, b in frames:
        owner += [s] * len(b)
    out, i = [], 0
    while i < len(data):
        n = int(rng.integers(1, most + 1))
        out.append((set(owner[i:i + n]), data[i:i + n]))
        i += n
    return out


def faulty_segment(rng, seq0, n, *, reset_at=None, compact=False):
    """STATEs seq0.. with positions of a wall push, and faults sprinkled in (``compact``:
    STATE_COMPACTs, without the implausible jump, which a 16-bit seq cannot carry)."""
    def st(seq, x, *, status=ARMED, fseq=None):
        if not compact:
            return state(seq, x, status=status, fseq=fseq)
        return cstate(seq, x, status=status, lag=D if fseq is None else seq - fseq)

    frames = [(-1, fp.encode(fp.Hello(fp.PROTOCOL_VERSION, 1, 7, 1e-6, 1e-3, 10.0, 1000.0)))]
    frames += [(-1, st(seq0 - 3 + j, 0.0, status=fp.STATUS_CONFIGURED)) for j in range(3)]
    seq = seq0
    usable = 0
    prev = None
    for j in range(n):
        x = 0.004 * math.sin(j / 40.0) + 1e-4 * rng.standard_normal()
        r = rng.random() if j < n - 10 else 1.0     # a clean tail: the run ends in it
        if r < 0.02:
            frames.append((-1, b"\x13\x37\x42" + b"\x00"))                 # bad COBS / CRC
        elif r < 0.04:
            good = bytearray(st(seq + 100, x))
            good[5] ^= 0x40                                                   # bit flip
            frames.append((-1, bytes(good)))
        elif r < 0.05:
            frames.append((-1, st(seq, x)[:9] + b"\x00"))                    # truncated
        elif r < 0.06 and prev is not None:
            frames.append((-1, prev))                                         # duplicate
        elif r < 0.07:
            frames.append((-1, fp.encode(fp.Fault(fp.FAULT_WATCHDOG, j))))    # non-latched
        elif r < 0.08:
            seq += int(rng.integers(1, 4))                                    # gap: missed
        elif r < 0.085:
            frames.append((-1, b"\x01" * 200 + b"\x00"))                      # overlong
        elif r < 0.09 and not compact:
            frames.append((-1, state(seq + 5_000_000, x)))                    # implausible
        fseq = seq - D if rng.random() > 0.03 else seq - D - 1                # late at times
        prev = st(seq, x, fseq=fseq)
        frames.append((seq, prev))
        usable += 1
        seq += 1
        if reset_at is not None and j == reset_at:
            frames.append((-1, fp.encode(fp.Hello(fp.PROTOCOL_VERSION, 1, 7, 1e-6, 1e-3, 10.0,
                                                  1000.0))))
            break
    return frames, usable


def run_loop(cls, segments, n_samples, *, stop=None, stop_at=None, scene=None, compact=False,
             engine=None, telemetry=None, loop_kw=None, **cfg_kw):
    """Run ``cls`` against a scripted device (``compact``: one that offers the compact
    frames, asked for by the host; ``engine``, ``telemetry``: the loop's, else new ones;
    ``loop_kw``: more arguments of ``cls``); (result, telemetry, forces, device)."""
    master, slave = os.openpty()
    tr = SerialTransport(os.ttyname(slave))
    os.close(slave)
    stop = stop or StopFlag()
    dev = ScriptedDevice(master, segments, (stop_at, stop) if stop_at is not None else None,
                         compact=compact)
    dev.start()
    sc = scene or prepare_scene(load_scene(WALL))[0]
    eng = engine if engine is not None else Engine(sc)
    tel = telemetry if telemetry is not None else Telemetry(n_samples + 10)
    kw = dict(rate_hz=sc.rate_hz, n_samples=n_samples, delay=D, force_limit=10.0,
              state_timeout=20.0, hello_timeout=20.0, lost_timeout=20.0, reconnect=True,
              position_bound=0.05, backlog="all",    # chunks arrive at random: answer all
              compact="on" if compact else "off")
    kw.update(cfg_kw)
    cfg = LoopConfig(**kw)
    loop = cls(eng, tr, cfg, tel, stop, **(loop_kw or {}))
    try:
        res = loop.run()
    finally:
        time.sleep(0.05)
        dev.done = True
        dev.join(2.0)
        tr.close()
        os.close(master)
    return res, tel, dev, loop


RESULT_FIELDS = ("samples", "stop_reason", "safety_stop", "late", "missed", "clamped", "skipped",
                 "stale",
                 "bad_axes", "implausible", "unarmed", "hello_mid_run", "device_faults",
                 "lost", "recovered", "energy", "energy_max", "energy_stored",
                 "energy_excess_max", "passivity_samples", "v_max", "f_max", "faults",
                 "bad_frames_seen", "decoder", "state")


def assert_same(a, b):
    (ra, ta, da, la), (rb, tb, db, lb) = a, b
    assert ra.frames == rb.frames
    assert lb.compiled and not getattr(la, "compiled", False)
    # the compiled path answers samples (a fault hands the rest of its read to Python, so
    # its share follows how many frames each read brings, which the load decides: 112 of
    # 746 in a loaded suite, under the fifth once asserted here: it failed so in two loaded
    # full runs, 2026-11-23 and a fresh clone's at six workers on 2026-11-24); the rows'
    # equality below is the claim
    assert lb.compiled_samples > 0
    for f in RESULT_FIELDS:
        if f == "decoder":          # frames read past the last sample depend on timing
            ra.decoder.pop("frames_ok")
            rb.decoder.pop("frames_ok")
        assert getattr(ra, f) == getattr(rb, f), f
    assert da.forces == db.forces
    assert da.stops == db.stops
    ca, cb = ta.columns(), tb.columns()
    for c in ("time", "position", "force", "seq", "late", "flags", "force_seq", "status"):
        np.testing.assert_array_equal(ca[c], cb[c], err_msg=c)
    assert [e["event"] for e in ra.events] == [e["event"] for e in rb.events]
    # which bad frames the decoder's history still held when they were noted depends on
    # how much one read brought (timing): the records' number is what both must share
    assert len(ra.bad_frames) == len(rb.bad_frames)


def both(segments, n, **kw):
    return (run_loop(HostLoop, segments, n, **kw), run_loop(CompiledHostLoop, segments, n, **kw))


@pytest.mark.parametrize("seed", [1, 2])
def test_compiled_equals_python_on_a_faulty_stream_with_a_reset(seed):
    """Bad frames of every kind, stale/implausible/unarmed STATEs, gaps, FAULTs, late ticks
    and a device reset (HELLO after arming: lost, recovered, scene restarted with the force
    ramp): identical forces, telemetry, counters, events and flags."""
    rng = np.random.default_rng(seed)
    s1, u1 = faulty_segment(rng, 100, 400, reset_at=250)
    s2, u2 = faulty_segment(rng, 5000, 500)
    n = u1 + u2 - 5
    a, b = both([chunked(s1, rng), chunked(s2, rng)], n, passivity_controller=True,
                energy_limit=1.0, late_growth=late_growth(load_scene(WALL), 0.05))
    assert_same(a, b)
    res = b[0]
    assert res.lost == 1 and res.recovered == 1 and res.samples == n
    assert res.stale and res.missed and res.implausible and res.unarmed and res.late
    assert res.bad_frames_seen and res.device_faults.get("WATCHDOG")
    flags = b[1].columns()["flags"]
    assert np.any(flags & 2) and np.any(flags & 4)          # FLAG_LOST, FLAG_RAMP


@pytest.mark.parametrize("kind", ["non-finite", "position", "clamp", "late", "open"])
def test_compiled_equals_python_on_safety_stops(kind):
    """Each safety stop ends both loops on the same sample with the same reason ("late":
    from tick 150 on the device names each FORCE for 12 ticks, the holds of a host 11
    periods away after each answer, and the lateness guard stops the shipped wall;
    "open": from tick 150 on it names FORCE 150 - d for ever, a hold that never ends, and
    the guard stops the wall inside it; the device then takes none of the host's FORCEs,
    so the host sends no braking, only the zero FORCE and STOP)."""
    rng = np.random.default_rng(3)
    frames = []
    for j in range(300):
        x = 0.003 * math.sin(j / 30.0)
        if j == 200:
            x = {"non-finite": math.nan, "position": 0.2}.get(kind, x)
        if kind == "clamp" and j > 150:
            x = -0.02                                     # the wall pushes at the limit
        held = j - D - (j - D) % 12 if kind == "late" and j > 150 else None
        if kind == "open" and j > 150:
            held = 150 - D
        frames.append((j, state(j, x, fseq=held)))
    a, b = both([chunked(frames, rng)], 290, late_growth=late_growth(load_scene(WALL), 0.05),
                brake_damping=25.0 if kind == "open" else 0.0)
    assert_same(a, b)
    assert b[0].safety_stop and b[0].samples < 290
    assert ("too late for the scene's loop" in b[0].stop_reason) == (kind in ("late", "open"))
    if kind == "open":
        for res, tel, dev, _ in (a, b):
            assert res.brake["ended"] == "ignored" and res.brake["periods"] == 0
            # one FORCE a row, then the zero FORCE, then STOP
            assert len(dev.forces) == tel.n + 1 and dev.forces[-1][1] == 0.0
            assert dev.stops == 1


def test_force_frames_equal_the_protocol_encoder():
    """The compiled FORCE encoder gives the protocol's frames (random seq and force,
    signed zeros, subnormals, limits)."""
    rng = np.random.default_rng(0)
    vals = list(rng.uniform(-20, 20, 300)) + [0.0, -0.0, 5e-324, -1e308, math.inf, math.nan]
    for v in vals:
        s = int(rng.integers(0, 2**32))
        assert encode_force(s, v) == fp.encode(fp.Force(s, (v,))), (s, v)


def test_a_stop_request_ends_the_compiled_stretch_within_one_sample():
    """The stop flag set just before the device writes STATE S: no STATE from S on is
    answered; the last FORCE is the zero one, then STOP."""
    rng = np.random.default_rng(4)
    frames = [(j, state(j, 0.001 * math.sin(j / 20.0))) for j in range(3000)]
    S = 1500
    res, tel, dev, loop = run_loop(CompiledHostLoop, [chunked(frames, rng)], 2900, stop_at=S)
    assert loop.compiled
    answered = [s for s, f in dev.forces[:-1]]
    assert answered and max(answered) < S
    assert dev.forces[-1][1] == 0.0 and dev.stops == 1
    assert res.samples == tel.n < S


def bursts(rng, n_bursts, seq0=0, kmax=5, enc=state):
    """Bursts of 1-``kmax`` STATEs (stalls of the device's stream), each written at once
    after the answer to the previous burst (an int in the script: wait for the FORCE of that
    seq); (script, sizes)."""
    script, sizes, seq = [], [], seq0
    for b in range(n_bursts):
        k = int(rng.integers(1, kmax + 1)) if b else 1     # the scene resumes on a lone STATE
        frames = b"".join(enc(seq + q, 0.002 * math.sin((seq + q) / 25.0)) for q in range(k))
        script += [(set(range(seq, seq + k)), frames), seq + k - 1]
        sizes.append(k)
        seq += k
    return script, sizes


@pytest.mark.parametrize("backlog", ["newest", "all"])
def test_backlog_policy_on_bursts(backlog):
    """A device stream of bursts: with "newest" only the last STATE of each burst is
    answered and the others are counted as skipped (FLAG_SKIPPED on the answered row);
    with "all" every STATE is answered in order. Both loops agree bit for bit."""
    rng = np.random.default_rng(5)
    script, sizes = bursts(rng, 150)
    n = 150 if backlog == "newest" else sum(sizes)
    a, b = both([script], n, backlog=backlog)
    assert_same(a, b)
    res, tel = b[0], b[1]
    cols = tel.columns()
    ends = np.cumsum(sizes) - 1
    # skipped or answered, every device sample is integrated by the scene (the velocity
    # of the next answered sample spans one period)
    assert a[3].engine.sample == b[3].engine.sample == sum(sizes)
    if backlog == "newest":
        assert res.skipped == sum(sizes) - len(sizes)
        np.testing.assert_array_equal(cols["seq"], ends)
        np.testing.assert_array_equal((cols["flags"] & 16) != 0, np.array(sizes) > 1)
    else:
        assert res.skipped == 0
        np.testing.assert_array_equal(cols["seq"], np.arange(sum(sizes)))
        assert not np.any(cols["flags"] & 16)


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_skipped_states_feed_the_scene_not_the_velocity(seed):
    """Random stall lengths (bursts of 1-40 STATEs of a moving hand), backlog "newest": the
    two loops agree bit for bit; every answered STATE gets the force the scene gives when
    every STATE is answered (backlog "all" on the same stream: an independent run), since a
    skipped STATE still steps the scene; and no skip feeds a velocity across the stall (a
    backward difference over k samples would be up to k times the hand's speed): the
    velocity maximum is that of the "all" run, under a velocity limit 25 % above it, and
    no safety stop ends either run."""
    rng = np.random.default_rng(seed)
    script, sizes = bursts(rng, 60, kmax=40)
    ends = np.cumsum(sizes) - 1
    vlim = 1.25 * 0.002 / 25.0 * 1000.0        # the hand's top speed 0.08 m/s, + 25 %
    new = both([script], len(sizes), backlog="newest", velocity_limit=vlim)
    assert_same(*new)
    ref = run_loop(CompiledHostLoop, [script], int(sum(sizes)), backlog="all",
                   velocity_limit=vlim)
    res, tel = new[1][0], new[1][1]
    assert not res.safety_stop and not ref[0].safety_stop
    assert res.samples == len(sizes) and res.skipped == sum(sizes) - len(sizes)
    cols, rcols = tel.columns(), ref[1].columns()
    np.testing.assert_array_equal(cols["seq"], ends)
    ramp = (cols["flags"] & 4) != 0                # the force ramp counts answered rows
    np.testing.assert_array_equal(cols["force"][~ramp], rcols["force"][ends][~ramp])
    assert res.v_max <= ref[0].v_max


# ----------------------------------------------------------------------------- compact


@pytest.mark.parametrize("seed, rate", [(31, 1000), (32, 3000)])
def test_compiled_equals_python_in_a_compact_session_across_the_seq_wrap(seed, rate, tmp_path):
    """A compact session (STATE_COMPACT / FORCE_COMPACT) on a faulty stream whose 16-bit
    seq wraps past 65535 in both segments, with gaps, duplicates (stale), late ticks (lag
    2), bad frames, FAULTs and a device reset (HELLO: lost, COMPACT asked again, the
    expansion restarted at CONFIG): the two loops expand the same 32-bit seqs (past 65535),
    force_seqs and times (rounded to the us at 3 kHz), send the same FORCE_COMPACTs and log
    the same telemetry."""
    scene = tmp_path / "wall.yaml"
    with open(WALL) as fh:
        scene.write_text(fh.read().replace("rate_hz: 1000", f"rate_hz: {rate}"))
    rng = np.random.default_rng(seed)
    s1, u1 = faulty_segment(rng, 65_300, 400, reset_at=250, compact=True)
    s2, u2 = faulty_segment(rng, 65_200, 500, compact=True)
    n = u1 + u2 - 5
    # chunks of as many frames as the full-frame test's (13-byte frames, not 31): the device
    # writes no faster in STATEs, so the compiled stretch answers as large a part
    a, b = both([chunked(s1, rng, most=50), chunked(s2, rng, most=50)], n, compact=True,
                passivity_controller=True, energy_limit=1.0,
                scene=prepare_scene(load_scene(str(scene)))[0])
    assert_same(a, b)
    res, tel = b[0], b[1]
    assert res.frames == "compact" and res.lost == 1 and res.recovered == 1
    assert res.samples == n and res.late and res.stale and res.missed
    cols = tel.columns()
    seq, fseq = cols["seq"], cols["force_seq"]
    assert seq.max() > 65_535                        # expanded past the 16-bit wrap
    # the expansion: each row's 32-bit seq has the wire's low 16 bits, the device time
    # is the tick's since CONFIG, force_seq = seq - lag (lag 1, or 2 on a late tick)
    applied = (cols["status"] & fp.STATUS_FORCE_APPLIED) != 0
    np.testing.assert_array_equal(cols["time"],
                                  [round(int(s) * 1e6 / rate) * 1e-6 for s in seq])
    assert set((seq - fseq)[applied]) == {D, D + 1}
    np.testing.assert_array_equal(cols["late"][applied] != 0, (seq - fseq)[applied] > D)
    # each row's FORCE_COMPACT, in order among those sent (the others: the zero forces of
    # the loss and the stop), carries the row's seq's low 16 bits and its force in binary32
    f32 = cols["force"].astype(np.float32).astype(np.float64)
    sent = iter(b[2].forces)
    for s, f in zip(seq, f32):
        assert (int(s) & 0xFFFF, f) in sent


@pytest.mark.parametrize("backlog", ["newest", "all"])
def test_backlog_policy_in_a_compact_session(backlog):
    """Bursts of STATE_COMPACTs across the 16-bit wrap: "newest" skips the same STATEs in
    both loops (a newer STATE_COMPACT waiting is found by expanding it), "all" answers each
    in order; bit for bit the same."""
    rng = np.random.default_rng(6)
    script, sizes = bursts(rng, 120, seq0=65_300, enc=cstate)
    n = 120 if backlog == "newest" else sum(sizes)
    a, b = both([script], n, backlog=backlog, compact=True)
    assert_same(a, b)
    ends = 65_300 + np.cumsum(sizes) - 1
    cols = b[1].columns()
    # the expansion's reference the compiled stretch moved is handed back to the decoder
    # (a frame Python expands later is expanded after the last STATE taken, not before)
    for run in (a, b):
        assert run[3].transport.decoder.expander.last == ends[-1]
    if backlog == "newest":
        assert b[0].skipped == sum(sizes) - len(sizes)
        np.testing.assert_array_equal(cols["seq"], ends)
    else:
        np.testing.assert_array_equal(cols["seq"], 65_300 + np.arange(sum(sizes)))


def test_compact_force_frames_equal_the_protocol_encoder():
    """The compiled FORCE_COMPACT encoder gives fp.encode(fp.compact_force(...)): 16-bit
    seq, binary32 rounding (ties to even), saturation of finite forces beyond binary32,
    signed zeros, subnormals, non-finite forces."""
    rng = np.random.default_rng(7)
    f32 = float(np.float32(1.5))
    vals = list(rng.uniform(-20, 20, 300)) + [0.0, -0.0, 5e-324, 1e-40, -1e308, 3.5e38,
                                              -3.4028235e38, math.inf, -math.inf, math.nan,
                                              f32 + 2.0 ** -24, 1.0 + 2.0 ** -24]
    for v in vals:
        s = int(rng.integers(0, 2**32))
        assert encode_force(s, v, compact=True) == fp.encode(fp.compact_force(
            fp.Force(s, (v,)))), (s, v)
