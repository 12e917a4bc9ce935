"""The matrix pencil cuts its order to the data's numerical rank (issue 10 audit).

A long lockstep record of a slow pair (ideal hold, d = 95, f0 = 0.024 Hz at 772 Hz) whose
d + 1 fast companions died out in the first samples has rank 2; identified at the loop's
order 97, the 95 noise vectors gave a spurious pole outside the unit circle and
``run --lockstep`` printed k = 611 N/m, b = -6.35 N s/m for a predicted 0.0183 / 0.00225.
Property over seeded random records: one slow pair + many fast modes, long record, the
full order asked: the slow pair comes back to the precision of the data.
"""

from __future__ import annotations

import numpy as np

from hapsim.analysis.pencil import pencil_poles


def test_slow_pair_among_dead_fast_modes_is_found_at_the_full_order():
    rng = np.random.default_rng(10)
    for _ in range(5):
        theta = 10 ** rng.uniform(-4, -2)                 # slow: 100..10,000 samples a turn
        slow = (1 - theta * 10 ** rng.uniform(-3, -1)) * np.exp(1j * theta)
        n_fast = int(rng.integers(10, 30))
        fast = rng.uniform(0.3, 0.92, n_fast) * np.exp(1j * rng.uniform(0.05, 3.1, n_fast))
        n = int(rng.integers(3000, 12000))
        k = np.arange(n)
        y = 2 * (1e-3 * slow ** k).real
        for z in fast:
            y += 2 * (rng.uniform(1e-5, 1e-3) * z ** k).real
        L = 10 * (2 + 2 * n_fast)
        z = pencil_poles(y, 2 + 2 * n_fast, pencil=L)
        assert np.all(np.abs(z) <= 1 + 1e-9), np.abs(z).max()   # no spurious growing pole
        best = z[np.argmax(np.abs(z))]
        assert abs(best - slow) < 1e-6 * abs(1 - slow), (best, slow)
