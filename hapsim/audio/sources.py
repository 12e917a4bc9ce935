"""Sound sources a sound server's callback reads: :class:`LiveSound` (the audio part of a
multi-rate scene, computed in the callback) and :class:`FrameRing` (frames an engine
computed elsewhere, played back).

Below both outputs: :mod:`hapsim.audio.live` (the JACK and PortAudio outputs) and
:mod:`hapsim.audio.jack_native` (the compiled JACK callback) read these sources; neither
imports the other's output code for them. The coupling they model is described in
:mod:`hapsim.audio.live`.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from typing import NamedTuple

import numpy as np

from hapsim.engine import Engine
from hapsim.errors import ConfigError, DeviceError
from hapsim.kernels import audio as audio_kernel

__all__ = ["LiveSound", "FrameRing", "LivePack", "RingPack", "sounding_engine"]

_S = audio_kernel.LIVE_STATE


class LivePack(NamedTuple):
    """A :class:`LiveSound`'s arguments of :func:`hapsim.kernels.audio.run_frames`, by
    part: what a compiled caller (the native JACK callback,
    :class:`hapsim.audio.jack_native.NativeProcess`) needs to render it. The arrays are
    the live sound's and its engine's own (shared, not copied: the kernel updates them in
    place); :meth:`LiveSound.render` calls the kernel with the same pack, so that both
    callers pass one argument list.

    Attributes
    ----------
    head : tuple
        ``(nsub, linear, last, port)``, as :attr:`hapsim.engine.MultiRatePack.head`.
    arrays : tuple of ndarray
        22 one-dimensional C-contiguous arrays in ``run_frames``' order: the position ring
        [m] (float64, shape (R,)), its write count (int64, (1,)), the live state
        (float64, indexed by :data:`hapsim.kernels.audio.LIVE_STATE`), the force ring [N]
        (float64, (R,)), then :attr:`hapsim.engine.MultiRatePack.args` without the
        trailing ``1 / Ta``.
    inv_ta : float
        ``1 / Ta`` [1/s], the audio rate.
    block : ndarray, shape (max_block, C), float32
        The frames buffer the kernel writes (:attr:`LiveSound.block`).
    """

    head: tuple
    arrays: tuple
    inv_ta: float
    block: np.ndarray


class RingPack(NamedTuple):
    """A :class:`FrameRing`'s arguments of :func:`hapsim.kernels.audio.ring_read` (shared,
    not copied): what the native JACK callback over the ring needs.

    Attributes
    ----------
    ring : ndarray, shape (R, C), float32
        The frames (C-contiguous).
    wr : ndarray, shape (1,), int64
        Frames written (the haptic loop's count).
    st : ndarray, shape (3,), int64
        Frames read, missing (silence), skipped (see ``ring_read``).
    block : ndarray, shape (max_block, C), float32
        The frames buffer the reader writes (:attr:`FrameRing.block`).
    """

    ring: np.ndarray
    wr: np.ndarray
    st: np.ndarray
    block: np.ndarray


class LiveSound:
    """A multi-rate engine driven by a haptic-rate position ring, rendered block by block.

    Parameters
    ----------
    engine : Engine
        Engine of a scene with ``audio`` (its state is advanced here from now on: do not
        call its :meth:`~Engine.port_step` as well).
    ring : int
        Ring length in device samples (positions and forces), a power of two >= 16.
    max_block : int
        Largest block a callback may ask for [frames].

    Raises
    ------
    ConfigError
        When the scene has no ``audio`` section.
    """

    def __init__(self, engine: Engine, ring: int = 4096, max_block: int = 8192) -> None:
        if engine.multirate_pack is None:
            raise ConfigError("live sound needs a scene with an audio section",
                              file=engine.scene.path, key="audio")
        self.engine = engine
        self.rate_hz = float(engine.scene.audio.rate_hz)
        self.channels = engine.channels
        self._ring = np.zeros(ring)
        self._fring = np.zeros(ring)
        self._wr = np.zeros(1, dtype=np.int64)
        self._st = np.zeros(len(_S))
        self._st[_S["gain"]] = self._st[_S["gain_target"]] = 1.0
        p = engine.port_index
        x0 = float(engine.x[0, p]) if p >= 0 else 0.0
        self._st[_S["p0"]] = self._st[_S["p1"]] = x0
        self.block = np.zeros((max_block, len(self.channels)), dtype=np.float32)
        head, state = engine.multirate_pack
        self._nsub = int(head[0])
        self._pack = LivePack(tuple(head), (self._ring, self._wr, self._st, self._fring)
                              + tuple(state[:-1]), state[-1], self.block)
        self._lock = threading.Lock()
        #: Device samples between a position and the force computed from it (set by
        #: :meth:`set_block` from the server's block size).
        self.lead = 0
        #: How long :meth:`port_step` waits for a force before giving up [s].
        self.timeout_s = 2.0
        #: Times :meth:`port_step` had to wait for the audio thread.
        self.waits = 0
        self._starved_end = None             # underruns when the haptic side finished
        self.render(0)       # compile (or load from cache) now, not in the first callback

    @staticmethod
    def lead_for(block: int, nsub: int) -> int:
        """The least lead [device samples] for callbacks of ``block`` frames and ``nsub``
        audio sub-steps per device period: ``ceil(block / nsub)``.

        A callback starts at most ``ceil(block / nsub)`` periods, the last one's position
        being ``ceil(block / nsub)`` samples past the last finished period; the haptic
        side, blocked on the force ``lead`` periods back, has pushed exactly that far.

        Parameters
        ----------
        block : int
            Frames per callback (the server's block size).
        nsub : int
            Audio sub-steps per device period (> 0).

        Returns
        -------
        int
            The lead [device samples].
        """
        return int(math.ceil(int(block) / int(nsub)))

    @property
    def callback_pack(self) -> LivePack:
        """The kernel arguments a compiled callback renders this live sound with
        (:class:`LivePack`), shared with it.

        Returns
        -------
        LivePack
            Fixed at construction: the arrays are read and written in place by every
            render, :meth:`push` and :meth:`set_gain`.
        """
        return self._pack

    def set_block(self, block: int) -> int:
        """Set :attr:`lead` for the server's block size [frames]; return it.

        Parameters
        ----------
        block : int
            Frames per callback.

        Returns
        -------
        int
            The new :attr:`lead` [device samples] (:meth:`lead_for`).
        """
        self.lead = self.lead_for(block, self._nsub)
        return self.lead

    def coupled_scene(self, scene):
        """``scene`` with its device delay increased by :attr:`lead`: the loop this live
        sound closes (period n's force reaches the device ``lead`` samples later).

        Parameters
        ----------
        scene : Scene
            The scene of :attr:`engine` (a dataclass with a ``device``).

        Returns
        -------
        Scene
            A copy, ``device.delay`` + :attr:`lead` [device samples]; ``scene`` unchanged.
        """
        return dataclasses.replace(scene, device=dataclasses.replace(
            scene.device, delay=scene.device.delay + int(self.lead)))

    # -------------------------------------------------------------- haptic thread
    def push(self, position: float) -> None:
        """Hand the audio thread the port position of the next device sample [m].

        Single producer: the value is written before the count that publishes it.

        Parameters
        ----------
        position : float
            Port position [m].
        """
        w = int(self._wr[0])
        self._ring[w % self._ring.size] = position
        self._wr[0] = w + 1

    def force(self) -> float:
        """The port force of the last device period the audio thread finished [N]
        (0.0 before the first).

        Returns
        -------
        float
            Port force [N].
        """
        w = int(self._st[_S["written"]])
        return float(self._fring[(w - 1) % self._fring.size]) if w > 0 else 0.0

    def port_step(self, position: float) -> float:
        """Haptic-loop form: push the position of device sample n, return the port force of
        period ``n - lead`` (0.0 for n < lead), waiting for the audio thread to finish it.

        Parameters
        ----------
        position : float
            Port position of device sample n [m].

        Returns
        -------
        float
            Port force of period ``n - lead`` [N].

        Raises
        ------
        DeviceError
            The audio thread finished no period for :attr:`timeout_s` (the sound server
            stopped calling back).
        """
        n = int(self._wr[0])
        self.push(position)
        m = n - self.lead
        if m < 0:
            return 0.0
        if self._st[_S["written"]] <= m:
            self.waits += 1
            last, t_last = self._st[_S["written"]], time.monotonic()
            while self._st[_S["written"]] <= m:
                time.sleep(2e-4)
                if self._st[_S["written"]] != last:
                    last, t_last = self._st[_S["written"]], time.monotonic()
                elif time.monotonic() - t_last > self.timeout_s:
                    raise DeviceError(f"the sound server stopped calling back: no audio "
                                      f"period finished for {self.timeout_s:g} s")
        return float(self._fring[m % self._fring.size])

    def set_gain(self, gain: float, ramp_s: float = 0.05) -> None:
        """Ramp the master gain linearly to ``gain`` over ``ramp_s`` [s] (no click).

        Parameters
        ----------
        gain : float
            Target gain [-], finite.
        ramp_s : float, optional
            Ramp duration [s], >= 0 (at least one audio frame; default 0.05).

        Raises
        ------
        ValueError
            Non-finite gain or negative ramp.
        """
        if not np.isfinite(gain) or not ramp_s >= 0:
            raise ValueError(f"gain must be finite and ramp >= 0, got {gain}, {ramp_s}")
        with self._lock:
            g0 = self._st[_S["gain"]]
            steps = max(1.0, ramp_s * self.rate_hz)
            self._st[_S["gain_step"]] = (gain - g0) / steps
            self._st[_S["gain_target"]] = gain

    @property
    def gain(self) -> float:
        """Master gain now (during a ramp: where it is)."""
        return float(self._st[_S["gain"]])

    @property
    def gain_target(self) -> float:
        """Master gain the current ramp ends at."""
        return float(self._st[_S["gain_target"]])

    def stats(self) -> dict:
        """``pushed``, ``consumed`` device samples, ``periods`` completed, ``underruns``
        (frames of silence because the next period's position had not arrived: the model
        waited), ``lead`` [device samples] and ``waits`` (haptic samples that waited for
        the audio thread).

        Returns
        -------
        dict
            Those six counts by name, as ints.
        """
        starved = self._starved_end if self._starved_end is not None \
            else int(self._st[_S["starved"]])
        return {"pushed": int(self._wr[0]), "consumed": int(self._st[_S["read"]]),
                "underruns": starved,
                "periods": int(self._st[_S["written"]]), "lead": int(self.lead),
                "waits": int(self.waits)}

    def finish(self) -> None:
        """The haptic side has pushed its last position: from now on the callback has
        nothing to play, which is the run's end, not starvation, so :meth:`stats` keeps the
        underruns counted until now."""
        self._starved_end = int(self._st[_S["starved"]])

    # -------------------------------------------------------------- audio thread
    def render(self, nframes: int) -> np.ndarray:
        """Compute the next ``nframes`` frames into :attr:`block` (one compiled call).

        Parameters
        ----------
        nframes : int
            Frames asked for, at most ``max_block``.

        Returns
        -------
        ndarray, shape (nframes, C), float32
            A view of the preallocated block.
        """
        pk = self._pack
        audio_kernel.run_frames(nframes, *pk.head, *pk.arrays, pk.inv_ta, pk.block)
        return self.block[:nframes]



class FrameRing:
    """Frames computed by the haptic loop, played by a sound server (``hapsim run --sound``).

    In ``hapsim run`` the multi-rate model stays in the haptic loop, so the force on the
    device is exactly what the analysis models; each device sample's N frames
    (:attr:`hapsim.engine.Engine.frames`) are appended here and the sound server's callback
    copies them out (:func:`hapsim.kernels.audio.ring_read`: one compiled call per block,
    silence counted on underrun, a jump counted when clock drift leaves the writer more
    than half a ring ahead).

    Parameters
    ----------
    rate_hz : float
        Audio rate [Hz].
    channels : tuple of str
        Channel names.
    ring : int
        Frames the ring holds (default 8192: 170 ms at 48 kHz).
    max_block : int
        Largest block a callback may ask for [frames].
    """

    def __init__(self, rate_hz: float, channels, ring: int = 8192, max_block: int = 8192):
        self.rate_hz = float(rate_hz)
        self.channels = tuple(channels)
        self._ring = np.zeros((ring, len(self.channels)), dtype=np.float32)
        self._wr = np.zeros(1, dtype=np.int64)
        self._st = np.zeros(3, dtype=np.int64)
        self.block = np.zeros((max_block, len(self.channels)), dtype=np.float32)
        self._missing_end = None             # frames missing when the loop finished
        self._pack = RingPack(self._ring, self._wr, self._st, self.block)
        audio_kernel.ring_write(np.zeros((0, len(self.channels))), self._ring, self._wr)
        self.render(0)

    @property
    def callback_pack(self) -> RingPack:
        """The arrays a compiled callback reads this ring with (:class:`RingPack`), shared
        with it.

        Returns
        -------
        RingPack
        """
        return self._pack

    def push(self, frames: np.ndarray) -> None:
        """Append one device sample's frames, shape (N, C) (haptic thread).

        Parameters
        ----------
        frames : ndarray, shape (N, C)
            N audio frames (the sub-steps) of C channels.
        """
        audio_kernel.ring_write(frames, self._ring, self._wr)

    def render(self, nframes: int) -> np.ndarray:
        """The next ``nframes`` frames into :attr:`block` (sound server's thread).

        Parameters
        ----------
        nframes : int
            Frames asked for, at most ``max_block``.

        Returns
        -------
        ndarray, shape (nframes, C), float32
            A view of the preallocated block (silence where the ring ran empty).
        """
        audio_kernel.ring_read(nframes, self._ring, self._wr, self._st, self.block)
        return self.block[:nframes]

    def stats(self) -> dict:
        """``written``, ``read`` frames, ``missing`` (silence on underrun), ``skipped``.

        Returns
        -------
        dict
            Those four counts [frames] by name, as ints (``read`` is the reader's position,
            the ``skipped`` frames included).
        """
        missing = self._missing_end if self._missing_end is not None else int(self._st[1])
        return {"written": int(self._wr[0]), "read": int(self._st[0]),
                "missing": missing, "skipped": int(self._st[2])}

    def finish(self) -> None:
        """The loop has written its last frames: silence from now on is the run's end, not
        an underrun, so :meth:`stats` keeps the frames missing until now."""
        self._missing_end = int(self._st[1])



def sounding_engine(ring: FrameRing) -> type:
    """An :class:`~hapsim.engine.Engine` subclass whose :meth:`port_step` also hands its
    frames to ``ring`` (the loop rebuilds it as ``type(engine)(scene)`` after a recovery,
    so the ring is a class attribute).

    Parameters
    ----------
    ring : FrameRing
        The ring each device sample's frames, shape (substeps, channels), are pushed to.

    Returns
    -------
    type
        The subclass (``frame_ring`` = ``ring``), built like :class:`~hapsim.engine.Engine`
        from a scene.
    """

    class SoundingEngine(Engine.layout(1)):      # multi-rate sound: the 1-D layout
        __doc__ = f"Engine whose device samples also feed a {type(ring).__name__}."
        frame_ring = ring

        def port_step(self, position: float) -> float:
            f = super().port_step(position)
            self.frame_ring.push(self.frames)
            return f

    return SoundingEngine
