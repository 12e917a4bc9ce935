"""Where the reader is in a scene file, and the values it reads there.

:class:`LineContext` holds the file read and turns every refusal into a
:class:`~hapsim.errors.ConfigError` naming the file, the line (from the line-numbered
mappings of :mod:`hapsim._yaml_lines`) and the key, for scene files of every dimension:
:mod:`hapsim.scene.reader` reads with it, as :mod:`hapsim.scene.devices` and
:mod:`hapsim.device_file` do; :func:`read_text` is the text of any scene file."""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from hapsim._yaml_lines import LDict, decode_text
from hapsim.errors import ConfigError, show, type_name
from hapsim.scene.rules import Invalid, bare_name, check_choice

__all__ = ["LineContext", "read_text"]


class LineContext:
    """Where the reader is in a file, for error messages: each refusal names the file, the
    line (from the line-numbered mappings of :mod:`hapsim._yaml_lines`) and the key.

    The 1-D reader reads mappings, keys and kinds with it; the 2-D/3-D reader also its
    values, checked at once (:meth:`number`, :meth:`integer`, :meth:`string`,
    :meth:`choice`, vectors of ``dimension`` numbers: :meth:`vector`, symmetric matrices:
    :meth:`matrix`), each returning the key's default when it is absent.

    Parameters
    ----------
    path : str
        The file read (``"<string>"`` for text).
    """

    def __init__(self, path: str) -> None:
        self.path = path

    def error(self, message: str, line: int | None, key: str) -> ConfigError:
        """A :class:`~hapsim.errors.ConfigError` naming this file, ``line`` and ``key``
        (returned, for the caller to raise).

        Parameters
        ----------
        message : str
            What is wrong with the value.
        line : int or None
            Line of the value in the file (1-based); None when unknown.
        key : str
            Dotted key of the value; empty for none.

        Returns
        -------
        ConfigError
            The error, not raised.
        """
        return ConfigError(message, file=self.path, line=line, key=key or None)

    @staticmethod
    def line_of(container: Any, key: Any = None) -> int | None:
        """Line of ``container[key]`` (a mapping's key or a list's item), else of the
        container itself (``key`` None or absent); None for a container read without
        lines.

        Parameters
        ----------
        container : LDict, LList or any
            The mapping or list read (its ``lines`` and ``line`` attributes, if any).
        key : str, int or None, optional
            The key or item index; None for the container itself.

        Returns
        -------
        int or None
            The line (1-based), or None.
        """
        lines = getattr(container, "lines", None)
        if lines and key in lines:
            return lines[key]
        return getattr(container, "line", None)

    def mapping(self, value: Any, key: str, line: int | None) -> LDict:
        """``value`` when it is a mapping; else ConfigError (``key`` at ``line``).

        Parameters
        ----------
        value : any
            The value read.
        key : str
            Its dotted key, for the message.
        line : int or None
            Its line, for the message.

        Returns
        -------
        LDict
            ``value`` itself.

        Raises
        ------
        ConfigError
            ``value`` is not a dict.
        """
        if not isinstance(value, dict):
            raise self.error(f"must be a mapping (key: value), got {type_name(value)}", line, key)
        return value

    def keys(self, d: LDict, allowed: tuple[str, ...], key: str,
             required: tuple[str, ...] = ()) -> None:
        """Refuse a key of ``d`` not in ``allowed`` (listing them) or a missing
        ``required`` one, at its line, naming ``key.k``.

        Parameters
        ----------
        d : LDict
            The mapping read.
        allowed : tuple of str
            The keys it may have.
        key : str
            Its dotted key (empty at the top level).
        required : tuple of str, optional
            The keys it must have (default none).

        Raises
        ------
        ConfigError
            A key not in ``allowed``, or one of ``required`` missing.
        """
        for k in d:
            if k not in allowed:
                raise self.error(f"unknown key {show(k)}; valid keys: {', '.join(allowed)}",
                                 self.line_of(d, k), _key_name(key, k))
        for k in required:
            if k not in d:
                raise self.error(f"missing required key {show(k)}", getattr(d, "line", None),
                                 f"{key}.{k}" if key else k)

    def not_null(self, d: LDict, k: str, key: str) -> None:
        """Refuse ``k: null`` for a key whose absence means "none" (say what was meant).

        Parameters
        ----------
        d : LDict
            The mapping read.
        k : str
            The key checked (absent is allowed).
        key : str
            The dotted key of ``d``.

        Raises
        ------
        ConfigError
            ``d[k]`` is None.
        """
        if k in d and d[k] is None:
            raise self.error(f"must be given a value, got {type_name(None)} (leave the key "
                             "out for none)", self.line_of(d, k), f"{key}.{k}")

    def kind(self, d: LDict, key: str, choices: tuple[str, ...]) -> str:
        """The ``kind`` of an entry, checked now: it decides which keys the entry may have.

        Parameters
        ----------
        d : LDict
            The entry read.
        key : str
            Its dotted key.
        choices : tuple of str
            The kinds allowed.

        Returns
        -------
        str
            ``d["kind"]``, one of ``choices``.

        Raises
        ------
        ConfigError
            ``kind`` missing or not one of ``choices``.
        """
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
        """Line of the value at path ``where`` in the document (or of its nearest parent).

        Parameters
        ----------
        doc : LDict
            The document read.
        where : tuple of str or int
            Keys and list indices from the top down.

        Returns
        -------
        int or None
            The line (1-based); None for a document read without lines.
        """
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

    def number(self, d, k, key, *, default=None, minimum=None, strict=False,
               maximum=None, unit=""):
        """``d[k]`` as a finite float in ``[minimum, maximum]`` (``> minimum`` when
        ``strict``) [``unit``]; ConfigError naming ``key.k`` at its line.

        Parameters
        ----------
        d : LDict
            The mapping read.
        k : str
            The key.
        key : str
            The dotted key of ``d`` (empty at the top level).
        default : any, optional
            Returned as given when ``k`` is absent (default None).
        minimum, maximum : float or None, optional
            Bounds [``unit``]; None for none.
        strict : bool, optional
            Refuse ``minimum`` itself too.
        unit : str, optional
            Unit named in the messages, e.g. ``"N/m"``.

        Returns
        -------
        float or any
            The number [``unit``], or ``default``.

        Raises
        ------
        ConfigError
            Not a number (a bool is none), not finite, or out of bounds.
        """
        if k not in d:
            return default
        v = d[k]
        where = f"{key}.{k}" if key else k
        line = self.line_of(d, k)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(f"must be a number{' [' + unit + ']' if unit else ''}, got "
                             f"{type_name(v)} {show(v)}", line, where)
        try:
            x = float(v)
        except OverflowError:
            x = math.inf
        if not math.isfinite(x):
            raise self.error(f"must be a finite number, got {show(v)}", line, where)
        if minimum is not None and (x < minimum or (strict and x == minimum)):
            raise self.error(f"must be {'>' if strict else '>='} {minimum:g}"
                             f"{' ' + unit if unit else ''}, got {x:g}", line, where)
        if maximum is not None and x > maximum:
            raise self.error(f"must be <= {maximum:g}{' ' + unit if unit else ''}, got "
                             f"{x:g}", line, where)
        return x

    def integer(self, d, k, key, *, default, minimum, maximum, unit):
        """``d[k]`` as a whole number of ``unit`` in ``[minimum, maximum]``; ConfigError
        naming ``key.k`` at its line.

        Parameters
        ----------
        d : LDict
            The mapping read.
        k : str
            The key.
        key : str
            The dotted key of ``d`` (empty at the top level).
        default : any
            Returned as given when ``k`` is absent.
        minimum, maximum : int
            Bounds, both included.
        unit : str
            Unit named in the messages, e.g. ``"samples"``.

        Returns
        -------
        int or any
            The number, or ``default``.

        Raises
        ------
        ConfigError
            Not an int (a bool or a float is none), or out of bounds.
        """
        if k not in d:
            return default
        v = d[k]
        where = f"{key}.{k}" if key else k
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.error(f"must be a whole number of {unit}, got {show(v)}",
                             self.line_of(d, k), where)
        if not minimum <= v <= maximum:
            raise self.error(f"must be between {minimum} and {maximum} {unit}, got {show(v)}",
                             self.line_of(d, k), where)
        return int(v)

    def string(self, d, k, key, default=None):
        """``d[k]`` as a non-empty string; ConfigError naming ``key.k`` at its line.

        Parameters
        ----------
        d : LDict
            The mapping read.
        k : str
            The key.
        key : str
            The dotted key of ``d``.
        default : any, optional
            Returned as given when ``k`` is absent (default None).

        Returns
        -------
        str or any
            The string, or ``default``.

        Raises
        ------
        ConfigError
            Not a string, or empty.
        """
        if k not in d:
            return default
        v = d[k]
        if not isinstance(v, str) or not v:
            raise self.error(f"must be a non-empty string, got {type_name(v)} {show(v)}",
                             self.line_of(d, k), f"{key}.{k}")
        return v

    def choice(self, d, k, key, choices, default=None):
        """``d[k]``, one of ``choices`` (required when ``default`` is None); ConfigError
        listing the choices, naming ``key.k`` at its line.

        Parameters
        ----------
        d : LDict
            The mapping read.
        k : str
            The key.
        key : str
            The dotted key of ``d`` (empty at the top level).
        choices : sequence of str
            The values allowed.
        default : str or None, optional
            Returned when ``k`` is absent; None makes ``k`` required.

        Returns
        -------
        str
            The value, or ``default``.

        Raises
        ------
        ConfigError
            ``k`` missing with no default, or its value not one of ``choices``.
        """
        if k not in d:
            if default is None:
                raise self.error(f"missing required key {show(k)}", self.line_of(d),
                                 f"{key}.{k}" if key else k)
            return default
        v = d[k]
        if not isinstance(v, str) or v not in choices:
            raise self.error(f"unknown value {show(v)}; valid choices: {', '.join(choices)}",
                             self.line_of(d, k), f"{key}.{k}" if key else k)
        return v

    def vector(self, d, k, key, n, default=None, unit="m"):
        """``d[k]`` as a finite float array of shape (n,) [``unit``] (absent: ``default``,
        or zeros); ConfigError naming ``key.k`` at its line for another length or type.

        Parameters
        ----------
        d : LDict
            The mapping read.
        k : str
            The key.
        key : str
            The dotted key of ``d``.
        n : int
            The length asked for (the scene's dimension).
        default : any, optional
            Returned as given when ``k`` is absent; None: zeros of shape (n,).
        unit : str, optional
            Unit named in the messages (default ``"m"``).

        Returns
        -------
        numpy.ndarray or any
            Shape (n,) [``unit``], or ``default``.

        Raises
        ------
        ConfigError
            Not a list of ``n`` numbers, or an entry not finite.
        """
        if k not in d:
            return np.zeros(n) if default is None else default
        v = d[k]
        where = f"{key}.{k}"
        line = self.line_of(d, k)
        if not isinstance(v, list) or len(v) != n or \
                any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in v):
            raise self.error(f"must be a list of {n} numbers [{unit}] (dimension {n}), got "
                             f"{show(v)}", line, where)
        try:
            a = np.array([float(c) for c in v])
        except OverflowError:
            a = np.array([math.inf])
        if not np.all(np.isfinite(a)):
            raise self.error(f"must be finite, got {show(v)}", line, where)
        return a

    def matrix(self, d, k, key, n, default, unit, *, definite):
        """``d[k]`` as a symmetric n x n float array [``unit``]: a number (times I), a list of
        n numbers (diagonal) or n lists of n (a matrix); ``definite`` "positive" or "semi"
        asks for a positive (semi-)definite one; ConfigError naming ``key.k`` at its line.

        Parameters
        ----------
        d : LDict
            The mapping read.
        k : str
            The key.
        key : str
            The dotted key of ``d``.
        n : int
            The size (the scene's dimension).
        default : any
            Returned as given when ``k`` is absent (None: the caller requires it).
        unit : str
            Unit named in the messages, e.g. ``"kg"``, ``"N s/m"``.
        definite : {"positive", "semi"} or None
            Eigenvalues required > 0, >= 0, or not checked.

        Returns
        -------
        numpy.ndarray or any
            Shape (n, n), symmetrised ``(a + a.T) / 2`` [``unit``], or ``default``.

        Raises
        ------
        ConfigError
            Another shape or type, not finite, not symmetric (relative 1e-12), or not
            (semi-)definite as asked.
        """
        if k not in d:
            return default
        v = d[k]
        where = f"{key}.{k}"
        line = self.line_of(d, k)
        shape_msg = (f"must be a number, a list of {n} numbers (diagonal) or {n} lists of "
                     f"{n} numbers [{unit}]")
        try:
            if isinstance(v, bool):
                raise TypeError
            if isinstance(v, (int, float)):
                if not math.isfinite(float(v)):
                    raise self.error(f"must be finite, got {show(v)}", line, where)
                a = float(v) * np.eye(n)
            elif isinstance(v, list) and len(v) == n and all(
                    isinstance(c, (int, float)) and not isinstance(c, bool) for c in v):
                a = np.diag([float(c) for c in v])
            elif isinstance(v, list) and len(v) == n and all(
                    isinstance(r, list) and len(r) == n and all(
                        isinstance(c, (int, float)) and not isinstance(c, bool) for c in r)
                    for r in v):
                a = np.array([[float(c) for c in r] for r in v])
            else:
                raise TypeError
        except (TypeError, OverflowError):
            raise self.error(f"{shape_msg}, got {show(v)}", line, where) from None
        if not np.all(np.isfinite(a)):
            raise self.error(f"must be finite, got {show(v)}", line, where)
        scale = max(float(np.max(np.abs(a))), 1e-300)
        if np.max(np.abs(a / scale - a.T / scale)) > 1e-12:
            raise self.error(f"must be symmetric, got {show(v)}", line, where)
        # eigenvalues of the matrix scaled to entries <= 1 (exact up to round-off): LAPACK's
        # symmetric solver does not converge on entries near the double range (1e308,
        # issue 31), and a + a.T would overflow there
        lam = scale * np.linalg.eigvalsh(0.5 * (a / scale) + 0.5 * (a.T / scale))
        if definite == "positive" and not lam[0] > 0:
            raise self.error(f"must be positive definite (every eigenvalue > 0 {unit}), "
                             f"got eigenvalues {show([float(x) for x in lam])}", line, where)
        if definite == "semi" and lam[0] < 0:
            raise self.error(f"must be positive semi-definite (every eigenvalue >= 0 "
                             f"{unit}), got eigenvalues {show([float(x) for x in lam])}",
                             line, where)
        return 0.5 * a + 0.5 * a.T


def _key_name(parent: str, k: Any) -> str:
    """Dotted key ``parent.k`` for a message (an odd key is :func:`show`-n)."""
    return f"{parent}.{bare_name(k)}" if parent else bare_name(k)


def read_text(path: str | os.PathLike, what: str = "scene file") -> str:
    """The text of a scene file (any dimension), decoded as the YAML reader takes it.

    Parameters
    ----------
    path : str or path-like
        The file.
    what : str
        What it is, for the message (``device file``).

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
    from hapsim.outputs import read_input
    path = os.fspath(path)
    # (a FIFO, /dev/zero: refused, not read)
    return decode_text(read_input(path, what=what), path)
