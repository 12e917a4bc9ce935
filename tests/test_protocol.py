"""Tests of the Python codec of the hapsim serial protocol (``firmware_protocol``).

Golden vectors (``firmware_protocol/vectors/vectors.json``, checked here against an
independent oracle), Hypothesis round trips for every message, and table-driven hostile
byte streams (split input, garbage, bit flips, truncation, zero runs, length limits).
"""

from __future__ import annotations

import ast
import dataclasses
import json
import math
import random
import struct
import subprocess
import sys
from pathlib import Path

from from_file import load_module  # same directory
import pytest
from hypothesis import given, settings, strategies as st

import firmware_protocol as fp
from tolerance import rel_tol

PKG = Path(fp.__file__).resolve().parent
VECTORS = json.loads((PKG / "vectors" / "vectors.json").read_text())
CLASSES = {"HELLO": fp.Hello, "HELLO_REQUEST": fp.HelloRequest, "CONFIG": fp.Config, "LINK": fp.Link,
           "SENSORS_REQUEST": fp.SensorsRequest, "SENSORS": fp.Sensors, "STATE": fp.State,
           "FORCE": fp.Force, "VELOCITY": fp.Velocity, "PING": fp.Ping, "PONG": fp.Pong,
           "FAULT": fp.Fault, "STOP": fp.Stop, "STATE_COMPACT": fp.StateCompact,
           "FORCE_COMPACT": fp.ForceCompact}


ORACLE = load_module(PKG / "vectors" / "check_vectors.py")


def message_of(vector: dict):
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in vector["fields"].items()}
    return CLASSES[vector["type"]](**fields)


GOOD = [(v["name"], message_of(v), bytes.fromhex(v["frame_hex"])) for v in VECTORS["good"]]
GOOD_IDS = [g[0] for g in GOOD]
BAD = [(b["name"], bytes.fromhex(b["frame_hex"]), b["error"]) for b in VECTORS["bad"]]


def feed_all(data: bytes, chunks=None, dec=None):
    """Feed ``data`` in the given chunk sizes (default: one chunk); return (messages, dec)."""
    dec = dec or fp.StreamDecoder()
    out = []
    if chunks is None:
        out += dec.feed(data)
    else:
        i = 0
        for n in chunks:
            out += dec.feed(data[i:i + n])
            i += n
        out += dec.feed(data[i:])
    assert dec.buffered <= fp.MAX_FRAME - 1
    return out, dec


# --------------------------------------------------------------------------- package


def test_package_is_standalone_and_io_free():
    """No import of hapsim, serial, os/io/socket in the codec sources."""
    forbidden = {"hapsim", "serial", "os", "io", "socket", "pathlib", "logging"}
    for path in (PKG / "__init__.py", PKG / "codec.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""] if node.level == 0 else []
            else:
                continue
            for name in names:
                assert name.split(".")[0] not in forbidden, (path.name, name)
    code = ("import sys, firmware_protocol; "
            "assert not [m for m in sys.modules if m.split('.')[0] == 'hapsim']")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=PKG.parent)


def test_constants():
    assert fp.PROTOCOL_VERSION == VECTORS["protocol_version"] == 1
    assert fp.MAX_FRAME == VECTORS["max_frame"] == 128
    assert fp.MAX_PACKET == fp.MAX_FRAME - 2
    ids = [fp.MSG_HELLO, fp.MSG_HELLO_REQUEST, fp.MSG_CONFIG, fp.MSG_LINK,
           fp.MSG_SENSORS_REQUEST, fp.MSG_SENSORS, fp.MSG_STATE, fp.MSG_FORCE, fp.MSG_VELOCITY,
           fp.MSG_PING, fp.MSG_PONG, fp.MSG_FAULT, fp.MSG_STOP, fp.MSG_STATE_COMPACT,
           fp.MSG_FORCE_COMPACT]
    assert len(set(ids)) == len(ids) and 0 not in ids
    assert sorted(fp.MESSAGE_TYPES) == sorted(ids)
    bits = [fp.STATUS_ARMED, fp.STATUS_WATCHDOG_TRIPPED, fp.STATUS_FORCE_CLAMPED,
            fp.STATUS_FAULT, fp.STATUS_RX_ERROR, fp.STATUS_OVERRUN, fp.STATUS_CONFIGURED,
            fp.STATUS_FORCE_APPLIED]
    assert all(b and b & (b - 1) == 0 for b in bits) and len(set(bits)) == len(bits)
    assert len(fp.FAULT_NAMES) == 9
    assert issubclass(fp.FrameError, ValueError)


