"""The compact frames STATE_COMPACT / FORCE_COMPACT (PROTOCOL.md §4 "Compact frames").

The codec, the C reference and the golden vectors are checked against each other in
``test_protocol.py`` and ``test_protocol_c.py`` (the vectors include the compact messages);
here: the spec's hand-written frames and byte budget, the host's restoration of the STATE a
compact frame stands for over random sessions, the binary32 rounding of a FORCE, and the
negotiation at the handshake with devices that offer the frames, know SENSORS_REQUEST but
not the frames, or were written before SENSORS_REQUEST. The firmware at 4 kHz over them
is in ``test_firmware.py``.
"""

from __future__ import annotations

import math
import os
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import firmware_protocol as fp
from pty_device import PtyDevice
from tolerance import rel_tol

SPEC = (Path(fp.__file__).resolve().parent / "PROTOCOL.md").read_text()
U32 = 0xFFFFFFFF


def _spec_frame(name: str) -> bytes:
    """The ``frame:`` line under the spec's byte-level example of ``name``."""
    at = SPEC.index(f"**{name}(")
    m = re.search(r"frame:\s+([0-9A-F ]+?)\s+\(", SPEC[at:])
    return bytes.fromhex(m.group(1))


def test_byte_examples_and_budget_of_the_spec():
    """The spec's two hand-written compact frames are the codec's, 13 and 11 bytes; the byte
    budget it derives: 50 bytes per 4 kHz tick each way at 2 Mbaud 8N1; a round trip of
    48 byte times (240 us) in full frames, 24 (120 us) compact; the LINK rule carries 12,307
    Hz with the compact STATE; a host asks for them at 4 kHz, not at 1 kHz, nor on a line
    that is not a UART."""
    state = fp.encode(fp.StateCompact(1, 0x41, 0, (0.01,)))
    force = fp.encode(fp.ForceCompact(1, (0.5,)))
    assert _spec_frame("STATE_COMPACT") == state and len(state) == 13
    assert _spec_frame("FORCE_COMPACT") == force and len(force) == 11
    assert fp.state_compact_frame_bytes(1) == 13 and fp.force_compact_frame_bytes(1) == 11
    assert 2_000_000 / (10 * 4000) == 50
    # bytes x bits is an exact integer, then one division; the decimal literal rounds once:
    # derived rel_tol(2)
    assert fp.link_round_trip(2_000_000, 10, 1) == pytest.approx(240e-6, rel=rel_tol(2))
    assert fp.link_round_trip(2_000_000, 10, 1, compact=True) == pytest.approx(
        120e-6, rel=rel_tol(2))
    assert int(fp.link_max_rate(2_000_000, 10, 1, compact=True)) == 12307
    assert fp.wants_compact(2_000_000, 10, 1, 4000.0)
    assert not fp.wants_compact(2_000_000, 10, 1, 1000.0)
    assert not fp.wants_compact(0, 10, 1, 4000.0)


def _f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


@st.composite
def sessions(draw):
    """A device's STATEs over sessions: ticks from 0 after each CONFIG, armed ones at gaps up
    to 30,000 ticks (past the 16-bit wrap), disarmed ones between, lags 0..255 (255: the
    saturated "255 or more")."""
    # (seq, status, lag, binary32 position) per STATE, one list per session
    out = []
    for _ in range(draw(st.integers(1, 3))):
        seq, states, last_armed = 0, [], 0
        for _ in range(draw(st.integers(1, 12))):
            seq += draw(st.sampled_from([1, 1, 1, 2, 7, 255, 4096, 30000]))
            # the host sees an armed STATE at least every 2^15 ticks (PROTOCOL.md §4)
            armed = draw(st.booleans()) or not states or seq - last_armed > 32768
            last_armed = seq if armed else last_armed
            applied = draw(st.booleans())
            lag = draw(st.sampled_from([0, 1, 254, 255]) | st.integers(0, 255)) if applied else 0
            status = draw(st.integers(0, 0xFF)) & ~(fp.STATUS_ARMED | fp.STATUS_FORCE_APPLIED)
            status |= (fp.STATUS_ARMED if armed else 0) | (
                fp.STATUS_FORCE_APPLIED if applied else 0)
            x = draw(st.floats(allow_nan=False, width=32))
            states.append((seq & U32, status, lag, x))
        out.append(states)
    return out


