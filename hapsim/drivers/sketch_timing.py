"""The Hapkit sketch's timing (haphub/WHC2017 ``Hapkit_arduino.ino``): its Timer1 tick,
its render after a read, and the rates a host can run it at (a whole number of ticks
whose period holds a command and its reply at any write phase): the constants and
:class:`SketchTiming`, the part of :class:`hapsim.drivers.hapkit_serial.HapkitSerial`
that says which rates the sketch holds.
"""

from __future__ import annotations

import math

__all__ = ["FIRMWARE_TICK_S", "PERIOD_TICKS_TOL", "RENDER_LATENCY_S", "RENDER_S",
           "SketchTiming", "whole_ticks"]

#: The time from the sketch's sensor sample to its motor's new duty [s], bounds: the
#: branch with no byte waiting (``Hapkit_arduino.ino:111-122``) samples in ``analogRead``
#: (ADC sample-and-hold 1.5 ADC clocks into a 13-clock conversion at 125 kHz: 92 us more
#: to its end, ATmega328P datasheet, "ADC conversion timing"; the Arduino core's ADC
#: prescaler 128), then runs ``computePosition``, the render and ``forceOutput``'s binary32
#: arithmetic (sim.h:130-149, 158-229: a division and a square root among ~12 float
#: operations, 3100-3600 cycles counted in simavr for avr-gcc -Os, 4900-5800 with
#: Timer0's overflow interrupt every 256 cycles, which ``setPwmFrequency(5, 1)`` makes,
#: ``Hapkit_arduino.h:76-91, 123``) and ``analogWrite``, whose compare register Timer0
#: takes at its next overflow (16 us at most): 0.43-0.50 ms by that count. The independent
#: board model takes 0.19 ms. The firmware's text fixes neither (a compiler, a core
#: version): the range covers both, and the run's verdict takes the prediction over it
#: (:func:`hapsim.pipeline.render_latency.timed_prediction`).
RENDER_LATENCY_S = (0.15e-3, 0.55e-3)
#: The emulated board's own render latency [s] (the count above; inside
#: :data:`RENDER_LATENCY_S`).
RENDER_S = 0.45e-3
#: The sketch's Timer1 tick [s]: the overflow interrupt reloads ``TCNT1 = 65474``
#: (``Hapkit_arduino.h:2``, the ISR at ``Hapkit_arduino.ino:137-140``) on a 16 MHz / 256
#: prescaler (``Hapkit_arduino.h:62-68``): 62 counts of 16 us, 0.992 ms (its comment,
#: ``Hapkit_arduino.h:59-60``: "0.992ms period equals 1.008kHz").
FIRMWARE_TICK_S = 62 * 256 / 16e6
def whole_ticks(period_s: float, tick_s: float = FIRMWARE_TICK_S) -> int | None:
    """``period_s`` in whole ``tick_s`` [s], or None when it is no whole number of them
    within :data:`PERIOD_TICKS_TOL` of a tick (:meth:`HapkitSerial.period_ticks`).

    Parameters
    ----------
    period_s : float
        The host's period [s].
    tick_s : float
        The sketch's tick [s] (default :data:`FIRMWARE_TICK_S`).

    Returns
    -------
    int or None
        The ticks in a period (>= 1), or None.
    """
    ticks = float(period_s) / float(tick_s)
    n = int(round(ticks))
    return n if n >= 1 and abs(ticks - n) <= PERIOD_TICKS_TOL else None

#: How far from a whole number of ticks a host period may be [ticks]
#: (:meth:`HapkitSerial.period_ticks`).
PERIOD_TICKS_TOL = 1e-4


