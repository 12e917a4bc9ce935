"""Live sound of a 2-D or 3-D scene: its listening points computed ahead of a sound
server's callback.

An n-D scene's sound (``audio: listen:``, :class:`hapsim.scene_nd.ListenND`) is its own
rate's samples (an n-D scene is not multi-rate), the same ones
:func:`hapsim.audio.offline_nd.render_nd` writes to a WAV. Here a producer (the calling
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
"""

from __future__ import annotations

import time

import numpy as np

from hapsim.audio.offline_nd import listen_plan
from hapsim.audio.sources import FrameRing
from hapsim.errors import ConfigError

__all__ = ["LiveND", "channel_names"]

_AXES = "xyz"


def channel_names(scene) -> tuple:
    """Channel names of an n-D scene's listening points: ``MASS.AXIS.QUANTITY``.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND

    Returns
    -------
    tuple of str
        One per listening point, in the scene's order (empty without ``audio``).
    """
    return tuple(f"{p.mass}.{_AXES[p.axis]}.{p.quantity}" for p in (scene.audio or ()))


class LiveND:
    """An n-D scene's listening points produced ahead of a sound server's callback.

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

    Attributes
    ----------
    ring : hapsim.audio.sources.FrameRing
        What the output plays (give it to :func:`hapsim.audio.live.open_output`).
    written : int
        Frames computed and pushed.

    Raises
    ------
    ConfigError
        No ``audio`` section; a chunk, ring or lead out of range.
    """

    def __init__(self, engine, *, chunk: int = 256, ring: int = 16384,
                 ahead: int | None = None) -> None:
        scene = engine.scene
        self.plan = listen_plan(engine)            # ConfigError without an audio section
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
        self._buf = np.empty((chunk, len(self.plan[0])))
        self._listen = engine.listener(*self.plan)    # checked and bound once
        self.written = 0
        self._missing0 = None           # the ring's silent frames before the first push
        self._missing_end = None        # ... after the last push of a run

    def produce(self, frames: int | None = None) -> int:
        """Compute and push the next chunk (or ``frames`` < chunk of them, once at the end).

        Parameters
        ----------
        frames : int, optional
            Frames to produce (default :attr:`chunk`).

        Returns
        -------
        int
            Frames pushed.
        """
        buf = self._buf if frames is None or frames >= self.chunk else self._buf[:frames]
        self._listen(buf)
        self.ring.push(buf)
        if self._missing0 is None and buf.shape[0]:
            # silence the callback played before the sound began is not an underrun
            self._missing0 = int(self.ring.callback_pack.st[1])
        self.written += buf.shape[0]
        return buf.shape[0]

    @property
    def read(self) -> int:
        """Frames the callback has read so far."""
        return int(self.ring.callback_pack.st[0])

    def run(self, total: int, stop=None, *, wait: float | None = None) -> int:
        """Produce ``total`` frames, each chunk once the callback has room for it.

        Parameters
        ----------
        total : int
            Frames to produce in all (>= 0).
        stop : object, optional
            Polled between chunks: its ``set`` true ends the run early.
        wait : float, optional
            Sleep while the ring is full [s] (default half a chunk's duration).

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
