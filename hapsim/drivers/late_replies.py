"""Late replies kept as readings: a reply read after its tick, with the replies after it,
recorded against the command it answers (issue 29; :class:`LateReplies`, a base of
:class:`hapsim.drivers.transport.DriverTransport`).

Firmware V1.5 of the Haply M3 answers every write it parses, in order, one reply each
(``Haply_M3_Firmware_V1_5.ino``, ``loop``: ``write_states`` then ``read_states``). Under
load a reply often misses its tick's deadline: the host loop steps that tick with an
*estimated* sample (``FLAG_ESTIMATED``, the position extrapolated from the two records
before) and writes its force, and the reply arrives with the next tick's. When one read
brings exactly as many replies as commands were unanswered (none damaged on the way), the
replies answer those commands in order (the transport's rule, the last answering the
newest, and the firmware's, the first answering the oldest unanswered, name the same
commands), so the estimated tick's command was parsed in step: its force is the one the
host sent, a known input, and the reply is a reading of the joint at that command. Such
replies are recorded in :attr:`LateReplies.late_answers` (``seq -> position``, shared
with the driver as ``driver.late_answers``), which the driver's account reads
(:meth:`hapsim.drivers.haply.HaplyM3.unknown_force_rows`: not cut). A read that brings
fewer replies than commands unanswered is ambiguous (a reply read alone may answer an
older command than the newest, or a write parsed out of step may have had none): nothing
is recorded, and the estimated rows stay cut as before.

The rows keep the position the loop stepped with (the estimate: what the engine saw), as
the 2DIY's record does (:func:`hapsim.pipeline.haply2_host.usable_rows`), and the
measurement states their error's worst case
(:func:`hapsim.analysis.measurement.estimated_bounds`).
"""

from __future__ import annotations

from hapsim.drivers.resync import RING

__all__ = ["LateReplies", "LATE_MAX"]

#: Late replies recorded at most (a run of 100 s at 1 kHz with every tick's reply late).
LATE_MAX = 1 << 17


class LateReplies:
    """The transport's record of replies that came late but in order (module notes).

    Attributes
    ----------
    late_answers : dict of int to float
        ``seq`` of an estimated tick -> the position [m or rad] its reply read, for the
        replies read together with every reply after them (module notes).
    """

    def _init_late(self, driver) -> None:
        """Start the record (no allocation per sample afterwards but one dict entry per
        late reply); ``driver.late_answers`` is the same dict."""
        self._est_seq = [-1] * RING
        self.late_answers: dict = {}
        driver.late_answers = self.late_answers

    def _mark_estimated(self, seq: int) -> None:
        """The host loop stepped command ``seq`` with an estimated sample."""
        self._est_seq[seq % RING] = seq

    def _note_late(self, first: int, xs: list, whole: bool) -> None:
        """Records ``xs`` read together, answering commands ``first, first + 1, ...``;
        ``whole``: they are every unanswered command's, none damaged (module notes).
        The estimated commands among them are recorded with their readings."""
        if not whole:
            return
        for k, x in enumerate(xs):
            s = first + k
            if self._est_seq[s % RING] == s and len(self.late_answers) < LATE_MAX:
                self.late_answers[s] = x
