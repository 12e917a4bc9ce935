#!/usr/bin/env python3
"""Independent oracle for the golden vectors in ``vectors.json``.

This script re-derives every golden frame from the field tables of ``PROTOCOL.md`` with its
own bit-by-bit CRC-16/CCITT-FALSE and its own byte-loop COBS; it shares no code with the
``firmware_protocol`` codec (nor with ``cobs`` or ``binascii``), so a bug in the codec cannot
hide in the reference it is tested against.

Usage::

    python firmware_protocol/vectors/check_vectors.py          # verify, exit 1 on mismatch
    python firmware_protocol/vectors/check_vectors.py --write  # (re)write vectors.json

``--write`` was run once to create the file; the hand-checked byte-level examples of
``PROTOCOL.md`` (STOP and FORCE) are asserted below as well.
"""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
VECTORS = HERE / "vectors.json"

# Type id and field layout per message, from PROTOCOL.md §4 (little-endian, no padding).
# A format ending in "*" is an array filling the rest of the body (1..8 elements).
LAYOUT = {
    "HELLO": (0x01, [("protocol_version", "B"), ("n_axes", "B"), ("device_id", "I"),
                     ("position_scale", "d"), ("force_scale", "d"), ("force_limit", "d"),
                     ("native_rate_hz", "d")]),
    "HELLO_REQUEST": (0x02, [("protocol_version", "B")]),
    "CONFIG": (0x03, [("rate_hz", "d"), ("watchdog_us", "I"), ("force_limit", "d")]),
    "LINK": (0x04, [("baud", "I"), ("bits_per_byte", "B")]),
    "SENSORS_REQUEST": (0x05, [("sensors", "H")]),
    "SENSORS": (0x06, [("offered", "H"), ("enabled", "H")]),
    "STATE": (0x10, [("seq", "I"), ("time_us", "Q"), ("status", "H"), ("force_seq", "I"),
                     ("position", "d*")]),
    "FORCE": (0x11, [("seq", "I"), ("force", "d*")]),
    "VELOCITY": (0x12, [("seq", "I"), ("velocity", "d*")]),
    "STATE_COMPACT": (0x13, [("seq", "H"), ("status", "B"), ("lag", "B"), ("position", "f*")]),
    "FORCE_COMPACT": (0x14, [("seq", "H"), ("force", "f*")]),
    "PING": (0x20, [("nonce", "I"), ("host_time_us", "Q")]),
    "PONG": (0x21, [("nonce", "I"), ("host_time_us", "Q"), ("device_time_us", "Q")]),
    "FAULT": (0x30, [("code", "H"), ("detail", "I")]),
    "STOP": (0x31, []),
}


def crc16_ccitt_false(data: bytes) -> int:
    """Bit-by-bit CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no xorout).

    Parameters
    ----------
    data : bytes
        Bytes to check (PROTOCOL.md §1: type and body of a packet).

    Returns
    -------
    int
        CRC, 0..0xFFFF (check value of ``b"123456789"``: 0x29B1).
    """
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def cobs_encode(data: bytes) -> bytes:
    """Textbook COBS (Cheshire & Baker 1999), without the delimiter.

    Parameters
    ----------
    data : bytes
        Packet to stuff.

    Returns
    -------
    bytes
        The COBS encoding: no ``0x00`` byte, ``len(data) + 1`` bytes for packets shorter
        than 254 bytes.
    """
    out = bytearray([0])
    code_at, code = 0, 1
    for byte in data:
        if byte == 0:
            out[code_at] = code
            code_at, code = len(out), 1
            out.append(0)
        else:
            out.append(byte)
            code += 1
            if code == 0xFF:
                out[code_at] = code
                code_at, code = len(out), 1
                out.append(0)
    out[code_at] = code
    return bytes(out)


