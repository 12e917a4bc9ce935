"""An independent model of a FireFader (an Arduino Nano at 57600 baud) running
``haptics_firmware.ino``, fader A driven, served on a pty in raw mode
(``docs/testing.md``, "Independent board models"). Nothing of ``hapsim`` is imported.

Read from eberdahl/Open-Source-Haptics-For-Artists,
``Hardware/FireFader/Firmware/haptics_firmware/haptics_firmware.ino`` (commit 6bbe9cd,
cited ``.ino:line``):

- the packet loop (``.ino:292-315``): hunt for a 127 (each byte read after
  ``waitForSerialInput``), take the next two bytes as the forces of faders A and B
  whatever they are, and go on reading while bytes wait: packets that came meanwhile are
  merged, the last one counts;
- ``waitForSerialInput`` (``.ino:264-277``): while no byte waits it counts polls, an
  ``unsigned int``; at 65000 it zeroes both enable filters and both motors, and again each
  time the 16-bit counter comes round (``--poll-us``: one poll's time, 65000 of them 0.1 s
  by default);
- the pass (``.ino:318-390``), timed by the firmware's own comments: ``setPWM`` of both
  faders first (``.ino:320-321``: ``2 f`` of the PWM, 0 while the enable is below 20,
  ``.ino:188-217``), the two capacitive senses (175 us each, ``.ino:324-325``), the two
  current reads (75 us each, ``.ino:328-331``), pot B's eight conversions then pot A's
  (150 us each, ``.ino:341-344``: their sum shifted by 3, then by 2), the 7-byte record
  (``.ino:350-358``, 255 then six values clipped to 0..254, ``SerialWriteNo255``), which
  ``Serial.flush`` waits out (7 bytes at 57600 baud, 1.215 ms), then the heat estimate
  (``.ino:366-371``, fader B's adding fader A's force as the firmware does) and the enable
  filters (``.ino:380-385``);
- the bytes on the wire at 57600 baud, 10 bits a byte, each way: a packet's last byte is
  in 0.52 ms after its first left the host, so the force of a packet takes effect ~0.52 ms
  after the host wrote it, pot A is read ~1.25 ms after and the record's last byte
  leaves ~2.54 ms after.

The fader: ``mass x'' + friction x' = force`` integrated exactly on the wall clock, end
stops at ``--travel``; the pot a 10-bit ADC of ``4 (x / q + 128)`` counts (``q`` 0.05 m /
128, the calibrated Pd patch's scale), read at each conversion's instant; the force
``full_scale * pwm / 254`` (0.39 N at 127 counts, the Pd patch's). A finger on fader A
(its capacitive sense counts to its cap, 15, ``.ino:242-246``); fader B untouched and at
rest.

Usage::

    python tools/independent_boards/firefader_ino.py --link /tmp/ff --truth /tmp/ff.json
"""

from __future__ import annotations

import argparse
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from board_core import Plant, common_arguments, serve  # noqa: E402

BAUD = 57600                  # .ino:103


class FaderState:
    """The firmware's globals (``.ino:59-72``) and the timings."""

    def __init__(self, args) -> None:
        self.cap_a = self.cap_b = 0
        self.enable_a = self.enable_b = 0
        self.heat_a = self.heat_b = 0
        self.q = 0.05 / 128.0
        self.full_scale = float(args.full_scale)
        self.adc_phase = float(args.adc_phase)
        self.poll_s = float(args.poll_us) * 1e-6
        self.cap_s = float(args.cap_us) * 1e-6
        self.current_s = float(args.current_us) * 1e-6
        self.pot_s = float(args.pot_us) * 1e-6
        self.touch_a = int(args.touch)
        self.pwm_a = 0
        self.passes = 0
        self.merged = 0
        self.silences = 0
        self.pot_read_after_pwm = []           # [s], for the truth
        self.pwm_after_first_byte = []

    def adc10(self, x: float) -> int:
        """The pot's 10-bit conversion at position ``x`` [m]."""
        return min(max(math.floor(4.0 * (x / self.q + 128.0) + self.adc_phase), 0), 1023)


def set_pwm(force: int, enable: int) -> int:
    """``setPWM`` (``.ino:188-217``): the signed PWM the motor gets."""
    if force > 127:
        force -= 256
    force *= 2
    if enable < 20:
        force = 0
    return force


