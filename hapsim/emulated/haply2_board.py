"""The Haply 2DIY emulated byte for byte: its board's parser with a pantograph as the plant
(the host loop that drives it in lockstep, ``hapsim run --driver haply`` on a 2-D scene,
is :mod:`hapsim.emulated.haply2_lockstep`; the records' verdict
:mod:`hapsim.emulated.haply2_verdict`).

The board (:class:`Haply2DIYBoard`) parses the host's bytes as firmware V1.5 does
(:class:`hapsim.emulated.haply_firmware.CommandDecoder`: no framing, a lost byte shifts
the parser), keeps each motor port's torque until a write changes it (no watchdog), and
answers every write with ``[id]`` + a float32 per analog pin and encoder port of that id.
Each write is one period: the torques ``d`` writes back (the scene's ``device.delay``) are
held over it while the plant advances (:class:`hapsim.joint_device.LocalJointDeviceND`,
the pantograph's joint-space dynamics), then the encoders are read: ``360 * count /
resolution`` with the count set to ``int(offset * resolution / 360)`` at the set-up and
moving by the joint's rotation in whole counts of the hardware's ``cpr``, in the direction
the set-up's byte says (the generation's wiring counts up with hapsim's joint angle; the
other byte counts down; the same for the motors' torque sign).

The hand: at each set-up the board's plant is at the scene's operating point (where the
host's offsets say it is); the hand then lets it go from start ``k mod (2n + 1)`` of
:func:`hapsim.lockstep.excitation_starts` (``k`` the set-ups so far), as the n-D mock
does at each CONFIG (:class:`hapsim.emulated.mock.MockDeviceND`). On the wall clock the
hand holds the handle at the operating point through the set-up's waits (each encoder's
count is written there, after its wait) and whatever the host does before the record's
first write (the host drains the link for 30 ms before a record,
:data:`hapsim.pipeline.haply2_record.QUIET_S`, and awaits a re-arming's answer up to
``REARM_REPLY_S`` plus its quiet), and lets it go at that write's pass: the record's first
sample, as in lockstep and as the Falcon's hand (:mod:`hapsim.emulated.falcon_device`). A
write that came in the same bytes as the set-up (a re-arming's closing zero write) is not
that write. Before, it let go at the set-up and the handle coasted under no torque
through the drain: the records reached 3.3-3.6 ``a`` against 2.19 ``a`` in lockstep,
and a start the lockstep prediction found inside a contact left it in real time.

Its time (``clock="wall"``, the default): the board keeps its own time, the firmware's
(``Haply_M3_Firmware_V1_5.ino`` of HaplyHaptics/Haply-Arduino-Firmware-Versions, read line
by line; its ``.h`` beside it). ``loop()`` takes at most one command per pass and passes
every 50 us, a command waiting or not (lines 59-64: ``micros() - lastPublished >= 50``,
``lastPublished`` set at each pass): a write that comes to an idle board waits up to 50 us
for the next pass, by a phase the host does not see
(:func:`hapsim.emulated.haply_firmware.pass_at`); a write sets the
motors' duties (``write_states``, line 77) and the same pass answers it with the encoders
read then (``read_states``, line 89), so the angles a reply carries are sampled when its
write is taken and its torques act from then on, held until the next write (no watchdog).
A set-up (line 74) builds a ``new Encoder(...)`` for each active encoder port
(``setup_encoders``, ``.h`` lines 332-360; ``initialize_encoder``, ``.h`` line 441), whose
constructor waits ``delayMicroseconds(2000)`` for the pins' R-C filter (the Encoder
library Haply ships), then writes the count at the offset (``.h`` line 442): the 2DIY's
two encoders cost :data:`SETUP_S` each, during which the commands wait and the joints do
not. A single ``SerialUSB.read()`` of an empty buffer returns -1, stored as the byte 255
(the address, masks, directions, pin lists, PWM bytes; only ``readBytes``, the torques and
the encoder parameters, waits: :class:`hapsim.emulated.haply_firmware.CommandDecoder` with
``absent=255``): on the wall clock a byte is absent at a pass that comes before it arrives
(a command's first bytes held until its pass; a silent host's pass reads them in
:meth:`Haply2DIYBoard.idle`); in lockstep each write's bytes have all arrived by its pass.
Between events the pantograph is integrated over the real time that passed
(:meth:`hapsim.joint_device.LocalJointDeviceND.advance_torque`). The loop's own delay is
one period (the read and the torques at the same write, the torques computed from that
read one write later); a scene stating more delays each write's torques by the rest.
``clock="lockstep"`` (named, for deterministic tests): each write is one period.
"""

