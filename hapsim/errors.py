"""One error root for hapsim.

Every error hapsim raises on purpose derives from :class:`HapsimError` and from the
matching built-in, so callers may catch either (pattern of pyserial's
``SerialException(IOError)``).
"""

from __future__ import annotations

import math
import re
import struct
import tokenize
import zipfile
import zlib

__all__ = [
    "num",
    "HapsimError",
    "ConfigError",
    "ProtocolError",
    "DeviceError",
    "FirmwareEchoError",
    "IdentificationError",
    "UnstableConfigError",
    "UnrenderableTargetError",
    "KinematicsError",
    "show",
    "type_name",
    "fixed",
    "dash",
    "plural",
    "error_record",
    "DAMAGED_FILE_ERRORS",
]

#: What reading a damaged or foreign data file raises (a telemetry file, a hand-force
#: profile): the OS; a short or garbled zip (``zipfile.BadZipFile``; a "version" or a
#: compression it does not know, ``NotImplementedError``; a deflate stream,
#: ``zlib.error``); an ``.npy`` header, which numpy parses as a Python literal
#: (``tokenize.TokenError``, ``SyntaxError``); packed numbers (``struct.error``); text
#: (``ValueError``, ``UnicodeDecodeError``); a header naming another shape or a missing
#: column (``KeyError``, ``IndexError``, ``TypeError``, ``OverflowError``). A reader
#: turns each into a :class:`ConfigError` naming the file (a fuzz of 400 damaged files
#: found the zip's and the header's escaping as tracebacks).
DAMAGED_FILE_ERRORS = (OSError, ValueError, KeyError, IndexError, TypeError, EOFError,
                       OverflowError, NotImplementedError, SyntaxError, tokenize.TokenError,
                       struct.error, zlib.error, zipfile.BadZipFile)


class HapsimError(Exception):
    """Root of every error hapsim raises on purpose."""


class ConfigError(HapsimError, ValueError):
    """A scene file, a command-line argument or a keyword argument is invalid.

    Parameters
    ----------
    message : str
        What is wrong and, where one exists, the valid choices.
    file : str, optional
        Path of the file the bad value came from.
    line : int, optional
        1-based line number in ``file``.
    key : str, optional
        Dotted path of the offending key, e.g. ``links[2].stiffness``.
    """

    def __init__(self, message: str, *, file: str | None = None,
                 line: int | None = None, key: str | None = None) -> None:
        self.file = file
        self.line = line
        self.key = key
        self.reason = message
        where = ""
        if file is not None:
            where = f"{file}:{line}: " if line is not None else f"{file}: "
        elif line is not None:
            where = f"line {line}: "
        what = f"{key}: " if key else ""
        super().__init__(f"{where}{what}{message}")


class ProtocolError(HapsimError, ValueError):
    """The device speaks the protocol in a way this host cannot work with.

    Raised by the host (:mod:`hapsim.host.loop`) when the device's HELLO carries another
    ``PROTOCOL_VERSION`` than ``firmware_protocol.PROTOCOL_VERSION``, or another number of
    axes than the scene drives (PROTOCOL.md §1, host duties in §5): the host then sends
    no CONFIG or FORCE. The message says what was expected and what was received, with
    the decoder's last frames (docs/design.md, rule 11).

    Not raised for a corrupt frame (bad COBS or CRC, over-long, unknown type): the stream
    decoder drops and counts those and the loop treats them like a missing frame
    (PROTOCOL.md §5, §8). A device that is absent, silent or reset is a
    :class:`DeviceError`.

    A ``ValueError`` (the device's values are wrong, like ``firmware_protocol.FrameError``),
    deliberately not a :class:`DeviceError` or ``OSError``: reconnecting does not cure it,
    and the loop's recovery retries on DeviceError. ``hapsim`` exits 1 on it.
    """


