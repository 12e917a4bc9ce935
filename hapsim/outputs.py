"""Checks a command makes before it starts work: can it write its outputs, will it fit;
and the file boundary itself: an input read only from a regular file of bounded size
(:func:`read_input`), an output written whole or not at all (:func:`atomic_write`).

A command that writes a file or allocates a large array checks both up front, so a long
simulation or a run on a device does not end in a traceback after minutes (issue 10).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import stat

from hapsim.errors import ConfigError

__all__ = ["check_writable", "available_memory", "check_fits", "format_bytes", "json_safe",
           "finite_or_none", "write_json", "say_error_after", "read_input", "atomic_write",
           "MAX_INPUT_BYTES"]


def check_writable(path: str, option: str) -> None:
    """Make sure ``path`` can be written, by creating and removing ``path.partial``.

    Parameters
    ----------
    path : str
        The output file a command will write (its ``.partial`` sibling is the temporary
        file hapsim writes before renaming).
    option : str
        The option that named it (``--out``, ``--telemetry``), for the message.

    Raises
    ------
    ConfigError
        When the directory does not exist, is not a directory, ``path`` is a directory,
        or the file cannot be created (permission, read-only file system); key ``option``.

    Notes
    -----
    A real write probe rather than ``os.access``, which says yes to root and ignores
    read-only mounts.
    """
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        what = "is not a directory" if os.path.exists(folder) else "does not exist"
        raise ConfigError(f"cannot write {path}: the directory {folder} {what}", key=option)
    if os.path.isdir(path):
        raise ConfigError(f"cannot write {path}: it is a directory; give a file name",
                          key=option)
    _regular_or_absent(path, option)
    probe = f"{path}.partial"
    existed = os.path.exists(probe)
    try:
        with open(probe, "ab"):
            pass
    except OSError as exc:
        raise ConfigError(f"cannot write {path}: {exc.strerror or exc}", key=option) from None
    if not existed:
        try:
            os.remove(probe)
        except OSError:
            pass


def available_memory() -> int | None:
    """Memory the system can give without swapping [bytes] (``MemAvailable``), or None.

    Returns
    -------
    int or None
        Linux ``/proc/meminfo`` ``MemAvailable``; else free physical pages times the page
        size (``os.sysconf``); None when neither is known.
    """
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def format_bytes(n: float) -> str:
    """``n`` bytes as a short figure with a binary unit (``1.5 GiB``).

    Parameters
    ----------
    n : float
        Bytes, >= 0.

    Returns
    -------
    str
        Three significant digits and B, KiB, MiB, GiB, TiB or PiB (EiB beyond).
    """
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024:
            return f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} EiB"


def check_fits(nbytes: float, what: str, option: str, fraction: float = 0.8) -> None:
    """Refuse work whose arrays cannot fit in memory, with the figures.

    Parameters
    ----------
    nbytes : float
        Bytes the work will allocate (estimate).
    what : str
        What needs them, e.g. ``"10^11 samples x 3 masses of positions"``.
    option : str
        The option or key to name (``--steps``, ``--duration``, ``rate_hz``).
    fraction : float
        Share of the available memory the work may take.

    Raises
    ------
    ConfigError
        When ``nbytes`` exceeds ``fraction`` of :func:`available_memory` (or 2^48 bytes,
        when the available memory is unknown).
    """
    avail = available_memory()
    limit = fraction * avail if avail is not None else float(2 ** 48)
    if nbytes > limit:
        have = (f"{format_bytes(avail)} available" if avail is not None
                else "more than this machine can address")
        raise ConfigError(f"{what} need {format_bytes(nbytes)}; {have}: ask for less",
                          key=option)


#: The largest file an input option reads whole [bytes] (a scene, a device file, a
#: gesture: /dev/zero read until the memory ran out).
MAX_INPUT_BYTES = 1 << 30


def _regular_or_absent(path: str, key: str | None) -> None:
    """Refuse a path that exists and is no regular file (a device, a pipe, a socket): a
    write replaces it (as root, /dev/full was made a file), a read never ends."""
    if os.path.exists(path) and not os.path.isfile(path):
        raise ConfigError(f"{path} is not a regular file (a directory, a device or a "
                          "pipe): give a file's name", key=key)


def read_input(path: str, key: str | None = None, limit: int = MAX_INPUT_BYTES,
               what: str = "input file") -> bytes:
    """The bytes of an input file, read whole, once it is known to be a regular file of a
    bounded size (before: a FIFO hung the command, /dev/zero filled the memory).

    Parameters
    ----------
    path : str or path-like
    key : str, optional
        The option that named it, for the message.
    limit : int
        The largest size taken [bytes].
    what : str
        What the file is, for the message (``scene file``).

    Returns
    -------
    bytes

    Raises
    ------
    ConfigError
        A missing or unreadable file, one that is no regular file, or one over ``limit``
        (the file named).
    """
    path = os.fspath(path)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise ConfigError(f"cannot read {what}: {exc.strerror or exc}", file=path,
                          key=key) from None
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError("not a regular file (a directory, a device or a pipe): give a "
                          "file", file=path, key=key)
    if st.st_size > limit:
        raise ConfigError(f"{format_bytes(st.st_size)}, more than the "
                          f"{format_bytes(limit)} an input file may be", file=path, key=key)
    try:
        with open(path, "rb") as fh:
            return fh.read(limit + 1)
    except OSError as exc:
        raise ConfigError(f"cannot read {what}: {exc.strerror or exc}", file=path,
                          key=key) from None


@contextlib.contextmanager
def atomic_write(path: str, mode: str = "w", key: str | None = None):
    """Write ``path`` whole or not at all: through ``path.partial``, renamed into place
    once the block ends without an error, removed when it raises.

    Parameters
    ----------
    path : str
    mode : {"w", "wb"}
    key : str, optional
        The option that named the path, for a refusal.

    Yields
    ------
    file
        The open ``.partial`` file.

    Raises
    ------
    ConfigError
        ``path`` exists and is no regular file (a device or a pipe is never replaced).
    """
    path = os.fspath(path)
    _regular_or_absent(path, key)
    tmp = f"{path}.partial"
    try:
        with open(tmp, mode) as fh:
            yield fh
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def write_json(path: str, obj, indent: int | None = None, key: str | None = None) -> None:
    """Write ``obj`` as JSON to ``path``, whole or not at all (:func:`atomic_write`: a
    reader never sees half a report, a failure leaves nothing, a device is never
    replaced).

    Parameters
    ----------
    path : str
    obj : object
        What ``json.dump`` writes.
    indent : int, optional
        As ``json.dump``'s.
    key : str, optional
        The option that named the path, for a refusal.

    Raises
    ------
    ConfigError
        ``path`` is no regular file.
    OSError
        The write failed (the ``.partial`` file removed).
    """
    with atomic_write(path, "w", key) as fh:
        json.dump(obj, fh, indent=indent)


def finite_or_none(v) -> float | None:
    """A number as JSON writes it strictly: ``float(v)``, or None when it is not finite or
    is None (``null``).

    Parameters
    ----------
    v : float, int, numpy scalar or None

    Returns
    -------
    float or None
    """
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def json_safe(obj):
    """A copy of ``obj`` that ``json.dumps`` writes as strict JSON: non-finite floats become
    None (``null``), tuples lists; dicts and lists are copied recursively.

    Parameters
    ----------
    obj : object
        A report (dicts, lists, tuples, numbers, strings).

    Returns
    -------
    object
    """
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def say_error_after(command: str, error: dict | None) -> None:
    """After a report, why its run ended: ``hapsim COMMAND: TYPE: MESSAGE`` on stderr, the
    report flushed to stdout first (nothing for None).

    Parameters
    ----------
    command : str
        The command's name (``"run"``, ``"identify"``, ``"zwidth"``).
    error : dict or None
        :func:`hapsim.errors.error_record`'s.
    """
    import sys
    if error is None:
        return
    sys.stdout.flush()
    print(f"hapsim {command}: {error['type']}: {error['message']}", file=sys.stderr)
