"""The rules of the scene format, checked on the dataclasses (a scene built in code or
read from a file meets the same ones): :func:`check_scene` raises :class:`Invalid` naming
the broken rule and the path of the offending value; :class:`~hapsim.scene.Scene` turns
it into a :class:`~hapsim.errors.ConfigError` with the file and the line. The single-key
rules (types, ranges, choices) are rows of :data:`hapsim.scene_schema.KEYS`; what spans
several keys is code here. A 2-D or 3-D scene's values are checked by its reader as it
builds them; the loop's products, the rule both share, are :func:`check_products_nd`'s."""

from __future__ import annotations

import math
import numbers
import os
from typing import Any

import numpy as np

from hapsim.errors import ConfigError, num, show, type_name
from hapsim.scene_schema import (MAX_PRODUCT, MIN_DELAY_FRACTION, Key, check_product,
                                  section_keys)
from hapsim.scene_schema import key as _key
from hapsim.scene.elements import (CORRECTIONS, Audio, Device, Excitation, Hand, Impulse, Link,
                                   Listen, Mass, Safety, audio_substeps)

__all__ = ["Invalid", "check_scene", "check_scene_ports", "PORTS_NOT_BUILT", "MAX_PORTS", "check_device", "check_key", "check_choice", "coerce",
           "code_line", "bare_name", "check_products_nd"]



