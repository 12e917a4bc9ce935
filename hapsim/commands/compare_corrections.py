"""``hapsim compare-corrections``: correction means on the paper's grid, side by side."""

from __future__ import annotations

import argparse
import json
import math

from hapsim.commands._loop_args import add_loop_arguments, loop_from_args
from hapsim.errors import ConfigError
from hapsim.option_values import Number

_DESCRIPTION = """\
Compare the correction means of the virtual element on the paper's grid (Florens, Voda &
Urma Figs. 7-9; their future work, Secs. 6.3 and 7), for one device.

Each correction changes the force law computed from the position samples; each is a linear
loop, so its (K, B) -> felt (k, b) map, calibration and exact stability boundary come from
P K + Q B + R = 0 as for the plain element:

  plain                    F = -K x[n] - B (x[n] - x[n-1]) / T
  velocity_sensor          the damper uses the measured velocity v[n]
  velocity_filter(fc)      the damper uses a first-order low-pass of the backward difference
  prediction(h)            the position extrapolated h samples ahead (default h = d; h = d +
                           1/2 also makes up for the zero-order hold's half sample)
  inertia_compensation(Mc) a negative virtual mass -Mc at the port (Mc < m)
  virtual_coupling(Kc,Bc)  Colgate et al. (1995): a coupling spring-damper to a massless
                           proxy held by the environment (K, B)

Figures of merit per correction:
  stable area     of the exact stable (K, B) region inside a window [0, Kw] x [0, Bw]
                  (and its ratio to the plain element's): "sampled (N)", the trapezoid
                  over N exact K_max(B) (--boundary-points), not certified between them;
  worst distort.  over the usable region of targets (--k-range x --b-range), the worst
                  relative gap between calibrated (K, B + b0) and the target (k, b)
                  ('inf' when some target there cannot be rendered);
  (the passivity controller, nonlinear, is compared in the time domain only: a lockstep run
  at 1.5 times the plain stiffness limit with and without it)
  tangent         whether the grid is tangent to the identity at K, B -> 0: the Jacobian
                  d(k, b)/d(K, B) in normalised units, exact in the limit (the finite one
                  at K T^2/m = B T/m = 1e-3 is shown beside it: a virtual coupling's dk/dK
                  is 0.81 there, 1.00 in the limit), is within 0.05 of the identity. The
                  delay tilts it (db/dK = -(d + 1/2) normalised, whatever the rate: raising
                  the rate does not help, paper's remark on Fig. 8)."""

_EPILOG = """\
examples:
  hapsim compare-corrections --mass 0.1 --friction 0.5 --rate 1000 --delay 1
  hapsim compare-corrections --mass 0.1 --friction 0.5 --rate 1000 --plot corrections.png
  hapsim compare-corrections --mass 0.1 --friction 0.5 --rate 1000 --json

exit codes: 0 success, 2 bad option"""


