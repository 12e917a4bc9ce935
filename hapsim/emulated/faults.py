"""Seeded fault injection for the mock device: wire faults and device-state faults.

A :class:`FaultPlan` says which faults to inject, either at random (a probability per
frame or per tick) or at scheduled device ticks; :class:`FaultyDevice` applies it around a
:class:`~hapsim.emulated.mock.MockDevice`, I/O-free: bytes in, timed bytes out. The mock's
serving loop (:func:`hapsim.emulated.serve.serve_fd`, a real pty) and the in-process
virtual-clock transport (:class:`hapsim.emulated.links.SimTransport`) both use it, so the
host always sees real wire faults (torn, corrupted, repeated, reordered, delayed frames)
through its own stream decoder.

SPEC syntax (``hapsim mock --faults SPEC``, ``hapsim run --faults SPEC``)
-------------------------------------------------------------------------
A comma-separated list of items::

    NAME=RATE[:DURATION]     at random: probability RATE in [0, 1] per frame (wire faults)
                             or per device tick (device faults)
    NAME@TICK[:DURATION]     once, at device tick TICK (ticks counted since the mock
                             started, across CONFIGs and resets)
    nohello                  the device never answers HELLO_REQUEST (nor says HELLO)

DURATION is a number with a unit ``us``, ``ms`` or ``s`` (``5ms``, ``0.3s``).

Wire faults (device -> host bytes):

``drop``     the frame is not sent.
``corrupt``  one byte of the frame is XORed with a random non-zero byte (CRC catches it; a
             byte becoming ``0x00`` splits it into two bad frames).
``garbage``  a burst of 1-64 random bytes is sent before the frame.
``dup``      the frame is sent twice.
``reorder``  the frame is held back and sent after the next one.
``spike``    every frame is held for DURATION (default 5 ms), then sent in one burst.

Host -> device wire faults: the same six names prefixed ``rx.`` (``rx.drop``,
``rx.corrupt``, ``rx.garbage``, ``rx.dup``, ``rx.reorder``, ``rx.spike``) act on each
frame the device *receives* (FORCE, CONFIG, PING, STOP, HELLO_REQUEST), after the port and
before the device's decoder: ``rx.drop=0.01,rx.corrupt=0.005``. They draw from their own
generator (seeded from the same seed), so adding them does not change which device -> host
frames are faulted. ``rx.NAME@TICK`` faults the first host frame received from device tick
TICK on.

Device faults:

``stall``    the device's link stalls for DURATION (default 200 ms): no STATE goes out and
             nothing is read (the host's bytes wait in the port); its control loop keeps
             ticking, so its watchdog zeroes the force.
``reset``    the device resets: disarmed, zero force, its receiver buffer cleared; it sends
             ``0x00`` then HELLO and waits for CONFIG.
``vanish``   the port disappears for DURATION (default 300 ms): on a pty the link is
             removed and the master closed (the host's reads fail, and its re-opens find
             no port, as a USB device's path is gone while it is unplugged), and a new pty
             is linked at the same path when it comes back (then ``0x00`` + HELLO); the
             device keeps ticking (watchdog).

Example: ``drop=0.01,corrupt=0.005,garbage=0.001,dup=0.002,reorder=0.002,spike=0.001:5ms,
stall@500:200ms,reset@800,vanish@1200:300ms,rx.drop=0.01,rx.corrupt=0.005`` with
``--fault-seed 1``.
"""

from __future__ import annotations

import math
import random
import re
from dataclasses import dataclass, field

import firmware_protocol as fp
from hapsim.errors import ConfigError

__all__ = ["FaultPlan", "FaultyDevice", "parse_faults", "mock_fault_plan", "reopener", "WIRE_FAULTS", "RX_WIRE_FAULTS",
           "DEVICE_FAULTS", "FAULT_NAMES", "DEFAULT_DURATIONS", "LOCKSTEP_FAULTS"]

