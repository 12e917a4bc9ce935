"""The Haply M3 board's firmware as the device side of the wire reads the host's bytes:
the command parser of Haply's "Arduino firmware" V1.5 (S. Ding and C. Gallacher, 2017,
``Haply_M3_Firmware_V1_5.h``), :class:`CommandDecoder`, which the emulated boards run
(:class:`hapsim.emulated.driver_mock.HaplyDevice`, the M3;
:class:`hapsim.emulated.haply2_board.Haply2DIYBoard`, the 2DIY). The bytes' layout and the
host's codec are :mod:`hapsim.drivers.haply` (module notes there: no framing, no
watchdog); the host never parses commands.
"""

from __future__ import annotations

import math
import struct

from hapsim.drivers.haply import CMD_RESET, CMD_SETUP, CMD_WRITE

__all__ = ["CommandDecoder", "PASS_S", "pass_at"]

#: The firmware's pass [s]: ``loop()`` runs its body when 50 us have passed since the
#: last pass began (``Haply_M3_Firmware_V1_5.ino`` lines 59-64: ``currentState -
#: lastPublished >= 50``, ``lastPublished = currentState`` at each pass, a command waiting
#: or not).
PASS_S = 50e-6


def pass_at(t: float, next_pass: float) -> float:
    """The firmware's first pass at or after ``t`` [s], the next one due at ``next_pass``
    [s] (the last pass's start plus :data:`PASS_S`, or the end of a body that took
    longer: the pass after it comes at once). The passes go on every :data:`PASS_S`
    whether a command waits or not, so a write that comes to an idle board waits up to a
    pass, by a phase the host does not see. (A body's own time, a few microseconds, and
    ``micros()``'s 1 us steps are left out.)

    Parameters
    ----------
    t : float
        When the bytes came [s].
    next_pass : float
        The next pass's time [s].

    Returns
    -------
    float
        The pass's time [s], ``next_pass + k PASS_S`` with ``k >= 0`` the least that is
        at or after ``t`` (a time a round-off past a pass, 1e-6 of one, is that pass).
    """
    if t <= next_pass or not math.isfinite(t):
        return max(t, next_pass)            # (no time: the caller's to refuse)
    return next_pass + math.ceil((t - next_pass) / PASS_S - 1e-6) * PASS_S


#: A float32, little-endian (the firmware's torques and encoder parameters).
_F = struct.Struct("<f")