class Invalid(Exception):
    """One broken rule: the message, the key to name and where in the scene it lies.

    ``where`` is the path of the offending value (``("masses", 2, "mass")``); it finds the
    line, in the YAML document for a file, else on the Mass or Link entry.

    Parameters
    ----------
    message : str
        What is wrong, with the valid values or range.
    where : tuple of str and int
        Path of the offending value in the scene.
    key : str, optional
        The key to name; default: ``where`` dotted (``masses[2].mass``).
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


def coerce(v: Any) -> Any:
    """``float(v)`` for a real number; anything else unchanged (the rules report it).

    Parameters
    ----------
    v : object
        A value read from a file or given in code.

    Returns
    -------
    float or object
        ``float(v)`` for a real number that is not a bool (an integer beyond the double
        range is ``+-inf``, which the rules refuse), else ``v`` itself.
    """
    return _float(v) if _is_number(v) else v


def _number(v: Any, *where: Any, positive: bool = False, minimum: float | None = None,
            allow_inf: bool = False, maximum: float | None = None) -> None:
    if not _is_number(v):
        raise Invalid(f"must be a number, got {type_name(v)} {show(v)}", where)
    v = _float(v)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise Invalid(f"must be a finite number, got {v}", where)
    if positive and not v > 0:
        raise Invalid(f"must be > 0, got {num(v)}", where)
    if minimum is not None and v < minimum:
        raise Invalid(f"must be >= {minimum:g}, got {num(v)}", where)
    if maximum is not None and v > maximum:
        raise Invalid(f"must be <= {maximum:g}, got {num(v)}", where)


def check_key(k: Key, v: Any, *where: Any) -> None:
    """Check ``v`` against its row ``k`` of the scene table (types the table can check).

    Parameters
    ----------
    k : hapsim.scene_schema.Key
        The row: type, range, choices, default.
    v : object
        The value (None for an absent key whose default is None: accepted).
    *where : str or int
        Path of the value in the scene, for the message.

    Raises
    ------
    Invalid
        Wrong type, out of the row's range, or not one of its choices.
    """
    if v is None and k.default is None:
        return                       # absent: none
    if k.type == "number":
        _number(v, *where, allow_inf=k.allow_inf)
        _in_range(k, _float(v), where)
    elif k.type == "integer":
        if not (isinstance(v, numbers.Integral) and not isinstance(v, bool)):
            raise Invalid(f"must be a whole number of {k.unit or 'units'}, got {show(v)}",
                           where)
        _in_range(k, v, where)
    elif k.type == "choice":
        check_choice(v, k.choices, *where)
    elif k.type == "string":
        _string(v, *where)
    elif k.type == "boolean":
        if not isinstance(v, bool):
            raise Invalid(f"must be true or false, got {type_name(v)} {show(v)}", where)


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
        # (the why is the largest value's: a value below the range gets none)
        raise Invalid(msg + (f": {k.why_text()}" if k.why and explained and not below
                             else ""), where)


def _check_section(obj: Any, section: str, *where: Any) -> None:
    """Check every field of a dataclass section against the table, in table order."""
    for k in section_keys(section):
        check_key(k, getattr(obj, k.name), *where, k.name)


def check_choice(v: Any, choices: tuple[str, ...], *where: Any) -> None:
    """Refuse ``v`` unless it is one of the strings ``choices``.

    Parameters
    ----------
    v : object
    choices : tuple of str
        The valid values, listed in the message.
    *where : str or int
        Path of the value in the scene.

    Raises
    ------
    Invalid
        Not a string, or not one of ``choices``.
    """
    if not isinstance(v, str):
        raise Invalid(f"must be a string, got {type_name(v)} {show(v)}", where)
    if v not in choices:
        raise Invalid(f"unknown value {show(v)}; valid choices: {', '.join(choices)}", where)


def _string(v: Any, *where: Any) -> None:
    if not isinstance(v, str):
        raise Invalid(f"must be a string, got {type_name(v)} {show(v)}", where)


def _first(line: int, where: tuple) -> str:
    return f"first on line {line}" if line else f"first is {_key_of(where)}"


def _check_named(items: tuple, i: int, cls: type, section: str, noun: str,
                 seen: dict[str, int]) -> None:
    """``items[i]`` is a ``cls`` with a valid kind and a name not used before in its
    section (``seen``: name -> index, updated)."""
    item = items[i]
    if not isinstance(item, cls):
        raise Invalid(f"must be a hapsim.scene.{cls.__name__}, got {type_name(item)}",
                      (section, i))
    check_key(_key(f"{section}[].kind"), item.kind, section, i, "kind")
    check_key(_key(f"{section}[].name"), item.name, section, i, "name")
    if item.name in seen:
        j = seen[item.name]
        raise Invalid(f"duplicate {noun} name {show(item.name)} "
                      f"({_first(items[j].line, (section, j))})", (section, i, "name"))
    seen[item.name] = i


def check_scene(s) -> None:
    """Every rule a scene obeys, whether it was read from YAML or built in code.

    The YAML reader checks only what the dataclasses cannot express (syntax, structure,
    unknown and missing keys); every value is checked here, once.

    Parameters
    ----------
    s : hapsim.scene.Scene
        The scene (its ``__post_init__`` calls this).

    Raises
    ------
    Invalid
        On the first broken rule, in scene order.
    """
    names, ports = _check_masses(s)
    if len(ports) > 1:
        raise Invalid(f"at most one port per scene (1-DoF device); found {len(ports)}: "
                       + ", ".join(bare_name(s.masses[p].name) for p in ports), ("masses", ports[1]),
                       key="masses")
    _check_links(s, names)
    if s.device is not None:
        check_device(s.device)
    elif ports:
        raise Invalid("a scene with a port needs a device section "
                       "(mass, friction, delay, hold, ...)", ("device",))
    _check_products(s)
    _check_excitation(s.excitation)
    _check_safety(s.safety)
    if s.audio is not None:
        _check_audio(s, names)


#: What a scene with several ports does not take yet, each with its reason (issue 30 item
#: 3, first slice: ports coupled through links to each other and to grounds).
PORTS_NOT_BUILT = {
    "mass": "virtual masses in a scene with several ports are not built yet: the ports "
            "couple through links to each other and to grounds",
    "contact": "contacts in a scene with several ports are not built yet: use a "
               "spring_damper",
    "target": "calibrating a felt target across several ports is not built yet: give "
              "stiffness and damping",
    "hold": "the n-D loop models the zero-order hold only: hold: zoh",
    "hand": "a hand model per port is not built yet",
    "correction": "a correction per port is not built yet",
}
#: Most ports one scene takes: the n-D loop (hapsim.analysis.ths.MatrixLoop) has at
#: most 3 axes.
MAX_PORTS = 3


def check_scene_ports(s) -> None:
    """Every rule of a scene with several ports (:class:`hapsim.scene.ScenePorts`).

    The rules of a one-port scene's masses, links and devices (each port's device is a
    ``device`` section, at ``devices.NAME``), with the loop's products at each port's
    device mass, and what this slice does not build refused with its reason
    (:data:`PORTS_NOT_BUILT`): 2 to :data:`MAX_PORTS` ports, each with a device and no
    device for another name, no virtual mass, no contact, no target, ``hold: zoh``, no
    hand or correction (each port its own delay, whole or sub-sample).

    Parameters
    ----------
    s : hapsim.scene.ScenePorts
        The scene (its ``__post_init__`` calls this).

    Raises
    ------
    Invalid
        On the first broken rule, in scene order.
    """
    names, ports = _check_masses(s)
    for i, m in enumerate(s.masses):
        if m.kind == "mass":
            raise Invalid(PORTS_NOT_BUILT["mass"], ("masses", i, "kind"))
    if not 2 <= len(ports) <= MAX_PORTS:
        raise Invalid(f"a scene with devices: takes 2 to {MAX_PORTS} ports (the n-D loop's "
                      f"axes), got {len(ports)}; one port is the device: section",
                      ("masses",), key="masses")
    _check_links(s, names)
    for i, lk in enumerate(s.links):
        if lk.kind == "contact":
            raise Invalid(PORTS_NOT_BUILT["contact"], ("links", i, "kind"))
        if lk.target is not None:
            raise Invalid(PORTS_NOT_BUILT["target"], ("links", i, "target"))
    if not (isinstance(s.devices, tuple) and all(
            isinstance(p, tuple) and len(p) == 2 and isinstance(p[0], str)
            for p in s.devices)):
        raise Invalid("must be pairs (port name, hapsim.scene.Device)", ("devices",))
    port_names = [s.masses[p].name for p in ports]
    given = [n for n, _ in s.devices]
    for n in given:
        if n not in port_names:
            raise Invalid(f"no port named {show(n)}; ports: {', '.join(port_names)}",
                          ("devices", n), key="devices")
    for n in port_names:
        if n not in given:
            raise Invalid(f"port {show(n)} has no device: give one under devices.{n}",
                          ("devices",), key="devices")
    for n, d in s.devices:
        try:
            check_device(d)
        except Invalid as bad:
            raise Invalid(bad.message, ("devices", n) + tuple(bad.where[1:])) from None
        for k in ("hand", "correction"):
            if getattr(d, k) is not None:
                raise Invalid(PORTS_NOT_BUILT[k], ("devices", n, k))
        if d.hold != "zoh":
            raise Invalid(PORTS_NOT_BUILT["hold"], ("devices", n, "hold"))
    _check_products(s)


def _check_masses(s) -> tuple[dict[str, int], list[int]]:
    """The rules of the rate, the integrator, the path and the masses; the masses' names
    (name -> index) and the ports' indices."""
    check_key(_key("rate_hz"), s.rate_hz, "rate_hz")
    check_key(_key("integrator"), s.integrator, "integrator")
    if not isinstance(s.path, str):
        raise Invalid(f"must be a string, got {type_name(s.path)}", ("path",))
    if not isinstance(s.masses, tuple) or not s.masses:
        raise Invalid("must be a non-empty list of masses", ("masses",))
    names: dict[str, int] = {}
    ports: list[int] = []
    for i, m in enumerate(s.masses):
        _check_named(s.masses, i, Mass, "masses", "mass", names)
        if m.kind == "mass":
            check_key(_key("masses[].mass"), m.mass, "masses", i, "mass")
        elif m.mass != 0:
            raise Invalid(f"must be 0 for a {m.kind} (only kind mass has inertia), "
                           f"got {show(m.mass)}", ("masses", i, "mass"))
        check_key(_key("masses[].x0"), m.x0, "masses", i, "x0")
        check_key(_key("masses[].v0"), m.v0, "masses", i, "v0")
        if m.kind != "mass" and m.v0 != 0:
            raise Invalid(f"must be 0 for a {m.kind} (it does not move by itself), "
                           f"got {show(m.v0)}", ("masses", i, "v0"))
        if m.kind == "port":
            ports.append(i)
    return names, ports


