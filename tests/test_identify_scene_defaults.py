"""``hapsim identify --mock-scene configs/X.yaml`` with nothing else identifies every shipped
1-D scene's device (hapsim.pipeline.identify_settings), or refuses the scene by name.

The class: every scene of configs/. A 1-D scene with a device identifies with the command's
defaults, through the protocol its device names (every 1-D device family of
:data:`hapsim.drivers.FAMILIES` is named by one), its mass and friction inside their
intervals; a scene without a device, one with several ports, and a 2-D or 3-D scene without
--lockstep are refused by name (as before these defaults; the 2-D and 3-D scenes' lockstep
identification is tests/test_identify_matrices.py's). Identical settings are one
identification: the scenes are grouped by what identify runs with (protocol, device, rate,
duration, force limit, envelope), five groups for the 16 one-device 1-D scenes.

Cost: about 10 CPU-s in all (the five identifications in lockstep; the FireFader's through
the command line in-process, its JSON read). No tolerance: each truth is inside the
interval the fit states (nominally 99.9 %: docs/identify.md), no figure of ours beside it.
"""

from __future__ import annotations

import json
import pathlib

import pytest

from hapsim import load_scene
from hapsim.api import identify
from hapsim.drivers import DEFAULT, FAMILIES
from hapsim.errors import ConfigError
from hapsim.pipeline.identify_settings import identify_settings

ROOT = pathlib.Path(__file__).resolve().parent.parent
CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))


def _classify():
    """Each shipped scene as ``(path, kind, scene)``: ``"ports"``, ``"nd"``, ``"none"`` (no
    device) or ``"1d"`` (a one-device 1-D scene, the class identified)."""
    from hapsim.scene import scene_has_ports
    out = []
    for path in CONFIGS:
        if scene_has_ports(str(path)):
            out.append((path, "ports", None))
            continue
        scene = load_scene(str(path))
        if getattr(scene, "dimension", 1) > 1:
            out.append((path, "nd", scene))
        elif scene.device is None:
            out.append((path, "none", scene))
        else:
            out.append((path, "1d", scene))
    return out


def _groups():
    """The one-device 1-D scenes grouped by the settings identify runs them with: a dict
    ``key -> [paths]``, the key the settings' repr (device included)."""
    groups: dict = {}
    for path, kind, scene in _classify():
        if kind == "1d":
            st = identify_settings(scene)
            key = repr((st.driver, st.rate_hz, st.duration, st.force_limit, st.envelope,
                        st.device, sorted((st.driver_options or {}).items())))
            groups.setdefault(key, []).append(path)
    return groups


GROUPS = sorted(_groups().values(), key=lambda ps: ps[0].name)


def test_every_shipped_scene_is_in_the_class_and_every_1d_family_is_named():
    kinds = {p.name: k for p, k, _ in _classify()}
    assert set(kinds.values()) <= {"ports", "nd", "none", "1d"}
    named = {identify_settings(s).driver for _, k, s in _classify() if k == "1d"}
    families = {f.name for f in FAMILIES if f.dimension <= 1}
    assert named == families, f"1-D families no shipped scene names: {families - named}"
    assert sum(len(g) for g in GROUPS) == sum(k == "1d" for k in kinds.values())


@pytest.mark.parametrize("paths", [g for g in GROUPS
                                   if identify_settings(load_scene(str(g[0]))).driver
                                   != "firefader"],
                         ids=lambda ps: "+".join(p.stem for p in ps))
def test_a_shipped_scene_identifies_with_the_defaults(paths):
    scene = load_scene(str(paths[0]))
    st = identify_settings(scene)
    # the framed mock in-process (lockstep); a driver's embedded mock is lockstep itself
    rep = identify(scene=str(paths[0]),
                   transport="inprocess" if st.driver == DEFAULT else None)
    fit, dev = rep.fit, scene.device
    assert rep.loop["stop_reason"] == "duration" and not rep.loop["safety_stop"]
    assert fit.explained, fit.verdict
    assert fit.mass.lo <= dev.mass <= fit.mass.hi, (paths, fit.mass)
    assert fit.friction.lo <= dev.friction <= fit.friction.hi, (paths, fit.friction)
    # its words in the protocol's units: a rotary joint's (the Haply's) in radians and
    # newton metres (hapsim.drivers.base.Driver.rotary), every other in metres and newtons
    from hapsim.drivers import get_driver
    text = rep.device_yaml(st.force_limit, driver=None if st.driver == DEFAULT else
                           get_driver(st.driver, **(st.driver_options or {})))
    # the report knows the driver it identified through: without one it says the same
    assert rep.device_yaml(st.force_limit) == text
    if st.driver == "haply":
        assert "urad" in fit.verdict and " um" not in fit.verdict, fit.verdict
        assert "[kg m^2]" in text and "N m)" in text, text
    else:
        assert "urad" not in fit.verdict and "[kg m^2]" not in text, (fit.verdict, text)


