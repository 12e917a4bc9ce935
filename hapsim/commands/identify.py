"""``hapsim identify``: measure the device hapsim drives (mass, friction, delay, ...)."""

from __future__ import annotations

import argparse
import json
import sys


from hapsim.drivers import DEFAULT, DRIVERS, family
from hapsim.errors import ConfigError
from hapsim.option_values import Number, declared
from hapsim.outputs import atomic_write

_DESCRIPTION = """\
Excite a 1-DoF force-feedback device safely and identify what hapsim's predictions rest
on: the moving mass m [kg], the viscous friction b0 [N s/m], the Coulomb friction fc [N]
(each direction), the delay d [samples], whether the force is held (zero-order hold) or
not, the encoder quantum and the sensor noise -- each with a 99.9 % confidence interval, the
fit's residual and a verdict on whether the mass-friction model explains the data.

The excitation is a force (a pseudo-random binary sequence on slow constant-force steps,
which separate Coulomb from viscous friction) on a weak centring spring that designs its
own level, with nothing to tune: a short probe raises it until the device moves, then the
steps reverse before the device would stop beyond 40 % of --envelope (its inertia bounded
from the probe, its overshoot measured after each reversal, the longest delay counted),
up to 0.4 x --force-limit (steps plus PRBS: 0.6 x). It runs under the same host loop as
'hapsim run': device watchdog armed, host force clamp, safety stop beyond the envelope, zero force
and STOP at the end or on Ctrl-C. The fit is an output-error least squares of the exact
zero-order-hold discretisation (multiple shooting) on the recorded STATE/FORCE stream,
with Newey-West intervals, driven by the force the device applied at each tick (its
STATEs' force_seq name it: a late tick is a known input, and the delay is the one the
device shows, never assumed). A STATE lost on the way cuts the record: every stretch of
consecutive STATEs is fitted, each from its own initial state. Without --port the embedded
mock (--mock-scene: its device) is identified."""

_EPILOG = """\
output:
  --out FILE.yaml  the 'device:' section with the intervals as comments; use it with
                   'hapsim run SCENE --device FILE.yaml' (replaces the scene's device)
  --json           the same on stdout as one JSON object (value, lo, hi, unit each)
  --plot FILE.png  measured positions against the model's, and the residual
--hand: hold the handle as you will when using the device. What is identified is then
  the THS (the paper's hand + handle): total mass and damping for this grip. hapsim
  reports that total; it does not split it into hand and device (a scene's hand model
  is another feature).
--driver haply: before the excitation, a torque pulse of each sign (raised until the
  encoder moves 3 counts, within --force-limit; zero torque after) finds the motor's
  direction byte, written to --out's protocol_options (not probed when motor_direction is
  given); the board's id is the host's choice (it answers any): nothing to identify.
limits: the Coulomb model is the first-order one of the mock (held -fc sign(v), sticks
  when the force cannot break it loose); the delay is a real number of samples d + f
  (under the zero-order hold the force switches f T into the period: the split hold),
  stated with its interval (delay_estimate; --out writes it when its interval excludes
  the whole delay); the model is 1-DoF rigid: a
  compliant transmission or a resonance makes the verdict negative (exit code 1).
exit codes: 0 identified and explained, 1 identified but the model does not explain the
  data (or a safety stop / device fault), or the record cannot be identified (the reason
  is printed: too short, the device hardly moved, ...), or the device was lost (the
  record up to the loss fitted and reported first, then the error), 2 bad arguments
delay: a framed device shows it (force_seq); for another protocol every delay up to
  --max-delay is tried, and one that another fits as well (a coarse encoder) is not
  stated as certain: delay_certain false, delay_range and the verdict name them
examples:
  hapsim identify --out device.yaml --plot fit.png
  hapsim identify --mock-scene configs/wall.yaml --lockstep --json
  hapsim identify --port /dev/ttyACM0 --force-limit 1 --envelope 0.02 --out device.yaml"""


