"""The linearisation bound stated at what the records did (issue 29: the 2DIY's board on
its own clock coasts through its set-up past the hand's ``a``; the Falcon's verdict had
computed its records' excursion and left it unused): its amplitude is the largest motion
of the fitted rows, and the contact it rests on "opens" exactly when some fitted row has
left it, checked against the contact laws themselves (a plane's penetration, a contact's
distance to its ground mass), not against the helper's algebra."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from hapsim.analysis.linearisation import bound_at_records, linearisation_bound
from hapsim.kinematics import device
from hapsim.scene import parse_scene_nd


def _scene(rng, dim: int):
    """A Cartesian handle at rest pressed on a plane (random normal, penetration 0.1-1 mm)
    and inside a contact with a ground mass (random centre 10-30 mm away, threshold
    0.1-1 mm beyond it), held by a ground spring; returns the scene and the laws' data."""
    normal = rng.normal(size=dim)
    normal /= np.linalg.norm(normal)
    p0 = float(rng.uniform(1e-4, 1e-3))
    u = rng.normal(size=dim)
    u /= np.linalg.norm(u)
    centre = u * float(rng.uniform(0.01, 0.03))
    threshold = float(np.linalg.norm(centre) + rng.uniform(1e-4, 1e-3))
    mass = np.diag(rng.uniform(0.05, 0.3, dim)).tolist()
    text = (f"dimension: {dim}\nrate_hz: 1000\nmasses:\n"
            f"  - {{name: hand, kind: port}}\n"
            f"  - {{name: c, kind: ground, x0: {centre.tolist()}}}\n"
            f"  - {{name: g, kind: ground, x0: {[0.0] * dim}}}\n"
            f"links:\n"
            f"  - {{name: ring, kind: contact, between: [hand, c], stiffness: 500, "
            f"damping: 1.0, threshold: {threshold!r}}}\n"
            f"  - {{name: hold, kind: spring_damper, between: [hand, g], stiffness: 200, "
            f"damping: 0.5}}\n"
            f"planes:\n  - {{name: wall, normal: {normal.tolist()}, offset: {p0!r}, "
            f"stiffness: 800, damping: 1.0}}\n"
            f"device: {{mass: {mass}, friction: {[0.3] * dim}, delay: 1}}\n")
    return parse_scene_nd(text, "random.yaml"), normal, p0, centre, threshold


def test_opening_is_the_contact_laws_over_random_scenes_and_records():
    """Random 2-D and 3-D scenes and records (random walks of 0.2-2 times the shallower
    depth, 5 % of rows missing, 10 % not fitted): the bound's amplitude is the hand's
    ``a`` or the largest fitted motion, whichever is larger; it says the contact opens
    exactly when a fitted row left the plane (``offset - n . x <= 0``) or reached the
    ring's threshold (``|x - c| >= L``), and then states no bound (inf); otherwise
    ``(c_kin + c_link)`` times its amplitude. A motion along the plane, farther than
    the depth, opens nothing: the bound at the norm alone (the hand's ``a`` against
    the shallowest depth in every direction) would have refused it."""
    rng = np.random.default_rng(2911)
    seen = {"opens": 0, "engaged": 0, "tangential": 0}
    for trial in range(200):
        dim = 2 + trial % 2
        sc, n, p0, c, L = _scene(rng, dim)
        x0 = np.asarray(sc.port.x0, float)
        depth = min(p0, L - float(np.linalg.norm(x0 - c)))
        a = float(rng.uniform(0.05, 0.5)) * depth
        recs, usable = [], []
        scale = float(rng.uniform(0.2, 2.0)) * depth
        for _ in range(5):
            N = int(rng.integers(20, 80))
            steps = rng.normal(size=(N, dim))
            if rng.random() < 0.3:                    # along the plane only
                steps -= np.outer(steps @ n, n)
            D = np.cumsum(steps, axis=0)
            D *= scale / max(float(np.max(np.linalg.norm(D, axis=1))), 1e-300)
            D[rng.random(N) < 0.05] = np.nan
            recs.append(D)
            usable.append(None if rng.random() < 0.3 else rng.random(N) < 0.9)
        bound, ex = bound_at_records(sc, a, recs, None, usable=usable)
        rows = np.concatenate([D[(np.isfinite(D).all(axis=1)) & (
            np.ones(len(D), bool) if u is None else u)] for D, u in zip(recs, usable)])
        x = x0 + rows
        left = bool(np.any(p0 - x @ n <= 0.0)            # the plane's penetration
                    or np.any(np.linalg.norm(x - c, axis=1) >= L))
        assert ex == (float(np.max(np.linalg.norm(rows, axis=1))) if rows.size else 0.0)
        assert bound.amplitude == max(a, ex)
        assert bound.opens == left, (trial, bound.opening, bound.opening_name)
        if left:
            assert math.isinf(bound.stiffness) and bound.to_dict()["felt_stiffness"] is None
            seen["opens"] += 1
        else:
            assert bound.stiffness == (bound.kinematic + bound.link) * bound.amplitude
            seen["engaged"] += 1
            if ex >= linearisation_bound(sc, a).depth:
                seen["tangential"] += 1
    # the draw reaches every case (not a test that passes on one branch)
    assert min(seen.values()) >= 5, seen


