"""A Falcon run over its USB link: the firmware loaded, the legs homed, the scene's loop
closed one packet per sample, and an account of the link that says what it saw.

:func:`run_falcon` takes any link with ``line(**)`` and ``exchange(send, n, done,
timeout)``: :class:`hapsim.drivers.falcon_usb.FalconUSB` on a real Falcon (libusb) or on
the emulated one (:func:`emulated_falcon`: :class:`hapsim.emulated.falcon_device.FalconDevice`
behind an emulated FT232R, :mod:`hapsim.emulated.ftdi_usb`, under the same pyftdi code).

The loop is libnifalcon's: one packet written, its reply read, the next written (the
Falcon's firmware answers each packet; its own loop sets the pace, ~1 kHz). It ends with
:data:`ZERO_PACKETS` zero-command packets whatever ends it (the loop's end, an error,
Ctrl-C): the firmware holds the last command. The
packets carry no checksum and no sequence number: a lost or mangled reply is a missing
sample (counted, the last reading held), a byte flipped inside a nibble is another count
no host can tell from a real one. The verdict says only what the host can know:
``"ok"`` (every reply came whole and plausible, every leg homed), ``"degraded"``
(replies missing, bytes dropped realigning, implausible packets dropped: the numbers
given). Against the emulator the report adds what no real run can: each reading
compared with the count the emulated encoder had (``truth``).
"""

from __future__ import annotations

import gc
import time

import numpy as np

# the legs' workspace and envelope in a run [rad] (hapsim.drivers.falcon's): a leg beyond
# the envelope stops the loop, and the legs are braked to rest before the zero commands
# (the scene's safety.brake)
from hapsim.drivers.falcon import ENVELOPE_RAD, WORKSPACE_RAD
from hapsim.errors import DeviceError

__all__ = ["run_falcon", "emulated_falcon", "falcon_verdict", "felt_statement",
           "felt_prediction",
           "measure_felt_emulated", "reply_timeout",
           "FIRMWARE_PROBES", "REPLY_SLACK_S", "WORKSPACE_RAD", "ENVELOPE_RAD"]

#: Packets sent after the load before concluding the firmware does not run.
FIRMWARE_PROBES = 10
#: Zero-command packets sent at the end of a loop (more than a device's delay of a few
#: packets: the last of them is applied).
ZERO_PACKETS = 5
#: Periods between two of the loop's packets beyond which the host stalled: the
#: firmware, on its own clock, held the last command over them (counted in ``stalls``;
#: on a paced Falcon the verdict is "degraded" then: another loop than the scene's).
HELD_PERIODS = 2.0
#: Periods between two of the loop's packets beyond which the second may have missed the
#: firmware's tick after the first (the first's command held two ticks): its row is
#: ``late`` (:func:`run_falcon`'s ``late_rows``, cut from the felt matrices' records).
#: Measured against the emulated Falcon's own ticks at load 12 on 2 cores (1,023 rows, 419
#: ticks missed): 1.25 caught 413-414 of them, cutting ~55 rows that missed none; 2 (the
#: stalls' :data:`HELD_PERIODS`) caught 375, and a packet sent more than a period after the
#: last reply was read (certain) only 8 of 470.
SKIP_PERIODS = 1.25
#: Longest time [s] a paced Falcon (its firmware on its own clock, no watchdog published)
#: is left with a command computed from a reading older than this: the loop then sends
#: zero commands until a reply comes (``held_zero``); the 1-DoF drivers' bound
#: (:data:`hapsim.drivers.resync.HOLD_BOUND_S`).
HOLD_BOUND_S = 0.02
#: The wait [s] for a reply beyond the firmware's tick: the FT232R's latency timer as the
#: firmware load leaves it (1 ms, the last line settings of
#: :meth:`hapsim.drivers.falcon.FalconFirmwareLoader.steps`) and one full-speed USB frame
#: (1 ms). A reply later than that is a missing
#: sample (read by the next exchange if it comes, libnifalcon's runIOLoop keeping the
#: newest): the host does not wait on, the Falcon (no watchdog published) holding the last
#: command meanwhile. Before, the command waited 50 ms for a lost reply, over twice
#: :data:`HOLD_BOUND_S`.
REPLY_SLACK_S = 0.002
#: The wait [s] for each of the firmware's first answers after its load
#: (:data:`FIRMWARE_PROBES` of them): the wait each reply had before, not the loop's.
PROBE_TIMEOUT_S = 0.05
#: The most states of a scene's loop whose felt feasibility a run computes
#: (:func:`felt_prediction`): configs/delta_sphere.yaml's 12 take ~1 s of CPU (the
#: lockstep records and their statement);
#: configs/delta_mesh.yaml's 162 took 3.5 min (its 3,240-sample records' sensitivities).
FEASIBILITY_STATES = 24


