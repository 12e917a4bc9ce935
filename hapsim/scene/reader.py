"""Reading scene files: YAML with line numbers (:mod:`hapsim._yaml_lines`) into the
dataclasses, refusing what only a file can get wrong (syntax, structure, unknown and
missing keys) with the file, the line and the key; the values are then checked by the
rules every :class:`~hapsim.scene.Scene` meets, and a broken one is named at its line.

A 2-D or 3-D scene file (``dimension: 2`` or ``3``; :func:`scene_dimension` tells which a
file is) is read by :func:`load_scene_nd` and :func:`parse_scene_nd` into a
:class:`~hapsim.scene.SceneND`, every value checked as it is read (its device by
:mod:`hapsim.scene.devices`, its loop's products by
:func:`hapsim.scene.rules.check_products_nd`)."""

from __future__ import annotations

import math
import os
from typing import Callable

import numpy as np

from hapsim._yaml_lines import LDict, load_yaml
from hapsim.errors import ConfigError, show, type_name
from hapsim.scene_schema import (LINK_KINDS, MASS_KINDS, MASS_RANGE, MAX_DELAY, RATE_RANGE,
                                 key_names, section_keys)
from hapsim.scene_schema import key as _key
from hapsim.scene.devices import nd_key_without_dimension, read_device_nd
from hapsim.scene.elements import (Audio, Device, Excitation, ExcitationND, Hand, Impulse, Link,
                                   LinkND, Listen, ListenND, Mass, MassND, PlaneND, Safety,
                                   SafetyND)
from hapsim.scene.lines import LineContext, read_text
from hapsim.scene.model import Scene, SceneND, ScenePorts
from hapsim.scene.rules import Invalid, check_key, check_products_nd, coerce

__all__ = ["load_scene", "parse_scene", "read_device", "scene_dimension", "scene_protocol",
           "load_scene_nd",
           "load_scene_ports", "parse_scene_ports", "scene_has_ports", "PORTS_REFUSAL",
           "PORTS_TOP_KEYS",
           "parse_scene_nd", "TOP_KEYS_ND", "MASS_KEYS_ND", "LINK_KEYS_ND", "PLANE_KEYS_ND",
           "EXCITATION_KEYS_ND", "IMPULSE_KEYS_ND", "LISTEN_KEYS_ND", "ENGINE_KEYS_ND",
           "PRECISIONS_ND", "SAFETY_KEYS_ND"]

# Valid keys, defaults, types and ranges: one table, hapsim.scene_schema (docs/scenes.md is
# written from it by hapsim.scene_doc). Add a key there, not here.
_TOP_KEYS = key_names("")
_LINK_KEYS = {kind: key_names("links[]", kind) for kind in LINK_KINDS}
_TARGET_KEYS = key_names("links[].target")
_HAND_KEYS = ("mass", "damping", "grip_stiffness", "grip_damping", "stiffness")

#: The keys of a 2-D or 3-D scene file, by section (the 1-D format's are
#: :data:`hapsim.scene_schema.KEYS`; docs/dimensions.md lists both).
TOP_KEYS_ND = ("dimension", "rate_hz", "integrator", "masses", "links", "planes", "device",
            "excitation", "audio", "engine", "safety")
EXCITATION_KEYS_ND = ("direction", "impulse", "profile")
IMPULSE_KEYS_ND = ("force", "start", "duration")
ENGINE_KEYS_ND = ("precision",)
SAFETY_KEYS_ND = ("brake",)
PRECISIONS_ND = ("double", "single")
LISTEN_KEYS_ND = ("mass", "axis", "quantity", "gain")
AXES_ND = ("x", "y", "z")
MASS_KEYS_ND = {"mass": ("name", "kind", "mass", "x0", "v0"),
             "ground": ("name", "kind", "x0"), "port": ("name", "kind")}
LINK_KEYS_ND = {"spring_damper": ("name", "kind", "between", "stiffness", "damping", "length"),
             "contact": ("name", "kind", "between", "stiffness", "damping", "threshold")}
