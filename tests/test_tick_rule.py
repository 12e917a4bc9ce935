"""The late-tick rule (hapsim.kernels.ticks) is one: the Python host loop, the compiled host
loop and the account of the record (hapsim.applied.account_from_force_seq) flag the same
ticks of a scripted STATE stream with seeded random late ticks (0-50 %, of every kind the
protocol has: an older FORCE held with or without OVERRUN, no FORCE applied yet, the
watchdog's zero force, a stale force_seq ahead), for a device that sets FORCE_APPLIED and
one written before the bit existed, at any delay. The measurement from that account
(measured = predicted to 1e-6 with late ticks) is tests/test_identify_late.py's."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import firmware_protocol as fp
from hapsim.applied import account_from_force_seq
from hapsim.host.fastloop import CompiledHostLoop
from hapsim.host.loop import HostLoop
from hapsim.kernels.ticks import late_ticks, named_delay, tick_late
from test_compiled_loop import chunked, run_loop  # same directory (pytest prepend mode)

A = fp.STATUS_FORCE_APPLIED
U32 = 0xFFFFFFFF


def late_stream(rng, n: int, d: int, frac: float, uses_bit: bool):
    """STATEs 0..n-1 of a device with delay ``d`` whose FORCEs miss their tick in bursts
    (about ``frac`` of the ticks); (frames, fields): ``fields`` the (seq, force_seq,
    status) of each STATE and whether the test's own reading calls it late."""
    frames, fields = [], []
    applied = None                        # seq of the FORCE held (None: none yet)
    burst = 0
    for s in range(n):
        x = 0.003 * math.sin(s / 30.0)
        status = fp.STATUS_ARMED
        kind = "on time"
        if s >= d:
            if burst == 0 and rng.random() < frac / 4.0:
                burst = int(rng.integers(1, 9))
            if burst:
                burst -= 1
                kind = ("held", "overrun", "watchdog", "ahead")[int(rng.integers(0, 4))]
            else:
                applied = s - d
        if kind == "overrun":
            status |= fp.STATUS_OVERRUN
        elif kind == "watchdog":
            status |= fp.STATUS_WATCHDOG_TRIPPED
        fseq = 0 if applied is None else applied
        if kind == "ahead":
            fseq = s + 3                  # a stale field ahead of the STATE: names nothing
        if applied is not None and uses_bit:
            status |= A
        fields.append((s, fseq & U32, status, s >= d and kind != "on time"
                       and not (d == 0 and kind != "overrun")))
        frames.append((s, fp.encode(fp.State(s, 1000 * s + 17, status, fseq & U32, (x,)))))
    return frames, fields


def test_rule_closed_cases():
    """The rule on its own: due from seq >= d; OVERRUN late at any delay; d = 0 reads
    nothing else; the watchdog's zero late; FORCE_APPLIED clear names nothing once the
    device is known to set it; a force_seq ahead names nothing."""
    assert not tick_late(1, 0, 0, 2, True)                    # not due yet
    assert tick_late(2, 0, 0, 2, True)                        # due, none applied
    assert not tick_late(2, 0, A, 2, True)                    # FORCE 0 at tick 2
    assert not tick_late(2, 0, 0, 2, False)                   # a device without the bit
    assert tick_late(5, 2, A | fp.STATUS_OVERRUN, 3, True)
    assert tick_late(5, 2, A | fp.STATUS_WATCHDOG_TRIPPED, 3, True)
    assert tick_late(5, 4, fp.STATUS_OVERRUN, 0, False)       # d = 0: OVERRUN only
    assert not tick_late(5, 4, A, 0, True)
    assert named_delay(5, 8, A, True) == -1 and tick_late(5, 8, A, 3, True)
    assert named_delay(1, U32, A, True) == 2                  # mod 2^32
    assert named_delay(7, -1, A, True) == -1                  # no force_seq carried


@settings(max_examples=3, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), frac=st.floats(0.0, 0.5), d=st.integers(0, 4),
       uses_bit=st.booleans())
