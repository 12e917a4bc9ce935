"""Every driver's closed loop beside CPU-bound processes, with and without byte loss: what
real timing does to it (issue 29 item 2).

Usage::

    nice python tools/driver_timing.py [--drivers haply haply2 firefader hapkit-serial falcon]
                                       [--seeds 1 2 ... 10] [--loss 0 0.005] [--hogs 2]
                                       [--duration S] [--falcon-scene PATH]
                                       [--starve P LO_MS HI_MS] [--board-ppm PPM]
                                       [--json PATH]
    python tools/driver_timing.py --resummarize PATH    # the summary again from the runs

For each driver, each loss (the probability that a byte is lost, each way: 0 and 1 in
200 by default) and each seed, one run beside ``--hogs`` CPU-bound processes (started
here, ended here by their pids):

- ``haply`` (Haply M3, one axis), ``firefader`` (``configs/firefader.yaml``, 250 Hz),
  ``hapkit-serial`` (``configs/hapkit_serial.yaml``): the driver's scene through
  :func:`hapsim.pipeline.runner.run_scene` and its driver's byte-exact mock on a pty, the
  mock's own clock (``clock``: the wall clock where the mock keeps it, else lockstep);
- ``haply2`` (2DIY, ``configs/pantograph_wall.yaml`` at the run's default start, the
  largest the wall allows, 0.42 mm; ``--haply2-scene`` and ``--haply2-amplitude``
  another, e.g. ``docs/pantograph_deep_wall.yaml`` at 3e-4): the real-time host loop
  (:func:`hapsim.pipeline.haply2_host.measure_felt_haply2_port`) against the emulated board
  in process behind a link that loses bytes (seeded; the board on its own clock, the
  wall clock: each write fed at its time, its replies readable when the board made them);
- ``falcon`` (``configs/falcon_spring.yaml``, ``--falcon-scene`` another, e.g.
  ``configs/delta_sphere.yaml``): :func:`hapsim.pipeline.falcon_run.run_falcon` over
  pyftdi and the emulated FT232R, the loss on its UART, the Falcon on its own clock (its
  firmware's ticks) and the run paced as a real one's; then the felt matrices' records
  (:func:`hapsim.pipeline.falcon_run.felt_statement`), the same loss on each.

``--starve P LO_MS HI_MS`` (the 1-D drivers' mocks): the board's process is starved,
after each answer with probability ``P``, for a silence drawn in ``LO_MS``..``HI_MS`` ms
(seeded; it reads nothing meanwhile: :func:`hapsim.emulated.driver_mock.serve`'s ``slow``
hook), as a board process behind CPU-bound processes, a USB hub or a descheduled pty
reader is; no byte is lost by it (``board_silences``: their number and the longest).

``--board-ppm PPM`` (``hapkit-serial``): the emulated Hapkit's oscillator runs ``PPM``
parts per million off the host's clock (positive slower), so its 0.992 ms tick walks
across the host's writes, which the transport aligns to it once, at the first arming
(:class:`hapsim.emulated.hapkit_serial_board.HapkitSerialDevice`, ``clock_ppm``).

``--host-stall MS`` (the 1-D drivers): this process, the host, is stopped once for ``MS``
ms (``SIGSTOP``, then ``SIGCONT`` from a child) at a seeded moment 1 to 1 + duration/2 s (the duration 1 s
when the run's own)
after the run starts: the host loop, its reader and everything else here stop together,
as a descheduled or swapped host does; the board's process runs on, holding the last
force as its firmware does (a watchdog or none), and the run shows what the host meets
when it wakes.
The host's watchdog (:mod:`hapsim.drivers.host_watchdog`), its own process, is not
stopped: ``longest_hold_s`` is the board's longest non-zero force held with no write,
``watchdog`` what the watchdog did; ``--no-host-watchdog`` is the A/B's baseline.

Each row: safety stop, re-synchronisations (and why, ``resync_reasons``; the silences the
host waited for instead, ``silences``; the host's ``frame_bound``: how far their estimates
may have moved the board's frame, summed; the emulated board's ``frame_walk``: how far its
set-ups moved its frame, the stop's included, and its parser's counters,
``board_parser``), host stalls, the largest excursion (the
device's own where its model reports it, ``true_excursion``; else the host's readings),
the verdict and the exit code ``hapsim run`` would give. A measurement program, not a
test: real time, on a shared machine; the 1-minute load average is in the JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from provenance import command_line  # tools/, beside this file



def _names(n_d: bool) -> tuple:
    """This tool's names of the registry's driven families (:data:`hapsim.drivers.FAMILIES`,
    the framed protocol left out), the 1-D ones or the n-D ones: a family's name, an n-D
    one's with its dimension when a 1-D family has the same name (``haply2``: the 2DIY)."""
    from hapsim.drivers import FAMILIES
    one_d = {f.name for f in FAMILIES if f.dimension == 1}
    return tuple(f.name + (str(f.dimension) if f.name in one_d and n_d else "")
                 for f in FAMILIES if f.dimension >= 1 and (f.dimension > 1) == n_d)