PLANE_KEYS_ND = ("name", "normal", "offset", "stiffness", "damping", "masses")


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
    text = read_text(path)
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

    ctx = LineContext(path)
    if doc is None:
        raise ctx.error("the scene is empty; it needs at least rate_hz and masses", 1, "rate_hz")
    doc = ctx.mapping(doc, "", 1)
    # the dimension first: a 2-D or 3-D scene's own keys (planes, ...) are not this
    # reader's, and 'unknown key planes' would hide why
    if "dimension" in doc:
        try:
            check_key(_key("dimension"), doc["dimension"], "dimension")
        except Invalid as bad:
            raise ctx.error(bad.message, ctx.line_of(doc, "dimension"), "dimension") from None
        if doc["dimension"] != 1:
            raise ctx.error(f"a {doc['dimension']}-D scene: the 1-D reader "
                            "(hapsim.scene.load_scene) takes dimension 1; hapsim.load_scene "
                            "reads every dimension, as `hapsim check`, `simulate`, `run`, "
                            "`play` and `mock` do",
                            ctx.line_of(doc, "dimension"), "dimension")
    if "devices" in doc:
        raise ctx.error(PORTS_REFUSAL, ctx.line_of(doc, "devices"), "devices")
    nd = None if "dimension" in doc else nd_key_without_dimension(
        doc, _TOP_KEYS, key_names("device"), TOP_KEYS_ND)
    if nd is not None:
        raise ctx.error("a 2-D or 3-D scene's key, and a scene without `dimension` is 1-D: "
                        "add dimension: 2 (or 3)", ctx.line_of(nd[1], nd[2]), nd[0])
    ctx.keys(doc, _TOP_KEYS, "", required=tuple(k.name for k in section_keys("") if k.required))
    masses = _read_masses(ctx, doc)
    links = _read_links(ctx, doc, masses)
    device = read_device(ctx, doc) if "device" in doc else None
    excitation = _read_excitation(ctx, doc, path) if "excitation" in doc else Excitation()
    safety = _read_safety(ctx, doc) if "safety" in doc else Safety()
    audio = _read_audio(ctx, doc) if "audio" in doc else None
    return _built(ctx, doc, lambda: Scene(
        rate_hz=coerce(doc["rate_hz"]), masses=tuple(masses), links=tuple(links),
        device=device, excitation=excitation, path=path,
        integrator=doc.get("integrator", _key("integrator").default), safety=safety,
        audio=audio))


def _built(ctx: LineContext, doc: LDict, make: Callable):
    """``make()``, a scene checked as it is built; a broken rule named at the line of its
    key in the document (the entry's line is all the scene itself knows)."""
    try:
        return make()
    except ConfigError as exc:
        where = getattr(exc, "scene_where", None)
        if where is None:
            raise
        raise ConfigError(exc.reason, file=ctx.path, line=ctx.doc_line(doc, where),
                          key=exc.key) from None


#: What the one-port reader, and every command that takes it, says of a scene with
#: several ports (``devices:``).
PORTS_REFUSAL = ("a scene with several ports (devices:, one device per port): this takes one "
                 "port (a device: section); 'hapsim check', 'hapsim simulate', 'hapsim run' "
                 "(in lockstep, or the FireFader's two faders in real time) and 'hapsim "
                 "mock' (the two faders' board) take several (docs/ports.md)")
#: The top-level keys of a scene with several ports.
PORTS_TOP_KEYS = ("rate_hz", "integrator", "masses", "links", "devices")
#: Top-level keys of a one-port scene a scene with several ports refuses, and why.
_PORTS_REFUSED = {
    "device": "give every port's device under devices: (one device: section is a one-port "
              "scene), not both",
    "excitation": "an excitation of several ports is not built yet ('hapsim run --lockstep' "
                  "excites each port in turn; 'hapsim simulate SCENE --x0 PORT=M --v0 "
                  "PORT=M/S' starts a port displaced or moving)",
    "audio": "the sound of a scene with several ports is not built yet",
    "safety": "the safety limits of a run on several ports are not built yet (its real-time "
              "run is not built)",
    "dimension": "several ports move along one axis each: a scene with devices: is 1-D",
}


def scene_has_ports(path: str | os.PathLike) -> bool:
    """Whether a scene file has several ports (a top-level ``devices`` key), read cheaply.

    Parameters
    ----------
    path : str or path-like
        Scene file.

    Returns
    -------
    bool
        True when its top mapping holds ``devices`` (:func:`load_scene_ports` reads it);
        False otherwise, or when the file cannot be read or parsed (the reader that reads
        it then says why).
    """
    return "devices" in _top_keys(path, "devices")


