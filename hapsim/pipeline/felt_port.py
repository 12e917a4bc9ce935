"""The felt matrices of a 2-D or 3-D scene measured over a port, in real time.

The host side of :class:`hapsim.emulated.mock.MockDeviceND` (or any framed-protocol device with
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
``A`` of :func:`hapsim.analysis.scene_check.closed_loop_nd`, ``B_w`` the device's ZOH
input, ``C`` the device position), subtracted from the record (superposition of a linear
loop driven by a known input). The records minus the record from rest are then free
responses, fitted as in lockstep (:func:`hapsim.analysis.pencil.fit_felt_nd`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import firmware_protocol as fp
from hapsim.applied import account_from_force_seq
from hapsim.host.loop_types import LATCHED_FAULTS
from hapsim.errors import ConfigError, DeviceError, ProtocolError, error_record
from hapsim.pipeline.port_session import (clock_of, handshake_nd, quiesce, reopen_port,
                                          stop_reason)

__all__ = ["RecordND", "measure_felt_port", "disturbance_response_nd", "verdict_nd"]

#: CONFIG's force limit [N]: the scene's device has none (finite, as CONFIG requires).
FORCE_LIMIT = 1e9


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
    rows : int
        Rows measured (the first ``rows`` of each array; ``N`` for a whole record).
    silent : float or None
        How long the device had sent no frame at all [s] when the record ended for want
        of a usable STATE (a device or link gone quiet: a loss, as the 1-D loop's
        ``lost_timeout``); None otherwise (a record cut by a STATE missed, or by a
        device that kept sending what the record could not use, a CONFIG it did not
        take).
    """

    def __init__(self, N: int, n: int) -> None:
        self.rows = N
        self.silent = None
        self.seq = np.zeros(N, np.int64)
        self.status = np.zeros(N, np.int64)
        self.force_seq = np.zeros(N, np.int64)
        self.position = np.zeros((N, n))
        self.force = np.zeros((N, n))


class _Counts:
    """What the records met (every field an int; :meth:`as_dict` for the report)."""

    __slots__ = ("hellos", "by_order", "stale", "reordered", "missed", "cut", "resets", "silences", "faults", "configs",
                 "out_of_turn", "lost", "recovered", "reconnect_attempts")

    def __init__(self) -> None:
        for k in self.__slots__:
            setattr(self, k, 0)

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__slots__}


