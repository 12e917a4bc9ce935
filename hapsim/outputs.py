"""Checks a command makes before it starts work: can it write its outputs, will it fit.

A command that writes a file or allocates a large array checks both up front, so a long
simulation or a run on a device does not end in a traceback after minutes (issue 10).
"""

from __future__ import annotations

import json
import math
import os

from hapsim.errors import ConfigError

__all__ = ["check_writable", "available_memory", "check_fits", "format_bytes", "json_safe",
           "finite_or_none", "write_json", "say_error_after"]


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


def write_json(path: str, obj, indent: int | None = None) -> None:
    """Write ``obj`` as JSON to ``path``, whole or not at all: through ``path.partial``,
    renamed into place (a reader never sees half a report).

    Parameters
    ----------
    path : str
    obj : object
        What ``json.dump`` writes.
    indent : int, optional
        As ``json.dump``'s.
    """
    tmp = f"{path}.partial"
    with open(tmp, "w") as fh:
        json.dump(obj, fh, indent=indent)
    os.replace(tmp, path)


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
