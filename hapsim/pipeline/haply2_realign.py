"""The 2DIY's realigning probe: the real-time loop's count of replies checked against the
board's own answer, never by a wait (issue 29).

A 2DIY board answers its writes in order, one reply each, so the loop files the ``i``-th
reply under write ``i`` (:mod:`hapsim.pipeline.haply2_record`). A host byte lost in write
``j`` breaks that count without the board losing its place (firmware V1.5 has no framing;
at the address 3, :data:`hapsim.drivers.haply.DEFAULT_ID`, no command byte): the board
completes ``j`` with ``j + 1``'s first byte and parses the rest of ``j + 1`` as no
command (lost in ``j``'s first byte, ``j`` is the write not answered), so one write is
never answered and every reply after it answers a write one newer than the count says. A
board that is only late (a loaded host, a USB frame) looks the same for a while: in both
cases the loop ends its ticks behind though replies come.

The probe tells the two apart by the board's own answer. At such a tick (:data:`SILENT_COUNT`
ticks in a row behind, a reply read in the last; or a count ahead of the writes sent) the
tick's command is a *marker* write, ``[2][MARK_ID]`` (:data:`MARK_ID`: an address no port
of the board has), instead of the torque write: one command a tick still, and the board,
which has no watchdog, holds the torques of the write before over that tick (the record
is cut there: ``probed``, :func:`hapsim.pipeline.haply2_host.usable_rows`). Firmware V1.5
answers a write with its address and the readings of the ports at that address
(``write_states`` then ``read_states``, ``Haply_M3_Firmware_V1_5.ino`` line 77 and 89;
``.h`` ``read_states``): ``[MARK_ID]``, one byte, in the marker's place among the 9-byte
replies (the decoder gives it as :data:`hapsim.drivers.decoders.MARK` where a reply would
start: :meth:`hapsim.drivers.decoders.AlignedDecoder.mark_at`). The replies before it answer
the writes before the marker, the one after it the write after the marker, so the count
is set there whatever it was: a late board's is unchanged, one that swallowed ``D``
writes moves on by ``D``. The loop writes on meanwhile; the answer comes with the next
tick's replies. The readings filed since the run of ticks behind began are dropped
(which write went unanswered is not known; those rows are cut in any case).

A marker whose address byte is lost is answered ``[255]`` (the firmware's single read of
an empty buffer; the emulated board's on either clock) and is taken as well. One whose
command byte is lost, that a short write before it swallowed, or whose answer is lost on
the way back is not answered: after :data:`PROBE_TICKS` ticks another is sent, and
:data:`PROBE_TRIES` unanswered are a board that lost its place (``lost``: the loop
re-synchronises it). A count more than :data:`SILENT_COUNT` replies ahead of the marker's
place is one too (a board answering writes it was not sent).

Before (issue 29's first probe): a zero-torque write, then up to ``SILENT_S / 2`` of the
host's awake time listening for the replies owed, twice: every probe that found a write
swallowed stalled the loop (27-42 host stalls a run of five records at 1 byte in 200
lost each way, ``tools/driver_timing.py --drivers haply2 --loss 0.005 --hogs 2``).
"""

from __future__ import annotations

import numpy as np

from hapsim.drivers.haply import CMD_WRITE

__all__ = ["Realigner", "MARK_ID", "MARK_ANSWERS", "PROBE_TICKS", "PROBE_TRIES",
           "SILENT_COUNT"]

#: The marker's address: no command byte (0 reset, 1 set-up, 2 write), not the 2DIY's
#: (3), not the 255 an absent byte reads as, and far from the small ids a board's other
#: devices are set up at (a write there would take torque bytes).
MARK_ID = 0xFE
#: The answers a marker gets: its address, or 255 when its address byte was lost (the
#: firmware's single read of an empty buffer).
MARK_ANSWERS = (MARK_ID, 255)
#: Unanswered writes that may be late replies whatever their age (a board's pass and a USB
#: frame hold a few): ticks in a row ended behind, a reply read in the last, before a
#: marker is sent.
SILENT_COUNT = 4
#: Ticks a marker's answer is looked for before another is sent (the loop writes on).
PROBE_TICKS = 4
#: Markers of one run behind sent without an answer before the board is taken as lost.
PROBE_TRIES = 3


