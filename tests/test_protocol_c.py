"""Tests of the C99 reference codec (``firmware_protocol/c``) against the golden vectors and
against the Python codec, in both directions.

The C sources are compiled with the system C compiler and
``-std=c99 -Wall -Wextra -Wpedantic -Werror`` together with ``tests/hproto_driver.c``, a
line-oriented driver (hex frames in, JSON lines out; see its header) that lives with the
tests, not in the shipped reference. Skipped when no C compiler is found.
"""

from __future__ import annotations

import dataclasses
import json
import random
import re
import shutil
import struct
import subprocess
from pathlib import Path

import pytest
from cobs import cobs

import firmware_protocol as fp

PKG = Path(fp.__file__).resolve().parent
CDIR = PKG / "c"
DRIVER = Path(__file__).resolve().parent / "hproto_driver.c"
VECTORS = json.loads((PKG / "vectors" / "vectors.json").read_text())
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-O2"]
CC = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")

#: pytest-xdist (the README command runs several workers): its module-scoped C driver is compiled
#: once, on one worker.
pytestmark = [pytest.mark.skipif(CC is None, reason="no C compiler (cc/gcc/clang) on PATH"),
              pytest.mark.xdist_group("test_protocol_c")]

# Field order on the wire per type id (what the driver's E command reads).
WIRE = {
    fp.MSG_HELLO: ["protocol_version", "n_axes", "device_id", "position_scale",
                   "force_scale", "force_limit", "native_rate_hz"],
    fp.MSG_HELLO_REQUEST: ["protocol_version"],
    fp.MSG_CONFIG: ["rate_hz", "watchdog_us", "force_limit"],
    fp.MSG_LINK: ["baud", "bits_per_byte"],
    fp.MSG_SENSORS_REQUEST: ["sensors"],
    fp.MSG_SENSORS: ["offered", "enabled"],
    fp.MSG_VELOCITY: ["seq", "velocity"],
    fp.MSG_STATE_COMPACT: ["seq", "status", "lag", "position"],
    fp.MSG_FORCE_COMPACT: ["seq", "force"],
    fp.MSG_STATE: ["seq", "time_us", "status", "force_seq", "position"],
    fp.MSG_FORCE: ["seq", "force"],
    fp.MSG_PING: ["nonce", "host_time_us"],
    fp.MSG_PONG: ["nonce", "host_time_us", "device_time_us"],
    fp.MSG_FAULT: ["code", "detail"],
    fp.MSG_STOP: [],
}
CLASSES = {"HELLO": fp.Hello, "HELLO_REQUEST": fp.HelloRequest, "CONFIG": fp.Config, "LINK": fp.Link,
           "SENSORS_REQUEST": fp.SensorsRequest, "SENSORS": fp.Sensors, "STATE": fp.State,
           "FORCE": fp.Force, "VELOCITY": fp.Velocity, "PING": fp.Ping, "PONG": fp.Pong,
           "FAULT": fp.Fault, "STOP": fp.Stop, "STATE_COMPACT": fp.StateCompact,
           "FORCE_COMPACT": fp.ForceCompact}
#: Messages whose value arrays are binary32 (the driver prints and reads 8 hex digits).
F32 = (fp.StateCompact, fp.ForceCompact)


def bits(x: float) -> str:
    return "0x%016x" % struct.unpack("<Q", struct.pack("<d", x))[0]


def bits32(x: float) -> str:
    return "0x%08x" % struct.unpack("<I", struct.pack("<f", x))[0]


def as_c_json(msg) -> dict:
    """What the driver prints for ``msg`` (doubles as their bit patterns)."""
    out = {"type": next(k for k, c in CLASSES.items() if isinstance(msg, c))}
    for name in (f.name for f in dataclasses.fields(msg)):
        v = getattr(msg, name)
        if isinstance(v, tuple):
            out[name] = [(bits32 if isinstance(msg, F32) else bits)(x) for x in v]
        elif isinstance(v, float):
            out[name] = bits(v)
        else:
            out[name] = v
    return out


