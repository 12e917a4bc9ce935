"""Reading scene files: YAML with line numbers (:mod:`hapsim._yaml_lines`) into the
dataclasses, refusing what only a file can get wrong (syntax, structure, unknown and
missing keys) with the file, the line and the key; the values are then checked by the
rules every :class:`~hapsim.scene.Scene` meets, and a broken one is named at its line."""

from __future__ import annotations

import math
import os
from typing import Any, Callable

from hapsim._yaml_lines import LDict, decode_text, load_yaml
from hapsim.errors import ConfigError, show, type_name
from hapsim.scene_schema import LINK_KINDS, MASS_KINDS, key_names, section_keys
from hapsim.scene_schema import key as _key
from hapsim.scene.elements import (Audio, Device, Excitation, Hand, Impulse, Link, Listen, Mass,
                                   Safety)
from hapsim.scene.model import Scene
from hapsim.scene.rules import Invalid, bare_name, check_choice, check_key, coerce

__all__ = ["load_scene", "parse_scene", "read_text", "LineContext", "read_device"]

# Valid keys, defaults, types and ranges: one table, hapsim.scene_schema (docs/scenes.md is
# written from it by hapsim.scene_doc). Add a key there, not here.
_TOP_KEYS = key_names("")
_LINK_KEYS = {kind: key_names("links[]", kind) for kind in LINK_KINDS}
_TARGET_KEYS = key_names("links[].target")
_HAND_KEYS = ("mass", "damping", "grip_stiffness", "grip_damping", "stiffness")



class LineContext:
    """Where the reader is in a file, for error messages: each refusal names the file, the
    line (from the line-numbered mappings of :mod:`hapsim._yaml_lines`) and the key.

    Parameters
    ----------
    path : str
        The file read (``"<string>"`` for text).
    """

    def __init__(self, path: str) -> None:
        self.path = path

    def error(self, message: str, line: int | None, key: str) -> ConfigError:
        """A :class:`~hapsim.errors.ConfigError` naming this file, ``line`` and ``key``
        (returned, for the caller to raise)."""
        return ConfigError(message, file=self.path, line=line, key=key or None)

    @staticmethod
    def line_of(container: Any, key: Any) -> int | None:
        """Line of ``container[key]`` (a mapping's key or a list's item), else of the
        container itself; None for a container read without lines."""
        lines = getattr(container, "lines", None)
        if lines and key in lines:
            return lines[key]
        return getattr(container, "line", None)

    def mapping(self, value: Any, key: str, line: int | None) -> LDict:
        """``value`` when it is a mapping; else ConfigError (``key`` at ``line``)."""
        if not isinstance(value, dict):
            raise self.error(f"must be a mapping (key: value), got {type_name(value)}", line, key)
        return value

    def keys(self, d: LDict, allowed: tuple[str, ...], key: str,
             required: tuple[str, ...] = ()) -> None:
        """Refuse a key of ``d`` not in ``allowed`` (listing them) or a missing
        ``required`` one, at its line, naming ``key.k``."""
        for k in d:
            if k not in allowed:
                raise self.error(f"unknown key {show(k)}; valid keys: {', '.join(allowed)}",
                                 self.line_of(d, k), _key_name(key, k))
        for k in required:
            if k not in d:
                raise self.error(f"missing required key {show(k)}", getattr(d, "line", None),
                                 f"{key}.{k}" if key else k)

    def not_null(self, d: LDict, k: str, key: str) -> None:
        """Refuse ``k: null`` for a key whose absence means "none" (say what was meant)."""
        if k in d and d[k] is None:
            raise self.error(f"must be given a value, got {type_name(None)} (leave the key "
                             "out for none)", self.line_of(d, k), f"{key}.{k}")

    def kind(self, d: LDict, key: str, choices: tuple[str, ...]) -> str:
        """The ``kind`` of an entry, checked now: it decides which keys the entry may have."""
        if "kind" not in d:
            raise self.error("missing required key 'kind'", getattr(d, "line", None),
                             f"{key}.kind")
        try:
            check_choice(d["kind"], choices, "kind")
        except Invalid as bad:
            raise self.error(bad.message, self.line_of(d, "kind"), f"{key}.kind") from None
        return d["kind"]

    @staticmethod
    def doc_line(doc: LDict, where: tuple) -> int | None:
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


def _key_name(parent: str, k: Any) -> str:
    """Dotted key ``parent.k`` for a message (an odd key is :func:`show`-n)."""
    return f"{parent}.{bare_name(k)}" if parent else bare_name(k)


def read_text(path: str | os.PathLike) -> str:
    """The text of a scene file (any dimension), decoded as the YAML reader takes it.

    Parameters
    ----------
    path : str or path-like
        The file.

    Returns
    -------
    str
        Its text (:func:`hapsim._yaml_lines.decode_text`: UTF-8/16/32 with or without a
        byte-order mark).

    Raises
    ------
    ConfigError
        The file cannot be read, or its bytes are no text (the file named).
    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise ConfigError(f"cannot read scene file: {exc.strerror or exc}", file=path) from exc
    return decode_text(data, path)


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
    ctx.keys(doc, _TOP_KEYS, "", required=tuple(k.name for k in section_keys("") if k.required))
    masses = _read_masses(ctx, doc)
    links = _read_links(ctx, doc, masses)
    device = read_device(ctx, doc) if "device" in doc else None
    excitation = _read_excitation(ctx, doc, path) if "excitation" in doc else Excitation()
    safety = _read_safety(ctx, doc) if "safety" in doc else Safety()
    audio = _read_audio(ctx, doc) if "audio" in doc else None
    try:
        return Scene(rate_hz=coerce(doc["rate_hz"]), masses=tuple(masses), links=tuple(links),
                     device=device, excitation=excitation, path=path,
                     integrator=doc.get("integrator", _key("integrator").default), safety=safety,
                     audio=audio)
    except ConfigError as exc:
        where = getattr(exc, "scene_where", None)
        if where is None:
            raise
        raise ConfigError(exc.reason, file=path, line=ctx.doc_line(doc, where),
                          key=exc.key) from None


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


def read_device(ctx: LineContext, doc: LDict) -> Device:
    """The ``device`` section of a document (a scene or a device file).

    Parameters
    ----------
    ctx : LineContext
        The file read.
    doc : LDict
        The document's top mapping, holding ``device``.

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
    d = ctx.mapping(doc["device"], "device", ctx.line_of(doc, "device"))
    vals = _read_values(ctx, d, "device", "device")
    if isinstance(vals["delay"], float) and vals["delay"].is_integer():
        vals["delay"] = int(vals["delay"])   # a whole delay: the plain hold's int, as before
    vals["hand"] = _read_hand(ctx, d) if "hand" in d else None
    vals["correction"] = (dict(ctx.mapping(d["correction"], "device.correction",
                                           ctx.line_of(d, "correction")))
                          if "correction" in d else None)
    vals["protocol_options"] = (dict(ctx.mapping(d["protocol_options"],
                                                 "device.protocol_options",
                                                 ctx.line_of(d, "protocol_options")))
                                if "protocol_options" in d else None)
    return Device(**vals)


def _read_hand(ctx: LineContext, dev: LDict) -> Hand:
    h = ctx.mapping(dev["hand"], "device.hand", ctx.line_of(dev, "hand"))
    ctx.keys(h, _HAND_KEYS, "device.hand", required=("mass",))

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
