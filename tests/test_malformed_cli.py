"""Malformed scenes through the CLI: one line on stderr naming file, line and key; exit 2.

Each case is a whole scene file with one mistake (YAML syntax, unknown keys, wrong types,
bad references, physically impossible values, an unrenderable target); the line the error
must name is marked ``#<``. Every case goes through ``hapsim run`` and ``hapsim check``
(``main(argv)``, no subprocess); the unrenderable target too, through both commands.
"""

from __future__ import annotations

import pytest

from hapsim.cli import main

HEAD = """\
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: 0.0}
"""
LINK = """\
links:
  - {name: wall, kind: spring_damper, between: [hand, wall], stiffness: 1000.0, damping: 1.5}
"""
DEVICE = """\
device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10.0}
"""
EXC = """\
excitation: {x0: 0.005}
"""


def scene(*parts):
    return "".join(parts)


# (id, text, key the message must name (None: YAML syntax, no key))
CASES = [
    # YAML syntax
    ("yaml-unclosed-list", "rate_hz: [1000\n#<\n", None),
    ("yaml-bad-indent", HEAD + "links:\n  - {name: w, kind: spring_damper\n   between: [a]}\n#<\n",
     None),
    ("yaml-tab", "rate_hz: 1000\nmasses:\n\t- {name: hand, kind: port} #<\n", None),
    ("yaml-duplicate-colon", "rate_hz: 1000: 2 #<\n", None),
    # unknown keys
    ("unknown-top", HEAD + LINK + DEVICE + "rate: 1000 #<\n", "rate"),
    ("unknown-mass-key", "rate_hz: 1000\nmasses:\n  - {name: hand, kind: port, mass: 1} #<\n"
     + "  - {name: wall, kind: ground}\n" + LINK + DEVICE, "masses[0].mass"),
    ("unknown-link-key", HEAD + "links:\n  - {name: w, kind: spring_damper, between: [hand, wall],"
     " stifness: 10} #<\n" + DEVICE, "links[0].stifness"),
    ("unknown-device-key", HEAD + LINK + "device:\n  mass: 0.1\n  fricton: 0.5 #<\n",
     "device.fricton"),
    ("unknown-excitation-key", HEAD + LINK + DEVICE + "excitation:\n  x: 0.1 #<\n",
     "excitation.x"),
    ("unknown-safety-key", HEAD + LINK + DEVICE + "safety:\n  energy: 1 #<\n", "safety.energy"),
    ("unknown-target-key", HEAD + "links:\n  - name: w\n    kind: spring_damper\n"
     "    between: [hand, wall]\n    target: {k: 1000, b: 2, z: 1} #<\n" + DEVICE,
     "links[0].target.z"),
    ("unknown-kind", HEAD + "links:\n  - {name: w, kind: spring, between: [hand, wall]} #<\n"
     + DEVICE, "links[0].kind"),
    ("unknown-hold", HEAD + LINK + "device:\n  mass: 0.1\n  hold: foh #<\n", "device.hold"),
    ("unknown-integrator", HEAD + LINK + DEVICE + "integrator: rk4 #<\n", "integrator"),
    # wrong types
    ("rate-string", "rate_hz: fast #<\nmasses:\n  - {name: a, kind: port}\n" + DEVICE,
     "rate_hz"),
    ("masses-not-list", "rate_hz: 1000\nmasses: 3 #<\n", "masses"),
    ("mass-not-mapping", "rate_hz: 1000\nmasses:\n  - hand #<\n", "masses[0]"),
    ("stiffness-string", HEAD + "links:\n  - {name: w, kind: spring_damper, between: [hand, wall],"
     " stiffness: stiff} #<\n" + DEVICE, "links[0].stiffness"),
    ("between-not-pair", HEAD + "links:\n  - {name: w, kind: spring_damper, between: hand,"
     " stiffness: 1} #<\n" + DEVICE, "links[0].between"),
    ("device-not-mapping", HEAD + LINK + "device: 0.1 #<\n", "device"),
    ("delay-fraction-ideal", HEAD + LINK + "device:\n  mass: 0.1\n  hold: ideal\n  delay: 1.5 #<\n",
     "device.delay"),
    ("delay-negative", HEAD + LINK + "device:\n  mass: 0.1\n  delay: -0.5 #<\n", "device.delay"),
    ("pc-not-bool", HEAD + LINK + DEVICE + "safety:\n  passivity_controller: yes please #<\n",
     "safety.passivity_controller"),
    ("bool-as-number", HEAD + LINK + "device:\n  mass: true #<\n", "device.mass"),
    # bad references
    ("unknown-mass-ref", HEAD + "links:\n  - {name: w, kind: spring_damper, between: [hand, wal],"
     " stiffness: 1} #<\n" + DEVICE, "links[0].between"),
    ("self-link", HEAD + "links:\n  - {name: w, kind: spring_damper, between: [hand, hand],"
     " stiffness: 1} #<\n" + DEVICE, "links[0].between"),
    ("duplicate-mass", "rate_hz: 1000\nmasses:\n  - {name: hand, kind: port}\n"
     "  - {name: hand, kind: ground} #<\n" + DEVICE, "masses[1].name"),
    ("profile-missing", HEAD + LINK + DEVICE + "excitation:\n  profile: nowhere.csv #<\n",
     "excitation.profile"),
    ("target-not-to-ground", "rate_hz: 1000\nmasses:\n  - {name: hand, kind: port}\n"
     "  - {name: bob, kind: mass, mass: 0.01}\nlinks:\n  - name: w\n    kind: spring_damper\n"
     "    between: [hand, bob]\n    target: {k: 100, b: 1} #<\n" + DEVICE, "links[0].target"),
    ("port-without-device", HEAD.replace("rate_hz: 1000\n", "rate_hz: 1000 #<\n") + LINK,
     "device"),
    # physically impossible values
    ("rate-zero", "rate_hz: 0 #<\nmasses:\n  - {name: a, kind: ground}\n", "rate_hz"),
    ("mass-negative", HEAD + LINK + "device:\n  mass: -0.1 #<\n", "device.mass"),
    ("friction-negative", HEAD + LINK + "device:\n  mass: 0.1\n  friction: -1 #<\n",
     "device.friction"),
    ("stiffness-negative", HEAD + "links:\n  - {name: w, kind: spring_damper, between: [hand,"
     " wall], stiffness: -5} #<\n" + DEVICE, "links[0].stiffness"),
    ("force-limit-zero", HEAD + LINK + "device:\n  mass: 0.1\n  force_limit: 0 #<\n",
     "device.force_limit"),
    ("virtual-mass-zero", HEAD + "  - {name: bob, kind: mass, mass: 0} #<\n" + LINK + DEVICE,
     "masses[2].mass"),
    ("nan-friction", HEAD + LINK + "device:\n  mass: 0.1\n  friction: .nan #<\n",
     "device.friction"),
    ("energy-limit-negative", HEAD + LINK + DEVICE + "safety:\n  energy_limit: -1 #<\n",
     "safety.energy_limit"),
    ("velocity-limit-zero", HEAD + LINK + DEVICE + "safety:\n  velocity_limit: 0 #<\n",
     "safety.velocity_limit"),
    ("max-damping-negative", HEAD + LINK + DEVICE + "safety:\n  max_damping: -2 #<\n",
     "safety.max_damping"),
    ("target-k-zero", HEAD + "links:\n  - name: w\n    kind: spring_damper\n"
     "    between: [hand, wall]\n    target: {k: 0, b: 1} #<\n" + DEVICE, "links[0].target.k"),
    ("two-ports", "rate_hz: 1000\nmasses:\n  - {name: a, kind: port}\n  - {name: b, kind: port}"
     " #<\n" + DEVICE, "masses"),
]