from __future__ import annotations

import copy
import math
import struct
from collections import deque

import numpy as np

from hapsim.drivers.haply2 import GENERATIONS, JOINT_PORTS
from hapsim.emulated.haply_firmware import PASS_S, CommandDecoder, pass_at
from hapsim.errors import ConfigError
from hapsim.joint_device import LocalJointDeviceND
from hapsim.lockstep import excitation_starts

__all__ = ["Haply2DIYBoard", "BoardLink", "in_hand_order", "PROBE_TORQUE", "PROBE_ENVELOPE",
           "SETUP_S", "PASS_S"]

#: What building one ``Encoder`` takes on the board [s]: its constructor's
#: ``delayMicroseconds(2000)`` (module notes).
SETUP_S = 2e-3

_F = struct.Struct("<f")
_F32_MAX = 3.4028234663852886e38


class Haply2DIYBoard:
    """An emulated Haply board driving a 2DIY pantograph (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 2-D scene whose device is a pantograph.
    generation : {"gen2", "gen3"}
        The hardware's wiring (direction bytes that count up) and encoders.
    cpr : float, optional
        The encoders' real counts per revolution (default the generation's).
    amplitude : float
        The hand's amplitude ``a`` [m].
    wiring : ((int, int), (int, int)), optional
        Per joint, the sign of its motor and of its encoder against the generation's
        wiring (1: as hAPI's direction bytes expect; -1: wired backwards, so that the
        generation's byte turns the motor, or counts the encoder, the other way).
    clock : {"wall", "lockstep"}
        The board's clock (module notes): its own time (``feed`` needs each read's time)
        or one period per write.

    Raises
    ------
    ConfigError
        Not a 2-D pantograph scene; an unknown generation; a bad wiring; an unknown clock.

    Attributes
    ----------
    parser : hapsim.emulated.haply_firmware.CommandDecoder
    setups : int
        Set-ups taken (the hand's cycle).
    writes : int
        Writes taken (periods advanced).
    torque : dict
        Torque held per motor port (1..4) [N m], as the wire gave it.
    ready_at : float
        Wall clock: the board's time [s] its last reply is ready at (:func:`serve
        <hapsim.emulated.driver_mock.serve>` writes it then).
    excursion : float
        The largest joint displacement from the operating point the plant reached [rad]
        (the truth, whatever the host believes).
    """

    def __init__(self, scene, generation: str = "gen3", *, cpr: float | None = None,
                 amplitude: float = 1e-8, wiring=((1, 1), (1, 1)),
                 clock: str = "wall") -> None:
        if clock not in ("wall", "lockstep"):
            raise ConfigError(f"unknown clock {clock!r}; valid: wall, lockstep", key="clock")
        self.clock = clock
        #: The board itself on the wall clock (what :func:`hapsim.emulated.driver_mock.serve` reads:
        #: its ``excursion``), None in lockstep.
        self.wall = self if clock == "wall" else None
        self.ready_at = 0.0
        self.excursion = 0.0
        #: The longest a non-zero torque was held with no write taking effect [s] (no
        #: watchdog: a silent host's), on the wall clock, up to the last write.
        self.longest_hold = 0.0
        self._since = 0.0                     # when the torques in effect took effect [s]
        self._t = 0.0                         # the board's time the plant has reached [s]
        self._busy_until = 0.0                # the firmware's next pass, not before [s]
        self._due: deque = deque()            # (time [s], torques) not yet in effect
        self._hand = None                     # the plant at the hand's start, not let go
        self._feeds = 0                       # the host's writes fed so far (wall clock)
        self._hand_feed = -1                  # the one the set-up the hand holds came in
        dev = scene.device
        if scene.dimension != 2 or dev is None or dev.kind != "pantograph":
            raise ConfigError("the Haply 2DIY drives a 2-D scene with a pantograph device",
                              file=scene.path, key="device.kind")
        if generation not in GENERATIONS:
            raise ConfigError(f"unknown 2DIY generation {generation!r}; valid: "
                              f"{', '.join(GENERATIONS)}", key="generation")
        w = tuple(tuple(int(v) for v in jw) for jw in wiring)
        if len(w) != 2 or any(len(jw) != 2 or set(jw) - {1, -1} for jw in w):
            raise ConfigError(f"wiring must be ((motor, encoder) sign of joint 1, of joint "
                              f"2), each 1 or -1, got {wiring!r}", key="wiring")
        self.wiring = w
        self.scene = scene
        self.gen = GENERATIONS[generation]
        self.cpr = float(cpr or self.gen.resolution)
        self.amplitude = float(amplitude)
        # firmware V1.5's single reads of an empty buffer give 255 (CommandDecoder notes);
        # on the wall clock only at a pass the next bytes come after (module notes)
        self.parser = CommandDecoder(absent=255)
        self._seen = -math.inf                # the board's time its bytes are known to [s]
        if clock == "wall":
            # (the pass that reads a held command's absent bytes: the first after they
            # came, at the last feed)
            self.parser.ready = lambda: self._pass_at(self._last_now) <= self._seen
        if float(dev.delay) % 1.0:
            # its joint-space plant applies whole periods (no split hold there)
            raise ConfigError(f"a sub-sample delay ({float(dev.delay):g} periods) is not "
                              "emulated by this board (its joint-space model applies whole "
                              "periods): use a whole delay", file=scene.path,
                              key="device.delay")
        self.delay = int(dev.delay)
        #: Wall clock: the latency added to each write's torques [s], what brings the
        #: board's own delay of one period to the scene's (never negative).
        self.extra_latency_s = max(0.0, self.delay - 1.0) * scene.period
        self._fifo = deque([None] * self.delay)
        self.torque = {1: 0.0, 2: 0.0, 3: 0.0, 4: 0.0}
        self.setups = 0
        self.writes = 0
        self.clamped = 0
        self.held = self.last_command = 0.0
        # the plant as each set-up leaves it, built once per start (its Newton solve and
        # finite-difference Hessian, ~1 ms, were most of a set-up) and copied at each:
        # the same state, bit for bit, as building it again
        self._starts = excitation_starts(2, self.amplitude, scene.period)
        self._rest = LocalJointDeviceND(scene, np.zeros(2), np.zeros(2))
        self._at_start: dict = {}
        self.plant = copy.deepcopy(self._rest)
        self._base = {}                       # port -> (count at set-up, hardware count then)

    def _hw_count(self, joint: int, plant=None) -> int:
        q = (self.plant if plant is None else plant).joints()[joint]
        return round(math.degrees(q) * self.cpr / 360.0)

    def _joint_of_port(self, port: int) -> int | None:
        return JOINT_PORTS.index(port) if port in JOINT_PORTS else None

    def _on_setup(self) -> None:
        p = self.parser
        # the hand holds the handle at the operating point while the board is set up
        self._base = {}
        for port in range(1, 5):
            if p.encoder_addr[port - 1]:
                off = p.encoder_offset[port - 1] * p.encoder_res[port - 1] / 360.0
                c0 = int(off) if math.isfinite(off) and abs(off) < 2 ** 31 else 0
                j = self._joint_of_port(port)
                self._base[port] = (c0, self._hw_count(j, self._rest) if j is not None
                                    else 0)
        i = self.setups % len(self._starts)
        self.setups += 1
        if i not in self._at_start:
            x0, v0 = self._starts[i]
            self._at_start[i] = LocalJointDeviceND(self.scene, x0, v0)
        self.plant = copy.deepcopy(self._at_start[i])
        self._fifo = deque([None] * self.delay)
        self._due.clear()

    def _k_of(self, port: int, kind: str) -> int:
        """The k-th active port's index (the firmware's actuators[k]/encoders[k])."""
        p = self.parser
        addrs = p.motor_addr if kind == "motor" else p.encoder_addr
        active = [q for q in range(1, 5) if addrs[q - 1]]
        return active.index(port) if port in active else 0

    def angle_deg(self, port: int) -> float:
        """Encoder ``port``'s reading [deg] (firmware ``read_encoder_value``).

        Parameters
        ----------
        port : int
            The encoder port, 1..4 (a port with no joint reads its set-up count).

        Returns
        -------
        float
            ``360 * count / resolution`` [deg]; a set-up's resolution 0 or not finite
            gives +-inf (nan at count 0).
        """
        p = self.parser
        res = p.encoder_res[port - 1]
        j = self._joint_of_port(port)
        c0, hw0 = self._base.get(port, (0, 0))
        moved = (self._hw_count(j) - hw0) if j is not None else 0
        up = True
        if j is not None:
            up = (p.encoder_direction[self._k_of(port, "encoder")]
                  == self.gen.encoder_direction[j]) == (self.wiring[j][1] == 1)
        c = c0 + (moved if up else -moved)
        if not (math.isfinite(res) and res):
            return math.copysign(math.inf, c) if c else math.nan
        return 360.0 * c / res

    def _joint_torques(self) -> np.ndarray:
        p = self.parser
        tau = np.zeros(2)
        for j, port in enumerate(JOINT_PORTS):
            t = self.torque[port]
            up = p.motor_direction[self._k_of(port, "motor")] == self.gen.motor_direction[j]
            up = up == (self.wiring[j][0] == 1)
            tau[j] = t if up else -t
        return tau

    # what hapsim.emulated.driver_mock.serve reads of a device (the board behind a pty)
    reply_delay_s = 0.0

    @property
    def decoder(self):
        """The parser (its ``stats``: writes, set-ups, resets, unknown bytes)."""
        return self.parser

    def idle(self, silent_s: float) -> bytes:
        """A silent host ``silent_s`` [s] since its last bytes: the board has no watchdog,
        it holds its torques; a command its parser held for a pass still to come (wall
        clock) reads its absent bytes at that pass (255): the replies it then makes.

        Parameters
        ----------
        silent_s : float
            Time since the host's last bytes [s].

        Returns
        -------
        bytes
            The replies (``b""`` in lockstep or with no command held).
        """
        if self.wall is None or not self.parser.waiting:
            return b""
        return self._flush(self._last_now + silent_s)

    def _flush(self, now: float) -> bytes:
        """Wall clock: the passes before ``now`` [s] (no byte arrived before them since
        the last feed) read what the parser held, absent bytes as 255."""
        if not self.parser.waiting:
            return b""
        at = self._pass_at(self._last_now)        # (the held bytes came at the last feed)
        if at >= now:
            return b""
        self._seen = math.nextafter(now, -math.inf)
        return self._run(b"", at)

    def _pass_at(self, t: float) -> float:
        """The firmware's first pass at or after ``t`` [s] (wall clock:
        :func:`hapsim.emulated.haply_firmware.pass_at`)."""
        return pass_at(t, self._busy_until)

    def commands(self) -> int:
        """Writes taken.

        Returns
        -------
        int
            :attr:`writes`.
        """
        return self.writes

    def settles_on(self, ports=None) -> float:
        """The largest torque the board holds once its queued writes apply [N m].

        Parameters
        ----------
        ports : iterable of int, optional
            The motor ports to read (default all four; a 2DIY's joints are
            :data:`hapsim.drivers.haply2.JOINT_PORTS`: a garbage set-up the stream made can
            leave a torque on a port wired to nothing, which no 2DIY set-up clears).

        Returns
        -------
        float
        """
        held = dict(self.torque)
        for w in self._fifo:
            if w:
                held.update(w)
        for _, w in self._due:
            held.update(w)
        want = held.keys() if ports is None else ports
        return max(abs(held[p]) for p in want)

    def run_to(self, t: float) -> None:
        """Wall clock: the pantograph integrated to the board's time ``t`` [s], the torques
        in effect held, each write's taking effect at its time (the plant not moving while
        the hand holds it after a set-up: module notes).

        Parameters
        ----------
        t : float
            The board's time to reach [s].

        Raises
        ------
        ValueError
            ``t`` is not finite (a board on the wall clock needs the time of its bytes).
        """
        if not math.isfinite(t):
            raise ValueError("a board on the wall clock needs the time of each read "
                             "(feed(data, now)); in process without time: clock='lockstep'")
        while self._t < t:
            nxt = t
            if self._due and self._due[0][0] < nxt:
                nxt = max(self._due[0][0], self._t)
            if self._hand is None:                # (else the hand holds the handle)
                self.plant.advance_torque(self._joint_torques(), nxt - self._t)
            self._t = nxt
            while self._due and self._due[0][0] <= self._t:
                self._take(self._due.popleft()[1])
        while self._due and self._due[0][0] <= self._t:
            self._take(self._due.popleft()[1])
        self.held = max(abs(v) for v in self.torque.values())
        self.excursion = max(self.excursion,
                             float(np.abs(self.plant.joints() - self.plant.q0).max()))

    def _take(self, torques: dict) -> None:
        """A write's torques take effect now: the hold they end counted."""
        if any(v != 0.0 for v in self.torque.values()):
            self.longest_hold = max(self.longest_hold, self._t - self._since)
        self.torque.update(torques)
        self._since = self._t

    def feed(self, data: bytes, now: float = math.inf) -> bytes:
        """Host bytes in, the board's replies out (one per write).

        Parameters
        ----------
        data : bytes
            What the host wrote.
        now : float
            The board's time the bytes came at [s] (wall clock; ignored in lockstep).

        Returns
        -------
        bytes
            The replies; on the wall clock they are ready at :attr:`ready_at`.
        """
        if self.wall is None:
            return self._run(data, now)
        if not math.isfinite(now):
            self.run_to(now)                      # (raises: the time is needed)
        early = self._flush(now)                  # passes before these bytes came
        self._seen = self._last_now = now
        # (the commands parsed from here on came in this write, those held before it in
        # an earlier one: what tells a set-up's own closing write from the next)
        self._feeds += 1
        return early + self._run(data, now)

    _last_now = 0.0

    def _run(self, data: bytes, now: float) -> bytes:
        """The parser's commands out of ``data`` (after what it held), taken one a pass
        from ``now`` [s] on (wall clock), and the replies to the writes."""
        out = bytearray()
        p = self.parser
        t = self._pass_at(now) if self.wall is not None else now
        for cmd in p.commands(data):
            if self.wall is not None:
                t = max(t, self._busy_until)  # one command a pass, after a set-up's waits
                self.run_to(t)
                self._busy_until = t + PASS_S
            if cmd[0] == "setup":
                self._on_setup()
                if self.wall is not None:
                    # each active encoder's constructor waits; the joint does not
                    n = sum(1 for a in p.encoder_addr if a)
                    self._busy_until = t + max(n * SETUP_S, PASS_S)
                    # the hand holds the handle at the operating point through the waits
                    # (each count is written there) and whatever the host does before
                    # the record's first write, and lets it go from its start there: a
                    # write that came in the set-up's own host write (a re-arming's
                    # closing zero write, taken after the set-up's waits and answered
                    # while the host waits up to ~25 ms) does not let it go
                    self._hand, self._hand_feed = self.plant, self._feeds
                    self.plant = copy.deepcopy(self._rest)
                continue
            if cmd[0] != "write":
                continue
            _, addr, tq = cmd
            new = {}
            for port0, tv in tq.items():
                if not math.isfinite(tv):
                    tv = 0.0                      # (the firmware: a NaN duty is 0)
                new[port0 + 1] = max(-0.123, min(0.123, tv))
            self.clamped += sum(abs(tv) >= 0.123 for tv in new.values())
            self.last_command = max((abs(tv) for tv in new.values()), default=0.0)
            if (self.wall is not None and self._hand is not None
                    and self._feeds != self._hand_feed):
                self.run_to(t)
                self.plant, self._hand = self._hand, None      # the hand lets go
                self._since = t                   # (no torque acted while it held)
            if self.wall is not None:
                # write_states, then read_states in the same pass: the angles below are
                # read at t, the torques act from t (plus the scene's extra delay)
                if new:
                    if self._due and self._due[-1][0] > t + self.extra_latency_s:
                        self._due.append((self._due[-1][0], new))
                    else:
                        self._due.append((t + self.extra_latency_s, new))
                    self.run_to(t)
                self.ready_at = t
            else:
                self._fifo.append(new)
                due = self._fifo.popleft()
                if due:
                    self.torque.update(due)
                self.held = max(abs(tv) for tv in self.torque.values())
                self.plant.step_torque(self._joint_torques())
            self.writes += 1
            na, encs = p.reply_layout(addr)
            out += bytes([addr]) + _F.pack(0.0) * na
            for port0 in encs:
                a = self.angle_deg(port0 + 1)
                if abs(a) > _F32_MAX:
                    a = math.copysign(math.inf, a)
                out += _F.pack(a)
        return bytes(out)


