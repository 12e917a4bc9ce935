"""When a driver transport re-synchronises an unframed board, and when it waits: the
evidence rule and its bounds (:class:`Resynchronising`, a base of
:class:`hapsim.drivers.transport.DriverTransport`; moved out of it, unchanged but for
the silence rule, when it reached 800 lines).

A board without framing (the Haply M3, firmware V1.5) that lost its place in the host's
byte stream is put back in step by the driver's
:meth:`~hapsim.drivers.base.Driver.resync` bytes (zero torque first, then its set-up).
That costs the board a set-up whose encoder offset is the host's *estimate* of the joint's
angle, so a re-synchronisation is only called on evidence that the board lost its place:

- bytes that make no reply (the decoder's ``desync``: more than two faulty replies
  explain; ``lone``: writes answered by the id alone, a board that forgot its set-up);
- a well-formed reply out of the joint's reach (``unreachable``: the motion the torque
  clamp over the joint's inertia allows since the last record,
  :meth:`hapsim.drivers.haply.ReplyDecoder.reach_deg`, plus whole encoder counts);
- answers that stopped for :data:`SILENT_S` and more than :data:`SILENT_COMMANDS`
  commands while the board *did* send bytes, at least a reply's length and none of them
  a reply (``garbled``).

**A silence is not evidence** (issue 29). On its own clock, a board that lost its place
still answers: firmware V1.5 answers every write it parses (``loop``: ``write_states``
then ``read_states``, ``Haply_M3_Firmware_V1_5.ino``; a reply of at least its address
byte), its single ``SerialUSB.read()`` of an empty buffer returns at once (255), and only
a ``readBytes`` waits, for at most :data:`hapsim.drivers.haply.LONGEST_WAIT` = 32 bytes
(``Haply_M3_Firmware_V1_5.h`` lines 188 and 218). The host writes one command (6 bytes)
a tick through a silence, so a board that swallowed writes answers again, in step or
with the evidence above, after at most ``ceil(32 / 6) + 1`` = 7 writes. No byte back for
longer is a board, or a link, that is late (a starved reader, a USB hub, a descheduled
process), not a board that lost its place: its encoder counts on and its frame is the
host's, and its replies, when they come, are checked against the reach grown over the
whole silence. So the transport waits: the torque it commands is zero once no fresh
sample came for :data:`HOLD_BOUND_S` (:meth:`hapsim.drivers.transport.DriverTransport.
hold`), one command a tick (never a burst), and a board silent for :data:`SILENCE_LOST_S`
is lost (the whole stop sequence is sent, :class:`~hapsim.errors.DeviceError`): at most
:data:`SILENCE_LOST_S` times the rate commands queue behind it (3 kB at 1 kHz, within a
pty's 4 kB buffer). Before, a silence of 20 ms and more than four commands re-synchronised
the board (measured beside two CPU-bound processes at normal priority,
``tools/driver_timing.py --drivers haply --hogs 2 --rt-priority 0``: 0 to 107
re-synchronisations a run, the emulated board's joint 13.8 rad from its start in one),
although the board had lost no byte. A lockstep mock (named, paced by the commands) is
unchanged: its time is the commands', and more than :data:`SILENT_COMMANDS` unanswered
there is a lost answer.

**A board that reads fixed-length commands without framing** (the Hapkit sketch:
:mod:`hapsim.drivers.hapkit_serial`, ``realign_quiet_s`` > 0) is not set up again: a host
byte lost makes it read every later command ``s`` bytes late, and it is put back by
bytes or by silence alone. Its out-of-step replies say ``s`` (:meth:`Resynchronising.
_shifted`): ``s`` fill bytes and a zero-force command, at the next tick (reason
``shifted``); without them (two bytes lost in one command) bytes that make no reply for
``garbled_commands`` commands and ``garbled_s`` (the driver's, shorter than the M3's) call
a silence of ``realign_quiet_s`` from the last write, longer than the sketch's read
timeout (``garbled``). Its position is absolute: no frame moves, ``frame_bound`` is not
grown. (Found with the independent board model of ``tools/independent_boards``; the
emulated board realigned on its own before, so the loop never saw it.)
"""

from __future__ import annotations

import math

from hapsim.errors import DeviceError

