"""What one chunk of ``hapsim play`` on a 2-D/3-D scene costs: the compiled call of
:meth:`hapsim.audio.live.LiveND.produce` (the loop closed on the device, the ramps,
the listening points, the ring), timed chunk by chunk without a sound server, beside the
chunk's duration at the scene's rate (the real-time budget). Prints one JSON object.

    python tools/bench_play_nd.py [SCENE ...] [--chunks N] [--chunk FRAMES]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

DEFAULT = (os.path.join(ROOT, "configs", "membrane.yaml"),
           os.path.join(ROOT, "tests", "data", "play_nd_2d.yaml"))


def bench(path: str, chunks: int, chunk: int) -> dict:
    """Time ``chunks`` chunks of ``chunk`` frames of the scene at ``path`` [us]."""
    from hapsim.audio.live import LiveND
    from hapsim.engine import Engine
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(path)
    live = LiveND(Engine(sc), chunk=chunk, ring=max(16384, 8 * chunk))
    live.produce(0)                                   # compiled (or loaded) first
    t = np.empty(chunks)
    for i in range(chunks):
        t0 = time.perf_counter()
        live.produce()
        t[i] = time.perf_counter() - t0
        live.ring.render(chunk)                       # the reader keeps up
    budget = chunk / sc.rate_hz
    return {"scene": os.path.relpath(path, ROOT), "dof": sc.dimension,
            "masses": len(sc.masses), "links": len(sc.links), "rate_hz": sc.rate_hz,
            "closed_loop": live.closed, "chunk_frames": chunk,
            "chunk_budget_us": budget * 1e6,
            "chunk_us_p50": float(np.percentile(t, 50) * 1e6),
            "chunk_us_p99": float(np.percentile(t, 99) * 1e6),
            "fraction_of_real_time_p50": float(np.percentile(t, 50) / budget),
            "load_average_1min": os.getloadavg()[0]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenes", nargs="*", default=list(DEFAULT))
    p.add_argument("--chunks", type=int, default=400)
    p.add_argument("--chunk", type=int, default=256)
    a = p.parse_args(argv)
    print(json.dumps({"results": [bench(s, a.chunks, a.chunk) for s in a.scenes]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
