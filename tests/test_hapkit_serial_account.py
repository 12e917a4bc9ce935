"""The Hapkit-serial sketch names what it rendered in every reply (its ``Tp``, or in its
2017-04-07 copy the force): the account takes it, through the sketch's output stage
(hapsim.drivers.hapkit_serial.HapkitSerial.account).

The closed-form matching tests below take the 2017-04-07 copy's reply (the force) and a
sketch that applies it as it is (``levels=0``, named): the matching of rows to replies is
what they check; the output stage's account is checked apart
(``test_the_account_applies_the_sketch_s_levels``).

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
from tolerance import rel_tol


def test_rows_are_matched_to_replies_by_position():
    """Closed form: an arming reply no row took is passed over, an estimated row keeps
    the timing account, every other row takes its reply's force (late where it is not
    the force the timing account names)."""
    drv = HapkitSerial(levels=0, reply="force")
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
    # no reply: the force sent (row 1's, 0.2 N) or what row 1's reply says the sketch
    # held (0.2 N): the same force, no doubt left
    assert acc.applied[2] == f32[2] and acc.half_width[2] == 0.0


def test_a_row_without_reply_spans_what_the_sketch_held():
    """Closed form: a row whose command may be lost applies the force sent or what the
    sketch held at the row before -- that row's reply's force (a damaged command's
    ~0 N, not the host's), or, itself unknown, its whole interval (two lost in a row)."""
    drv = HapkitSerial(levels=0, reply="force")
    drv.loop_delay = 1
    dec = drv.decoder()
    xs = [1.0e-3, 2.0e-3, 5.0e-3]
    fs = [0.1, 1e-28, 0.5]                              # row 1: a damaged command
    for x, f in zip(xs, fs):
        dec.feed(reply_packet(drv.function, x, f))
    pos = np.array([np.float32(v) for v in (1.0e-3, 2.0e-3, 3.0e-3, 4.0e-3, 5.0e-3)],
                   float)
    flags = np.array([0, 0, FLAG_ESTIMATED, FLAG_ESTIMATED, 0])
    sent = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    forces = np.array([drv.applied_force(v) for v in sent])
    acc = drv.account({"position": pos, "flags": flags}, forces)
    f32 = [float(np.float32(v)) for v in (0.1, 0.2, 0.3, 1e-28)]
    lo = acc.applied - acc.half_width
    hi = acc.applied + acc.half_width
    # row 2: the force sent (row 1's, 0.2 N) or the ~0 N row 1's reply says was held
    assert lo[2] <= f32[3] and hi[2] >= f32[1] and lo[2] <= f32[1] and hi[2] >= f32[3]
    # row 3: row 2's force (0.3 N), or whatever row 2 held: its whole interval
    assert lo[3] <= min(lo[2], f32[2]) and hi[3] >= max(hi[2], f32[2])
    assert acc.half_width[4] == 0.0 and acc.applied[4] == float(np.float32(0.5))


def _sketch_level_force(f: float) -> float:
    """The force the sketch's motor makes for a rendered force [N], from its text
    (haphub/WHC2017 ef6028f, Hapkit_Kinematics_Simulation.h: ``Tp = rp/rs * rh * force``,
    ``duty = sqrt(abs(Tp)/0.0183)``, ``(int)(duty * 255)``), written here in binary32
    apart from the module; its motor model inverted: ``0.0183 (n/255)^2 / (rp/rs rh)``."""
    f32 = np.float32
    tp = f32(f32(f32(0.004191) / f32(0.073152)) * f32(0.075)) * f32(f)
    duty = min(np.sqrt(f32(abs(tp)) / f32(0.0183)), f32(1.0))
    n = int(np.floor(f32(duty * f32(255))))
    return float(np.sign(f) if f > 0 else -1.0) * 0.0183 * (n / 255) ** 2 / (
        0.004191 / 0.073152 * 0.075)


def test_the_account_applies_the_sketch_s_levels():
    """Closed form, the repository's head (the reply's float is ``Tp``, found from the
    replies), 256 levels: every row with its reply in step applies the level of the
    force sent; a damaged command (~1e-28 N rendered) applies level 0, a late tick taken
    out; the account says which float the replies carry."""
    from hapsim.drivers.output_stage import sketch_tp
    drv = HapkitSerial()
    drv.loop_delay = 1
    dec = drv.decoder()
    sent = np.array([0.1, -0.37, 1.2, 0.8, 0.05])
    forces = np.array([drv.applied_force(v) for v in sent])
    rendered = [0.0, forces[0], forces[1], 1e-28, forces[3]]   # row 3: a damaged command
    xs = [1.0e-3, 2.0e-3, 3.0e-3, 4.0e-3, 5.0e-3]
    for x, f in zip(xs, rendered):
        dec.feed(reply_packet(drv.function, x, float(sketch_tp([f])[0])))
    pos = np.array([np.float32(v) for v in xs], float)
    acc = drv.account({"position": pos, "flags": np.zeros(5, int)}, forces)
    assert drv.reply_found == "Tp"
    for r in (1, 2, 4):
        if acc.half_width[r] == 0.0:
            # the same level, its force computed in another order of binary64 operations:
            # each side 5 roundings deep (a quotient, two products, a square; the gearing's
            # two), a product of them: rel_tol(10)
            assert acc.applied[r] == pytest.approx(_sketch_level_force(rendered[r]),
                                                   rel=rel_tol(10), abs=0.0), r
    assert acc.applied[3] == 0.0 and acc.late[3] and not acc.late[1]
    # the level is below the force, by less than 2 / n of it (n >= 1: the next level's)
    for r in (1, 2, 4):
        assert abs(acc.applied[r]) <= abs(rendered[r]) + acc.half_width[r]


#: Lockstep runs with byte loss: seeds and patterns. Seed 19 both ways made a false
#: reading before the reply decoder's check (tests/test_hapkit_serial_framing.py): k
#: 6.9 % off, stated 5.2 %, "differs" for a matching device.
#: Host bytes lost at 1 in 100 (seed 5) cut the record at every damaged command (a gap in
#: seq): its stretches may be too short to measure, "not measurable" with the reason.
LOSSY = [(1, 0.005, 0.005), (4, 0.005, 0.005), (19, 0.005, 0.005), (5, 0.01, 0.0),
         (6, 0.0, 0.01)]


def _lossy_run(seed, drop_rx, drop_tx, extra_friction=0.0, monkeypatch=None):
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    if extra_friction:
        import dataclasses

        import hapsim.emulated.driver_mock as dm
        init = dm.EmbeddedDriverMock.__init__

        def hidden(self, driver, device, *a, **k):
            # the device the mock is: the scene's with a damping the host does not know
            init(self, driver, dataclasses.replace(
                device, friction=device.friction + extra_friction), *a, **k)
        monkeypatch.setattr(dm.EmbeddedDriverMock, "__init__", hidden)
    return run_scene(load_scene("configs/hapkit_serial.yaml"), driver="hapkit-serial",
                     duration=1.5, lockstep=True, handle_signals=False, rt_priority=0,
                     seed=seed, driver_faults={"drop_tx": drop_tx, "drop_rx": drop_rx,
                                               "seed": seed})


@pytest.mark.parametrize("seed,drop_rx,drop_tx", LOSSY,
                         ids=[f"seed{s}-rx{r:g}-tx{t:g}" for s, r, t in LOSSY])
def test_a_lossy_link_never_says_differs_for_a_matching_device(seed, drop_rx, drop_tx):
    """The run over the sketch's byte-exact mock, stepped one period per command (named
    lockstep: deterministic, the same bytes lost on any host), bytes lost host -> device,
    device -> host or both: the device is the scene's, so the verdict is "within"
    (measured = predicted within the stated uncertainty) or not measurable with its
    reason, never "differs"; at 1 byte in 200 each way it is measured."""
    rep = _lossy_run(seed, drop_rx, drop_tx)
    m = rep["measured"]
    assert rep["loop"]["estimated"] > 0 or rep["loop"]["missed"] > 0
    assert m.get("within") is not False, (m.get("verdict"), m.get("k"),
                                          rep["predicted"]["k"], m.get("k_unc"), m.get("b"),
                                          rep["predicted"]["b"], m.get("b_unc"))
    if "k" not in m:
        assert m.get("error") or str(m.get("verdict")).startswith("not measurable")
    if drop_rx == drop_tx == 0.005 and seed != 4:
        # seed 4's longest stretches hold 1.49-1.53 cycles above 5 x the fit's residual
        # (the estimated rows' extrapolations), on identify's threshold of 1.5: measured
        # (k +-53 N/m) with the float applied, "not measurable" with that reason with the
        # sketch's levels (the same stretches and residual, the path a little other)
        assert m["within"] is True


@pytest.mark.parametrize("seed", [1, 19])
def test_a_lossy_link_still_sees_a_device_that_differs(seed, monkeypatch):
    """The same lossy runs against a device with a hidden viscous friction of 0.3 N s/m
    more than the scene states (the felt b, predicted 0.2 N s/m, becomes about 0.5): the
    verdict is "differs" -- the stated uncertainty under loss is not so wide that nothing
    can be seen through it."""
    rep = _lossy_run(seed, 0.005, 0.005, extra_friction=0.3, monkeypatch=monkeypatch)
    m = rep["measured"]
    assert m["within"] is False and m["verdict"].startswith("measured differs"), (
        m.get("verdict"), m.get("b"), m.get("b_unc"))
    assert m["b"] - rep["predicted"]["b"] > m["b_unc"]


def test_a_host_late_row_stays_a_cut_when_the_account_takes_ticks_out():
    """A reply that names a force the host did not send is a late tick the account takes
    out; a row the host loop marked late (its tick went out a period late: the force before
    it held longer, which no reply says) is still a cut of the record (before, the
    account's path returned no late flags and such rows were measured as on time)."""
    from hapsim.analysis.measurement import late_accounted
    from hapsim.scene import load_scene
    sc = load_scene("configs/hapkit_serial.yaml")
    drv = HapkitSerial()
    drv.loop_delay = int(sc.device.delay)
    dec = drv.decoder()
    n = 200
    x = np.float32(0.01 * np.exp(-np.arange(n) / 80.0) * np.cos(np.arange(n) / 7.0))
    sent = np.array([drv.applied_force(-50.0 * float(v)) for v in x])
    replied = sent.copy()
    replied[1:] = sent[:-1]                       # row r applies the force of row r - 1
    replied[0] = 0.0
    replied[120] = 1e-28                          # a damaged command: ~0 N applied
    for v, f in zip(x, replied):
        dec.feed(reply_packet(drv.function, float(v), float(f)))
    cols = {"position": x.astype(float), "force": sent, "seq": np.arange(n),
            "flags": np.zeros(n, np.uint8), "late": np.zeros(n, np.uint8),
            "force_seq": np.arange(n) - 1, "status": np.zeros(n, np.uint16)}
    cols["late"][60] = 1                          # the host's tick went out late
    pos, late, info = late_accounted(sc, cols, None, drv)
    assert info.get("late_accounted", 0) >= 1     # the damaged command taken out
    assert late is not None and late[60] and np.count_nonzero(late) == 1


@pytest.mark.parametrize("driver", ["hapkit_serial", "haply", "firefader"])
def test_the_array_quantisation_is_the_commands_force_bit_for_bit(driver):
    """A driver's applied_forces (the timing account's forces, at numpy's speed where it
    has its own: the binary32 wire of the HapkitSerial sketch and of the Haply M3) against
    its applied_force, which packs each command (struct): random forces over 40 decades
    either side of the limit, exactly at it, -0.0, subnormals, binary32 ties and NaN/inf,
    byte for byte. The FireFader keeps the base class's call per force (its counts)."""
    from hapsim.drivers.firefader import FireFader
    from hapsim.drivers.haply import MAX_TORQUE, HaplyM3
    drv, lim = {"hapkit_serial": (HapkitSerial(), None), "haply": (HaplyM3(), MAX_TORQUE),
                "firefader": (FireFader(), 1.0)}[driver]
    lim = float(drv.force_limit) if lim is None else lim
    rng = np.random.default_rng(13)
    f = np.concatenate([
        rng.standard_normal(4000) * 10.0 ** rng.integers(-40, 3, 4000),
        [lim, -lim, np.nextafter(lim, 10), -np.nextafter(lim, 10), 0.0, -0.0, 5e-324,
         -1e-310, np.inf, -np.inf, np.nan, 1.0 + 2.0 ** -24, 1.0 + 3 * 2.0 ** -24]])
    want = np.array([drv.applied_force(float(v)) for v in f])
    got = drv.applied_forces(f)
    assert got.dtype == np.float64 and got.tobytes() == want.tobytes()
