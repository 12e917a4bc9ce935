"""``simulate``: a scene run offline, in any dimension or with several ports (issue 30: the
same function and command take a 1-D, a 2-D, a 3-D and a several-port scene): the engine
with its port held (a 1-D, 2-D or 3-D scene, ``hapsim simulate``'s trajectory), or each
port closed through its own device model (several ports; docs/ports.md, 'Offline:
simulate')."""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from hapsim.errors import ConfigError
from hapsim.results import Report

__all__ = ["SimulateReport", "SimulateReportND", "SimulateReportPorts", "simulate",
           "line_columns", "run_finite"]


@dataclasses.dataclass(frozen=True)
class SimulateReport(Report):
    """What ``hapsim simulate SCENE --json`` says of a 1-D scene (without ``out`` and
    ``seconds``, the command's), with the trajectory beside it.

    Attributes
    ----------
    scene : str
    steps : int
        Samples simulated: the ones asked, or the step at which a position became
        non-finite (the rows before it kept).
    rate_hz : float
    recorded : int
        Masses recorded (R).
    calibrations : list of dict
        One per felt ``target`` link, calibrated for the scene's device first
        (:meth:`hapsim.analysis.targets.TargetCalibration.to_dict`).
    diverged : dict or None
        ``{"step", "mass", "recorded"}`` of the first non-finite position (for a mass not
        recorded, the end of the stretch it was found in), else None.

    Other attributes: ``time`` [s] (M+1,), ``position`` [m] (M+1, R), ``names`` (list
    of R str), ``exit_code`` (0, or 1 when diverged).
    """

    scene: str
    steps: int
    rate_hz: float
    recorded: int
    calibrations: list
    diverged: dict | None


@dataclasses.dataclass(frozen=True)
class SimulateReportND(Report):
    """What ``hapsim simulate SCENE --json`` says of a 2-D or 3-D scene (without ``out``
    and ``seconds``), with the trajectory beside it.

    Attributes
    ----------
    scene : str
    dimension : int
        2 or 3 (n).
    steps : int
        Samples simulated (as :class:`SimulateReport`'s).
    rate_hz : float
    recorded : int
    diverged : dict or None
        ``{"step"}``: the first step at which a position is not finite, else None.

    Other attributes: ``time`` [s] (M+1,), ``position`` [m] (M+1, R, n), ``names``
    (list of R str), ``exit_code``.
    """

    scene: str
    dimension: int
    steps: int
    rate_hz: float
    recorded: int
    diverged: dict | None


@dataclasses.dataclass(frozen=True)
class SimulateReportPorts(Report):
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
    ``position`` [m] shape (M+1, R, 1), ``names`` (list of R str), ``port_position`` [m] and
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


def simulate(scene, steps: int, *, record=None, x0=None, v0=None, progress=None):
    """Run a scene offline (``hapsim simulate SCENE``), in the dimension it declares or
    with several ports.

    A 1-D scene: its felt targets calibrated for its device first (as ``hapsim run``
    does), the engine run with the port (if any) held at the excitation's ``x0`` (no
    device is simulated). A 2-D or 3-D scene: the engine run with the port (if any) held
    at its rest position. A scene with several ports: each port closed through its own
    device, below.

    The several ports' loop is the lockstep run's (:class:`hapsim.lockstep_ports.LockstepPorts`, the
    model ``hapsim run SCENE --lockstep`` measures): each sample every port is at its
    device's sample, the links' forces follow the scheme's law
    (docs/design.md, 'The scheme'), and each device (:class:`hapsim.lockstep_ports.PortDevice`: ``m x'' + b0
    x' = u``, its exact zero-order hold, its own delay line, a real number of periods)
    takes the force on its port, clipped to its ``force_limit``, and ticks once.

    Parameters
    ----------
    scene : hapsim.scene.Scene, SceneND or ScenePorts, or str or path-like
        A scene (docs/scenes.md, docs/dimensions.md, docs/ports.md), or its file.
    steps : int
        Samples to simulate, N >= 0.
    record : list of str, optional
        Masses to record, in this order (default: every mass, in file order).
    x0, v0 : dict or sequence, optional
        Several ports only: each port's initial displacement [m] and velocity [m/s] (a
        mapping port name -> value, ports left out at 0, or one value per port in port
        order); default 0: the ports at rest, as a one-port scene's port without an
        excitation.
    progress : callable, optional
        ``progress(done, steps)`` after each stretch of samples.

    Returns
    -------
    SimulateReport, SimulateReportND or SimulateReportPorts
        The summary (the command's ``--json`` object but its ``out`` and ``seconds``)
        with the arrays beside it; ``exit_code`` 1 when a position became non-finite.

    Raises
    ------
    ConfigError
        Negative ``steps``, an unknown or repeated ``record`` name, ``x0``/``v0`` for a
        scene without several ports or naming no port, a value that is not a finite
        number, a trajectory too large for memory (key ``steps``), a ``progress`` that is
        no function, an invalid scene file (file, line, key).
    UnrenderableTargetError
        A 1-D felt target no (K, B) renders (key ``links.NAME.target``).
    """
    from hapsim.api.common import load_scene
    from hapsim.scene import SceneND, ScenePorts
    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ConfigError(f"must be a whole number >= 0, got {steps!r}", key="steps")
    if progress is not None and not callable(progress):     # (was a TypeError mid-run)
        raise ConfigError(f"must be a function progress(done, steps), got {progress!r}",
                          key="progress")
    if isinstance(scene, ScenePorts):
        return _simulate_ports(scene, int(steps), record, x0, v0, progress)
    for key, given in (("x0", x0), ("v0", v0)):
        if given is not None:
            raise ConfigError(f"names a port of a scene with several ports (devices:); a "
                              f"one-port, 2-D or 3-D scene's port starts at its "
                              f"excitation's {key} (the scene file)", key=key)
    if isinstance(scene, SceneND):
        return _simulate_nd(scene, int(steps), record, progress)
    return _simulate_line(scene, int(steps), record, progress)