#: The drivers measured: the 1-D ones through run_scene, then the n-D ones' own routes
DRIVERS = _names(False) + _names(True)


def _load():
    """The 1-minute load average, or None where the platform has none."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def _stall_this_process(stall_ms: float, at_s: float) -> subprocess.Popen:
    """A child that stops this process (SIGSTOP) ``at_s`` seconds from now for
    ``stall_ms`` ms, then continues it (SIGCONT): every thread here stops, the board's
    process does not (module notes, ``--host-stall``)."""
    pid = os.getpid()
    return subprocess.Popen([sys.executable, "-c", (
        f"import os, signal, time\ntime.sleep({at_s!r})\nos.kill({pid}, signal.SIGSTOP)\n"
        f"try:\n    time.sleep({stall_ms / 1e3!r})\nfinally:\n"
        f"    os.kill({pid}, signal.SIGCONT)")])


def run_1d(driver: str, seed: int, loss: float, duration: float, rt_priority: int = 10,
           starve=None, stall_ms=None, board_ppm=None) -> dict:
    """One run of ``configs/<driver>.yaml`` through the driver's mock (module notes);
    ``starve``: ``(P, lo_ms, hi_ms)``, the board's process starved; ``stall_ms``: one
    stall of this process (module notes, ``--host-stall``); ``board_ppm``: the Hapkit
    board's oscillator off the host's clock [ppm] (``--board-ppm``)."""
    faults = {"drop_tx": loss, "drop_rx": loss, "seed": seed}
    staller = None
    if stall_ms:
        # the loop is armed ~0.5-1 s after run_scene starts (imports done, the mock's
        # start-up, the handshake): the stall falls inside the run's first second or so
        at_s = float(np.random.default_rng(seed).uniform(1.0, 1.0 + 0.5 * (duration or 1.0)))
        staller = _stall_this_process(float(stall_ms), at_s)
    if starve:
        faults.update(slow=float(starve[0]),
                      slow_s=[float(starve[1]) * 1e-3, float(starve[2]) * 1e-3])
    from hapsim.pipeline.runner import run_scene
    from hapsim.errors import DeviceError, ProtocolError
    from hapsim.scene import load_scene
    hardware = None
    if board_ppm:
        from hapsim.drivers import get_driver
        hardware = {**get_driver(driver).mock_hardware(), "clock_ppm": float(board_ppm)}
    with tempfile.TemporaryDirectory() as tmp:
        tel = os.path.join(tmp, "t.npz")
        try:
            rep = run_scene(load_scene(f"configs/{driver.replace('-', '_')}.yaml"),
                            driver=driver,
                            duration=duration, handle_signals=False,
                            rt_priority=rt_priority,
                            telemetry=tel, seed=seed,
                            driver_faults=faults, mock_options=hardware)
            err = None
        except (DeviceError, ProtocolError) as exc:
            rep = getattr(exc, "report", None)
            err = f"{type(exc).__name__}: {exc}"
            if rep is None:
                return {"error": err}
        finally:
            if staller is not None:
                staller.wait()
        x_host = None
        if os.path.exists(tel):
            d = np.load(tel)
            if "position" in d.files and d["position"].size:
                x_host = float(np.nanmax(np.abs(d["position"])))
    lp, m = rep["loop"], rep["measured"]
    mk, dl = lp.get("mock") or {}, lp.get("driver") or {}
    return {"clock": mk.get("clock", "lockstep" if lp.get("lockstep") else "?"),
            "safety_stop": bool(lp["safety_stop"]), "stop": lp["stop_reason"],
            "resyncs": dl.get("resyncs"), "stalls": dl.get("host_stalls", lp.get("overruns")),
            "excursion_true": mk.get("true_excursion"), "excursion_host": x_host,
            "frame_walk": mk.get("frame_walk"), "frame_bound": dl.get("frame_bound"),
            # the board's longest non-zero hold without a write [s], and the host's
            # watchdog (hapsim.drivers.host_watchdog): the bound on it
            "longest_hold_s": mk.get("longest_hold_s"), "watchdog": dl.get("watchdog"),
            "resync_reasons": {k: v for k, v in (dl.get("resync_reasons") or {}).items() if v},
            "silences": dl.get("silences"), "silence_max_s": dl.get("silence_max_s"),
            "board_silences": mk.get("starved"),
            # the board's own parser (CommandDecoder.stats): set-ups, resets, bytes that
            # were no command, single reads of a byte not arrived -- whether it lost its
            # place in the host's stream, or only answered late
            "board_parser": mk.get("decoder"),
            "workspace": lp["safety"]["position_limit"],
            "verdict": m.get("verdict"), "within": m.get("within"),
            "exit_code": rep.get("exit_code"), "error": err or m.get("error"),
            "scheduling": lp.get("scheduling"),
            # a board on its own tick: the holds it took off the period (its own count)
            # and those the measurement found in the record and cut
            "board_off_period": (mk.get("tick_arrivals") or {}).get("off_period"),
            "unseen_holds": m.get("unseen_holds"),
            # a ticking board: how far its tick moved against the host's writes over the
            # run (the probe at its stop, hapsim.drivers.tick_align.TickAligned.end_probe)
            "tick_moved": dl.get("tick_moved")}


def run_haply2(seed: int, loss: float, clock: str = "wall",
               scene: str = "configs/pantograph_wall.yaml",
               amplitude: float | None = None) -> dict:
    """One 2DIY measurement against the in-process emulated board behind a lossy link.

    On the wall clock (the board's default, firmware V1.5's own time: its joints move
    under the torques held while the host is late or silent) each write is fed at its
    time and its replies are readable from the board's ``ready_at`` on; in lockstep
    (named) each write is one period and its reply there at once. ``excursion_true`` is
    the joints' largest departure from the operating point [rad] (the board's truth);
    ``workspace`` the bound it is held to
    (:data:`hapsim.pipeline.haply2_host.WORKSPACE_RAD`). ``scene`` and ``amplitude``
    (the hand's ``a`` [m]; None: the run's default,
    :func:`hapsim.commands.run_haply2.designed_start`): ``--haply2-scene``,
    ``--haply2-amplitude``."""
    from hapsim.emulated.haply2_board import Haply2DIYBoard
    from hapsim.pipeline.haply2_host import WORKSPACE_RAD, measure_felt_haply2_port
    from hapsim.emulated.driver_mock import ByteFaults
    from hapsim.lockstep import identification_plan
    from hapsim.scene import load_scene_nd
    from hapsim.errors import DeviceError
    sc = load_scene_nd(scene)
    if amplitude is None:
        from hapsim.commands.run_haply2 import designed_start
        amplitude = designed_start(sc)[0]
    if clock == "wall":
        # the board's compiled plant loaded before the clock (in process its first call
        # would be the host's stall and the held torque's time: a first run's 2.2 rad)
        from hapsim.drivers.haply2 import Haply2DIY
        warm, drv = Haply2DIYBoard(sc, "gen3", clock="wall"), Haply2DIY("gen3")
        warm.feed(drv.arm_bytes([float(np.degrees(v)) for v in sc.device.joints]), 0.0)
        warm.feed(drv.write_bytes((0.0, 0.0)), 0.01)
    board = Haply2DIYBoard(sc, "gen3", cpr=2.0 ** 22, amplitude=amplitude, clock=clock)
    f = ByteFaults({"drop_rx": loss, "drop_tx": loss, "seed": seed})
    q0 = np.asarray(sc.device.joints, float)
    exc_max = [0.0]
    t0 = time.perf_counter()

    class Link:
        out = bytearray()
        queue = []                      # wall clock: (ready at [s], reply bytes)

        def write(self, data):
            if clock == "wall":
                rep = board.feed(f.rx(bytes(data)), time.perf_counter() - t0)
                if rep:
                    self.queue.append((board.ready_at, f.tx(rep)))
            else:
                self.out += f.tx(board.feed(f.rx(bytes(data))))
            exc_max[0] = max(exc_max[0], float(np.abs(board.plant.joints() - q0).max()))
            return len(data)

        def _release(self):
            now = time.perf_counter() - t0
            while self.queue and self.queue[0][0] <= now:
                self.out += self.queue.pop(0)[1]

        @property
        def in_waiting(self):
            self._release()
            return len(self.out)

        def read(self, n):
            self._release()
            b = bytes(self.out[:n])
            del self.out[:n]
            return b
    # the run's own record length (hapsim run --driver haply's: the identification
    # plan's default, hapsim.lockstep.default_samples, 300 on the pantograph scenes);
    # the tables before 2026-11-26 took 200
    N = None

    def truth():
        # the joints' largest departure while the host ran them: after each of its writes
        # and, on the wall clock, every instant the board integrated to (its passes ahead
        # of the host's time included); not the free coast at zero torque after the run,
        # which no hand damps in the model (up to 0.3 rad measured while the fit ran)
        return max(exc_max[0], board.excursion)
    try:
        r = measure_felt_haply2_port(Link(), sc, "gen3", amplitude=amplitude,
                                     resolution=2.0 ** 22, samples=N,
                                     plan=None if N is None else identification_plan(sc, N),
                                     probe_wiring=False,
                                     lockstep_board=clock == "lockstep")
    except DeviceError as exc:
        return {"clock": clock, "error": f"DeviceError: {exc}",
                "excursion_true": truth(), "workspace": WORKSPACE_RAD}
    return {"clock": clock, "safety_stop": False, "stop": "end",
            "resyncs": int(sum(r["resyncs"])), "stalls": int(sum(r.get("stalls", [0]))),
            "excursion_true": truth(), "excursion_host": None,
            "workspace": WORKSPACE_RAD, "beyond_workspace": truth() > WORKSPACE_RAD,
            "verdict": r["verdict"], "within": r["within"],
            "exit_code": 0 if r["verdict"] != "differs" else 1,
            "reason": r.get("reason"), "estimated": int(sum(r["estimated"])),
            "amplitude_m": amplitude, "not_stated": r.get("not_stated"),
            "held_zero": int(sum(r["held_zero"])), "left": r.get("left"),
            # per record: markers sent (hapsim.pipeline.haply2_realign), their answers
            # that moved the count (writes the board swallowed: no re-synchronisation),
            # re-synchronisations, rows left to the fit (of the record's)
            "probes": r.get("probes"),
            "realigned": r.get("realigned"), "resyncs_per_record": r.get("resyncs"),
            "usable": r.get("usable"),
            "held_at_end": board.settles_on(), "error": None,
            # the figures beside the verdict (issue 29): each felt matrix's deviation, its
            # stated uncertainty, the wire's term in it, the largest hold off a period
            **{key: {q: (r.get(src) or {}).get(q) for q in ("felt_stiffness", "felt_damping")}
               for key, src in (("deviation", "deviation"), ("uncertainty", "uncertainty"),
                                ("wire_term", "wire"))},
            "hold_s": (r.get("wire") or {}).get("hold_s")}


def run_falcon_once(seed: int, loss: float, clock: str = "wall",
                    scene: str = "configs/falcon_spring.yaml", stall_ms=None,
                    start_mm: float = 0.0) -> dict:
    """One Falcon run over the emulated FT232R with seeded loss on its UART, as
    ``hapsim run SCENE --driver falcon`` runs it: the loop from rest (the link's verdict,
    ``link_verdict``), then the felt matrices' statement
    (:func:`hapsim.pipeline.falcon_run.felt_statement`: where the Falcon's counts allow,
    the identification's records from the hand's starts, each on a fresh emulated Falcon
    with the same loss, seeded ``100 seed + record``), whose verdict is the row's.

    The emulated Falcon on its own clock (its firmware's ticks, the default; lockstep by
    name), the run paced as a real Falcon's is (a host stall is the firmware holding the
    last command: "degraded"; in the records, a row cut). ``excursion_true`` is the legs'
    largest departure from the operating point [rad] over the loop (the emulator's
    truth) and the records (their readings; ``felt_excursion_true``: the emulator's,
    which adds the free coast after each record's zero commands, no hand holding the
    handle), ``workspace`` the bound it is held to
    (:data:`hapsim.pipeline.falcon_run.WORKSPACE_RAD`). ``stall_ms``: this process, the
    host and the emulated Falcon in it, stopped once at a seeded moment of the loop
    (``--host-stall``: the emulated chip takes the host watchdog's write at the time it
    was made); ``start_mm``: the hand let go that far off rest along x as the loop
    starts (``--falcon-start``: a loop from rest commands nothing to hold)."""
    from hapsim.pipeline.falcon_run import (WORKSPACE_RAD, emulated_falcon, felt_statement,
                                            run_falcon)
    from hapsim.emulated.driver_mock import ByteFaults
    from hapsim.errors import DeviceError
    from hapsim.scene import load_scene_nd
    sc = load_scene_nd(scene)
    image = bytes(np.random.default_rng(7).integers(0, 256, 1000, dtype=np.uint8))
    faults = ByteFaults({"drop_rx": loss, "drop_tx": loss, "seed": seed})
    link, dev, chip = emulated_falcon(sc, image, faults=faults, clock=clock)
    chip.faults_on = False

    staller = []

    def start():
        chip.faults_on = True
        dev.excursion = 0.0                    # the loop's, not the homing's
        if stall_ms:
            at_s = float(np.random.default_rng(seed).uniform(0.1, 0.6))
            staller.append(_stall_this_process(float(stall_ms), at_s))
    let_go = (None if not start_mm else
              lambda: dev.let_go(np.array([start_mm * 1e-3, 0.0, 0.0]), np.zeros(3)))
    try:
        res = run_falcon(sc, link, image, 1000, truth=dev.counts, timeout=0.002,
                         before_loop=start, paced=clock == "wall", start=let_go)
    except DeviceError as exc:
        return {"clock": clock, "error": f"DeviceError: {exc}",
                "excursion_true": dev.excursion, "workspace": WORKSPACE_RAD}
    finally:
        link.close()
        for c in staller:
            c.wait()
    try:
        felt = felt_statement(sc, image, clock=clock, faults=lambda i: ByteFaults(
            {"drop_rx": loss, "drop_tx": loss, "seed": 100 * seed + i}) if loss else None)
    except DeviceError as exc:
        felt = {"verdict": None, "reason": f"DeviceError: {exc}", "error": True}
    recs = felt.get("records") or []
    pos = res["position"]
    stopped = res.get("stopped")
    stops = [r["stopped"] for r in recs if r["stopped"]]
    exc_true = max([dev.excursion] + [r["excursion_rad"] for r in recs])
    return {"clock": clock, "scene": scene,
            "safety_stop": bool(stopped) or bool(stops),
            "stop": stopped[1] if stopped else (stops[0][1] if stops else "end"),
            "resyncs": 0, "stalls": res.get("stalls"), "waits": res.get("waits"),
            "excursion_true": exc_true,
            "felt_excursion_true": max([r["excursion_true_rad"] for r in recs],
                                       default=None),
            "excursion_host": float(np.nanmax(np.abs(pos - pos[0]))) if pos.size else None,
            "workspace": WORKSPACE_RAD, "beyond_workspace": exc_true > WORKSPACE_RAD,
            "longest_hold_s": dev.longest_hold_s, "watchdog": res.get("watchdog"),
            "link_stopped": stopped[1] if stopped else None,
            "verdict": felt["verdict"], "within": felt.get("within"),
            "felt_reason": felt["reason"],
            "deviation": felt.get("deviation"), "uncertainty": felt.get("uncertainty"),
            "wire_term": felt.get("wire"), "amplitude_m": felt.get("amplitude_m"),
            "felt_missing": felt.get("missing"), "felt_late_rows": felt.get("late_rows"),
            "felt_stalls": sum(r["stalls"] for r in recs),
            "felt_link_verdicts": [r["link_verdict"] for r in recs],
            # each statement made or not (its name, verdict, departure, uncertainty and
            # wire term: the principal directions' too)
            "statements": felt.get("statements"),
            "link_verdict": res["verdict"],
            "exit_code": 0, "missing": res["missing"], "reason": res["reason"],
            "held_zero": res["held_zero"],
            "truth": res["truth"], "error": felt["reason"] if felt.get("error") else None}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="driver_timing", description=__doc__.split("\n\n")[0])
    p.add_argument("--drivers", nargs="+", default=list(DRIVERS), choices=DRIVERS)
    p.add_argument("--seeds", nargs="+", type=int, default=list(range(1, 11)))
    p.add_argument("--loss", nargs="+", type=float, default=[0.0, 1 / 200])
    p.add_argument("--hogs", type=int, default=2, help="CPU-bound processes beside (2)")
    p.add_argument("--duration", type=float, default=None,
                   help="1-D runs [s] (default: the run's own, as 'hapsim run' designs it: "
                        "at least 1 s, ten cycles of the predicted oscillation)")
    p.add_argument("--rt-priority", type=int, default=10, metavar="N",
                   help="SCHED_FIFO priority of the host loops (and the boards' processes) "
                        "where the OS permits it: 10, as 'hapsim run' takes by default; 0 "
                        "for normal scheduling")
    p.add_argument("--haply2-scene", default="configs/pantograph_wall.yaml",
                   metavar="PATH", help="the 2DIY's scene (default "
                   "configs/pantograph_wall.yaml; docs/pantograph_deep_wall.yaml: the same "
                   "loop with the wall 2 mm deep)")
    p.add_argument("--haply2-amplitude", type=float, default=None, metavar="M",
                   help="the 2DIY hand's start a [m] (default the run's: the largest the "
                        "scene's linear range allows, 0.42 mm on the shallow wall)")
    p.add_argument("--falcon-scene", default="configs/falcon_spring.yaml", metavar="PATH",
                   help="the Falcon's scene (configs/falcon_spring.yaml: its felt "
                        "matrices measurable; configs/delta_sphere.yaml: the contact's "
                        "link verdict, its felt matrices not measurable by its depth)")
    p.add_argument("--starve", nargs=3, type=float, default=None,
                   metavar=("P", "LO_MS", "HI_MS"),
                   help="starve the 1-D boards' processes: after an answer, with "
                        "probability P, a silence of LO_MS..HI_MS ms (module notes)")
    p.add_argument("--host-stall", type=float, default=None, metavar="MS",
                   help="the 1-D and Falcon runs: stop the host's process once for MS ms at "
                        "a seeded moment of its loop (SIGSTOP/SIGCONT; module notes)")
    p.add_argument("--board-ppm", type=float, nargs="+", default=[0.0], metavar="PPM",
                   help="the Hapkit-serial board's oscillator this far off the host's "
                        "clock [parts per million], positive slower: its 0.992 ms tick "
                        "walks against the host's writes, aligned once at the arming "
                        "(hapsim.emulated.hapkit_serial_board, clock_ppm; default 0); "
                        "several: each seed run on each in turn, the summary keyed by "
                        "the offset too")
    p.add_argument("--falcon-start", type=float, default=0.0, metavar="MM",
                   help="the Falcon's loop: the hand let go MM mm off rest along x as it "
                        "starts (default 0: from rest)")
    p.add_argument("--no-host-watchdog", action="store_true",
                   help="the baseline of an A/B: no host watchdog is started "
                        "(hapsim.drivers.torque_watchdog.start_watchdog)")
    p.add_argument("--link", nargs="+", choices=("emulated", "pty"), default=["emulated"],
                   help="the 1-D boards' link (hapsim.emulated.driver_mock.WALL_LINK): "
                        "emulated (the default: each host write taken at its kernel "
                        "stamp) or pty (each taken when the board's process reads it: "
                        "the link before); both: each seed run on each in turn, an A/B "
                        "whose two arms share the hour (the summary keyed by link too)")
    p.add_argument("--json", default=None, metavar="PATH")
    p.add_argument("--resummarize", default=None, metavar="PATH",
                   help="recompute the summary of a JSON this tool wrote from its runs "
                        "(no run is taken) and write it back")
    a = p.parse_args(argv)
    if a.resummarize:
        print(json.dumps(resummarize(a.resummarize), indent=1))
        return 0
    import hapsim.emulated.driver_mock as dm
    if a.no_host_watchdog:
        import hapsim.drivers.torque_watchdog as tw
        tw.start_watchdog = lambda *_a, **_k: (None, "off: --no-host-watchdog")
    from hapsim.host.realtime import RealtimePriority
    import signal
    # a SIGTERM ends the runs through the finally below (the CPU-bound processes too)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(a.hogs)]
    load_before = _load()
    rows = []
    try:
        for drv in a.drivers:
            for loss in a.loss:
                for seed, link, ppm in ((s, k, e) for s in a.seeds for k in a.link
                                        for e in a.board_ppm):
                    dm.WALL_LINK = link
                    t = time.monotonic()
                    if drv in _names(True):
                        # the host loop (and the in-process board) at the command's
                        # priority, as 'hapsim run --driver haply/falcon' runs it
                        rt = RealtimePriority(a.rt_priority)
                        with rt:
                            row = (run_haply2(seed, loss, scene=a.haply2_scene,
                                              amplitude=a.haply2_amplitude)
                                   if drv == "haply2"  # else falcon
                                   else run_falcon_once(seed, loss,
                                                        scene=a.falcon_scene,
                                                        stall_ms=a.host_stall,
                                                        start_mm=a.falcon_start))
                        sched = rt.note
                    else:
                        row = run_1d(drv, seed, loss, a.duration, a.rt_priority,
                                     a.starve, a.host_stall,
                                     ppm if drv == "hapkit-serial" else None)
                        sched = row.get("scheduling")
                    if len(a.link) > 1 and drv not in _names(True):
                        row["link"] = link
                    if len(a.board_ppm) > 1 and drv == "hapkit-serial":
                        row["board_ppm"] = ppm
                    row.update(driver=drv, seed=seed, loss=loss, scheduling=sched,
                               seconds=round(time.monotonic() - t, 1), load=_load())
                    rows.append(row)
                    print(json.dumps({k: row.get(k) for k in (
                        "driver", "loss", "seed", "clock", "safety_stop", "resyncs",
                        "resync_reasons", "silences", "board_silences", "board_parser",
                        "frame_walk", "frame_bound", "stalls",
                        "excursion_true", "excursion_host", "verdict", "exit_code",
                        "error", "board_off_period", "unseen_holds", "link_verdict",
                        "tick_moved")},
                                     default=str),
                          file=sys.stderr, flush=True)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    out = {"command": command_line("tools/driver_timing.py", argv), "hogs": a.hogs,
           "starve": a.starve, "host_stall_ms": a.host_stall, "board_ppm": a.board_ppm,
           "host_watchdog": not a.no_host_watchdog, "link": a.link,
           "haply2_scene": a.haply2_scene, "haply2_amplitude": a.haply2_amplitude,
           "load_before": load_before, "load_after": _load(), "cpus": os.cpu_count(),
           "runs": normalize(rows), "summary": summarize(rows)}
    text = json.dumps(out, indent=1, default=str)
    if a.json:
        with open(a.json, "w") as f:
            f.write(text + "\n")
    print(json.dumps(out["summary"], indent=1))
    return 0


#: The keys every row has (None where a run does not give one): the docs' table reads them.
ROW_KEYS = ("driver", "loss", "seed", "clock", "safety_stop", "stop", "resyncs", "stalls",
            "excursion_true", "excursion_host", "workspace", "verdict", "within",
            "exit_code", "error", "seconds", "load", "scheduling", "board_off_period",
            "unseen_holds")


def normalize(rows):
    """Every row with every key of :data:`ROW_KEYS` (None where missing), in place.

    Parameters
    ----------
    rows : list of dict

    Returns
    -------
    list of dict
    """
    for r in rows:
        for k in ROW_KEYS:
            r.setdefault(k, None)
    return rows


#: The verdicts every summary counts, 0 where none was said (the docs name them whether or
#: not a run said them): the 1-D runs' and the n-D felt matrices'.
VERDICTS = ("measured = predicted within the stated uncertainty",
            "measured differs from predicted by more than the stated uncertainty",
            "within", "partly within", "not measurable", "differs")


def summarize(rows):
    """Per driver and loss (and link, for an A/B of ``--link``; the board's offset, of
    ``--board-ppm``): runs, safety stops, runs
    with a re-synchronisation, the most re-synchronisations, the largest excursion,
    verdicts counted, errors, the range of the host's stalls and of the commands the
    board took off its period (``stalls_range``, ``board_off_period_range``).

    Parameters
    ----------
    rows : list of dict

    Returns
    -------
    dict
        ``{"driver loss": {...}}``.
    """
    out = {}
    for r in rows:
        key = (f"{r['driver']} {r['loss']:g}" + (f" {r['link']}" if r.get("link") else "")
               + (f" {r['board_ppm']:g}ppm" if r.get("board_ppm") is not None else ""))
        s = out.setdefault(key, {
            "runs": 0, "safety_stops": 0, "runs_resynced": 0, "resyncs_max": 0,
            "excursion_true_max": None, "excursion_host_max": None,
            "longest_hold_s_max": None, "verdicts": dict.fromkeys(VERDICTS, 0),
            "errors": 0, "clock": r.get("clock")})
        s["runs"] += 1
        s["safety_stops"] += bool(r.get("safety_stop"))
        s["runs_resynced"] += bool(r.get("resyncs"))
        s["resyncs_max"] = max(s["resyncs_max"], r.get("resyncs") or 0)
        for k in ("excursion_true", "excursion_host", "longest_hold_s"):
            v = r.get(k)
            if v is not None:
                s[k + "_max"] = v if s[k + "_max"] is None else max(s[k + "_max"], v)
        v = str(r.get("verdict")).split(":")[0]
        s["verdicts"][v] = s["verdicts"].get(v, 0) + 1
        s["errors"] += bool(r.get("error")) and r.get("verdict") is None
        for k in ("stalls", "board_off_period"):
            v = r.get(k)
            if isinstance(v, int):
                lo, hi = s.get(k + "_range") or (v, v)
                s[k + "_range"] = [min(lo, v), max(hi, v)]
        _felt_ranges(s, r)
    return out


#: The felt statements the 2DIY's and the Falcon's rows carry (``deviation``,
#: ``uncertainty``, ``wire_term``: relative, per matrix), summarised by :func:`summarize`.
FELT = ("felt_stiffness", "felt_damping")


def _felt_ranges(s: dict, r: dict) -> None:
    """Into a summary entry ``s``: per felt matrix, the runs that stated it
    (``stated_k``/``stated_b``), the range of their deviation and of the uncertainty
    stated (``dev_k`` = [min, max], ``unc_k``, ...) and of the wire's term over every run
    (``wire_k``, ...), and of the estimated samples (``estimated``, the 2DIY's); the rows
    without felt figures (the 1-D drivers') add nothing."""
    dev, unc, wire = r.get("deviation"), r.get("uncertainty"), r.get("wire_term")
    if not isinstance(dev, dict) or not isinstance(unc, dict):
        return

    def widen(key, v):
        lo, hi = s.get(key) or (v, v)
        s[key] = [min(lo, v), max(hi, v)]
    for q, t in zip(FELT, "kb"):
        s.setdefault(f"stated_{t}", 0)
        if unc.get(q) is not None and dev.get(q) is not None:
            s[f"stated_{t}"] += 1
            widen(f"dev_{t}", dev[q])
            widen(f"unc_{t}", unc[q])
        w = (wire or {}).get(q)
        if w is not None and math.isfinite(w):
            widen(f"wire_{t}", w)
    if isinstance(r.get("estimated"), int):
        widen("estimated", r["estimated"])


def resummarize(path: str) -> dict:
    """A JSON this tool wrote, its ``summary`` recomputed from its ``runs`` and written
    back (the summary is a function of the runs alone: no run is taken again).

    Parameters
    ----------
    path : str
        The ``--json`` file.

    Returns
    -------
    dict
        The new summary.

    Raises
    ------
    OSError, ValueError, KeyError
        The file unreadable, not JSON, or without ``runs``.
    """
    with open(path) as f:
        out = json.load(f)
    out["summary"] = summarize(out["runs"])
    with open(path, "w") as f:
        f.write(json.dumps(out, indent=1, default=str) + "\n")
    return out["summary"]


if __name__ == "__main__":
    sys.exit(main())