def _check_products(s) -> None:
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
            raise Invalid(exc.reason, where) from None

    inertia = {m.name: float(m.mass) for m in s.masses if m.kind == "mass"}
    port = next((m.name for m in s.masses if m.kind == "port"), None)
    # each port with its device, and the path of that device's section
    devices = (((n, d, ("devices", n)) for n, d in s.devices) if hasattr(s, "devices") else
               (((port, s.device, ("device",)),) if s.device is not None and port else ()))
    for port, d, at in devices:
        m_dev = float(d.mass)
        inertia[port] = m_dev
        refuse(d.friction, T / m_dev, "N s/m", "b0 T/m", (*at, "friction"))
        h = d.hand
        if h is not None:
            hi = lambda v: float(v[1]) if isinstance(v, tuple) else float(v)  # noqa: E731
            lo = lambda v: float(v[0]) if isinstance(v, tuple) else float(v)  # noqa: E731
            if hi(h.stiffness) > 0:
                refuse(hi(h.stiffness), T * T / lo(h.mass), "N/m", "kh T^2/m",
                       (*at, "hand", "stiffness"))
            refuse(hi(h.damping), T / lo(h.mass), "N s/m", "bh T/m",
                   (*at, "hand", "damping"))
            # the grip joins the hand and the handle: the lighter of the two moves most
            m_grip = min(lo(h.mass), m_dev)
            if math.isfinite(hi(h.grip_stiffness)):       # inf: a rigid grip
                refuse(hi(h.grip_stiffness), T * T / m_grip, "N/m", "kg T^2/m",
                       (*at, "hand", "grip_stiffness"))
            refuse(hi(h.grip_damping), T / m_grip, "N s/m", "bg T/m",
                   (*at, "hand", "grip_damping"))
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


