"""The Hapkit-serial sketch names the force it applied in every reply: the account takes
it (hapsim.drivers.hapkit_serial.HapkitSerial.account).

With 1 byte in 200 lost each way, the sketch's parser takes a shifted command now and
then (the next command's header as the last byte of the force float: ~1e-28 N, or a
corrupted float byte) and applies a force the host never sent. Taken as the force sent
(or the one before, the timing account), that was an unknown disturbance: k 2.4 % and b
25 % off, "differs" in 10 of 10 runs beside two CPU-bound processes
(tools/driver_timing.py); the replies name it, a known input the measurement takes out.
"""

from __future__ import annotations

import numpy as np
import pytest

from hapsim.drivers.base import FLAG_ESTIMATED
from hapsim.drivers.hapkit_serial import HapkitSerial, reply_packet


def test_rows_are_matched_to_replies_by_position():
    """Closed form: an arming reply no row took is passed over, an estimated row keeps
    the timing account, every other row takes its reply's force (late where it is not
    the force the timing account names)."""
    drv = HapkitSerial()
    drv.loop_delay = 1
    dec = drv.decoder()
    xs = [0.5e-3, 1.0e-3, 2.0e-3, 3.0e-3, 4.0e-3]      # reply 0: the arming's
    fs = [0.0, 0.1, 0.2, 1e-28, 0.4]                    # reply 3: a shifted command
    got = []
    for x, f in zip(xs, fs):
        got += dec.feed(reply_packet(drv.function, x, f))
    pos = np.array([np.float32(v) for v in (1.0e-3, 2.0e-3, 2.0e-3, 3.0e-3, 4.0e-3)],
                   float)
    flags = np.array([0, 0, FLAG_ESTIMATED, 0, 0])
    sent = np.array([0.1, 0.2, 0.3, 0.3, 0.4])
    forces = np.array([drv.applied_force(v) for v in sent])
    acc = drv.account({"position": pos, "flags": flags}, forces)
    f32 = [float(np.float32(v)) for v in fs]
    assert acc.method == "replies"
    assert acc.applied[0] == f32[1] and acc.applied[1] == f32[2] and acc.applied[4] == f32[4]
    assert acc.applied[3] == f32[3] and acc.late[3] and acc.half_width[3] == 0.0
    assert acc.half_width[2] > 0.0                  # no reply: sent or the one before


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_a_lossy_link_measures_the_prediction(seed):
    """The run over the sketch's byte-exact mock, stepped one period per command (named
    lockstep: the account, not the timing, is what is tested), 1 byte in 200 lost each
    way: measured = predicted within the stated uncertainty, and the replies named forces
    the timing account did not (before: every seed "differs")."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    rep = run_scene(load_scene("configs/hapkit_serial.yaml"), driver="hapkit-serial",
                    duration=1.5, lockstep=True, handle_signals=False, rt_priority=0,
                    seed=seed, driver_faults={"drop_tx": 0.005, "drop_rx": 0.005,
                                              "seed": seed})
    m = rep["measured"]
    assert rep["loop"]["estimated"] > 0
    assert m["within"] is True, (m["k"], rep["predicted"]["k"], m.get("k_unc"), m["b"],
                                 rep["predicted"]["b"], m.get("b_unc"))
