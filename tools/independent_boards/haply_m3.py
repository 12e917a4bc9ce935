"""An independent model of a Haply M3 board running firmware V1.5, one joint on motor
port 1 and encoder port 1, served on a pty in raw mode (``docs/testing.md``, "Independent
board models"). Nothing of ``hapsim`` is imported.

Read from HaplyHaptics/Haply-Arduino-Firmware-Versions (``Haply_M3_Firmware_V1_5/``,
cited ``.ino:line`` and ``.h:line``), the Encoder library it ships
(``Arduino_Support_Libraries/Encoder/Encoder.h``), the PWM library it includes
(``pwm01.h``, randomvibe's version 01, not shipped in that repository: read from the copy
in Dirk7589/TactileEMFSandboxWHC17SIC ``EMFSandbox/Arduino/libraries/PWM/pwm01.h``) and
the Arduino Due's core (arduino/ArduinoCore-sam ``variants/arduino_due_x/variant.h``):

- the loop runs one pass at least 50 us after the last (``.ino:61-63``); a pass with a
  byte waiting takes one command (``.ino:65-83``): 0 reset, 1 set-up, 2 write, any other
  byte nothing; a write sets ``replyCode = 1`` and the same pass answers
  (``.ino:85-94``, ``read_states``);
- every single ``SerialUSB.read()`` of a byte not yet arrived gives -1, stored in a
  ``byte``: 255 (``.h:139-141, 146, 175, 179, 182, 202, 206, 308, 323, 546, 560, 569,
  583``); only ``readBytes`` waits, for the torques (``.h:218``) and the encoder
  parameters (``.h:188``), up to the Stream's default timeout, 1000 ms, per byte (a byte
  not come by then leaves the buffer's old content);
- a reset (``.h:144-164``) clears every address and the PWM pins' pulses; it does not
  touch the motor's duty: the torque goes on;
- a set-up (``.h:167-195``) clears the addresses (``reset_device``, ``.h:283-299``), reads
  the address, the motors' and encoders' masks and direction bytes (``mtr_parameters``,
  ``enc_parameters``, ``.h:544-587``: direction bytes stored from index 0, whatever the
  mask), the sensors and PWM pins, the encoders' offsets and resolutions
  (``readBytes``); each encoder set up is a ``new Encoder``, whose constructor waits
  ``delayMicroseconds(2000)`` with its count at 0 (Encoder.h, the constructor), then
  ``write(offset * resolution / 360)``, a float truncated to an int32 (``.h:441-442``);
  then each motor set up gets ``pwm_setup`` (``.h:446-461``), which writes duty 0
  (pwm01.h ``pwm_setup``: ``PWMC_SetDutyCycle(..., pwm_duty)`` with ``pwm_duty = 0``):
  **a set-up zeroes the motors it names**, after its encoders' 2 ms each;
- a write (``.h:198-233``) reads its address, a pulse byte for each PWM pin of that
  address, then ``4 n`` torque bytes for the ``n`` motors of that address and sets each;
  the reply (``.h:236-278``) is the address and a float32 per analog sensor and encoder of
  that address (``read_encoder_value``, ``.h:533-538``: ``360.0 * count / resolution``);
- the torque (``create_torque``, ``.h:467-492``): clamped to 0.123 N m,
  ``duty = 4095 * |torque| / 0.123`` truncated (12-bit), written with ``pwm_write_duty``
  which maps the 12 bits set by ``pwm_set_resolution(12)`` (``.h:173``) to the Due's
  ``PWM_RESOLUTION`` 8 (variant.h) by a shift of 4, on a channel whose period is 255
  counts (pwm01.h ``pwm_max_duty_Ncount``): the motor gets ``(duty >> 4) / 255`` of its
  torque, 256 levels (one 4.8e-4 N m step, truncated toward zero) -- ``--torque-levels 0``
  applies the float exactly instead, for a comparison;
- no watchdog: the last torque is held through any silence.

The joint: ``inertia x'' + friction x' = torque`` integrated exactly on the wall clock
(:class:`board_core.Plant`); its encoder counts edges on a fixed physical grid
(``--cpr`` counts a revolution, a seeded phase), counting up with the angle unless the
set-up's encoder direction byte swaps its pins (``.h:435-439``); a positive torque turns
it the way the angle grows with motor direction byte 0 (``--motor-sign -1``: wired the
other way).

Usage::

    python tools/independent_boards/haply_m3.py --link /tmp/m3 --truth /tmp/m3.json \\
        [--x0 0.2] [--inertia 0.001] [--friction 0.001] [--drop-rx 0.005 --drop-tx 0.005]

It prints the pty's path and serves until SIGTERM, then writes the truth log.
"""

