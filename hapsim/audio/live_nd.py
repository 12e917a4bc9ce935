"""Live sound of a 2-D or 3-D scene: its listening points computed ahead of a sound
server's callback, the scene felt through its device's model and changed while it plays.

An n-D scene's sound (``audio: listen:``, :class:`hapsim.scene.ListenND`) is its own
rate's samples (an n-D scene is not multi-rate), the same ones
:func:`hapsim.audio.offline.render_nd` writes to a WAV. Here a producer (the calling
thread) advances the n-D engine one chunk at a time into a preallocated buffer
(:meth:`hapsim.engine_nd.EngineND.listen`, compiled, no allocation) and appends it to a
:class:`hapsim.audio.sources.FrameRing`, whose frames the sound server's callback copies
out (:class:`hapsim.audio.live.JackOutput`'s native callback: no GIL, nothing allocated per
block; PortAudio's Python callback where no JACK server runs). The producer keeps at most
``ahead`` frames written beyond what the callback has read, so the sound leaves on the
sound card's clock with a latency of ``ahead`` frames; when it falls behind, the callback
plays silence, counted (``underruns``), and the sound resumes where it stopped: the frames
played are the offline rendering's, in order, to float32 rounding (the ring's type), with
the counted silences between.

A scene with a port and a device is played closed on the device's model at the scene's
rate (the loop :mod:`hapsim.lockstep` runs and :mod:`hapsim.analysis.scene_nd_check`
analyses: the exact zero-order hold of the Cartesian mass and friction, the delay line),
the hand's force (the scene's ``excitation``, along its direction, again every ``every``
samples) acting on the device's mass; live changes (:class:`hapsim.audio.control_nd.
ControllerND`) are ramped sample by sample in the same compiled call
(:func:`hapsim.kernels.play.play_chunk`: one argument, nothing allocated per chunk).
"""

from __future__ import annotations

import time

import numpy as np

from hapsim.audio.offline import listen_plan
from hapsim.audio.sources import FrameRing
from hapsim.errors import ConfigError
from hapsim.kernels import play as kernel

__all__ = ["LiveND", "channel_names"]

_AXES = "xyz"


def channel_names(scene) -> tuple:
    """Channel names of an n-D scene's listening points: ``MASS.AXIS.QUANTITY``.

    Parameters
    ----------
    scene : hapsim.scene.SceneND

    Returns
    -------
    tuple of str
        One per listening point, in the scene's order (empty without ``audio``).
    """
    return tuple(f"{p.mass}.{_AXES[p.axis]}.{p.quantity}" for p in (scene.audio or ()))


