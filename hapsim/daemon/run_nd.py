"""The felt matrices of a 2-D or 3-D scene measured over a port, in real time.

The host side of :mod:`hapsim.daemon.mock_nd`'s device (or any framed-protocol device with
``n_axes = n`` whose hand lets the handle go from the identification starts at each
CONFIG): HELLO asked and checked (version, ``n_axes``), then ``2n + 1`` records, each a
CONFIG, ``N`` STATEs answered by the n-D engine's FORCE, and a STOP. Every STATE is
answered as it comes (the device keeps the clock); a FORCE that misses its tick leaves the
device holding the one before (a *late* tick) and its STATE says so: ``force_seq`` names
the FORCE held over every period (``firmware_protocol/PROTOCOL.md`` §4).

Late ticks are handled as in 1-D (:mod:`hapsim.applied`), per axis: the account of the
force applied over every period (:func:`hapsim.applied.account_from_force_seq` on each
axis's column; the rows it names are the same on every axis), the known disturbance
``w[k] = applied[k] - F[k - d]`` (an n-vector), and its response through the predicted
closed loop, ``x_w[k] = sum_{j<k} C A^(k-1-j) B_w w[j]`` (:func:`disturbance_response_nd`:
``A`` of :func:`hapsim.analysis.scene_nd_check.closed_loop_nd`, ``B_w`` the device's ZOH
input, ``C`` the device position), subtracted from the record (superposition of a linear
loop driven by a known input). The records minus the record from rest are then free
responses, fitted as in lockstep (:func:`hapsim.analysis.identify_nd.fit_felt_nd`).
"""

from __future__ import annotations

import time

import numpy as np

import firmware_protocol as fp
from hapsim.applied import account_from_force_seq
from hapsim.errors import DeviceError, ProtocolError

__all__ = ["RecordND", "measure_felt_port", "disturbance_response_nd", "handshake_nd"]

#: CONFIG's force limit [N]: the scene's device has none (finite, as CONFIG requires).
FORCE_LIMIT = 1e9
#: STATEs of a record that may be lost (a gap in seq) before the record is run again.
RETRIES = 3


class RecordND:
    """One record of an n-D run over a port.

    Attributes
    ----------
    seq, status, force_seq : ndarray of int64, shape (N,)
        The STATEs' fields.
    position : ndarray, shape (N, n)
        Handle position of each STATE [m].
    force : ndarray, shape (N, n)
        Force sent answering each STATE [N].
    """

    def __init__(self, N: int, n: int) -> None:
        self.seq = np.zeros(N, np.int64)
        self.status = np.zeros(N, np.int64)
        self.force_seq = np.zeros(N, np.int64)
        self.position = np.zeros((N, n))
        self.force = np.zeros((N, n))


def handshake_nd(transport, n: int, timeout: float = 1.0) -> fp.Hello:
    """Ask the device's HELLO and check it speaks version 1 with ``n`` axes.

    Parameters
    ----------
    transport : transport of :mod:`hapsim.daemon.transport`
    n : int
        Axes the scene has.
    timeout : float
        Wait per request [s] (3 requests).

    Returns
    -------
    firmware_protocol.Hello

    Raises
    ------
    DeviceError
        No HELLO after 3 requests.
    ProtocolError
        Another protocol version or another number of axes.
    """
    for _ in range(3):
        transport.send(fp.HelloRequest(fp.PROTOCOL_VERSION))
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in transport.receive(0.02):
                if isinstance(m, fp.Hello):
                    if m.protocol_version != fp.PROTOCOL_VERSION:
                        raise ProtocolError(f"device speaks protocol version "
                                            f"{m.protocol_version}, hapsim "
                                            f"{fp.PROTOCOL_VERSION}")
                    if m.n_axes != n:
                        raise ProtocolError(f"device has {m.n_axes} axes, the scene "
                                            f"{n} (dimension)")
                    return m
    raise DeviceError("no HELLO from the device after 3 requests\nlast frames:\n"
                      + transport.last_frames())


def _drain(transport, quiet: float = 0.03, limit: float = 1.0) -> None:
    """Read and drop until nothing but disarmed STATEs came for ``quiet`` seconds (at most
    ``limit``): a device sends STATE every tick, armed or not (``PROTOCOL.md`` §5.1: the
    Hapkit firmware does), so a disarmed device is never silent."""
    now = time.monotonic()
    end = now + limit
    last = now
    while now < end:
        for m in transport.receive(quiet):
            if not (isinstance(m, fp.State) and not m.status & fp.STATUS_ARMED):
                last = time.monotonic()
        now = time.monotonic()
        if now - last >= quiet:
            return


