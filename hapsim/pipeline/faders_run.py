"""The FireFader's two faders felt in real time: a scene whose two ports are the faders of
one FireFader (both devices ``protocol: firefader``), its loop closed through the board's
own bytes on the host's clock, and the felt matrices across the two faders measured from
the records (issue 30 item 3; docs/ports.md, 'In real time').

**The board.** One FireFader carries both faders in every packet (``[127, fA, fB]``) and
every record (``[255, pA, pB, ...]``): :mod:`hapsim.drivers.firefader`. The emulated one
(:class:`hapsim.emulated.firefader_board.FireFaderDevice` with ``device_b``) runs the
``.ino``'s loop for both faders, each its own mass and friction from the scene's
``devices:``, on its own wall clock, in a child process behind a pty
(:class:`hapsim.emulated.driver_mock.EmbeddedDriverMock`), or it is a real board on a
port (``--port``).

**The host's loop** (:func:`record_faders`), Python at the scene's rate on the host's
clock (:func:`hapsim.host.realtime.sleep_until_ns` on an absolute grid, as the 1-D loop
paces itself): packet ``w`` is written at ``t0 + w T``; its record is read; the forces on
the two ports are the links' law on the two readings and the ones before
(:meth:`hapsim.lockstep_ports.LockstepPorts.forces`, docs/design.md 'The scheme'), clamped to
each device's ``force_limit`` and the protocol's 126 counts, and go out with the next
packet. Between records the host is silent longer than the ``.ino``'s silence rule
(:data:`hapsim.drivers.firefader.SILENCE_S`): the board zeroes both forces; a hand (the
emulated board's ``hand``; a person's at a real one) puts the faders at the record's
start and lets go after :data:`hapsim.drivers.firefader.HAND_PASSES` passes of zero
force (the enables climbing back over their gate); that pass's
record is the record's row 0. The records are the rest and the ``2 P`` starts of
:func:`hapsim.lockstep.excitation_starts` (each fader displaced by ``a``, then moving at
``a / (10 T)``).

**Safety** (as the 1-D FireFader run): a fader beyond :data:`WORKSPACE_M` of the centre, a
reply that never comes, or the host itself later than :data:`LATE_STOP_S` (the board may
have switched the force off by its silence rule: the loop is no longer the one measured)
ends the run with a zero packet: both faders are left at zero force, as after the last
record.

**The measurement** (:func:`measure_faders`): the records minus the record from rest,
fitted by :func:`hapsim.analysis.pencil.fit_felt_nd` (the n-D fit of the lockstep
measurement) on their undisturbed stretches (:func:`usable_rows`), against the prediction
(:func:`hapsim.analysis.ports.check_ports`: the split hold of the sub-sample delay,
0.725 periods for the FireFader at 250 Hz). The stated uncertainty is the n-D run's
(:func:`hapsim.analysis.felt_matrices.felt_verdict`): the linear loop's round-off and the
wire's term (:func:`hapsim.lockstep.wire_terms_nd` on the ports' loop): each reading to
within half a pot count (:data:`hapsim.drivers.firefader.METRES_PER_COUNT`), each force to
within half a force count, and the host's write times: a packet written ``delta`` off
its time (:func:`departures`: from the record's median lateness, which shifts the whole
loop and changes no hold) reads its pot ``delta`` off (a reading error up to ``|v|
|delta|``) and leaves the force before it on ``delta`` longer or shorter (an impulse
``|du| |delta|``, stated as a force error ``|du| |delta| / T`` over the period: first
order in ``delta / T``). The wire's term is the worst case over the error box
(:mod:`hapsim.analysis.wire_box`, ``box=True``), not the first-order one at the records:
measured on the lockstep board (the shipped scene and random soft ones, each error
coordinate's effect on the decimated fit by finite differences, then the records moved
by each statement's first-order worst errors and refitted), the errors moved a stated
felt stiffness by 0.17-0.90 of its first-order term and an unstated damping by up to
1.36 of it, and the sensitivity sampled over the box was 1.06-1.95 times the one at the
records: the first-order term was no bound, and a "differs" built on it could be wrong.
With the box the 8-bit pots state nothing at the shipped amplitude; the run says so
before it starts (:func:`faders_feasibility`).
"""

from __future__ import annotations

import math
import time

import numpy as np

from hapsim.analysis.write_holds import HOLD_CUT_PERIODS
from hapsim.errors import ConfigError, DeviceError, error_record
from hapsim.emulated.links import LockstepBoardLink  # noqa: F401  (re-exported)

__all__ = ["WORKSPACE_M", "LATE_STOP_S", "CUT_PERIODS", "FADERS_TAKES", "FADER_AMPLITUDE",
           "faders_refusal", "record_faders", "departures", "usable_rows", "measure_faders",
           "run_faders", "decimation", "faders_feasibility", "LockstepBoardLink"]

