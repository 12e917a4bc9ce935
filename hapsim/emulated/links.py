"""How the host reaches an emulated device: with no bytes (:class:`InProcessTransport`, a
:class:`~hapsim.emulated.mock.MockDevice` called directly: fast lockstep tests), on a virtual
clock (:class:`SimTransport`: a real-time mock with an optional fault plan, in-process;
bytes, decoder, ticks, watchdog and faults are real, time is simulated, so fault tests are
fast and deterministic), or as a child process on a pseudo-terminal
(:class:`EmbeddedMock`: ``python -m hapsim mock --fd`` on the master side of a fresh pty,
whose slave path the host opens with :class:`hapsim.host.transport.SerialTransport`).

The first two offer the host loop the interface of :mod:`hapsim.host.transport` (``send``,
``receive``, ``close``, ``info``, ``last_frames``; a virtual ``clock`` and ``sleep``)."""

from __future__ import annotations

import json
import math
import os
import sys
from collections import deque

import firmware_protocol as fp
from hapsim.errors import DeviceError
from hapsim.spawn import PtyChild

__all__ = ["InProcessTransport", "EmbeddedMock", "SimTransport", "BoardLink",
           "LockstepBoardLink"]


class InProcessTransport:
    """The host talks to a mock device object directly (lockstep, no bytes).

    Parameters
    ----------
    mock : MockDevice
        A lockstep mock; its replies are queued and returned by :meth:`receive`.
    """

    def __init__(self, mock) -> None:
        self.mock = mock
        self._q: deque = deque([mock.hello()])
        self.info = {"kind": "in-process", "port": None, "baud": None, "low_latency": False,
                     "low_latency_note": "in-process: no port"}

    def send(self, msg) -> None:
        """Hand ``msg`` to the mock; queue its replies.

        Parameters
        ----------
        msg : firmware_protocol message
            A host message (HELLO_REQUEST, CONFIG, FORCE, PING, STOP).
        """
        self._q.extend(self.mock.handle(msg, 0))

    def receive(self, timeout: float = 0.0) -> list:
        """Queued replies (never waits: the mock answers synchronously).

        Parameters
        ----------
        timeout : float
            Ignored [s] (kept for the transport interface).

        Returns
        -------
        list of firmware_protocol messages
            The mock's replies since the last call, in order (possibly empty).
        """
        out = list(self._q)
        self._q.clear()
        return out

    def close(self) -> None:
        """Nothing to release."""

    def last_frames(self) -> str:
        """The last frames received, as text (docs/design.md, rule 11).

        Returns
        -------
        str
            Always ``""``: in-process there are no frames.
        """
        return ""