class SketchTiming:
    """The sketch's rates, for a driver (:class:`hapsim.drivers.hapkit_serial.
    HapkitSerial`) with ``name``, ``baud`` (its link's), ``tick_s`` (the sketch's tick)
    and ``native_rate_hz`` (the highest rate it takes)."""

    def period_ticks(self, rate_hz: float) -> int | None:
        """The host's period at ``rate_hz`` in whole :attr:`tick_s`, or None when it is no
        whole number of them.

        Whole within :data:`PERIOD_TICKS_TOL` of a tick: a period off a whole number by
        ``e`` ticks walks the host's writes ``e`` of a tick a period through the board's
        tick, which the aligned writes follow and re-centre once the walk reaches 0.35 of
        a tick (:attr:`hapsim.drivers.tick_align.TickAligned.BAND`): at most once in 3,500
        periods, 14 s at 252 Hz, as a board whose crystal is 25 ppm off the host's clock.
        A rate written to six figures (252.016 Hz: 2e-5 of a tick off) is whole.

        Parameters
        ----------
        rate_hz : float
            The host's rate [Hz], > 0.

        Returns
        -------
        int or None
        """
        return whole_ticks(1.0 / float(rate_hz), self.tick_s)

    def board_rate_hz(self, rate_hz: float) -> float:
        """The rate of a whole number of the sketch's ticks that ``rate_hz`` stands for
        (:meth:`period_ticks`: 252.016 Hz is 4 ticks, 252.0161290... Hz), else
        ``rate_hz`` (which :meth:`check_rate` refuses). The loop is modelled and run at
        the board's period: a period 2.6e-5 of a tick off (the rate written to six
        figures) made a matching paddle's exact record say "differs"
        (``tests/test_unseen_holds.py``'s seed 0: the latency search ran off to 0.19 ms
        and the prediction there, b 0.093 N s/m, was far from the 0.0708 measured; on the
        board's own period the record gave its own loop's pair to 1e-8).

        Parameters
        ----------
        rate_hz : float
            The scene's rate [Hz].

        Returns
        -------
        float
        """
        n = self.period_ticks(rate_hz)
        return float(rate_hz) if n is None else 1.0 / (n * self.tick_s)

    def rate_candidates(self, rates) -> list:
        """The rates of whole ticks within the ladder's span, increasing: ``1 / (n tick)``
        for whole ``n`` from the lowest rate of ``rates`` (less :data:`PERIOD_TICKS_TOL` of
        a tick) to the highest. The ladder's own rates are mostly no whole number of ticks
        (250 Hz is 4.03), which :meth:`check_rate` refuses; of these
        :meth:`~hapsim.drivers.base.Driver.board_rates` keeps those the link holds. A
        ladder that starts above the highest rate the sketch holds (``hapsim advise``'s,
        250 Hz) spans down to it: the sketch's 201.613 Hz (:attr:`native_rate_hz`) is
        then its one candidate.

        Parameters
        ----------
        rates : sequence of float
            Candidate rates [Hz], increasing.

        Returns
        -------
        list of float
            Increasing [Hz].
        """
        lo, hi = min(float(r) for r in rates), max(float(r) for r in rates)
        lo = min(lo, self.native_rate_hz)
        most = math.floor(1.0 / (lo * self.tick_s) + PERIOD_TICKS_TOL)
        least = max(math.ceil(1.0 / (hi * self.tick_s) - PERIOD_TICKS_TOL), 1)
        return [1.0 / (n * self.tick_s) for n in range(most, least - 1, -1)]

    def check_rate(self, rate_hz: float) -> None:
        """Refuse a rate the sketch cannot hold (:meth:`Driver.check_rate`: a command and
        its reply must fit in a period at any write phase, :meth:`latest_answer_s`; at 4
        ticks, where the least answer fits, answers came after the next deadline for much
        of an idle host's run and were paired with the next command), or whose period is
        no whole number of its :attr:`tick_s` (:meth:`period_ticks`): the board reads the
        handle and applies a force only on its ticks, so such a period is sampled at
        intervals of whole ticks that alternate (at 250 Hz on the sketch's 0.992 ms: 4
        ticks, and 5 once in 31 periods; at 300 Hz: 3, 3 and 4 ticks), not the period the
        loop is modelled with, and the measurement would compare another loop with the
        prediction.

        Parameters
        ----------
        rate_hz : float
            The scene's rate [Hz].

        Raises
        ------
        ConfigError
            The rate's period is shorter than the latest answer (the message names the
            highest rate of whole ticks that holds it: 201.613 Hz, 5 ticks, not the
            answer's 234 Hz, which is no whole number of ticks), or its period is not a
            whole number of ticks (the message names the nearest rates that are).
        """
        from hapsim.errors import ConfigError
        rt = self.latest_answer_s()
        least = max(math.ceil(rt / self.tick_s - PERIOD_TICKS_TOL), 1)
        n = self.period_ticks(rate_hz)
        if float(rate_hz) * rt > 1.0 or (n is not None and n < least):
            raise ConfigError(
                f"{self.name}: {rate_hz:g} Hz cannot be held: {self.rate_reason()}; the "
                f"highest rate this device can hold is {1.0 / (least * self.tick_s):.3f} "
                f"Hz ({least} of the sketch's {self.tick_s * 1e3:g} ms ticks)",
                key="rate_hz")
        if n is None:
            ticks = 1.0 / (float(rate_hz) * self.tick_s)
            lo, hi = math.floor(ticks), math.ceil(ticks)
            ok = [1.0 / (t * self.tick_s) for t in (lo, hi) if t >= 1]
            near = [f"{r:.3f} Hz" for r in sorted(ok, key=lambda r: abs(r - rate_hz))
                    if r * rt <= 1.0]
            raise ConfigError(
                f"{self.name}: {rate_hz:g} Hz is no whole number of the sketch's "
                f"{self.tick_s * 1e3:g} ms ticks (Timer1, Hapkit_arduino.h:59-68; the "
                f"board samples and applies forces on them: its intervals would "
                f"alternate, not the loop modelled); nearest: {', '.join(near) or 'none'}",
                key="rate_hz")

    def round_trip_s(self) -> float:
        """The least time from a command's first byte to its reply's last [s]: the 10-byte
        command and the 9-byte reply at 57600 baud, 10 bits a byte, and the render's least
        latency between them (:data:`RENDER_LATENCY_S`): 3.45 ms. The sketch reads the
        handle at the command's end or at the tick after its read began, so its tick
        adds up to 0.42 ms more (:meth:`latest_answer_s`; ``Hapkit_arduino.ino:96-135``;
        :func:`hapsim.drivers.tick_align.fit_tick_jump`).

        Returns
        -------
        float
            [s]: ``190 / baud`` plus the render's least latency.
        """
        return (10 + 9) * 10 / self.baud + RENDER_LATENCY_S[0]

    def latest_answer_s(self) -> float:
        """The most time from a command's first byte to its reply's last [s], whatever the
        write's phase on the sketch's tick: both messages' wire time, the render's
        largest latency (:data:`RENDER_LATENCY_S`) and the tick's wait, ``L = 2 T - W``
        with ``W`` the 9 bytes after the header (:func:`hapsim.drivers.tick_align.
        fit_tick_jump`: the handle read on the tick after the read's, 0.42 ms after the
        command's end at most): 4.27 ms. The emulated board's, swept over a tick's
        phases at each bound of the render's latency, is 3.87-4.27 ms; its own render,
        4.17 ms.

        Returns
        -------
        float
            [s].
        """
        return (self.round_trip_s() - RENDER_LATENCY_S[0] + RENDER_LATENCY_S[1]
                + 2 * self.tick_s - 9 * 10 / self.baud)

    def rate_reason(self) -> str:
        """Why the highest rate is what it is (:meth:`check_rate`'s message).

        Returns
        -------
        str
            The latest answer [ms] and its parts.
        """
        return (f"a command and its reply take up to {self.latest_answer_s() * 1e3:.3g} ms "
                f"(both on the wire at {self.baud} baud, the sketch's tick and its render "
                f"at the write's worst phase)")
