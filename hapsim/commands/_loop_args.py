"""Loop options shared by ``render``, ``calibrate``, ``stability`` and ``map``."""

from __future__ import annotations

import argparse
import textwrap

from hapsim.errors import fixed
from hapsim.option_values import declared
# the holds a loop takes (hapsim.analysis.loop.HOLDS, the same tuple as the scene's
# device.hold): from the schema, so that building the parser (hapsim --help) loads no
# analysis; LoopModel is imported where a loop is built
from hapsim.scene_schema import HOLDS

#: Text appended to each command's help: what k/b and K/B are, and the units.
UNITS_HELP = """\
terms:
  K, B  virtual stiffness [N/m] and damping [N s/m] you put in the simulation:
        F[n] = -K x[n-d] - B (x[n-d] - x[n-d-1]) / T
  k, b  stiffness [N/m] and damping [N s/m] the user actually feels: the real mass m
        with the least damped closed-loop pole pair, read as m s^2 + b s + k = 0.
        b is the whole damping (real friction b0 + virtual), k differs from K because
        of sampling, hold and delay (Florens, Voda & Urma's temporary hybrid system).
units: SI throughout. --mass 1 --rate 1 gives the paper's normalised units (m = T = 1).
"""


def para(text: str) -> str:
    """Wrap a help paragraph to 78 columns (the raw formatter does not wrap).

    Parameters
    ----------
    text : str
        Paragraph; runs of white space are collapsed.

    Returns
    -------
    str
    """
    return textwrap.fill(" ".join(text.split()), 78)


def _default(value, usual) -> str:
    """`` (default: VALUE)`` for a help text; for None (only ``hapsim map`` leaves loop
    options unset, for its presets) `` (default: the --paper preset, else USUAL)``."""
    if value is None:
        return f" (default: the --paper preset, else {usual})"
    return f" (default: {value})"


def add_loop_arguments(parser: argparse.ArgumentParser, *, defaults: dict | None = None,
                       require: bool = True) -> None:
    """Add ``--mass --friction --rate --delay --hold`` to ``parser``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
    defaults : dict, optional
        Overrides of the defaults (``mass``, ``friction``, ``rate``, ``delay``, ``hold``).
    require : bool, optional
        Make ``--mass`` and ``--rate`` required when their default is None.
    """
    usual = {"mass": None, "friction": 0.0, "rate": None, "delay": 1, "hold": "zoh"}
    d = {**usual, **(defaults or {})}
    g = parser.add_argument_group("loop (the real side of the THS)")
    g.add_argument("--mass", type=declared("loop", "mass"),
                   default=d["mass"], required=require and d["mass"] is None,
                   metavar="M", help="moving mass m of hand + handle [kg], 1e-12 to 1e12")
    g.add_argument("--friction", type=declared("loop", "friction"),
                   default=d["friction"], metavar="B0",
                   help="real viscous friction b0 [N s/m], >= 0, b0 T/m <= 1e6"
                        + _default(d["friction"], usual["friction"]))
    g.add_argument("--rate", type=declared("loop", "rate_hz"),
                   default=d["rate"], required=require and d["rate"] is None,
                   metavar="HZ", help="sample rate [Hz], 1e-6 to 1e9; period T = 1/rate")
    g.add_argument("--delay", type=declared("loop", "delay"), default=d["delay"], metavar="D",
                   help="periods from reading x to the force computed from it taking "
                        "effect, a real number 0 to 500 (1.3: the force switches 0.3 T into "
                        "the period, the split hold; the analysis is O(d^3))"
                        + _default(d["delay"], usual["delay"]))
    g.add_argument("--hold", choices=HOLDS, default=d["hold"],
                   help="zoh: exact zero-order hold of the force; ideal: the paper's "
                        "idealised sampled mass" + _default(d["hold"], usual["hold"]))