def check_products_nd(r, T: float, masses, links, planes, device, dev_line,
                      friction_at=None) -> None:
    """The dimensionless products of a 2-D or 3-D scene's loop, the 1-D scene's rule
    (:func:`check_scene`'s, here on the reader's values as it builds them): ``|K| T^2/m``
    and ``|B| T/m`` of every link and plane, ``m`` its lightest moving end (a virtual mass, or the device's
    Cartesian mass along its lightest axis at the port), and the device's ``b0 T/m``
    (largest friction over the lightest mass axis): at most
    :data:`hapsim.scene_schema.MAX_PRODUCT`, whose reason is there (the state matrix's
    entries would span more than a double resolves; 1e308 overflowed it into inf or
    made LAPACK's SVD fail, issue 31).

    Parameters
    ----------
    r : hapsim.scene.lines.LineContext
        The file read (the refusal names it, the line and the key).
    T : float
        Sample period [s].
    masses, links, planes : sequence of MassND, LinkND, PlaneND
        As read (their ``line``).
    device : DeviceND or None
        The device (its Cartesian mass [kg] and friction [N s/m], shape (n, n)).
    dev_line : int or None
        Line of the ``device`` section.
    friction_at : (int or None, str), optional
        Line and key of the friction's input (a kinematic device's ``joint_friction``);
        default ``dev_line`` and ``device.friction``.

    Returns
    -------
    None
        Nothing: the scene's products pass, or the first beyond the bound is refused.

    Raises
    ------
    ConfigError
        The first product beyond the bound, with file, line and key.
    """
    inertia = {m.name: float(m.mass) for m in masses if m.kind == "mass"}
    if device is not None:
        def eigs(X):            # scaled to entries <= 1: eigvalsh fails near 1e308
            sx = max(float(np.max(np.abs(X))), np.finfo(float).tiny)
            return sx * np.linalg.eigvalsh(0.5 * (X / sx) + 0.5 * (X.T / sx))
        light = float(np.min(eigs(device.mass)))
        # the key the friction was given by: a kinematic device's joint_friction, mapped
        # to the Cartesian J^-T B_q J^-1 (before: keyed device.friction, a key not there)
        f_line, f_key = friction_at or (dev_line, "device.friction")
        if not np.all(np.isfinite(device.friction)):
            raise r.error("the device's friction is not finite", f_line, f_key)
        heavy_b0 = float(np.max(np.abs(eigs(device.friction))))
        if not (math.isfinite(light) and light > 0):
            raise r.error("the device's Cartesian mass is not positive definite here",
                          dev_line, "device")
        try:
            check_product(heavy_b0, T / light, "friction", "N s/m", "b0 T/m")
        except ConfigError as exc:
            raise r.error(exc.reason + (" (the Cartesian J^-T B_q J^-1 + hand_damping "
                                        "at these joints)" if f_key != "device.friction"
                                        else ""),
                          f_line, f_key) from None
        for m in masses:
            if m.kind == "port":
                inertia[m.name] = light
    # a Euclidean link at rest distance r with rest length (or threshold) L stiffens
    # across its axis by K |1 - L/r| (its linearisation,
    # hapsim.analysis.virtual_network.link_blocks): the product bounds that too (a length of
    # 1e308 overflowed the state matrix)
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


