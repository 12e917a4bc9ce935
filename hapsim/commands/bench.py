"""``hapsim bench``: not implemented yet."""

from __future__ import annotations

import sys


def register(sub) -> None:
    """Add the ``bench`` parser to ``sub`` (an argparse sub-parsers action)."""
    p = sub.add_parser("bench", help="(not implemented yet)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Report that the command does not exist yet; exit code 2."""
    print("hapsim bench: not implemented yet", file=sys.stderr)
    return 2
