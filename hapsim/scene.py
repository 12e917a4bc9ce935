"""YAML scene files: parsing and validation.

A scene is a CORDIS-ANIMA style mass-interaction network in SI units, plus the
description of the device it is felt through. Nothing reaches the engine or the
analysis without passing :func:`parse_scene`, which reports every problem as a
:class:`~hapsim.errors.ConfigError` naming the file, the line and the key.

Format
------
.. code-block:: yaml

    rate_hz: 1000                 # sample rate [Hz], > 0 (required)
    integrator: centred           # centred | symplectic_euler | exact (default centred;
                                  # hapsim.kernels.schemes; exact: no contact links)
    masses:                       # list; names unique
      - {name: hand, kind: port}                    # driven by the device position
      - {name: wall, kind: ground, x0: 0.0}         # fixed point [m]
      - {name: bob, kind: mass, mass: 0.01, x0: 0.0, v0: 0.0}   # [kg], [m], [m/s]
    links:                        # list; names unique (default link0, link1, ...)
      - {name: wall, kind: spring_damper, between: [hand, wall],
         stiffness: 2000, damping: 2}               # K [N/m], B [N s/m]
      - {kind: contact, between: [hand, bob], stiffness: 500, damping: 0.1,
         threshold: 0.0}                            # acts while x2 - x1 < threshold [m]
      - {name: felt, kind: spring_damper, between: [hand, wall],
         target: {k: 2000, b: 3}}                   # felt (k, b): calibrated by the daemon
    device:                       # required when the scene has a port
      mass: 0.1                   # hand + handle moving mass m [kg], > 0
      friction: 0.5               # real viscous friction b0 [N s/m], >= 0
      delay: 1                    # whole samples between position read and force applied
      hold: zoh                   # zoh | ideal
      force_limit: 10             # [N], > 0 (default: none)
      position_resolution: 0      # encoder quantum [m] (mock device only; 0 = none)
      coulomb: 0                  # Coulomb friction [N] (mock device only)
      noise: 0                    # position sensor noise, standard deviation [m]
    excitation:                   # how the mock device's hand starts the motion
      x0: 0.002                   # initial device displacement [m]
      v0: 0.0                     # initial device velocity [m/s]
      impulse: {force: 1.0, start: 0.0, duration: 0.001}   # [N], [s], [s]
      profile: hand_force.csv     # recorded hand force: columns time [s], force [N]
    safety:                       # limits of hapsim run (all optional)
      position_limit: 0.1         # safety stop when |x| exceeds it [m], > 0
                                  # (default max(0.1, 20 |excitation.x0|))
      velocity_limit: 2.0         # safety stop when |v| exceeds it [m/s], > 0 (default none)
      energy_limit: 1.0           # safety stop when the scene has given the hand this much
                                  # energy [J], > 0 (passivity observer; default 1 J)
      passivity_controller: false # add Hannaford & Ryu's adaptive damping (default false)
      max_damping: 50             # its cap [N s/m], >= 0 (default 50)

Link law (DESIGN §3, Faust ``mi.lib`` ``spring``/``collision``): with ``x1``, ``x2``
the positions of the first and second mass named in ``between``,
``F = K (x1 - x2) + B ((x1 - x2) - (x1p - x2p)) / T`` is applied as ``-F`` on the first
mass and ``+F`` on the second. A contact acts only while ``x2 - x1 < threshold``, with its
spring measured from the threshold, ``F = K (x1 - x2 + threshold) + B (...) / T``, so the
force is continuous when the contact engages (Faust 2.54 ``mi.lib`` ``collision``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from dataclasses import dataclass, field
from typing import Any

import yaml

from hapsim.errors import ConfigError

__all__ = ["Mass", "Link", "Device", "Impulse", "Excitation", "Safety", "Scene",
           "load_scene", "parse_scene", "MASS_KINDS", "LINK_KINDS", "HOLDS", "INTEGRATORS"]

#: Mass kinds a scene may use.
MASS_KINDS = ("mass", "ground", "port")
#: Link kinds a scene may use.
LINK_KINDS = ("spring_damper", "contact")
#: Output holds a device may use (DESIGN §4).
HOLDS = ("zoh", "ideal")
#: Integrators of the virtual masses (first is the default; hapsim.kernels.schemes).
INTEGRATORS = ("centred", "symplectic_euler", "exact")

_TOP_KEYS = ("rate_hz", "masses", "links", "device", "excitation", "integrator", "safety")
_MASS_KEYS = {"mass": ("name", "kind", "mass", "x0", "v0"),
              "ground": ("name", "kind", "x0"),
              "port": ("name", "kind")}
_LINK_KEYS = {"spring_damper": ("name", "kind", "between", "stiffness", "damping", "target"),
              "contact": ("name", "kind", "between", "stiffness", "damping", "threshold")}
_DEVICE_KEYS = ("mass", "friction", "delay", "hold", "force_limit",
                "position_resolution", "coulomb", "noise")
_EXCITATION_KEYS = ("x0", "v0", "impulse", "profile")
_SAFETY_KEYS = ("position_limit", "velocity_limit", "energy_limit", "passivity_controller",
                "max_damping")
_IMPULSE_KEYS = ("force", "start", "duration")
_TARGET_KEYS = ("k", "b")


@dataclass(frozen=True)
class Mass:
    """One point of the network.

    Parameters
    ----------
    name : str
        Unique name.
    kind : {"mass", "ground", "port"}
        ``mass`` moves under the forces on it; ``ground`` is a fixed point; ``port`` is
        moved by the device position and its force is sent to the device.
    mass : float
        Inertia [kg], > 0 for ``mass``; 0.0 for ``ground`` and ``port``.
    x0 : float
        Initial position [m].
    v0 : float
        Initial velocity [m/s] (``mass`` only).
    line : int
        Line of the entry in the scene file (0 when built in code).
    """

    name: str
    kind: str
    mass: float = 0.0
    x0: float = 0.0
    v0: float = 0.0
    line: int = 0


@dataclass(frozen=True)
class Link:
    """One interaction between two masses.

    Parameters
    ----------
    name : str
        Unique name.
    kind : {"spring_damper", "contact"}
        ``contact`` acts only while ``x2 - x1 < threshold``, with its spring force
        ``K (x1 - x2 + threshold)`` (Faust 2.54 ``mi.lib`` ``collision``).
    m1, m2 : str
        Names of the first and second mass (order fixes the sign convention).
    stiffness : float
        Virtual stiffness K [N/m], >= 0; NaN while a ``target`` awaits calibration.
    damping : float
        Virtual damping B [N s/m], >= 0; NaN while a ``target`` awaits calibration.
    threshold : float
        Contact threshold [m] (``contact`` only; 0.0 otherwise).
    target : tuple of float, optional
        Felt (k [N/m], b [N s/m]) the daemon calibrates (K, B) for; ``spring_damper``
        between the port and a ground only.
    line : int
        Line of the entry in the scene file.
    """

    name: str
    kind: str
    m1: str
    m2: str
    stiffness: float = 0.0
    damping: float = 0.0
    threshold: float = 0.0
    target: tuple[float, float] | None = None
    line: int = 0


@dataclass(frozen=True)
class Device:
    """The real side of the temporary hybrid system, as the scene describes it.

    Parameters
    ----------
    mass : float
        Moving mass m of hand + handle [kg], > 0.
    friction : float
        Real viscous friction b0 [N s/m], >= 0.
    delay : int
        Whole samples d between the position a force is computed from and the sample
        the force is applied at, >= 0.
    hold : {"zoh", "ideal"}
        Zero-order hold of the force, or the paper's idealised sampled image.
    force_limit : float
        Largest force magnitude sent to the device [N]; ``inf`` when none.
    position_resolution : float
        Encoder quantum of the mock device [m]; 0 for none.
    coulomb : float
        Coulomb friction of the mock device [N]; 0 for none.
    noise : float
        Standard deviation of the mock device's position noise [m]; 0 for none.
    """

    mass: float
    friction: float = 0.0
    delay: int = 1
    hold: str = "zoh"
    force_limit: float = math.inf
    position_resolution: float = 0.0
    coulomb: float = 0.0
    noise: float = 0.0


@dataclass(frozen=True)
class Impulse:
    """A rectangular force pulse applied by the hand [N] from ``start`` for ``duration`` [s]."""

    force: float
    start: float = 0.0
    duration: float = 0.0


@dataclass(frozen=True)
class Excitation:
    """How the (mock) device's hand sets the closed loop in motion.

    Parameters
    ----------
    x0 : float
        Initial device displacement [m].
    v0 : float
        Initial device velocity [m/s].
    impulse : Impulse, optional
        A force pulse from the hand.
    profile : str, optional
        Path of a recorded hand-force profile (``.csv`` or ``.npz``: time [s], force [N]),
        resolved relative to the scene file.
    """

    x0: float = 0.0
    v0: float = 0.0
    impulse: Impulse | None = None
    profile: str | None = None


@dataclass(frozen=True)
class Safety:
    """Limits ``hapsim run`` enforces on the device (scene section ``safety:``).

    Parameters
    ----------
    position_limit : float or None
        Safety stop when ``|x|`` exceeds it [m]; None: ``max(0.1, 20 |excitation.x0|)``.
    velocity_limit : float
        Safety stop when the backward-difference velocity ``|v|`` exceeds it [m/s];
        ``inf``: none.
    energy_limit : float
        Safety stop when the passivity observer says the scene has given the hand this
        much energy [J] (Hannaford & Ryu 2002; see :mod:`hapsim.daemon.loop`).
    passivity_controller : bool
        Add the adaptive damping ``alpha = E / (T v^2)`` while that energy is positive.
    max_damping : float
        Cap of the adaptive damping [N s/m].
    """

    position_limit: float | None = None
    velocity_limit: float = math.inf
    energy_limit: float = 1.0
    passivity_controller: bool = False
    max_damping: float = 50.0


@dataclass(frozen=True)
class Scene:
    """A validated scene. Build it with :func:`load_scene` or :func:`parse_scene`.

    Parameters
    ----------
    rate_hz : float
        Sample rate [Hz].
    masses : tuple of Mass
        The points, in file order.
    links : tuple of Link
        The interactions, in file order.
    device : Device or None
        The device section (required when a port exists).
    excitation : Excitation
        Excitation section (all zero when absent).
    path : str
        File the scene came from (``"<string>"`` for text).
    integrator : {"centred", "symplectic_euler", "exact"}
        Integrator of the virtual masses (:mod:`hapsim.kernels.schemes`).
    safety : Safety
        Limits of ``hapsim run`` (section ``safety:``; defaults when absent).
    """

    rate_hz: float
    masses: tuple[Mass, ...]
    links: tuple[Link, ...]
    device: Device | None = None
    excitation: Excitation = field(default_factory=Excitation)
    path: str = "<string>"
    integrator: str = "centred"
    safety: Safety = field(default_factory=Safety)

    @property
    def period(self) -> float:
        """Sample period T = 1 / rate_hz [s]."""
        return 1.0 / self.rate_hz

    @property
    def port(self) -> Mass | None:
        """The port mass, or None when the scene has none."""
        for m in self.masses:
            if m.kind == "port":
                return m
        return None

    def index(self, name: str) -> int:
        """Index of the mass called ``name`` in :attr:`masses`.

        Raises
        ------
        KeyError
            When no mass has that name.
        """
        return self._mass_index[name]

    @functools.cached_property
    def _mass_index(self) -> dict[str, int]:
        return {m.name: i for i, m in enumerate(self.masses)}

    def link(self, name: str) -> Link:
        """The link called ``name``.

        Raises
        ------
        KeyError
            When no link has that name.
        """
        for lk in self.links:
            if lk.name == name:
                return lk
        raise KeyError(name)

    @property
    def kinds(self) -> frozenset[str]:
        """Link kinds this scene uses (what the engine must compile)."""
        return frozenset(lk.kind for lk in self.links)

    @property
    def unresolved_targets(self) -> tuple[Link, ...]:
        """Links given as a felt ``target`` whose (K, B) are not calibrated yet."""
        return tuple(lk for lk in self.links
                     if lk.target is not None
                     and (math.isnan(lk.stiffness) or math.isnan(lk.damping)))

    def with_link(self, name: str, *, stiffness: float, damping: float) -> "Scene":
        """A copy of the scene with the (K, B) of one link replaced.

        Parameters
        ----------
        name : str
            Link name.
        stiffness : float
            New K [N/m], finite and >= 0.
        damping : float
            New B [N s/m], finite (may be negative after calibration: the real friction
            can exceed the felt damping).

        Raises
        ------
        KeyError
            When no link has that name.
        ConfigError
            When the values are not finite or the stiffness is negative.
        """
        old = self.link(name)
        if not (math.isfinite(stiffness) and math.isfinite(damping)) or stiffness < 0:
            raise ConfigError(f"invalid calibrated values K={stiffness}, B={damping}",
                              file=self.path, line=old.line or None, key=f"links.{name}")
        links = tuple(dataclasses.replace(lk, stiffness=float(stiffness), damping=float(damping))
                      if lk.name == name else lk for lk in self.links)
        return dataclasses.replace(self, links=links)

    def with_rate(self, rate_hz: float) -> "Scene":
        """A copy of the scene at another sample rate [Hz] (> 0).

        Raises
        ------
        ConfigError
            When ``rate_hz`` is not a positive finite number.
        """
        if not (isinstance(rate_hz, (int, float)) and math.isfinite(rate_hz) and rate_hz > 0):
            raise ConfigError(f"must be a positive number, got {rate_hz!r}", key="rate_hz")
        return dataclasses.replace(self, rate_hz=float(rate_hz))


# --------------------------------------------------------------------------- YAML with lines

class _Node:
    """Mixin that records the line of a YAML mapping or sequence and of its items."""

    line: int
    lines: dict


class _LDict(dict, _Node):
    pass


class _LList(list, _Node):
    pass


class _LineLoader(yaml.SafeLoader):
    """SafeLoader that records 1-based lines and refuses duplicate keys."""


def _construct_mapping(loader: _LineLoader, node: yaml.MappingNode) -> _LDict:
    loader.flatten_mapping(node)
    out = _LDict()
    out.line = node.start_mark.line + 1
    out.lines = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if key in out:
            raise ConfigError(f"duplicate key {key!r} (first on line {out.lines[key]})",
                              file=getattr(loader, "_hapsim_path", None),
                              line=key_node.start_mark.line + 1, key=str(key))
        out[key] = loader.construct_object(value_node, deep=True)
        out.lines[key] = key_node.start_mark.line + 1
    return out


def _construct_sequence(loader: _LineLoader, node: yaml.SequenceNode) -> _LList:
    out = _LList(loader.construct_object(child, deep=True) for child in node.value)
    out.line = node.start_mark.line + 1
    out.lines = {i: child.start_mark.line + 1 for i, child in enumerate(node.value)}
    return out


_LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_SEQUENCE_TAG, _construct_sequence)


# --------------------------------------------------------------------------- validation

class _Ctx:
    """Where we are in the file, for error messages."""

    def __init__(self, path: str) -> None:
        self.path = path

    def error(self, message: str, line: int | None, key: str) -> ConfigError:
        return ConfigError(message, file=self.path, line=line, key=key or None)

    @staticmethod
    def line_of(container: Any, key: Any) -> int | None:
        lines = getattr(container, "lines", None)
        if lines and key in lines:
            return lines[key]
        return getattr(container, "line", None)

    def mapping(self, value: Any, key: str, line: int | None) -> _LDict:
        if not isinstance(value, dict):
            raise self.error(f"must be a mapping (key: value), got {_typename(value)}", line, key)
        return value

    def keys(self, d: _LDict, allowed: tuple[str, ...], key: str, required: tuple[str, ...] = ()) -> None:
        for k in d:
            if k not in allowed:
                raise self.error(f"unknown key {k!r}; valid keys: {', '.join(allowed)}",
                                 self.line_of(d, k), f"{key}.{k}" if key else str(k))
        for k in required:
            if k not in d:
                raise self.error(f"missing required key {k!r}", getattr(d, "line", None),
                                 f"{key}.{k}" if key else k)

    def number(self, d: _LDict, k: str, key: str, default: float | None = None, *,
               minimum: float | None = None, positive: bool = False,
               allow_inf: bool = False) -> float:
        full = f"{key}.{k}" if key else k
        if k not in d:
            if default is None:
                raise self.error(f"missing required key {k!r}", getattr(d, "line", None), full)
            return default
        v = d[k]
        line = self.line_of(d, k)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(f"must be a number, got {_typename(v)} {v!r}", line, full)
        v = float(v)
        if math.isnan(v) or (math.isinf(v) and not allow_inf):
            raise self.error(f"must be a finite number, got {v}", line, full)
        if positive and not v > 0:
            raise self.error(f"must be > 0, got {v:g}", line, full)
        if minimum is not None and v < minimum:
            raise self.error(f"must be >= {minimum:g}, got {v:g}", line, full)
        return v

    def string(self, d: _LDict, k: str, key: str, choices: tuple[str, ...] | None = None,
               default: str | None = None) -> str:
        full = f"{key}.{k}" if key else k
        if k not in d:
            if default is None:
                raise self.error(f"missing required key {k!r}", getattr(d, "line", None), full)
            return default
        v = d[k]
        line = self.line_of(d, k)
        if not isinstance(v, str):
            raise self.error(f"must be a string, got {_typename(v)} {v!r}", line, full)
        if choices is not None and v not in choices:
            raise self.error(f"unknown value {v!r}; valid choices: {', '.join(choices)}", line, full)
        return v


def _typename(v: Any) -> str:
    if v is None:
        return "nothing (null)"
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, dict):
        return "a mapping"
    if isinstance(v, list):
        return "a list"
    return {int: "an integer", float: "a number", str: "a string"}.get(type(v), type(v).__name__)


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and validate a scene file.

    Parameters
    ----------
    path : str or path-like
        YAML scene file (format in the module docstring).

    Returns
    -------
    Scene
        The validated scene.

    Raises
    ------
    ConfigError
        When the file cannot be read, is not valid YAML, or fails validation; the
        message names the file, the line and the key.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as exc:
        raise ConfigError(f"cannot read scene file: {exc.strerror or exc}", file=path) from exc
    return parse_scene(text, path)


def parse_scene(text: str, path: str = "<string>") -> Scene:
    """Parse and validate scene text.

    Parameters
    ----------
    text : str
        YAML text of the scene.
    path : str
        Name used in error messages and to resolve relative ``excitation.profile`` paths.

    Returns
    -------
    Scene
        The validated scene.

    Raises
    ------
    ConfigError
        On YAML syntax errors, unknown keys (listing the valid ones), wrong types,
        non-positive masses or rates, negative stiffness or damping, links naming masses
        that do not exist, a link from a mass to itself, duplicate names, a missing
        ``rate_hz``, an unknown ``integrator`` (listing the choices), a contact link with
        ``integrator: exact``, a port without a device section, more than one port, or a
        ``target`` on a link that is not between the port and a ground.
    """
    loader = _LineLoader(text)
    loader._hapsim_path = path  # type: ignore[attr-defined]
    try:
        doc = loader.get_single_data()
    except ConfigError:
        raise
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        raise ConfigError(f"invalid YAML: {exc.problem or exc}", file=path, line=line) from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"invalid YAML: {exc}", file=path) from exc
    finally:
        loader.dispose()

    ctx = _Ctx(path)
    if doc is None:
        raise ctx.error("the scene is empty; it needs at least rate_hz and masses", 1, "rate_hz")
    doc = ctx.mapping(doc, "", 1)
    ctx.keys(doc, _TOP_KEYS, "", required=("rate_hz", "masses"))
    rate_hz = ctx.number(doc, "rate_hz", "", positive=True)

    masses = _parse_masses(ctx, doc)
    names = {m.name: m for m in masses}
    links = _parse_links(ctx, doc, names)

    ports = [m for m in masses if m.kind == "port"]
    if len(ports) > 1:
        raise ctx.error(f"at most one port per scene (1-DoF device); found {len(ports)}: "
                        + ", ".join(p.name for p in ports), ports[1].line, "masses")

    device = None
    if "device" in doc:
        device = _parse_device(ctx, doc)
    elif ports:
        raise ctx.error("a scene with a port needs a device section "
                        "(mass, friction, delay, hold, ...)", doc.line, "device")

    excitation = Excitation()
    if "excitation" in doc:
        excitation = _parse_excitation(ctx, doc, path)

    integrator = ctx.string(doc, "integrator", "", INTEGRATORS, default="centred")
    if integrator == "exact":
        for i, lk in enumerate(links):
            if lk.kind == "contact":
                raise ctx.error("the exact integrator takes linear links only; a contact "
                                "switches the network (use centred or symplectic_euler)",
                                lk.line, f"links[{i}].kind")

    safety = _parse_safety(ctx, doc) if "safety" in doc else Safety()

    return Scene(rate_hz=rate_hz, masses=tuple(masses), links=tuple(links), device=device,
                 excitation=excitation, path=path, integrator=integrator, safety=safety)


def _parse_masses(ctx: _Ctx, doc: _LDict) -> list[Mass]:
    seq = doc["masses"]
    if not isinstance(seq, list) or not seq:
        raise ctx.error("must be a non-empty list of masses", ctx.line_of(doc, "masses"), "masses")
    out: list[Mass] = []
    seen: dict[str, int] = {}
    for i, item in enumerate(seq):
        key = f"masses[{i}]"
        line = ctx.line_of(seq, i)
        d = ctx.mapping(item, key, line)
        kind = ctx.string(d, "kind", key, MASS_KINDS)
        ctx.keys(d, _MASS_KEYS[kind], key, required=("name",))
        name = ctx.string(d, "name", key)
        if name in seen:
            raise ctx.error(f"duplicate mass name {name!r} (first on line {seen[name]})",
                            ctx.line_of(d, "name"), f"{key}.name")
        seen[name] = d.line
        if kind == "mass":
            out.append(Mass(name, kind, ctx.number(d, "mass", key, positive=True),
                            ctx.number(d, "x0", key, 0.0), ctx.number(d, "v0", key, 0.0), d.line))
        elif kind == "ground":
            out.append(Mass(name, kind, 0.0, ctx.number(d, "x0", key, 0.0), 0.0, d.line))
        else:
            out.append(Mass(name, kind, 0.0, 0.0, 0.0, d.line))
    return out


def _parse_links(ctx: _Ctx, doc: _LDict, masses: dict[str, Mass]) -> list[Link]:
    if "links" not in doc or doc["links"] is None:
        return []
    seq = doc["links"]
    if not isinstance(seq, list):
        raise ctx.error(f"must be a list of links, got {_typename(seq)}",
                        ctx.line_of(doc, "links"), "links")
    out: list[Link] = []
    seen: dict[str, int] = {}
    for i, item in enumerate(seq):
        key = f"links[{i}]"
        d = ctx.mapping(item, key, ctx.line_of(seq, i))
        kind = ctx.string(d, "kind", key, LINK_KINDS)
        ctx.keys(d, _LINK_KEYS[kind], key, required=("between",))
        name = ctx.string(d, "name", key, default=f"link{i}")
        if name in seen:
            raise ctx.error(f"duplicate link name {name!r} (first on line {seen[name]})",
                            ctx.line_of(d, "name"), f"{key}.name")
        seen[name] = d.line
        between = d["between"]
        bline = ctx.line_of(d, "between")
        if not (isinstance(between, list) and len(between) == 2
                and all(isinstance(n, str) for n in between)):
            raise ctx.error("must be a list of two mass names, e.g. [hand, wall]", bline,
                            f"{key}.between")
        m1, m2 = between
        for n in (m1, m2):
            if n not in masses:
                raise ctx.error(f"no mass named {n!r}; masses are: {', '.join(masses)}", bline,
                                f"{key}.between")
        if m1 == m2:
            raise ctx.error(f"a link cannot join mass {m1!r} to itself", bline, f"{key}.between")
        target = None
        if "target" in d:
            if "stiffness" in d or "damping" in d:
                raise ctx.error("give either target {k, b} or stiffness/damping, not both",
                                ctx.line_of(d, "target"), f"{key}.target")
            kinds = {masses[m1].kind, masses[m2].kind}
            if kinds != {"port", "ground"}:
                raise ctx.error("a felt target {k, b} can only be calibrated for a "
                                "spring_damper between the port and a ground",
                                ctx.line_of(d, "target"), f"{key}.target")
            t = ctx.mapping(d["target"], f"{key}.target", ctx.line_of(d, "target"))
            ctx.keys(t, _TARGET_KEYS, f"{key}.target", required=_TARGET_KEYS)
            target = (ctx.number(t, "k", f"{key}.target", positive=True),
                      ctx.number(t, "b", f"{key}.target", minimum=0.0))
            stiffness = damping = math.nan
        else:
            stiffness = ctx.number(d, "stiffness", key, 0.0, minimum=0.0)
            damping = ctx.number(d, "damping", key, 0.0, minimum=0.0)
            if "stiffness" not in d and "damping" not in d:
                raise ctx.error("a link needs stiffness and/or damping (or a target)",
                                d.line, f"{key}.stiffness")
        threshold = ctx.number(d, "threshold", key, 0.0) if kind == "contact" else 0.0
        out.append(Link(name, kind, m1, m2, stiffness, damping, threshold, target, d.line))
    return out


def _parse_device(ctx: _Ctx, doc: _LDict) -> Device:
    d = ctx.mapping(doc["device"], "device", ctx.line_of(doc, "device"))
    ctx.keys(d, _DEVICE_KEYS, "device", required=("mass",))
    delay = ctx.number(d, "delay", "device", 1.0, minimum=0.0)
    if delay != int(delay) or isinstance(d.get("delay"), float):
        raise ctx.error(f"must be a whole number of samples, got {d.get('delay')!r}",
                        ctx.line_of(d, "delay"), "device.delay")
    return Device(
        mass=ctx.number(d, "mass", "device", positive=True),
        friction=ctx.number(d, "friction", "device", 0.0, minimum=0.0),
        delay=int(delay),
        hold=ctx.string(d, "hold", "device", HOLDS, default="zoh"),
        force_limit=ctx.number(d, "force_limit", "device", math.inf, positive=True, allow_inf=True),
        position_resolution=ctx.number(d, "position_resolution", "device", 0.0, minimum=0.0),
        coulomb=ctx.number(d, "coulomb", "device", 0.0, minimum=0.0),
        noise=ctx.number(d, "noise", "device", 0.0, minimum=0.0),
    )


def _parse_excitation(ctx: _Ctx, doc: _LDict, path: str) -> Excitation:
    d = ctx.mapping(doc["excitation"], "excitation", ctx.line_of(doc, "excitation"))
    ctx.keys(d, _EXCITATION_KEYS, "excitation")
    impulse = None
    if "impulse" in d:
        i = ctx.mapping(d["impulse"], "excitation.impulse", ctx.line_of(d, "impulse"))
        ctx.keys(i, _IMPULSE_KEYS, "excitation.impulse", required=("force",))
        impulse = Impulse(ctx.number(i, "force", "excitation.impulse"),
                          ctx.number(i, "start", "excitation.impulse", 0.0, minimum=0.0),
                          ctx.number(i, "duration", "excitation.impulse", 0.0, minimum=0.0))
    profile = None
    if "profile" in d:
        profile = ctx.string(d, "profile", "excitation")
        if not os.path.isabs(profile) and path != "<string>":
            profile = os.path.join(os.path.dirname(os.path.abspath(path)), profile)
        if not os.path.exists(profile):
            raise ctx.error(f"profile file not found: {profile}", ctx.line_of(d, "profile"),
                            "excitation.profile")
    return Excitation(ctx.number(d, "x0", "excitation", 0.0), ctx.number(d, "v0", "excitation", 0.0),
                      impulse, profile)


def _parse_safety(ctx: _Ctx, doc: _LDict) -> Safety:
    d = ctx.mapping(doc["safety"], "safety", ctx.line_of(doc, "safety"))
    ctx.keys(d, _SAFETY_KEYS, "safety")
    pc = d.get("passivity_controller", False)
    if not isinstance(pc, bool):
        raise ctx.error(f"must be true or false, got {_typename(pc)} {pc!r}",
                        ctx.line_of(d, "passivity_controller"), "safety.passivity_controller")
    pos = None
    if "position_limit" in d:
        pos = ctx.number(d, "position_limit", "safety", positive=True, allow_inf=True)
    return Safety(
        position_limit=pos,
        velocity_limit=ctx.number(d, "velocity_limit", "safety", math.inf, positive=True,
                                  allow_inf=True),
        energy_limit=ctx.number(d, "energy_limit", "safety", 1.0, positive=True, allow_inf=True),
        passivity_controller=pc,
        max_damping=ctx.number(d, "max_damping", "safety", 50.0, minimum=0.0),
    )
