"""Numeric command-line options, each declared with its valid range once.

Every ``float`` or ``int`` option of ``hapsim`` is added with ``type=Number(...)``: the
declaration is the argparse type (which turns the text into a number, or refuses a
non-number with the valid range) and the range check :func:`check_numbers` runs on the
parsed namespace before the command does any work. A bad value (``nan``, ``inf``, a
negative where the range starts at 0) is then a :class:`~hapsim.errors.ConfigError`
keyed by the flag the user typed (``--joints``), with the valid range, exit code 2.

The options a command shares with its function of :mod:`hapsim.api` (and the fields of
:class:`hapsim.analysis.loop.LoopModel`) are declared once in :data:`API_OPTIONS`: the
command's parser takes their type from there (:func:`declared`) and the function checks
its keywords with :func:`check_values`, so a bad value gets the same message through
both doors (keyed by the flag, as :func:`hapsim.api.run` keys its options).
"""

from __future__ import annotations

import argparse
import math
import numbers
import os

from hapsim.errors import ConfigError

__all__ = ["Number", "check_numbers", "typed_flag", "API_OPTIONS", "declared", "check_values",
           "option_value", "check_kind", "KINDS"]


def option_value(key: str, value, unit: str = "", *, low: float = -math.inf,
                 low_ok: bool = True, high: float = math.inf, whole: bool = False):
    """A driver's or an emulated board's numeric option (``--protocol-option``,
    ``--mock-option``, a device file's ``protocol_options``), checked where the object
    that takes it is built.

    Parameters
    ----------
    key : str
        The option's name (the error's key).
    value : int or float
        The value given (a word, a bool, NaN or an infinity are refused).
    unit : str
        Its unit, said in the error (``"N"``; empty for a count or a code).
    low, high : float
        The range; ``low`` itself allowed where ``low_ok`` (``high`` always is).
    whole : bool
        Only whole numbers (an id, a code, a level count); 2.5 is refused, 2.0 is 2.

    Returns
    -------
    int or float
        ``value`` as an int (``whole``) or a float.

    Raises
    ------
    hapsim.errors.ConfigError
        ``value`` is no finite number in the range (a whole one where ``whole``): its
        key, the range and what was given named. Before, a device id of NaN was "cannot
        convert float NaN to integer" with no key, 2.5 was taken as 2, and a word was
        "must be real number, not str".
    """
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    try:
        v = float(value) if ok else math.nan
    except OverflowError:               # an int beyond the float range (10**400)
        v = math.inf
    ok = math.isfinite(v) and (v >= low if low_ok else v > low) and v <= high \
        and (not whole or v.is_integer())
    if not ok:
        kind = "a whole number" if whole else "a finite number"
        if math.isfinite(low) and math.isfinite(high):
            rng = f"in {'[' if low_ok else '('}{low:g}, {high:g}]"
        elif math.isfinite(low):
            rng = f"{'>=' if low_ok else '>'} {low:g}"
        elif math.isfinite(high):
            rng = f"<= {high:g}"
        else:
            rng = ""
        raise ConfigError(f"must be {kind}{' ' + rng if rng else ''}"
                          f"{f' [{unit}]' if unit else ''}, got {_shown(value)}", key=key)
    return int(v) if whole else v


