"""Scene validation: every malformed case names the file, the line and the key."""

from __future__ import annotations

import math
import textwrap

import pytest

from hapsim.cli import main
from hapsim.errors import ConfigError, HapsimError
from hapsim.scene import load_scene, parse_scene

GOOD = """\
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: 0.0}
  - {name: bob, kind: mass, mass: 0.01}
links:
  - {name: w, kind: spring_damper, between: [hand, wall], stiffness: 2000, damping: 2}
  - {name: c, kind: contact, between: [hand, bob], stiffness: 500, damping: 0.1, threshold: 0.0}
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10}
excitation: {x0: 0.002}
"""


def test_good_scene_parses():
    s = parse_scene(GOOD, "good.yaml")
    assert s.rate_hz == 1000 and s.period == pytest.approx(1e-3)
    assert [m.kind for m in s.masses] == ["port", "ground", "mass"]
    assert s.port.name == "hand" and s.index("bob") == 2
    assert s.links[1].threshold == 0.0 and s.links[0].line == 7
    assert s.device.delay == 1 and s.device.hold == "zoh" and s.device.force_limit == 10
    assert s.excitation.x0 == 0.002
    assert s.kinds == {"spring_damper", "contact"}


@pytest.mark.parametrize("name", ["wall", "string", "oscillator"])
def test_shipped_scenes_load(name):
    s = load_scene(f"configs/{name}.yaml")
    assert s.masses and s.rate_hz > 0


def test_string_has_50_masses_between_two_grounds_and_a_plucking_contact():
    s = load_scene("configs/string.yaml")
    assert sum(m.kind == "mass" for m in s.masses) == 50
    assert sum(m.kind == "ground" for m in s.masses) == 2
    assert [lk.kind for lk in s.links].count("contact") == 1


# (description, text, expected line, expected key, fragment of the message)
CASES = [
    ("missing rate_hz", "masses: [{name: a, kind: ground}]\n", 1, "rate_hz", "missing required key 'rate_hz'"),
    ("rate not a number", "rate_hz: fast\nmasses: [{name: a, kind: ground}]\n", 1, "rate_hz", "must be a number"),
    ("rate zero", "rate_hz: 0\nmasses: [{name: a, kind: ground}]\n", 1, "rate_hz", "must be > 0"),
    ("unknown top key", "rate_hz: 1000\nmases: []\nmasses: [{name: a, kind: ground}]\n", 2, "mases",
     "unknown key 'mases'; valid keys: rate_hz, masses, links, device, excitation"),
    ("unknown mass kind", "rate_hz: 1000\nmasses:\n  - {name: a, kind: rock}\n", 3, "masses[0].kind",
     "unknown value 'rock'; valid choices: mass, ground, port"),
    ("unknown mass key", "rate_hz: 1000\nmasses:\n  - {name: a, kind: mass, mass: 1, colour: red}\n", 3,
     "masses[0].colour", "valid keys: name, kind, mass, x0, v0"),
    ("non-positive mass", "rate_hz: 1000\nmasses:\n  - name: a\n    kind: mass\n    mass: -1\n", 5,
     "masses[0].mass", "must be > 0"),
    ("zero mass", "rate_hz: 1000\nmasses:\n  - {name: a, kind: mass, mass: 0}\n", 3, "masses[0].mass", "must be > 0"),
    ("mass is a string", "rate_hz: 1000\nmasses:\n  - {name: a, kind: mass, mass: heavy}\n", 3,
     "masses[0].mass", "must be a number, got a string 'heavy'"),
    ("mass is a boolean", "rate_hz: 1000\nmasses:\n  - {name: a, kind: mass, mass: true}\n", 3,
     "masses[0].mass", "must be a number, got a boolean"),
    ("duplicate mass name", "rate_hz: 1000\nmasses:\n  - {name: a, kind: ground}\n  - {name: a, kind: ground}\n",
     4, "masses[1].name", "duplicate mass name 'a' (first on line 3)"),
    ("missing mass name", "rate_hz: 1000\nmasses:\n  - {kind: ground}\n", 3, "masses[0].name", "missing required key 'name'"),
    ("masses not a list", "rate_hz: 1000\nmasses: 3\n", 2, "masses", "non-empty list"),
    ("negative stiffness", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: spring_damper, between: [a, b], stiffness: -5}\n", 4, "links[0].stiffness", "must be >= 0"),
    ("negative damping", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: spring_damper, between: [a, b], stiffness: 5, damping: -1}\n", 4, "links[0].damping",
     "must be >= 0"),
    ("link to missing mass", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: spring_damper, between: [a, c], stiffness: 5}\n", 4, "links[0].between",
     "no mass named 'c'; masses are: a, b"),
    ("link to itself", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: spring_damper, between: [b, b], stiffness: 5}\n", 4, "links[0].between",
     "cannot join mass 'b' to itself"),
    ("between not a pair", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: spring_damper, between: [a], stiffness: 5}\n", 4, "links[0].between", "two mass names"),
    ("unknown link kind", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: rope, between: [a, b]}\n", 4, "links[0].kind",
     "valid choices: spring_damper, contact"),
    ("threshold on a spring", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: spring_damper, between: [a, b], stiffness: 5, threshold: 1}\n", 4,
     "links[0].threshold", "valid keys: name, kind, between, stiffness, damping, target"),
    ("duplicate link name", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {name: s, kind: spring_damper, between: [a, b], stiffness: 5}\n"
     "  - {name: s, kind: spring_damper, between: [a, b], stiffness: 5}\n", 5, "links[1].name",
     "duplicate link name 's'"),
    ("link with neither", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: spring_damper, between: [a, b]}\n", 4, "links[0].stiffness", "needs stiffness"),
    ("target and stiffness", "rate_hz: 1000\nmasses: [{name: p, kind: port}, {name: g, kind: ground}]\n"
     "links:\n  - {kind: spring_damper, between: [p, g], stiffness: 5, target: {k: 1, b: 0}}\n"
     "device: {mass: 0.1}\n", 4, "links[0].target", "not both"),
    ("target not at port", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: spring_damper, between: [a, b], target: {k: 1, b: 0}}\n", 4, "links[0].target",
     "between the port and a ground"),
    ("port without device", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\n", 1, "device",
     "a scene with a port needs a device section"),
    ("two ports", "rate_hz: 1000\nmasses:\n  - {name: p, kind: port}\n  - {name: q, kind: port}\n"
     "device: {mass: 0.1}\n", 4, "masses", "at most one port"),
    ("device unknown hold", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\ndevice:\n  mass: 0.1\n  hold: foh\n",
     5, "device.hold", "valid choices: zoh, ideal"),
    ("device fractional delay", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\ndevice:\n  mass: 0.1\n  delay: 1.5\n",
     5, "device.delay", "whole number of samples"),
    ("device negative delay", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\ndevice:\n  mass: 0.1\n  delay: -1\n",
     5, "device.delay", "must be >= 0"),
    ("device unknown key", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\ndevice:\n  mass: 0.1\n  frcition: 1\n",
     5, "device.frcition", "valid keys: mass, friction, delay, hold, force_limit"),
    ("device missing mass", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\ndevice:\n  friction: 1\n", 4,
     "device.mass", "missing required key 'mass'"),
    ("excitation unknown key", "rate_hz: 1000\nmasses: [{name: a, kind: ground}]\nexcitation: {x1: 3}\n", 3,
     "excitation.x1", "valid keys: x0, v0, impulse, profile"),
    ("yaml syntax", "rate_hz: 1000\nmasses: [{name: a, kind: ground}\n", 3, None, "invalid YAML"),
    ("duplicate yaml key", "rate_hz: 1000\nrate_hz: 2000\nmasses: [{name: a, kind: ground}]\n", 2, "rate_hz",
     "duplicate key 'rate_hz' (first on line 1)"),
    ("not a mapping", "- 1\n- 2\n", 1, None, "must be a mapping"),
    ("empty file", "", 1, "rate_hz", "the scene is empty"),
    ("infinite stiffness", "rate_hz: 1000\nmasses: [{name: a, kind: ground}, {name: b, kind: mass, mass: 1}]\n"
     "links:\n  - {kind: spring_damper, between: [a, b], stiffness: .inf}\n", 4, "links[0].stiffness",
     "finite"),
]