#: Faults applied to each device -> host frame.
WIRE_FAULTS = ("drop", "corrupt", "garbage", "dup", "reorder", "spike")
#: Faults applied to each host -> device frame (what the device receives).
RX_WIRE_FAULTS = tuple("rx." + n for n in WIRE_FAULTS)
#: Faults of the device's state machine (per tick).
DEVICE_FAULTS = ("stall", "reset", "vanish")
#: Every fault name the SPEC accepts.
FAULT_NAMES = WIRE_FAULTS + RX_WIRE_FAULTS + DEVICE_FAULTS + ("nohello",)
#: A lockstep mock's faults, at a rate (:meth:`FaultPlan.lockstep_refusal`).
LOCKSTEP_FAULTS = ("dup", "spike", "rx.dup", "rx.spike")
#: Default DURATION [s] of the faults that have one.
DEFAULT_DURATIONS = {"spike": 0.005, "rx.spike": 0.005, "stall": 0.2, "vanish": 0.3}

_ITEM = re.compile(r"^\s*([a-z]+(?:\.[a-z]+)?)\s*(?:([=@])\s*([^:\s]+)\s*(?::\s*(\S+))?)?\s*$")
_DUR = re.compile(r"^([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)(us|ms|s)$")
_UNIT = {"us": 1e-6, "ms": 1e-3, "s": 1.0}


def _duration(text: str, item: str) -> float:
    m = _DUR.match(text)
    if not m:
        raise ConfigError(f"bad duration {text!r} in {item!r}: a number with a unit us, ms "
                          f"or s (e.g. 5ms)", key="--faults")
    return float(m.group(1)) * _UNIT[m.group(2)]