def packet_of(type_name: str, fields: dict) -> bytes:
    """Packet ``type | body | crc`` of a message given by name and field dict.

    Parameters
    ----------
    type_name : str
        A key of :data:`LAYOUT` (``"STATE"``, ...).
    fields : dict
        Field values by name, in PROTOCOL.md §4's units; array fields as lists.

    Returns
    -------
    bytes
        Type id, little-endian body, CRC-16 MSB first.
    """
    type_id, layout = LAYOUT[type_name]
    body = bytearray([type_id])
    for name, fmt in layout:
        if fmt.endswith("*"):
            for v in fields[name]:
                body += struct.pack("<" + fmt[0], v)
        else:
            body += struct.pack("<" + fmt, fields[name])
    crc = crc16_ccitt_false(bytes(body))
    return bytes(body) + bytes([crc >> 8, crc & 0xFF])


def frame_of(type_name: str, fields: dict) -> bytes:
    """Whole frame ``COBS(packet) + 00``.

    Parameters
    ----------
    type_name : str
        As :func:`packet_of`.
    fields : dict
        As :func:`packet_of`.

    Returns
    -------
    bytes
        The frame as sent on the wire, delimiter included.
    """
    return cobs_encode(packet_of(type_name, fields)) + b"\x00"


GOOD = [
    ("hello", "HELLO", dict(protocol_version=1, n_axes=1, device_id=0x48415031,
                            position_scale=1.0e-6, force_scale=0.001, force_limit=5.0,
                            native_rate_hz=1000.0)),
    ("hello_3axes", "HELLO", dict(protocol_version=1, n_axes=3, device_id=0,
                                  position_scale=2.5e-5, force_scale=1.0 / 4096,
                                  force_limit=12.5, native_rate_hz=4000.0)),
    ("hello_request", "HELLO_REQUEST", dict(protocol_version=1)),
    ("config", "CONFIG", dict(rate_hz=1000.0, watchdog_us=5000, force_limit=4.0)),
    ("state_1axis", "STATE", dict(seq=1, time_us=1000, status=0x0041, force_seq=0,
                                  position=[0.01])),
    ("state_1axis_zeros", "STATE", dict(seq=0, time_us=0, status=0, force_seq=0,
                                        position=[0.0])),
    ("state_2axes", "STATE", dict(seq=0xFFFFFFFF, time_us=2**64 - 1, status=0x007F,
                                  force_seq=0xFFFFFFFE, position=[-0.0, -1.25e-3])),
    ("state_8axes_max_frame", "STATE", dict(seq=123456789, time_us=9876543210123, status=0x0005,
                                            force_seq=123456788,
                                            position=[0.1 * k - 0.35 for k in range(8)])),
    ("force_1axis", "FORCE", dict(seq=1, force=[0.5])),
    ("force_3axes", "FORCE", dict(seq=0x01020304, force=[-2.0, 5e-324, 1.7976931348623157e308])),
    ("ping", "PING", dict(nonce=42, host_time_us=1234567890)),
    ("pong", "PONG", dict(nonce=42, host_time_us=1234567890, device_time_us=777)),
    ("fault_watchdog", "FAULT", dict(code=1, detail=5000)),
    ("stop", "STOP", {}),
    # FORCE 0 applied (FORCE_APPLIED 0x0080, added within version 1): force_seq = 0 names
    # it, not "none yet"
    ("state_force_applied_seq0", "STATE", dict(seq=1, time_us=1000, status=0x00C1,
                                               force_seq=0, position=[0.01])),
    # LINK (0x04, added within version 1): a 1 Mbaud 8N1 UART
    ("link", "LINK", dict(baud=1000000, bits_per_byte=10)),
    # SENSORS_REQUEST / SENSORS / VELOCITY (0x05, 0x06, 0x12, added within version 1): the
    # host asks for the velocity sensor; a device that has it enables it, one that has none
    # answers 0, 0; then VELOCITY precedes each STATE with the same seq
    ("sensors_request_velocity", "SENSORS_REQUEST", dict(sensors=0x0001)),
    ("sensors_velocity_enabled", "SENSORS", dict(offered=0x0001, enabled=0x0001)),
    ("sensors_none_offered", "SENSORS", dict(offered=0, enabled=0)),
    ("velocity_1axis", "VELOCITY", dict(seq=1, velocity=[-0.125])),
    ("velocity_3axes", "VELOCITY", dict(seq=0xFFFFFFFF, velocity=[0.0, 2.5e-3, -1e300])),
    # compact frames (0x13, 0x14, and the SENSORS_REQUEST bit COMPACT 0x0002, added within
    # version 1): a host asks for them with the velocity sensor or alone; a device that has
    # both enables both; then STATE_COMPACT replaces STATE and FORCE_COMPACT answers it.
    # Values are binary32 (0.01 is not: its binary32 0.00999999977648258209228515625 is sent)
    ("sensors_request_compact", "SENSORS_REQUEST", dict(sensors=0x0002)),
    ("sensors_compact_enabled", "SENSORS", dict(offered=0x0002, enabled=0x0002)),
    ("state_compact_1axis", "STATE_COMPACT", dict(seq=1, status=0x41, lag=0,
                                                  position=[0.009999999776482582])),
    ("state_compact_applied_lag1", "STATE_COMPACT", dict(seq=0xFFFF, status=0xC1, lag=1,
                                                         position=[-0.0])),
    ("state_compact_3axes_saturated", "STATE_COMPACT", dict(
        seq=0x1234, status=0xE5, lag=255, position=[3.4028234663852886e38, -1.401298464324817e-45, 0.5])),
    ("force_compact_1axis", "FORCE_COMPACT", dict(seq=1, force=[0.5])),
    ("force_compact_8axes", "FORCE_COMPACT", dict(seq=0xFFFF, force=[
        -2.0, 1.401298464324817e-45, -3.4028234663852886e38, 0.25, 1.0, -1.0, 0.0, -0.0])),
]


