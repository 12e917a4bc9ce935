"""The framed-protocol face of a driver: what the host loop talks to.

:class:`DriverTransport` offers the loop the transport interface of
:mod:`hapsim.host.transport` (``send``, ``receive``, ``close``, ``info``,
``last_frames``, ``decoder``) and speaks the driver's bytes on the port:

- HELLO_REQUEST -> a HELLO made from the driver's facts (1 axis, its resolutions and
  force limit); PING -> a PONG at once (the driver has no round trip to measure);
- CONFIG -> arms: the driver's set-up bytes and one zero-force command, whose answer is
  the first record (after the driver's ``arming_records`` at zero force, for a firmware
  whose force comes up slowly; re-sent every :data:`REARM_INTERVAL` until a record comes: a board that
  resets when its port opens, like the FireFader's Arduino Nano, drops what arrives while
  its bootloader runs);
- FORCE -> the driver's force packet (a *command*); the record the device answers with
  becomes a STATE;
- STOP -> zero force (:meth:`~hapsim.drivers.base.Driver.stop_bytes`: for the Haply board,
  which has no watchdog, its whole re-synchronisation, so that zero torque is taken
  whatever its parser is doing); closing the port sends the same first.
- A board that holds a force longer than the hold bound by itself, on its own clock, has
  the host's watchdog beside it (:mod:`hapsim.drivers.host_watchdog`): a zero write when
  the host does not run, a command of its own.

Host-clocked only (the loop must run with ``host_clocked``): the device answers packets.

The host clock, and a missing reply (neither protocol has a sequence number)
---------------------------------------------------------------------------
Every command is one host tick, numbered here (``seq``). The host loop (for a driver that
declares :attr:`~hapsim.drivers.base.Driver.request_reply`) sends one per tick:
a FORCE when it has a new STATE; when the answer is :meth:`DriverTransport.overdue`, a
FORCE computed from the position :meth:`DriverTransport.estimate` extrapolates (the
loop's estimated sample); else (a
longer silence) :meth:`DriverTransport.hold` (the last force again), so the device keeps
being asked and keeps answering. A record is the answer to the newest
command sent before it was read, which is exact when the device answers within one period
(the rates a driver accepts, :meth:`hapsim.drivers.base.Driver.check_rate`); records read
together are the answers to the commands before it, in order, and a record with no
unanswered command left is *unprompted* (counted: a firmware that streams records, the
FireFader's older ``.pde``). A command that gets no record is a *missing sample*: counted
(``missing``), never a lost device: the loop counts the tick as missed and goes on; only a
silence of the loop's ``lost_timeout`` is a loss. The STATE carries ``seq`` = the command
it answers (gaps are the missing samples), ``time_us`` = the host clock when that command
was sent [us] (the real time base of the sample), and ``force_seq = seq - d`` with ``d``
the delay the scene states (the protocol cannot tell which force the device applied; its
status has ``STATUS_FORCE_APPLIED`` clear, so nothing downstream takes that for a
measurement).

A driver whose replies can show that the *device* lost its place in the byte stream (the
Haply board: no framing, one lost host byte desynchronises its parser) says so through
its decoder's ``desync`` counter, by a reading out of its reach, or by bytes that make no
reply while commands go out (never by a silence alone: a board on its own clock that is
late is waited for, at zero torque after the hold bound,
:mod:`hapsim.drivers.resync`); the transport then re-synchronises the device with the
driver's
:meth:`~hapsim.drivers.base.Driver.resync` bytes (zero force first; the position the last
two records extrapolate to now as the Haply encoder's new offset) and counts it
(``resyncs``); the samples until the next good record are missing samples, and ``seq``
skips one number there, so that a measurement does not run across the position's jump
(the error of that extrapolation).

A lockstep mock (named, a test device stepped one period per command) has no time of its
own: a slow mock process and a lost packet cannot be told apart by the time waited (a
20 ms deadline re-asked commands a loaded host's mock answered late: the mock stepped
twice, another record). Given its account of the bytes it handled (``handled``,
:class:`hapsim.spawn.HandledBytes`), the transport reads only once the mock has handled
every byte written to it, then all it wrote (the decisions on them do not depend on how
its writes were cut up in time); an unanswered command is an estimated sample only when
the mock is quiet and bytes came that made no record (a damaged answer: the mock stepped),
and is asked again (:meth:`DriverTransport.hold`, no row) when the mock is quiet and
nothing came (the packet may never have reached it: its time did not go on); the hold
bound and the re-synchronisations' bounds count the commands' time. The same run gives
the same record on a quiet host and a loaded one.

A reading is believed only where the device can be: for a driver whose decoder checks it
(``checks_reach``: the Haply M3), the transport states before each read the time since
the command the last record answered was sent (the board sampled it no earlier), and the
decoder takes a reply only within the motion the force limit over the device's
``inertia`` allows in that time (:meth:`hapsim.drivers.haply.ReplyDecoder.reach_deg`);
a well-formed reply out of reach (a frame a corrupted set-up made) is evidence that the
board lost its place, and re-synchronises it like a desync. The first record after an
arming is no velocity (nothing came before it): an estimate from one record holds it.
"""

