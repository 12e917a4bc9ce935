"""What the independent board models share: a pseudo-terminal in raw mode, the handle's
physics integrated exactly on the wall clock, optional byte loss each way, a firmware run
as a coroutine against real time, and the truth log.

Written from the boards' published firmware only: nothing here imports ``hapsim`` (the
point of these models is that they do not share hapsim's emulators' assumptions,
``docs/testing.md``, "Independent board models"). Standard library and numpy.

The firmware of a board is a generator function ``firmware(board)``; it yields what it
waits for and reads and writes bytes through the board between its yields:

- ``("sleep", dt)``: busy for ``dt`` seconds of the board's time (a ``delayMicroseconds``,
  an ADC conversion, a byte's time on the wire that ``Serial.flush`` waits out);
- ``("rx", deadline)``: until a byte is available or the board's time reaches
  ``deadline`` (``math.inf``: no deadline);
- ``("at", t)``: until the board's time ``t`` (a timer interrupt).

The board's time is ``time.monotonic()`` from the start; a board process descheduled by
the host machine's load is late like any process, so the server asks for ``SCHED_FIFO``
(priority 20, above hapsim's loop at 10) where the system permits it and says in the truth
log what it got.
"""

from __future__ import annotations

import json
import math
import os
import select
import signal
import struct
import sys
import termios
import time
import tty
from collections import deque

import numpy as np

__all__ = ["Plant", "Board", "serve", "f32", "common_arguments"]

_F32 = struct.Struct("<f")


def f32(x: float) -> float:
    """``x`` rounded to IEEE-754 binary32 (what a ``float`` of the firmware holds): beyond
    its range, +-inf, as the board's FPU rounds a ``double`` there (a garbled set-up's
    resolution of 1e-40 made a count of 360 c / res overflow; Python's ``struct`` raises
    instead, and the model's process died mid-run)."""
    x = float(x)
    try:
        return _F32.unpack(_F32.pack(x))[0]
    except OverflowError:
        return math.copysign(math.inf, x)


class Plant:
    """A handle ``m x'' + b0 x' = u`` under a force ``u`` held between events, integrated
    exactly (closed form of the 2x2 system) from event to event on the board's clock.

    Parameters
    ----------
    mass : float
        Moving mass [kg] or inertia [kg m^2], > 0.
    friction : float
        Viscous friction b0 [N s/m] or [N m s/rad], >= 0.
    x0, v0 : float
        Initial position [m or rad] and velocity, at rest by default.
    stops : tuple of float, optional
        ``(low, high)`` end stops [m or rad]: an inelastic stop (the velocity zeroed there).
    reference : float
        The position the truth's excursion is measured from (the rest of the scene's
        spring in the board's physical frame).

    Attributes
    ----------
    t, x, v, u : float
        Time [s], position, velocity, force in effect [N or N m].
    longest_hold : float
        Longest time a non-zero force was in effect with no command taking effect [s].
    excursion : float
        Largest ``|x - reference|`` reached [m or rad] (checked at every event and at the
        velocity's zeros between events, so a peak between events is not missed).
    """

    def __init__(self, mass: float, friction: float, x0: float = 0.0, v0: float = 0.0,
                 stops=None, reference: float = 0.0) -> None:
        if not (mass > 0 and friction >= 0):
            raise ValueError("mass must be > 0 and friction >= 0")
        self.m, self.b0 = float(mass), float(friction)
        self.t, self.x, self.v, self.u = 0.0, float(x0), float(v0), 0.0
        self.stops = None if stops is None else (float(stops[0]), float(stops[1]))
        self.reference = float(reference)
        self.excursion = abs(self.x - self.reference)
        self.longest_hold = 0.0
        self.hold_since = 0.0
        self.stop_hits = 0
        self.log_t, self.log_x, self.log_v, self.log_u = [], [], [], []
        self._record()

    def _record(self) -> None:
        self.log_t.append(self.t)
        self.log_x.append(self.x)
        self.log_v.append(self.v)
        self.log_u.append(self.u)

    def _state_after(self, dt: float) -> tuple:
        """Position and velocity after ``dt`` [s] under the force held (closed form)."""
        m, b, u, x, v = self.m, self.b0, self.u, self.x, self.v
        if b == 0.0:
            a = u / m
            return x + v * dt + 0.5 * a * dt * dt, v + a * dt
        r = b / m
        e = math.exp(-r * dt)
        vinf = u / b
        return x + vinf * dt + (v - vinf) * (1.0 - e) / r, vinf + (v - vinf) * e

    def advance_to(self, t: float) -> None:
        """Integrate to the board's time ``t`` [s] under the force held (nothing when ``t``
        is not later); the excursion includes a turning point between events."""
        dt = float(t) - self.t
        if not dt > 0.0:
            return
        m, b, u = self.m, self.b0, self.u
        # a velocity zero inside the interval is a turning point: its position may be the
        # interval's extreme
        vinf = u / b if b > 0 else None
        tz = None
        if b > 0 and self.v != vinf and (self.v - vinf) * (0.0 - vinf) > 0 and \
                abs(0.0 - vinf) < abs(self.v - vinf):
            tz = -math.log((0.0 - vinf) / (self.v - vinf)) * m / b
        elif b == 0.0 and u != 0.0 and self.v * u < 0:
            tz = -self.v * m / u
        if tz is not None and 0.0 < tz < dt:
            xz, _ = self._state_after(tz)
            self.excursion = max(self.excursion, abs(xz - self.reference))
        x, v = self._state_after(dt)
        self.t, self.x, self.v = float(t), x, v
        if self.stops is not None and not (self.stops[0] < x < self.stops[1]):
            self.x = min(max(x, self.stops[0]), self.stops[1])
            self.v = 0.0
            self.stop_hits += 1
        self.excursion = max(self.excursion, abs(self.x - self.reference))

    def set_force(self, t: float, u: float, by_command: bool = True) -> None:
        """The force ``u`` takes effect at ``t`` [s]; ``by_command``: a command of the host
        set it (it ends a hold), else the firmware itself (a silence rule, a set-up)."""
        self.advance_to(t)
        if self.u != 0.0:
            self.longest_hold = max(self.longest_hold, self.t - self.hold_since)
        if by_command or u != self.u:
            self.hold_since = self.t
        self.u = float(u)
        self._record()

    def finish(self, t: float) -> None:
        """Integrate to ``t`` and close the hold in progress."""
        self.advance_to(t)
        if self.u != 0.0:
            self.longest_hold = max(self.longest_hold, self.t - self.hold_since)
        self._record()

    def trajectory(self) -> dict:
        """The events' ``t``, ``x``, ``v``, ``u`` as arrays."""
        return {"t": np.array(self.log_t), "x": np.array(self.log_x),
                "v": np.array(self.log_v), "u": np.array(self.log_u)}


