"""Chart 3: loop capacity over a real pseudo-terminal, against the floor this machine allows.

Two measurements in the same run, at each rate:

- **raw echo floor**: a child process echoes bytes on the slave side of a raw pty with bare
  ``os.read``/``os.write``; the parent, clocked on ``time.perf_counter`` (sleep, then spin to
  each deadline), writes one frame-sized message per period and reads the echo back. This
  is the least any host loop can do through a pty on this machine (no codec, no physics).
- **daemon**: :func:`hapsim.daemon.runner.run_scene` on ``configs/wall.yaml`` at that rate,
  real-time, with the mock device in another process on a pty (``transport="pty"``); its
  loop report gives missed/late samples and the turnaround (STATE read -> FORCE written).

Missed deadlines: echo, replies that arrive after the next deadline (``t_k + T``); daemon,
``missed + late`` samples of its report. Ratios daemon / echo of the p50/p99 turnaround are
reported. The machine is shared: figures are medians of what one run saw, not guarantees.
"""

from __future__ import annotations

import math
import os
import platform
import subprocess
import sys
import time

import numpy as np

__all__ = ["RATES", "QUICK_RATES", "echo_floor", "daemon_run", "loop_capacity"]

#: Rates of chart 3 [Hz].
RATES = (1000.0, 2000.0, 5000.0, 10000.0)
QUICK_RATES = (1000.0, 5000.0)

_ECHO = r"""
import os, sys
fd = int(sys.argv[1])
try:
    while True:
        b = os.read(fd, 256)
        if not b:
            break
        os.write(fd, b)
except OSError:  # the host closed its end
    pass
"""


def _pct(values) -> dict:
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"p50": None, "p99": None, "p999": None, "max": None}
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)),
            "p999": float(np.percentile(v, 99.9)), "max": float(v.max())}


def echo_floor(rate_hz: float, duration: float = 1.0, frame: int = 24) -> dict:
    """Raw pty echo at a rate: turnaround and missed deadlines.

    Parameters
    ----------
    rate_hz : float
        Request rate [Hz].
    duration : float
        Run length [s].
    frame : int
        Bytes per message (about a STATE frame of the hapsim protocol).

    Returns
    -------
    dict
        ``rate_hz``, ``samples``, ``missed`` (replies later than the next deadline),
        ``missed_pct``, ``turnaround_us`` (``p50``, ``p99``, ``p999``, ``max``).
    """
    import pty
    import tty

    master, slave = pty.openpty()
    tty.setraw(slave)
    # as hapsim.daemon.transport: the far side (here the echo) owns the master, the host
    # loop reads and writes the raw slave
    child = subprocess.Popen([sys.executable, "-c", _ECHO, str(master)], pass_fds=[master])
    os.close(master)
    master = slave  # the host's end, below
    try:
        msg = bytes(range(frame))
        # warm-up: the child is up when an echo comes back
        os.write(master, msg)
        got = 0
        while got < frame:
            got += len(os.read(master, 256))
        T = 1.0 / rate_hz
        n = max(10, int(duration * rate_hz))
        turn = np.empty(n)
        missed = 0
        t0 = time.perf_counter() + 0.01
        for k in range(n):
            dl = t0 + k * T
            while True:
                now = time.perf_counter()
                if now >= dl:
                    break
                if dl - now > 0.0015:
                    time.sleep(dl - now - 0.001)
            ts = time.perf_counter()
            os.write(master, msg)
            got = 0
            while got < frame:
                got += len(os.read(master, 256))
            te = time.perf_counter()
            turn[k] = (te - ts) * 1e6
            if te > dl + T:
                missed += 1
        return {"rate_hz": float(rate_hz), "samples": n, "missed": missed,
                "missed_pct": 100.0 * missed / n, "turnaround_us": _pct(turn)}
    finally:
        os.close(master)
        child.terminate()
        try:
            child.wait(timeout=2)
        except subprocess.TimeoutExpired:  # pragma: no cover
            child.kill()


def daemon_run(rate_hz: float, duration: float = 1.0, scene_path: str | None = None) -> dict:
    """The hapsim daemon in real time against the mock on a pty, at one rate.

    Parameters
    ----------
    rate_hz : float
        [Hz].
    duration : float
        [s].
    scene_path : str, optional
        Scene; ``configs/wall.yaml`` of the repository by default.

    Returns
    -------
    dict
        ``rate_hz``, ``samples``, ``missed`` (missed + late samples), ``missed_pct``,
        ``turnaround_us``, ``stop_reason``; or ``{"rate_hz", "error"}`` when the run failed.
    """
    from hapsim.daemon.runner import run_scene
    from hapsim.scene import load_scene

    if scene_path is None:
        scene_path = os.path.join(os.path.dirname(__file__), "..", "..", "configs", "wall.yaml")
    scene = load_scene(scene_path)
    try:
        rep = run_scene(scene, rate_hz=rate_hz, duration=duration, transport="pty",
                        handle_signals=False, allow_unstable=False)
    except Exception as exc:  # a failed run is a data point, not a crash of the bench
        return {"rate_hz": float(rate_hz), "error": f"{type(exc).__name__}: {exc}"}
    lp = rep.get("loop", {})
    n = int(lp.get("samples") or 0) or max(1, int(duration * rate_hz))
    missed = int(lp.get("missed") or 0) + int(lp.get("late") or 0)
    return {"rate_hz": float(rate_hz), "samples": n, "missed": missed,
            "missed_pct": 100.0 * missed / n, "turnaround_us": lp.get("turnaround_us", {}),
            "stop_reason": lp.get("stop_reason", rep.get("stop_reason")),
            "overruns": lp.get("overruns")}


def loop_capacity(rates=RATES, duration: float = 1.0, *, daemon: bool = True) -> dict:
    """Data of chart 3.

    Parameters
    ----------
    rates : sequence of float
        [Hz].
    duration : float
        Seconds per rate and per measurement.
    daemon : bool
        Also run the daemon (when importable).

    Returns
    -------
    dict
        JSON-ready: ``rates``, ``echo`` (list of :func:`echo_floor`), ``daemon`` (list of
        :func:`daemon_run` or empty), ``daemon_note`` (why it is missing, else ""),
        ``ratios`` (daemon / echo p50 and p99 per rate), ``machine``.
    """
    out = {"rates": [float(r) for r in rates], "duration_s": duration, "echo": [],
           "daemon": [], "daemon_note": "", "ratios": [],
           "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python "
                      f"{platform.python_version()}"}
    have = False
    if daemon:
        try:
            import hapsim.daemon.runner  # noqa: F401
            have = True
        except Exception as exc:  # pragma: no cover - depends on the tree
            out["daemon_note"] = f"daemon not available: {type(exc).__name__}: {exc}"
    else:
        out["daemon_note"] = "daemon not run (--no-daemon)"
    for r in rates:
        e = echo_floor(r, duration)
        out["echo"].append(e)
        if have:
            d = daemon_run(r, duration)
            out["daemon"].append(d)
            ratio = {"rate_hz": float(r)}
            for q in ("p50", "p99"):
                a = (d.get("turnaround_us") or {}).get(q)
                b = e["turnaround_us"].get(q)
                ratio[q] = (a / b) if a and b else None
            out["ratios"].append(ratio)
    if have and any("error" in d for d in out["daemon"]):
        out["daemon_note"] = "; ".join(f"{d['rate_hz']:g} Hz: {d['error']}"
                                       for d in out["daemon"] if "error" in d)
    return out
