"""A board that reads its sensor as late as the host's write comes (the Hapkit sketch for
most write phases: ``Hapkit_arduino.ino:96-135``): the writes' jitter is its readings'
noise, ``v_k delta_k`` (:func:`hapsim.analysis.measurement.aperture_noise`), in the
stated uncertainty of its runs.
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np
import pytest

from hapsim.analysis.measurement import aperture_noise
from hapsim.host.telemetry import FLAG_ESTIMATED


def _record(n, T, delta, omega=20.0, amp=0.01):
    k = np.arange(n)
    t = k * T + delta
    return {"time": 0.3 + t, "seq": 1000 + k, "flags": np.zeros(n, np.uint8),
            "position": amp * np.sin(omega * t)}


def test_the_noise_is_the_slope_times_the_write_s_departure():
    """Against an independent computation: the departures detrended with numpy's polyfit,
    the slope the sine's own derivative at the sample. The central difference's error on
    a sine is ``1 - sin(omega T) / (omega T)``, (omega T)^2 / 6 = 1.1e-3 relative at
    omega T = 0.08 (derived): the tolerance 2e-3. Estimated rows are left out; exact
    times give 0 (a record without jitter is measured as before)."""
    rng = np.random.default_rng(5)
    T, n, omega = 0.004, 400, 20.0
    delta = rng.uniform(0.0, 80e-6, n)
    cols = _record(n, T, delta, omega)
    seq, t = cols["seq"].astype(float), cols["time"]
    d = t - np.polyval(np.polyfit(seq, t, 1), seq)
    v = 0.01 * omega * np.cos(omega * (np.arange(n) * T + delta))
    # the central difference at the ends is one-sided (np.gradient): the ends left out
    # of both sums would differ by 2 of 400 terms; the sine's ends are kept in both
    want = np.sqrt(np.mean((v * d) ** 2))
    # derived bound: the central difference's error on a sine, (omega T)^2 / 6 = 1.1e-3
    assert aperture_noise(cols, T) == pytest.approx(want, rel=2e-3)
    # estimated rows are no readings
    est = dict(cols, flags=np.zeros(n, np.uint8))
    est["flags"][::3] = FLAG_ESTIMATED
    keep = est["flags"] == 0
    d2 = t[keep] - np.polyval(np.polyfit(seq[keep], t[keep], 1), seq[keep])
    want2 = np.sqrt(np.mean((v[keep] * d2) ** 2))
    # derived bound: the same central difference's error (every row's slope from its
    # neighbours, read or not: the positions here are exact)
    assert aperture_noise(est, T, FLAG_ESTIMATED) == pytest.approx(want2, rel=2e-3)
    assert aperture_noise(_record(n, T, np.zeros(n)), T) == 0.0
    assert aperture_noise({k: a for k, a in cols.items() if k != "time"}, T) == 0.0


@pytest.mark.parametrize("seed", range(4))
def test_jittered_writes_on_the_sketch_s_board_keep_the_truth_inside(seed, tmp_path):
    """Random paddles on the sketch's board on a simulated clock (its loop read line by
    line: the handle read at each command's end), every write 0-0.3 of a tick late, known
    to the host (its write times in the record): the noise the run states is the
    jitter's (> 0, and 0 with the writes on time), "within", and the scene's own felt pair
    inside the stated interval (the board that applies the float at its read: the scene's
    loop is the truth)."""
    import sys
    sys.path.insert(0, str(pathlib.Path(__file__).parent))
    from test_unseen_holds import _measure, _random_case

    from hapsim.analysis.prediction import predict
    from hapsim.emulated.hapkit_serial_board import HapkitSerialDevice, hapkit_serial_offline_loop
    prep, n, _ = _random_case(seed, tmp_path)
    prep = dataclasses.replace(prep, model_scene=None, pred=predict(prep.scene))
    jit = np.random.default_rng(100 + seed).uniform(0.0, 0.3, n)
    ideal = {"levels": 0, "render_s": 0.0}
    cols, drv, _ = hapkit_serial_offline_loop(
        prep.scene, n, read_late={k: float(jit[k]) for k in range(n)}, **ideal)
    assert aperture_noise(cols, prep.scene.period) == 0.0     # the host's grid times
    cols["time"] = cols["time"] + jit * HapkitSerialDevice.TICK_S
    assert aperture_noise(cols, prep.scene.period) > 0.0
    m = _measure(prep, cols, drv)
    p = prep.pred
    assert m.get("within") is True, (m.get("verdict"), m.get("error"))
    assert abs(m["k"] - p["k"]) <= m["k_interval"] and abs(m["b"] - p["b"]) <= m["b_interval"]