def bad_vectors() -> list[dict]:
    """Frames every decoder must drop, each with the counter it must feed.

    Returns
    -------
    list of dict
        ``{"name", "frame_hex", "error"}``, ``error`` a counter of PROTOCOL.md §8.
    """
    force = frame_of("FORCE", dict(seq=1, force=[0.5]))
    flipped = bytearray(force)
    flipped[12] ^= 0x10  # one bit of the float 0.5 (not a COBS code byte): CRC mismatch
    unknown = cobs_encode(b"\x7f" + bytes([crc16_ccitt_false(b"\x7f") >> 8,
                                           crc16_ccitt_false(b"\x7f") & 0xFF])) + b"\x00"
    short_body = b"\x11\x01\x00\x00\x00"  # FORCE with no axis
    c = crc16_ccitt_false(short_body)
    malformed = cobs_encode(short_body + bytes([c >> 8, c & 0xFF])) + b"\x00"
    hello0 = bytearray(packet_of("HELLO", dict(GOOD[0][2], n_axes=1))[:-2])
    hello0[2] = 0  # n_axes = 0
    c = crc16_ccitt_false(bytes(hello0))
    malformed_hello = cobs_encode(bytes(hello0) + bytes([c >> 8, c & 0xFF])) + b"\x00"
    vel_short = b"\x12\x01\x00\x00\x00"  # VELOCITY with no axis
    c = crc16_ccitt_false(vel_short)
    malformed_velocity = cobs_encode(vel_short + bytes([c >> 8, c & 0xFF])) + b"\x00"
    sc_short = b"\x13\x01\x00\x41\x00"  # STATE_COMPACT with no axis
    c = crc16_ccitt_false(sc_short)
    malformed_state_compact = cobs_encode(sc_short + bytes([c >> 8, c & 0xFF])) + b"\x00"
    fc_odd = b"\x14\x01\x00\x00\x00\x00\x3f\x00"  # FORCE_COMPACT, 5 value bytes
    c = crc16_ccitt_false(fc_odd)
    malformed_force_compact = cobs_encode(fc_odd + bytes([c >> 8, c & 0xFF])) + b"\x00"
    return [
        {"name": "bad_crc_bitflip", "frame_hex": bytes(flipped).hex(), "error": "bad_crc"},
        {"name": "bad_crc_runt", "frame_hex": cobs_encode(b"\x31\xc7").hex() + "00",
         "error": "bad_crc"},
        {"name": "bad_cobs_code_past_end", "frame_hex": "0531c78200", "error": "bad_cobs"},
        {"name": "unknown_type", "frame_hex": unknown.hex(), "error": "unknown_type"},
        {"name": "malformed_force_no_axis", "frame_hex": malformed.hex(), "error": "malformed"},
        {"name": "malformed_hello_zero_axes", "frame_hex": malformed_hello.hex(),
         "error": "malformed"},
        {"name": "overlong", "frame_hex": "ff" * 128 + "00", "error": "overlong"},
        {"name": "malformed_velocity_no_axis", "frame_hex": malformed_velocity.hex(),
         "error": "malformed"},
        {"name": "malformed_state_compact_no_axis", "frame_hex": malformed_state_compact.hex(),
         "error": "malformed"},
        {"name": "malformed_force_compact_partial_axis",
         "frame_hex": malformed_force_compact.hex(), "error": "malformed"},
    ]


