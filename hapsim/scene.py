"""YAML scene files: parsing and validation.

A scene is a CORDIS-ANIMA style mass-interaction network in SI units, plus the
description of the device it is felt through. Nothing reaches the engine or the
analysis without passing :func:`parse_scene`, which reports every problem as a
:class:`~hapsim.errors.ConfigError` naming the file, the line and the key.

Format
------
Every key, unit, default and limit is one row of :data:`hapsim.scene_schema.KEYS`, the
table this module reads and checks with; ``docs/scenes.md`` (the reference, with an example
for each key) is written from it by ``python -m hapsim.scene_doc``. A small scene:

.. code-block:: yaml

    rate_hz: 1000                 # sample rate [Hz]
    masses:
      - {name: hand, kind: port}                    # driven by the device position
      - {name: wall, kind: ground, x0: 0.0}         # fixed point [m]
    links:
      - {name: wall, kind: spring_damper, between: [hand, wall],
         stiffness: 1000, damping: 1.5}             # K [N/m], B [N s/m]
    device: {mass: 0.1, friction: 0.5, delay: 1, hold: zoh, force_limit: 10}
    excitation: {x0: 0.005}       # the hand starts 5 mm into the wall [m]

Link law (docs/design.md, 'The scheme'; Faust ``mi.lib`` ``spring``/``collision``): with
``x1``, ``x2`` the positions of the first and second mass named in ``between``,
``F = K (x1 - x2) + B ((x1 - x2) - (x1p - x2p)) / T`` is applied as ``-F`` on the first
mass and ``+F`` on the second. A contact acts only while ``x2 - x1 < threshold``, with its
spring measured from the threshold, ``F = K (x1 - x2 + threshold) + B (...) / T``, so the
force is continuous when the contact engages (Faust 2.54 ``mi.lib`` ``collision``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import os
from dataclasses import dataclass, field
from typing import Any, Callable

from hapsim._yaml_lines import LDict, LList, decode_text, load_yaml
from hapsim.errors import ConfigError, num, show, type_name
from hapsim.scene_schema import (HOLDS, INTEGRATORS, LINK_KINDS, LISTEN_QUANTITIES, MASS_KINDS,
                                 PORT_FORCE_MODES, PORT_POSITION_MODES, PROTOCOLS, Key,
                                 check_product, key_names, section_keys)
from hapsim.scene_schema import key as _key

__all__ = ["Mass", "Link", "Device", "Hand", "CORRECTIONS", "Impulse", "Excitation", "Safety",
           "Listen", "Audio",
           "Scene", "load_scene", "parse_scene", "MASS_KINDS", "LINK_KINDS", "HOLDS",
           "INTEGRATORS", "LISTEN_QUANTITIES", "PORT_POSITION_MODES", "PORT_FORCE_MODES",
           "PROTOCOLS"]

# Valid keys, defaults, types and ranges: one table, hapsim.scene_schema (docs/scenes.md is
# written from it by hapsim.scene_doc). Add a key there, not here.
_TOP_KEYS = key_names("")
_LINK_KEYS = {kind: key_names("links[]", kind) for kind in LINK_KINDS}
_TARGET_KEYS = key_names("links[].target")
_HAND_KEYS = ("mass", "damping", "grip_stiffness", "grip_damping", "stiffness")
#: Corrections of the virtual element and their parameters (hapsim.analysis.corrections).
CORRECTIONS = {"velocity_sensor": (), "velocity_filter": ("cutoff_hz",),
               "prediction": ("horizon",), "inertia_compensation": ("mass",),
               "virtual_coupling": ("stiffness", "damping")}


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
        Line of the entry in the scene file (0 when built in code).
    calibrated : bool
        True when (K, B) were written by calibration (:meth:`Scene.with_link`): the
        damping may then be negative, because the device's real friction b0 can exceed
        the damping to be felt (docs/design.md, 'The forward map'). A scene file cannot set
        it.
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
    calibrated: bool = False


@dataclass(frozen=True)
class Device:
    """The real side of the temporary hybrid system, as the scene describes it.

    Parameters
    ----------
    mass : float
        Moving mass m of hand + handle [kg], in [1e-12, 1e12].
    friction : float
        Real viscous friction b0 [N s/m], >= 0, with b0 T / m <= 1e6.
    delay : int
        Whole samples d between the position a force is computed from and the sample
        the force is applied at, 0 to 500 (the analysis's cost: O(d^3)).
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
    velocity_resolution : float
        Quantum of the mock device's velocity sensor (VELOCITY frames) [m/s]; 0 for none.
    velocity_noise : float
        Standard deviation of the mock device's velocity-sensor noise [m/s]; 0 for none.
    hand : Hand, optional
        The hand holding the handle; then ``mass`` and ``friction`` are the handle's alone.
    correction : dict, optional
        ``{"kind": name, param: value, ...}``, a correction of the virtual element
        (:data:`CORRECTIONS`, :mod:`hapsim.analysis.corrections`).
    protocol : str
        The protocol the device speaks on its port, one of :data:`PROTOCOLS`
        (``"framed"``, hapsim's own, by default).
    protocol_options : dict, optional
        The device's parameters in its driver's terms (the keywords of the driver's
        constructor, :mod:`hapsim.drivers`: FireFader ``full_scale``, ``metres_per_count``,
        ``axis``; Haply ``resolution``, ``direction``, ``device_id``, ``offset_deg``;
        Hapkit-serial ``function``, ``force_limit``); a driver's protocol only.
    """

    mass: float
    friction: float = 0.0
    delay: int = 1
    hold: str = "zoh"
    force_limit: float = math.inf
    position_resolution: float = 0.0
    coulomb: float = 0.0
    noise: float = 0.0
    velocity_resolution: float = 0.0
    velocity_noise: float = 0.0
    hand: "Hand | None" = None
    correction: dict | None = None
    protocol: str = "framed"
    protocol_options: dict | None = None


@dataclass(frozen=True)
class Hand:
    """The hand on the handle: a mass tied to the handle by a grip spring-damper.

    Each field is a number or a range ``(lo, hi)`` (a family of THS, Florens et al. Sec. 4).

    Parameters
    ----------
    mass : float or (float, float)
        Hand mass [kg], > 0.
    damping : float or (float, float)
        Hand damping to ground (the arm) [N s/m], >= 0.
    grip_stiffness : float or (float, float)
        Grip spring between hand and handle [N/m], > 0; ``inf`` for a rigid grip (then
        the hand mass and damping add to the handle's).
    grip_damping : float or (float, float)
        Grip damper between hand and handle [N s/m], >= 0.
    stiffness : float or (float, float)
        Hand (arm) stiffness to ground [N/m], >= 0 (Hogan's arm impedance: mass, damping,
        stiffness): a real spring in the THS (:mod:`hapsim.analysis.hand`).
    """

    mass: Any
    damping: Any = 0.0
    grip_stiffness: Any = math.inf
    grip_damping: Any = 0.0
    stiffness: Any = 0.0

    @property
    def rigid(self) -> bool:
        """Whether the grip is rigid (``grip_stiffness`` is ``inf``)."""
        return isinstance(self.grip_stiffness, float) and math.isinf(self.grip_stiffness)


@dataclass(frozen=True)
class Impulse:
    """A rectangular force pulse applied by the hand on the (mock) device.

    Parameters
    ----------
    force : float
        Pulse height [N], finite.
    start : float
        Time the pulse starts [s], >= 0.
    duration : float
        Pulse length [s], >= 0 (0: no pulse).
    """

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
        Add the adaptive damping ``alpha = E / (T v^2)`` while ``E``, the energy given
        to the hand beyond what the scene stored at its (re)start, is positive.
    max_damping : float
        Cap of the adaptive damping [N s/m].
    """

    position_limit: float | None = None
    velocity_limit: float = math.inf
    energy_limit: float = 1.0
    passivity_controller: bool = False
    max_damping: float = 50.0


@dataclass(frozen=True)
class Listen:
    """One listening point of a scene's sound (scene section ``audio.listen``).

    Parameters
    ----------
    mass : str
        Name of the mass listened to.
    quantity : {"velocity", "position", "force"}
        What is heard: its backward-difference velocity ``(x[k] - x[k-1]) / Ta`` [m/s], its
        position [m] or the force on it [N], at every audio sample ``k``.
    gain : float
        Factor from that quantity to the output sample (full scale 1.0), finite.
    """

    mass: str
    quantity: str = "velocity"
    gain: float = 1.0


@dataclass(frozen=True)
class Audio:
    """The sound of a scene (section ``audio:``): a multi-rate model.

    Every virtual mass runs at the audio rate ``rate_hz`` (period ``Ta = 1 / rate_hz``);
    the device couples at the scene's rate (period ``T = N Ta``, ``N`` a whole number).
    Within device period ``n`` the port position at audio sub-step ``j = 0 .. N-1`` is
    ``p[n]`` (``"hold"``, a zero-order hold of the device sample) or
    ``p[n-1] + (j + 1) / N (p[n] - p[n-1])`` (``"linear"``, the miPhysics-style smoothing
    of the haptic input); the force sent to the device is the mean of the N sub-step port
    forces (``"mean"``, a boxcar decimator) or the last one (``"last"``). The closed-loop
    analysis (:func:`hapsim.analysis.network.closed_loop`) composes these N audio steps into
    one device-rate map, so ``check`` and the felt (k, b) stay exact for this model.

    Parameters
    ----------
    rate_hz : float
        Audio rate [Hz]: a whole multiple of the scene's ``rate_hz``.
    listen : tuple of Listen
        Listening points, one output channel each (non-empty).
    port_position : {"hold", "linear"}
        Port position up to the audio rate. With ``"hold"`` and ``"mean"`` a port-ground
        link renders exactly as at the device rate (so felt targets calibrate as there).
    port_force : {"mean", "last"}
        Port force down to the device rate.
    """

    rate_hz: float
    listen: tuple[Listen, ...]
    port_position: str = "hold"
    port_force: str = "mean"

    def __post_init__(self) -> None:
        if isinstance(self.listen, list):
            object.__setattr__(self, "listen", tuple(self.listen))

    @property
    def period(self) -> float:
        """Audio sample period Ta = 1 / rate_hz [s]."""
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class Scene:
    """A validated scene: read it with :func:`load_scene` or :func:`parse_scene`, or build it.

    Every scene is checked when it is constructed (in code, by :func:`dataclasses.replace`
    or from a file), with the same rules as a scene file, so none reaches the engine or
    the analysis unvalidated.

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
    audio : Audio or None
        The scene's sound (section ``audio:``): multi-rate model, listening points.

    Raises
    ------
    ConfigError
        When a rule of the scene format is broken: the message names the key (e.g.
        ``masses[2].mass``) and, for an entry read from a file, the file and the line.
        Rules: ``rate_hz`` in [1e-6, 1e9] Hz; a known ``integrator``; a non-empty tuple of
        masses with unique names and a known kind; ``mass`` in [1e-12, 1e12] kg for kind
        ``mass`` (0 otherwise); ``device.delay`` <= 500 samples (ranges and their reasons:
        ``hapsim.analysis.loop.RATE_RANGE``, ``MASS_RANGE``, ``MAX_DELAY``);
        finite ``x0``, ``v0`` (``v0`` = 0 unless kind ``mass``); at most one port, and a
        ``device`` when there is one; links with unique names and a known kind between two
        different existing masses; stiffness >= 0 and damping >= 0, finite (NaN only
        while a ``target`` awaits calibration; negative damping only when ``calibrated``);
        a finite threshold on a contact, 0 on a spring_damper; a ``target`` only on a
        spring_damper between the port and a ground, with k > 0, b >= 0; no contact
        with ``integrator: exact``; the loop's dimensionless products (``b0 T/m``,
        ``|K| T^2/m``, ``|B| T/m`` at a link's lightest moving end, a target's ``k T^2/m``
        and ``b T/m``, the hand's ``kh T^2/mh``) at most
        ``hapsim.analysis.loop.MAX_PRODUCT``; and the ranges given in :class:`Device`,
        :class:`Excitation` (the ``profile`` file must exist) and :class:`Safety`.
    """

    rate_hz: float
    masses: tuple[Mass, ...]
    links: tuple[Link, ...]
    device: Device | None = None
    excitation: Excitation = field(default_factory=Excitation)
    path: str = "<string>"
    integrator: str = "centred"
    safety: Safety = field(default_factory=Safety)
    audio: Audio | None = None

    def __post_init__(self) -> None:
        for name in ("masses", "links"):
            value = getattr(self, name)
            if isinstance(value, list):
                object.__setattr__(self, name, tuple(value))
        try:
            _check_scene(self)
        except _Invalid as bad:
            line = _code_line(self, bad.where)
            shown = self.path if (line is not None or self.path != "<string>") else None
            err = ConfigError(bad.message, file=shown, line=line, key=bad.key)
            err._scene_where = bad.where  # lets parse_scene name the line of the key itself
            raise err from None

    @property
    def dimension(self) -> int:
        """Degrees of freedom of the scene: 1 (n-D scenes are :mod:`hapsim.scene_nd`'s)."""
        return 1

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

        Parameters
        ----------
        name : str
            Mass name.

        Returns
        -------
        int
            0-based position in :attr:`masses` (the column of that mass in the engine's
            arrays and in :meth:`hapsim.engine.Engine.positions`).

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

        Parameters
        ----------
        name : str
            Link name (``link<i>`` for an unnamed link of a scene file, i its index).

        Returns
        -------
        Link
            The link as stored (K [N/m], B [N s/m] NaN while a target awaits calibration).

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

        Returns
        -------
        Scene
            A validated copy in which that link has the given (K, B) and
            ``calibrated=True``; every other field is unchanged.

        Raises
        ------
        KeyError
            When no link has that name.
        ConfigError
            When the values are not finite or the stiffness is negative (key
            ``links[i].stiffness`` / ``links[i].damping``, with the file and the link's line
            for a scene read from a file).
        """
        self.link(name)
        links = tuple(dataclasses.replace(lk, stiffness=_coerce(stiffness),
                                          damping=_coerce(damping), calibrated=True)
                      if lk.name == name else lk for lk in self.links)
        return dataclasses.replace(self, links=links)

    def with_rate(self, rate_hz: float) -> "Scene":
        """A copy of the scene at another sample rate.

        Parameters
        ----------
        rate_hz : float
            New sample rate [Hz], finite and > 0.

        Returns
        -------
        Scene
            A validated copy with ``rate_hz`` replaced (period ``T = 1 / rate_hz`` [s]).
            The links keep their (K, B): recalibrate target links for the new rate.

        Raises
        ------
        ConfigError
            When ``rate_hz`` is not a positive finite number (key ``rate_hz``).
        """
        return dataclasses.replace(self, rate_hz=_coerce(rate_hz))


# --------------------------------------------------------------------------- YAML with lines
# The bounded reader (encodings, depth, alias size, merge keys, YAML 1.2 floats) lives in
# hapsim._yaml_lines; these names keep the rest of this module unchanged.
_LDict = LDict
_LList = LList


# --------------------------------------------------------------------------- the rules

class _Invalid(Exception):
    """One broken rule: the message, the key to name and where in the scene it lies.

    ``where`` is the path of the offending value (``("masses", 2, "mass")``); it finds the
    line, in the YAML document for a file, else on the Mass or Link entry.
    """

    def __init__(self, message: str, where: tuple, key: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.where = where
        self.key = key if key is not None else _key_of(where)


def _key_of(where: tuple) -> str:
    out = ""
    for step in where:
        out += f"[{step}]" if isinstance(step, int) else (f".{step}" if out else str(step))
    return out


def _is_number(v: Any) -> bool:
    if type(v) is float or type(v) is int:   # the common case, without the ABC check
        return True
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _float(v: Any) -> float:
    """``float(v)``; an integer beyond the double range (YAML reads 400 digits as one) is
    ``+-inf``, which the rules refuse as not finite, instead of an ``OverflowError``."""
    try:
        return float(v)
    except OverflowError:
        return math.inf if v > 0 else -math.inf


def _coerce(v: Any) -> Any:
    """``float(v)`` for a real number; anything else unchanged (the rules report it)."""
    return _float(v) if _is_number(v) else v


def _number(v: Any, *where: Any, positive: bool = False, minimum: float | None = None,
            allow_inf: bool = False, maximum: float | None = None) -> None:
    if not _is_number(v):
        raise _Invalid(f"must be a number, got {type_name(v)} {show(v)}", where)
    v = _float(v)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise _Invalid(f"must be a finite number, got {v}", where)
    if positive and not v > 0:
        raise _Invalid(f"must be > 0, got {num(v)}", where)
    if minimum is not None and v < minimum:
        raise _Invalid(f"must be >= {minimum:g}, got {num(v)}", where)
    if maximum is not None and v > maximum:
        raise _Invalid(f"must be <= {maximum:g}, got {num(v)}", where)


def _check_key(k: Key, v: Any, *where: Any) -> None:
    """Check ``v`` against its row ``k`` of the scene table (types the table can check)."""
    if v is None and k.default is None:
        return                       # absent: none
    if k.type == "number":
        _number(v, *where, allow_inf=k.allow_inf)
        _in_range(k, _float(v), where)
    elif k.type == "integer":
        if not (isinstance(v, numbers.Integral) and not isinstance(v, bool)):
            raise _Invalid(f"must be a whole number of {k.unit or 'units'}, got {show(v)}",
                           where)
        _in_range(k, v, where)
    elif k.type == "choice":
        _choice(v, k.choices, *where)
    elif k.type == "string":
        _string(v, *where)
    elif k.type == "boolean":
        if not isinstance(v, bool):
            raise _Invalid(f"must be true or false, got {type_name(v)} {show(v)}", where)


def _in_range(k: Key, x: float, where: tuple) -> None:
    """The row's ``minimum`` (``strict``: excluded) and ``maximum``, then the analysis's
    limits it names (``limits_from``), with its ``why``."""
    unit = f" {k.unit}" if k.unit else ""
    checks = ((k.minimum, k.maximum, k.strict, not k.limits_from),
              (*k.analysis_limits(), False, True))
    for lo, hi, strict, explained in checks:
        below = lo is not None and (x < lo or (strict and x == lo))
        if not (below or (hi is not None and x > hi)):
            continue
        if lo is not None and hi is not None:
            msg = f"must be between {lo:g} and {hi:g}{unit}, got {num(x)}"
        elif below:
            msg = f"must be {'>' if strict else '>='} {lo:g}, got {num(x)}"
        else:
            msg = f"must be <= {hi:g}{unit}, got {num(x)}"
        raise _Invalid(msg + (f": {k.why_text()}" if k.why and explained else ""), where)


def _check_section(obj: Any, section: str, *where: Any) -> None:
    """Check every field of a dataclass section against the table, in table order."""
    for k in section_keys(section):
        _check_key(k, getattr(obj, k.name), *where, k.name)


def _choice(v: Any, choices: tuple[str, ...], *where: Any) -> None:
    if not isinstance(v, str):
        raise _Invalid(f"must be a string, got {type_name(v)} {show(v)}", where)
    if v not in choices:
        raise _Invalid(f"unknown value {show(v)}; valid choices: {', '.join(choices)}", where)


def _string(v: Any, *where: Any) -> None:
    if not isinstance(v, str):
        raise _Invalid(f"must be a string, got {type_name(v)} {show(v)}", where)


def _first(line: int, where: tuple) -> str:
    return f"first on line {line}" if line else f"first is {_key_of(where)}"


def _check_scene(s: Scene) -> None:
    """Every rule a scene obeys, whether it was read from YAML or built in code.

    The YAML reader checks only what the dataclasses cannot express (syntax, structure,
    unknown and missing keys); every value is checked here, once.

    Raises
    ------
    _Invalid
        On the first broken rule, in scene order.
    """
    _check_key(_key("rate_hz"), s.rate_hz, "rate_hz")
    _check_key(_key("integrator"), s.integrator, "integrator")
    if not isinstance(s.path, str):
        raise _Invalid(f"must be a string, got {type_name(s.path)}", ("path",))
    if not isinstance(s.masses, tuple) or not s.masses:
        raise _Invalid("must be a non-empty list of masses", ("masses",))
    names: dict[str, int] = {}
    ports: list[int] = []
    for i, m in enumerate(s.masses):
        if not isinstance(m, Mass):
            raise _Invalid(f"must be a hapsim.scene.Mass, got {type_name(m)}", ("masses", i))
        _check_key(_key("masses[].kind"), m.kind, "masses", i, "kind")
        _check_key(_key("masses[].name"), m.name, "masses", i, "name")
        if m.name in names:
            j = names[m.name]
            raise _Invalid(f"duplicate mass name {show(m.name)} "
                           f"({_first(s.masses[j].line, ('masses', j))})", ("masses", i, "name"))
        names[m.name] = i
        if m.kind == "mass":
            _check_key(_key("masses[].mass"), m.mass, "masses", i, "mass")
        elif m.mass != 0:
            raise _Invalid(f"must be 0 for a {m.kind} (only kind mass has inertia), "
                           f"got {show(m.mass)}", ("masses", i, "mass"))
        _check_key(_key("masses[].x0"), m.x0, "masses", i, "x0")
        _check_key(_key("masses[].v0"), m.v0, "masses", i, "v0")
        if m.kind != "mass" and m.v0 != 0:
            raise _Invalid(f"must be 0 for a {m.kind} (it does not move by itself), "
                           f"got {show(m.v0)}", ("masses", i, "v0"))
        if m.kind == "port":
            ports.append(i)
    if len(ports) > 1:
        raise _Invalid(f"at most one port per scene (1-DoF device); found {len(ports)}: "
                       + ", ".join(_bare(s.masses[p].name) for p in ports), ("masses", ports[1]),
                       key="masses")
    _check_links(s, names)
    if s.device is not None:
        _check_device(s.device)
    elif ports:
        raise _Invalid("a scene with a port needs a device section "
                       "(mass, friction, delay, hold, ...)", ("device",))
    _check_products(s)
    _check_excitation(s.excitation)
    _check_safety(s.safety)
    if s.audio is not None:
        _check_audio(s, names)


def _check_products(s: Scene) -> None:
    """The loop's dimensionless products, for every command alike (``check`` and
    ``simulate`` once disagreed): ``b0 T/m`` of the device, ``kh T^2/mh`` of the hand's
    spring, ``|K| T^2/m`` and ``|B| T/m`` of every link (``m`` its lightest moving end: a
    virtual mass, or the device mass at the port) and, for a felt target, ``k T^2/m`` and
    ``b T/m`` at the port: at most :data:`hapsim.analysis.loop.MAX_PRODUCT` (the reason is
    there: the characteristic's coefficients would span more than a double resolves, and
    the engine's update diverges within a row)."""
    T = 1.0 / float(s.rate_hz)

    def refuse(value, scale, unit, what, where):
        try:
            check_product(float(value), scale, _key_of(where), unit, what)
        except ConfigError as exc:
            raise _Invalid(exc.reason, where) from None

    inertia = {m.name: float(m.mass) for m in s.masses if m.kind == "mass"}
    d = s.device
    port = next((m.name for m in s.masses if m.kind == "port"), None)
    if d is not None and port is not None:
        m_dev = float(d.mass)
        inertia[port] = m_dev
        refuse(d.friction, T / m_dev, "N s/m", "b0 T/m", ("device", "friction"))
        h = d.hand
        if h is not None:
            hi = lambda v: float(v[1]) if isinstance(v, tuple) else float(v)  # noqa: E731
            lo = lambda v: float(v[0]) if isinstance(v, tuple) else float(v)  # noqa: E731
            if hi(h.stiffness) > 0:
                refuse(hi(h.stiffness), T * T / lo(h.mass), "N/m", "kh T^2/m",
                       ("device", "hand", "stiffness"))
    for i, lk in enumerate(s.links):
        ends = [inertia[n] for n in (lk.m1, lk.m2) if n in inertia]
        if not ends:
            continue
        m = min(ends)
        for value, scale, unit, what, where in (
                (lk.stiffness, T * T / m, "N/m", "K T^2/m", ("links", i, "stiffness")),
                (lk.damping, T / m, "N s/m", "B T/m", ("links", i, "damping"))):
            if not math.isnan(float(value)):          # NaN: a target awaiting calibration
                refuse(value, scale, unit, what, where)
        if lk.target is not None and not lk.calibrated:
            refuse(lk.target[0], T * T / m, "N/m", "k T^2/m", ("links", i, "target", "k"))
            refuse(lk.target[1], T / m, "N s/m", "b T/m", ("links", i, "target", "b"))


def audio_substeps(audio_rate: float, rate_hz: float) -> int:
    """Audio sub-steps per device period, ``N = audio_rate / rate_hz``.

    Parameters
    ----------
    audio_rate, rate_hz : float
        Audio and device rates [Hz].

    Returns
    -------
    int
        N >= 1.

    Raises
    ------
    ValueError
        When the ratio is not a whole number >= 1 (to 1e-9 relative).
    """
    r = float(audio_rate) / float(rate_hz)
    n = round(r)
    if n < 1 or abs(r - n) > 1e-9 * r:
        raise ValueError(f"the audio rate {audio_rate:g} Hz must be a whole multiple of "
                         f"rate_hz {rate_hz:g} Hz (ratio {r:g})")
    return int(n)


def _check_audio(s: Scene, names: dict[str, int]) -> None:
    a = s.audio
    if not isinstance(a, Audio):
        raise _Invalid(f"must be a hapsim.scene.Audio, got {type_name(a)}", ("audio",))
    _check_key(_key("audio.rate_hz"), a.rate_hz, "audio", "rate_hz")
    try:
        audio_substeps(a.rate_hz, s.rate_hz)
    except ValueError as exc:
        raise _Invalid(str(exc), ("audio", "rate_hz")) from None
    if s.integrator != "centred":
        raise _Invalid(f"audio runs the centred scheme only; got integrator "
                       f"{s.integrator!r}", ("integrator",))
    _check_key(_key("audio.port_position"), a.port_position, "audio", "port_position")
    _check_key(_key("audio.port_force"), a.port_force, "audio", "port_force")
    if not isinstance(a.listen, tuple) or not a.listen:
        raise _Invalid("must be a non-empty list of listening points {mass, quantity, gain}",
                       ("audio", "listen"))
    for i, ls in enumerate(a.listen):
        if not isinstance(ls, Listen):
            raise _Invalid(f"must be a hapsim.scene.Listen, got {type_name(ls)}",
                           ("audio", "listen", i))
        _check_key(_key("audio.listen[].mass"), ls.mass, "audio", "listen", i, "mass")
        if ls.mass not in names:
            raise _Invalid(f"no mass named {ls.mass!r}; masses are: "
                           + ", ".join(list(names)[:20]), ("audio", "listen", i, "mass"))
        _check_key(_key("audio.listen[].quantity"), ls.quantity, "audio", "listen", i,
                   "quantity")
        _check_key(_key("audio.listen[].gain"), ls.gain, "audio", "listen", i, "gain")
    if a.port_position != "hold" and s.port is not None:
        for i, lk in enumerate(s.links):
            if lk.target is not None:
                raise _Invalid("a felt target is calibrated for the device-rate link; with "
                               "audio.port_position: linear the port link renders "
                               "differently: use port_position: hold, or give (K, B)",
                               ("links", i, "target"))


def _check_links(s: Scene, names: dict[str, int]) -> None:
    if not isinstance(s.links, tuple):
        raise _Invalid(f"must be a list of links, got {type_name(s.links)}", ("links",))
    seen: dict[str, int] = {}
    for i, lk in enumerate(s.links):
        if not isinstance(lk, Link):
            raise _Invalid(f"must be a hapsim.scene.Link, got {type_name(lk)}", ("links", i))
        _check_key(_key("links[].kind"), lk.kind, "links", i, "kind")
        _check_key(_key("links[].name"), lk.name, "links", i, "name")
        if lk.name in seen:
            j = seen[lk.name]
            raise _Invalid(f"duplicate link name {show(lk.name)} "
                           f"({_first(s.links[j].line, ('links', j))})", ("links", i, "name"))
        seen[lk.name] = i
        for n in (lk.m1, lk.m2):
            if n not in names:
                shown = ", ".join(_bare(k) for k in list(names)[:20])
                shown += ", ..." if len(names) > 20 else ""
                raise _Invalid(f"no mass named {show(n)}; masses are: {shown}",
                               ("links", i, "between"))
        if lk.m1 == lk.m2:
            raise _Invalid(f"a link cannot join mass {show(lk.m1)} to itself", ("links", i, "between"))
        if not isinstance(lk.calibrated, bool):
            raise _Invalid(f"must be True or False, got {show(lk.calibrated)}",
                           ("links", i, "calibrated"))
        awaiting = False
        if lk.target is not None:
            ends = {s.masses[names[lk.m1]].kind, s.masses[names[lk.m2]].kind}
            if lk.kind != "spring_damper" or ends != {"port", "ground"}:
                raise _Invalid("a felt target {k, b} can only be calibrated for a "
                               "spring_damper between the port and a ground",
                               ("links", i, "target"))
            if not (isinstance(lk.target, tuple) and len(lk.target) == 2):
                raise _Invalid(f"must be a pair (k, b), got {show(lk.target)}", ("links", i, "target"))
            _check_key(_key("links[].target.k"), lk.target[0], "links", i, "target", "k")
            _check_key(_key("links[].target.b"), lk.target[1], "links", i, "target", "b")
            awaiting = not lk.calibrated
        # NaN (K, B) mean "awaiting calibration" for a target link, nothing else.
        if not (awaiting and _is_number(lk.stiffness) and math.isnan(lk.stiffness)):
            _check_key(_key("links[].stiffness"), lk.stiffness, "links", i, "stiffness")
        if not (awaiting and _is_number(lk.damping) and math.isnan(lk.damping)):
            # A calibrated B may be negative: the device's real friction b0 can exceed the
            # felt damping (docs/design.md, 'The forward map'); a scene file or a hand-built
            # link may not.
            if lk.calibrated:
                _number(lk.damping, "links", i, "damping")
            else:
                _check_key(_key("links[].damping"), lk.damping, "links", i, "damping")
        if lk.kind == "contact":
            _check_key(_key("links[].threshold"), lk.threshold, "links", i, "threshold")
            if s.integrator == "exact":
                raise _Invalid("the exact integrator takes linear links only; a contact "
                               "switches the network (use centred or symplectic_euler)",
                               ("links", i, "kind"))
        elif lk.threshold != 0:
            raise _Invalid(f"only a contact has a threshold; must be 0 for a {lk.kind}, "
                           f"got {show(lk.threshold)}", ("links", i, "threshold"))


def _check_device(d: Any) -> None:
    if not isinstance(d, Device):
        raise _Invalid(f"must be a hapsim.scene.Device, got {type_name(d)}", ("device",))
    _check_section(d, "device", "device")
    if d.hand is not None:
        _check_hand(d.hand, d.hold)
    if d.correction is not None:
        _check_correction(d.correction, d.hold)
    if d.protocol_options is not None:
        _check_protocol_options(d.protocol_options, d.protocol)


def _check_protocol_options(o: Any, protocol: str) -> None:
    """A driver's parameters: a mapping its constructor accepts (unknown keys and bad
    values named with the valid choices)."""
    where = ("device", "protocol_options")
    if not isinstance(o, dict):
        raise _Invalid(f"must be a mapping, got {type_name(o)} {show(o)}", where)
    if protocol == "framed":
        raise _Invalid("the framed protocol takes no options (its device says its own "
                       "units in HELLO); set device.protocol to a driver", where)
    import inspect

    from hapsim.drivers import get_driver
    from hapsim.errors import ConfigError
    cls = type(get_driver(protocol))
    valid = tuple(n for n in inspect.signature(cls.__init__).parameters if n != "self")
    for name in o:
        if name not in valid:
            raise _Invalid(f"unknown option {show(name)} for {protocol}; valid: "
                           f"{', '.join(valid)}", (*where, name))
    try:
        get_driver(protocol, **o)
    except ConfigError as exc:
        raise _Invalid(exc.reason, (*where, exc.key) if exc.key else where) from None
    except (TypeError, ValueError) as exc:
        raise _Invalid(str(exc), where) from None


def _check_hand(h: Any, hold: str) -> None:
    if not isinstance(h, Hand):
        raise _Invalid(f"must be a hapsim.scene.Hand, got {type_name(h)}", ("device", "hand"))
    for key, positive, inf in (("mass", True, False), ("damping", False, False),
                               ("grip_stiffness", True, True), ("grip_damping", False, False),
                               ("stiffness", False, False)):
        v = getattr(h, key)
        where = ("device", "hand", key)
        if isinstance(v, tuple):
            if len(v) != 2:
                raise _Invalid(f"a range is [lo, hi], got {list(v)!r}", where)
            for x in v:
                _number(x, *where, positive=positive, minimum=None if positive else 0.0)
            if not v[0] <= v[1]:
                raise _Invalid(f"a range [lo, hi] needs lo <= hi, got {list(v)!r}", where)
        else:
            _number(v, *where, positive=positive, minimum=None if positive else 0.0,
                    allow_inf=inf)
    if not h.rigid and hold != "zoh":
        raise _Invalid("a compliant grip needs hold: zoh (the ideal hold models one mass); "
                       "use grip_stiffness: rigid", ("device", "hand", "grip_stiffness"))


def _check_correction(c: Any, hold: str) -> None:
    where = ("device", "correction")
    if not isinstance(c, dict) or "kind" not in c:
        raise _Invalid("must be a mapping with a kind; valid kinds: "
                       + ", ".join(CORRECTIONS), where)
    _choice(c["kind"], tuple(CORRECTIONS), *where, "kind")
    allowed = ("kind",) + CORRECTIONS[c["kind"]]
    for k, v in c.items():
        if k not in allowed:
            raise _Invalid(f"unknown key {k!r} for {c['kind']}; valid keys: "
                           + ", ".join(allowed), where + (k,))
        if k != "kind":
            _number(v, *where, k, minimum=0.0)
    if c["kind"] == "velocity_filter":
        if "cutoff_hz" not in c:
            raise _Invalid("velocity_filter needs cutoff_hz [Hz]", where + ("cutoff_hz",))
        _number(c["cutoff_hz"], *where, "cutoff_hz", positive=True)
    if c["kind"] == "velocity_sensor" and hold != "zoh":
        raise _Invalid("a velocity sensor needs hold: zoh (the ideal hold has no velocity)",
                       where + ("kind",))


def _check_excitation(e: Any) -> None:
    if not isinstance(e, Excitation):
        raise _Invalid(f"must be a hapsim.scene.Excitation, got {type_name(e)}", ("excitation",))
    if e.impulse is not None and not isinstance(e.impulse, Impulse):
        raise _Invalid(f"must be a hapsim.scene.Impulse, got {type_name(e.impulse)}",
                       ("excitation", "impulse"))
    _check_section(e, "excitation", "excitation")
    if e.impulse is not None:
        _check_section(e.impulse, "excitation.impulse", "excitation", "impulse")
    if e.profile is not None:
        if not os.path.exists(e.profile):
            raise _Invalid(f"profile file not found: {e.profile}", ("excitation", "profile"))


def _check_safety(f: Any) -> None:
    if not isinstance(f, Safety):
        raise _Invalid(f"must be a hapsim.scene.Safety, got {type_name(f)}", ("safety",))
    _check_section(f, "safety", "safety")


def _code_line(s: Scene, where: tuple) -> int | None:
    """Line of the Mass or Link entry ``where`` points into (None when unknown)."""
    if len(where) >= 2 and where[0] in ("masses", "links") and isinstance(where[1], int):
        seq = getattr(s, where[0])
        if isinstance(seq, tuple) and 0 <= where[1] < len(seq):
            return getattr(seq[where[1]], "line", 0) or None
    return None


# --------------------------------------------------------------------------- YAML reading

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
            raise self.error(f"must be a mapping (key: value), got {type_name(value)}", line, key)
        return value

    def keys(self, d: _LDict, allowed: tuple[str, ...], key: str, required: tuple[str, ...] = ()) -> None:
        for k in d:
            if k not in allowed:
                raise self.error(f"unknown key {show(k)}; valid keys: {', '.join(allowed)}",
                                 self.line_of(d, k), _key_name(key, k))
        for k in required:
            if k not in d:
                raise self.error(f"missing required key {show(k)}", getattr(d, "line", None),
                                 f"{key}.{k}" if key else k)

    def not_null(self, d: _LDict, k: str, key: str) -> None:
        """Refuse ``k: null`` for a key whose absence means "none" (say what was meant)."""
        if k in d and d[k] is None:
            raise self.error(f"must be given a value, got {type_name(None)} (leave the key "
                             "out for none)", self.line_of(d, k), f"{key}.{k}")

    def kind(self, d: _LDict, key: str, choices: tuple[str, ...]) -> str:
        """The ``kind`` of an entry, checked now: it decides which keys the entry may have."""
        if "kind" not in d:
            raise self.error("missing required key 'kind'", getattr(d, "line", None),
                             f"{key}.kind")
        try:
            _choice(d["kind"], choices, "kind")
        except _Invalid as bad:
            raise self.error(bad.message, self.line_of(d, "kind"), f"{key}.kind") from None
        return d["kind"]

    @staticmethod
    def doc_line(doc: _LDict, where: tuple) -> int | None:
        """Line of the value at path ``where`` in the document (or of its nearest parent)."""
        node: Any = doc
        line = getattr(doc, "line", None)
        for step in where:
            lines = getattr(node, "lines", None)
            if not lines or step not in lines:
                break
            line = lines[step]
            try:
                node = node[step]
            except (KeyError, IndexError, TypeError):
                break
        return line


def _bare(k: Any) -> str:
    """A name as a message prints it: bare when short and plain, else :func:`show`-n."""
    plain = isinstance(k, str) and k.isprintable() and 0 < len(k) <= 40 and " " not in k
    return k if plain else show(k, 40)


def _key_name(parent: str, k: Any) -> str:
    """Dotted key ``parent.k`` for a message (an odd key is :func:`show`-n)."""
    return f"{parent}.{_bare(k)}" if parent else _bare(k)


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
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise ConfigError(f"cannot read scene file: {exc.strerror or exc}", file=path) from exc
    text = decode_text(data, path)
    if len(text) < 1_000_000:
        return parse_scene(text, path)
    from hapsim.progress import Progress
    with Progress(len(text), f"reading {os.path.basename(path)}", unit="chars") as bar:
        return parse_scene(text, path, progress=bar.update)


def parse_scene(text: str, path: str = "<string>",
                progress: Callable[[int, int], None] | None = None) -> Scene:
    """Parse and validate scene text.

    Parameters
    ----------
    text : str
        YAML text of the scene.
    path : str
        Name used in error messages and to resolve relative ``excitation.profile`` paths.
    progress : callable, optional
        ``progress(done, total)`` [characters] while the YAML is read (see
        :func:`hapsim._yaml_lines.load_yaml`).

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

    Notes
    -----
    This reader checks what only a file has (syntax, structure, unknown and missing keys)
    and builds the dataclasses; the values are checked by the same rules as a scene built
    in code (:class:`Scene` validates itself), with the line of the offending key.
    """
    doc = load_yaml(text, path, progress)

    ctx = _Ctx(path)
    if doc is None:
        raise ctx.error("the scene is empty; it needs at least rate_hz and masses", 1, "rate_hz")
    doc = ctx.mapping(doc, "", 1)
    ctx.keys(doc, _TOP_KEYS, "", required=tuple(k.name for k in section_keys("") if k.required))
    if "dimension" in doc:
        try:
            _check_key(_key("dimension"), doc["dimension"], "dimension")
        except _Invalid as bad:
            raise ctx.error(bad.message, ctx.line_of(doc, "dimension"), "dimension") from None
        if doc["dimension"] != 1:
            raise ctx.error(f"a {doc['dimension']}-D scene: `hapsim check` reads it "
                            "(hapsim.scene_nd); this reader and the commands that run a "
                            "scene take dimension 1", ctx.line_of(doc, "dimension"),
                            "dimension")
    masses = _read_masses(ctx, doc)
    links = _read_links(ctx, doc, masses)
    device = _read_device(ctx, doc) if "device" in doc else None
    excitation = _read_excitation(ctx, doc, path) if "excitation" in doc else Excitation()
    safety = _read_safety(ctx, doc) if "safety" in doc else Safety()
    audio = _read_audio(ctx, doc) if "audio" in doc else None
    try:
        return Scene(rate_hz=_coerce(doc["rate_hz"]), masses=tuple(masses), links=tuple(links),
                     device=device, excitation=excitation, path=path,
                     integrator=doc.get("integrator", _key("integrator").default), safety=safety,
                     audio=audio)
    except ConfigError as exc:
        where = getattr(exc, "_scene_where", None)
        if where is None:
            raise
        raise ConfigError(exc.reason, file=path, line=ctx.doc_line(doc, where),
                          key=exc.key) from None


def _read_values(ctx: _Ctx, d: _LDict, section: str, key: str,
                 kind: str | None = None) -> dict:
    """The keys of ``section`` the table checks by value, read from mapping ``d`` with the
    table's defaults (unknown and missing keys refused first, naming ``key``)."""
    rows = section_keys(section, kind)
    ctx.keys(d, tuple(k.name for k in rows), key,
             required=tuple(k.name for k in rows if k.required))
    out = {}
    for k in rows:
        if k.type in ("list", "mapping", "pair"):
            continue                                 # read by the section's own code
        if k.default is None:
            ctx.not_null(d, k.name, key)
        v = d.get(k.name, k.default)
        out[k.name] = _coerce(v) if k.type == "number" else v
    return out


def _read_masses(ctx: _Ctx, doc: _LDict) -> list[Mass]:
    seq = doc["masses"]
    if not isinstance(seq, list) or not seq:
        raise ctx.error("must be a non-empty list of masses", ctx.line_of(doc, "masses"), "masses")
    out: list[Mass] = []
    for i, item in enumerate(seq):
        key = f"masses[{i}]"
        d = ctx.mapping(item, key, ctx.line_of(seq, i))
        kind = ctx.kind(d, key, MASS_KINDS)
        out.append(Mass(**_read_values(ctx, d, "masses[]", key, kind), line=d.line))
    return out


def _read_links(ctx: _Ctx, doc: _LDict, masses: list[Mass]) -> list[Link]:
    if "links" not in doc or doc["links"] is None:
        return []
    seq = doc["links"]
    if not isinstance(seq, list):
        raise ctx.error(f"must be a list of links, got {type_name(seq)}",
                        ctx.line_of(doc, "links"), "links")
    out: list[Link] = []
    for i, item in enumerate(seq):
        key = f"links[{i}]"
        d = ctx.mapping(item, key, ctx.line_of(seq, i))
        kind = ctx.kind(d, key, LINK_KINDS)
        ctx.keys(d, _LINK_KEYS[kind], key, required=("between",))
        between = d["between"]
        if not (isinstance(between, list) and len(between) == 2
                and all(isinstance(n, str) for n in between)):
            raise ctx.error("must be a list of two mass names, e.g. [hand, wall]",
                            ctx.line_of(d, "between"), f"{key}.between")
        target = None
        stiffness = _coerce(d.get("stiffness", _key("links[].stiffness").default))
        damping = _coerce(d.get("damping", _key("links[].damping").default))
        if "target" in d:
            if "stiffness" in d or "damping" in d:
                raise ctx.error("give either target {k, b} or stiffness/damping, not both",
                                ctx.line_of(d, "target"), f"{key}.target")
            t = ctx.mapping(d["target"], f"{key}.target", ctx.line_of(d, "target"))
            ctx.keys(t, _TARGET_KEYS, f"{key}.target", required=_TARGET_KEYS)
            target = (_coerce(t["k"]), _coerce(t["b"]))
            stiffness = damping = math.nan
        elif "stiffness" not in d and "damping" not in d:
            raise ctx.error("a link needs stiffness and/or damping (or a target)",
                            d.line, f"{key}.stiffness")
        out.append(Link(d.get("name", f"link{i}"), kind, between[0], between[1], stiffness,
                        damping, _coerce(d.get("threshold", _key("links[].threshold").default)),
                        target, line=d.line))
    return out


def _read_device(ctx: _Ctx, doc: _LDict) -> Device:
    d = ctx.mapping(doc["device"], "device", ctx.line_of(doc, "device"))
    vals = _read_values(ctx, d, "device", "device")
    vals["hand"] = _read_hand(ctx, d) if "hand" in d else None
    vals["correction"] = (dict(ctx.mapping(d["correction"], "device.correction",
                                           ctx.line_of(d, "correction")))
                          if "correction" in d else None)
    vals["protocol_options"] = (dict(ctx.mapping(d["protocol_options"],
                                                 "device.protocol_options",
                                                 ctx.line_of(d, "protocol_options")))
                                if "protocol_options" in d else None)
    return Device(**vals)


def _read_hand(ctx: _Ctx, dev: _LDict) -> Hand:
    h = ctx.mapping(dev["hand"], "device.hand", ctx.line_of(dev, "hand"))
    ctx.keys(h, _HAND_KEYS, "device.hand", required=("mass",))

    def val(key, default):
        v = h.get(key, default)
        if key == "grip_stiffness" and v == "rigid":
            return math.inf
        if isinstance(v, list):
            return tuple(_coerce(x) for x in v)
        return _coerce(v)
    return Hand(val("mass", None), val("damping", 0.0), val("grip_stiffness", math.inf),
                val("grip_damping", 0.0), val("stiffness", 0.0))


def _read_excitation(ctx: _Ctx, doc: _LDict, path: str) -> Excitation:
    d = ctx.mapping(doc["excitation"], "excitation", ctx.line_of(doc, "excitation"))
    values = _read_values(ctx, d, "excitation", "excitation")
    if "impulse" in d:
        i = ctx.mapping(d["impulse"], "excitation.impulse", ctx.line_of(d, "impulse"))
        values["impulse"] = Impulse(**_read_values(ctx, i, "excitation.impulse",
                                                   "excitation.impulse"))
    profile = values["profile"]
    if isinstance(profile, str) and not os.path.isabs(profile) and path != "<string>":
        values["profile"] = os.path.join(os.path.dirname(os.path.abspath(path)), profile)
    return Excitation(**values)


def _read_safety(ctx: _Ctx, doc: _LDict) -> Safety:
    d = ctx.mapping(doc["safety"], "safety", ctx.line_of(doc, "safety"))
    return Safety(**_read_values(ctx, d, "safety", "safety"))


def _read_audio(ctx: _Ctx, doc: _LDict) -> Audio:
    d = ctx.mapping(doc["audio"], "audio", ctx.line_of(doc, "audio"))
    values = _read_values(ctx, d, "audio", "audio")
    seq = d["listen"]
    if not isinstance(seq, list) or not seq:
        raise ctx.error("must be a non-empty list of listening points {mass, quantity, gain}",
                        ctx.line_of(d, "listen"), "audio.listen")
    listen = []
    for i, item in enumerate(seq):
        key = f"audio.listen[{i}]"
        it = ctx.mapping(item, key, ctx.line_of(seq, i))
        listen.append(Listen(**_read_values(ctx, it, "audio.listen[]", key)))
    return Audio(listen=tuple(listen), **values)
