"""Hostile values in otherwise valid 2-D and 3-D scenes (a pantograph's geometry given as
numbers among them): every scalar of each base scene
replaced by each hostile YAML value (overflowing integers, NaN/inf literals, tags, aliases,
nesting, merge keys, lists, mappings) is read and checked or refused with a ConfigError
whose message is one bounded line, never another exception (the n-D reader and check
held to the 1-D reader's rule, tests/test_hostile_values.py)."""

from __future__ import annotations

import re

from hapsim.analysis.scene_check import check_scene_nd
from hapsim.errors import ConfigError
from hapsim.scene import parse_scene_nd

HOSTILE = ["!!float abc", ".nan", ".inf", "-.inf", "1e400", "-1e400", "1e-400", "9" * 400,
           "-" + "9" * 400, "[]", "{}", "null", "true", "'x'", "[[[[1]]]]", "{a: 1}",
           "*nope", "0x10", "-0", "[1, 2]", "1e12", "-1e12", "0", "1e-300"]
SCALAR = re.compile(r"(?<=[:\[ ,])\s*-?[0-9][^\s,{}\[\]#]*|(?<=: )[a-z_]+")

BASES = [
    """\
dimension: 2
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: [0.0, 0.01]}
  - {name: bob, kind: mass, mass: 0.01, x0: [0.01, 0.0], v0: [0.1, 0]}
links:
  - {name: w, kind: spring_damper, between: [hand, wall], stiffness: 300, damping: 1}
  - {name: e, kind: spring_damper, between: [hand, bob], stiffness: 50, length: 0.005}
  - {name: c, kind: contact, between: [bob, wall], stiffness: 80, threshold: 0.002}
planes:
  - {name: p, normal: [0, 1], offset: -0.01, stiffness: 100, damping: 0.2}
device: {mass: [[0.1, 0.01], [0.01, 0.2]], friction: [0.5, 0.4], delay: 2}
""",
    """\
dimension: 3
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: wall, kind: ground, x0: [0.0, 0.0, 0.1]}
links:
  - {name: w, kind: spring_damper, between: [hand, wall], stiffness: 300, damping: 1}
device: {kind: delta, geometry: falcon, joints: [10, 20, 30], joint_inertia: 1.0e-4,
         joint_friction: [1.0e-3, 1.0e-3, 1.0e-3], hand_mass: 0.05, delay: 1}
""",
    """\
dimension: 2
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: centre, kind: ground, x0: [0.01, 0.09]}
links:
  - {name: s, kind: spring_damper, between: [hand, centre], stiffness: 500, damping: 2}
device:
  kind: pantograph
  geometry: {l1: 0.05, l2: 0.05, L1: 0.07, L2: 0.07, d: 0.02}
  joints: [130, 50]
  joint_inertia: [2.0e-4, 2.0e-4]
  hand_mass: 0.05
""",
]


def test_hostile_value_at_every_scalar_is_read_or_one_line():
    """Every scalar x every hostile value is read or refused in one line; the check runs
    on every 16th scene read (the check is the costly part; each accepted value class is
    met many times over)."""
    n_refused = 0
    read = []
    for b, base in enumerate(BASES):
        spots = list(SCALAR.finditer(base))
        assert len(spots) > 10
        values = HOSTILE[::6] if b == 1 else HOSTILE     # the delta's reads cost more
        for m in spots:
            for value in values:
                text = base[:m.start()] + " " + value + base[m.end():]
                try:
                    read.append(parse_scene_nd(text, "h.yaml"))
                except ConfigError as exc:
                    msg = str(exc)
                    assert "\n" not in msg and len(msg) < 600, msg
                    n_refused += 1
    assert n_refused > 200 and len(read) > 40
    for scene in read[::16]:
        try:
            chk = check_scene_nd(scene)
            assert isinstance(chk.render.spectral_radius, float)
        except ConfigError as exc:
            assert "\n" not in str(exc)
