"""The Haply 2DIY's real-time record loop: the host loop on its own clock against a board
behind a port (the emulated board in a child process on a pseudo-terminal,
:class:`hapsim.pipeline.haply2_embedded.Embedded2DIY`, as the 1-DoF Haply mock runs; or a
real board), one record per :func:`record_realtime`. The records are measured by
:mod:`hapsim.pipeline.haply2_host` (the estimates' bounds, the cuts, the verdict).

The board answers each write with the angles read when its pass took the write, whose
torques it then holds until the next (firmware V1.5 on its own time, no watchdog:
:class:`hapsim.emulated.haply2_board.Haply2DIYBoard`'s default; named, in lockstep, each
write is one period of its plant). The host ticks every ``T``: at tick
``k`` the sample is the reply to write ``k`` (write 0 is the arming's zero write; replies
come in order, one per write, and none is lost on a clean stream, so the ``i``-th reply
answers write ``i``). A reply not read by tick ``k`` is a *missing reply*: the tick is an
*estimated sample* (counted, as the 1-DoF driver loop counts its ``FLAG_ESTIMATED``
rows), its position extrapolated from the last two readings,
``x_e = x[i] + r (x[i] - x[i-1])`` with ``r = k - i``
(:func:`hapsim.pipeline.haply2_host.estimate_bounds` bounds its error), the engine's
force computed from it and its torques written; the reply counts when it comes, but
never replaces the estimate the engine used (the record holds what the loop saw). The
records' verdict is :func:`hapsim.emulated.haply2_verdict.felt_verdict_of_runs`: the
estimated rows' bounds enter the wire's term through the loop as reading errors do.

Before any record, each joint's wiring is checked (:mod:`hapsim.drivers.haply2_probe`,
run by :func:`hapsim.pipeline.haply2_host.measure_felt_haply2_port` over a
:class:`PortLink`): a joint its direction bytes turn backwards is refused.

The board has no framing (:mod:`hapsim.drivers.haply`): a host byte lost or corrupted
shifts its parser, and it then answers garbage, one byte per write, or nothing. The loop
re-synchronises it as the 1-DoF driver does (:class:`hapsim.drivers.haply.ResyncRule`:
the decoder counted a desync, or writes went unanswered for :data:`SILENT_S`): the
re-arming bytes (:func:`hapsim.drivers.haply.resync_bytes`: zero torque first, then the
set-up), the link drained, and the set-up's zero write, whose reply is that tick's
sample. The set-up's offsets are the operating point's joints, as at arming: the
emulated board's hand holds the handle there at each set-up
(:mod:`hapsim.emulated.haply2_board`), and on a board whose handle goes on moving they
are wrong by the record's motion since the arming (its amplitude, 1e-4 m: about 1e-3
rad) where the joints last read, extrapolated, would be wrong by the estimate's error.
The clock starts again from the re-arming's reply (the time it took is counted,
``resync_s``); a re-armed record is cut there (the hand restarts it: the stretch after is
another free response, :func:`hapsim.pipeline.haply2_host.usable_rows`). A reply damaged
on the way back (bytes lost or corrupted, fewer than a desync) was still its write's
answer: the replies after it answer the writes after (the decoder's ``damaged``; when
one read holds several replies and a damaged one, all of them are taken as after it).
A host byte lost in a write makes the board skip one write without losing its place
(the address 3): the loop, behind though replies come, sends a marker as a tick's command
and sets its count where the board's answer to it stands
(:mod:`hapsim.pipeline.haply2_realign`), never waiting for it.
A host stall (a tick begun more than a period late: a descheduled process) is a stall,
never a burst of catch-up writes: the clock goes on from where the host woke, the stall
is counted (``stalled``), and the board, which held the last torque meanwhile on its own
clock, is not re-synchronised for it: a late reply is a late sample (the decoder's step
check widens with the ticks since the last reply read, by the motion the board's torque
clamp and the joint inertia allow), and only writes unanswered for :data:`SILENT_S` and more than :data:`SILENT_COUNT` are
taken for a board out of step. An estimated tick whose newest reading is older than
:data:`HOLD_BOUND_S` writes zero torque (no watchdog on the board holds it otherwise);
a host that does not run at all cannot, and the host's watchdog beside it does
(``watchdog``, :mod:`hapsim.drivers.host_watchdog`: its zero write after
:data:`HOLD_BOUND_S` of the host's silence is a write of its own, its reply dropped; while
bytes read made no reply yet, or in a long silence of a link that has lost bytes, its
write is the robust one, :func:`watchdog_robust`, the loop's re-arming, which a board
whose parser lost its place takes where it takes no zero command: the host, awake, reads
no reply after it and re-arms the board itself, the record cut there).
The loop is linear and time-invariant between disturbances, so a record is cut at each
(a stall, a run of missing replies, a zeroed tick, a re-synchronisation, a torque at the
clamp: :func:`hapsim.pipeline.haply2_host.usable_rows`) and its undisturbed stretches
are fitted jointly, each a free response of the same loop (before, one stall or
re-synchronisation made the whole run "not measurable": 5 of 10 no-fault runs beside two
CPU-bound processes, 0 of 10 with 1 byte in 200 lost).
A record ends with a zero write; when its reply does not come in step the board is
re-armed (zero torque whatever its parser is inside: no watchdog); on a board on its own
clock that reply is awaited only while replies keep coming (:data:`SILENT_S` of the host's
awake time, :data:`AWAKE_GAP_S`), not :data:`END_WAIT_S` with whatever the board holds. A
re-synchronisation of a board on its own clock waits for physical evidence that the board
took it (a reply reading the set-up's offsets) at most :data:`REARM_REPLY_S` of the host's
awake time, then sends it again, zero torque first (:data:`REARM_SENDS` at most): before,
a re-arming the stream corrupted waited 0.25 s with the clamp's torque held (16.8 rad of
true excursion, 1 byte in 200 lost). A reading farther than :data:`ENVELOPE_RAD` from the
operating point ends the record's torque loop (not measured): a stop on the motion, after
which the joints are braked to rest (:mod:`hapsim.braking`, ``tau = -B q'`` from the
readings, at most :data:`hapsim.braking.BRAKE_MAX_S`, on past the record's last tick if
need be) and then held at zero torque (the scene's ``safety: {brake: false}``: zero torque
at once). A corrupted byte in a write the board takes cannot be seen (no checksum: a
wrong torque for one period).
"""

