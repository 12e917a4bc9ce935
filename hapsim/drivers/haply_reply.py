"""The Haply M3's host-side reply decoder (:class:`ReplyDecoder`), split out of
:mod:`hapsim.drivers.haply` (which re-exports it): the checks a reply passes before it is
taken (the id, a finite angle within range, a whole number of encoder counts, within the
joint's reach since the earliest command it can answer) and the count of bytes that make no
reply (``desync``). The layout and the firmware's behaviour it reads are in
:mod:`hapsim.drivers.haply`'s notes (Haply "Arduino firmware" V1.5, S. Ding and
C. Gallacher, 2017).
"""

from __future__ import annotations

import math
import struct
import time

from hapsim.drivers.decoders import AlignedDecoder

__all__ = ["ReplyDecoder", "DESYNC_BYTES"]


#: Bytes skipped since the last good reply that mean the board lost its place: more than
#: two replies' worth of single faults on the way back (a lost byte skips at most 4 bytes,
#: a corrupted one 5); a board that lost its set-up answers 1 byte per write, so this is
#: about 11 writes. That of the M3's 5-byte reply: a decoder of ``L``-byte replies counts
#: ``2 L + 1`` (:attr:`ReplyDecoder.desync_bytes`; the 2DIY's 9-byte replies, 19).
DESYNC_BYTES = 11