class CommandDecoder:
    """The board's command parser, as the firmware V1.5 runs it.

    One command byte, then the bytes its layout says: reset ``[0][addr]`` clears every
    port's address (motors, encoders, analog and PWM pins; not the motor's torque: the
    caller holds it); set-up ``[1][addr]...`` first does the same, then gives ``addr`` to
    the ports its masks name (direction bytes go to the first ports in order, as the
    firmware's ``mtr_parameters``/``enc_parameters`` store them), reads one pin byte per
    analog and PWM pin and 8 bytes (offset [deg], counts per revolution) per encoder;
    write ``[2][addr]`` reads one byte per PWM pin of ``addr`` and a float32 torque per
    motor of ``addr``; any other byte is no command. The firmware's ``readBytes``
    (torques, encoder parameters: ``Haply_M3_Firmware_V1_5.h`` lines 188 and 218) waits
    for its bytes; its single ``SerialUSB.read()`` calls (address, masks, directions, pin
    lists, PWM bytes: lines 146, 175-182, 202, 206, 308, 323, 546-583) return -1, stored
    as the byte 255, when the buffer is empty. With ``absent=255``
    (:class:`hapsim.emulated.driver_mock.HaplyDevice`, the M3 board) that is modelled: a
    single read past the bytes arrived so far (those of the host's writes fed up to now:
    over USB a write's bytes come together) reads 255 and the bytes that come later are
    the next command's, so a set-up out of garbage ends at once instead of swallowing up
    to :data:`hapsim.drivers.haply.LONGEST_COMMAND` bytes, and only a ``readBytes`` (at
    most :data:`hapsim.drivers.haply.LONGEST_WAIT` bytes) waits. With ``absent=None`` a
    command waits for all its bytes. A board on its own clock reads a byte as absent only
    at a pass that comes before the next bytes arrive: :attr:`ready` says whether that
    pass has come (the 2DIY board, :class:`hapsim.emulated.haply2_board.Haply2DIYBoard`);
    the parser waits until then.

    Parameters
    ----------
    absent : {None, 255}
        What a single read of a byte not arrived gives (None: the command waits for it).

    Attributes
    ----------
    stats : dict
        ``writes``, ``setups``, ``resets``, ``unknown`` (bytes that are no command).
    motor_addr, encoder_addr : list of int, length 4
        Address of each motor / encoder port (0: none).
    encoder_offset, encoder_res : list of float, length 4
        Each encoder's set-up (offset [deg], counts per revolution).
    motor_direction, encoder_direction : list of int, length 4
        Rotational direction byte of the k-th motor / encoder port set up (the firmware
        keeps them apart, in ``actuators[k]`` and ``encoders[k]``: a 2DIY gen3 sets its
        motors CW and its encoders CCW).
    analog_addr : list of int, length 12
    pwm_addr : list of int, length 14
    ready : callable or None
        ``ready() -> bool``: whether the pass that would read an absent byte has come
        (no more bytes can arrive before it); None: at once (each feed is every byte
        that has arrived by the next pass: a lockstep board, or one fed at its passes).
    """

    def __init__(self, absent=None) -> None:
        if absent not in (None, 255):
            raise ValueError(f"absent must be None or 255, got {absent!r}")
        self.absent = absent
        self.ready = None
        self._buf = bytearray()
        self.stats = {"writes": 0, "setups": 0, "resets": 0, "unknown": 0, "absent": 0}
        self._clear()
        self.encoder_offset = [0.0] * 4
        self.encoder_res = [0.0] * 4
        self.motor_direction = [0] * 4
        self.encoder_direction = [0] * 4

    def _clear(self) -> None:
        self.motor_addr = [0] * 4
        self.encoder_addr = [0] * 4
        self.analog_addr = [0] * 12
        self.pwm_addr = [0] * 14

    @property
    def id(self):
        """Address of motor port 1 (None when it is not set up)."""
        return self.motor_addr[0] or None

    def _setup(self, b) -> int:
        self._clear()
        addr = b[1]
        mmask = b[2] & 0x0F
        nm = bin(mmask).count("1")
        for k in range(nm):
            self.motor_direction[k] = b[3 + k]
        i = 3 + nm
        emask = b[i] & 0x0F
        ne = bin(emask).count("1")
        for k in range(ne):
            self.encoder_direction[k] = b[i + 1 + k]
        i += 1 + ne
        for k in range(b[i]):
            pin = b[i + 1 + k]
            if 54 <= pin <= 65:
                self.analog_addr[pin - 54] = addr
        i += 1 + b[i]
        for k in range(b[i]):
            pin = b[i + 1 + k]
            if pin <= 13:
                self.pwm_addr[pin] = addr
        i += 1 + b[i]
        for port in range(4):
            if emask >> port & 1:
                self.encoder_addr[port] = addr
                self.encoder_offset[port] = _F.unpack_from(b, i)[0]
                self.encoder_res[port] = _F.unpack_from(b, i + 4)[0]
                i += 8
        for port in range(4):
            if mmask >> port & 1:
                self.motor_addr[port] = addr
        return addr

    def feed(self, data: bytes) -> list:
        """Bytes in; ``("write", addr, {motor port: torque})``, ``("setup", addr)``,
        ``("reset", addr)`` out (the parser's state is the last command's).

        Parameters
        ----------
        data : bytes
            The host's bytes, after those held.

        Returns
        -------
        list of tuple
            The commands completed, in order: a write's ports 0..3 (motor port - 1), its
            torques the float32 sent [N m]; a command not complete stays held.
        """
        return list(self.commands(data))

    @property
    def waiting(self) -> int:
        """Bytes held: a command not complete yet [bytes]."""
        return len(self._buf)

    def _pad(self, buf, n: int) -> bool:
        """Whether the single reads up to byte ``n`` of the command at the start of
        ``buf`` can be made: the bytes are there, or (``absent=255``) those not arrived
        are read as 255, put in their place (the bytes that come later follow them)."""
        if len(buf) >= n:
            return True
        if self.absent is None or (self.ready is not None and not self.ready()):
            return False
        self.stats["absent"] += n - len(buf)
        buf += bytes([self.absent]) * (n - len(buf))
        return True

    def _single_len(self, b) -> int:
        """How many bytes of the set-up at the start of ``b`` are single reads (address,
        masks, directions, pin counts and pins: all but the encoder parameters), padding
        with 255 where they have not arrived (``absent``); -1 when they are not all there
        and the parser waits."""
        i = 3                                      # [1][addr][motor mask]
        if not self._pad(b, i):
            return -1
        i += bin(b[2] & 0x0F).count("1") + 1       # directions, the encoder mask
        if not self._pad(b, i):
            return -1
        i += bin(b[i - 1] & 0x0F).count("1") + 1   # directions, the analog count
        if not self._pad(b, i):
            return -1
        i += b[i - 1] + 1                          # pins, the PWM count
        if not self._pad(b, i):
            return -1
        i += b[i - 1]                              # pins
        if not self._pad(b, i):
            return -1
        return i

    def commands(self, data: bytes):
        """As :meth:`feed`, one command at a time: the parser's state (addresses, set-up)
        is each command's own when it is yielded.

        One parser for both rules (class notes): a single read of a byte not arrived
        waits for it (``absent=None``) or reads :attr:`absent` in its place
        (:meth:`_pad`); a ``readBytes`` (the set-up's encoder parameters, a write's
        torques) waits for its bytes either way.

        Parameters
        ----------
        data : bytes
            The host's bytes, after those held.

        Yields
        ------
        tuple
            A command, as :meth:`feed`'s.
        """
        buf = self._buf
        buf += data
        while buf:
            c = buf[0]
            if c == CMD_RESET:
                if not self._pad(buf, 2):          # [0][addr]
                    break
                a = buf[1]
                self.stats["resets"] += 1
                self._clear()
                del buf[:2]
                yield ("reset", a)
            elif c == CMD_SETUP:
                i = self._single_len(buf)
                if i < 0:
                    break
                ne = bin(buf[3 + bin(buf[2] & 0x0F).count("1")] & 0x0F).count("1")
                n = i + 8 * ne
                if len(buf) < n:
                    break                          # readBytes waits for the parameters
                a = self._setup(buf)
                self.stats["setups"] += 1
                del buf[:n]
                yield ("setup", a)
            elif c == CMD_WRITE:
                if not self._pad(buf, 2):          # [2][addr]
                    break
                addr = buf[1]
                npwm = sum(a == addr for a in self.pwm_addr)
                if not self._pad(buf, 2 + npwm):   # one single read per PWM pin
                    break
                ports = [p for p in range(4) if self.motor_addr[p] == addr]
                n = 2 + npwm + 4 * len(ports)
                if len(buf) < n:
                    break                          # readBytes waits for the torques
                tq = {p: _F.unpack_from(buf, 2 + npwm + 4 * k)[0] for k, p in enumerate(ports)}
                self.stats["writes"] += 1
                del buf[:n]
                yield ("write", addr, tq)
            else:
                self.stats["unknown"] += 1
                del buf[:1]

    def reply_layout(self, addr: int) -> tuple:
        """What the board answers a write to ``addr`` with: ``(analog pins, encoder
        ports)`` of that address (the reply is ``[addr]`` and a float32 for each).

        Parameters
        ----------
        addr : int
            The write's address, 0..255.

        Returns
        -------
        (int, list of int)
            The analog pins of ``addr`` and its encoder ports 0..3 (port - 1), in order.
        """
        return (sum(a == addr for a in self.analog_addr),
                [p for p in range(4) if self.encoder_addr[p] == addr])
