"""The run's stated uncertainty covers a quantised sensor and a quantised actuator.

An exact simulation of the sampled loop, written here independently of hapsim's loop (the
device ``m x'' + b0 x' = f`` under a zero-order hold, its exact transition over a period;
the host reads the position rounded to the sensor step q and commands
``-K x[n-d] - B (x[n-d] - x[n-d-1]) / T``, which the device rounds to its actuator step s
and applies d ticks later), is measured as ``hapsim run`` measures a run over a framed
device (:func:`hapsim.analysis.measurement.late_accounted` takes the actuator's rounding
out as a known input, HELLO's ``force_scale``; :func:`hapsim.analysis.measurement.identify`
with the sensor step). Over seeded random loops (mass, friction, virtual (K, B), delay 0-3,
rate 1-4 kHz, 1200 samples, q up to 30 um, s from K x0 / 300 to K x0 / 30 or none) the THS
prediction is inside the stated interval in every case, and a virtual stiffness wrong by
four times that interval is detected.

With the rounding left in and only the sensor in the interval (before commit 50b6e8a), 5 of
10 force-quantised loops here fell outside (up to 1.5 times the interval), as the emulated
Hapkit's 8-bit PWM at 4 kHz did (k = 503.55 +- 0.18 N/m against 503.29). Over 200 seeded
loops (seeds 0-19, 10 loops each, this generator; not in the suite) the worst error was
0.81 of the interval.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from hapsim.analysis.error_response import sensor_error_response
from hapsim.analysis.loop import LoopModel
from hapsim.analysis.measurement import identify, late_accounted
from hapsim.analysis.prediction import predict, predicted_poles
from hapsim.analysis.ths import render
from hapsim.analysis.stability import stability_limit
from hapsim.scene import parse_scene
from test_daemon import wall_text  # same directory (pytest prepend import mode)

CASES = 20


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """One BLAS thread, as every hapsim command runs (hapsim.blas): a threaded OpenBLAS
    spins on a loaded machine (the pencil's SVDs took 25 s here beside 8 processes, 0.8 s
    with one thread)."""
    with threadpool_limits(1, user_api="blas"):
        yield
SAMPLES = 1200      # the record: 0.3-1.2 s (the pencil's SVD costs O(n^3))


def _simulate(m, b0, K, B, d, rate, q, s, x0, n):
    """Logged (quantised) positions [m] and commanded (unrounded) forces [N] of the exact
    sampled loop, each shape (n,)."""
    T = 1.0 / rate
    a = b0 / m
    # x'' = -a x' + f / m under a hold: the exact transition over one period
    ea = math.exp(-a * T)
    phi12 = T if a == 0 else -math.expm1(-a * T) / a
    g1 = T * T / (2 * m) if a == 0 else (T - phi12) / (a * m)
    g2 = phi12 / m
    x, v = x0, 0.0
    y, cmd = np.empty(n), np.empty(n)
    f = [0.0] * (n + d + 1)
    prev = round(x0 / q) * q if q else x0
    for i in range(n):
        yi = round(x / q) * q if q else x
        y[i] = yi
        fi = cmd[i] = -K * yi - B * (yi - prev) / T
        f[i + d] = round(fi / s) * s if s else fi
        prev = yi
        x, v = x + phi12 * v + g1 * f[i], ea * v + g2 * f[i]
    return y, cmd


def _loop(rng):
    """A stable, lightly damped loop ringing at least 5 cycles in the record."""
    while True:
        m = float(rng.uniform(0.05, 0.5))
        b0 = float(rng.uniform(0.0, 1.0))
        d = int(rng.integers(0, 4))
        rate = float(rng.choice([1000.0, 2000.0, 4000.0]))
        B = float(rng.uniform(0.0, 2.0))
        loop = LoopModel(mass=m, friction=b0, rate_hz=rate, delay=d, hold="zoh")
        K = float(rng.uniform(0.05, 0.6) * min(stability_limit(loop, B), 5000.0))
        r = render(loop, K, B)
        if r.stable and r.rendered is not None and r.spectral_radius < 0.9995 \
                and r.f0_hz * SAMPLES / rate >= 5 and r.damping_ratio < 0.2:
            return m, b0, K, B, d, rate


def _measure(m, b0, K, B, d, rate, q, s, x0, *, K_true=None, n=SAMPLES):
    """The run's measurement of the simulated record (as hapsim.pipeline.runner's): the
    actuator's rounding taken out as a known input (late_accounted, from HELLO's step and
    STATE's force_seq), then identify with the sensor step."""
    import firmware_protocol as fp
    scene = parse_scene(wall_text(K, B, m=m, b0=b0, d=d, rate=rate, x0=x0, force_limit=1e4))
    y, cmd = _simulate(m, b0, K if K_true is None else K_true, B, d, rate, q, s, x0, n)
    seq = np.arange(n)
    applied = seq >= d            # STATE n reports the FORCE of STATE n - d applied
    cols = {"seq": seq, "position": y, "force": cmd, "late": np.zeros(n, np.uint8),
            "force_seq": np.where(applied, seq - d, 0),
            "status": np.where(applied, fp.STATUS_ARMED | fp.STATUS_FORCE_APPLIED,
                               fp.STATUS_ARMED)}
    hello = SimpleNamespace(force_scale=s, position_scale=q, force_limit=math.inf)
    position, late, _ = late_accounted(scene, cols, hello, None)
    poles, felt = predicted_poles(scene)
    meas = identify(position, seq, 1.0 / rate, len(poles), m, d + 3, late=late, skip=d + 2,
                    predicted=poles, felt=felt, quantum=q,
                    sensor_response=sensor_error_response(scene, n))
    return meas, predict(scene)


