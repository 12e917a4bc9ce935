"""The Falcon's feasibility (:func:`hapsim.emulated.falcon_felt.felt_feasibility`)
computed once per test process for each scene, plan, decoder step and Falcon count.

Several tests ask it of the same shipped scene: a module's fixture, `hapsim run --driver
falcon`'s prediction before its loop, a real Falcon's statement (configs/delta_sphere.yaml
in tests/test_falcon_felt.py and twice in tests/test_falcon_usb.py; configs/
falcon_spring.yaml four times in tests/test_falcon_spring.py; ~1-1.3 CPU-s each). It is
deterministic (the emulated Falcon in lockstep: the same records, the same box), so each
caller gets a deep copy of exactly what it computed alone. The key is the pickled scene
(its path included), the plan's order and length, the decoder's step and the Falcon's
count as the driver module holds them when called (a test that makes the encoder finer
gets its own); anything else is computed anew.
"""

from __future__ import annotations

import contextlib
import copy
import pickle

import pytest

#: ``key -> felt_feasibility's result``, for the whole process (every module using it).
MEMO: dict = {}


@contextlib.contextmanager
def feasibility_once():
    """While inside, :func:`hapsim.emulated.falcon_felt.felt_feasibility` (as every
    caller imports it at call time: the fixtures, :func:`hapsim.pipeline.falcon_run.
    felt_prediction`) answers from :data:`MEMO` (module notes)."""
    import hapsim.drivers.falcon as falcon
    import hapsim.emulated.falcon_felt as ff
    real = ff.felt_feasibility

    def once(scene, plan=None, *, max_step=8, progress=None):
        key = pickle.dumps((scene, None if plan is None else tuple(plan[1:]), max_step,
                            falcon.DEG_PER_TICK, falcon.THETA_OFFSET_DEG,
                            falcon.START_STEP))
        if key not in MEMO:
            MEMO[key] = real(scene, plan, max_step=max_step)
        return copy.deepcopy(MEMO[key])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ff, "felt_feasibility", once)
        yield
