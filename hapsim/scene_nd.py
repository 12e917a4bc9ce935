"""Scenes in two and three dimensions (``dimension: 2`` or ``3``): reader and validation.

A 1-D scene (no ``dimension`` key, or ``dimension: 1``) is read by :mod:`hapsim.scene`,
unchanged. This module reads the n-D format: the same structure with vector positions,
Euclidean links, planes and a device that may be a kinematic one (the pantograph, the
delta of :mod:`hapsim.kinematics`) at an operating point. Every value is checked, and an
error names the file, the line and the key (``masses[2].x0``) as the 1-D reader's do.

Format (n = ``dimension``; vectors are lists of n numbers; a scalar where a vector is
expected is refused)::

    dimension: 2                  # 2 or 3
    rate_hz: 1000                 # > 0 [Hz]
    integrator: centred           # the only one in n-D
    masses:                       # non-empty
      - {name: hand, kind: port}                       # at most one; rests where the
                                                       # device's handle is
      - {name: anchor, kind: ground, x0: [0.0, 0.02]}  # fixed point [m]
      - {name: bob, kind: mass, mass: 0.01, x0: [0.01, 0.0], v0: [0, 0]}  # [kg] [m] [m/s]
    links:
      - {name: s, kind: spring_damper, between: [hand, bob], stiffness: 300, damping: 0.5,
         length: 0.01}            # rest length [m] >= 0 (default 0)
      - {name: c, kind: contact, between: [hand, bob], stiffness: 800, threshold: 0.01}
    planes:
      - {name: wall, normal: [0, -1], offset: -0.02, stiffness: 1000, damping: 1.5,
         masses: [hand]}          # acts on the named masses (default: every moving one)
    excitation:                   # optional, with a port: the hand's force on the device's
      direction: [0, 1]           # mass along this direction (normalised; required)
      impulse: {force: 2.0, start: 0.0, duration: 0.002}   # [N] [s] [s]; and/or
      profile: hand_force.csv     # a recorded force profile (time [s], force [N]),
                                  # relative to the scene file (hapsim play plucks with
                                  # it, again every --pluck-every seconds)
    engine:                       # optional
      precision: double           # double (float64, the default) | single (float32:
                                  # twice the engine's speed on a mesh, 24-bit positions;
                                  # no port; docs/dimensions.md, 'Single precision')
    audio:                        # optional: the scene heard (hapsim simulate --audio)
      listen:                     # one WAV channel each, at rate_hz
        - {mass: bob, axis: z, quantity: velocity, gain: 10.0}   # axis x|y|z (0..n-1),
                                  # quantity position [m] | velocity [m/s], gain [-]
    device:                       # required with a port
      kind: cartesian             # cartesian | pantograph | delta
      mass: 0.1                   # cartesian: [kg], a number (isotropic), a vector
                                  # (diagonal) or an n x n matrix (SPD)
      friction: 0.5               # cartesian: [N s/m], same shapes (PSD)
      position: [0.0, 0.0]        # cartesian: the handle's rest position [m]
      delay: 1                    # [periods, a real number]
      hold: zoh                   # the only one in n-D
    # a kinematic device instead: kind: pantograph (n = 2) or delta (n = 3), geometry: a
    # preset (haply, falcon) or, for a pantograph, its lengths as numbers
    # {l1: 0.05, l2: 0.05, L1: 0.07, L2: 0.07, d: 0.02} [m], joints: the operating point [deg], joint_inertia [kg m^2]
    # and joint_friction [N m s/rad] (vectors or matrices), hand_mass [kg] and
    # hand_damping [N s/m] (isotropic, default 0); the handle rests at the forward
    # kinematics of the joints.

Link laws (per sample, ``T`` the period; ``d = x1 - x2`` between the first and the second
mass of ``between``; ``F`` acts as ``-F`` on the first and ``+F`` on the second):

- ``spring_damper`` with ``length: 0`` (the default): ``F = K d + B (d - d_prev) / T``,
  the 1-D law on every axis (Faust ``mi.lib``; a 2-D scene whose links are all of this
  kind is n independent copies of the 1-D scene);
- ``spring_damper`` with ``length: L > 0``: ``F = [K (|d| - L) + B (|d| - |d_prev|) / T]
  d / |d|``: the Euclidean stretch and the damping on the relative velocity along the link
  (miPhysics ``SpringDamper3D``);
- ``contact`` (between spheres): the Euclidean law with ``L = threshold`` (> 0, the sum
  of the radii), acting only while ``|d| < threshold``;
- ``planes[]``: with the unit ``normal`` and the penetration ``p = offset - normal . x``,
  the force ``[K p + B (p - p_prev) / T] normal`` on each named mass while ``p > 0``.

:mod:`hapsim.analysis.scene_nd_check` linearises the scene at its rest configuration
(contacts and planes engaged, as the 1-D check does) and analyses the coupled loop.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from hapsim._yaml_lines import load_yaml
from hapsim.errors import ConfigError, show, type_name
from hapsim.scene.reader import LineContext, read_text

__all__ = ["MassND", "LinkND", "PlaneND", "DeviceND", "ListenND", "ExcitationND", "SceneND",
           "scene_dimension", "load_scene_nd", "parse_scene_nd", "TOP_KEYS", "DEVICE_KINDS",
           "PRECISIONS", "ENGINE_KEYS"]

TOP_KEYS = ("dimension", "rate_hz", "integrator", "masses", "links", "planes", "device",
            "excitation", "audio", "engine")
EXCITATION_KEYS = ("direction", "impulse", "profile")
IMPULSE_KEYS = ("force", "start", "duration")
ENGINE_KEYS = ("precision",)
PRECISIONS = ("double", "single")
LISTEN_KEYS = ("mass", "axis", "quantity", "gain")
AXES = ("x", "y", "z")
MASS_KEYS = {"mass": ("name", "kind", "mass", "x0", "v0"),
             "ground": ("name", "kind", "x0"), "port": ("name", "kind")}
LINK_KEYS = {"spring_damper": ("name", "kind", "between", "stiffness", "damping", "length"),
             "contact": ("name", "kind", "between", "stiffness", "damping", "threshold")}
PLANE_KEYS = ("name", "normal", "offset", "stiffness", "damping", "masses")
DEVICE_KINDS = ("cartesian", "pantograph", "delta")
DEVICE_KEYS = {"cartesian": ("kind", "mass", "friction", "position", "delay", "hold"),
               "pantograph": ("kind", "geometry", "joints", "joint_inertia",
                              "joint_friction", "hand_mass", "hand_damping", "delay", "hold"),
               "delta": ("kind", "geometry", "joints", "joint_inertia", "joint_friction",
                         "hand_mass", "hand_damping", "delay", "hold")}
DEVICE_DOF = {"pantograph": 2, "delta": 3}
#: A pantograph's lengths given as numbers (``geometry: {l1: .., l2: .., L1: .., L2: ..,
#: d: ..}`` [m]: :class:`hapsim.kinematics.PantographGeometry`).
PANTOGRAPH_GEOMETRY_KEYS = ("l1", "l2", "L1", "L2", "d")


@dataclass(frozen=True)
class MassND:
    """A point of an n-D scene: ``kind`` in mass/ground/port, ``mass`` [kg] (0 unless
    ``mass``), rest position ``x0`` [m] and velocity ``v0`` [m/s] (shape (n,))."""

    name: str
    kind: str
    mass: float
    x0: np.ndarray
    v0: np.ndarray
    line: int | None = None


@dataclass(frozen=True)
class LinkND:
    """A link of an n-D scene (module docstring for its law): stiffness ``K`` [N/m],
    damping ``B`` [N s/m], rest ``length`` [m] (spring_damper) or ``threshold`` [m]
    (contact)."""

    name: str
    kind: str
    m1: str
    m2: str
    stiffness: float
    damping: float
    length: float
    threshold: float
    line: int | None = None


@dataclass(frozen=True)
class PlaneND:
    """A plane contact: unit ``normal``, ``offset`` [m] (the plane ``normal . x =
    offset``), ``stiffness`` [N/m], ``damping`` [N s/m], the ``masses`` it acts on."""

    name: str
    normal: np.ndarray
    offset: float
    stiffness: float
    damping: float
    masses: tuple
    line: int | None = None


@dataclass(frozen=True)
class DeviceND:
    """The device of an n-D scene, at its operating point.

    Attributes
    ----------
    kind : {"cartesian", "pantograph", "delta"}
    mass : ndarray, shape (n, n)
        Cartesian mass of hand + handle [kg] (for a kinematic device, ``J^-T M_q J^-1``
        plus the hand's).
    friction : ndarray, shape (n, n)
        Cartesian friction [N s/m].
    position : ndarray, shape (n,)
        The handle's rest position [m].
    delay : int or float
        [periods]: an int for a whole delay, a float ``m + f`` for the split hold
        (:mod:`hapsim.analysis.subsample`).
    hold : str
        ``"zoh"``.
    joints : ndarray or None
        Operating point [rad] of a kinematic device.
    geometry : str, hapsim.kinematics.PantographGeometry or None
        Its preset's name, or a pantograph's lengths given as numbers.
    joint_inertia, joint_friction : ndarray, shape (n, n), or None
        A kinematic device's joint-space inertia [kg m^2] and friction [N m s/rad].
    hand_mass, hand_damping : float
        The hand's isotropic mass [kg] and damping [N s/m] (in ``mass``, ``friction``).
    """

    kind: str
    mass: np.ndarray
    friction: np.ndarray
    position: np.ndarray
    delay: int | float
    hold: str
    joints: np.ndarray | None = None
    geometry: Any = None
    joint_inertia: np.ndarray | None = None
    joint_friction: np.ndarray | None = None
    hand_mass: float = 0.0
    hand_damping: float = 0.0


@dataclass(frozen=True)
class ListenND:
    """A listening point of an n-D scene: the ``axis`` (0..n-1) component of a mass's
    ``quantity`` (``"position"`` [m] or ``"velocity"`` [m/s], the backward difference
    ``(x[n] - x[n-1]) / T``) times ``gain`` [-] is one channel of the sound."""

    mass: str
    axis: int
    quantity: str
    gain: float
    line: int | None = None


@dataclass(frozen=True)
class ExcitationND:
    """The hand's force on the device's mass in an n-D scene: the 1-D excitation's
    ``impulse`` (:class:`hapsim.scene.elements.Impulse`, [N], [s]) and/or ``profile`` (a
    file of time [s], force [N]; an absolute path) acting along the unit ``direction``
    (shape (n,)): force vector ``h(t) direction`` (``h`` as
    :func:`hapsim.device_model.hand_force_samples` samples it)."""

    direction: np.ndarray
    impulse: object | None = None
    profile: str | None = None
    line: int | None = None


@dataclass(frozen=True)
class SceneND:
    """A validated 2-D or 3-D scene (:func:`load_scene_nd`); ``audio`` is its listening
    points (a tuple of :class:`ListenND`) or None, ``excitation`` the hand's force
    (:class:`ExcitationND`) or None; ``precision`` the engine's floating type,
    ``"double"`` (float64, default) or ``"single"`` (float32)."""

    dimension: int
    rate_hz: float
    masses: tuple
    links: tuple
    planes: tuple
    device: DeviceND | None
    path: str = "<string>"
    integrator: str = "centred"
    audio: tuple | None = None
    excitation: ExcitationND | None = None
    precision: str = "double"

    @property
    def period(self) -> float:
        """Sample period ``T`` [s]."""
        return 1.0 / self.rate_hz

    @property
    def port(self) -> MassND | None:
        """The port mass, or None."""
        return next((m for m in self.masses if m.kind == "port"), None)


class _Reader(LineContext):
    """Where we are in the file, for error messages (file, line, key): the 1-D reader's
    :class:`~hapsim.scene.reader.LineContext` (mappings, keys, lines), with the n-D
    values (numbers, vectors of ``dimension`` numbers, matrices) read and checked here."""

    @staticmethod
    def line(container, key=None):
        """Line of ``container[key]``, else of the container (None without lines)."""
        return LineContext.line_of(container, key)

    def number(self, d, k, key, *, default=None, minimum=None, strict=False,
               maximum=None, unit=""):
        if k not in d:
            return default
        v = d[k]
        where = f"{key}.{k}" if key else k
        line = self.line(d, k)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(f"must be a number{' [' + unit + ']' if unit else ''}, got "
                             f"{type_name(v)} {show(v)}", line, where)
        try:
            x = float(v)
        except OverflowError:
            x = math.inf
        if not math.isfinite(x):
            raise self.error(f"must be a finite number, got {show(v)}", line, where)
        if minimum is not None and (x < minimum or (strict and x == minimum)):
            raise self.error(f"must be {'>' if strict else '>='} {minimum:g}"
                             f"{' ' + unit if unit else ''}, got {x:g}", line, where)
        if maximum is not None and x > maximum:
            raise self.error(f"must be <= {maximum:g}{' ' + unit if unit else ''}, got "
                             f"{x:g}", line, where)
        return x

    def integer(self, d, k, key, *, default, minimum, maximum, unit):
        if k not in d:
            return default
        v = d[k]
        where = f"{key}.{k}" if key else k
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.error(f"must be a whole number of {unit}, got {show(v)}",
                             self.line(d, k), where)
        if not minimum <= v <= maximum:
            raise self.error(f"must be between {minimum} and {maximum} {unit}, got {show(v)}",
                             self.line(d, k), where)
        return int(v)

    def string(self, d, k, key, default=None):
        if k not in d:
            return default
        v = d[k]
        if not isinstance(v, str) or not v:
            raise self.error(f"must be a non-empty string, got {type_name(v)} {show(v)}",
                             self.line(d, k), f"{key}.{k}")
        return v

    def choice(self, d, k, key, choices, default=None):
        if k not in d:
            if default is None:
                raise self.error(f"missing required key {show(k)}", self.line(d),
                                 f"{key}.{k}" if key else k)
            return default
        v = d[k]
        if not isinstance(v, str) or v not in choices:
            raise self.error(f"unknown value {show(v)}; valid choices: {', '.join(choices)}",
                             self.line(d, k), f"{key}.{k}" if key else k)
        return v

    def vector(self, d, k, key, n, default=None, unit="m"):
        if k not in d:
            return np.zeros(n) if default is None else default
        v = d[k]
        where = f"{key}.{k}"
        line = self.line(d, k)
        if not isinstance(v, list) or len(v) != n or \
                any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in v):
            raise self.error(f"must be a list of {n} numbers [{unit}] (dimension {n}), got "
                             f"{show(v)}", line, where)
        try:
            a = np.array([float(c) for c in v])
        except OverflowError:
            a = np.array([math.inf])
        if not np.all(np.isfinite(a)):
            raise self.error(f"must be finite, got {show(v)}", line, where)
        return a

    def matrix(self, d, k, key, n, default, unit, *, definite):
        """A number (times I), a list of n numbers (diagonal) or n lists of n (a matrix)."""
        if k not in d:
            return default
        v = d[k]
        where = f"{key}.{k}"
        line = self.line(d, k)
        shape_msg = (f"must be a number, a list of {n} numbers (diagonal) or {n} lists of "
                     f"{n} numbers [{unit}]")
        try:
            if isinstance(v, bool):
                raise TypeError
            if isinstance(v, (int, float)):
                if not math.isfinite(float(v)):
                    raise self.error(f"must be finite, got {show(v)}", line, where)
                a = float(v) * np.eye(n)
            elif isinstance(v, list) and len(v) == n and all(
                    isinstance(c, (int, float)) and not isinstance(c, bool) for c in v):
                a = np.diag([float(c) for c in v])
            elif isinstance(v, list) and len(v) == n and all(
                    isinstance(r, list) and len(r) == n and all(
                        isinstance(c, (int, float)) and not isinstance(c, bool) for c in r)
                    for r in v):
                a = np.array([[float(c) for c in r] for r in v])
            else:
                raise TypeError
        except (TypeError, OverflowError):
            raise self.error(f"{shape_msg}, got {show(v)}", line, where) from None
        if not np.all(np.isfinite(a)):
            raise self.error(f"must be finite, got {show(v)}", line, where)
        scale = max(float(np.max(np.abs(a))), 1e-300)
        if np.max(np.abs(a / scale - a.T / scale)) > 1e-12:
            raise self.error(f"must be symmetric, got {show(v)}", line, where)
        # eigenvalues of the matrix scaled to entries <= 1 (exact up to round-off): LAPACK's
        # symmetric solver does not converge on entries near the double range (1e308,
        # issue 31), and a + a.T would overflow there
        lam = scale * np.linalg.eigvalsh(0.5 * (a / scale) + 0.5 * (a.T / scale))
        if definite == "positive" and not lam[0] > 0:
            raise self.error(f"must be positive definite (every eigenvalue > 0 {unit}), "
                             f"got eigenvalues {show([float(x) for x in lam])}", line, where)
        if definite == "semi" and lam[0] < 0:
            raise self.error(f"must be positive semi-definite (every eigenvalue >= 0 "
                             f"{unit}), got eigenvalues {show([float(x) for x in lam])}",
                             line, where)
        return 0.5 * a + 0.5 * a.T


def scene_dimension(path: str | os.PathLike) -> int:
    """The ``dimension`` a scene file declares (1 when absent), read cheaply.

    Parameters
    ----------
    path : str or path-like
        Scene file.

    Returns
    -------
    int
        The value of a top-level ``dimension`` key when it is 2 or 3, else 1 (the 1-D
        reader then reads the file and reports any other problem, including a bad
        ``dimension``).
    """
    try:
        text = read_text(path)
    except ConfigError:
        return 1                       # the 1-D reader reports it
    if "dimension" not in text:
        return 1
    try:
        doc = load_yaml(text, os.fspath(path))
    except ConfigError:
        return 1                       # the 1-D reader reports it
    d = doc.get("dimension") if isinstance(doc, dict) else None
    return d if d in (2, 3) and not isinstance(d, bool) else 1


def load_scene_nd(path: str | os.PathLike) -> SceneND:
    """Read and validate a 2-D or 3-D scene file.

    Parameters
    ----------
    path : str or path-like
        YAML scene file (format in the module docstring).

    Returns
    -------
    SceneND

    Raises
    ------
    ConfigError
        The file cannot be read, is not valid YAML or breaks a rule; the message names the
        file, the line and the key.
    """
    path = os.fspath(path)
    return parse_scene_nd(read_text(path), path)


def parse_scene_nd(text: str, path: str = "<string>") -> SceneND:
    """Parse and validate n-D scene text (module docstring).

    Parameters
    ----------
    text : str
        YAML text.
    path : str
        Name used in messages.

    Returns
    -------
    SceneND

    Raises
    ------
    ConfigError
        Unknown keys (listing the valid ones), missing ones, wrong types or shapes
        (vectors of ``dimension`` numbers), non-positive masses or rates, negative
        stiffness, damping or length, a contact without a positive threshold, duplicate
        names, links naming masses that do not exist or joining a mass to itself, more
        than one port, a port without a device, a device of another dimension, a mass
        matrix not positive definite, a kinematic device at a singular or unreachable
        operating point.
    """
    r = _Reader(path)
    doc = load_yaml(text, path)
    if doc is None:
        raise r.error("the scene is empty", 1, "dimension")
    doc = r.mapping(doc, "", 1)
    r.keys(doc, TOP_KEYS, "", required=("dimension", "rate_hz", "masses"))
    n = r.integer(doc, "dimension", "", default=1, minimum=1, maximum=3,
                  unit="dimensions")
    if n == 1:
        raise r.error("a 1-D scene is the 1-D format (hapsim.scene, docs/scenes.md): "
                      "this reader takes dimension 2 or 3", r.line(doc, "dimension"),
                      "dimension")
    rate = r.number(doc, "rate_hz", "", minimum=0.0, strict=True, unit="Hz")
    from hapsim.scene_schema import MASS_RANGE, MAX_DELAY, RATE_RANGE
    if not RATE_RANGE[0] <= rate <= RATE_RANGE[1]:
        raise r.error(f"must be between {RATE_RANGE[0]:g} and {RATE_RANGE[1]:g} Hz, got "
                      f"{rate:g}", r.line(doc, "rate_hz"), "rate_hz")
    r.choice(doc, "integrator", "", ("centred",), default="centred")

    # masses
    seq = doc["masses"]
    if not isinstance(seq, list) or not seq:
        raise r.error("must be a non-empty list of masses", r.line(doc, "masses"), "masses")
    masses, names = [], {}
    for i, item in enumerate(seq):
        key = f"masses[{i}]"
        d = r.mapping(item, key, r.line(seq, i))
        kind = r.choice(d, "kind", key, ("mass", "ground", "port"))
        r.keys(d, MASS_KEYS[kind], key, required=("name",) + (("mass",) if kind == "mass"
                                                              else ()))
        name = r.string(d, "name", key)
        if name in names:
            raise r.error(f"duplicate mass name {show(name)} (first on line "
                          f"{names[name]})", r.line(d, "name"), f"{key}.name")
        names[name] = r.line(d)
        m = 0.0
        if kind == "mass":
            m = r.number(d, "mass", key, minimum=0.0, strict=True, unit="kg")
            if not MASS_RANGE[0] <= m <= MASS_RANGE[1]:
                raise r.error(f"must be between {MASS_RANGE[0]:g} and {MASS_RANGE[1]:g} kg,"
                              f" got {m:g}", r.line(d, "mass"), f"{key}.mass")
        masses.append(MassND(name, kind, m, r.vector(d, "x0", key, n),
                             r.vector(d, "v0", key, n, unit="m/s"), line=r.line(d)))
    ports = [m for m in masses if m.kind == "port"]
    if len(ports) > 1:
        raise r.error(f"at most one mass of kind 'port', got {len(ports)} (first on line "
                      f"{ports[0].line})", ports[1].line, "masses")

    # links
    links, lnames = [], {}
    lseq = doc.get("links") or []
    if not isinstance(lseq, list):
        raise r.error(f"must be a list of links, got {type_name(lseq)}",
                      r.line(doc, "links"), "links")
    for i, item in enumerate(lseq):
        key = f"links[{i}]"
        d = r.mapping(item, key, r.line(lseq, i))
        kind = r.choice(d, "kind", key, tuple(LINK_KEYS))
        r.keys(d, LINK_KEYS[kind], key, required=("between",) + (
            ("threshold",) if kind == "contact" else ()))
        name = r.string(d, "name", key, default=f"link{i}")
        if name in lnames:
            raise r.error(f"duplicate link name {show(name)} (first on line "
                          f"{lnames[name]})", r.line(d, "name"), f"{key}.name")
        lnames[name] = r.line(d)
        between = d["between"]
        if not (isinstance(between, list) and len(between) == 2
                and all(isinstance(x, str) for x in between)):
            raise r.error("must be a list of two mass names, e.g. [hand, wall]",
                          r.line(d, "between"), f"{key}.between")
        for x in between:
            if x not in names:
                raise r.error(f"no mass named {show(x)}; masses: {', '.join(names)}",
                              r.line(d, "between"), f"{key}.between")
        if between[0] == between[1]:
            raise r.error("a link joins two different masses", r.line(d, "between"),
                          f"{key}.between")
        if "stiffness" not in d and "damping" not in d:
            raise r.error("a link needs stiffness and/or damping", r.line(d),
                          f"{key}.stiffness")
        K = r.number(d, "stiffness", key, default=0.0, minimum=0.0, unit="N/m")
        B = r.number(d, "damping", key, default=0.0, minimum=0.0, unit="N s/m")
        length = r.number(d, "length", key, default=0.0, minimum=0.0, unit="m")
        threshold = r.number(d, "threshold", key, default=0.0, minimum=0.0, strict=True,
                             unit="m") if kind == "contact" else 0.0
        links.append(LinkND(name, kind, between[0], between[1], K, B, length, threshold,
                            line=r.line(d)))

    # planes
    planes, pnames = [], {}
    pseq = doc.get("planes") or []
    if not isinstance(pseq, list):
        raise r.error(f"must be a list of planes, got {type_name(pseq)}",
                      r.line(doc, "planes"), "planes")
    moving = tuple(m.name for m in masses if m.kind != "ground")
    for i, item in enumerate(pseq):
        key = f"planes[{i}]"
        d = r.mapping(item, key, r.line(pseq, i))
        r.keys(d, PLANE_KEYS, key, required=("normal",))
        name = r.string(d, "name", key, default=f"plane{i}")
        if name in pnames or name in lnames:
            raise r.error(f"duplicate name {show(name)} (links and planes share names)",
                          r.line(d, "name"), f"{key}.name")
        pnames[name] = r.line(d)
        normal = r.vector(d, "normal", key, n, unit="-")
        if not np.linalg.norm(normal) > 0:
            raise r.error("must be a non-zero vector (the plane's outward normal)",
                          r.line(d, "normal"), f"{key}.normal")
        if "stiffness" not in d and "damping" not in d:
            raise r.error("a plane needs stiffness and/or damping", r.line(d),
                          f"{key}.stiffness")
        on = d.get("masses", list(moving))
        if not isinstance(on, list) or not on or not all(isinstance(x, str) for x in on):
            raise r.error("must be a non-empty list of mass names", r.line(d, "masses"),
                          f"{key}.masses")
        for x in on:
            if x not in names or x not in moving:
                raise r.error(f"must name moving masses or the port; valid: "
                              f"{', '.join(moving)}; got {show(x)}", r.line(d, "masses"),
                              f"{key}.masses")
        planes.append(PlaneND(name, normal / np.linalg.norm(normal),
                              r.number(d, "offset", key, default=0.0, unit="m"),
                              r.number(d, "stiffness", key, default=0.0, minimum=0.0,
                                       unit="N/m"),
                              r.number(d, "damping", key, default=0.0, minimum=0.0,
                                       unit="N s/m"),
                              tuple(on), line=r.line(d)))

    # device
    device = None
    if "device" in doc:
        device = _read_device(r, doc, n, MAX_DELAY)
    elif ports:
        raise r.error("a scene with a port needs a device section", ports[0].line,
                      "device")
    if ports and device is not None:
        masses = [MassND(m.name, m.kind, m.mass, device.position.copy(), m.v0, m.line)
                  if m.kind == "port" else m for m in masses]
    _check_products(r, 1.0 / rate, masses, links, planes, device,
                    r.line(doc, "device") if "device" in doc else None)
    audio = _read_audio(r, doc, n, names) if "audio" in doc else None
    excitation = None
    if "excitation" in doc:
        if not ports:
            raise r.error("an excitation is the hand's force on the device: the scene needs "
                          "a port and a device", r.line(doc, "excitation"), "excitation")
        excitation = _read_excitation(r, doc, n, path)
    precision = "double"
    if "engine" in doc:
        e = r.mapping(doc["engine"], "engine", r.line(doc, "engine"))
        r.keys(e, ENGINE_KEYS, "engine")
        precision = r.choice(e, "precision", "engine", PRECISIONS, default="double")
        if precision == "single" and ports:
            raise r.error("single precision is for scenes without a port: a felt scene "
                          "runs the double-precision engine (exact to round-off)",
                          r.line(e, "precision"), "engine.precision")
    return SceneND(dimension=n, rate_hz=rate, masses=tuple(masses), links=tuple(links),
                   planes=tuple(planes), device=device, path=path, audio=audio,
                   excitation=excitation, precision=precision)


def _check_products(r: _Reader, T: float, masses, links, planes, device, dev_line) -> None:
    """The n-D loop's dimensionless products, the 1-D scene's rule
    (:func:`hapsim.scene.rules._check_products`): ``|K| T^2/m`` and ``|B| T/m`` of every
    link and plane, ``m`` its lightest moving end (a virtual mass, or the device's
    Cartesian mass along its lightest axis at the port), and the device's ``b0 T/m``
    (largest friction over the lightest mass axis): at most
    :data:`hapsim.scene_schema.MAX_PRODUCT`, whose reason is there (the state matrix's
    entries would span more than a double resolves; 1e308 overflowed it into inf or
    made LAPACK's SVD fail, issue 31).

    Raises
    ------
    ConfigError
        The first product beyond the bound, with file, line and key.
    """
    from hapsim.scene_schema import MAX_PRODUCT, check_product
    inertia = {m.name: float(m.mass) for m in masses if m.kind == "mass"}
    if device is not None:
        def eigs(X):            # scaled to entries <= 1: eigvalsh fails near 1e308
            sx = max(float(np.max(np.abs(X))), np.finfo(float).tiny)
            return sx * np.linalg.eigvalsh(0.5 * (X / sx) + 0.5 * (X.T / sx))
        light = float(np.min(eigs(device.mass)))
        if not np.all(np.isfinite(device.friction)):
            raise r.error("the device's friction is not finite", dev_line, "device.friction")
        heavy_b0 = float(np.max(np.abs(eigs(device.friction))))
        if not (math.isfinite(light) and light > 0):
            raise r.error("the device's Cartesian mass is not positive definite here",
                          dev_line, "device")
        try:
            check_product(heavy_b0, T / light, "friction", "N s/m", "b0 T/m")
        except ConfigError as exc:
            raise r.error(exc.reason, dev_line, "device.friction") from None
        for m in masses:
            if m.kind == "port":
                inertia[m.name] = light
    # a Euclidean link at rest distance r with rest length (or threshold) L stiffens
    # across its axis by K |1 - L/r| (its linearisation, scene_nd_check.link_blocks): the
    # product bounds that too (a length of 1e308 overflowed the state matrix)
    where = {m.name: m.x0 for m in masses}
    groups = []
    for i, lk in enumerate(links):
        L = lk.length if lk.kind == "spring_damper" else lk.threshold
        rr = float(np.linalg.norm(where[lk.m1] - where[lk.m2]))
        gain = max(1.0, abs(1.0 - L / rr)) if L > 0 and rr > 0 else 1.0
        groups.append((f"links[{i}]", lk.line, (lk.m1, lk.m2), lk.stiffness, lk.damping,
                       gain, "length" if lk.kind == "spring_damper" else "threshold"))
    groups += [(f"planes[{i}]", pl.line, pl.masses, pl.stiffness, pl.damping, 1.0, None)
               for i, pl in enumerate(planes)]
    for key, line, ends, K, B, gain, lkey in groups:
        ms = [inertia[x] for x in ends if x in inertia]
        if not ms:
            continue
        m = min(ms)
        for val, scale, unit, what, field in ((K, T * T / m, "N/m", "K T^2/m", "stiffness"),
                                              (B, T / m, "N s/m", "B T/m", "damping")):
            try:
                check_product(val, scale, field, unit, what)
            except ConfigError as exc:
                raise r.error(exc.reason, line, f"{key}.{field}") from None
        if gain > 1.0 and not K * gain * T * T / m <= MAX_PRODUCT:
            raise r.error(f"the link's stiffness across its axis at rest, K |1 - L/r| = "
                          f"{K * gain:.3g} N/m, makes |K T^2/m| > {MAX_PRODUCT:g}: the rest "
                          f"{lkey} is {gain:.3g} times too far from the rest distance",
                          line, f"{key}.{lkey}")


def _read_excitation(r: _Reader, doc, n: int, path: str) -> ExcitationND:
    """The ``excitation: {direction, impulse, profile}`` section (module docstring)."""
    from hapsim.scene import Impulse
    key = "excitation"
    d = r.mapping(doc[key], key, r.line(doc, key))
    r.keys(d, EXCITATION_KEYS, key, required=("direction",))
    if "impulse" not in d and "profile" not in d:
        raise r.error("needs an impulse ({force, start, duration}) or a profile (a file of "
                      "time [s], force [N])", r.line(d), f"{key}.impulse")
    e = r.vector(d, "direction", key, n, unit="-")
    norm = float(np.linalg.norm(e))
    if not norm > 0:
        raise r.error("must be a non-zero vector (the direction of the hand's force)",
                      r.line(d, "direction"), f"{key}.direction")
    impulse = None
    if "impulse" in d:
        ik = f"{key}.impulse"
        i = r.mapping(d["impulse"], ik, r.line(d, "impulse"))
        r.keys(i, IMPULSE_KEYS, ik, required=("force",))
        impulse = Impulse(force=r.number(i, "force", ik, unit="N"),
                          start=r.number(i, "start", ik, default=0.0, minimum=0.0, unit="s"),
                          duration=r.number(i, "duration", ik, default=0.0, minimum=0.0,
                                            unit="s"))
    profile = r.string(d, "profile", key)
    if profile is not None and not os.path.isabs(profile) and path != "<string>":
        profile = os.path.join(os.path.dirname(os.path.abspath(path)), profile)
    return ExcitationND(e / norm, impulse, profile, line=r.line(d))


def _read_audio(r: _Reader, doc, n: int, names) -> tuple:
    """The ``audio: {listen: [...]}`` section: a tuple of :class:`ListenND`."""
    d = r.mapping(doc["audio"], "audio", r.line(doc, "audio"))
    r.keys(d, ("listen",), "audio", required=("listen",))
    seq = d["listen"]
    if not isinstance(seq, list) or not seq:
        raise r.error("must be a non-empty list of listening points, e.g. "
                      "[{mass: m1, axis: z, quantity: velocity, gain: 10}]",
                      r.line(d, "listen"), "audio.listen")
    out = []
    axes = AXES[:n]
    for i, item in enumerate(seq):
        key = f"audio.listen[{i}]"
        e = r.mapping(item, key, r.line(seq, i))
        r.keys(e, LISTEN_KEYS, key, required=("mass",))
        mass = r.string(e, "mass", key)
        if mass not in names:
            raise r.error(f"no mass named {show(mass)}; masses: {', '.join(names)}",
                          r.line(e, "mass"), f"{key}.mass")
        ax = e.get("axis", axes[-1])
        if isinstance(ax, bool) or not (ax in axes or (isinstance(ax, int)
                                                        and 0 <= ax < n)):
            raise r.error(f"must be one of {', '.join(axes)} or 0..{n - 1}, got {show(ax)}",
                          r.line(e, "axis"), f"{key}.axis")
        ax = axes.index(ax) if isinstance(ax, str) else int(ax)
        q = r.choice(e, "quantity", key, ("position", "velocity"), default="velocity")
        g = r.number(e, "gain", key, default=1.0, unit="-")
        out.append(ListenND(mass, ax, q, g, line=r.line(e)))
    return tuple(out)


def _read_geometry(r: _Reader, d, key: str, kind: str, presets: dict):
    """A kinematic device's ``geometry``: a preset's name (the default: the first
    preset), or for a pantograph a mapping of its five lengths [m]
    (:data:`PANTOGRAPH_GEOMETRY_KEYS`; ``l1, l2, L1, L2`` > 0, ``d`` >= 0), returned as a
    :class:`hapsim.kinematics.PantographGeometry`. ConfigError naming the file, the line,
    the key (``device.geometry`` or ``device.geometry.l1``) and the valid forms."""
    from hapsim.kinematics import PantographGeometry
    if "geometry" not in d:
        return next(iter(presets))
    v = d["geometry"]
    where = f"{key}.geometry"
    line = r.line(d, "geometry")
    names = ", ".join(presets)
    forms = (f"a preset ({names}) or a mapping of the five lengths "
             "{l1, l2, L1, L2, d} [m]" if kind == "pantograph" else f"a preset ({names})")
    if isinstance(v, str):
        if v not in presets:
            raise r.error(f"unknown value {show(v)}; valid forms: {forms}", line, where)
        return v
    if kind != "pantograph" or not isinstance(v, dict):
        got = type_name(v) + ("" if v is None else f" {show(v)}")
        raise r.error(f"must be {forms}, got {got}", line, where)
    r.keys(v, PANTOGRAPH_GEOMETRY_KEYS, where, required=PANTOGRAPH_GEOMETRY_KEYS)
    vals = {k: r.number(v, k, where, minimum=0.0, strict=(k != "d"), unit="m")
            for k in PANTOGRAPH_GEOMETRY_KEYS}
    return PantographGeometry(**vals)


def _jacobian_regular(dev, q) -> bool:
    """Whether the device's Jacobian at ``q`` is finite and well conditioned (``cond(J)``
    below ``1 / sqrt(eps)``: its inverse has half the digits or more)."""
    try:
        J = np.asarray(dev.jacobian(q), float)
        c = float(np.linalg.cond(J))
    except Exception:           # a pose the kinematics refuse: not regular
        return False
    return math.isfinite(c) and c < 1.0 / math.sqrt(np.finfo(float).eps)


def _mass_in_range(r: _Reader, M, line, key: str, what: str = "") -> None:
    """Refuse a device mass matrix whose eigenvalues leave
    :data:`hapsim.scene_schema.MASS_RANGE` (the 1-D device's range, and its reason)."""
    from hapsim.scene_schema import MASS_RANGE
    s = max(float(np.max(np.abs(M))), np.finfo(float).tiny)
    lam = s * np.linalg.eigvalsh(0.5 * (M / s) + 0.5 * (M.T / s))
    if not (MASS_RANGE[0] <= lam[0] and lam[-1] <= MASS_RANGE[1]):
        raise r.error(f"the mass along every direction must be between {MASS_RANGE[0]:g} "
                      f"and {MASS_RANGE[1]:g} kg{what}, got eigenvalues "
                      f"{show([float(x) for x in lam])}", line, key)


def _read_device(r: _Reader, doc, n: int, max_delay: int) -> DeviceND:
    key = "device"
    d = r.mapping(doc["device"], key, r.line(doc, "device"))
    kind = r.choice(d, "kind", key, DEVICE_KINDS, default="cartesian")
    need = ("mass",) if kind == "cartesian" else ("joints", "joint_inertia")
    r.keys(d, DEVICE_KEYS[kind], key, required=need)
    # a real number of periods (hapsim.analysis.subsample); a whole one stays an int
    delay = r.number(d, "delay", key, default=1, minimum=0.0, maximum=float(max_delay),
                     unit="periods")
    if float(delay).is_integer():
        delay = int(delay)
    hold = r.choice(d, "hold", key, ("zoh",), default="zoh")
    if kind == "cartesian":
        M = r.matrix(d, "mass", key, n, None, "kg", definite="positive")
        _mass_in_range(r, M, r.line(d, "mass"), f"{key}.mass")
        B0 = r.matrix(d, "friction", key, n, np.zeros((n, n)), "N s/m", definite="semi")
        pos = r.vector(d, "position", key, n)
        return DeviceND(kind, M, B0, pos, delay, hold)
    if DEVICE_DOF[kind] != n:
        raise r.error(f"a {kind} has {DEVICE_DOF[kind]} degrees of freedom; this scene has "
                      f"dimension {n}", r.line(d, "kind"), f"{key}.kind")
    from hapsim.errors import KinematicsError
    from hapsim.kinematics import DELTA_PRESETS, PANTOGRAPH_PRESETS, device as make
    presets = PANTOGRAPH_PRESETS if kind == "pantograph" else DELTA_PRESETS
    geometry = _read_geometry(r, d, key, kind, presets)
    q = np.radians(r.vector(d, "joints", key, n, unit="deg"))
    Mq = r.matrix(d, "joint_inertia", key, n, None, "kg m^2", definite="positive")
    Bq = r.matrix(d, "joint_friction", key, n, np.zeros((n, n)), "N m s/rad",
                  definite="semi")
    from hapsim.scene_schema import MASS_RANGE
    mh = r.number(d, "hand_mass", key, default=0.0, minimum=0.0, maximum=MASS_RANGE[1],
                  unit="kg")
    bh = r.number(d, "hand_damping", key, default=0.0, minimum=0.0, unit="N s/m")
    dev = make(kind, geometry)
    try:
        from hapsim.analysis.ths_nd import LoopModelND
        with np.errstate(over="ignore", invalid="ignore"):   # refused below when not finite
            loop = LoopModelND.from_device(dev, q, Mq, Bq, hand_mass=mh, hand_damping=bh,
                                           rate_hz=1.0, delay=0)
        pos = dev.forward(q)
    except (KinematicsError, ConfigError) as exc:
        # a configuration the kinematics refuse, or one so near a singularity that the
        # Cartesian mass is not finite (e.g. a link of 1e-300 m)
        given = ("" if isinstance(geometry, str) else " with the geometry given ("
                 + ", ".join(f"{k} = {getattr(geometry, k):g}" for k in
                             PANTOGRAPH_GEOMETRY_KEYS) + " m)")
        if isinstance(exc, ConfigError) and _jacobian_regular(dev, q):
            # a regular Jacobian: the joint values, not the pose, overflowed the mass
            raise r.error(f"the device's Cartesian mass J^-T M_q J^-1 at these joints is "
                          f"not finite ({exc.key}: {exc.reason}): the joint inertia, "
                          "friction or hand values are beyond the double range",
                          r.line(d, "joint_inertia"), f"{key}.joint_inertia") from None
        what = exc.reason if isinstance(exc, KinematicsError) else (
            f"the device's Cartesian mass at these joints is not usable ({exc.key}: "
            f"{exc.reason}): too near a singularity")
        raise r.error(what + given, r.line(d, "joints"), f"{key}.joints") from None
    _mass_in_range(r, loop.mass, r.line(d, "joint_inertia"), f"{key}.joint_inertia",
                   " (the Cartesian mass J^-T M_q J^-1 at these joints, hand included)")
    if not np.all(np.isfinite(loop.friction)):
        # (a hand_damping of 1e308 with the joint friction mapped: inf; it passed the
        # reader and failed later without file or line, issue 31's fuzz)
        k_bad = "hand_damping" if bh > 0 and "hand_damping" in d else "joint_friction"
        raise r.error("the device's Cartesian friction J^-T B_q J^-1 + hand_damping at these "
                      "joints is not finite: the value is beyond the double range",
                      r.line(d, k_bad), f"{key}.{k_bad}")
    return DeviceND(kind, loop.mass, loop.friction, pos, delay, hold, joints=q,
                    geometry=geometry, joint_inertia=Mq, joint_friction=Bq, hand_mass=mh,
                    hand_damping=bh)