@pytest.mark.parametrize("desc,text,line,key,fragment", CASES, ids=[c[0] for c in CASES])
def test_malformed_scene_names_file_line_key(desc, text, line, key, fragment):
    with pytest.raises(ConfigError) as info:
        parse_scene(text, "bad.yaml")
    err = info.value
    assert isinstance(err, ValueError) and isinstance(err, HapsimError)
    assert fragment in str(err)
    assert err.file == "bad.yaml"
    assert err.line == line, str(err)
    assert err.key == key, str(err)
    assert str(err).startswith(f"bad.yaml:{line}: ")


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read scene file"):
        load_scene(tmp_path / "nope.yaml")


def test_cli_reports_bad_scene_with_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(textwrap.dedent("""\
        rate_hz: 1000
        masses:
          - {name: a, kind: mass, mass: -1}
        """))
    code = main(["simulate", str(bad), "--steps", "10", "--out", str(tmp_path / "o.npz")])
    assert code == 2
    err = capsys.readouterr().err
    assert f"{bad}:3: masses[0].mass: must be > 0" in err
    assert not (tmp_path / "o.npz").exists()


def test_target_scene_has_nan_until_calibrated():
    s = parse_scene("rate_hz: 1000\nmasses: [{name: p, kind: port}, {name: g, kind: ground}]\n"
                    "links:\n  - {name: felt, kind: spring_damper, between: [p, g], target: {k: 1000, b: 3}}\n"
                    "device: {mass: 0.1}\n")
    lk = s.link("felt")
    assert lk.target == (1000.0, 3.0) and math.isnan(lk.stiffness)
    assert s.unresolved_targets == (lk,)
    s2 = s.with_link("felt", stiffness=900.0, damping=-0.2)
    assert s2.unresolved_targets == () and s2.link("felt").stiffness == 900.0
