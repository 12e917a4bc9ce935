"""The FireFader's two faders in real time, run after run: ``hapsim run
configs/two_faders.yaml`` (the embedded emulated board on its own wall clock) once per
seed (the board's seed), beside ``--hogs`` CPU-bound processes, each run's verdict,
statements, stop and timing written as JSON (docs/ports.md, 'In real time').

Usage::

    python tools/faders_realtime.py --seeds 0 1 2 3 4 --hogs 1 --json /tmp/faders.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import time
from pathlib import Path


def _burn(until: float) -> None:
    while time.monotonic() < until:
        pass


def main(argv=None) -> int:
    """Run the scene once per seed and print (and write) each run's figures.

    Parameters
    ----------
    argv : list of str, optional
        ``--scene``, ``--seeds``, ``--hogs``, ``--json`` (module notes; default the
        process's arguments).

    Returns
    -------
    int
        0 whatever the verdicts (they are the figures).
    """
    import hapsim
    from hapsim.scene import load_scene_ports
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=str(Path(__file__).resolve().parents[1] / "configs"
                                          / "two_faders.yaml"))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--hogs", type=int, default=1)
    p.add_argument("--json")
    a = p.parse_args(argv)
    ctx = mp.get_context("spawn")
    hogs = [ctx.Process(target=_burn, args=(time.monotonic() + 3600.0,), daemon=True)
            for _ in range(a.hogs)]
    for h in hogs:
        h.start()
    runs = []
    try:
        scene = load_scene_ports(a.scene)
        for seed in a.seeds:
            load = os.getloadavg()[0]
            t = time.monotonic()
            d = hapsim.run(scene, seed=seed).to_dict()
            row = {"seed": seed, "load_before": load, "wall_s": time.monotonic() - t,
                   "verdict": d["verdict"], "reason": d["reason"],
                   "statements": [(s["name"], s["verdict"]) for s in d["statements"]],
                   "deviation": d["deviation"], "uncertainty": d.get("uncertainty"),
                   "realtime": d["realtime"]}
            runs.append(row)
            print(json.dumps(row))
    finally:
        for h in hogs:
            h.terminate()
    if a.json:
        Path(a.json).write_text(json.dumps({"scene": a.scene, "hogs": a.hogs,
                                            "cpus": os.cpu_count(), "runs": runs},
                                           indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