def load_scene_ports(path: str | os.PathLike) -> ScenePorts:
    """Read and validate a scene file with several ports (:func:`parse_scene_ports`).

    Parameters
    ----------
    path : str or path-like
        YAML scene with a ``devices:`` section.

    Returns
    -------
    ScenePorts

    Raises
    ------
    ConfigError
        As :func:`parse_scene_ports`, or an unreadable file.
    """
    path = os.fspath(path)
    return parse_scene_ports(read_text(path), path)


def parse_scene_ports(text: str, path: str = "<string>") -> ScenePorts:
    """Parse and validate a scene with several ports, each with its own device.

    The one-port format (docs/scenes.md) with ``devices:`` instead of ``device:``: a
    mapping from each port's name to a ``device`` section of the one-port format (mass,
    friction, delay, protocol, ...); the scene's ``rate_hz`` drives every port.

    Parameters
    ----------
    text : str
        YAML text.
    path : str
        Name used in messages.

    Returns
    -------
    ScenePorts

    Raises
    ------
    ConfigError
        The one-port reader's errors (file, line, key, the valid keys or choices); a
        top-level key this format does not take, with its reason; a ``rate_hz`` in a
        device (several rates: not built); a broken rule of
        :func:`hapsim.scene.rules.check_scene_ports`.
    """
    doc = load_yaml(text, path)
    ctx = LineContext(path)
    if doc is None:
        raise ctx.error("the scene is empty", 1, "devices")
    doc = ctx.mapping(doc, "", 1)
    for k, why in _PORTS_REFUSED.items():
        if k in doc:
            raise ctx.error(why, ctx.line_of(doc, k), k)
    ctx.keys(doc, PORTS_TOP_KEYS, "", required=("rate_hz", "masses", "devices"))
    masses = _read_masses(ctx, doc)
    links = _read_links(ctx, doc, masses)
    devs = ctx.mapping(doc["devices"], "devices", ctx.line_of(doc, "devices"))
    devices = []
    for name in devs:
        key = f"devices.{name}"
        block = ctx.mapping(devs[name], key, ctx.line_of(devs, name))
        if "rate_hz" in block:
            raise ctx.error("a rate per port: multi-rate ports are not built; the scene's "
                            "rate_hz drives every port", ctx.line_of(block, "rate_hz"),
                            f"{key}.rate_hz")
        devices.append((name, read_device(ctx, devs, key)))
    return _built(ctx, doc, lambda: ScenePorts(
        rate_hz=coerce(doc["rate_hz"]), masses=tuple(masses), links=tuple(links),
        devices=tuple(devices), path=path,
        integrator=doc.get("integrator", _key("integrator").default)))