def test_status_bits_agree_in_spec_python_and_c():
    """The status table of PROTOCOL.md §4, the codec's STATUS_* and the C header's
    HP_STATUS_* list the same bits with the same values (FORCE_APPLIED included)."""
    import re
    spec = {name: int(value, 16) for value, name in re.findall(
        r"^\| (0x[0-9A-Fa-f]{4}) \| ([A-Z_]+)\s*\|", _status_table(), re.M)}
    header = (PKG / "c" / "hproto.h").read_text()
    c = {name: int(value, 16)
         for name, value in re.findall(r"#define HP_STATUS_([A-Z_]+) (0x[0-9A-Fa-f]+)u", header)}
    py = {name[len("STATUS_"):]: getattr(fp, name) for name in fp.__all__
          if name.startswith("STATUS_")}
    assert spec == c == py, (spec, c, py)
    assert spec["FORCE_APPLIED"] == 0x0080 and len(spec) == 8


def _status_table() -> str:
    text = (PKG / "PROTOCOL.md").read_text()
    start = text.index("### Status bits (STATE.status)")
    return text[start:text.index("###", start + 3)]


def test_force_applied_tells_force_seq_0_from_none_yet():
    """PROTOCOL.md §4/§10: after CONFIG the mock's STATE seq starts at 0, so the FORCE
    answering STATE 0 has seq 0 as well; FORCE_APPLIED tells the two force_seq = 0 apart."""
    from hapsim.emulated.mock import MockDevice
    from hapsim.scene import Device, Excitation

    applied = fp.STATUS_FORCE_APPLIED

    def mock(d, lockstep):
        return MockDevice(Device(mass=0.1, friction=0.5, delay=d, force_limit=10.0),
                          Excitation(x0=0.001), lockstep=lockstep)

    # lockstep, d = 1: STATE 0 (nothing applied), FORCE 0 -> STATE 1 reports FORCE 0 applied
    m = mock(1, True)
    (s0,) = m.handle(fp.Config(1000.0, 5000, 10.0), 0)
    assert (s0.seq, s0.force_seq) == (0, 0) and not s0.status & applied
    (s1,) = m.handle(fp.Force(0, (1.0,)), 0)
    assert (s1.seq, s1.force_seq) == (1, 0) and s1.status & applied
    assert m.stats.last_applied == 1.0
    # lockstep, d = 0: STATE n reports the FORCE applied over the previous period
    m = mock(0, True)
    (s0,) = m.handle(fp.Config(1000.0, 5000, 10.0), 0)
    assert s0.force_seq == 0 and not s0.status & applied
    (s1,) = m.handle(fp.Force(0, (1.0,)), 0)
    assert (s1.seq, s1.force_seq) == (1, 0) and s1.status & applied
    # ... and a new CONFIG restarts force_seq and clears the bit with it
    (r0,) = m.handle(fp.Config(1000.0, 5000, 10.0), 0)
    assert (r0.seq, r0.force_seq) == (0, 0) and not r0.status & applied
    # real time, d = 1: the bit stays while a late tick holds the force, until CONFIG
    m = mock(1, False)
    m.handle(fp.Config(1000.0, 5000, 10.0), 0)
    t0 = m.tick(0)
    assert t0.seq == 0 and not t0.status & applied
    m.handle(fp.Force(0, (2.0,)), 500)
    t1 = m.tick(1000)                            # FORCE 0 applied from tick 1
    assert t1.force_seq == 0 and t1.status & applied
    t2 = m.tick(2000)                            # FORCE 1 missing: FORCE 0 held
    assert t2.status & fp.STATUS_OVERRUN and t2.force_seq == 0 and t2.status & applied
    m.handle(fp.Config(1000.0, 5000, 10.0), 3000)
    t0 = m.tick(3000)
    assert t0.seq == 0 and t0.force_seq == 0 and not t0.status & applied
    t1 = m.tick(4000)                            # no FORCE since CONFIG: late, none applied
    assert t1.status & fp.STATUS_OVERRUN and not t1.status & applied