def build() -> dict:
    """The whole vector file as a dict.

    Returns
    -------
    dict
        ``protocol_version``, ``max_frame``, ``crc`` (description), ``good`` (name, type,
        fields, packet_hex, frame_hex) and ``bad`` (:func:`bad_vectors`).
    """
    good = []
    for name, type_name, fields in GOOD:
        good.append({"name": name, "type": type_name, "fields": fields,
                     "packet_hex": packet_of(type_name, fields).hex(),
                     "frame_hex": frame_of(type_name, fields).hex()})
    return {"protocol_version": 1, "max_frame": 128,
            "crc": "CRC-16/CCITT-FALSE poly=0x1021 init=0xFFFF refin=false refout=false "
                   "xorout=0x0000, sent MSB first",
            "good": good, "bad": bad_vectors()}


def check(data: dict) -> list[str]:
    """Compare a loaded ``vectors.json`` with this oracle.

    Parameters
    ----------
    data : dict
        The parsed vector file.

    Returns
    -------
    list of str
        One line per mismatch; empty when the file agrees.
    """
    errors = []
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    # Hand-checked examples of PROTOCOL.md §7.
    assert frame_of("STOP", {}).hex() == "0431c78200"
    assert frame_of("FORCE", dict(seq=1, force=[0.5])).hex() == \
        "031101" "0101010101010101" "05e03fafa0" "00"
    for v in data["good"]:
        for key, want in (("packet_hex", packet_of(v["type"], v["fields"]).hex()),
                          ("frame_hex", frame_of(v["type"], v["fields"]).hex())):
            if v[key] != want:
                errors.append(f"{v['name']}.{key}: file {v[key]} != oracle {want}")
        if len(bytes.fromhex(v["frame_hex"])) > data["max_frame"]:
            errors.append(f"{v['name']}: frame longer than max_frame")
    want_bad = {b["name"]: b for b in bad_vectors()}
    for b in data["bad"]:
        if want_bad.get(b["name"]) != b:
            errors.append(f"bad vector {b['name']} differs from the oracle")
    return errors


def main(argv: list[str] | None = None) -> int:
    """Verify (default) or write (``--write``) vectors.json.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (``sys.argv[1:]`` when None).

    Returns
    -------
    int
        Exit code: 0 when the file agrees (or was written), 1 on a mismatch.
    """
    argv = sys.argv[1:] if argv is None else argv
    if "--write" in argv:
        VECTORS.write_text(json.dumps(build(), indent=1) + "\n")
        print(f"wrote {VECTORS}")
        return 0
    errors = check(json.loads(VECTORS.read_text()))
    for e in errors:
        print(e)
    print("vectors OK" if not errors else f"{len(errors)} mismatches")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
