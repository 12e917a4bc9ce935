"""The report of a run: :func:`build_report` gathers the dict that
:func:`hapsim.pipeline.runner.run_scene` returns (the same fields as ``hapsim run --json``)
from the run's steps; :func:`format_report` turns it into the compact, aligned lines
``hapsim run`` prints. Gathering and formatting only: nothing here runs, measures or
decides."""

from __future__ import annotations

from typing import TYPE_CHECKING

from hapsim.analysis.prediction import port_links
from hapsim.drivers import DEFAULT, axis_units, in_axis_units, run_units
from hapsim.drivers.urlhandler import is_emulated
from hapsim.pipeline.run_types import Connection, LoopRun, PreparedRun
from hapsim.pipeline.startup import process_start
from hapsim.braking import brake_text
from hapsim.kernels.late_growth import LATE_GROWTH_SLACK, LATE_GROWTH_STOP
from hapsim.errors import dash

if TYPE_CHECKING:
    from hapsim.pipeline.options import RunOptions

__all__ = ["build_report", "run_failed", "device_clock_warning", "format_report", "loss_lines",
           "safety_context", "verdict_summary"]


#: A device on a port whose ticks run this many times faster than the wall clock in a run
#: the host takes for real time is paced by the FORCEs (an emulated board or mock in
#: lockstep): a real-time device ticks at its rate or, descheduled, slower.
FAST_CLOCK_RATIO = 1.25


def device_clock_warning(ticks: int, rate_hz: float, armed_at: float | None,
                         ended_at: float | None, real_time: bool) -> tuple:
    """How fast the device ticked against the wall clock, and the warning when a run taken
    for real time was in fact paced by the FORCEs.

    A device that waits for each FORCE (``hapsim mock --lockstep``, the emulated Hapkit
    board without ``--realtime``: ``hapsim mock --firmware --lockstep``) ticks as fast as the
    host answers, 1.7x real time and more; ``hapsim run --port`` without ``--lockstep`` then
    counts its late ticks, takes real-time priority and silence limits for a device that has
    none. The ratio is ``ticks / rate_hz`` over the wall time from arming (CONFIG) to the
    loop's end; a real-time device's is at most 1 (a start-up, a missed tick make it less).

    Parameters
    ----------
    ticks : int
        Samples the loop ran.
    rate_hz : float
        The scene's rate [Hz].
    armed_at, ended_at : float or None
        The loop's arming and end on ``time.monotonic`` [s].
    real_time : bool
        The run took the device for a real-time one (framed protocol over a port, neither
        ``--lockstep`` nor ``--host-clocked``): only then is a fast clock warned about.

    Returns
    -------
    tuple of (float or None, str or None)
        The ratio (None when not measurable: under 0.2 s of ticks, or no times) and the
        warning (None unless ``real_time`` and the ratio exceeds :data:`FAST_CLOCK_RATIO`).
    """
    if not armed_at or ended_at is None or ended_at <= armed_at or ticks < 0.2 * rate_hz:
        return None, None
    ratio = ticks / rate_hz / (ended_at - armed_at)
    if not real_time or ratio <= FAST_CLOCK_RATIO:
        return ratio, None
    return ratio, (f"the device ticked {ratio:.2f}x faster than the wall clock: it is paced "
                   "by the FORCEs (an emulated board or a mock in lockstep, e.g. 'hapsim mock "
                   "--firmware --lockstep'), not real time; run with --lockstep (late ticks, "
                   "real-time priority and the lost-device timeout do not apply to it), or "
                   "start the device in real time (without --lockstep)")