@dataclass
class FaultPlan:
    """Which faults to inject, and the seeded generator that decides when.

    Parameters
    ----------
    rates : dict of str to float
        Probability per frame (wire faults) or per tick (device faults), in [0, 1].
    durations : dict of str to float
        DURATION of the random ``spike``, ``stall`` and ``vanish`` [s].
    schedule : list of (int, str, float)
        ``(tick, name, duration [s])`` events, each fired once at that device tick.
    nohello : bool
        The device never answers HELLO_REQUEST.
    seed : int
        Seed of the generator (:class:`random.Random`: cheap per-frame draws).
    spec : str
        The SPEC text the plan came from (for reports).

    Attributes
    ----------
    injected : dict of str to int
        How many of each fault were injected so far.
    """

    rates: dict = field(default_factory=dict)
    durations: dict = field(default_factory=lambda: dict(DEFAULT_DURATIONS))
    schedule: list = field(default_factory=list)
    nohello: bool = False
    seed: int = 0
    spec: str = ""
    injected: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.rng = random.Random(self.seed)
        # host -> device faults draw from their own generator: adding them leaves the
        # device -> host faults of a given seed unchanged
        self.rx_rng = random.Random(f"rx:{self.seed}")
        self.injected = {name: 0 for name in FAULT_NAMES}
        self._wire = self._wire_active(WIRE_FAULTS)
        self._rx_wire = self._wire_active(RX_WIRE_FAULTS)
        self._dev_rates = [(n, self.rates[n]) for n in DEVICE_FAULTS if self.rates.get(n, 0) > 0]
        self._by_tick: dict[int, list] = {}
        for tick, name, dur in self.schedule:
            self._by_tick.setdefault(int(tick), []).append((name, dur))
        self._armed_wire: list = []      # scheduled wire faults waiting for the next frame
        self._armed_rx: list = []        # scheduled rx. faults waiting for the next host frame

    def _wire_active(self, names: tuple) -> bool:
        return any(self.rates.get(n, 0.0) > 0 for n in names) or any(
            name in names for _, name, _ in self.schedule)

    @property
    def has_rx(self) -> bool:
        """True when the plan faults host -> device frames (``rx.`` names)."""
        return self._rx_wire

    @property
    def empty(self) -> bool:
        """True when the plan injects nothing."""
        return not (self.rates and any(v > 0 for v in self.rates.values())) \
            and not self.schedule and not self.nohello

    @property
    def has_vanish(self) -> bool:
        """True when the plan can make the port vanish."""
        return self.rates.get("vanish", 0) > 0 or any(n == "vanish" for _, n, _ in self.schedule)

    def lockstep_refusal(self) -> str | None:
        """Why a lockstep mock, which ticks on the host's FORCE, cannot take this plan
        (a str naming the faults, why, and what takes them), or None
        (:data:`LOCKSTEP_FAULTS`, ``nohello``). A frame lost there stops both sides
        until the device is called lost (10 s); a fault at or per tick never fires
        (``reset@100`` ran as if not asked, ``injected: {}``).

        Returns
        -------
        str or None"""
        names = sorted({n for n, v in self.rates.items() if v > 0
                        and n not in LOCKSTEP_FAULTS}
                       | {f"{n}@{t}" for t, n, _ in self.schedule})
        if not names:
            return None
        return (f"{', '.join(names)}: not with a lockstep mock, which ticks on the host's "
                f"FORCE (a frame lost on the wire stops both sides until the device is "
                f"called lost; a fault at or per tick never fires); with --lockstep: "
                f"{', '.join(n + '=RATE' for n in LOCKSTEP_FAULTS)}, nohello; the others "
                f"on the mock's own clock (without --lockstep)")

    def to_dict(self) -> dict:
        """JSON-ready description of the plan.

        Returns
        -------
        dict
            ``spec`` (str), ``seed`` (int), ``injected`` (fault name to count, only the
            faults injected at least once).
        """
        return {"spec": self.spec, "seed": self.seed,
                "injected": {k: v for k, v in self.injected.items() if v}}

    # ------------------------------------------------------------------ decisions
    def device_events(self, tick: int) -> list:
        """Device faults firing at a device tick (scheduled, then drawn at random).

        Scheduled wire faults (``drop@TICK``, ``rx.drop@TICK``, ...) are armed here for the
        next frame in their direction instead of being returned. Counts them in
        :attr:`injected`.

        Parameters
        ----------
        tick : int
            Device tick, counted since the mock started (across CONFIGs and resets), >= 0.

        Returns
        -------
        list of (str, float)
            ``(name, duration [s])`` of the device faults (``stall``, ``reset``, ``vanish``)
            to apply now, scheduled ones first; the duration is 0.0 for ``reset``.
        """
        out = list(self._by_tick.get(tick, ()))
        if self._dev_rates:
            rnd = self.rng.random
            for name, p in self._dev_rates:
                if rnd() < p:
                    out.append((name, self.durations.get(name, 0.0)))
        for name, dur in list(out):
            if name in WIRE_FAULTS:
                out.remove((name, dur))
                self._armed_wire.append((name, dur))
            elif name in RX_WIRE_FAULTS:
                out.remove((name, dur))
                self._armed_rx.append((name[3:], dur))
        for name, _ in out:
            self.injected[name] += 1
        return out

    def wire(self, frame: bytes) -> tuple[list, float]:
        """Apply the wire faults to one device -> host frame.

        Parameters
        ----------
        frame : bytes
            One encoded frame (with its ``0x00`` delimiter).

        Returns
        -------
        frames : list of bytes
            What to send instead, in order (possibly empty); a first element
            ``"REORDER"`` (a str marker) means: hold the frames that follow and send them
            after the next frame (:class:`FaultyDevice` does).
        hold : float
            Hold every frame from now on for this long [s] (``spike``), else 0.0.
        """
        if not self._wire:
            return [frame], 0.0
        return self._apply(frame, "", self._armed_wire, self.rng)

    def wire_rx(self, frame: bytes) -> tuple[list, float]:
        """Apply the ``rx.`` wire faults to one host -> device frame.

        Parameters
        ----------
        frame : bytes
            One frame as the host wrote it (with its ``0x00`` delimiter).

        Returns
        -------
        frames : list of bytes
            What the device's receiver gets instead, in order (as :meth:`wire`, with the
            same ``"REORDER"`` marker).
        hold : float
            Hold every received frame from now on for this long [s] (``rx.spike``).
        """
        if not self._rx_wire:
            return [frame], 0.0
        return self._apply(frame, "rx.", self._armed_rx, self.rx_rng)

    def _apply(self, frame: bytes, prefix: str, armed: list, rng) -> tuple[list, float]:
        """The six wire faults on one frame; ``prefix`` selects the rates and counters."""
        rates = self.rates
        inj = self.injected
        rnd = rng.random
        fire = {name for name, _ in armed}
        spike_dur = next((d for n, d in armed if n == "spike"), None)
        armed.clear()
        hold = 0.0
        if "spike" in fire or rnd() < rates.get(prefix + "spike", 0.0):
            hold = spike_dur if spike_dur else self.durations.get(prefix + "spike", 0.005)
            inj[prefix + "spike"] += 1
        if "drop" in fire or rnd() < rates.get(prefix + "drop", 0.0):
            inj[prefix + "drop"] += 1
            return [], hold
        out = [frame]
        if "corrupt" in fire or rnd() < rates.get(prefix + "corrupt", 0.0):
            inj[prefix + "corrupt"] += 1
            b = bytearray(frame)
            i = rng.randrange(len(b) - 1)
            b[i] ^= rng.randrange(1, 256)
            out = [bytes(b)]
        if "garbage" in fire or rnd() < rates.get(prefix + "garbage", 0.0):
            inj[prefix + "garbage"] += 1
            n = rng.randrange(1, 65)
            out.insert(0, bytes(rng.getrandbits(8) for _ in range(n)))
        if "dup" in fire or rnd() < rates.get(prefix + "dup", 0.0):
            inj[prefix + "dup"] += 1
            out.append(out[-1])
        if "reorder" in fire or rnd() < rates.get(prefix + "reorder", 0.0):
            inj[prefix + "reorder"] += 1
            return ["REORDER"] + out, hold       # marker: hold these behind the next frame
        return out, hold


