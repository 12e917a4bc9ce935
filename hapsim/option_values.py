"""Numeric command-line options, each declared with its valid range once.

Every ``float`` or ``int`` option of ``hapsim`` is added with ``type=Number(...)``: the
declaration is the argparse type (which turns the text into a number, or refuses a
non-number with the valid range) and the range check :func:`check_numbers` runs on the
parsed namespace before the command does any work. A bad value (``nan``, ``inf``, a
negative where the range starts at 0) is then a :class:`~hapsim.errors.ConfigError`
keyed by the flag the user typed (``--joints``), with the valid range, exit code 2.
"""

from __future__ import annotations

import argparse
import math

from hapsim.errors import ConfigError

__all__ = ["Number", "check_numbers", "typed_flag"]


class Number:
    """The type and valid range of one numeric option (an argparse ``type``).

    Parameters
    ----------
    kind : {float, int}
        ``int`` also reads a whole number written ``2e4``.
    low, high : float, optional
        Bounds of the valid range (None: unbounded on that side). Always finite:
        ``nan`` and ``inf`` are refused for every option.
    open_low, open_high : bool, optional
        ``value > low`` rather than ``value >= low``; ``value < high`` rather than
        ``value <= high``.
    unit : str, optional
        Unit shown in brackets in messages (``"kg"``, ``"Hz"``).
    """

    def __init__(self, kind=float, *, low: float | None = None, high: float | None = None,
                 open_low: bool = False, open_high: bool = False, unit: str = "") -> None:
        if kind not in (float, int):
            raise TypeError(f"Number kind must be float or int, got {kind!r}")
        self.kind = kind
        self.low = low
        self.high = high
        self.open_low = open_low
        self.open_high = open_high
        self.unit = unit
        # argparse names the type in its own messages: "invalid float value"
        self.__name__ = kind.__name__

    def describe(self) -> str:
        """The valid range in words: ``"a number > 0 [kg]"``, ``"an integer from 0 to 99"``.

        Returns
        -------
        str
        """
        what = "an integer" if self.kind is int else "a finite number"
        lo = f"{'>' if self.open_low else '>='} {self.low:g}" if self.low is not None else ""
        hi = f"{'<' if self.open_high else '<='} {self.high:g}" if self.high is not None else ""
        if lo and hi and not (self.open_low or self.open_high):
            rng = f" from {self.low:g} to {self.high:g}"
        else:
            rng = " and ".join(r for r in (lo, hi) if r)
            rng = f" {rng}" if rng else ""
        unit = f" [{self.unit}]" if self.unit else ""
        return f"{what}{rng}{unit}"

    def __call__(self, text: str):
        """Read the option's text (argparse calls this for each value).

        Parameters
        ----------
        text : str

        Returns
        -------
        float or int
            ``nan`` and ``inf`` are returned as read: :meth:`check` refuses them with the
            flag as the key.

        Raises
        ------
        argparse.ArgumentTypeError
            Not a number (or, for ``int``, not a whole one): the message gives the range.
        """
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"must be {self.describe()}, got {text!r}") from None
        if self.kind is int:
            try:
                return int(text)
            except ValueError:
                pass
            if math.isfinite(value) and value == int(value):
                return int(value)
            if math.isfinite(value):
                raise argparse.ArgumentTypeError(
                    f"must be {self.describe()}, got {text!r}")
        return value

    def ok(self, value) -> bool:
        """Whether ``value`` is in the valid range (finite, within the bounds).

        Parameters
        ----------
        value : float or int

        Returns
        -------
        bool
        """
        if not math.isfinite(value):
            return False
        if self.low is not None and (value <= self.low if self.open_low else value < self.low):
            return False
        return self.high is None or (value < self.high if self.open_high
                                     else value <= self.high)

    def check(self, value, flag: str) -> None:
        """Refuse a value outside the valid range.

        Parameters
        ----------
        value : float, int or list of them
            A parsed value (a list for ``nargs``); None is not checked.
        flag : str
            The option as the user typed it: the error's key.

        Raises
        ------
        ConfigError
            Keyed by ``flag``, with the valid range and the value refused.
        """
        values = value if isinstance(value, (list, tuple)) else [value]
        for v in values:
            if v is not None and not self.ok(v):
                raise ConfigError(f"must be {self.describe()}, got {v!r}", key=flag)


def typed_flag(option_strings, argv) -> str:
    """The option string the user typed (``-n`` or ``--steps``), else the longest.

    Parameters
    ----------
    option_strings : sequence of str
        The action's option strings.
    argv : sequence of str
        The command line as given.

    Returns
    -------
    str
    """
    tokens = {a.split("=", 1)[0] for a in argv if a.startswith("-")}
    given = [o for o in option_strings if o in tokens]
    return given[0] if given else max(option_strings, key=len)


def check_numbers(parser: argparse.ArgumentParser, args: argparse.Namespace,
                  argv=()) -> None:
    """Check every :class:`Number` option of ``parser`` on the parsed ``args``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The (sub-)command's parser.
    args : argparse.Namespace
        What it parsed.
    argv : sequence of str, optional
        The command line, to name the flag as typed.

    Raises
    ------
    ConfigError
        The first value outside its option's range, keyed by the flag.
    """
    for action in parser._actions:
        if isinstance(action.type, Number) and action.option_strings:
            value = getattr(args, action.dest, None)
            action.type.check(value, typed_flag(action.option_strings, argv))
