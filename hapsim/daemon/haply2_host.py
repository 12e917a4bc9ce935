"""The Haply 2DIY in real time: the host loop on its own clock against a board behind a
port (the emulated board in a child process on a pseudo-terminal, :class:`Embedded2DIY`,
as the 1-DoF Haply mock runs; or a real board).

The board answers each write with the angles after one period (firmware V1.5 has no
clock of its own: each write is one period of its plant, as
:class:`hapsim.daemon.haply2_board.Haply2DIYBoard` and the 1-DoF
:class:`hapsim.driver_mock.HaplyDevice` model it). The host ticks every ``T``: at tick
``k`` the sample is the reply to write ``k`` (write 0 is the arming's zero write; replies
come in order, one per write, and none is lost on a clean stream, so the ``i``-th reply
answers write ``i``). A reply not read by tick ``k`` is a *missing reply*: the tick is an
*estimated sample* (counted, as the 1-DoF driver loop counts its ``FLAG_ESTIMATED``
rows), its position extrapolated from the last two readings,
``x_e = x[i] + r (x[i] - x[i-1])`` with ``r = k - i`` (:func:`estimate_bounds` bounds
its error), the engine's force computed from it and its torques written; the reply
counts when it comes, but never replaces the estimate the engine used (the record
holds what the loop saw). The records' verdict is
:func:`hapsim.daemon.haply2_board.felt_verdict_of_runs`: the estimated rows' bounds
enter the wire's term through the loop as reading errors do.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time

import numpy as np

from hapsim.daemon.haply2_board import Haply2DIYBoard, felt_verdict_of_runs
from hapsim.drivers.haply2 import Haply2DIY
from hapsim.errors import ConfigError, DeviceError
from hapsim.spawn import PtyChild

__all__ = ["Embedded2DIY", "estimate_bounds", "record_realtime", "measure_felt_haply2_port",
           "main"]

#: Longest wait for the first reply after a set-up [s] (a board process just started
#: loads its compiled plant first).
ARM_TIMEOUT = 10.0
#: Silence that ends the draining before a set-up [s].
QUIET_S = 0.03
#: How long before a tick's deadline the host stops sleeping and polls [s].
SPIN_S = 3e-4


def estimate_bounds(rec: dict, scene, J, delta) -> np.ndarray:
    """The largest error of each estimated row's position, per axis [m].

    An estimate ``r`` periods after the last reading ``x[i]`` is
    ``x[i] + r (x[i] - x[i-1])``; with ``x = p + eps`` (``p`` the handle's position,
    ``|eps_a| <= sum_j |J_aj| delta_j`` on axis ``a``: the readings' rounding through the
    Jacobian at rest), its error is the linear extrapolation's, at most
    ``r (r + 1) / 2 T^2 a_max`` by Taylor's theorem, plus ``(1 + r) eps[i] - r eps[i-1]``,
    at most ``(2 r + 1) eps`` (as the 1-DoF
    :func:`hapsim.analysis.measurement.estimated_bounds`). The handle's acceleration is at
    most ``a_max = (max |F| + b_max v_max) / m_min`` over the record: ``F = J^-T tau`` the
    force of the torques written, ``m_min`` and ``b_max`` the extreme eigenvalues of the
    Cartesian mass and friction at rest, ``v_max`` the largest step between consecutive
    readings over ``T`` plus ``2 eps / T`` (every reading, the replies read late too; no
    hand on the handle in a free response; the velocity-product terms, second order in
    the amplitude, are left out). A *hold* (only reply 0 read, ``r = k``: no
    extrapolation yet, the estimate is ``x[0]``) is wrong by the motion since ``t_0``,
    at most ``r T (v_max + T a_max / 2) + (r T)^2 / 2 a_max + eps`` (Taylor's theorem,
    ``|v(t_0)|`` bounded by the first period's mean velocity plus ``T a_max / 2``).

    Parameters
    ----------
    rec : dict
        :func:`record_realtime`'s record: ``position`` (N, 2) [m], ``torque`` (N, 2)
        [N m], ``estimated`` (N,) bool, ``lag`` (N,) int (``r``), optionally
        ``readings`` (N, 2) [m] (every reply's reading, NaN where none came).
    scene : hapsim.scene_nd.SceneND
    J : ndarray, shape (2, 2)
        The Jacobian at rest [m/rad].
    delta : array_like, shape (2,)
        The readings' rounding per joint [rad].

    Returns
    -------
    ndarray, shape (N, 2)
        0 on the rows read.
    """
    est = np.asarray(rec["estimated"], bool)
    x = np.asarray(rec["position"], float)
    out = np.zeros_like(x)
    if not est.any():
        return out
    T = scene.period
    eps = np.abs(J) @ np.asarray(delta, float)
    F = np.abs(np.linalg.solve(J.T, np.asarray(rec["torque"], float).T).T)
    # every reading, the late ones too (they hold the steps over the estimated ticks)
    xs = np.asarray(rec.get("readings", np.where(est[:, None], np.nan, x)), float)
    steps = np.diff(xs, axis=0)
    steps = steps[np.isfinite(steps).all(axis=1)]
    v = (float(np.max(np.linalg.norm(steps, axis=1))) if steps.size else 0.0) / T \
        + 2 * float(np.linalg.norm(eps)) / T
    m_min = float(np.min(np.linalg.eigvalsh(scene.device.mass)))
    b_max = float(np.max(np.abs(np.linalg.eigvalsh(
        0.5 * (scene.device.friction + scene.device.friction.T)))))
    a_max = (float(np.max(np.linalg.norm(F, axis=1))) + b_max * v) / m_min
    lag = np.asarray(rec["lag"], np.int64)
    r = lag[est].astype(float)
    ext = (r * (r + 1) / 2 * T * T * a_max)[:, None] + (2 * r + 1)[:, None] * eps
    # a hold (only reply 0 read: lag == k) is x[0]: its error is the motion since t_0,
    # r T |v(t_0)| + (r T)^2 / 2 a_max, plus eps; |v(t_0)| <= v + T a_max / 2 (the
    # mean velocity over the first period, within v, and Taylor's theorem)
    hold = (lag == np.arange(len(lag)))[est]
    held = (r * T * (v + T * a_max / 2) + (r * T) ** 2 / 2 * a_max)[:, None] + eps
    out[est] = np.where(hold[:, None], held, ext)
    return out


def _read(ser) -> bytes:
    try:
        n = ser.in_waiting
        return ser.read(n) if n else b""
    except Exception as exc:  # serial.SerialException, OSError
        raise DeviceError(f"read from the 2DIY's port failed: {exc}") from None


def _write(ser, data: bytes) -> None:
    try:
        ser.write(data)
    except Exception as exc:  # serial.SerialException, OSError, timeouts
        raise DeviceError(f"write to the 2DIY's port failed: {exc}") from None


def record_realtime(ser, driver: Haply2DIY, scene, samples: int, *, engine=None) -> dict:
    """One record in real time: arm (the set-up, whose hand starts the record), then one
    write per tick of the host's clock (module notes).

    Parameters
    ----------
    ser : serial.Serial
        The board's port (non-blocking reads).
    driver : hapsim.drivers.haply2.Haply2DIY
    scene : hapsim.scene_nd.SceneND
        A 2-D pantograph scene (its rate is the clock's).
    samples : int
        Ticks ``N``.
    engine : hapsim.engine_nd.EngineND, optional
        A fresh engine (default: one of ``scene``).

    Returns
    -------
    dict
        ``position`` (N, 2) [m] (the readings, or the estimates the engine used),
        ``joints`` (N, 2) [rad] read (NaN where estimated), ``torque`` (N, 2) [N m]
        written, ``estimated`` (N,) bool, ``lag`` (N,) int (ticks since the last reading
        where estimated), ``late_ticks`` (ticks the host itself began more than a period
        late), ``replies`` (replies to the record's writes, read by its end: all of them
        on a clean stream), ``writes``, ``readings`` (N, 2) [m] (reply ``k``'s reading,
        read in time or late; NaN where it never came).

    Raises
    ------
    DeviceError
        No first reply after the set-up within :data:`ARM_TIMEOUT`; a first reply that
        does not read the offsets sent; bytes that make no reply (the stream is not
        clean: this loop does not re-synchronise a board); the port failing.
    """
    from hapsim.engine_nd import EngineND
    from hapsim.kinematics import device
    dev = scene.device
    kin = device(dev.kind, dev.geometry)
    q0deg = [math.degrees(v) for v in dev.joints]
    N = int(samples)
    T = scene.period
    dec = driver.decoder()
    eng = EngineND(scene) if engine is None else engine
    port = eng.port
    xr = np.full((N + 2, 2), np.nan)                # reading of reply i (answer to write i)
    qr = np.full((N + 2, 2), np.nan)
    got = 0

    def take(data):
        nonlocal got
        for rep in dec.feed(data):
            if got < xr.shape[0]:
                q = np.asarray(driver.joints_of(rep))
                qr[got] = q
                xr[got] = kin.forward(q)
            got += 1
    # the arming: zero torque and the re-synchronising bytes, whose answer (the zero
    # write's, from before the set-up) is dropped with what an earlier record left; then
    # the set-up and a zero write, whose reply is tick 0's sample
    arm = driver.arm_bytes(q0deg)
    zero = driver.write_bytes((0.0, 0.0))
    _write(ser, arm[:-len(zero)])
    end = time.monotonic() + ARM_TIMEOUT
    quiet = math.inf                                # the board answers a write: wait for it
    while time.monotonic() < min(end, quiet):
        if _read(ser):
            quiet = time.monotonic() + QUIET_S
        time.sleep(1e-3)
    _write(ser, zero)
    end = time.monotonic() + ARM_TIMEOUT
    while got == 0 and time.monotonic() < end:
        take(_read(ser))
        if got == 0:
            time.sleep(2e-4)
    if got == 0:
        raise DeviceError("no reply from the 2DIY after its set-up")
    if got > 1 or np.max(np.abs(np.degrees(qr[0]) - q0deg)) > dec.max_step:
        raise DeviceError("the 2DIY's first reply does not read the offsets sent: the "
                          "stream corrupted its set-up")
    pos = np.zeros((N, 2))
    joints = np.full((N, 2), np.nan)
    torque = np.zeros((N, 2))
    est = np.zeros(N, bool)
    lag = np.zeros(N, np.int64)
    late = 0
    t0 = time.perf_counter()
    for k in range(N):
        deadline = t0 + k * T
        now = time.perf_counter()
        if now > deadline + T:
            late += 1
        elif deadline - now > SPIN_S:
            time.sleep(deadline - now - SPIN_S)
        while time.perf_counter() < deadline:
            pass
        take(_read(ser))
        if got > k:                                 # reply k read: a fresh sample
            x, q = xr[k], qr[k]
            joints[k] = q
        else:                                       # missing: an estimated sample
            i = got - 1
            x = xr[i] + (k - i) * (xr[i] - xr[i - 1]) if i >= 1 else xr[i]
            q = qr[i]
            est[k] = True
            lag[k] = k - i
        if k == 0:
            eng.x[:, port] = x
            eng.xp[:, port] = x
        eng.set_port_position(x)
        eng.step()
        tau = kin.jacobian(q).T @ eng.port_force
        torque[k] = driver.clamp(tau)
        pos[k] = x
        _write(ser, driver.write_bytes(tau))
    _write(ser, driver.write_bytes((0.0, 0.0)))     # zero torque (no watchdog)
    end = time.monotonic() + 0.2
    while got < N + 2 and time.monotonic() < end:   # the late replies, counted
        take(_read(ser))
        time.sleep(1e-3)
    if dec.stats["skipped"]:
        raise DeviceError(f"{dec.stats['skipped']} bytes made no reply: the stream is not "
                          "clean (the real-time 2DIY loop does not re-synchronise a board)")
    return {"position": pos, "joints": joints, "torque": torque, "estimated": est,
            "lag": lag, "late_ticks": late, "replies": got, "writes": N + 2,
            "readings": xr[:N].copy()}


def measure_felt_haply2_port(port: str, scene, generation: str = "gen3", *,
                             amplitude: float, resolution: float | None = None,
                             samples: int | None = None, progress=None, plan=None) -> dict:
    """The felt matrices of a pantograph scene measured through a 2DIY in real time, and
    their verdict (module notes).

    Parameters
    ----------
    port : str or serial-like
        The board's serial port (or :class:`Embedded2DIY`'s pty), or an open object with
        ``in_waiting``, ``read``, ``write`` (left open).
    scene : hapsim.scene_nd.SceneND
        A 2-D pantograph scene.
    generation : {"gen2", "gen3"}
    amplitude : float
        The hand's ``a`` [m] (the board's: the linearisation bound is stated at it).
    resolution : float, optional
        The set-up's counts per revolution (default the generation's).
    samples : int, optional
        Ticks per record (default :func:`hapsim.lockstep_nd.default_samples`).
    progress : callable, optional
    plan : tuple, optional
        :func:`hapsim.lockstep_nd.identification_plan`, already computed.

    Returns
    -------
    dict
        :func:`hapsim.daemon.haply2_board.felt_verdict_of_runs`'s, with ``estimated``
        (estimated samples per record), ``late_ticks`` (per record) and ``replies``
        (replies read per record, of ``writes``).

    Raises
    ------
    DeviceError
        As :func:`record_realtime`; the port cannot be opened.
    ConfigError
        Not a 2-D pantograph scene.
    """
    import serial

    from hapsim.kinematics import device
    from hapsim.lockstep_nd import identification_plan
    if scene.dimension != 2 or scene.device is None or scene.device.kind != "pantograph":
        raise ConfigError("the Haply 2DIY drives a 2-D scene with a pantograph device",
                          file=scene.path, key="device.kind")
    chk, order, N = identification_plan(scene, samples) if plan is None else plan
    drv = Haply2DIY(generation, resolution=resolution)
    own = isinstance(port, str)
    try:
        ser = (serial.serial_for_url(port, baudrate=115200, timeout=0, write_timeout=1.0)
               if own else port)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceError(f"cannot open port {port}: {exc}") from None
    from hapsim.engine_nd import EngineND
    EngineND(scene).step()               # the compiled kernels loaded before the clock
    runs = []
    try:
        for j in range(5):
            runs.append(record_realtime(ser, drv, scene, N))
            if progress is not None:
                progress(j + 1, 5)
    finally:
        if own:
            try:
                ser.write(drv.write_bytes((0.0, 0.0)))
                ser.flush()
            except Exception:  # best effort: the port may be gone
                pass
            ser.close()
    J = device("pantograph", scene.device.geometry).jacobian(scene.device.joints)
    ang = np.max([np.nanmax(np.abs(r["joints"]), axis=0) for r in runs], axis=0)
    delta = math.pi / drv.resolution + np.radians(
        np.spacing(np.float32(np.degrees(ang))).astype(float))
    for r in runs:
        if r["estimated"].any():
            r["bounds"] = estimate_bounds(r, scene, J, delta)
    out = felt_verdict_of_runs(scene, runs, (chk, order, N), drv.resolution, amplitude)
    out.update(estimated=[int(r["estimated"].sum()) for r in runs],
               late_ticks=[r["late_ticks"] for r in runs],
               replies=[r["replies"] for r in runs], writes=[r["writes"] for r in runs])
    return out


class Embedded2DIY(PtyChild):
    """The emulated 2DIY board (:class:`hapsim.daemon.haply2_board.Haply2DIYBoard`) in a
    child process on the master side of a new pty, served by
    :func:`hapsim.driver_mock.serve` (one period per write, replies at once).

    Parameters
    ----------
    scene_path : str
        The 2-D pantograph scene's file.
    generation : {"gen2", "gen3"}
    amplitude : float
        The hand's ``a`` [m].
    cpr : float, optional
        The emulated encoders' counts per revolution (default the generation's).
    slow_every : int, optional
        Every ``slow_every``-th write's reply waits ``slow_s`` [s] (a slow board; 0: none).
    slow_s : float, optional
    rate_hz : float, optional
        The loop's rate [Hz] (default the scene file's): the plant's period.

    Attributes
    ----------
    port : str
        The slave path to open.
    """

    def __init__(self, scene_path: str, generation: str = "gen3", *, amplitude: float,
                 cpr: float | None = None, slow_every: int = 0, slow_s: float = 0.0,
                 rate_hz: float | None = None) -> None:
        master = self.open_pty("hapsim-2diy-")
        self.start([sys.executable, "-m", "hapsim.daemon.haply2_host", "--fd", str(master),
                    "--scene", str(scene_path), "--generation", generation, "--amplitude",
                    repr(float(amplitude)), "--cpr", repr(float(cpr or 0.0)), "--report",
                    self.report_path, "--slow-every", str(int(slow_every)), "--slow-s",
                    repr(float(slow_s)), "--rate", repr(float(rate_hz or 0.0))], master)


class _SlowBoard(Haply2DIYBoard):
    """A board whose every ``slow_every``-th reply waits ``slow_s`` [s] (what
    :func:`hapsim.driver_mock.serve` reads as ``reply_delay_s`` after each write)."""

    slow_every = 0
    slow_s = 0.0

    @property
    def reply_delay_s(self) -> float:
        k = self.slow_every
        return self.slow_s if k and self.writes and self.writes % k == 0 else 0.0


def main(argv=None) -> int:
    """Child-process entry: ``python -m hapsim.daemon.haply2_host --fd N --scene PATH
    --generation G --amplitude A [--cpr C] [--report FILE]``: serve the emulated board
    until the host closes the port or SIGTERM; the serving report as JSON."""
    import argparse
    import signal

    from hapsim.driver_mock import serve
    from hapsim.scene_nd import load_scene_nd
    p = argparse.ArgumentParser(prog="hapsim.daemon.haply2_host")
    p.add_argument("--fd", type=int, required=True)
    p.add_argument("--scene", required=True)
    p.add_argument("--generation", default="gen3")
    p.add_argument("--amplitude", type=float, required=True)
    p.add_argument("--cpr", type=float, default=0.0)
    p.add_argument("--report")
    p.add_argument("--slow-every", type=int, default=0)
    p.add_argument("--slow-s", type=float, default=0.0)
    p.add_argument("--rate", type=float, default=0.0)
    a = p.parse_args(argv)
    scene = load_scene_nd(a.scene)
    if a.rate:
        import dataclasses
        scene = dataclasses.replace(scene, rate_hz=a.rate)
    board = _SlowBoard(scene, a.generation, cpr=a.cpr or None, amplitude=a.amplitude)
    board.slow_every, board.slow_s = a.slow_every, a.slow_s
    flag = {"stop": False}
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: flag.__setitem__("stop", True))
    rep = serve(a.fd, board, stop=lambda: flag["stop"])
    if a.report:
        with open(a.report + ".partial", "w") as fh:
            json.dump(rep, fh)
        os.replace(a.report + ".partial", a.report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
