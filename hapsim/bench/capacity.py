"""Chart 3: loop capacity over a real pseudo-terminal, against the floor this machine allows.

Two measurements in the same run, at each rate:

- **raw echo floor** (:func:`echo_floor`): a child process ticks like the mock device on the
  pty master (one frame-sized message per period on its own clock) and this process echoes
  each message with bare ``os.read``/``os.write`` on the raw slave. This is the least any
  host loop can do through a pty on this machine (no codec, no physics, no telemetry).
- **daemon**: :func:`hapsim.pipeline.runner.run_scene` on ``configs/wall.yaml`` at that rate,
  real-time, with the mock device in another process on a pty (``transport="pty"``); its
  loop report gives missed/late samples and the turnaround (STATE read -> FORCE written).

Both report the same two things: missed deadlines (echo: ticks at which the reply to the
previous tick had not arrived; daemon: ``missed + late`` samples of its loop report) and the
host turnaround (message read -> reply written). Ratios daemon / echo of the p50, p99 and
p999 turnaround and of the missed fraction are reported (:func:`capacity_ratios`, which can
also re-derive them from a saved JSON without measuring again). The machine is shared: figures are medians of what one run saw, not guarantees.
"""

from __future__ import annotations

import errno
import os
import platform
import subprocess
import sys
import time

import numpy as np

__all__ = ["RATES", "QUICK_RATES", "QUANTILES", "echo_floor", "daemon_run", "capacity_ratios",
           "loop_capacity"]

#: Rates of chart 3 [Hz].
RATES = (1000.0, 2000.0, 5000.0, 10000.0)
QUICK_RATES = (1000.0, 5000.0)
#: Turnaround quantiles compared daemon / echo.
QUANTILES = ("p50", "p99", "p999")

_TICKER = r"""
import json, os, sys, time
fd, rate, n, frame = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
os.set_blocking(fd, False)
T = 1.0 / rate
buf = bytearray()
sent = [0.0] * n
got = bytearray(n)
rtt = []
late = 0
pad = bytes(frame - 4)
t0 = time.perf_counter() + 0.05
for k in range(n + 1):
    dl = t0 + k * T
    while True:
        now = time.perf_counter()
        try:
            buf += os.read(fd, 65536)
            now = time.perf_counter()
        except BlockingIOError:
            pass
        while len(buf) >= frame:
            seq = int.from_bytes(buf[:4], "little")
            del buf[:frame]
            if seq < n and not got[seq]:
                got[seq] = 1
                rtt.append((now - sent[seq]) * 1e6)
        if now >= dl:
            break
        if dl - now > 0.002:
            time.sleep(dl - now - 0.0015)
    if now - dl > T:       # descheduled for more than a period: the schedule slips (as the
        t0 += now - dl     # daemon's mock) instead of firing the missed ticks back to back
    if k > 0 and not got[k - 1]:
        late += 1          # the reply to tick k-1 is not in at tick k: the device holds
    if k < n:
        sent[k] = time.perf_counter()
        os.write(fd, k.to_bytes(4, "little") + pad)
print(json.dumps({"late": late, "rtt": rtt}))
"""


def _pct(values) -> dict:
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"p50": None, "p99": None, "p999": None, "max": None}
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)),
            "p999": float(np.percentile(v, 99.9)), "max": float(v.max())}


