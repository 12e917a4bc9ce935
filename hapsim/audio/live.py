"""Live sound: the audio part of a multi-rate scene computed in a sound server's callback.

The haptic side (the mock hand of ``hapsim play``) pushes one port position per device
sample into a ring and reads back the port force of the device period ``lead`` samples
earlier (:meth:`LiveSound.port_step`); the sound server's process callback calls one
compiled function, :func:`hapsim.kernels.audio.run_frames`, on preallocated buffers: it
runs the N audio sub-steps of each device period, takes the next port position from the
ring at each period start and writes the period's port force back. When a period's position
has not arrived the model waits (silence, counted as starved frames) rather than hold the
last one, and the haptic side waits for the force it needs: so device period n always runs
on the n-th position and the n-th force reaches the device ``lead`` samples later, whatever
the block size and the threads' timing. The coupling is then a pure delay of ``lead``
device samples, which the analysis models by adding it to the device's delay
(:meth:`LiveSound.coupled_scene`); ``lead = ceil(block / N)`` is the least that lets one
callback find the positions of every period it starts. The callback itself does per block
only what the server's Python binding needs (fetch the port buffers, one copy per channel):
no per-sample Python, no allocation by hapsim, the GIL released inside the compiled
function (``nogil``).

Backends: JACK (``JACK-Client``; xruns counted by the server's xrun callback) and, where no
JACK server runs, PortAudio through ``sounddevice`` (output underflows counted as xruns).

**A 2-D or 3-D scene** (:class:`LiveND`): its listening points computed ahead of the
callback, the scene felt through its device's model and changed while it plays.

An n-D scene's sound (``audio: listen:``, :class:`hapsim.scene.ListenND`) is its own
rate's samples (an n-D scene is not multi-rate), the same ones
:func:`hapsim.audio.offline.render_nd` writes to a WAV. Here a producer (the calling
thread) advances the n-D engine one chunk at a time into a preallocated buffer
(:meth:`hapsim.engine.Engine.listen`, compiled, no allocation) and appends it to a
:class:`hapsim.audio.sources.FrameRing`, whose frames the sound server's callback copies
out (:class:`JackOutput`'s native callback: no GIL, nothing allocated per block;
PortAudio's Python callback where no JACK server runs). The producer keeps at most
``ahead`` frames written beyond what the callback has read, so the sound leaves on the
sound card's clock with a latency of ``ahead`` frames; when it falls behind, the callback
plays silence, counted (``underruns``), and the sound resumes where it stopped: the frames
played are the offline rendering's, in order, to float32 rounding (the ring's type), with
the counted silences between.

A scene with a port and a device is played closed on the device's model at the scene's
rate (the loop :mod:`hapsim.lockstep` runs and :mod:`hapsim.analysis.scene_check`
analyses: the exact zero-order hold of the Cartesian mass and friction, the delay line),
the hand's force (the scene's ``excitation``, along its direction, again every ``every``
samples) acting on the device's mass; live changes
(:class:`hapsim.audio.control.ControllerND`) are ramped sample by sample in the same
compiled call
(:func:`hapsim.kernels.play.play_chunk`: one argument, nothing allocated per chunk).
"""

from __future__ import annotations

import atexit
import os
import sys
import time

import numpy as np

from hapsim.audio.offline import listen_plan
from hapsim.audio.sources import (FrameRing, LivePack, LiveSound, RingPack,
                                  sounding_engine)
from hapsim.audio.jack_client import PythonProcessEnd, open_client
from hapsim.errors import ConfigError, DeviceError

__all__ = ["LiveSound", "FrameRing", "LivePack", "RingPack", "sounding_engine", "JackOutput",
           "SoundDeviceOutput", "open_output", "wait_priority", "BACKENDS", "LiveND",
           "channel_names"]

#: Sound backends, in the order ``auto`` tries them.
BACKENDS = ("jack", "sounddevice")


