"""The Haply 2DIY driven over its bytes in lockstep: the host loop
(:func:`drive_haply2`: arm, then one write per sample, each one period of the emulated
board's plant, :class:`hapsim.emulated.haply2_board.Haply2DIYBoard`) and the felt
matrices measured through it (:func:`measure_felt_haply2`, ``hapsim run --driver haply``
on a 2-D scene with ``--lockstep``; the records' verdict is
:func:`hapsim.emulated.haply2_verdict.felt_verdict_of_runs`).
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.drivers.haply import ResyncRule
from hapsim.drivers.haply2 import Haply2DIY
from hapsim.emulated.haply2_board import (PROBE_ENVELOPE, PROBE_TORQUE, BoardLink,
                                          Haply2DIYBoard, in_hand_order)
from hapsim.emulated.haply2_verdict import felt_verdict_of_runs
from hapsim.errors import ConfigError, DeviceError

__all__ = ["drive_haply2", "measure_felt_haply2", "MISSING_RESYNC"]


def drive_haply2(board_feed, driver: Haply2DIY, scene, samples: int, *, faults=None,
                 engine=None) -> dict:
    """Drive a 2DIY over its bytes in lockstep: arm, then one write per sample.

    Each sample: the reply's angles (whole counts) are the joints ``q`` [rad], the handle
    at ``f(q)`` (:class:`hapsim.kinematics.Pantograph`, exact), the n-D engine's force
    ``F`` on the port, the torques ``J(q)^T F`` written (clamped, binary32). A write whose
    reply does not come (lost, corrupted, misaligned) leaves that sample missing (the last
    position held for the engine; counted); a desync the decoder counts, or
    :data:`MISSING_RESYNC` missing replies in a row, re-arm the board (counted; the
    re-arming write is that sample's). The first reply after a set-up must read the
    offsets the set-up sent (within the decoder's step, 2 deg): otherwise the stream
    corrupted the set-up (a wrong offset would shift every later angle), which is counted
    in ``bad_setups`` and armed again.

    Parameters
    ----------
    board_feed : callable
        ``board_feed(bytes) -> bytes``: the device (an emulated board, through faults).
    driver : hapsim.drivers.haply2.Haply2DIY
    scene : hapsim.scene.SceneND
    samples : int
        Writes after arming.
    faults : object, optional
        ``rx(bytes)``, ``tx(bytes)`` (:class:`hapsim.emulated.driver_mock.ByteFaults`).
    engine : hapsim.engine.Engine, optional
        A fresh engine (default: one of ``scene``).

    Returns
    -------
    dict
        ``position`` (N, 2) [m] (NaN where missing), ``joints`` (N, 2) [rad], ``torque``
        (N, 2) [N m] written, ``missing`` (samples without a reply), ``resyncs``,
        ``bad_setups``, ``decoder`` (the reply decoder's counters), ``writes``.
    """
    from hapsim.engine import Engine
    from hapsim.kinematics import device
    dev = scene.device
    kin = device(dev.kind, dev.geometry)
    q0deg = [math.degrees(v) for v in dev.joints]
    eng = Engine(scene) if engine is None else engine
    port = eng.port
    dec = driver.decoder()
    rx = (lambda b: b) if faults is None else faults.rx
    tx = (lambda b: b) if faults is None else faults.tx
    N = int(samples)
    pos = np.full((N, 2), np.nan)
    joints = np.full((N, 2), np.nan)
    torque = np.zeros((N, 2))
    missing = 0
    in_row = 0
    zero = driver.write_bytes((0.0, 0.0))
    bad_setups = 0
    # The board is stepped one period per write: its time, not the wall clock's, is what a
    # reply's reach grows with (ReplyDecoder.reach_deg). Left to the decoder's default
    # (the wall time between two reads), a loaded host widened the reach of a lockstep
    # board's replies and took garbage 2.6 rad off (test_haply2's hostile streams, in a
    # full suite at load 12).
    T = 1.0 / float(scene.rate_hz)
    since = 0                                   # writes since the one last answered

    def send(data: bytes) -> list:
        """One write to the board, through the faults; the replies the decoder takes."""
        nonlocal since
        since += 1
        dec.elapsed(since * T)
        got = dec.feed(tx(board_feed(rx(data))))
        if got:
            since = 0
        return got

    def arm(at_deg):
        """Re-arm at the joints ``at_deg``; the first reply, or None when it is missing
        or does not read the offsets just sent (a set-up the stream corrupted)."""
        nonlocal bad_setups
        data = driver.arm_bytes(at_deg)
        send(data[:-len(zero)])                         # a reply before the set-up: dropped
        dec.reset_prediction()                           # the hand moved the handle
        got = send(zero)
        if not got:
            return None
        a = driver.joints_of(got[-1])
        if max(abs(math.degrees(a[j]) - at_deg[j]) for j in range(2)) > dec.max_step:
            bad_setups += 1
            dec.reset_prediction()
            return None
        return got[-1]
    last = arm(q0deg)
    if last is None:
        in_row = MISSING_RESYNC                          # arm again at once
    x = None
    rule = ResyncRule(dec.stats, MISSING_RESYNC - 1)
    for k in range(N):
        if last is None:
            missing += 1
            in_row += 1
        else:
            in_row = 0
            q = np.asarray(driver.joints_of(last))
            joints[k] = q
            try:
                x = kin.forward(q)
                J = kin.jacobian(q)
            except ConfigError:             # a reply the kinematics refuses: no sample
                missing += 1
                x = None
            if x is not None:
                pos[k] = x
        if x is not None:
            if k == 0:
                eng.x[:, port] = x
                eng.xp[:, port] = x
            eng.set_port_position(x)
        eng.step()
        F = eng.port_force
        tau = J.T @ F if x is not None else np.zeros(2)
        torque[k] = driver.clamp(tau)
        if rule.due(in_row):
            in_row = 0
            # zero torque, the set-up at the operating point's joints, a zero write (its
            # reply is the next sample): the emulated board's hand holds the handle
            # there at each set-up (as the real-time loop arms it, haply2_record). Armed
            # at the last joints read instead, each re-arming left the readings off the
            # joints by the motion since that reading: 28 re-armings of a hostile stream
            # walked them 0.66 deg off, and the loop pushed the handle 1.4 deg away
            last = arm(q0deg)
            if last is None:
                in_row = MISSING_RESYNC
            continue
        got = send(driver.write_bytes(tau))
        last = got[-1] if got else None
    return {"position": pos, "joints": joints, "torque": torque, "missing": missing,
            "resyncs": rule.count, "bad_setups": bad_setups, "decoder": dict(dec.stats),
            "writes": N}


#: Missing replies in a row after which the host re-arms the board (it may be inside a
#: garbage command, or have lost its set-up).
MISSING_RESYNC = 5


def measure_felt_haply2(scene, generation: str = "gen3", *, amplitude: float = 1e-5,
                        cpr: float | None = None, resolution: float | None = None,
                        samples: int | None = None, progress=None, plant=None,
                        plan=None, probe_wiring: bool = True, wiring=((1, 1), (1, 1)),
                        directions: dict | None = None) -> dict:
    """The felt matrices of a pantograph scene measured through the emulated 2DIY's bytes,
    and their verdict against the stated uncertainty.

    ``2n + 1`` records (each an arm: the set-up, whose hand starts the record; then
    ``samples`` writes) driven by :func:`drive_haply2` on a clean stream, the records
    minus the one from rest fitted as in lockstep
    (:func:`hapsim.analysis.pencil.fit_felt_nd`).

    The stated uncertainty (:func:`hapsim.analysis.felt_matrices.felt_verdict`) is the
    linearisation bound at ``a`` plus the wire's term
    (:func:`hapsim.emulated.haply2_verdict.felt_verdict_of_runs`): each reading is the
    joint angle rounded to a count of the set-up's resolution, then ``360 c / res`` in
    single precision, and each torque the host computed reaches the board rounded to
    binary32; that rounding is taken by draws of its phase through the predicted loop,
    each refitted by the run's fit (:mod:`hapsim.analysis.wire_rounding`: 1.5 times the
    largest change of 100 draws). Before, it was the first-order worst case over the
    errors' box (:func:`hapsim.analysis.wire_box.box_worst_case`), every sign of half a
    count plus a binary32 ulp per reading and ``2^-24 |tau|`` per torque, which the
    verdict still takes for the errors that are no rounding (estimated samples, the
    host's write timing).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    generation : {"gen2", "gen3"}
    amplitude : float
        The hand's ``a`` [m].
    cpr : float, optional
        The emulated encoders' counts per revolution (default the generation's).
    resolution : float, optional
        The set-up's counts per revolution (default ``cpr``).
    samples : int, optional
        Writes per record (default :func:`hapsim.lockstep.default_samples`).
    progress : callable, optional
    plant : hapsim.scene.SceneND, optional
        The scene whose device the emulated board carries (default ``scene``): a device
        that is not the one the scene states (a test of the verdict).
    plan : tuple, optional
        :func:`hapsim.lockstep.identification_plan` of ``scene`` and ``samples``,
        already computed (several measurements of one scene).
    probe_wiring : bool, optional
        Check each joint's wiring first (:func:`hapsim.drivers.haply2_probe.
        find_directions`, within :data:`hapsim.emulated.haply2_board.PROBE_TORQUE`): a
        joint turned backwards by its direction bytes is refused before any torque loop
        runs.
    wiring : ((int, int), (int, int)), optional
        The emulated board's wiring
        (:class:`hapsim.emulated.haply2_board.Haply2DIYBoard`).
    directions : dict, optional
        ``motor_direction`` / ``encoder_direction`` bytes the host sets up instead of the
        generation's (:class:`hapsim.drivers.haply2.Haply2DIY`).

    Returns
    -------
    dict
        ``measured``, ``predicted``, ``deviation`` (as
        :func:`hapsim.lockstep.measure_felt_lockstep`); ``bound`` (the linearisation
        bound at ``a``); ``wire`` (``felt_stiffness``, ``felt_damping``: the wire's
        relative terms, inf when the records give no sensitivity; ``reading_bound_rad``
        per joint; ``torque_rel``); ``verdict``, ``within``, ``uncertainty``, ``reason``
        (:func:`hapsim.analysis.felt_matrices.felt_verdict`; "not measurable" also when the board's
        torque clamp engaged, ``clamped`` samples); ``quantum`` (one step of a reading
        at the handle over ``a`` [-]: one count or one binary32 ulp, the larger, times
        ``|J|``), ``quantum_encoders`` (one count of each generation's encoders at the
        handle over ``a``), ``records``, ``samples``, ``direction_probe`` (what the
        wiring probe found: :meth:`hapsim.drivers.haply2_probe.WiringProbe.to_dict`, or
        None).

    Raises
    ------
    DeviceError
        A record with a missing reply (the clean stream lost one).
    IdentificationError
        A joint wired backwards against its direction bytes (the probe's refusal).
    """
    from hapsim.lockstep import identification_plan
    chk, order, N = identification_plan(scene, samples) if plan is None else plan
    n = 2
    board = Haply2DIYBoard(plant if plant is not None else scene, generation, cpr=cpr,
                           amplitude=amplitude, wiring=wiring, clock="lockstep")
    drv = Haply2DIY(generation, resolution=resolution or board.cpr, **(directions or {}))
    probe = None
    if probe_wiring:
        from hapsim.drivers.haply2_probe import find_directions
        probe = find_directions(drv, BoardLink(board.feed),
                                [math.degrees(v) for v in scene.device.joints],
                                force_limit=PROBE_TORQUE, envelope=PROBE_ENVELOPE,
                                rate_hz=scene.rate_hz, pace=False, timeout=0.0)
    runs = []
    for j in range(2 * n + 1):
        r = drive_haply2(board.feed, drv, scene, N)
        if r["missing"]:
            raise DeviceError(f"record {j}: {r['missing']} replies missing on a clean stream")
        runs.append(r)
        if progress is not None:
            progress(j + 1, 2 * n + 1)
    runs = in_hand_order(runs, 0 if probe is None else probe.setups)
    out = felt_verdict_of_runs(scene, runs, (chk, order, N), drv.resolution, amplitude)
    out["direction_probe"] = None if probe is None else probe.to_dict()
    return out
