"""The scene: :class:`Scene`, a validated mass-interaction network with its device,
checked by :mod:`hapsim.scene.rules` whenever one is built; :class:`SceneND`, a 2-D or 3-D
one, checked by the reader that builds it (:func:`hapsim.scene.parse_scene_nd`)."""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field

from hapsim.errors import ConfigError
from hapsim.scene.elements import (Audio, Device, DeviceND, Excitation, ExcitationND, Link, Mass,
                                   MassND, Safety, SafetyND)
from hapsim.scene.rules import Invalid, check_scene, check_scene_ports, code_line, coerce

__all__ = ["Scene", "SceneND", "ScenePorts"]


def _validate(scene, sequences: tuple, check) -> None:
    """Turn the ``sequences`` fields given as lists into tuples, then ``check(scene)``; a
    broken rule raised as a :class:`ConfigError` with the entry's line, and the path of
    the value (``scene_where``) that lets the reader name the line of the key itself."""
    for name in sequences:
        value = getattr(scene, name)
        if isinstance(value, list):
            object.__setattr__(scene, name, tuple(value))
    try:
        check(scene)
    except Invalid as bad:
        line = code_line(scene, bad.where)
        shown = scene.path if (line is not None or scene.path != "<string>") else None
        err = ConfigError(bad.message, file=shown, line=line, key=bad.key)
        err.scene_where = bad.where
        raise err from None


def _link_named(links, name: str) -> Link:
    """The link called ``name`` in ``links`` (KeyError when none)."""
    for lk in links:
        if lk.name == name:
            return lk
    raise KeyError(name)


class _OneAxis:
    """What a 1-D scene (:class:`Scene`, :class:`ScenePorts`) says of its time and axes."""

    @property
    def dimension(self) -> int:
        """Degrees of freedom of each port: 1 (a 2-D or 3-D scene is a :class:`SceneND`)."""
        return 1

    @property
    def period(self) -> float:
        """Sample period T = 1 / rate_hz [s]."""
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class Scene(_OneAxis):
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
        _validate(self, ("masses", "links"), check_scene)

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
        return _link_named(self.links, name)

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
        links = tuple(dataclasses.replace(lk, stiffness=coerce(stiffness),
                                          damping=coerce(damping), calibrated=True)
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
        return dataclasses.replace(self, rate_hz=coerce(rate_hz))


@dataclass(frozen=True)
class SceneND:
    """A validated 2-D or 3-D scene (:func:`~hapsim.scene.load_scene_nd`, which checks it as it
    reads it); ``audio`` is its listening
    points (a tuple of :class:`ListenND`) or None, ``excitation`` the hand's force
    (:class:`ExcitationND`) or None; ``safety`` what a run does after a stop on the
    motion (:class:`SafetyND`); ``precision`` the engine's floating type,
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
    safety: SafetyND = field(default_factory=SafetyND)

    @property
    def period(self) -> float:
        """Sample period ``T`` [s]."""
        return 1.0 / self.rate_hz

    @property
    def port(self) -> MassND | None:
        """The port mass, or None."""
        return next((m for m in self.masses if m.kind == "port"), None)


@dataclass(frozen=True)
class ScenePorts(_OneAxis):
    """A validated 1-D scene with several ports, each felt through its own device (issue 30
    item 3): read it with :func:`hapsim.scene.load_scene_ports`, or build it.

    Checked when constructed (:func:`hapsim.scene.rules.check_scene_ports`), as
    :class:`Scene` is.

    Parameters
    ----------
    rate_hz : float
        The one sample rate of every port's loop [Hz] (several rates: not built).
    masses : tuple of Mass
        Ports and grounds, in file order (2 to 3 ports).
    links : tuple of Link
        Spring-dampers between ports and to grounds, in file order.
    devices : tuple of (str, Device)
        Each port's name and its device (mass [kg], friction [N s/m], delay [periods],
        protocol), in port order.
    path : str
        File the scene came from.
    integrator : str
        As :class:`Scene` (no virtual mass moves by it here).

    Raises
    ------
    ConfigError
        A broken rule, naming the key (``devices.fader_b.delay``) and, from a file, the
        file and the line.
    """

    rate_hz: float
    masses: tuple[Mass, ...]
    links: tuple[Link, ...]
    devices: tuple
    path: str = "<string>"
    integrator: str = "centred"

    def __post_init__(self) -> None:
        if isinstance(self.devices, (dict, list)):
            object.__setattr__(self, "devices", tuple(
                self.devices.items() if isinstance(self.devices, dict) else self.devices))
        masses = self.masses if isinstance(self.masses, (list, tuple)) else ()
        order = [m.name for m in masses if getattr(m, "kind", None) == "port"
                 and isinstance(getattr(m, "name", None), str)]
        if isinstance(self.devices, tuple) and all(
                isinstance(p, tuple) and len(p) == 2 and isinstance(p[0], str)
                for p in self.devices):
            rank = {n: i for i, n in enumerate(order)}
            object.__setattr__(self, "devices", tuple(sorted(
                self.devices, key=lambda p: rank.get(p[0], len(rank)))))
        _validate(self, ("masses", "links"), check_scene_ports)

    @property
    def ports(self) -> tuple[str, ...]:
        """The ports' names, in file order (the axes of the coupled loop)."""
        return tuple(n for n, _ in self.devices)

    def device(self, port: str) -> Device:
        """The device of the port called ``port``.

        Parameters
        ----------
        port : str
            A port's name.

        Returns
        -------
        Device

        Raises
        ------
        KeyError
            No port has that name.
        """
        return dict(self.devices)[port]

    def link(self, name: str) -> Link:
        """The link called ``name``.

        Parameters
        ----------
        name : str
            Link name.

        Returns
        -------
        Link
            The link as stored (K [N/m], B [N s/m]).

        Raises
        ------
        KeyError
            When no link has that name.
        """
        return _link_named(self.links, name)
