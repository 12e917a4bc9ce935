"""The command line and paths a tool records in the files it writes, as a clone reads them.

The tools' JSON and text reports are committed under ``docs/`` and quoted by the site, so
what they record must mean the same in any clone: no interpreter path of the machine they ran
on, no temporary directory, no worktree. ``tests/test_committed_paths.py`` refuses a committed
file under ``docs/`` or ``tests/data/`` that names an absolute machine path.

Rules (one place, every tool):

- the interpreter is written ``python`` (never ``sys.executable``);
- a path inside the repository is written relative to its root (``docs/bench_audio.json``);
- any other absolute path is written as its file name alone (``/tmp/q/x.json`` -> ``x.json``):
  the command, run from a clone, then writes that file in the current directory;
- a path of the tool's own temporary directory is written ``None`` by the tool (nothing a
  reader could open) or replaced by :func:`scrub` in free text.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["REPO", "portable_path", "command_line", "scrub"]

#: The repository's root (this file is ``tools/provenance.py``).
REPO = Path(__file__).resolve().parents[1]


def portable_path(path, root: Path = REPO) -> str:
    """A path as a clone reads it: relative to ``root`` when inside it, else its file name.

    Parameters
    ----------
    path : str or os.PathLike
        Any path; a relative one is returned unchanged (it already reads the same
        everywhere).
    root : pathlib.Path
        The repository root (default: this repository's).

    Returns
    -------
    str
        ``path`` relative to ``root`` (POSIX separators) when it lies inside ``root``,
        the file name alone when it is absolute elsewhere, ``path`` itself when relative.
    """
    text = os.fspath(path)
    if not os.path.isabs(text):
        return text
    p = Path(os.path.normpath(text))
    try:
        return p.relative_to(root.resolve()).as_posix()
    except ValueError:
        pass
    try:    # a symlinked checkout: compare the resolved paths too
        return p.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        return p.name


def command_line(script: str, argv=None, *, prefix: str = "python") -> str:
    """The command that reproduces a tool's run, with portable paths.

    Parameters
    ----------
    script : str
        The tool as run from the repository root, e.g. ``"tools/bench_loop.py"`` (an
        absolute path, such as ``__file__``, is made relative by :func:`portable_path`).
    argv : list of str, optional
        The tool's arguments (``sys.argv[1:]`` when None). Each absolute path, alone or as
        the value of ``--option=PATH``, goes through :func:`portable_path`.
    prefix : str
        What runs the script (``"python"``, ``"PYTHONPATH=. python"``).

    Returns
    -------
    str
        ``prefix script arg ...``, space-separated.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    out = []
    for a in args:
        a = str(a)
        if a.startswith("--") and "=" in a:
            key, _, value = a.partition("=")
            out.append(f"{key}={portable_path(value)}")
        else:
            out.append(portable_path(a))
    return " ".join([prefix, portable_path(script), *out])


def scrub(text, paths: dict):
    """Replace machine paths in free text (a child's message) by placeholders.

    Parameters
    ----------
    text : str or None
        The text (None is returned unchanged).
    paths : dict of str to str
        Each absolute path (a temporary directory) and what stands for it in the record,
        e.g. ``{"/tmp/bench_startup_x1/cache_this": "<NUMBA_CACHE_DIR>"}``; longer paths are
        replaced first, so a directory and its parent can both be given.

    Returns
    -------
    str or None
        ``text`` with every occurrence replaced.
    """
    if text is None:
        return None
    for path in sorted(paths, key=len, reverse=True):
        text = text.replace(os.fspath(path), paths[path])
    return text