#: The measurement's workspace [m] from the centre: 100 pot counts (39 mm), inside the
#: ``.ino``'s enable range (``4 < pot < 251``, line 382) and the emulated board's end stops.
WORKSPACE_M = 100 * 0.05 / 128
#: The host later than this for a write ends the run [s]: beyond the board's silence
#: rule (its force off from 0.1 s) and the hand's patience
#: (:attr:`hapsim.emulated.firefader_board.FireFaderDevice.HAND_SILENCE_S`, 0.3 s: a person
#: whose faders went limp takes them). A shorter stall is cut from the record
#: (:func:`usable_rows`): a host descheduled 100-160 ms was measured at 16 % of the ticks
#: of a bare 250 Hz sleep loop on the shared 2-core machine at load 3.
LATE_STOP_S = 0.25
#: The arming's time limit [s] (the Nano's ~1 s bootloader, an emulated board's start).
ARM_TIMEOUT_S = 10.0
#: A write more than this many periods off its time on the grid is cut from the records
#: with the rows its forces reach (:func:`usable_rows`); smaller departures enter the
#: stated uncertainty (module notes). The 2DIY's cut
#: (:data:`hapsim.analysis.write_holds.HOLD_CUT_PERIODS`, half a period): at a quarter,
#: beside the other sessions' loads (load 7 on 2 cores), 30-60 writes a record were cut,
#: and a decimated sample needs all its ``D`` rows.
CUT_PERIODS = HOLD_CUT_PERIODS
#: The excitation ``a`` of the real-time run [m] (``--amplitude``): 4 mm, about 10 pot
#: counts (0.39 mm each) so the quantiser's rounding is a few percent of the motion, and
#: small enough that the two-fader scene's forces stay under its 0.38 N limit.
FADER_AMPLITUDE = 4e-3
#: The fit's samples per cycle of the fastest rendered mode (:func:`decimation`): the
#: records are fitted on every ``D``-th sample. Measured on one run's records (4 mm, the
#: shipped scene, 6.2 Hz): every sample (the full order), the pots' steps of a tenth of
#: a count per sample left the felt matrices unmeasurable (the rounding's term 10^3-10^4
#: times them); every 8th to 16th sample (5 to 2.5 a cycle), the felt stiffness within
#: 0.4-1.4 % of the prediction; every 24th aliased.
SAMPLES_PER_CYCLE = 4
#: The decimated fit's order: the rendered pairs only (2 per port's pair, a second-order
#: vector recursion); the hold's and the delay's fast modes (``|z|`` ~0.09 a period at
#: the FireFader's 250 Hz) are gone after one decimated sample (``0.09^D``), which the
#: fit skips (:func:`_decimated`).
FIT_ORDER = 2
#: What the real-time run of the two faders takes (every other option refused by name).
FADERS_TAKES = ("port", "driver", "allow_unstable", "rt_priority", "seed")
#: The host's wait for a reply before the run is stopped [s] (the board answers within
#: ~3 ms: :meth:`hapsim.drivers.firefader.FireFader.round_trip_s`).
REPLY_TIMEOUT_S = 0.5
#: After the record of a write the host's watchdog preceded with zero writes, how long
#: the others may take [periods]: the ``.ino`` answers each packet's pass within ~3 ms
#: (its reads and the 7-byte record at 57600 baud), a period at most of its rates, so
#: two passes back to back; a record not come by then is taken as merged.
MERGE_WAIT_PERIODS = 3
#: The host's silence between records [s]: beyond the hand's patience (0.3 s).
PAUSE_S = 0.4


def faders_refusal(scene, options) -> str | None:
    """Why a scene with several ports cannot run in real time here, or None if it can: the
    real-time run takes the two faders of one FireFader.

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
    options : hapsim.pipeline.options.RunOptions

    Returns
    -------
    str or None
        The reason (several boards, other protocols, another driver), naming what is built
        (the driver class's :attr:`~hapsim.drivers.base.Driver.ports_per_board`).
    """
    from hapsim.drivers import family
    protos = sorted({d.protocol or "framed" for _, d in scene.devices})
    got = ", ".join(f"{n}: {d.protocol or 'framed'}" for n, d in scene.devices)
    if len(protos) != 1:
        return (f"devices of different protocols ({got}): the real-time run of several "
                "ports drives the ports of one board (the FireFader's two faders); several "
                "boards, or devices of different protocols, are not built yet")
    proto = protos[0]
    if options.driver is not None and options.driver != proto:
        return (f"driver {options.driver!r}: the scene's devices speak {proto}, and the "
                "real-time run of several ports drives the ports of one board of theirs")
    cls = family(proto).load()                  # None: the framed protocol
    per = getattr(cls, "ports_per_board", 1)
    if per != len(scene.devices):
        return (f"{len(scene.devices)} ports of {proto} ({got}): the real-time run of "
                f"several ports drives the ports one board carries ({per} on a {proto} "
                "board; the FireFader's two faders); several boards, or devices of "
                "different protocols, are not built yet")
    return None


