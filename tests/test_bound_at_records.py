"""The linearisation bound stated at what the records did (issue 29: the 2DIY's board on
its own clock coasts through its set-up past the hand's ``a``; the Falcon's verdict had
computed its records' excursion and left it unused): its amplitude is the largest motion
of the fitted rows, and the contact it rests on "opens" exactly when some fitted row has
left it, checked against the contact laws themselves (a plane's penetration, a contact's
distance to its ground mass), not against the helper's algebra."""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.linearisation import bound_at_records, linearisation_bound
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
