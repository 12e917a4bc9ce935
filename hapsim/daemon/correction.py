"""A device correction in the host loop: the engine of a one-link scene, corrected.

The host loop asks its engine for ``port_step(x)`` once per STATE. For a scene whose only
link is a spring_damper between the port and a ground, :func:`corrected_engine` returns an
engine whose ``port_step`` runs :class:`hapsim.analysis.corrections.CorrectionLaw` instead
(the engine itself still advances, so its energy and restart behave as before). What the
loop needs per sample is therefore only the position of the STATE (and, for
``velocity_sensor``, the measured velocity: the device's VELOCITY frame of that STATE,
PROTOCOL.md §4, kept by :class:`hapsim.daemon.loop.MeasuredVelocity`).
"""

from __future__ import annotations

from hapsim.errors import ConfigError

__all__ = ["corrected_engine"]


def corrected_engine(scene, velocity=None):
    """An :class:`hapsim.engine.Engine` of ``scene`` applying ``scene.device.correction``.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Calibrated scene: one spring_damper link between its port and a ground, no virtual
        mass, a device with a ``correction``.
    velocity : callable, optional
        ``velocity() -> float``, the handle velocity at the current STATE [m/s] (the
        loop's :class:`~hapsim.daemon.loop.MeasuredVelocity`); required for
        ``velocity_sensor``.

    Returns
    -------
    Engine
        An instance of a subclass of :class:`hapsim.engine.Engine` built for this scene;
        ``type(engine)(scene)`` (the loop's restart) gives a fresh one with the same law.

    Raises
    ------
    ConfigError
        Another scene shape, or a velocity sensor without a velocity source.
    """
    from hapsim.analysis.corrections import Correction, CorrectionLaw
    from hapsim.engine import Engine

    dev = scene.device
    corr = Correction.from_dict(dev.correction)
    kinds = {m.name: m.kind for m in scene.masses}
    links = scene.links
    if (len(links) != 1 or links[0].kind != "spring_damper"
            or {kinds[links[0].m1], kinds[links[0].m2]} != {"port", "ground"}
            or any(k == "mass" for k in kinds.values())):
        raise ConfigError("device.correction runs on a scene of one spring_damper between "
                          "the port and a ground (the analysed loop)", file=scene.path,
                          key="device.correction")
    if corr.kind == "velocity_sensor" and velocity is None:
        raise ConfigError("velocity_sensor needs the device's measured velocity (its "
                          "VELOCITY frames); none was given", file=scene.path,
                          key="device.correction.kind")
    lk = links[0]
    K, B, T, d = float(lk.stiffness), float(lk.damping), scene.period, int(dev.delay)
    vel = velocity if velocity is not None else (lambda: 0.0)

    class CorrectedEngine(Engine):
        """Engine whose port force follows the device correction (module docstring)."""

        def __init__(self, sc):
            super().__init__(sc)
            self._law = CorrectionLaw(corr, K, B, T, d)
            self._fresh = True

        def set_port_position(self, position, at_rest=False):
            super().set_port_position(position, at_rest=at_rest)
            self._law.reset(float(position))
            self._fresh = False

        def port_step(self, position):
            super().port_step(position)
            if self._fresh:
                self._law.reset(float(position))
                self._fresh = False
            return self._law.step(position, vel())

    return CorrectedEngine(scene)
