"""An independent model of a Hapkit (an Arduino Uno-class board at 57600 baud) running
the WHC2017 hAPI sketch with one function added that applies the host's force, served on
a pty in raw mode (``docs/testing.md``, "Independent board models"). Nothing of
``hapsim`` is imported.

Read from haphub/WHC2017 ``hFirmware/Hapkit_Arduino_Control/Hapkit_arduino/`` (commit
ef6028f; ``Hapkit_arduino.ino`` cited ``.ino:line``, ``Hapkit_arduino.h`` ``.h``,
``Hapkit_Kinematics_Simulation.h`` ``sim.h``), and its copy of 2017-04-07 in
``Virtual-Environment/Hapkit_arduino/`` (commit e09075d):

- Timer1's overflow interrupt sets a flag; it reloads ``TCNT1 = 65474`` at a 16 MHz / 256
  prescaler: 62 counts of 16 us, a **0.992 ms** tick (``.h``, ``setTimer1Interrupt`` and
  its comment "0.992ms period equals 1.008kHz"; ``--tick-us``);
- ``loop`` (``.ino:96-135``): on a tick, if a byte waits, the command is read -- the
  header with one ``Serial.read()`` and 9 bytes with ``Serial.readBytes`` (``.h``,
  ``receive_data``): no framing, so a lost byte shifts every later command by one until
  something realigns the reads; nothing else that tick. On a tick with no byte waiting
  the sensor is read (``updateSensorPosition``, ``sim.h:86-123``: ``analogRead``), the
  position computed (``sim.h:130-149``, binary32), the force rendered
  (``renderingAlgorithm``, ``sim.h:158-194``) and output (``forceOutput``,
  ``sim.h:206-229``), and, if a command came since the last reply, the 9-byte reply
  ``[function][float x][float force]`` written (``.ino:124-132``; the 2017-04-07 copy sends
  ``force``, the repository's head ``Tp``, the motor pulley's torque: ``--reply-second``);
  the flag is one bit: ticks that pass while ``readBytes`` waits are one tick;
- ``Serial.readBytes`` waits per byte up to the Stream timeout, 1000 ms of ``millis()``;
  ``standard_hapkit_setup`` sets Timer0's prescaler to 1 for the motor's PWM on pin 5
  (``.h``, ``initialize_actuator`` -> ``setPwmFrequency(pwm, 1)``), which makes
  ``millis()`` run 64 times fast: **15.6 ms** of real time (``--readbytes-timeout-ms``); a
  byte not come by then leaves the buffer's old content (the stack's, modelled as the
  last command's byte at that place);
- the force: the host's force for the added function (``--function``, 255 by default:
  ``force = amplitude``, the command's second float), functions 0-3 as the sketch renders
  them (0 none, 1 a wall at 5 mm, 2 damping, 3 a spring), any other none; the motor's
  output ``(int)(255 sqrt(|Tp| / 0.0183))`` with ``Tp = rp / rs * rh * force``
  (``sim.h:191, 218-228``), the torque the sketch's own motor model gives back for that
  output (``--force-levels 0``: the float exactly, for a comparison);
- the sensor: ``xh = rh (m updatedPos + b)`` in binary32 (``sim.h:130-138``), one count
  ``rh m`` = 17.2 um at the handle, counted from the power-up pose (``sim.h:73-78``:
  ``b`` makes it 0 there); ``--count-um 0`` reads the position exactly;
- its timing within a tick: the sensor's sample 12 us into the branch (the ADC's
  sample-and-hold), the motor's output ``--render-us`` after the branch starts
  (``analogRead``'s 104 us at the default prescaler 128, then the binary32 arithmetic and
  ``sqrt`` of ``computePosition``, ``renderingAlgorithm`` and ``forceOutput``), the reply
  then, its 9 bytes at 57600 baud on the wire.

The paddle: ``mass x'' + friction x' = force`` at the handle, integrated exactly on the
wall clock; powered up at 0 (the spring's rest), then put at ``--x0`` at rest by the hand
before the host connects.

Usage::

    python tools/independent_boards/hapkit_sketch.py --link /tmp/hk --truth /tmp/hk.json
"""

from __future__ import annotations

import argparse
import math
import os
import struct
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from board_core import Plant, common_arguments, f32, seeded_phase, serve  # noqa: E402

BAUD = 57600
RS, RP, RH = 0.073152, 0.004191, 0.075      # sim.h:38-40
M_CAL = 0.0002292                            # sim.h:23, rad a count
OFFSET_NEG = 50                              # sim.h:7
MOTOR_K = 0.0183                             # sim.h:218


class SketchState:
    """The sketch's globals (``.ino:61-77``, ``sim.h:10-55``) and the timings."""

    def __init__(self, args) -> None:
        self.tick_s = float(args.tick_us) * 1e-6
        self.timeout_s = float(args.readbytes_timeout_ms) * 1e-3
        self.render_s = float(args.render_us) * 1e-6
        self.count_m = float(args.count_um) * 1e-6
        self.levels = int(args.force_levels)
        self.host_function = int(args.function)
        self.reply_second = args.reply_second
        self.device_function = 0
        self.freq = self.amplitude = 0.0
        self.reply = False
        self.raw0 = 500                           # the MR sensor's raw count at power-up
        self.b = f32(-(self.raw0 - OFFSET_NEG) * f32(M_CAL))
        self.xh = self.xh_prev = self.dxh = self.dxh_prev = self.dxh_filt = 0.0
        self.force = 0.0
        self.tp = 0.0
        self.buf = bytes(9)
        self.phase = float(args.phase)
        self.ticks_read = 0
        self.renders = 0
        self.misparsed = 0
        self.timeouts = 0