def _record(transport, scene, N: int, rate_hz: float, watchdog_us: int) -> RecordND | None:
    """One CONFIG, N STATEs answered, STOP; None when a STATE was lost (a seq gap)."""
    from hapsim.engine_nd import EngineND
    n = scene.dimension
    rec = RecordND(N, n)
    eng = EngineND(scene)
    port = eng.port
    # per sample no array is made (the real-time rule): the position goes into a reused
    # buffer, the force is read from the engine's own (a view made once)
    pos = np.zeros(n)
    F = eng.port_f[:n]
    items = _items(n)
    transport.send(fp.Config(rate_hz, watchdog_us, FORCE_LIMIT))
    k = 0
    deadline = time.monotonic() + 5.0 + 3.0 * N / rate_hz
    ok = True
    while k < N:
        if time.monotonic() > deadline:
            transport.send(fp.Stop())
            raise DeviceError(f"the device sent {k} of {N} STATEs in time\nlast frames:\n"
                              + transport.last_frames())
        for m in transport.receive(0.05):
            if isinstance(m, fp.Fault):
                transport.send(fp.Stop())
                raise DeviceError(f"the device sent FAULT code {m.code} detail {m.detail}")
            if not isinstance(m, fp.State) or k >= N:
                continue
            if not m.status & fp.STATUS_ARMED or len(m.position) != n:
                continue
            if m.seq != k:
                if k == 0:          # a STATE of an earlier session
                    continue
                ok = False
                k = N
                break
            mp = m.position
            for a in range(n):
                pos[a] = mp[a]
            if k == 0:                       # the port starts where the handle is, at rest
                eng.x[:, port] = pos
                eng.xp[:, port] = pos
            eng.set_port_position(pos)
            eng.step()
            transport.send(fp.Force(m.seq, items(F)))
            rec.seq[k], rec.status[k], rec.force_seq[k] = m.seq, m.status, m.force_seq
            rp, rf = rec.position, rec.force
            for a in range(n):
                rp[k, a] = pos[a]
                rf[k, a] = F[a]
            k += 1
    transport.send(fp.Stop())
    _drain(transport)
    return rec if ok else None


def _items(n: int):
    """A function ``v -> (v[0], ..., v[n-1])`` as floats (1 <= n <= 3) that makes no
    array (a FORCE's values, per sample)."""
    if n == 1:
        return lambda v: (v.item(0),)
    if n == 2:
        return lambda v: (v.item(0), v.item(1))
    return lambda v: (v.item(0), v.item(1), v.item(2))


def disturbance_response_nd(scene, W, *, A=None) -> np.ndarray:
    """Device-position response of the closed loop to a known force disturbance.

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene with a port and a device.
    W : array_like, shape (N, n)
        ``w[k]``: force applied over period ``k`` minus the on-time loop's ``F[k - d]`` [N].
    A : ndarray, optional
        :func:`hapsim.analysis.scene_nd_check.closed_loop_nd`'s matrix (computed when None).

    Returns
    -------
    ndarray, shape (N, n)
        ``x_w[k] = sum_{j<k} C A^(k-1-j) B_w w[j]`` [m], ``B_w`` the ZOH input of the
        device (the first ``2n`` rows of the state, :func:`hapsim.analysis.ths_nd.zoh_matrices`)
        and ``C`` the device position (superposition, as the 1-D
        :func:`hapsim.analysis.error_response.disturbance_response`).

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.scene_nd_check.closed_loop_nd`.
    """
    from hapsim.analysis.scene_nd_check import closed_loop_nd
    from hapsim.analysis.ths_nd import LoopModelND, zoh_matrices
    W = np.asarray(W, float)
    n = scene.dimension
    if A is None:
        A = closed_loop_nd(scene)[0]
    dev = scene.device
    _, Bd = zoh_matrices(LoopModelND(mass=dev.mass, friction=dev.friction,
                                     rate_hz=scene.rate_hz, delay=dev.delay))
    out = np.zeros_like(W)
    nz = np.flatnonzero(np.any(W != 0, axis=1))
    if nz.size == 0:
        return out
    s = np.zeros(A.shape[0])
    for k in range(int(nz[0]), W.shape[0]):
        out[k] = s[:n]
        s = A @ s
        s[:2 * n] += Bd @ W[k]
    return out