def test_python_loop_compiled_loop_and_account_flag_the_same_ticks(seed, frac, d, uses_bit):
    """Property: on a scripted STATE stream with seeded random late ticks, the Python loop
    and the compiled loop log the same ``late`` column and count, equal to the rule's own
    reading of the stream (``late_ticks`` with the loop's knowledge) and to the test's
    reading of how the stream was made; the account of the logged record says the same
    late ticks and the device's delay, with one documented exception: a device that sets
    FORCE_APPLIED and applied nothing at tick d, which only the whole record shows late."""
    rng = np.random.default_rng(seed)
    n = 260
    frames, fields = late_stream(rng, n, d, frac, uses_bit)
    runs = [run_loop(cls, [chunked(frames, rng)], n - 2, delay=d, position_bound=0.05)
            for cls in (HostLoop, CompiledHostLoop)]
    (ra, ta, _, la), (rb, tb, _, lb) = runs
    assert lb.compiled and not getattr(la, "compiled", False)
    ca, cb = ta.columns(), tb.columns()
    np.testing.assert_array_equal(ca["seq"], np.arange(n - 2))
    np.testing.assert_array_equal(ca["late"], cb["late"])
    assert ra.late == rb.late == int(np.count_nonzero(ca["late"]))
    seq, fseq, status, made_late = (np.array(c, np.int64) for c in zip(*fields[:n - 2]))
    tick, late, flags = (np.empty(n - 2, np.int64), np.zeros(n - 2, bool),
                         np.zeros(n - 2, bool))
    late_ticks(seq, fseq, status, d, False, tick, late, flags)
    np.testing.assert_array_equal(ca["late"] != 0, late)
    # the stream's own truth, but for the ambiguity no reader of the stream so far can
    # resolve: force_seq = 0 without FORCE_APPLIED at tick d ("FORCE 0 or none yet")
    made = made_late.astype(bool)
    ambiguous = (seq == d) & (d > 0) & (fseq == 0) & (status & A == 0) & made
    np.testing.assert_array_equal(late | ambiguous, made)
    acc = account_from_force_seq(cb["seq"], cb["force"], cb["force_seq"], cb["status"],
                                 zero_delay=d == 0)
    # the whole record resolves it when the device sets the bit on a later row
    np.testing.assert_array_equal(acc.late, late | (ambiguous & bool(np.any(status & A))))
    if d > 0 and np.any(~made[d:]):
        assert acc.delay == d


@settings(max_examples=100, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2 ** 32 - 1), frac=st.floats(0.0, 0.5), d=st.integers(0, 6),
       uses_bit=st.booleans())
def test_the_rule_reads_every_stream_as_it_was_made(seed, frac, d, uses_bit):
    """Property, on the rule alone (no loop: cheap, so over many streams, every delay
    0-6 and both kinds of device): ``late_ticks`` with a loop's knowledge flags exactly
    the ticks the stream made late, but for the one documented ambiguity (force_seq 0
    without FORCE_APPLIED at tick d), and the account of the record flags the same,
    resolving the ambiguity from the later rows as documented."""
    rng = np.random.default_rng(seed)
    n = 200
    _, fields = late_stream(rng, n, d, frac, uses_bit)
    seq, fseq, status, made = (np.array(c, np.int64) for c in zip(*fields))
    made = made.astype(bool)
    tick, late, flags = np.empty(n, np.int64), np.zeros(n, bool), np.zeros(n, bool)
    late_ticks(seq, fseq, status, d, False, tick, late, flags)
    ambiguous = (seq == d) & (d > 0) & (fseq == 0) & (status & A == 0) & made
    np.testing.assert_array_equal(late | ambiguous, made)
    acc = account_from_force_seq(seq, np.zeros(n), fseq, status, zero_delay=d == 0)
    np.testing.assert_array_equal(acc.late, late | (ambiguous & bool(np.any(status & A))))
    if d > 0 and np.any(~made[d:]):
        assert acc.delay == d
