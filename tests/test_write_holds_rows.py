"""hold_corrections' rows all at once (hapsim.analysis.write_holds._corrected_rows, issue 31:
its loop over the rows was most of a Haply measurement's CPU) against that loop itself,
kept here as the oracle: the loop of the docstring's formulas, one row at a time, as
``hold_corrections`` ran it before. The same estimates, bounds, rows corrected and
rounding gains, bit for bit, on seeded random records of a 1-D joint (``configs/haply.yaml``)
and of the 2DIY (``configs/pantograph_wall.yaml``): jittered and stalled writes, readings
missing, a latency, windows cut short by the record's ends and its cuts, every option."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hapsim.analysis import write_holds as wh
from hapsim.kinematics import device
from hapsim.scene import load_scene, load_scene_nd

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def _loop(rec, scene, J, delta, *, latency_s=0.0, first_torque=None, rounding_apart=False,
          window=0):
    """The oracle: ``hold_corrections``' loop over the rows as it was (its numpy calls,
    one row at a time), from the same set-up (``write_holds._hold_setup``)."""
    out, su = wh._hold_setup(rec, scene, J, delta, latency_s=latency_s,
                             first_torque=first_torque, rounding_apart=rounding_apart)
    if su is None:
        return out
    T, L, N, b, x = su.T, su.L, su.N, su.b, su.x
    Mi, B, MiB, nMi, nMiB, eps = su.Mi, su.B, su.MiB, su.nMi, su.nMiB, su.eps
    Fall, eFall, a_max, ok_hold = su.Fall, su.eFall, su.a_max, su.ok_hold
    n = Mi.shape[0]
    pos, vel = out["position"].copy(), out["velocity"].copy()
    QV = wh._known_motion(b, Fall, Mi) if window else None
    acc = np.zeros((N, 2))
    for k in range(1 if first_torque is not None else 2, N):
        h = b[k] - b[k - 1]
        dh = h - T
        dx = x[k] - x[k - 1]
        h_lo, h_hi = h - L, h + L
        if not (np.isfinite(dx).all() and np.isfinite(h) and np.isfinite(out["delta"][k])
                and h_lo > 0 and h_hi * nMiB < 2):
            continue
        F, eF = Fall[k - 1], float(eFall[k - 1])
        c = 1.0 / (1.0 - h_hi * nMiB / 2)
        v_hat = np.linalg.solve(np.eye(n) + h / 2 * MiB, dx / h + h / 2 * (Mi @ F))
        a_hat = Mi @ (F - B @ v_hat)
        ndx = float(np.linalg.norm(dx))
        V = (ndx + 2 * eps) / h_lo + a_max * h_hi
        e_v = (c * ((0.0 if rounding_apart else 2 * eps / h_lo) + nMiB * a_max * h_hi ** 2 / 6
                    + h_hi / 2 * nMi * eF)
               + L * c * ((ndx + 2 * eps) / h_lo ** 2 + float(np.linalg.norm(Mi @ F)) / 2)
               + L * c * c * nMiB * V / 2)
        g_r = 2 * c / h_lo
        fit = wh._window_velocity(k, window, b, x, QV, ok_hold) if window else None
        cw = None
        if fit is not None:
            v_hat, sc1, sc2, sq, tmax, lo, cw = fit
            a_hat = Mi @ (F - B @ v_hat)
            e_v = (nMiB * V * sc2 / 2 + nMi * float(np.max(eFall)) * sc2 / 2
                   + (0.0 if rounding_apart else eps * sc1)
                   + 2 * L * sc1 * (V + a_max * tmax))
            g_r = sq * np.sqrt(2 * window + 1)
        out["state"][k, :n] = dh * v_hat - dh * dh / 2 * a_hat
        out["state"][k, n:] = dh * a_hat
        e_a = nMi * eF + nMiB * e_v
        D = abs(dh) + L
        nv, na = float(np.linalg.norm(v_hat)), float(np.linalg.norm(a_hat))
        pos[k] = (D * e_v + L * nv + D * D / 2 * e_a + L * (2 * abs(dh) + L) / 2 * na
                  + nMiB * a_max * D ** 3 / 6)
        vel[k] = D * e_a + L * na + nMiB * a_max * D * D / 2
        out["corrected"][k] = True
        if rounding_apart and window and abs(dh) <= wh.HOLD_CUT_PERIODS * T:
            if cw is None:
                lo, cw = k - 1, np.array([-c / h_lo, c / h_lo])
            G = np.array([D * (1 + D * nMiB / 2), D * nMiB])
            acc[lo:lo + cw.size] += np.outer(cw * cw, G * G)
        elif rounding_apart:
            out["rounding_gain"][k] = (g_r * D * (1 + D * nMiB / 2), g_r * D * nMiB)
    if rounding_apart and window:
        out["rounding_gain"] = np.sqrt((2 * window + 1) * acc)
    out["position"], out["velocity"] = pos, vel
    return out


def _record(rng, scene, n, N):
    """A random record: writes a period apart with a host's jitter (up to 0.4 periods),
    a few stalls (1-3 periods) and a gap, readings on a random walk (some missing),
    torques of a few tenths of the force limit's order."""
    T = scene.period
    dt = T + rng.uniform(0.0, 0.4 * T, N - 1) * (rng.random(N - 1) < 0.8)
    stall = rng.choice(N - 1, size=int(rng.integers(0, 4)), replace=False)
    dt[stall] += rng.uniform(1.0, 3.0, stall.size) * T
    b = np.concatenate([[0.0], np.cumsum(dt)])
    if rng.random() < 0.3:
        b[int(rng.integers(2, N))] = np.nan
    x = np.cumsum(rng.normal(0.0, 1e-5, (N, n)), axis=0)
    read = x.copy()
    read[rng.random(N) < 0.03] = np.nan
    tau = rng.normal(0.0, 0.02, (N, n))
    return {"write_s": b[:, None], "position": x, "readings": read, "torque": tau}


