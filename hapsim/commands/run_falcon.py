"""``hapsim run SCENE --driver falcon --firmware FILE [--port URL]``: a 3-D delta scene's
loop closed on a Novint Falcon over its USB link (pyftdi), or, without ``--port``, on the
emulated Falcon behind an emulated FT232R under the same pyftdi code
(:mod:`hapsim.pipeline.falcon_run`)."""

from __future__ import annotations

import json
import sys

import numpy as np

from hapsim.braking import brake_text
from hapsim.drivers.torque_watchdog import watchdog_text
from hapsim.errors import ConfigError

__all__ = ["run_falcon_command", "DEFAULT_PACKETS"]

#: Packets of the loop when ``--packets`` is not given (~1 s at the Falcon's ~1 kHz).
DEFAULT_PACKETS = 1000

#: Options a Falcon run refuses (flag, attribute, why).
_REFUSED = (("--baud", "baud", "the Falcon's rates are its loader's and firmware's"),
            ("--lockstep", "lockstep", "the Falcon's loop is one packet per sample "
             "already: the firmware answers each packet"),
            ("--faults", "faults", "the Falcon's hostile streams are injected by its "
             "emulated FT232R in the tests (tests/test_falcon_usb.py)"),
            ("--amplitude", "amplitude", "the run's hand starts are the largest the "
             "scene's linear range allows (the felt matrices' feasibility: the Falcon's "
             "counts need them; docs/devices.md)"))


#: What the emulated Falcon loads without ``--firmware``: its loader takes any non-empty
#: image (:class:`hapsim.emulated.falcon_device.FalconDevice`, ``expected_image`` None);
#: a real Falcon needs Novint's.
STAND_IN_IMAGE = b"hapsim: a stand-in for the Novint firmware image (emulated Falcon)"


def _image(path, emulated: bool = False) -> bytes:
    """The firmware image to load: the file ``path``; without one, on the emulated
    Falcon, :data:`STAND_IN_IMAGE` (said on stderr).

    Raises
    ------
    ConfigError
        No file for a real Falcon, an unreadable or empty one (key ``--firmware``).
    """
    if not path and emulated:
        print("hapsim run: no --firmware: the emulated Falcon loads a stand-in image (a "
              "real Falcon needs the Novint image: --firmware FILE)", file=sys.stderr,
              flush=True)
        return STAND_IN_IMAGE
    if not path:
        raise ConfigError("--driver falcon needs --firmware FILE on a real Falcon: the "
                          "Novint firmware image it loads at each power-up (hapsim does "
                          "not ship it: take it from the Novint SDK, or libnifalcon's "
                          "firmware/ folder); without --port the emulated Falcon takes "
                          "a stand-in", key="--firmware")
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise ConfigError(f"cannot read the firmware image: {exc.strerror}", file=path,
                          key="--firmware") from None
    if not data:
        raise ConfigError("the firmware image is empty", file=path, key="--firmware")
    return data