class EmbeddedMock(PtyChild):
    """A mock device in a child process on the master side of a new pseudo-terminal.

    Parameters
    ----------
    device : hapsim.scene.Device
        The device the mock models (passed to the child as JSON).
    excitation : hapsim.scene.Excitation
        How the mock's hand starts the motion.
    rate_hz : float
        Native rate announced by the mock [Hz] (the host's CONFIG sets the rate used).
    lockstep : bool
        One period per FORCE (deterministic) instead of real-time ticks.
    seed : int
        Sensor-noise seed.
    base_dir : str, optional
        Directory relative profile paths are resolved against.
    faults : str, optional
        Fault SPEC for the mock (:mod:`hapsim.emulated.faults`); validated here first.
    fault_seed : int
        Seed of the fault generator.
    rt_priority : int
        ``SCHED_FIFO`` priority the child takes once started, after its imports
        (``hapsim mock --rt-priority``); 0: the caller's scheduling. Start it from a thread
        under normal scheduling: a child inherits ``SCHED_FIFO``, and its start-up (~0.5 s
        of CPU) would then run as a real-time process and starve every other real-time
        loop of the machine.
    tick : {"auto", "compiled", "python"}
        The mock's real-time ticks (``hapsim mock --tick``).

    Attributes
    ----------
    port : str
        Slave path (``/dev/pts/N``), to open with :class:`SerialTransport`; with a
        ``vanish`` fault, a symbolic link in a temporary directory that the child points
        at each new pty (like a udev ``/dev/serial/by-id`` link).
    report_path : str
        JSON file where the child writes its report on exit (:meth:`PtyChild.report`):
        the :class:`~hapsim.emulated.mock.MockStats` fields, ``end``, ``decoder``,
        ``totals``, and with faults ``faults_injected``, ``fault_events``.

    Notes
    -----
    The child is ``sys.executable -m hapsim mock --fd N`` with the pty master passed by
    ``pass_fds`` and ``PYTHONPATH`` extended with this package's parent, started in a new
    session (a Ctrl-C at the terminal reaches only the host, which then stops the device
    cleanly). The slave is put in raw mode (``tty.setraw``) and kept open by this object
    until :meth:`close`, so the child never sees EIO before the host opens the port.
    """

    def __init__(self, device, excitation, rate_hz: float, *, lockstep: bool = False,
                 seed: int = 0, base_dir: str | None = None, faults: str | None = None,
                 fault_seed: int = 0, rt_priority: int = 0, tick: str = "auto") -> None:
        import dataclasses
        import tempfile

        from hapsim.emulated.faults import parse_faults

        plan = parse_faults(faults, fault_seed)      # ConfigError before any process starts
        master = self.open_pty("hapsim-mock-")
        self._linkdir = None
        if plan.has_vanish:
            self._linkdir = tempfile.mkdtemp(prefix="hapsim-port-")
            link = os.path.join(self._linkdir, "port")
            os.symlink(self.port, link)
            self.port = link
        spec = {"device": dataclasses.asdict(device),
                "excitation": dataclasses.asdict(excitation), "base_dir": base_dir}
        if not math.isfinite(spec["device"]["force_limit"]):
            spec["device"]["force_limit"] = None
        cmd = [sys.executable, "-m", "hapsim", "mock", "--fd", str(master),
               "--spec", json.dumps(spec), "--rate", repr(float(rate_hz)),
               "--report", self.report_path, "--seed", str(seed), "--tick", tick]
        if lockstep:
            cmd.append("--lockstep")
        if faults:
            cmd += ["--faults", faults, "--fault-seed", str(int(fault_seed))]
        if self._linkdir:
            cmd += ["--link", self.port]
        if rt_priority:
            cmd += ["--rt-priority", str(int(rt_priority))]
        self.start(cmd, master)

    def close(self) -> None:
        """:meth:`PtyChild.close`, and the ``vanish`` fault's link directory removed."""
        super().close()
        if self._linkdir:
            import shutil
            shutil.rmtree(self._linkdir, ignore_errors=True)