def build_report(prep: PreparedRun, conn: Connection, run: LoopRun, opts: RunOptions,
                 measured: dict, tel_info: dict | None) -> dict:
    """Step 6: the report dict of :func:`hapsim.pipeline.runner.run_scene` (see there for its
    keys).

    Parameters
    ----------
    prep, conn, run, opts
        The results of the earlier steps and the options.
    measured : dict
        :func:`hapsim.pipeline.measure.identify_run`'s result.
    tel_info : dict or None
        The telemetry file's description.

    Returns
    -------
    dict
    """
    scene, res, cfg, tr = prep.scene, run.res, conn.cfg, conn.tr
    transport, mock_report = opts.transport, run.mock_report
    plinks = port_links(scene)
    virtual = {"links": [{"link": lk.name, "K": lk.stiffness, "B": lk.damping}
                         for lk in scene.links]}
    if plinks:
        virtual.update(link=plinks[0].name, K=plinks[0].stiffness, B=plinks[0].damping)
    hello = res.hello
    clock_ratio, clock_warning = device_clock_warning(
        res.samples, scene.rate_hz, getattr(run.loop, "armed_at", None),
        getattr(run, "ended_at", None),
        real_time=(transport == "serial" and opts.port is not None and not opts.lockstep
                   and not opts.host_clocked and opts.driver is None))
    loop_info = {
        "mode": "host-clocked" if opts.host_clocked else "device-clocked",
        "loop": "compiled" if getattr(run.loop, "compiled", False) else "python",
        # --loop compiled asked but the Python loop ran: why (None otherwise)
        "python_reason": getattr(run.loop, "python_reason", None),
        "compiled_samples": getattr(run.loop, "compiled_samples", 0),
        # the first sample's moment (CONFIG sent), on time.monotonic (start-up benchmark)
        "armed_monotonic_s": getattr(run.loop, "armed_at", None),
        # start-up: the first armed STATE, seconds after this process started
        "first_sample_s": _since_start(getattr(run.loop, "first_state_at", None), opts),
        "lockstep": bool(opts.lockstep),
        # the device's protocol (a driver's mock answers each command: paced by the host)
        "protocol": opts.protocol,
        # what the host knows of the clock: its own (host-clocked), the embedded mock's
        # (real time), or a device on a port that sets the pace, real time or not (a
        # `hapsim mock --lockstep` behind --port is paced by the FORCEs: HELLO does not say)
        "pace": ("lockstep" if opts.lockstep else "real-time"
                 if opts.host_clocked or transport != "serial" or opts.port is None
                 else "device-paced"),
        # the device's ticks per second of the wall clock, in ticks of the scene's rate
        # (a device paced by the FORCEs runs as fast as the host answers): see
        # device_clock_warning
        "device_clock_ratio": clock_ratio,
        "warnings": [w for w in (clock_warning, prep.pred.get("late_force_warning"),
                                 prep.pred.get("missing_reply_warning")) if w],
        "transport": transport if transport != "pty" else
        ("embedded mock on an emulated link" if is_emulated(tr.info.get("port"))
         else "embedded mock on a pty"),
        "port": tr.info.get("port"), "baud": tr.info.get("baud"),
        "rate_hz": scene.rate_hz, "ticks": res.samples,
        "requested": prep.n_samples or None, "open_ended": not prep.n_samples,
        "late": res.late, "missed": res.missed, "estimated": res.estimated,
        "overruns": res.overruns,
        "clamped": res.clamped, "skipped": res.skipped, "turnaround_us": res.turnaround_us,
        "ping_rtt_us": res.ping_rtt_us,
        "low_latency": bool(tr.info.get("low_latency")),
        "scheduling": conn.rt.note,
        "low_latency_note": tr.info.get("low_latency_note", ""),
        "stop_reason": res.stop_reason, "safety_stop": res.safety_stop, "state": res.state,
        "lost_timeout_s": cfg.lost_timeout if cfg.lost_timeout is not None
        else cfg.watchdog_us * 1e-6,
        "decoder": res.decoder,
        "bad_frames": res.bad_frames, "bad_frames_seen": res.bad_frames_seen,
        "device": None if hello is None else {
            "device_id": hello.device_id, "force_limit": hello.force_limit,
            "native_rate_hz": hello.native_rate_hz},
        "mock": mock_report,
        # a driver's link: commands, records, missing samples, re-synchronisations, and
        # the firmware seen (hapsim.drivers.transport.DriverTransport.report)
        "driver": tr.report() if hasattr(tr, "report") else None,
        "excitation_end_s": prep.exc_end,
        "stale": res.stale, "bad_axes": res.bad_axes, "unarmed": res.unarmed,
        "implausible": res.implausible, "earlier_session": res.earlier_session,
        "quiesced": res.quiesced,
        "hello_mid_run": res.hello_mid_run, "device_faults": res.device_faults,
        "lost": res.lost, "recovered": res.recovered,
        "reconnect_attempts": res.reconnect_attempts, "events": res.events,
        "energy_j": res.energy, "energy_max_j": res.energy_max,
        "energy_stored_j": res.energy_stored, "energy_excess_max_j": res.energy_excess_max,
        "passivity_samples": res.passivity_samples, "v_max": res.v_max, "f_max": res.f_max,
        "velocity_sensor": res.velocity or None,
        "frames": res.frames,
        "brake": res.brake or None,
        "safety": {"position_limit": cfg.position_bound, "velocity_limit": cfg.velocity_limit,
                   "energy_limit": cfg.energy_limit,
                   "passivity_controller": cfg.passivity_controller,
                   "max_damping": cfg.max_damping, "brake_damping": cfg.brake_damping,
                   # the lateness guard (hapsim.kernels.late_growth): None where off
                   "late_guard": None if cfg.late_growth is None else {
                       "stable_to_periods": cfg.late_growth.stable_to,
                       "modes": len(cfg.late_growth.table),
                       "stop_growth": LATE_GROWTH_STOP, "slack_per_s": LATE_GROWTH_SLACK}},
        "faults": res.faults, "fault_plan": _fault_plan(opts.plan, mock_report),
        # what came before a safety stop (a host stall, a held force, a loop that grew)
        "safety_context": safety_context(conn.tel) if res.safety_stop else None,
    }
    targets = prep.targets
    ctl = run.control
    osc = None
    if ctl is not None:
        # the measurement is compared with the prediction of the scene it measured (the
        # changes accepted before its window), as hapsim play re-predicts
        from hapsim.audio.journal import revise_measurement
        osc = {"accepted": ctl.accepted, "refused": ctl.refused, "felt": ctl.felt,
               "links": {lk.name: [lk.stiffness, lk.damping] for lk in ctl.scene.links},
               "changes": revise_measurement(measured, ctl.journal, scene.rate_hz),
               "journal": ctl.journal}
    # a run whose device left its workspace, or whose board was re-synchronised more than
    # the stated bound, does not say "within" (the latter exits 1: the link is unfit)
    from hapsim.host.link_verdict import link_verdict
    unfit = link_verdict(measured, loop_info)
    # a rotary axis's figures are radians and newton metres: its sentences say so
    units = run_units(scene, opts.protocol)
    measured = in_axis_units(measured, units)
    loop_info["warnings"] = in_axis_units(loop_info["warnings"], units)
    return {"scene": scene.path, "target": targets[0] if targets else None,
            "targets": in_axis_units(targets, units), "virtual": virtual,
            "predicted": in_axis_units(prep.pred, units), "units": units,
            "measured": measured, "loop": loop_info, "telemetry": tel_info, "osc": osc,
            "sound": run.sound, **verdict_summary(measured),
            "exit_code": 1 if run_failed(loop_info, unfit) else 0}