from __future__ import annotations

import math
import time
from collections import deque

import firmware_protocol as fp
from hapsim.drivers.handled_account import LOCKSTEP_WRITE_TIMEOUT_S, HandledAccount
from hapsim.drivers.host_watchdog import Watched
from hapsim.drivers.late_replies import LateReplies
from hapsim.drivers.resync import HOLD_BOUND_S, RING as _RING, SILENCE_LOST_S, Resynchronising
from hapsim.drivers.tick_align import REARM_INTERVAL, TickAligned
from hapsim.errors import DeviceError

__all__ = ["DriverTransport", "DriverStats", "REARM_INTERVAL"]

#: Listening before arming, for records nobody asked for (a streaming firmware) [s].
LISTEN_S = 0.03
#: The shortest time between two replies' samples [s] (by the host's times) that bound
#: the joint's speed (:meth:`DriverTransport._speed_bound`): over 5 ms the readings'
#: rounding and the sample times' uncertainty (a period each) cost little.
SPEED_BASE_S = 0.005
#: Most host ticks kept as mistimed (:meth:`DriverTransport._note_hold`): the measurement
#: reads the record's head; an open-ended run's later ones are not needed.
MISTIMED_MAX = 1 << 16


class DriverStats:
    """Decoder counters in the shape the host loop reads (:class:`firmware_protocol.DecoderStats`).

    The driver's own counters map as ``skipped`` + ``out_of_range`` -> ``malformed``,
    ``truncated`` -> ``overlong``; the protocol has no CRC, COBS or message types.
    """

    def __init__(self, raw: dict) -> None:
        self.raw = raw
        self.bad_crc = 0
        self.bad_cobs = 0
        self.unknown_type = 0

    @property
    def malformed(self) -> int:
        return int(self.raw.get("skipped", 0) + self.raw.get("out_of_range", 0))

    @property
    def overlong(self) -> int:
        return int(self.raw.get("truncated", 0))

    def as_dict(self) -> dict:
        """The counters as a plain dict (a copy, for the report)."""
        return dict(self.raw)


class _Dec:
    """What the loop reads of a decoder: counters, and no frame history (no frames)."""

    last_frames = ()

    def __init__(self, stats):
        self.stats = stats


