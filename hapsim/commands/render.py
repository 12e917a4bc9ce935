"""``hapsim render``: not implemented yet."""

from __future__ import annotations

import sys


def register(sub) -> None:
    """Add the ``render`` parser to ``sub`` (an argparse sub-parsers action)."""
    p = sub.add_parser("render", help="(not implemented yet)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Report that the command does not exist yet; exit code 2."""
    print("hapsim render: not implemented yet", file=sys.stderr)
    return 2