def reply_timeout(rate_hz: float) -> float:
    """The loop's wait for one reply [s]: one period of the firmware's clock (the packet
    is taken at its next tick) and :data:`REPLY_SLACK_S`.

    Parameters
    ----------
    rate_hz : float
        The scene's rate [Hz] (> 0), the Falcon's packet rate.

    Returns
    -------
    float
        ``1 / rate_hz + REPLY_SLACK_S`` (3 ms at 1 kHz: below :data:`HOLD_BOUND_S`).
    """
    return 1.0 / float(rate_hz) + REPLY_SLACK_S




def emulated_falcon(scene, image: bytes, *, faults=None, unplug_after: int | None = None,
                    dup_tx: float = 0.0, seed: int = 0, **device_options):
    """An emulated Falcon behind an emulated FT232R, opened with pyftdi.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D scene with a delta device (the plant).
    image : bytes
        The firmware image the emulated loader accepts (the user's file).
    faults : hapsim.emulated.driver_mock.ByteFaults, optional
        Byte loss and bit flips on the UART, both ways.
    unplug_after : int, optional
        Bulk transfers after which the chip leaves the bus.
    dup_tx : float
        Probability that a device -> host byte comes twice.
    seed : int
        Seed of the duplication.
    **device_options
        :class:`hapsim.emulated.falcon_device.FalconDevice`'s keywords.

    Returns
    -------
    (FalconUSB, FalconDevice, VirtualFT232R)
        The link (pyftdi over the emulated chip), the device, the chip.
    """
    from hapsim.emulated.falcon_device import FalconDevice
    from hapsim.emulated.ftdi_usb import VirtualFT232R, VirtualUSB
    from hapsim.drivers.falcon_usb import FalconUSB
    dev = FalconDevice(scene, expected_image=image, **device_options)
    chip = VirtualFT232R(dev, faults=faults, unplug_after=unplug_after, dup_tx=dup_tx,
                         seed=seed)
    link = FalconUSB(backend=VirtualUSB([chip]))
    link.sink = chip.side_channel
    return link, dev, chip


def falcon_verdict(res: dict) -> dict:
    """The run's verdict from what the host saw (module notes).

    Parameters
    ----------
    res : dict
        :func:`run_falcon`'s result.

    Returns
    -------
    dict
        ``verdict`` (``"ok"`` or ``"degraded"``) and ``reason``.
    """
    d = res["decoder"]
    bad = {"replies missing": res["missing"], "bytes dropped realigning": d["skipped"],
           "implausible packets dropped": d["implausible"], "samples unhomed": res["unhomed"],
           "packets sent at zero for want of a fresh reading": res.get("held_zero", 0)}
    said = ", ".join(f"{k} {v}" for k, v in bad.items() if v)
    if res.get("paced") and res.get("stalls"):
        said = (said + "; " if said else "") + (
            f"the host stalled {res['stalls']} times (a command held up to "
            f"{res['held_max_s'] * 1e3:.1f} ms, more than {HELD_PERIODS:g} periods): the "
            "Falcon held it on its own clock, another loop than the scene's")
    if res.get("paced") and res.get("waits"):
        said = (said + "; " if said else "") + (
            f"{res['waits']} commands held more than {HELD_PERIODS:g} periods while the "
            "host waited for a reply that did not come: another loop than the scene's")
    slow = res.get("slow")
    if slow:
        said = (said + "; " if said else "") + (
            f"the loop ran at {res['packets_per_s']:.0f} packets/s, below the scene's "
            f"{res['rate_hz']:g} Hz: the Falcon held each command {slow:.1f} periods, so "
            "it rendered another loop than the scene's")
    if res.get("stopped"):
        said = (said + "; " if said else "") + (
            f"stopped at packet {res['stopped'][0]}: {res['stopped'][1]}")
    caveat = ("the packets carry no checksum: a bit flipped inside a nibble is another "
              "count, which no host can see")
    if not said:
        return {"verdict": "ok", "reason": f"every one of the {res['samples']} replies "
                f"came whole and plausible, every leg homed ({caveat})"}
    return {"verdict": "degraded", "reason": f"{said} (of {res['samples']} samples; a "
            f"missing sample holds the last reading); {caveat}"}


