"""The Haply 2DIY emulated byte for byte: its board's parser with a pantograph as the plant,
and the host loop that drives it in lockstep (``hapsim run --driver haply`` on a 2-D scene).

The board (:class:`Haply2DIYBoard`) parses the host's bytes as firmware V1.5 does
(:class:`hapsim.drivers.haply.CommandDecoder`: no framing, a lost byte shifts the parser),
keeps each motor port's torque until a write changes it (no watchdog), and answers every
write with ``[id]`` + a float32 per analog pin and encoder port of that id. Each write is
one period: the torques ``d`` writes back (the scene's ``device.delay``) are held over it
while the plant advances (:class:`hapsim.joint_device.LocalJointDeviceND`, the pantograph's
joint-space dynamics), then the encoders are read: ``360 * count / resolution`` with the
count set to ``int(offset * resolution / 360)`` at the set-up and moving by the joint's
rotation in whole counts of the hardware's ``cpr``, in the direction the set-up's byte says
(the generation's wiring counts up with hapsim's joint angle; the other byte counts down;
the same for the motors' torque sign).

The hand: at each set-up the board's plant is at the scene's operating point (where the
host's offsets say it is); the hand then lets it go from start ``k mod (2n + 1)`` of
:func:`hapsim.lockstep.excitation_starts` (``k`` the set-ups so far), as the n-D mock
does at each CONFIG (:class:`hapsim.emulated.mock.MockDeviceND`).

Its time (``clock="wall"``, the default): the board keeps its own time, the firmware's
(``Haply_M3_Firmware_V1_5.ino`` of HaplyHaptics/Haply-Arduino-Firmware-Versions, read
line by line; its ``.h`` beside it). ``loop()`` takes at most one command per pass and a
pass at most every 50 us (lines 59-64: ``micros() - lastPublished >= 50``); a write sets
the motors' duties (``write_states``, line 77) and the same pass answers it with the
encoders read then (``read_states``, line 89), so the angles a reply carries are sampled
when its write is taken and its torques act from then on, held until the next write (no
watchdog). A set-up (line 74) builds a ``new Encoder(...)`` for each active encoder port
(``setup_encoders``, ``.h`` lines 332-360; ``initialize_encoder``, ``.h`` line 441),
whose constructor waits ``delayMicroseconds(2000)`` for the pins' R-C filter (the Encoder
library Haply ships), then writes the count at the offset (``.h`` line 442): the 2DIY's
two encoders cost :data:`SETUP_S` each, during which the commands wait and the joints
do not. A single ``SerialUSB.read()`` of an empty buffer returns -1, stored as the byte
255 (the address, masks, directions, pin lists, PWM bytes; only ``readBytes``, the
torques and the encoder parameters, waits: :class:`hapsim.drivers.haply.CommandDecoder`
with ``absent=255``): on the wall clock a byte is absent at a pass that comes before it
arrives (a command's first bytes held until its pass; a silent host's pass reads them
in :meth:`Haply2DIYBoard.idle`); in lockstep each write's bytes have all arrived by its
pass. Between events the pantograph is integrated over the real time that passed
(:meth:`hapsim.joint_device.LocalJointDeviceND.advance_torque`). The loop's own delay is
one period (the read and the torques at the same write, the torques computed from that
read one write later); a scene stating more delays each write's torques by the rest.
``clock="lockstep"`` (named, for deterministic tests): each write is one period.
"""

from __future__ import annotations

import math
import struct
from collections import deque

import numpy as np

from hapsim.drivers.haply import CommandDecoder, ResyncRule
from hapsim.drivers.haply2 import GENERATIONS, JOINT_PORTS, Haply2DIY
from hapsim.errors import ConfigError, DeviceError
from hapsim.joint_device import LocalJointDeviceND
from hapsim.lockstep import excitation_starts

__all__ = ["Haply2DIYBoard", "drive_haply2", "measure_felt_haply2", "BoardLink", "in_hand_order",
           "PROBE_TORQUE", "PROBE_ENVELOPE", "SETUP_S", "PASS_S"]