__all__ = ["Resynchronising", "SILENT_COMMANDS", "SILENT_S", "MAX_RESYNCS_PER_S",
           "RESYNC_GAP_S", "HOLD_BOUND_S", "SILENCE_LOST_S", "RESYNC_REASONS", "RING",
           "REARM_PROBE_S"]

#: Commands in a row without an answer after which the device may be re-synchronised
#: (with :data:`SILENT_S` and, on the board's own clock, bytes that made no reply: all
#: must hold).
SILENT_COMMANDS = 4
#: The oldest unanswered command's wait [s] that, with bytes that made no reply, shows the
#: board lost its place: a board answers a write within its pass and a USB frame (about
#: 1 ms); a late reply, a slow host or a host stall is not this.
SILENT_S = 0.02
#: Re-synchronisations within one second beyond which the link is declared unfit and the
#: run ends (each puts zero torque first; the position after each is an estimate). One
#: lost host byte in 200 costs the Haply M3 about 16 a second at 1 kHz (a 6-byte write).
MAX_RESYNCS_PER_S = 50
#: The shortest time between two re-synchronisations [s]: one costs the board a set-up
#: (2 ms on the Haply M3) and ~1 ms of passes for its 62 bytes; a second one sooner is no
#: new evidence (zero torque is commanded meanwhile).
RESYNC_GAP_S = 0.005
#: Longest time [s] the host lets a board without a watchdog hold a torque computed from
#: a sample older than this: a missed tick past it commands zero torque.
HOLD_BOUND_S = 0.02
#: Longest silence of a board on its own clock [s] (no byte back while the host commands
#: on) the transport waits for: then the board is lost (module notes).
SILENCE_LOST_S = 0.5
#: Why a re-synchronisation was called (``stats["resync_reasons"]``): the decoder's
#: ``desync`` (``lone`` among them), ``unreachable``, ``garbled`` (bytes and no reply for
#: :data:`SILENT_S`), ``silent`` (a lockstep mock's commands unanswered), ``unarmed`` (no
#: record yet: the arming again), ``watchdog`` (made by the host's watchdog while the board
#: may have lost its place: :mod:`hapsim.drivers.host_watchdog`), ``shifted`` (a board
#: reading fixed-length commands out of step, by how much its replies say:
#: :meth:`Resynchronising._shifted`).
RESYNC_REASONS = ("desync", "lone", "unreachable", "garbled", "silent", "unarmed",
                  "watchdog", "shifted")
#: Commands remembered for attributing records and timing silences (the transport's ring):
#: more than :data:`SILENCE_LOST_S` holds at 4 kHz, so the oldest command of a silence
#: waited for keeps its time (64 before, when 20 ms ended any silence: past 64 commands
#: its time was overwritten by a newer one's).
RING = 2048
#: How long a re-arming waits for the reply that gives the joint's angle now [s]
#: (:meth:`Resynchronising._angle_now`): a board answers within its pass and a USB frame.
REARM_PROBE_S = 0.005