def _read_values(ctx: LineContext, d: LDict, section: str, key: str,
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
        out[k.name] = coerce(v) if k.type == "number" else v
    return out


def _read_masses(ctx: LineContext, doc: LDict) -> list[Mass]:
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


def _read_links(ctx: LineContext, doc: LDict, masses: list[Mass]) -> list[Link]:
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
        stiffness = coerce(d.get("stiffness", _key("links[].stiffness").default))
        damping = coerce(d.get("damping", _key("links[].damping").default))
        if "target" in d:
            if "stiffness" in d or "damping" in d:
                raise ctx.error("give either target {k, b} or stiffness/damping, not both",
                                ctx.line_of(d, "target"), f"{key}.target")
            t = ctx.mapping(d["target"], f"{key}.target", ctx.line_of(d, "target"))
            ctx.keys(t, _TARGET_KEYS, f"{key}.target", required=_TARGET_KEYS)
            target = (coerce(t["k"]), coerce(t["b"]))
            stiffness = damping = math.nan
        elif "stiffness" not in d and "damping" not in d:
            raise ctx.error("a link needs stiffness and/or damping (or a target)",
                            d.line, f"{key}.stiffness")
        out.append(Link(d.get("name", f"link{i}"), kind, between[0], between[1], stiffness,
                        damping, coerce(d.get("threshold", _key("links[].threshold").default)),
                        target, line=d.line))
    return out


def read_device(ctx: LineContext, doc: LDict, key: str = "device") -> Device:
    """The ``device`` section of a document (a scene or a device file).

    Parameters
    ----------
    ctx : LineContext
        The file read.
    doc : LDict
        The mapping holding the section (a document's top mapping, holding ``device``).
    key : str, optional
        The section's path in messages: ``device``, or ``devices.NAME`` (the mapping's
        key is its last part).

    Returns
    -------
    Device
        Read with the table's defaults; its values are checked by
        :func:`hapsim.scene.rules.check_device` (a scene's, when the scene is built).

    Raises
    ------
    ConfigError
        A section that is not a mapping, an unknown or missing key, ``null`` where a value
        is needed (file, line and key named).
    """
    last = key.rsplit(".", 1)[-1]
    d = ctx.mapping(doc[last], key, ctx.line_of(doc, last))
    vals = _read_values(ctx, d, "device", key)
    if isinstance(vals["delay"], float) and vals["delay"].is_integer():
        vals["delay"] = int(vals["delay"])   # a whole delay: the plain hold's int, as before
    vals["hand"] = _read_hand(ctx, d, key) if "hand" in d else None
    vals["correction"] = (dict(ctx.mapping(d["correction"], f"{key}.correction",
                                           ctx.line_of(d, "correction")))
                          if "correction" in d else None)
    vals["protocol_options"] = (dict(ctx.mapping(d["protocol_options"],
                                                 f"{key}.protocol_options",
                                                 ctx.line_of(d, "protocol_options")))
                                if "protocol_options" in d else None)
    return Device(**vals)


def _read_hand(ctx: LineContext, dev: LDict, key: str = "device") -> Hand:
    h = ctx.mapping(dev["hand"], f"{key}.hand", ctx.line_of(dev, "hand"))
    ctx.keys(h, _HAND_KEYS, f"{key}.hand", required=("mass",))

    def val(key, default):
        v = h.get(key, default)
        if key == "grip_stiffness" and v == "rigid":
            return math.inf
        if isinstance(v, list):
            return tuple(coerce(x) for x in v)
        return coerce(v)
    return Hand(val("mass", None), val("damping", 0.0), val("grip_stiffness", math.inf),
                val("grip_damping", 0.0), val("stiffness", 0.0))


def _read_excitation(ctx: LineContext, doc: LDict, path: str) -> Excitation:
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


def _read_safety(ctx: LineContext, doc: LDict) -> Safety:
    d = ctx.mapping(doc["safety"], "safety", ctx.line_of(doc, "safety"))
    return Safety(**_read_values(ctx, d, "safety", "safety"))


def _read_audio(ctx: LineContext, doc: LDict) -> Audio:
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
    d = _top_keys(path, "dimension").get("dimension")
    return d if d in (2, 3) and not isinstance(d, bool) else 1


def scene_protocol(path: str | os.PathLike) -> str | None:
    """The ``device.protocol`` a scene file names, read cheaply (as :func:`scene_dimension`).

    Parameters
    ----------
    path : str or path-like
        Scene file.

    Returns
    -------
    str or None
        The value when it is a string, else None (the reader then reads the file and
        reports any problem with it).
    """
    dev = _top_keys(path, "protocol").get("device")
    proto = dev.get("protocol") if isinstance(dev, dict) else None
    return proto if isinstance(proto, str) else None


def _top_keys(path: str | os.PathLike, word: str) -> dict:
    """The top mapping of the scene file, cheaply: empty when the file cannot be read or
    parsed (the reader that reads it then says why) or its text lacks ``word``."""
    try:
        text = read_text(path)
    except ConfigError:
        return {}
    if word not in text:
        return {}
    got = _TOPS.get(text)
    if got is not None:
        return got
    try:
        doc = load_yaml(text, os.fspath(path))
    except ConfigError:
        doc = None
    got = doc if isinstance(doc, dict) else {}
    if len(_TOPS) >= 16:               # a few texts: a command asks two or three times
        _TOPS.clear()
    _TOPS[text] = got
    return got


#: :func:`_top_keys`'s answers by the file's text: a command of an n-D scene asked its
#: dimension two or three times (``check`` in the command and again in
#: ``api.load_scene``), and each time parsed the whole file (a membrane's ~14 ms); the
#: same text, the same answer.
_TOPS: dict = {}


def load_scene_nd(path: str | os.PathLike) -> SceneND:
    """Read and validate a 2-D or 3-D scene file.

    Parameters
    ----------
    path : str or path-like
        YAML scene file (format: :mod:`hapsim.scene`, 'Format in two and three
        dimensions').

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
    """Parse and validate n-D scene text (format: :mod:`hapsim.scene`).

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
    r = LineContext(path)
    doc = load_yaml(text, path)
    if doc is None:
        raise r.error("the scene is empty", 1, "dimension")
    doc = r.mapping(doc, "", 1)
    r.keys(doc, TOP_KEYS_ND, "", required=("dimension", "rate_hz", "masses"))
    n = r.integer(doc, "dimension", "", default=1, minimum=1, maximum=3,
                  unit="dimensions")
    if n == 1:
        raise r.error("a 1-D scene is the 1-D format (hapsim.scene, docs/scenes.md): "
                      "this reader takes dimension 2 or 3", r.line_of(doc, "dimension"),
                      "dimension")
    rate = r.number(doc, "rate_hz", "", minimum=0.0, strict=True, unit="Hz")
    if not RATE_RANGE[0] <= rate <= RATE_RANGE[1]:
        raise r.error(f"must be between {RATE_RANGE[0]:g} and {RATE_RANGE[1]:g} Hz, got "
                      f"{rate:g}", r.line_of(doc, "rate_hz"), "rate_hz")
    r.choice(doc, "integrator", "", ("centred",), default="centred")

    # masses
    seq = doc["masses"]
    if not isinstance(seq, list) or not seq:
        raise r.error("must be a non-empty list of masses", r.line_of(doc, "masses"), "masses")
    masses, names = [], {}
    for i, item in enumerate(seq):
        key = f"masses[{i}]"
        d = r.mapping(item, key, r.line_of(seq, i))
        kind = r.choice(d, "kind", key, ("mass", "ground", "port"))
        r.keys(d, MASS_KEYS_ND[kind], key, required=("name",) + (("mass",) if kind == "mass"
                                                              else ()))
        name = r.string(d, "name", key)
        if name in names:
            raise r.error(f"duplicate mass name {show(name)} (first on line "
                          f"{names[name]})", r.line_of(d, "name"), f"{key}.name")
        names[name] = r.line_of(d)
        m = 0.0
        if kind == "mass":
            m = r.number(d, "mass", key, minimum=0.0, strict=True, unit="kg")
            if not MASS_RANGE[0] <= m <= MASS_RANGE[1]:
                raise r.error(f"must be between {MASS_RANGE[0]:g} and {MASS_RANGE[1]:g} kg,"
                              f" got {m:g}", r.line_of(d, "mass"), f"{key}.mass")
        masses.append(MassND(name, kind, m, r.vector(d, "x0", key, n),
                             r.vector(d, "v0", key, n, unit="m/s"), line=r.line_of(d)))
    ports = [m for m in masses if m.kind == "port"]
    if len(ports) > 1:
        raise r.error(f"at most one mass of kind 'port', got {len(ports)} (first on line "
                      f"{ports[0].line})", ports[1].line, "masses")

    # links
    links, lnames = [], {}
    lseq = [] if doc.get("links") is None else doc["links"]     # (0 or "" was read as none)
    if not isinstance(lseq, list):
        raise r.error(f"must be a list of links, got {type_name(lseq)}",
                      r.line_of(doc, "links"), "links")
    for i, item in enumerate(lseq):
        key = f"links[{i}]"
        d = r.mapping(item, key, r.line_of(lseq, i))
        kind = r.choice(d, "kind", key, tuple(LINK_KEYS_ND))
        r.keys(d, LINK_KEYS_ND[kind], key, required=("between",) + (
            ("threshold",) if kind == "contact" else ()))
        name = r.string(d, "name", key, default=f"link{i}")
        if name in lnames:
            raise r.error(f"duplicate link name {show(name)} (first on line "
                          f"{lnames[name]})", r.line_of(d, "name"), f"{key}.name")
        lnames[name] = r.line_of(d)
        between = d["between"]
        if not (isinstance(between, list) and len(between) == 2
                and all(isinstance(x, str) for x in between)):
            raise r.error("must be a list of two mass names, e.g. [hand, wall]",
                          r.line_of(d, "between"), f"{key}.between")
        for x in between:
            if x not in names:
                raise r.error(f"no mass named {show(x)}; masses: {', '.join(names)}",
                              r.line_of(d, "between"), f"{key}.between")
        if between[0] == between[1]:
            raise r.error("a link joins two different masses", r.line_of(d, "between"),
                          f"{key}.between")
        if "stiffness" not in d and "damping" not in d:
            raise r.error("a link needs stiffness and/or damping", r.line_of(d),
                          f"{key}.stiffness")
        K = r.number(d, "stiffness", key, default=0.0, minimum=0.0, unit="N/m")
        B = r.number(d, "damping", key, default=0.0, minimum=0.0, unit="N s/m")
        length = r.number(d, "length", key, default=0.0, minimum=0.0, unit="m")
        threshold = r.number(d, "threshold", key, default=0.0, minimum=0.0, strict=True,
                             unit="m") if kind == "contact" else 0.0
        links.append(LinkND(name, kind, between[0], between[1], K, B, length, threshold,
                            line=r.line_of(d)))

    # planes
    planes, pnames = [], {}
    pseq = [] if doc.get("planes") is None else doc["planes"]     # (0 or "" was read as none)
    if not isinstance(pseq, list):
        raise r.error(f"must be a list of planes, got {type_name(pseq)}",
                      r.line_of(doc, "planes"), "planes")
    moving = tuple(m.name for m in masses if m.kind != "ground")
    for i, item in enumerate(pseq):
        key = f"planes[{i}]"
        d = r.mapping(item, key, r.line_of(pseq, i))
        r.keys(d, PLANE_KEYS_ND, key, required=("normal",))
        name = r.string(d, "name", key, default=f"plane{i}")
        if name in pnames or name in lnames:
            raise r.error(f"duplicate name {show(name)} (links and planes share names)",
                          r.line_of(d, "name"), f"{key}.name")
        pnames[name] = r.line_of(d)
        normal = r.vector(d, "normal", key, n, unit="-")
        if not np.linalg.norm(normal) > 0:
            raise r.error("must be a non-zero vector (the plane's outward normal)",
                          r.line_of(d, "normal"), f"{key}.normal")
        if "stiffness" not in d and "damping" not in d:
            raise r.error("a plane needs stiffness and/or damping", r.line_of(d),
                          f"{key}.stiffness")
        on = d.get("masses", list(moving))
        if not isinstance(on, list) or not on or not all(isinstance(x, str) for x in on):
            raise r.error("must be a non-empty list of mass names", r.line_of(d, "masses"),
                          f"{key}.masses")
        for x in on:
            if x not in names or x not in moving:
                raise r.error(f"must name moving masses or the port; valid: "
                              f"{', '.join(moving)}; got {show(x)}", r.line_of(d, "masses"),
                              f"{key}.masses")
        planes.append(PlaneND(name, normal / np.linalg.norm(normal),
                              r.number(d, "offset", key, default=0.0, unit="m"),
                              r.number(d, "stiffness", key, default=0.0, minimum=0.0,
                                       unit="N/m"),
                              r.number(d, "damping", key, default=0.0, minimum=0.0,
                                       unit="N s/m"),
                              tuple(on), line=r.line_of(d)))

    # device
    device = None
    if "device" in doc:
        device = read_device_nd(r, doc, n, MAX_DELAY)
    elif ports:
        raise r.error("a scene with a port needs a device section", ports[0].line,
                      "device")
    if ports and device is not None:
        masses = [MassND(m.name, m.kind, m.mass, device.position.copy(), m.v0, m.line)
                  if m.kind == "port" else m for m in masses]
    dd = doc.get("device") if isinstance(doc.get("device"), dict) else {}
    check_products_nd(r, 1.0 / rate, masses, links, planes, device,
                      r.line_of(doc, "device") if "device" in doc else None,
                      next(((r.line_of(dd, k), f"device.{k}") for k in ("joint_friction",
                                                                         "friction")
                           if k in dd), None))
    audio = _read_audio_nd(r, doc, n, names) if "audio" in doc else None
    excitation = None
    if "excitation" in doc:
        if not ports:
            raise r.error("an excitation is the hand's force on the device: the scene needs "
                          "a port and a device", r.line_of(doc, "excitation"), "excitation")
        excitation = _read_excitation_nd(r, doc, n, path)
    precision = "double"
    if "engine" in doc:
        e = r.mapping(doc["engine"], "engine", r.line_of(doc, "engine"))
        r.keys(e, ENGINE_KEYS_ND, "engine")
        precision = r.choice(e, "precision", "engine", PRECISIONS_ND, default="double")
        if precision == "single" and ports:
            raise r.error("single precision is for scenes without a port: a felt scene "
                          "runs the double-precision engine (exact to round-off)",
                          r.line_of(e, "precision"), "engine.precision")
    safety = SafetyND()
    if "safety" in doc:
        sd = r.mapping(doc["safety"], "safety", r.line_of(doc, "safety"))
        r.keys(sd, SAFETY_KEYS_ND, "safety")
        brake = sd.get("brake", True)
        if not isinstance(brake, bool):
            raise r.error(f"must be true or false, got {brake!r}", r.line_of(sd, "brake"),
                          "safety.brake")
        safety = SafetyND(brake=brake)
    return SceneND(dimension=n, rate_hz=rate, masses=tuple(masses), links=tuple(links),
                   planes=tuple(planes), device=device, path=path, audio=audio,
                   excitation=excitation, precision=precision, safety=safety)


def _read_excitation_nd(r: LineContext, doc, n: int, path: str) -> ExcitationND:
    """The ``excitation: {direction, impulse, profile}`` section (:mod:`hapsim.scene`)."""
    key = "excitation"
    d = r.mapping(doc[key], key, r.line_of(doc, key))
    r.keys(d, EXCITATION_KEYS_ND, key, required=("direction",))
    if "impulse" not in d and "profile" not in d:
        raise r.error("needs an impulse ({force, start, duration}) or a profile (a file of "
                      "time [s], force [N])", r.line_of(d), f"{key}.impulse")
    e = r.vector(d, "direction", key, n, unit="-")
    norm = float(np.linalg.norm(e))
    if not norm > 0:
        raise r.error("must be a non-zero vector (the direction of the hand's force)",
                      r.line_of(d, "direction"), f"{key}.direction")
    impulse = None
    if "impulse" in d:
        ik = f"{key}.impulse"
        i = r.mapping(d["impulse"], ik, r.line_of(d, "impulse"))
        r.keys(i, IMPULSE_KEYS_ND, ik, required=("force",))
        impulse = Impulse(force=r.number(i, "force", ik, unit="N"),
                          start=r.number(i, "start", ik, default=0.0, minimum=0.0, unit="s"),
                          duration=r.number(i, "duration", ik, default=0.0, minimum=0.0,
                                            unit="s"))
    profile = r.string(d, "profile", key)
    if profile is not None and not os.path.isabs(profile) and path != "<string>":
        profile = os.path.join(os.path.dirname(os.path.abspath(path)), profile)
    return ExcitationND(e / norm, impulse, profile, line=r.line_of(d))


def _read_audio_nd(r: LineContext, doc, n: int, names) -> tuple:
    """The ``audio: {listen: [...]}`` section: a tuple of :class:`ListenND`."""
    d = r.mapping(doc["audio"], "audio", r.line_of(doc, "audio"))
    r.keys(d, ("listen",), "audio", required=("listen",))
    seq = d["listen"]
    if not isinstance(seq, list) or not seq:
        raise r.error("must be a non-empty list of listening points, e.g. "
                      "[{mass: m1, axis: z, quantity: velocity, gain: 10}]",
                      r.line_of(d, "listen"), "audio.listen")
    out = []
    axes = AXES_ND[:n]
    for i, item in enumerate(seq):
        key = f"audio.listen[{i}]"
        e = r.mapping(item, key, r.line_of(seq, i))
        r.keys(e, LISTEN_KEYS_ND, key, required=("mass",))
        mass = r.string(e, "mass", key)
        if mass not in names:
            raise r.error(f"no mass named {show(mass)}; masses: {', '.join(names)}",
                          r.line_of(e, "mass"), f"{key}.mass")
        ax = e.get("axis", axes[-1])
        if isinstance(ax, bool) or not (ax in axes or (isinstance(ax, int)
                                                        and 0 <= ax < n)):
            raise r.error(f"must be one of {', '.join(axes)} or 0..{n - 1}, got {show(ax)}",
                          r.line_of(e, "axis"), f"{key}.axis")
        ax = axes.index(ax) if isinstance(ax, str) else int(ax)
        q = r.choice(e, "quantity", key, ("position", "velocity"), default="velocity")
        g = r.number(e, "gain", key, default=1.0, unit="-")
        out.append(ListenND(mass, ax, q, g, line=r.line_of(e)))
    return tuple(out)