def _shown(value, as_float: bool = False) -> str:
    """A refused value as a message shows it: a whole number as it is (as a float with
    ``as_float``, a float option's value), a float's repr, a number too large to write
    out as a float (1e300 was shown with its 301 digits), one beyond even that by its
    count of digits."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return repr(value)
    if isinstance(value, int) and abs(value) < 1e16 and not as_float:
        return repr(value)
    try:
        return repr(float(value))
    except OverflowError:
        return f"an integer of about {int(abs(value).bit_length() * 0.30103) + 1} digits"


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
            if math.isfinite(value):      # as check() says it of a program's 2.5
                raise argparse.ArgumentTypeError(
                    f"must be {self.describe()}, got {self.shown(value)}")
        return value

    def ok(self, value) -> bool:
        """Whether ``value`` is in the valid range (a real number, not a bool; finite; a
        whole one for ``int``; within the bounds).

        Parameters
        ----------
        value : object
            A parsed value, or a keyword a program passed.

        Returns
        -------
        bool
        """
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return False
        if not math.isfinite(value):
            return False
        if self.kind is int and not float(value).is_integer():
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
                raise ConfigError(f"must be {self.describe()}, got {self.shown(v)}", key=flag)

    def shown(self, value) -> str:
        """``value`` as the messages show it: a number as the command line reads it (a
        ``float`` option's ``-1`` is ``-1.0``, an ``int`` one's ``2.0`` is ``2``), so a
        program's keyword and the same value typed get the same message.

        Parameters
        ----------
        value : object

        Returns
        -------
        str
        """
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return repr(value)
        if self.kind is int and abs(value) < 1e16 and float(value).is_integer():
            return repr(int(value))
        return _shown(value, as_float=True)


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


#: The numeric options a command and its :mod:`hapsim.api` function both take, each
#: declared once: ``{function: {parameter: (flag, Number)}}``. ``"loop"`` is
#: :class:`hapsim.analysis.loop.LoopModel`'s fields (``--mass --friction --rate --delay``
#: of ``render``, ``calibrate``, ``stability``, ...; the model keys its errors by its
#: field, the command re-keys them by the flag). The ranges beyond these (the mass and
#: rate ranges, ``b0 T / m``) are the model's, checked through both doors alike.
API_OPTIONS = {
    "loop": {"mass": ("--mass", Number(float, low=0, open_low=True, unit="kg")),
             "friction": ("--friction", Number(float, low=0, unit="N s/m")),
             "rate_hz": ("--rate", Number(float, low=0, open_low=True, unit="Hz")),
             # the analysis is O(d^3): hapsim.analysis.loop.MAX_DELAY
             "delay": ("--delay", Number(float, low=0, high=500, unit="periods"))},
    "render": {"K": ("--K", Number(unit="N/m")), "B": ("--B", Number(unit="N s/m"))},
    "calibrate": {"k": ("--k", Number(float, low=0, open_low=True, unit="N/m")),
                  "b": ("--b", Number(unit="N s/m"))},
    "stability": {"B": ("--B", Number(unit="N s/m"))},
    "family": {"samples": ("--samples", Number(int, low=1)),
               "grid": ("--grid", Number(int, low=2)),
               "seed": ("--seed", Number(int, low=0)),
               "certify": ("--certify-boxes", Number(int, low=0))},
    "identify": {"baud": ("--baud", Number(int, low=1)),
                 "force_limit": ("--force-limit", Number(float, low=0, open_low=True,
                                                         unit="N")),
                 "envelope": ("--envelope", Number(float, low=0, open_low=True, unit="m")),
                 "duration": ("--duration", Number(float, low=0, open_low=True, unit="s")),
                 "rate_hz": ("--rate", Number(float, low=0, open_low=True, unit="Hz")),
                 "max_delay": ("--max-delay", Number(int, low=0)),
                 "seed": ("--seed", Number(int, low=0)),
                 # (high: a device's mass range, hapsim.scene_schema.MASS_RANGE)
                 "added_mass": ("--added-mass", Number(float, low=0, open_low=True,
                                                       high=1e12, unit="kg")),
                 "rt_priority": ("--rt-priority", Number(int, low=0, high=99))},
    "run_nd": {"amplitude": ("--amplitude", Number(float, low=0, open_low=True, unit="m"))},
    "play": {"duration": ("--duration", Number(float, low=0, open_low=True, unit="s")),
             "osc": ("--osc", Number(int, low=0, high=65535)),
             "view": ("--view", Number(int, low=0, high=65535)),
             "ramp": ("--ramp", Number(float, low=0, unit="s")),
             "pluck_every": ("--pluck-every", Number(float, low=0, unit="s")),
             "rt_priority": ("--rt-priority", Number(int, low=0, high=99))},
}


def declared(function: str, parameter: str) -> Number:
    """The declared type and range of one option of :data:`API_OPTIONS` (a parser's
    ``type``).

    Parameters
    ----------
    function : str
        A key of :data:`API_OPTIONS` (``"identify"``, ``"loop"``, ...).
    parameter : str
        The function's keyword (``"force_limit"``).

    Returns
    -------
    Number

    Raises
    ------
    KeyError
        Not declared (a programming error).
    """
    return API_OPTIONS[function][parameter][1]


#: The kinds of value :func:`check_kind` knows, each with its test.
KINDS = {"a number": lambda v: isinstance(v, numbers.Real) and not isinstance(v, bool),
         "True or False": lambda v: isinstance(v, bool),
         "a text": lambda v: isinstance(v, str),
         "a path": lambda v: isinstance(v, (str, os.PathLike)),
         "a mapping of options": lambda v: isinstance(v, dict)}


def check_kind(key: str, value, kind: str, required: bool = False) -> None:
    """Refuse a keyword whose value is not of the kind its flag gives (a program may pass
    anything: a list where a number goes, a number where a path goes).

    Parameters
    ----------
    key : str
        The error's key (the flag).
    value : object
        None is not checked, unless ``required``.
    kind : str
        A key of :data:`KINDS`.
    required : bool
        None is refused too (a flag whose default is False).

    Raises
    ------
    ConfigError
        ``must be KIND, got VALUE``, keyed ``key``.
    """
    if (value is not None or required) and not KINDS[kind](value):
        raise ConfigError(f"must be {kind}, got {value!r}", key=key)


def check_values(function: str, key_by: str = "flag", *, required: bool = False,
                 **values) -> None:
    """Refuse a function's keyword outside its declared range, as the command line does.

    Parameters
    ----------
    function : str
        A key of :data:`API_OPTIONS`.
    key_by : {"flag", "parameter"}, optional
        The error's key: the command's flag (``--force-limit``, as the command line and
        :func:`hapsim.api.run` say it) or the keyword (``mass``, for a model's field).
    required : bool
        None is refused too (a required number); otherwise None is not checked.
    **values
        Keyword -> value.

    Raises
    ------
    ConfigError
        The first value that is no number (a word, a bool, a list: before, ``render(loop,
        None)`` was a TypeError from ``float()``), or outside its range:
        :meth:`Number.check`'s message.
    KeyError
        A keyword not declared for ``function`` (a programming error).
    """
    table = API_OPTIONS[function]
    for name, value in values.items():
        flag, number = table[name]
        key = flag if key_by == "flag" else name
        if value is None and not required:
            continue
        if not isinstance(value, numbers.Real) or isinstance(value, bool):
            raise ConfigError(f"must be {number.describe()}, got {value!r}", key=key)
        number.check(value, key)
