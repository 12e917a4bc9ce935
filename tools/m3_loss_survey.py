"""The Haply M3 on a lossy link, on the simulated clock: why it is re-synchronised, and
what its verdict is however often (issue 29; docs/drivers.md, "Re-synchronisation and
the verdict").

Usage::

    python tools/m3_loss_survey.py resyncs [--loss 0.005] [--seeds 40]
                                           [--nudge none|low|all]
    python tools/m3_loss_survey.py verdicts [--loss 0.005] [--seeds 0 80] [--heavier 1.0]

``resyncs``: ``tests/test_haply_silence.py``'s run (the host's transport on a simulated
clock, the emulated board on its own, seeded byte loss each way ``4000 + seed``, 1,500
ticks, the host loop's loss rule on), the re-synchronisations per run and their reasons.
``--nudge`` sends, instead of each torque, the nearest binary32 none of whose bytes is 0
or 1 (``all``), or whose two low bytes are none (``low``), zero torque as the float of
bytes ``03 03 03 03`` (3.9e-37 N m) in both: an experiment on the cause (a lost host byte
makes the firmware read the torque's bytes as commands, 0 a reset and 1 a set-up), not
hapsim's encoding (the third byte's nudge moves a torque by up to 0.8 %). Measured: 1.12
a run (35 of 45 ``lone``), ``all`` 0.15, ``low`` 0.62.

``verdicts``: ``tests/test_haply_lossy_verdict.py``'s run (``configs/haply.yaml``'s
engine closing the loop, measured as ``hapsim run`` measures it, the link's loss seeded
``5000 + seed``), the board's joint ``--heavier`` times the scene's inertia; one line a
run: re-synchronisations and reasons, ``frame_bound`` [rad], the verdict. Measured at 1 in
200: the matching joint 80 of 80 within (seeds 0-79), 30 % heavier 0 of 60 (48
"differs"). Deterministic: the same seed gives the same run on any host.
"""

from __future__ import annotations

import argparse
import collections
import math
import struct
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

_F = struct.Struct("<f")


def command_free(torque: float, low_only: bool = False) -> float:
    """The binary32 nearest ``torque`` none of whose bytes is 0 or 1 (``low_only``: none of
    its two low bytes), the same sign; zero torque as the float of bytes 3 (module notes).
    An experiment, not hapsim's encoding.

    Parameters
    ----------
    torque : float
        [N m], already a binary32 value.
    low_only : bool

    Returns
    -------
    float
        [N m]
    """
    if torque == 0.0:
        return _F.unpack(bytes((3, 3, 3, 3)))[0]
    lim = 2 if low_only else 4
    u = struct.unpack("<I", _F.pack(torque))[0]
    for step in range(0, 1 << 18):
        for w in (u + step, u - step):
            b = struct.pack("<I", w & 0xFFFFFFFF)
            if (w >> 31) == (u >> 31) and all(x > 1 for x in b[:lim]):
                return _F.unpack(b)[0]
    return torque


def resyncs(loss: float, seeds: int, nudge: str) -> None:
    """Re-synchronisations per run (module notes), printed per seed and in all."""
    from _pytest.monkeypatch import MonkeyPatch

    import test_haply_silence as hs
    from hapsim.drivers import haply as hp
    write = hp.write_packet
    if nudge != "none":
        def nudged(device_id, torque):
            t = _F.unpack(_F.pack(torque))[0]
            return write(device_id, command_free(t, nudge == "low"))
        hp.write_packet = nudged
    total, reasons = 0, collections.Counter()
    for seed in range(seeds):
        mp = MonkeyPatch()
        try:
            tr, _, board, _, _ = hs._run(mp, seed, [], n_ticks=1500, recover=True,
                                         faults={"drop_rx": loss, "drop_tx": loss,
                                                 "seed": 4000 + seed})
        finally:
            mp.undo()
        r = {k: v for k, v in tr.stats["resync_reasons"].items() if v}
        total += tr.stats["resyncs"]
        reasons.update(r)
        print(seed, tr.stats["resyncs"], r, f"frame walk {board.frame_walk:.3f} rad")
    hp.write_packet = write
    print(f"nudge {nudge}, loss {loss:g}: {total / seeds:.2f} a run", dict(reasons))


def verdicts(loss: float, first: int, last: int, heavier: float) -> None:
    """The measurement of each run (module notes), one line a run."""
    from _pytest.monkeypatch import MonkeyPatch

    import test_haply_lossy_verdict as lv
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.scene import load_scene
    prep = prepare_run(load_scene("configs/haply.yaml"),
                       RunOptions(driver="haply", rt_priority=0, handle_signals=False,
                                  duration=lv.N_TICKS * 1e-3))
    count = collections.Counter()
    for seed in range(first, last):
        mp = MonkeyPatch()
        try:
            tr, m, _ = lv._lossy_run(mp, prep, seed, loss, heavier=heavier)
        finally:
            mp.undo()
        v = m.get("verdict") or m.get("error")
        count["within" if m.get("within") else str(v).split(":")[0][:30]] += 1
        print(seed, tr.stats["resyncs"],
              {k: n for k, n in tr.stats["resync_reasons"].items() if n},
              f"frame_bound {tr.stats['frame_bound']:.3f}", v,
              f"k {m.get('k', math.nan):.5g} +- {m.get('k_unc') or math.nan:.2g}")
    print(f"loss {loss:g}, heavier {heavier:g}:", dict(count))


def main(argv=None) -> int:
    """The command line (module notes)."""
    p = argparse.ArgumentParser(prog="m3_loss_survey", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    a = sub.add_parser("resyncs")
    a.add_argument("--loss", type=float, default=0.005)
    a.add_argument("--seeds", type=int, default=40)
    a.add_argument("--nudge", choices=("none", "low", "all"), default="none")
    b = sub.add_parser("verdicts")
    b.add_argument("--loss", type=float, default=0.005)
    b.add_argument("--seeds", type=int, nargs=2, default=(0, 80), metavar=("FIRST", "END"))
    b.add_argument("--heavier", type=float, default=1.0)
    a = p.parse_args(argv)
    if a.what == "resyncs":
        resyncs(a.loss, a.seeds, a.nudge)
    else:
        verdicts(a.loss, a.seeds[0], a.seeds[1], a.heavier)
    return 0


if __name__ == "__main__":
    sys.exit(main())