def test_crc_check_value():
    assert fp.crc16(b"123456789") == 0x29B1
    assert ORACLE.crc16_ccitt_false(b"123456789") == 0x29B1


# --------------------------------------------------------------------------- vectors


def test_vectors_match_independent_oracle():
    """The golden file agrees with the oracle built from PROTOCOL.md alone."""
    assert ORACLE.check(VECTORS) == []
    types = {v["type"] for v in VECTORS["good"]}
    assert types == set(CLASSES)


@pytest.mark.parametrize("name,msg,frame", GOOD, ids=GOOD_IDS)
def test_golden_encode_decode(name, msg, frame):
    vec = next(v for v in VECTORS["good"] if v["name"] == name)
    assert fp.encode_packet(msg).hex() == vec["packet_hex"]
    assert fp.encode(msg) == frame
    assert fp.decode_frame(frame) == msg
    assert fp.decode_frame(frame[:-1]) == msg  # delimiter optional for decode_frame
    assert len(frame) <= fp.MAX_FRAME and frame.count(0) == 1 and frame[-1] == 0


@pytest.mark.parametrize("name,frame,reason", BAD, ids=[b[0] for b in BAD])
def test_bad_vectors_rejected_and_counted(name, frame, reason):
    with pytest.raises(fp.FrameError) as info:
        fp.decode_frame(frame)
    assert info.value.reason == reason
    msgs, dec = feed_all(frame + GOOD[0][2])
    assert msgs == [GOOD[0][1]]  # the next good frame is still decoded
    assert getattr(dec.stats, reason) == 1 and dec.stats.bad_frames == 1
    assert dec.stats.frames_ok == 1


def test_byte_level_examples_of_protocol_md():
    """The two examples worked by hand in PROTOCOL.md §7."""
    assert fp.encode(fp.Stop()).hex() == "0431c78200"
    assert fp.encode(fp.Force(seq=1, force=(0.5,))).hex() == \
        "031101" "0101010101010101" "05e03fafa0" "00"
    text = (PKG / "PROTOCOL.md").read_text()
    assert "04 31 C7 82 00" in text
    assert "03 11 01 01 01 01 01 01 01 01 01 05 E0 3F AF A0 00" in text
    # the velocity sensor on the wire (SENSORS_REQUEST, VELOCITY: added within version 1)
    for msg, shown in ((fp.SensorsRequest(fp.SENSOR_VELOCITY), "03 05 01 03 14 5D 00"),
                       (fp.Velocity(1, (-0.125,)),
                        "03 12 01 01 01 01 01 01 01 01 01 05 C0 BF F7 6B 00")):
        assert fp.encode(msg).hex(" ").upper() == shown and shown in text