@settings(max_examples=30, deadline=None)
@given(sessions(), st.sampled_from([1000.0, 4000.0, 3000.0]))
def test_the_host_restores_every_state_a_compact_frame_stands_for(sess, rate):
    """Property over random sessions (PROTOCOL.md §4): through the wire and a decoder with
    the expander restarted at each CONFIG, each STATE_COMPACT comes out as the STATE the
    device would have sent: seq past the 16-bit wrap, force_seq = seq - lag with
    FORCE_APPLIED and lag < 255 (a saturated lag names no FORCE: -1; else 0), time_us = round(seq * 1e6 / rate), the binary32 position
    exactly. Disarmed STATEs (before the first armed one of a session) do not move the
    reference, whatever their seq."""
    dec = fp.StreamDecoder()
    dec.expander = fp.CompactExpander(rate)
    for states in sess:
        dec.expander.restart(rate)                      # the host sends CONFIG
        # a disarmed STATE of the previous session, in flight: expanded, not a reference
        stray = fp.encode(fp.StateCompact(0xBEEF, 0x40, 0, (1.0,)))
        assert not dec.feed(stray)[0].status & fp.STATUS_ARMED
        for seq, status, lag, x in states:
            got = dec.feed(fp.encode(fp.StateCompact(seq & 0xFFFF, status, lag, (x,))))
            if not status & fp.STATUS_ARMED:
                continue    # restored against the last armed one (a different question)
            fseq = 0 if not status & fp.STATUS_FORCE_APPLIED else \
                -1 if lag == fp.COMPACT_LAG_MAX else (seq - lag) & U32
            want = fp.State(seq, int(round(seq * 1e6 / rate)), status, fseq, (x,))
            assert got == [want]
    assert dec.stats.bad_frames == 0


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 0xFFFF), st.integers(0, 300), st.integers(1, 300))
def test_a_saturated_lag_names_no_force_and_the_tick_is_late(seq16, gap, d):
    """A compact STATE's lag 255 means "255 ticks or more": the FORCE applied is not
    known, so the STATE names none (``force_seq`` -1, as a protocol without the field),
    and the late-tick rule (hapsim.kernels.ticks, read by both host loops and the
    account) calls the (due) tick late at every delay, 255 included, where ``seq - 255``
    would have named a FORCE and an on-time tick."""
    from hapsim.kernels.ticks import late_ticks, named_delay, tick_late
    ex = fp.CompactExpander(1000.0)
    armed = fp.STATUS_ARMED | fp.STATUS_FORCE_APPLIED
    ex.expand(fp.StateCompact(seq16, armed, 1, (0.0,)))        # the session's reference
    s = ex.expand(fp.StateCompact((seq16 + 300 + gap) & 0xFFFF, armed, fp.COMPACT_LAG_MAX,
                                  (0.0,)))
    assert s.force_seq == -1
    assert named_delay(s.seq, s.force_seq, s.status, True) == -1
    assert tick_late(s.seq, s.force_seq, s.status, d, True)
    assert tick_late(s.seq, s.force_seq, s.status, 255, True)
    tick, late = np.empty(1, np.int64), np.zeros(1, bool)
    late_ticks(np.array([s.seq]), np.array([s.force_seq]), np.array([s.status]), 255, True,
               tick, late, np.zeros(1, bool))
    assert tick[0] == -1 and late[0]
    # one below saturation is still exact
    t = ex.expand(fp.StateCompact((seq16 + 301 + gap) & 0xFFFF, armed, 254, (0.0,)))
    assert t.force_seq == (t.seq - 254) & U32
    assert named_delay(t.seq, t.force_seq, t.status, True) == 254


