"""``hapsim check``: not implemented yet."""

from __future__ import annotations

import sys


def register(sub) -> None:
    """Add the ``check`` parser to ``sub`` (an argparse sub-parsers action)."""
    p = sub.add_parser("check", help="(not implemented yet)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Report that the command does not exist yet; exit code 2."""
    print("hapsim check: not implemented yet", file=sys.stderr)
    return 2