class Board:
    """The device side of the wire: the pty's master end, the bytes each way (a UART's
    time per byte when ``baud`` is given, lost with a probability each way), the board's
    clock and its counters.

    Parameters
    ----------
    master : int
        The pty's master file descriptor (non-blocking).
    baud : int or None
        A UART's rate (10 bits a byte): host bytes become available to the firmware one
        byte time apart, the board's bytes reach the host one byte time apart; None: a
        USB device (bytes available as they come, written at once).
    drop_rx, drop_tx : float
        Probability that a host byte is lost on its way to the board, and a board byte on
        its way to the host.
    seed : int
        The loss's seed.

    Attributes
    ----------
    counters : dict
        ``bytes_in`` (host bytes that came), ``lost_in``, ``bytes_out``, ``lost_out``, and
        whatever the firmware adds.
    events : list of dict
        What the firmware notes (set-ups, resets, silences), with the board's time.
    """

    def __init__(self, master: int, baud=None, drop_rx: float = 0.0, drop_tx: float = 0.0,
                 seed: int = 0) -> None:
        self.master = master
        self.byte_s = None if baud is None else 10.0 / float(baud)
        self.rng = np.random.default_rng(seed)
        self.drop_rx, self.drop_tx = float(drop_rx), float(drop_tx)
        self.t0 = time.monotonic()
        self._rx: deque = deque()          # (available at [s], byte)
        self._rx_line_free = 0.0
        self._tx: deque = deque()          # (leaves at [s], byte)
        self._tx_line_free = 0.0
        self.counters = {"bytes_in": 0, "lost_in": 0, "bytes_out": 0, "lost_out": 0}
        self.events: list = []
        self.host_bytes_times: list = []   # when host writes came (first byte) [s]
        self.late_max = 0.0                # the server's largest lateness [s]
        self.late_over_1ms = 0             # resumptions more than 1 ms late
        #: The firmware's clock [s]: the time of what it does now. It follows the real
        #: clock; when this process was late to resume it (descheduled), it keeps the
        #: time the firmware meant (a board is never descheduled) and the physics is
        #: integrated to it, only the bytes to the host leave late (counted).
        self.fw = 0.0

    def real(self) -> float:
        """The real time since the board started [s]."""
        return time.monotonic() - self.t0

    def now(self) -> float:
        """The firmware's time [s] (:attr:`fw`)."""
        return self.fw

    # -- host -> board ---------------------------------------------------------------
    def _take_host_bytes(self, data: bytes, t: float) -> None:
        self.counters["bytes_in"] += len(data)
        self.host_bytes_times.append(t)
        for b in data:
            if self.drop_rx > 0 and self.rng.random() < self.drop_rx:
                self.counters["lost_in"] += 1
                continue
            if self.byte_s is None:
                self._rx.append((t, b))
            else:
                start = max(t, self._rx_line_free)
                self._rx_line_free = start + self.byte_s
                self._rx.append((self._rx_line_free, b))

    def available(self) -> int:
        """Bytes the firmware can read now (``Serial.available()``)."""
        t = self.now()
        n = 0
        for at, _ in self._rx:
            if at > t:
                break
            n += 1
        return n

    def read(self) -> int:
        """One byte, or -1 when none is available now (``Serial.read()``)."""
        if self._rx and self._rx[0][0] <= self.now():
            return self._rx.popleft()[1]
        return -1

    def next_rx_time(self) -> float:
        """When the next byte becomes available [s] (inf when none is on its way)."""
        return self._rx[0][0] if self._rx else math.inf

    # -- board -> host ---------------------------------------------------------------
    def write(self, data: bytes) -> float:
        """Queue the firmware's bytes (``Serial.write``); returns when the last leaves [s]
        (the board's time; at once for a USB device)."""
        t = self.now()
        for b in data:
            if self.byte_s is None:
                at = t
            else:
                start = max(t, self._tx_line_free)
                self._tx_line_free = start + self.byte_s
                at = self._tx_line_free
            self._tx.append((at, b))
        self._flush_tx()
        return self._tx_line_free if self.byte_s is not None else t

    def tx_done_at(self) -> float:
        """When the bytes queued so far have left [s]."""
        return self._tx[-1][0] if self._tx else self.now()

    def _flush_tx(self) -> None:
        t = self.real()
        out = bytearray()
        while self._tx and self._tx[0][0] <= t:
            b = self._tx.popleft()[1]
            self.counters["bytes_out"] += 1
            if self.drop_tx > 0 and self.rng.random() < self.drop_tx:
                self.counters["lost_out"] += 1
                continue
            out.append(b)
        if out:
            try:
                os.write(self.master, bytes(out))
            except BlockingIOError:
                self.counters["tx_overflow"] = self.counters.get("tx_overflow", 0) + len(out)
            except OSError:
                pass

    def note(self, kind: str, **what) -> None:
        """An event of the firmware's, stamped with the board's time."""
        self.events.append({"t": round(self.now(), 6), "kind": kind, **what})
        self.counters[kind] = self.counters.get(kind, 0) + 1