from __future__ import annotations

import math
import time
from collections import deque

import numpy as np

from hapsim.braking import BRAKE_MAX_S, Brake, brake_damping, brake_rest
from hapsim.drivers.decoders import MARK
from hapsim.drivers.haply import MAX_TORQUE, ResyncRule
from hapsim.drivers.haply2 import Haply2DIY
from hapsim.errors import DeviceError
# the loop's limits (re-exported: hapsim.pipeline.haply2_limits)
from hapsim.pipeline.haply2_limits import (  # noqa: F401
    ARM_TIMEOUT, AWAKE_GAP_S, END_WAIT_S, ENVELOPE_RAD, HOLD_BOUND_S, QUIET_S,
    REARM_QUIET_S, REARM_REPLY_S, REARM_SENDS, REARM_WAIT_S, REPLY_WAIT_S, SILENT_S,
    SILENT_WRITES, SPIN_S, ARM_TRIES, WORKSPACE_RAD, watchdog_robust)
from hapsim.pipeline.haply2_port import PortLink, read_waiting as _read, write_all as _write
from hapsim.pipeline.haply2_realign import SILENT_COUNT, Realigner

__all__ = ["record_realtime", "watchdog_robust", "PortLink", "ENVELOPE_RAD",
           "WORKSPACE_RAD"]


