"""Several ports in lockstep: each port's device keeping its own tick count, the links'
forces by the scheme's law, and the felt matrices across ports measured from each port's
free responses (issue 30 item 3; docs/ports.md). The n-D loop of one device is
:mod:`hapsim.lockstep`; this is its several-port twin's measurement, built on it.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.felt_matrices import felt_deviation
from hapsim.analysis.ths import MatrixLoop, split_hold_matrices
from hapsim.errors import ConfigError
from hapsim.lockstep import default_samples, excitation_starts

__all__ = ["PortDevice", "LockstepPorts", "measure_felt_ports", "port_error_responses",
           "ports_bound"]


class PortDevice:
    """One port's device in lockstep, keeping its own tick count: ``m x'' + b0 x' = u``
    held over each period, the force applied ``d`` periods after the sample it answers.

    Parameters
    ----------
    device : hapsim.scene.Device
        Mass ``m`` [kg], friction ``b0`` [N s/m], delay ``d`` [periods] (``m + f``: the
        split hold).
    rate_hz : float
        The sample rate [Hz] (one period per :meth:`tick`: lockstep, asked by name).
    x0, v0 : float, optional
        Initial deviation from rest [m] and velocity [m/s].

    Notes
    -----
    The exact hold of the 1-DoF device (:func:`hapsim.analysis.ths.split_hold_matrices`
    of its own 1 x 1 loop, the zero-order hold for a whole delay): ``[x, v][n+1] = Ad [x,
    v][n] + Gamma0 F[n-m] + Gamma1 F[n-m-1]`` (docs/design.md, 'The timing convention').
    """

    def __init__(self, device, rate_hz: float, x0: float = 0.0, v0: float = 0.0) -> None:
        lm = MatrixLoop(mass=[[float(device.mass)]], friction=[[float(device.friction)]],
                        rate_hz=rate_hz, delay=device.delay)
        self.Ad, self._G0, self._G1 = split_hold_matrices(lm)
        self.state = np.array([float(x0), float(v0)])
        self.fifo = [0.0] * int(math.floor(float(device.delay)))   # F[n-1], ..., F[n-m]
        self.held = 0.0
        self.ticks = 0

    @property
    def position(self) -> float:
        """The sampled position (deviation from rest) [m]."""
        return float(self.state[0])

    def tick(self, force: float) -> None:
        """One period: take the force answering this tick's sample [N], apply the one
        due now.

        Parameters
        ----------
        force : float
            ``F[n]`` [N], computed from the sample of this tick.
        """
        if self.fifo:
            self.fifo.insert(0, float(force))
            u = self.fifo.pop()
        else:
            u = float(force)
        self.state = self.Ad @ self.state + self._G0[:, 0] * u + self._G1[:, 0] * self.held
        self.held = u
        self.ticks += 1


class LockstepPorts:
    """A scene with several ports closed in-process in lockstep, each port its own device
    model (:class:`PortDevice`).

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
    x0, v0 : array_like, shape (P,), optional
        The devices' initial deviations [m] and velocities [m/s], in port order.

    Notes
    -----
    One sample: each port is at its device's sample; every link's force is the scheme's
    law on the positions at ``n`` and ``n - 1`` (docs/design.md, 'The scheme':
    ``F = K (x1 - x2) + B ((x1 - x2) - (x1p - x2p)) / T``, ``-F`` on the first mass,
    ``+F`` on the second; grounds at their ``x0``); each device takes the force on its
    port and ticks. A port's previous position starts one period back at its initial
    velocity, as in :class:`LockstepND`.
    """

    def __init__(self, scene, x0=None, v0=None) -> None:
        P = len(scene.devices)
        x0 = np.zeros(P) if x0 is None else np.asarray(x0, float)
        v0 = np.zeros(P) if v0 is None else np.asarray(v0, float)
        self.P, self.T = P, scene.period
        self.devices = [PortDevice(d, scene.rate_hz, x0[i], v0[i])
                        for i, (_, d) in enumerate(scene.devices)]
        names = list(scene.ports) + [m.name for m in scene.masses if m.kind == "ground"]
        at = {n: i for i, n in enumerate(names)}
        self.x = np.array([0.0] * P + [float(m.x0) for m in scene.masses
                                       if m.kind == "ground"])
        self.xp = self.x.copy()
        self.xp[:P] = x0 - v0 * self.T
        self.i1 = np.array([at[lk.m1] for lk in scene.links], int)
        self.i2 = np.array([at[lk.m2] for lk in scene.links], int)
        self.K = np.array([lk.stiffness for lk in scene.links], float)
        self.B = np.array([lk.damping for lk in scene.links], float)
        self._buffers = None                 # :meth:`forces`' scratch, made at first use

    def step(self, samples: int, *, reading_error=None, force_error=None,
             limits=None, forces=None) -> np.ndarray:
        """Advance the loop and record the ports.

        Parameters
        ----------
        samples : int
        reading_error : ndarray, shape (samples, P), optional
            An error of the host's reading [m], as :meth:`LockstepND.step`'s: the links
            are given, and the record holds, the device's sample plus it.
        force_error : ndarray, shape (samples, P), optional
            A force error [N] added to the force each device takes at sample ``i``.
        limits : ndarray, shape (P,), optional
            Each device's force limit [N] (``inf``: none): the force a device takes is
            clipped to ``[-limit, limit]`` (after ``force_error``), as the host clamps
            every force to its device's ``force_limit`` before it is sent
            (docs/design.md, 'The data path', step 4). None: not clipped (the
            measurement's records, :func:`measure_felt_ports`, keep the linear loop).
        forces : ndarray, shape (samples, P), optional
            Filled with the force [N] each device took at each sample (the links' force
            on its port, plus ``force_error``, clipped to ``limits``).

        Returns
        -------
        ndarray, shape (samples, P)
            Each port's sampled position [m], before the step (plus ``reading_error``).
        """
        out = np.empty((int(samples), self.P))
        for n in range(int(samples)):
            self.x[:self.P] = [d.position for d in self.devices]
            if reading_error is not None:
                self.x[:self.P] += reading_error[n]
            out[n] = self.x[:self.P]
            force = self.forces()
            if force_error is not None:
                force[:self.P] += force_error[n]
            if limits is not None:
                np.clip(force[:self.P], -limits, limits, out=force[:self.P])
            if forces is not None:
                forces[n] = force[:self.P]
            self.xp = self.x.copy()
            for i, dev in enumerate(self.devices):
                dev.tick(force[i])
        return out

    def forces(self, out: np.ndarray | None = None) -> np.ndarray:
        """The links' forces on every mass at the current positions ``x`` and the previous
        ``xp`` [N], shape (P + grounds,): ports first (the scheme's law, class notes).

        With ``out`` (shape (P + grounds,), float) the forces are written there through
        buffers held by the loop, so a real-time caller allocates nothing per sample;
        the operations and their order are the same, so the result is the same to the bit.

        Parameters
        ----------
        out : ndarray, shape (P + grounds,), optional
            Where to write the forces (overwritten); None: a new array.

        Returns
        -------
        ndarray, shape (P + grounds,)
            ``out`` itself, or the new array [N]: per link ``F = K d + B (d - dp) / T``,
            ``-F`` on its first mass and ``+F`` on its second.
        """
        if out is None:
            d = self.x[self.i1] - self.x[self.i2]
            dp = self.xp[self.i1] - self.xp[self.i2]
            F = self.K * d + self.B * (d - dp) / self.T
            force = np.zeros(self.x.size)
            np.add.at(force, self.i1, -F)
            np.add.at(force, self.i2, F)
            return force
        b = self._buffers
        if b is None:
            b = self._buffers = tuple(np.empty(self.K.size) for _ in range(5))
        d, dp, F, t, u = b
        np.take(self.x, self.i1, out=t)
        np.take(self.x, self.i2, out=u)
        np.subtract(t, u, out=d)
        np.take(self.xp, self.i1, out=t)
        np.take(self.xp, self.i2, out=u)
        np.subtract(t, u, out=dp)
        np.subtract(d, dp, out=t)
        np.multiply(self.B, t, out=t)
        np.divide(t, self.T, out=t)
        np.multiply(self.K, d, out=F)
        np.add(F, t, out=F)
        out[:] = 0.0
        np.negative(F, out=u)
        np.add.at(out, self.i1, u)
        np.add.at(out, self.i2, F)
        return out


def port_error_responses(scene, samples: int, *, size: float = 1e-9) -> tuple:
    """:func:`error_responses` of a scene with several ports (:class:`LockstepPorts`).

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
    samples : int
        Length ``L`` of the responses.
    size : float, optional
        The error's size [m] or [N] for the runs (the loop is linear: exact).

    Returns
    -------
    (ndarray, ndarray)
        Shapes (L, P, P): the record's change per unit reading error [m/m] and per unit
        force error [m/N] at sample 0 along each port (``[t, :, j]`` for port ``j``).
    """
    L, P = int(samples), len(scene.devices)
    rest = LockstepPorts(scene).step(L)
    out = []
    for kw in ("reading_error", "force_error"):
        R = np.empty((L, P, P))
        for j in range(P):
            e = np.zeros((L, P))
            e[0, j] = size
            R[:, :, j] = (LockstepPorts(scene).step(L, **{kw: e}) - rest) / size
        out.append(R)
    return tuple(out)


def measure_felt_ports(scene, amplitude: float = 1e-8, samples: int | None = None,
                       progress=None) -> dict:
    """The felt matrices across ports measured in lockstep, against the prediction.

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
    amplitude : float, optional
        ``a`` [m]: record ``i`` starts port ``i`` displaced by ``a``, record ``P + i``
        moving at ``a / (10 T)`` (:func:`excitation_starts`).
    samples : int, optional
        Samples per record (default :func:`default_samples` of the loop's order).
    progress : callable, optional
        ``progress(done, total)`` after each record.

    Returns
    -------
    dict
        ``measured`` (:func:`hapsim.analysis.pencil.fit_felt_nd` of the records minus the
        record from rest), ``predicted`` (:class:`hapsim.analysis.ports.PortsCheck`),
        ``deviation`` (:func:`hapsim.analysis.felt_matrices.felt_deviation`), ``bound``
        (a :class:`hapsim.analysis.linearisation.LinearisationBound` of a linear loop:
        its round-off allowance only), ``verdict``
        (:func:`hapsim.analysis.felt_matrices.felt_verdict`), ``order``, ``records``,
        ``samples``.

    Raises
    ------
    ConfigError
        ``amplitude`` not a positive number; ``samples`` fewer than the regression's
        ``2 p P`` unknowns.
    """
    from hapsim.analysis.felt_matrices import felt_verdict
    from hapsim.analysis.pencil import fit_felt_nd
    from hapsim.analysis.ports import check_ports, port_loop
    a = float(amplitude)
    if not (math.isfinite(a) and a > 0):
        raise ConfigError(f"must be a positive number [m], got {amplitude!r}",
                          key="amplitude")
    chk = check_ports(scene)
    P, T = len(chk.ports), scene.period
    order = chk.states // P
    N = int(samples) if samples is not None else default_samples(order, P)
    if N < 2 * order * P:
        raise ConfigError(f"must be at least {2 * order * P} samples for this loop "
                          f"({chk.states} states), got {N}", key="samples")
    rest = LockstepPorts(scene).step(N)
    starts = excitation_starts(P, a, T)[1:]
    recs = []
    for j, (x0, v0) in enumerate(starts):
        recs.append(LockstepPorts(scene, x0, v0).step(N) - rest)
        if progress is not None:
            progress(j + 1, len(starts))
    fit = fit_felt_nd(recs, port_loop(scene)[0].mass, T, order)
    bound = ports_bound(scene, chk, a)
    dev = felt_deviation(fit, chk)
    return {"measured": fit, "predicted": chk, "deviation": dev, "bound": bound,
            "verdict": felt_verdict(dev, bound), "order": order, "records": len(recs),
            "samples": N}


def ports_bound(scene, chk, amplitude: float):
    """The linearisation bound of a scene with several ports: a linear loop (spring-dampers
    between ports and to grounds), so its round-off allowance only.

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
    chk : hapsim.analysis.ports.PortsCheck
    amplitude : float
        The excitation ``a`` [m].

    Returns
    -------
    hapsim.analysis.linearisation.LinearisationBound
        No kinematic or link term; the damping factor ``max |s| / (2 |Re s|)`` of the
        rendered poles and the position scale of the grounds (the round-off's).
    """
    from hapsim.analysis.linearisation import LinearisationBound
    from hapsim.analysis.ths import continuous_poles
    s = continuous_poles(chk.render.rendered_poles, scene.period)
    damping = float(np.max(np.abs(s) / (2 * np.abs(s.real)))) if s.size else math.nan
    scale = max([abs(float(m.x0)) for m in scene.masses] + [0.0])
    return LinearisationBound(amplitude=float(amplitude), kinematic=0.0, link=0.0,
                              link_name=None, depth=math.inf, depth_name=None,
                              damping_factor=damping, position_scale=scale)
