"""A bounded, line-keeping YAML reader for scene files.

Scene files come from users and from the network, so the reader must answer fast on any
input, with one :class:`~hapsim.errors.ConfigError` naming the file and the line:

* bytes that are not text (Latin-1, binary) are refused; UTF-8 (with or without a byte
  order mark) and UTF-16/UTF-32 with a byte order mark are read (YAML 1.2 §5.2);
* the document is built from the parser's *events*, never recursively: nesting deeper than
  :data:`MAX_DEPTH` is refused at the first event beyond it (PyYAML's composer recurses and
  libyaml's composer overflows the C stack on ``[[[[...``);
* aliases share the anchored object, and the document's *expanded* size (every alias
  counted with the size of what it names) is bounded by :data:`MAX_NODES` plus twice the
  nodes actually written, so an alias bomb ("billion laughs") is refused in microseconds;
* mapping keys must be scalars (a list as a key is refused, not ``TypeError: unhashable``);
* duplicate keys are refused, but a merge key ``<<: *anchor`` is honoured (YAML 1.1 merge:
  explicit keys override merged ones, earlier merged mappings override later ones);
* numbers are read as YAML 1.2 reads them: ``1e12``, ``2E-4`` and ``.5`` are floats (YAML
  1.1 wants a dot in the mantissa and reads ``1e12`` as a string).

libyaml's C parser (``yaml.CSafeLoader``) is used where PyYAML was built with it (about 10x
faster on large scenes); the pure-Python parser otherwise. Both are event parsers with
explicit stacks, so neither recurses on deep input.
"""

from __future__ import annotations

import codecs
import gc
import re
from typing import Any, Callable

import yaml

from hapsim.errors import ConfigError, show

__all__ = ["LDict", "LList", "load_yaml", "decode_text", "MAX_DEPTH", "MAX_NODES"]

#: Deepest nesting of lists and mappings a scene may use (a scene needs 4).
MAX_DEPTH = 64
#: Nodes that aliases may add to a document beyond twice the nodes written in it.
MAX_NODES = 200_000

_MAP_TAG = "tag:yaml.org,2002:map"
_SEQ_TAG = "tag:yaml.org,2002:seq"
_MERGE_TAG = "tag:yaml.org,2002:merge"
_STR_TAG = "tag:yaml.org,2002:str"

try:  # libyaml's parser, where PyYAML was built with it
    _BaseLoader: type = yaml.CSafeLoader
except AttributeError:  # pragma: no cover - depends on the PyYAML build
    _BaseLoader = yaml.SafeLoader


class LDict(dict):
    """A mapping read from YAML: ``line`` of the mapping and ``lines[key]`` of each key."""

    line: int
    lines: dict


class LList(list):
    """A sequence read from YAML: ``line`` of the sequence and ``lines[i]`` of each item."""

    line: int
    lines: dict


class _Loader(_BaseLoader):  # type: ignore[misc, valid-type]
    """SafeLoader (C parser where available) whose plain scalars follow YAML 1.2 floats."""


# YAML 1.2 core schema floats the 1.1 resolver misses: an exponent without a dot in the
# mantissa (1e12, 2E-4, +3e5). Appended after the 1.1 resolvers, so ints stay ints.
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def decode_text(data: bytes, path: str) -> str:
    """Decode a scene file's bytes as YAML allows, or refuse in one line.

    Parameters
    ----------
    data : bytes
        The file's content.
    path : str
        File name for the message.

    Returns
    -------
    str
        The text, without a byte order mark.

    Raises
    ------
    ConfigError
        For bytes that are not UTF-8 (and carry no UTF-16/32 byte order mark), or that
        hold a NUL byte (binary): the message names the line and column of the first bad
        byte and says to save the file as UTF-8.

    Notes
    -----
    YAML 1.2 §5.2: a stream is UTF-8, UTF-16 or UTF-32; a byte order mark names the latter.
    """
    for bom, codec in ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"),
                       (codecs.BOM_UTF8, "utf-8-sig"), (codecs.BOM_UTF16_LE, "utf-16"),
                       (codecs.BOM_UTF16_BE, "utf-16")):
        if data.startswith(bom):
            break
    else:
        codec = "utf-8"
    try:
        text = data.decode(codec)
    except UnicodeDecodeError as exc:
        good = data[:exc.start]
        line = good.count(b"\n") + 1
        col = exc.start - (good.rfind(b"\n") + 1) + 1
        raise ConfigError(f"not a text file in {codec.upper().replace('-SIG', '')} (byte "
                          f"0x{data[exc.start]:02x} at column {col}); save the scene as "
                          "UTF-8 text", file=path, line=line) from None
    nul = text.find("\0")
    if nul >= 0:
        line = text.count("\n", 0, nul) + 1
        raise ConfigError("a binary file, not YAML text (NUL character); a scene is a "
                          "UTF-8 text file", file=path, line=line)
    return text


