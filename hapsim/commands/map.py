"""``hapsim map``: the (k, b) grid in the (K, B) plane (Florens et al. Figs. 4, 7-9)."""

from __future__ import annotations

import json

from hapsim.commands._loop_args import loop_from_args, loop_line, loop_parser
from hapsim.errors import ConfigError
from hapsim.option_values import Number


def register(sub) -> None:
    """Add the ``map`` parser to ``sub`` (an argparse sub-parsers action).

    Parameters
    ----------
    sub : argparse._SubParsersAction
    """
    p = loop_parser(
        sub, "map", "draw the felt (k, b) grid in the virtual (K, B) plane",
        "Sweep target (k, b), calibrate each to (K, B) and draw iso-k and iso-b "
        "curves in the (K, B + b0) plane, with the identity grid (dashed: what a "
        "perfect simulator would need) and the exact stability boundary (bold; "
        "it is the b = 0 curve). A bent or sheared grid is a distorted parameter "
        "scale. --paper 7|8|9 reproduces the paper's figures (normalised units, "
        "ideal hold; --hold zoh gives the exact zero-order hold instead).",
        "\nthe damping axis is B + b0 (the paper's Fig. 9 convention).\n"
        "\nexamples:\n  hapsim map --paper 8 --out fig8.png\n"
        "  hapsim map --mass 0.1 --friction 0.5 --rate 1000 --delay 1 --hold zoh "
        "--k-range 100 1500 --b-range 0.5 5 --out map.png --data map.json\n",
        defaults={"friction": None, "delay": None, "hold": None}, require=False)
    p.add_argument("--paper", type=Number(int, low=7, high=9), metavar="{7,8,9}",
                   help="preset of the paper's Fig. 7, 8 or 9 (m = T = 1, ideal hold; "
                        "d = 0/1/1, b0 = 0/0/0.5); loop options override it")
    p.add_argument("--k-range", type=Number(unit="N/m"), nargs=2, metavar=("KMIN", "KMAX"),
                   help="range of felt stiffness k [N/m] (required without --paper)")
    p.add_argument("--b-range", type=Number(unit="N s/m"), nargs=2, metavar=("BMIN", "BMAX"),
                   help="range of felt damping b [N s/m] (required without --paper)")
    p.add_argument("--n", type=Number(int, low=2),
                   default=9, help="iso curves per family (default: 9)")
    p.add_argument("--samples", type=Number(int, low=0), default=80,
                   help="points along each curve (default: 80)")
    p.add_argument("--out", metavar="FIG.png", help="write the figure (needs matplotlib)")
    p.add_argument("--data", metavar="FILE.json", help="write the grid data as JSON")
    p.add_argument("--json", action="store_true", help="print the grid data as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    """Run ``hapsim map``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed ``map`` options.

    Returns
    -------
    int
        0 on success.

    Raises
    ------
    ConfigError
        Bad loop options or ranges; an ``--out`` with no or an unsupported extension; an
        ``--out`` / ``--data`` in a directory that does not exist, or that is a directory
        (all checked before any computation); a file that cannot be written. The CLI turns
        these into a one-line error naming the option and exit code 2.
    """
    import numpy as np
    from hapsim.analysis.grid import grid, paper_preset
    title = None
    if args.paper is not None:
        base, k_range, b_range, title = paper_preset(args.paper)
        for key, attr in (("mass", "mass"), ("friction", "friction"), ("rate", "rate_hz"),
                          ("delay", "delay"), ("hold", "hold")):
            if getattr(args, key) is None:
                setattr(args, key, getattr(base, attr))
        if args.k_range is None:
            args.k_range = k_range
        if args.b_range is None:
            args.b_range = b_range
    else:
        for key in ("mass", "rate", "k_range", "b_range"):
            if getattr(args, key) is None:
                raise ConfigError("is required without --paper",
                                  key="--" + key.replace("_", "-"))
        args.friction = 0.0 if args.friction is None else args.friction
        args.delay = 1 if args.delay is None else args.delay
        args.hold = "zoh" if args.hold is None else args.hold
    loop = loop_from_args(args)
    if args.out:
        from hapsim.plots import check_figure_path
        check_figure_path(args.out, "--out")
    if args.data:
        from hapsim.plots import check_output_path
        check_output_path(args.data, "--data")
        if not args.data.lower().endswith(".json"):     # (any name was taken)
            raise ConfigError(f"the grid data is JSON: give a file ending in .json, got "
                              f"{args.data!r}", key="--data")
    k0, k1 = args.k_range
    b0_, b1 = args.b_range
    if not (0 < k0 < k1):
        raise ConfigError(f"need 0 < KMIN < KMAX, got {k0:g} {k1:g}", key="--k-range")
    if not (0 <= b0_ < b1):
        raise ConfigError(f"need 0 <= BMIN < BMAX, got {b0_:g} {b1:g}", key="--b-range")
    g = grid(loop, np.linspace(k0, k1, args.n), np.linspace(b0_, b1, args.n),
             samples=max(0, args.samples))
    if title is not None and loop.hold != "ideal":
        title += f" ({loop.hold} hold)"
    if args.out:
        from hapsim.plots import plot_grid, save_figure
        try:
            save_figure(plot_grid(g, title=title), args.out)
        except ConfigError as exc:
            raise ConfigError(exc.reason, key="--out") from None
    data = g.to_dict()
    if args.data:
        from hapsim.outputs import write_json
        try:                            # whole or not at all (a full disk left 0 bytes)
            write_json(args.data, data, key="--data")
        except OSError as exc:
            raise ConfigError(f"cannot write {args.data!r}: {exc.strerror or exc}",
                              key="--data") from None
    if args.json:
        print(json.dumps(data))
    else:
        n_ok = int(np.count_nonzero(g.rendered))
        print(loop_line(loop))
        print(f"  {n_ok} of {g.rendered.size} grid targets renderable; "
              f"boundary K_max peaks at {np.nanmax(np.where(np.isfinite(g.boundary_K), g.boundary_K, np.nan)):.6g} N/m")
        if args.out:
            print(f"  figure: {args.out}")
        if args.data:
            print(f"  data:   {args.data}")
    return 0
