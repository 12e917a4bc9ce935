"""The ``hapsim`` command line.

Each sub-command lives in its own module under :mod:`hapsim.commands` and exposes
``register(subparsers)``, which adds its parser and sets ``func`` to a callable
``func(args) -> int`` returning the exit code.

Exit codes (all commands)
-------------------------
0
    Success (for ``check``: the closed loop is stable).
1
    The command ran but the verdict is negative: unstable or unrenderable
    configuration, a device fault, a safety stop.
2
    Bad input: unknown option, invalid scene file, invalid argument value.
130
    Interrupted from the keyboard before any safe shutdown could be done.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from hapsim import __version__
from hapsim.errors import ConfigError, HapsimError

#: Sub-command modules, in the order ``--help`` lists them.
COMMANDS = ("simulate", "render", "calibrate", "stability", "map", "check",
            "run", "mock", "bench", "advise", "identify")


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level argument parser with every sub-command registered.

    Returns
    -------
    argparse.ArgumentParser
        The parser; ``parse_args`` yields a namespace whose ``func`` runs the command.
    """
    parser = argparse.ArgumentParser(
        prog="hapsim",
        description=(
            "Real-time haptic simulator for 1-DoF force-feedback devices. It runs a "
            "mass-interaction scene against a device (or its mock) and tells you the "
            "stiffness k and damping b you actually feel, for the virtual K and B you "
            "simulate (Florens, Voda & Urma's temporary hybrid system)."),
        epilog=(
            "examples:\n"
            "  hapsim run configs/wall.yaml             close the loop on the embedded mock\n"
            "  hapsim simulate configs/string.yaml --steps 2000 --out string.npz\n"
            "  hapsim render --mass 0.1 --friction 0.5 --rate 1000 --delay 1 --hold zoh --K 2000 --B 2\n"
            "  hapsim calibrate --mass 0.1 --friction 0.5 --rate 1000 --delay 1 --hold zoh --k 2000 --b 3\n"
            "\nexit codes: 0 success, 1 negative verdict (unstable, unrenderable, device fault),\n"
            "2 bad input. Run 'hapsim COMMAND --help' for each command."),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"hapsim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        module = importlib.import_module(f"hapsim.commands.{name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the ``hapsim`` command line.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; ``sys.argv[1:]`` when None.

    Returns
    -------
    int
        Exit code (see the module docstring).
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse exits 2 on bad input, 0 on --help
        return int(exc.code or 0)
    try:
        return int(args.func(args))
    except ConfigError as exc:
        print(f"hapsim {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except HapsimError as exc:
        print(f"hapsim {args.command}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"hapsim {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