class Realigner:
    """The probe's state in one record (module notes): the run of ticks behind, the
    marker outstanding, and what the marker's answers found.

    Parameters
    ----------
    decoder : hapsim.drivers.haply2.Reply2Decoder
        The loop's reply decoder (its ``marks`` are set while a marker is outstanding).
    xr, qr : ndarray, shape (C, 2)
        The loop's readings per write [m] and [rad] (rows dropped here: NaN).

    Attributes
    ----------
    marker : bytes
        The marker write, ``[2][MARK_ID]``.
    probes : int
        Markers sent.
    realigned : int
        Answers that moved the count (writes the board swallowed, or answers it counted
        that were none).
    late : int
        Answers that left the count as it was (a late board).
    lost : bool
        The board lost its place (:data:`PROBE_TRIES` markers unanswered, or a count far
        ahead): the loop re-synchronises it, then :meth:`reset`.
    """

    def __init__(self, decoder, xr: np.ndarray, qr: np.ndarray) -> None:
        self.dec = decoder
        self.xr, self.qr = xr, qr
        self.marker = bytes((CMD_WRITE, MARK_ID))
        self.probes = self.realigned = self.late = 0
        self.reset()

    def reset(self) -> None:
        """Nothing outstanding (a record's start, a re-synchronisation: the count
        re-anchored at the set-up)."""
        self.behind = 0                 # ticks in a row ended behind
        self.run0 = -1                  # the first of them
        self.first = -1                 # the first row whose filing is in doubt
        self.kp = -1                    # the tick of the marker outstanding
        self.tries = 0
        self.lost = False
        self.dec.marks = ()

    def _drop(self, a: int, b: int) -> None:
        a, b = max(a, 0), min(b, self.xr.shape[0])
        if a < b:
            self.xr[a:b] = np.nan
            self.qr[a:b] = np.nan

    def due(self, k: int, got: int, g0: int) -> bool:
        """Whether tick ``k``'s command is a marker, its replies read (``g0``, ``got``:
        the write the next reply answers before and after the read).

        A count ahead of the writes sent (``got > k + 1``) drops the readings filed from
        row ``k`` on at once (row ``k``'s would be taken as fresh). With a marker
        outstanding for :data:`PROBE_TICKS` ticks, another, up to :data:`PROBE_TRIES`
        (then ``lost``).

        Parameters
        ----------
        k : int
            The tick.
        got, g0 : int
            The write the next reply answers, by the count, after and before the tick's
            read.

        Returns
        -------
        bool
        """
        if got > k + 1:
            self._drop(k, got)
            if self.first < 0 or self.first > k:
                self.first = k
        if self.kp >= 0:
            if k - self.kp < PROBE_TICKS:
                return False
            if self.tries >= PROBE_TRIES:
                self.lost = True
                return False
            return True
        return got > k + 1 or (self.behind >= SILENT_COUNT and got > g0)

    def sent(self, k: int) -> None:
        """The marker was tick ``k``'s command (write ``k + 1``): its answer is looked
        for (the decoder's ``marks``).

        Parameters
        ----------
        k : int
        """
        if self.first < 0:
            self.first = self.run0 if self.run0 >= 0 else k
        self.kp = k
        self.tries += 1
        self.probes += 1
        self.dec.marks = MARK_ANSWERS

    def marked(self, got: int) -> int:
        """The marker's answer read, the count at ``got`` (the write the next reply would
        have been filed under): the count after it (the write after the marker's), and the
        readings of the rows in doubt dropped.

        Parameters
        ----------
        got : int

        Returns
        -------
        int
        """
        kp = self.kp
        if kp < 0:
            return got + 1                  # (not asked for: an answer, counted)
        shift = kp + 1 - got                # writes swallowed (< 0: answers that were none)
        self._drop(self.first, max(got, kp + 2))
        if shift < -SILENT_COUNT:
            self.lost = True
        elif shift:
            self.realigned += 1
        else:
            self.late += 1
        self.kp = self.first = self.run0 = -1
        self.tries = self.behind = 0            # (the count confirmed: no run behind)
        self.dec.marks = ()
        return kp + 2

    def tick_end(self, k: int, got: int, resynced: bool) -> None:
        """Tick ``k`` ended with the count at ``got`` (``resynced``: re-armed at it, the
        readings of the rows in doubt before it dropped: a write swallowed before the
        board lost its place left them filed a write off).

        Parameters
        ----------
        k, got : int
        resynced : bool
        """
        if resynced:
            self.drop_open(k)
            self.reset()
        elif got <= k:
            if not self.behind:
                self.run0 = k
            self.behind += 1
        else:
            self.behind = 0
            self.run0 = -1

    def drop_open(self, end: int) -> None:
        """The count not confirmed (a re-synchronisation; the record's closing zero
        write's reply not in step): the readings of the rows in doubt, from the open run
        behind or marker on, up to ``end`` (not included), dropped.

        Parameters
        ----------
        end : int
        """
        starts = [s for s in (self.first, self.run0) if s >= 0]
        if starts:
            self._drop(min(starts), end)
