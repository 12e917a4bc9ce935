"""The Haply M3 one-axis loop with byte loss and host stalls, in simulated time: what a lost
byte costs the board and the joint, deterministically (issue 29 item 2).

Usage::

    python tools/haply_loss_sim.py [--seeds 0 1 ... 15] [--loss 0.005] [--stalls 0.03]
                                   [--device-id N] [--duration 1.5]

The host side is hapsim's own: :class:`hapsim.drivers.transport.DriverTransport` (its
re-synchronisation rules, the reply checks) and the :class:`hapsim.drivers.haply.HaplyM3`
driver, the scene's law through :class:`hapsim.engine.Engine`. The board is the byte-exact
:class:`hapsim.emulated.driver_mock.HaplyDevice` on its own clock. Between them a port that
lands each write on the board a USB frame (0.3 ms) later and each reply as much after the
board's pass, with seeded byte loss each way (:class:`hapsim.emulated.driver_mock.
ByteFaults`). Time is simulated: the transport's clock is this program's (its module's
``time`` is replaced here, a measurement program's liberty: nothing of it is a test), the
host ticks at the scene's rate, and with probability ``--stalls`` a tick is a host stall of
1-6 periods (the host loop's :meth:`~hapsim.drivers.transport.DriverTransport.host_stalled`
told, as the real loop does). The host loop itself is a sketch of
:mod:`hapsim.host.loop`'s driver path (a new record answered; an overdue one estimated, at
most 2 in a row; else the last force again), with its safety stop on the force at the
limit in 50 of the last 100 samples. The same seed gives the same run on any host.

Each row: the stop (None: the run's duration), re-synchronisations, the joint's true
largest angle (the board's physics; it starts at 0.2 rad) and the host's. With the address
1 (``--device-id 1``, the default before), 1 byte in 200 lost and 3 % of ticks stalled: 5
of 16 runs stopped on the force at the limit, ~25 re-synchronisations each, true angles up
to 0.5 rad; with the default address 3: none stopped, 0.5 re-synchronisations (median),
the joint never past 0.2 rad.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import types

import numpy as np


class _Clock:
    t = 0.0


CLK = _Clock()


class SimPort:
    """A port in simulated time to a board (``feed(bytes, now) -> bytes``, ``ready_at``):
    writes land a USB frame later, replies a USB frame after the board's pass; seeded
    loss each way (pyserial's interface as the transport uses it)."""

    USB_S = 0.3e-3

    def __init__(self, board, faults):
        self.board, self.faults, self.queue = board, faults, []
        self.rx = bytearray()
        self.is_open = True

    def set_low_latency_mode(self, on):
        """Nothing to set (the transport asks)."""

    def write(self, data):
        """The board takes the bytes a USB frame later; its answer is queued."""
        t = CLK.t + self.USB_S
        out = self.board.feed(self.faults.rx(bytes(data)), t)
        if out:
            self.queue.append((max(self.board.ready_at, t) + self.USB_S, self.faults.tx(out)))
        return len(data)

    def _pull(self):
        keep = []
        for ready, data in self.queue:
            if ready <= CLK.t:
                self.rx += data
            else:
                keep.append((ready, data))
        self.queue = keep

    @property
    def in_waiting(self):
        """Bytes arrived by now."""
        self._pull()
        return len(self.rx)

    def read(self, n=1):
        """Up to ``n`` bytes; a read with nothing there waits 0.1 ms (pyserial's timeout)."""
        self._pull()
        if not self.rx:
            CLK.t += 1e-4
            self._pull()
        data = bytes(self.rx[:n])
        del self.rx[:n]
        return data

    def flush(self):
        """Nothing buffered."""

    def close(self):
        """Closed."""
        self.is_open = False


def run(seed: int, loss: float, stalls: float, device_id=None, duration: float = 1.5) -> dict:
    """One run (module notes).

    Parameters
    ----------
    seed : int
        Seeds the loss and the stalls.
    loss : float
        Probability that a byte is lost, each way.
    stalls : float
        Probability that a host tick is a stall of 1-6 periods.
    device_id : int, optional
        The host's address (None: the driver's default).
    duration : float
        [s] of simulated time.

    Returns
    -------
    dict
        ``stop``, ``resyncs``, ``true_excursion`` [rad], ``host_excursion`` [rad],
        ``t`` [s] reached, the transport's ``stats``.
    """
    import firmware_protocol as fp
    import serial

    import hapsim.drivers.transport as tr_mod
    from hapsim.drivers import get_driver
    from hapsim.emulated.driver_mock import ByteFaults, HaplyDevice
    from hapsim.engine import Engine
    from hapsim.scene import load_scene
    tr_mod.time = types.SimpleNamespace(
        monotonic=lambda: CLK.t, monotonic_ns=lambda: int(CLK.t * 1e9),
        sleep=lambda s: setattr(CLK, "t", CLK.t + s), perf_counter=lambda: CLK.t)
    sc = load_scene("configs/haply.yaml")
    dev = sc.device
    rng = np.random.default_rng(seed + 1000)
    board = HaplyDevice(dev, sc.rate_hz, sc.excitation, cpr=4880.0, clock="wall")
    opts = {"offset_deg": math.degrees(sc.excitation.x0)}
    if device_id is not None:
        opts["device_id"] = int(device_id)
    drv = get_driver("haply", **opts)
    port = SimPort(board, ByteFaults({"drop_rx": loss, "drop_tx": loss, "seed": seed}))
    serial.serial_for_url = lambda *a, **k: port
    CLK.t = 0.0
    tr = tr_mod.DriverTransport(drv, "sim://", delay=int(dev.delay), reply_deadline=0.0,
                                inertia=dev.mass)
    eng = Engine(sc)
    tr.send(fp.Config(sc.rate_hz, 0, dev.force_limit))
    period, lim, d = 1.0 / sc.rate_hz, dev.force_limit, int(dev.delay)
    latest, used, run_est, clamp, xs, stop = None, -1, 0, [], [], None
    while latest is None and CLK.t < 0.5:
        for m in tr.receive(0.0):
            if isinstance(m, fp.State):
                latest = m
        CLK.t += 1e-4
    deadline = CLK.t + period / 3

    def send(seq, x):
        f = max(-lim, min(lim, eng.port_step(x)))
        tr.send(fp.Force(seq, (f,)))
        clamp.append(abs(f) >= lim)
        xs.append(x)

    while latest is not None and CLK.t < duration:
        CLK.t = max(CLK.t, deadline)
        if rng.random() < stalls:
            CLK.t += rng.uniform(1, 6) * period
        for m in tr.receive(0.0):
            if isinstance(m, fp.State) and ((m.seq - latest.seq) & 0xFFFFFFFF) < 2 ** 31:
                latest = m
        behind = CLK.t - deadline
        if behind > period:
            tr.host_stalled(int(behind // period))
            deadline = CLK.t
        if latest.seq == used or ((latest.seq - used) & 0xFFFFFFFF) >= 2 ** 31:
            if run_est < 2 and tr.overdue():
                st = types.SimpleNamespace()
                x = tr.estimate(st, (used + 1) & 0xFFFFFFFF, d)
                if x == x:
                    run_est += 1
                    used = st.seq
                    send(st.seq, x)
                    deadline += period
                    continue
            tr.hold()
            deadline += period
            continue
        used, run_est = latest.seq, 0
        send(latest.seq, latest.position[0])
        if len(clamp) >= 100 and sum(clamp[-100:]) >= 50:
            stop = "force at the limit"
            break
        deadline += period
    return {"stop": stop, "resyncs": tr.stats["resyncs"],
            "true_excursion": board.wall.excursion,
            "host_excursion": float(np.max(np.abs(xs))) if xs else None, "t": CLK.t,
            "stats": dict(tr.stats)}


def main(argv=None) -> int:
    """Run the seeds, print a row each and the summary (JSON)."""
    p = argparse.ArgumentParser(prog="haply_loss_sim", description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", nargs="+", type=int, default=list(range(16)))
    p.add_argument("--loss", type=float, default=0.005)
    p.add_argument("--stalls", type=float, default=0.03)
    p.add_argument("--device-id", type=int, default=None)
    p.add_argument("--duration", type=float, default=1.5)
    a = p.parse_args(argv)
    rows = []
    for s in a.seeds:
        r = run(s, a.loss, a.stalls, a.device_id, a.duration)
        r["seed"] = s
        rows.append(r)
        print(json.dumps({k: r[k] for k in ("seed", "stop", "resyncs", "true_excursion",
                                             "host_excursion")}), flush=True)
    print(json.dumps({"runs": len(rows), "stops": sum(r["stop"] is not None for r in rows),
                      "resyncs_median": float(np.median([r["resyncs"] for r in rows])),
                      "true_excursion_max": max(r["true_excursion"] for r in rows)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