def _check_audio(s, names: dict[str, int]) -> None:
    a = s.audio
    if not isinstance(a, Audio):
        raise Invalid(f"must be a hapsim.scene.Audio, got {type_name(a)}", ("audio",))
    check_key(_key("audio.rate_hz"), a.rate_hz, "audio", "rate_hz")
    try:
        audio_substeps(a.rate_hz, s.rate_hz)
    except ValueError as exc:
        raise Invalid(str(exc), ("audio", "rate_hz")) from None
    if s.integrator != "centred":
        raise Invalid(f"audio runs the centred scheme only; got integrator "
                       f"{s.integrator!r}", ("integrator",))
    check_key(_key("audio.port_position"), a.port_position, "audio", "port_position")
    check_key(_key("audio.port_force"), a.port_force, "audio", "port_force")
    if not isinstance(a.listen, tuple) or not a.listen:
        raise Invalid("must be a non-empty list of listening points {mass, quantity, gain}",
                       ("audio", "listen"))
    for i, ls in enumerate(a.listen):
        if not isinstance(ls, Listen):
            raise Invalid(f"must be a hapsim.scene.Listen, got {type_name(ls)}",
                           ("audio", "listen", i))
        check_key(_key("audio.listen[].mass"), ls.mass, "audio", "listen", i, "mass")
        if ls.mass not in names:
            raise Invalid(f"no mass named {ls.mass!r}; masses are: "
                           + ", ".join(list(names)[:20]), ("audio", "listen", i, "mass"))
        check_key(_key("audio.listen[].quantity"), ls.quantity, "audio", "listen", i,
                   "quantity")
        check_key(_key("audio.listen[].gain"), ls.gain, "audio", "listen", i, "gain")
    if a.port_position != "hold" and s.port is not None:
        for i, lk in enumerate(s.links):
            if lk.target is not None:
                raise Invalid("a felt target is calibrated for the device-rate link; with "
                               "audio.port_position: linear the port link renders "
                               "differently: use port_position: hold, or give (K, B)",
                               ("links", i, "target"))


def _check_links(s, names: dict[str, int]) -> None:
    if not isinstance(s.links, tuple):
        raise Invalid(f"must be a list of links, got {type_name(s.links)}", ("links",))
    seen: dict[str, int] = {}
    for i, lk in enumerate(s.links):
        _check_named(s.links, i, Link, "links", "link", seen)
        for n in (lk.m1, lk.m2):
            if n not in names:
                shown = ", ".join(bare_name(k) for k in list(names)[:20])
                shown += ", ..." if len(names) > 20 else ""
                raise Invalid(f"no mass named {show(n)}; masses are: {shown}",
                               ("links", i, "between"))
        if lk.m1 == lk.m2:
            raise Invalid(f"a link cannot join mass {show(lk.m1)} to itself", ("links", i, "between"))
        if not isinstance(lk.calibrated, bool):
            raise Invalid(f"must be True or False, got {show(lk.calibrated)}",
                           ("links", i, "calibrated"))
        awaiting = False
        if lk.target is not None:
            ends = {s.masses[names[lk.m1]].kind, s.masses[names[lk.m2]].kind}
            if lk.kind != "spring_damper" or ends != {"port", "ground"}:
                raise Invalid("a felt target {k, b} can only be calibrated for a "
                               "spring_damper between the port and a ground",
                               ("links", i, "target"))
            if not (isinstance(lk.target, tuple) and len(lk.target) == 2):
                raise Invalid(f"must be a pair (k, b), got {show(lk.target)}", ("links", i, "target"))
            check_key(_key("links[].target.k"), lk.target[0], "links", i, "target", "k")
            check_key(_key("links[].target.b"), lk.target[1], "links", i, "target", "b")
            awaiting = not lk.calibrated
        # NaN (K, B) mean "awaiting calibration" for a target link, nothing else.
        if not (awaiting and _is_number(lk.stiffness) and math.isnan(lk.stiffness)):
            check_key(_key("links[].stiffness"), lk.stiffness, "links", i, "stiffness")
        if not (awaiting and _is_number(lk.damping) and math.isnan(lk.damping)):
            # A calibrated B may be negative: the device's real friction b0 can exceed the
            # felt damping (docs/design.md, 'The forward map'); a scene file or a hand-built
            # link may not.
            if lk.calibrated:
                _number(lk.damping, "links", i, "damping")
            else:
                check_key(_key("links[].damping"), lk.damping, "links", i, "damping")
        if lk.kind == "contact":
            check_key(_key("links[].threshold"), lk.threshold, "links", i, "threshold")
            if s.integrator == "exact":
                raise Invalid("the exact integrator takes linear links only; a contact "
                               "switches the network (use centred or symplectic_euler)",
                               ("links", i, "kind"))
        elif lk.threshold != 0:
            raise Invalid(f"only a contact has a threshold; must be 0 for a {lk.kind}, "
                           f"got {show(lk.threshold)}", ("links", i, "threshold"))


