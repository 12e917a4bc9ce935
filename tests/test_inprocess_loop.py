"""The one in-process loop stepper (:class:`hapsim.device_model.InProcessLoop`), held
against the analysis: closed on the plain virtual element, the device positions it produces
obey the closed loop's characteristic recurrence (the poles of
:func:`hapsim.analysis.closed_loop_poles`, Florens, Voda & Urma eq. (4)) to round-off, for
random devices, rates, delays, holds and (K, B)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hapsim.analysis import LoopModel, closed_loop_poles, stability_limit
from hapsim.device_model import InProcessLoop, MockPhysics
from hapsim.scene import Device, Excitation


def _trajectory(dev: Device, rate: float, K: float, B: float, n: int) -> np.ndarray:
    T = 1.0 / rate
    phys = MockPhysics(dev, rate, Excitation(x0=0.004))
    prev = [phys.sample()]                       # the port at rest: x[-1] = x[0]

    def law(x: float) -> float:                  # F[n] = -K x[n] - B (x[n] - x[n-1]) / T
        f = -K * x - B * (x - prev[0]) / T
        prev[0] = x
        return f

    loop = InProcessLoop(phys, law, dev.delay, dev.force_limit)
    return np.array([loop.step()[0] for _ in range(n)])


@pytest.mark.parametrize("seed", range(12))
def test_positions_obey_the_predicted_characteristic_recurrence(seed):
    rng = np.random.default_rng(seed)
    hold = ("zoh", "ideal")[seed % 2]
    dev = Device(mass=float(rng.uniform(0.05, 1.0)), friction=float(rng.uniform(0.0, 2.0)),
                 delay=int(rng.integers(1, 5)), hold=hold, force_limit=math.inf)
    rate = float(rng.choice([500.0, 1000.0, 4000.0]))
    loop = LoopModel.from_device(dev, rate)
    B = float(rng.uniform(0.0, 1.0))
    K = float(rng.uniform(0.1, 0.8)) * stability_limit(loop, B)
    x = _trajectory(dev, rate, K, B, 400)
    c = np.real(np.poly(closed_loop_poles(loop, K, B)))          # monic, degree p
    p = c.size - 1
    windows = np.lib.stride_tricks.sliding_window_view(x, p + 1)[:, ::-1]   # x[n], x[n-1]...
    resid = windows @ c
    scale = np.abs(windows) @ np.abs(c)
    assert np.all(np.abs(resid) <= 1e-9 * scale + 1e-18), (hold, dev, rate, K, B)
    assert np.ptp(x) > 1e-4                                      # the loop moved


def test_a_wrong_delay_breaks_the_recurrence():
    """The check can fail: one sample more delay in the stepper than in the prediction."""
    dev = Device(mass=0.1, friction=0.5, delay=1, hold="zoh", force_limit=math.inf)
    loop = LoopModel.from_device(dev, 1000.0)
    K, B = 0.5 * stability_limit(loop, 0.2), 0.2
    x = _trajectory(Device(mass=0.1, friction=0.5, delay=2, hold="zoh",
                           force_limit=math.inf), 1000.0, K, B, 400)
    c = np.real(np.poly(closed_loop_poles(loop, K, B)))
    w = np.lib.stride_tricks.sliding_window_view(x, c.size)[:, ::-1]
    assert np.max(np.abs(w @ c)) > 1e-6 * np.max(np.abs(w) @ np.abs(c))


def test_the_applied_force_is_clamped_and_delayed():
    """d zeros first, then the force computed d samples earlier, clamped to force_limit."""
    applied = []

    class Probe:
        def sample(self):
            return 0.0

        def advance(self, u):
            applied.append(u)

    forces = iter([5.0, -0.5, 20.0, -30.0, 1.0])
    loop = InProcessLoop(Probe(), lambda x: next(forces), 2, 10.0)
    got = [loop.step()[1] for _ in range(5)]
    assert got == [5.0, -0.5, 20.0, -30.0, 1.0]
    assert applied == [0.0, 0.0, 5.0, -0.5, 10.0]
