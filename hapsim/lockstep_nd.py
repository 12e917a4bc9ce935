"""The n-DoF loop closed in-process, in lockstep: the n-D engine coupled to the exact
sampled device (the first piece of issue 23's n-DoF mock).

One sample ``n`` (the timing of :mod:`hapsim.analysis.scene_nd_check`, so the analysis's
state matrix is exactly this loop's one-step map for a linear scene):

1. the port is at the device sample ``x_dev[n]``;
2. the engine advances (:class:`hapsim.engine_nd.EngineND`), computing the force on the
   port ``F[n]`` from the positions at ``n`` and ``n - 1``;
3. ``F[n]`` enters the delay line; the device holds ``u[n] = F[n-d]`` over the period and
   advances exactly, ``[x, v][n+1] = Ad [x, v][n] + Bd u[n]``
   (:func:`hapsim.analysis.ths_nd.zoh_matrices` of its Cartesian mass and friction).

No protocol and no pseudo-terminal yet: the n-axis device, its mock behind a port, the
hand's excitation and the identification of the felt matrices from a record are what is
left of the n-DoF run.
"""

from __future__ import annotations

import numpy as np

from hapsim.analysis.ths_nd import LoopModelND, zoh_matrices
from hapsim.engine_nd import EngineND
from hapsim.errors import ConfigError

__all__ = ["LockstepND", "measure_felt_lockstep"]


class LockstepND:
    """An n-D scene felt through its device, closed in-process.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene with a port and a device.
    x0, v0 : array_like, shape (n,), optional
        The device's initial displacement from its rest position [m] and velocity [m/s].

    Raises
    ------
    ConfigError
        No port or device; ``x0``/``v0`` not n finite numbers.
    """

    def __init__(self, scene, x0=None, v0=None) -> None:
        if scene.port is None or scene.device is None:
            raise ConfigError("the lockstep loop needs a port and its device",
                              file=scene.path, key="masses")
        n = scene.dimension
        self.n = n
        dev = scene.device
        self.Ad, self.Bd = zoh_matrices(LoopModelND(mass=dev.mass, friction=dev.friction,
                                                    rate_hz=scene.rate_hz, delay=dev.delay))
        self.engine = EngineND(scene)
        self.rest = dev.position.copy()

        def vec(v, key):
            a = np.zeros(n) if v is None else np.asarray(v, float)
            if a.shape != (n,) or not np.all(np.isfinite(a)):
                raise ConfigError(f"must be {n} finite numbers, got {v!r}", key=key)
            return a
        self.state = np.concatenate([vec(x0, "x0"), vec(v0, "v0")])  # deviation, velocity
        self.delay = np.zeros((dev.delay, n))     # F[n-1], ..., F[n-d]
        p = self.rest + self.state[:n]
        # the port's previous position: where it was one period ago at the initial velocity
        self.engine.xp[:, self.engine.port] = p - self.state[n:] * scene.period
        self.engine.x[:, self.engine.port] = p

    def step(self, samples: int = 1, record: bool = False):
        """Advance the loop.

        Parameters
        ----------
        samples : int
            Samples to run.
        record : bool, optional
            Return the device positions.

        Returns
        -------
        ndarray, shape (samples, n) or None
            The device's position deviation ``x_dev[n]`` [m] at each sample, before the
            step (when ``record``).
        """
        n = self.n
        out = np.empty((samples, n)) if record else None
        eng = self.engine
        for i in range(int(samples)):
            x = self.state[:n]
            if record:
                out[i] = x
            eng.set_port_position(self.rest + x)
            eng.step()
            F = eng.port_force
            if self.delay.shape[0]:
                u = self.delay[-1].copy()
                self.delay[1:] = self.delay[:-1]
                self.delay[0] = F
            else:
                u = F
            self.state = self.Ad @ self.state + self.Bd @ u
        return out


def measure_felt_lockstep(scene, amplitude: float = 1e-8, samples: int | None = None,
                          progress=None) -> dict:
    """The felt matrices measured from lockstep free responses, against the prediction.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene with a port and a device.
    amplitude : float, optional
        Excitation amplitude ``a`` [m]: record ``i`` starts the handle displaced by
        ``a e_i``, record ``n + i`` moving at ``a / (10 T) e_i`` (``e_i`` the axes).
    samples : int, optional
        Samples per record (default ``max(300, 20 x`` the prediction order ``x n)``).
    progress : callable, optional
        ``progress(done, total)`` after each record.

    Returns
    -------
    dict
        ``measured`` (:func:`hapsim.analysis.identify_nd.fit_felt_nd`'s dict of the
        records minus the record from rest, which removes the loop's response to a rest
        that is not exactly an equilibrium: exact for a linear loop), ``predicted``
        (:class:`hapsim.analysis.scene_nd_check.SceneCheckND`), ``deviation`` (the largest
        difference of the felt stiffness and damping matrices, each over the predicted
        matrix's largest entry [-]; None without felt matrices), ``bound``
        (:class:`hapsim.analysis.linearisation_nd.LinearisationBound` at ``a``), ``order``,
        ``records``, ``samples``.

    Raises
    ------
    ConfigError
        As :class:`LockstepND`, :func:`hapsim.analysis.scene_nd_check.closed_loop_nd`;
        ``amplitude`` not positive; ``samples`` too short for the order.
    """
    from hapsim.analysis.identify_nd import fit_felt_nd
    from hapsim.analysis.linearisation_nd import linearisation_bound
    from hapsim.analysis.scene_nd_check import check_scene_nd
    chk = check_scene_nd(scene)
    bound = linearisation_bound(scene, amplitude, chk.render.rendered_poles)
    n = scene.dimension
    order = chk.states // n
    N = int(samples) if samples is not None else max(300, 20 * order * n)
    if N < 2 * order * n:
        raise ConfigError(f"must be at least {2 * order * n} samples for this loop "
                          f"({chk.states} states), got {N}", key="samples")
    a = bound.amplitude
    T = scene.period
    starts = [(a * np.eye(n)[i], None) for i in range(n)] + \
             [(None, a / (10 * T) * np.eye(n)[i]) for i in range(n)]
    rest = LockstepND(scene).step(N, record=True)
    recs = []
    for j, (x0, v0) in enumerate(starts):
        recs.append(LockstepND(scene, x0=x0, v0=v0).step(N, record=True) - rest)
        if progress is not None:
            progress(j + 1, len(starts))
    fit = fit_felt_nd(recs, scene.device.mass, T, order)
    k, b = chk.render.felt_stiffness, chk.render.felt_damping
    dev = None
    if fit["felt_stiffness"] is not None and k is not None:
        dev = {"felt_stiffness": float(np.max(np.abs(fit["felt_stiffness"] - k))
                                       / np.max(np.abs(k))),
               "felt_damping": float(np.max(np.abs(fit["felt_damping"] - b))
                                     / np.max(np.abs(b)))}
    return {"measured": fit, "predicted": chk, "deviation": dev, "bound": bound,
            "order": order, "records": len(recs), "samples": N}