def parse_faults(spec: str | None, seed: int = 0) -> FaultPlan:
    """Parse a fault SPEC (see the module docstring).

    Parameters
    ----------
    spec : str or None
        The SPEC; None or empty: no faults.
    seed : int
        Generator seed.

    Returns
    -------
    FaultPlan

    Raises
    ------
    ConfigError
        Unknown fault name (the message lists the valid ones), a rate outside [0, 1], a bad
        tick or duration, or a form the fault does not take (key ``--faults``).
    """
    plan_rates: dict = {}
    durations = dict(DEFAULT_DURATIONS)
    schedule: list = []
    nohello = False
    text = (spec or "").strip()
    for item in filter(None, (s.strip() for s in text.split(","))):
        m = _ITEM.match(item)
        if not m:
            raise ConfigError(f"cannot parse {item!r}: expected NAME=RATE[:DURATION], "
                              f"NAME@TICK[:DURATION] or nohello", key="--faults")
        name, op, value, dur = m.groups()
        if name not in FAULT_NAMES:
            raise ConfigError(f"unknown fault {name!r}; valid faults: {', '.join(FAULT_NAMES)}",
                              key="--faults")
        if name == "nohello":
            if op:
                raise ConfigError("nohello takes no rate or tick", key="--faults")
            nohello = True
            continue
        if not op:
            raise ConfigError(f"{name} needs =RATE or @TICK (e.g. {name}=0.01 or {name}@500)",
                              key="--faults")
        d = None
        if dur is not None:
            if name not in DEFAULT_DURATIONS:
                raise ConfigError(f"{name} takes no duration (only "
                                  f"{', '.join(DEFAULT_DURATIONS)} do)", key="--faults")
            d = _duration(dur, item)
        if op == "=":
            try:
                p = float(value)
            except ValueError:
                p = math.nan
            if not 0.0 <= p <= 1.0:
                raise ConfigError(f"rate of {name} must be a probability in [0, 1], got "
                                  f"{value!r}", key="--faults")
            plan_rates[name] = p
            if d is not None:
                durations[name] = d
        else:
            if not value.isdigit():
                raise ConfigError(f"tick of {name} must be a whole number >= 0, got {value!r}",
                                  key="--faults")
            schedule.append((int(value), name, d if d is not None
                             else DEFAULT_DURATIONS.get(name, 0.0)))
    return FaultPlan(rates=plan_rates, durations=durations, schedule=schedule,
                     nohello=nohello, seed=int(seed), spec=text)


def mock_fault_plan(spec: str | None, seed: int | None, link: str | None,
                    lockstep: bool = False):
    """A mock's fault plan from ``--faults``, ``--fault-seed``, ``--link`` and
    ``--lockstep`` (the 1-D, 2-D and 3-D mocks alike).

    Parameters
    ----------
    spec : str or None
        The SPEC (None or empty: no faults).
    seed : int or None
        ``--fault-seed`` (None: 0).
    link : str or None
        ``--link PATH``, which a ``vanish`` fault needs.
    lockstep : bool
        A lockstep mock (:meth:`FaultPlan.lockstep_refusal`).

    Returns
    -------
    FaultPlan or None
        None without a SPEC.

    Raises
    ------
    ConfigError
        A bad SPEC (:func:`parse_faults`); a fault a lockstep mock cannot take; a
        ``vanish`` fault without ``--link`` (exit 2).
    """
    if not spec:
        return None
    plan = parse_faults(spec, int(seed or 0))
    why = plan.lockstep_refusal() if lockstep else None
    if why:
        raise ConfigError(why, key="--faults")
    if plan.has_vanish and not link:
        raise ConfigError("a vanish fault closes the pty and opens a new one: give --link "
                          "PATH and open PATH from the host", key="--link")
    return plan