def loop_parser(sub, name: str, help: str, description: str, epilog: str,
                **loop) -> argparse.ArgumentParser:
    """The parser of a command on one loop, with the loop options.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-parsers.
    name, help : str
        The command and its one line in ``hapsim --help``.
    description : str
        Its description, one paragraph (:func:`para`).
    epilog : str
        Shown after :data:`UNITS_HELP` (its examples), as written.
    **loop
        :func:`add_loop_arguments`'s keywords (``defaults``, ``require``).

    Returns
    -------
    argparse.ArgumentParser
    """
    p = sub.add_parser(name, help=help, description=para(description),
                       epilog=UNITS_HELP + epilog,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_loop_arguments(p, **loop)
    return p


def loop_line(loop: LoopModel) -> str:
    """The loop a command reports on, as its first line: ``loop: m=... kg  b0=... N s/m
    ... Hz  d=...  hold=...``."""
    return (f"loop: m={loop.mass:g} kg  b0={loop.friction:g} N s/m  {loop.rate_hz:g} Hz  "
            f"d={loop.delay}  hold={loop.hold}")


def loop_from_args(args) -> LoopModel:
    """Build the :class:`LoopModel` from parsed arguments.

    Parameters
    ----------
    args : argparse.Namespace
        With ``mass`` [kg], ``friction`` [N s/m], ``rate`` [Hz], ``delay`` [samples],
        ``hold``.

    Returns
    -------
    LoopModel

    Raises
    ------
    ConfigError
        With the option name (``--mass`` ...) as key, on an invalid value.
    """
    from hapsim.analysis.loop import LoopModel
    from hapsim.errors import ConfigError
    try:
        return LoopModel(mass=args.mass, friction=args.friction, rate_hz=args.rate,
                         delay=args.delay, hold=args.hold)
    except ConfigError as exc:
        opt = {"mass": "--mass", "friction": "--friction", "rate_hz": "--rate",
               "delay": "--delay", "hold": "--hold"}.get(exc.key, exc.key)
        raise ConfigError(exc.reason, key=opt) from None


def fmt(v) -> str:
    """Format a float for the human tables.

    Parameters
    ----------
    v : float, None or any
        Value to show.

    Returns
    -------
    str
        ``"-"`` for None or NaN, 6 significant digits for a number (a negative zero printed
        as ``0``), ``str(v)`` otherwise.
    """
    if v is None:
        return "-"
    try:
        x = float(v)
    except (TypeError, ValueError):
        return str(v)
    if x != x:
        return "-"
    return f"{x + 0.0:.6g}"


def print_modes(modes, out) -> None:
    """Print a short table of parasitic modes.

    Parameters
    ----------
    modes : list of hapsim.analysis.Mode
        Modes to list (``kind``, ``|z|``, ``f0`` [Hz], damping ratio, ``k`` [N/m], ``b``
        [N s/m] each). Poles at ``z = 0`` (the delay line's dead-beat modes, which have no
        continuous-time equivalent: ``ln 0``) are counted on one line, as ``hapsim check``
        does, not listed with infinite figures.
    out : file-like
        Where to print.
    """
    deadbeat = sum(1 for md in modes if md.z == 0)
    modes = [md for md in modes if md.z != 0]
    if not modes and not deadbeat:
        print("  (no other modes)", file=out)
        return
    if deadbeat:
        print(f"  {deadbeat} dead-beat mode(s) at z = 0 (delay line: settled after one sample)",
              file=out)
    if not modes:
        return
    print(f"  {'kind':<5} {'|z|':>12} {'f0 [Hz]':>11} {'zeta':>9} {'k [N/m]':>11} "
          f"{'b [N s/m]':>11}", file=out)
    for md in modes:
        print(f"  {md.kind:<5} {fixed(abs(md.z), '>12.9f')} {fmt(md.f0_hz):>11} "
              f"{fmt(md.damping_ratio):>9} {fmt(md.k):>11} {fmt(md.b):>11}", file=out)
