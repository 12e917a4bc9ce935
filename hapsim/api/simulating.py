"""``simulate``: a scene with several ports run offline, each port closed through its own
device model (issue 30: the same command takes a 1-D, a 2-D, a 3-D and a several-port
scene; docs/ports.md, 'Offline: simulate')."""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from hapsim.errors import ConfigError
from hapsim.results import Report

__all__ = ["SimulateReport", "simulate"]


@dataclasses.dataclass(frozen=True)
class SimulateReport(Report):
    """What ``hapsim simulate SCENE --json`` says of a scene with several ports, with the
    trajectory beside it.

    Attributes
    ----------
    scene : str
        The scene's file.
    steps : int
        Samples simulated: the ones asked, or the step at which a port's position became
        non-finite (then the rows before it are kept).
    rate_hz : float
        The sample rate of every port's loop [Hz].
    recorded : int
        Masses recorded (R).
    ports : list of str
        The ports, in file order (the columns of ``port_position`` and ``port_force``).
    delays : list of float
        Each port's delay [periods].
    x0, v0 : list of float
        Each port's initial displacement [m] and velocity [m/s].
    diverged : dict or None
        ``{"step": k, "port": name}``: the first sample whose position is not finite
        (the loop is unstable and the port's device has no force limit), else None.

    Other attributes (arrays, not in the ``--json`` object): ``time`` [s] shape (M+1,),
    ``position`` [m] shape (M+1, R, 1), ``names`` shape (R,), ``port_position`` [m] and
    ``port_force`` [N] shape (M+1, P) (row ``k``: the port's sample at ``t = k T`` and the
    force its device took from it, applied ``delay`` periods later), ``exit_code`` (0, or
    1 when diverged); ``M = steps``.
    """

    scene: str
    steps: int
    rate_hz: float
    recorded: int
    ports: list
    delays: list
    x0: list
    v0: list
    diverged: dict | None


def _per_port(values, ports: tuple, key: str) -> np.ndarray:
    """``values`` (None, a mapping port -> number, or a sequence in port order) as an
    array in port order; zeros for None and for a port a mapping leaves out."""
    out = np.zeros(len(ports))
    if values is None:
        return out
    if isinstance(values, dict):
        for name, v in values.items():
            if name not in ports:
                raise ConfigError(f"no port named {name!r}; ports: {', '.join(ports)}",
                                  key=key)
            out[ports.index(name)] = _finite(v, key)
        return out
    vals = list(values)
    if len(vals) != len(ports):
        raise ConfigError(f"one value per port ({', '.join(ports)}), got {len(vals)}",
                          key=key)
    for i, v in enumerate(vals):
        out[i] = _finite(v, key)
    return out