from __future__ import annotations

import argparse
import math
import os
import struct
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from board_core import Plant, common_arguments, f32, seeded_phase, serve  # noqa: E402

MAX_TORQUE = 0.123            # .h:54
PWM_OUTPUT_RESOLUTION = 4095  # .h:55
PASS_S = 50e-6                # .ino:61
ENCODER_WAIT_S = 2000e-6      # Encoder.h, the constructor's delayMicroseconds(2000)
READBYTES_TIMEOUT_S = 1.0     # Stream's default timeout
PWMPIN1 = 9                   # .h:41, the motor on port 1
ENC_PORT1 = 0                 # encoders[0]: ENCPIN1 (.h:27-28)


class M3State:
    """The firmware's globals (``.ino:24-42``) and the joint's wiring."""

    def __init__(self, args) -> None:
        # actuators: hostAddress, rotationalDirection, pwmPin, dirPin (.h:64-70)
        self.act = [{"addr": 0, "dir": 0, "pwm": 0, "dirpin": 0} for _ in range(4)]
        # encoders: hostAddress, rotationalDirection, offset, resolution, count state
        self.enc = [{"addr": 0, "dir": 0, "off": 0.0, "res": 0.0, "ref": None}
                    for _ in range(4)]
        self.pulse = [{"addr": 0, "pulse": 0, "pin": 0} for _ in range(14)]
        self.analog = [{"addr": 0, "pin": 0} for _ in range(12)]
        self.reply_code = 3
        self.device_address = 0
        self.q = 2 * math.pi / float(args.cpr)          # one count [rad]
        self.phase = float(args.phase)
        self.motor_sign = float(args.motor_sign)
        self.levels = int(args.torque_levels)
        self.duty8 = 0                                  # the motor's duty, 0..255
        self.dir_low = True                             # the motor's direction pin
        self.frames = []                                # (t, physical angle at count 0)
        self.null_encoder_reads = 0
        self.last_buf = {}

    def raw_count(self, theta: float, swapped: bool) -> int:
        """Edges counted from the grid's origin at the physical angle ``theta`` [rad]."""
        c = math.floor(theta / self.q + self.phase)
        return -c if swapped else c