class SimTransport:
    """A real-time mock device on a virtual clock, in-process, with optional faults.

    Parameters
    ----------
    mock : MockDevice
        A real-time mock (``lockstep=False``).
    plan : FaultPlan, optional
        Faults to inject (:mod:`hapsim.emulated.faults`).
    host_latency_us : int
        Virtual time the host takes per call to :meth:`send` [us] (0: instant).

    Attributes
    ----------
    device : FaultyDevice
        The device side (mock + faults), for inspection by tests.
    now_us : int
        Virtual time [us].
    sent : list or None
        When a list, every message the host sends is appended (tests).

    Notes
    -----
    Frames are really encoded, faulted, and decoded by this transport's
    :class:`firmware_protocol.StreamDecoder`; the device ticks every ``1 / rate`` of
    virtual time while armed; :meth:`receive` advances virtual time to the next event
    (tick, held frame) up to its timeout; :meth:`sleep` advances it. While the device's
    port has vanished, :meth:`send` and :meth:`receive` raise :class:`DeviceError` and
    :meth:`reopen` fails until the port is back. While its link is stalled, the host's bytes
    wait and are read when it resumes.
    """

    def __init__(self, mock, plan=None, *, host_latency_us: int = 0) -> None:
        from hapsim.emulated.faults import FaultyDevice

        self.device = FaultyDevice(mock, plan)
        self.mock = mock
        self.now_us = 0
        self._next_tick = None
        self._dec = fp.StreamDecoder()
        self._pending_in = []
        self._dead = False
        self.host_latency_us = int(host_latency_us)
        self.sent = None
        self.reopened = 0
        self.info = {"kind": "sim", "port": "sim://mock", "baud": None, "low_latency": False,
                     "low_latency_note": "virtual clock"}
        self.device.connect(0)

    @property
    def decoder(self) -> fp.StreamDecoder:
        """The host-side stream decoder (counters in ``.stats``)."""
        return self._dec

    def clock(self) -> float:
        """Virtual time.

        Returns
        -------
        float
            :attr:`now_us` in seconds [s].
        """
        return self.now_us * 1e-6

    def _check_port(self) -> None:
        dev = self.device
        if dev.vanish_pending:
            dev.vanish_pending = False
            self._dead = True
        if self._dead:
            raise DeviceError("read from sim://mock failed: [Errno 5] Input/output error "
                              "(the port vanished)")

    def _step_to(self, t_us: int) -> None:
        """Advance virtual time to ``t_us``, ticking the device on the way."""
        dev = self.device
        while True:
            if self._pending_in and not dev.link_down(self.now_us):
                data = b"".join(self._pending_in)
                self._pending_in.clear()
                dev.feed(data, self.now_us)
            if dev.ticking:
                if self._next_tick is None:
                    self._next_tick = self.now_us
                if self._next_tick <= t_us:
                    self.now_us = max(self.now_us, self._next_tick)
                    # the period at the rate the device ticks now (a CONFIG sets it)
                    self._next_tick += int(round(1e6 / self.mock.rate_hz))
                    dev.tick(self.now_us)
                    continue
            else:
                self._next_tick = None
            break
        self.now_us = max(self.now_us, t_us)
        dev.poll(self.now_us)
        if dev.vanish_pending:
            dev.vanish_pending = False
            self._dead = True

    def sleep(self, seconds: float) -> None:
        """Let virtual time pass, ticking the device meanwhile.

        Parameters
        ----------
        seconds : float
            Time to let pass [s] (rounded to 1 us; negative: none).
        """
        self._step_to(self.now_us + max(int(round(seconds * 1e6)), 0))

    def send(self, msg) -> None:
        """Encode ``msg`` and hand the bytes to the device (queued while it is stalled).

        Parameters
        ----------
        msg : firmware_protocol message
            A host message (recorded in :attr:`sent` when that is a list); takes
            ``host_latency_us`` of virtual time.

        Raises
        ------
        DeviceError
            While the port is gone.
        """
        self._check_port()
        if self.sent is not None:
            self.sent.append(msg)
        data = fp.encode(msg)
        if self.host_latency_us:
            self._step_to(self.now_us + self.host_latency_us)
        if self.device.link_down(self.now_us) or self._pending_in:
            self._pending_in.append(data)
        else:
            self.device.feed(data, self.now_us)

    def receive(self, timeout: float = 0.0) -> list:
        """Messages received, advancing virtual time up to ``timeout`` for one.

        Parameters
        ----------
        timeout : float
            Longest virtual wait [s] for a first message (truncated to whole
            microseconds; 0: only what is due now). Time advances tick by tick (or to the
            next held frame), so the device's ticks, watchdog and faults happen on the way.

        Returns
        -------
        list of firmware_protocol messages
            Messages of the frames completed, in order; empty after the timeout. Bad frames
            are dropped and counted by :attr:`decoder`.

        Raises
        ------
        DeviceError
            While the port is gone.
        """
        dev = self.device
        end = self.now_us + max(int(timeout * 1e6), 0)
        while True:
            self._check_port()
            data = dev.pop_due(self.now_us)
            if data:
                msgs = self._dec.feed(data)
                if msgs:
                    return msgs
            if self.now_us >= end:
                return []
            nxt = end
            if dev.ticking:
                nt = self._next_tick if self._next_tick is not None else self.now_us
                nxt = min(nxt, max(nt, self.now_us))
            rel = dev.next_release_us()
            if rel is not None and rel > self.now_us:
                nxt = min(nxt, rel)
            if dev.link_down(self.now_us):
                nxt = min(nxt, max(dev.stalled_until_us, dev.vanished_until_us))
            self._step_to(nxt)

    def reopen(self) -> None:
        """Open the port again: fails while the device's port is still gone.

        Raises
        ------
        DeviceError
            While the port is gone.
        """
        if self.device.vanished(self.now_us):
            raise DeviceError("cannot open port sim://mock: [Errno 2] No such file or directory")
        self._dead = False
        self.device.vanish_pending = False
        self._dec.reset()
        self.reopened += 1

    def close(self) -> None:
        """Nothing to release."""

    def last_frames(self) -> str:
        """The last frames received as text (docs/design.md, rule 11).

        Returns
        -------
        str
            One line ``outcome: hex`` per frame, oldest first (the decoder keeps 16);
            ``""`` before any frame.
        """
        return self._dec.format_last_frames()