def encode_command(msg) -> str:
    tokens = [str(msg.TYPE)]
    for name in WIRE[msg.TYPE]:
        v = getattr(msg, name)
        if isinstance(v, tuple):
            tokens += [(bits32 if isinstance(msg, F32) else bits)(x) for x in v]
        elif isinstance(v, float):
            tokens.append(bits(v))
        else:
            tokens.append(str(v))
    return "E " + " ".join(tokens)


def message_of(vector: dict):
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in vector["fields"].items()}
    return CLASSES[vector["type"]](**fields)


@pytest.fixture(scope="module")
def driver(tmp_path_factory):
    exe = tmp_path_factory.mktemp("hproto") / "hp_driver"
    cmd = [CC, *CFLAGS, "-I", str(CDIR), "-o", str(exe), str(CDIR / "hproto.c"), str(DRIVER)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, f"{' '.join(cmd)}\n{res.stderr}"

    def run(lines: list[str]) -> list[dict]:
        res = subprocess.run([str(exe)], input="\n".join(lines) + "\n", capture_output=True,
                             text=True, check=True, timeout=60)
        return [json.loads(line) for line in res.stdout.splitlines()]
    return run


def test_library_is_freestanding_c99():
    """hproto.c/h include only <stdint.h> and <string.h> (issue 4); no malloc, no stdio.
    The shipped c/ folder holds exactly the header and the source (the driver is a test)."""
    assert sorted(p.name for p in CDIR.iterdir() if p.suffix in (".c", ".h")) == \
        ["hproto.c", "hproto.h"]
    for name in ("hproto.h", "hproto.c"):
        src = (CDIR / name).read_text()
        includes = set(re.findall(r"#include\s+[<\"]([^>\"]+)[>\"]", src))
        assert includes <= {"stdint.h", "string.h", "hproto.h"}, (name, includes)
        code = re.sub(r"/\*.*?\*/", "", src, flags=re.S)
        for word in ("malloc", "free(", "printf", "calloc", "realloc"):
            assert word not in code, (name, word)


def test_library_compiles_alone_with_strict_flags(tmp_path):
    res = subprocess.run([CC, *CFLAGS, "-c", str(CDIR / "hproto.c"), "-o",
                          str(tmp_path / "hproto.o")], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_header_is_self_contained(tmp_path):
    """A unit that includes only hproto.h gets size_t and uint*_t from it (through
    <string.h> and <stdint.h>, no <stddef.h>) and compiles with the strict flags."""
    unit = tmp_path / "only_header.c"
    unit.write_text('#include "hproto.h"\n'
                    "size_t hp_frame_room(const hp_msg_t *m, uint8_t *out)\n"
                    "{ return hp_encode(m, out, HP_MAX_FRAME); }\n")
    res = subprocess.run([CC, *CFLAGS, "-I", str(CDIR), "-c", str(unit), "-o",
                          str(tmp_path / "only_header.o")], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_c_decodes_golden_frames(driver):
    out = driver(["D " + v["frame_hex"] for v in VECTORS["good"]])
    assert out == [as_c_json(message_of(v)) for v in VECTORS["good"]]


def test_c_encodes_golden_messages(driver):
    out = driver([encode_command(message_of(v)) for v in VECTORS["good"]])
    assert [o["frame"] for o in out] == [v["frame_hex"] for v in VECTORS["good"]]


def test_c_rejects_bad_vectors_with_the_same_reason(driver):
    out = driver(["D " + b["frame_hex"] for b in VECTORS["bad"]])
    assert [o["error"] for o in out] == [b["error"] for b in VECTORS["bad"]]


def test_c_refuses_to_encode_bad_axis_counts(driver):
    out = driver([f"E {fp.MSG_FORCE} 1", f"E {fp.MSG_STATE} 1 2 3 4 " + " ".join(["0x0"] * 9),
                  f"E {fp.MSG_HELLO} 1 0 7 0x0 0x0 0x0 0x0", "E 127", f"E {fp.MSG_VELOCITY} 1",
                  f"E {fp.MSG_VELOCITY} 1 " + " ".join(["0x0"] * 9)])
    assert out == [{"error": "encode"}] * 6


def random_message(rng: random.Random):
    def f():
        return struct.unpack("<d", struct.pack("<Q", rng.getrandbits(64)))[0] \
            if rng.random() < 0.3 else rng.uniform(-1e3, 1e3)

    def ax():
        return tuple(f() for _ in range(rng.randint(1, fp.MAX_AXES)))

    def ax32():     # binary32 values (random bit patterns but NaN: NaN != NaN in the check)
        out, n = [], rng.randint(1, fp.MAX_AXES)
        while len(out) < n:
            x = struct.unpack("<f", struct.pack("<I", rng.getrandbits(32)))[0]
            if x == x:
                out.append(x)
        return tuple(out)
    u32, u64 = (lambda: rng.getrandbits(32)), (lambda: rng.getrandbits(64))
    return rng.choice([
        lambda: fp.Hello(rng.getrandbits(8), rng.randint(1, 8), u32(), f(), f(), f(), f()),
        lambda: fp.HelloRequest(rng.getrandbits(8)),
        lambda: fp.Config(f(), u32(), f()),
        lambda: fp.State(u32(), u64(), rng.getrandbits(16), u32(), ax()),
        lambda: fp.Force(u32(), ax()),
        lambda: fp.Velocity(u32(), ax()),
        lambda: fp.SensorsRequest(rng.getrandbits(16)),
        lambda: fp.Sensors(rng.getrandbits(16), rng.getrandbits(16)),
        lambda: fp.Ping(u32(), u64()),
        lambda: fp.Pong(u32(), u64(), u64()),
        lambda: fp.Fault(rng.getrandbits(16), u32()),
        lambda: fp.Stop(),
        lambda: fp.StateCompact(rng.getrandbits(16), rng.getrandbits(8), rng.getrandbits(8),
                                ax32()),
        lambda: fp.ForceCompact(rng.getrandbits(16), ax32()),
    ])()


def test_c_and_python_agree_on_random_messages(driver):
    """Python encode -> C decode and C encode == Python encode, NaN payloads included."""
    rng = random.Random(1)
    msgs = [random_message(rng) for _ in range(500)]
    frames = [fp.encode(m) for m in msgs]
    decoded = driver(["D " + fr.hex() for fr in frames])
    assert decoded == [as_c_json(m) for m in msgs]
    encoded = driver([encode_command(m) for m in msgs])
    assert [bytes.fromhex(o["frame"]) for o in encoded] == frames


def python_stream(data: bytes, chunk: int):
    dec = fp.StreamDecoder()
    msgs = []
    for i in range(0, len(data), chunk):
        msgs += dec.feed(data[i:i + chunk])
    return [as_c_json(m) for m in msgs], dec.stats.as_dict(), dec.buffered


def c_stream(driver, data: bytes):
    # The driver reads lines of up to 64 KiB: feed 8000 bytes per S command.
    out = driver(["I"] + ["S " + data[i:i + 8000].hex() for i in range(0, len(data), 8000)])
    msgs = [line for line in out[1:] if "type" in line]
    last = out[-1]
    return msgs, last["stats"], last["buffered"]


def hostile_streams():
    good = [bytes.fromhex(v["frame_hex"]) for v in VECTORS["good"]]
    bad = [bytes.fromhex(b["frame_hex"]) for b in VECTORS["bad"]]
    allg = b"".join(good)
    rng = random.Random(7)
    flips = bytearray()
    for fr in good:
        for i in range(len(fr)):
            for bit in range(8):
                x = bytearray(fr)
                x[i] ^= 1 << bit
                flips += x + b"\x00"
    # Valid-CRC packets making a frame of exactly MAX_FRAME bytes and of one more.
    edge = b""
    for size in (fp.MAX_PACKET - 2, fp.MAX_PACKET - 1):
        raw = bytes([0x7F]) + bytes(range(1, size))
        edge += cobs.encode(raw + struct.pack(">H", fp.crc16(raw))) + b"\x00"
    assert len(edge) == 2 * fp.MAX_FRAME + 1
    noisy = bytearray(allg * 20)
    for _ in range(80):
        noisy[rng.randrange(len(noisy))] = rng.randrange(256)
    return [
        ("back_to_back", allg),
        ("zeros_and_frames", b"\x00" * 3000 + b"\x00\x00".join(good) + b"\x00" * 3000),
        ("garbage_around", b"junk\x01\x02" + allg + b"\xff" * 500 + b"\x00" + allg + b"\x07"),
        ("bad_vectors", b"".join(bad) + allg),
        ("every_bit_flip", bytes(flips) + allg),
        ("truncated", b"".join(fr[:k] + b"\x00" for fr in good for k in range(1, len(fr) - 1))),
        ("random_noise", bytes(noisy)),
        ("random_bytes", bytes(rng.getrandbits(8) for _ in range(20000))),
        ("overlong_tail", allg + b"\x11" * 1000),
        ("at_and_over_max_frame", edge + allg + edge),
    ]


@pytest.mark.parametrize("name,data", hostile_streams(), ids=[h[0] for h in hostile_streams()])
def test_c_stream_decoder_matches_python(driver, name, data):
    """Same messages, same counters, same buffered bytes, for any split of the input."""
    c_msgs, c_stats, c_buf = c_stream(driver, data)
    for chunk in (1, 97, len(data) or 1):
        py_msgs, py_stats, py_buf = python_stream(data, chunk)
        assert c_msgs == py_msgs
        assert c_stats == py_stats
        assert c_buf == py_buf <= fp.MAX_FRAME - 1
    if name in ("back_to_back", "zeros_and_frames", "every_bit_flip"):
        n_good = len(VECTORS["good"])
        assert c_stats["frames_ok"] == n_good


INF, NAN = float("inf"), float("nan")


@pytest.mark.parametrize("limit,force,status,want", [
    (4.0, (1.0, -2.0), 0, (1.0, -2.0)),
    (4.0, (4.0, -4.0), 0, (4.0, -4.0)),                       # at the limit: not clamped
    (4.0, (5.0, -1e300, 3.0), fp.STATUS_FORCE_CLAMPED, (4.0, -4.0, 3.0)),
    (0.0, (1e-300,), fp.STATUS_FORCE_CLAMPED, (0.0,)),
    (4.0, (1.0, NAN), fp.STATUS_FAULT, (0.0, 0.0)),           # non-finite: all zero
    (4.0, (INF,), fp.STATUS_FAULT, (0.0,)),
    (4.0, (2.0, -INF, 9.0), fp.STATUS_FAULT, (0.0, 0.0, 0.0)),
], ids=lambda p: repr(p)[:30])
def test_c_force_limit(driver, limit, force, status, want):
    out = driver(["L " + " ".join(bits(x) for x in (limit, *force))])
    assert out == [{"status": status, "force": [bits(x) for x in want]}]


@pytest.mark.parametrize("last,now,timeout,expired", [
    (100, 5100, 5000, 0),          # exactly the timeout: a FORCE then is in time
    (100, 5101, 5000, 1),
    (2**64 - 1000, 3000, 5000, 0),  # clock wrapped: 4000 us elapsed
    (2**64 - 1000, 4001, 5000, 1),
])
def test_c_watchdog(driver, last, now, timeout, expired):
    assert driver([f"W {last} {now} {timeout}"]) == [{"expired": expired}]