#: What building one ``Encoder`` takes on the board [s]: its constructor's
#: ``delayMicroseconds(2000)`` (module notes).
SETUP_S = 2e-3
#: The firmware's shortest pass [s]: ``loop()`` runs when 50 us have passed since the last.
PASS_S = 50e-6

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
    parser : hapsim.drivers.haply.CommandDecoder
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
        self._t = 0.0                         # the board's time the plant has reached [s]
        self._busy_until = 0.0                # the firmware's next pass, not before [s]
        self._due: deque = deque()            # (time [s], torques) not yet in effect
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
            self.parser.ready = lambda: self._busy_until <= self._seen
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
        self.plant = LocalJointDeviceND(scene, np.zeros(2), np.zeros(2))
        self._base = {}                       # port -> (count at set-up, hardware count then)

    def _hw_count(self, joint: int) -> int:
        return round(math.degrees(self.plant.joints()[joint]) * self.cpr / 360.0)

    def _joint_of_port(self, port: int) -> int | None:
        return JOINT_PORTS.index(port) if port in JOINT_PORTS else None

    def _on_setup(self) -> None:
        p = self.parser
        # the hand holds the handle at the operating point while the board is set up
        self.plant = LocalJointDeviceND(self.scene, np.zeros(2), np.zeros(2))
        self._base = {}
        for port in range(1, 5):
            if p.encoder_addr[port - 1]:
                off = p.encoder_offset[port - 1] * p.encoder_res[port - 1] / 360.0
                c0 = int(off) if math.isfinite(off) and abs(off) < 2 ** 31 else 0
                j = self._joint_of_port(port)
                self._base[port] = (c0, self._hw_count(j) if j is not None else 0)
        starts = excitation_starts(2, self.amplitude, self.scene.period)
        x0, v0 = starts[self.setups % len(starts)]
        self.setups += 1
        self.plant = LocalJointDeviceND(self.scene, x0, v0)
        self._fifo = deque([None] * self.delay)
        self._due.clear()

    def _k_of(self, port: int, kind: str) -> int:
        """The k-th active port's index (the firmware's actuators[k]/encoders[k])."""
        p = self.parser
        addrs = p.motor_addr if kind == "motor" else p.encoder_addr
        active = [q for q in range(1, 5) if addrs[q - 1]]
        return active.index(port) if port in active else 0

    def angle_deg(self, port: int) -> float:
        """Encoder ``port``'s reading [deg] (firmware ``read_encoder_value``)."""
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
        clock) reads its absent bytes at that pass (255): the replies it then makes."""
        if self.wall is None or not self.parser.waiting:
            return b""
        return self._flush(self._last_now + silent_s)

    def _flush(self, now: float) -> bytes:
        """Wall clock: the passes before ``now`` [s] (no byte arrived before them since
        the last feed) read what the parser held, absent bytes as 255."""
        if not self.parser.waiting or self._busy_until >= now:
            return b""
        self._seen = math.nextafter(now, -math.inf)
        return self._run(b"", self._busy_until)

    def commands(self) -> int:
        """Writes taken."""
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
        in effect held, each write's taking effect at its time.

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
            self.plant.advance_torque(self._joint_torques(), nxt - self._t)
            self._t = nxt
            while self._due and self._due[0][0] <= self._t:
                self.torque.update(self._due.popleft()[1])
        while self._due and self._due[0][0] <= self._t:
            self.torque.update(self._due.popleft()[1])
        self.held = max(abs(v) for v in self.torque.values())
        self.excursion = max(self.excursion,
                             float(np.abs(self.plant.joints() - self.plant.q0).max()))

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
        return early + self._run(data, now)

    _last_now = 0.0

    def _run(self, data: bytes, now: float) -> bytes:
        """The parser's commands out of ``data`` (after what it held), taken one a pass
        from ``now`` [s] on (wall clock), and the replies to the writes."""
        out = bytearray()
        p = self.parser
        t = max(now, self._busy_until) if self.wall is not None else now
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


def drive_haply2(board_feed, driver: Haply2DIY, scene, samples: int, *, faults=None,
                 engine=None) -> dict:
    """Drive a 2DIY over its bytes in lockstep: arm, then one write per sample.

    Each sample: the reply's angles (whole counts) are the joints ``q`` [rad], the handle
    at ``f(q)`` (:class:`hapsim.kinematics.Pantograph`, exact), the n-D engine's force
    ``F`` on the port, the torques ``J(q)^T F`` written (clamped, binary32). A write whose
    reply does not come (lost, corrupted, misaligned) leaves that sample missing (the last
    position held for the engine; counted); a desync the decoder counts, or
    :data:`MISSING_RESYNC` missing replies in a row, re-arm the board (counted; the
    re-arming write is that sample's). The first reply after a set-up must read the
    offsets the set-up sent (within the decoder's step, 2 deg): otherwise the stream
    corrupted the set-up (a wrong offset would shift every later angle), which is counted
    in ``bad_setups`` and armed again.

    Parameters
    ----------
    board_feed : callable
        ``board_feed(bytes) -> bytes``: the device (an emulated board, through faults).
    driver : hapsim.drivers.haply2.Haply2DIY
    scene : hapsim.scene.SceneND
    samples : int
        Writes after arming.
    faults : object, optional
        ``rx(bytes)``, ``tx(bytes)`` (:class:`hapsim.emulated.driver_mock.ByteFaults`).
    engine : hapsim.engine_nd.EngineND, optional
        A fresh engine (default: one of ``scene``).

    Returns
    -------
    dict
        ``position`` (N, 2) [m] (NaN where missing), ``joints`` (N, 2) [rad], ``torque``
        (N, 2) [N m] written, ``missing`` (samples without a reply), ``resyncs``,
        ``bad_setups``, ``decoder`` (the reply decoder's counters), ``writes``.
    """
    from hapsim.engine_nd import EngineND
    from hapsim.kinematics import device
    dev = scene.device
    kin = device(dev.kind, dev.geometry)
    q0deg = [math.degrees(v) for v in dev.joints]
    eng = EngineND(scene) if engine is None else engine
    port = eng.port
    dec = driver.decoder()
    rx = (lambda b: b) if faults is None else faults.rx
    tx = (lambda b: b) if faults is None else faults.tx
    N = int(samples)
    pos = np.full((N, 2), np.nan)
    joints = np.full((N, 2), np.nan)
    torque = np.zeros((N, 2))
    missing = 0
    in_row = 0
    zero = driver.write_bytes((0.0, 0.0))
    bad_setups = 0
    # The board is stepped one period per write: its time, not the wall clock's, is what a
    # reply's reach grows with (ReplyDecoder.reach_deg). Left to the decoder's default
    # (the wall time between two reads), a loaded host widened the reach of a lockstep
    # board's replies and took garbage 2.6 rad off (test_haply2's hostile streams, in a
    # full suite at load 12).
    T = 1.0 / float(scene.rate_hz)
    since = 0                                   # writes since the one last answered

    def send(data: bytes) -> list:
        """One write to the board, through the faults; the replies the decoder takes."""
        nonlocal since
        since += 1
        dec.elapsed(since * T)
        got = dec.feed(tx(board_feed(rx(data))))
        if got:
            since = 0
        return got

    def arm(at_deg):
        """Re-arm at the joints ``at_deg``; the first reply, or None when it is missing
        or does not read the offsets just sent (a set-up the stream corrupted)."""
        nonlocal bad_setups
        data = driver.arm_bytes(at_deg)
        send(data[:-len(zero)])                         # a reply before the set-up: dropped
        dec.reset_prediction()                           # the hand moved the handle
        got = send(zero)
        if not got:
            return None
        a = driver.joints_of(got[-1])
        if max(abs(math.degrees(a[j]) - at_deg[j]) for j in range(2)) > dec.max_step:
            bad_setups += 1
            dec.reset_prediction()
            return None
        return got[-1]
    last = arm(q0deg)
    if last is None:
        in_row = MISSING_RESYNC                          # arm again at once
    x = None
    rule = ResyncRule(dec.stats, MISSING_RESYNC - 1)
    for k in range(N):
        if last is None:
            missing += 1
            in_row += 1
        else:
            in_row = 0
            q = np.asarray(driver.joints_of(last))
            joints[k] = q
            try:
                x = kin.forward(q)
                J = kin.jacobian(q)
            except ConfigError:             # a reply the kinematics refuses: no sample
                missing += 1
                x = None
            if x is not None:
                pos[k] = x
        if x is not None:
            if k == 0:
                eng.x[:, port] = x
                eng.xp[:, port] = x
            eng.set_port_position(x)
        eng.step()
        F = eng.port_force
        tau = J.T @ F if x is not None else np.zeros(2)
        torque[k] = driver.clamp(tau)
        if rule.due(in_row):
            in_row = 0
            # zero torque, the set-up at the operating point's joints, a zero write (its
            # reply is the next sample): the emulated board's hand holds the handle
            # there at each set-up (as the real-time loop arms it, haply2_host). Armed
            # at the last joints read instead, each re-arming left the readings off the
            # joints by the motion since that reading: 28 re-armings of a hostile stream
            # walked them 0.66 deg off, and the loop pushed the handle 1.4 deg away
            last = arm(q0deg)
            if last is None:
                in_row = MISSING_RESYNC
            continue
        got = send(driver.write_bytes(tau))
        last = got[-1] if got else None
    return {"position": pos, "joints": joints, "torque": torque, "missing": missing,
            "resyncs": rule.count, "bad_setups": bad_setups, "decoder": dict(dec.stats),
            "writes": N}


#: Missing replies in a row after which the host re-arms the board (it may be inside a
#: garbage command, or have lost its set-up).
MISSING_RESYNC = 5


def measure_felt_haply2(scene, generation: str = "gen3", *, amplitude: float = 1e-5,
                        cpr: float | None = None, resolution: float | None = None,
                        samples: int | None = None, progress=None, plant=None,
                        plan=None, probe_wiring: bool = True, wiring=((1, 1), (1, 1)),
                        directions: dict | None = None) -> dict:
    """The felt matrices of a pantograph scene measured through the emulated 2DIY's bytes,
    and their verdict against the stated uncertainty.

    ``2n + 1`` records (each an arm: the set-up, whose hand starts the record; then
    ``samples`` writes) driven by :func:`drive_haply2` on a clean stream, the records
    minus the one from rest fitted as in lockstep
    (:func:`hapsim.analysis.pencil.fit_felt_nd`).

    The stated uncertainty (:func:`hapsim.analysis.felt_matrices.felt_verdict`) is the linearisation
    bound at ``a`` plus the wire's term: each reading is the joint angle to within
    ``delta_j`` = half a count of the set-up's resolution plus one binary32 ulp of the
    largest angle read (the count rounded, then ``360 c / res`` in single precision: two
    roundings of half an ulp), and each torque the host computed reaches the board
    rounded to binary32 (``2^-24 |tau|``). Each error moves the records through the loop
    (:func:`hapsim.lockstep.error_responses`: observed and fed back through the links;
    the joint errors reach the handle through ``J(q0)``, the torque errors through
    ``J(q0)^-T``), and the fit to first order
    (:func:`hapsim.analysis.pencil.felt_sensitivity_nd`); their worst case, whatever
    their signs and correlation (:func:`hapsim.analysis.pencil.worst_case_nd`; the
    rest record's errors enter every difference), is the wire's term. A rounding of a
    smooth signal a few counts wide is not white noise, so no statistical interval is
    taken for it.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    generation : {"gen2", "gen3"}
    amplitude : float
        The hand's ``a`` [m].
    cpr : float, optional
        The emulated encoders' counts per revolution (default the generation's).
    resolution : float, optional
        The set-up's counts per revolution (default ``cpr``).
    samples : int, optional
        Writes per record (default :func:`hapsim.lockstep.default_samples`).
    progress : callable, optional
    plant : hapsim.scene.SceneND, optional
        The scene whose device the emulated board carries (default ``scene``): a device
        that is not the one the scene states (a test of the verdict).
    plan : tuple, optional
        :func:`hapsim.lockstep.identification_plan` of ``scene`` and ``samples``,
        already computed (several measurements of one scene).
    probe_wiring : bool, optional
        Check each joint's wiring first (:func:`hapsim.drivers.haply2_probe.
        find_directions`, within :data:`PROBE_TORQUE`): a joint turned backwards by its
        direction bytes is refused before any torque loop runs.
    wiring : ((int, int), (int, int)), optional
        The emulated board's wiring (:class:`Haply2DIYBoard`).
    directions : dict, optional
        ``motor_direction`` / ``encoder_direction`` bytes the host sets up instead of the
        generation's (:class:`hapsim.drivers.haply2.Haply2DIY`).

    Returns
    -------
    dict
        ``measured``, ``predicted``, ``deviation`` (as
        :func:`hapsim.lockstep.measure_felt_lockstep`); ``bound`` (the linearisation
        bound at ``a``); ``wire`` (``felt_stiffness``, ``felt_damping``: the wire's
        relative terms, inf when the records give no sensitivity; ``reading_bound_rad``
        per joint; ``torque_rel``); ``verdict``, ``within``, ``uncertainty``, ``reason``
        (:func:`hapsim.analysis.felt_matrices.felt_verdict`; "not measurable" also when the board's
        torque clamp engaged, ``clamped`` samples); ``quantum`` (one step of a reading
        at the handle over ``a`` [-]: one count or one binary32 ulp, the larger, times
        ``|J|``), ``quantum_encoders`` (one count of each generation's encoders at the
        handle over ``a``), ``records``, ``samples``, ``direction_probe`` (what the
        wiring probe found: :meth:`hapsim.drivers.haply2_probe.WiringProbe.to_dict`, or
        None).

    Raises
    ------
    DeviceError
        A record with a missing reply (the clean stream lost one).
    IdentificationError
        A joint wired backwards against its direction bytes (the probe's refusal).
    """
    from hapsim.lockstep import identification_plan
    chk, order, N = identification_plan(scene, samples) if plan is None else plan
    n = 2
    board = Haply2DIYBoard(plant if plant is not None else scene, generation, cpr=cpr,
                           amplitude=amplitude, wiring=wiring, clock="lockstep")
    drv = Haply2DIY(generation, resolution=resolution or board.cpr, **(directions or {}))
    probe = None
    if probe_wiring:
        from hapsim.drivers.haply2_probe import find_directions
        probe = find_directions(drv, BoardLink(board.feed),
                                [math.degrees(v) for v in scene.device.joints],
                                force_limit=PROBE_TORQUE, envelope=PROBE_ENVELOPE,
                                rate_hz=scene.rate_hz, pace=False, timeout=0.0)
    runs = []
    for j in range(2 * n + 1):
        r = drive_haply2(board.feed, drv, scene, N)
        if r["missing"]:
            raise DeviceError(f"record {j}: {r['missing']} replies missing on a clean stream")
        runs.append(r)
        if progress is not None:
            progress(j + 1, 2 * n + 1)
    runs = in_hand_order(runs, 0 if probe is None else probe.setups)
    out = felt_verdict_of_runs(scene, runs, (chk, order, N), drv.resolution, amplitude)
    out["direction_probe"] = None if probe is None else probe.to_dict()
    return out


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
        :meth:`read`."""
        self._buf += self._feed(data)

    def read(self, timeout: float) -> bytes:
        """Every reply byte the board has made since the last read (``timeout`` [s] is
        not waited: in lockstep the replies are there at once; ``b""`` when none)."""
        out, self._buf = self._buf, b""
        return out


def felt_verdict_of_runs(scene, runs, plan, resolution: float, amplitude: float) -> dict:
    """The felt matrices of a 2DIY's ``2n + 1`` records and their verdict (the analysis of
    :func:`measure_felt_haply2`, whose notes give the wire's term).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    runs : list of dict
        The records, the one from rest first: ``position`` (N, 2) [m], ``joints``
        (N, 2) [rad] read, ``torque`` (N, 2) [N m] written, and optionally ``bounds``
        (N, 2): the largest error of each row's position beyond the readings' rounding
        [m] (an estimated sample's, :func:`hapsim.pipeline.haply2_host.estimate_bounds`),
        which enters the wire's term through the loop as a reading error does;
        optionally ``usable`` (N,) bool: the rows of the record's undisturbed stretches
        (:func:`hapsim.pipeline.haply2_host.usable_rows`: a record cut at a host stall or
        a re-synchronisation). A difference is fitted on the rows usable in both its
        record and the one from rest, every stretch jointly
        (:func:`hapsim.analysis.pencil.fit_felt_nd`'s ``usable``).
    plan : tuple
        :func:`hapsim.lockstep.identification_plan`'s ``(check, order, N)``.
    resolution : float
        The set-up's counts per revolution.
    amplitude : float
        The hand's ``a`` [m].

    Returns
    -------
    dict
        As :func:`measure_felt_haply2`, and ``fitted_rows``: with ``usable`` given, per
        difference, the rows whose equation was fitted (None without). When the
        stretches give too few equations for the fit the verdict is "not measurable"
        with the reason (the whole records' fit reported, nothing stated of it).
    """
    from hapsim.analysis.pencil import fit_felt_nd
    from hapsim.analysis.linearisation import linearisation_bound
    from hapsim.drivers.haply import MAX_TORQUE
    from hapsim.kinematics import device
    from hapsim.analysis.felt_matrices import felt_deviation, felt_directions, felt_verdict
    from hapsim.lockstep import wire_terms_nd
    chk, order, N = plan
    n = 2
    rest = runs[0]["position"]
    diffs = [r["position"] - rest for r in runs[1:]]
    mass, T = scene.device.mass, scene.period
    usable = None
    if any("usable" in r for r in runs):
        ok0 = np.asarray(runs[0].get("usable", np.ones(len(rest), bool)), bool)
        usable = [ok0 & np.asarray(r.get("usable", np.ones(len(rest), bool)), bool)
                  for r in runs[1:]]
    short = None
    if usable is not None and not all(np.all(u) for u in usable):
        usable = _within_excursion(scene, diffs, usable, amplitude)
    try:
        fit = fit_felt_nd(diffs, mass, T, order, usable=usable)
    except ConfigError as exc:
        if usable is None:
            raise
        # the records' undisturbed stretches hold too few equations (each stretch gives
        # its rows beyond the first ``order``): not measured; the whole records' fit is
        # reported, no statement made of it
        short = (f"the records cut at their disturbances (host stalls, "
                 f"re-synchronisations, missing replies) leave too few undisturbed "
                 f"stretches of more than {order} rows for the fit ({exc})")
        usable = None
        fit = fit_felt_nd(diffs, mass, T, order)
    dev = felt_deviation(fit, chk)
    bound = linearisation_bound(scene, amplitude, chk.render.rendered_poles)
    q = np.asarray(scene.device.joints, float)
    J = device("pantograph", scene.device.geometry).jacobian(q)
    # the wire's term (docstring)
    ang = np.max([np.nanmax(np.abs(r["joints"]), axis=0) for r in runs], axis=0)
    ulp = np.radians(np.spacing(np.float32(np.degrees(ang))).astype(float))
    delta = math.pi / float(resolution) + ulp                 # [rad] per joint
    torque_rel = 2.0 ** -24
    wire = {"felt_stiffness": math.inf, "felt_damping": math.inf,
            "reading_bound_rad": delta.tolist(), "torque_rel": torque_rel}
    errors = [("reading", J, delta),
              ("force", np.linalg.inv(J).T, [torque_rel * np.abs(r["torque"]) for r in runs])]
    if any("bounds" in r for r in runs):
        errors.append(("reading", np.eye(n), [r.get("bounds", np.zeros(2)) for r in runs]))
    if usable is not None:
        # an error at a row no stretch holds (cut out) only changes the initial state of
        # the stretches after it, a free response the fit does not see to first order
        # (the prediction error of a free response of the loop is 0): those rows' errors
        # are left out of the worst case (an estimated row's extrapolation, cut with its
        # run, is one). The record from rest's errors enter every difference: kept where
        # any difference uses its row
        keep = [np.logical_or.reduce(usable)] + list(usable)
        errors = [(kind, G, [np.where(keep[i][:, None], np.broadcast_to(
            np.asarray(b[i] if isinstance(b, list) else b, float), (N, n)), 0.0)
            for i in range(len(runs))]) for kind, G, b in errors]
    wire.update(wire_terms_nd(scene, diffs, chk, order, errors, usable=usable))
    # a torque at the clamp in a row fitted (a record cut there has none in its
    # stretches: hapsim.pipeline.haply2_host.usable_rows)
    clamped = int(sum(np.count_nonzero(
        (np.abs(r["torque"]) >= np.float32(MAX_TORQUE))
        & np.asarray(r.get("usable", np.ones(len(r["torque"]), bool)), bool)[:, None])
        for r in runs))
    v = felt_verdict(dev, bound, wire, estimated=int(sum(
        np.count_nonzero(r["estimated"]) for r in runs if "estimated" in r)),
        directions=felt_directions(fit, chk))
    if short is not None:
        v = {"verdict": "not measurable", "within": None, "uncertainty": None,
             "statements": [], "not_stated": ["felt stiffness", "felt damping"],
             "reason": short}
    if clamped:
        v = {"verdict": "not measurable", "within": None, "uncertainty": None,
             "statements": [], "not_stated": ["felt stiffness", "felt damping"],
             "reason": f"the board's torque clamp ({MAX_TORQUE} N m) engaged in {clamped} "
                       "writes: the loop was not the linear one predicted"}
    Jn = float(np.linalg.norm(J, 2))
    step = max(2 * math.pi / float(resolution), float(np.max(ulp)))
    return {"measured": fit, "predicted": chk, "deviation": dev, "bound": bound,
            "wire": wire, **v, "clamped": clamped,
            "quantum": Jn * step / amplitude,
            "quantum_encoders": {g: Jn * 2 * math.pi / GENERATIONS[g].resolution / amplitude
                                 for g in GENERATIONS},
            "records": 2 * n, "samples": N,
            "fitted_rows": ([0] * len(diffs) if short is not None else
                            [int(np.count_nonzero(_window_ok(u, order))) for u in usable]
                            if usable is not None else None)}


def _within_excursion(scene, diffs, usable, amplitude: float) -> list:
    """``usable`` with the rows after a record's first cut left out where the handle is
    farther from rest than any undisturbed record goes (the largest excursion of the
    loop predicted in lockstep from the hand's starts, :class:`hapsim.lockstep.LockstepND`).

    A stretch after a host stall starts where the torque held over the stall left the
    handle, not from one of the hand's starts: its rows beyond the undisturbed excursion
    are at an amplitude the linearisation bound (stated at ``a``, as for a record without
    a cut) does not cover. Measured on the emulated board (configs/pantograph_wall.yaml,
    the board on its own clock): a 30 ms stall carried a record to 1.0 mm from rest,
    2.9 times the undisturbed excursion and out of the wall (its depth 0.5 mm), and the
    felt stiffness fitted there was 14 % off the prediction. The rows before the first
    cut are the hand's start's, as in a record without one (kept whatever their
    excursion).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    diffs : list of ndarray, each shape (N, n)
        The records minus the record from rest [m].
    usable : list of ndarray of bool, each shape (N,)
    amplitude : float
        The hand's ``a`` [m].

    Returns
    -------
    list of ndarray of bool, each shape (N,)
    """
    from hapsim.lockstep import LockstepND, excitation_starts
    N = diffs[0].shape[0]
    rest = LockstepND(scene).step(N, record=True)
    nominal = 0.0
    for x0, v0 in excitation_starts(scene.dimension, amplitude, scene.period)[1:]:
        r = LockstepND(scene, x0=x0, v0=v0).step(N, record=True)
        nominal = max(nominal, float(np.max(np.linalg.norm(r - rest, axis=1))))
    out = []
    for d_, u in zip(diffs, usable):
        u = np.asarray(u, bool).copy()
        cut = np.flatnonzero(~u)
        if cut.size:
            after = np.arange(N) > cut[0]
            u &= ~(after & (np.linalg.norm(d_, axis=1) > nominal))
        out.append(u)
    return out


def _window_ok(usable, order: int) -> np.ndarray:
    """Rows ``k >= order`` whose rows ``k - order .. k`` are all usable (the equations
    :func:`hapsim.analysis.pencil.fit_felt_nd` forms), as a mask."""
    u = np.asarray(usable, bool)
    bad = np.concatenate(([0], np.cumsum(~u)))
    k = np.arange(u.size)
    return (k >= order) & (bad[k + 1] - bad[np.maximum(k - order, 0)] == 0)
