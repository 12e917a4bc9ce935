"""Offline sound of a scene, in any dimension: a 1-D scene's scripted gesture through the
multi-rate engine, a 2-D or 3-D scene's listening points through the n-D engine
(:func:`render_nd`), to a WAV file."""

from __future__ import annotations

import math
import os
import wave

import numpy as np

from hapsim.engine import Engine
from hapsim.errors import ConfigError

__all__ = ["load_gesture", "closed_loop_pluck", "open_loop_gesture", "write_wav", "read_wav",
           "render_nd", "listen_plan"]


def load_gesture(path: str, rate_hz: float, steps: int | None = None) -> np.ndarray:
    """A recorded port-position profile resampled at the device rate.

    Parameters
    ----------
    path : str
        ``.csv`` (columns time [s], position [m]; a header line allowed) or ``.npz``
        (arrays ``time`` and ``position``; a 2-D ``position`` uses its first column, as
        ``hapsim simulate`` writes it).
    rate_hz : float
        Device rate [Hz].
    steps : int, optional
        Samples wanted; default: up to the profile's last time.

    Returns
    -------
    ndarray, shape (steps,)
        Position at ``t = n / rate_hz`` [m], linearly interpolated, held after the end.

    Raises
    ------
    ConfigError
        Unreadable file, non-finite or non-increasing time (key ``--gesture``).
    """
    from hapsim.device_model import load_profile

    t, x = load_profile(path, "position", "m", key="--gesture")
    n = steps if steps is not None else int(math.floor(t[-1] * rate_hz + 1e-9)) + 1
    return np.interp(np.arange(n) / rate_hz, t, x)


def open_loop_gesture(engine: Engine, positions: np.ndarray, progress=None):
    """Drive the port along a position profile (no device): the sound and the port force.

    Parameters
    ----------
    engine : Engine
        Engine of a scene with ``audio`` and a port.
    positions : ndarray, shape (n,)
        Port position per device sample [m].
    progress : callable, optional
        ``progress(done, n)``.

    Returns
    -------
    audio : ndarray, shape (n * N, C)
        Listened frames.
    force : ndarray, shape (n,)
        Port force [N].
    """
    engine.set_port_position(float(positions[0]) if len(positions) else 0.0, at_rest=True)
    return engine.play(positions, progress=progress)


def closed_loop_pluck(engine: Engine, steps: int, progress=None, seed: int = 0):
    """The scene's excitation played on the mock device closed on the engine (lockstep).

    The hand force of ``scene.excitation`` (impulse, profile) pushes the device
    (:class:`hapsim.emulated.mock.MockPhysics`: exact ZOH plant, quantisation, noise); every
    device sample the engine takes the device position, runs its N audio sub-steps and
    returns the port force, which the device applies ``d`` samples later, clamped to
    ``force_limit`` (the THS the analysis models, docs/design.md, 'The THS').

    Parameters
    ----------
    engine : Engine
        Engine of a scene with ``audio``, a port and a device.
    steps : int
        Device samples, >= 0.
    progress : callable, optional
        ``progress(done, steps)`` every 1000 samples.
    seed : int
        Sensor-noise seed of the mock.

    Returns
    -------
    audio : ndarray, shape (steps * N, C)
        Listened frames.
    device_position : ndarray, shape (steps,)
        Device position at each sample [m].
    force : ndarray, shape (steps,)
        Port force computed at each sample [N] (before the clamp).
    """
    from hapsim.device_model import InProcessLoop, MockPhysics

    scene = engine.scene
    dev = scene.device
    phys = MockPhysics(dev, scene.rate_hz, scene.excitation, seed=seed,
                       base_dir=os.path.dirname(os.path.abspath(scene.path)))
    loop = InProcessLoop(phys, engine.port_step, dev.delay, dev.force_limit)
    N = engine.substeps
    audio = np.zeros((steps * N, len(engine.channels)))
    xs = np.zeros(steps)
    fs = np.zeros(steps)
    engine.set_port_position(phys.sample(), at_rest=True)
    for n in range(steps):
        xs[n], fs[n] = loop.step()
        audio[n * N:(n + 1) * N] = engine.frames
        if progress is not None and (n + 1) % 1000 == 0:
            progress(n + 1, steps)
    return audio, xs, fs