class BoardLink:
    """A driver's board stepped by its bytes, behind a serial port's ``write``,
    ``in_waiting`` and ``read`` (pyserial's names): each write fed to ``board.feed`` at
    once (a lockstep board: its time is the writes'), its replies readable at once. The
    host's bytes pass through ``rx`` and the board's through ``tx`` (the link's faults:
    :class:`hapsim.emulated.driver_mock.ByteFaults`' ``rx``/``tx``); ``truth`` keeps the
    board's joints after each write when it has a plant.

    Parameters
    ----------
    board : object
        ``feed(bytes) -> bytes`` (e.g. :class:`hapsim.emulated.haply2_board.Haply2DIYBoard`
        with ``clock="lockstep"``).
    rx, tx : callable, optional
        ``bytes -> bytes`` on the host's and the board's bytes (default: unchanged).

    Attributes
    ----------
    truth : list of ndarray
        The board's ``plant.joints()`` after each write [rad] (empty without a plant).
    """

    def __init__(self, board, rx=None, tx=None) -> None:
        self.board = board
        self.rx = rx or (lambda b: b)
        self.tx = tx or (lambda b: b)
        self.out = bytearray()
        self.truth: list = []

    def write(self, data) -> int:
        """The host's bytes to the board (through ``rx``), its answer queued (through
        ``tx``); returns ``len(data)``, as pyserial's ``write``.

        Parameters
        ----------
        data : bytes-like
            What the host writes.

        Returns
        -------
        int
            ``len(data)`` (those ``rx`` drops included).
        """
        self.out += self.tx(self.board.feed(self.rx(bytes(data))))
        plant = getattr(self.board, "plant", None)
        if plant is not None:
            self.truth.append(plant.joints().copy())
        return len(data)

    @property
    def in_waiting(self) -> int:
        return len(self.out)

    def read(self, n: int) -> bytes:
        """Up to ``n`` bytes the board sent (never waits), as pyserial's ``read``.

        Parameters
        ----------
        n : int
            Most bytes to take.

        Returns
        -------
        bytes
            The oldest bytes not yet read (``b""`` when none).
        """
        b = bytes(self.out[:n])
        del self.out[:n]
        return b

    def reset_input_buffer(self) -> None:
        """Drop what the board sent and the host has not read."""
        self.out.clear()

    def flush(self) -> None:
        """Nothing waits to be written (each write is taken at once)."""


class LockstepBoardLink(BoardLink):
    """The emulated FireFader in-process on its lockstep clock, as
    :func:`hapsim.pipeline.faders_run.record_faders`'s serial port: each write is one tick
    of the board (asked for by name: deterministic, no pty), the host's silences told to
    it (``idle``).

    Parameters
    ----------
    dev : hapsim.emulated.firefader_board.FireFaderDevice
        Made with ``clock="lockstep"``.
    """

    def __init__(self, dev) -> None:
        super().__init__(dev)
        self.dev = dev

    def write(self, data) -> int:
        """Feed one write to the board: one tick; its record waits to be read.

        Parameters
        ----------
        data : bytes-like
            What the host writes (no faults on this link).

        Returns
        -------
        int
            ``len(data)``.
        """
        self.out += self.dev.feed(bytes(data), writes=[b"", bytes(data)])
        return len(data)

    def idle(self, s: float) -> None:
        """The host silent for ``s`` [s] (the board's silence rule counts it).

        Parameters
        ----------
        s : float
            The silence [s].
        """
        self.dev.idle(s)