def __getattr__(name: str):
    """``identify``: the API behind the command (:func:`hapsim.api.excite_and_fit`), imported
    on first use (PEP 562) so that building the parser (``hapsim --help``) loads no API.

    Raises
    ------
    AttributeError
        For any other name.
    """
    if name == "identify":
        from hapsim.api import excite_and_fit
        return excite_and_fit
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def register(sub) -> None:
    """Add the ``identify`` parser to the CLI.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The sub-parsers action of ``hapsim``'s parser; ``identify``'s ``func`` is :func:`run`.
    """
    p = sub.add_parser("identify", help="measure a device's mass, friction, delay and hold "
                                        "(with confidence intervals)",
                       description=_DESCRIPTION, epilog=_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--port", metavar="PORT",
                   help="serial port of the device (default: the embedded mock on a pty)")
    p.add_argument("--baud", type=declared("identify", "baud"),
                   default=115200, metavar="BAUD", help="baud rate")
    p.add_argument("--driver", default=None, metavar="NAME",
                   help=f"device protocol (default: --mock-scene's device.protocol, as "
                        f"hapsim run takes it, else framed; valid: {', '.join(DRIVERS)})")
    p.add_argument("--protocol-option", action="append", default=[], metavar="KEY=VALUE",
                   help="a driver's device parameter (device.protocol_options; repeat: "
                        "e.g. full_scale=0.39 for the FireFader, resolution=4880 for the "
                        "Haply board); written to --out with the protocol")
    p.add_argument("--added-mass", type=declared("identify", "added_mass"),
                   metavar="KG",
                   help="find the driver's scale (the FireFader's full_scale, the Haply "
                        "board's resolution): identify, then identify again with KG [kg] "
                        "(an inertia [kg m^2] for a rotary axis) clamped to the handle "
                        "(the embedded mock adds it itself; with --port, press Enter once "
                        "it is on); --out gets the scale and the device in its own units")
    p.add_argument("--travel", type=Number(float, low=0, open_low=True, unit="mm"),
                   metavar="MM",
                   help="the FireFader's travel between its end stops [mm] (its "
                        "datasheet's): before the excitation the fader is pushed to each "
                        "stop and metres_per_count = travel / (counts between the stops) "
                        "is found, with its interval, and written to --out (with "
                        "--added-mass, full_scale is then found in those units)")
    p.add_argument("--mock-option", action="append", default=[], metavar="KEY=VALUE",
                   help="the embedded driver mock's hardware, other than the device "
                        "--protocol-option describes (repeat: e.g. full_scale=1.56 for "
                        "the FireFader mock, cpr=4096 for the Haply mock)")
    p.add_argument("--out", metavar="FILE.yaml", help="write the device section there")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--plot", metavar="FILE.png", help="plot measured vs model response")
    p.add_argument("--hand", action="store_true",
                   help="a hand holds the handle: report the THS (hand + handle) mass and "
                        "damping")
    p.add_argument("--force-limit", type=declared("identify", "force_limit"),
                   default=None, metavar="N",
                   help="largest force sent [N] (default 2, or the --mock-scene device's "
                        "force_limit or its protocol's limit where smaller)")
    p.add_argument("--envelope", type=declared("identify", "envelope"),
                   default=None, metavar="M",
                   help="position envelope +-M around the start [m]; beyond it the "
                        "excitation stops (default 0.01, or --mock-scene's |excitation.x0| "
                        "where larger, in the scene's units)")
    p.add_argument("--duration", type=declared("identify", "duration"),
                   default=None, metavar="S",
                   help="excitation length [s] (default: 2.4 s of probe plus 1,600 "
                        "samples at the rate, at least 4 s: 4 s at 1 kHz, 8.8 s at 250 Hz)")
    p.add_argument("--rate", type=declared("identify", "rate_hz"),
                   default=None, metavar="HZ",
                   help="loop rate [Hz] (default: --mock-scene's rate_hz, else 1000)")
    p.add_argument("--max-delay", type=declared("identify", "max_delay"), default=20, metavar="D",
                   help="largest device delay [samples] the centring loop is stable for "
                        "and, for a protocol that does not report the force it applied, "
                        "the largest delay tried (default 20: a USB latency timer of 16 ms "
                        "at 1 kHz and some; a framed device shows its delay itself)")
    p.add_argument("--lockstep", action="store_true", help="lockstep embedded mock")
    p.add_argument("--rt-priority", type=declared("identify", "rt_priority"), default=10, metavar="P",
                   help="SCHED_FIFO priority of the excitation's loop where the OS permits "
                        "it (default 10, as hapsim run; 0: normal scheduling): a loop "
                        "preempted mid-push leaves the device its force for that long")
    p.add_argument("--mock-scene", metavar="SCENE",
                   help="scene whose device the embedded mock models (default: m = 0.1 kg, "
                        "b0 = 0.5 N s/m, d = 1); a 2-D or 3-D scene with --lockstep: its "
                        "device's mass and friction matrices and delay")
    p.add_argument("--seed", type=declared("identify", "seed"),
                   default=0, help="excitation and mock-noise seed")
    p.set_defaults(func=run)


