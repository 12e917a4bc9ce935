"""A device correction in the host loop: the engine of any scene with a port, corrected.

The host loop asks its engine for ``port_step(x)`` once per STATE. The correction acts at
the port (:func:`hapsim.analysis.corrections.corrected_frame`, whose closed loop the
analysis solves): the engine is stepped with the corrected port position ``q[n]`` and, as
the port's previous position, ``qq[n]`` (so the dampers at the port see the velocity
estimate ``(q - qq)/T``), and for ``inertia_compensation`` the compensating force is added:

=========================  ==============================================================
kind                       ``q[n]``, ``qq[n]``, force to the device
=========================  ==============================================================
``velocity_sensor``        ``x``, ``x - T v`` (``v`` the measured handle velocity)
``velocity_filter``        ``x``, ``x - T vf``, ``vf = a vf[n-1] + (1 - a)(x - x[n-1])/T``
``prediction``             ``xp[n]``, ``xp[n-1]``, ``xp = x + h (x - x[n-1])``
``inertia_compensation``   ``x``, ``x[n-1]``; ``F + Mc (x - 2 x[n-1] + x[n-2]) / T^2``
``virtual_coupling``       ``y[n]``, ``y[n-1]``: the massless proxy balancing the coupling
                           ``(Kc, Bc)`` and the links at the port (spring_dampers only)
=========================  ==============================================================

The engine itself advances as before, so its energy and restart behave as before. For
``velocity_sensor`` the measured velocity comes from the ``velocity`` callable: the
device's VELOCITY frame of that STATE (PROTOCOL.md §4), kept by
:class:`hapsim.host.loop.MeasuredVelocity`.
"""

from __future__ import annotations

from hapsim.errors import ConfigError

__all__ = ["corrected_engine"]


def _port_links(scene):
    """``(name, other end index, sign, threshold or None)`` of every link at the port.

    ``sign`` is +1 when the port is the link's first end (the kernels' ``d = x1 - x2``).
    """
    port = scene.port.name
    out = []
    for lk in scene.links:
        if port in (lk.m1, lk.m2):
            first = lk.m1 == port
            out.append((lk.name, scene.index(lk.m2 if first else lk.m1), 1.0 if first else -1.0,
                        float(lk.threshold) if lk.kind == "contact" else None))
    return out


