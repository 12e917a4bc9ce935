"""What a run's link did to its verdict: a run whose device left its workspace, or whose
board was re-synchronised more often than stated, does not say "within".

A measurement compares the free response the host recorded with the THS prediction
(Florens, Voda & Urma). Two things make the record something else than that loop:

- **a safety stop**: ``|x|`` beyond the scene's ``safety.position_limit``, a speed or
  an energy beyond theirs, or a host or link that fell behind the device (the lateness
  guard, a driver's lateness stop) ended the loop; the record before it is a loop that
  ran away or one with another delay, not the THS (the verdict names which,
  :func:`stop_cause`). A stop on the host's own force
  clamp (:data:`CLAMP_STOP`: the force at the limit in half the last samples) is not
  one: the device stayed inside its bounds and every clamped force is a known input of
  the measurement (replayed from the logged positions, or its rows left out,
  :mod:`hapsim.pipeline.contact_replay`), so its pair is measured as far as the record
  went; the stop is still in the report, and the run exits 1 for it;
- **re-synchronisations**: an unframed board (the Haply M3 and 2DIY: no framing, no
  watchdog) that lost its place is put back in step with zero torque and a set-up whose
  encoder offset is the host's estimate of where the joint is
  (:meth:`hapsim.drivers.resync.Resynchronising._resync`). Between the last reply
  and the set-up's, the joint moves blind: each re-synchronisation re-anchors the angle
  the host reads by the estimate's error, which nothing in the record shows. A few in a
  run are a few gaps in ``seq`` the measurement does not run across; many are a record
  whose positions the host no longer knows, and a joint that may have turned anywhere
  (issue 29: 48 to 1,361 in a 2.8 s run, the joint turned 1 to 12.5 rad, the report said
  "within").

The bound is stated per second of the run, :data:`MAX_RESYNCS_PER_S`, from what one
costs: a re-synchronisation leaves the joint blind (zero torque, no reading) from the last
reply to the set-up's, at least :data:`RESYNC_BLIND_S`: the firmware's ``new
Encoder(...)`` waits 2 ms (``delayMicroseconds(2000)`` in the Encoder library it ships);
the resets before it take the board's passes of at least 50 us each (``loop``: ``micros()
- lastPublished >= 50``): about 1 ms for the Haply M3's 62 bytes, 14 ms for the 2DIY's
556 zeros. At the
bound, at least :data:`BLIND_SHARE` of the run may be blind. It is the rate at which the
1-DoF driver's transport gives the link up altogether (``MAX_RESYNCS_PER_S`` of
:mod:`hapsim.drivers.resync`, 50 within any second); one host byte lost in 200 costs
the Haply M3 a re-synchronisation per byte lost, 30 a second at 1 kHz (6-byte writes:
18 to 32 in a 1 s run measured with ``tools/driver_timing.py``), within it.
Beyond it the verdict is "not measurable"
with the reason, ``within`` is False and ``hapsim run`` exits 1 (its documented code for
a device fault: the link is not fit for a measurement).
"""

from __future__ import annotations

import math

__all__ = ["MAX_RESYNCS_PER_S", "RESYNC_BLIND_S", "BLIND_SHARE", "CLAMP_STOP",
           "resync_bound", "link_verdict", "left_workspace", "stop_cause"]

#: How a stop on the host's force clamp begins (:func:`hapsim.host.loop.safety_reason`).
CLAMP_STOP = "safety: force at the limit"

#: Shortest time a re-synchronisation leaves the joint blind [s] (module notes).
RESYNC_BLIND_S = 0.002
#: Largest share of a run its re-synchronisations may leave blind and the run still state
#: a verdict.
BLIND_SHARE = 0.1
#: Re-synchronisations per second of the run beyond which its verdict is "not
#: measurable": :data:`BLIND_SHARE` / :data:`RESYNC_BLIND_S` (module notes).
MAX_RESYNCS_PER_S = BLIND_SHARE / RESYNC_BLIND_S


