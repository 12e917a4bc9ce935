"""The allowance live-sound tests take for xruns (:mod:`recording`): what a late client was
measured to do to a recording (a garbled period, then a lost one; a producer resuming one
period late) passes with the xruns it costs, and no more; a wrong sound never passes."""
from __future__ import annotations

import numpy as np
import pytest

from recording import assert_periods_match

BLOCK = 128
ATOL = 1e-6


def recorded(rng, ref, phase, events):
    """A recording of ``ref`` by a client copying whole periods, starting ``phase`` frames
    into one: ``events`` maps a recorded period to what befell it, "late" (the recording
    client copied a later period there and missed the next), "producer" (the producer
    missed a cycle: a silent period, the sound one period later) or "noise"."""
    out, k, p = [], 0, 0          # k: the reference's frame recorded next
    first = BLOCK - phase
    while k < ref.size:
        size = first if p == 0 else BLOCK
        what = events.get(p)
        if what == "late":
            out.append(ref[k + 2 * size:k + 3 * size])
            k += 2 * size
        elif what == "producer":
            out.append(np.zeros(size, ref.dtype))
        elif what == "noise":
            out.append(rng.standard_normal(size).astype(ref.dtype))
            k += size
        else:
            out.append(ref[k:k + size])
            k += size
        p += 1
    return np.concatenate(out)


@pytest.mark.parametrize("seed", range(40))
def test_what_an_xrun_was_measured_to_do_passes_with_its_xruns_and_no_fewer(seed):
    """Random references, phases and 0-3 events: the recording passes with the xruns its
    anomalies take (a late client or producer: a garbled period and a move, two; a noisy
    period, one; at most two per xrun), fails with one xrun fewer, and a sound off by 10
    atol from a random frame on (a wrong rendering) fails whatever the events allowed."""
    rng = np.random.default_rng(seed)
    ref = rng.standard_normal(int(rng.integers(40, 80)) * BLOCK).astype(np.float32)
    phase = int(rng.integers(0, BLOCK))
    count = int(rng.integers(0, 4))
    at = rng.choice(np.arange(2, ref.size // BLOCK - 8, 4), size=count, replace=False)
    events = {int(p): str(rng.choice(["late", "producer", "noise"])) for p in at}
    rec = recorded(rng, ref, phase, events)
    cost = sum(1 if e == "noise" else 2 for e in events.values())
    xruns = -(-cost // 2)
    seen = assert_periods_match(rec, ref, phase, BLOCK, xruns, ATOL)
    assert seen["moved"] + seen["garbled"] == cost
    assert seen["compared"] >= ref.size - (2 * count + 3) * BLOCK
    if cost:
        with pytest.raises(AssertionError, match="xruns reported"):
            assert_periods_match(rec, ref, phase, BLOCK, xruns - 1, ATOL)
    wrong = rec.copy()
    start = int(rng.integers(0, rec.size - 3 * (2 * count + 2) * BLOCK))
    wrong[start:] += 10 * ATOL
    with pytest.raises(AssertionError, match="xruns reported"):
        assert_periods_match(wrong, ref, phase, BLOCK, count, ATOL)


def test_with_no_xrun_one_frame_off_fails_and_every_frame_is_compared():
    """No xrun: the comparison is frame for frame in place (one frame off by 2 atol fails,
    by atol passes), and every frame the reference holds is compared."""
    ref = np.linspace(-1, 1, 20 * BLOCK).astype(np.float32)
    rec = ref[:-5].copy()
    assert assert_periods_match(rec, ref, 17, BLOCK, 0, ATOL) == {
        "compared": rec.size, "moved": 0, "garbled": 0}
    rec[700] += ATOL
    assert_periods_match(rec, ref, 17, BLOCK, 0, 2 * ATOL)
    rec[700] += 2 * ATOL
    with pytest.raises(AssertionError, match="at frame 623"):  # its period: 111 + 4 * 128
        assert_periods_match(rec, ref, 17, BLOCK, 0, 2 * ATOL)