def test_velocity_on_the_wire_stays_within_version_1():
    """PROTOCOL.md §9: the velocity sensor adds message types only. STATE, FORCE and HELLO
    keep their layouts (an old receiver decodes every frame it was written for), and each
    new type is one an old decoder counts as unknown_type and drops without acting."""
    old_types = {0x01, 0x02, 0x03, 0x04, 0x10, 0x11, 0x20, 0x21, 0x30, 0x31}
    new = {fp.MSG_SENSORS_REQUEST, fp.MSG_SENSORS, fp.MSG_VELOCITY}
    later = {fp.MSG_STATE_COMPACT, fp.MSG_FORCE_COMPACT}   # the compact frames, after
    assert not new & old_types and set(fp.MESSAGE_TYPES) == old_types | new | later
    assert fp.PROTOCOL_VERSION == 1
    assert len(fp.encode(fp.State(0, 0, 0, 0, (0.0,)))) == fp.state_frame_bytes(1) == 31
    assert len(fp.encode(fp.Velocity(0, (0.0,) * 3))) == fp.velocity_frame_bytes(3) == 33
    # an old decoder: the same codec without the three new types
    old = fp.StreamDecoder()
    saved = {t: fp.codec._UNPACKERS.pop(t) for t in new}
    try:
        stream = b"".join(fp.encode(m) for m in (
            fp.Sensors(1, 1), fp.Velocity(5, (0.25,)), fp.State(5, 0, 0x41, 4, (0.01,))))
        assert old.feed(stream) == [fp.State(5, 0, 0x41, 4, (0.01,))]
    finally:
        fp.codec._UNPACKERS.update(saved)
    assert old.stats.unknown_type == 2 and old.stats.frames_ok == 1
    # the LINK rule counts the VELOCITY frame going up with each STATE
    # load x baud / (bits x bytes): two roundings each side (the bytes' product is an exact
    # integer), cond 1: derived rel_tol(4)
    assert fp.link_max_rate(115200, velocity=True) == pytest.approx(0.8 * 115200 / 480,
                                                                    rel=rel_tol(4))


# --------------------------------------------------------------------------- round trips

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
u64 = st.integers(0, 2**64 - 1)
f64 = st.floats(allow_nan=False)  # NaN != NaN; NaN bits are tested separately
axes = st.lists(f64, min_size=1, max_size=fp.MAX_AXES).map(tuple)
f32 = st.floats(allow_nan=False, width=32)
axes32 = st.lists(f32, min_size=1, max_size=fp.MAX_AXES).map(tuple)

MESSAGES = st.one_of(
    st.builds(fp.Hello, u8, st.integers(1, fp.MAX_AXES), u32, f64, f64, f64, f64),
    st.builds(fp.HelloRequest, u8),
    st.builds(fp.Config, f64, u32, f64),
    st.builds(fp.State, u32, u64, u16, u32, axes),
    st.builds(fp.Force, u32, axes),
    st.builds(fp.Velocity, u32, axes),
    st.builds(fp.SensorsRequest, u16),
    st.builds(fp.Sensors, u16, u16),
    st.builds(fp.Ping, u32, u64),
    st.builds(fp.Pong, u32, u64, u64),
    st.builds(fp.Fault, u16, u32),
    st.just(fp.Stop()),
    st.builds(fp.StateCompact, u16, u8, u8, axes32),
    st.builds(fp.ForceCompact, u16, axes32),
)


@settings(max_examples=400, deadline=None)
@given(MESSAGES)
def test_round_trip_every_message(msg):
    frame = fp.encode(msg)
    assert frame[-1] == 0 and frame.count(0) == 1 and len(frame) <= fp.MAX_FRAME
    assert fp.decode_frame(frame) == msg
    # The independent oracle builds the same bytes.
    name = next(k for k, c in CLASSES.items() if isinstance(msg, c))
    fields = {k: list(getattr(msg, k)) if isinstance(getattr(msg, k), tuple)
              else getattr(msg, k) for k in (f.name for f in dataclasses.fields(msg))}
    assert frame == ORACLE.frame_of(name, fields)


