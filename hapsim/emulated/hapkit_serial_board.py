"""A Hapkit running the WHC2017 sketch with the host-force function, byte for byte: the
command taken at the sketch's next 1 ms tick, the handle read and the force applied there,
driving the handle's physics (:class:`hapsim.emulated.actuated.Actuated`); served on a pty
by :func:`hapsim.emulated.driver_mock.serve`.
"""

from __future__ import annotations

import math

from hapsim.emulated.actuated import Actuated, offline_record

__all__ = ["HapkitSerialDevice", "hapkit_serial_offline_loop"]


class HapkitSerialDevice(Actuated):
    """A Hapkit running the WHC2017 sketch with the host-force function: its handle is the
    mock device's moving mass.

    Its time, ``clock="wall"`` (the default): the sketch runs a fixed 1 kHz tick on its
    own clock (:data:`TICK_S`, from power-on: the board's time 0) and answers each
    command on the tick after it has come, with one 9-byte reply (the driver's reading of
    ``Hapkit_arduino.ino`` and ``Board.java``: :mod:`hapsim.drivers.hapkit_serial`, whose
    module notes this follows; the sketch's source is not in this project's reference
    library, so the order within a tick is taken as the driver states it: the handle read
    at the tick, the command's force applied from it). The handle is integrated exactly
    over the real time between ticks that change something (:class:`WallClock`), the
    force held whatever the host does: the sketch has no silence rule. The reply's last
    byte leaves the 9 bytes' wire time at 57600 baud (:data:`REPLY_WIRE_S`, 1.56 ms)
    after its tick. Its loop delay is one host period (the read and the force at the same
    tick, the force computed from that read one command later), to the tick's grid; a
    scene stating more delays each force by the rest (:attr:`hapsim.emulated.actuated.Actuated.extra_latency_s`).
    ``clock="lockstep"`` (named, for deterministic tests): one period per command, the
    reply at once.

    Parameters
    ----------
    device, rate_hz, excitation, seed
        As :class:`hapsim.emulated.actuated.Actuated`.
    force_limit : float
        The firmware's force clamp [N].
    clock : {"wall", "lockstep"}
        The board's clock (above).

    Attributes
    ----------
    decoder : CommandDecoder
    ready_at : float
        Wall clock: the board's time [s] its last reply has left at (:func:`serve` writes
        it then).
    """

    #: The sketch's control tick [s] (1 kHz).
    TICK_S = 1e-3
    #: A 9-byte reply's time on the wire at 57600 baud, 10 bits a byte [s].
    REPLY_WIRE_S = 9 * 10 / 57600

    def __init__(self, device, rate_hz: float, excitation=None, *, force_limit: float = 2.0,
                 clock: str = "wall", seed: int = 0) -> None:
        from hapsim.drivers import hapkit_serial as hk
        self._hk = hk
        self._phases: list = []                       # where in its tick each came
        self._ticks: list = []                        # the tick that took each
        super().__init__(device, rate_hz, excitation, force_limit, seed, clock=clock)
        self.decoder = hk.CommandDecoder()
        self.ready_at = 0.0
        self._tick = -1                               # the last tick that took a command

    def feed(self, data: bytes, now: float = math.inf) -> bytes:
        """Bytes from the host in (at the board's time ``now`` [s], needed on the wall
        clock), one 9-byte reply per command out."""
        out = b""
        wall = self.wall is not None
        for f in self.decoder.feed(data):
            if wall:
                # the tick after the command came (several in one read: one tick each)
                k = max(math.floor(now / self.TICK_S) + 1, self._tick + 1)
                self._phases.append(now / self.TICK_S - math.floor(now / self.TICK_S))
                self._ticks.append(k)
                self._tick = k
                tick = k * self.TICK_S
                self.wall.run_to(tick)
                x = self.physics.sample()             # the handle read at the tick
                self.apply(f, now=tick)               # the force from the tick on
                out += self._hk.reply_packet(self.decoder.function, x,
                                             self.wall.settles_on())
                self.ready_at = tick + self.REPLY_WIRE_S
                continue
            self.apply(f)
            # the sketch replies with the handle it read and the force it applies from
            # that tick on (as on the wall clock): the queue's head, not the force of the
            # period just ended
            out += self._hk.reply_packet(self.decoder.function, self.physics.sample(),
                                         self.held_from_now())
        return out

    def idle(self, silent_s: float) -> bytes:
        """The sketch has no silence rule: it holds its force."""
        return b""

    @property
    def tick_arrivals(self) -> dict:
        """Where in the sketch's tick the commands came (wall clock), for the host's
        timing: ``commands``; ``near_boundary``, those within a tenth of a tick of the
        tick's end or start (a command coming there is taken at one tick or the next by
        a jitter of 0.1 ms: a sample interval a tick off the host's period);
        ``median_phase``, the median arrival phase [fraction of a tick, 0 at a tick];
        ``off_period``, the commands taken another number of ticks after the one before
        than the period holds (a force held a tick longer or shorter; a gap of more than
        two periods, the probes' and an arming's, not counted), with ``off_at`` the
        first 1000 of them (their index among the commands)."""
        ph = sorted(self._phases)
        near = sum(1 for p in ph if p < 0.1 or p > 0.9)
        per = self.physics.period / self.TICK_S
        off = []
        if abs(per - round(per)) < 1e-6:
            per = int(round(per))
            t = self._ticks
            off = [i for i in range(1, len(t))
                   if t[i] - t[i - 1] != per and t[i] - t[i - 1] <= 2 * per]
        return {"commands": len(ph), "near_boundary": near,
                "median_phase": ph[len(ph) // 2] if ph else None,
                "off_period": len(off), "off_at": off[:1000]}


def hapkit_serial_offline_loop(scene, n: int, *, read_late=None, device=None,
                               phase: float = 0.5):
    """The Hapkit-serial THS closed offline on a simulated clock: the sketch on its own
    1 kHz tick (:class:`HapkitSerialDevice` with ``clock="wall"``, fed the simulated time
    of each command), hapsim's engine as the host; deterministic, no pty, no real time.

    The host loop's arithmetic: row ``k`` is the reply to command ``k`` (the handle read
    at the tick that took it), the force computed from it goes out with command ``k + 1``.
    The host writes command ``k`` at ``k T + phase`` ticks, in the middle of a tick as the
    transport aligns them (:meth:`hapsim.drivers.tick_align.TickAligned.tick_phase`); the
    board reads command ``k`` ``read_late[k]`` ticks after it came (its own read latency:
    a USB-serial bridge's frame, its process scheduled late), unseen by the host (nothing
    is marked in the driver's ``mistimed_seqs``): a latency past the tick's end takes the
    command at a later tick, the reply's position read that much late and the force before
    held that much longer (:attr:`HapkitSerialDevice.tick_arrivals` counts them).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A calibrated scene whose device speaks ``hapkit-serial`` (its rate a whole number
        of ticks, its delay, force limit and excitation).
    n : int
        Rows [samples].
    read_late : dict of int to float, optional
        ``{command: ticks}``: the board's read latency of those commands [ticks].
    device : hapsim.scene.Device, optional
        The board's true device when it is not the scene's (a hidden mass or friction).
    phase : float
        Where in its tick the host's writes come [fraction of a tick].

    Returns
    -------
    tuple
        ``(columns, driver, board)``: telemetry columns (``time`` [s], ``position`` [m],
        ``force`` [N], ``seq``, ``flags``, ``late``, ``force_seq``, ``status``), shape
        (n,); the :class:`hapsim.drivers.hapkit_serial.HapkitSerial` whose replies they
        are (its ``loop_delay`` and ``own_tick`` set, no hold marked); the board.
    """
    from hapsim.drivers.hapkit_serial import HapkitSerial
    sc = scene
    drv = HapkitSerial()
    drv.loop_delay = int(sc.device.delay)
    drv.mistimed_seqs = set()
    drv.own_tick = True                        # the sketch keeps its tick (simulated)
    board = HapkitSerialDevice(device or sc.device, sc.rate_hz, sc.excitation, clock="wall")
    dec = drv.decoder()
    T, tick = sc.period, board.TICK_S
    late = dict(read_late or {})

    def command(j: int, f: float) -> float:
        now = j * T + (phase + float(late.get(j, 0.0))) * tick
        return dec.feed(board.feed(drv.encode_force(f), now))[-1]

    cols = offline_record(sc, drv, command, n, lambda k: k * T)
    return cols, drv, board
