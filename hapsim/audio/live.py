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
"""

from __future__ import annotations

import atexit
import os
import sys
import time

from hapsim.audio.sources import (FrameRing, LivePack, LiveSound, RingPack,
                                  sounding_engine)
from hapsim.errors import ConfigError, DeviceError

__all__ = ["LiveSound", "FrameRing", "LivePack", "RingPack", "sounding_engine", "JackOutput",
           "SoundDeviceOutput", "open_output", "wait_priority", "BACKENDS"]

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

        try:
            self.client = jack.Client(name, no_start_server=True, servername=server)
        except jack.JackOpenError as exc:
            raise DeviceError(f"no JACK server{' ' + repr(server) if server else ''} "
                              f"running ({exc})") from None
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
        #: Why the Python callback is used (None when native).
        self.python_reason = None
        self._rt_priority = None
        self._native_setup(live, jack)
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
        self.blocksize = int(blocksize)
        if hasattr(self.live, "set_block"):
            self.live.set_block(self.blocksize)

    def _process(self, frames: int) -> None:
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
        self.xruns += 1
        if len(self.xrun_at) < 1000:
            self.xrun_at.append(round(time.monotonic() - self.t_active, 6))

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
        self.client.deactivate()
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