def run_failed(loop: dict, unfit: bool) -> bool:
    """A 1-D run's exit rule from its report's ``loop`` section: it failed (exit 1) after
    a safety stop, a device fault, or a link that did not keep the loop it measured
    (``unfit``: :func:`hapsim.host.link_verdict.link_verdict`); a device lost is the
    runner's own exit 1. The report built and one read back from JSON
    (:meth:`hapsim.api.RunReport.exit_rule`) apply it alike.

    Parameters
    ----------
    loop : dict
        ``safety_stop``, ``faults``.
    unfit : bool

    Returns
    -------
    bool
    """
    return bool(loop.get("safety_stop") or loop.get("faults") or unfit)


#: Rows before a safety stop that :func:`safety_context` reads (a few of the device's
#: watchdog periods at 1 kHz).
SAFETY_CONTEXT_ROWS = 300


def safety_context(tel, rows: int = SAFETY_CONTEXT_ROWS) -> dict | None:
    """What the device did over the last ``rows`` samples of a run that ended on a safety
    stop, from its telemetry: what tells a host that stalled (the device's time stepping
    by more than a period between two samples the host took, a FORCE held for many
    samples, the watchdog's zero) from a loop that grew (forces at the limit, growing
    positions).

    Parameters
    ----------
    tel : hapsim.host.telemetry.Telemetry
        The run's telemetry (its rows in memory; a 1-D run).
    rows : int
        Rows read, the last ones (default :data:`SAFETY_CONTEXT_ROWS`).

    Returns
    -------
    dict or None
        ``rows`` (read), ``from_s`` (the device time of the first [s]), ``largest_step_s``
        (the largest device time between two successive samples [s]) and ``step_at_s``
        (the device time it ended at [s]), ``longest_same_force_rows`` (the most successive
        samples that reported the same FORCE applied: one a period in a loop that keeps
        up), ``watchdog_rows`` and ``overrun_rows`` (samples whose status says the
        device's watchdog zeroed the force, or that it held the last FORCE for a late
        one: PROTOCOL.md, STATE), ``late_rows`` (samples the host answered late),
        ``force_abs_max_n`` [N], ``position_first_m`` and ``position_last_m`` [m]; None
        without a row.
    """
    import numpy as np

    import firmware_protocol as fp
    spans = tel.rows_in_memory()
    if not spans:
        return None
    a, b = spans[-1]
    a = max(a, b - int(rows))
    c = tel.columns((a, b))
    t, fs = np.asarray(c["time"], float), np.asarray(c["force_seq"])
    if t.size == 0:
        return None
    steps = np.diff(t)
    changes = np.flatnonzero(np.diff(fs) != 0)
    runs = np.diff(np.concatenate(([-1], changes, [fs.size - 1])))
    status = np.asarray(c["status"], np.int64)
    f, x = np.asarray(c["force"], float), np.asarray(c["position"], float)
    return {"rows": int(t.size), "from_s": float(t[0]),
            "largest_step_s": float(steps.max()) if steps.size else 0.0,
            "step_at_s": float(t[int(steps.argmax()) + 1]) if steps.size else float(t[0]),
            "longest_same_force_rows": int(runs.max()),
            "watchdog_rows": int(np.count_nonzero(status & fp.STATUS_WATCHDOG_TRIPPED)),
            "overrun_rows": int(np.count_nonzero(status & fp.STATUS_OVERRUN)),
            "late_rows": int(np.count_nonzero(c["late"])),
            "force_abs_max_n": float(np.abs(f).max()),
            "position_first_m": float(x[0]), "position_last_m": float(x[-1])}