class IdentificationError(HapsimError, ValueError):
    """A record that cannot be identified (too short, too little motion, no force applied,
    a fit that fails): a negative verdict on the data, not bad input. ``hapsim`` exits 1
    on it with the reason.

    Parameters
    ----------
    message : str
        Why, and what to change (``--duration``, ``--force-limit``, ...).
    """


class DeviceError(HapsimError, OSError):
    """The device or its port failed (absent, silent, reset, faulted)."""


class FirmwareEchoError(DeviceError):
    """A firmware loader's echo of the image differed or stopped (the Novint Falcon's:
    :func:`hapsim.drivers.falcon_usb.load_firmware_link`); the load may be tried again
    from the loader's restart."""


class UnstableConfigError(HapsimError, ValueError):
    """A configuration whose closed loop is unstable or whose target is not renderable.

    Parameters
    ----------
    message : str
        Explanation, with the spectral radius and the stiffness limit where known.
    spectral_radius : float, optional
        Largest closed-loop pole modulus (>= 1 means unstable).
    stiffness_limit : float, optional
        Largest stable virtual stiffness K for the configuration [N/m].
    """

    def __init__(self, message: str, *, spectral_radius: float | None = None,
                 stiffness_limit: float | None = None) -> None:
        self.spectral_radius = spectral_radius
        self.stiffness_limit = stiffness_limit
        super().__init__(message)


class UnrenderableTargetError(UnstableConfigError, ConfigError):
    """A felt target ``{k, b}`` that no virtual (K, B) renders with this device and rate.

    A negative verdict (exit code 1, as ``hapsim calibrate`` gives for the same target:
    docs/commands.md, 'Exit codes') that is also a :class:`ConfigError`, so the message names the file,
    the line and the key ``links.NAME.target``; :func:`hapsim.cli.main` tests for
    :class:`UnstableConfigError` first.

    Parameters
    ----------
    message : str
        Why the target is not renderable (the calibration's reason).
    file : str, optional
        Scene file.
    line : int, optional
        1-based line of the link.
    key : str, optional
        ``links.NAME.target``.
    spectral_radius : float, optional
        Spectral radius of the closest (K, B) found.
    """

    def __init__(self, message: str, *, file: str | None = None, line: int | None = None,
                 key: str | None = None, spectral_radius: float | None = None) -> None:
        ConfigError.__init__(self, message, file=file, line=line, key=key)
        self.spectral_radius = spectral_radius
        self.stiffness_limit = None


class KinematicsError(ConfigError):
    """A device configuration the kinematics refuses: outside the workspace or singular.

    Bad input (a ``ConfigError``, exit code 2): the joint angles given are not a
    configuration at which the device renders a force (:mod:`hapsim.kinematics`).

    Parameters
    ----------
    message : str
        Where (the joints in degrees) and why (no assembly, which singularity).
    joints : array_like, optional
        The refused joint angles [rad].
    kind : {"workspace", "serial", "parallel"}, optional
        No assembly; a serial singularity (an arm stretched or folded: the Jacobian loses
        rank); a parallel one (the handle gains a freedom: the Jacobian is unbounded).
    key : str, optional
        Option or scene key, default ``joints``.
    """

    def __init__(self, message: str, *, joints=None, kind: str | None = None,
                 key: str | None = "joints") -> None:
        super().__init__(message, key=key)
        self.joints = None if joints is None else [float(v) for v in joints]
        self.kind = kind