def firmware(board, st: M3State):
    """The firmware's ``loop`` (``.ino:59-96``) as a coroutine (board_core notes)."""
    plant = board.plant
    last = -1.0

    def read1() -> int:
        b = board.read()
        if b < 0:
            board.counters["absent_reads"] = board.counters.get("absent_reads", 0) + 1
            return 255
        return b

    def read_bytes(n: int, key: str):
        """``Stream::readBytes``: each byte waited for up to the timeout; a byte not
        come leaves the buffer's old content (the stack's, modelled as the last time)."""
        old = st.last_buf.get(key, bytes(n))
        out = bytearray(old[:n].ljust(n, b"\0"))
        for i in range(n):
            if board.available() == 0:
                deadline = board.now() + READBYTES_TIMEOUT_S
                while board.available() == 0 and board.now() < deadline:
                    yield ("rx", deadline)
                if board.available() == 0:
                    board.note("readbytes_timeout", got=i, of=n)
                    break
            out[i] = board.read()
        st.last_buf[key] = bytes(out)
        return bytes(out)

    def set_motor(torque_f32: float, motor: dict, by_command=True) -> None:
        """``create_torque`` on ``motor``: only PWMPIN1 drives the joint."""
        if motor["pwm"] != PWMPIN1:
            return
        output_low = motor["dir"] == 0          # output = !LOW when direction 0
        # torque <= 0 -> dirPin = output; else !output (.h:476-481)
        if torque_f32 <= 0 or math.isnan(torque_f32):
            pin = output_low if not math.isnan(torque_f32) else (not output_low)
        else:
            pin = not output_low
        # pin True = HIGH. Wiring: dirPin LOW turns the joint the positive way (times
        # motor_sign)
        t = abs(torque_f32)
        if t > MAX_TORQUE:
            t = f32(MAX_TORQUE)
        if math.isnan(t):
            duty = 0                            # a NaN's conversion (ARM vcvt: 0)
        else:
            duty = int(f32(PWM_OUTPUT_RESOLUTION * t) / MAX_TORQUE)
        if st.levels > 0:
            duty8 = duty >> 4                   # pwm_write_duty: 12 -> 8 bits
            mag = MAX_TORQUE * duty8 / 255.0
        else:
            duty8 = duty >> 4
            mag = min(t, MAX_TORQUE) if not math.isnan(t) else 0.0
        st.duty8, st.dir_low = duty8, not pin
        u = (mag if not pin else -mag) * st.motor_sign
        plant.set_force(board.now(), u, by_command=by_command)

    def encoder_value(e: dict) -> float:
        if e["ref"] is None:
            st.null_encoder_reads += 1
            return 0.0
        plant.advance_to(board.now())
        c = e["count0"] + st.raw_count(plant.x, e["swapped"]) - e["ref"]
        return f32(360.0 * c / e["res"]) if e["res"] != 0 else float("nan")

    def reset_device() -> None:
        for i in range(4):
            st.act[i]["addr"] = 0
            st.enc[i]["addr"] = 0
        for p in st.pulse:
            p["addr"] = 0
            p["pulse"] = 0
        for a in st.analog:
            a["addr"] = 0

    while True:
        if board.now() < last + PASS_S:
            yield ("at", last + PASS_S)
            continue
        if board.available() == 0:
            yield ("rx", math.inf)
            continue
        last = board.now()
        cmd = read1()
        if cmd == 0:                                        # reset_haply (.h:144-164)
            st.device_address = read1()
            reset_device()
            board.note("reset", address=st.device_address)
        elif cmd == 1:                                      # setup_device (.h:167-195)
            reset_device()
            addr = read1()
            motor_use = read1()
            mask_m = [(motor_use >> i) & 1 for i in range(4)]
            for i in range(sum(mask_m)):
                st.act[i]["dir"] = read1()
            enc_use = read1()
            mask_e = [(enc_use >> i) & 1 for i in range(4)]
            for i in range(sum(mask_e)):
                st.enc[i]["dir"] = read1()
            n_sensors = read1()
            for _ in range(n_sensors):
                pin = read1()
                if 54 <= pin <= 65:
                    st.analog[pin - 54] = {"addr": addr, "pin": pin}
            n_pwms = read1()
            for _ in range(n_pwms):
                pin = read1()
                if 0 <= pin <= 13:
                    st.pulse[pin] = {"addr": addr, "pulse": st.pulse[pin]["pulse"],
                                     "pin": pin}
            n_enc = sum(mask_e)
            params = b""
            if n_enc > 0:
                params = yield from read_bytes(n_enc * 8, "encparams")
            j = 0
            for i in range(4):
                if not mask_e[i]:
                    continue
                off, res = struct.unpack_from("<ff", params, j)
                j += 8
                e = st.enc[i]
                e["addr"] = addr
                e["off"], e["res"] = off, res
                e["swapped"] = e["dir"] > 0
                yield ("sleep", ENCODER_WAIT_S)             # new Encoder: 2 ms
                plant.advance_to(board.now())
                e["ref"] = st.raw_count(plant.x, e["swapped"])
                v = f32(f32(off * res) / 360.0)
                e["count0"] = int(v) if math.isfinite(v) and abs(v) < 2 ** 31 else 0
                if i == ENC_PORT1:
                    # the physical angle that reads 0 in this frame [rad]
                    sgn = -1.0 if e["swapped"] else 1.0
                    st.frames.append((board.now(), plant.x - sgn * e["count0"] * st.q
                                      if res else float("nan")))
            for i in range(4):                               # setup_actuators (.h:366-392)
                if mask_m[i]:
                    a = st.act[i]
                    a["addr"] = addr
                    a["pwm"], a["dirpin"] = [(9, 26), (8, 22), (6, 34), (7, 30)][i]
                    if a["pwm"] == PWMPIN1:
                        st.duty8 = 0                         # pwm_setup writes duty 0
                        plant.set_force(board.now(), 0.0, by_command=False)
            st.device_address = addr
            board.note("setup", address=addr, motors=motor_use, encoders=enc_use,
                       offset=float(st.enc[0]["off"]) if mask_e[0] else None,
                       resolution=float(st.enc[0]["res"]) if mask_e[0] else None)
        elif cmd == 2:                                      # write_states (.h:198-233)
            addr = read1()
            for p in st.pulse:
                if p["addr"] == addr:
                    p["pulse"] = read1()
            motors = [a for a in st.act if a["addr"] == addr]
            data = yield from read_bytes(4 * len(motors), "torques")
            for k, a in enumerate(motors):
                tq = struct.unpack_from("<f", data, 4 * k)[0]
                set_motor(tq, a)
            st.device_address = addr
            st.reply_code = 1
            board.counters["writes"] = board.counters.get("writes", 0) + 1
            if not motors:
                board.counters["writes_no_motor"] = board.counters.get(
                    "writes_no_motor", 0) + 1
        else:
            board.counters["no_command"] = board.counters.get("no_command", 0) + 1
        if st.reply_code == 1:                              # read_states (.h:236-278)
            addr = st.device_address
            out = bytearray([addr])
            for a in st.analog:
                if a["addr"] == addr:
                    out += struct.pack("<f", 512.0)
            for e in st.enc:
                if e["addr"] == addr:
                    out += struct.pack("<f", encoder_value(e))
            board.write(bytes(out))
            st.reply_code = 3