def felt_prediction(scene, real: bool = False, plan=None, progress=None) -> dict:
    """What a Falcon run will say of the felt matrices, predicted before its loop starts
    (issue 31 item 4): whether they can be measured through the Falcon's counts at all
    (:func:`hapsim.emulated.falcon_felt.felt_feasibility`: the run's own records and
    statement, the emulated Falcon in lockstep, at the largest hand start the scene's
    linear range allows) and, when something will not be stated, the sentence the run
    says first (``statement``).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D delta scene.
    real : bool, optional
        A real Falcon (no image: no host can start a hand, nothing is measured).
    plan : tuple, optional
        :func:`hapsim.lockstep.identification_plan` of ``scene``.
    progress : callable, optional
        ``progress(done, total)`` over the rounding's draws
        (:func:`hapsim.emulated.falcon_felt.felt_feasibility`'s).

    Returns
    -------
    dict
        The feasibility's keys (less ``worst_reading``, ``worst_command``) and
        ``statement`` (None: every statement will be made; else the sentence); or, for a
        loop of more than :data:`FEASIBILITY_STATES` states, ``verdict`` ``"not
        measured"``, ``states``, ``reason``, ``statement``. With ``real``, a feasible
        scene's ``verdict`` is ``"not measured"`` (the reason says why).

    Raises
    ------
    hapsim.errors.DeviceError
        The emulated Falcon of the lockstep records did not home.
    """
    from hapsim.emulated.falcon_felt import felt_feasibility
    from hapsim.lockstep import identification_plan
    plan = identification_plan(scene) if plan is None else plan
    if plan[0].states > FEASIBILITY_STATES:
        why = (f"the loop has {plan[0].states} states, more than the {FEASIBILITY_STATES} "
               "whose feasibility a run computes (the records' figures would take "
               "minutes): tools/falcon_felt_figures.py computes them")
        return {"verdict": "not measured", "states": int(plan[0].states), "reason": why,
                "statement": f"felt matrices not measured, said before the run: {why}"}
    f = (felt_feasibility(scene, plan) if progress is None
         else felt_feasibility(scene, plan, progress=progress))
    out = {k: v for k, v in f.items() if k not in ("worst_reading", "worst_command")}
    if real and f["verdict"] == "measurable":
        out["verdict"] = "not measured"
        out["reason"] = ("no host can start a hand on a real Falcon: the records are taken "
                         "on the emulated one (hapsim run --driver falcon without --port); "
                         "at its counts: " + f["reason"])
        out["statement"] = f"felt matrices not measured, said before the run: {out['reason']}"
    return out


def felt_statement(scene, image: bytes | None = None, *, clock: str = "wall",
                   faults=None, predicted: dict | None = None, progress=None) -> dict:
    """What a Falcon run says of the felt matrices: the prediction made before the loop
    (:func:`felt_prediction`: what the Falcon's counts let a run state at all) and, where
    something can be stated and the Falcon is the emulated one (``image`` given), their
    measurement (:func:`measure_felt_emulated` at the prediction's start); never a
    verdict the stated uncertainty does not cover. What the prediction says cannot be
    stated is not measured again (the lockstep records are the run's own).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D delta scene.
    image : bytes, optional
        The firmware image of the emulated Falcon the records are taken on; None (a real
        Falcon): no records (no host can start a hand).
    clock : {"wall", "lockstep"}
        The emulated Falcon's clock (:class:`hapsim.emulated.falcon_device.FalconDevice`).
    faults : callable, optional
        ``record index -> ByteFaults or None``, as :func:`measure_felt_emulated`.
    predicted : dict, optional
        :func:`felt_prediction`'s, made before the loop (default: made here).
    progress : callable, optional
        ``progress(done, total)`` over the records and the rounding's draws
        (:func:`measure_felt_emulated`'s).

    Returns
    -------
    dict
        ``verdict``: ``"not measurable"`` (the counts too coarse for this scene: the
        reason gives the figures), ``"not measured"`` (no hand can be started on a real
        Falcon; or the loop has more than :data:`FEASIBILITY_STATES` states, ``states``,
        and the figures are not computed in a run), or the measured verdict
        (``"within"``, ``"partly within"``, ``"differs"``, ``"not measurable"``:
        :func:`measure_felt_emulated`'s ``summary``, its keys here); ``reason``;
        ``stated_before_run`` (the prediction's sentence, when it had one); and the
        feasibility's figures (``amplitude_m``, ``stated``, ``not_stated``,
        ``lockstep``, ``count_at_handle_m``, ``worst``, ``widrow_kollar``, ``limit``,
        ``needed_amplitude_m``, ``needed_count_rad``, when computed; the measured
        summary's ``feasibility`` then holds its reason).
    """
    if predicted is None:
        predicted = felt_prediction(scene, image is None)
    out = {k: v for k, v in predicted.items() if k != "statement"}
    if predicted.get("statement"):
        out["stated_before_run"] = predicted["statement"]
    if predicted["verdict"] != "measurable" or image is None:
        return out
    # a statement the prediction excluded (beyond the limit on the complete lockstep
    # records) is not made from records the host's timing cut, which hold less: the run
    # never contradicts what it said before
    why = ("not stated, predicted before the run: the wire's term on the complete "
           "records in lockstep is beyond the limit")
    m = measure_felt_emulated(scene, image, predicted["amplitude_m"], clock=clock,
                              faults=faults, progress=progress,
                              excluded={n: why for n in predicted.get("not_stated", [])})
    out.update(m["summary"])
    out["feasibility"] = predicted["reason"]
    return out