def resync_bound(ticks: int, rate_hz: float) -> int:
    """The re-synchronisations a run of ``ticks`` host ticks may have and still state a
    verdict: :data:`MAX_RESYNCS_PER_S` times its duration, rounded down, at least 1.

    Parameters
    ----------
    ticks : int
        Host ticks the run lasted.
    rate_hz : float
        The scene's rate [Hz].

    Returns
    -------
    int
    """
    dur = max(int(ticks), 0) / float(rate_hz)
    # (rounded to 9 digits before the floor: a product a unit in the last place below a
    # whole number is that number)
    return max(1, int(math.floor(round(MAX_RESYNCS_PER_S * dur, 9))))


def link_verdict(measured: dict, loop: dict) -> bool:
    """Withdraw a run's "within" when its link did not keep the loop it measured (module
    notes); in place.

    Parameters
    ----------
    measured : dict
        :func:`hapsim.pipeline.measure.identify_run`'s result (``within``, ``verdict``).
    loop : dict
        The report's ``loop`` section: ``safety_stop``, ``stop_reason``, ``ticks``,
        ``rate_hz`` and the driver's ``driver.resyncs`` (None for the framed link).

    Returns
    -------
    bool
        True when the link failed the run by re-synchronisations (the caller exits 1);
        ``measured`` then has ``within`` False, ``verdict`` "not measurable: ...",
        ``link`` (``resyncs``, ``resync_bound``, ``reason``). A safety stop that left
        the workspace (:func:`left_workspace`) withdraws "within" too and returns False
        (its exit code is the safety stop's own).
    """
    dl = loop.get("driver") or {}
    resyncs = int(dl.get("resyncs", 0) or 0)
    bound = resync_bound(int(loop.get("ticks") or 0), float(loop.get("rate_hz") or 1.0))
    reasons = []
    failed = False
    if left_workspace(loop):
        reason = str(loop.get("stop_reason") or "")
        reasons.append(f"the run ended on a safety stop ({reason}): {stop_cause(reason)}, "
                       "the record is no free response of the loop")
    if dl and resyncs > bound:
        failed = True
        reasons.append(f"the board was re-synchronised {resyncs} times, more than the "
                       f"{bound} allowed ({MAX_RESYNCS_PER_S:g} a second): the positions "
                       "after each are the host's estimate, the joint moved blind between")
    measured["link"] = {"resyncs": resyncs, "resync_bound": bound,
                        "reason": "; ".join(reasons) or None}
    if reasons:
        measured["within"] = False
        measured["verdict"] = "not measurable: " + "; ".join(reasons)
    return failed


#: A safety stop's beginning, and what it says of the record (:func:`stop_cause`).
_CAUSES = (
    ("safety: position", "the device left its workspace"),
    ("safety: velocity", "the device passed its speed limit"),
    ("safety: leg", "the device left its workspace"),
    ("safety: fader", "the device left its workspace"),
    ("safety: the handle went", "the device left its workspace"),
    ("safety: the host's FORCEs came too late",
     "the device held the host's forces longer than the scene's delay"),
    ("safety: the host was", "the host fell behind the device's rate"),
    ("safety: the scene gave the hand", "the scene gave the hand more energy than its limit"),
    ("safety: non-finite", "a position or force was not finite"),
)


def stop_cause(stop_reason: str) -> str:
    """What a safety stop says of its run's record, for the verdict's reason.

    Parameters
    ----------
    stop_reason : str
        The run's ``stop_reason`` (the host loop's :func:`hapsim.host.loop.safety_reason`,
        the lateness guard's, a driver's or an emulated board's safety stop).

    Returns
    -------
    str
        E.g. "the device left its workspace" for a position bound, "the device held the
        host's forces longer than the scene's delay" for the lateness guard; "the run
        stopped before its end" for a reason not listed.
    """
    for head, cause in _CAUSES:
        if stop_reason.startswith(head):
            return cause
    return "the run stopped before its end"


def left_workspace(loop: dict) -> bool:
    """Whether a run's safety stop withdraws its verdict: every safety stop but the host's
    force clamp alone (module notes): the device left its workspace or its limits
    (position, speed, the energy given to the hand), or the host or the link fell behind
    it (:func:`stop_cause` says which).

    Parameters
    ----------
    loop : dict
        The report's ``loop`` section (``safety_stop``, ``stop_reason``).

    Returns
    -------
    bool
    """
    if not loop.get("safety_stop"):
        return False
    return not str(loop.get("stop_reason") or "").startswith(CLAMP_STOP)
