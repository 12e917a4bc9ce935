"""What an xrun may do to a recording a JACK client of ours made, and no more.

Measured on a private ``jackd -d dummy`` (48 kHz, 256-frame periods), with the recording
client's Python callback made late on purpose (12 ms, every 40th cycle): the period it
was copying when it fell behind is not the one the producer wrote (the server had moved
on), and JACK then skips that client for the next cycle (its ``last_frame_time`` steps by
two periods), so **one period is missing from the recording and every later frame comes
one period early**. Over a 2.7 s run, 4 late callbacks: 6 xruns reported, 4 periods
garbled and 4 lost. A third, unconnected client made late the same way caused 6 xruns
and no frame off; the producer's own callback made late, 12 xruns and no frame off.

A fresh-clone suite failed so (3 xruns, 13,952 frames off of a pluck), where the earlier
allowance (:func:`without_xrun_periods`: one period of frames off per xrun, the rest in
place) assumed an xrun garbles a period but never moves the frames after it.

:func:`assert_periods_match` allows what was measured: each period the client recorded
must equal the reference frame for frame, at an offset that moves only by whole periods;
each period moved and each period matching at no offset is one anomaly, and there may be
at most two per xrun reported (a late client garbles one period and loses the next).
With no xrun, every frame is compared in place.
"""
from __future__ import annotations

import numpy as np


def assert_periods_match(seg, ref, phase, block, xruns, atol):
    """Every recorded period is the reference's, at an offset moved only by xruns.

    Parameters
    ----------
    seg : numpy.ndarray, shape (n,)
        The recording from its first frame to compare on; ``seg[0]`` is ``ref[0]`` when
        nothing was lost before it.
    ref : numpy.ndarray, shape (r,)
        The reference frames (the offline rendering), from the one ``seg[0]`` should be.
    phase : int
        Where ``seg[0]`` lies in the recording client's period: the recording's index of
        ``seg[0]`` modulo ``block`` (the client copies one whole period per callback).
    block : int
        The server's period [frames], > 0.
    xruns : int
        Xruns the server reported while the recording ran.
    atol : float
        Largest difference of one frame from its reference (a derived round-off bound).

    Returns
    -------
    dict
        ``compared`` (frames compared equal), ``moved`` (periods the offset moved, summed
        in absolute value) and ``garbled`` (periods matching at no offset).

    Raises
    ------
    AssertionError
        More than ``2 * xruns`` anomalies (with no xrun: any frame off), a period that
        moved or matched nowhere named with its first frame, or nothing compared.
    """
    seg = np.asarray(seg)
    ref = np.asarray(ref)
    budget = 2 * int(xruns)
    assert block > 0 and 0 <= phase < block, (block, phase)
    edges = [0, *range(block - phase if phase else block, seg.size, block), seg.size]
    periods = list(zip(edges[:-1], edges[1:]))

    def at(p, k):
        # frames compared equal when period p is ref's moved by k periods (0: one differs;
        # None: the reference holds none of its frames there)
        a, e = periods[p]
        lo, hi = max(a, -k * block), min(e, ref.size - k * block)
        if lo >= hi:
            return None
        ok = np.all(np.abs(seg[lo:hi] - ref[lo + k * block:hi + k * block]) <= atol)
        return hi - lo if ok else 0

    shift = moved = garbled = compared = 0
    events = []
    for p, (a, _) in enumerate(periods):
        if a + shift * block >= ref.size:
            break                        # past the reference's end: nothing more to compare
        got = at(p, shift)
        if got is None or got:
            compared += got or 0
            continue
        # a period off: where do this one and the next one sit? A late recording client
        # garbles the period it copies (it may hold frames of a later one) and loses the
        # next, so the offset the next period takes is the one the recording moved to
        left = budget - moved - garbled
        tries = sorted((k for k in range(shift - left, shift + left + 1) if k != shift),
                       key=lambda k: (abs(k - shift), k))
        here = next((k for k in tries if at(p, k)), None)
        after = (None if p + 1 == len(periods) else
                 next((k for k in [shift, *tries] if at(p + 1, k)), None))
        if here is not None and (after is None or after == here):
            moved += abs(here - shift)
            events.append(f"moved {here - shift:+d} period(s) at frame {a}")
            shift = here
            compared += at(p, shift)
        else:
            garbled += 1
            events.append(f"period at frame {a} matches no offset the next one takes")
            if after is not None and after != shift:
                moved += abs(after - shift)
                events.append(f"moved {after - shift:+d} period(s) after frame {a}")
                shift = after
        assert moved + garbled <= budget, (
            f"{moved} period(s) moved and {garbled} garbled with {xruns} xruns reported "
            f"(at most 2 per xrun): {events[:8]}")
    assert compared > 0, "no recorded frame was compared"
    return {"compared": compared, "moved": moved, "garbled": garbled}