def main(argv=None) -> int:
    """Serve the board (module notes); exit status 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common_arguments(p)
    p.add_argument("--inertia", type=float, default=0.001, help="joint inertia [kg m^2]")
    p.add_argument("--friction", type=float, default=0.001, help="viscous friction [N m s/rad]")
    p.add_argument("--x0", type=float, default=0.2,
                   help="the joint's angle at power-up, at rest, from the spring's rest [rad]")
    p.add_argument("--cpr", type=float, default=4880.0, help="encoder counts a revolution")
    p.add_argument("--phase", type=float, default=None,
                   help="the edge grid's phase at angle 0 [counts] (default: seeded)")
    p.add_argument("--motor-sign", type=float, default=1.0, choices=(1.0, -1.0))
    p.add_argument("--torque-levels", type=int, default=256,
                   help="256: the firmware's 8-bit duty (module notes); 0: exact float")
    args = p.parse_args(argv)
    args.board_name = "haply-m3-v1.5"
    if args.phase is None:
        args.phase = seeded_phase(args.seed, 7919)
    st = M3State(args)
    plant = Plant(args.inertia, args.friction, x0=args.x0, reference=0.0)

    def truth() -> dict:
        frames = [f for _, f in st.frames]
        walk = max((abs(f - frames[0]) for f in frames), default=0.0) if frames else None
        return {"frames": st.frames[:500], "frame_walk": walk,
                "first_frame_zero": frames[0] if frames else None,
                "null_encoder_reads": st.null_encoder_reads,
                "params": {"inertia": args.inertia, "friction": args.friction,
                           "x0": args.x0, "cpr": args.cpr, "phase": args.phase,
                           "motor_sign": args.motor_sign,
                           "torque_levels": args.torque_levels}}

    return serve(lambda board: firmware(board, st), None, plant, args, truth)


if __name__ == "__main__":
    sys.exit(main())