class _Frame:
    """A mapping or sequence being built."""

    __slots__ = ("obj", "start", "key", "key_line", "merges", "anchor")

    def __init__(self, obj: Any, start: int, anchor: str | None) -> None:
        self.obj = obj
        self.start = start          # node count when the container opened
        self.key: Any = _NOKEY      # mapping: the key awaiting its value
        self.key_line = 0
        self.merges: list = []      # mapping: (line, merged mapping or list of them)
        self.anchor = anchor


_NOKEY = object()
_MERGE = object()


def load_yaml(text: str, path: str = "<string>",
              progress: Callable[[int, int], None] | None = None) -> Any:
    """Read one YAML document into plain values, with bounded cost.

    Parameters
    ----------
    text : str
        The YAML text.
    path : str
        File name for messages.
    progress : callable, optional
        ``progress(done, total)`` called every 20000 parser events with the characters
        read so far and ``len(text)`` (for a progress bar on large scenes).

    Returns
    -------
    object
        None for an empty document; else an :class:`LDict`, :class:`LList` or scalar
        (``str``, ``int``, ``float``, ``bool``, ``None``, ``datetime``, ``bytes``).
        Aliased containers are shared, not copied.

    Raises
    ------
    ConfigError
        Syntax errors (with the line the parser names), nesting deeper than
        :data:`MAX_DEPTH`, aliases expanding the document beyond its bound, a list or a
        mapping as a mapping key, duplicate keys, a merge key that is not a mapping, an
        unknown or unsafe tag, a recursive alias, more than one document.
    """
    loader = _Loader(text)
    # the builder only allocates (no cycles to collect): the cyclic GC, which would walk
    # every container made so far again and again, is paused while it runs
    collecting = gc.isenabled()
    gc.disable()
    try:
        return _Builder(loader, path, progress, len(text)).build()
    except ConfigError:
        raise
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        if "nesting depth" in (exc.problem or ""):
            # libyaml >= 0.2.5 (PyYAML 6.0.4's wheels) stops at 1000 levels in its scanner,
            # which reads ahead of the events this builder counts (an unclosed '[[[...'):
            # the same refusal as the builder's own, whichever meets the depth first
            raise ConfigError(f"invalid YAML: nested deeper than {MAX_DEPTH} levels of lists "
                              "and mappings (a scene needs 4)", file=path, line=line) from None
        raise ConfigError(f"invalid YAML: {_one_line(exc.problem or str(exc))}", file=path,
                          line=line) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"invalid YAML: {_one_line(str(exc))}", file=path) from None
    except RecursionError:  # not expected: the builder does not recurse
        raise ConfigError(f"invalid YAML: nested deeper than {MAX_DEPTH} levels",
                          file=path) from None
    finally:
        if collecting:
            gc.enable()
        loader.dispose()


def _one_line(s: str) -> str:
    s = " ".join(s.split())
    return s if len(s) <= 200 else s[:197] + "..."