#: The wiring probe's largest torque [N m] and envelope [rad] on the 2DIY
#: (:func:`hapsim.drivers.haply2_probe.find_directions`: pulses raised from 1/16 of it).
PROBE_TORQUE = 0.05
PROBE_ENVELOPE = 0.1


def in_hand_order(runs: list, setups_before: int) -> list:
    """Records taken one per set-up, in the order of the emulated board's hand starts
    (module notes: set-up ``k`` lets the handle go from start ``k mod (2n + 1)``), given
    the set-ups the board took before the first record (the wiring probe's).

    Parameters
    ----------
    runs : list
        The ``2n + 1`` records, in the order taken.
    setups_before : int

    Returns
    -------
    list
        ``runs`` rotated so that record ``i`` is start ``i``'s.
    """
    s = setups_before % len(runs)
    return runs[-s:] + runs[:-s] if s else list(runs)


class BoardLink:
    """``write``/``read(timeout)`` on an in-process board's ``feed`` (the wiring probe's
    link in lockstep: each write's replies are there at once)."""

    def __init__(self, feed) -> None:
        self._feed = feed
        self._buf = b""

    def write(self, data: bytes) -> None:
        """Feed ``data`` (host -> board bytes) to the board; its replies wait for
        :meth:`read`.

        Parameters
        ----------
        data : bytes
            What the host writes.
        """
        self._buf += self._feed(data)

    def read(self, timeout: float) -> bytes:
        """Every reply byte the board has made since the last read (``timeout`` [s] is
        not waited: in lockstep the replies are there at once; ``b""`` when none).

        Parameters
        ----------
        timeout : float
            The host's wait [s] (ignored).

        Returns
        -------
        bytes
            The replies' bytes, in order.
        """
        out, self._buf = self._buf, b""
        return out
