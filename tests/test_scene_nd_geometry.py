"""A pantograph's geometry in a scene given as numbers (issue 23, items 3 and 7): the
five lengths ``{l1, l2, L1, L2, d}`` [m] instead of a preset's name, read and checked
with the file, the line, the key and the valid forms in every refusal; the device built
from them is the kinematics' own (independent check: the five-bar's forward kinematics
and Jacobian written here from the circle intersection)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hapsim.errors import ConfigError
from hapsim.scene import parse_scene_nd

BASE = """\
dimension: 2
rate_hz: 1000
masses:
  - {name: hand, kind: port}
  - {name: centre, kind: ground, x0: [0.01, 0.09]}
links:
  - {name: spring, kind: spring_damper, between: [hand, centre], stiffness: 500, damping: 2}
device:
  kind: pantograph
  GEOMETRY
  joints: [130, 50]
  joint_inertia: [2.0e-4, 3.0e-4]
  hand_mass: 0.05
"""


def _scene(geometry: str):
    return parse_scene_nd(BASE.replace("GEOMETRY", geometry), "g.yaml")


def _five_bar(g, q):
    """Handle position of the five-bar (base 1 at the origin, base 2 at (d, 0); the
    handle on the elbows' circles, the upper of the two intersections): the law written
    here, not hapsim.kinematics's."""
    l1, l2, L1, L2, d = g
    A = np.array([l1 * math.cos(q[0]), l1 * math.sin(q[0])])
    B = np.array([d + l2 * math.cos(q[1]), l2 * math.sin(q[1])])
    D = np.linalg.norm(B - A)
    a = (L1 ** 2 - L2 ** 2 + D ** 2) / (2 * D)
    h = math.sqrt(L1 ** 2 - a ** 2)
    e = (B - A) / D
    return A + a * e + h * np.array([-e[1], e[0]])


def test_numbers_equal_to_the_preset_are_the_preset():
    """The Haply 2DIY's lengths written out give the scene ``geometry: haply`` gives: the
    same rest position and Cartesian mass, bit for bit."""
    a = _scene("geometry: haply")
    b = _scene("geometry: {l1: 0.05, l2: 0.05, L1: 0.07, L2: 0.07, d: 0.02}")
    assert np.array_equal(a.device.position, b.device.position)
    assert np.array_equal(a.device.mass, b.device.mass)
    assert b.device.geometry.to_dict() == {"l1": 0.05, "l2": 0.05, "L1": 0.07, "L2": 0.07,
                                           "d": 0.02}


@pytest.mark.parametrize("g", [(0.06, 0.05, 0.08, 0.075, 0.03), (0.05, 0.05, 0.07, 0.07, 0.0),
                               (0.045, 0.055, 0.072, 0.068, 0.015)])
def test_an_asymmetric_five_bar_is_its_kinematics(g):
    """Lengths of a five-bar that is no preset, block-style in the file: the handle rests at
    the five-bar's forward kinematics (written here, 1e-12 m), the Cartesian mass is
    ``J^-T M_q J^-1 + m_h I`` with the Jacobian by central differences of that law (1e-6
    relative), and the check and the lockstep run take the device."""
    from hapsim.analysis.scene_check import check_scene_nd
    sc = _scene("geometry:\n" + "\n".join(f"    {k}: {v!r}" for k, v in
                                            zip(("l1", "l2", "L1", "L2", "d"), g)))
    q = np.radians([130.0, 50.0])
    # measured 0 (generic 0): exact on both targets
    assert np.max(np.abs(sc.device.position - _five_bar(g, q))) < 1e-12
    h = 1e-6
    J = np.column_stack([(_five_bar(g, q + h * e) - _five_bar(g, q - h * e)) / (2 * h)
                         for e in np.eye(2)])
    Ji = np.linalg.inv(J)
    M = Ji.T @ np.diag([2e-4, 3e-4]) @ Ji + 0.05 * np.eye(2)
    # the reference's Jacobian by centred differences (h = 1e-6: round-off ~eps/h of it):
    # measured 3.2e-10 relative (generic 3.2e-10), margin 3100
    assert np.max(np.abs(sc.device.mass - M)) < 1e-6 * np.max(np.abs(M))
    chk = check_scene_nd(sc)
    assert chk.render.felt_stiffness is not None
    from hapsim.api import run_nd
    r = run_nd(sc)              # the lockstep run through these lengths' kinematics
    assert r.verdict == "within", r.reason
    # measured 2.3e-7 abs, 2.2e-6 rel (generic 2.5e-7, 2.2e-6), margin 2000
    assert np.allclose(r.measured["felt_stiffness"], chk.render.felt_stiffness,
                       rtol=1e-6, atol=1e-6 * np.max(np.abs(chk.render.felt_stiffness)))


@pytest.mark.parametrize("geometry, key, words", [
    ("geometry: hapkit", "device.geometry", "valid forms: a preset (haply) or a mapping"),
    ("geometry: [0.05, 0.05, 0.07, 0.07, 0.02]", "device.geometry", "got a list"),
    ("geometry: 0.05", "device.geometry", "{l1, l2, L1, L2, d} [m]"),
    ("geometry: null", "device.geometry", "must be a preset (haply) or a mapping"),
    ("geometry: {l1: 0.05, l2: 0.05, L1: 0.07, L2: 0.07}", "device.geometry.d",
     "missing required key 'd'"),
    ("geometry: {l1: 0.05, l2: 0.05, L1: 0.07, L2: 0.07, d: 0.02, l3: 1}",
     "device.geometry.l3", "valid keys: l1, l2, L1, L2, d"),
    ("geometry: {l1: 0, l2: 0.05, L1: 0.07, L2: 0.07, d: 0.02}", "device.geometry.l1",
     "must be > 0"),
    ("geometry: {l1: 0.05, l2: 0.05, L1: 0.07, L2: .inf, d: 0.02}", "device.geometry.L2",
     "finite"),
    ("geometry: {l1: 0.05, l2: 0.05, L1: 0.07, L2: 0.07, d: -0.01}", "device.geometry.d",
     "must be >= 0"),
    ("geometry: {l1: 0.05, l2: 0.05, L1: 0.07, L2: 0.07, d: '0.02'}", "device.geometry.d",
     "must be a number"),
    ("geometry: {l1: 0.05, l2: 0.05, L1: 0.01, L2: 0.01, d: 0.02}", "device.joints",
     "with the geometry given (l1 = 0.05"),
    ("geometry: {l1: 1e-300, l2: 0.05, L1: 0.07, L2: 0.07, d: 0.02}", "device.joints",
     "too near a singularity with the geometry given (l1 = 1e-300"),
])
def test_a_bad_geometry_names_file_line_key_and_forms(geometry, key, words):
    """Every refusal is a ConfigError naming g.yaml, the line of ``geometry`` (10), the key
    (down to the length) and what is valid; lengths the joints cannot assemble are refused
    at ``device.joints`` naming the lengths given."""
    with pytest.raises(ConfigError) as ei:
        _scene(geometry)
    msg = str(ei.value)
    assert msg.startswith(f"g.yaml:{11 if key == 'device.joints' else 10}: {key}: "), msg
    assert words in msg and "\n" not in msg


def test_a_delta_takes_a_preset_only():
    """The delta's geometry is a preset's name; a mapping is refused naming the preset."""
    text = """\
dimension: 3
rate_hz: 1000
masses:
  - {name: hand, kind: port}
device: {kind: delta, geometry: {a: 0.06}, joints: [10, 20, 30], joint_inertia: 1.0e-4}
"""
    with pytest.raises(ConfigError) as ei:
        parse_scene_nd(text, "d.yaml")
    assert str(ei.value).startswith("d.yaml:5: device.geometry: must be a preset (falcon)")