def check_device(d: Any) -> None:
    """The rules of a ``device`` section alone (a scene's, or a device file's).

    Parameters
    ----------
    d : Device
        The section: mass [kg], friction [N s/m], delay [periods, real], hold, force
        limit [N], hand, correction and the protocol's options.

    Raises
    ------
    Invalid
        Not a :class:`~hapsim.scene.Device`, a value out of its row's range, a fractional
        delay with the ideal hold, a hand or a
        correction the hold cannot render, or options the protocol's driver refuses.
    """
    if not isinstance(d, Device):
        raise Invalid(f"must be a hapsim.scene.Device, got {type_name(d)}", ("device",))
    _check_section(d, "device", "device")
    why = delay_fraction_refusal(d.delay)
    if why is not None:
        raise Invalid(why, ("device", "delay"))
    if d.hold != "zoh" and float(d.delay) % 1.0:
        raise Invalid(f"a delay of {num(float(d.delay))} periods switches the force inside "
                      "the period (the split hold): it needs hold: zoh; the 'ideal' hold "
                      "takes a whole delay", ("device", "delay"))
    if d.hand is not None:
        _check_hand(d.hand, d.hold)
    if d.correction is not None:
        _check_correction(d.correction, d.hold)
    if d.protocol_options is not None:
        _check_protocol_options(d.protocol_options, d.protocol)


def delay_fraction_refusal(delay) -> str | None:
    """Why a delay's fraction of a period is refused, or None
    (:data:`hapsim.scene_schema.MIN_DELAY_FRACTION`).

    Parameters
    ----------
    delay : float
        [periods], finite and >= 0 (its range checked already).

    Returns
    -------
    str or None
    """
    d = float(delay)
    f = d - math.floor(d)
    if 0.0 < f < MIN_DELAY_FRACTION or 0.0 < 1.0 - f < MIN_DELAY_FRACTION:
        whole = round(d)
        return (f"a delay of {d!r} periods is {min(f, 1.0 - f):.3g} of a period from "
                f"the whole {whole}: no clock resolves it; give {whole}, or a fraction of at "
                f"least {MIN_DELAY_FRACTION:g} of a period")
    return None


def _check_protocol_options(o: Any, protocol: str) -> None:
    """A driver's parameters: a mapping its constructor accepts (unknown keys and bad
    values named with the valid choices)."""
    where = ("device", "protocol_options")
    if not isinstance(o, dict):
        raise Invalid(f"must be a mapping, got {type_name(o)} {show(o)}", where)
    import inspect

    from hapsim.drivers import family, get_driver
    from hapsim.errors import ConfigError
    cls = family(protocol).load()           # the registry's driver class
    if cls is None:
        raise Invalid("the framed protocol takes no options (its device says its own "
                       "units in HELLO); set device.protocol to a driver", where)
    valid = tuple(n for n in inspect.signature(cls.__init__).parameters if n != "self")
    for name in o:
        if name not in valid:
            raise Invalid(f"unknown option {show(name)} for {protocol}; valid: "
                           f"{', '.join(valid)}", (*where, name))
    try:
        get_driver(protocol, **o)
    except ConfigError as exc:
        raise Invalid(exc.reason, (*where, exc.key) if exc.key else where) from None
    except (TypeError, ValueError) as exc:
        raise Invalid(str(exc), where) from None