def measure_felt_port(transport, scene, *, samples: int | None = None, progress=None,
                      watchdog_periods: int = 20) -> dict:
    """The felt matrices of ``scene`` measured over ``transport`` (module notes).

    Parameters
    ----------
    transport : transport of :mod:`hapsim.daemon.transport`
        :class:`~hapsim.daemon.transport.SerialTransport` (real time or a lockstep mock) or
        :class:`~hapsim.daemon.transport.InProcessTransport`.
    scene : hapsim.scene_nd.SceneND
        A validated scene with a port and a device.
    samples : int, optional
        STATEs per record (default :func:`hapsim.lockstep_nd.default_samples`).
    progress : callable, optional
        ``progress(done, total)`` after each record.
    watchdog_periods : int
        CONFIG's watchdog in periods.

    Returns
    -------
    dict
        ``measured`` (:func:`hapsim.analysis.identify_nd.fit_felt_nd`), ``predicted``
        (:class:`hapsim.analysis.scene_nd_check.SceneCheckND`), ``deviation``
        (:func:`hapsim.lockstep_nd.felt_deviation`), ``responses`` (the ``2n + 1``
        records as fitted, shape (N, n) each [m]: the handle from rest, minus the late
        ticks' known response), ``order``, ``records``, ``samples``,
        ``late`` (late rows over every record), ``excursion`` (the largest distance
        [m] of the handle from rest over every record, the amplitude the linearisation
        bound must be taken at: late ticks can drive the handle past the nominal
        excitation), ``watchdog`` (rows whose force the
        watchdog zeroed), ``delay`` (the delay the device showed, per record; -1 for a
        record in which no FORCE arrived in time: the device held zero throughout, and the
        whole force sent is the known disturbance), ``lost`` (records run again for a
        lost STATE), ``hello`` (the device's HELLO).

    Raises
    ------
    DeviceError, ProtocolError
        No or a wrong HELLO, a FAULT, a device that stops sending, a record lost
        :data:`RETRIES` times.
    ConfigError
        ``samples`` too short for the loop's order.
    """
    from hapsim.analysis.identify_nd import fit_felt_nd
    from hapsim.analysis.scene_nd_check import closed_loop_nd
    from hapsim.lockstep_nd import felt_deviation, identification_plan
    chk, order, N = identification_plan(scene, samples)
    n = scene.dimension
    A = closed_loop_nd(scene)[0]
    from hapsim.engine_nd import EngineND
    EngineND(scene).step()       # the compiled kernels loaded before the first CONFIG
    rate = scene.rate_hz
    wd = max(1, int(round(watchdog_periods * 1e6 / rate)))
    rest_pos = np.asarray(scene.device.position, float)
    lost = 0
    while True:
        # HELLO restarts the hand's cycle: the first record is the one from rest
        hello = handshake_nd(transport, n)
        _drain(transport, 0.01, 0.2)
        raw = []
        for j in range(2 * n + 1):
            rec = _record(transport, scene, N, rate, wd)
            if rec is None:
                break
            raw.append(rec)
            if progress is not None:
                progress(j + 1, 2 * n + 1)
        if len(raw) == 2 * n + 1:
            break
        lost += 1
        if lost >= RETRIES:
            raise DeviceError(f"a STATE was lost in {lost} runs of the records (a gap in "
                              "seq): the link loses frames\nlast frames:\n"
                              + transport.last_frames())
    recs, late, wdog, delays = [], 0, 0, []
    d = scene.device.delay
    for rec in raw:
        W = np.zeros((N, n))
        wdog += int(np.count_nonzero(rec.status & fp.STATUS_WATCHDOG_TRIPPED))
        if not np.any(rec.status & fp.STATUS_FORCE_APPLIED) and not np.any(rec.force_seq):
            # no FORCE arrived in time in the whole record (a host starved for longer
            # than the watchdog): the device held zero throughout. (The account's rule
            # for devices without the FORCE_APPLIED bit would name FORCE 0 on every row.)
            # A device written before the bit existed (PROTOCOL.md §9) names its FORCEs
            # in force_seq alone: the account reads it.
            W[d:] = -rec.force[:N - d]
            late += N - d
            delays.append(-1)
            recs.append(rec.position - rest_pos - disturbance_response_nd(scene, W, A=A))
            continue
        acc = None
        for i in range(n):
            acc = account_from_force_seq(rec.seq, rec.force[:, i], rec.force_seq,
                                         rec.status, force_limit=FORCE_LIMIT)
            W[:, i] = acc.disturbance(rec.force[:, i], rec.seq)
        late += acc.n_late
        delays.append(int(acc.delay))
        if acc.delay >= 0 and acc.delay != scene.device.delay:
            raise ProtocolError(f"the device's delay is {acc.delay} ticks (seq - force_seq), "
                                f"the scene's device.delay {scene.device.delay}")
        xw = disturbance_response_nd(scene, W, A=A)
        recs.append(rec.position - rest_pos - xw)
    excursion = max(float(np.max(np.linalg.norm(rec.position - rest_pos, axis=1)))
                    for rec in raw)
    rest = recs[0]
    fit = fit_felt_nd([r - rest for r in recs[1:]], scene.device.mass, scene.period, order)
    return {"measured": fit, "predicted": chk, "deviation": felt_deviation(fit, chk),
            "responses": recs,
            "order": order, "records": 2 * n, "samples": N, "late": late,
            "excursion": excursion, "watchdog": wdog, "delay": delays, "lost": lost, "hello": hello}