def _recorded(every: list, record) -> list:
    """The masses to record: ``record`` (each a mass of ``every``, once) or, when None or
    empty, every mass in file order (key ``record`` in the errors)."""
    names = list(record) if record else list(every)
    for nm in names:
        if nm not in every:
            raise ConfigError(f"no mass named {nm!r}; masses: {', '.join(every)}",
                              key="record")
    if len(set(names)) != len(names):
        raise ConfigError("names a mass twice; each once", key="record")
    return names


def _simulate_ports(scene, N: int, record, x0, v0, progress) -> SimulateReportPorts:
    """:func:`simulate` of a scene with several ports (its notes)."""
    from hapsim.lockstep_ports import LockstepPorts
    from hapsim.outputs import check_fits
    ports = scene.ports
    P = len(ports)
    names = _recorded([m.name for m in scene.masses], record)
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
    return SimulateReportPorts.from_dict(
        d, time=np.arange(rows) / scene.rate_hz, position=position,
        names=names, port_position=xs[:rows], port_force=fs[:rows],
        exit_code=0 if bad is None else 1)


def _noop(done: int, total: int | None = None) -> None:
    """A progress callback that says nothing."""


def line_columns(scene, N: int, record, keys=("record", "steps")):
    """A 1-D scene with its felt targets calibrated and the masses a run of ``N`` samples
    records, checked before the engine is compiled (:func:`simulate`, ``hapsim simulate``).

    Parameters
    ----------
    scene : hapsim.scene.Scene
    N : int
        Samples to record.
    record : sequence of str or None
        Masses to record, in order (None or empty: every mass of the scene).
    keys : (str, str), optional
        The keys the errors name for ``record`` and ``N``.

    Returns
    -------
    (hapsim.scene.Scene, list, list of str)
        The scene with (K, B) for its targets (:func:`hapsim.api.checking.board_scene`:
        for the loop its board runs, where the device names one), its calibrations and
        the recorded masses.

    Raises
    ------
    ConfigError
        An unknown or repeated name; time and positions, (N + 1) x (R + 1) float64, too
        large for memory.
    UnrenderableTargetError
        A felt target no (K, B) renders.
    """
    from hapsim.outputs import check_fits
    calibrations = []
    if scene.unresolved_targets:
        # felt targets into (K, B) as hapsim run and check take them: for the loop the
        # board the device.protocol names runs (its rate, its render latency)
        from hapsim.api.checking import board_scene
        scene, calibrations, _, _ = board_scene(scene)
    masses = tuple(m.name for m in scene.masses)
    names = list(record) if record else list(masses)
    from hapsim.engine import mass_indices     # numba: after the input's checks
    mass_indices(masses, names, key=keys[0])
    if len(set(names)) != len(names):
        twice = sorted({n for n in names if names.count(n) > 1})
        raise ConfigError(f"names a mass twice: {', '.join(twice)}; each column once",
                          key=keys[0])
    check_fits(8.0 * (N + 1) * (len(names) + 1),
               f"{N} samples x {len(names)} masses of positions", keys[1])
    return scene, calibrations, names


