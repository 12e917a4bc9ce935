"""The compiled I/O primitives of the numba host loop and the numba mock tick: libc's
``read``, ``write``, ``poll`` and ``clock_gettime`` called by symbol from nopython code,
the CRC-16 and COBS of the framed protocol (PROTOCOL.md §2-§3), the little-endian field
reader and the frame splitter, the host's FORCE frames and the compact seq's expansion.
One implementation for both sides of the wire:
:mod:`hapsim.host.fastloop` (host) and :mod:`hapsim.emulated.fastmock` (device).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import types
from numba.extending import register_jitable

import firmware_protocol as fp

__all__ = ["c_read", "c_write", "c_poll", "c_clock_gettime", "CLOCK_MONOTONIC", "POLLIN",
           "POLLOUT", "POLLERR", "POLLHUP", "POLLNVAL", "crc_table", "CRC_TABLE", "jit",
           "jit_helper", "now_ns", "crc16", "le", "next_frame", "cobs_decode", "cobs_encode",
           "F32_MAX", "force_frame", "force_compact_frame", "expand_seq"]

# ----------------------------------------------------------------------------- libc
# libc by symbol (numba ExternalFunction: resolved at link time, so the compiled loop can be
# cached on disk); pointers are passed as integers (intp), as the x86-64 / aarch64 ABI does
c_read = types.ExternalFunction("read", types.intp(types.int32, types.intp, types.uintp))
c_write = types.ExternalFunction("write", types.intp(types.int32, types.intp, types.uintp))
c_poll = types.ExternalFunction("poll", types.int32(types.intp, types.uint64, types.int32))
c_clock_gettime = types.ExternalFunction("clock_gettime",
                                         types.int32(types.int32, types.intp))

CLOCK_MONOTONIC = 1
POLLIN, POLLOUT, POLLERR, POLLHUP, POLLNVAL = 0x1, 0x4, 0x8, 0x10, 0x20


# ----------------------------------------------------------------------------- frames
def crc_table() -> np.ndarray:
    """CRC-16/CCITT-FALSE table (poly 0x1021, MSB first), as :func:`binascii.crc_hqx`.

    Returns
    -------
    ndarray of uint16, shape (256,)
    """
    t = np.zeros(256, dtype=np.uint16)
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else (c << 1)
        t[i] = c & 0xFFFF
    return t


#: :func:`crc_table`, built once.
CRC_TABLE = crc_table()

#: The decorator of every compiled function here and in the compiled loop and mock:
#: nopython, no GIL, cached on disk.
jit = numba.njit(nogil=True, cache=True)
#: The small helpers the loop and the mock call with literal offsets and lengths
#: (``le(pkt, 1, 4)``, ``crc16(pkt, 13, table)``): overloads (``register_jitable``), which
#: numba types with their arguments' plain types (``int64``, not ``Literal[int]``), so each
#: compiles once per signature and LLVM inlines the call. (As ``njit`` functions they
#: compiled once per literal combination, ``le`` five times; inlined at numba's IR level
#: instead, they were translated and typed again at each of their ~30 call sites.) Same
#: integer operations, same bytes.
jit_helper = register_jitable


@jit
def now_ns(ts):
    """``CLOCK_MONOTONIC`` now [ns], read into ``ts`` (int64, shape (2,): s, ns).

    Parameters
    ----------
    ts : ndarray of int64, shape (2,)
        Scratch ``struct timespec`` (seconds, nanoseconds), overwritten.

    Returns
    -------
    int
        Monotonic time [ns].
    """
    c_clock_gettime(CLOCK_MONOTONIC, ts.ctypes.data)
    return ts[0] * 1_000_000_000 + ts[1]


@jit_helper
def crc16(buf, n, table):
    """CRC-16/CCITT-FALSE of ``buf[:n]`` with ``table`` (:data:`CRC_TABLE`); 0 over a
    packet whose last two bytes are its CRC (PROTOCOL.md §2).

    Parameters
    ----------
    buf : ndarray of uint8
        The bytes.
    n : int
        How many of them, from the first.
    table : ndarray of uint16, shape (256,)
        :data:`CRC_TABLE`.

    Returns
    -------
    int
        The CRC, 0 .. 0xFFFF (initial value 0xFFFF, no final XOR).
    """
    c = 0xFFFF
    for j in range(n):
        c = ((c << 8) & 0xFFFF) ^ table[((c >> 8) ^ buf[j]) & 0xFF]
    return c


@jit_helper
def le(buf, off, nbytes):
    """The little-endian unsigned integer in ``buf[off:off + nbytes]`` (PROTOCOL.md §3:
    every integer field is little-endian).

    Parameters
    ----------
    buf : ndarray of uint8
        The packet.
    off : int
        Offset of the field's first byte.
    nbytes : int
        Its width in bytes, 1 to 8 (8 bytes read as a two's-complement int64).

    Returns
    -------
    int64
        The field's value.
    """
    v = np.int64(0)
    for j in range(nbytes):
        v |= np.int64(buf[off + j]) << (8 * j)
    return v


@jit_helper
def next_frame(rb, a, n_rb):
    """The next frame in ``rb[a:n_rb]``: ``(a, z)`` with ``rb[a:z]`` the frame's COBS
    bytes and ``rb[z]`` its 0x00 delimiter, idle fill (empty frames) skipped; ``z = -1``
    when no delimiter has arrived yet (``rb[a:n_rb]`` is a partial frame).

    PROTOCOL.md §2 (framing); shared by the compiled host loop
    (:mod:`hapsim.host.fastloop`) and the compiled mock tick
    (:mod:`hapsim.emulated.fastmock`), which each apply their own overlong rule to
    ``z - a``.

    Parameters
    ----------
    rb : ndarray of uint8
        The bytes received.
    a : int
        Where the search starts.
    n_rb : int
        Bytes held in ``rb``.

    Returns
    -------
    a : int
        First byte of the frame (past any idle fill).
    z : int
        Its delimiter's index, or -1 when none has arrived yet.
    """
    while True:
        z = -1
        for j in range(a, n_rb):
            if rb[j] == 0:
                z = j
                break
        if z != a:
            return a, z
        a = z + 1                   # idle fill between frames


@jit
def cobs_decode(src, a, b, dst):
    """COBS-decode ``src[a:b]`` (no 0x00 in it) into ``dst``; its length, -1 when bad
    (Cheshire & Baker 1999, as the ``cobs`` package decodes).

    Parameters
    ----------
    src : ndarray of uint8
        Bytes holding the encoded frame.
    a, b : int
        The frame is ``src[a:b]``, delimiter excluded.
    dst : ndarray of uint8
        Receives the decoded bytes from index 0.

    Returns
    -------
    int
        Bytes decoded, or -1 for a code running past ``b`` or past ``dst``'s end.
    """
    i = a
    o = 0
    while i < b:
        code = np.int64(src[i])
        i += 1
        end = i + code - 1
        if end > b or o + code > dst.size:
            return -1
        for j in range(i, end):
            dst[o] = src[j]
            o += 1
        i = end
        if i < b and code < 0xFF:
            dst[o] = 0
            o += 1
    return o


@jit_helper
def cobs_encode(src, n, dst):
    """COBS-encode ``src[:n]`` (n < 254) into ``dst`` with the 0x00 delimiter; the length.

    Parameters
    ----------
    src : ndarray of uint8
        The packet.
    n : int
        Its length, < 254 (one code byte covers it: no 0xFF block).
    dst : ndarray of uint8, shape (>= n + 2,)
        Receives the encoded frame and its delimiter from index 0.

    Returns
    -------
    int
        Bytes written, ``n + 2`` (delimiter included).
    """
    code_at = 0
    o = 1
    code = 1
    for j in range(n):
        byte = src[j]
        if byte == 0:
            dst[code_at] = code
            code_at = o
            o += 1
            code = 1
        else:
            dst[o] = byte
            o += 1
            code += 1
    dst[code_at] = code
    dst[o] = 0
    return o + 1


# ----------------------------------------------------------------------------- host frames
#: Largest finite binary32 [N] (:data:`firmware_protocol.F32_MAX`): a compact FORCE
#: saturates there.
F32_MAX = fp.F32_MAX


@jit
def force_frame(seq, f, pkt, f8, u8, table, out):
    """FORCE(seq, (f,)) as a whole frame (PROTOCOL.md §4: type 0x11, seq, one binary64
    force, CRC-16, COBS, delimiter): :func:`firmware_protocol.encode` on bytes.

    Parameters
    ----------
    seq : int
        The STATE's seq it answers (32 bits).
    f : float
        Force [N].
    pkt : ndarray of uint8, shape (>= 15,)
        Scratch for the packet before COBS.
    f8, u8 : ndarray
        One float64 and its 8 bytes: the same memory (``u8 = f8.view(np.uint8)``).
    table : ndarray of uint16, shape (256,)
        :data:`CRC_TABLE`.
    out : ndarray of uint8, shape (>= 17,)
        The frame.

    Returns
    -------
    int
        The frame's length in ``out`` (17 bytes).
    """
    pkt[0] = 0x11
    for j in range(4):
        pkt[1 + j] = (seq >> (8 * j)) & 0xFF
    f8[0] = f
    for j in range(8):
        pkt[5 + j] = u8[j]
    c = crc16(pkt, 13, table)
    pkt[13] = (c >> 8) & 0xFF
    pkt[14] = c & 0xFF
    return cobs_encode(pkt, 15, out)


@jit
def force_compact_frame(seq, f, pkt, f4, u8, table, out):
    """FORCE_COMPACT(seq, (f,)) as a whole frame: :func:`firmware_protocol.compact_force`
    on bytes (PROTOCOL.md §4 "Compact frames"): the seq's low 16 bits, the force rounded
    to binary32 (to nearest, ties to even), a finite force beyond the binary32 range
    saturated to :data:`F32_MAX` with its sign.

    Parameters
    ----------
    seq : int
        The STATE's seq it answers (its low 16 bits are sent).
    f : float
        Force [N].
    pkt : ndarray of uint8, shape (>= 9,)
        Scratch for the packet before COBS.
    f4, u8 : ndarray
        One float32 and its 4 bytes: the same memory (``u8 = f4.view(np.uint8)``).
    table : ndarray of uint16, shape (256,)
        :data:`CRC_TABLE`.
    out : ndarray of uint8, shape (>= 11,)
        The frame.

    Returns
    -------
    int
        The frame's length in ``out`` (11 bytes).
    """
    pkt[0] = 0x14
    pkt[1] = seq & 0xFF
    pkt[2] = (seq >> 8) & 0xFF
    if (f > F32_MAX or f < -F32_MAX) and math.isfinite(f):
        f = math.copysign(F32_MAX, f)
    f4[0] = f
    for j in range(4):
        pkt[3 + j] = u8[j]
    c = crc16(pkt, 7, table)
    pkt[7] = (c >> 8) & 0xFF
    pkt[8] = c & 0xFF
    return cobs_encode(pkt, 9, out)


@jit
def expand_seq(s16, last):
    """The 32-bit seq of a STATE_COMPACT's 16-bit ``s16`` after the reference ``last``:
    :meth:`firmware_protocol.CompactExpander.expand` (the nearest seq at or after
    ``last`` whose low 16 bits are ``s16``, modulo 2^32).

    Parameters
    ----------
    s16 : int
        The frame's 16-bit seq.
    last : int
        The reference seq (< 0: none, ``s16`` is taken as is).

    Returns
    -------
    int
    """
    if last < 0:
        return s16
    return (last + ((s16 - last) & 0xFFFF)) & 0xFFFFFFFF