def _plot(fit, rec, path: str, driver=None) -> None:
    from hapsim.drivers import axis_units
    from hapsim.plots import plot_identify, save_figure
    save_figure(plot_identify(fit, rec, axis_units(driver)), path)


def _mock_keys_known(driver: str, given: dict) -> None:
    """Refuse a ``--mock-option`` the driver's board model does not take, naming those it
    does (its constructor's numeric keywords): before, the board's process stopped at its
    start on it, and the host said only that its port was gone."""
    from hapsim.emulated.driver_mock import board_options
    valid = board_options(driver, numeric=True)
    bad = sorted(set(given) - set(valid))
    if bad:
        raise ConfigError(f"{', '.join(bad)}: not an option of the {driver} board's model; "
                          f"valid: {', '.join(valid)}", key="--mock-option")


def _key_values(items, key: str) -> dict:
    """``KEY=VALUE`` options as a dict of numbers (int when whole)."""
    out = {}
    for item in items:
        k, sep, val = item.partition("=")
        if not sep:
            raise ConfigError(f"must be KEY=VALUE, got {item!r}", key=key)
        try:
            out[k.strip()] = int(val) if val.strip().lstrip("-").isdigit() else float(val)
        except ValueError:
            raise ConfigError(f"{k}: must be a number, got {val!r}", key=key) from None
    return out


def _loaded(device, args):
    """The device of the second identification of ``--added-mass``: the embedded mock's
    with the mass added; with ``--port``, the user clamps it on (asked on stderr)."""
    import dataclasses
    if args.port:
        print(f"clamp {args.added_mass:g} kg to the handle, then press Enter",
              file=sys.stderr, flush=True)
        sys.stdin.readline()
        return device
    from hapsim.device_model import DEFAULT_DEVICE
    dev = device or DEFAULT_DEVICE
    return dataclasses.replace(dev, mass=dev.mass + args.added_mass)