def _open_pty(link: str | None) -> tuple:
    """A pty in raw mode: ``(master, slave, path)``; the slave end is kept open here so
    the master reads no EIO between the host's openings; ``link`` a symlink to it."""
    master, slave = os.openpty()
    tty.setraw(slave, termios.TCSANOW)
    attrs = termios.tcgetattr(slave)
    attrs[3] &= ~termios.ECHO
    termios.tcsetattr(slave, termios.TCSANOW, attrs)
    os.set_blocking(master, False)
    path = os.ttyname(slave)
    if link:
        try:
            os.unlink(link)
        except FileNotFoundError:
            pass
        os.symlink(path, link)
    return master, slave, path


def _realtime(priority: int) -> str:
    """Ask for ``SCHED_FIFO`` at ``priority``; what was obtained."""
    if priority <= 0:
        return "normal"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return f"SCHED_FIFO {priority}"
    except (OSError, AttributeError) as exc:
        return f"normal ({type(exc).__name__}: {exc})"


def _poll(board: Board, master: int) -> None:
    """Take whatever the host has written (non-blocking)."""
    try:
        data = os.read(master, 4096)
    except OSError:
        return
    if data:
        board._take_host_bytes(data, board.real())


def seeded_phase(seed: int, salt: int) -> float:
    """A sensor grid's phase in [0, 1) [counts], seeded by the board's ``--seed`` and a
    board's own ``salt`` (two boards of one seed do not share it)."""
    import numpy as np
    return float(np.random.default_rng(seed + salt).random())


