"""The longest silence on a terminal of every ``hapsim`` command (issue 31 item 3).

Each command of ``tests/test_no_silence.py``'s list runs with its stderr on a
pseudo-terminal; printed: its first output [s from start], its longest gap between two
outputs [s], its exit code, and the bound on the first output (0.7 s + the measured
start-up of ``python -c "import hapsim.cli"`` + 0.3 s). Give the load (``uptime``) beside
the figures.

Usage: ``python tools/silence.py [COMMAND ...]`` (default: all of them).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_no_silence import COMMANDS, silences  # noqa: E402


def main() -> int:
    """Print the table; exit 1 when a command was silent longer than the bounds."""
    names = sys.argv[1:] or list(COMMANDS)
    bad = 0
    with tempfile.TemporaryDirectory() as out:
        print(f"{'command':<22}{'first [s]':>10}{'bound [s]':>10}{'gap [s]':>9}{'exit':>6}")
        for name, (first, gap, code, _text, bound) in silences(names, out).items():
            bad += first > bound or gap > 1.0
            print(f"{name:<22}{first:>10.2f}{bound:>10.2f}{gap:>9.2f}{code:>6}", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