def reopener(link: str | None, new_pty, announce: bool):
    """The ``reopen() -> fd`` a ``vanish`` fault calls when the port comes back
    (:func:`hapsim.emulated.serve.serve_fd`): a new pty, ``link`` pointed at it; and its
    ``gone()``, which removes ``link`` when the port vanishes.

    Parameters
    ----------
    link : str or None
        ``--link PATH``.
    new_pty : callable
        ``new_pty(link, announce) -> (master, slave)`` (``hapsim mock``'s pty opener).
    announce : bool
        Print ``PORT PATH`` again.

    Returns
    -------
    callable
        ``reopen() -> int``: the new pty's master fd. Its slave is closed at once: the
        raw settings stay with the pty, and the mock ignores EIO until the host opens it.
        Its attribute ``gone() -> None`` removes ``link`` (no error when it is absent);
        :func:`~hapsim.emulated.serve.serve_fd` calls it before it closes the vanished
        master.

    Notes
    -----
    Why the link goes while the port is away: a vanished pty's number (``/dev/pts/N``) is
    free once the host closes its slave, and the kernel gives the lowest free number to
    the next pty opened on the machine. A link left pointing at it would let the host's
    re-open reach another program's pty (seen in a loaded test suite: a run that lost
    its device at device tick 300 went on for 877 host ticks on another test's mock,
    counted as a recovery). Without the link the re-open fails until the new pty is
    linked, as a USB device's ``/dev/serial/by-id`` path is gone while it is unplugged.
    """
    import os

    def reopen() -> int:
        master, slave = new_pty(link, announce=announce)
        os.close(slave)
        return master

    def gone() -> None:
        if link:
            try:
                os.unlink(link)
            except FileNotFoundError:
                pass

    reopen.gone = gone
    return reopen


class _Lane:
    """One direction of the faulty wire: frames queued with their release time [us].

    A delay spike holds every later frame until ``hold_until`` (frames stay in order); a
    reorder holds its frames back (``held``) and releases them behind the next frames that
    pass. Shared by the device -> host and the host -> device (``rx.``) directions.
    """

    __slots__ = ("q", "held", "hold_until")

    def __init__(self) -> None:
        self.q: list = []           # (release_us, bytes), release non-decreasing
        self.held: list = []        # frames held back by a reorder
        self.hold_until = 0

    def push(self, frames: list, hold: float, now_us: int) -> None:
        """Queue what :meth:`FaultPlan.wire` / ``wire_rx`` made of one frame.

        Parameters
        ----------
        frames : list
            Frames to send (bytes), or ``["REORDER", *frames]`` to hold them back.
        hold : float
            Delay spike starting now [s] (0: none).
        now_us : int
            Device clock [us].
        """
        if hold > 0:
            self.hold_until = max(self.hold_until, now_us + int(hold * 1e6))
        rel = max(now_us, self.hold_until)
        if frames and frames[0] == "REORDER":
            self.held.extend(frames[1:])
            return
        for f in frames:
            self.q.append((rel, f))
        if self.held:
            for f in self.held:
                self.q.append((rel, f))
            self.held.clear()

    def drop(self) -> None:
        """Drop every queued and held frame (the port went away); a spike's hold stays."""
        self.q.clear()
        self.held.clear()

    def clear(self) -> None:
        """Drop every frame and end any hold (the receiver was reset)."""
        self.drop()
        self.hold_until = 0