class DriverTransport(TickAligned, Resynchronising, LateReplies, Watched, HandledAccount):
    """A driver's device on a serial port, as the host loop's transport.

    Parameters
    ----------
    driver : hapsim.drivers.base.Driver
        The protocol.
    port : str
        Serial port (hardware or the driver mock's pty).
    delay : int >= 0
        The loop delay d the scene states [samples] (reported in ``force_seq``).
    read_timeout : float
        pyserial read timeout [s].
    reply_deadline : float
        How long a command may wait for its answer before a missed tick asks again [s]:
        0 for hardware (the device's time goes on: each missed tick asks again). A mock
        paced by the commands is given ``handled`` instead (a deadline there took a slow
        mock process for a lost answer: the command was asked again and the mock stepped
        twice, another record on a loaded host).
    delay_known : bool
        ``delay`` is the device's (a scene states it, a mock has it); False when it is a
        guess that identification must search (then the driver gives no account).
    inertia : float, optional
        The device's smallest inertia [kg m^2] (the scene's ``device.mass`` of a rotary
        axis): a driver whose decoder checks a reading's reach (``checks_reach``: the
        Haply M3) believes a record only within what its force limit over this inertia
        allows in the time since the command the last record answered (stated to the
        decoder before each read, module notes); None: the decoder's default.
    board_period : float, optional
        A board stepped one period per command (a lockstep mock) [s]: its time is the
        commands', so the time a reading's reach grows with is the commands sent since
        the last record's, times this period, whatever the host's wall clock did (a
        loaded host widened a lockstep board's reach and let garbage through); None
        (hardware, a board on its own clock): the wall clock. With ``handled``, also the
        time of the hold bound and of the re-synchronisations' bounds.
    handled : callable, optional
        A lockstep mock's account (:class:`hapsim.spawn.HandledBytes` ``totals``):
        ``handled() -> (read, written)``, the bytes it has read from the host and written
        to it, every one handled. A command is then asked again (a missed tick's
        estimate or hold, a re-arming) only when the mock is *quiet* -- it has read every
        byte written here and every byte it wrote has been read -- and the command is
        still unanswered: its packet was lost or damaged (the link's injected faults),
        never because the mock was slow. The same command sequence, hence the same
        record, on a quiet host and a loaded one (module notes). Needs ``board_period``.

    Attributes
    ----------
    stats : dict
        ``commands`` (sent, one per host tick), ``records`` (taken as answers),
        ``missing`` (commands no record answered: missing samples), ``unprompted``
        (records with no command left to answer: a streaming firmware), ``resyncs``
        (device re-synchronisations), ``rearms`` (arming commands sent again while the
        device was silent at the start).

    Raises
    ------
    DeviceError
        The port cannot be opened.
    """

    def __init__(self, driver, port: str, delay: int = 1, read_timeout: float = 0.005,
                 reply_deadline: float = 0.0, delay_known: bool = True,
                 inertia: float | None = None, board_period: float | None = None,
                 handled=None) -> None:
        from hapsim.drivers.urlhandler import serial_for_url
        try:
            wt = 1.0 if handled is None else LOCKSTEP_WRITE_TIMEOUT_S   # (a lockstep mock)
            self._ser = serial_for_url(port, baudrate=driver.baud, rtscts=driver.rtscts,
                                       timeout=read_timeout, write_timeout=wt)
        except (OSError, ValueError) as exc:        # (serial.SerialException is an OSError)
            raise DeviceError(f"cannot open port {port}: {exc}") from None
        self.driver = driver
        self._d = int(delay)
        # for the driver's account: the delay when known (a scene's, a mock's); else None
        driver.loop_delay = self._d if delay_known else None
        self._init_late(driver)             # late replies kept as readings (late_replies)
        self._deadline_us = int(reply_deadline * 1e6)
        self._reach = bool(getattr(driver, "checks_reach", False))
        self._dec = (driver.decoder(inertia=inertia) if self._reach else driver.decoder())
        # the frame decoder told the time since the last record's command (its elapsed)
        self._frames = getattr(self._dec, "frames", self._dec) if self._reach else None
        self.decoder = _Dec(DriverStats(self._dec.stats))
        self._q: deque = deque()
        self._armed = self._ever_armed = False    # (_ever_armed: a CONFIG armed it once)
        self._t0 = time.monotonic_ns()
        self._last = deque(maxlen=16)
        # command ring: host time [us] each command was sent; seq of the newest command
        # sent (-1: none), of the newest answered, the force last commanded
        self._sent_us = [0] * _RING
        self._cmd = -1
        self._answered = -1
        self._force = 0.0
        self._x_last = self._x_prev = 0.0
        self._s_last = -1
        self._s_prev = None
        self._arm_ns = 0
        self._anchor_us = 0                 # host time of the last record's command [us]
        self._anchor_cmd = 0                # its seq (a lockstep board's time: commands)
        # the earliest command the last reply decoded can answer (the board answers its
        # writes in order, one reply each; a late board's reply read alone answers an
        # older command than the newest): its time bounds the reach's elapsed time
        self._floor = 0
        self._damaged = 0                   # the decoder's 'damaged' seen
        # replies of the frame before the last arming still to come, until when [s]
        self._old_left, self._old_until, self._stop_owed, self._late = 0, 0.0, 0, 0
        self._hist: deque = deque(maxlen=_RING)   # replies: (x, sample's earliest, latest [us])
        # the largest acceleration [rad/s^2]: force limit / inertia (None: no speed bound)
        self._accel = (float(driver.force_limit) / float(inertia)
                       if inertia is not None and math.isfinite(inertia) and inertia > 0
                       else None)
        self._board_T = None if board_period is None else float(board_period)
        if handled is not None and self._board_T is None:
            raise ValueError("a lockstep mock's account (handled) needs its board_period")
        self._handled = handled
        self._n_written = 0                 # bytes written to the port, read from it
        self._n_read = 0
        if handled is not None:
            self._claim()
        self._settle = 0
        # a board that takes commands on its own tick (driver.tick_s): where a write must
        # fall in it, measured at the first arming on the wall clock (tick_phase)
        self._tick_ns = int(round(float(getattr(driver, "tick_s", 0.0) or 0.0) * 1e9))
        self._write_at = None               # a monotonic_ns time of the boundary (or None)
        self._phase_z = None                # the writes' own phase, a running mean
        self._delay_ns = 0                  # the delay that puts them mid-tick
        self._over_ns = self._aligned_ns = self._grid_ns = 0   # (TickAligned's)
        self.tick_probe = None              # what the last probe found (report)
        self._write_tick = None             # the last write's (tick index, near) on it
        self._period_ticks = None           # the host's period in whole ticks, or None
        self._prev_tick = None              # (seq, tick index, near) of the last FORCE
        # the host ticks whose FORCE the board may have taken a tick early or late (its
        # write near the tick's boundary, or a hold of another number of ticks than the
        # period's): the driver's measurement cuts the record there (mistimed_rows)
        self.mistimed: set = set()
        driver.mistimed_seqs = self.mistimed
        # the board keeps its own tick (no lockstep mock): its unseen holds are sought
        driver.own_tick = bool(self._tick_ns) and handled is None and board_period is None
        # its own clock (Driver.holds_from_write), or a lockstep mock's, its commands'
        driver.own_clock = handled is None and board_period is None
        driver.command_period = None if handled is None else self._board_T
        self._tick_probed = False           # probed at the first arming
        self._stray = False                 # the last bytes read made no record
        self._t_write = -1.0                # time.monotonic() of the last write [s]
        self._desyncs = 0
        self._unreach = 0                   # the decoder's 'unreachable' seen
        self._lone = 0                      # the decoder's 'lone' seen
        self.stats = {"commands": 0, "records": 0, "missing": 0, "unprompted": 0, "rearms": 0,
                      "unprompted_before_arming": 0, "held_zero": 0, "host_stalls": 0,
                      "watchdog_zeroed": 0, "watchdog_replies": 0, "read_late": 0, "mispaired": 0}
        self._init_resync()                 # resyncs and their reasons (Resynchronising)
        self._init_watchdog(driver, port, driver.own_clock)   # (host_watchdog)
        self.info = {"kind": f"driver {driver.name}", "port": port, "baud": driver.baud,
                     "low_latency": False, "driver": driver.name,
                     "low_latency_note": "driver protocol"}
        try:
            self._ser.set_low_latency_mode(True)
            self.info["low_latency"] = True
        except (AttributeError, NotImplementedError, ValueError, OSError) as exc:
            self.info["low_latency_note"] = f"not available: {exc}".strip()

    def _now_us(self) -> int:
        return (time.monotonic_ns() - self._t0) // 1000

    def _clock(self) -> float:
        """The device's time [s]: a lockstep mock's (given ``handled``) is the commands'
        (commands sent times its period), whatever the host's wall clock did; otherwise
        the monotonic clock."""
        if self._handled is not None:
            return (self._cmd + 1) * self._board_T
        return time.monotonic()

    def _write(self, data: bytes, force: float = 0.0) -> None:
        """Write ``data``, encoded from ``force`` [N] (0: a set-up, an arming, a stop),
        which tells the host watchdog whether it leaves a force held (docs/drivers.md);
        the watchdog's writes made before it are commands of their own (host_watchdog)."""
        self._t_write = time.monotonic()
        self._n_written += len(data)
        try:
            if self.watchdog is None:
                self._ser.write(data)
            else:
                self._wd_take(self.watchdog.write(self._ser, data, force != 0.0))
        except Exception as exc:  # serial.SerialException, OSError, timeouts
            raise DeviceError(f"write to {self.info['port']} failed: {exc}") from None
        self._force = force                 # (the watchdog's writes taken came before)

    def _command(self, data: bytes, force: float = 0.0) -> None:
        """Send one command (one host tick), ``force`` as :meth:`_write`'s: number it and
        stamp it; to a board that takes commands on its own tick, once the write falls in
        the tick's middle (:meth:`tick_phase`)."""
        n = self.stats["commands"]
        self._wd_settle()                   # (the host watchdog's writes: host_watchdog)
        if self.stats["commands"] != n:
            # the watchdog's answers, read first, called for a re-synchronisation (zero
            # force first), which went out: this tick's command, not ``data`` (encoded
            # before, from a force the re-synchronisation has set to zero)
            return
        sent = self._now_us()
        quiet = self._quiet_now()           # (a realignment's silence: Resynchronising)
        if not quiet:
            if self._write_at is not None:
                self._wait_for_band()
                sent = self._now_us()
            self._write(data, force)        # (numbers the watchdog's writes before it)
        self._cmd += 1
        self._sent_us[self._cmd % _RING] = sent
        self._sent_bytes[self._cmd % _RING] = data
        self._stray = False                 # bytes read from now on are its answer
        self.stats["commands"] += 1
        if quiet:
            self._quiet_missing()
        self._wd_note()                     # (the board may have lost its place)

    def send(self, msg) -> None:
        """Translate one framed-protocol message into the driver's bytes (module notes)."""
        dr = self.driver
        t = type(msg)
        if t is fp.Force:
            f = msg.force[0]
            why = self._lost_place()
            if why:
                self._resync(why)
                return
            self._force = f
            self._write_tick = None
            self._command(dr.encode_force(f), f)
            if self._write_tick is not None and self._period_ticks:
                self._note_hold(msg.seq)
        elif t is fp.HelloRequest:
            self._q.append(fp.Hello(fp.PROTOCOL_VERSION, 1, dr.device_id, dr.position_scale,
                                    dr.force_scale, dr.force_limit, dr.native_rate_hz))
        elif t is fp.Ping:
            self._q.append(fp.Pong(msg.nonce, msg.host_time_us, self._now_us()))
        elif t is fp.Config:
            self._wd_poll()
            if self.watchdog is not None:
                self.watchdog.arm(False)    # (the listening waits on purpose)
            st = self._dec.stats
            seen = st.get("frames", 0) + st.get("unreachable", 0)
            owed = (max(0, self._cmd - self._answered) + self._stop_owed
                    if self._ever_armed else 0)
            self._listen(owed)
            # the replies still owed (a starved board's) and the arming's own first one
            # (its zero write, before its set-up) are in the frame before it: out of the
            # new offset's reach, they are no evidence (before: a re-arming with the joint
            # away from the offset re-synchronised the board, 5 re-armings in 6)
            got = st.get("frames", 0) + st.get("unreachable", 0) - seen
            self._old_left = 1 + max(0, owed - got) if self._ever_armed else 0
            self._old_until, self._stop_owed = time.monotonic() + SILENCE_LOST_S, 0
            self._desyncs, self._unreach, self._lone = (st.get(k, 0) for k in (
                "desync", "unreachable", "lone"))
            # the arming's set-up may restart the device's values (the Haply board sets
            # its angle to the set-up's offset): what came before predicts nothing, and
            # the arming is answered twice (a zero write before its set-up, one after)
            arming = self._arming_bytes()   # (the decoder's prediction restarts too)
            # the decoder's anchor (the set-up's offset) is as old as this arming
            self._anchor_us = self._now_us()
            self._anchor_cmd = self._cmd + 1
            self._floor = self._cmd - 1     # (the arming is answered twice)
            self._armed = self._ever_armed = True
            self._force = 0.0
            self._answered = self._cmd          # records of earlier commands are stale
            self._arm_ns = time.monotonic_ns()
            self._settle = int(dr.arming_records)
            self._prev_tick = None
            if self._tick_ns:
                # a period of whole ticks: every hold is that many (else they alternate
                # by nature, which the loop's model does not hold either)
                self._period_ticks = self._host_period(float(msg.rate_hz))
            if (self._tick_ns and self._handled is None and self._board_T is None
                    and not self._tick_probed):
                # once, at the first arming (the device at rest): a re-arming mid-run
                # keeps the board's grid (its tick does not move), and probing then held
                # zero force while the handle coasted (0.4 s, 12 cm, at three tries)
                self._tick_probed = True
                self.tick_phase()           # (its sweeps until two agree, or none)
            self._command(arming)
            if self.watchdog is not None:
                self.watchdog.arm()
        elif t is fp.Stop:
            self._wd_stop()                 # (its last writes' answers read: host_watchdog)
            self._armed, self._force = False, 0.0
            self.end_probe()                # (a ticking board: where its tick went)
            self._stop_owed = 2             # (its zero writes before and after its set-up)
            self._write(dr.stop_bytes(self._x_last))

    def _note_hold(self, seq: int) -> None:
        """After the FORCE of host tick ``seq`` was written to a ticking board: mark it
        mistimed (:attr:`mistimed`) when its write fell near the board's tick boundary, or
        the one before it did, or the board ticks between the two writes were not the
        period's (:meth:`hapsim.drivers.tick_align.TickAligned._note_tick`): the force
        before it was then held a tick longer or shorter than the loop's period, an input
        no reply names (docs/drivers.md, "Hapkit-serial: the sketch's tick")."""
        n, near = self._write_tick
        prev = self._prev_tick
        if near or (prev is not None and prev[0] == seq - 1
                    and (prev[2] or n - prev[1] != self._period_ticks)):
            if len(self.mistimed) < MISTIMED_MAX:
                self.mistimed.add(int(seq))
        self._prev_tick = (int(seq), n, near)

    def _drain(self, quiet_s: float) -> None:
        """Read and drop until the port has been silent ``quiet_s`` [s] (at most 1 s)."""
        ser = self._ser
        t0 = t = last = time.monotonic()
        while t - last < quiet_s and t - t0 < 1.0:
            data = ser.read(max(ser.in_waiting, 1))
            t = time.monotonic()
            if data:
                self._n_read += len(data)
                last = t

    def _listen(self, owed: int = 0) -> None:
        """Before arming: listen for :data:`LISTEN_S`, asking nothing; records beyond the
        ``owed`` answers (a late board's, a STOP's: read late by a loaded host, the .ino was
        once taken for the .pde) are a streaming firmware (``unprompted_before_arming``)."""
        dec = self._dec
        quiet = self._t_write + LISTEN_S
        end = max(time.monotonic(), quiet) + LISTEN_S
        try:
            while time.monotonic() < end:
                data = self._ser.read(max(self._ser.in_waiting, 1))
                if data:
                    self._n_read += len(data)
                    n = len(dec.feed(data))
                    answers, owed = min(n, owed), max(owed - n, 0)
                    if time.monotonic() >= quiet:
                        self.stats["unprompted_before_arming"] += n - answers
        except Exception as exc:  # serial.SerialException, OSError
            raise DeviceError(f"read from {self.info['port']} failed: {exc}") from None

    def overdue(self) -> bool:
        """Whether the newest command's answer is overdue: none came and the reply
        deadline passed (with a zero deadline, at once). The host loop then takes the tick
        as a missing sample and sends its FORCE anyway (module notes)."""
        if not (self._armed and self._settle <= 0 and self._answered < self._cmd):
            return False
        return self._given_up()

    def _given_up(self) -> bool:
        """The newest command's answer will not come: at once on hardware (its time went
        on); for a mock paced by the commands, once bytes came that made no record (a
        damaged answer: the mock stepped a period for it) and, with its account
        (``handled``), it is quiet, whatever the time; without one, 20 ms after those
        bytes, or after a long silence. A command that got no byte at all is no
        estimated sample on a lockstep mock: it may never have reached the mock, whose
        time then did not go on (:meth:`hold` asks again, no row)."""
        if self._handled is not None:
            return self._stray and self._quiet()
        if self._deadline_us <= 0:
            return True
        waited = self._now_us() - self._sent_us[self._cmd % _RING]
        return waited >= (self._deadline_us if self._stray else 10 * self._deadline_us)

    def _extrapolate(self, seq: int) -> float:
        """The position at command ``seq``, extrapolated linearly from the last two
        records (the one place it is done: an estimated sample, a re-synchronisation);
        NaN before two records came."""
        if self._s_prev is None or self._s_last <= self._s_prev:
            return float("nan")
        v = (self._x_last - self._x_prev) / (self._s_last - self._s_prev)
        return self._x_last + v * (seq - self._s_last)

    def estimate(self, out, seq: int, delay: int) -> float:
        """An estimated sample for command ``seq``, whose answer is overdue (the host
        loop's missing sample): ``out`` (an object with ``seq``, ``time_us``, ``status``,
        ``force_seq``, filled in place: no allocation per sample) gets the command's seq,
        the host time it was sent [us], the status of this transport's STATEs and
        ``seq - delay``; the position [m] extrapolated from the last two records is
        returned (NaN before two came: no estimate)."""
        x = self._extrapolate(seq)
        self._mark_estimated(seq)
        out.seq = seq
        out.time_us = self._sent_us[seq % _RING]
        out.status = fp.STATUS_ARMED | fp.STATUS_CONFIGURED
        out.force_seq = (seq - delay) & 0xFFFFFFFF
        return x

    def hold(self) -> None:
        """A host tick without a new sample: command the last force again (a request-reply
        device answers only what it is asked), or, while the device is re-synchronising,
        zero force. Called by the host loop on each missed tick."""
        # (asked again after the reply deadline, not the longer silence overdue waits
        # for: a packet lost on the way gets no answer at all, and the loop's silence
        # allowed is shorter; a lockstep mock with its account: once it is quiet)
        if not self._armed:
            return
        if self._answered == self._cmd or (
                self._quiet() if self._handled is not None
                else self._now_us() - self._sent_us[self._cmd % _RING] >= self._deadline_us):
            why = self._lost_place()
            if why:
                self._resync(why)
                return
            if self._s_last >= 0 and (
                    (self._cmd - self._s_last) * self._board_T > HOLD_BOUND_S
                    if self._handled is not None else self._now_us()
                    - self._sent_us[self._s_last % _RING] > HOLD_BOUND_S * 1e6):
                # no fresh sample for HOLD_BOUND_S: the force was computed from where the
                # device was, not where it is; a board without a watchdog would hold it
                self._force = 0.0
                self.stats["held_zero"] += 1
            self._command(self.driver.encode_force(self._force), self._force)

    def host_stalled(self, ticks: int) -> None:
        """The host loop missed ``ticks`` of its deadlines at once (the host stalled): no
        catch-up writes are sent for them (the device held its force meanwhile, a known
        input); when every command is answered, ``seq`` skips those ticks, so a
        measurement does not run across the stall as if it were one period (the host
        loop calls this).

        Parameters
        ----------
        ticks : int
            Deadlines missed, >= 1.
        """
        self.stats["host_stalls"] += 1
        if not self._armed or self._answered != self._cmd or ticks < 1:
            return
        t_us = self._sent_us[self._cmd % _RING]
        for _ in range(int(ticks)):
            self._cmd += 1
            self._sent_us[self._cmd % _RING] = t_us
            self._sent_bytes[self._cmd % _RING] = b""     # numbers, no writes
        self._answered = self._cmd
        self.stats["missing"] += int(ticks)

    def _take(self, xs: list, out: list) -> None:
        """Records decoded in one read -> STATEs: the last answers the newest command sent,
        the ones before it the commands before that (module notes)."""
        st = self.stats
        if not self._armed:
            # before the first arming a record nobody asked for (a streaming firmware,
            # still heard by each arming's _listen); after a STOP the answer to a command
            # before it or to its zero force, read late by a loaded host (the FireFader's
            # .ino was taken for the .pde in 2 of 4 runs beside two hogs): dropped
            if not self._ever_armed:
                st["unprompted_before_arming"] += len(xs)
            return
        if self._settle > 0:
            # zero force while the device's own force comes up (Driver.arming_records)
            self._settle -= len(xs)
            self._answered = self._cmd
            self._arm_ns = time.monotonic_ns()
            self._command(self.driver.encode_force(0.0))
            return
        n = len(xs)
        newest = self._cmd - self._answer_shift(n)
        first = newest - n + 1
        self._note_late(first, xs, first == self._answered + 1
                        and self._dec.stats.get("damaged", 0) == self._damaged)
        for k, x in enumerate(xs):
            s = first + k
            if s <= self._answered:
                st["unprompted"] += 1          # nothing left for it to answer
                continue
            if self._wd_answer(s):             # the host watchdog's zero write's
                st["missing"] += s - self._answered - 1
                self._answered = s
                continue
            st["missing"] += s - self._answered - 1
            st["records"] += 1
            self._answered = s
            if self._s_last >= 0:
                # (before the first record there is none: the host's initial 0 at seq -1
                # is no reading; taken as one, the first record's position per tick was
                # extrapolated as a velocity: estimated samples and a re-synchronisation's
                # offset 0.2 rad a tick off)
                self._x_prev, self._s_prev = self._x_last, self._s_last
            self._x_last, self._s_last = x, s
            self._anchor_cmd = s
            out.append(fp.State(s & 0xFFFFFFFF, self._sent_us[s % _RING],
                                fp.STATUS_ARMED | fp.STATUS_CONFIGURED,
                                (s - self._d) & 0xFFFFFFFF, (x,)))

    def receive(self, timeout: float = 0.0) -> list:
        """Messages: queued HELLO/PONG, and one STATE per record taken (module notes).

        With a lockstep mock's account (``handled``), bytes are read only once the mock
        has handled every byte written to it, and then all it wrote: each decision taken
        on them (a record's command, a desync's re-synchronisation) sees the whole
        answer to everything sent, however the mock's writes were cut up in time.

        Parameters
        ----------
        timeout : float
            Longest wait [s] for a first message.

        Returns
        -------
        list of firmware_protocol messages
        """
        out = list(self._q)
        self._q.clear()
        ser = self._ser
        self._wd_poll()
        end = time.monotonic() + timeout
        lockstep = self._handled is not None
        try:
            while True:
                if lockstep:
                    data = self._read_handled()
                else:
                    waiting = ser.in_waiting
                    if waiting:
                        self._wd_poll()     # (its writes before the bytes are decoded)
                        data = ser.read(waiting)
                    elif timeout > 0 and not out:
                        data = ser.read(1)
                        self._wd_poll()     # (its writes before the bytes are decoded)
                    else:
                        data = b""
                if data:
                    self._feed(data, out)
                if (self._armed and (self._answered < 0 or self._settle > 0) and not out
                        and time.monotonic_ns() - self._arm_ns > REARM_INTERVAL * 1e9
                        and (not lockstep or self._quiet())):
                    # no first record yet: a board still in its bootloader dropped the
                    # arming command, or a record was lost while the force comes up (no
                    # host tick asks again then); ask again
                    self._arm_ns = time.monotonic_ns()
                    self.stats["rearms"] += 1
                    if self._answered < 0:
                        self._arm_again()
                    else:
                        self._command(self.driver.encode_force(0.0))
                if out or timeout <= 0 or time.monotonic() >= end:
                    return out
                if lockstep and not data:
                    time.sleep(2e-4)
        except Exception as exc:  # serial.SerialException, OSError
            raise DeviceError(f"read from {self.info['port']} failed: {exc}") from None

    def _feed(self, data: bytes, out: list) -> None:
        """Bytes read: decoded, their records taken, a desync or an unreachable reading
        answered with a re-synchronisation."""
        dec = self._dec
        self._n_read += len(data)
        self._last.append(data)         # hex only when a message shows it
        if self._frames is not None:
            # the board sampled the last record when its command arrived (not before it
            # was sent): what the joint can have moved since bounds the readings
            # believed now
            if self._board_T is None:
                self._frames.elapsed((self._now_us() - self._anchor_us) * 1e-6,
                                     self._speed_bound())
            else:
                self._frames.elapsed(max(self._cmd - self._anchor_cmd, 1) * self._board_T)
        floor0 = self._floor
        xs = dec.feed(data)
        self._stray = not xs
        dmg = dec.stats.get("damaged", 0)
        if xs:
            self._silence_ended()           # (a silence waited for ends here)
            # the commands the board may be behind: those unanswered when its answers came,
            # consumed by the answers that follow (a late board's backlog)
            self._late = max(self._late - len(xs), self._cmd - self._answered)
            self._take(xs, out)
            # the last reply answers at the earliest the command after the one the reply
            # before could, one per reply (damaged too), no further back than the lateness
            # allows and 3 more (a count alone lags by every answer lost): the reach runs
            # from its time (before: from the newest command's, and a starved board's late
            # reply read alone made the backlog's after it "out of reach")
            self._floor = max(min(self._cmd, self._floor + len(xs) + dmg - self._damaged),
                              self._cmd - self._late - 3, self._cmd - _RING + 1)
            self._anchor_us = self._sent_us[self._floor % _RING]
            if self._frames is not None:
                now = self._now_us()
                for i, x in enumerate(xs):
                    c = min(self._floor, floor0 + i + 1)
                    self._hist.append((x, self._sent_us[c % _RING], now))
        else:
            self._rx_since_record += len(data)
        self._damaged = dmg
        d = dec.stats.get("desync", 0)
        u = dec.stats.get("unreachable", 0)
        lone = dec.stats.get("lone", 0)
        if self._old_left > 0:
            self._old_left -= len(xs) + (u - self._unreach)
            if (d == self._desyncs and u != self._unreach
                    and time.monotonic() < self._old_until):
                self._unreach = u           # a reply of the frame before the arming
                self._rx_since_record = 0
        if d != self._desyncs or u != self._unreach:
            # a desync, or a well-formed reply no motion reaches from the last record (a
            # set-up the stream corrupted answers in another frame; waiting would let
            # the reach grow until it is believed): put the board back in step now
            why = ("lone" if lone != self._lone else "desync" if d != self._desyncs
                   else "unreachable")
            self._desyncs, self._unreach, self._lone = d, u, lone
            if self._armed:
                self._resync(why)
        self._wd_note()                     # (the board may have lost its place)

    def _speed_bound(self):
        """A bound on the joint's speed at the last reply decoded [deg/s], or None (no two
        replies far enough apart yet): for replies i before j whose samples are at least
        :data:`SPEED_BASE_S` apart by the host's times (each sampled between its earliest
        command's sending and its read: ``dlo`` = j's earliest - i's latest, ``dhi`` = j's
        latest - i's earliest), the mean speed over the two, ``(|x_j - x_i| + 2 q) /
        dlo`` (q: one count, each reading's rounding), plus what the largest acceleration
        adds over ``dhi`` (the mean value theorem: the speed at j is the mean's within
        ``alpha dhi``, alpha the force limit over the inertia). The newest such pair.
        Known by the decoder's reach
        (:meth:`hapsim.drivers.haply.ReplyDecoder.elapsed`)."""
        h = self._hist
        if self._accel is None or len(h) < 2:
            return None
        q = float(self.driver.position_scale)         # one count [rad]
        xj, loj, hij = h[-1]
        for xi, loi, hii in reversed(h):
            dlo = (loj - hii) * 1e-6
            if dlo >= SPEED_BASE_S:
                return math.degrees((abs(xj - xi) + 2.0 * q) / dlo
                                    + self._accel * (hij - loi) * 1e-6)
        return None

    def report(self) -> dict:
        """What the driver's link did: :attr:`stats` and the firmware seen (``firmware``:
        the driver's ``streaming_firmware`` when records came before anything was asked
        (:data:`LISTEN_S` of listening at each arming), else its ``answering_firmware``;
        ``None`` before any record); for a board that ticks (``driver.tick_s``) on the wall
        clock, ``tick_probe`` (:meth:`tick_phase`'s last finding, None when it found none)
        and ``tick_aligned`` (whether the writes were timed in the tick's middle)."""
        st = dict(self.stats)
        st["resync_reasons"] = dict(self.stats["resync_reasons"])
        if self._tick_ns and self._handled is None and self._board_T is None:
            st["tick_probe"] = None if self.tick_probe is None else dict(self.tick_probe)
            st["tick_aligned"] = self._write_at is not None
            st["tick_landed_median"], st["tick_moved"] = (self.tick_landed_median(),
                                                          self.driver.tick_moved)
        st["decoder"] = dict(self._dec.stats)
        st["firmware"] = (self.driver.streaming_firmware if st["unprompted_before_arming"]
                          else self.driver.answering_firmware if st["records"] else None)
        st["watchdog"] = self._watchdog_report()
        return st

    def close(self) -> None:
        """Close the port (idempotent): zero force first (a device may hold it)."""
        if self.watchdog is not None:
            self.watchdog.close()
        try:
            if self._ser.is_open:
                self._ser.write(self.driver.stop_bytes(self._x_last))
                self._ser.flush()
        except Exception:  # best effort: the port may be gone
            pass
        try:
            self._ser.close()
        except Exception:  # pragma: no cover
            pass

    def last_frames(self) -> str:
        """The last chunks of bytes received, as hex (docs/design.md, rule 11)."""
        return "\n".join(chunk.hex() for chunk in self._last)