def test_the_firefader_scene_identifies_on_the_command_line_with_nothing_else(capsys):
    """The issue: refused for its 0.725-period delay (no --driver), then 'hardly moved' in
    4 s; now its device.protocol and 8.8 s at 250 Hz."""
    from hapsim.cli import main
    path = ROOT / "configs" / "firefader.yaml"
    code = main(["identify", "--mock-scene", str(path), "--json"])
    doc = json.loads(capsys.readouterr().out)
    dev = load_scene(str(path)).device
    assert code == 0, doc["device"]["verdict"]
    assert doc["loop"]["settings"]["duration"] == 8.8 and doc["loop"]["settings"]["rate_hz"] == 250.0
    assert "device.protocol" in doc["loop"]["settings"]["protocol"]
    m, b = doc["device"]["mass"], doc["device"]["friction"]
    assert m["lo"] <= dev.mass <= m["hi"] and b["lo"] <= dev.friction <= b["hi"], (m, b)


@pytest.mark.parametrize("kind", ["ports", "none", "nd"])
def test_a_scene_that_cannot_be_identified_so_is_refused_by_name(kind):
    paths = [p for p, k, _ in _classify() if k == kind]
    assert paths, kind
    for path in paths:
        # 2-D, 3-D: without --lockstep (its lockstep run: test_identify_matrices.py)
        with pytest.raises(ConfigError) as exc:
            _cli(["identify", "--mock-scene", str(path)])
        key = {"ports": "devices", "none": "device", "nd": "--lockstep"}[kind]
        assert exc.value.key == key, str(exc.value)


def _cli(argv):
    """The command's function on parsed arguments (its ConfigError raised, not printed)."""
    import argparse

    from hapsim.commands import identify as cmd
    parser = argparse.ArgumentParser()
    cmd.register(parser.add_subparsers())
    args = parser.parse_args(argv)
    return args.func(args)


ONE_D_DRIVERS = [f.name for f in FAMILIES if f.dimension == 1 and f.driver]


@pytest.mark.parametrize("name", ONE_D_DRIVERS)
def test_without_a_scene_every_1d_protocols_defaults_are_held_by_its_board(name):
    """``hapsim identify --driver NAME`` with nothing else (over a port or on the mock):
    the default rate is one the board holds (its own refusal, :meth:`check_rate`, is the
    test), 1000 Hz where it can (before, 1000 Hz for every board: refused on the FireFader
    and the Hapkit sketch), and the envelope spans more than a few of the protocol's
    encoder counts. The rate and envelope are derived from the driver, not listed here:
    a new 1-D family is in the class."""
    from hapsim.drivers import get_driver
    from hapsim.pipeline.identify_settings import DEFAULT_RATE_HZ, RATE_LADDER
    st = identify_settings(None, driver=name)
    drv = get_driver(name, **(st.driver_options or {}))
    drv.check_rate(st.rate_hz)                              # held: no ConfigError
    # the highest the ladder offers it: the default never leaves a higher held rate
    higher = [r for r in drv.board_rates(RATE_LADDER) if r > st.rate_hz]
    assert not higher and st.rate_hz <= DEFAULT_RATE_HZ, (st.rate_hz, higher)
    # the mock's device is the protocol's own where it has one, hapsim's default else
    assert (st.device is None) == (drv.identify_device is None), st.device
    assert st.envelope >= (drv.identify_envelope or 0.01)


def test_the_haply_joint_identifies_with_nothing_but_its_driver():
    """The Haply joint without a scene, in lockstep: the protocol's own device and reach
    (:attr:`hapsim.drivers.haply.HaplyDriver.identify_device`): its inertia and friction
    inside their intervals, in its units. Before: hapsim's default mock device (0.1
    kg m^2 read as an inertia) did not turn under the board's 0.123 N m ("the motor
    direction cannot be found"), and 0.01 rad spans 8 of its counts. About 2.5 CPU-s."""
    rep = identify(driver="haply", lockstep=True)
    dev = identify_settings(None, driver="haply").device
    fit = rep.fit
    assert fit.explained, fit.verdict
    assert fit.mass.lo <= dev.mass <= fit.mass.hi, fit.mass
    assert fit.friction.lo <= dev.friction <= fit.friction.hi, fit.friction
    assert rep.loop["settings"]["driver"] == "haply"
    assert rep.loop["settings"]["protocol"] == "the haply protocol (--driver)"
    assert "[kg m^2]" in rep.device_yaml(0.123)