@settings(max_examples=100, deadline=None)
@given(st.lists(MESSAGES, min_size=1, max_size=6), st.data())
def test_round_trip_stream_any_split(msgs, data):
    stream = b"".join(fp.encode(m) for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    chunks = [b - a for a, b in zip([0] + cuts, cuts)]
    out, dec = feed_all(stream, chunks)
    assert out == msgs
    assert dec.stats.frames_ok == len(msgs) and dec.stats.bad_frames == 0


def test_nan_and_signed_zero_bits_survive():
    bits = [0x7FF8000000000001, 0xFFF0000000000000, 0x8000000000000000, 0x0000000000000001]
    vals = tuple(struct.unpack("<d", struct.pack("<Q", b))[0] for b in bits)
    out = fp.decode_frame(fp.encode(fp.State(1, 2, 3, 4, vals)))
    assert [struct.unpack("<Q", struct.pack("<d", v))[0] for v in out.position] == bits
    assert math.isnan(out.position[0])


@pytest.mark.parametrize("msg,exc", [
    (fp.State(0, 0, 0, 0, ()), ValueError),
    (fp.State(0, 0, 0, 0, (0.0,) * 9), ValueError),
    (fp.Force(0, ()), ValueError),
    (fp.Force(-1, (0.0,)), ValueError),
    (fp.Force(2**32, (0.0,)), ValueError),
    (fp.Hello(1, 0, 0, 1.0, 1.0, 1.0, 1.0), ValueError),
    (fp.Hello(256, 1, 0, 1.0, 1.0, 1.0, 1.0), ValueError),
    (fp.Ping(0, 2**64), ValueError),
    (fp.Fault(0x10000, 0), ValueError),
    (fp.Velocity(0, ()), ValueError),
    (fp.Velocity(0, (0.0,) * 9), ValueError),
    (fp.SensorsRequest(0x10000), ValueError),
    (fp.Sensors(0, -1), ValueError),
    (b"\x00", TypeError),
    ("STOP", TypeError),
], ids=lambda p: repr(p)[:40])
def test_encode_rejects_out_of_range(msg, exc):
    with pytest.raises(exc):
        fp.encode(msg)


def _frame_of_packet(raw: bytes) -> bytes:
    """Frame of a hand-built ``type | body`` (CRC added by the oracle, not the codec)."""
    c = ORACLE.crc16_ccitt_false(raw)
    return ORACLE.cobs_encode(raw + bytes([c >> 8, c & 0xFF])) + b"\x00"


@pytest.mark.parametrize("raw,reason", [
    (bytes([fp.MSG_STATE]) + bytes(18), "malformed"),              # STATE, 0 axes
    (bytes([fp.MSG_STATE]) + bytes(18 + 8 * 9), "malformed"),      # STATE, 9 axes
    (bytes([fp.MSG_STATE]) + bytes(18 + 7), "malformed"),          # STATE, partial axis
    (bytes([fp.MSG_FORCE]) + bytes(4 + 12), "malformed"),          # FORCE, 1.5 axes
    (bytes([fp.MSG_STOP, 0]), "malformed"),                        # STOP with a body
    (bytes([fp.MSG_PING]) + bytes(11), "malformed"),               # PING one short
    (bytes([fp.MSG_PONG]) + bytes(21), "malformed"),               # PONG one long
    (bytes([fp.MSG_CONFIG]) + bytes(19), "malformed"),
    (bytes([fp.MSG_FAULT]) + bytes(5), "malformed"),
    (bytes([fp.MSG_HELLO_REQUEST]), "malformed"),
    (bytes([fp.MSG_VELOCITY]) + bytes(4), "malformed"),            # VELOCITY, 0 axes
    (bytes([fp.MSG_VELOCITY]) + bytes(4 + 8 * 9), "malformed"),    # VELOCITY, 9 axes
    (bytes([fp.MSG_SENSORS_REQUEST]) + bytes(1), "malformed"),     # SENSORS_REQUEST short
    (bytes([fp.MSG_SENSORS]) + bytes(5), "malformed"),             # SENSORS one long
    (bytes([fp.MSG_HELLO, 1, 9]) + bytes(36), "malformed"),        # HELLO, 9 axes
    (bytes([0x00]), "unknown_type"),
    (bytes([0xFF]) + bytes(10), "unknown_type"),
    (b"", "bad_crc"),                                              # type missing
])
def test_valid_crc_invalid_body(raw, reason):
    frame = _frame_of_packet(raw)
    with pytest.raises(fp.FrameError) as info:
        fp.decode_frame(frame)
    assert info.value.reason == reason
    _, dec = feed_all(frame)
    assert getattr(dec.stats, reason) == 1


# --------------------------------------------------------------------------- hostile streams

ALL_FRAMES = b"".join(g[2] for g in GOOD)
ALL_MSGS = [g[1] for g in GOOD]


def test_split_at_every_byte_boundary():
    for cut in range(len(ALL_FRAMES) + 1):
        out, dec = feed_all(ALL_FRAMES, [cut])
        assert out == ALL_MSGS, cut
        assert dec.stats.bad_frames == 0


def test_byte_at_a_time():
    dec = fp.StreamDecoder()
    out = []
    for b in ALL_FRAMES:
        out += dec.feed(bytes([b]))
        assert dec.buffered <= fp.MAX_FRAME - 1
    assert out == ALL_MSGS and dec.stats.frames_ok == len(GOOD)


def test_accepts_bytearray_and_memoryview():
    frame = GOOD[0][2]
    assert fp.StreamDecoder().feed(bytearray(frame)) == [GOOD[0][1]]
    assert fp.StreamDecoder().feed(memoryview(frame)) == [GOOD[0][1]]
    assert fp.decode_frame(bytearray(frame)) == GOOD[0][1]


GARBAGE = [
    ("none", b""),
    ("text", b"hello world, no zero here"),
    ("with_zeros", b"\x01\x02\x00\xff\x00\x00\x17"),
    ("ff_run", b"\xff" * 300),
    ("half_frame", GOOD[4][2][:10]),
    ("cobs_like", bytes(range(1, 200))),
]


@pytest.mark.parametrize("name,garbage", GARBAGE, ids=[g[0] for g in GARBAGE])
@pytest.mark.parametrize("where", ["before", "after", "between"])
def test_garbage_around_frames(name, garbage, where):
    a, b = GOOD[4][2], GOOD[8][2]  # STATE and FORCE
    sep = b"\x00"  # garbage without a trailing zero swallows the next frame: resync point
    if where == "before":
        stream, want = garbage + sep + a + b, [GOOD[4][1], GOOD[8][1]]
    elif where == "after":
        stream, want = a + b + garbage, [GOOD[4][1], GOOD[8][1]]
    else:
        stream, want = a + garbage + sep + b, [GOOD[4][1], GOOD[8][1]]
    for chunks in (None, [1] * len(stream), [7] * (len(stream) // 7)):
        out, dec = feed_all(stream, chunks)
        assert out == want


@pytest.mark.parametrize("pos", [1, 5, 15, 30])
def test_garbage_inside_frame_loses_only_that_frame(pos):
    a, b, c = GOOD[4][2], GOOD[8][2], GOOD[13][2]
    hurt = b[:pos] + b"\x55\xaa" + b[pos:] if pos < len(b) else b[:-1] + b"\x55\x00"
    out, dec = feed_all(a + hurt + c)
    assert out == [GOOD[4][1], GOOD[13][1]]
    assert dec.stats.frames_ok == 2 and dec.stats.bad_frames == 1


@pytest.mark.parametrize("name,msg,frame", GOOD, ids=GOOD_IDS)
def test_every_single_bit_flip_is_dropped(name, msg, frame):
    """Every single-bit error gives no message, and the next frame is still decoded."""
    follow = GOOD[8]
    for i in range(len(frame)):
        for bit in range(8):
            bad = bytearray(frame)
            bad[i] ^= 1 << bit
            bad = bytes(bad)
            with pytest.raises(fp.FrameError):
                fp.decode_frame(bad[:-1] if i < len(frame) - 1 else bad)
            # b"\x00" ends the frame even when the flip hit its delimiter.
            out, dec = feed_all(bad + b"\x00" + follow[2])
            assert out == [follow[1]], (name, i, bit)
            assert dec.stats.bad_frames >= 1


@pytest.mark.parametrize("name,msg,frame", GOOD, ids=GOOD_IDS)
def test_truncated_frames_are_dropped(name, msg, frame):
    for n in range(1, len(frame) - 1):
        out, dec = feed_all(frame[:n] + b"\x00" + GOOD[13][2])
        assert out == [GOOD[13][1]], (name, n)
        assert dec.stats.bad_frames == 1
    out, dec = feed_all(frame[:-1])  # no delimiter yet: nothing, nothing counted
    assert out == [] and dec.stats.bad_frames == 0 and dec.buffered == len(frame) - 1


def test_back_to_back_and_zero_runs():
    stream = b"\x00" * 5000 + b"\x00".join(g[2] for g in GOOD) + b"\x00" * 5000 + ALL_FRAMES
    out, dec = feed_all(stream, [4096] * 3)
    assert out == ALL_MSGS * 2
    assert dec.stats.bad_frames == 0 and dec.stats.frames_ok == 2 * len(GOOD)


def test_frame_at_and_over_max_length():
    # A packet of MAX_PACKET bytes with a valid CRC: the frame is exactly MAX_FRAME bytes.
    at_max = _frame_of_packet(bytes([0x7F]) + bytes(range(1, fp.MAX_PACKET - 2)))
    assert len(at_max) == fp.MAX_FRAME
    with pytest.raises(fp.FrameError) as info:
        fp.decode_frame(at_max)
    assert info.value.reason == "unknown_type"  # decoded, not rejected for its length
    over = _frame_of_packet(bytes([0x7F]) + bytes(range(1, fp.MAX_PACKET - 1)))
    assert len(over) == fp.MAX_FRAME + 1
    with pytest.raises(fp.FrameError) as info:
        fp.decode_frame(over)
    assert info.value.reason == "overlong"
    for chunks in (None, [1] * len(over)):
        out, dec = feed_all(at_max + over + b"\xff" * 10_000 + b"\x00" + GOOD[4][2], chunks)
        assert out == [GOOD[4][1]]
        s = dec.stats
        assert (s.unknown_type, s.overlong, s.frames_ok, s.bad_frames) == (1, 2, 1, 3)
    # The largest real message fits.
    assert len(GOOD[7][2]) == 87 <= fp.MAX_FRAME


def test_buffer_never_exceeds_one_max_frame():
    dec = fp.StreamDecoder()
    for _ in range(50):
        dec.feed(b"\x01" * 1000)
        assert dec.buffered == fp.MAX_FRAME - 1
    assert dec.feed(b"\x00") == [] and dec.stats.overlong == 1 and dec.buffered == 0
    dec.feed(b"\x02" * 10)
    dec.reset()
    assert dec.buffered == 0 and dec.feed(GOOD[0][2]) == [GOOD[0][1]]


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600), st.lists(st.integers(1, 64), max_size=20))
def test_random_bytes_never_raise(data, chunks):
    out, dec = feed_all(data, chunks)
    assert len(out) == dec.stats.frames_ok
    assert dec.stats.frames_ok + dec.stats.bad_frames <= data.count(0)
    # Whatever came before, a zero and a good frame resynchronise.
    more = dec.feed(b"\x00" + GOOD[4][2])
    assert more == [GOOD[4][1]]


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=200))
def test_decode_frame_raises_only_frame_error(data):
    try:
        fp.decode_frame(data)
    except fp.FrameError as exc:
        assert exc.reason in fp.DecoderStats().as_dict()