def run_falcon_command(args) -> int:
    """Run a delta scene on the Falcon (module notes).

    Parameters
    ----------
    args : argparse.Namespace
        ``scene``, ``port`` (an ``ftdi://`` URL or None: the emulated Falcon),
        ``firmware`` (the image's path), ``packets``, ``allow_unstable``, ``json``.

    Returns
    -------
    int
        0 when the loop ran (verdict ``ok`` or ``degraded``, said; the felt matrices'
        statement beside it, :func:`hapsim.pipeline.falcon_run.felt_statement`: on the
        emulated Falcon, where its counts allow, measured; what they cannot state is said
        on stderr before the loop, :func:`hapsim.pipeline.falcon_run.felt_prediction`,
        and is no device fault); 1 when the loop stopped on the motion (a leg beyond its
        envelope, the host too late: a safety stop, as every run's) or the Falcon was lost
        in it (its rows up to the loss reported, the error on stderr after the report,
        ``error`` in ``--json``), the device failed before the loop (not found, no
        permission, the loader's handshake, unplugged: the message says what to check)
        or the loop is unstable without ``--allow-unstable``.

    Raises
    ------
    ConfigError
        No or an unreadable ``--firmware``, a refused option, a bad ``--port``, a scene
        that is not 3-D with a delta device (exit 2).
    """
    from hapsim.pipeline.falcon_run import (emulated_falcon, felt_prediction, felt_statement,
                                            run_falcon)
    from hapsim.drivers.falcon_usb import FalconUSB, parse_url
    from hapsim.errors import DeviceError
    from hapsim.outputs import say_error_after
    from hapsim.progress import Progress
    from hapsim.scene import load_scene_nd
    from hapsim.pipeline.options import command_line_fields
    defaults = {f.name: f.metadata["cli"]["cli_default"] for f in command_line_fields()}
    for flag, attr, why in _REFUSED:
        v = getattr(args, attr, None)
        if v not in (None, False, "") and v != defaults.get(attr):
            raise ConfigError(f"--driver falcon does not take {flag}: {why}", key=flag)
    image = _image(getattr(args, "firmware", None), emulated=args.port is None)
    if args.port is not None:
        parse_url(args.port)                      # a bad URL is exit 2, before any USB
    scene = load_scene_nd(args.scene)
    if scene.dimension != 3 or scene.device is None or scene.device.kind != "delta":
        raise ConfigError("--driver falcon drives a 3-D scene whose device is a delta "
                          "(configs/delta_sphere.yaml, delta_mesh.yaml)", file=scene.path,
                          key="device.kind")
    from hapsim.api import stable_prediction_nd
    stable_prediction_nd(scene, args.allow_unstable, "--allow-unstable")   # refused if not
    packets = DEFAULT_PACKETS if getattr(args, "packets", None) is None else args.packets
    emulated = args.port is None
    # before the loop: what the Falcon's counts let this run state of the felt matrices
    # (the run's own records and statement, the emulated Falcon in lockstep and the
    # rounding's draws: ~1 s of CPU); what will not be stated is said first, with
    # the reason (issue 31 item 4), and the run goes on: exit 0, not a device fault
    try:
        with Progress(1, "run (Falcon: the felt matrices' feasibility, the emulated Falcon "
                      "in lockstep and the rounding's draws)", unit="steps") as bar:
            predicted = felt_prediction(scene, real=not emulated, progress=bar.update)
            bar.update(bar.total)
    except DeviceError as exc:       # exit 1: cli's error line, --json's error object
        raise DeviceError(f"the felt matrices' feasibility: {exc}") from exc
    if predicted.get("statement"):
        print(f"hapsim run: {scene.path}: {predicted['statement']}; the run goes on (exit "
              "code 0: not a device fault)", file=sys.stderr, flush=True)
    link = truth = None
    try:
        if emulated:
            link, dev, _ = emulated_falcon(scene, image)
            truth = dev.counts
        else:
            link = FalconUSB(args.port)
        with Progress(3, "run (Falcon: firmware, homing, loop)", unit="stages") as bar:
            # the emulated Falcon keeps its own time (its firmware's ticks) unless
            # lockstep: then it is paced as a real one is
            from hapsim.host.realtime import RealtimePriority
            paced = not emulated or dev.clock == "wall"
            # a paced loop at SCHED_FIFO where permitted, as every real-time loop of
            # hapsim's: the firmware does not wait for a descheduled host (in process,
            # the emulated Falcon's clock with it)
            rt = RealtimePriority(max(int(getattr(args, "rt_priority", 0) or 0), 0)
                                  if paced else 0)
            with rt:
                res = run_falcon(scene, link, image, packets, truth=truth,
                                 progress=bar.update, paced=paced)
            res["scheduling"] = rt.note
    finally:
        if link is not None:
            link.close()
    # the felt matrices: where the prediction says the Falcon's counts state something,
    # on the emulated Falcon, measured: the identification's records, each from a hand's
    # start on a fresh emulated Falcon on the same clock (~7 x 0.3 s)
    lost = res["error"]
    if lost is not None:
        # the Falcon went away in the loop: its rows up to the loss are reported, the
        # felt matrices' records are not taken (the run ended there)
        felt = {"verdict": "not measurable",
                "reason": "the Falcon was lost in the loop: no records were taken"}
    else:
        try:
            with Progress(1, "run (Falcon: the felt matrices' records and the rounding's "
                          "draws)", unit="steps") as bar:
                felt = felt_statement(scene, image if emulated else None,
                                      clock=dev.clock if emulated else "wall",
                                      predicted=predicted, progress=bar.update)
        except DeviceError as exc:   # exit 1: cli's error line, --json's error object
            raise DeviceError(f"the felt matrices' records: {exc}") from exc
    # a stop on the motion (a leg beyond the envelope, the host too late) or the Falcon
    # lost: exit 1 after the report, as every run's
    code = 1 if res["stopped"] is not None else 0
    where = ("the emulated Falcon (an emulated FT232R under pyftdi's code)" if emulated
             else f"the Falcon at {args.port}")
    pos = res["position"]
    taken = pos[~np.isnan(pos[:, 0])]
    travel = (float(np.max(np.linalg.norm(taken - taken[0], axis=1)))
              if len(taken) else None)
    out = {"scene": scene.path, "dof": 3, "driver": "falcon", "emulated": emulated,
           "port": args.port, "firmware_bytes": res["firmware"]["bytes"],
           "firmware_chunks": res["firmware"]["chunks"],
           "loader_checks": res["firmware"]["checks"],
           "firmware_attempts": res["firmware"]["attempts"], "homing_packets": res["homing"],
           "packets": res["samples"], "packets_per_s": res["packets_per_s"],
           "rate_hz": res["rate_hz"], "slow": res["slow"],
           "missing": res["missing"], "unhomed": res["unhomed"],
           "skipped_bytes": res["decoder"]["skipped"],
           "implausible": res["decoder"]["implausible"], "truth": res["truth"],
           "travel_m": travel,
           "max_command": int(np.abs(res["commands"]).max()) if packets else 0,
           "felt_matrices": felt, "scheduling": res["scheduling"],
           # a stop on the motion and the braking after it (hapsim.braking; None: none)
           "stopped": res["stopped"], "brake": res["brake"],
           # the host's watchdog over the loop (its firmware holds the last command)
           "watchdog": res["watchdog"],
           "verdict": res["verdict"], "reason": res["reason"],
           **({} if lost is None else {"error": lost})}
    if args.json:
        print(json.dumps(out))
        say_error_after("run", lost)
        return code
    o = sys.stdout
    print(f"{scene.path}: the Novint Falcon's bytes over USB (pyftdi), {where}", file=o)
    print(f"  firmware: {out['firmware_bytes']} bytes in {out['firmware_chunks']} chunks, "
          f"each echoed byte for byte (loader answered check {out['loader_checks']}; "
          f"load attempt {out['firmware_attempts']})", file=o)
    print(f"  homing: {out['homing_packets']} packets until all three legs reported homed",
          file=o)
    rate = out["packets_per_s"]
    print(f"  loop: {packets} packets, one per sample, at {rate:.0f} packets/s ("
          + ("the emulated firmware answers each packet at its next tick, on its own "
             "clock" if emulated and res["paced"] else "the emulator answers at once and "
             "steps one period per packet: the host's own pace" if emulated
             else "the Falcon's replies and the host set the pace")
          + f"; the scene's rate {res['rate_hz']:g} Hz; host loop scheduling: "
          f"{res['scheduling']})", file=o)
    print(f"  replies missing {out['missing']}, bytes dropped realigning "
          f"{out['skipped_bytes']}, implausible packets dropped {out['implausible']}, "
          f"samples unhomed {out['unhomed']}", file=o)
    t = res["truth"]
    if t is not None:
        print(f"  readings against the emulated encoders: exact in {t['exact']} of the "
              f"{t['compared']} samples read"
              + (f" (largest difference {t['max_error_counts']} counts)"
                 if t["max_error_counts"] else ""), file=o)
    if travel is not None:
        print(f"  handle travel {travel * 1e3:.3f} mm from its first reading; largest motor "
              f"command {out['max_command']} counts", file=o)
    print("  " + watchdog_text(res["watchdog"], "the zero command"), file=o)
    if res["brake"]:
        print("  " + brake_text(res["brake"], "N m s/rad", "rad/s"), file=o)
    if "records" in felt:
        d, u = felt["deviation"] or {}, felt["uncertainty"] or {}
        print(f"  felt matrices measured: {len(felt['records'])} records of the hand let go "
              f"{felt['amplitude_m'] * 1e3:.2f} mm from rest, each on a fresh emulated "
              f"Falcon; replies missing {felt['missing']}, rows after a host stall "
              f"{felt['late_rows']} (both cut)", file=o)
        for q in ("felt_stiffness", "felt_damping"):
            dv, uc = d.get(q), u.get(q)
            print(f"    {q.replace('_', ' ')}: measured - predicted "
                  + ("-" if dv is None else f"{dv:.3g}") + " of the predicted, stated "
                  "uncertainty " + ("none (not measurable)" if uc is None else f"{uc:.3g}"),
                  file=o)
    print(f"  felt matrices: {felt['verdict']}: {felt['reason']}", file=o)
    print(f"  verdict: {res['verdict']}: {res['reason']}", file=o)
    say_error_after("run", lost)        # the report first, then why the loop ended
    return code
