"""Before a run: will its record be comparable with the prediction?

A scene with contacts is predicted with every contact engaged
(docs/design.md, 'A whole scene'); after the run only the longest stretch of the free response with every contact
closed is identified (:func:`hapsim.analysis.measurement.identify`, ``closed``). Whether
that stretch is long enough is decided here *before* the run, from the scene alone: the
closed loop of the device model and the engine is stepped offline in lockstep
(:class:`hapsim.device_model.InProcessLoop`, the THS without a protocol), its record is
replayed exactly as the run's telemetry is (:func:`hapsim.pipeline.contact_replay.
replay_contacts`) and the stretch is measured with identify's own rule (``max(4 order +
10, 100)`` samples). The run then says on stderr, before it starts, what it will not be able
to measure and why; its report says the same (``measured.stated_before_run``).

In lockstep the prediction is the run's record sample for sample (the same device model,
the same engine, the same timing convention), so it agrees with what the run finds
(tests/test_scene_measurability.py). In real time a backlog (skipped STATEs) or a late
FORCE can still cut the record: that is the loop's timing, not the scene, and the report
says it after the run.
"""

from __future__ import annotations

import math
import os

import numpy as np

__all__ = ["predict_comparable", "closed_stretch"]


def closed_stretch(closed: np.ndarray, seq: np.ndarray, start: int, order: int,
                   skip: int) -> tuple[int, int, int]:
    """The longest stretch of closed rows of the free response, by identify's rule.

    The rows from sequence number ``start`` on are cut wherever the contact state changes
    (or ``seq`` jumps); a stretch that follows a cut loses its first ``skip`` rows (the
    dead-beat transient of the delay line); the stretches with every contact closed are
    kept (hapsim/analysis/measurement.py, ``identify``'s ``segments``).

    Parameters
    ----------
    closed : ndarray of bool, shape (n,)
        Per row: every contact engaged.
    seq : ndarray of int, shape (n,)
        The rows' sequence numbers.
    start : int
        First sequence number of the free response.
    order : int
        Identification order (non-zero closed-loop poles seen at the port).
    skip : int
        Rows dropped after a cut (``ceil(d) + 2``).

    Returns
    -------
    first : int
        Index (row of the free response, from ``start``) where the stretch begins.
    length : int
        Its length [samples].
    needed : int
        What the fit needs: ``max(4 order + 10, 100)`` [samples].
    """
    seq = np.asarray(seq, dtype=np.int64)
    sel = seq >= start
    cl, s = np.asarray(closed, dtype=bool)[sel], seq[sel]
    need = max(4 * int(order) + 10, 100)
    if cl.size == 0:
        return 0, 0, need
    cut = (np.diff(s) != 1) | (cl[1:] != cl[:-1])
    edges = np.concatenate([[0], np.flatnonzero(cut) + 1, [cl.size]])
    best = (0, 0)
    for a, b in zip(edges[:-1], edges[1:]):
        if not cl[a]:
            continue
        a2 = a if a == 0 else min(a + skip, b)
        if b - a2 > best[1] - best[0]:
            best = (a2, b)
    return int(best[0]), int(best[1] - best[0]), need


def predict_comparable(prep, n: int | None = None) -> dict | None:
    """Predict, before running, whether a run's record will be comparable.

    Parameters
    ----------
    prep : hapsim.pipeline.run_types.PreparedRun
        :func:`hapsim.pipeline.runner.prepare_run`'s result (calibrated scene, prediction,
        excitation end, sizes).
    n : int, optional
        Samples to simulate; default the run's (``n_samples``, the identification window
        ``n_window`` for an open-ended run, at most the window: what identification reads).

    Returns
    -------
    dict or None
        None when the scene has no contact, no port or device, or no identification order
        (nothing to predict). Otherwise ``comparable`` (bool), ``closed_samples`` (the
        longest closed stretch), ``needed``, ``samples`` (simulated), and when not
        comparable ``reason`` (which contact, at which sample, as the run's verdict says
        it: :func:`hapsim.analysis.measurement.contact_verdict`), ``first_open_sample`` and
        ``open_contact``.

    Raises
    ------
    ConfigError
        An unreadable excitation profile (the run would refuse it too).
    """
    from hapsim.analysis.measurement import contact_verdict
    from hapsim.pipeline.contact_replay import contact_links, replay_contacts
    from hapsim.host.telemetry import FLAG_CLAMPED
    from hapsim.device_model import InProcessLoop, MockPhysics
    from hapsim.engine import Engine

    scene = prep.scene
    dev = scene.device
    order = int(prep.pred.get("order") or 0)
    if scene.port is None or dev is None or not order or not contact_links(scene):
        return None
    if n is None:
        n = prep.n_samples if prep.n_samples > 0 else prep.n_window
        n = min(n, prep.n_window)
    n = int(n)
    T = scene.period
    base = prep.base_dir or (os.path.dirname(os.path.abspath(scene.path))
                             if scene.path != "<string>" else None)
    phys = MockPhysics(dev, scene.rate_hz, scene.excitation, base_dir=base)
    eng = Engine(scene)
    loop = InProcessLoop(phys, eng.port_step, int(math.ceil(float(dev.delay))),
                         dev.force_limit)
    eng.set_port_position(phys.sample(), at_rest=True)
    x = np.zeros(n)
    f = np.zeros(n)
    for i in range(n):
        x[i], f[i] = loop.step()
    lim = float(dev.force_limit)
    flags = np.where(np.abs(f) > lim, FLAG_CLAMPED, 0).astype(np.int64)
    seq = np.arange(n, dtype=np.int64)
    replay = replay_contacts(scene, {"position": x, "force": f, "flags": flags})
    start = int(math.ceil(prep.exc_end / T - 1e-9)) + math.ceil(float(dev.delay)) + 3
    skip = math.ceil(float(dev.delay)) + 2
    _, length, need = closed_stretch(replay.closed, seq, start, order, skip)
    out = {"comparable": bool(length >= need), "closed_samples": length, "needed": need,
           "samples": n}
    if not out["comparable"]:
        m = {"comparable": False, "closed_samples": length, "needed": need}
        contact_verdict(m, replay, seq, start, T)
        out.update(reason=m["reason"], first_open_sample=m["first_open_sample"],
                   open_contact=m["open_contact"])
    return out