class ReplyDecoder(AlignedDecoder):
    """Host side: 5-byte replies ``[id][float32 deg]`` out of a byte stream (or, with
    ``angles`` encoders of one id, ``1 + 4 angles``-byte replies, each angle checked).

    A reply is taken where the id matches and the angle is finite, within
    ``max_angle_deg``, within ``max_step_deg`` of where the last two replies say the joint
    is going, and a whole number of encoder counts (the firmware sends
    ``360 * count / resolution``: the window ``01 01 01 3f c5``, -3056.06 deg, is 41426.4
    counts at 4880 per revolution, no reply); otherwise one byte is dropped and the next
    position tried. :attr:`desync_bytes` (:data:`DESYNC_BYTES` for 5-byte replies, ``2 L +
    1`` for ``L``-byte ones) or more bytes dropped since the last reply mean the
    stream lost its format: the board answers something else than the replies it was set
    up for (counted in ``desync``, once per run of bad bytes, again every 100 bytes).

    Parameters
    ----------
    device_id : int
    max_angle_deg : float
        Largest plausible angle [deg].
    resolution : float or None
        Encoder counts per revolution (None: the whole-count check is off).
    max_step_deg : float
        Largest distance of a reply from the linear prediction of the last two taken
        [deg] when it comes within ``period_s`` of the last (2 deg: an acceleration of
        35000 rad/s^2 at 1 kHz, or a missed reply at 30 rad/s); a reply farther off is
        misaligned or corrupted. Later replies get the reach of :meth:`reach_deg` over
        the time that passed: a board on its own clock moved on while the host was late
        or stalled, and that is no evidence of a lost place.
    period_s : float
        The period the step bound is stated for [s] (1 ms).
    clock : callable
        Monotonic time [s] of a read (``time.monotonic``): the time between two reads is
        the elapsed time of :meth:`reach_deg` unless the host states it
        (:meth:`elapsed`).
    angles : int, optional
        Encoders in a reply (1: the angle is returned as a float; more: a tuple, in port
        order, and ``resolution`` may give one per encoder).
    accel : float, optional
        Largest angular acceleration of the joint(s) [rad/s^2]: the board's torque clamp
        over the smallest joint inertia (:meth:`set_accel`). None: ``max_step_deg`` per
        period squared (no physics known: 35000 rad/s^2 at 1 kHz).
    arm_deg : float or tuple, optional
        The angle(s) the arming's set-up sets the encoder(s) to [deg]: the replies after
        an arming (:meth:`reset_prediction`) are checked against it, not taken blind.

    Attributes
    ----------
    stats : dict
        ``frames`` (replies), ``skipped`` (bytes dropped realigning), ``desync``,
        ``damaged`` (replies the dropped bytes held, short of a desync), ``unreachable``
        (well-formed replies out of the reach of :meth:`reach_deg`: a frame another
        set-up made, or a misaligned window that looked like a reply), ``lone`` (desyncs
        counted at once on three writes answered by the id alone: a board that lost its
        set-up; before, after :attr:`desync_bytes` of them).
    desync_bytes : int
        Bytes dropped in a row that are a desync: more than two replies' worth.
    """

    length = 5

    def __init__(self, device_id: int, max_angle_deg: float = 3600.0,
                 resolution=None, max_step_deg: float = 2.0, angles: int = 1,
                 period_s: float = 1e-3, clock=time.monotonic, accel=None,
                 arm_deg=None) -> None:
        super().__init__()
        self.period_s = float(period_s)
        self._clock = clock
        self._t_read = self._t_prev = None
        self._tau = None
        self._speed = None                # a bound on the speed [deg/s] (elapsed)
        self._accel_deg = None
        self.set_accel(accel)
        self.arm_deg = arm_deg
        self.angles = int(angles)
        self.length = 1 + 4 * self.angles
        # more than two replies' worth of single faults on the way back (DESYNC_BYTES for
        # 5 bytes). With 11 for the 2DIY's 9-byte replies two replies in a row that each
        # lost a byte (8 + 8 bytes skipped, about 1 in 500 pairs at 1 byte in 200 lost)
        # were a desync: the board, in step, re-synchronised (2-3 a run, issue 29)
        self.desync_bytes = 2 * self.length + 1
        self._fmt = struct.Struct("<" + "f" * self.angles)
        self.max_step = float(max_step_deg)
        self._prev = self._prev2 = None
        self.id = device_id & 0xFF
        self.max = float(max_angle_deg)
        if resolution is None:
            self.res = None
        elif isinstance(resolution, (int, float)):
            self.res = (float(resolution),) * self.angles
        else:
            self.res = tuple(float(r) for r in resolution)
        # one encoder count [deg] per angle (0: no whole-count check, no count term)
        self._count = tuple(360.0 / r if r > 0 and math.isfinite(r) else 0.0
                            for r in self.res) if self.res else (0.0,) * self.angles
        self.stats["desync"] = 0
        self.stats["damaged"] = 0
        self.stats["unreachable"] = 0
        self.stats["lone"] = 0
        self._lone = False
        self._bad = 0
        self._free = 0

    def feed(self, data: bytes) -> list:
        """Replies out of the bytes of one read (the read's time scales the step bound:
        ``max_step_deg``).

        Parameters
        ----------
        data : bytes

        Returns
        -------
        list
            The angles [deg] decoded (tuples with several encoders).
        """
        self._t_read = self._clock()
        return super().feed(data)

    def clear(self) -> None:
        """Drop the bytes held and the run of dropped bytes counted so far: a re-arming
        drains the link, and the bytes skipped before it are no reply's that follows (left
        counted, the first good reply after the set-up was taken as answering a damaged
        reply before it: the set-up's reply read as the next write's, a bad set-up)."""
        super().clear()
        self._bad = 0

    def set_accel(self, accel) -> None:
        """State the joint's largest angular acceleration [rad/s^2] (None: the default of
        the class notes): the board's torque clamp over the smallest joint inertia (a hand
        on the handle only adds inertia).

        Parameters
        ----------
        accel : float or None
            [rad/s^2], finite and > 0; None: the default.

        Raises
        ------
        ValueError
            ``accel`` not finite and > 0.
        """
        if accel is None:
            self._accel_deg = None
            return
        if not (math.isfinite(accel) and accel > 0):
            raise ValueError(f"accel must be a finite acceleration > 0 [rad/s^2], got "
                             f"{accel!r}")
        self._accel_deg = math.degrees(float(accel))

    def elapsed(self, tau, speed_deg=None) -> None:
        """The host states the time [s] from the write the last reply taken answered to
        now (an upper bound of the time between the two samples: the board samples when
        a write arrives), for the replies of the next reads; None: the time between the
        reads (the class notes). A host that knows its writes' times states it: a reply
        read late was still sampled when its write arrived.

        ``speed_deg``: a bound on the joint's speed at the last reply taken [deg/s], from
        the host's times of two replies far enough apart
        (:meth:`hapsim.drivers.transport.DriverTransport._speed_bound`), or None. The
        last two replies' step stands for the speed over one period; two replies sampled
        close together (a late board's backlog, 50 us apart) make it ~0, and a joint
        moving at speed was then "out of reach" a few ms later. With a bound, the speed
        the reach assumes is never below it (:meth:`reach_deg`).

        Parameters
        ----------
        tau : float or None
            Time from the last taken reply's write to now [s]; None: the reads' times.
        speed_deg : float, optional
            A bound on the joint's speed at the last reply taken [deg/s]; None: none.
        """
        self._tau = None if tau is None else float(tau)
        self._speed = None if speed_deg is None else float(speed_deg)

    def reach_deg(self, k: int, tau) -> float:
        """How far [deg] a reply ``tau`` seconds after the last one taken may be from the
        linear prediction of the last two (one period ahead), encoder ``k``: the motion
        the largest acceleration allows, with the prediction's lag and the encoder's whole
        counts.

        With r = max(1, tau / T) (T = ``period_s``), v = |q1 - q2| the last step and
        alpha the acceleration [deg/s^2] (``accel``): the joint is then within
        ``(r - 1) v + alpha tau^2`` of the prediction (Taylor's theorem: 1/2 alpha tau^2,
        a factor 2 of margin for the velocity's own error), never less than
        ``max_step_deg``, plus ``2 r + 2`` counts (each reading is a whole count: the
        prediction off by 3, its slope by 2 a period; the reply by 1). The same rule the
        2DIY's host states its elapsed time to (:mod:`hapsim.pipeline.haply2_record`).

        Parameters
        ----------
        k : int
            Encoder index in the reply.
        tau : float or None
            Time since the last reply taken [s] (None: one period).

        Returns
        -------
        float
        """
        T = self.period_s
        r = 1.0 if tau is None else max(1.0, tau / T)
        tau = r * T
        acc = self._accel_deg if self._accel_deg is not None else self.max_step / (T * T)
        v = self._step_v(k)
        step = max(self.max_step, (r - 1.0) * v + acc * tau * tau)
        return step + (2.0 * r + 2.0) * self._count[k]

    def _step_v(self, k: int) -> float:
        """The joint's motion per period the reach assumes, encoder ``k`` [deg]: the last
        two replies' step, never below the host's stated speed bound times the period
        (:meth:`elapsed`)."""
        v = 0.0
        if self._prev is not None and self._prev2 is not None:
            v = abs(self._prev[k] - self._prev2[k])
            v = v if v == v else 0.0
        if self._speed is not None:
            v = max(v, self._speed * self.period_s)
        return v

    def reset_prediction(self, jumps: int = 1, anchor=None) -> None:
        """Forget the last replies (an arming: the angles start afresh at the set-up's
        offset). With an anchor (``anchor``, else the decoder's ``arm_deg``) the
        prediction restarts there, with no velocity: the next replies are checked against
        it (the reach of :meth:`reach_deg` from the arming on), so a reply of a set-up the
        stream corrupted (another offset: a frame no motion reaches) is not taken; an
        answer from before the set-up, at the old angle, is dropped too. Without one, the
        next ``jumps`` replies are taken without the step check, each restarting the
        prediction (the 2DIY's arming checks its first reply against its offsets
        itself).

        Parameters
        ----------
        jumps : int
            Replies taken unchecked when there is no anchor.
        anchor : float or tuple, optional
            The set-up's angle(s) [deg].
        """
        anchor = self.arm_deg if anchor is None else anchor
        self._prev2 = None
        if anchor is None:
            self._prev = None
            self._free = int(jumps)
            return
        a = (anchor,) if isinstance(anchor, (int, float)) else tuple(anchor)
        self._prev = tuple(float(x) for x in a)
        self._free = 0
        self._t_prev = self._clock()

    def parse(self, buf):
        """The angle [deg] (a tuple of ``angles``, port order, when more than one) of a
        reply at the start of ``buf``, or None.

        Parameters
        ----------
        buf : bytearray
            At least :attr:`length` (``1 + 4 angles``) bytes.

        Returns
        -------
        float or tuple of float or None
            The angle [deg] (``angles`` 1), the angles in port order [deg], or None (no
            reply: a wrong id, an angle not finite, out of range, not a whole count, or
            out of reach, counted in ``unreachable``).
        """
        # (index loops, floats only: the real-time loops decode without allocating)
        self._lone = False
        if buf[0] != self.id:
            return None
        a = self._fmt.unpack_from(buf, 1)
        res = self.res
        na = self.angles
        # three id bytes in a row that make no reply: writes answered by the id alone,
        # as a board answers when it has no encoder at that address (a reset or a set-up
        # out of garbage forgot its set-up: Haply_M3_Firmware_V1_5.h read_states); a byte
        # lost or corrupted on the way back leaves the id and 3 or 4 bytes of an angle
        lone = buf[1] == self.id and buf[2] == self.id
        k = 0
        while k < na:
            v = a[k]
            if not (math.isfinite(v) and abs(v) <= self.max):
                self._lone = lone
                return None
            if res is not None:
                # the firmware's 360 * count / resolution, rounded once to binary32: a
                # count of 0 is exactly 0.0 (a tiny garbage float is no reply); the
                # nearest whole count as a float (remainder rounds half to even, as
                # round does)
                n = v * res[k] / 360.0
                n -= math.remainder(n, 1.0)
                want = 360.0 * n / res[k]
                if abs(v - want) > 1e-6 * abs(want):
                    self._lone = lone
                    return None
            k += 1
        if self._free:
            # a jump allowed (reset_prediction): predict from this reply on
            self._free -= 1
            self._t_prev = self._t_read
            self._prev2, self._prev = None, a
            return a[0] if self.angles == 1 else a
        if self._prev is not None:
            # a flipped exponent bit is still a whole count (x 2^k, half the time), and a
            # set-up the stream corrupted answers whole counts of another offset: no
            # joint moves that far from where its last two replies say it is going, in the
            # time that passed (reach_deg: the host's stated time, else the reads')
            tau = self._tau
            if tau is None and self._t_read is not None and self._t_prev is not None:
                tau = self._t_read - self._t_prev
            k = 0
            while k < na:
                step = self.reach_deg(k, tau)
                p1 = self._prev[k]
                guess = p1 if self._prev2 is None else 2.0 * p1 - self._prev2[k]
                # off the linear prediction, a reply is still a joint's motion when it
                # moved no more than last time plus the step: the board samples when a
                # write arrives, so two replies a late host's writes brought close
                # together are close in time too, though the last two were far apart
                if abs(a[k] - guess) > step and (
                        self._prev2 is None
                        or abs(a[k] - p1) > self._step_v(k) + step):
                    # a well-formed reply no motion reaches: counted (the host takes it
                    # for evidence that the board answers in another frame)
                    self.stats["unreachable"] += 1
                    return None
                k += 1
        self._t_prev = self._t_read
        self._prev2, self._prev = self._prev, a
        return a[0] if self.angles == 1 else a

    def starts_frame(self, byte: int) -> bool:
        """Whether a reply can start with ``byte``: the id (the byte after a one-byte
        answer the host asked for, :meth:`hapsim.drivers.decoders.AlignedDecoder.mark_at`;
        :attr:`confirm_next` is off).

        Parameters
        ----------
        byte : int

        Returns
        -------
        bool
        """
        return byte == self.id

    def accept(self, value) -> bool:
        """A reply taken: the run of dropped bytes before it ends; the replies it held
        are counted in ``damaged`` (a run of ``s`` bytes held ``ceil(s / length)``: a
        byte lost leaves ``length - 1``, a corrupted reply ``length``; a run long enough
        to be a desync is the re-synchronisation's, not counted).

        Parameters
        ----------
        value : float or tuple of float
            The reply :meth:`parse` gave [deg].

        Returns
        -------
        bool
            Always True.
        """
        if self._bad:
            if self._bad < self.desync_bytes:
                self.stats["damaged"] += -(-self._bad // self.length)
            self._bad = 0
        return True

    def on_skip(self) -> None:
        """A byte dropped: after :attr:`desync_bytes` in a row (and every 100 more while
        it lasts) a ``desync`` is counted. The prediction is kept: the re-synchronisation
        sets the encoder to the host's estimate of where the joint is, so the replies after
        it are still within reach of the last one taken (before, the next reply was taken
        unchecked: a garbage one, whole counts of 7.4 rad, was believed and stopped the
        run)."""
        self._bad += 1
        if self._lone and self._bad < self.desync_bytes:
            # the board answers the id alone (parse): it lost its set-up; a desync now,
            # not after desync_bytes of them (the run counts as that long)
            self._lone = False
            self._bad = self.desync_bytes
            self.stats["desync"] += 1
            self.stats["lone"] += 1
            return
        if self._bad % 100 == self.desync_bytes:
            self.stats["desync"] += 1