def run(args) -> int:
    """Run ``hapsim identify``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options of :func:`register`.

    Returns
    -------
    int
        0 identified and explained, 1 the model does not explain the data, the
        excitation ended on a safety stop or device fault, or the device was lost after
        the excitation's first row (its record up to the loss fitted and reported, then
        the error on stderr; ``--json``: ``error`` in the report).

    Raises
    ------
    ConfigError
        Bad option values, an unknown driver, an invalid --mock-scene (exit 2).
    """
    if args.driver is not None:
        family(args.driver)             # an unknown name: the valid ones listed
    if args.plot:
        from hapsim.plots import check_figure_path
        check_figure_path(args.plot, "--plot")
    if args.out:
        from hapsim.plots import check_output_path
        check_output_path(args.out, "--out")
        if not args.out.lower().endswith((".yaml", ".yml")):    # (any name was taken)
            raise ConfigError(f"the device file is YAML: give a file ending in .yaml, got "
                              f"{args.out!r}", key="--out")
    scene = None
    if args.mock_scene:
        from hapsim import load_scene
        scene = load_scene(args.mock_scene)
        if getattr(scene, "dimension", 1) > 1:
            return _run_space(args, scene)
        from hapsim.commands.dimension import load_one_d_scene
        scene = load_one_d_scene(args.mock_scene, "identify", "--mock-scene")
        if scene.device is None:
            raise ConfigError("the scene has no device section: nothing to identify",
                              file=args.mock_scene, key="device")
    # the protocol (--driver, else the scene's device.protocol, as hapsim run's), the
    # rate, duration, force limit and envelope: each given, else its default
    # (hapsim.pipeline.identify_settings: the API's resolver too)
    from hapsim.pipeline.identify_settings import identify_settings
    st = identify_settings(scene, driver=args.driver,
                           driver_options=_key_values(args.protocol_option,
                                                      "--protocol-option"),
                           rate_hz=args.rate, duration=args.duration,
                           force_limit=args.force_limit, envelope=args.envelope,
                           hand=args.hand)
    args.driver, args.rate, args.duration = st.driver, st.rate_hz, st.duration
    args.force_limit, args.envelope = st.force_limit, st.envelope
    device = st.device
    if scene is not None and args.driver == DEFAULT and not args.lockstep and args.port is None:
        from hapsim.emulated.mock import require_whole_delay
        require_whole_delay(device.delay, file=args.mock_scene, command="identify")
    dopts = st.driver_options
    drv = None
    mopts = None
    if args.driver != DEFAULT:
        from hapsim.drivers import get_driver
        drv = get_driver(args.driver, **dopts)
        if args.mock_option and args.port:      # (before: taken and ignored)
            raise ConfigError("the embedded board's hardware; with --port the device is "
                              "the one on the port", key="--mock-option")
        if args.mock_option:
            given = _key_values(args.mock_option, "--mock-option")
            _mock_keys_known(args.driver, given)
            mopts = {**drv.mock_hardware(), **given}
    elif args.mock_option or args.added_mass is not None:
        raise ConfigError("the framed protocol takes no options (its device says its units "
                          "in HELLO); give --driver",
                          key="--mock-option" if args.mock_option else "--added-mass")
    if args.added_mass is not None:       # (its range: the declaration, checked before)
        if drv.scale_option is None:
            from hapsim.drivers import FAMILIES
            scaled = [f.name for f in FAMILIES
                      if f.dimension == 1 and f.driver and f.load().scale_option]
            raise ConfigError(f"the {drv.name} protocol carries SI units: no scale to "
                              f"calibrate; valid with --added-mass: --driver "
                              f"{', '.join(scaled)}", key="--added-mass")
    # (a --travel of another driver than the FireFader: refused by the identification,
    # hapsim.pipeline.identify_run.record, before anything runs)
    from hapsim.api import identify as identify_api
    kw = dict(baud=args.baud, force_limit=args.force_limit, envelope=args.envelope,
              duration=args.duration, rate_hz=args.rate, max_delay=args.max_delay,
              lockstep=args.lockstep, seed=args.seed, driver=args.driver,
              driver_options=dopts, hand=args.hand, progress=True, handle_signals=True,
              mock_options=mopts, rt_priority=args.rt_priority,
              travel=None if args.travel is None else args.travel * 1e-3)
    rep = identify_api(args.port, device=device, **kw)
    rep.loop["settings"]["protocol"] = st.said     # (the API was given the driver resolved)
    fit, rec = rep.fit, rep.record
    if drv is not None:
        # the driver as the record found it (the Haply motor direction, probed first)
        drv = rep.found_driver() or drv
    scale = None
    lost_loaded = False         # the device lost in the identification with the mass on
    if args.added_mass is not None and rep.error is None:
        # the second identification in the units the first found (the position scale
        # of the sweep), without sweeping again
        kw.update(driver_options=drv.options(), travel=None)
        rep2 = identify_api(args.port, device=_loaded(device, args), **kw)
        if rep2.error is not None:
            # lost with the mass on: the first identification is the report, no scale
            # is taken from a record cut short, and the loss is the run's
            lost_loaded = True
            rep = rep.replace(error=rep2.error)
        else:
            from hapsim.api import calibrate_scale
            scale, fit, drv = calibrate_scale(rep, rep2, args.added_mass, drv)
    from hapsim.device_file import device_yaml
    source = args.port or "the embedded mock"
    from hapsim.drivers import in_axis_units, run_units
    # (the file in its axis's units: a rotary scene's over the framed protocol too)
    text = in_axis_units(device_yaml(fit, args.force_limit, hand=args.hand, source=source,
                                     driver=drv), run_units(scene, args.driver))
    probe = rec["loop"].get("direction_probe")
    if probe is not None:
        tried = probe["motor_direction"] if probe["relative"] > 0 else 1 - probe["motor_direction"]
        text = (f"# motor_direction {probe['motor_direction']} found before the excitation: "
                f"{probe['torque'][0]:+.3g} N m moved the encoder {probe['counts'][0]:+d} "
                f"counts with motor byte {tried} (encoder direction "
                f"{drv.options().get('direction')}); the device id is the host's choice "
                f"(the board answers any): nothing to identify\n") + text
    sweep = rec["loop"].get("travel_sweep")
    if sweep is not None:
        c_lo, c_hi = sweep["counts"]
        text = (f"# metres_per_count found by a sweep between the end stops: "
                f"{sweep['metres_per_count'] * 1e3:.5g} mm [{sweep['lo'] * 1e3:.5g}, "
                f"{sweep['hi'] * 1e3:.5g}] per count ({sweep['travel'] * 1e3:g} mm of "
                f"travel given over counts {c_lo:.1f} to {c_hi:.1f}; the travel's own "
                f"tolerance adds to that interval)\n") + text
    if scale is not None:
        opt = drv.scale_option
        text = (f"# {opt} found with {args.added_mass:g} kg added: {scale.full_scale:.6g} "
                f"[{scale.full_scale_lo:.4g}, {scale.full_scale_hi:.4g}] (gain "
                f"{scale.gain:.4g} over the {opt} assumed); mass and friction in the "
                f"device's own units\n") + text
    if args.out:                                # whole or not at all (a device refused)
        with atomic_write(args.out, "wb", "--out") as fh:
            fh.write(text.encode("utf-8"))
    if args.plot:
        _plot(fit, rec, args.plot, drv)
    loop = rec["loop"]
    code = 0 if (fit.explained and not loop["safety_stop"] and not loop["faults"]
                 and rep.error is None) else 1
    if scale is not None:
        # the report of the device in its own units, with the scale found (an extra key)
        from hapsim.api import IdentifyReport
        from hapsim.outputs import json_safe
        rep = IdentifyReport.from_dict(json_safe({
            **rep.to_dict(), "device": fit.to_dict(), "scale": {
                "option": drv.scale_option, "value": scale.full_scale,
                "lo": scale.full_scale_lo, "hi": scale.full_scale_hi, "gain": scale.gain,
                "added_mass": args.added_mass, "protocol_options": drv.options()}}),
            fit=fit, record=rec)
    if args.json:
        print(json.dumps({**rep.to_dict(), "out": args.out, "plot": args.plot}))
    else:
        if args.hand:
            print("# with the hand on the handle: the mass and damping below are the THS's "
                  "(hand + handle)")
        print(text, end="")
        print(f"# excitation: {loop['samples']}/{loop['requested']} samples ("
              f"{args.duration:g} s at {args.rate:g} Hz, force limit {args.force_limit:g}, "
              f"envelope {args.envelope:g}; {st.said}), stop: "
              f"{loop['stop_reason']}, late {loop['late']}, clamped {loop['clamped']}"
              + ("" if rep.error is None else
                 " (the device was lost with the added mass on: its scale was not found)"
                 if lost_loaded else
                 " (the device was lost: the fit is of the record up to the loss"
                 + ("; the added mass was not identified" if args.added_mass is not None
                    else "") + ")"))
    sys.stdout.flush()
    from hapsim.outputs import say_error_after
    say_error_after("identify", rep.error)  # the report first, then why it ended
    return code