def write_wav(path: str, audio: np.ndarray, rate_hz: float) -> dict:
    """Write frames as a 16-bit PCM WAV, atomically (``path.partial`` then renamed).

    Parameters
    ----------
    audio : ndarray, shape (n, C)
        Frames, full scale 1.0; values beyond +-1 are clipped (counted).
    rate_hz : float
        Sample rate [Hz] (a whole number).

    Returns
    -------
    dict
        ``frames``, ``channels``, ``rate_hz``, ``peak`` (largest |value| before the clip),
        ``clipped`` (samples beyond full scale).

    Raises
    ------
    ValueError
        Non-finite frames (an unstable scene).
    """
    a = np.atleast_2d(np.asarray(audio, float).T).T
    if not np.all(np.isfinite(a)):
        raise ValueError("the sound has non-finite samples (the scene diverged)")
    peak = float(np.max(np.abs(a))) if a.size else 0.0
    clipped = int(np.sum(np.abs(a) > 1.0))
    pcm = np.round(np.clip(a, -1.0, 1.0) * 32767.0).astype("<i2")
    from hapsim.outputs import atomic_write
    with atomic_write(path, "wb", "--audio") as fh, wave.open(fh, "wb") as w:
        w.setnchannels(a.shape[1])
        w.setsampwidth(2)
        w.setframerate(int(round(rate_hz)))
        w.writeframes(pcm.tobytes())
    return {"frames": int(a.shape[0]), "channels": int(a.shape[1]),
            "rate_hz": int(round(rate_hz)), "peak": peak, "clipped": clipped}


def read_wav(path: str) -> tuple[np.ndarray, int]:
    """Read a 16-bit PCM WAV (as :func:`write_wav` writes it).

    Returns
    -------
    audio : ndarray, shape (n, C)
        Frames, full scale 1.0.
    rate : int
        Sample rate [Hz].
    """
    with wave.open(path, "rb") as w:
        if w.getsampwidth() != 2:
            raise ValueError(f"{path}: {8 * w.getsampwidth()}-bit samples, expected 16-bit")
        n, c, rate = w.getnframes(), w.getnchannels(), w.getframerate()
        data = np.frombuffer(w.readframes(n), dtype="<i2").reshape(n, c)
    return data.astype(float) / 32767.0, rate


def render_nd(engine, steps: int, progress=None) -> np.ndarray:
    """Run an n-D scene and return its listening points, one channel each.

    The scene runs at its own ``rate_hz`` (the sound's rate: an n-D scene is not
    multi-rate); a port, if any, is held at its rest position.

    Parameters
    ----------
    engine : hapsim.engine.Engine
        Engine of a scene with an ``audio`` section (:class:`hapsim.scene.ListenND`).
    steps : int
        Samples (>= 0).
    progress : callable, optional
        ``progress(done)``, called every 4,096 samples (the engine records them in one
        compiled loop: :meth:`hapsim.engine.Engine.listen`).

    Returns
    -------
    ndarray, shape (steps, C)
        Channel ``c`` at sample ``k`` (after ``k + 1`` steps): ``gain x[axis]`` (position
        [m]) or ``gain (x[axis] - x_prev[axis]) / T`` (velocity [m/s]) of its mass, the
        ``gain`` [-] making full scale 1.0 in the WAV.

    Raises
    ------
    ConfigError
        The scene has no ``audio`` section (key ``audio``).
    """
    plan = listen_plan(engine)
    out = np.empty((steps, len(plan[0])))
    chunk = 4096
    for k in range(0, steps, chunk):
        engine.listen(out[k:k + chunk], *plan)
        if progress is not None:
            progress(min(steps, k + chunk))
    return out


def listen_plan(engine) -> tuple:
    """The arguments of :meth:`hapsim.engine.Engine.listen` for the scene's listening
    points (offline and live alike: :class:`hapsim.audio.live.LiveND`).

    Parameters
    ----------
    engine : hapsim.engine.Engine

    Returns
    -------
    (axis, mass, velocity, gain)
        ndarrays of shape (C,): int64 axes, int64 mass indices, bool, float gains [-]
        (a velocity's gain times the rate [Hz]: ``gain (x - x_prev) / T``).

    Raises
    ------
    ConfigError
        The scene has no ``audio`` section (key ``audio``).
    """
    scene = engine.scene
    if not scene.audio:
        raise ConfigError("the scene needs an audio section (listen: [{mass, axis, "
                          "quantity, gain}]) to be heard; see configs/membrane.yaml",
                          file=scene.path, key="audio")
    idx = np.array([engine.names.index(p.mass) for p in scene.audio], np.int64)
    ax = np.array([p.axis for p in scene.audio], np.int64)
    vel = np.array([p.quantity == "velocity" for p in scene.audio])
    gain = np.array([p.gain for p in scene.audio], float)
    gain = np.where(vel, gain * scene.rate_hz, gain)
    return ax, idx, vel, gain