def verdict_summary(measured: dict) -> dict:
    """The run's verdict in the keys every dimension's ``run --json`` has at its top level
    (a 2-D/3-D run's :class:`hapsim.api.RunReportND`: ``verdict``, ``within``,
    ``reason``), read from a 1-D measurement's own sentence.

    Parameters
    ----------
    measured : dict
        The 1-D measurement (:func:`hapsim.pipeline.identify_run.identify_run`, after
        every rule that revises it): ``verdict`` (a sentence), ``within``, or ``error``.

    Returns
    -------
    dict
        ``verdict``: ``"within"`` (measured = predicted within the stated uncertainty),
        ``"differs"`` (by more than it) or ``"not measurable"`` (not comparable, not
        measurable, or nothing identified); ``within``: True, False, or None when not
        measurable; ``reason``: the measurement's sentence (or its error).
    """
    reason = measured.get("verdict") or measured.get("error") or "nothing was measured"
    if reason.startswith("measured = predicted"):
        word, within = "within", True
    elif reason.startswith("measured differs"):
        word, within = "differs", False
    else:
        word, within = "not measurable", None
    return {"verdict": word, "within": within, "reason": str(reason)}


def format_report(rep: dict) -> str:
    """The compact, aligned human report of :func:`hapsim.pipeline.runner.run_scene`.

    Parameters
    ----------
    rep : dict
        A report returned by :func:`hapsim.pipeline.runner.run_scene`.

    Returns
    -------
    str
        Several lines, no trailing newline.
    """
    lp = rep["loop"]
    lines = []
    protocol = lp.get("protocol", DEFAULT)
    clock = lp["mode"] + (f", {protocol} protocol" if protocol != DEFAULT    # host-paced
                          else ", lockstep" if lp["lockstep"]
                          else f", {lp.get('pace', 'real-time')}")
    lines.append(f"hapsim run {rep['scene']}: {lp['transport']} {lp['port'] or ''} ({clock})"
                 .replace("  ", " "))
    for w in lp.get("warnings") or []:
        lines.append(f"  warning: {w}")
    u = rep.get("units") or axis_units(None)
    k_head, b_head = f"k [{u['stiffness']}]", f"b [{u['friction']}]"
    bw = max(11, len(b_head))            # (a rotary axis's damping unit is longer)
    lines.append(f"  {'':<12} {k_head:>12} {b_head:>{bw}} {'f0 [Hz]':>10} {'zeta':>9}")

    def row(name, d):
        if d is None:
            return
        lines.append(f"  {name:<12} {dash(d.get('k'), '12.4f')} {dash(d.get('b'), f'{bw}.5f')} "
                     f"{dash(d.get('f0_hz'), '10.4f')} {dash(d.get('damping_ratio'), '9.5f')}")

    targets = rep.get("targets")
    if targets is None:
        targets = [rep["target"]] if rep.get("target") is not None else []
    for t in targets:
        row("target", t)
        reason = str(t.get("reason") or "")
        for word in ("renderable: ", "not renderable: "):
            if reason.startswith(word):
                reason = reason[len(word):]
        lines.append(f"  {'':<12} link {t['link']}: "
                     f"{'renderable' if t.get('renderable') else 'NOT renderable'}"
                     + (f" ({reason})" if reason else ""))
    v = rep["virtual"]
    if "K" in v:
        lines.append(f"  {'virtual K,B':<12} {dash(v['K'], '12.4f')} {dash(v['B'], f'{bw}.5f')}"
                     f"   (link {v['link']})")
    p = rep["predicted"]
    row("predicted", p)
    m = rep["measured"]
    after = m.get("compared_with")
    if isinstance(after, dict):          # live changes came before the measured window
        row("after OSC", after)
    if "k" in m:
        row("measured", m)
        re = m["rel_err"]
        lines.append(f"  {'rel. error':<12} {dash(re['k'], '+12.2e')} {dash(re['b'], f'+{bw}.2e')} "
                     f"{dash(re['f0_hz'], '+10.2e')} {dash(re['damping_ratio'], '+9.2e')}")
        if m.get("interval_note"):
            # general format: a stated uncertainty far below the last fixed digit is
            # printed as what it is, not as 0.0000
            lines.append(f"  {'+-':<12} {dash(m['k_interval'], '12.4g')} "
                         f"{dash(m['b_interval'], f'{bw}.4g')}   ({m['interval_note']})")
        if m.get("verdict"):
            lines.append(f"  verdict: {m['verdict']}")
        if "rel_err_target" in m:
            rt = m["rel_err_target"]
            lines.append(f"  {'vs target':<12} {dash(rt['k'], '+12.2e')} "
                         f"{dash(rt['b'], f'+{bw}.2e')} {dash(rt['f0_hz'], '+10.2e')} "
                         f"{dash(rt['damping_ratio'], '+9.2e')}")
    elif m.get("comparable") is False:
        lines.append(f"  {'measured':<12} not comparable (see verdict)")
        lines.append(f"  verdict: {m['verdict']}")
    else:
        lines.append(f"  {'measured':<12} not identified: {m.get('error')}")
    if m.get("stated_before_run"):
        # what hapsim run said on stderr before the loop started (hapsim/pipeline/precheck.py)
        lines.append(f"  stated before the run: {m['stated_before_run']}")
    if m.get("note"):
        lines.append(f"  note: {m['note']}")
    lines += _osc_lines(rep.get("osc"), m)
    if p.get("stable") is not None:
        # K_max is the limit of the links at the port as one port-ground spring: the felt
        # k of a scene with virtual masses is another quantity, so say which it is there
        kmax = f"K_max {dash(p['stiffness_limit'], '.6g')} N/m"
        if p.get("source") == "check_scene" and p.get("port_K") is not None:
            kmax += (f" of the links at the port as a port-ground spring (K = "
                     f"{p['port_K']:g} N/m, B = {p['port_B']:g} N s/m), not of the felt k")
        used = (": not comparable" if m.get("comparable") is False
                else f" from {m.get('samples_used', 0)} samples")
        lines.append(f"  stable: {'yes' if p['stable'] else 'NO'} (spectral radius "
                     f"{dash(p['spectral_radius'], '.9f')}, {kmax}; identification order "
                     f"{p['order']}{used})")
    ta = lp["turnaround_us"]
    ll = "on" if lp["low_latency"] else f"off ({lp['low_latency_note'] or 'n/a'})"
    lines.append(f"loop: {lp['rate_hz']:g} Hz, {lp['ticks']}/"
                 f"{lp['requested'] if lp.get('requested') else 'open-ended'} ticks, "
                 f"late {lp['late']}, missed {lp['missed']}, skipped {lp.get('skipped', 0)}, "
                 f"clamped {lp['clamped']}; "
                 f"stop: {lp['stop_reason']} (state {lp.get('state', '-')}); scheduling "
                 f"{lp.get('scheduling', 'normal')}, {lp.get('loop', 'python')} host loop")
    if lp.get("python_reason"):
        lines.append(f"loop: the Python loop ran, not the compiled one: {lp['python_reason']}")
    if lp.get("first_sample_s") is not None:
        lines.append(f"start-up: first sample {lp['first_sample_s']:.2f} s after the process "
                     f"started")
    pr = lp.get("ping_rtt_us") or {}
    if pr.get("p50") is not None:
        lines.append(f"ping round trip [us]: p50 {dash(pr.get('p50'), '.0f')}  max "
                     f"{dash(pr.get('max'), '.0f')} ({pr.get('answered')}/{pr.get('sent')} "
                     f"answered, before arming)")
    lines.append(f"turnaround [us]: p50 {dash(ta.get('p50'), '.0f')}  p99 "
                 f"{dash(ta.get('p99'), '.0f')}  p99.9 {dash(ta.get('p999'), '.0f')}  max "
                 f"{dash(ta.get('max'), '.0f')}"
                 # on a pty (the embedded mock) the serial driver's mode does not exist
                 + ("" if (lp.get("low_latency_note") or "").startswith("a pty") and not lp["low_latency"]
                    else f"; low-latency mode {ll}"))
    if lp.get("lost") or lp.get("stale") or lp.get("bad_axes") or lp.get("device_faults") \
            or lp.get("fault_plan") or lp.get("implausible"):
        dec = lp.get("decoder") or {}
        bad = sum(v for k, v in dec.items() if k != "frames_ok")
        lines.append(f"faults: lost {lp['lost']}, recovered {lp['recovered']} "
                     f"({lp['reconnect_attempts']} attempts), stale {lp['stale']}, bad frames "
                     f"{bad}, wrong axes {lp['bad_axes']}, implausible seq "
                 f"{lp.get('implausible', 0)}, device faults "
                     f"{lp['device_faults'] or 0}")
        lines += loss_lines(lp.get("events", []))
        if lp.get("fault_plan"):
            lines.append(f"injected: {lp['fault_plan']['injected']} "
                         f"(--faults {lp['fault_plan']['spec']}, seed {lp['fault_plan']['seed']})")
    bf = lp.get("bad_frames") or []
    if bf:
        kinds: dict = {}
        for r in bf:
            kinds[r["kind"]] = kinds.get(r["kind"], 0) + 1
        last = bf[-1]
        shown = last["hex"] if len(last["hex"]) <= 48 else last["hex"][:45] + "..."
        lines.append(f"bad frames: {lp.get('bad_frames_seen', len(bf))} dropped, last "
                     f"{len(bf)} recorded ({', '.join(f'{k} {v}' for k, v in kinds.items())}); "
                     f"last at sample {last['sample']}, t = {last['t']:.3f} s: {last['kind']} "
                     f"{shown} ({last['outcome']}); all in --json loop.bad_frames")
    sf = lp["safety"]
    lines.append(f"energy to the hand [J]: max {dash(lp.get('energy_max_j'), '.4g')}, end "
                 f"{dash(lp.get('energy_j'), '.4g')}; stored at start "
                 f"{dash(lp.get('energy_stored_j'), '.4g')}, excess max "
                 f"{dash(lp.get('energy_excess_max_j'), '.4g')} (limit "
                 f"{dash(sf['energy_limit'], 'g')}"
                 f"{', passivity controller on' if sf['passivity_controller'] else ''})")
    sc = lp.get("safety_context")
    if sc:
        lines.append(f"before the stop (its last {sc['rows']} samples): the device's time "
                     f"stepped up to {sc['largest_step_s'] * 1e3:.1f} ms between two, the "
                     f"same FORCE applied for up to {sc['longest_same_force_rows']} of "
                     f"them, watchdog zero in {sc['watchdog_rows']}, force up to "
                     f"{sc['force_abs_max_n']:.3g} N, position {sc['position_first_m']:.4g} "
                     f"-> {sc['position_last_m']:.4g} m")
    bk = lp.get("brake")
    if bk:
        # the host braked the device after the safety stop (hapsim.host.recovery)
        lines.append(brake_text(bk))
    dl = lp.get("driver")
    if dl:
        # a driver's link (hapsim.drivers.transport): what came back of what was asked
        lines.append(f"driver link: {dl['commands']} commands, {dl['records']} records, "
                     f"missing {dl['missing']} (stepped through estimated: "
                     f"{lp.get('estimated', 0)}), re-synchronised {dl['resyncs']}, arming "
                     f"repeated {dl['rearms']}; firmware: {dl['firmware'] or 'not seen'}")
        wd = dl.get("watchdog")
        if wd:
            # the host's watchdog beside a board that holds its force (host_watchdog)
            from hapsim.drivers.torque_watchdog import watchdog_text
            lines.append(watchdog_text(wd))
    mk = lp.get("mock")
    if mk:
        lines.append(f"device (mock): {mk['ticks']} ticks, late {mk['late']}, watchdog "
                     f"{mk['watchdog_trips']}, overruns {mk['overruns']}, clamped {mk['clamped']}, "
                     f"last force {dash(mk['last_applied'], 'g')} N, "
                     f"STOP {'seen' if mk['saw_stop'] else 'not seen'}")
    tl = rep["telemetry"]
    if tl:
        extra = ""
        if tl.get("lost_rows"):
            extra += (f"; {tl['lost_rows']} rows LOST: the journal writer fell more than the "
                      f"{tl['ring']}-row ring behind")
        if tl.get("events_journaled"):
            extra += f"; {tl['events_journaled']} events journaled"
        if tl.get("writer_error"):
            extra += f"; journal writer stopped: {tl['writer_error']}"
        lines.append(f"telemetry: {tl['path']} ({tl['samples']} samples{extra})")
    # a rotary axis: the lines made in SI words (the braking's, the mock's, the losses')
    return in_axis_units("\n".join(lines), u)