def echo_floor(rate_hz: float, duration: float = 1.0, frame: int = 24) -> dict:
    """The floor: a device-clocked ticker and a host that only echoes, over a raw pty.

    A child process (the device side, on the pty master, as the daemon's mock) writes one
    ``frame``-byte message per period on its own clock and counts the ticks at which the
    reply to the previous tick has not arrived (late: a device would hold the old force);
    this process (the host side, raw slave) reads each message with ``os.read`` and writes it
    straight back with ``os.write``: a host loop with no codec, no physics, no telemetry.

    Parameters
    ----------
    rate_hz : float
        Tick rate [Hz].
    duration : float
        Run length [s].
    frame : int
        Bytes per message (about a STATE frame of the hapsim protocol), >= 4.

    Returns
    -------
    dict
        ``rate_hz``, ``samples``, ``missed`` (late ticks), ``missed_pct``,
        ``turnaround_us`` (host side, message read -> echo written; ``p50``, ``p99``,
        ``p999``, ``max``), ``round_trip_upper_us`` (device side, written -> reply seen; an
        upper bound, the ticker sleeps between deadlines).
    """
    import json
    import pty
    import tty

    n = max(10, int(duration * rate_hz))
    master, slave = pty.openpty()
    tty.setraw(slave)
    child = subprocess.Popen([sys.executable, "-c", _TICKER, str(master), repr(float(rate_hz)),
                              str(n), str(frame)], pass_fds=[master], stdout=subprocess.PIPE)
    os.close(master)
    turn = np.empty(n)
    got = 0
    buf = bytearray()
    try:
        while got < n:
            try:
                b = os.read(slave, 65536)
            except OSError as exc:
                # the ticker has sent its n messages and exited, closing its side, while
                # this host (late on a loaded machine) had not read the last of them:
                # Linux ends the pty then (EIO), and the ticker's own count of the
                # replies not in by the next tick (``late``) holds what was not read
                if exc.errno != errno.EIO:
                    raise
                break
            t_in = time.perf_counter()
            if not b:
                break
            buf += b
            m = len(buf) // frame * frame
            if m:
                os.write(slave, bytes(buf[:m]))
                t_out = time.perf_counter()
                del buf[:m]
                for _ in range(m // frame):
                    if got < n:
                        turn[got] = (t_out - t_in) * 1e6
                        got += 1
        out, _ = child.communicate(timeout=10 + 2 * duration)
        res = json.loads(out)
    finally:
        os.close(slave)
        if child.poll() is None:  # pragma: no cover
            child.kill()
    return {"rate_hz": float(rate_hz), "samples": n, "missed": int(res["late"]),
            "missed_pct": 100.0 * res["late"] / n, "turnaround_us": _pct(turn[:got]),
            "round_trip_upper_us": _pct(res["rtt"]),
            "round_trip_note": "device side, written -> reply seen; an upper bound: a reply "
                               "that arrives while the ticker sleeps is seen when it wakes"}


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
    from hapsim.pipeline.runner import run_scene
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


def capacity_ratios(echo, daemon) -> list:
    """Daemon / echo ratios per rate, derived from the measured rows only.

    Parameters
    ----------
    echo : list of dict
        :func:`echo_floor` rows (``rate_hz``, ``missed_pct``, ``turnaround_us``).
    daemon : list of dict
        :func:`daemon_run` rows, matched to ``echo`` by ``rate_hz`` (a row with ``error``
        gives None ratios).

    Returns
    -------
    list of dict
        One per echo row with a daemon row of the same rate: ``rate_hz`` [Hz],
        ``turnaround_p50``, ``turnaround_p99``, ``turnaround_p999`` [-] (daemon turnaround
        quantile / echo's), ``missed`` [-] (daemon missed % / echo's); None where either is
        missing or the echo's is 0.
    """
    by_rate = {float(d["rate_hz"]): d for d in daemon or []}
    out = []
    for e in echo or []:
        d = by_rate.get(float(e["rate_hz"]))
        if d is None:
            continue
        ratio = {"rate_hz": float(e["rate_hz"])}
        for q in QUANTILES:
            a = (d.get("turnaround_us") or {}).get(q)
            b = (e.get("turnaround_us") or {}).get(q)
            ratio[f"turnaround_{q}"] = (a / b) if a and b else None
        a, b = d.get("missed_pct"), e.get("missed_pct")
        ratio["missed"] = (a / b) if a is not None and b else None
        out.append(ratio)
    return out


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
        ``ratios`` (:func:`capacity_ratios`: daemon / echo p50, p99, p999 and missed per
        rate), ``machine``.
    """
    out = {"rates": [float(r) for r in rates], "duration_s": duration, "echo": [],
           "daemon": [], "daemon_note": "", "ratios": [],
           "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python "
                      f"{platform.python_version()}"}
    have = False
    if daemon:
        try:
            import hapsim.pipeline.runner  # noqa: F401
            have = True
        except Exception as exc:  # pragma: no cover - depends on the tree
            out["daemon_note"] = f"daemon not available: {type(exc).__name__}: {exc}"
    else:
        out["daemon_note"] = "daemon not run (--no-daemon)"
    for r in rates:
        e = echo_floor(r, duration)
        out["echo"].append(e)
        if have:
            out["daemon"].append(daemon_run(r, duration))
    out["ratios"] = capacity_ratios(out["echo"], out["daemon"])
    if have and any("error" in d for d in out["daemon"]):
        out["daemon_note"] = "; ".join(f"{d['rate_hz']:g} Hz: {d['error']}"
                                       for d in out["daemon"] if "error" in d)
    return out