def _simulate_line(scene, N: int, record, progress) -> SimulateReport:
    """:func:`simulate` of a 1-D scene: targets calibrated, the port held at the
    excitation's ``x0``, :func:`run_finite`."""
    scene, calibrations, names = line_columns(scene, N, record)
    from hapsim.engine import Engine
    engine = Engine(scene)
    if scene.port is not None:
        engine.set_port_position(scene.excitation.x0, at_rest=True)
    t, x, bad = run_finite(engine, N, names, progress or _noop)
    diverged = (None if bad is None
                else {"step": bad[0], "mass": bad[1], "recorded": bad[2]})
    d = {"scene": scene.path, "steps": N if bad is None else bad[0],
         "rate_hz": scene.rate_hz, "recorded": len(names),
         "calibrations": [c.to_dict() for c in calibrations], "diverged": diverged}
    return SimulateReport.from_dict(d, time=t, position=x, names=names,
                                    calibrated=calibrations, engine=engine,
                                    exit_code=0 if bad is None else 1)


def _simulate_nd(scene, N: int, record, progress) -> SimulateReportND:
    """:func:`simulate` of a 2-D or 3-D scene: the port (if any) held at its rest
    position, every step; stopped at the first non-finite position."""
    from hapsim.engine import Engine
    from hapsim.outputs import check_fits
    engine = Engine(scene)
    names = _recorded(list(engine.names), record)
    idx = np.array([engine.names.index(nm) for nm in names], dtype=np.int64)
    n = scene.dimension
    check_fits(8.0 * (N + 1) * (len(names) * n + 1),
               f"{N} samples x {len(names)} masses x {n} axes", "steps")
    pos = np.empty((N + 1, len(names), n))
    pos[0] = engine.x[:, idx].T
    rest = None if engine.port is None else engine.x[:, engine.port].copy()
    bad = None
    progress = progress or _noop
    for k in range(1, N + 1):
        if rest is not None:
            engine.set_port_position(rest)
        engine.step()
        pos[k] = engine.x[:, idx].T
        if not np.all(np.isfinite(engine.x)):
            bad = k
            break
        if k % 4096 == 0:
            progress(k, N)
    rows = N + 1 if bad is None else bad
    d = {"scene": scene.path, "dimension": n, "steps": N if bad is None else bad,
         "rate_hz": scene.rate_hz, "recorded": len(names),
         "diverged": None if bad is None else {"step": bad}}
    return SimulateReportND.from_dict(d, time=np.arange(rows) / scene.rate_hz,
                                      position=pos[:rows], names=names, engine=engine,
                                      exit_code=0 if bad is None else 1)


def run_finite(engine, steps: int, names: list, progress,
               chunk: int = 65536) -> tuple:
    """Run a 1-D engine ``steps`` samples in chunks, stopping at the first non-finite
    position.

    Parameters
    ----------
    engine : hapsim.engine.Engine
        The engine, at its initial state.
    steps : int
        Samples to run, >= 0.
    names : list of str
        Masses to record (R of them).
    progress : callable
        ``progress(done, steps)`` after each chunk.
    chunk : int
        Samples per engine call.

    Returns
    -------
    time : ndarray, shape (M+1,)
        Time [s]; M = steps, or the last finite step when the scene diverged.
    position : ndarray, shape (M+1, R)
        Positions [m], all finite.
    bad : (int, str, bool) or None
        ``(step, mass, recorded)`` of the first non-finite position (any mass of the scene;
        for a mass not recorded the step is the end of the chunk it was found in), or None.
    """
    t = np.empty(steps + 1)
    x = np.empty((steps + 1, len(names)))
    t[0:1], x[0:1] = engine.run(0, names)
    done = 0
    all_names = list(engine.names)
    while done < steps:
        m = min(chunk, steps - done)
        tc, xc = engine.run(m, names)
        t[done + 1:done + m + 1], x[done + 1:done + m + 1] = tc[1:], xc[1:]
        state = engine.x[0]
        if not (np.isfinite(xc).all() and np.isfinite(state).all()):
            rows = np.flatnonzero(~np.isfinite(xc[1:]).all(axis=1))
            if rows.size:
                step = done + 1 + int(rows[0])
                col = int(np.flatnonzero(~np.isfinite(xc[1 + rows[0]]))[0])
                mass = names[col]
            else:  # an unrecorded mass went first: name it, at the chunk's end
                step = done + m
                mass = all_names[int(np.flatnonzero(~np.isfinite(state))[0])]
                return t[:step], x[:step], (step, mass, False)
            return t[:step], x[:step], (step, mass, True)
        done += m
        progress(done, steps)
    return t, x, None