class JackOutput:
    """Play a :class:`LiveSound` through a JACK server, one output port per listening point.

    Parameters
    ----------
    live : LiveSound or FrameRing
        What renders the frames (``render(n)``, ``rate_hz``, ``channels``).
    name : str
        JACK client name.
    server : str, optional
        JACK server name (``jackd -n NAME``); the default server when None.
    connect : bool
        Connect the outputs to the server's physical playback ports (if any).

    Attributes
    ----------
    xruns : int
        xruns the server reported while this client was active.
    blocksize : int
        Frames per process callback (the server's period; a :class:`LiveSound`'s lead is
        set from it).
    callback_priority : int or None
        ``SCHED_FIFO`` priority of the process callback's thread (0: not real-time), read
        in its first call (None before): a haptic thread must run below it, or it
        delays the callback past its deadline (:func:`wait_priority`).
    native : hapsim.audio.jack_native.NativeProcess or None
        The native process callback (a numba ``cfunc`` that never takes the GIL), for a
        :class:`LiveSound` or a :class:`FrameRing`; None when JACK-Client's Python callback
        runs instead.
    python_reason : str or None
        Why the Python callback runs (``HAPSIM_JACK_PYTHON_CALLBACK`` set, the native one
        could not be built).
    callback : str
        ``"native"`` or ``"python (reason)"``, as the reports print it.
    xrun_at : list of float
        When each xrun was reported [s after activation] (the first 1000).

    Raises
    ------
    DeviceError
        No JACK server (the server is never started by this class), or its rate is not
        the scene's audio rate.
    """

    def __init__(self, live: LiveSound, name: str = "hapsim", server: str | None = None,
                 connect: bool = False) -> None:
        import jack

        self.client = open_client(jack, name, server)
        if self.client.samplerate != int(round(live.rate_hz)):
            rate = self.client.samplerate
            self.client.close()
            raise DeviceError(f"the JACK server runs at {rate} Hz, the scene's audio at "
                              f"{live.rate_hz:g} Hz: start jackd -r {live.rate_hz:g}")
        self.live = live
        self.xruns = 0
        self.callback_priority = None
        self.blocksize = int(self.client.blocksize)
        if hasattr(live, "set_block"):
            live.set_block(self.blocksize)
        self.ports = [self.client.outports.register(f"out_{c.replace('.', '_')}")
                      for c in live.channels]
        self._arrays = None
        #: The native process callback (:class:`hapsim.audio.jack_native.NativeProcess`)
        #: when the live sound can use it, else None (the Python callback).
        self.native = None
        self._calls_end = None
        self._calls_start = None
        #: Why the Python callback is used (None when native).
        self.python_reason = None
        self._rt_priority = None
        self._native_setup(live, jack)
        #: Ends the Python callback's thread before deactivation (jack2 cancels it).
        self._process_end = PythonProcessEnd()
        self._jack = jack
        if self.native is None:
            self.client.set_process_callback(self._process)
        self.client.set_xrun_callback(self._xrun)
        self.client.set_blocksize_callback(self._blocksize)
        #: When each xrun was reported [s after activation] (the first 1000).
        self.xrun_at: list[float] = []
        #: ``time.monotonic()`` at activation (what :attr:`xrun_at` counts from).
        self.t_active = time.monotonic()
        self._closed = False
        atexit.register(self.close)
        self.client.activate()
        if connect:
            targets = self.client.get_ports(is_physical=True, is_input=True, is_audio=True)
            for p, t in zip(self.ports, targets):
                self.client.connect(p, t)

    def _native_setup(self, live, jack) -> None:
        """Install the native callback (no GIL, :mod:`hapsim.audio.jack_native`) where
        ``live`` allows it, else note why not."""
        try:
            from hapsim.audio import jack_native
        except Exception as exc:  # numba/llvmlite could not link libjack: Python's callback
            self.python_reason = f"the native callback could not be built: {exc}"
            return
        why = jack_native.native_available(live)
        if why is None and os.environ.get("HAPSIM_JACK_PYTHON_CALLBACK"):
            why = "HAPSIM_JACK_PYTHON_CALLBACK is set"
        if why is not None:
            self.python_reason = why
            return
        ffi, lib = jack._ffi, jack._lib
        ptrs = [int(ffi.cast("uintptr_t", p._ptr)) for p in self.ports]
        self.native = jack_native.NativeProcess(live, ptrs)
        err = lib.jack_set_process_callback(
            self.client._ptr, ffi.cast("JackProcessCallback", self.native.address),
            ffi.cast("void *", self.native.ctx.ctypes.data))
        if err:
            self.native = None
            self.python_reason = f"jack_set_process_callback failed ({err})"
            return
        self._rt_priority = jack_native.client_rt_priority(self.client)

    @property
    def callback_priority(self) -> int | None:
        """``SCHED_FIFO`` priority of the process callback's thread (0: not real-time),
        known once the callback has run (None before)."""
        if self.native is not None:
            return self._rt_priority if self.native.calls > 0 else None
        return self._callback_priority

    @callback_priority.setter
    def callback_priority(self, v) -> None:
        self._callback_priority = v

    def _blocksize(self, blocksize: int) -> None:
        # JACK's non-real-time thread, before the first block of the new size
        self._process_end.note(1)
        try:
            self.blocksize = int(blocksize)
            if hasattr(self.live, "set_block"):
                self.live.set_block(self.blocksize)
        finally:
            self._process_end.note(-1)

    def _process(self, frames: int) -> None:
        self._process_end.check(self._jack)
        if self.callback_priority is None:   # once: the thread's SCHED_FIFO priority
            self.callback_priority = _thread_priority()
        if frames != self.blocksize:     # the server changed its period: keep it exact
            self.blocksize = frames
            if hasattr(self.live, "set_block"):
                self.live.set_block(frames)
        block = self.live.render(frames)
        for c, p in enumerate(self.ports):
            p.get_array()[:] = block[:, c]

    def _xrun(self, delay_usecs: float) -> None:
        self._process_end.note(1)
        try:
            self.xruns += 1
            if len(self.xrun_at) < 1000:
                self.xrun_at.append(round(time.monotonic() - self.t_active, 6))
        finally:
            self._process_end.note(-1)

    def begin(self) -> None:
        """The producer starts (the loop's first position comes next): the callbacks
        before it played the run's start, not its sound (:attr:`begin_s`)."""
        self._calls_start = self.native.calls if self.native is not None else None

    @property
    def begin_s(self) -> float | None:
        """When the producer began [s after activation, at the current block size, as
        :meth:`underrun_at` counts]; None before :meth:`begin` or without the native
        callback."""
        if self._calls_start is None:
            return None
        return round(self._calls_start * self.blocksize / float(self.live.rate_hz), 6)

    def finish(self) -> None:
        """The producer is done (the loop's last position or frames): what the callback
        plays from now on is the run's end, not starvation. The source's counters
        (:meth:`LiveSound.finish`, :meth:`FrameRing.finish`) and :meth:`underrun_at` stop
        here; the client plays on until :meth:`close`."""
        self._calls_end = self.native.calls if self.native is not None else None
        if hasattr(self.live, "finish"):
            self.live.finish()

    def underrun_at(self, upto_calls: int | None = None) -> list[float]:
        """When blocks with starved frames started [s after activation, at the current
        block size] (native callback over a LiveSound: the first 256; else empty).

        Parameters
        ----------
        upto_calls : int, optional
            Only the callbacks up to this one (default: the callbacks until
            :meth:`finish`, when it was called: after it the callback has no positions
            left, which is not starvation).
        """
        if self.native is None:
            return []
        if upto_calls is None:
            upto_calls = self._calls_end
        per = self.blocksize / float(self.live.rate_hz)
        return [round((i - 1) * per, 6) for i in self.native.starved_calls
                if upto_calls is None or i <= upto_calls]

    @property
    def callback(self) -> str:
        """Which process callback runs: ``"native"`` (no GIL) or ``"python (why)"``."""
        return "native" if self.native is not None else f"python ({self.python_reason})"

    @property
    def out_names(self) -> list[str]:
        """Full JACK names of the output ports (``client:port``)."""
        return [p.name for p in self.ports]

    def close(self) -> None:
        """Deactivate and close the client (once; also run at interpreter exit when it was
        not called, so that a native callback never runs on freed arrays)."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        if self.native is None:
            self._process_end.end()      # (the Python callback's thread ends itself)
        self.client.deactivate()
        # (the Python notification callbacks: none sent, none running, at the close)
        self._process_end.end_notifications(self._jack, self.client)
        self.client.close()


class SoundDeviceOutput:
    """Play a :class:`LiveSound` through PortAudio (``sounddevice``), the fallback.

    Parameters
    ----------
    live : LiveSound or FrameRing
        What renders the frames.
    device : int or str, optional
        PortAudio output device (default: the host's default output).
    blocksize : int
        Frames per callback, fixed (PortAudio adapts the device's buffers to it), so a
        :class:`LiveSound`'s lead is exact.

    Attributes
    ----------
    xruns : int
        Callbacks that reported an output underflow.
    blocksize : int

    Raises
    ------
    DeviceError
        PortAudio found no output it can open.
    """

    def __init__(self, live: LiveSound, device=None, blocksize: int = 256) -> None:
        import sounddevice as sd

        self.live = live
        self.xruns = 0
        self.xrun_at: list[float] = []
        self.t_active = time.monotonic()
        #: Which callback runs (PortAudio's callback is always Python here).
        self.callback = "python (sounddevice calls a Python function)"
        self.blocksize = int(blocksize)
        if hasattr(live, "set_block"):
            live.set_block(self.blocksize)

        self.callback_priority = None

        def callback(outdata, frames, time, status):
            if self.callback_priority is None:
                self.callback_priority = _thread_priority()
            if status.output_underflow:
                self.xruns += 1
            outdata[:] = live.render(frames)

        try:
            self.stream = sd.OutputStream(samplerate=live.rate_hz, channels=len(live.channels),
                                          dtype="float32", callback=callback, device=device,
                                          blocksize=self.blocksize)
            self.stream.start()
        except Exception as exc:  # PortAudio raises its own error types
            raise DeviceError(f"no audio output through PortAudio: {exc}") from None

    def finish(self) -> None:
        """The producer is done (:meth:`JackOutput.finish`)."""
        if hasattr(self.live, "finish"):
            self.live.finish()

    def close(self) -> None:
        """Stop and close the stream."""
        self.stream.stop()
        self.stream.close()


def _thread_priority() -> int:
    """``SCHED_FIFO``/``SCHED_RR`` priority of the calling thread (0 otherwise)."""
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            return int(os.sched_getparam(0).sched_priority)
    except (AttributeError, OSError):
        pass
    return 0


def wait_priority(out, timeout_s: float = 1.0) -> int | None:
    """The real-time priority of ``out``'s callback thread once it has run (None when it
    did not run within ``timeout_s`` [s] or the backend does not say)."""
    t_end = time.monotonic() + timeout_s
    while getattr(out, "callback_priority", None) is None and time.monotonic() < t_end:
        time.sleep(0.005)
    return getattr(out, "callback_priority", None)


def open_output(live: LiveSound, backend: str = "auto", *, server: str | None = None,
                connect: bool = True):
    """Open a sound output for ``live``: JACK, else sounddevice.

    Parameters
    ----------
    backend : {"auto", "jack", "sounddevice"}
    server : str, optional
        JACK server name.
    connect : bool
        JACK: connect to the physical playback ports.

    Returns
    -------
    JackOutput or SoundDeviceOutput

    Raises
    ------
    ConfigError
        Unknown backend (key ``--sound``).
    DeviceError
        The backend asked for (or every one, with ``auto``) cannot play.
    """
    if backend not in ("auto",) + BACKENDS:
        raise ConfigError(f"unknown sound backend {backend!r}; valid: auto, "
                          + ", ".join(BACKENDS), key="--sound")
    # The callback enters Python once per block and needs the GIL: with the default switch
    # interval (5 ms, the length of a 256-frame block at 48 kHz) a busy haptic thread can
    # hold it past the deadline. 0.2 ms bounds that wait.
    sys.setswitchinterval(min(sys.getswitchinterval(), 2e-4))
    errors = []
    for b in (BACKENDS if backend == "auto" else (backend,)):
        try:
            if b == "jack":
                return JackOutput(live, server=server, connect=connect)
            return SoundDeviceOutput(live)
        except (DeviceError, ImportError, OSError) as exc:
            errors.append(f"{b}: {exc}")
    raise DeviceError("no sound output: " + "; ".join(errors))


# ---------------------------------------------------------------- a 2-D or 3-D scene
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
    engine : hapsim.engine.Engine
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
    control : hapsim.audio.control.ControllerND, optional
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
        # the n-D compiled call is loaded on the first LiveND: a 1-D play or run does not
        # pay for it when importing this module
        from hapsim.kernels import play as kernel
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
            from hapsim.analysis.ths import MatrixLoop, zoh_matrices
            Ad, Bd = zoh_matrices(MatrixLoop(mass=dev.mass, friction=dev.friction,
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
        self._ramps_at = kernel.RAMPS       # where the context holds the ramps' count
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
        self._ctx[self._ramps_at] = self._nr
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
        self._ctx[self._ramps_at] = self._nr

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
