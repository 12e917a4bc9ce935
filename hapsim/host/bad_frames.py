"""The record of the frames a run's decoder dropped: when (sample, time), which bytes, what
came before them and what followed (:attr:`hapsim.host.loop_types.LoopResult.bad_frames`).

:class:`BadFrames` is the part of :class:`hapsim.host.loop.HostLoop` that keeps it: a
snapshot of the decoder's last frames whenever its bad-frame count moves (rare: only on a
fault, so nothing is copied per sample), formatted once at the end.
"""

from __future__ import annotations

from hapsim.host.loop_types import BAD_FRAME_CONTEXT, BAD_FRAME_RECORDS

__all__ = ["BadFrames", "bad_count"]


def bad_count(ds) -> int:
    """Frames a decoder dropped so far.

    Parameters
    ----------
    ds : firmware_protocol.DecoderStats
        The decoder's counters.

    Returns
    -------
    int
        Frames with a bad CRC or COBS, overlong, malformed or of an unknown type.
    """
    return ds.bad_crc + ds.bad_cobs + ds.overlong + ds.malformed + ds.unknown_type


class BadFrames:
    """Bad-frame snapshots and their records (a base of
    :class:`~hapsim.host.loop.HostLoop`)."""

    # ------------------------------------------------------------------ bad frames
    def _check_bad(self) -> None:
        """Snapshot the decoder's last frames if its bad-frame count changed (rare: only
        on a fault, so the copy is not paid per sample)."""
        ds = self._dstats
        if ds is None:
            return
        n = bad_count(ds)
        if n != self._nbad:
            self._snap_bad(n)

    def _snap_bad(self, n: int) -> int:
        """Record that the bad-frame count is now ``n``: sample, time and the references of
        the decoder's last frames (formatted later by :meth:`_bad_frame_records`).

        Parameters
        ----------
        n : int
            The decoder's bad-frame count now.

        Returns
        -------
        int
            ``n``.
        """
        delta = n - self._nbad
        self._nbad = n
        self._bad_snaps.append((self.tel.n, self._clock() - self._t0, delta,
                                tuple(self.transport.decoder.last_frames)))
        return n

    def _bad_frame_records(self) -> list:
        """The recorded bad frames as dicts (see :attr:`LoopResult.bad_frames`)."""
        out = []
        lost = {}
        for ev in self.result.events:
            if ev["event"] in ("lost", "lost again"):
                lost.setdefault(ev["sample"], ev.get("reason", ""))
        for sample, t, delta, frames in self._bad_snaps:
            bad = [j for j, (_, oc) in enumerate(frames) if oc != "ok"][-delta:]
            outcome = "dropped" if sample not in lost else f"dropped; then lost: {lost[sample]}"
            for _ in range(delta - len(bad)):
                out.append({"sample": sample, "t": round(t, 6), "kind": "unrecorded",
                            "hex": "", "before": [], "outcome": outcome})
            for j in bad:
                raw, oc = frames[j]
                out.append({"sample": sample, "t": round(t, 6), "kind": oc,
                            "hex": raw.hex(" "),
                            "before": [f"{o}: {r.hex(' ')}"
                                       for r, o in frames[max(j - BAD_FRAME_CONTEXT, 0):j]],
                            "outcome": outcome})
        return out[-BAD_FRAME_RECORDS:]
