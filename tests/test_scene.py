"""Scene validation: every malformed case names the file, the line and the key."""

from __future__ import annotations

import dataclasses
import math
import textwrap

import pytest

from hapsim.cli import main
from hapsim.engine import Engine
from hapsim.errors import ConfigError, HapsimError
from hapsim.scene import Device, Link, Mass, Scene, load_scene, parse_scene

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
    # measured 0 (generic 0): exact on both targets
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
    ("device fractional delay, ideal hold", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\ndevice:\n  mass: 0.1\n  delay: 1.5\n  hold: ideal\n",
     5, "device.delay", "needs hold: zoh"),
    ("device delay not a number", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\ndevice:\n  mass: 0.1\n  delay: .nan\n",
     5, "device.delay", "must be a finite number"),
    ("device delay beyond the analysis", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\ndevice:\n  mass: 0.1\n  delay: 500.5\n",
     5, "device.delay", "between 0 and 500 periods"),
    ("device negative delay", "rate_hz: 1000\nmasses: [{name: p, kind: port}]\ndevice:\n  mass: 0.1\n  delay: -1\n",
     5, "device.delay", "must be between 0 and 500 periods"),
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


# ---------------------------------------------------------------- scenes built in code
# The same rules as a scene file: Scene validates itself when it is constructed, so a
# scene built in code (or changed with dataclasses.replace) never reaches the engine
# unvalidated either.

def _osc(**changes):
    """The oscillator of configs/oscillator.yaml built in code, with some fields changed."""
    masses = [Mass("anchor", "ground"), Mass("bob", "mass", 0.1, 0.01)]
    links = [Link("spring", "spring_damper", "bob", "anchor", 1000.0, 0.0)]
    if "bob" in changes:
        masses[1] = dataclasses.replace(masses[1], **changes.pop("bob"))
    if "spring" in changes:
        links[0] = dataclasses.replace(links[0], **changes.pop("spring"))
    return Scene(**{"rate_hz": 1000.0, "masses": tuple(masses), "links": tuple(links),
                    **changes})


# (id, changes to the code-built oscillator, key, message fragment, the same mistake in YAML)
CODE_CASES = [
    ("negative rate", {"rate_hz": -5}, "rate_hz", "must be > 0, got -5", "rate_hz: -5"),
    ("negative stiffness", {"spring": {"stiffness": -1.0}}, "links[0].stiffness",
     "must be >= 0, got -1", "stiffness: -1.0"),
    ("negative damping", {"spring": {"damping": -0.5}}, "links[0].damping",
     "must be >= 0, got -0.5", "damping: -0.5"),
    ("kind rock", {"bob": {"kind": "rock"}}, "masses[1].kind",
     "unknown value 'rock'; valid choices: mass, ground, port", "kind: rock"),
    ("zero mass", {"bob": {"mass": 0.0}}, "masses[1].mass", "must be > 0, got 0", "mass: 0.0"),
    ("link to a missing mass", {"spring": {"m2": "ankor"}}, "links[0].between",
     "no mass named 'ankor'; masses are: anchor, bob", "between: [bob, ankor]"),
    ("link to itself", {"spring": {"m2": "bob"}}, "links[0].between",
     "a link cannot join mass 'bob' to itself", "between: [bob, bob]"),
    ("nan stiffness", {"spring": {"stiffness": math.nan}}, "links[0].stiffness",
     "must be a finite number", "stiffness: .nan"),
    ("unknown integrator", {"integrator": "rk4"}, "integrator",
     "unknown value 'rk4'; valid choices: centred, symplectic_euler, exact", "integrator: rk4"),
]

OSC_YAML = """\
rate_hz: 1000
masses:
  - {name: anchor, kind: ground}
  - {name: bob, kind: mass, mass: 0.1, x0: 0.01}
links:
  - {name: spring, kind: spring_damper, between: [bob, anchor], stiffness: 1000.0, damping: 0.0}
"""


def _yaml_with(fragment):
    """OSC_YAML with one value replaced by ``fragment`` (``key: value``)."""
    key = fragment.split(":")[0]
    if key == "integrator":
        return OSC_YAML + fragment + "\n"
    if key == "rate_hz":
        return OSC_YAML.replace("rate_hz: 1000", fragment)
    lines = OSC_YAML.splitlines(keepends=True)
    row = 5 if key in ("stiffness", "damping", "between") else 3
    import re
    lines[row] = re.sub(rf"{key}: (\[[^\]]*\]|[^,}}]+)", fragment, lines[row], count=1)
    assert fragment in lines[row]
    return "".join(lines)


@pytest.mark.parametrize("desc,changes,key,fragment,yaml_fragment", CODE_CASES,
                         ids=[c[0] for c in CODE_CASES])
def test_scene_built_in_code_is_validated_like_a_file(desc, changes, key, fragment,
                                                     yaml_fragment):
    with pytest.raises(ConfigError) as info:
        _osc(**changes)
    err = info.value
    assert isinstance(err, ValueError) and isinstance(err, HapsimError)
    assert err.key == key and fragment in err.reason, str(err)
    assert err.file is None and err.line is None          # built in code: no file, no line
    assert str(err) == f"{key}: {err.reason}"
    # one set of rules: the same mistake in a file gives the same message, with its line
    with pytest.raises(ConfigError) as from_file:
        parse_scene(_yaml_with(yaml_fragment), "osc.yaml")
    assert from_file.value.reason == err.reason and from_file.value.key == key
    assert from_file.value.line is not None