@settings(max_examples=100, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True), st.integers(0, U32))
def test_compact_force_is_the_binary32_a_float32_device_rounds_a_full_force_to(x, seq):
    """FORCE_COMPACT carries what a float32 device makes of the full FORCE (numpy's
    float64 -> float32, IEEE round to nearest even), except that a finite force beyond the
    binary32 range saturates to +-F32_MAX instead of becoming infinite: it stays a force
    the device clamps, not a non-finite one it faults on. seq: the low 16 bits."""
    m = fp.compact_force(fp.Force(seq, (x,)))
    assert m.seq == seq & 0xFFFF
    y = m.force[0]
    with np.errstate(over="ignore"):
        ref = float(np.float32(x))
    if math.isnan(x):
        assert math.isnan(y)
    elif math.isinf(x) or abs(x) <= fp.F32_MAX:
        assert y == ref and math.copysign(1, y) == math.copysign(1, ref)
    else:
        assert y == math.copysign(fp.F32_MAX, x) and math.isfinite(y)
    assert fp.decode_frame(fp.encode(m)).force[0] == y or math.isnan(y)


# ----------------------------------------------------------------------------- negotiation

class _Device(PtyDevice):
    """A 1-axis device on a pty with a 2 Mbaud UART (LINK before HELLO): ``kind`` "compact"
    offers the compact frames (and then sends STATE_COMPACT), "sensors" answers
    SENSORS_REQUEST without them (a device of before the frames), "old" does not answer it
    (a device of before SENSORS_REQUEST). Records what it receives."""

    def __init__(self, master: int, kind: str, force_scale: float = 0.0) -> None:
        super().__init__(master, fp.encode(fp.Link(2_000_000, 10)) + fp.encode(
            fp.Hello(1, 1, 7, 1e-6, force_scale, 10.0, 1000.0)))
        self.kind = kind
        self.requests: list = []
        self.received: list = []

    def on_message(self, msg) -> None:
        self.received.append(msg)
        if type(msg) is fp.SensorsRequest:
            self.requests.append(msg.sensors)
            if self.kind == "compact":
                on = msg.sensors & fp.FEATURE_COMPACT
                os.write(self.master, fp.encode(fp.Sensors(fp.FEATURE_COMPACT, on)))
                if on:   # from its next tick: a disarmed compact STATE
                    os.write(self.master, fp.encode(fp.StateCompact(77, 0x40, 0, (0.25,))))
            elif self.kind == "sensors":
                os.write(self.master, fp.encode(fp.Sensors(0, 0)))


def _handshake(kind: str, rate: float, compact: str = "auto", force_scale: float = 0.0):
    """HELLO (``force_scale``: 0, a continuous actuator), its check and SENSORS with a
    :class:`_Device`; then one CONFIG, a compact STATE from the device and a FORCE from the
    host. (loop, device, messages received)."""
    from hapsim.host.loop import HostLoop, LoopConfig
    from hapsim.host.transport import SerialTransport
    master, slave = os.openpty()
    dev = _Device(master, kind, force_scale)
    dev.start()
    tr = SerialTransport(os.ttyname(slave))
    try:
        loop = HostLoop(None, tr, LoopConfig(rate_hz=rate, n_samples=10, watchdog_us=5000,
                                             compact=compact), None)
        hello = loop._ask_hello(2.0)
        loop._check_hello(hello)
        loop._ask_sensors()
        got = []
        if tr.compact:
            loop._send_config()
            os.write(master, fp.encode(fp.StateCompact(0, 0xC1, 0, (0.125,))))
            for _ in range(50):
                got += [m for m in tr.receive(0.02) if type(m) is fp.State]
                if any(m.status & fp.STATUS_ARMED for m in got):
                    break
        tr.send(fp.Force(65537, (1e39,)))
        for _ in range(50):
            if any(type(m) in (fp.Force, fp.ForceCompact) for m in dev.received):
                break
            tr.receive(0.02)
        return loop, dev, got
    finally:
        dev.done = True
        dev.join(2.0)
        tr.close()
        os.close(slave)
        os.close(master)