def _number(v):
    """A JSON-able copy of a verdict's value (numpy scalars as floats, inf as None)."""
    if isinstance(v, dict):
        return {k: _number(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_number(x) for x in v]
    if isinstance(v, (bool, str)) or v is None:
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    try:
        x = float(v)
    except (TypeError, ValueError):
        return str(v)
    return x if np.isfinite(x) else None


def measure_felt_emulated(scene, image: bytes, amplitude: float, *, plan=None,
                          clock: str = "wall", faults=None, excluded=None,
                          progress=None) -> dict:
    """The felt matrices of a delta scene measured as a run takes them: the
    identification's ``2n + 1`` records (:func:`hapsim.lockstep.excitation_starts` at
    ``amplitude``, the one from rest first), each one :func:`run_falcon` over pyftdi and
    an emulated FT232R on a fresh emulated Falcon (:func:`emulated_falcon`: the firmware
    loaded, the legs homed, the hand's start, ``N`` packets of the loop), fitted and
    stated by :func:`hapsim.emulated.falcon_felt.falcon_felt_verdict`.

    On the Falcon's own clock (``clock="wall"``) the loop is paced as a real Falcon's: a
    row whose packet left more than :data:`SKIP_PERIODS` periods after the one before
    (``late_rows``: the firmware may have held the last command over a tick, the record not
    the scene's loop there) is cut as a missing reply is, with the rows its held command
    acted on (:func:`hapsim.emulated.falcon_felt.falcon_usable_rows`); a record stopped
    on the motion (a leg beyond :data:`ENVELOPE_RAD`) or by the late-stop rule leaves
    its rows after the stop missing. ``clock="lockstep"`` (named, deterministic): one
    period a packet.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D delta scene (the plant and the host's scene).
    image : bytes
        The firmware image the emulated loader accepts.
    amplitude : float
        The hand's ``a`` [m] (:func:`hapsim.emulated.falcon_felt.felt_feasibility`'s
        ``amplitude_m`` in a run).
    plan : tuple, optional
        :func:`hapsim.lockstep.identification_plan` of ``scene``.
    clock : {"wall", "lockstep"}
        The emulated Falcon's clock.
    faults : callable, optional
        ``record index -> hapsim.emulated.driver_mock.ByteFaults or None``: byte faults
        on the UART during that record's loop (the load and the homing clean).
    excluded : dict, optional
        ``{statement name: reason}``: statements the prediction before the run excluded,
        never made (:func:`hapsim.emulated.falcon_felt.falcon_felt_verdict`).
    progress : callable, optional
        ``progress(done, total)``: one unit per record, then one per draw of the
        rounding's phase (the verdict's wire term).

    Returns
    -------
    dict
        :func:`hapsim.emulated.falcon_felt.falcon_felt_verdict`'s, and ``records``
        (per record: ``missing``, ``late_rows``, ``stalls``, ``waits``, ``held_zero``,
        ``stopped``, ``link_verdict``, ``link_reason``, ``excursion_rad``: the legs'
        largest departure from the operating point read over the loop,
        ``excursion_true_rad``: the emulated legs' own from the start to the end of the
        zero commands, the free coast after the loop included), ``summary`` (JSON-able: ``verdict``,
        ``reason``, ``amplitude_m``, ``deviation``, ``uncertainty``, ``wire``,
        ``statements``, ``not_stated``, ``missing``, ``late_rows``, ``fitted_rows``,
        ``records``).

    Raises
    ------
    hapsim.errors.DeviceError
        As :func:`run_falcon` (the firmware load, the homing, the link).
    """
    from hapsim.analysis.wire_rounding import ROUNDING_DRAWS
    from hapsim.emulated.falcon_felt import falcon_felt_verdict
    from hapsim.lockstep import excitation_starts, identification_plan
    if plan is None:
        plan = identification_plan(scene)
    N = plan[2]
    runs, recs = [], []
    starts = excitation_starts(3, amplitude, scene.period)
    for i, (x0, v0) in enumerate(starts):
        f = None if faults is None else faults(i)
        link, dev, chip = emulated_falcon(scene, image, faults=f, clock=clock)
        chip.faults_on = False

        def start(dev=dev, chip=chip, f=f, x0=x0, v0=v0):
            dev.let_go(x0, v0)
            chip.faults_on = f is not None
            dev.excursion = 0.0                  # the record's, not the homing's
        try:
            res = run_falcon(scene, link, image, N, start=start, paced=clock == "wall")
        finally:
            link.close()
        q = np.array(res["joints"], float)
        # lockstep: one period a packet whatever the host's gaps
        late = np.asarray(res["late_rows"], bool) & (clock == "wall")
        q[late] = np.nan                         # cut as a missing reply (notes)
        if res["stopped"]:
            q[res["stopped"][0]:] = np.nan
        runs.append({"position": res["position"], "joints": q, "commands": res["commands"]})
        recs.append({"missing": int(res["missing"]), "late_rows": int(late.sum()),
                     "stalls": int(res["stalls"]), "waits": int(res["waits"]),
                     "held_zero": int(res["held_zero"]), "stopped": res["stopped"],
                     "link_verdict": res["verdict"], "link_reason": res["reason"],
                     "excursion_rad": float(np.nanmax(np.abs(
                         np.asarray(res["joints"], float)
                         - np.asarray(scene.device.joints, float)), initial=0.0)),
                     "excursion_true_rad": float(dev.excursion)})
        if progress is not None:
            progress(i + 1, len(starts) + ROUNDING_DRAWS)
    out = falcon_felt_verdict(scene, runs, plan, amplitude, excluded=excluded,
                              progress=None if progress is None else (
                                  lambda done, total: progress(len(starts) + done,
                                                               len(starts) + total)))
    out["records"] = recs
    out["summary"] = _number({
        "verdict": out["verdict"], "within": out["within"], "reason": out["reason"],
        "amplitude_m": amplitude,
        "deviation": out["deviation"], "uncertainty": out["uncertainty"],
        "wire": {k: out["wire"][k] for k in ("felt_stiffness", "felt_damping")},
        "statements": [{k: st.get(k) for k in ("name", "verdict", "deviation",
                                               "uncertainty", "wire")}
                       for st in out["statements"]],
        "not_stated": out["not_stated"], "missing": out["missing"],
        "late_rows": sum(r["late_rows"] for r in recs), "fitted_rows": out["fitted_rows"],
        "records": recs})
    return out


def _zero(link, timeout: float) -> int:
    """Send :data:`ZERO_PACKETS` zero-command packets (red LED); the number that went."""
    from hapsim.drivers.falcon import LED_RED, host_packet
    sent = 0
    for _ in range(ZERO_PACKETS):
        try:
            link.exchange(host_packet((0, 0, 0), LED_RED), 32, _reply_end, timeout)
        except (DeviceError, OSError):
            break
        sent += 1
    return sent


def _start_watchdog(link, paced: bool):
    """The host's watchdog for the loop over a Falcon on its own clock (its firmware
    holds the last command: no watchdog published), writing a zero command through the
    link's :meth:`~hapsim.drivers.falcon_usb.FalconUSB.watchdog_sink` after the host's
    silence of :data:`HOLD_BOUND_S`; or None and the reason."""
    if not paced:
        return None, "a lockstep Falcon: its time is the packets'"
    sink = getattr(link, "watchdog_sink", None)
    if sink is None:
        return None, "the link gives the watchdog nothing to write to"
    from hapsim.drivers.falcon import LED_RED, host_packet
    from hapsim.drivers.torque_watchdog import start_watchdog
    try:
        where = sink()
    except OSError as exc:
        return None, str(exc)
    return start_watchdog(f"the Falcon's {where[0]} file", host_packet((0, 0, 0), LED_RED),
                          HOLD_BOUND_S, sink=where)


def _close_watchdog(wd, why, rows) -> dict:
    """The watchdog disarmed and stopped; its report, with ``rows`` (the exchanges
    before which it had written)."""
    from hapsim.drivers.torque_watchdog import watchdog_report
    if wd is None:
        return watchdog_report(None, why)
    wd.arm(False)
    wd.close()
    rep = watchdog_report(wd, why)
    rep["rows"] = list(rows)
    return rep


def _reply_end(b: bytes) -> bool:
    return len(b) >= 8 and b[-1] == 0x3E


def run_falcon(scene, link, image: bytes, samples: int, *, truth=None, progress=None,
               timeout: float | None = None, before_loop=None,
               homing_limit: int = 20000, paced: bool = False,
               load_attempts: int = 3, start=None) -> dict:
    """Load the firmware, home the legs, run the scene's loop over ``samples`` packets.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 3-D scene with a delta device.
    link : object
        ``line``, ``exchange`` (:class:`hapsim.drivers.falcon_usb.FalconUSB`).
    image : bytes
        The firmware image.
    samples : int
        Packets of the loop.
    truth : callable, optional
        ``() -> (3,) counts`` the emulated encoders hold after each exchange
        (:meth:`hapsim.emulated.falcon_device.FalconDevice.counts`); compared with the
        readings.
    progress : callable, optional
        ``progress(k)`` after each stage (firmware, homing, loop).
    timeout : float, optional
        Wait for each reply [s]; default :func:`reply_timeout` of the scene's rate (the
        Falcon holds the last command while the host waits: a lost reply must not keep
        it longer than :data:`HOLD_BOUND_S`).
    before_loop : callable, optional
        Called once the legs are homed, before the loop (the tests switch faults on).
    homing_limit : int
        Most homing packets (~20 s at the firmware's ~1 kHz).
    load_attempts : int
        Firmware loads tried when the loader's echo differs or stops (each from the
        loader's restart by DTR, as libnifalcon's ``loadFirmware(retries)``).
    paced : bool
        A real Falcon (its firmware on its own clock): a loop slower than 0.9 times the
        scene's rate is ``slow`` (each command held that many periods: another loop
        than the scene's) and the verdict says so; the emulator steps one period per
        packet, whatever the pace.
    start : callable, optional
        The hand's start of an identification record (the emulated Falcon's
        :meth:`~hapsim.emulated.falcon_device.FalconDevice.let_go`), called once the legs
        are homed, after ``before_loop``, just before the loop's first packet
        (:func:`hapsim.emulated.falcon_device.drive_falcon`); the loop's reply decoder
        then starts afresh (the
        start is a jump from the homing's last counts: its first reply taken unchecked,
        the steps after it checked), as :func:`hapsim.emulated.falcon_felt.
        measure_felt_falcon` does.

    Returns
    -------
    dict
        ``firmware`` (:func:`hapsim.drivers.falcon_usb.load_firmware_link`, with
        ``attempts``), ``homing``
        (packets), ``samples``, ``missing``, ``unhomed``, ``decoder`` (``frames``,
        ``skipped``, ``implausible``), ``packets_per_s`` (the loop's pace),
        ``position`` (N, 3) [m] (NaN where missing), ``commands`` (N, 3), ``truth`` (with
        ``truth``: ``compared``, ``exact``, ``max_error_counts``), ``rate_hz`` (the
        scene's), ``slow`` (periods each command was held, when ``paced`` and slow; else
        None), ``zeroed`` (zero-command packets sent after the loop), ``stalls`` (gaps
        of more than :data:`HELD_PERIODS` periods between two of the loop's packets after
        a reply that came: the host stalled, the firmware held the last command),
        ``waits`` (such gaps after a reply that did not come before ``timeout``: the host
        waited for it), ``held_max_s`` (the longest
        gap [s]), ``paced``, ``stopped`` (None, or the packet and the reason of a stop on
        the motion: a leg beyond :data:`ENVELOPE_RAD`, a paced host too late), ``brake``
        (None, or the braking after that stop,
        :func:`hapsim.emulated.falcon_device.brake_legs`), ``joints`` (N, 3) [rad] read
        (NaN where missing), ``late_rows`` (N,) bool (the rows whose packet left more
        than :data:`SKIP_PERIODS` periods after the one before, or more than one after the
        previous reply was read: the firmware's tick may have passed without a packet,
        the last command held over it, so the row not one period after the last),
        ``error`` (None, or the DeviceError's ``type`` and ``message`` when the Falcon
        went away after the loop's first packet: the rows up to it kept, ``stopped``
        "device lost: ..."), ``verdict``, ``reason``.

    Raises
    ------
    DeviceError
        The firmware load failed (what to check), the legs did not home, the link failed
        or the Falcon went away (after how many packets) before the loop's first packet.
    """
    from hapsim.drivers.falcon_usb import load_firmware_link
    from hapsim.errors import FirmwareEchoError
    for attempt in range(1, load_attempts + 1):
        try:
            fw = load_firmware_link(link, image)
            break
        except FirmwareEchoError as exc:
            # libnifalcon's loadFirmware(retries): DTR's edge restarts the loader
            if attempt == load_attempts:
                raise FirmwareEchoError(f"{exc} ({attempt} attempts, each from the "
                                        "loader's restart)") from None
    fw["attempts"] = attempt
    if progress:
        progress(1)
    if timeout is None:
        timeout = reply_timeout(scene.rate_hz)
    # as every real-time loop of hapsim (hapsim.host.loop): no collector pause while the
    # Falcon runs on its own clock (a full collection in a process with numba and scipy
    # loaded took 40 ms, forty periods of a command held), collected here, before the
    # first packet, while the firmware holds none
    gc_was = gc.isenabled()
    if paced:
        gc.collect()
    gc.disable()
    try:
        return _probe_home_drive(link, image, scene, samples, fw, truth, timeout, paced,
                                 homing_limit, before_loop, progress, start)
    finally:
        if gc_was:
            gc.enable()


def _probe_home_drive(link, image, scene, samples, fw, truth, timeout, paced,
                      homing_limit, before_loop, progress, start=None):
    """:func:`run_falcon` after the firmware load: the probes, the homing, the loop."""
    from hapsim.emulated.falcon_device import drive_falcon, home
    from hapsim.drivers.falcon import LED_BLUE, LED_GREEN, ticks_of
    sent = [0]
    truths = []
    # the loop's exchanges on the host's clock: a gap of more than HELD_PERIODS periods
    # between two packets is a host stall (the firmware held the last command over it)
    stamps = []
    # when each exchange returned (its reply read, or its wait over)
    replied = []
    # whether each exchange's reply came before its timeout: a gap after one that did
    # not is the host waiting for a lost reply, not the host stalled
    answered = []

    # the host's watchdog (paced: a Falcon on its own clock), armed over the loop
    wd = [None]
    wd_rows = []                            # exchanges before which it had written
    wd_next = [False]                       # it wrote during the last exchange

    drain = getattr(link, "read", None)
    # the firmware's first answers after its load are waited for as long as the load's
    # own (PROBE_TIMEOUT_S: a firmware still starting is not one that does not run); from
    # the homing on, a reply is waited for ``timeout`` (reply_timeout: the Falcon holds
    # the last command meanwhile)
    wait = [max(timeout, PROBE_TIMEOUT_S)]

    def feed(packet: bytes) -> bytes:
        sent[0] += 1
        stamps.append(time.perf_counter())
        try:
            # what came after the last exchange stopped waiting (a reply later than
            # ``timeout``) is read first, with this packet's answer after it: the decoder
            # takes the newest reply. libnifalcon's runIOLoop reads every byte available
            # and keeps the last whole packet (FalconFirmwareNovintSDK.cpp, formatOutput
            # and runIOLoop). Before, a late reply was read as the next packet's answer,
            # and every reply after it one packet late: a loop with a period more delay,
            # which ran the emulated legs 45-110 rad beside two CPU-bound processes
            late = drain(64, 0.0) if drain is not None and sent[0] > 1 else b""
            if wd[0] is not None:
                holds = not commands_zero(packet)
                if wd[0].beat() or wd_next[0]:
                    wd_rows.append(len(stamps) - 1)
                wd_next[0] = False
                if holds:
                    # holding from before the write: a host stopped while it waits for
                    # the reply leaves this packet's command held (the flag set after
                    # the exchange missed a stall there after a zero packet)
                    wd[0].hold(True)
            # a reply is 16 bytes ending in '>': read on to its end (a duplicated byte
            # would otherwise leave the next reply one byte behind, read one packet late)
            began = time.monotonic_ns() if wd[0] is not None else 0
            ans = late + link.exchange(packet, 32, _reply_end, wait[0])
            if wd[0] is not None:
                wd[0].hold(holds, began)    # (the silence from the write's start)
                if wd[0].take():
                    # written while this exchange ran: its reply may be the one read, or
                    # come after this exchange stopped reading and be the next one's
                    if not wd_rows or wd_rows[-1] != len(stamps) - 1:
                        wd_rows.append(len(stamps) - 1)
                    wd_next[0] = True
            answered.append(_reply_end(ans))
            replied.append(time.perf_counter())
        except DeviceError as exc:
            raise DeviceError(f"{exc} (after {sent[0] - 1} packets since the firmware "
                              "load)") from None
        if truth is not None:
            truths.append(tuple(truth()))
        return ans

    # the firmware answers packets (libnifalcon's isFirmwareLoaded): else the image was
    # not the Falcon's firmware, or the load did not take
    from hapsim.drivers.falcon import DevicePacketDecoder, commands_zero, host_packet
    dec = DevicePacketDecoder()
    if not any(dec.feed(feed(host_packet((0, 0, 0)))) for _ in range(FIRMWARE_PROBES)):
        raise DeviceError(f"the Falcon answered none of {FIRMWARE_PROBES} packets after the "
                          "firmware load: is the image the Novint firmware for the Falcon "
                          "(libnifalcon's test firmware answers no packets)? Unplug and "
                          "plug the Falcon and load again")
    wait[0] = timeout
    try:
        homing = home(feed, LED_BLUE, limit=homing_limit, decoder=dec)
    except DeviceError as exc:
        raise DeviceError(f"{exc}: move the grip slowly in and out, all the way, while "
                          "homing (each leg finds its encoder index)") from None
    if progress:
        progress(1)
    truths.clear()
    for k in dec.stats:                     # the loop's account from here
        dec.stats[k] = 0
    if before_loop is not None:
        before_loop()
    if start is not None:
        dec = DevicePacketDecoder()
    stamps.clear()
    replied.clear()
    answered.clear()
    watchdog = None
    wd_why = None
    try:
        wd[0], wd_why = _start_watchdog(link, paced)
        if wd[0] is not None:
            wd[0].arm(True)
        # the loop's own time, its packets_per_s: not the watchdog's start (a process of
        # its own, 25-100 ms, which made a 300-packet record "slow") nor the zero packets
        t0 = time.perf_counter()
        # a stop on the motion (the legs out of their envelope, a paced host too late)
        # brakes the legs before the zero commands below, unless the scene says not to
        res = drive_falcon(feed, scene, samples, leds=LED_GREEN, decoder=dec,
                           hold_bound_s=HOLD_BOUND_S if paced else None,
                           late_stop=paced, envelope_rad=ENVELOPE_RAD,
                           brake=scene.safety.brake, start=start)
        dt = time.perf_counter() - t0
    finally:
        # the firmware holds the last command (no watchdog is published): zero torque
        # at every end, a normal one, an error or Ctrl-C (a device gone takes none)
        try:
            zeroed = _zero(link, timeout)
        finally:
            # (stopped whatever ends the zero packets: Ctrl-C there too)
            watchdog = _close_watchdog(wd[0], wd_why, wd_rows)
            wd[0] = None
    if progress:
        progress(1)
    out = {"firmware": fw, "homing": homing, "samples": int(samples),
           "missing": res["missing"], "unhomed": res["unhomed"], "decoder": res["decoder"],
           # (every packet of the loop's time: the priming one, the loop's, a braking's;
           # (samples + 1) before, which overstated the pace of a loop stopped early)
           "packets_per_s": len(stamps) / dt if dt > 0 else None,
           "position": res["position"], "commands": res["commands"], "truth": None,
           "rate_hz": float(scene.rate_hz), "slow": None, "zeroed": zeroed,
           "held_zero": res["held_zero"], "stopped": res["stopped"],
           "brake": res["brake"], "joints": res["joints"], "watchdog": watchdog,
           "error": res["error"]}
    gaps = np.diff(np.asarray(stamps)) * scene.rate_hz     # [periods]
    # sample k reads the reply of exchange k (stamps[0]: the loop's priming packet). The
    # firmware takes a packet at its next tick, so packet k missed a tick (the command of
    # packet k - 1 held over two: row k not one period after row k - 1) when it left more
    # than a period after the tick packet k - 1 took, which lies between that packet's
    # sending and its reply's reading: certainly when it left more than a period after
    # that reply was read, possibly when it left more than a period after packet k - 1.
    # Rows whose packet left more than SKIP_PERIODS after the last are cut, and those
    # certain ones (module constants: the rule measured against the emulator's ticks)
    late = np.zeros(int(samples), bool)
    sent_after = (np.asarray(stamps[1:]) - np.asarray(replied[:len(stamps) - 1])) \
        * scene.rate_hz                                   # [periods]
    m = min(sent_after.size, gaps.size, late.size - 1)
    if m > 0:
        late[1:m + 1] = (gaps[:m] > SKIP_PERIODS) | (sent_after[:m] > 1.0)
    out["late_rows"] = late
    # gap k follows exchange k: after a reply that never came (lost bytes) the host
    # waited its timeout for it; after one that came, a long gap is the host's own
    waited = ~np.asarray(answered[:gaps.size], bool)
    out["stalls"] = int(np.sum((gaps > HELD_PERIODS) & ~waited))
    out["waits"] = int(np.sum((gaps > HELD_PERIODS) & waited))
    out["held_max_s"] = float(gaps.max() / scene.rate_hz) if gaps.size else 0.0
    pps = out["packets_per_s"]
    if paced and pps and pps < 0.9 * scene.rate_hz:
        out["slow"] = scene.rate_hz / pps
    out["paced"] = bool(paced)
    if truth is not None:
        # sample k reads the reply of exchange k (exchange 0 primes the loop)
        read = ~np.isnan(res["joints"][:, 0])
        # a reply read after the watchdog wrote may answer its zero command: the counts
        # of an earlier tick than the truth taken after this exchange (not compared)
        read[[k for k in wd_rows if k < read.size]] = False
        err = [max(abs(ticks_of(np.degrees(res["joints"][k, i])) - truths[k][i])
                   for i in range(3)) for k in np.flatnonzero(read)]
        out["truth"] = {"compared": int(read.sum()), "exact": int(sum(e == 0 for e in err)),
                        "max_error_counts": int(max(err)) if err else None}
    out.update(falcon_verdict(out))
    return out
