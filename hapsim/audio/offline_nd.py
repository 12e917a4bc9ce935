"""Offline sound of a 2-D or 3-D scene: its listening points through the n-D engine."""

from __future__ import annotations

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["render_nd", "listen_plan"]


def render_nd(engine, steps: int, progress=None) -> np.ndarray:
    """Run an n-D scene and return its listening points, one channel each.

    The scene runs at its own ``rate_hz`` (the sound's rate: an n-D scene is not
    multi-rate); a port, if any, is held at its rest position.

    Parameters
    ----------
    engine : hapsim.engine_nd.EngineND
        Engine of a scene with an ``audio`` section (:class:`hapsim.scene_nd.ListenND`).
    steps : int
        Samples (>= 0).
    progress : callable, optional
        ``progress(done)``, called every 4,096 samples (the engine records them in one
        compiled loop: :meth:`hapsim.engine_nd.EngineND.listen`).

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
    """The arguments of :meth:`hapsim.engine_nd.EngineND.listen` for the scene's listening
    points (offline and live alike: :mod:`hapsim.audio.live_nd`).

    Parameters
    ----------
    engine : hapsim.engine_nd.EngineND

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
