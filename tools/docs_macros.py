"""MkDocs hook: measured figures in the documentation come from the files the tools write.

A page never types a measured number that a tool's output file holds: it names the file and
the field, and the build puts the value (or the whole table) in. Three macros, each on one
line or inside a line of Markdown, with arguments quoted as in a shell:

``{{ include "table1.md" }}``
    The text of a file (a Markdown table a tool wrote), relative to ``docs/``.
``{{ value "bench_startup.json" "cold.first_sample_s.median" ".2f" }}``
    One field of a JSON file: a dotted path (list indices are numbers), formatted with a
    format spec (default ``g``).
``{{ table "bench_firmware.json" "" "rate [Hz]=rate_hz:.0f" "busy mean=busy_mean_cycles" }}``
    A Markdown table with one row per entry of the list or mapping at the path (``""``: the
    whole file); each column is ``HEADER=PATH[:FORMAT]`` with ``PATH`` a dotted path inside
    the entry, ``@key`` for the mapping's key, ``A/B`` for a ratio of two paths; a format
    ending in ``%`` multiplies by 100 (``:.1f%``). ``None`` is shown as ``-``, booleans as
    ``yes``/``no``.

``{{ families }}``
    The device families of the drivers' registry (:data:`hapsim.drivers.FAMILIES`), one
    row each: the page's list of devices cannot drift from what ``--driver`` accepts.

The build also says how far it is (``on_page_markdown``, ``on_post_page``): a line on the
``mkdocs`` logger at most every :data:`PROGRESS_S` seconds, so ``mkdocs build`` is never
silent for seconds (issue 31: nothing a newcomer runs is silent over 2 s; it was ~4 s on
a loaded 2-core machine between "Building documentation" and "Documentation built").

A missing file, key or a malformed macro fails the build (``mkdocs build --strict`` in the
tests), so a figure cannot silently drift from its file. Used by ``mkdocs.yml`` (``hooks:``)
and by ``tests/test_docs_site.py``.
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

MACRO = re.compile(r"\{\{\s*(include|value|table|families)\s*(.*?)\s*\}\}")


class MacroError(ValueError):
    """A macro names a file, a field or a format that does not exist."""


def _field(data, path: str):
    """The value at a dotted ``path`` of parsed JSON (``""``: the whole; ``\\.`` is a dot
    inside a key, as in ``faults_injected.rx\\.drop``)."""
    cur = data
    parts = [p.replace("\\.", ".") for p in re.split(r"(?<!\\)\.", path)] if path else []
    for part in [p for p in parts if p]:
        if isinstance(cur, list):
            cur = cur[int(part)]
        elif isinstance(cur, dict):
            if part not in cur:
                raise KeyError(part)
            cur = cur[part]
        else:
            raise KeyError(part)
    return cur


def _fmt(v, spec: str) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, str):
        return v
    if spec.endswith("%"):
        return format(100.0 * v, spec[:-1]) + " %"
    return format(v, spec or "g")


def _cell(entry, key, col: str):
    head, _, rest = col.partition("=")
    path, _, spec = rest.partition(":")
    if path == "@key":
        v = key
    elif "/" in path:
        a, b = path.split("/", 1)
        den = _field(entry, b)
        v = None if not den else _field(entry, a) / den
    else:
        v = _field(entry, path)
    return head, _fmt(v, spec)


def expand(text: str, root: Path) -> str:
    """Replace every macro of ``text`` (files relative to ``root``).

    Raises
    ------
    MacroError
        A file, a field or a format that does not exist, or a malformed macro.
    """
    def one(m: re.Match) -> str:
        kind, args = m.group(1), shlex.split(m.group(2))
        try:
            if kind == "families":
                return _families()
            path = root / args[0]
            if kind == "include":
                return path.read_text().rstrip("\n")
            data = json.loads(path.read_text())
            if kind == "value":
                return _fmt(_field(data, args[1]), args[2] if len(args) > 2 else "")
            rows = _field(data, args[1])
            items = list(rows.items()) if isinstance(rows, dict) else list(enumerate(rows))
            cells = [[_cell(e, k, c) for c in args[2:]] for k, e in items]
            heads = [h for h, _ in cells[0]]
            lines = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
            lines += ["| " + " | ".join(v for _, v in row) + " |" for row in cells]
            return "\n".join(lines)
        except (OSError, KeyError, IndexError, ValueError, TypeError,
                ZeroDivisionError) as exc:
            raise MacroError(f"{m.group(0)}: {type(exc).__name__}: {exc}") from None
    return MACRO.sub(one, text)


def _families() -> str:
    """The drivers' registry as a Markdown table (``{{ families }}``)."""
    from hapsim.drivers import FAMILIES
    route = {"loop": "the host loop"}
    link = {"framed": "`SerialTransport`", "driver": "`DriverTransport`", "own": "its route's"}
    lines = ["| `--driver` | scenes | device | link | run by |", "|---|---|---|---|---|"]
    lines += [f"| `{f.name}` | {f'{f.dimension}-D' if f.dimension else 'any'} | {f.device} | "
              f"{link[f.transport]} | {route.get(f.route, f'`{f.route}`')} |" for f in FAMILIES]
    return "\n".join(lines)


#: Most seconds between two of the build's progress lines (module notes).
PROGRESS_S = 0.5
_progress = {"last": 0.0, "read": 0, "written": 0, "pages": 0}


def on_files(files, config):   # MkDocs hook (event name fixed)
    """Count the pages the build renders (for its progress lines); the files unchanged."""
    import time
    _progress.update(last=time.monotonic(), read=0, written=0,
                     pages=sum(1 for f in files if f.is_documentation_page()))
    return files


def _say(stage: str, page) -> None:
    """A progress line on the ``mkdocs`` logger when :data:`PROGRESS_S` has passed."""
    import logging
    import time
    _progress[stage] += 1
    now = time.monotonic()
    if now - _progress["last"] >= PROGRESS_S:
        _progress["last"] = now
        logging.getLogger("mkdocs").info(
            f"hapsim docs: {_progress[stage]} of {_progress['pages']} pages {stage} "
            f"({page.file.src_path})")


def on_post_page(output, page, config):   # MkDocs hook (event name fixed)
    """Say the build's progress (module notes); the page's HTML unchanged."""
    _say("written", page)
    return output


def on_page_markdown(markdown, page, config, files):   # MkDocs hook (event name fixed)
    """Expand the macros of one page; the files are read from ``docs_dir``. Says the
    build's progress (module notes).

    Raises
    ------
    mkdocs.exceptions.PluginError
        A macro that cannot be expanded (the build stops with the page and the macro).
    """
    from mkdocs.exceptions import PluginError
    _say("read", page)
    try:
        return expand(markdown, Path(config["docs_dir"]))
    except MacroError as exc:
        raise PluginError(f"{page.file.src_path}: {exc}") from None
