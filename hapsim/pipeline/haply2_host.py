"""The Haply 2DIY measured in real time: the felt matrices of a pantograph scene from five
records of the host's real-time loop against a board behind a port, and their verdict
(:func:`measure_felt_haply2_port`).

The records are :func:`hapsim.pipeline.haply2_record.record_realtime`'s (the loop on the
host's clock, its estimated samples, its re-synchronisations, its host stalls: the module
notes of :mod:`hapsim.pipeline.haply2_record`); the emulated board behind a pty is
:class:`hapsim.pipeline.haply2_embedded.Embedded2DIY`. Before any record, each joint's
wiring is checked (:mod:`hapsim.drivers.haply2_probe`): a joint its direction bytes turn
backwards is refused. An estimated sample's error is bounded (:func:`estimate_bounds`),
and the records' verdict is :func:`hapsim.emulated.haply2_verdict.felt_verdict_of_runs`:
the estimated rows' bounds enter the wire's term through the loop as reading errors do.
The loop is linear and time-invariant between disturbances, so a record is cut at each
(a stall, a run of missing replies, a zeroed tick, a re-synchronisation, a torque at the
clamp, a hold far off a period: :func:`usable_rows`) and its undisturbed stretches are
fitted jointly, each a free response of the same loop. On a board that keeps its own
time each torque acts from when the board takes its write to when it takes the next: the
holds' departures from a period, from the host's write times, are changes of the
device's state (:func:`hold_bounds`): known with their signs, they are estimated and
their motion through the loop removed from the records (:func:`hold_corrections`,
:func:`hold_motion`, dimension-free in :mod:`hapsim.analysis.write_holds`), and what
that estimate leaves enters the stated uncertainty.

``python -m hapsim.pipeline.haply2_host`` still starts the emulated board's child
(:func:`hapsim.pipeline.haply2_embedded.main`, its own entry since the split).
"""

from __future__ import annotations

import math
import sys

import numpy as np

from hapsim.analysis.write_holds import (HOLD_CUT_PERIODS, hold_bounds, hold_corrections,
                                         hold_motion)
from hapsim.emulated.haply2_board import PASS_S, in_hand_order
from hapsim.emulated.haply2_verdict import felt_verdict_of_runs
from hapsim.drivers.haply import MAX_TORQUE
from hapsim.drivers.haply2 import Haply2DIY
from hapsim.errors import ConfigError, DeviceError, error_record
from hapsim.pipeline.haply2_record import (ARM_TIMEOUT, ENVELOPE_RAD, WORKSPACE_RAD, PortLink,
                                           record_realtime)

# hold_bounds, hold_corrections, hold_motion, HOLD_CUT_PERIODS: dimension-free since the
# Haply M3 uses them too (hapsim.analysis.write_holds), named here as before
__all__ = ["estimate_bounds", "hold_bounds", "hold_corrections", "hold_motion",
           "measure_felt_haply2_port", "usable_rows", "HOLD_CUT_PERIODS", "WORKSPACE_RAD"]


#: How much the time a board takes a write may vary from one write to the next beyond
#: what the host's own write times show [s], before a departure beyond the stated
#: uncertainty is called "differs" on a board that keeps its own time
#: (:func:`measure_felt_haply2_port`): one pass of firmware V1.5's loop (``.ino`` lines
#: 59-64: a command waits for the next pass, at most 50 us). Not covered: a link whose
#: latency varies more (a USB frame's scheduling, an emulated board's process
#: descheduled); a departure within what this allowance explains stays "not measurable".
LINK_JITTER_S = PASS_S


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
    scene : hapsim.scene.SceneND
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