def firmware(board, st: FaderState):
    """The ``.ino``'s ``loop`` (``.ino:283-391``) as a coroutine (board_core notes)."""
    plant = board.plant

    def wait_for_serial_input():
        """``.ino:264-277``: the silence rule while no byte waits."""
        if board.available() > 0:
            return
        start = board.now()
        nxt = start + 65000 * st.poll_s
        while board.available() == 0:
            yield ("rx", nxt)
            if board.available() == 0 and board.now() >= nxt:
                st.enable_a = st.enable_b = 0
                st.pwm_a = 0
                plant.set_force(board.now(), 0.0, by_command=False)
                st.silences += 1
                board.note("silence_zero", waited=round(board.now() - start, 6))
                nxt += 65536 * st.poll_s

    while True:
        first = None
        packets = 0
        while True:
            serial_in = 1000
            while serial_in != 127:
                yield from wait_for_serial_input()
                serial_in = board.read()
                if first is None:
                    first = board.now()
                if serial_in != 127:
                    board.counters["hunted"] = board.counters.get("hunted", 0) + 1
            yield from wait_for_serial_input()
            fa = board.read()
            yield from wait_for_serial_input()
            fb = board.read()
            packets += 1
            if board.available() == 0:
                break
        st.merged += packets - 1
        # the pass: the forces first
        st.pwm_a = set_pwm(fa, st.enable_a)
        pwm_b = set_pwm(fb, st.enable_b)     # fader B: untouched, at rest (module notes)
        t_pwm = board.now()
        plant.set_force(t_pwm, st.full_scale * st.pwm_a / 254.0, by_command=True)
        st.pwm_after_first_byte.append(t_pwm - first)
        # capacitive sense A (touched: the count reaches its cap), then B
        yield ("sleep", st.cap_s)
        st.cap_a = ((st.cap_a * 7) >> 3) + (15 if st.touch_a else 1)
        yield ("sleep", st.cap_s)
        st.cap_b = ((st.cap_b * 7) >> 3) + 1
        yield ("sleep", 2 * st.current_s)        # the current reads (not modelled: 0)
        yield ("sleep", st.pot_s)                # pot B's eight conversions (at rest)
        pot_b = ((8 * (512 + int(st.adc_phase)) >> 3) >> 2)
        # pot A: eight conversions, each sampled at its start
        total = 0
        for i in range(8):
            plant.advance_to(board.now() + (i + 0.1) * st.pot_s / 8)   # S/H near its start
            total += st.adc10(plant.x)
        yield ("sleep", st.pot_s)
        pot_a = (total >> 3) >> 2
        st.pot_read_after_pwm.append(board.now() - 0.5 * st.pot_s - t_pwm)

        def no255(v):
            return 254 if v > 254 else 0 if v < 0 else v
        rec = bytes([255, no255(pot_a), no255(pot_b), 0, 0, no255(st.cap_a),
                     no255(st.cap_b)])
        done = board.write(rec)
        yield ("at", done)                        # Serial.flush
        st.heat_a = ((st.heat_a * 16383) >> 14) + (st.pwm_a >> 5)
        st.heat_b = ((st.heat_b * 16383) >> 14) + (st.pwm_a >> 5)
        st.enable_a = ((st.enable_a * 31) >> 5) + 5 * int(
            pot_a < 251 and pot_a > 4 and (st.heat_a >> 10) < 40 and st.cap_a > 30)
        st.enable_b = ((st.enable_b * 31) >> 5) + 5 * int(
            pot_b < 251 and pot_b > 4 and (st.heat_b >> 10) < 40 and st.cap_b > 30)
        st.passes += 1
        del pwm_b


def main(argv=None) -> int:
    """Serve the board (module notes); exit status 0."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common_arguments(p)
    p.add_argument("--mass", type=float, default=0.05, help="knob, belt, rotor, finger [kg]")
    p.add_argument("--friction", type=float, default=0.1, help="viscous friction [N s/m]")
    p.add_argument("--x0", type=float, default=0.015, help="start, at rest [m from centre]")
    p.add_argument("--travel", type=float, default=0.0976,
                   help="between the end stops, centred [m]")
    p.add_argument("--full-scale", type=float, default=0.39, help="force at 127 counts [N]")
    p.add_argument("--adc-phase", type=float, default=0.5,
                   help="the 10-bit ADC's offset [LSB] (0.5: transitions mid-way)")
    p.add_argument("--poll-us", type=float, default=0.1e6 / 65000,
                   help="one idle poll of waitForSerialInput [us]")
    p.add_argument("--cap-us", type=float, default=175.0, help="one capacitive sense [us]")
    p.add_argument("--current-us", type=float, default=75.0, help="one current read [us]")
    p.add_argument("--pot-us", type=float, default=150.0, help="one pot's 8 conversions [us]")
    p.add_argument("--touch", type=int, default=1, help="a finger on fader A (1) or not")
    args = p.parse_args(argv)
    args.board_name = "firefader-ino"
    st = FaderState(args)
    half = args.travel / 2
    plant = Plant(args.mass, args.friction, x0=args.x0, stops=(-half, half), reference=0.0)

    def truth() -> dict:
        import numpy as np
        pr = np.array(st.pot_read_after_pwm[50:] or [np.nan])
        pw = np.array(st.pwm_after_first_byte[50:] or [np.nan])
        return {"passes": st.passes, "merged_packets": st.merged,
                "silence_zeroings": st.silences,
                "pot_read_after_pwm_s": float(np.nanmedian(pr)),
                "pwm_after_first_byte_s": float(np.nanmedian(pw)),
                "params": {"mass": args.mass, "friction": args.friction, "x0": args.x0,
                           "travel": args.travel, "full_scale": args.full_scale,
                           "poll_us": args.poll_us, "cap_us": args.cap_us,
                           "current_us": args.current_us, "pot_us": args.pot_us,
                           "adc_phase": args.adc_phase, "touch": args.touch}}

    return serve(lambda board: firmware(board, st), BAUD, plant, args, truth)


if __name__ == "__main__":
    sys.exit(main())