def firmware(board, st: SketchState):
    """The sketch's ``loop`` and Timer1 flag (``.ino:96-140``) as a coroutine."""
    plant = board.plant
    tick = st.tick_s
    consumed = 0          # the index of the last tick whose flag was taken

    def position_counts(x: float) -> int:
        if st.count_m <= 0:
            return 0
        return math.floor(x / st.count_m + st.phase) - math.floor(st.phase)

    def render(function: int) -> float:
        """``renderingAlgorithm`` (``sim.h:158-194``) with the host's function added."""
        xh = st.xh
        if function == st.host_function:
            return st.amplitude
        if function == 0:
            return 0.0
        if function == 1:
            return f32(-400.0 * f32(xh - 0.005)) if xh > 0.005 else 0.0
        if function == 2:
            return f32(-15.0 * st.dxh_filt)
        if function == 3:
            return f32(-100.0 * xh)
        return 0.0

    while True:
        # the timer's flag: set at every tick since the last taken
        k_now = math.floor(board.now() / tick + 1e-9)
        if k_now <= consumed:
            yield ("at", (consumed + 1) * tick)
            continue
        consumed = k_now
        if board.available() > 0:
            st.reply = True
            board.read()                          # the header: command_instructions
            buf = bytearray(st.buf)
            for i in range(9):                    # Serial.readBytes(9)
                if board.available() == 0:
                    deadline = board.now() + st.timeout_s
                    while board.available() == 0 and board.now() < deadline:
                        yield ("rx", deadline)
                    if board.available() == 0:
                        st.timeouts += 1
                        board.note("readbytes_timeout", got=i)
                        break
                buf[i] = board.read()
            st.buf = bytes(buf)
            st.device_function = buf[0]
            st.freq, st.amplitude = struct.unpack_from("<ff", buf, 1)
            if st.device_function != st.host_function:
                st.misparsed += 1
            st.ticks_read += 1
            continue
        # the branch with no byte waiting: sensor, position, force, reply
        t0 = board.now()
        plant.advance_to(t0 + 12e-6)
        u = position_counts(plant.x) if st.count_m > 0 else None
        if u is None:
            theta = f32(plant.x / RH)
        else:
            upd = st.raw0 - OFFSET_NEG + u
            theta = f32(f32(f32(M_CAL) * float(upd)) + st.b)
        st.xh = f32(f32(RH) * theta)
        st.dxh = f32((st.xh - st.xh_prev) / 0.001)
        st.dxh_filt = f32(0.9 * st.dxh + 0.1 * st.dxh_prev)
        st.xh_prev, st.dxh_prev = st.xh, st.dxh
        force = f32(render(st.device_function))
        tp = f32(f32(f32(RP / RS) * RH) * force)
        st.force, st.tp = force, tp
        yield ("sleep", st.render_s)
        if not math.isfinite(force):
            applied = 0.0
        elif st.levels > 0:
            duty = math.sqrt(abs(tp) / MOTOR_K) if math.isfinite(tp) else 1.0
            duty = min(max(duty, 0.0), 1.0)
            out = int(duty * 255)
            applied = MOTOR_K * (out / 255.0) ** 2 / (RP / RS * RH)
            applied = applied if force > 0 else -applied
        else:
            applied = force
        plant.set_force(board.now(), applied, by_command=st.reply)
        st.renders += 1
        if st.reply:
            st.reply = False
            second = force if st.reply_second == "force" else tp
            board.write(bytes([st.device_function]) + struct.pack("<ff", st.xh, second))


def main(argv=None) -> int:
    """Serve the board (module notes); exit status 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common_arguments(p)
    p.add_argument("--mass", type=float, default=0.1, help="hand and paddle at the handle [kg]")
    p.add_argument("--friction", type=float, default=0.3, help="viscous friction [N s/m]")
    p.add_argument("--x0", type=float, default=0.01, help="start, at rest [m]")
    p.add_argument("--tick-us", type=float, default=992.0, help="Timer1's tick [us]")
    p.add_argument("--readbytes-timeout-ms", type=float, default=1000.0 / 64,
                   help="readBytes' timeout per byte in real time [ms]")
    p.add_argument("--render-us", type=float, default=200.0,
                   help="from the branch's start to the motor's output [us]")
    p.add_argument("--count-um", type=float, default=RH * M_CAL * 1e6,
                   help="one sensor count at the handle [um] (0: exact)")
    p.add_argument("--phase", type=float, default=None,
                   help="the sensor's count grid phase [counts] (default: seeded)")
    p.add_argument("--force-levels", type=int, default=256,
                   help="256: the sketch's 8-bit output and motor model; 0: exact float")
    p.add_argument("--function", type=int, default=255, help="the host-force function code")
    p.add_argument("--reply-second", choices=("force", "Tp"), default="force",
                   help="the reply's second float (module notes)")
    p.add_argument("--workspace", type=float, default=0.06,
                   help="the paddle's end stops at +-this [m]")
    args = p.parse_args(argv)
    args.board_name = "hapkit-whc2017"
    if args.phase is None:
        args.phase = seeded_phase(args.seed, 104729)
    st = SketchState(args)
    plant = Plant(args.mass, args.friction, x0=args.x0,
                  stops=(-args.workspace, args.workspace), reference=0.0)

    def truth() -> dict:
        return {"ticks_read": st.ticks_read, "renders": st.renders,
                "misparsed_commands": st.misparsed, "readbytes_timeouts": st.timeouts,
                "params": {k: getattr(args, k) for k in (
                    "mass", "friction", "x0", "tick_us", "readbytes_timeout_ms",
                    "render_us", "count_um", "phase", "force_levels", "function",
                    "reply_second", "workspace")}}

    return serve(lambda board: firmware(board, st), BAUD, plant, args, truth)


if __name__ == "__main__":
    sys.exit(main())