def loss_lines(events: list) -> list:
    """The report's lines of a run's losses and recoveries, one per event.

    A recovery says where the handle was found and how far it moved from the last STATE
    answered before the loss: through a silence a device holds its last force until its
    watchdog, then the handle coasts on its own friction (``docs/reliability.md``).

    Parameters
    ----------
    events : list of dict
        The loop's events (:attr:`hapsim.host.loop_types.LoopResult.events`): ``"lost"``
        with ``t`` [s], ``sample``, ``reason`` and ``x`` [m] (None before any sample);
        ``"recovered"`` with ``t``, ``sample``, ``after_s`` [s], ``attempts`` and ``x``
        [m]; others are skipped.

    Returns
    -------
    list of str
        Indented lines, ``"  t = T s, sample N: ..."``.
    """
    lines, x_lost = [], None
    for ev in events:
        if ev["event"] == "lost":
            x_lost = ev.get("x")
            what = f"lost ({ev['reason']})"
        elif ev["event"] == "recovered":
            what = f"recovered after {ev['after_s']:.3g} s, {ev['attempts']} attempt(s)"
            x = ev.get("x")
            if x is not None and x_lost is not None:
                what += (f", the handle at {x * 1e3:.3g} mm ({(x - x_lost) * 1e3:+.3g} mm "
                         "from where it was lost)")
        else:
            continue
        lines.append(f"  t = {ev['t']:.3f} s, sample {ev['sample']}: {what}")
    return lines


