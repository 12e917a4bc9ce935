"""The small interface every driver implements (see :mod:`hapsim.drivers`); its frame
decoders are in :mod:`hapsim.drivers.decoders`."""

from __future__ import annotations

import math

__all__ = ["Driver", "FLAG_ESTIMATED", "LATE_WINDOW", "LATE_STOP", "binary32_commands"]

#: The telemetry ``flags`` bit of an estimated sample
#: (:data:`hapsim.host.telemetry.FLAG_ESTIMATED`, repeated so that the drivers import
#: nothing of the daemon above them).
FLAG_ESTIMATED = 32
#: A driver's run on the wall clock stops (safety) when its host was late, summed over the
#: ticks late by a period or more among the last LATE_WINDOW, by more than LATE_STOP of
#: the window's time (a board without a watchdog held older torques that long): the host
#: loop's rule (:class:`hapsim.host.loop.HostLoop`) and the Falcon's
#: (:func:`hapsim.emulated.falcon_device.drive_falcon`), here where both sides read it.
LATE_WINDOW = 100
LATE_STOP = 0.5
class Driver:
    """Base class of the drivers: serial settings, units and codec of one device.

    Attributes
    ----------
    name : str
        ``--driver`` name.
    baud : int
        Baud rate.
    rtscts : bool
        Hardware flow control.
    position_scale : float
        Position resolution [m/count] (or [rad/count]).
    force_scale : float
        Force resolution [N/count] (or [N m/count]).
    force_limit : float
        Largest force the protocol can carry [N].
    native_rate_hz : float
        Rate the device is usually run at [Hz].
    device_id : int
        Reported as HELLO.device_id.
    limits : str
        What the protocol cannot do, for ``--help`` and docs/devices.md.
    position_rel, force_rel : float
        Largest relative rounding of the position / force fields on the wire (``2^-24``
        for IEEE-754 binary32, 0 when exact): the run's stated uncertainty covers it
        (:func:`hapsim.pipeline.measure.identify_run`).
    """

    name = ""
    baud = 115200
    rtscts = False
    position_scale = 0.0
    force_scale = 0.0
    force_limit = 0.0
    native_rate_hz = 1000.0
    device_id = 0
    limits = ""
    position_rel = 0.0
    force_rel = 0.0
    #: What :meth:`hapsim.drivers.transport.DriverTransport.report` says of a firmware
    #: that answers each command, and of one that streams records unprompted.
    #: Records to let pass after arming, at zero force, before the first sample: a
    #: firmware whose force comes up slowly (the FireFader's enable ramp) is full by then.
    arming_records = 0
    #: The device parameter an added-mass calibration finds (``hapsim identify
    #: --added-mass``; :mod:`hapsim.analysis.calibration`) and what it scales
    #: (``"force"`` or ``"position"``); None: the protocol carries SI units.
    scale_option: str | None = None
    scale_kind = "force"
    #: The axis turns (one joint): a scene's and an identification's values are in
    #: rotary units (inertia [kg m^2], torque [N m], angle [rad]), not [kg], [N], [m].
    rotary = False
    #: What ``hapsim identify`` through this protocol takes where no scene says: the
    #: embedded mock's device (:class:`hapsim.scene.Device` fields over
    #: :data:`hapsim.device_model.DEFAULT_DEVICE`) and the envelope [the protocol's
    #: units]; None: hapsim's defaults (:mod:`hapsim.pipeline.identify_settings`).
    identify_device: dict | None = None
    identify_envelope: float | None = None
    #: The device's position scale can be found by a sweep between its end stops
    #: (``hapsim identify --travel``; :mod:`hapsim.drivers.firefader_travel`).
    travel_sweep = False
    #: The ports one board carries in every command and record: a scene with that many
    #: ports whose devices all speak this protocol runs them on one board, in real time
    #: (:mod:`hapsim.pipeline.faders_run`); 1: a board per port.
    ports_per_board = 1
    #: The device answers each command with one record (request-reply): a command whose
    #: answer is overdue is a missing sample that the host loop steps through with an
    #: estimated position (:meth:`hapsim.drivers.transport.DriverTransport.overdue`,
    #: ``estimate``, ``hold``): the capability the loop reads, not the transport's methods.
    request_reply = True
    #: The device's parser has no framing: answers that stop while commands go out mean
    #: it may be inside a garbage command (the transport re-synchronises it).
    unframed = False
    answering_firmware = "answers each command"
    streaming_firmware = "streams records unprompted"
    #: The host ticks whose force a board on its own tick may have taken a tick early or
    #: late (set by the run's :class:`hapsim.drivers.transport.DriverTransport`: its
    #: ``mistimed``); None: none known (:meth:`mistimed_rows`).
    mistimed_seqs: set | None = None
    #: How far the board's tick moved against the host's writes over the run (set by the
    #: run's transport at its end, :meth:`hapsim.drivers.tick_align.TickAligned.
    #: end_probe`); None: not probed.
    tick_moved: dict | None = None
    #: The run's board takes commands on its own tick, on its own clock (set by the run's
    #: transport; a lockstep mock's is not): the measurement seeks the holds it mistimed
    #: that no host saw (:func:`hapsim.pipeline.measure.identify_run`).
    own_tick = False
    #: The board holds each force from when it takes the write to when it takes the next
    #: (no tick of its own, no watchdog: the Haply M3, firmware V1.5), so each hold lasts
    #: the time between two writes' arrivals, not a period: the measurement corrects the
    #: record for the host's write times (:func:`hapsim.analysis.write_holds.
    #: write_time_terms`) when the run's board keeps its own clock (:attr:`own_clock`).
    holds_from_write = False
    #: The longest a board holds a force with no write before it zeroes it itself [s]:
    #: its watchdog or silence rule (the FireFader's ``.ino``: 0.1 s); ``inf`` for none
    #: (the Haply M3, firmware V1.5; the Hapkit serial sketch), and for a driver that
    #: does not say. Beyond :data:`hapsim.drivers.resync.HOLD_BOUND_S`, on a board on its
    #: own clock, the transport runs the host's watchdog beside it
    #: (:mod:`hapsim.drivers.host_watchdog`).
    holds_force_s = math.inf
    #: The run's board keeps its own clock (set by the run's transport; a lockstep mock,
    #: stepped one period per command, does not).
    own_clock = False
    #: Whether the board reads its sensor as late as the host's write comes (the Hapkit
    #: sketch for most write phases): on its own tick (:attr:`own_tick`; a lockstep mock's
    #: time is the commands'), the writes' jitter is its readings' noise
    #: (:func:`hapsim.analysis.measurement.aperture_noise`).
    samples_at_write = False
    #: Periods by which the host may take the board's reading late while the board runs on
    #: (its reply can come so near the host's next deadline that a host waking a little
    #: late steps the loop with the reading before it): a loop that such a late reading
    #: makes unstable is refused by the run and called unstable by ``check``
    #: (:func:`hapsim.pipeline.render_latency.timed_prediction`,
    #: ``late_reading_unstable``). 0: the host takes every reading in its period.
    late_reading_periods = 0
    #: A lockstep mock's time per command [s] (set by the run's transport; None for a
    #: board on its own clock): what its firmware's silence rule counts, not the host's
    #: wall clock, which a loaded host stretches.
    command_period: float | None = None

    def mistimed_rows(self, columns: dict):
        """Rows whose force was held a tick longer or shorter than the loop's period, or
        whose reading was found paired with another command, left out of the measurement,
        or None.

        A board that takes commands on its own tick (the Hapkit sketch's 1 ms) takes a
        write near its tick's boundary at one tick or the next, and a write a host made
        late by more than half a tick at the next: the force before that write is then
        held a tick longer (or shorter), and its own a tick shorter (or longer), which no
        reply says. The transport marks such host ticks from its own write times against
        the probed boundary (:meth:`hapsim.drivers.transport.DriverTransport._note_hold`);
        rows ``k - 1`` and ``k`` of a marked tick ``k`` are left out here, the record cut
        there as at a clamped force it cannot replay (``exclude`` of
        :func:`hapsim.analysis.identify.identify`: each stretch after a cut a free
        response from its own initial state, its first ``d + 2`` rows dropped: the holds
        in flight). The transport marks there too the commands whose answers it paired
        with the command after their own, as an echo later showed
        (:meth:`hapsim.drivers.late_replies.LateReplies._answer_shift`).

        Parameters
        ----------
        columns : dict of str to ndarray
            The run's telemetry columns (``seq``, shape (n,)).

        Returns
        -------
        ndarray of bool, shape (n,), or None
        """
        if not self.mistimed_seqs:
            return None
        import numpy as np
        seq = np.asarray(columns["seq"], np.int64)
        hit = np.isin(seq, np.fromiter(self.mistimed_seqs, np.int64,
                                       len(self.mistimed_seqs)))
        out = hit.copy()
        out[:-1] |= hit[1:]                 # the row before: its force's hold ended there
        return out

    def options(self) -> dict:
        """The device parameters this driver was built with (its constructor's keywords
        and their values): what ``device.protocol_options`` holds.

        Returns
        -------
        dict
            Keyword name to its value, for each constructor keyword the driver keeps as
            an attribute of that name (a new dict).
        """
        import inspect
        names = [n for n in inspect.signature(type(self).__init__).parameters if n != "self"]
        return {n: getattr(self, n) for n in names if hasattr(self, n)}

    @classmethod
    def embedded_options(cls, options: dict, x0: float) -> dict:
        """The driver's keywords when ``hapsim run`` embeds its board (no ``--port``):
        ``options`` with what the board's set-up takes from the scene (by default
        nothing: ``options`` unchanged).

        Parameters
        ----------
        options : dict
            The keywords given (``--driver-options``, else the scene's
            ``device.protocol_options``).
        x0 : float
            The excitation's start position [m or rad]: where the embedded board is armed.

        Returns
        -------
        dict
            A new dict; ``options`` is not changed.
        """
        return dict(options)

    def mock_hardware(self) -> dict:
        """The keywords of this driver's mock (:mod:`hapsim.emulated.driver_mock`) that build the
        device this driver describes (by default none).

        Returns
        -------
        dict
            Keyword name to value; empty by default.
        """
        return {}

    def round_trip_s(self) -> float:
        """Shortest time from a command's first byte to the end of its answer [s] (wire
        time of both at the baud rate, 10 bits a byte, plus the device's own work); 0 for
        a link whose wire time is negligible (USB at full speed).

        Returns
        -------
        float
            [s], >= 0; 0.0 by default.
        """
        return 0.0

    def least_answer_s(self) -> float:
        """The least time [s] from a command's write to its answer's last byte that the
        board's firmware allows (its bytes and the answer's on the wire, its least work),
        where the board's emulation honours it too: an answer read sooner is not that
        command's (:meth:`hapsim.drivers.transport.DriverTransport._take`). 0 (the
        default): not stated, the newest command is taken as answered.

        Returns
        -------
        float
            [s], >= 0; 0.0 by default.
        """
        return 0.0

    def answer_names(self, command: bytes, echo) -> bool | None:
        """Whether an answer whose echo (:meth:`answer_echo`) is ``echo`` can answer
        ``command`` (the bytes written); None (the default): the board's answers name no
        command, the transport's rule of time alone pairs them
        (:meth:`hapsim.drivers.transport.DriverTransport._take`).

        Parameters
        ----------
        command : bytes
            The bytes written (one command of :meth:`encode_force`).
        echo : object
            What the answer echoes (:meth:`answer_echo`; the Hapkit sketch's: a float).

        Returns
        -------
        bool or None
            True: it can; False: it cannot; None: not known (always, by default).
        """
        return None

    def answer_echo(self):
        """What the last answer decoded echoes of its command (:meth:`answer_names`); None
        (the default): nothing."""
        return None

    def max_rate_hz(self) -> float:
        """Highest host rate whose period holds a command and its answer [Hz] (inf when
        the link sets no bound).

        Returns
        -------
        float
            ``1 / round_trip_s()`` [Hz]; ``math.inf`` when :meth:`round_trip_s` is 0.
        """
        rt = self.round_trip_s()
        return 1.0 / rt if rt > 0 else math.inf

    def board_rate_hz(self, rate_hz: float) -> float:
        """The rate the board really runs a loop asked for at ``rate_hz`` at [Hz]: the same,
        for a board with no tick of its own (a board that takes commands on its own tick,
        the Hapkit sketch, overrides it: a whole number of its ticks).

        Parameters
        ----------
        rate_hz : float
            The scene's rate [Hz].

        Returns
        -------
        float
        """
        return float(rate_hz)

    def rate_candidates(self, rates) -> list:
        """The rates a ladder's span offers this board, increasing [Hz]: the ladder's own
        (a board on its own tick overrides it: the whole numbers of its ticks within the
        span). :meth:`board_rates` keeps those it holds.

        Parameters
        ----------
        rates : iterable of float
            Candidate rates [Hz], increasing (``hapsim advise``'s ladder).

        Returns
        -------
        list of float
            [Hz]; by default ``rates`` as floats, in their order.
        """
        return [float(r) for r in rates]

    def board_rates(self, rates) -> list:
        """The rates a ladder of candidates offers this board (:meth:`rate_candidates`)
        that it holds (:meth:`check_rate`), increasing.

        Parameters
        ----------
        rates : sequence of float
            Candidate rates [Hz], increasing (``hapsim advise``'s ladder).

        Returns
        -------
        list of float
            Increasing [Hz]; empty when the board holds none of them.
        """
        from hapsim.errors import ConfigError
        out = []
        for r in self.rate_candidates(rates):
            try:
                self.check_rate(float(r))
            except ConfigError:
                continue
            out.append(float(r))
        return out

    def check_rate(self, rate_hz: float) -> None:
        """Refuse a rate the device cannot hold: its period must hold one command and its
        answer (:meth:`round_trip_s`), or answers come a period late and are taken for the
        next command's (the protocols have no sequence number).

        Parameters
        ----------
        rate_hz : float
            The scene's rate [Hz].

        Raises
        ------
        ConfigError
            The period is shorter than the round trip; the message gives the round trip's
            parts and the highest rate the device can hold.
        """
        top = self.max_rate_hz()
        if rate_hz > top:
            from hapsim.errors import ConfigError
            raise ConfigError(
                f"{self.name}: {rate_hz:g} Hz cannot be held: {self.rate_reason()}; the "
                f"highest rate this device can hold is {math.floor(top):d} Hz", key="rate_hz")

    def rate_reason(self) -> str:
        """Why :meth:`max_rate_hz` is what it is (for :meth:`check_rate`'s message).

        Returns
        -------
        str
            By default the round trip (:meth:`round_trip_s`) in [ms].
        """
        return f"a command and its answer take {self.round_trip_s() * 1e3:.3g} ms"

    def stop_bytes(self, position: float = 0.0) -> bytes:
        """What the host sends to leave the device at zero force (STOP, a loss, closing
        the port): a zero-force command by default; a device that may have lost its place
        in the byte stream gets its re-synchronisation, which ends at zero force.

        Parameters
        ----------
        position : float
            The last position read [m] or [rad] (used by a re-synchronisation that sets
            the device's position, the Haply's; ignored by default).

        Returns
        -------
        bytes
            By default ``encode_force(0.0)``.

        Raises
        ------
        NotImplementedError
            By default, for a driver that does not implement :meth:`encode_force`.
        """
        return self.encode_force(0.0)

    def resync(self, position: float = 0.0) -> bytes:
        """Bytes that put a device which lost its place in the byte stream back in step,
        zero force first (default: a zero-force command; a start byte re-aligns a framed
        device by itself). ``position`` is the last position read [m] or [rad].

        Parameters
        ----------
        position : float
            The last position read [m] or [rad] (ignored by default).

        Returns
        -------
        bytes
            By default ``encode_force(0.0)``.

        Raises
        ------
        NotImplementedError
            By default, for a driver that does not implement :meth:`encode_force`.
        """
        return self.encode_force(0.0)

    def encode_force(self, force: float) -> bytes:
        """Bytes commanding ``force`` [N] on the driven axis (zero on the others).

        Parameters
        ----------
        force : float
            The force to send [N] (a rotary device's torque [N m]); a driver clamps it to
            :attr:`force_limit`.

        Returns
        -------
        bytes
            One command, as written to the port.

        Raises
        ------
        NotImplementedError
            Always, here: every driver overrides it.
        """
        raise NotImplementedError

    def arm(self) -> bytes:
        """Bytes sent when the host arms the device (CONFIG): by default one zero-force
        command, whose answer is the first record.

        Returns
        -------
        bytes
            By default ``encode_force(0.0)``.
        """
        return self.encode_force(0.0)

    def rearm_anchor(self, position: float):
        """For a device whose set-up sets its position (re-arming it at :meth:`arm`'s
        pose would move its frame), the decoder's anchor at ``position`` (the last read,
        [m] or [rad]), and the transport re-arms it with :meth:`resync` there; None (the
        default): a re-arming is :meth:`arm` again.

        Parameters
        ----------
        position : float
            The last position read [m] or [rad].

        Returns
        -------
        float or None
            The decoder's anchor (the Haply's: the angle in [deg]); None by default.
        """
        return None

    def applied_force(self, force: float) -> float:
        """The force [N] the device receives for ``force`` (after the protocol's
        quantisation and clamp): what identification must fit against.

        Parameters
        ----------
        force : float
            The force sent [N] (or torque [N m]).

        Returns
        -------
        float
            [N]; by default ``force`` itself, as a float.
        """
        return float(force)

    def applied_forces(self, force):
        """:meth:`applied_force` of every force of an array (the timing account's
        ``quantise``: :func:`hapsim.applied.account_from_timing`). This default calls it
        once per force; a driver whose rule numpy computes as well overrides it (tested
        equal to it, bit for bit).

        Parameters
        ----------
        force : array_like of float, shape (n,)
            Forces sent [N].

        Returns
        -------
        ndarray of float64, shape (n,)
            The forces the device receives [N].
        """
        import numpy as np
        f = np.asarray(force, float)
        return np.array([self.applied_force(float(v)) for v in f.ravel()],
                        dtype=np.float64).reshape(f.shape)

    def output_stage(self, force):
        """What the board's firmware makes of the forces its commands carry before its
        motor gets them, or None (the default: the command's value is applied as it is).

        A board whose firmware quantises the force on its way to the motor (the Hapkit
        sketch's square-root PWM, the Haply M3's 8-bit duty:
        :mod:`hapsim.drivers.output_stage`) applies a deterministic function of the value
        the command carries; the account (:meth:`account`) and the measurement
        (:func:`hapsim.analysis.measurement.late_accounted`) take the difference out as a
        known input at every row.

        Parameters
        ----------
        force : ndarray, shape (n,)
            Forces the host sent [N] (before the wire's rounding and the clamp, which
            this applies too).

        Returns
        -------
        tuple of ndarray or None
            ``(out, half_width)``, each shape (n,): the force the motor gets [N] and how
            far the firmware's rounding leaves it uncertain [N].
        """
        return None

    def unknown_force_rows(self, columns: dict):
        """Rows whose applied force no account can name, left out of the measurement, or
        None (the default: every row's force is the one sent, the one before, or named by
        the device).

        A protocol without framing or checksum whose device does not name the force it
        applied (the Haply M3) turns a host byte lost into a command parsed from the
        wrong bytes: an arbitrary force, held until the parser is back in step.
        :meth:`account` marks these rows not known (``AppliedAccount.known`` False): the
        measurement cuts the record there (``exclude`` of
        :func:`hapsim.analysis.identify.identify`: each stretch after a cut is a free
        response from its own initial state), as it does at a clamped force it cannot
        replay, and ``identify``'s fit leaves them out (each stretch fitted from its own
        initial state).

        Parameters
        ----------
        columns : dict of str to ndarray
            The run's telemetry columns (``flags``, each shape (n,)).

        Returns
        -------
        ndarray of bool, shape (n,), or None
        """
        return None

    def account(self, columns: dict, force):
        """The force the device applied per tick, from this driver's timing, or None.

        A protocol without ``force_seq`` cannot name the force the device held at a tick;
        a driver that times its commands and records fills this in with
        :func:`hapsim.applied.account_from_timing` (late ticks, and the ticks it
        cannot order, whose force half-width the stated uncertainty then covers).
        ``identify`` fits the device to it and ``run`` takes the late ticks out as known
        inputs; None (the default): the forces sent, every delay tried.

        Parameters
        ----------
        columns : dict of str to ndarray
            The run's telemetry columns (:data:`hapsim.host.telemetry.COLUMNS`).
        force : ndarray, shape (n,)
            The force each row's command carried [N] (:meth:`applied_force` of the sent).

        Returns
        -------
        hapsim.applied.AppliedAccount or None

        Notes
        -----
        The drivers here (all three protocols run through
        :class:`~hapsim.drivers.transport.DriverTransport`) know one thing per tick: whether
        the command's answer came. A command whose answer did not come (the next row is
        an estimated sample, ``FLAG_ESTIMATED``) may not have reached the device (a lost
        or merged packet) or may have (a lost record): the force applied from it is the
        one sent or the one before, so those rows are *ambiguous* and the account states
        the half-difference (:func:`~hapsim.applied.account_from_timing`, with
        the transport's delay d: ``loop_delay``). None when every answer came.

        The rows :meth:`unknown_force_rows` names are the account's unknown rows
        (``known`` False): a force none of the two may have been applied there, so
        ``identify`` (:func:`hapsim.analysis.device_fit.fit_device` drops rows whose input
        is not known) and ``run``'s measurement (it cuts the record there:
        :func:`hapsim.analysis.measurement.late_accounted`) leave them out, from this one
        source.
        """
        import numpy as np     # here: building the CLI's parser loads no numpy
        flags = columns.get("flags")
        d = getattr(self, "loop_delay", None)
        if flags is None or d is None:
            return None
        est = (np.asarray(flags) & FLAG_ESTIMATED) != 0
        if not est.any():
            return None
        from hapsim.applied import account_from_timing
        n = est.size
        amb = np.zeros(n, bool)
        # row r applies the force of row r - d, carried by the command answered (or not)
        # at row r - d + 1
        k = np.flatnonzero(est) + d - 1
        amb[k[(k >= 0) & (k < n)]] = True
        stage = self.output_stage(np.asarray(force, float))
        if stage is not None:
            # the board's output stage (Driver.output_stage): the forces its motor got
            acc = account_from_timing(stage[0], d, ambiguous=amb, stage_half_width=stage[1])
        else:
            acc = account_from_timing(force, d, ambiguous=amb, force_scale=self.force_scale,
                                      quantise=self.applied_forces if self.force_scale > 0
                                      else None)
        # the rows whose force no account can name (an unframed board's parser out of
        # step): not known, so identify's fit and run's measurement both leave them out
        unknown = self.unknown_force_rows(columns)
        if unknown is not None:
            acc.known = acc.known & ~np.asarray(unknown, bool)
        return acc

    def decoder(self):
        """A fresh decoder: ``feed(data) -> list of positions [m]``, ``stats`` dict."""
        raise NotImplementedError


def binary32_commands(force, limit: float):
    """The values of commands that carry each force as a binary32 float, clamped to
    ``limit`` (NaN and infinities: 0): the HapkitSerial sketch's and the Haply M3's wire
    rule, their drivers' ``applied_force`` (a ``struct`` pack of each command) at numpy's
    speed. numpy's cast to float32 rounds to nearest even, as C's conversion ``struct``
    packs with does: the same numbers bit for bit (tests/test_hapkit_serial_account.py).

    Parameters
    ----------
    force : array_like of float, shape (n,)
        Forces sent [N] (or torques [N m]).
    limit : float
        The clamp, > 0, in the same unit.

    Returns
    -------
    ndarray of float64, shape (n,)
        The values the commands carry.
    """
    import numpy as np
    f = np.asarray(force, float)
    f = np.where(np.isfinite(f), f, 0.0)
    lim = float(limit)
    return np.maximum(np.minimum(f, lim), -lim).astype(np.float32).astype(np.float64)