def test_random_corruption_of_a_long_stream():
    rng = random.Random(4)
    frames = [fp.encode(fp.State(i, 1000 * i, 1, i - 1, (rng.uniform(-1, 1),)))
              for i in range(1, 400)]
    stream = bytearray(b"".join(frames))
    for _ in range(60):
        stream[rng.randrange(len(stream))] = rng.randrange(256)
    dec = fp.StreamDecoder()
    out = []
    i = 0
    while i < len(stream):
        n = rng.randrange(1, 100)
        out += dec.feed(bytes(stream[i:i + n]))
        i += n
    good = {bytes(f) for f in frames}
    assert all(fp.encode(m) in good for m in out)  # no corrupted frame ever accepted
    assert len(out) >= 399 - 2 * 60
    assert dec.stats.frames_ok == len(out)


def test_last_frames_diagnostics():
    dec = fp.StreamDecoder(history=4)
    dec.feed(BAD[0][1] + ALL_FRAMES)
    assert len(dec.last_frames) == 4
    assert all(outcome == "ok" for _, outcome in dec.last_frames)
    dec.feed(BAD[0][1] + b"\xff" * 300 + b"\x00")
    raw, outcome = dec.last_frames[-1]
    assert outcome == "overlong" and len(raw) == fp.MAX_FRAME - 1
    assert dec.last_frames[-2] == (BAD[0][1][:-1], "bad_crc")
    text = dec.format_last_frames()
    assert text.splitlines()[-2].startswith("bad_crc: ")
    assert dec.stats.as_dict()["bad_crc"] == 2