class _Builder:
    """Builds the document from parser events with an explicit stack (no recursion)."""

    def __init__(self, loader: Any, path: str, progress: Callable | None = None,
                 size: int = 0) -> None:
        self.progress = progress
        self.size = size
        self.loader = loader
        self.path = path
        self.nodes = 0        # nodes written in the text
        self.expanded = 0     # nodes the document stands for, aliases expanded
        self.anchors: dict[str, tuple[Any, int]] = {}   # name -> (object, expanded size)
        self.open_anchors: set[str] = set()
        self.stack: list[_Frame] = []
        self.scalar_cache: dict[tuple, Any] = {}
        self.constructors: dict[str, Callable] = loader.yaml_constructors
        # first characters some implicit resolver (int, float, bool, null, ...) looks at
        self.resolvable = frozenset(c for c in loader.yaml_implicit_resolvers if c)

    def error(self, message: str, mark: Any) -> ConfigError:
        line = mark.line + 1 if mark is not None else None
        return ConfigError(message, file=self.path, line=line)

    def build(self) -> Any:
        ld = self.loader
        ev = ld.get_event()                      # StreamStart
        if not ld.check_event(yaml.DocumentStartEvent):
            ld.get_event()                       # StreamEnd: empty stream
            return None
        ld.get_event()                           # DocumentStart
        root: list = []
        push = self._push
        events = 0
        while True:
            ev = ld.get_event()
            events += 1
            if self.progress is not None and events % 20000 == 0:
                self.progress(ev.start_mark.index, self.size)
            cls = type(ev)
            if cls is yaml.ScalarEvent:
                self.nodes += 1
                self._count(1, ev)
                value = self._scalar(ev)
                if ev.anchor:
                    self.anchors[ev.anchor] = (value, 1)
                push(value, ev, root, is_scalar=True)
            elif cls is yaml.MappingStartEvent or cls is yaml.SequenceStartEvent:
                self._open(ev, cls is yaml.MappingStartEvent, root)
            elif cls is yaml.MappingEndEvent or cls is yaml.SequenceEndEvent:
                fr = self.stack.pop()
                if isinstance(fr.obj, LDict):
                    self._merge(fr)
                size = self.expanded - fr.start + 1
                if fr.anchor:
                    self.anchors[fr.anchor] = (fr.obj, size)
                    self.open_anchors.discard(fr.anchor)
                push(fr.obj, ev, root, is_scalar=False, placed=True)
            elif cls is yaml.AliasEvent:
                if ev.anchor in self.open_anchors:
                    raise self.error(f"recursive alias *{_show_name(ev.anchor, quote=False)} (a value that "
                                     "contains itself)", ev.start_mark)
                if ev.anchor not in self.anchors:
                    raise self.error(f"unknown alias *{_show_name(ev.anchor, quote=False)} (no "
                                     "&anchor of that name above it)", ev.start_mark)
                value, size = self.anchors[ev.anchor]
                self.nodes += 1
                self._count(size, ev)
                push(value, ev, root, is_scalar=not isinstance(value, (LDict, LList)),
                     alias=True)
            elif cls is yaml.DocumentEndEvent:
                break
            else:  # pragma: no cover - the parser emits nothing else inside a document
                raise self.error(f"unexpected YAML event {cls.__name__}", ev.start_mark)
        if not ld.check_event(yaml.StreamEndEvent):
            ev = ld.get_event()
            raise self.error("more than one YAML document ('---'); a scene is one document",
                             ev.start_mark)
        return root[0] if root else None

    # ---------------------------------------------------------------- bookkeeping
    def _count(self, size: int, ev: Any) -> None:
        self.expanded += size
        if self.expanded > MAX_NODES + 2 * self.nodes:
            raise self.error(f"aliases expand the document beyond {MAX_NODES + 2 * self.nodes}"
                             " values (an alias bomb?); write the values out or use fewer "
                             "aliases", ev.start_mark)

    def _open(self, ev: Any, mapping: bool, root: list) -> None:
        if len(self.stack) >= MAX_DEPTH:
            raise self.error(f"nested deeper than {MAX_DEPTH} levels of lists and mappings "
                             "(a scene needs 4)", ev.start_mark)
        tag = ev.tag
        want = _MAP_TAG if mapping else _SEQ_TAG
        if tag not in (None, "!", want):
            raise self.error(f"unsupported tag {_show_name(tag)} (a scene uses plain "
                             "mappings, lists and scalars)", ev.start_mark)
        if self.stack and isinstance(self.stack[-1].obj, LDict) \
                and self.stack[-1].key is _NOKEY:
            kind = "mapping" if mapping else "list"
            raise self.error(f"a {kind} cannot be a mapping key; keys are names", ev.start_mark)
        self.nodes += 1
        self._count(1, ev)
        obj = LDict() if mapping else LList()
        obj.line = ev.start_mark.line + 1
        obj.lines = {}
        if ev.anchor:
            self.open_anchors.add(ev.anchor)
        # the container is placed in its parent when it closes (its line is known now)
        fr = _Frame(obj, self.expanded, ev.anchor)
        fr.key_line = ev.start_mark.line + 1
        self.stack.append(fr)

    def _scalar(self, ev: Any) -> Any:
        tag = ev.tag
        key = None
        if tag is None or tag == "!":
            text = ev.value
            if ev.implicit[0] and text and text[0] not in self.resolvable:
                return text                       # a plain name: no resolver can match
            key = (text, ev.implicit)
            hit = self.scalar_cache.get(key, _NOKEY)
            if hit is not _NOKEY:
                return hit
            tag = self.loader.resolve(yaml.ScalarNode, text, ev.implicit)
        if tag == _STR_TAG:
            value = ev.value
        elif tag == _MERGE_TAG:
            value = _MERGE
        else:
            ctor = self.constructors.get(tag)
            if ctor is None or tag.startswith("tag:yaml.org,2002:python/"):
                raise self.error(f"unsupported tag {_show_name(tag)} (a scene uses plain "
                                 "mappings, lists and scalars)", ev.start_mark)
            node = yaml.ScalarNode(tag, ev.value, ev.start_mark, ev.end_mark, ev.style)
            try:
                value = ctor(self.loader, node)
            except (ValueError, TypeError, OverflowError, ArithmeticError):
                # an explicit tag on text it cannot read: '!!float abc', '!!int 1.5x'
                raise self.error(f"{_show_name(tag)} cannot read "
                                 f"{_show_name(ev.value)}", ev.start_mark) from None
        if key is not None and len(self.scalar_cache) < 65536 and len(ev.value) < 64:
            self.scalar_cache[key] = value
        return value

    def _push(self, value: Any, ev: Any, root: list, *, is_scalar: bool, placed: bool = False,
              alias: bool = False) -> None:
        """Put a finished value into the open container (or make it the document)."""
        if not self.stack:
            root.append(value)
            return
        fr = self.stack[-1]
        line = ev.start_mark.line + 1
        if placed:  # a closed container: its line is where it opened
            line = value.line
        obj = fr.obj
        if isinstance(obj, LList):
            obj.lines[len(obj)] = line
            obj.append(value)
            return
        if fr.key is _NOKEY:  # this value is a key
            if not is_scalar:
                kind = "mapping" if isinstance(value, dict) else "list"
                raise self.error(f"a {kind} cannot be a mapping key; keys are names",
                                 ev.start_mark)
            fr.key = value
            fr.key_line = line
            return
        key = fr.key
        fr.key = _NOKEY
        if key is _MERGE:
            fr.merges.append((fr.key_line, value))
            return
        if key in obj:
            raise ConfigError(f"duplicate key {_show_name(key)} (first on line "
                              f"{obj.lines[key]})", file=self.path, line=fr.key_line,
                              key=self._path(_show_name(key, quote=False)))
        obj[key] = value
        obj.lines[key] = fr.key_line

    def _path(self, last: str) -> str:
        """The dotted key of ``last`` in the innermost open mapping, as the scene's
        messages name keys (``masses[25].name``; before: the bare ``name``)."""
        out = ""
        for fr in self.stack[:-1]:
            if isinstance(fr.obj, LList):
                out += f"[{len(fr.obj)}]"
            elif isinstance(fr.key, str):
                out += ("." if out else "") + _show_name(fr.key, quote=False)
            else:                           # a merge's or a number's key: the bare name
                return last
        return out + ("." if out else "") + last

    def _merge(self, fr: _Frame) -> None:
        """Apply ``<<`` merge keys: explicit keys win, then earlier merged mappings."""
        obj = fr.obj
        for line, value in fr.merges:
            sources = value if isinstance(value, LList) else [value]
            for src in sources:
                if not isinstance(src, LDict):
                    raise ConfigError("a merge key '<<' takes a mapping or a list of "
                                      "mappings (e.g. <<: *defaults)", file=self.path,
                                      line=line, key="<<")
                for k, v in src.items():
                    if k not in obj:
                        obj[k] = v
                        obj.lines[k] = src.lines.get(k, line)


def _show_name(v: Any, quote: bool = True) -> str:
    """``show(v)``; without the quotes of a string when ``quote`` is False."""
    text = show(v)
    return text[1:-1] if not quote and isinstance(v, str) and text[:1] in "'\"" else text