def _check_hand(h: Any, hold: str) -> None:
    if not isinstance(h, Hand):
        raise Invalid(f"must be a hapsim.scene.Hand, got {type_name(h)}", ("device", "hand"))
    for key, positive, inf in (("mass", True, False), ("damping", False, False),
                               ("grip_stiffness", True, True), ("grip_damping", False, False),
                               ("stiffness", False, False)):
        v = getattr(h, key)
        where = ("device", "hand", key)
        if isinstance(v, tuple):
            if len(v) != 2:
                raise Invalid(f"a range is [lo, hi], got {list(v)!r}", where)
            for x in v:
                _number(x, *where, positive=positive, minimum=None if positive else 0.0)
            if not v[0] <= v[1]:
                raise Invalid(f"a range [lo, hi] needs lo <= hi, got {list(v)!r}", where)
        else:
            _number(v, *where, positive=positive, minimum=None if positive else 0.0,
                    allow_inf=inf)
    if not h.rigid and hold != "zoh":
        raise Invalid("a compliant grip needs hold: zoh (the ideal hold models one mass); "
                       "use grip_stiffness: rigid", ("device", "hand", "grip_stiffness"))


def _check_correction(c: Any, hold: str) -> None:
    where = ("device", "correction")
    if not isinstance(c, dict) or "kind" not in c:
        raise Invalid("must be a mapping with a kind; valid kinds: "
                       + ", ".join(CORRECTIONS), where)
    check_choice(c["kind"], tuple(CORRECTIONS), *where, "kind")
    allowed = ("kind",) + CORRECTIONS[c["kind"]]
    for k, v in c.items():
        if k not in allowed:
            raise Invalid(f"unknown key {k!r} for {c['kind']}; valid keys: "
                           + ", ".join(allowed), where + (k,))
        if k != "kind":
            _number(v, *where, k, minimum=0.0)
    if c["kind"] == "velocity_filter":
        if "cutoff_hz" not in c:
            raise Invalid("velocity_filter needs cutoff_hz [Hz]", where + ("cutoff_hz",))
        _number(c["cutoff_hz"], *where, "cutoff_hz", positive=True)
    if c["kind"] == "velocity_sensor" and hold != "zoh":
        raise Invalid("a velocity sensor needs hold: zoh (the ideal hold has no velocity)",
                       where + ("kind",))


def _check_excitation(e: Any) -> None:
    if not isinstance(e, Excitation):
        raise Invalid(f"must be a hapsim.scene.Excitation, got {type_name(e)}", ("excitation",))
    if e.impulse is not None and not isinstance(e.impulse, Impulse):
        raise Invalid(f"must be a hapsim.scene.Impulse, got {type_name(e.impulse)}",
                       ("excitation", "impulse"))
    _check_section(e, "excitation", "excitation")
    if e.impulse is not None:
        _check_section(e.impulse, "excitation.impulse", "excitation", "impulse")
    if e.profile is not None:
        if not os.path.exists(e.profile):
            raise Invalid(f"profile file not found: {e.profile}", ("excitation", "profile"))


def _check_safety(f: Any) -> None:
    if not isinstance(f, Safety):
        raise Invalid(f"must be a hapsim.scene.Safety, got {type_name(f)}", ("safety",))
    _check_section(f, "safety", "safety")


def code_line(s, where: tuple) -> int | None:
    """Line of the Mass or Link entry ``where`` points into.

    Parameters
    ----------
    s : hapsim.scene.Scene
        The scene (its masses and links carry the line they were read from, 0 in code).
    where : tuple
        Path of a value (``("links", 1, "stiffness")``).

    Returns
    -------
    int or None
        The entry's line, None when unknown (a scene built in code, another section).
    """
    if len(where) >= 2 and where[0] in ("masses", "links") and isinstance(where[1], int):
        seq = getattr(s, where[0])
        if isinstance(seq, tuple) and 0 <= where[1] < len(seq):
            return getattr(seq[where[1]], "line", 0) or None
    return None


def bare_name(k: Any) -> str:
    """A name as a message prints it: bare when short and plain, else :func:`show`-n.

    Parameters
    ----------
    k : object
        A key or a name read from a file.

    Returns
    -------
    str
        ``k`` itself for a printable string of 1 to 40 characters without spaces, else its
        quoted, shortened :func:`hapsim.errors.show`.
    """
    plain = isinstance(k, str) and k.isprintable() and 0 < len(k) <= 40 and " " not in k
    return k if plain else show(k, 40)