def test_without_records_the_amplitude_is_taken_in_every_direction():
    """``linearisation_bound`` alone (no records: ``opening`` not measured) keeps the
    rule it had: the hand's ``a`` against the shallowest depth, whatever the direction."""
    rng = np.random.default_rng(5)
    sc, n, p0, c, L = _scene(rng, 2)
    depth = linearisation_bound(sc, 1e-6).depth
    b = linearisation_bound(sc, 0.999 * depth)
    assert math.isnan(b.opening) and not b.opens
    assert linearisation_bound(sc, b.depth).opens


def test_the_falcon_verdict_states_its_bound_at_its_fitted_rows():
    """The Falcon's verdict (it computed its records' excursion and stated the bound at the
    hand's ``a``): on ``configs/delta_sphere.yaml``'s exact lockstep records at
    ``a`` = 0.1 mm the bound is at their largest distance from the operating point, the
    record from rest's own included (the velocity starts go past ``a``; a scene not at
    rest at its joints drifts in every record), the sphere named and not reached along
    its radius; a
    record pushed 8 times out over 20 rows reaches the sphere's depth and the verdict
    says the contact opens; the same rows missing (their replies lost: cut from the fit)
    leave the bound where the clean records put it."""
    from hapsim.emulated.falcon_felt import falcon_felt_verdict
    from hapsim.lockstep import LockstepND, excitation_starts, identification_plan
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd("configs/delta_sphere.yaml")
    N, a = 100, 1e-4
    plan = identification_plan(sc, N)
    X = [LockstepND(sc).step(N, record=True)] + [
        LockstepND(sc, x0=x0, v0=v0).step(N, record=True)
        for x0, v0 in excitation_starts(3, a, sc.period)[1:]]

    kin = device("delta", sc.device.geometry)
    x_eq = kin.forward(np.asarray(sc.device.joints, float))

    def verdict(X, joints=None):
        # the readings' positions are the handle's (the operating point plus the motion)
        runs = [{"position": x_eq + x, "commands": np.zeros((N, 3)),
                 "joints": np.zeros((N, 3)) if joints is None else joints[j]}
                for j, x in enumerate(X)]
        return falcon_felt_verdict(sc, runs, plan, a)
    clean = verdict(X)["bound"]
    reach = max(float(np.max(np.linalg.norm(x, axis=1))) for x in X)
    # (x_eq + x) - x_eq: a few ulps of x_eq off x
    ulps = 8 * float(np.spacing(np.max(np.abs(x_eq))))
    assert abs(clean.amplitude - reach) <= ulps and reach > 1.5 * a
    assert clean.opening_name == "sphere" and 0.0 < clean.opening < 1.0
    pushed = [x.copy() for x in X]
    pushed[3][40:60] *= 8.0
    r = verdict(pushed)
    assert r["bound"].opens and r["verdict"] == "not measurable"
    assert "'sphere'" in r["reason"] and "opens" in r["reason"], r["reason"]
    lost = [x.copy() for x in pushed]
    joints = [np.zeros((N, 3)) for _ in X]
    lost[3][38:62] = joints[3][38:62] = np.nan
    b = verdict(lost, joints)["bound"]
    # the cut records' motion and the clean ones' are both taken about the operating
    # point: the rows left are the clean records' own, so the same bound to a few ulps
    # of x_eq (the rows cut do not hold the clean records' largest motion)
    assert abs(b.amplitude - clean.amplitude) <= ulps
    assert abs(b.opening - clean.opening) <= ulps / b.depth


def _restarted(X, at, start):
    """The record from rest cut at rows ``at``..``at + 3`` and moving after the cut as
    ``start`` does from its own first row (a re-synchronisation: the hand's next start)."""
    N = X[0].shape[0]
    rest = X[0].copy()
    rest[at + 4:] = start[:N - at - 4]
    usable = np.ones(N, bool)
    usable[at:at + 4] = False
    return rest, usable