def show(value: object, limit: int = 60) -> str:
    """A value as a message may print it: its repr, on one line, at most ``limit`` chars.

    Parameters
    ----------
    value : object
        Anything (a scene value, a name, a command-line argument).
    limit : int
        Most characters returned (>= 8).

    Returns
    -------
    str
        ``repr(value)`` with line breaks escaped, cut to ``limit`` characters with ``...``.
        Containers are walked at most 3 levels deep and 4 items wide (``reprlib``), so the
        cost is bounded even for a document whose aliases make it huge.
    """
    import reprlib
    if isinstance(value, int) and value.bit_length() > 200:     # ~60 digits and more:
        digits = int(value.bit_length() * 0.30103) + 1          # no decimal conversion,
        return f"{'-' if value < 0 else ''}<a whole number of about {digits} digits>"  # cost O(1)
    r = reprlib.Repr()
    r.maxlevel, r.maxlist, r.maxtuple, r.maxdict, r.maxset = 3, 4, 4, 4, 4
    r.maxstring = r.maxother = r.maxlong = max(limit, 8)
    text = r.repr(value)
    text = text.replace("\r", "\\r").replace("\n", "\\n")
    if len(text) > limit:
        text = text[:limit - 3] + "..."
    return text


def num(value) -> str:
    """A number as a message prints it: ``format(value, "g")``, or :func:`show` where a
    whole number is beyond the float range (a 400-digit integer from a scene file).

    Parameters
    ----------
    value : int or float
        The number.

    Returns
    -------
    str
        Six significant digits, or a bounded description of a huge whole number.
    """
    try:
        return f"{value:g}"
    except (OverflowError, ValueError):
        return show(value)


def type_name(value: object) -> str:
    """What kind of value a message says it got: ``"a number"``, ``"a list"``, ...

    Parameters
    ----------
    value : object
        A value read from a file (YAML: null, boolean, mapping, list, integer, float,
        string) or anything else.

    Returns
    -------
    str
        ``"nothing (null)"``, ``"a boolean"``, ``"a mapping"``, ``"a list"``,
        ``"an integer"``, ``"a number"`` or ``"a string"``; else the type's name.
    """
    if value is None:
        return "nothing (null)"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    return {int: "an integer", float: "a number", str: "a string"}.get(
        type(value), type(value).__name__)


def fixed(value: float, spec: str) -> str:
    """``format(value, spec)`` for a fixed-point ``spec`` (``"12.9f"``), never 300 digits.

    Parameters
    ----------
    value : float
        The number.
    spec : str
        A format spec ending in ``f`` (width, alignment, sign and precision kept).

    Returns
    -------
    str
        The fixed-point text while it stays within the field (or 16 characters), else the
        same field in ``g`` with the precision as significant digits (``1e+300``, not a
        301-digit integer part).
    """
    text = format(value, spec)
    m = re.fullmatch(r"(.*?)(\d*)(?:\.(\d+))?f", spec)
    width = int(m.group(2)) if m and m.group(2) else 0
    if len(text.strip()) <= max(width, 16) or not m:
        return text
    digits = int(m.group(3)) if m.group(3) else 6
    return format(value, f"{m.group(1)}{m.group(2)}.{max(digits, 1)}g")


def dash(value, spec: str) -> str:
    """``value`` in a report's column: ``"-"`` when it is None or a non-finite float, else
    :func:`fixed` for a fixed-point ``spec`` and ``format(value, spec)`` otherwise.

    Parameters
    ----------
    value : float or None
        The number.
    spec : str
        A format spec (``"12.4f"``, ``"+9.2e"``, ``".6g"``).

    Returns
    -------
    str
    """
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return fixed(value, spec) if spec.endswith("f") else format(value, spec)


def plural(n: int, word: str, many: str | None = None) -> str:
    """``"1 link"``, ``"3 links"``: a count with its noun in the right number.

    Parameters
    ----------
    n : int
        The count (singular only for exactly 1).
    word : str
        The noun, singular.
    many : str, optional
        Its plural when not ``word + "s"``.

    Returns
    -------
    str
    """
    return f"{n} {word if n == 1 else (many or word + 's')}"


def error_record(exc: BaseException | None) -> dict | None:
    """The ``error`` entry of a report whose run an exception ended (a device lost
    after its first record): ``{"type": class name, "message": str(exc)}``; None for
    None.

    Parameters
    ----------
    exc : BaseException or None

    Returns
    -------
    dict or None
    """
    return None if exc is None else {"type": type(exc).__name__, "message": str(exc)}
