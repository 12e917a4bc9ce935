"""Arming a device: HELLO asked and checked (protocol version, axes, the line's capacity
from LINK), the velocity sensor asked for, PING round trips, CONFIG sent (PROTOCOL.md §4).

:class:`Handshake` is the part of :class:`hapsim.host.loop.HostLoop` that does it, at the
start and again on each recovery (:mod:`hapsim.host.recovery`). It reads the loop's
``transport``, ``config``, ``stop``, ``measured`` and ``result``, and sets
``force_limit``, ``state`` and the start time.
"""

from __future__ import annotations

import math
import time

import numpy as np

import firmware_protocol as fp
from hapsim.host.loop_types import (QUIESCE_NONCE, QUIESCE_TRIES, QUIESCE_WAIT,
                                      SENSORS_TRIES, SENSORS_WAIT, percentiles_us)
from hapsim.errors import ConfigError, DeviceError, ProtocolError

__all__ = ["Handshake"]


class Handshake:
    """HELLO, SENSORS, PING and CONFIG: the host loop's handshake (a base of
    :class:`~hapsim.host.loop.HostLoop`)."""

    # ------------------------------------------------------------------ handshake
    def _ask_hello(self, timeout: float):
        """Send HELLO_REQUEST (every 0.5 s) until a HELLO arrives; None after ``timeout``."""
        tr = self.transport
        clock = self._clock
        end = clock() + timeout
        next_ask = -math.inf
        while True:
            if self.stop.set:
                return None
            now = clock()
            if now >= end:
                return None
            if now >= next_ask:
                tr.send(fp.HelloRequest(fp.PROTOCOL_VERSION))
                next_ask = now + 0.5
            for msg in tr.receive(min(0.05, max(end - now, 0.0))):
                if isinstance(msg, fp.Link):
                    self._link = msg  # the device sends it just before HELLO
                if isinstance(msg, fp.Hello):
                    return msg

    def _check_hello(self, hello) -> None:
        """Check a HELLO and set the force limit from it.

        Parameters
        ----------
        hello : firmware_protocol.Hello
            The device's HELLO.

        Raises
        ------
        ProtocolError
            The device speaks another protocol version, or has another number of axes
            than 1 (the message carries the last frames received, docs/design.md, rule 11).
        ConfigError
            The device's LINK (sent with HELLO) shows that its serial line cannot carry a
            STATE and a FORCE frame per tick at the configured rate
            (:func:`firmware_protocol.link_max_rate`).
        """
        cfg = self.config
        if hello.protocol_version != fp.PROTOCOL_VERSION:
            raise ProtocolError(f"device speaks protocol {hello.protocol_version}, "
                                f"hapsim speaks {fp.PROTOCOL_VERSION} (port "
                                f"{self.transport.info.get('port')}); last frames:\n"
                                f"{self.transport.last_frames() or '(none received)'}")
        if hello.n_axes != 1:
            raise ProtocolError(f"device has {hello.n_axes} axes; hapsim run drives 1-DoF "
                                f"devices (port {self.transport.info.get('port')}); last "
                                f"frames:\n{self.transport.last_frames() or '(none received)'}")
        link = getattr(self, "_link", None)
        self._compact_ask = False
        self._link_refusal = None
        periods = cfg.watchdog_us * 1e-6 * cfg.rate_hz
        compact_ok = (cfg.compact != "off" and periods <= 250
                      and hasattr(self.transport, "set_compact"))
        if cfg.compact == "on" and compact_ok:
            self._compact_ask = True
        if link is not None:
            vel = self.measured is not None
            top = fp.link_max_rate(link.baud, link.bits_per_byte, hello.n_axes,
                                   velocity=vel)
            top_c = fp.link_max_rate(link.baud, link.bits_per_byte, hello.n_axes,
                                     velocity=vel, compact=True)
            # a UART device that applies its FORCEs in binary32 steps (HELLO.force_scale >
            # 0: PROTOCOL.md §4, HELLO) loses nothing to the compact frames, and its tick
            # gains the codec time of the binary64 fields: on the emulated Hapkit at 1 kHz
            # the STATE leaves 155 us after its tick instead of 423 us, which leaves the
            # host ~670 us to answer instead of ~340 us (tools/bench_firmware.py --realtime)
            if compact_ok and cfg.compact == "auto" and (
                    cfg.rate_hz > top or fp.wants_compact(
                        link.baud, link.bits_per_byte, hello.n_axes, cfg.rate_hz)
                    or (link.baud > 0 and float(hello.force_scale) > 0)):
                self._compact_ask = True
            if cfg.rate_hz > top:
                up = fp.state_frame_bytes(hello.n_axes) + (
                    fp.velocity_frame_bytes(hello.n_axes) if vel else 0)
                why = (f"{cfg.rate_hz:g} Hz is more than the device's link carries: at "
                       f"{link.baud} baud ({link.bits_per_byte} bits per byte) a "
                       f"{up}-byte STATE{' + VELOCITY' if vel else ''} up and a "
                       f"{fp.force_frame_bytes(hello.n_axes)}-byte FORCE down per tick fit "
                       f"{top:.0f} Hz at most ({fp.LINK_LOAD:.0%} of the line); choose "
                       f"rate_hz <= {int(top)}")
                if not (self._compact_ask and cfg.rate_hz <= top_c):
                    raise ConfigError(why, key="rate_hz")
                # the compact frames would carry it: refused after SENSORS if not taken
                self._link_refusal = (why + f", or a device that offers the compact "
                                            f"frames (they carry {top_c:.0f} Hz)")
        limit = cfg.force_limit if math.isfinite(cfg.force_limit) else hello.force_limit
        self.force_limit = min(float(limit), float(hello.force_limit))

    def _ask_sensors(self) -> None:
        """Enable the device's velocity sensor, when the loop has a :attr:`measured`
        velocity to fill, and the compact frames, when :meth:`_check_hello` decided to ask
        for them (SENSORS_REQUEST, PROTOCOL.md §4); nothing when neither.

        A device that does not answer (written before SENSORS_REQUEST) within
        ``SENSORS_TRIES * SENSORS_WAIT``, or leaves COMPACT out of its answer, keeps the
        full frames; one that enables COMPACT sends STATE_COMPACT from its next tick, and the
        transport then sends FORCE_COMPACT (:attr:`LoopResult.frames`).

        Raises
        ------
        ConfigError
            The device answers that it has no velocity sensor, or does not answer, when the
            velocity was asked; or it does not take the compact frames at a rate only they
            carry on its line.
        """
        tr = self.transport
        set_compact = getattr(tr, "set_compact", None)
        if set_compact is not None:
            set_compact(None)          # full frames until the device says otherwise
        self.result.frames = "full"
        want = (fp.SENSOR_VELOCITY if self.measured is not None else 0) | (
            fp.FEATURE_COMPACT if getattr(self, "_compact_ask", False) else 0)
        if not want:
            return
        clock = self._clock
        answer = None
        for _ in range(SENSORS_TRIES):
            tr.send(fp.SensorsRequest(want))
            end = clock() + SENSORS_WAIT
            while answer is None and clock() < end and not self.stop.set:
                for msg in tr.receive(0.02):
                    if type(msg) is fp.Sensors:
                        answer = msg
            if answer is not None or self.stop.set:
                break
        if answer is not None and answer.enabled & want & fp.FEATURE_COMPACT:
            set_compact(float(self.config.rate_hz))
            self.result.frames = "compact"
        elif getattr(self, "_link_refusal", None) and not self.stop.set:
            raise ConfigError(self._link_refusal, key="rate_hz")
        if self.measured is None:
            return
        if answer is not None and answer.enabled & fp.SENSOR_VELOCITY:
            self.result.velocity = self.measured.as_dict()
            return
        if self.stop.set:
            return
        why = (f"it answers SENSORS offered=0x{answer.offered:04X}" if answer is not None
               else f"no SENSORS answer to {SENSORS_TRIES} requests: a device written "
                    f"before the velocity message")
        where = tr.info.get("port") or tr.info.get("kind", "the transport")
        raise ConfigError(f"velocity_sensor: the device on {where} does not offer a "
                          f"velocity sensor ({why}); choose "
                          f"another correction, or a device that measures its velocity",
                          key="device.correction.kind")

    def _quiesce(self) -> bool:
        """Disarm the device and read everything it sent before: STOP, then PING, until
        its PONG (PROTOCOL.md §4: STOP disarms; a device answers PING in order).

        A device keeps ticking armed STATEs of the session it had (a port that vanished and
        came back, a host that died without STOP) until it takes the next CONFIG. Those
        STATEs carry the handle of that session, not the one the CONFIG (re)starts: a host
        that resumed the scene at one would start from the wrong position (when the
        real-time mock restarted its plant at CONFIG, the state after a reconnect showed a
        handle 0.105 m out, beyond the position bound; it now carries its handle across
        CONFIGs, as a board does, and the old session's seq still differs). The byte stream is in order, so once the
        PONG of a PING sent after the STOP is read, every STATE sent before the STOP has
        been read too (and dropped here), and the device, disarmed, sends no armed STATE
        until CONFIG arms it: the first armed STATE after CONFIG is of the new session. An
        armed STATE within two periods after the PONG shows that the STOP was lost on the
        way (a lossy link): STOP and PING again.

        Returns
        -------
        bool
            True when the PONG came (:attr:`LoopResult.quiesced`); False after
            :data:`QUIESCE_TRIES` waits of :data:`QUIESCE_WAIT` without it (a lossy link or
            a device that does not answer PING: the loop then skips, before it resumes, a
            STATE that shows an earlier session, :attr:`LoopResult.earlier_session`), or on
            a stop.
        """
        tr = self.transport
        clock = self._clock
        settle = 2.0 / self.config.rate_hz
        for k in range(QUIESCE_TRIES):
            nonce = QUIESCE_NONCE + k
            tr.send(fp.Stop())
            tr.send(fp.Ping(nonce, 0))
            end = clock() + QUIESCE_WAIT
            pong = None
            armed = False
            while not armed and clock() < (end if pong is None else pong + settle):
                if self.stop.set:
                    return False
                for msg in tr.receive(0.02 if pong is None else settle):
                    if type(msg) is fp.Pong and msg.nonce == nonce:
                        pong = clock()
                    elif (pong is not None and type(msg) is fp.State
                          and msg.status & fp.STATUS_ARMED):
                        armed = True    # the STOP was lost on the way: send it again
            if pong is not None and not armed:
                return True
        return False

    def _send_config(self) -> None:
        cfg = self.config
        self.transport.receive(0.0)  # drop anything stale before arming
        self.transport.send(fp.Config(float(cfg.rate_hz), int(cfg.watchdog_us),
                                      float(self.force_limit)))
        self._fresh = True

    def handshake(self) -> fp.Hello:
        """Ask for HELLO, check it, send CONFIG (arms the device).

        Returns
        -------
        Hello or None
            None when the stop flag was set before the device answered.

        Raises
        ------
        DeviceError
            No HELLO within ``hello_timeout``.
        ProtocolError
            A protocol version mismatch, or not 1 axis.
        """
        cfg = self.config
        tr = self.transport
        self.state = "handshake"
        hello = self._ask_hello(cfg.hello_timeout)
        if hello is None:
            if self.stop.set:
                return None
            raise DeviceError(f"no HELLO from the device within {cfg.hello_timeout:g} s "
                              f"(port {tr.info.get('port')}); last frames:\n"
                              f"{tr.last_frames() or '(none received)'}")
        self._check_hello(hello)
        if self.before_arm is not None:
            self.before_arm()
            if self.stop.set:       # a signal during the warm-up: the device is not armed
                return None
        self._ask_sensors()
        self._measure_ping()
        self._send_config()
        self.state = "armed"
        self.result.hello = hello
        self._t0 = self._clock()
        return hello

    @property
    def armed_at(self) -> float:
        """The moment the loop was armed (CONFIG sent) on the loop's clock [s]
        (``time.monotonic`` unless the transport brings its own ``clock``); 0.0 before;
        what the run's events count their times from."""
        return self._t0

    def _measure_ping(self, count: int = 16) -> None:
        """Round-trip PING -> PONG before arming [us] (transport + device answer time)."""
        tr = self.transport
        clock = self._clock
        rtts = []
        for nonce in range(count):
            t0 = time.perf_counter_ns()
            tr.send(fp.Ping(nonce, t0 // 1000))
            end = clock() + 0.2
            got = False
            while not got and clock() < end:
                for msg in tr.receive(0.02):
                    if isinstance(msg, fp.Pong) and msg.nonce == nonce:
                        got = True
            if got:
                rtts.append((time.perf_counter_ns() - t0) * 1e-3)
        self.result.ping_rtt_us = percentiles_us(np.array(rtts))
        self.result.ping_rtt_us["answered"] = len(rtts)
        self.result.ping_rtt_us["sent"] = count
