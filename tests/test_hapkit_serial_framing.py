"""The Hapkit sketch's replies have no start byte and no checksum: a lost byte must cost a
reading, never make a false one (hapsim.drivers.hapkit_serial.ReplyDecoder, issue 29).

The class: a reply that lost a byte leaves its tail and the head of the next reply in the
decoder's window. Where the next reply's function byte is lost too, or where realigning
starts at a value byte equal to it, the window's floats can be plausible, and the host
took them as a fresh reading: in a lockstep run with 1 byte in 200 lost each way (seed
19) a reading of 1.1e-5 m where the handle was at 4.5 mm, and the measured k 6.9 % off
against a stated 5.2 %: "differs" for a device that matched its prediction. Now a window
is a reply only where the byte after it, when one has come, is a reply's function byte,
and one found by realigning waits for that byte.

The property, over seeded loss patterns at the issue's 1 byte in 200: every reading the
decoder gives is one the device sent, in order. The same streams through the decoder
without the check give false readings (the test can fail). The streams are read as the
host reads them from the pty and from a lockstep mock: whole replies, or several
together. What is left (no checksum: no decoder is exact): at 1 byte in 50, 1 false
reading in 300 runs of 375 replies (289 before), lost bytes in two replies in a row whose
lengths add up to a reply boundary; a read that ends inside a reply, as a hardware UART's
may, can end a straddling window with nothing after it (random read boundaries at 1 in
200: 4 false readings in 1000 runs, 77 before).
"""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.drivers import hapkit_serial as hk
from hapsim.emulated.driver_mock import ByteFaults

#: A run's replies: the free response of configs/hapkit_serial.yaml's loop (10 mm from
#: the wall, about 3.5 Hz, decaying), 375 rows at 250 Hz, and the spring's force.
N = 375


def _replies():
    t = np.arange(N) / 250.0
    x = 0.01 * np.exp(-2.0 * t) * np.cos(2 * np.pi * 3.5 * t)
    return x, -50.0 * x


def _decode(dec, seed: int, loss: float, per_read: int):
    """Readings the decoder gives for the run's replies with ``loss`` of their bytes lost
    (seeded), ``per_read`` replies read at a time; and the readings sent (binary32)."""
    x, f = _replies()
    faults = ByteFaults({"drop_tx": loss, "seed": seed})
    got, pending = [], b""
    for k in range(N):
        pending += faults.tx(hk.reply_packet(dec.function, x[k], f[k]))
        if (k + 1) % per_read == 0:
            got += dec.feed(pending)
            pending = b""
    got += dec.feed(pending)
    return got, np.float32(x).astype(float)


class _Unchecked(hk.ReplyDecoder):
    """The decoder before: any window that parses is a reply."""

    confirm_next = False


@pytest.mark.parametrize("per_read", [1, 2], ids=["whole", "pairs"])
def test_a_lost_byte_never_makes_a_false_reading(per_read):
    """Over 100 seeded loss patterns (1 byte in 200): every reading is a reply the device
    sent, in the order sent; the decoder without the check reads false ones on the same
    streams."""
    loss = 0.005
    false_before = 0
    lost = 0
    for seed in range(100):
        got, sent = _decode(hk.ReplyDecoder(), seed, loss, per_read)
        xs = np.array([g[0] for g in got])
        pos = {v: i for i, v in enumerate(sent.tolist())}
        order = [pos.get(v) for v in xs.tolist()]
        assert None not in order, (seed, [g for g, o in zip(got, order) if o is None])
        assert order == sorted(order), seed
        lost += N - len(order)
        old, _ = _decode(_Unchecked(), seed, loss, per_read)
        false_before += sum(g[0] not in pos for g in old)
    # the class is exercised: without the check these streams made false readings
    assert false_before > 0
    # a lost byte costs readings, not the run: most replies are still read
    assert lost < 0.5 * 100 * N


def test_a_reading_found_realigning_waits_for_the_next_reply():
    """Closed form: a reply that lost a byte, then whole replies read one at a time: the
    first whole reply after it is found by realigning and given only when the next one
    comes (a lost byte costs it a period), then both; none is made up."""
    dec = hk.ReplyDecoder()
    p = [hk.reply_packet(dec.function, 1e-3 * (k + 1), 0.1 * (k + 1)) for k in range(4)]
    assert [g[0] for g in dec.feed(p[0])] == [np.float32(1e-3)]
    assert dec.feed(p[1][:4] + p[1][5:]) == []          # 8 bytes: waits for a ninth
    assert dec.feed(p[2]) == []                         # realigned on it: waits
    got = dec.feed(p[3])
    assert [g[0] for g in got] == [np.float32(3e-3), np.float32(4e-3)]
    assert dec.stats["skipped"] == 8
