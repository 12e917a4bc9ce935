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
    """The transport's record of replies that came late but in order (module notes), and
    the pairing of a reply read after the next write with its own command
    (:meth:`_answer_shift`).

    Attributes
    ----------
    late_answers : dict of int to float
        ``seq`` of an estimated tick -> the position [m or rad] its reply read, for the
        replies read together with every reply after them (module notes).
    """

    def _init_late(self, driver) -> None:
        """Start the record (no allocation per sample afterwards but one dict entry per
        late reply); ``driver.late_answers`` is the same dict; the pairing's state."""
        self._est_seq = [-1] * RING
        self.late_answers: dict = {}
        driver.late_answers = self.late_answers
        # each command's bytes (by seq), and the least time from a write to its answer
        # [us] (Driver.least_answer_s): what pairs an answer with its command
        # (_answer_shift)
        self._sent_bytes = [b""] * RING
        self._rt_us = int(driver.least_answer_s() * 1e6)
        # the last pairing the echo named (its shift), and the first command after it
        self._named_shift = 0
        self._named_at = 0

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

    def _answer_shift(self, n: int) -> int:
        """By how many commands the last of ``n`` answers read now is older than the newest
        command sent: 1 where it cannot be the newest's, else 0.

        A board that answers later than the next write (the Hapkit sketch at 4 ticks a
        period answers 3.75-4.3 ms after a write, a period being 3.97 ms) had every reading
        taken one command off by the rule "the last answers the newest" alone: a loop of
        one delay more than the scene's, measured as the scene's. The evidence, in order:

        1. the echo (:meth:`Driver.answer_names`: the sketch's reply carries the force it
           rendered): it is the one before the newest's where it names that command and
           not the newest, the newest's where it names the newest and not the one before
           -- whatever was paired before. An answer so named for a command already
           answered shows that a pairing since the last named one took an answer for the
           command after its own (the rows from there are put in :attr:`mistimed`, cut
           by the measurement; counted in ``mispaired``): an idle host reads at its
           deadlines, long after the answer came, and before, one run of equal forces
           (the excitation's hold) left every later reading one command off while the
           echo was not asked (the one before the newest taken as answered);
        2. where the echo tells neither (equal forces): the answer was read sooner after
           the newest write than the board can answer any command
           (:meth:`Driver.least_answer_s`: the bytes of both on the wire, the least
           render): the one before's;
        3. else, while the command before the newest is unanswered, the last named
           pairing's shift (the board's answer time is its own: it stays), else 0.

        Counted in ``read_late`` where 1."""
        newest = self._cmd
        if self._handled is not None or newest <= self._answered:
            return 0
        dr = self.driver
        echo = dr.answer_echo()
        shift = None
        if echo is not None and newest >= 1:
            now = dr.answer_names(self._sent_bytes[newest % RING], echo)
            before = dr.answer_names(self._sent_bytes[(newest - 1) % RING], echo)
            if now is not None and before is not None and now != before:
                shift = int(before)
                self._named_shift = shift
                if newest - shift <= self._answered:
                    # an answer for a command taken as answered: the pairings since the
                    # last named one were one command off
                    self.stats["mispaired"] += 1
                    self.mistimed.update(range(max(self._named_at, self._answered + 1 - RING),
                                               self._answered + 1))
                self._named_at = newest - shift + 1
        if shift is None:
            if (self._rt_us > 0
                    and self._now_us() - self._sent_us[newest % RING] < self._rt_us):
                shift = 1
            else:
                shift = self._named_shift if newest - 1 > self._answered else 0
        if shift:
            self.stats["read_late"] += 1
        return shift