def _record(transport, scene, N: int, rate_hz: float, watchdog_us: int, *,
            counts: _Counts | None = None, first_wait: float = 1.0,
            silence: float = 0.25, stop=None, guard=None) -> RecordND:
    """One CONFIG and its STATEs answered, then STOP: the record's rows up to the first
    STATE the host did not get (a gap in seq), the device falling silent or disarmed, a
    HELLO (the device reset) or another session starting (seq back, other content).

    The engine starts at the handle's first STATE (seq 0 of this CONFIG's session, not
    one that says a FORCE was applied: none was sent) and steps once per STATE; a STATE
    the host did not get leaves its tick unknown, so the rows stop there
    (:attr:`RecordND.rows`): every row kept is a measured sample of the loop, never a
    guessed one. A duplicated STATE (the same seq and content again) is ignored. A stop
    requested (``stop.set``: Ctrl-C, SIGTERM) ends the record at the next read (within
    0.05 s), and STOP is sent as at any end. A ``guard``
    (:class:`hapsim.pipeline.record_guard.RecordGuard`) checks each STATE before it is
    answered; a breach ends the record there, after the braking.
    """
    from hapsim.engine import Engine
    counts = counts if counts is not None else _Counts()
    clock, _ = clock_of(transport)
    n = scene.dimension
    rec = RecordND(N, n)
    eng = Engine(scene)
    port = eng.port
    # per sample no array is made (the real-time rule): the position goes into a reused
    # buffer, the force is read from the engine's own (a view made once)
    pos = np.zeros(n)
    F = eng.port_f[:n]
    items = _items(n)
    armed_bit, applied_bit = fp.STATUS_ARMED, fp.STATUS_FORCE_APPLIED
    State = fp.State
    transport.send(fp.Config(rate_hz, watchdog_us, FORCE_LIMIT))
    counts.configs += 1
    if guard is not None:
        guard.start()
    k = 0
    last = heard = clock()
    end = False
    ahead = None                                # a STATE k + 1 that came before STATE k
    while not end:
        if stop is not None and stop.set:
            break                               # Ctrl-C, SIGTERM: the device is stopped below
        msgs = transport.receive(0.05)
        now = clock()
        if msgs:
            heard = now
        if now - last > (first_wait if k == 0 else silence):
            # nothing usable came for that long: the record ends here (a host that
            # stalled as long reads the STATEs that waited, a burst: it ends too, as ever)
            counts.silences += 1
            if now - heard > silence:
                rec.silent = now - heard        # ... nor anything at all: a loss
            break
        for m in msgs:
            if type(m) is not State:
                if isinstance(m, fp.Fault):
                    if m.code in LATCHED_FAULTS:
                        transport.send(fp.Stop())
                        raise DeviceError(f"the device sent FAULT code {m.code} detail "
                                          f"{m.detail}")
                    counts.faults += 1
                elif isinstance(m, fp.Hello):
                    counts.hellos += 1          # the device restarted its hand's cycle
                    if k:
                        counts.resets += 1      # ... and this session ended
                        end = True
                        break
                continue
            if len(m.position) != n:
                continue
            if k == 0:
                # the first STATE of this CONFIG's session: seq 0, armed, no FORCE applied
                if not m.status & armed_bit or m.status & applied_bit:
                    continue
                if m.seq != 0:
                    # this session's (the device was silent before the CONFIG): its
                    # STATE 0 never came
                    counts.missed += 1
                    end = True
                    break
                mp = m.position
                for a in range(n):
                    pos[a] = mp[a]
                eng.x[:, port] = pos            # the engine starts where the handle is
                eng.xp[:, port] = pos
            elif m.seq != k:
                if m.seq == k + 1 and ahead is None:
                    ahead = m                   # STATE k may come next (reordered)
                    continue
                if m.seq < k and _same_row(rec, m):
                    counts.stale += 1           # duplicated or reordered: used once
                    continue
                if m.seq > k:
                    counts.missed += m.seq - k  # the STATEs between never came
                end = True                      # a gap, or another session's seq
                break
            while m is not None:
                if k and not m.status & armed_bit:
                    end = True                  # disarmed (a reset, a watchdog STOP)
                    break
                mp = m.position
                for a in range(n):
                    pos[a] = mp[a]
                last = clock()
                if guard is not None and guard.check(m, pos) is not None:
                    guard.stop_device(transport, m, pos)    # brakes, then zero force
                    end = True
                    break
                eng.set_port_position(pos)
                eng.step()
                transport.send(fp.Force(m.seq, items(F)))
                rec.seq[k], rec.status[k], rec.force_seq[k] = m.seq, m.status, m.force_seq
                rp, rf = rec.position, rec.force
                for a in range(n):
                    rp[k, a] = pos[a]
                    rf[k, a] = F[a]
                k += 1
                if k >= N:
                    end = True
                    break
                m = None
                if ahead is not None and ahead.seq == k:
                    m = ahead                   # the one that came before its turn
                    ahead = None
                    counts.reordered += 1
            if end:
                break
    rec.rows = k
    if k < N and not (stop is not None and stop.set) and not (
            guard is not None and guard.reason):
        counts.cut += 1
    transport.send(fp.Stop())
    return rec