def test_protocol_error_family(monkeypatch, tmp_path, capsys):
    """ProtocolError (protocol-version / axis mismatch, raised by the host loop): a
    HapsimError and a ValueError, never a DeviceError/OSError (the loop's recovery retries
    on DeviceError, and reconnecting cannot cure a mismatch); the CLI exits 1 on it."""
    import hapsim.commands.simulate as sim
    from hapsim.cli import main
    from hapsim.errors import DeviceError, HapsimError, ProtocolError

    assert issubclass(ProtocolError, HapsimError) and issubclass(ProtocolError, ValueError)
    assert not issubclass(ProtocolError, (DeviceError, OSError))
    assert "PROTOCOL_VERSION" in ProtocolError.__doc__ and "axes" in ProtocolError.__doc__

    def mismatch(args):
        raise ProtocolError("device speaks protocol 2, this host 1")

    monkeypatch.setattr(sim, "run", mismatch)      # register() binds sim.run when called
    out = tmp_path / "x.npz"
    assert main(["simulate", "configs/oscillator.yaml", "--steps", "1", "--out", str(out)]) == 1
    assert "ProtocolError: device speaks protocol 2" in capsys.readouterr().err
    assert not out.exists()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-10, 10), st.integers(0, 65535)), min_size=1,
                max_size=6),
       st.binary(max_size=40), st.lists(st.integers(0, 400), max_size=8))
def test_a_partial_frame_handed_over_and_back_decodes_as_if_never_taken(forces, junk, cuts):
    """StreamDecoder.take_partial/put_partial (the compiled loop's hand-over): a stream
    cut anywhere, its held partial frame taken out and put back at every cut, gives the
    same messages and counters as the stream fed whole; take_partial leaves nothing
    held, and put_partial refuses what is not a frame's start."""
    stream = junk + b"".join(fp.encode(fp.Force(seq, (f,))) for f, seq in forces)
    whole = fp.StreamDecoder()
    want = whole.feed(stream)
    dec, got, a = fp.StreamDecoder(), [], 0
    for c in sorted(min(c, len(stream)) for c in cuts) + [len(stream)]:
        got += dec.feed(stream[a:c])
        a = c
        if not dec.overflow:
            pre = dec.take_partial()
            assert dec.buffered == 0 and b"\x00" not in pre
            dec.put_partial(pre)
    assert got == want and dec.stats.as_dict() == whole.stats.as_dict()
    for bad in (b"ab\x00", b"x" * fp.MAX_FRAME):
        with pytest.raises(ValueError):
            dec.put_partial(bad)