def usable_rows(rec: dict, delay: int, *, lockstep_board: bool = False,
                T: float | None = None) -> np.ndarray:
    """The rows of a record that belong to an undisturbed stretch of the loop: the record
    cut where an input no account names acted (issue 29: measure only what is known).

    Between disturbances the loop is linear and time-invariant, so each stretch between
    them is a free response of the same loop from its own initial state, which the fit
    of the felt matrices takes jointly with every other
    (:func:`hapsim.analysis.pencil.fit_felt_nd`'s ``usable``). Left out, with ``d`` the
    scene's delay (the torques written before a cut act up to ``d`` ticks after it):

    * a host stall at tick ``s`` (a board on its own clock held the torque over more
      than a period; not on a lockstep board, which waited): rows ``s - 1 .. s + d + 1``;
    * each run ``[r0, r1]`` of estimated rows (a reply not read by its tick, or a damaged
      one: the write may have been parsed from the wrong bytes, firmware V1.5 has no
      framing, and a torque zeroed for want of a fresh sample is one too): rows
      ``r0 - 1 .. r1 + d + 1`` -- unless every reply of rows ``r0 .. r1 + d + 1`` came,
      late (``readings`` finite) and no re-synchronisation is among them: the board
      answered each of those writes in order, so it parsed them in step (a lost host
      byte makes it complete a write with the next one's first byte and parse the rest
      of that one out of step, whose reply never comes), and the rows are measured with
      their estimates' bounds (:func:`estimate_bounds`), unless a realigning marker
      (``probed``) is among them or the two rows their estimates start from (the
      torques held over its tick are a hold the estimates do not know of);
    * a re-synchronisation at tick ``s`` (the board out of step since the run of missing
      or damaged replies before it, then zero torque and the set-up; the emulated board's
      hand restarts the handle there): from that run's first row - 1 to ``s + d + 1``;
    * with the period ``T`` and the host's write times (``write_s``) of a board on its
      own clock: a hold more than :data:`HOLD_CUT_PERIODS` off a period (write ``k``
      began that far from one period after write ``k - 1``; a host late, not yet a
      stall): rows ``k - 1 .. k + d + 1`` (the smaller ones are corrected,
      :func:`hold_corrections`);
    * a realigning marker at tick ``k`` (``probed``: the tick's command a write to no
      port, the torques of the write before held over it,
      :mod:`hapsim.pipeline.haply2_realign`): rows ``k - 1 .. k + d + 1``;
    * a torque written at the board's clamp at tick ``k`` (the loop not the linear one
      there): rows ``k - 1 .. k + d + 1``;
    * the last ``d + 2`` rows when the closing zero write's reply did not come in step
      (the board may have been out of step at the end).

    A stretch gives the fit ``len - p`` equations (``p`` its order): one shorter than
    ``p + 1`` rows gives none.

    Parameters
    ----------
    rec : dict
        :func:`record_realtime`'s record (``estimated``, ``readings``, ``stalled``,
        ``resynced``, ``joints``, ``torque``, ``rearmed_at_end``), N rows.
    delay : int >= 0
        The scene's delay ``d`` [ticks].
    lockstep_board : bool, optional
        The board advanced one period per write: a host stall is no disturbance.
    T : float, optional
        The period [s]: holds far off it are cut (above; not without it).

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    est = np.asarray(rec["estimated"], bool).copy()
    N = est.size
    joints = np.asarray(rec.get("joints", np.zeros((N, 2))), float)
    est |= ~np.isfinite(joints).all(axis=1)         # a damaged reply: no reading
    d = max(int(delay), 0)
    bad = np.zeros(N + 1, np.int64)

    def cut(a, b):                                  # rows a .. b
        a, b = max(int(a), 0), min(int(b), N - 1)
        if a <= b:
            bad[a] += 1
            bad[b + 1] -= 1
    read = np.isfinite(np.asarray(rec.get("readings", np.full((N, 2), np.nan)),
                                  float)).all(axis=1)
    resynced = np.asarray(rec.get("resynced", np.zeros(N, bool)), bool)
    probed = np.asarray(rec.get("probed", np.zeros(N, bool))).astype(bool)
    edge = np.diff(np.concatenate(([0], est.astype(np.int8), [0])))
    r0s, r1s = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1) - 1
    for r0, r1 in zip(r0s, r1s):
        span = slice(r0, min(r1 + d + 2, N))
        if (read[span].all() and not resynced[span].any()
                and not probed[max(r0 - 2, 0):span.stop].any()):
            continue                                # late replies, in step
        cut(r0 - 1, r1 + d + 1)
    if not lockstep_board:
        for s_ in np.flatnonzero(np.asarray(rec.get("stalled", np.zeros(N, bool)), bool)):
            cut(s_ - 1, s_ + d + 1)
    for s_ in np.flatnonzero(np.asarray(rec.get("probed", np.zeros(N, bool)), bool)):
        cut(s_ - 1, s_ + d + 1)                     # a realigning marker's held torque
    for s_ in np.flatnonzero(resynced):
        a = s_
        while a > 0 and est[a - 1]:
            a -= 1
        cut(a - 1, s_ + d + 1)
    if not lockstep_board and "write_s" in rec and T is not None and N > 1:
        b = np.asarray(rec["write_s"], float)[:, 0]
        off = np.abs(np.diff(b) - T)
        for k in np.flatnonzero(~(off <= HOLD_CUT_PERIODS * T)) + 1:
            cut(k - 1, k + d + 1)
    if "torque" in rec:
        tq = np.abs(np.asarray(rec["torque"], float))
        for k in np.flatnonzero((tq >= np.float32(MAX_TORQUE)).any(axis=1)):
            cut(k - 1, k + d + 1)
    if rec.get("rearmed_at_end"):
        cut(N - d - 2, N - 1)
    return np.cumsum(bad[:N]) == 0


def measure_felt_haply2_port(port: str, scene, generation: str = "gen3", *,
                             amplitude: float, resolution: float | None = None,
                             samples: int | None = None, progress=None, plan=None,
                             probe_wiring: bool = True,
                             directions: dict | None = None,
                             lockstep_board: bool = False, excluded=None) -> dict:
    """The felt matrices of a pantograph scene measured through a 2DIY in real time, and
    their verdict (module notes; the loop's: :mod:`hapsim.pipeline.haply2_record`).

    Parameters
    ----------
    port : str or serial-like
        The board's serial port (or
        :class:`hapsim.pipeline.haply2_embedded.Embedded2DIY`'s pty), or an open object
        with ``in_waiting``, ``read``, ``write`` (left open).
    scene : hapsim.scene.SceneND
        A 2-D pantograph scene.
    generation : {"gen2", "gen3"}
    amplitude : float
        The hand's ``a`` [m] (the board's: the linearisation bound is stated at it).
    resolution : float, optional
        The set-up's counts per revolution (default the generation's).
    samples : int, optional
        Ticks per record (default :func:`hapsim.lockstep.default_samples`).
    progress : callable, optional
    plan : tuple, optional
        :func:`hapsim.lockstep.identification_plan`, already computed.
    probe_wiring : bool, optional
        Check each joint's wiring first (:func:`hapsim.drivers.haply2_probe.
        find_directions`): a joint its direction bytes turn backwards is refused before
        any torque loop runs (the records are then put in the emulated board's hand
        order, :func:`hapsim.emulated.haply2_board.in_hand_order`).
    directions : dict, optional
        ``motor_direction`` / ``encoder_direction`` bytes instead of the generation's.
    lockstep_board : bool, optional
        The board advances one period per write (an emulated board in lockstep, asked
        for by name): a host stall then costs its record nothing (the board waited), and
        a stalled record is measured whole. False (a real board, or one on the wall
        clock): a record is cut at each host stall, and measured on its stretches
        (module notes).

    excluded : dict, optional
        ``{statement name: reason}``: statements the prediction before the run excluded
        (the same records in lockstep, :func:`hapsim.emulated.haply2_lockstep.
        measure_felt_haply2`), never made here
        (:func:`hapsim.emulated.haply2_verdict.felt_verdict_of_runs`).

    Returns
    -------
    dict
        :func:`hapsim.emulated.haply2_verdict.felt_verdict_of_runs`'s, with ``estimated``
        (estimated samples per record), ``late_ticks`` (per record), ``replies``
        (replies read per record, of ``writes`` and ``rearm_writes``), ``left`` and
        ``brake`` per record (the tick the joints left the envelope, -1 if none; the
        braking after it,
        :func:`record_realtime`'s, or None), ``resyncs`` (the loop's
        re-synchronisations, the re-arming at a record's end, and those after the
        watchdog's robust writes) and ``skipped`` (bytes
        that made no reply) per record, ``stalls`` (host stalls per record),
        ``watchdog`` (:func:`hapsim.drivers.torque_watchdog.watchdog_report`'s, with per
        record ``zeroed``, ``replies`` and ``resyncs``: its writes, their replies dropped,
        its robust writes each followed by the host's re-arming),
        ``held_zero`` (ticks written at zero torque for want of a fresh sample,
        :data:`hapsim.pipeline.haply2_record.HOLD_BOUND_S`), ``probes`` and
        ``realigned`` per record (markers sent, and their answers that moved the count of
        replies: :mod:`hapsim.pipeline.haply2_realign`) and ``usable`` (rows per
        record left after the cuts at those disturbances, :func:`usable_rows`; the
        stretches are fitted jointly, ``fitted_rows``): "not measurable" with the reason
        when the stretches hold too few equations for the fit. On a board on its own
        clock the records are corrected for the host's write timing and the stated
        uncertainty counts what the correction leaves (:func:`hold_corrections`,
        ``wire["hold_s"]``); a "differs" there stands only when the departure is beyond
        the uncertainty with :data:`LINK_JITTER_S` of unseen latency variation too
        (``link_uncertainty``), else "not measurable" with the departure in the reason.
        ``stop`` ("end") and ``error`` (None). A board lost after the first record
        (:func:`record_realtime`'s DeviceError) ends the run there: the records made are
        counted, nothing is fitted (``measured`` None), the verdict is "not measurable",
        ``stop`` is "device lost: ..." and ``error`` its type and message.

    Raises
    ------
    DeviceError
        As :func:`record_realtime`, before the first record was made; the port cannot be
        opened.
    ConfigError
        Not a 2-D pantograph scene.
    IdentificationError
        A joint wired backwards against its direction bytes (the probe's refusal).
    """
    import serial

    from hapsim.drivers.urlhandler import serial_for_url
    from hapsim.kinematics import device
    from hapsim.lockstep import identification_plan
    if scene.dimension != 2 or scene.device is None or scene.device.kind != "pantograph":
        raise ConfigError("the Haply 2DIY drives a 2-D scene with a pantograph device",
                          file=scene.path, key="device.kind")
    chk, order, N = identification_plan(scene, samples) if plan is None else plan
    drv = Haply2DIY(generation, resolution=resolution, **(directions or {}))
    own = isinstance(port, str)
    try:
        ser = (serial_for_url(port, baudrate=115200, timeout=0, write_timeout=1.0)
               if own else port)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceError(f"cannot open port {port}: {exc}") from None
    from hapsim.drivers.device_port import DevicePort
    ser = DevicePort.of(ser, "the 2DIY")         # its failures: DeviceError
    from hapsim.engine import Engine
    Engine(scene).step()               # the compiled kernels loaded before the clock
    runs = []
    probe = None
    wd, wd_why = None, "a lockstep board: its time is the writes'"
    ended = False
    lost = None                 # the DeviceError that ended the records after the first
    if not lockstep_board:
        # the board has no watchdog: the host's beside it (hapsim.drivers.host_watchdog)
        # with its robust write (the loop's re-arming: a board whose parser lost its
        # place takes no zero command; hapsim.pipeline.haply2_record.watchdog_robust)
        from hapsim.drivers.resync import HOLD_BOUND_S
        from hapsim.drivers.torque_watchdog import start_watchdog
        from hapsim.pipeline.haply2_record import watchdog_robust
        wd, wd_why = (start_watchdog(port, drv.write_bytes((0.0, 0.0)), HOLD_BOUND_S,
                                     robust=watchdog_robust(drv, scene), ser=ser)
                      if own else (None, "a port object, not a device file"))
    try:
        if probe_wiring:
            from hapsim.errors import IdentificationError
            # each joint's wiring before any torque loop runs (paced on the host's clock:
            # a board on its own clock moves in real time; a lockstep board advances one
            # period per write: unpaced, each reply waited for)
            from hapsim.emulated.haply2_board import PROBE_ENVELOPE, PROBE_TORQUE
            from hapsim.drivers.haply2_probe import find_directions
            try:
                probe = find_directions(drv, PortLink(ser),
                                        [math.degrees(v) for v in scene.device.joints],
                                        force_limit=PROBE_TORQUE, envelope=PROBE_ENVELOPE,
                                        rate_hz=scene.rate_hz, pace=not lockstep_board,
                                        timeout=0.5,
                                        first_timeout=ARM_TIMEOUT)
            except IdentificationError:
                ended = True                # (the probe's refusal: its stop made, in step)
                raise
        for j in range(5):
            try:
                runs.append(record_realtime(ser, drv, scene, N,
                                            lockstep_board=lockstep_board,
                                            running=j > 0 or probe is not None,
                                            watchdog=wd))
            except DeviceError as exc:
                if not runs:
                    raise                   # lost before any record: the error alone
                lost = exc                  # the records made by then are reported
                break
            if progress is not None:
                progress(j + 1, 5)
        ended = lost is None
    finally:
        from hapsim.drivers.torque_watchdog import watchdog_report
        wd_report = watchdog_report(wd, wd_why)
        if wd is not None:
            wd.close()
        if own:
            try:
                # a run cut short (Ctrl-C, an error) may have left the board's parser out
                # of step, where the zero command reaches no motor: the re-arming then
                # (zero torque whatever the parser is inside; the watchdog, closed, makes
                # no dying write); a record's end left it in step
                if ended or lockstep_board:
                    ser.write(drv.write_bytes((0.0, 0.0)))
                else:
                    from hapsim.pipeline.haply2_record import watchdog_robust
                    ser.write(watchdog_robust(drv, scene)[0])
                ser.flush()
            except Exception:  # best effort: the port may be gone
                pass
            ser.close()
    J = device("pantograph", scene.device.geometry).jacobian(scene.device.joints)
    ang = np.max([np.nanmax(np.abs(r["joints"]), axis=0) for r in runs], axis=0)
    delta = math.pi / drv.resolution + np.radians(
        np.spacing(np.float32(np.degrees(ang))).astype(float))
    d = int(math.ceil(float(scene.device.delay)))
    for r in runs:
        if r["estimated"].any():
            r["bounds"] = estimate_bounds(r, scene, J, delta)
        # the record cut at its disturbances (host stalls, re-synchronisations, missing
        # replies): each stretch between them a free response of the loop, fitted jointly
        # (before, one re-synchronisation or stall made the whole run "not measurable":
        # 0 of 10 runs with 1 byte in 200 lost, 5 of 10 beside two CPU-bound processes)
        r["usable"] = usable_rows(r, d, lockstep_board=lockstep_board, T=scene.period)
        if not lockstep_board and float(scene.device.delay) == 1.0 and "write_s" in r:
            # the host's write times: each torque held over its real interval, not one
            # period (hold_bounds); a lockstep board's holds are exact periods (no term).
            # The board's own delay of one period only: a scene stating more delays the
            # torques on the board's clock, not at the writes.
            # The holds' known (signed) departures corrected: the estimated state changes'
            # motion through the loop removed from the record, only the estimate's
            # remainder in the uncertainty (hold_corrections; the worst case of each
            # hold's sign let 6 of 10 correct runs leave the damping unstated), and the
            # same with the link's unseen latency for a "differs" (below)
            # (row 0's write is the arming's zero write: the first hold's torque is 0)
            hc = hold_corrections(r, scene, J, delta, first_torque=(0.0, 0.0))
            r["holds_link"] = hold_corrections(r, scene, J, delta, latency_s=LINK_JITTER_S,
                                               first_torque=(0.0, 0.0))
            w_hat = np.where(np.asarray(r["usable"], bool)[:, None], hc["state"], 0.0)
            r["position"] = np.asarray(r["position"], float) - hold_motion(scene, w_hat)
            r["holds"] = hc
    if lost is not None:
        return _lost_result(chk, runs, lost, wd_report, probe)
    runs = in_hand_order(runs, 0 if probe is None else probe.setups)
    out = felt_verdict_of_runs(scene, runs, (chk, order, N), drv.resolution, amplitude,
                               excluded=excluded)
    out["direction_probe"] = None if probe is None else probe.to_dict()
    counts = _record_counts(runs, wd_report)
    left = counts["left"]
    if any(v >= 0 for v in left):
        # the joints left the measurement's envelope (braked, then zero torque from
        # there): the loop was not the linear one predicted, whatever else the records say
        out.update(verdict="not measurable", within=None, uncertainty=None,
                   statements=[], not_stated=["felt stiffness", "felt damping"],
                   reason=f"the joints left the measurement's envelope ({ENVELOPE_RAD:g} "
                          f"rad from the operating point) in {sum(v >= 0 for v in left)} "
                          "records: " + ("braked to rest, then zero torque"
                                         if scene.safety.brake else "zero torque written")
                          + " from there (the host too late for the scene's loop, or a "
                          "torque held over its stalls)")
    if not lockstep_board and out.get("verdict") == "differs":
        # A board on its own clock held each torque from when it took the write to when
        # it took the next. The stated uncertainty counts the host's own write times
        # (hold_bounds), not how the link's latency varied (unseen by the host): the
        # departure is called "differs" only if it is beyond the uncertainty with that
        # latency varying by up to LINK_JITTER_S too; otherwise not measurable,
        # the departure kept (before any write-timing term: 4 of 10 correct runs
        # "differed" by 0.6-0.7 % in the felt stiffness)
        jitter = LINK_JITTER_S
        link = None
        if any("holds" in r for r in runs):
            for r in runs:
                if "holds" in r:
                    # the same correction (the signed holds from the host's write times),
                    # its remainder with the unseen latency varying by the jitter
                    r["holds"] = r["holds_link"]
            link = felt_verdict_of_runs(scene, runs, (chk, order, N), drv.resolution,
                                        amplitude, excluded=excluded)
        dev_txt = ", ".join(f"{k} {v:.3g}" for k, v in (out.get("deviation") or {}).items()
                            if isinstance(v, (int, float)))
        if link is not None and link.get("verdict") == "differs":
            out["link_uncertainty"] = link["uncertainty"]
            out["reason"] = (f"{out['reason']}; beyond the uncertainty with the link's "
                             f"latency varying by up to {jitter * 1e6:.0f} us between writes "
                             "too (" + ", ".join(
                                 f"{k} {v:.3g}" for k, v in
                                 (link.get("uncertainty") or {}).items()
                                 if isinstance(v, (int, float))) + ")")
        else:
            out.update(verdict="not measurable", within=None, statements=[],
                       not_stated=["felt stiffness", "felt damping"],
                       reason="the board keeps its own time: a departure beyond the stated "
                              "uncertainty (" + dev_txt + ") "
                              + ("is within what the link's latency, unseen by the host, "
                                 f"varying by up to {jitter * 1e6:.0f} us between writes "
                                 "could make" if link is not None else
                                 "is not told from the host's write timing (no write times "
                                 "recorded, or a scene delay other than the board's one "
                                 "period)")
                              + " (rerun with the board in lockstep to measure the loop)")
    out.update(counts)
    out["stop"], out["error"] = "end", None
    return out


def _record_counts(runs: list, wd_report: dict) -> dict:
    """What each record of a real-time run counted (:func:`measure_felt_haply2_port`'s
    per-record entries: ``estimated``, ``stalls``, ``held_zero``, ``usable``,
    ``late_ticks``, ``replies``, ``writes``, ``rearm_writes``, ``resyncs`` with the
    host's re-armings after the watchdog's robust writes, ``skipped``, ``realigned``,
    ``probes``, ``left``, ``brake``, and ``watchdog``: ``wd_report`` with its writes per
    record)."""
    return dict(
        estimated=[int(r["estimated"].sum()) for r in runs],
        stalls=[int(r["stalled"].sum()) for r in runs],
        held_zero=[int(r["held_zero"]) for r in runs],
        usable=[int(np.count_nonzero(r["usable"])) for r in runs],
        late_ticks=[r["late_ticks"] for r in runs],
        replies=[r["replies"] for r in runs], writes=[r["writes"] for r in runs],
        rearm_writes=[r.get("rearm_writes", 0) for r in runs],
        resyncs=[r["resyncs"] + (r["rearmed_at_end"] and not r.get("rearmed_for_watchdog"))
                 + r.get("watchdog_resyncs", 0) for r in runs],
        skipped=[r["decoder"]["skipped"] for r in runs],
        realigned=[int(r.get("realigned", 0)) for r in runs],
        probes=[int(r.get("probes", 0)) for r in runs],
        left=[int(r.get("left", -1)) for r in runs], brake=[r.get("brake") for r in runs],
        watchdog=dict(wd_report, zeroed=[r.get("watchdog_zeroed", 0) for r in runs],
                      replies=[r.get("watchdog_replies", 0) for r in runs],
                      resyncs=[r.get("watchdog_resyncs", 0) for r in runs]))


def _lost_result(chk, runs: list, lost: Exception, wd_report: dict, probe) -> dict:
    """The result of a run whose board was lost after its first record: the records
    made by then counted (:func:`_record_counts`), nothing fitted (the felt matrices need
    all ``2n + 1 = 5``), "not measurable" with the loss as the reason, ``stop`` ("device
    lost: ...") and ``error`` (type and message), as the other runs' losses
    (:func:`hapsim.pipeline.felt_port.measure_felt_port`)."""
    why = f"device lost: {lost}"
    return {"predicted": chk, "measured": None, "deviation": None,
            "verdict": "not measurable", "within": None, "uncertainty": None,
            "statements": [], "not_stated": ["felt stiffness", "felt damping"],
            "reason": f"the board was lost after {len(runs)} of the 5 records (the felt "
                      "matrices need all 5): nothing was fitted",
            "records": len(runs) - 1,     # (free responses: the one from rest first)
            "direction_probe": None if probe is None else probe.to_dict(),
            "stop": why, "error": error_record(lost),
            **_record_counts(runs, wd_report)}


if __name__ == "__main__":
    # the emulated board's child, started so before the split: its entry is
    # hapsim.pipeline.haply2_embedded's
    from hapsim.pipeline.haply2_embedded import main
    sys.exit(main())
