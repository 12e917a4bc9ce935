"""Which samples of a run had every contact engaged: the scene replayed from its telemetry.

The prediction of a scene with contacts (:func:`hapsim.analysis.check_scene`) takes every
contact engaged; the run lets them open. The engine is deterministic given the port
positions, so replaying the logged positions through a fresh engine, as the host loop
stepped it (:meth:`hapsim.host.loop.HostLoop._drive`), gives each contact's state at every
sample exactly, offline, after the run: the real-time loop does no extra work.

Replay rules (the loop's):

* row 0 and every row flagged ``FLAG_LOST`` (a recovery) restart the scene: a fresh
  engine (``type(engine)(scene)``) with the port set at rest at that row's position, then
  ``port_step(x)`` of the row;
* every other row is one ``port_step(x)``;
* a row flagged ``FLAG_SKIPPED`` follows STATEs the loop stepped the scene with but did not
  answer (a backlog). The loop records each one's position with the row it precedes
  (:meth:`hapsim.host.telemetry.Telemetry.skipped`): given that record, the replay steps
  them, in order, before the row's own step, and the row is closed only when every contact
  was engaged at each of those steps too. Without the record, or on a row past the point
  where it overflowed (``complete_below``), their positions are unknown, so the states are
  unknown from that row to the next restart. Recorded steps before a restart row are
  dropped with the engine they stepped;
* with a ``velocity_sensor`` correction the scene moves with a velocity the telemetry does
  not hold: only contacts between the port and grounds are known (from the logged port
  position, where the correction places the port).

A contact ``(m1, m2, threshold)`` is engaged at a step when ``x2 - x1 < threshold`` on the
positions the step evaluates (:mod:`hapsim.kernels.cordis`, ``contacts``); after the step
those are the engine's previous positions (every kernel moves ``x`` to ``xp``). A scene
with ``audio`` is replayed with every sub-step's positions of the contacts' ends
(:class:`_AudioStepper`), so a contact that opens between two device samples is seen.

The replay is checked against the telemetry's force column (the force the loop sent): it
equals the replayed port force bit for bit on every row whose force the loop did not
change afterwards (ramp, clamp, passivity controller). The first row where it does not (a
live OSC change, a sounding engine, a correction reading the handle's velocity) ends what
the replay knows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hapsim.host.telemetry import FLAG_CLAMPED, FLAG_LOST, FLAG_RAMP, FLAG_SKIPPED

__all__ = ["ContactReplay", "replay_contacts", "contact_links", "computed_forces",
           "fill_skipped"]


def contact_links(scene) -> list:
    """The scene's contact links.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A validated scene.

    Returns
    -------
    list of hapsim.scene.Link
        Its links of kind ``contact``, in scene order (the kernels' order,
        :class:`hapsim.engine.Engine`); empty when it has none.
    """
    return [lk for lk in scene.links if lk.kind == "contact"]


@dataclass
class ContactReplay:
    """Contact states of every telemetry row.

    Attributes
    ----------
    closed : ndarray of bool, shape (n,)
        Every contact engaged at every (sub-)step of the row, and the replay known there.
    known : ndarray of bool, shape (n,)
        The replay knows the scene's state at the row (False after a skipped STATE whose
        position is not recorded until the next restart, and from the first force
        mismatch on).
    open_link : list of (str or None)
        Per row, the name of the first contact open at the row (None when all closed or
        unknown).
    mismatch_row : int or None
        First row whose logged force differs from the replayed one (None: none).
    reason : str or None
        Why the replay stops knowing (a skipped STATE, a force mismatch, a correction that
        reads the handle's velocity), or None.
    """

    closed: np.ndarray
    known: np.ndarray
    open_link: list
    mismatch_row: int | None = None
    reason: str | None = None


def _skip_plan(skipped, n: int):
    """The skipped STATEs' record per row: ``(start, stop, positions, complete_below)``
    with ``start[i]:stop[i]`` the record's entries before row ``i`` (module notes' rules);
    None without a record."""
    if skipped is None:
        return None
    rows, xs, below = skipped
    rows = np.asarray(rows, dtype=np.int64)
    start = np.searchsorted(rows, np.arange(n), side="left")
    stop = np.searchsorted(rows, np.arange(n), side="right")
    return start, stop, np.asarray(xs, dtype=float), int(below)


def computed_forces(scene, cols: dict, skipped=None):
    """The port force the run's law computed at every row, before the host clamped it at
    the force limit, replayed from the logged positions (module notes' replay rules).

    A clamp is a known input of the linear loop, as a late tick is: the device held the
    clamped force, ``computed + (sent - computed)``, and the response to that difference
    is taken out with the late ticks' (:func:`hapsim.analysis.measurement.late_accounted`).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The calibrated scene the run stepped.
    cols : dict of ndarray
        Telemetry columns from the run's first row: ``position`` [m], ``force`` [N],
        ``flags``, each shape (n,).
    skipped : tuple, optional
        The run's skipped STATEs' record (:meth:`hapsim.host.telemetry.Telemetry.skipped`):
        its steps are replayed (module notes).

    Returns
    -------
    ndarray, shape (n,), or None
        Forces [N]; None when the replay cannot give them: a law the telemetry does not
        hold the inputs of (a velocity sensor), skipped STATEs not in the record, a ramp,
        or a replayed force
        that differs from the logged one on a row the loop did not clamp (a live change,
        the passivity controller).
    """
    x_log = np.asarray(cols["position"], dtype=float)
    f_log = np.asarray(cols["force"], dtype=float)
    flags = np.asarray(cols["flags"]).astype(np.int64)
    plan = _skip_plan(skipped, x_log.size)
    sk = (flags & FLAG_SKIPPED) != 0
    if np.any(flags & FLAG_RAMP) or (np.any(sk) and (
            plan is None or np.any(np.flatnonzero(sk) >= plan[3]))):
        return None
    eng = _replay_engine(scene)
    if eng is None:
        return None
    out = np.empty(x_log.size)
    for i in range(x_log.size):
        if i and flags[i] & FLAG_LOST:
            eng = type(eng)(eng.scene)            # the loop's restart (HostLoop._resume)
        if i == 0 or flags[i] & FLAG_LOST:
            eng.set_port_position(float(x_log[i]), at_rest=True)
        elif plan is not None:
            for e in range(plan[0][i], plan[1][i]):
                eng.port_step(float(plan[2][e]))  # the skipped STATEs before the row
        f = eng.port_step(float(x_log[i]))
        if not flags[i] & FLAG_CLAMPED and not f == f_log[i]:
            return None
        out[i] = f
    return out


def fill_skipped(scene, cols: dict, skipped, ticks, delay: int, passivity: bool = False):
    """The record with the recorded skipped STATEs put back as the rows they would have been.

    A skipped STATE is a sample of the device like any other: its position, seq,
    force_seq and status are recorded (:meth:`hapsim.host.telemetry.Telemetry.skipped`,
    :meth:`~hapsim.host.telemetry.Telemetry.skipped_ticks`), and the force the law computed
    with it, which the loop did not send, is replayed. Put back before the row it preceded,
    the record has no gap in seq there: the device held an older force at the ticks that
    FORCE would have reached, which its force_seq names, a known input like any late tick
    (:func:`hapsim.analysis.measurement.late_accounted`), so a backlog no longer cuts the
    free response into stretches.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The calibrated scene the run stepped.
    cols : dict of ndarray
        Telemetry columns from the run's first row (:data:`hapsim.host.telemetry.COLUMNS`),
        each shape (n,).
    skipped : tuple
        :meth:`~hapsim.host.telemetry.Telemetry.skipped`: rows, positions [m],
        ``complete_below``.
    ticks : ndarray of int64, shape (m, 4)
        :meth:`~hapsim.host.telemetry.Telemetry.skipped_ticks`: seq, force_seq, status,
        time [us] of the same entries.
    delay : int
        The device's delay [samples] (a put-back row's late flag, :mod:`hapsim.kernels.ticks`).
    passivity : bool
        The passivity controller was on: the forces sent are not the law's; nothing is put
        back.

    Returns
    -------
    (dict, tuple) or None
        The columns with the rows put back (shape (n + p,); their ``flags`` FLAG_LATE where
        late, ``turnaround_us`` 0; FLAG_SKIPPED cleared on the rows whose skipped STATEs
        are all back) and the record for :func:`replay_contacts` on them (empty, its
        ``complete_below`` moved with its row); None when nothing is put back: no entry
        before ``complete_below``, a law the telemetry does not hold the inputs of
        (velocity sensor, multi-rate scene, passivity controller), or a replayed force that
        differs from a logged one (the scene changed during the run).
    """
    from hapsim.kernels.ticks import STATUS_FORCE_APPLIED, tick_late
    from hapsim.host.telemetry import FLAG_LATE
    rows, xs, below = (np.asarray(skipped[0], np.int64), np.asarray(skipped[1], float),
                       int(skipped[2]))
    ticks = np.asarray(ticks, np.int64)
    x_log = np.asarray(cols["position"], dtype=float)
    f_log = np.asarray(cols["force"], dtype=float)
    flags = np.asarray(cols["flags"]).astype(np.int64)
    n = x_log.size
    below = min(below, n)
    ok_row = (rows < below) & (rows > 0)
    ok_row[ok_row] = (flags[rows[ok_row]] & FLAG_LOST) == 0   # a restart drops them
    if passivity or not ok_row.any() or ticks.shape[0] != rows.size:
        return None
    eng = _replay_engine(scene)
    if eng is None or eng.multirate_pack is not None:
        return None
    start, stop = (np.searchsorted(rows, np.arange(n), side=sd) for sd in ("left", "right"))
    law = np.zeros(rows.size)
    for i in range(n):
        if i and flags[i] & FLAG_LOST:
            eng = type(eng)(eng.scene)            # the loop's restart (HostLoop._resume)
        if i == 0 or flags[i] & FLAG_LOST:
            eng.set_port_position(float(x_log[i]), at_rest=True)
        else:
            for e in range(start[i], stop[i]):
                law[e] = eng.port_step(float(xs[e]))
        f = eng.port_step(float(x_log[i]))
        if not flags[i] & (FLAG_CLAMPED | FLAG_RAMP) and not (
                f == f_log[i] or (np.isnan(f) and np.isnan(f_log[i]))):
            if i >= below:
                break                             # past the record: not put back anyway
            return None
    keep = np.flatnonzero(ok_row)
    at = rows[keep]
    meta = ticks[keep]
    applied = np.cumsum((np.asarray(cols["status"], np.int64) & STATUS_FORCE_APPLIED) != 0)
    seen = applied[np.maximum(at - 1, 0)] > 0
    late = np.array([tick_late(int(q), int(fq), int(st), int(delay),
                               bool(sn or st & STATUS_FORCE_APPLIED))
                     for (q, fq, st, _), sn in zip(meta, seen)], dtype=bool)
    new = {"time": meta[:, 3] * 1e-6, "position": xs[keep], "force": law[keep],
           "seq": meta[:, 0], "turnaround_us": np.zeros(keep.size),
           "late": late.astype(np.int8), "flags": np.where(late, FLAG_LATE, 0),
           "force_seq": meta[:, 1], "status": meta[:, 2]}
    done = flags.copy()
    done[np.unique(at)] &= ~FLAG_SKIPPED
    out = {}
    for c, v in cols.items():
        base = done.astype(np.asarray(v).dtype) if c == "flags" else np.asarray(v)
        out[c] = np.insert(base, at, new[c].astype(base.dtype)) if c in new else v
    moved = below + int(np.count_nonzero(at < below))
    return out, (np.zeros(0, np.int64), np.zeros(0), moved)


def _replay_engine(scene):
    """A fresh engine that steps the scene as the run's did, or None when the run's law
    needs signals the telemetry does not hold (a velocity sensor)."""
    from hapsim.engine import Engine
    corr = getattr(scene.device, "correction", None) if scene.device is not None else None
    if corr is None:
        return Engine(scene)
    if corr.get("kind") == "velocity_sensor":
        return None
    from hapsim.host.correction import corrected_engine
    return corrected_engine(scene)


class _AudioStepper:
    """Device samples of a multi-rate engine with each sub-step's contact states.

    One :func:`hapsim.kernels.audio.run_periods` call per device sample (so the port force
    is the kernel's own, bit for bit) whose listening channels are replaced by the
    positions of the contacts' ends (code 0, gain 1: ``x`` exactly): the positions a
    sub-step evaluates are those after the previous sub-step (before the period for the
    first), except the port's, which the kernel places at the start of each sub-step
    (held, or interpolated: the frame of that sub-step holds it).
    """

    def __init__(self, eng, ends) -> None:
        head, state = eng.multirate_pack
        self.eng, self.head = eng, head
        self.x = eng.kernel_pack.state[0]          # the engine's positions (shared)
        nsub, port = head[0], head[3]
        self.uniq = np.unique(np.concatenate(ends))
        col = {int(m): j for j, m in enumerate(self.uniq)}
        self.c1 = np.array([col[int(m)] for m in ends[0]], dtype=np.int64)
        self.c2 = np.array([col[int(m)] for m in ends[1]], dtype=np.int64)
        self.is_port = self.uniq == port
        self.state = state[:15] + (self.uniq, np.zeros(self.uniq.size, dtype=np.int64),
                                   np.ones(self.uniq.size), state[18])
        self.frames = np.zeros((nsub, self.uniq.size))
        self.pos = np.zeros(1)
        self.force = np.zeros(1)
        self.rec = np.empty(0, dtype=np.int64)
        self.out = np.empty((0, 0))

    def step(self, x: float, thr: np.ndarray):
        """One device sample at port position ``x`` [m]: (force [N], open mask of shape
        (n_contacts,): open at any sub-step, index of the first contact open at the first
        sub-step with one (-1 when none))."""
        from hapsim.kernels import audio as audio_kernel
        eng = self.eng
        before = self.x[self.uniq]                # (fancy indexing: a copy)
        self.pos[0] = x
        audio_kernel.run_periods(1, *self.head, self.pos, *self.state, self.frames, 0,
                                 self.force, self.rec, self.out, 0)
        eng.sample += 1
        ev = np.vstack([before[None, :], self.frames[:-1]])   # sub-step j evaluates row j
        ev[:, self.is_port] = self.frames[:, self.is_port]
        op = ~(ev[:, self.c2] - ev[:, self.c1] < thr)          # (nsub, n_contacts)
        rows = np.flatnonzero(op.any(axis=1))
        first = int(np.argmax(op[rows[0]])) if rows.size else -1
        return float(self.force[0]), first


def _fixed_contacts(scene, x_log, names, ends, thr) -> ContactReplay:
    """Contact states without a replay (a velocity sensor: the scene's masses move with a
    velocity the telemetry does not hold). A contact between the port and grounds is known
    from the logged port position alone (the sensor's correction places the port at the
    position read); one touching a virtual mass is not."""
    n = x_log.size
    known = np.zeros(n, dtype=bool)
    closed = np.zeros(n, dtype=bool)
    open_link: list = [None] * n
    moving = {scene.index(m.name) for m in scene.masses if m.kind == "mass"}
    if any(int(a) in moving or int(b) in moving for a, b in zip(*ends)):
        return ContactReplay(closed, known, open_link, None,
                             "the run's correction (velocity_sensor) steps the scene with "
                             "the handle's measured velocity, which the telemetry does not "
                             "hold: the states of contacts at virtual masses cannot be "
                             "replayed")
    x0 = np.array([m.x0 for m in scene.masses], dtype=float)
    pos = np.repeat(x0[None, :], n, axis=0)
    pos[:, scene.index(scene.port.name)] = x_log
    op = ~(pos[:, ends[1]] - pos[:, ends[0]] < thr)            # (n, n_contacts)
    known[:] = True
    closed[:] = ~op.any(axis=1)
    for i in np.flatnonzero(~closed):
        open_link[i] = names[int(np.argmax(op[i]))]
    return ContactReplay(closed, known, open_link, None, None)


def replay_contacts(scene, cols: dict, passivity: bool = False,
                    skipped=None) -> ContactReplay:
    """Replay a run's logged port positions through a fresh engine; contact states per row.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The calibrated scene the run stepped (with a port and at least one contact).
    cols : dict of ndarray
        Telemetry columns (:meth:`hapsim.host.telemetry.Telemetry.columns`) from the
        run's first row: ``position`` [m], ``force`` [N], ``flags``, each shape (n,).
    passivity : bool
        The passivity controller was on (it changes the force sent without a flag: the
        force check is then skipped; the scene's states do not depend on the force sent).
    skipped : tuple, optional
        The run's skipped STATEs' record (:meth:`hapsim.host.telemetry.Telemetry.skipped`:
        rows, positions [m], ``complete_below``); None: no record (a skipped STATE makes
        the states unknown until the next restart).

    Returns
    -------
    ContactReplay
        Per-row contact states (module notes give the replay rules and their source, the
        host loop's ``_drive``).
    """
    contacts = contact_links(scene)
    x_log = np.asarray(cols["position"], dtype=float)
    f_log = np.asarray(cols["force"], dtype=float)
    flags = np.asarray(cols["flags"]).astype(np.int64)
    n = x_log.size
    closed = np.zeros(n, dtype=bool)
    known = np.zeros(n, dtype=bool)
    open_link: list = [None] * n
    names = [lk.name for lk in contacts]
    ends = (np.array([scene.index(lk.m1) for lk in contacts], dtype=np.int64),
            np.array([scene.index(lk.m2) for lk in contacts], dtype=np.int64))
    thr = np.array([lk.threshold for lk in contacts], dtype=float)
    eng = _replay_engine(scene)
    if eng is None:
        return _fixed_contacts(scene, x_log, names, ends, thr)
    multi = eng.multirate_pack is not None and not eng.corrected
    if eng.multirate_pack is not None and not multi:
        return ContactReplay(closed, known, open_link, None,
                             "a corrected multi-rate scene cannot be replayed sub-step by "
                             "sub-step: the contact states are unknown")
    stepper = _AudioStepper(eng, ends) if multi else None
    plan = _skip_plan(skipped, n)
    alive = True
    mismatch = None
    reason = None
    for i in range(n):
        fl = int(flags[i])
        if i == 0 or fl & FLAG_LOST:
            if i:
                eng = type(eng)(eng.scene)        # the loop's restart (HostLoop._resume)
                stepper = _AudioStepper(eng, ends) if multi else None
            eng.set_port_position(float(x_log[i]), at_rest=True)
            alive = mismatch is None
        elif fl & FLAG_SKIPPED and alive and (plan is None or i >= plan[3]):
            alive = False
            reason = reason or (f"STATEs before row {i} were skipped (a backlog): the scene "
                                f"took positions the telemetry does not hold" +
                                ("" if plan is None else " (the skipped STATEs' record "
                                 "was full)"))
        steps = [] if (i == 0 or fl & FLAG_LOST or plan is None) else \
            plan[2][plan[0][i]:plan[1][i]].tolist()
        steps.append(float(x_log[i]))
        first = -1                                # the first contact open at any step
        for x in steps:
            if multi:
                f, op1 = stepper.step(x, thr)
            else:
                f = eng.port_step(x)
                xp = eng.kernel_pack.state[1]    # positions before this step (shared)
                op = ~(xp[ends[1]] - xp[ends[0]] < thr)
                op1 = int(np.argmax(op)) if op.any() else -1
            if first < 0:
                first = op1
        ok = first < 0
        if not alive:
            continue
        if (not passivity and not fl & (FLAG_RAMP | FLAG_CLAMPED)
                and not (f == f_log[i] or (np.isnan(f) and np.isnan(f_log[i])))):
            mismatch = i
            alive = False
            reason = (f"the replayed force differs from the logged one from row {i} on "
                      f"({f!r} N against {float(f_log[i])!r} N): the scene was changed "
                      f"during the run or stepped by another engine")
            continue
        known[i] = True
        closed[i] = ok
        if not ok:
            open_link[i] = names[first]
    return ContactReplay(closed, known, open_link, mismatch, reason)