def corrected_engine(scene, velocity=None):
    """An :class:`hapsim.engine.Engine` of ``scene`` applying ``scene.device.correction``.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Calibrated scene with a port and a device with a ``correction``; any network
        (virtual masses, several links, contacts, any integrator). ``virtual_coupling``
        needs a single-rate scene (no ``audio`` section).
    velocity : callable, optional
        ``velocity() -> float``, the handle velocity at the current STATE [m/s] (the
        loop's :class:`~hapsim.host.loop.MeasuredVelocity`); required for
        ``velocity_sensor``.

    Returns
    -------
    Engine
        An instance of a subclass of :class:`hapsim.engine.Engine` built for this scene;
        ``type(engine)(scene)`` (the loop's restart) gives a fresh one with the same law.

    Raises
    ------
    ConfigError
        No port, a velocity sensor without a velocity source, a virtual coupling on a
        multi-rate (audio) scene.

    Notes
    -----
    The coupling proxy ``y`` solves ``Kc (x - y) + Bc (Dx - Dy) + F_port(y) = 0`` with the
    port force of the engine's own link laws (``cordis``/``schemes`` kernels): a spring_damper
    ``-k (y - o) - z (y - y[n-1] - T v_o)``, a contact the same plus ``-s k thr`` while
    engaged (``-s (y - o) < thr``). A contact makes ``F_port`` piecewise linear; the
    engaged set is found by fixed-point iteration from the one at ``y[n-1]`` (at most one
    pass per contact, the force being monotone in ``y``).
    """
    from hapsim.analysis.corrections import Correction
    from hapsim.engine import Engine

    if scene.port is None:
        raise ConfigError("device.correction acts at the port; the scene has none",
                          file=scene.path, key="device.correction")
    corr = Correction.from_dict(scene.device.correction)
    kind = corr.kind
    if kind == "velocity_sensor" and velocity is None:
        raise ConfigError("velocity_sensor needs the device's measured velocity (its "
                          "VELOCITY frames); none was given", file=scene.path,
                          key="device.correction.kind")
    if kind == "virtual_coupling" and scene.audio is not None:
        raise ConfigError("virtual_coupling runs on single-rate scenes (no audio section)",
                          file=scene.path, key="device.correction")
    plinks = _port_links(scene) if kind == "virtual_coupling" else []
    T = float(scene.period)
    h = float(scene.device.delay if corr.horizon is None else corr.horizon)
    a, eps = corr.filter_pole(T) if kind == "velocity_filter" else (0.0, 0.0)
    Mc_T2 = corr.mass / (T * T)
    Kc = corr.stiffness if kind == "virtual_coupling" else 0.0
    Bc_T = corr.damping / T
    vel = velocity if velocity is not None else (lambda: 0.0)

    class CorrectedEngine(Engine.layout(1)):     # the 1-D layout: a correction is 1-D
        """Engine whose port force follows the device correction (module docstring)."""

        corrected = True

        def __init__(self, sc):
            super().__init__(sc)
            # (stiffness array, damping/T array, slot, other end) of the links at the port
            self._plinks = [self._link_slot[nm] + (o, sgn, thr) for nm, o, sgn, thr in plinks]
            self._mobile_set = frozenset(int(i) for i in self._mobile)
            self._fresh = True

        def _reset_law(self, x: float) -> None:
            self._x1 = self._x2 = self._q1 = float(x)
            self._vf = 0.0
            self._y1 = float(x)
            if kind == "virtual_coupling":        # at rest: y[n] = y[n-1]
                self._y1 = self._proxy(float(x), float(x), float(x), 0.0, rest=True)

        def _proxy(self, x: float, x1: float, y1: float, bc_t: float, rest=False) -> float:
            """Coupling proxy ``y[n]`` (Notes of :func:`corrected_engine`)."""
            xs, xps, v = self._x, self._xp, self._v
            y = y1
            for _ in range(len(self._plinks) + 1):
                num = Kc * x + bc_t * (x - x1 + y1)
                den = Kc + bc_t
                for k_arr, z_arr, j, o, sgn, thr in self._plinks:
                    k, z = k_arr[j], z_arr[j]
                    if thr is not None and not (-sgn * (y - xs[o]) < thr):
                        continue                   # contact open at this y
                    tvo = v[o] * T if v is not None and o in self._mobile_set \
                        else xs[o] - xps[o]
                    num += k * xs[o] + z * tvo + (0.0 if rest else z * y1)
                    if thr is not None:
                        num -= sgn * k * thr
                    den += k + (0.0 if rest else z)
                y_new = num / den
                if y_new == y:
                    break
                y = y_new
            return y

        def set_port_position(self, position, at_rest=False):
            super().set_port_position(position, at_rest=at_rest)
            self._reset_law(float(position))
            self._fresh = False

        def port_step(self, position):
            x = float(position)
            if self._fresh:
                self._reset_law(x)
                self._fresh = False
            extra = 0.0
            if kind == "velocity_sensor":
                q, qq = x, x - T * vel()
            elif kind == "velocity_filter":
                self._vf = a * self._vf + eps * (x - self._x1) / T
                q, qq = x, x - T * self._vf
            elif kind == "prediction":
                q, qq = x + h * (x - self._x1), self._q1
                self._q1 = q
            elif kind == "inertia_compensation":
                q, qq = x, self._x1
                extra = Mc_T2 * (x - 2.0 * self._x1 + self._x2)
            else:
                q = self._proxy(x, self._x1, self._y1, Bc_T)
                qq = self._y1
                self._y1 = q
            p = self._port
            self._x[p] = qq          # the multi-rate kernel reads the previous port position
            self._xp[p] = qq         # from x, the single-rate ones from xp
            f = super().port_step(q) + extra
            self._x2 = self._x1
            self._x1 = x
            return f

    return CorrectedEngine(scene)