UNRENDERABLE = (HEAD + "links:\n  - {name: felt, kind: spring_damper, between: [hand, wall],"
                " target: {k: 50000.0, b: 0.01}} #<\n"
                "device: {mass: 0.1, friction: 0.0, delay: 2, hold: zoh, force_limit: 10.0}\n"
                + EXC)


def marked_line(text):
    lines = text.splitlines()
    hits = [i + 1 for i, ln in enumerate(lines) if ln.rstrip().endswith("#<")]
    assert len(hits) == 1
    return hits[0]


def check_error(err, path, line, key):
    # (an empty numba cache adds run's notice of what it compiles, said before the scene)
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("hapsim run: compil")]
    assert len(lines) == 1, err
    msg = lines[0]
    assert f"{path}:{line}:" in msg, msg
    if key is not None:
        assert f" {key}: " in msg, msg
    return msg


def test_at_least_30_cases():
    assert len(CASES) + 1 >= 30
    assert len({c[0] for c in CASES}) == len(CASES)


@pytest.mark.parametrize("cmd", ["run", "check"])
@pytest.mark.parametrize("name, text, key", CASES, ids=[c[0] for c in CASES])
def test_malformed_scene_exit_2_one_line(tmp_path, capsys, cmd, name, text, key):
    path = tmp_path / f"{name}.yaml"
    path.write_text(text)
    code = main([cmd, str(path)])
    err = capsys.readouterr().err
    assert code == 2, err
    line = marked_line(text)
    # YAML reports a syntax error where it noticed it: at or after the marked line
    if key is None:
        msg = err.strip()
        assert len(msg.splitlines()) == 1 and str(path) in msg and "invalid YAML" in msg
        got = int(msg.split(str(path) + ":")[1].split(":")[0])
        assert line - 1 <= got <= line + 1, msg
    else:
        check_error(err, path, line, key)


@pytest.mark.parametrize("command", [["run", "--lockstep"], ["check"]])
def test_unrenderable_target_is_a_negative_verdict(tmp_path, capsys, command):
    """Not renderable is a verdict (exit 1, as calibrate says it), named like a bad key."""
    path = tmp_path / "unrenderable.yaml"
    path.write_text(UNRENDERABLE)
    assert main([command[0], str(path), *command[1:]]) == 1
    msg = check_error(capsys.readouterr().err, path, marked_line(UNRENDERABLE),
                      "links.felt.target")
    assert "not renderable" in msg


def test_unrenderable_target_error_is_both_families():
    from hapsim.errors import ConfigError, UnrenderableTargetError, UnstableConfigError
    e = UnrenderableTargetError("x", file="f.yaml", line=3, key="links.a.target",
                                spectral_radius=1.2)
    assert isinstance(e, ConfigError) and isinstance(e, UnstableConfigError)
    assert str(e) == "f.yaml:3: links.a.target: x" and e.spectral_radius == 1.2


def test_unstable_scene_stays_exit_1(tmp_path, capsys):
    path = tmp_path / "unstable.yaml"
    path.write_text(HEAD + LINK.replace("1000.0", "5000.0") + DEVICE + EXC)
    assert main(["run", str(path), "--lockstep"]) == 1
    assert "UnstableConfigError" in capsys.readouterr().err