class Resynchronising:
    """The re-synchronisation rule and its bounds of a driver transport (module notes).
    A base of :class:`hapsim.drivers.transport.DriverTransport`, whose port, clock, ring
    and counters it uses (``driver``, ``_armed``, ``_cmd``, ``_answered``, ``_sent_us``,
    ``_now_us``, ``_clock``, ``_handled``, ``_deadline_us``, ``_command``, ``_write``,
    ``_extrapolate``, ``_x_last``, ``_s_last``, ``_dec``, ``_floor``, ``stats``).

    Its counters (in ``stats``): ``resyncs``; ``resync_reasons`` (a dict, one count per
    :data:`RESYNC_REASONS` key); ``silences`` (silences of the board longer than
    :data:`SILENT_S` waited for instead) and ``silence_max_s`` (the longest, from the
    oldest unanswered command's sending to the record that ended it [s]); ``frame_bound``
    (the sum over the re-synchronisations of how far each can move the board's frame
    [rad], :meth:`_frame_error_bound`).
    """

    def _init_resync(self) -> None:
        """The rule's state (called by the transport's constructor)."""
        from collections import deque
        self._t_resync = -math.inf            # the device clock's last re-synchronisation
        self._resync_times = deque()          # those of the last second
        self._rx_since_record = 0             # bytes read since the last record taken
        self._silent_from_us = None           # a silence being waited for: its start
        self._quiet_until = -math.inf         # no write before then (a realignment) [s]
        self._fill = b""                      # bytes that put a shifted reader in step
        self._shifts_seen = 0                 # its decoder's out-of-step replies taken
        self._skip_shift = 0                  # of those, the next one to pass over
        self.stats.update(resyncs=0, resync_reasons=dict.fromkeys(RESYNC_REASONS, 0),
                          silences=0, silence_max_s=0.0, frame_bound=0.0)

    @property
    def waits_silence_s(self) -> float:
        """How long this transport waits for a silent board itself [s]:
        :data:`SILENCE_LOST_S` for an unframed driver on the board's own clock (then it
        gives up, zero torque sent), else 0. The host loop's loss rule waits as long
        (:meth:`hapsim.host.recovery.Recovery._silence`): a recovery's STOP and CONFIG
        set the board up at a stale angle, moving its frame."""
        own_clock = self._handled is None and self._deadline_us <= 0
        return SILENCE_LOST_S if (self.driver.unframed and own_clock) else 0.0

    def _silence_ended(self) -> None:
        """A record came: a silence being waited for ends (its length counted)."""
        self._rx_since_record = 0
        if self._silent_from_us is not None:
            s = (self._now_us() - self._silent_from_us) * 1e-6
            self.stats["silence_max_s"] = max(self.stats["silence_max_s"], s)
            self._silent_from_us = None

    def _lost_place(self) -> str | None:
        """Why the board must be put back in step now, or None: its replies' shift
        (:meth:`_shifted`, ``"shifted"``), else :meth:`_stalled`'s evidence."""
        return "shifted" if self._shifted() else self._stalled()

    def _quiet_now(self) -> bool:
        """Whether the host keeps silent now, for a board realigning on its silence
        (:meth:`_resync`): this tick's command is then not written (counted
        ``quiet_commands``)."""
        if self._clock() < self._quiet_until:
            self.stats["quiet_commands"] = self.stats.get("quiet_commands", 0) + 1
            return True
        return False

    def _quiet_missing(self) -> None:
        """A command not written in a realignment's silence, just numbered: a missing
        sample at once (no answer is owed; the realignment is judged on the commands
        written after it)."""
        if self._answered == self._cmd - 1:
            self._answered = self._cmd
            self.stats["missing"] += 1

    def _shifted(self) -> bool:
        """Whether a board that reads fixed-length commands without framing says it reads
        them out of step, by how much it does (the driver's
        :meth:`~hapsim.drivers.hapkit_serial.HapkitSerial.realign_bytes` from its frame
        decoder's evidence: the Hapkit sketch's replies ``[0xA0 + s]...``); the bytes that
        put it back are kept for :meth:`_resync` (reason ``shifted``). The first such
        reply after a fill is the fill's own command's (read out of step by design) and
        is passed over.

        Returns
        -------
        bool
        """
        hook = getattr(self.driver, "realign_bytes", None)
        if hook is None or not self._armed:
            return False
        frames = getattr(self._dec, "frames", self._dec)
        n = int(getattr(frames, "shifts", 0))
        if n <= self._shifts_seen:
            return False
        fresh, self._shifts_seen = n - self._shifts_seen, n
        if self._skip_shift:
            fresh, self._skip_shift = fresh - 1, 0
        if fresh <= 0:
            return False
        self._fill = hook(frames)
        return bool(self._fill)

    def _stalled(self) -> str | None:
        """Whether answers stopped in a way that is evidence the board lost its place
        (module notes): more than :data:`SILENT_COMMANDS` commands unanswered (armed, an
        unframed driver) and, for a lockstep mock, nothing else (``"silent"``: its time is
        the commands'); on the board's own clock, the oldest of them waiting
        :data:`SILENT_S` *and* at least a reply's length of bytes read since the last
        record, none of them one (``"garbled"``). A silence with no byte back is waited
        for (counted in ``silences``), up to :data:`SILENCE_LOST_S`.

        Returns
        -------
        str or None
            The reason to re-synchronise now (a :data:`RESYNC_REASONS` key), or None.

        Raises
        ------
        DeviceError
            No byte back for :data:`SILENCE_LOST_S` while commands went out (the stop
            sequence, zero torque whatever the board's parser is inside, is sent first).
        """
        drv = self.driver
        quiet = float(getattr(drv, "realign_quiet_s", 0.0) or 0.0)
        n_max = int(getattr(drv, "garbled_commands", SILENT_COMMANDS))
        if not (drv.unframed and self._armed and self._cmd - self._answered > n_max):
            return None
        if self._handled is not None or self._deadline_us > 0:
            # a mock paced by the commands (a lockstep run): its time is the commands';
            # one that realigns only on a silence has none to realign on
            return None if quiet > 0 else "silent"
        oldest = self._sent_us[(self._answered + 1) % RING]
        waited = self._now_us() - oldest
        if waited < float(getattr(drv, "garbled_s", SILENT_S)) * 1e6:
            return None
        # (fewer bytes than one reply, then nothing: a reply whose rest is late, as the
        # silence after it; a board that lost its place answers each write, and its id
        # alone three times is the decoder's 'lone' already)
        frames = getattr(self._dec, "frames", self._dec)
        if self._rx_since_record >= int(getattr(frames, "length", 1)):
            return "garbled"
        if self._silent_from_us is None:
            self._silent_from_us = oldest
            self.stats["silences"] += 1
        waited = self._now_us() - self._silent_from_us
        if waited >= SILENCE_LOST_S * 1e6:
            self._armed = False
            raise self._give_up(
                f"sent no byte for {waited * 1e-3:.0f} ms while {self._cmd - self._answered} "
                f"commands went out (> {SILENCE_LOST_S * 1e3:g} ms): it is gone or its link "
                f"stalled")
        return None

    def _give_up(self, why: str) -> DeviceError:
        """Zero torque whatever the board's parser is inside (the driver's stop bytes),
        and the error that ends the run: ``the <driver> board <why> (zero torque sent)``."""
        self._force = 0.0
        self._write(self.driver.stop_bytes(self._x_last))
        return DeviceError(f"the {self.driver.name} board {why} (zero torque sent)")

    def _resync(self, reason: str) -> None:
        """The device lost its place in the byte stream: the driver's re-synchronisation
        (zero force first, then its set-up), as one command; the force held is zero.

        Bounded in time and bytes: not sooner than :data:`RESYNC_GAP_S` after the last
        one (meanwhile zero torque is commanded), and not more than
        :data:`MAX_RESYNCS_PER_S` within a second.

        Parameters
        ----------
        reason : str
            The evidence (a :data:`RESYNC_REASONS` key), counted in
            ``stats["resync_reasons"]`` when the re-synchronisation is sent.

        Raises
        ------
        DeviceError
            A re-synchronisation beyond :data:`MAX_RESYNCS_PER_S` in one second (the link
            loses the board's place faster than it can be restored: zero torque has been
            sent).
        """
        now = self._clock()
        if now - self._t_resync < RESYNC_GAP_S:
            self._force = 0.0
            self._command(self.driver.encode_force(0.0))
            return
        recent = self._resync_times
        while recent and now - recent[0] > 1.0:
            recent.popleft()
        if len(recent) >= MAX_RESYNCS_PER_S:
            raise self._give_up(
                f"lost its place in the byte stream more than {MAX_RESYNCS_PER_S} times in a "
                f"second: the link is not fit for a run (decoder {dict(self._dec.stats)}; "
                f"reasons {self.stats['resync_reasons']})")
        recent.append(now)
        self._t_resync = now
        self.stats["resyncs"] += 1
        self._force = 0.0
        self._rx_since_record = 0
        quiet = float(getattr(self.driver, "realign_quiet_s", 0.0) or 0.0)
        if quiet > 0:
            # a fixed-length reader with no framing (the Hapkit sketch): put back in step
            # by the bytes its shift asks for (its out-of-step replies say it: the fill
            # and a zero-force command, this tick's), else by a silence longer than its
            # read's timeout (no byte until then, the commands meanwhile missing samples:
            # DriverTransport._command). Its position is absolute: no frame moves
            if reason == "shifted" and self._fill:
                self._command(self._fill + self.driver.encode_force(0.0))
                self._skip_shift = 1        # the fill's own command answers out of step
            else:
                self._quiet_until = max(self._quiet_until, self._t_write + quiet)
                self.stats["quiet_s"] = self.stats.get("quiet_s", 0.0) + quiet
            self._fill = b""
            self._close_gap(reason)
            return
        # where the device is now: the last two records extrapolated to this command (a
        # board that re-zeroes its position at the set-up goes on from there)
        x = self._extrapolate(self._cmd + 1)
        self.stats["frame_bound"] += self._frame_error_bound(x)
        if self._s_last < 0:
            # no record yet: the arming's offset is the only position known (the
            # decoder's anchor), not the 0 the host starts from
            reason = "unarmed"
            self._arm_again()
        else:
            # (answered twice: its zero writes before and after the set-up; replies of
            # the commands before it may still come)
            self._floor = min(self._floor, self._cmd - 1)
            self._command(self.driver.resync(self._x_last if x != x else x))
        self._close_gap(reason)

    def _close_gap(self, reason: str) -> None:
        """A re-synchronisation's end: its reason counted, and a deliberate gap in
        ``seq`` (the commands before it unanswered are missing samples)."""
        self.stats["resync_reasons"][reason] = self.stats["resync_reasons"].get(reason, 0) + 1
        # a deliberate gap in seq: the position may jump by the error of that estimate, so
        # a measurement does not run across a re-synchronisation
        self._cmd += 1
        self._sent_us[self._cmd % RING] = self._sent_us[(self._cmd - 1) % RING]
        self._sent_bytes[self._cmd % RING] = b""      # a number, no command: names nothing
        if self._answered < self._cmd - 1:      # the commands before it: missing samples
            self.stats["missing"] += self._cmd - 1 - self._answered
            self._answered = self._cmd - 1

    def _frame_error_bound(self, x: float, at_us: int | None = None) -> float:
        """How far [rad] a re-synchronisation about to be sent can move the board's frame:
        the error of the angle its set-up writes into the encoder's count, the estimate
        ``x`` (the last two records extrapolated to this command), against where the joint
        is when the count is written (at most :data:`RESYNC_GAP_S` from now: the set-up's
        2 ms wait and the bytes' passes).

        The decoder's reach (:meth:`hapsim.drivers.haply.ReplyDecoder.reach_deg`, the rule
        every reply is believed by: the motion the torque clamp over the joint's inertia
        allows, Taylor's bound with a factor 2, and whole encoder counts) bounds the joint's
        distance from the last two records' prediction one period ahead over the time
        ``tau`` since the last record's command; the estimate lies ``(n - 1) |v|`` beyond
        that prediction (``n`` commands ahead, ``v`` the records' step per command). So
        ``|x - x_true| <= reach(tau) + (n - 1) |v|``. Before any record (``unarmed``: the
        arming's set-up again), the set-up's offset is the arming's, and the joint is
        within the reach of it since the arming (the decoder's anchor, no velocity).
        A frame's error moves the spring's rest in the joint's real frame, not the loop
        the host closes in its own (translation-invariant: the measurement's stretches, cut
        at each re-synchronisation's ``seq`` gap, fit their own initial states), so the
        sum of these bounds is what the joint's real position may differ from the host's
        readings by (:func:`hapsim.pipeline.measure.timing_verdict`).

        Parameters
        ----------
        x : float
            The estimate the set-up writes [rad] (NaN: none).
        at_us : int, optional
            When the re-synchronisation was sent, on the transport's clock [us] (default
            now; the host's watchdog sent its own earlier:
            :meth:`hapsim.drivers.host_watchdog.Watched._wd_resynced`).

        Returns
        -------
        float
            The bound [rad]; ``inf`` for a driver whose decoder states no reach.
        """
        frames = self._frames
        if frames is None:
            return math.inf
        n, v = 1, 0.0
        if self._s_last < 0:
            since_us = self._anchor_us
        else:
            # (one record only: the set-up takes it as it is, the prediction too)
            since_us = self._sent_us[self._s_last % RING]
            if x == x:
                n, v = self._cmd + 1 - self._s_last, self._step_per_command()
        now = self._now_us() if at_us is None else at_us
        tau = max(now - since_us, 0) * 1e-6 + RESYNC_GAP_S
        return math.radians(frames.reach_deg(0, tau)) + max(n - 1, 0) * v

    def _step_per_command(self) -> float:
        """The last two records' step per command [rad] (0 before two came)."""
        if self._s_prev is None or self._s_last <= self._s_prev:
            return 0.0
        return abs(self._x_last - self._x_prev) / (self._s_last - self._s_prev)

    def _arming_bytes(self) -> bytes:
        """A CONFIG's bytes, and the decoder's prediction restarted for them: the
        driver's :meth:`~hapsim.drivers.base.Driver.arm` at the first arming; at a
        re-arming (a recovery after a loss, a STOP and CONFIG), for a driver whose set-up
        sets the joint's angle (:meth:`~hapsim.drivers.base.Driver.rearm_anchor` not
        None: the Haply M3), its re-synchronisation at the last angle read, as a STOP's
        is. The arming's offset is the pose the joint is *armed* in (the hand holds it
        there); mid-run the joint is elsewhere, and a set-up there moved the board's frame
        by the difference at every re-arming: the spring's rest walked with it (issue 29:
        the lossy runs' 0.5-13 rad, each loss of 50 ms a re-arming). What the STOP's
        set-up (at the last angle read) and this one may still move the frame by is added
        to ``stats["frame_bound"]`` (as a re-synchronisation's,
        :meth:`_frame_error_bound`)."""
        x = self._x_last
        anchor = (self.driver.rearm_anchor(x)
                  if self._ever_armed and self._s_last >= 0 and math.isfinite(x) else None)
        if anchor is not None and self._frames is not None:
            # the STOP before set the board up at the last angle read: its frame moved by
            # the joint's motion since that record (the reach from its prediction, and
            # the prediction's one step), the frame_bound of a re-synchronisation
            tau = (max(self._now_us() - self._sent_us[self._s_last % RING], 0) * 1e-6
                   + RESYNC_GAP_S)
            stop = math.radians(self._frames.reach_deg(0, tau)) + self._step_per_command()
            self.stats["frame_bound"] += stop
        if anchor is not None and self.waits_silence_s > 0:
            # (on the board's own clock: a lockstep mock's time is the commands', and a
            # write more would step it)
            sent = self._now_us()
            x = self._angle_now(x)
            anchor = self.driver.rearm_anchor(x)
            if self._frames is not None:
                # this set-up at the angle read in the STOP's frame (the probe's reply, or
                # the last record's angle again: the joint coasted since, as far again)
                probe = self._probe_got
                tau = (max(self._now_us() - sent, 0) * 1e-6 + RESYNC_GAP_S
                       if probe else None)
                self.stats["frame_bound"] += (math.radians(self._frames.reach_deg(0, tau))
                                              if probe else stop)
        if anchor is None:
            self._dec.reset_prediction(jumps=2)
            return self.driver.arm()
        self._dec.reset_prediction(jumps=2, anchor=anchor)
        return self.driver.resync(x)

    def _angle_now(self, x: float) -> float:
        """The joint's angle now, for a re-arming's set-up: a zero-torque write and its
        reply, read for :data:`REARM_PROBE_S` (the STOP before left the board at zero
        torque, in step, its frame at the last angle read; the listening and the
        recovery's HELLO since are tens of ms of coasting). ``x`` (the last angle read)
        when no reply comes or the decoder takes none (its reach check, as any reply's).
        The decoder's counters it moved are the arming's, not evidence."""
        if self._frames is not None:
            # judged from the last angle read, over the time since its command (the
            # decoder's reach: the joint coasted, or was held, meanwhile)
            self._dec.reset_prediction(jumps=1, anchor=self.driver.rearm_anchor(x))
            self._frames.elapsed((self._now_us() - self._sent_us[self._s_last % RING]) * 1e-6)
        self._write(self.driver.encode_force(0.0))
        end = self._now_us() + REARM_PROBE_S * 1e6
        got = []
        while not got and self._now_us() < end:
            data = self._ser.read(max(self._ser.in_waiting, 1))
            if data:
                got = [v for v in self._dec.feed(data) if v == v and abs(v) < math.inf]
        st = self._dec.stats
        self._desyncs, self._unreach, self._lone = (st.get(k, 0) for k in (
            "desync", "unreachable", "lone"))
        self._probe_got = bool(got)
        return got[-1] if got else x

    def _arm_again(self) -> None:
        """The arming's bytes again, as one command (no record came yet): the decoder's
        prediction restarts at the set-up's offset, as old as this command."""
        self._dec.reset_prediction(jumps=2)
        self._anchor_us = self._now_us()
        self._anchor_cmd = self._cmd + 1
        self._floor = self._cmd - 1         # (the arming is answered twice)
        self._command(self.driver.arm())