def test_negotiation_with_a_device_that_offers_the_compact_frames():
    """New host, new device, 4 kHz on 2 Mbaud: the host asks (the full round trip is 96 % of
    the period), the device enables them; its STATE_COMPACT comes out as the STATE (seq 0
    after CONFIG, FORCE_APPLIED with lag 0: force_seq 0); the host's FORCE goes out as
    FORCE_COMPACT (seq's low 16 bits, a finite force beyond binary32 saturated)."""
    loop, dev, got = _handshake("compact", 4000.0)
    assert dev.requests == [fp.FEATURE_COMPACT] and loop.result.frames == "compact"
    armed = [m for m in got if m.status & fp.STATUS_ARMED]
    assert armed == [fp.State(0, 0, 0xC1, 0, (0.125,))]
    forces = [m for m in dev.received if type(m) in (fp.Force, fp.ForceCompact)]
    assert forces == [fp.ForceCompact(1, (fp.F32_MAX,))]


@pytest.mark.parametrize("kind,requests", [("sensors", 1), ("old", 3)])
def test_negotiation_with_devices_that_do_not_offer_them_keeps_the_full_frames(kind,
                                                                               requests):
    """New host, old device: one that answers SENSORS without COMPACT, or one that does not
    answer at all (3 requests, 0.1 s apart): the session keeps STATE / FORCE (a full FORCE
    goes out, the f64 value untouched)."""
    loop, dev, _ = _handshake(kind, 4000.0)
    assert dev.requests == [fp.FEATURE_COMPACT] * requests
    assert loop.result.frames == "full"
    forces = [m for m in dev.received if type(m) in (fp.Force, fp.ForceCompact)]
    assert forces == [fp.Force(65537, (1e39,))]


@pytest.mark.parametrize("rate,compact,force_scale", [(1000.0, "auto", 0.0),
                                                      (4000.0, "off", 0.0),
                                                      (1000.0, "off", 1e-3)])
def test_the_host_does_not_ask_when_it_needs_no_compact_frames(rate, compact, force_scale):
    """At 1 kHz on 2 Mbaud (the full round trip is 24 % of the period) to a continuous
    actuator (HELLO.force_scale 0), or with ``compact="off"``, the host sends no
    SENSORS_REQUEST to a device that offers them: the device never sends a compact frame
    (nothing unasked for)."""
    loop, dev, _ = _handshake("compact", rate, compact, force_scale)
    assert dev.requests == [] and loop.result.frames == "full"


@pytest.mark.parametrize("force_scale", [1e-3, 0.0227])
def test_the_host_asks_at_1khz_a_uart_device_that_steps_its_force_in_binary32(force_scale):
    """At 1 kHz on 2 Mbaud a device whose HELLO.force_scale > 0 applies each FORCE as the
    firmware's binary32 step (PROTOCOL.md §4, HELLO): the compact FORCE loses nothing, and
    its chip saves the binary64 codec's time, so the host asks (``auto``) and the session
    runs compact."""
    loop, dev, _ = _handshake("compact", 1000.0, "auto", force_scale)
    assert dev.requests == [fp.FEATURE_COMPACT] and loop.result.frames == "compact"


def test_a_rate_only_the_compact_frames_carry_is_refused_when_the_device_has_none():
    """8 kHz on 2 Mbaud: more than the full frames' LINK rule (5161 Hz), less than the
    compact frames' (12307 Hz). With a device that offers them the host arms; with one that
    does not, the refusal names the rate, the baud and both limits."""
    from hapsim.errors import ConfigError
    loop, _, _ = _handshake("compact", 8000.0)
    assert loop.result.frames == "compact"
    with pytest.raises(ConfigError) as info:
        _handshake("sensors", 8000.0)
    msg = str(info.value)
    assert "8000 Hz" in msg and "2000000 baud" in msg and "5161 Hz" in msg
    assert "12308 Hz" in msg or "12307 Hz" in msg
