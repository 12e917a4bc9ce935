"""The API's edges a fuzz of its remaining public functions and its reports found (stop 92):
a number rounded to digits that are not known, a report whose ``ok`` said the opposite of
its exit code once read back from JSON, a device file stating another force limit than
the identification's, a scale calibrated through a driver the records never went through,
keywords taken and ignored or failing deep in the run, and charts written to another file
than the one named. Each class is tested over its members, not by the one case found."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

import hapsim
from hapsim import api
from hapsim.errors import ConfigError
from hapsim.pipeline.options import RunOptions

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
WALL = str(CONFIGS / "wall.yaml")
PANTOGRAPH = str(CONFIGS / "pantograph_wall.yaml")


def test_known_digits_rounds_to_the_decade_the_error_leaves_known():
    """:func:`hapsim.api.known_digits` over random values and errors (12 decades each):
    the result is a whole number of the unit ``u = 10**ceil(log10(2 error))``, the decade
    at or above ``2 error`` (so ``2 error <= u < 20 error``), within half a unit of the
    value (before: never coarser than units, so 987654 known to 2000 kept its 654)."""
    rng = np.random.default_rng(92)
    for value, error in zip(rng.uniform(-1, 1, 400) * 10.0 ** rng.integers(-6, 7, 400),
                            10.0 ** rng.uniform(-6, 6, 400)):
        got = api.known_digits(float(value), float(error))
        u = 10.0 ** math.ceil(math.log10(2.0 * error))
        # (1 + 1e-12: a bound on the round-off of log10 and of the power, derived: a few
        # ulps each)
        assert 2.0 * error <= u * (1 + 1e-12) and u < 20.0 * error * (1 + 1e-12)
        # half a unit, and a bound on round()'s own round-off (derived: a few ulps of
        # |value|)
        assert abs(got - value) <= 0.5 * u * (1 + 1e-9) + 4 * np.spacing(abs(value))
        # a whole number of units: got / u is off a whole number by its round-off, a
        # bound of a few ulps of |got / u| (derived: one rounding in round(), one in
        # the division)
        assert abs(got / u - round(got / u)) <= 1e-9 + 4 * np.spacing(abs(got / u))
    assert api.known_digits(987654.0, 2000.0) == 990000.0
    assert api.known_digits(1234.5, 30.0) == 1200.0
    assert api.known_digits(0.123456, 0.001) == 0.12
    assert api.known_digits(1.5, 0.0) == 1.5 and api.known_digits(1.5, math.inf) == 1.5


@pytest.mark.parametrize("call, key", [
    (lambda: api.known_digits(1.2, -1.0), "error"),
    (lambda: api.known_digits(1.2, True), "error"),
    (lambda: api.known_digits("x", 0.1), "value"),
    (lambda: api.known_digits(None, 0.1), "value"),
    (lambda: api.known_digits(1.2, [1]), "error"),
    (lambda: api.known_decimals(0.0), "error"),
    (lambda: api.known_decimals(-1.0), "error"),
    (lambda: api.known_decimals(math.nan), "error"),
    (lambda: api.known_decimals(math.inf), "error"),
    (lambda: api.known_decimals("x"), "error")])
def test_known_digits_refuses_what_is_no_uncertainty(call, key):
    """A negative, boolean, word or missing uncertainty (and a value that is no number)
    is a ConfigError keyed by the argument (before: ValueError from math.log10, TypeError,
    or the value returned as if known)."""
    with pytest.raises(ConfigError) as info:
        call()
    assert info.value.key == key


def test_a_run_report_read_back_from_json_is_ok_as_its_run_exited():
    """``ok`` of a report rebuilt from its JSON (no exit code: a program that stored it)
    follows the command's rule on what the report says: a run that ended well is ok, the
    same report with a device lost or a safety stop is not (before: the 1-D report's
    ``ok`` was an AttributeError, the n-D one's always True)."""
    rep = hapsim.run(WALL, lockstep=True, transport="inprocess", duration=0.5,
                     handle_signals=False)
    assert rep.exit_code == 0 and rep.ok
    back = api.RunReport.from_dict(json.loads(json.dumps(rep.to_dict())))
    assert back.ok
    lost = {**rep.to_dict(), "error": {"type": "DeviceError", "message": "lost"}}
    assert not api.RunReport.from_dict(lost).ok
    stopped = {**rep.to_dict(), "loop": {**rep.loop, "safety_stop": "position"}}
    assert not api.RunReport.from_dict(stopped).ok
    nd = api.run_nd(hapsim.load_scene(PANTOGRAPH))
    d = json.loads(json.dumps(nd.to_dict()))
    assert api.RunReportND.from_dict(d).ok == nd.ok
    assert not api.RunReportND.from_dict({**d, "error": {"type": "DeviceError",
                                                         "message": "lost"}}).ok
    assert not api.RunReportND.from_dict({**d, "safety": {"stop": "position"}}).ok
    assert not api.RunReportND.from_dict({**d, "realtime": {"stop": "safety: x"}}).ok
    # a report that carries its exit code keeps it
    assert not api.RunReportND.from_dict(d, exit_code=1).ok


def test_the_device_file_states_the_identifications_force_limit():
    """``IdentifyReport.device_yaml()`` without a force limit states the one the
    excitation ran with (before: 2 N whatever it was); a given one is checked."""
    rep = api.identify(lockstep=True, transport="inprocess", duration=1.0, force_limit=0.5)
    text = rep.device_yaml()
    assert "within 0.5 N" in text and "within 2 N" not in text, text
    assert "within 0.25 N" in rep.device_yaml(0.25)
    for bad in (math.nan, -1.0, 0.0, True, "x", math.inf):
        with pytest.raises(ConfigError) as info:
            rep.device_yaml(bad)
        assert info.value.key == "force_limit"
    with pytest.raises(ConfigError) as info:
        rep.device_yaml(driver="haply")
    assert info.value.key == "driver"
    # calibrate_scale: reports with their fits, through the driver they name
    from hapsim.drivers import get_driver
    back = api.IdentifyReport.from_dict(rep.to_dict())
    for args, key in (((back, rep, 0.05, get_driver("haply")), "bare"),
                      ((rep, 1.0, 0.05, get_driver("haply")), "loaded"),
                      ((rep, rep, 0.05, "firefader"), "driver"),
                      ((rep, rep, 0.05, get_driver("haply")), "driver"),
                      ((rep, rep, None, get_driver("haply")), "--added-mass"),
                      ((rep, rep, 1e300, get_driver("haply")), "--added-mass")):
        with pytest.raises(ConfigError) as info:
            api.calibrate_scale(*args)
        assert info.value.key == key, (args, info.value)


#: excite_and_fit's keywords against values of the wrong kind or range, each refused
#: by its flag before any device is started (before: only max_delay was checked).
EXCITE_BAD = [("baud", math.nan), ("baud", 0), ("baud", True), ("force_limit", "x"),
              ("force_limit", None), ("force_limit", True), ("envelope", [1]),
              ("duration", None), ("duration", 1e300), ("rate_hz", math.nan),
              ("rate_hz", math.inf), ("rate_hz", "x"), ("seed", -1), ("seed", None),
              ("max_delay", None), ("max_delay", -1), ("rt_priority", "x"),
              ("rt_priority", math.nan), ("lockstep", "no"), ("progress", math.nan),
              ("handle_signals", [1]), ("device", 1.0), ("device", 0),
              ("driver_options", "x"), ("mock_options", "x"), ("travel", True),
              ("travel", "x"), ("transport", 3)]


@pytest.mark.parametrize("key, value", EXCITE_BAD)
def test_excite_and_fit_refuses_a_bad_keyword_by_its_flag(key, value):
    kw = dict(lockstep=True, transport="inprocess", duration=0.5, progress=False,
              handle_signals=False)
    with pytest.raises(ConfigError) as info:
        api.excite_and_fit(**{**kw, key: value})
    got = info.value.key
    assert got is not None and key.replace("_hz", "").replace("_", "-") in got.replace(
        "_", "-").replace("protocol-option", "driver-options").replace(
        "mock-option", "mock-options"), (key, got, str(info.value))


def test_options_of_a_driver_without_one_and_a_driver_in_process_are_refused():
    """A driver's options with no driver (before: ignored), and a driver over the
    in-process transport (before: its board ran over a pty all the same, with the
    in-process link's 0.5 s timeout, and the report said 'inprocess')."""
    kw = dict(lockstep=True, transport="inprocess", duration=0.5, progress=False,
              handle_signals=False)
    with pytest.raises(ConfigError) as info:
        api.excite_and_fit(**kw, driver_options={"device_id": 1})
    assert info.value.key == "--protocol-option"
    with pytest.raises(ConfigError) as info:
        api.identify(driver="firefader", lockstep=True, transport="inprocess",
                     duration=0.5)
    assert info.value.key == "transport" and "pty, serial" in str(info.value)


#: RunOptions fields a program sets (no flag), with values of the wrong kind.
PROGRAM_BAD = [("transport", "word"), ("stop", "word"), ("handle_signals", "word"),
               ("on_start", "word"), ("on_precheck", 3), ("telemetry_interval", -1.0),
               ("telemetry_interval", math.nan), ("driver_options", "x"),
               ("mock_options", "word"), ("driver_faults", 5)]


@pytest.mark.parametrize("key, value", PROGRAM_BAD)
def test_a_programs_run_option_of_the_wrong_kind_is_refused_in_every_dimension(key, value):
    """The same refusal, keyed by the field, from a 2-D run and a 1-D one (before: the
    n-D run took each and said "within"; the 1-D one ran, or failed with a TypeError
    at its start)."""
    o = RunOptions(lockstep=True, handle_signals=False)
    with pytest.raises(ConfigError) as info:
        api.run_scene_nd(PANTOGRAPH, dataclasses.replace(o, **{key: value}))
    assert info.value.key == key
    with pytest.raises(ConfigError) as info:
        hapsim.run(WALL, lockstep=True, duration=0.2, **{"handle_signals": False,
                                                         key: value})
    assert info.value.key == key


@pytest.mark.parametrize("scene, options, key", [
    (None, RunOptions(), "scene"), (1.0, RunOptions(), "scene"),
    ("wall", RunOptions(), "scene"), ("pw", None, "options"), ("pw", "x", "options")])
def test_run_scene_nd_refuses_what_is_no_scene_or_options(scene, options, key):
    scenes = {"wall": hapsim.load_scene(WALL), "pw": hapsim.load_scene(PANTOGRAPH)}
    with pytest.raises(ConfigError) as info:
        api.run_scene_nd(scenes.get(scene, scene) if isinstance(scene, str) else scene,
                         options)
    assert info.value.key == key


@pytest.mark.parametrize("amplitude", [True, math.nan, -1e-3, 0.0, "x", math.inf])
def test_an_amplitude_that_is_no_length_is_refused(amplitude):
    """``amplitude=True`` was taken as 1 m by ``run`` and ``run_scene_nd``."""
    with pytest.raises(ConfigError):
        hapsim.run(PANTOGRAPH, lockstep=True, amplitude=amplitude, handle_signals=False)
    with pytest.raises(ConfigError):
        api.run_scene_nd(PANTOGRAPH, RunOptions(lockstep=True, handle_signals=False),
                         amplitude)


def test_a_chart_goes_to_the_file_named_or_is_refused(tmp_path):
    """Every report's ``plot``: a path without an extension or to a folder is refused
    before drawing (before: the 2-D/3-D charts wrote ``x.png`` beside ``x``); a target
    that is no path and no axes is refused, keyed ``plot``; axes are refused by the
    charts that draw a figure of their own (before: ignored)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ax = plt.figure().add_subplot()
    pw = hapsim.load_scene(PANTOGRAPH)
    reports = {"check": api.check(hapsim.load_scene(WALL)), "check_nd": api.check_nd(pw),
               "modes_nd": api.modes_nd(hapsim.load_scene(str(CONFIGS / "membrane.yaml")))}
    own_figure = {"check_nd", "modes_nd"}
    for name, rep in reports.items():
        for target in (str(tmp_path / "noext"), str(tmp_path), 123, [1]) + (
                (ax,) if name in own_figure else ()):
            with pytest.raises(ConfigError) as info:
                rep.plot(target)
            assert info.value.key == "plot", (name, target)
        assert not (tmp_path / "noext.png").exists() and not Path(f"{tmp_path}.png").exists()
        path = tmp_path / f"{name}.png"
        rep.plot(str(path))
        assert path.stat().st_size > 0
    plt.close("all")


@pytest.mark.parametrize("bad", [None, 1, "word", [1]])
def test_every_report_refuses_what_is_no_json_object(bad):
    """``from_dict`` of every report class of the API with what is no JSON object: a
    ConfigError keyed ``d`` (before: an AttributeError on ``.get``)."""
    from hapsim.results import Report
    classes = [getattr(api, n) for n in api.__all__ if isinstance(getattr(api, n), type)
               and issubclass(getattr(api, n), Report) and getattr(api, n) is not Report]
    assert len(classes) >= 15
    for cls in classes:
        with pytest.raises(ConfigError) as info:
            cls.from_dict(bad)
        assert info.value.key == "d", cls


@pytest.mark.parametrize("empty", [0, "", False, {}])
def test_a_list_section_given_as_no_list_is_refused_by_its_key(tmp_path, empty):
    """Every shipped scene, each top-level section that is a list (masses, links,
    planes, ...) replaced by a value that is no list but reads as false: refused at its
    key by every reader (before: the 2-D/3-D reader took ``links: 0`` and ``planes: 0``
    as none, where the 1-D one refused them)."""
    import yaml
    tried = 0
    for path in sorted(CONFIGS.glob("*.yaml")):
        doc = yaml.safe_load(path.read_text())
        for key in [k for k, v in doc.items() if isinstance(v, list)]:
            out = tmp_path / f"{path.stem}_{key}.yaml"
            out.write_text(yaml.safe_dump({**doc, key: empty}, sort_keys=False))
            with pytest.raises(ConfigError) as info:
                hapsim.load_scene(str(out))
            assert info.value.key == key, (path.name, key, str(info.value))
            tried += 1
    assert tried >= 30


def test_a_2d_or_3d_scene_without_its_dimension_is_told_to_give_it(tmp_path):
    """Every shipped 2-D and 3-D scene with its ``dimension`` line deleted: read as 1-D,
    it is refused at its first key a 1-D scene does not have, saying to give the
    dimension (before: "unknown key 'kind'; valid keys: mass, friction, ..." of the
    3-D device, which hid why)."""
    import yaml
    tried = 0
    for path in sorted(CONFIGS.glob("*.yaml")):
        doc = yaml.safe_load(path.read_text())
        if doc.get("dimension", 1) == 1:
            continue
        out = tmp_path / path.name
        out.write_text("".join(line for line in path.read_text().splitlines(True)
                               if not line.startswith("dimension:")))
        with pytest.raises(ConfigError) as info:
            hapsim.load_scene(str(out))
        assert "add dimension: 2 (or 3)" in str(info.value), (path.name, str(info.value))
        assert info.value.line is not None and info.value.key is not None
        tried += 1
    assert tried >= 5


def test_the_added_mass_calibration_says_which_way_the_masses_miss():
    """:func:`hapsim.analysis.calibration.full_scale_from_added_mass` over random
    intervals: apart and heavier with the mass, a gain whose interval holds the exact
    ratio ``added / (m2 - m1)`` of the intervals' ends; overlapping, "not resolved";
    apart and lighter with the mass, "swapped" (before: said to overlap)."""
    from types import SimpleNamespace as E

    from hapsim.analysis.calibration import full_scale_from_added_mass
    rng = np.random.default_rng(7)
    seen = {"resolved": 0, "overlap": 0, "swapped": 0}
    for _ in range(300):
        c1, c2 = rng.uniform(0.05, 0.2, 2)
        w1, w2 = rng.uniform(0.001, 0.05, 2)
        m1 = E(value=c1, lo=c1 - w1, hi=c1 + w1)
        m2 = E(value=c2, lo=c2 - w2, hi=c2 + w2)
        if m2.lo > m1.hi:
            sc = full_scale_from_added_mass(m1, m2, 0.05, 0.39)
            assert sc.gain_lo <= 0.05 / (c2 - c1) <= sc.gain_hi
            seen["resolved"] += 1
            continue
        with pytest.raises(ConfigError) as info:
            full_scale_from_added_mass(m1, m2, 0.05, 0.39)
        if m2.hi < m1.lo:
            assert "swapped" in str(info.value) and "overlap" not in str(info.value)
            seen["swapped"] += 1
        else:
            assert "overlap" in str(info.value)
            seen["overlap"] += 1
    assert min(seen.values()) >= 20, seen


def test_a_kinematic_devices_friction_is_refused_at_the_key_it_was_given_by(tmp_path):
    """Every shipped pantograph and delta scene, its ``joint_friction`` raised until the
    Cartesian friction's ``b0 T/m`` passes the bound: refused at ``device.joint_friction``
    and its line (before: keyed ``device.friction``, a key the file does not have, at
    the device's line)."""
    import yaml
    tried = 0
    for path in sorted(CONFIGS.glob("*.yaml")):
        doc = yaml.safe_load(path.read_text())
        dev = doc.get("device") or {}
        if "joint_friction" not in dev:
            continue
        n = len(dev["joints"])
        for big in (1e30, 1e300):
            dev = {**dev, "joint_friction": [big] * n}
            out = tmp_path / path.name
            out.write_text(yaml.safe_dump({**doc, "device": dev}, sort_keys=False))
            with pytest.raises(ConfigError) as info:
                hapsim.load_scene(str(out))
            assert info.value.key == "device.joint_friction", str(info.value)
            lines = out.read_text().splitlines()
            assert "joint_friction" in lines[info.value.line - 1], str(info.value)
            tried += 1
    assert tried >= 4


def test_a_duplicate_key_is_named_by_its_whole_path(tmp_path):
    """Every block-style ``key: value`` line of every shipped scene, written twice: the
    refusal names the key by its whole dotted path, as every other message of a scene
    names keys (``device.mass``, ``masses[3].x0``; before: the bare ``mass``), at the
    second line. The paths expected are read from the file's own parse."""
    import re

    from hapsim._yaml_lines import LDict, LList, load_yaml

    def paths(node, prefix, out):
        if isinstance(node, LDict):
            for k, v in node.items():
                p = f"{prefix}.{k}" if prefix else str(k)
                out.setdefault(node.lines[k], p)
                paths(v, p, out)
        elif isinstance(node, LList):
            for i, v in enumerate(node):
                paths(v, f"{prefix}[{i}]", out)
        return out
    tried = 0
    for path in sorted(CONFIGS.glob("*.yaml")):
        text = path.read_text()
        by_line = paths(load_yaml(text, str(path)), "", {})
        lines = text.splitlines(True)
        depth = 0                               # open flow brackets before the line
        for i, line in enumerate(lines):
            code = line.split("#", 1)[0]
            inside, depth = depth > 0, depth + sum(map(code.count, "{[")) - sum(
                map(code.count, "}]"))
            m = re.match(r"^( *)([a-z_0-9]+): *[^\s#{\[][^{\[]*$", line)
            if m is None or inside or (i + 1) not in by_line or tried > 400:
                continue
            out = tmp_path / "dup.yaml"
            out.write_text("".join(lines[:i + 1] + [line] + lines[i + 1:]))
            with pytest.raises(ConfigError) as info:
                hapsim.load_scene(str(out))
            assert info.value.key == by_line[i + 1], (path.name, i + 1, str(info.value))
            assert info.value.line == i + 2 and "duplicate key" in str(info.value)
            tried += 1
    assert tried >= 40


def test_run_report_nd_refuses_what_is_no_measurement():
    """:func:`hapsim.api.run_report_nd` (public) with a scene, a result, a lockstep flag
    or port facts of the wrong kind: a ConfigError keyed by the argument (before: an
    AttributeError, a KeyError, or ``[1.0]`` taken as lockstep True)."""
    from hapsim.lockstep import measure_felt_lockstep
    pw = hapsim.load_scene(PANTOGRAPH)
    res = measure_felt_lockstep(pw, 1e-8)
    assert api.run_report_nd(pw, res, True).lockstep is True
    for args, key in (((None, res, True), "scene"), ((pw, {}, True), "res"),
                      ((pw, [res], True), "res"), ((pw, res, [1.0]), "lockstep"),
                      ((pw, res, "yes"), "lockstep"), ((pw, res, True, "word"), "port_info")):
        with pytest.raises(ConfigError) as info:
            api.run_report_nd(*args)
        assert info.value.key == key, args


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")   # (its subject)
@pytest.mark.parametrize("far", [1e100, 1e200, 1e300])
def test_a_record_the_fit_cannot_take_is_not_measurable_not_a_traceback(tmp_path, far):
    """The shipped wall with its ground ``far`` metres away: the loop pushes the hand at
    its force limit until the safety stop, and the record's fit has no finite covariance.
    The run reports it (a verdict, exit 1 for the safety stop) where a LinAlgError came
    out of ``hapsim run`` before."""
    text = Path(WALL).read_text().replace("{name: wall, kind: ground, x0: 0.0}",
                                          f"{{name: wall, kind: ground, x0: {far!r}}}")
    assert repr(far) in text
    path = tmp_path / "far.yaml"
    path.write_text(text)
    rep = hapsim.run(str(path), lockstep=True, transport="inprocess", duration=0.3,
                     handle_signals=False)
    assert rep.verdict is not None and rep.within is not True, rep.verdict