def register(sub) -> None:
    """Add the ``compare-corrections`` parser to ``sub``.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        The ``hapsim`` sub-parsers.
    """
    p = sub.add_parser(
        "compare-corrections", help="correction means on the paper's grid: which is best",
        description=_DESCRIPTION, epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    add_loop_arguments(p)
    p.add_argument("--k-range", type=Number(float, low=0, open_low=True, unit="N/m"),
                   nargs=2, metavar=("LO", "HI"), default=None,
                   help="usable felt stiffnesses [N/m] (default 5-50 %% of the plain K_max)")
    p.add_argument("--b-range", type=Number(float, low=0, open_low=True, unit="N s/m"),
                   nargs=2, metavar=("LO", "HI"), default=None,
                   help="usable felt dampings [N s/m] (default: damping ratios 0.05-0.5)")
    # (upper bounds: the grid's n^2 calibrations and the boundary's exact limits take
    # ~6 ms and ~14 ms each on a 2-core AMD EPYC; --boundary-points 1e8 ran for days,
    # silently)
    p.add_argument("--n", type=Number(int, low=2, high=200),
                   default=6, help="grid points per axis (default 6; at most 200)")
    p.add_argument("--boundary-points", type=Number(int, low=2, high=10000), default=61,
                   metavar="N", help="points of the exact boundary K_max(B) for the stable "
                                     "area (default 61; at most 10000)")
    p.add_argument("--no-time-domain", action="store_true",
                   help="skip the passivity controller's time-domain comparison")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument("--plot", metavar="FILE", default=None,
                   help="one page: the grid of every correction")
    p.set_defaults(func=run)


def _g(v, spec=".4g"):
    return "inf" if v is not None and math.isinf(v) else format(v, spec)


def table(data: dict) -> str:
    """Markdown table of the figures of merit (docs/stability.md's).

    Parameters
    ----------
    data : dict
        From :func:`hapsim.analysis.compare.compare_corrections`.

    Returns
    -------
    str
        One row per correction: stable area ratio (and how the area was taken), worst
        distortion, ``db/dK`` (normalised) in the limit ``K, B -> 0`` and at the finite
        point of :data:`hapsim.analysis.compare.TANGENCY_AT`, tangent (in the limit).
    """
    lines = [f"| correction | stable area (ratio to plain; {data['stable_area_method']}) | "
             "worst distortion | db/dK (normalised, limit K, B -> 0) | "
             f"db/dK at K T^2/m = B T/m = {data['jacobian_at']['finite_normalised']:g} | "
             "tangent at K, B -> 0 |",
             "|---|---|---|---|---|---|"]
    for r in data["rows"]:
        ratio = r["stable_area_ratio"]
        lines.append(f"| {r['label']} | {_g(ratio, '.3f') if ratio is not None else '-'} | "
                     f"{_g(r['worst_distortion'], '.3g')} | {r['jacobian'][1][0]:+.3f} | "
                     f"{r['jacobian_finite'][1][0]:+.3f} | "
                     f"{'yes' if r['tangent'] else 'no'} |")
    return "\n".join(lines)


def run(args) -> int:
    """Run ``hapsim compare-corrections``.

    Parameters
    ----------
    args : argparse.Namespace

    Returns
    -------
    int
        0.

    Raises
    ------
    ConfigError
        Bad loop option, range or ``--n``.
    """
    from hapsim.analysis.compare import compare_corrections
    from hapsim.progress import Progress

    loop = loop_from_args(args)
    for key, rng in (("--k-range", args.k_range), ("--b-range", args.b_range)):
        if rng is not None and not (0 < rng[0] < rng[1] and math.isfinite(rng[1])):
            raise ConfigError(f"must be 0 < LO < HI, got {rng}", key=key)
    if args.plot:
        from hapsim.plots import check_figure_path
        check_figure_path(args.plot, "--plot")
    with Progress(7, "comparing corrections", "corrections") as bar:
        data = compare_corrections(loop, k_range=args.k_range, b_range=args.b_range,
                                   n=args.n, n_boundary=args.boundary_points, progress=lambda i, n, lab: bar.update(i, n))
    td = None
    if not args.no_time_domain:
        from hapsim.analysis.stability import stability_limit
        B = 0.5 * sum(data["b_range"]) - data["b0"]
        td = passivity_time_domain(loop, 1.5 * stability_limit(loop, B), B)
    if args.plot:
        from hapsim.plots import save_figure
        from hapsim.plots.family import plot_corrections
        save_figure(plot_corrections(data), args.plot)
    if args.json:
        out = {k: v for k, v in data.items() if k != "rows"}
        out["passivity_time_domain"] = td
        out["rows"] = [{k: (None if isinstance(v, float) and math.isinf(v) else v)
                        for k, v in r.items() if k not in ("grid", "boundary")}
                       for r in data["rows"]]
        print(json.dumps(out))
        return 0
    lp = data["loop"]
    print(f"loop: m = {lp['mass']:g} kg, b0 = {lp['friction']:g} N s/m, {lp['rate_hz']:g} Hz, "
          f"d = {lp['delay']}, {lp['hold']}")
    print(f"usable region: k {data['k_range'][0]:.4g} .. {data['k_range'][1]:.4g} N/m, "
          f"b {data['b_range'][0]:.4g} .. {data['b_range'][1]:.4g} N s/m ({data['n']} x "
          f"{data['n']} targets); stable-area window K <= {data['window'][0]:.4g} N/m, "
          f"B <= {data['window'][1]:.4g} N s/m")
    print(table(data))
    if td is not None:
        print(f"passivity controller (nonlinear: time domain only), wall K = {td['K']:.5g} N/m "
              f"= 1.5 K_max, B = {td['B']:.4g} N s/m, {td['duration']:g} s lockstep:")
        for key in ("plain", "passivity_controller"):
            r = td[key]
            print(f"  {key:21s} {'bounded' if r['bounded'] else 'NOT bounded'}: "
                  f"{r['ticks']} ticks, energy excess max {r['energy_excess_max_j']:.4g} J, "
                  f"controller active {r['passivity_samples']} samples, |v| max "
                  f"{r['v_max']:.4g} m/s ({r['stop_reason']})")
    if args.plot:
        print(f"figure: {args.plot}")
    return 0


def passivity_time_domain(loop, K: float, B: float, *, duration: float = 2.0,
                          x0: float = 0.005) -> dict:
    """The passivity controller beside the plain element, in the time domain only.

    Hannaford & Ryu's passivity observer/controller (``safety.passivity_controller`` of
    ``hapsim run``) is nonlinear: it has no P, Q, R and no grid. It is compared by running
    the lockstep daemon on a one-link wall ``(K, B)`` with and without it (energy limit
    raised to 100 J, position limit 10 m, so that only the loop decides).

    Parameters
    ----------
    loop : LoopModel
        Rigid device without correction (mass, friction, rate, delay, hold).
    K, B : float
        Virtual wall [N/m], [N s/m]; typically beyond the plain ``K_max(B)``.
    duration : float, optional
        Run length [s].
    x0 : float, optional
        Initial displacement into the wall [m].

    Returns
    -------
    dict
        ``{"plain": run, "passivity_controller": run}``, each with ``bounded`` (the run
        lasted its duration with no safety stop), ``ticks``, ``stop_reason``,
        ``energy_excess_max_j`` [J], ``passivity_samples`` (samples where the controller
        damped), ``v_max`` [m/s], ``f_max`` [N] and the equivalent felt ``k``, ``b`` of a
        linear fit (for the nonlinear run only an indication; None when not identified).
    """
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import parse_scene

    out = {}
    for key, pc in (("plain", "false"), ("passivity_controller", "true")):
        text = f"""
rate_hz: {loop.rate_hz!r}
masses: [{{name: hand, kind: port}}, {{name: wall, kind: ground}}]
links: [{{name: wall, kind: spring_damper, between: [hand, wall], stiffness: {float(K)!r},
          damping: {float(B)!r}}}]
device: {{mass: {loop.mass!r}, friction: {loop.friction!r}, delay: {loop.delay},
          hold: {loop.hold}, force_limit: 1000000.0}}
excitation: {{x0: {float(x0)!r}}}
safety: {{passivity_controller: {pc}, energy_limit: 100.0, position_limit: 10.0}}
"""
        rep = run_scene(parse_scene(text), transport="inprocess", lockstep=True,
                        handle_signals=False, duration=duration, allow_unstable=True)
        lp, ms = rep["loop"], rep["measured"]
        out[key] = {"bounded": not lp["safety_stop"] and lp["ticks"] >= lp["requested"],
                    "ticks": lp["ticks"], "stop_reason": lp["stop_reason"],
                    "energy_excess_max_j": lp["energy_excess_max_j"],
                    "passivity_samples": lp["passivity_samples"], "v_max": lp["v_max"],
                    "f_max": lp["f_max"], "k": ms.get("k"), "b": ms.get("b")}
    return {"K": float(K), "B": float(B), "duration": float(duration), **out}