#: The options a 2-D or 3-D identification in lockstep does not take, and why.
_SPACE_REFUSED = {
    "port": "over a port in real time a 2-D or 3-D device is not identified yet: --lockstep "
            "identifies the scene's own device model",
    "driver": "the lockstep device is the scene's own model: no protocol",
    "hand": "a hand on a 2-D or 3-D handle is not modelled",
    "added_mass": "the lockstep device is in SI units: no scale to calibrate",
    "travel": "the lockstep device is in SI units: no travel to sweep",
    "plot": "the 2-D or 3-D fit has no plot yet (--json has every number)",
}


def _run_space(args, scene) -> int:
    """``hapsim identify --mock-scene SCENE --lockstep`` of a 2-D or 3-D scene: its
    device's mass and friction matrices and its delay
    (:func:`hapsim.pipeline.identify_matrices.identify_matrices_lockstep`), against what
    the scene states.

    Returns
    -------
    int
        0 when the scene's matrices are within the intervals identified and the delay is
        the scene's, else 1.

    Raises
    ------
    ConfigError
        Without ``--lockstep``, or with an option it does not take (:data:`_SPACE_REFUSED`,
        keyed by the option); a scene without a device or with a sub-sample delay.
    hapsim.errors.IdentificationError
        The handle left the envelope, or the record does not determine the device.
    """
    import numpy as np

    from hapsim.pipeline.identify_matrices import identify_matrices_lockstep
    from hapsim.progress import Progress
    from hapsim.pipeline.identify_settings import (DEFAULT_ENVELOPE, DEFAULT_FORCE_LIMIT,
                                                   default_duration)
    given = {"port": args.port, "driver": args.driver not in (None, DEFAULT),
             "hand": args.hand,
             "added_mass": args.added_mass is not None, "travel": args.travel is not None,
             "plot": args.plot}
    for key, why in _SPACE_REFUSED.items():
        if given[key]:
            raise ConfigError(why, key="--" + key.replace("_", "-"))
    if not args.lockstep:
        raise ConfigError(_SPACE_REFUSED["port"] + " (give --lockstep)", key="--lockstep")
    # the defaults as before (the n-D scenes' devices state no force limit; 4 s at their
    # 1 kHz, default_duration's floor)
    if args.force_limit is None:
        args.force_limit = DEFAULT_FORCE_LIMIT
    if args.envelope is None:
        args.envelope = DEFAULT_ENVELOPE
    if args.duration is None:
        args.duration = default_duration(float(scene.rate_hz))
    with Progress(1, f"identifying the {scene.dimension}-D device (two records of "
                     f"{args.duration:g} s)", unit="samples") as bar:
        r = identify_matrices_lockstep(
            scene, force_limit=args.force_limit, envelope=args.envelope,
            duration=args.duration, max_delay=args.max_delay, seed=args.seed,
            progress=lambda done, total: bar.update(done, total))
    fit, dev = r["fit"], scene.device
    hm, hb = r["mass_half_width"], r["friction_half_width"]
    em = float(np.abs(fit.mass - dev.mass).max())
    eb = float(np.abs(fit.friction - dev.friction).max())
    agree = em <= hm and eb <= hb and fit.delay == int(dev.delay)
    doc = {"scene": str(args.mock_scene), "dof": scene.dimension, "device": dev.kind,
           "rate_hz": scene.rate_hz, "identified": fit.to_dict(),
           "mass_half_width": hm, "friction_half_width": hb,
           "scene_states": {"mass": dev.mass.tolist(), "friction": dev.friction.tolist(),
                            "delay": dev.delay},
           "within": agree, "excursion": r["excursion"],
           "largest_force": r["largest_force"], "samples": r["samples"],
           "centring": r["centring"], "out": args.out}

    def mat(a):
        return "[" + ", ".join("[" + ", ".join(f"{v:.6g}" for v in row) + "]"
                               for row in a) + "]"
    text = (f"# identified in lockstep from {args.mock_scene}'s {dev.kind} (its "
            f"{scene.dimension}-D Cartesian mass and friction at the operating point; two "
            f"records of {args.duration:g} s, the handle within "
            f"{r['excursion'] * 1e3:.3g} mm of rest)\n"
            f"# mass +- {hm:.2g} kg and friction +- {hb:.2g} N s/m on every entry (the "
            f"device's nonlinearity from two amplitudes, and the fit's standard errors); "
            f"delay {fit.delay} periods (the next best fit's residual "
            f"{fit.runner_up / max(fit.residual, 1e-300):.3g} times larger)\n"
            f"device: {{kind: cartesian, mass: {mat(fit.mass)},\n"
            f"         friction: {mat(fit.friction)},\n"
            f"         position: [{', '.join(f'{v:.6g}' for v in dev.position)}], "
            f"delay: {fit.delay}}}\n")
    if args.out:                                # whole or not at all (a device refused)
        with atomic_write(args.out, "wb", "--out") as fh:
            fh.write(text.encode("utf-8"))
    if args.json:
        print(json.dumps(doc))
    else:
        print(text, end="")
        print(f"# the scene states mass {mat(dev.mass)} kg, friction {mat(dev.friction)} "
              f"N s/m, delay {dev.delay}: "
              + ("within the intervals" if agree else
                 f"NOT within (mass off by {em:.3g} kg, friction by {eb:.3g} N s/m, delay "
                 f"{fit.delay} against {dev.delay})"))
    return 0 if agree else 1