def test_cut_records_state_the_bound_at_their_own_motion_not_at_differences():
    """Records cut at their disturbances are fitted each on its own stretches about the
    operating point (the 2DIY's and the Falcon's verdicts), the record from rest too: the
    bound is at that motion. Before, it was at the differences against the record from
    rest over the other records' rows: when the record from rest moved after its cut (a
    re-synchronisation restarts it from the hand's next start), a difference added its
    motion to another record's (the lossy 2DIY's runs on the 0.5 mm wall said the wall
    opened, 1.04-1.69 of its depth, from fitted rows that stayed at 0.9 of it) or left it
    out. Checked against the plane's law itself: the largest rise of ``n . x`` over the
    fitted rows, over the depth."""
    from hapsim.emulated.falcon_felt import falcon_felt_verdict
    from hapsim.emulated.haply2_verdict import felt_verdict_of_runs
    from hapsim.lockstep import LockstepND, excitation_starts, identification_plan
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd("configs/pantograph_wall.yaml")
    N, a = 200, 1e-4
    plan = identification_plan(sc, N)
    starts = excitation_starts(2, a, sc.period)
    X = [LockstepND(sc, x0=x0, v0=v0).step(N, record=True) for x0, v0 in starts]
    # after its cut the record from rest moves as the start at -a along the wall's
    # normal (into the wall): every difference then adds that motion's mirror
    rest, ok0 = _restarted(X, 60, -X[2])
    recs = [rest] + X[1:]
    kin = device("pantograph", sc.device.geometry)
    q0 = np.asarray(sc.device.joints, float)
    x_eq = kin.forward(q0)
    runs = [{"position": x_eq + x, "joints": np.tile(q0, (N, 1)), "torque": np.zeros((N, 2)),
             "usable": ok0 if j == 0 else np.ones(N, bool)} for j, x in enumerate(recs)]
    b = felt_verdict_of_runs(sc, runs, plan, 2.0 ** 22, a)["bound"]
    wall = sc.planes[0]
    normal = np.asarray(wall.normal, float) / np.linalg.norm(wall.normal)
    depth = float(wall.offset - normal @ x_eq)
    fitted = [x[ok0] if j == 0 else x for j, x in enumerate(recs)]
    rise = max(float(np.max(f @ normal)) for f in fitted)
    reach = max(float(np.max(np.linalg.norm(f, axis=1))) for f in fitted)
    ulps = 8 * float(np.spacing(np.max(np.abs(x_eq))))
    assert b.opening_name == "wall"
    assert abs(b.opening - rise / depth) <= ulps / depth, (b.opening, rise / depth)
    assert abs(b.amplitude - reach) <= ulps
    # the differences' rise, what the bound was stated at before: larger by the mirror
    diffs = [x - rest for x in X[1:]]
    assert max(float(np.max(d[ok0] @ normal)) for d in diffs) > 1.3 * rise
    # the Falcon's verdict, the same wiring: the excursion of the fitted rows about the
    # operating point, the record from rest's own motion after its cut included
    sd = load_scene_nd("configs/delta_sphere.yaml")
    pd = identification_plan(sd, 100)
    Y = [LockstepND(sd, x0=x0, v0=v0).step(100, record=True)
         for x0, v0 in excitation_starts(3, a, sd.period)]
    big = 1.5 * Y[6]                          # a start half as fast again after the cut
    rest3, ok3 = _restarted(Y, 30, big)
    kd = device("delta", sd.device.geometry)
    y_eq = kd.forward(np.asarray(sd.device.joints, float))
    joints = [np.zeros((100, 3)) for _ in Y]
    joints[0][~ok3] = np.nan                  # the cut: its replies missing
    runs3 = [{"position": y_eq + (rest3 if j == 0 else y), "commands": np.zeros((100, 3)),
              "joints": joints[j]} for j, y in enumerate(Y)]
    r3 = falcon_felt_verdict(sd, runs3, pd, a)
    own_reach = max(float(np.max(np.linalg.norm(rest3[ok3], axis=1))),
                    max(float(np.max(np.linalg.norm(y, axis=1))) for y in Y[1:]))
    assert abs(r3["bound"].amplitude - own_reach) <= 8 * float(np.spacing(np.max(np.abs(y_eq))))