def _same_row(rec: RecordND, m) -> bool:
    """STATE ``m`` is the record's row ``m.seq`` again (a duplicate), not another
    session's STATE with that seq."""
    k = int(m.seq)
    if k < 0 or k >= rec.seq.size or rec.seq[k] != k or rec.force_seq[k] != m.force_seq:
        return False
    return all(rec.position[k, a] == v for a, v in enumerate(m.position))


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
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device.
    W : array_like, shape (N, n)
        ``w[k]``: force applied over period ``k`` minus the on-time loop's ``F[k - d]`` [N].
    A : ndarray, optional
        :func:`hapsim.analysis.scene_check.closed_loop_nd`'s matrix (computed when None).

    Returns
    -------
    ndarray, shape (N, n)
        ``x_w[k] = sum_{j<k} C A^(k-1-j) B_w w[j]`` [m], ``B_w`` the ZOH input of the
        device (the first ``2n`` rows of the state, :func:`hapsim.analysis.ths.zoh_matrices`)
        and ``C`` the device position (superposition, as the 1-D
        :func:`hapsim.analysis.error_response.disturbance_response`).

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.scene_check.closed_loop_nd`.
    """
    from hapsim.analysis.scene_check import closed_loop_nd
    from hapsim.analysis.ths import MatrixLoop, split_hold_matrices, zoh_matrices
    W = np.asarray(W, float)
    n = scene.dimension
    if A is None:
        A = closed_loop_nd(scene)[0]
    dev = scene.device
    lm = MatrixLoop(mass=dev.mass, friction=dev.friction, rate_hz=scene.rate_hz,
                    delay=dev.delay)
    split = float(dev.delay) % 1.0 > 0
    if split:    # the force applied enters through Gamma0 and is held next period (last)
        _, Bd, _ = split_hold_matrices(lm)
    else:
        _, Bd = zoh_matrices(lm)
    out = np.zeros_like(W)
    nz = np.flatnonzero(np.any(W != 0, axis=1))
    if nz.size == 0:
        return out
    s = np.zeros(A.shape[0])
    for k in range(int(nz[0]), W.shape[0]):
        out[k] = s[:n]
        s = A @ s
        s[:2 * n] += Bd @ W[k]
        if split:
            s[-n:] += W[k]
    return out


def start_of(position, rest, amplitude: float, period: float):
    """Which identification start a record's first two samples show.

    Parameters
    ----------
    position : array_like, shape (>= 2, n)
        The record's first handle positions [m].
    rest : array_like, shape (n,)
        The handle's rest position [m].
    amplitude : float
        The hand's amplitude ``a`` [m].
    period : float
        Sample period ``T`` [s].

    Returns
    -------
    int or None
        Index into :func:`hapsim.lockstep.excitation_starts` (0 rest, ``1..n``
        displaced, ``n+1..2n`` moving), or None when no start is within a quarter of its
        distance to the others: the displacement at sample 0 within ``a / 4`` of ``x0``,
        the step to sample 1 within ``a / 40`` of ``v0 T`` (the device holds zero force
        over the first period when ``d >= 1``: the step is the free motion, ``v0 T``
        times ``1 - O(b T / m)``).
    """
    from hapsim.lockstep import excitation_starts
    p = np.asarray(position, float)
    rest = np.asarray(rest, float)
    n = rest.size
    d0 = p[0] - rest
    d1 = p[1] - p[0]
    for j, (x0, v0) in enumerate(excitation_starts(n, amplitude, period)):
        if (np.max(np.abs(d0 - x0)) < amplitude / 4
                and np.max(np.abs(d1 - v0 * period)) < amplitude / 40):
            return j
    return None


def min_rows(N: int, order: int, n: int) -> int:
    """Fewest rows a record cut short by a lost STATE may keep to be used: half the
    record, and at least ten times the regression's ``2 p n`` unknowns over the ``2n + 1``
    records (so the fit stays overdetermined tenfold, as
    :func:`hapsim.lockstep.default_samples`).

    Parameters
    ----------
    N : int
        Samples of a whole record.
    order : int
        Prediction order ``p`` of the loop's regression.
    n : int
        Axes (the ports' dimension).

    Returns
    -------
    int
        ``max(N // 2, ceil(20 p n / (2n + 1)), p + 2)`` rows.
    """
    return max(N // 2, -(-20 * order * n // (2 * n + 1)), order + 2)


def measure_felt_port(transport, scene, *, samples: int | None = None, progress=None,
                      watchdog_periods: int = 20, amplitude: float | None = None,
                      max_configs: int | None = None, reconnect: bool = True,
                      reconnect_time: float = 10.0, reconnect_attempts: int | None = None,
                      lost_timeout: float | None = None,
                      backoff: float = 0.05, backoff_max: float = 1.0,
                      frames: str = "auto", stop=None, late_guard: bool = True) -> dict:
    """The felt matrices of ``scene`` measured over ``transport`` (module notes).

    Each CONFIG gives one record; the device's hand picks its start (the mock: the next
    one after each CONFIG, from rest again after each HELLO). The host counts the CONFIGs
    since the last HELLO it saw and reads the start from the record's first two samples
    (:func:`start_of`) where they tell it (not through a quantised device's readings:
    then the count says), so records lost, cut short, or taken by a device that reset or
    counted a CONFIG twice never put a start in the wrong place. CONFIGs go on until every start has a whole record, or ``max_configs`` have
    been sent; then each start's longest record is used if it keeps at least
    :func:`min_rows` rows (a record stops at the first STATE the host did not get:
    :func:`_record`), all cut to the record from rest's length. Otherwise nothing is
    fitted and the result says why (``incomplete``: the verdict is "not measurable").
    A port that fails (the device's port vanished) is opened again with backoff, HELLO
    asked, and the records go on (``lost``, ``recovered``); each record's engine starts
    at its own first STATE, the handle of the new session. A device lost for good once
    it has said HELLO (``reconnect`` off, or the time or attempts allowed used up) ends
    the measurement as a stop does: what was recorded by then is returned, ``stop``
    "device lost" and ``error`` say why (the 1-D run's report after such a loss, exit 1).

    Parameters
    ----------
    transport : transport of :mod:`hapsim.host.transport`
        :class:`~hapsim.host.transport.SerialTransport` (real time or a lockstep mock),
        :class:`~hapsim.emulated.links.InProcessTransport` or
        :class:`~hapsim.emulated.links.SimTransport` (virtual clock, faults).
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device.
    samples : int, optional
        STATEs per record (default :func:`hapsim.lockstep.default_samples`).
    progress : callable, optional
        ``progress(done, total)`` as starts get their whole record.
    watchdog_periods : int
        CONFIG's watchdog in periods.
    amplitude : float, optional
        The device hand's amplitude ``a`` [m] (default
        :data:`hapsim.emulated.mock.DEFAULT_AMPLITUDE`).
    max_configs : int, optional
        CONFIGs sent at most (default ``4 (2n + 1)``).
    reconnect : bool
        Recover a lost device (``--no-reconnect``: False, the loss ends the measurement).
    reconnect_time : float
        Time allowed to open a failed port again [s], per loss (``--reconnect-time``).
    reconnect_attempts : int, optional
        Attempts allowed to open it per loss (``--reconnect-attempts``); None: as many as
        ``reconnect_time`` allows.
    lost_timeout : float, optional
        Silence after which the device is lost [s] (``--lost-timeout``): no frame at all
        for that long in a record (or for ``max(1, lost_timeout)`` s after a CONFIG) is a
        loss, recovered as a failed port is (HELLO asked again). Default: two watchdog
        periods, at least 0.25 s. A device that goes on sending what the record cannot
        use (a CONFIG it did not take) only ends that record.
    backoff, backoff_max : float
        First wait between attempts [s], doubled up to ``backoff_max``.
    frames : {"auto", "full"}
        ``"auto"``: the compact frames with a device that applies its forces in steps and
        offers them (:func:`hapsim.pipeline.port_session.handshake_nd`); ``"full"``: never.
    stop : hapsim.spawn.StopFlag, optional
        A stop requested (``stop.set``: a signal handler's) ends the record under way at
        its next read and the measurement there: the starts with a whole record by then
        are fitted if they are all there, else nothing is (``incomplete`` says the stop
        and how far it got); ``stop`` in the result names it.
    late_guard : bool
        Guard the records against late FORCEs (:mod:`hapsim.pipeline.record_guard`;
        False for a device that waits for the host, a lockstep mock). The position bound
        and the braking hold either way.

    Returns
    -------
    dict
        ``measured`` (:func:`hapsim.analysis.pencil.fit_felt_nd`; matrices None when
        incomplete), ``predicted`` (:class:`hapsim.analysis.scene_check.SceneCheckND`),
        ``deviation`` (:func:`hapsim.analysis.felt_matrices.felt_deviation`, None when incomplete),
        ``responses`` (the records as fitted, each shape (rows, n) [m]: the handle from
        rest, minus the late ticks' known response; empty when incomplete),
        ``order``, ``records`` (``2n``), ``samples`` (``N``), ``rows`` (rows used, per
        start, the record from rest first), ``late`` (late rows over the records used),
        ``excursion`` (the largest distance [m] of the handle from rest over them, the
        amplitude the linearisation bound must be taken at: late ticks can drive the
        handle past the nominal excitation), ``moved`` (each record's rows used, the
        handle from rest [m], shape (rows, n): what
        :func:`hapsim.analysis.linearisation.bound_at_records` takes; absent when
        incomplete), ``watchdog`` (rows whose force the watchdog
        zeroed), ``delay`` (the delay the device showed, per record used; -1 for a record
        in which no FORCE arrived in time: the device held zero throughout, and the whole
        force sent is the known disturbance; more than ``device.delay`` for a record in
        which no FORCE made its tick: its rows past the scene's delay are late, each
        holding a known older force), ``lost`` (port failures), ``recovered``,
        ``counts`` (``hellos`` seen, ``by_order`` (records whose start the readings
        could not tell: taken from the hand's cycle), ``stale``, ``reordered``,
        ``missed``, ``cut``, ``resets``, ``silences``, ``faults``, ``configs``,
        ``out_of_turn`` (records whose start was not the one the cycle says: the device
        skipped one), ``lost``, ``recovered``, ``reconnect_attempts``),
        ``bad_frames`` (the host decoder's count, when it has one), ``incomplete``
        (None, or why nothing was fitted), ``hello`` (the device's first HELLO),
        ``frames`` (``"compact"`` or ``"full"``: the last session's), ``stop``
        (``"end"``, ``"signal NAME"`` / the stop's reason when one was requested, a
        safety stop's ``"safety: ..."``, or ``"device lost"``), ``error`` (None, or the
        ``type`` and ``message`` of the error that lost the device for good), ``safety``
        (:meth:`hapsim.pipeline.record_guard.RecordGuard.to_dict`: the position bound,
        the lateness guard, a safety stop and its braking).

    Raises
    ------
    DeviceError, ProtocolError
        No or a wrong HELLO before the first record, a latched FAULT; a port failing
        before the device ever said HELLO and not back within ``reconnect_time``.
    ConfigError
        ``samples`` too short for the loop's order; ``frames`` not one of its choices.
    """
    from hapsim.analysis.pencil import fit_felt_nd
    from hapsim.analysis.scene_check import closed_loop_nd
    from hapsim.emulated.mock import DEFAULT_AMPLITUDE
    from hapsim.engine import Engine
    from hapsim.analysis.felt_matrices import felt_deviation
    from hapsim.lockstep import identification_plan
    if frames not in ("auto", "full"):
        raise ConfigError(f"frames must be 'auto' or 'full', got {frames!r}", key="frames")
    chk, order, N = identification_plan(scene, samples)
    n = scene.dimension
    S = 2 * n + 1
    a = DEFAULT_AMPLITUDE if amplitude is None else float(amplitude)
    A = closed_loop_nd(scene)[0]
    Engine(scene).step()       # the compiled kernels loaded before the first CONFIG
    rate = scene.rate_hz
    wd = max(1, int(round(watchdog_periods * 1e6 / rate)))
    # the compact STATE's lag is exact while a FORCE is held for fewer than 255 ticks,
    # which the watchdog ensures at 250 periods or fewer (PROTOCOL.md §4)
    compact = frames != "full" and watchdog_periods <= 250
    rest_pos = np.asarray(scene.device.position, float)
    clock, _ = clock_of(transport)
    counts = _Counts()
    budget = 4 * S if max_configs is None else int(max_configs)
    silence = max(0.25, 2.0 * wd * 1e-6) if lost_timeout is None else float(lost_timeout)
    best: list = [None] * S
    hello = None
    need_hello = True
    lost_since = None
    lost_for_good = None                        # the DeviceError that ended it
    silent = None                               # a record ended by the device's silence
    attempts0 = 0                               # reconnect attempts before this loss
    first = None                                # this loss's first error
    since_hello = 0                             # CONFIGs the device took since its HELLO
    # the records' bounds, checked STATE by STATE (hapsim.pipeline.record_guard)
    from hapsim.analysis.late_growth import late_growth
    from hapsim.pipeline.record_guard import RecordGuard
    guard = RecordGuard(scene, a, late_growth(scene, wd * 1e-6) if late_guard else None,
                        FORCE_LIMIT)
    stopped = ((lambda: guard.reason is not None) if stop is None else
               (lambda: bool(stop.set) or guard.reason is not None))
    asked = (lambda: False) if stop is None else (lambda: bool(stop.set))
    while (counts.configs < budget and not all(r is not None and r.rows == N for r in best)
           and not stopped()):
        try:
            if silent is not None:
                exc, silent = silent, None
                raise exc                       # the last record's silence: a loss
            if need_hello:
                h = handshake_nd(transport, n, compact_rate=rate if compact else None)
                hello = hello or h
                need_hello = False
                since_hello = 0
            h0 = counts.hellos
            quiesce(transport, counts=counts)
            if counts.hellos != h0:
                since_hello = 0                 # a HELLO: the hand starts from rest again
            expected = since_hello % S
            h0 = counts.hellos
            rec = _record(transport, scene, N, rate, wd, counts=counts, silence=silence,
                          first_wait=max(1.0, silence), stop=stop, guard=guard)
            since_hello = 0 if counts.hellos != h0 else since_hello + 1
        except DeviceError as exc:
            if "FAULT" in str(exc).split("\n")[0]:
                raise
            if guard.reason is not None:
                break                           # a safety stop, then the port failed
            if lost_since is None:
                lost_since = clock()
                counts.lost += 1
                attempts0 = counts.reconnect_attempts
                first = exc
            try:
                if not reconnect:
                    raise DeviceError(f"device lost ({str(exc).splitlines()[0]}); "
                                      "reconnect is off (--no-reconnect)\nlast frames:\n"
                                      + transport.last_frames())
                reopen_port(transport, counts, first=first, last=exc, since=lost_since,
                            until=lost_since + reconnect_time,
                            tried=counts.reconnect_attempts - attempts0,
                            most=reconnect_attempts, backoff=backoff,
                            backoff_max=backoff_max, stopped=asked)
            except DeviceError as gone:
                if hello is None:
                    raise                       # it never said HELLO: nothing ran
                lost_for_good = gone
                break
            need_hello = True
            continue
        if rec.silent is not None:
            # its rows are kept; the device is then lost (recovered at the loop's top)
            silent = DeviceError(f"the device fell silent (no frame for {rec.silent:.3g} "
                                 f"s)\nlast frames:\n" + transport.last_frames())
        if rec.rows and lost_since is not None:
            counts.recovered += 1           # a record again after the loss
            lost_since = None
        if rec.rows < 2:
            continue
        j = start_of(rec.position[:2], rest_pos, a, 1.0 / rate)
        if j is None:
            # readings that cannot tell the starts apart (a quantised device, another
            # amplitude): the hand's cycle says which start it was
            counts.by_order += 1
            j = expected
        elif j != expected:
            counts.out_of_turn += 1             # the device's cycle is not the host's:
            since_hello = j + 1                 # follow the device's
        if best[j] is None or rec.rows > best[j].rows:
            best[j] = rec
            if progress is not None and rec.rows == N:
                progress(sum(r is not None and r.rows == N for r in best), S)
    try:
        quiesce(transport, 2)
    except DeviceError:
        pass
    out = {"predicted": chk, "order": order, "records": 2 * n, "samples": N,
           "hello": hello, "counts": counts.as_dict(), "lost": counts.lost,
           "recovered": counts.recovered, "incomplete": None,
           "frames": "compact" if getattr(transport, "compact", False) else "full",
           "stop": ("device lost" if lost_for_good is not None else
                    "end" if not stopped() else guard.reason or stop_reason(stop)),
           "error": error_record(lost_for_good),
           "safety": guard.to_dict()}
    dec = getattr(transport, "decoder", None)
    st = getattr(dec, "stats", None)
    out["bad_frames"] = (None if st is None else int(
        st.bad_crc + st.bad_cobs + st.overlong + st.malformed + st.unknown_type))
    need = min_rows(N, order, n)
    short = [j for j, r in enumerate(best) if r is None or r.rows < need]
    L = best[0].rows if best[0] is not None else 0
    if short or L < need:
        out.update(measured={"felt_stiffness": None, "felt_damping": None, "poles": [],
                             "rendered_poles": [], "residual": float("nan"), "rank": 0},
                   deviation=None, rows=[0 if r is None else r.rows for r in best],
                   late=0, watchdog=0, delay=[], excursion=0.0,
                   incomplete=(f"stopped ({out['stop']}) with "
                               f"{sum(r is not None and r.rows == N for r in best)} of "
                               f"the {S} starts wholly recorded: the felt matrices are "
                               "not measured"
                               if stopped() or lost_for_good is not None else
                               f"{len(short)} of the {S} starts got no record of "
                               f"{need} rows or more in {counts.configs} CONFIGs (STATEs "
                               f"missed: {counts.missed}, records cut short: {counts.cut}, "
                               f"device losses: {counts.lost}): the felt matrices are not "
                               "measured" + (
                                   f"; {counts.out_of_turn} of the {counts.configs} records "
                                   "began at another start than the one expected: the "
                                   "device's hand moves to the starts of another amplitude "
                                   f"(an emulated device's --amplitude must be this run's, "
                                   f"{a:g} m)" if 2 * counts.out_of_turn >= counts.configs
                                   else "")))
        return out
    recs, late, wdog, delays = [], 0, 0, []
    d = int(scene.device.delay)       # whole ticks (force_seq); a fraction is the physics'

    for r in best:
        k = min(r.rows, L)
        seq, status, fseq = r.seq[:k], r.status[:k], r.force_seq[:k]
        pos, force = r.position[:k], r.force[:k]
        W = np.zeros((k, n))
        wdog += int(np.count_nonzero(status & fp.STATUS_WATCHDOG_TRIPPED))
        if not np.any(status & fp.STATUS_FORCE_APPLIED) and not np.any(fseq):
            # no FORCE arrived in time in the whole record (a host starved for longer
            # than the watchdog): the device held zero throughout. (The account's rule
            # for devices without the FORCE_APPLIED bit would name FORCE 0 on every row.)
            # A device written before the bit existed (PROTOCOL.md §9) names its FORCEs
            # in force_seq alone: the account reads it.
            W[d:] = -force[:k - d]
            late += k - d
            delays.append(-1)
            recs.append(pos - rest_pos - disturbance_response_nd(scene, W, A=A))
            continue
        acc = None
        rows = np.arange(k)
        shown = -1
        for i in range(n):
            acc = account_from_force_seq(seq, force[:, i], fseq, status,
                                         force_limit=FORCE_LIMIT)
            shown = int(acc.delay)
            if 0 <= shown < d:
                raise ProtocolError(f"the device's delay is {shown} ticks (seq - "
                                    f"force_seq), the scene's device.delay {d}")
            if shown > d:
                # no FORCE of the record made its tick (a host late throughout): the
                # smallest delay shown is a late one (a device never applies a FORCE
                # before it is due), so the loop's delay is the scene's and every row
                # past it holds a known, older force (or zero: the watchdog's)
                acc = replace(acc, delay=d, late=(rows >= d) & (acc.source != rows - d))
            W[:, i] = acc.disturbance(force[:, i], seq)
        late += acc.n_late
        delays.append(shown)
        recs.append(pos - rest_pos - disturbance_response_nd(scene, W, A=A))
    moved = [r.position[:min(r.rows, L)] - rest_pos for r in best]
    excursion = max(float(np.max(np.linalg.norm(m, axis=1))) for m in moved)
    rest = recs[0]
    fit = fit_felt_nd([r - rest[:r.shape[0]] for r in recs[1:]], scene.device.mass,
                      scene.period, order)
    out.update(measured=fit, deviation=felt_deviation(fit, chk), late=late,
               excursion=excursion, moved=moved, watchdog=wdog, delay=delays,
               rows=[min(r.rows, L) for r in best], responses=recs)
    return out


def verdict_nd(res: dict) -> dict:
    """The verdict of an n-D run's result (:func:`hapsim.analysis.felt_matrices.felt_verdict`), or
    "not measurable" with the reason when the records were incomplete
    (:func:`measure_felt_port`'s ``incomplete``).

    Parameters
    ----------
    res : dict
        A measurement with ``deviation`` and ``bound`` (and ``wire``, a quantised
        device's term: :func:`hapsim.emulated.pantograph_board.wire_term`).

    Returns
    -------
    dict
        ``verdict``, ``within``, ``uncertainty``, ``reason``, ``statements``,
        ``not_stated`` (per quantity and principal direction: the felt matrices along
        :func:`hapsim.analysis.felt_matrices.felt_directions`).
    """
    from hapsim.analysis.felt_matrices import felt_directions, felt_verdict
    if res.get("incomplete"):
        return {"verdict": "not measurable", "within": None, "uncertainty": None,
                "reason": res["incomplete"], "statements": [],
                "not_stated": ["felt stiffness", "felt damping"]}
    return felt_verdict(res["deviation"], res["bound"], res.get("wire"),
                        directions=felt_directions(res["measured"], res["predicted"]))