def _zero(ser) -> bool:
    """Both faders at zero force: a zero packet, and its record waited for (the board has
    run its pass). Returns whether the record came."""
    from hapsim.drivers.firefader import RecordDecoder, Records, encode_packet
    ser.write(encode_packet(0, 0))
    ser.flush()
    return Records(RecordDecoder()).next(ser, REPLY_TIMEOUT_S) is not None


def record_faders(ser, scene, samples: int, starts: int, *, force_scale: float,
                  arming: int = 72, progress=None, pace: bool = True,
                  watchdog=None) -> dict:
    """The host's real-time loop over one FireFader's two faders (module notes).

    Parameters
    ----------
    ser : serial.Serial
        The board's port, open (``in_waiting``, ``read``, ``write``, ``fileno``).
    scene : hapsim.scene.ScenePorts
        Two ports, both faders of one FireFader.
    samples : int
        Rows ``N`` per record.
    starts : int
        Records (the rest's first): each after a pause, the hand's start.
    force_scale : float
        The force per count [N] (:attr:`hapsim.drivers.firefader.FireFader.force_scale`).
    arming : int, optional
        Zero packets before the first record (the enables' climb,
        :attr:`hapsim.drivers.firefader.FireFader.arming_records`).
    progress : callable, optional
        ``progress(done, total)`` after each record.
    pace : bool, optional
        Pace the writes on the host's clock (the real-time run). False (a board in
        lockstep, asked for by name, on an in-process link): no wait, every write on
        time, and each silence between records told to the link (``ser.idle(s)``: the
        board's time is the host's writes, not the wall clock).
    watchdog : hapsim.drivers.torque_watchdog.TorqueWatchdog, optional
        The host's watchdog on this port (the ``.ino`` zeroes its forces only after
        0.1 s): armed over the records; the record of each of its zero writes is read
        and dropped before the host's next write (counted, ``watchdog_zeroed``;
        :mod:`hapsim.drivers.host_watchdog`).

    Returns
    -------
    dict
        ``records``: per record, ``position`` (N, 2) [m] (the pots' readings), ``force``
        (N, 2) [N] (the forces sent, as counts times the scale, computed from each row),
        ``late`` (N,) [s] (how late the write whose pass read the row was, on the grid),
        ``clamped`` (N,) bool; ``stop`` (``"end"``, or why the run stopped: a safety
        limit, a lost reply, the host's own lateness), ``late_ticks`` per record (writes
        more than :data:`CUT_PERIODS` periods off their time, :func:`departures`), ``latest`` [s] (the latest write).

    Raises
    ------
    DeviceError
        No record during the arming.
    """
    from hapsim.drivers.firefader import (CENTRE, FORCE_MAX, HAND_PASSES, METRES_PER_COUNT,
                                          RecordDecoder, Records, encode_packet,
                                          force_counts)
    from hapsim.drivers.device_port import DevicePort
    from hapsim.host.realtime import sleep_until_ns
    from hapsim.lockstep_ports import LockstepPorts
    ser = DevicePort.of(ser, "the FireFader")   # the port failing: a DeviceError
    T = scene.period
    Tns = int(round(T * 1e9))
    zeroed = [0]

    def put(pk):
        # the commands now owed a record: pk and the watchdog's zero writes that went out
        # before it (a zero packet holds no force)
        if watchdog is None:
            ser.write(pk)
            return 1
        n = len(watchdog.write(ser, pk, pk != zero))
        zeroed[0] += n
        return 1 + n
    P = 2
    lim = np.array([float(d.force_limit) for _, d in scene.devices])
    fs = force_scale * 127.0
    records = Records(RecordDecoder())
    zero = encode_packet(0, 0)
    host = LockstepPorts(scene)              # the links' law: host.forces()
    wait = sleep_until_ns if pace else (lambda ns: None)
    t0 = time.monotonic_ns()
    got = w = 0
    while got < arming:                      # (the Nano's bootloader eats the first ones)
        wait(t0 + w * Tns)
        ser.write(zero)
        got += records.next(ser, 2 * T) is not None
        w += 1
        if w * T > ARM_TIMEOUT_S or (not pace and w > 2 * arming):
            raise DeviceError(f"the FireFader sent {got} of {arming} records in "
                              f"{ARM_TIMEOUT_S:g} s while it was armed (no board on the "
                              "port, or another baud rate)")
    out = []
    stop = "end"
    latest = 0.0
    H = HAND_PASSES
    if watchdog is not None:
        watchdog.arm()
    error = None                             # the DeviceError that ended the run
    for j in range(starts):
        pos = frc = late = clamped = None
        try:
            put(zero)
            if pace:
                time.sleep(PAUSE_S)              # the silence rule: forces off, the hand
            else:
                ser.idle(PAUSE_S)
            records.clear(ser)
            pos = np.full((samples, P), np.nan)
            frc = np.zeros((samples, P))
            late = np.zeros(samples)
            clamped = np.zeros(samples, bool)
            f = np.zeros(P)
            t0 = time.monotonic_ns()
            # the loop's buffers, made once per record: a sample allocates no array
            x = np.empty(P)
            raw = np.empty(host.x.size)
            for w in range(H - 1 + samples):
                k = w - (H - 1)                   # the row this write's pass reads
                due = t0 + w * Tns
                wait(due)
                pk = (zero if k <= 0 else
                      encode_packet(*(max(force_counts(v, fs), -FORCE_MAX) for v in f)))
                owed = put(pk)
                lag = (time.monotonic_ns() - due) * 1e-9 if pace else 0.0
                latest = max(latest, lag)
                if lag > LATE_STOP_S:
                    stop = f"host late: a write {lag * 1e3:.0f} ms behind its time"
                    break
                rec, got = records.answers(ser, owed, REPLY_TIMEOUT_S, MERGE_WAIT_PERIODS * T)
                if rec is None:
                    stop = f"no record within {REPLY_TIMEOUT_S:g} s (the board lost)"
                    break
                if got < owed:
                    # the watchdog's zero writes in a stall, then this write, and the board
                    # merged packets that waited for its pass: no record says whose it is, and
                    # the run stops rather than take a reading a pass off its row
                    stop = (f"host late: the watchdog zeroed the forces in a "
                            f"{lag * 1e3:.0f} ms stall, and the board answered {got} "
                            f"of the {owed} packets within "
                            f"{MERGE_WAIT_PERIODS * T * 1e3:.0f} ms (it merges those that "
                            f"wait for its pass): which record is whose is lost")
                    break
                if k < 0:
                    continue
                for i in range(P):
                    x[i] = (float(rec[i]) - CENTRE) * METRES_PER_COUNT
                pos[k], late[k] = x, lag
                far = 0                           # the fader furthest out (no closure made)
                for i in range(1, P):
                    if abs(x[i]) > abs(x[far]):
                        far = i
                if abs(x[far]) > WORKSPACE_M:
                    stop = (f"safety: fader {'AB'[far]} {abs(x[far]) * 1e3:.1f} mm from the "
                            f"centre, beyond the workspace's {WORKSPACE_M * 1e3:.1f} mm")
                    break
                host.xp[:P] = pos[k - 1] if k > 0 else x
                host.x[:P] = x
                host.forces(out=raw)
                hit = False
                for i in range(P):
                    r, m = float(raw[i]), float(lim[i])
                    v = min(max(r, -m), m)
                    f[i] = v
                    c = max(force_counts(v, fs), -FORCE_MAX)
                    frc[k, i] = c * force_scale
                    hit = hit or abs(r) >= m or abs(round(v / force_scale)) > FORCE_MAX
                clamped[k] = hit
            # both faders at zero force, its record
            records.answers(ser, put(zero), REPLY_TIMEOUT_S, MERGE_WAIT_PERIODS * T)
        except DeviceError as exc:
            # the port failed in the middle of the run (a board unplugged, its process
            # ended): the run stops there with what it recorded, the board left to its
            # own watchdog (nothing more can be written)
            error = exc
            stop = f"device lost: {str(exc).splitlines()[0]}"
            if pos is not None:
                out.append({"position": pos, "force": frc, "late": late,
                            "clamped": clamped})
            break
        out.append({"position": pos, "force": frc, "late": late, "clamped": clamped})
        if progress is not None:
            progress(j + 1, starts)
        if stop != "end":
            break
    if watchdog is not None:
        watchdog.arm(False)
    return {"records": out, "stop": stop, "latest": latest, "watchdog_zeroed": zeroed[0],
            "error": error_record(error),
            "late_ticks": [int(np.sum(departures(r) > CUT_PERIODS * T)) for r in out]}