class LiveND:
    """An n-D scene's listening points produced ahead of a sound server's callback, its
    loop closed on its device's model, its live changes ramped.

    Parameters
    ----------
    engine : hapsim.engine_nd.EngineND
        Engine of a scene with an ``audio`` section, at its initial state (or wherever the
        sound should start).
    chunk : int
        Frames the producer computes at a time (>= 1).
    ring : int
        Frames the ring holds (>= 4 ``chunk``).
    ahead : int, optional
        Frames written beyond those read at most (default ``ring // 4``; at most
        ``ring // 2``, beyond which the ring's reader would skip:
        :func:`hapsim.kernels.audio.ring_read`): the sound's latency [frames].
    hand : array_like, shape (H,), optional
        The hand's force on the device's mass [N], one value held per sample
        (:func:`hapsim.device_model.hand_force_samples`); needs a port and a device.
    direction : array_like, shape (dim,), optional
        Its direction (unit vector; required with ``hand``).
    every : int
        Repeat the hand's force every ``every`` samples (0: once).
    control : hapsim.audio.control_nd.ControllerND, optional
        Its accepted changes are taken between chunks and ramped sample by sample; their
        ramps' start and end are journaled there.
    max_ramps : int
        Parameter cells ramped at once at most (a change waits while the table is full).

    Attributes
    ----------
    ring : hapsim.audio.sources.FrameRing
        What the output plays (give it to :func:`hapsim.audio.live.open_output`).
    written : int
        Frames computed and pushed (= samples the loop has run).
    closed : bool
        Whether the loop is closed on a device (the scene has a port and a device).

    Raises
    ------
    ConfigError
        No ``audio`` section; a chunk, ring or lead out of range; a hand force without a
        port and device, or with a direction that is not ``dim`` finite numbers of norm 1.
    """

    def __init__(self, engine, *, chunk: int = 256, ring: int = 16384,
                 ahead: int | None = None, hand=None, direction=None, every: int = 0,
                 control=None, max_ramps: int = 64) -> None:
        scene = engine.scene
        axis, mass, vel, gain = listen_plan(engine)   # ConfigError without audio
        self.plan = (axis, mass, vel, gain)
        chunk, ring = int(chunk), int(ring)
        ahead = ring // 4 if ahead is None else int(ahead)
        if chunk < 1 or ring < 4 * chunk or not chunk <= ahead <= ring // 2:
            raise ConfigError(f"chunk {chunk}, ring {ring}, ahead {ahead}: need chunk >= 1, "
                              "ring >= 4 chunk and chunk <= ahead <= ring / 2", key="audio")
        self.engine = engine
        self.rate_hz = float(scene.rate_hz)
        self.chunk = chunk
        self.ahead = ahead
        self.ring = FrameRing(self.rate_hz, channel_names(scene), ring=ring,
                              max_block=max(8192, ring))
        dim = engine.dim
        self.dim = dim
        self.closed = scene.port is not None and scene.device is not None
        dev = scene.device
        if self.closed and float(dev.delay) % 1.0:
            raise ConfigError(f"the live n-D loop's device applies whole periods; a "
                              f"sub-sample delay ({float(dev.delay):g} periods) is analysed "
                              "by check and stability but not played: use a whole delay",
                              file=scene.path, key="device.delay")
        d = int(dev.delay) if self.closed else 0
        Ad, Bd = np.zeros((2 * dim, 2 * dim)), np.zeros((2 * dim, dim))
        if self.closed:
            from hapsim.analysis.ths_nd import LoopModelND, zoh_matrices
            Ad, Bd = zoh_matrices(LoopModelND(mass=dev.mass, friction=dev.friction,
                                              rate_hz=scene.rate_hz, delay=d))
        self.hand = np.zeros(1)
        self.direction = np.zeros(dim)
        if hand is not None and np.size(hand):
            if not self.closed:
                raise ConfigError("a hand force needs a port and a device", file=scene.path,
                                  key="excitation")
            e = np.asarray(direction, float) if direction is not None else None
            if e is None or e.shape != (dim,) or not np.all(np.isfinite(e)) or \
                    abs(float(np.linalg.norm(e)) - 1.0) > 1e-9:
                raise ConfigError(f"the hand's direction must be {dim} finite numbers of "
                                  f"norm 1, got {direction!r}", file=scene.path,
                                  key="excitation.direction")
            self.hand = np.ascontiguousarray(hand, float).copy()
            self.direction = e.copy()
        self.every = int(every)
        self._buf = np.zeros((chunk, len(axis)))
        self.state = np.zeros(5 * dim)                       # x, v, u, next x, v
        self.rest = (np.asarray(dev.position, float).copy() if self.closed
                     else np.zeros(dim))
        self.line = np.zeros((max(d, 1), dim))
        #: [force scale, master gain]: ramped by pause/resume and /hapsim/gain
        self.params = np.array([1.0, 1.0])
        self.cells = np.zeros((int(max_ramps), 2), np.int64)
        self.ramps = np.zeros((int(max_ramps), kernel.RAMP_COLUMNS))
        self._rows: list = []            # per ramp row: (change, cell key, first sample)
        self._left: dict = {}            # change id -> rows still ramping
        self._waiting: list = []         # changes taken, not yet in the table
        pack = self.ring.callback_pack
        port = engine.port if self.closed else -1
        # every array the context names, kept here (alive and in place while it is used)
        self._arrays = {
            "engine": engine.context, "out": self._buf, "axis": axis, "mass": mass,
            "velocity": vel.astype(np.int64), "gain": gain, "ring": pack.ring,
            "wr": pack.wr, "x": engine.step_rows[0], "xp": engine.step_rows[1],
            "port_f": engine.port_f, "Ad": np.ascontiguousarray(Ad, float),
            "Bd": np.ascontiguousarray(Bd, float), "state": self.state, "rest": self.rest,
            "line": self.line, "hand": self.hand, "direction": self.direction,
            "params": self.params, "cells": self.cells, "ramps": self.ramps}
        # a single-precision engine (float32 state in the velocity form; no port) runs
        # through its own entry point, the ramps writing its float32 cells
        single = engine.dtype is not np.float64
        self._ctx = kernel.play_context(dim, d, port, self.every, self._arrays,
                                        dtype=engine.dtype)
        self._chunk = kernel.play_chunk32 if single else kernel.play_chunk
        self._nr = 0
        self.control = control
        self._mail = control.mailbox if control is not None else None
        self._gain_before_pause = 1.0
        self._paused = False
        self.written = 0
        self._missing0 = None           # the ring's silent frames before the first push
        self._missing_end = None        # ... after the last push of a run

    # ------------------------------------------------------------------ changes
    def _cells_of(self, ch) -> list:
        """``(array, index, law, c, end)`` per parameter cell a change ramps."""
        T = 1.0 / self.rate_hz
        if ch.kind == "link":
            c = self.engine.cells(ch.name)
            return ([(a, i, 0, 1.0, ch.end[0]) for a, i in c["stiffness"]]
                    + [(a, i, 0, 1.0 / T, ch.end[1]) for a, i in c["damping"]])
        if ch.kind == "mass":
            return [(a, i, 1, T * T, ch.end[0]) for a, i in self.engine.cells(ch.name)["mass"]]
        if ch.kind == "gain":
            if self._paused:
                self._gain_before_pause = float(ch.end[0])      # heard on resume
                return []
            return [(self.params, 1, 0, 1.0, ch.end[0])]
        pause = ch.kind == "pause"
        if pause and not self._paused:
            self._gain_before_pause = self._target(self.params, 1)
        self._paused = pause
        return [(self.params, 0, 0, 1.0, 0.0 if pause else 1.0),
                (self.params, 1, 0, 1.0, 0.0 if pause else self._gain_before_pause)]

    def _target(self, arr, i) -> float:
        """Where a cell is going: the end of its ramp under way, else its value."""
        key = (int(arr.ctypes.data), int(i))
        for r, (_, k, _) in enumerate(self._rows):
            if k == key:
                return float(self.ramps[r, 3])
        return float(arr[i])

    def _install(self, ch) -> bool:
        cells = self._cells_of(ch)
        keys = [(int(a.ctypes.data), int(i)) for a, i, *_ in cells]
        # a cell already ramping restarts from where it is now
        self._drop([r for r, (_, k, _) in enumerate(self._rows) if k in keys])
        if self._nr + len(cells) > self.cells.shape[0]:
            return False
        for (a, i, law, c, end), key in zip(cells, keys):
            r = self._nr
            now = float(a[i])
            start = (c / now if now != 0.0 else np.inf) if law == 1 else now / c
            self.cells[r] = key
            self.ramps[r] = (float(law), c, start, float(end), float(max(1, ch.steps)), 0.0)
            self._rows.append((ch, key, self.written))
            self._nr += 1
        self._left[id(ch)] = len(cells)
        self._ctx[kernel.RAMPS] = self._nr
        if self.control is not None:
            self.control.ramp_event("ramp_start", ch, self.written)
            if not cells:
                self.control.ramp_event("ramp_end", ch, self.written)
        return True

    def _drop(self, rows) -> None:
        """Remove ramp rows (finished or replaced); a change whose rows are all gone
        ended its ramp (journaled when it finished rather than being replaced)."""
        if not rows:
            return
        keep = [r for r in range(self._nr) if r not in rows]
        for r in rows:
            ch, _, start = self._rows[r]
            self._left[id(ch)] -= 1
            if self._left[id(ch)] == 0:
                del self._left[id(ch)]
                if self.control is not None and self.ramps[r, 5] >= self.ramps[r, 4]:
                    # the sample its last value was first used at
                    self.control.ramp_event("ramp_end", ch, start + int(self.ramps[r, 4]))
        self.cells[:len(keep)] = self.cells[keep]
        self.ramps[:len(keep)] = self.ramps[keep]
        self._rows = [self._rows[r] for r in keep]
        self._nr = len(keep)
        self._ctx[kernel.RAMPS] = self._nr

    def _changes(self) -> None:
        """Between chunks: retire the finished ramps, install the changes posted."""
        if self._nr:
            self._drop([r for r in range(self._nr)
                        if self.ramps[r, 5] >= self.ramps[r, 4]])
        mail = self._mail
        while mail:
            self._waiting.append(mail.popleft())
        while self._waiting and self._install(self._waiting[0]):
            self._waiting.pop(0)

    # ------------------------------------------------------------------ producing
    def produce(self, frames: int | None = None) -> int:
        """Take the changes posted, then compute and push the next chunk (or ``frames`` <
        chunk of them, once at the end): one compiled call with one argument.

        Parameters
        ----------
        frames : int, optional
            Frames to produce (default :attr:`chunk`).

        Returns
        -------
        int
            Frames pushed.
        """
        if self._nr or self._mail or self._waiting:
            self._changes()
        n = self.chunk if frames is None or frames >= self.chunk else int(frames)
        ctx = self._ctx
        ctx[0] = n
        self._chunk(ctx)
        if self._missing0 is None and n:
            # silence the callback played before the sound began is not an underrun
            self._missing0 = int(self.ring.callback_pack.st[1])
        self.written += n
        return n

    @property
    def gain(self) -> float:
        """The master gain on every channel now [-] (ramped by ``/hapsim/gain``)."""
        return float(self.params[1])

    @property
    def ramping(self) -> bool:
        """Whether a change is being ramped or waits to be."""
        return bool(self._nr or self._mail or self._waiting)

    def port_position(self) -> np.ndarray:
        """The device's position now [m], shape (dim,) (a copy; the rest position
        without a device loop)."""
        return self.rest + self.state[:self.dim]

    def port_force(self) -> np.ndarray:
        """The force on the port at the last sample, before the scale of a pause [N],
        shape (dim,) (a copy; zeros without a device loop)."""
        return self.engine.port_f[:self.dim].copy()

    @property
    def read(self) -> int:
        """Frames the callback has read so far."""
        return int(self.ring.callback_pack.st[0])

    def run(self, total: int, stop=None, *, wait: float | None = None,
            on_chunk=None) -> int:
        """Produce ``total`` frames, each chunk once the callback has room for it.

        Parameters
        ----------
        total : int
            Frames to produce in all (>= 0).
        stop : object, optional
            Polled between chunks: its ``set`` true ends the run early.
        wait : float, optional
            Sleep while the ring is full [s] (default half a chunk's duration).
        on_chunk : callable, optional
            ``on_chunk(self)`` after each chunk (telemetry).

        Returns
        -------
        int
            Frames produced (``total`` unless stopped).
        """
        wait = 0.5 * self.chunk / self.rate_hz if wait is None else float(wait)
        st = self.ring.callback_pack.st
        chunk, ahead = self.chunk, self.ahead
        while self.written < total and not (stop is not None and stop.set):
            if self.written + chunk - st[0] > ahead:
                time.sleep(wait)
                continue
            self.produce(min(chunk, total - self.written))
            if on_chunk is not None:
                on_chunk(self)
        # the silence after the last frame is the end (the callback's last block is
        # filled up with it), not an underrun: the count stops at the last push
        self._missing_end = int(st[1])
        return self.written

    def finish(self, timeout: float = 5.0) -> None:
        """Wait until the callback has read every frame written (at most ``timeout`` [s]),
        then mark the ring finished: silence from now on is the end, not an underrun."""
        end = time.monotonic() + timeout
        while self.read < self.written and time.monotonic() < end:
            time.sleep(0.5 * self.chunk / self.rate_hz)
        self.ring.finish()

    def stats(self) -> dict:
        """What the sound did.

        Returns
        -------
        dict
            ``written``, ``read`` [frames], ``underruns`` (frames of silence the callback
            played between the first and the last frame pushed, because the producer was
            late; the silence before and after the sound is not counted), ``skipped``
            (frames the reader jumped over: 0 unless the producer ran more than half a ring
            ahead), ``ahead`` [frames] (the latency the producer keeps).
        """
        s = self.ring.stats()
        end = self._missing_end if self._missing_end is not None else s["missing"]
        return {"written": self.written, "read": s["read"],
                "underruns": max(0, end - self._missing0) if self._missing0 is not None
                else 0,
                "skipped": s["skipped"], "ahead": self.ahead}