def test_engine_refuses_what_it_used_to_step():
    """What the engine accepted before (and stepped, or crashed on) is now a ConfigError."""
    good = _osc()
    for bad in ({"rate_hz": -5}, {"spring": {"stiffness": -1.0}}, {"bob": {"kind": "rock"}},
                {"bob": {"mass": 0.0}}, {"spring": {"m2": "nope"}}):
        with pytest.raises(ConfigError):
            Engine(_osc(**bad))
    # ... and dataclasses.replace is no back door
    with pytest.raises(ConfigError, match=r"masses\[1\]\.mass: must be > 0"):
        dataclasses.replace(good, masses=(good.masses[0], dataclasses.replace(good.masses[1],
                                                                              mass=-1.0)))
    assert Engine(good).run(3)[1].shape == (4, 2)


def test_code_change_to_a_file_scene_names_file_and_line():
    """A scene read from a file and then broken in code names the file and the entry's line."""
    s = load_scene("configs/oscillator.yaml")
    text = open("configs/oscillator.yaml").read().splitlines()
    bob_line = next(i + 1 for i, ln in enumerate(text) if "name: bob" in ln)
    spring_line = next(i + 1 for i, ln in enumerate(text) if "name: spring" in ln)
    with pytest.raises(ConfigError) as info:
        dataclasses.replace(s, masses=(s.masses[0], dataclasses.replace(s.masses[1], mass=0)))
    assert str(info.value) == (f"configs/oscillator.yaml:{bob_line}: masses[1].mass: "
                               "must be > 0, got 0")
    with pytest.raises(ConfigError) as info:
        s.with_link("spring", stiffness=math.inf, damping=0.0)
    assert str(info.value).startswith(f"configs/oscillator.yaml:{spring_line}: "
                                      "links[0].stiffness: must be a finite number")
    with pytest.raises(ConfigError, match=r"configs/oscillator.yaml: rate_hz: must be > 0"):
        s.with_rate(0.0)


def test_calibrated_links_may_have_negative_damping_hand_built_ones_may_not():
    """B < 0 arises from calibration (real friction above the felt damping, docs/design.md,
    'The forward map'):
    Scene.with_link marks the link calibrated; a file or a hand-built link cannot."""
    s = load_scene("configs/felt_wall.yaml")
    cal = s.with_link("wall", stiffness=900.0, damping=-0.2)
    assert cal.link("wall").calibrated and cal.link("wall").damping == -0.2
    # measured 0 (generic 0): exact on both targets
    assert Engine(cal).port_step(0.001) == pytest.approx(-0.9 + 0.2)
    osc = _osc().with_link("spring", stiffness=1000.0, damping=-0.01)   # active element
    assert osc.link("spring").damping == -0.01
    with pytest.raises(ConfigError, match=r"links\[0\]\.damping: must be >= 0"):
        _osc(spring={"damping": -0.01})
    # calibration must write numbers: NaN means "awaiting calibration", nothing else
    with pytest.raises(ConfigError, match=r"links\[0\]\.stiffness: must be a finite number"):
        s.with_link("wall", stiffness=math.nan, damping=1.0)
    with pytest.raises(ConfigError, match=r"links\[0\]\.damping: must be a finite number"):
        _osc(spring={"damping": math.nan})                  # no target: NaN is just wrong
    awaiting = dataclasses.replace(s, links=(dataclasses.replace(s.links[0], line=0),))
    assert awaiting.unresolved_targets                       # a target link built in code


def test_code_scene_structure_rules():
    good = _osc()
    with pytest.raises(ConfigError, match=r"^masses: must be a non-empty list"):
        dataclasses.replace(good, masses=())
    with pytest.raises(ConfigError, match=r"^masses\[1\]\.name: duplicate mass name 'anchor' "
                                          r"\(first is masses\[0\]\)"):
        _osc(bob={"name": "anchor"})
    with pytest.raises(ConfigError, match=r"^links\[0\]\.threshold: only a contact"):
        _osc(spring={"threshold": 0.001})
    with pytest.raises(ConfigError, match=r"^links\[0\]\.kind: the exact integrator"):
        _osc(spring={"kind": "contact"}, integrator="exact")
    with pytest.raises(ConfigError, match=r"^device: a scene with a port needs a device"):
        Scene(1000.0, (Mass("p", "port"), Mass("g", "ground")),
              (Link("w", "spring_damper", "p", "g", 100.0),))
    with pytest.raises(ConfigError, match=r"^device\.delay: a delay of 1\.5 periods"):
        Scene(1000.0, (Mass("p", "port"),), (), device=Device(mass=0.1, delay=1.5,
                                                              hold="ideal"))
    assert Scene(1000.0, (Mass("p", "port"),), (),
                 device=Device(mass=0.1, delay=1.5)).device.delay == 1.5
    with pytest.raises(ConfigError, match=r"^masses\[0\]\.mass: must be 0 for a ground"):
        Scene(1000.0, (Mass("g", "ground", 2.0),), ())
    # lists are accepted and frozen into tuples
    sc = Scene(1000.0, [Mass("g", "ground")], [])
    assert sc.masses == (Mass("g", "ground"),) and sc.links == ()
