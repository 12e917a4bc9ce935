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
must equal the reference frame for frame, at an offset found by its content (the first
period with sound, which may itself be garbled, so no frame is taken as the sound's start)
and moving afterwards only by whole periods; each period moved and each period matching at
no offset is one anomaly, and there may be at most two per xrun reported (a late client
garbles one period and loses the next). With no xrun, every frame is compared in place.
"""
from __future__ import annotations

import numpy as np


def assert_periods_match(rec, ref, block, xruns, atol):
    """Every recorded period is the reference's, at an offset moved only by xruns.

    Parameters
    ----------
    rec : numpy.ndarray, shape (n,)
        The whole recording, from the recording client's first armed period (it copies
        one whole period per callback: period ``p`` is ``rec[p * block:(p + 1) * block]``).
    ref : numpy.ndarray, shape (r,)
        The reference frames (the offline rendering); silence before its first frame, none
        compared after its last.
    block : int
        The server's period [frames], > 0.
    xruns : int
        Xruns the server reported while the recording ran.
    atol : float
        Largest difference of one frame from its reference (a derived round-off bound);
        a frame no larger is silence.

    Returns
    -------
    dict
        ``offset`` (the recording's index of ``ref[0]`` where the first sound matched),
        ``compared`` (frames compared equal), ``moved`` (periods the offset moved, summed
        in absolute value) and ``garbled`` (periods matching at no offset).

    Raises
    ------
    AssertionError
        More than ``2 * xruns`` anomalies (with no xrun: any frame off), listed with the
        first frame of each; or no sound recorded that matches the reference anywhere.
    """
    rec = np.asarray(rec)
    ref = np.asarray(ref)
    budget = 2 * int(xruns)
    assert block > 0, block
    periods = [(a, min(a + block, rec.size)) for a in range(0, rec.size, block)]

    def at(p, d):
        # frames compared equal when period p holds ref from the recording's index d on
        # (0: one differs; None: the reference holds none of its frames there)
        a, e = periods[p]
        lo, hi = a, min(e, ref.size + d)
        if lo >= hi:
            return None
        j = np.arange(lo, hi) - d
        want = np.where(j >= 0, ref[np.clip(j, 0, ref.size - 1)], 0)
        return hi - lo if np.all(np.abs(rec[lo:hi] - want) <= atol) else 0

    def found(p):
        # where period p's first sound is in the reference: the offsets its frames match at
        a, e = periods[p]
        loud = np.flatnonzero(np.abs(rec[a:e]) > atol)
        if not loud.size:
            return None
        i = a + int(loud[0])
        for j in np.flatnonzero(np.abs(ref - rec[i]) <= atol):
            if at(p, i - int(j)):
                return i - int(j)
        return None

    offset = shift = None
    moved = garbled = compared = 0
    events = []
    for p, (a, e) in enumerate(periods):
        if shift is None:
            if not np.any(np.abs(rec[a:e]) > atol):
                continue                 # silence before the sound
            shift = offset = found(p)
            if shift is None:
                garbled += 1
                events.append(f"period at frame {a} matches the reference nowhere")
            else:
                compared += at(p, shift)
        elif a - shift >= ref.size:
            break                        # past the reference's end: nothing more to compare
        else:
            got = at(p, shift)
            if got is None or got:
                compared += got or 0
                continue
            # a period off: where do this one and the next one sit? A late recording
            # client garbles the period it copies (it may hold frames of a later one) and
            # loses the next, so the offset the next period takes is where it moved to
            left = budget - moved - garbled
            tries = sorted((shift + m * block for m in range(-left, left + 1) if m),
                           key=lambda d: (abs(d - shift), d))
            here = next((d for d in tries if at(p, d)), None)
            after = (None if p + 1 == len(periods) else
                     next((d for d in [shift, *tries] if at(p + 1, d)), None))
            if here is not None and (after is None or after == here):
                moved += abs(here - shift) // block
                events.append(f"moved {(shift - here) // block:+d} period(s) at frame {a}")
                shift = here
                compared += at(p, shift)
            else:
                garbled += 1
                events.append(f"period at frame {a} matches no offset the next one takes")
                if after is not None and after != shift:
                    moved += abs(after - shift) // block
                    events.append(f"moved {(shift - after) // block:+d} period(s) after "
                                  f"frame {a}")
                    shift = after
        assert moved + garbled <= budget, (
            f"{moved} period(s) moved and {garbled} garbled with {xruns} xruns reported "
            f"(at most 2 per xrun): {events[:8]}")
    assert compared > 0, "no recorded sound matches the reference anywhere"
    return {"offset": offset, "compared": compared, "moved": moved, "garbled": garbled}
