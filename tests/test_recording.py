"""The allowance live-sound tests take for xruns (:mod:`recording`): what a late client was
measured to do to a recording (a garbled period, then a lost one; a producer resuming one
period late) passes with the xruns it costs, and no more; a wrong sound never passes."""
from __future__ import annotations

import numpy as np
import pytest

from recording import assert_periods_match

BLOCK = 128
ATOL = 1e-6


def recorded(rng, ref, lead, events):
    """A recording of ``ref`` by a client copying whole periods, the sound starting
    ``lead`` frames in (silence before): ``events`` maps a recorded period to what befell
    it, "late" (the recording client copied a later period there and missed the next),
    "producer" (the producer missed a cycle: a silent period, the sound one period later)
    or "noise"."""
    timeline = np.concatenate([np.zeros(lead, ref.dtype), ref])
    out, k, p = [], 0, 0          # k: the timeline's frame recorded next
    while k < timeline.size:
        what = events.get(p)
        if what == "late":
            out.append(timeline[k + 2 * BLOCK:k + 3 * BLOCK])
            k += 2 * BLOCK
        elif what == "producer":
            out.append(np.zeros(BLOCK, ref.dtype))
        elif what == "noise":
            out.append(rng.standard_normal(BLOCK).astype(ref.dtype))
            k += BLOCK
        else:
            out.append(timeline[k:k + BLOCK])
            k += BLOCK
        p += 1
    return np.concatenate(out)


@pytest.mark.parametrize("seed", range(40))
def test_what_an_xrun_was_measured_to_do_passes_with_its_xruns_and_no_fewer(seed):
    """Random references, leads and 0-3 events, the first period of the sound among the
    places they strike: the recording passes with the xruns its anomalies take (a late
    client or producer: a garbled period and a move, two; a noisy period, one; at most two
    per xrun), fails with one xrun fewer, and a sound off by 10 atol from a random frame on
    (a wrong rendering) fails whatever the events allowed."""
    rng = np.random.default_rng(seed)
    ref = rng.standard_normal(int(rng.integers(40, 80)) * BLOCK).astype(np.float32)
    lead = int(rng.integers(0, 6 * BLOCK))
    first = -(-lead // BLOCK)            # the first period holding sound, or the one after
    count = int(rng.integers(0, 4))
    places = np.r_[first, np.arange(first + 4, ref.size // BLOCK - 8, 4)]
    at = rng.choice(places, size=count, replace=False)
    events = {int(p): str(rng.choice(["late", "producer", "noise"])) for p in at}
    rec = recorded(rng, ref, lead, events)
    cost = sum(1 if e == "noise" else 2 for e in events.values())
    xruns = -(-cost // 2)
    seen = assert_periods_match(rec, ref, BLOCK, xruns, ATOL)
    took = seen["moved"] + seen["garbled"]
    assert count <= took <= cost         # (a late first period anchors the later offset)
    assert seen["compared"] >= ref.size - (2 * count + 3) * BLOCK
    if took:
        with pytest.raises(AssertionError, match="xruns reported"):
            assert_periods_match(rec, ref, BLOCK, -(-took // 2) - 1, ATOL)
    wrong = rec.copy()
    start = int(rng.integers(lead, rec.size - 3 * (2 * count + 2) * BLOCK))
    wrong[start:] += 10 * ATOL
    with pytest.raises(AssertionError, match="xruns reported|anywhere"):
        assert_periods_match(wrong, ref, BLOCK, count, ATOL)


def test_with_no_xrun_one_frame_off_fails_and_every_frame_is_compared():
    """No xrun: the comparison is frame for frame in place (one frame off by 2 atol fails,
    by atol passes), every frame the reference holds is compared, and the sound's start is
    found where it is (a lead of 3 periods and 17 frames)."""
    ref = np.linspace(-1, 1, 20 * BLOCK).astype(np.float32)
    rec = np.r_[np.zeros(3 * BLOCK + 17, np.float32), ref[:-5]]
    assert assert_periods_match(rec, ref, BLOCK, 0, ATOL) == {
        "offset": 3 * BLOCK + 17, "compared": ref.size - 5 + 17,   # (17: silence before)
        "moved": 0, "garbled": 0}
    rec[3 * BLOCK + 17 + 700] += ATOL
    assert_periods_match(rec, ref, BLOCK, 0, 2 * ATOL)
    rec[3 * BLOCK + 17 + 700] += 2 * ATOL
    with pytest.raises(AssertionError, match=f"at frame {8 * BLOCK}"):   # its period
        assert_periods_match(rec, ref, BLOCK, 0, 2 * ATOL)