def _osc_lines(osc: dict | None, measured: dict) -> list:
    """What ``run --osc`` changed, and which prediction the measurement is compared with."""
    if not osc or not (osc.get("accepted") or osc.get("refused")):
        return []
    changes = osc.get("changes") or []
    n = osc.get("accepted", 0)
    lines = [f"osc: {n} change{'' if n == 1 else 's'} accepted, {osc.get('refused', 0)} "
             f"refused"]
    for c in changes[:8]:
        k, b = (c.get("felt") or [None, None])[:2]
        lines.append(f"  sample {c['sample']}: {c['address']} "
                     f"{' '.join(map(str, c['args']))} -> felt k {dash(k, '.6g')} N/m, "
                     f"b {dash(b, '.6g')} N s/m (ramp {c.get('ramp_s', 0):g} s)")
    if len(changes) > 8:
        lines.append(f"  ... and {len(changes) - 8} more (--json: osc.changes)")
    after = measured.get("compared_with")
    if isinstance(after, dict):
        lines.append(f"  the measurement is compared with the prediction after "
                     f"{after['after']} (row 'after OSC')")
    elif isinstance(after, str):
        lines.append(f"  the measurement is compared with {after}")
    return lines


def _since_start(t, opts: RunOptions):
    """``t`` (time.monotonic [s]) in seconds since the process started; None when ``t`` is
    None or the loop's clock is not the wall's (a virtual-clock transport)."""
    if t is None or opts.transport == "sim":
        return None
    return round(t - process_start(), 4)


def _fault_plan(plan, mock_report) -> dict | None:
    """Spec, seed and the faults the mock injected (its own count when it is a child)."""
    if plan.empty:
        return None
    out = plan.to_dict()
    if mock_report and mock_report.get("faults_injected") is not None:
        out["injected"] = mock_report["faults_injected"]
    return out