def usable_rows(rec: dict, period: float, delay: float) -> np.ndarray:
    """The rows of a record on its undisturbed stretches: cut, with the rows the forces
    then sent reach (``ceil(d) + 1`` more), at a write more than :data:`CUT_PERIODS`
    periods off its time (:func:`departures`: its force held that much longer or shorter;
    after a silence that may have reset
    the enables, :data:`hapsim.drivers.firefader.SILENCE_DOUBT_S`, the gate's
    :data:`~hapsim.drivers.firefader.GATE_PASSES` passes of zero force too), at a force
    at its clamp (the loop is not the linear one there) and where no record came.

    Parameters
    ----------
    rec : dict
        One of :func:`record_faders`'s records (``position``, ``late``, ``clamped``).
    period : float
        ``T`` [s].
    delay : float
        The scene's delay [periods].

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    from hapsim.drivers.firefader import GATE_PASSES, SILENCE_DOUBT_S
    N = rec["late"].size
    d = int(math.ceil(float(delay)))
    dep = departures(rec)
    bad = (dep > CUT_PERIODS * period) | rec["clamped"] \
        | ~np.isfinite(rec["position"]).all(axis=1)
    # a silence that may have reset the enables: the force is off for GATE_PASSES more
    gated = dep >= SILENCE_DOUBT_S[0]
    ok = np.ones(N, bool)
    for k in np.flatnonzero(bad):
        ok[max(k - 1, 0):k + d + 2 + (GATE_PASSES if gated[k] else 0)] = False
    return ok


def departures(rec: dict) -> np.ndarray:
    """Each write's departure from its time [s], shape (N,): ``|late - median(late)|``.

    The board sets a packet's forces when it comes and reads the pots ``adc_s`` later,
    so a lateness common to every write of a record shifts the whole loop's timing and
    leaves it the loop predicted (its holds all ``T``): the writes are on the grid
    ``t0 + median + k T``, and only their departures from it change a hold.

    Parameters
    ----------
    rec : dict
        One of :func:`record_faders`'s records (``late`` [s]).

    Returns
    -------
    ndarray
    """
    late = np.asarray(rec["late"], float)
    return np.abs(late - np.median(late))


def _bounds(rec: dict, period: float, quantum: float, force_scale: float):
    """Per row: the reading's and the force's error bounds [m], [N], shape (N, 2) each
    (module notes: half a count, and the write's lateness through the motion and the
    force's step)."""
    x = np.nan_to_num(rec["position"])
    dx = np.abs(np.diff(x, axis=0))
    v = (np.maximum(np.vstack([dx[:1], dx]), np.vstack([dx, dx[-1:]])) + quantum) / period
    lag = departures(rec)[:, None]
    reading = quantum / 2 + v * lag
    u = rec["force"]
    du = np.abs(np.diff(np.vstack([np.zeros((1, 2)), u]), axis=0))
    # row i's force goes out with the write that reads row i + 1: that write's lateness
    lag_next = np.vstack([lag[1:], lag[-1:]])
    force = force_scale / 2 + du * lag_next / period
    return reading, force


def measure_faders(scene, run: dict, amplitude: float, *, samples: int, order: int,
                   chk=None, force_scale: float, excluded=None) -> dict:
    """The felt matrices across the two faders from :func:`record_faders`'s records, and
    their verdict (module notes).

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
    run : dict
        :func:`record_faders`'s result.
    amplitude : float
        ``a`` [m].
    samples, order : int
        Rows per record, the fit's order (the coupled loop's states over 2).
    chk : hapsim.analysis.ports.PortsCheck, optional
        The prediction (computed when not given).
    force_scale : float
        The force per count [N].
    excluded : dict, optional
        ``{statement name: reason}``: statements the prediction before the run excluded
        (:func:`faders_feasibility`), never made here
        (:func:`hapsim.analysis.felt_matrices.felt_verdict`).

    Returns
    -------
    dict
        As :func:`hapsim.lockstep_ports.measure_felt_ports`'s (``measured``, ``predicted``,
        ``deviation``, ``bound``, ``verdict``, ``order``, ``records``, ``samples``; an
        incomplete run's ``measured`` has None matrices) with
        ``wire`` (:func:`hapsim.lockstep.wire_terms_nd`'s, ``reading_bound_m``,
        ``force_bound_n``), ``usable`` (rows per record), ``incomplete`` (why nothing was
        fitted, or None).
    """
    from hapsim.analysis.felt_matrices import felt_deviation, felt_directions, felt_verdict
    from hapsim.analysis.pencil import fit_felt_nd
    from hapsim.analysis.ports import check_ports, port_loop
    from hapsim.drivers.firefader import METRES_PER_COUNT
    from hapsim.lockstep_ports import ports_bound
    chk = check_ports(scene) if chk is None else chk
    T = scene.period
    delay = max(float(d.delay) for _, d in scene.devices)
    recs = run["records"]
    bound = ports_bound(scene, chk, amplitude)
    base = {"predicted": chk, "bound": bound, "order": order, "records": len(recs) - 1,
            "samples": samples}
    none = {"felt_stiffness": None, "felt_damping": None, "rendered_poles": [],
            "residual": None, "rank": None}

    def unmeasured(why, usable=()):
        return {**base, "measured": none, "deviation": None, "wire": None,
                "usable": list(usable), "incomplete": why,
                "verdict": {"verdict": "not measurable", "within": None, "uncertainty": None,
                            "reason": why, "statements": [],
                            "not_stated": ["felt stiffness", "felt damping"]}}
    if len(recs) < 5 or run["stop"] != "end":
        return unmeasured(f"the run stopped ({run['stop']}) after {len(recs)} of 5 records"
                          if run["stop"] != "end" else "fewer than 5 records")
    ok = [usable_rows(r, T, delay) for r in recs]
    rest = recs[0]["position"]
    D = decimation(chk, T)
    Nd = len(range(0, samples, D))
    diffs = [(r["position"] - rest)[::D] for r in recs[1:]]
    use = [_decimated(u & ok[0], D) for u in ok[1:]]
    mass = port_loop(scene)[0].mass
    try:
        fit = fit_felt_nd(diffs, mass, D * T, FIT_ORDER, usable=use)
    except ConfigError as exc:                # the stretches left hold too few equations
        return unmeasured(f"the host's late writes cut the records to "
                          f"{[int(u.sum()) for u in ok]} rows of {samples}: {exc}",
                          [int(u.sum()) for u in ok])
    dev = felt_deviation(fit, chk)
    bounds = [_bounds(r, T, METRES_PER_COUNT, force_scale) for r in recs]
    wire = _decimated_wire(scene, chk, diffs, use, mass, bounds, D, Nd)
    wire.update(reading_bound_m=float(max(np.max(b[0]) for b in bounds)),
                force_bound_n=float(max(np.max(b[1]) for b in bounds)), decimation=D)
    v = felt_verdict(dev, bound, wire, directions=felt_directions(fit, chk),
                     excluded=excluded)
    return {**base, "measured": fit, "deviation": dev, "wire": wire, "verdict": v,
            "order": FIT_ORDER, "usable": [int(u.sum()) for u in ok], "incomplete": None}


def decimation(chk, period: float) -> int:
    """The records' decimation ``D``: every ``D``-th sample, so the fastest rendered mode
    has :data:`SAMPLES_PER_CYCLE` samples a cycle (at least 1).

    Parameters
    ----------
    chk : hapsim.analysis.ports.PortsCheck
    period : float
        ``T`` [s].

    Returns
    -------
    int
    """
    from hapsim.analysis.ths import continuous_poles
    s = continuous_poles(chk.render.rendered_poles, period)
    f = float(np.max(np.abs(s.imag))) / (2 * math.pi) if s.size else 0.0
    return max(1, int(1.0 / (SAMPLES_PER_CYCLE * f * period))) if f > 0 else 1


def _decimated(ok, D: int) -> np.ndarray:
    """Decimated sample ``j`` is usable when every row from the one after sample
    ``j - 1`` to row ``D j`` is (an equation spans undisturbed rows only); sample 0
    never (its rows before it hold the hold's and the delay's fast modes' start)."""
    Nd = len(range(0, ok.size, D))
    out = np.zeros(Nd, bool)
    for j in range(1, Nd):
        out[j] = bool(ok[D * (j - 1) + 1:D * j + 1].all())
    return out


def _decimated_wire(scene, chk, diffs, use, mass, bounds, D: int, Nd: int) -> dict:
    """The wire's term of the decimated fit: every row's errors, through the loop, onto
    the decimated samples. An error at row ``D j' - o`` (``0 <= o < D``) reaches sample
    ``j`` through the loop's response at lag ``D (j - j') + o``: for each ``o`` a
    convolution in ``j - j'`` (:func:`hapsim.lockstep.wire_terms_nd` with the responses
    ``R[D m + o]`` and the bounds of rows ``D j' - o``); the classes of rows are
    disjoint, so their worst cases add (Hoelder over all rows)."""
    from hapsim.lockstep import wire_terms_nd
    from hapsim.lockstep_ports import port_error_responses
    Rr, Rf = port_error_responses(scene, D * Nd)
    T = scene.period
    out = None
    eye = np.eye(2)
    for o in range(D):
        lag = D * np.arange(Nd) + o
        rows = D * np.arange(Nd) - o

        def at(b):
            x = np.zeros((Nd, 2))
            x[rows >= 0] = b[rows[rows >= 0]]
            return x
        w = wire_terms_nd(scene, diffs, chk, FIT_ORDER,
                          [("reading", eye, [at(b[0]) for b in bounds]),
                           ("force", eye, [at(b[1]) for b in bounds])],
                          usable=use, mass=mass, responses=(Rr[lag], Rf[lag]),
                          period=D * T, box=True)
        if out is None:
            out = w
            continue
        for q in ("felt_stiffness", "felt_damping"):
            out[q] += w[q]
            out["directions"][q] = [a + b for a, b in zip(out["directions"][q],
                                                          w["directions"][q])]
    return out


def faders_feasibility(scene, amplitude: float, samples: int, chk=None) -> dict:
    """What a run of the two faders can state, predicted before it: the same records and
    measurement (:func:`record_faders`, :func:`measure_faders`) on the emulated board in
    its lockstep clock, in-process (asked for by name: the pots' and the forces' rounding
    alone, no host timing). In real time the host's late writes add their bounds to the
    wire's term, and what is not stated here is not stated there
    (:func:`run_faders` passes it as excluded: a term over the box is a sampled maximum,
    and a smaller one at other records is no better evidence).

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
        The FireFader's two faders (:func:`faders_refusal` passed).
    amplitude : float
        ``a`` [m].
    samples : int
        Rows per record.
    chk : hapsim.analysis.ports.PortsCheck, optional
        The prediction (default :func:`hapsim.analysis.ports.check_ports`).

    Returns
    -------
    dict
        ``stated``, ``not_stated`` (the statements' names), ``verdict`` (the lockstep
        run's) and ``statement``: None when something is stated, else the sentence the
        run says before it starts.
    """
    from hapsim.analysis.ports import check_ports
    from hapsim.drivers.firefader import FireFader
    from hapsim.emulated.firefader_board import FireFaderDevice
    from hapsim.lockstep import excitation_starts
    chk = check_ports(scene) if chk is None else chk
    drv = FireFader()
    starts = excitation_starts(2, amplitude, scene.period)
    (_, da), (_, db) = scene.devices
    dev = FireFaderDevice(da, scene.rate_hz, None, clock="lockstep", device_b=db,
                          hand=[(x0[0], x0[1], v0[0], v0[1]) for x0, v0 in starts],
                          **drv.mock_hardware())
    run = record_faders(LockstepBoardLink(dev), scene, samples, len(starts),
                        force_scale=drv.force_scale, pace=False)
    v = measure_faders(scene, run, amplitude, samples=samples, order=chk.states // 2,
                       chk=chk, force_scale=drv.force_scale)["verdict"]
    stated = [st["name"] for st in v["statements"] if st["verdict"] != "not measurable"]
    not_stated = [st["name"] for st in v["statements"] if st["verdict"] == "not measurable"]
    said = None
    if not stated:
        said = ("not measurable, predicted before the run (the emulated board in lockstep, "
                f"the 8-bit pots' and the forces' rounding alone, a = {amplitude:g} m): "
                f"{v['reason']}")
    return {"stated": stated, "not_stated": not_stated, "verdict": v["verdict"],
            "statement": said}


def run_faders(scene, options, amplitude: float | None = None, *, by: str = "field",
               samples: int | None = None, board: dict | None = None):
    """:func:`hapsim.api.run` of the FireFader's two faders in real time: the embedded
    emulated board on its own wall clock (or the board on ``options.port``), the host's
    loop (:func:`record_faders`) and the measurement (:func:`measure_faders`).

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
        Two ports, both devices ``protocol: firefader``.
    options : hapsim.pipeline.options.RunOptions
        ``port``, ``driver`` (``firefader``), ``allow_unstable``, ``rt_priority``,
        ``seed`` (the emulated board's); any other option set is refused by name.
    amplitude : float, optional
        ``a`` [m] (default :data:`FADER_AMPLITUDE`).
    by : {"field", "flag"}
        Name a refused option by its field or its flag.
    samples : int, optional
        Rows per record (default :func:`hapsim.lockstep.default_samples`).
    board : dict, optional
        The emulated board's own keywords over the defaults (tests:
        ``clock="lockstep"``, asked by name).

    Returns
    -------
    dict
        :func:`measure_faders`'s, with ``amplitude`` [m] and ``realtime``: ``stop``,
        ``late_ticks`` per record, ``latest`` [s], ``usable`` rows per record,
        ``held_at_end`` (each fader's force when the host left [N], from the emulated
        board's report; None on a port), ``port``
        (:func:`hapsim.api.running.run_scene_ports` makes it the run's report).

    Raises
    ------
    ConfigError
        Not the two faders of one FireFader (:func:`faders_refusal`); an option not taken.
    UnstableConfigError
        The coupled loop is unstable and ``allow_unstable`` is false.
    DeviceError
        The port cannot be opened, or the board does not answer while it is armed. A
        port that fails later ends the run (``realtime.stop`` "device lost: ...",
        ``error`` its type and message) with what it recorded.
    """
    import dataclasses

    import serial

    from hapsim.analysis.ports import stable_ports_check
    from hapsim.drivers.firefader import FireFader, encode_packet
    from hapsim.drivers.urlhandler import serial_for_url
    from hapsim.host.realtime import RealtimePriority
    from hapsim.lockstep import default_samples, excitation_starts
    from hapsim.pipeline.felt_run import refuse_options
    name = (lambda f: "--" + f.replace("_", "-")) if by == "flag" else (lambda f: f)
    why = faders_refusal(scene, options)
    if why is not None:
        raise ConfigError(why, key=name("driver") if why.startswith("driver") else "devices")
    refuse_options(options, by, FADERS_TAKES, "the real-time run of two faders",
                   "it takes " + ", ".join(name(f) for f in FADERS_TAKES
                                           + ("amplitude",)))
    a = FADER_AMPLITUDE if amplitude is None else float(amplitude)
    if not (math.isfinite(a) and 0 < a <= WORKSPACE_M / 4):
        raise ConfigError(f"must be a positive length up to {WORKSPACE_M / 4:g} m (a "
                          f"quarter of the workspace), got {amplitude!r}", key=name("amplitude"))
    chk = stable_ports_check(scene, options.allow_unstable, name("allow_unstable"))
    order = chk.states // 2
    N = default_samples(order, 2) if samples is None else int(samples)
    T = scene.period
    starts = excitation_starts(2, a, T)
    # before the run: what can its records state at all (the pots' rounding alone)? Said
    # first, then run (the real-time records may state less, never more)
    pre = faders_feasibility(scene, a, N, chk)
    if pre["statement"] is not None and getattr(options, "on_precheck", None) is not None:
        options.on_precheck(pre["statement"])
    drv = FireFader()
    mock = None
    port = options.port
    (_, dev_a), (_, dev_b) = scene.devices
    if port is None:
        from hapsim.emulated.driver_mock import EmbeddedDriverMock
        from hapsim.scene import Excitation
        opts = {**drv.mock_hardware(), "clock": "wall", "device_b": dataclasses.asdict(dev_b),
                "hand": [[float(x0[0]), float(x0[1]), float(v0[0]), float(v0[1])]
                         for x0, v0 in starts], **(board or {})}
        if not math.isfinite(opts["device_b"]["force_limit"]):
            opts["device_b"]["force_limit"] = None
        mock = EmbeddedDriverMock("firefader", dev_a, Excitation(), scene.rate_hz,
                                  seed=options.seed, options=opts)
        port = mock.port
    report = None
    try:
        try:
            ser = serial_for_url(port, baudrate=drv.baud, timeout=0, write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open port {port}: {exc}") from None
        if mock is not None:
            mock.release_slave()
        wd, wd_why = None, "a board in lockstep: its time is the writes'"
        if (board or {}).get("clock", "wall") == "wall":
            from hapsim.drivers.resync import HOLD_BOUND_S
            from hapsim.drivers.torque_watchdog import start_watchdog
            wd, wd_why = start_watchdog(port, encode_packet(0, 0), HOLD_BOUND_S, ser=ser)
        try:
            with RealtimePriority(options.rt_priority or 0):
                run = record_faders(ser, scene, N, len(starts),
                                    force_scale=drv.force_scale,
                                    arming=drv.arming_records, watchdog=wd)
        finally:
            from hapsim.drivers.torque_watchdog import watchdog_report
            wd_report = watchdog_report(wd, wd_why)
            if wd is not None:
                wd.close()
            try:
                _zero(ser)                     # both faders at zero force, its pass run
            except Exception:  # best effort: the port may be gone
                pass
            ser.close()
    finally:
        if mock is not None:
            mock.end()
            report = mock.report()
            mock.close()
    # what the lockstep records do not state, the real-time ones do not either: their
    # term over the box is a sampled maximum at other records, no better evidence
    why = ("not stated, predicted before the run: the wire's term over the errors' box on "
           "the same records in lockstep is beyond the limit")
    res = measure_faders(scene, run, a, samples=N, order=order, chk=chk,
                         force_scale=drv.force_scale,
                         excluded={n: why for n in pre["not_stated"]})
    held = (None if report is None else
            [report.get("held_at_end"), report.get("held_b_at_end")])
    res["error"] = run["error"]           # the board lost in the middle of the run
    res["realtime"] = {"stop": run["stop"], "late_ticks": run["late_ticks"],
                       "latest": run["latest"], "usable": res["usable"],
                       "held_at_end": held,
                       # the host's watchdog; the emulated board's longest hold [s]
                       "watchdog": dict(wd_report, zeroed=run.get("watchdog_zeroed", 0)),
                       "board_longest_hold_s": (None if report is None
                                                else report.get("longest_hold_s")),
                       "port": options.port or "embedded emulated FireFader (wall clock)"}
    res["amplitude"] = a
    if pre["statement"] is not None:
        res["stated_before_run"] = pre["statement"]
    return res
