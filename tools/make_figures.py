"""Regenerate the documentation figures: the paper's Table 1 and Figs. 7, 8 and 9.

Usage::

    python tools/make_figures.py --out docs/

writes ``table1_table.md`` (the paper's Table 1 computed,
:func:`hapsim.analysis.table1.table1_experiment`; ``docs/table1.md`` includes it) and
``fig7_ideal.png``, ``fig7_zoh.png``, ..., ``fig9_zoh.png``: the (k, b) grid in the
(K, B + b0) plane for the paper's three configurations (normalised units m = T = 1;
d = 0, 1, 1; b0 = 0, 0, 0.5), once with the paper's idealised sampled mass and once with the
exact zero-order hold. Needs matplotlib (``pip install 'hapsim[plot]'``).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from hapsim.analysis.grid import grid, paper_preset  # noqa: E402
from hapsim.analysis.table1 import table1_experiment, table1_markdown  # noqa: E402


def main(argv=None) -> int:
    """Write Table 1 and the six figures; return 0."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs", help="output directory (default: docs)")
    ap.add_argument("--n", type=int, default=9, help="iso curves per family")
    ap.add_argument("--samples", type=int, default=120, help="points per curve")
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "table1_table.md")
    with open(path, "w") as fh:
        fh.write(table1_markdown(table1_experiment()).rstrip("\n") + "\n")
    print(path)
    from hapsim.plots import plot_grid, save_figure   # matplotlib: the figures only
    for number in (7, 8, 9):
        for hold in ("ideal", "zoh"):
            loop, k_range, b_range, title = paper_preset(number, hold)
            g = grid(loop, np.linspace(*k_range, args.n), np.linspace(*b_range, args.n),
                     samples=args.samples)
            what = ("paper's ideal sampled mass" if hold == "ideal"
                    else "exact zero-order hold")
            path = os.path.join(args.out, f"fig{number}_{hold}.png")
            save_figure(plot_grid(g, title=f"{title} — {what}"), path)
            print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
