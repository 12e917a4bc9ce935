"""How many CPU-bound processes a test starts to run "beside N busy processes".

Under pytest-xdist the other workers are busy processes too: the suite keeps each of them
running tests (real-time loops, compilers, browsers) while this one runs. A test that
started N burners of its own ran beside N + (workers - 1): on the 2-core CI machine, a
wall-clock board's emulation then went unscheduled for 20 ms now and then and the host
took its silence for a board out of step (a re-synchronisation where the test asserts
none; test_haply_wallclock, CI once in five full runs this stop).
"""

from __future__ import annotations

import os


def burners_for(n: int) -> int:
    """CPU-bound processes to start so that a test runs beside ``n`` busy ones.

    Parameters
    ----------
    n : int
        Busy processes the test states it runs beside.

    Returns
    -------
    int
        ``n`` less the other pytest-xdist workers (``PYTEST_XDIST_WORKER_COUNT - 1``),
        at least 0.
    """
    others = max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1) - 1, 0)
    return max(int(n) - others, 0)