def test_a_scene_not_at_rest_states_its_bound_at_its_drift_too():
    """configs/pantograph_wall.yaml with the press spring 1.75 times as stiff and the wall
    0.37 times (their rest positions kept): the forces no longer balance at the joints,
    and every record, the one from rest too, drifts about 1.7 mm toward the new
    equilibrium. The loop the records' differences measure is the one linearised along
    that drift, so the 2DIY's verdict states its linearisation bound at the records'
    own motion about the operating point, the drift included: at least the record from
    rest's excursion (before: at the differences', 0.21 mm at a = 0.1 mm, an eighth of
    it)."""
    import dataclasses
    from hapsim.analysis.linearisation import records_excursion
    from hapsim.emulated.haply2_lockstep import measure_felt_haply2
    from hapsim.lockstep import LockstepND, identification_plan
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd("configs/pantograph_wall.yaml")
    sc = dataclasses.replace(
        sc, links=[dataclasses.replace(lk, stiffness=1.75 * lk.stiffness) for lk in sc.links],
        planes=[dataclasses.replace(p, stiffness=0.37 * p.stiffness) for p in sc.planes])
    N = 150
    plan = identification_plan(sc, N)
    drift = records_excursion([LockstepND(sc).step(N, record=True)])
    a = 1e-4
    assert drift > 10 * a                                # the scene is not at rest
    r = measure_felt_haply2(sc, amplitude=a, plan=plan, samples=N)
    # the drift read through the encoders: a count of 2^22 per revolution is 1.5e-6 rad,
    # at most |J| 1.5e-6 = 2e-7 m at the handle (|J| < 0.15 m here), derived; 1e-6 m is
    # five counts (measured: the bound 1.8e-5 m above the drift, the starts' motion on
    # top of it; 0.21 mm before, at the differences)
    assert r["bound"].amplitude >= drift - 1e-6, (r["bound"].amplitude, drift)


def test_held_forces_taken_out_of_the_records_leave_their_departure_in_the_bound():
    """The 2DIY's wall (``configs/pantograph_wall.yaml``) over a port on the simulated
    clock, its framed device on its own clock, the host stalled 20-100 % of ``ms`` (20, 30
    and 50) before a seeded 2 % of its FORCEs (seeds 0-5): the device holds the force
    before through each stall (late ticks, their response taken out through the linear
    loop, :mod:`hapsim.pipeline.felt_port`), which carries the handle to 1.4-494 times
    the free response's excursion, and that response's departure from the linear loop is
    left in what the fit sees. The felt matrices are within the bound stated
    (:func:`~hapsim.analysis.linearisation.bound_at_records` with ``free``) in all 18
    (at most 0.10 of it measured). Taken at the excursion alone, as before, 4 of them
    were off by more than the bound, up to 10.7 times it (seed 1 at 50 ms; a fresh-clone
    CI run under the suite's load found it at 2.1): asserted too, so the class is there."""
    import firmware_protocol as fp
    from hapsim.emulated.links import SimTransport
    from hapsim.emulated.mock import MockDeviceND
    from hapsim.pipeline.felt_port import measure_felt_port
    from hapsim.scene import load_scene_nd

    sc = load_scene_nd(str(Path(__file__).resolve().parents[1] / "configs"
                           / "pantograph_wall.yaml"))

    class Stalled:
        def __init__(self, inner, seed, ms):
            self.inner, self.rng, self.ms = inner, np.random.default_rng(seed), ms
            self.info = inner.info

        def send(self, msg):
            if isinstance(msg, fp.Force) and self.rng.random() < 0.02:
                self.inner.sleep(self.rng.uniform(0.2, 1.0) * self.ms * 1e-3)
            self.inner.send(msg)

        def receive(self, timeout=0.0):
            return self.inner.receive(timeout)

        def last_frames(self):
            return self.inner.last_frames()

    now, before = [], []
    for seed in range(6):
        for ms in (20, 30, 50):
            res = measure_felt_port(Stalled(SimTransport(MockDeviceND(sc, lockstep=False)),
                                            seed, ms), sc)
            poles = res["predicted"].render.rendered_poles
            bound, _ = bound_at_records(sc, 1e-8, res["moved"], poles,
                                        free=res["responses"])
            old, _ = bound_at_records(sc, 1e-8, res["moved"], poles)
            for key in ("felt_stiffness", "felt_damping"):
                now.append(res["deviation"][key] / bound.to_dict()[key])
                before.append(res["deviation"][key] / old.to_dict()[key])
    assert max(now) <= 1.0, max(now)
    assert max(before) > 1.0, max(before)           # the class happened