@pytest.mark.parametrize("dim", [1, 2])
def test_the_rows_at_once_are_the_loop_over_the_rows_bit_for_bit(dim):
    """30 seeded random records a dimension, each under the options as the drivers call
    them and as they do not (the window with the rounding in the bounds, the rounding
    apart without a window, a latency, a short window, row 1's torque known): every
    output array identical to the oracle loop's."""
    if dim == 1:
        scene = load_scene(str(CONFIGS / "haply.yaml"))
        J = np.eye(1)
    else:
        scene = load_scene_nd(str(CONFIGS / "pantograph_wall.yaml"))
        J = device("pantograph", scene.device.geometry).jacobian(scene.device.joints)
    rng = np.random.default_rng(310 + dim)
    options = [dict(), dict(window=wh.VELOCITY_WINDOW, rounding_apart=True),
               dict(window=wh.VELOCITY_WINDOW), dict(rounding_apart=True),
               dict(window=3, rounding_apart=True, latency_s=2e-5),
               dict(latency_s=5e-5, first_torque=np.full(dim, 0.01)),
               dict(window=wh.VELOCITY_WINDOW, latency_s=1e-5, first_torque=np.zeros(dim))]
    corrected = 0
    for trial in range(30):
        rec = _record(rng, scene, dim, int(rng.integers(5, 160)))
        delta = rng.uniform(0.0, 1e-6, dim)
        for opts in options:
            got = wh.hold_corrections(rec, scene, J, delta, **opts)
            ref = _loop(rec, scene, J, delta, **opts)
            assert got.keys() == ref.keys(), (trial, opts)
            for key in ref:
                assert np.array_equal(np.asarray(got[key]), np.asarray(ref[key]),
                                      equal_nan=True), (trial, opts, key)
            corrected += int(ref["corrected"].sum())
    assert corrected > 10000                 # the rows were corrected, not skipped