def serve(firmware, baud, plant: Plant, args, extra_truth) -> int:
    """Run ``firmware(board)`` on a fresh pty until SIGTERM/SIGINT, then write the truth.

    Parameters
    ----------
    firmware : callable
        ``firmware(board) -> generator`` (module notes).
    baud : float or None
        :class:`Board`'s ``baud`` (None: a USB link's); its loss and seed are ``args``'.
    plant : Plant
        The handle, its time measured from the board's start.
    args : argparse.Namespace
        :func:`common_arguments`' options.
    extra_truth : callable
        ``extra_truth() -> dict``: the firmware's own part of the truth log.

    Returns
    -------
    int
        Exit status (0).
    """
    master, slave, path = _open_pty(args.link)
    stop = {"flag": False}

    def _stop(signum, frame):
        stop["flag"] = True

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    sched = _realtime(args.rt_priority)
    board = Board(master, baud=baud, drop_rx=args.drop_rx, drop_tx=args.drop_tx,
                  seed=args.seed)
    board.plant = plant
    if args.ready:
        with open(args.ready, "w") as fh:
            fh.write(path + "\n")
    print(path, flush=True)
    gen = firmware(board)

    def _norm(w):
        return ("at", board.fw + float(w[1])) if w[0] == "sleep" else w

    wait = _norm(next(gen))
    spins, last_fw = 0, -1.0
    while not stop["flag"]:
        real = board.real()
        kind, target = wait[0], float(wait[1])
        if kind == "at":
            ready, fw = real >= target, target
        elif kind == "rx":
            nb = board.next_rx_time()
            if nb <= real and nb <= target:
                ready, fw = True, nb
            else:
                ready, fw = real >= target, target
            target = min(target, nb)
        else:
            raise ValueError(f"unknown wait {wait!r}")
        if ready:
            _poll(board, master)            # the host's bytes, even when never idle
            late = real - fw
            if late > board.late_max:
                board.late_max = late
            if late > 1e-3:
                board.late_over_1ms += 1
            board.fw = max(board.fw, fw)
            spins = spins + 1 if board.fw == last_fw else 0
            last_fw = board.fw
            if spins > 100000:
                raise RuntimeError(f"the firmware model spins at t = {board.fw} s "
                                   f"without its time advancing (last wait {wait!r})")
            board._flush_tx()
            try:
                wait = _norm(gen.send(None))
            except StopIteration:
                break
            continue
        # sleep in select until the target, a host byte or a board byte's departure
        nxt = target
        if board._tx:
            nxt = min(nxt, board._tx[0][0])
        timeout = 0.5 if not math.isfinite(nxt) else min(0.5, max(0.0, nxt - real))
        try:
            r, _, _ = select.select([master], [], [], timeout)
        except InterruptedError:
            continue
        if r:
            _poll(board, master)
        board._flush_tx()
    t_end = max(board.real(), board.fw)
    plant.finish(t_end)
    truth = {
        "board": args.board_name, "pty": path, "scheduling": sched, "seed": args.seed,
        "drop_rx": board.drop_rx, "drop_tx": board.drop_tx,
        "duration_s": t_end, "counters": board.counters,
        "server_late_max_s": board.late_max, "server_late_over_1ms": board.late_over_1ms,
        "longest_hold_s": plant.longest_hold,
        "excursion": plant.excursion, "reference": plant.reference,
        "stop_hits": plant.stop_hits, "final": {"x": plant.x, "v": plant.v, "u": plant.u},
        "events": board.events[:2000], "events_total": len(board.events),
        # when the host's writes came, the longest gap between two (the host's own
        # silences, beside the force the firmware held over them)
        "host_gap_max_s": (max((b - a for a, b in zip(board.host_bytes_times,
                                                       board.host_bytes_times[1:])),
                               default=0.0)),
    }
    if getattr(args, "write_times", False):
        truth["host_write_times"] = board.host_bytes_times[:50000]
    truth.update(extra_truth())
    if args.truth:
        tmp = args.truth + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(truth, fh, indent=1, default=float)
        os.replace(tmp, args.truth)
        np.savez_compressed(os.path.splitext(args.truth)[0] + "_trajectory.npz",
                            **plant.trajectory())
    os.close(master)
    os.close(slave)
    if args.link:
        try:
            os.unlink(args.link)
        except OSError:
            pass
    return 0


def common_arguments(parser) -> None:
    """The options every board takes: its link, loss, seed, truth log and priority."""
    parser.add_argument("--link", help="make this path a symlink to the pty's slave")
    parser.add_argument("--ready", help="write the pty's path to this file once serving")
    parser.add_argument("--truth", help="write the truth log (JSON) here at SIGTERM")
    parser.add_argument("--drop-rx", type=float, default=0.0,
                        help="probability a host byte is lost on its way to the board")
    parser.add_argument("--drop-tx", type=float, default=0.0,
                        help="probability a board byte is lost on its way to the host")
    parser.add_argument("--seed", type=int, default=0, help="seed of the loss (and phases)")
    parser.add_argument("--write-times", action="store_true",
                        help="keep every host write's arrival time in the truth log")
    parser.add_argument("--rt-priority", type=int, default=20,
                        help="SCHED_FIFO priority of the board process (0: normal)")


if __name__ == "__main__":          # pragma: no cover
    sys.exit("a library of tools/independent_boards; run one of the boards")