def _finite(v, key: str) -> float:
    """``v`` as a finite float, else a ConfigError on ``key``."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        f = math.nan
    if isinstance(v, bool) or not math.isfinite(f):
        raise ConfigError(f"must be a finite number, got {v!r}", key=key)
    return f


def simulate(scene, steps: int, *, record=None, x0=None, v0=None,
             progress=None) -> SimulateReport:
    """Run a scene with several ports offline, each port closed through its own device
    (``hapsim simulate SCENE`` of a ``devices:`` scene).

    The loop is the lockstep run's (:class:`hapsim.lockstep_ports.LockstepPorts`, the
    model ``hapsim run SCENE --lockstep`` measures): each sample every port is at its
    device's sample, the links' forces follow the scheme's law
    (docs/design.md, 'The scheme'), and each device (:class:`hapsim.lockstep_ports.PortDevice`: ``m x'' + b0
    x' = u``, its exact zero-order hold, its own delay line, a real number of periods)
    takes the force on its port, clipped to its ``force_limit``, and ticks once.

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts or str or path-like
        A scene with several ports (``devices:``; docs/ports.md), or its file.
    steps : int
        Samples to simulate, N >= 0.
    record : list of str, optional
        Masses to record, in this order (default: every mass, in file order).
    x0, v0 : dict or sequence, optional
        Each port's initial displacement [m] and velocity [m/s] (a mapping port name ->
        value, ports left out at 0, or one value per port in port order); default 0:
        the ports at rest, as a one-port scene's port without an excitation.
    progress : callable, optional
        ``progress(done, steps)`` after each stretch of samples.

    Returns
    -------
    SimulateReport
        The summary (the command's ``--json`` object) with the arrays beside it.

    Raises
    ------
    ConfigError
        A scene without several ports (key ``devices``: ``hapsim simulate SCENE`` runs a
        1-D, 2-D or 3-D one), negative ``steps``, an unknown or repeated ``record`` name,
        an unknown port or a non-finite value in ``x0``/``v0``, a trajectory too large
        for memory (key ``steps``), an invalid scene file (file, line, key).
    """
    from hapsim.lockstep_ports import LockstepPorts
    from hapsim.outputs import check_fits
    from hapsim.scene import ScenePorts, load_scene_ports
    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene_ports(scene)
    if not isinstance(scene, ScenePorts):
        raise ConfigError("hapsim.simulate takes a scene with several ports (devices:); "
                          "'hapsim simulate SCENE' runs a 1-D, 2-D or 3-D scene",
                          file=getattr(scene, "path", None), key="devices")
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ConfigError(f"must be a whole number >= 0, got {steps!r}", key="steps")
    N = int(steps)
    ports = scene.ports
    P = len(ports)
    every = [m.name for m in scene.masses]
    names = list(record) if record else list(every)
    for nm in names:
        if nm not in every:
            raise ConfigError(f"no mass named {nm!r}; masses: {', '.join(every)}",
                              key="record")
    if len(set(names)) != len(names):
        raise ConfigError("names a mass twice; each once", key="record")
    start, speed = _per_port(x0, ports, "x0"), _per_port(v0, ports, "v0")
    check_fits(8.0 * (N + 1) * (len(names) + 2 * P + 1),
               f"{N} samples x ({len(names)} masses + {P} ports' positions and forces)",
               "steps")
    loop = LockstepPorts(scene, start, speed)
    limits = np.array([float(d.force_limit) for _, d in scene.devices])
    xs, fs = np.empty((N + 1, P)), np.empty((N + 1, P))
    done, bad = 0, None
    with np.errstate(all="ignore"):          # an unstable loop's overflow: found below
        while done < N + 1:
            m = min(4096, N + 1 - done)
            xs[done:done + m] = loop.step(m, limits=limits, forces=fs[done:done + m])
            rows = np.flatnonzero(~np.isfinite(xs[done:done + m]).all(axis=1))
            if rows.size:
                k = done + int(rows[0])
                bad = {"step": k, "port": ports[int(np.flatnonzero(
                    ~np.isfinite(xs[k]))[0])]}
                break
            done += m
            if progress is not None:
                progress(min(done, N), N)
    rows = N + 1 if bad is None else bad["step"]
    fixed = {m.name: float(m.x0) for m in scene.masses if m.kind == "ground"}
    position = np.empty((rows, len(names), 1))
    for j, nm in enumerate(names):
        position[:, j, 0] = xs[:rows, ports.index(nm)] if nm in ports else fixed[nm]
    d = {"scene": scene.path, "steps": N if bad is None else bad["step"],
         "rate_hz": scene.rate_hz, "recorded": len(names), "ports": list(ports),
         "delays": [float(dv.delay) for _, dv in scene.devices],
         "x0": start.tolist(), "v0": speed.tolist(), "diverged": bad}
    return SimulateReport.from_dict(
        d, time=np.arange(rows) / scene.rate_hz, position=position,
        names=np.array(names), port_position=xs[:rows], port_force=fs[:rows],
        exit_code=0 if bad is None else 1)
