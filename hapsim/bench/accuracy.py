"""Chart 1: accuracy of the felt (k, b) against the sample rate, naive and calibrated rendering.

For a target oscillator ``(k, b)`` felt through a device of mass ``m`` and friction ``b0``:

- **naive** rendering sends ``K = k``, ``B = b - b0`` (what a scene author would type);
- **calibrated** rendering sends the ``(K, B)`` of :func:`hapsim.analysis.calibrate` (pole
  placement on the sampled THS, Florens, Voda & Urma Sec. 5).

Each is judged by :func:`hapsim.analysis.render`: the felt ``(k', b')`` of the closed loop
and the relative error ``max(|k' - k|/k, |b' - b|/b)``.

**Which pair is felt.** The felt pair is the *dominant* mode of the closed loop when that mode
is a complex pair: the least damped pair of ``render`` (largest ``|z|``), accepted only if no
other mode (real pole or pair) decays more slowly. This is the criterion ``calibrate`` uses to
call a target renderable ("every other pole decays faster than the target"), applied to the
naive loop. When a real pole is the slowest mode the hand feels a non-oscillating (over-damped)
response dominated by it, and the least damped pair is a faster, secondary mode: no ``(k, b)``
is felt there and the rate is reported as **no felt pair** (a gap in the error curve), never as
an error against that secondary pair. (Example: the damped wall, ZOH, d = 2, naive, at
3.2 kHz: the target's pair has split into two real poles, ``|z| = 0.93`` and ``0.87``; the only
complex pair is a fast delay mode, ``|z| = 0.34``, ``k' = 6.5e6 N/m``.) "Nearest pair to the
target" was rejected as the rule: it would still pick that delay mode when it is the only pair,
and it would hide a large error when the delay has turned the target into a faster, lighter
damped pair that really dominates (d = 1 at 0.9 kHz: 80 Hz, damping ratio 0.22, 4.3x the
target's k).

**Boundaries.** Two different things are recorded per curve:

- ``stability_boundary_hz``: every rate where the loop's spectral radius crosses 1
  (``render(...).stable`` flips; bisection in ``log(rate)`` between grid points); for the naive
  method ``K = k, B = b - b0`` are fixed, so this is the rate at which ``stability_limit(loop,
  B) = k``;
- ``works_from_hz``: the lowest rate above which the method works on the whole grid (stable
  and with a felt pair; for calibrated: renderable), also bisected. Below the stability
  boundary the loop diverges; between the two it is stable but either has no felt pair or
  (calibrated) the target is not renderable.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis import LoopModel, calibrate, render
from hapsim.errors import ConfigError
from hapsim.outputs import finite_or_none

__all__ = ["TARGETS", "DEVICE", "FULL_RATES", "QUICK_RATES", "STATUSES", "felt_pair",
           "felt_status", "method_ok", "accuracy_vs_rate"]

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
#: Per-rate verdicts of a curve: felt pair measured; loop unstable (spectral radius > 1);
#: stable but the slowest mode is real (no felt pair); calibrated target not renderable.
STATUSES = ("ok", "unstable", "no felt pair", "not renderable")
METHODS = ("naive", "calibrated")


def felt_pair(result):
    """The pair the hand feels in a rendered loop, or None.

    Parameters
    ----------
    result : hapsim.analysis.RenderResult
        Output of :func:`hapsim.analysis.render`.

    Returns
    -------
    hapsim.analysis.Mode or None
        ``result.rendered`` (the least damped complex pair) if it is the dominant mode, i.e.
        its decay rate ``-Re s`` [1/s] is no larger than that of every parasitic mode (same
        test as :func:`hapsim.analysis.calibrate`'s renderability); None when the loop has no
        pair or a real pole decays more slowly (see the module docstring).
    """
    pair = result.rendered
    if pair is None:
        return None
    slowest = max((md.s.real for md in result.modes), default=-math.inf)
    return pair if pair.s.real >= slowest else None


def felt_status(loop: LoopModel, k: float, b: float, method: str) -> dict:
    """Render a target with one method and classify what is felt.

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
    dict
        ``status`` (one of :data:`STATUSES`), ``stable`` (bool: spectral radius
        ``<= 1 + STABILITY_TOL``; False without a finite (K, B)), ``spectral_radius`` [-]
        (nan without a finite (K, B)), ``err`` [-] (``max(|k' - k|/k, |b' - b|/b)``, nan unless
        ``status == "ok"``), ``k_felt`` [N/m], ``b_felt`` [N s/m] (the :func:`felt_pair`, nan
        when there is none).

    Raises
    ------
    hapsim.errors.ConfigError
        For an unknown ``method``.
    """
    nan = math.nan
    if method == "naive":
        K, B = k, b - loop.friction
        renderable = True
    elif method == "calibrated":
        c = calibrate(loop, k, b)
        K, B, renderable = c.K, c.B, c.renderable
    else:
        raise ConfigError(f"unknown method {method!r}; valid: {', '.join(METHODS)}",
                          key="method")
    out = {"status": "not renderable", "stable": False, "spectral_radius": nan, "err": nan,
           "k_felt": nan, "b_felt": nan}
    if not (math.isfinite(K) and math.isfinite(B)):
        return out
    r = render(loop, K, B)
    pair = felt_pair(r)
    out.update(stable=bool(r.stable), spectral_radius=r.spectral_radius)
    if pair is not None:
        out.update(k_felt=pair.k, b_felt=pair.b)
    if not renderable:
        return out
    if not r.stable:
        out["status"] = "unstable"
    elif pair is None:
        out["status"] = "no felt pair"
    else:
        out.update(status="ok", err=max(abs(pair.k - k) / k, abs(pair.b - b) / b))
    return out


def method_ok(loop: LoopModel, k: float, b: float, method: str) -> bool:
    """Whether a method renders a target at this loop with a felt pair.

    Parameters
    ----------
    loop : LoopModel
        Device, rate, delay and hold.
    k : float > 0
        Target stiffness [N/m].
    b : float > 0
        Target whole damping [N s/m] (device ``b0`` included).
    method : {"naive", "calibrated"}
        See :func:`felt_status`.

    Returns
    -------
    bool
        ``felt_status(...)["status"] == "ok"``: naive: the loop is stable and its dominant mode
        is a complex pair; calibrated: the target is renderable
        (:func:`hapsim.analysis.calibrate`).

    Raises
    ------
    hapsim.errors.ConfigError
        For an unknown ``method``.
    """
    return felt_status(loop, k, b, method)["status"] == "ok"


def _bisect_rate(lo_hz: float, hi_hz: float, pred, iters: int = 40) -> float:
    """Rate in ``[lo_hz, hi_hz]`` where ``pred`` flips (``pred(lo) != pred(hi)``), bisected in
    ``log(rate)`` to a relative ~1e-12 of the interval."""
    lo, hi = math.log(lo_hz), math.log(hi_hz)
    p_lo = pred(lo_hz)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if pred(math.exp(mid)) == p_lo:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


def _stability_crossings(rates, stables, make_loop, K_of):
    """Every spectral-radius-1 crossing between grid points where ``stable`` flips (located
    on ``max |z| < 1`` strictly, to the bisection's ~1e-12 relative)."""
    out = []
    for i in range(len(rates) - 1):
        if stables[i] is None or stables[i + 1] is None or stables[i] == stables[i + 1]:
            continue

        def stable_at(r):  # strictly |z| < 1: the crossing itself, not the tolerance band
            KB = K_of(make_loop(r))
            return KB is not None and render(make_loop(r), *KB).spectral_radius < 1.0
        f = _bisect_rate(rates[i], rates[i + 1], stable_at)
        out.append({"rate_hz": f, "stable_above": bool(stables[i + 1])})
    return out


def _works_from(rates, oks, make_loop, k, b, method, iters: int = 30):
    """Lowest rate above which the method works on the whole grid (bisection refined)."""
    oks = list(oks)
    if all(oks):
        return rates[0], "below the grid"
    if not oks[-1]:
        return None, "not reached on the grid"
    i = max(j for j, o in enumerate(oks) if not o)
    f = _bisect_rate(rates[i], rates[i + 1],
                     lambda r: method_ok(make_loop(r), k, b, method), iters)
    return f, "bisection"


def accuracy_vs_rate(rates=FULL_RATES, targets=None, *, mass: float = DEVICE["mass"],
                     friction: float = DEVICE["friction"], delays=(0, 1, 2),
                     holds=("zoh", "ideal"), methods=METHODS) -> dict:
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
        JSON-ready: ``device``, ``rates``, ``felt_pair`` (the rule), ``targets``: list of
        ``{name, k, b, curves}`` with ``curves`` a list of ``{method, delay, hold}`` and, per
        rate, ``status`` (:data:`STATUSES`), ``ok`` (bool, ``status == "ok"``), ``stable``,
        ``spectral_radius``, ``err``, ``k_felt``, ``b_felt`` (None where not ``ok``); and
        ``stability_boundary_hz`` (list of ``{rate_hz, stable_above}``: spectral radius 1),
        ``works_from_hz`` (float or None) with ``works_from_note``.

    Raises
    ------
    hapsim.errors.ConfigError
        For an unknown method, or a device / rate / delay / hold :class:`LoopModel` refuses.
    """
    targets = dict(TARGETS if targets is None else targets)
    rates = [float(r) for r in rates]
    out = {"device": {"mass": mass, "friction": friction}, "rates": rates,
           "error": "max(|k'-k|/k, |b'-b|/b), felt (k', b') from analysis.render",
           "felt_pair": "the least damped complex pair of the closed loop, only when it is "
                        "the dominant mode (no real pole decays more slowly); otherwise "
                        "'no felt pair'",
           "targets": []}
    nz = finite_or_none
    for name, (k, b) in targets.items():
        curves = []
        for method in methods:
            for hold in holds:
                for d in delays:
                    def make_loop(r, d=d, hold=hold):
                        return LoopModel(mass, friction, r, d, hold)

                    def K_of(loop, method=method, k=k, b=b):
                        if method == "naive":
                            return k, b - loop.friction
                        c = calibrate(loop, k, b)
                        ok = math.isfinite(c.K) and math.isfinite(c.B)
                        return (c.K, c.B) if ok else None
                    res = [felt_status(make_loop(r), k, b, method) for r in rates]
                    oks = [x["status"] == "ok" for x in res]
                    stables = [x["stable"] if math.isfinite(x["spectral_radius"]) else None
                               for x in res]
                    works, note = _works_from(rates, oks, make_loop, k, b, method)
                    curves.append({
                        "method": method, "delay": d, "hold": hold,
                        "status": [x["status"] for x in res], "ok": oks,
                        "stable": stables,
                        "spectral_radius": [nz(x["spectral_radius"]) for x in res],
                        "err": [nz(x["err"]) for x in res],
                        "k_felt": [nz(x["k_felt"]) if o else None for x, o in zip(res, oks)],
                        "b_felt": [nz(x["b_felt"]) if o else None for x, o in zip(res, oks)],
                        "stability_boundary_hz": _stability_crossings(rates, stables,
                                                                      make_loop, K_of),
                        "works_from_hz": works, "works_from_note": note})
        out["targets"].append({"name": name, "k": k, "b": b, "curves": curves})
    return out