def test_simulation_is_the_predicted_loop_when_nothing_is_quantised():
    """The independent simulation and hapsim's prediction are one loop (to round-off)."""
    meas, pred = _measure(0.1, 0.5, 500.0, 1.0, 1, 1000.0, 0.0, 0.0, 0.005)
    # measured 5.7e-15 relative (generic 7.8e-16), margin 1.7e5
    assert abs(meas["k"] - pred["k"]) <= 1e-9 * pred["k"], (meas["k"], pred["k"])
    # measured 1.1e-13 relative (generic 2e-13), margin 50000
    assert abs(meas["b"] - pred["b"]) <= 1e-8 * pred["b"], (meas["b"], pred["b"])


def test_interval_covers_sensor_and_actuator_steps_and_detects_a_wrong_stiffness():
    rng = np.random.default_rng(20261122)
    worst = 0.0
    for i in range(CASES):
        m, b0, K, B, d, rate = _loop(rng)
        x0 = float(rng.uniform(2e-3, 8e-3))
        q = float(rng.uniform(1e-6, 30e-6))
        s = K * x0 / float(rng.uniform(30, 300)) if i % 3 else 0.0
        meas, pred = _measure(m, b0, K, B, d, rate, q, s, x0)
        assert "k" in meas, (i, meas.get("error"))
        ek, eb = abs(meas["k"] - pred["k"]), abs(meas["b"] - pred["b"])
        case = dict(i=i, m=m, b0=b0, K=K, B=B, d=d, rate=rate, q=q, s=s, x0=x0,
                    k=meas["k"], k_pred=pred["k"], k_unc=meas["k_unc"], b=meas["b"],
                    b_pred=pred["b"], b_unc=meas["b_unc"])
        assert ek <= meas["k_unc"] and eb <= meas["b_unc"], case
        worst = max(worst, ek / meas["k_unc"], eb / meas["b_unc"])
        # the interval is no blanket: a virtual stiffness 4 intervals off is detected (the
        # felt k follows K one for one up to the loop's O(KT^2/m) terms)
        wrong, _ = _measure(m, b0, K, B, d, rate, q, s, x0, K_true=K + 4 * meas["k_unc"])
        assert abs(wrong["k"] - pred["k"]) > wrong["k_unc"], (case, wrong["k"])
    print(f"worst error / stated interval over {CASES} loops: {worst:.2f}")