def record_realtime(ser, driver: Haply2DIY, scene, samples: int, *, engine=None,
                    lockstep_board: bool = False, running: bool = False,
                    brake: bool | None = None, watchdog=None) -> dict:
    """One record in real time: arm (the set-up, whose hand starts the record), then one
    write per tick of the host's clock (module notes).

    Parameters
    ----------
    ser : serial.Serial
        The board's port (non-blocking reads).
    driver : hapsim.drivers.haply2.Haply2DIY
    scene : hapsim.scene.SceneND
        A 2-D pantograph scene (its rate is the clock's).
    samples : int
        Ticks ``N``.
    engine : hapsim.engine.Engine, optional
        A fresh engine (default: one of ``scene``).
    lockstep_board : bool, optional
        The board advances one period per write (named lockstep): a sample's age and a
        silence are then counted in the board's periods, not on the wall clock
        (:data:`HOLD_BOUND_S`, :data:`SILENT_S`).
    running : bool, optional
        The board already runs (a record after the first, or after the wiring probe):
        the arming's answers are then awaited :data:`REPLY_WAIT_S`, not the
        :data:`ARM_TIMEOUT` a board process that loads its plant is given (its torque is
        the power-up's zero). A re-synchronisation on a board on its own clock waits for
        the evidence that the board took it, at most :data:`REARM_REPLY_S` of the host's
        awake time a sending (:data:`REARM_SENDS` sendings).
    brake : bool, optional
        Default: the scene's ``safety.brake`` (:class:`hapsim.scene.SafetyND`, true
        unless the scene says otherwise). After the joints left :data:`ENVELOPE_RAD` (a
        stop on the motion), brake them to
        rest (:mod:`hapsim.braking`: ``tau = -B q'``, ``B = g M_q / T`` from the scene's
        joint inertia, clamped to the board's torque, at most
        :data:`hapsim.braking.BRAKE_MAX_S`, on past the record's last tick if it needs
        to) before the zero torque; False (the scene's ``safety: {brake: false}``): zero
        torque at once.
    watchdog : hapsim.drivers.torque_watchdog.TorqueWatchdog, optional
        The host's watchdog on this port (a board on its own clock: no watchdog of its
        own): armed from the arming's reply to the record's closing zero write; each of
        its zero writes is a write of its own, whose reply is dropped (counted
        ``watchdog_zeroed``, ``watchdog_replies``; :mod:`hapsim.drivers.host_watchdog`).
        With a robust write (:func:`watchdog_robust`) the loop tells it when bytes read
        made no reply yet (``suspect``: its write in a silence is then the robust one)
        and, once the link has shown it loses bytes (a damaged reply, a desync, a
        re-synchronisation since the first arming), that a long silence's write must be
        the robust one too (``lossy``); a robust write taken is the board set up again
        by the watchdog: no reply is taken after it, the host re-arms the board itself at
        that tick (``resynced``, the record cut there, counted ``watchdog_resyncs``), or at
        the record's end (``rearmed_at_end``).

    Returns
    -------
    dict
        ``position`` (N, 2) [m] (the readings, or the estimates the engine used),
        ``joints`` (N, 2) [rad] read (NaN where estimated), ``torque`` (N, 2) [N m]
        written, ``estimated`` (N,) bool, ``lag`` (N,) int (ticks since the last reading
        where estimated), ``late_ticks`` (ticks the host itself began more than a period
        late), ``replies`` (replies to the record's writes, read by its end: all of them
        on a clean stream; a re-arming's closing replies, counted too, answer writes
        of its own), ``writes`` (the record's: the arming's zero write, the ticks', the
        closing zero write, the watchdog's), ``rearm_writes`` (the re-armings' own
        writes a board answers: each one's zero writes; ``replies`` is at most
        ``writes + rearm_writes``), ``readings`` (N, 2) [m] (reply ``k``'s reading,
        read in time or late; NaN where it never came), ``resyncs`` (re-synchronisations
        of a board that lost its place), ``resynced`` (N,) bool (the ticks they were
        made at), ``resync_s`` (the time they took [s], out of the clock),
        ``stalled`` (N,) bool (ticks the host began more than a period late: the
        clock went on from there, no catch-up writes), ``stall_s`` (their lateness [s]),
        ``held_zero`` (estimated ticks written at zero torque: no fresh sample for
        :data:`HOLD_BOUND_S`), ``bad_setups`` (armings whose first reply did not come or did not read the
        offsets sent, armed again), ``rearmed_at_end`` (the closing zero write's reply
        did not come, or the watchdog's robust write came before it: the board was
        re-armed to leave it at zero torque), ``watchdog_zeroed``,
        ``watchdog_replies``, ``watchdog_resyncs`` (the watchdog's writes, their replies
        dropped, its robust writes, each followed by a re-arming of the host's),
        ``decoder``
        (the reply decoder's counters: ``frames``, ``skipped``, ``desync``,
        ``damaged``), ``write_s`` (N, 2) [s]: when the host's write whose reply is row
        ``k``'s sample began and ended (``perf_counter``, from the first one's start;
        the board took it in between, or a latency after: the holds' lengths,
        :func:`hapsim.pipeline.haply2_host.hold_bounds`), ``write_t0`` (that first
        start, ``perf_counter`` [s]), ``probed`` (N,) bool (ticks whose command was a
        marker, :mod:`hapsim.pipeline.haply2_realign`), ``probes`` (markers sent),
        ``realigned`` (their answers that moved the count of replies: writes the board
        swallowed), ``probes_late`` (those that left it: a late board), ``left`` (the tick a reading
        left :data:`ENVELOPE_RAD`, -1 if none), ``brake`` (None, or after ``left`` with
        ``brake``: :meth:`hapsim.braking.Brake.report`'s dict: ``damping`` [N m s/rad],
        ``periods`` (ticks braked), ``seconds``, ``v_start``/``v_end`` (the joints'
        velocities [rad/s]), ``ended`` (``"rest"`` or ``"time"``), ``late`` (its ticks
        the host began a period or more late)). The
        row arrays have the record's ``N`` rows; the braking's ticks after them are not
        rows.

    Raises
    ------
    DeviceError
        No first reply after the first set-up within :data:`ARM_TIMEOUT`;
        :data:`ARM_TRIES` armings in a row whose first reply did not come or did not
        read the offsets sent; the port failing.
    """
    from hapsim.drivers.device_port import DevicePort
    ser = DevicePort.of(ser, "the 2DIY")     # its failures: DeviceError (haply2_port)
    from hapsim.engine import Engine
    from hapsim.kinematics import device
    dev = scene.device
    kin = device(dev.kind, dev.geometry)
    q0deg = [math.degrees(v) for v in dev.joints]
    N = int(samples)
    T = scene.period
    dec = driver.decoder()
    rule = ResyncRule(dec.stats, SILENT_WRITES)
    # the decoder's step check (an angle no motion could reach from the linear prediction
    # of the last two replies, one tick ahead) a time tau after the last reading's write
    # (a host stall is time, not ticks: the clock went on from it): the joint may
    # accelerate at most alpha = 0.123 N m over the smallest joint inertia (the board's
    # clamp; a hand on the handle only adds inertia), the reach of
    # ReplyDecoder.reach_deg, the same rule as the 1-DoF driver's: a late reply, or the
    # first after a host stall, is a late sample, not bytes of a board out of step
    ji = getattr(dev, "joint_inertia", None)
    alpha = (MAX_TORQUE / float(np.min(np.linalg.eigvalsh(np.atleast_2d(ji))))
             if ji is not None and np.all(np.isfinite(ji)) else 0.0)
    dec.set_accel(alpha if alpha > 0 else None)
    dec.period_s = T                                # the last two replies: a tick apart
    eng = Engine(scene) if engine is None else engine
    # the braking's damping from the joint-space inertia (hapsim.braking.brake_damping
    # says why not the Cartesian mass) and its rest speed; no inertia stated: no braking
    Bq = brake_damping(ji, 1.0 / T) if ji is not None else None
    if brake is None:
        brake = getattr(getattr(scene, "safety", None), "brake", True)
    brake = bool(brake) and Bq is not None and bool(np.any(Bq))
    if brake:
        Bfq = getattr(dev, "joint_friction", None)
        rest = brake_rest(WORKSPACE_RAD, ji, 0.0 if Bfq is None else Bfq)
    port = eng.port
    # the ticks the loop may run: the record's, and after a stop on the motion the
    # braking's, at most BRAKE_MAX_S more (its rows are not the record's: cut at N)
    C = N + (int(math.ceil(BRAKE_MAX_S / T)) + 3 if brake else 0)
    xr = np.full((C + 2, 2), np.nan)                # reading of tick i's reply
    qr = np.full((C + 2, 2), np.nan)
    # got: the tick whose write the next reply answers (replies come in order, one per
    # write; a re-arming re-anchors it); replies: replies taken in all
    got = 0
    replies = 0
    seen = 0                                        # the last tick whose reply was read
    bad_setups = 0
    resync_s = 0.0

    # the per-sample work below makes no array (the real-time rule): kinematics on
    # floats (forward_at, jacobian_at), rows written element by element, the write
    # packed into a reused buffer
    fwd = kin.forward_at
    jac = kin.jacobian_at
    feed_into = dec.feed_into
    joints_of = driver.joints_of
    frames = [None] * 8                             # the decoder's frames, reused
    nr = xr.shape[0]

    def take(data):
        nonlocal got, replies, seen
        if not data:
            return
        st = dec.stats
        d0 = st["damaged"]
        m = feed_into(data, frames)
        # a damaged reply (bytes lost or corrupted on the way back) was a write's
        # answer: the replies after it answer the writes after that one
        got += st["damaged"] - d0
        j = 0
        while j < m:                                # (no iterator: no allocation)
            rep = frames[j]
            if rep is MARK:
                # a marker's answer (hapsim.pipeline.haply2_realign): the count set at
                # its place, the readings in doubt dropped
                got = realign.marked(got)
                replies += 1
                seen = min(seen, got - 1)
                while seen > 0 and xr[seen, 0] != xr[seen, 0]:
                    seen -= 1
                j += 1
                continue
            if wd_before and wd_before[0] <= got:
                # the host watchdog's zero write went out before write `got`, after the
                # one before: this reply is its answer (dropped, counted)
                wd_before.popleft()
                wd_count[1] += 1
                replies += 1
                j += 1
                continue
            if got < nr:
                q1, q2 = joints_of(rep)
                qr[got, 0] = q1
                qr[got, 1] = q2
                xr[got, 0], xr[got, 1] = fwd(q1, q2)
                seen = got
            got += 1
            replies += 1
            j += 1
        if wd_rob:
            # bytes read since the last reply that made none (the board may have lost
            # its place: the watchdog's write in a silence is then its robust one),
            # told on a change only
            on = dec.unframed()
            if on != wd_susp[0]:
                wd_susp[0] = on
                watchdog.suspect(on)

    zero = driver.write_bytes((0.0, 0.0))
    # the host watchdog's zero writes not answered yet: the host write each went out
    # before (its reply comes after that write's predecessor's); zero writes, replies
    wd_before: deque = deque()
    # zero writes, their replies, robust writes taken (each followed by a re-arming)
    wd_count = [0, 0, 0]
    # the watchdog has a robust write (watchdog_robust: the re-arming at the arming's
    # offsets); the board suspect as told it; a robust write taken, the re-arming due;
    # the link shown lossy (told once), and the evidence's count at the first arming
    wd_rob = watchdog is not None and bool(getattr(watchdog, "robust", False))
    wd_susp = [False]
    wd_due = [False]
    wd_lossy = [False, -1]

    def wd_note(before: int, times) -> None:
        """The watchdog's writes ``times``, made before host write ``before``; a robust
        one among them (the board set up again at the arming's offsets: its answers
        unknown in number, one of them reading the set-up's offsets) makes a re-arming
        due, before any more replies are taken (module notes)."""
        if times:
            wd_before.extend([before] * len(times))
            wd_count[0] += len(times)
            if wd_rob:
                n = watchdog.take_robust()[0]
                if n:
                    wd_count[2] += n
                    wd_due[0] = True

    link = PortLink(ser)                    # (its write: the port's DeviceError)

    def send(data, before: int, holding: bool, swap: bool = True) -> bool:
        """Write ``data``, host write ``before`` (``holding``: it leaves a torque), the
        watchdog's writes since taken first (:meth:`TorqueWatchdog.write`'s halves). A
        robust write of the watchdog's among them (made in the tick's work, after its
        take: the board set up again at the arming's offsets, in step) gets the zero
        write instead of a torque computed in the old frame (the re-arming follows at the
        next tick; ``swap`` False: a marker, whose answer the count awaits, goes as it
        is, the board zeroed by the robust write holding zero through it); True then."""
        if watchdog is None:
            _write(ser, data)
            return False
        wd_note(before, watchdog.beat())
        swap = swap and holding and wd_due[0]
        if swap:
            data, holding = zero, False
        watchdog.write(link, data, holding, beaten=True)
        return swap
    # the count of replies checked by a marker write when the loop ends ticks behind
    # though replies come (a write swallowed, or a late board: never a wait)
    realign = Realigner(dec, xr, qr)
    # perf_counter() of the write whose reply is each tick's sample (the arming's zero
    # write for tick 0)
    t_wrote = np.full(C + 2, np.nan)
    t_began = np.full(C + 2, np.nan)                # perf_counter() as that write began

    def arm(at_deg, k):
        """Arm (or re-arm) the board at the joints ``at_deg`` [deg]: zero torque and the
        re-synchronising bytes, whose answers (the zero write's, from before the set-up,
        and whatever an earlier record or a desynchronised stream left) are drained and
        dropped; then the set-up's zero write, whose reply is tick ``k``'s sample. A
        first reply that does not read the offsets sent is a set-up the stream corrupted
        (counted in ``bad_setups``): armed again, at most :data:`ARM_TRIES` times."""
        nonlocal got, seen, bad_setups, rearm_sends, rearm_writes
        if watchdog is not None:
            watchdog.arm(False)                 # (its waits are on purpose)
            wd_note(k, watchdog.take())         # (drained below with the rest)
            wd_before.clear()
            wd_due[0] = False                   # (a robust write: this re-arming follows)
            # (told whatever this record last told: the page keeps an earlier record's
            # flag, and a stale one makes every silence's write the robust one)
            wd_susp[0] = False
            watchdog.suspect(False)
        data = driver.arm_bytes(at_deg)
        # the first set-up waits for a board process that loads its plant first; the
        # others for a board already running
        wait = ARM_TIMEOUT if k == 0 and not replies and not running else REPLY_WAIT_S
        tries = 0
        while tries < ARM_TRIES:
            # a re-synchronisation (k > 0): the whole bytes, the closing zero write too:
            # the board (no watchdog) takes zero torque right after its set-up, not after
            # the drain below (a torque a garbage command left was held through it); a
            # record's first arming leaves it for the sample's write (a lockstep board
            # would advance a period on it before the record)
            bounded = k > 0 and not lockstep_board
            _write(ser, data if k > 0 else data[:-len(zero)])
            rearm_writes += k > 0               # (its closing zero write)
            if bounded:
                # a board on its own clock holds what its parser last took: until its
                # answer to the closing zero write reads the offsets sent (the board in
                # step, zero torque set after the set-up), the re-arming may have been
                # corrupted and a garbage torque held. Awaited at most REARM_REPLY_S of
                # the host's awake time, then sent again, zero torque first (bounded)
                if not _await_setup(at_deg):
                    rearm_sends += 1
                    if rearm_sends >= REARM_SENDS:
                        raise DeviceError(f"the 2DIY did not answer {REARM_SENDS} "
                                          "re-armings in a row with the offsets sent")
                    continue
            else:
                end = time.monotonic() + wait
                # the board answers the zero write when it is in step: wait for it (a
                # board process just started loads its plant first); one out of step
                # may not
                quiet = math.inf if wait == ARM_TIMEOUT else time.monotonic() + REARM_WAIT_S
                while time.monotonic() < min(end, quiet):
                    if _read(ser):
                        quiet = time.monotonic() + QUIET_S
                    time.sleep(1e-3)
            dec.clear()                         # a reply's part left: dropped too
            dec.reset_prediction()              # the set-up's offsets start afresh
            got = k
            t_began[k] = time.perf_counter()
            _write(ser, zero)
            rearm_writes += k > 0 or tries > 0  # (a record's first: its write 0)
            t_wrote[k] = time.perf_counter()
            if bounded:
                _awake_wait(lambda: got != k, REARM_REPLY_S, take)
            else:
                end = time.monotonic() + wait
                while got == k and time.monotonic() < end:
                    take(_read(ser))
                    if got == k:
                        time.sleep(2e-4)
            if (bounded and got == k + 2 and k + 1 < nr
                    and np.max(np.abs(np.degrees(qr[k]) - at_deg)) <= dec.max_step):
                # the re-arming's closing reply came after the quiet (a board process
                # the host's machine held): the sample is the reply after it
                qr[k] = qr[k + 1]
                xr[k] = xr[k + 1]
                qr[k + 1] = xr[k + 1] = np.nan
                got, seen = k + 1, k
            if got == k + 1 and np.max(np.abs(np.degrees(qr[k]) - at_deg)) <= dec.max_step:
                rearm_sends = 0
                if watchdog is not None:
                    if wd_lossy[1] < 0:         # (the evidence counted from here)
                        wd_lossy[1] = _evidence()
                    watchdog.arm()
                return
            if bounded and got == k:
                # no answer within the bound (not a set-up the stream corrupted): sent
                # again, zero torque first; bounded by REARM_SENDS
                rearm_sends += 1
                if rearm_sends >= REARM_SENDS:
                    raise DeviceError(f"the 2DIY did not answer {REARM_SENDS} "
                                      "re-armings in a row")
                continue
            bad_setups += 1
            tries += 1
            wait = REPLY_WAIT_S
        if not replies:
            raise DeviceError(f"no reply from the 2DIY after {ARM_TRIES} set-ups")
        raise DeviceError(f"the 2DIY's first reply after {ARM_TRIES} set-ups did not read "
                          "the offsets sent: the stream corrupts its set-ups")

    def _evidence() -> int:
        """The link's evidence that it loses bytes so far: damaged replies, desyncs and
        writes the board swallowed (a marker's answer: haply2_realign). Not the
        re-synchronisations of a board that stopped answering (a board late on a loaded
        machine) nor the watchdog's robust writes (a reply split across two reads makes
        the board suspect): neither is a byte lost."""
        st = dec.stats
        return st["damaged"] + st["desync"] + realign.realigned

    def _await_setup(at_deg) -> bool:
        """A re-arming's evidence: a reply, among what the board sent after the bytes,
        that reads the offsets ``at_deg`` [deg] (the closing zero write's, the board in
        step after its set-up). Polled for :data:`REARM_REPLY_S` of awake time; the bytes
        read are dropped (a decoder of their own: the loop's counters unchanged)."""
        probe = driver.decoder()
        ok = [False]

        def look(data):
            for rep in probe.feed(data):
                q = driver.joints_of(rep)
                if max(abs(math.degrees(q[j]) - at_deg[j]) for j in range(2)) \
                        <= probe.max_step:
                    ok[0] = True
            probe.reset_prediction()            # each reply on its own (no prediction)
        _awake_wait(lambda: ok[0], REARM_REPLY_S, look)
        if ok[0]:
            # what else the re-arming's bytes made (a reply after the one that read the
            # offsets: that was the first zero write's, a joint at rest): dropped once
            # the board has been quiet for a set-up's time of the host's awake time
            came = [True]

            def drop(data):
                came[0] = bool(data)
            while came[0]:
                came[0] = False
                _awake_wait(lambda: came[0], REARM_QUIET_S, drop)
        return ok[0]

    def _awake_wait(done, limit, sink):
        """Poll the port into ``sink`` until ``done()`` or ``limit`` [s] of the host's
        awake time (:data:`AWAKE_GAP_S`: a host stall is not the board's silence)."""
        awake = 0.0
        last = time.perf_counter()
        while True:
            sink(_read(ser))
            if done():
                return
            now = time.perf_counter()
            awake += min(now - last, AWAKE_GAP_S)
            last = now
            if awake >= limit:
                return
            time.sleep(2e-4)

    rearm_sends = 0
    rearm_writes = 0
    arm(q0deg, 0)
    pos = np.zeros((C, 2))
    joints = np.full((C, 2), np.nan)
    torque = np.zeros((C, 2))
    est = np.zeros(C, bool)
    lag = np.zeros(C, np.int64)
    resynced = np.zeros(C, bool)
    stalled = np.zeros(C, bool)
    # ticks whose command was a marker (hapsim.pipeline.haply2_realign: the torques of
    # the write before held over it)
    probed = np.zeros(C, bool)
    # the braking after the joints left the envelope (hapsim.braking, the joints'
    # velocities from the readings, the joint-space inertia's B): None until then, and
    # its end ("rest", "time") once done
    law = None
    braked = None
    brake_at = brake_k = 0
    obs = -1                                        # the last tick the law read
    late = 0
    stall_s = 0.0
    held_zero = 0
    left = -1                                       # the tick the joints left ENVELOPE_RAD
    q0r0, q0r1 = float(dev.joints[0]), float(dev.joints[1])
    x = np.zeros(2)                                 # the sample the engine is given
    F = eng.port_f[:2]                              # the engine's port force (a view)
    wbuf = bytearray(zero)
    write_into = driver.write_into
    clamp1 = driver.clamp1
    t0 = time.perf_counter()
    if not lockstep_board:
        # the first hold a period too: the board holds the arming's zero write from when
        # it took it, so tick 0's write goes out a period after that write began, not
        # when its reply came (before: 0.4-0.6 ms after, every record's first hold short
        # by ~0.6 ms, the velocity records' second sample off by ~6 % of the amplitude).
        # A reply later than that: from now, as before
        t0 = max(t0, t_began[0] + T)
    K = N                                           # ticks run (more while braking)
    for k in range(C):
        if k >= N and (law is None or braked is not None):
            break                                   # the record's end (the braking's)
        K = max(K, k + 1)
        deadline = t0 + k * T
        now = time.perf_counter()
        if now > deadline + 0.5 * T:
            # the host is behind (a descheduled process): no catch-up burst of writes,
            # each a period's torque sent 0.1 ms apart; the clock goes on from now (any
            # three writes span at least half a period). A whole period or more behind is
            # a stall, counted: the board held the last torque over it, on its own clock,
            # and the record is no uniform loop of the THS then (not measured)
            if now > deadline + T:
                late += 1
                stalled[k] = True
                stall_s += now - deadline
            t0 += now - deadline
            deadline = now
        elif deadline - now > SPIN_S:
            time.sleep(deadline - now - SPIN_S)
        while time.perf_counter() < deadline:
            pass
        dec.elapsed(time.perf_counter() - t_wrote[seen])   # since the last reading's write
        g0 = got
        # read, then the watchdog's writes taken: it counts a write before making it, so
        # every answer in the bytes read belongs to a write taken here (taken first, a
        # robust write made between the take and the read had its answers read as motion)
        data = _read(ser)
        if watchdog is not None:
            wd_note(k + 1, watchdog.take())     # (its writes since write k)
            if wd_rob and not wd_lossy[0] and 0 <= wd_lossy[1] != _evidence():
                # the link has shown it loses bytes since the first arming: a long
                # silence's robust write goes too (torque_watchdog.ROBUST_AFTER)
                wd_lossy[0] = True
                watchdog.lossy()
        if not wd_due[0]:
            # (after a robust write of the watchdog's the bytes waiting may be its
            # answers, one reading the set-up's offsets: no motion; the re-arming below
            # drains them)
            take(data)
        # behind for SILENT_COUNT ticks, though replies come: a board late (it catches up
        # within a few: the backlog comes in one read), or a write it swallowed (a host
        # byte lost: firmware V1.5 completes the write with the next one's first byte and
        # parses the rest of that one as no command, so one write is never answered and
        # every reply after it answers a write one newer than the count says). Told apart
        # by the board's answer to a marker, this tick's command (haply2_realign)
        mark = realign.due(k, got, g0)
        unanswered = k + 1 - got                    # (damaged: answered)
        if unanswered > SILENT_COUNT:
            # writes unanswered for SILENT_S are a board that stopped answering (a board
            # in step answers within its pass and a USB frame, ~1 ms); fewer, or younger,
            # are late replies (a count alone is no evidence); a lockstep board's time is
            # its periods (one per write), not the wall clock's
            age = ((k - got) * T if lockstep_board
                   else time.perf_counter() - t_wrote[got])
            unanswered = SILENT_WRITES + 1 if age >= SILENT_S else 0
        else:
            unanswered = 0
        if realign.lost:
            unanswered = SILENT_WRITES + 1          # (markers unanswered, or answers too many)
            mark = False
        if wd_due[0] or rule.due(unanswered):
            # the board lost its place (module notes), or the watchdog set it up again
            # (its robust write: the host follows it with its own, so that the count of
            # replies and the record start again from a set-up of its own; the record is
            # cut here, usable_rows): zero torque first, the set-up; its reply is this
            # tick's sample, and the clock starts again from it (the time it took is
            # counted)
            if wd_due[0]:
                rule.answered()
            t_r = time.perf_counter()
            arm(q0deg, k)
            resynced[k] = True
            t0 += time.perf_counter() - t_r
            resync_s += time.perf_counter() - t_r
            mark = False
        # ticks in a row ended behind (the re-arming re-anchors the count)
        realign.tick_end(k, got, resynced[k])
        if got > k and xr[k, 0] == xr[k, 0]:        # reply k read: a fresh sample
            i = k
            x[0] = xr[k, 0]
            x[1] = xr[k, 1]
            joints[k, 0] = qr[k, 0]
            joints[k, 1] = qr[k, 1]
            if left < 0 and (abs(qr[k, 0] - q0r0) > ENVELOPE_RAD
                             or abs(qr[k, 1] - q0r1) > ENVELOPE_RAD):
                left = k                            # braked, then zero torque (below)
                if brake:
                    law = Brake(Bq, MAX_TORQUE, rest)
                    brake_at, brake_k = time.perf_counter(), k
                    if k >= 1 and qr[k - 1, 0] == qr[k - 1, 0] and not resynced[k]:
                        obs = k - 1
                        law.observe(qr[k - 1], None)
            if law is not None and braked is None:
                # the joints' velocity from this reading and the last the law read (the
                # times of the writes they answer: the board read them as it took them)
                # (a re-synchronisation between re-anchors the angles at the set-up's
                # offsets: the difference restarts there, no velocity across it)
                law.observe(qr[k], None if obs < 0 or resynced[obs + 1:k + 1].any() else (
                    (k - obs) * T if lockstep_board else t_wrote[k] - t_wrote[obs]))
                obs = k
        else:                                       # missing: an estimated sample
            # from the last reading before it (reply k damaged on the way back, the
            # replies after it read; a probe dropped readings, or filed a damaged one)
            i = min(seen, k - 1)
            while i > 0 and xr[i, 0] != xr[i, 0]:
                i -= 1
            r = k - i
            if i >= 1 and not resynced[i] and qr[i - 1, 0] == qr[i - 1, 0]:
                # extrapolated from the last two (read, on one set-up)
                x[0] = xr[i, 0] + r * (xr[i, 0] - xr[i - 1, 0])
                x[1] = xr[i, 1] + r * (xr[i, 1] - xr[i - 1, 1])
            else:                                   # held: one reading only
                x[0] = xr[i, 0]
                x[1] = xr[i, 1]
            est[k] = True
            lag[k] = r
        if k == 0:
            eng.x[:, port] = x
            eng.xp[:, port] = x
        eng.set_port_position(x)
        eng.step()
        j00, j01, j10, j11 = jac(qr[i, 0], qr[i, 1])
        f0, f1 = F[0], F[1]
        tau1 = j00 * f0 + j10 * f1                  # tau = J^T F
        tau2 = j01 * f0 + j11 * f1
        if left >= 0:
            # the joints left the measurement's envelope: the loop is not the one
            # measured (a host too slow for its scene, a torque held over stalls), the
            # record not measured. The board (no watchdog) is braked, tau = -B q' from
            # the readings, until at rest or BRAKE_MAX_S (a sample older than
            # HOLD_BOUND_S: zero), then zero torque (before: zero torque at once, and the
            # light joint coasted on its friction alone)
            tau1 = tau2 = 0.0
            if law is not None and braked is None:
                gone = ((k - brake_k) * T if lockstep_board
                        else time.perf_counter() - brake_at)
                if law.at_rest or gone >= BRAKE_MAX_S:
                    braked = "rest" if law.at_rest else "time"
                    brake_end = (k - brake_k, gone)
                elif not (est[k] and ((k - i) * T if lockstep_board
                                      else time.perf_counter() - t_wrote[i]) > HOLD_BOUND_S):
                    tau1, tau2 = law.command()
        elif est[k] and ((k - i) * T if lockstep_board
                         else time.perf_counter() - t_wrote[i]) > HOLD_BOUND_S:
            # no fresh sample for HOLD_BOUND_S: the torque was computed from where the
            # joints were, not where they are; the board (no watchdog) would hold it
            tau1 = tau2 = 0.0
            held_zero += 1
        if mark:
            # the marker instead of the torques: the board holds the write before's
            realign.sent(k)
            probed[k] = True
            tau1, tau2 = (torque[k - 1, 0], torque[k - 1, 1]) if k else (0.0, 0.0)
        torque[k, 0] = clamp1(tau1)
        torque[k, 1] = clamp1(tau2)
        pos[k, 0] = x[0]
        pos[k, 1] = x[1]
        write_into(wbuf, tau1, tau2)
        t_began[k + 1] = time.perf_counter()
        if send(realign.marker if mark else wbuf, k + 1, tau1 != 0.0 or tau2 != 0.0,
                swap=not mark):
            torque[k, 0] = torque[k, 1] = 0.0   # (the zero write went: send)
        t_wrote[k + 1] = time.perf_counter()
    # zero torque (no watchdog), and the late replies, counted. The zero write's reply,
    # read in step, says the board took it as a write (only a flipped top exponent bit
    # of its zeros, 1 bit in 32, would be a torque it cannot show: no checksum); without
    # it the board may be out of step, where a zero write is read as something else:
    # re-armed then (zero torque first, whatever its parser is inside)
    brake_out = None
    if law is not None:
        if braked is None:                          # the ticks' room ran out first
            braked, brake_end = "time", (K - brake_k, (
                (K - brake_k) * T if lockstep_board else time.perf_counter() - brake_at))
        # late: the braking's ticks the host began a period or more late (stalls)
        brake_out = law.report(brake_end[0], brake_end[1], braked,
                               int(stalled[brake_k:K].sum()))
    send(zero, K + 1, False)
    t_wrote[K + 1] = time.perf_counter()
    if watchdog is not None:
        watchdog.arm(False)                     # (zero torque held: the record's end)
        wd_note(K + 1, watchdog.take())         # (its writes up to the disarming)
    if lockstep_board:
        end = time.monotonic() + END_WAIT_S
        while seen < K + 1 and time.monotonic() < end:
            take(_read(ser))
            if seen < K + 1:
                time.sleep(2e-4)
    else:
        # a board on its own clock holds what it last took: the replies are awaited while
        # they come, and a silence of SILENT_S of the host's awake time with the closing
        # reply not read is a board out of step (re-armed below, zero torque first), as
        # in the loop; before, END_WAIT_S (1 s) of a garbage torque held
        end = time.monotonic() + END_WAIT_S

        def take_late(data):
            # the step check widens with the time since the last reading's write, as in
            # the loop: a reply read late is a late sample
            dec.elapsed(time.perf_counter() - t_wrote[seen])
            take(data)
        while seen < K + 1 and time.monotonic() < end and not wd_due[0]:
            n0 = replies
            _awake_wait(lambda: replies != n0 or seen >= K + 1, SILENT_S, take_late)
            if replies == n0:
                break
    # (a robust write of the watchdog's before the closing zero write: its answers
    # unknown, the board re-armed by the host too)
    rearmed_at_end = seen < K + 1 or wd_due[0]
    rearmed_for_watchdog = bool(wd_due[0])      # (counted in watchdog_resyncs)
    if rearmed_at_end:
        # (a write swallowed at the end leaves the count short: the rows in doubt)
        realign.drop_open(K + 1)
        arm(q0deg, K + 1)
    return {"position": pos[:N], "joints": joints[:N], "torque": torque[:N],
            "estimated": est[:N], "lag": lag[:N], "late_ticks": late, "replies": replies,
            "writes": K + 2 + wd_count[0], "rearm_writes": rearm_writes, "readings": xr[:N].copy(), "resyncs": rule.count,
            "watchdog_zeroed": wd_count[0], "watchdog_replies": wd_count[1],
            "watchdog_resyncs": wd_count[2],
            "resynced": resynced[:N], "resync_s": resync_s, "stalled": stalled[:N],
            "stall_s": stall_s, "held_zero": held_zero, "bad_setups": bad_setups,
            "left": left, "brake": brake_out,
            "rearmed_at_end": rearmed_at_end, "rearmed_for_watchdog": rearmed_for_watchdog,
            "realigned": realign.realigned,
            "probes": realign.probes, "probes_late": realign.late, "probed": probed[:N],
            "decoder": dict(dec.stats),
            "write_s": np.stack([t_began[:N], t_wrote[:N]], axis=1) - t_began[0],
            "write_t0": float(t_began[0])}
