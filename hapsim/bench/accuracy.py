"""Chart 1: accuracy of the felt (k, b) against the sample rate, naive and calibrated rendering.

For a target oscillator ``(k, b)`` felt through a device of mass ``m`` and friction ``b0``:

- **naive** rendering sends ``K = k``, ``B = b - b0`` (what a scene author would type);
- **calibrated** rendering sends the ``(K, B)`` of :func:`hapsim.analysis.calibrate` (pole
  placement on the sampled THS, Florens, Voda & Urma Sec. 5).

Each is judged by :func:`hapsim.analysis.render`: the felt ``(k', b')`` of the closed loop
(least damped pair) and the relative error ``max(|k' - k|/k, |b' - b|/b)``. A method fails at a
rate when its loop is unstable (naive) or the target is not renderable (calibrated: no
solution, unstable, or a parasitic mode less damped than the target); the boundary rate is
found by bisection in ``log(rate)`` between the grid points where the verdict flips.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis import LoopModel, calibrate, render

__all__ = ["TARGETS", "DEVICE", "FULL_RATES", "QUICK_RATES", "felt_error", "method_ok",
           "accuracy_vs_rate"]

#: The three targets of chart 1: name -> (k [N/m], b [N s/m]) (b includes the device b0).
TARGETS = {"soft spring": (200.0, 1.0),
           "stiff wall": (20000.0, 4.0),
           "damped wall": (5000.0, 40.0)}
#: Device of chart 1, as configs/wall.yaml: mass [kg], friction b0 [N s/m].
DEVICE = {"mass": 0.1, "friction": 0.5}
#: Rates of the full chart [Hz] (250 Hz - 20 kHz, 25 log-spaced points).
FULL_RATES = tuple(float(r) for r in np.round(np.geomspace(250.0, 20000.0, 25), 1))
#: Rates of ``--quick`` [Hz].
QUICK_RATES = (250.0, 1000.0, 4000.0, 20000.0)


def felt_error(loop: LoopModel, k: float, b: float, method: str) -> tuple[bool, float, float, float]:
    """Render a target with one method and measure what is felt.

    Parameters
    ----------
    loop : LoopModel
        Device, rate, delay and hold.
    k : float > 0
        Target stiffness [N/m].
    b : float > 0
        Target whole damping [N s/m] (device ``b0`` included).
    method : {"naive", "calibrated"}
        ``K = k, B = b - b0``, or :func:`hapsim.analysis.calibrate`.

    Returns
    -------
    ok : bool
        Stable (naive) / renderable (calibrated), with a rendered pair.
    err : float
        ``max(|k' - k|/k, |b' - b|/b)`` [-]; nan when not ``ok``.
    k_felt, b_felt : float
        The felt pair [N/m], [N s/m]; nan when none.
    """
    if method == "naive":
        K, B = k, b - loop.friction
        ok = True
    elif method == "calibrated":
        c = calibrate(loop, k, b)
        K, B, ok = c.K, c.B, c.renderable
    else:
        raise ValueError(f"unknown method {method!r}; valid: naive, calibrated")
    if not (math.isfinite(K) and math.isfinite(B)):
        return False, math.nan, math.nan, math.nan
    r = render(loop, K, B)
    if not (ok and r.stable and math.isfinite(r.k)):
        return False, math.nan, r.k, r.b
    return True, max(abs(r.k - k) / k, abs(r.b - b) / b), r.k, r.b


def method_ok(loop: LoopModel, k: float, b: float, method: str) -> bool:
    """``felt_error(...)[0]``: the method renders the target stably at this loop."""
    return felt_error(loop, k, b, method)[0]


def _boundary(rates, oks, make_loop, k, b, method, iters: int = 14):
    """Lowest rate above which the method works on the whole grid (bisection refined)."""
    oks = list(oks)
    if all(oks):
        return rates[0], "below the grid"
    if not oks[-1]:
        return None, "not reached on the grid"
    i = max(j for j, o in enumerate(oks) if not o)
    lo, hi = math.log(rates[i]), math.log(rates[i + 1])
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if method_ok(make_loop(math.exp(mid)), k, b, method):
            hi = mid
        else:
            lo = mid
    return math.exp(hi), "bisection"


def accuracy_vs_rate(rates=FULL_RATES, targets=None, *, mass: float = DEVICE["mass"],
                     friction: float = DEVICE["friction"], delays=(0, 1, 2),
                     holds=("zoh", "ideal"), methods=("naive", "calibrated")) -> dict:
    """Data of chart 1.

    Parameters
    ----------
    rates : sequence of float
        Sample rates [Hz], increasing.
    targets : mapping of str to (float, float), optional
        ``name -> (k [N/m], b [N s/m])``; :data:`TARGETS` by default.
    mass, friction : float
        Device ``m`` [kg] and ``b0`` [N s/m].
    delays : sequence of int
        Delays ``d`` [samples].
    holds : sequence of {"zoh", "ideal"}
    methods : sequence of {"naive", "calibrated"}

    Returns
    -------
    dict
        JSON-ready: ``device``, ``rates``, ``targets``: list of ``{name, k, b, curves}`` with
        ``curves`` a list of ``{method, delay, hold, ok (list of bool), err, k_felt, b_felt
        (lists, None where not ok), boundary_hz (float or None), boundary_note}``.
    """
    targets = dict(TARGETS if targets is None else targets)
    rates = [float(r) for r in rates]
    out = {"device": {"mass": mass, "friction": friction}, "rates": rates,
           "error": "max(|k'-k|/k, |b'-b|/b), felt (k', b') from analysis.render",
           "targets": []}

    def nz(v):
        return None if not math.isfinite(v) else float(v)

    for name, (k, b) in targets.items():
        curves = []
        for method in methods:
            for hold in holds:
                for d in delays:
                    def make_loop(r, d=d, hold=hold):
                        return LoopModel(mass, friction, r, d, hold)
                    res = [felt_error(make_loop(r), k, b, method) for r in rates]
                    oks = [x[0] for x in res]
                    bnd, note = _boundary(rates, oks, make_loop, k, b, method)
                    curves.append({"method": method, "delay": d, "hold": hold, "ok": oks,
                                   "err": [nz(x[1]) for x in res],
                                   "k_felt": [nz(x[2]) if x[0] else None for x in res],
                                   "b_felt": [nz(x[3]) if x[0] else None for x in res],
                                   "boundary_hz": bnd, "boundary_note": note})
        out["targets"].append({"name": name, "k": k, "b": b, "curves": curves})
    return out