class FaultyDevice:
    """A :class:`~hapsim.emulated.mock.MockDevice` behind a fault plan, I/O-free.

    Parameters
    ----------
    mock : MockDevice
        A real-time mock (``lockstep=False``) or a lockstep one.
    plan : FaultPlan, optional
        Faults to inject; none when omitted.

    Attributes
    ----------
    tick_count : int
        Device ticks since start (the clock of scheduled faults).
    stalled_until_us, vanished_until_us : int
        Device time until which the link is stalled / gone [us] (0: not).
    events : list of dict
        Device faults fired: ``{"tick", "name", "t_us", "duration_s"}``.
    decoder : firmware_protocol.StreamDecoder
        The device's receiver.

    Notes
    -----
    Use: :meth:`connect` when the port opens, :meth:`feed` with the host's bytes,
    :meth:`tick` at each device tick (real-time), :meth:`poll` between ticks, :meth:`pop_due`
    for the bytes to write by now (in order), :meth:`next_release_us` for the next held
    frame (either direction). With ``rx.`` faults the host's bytes are cut into frames at
    their ``0x00`` delimiters, faulted one frame at a time and then handed to
    :attr:`decoder` (at once, or when a held frame's time comes).
    """

    def __init__(self, mock, plan: FaultPlan | None = None) -> None:
        self.mock = mock
        self.plan = plan or FaultPlan()
        self.decoder = fp.StreamDecoder()
        self.tick_count = 0
        self.stalled_until_us = 0
        self.vanished_until_us = 0
        self.events: list = []
        self._tx = _Lane()              # device -> host
        self._out = self._tx.q          # (release_us, bytes), release non-decreasing
        self.vanish_pending = False     # serve_fd: close the port now
        self.reconnect_pending = False  # the port came back: say HELLO
        self._rx_on = self.plan.has_rx
        self._rx_buf = b""              # host bytes not yet ending a frame (rx. faults)
        self._rx = _Lane()              # host -> device (rx. faults)
        self._in = self._rx.q           # (release_us, bytes) for the receiver

    # ------------------------------------------------------------------ output
    def _send(self, msg, now_us: int) -> None:
        self._tx.push(*self.plan.wire(fp.encode(msg)), now_us)

    def connect(self, now_us: int) -> None:
        """The port (re)opened: queue ``0x00`` then HELLO (unless ``nohello``).

        Parameters
        ----------
        now_us : int
            Device clock [us]; the bytes are due at once (HELLO through the wire faults).
        """
        self._out.append((now_us, b"\x00"))
        if not self.plan.nohello:
            self._send(self.mock.hello(), now_us)

    def pop_due(self, now_us: int) -> bytes:
        """Take the bytes to write to the host by now.

        Parameters
        ----------
        now_us : int
            Device clock [us].

        Returns
        -------
        bytes
            The queued frames whose release time is ``<= now_us``, in order, joined; empty
            while the link is stalled or the port gone (they wait).
        """
        out = self._out
        if not out or out[0][0] > now_us or self.link_down(now_us):
            return b""
        if len(out) == 1:               # the usual case: one frame (a tick's STATE) due
            data = out[0][1]
            out.clear()
            return data
        i = 1
        while i < len(out) and out[i][0] <= now_us:
            i += 1
        data = b"".join(f for _, f in out[:i])
        del out[:i]
        return data

    def next_release_us(self) -> int | None:
        """When the next queued frame is due, in either direction.

        Returns
        -------
        int or None
            Release time [us] of the first frame queued for the host or for the device's
            receiver, whichever is earlier; None when nothing is queued.
        """
        out = self._out[0][0] if self._out else None
        if self._in:
            rx = self._in[0][0]
            return rx if out is None or rx < out else out
        return out

    def link_down(self, now_us: int) -> bool:
        """Whether nothing passes the link now.

        Parameters
        ----------
        now_us : int
            Device clock [us].

        Returns
        -------
        bool
            True while the link is stalled or the port is gone.
        """
        return now_us < self.stalled_until_us or now_us < self.vanished_until_us

    def vanished(self, now_us: int) -> bool:
        """Whether the port is gone now.

        Parameters
        ----------
        now_us : int
            Device clock [us].

        Returns
        -------
        bool
            True before ``vanished_until_us`` (a ``vanish`` fault's DURATION).
        """
        return now_us < self.vanished_until_us

    # ------------------------------------------------------------------ input
    def feed(self, data: bytes, now_us: int) -> list:
        """Bytes from the host (call only while the link is up); returns the messages seen.

        Parameters
        ----------
        data : bytes
            Bytes the host wrote (any split: whole frames, parts, several frames).
        now_us : int
            Device clock [us].

        Returns
        -------
        list
            Messages the device's receiver decoded and acted on by now (with ``rx.``
            faults, frames held back by ``rx.spike`` / ``rx.reorder`` are acted on later,
            by :meth:`poll` or :meth:`tick`).
        """
        if not self._rx_on:
            return self._receive(data, now_us)
        buf = self._rx_buf + data
        start = 0
        plan = self.plan
        while True:
            end = buf.find(b"\x00", start)
            if end < 0:
                break
            self._rx.push(*plan.wire_rx(buf[start:end + 1]), now_us)
            start = end + 1
        self._rx_buf = buf[start:]
        if len(self._rx_buf) > 2 * fp.MAX_FRAME:       # no delimiter: the receiver's problem
            self._in.append((max(now_us, self._rx.hold_until), self._rx_buf))
            self._rx_buf = b""
        return self._deliver(now_us)

    def _deliver(self, now_us: int) -> list:
        """Hand the received frames whose time has come to the device's receiver."""
        inq = self._in
        if not inq or inq[0][0] > now_us or self.link_down(now_us):
            return []
        i = 0
        while i < len(inq) and inq[i][0] <= now_us:
            i += 1
        data = b"".join(f for _, f in inq[:i])
        del inq[:i]
        return self._receive(data, now_us)

    def _receive(self, data: bytes, now_us: int) -> list:
        """The device's receiver: decode (bad frames dropped and counted), then act."""
        msgs = self.decoder.feed(data)
        mock = self.mock
        for msg in msgs:
            if self.plan.nohello and isinstance(msg, fp.HelloRequest):
                mock.stats.last_host_message = "HelloRequest"
                continue
            for reply in mock.handle(msg, now_us):
                self._send(reply, now_us)
        return msgs

    def _clear_rx(self) -> None:
        self._rx_buf = b""
        self._rx.clear()

    # ------------------------------------------------------------------ ticks
    def tick(self, now_us: int) -> None:
        """One device tick: fire scheduled/random device faults, then tick the mock.

        The STATE of the tick is queued for the host (through the wire faults) unless the
        link is down; a ``reset`` or ``vanish`` takes effect before the mock ticks.

        Parameters
        ----------
        now_us : int
            Device clock at the tick [us].
        """
        n = self.tick_count
        self.tick_count = n + 1
        if not self.plan.empty:
            for name, dur in self.plan.device_events(n):
                self.events.append({"tick": n, "name": name, "t_us": now_us,
                                    "duration_s": dur})
                if name == "stall":
                    self.stalled_until_us = now_us + int(dur * 1e6)
                elif name == "vanish":
                    self.vanished_until_us = now_us + int(dur * 1e6)
                    self.vanish_pending = True
                    self.reconnect_pending = True
                    self._tx.drop()
                    self._clear_rx()
                elif name == "reset":
                    self.reset(now_us)
        self.poll(now_us)
        st = self.mock.tick(now_us)
        if st is not None and not self.link_down(now_us):
            for msg in self.mock.frames(st):       # VELOCITY (when enabled), then STATE
                self._send(msg, now_us)

    def poll(self, now_us: int) -> list:
        """Housekeeping between ticks: when a vanished port is back, say ``0x00`` + HELLO;
        hand the host frames held by ``rx.`` faults whose time has come to the receiver.

        Parameters
        ----------
        now_us : int
            Device clock [us].

        Returns
        -------
        list
            Messages the receiver decoded now (empty without ``rx.`` faults).
        """
        if self.reconnect_pending and not self.vanished(now_us) and not self.vanish_pending:
            self.reconnect_pending = False
            self.decoder.reset()
            self._clear_rx()
            self.connect(now_us)
        if self._in:
            return self._deliver(now_us)
        return []

    def reset(self, now_us: int) -> None:
        """Device reset: zero force, disarmed, unconfigured, receiver and queues cleared,
        then ``0x00`` + HELLO (as a device that restarts says HELLO).

        Parameters
        ----------
        now_us : int
            Device clock [us].
        """
        mock = self.mock
        mock.stop()
        mock.configured = False
        mock.physics = None
        mock.sensors = 0                 # a reset device sends no VELOCITY until asked
        self.decoder.reset()
        self._clear_rx()
        self._tx.clear()
        self.connect(now_us)

    @property
    def ticking(self) -> bool:
        """True when the device produces ticks (armed and configured)."""
        return self.mock.armed and self.mock.physics is not None
