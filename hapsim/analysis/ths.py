"""Rendered (k, b), calibration (k, b) -> (K, B) and the exact stability boundary.

Florens, Voda & Urma, Secs. 5-6; docs/design.md, 'The THS'. All computations use the
dimensionless pieces of :mod:`hapsim.analysis.loop` in ``w = z - 1``, never expanded (the
delay factor ``(1 + w)^(d+1)`` is evaluated as a power, reduced modulo a quadratic by binary
powering,
or found through the companion matrix in ``z``): the same precision at every delay.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.analysis.loop import (STABILITY_TOL, LoopModel, char_parts, roots_w, scaled_gains,
                                  char_eval)
from hapsim.analysis.modes import Mode, mode_from_pole, modes_from_poles, rendered_pair
from hapsim.errors import ConfigError

__all__ = ["RenderResult", "CalibrationResult", "render", "calibrate", "stability_limit",
           "damping_limits", "circle_scan_points",
           "stability_boundary", "published_limits"]


def _f(v):
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _modes_of(loop: LoopModel, w: np.ndarray) -> list[Mode]:
    return modes_from_poles(1.0 + w, loop.mass, loop.period, w=w)


def _log_rho(w: np.ndarray) -> float:
    """``ln max |1 + w|``, accurate near the unit circle."""
    wr, wi = w.real, w.imag
    arg = 2.0 * wr + wr * wr + wi * wi
    with np.errstate(divide="ignore"):
        return float(np.max(0.5 * np.log1p(np.maximum(arg, -1.0))))


def log_abs_w(w: complex) -> float:
    """``ln |1 + w|`` = ``ln |z|`` of a pole given as ``w = z - 1``, accurate near the unit
    circle.

    Parameters
    ----------
    w : complex

    Returns
    -------
    float
        ``-inf`` at ``w = -1``.
    """
    arg = 2.0 * w.real + w.real * w.real + w.imag * w.imag
    return 0.5 * math.log1p(arg) if arg > -1.0 else -math.inf


# --------------------------------------------------------------------------- render

@dataclass(frozen=True)
class RenderResult:
    """What the user feels for a virtual ``(K, B)``: the rendered oscillator.

    Attributes
    ----------
    K, B : float
        The virtual stiffness [N/m] and damping [N s/m] analysed.
    k : float
        Rendered stiffness ``m |s|^2`` of the least damped complex pair [N/m]; nan if the
        loop has no complex pair.
    b : float
        Rendered damping ``-2 m Re s`` [N s/m]: the whole THS damping (real ``b0`` plus
        virtual, as deformed by sampling and delay); nan if no complex pair.
    f0_hz : float
        Natural frequency ``sqrt(k/m) / (2 pi)`` [Hz]; nan if no complex pair.
    damping_ratio : float
        ``b / (2 sqrt(k m))`` [-]; nan if no complex pair.
    stable : bool
        True iff every closed-loop pole has ``|z| <= 1 + STABILITY_TOL``
        (:data:`hapsim.analysis.loop.STABILITY_TOL`, the tolerance ``check_scene`` uses):
        marginal loops count as stable.
    spectral_radius : float
        ``max |z|`` over the closed-loop poles [-].
    marginal : bool
        ``|spectral_radius - 1| <= STABILITY_TOL``: the least damped mode sits on the unit
        circle up to round-off and never decays (a lossless loop, e.g. the paper's
        centred-difference oscillator: ideal hold, ``d = 0``, ``b0 = B = 0``,
        ``0 < K < 4 m / T^2``). Implies ``stable``.
    modes : list of Mode
        The parasitic modes: every mode except the rendered pair, least damped first.
    rendered : Mode or None
        The rendered pair itself.
    note : str
        Empty, or why ``k``/``b`` are nan.
    """

    K: float
    B: float
    k: float
    b: float
    f0_hz: float
    damping_ratio: float
    stable: bool
    spectral_radius: float
    modes: list = field(default_factory=list)
    rendered: Mode | None = None
    note: str = ""
    marginal: bool = False

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite floats become ``None``).

        Returns
        -------
        dict
            Keys ``K`` [N/m], ``B`` [N s/m], ``k`` [N/m], ``b`` [N s/m], ``f0_hz`` [Hz],
            ``damping_ratio``, ``stable``, ``marginal``, ``spectral_radius``, ``rendered``
            (:meth:`Mode.to_dict` or None), ``modes`` (list), ``note``.
        """
        return {"K": _f(self.K), "B": _f(self.B), "k": _f(self.k), "b": _f(self.b),
                "f0_hz": _f(self.f0_hz), "damping_ratio": _f(self.damping_ratio),
                "stable": bool(self.stable), "marginal": bool(self.marginal),
                "spectral_radius": _f(self.spectral_radius),
                "rendered": None if self.rendered is None else self.rendered.to_dict(),
                "modes": [md.to_dict() for md in self.modes], "note": self.note}


def render(loop: LoopModel, K: float, B: float = 0.0) -> RenderResult:
    """Inverse map ``(K, B) -> (k, b)``: the oscillator the user feels.

    Parameters
    ----------
    loop : LoopModel
        The simulator configuration.
    K : float
        Virtual stiffness [N/m].
    B : float, optional
        Virtual damping [N s/m].

    Returns
    -------
    RenderResult
        Rendered pair = least damped complex pair of the closed loop (largest ``|z|``);
        ``s = ln(z)/T``, ``k = m|s|^2``, ``b = -2 m Re s`` (Florens et al. Sec. 5,
        docs/design.md, 'The inverse map'). Other poles are reported as parasitic modes.

    Raises
    ------
    ConfigError
        If ``K`` or ``B`` is not finite, or ``|K| T^2/m`` or ``|B| T/m`` exceeds
        :data:`hapsim.analysis.loop.MAX_PRODUCT`.
    """
    for key, v in (("K", K), ("B", B)):
        if not math.isfinite(float(v)):
            raise ConfigError(f"must be finite, got {v!r}", key=key)
    kappa, beta = scaled_gains(loop, K, B)
    w = roots_w(loop, kappa, beta)
    modes = _modes_of(loop, w)
    pair = rendered_pair(modes)
    rho = float(np.max(np.abs(1.0 + w)))
    # Same verdict as check_scene: within STABILITY_TOL of the unit circle the sign of
    # |z| - 1 is round-off, so such a loop is marginal and counted as stable.
    stable = rho <= 1.0 + STABILITY_TOL
    marginal = abs(rho - 1.0) <= STABILITY_TOL
    if pair is None:
        return RenderResult(K=float(K), B=float(B), k=math.nan, b=math.nan, f0_hz=math.nan,
                            damping_ratio=math.nan, stable=stable, spectral_radius=rho,
                            modes=modes, rendered=None, marginal=marginal,
                            note="the closed loop has no complex pair: nothing oscillates, "
                                 "no (k, b) is rendered")
    others = [md for md in modes if md is not pair]
    return RenderResult(K=float(K), B=float(B), k=pair.k, b=pair.b, f0_hz=pair.f0_hz,
                        damping_ratio=pair.damping_ratio, stable=stable, spectral_radius=rho,
                        modes=others, rendered=pair, marginal=marginal)


# --------------------------------------------------------------------------- calibrate

@dataclass(frozen=True)
class CalibrationResult:
    """Virtual ``(K, B)`` that renders a target ``(k, b)``, and whether it really does.

    Attributes
    ----------
    k, b : float
        The target stiffness [N/m] and whole THS damping [N s/m].
    K, B : float
        Virtual stiffness [N/m] and damping [N s/m] placing two closed-loop poles on the
        target's; nan if the equations have no solution.
    renderable : bool
        True iff the solution exists, the loop is stable and every other pole decays faster
        than the target (``|z_other| < |z_target|``), i.e. the target is what is felt.
    reason : str
        Human explanation (names the offending pole when not renderable).
    spectral_radius : float
        ``max |z|`` of the calibrated closed loop [-]; nan without a solution.
    modes : list of Mode
        The parasitic modes (every pole except the two target ones), least damped first.
    target : Mode or None
        The target pair (``kind="pair"``) or, for an over-damped target, its slower pole.
    """

    k: float
    b: float
    K: float
    B: float
    renderable: bool
    reason: str
    spectral_radius: float
    modes: list = field(default_factory=list)
    target: Mode | None = None

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite floats become ``None``).

        Returns
        -------
        dict
            Keys ``k`` [N/m], ``b`` [N s/m], ``K`` [N/m], ``B`` [N s/m], ``renderable``,
            ``reason``, ``spectral_radius``, ``target`` (:meth:`Mode.to_dict` or None),
            ``modes`` (list).
        """
        return {"k": _f(self.k), "b": _f(self.b), "K": _f(self.K), "B": _f(self.B),
                "renderable": bool(self.renderable), "reason": self.reason,
                "spectral_radius": _f(self.spectral_radius),
                "target": None if self.target is None else self.target.to_dict(),
                "modes": [md.to_dict() for md in self.modes]}


def _expm1c(x: complex) -> complex:
    """``e^x - 1`` for complex ``x``, accurate for small ``|x|``."""
    a, b = x.real, x.imag
    s2 = math.sin(0.5 * b)
    return complex(math.expm1(a) * math.cos(b) - 2.0 * s2 * s2, math.exp(a) * math.sin(b))


def _target_w(loop: LoopModel, k: float, b: float):
    """Target poles as ``w = z - 1`` and the monic quadratic ``w^2 + c1 w + c0``."""
    m, T = loop.mass, loop.period
    disc = b * b - 4.0 * m * k
    if disc < 0:
        s = complex(-b / (2 * m), math.sqrt(-disc) / (2 * m))
        w1 = _expm1c(s * T)
        w = (w1, w1.conjugate())
        c1 = -2.0 * w1.real
        c0 = w1.real * w1.real + w1.imag * w1.imag
        return w, c1, c0, "pair", s
    r = math.sqrt(disc)
    s_fast = (-b - r) / (2 * m) if b >= 0 else (-b + r) / (2 * m)
    s_slow = k / (m * s_fast)  # product of roots = k/m (no cancellation)
    w1, w2 = math.expm1(s_slow * T), math.expm1(s_fast * T)
    return (complex(w1), complex(w2)), -(w1 + w2), w1 * w2, "real", complex(s_slow)


def _divmod_quadratic(p, c1: float, c0: float):
    """Quotient and remainder ``(r1, r0)`` of ``p`` (highest first) by ``w^2 + c1 w + c0``."""
    p = np.asarray(p, dtype=float)
    if p.size < 3:
        p = np.concatenate([np.zeros(3 - p.size), p])
    q = np.zeros(p.size - 2)
    rem = p.copy()
    for i in range(q.size):
        q[i] = rem[i]
        rem[i + 1] -= c1 * q[i]
        rem[i + 2] -= c0 * q[i]
    return q, rem[-2], rem[-1]


def _mulmod(a, b, c1: float, c0: float):
    """``(a1 w + a0)(b1 w + b0)`` modulo ``w^2 + c1 w + c0``, as ``(r1, r0)``."""
    hi = a[0] * b[0]
    return a[0] * b[1] + a[1] * b[0] - hi * c1, a[1] * b[1] - hi * c0


def _powmod(e: int, c1: float, c0: float):
    """``(1 + w)^e`` modulo ``w^2 + c1 w + c0`` by binary powering, as ``(r1, r0)``.

    The remainder interpolates ``z^e`` at the two roots, so it stays O(1) for poles inside
    the unit circle whatever ``e`` (the expanded ``(1 + w)^e`` does not).
    """
    out, base = (0.0, 1.0), (1.0, 1.0)
    while e:
        if e & 1:
            out = _mulmod(out, base, c1, c0)
        base = _mulmod(base, base, c1, c0)
        e >>= 1
    return out


def calibrate_core(loop: LoopModel, k: float, b: float):
    """Solve the characteristic equation for the gains that put a pole pair at the felt
    target and return the other poles (Florens, Voda & Urma eq. (4), inverted).

    Parameters
    ----------
    loop : LoopModel
    k, b : float
        Felt target stiffness [N/m] and damping [N s/m].

    Returns
    -------
    tuple or None
        ``(kappa, beta, others, w_t, kind, s_t)``: the gains ``K T^2 / m``, ``B T / m``,
        the other closed-loop poles and the target's in ``w = z - 1`` (ndarray of
        complex), the target's kind and its continuous pole; None when the target's
        equations are singular.
    """
    w_t, c1, c0, kind, s_t = _target_w(loop, k, b)
    P, Q, D, e = char_parts(loop)
    _, p1, p0 = _divmod_quadratic(P, c1, c0)
    _, q1, q0 = _divmod_quadratic(Q, c1, c0)
    _, d1, d0 = _divmod_quadratic(D, c1, c0)
    r1, r0 = _mulmod(_powmod(e, c1, c0), (d1, d0), c1, c0)
    A = np.array([[p1, q1], [p0, q0]])
    rhs = -np.array([r1, r0])
    det = p1 * q0 - q1 * p0
    scale = max(abs(p1 * q0), abs(q1 * p0), 1e-300)
    if abs(det) <= 1e-13 * scale:
        return None
    kappa, beta = np.linalg.solve(A, rhs)
    others = list(roots_w(loop, float(kappa), float(beta)))
    for wt in w_t:  # the two target poles are among the closed-loop poles: take them out
        if others:
            w = others.pop(int(np.argmin([abs(w - wt) for w in others])))
            if complex(wt).imag == 0 and w.imag != 0 and others:
                # a real target pole inside a numerically multiple root (e.g. a target
                # pole e^(sT) that underflows onto the delay line's poles at z = 0): the
                # eigensolver split the multiple root into a pair of size ~sqrt(eps), and
                # one member went with the target. The rest are the roots of the real
                # quotient, so the removed member's partner is real too: its imaginary
                # part was that round-off (issue 31, a fuzzed felt target {k: 1e-12,
                # b: 1e6} left it unpaired: "poles are not closed under conjugation").
                i = int(np.argmin([abs(v - np.conj(w)) for v in others]))
                others[i] = complex(others[i].real, 0.0)
    return float(kappa), float(beta), np.array(others, dtype=complex), w_t, kind, s_t


def calibrate(loop: LoopModel, k: float, b: float) -> CalibrationResult:
    """Forward map ``(k, b) -> (K, B)``: virtual parameters rendering a target oscillator.

    Parameters
    ----------
    loop : LoopModel
        The simulator configuration.
    k : float > 0
        Target stiffness [N/m] (what the user should feel).
    b : float
        Target whole THS damping [N s/m] (real ``b0`` included).

    Returns
    -------
    CalibrationResult
        ``renderable=False`` with a reason when the equations have no solution, the target
        is above the Nyquist frequency, undamped, or when another closed-loop pole lies on or
        outside the unit circle or is less damped than the target.

    Raises
    ------
    ConfigError
        If ``k <= 0`` or ``k``, ``b`` are not finite, or ``k T^2/m`` or ``|b| T/m`` exceeds
        :data:`hapsim.analysis.loop.MAX_PRODUCT`.

    Notes
    -----
    Poles of ``m s^2 + b s + k`` (m: the loop mass) are mapped by ``z = e^(sT)`` and placed
    on the closed loop ``P K + Q B + R = 0`` (Florens et al. Sec. 5, Fig. 4;
    docs/design.md, 'The forward map'). Rather than evaluating at one complex root, the
    characteristic polynomial is
    required to be divisible by the real quadratic ``(w - w1)(w - w2)``, ``w = z - 1``: the
    remainder is linear in ``(K, B)`` and gives two real equations. This single form covers
    the under-damped pair, the two real poles of an over-damped target and the double pole
    of a critically damped one (where it equals the value + derivative conditions), without
    perturbation. The other poles are the roots of the exact quotient (deflation).
    """
    k = float(k)
    b = float(b)
    if not (math.isfinite(k) and math.isfinite(b)):
        raise ConfigError(f"target must be finite, got k={k!r}, b={b!r}", key="k")
    if k <= 0:
        raise ConfigError(f"target stiffness must be > 0 [N/m], got {k!r}", key="k")
    m, T = loop.mass, loop.period
    nan = math.nan
    scaled_gains(loop, k, b, keys=("k", "b"))

    def fail(reason, K=nan, B=nan, rho=nan, modes=(), target=None):
        return CalibrationResult(k=k, b=b, K=K, B=B, renderable=False, reason=reason,
                                 spectral_radius=rho, modes=list(modes), target=target)

    disc = b * b - 4 * m * k
    if disc < 0 and math.sqrt(-disc) / (2 * m) * T >= math.pi:
        fN = 0.5 / T
        return fail(f"target damped frequency {math.sqrt(-disc) / (4 * math.pi * m):.6g} Hz "
                    f"is at or above the Nyquist frequency {fN:.6g} Hz")
    core = calibrate_core(loop, k, b)
    if core is None:
        return fail("the calibration equations are singular for this target: no (K, B) "
                    "places a closed-loop pole pair there")
    kappa, beta, others, w_t, kind, s_t = core
    K, B = kappa * m / (T * T), beta * m / T
    zt = 1.0 + np.asarray(w_t)
    if kind == "pair":
        target = mode_from_pole(zt[0], m, T, "pair", w_t[0])
    else:
        target = mode_from_pole(zt[0], m, T, "real", w_t[0])
    modes = _modes_of(loop, others) if others.size else []
    all_w = np.concatenate([np.asarray(w_t), others])
    rho = float(np.max(np.abs(1.0 + all_w)))
    log_t = min(log_abs_w(w) for w in w_t)
    if b <= 0:
        return fail(f"target damping b = {b:.6g} N s/m is not positive: the target "
                    f"oscillator does not decay (spectral radius {rho:.12g})",
                    K, B, rho, modes, target)
    worst = None
    for w in others:
        z = 1.0 + w
        lz = log_abs_w(w)
        if worst is None or lz > worst[0]:
            worst = (lz, complex(z))
    if worst is not None:
        lz, z = worst
        where = (f"z = {z.real:.9g}{z.imag:+.9g}j (|z| = {abs(z):.12g}, "
                 f"{abs(cmath.log(z).imag) / (2 * math.pi * T) if z != 0 else 0:.6g} Hz)")
        if lz >= 0:
            return fail(f"unstable: the parasitic pole {where} is on or outside the unit "
                        f"circle; spectral radius {rho:.12g}", K, B, rho, modes, target)
        if lz >= log_t:
            return fail(f"the parasitic pole {where} is less damped than the target "
                        f"(|z_target| = {math.exp(log_t):.12g}); the user would feel it, not "
                        f"the target; spectral radius {rho:.12g}", K, B, rho, modes, target)
    return CalibrationResult(k=k, b=b, K=K, B=B, renderable=True,
                             reason=f"renderable: every other pole decays faster than the "
                                    f"target; spectral radius {rho:.12g}",
                             spectral_radius=rho, modes=modes, target=target)


# --------------------------------------------------------------------------- stability

def _roots_outside(loop: LoopModel, kappa: float, beta: float) -> int | None:
    """Number of closed-loop poles outside the unit circle by the argument principle.

    The winding of ``f(e^{i theta})`` (:func:`hapsim.analysis.loop.char_eval`, unexpanded)
    round the circle counts the poles inside; ``f`` has real coefficients, so half a turn
    (``theta`` in ``[0, pi]``) gives half the count. O(d) evaluations (64 points per turn of
    ``z^e`` plus a geometric grid down to 1e-9 for the poles near ``z = 1``; every step that
    turns by more than pi/4 is bisected, up to 40 times), against O(d^3) for the
    eigenvalues. Returns None when it cannot be trusted (a pole on or within ~1e-12 of the
    circle: the caller then takes the eigenvalues).
    """
    P, Q, D, e = char_parts(loop)
    # degree of the characteristic polynomial: e + 2 for the plain loop, deg R for a
    # hand or a correction (e = 0 there, R expanded)
    deg = max(len(np.trim_zeros(np.asarray(D, float), "f")) - 1 + e,
              len(np.trim_zeros(np.asarray(P, float), "f")) - 1,
              len(np.trim_zeros(np.asarray(Q, float), "f")) - 1)
    n = max(2048, 64 * (e + 1))
    th = np.unique(np.concatenate([[0.0], np.geomspace(1e-9, math.pi, n // 2),
                                   np.linspace(0.0, math.pi, n + 1)]))

    def ev(t):
        return char_eval(loop, kappa, beta, -2.0 * np.sin(0.5 * t) ** 2 + 1j * np.sin(t))

    f = ev(th)
    for _ in range(40):
        if not np.all(np.isfinite(f)) or np.any(f == 0):
            return None
        step = np.angle(f[1:] / f[:-1])
        big = np.flatnonzero(np.abs(step) > 0.25 * math.pi)
        if big.size == 0:
            inside = float(np.sum(step)) / math.pi
            k = round(inside)
            return None if abs(inside - k) > 1e-6 else deg - k
        mid = 0.5 * (th[big] + th[big + 1])
        if np.any(mid - th[big] < 1e-13):
            return None
        th = np.insert(th, big + 1, mid)
        f = np.insert(f, big + 1, ev(mid))
    return None


def _stable_at(loop: LoopModel, kappa: float, beta: float) -> bool:
    """Every pole strictly inside the unit circle (argument principle, else eigenvalues)."""
    out = _roots_outside(loop, kappa, beta)
    if out is not None:
        return out == 0
    return _log_rho(roots_w(loop, kappa, beta)) < 0.0


def brent_root(f, a: float, b: float, *, xtol: float = 1e-12, rtol: float = 1e-15,
               maxiter: int = 200) -> float:
    """A root of ``f`` in ``[a, b]`` by Brent's method (bisection, secant and inverse
    quadratic interpolation).

    Written here so that the stability limit, which every ``hapsim run`` reports, needs no
    ``scipy.optimize`` (its import costs ~0.3 s of start-up).

    Parameters
    ----------
    f : callable
        ``f(x) -> float``, continuous on ``[a, b]``.
    a, b : float
        Bracket; ``f(a)`` and ``f(b)`` of opposite signs (or one of them 0).
    xtol, rtol : float
        The root is returned once the bracket is below ``xtol + rtol |x|`` [units of x].
    maxiter : int
        Most evaluations of ``f`` after the two at the ends.

    Returns
    -------
    float
        ``x`` in ``[a, b]`` with ``f(x) = 0`` or within the tolerance of a sign change.

    Raises
    ------
    ValueError
        ``f(a)`` and ``f(b)`` have the same sign (no bracket).
    RuntimeError
        Not converged within ``maxiter`` evaluations.

    Notes
    -----
    R. P. Brent, *Algorithms for Minimization without Derivatives* (Prentice-Hall, 1973),
    ch. 4 (procedure *zero*): each step takes the interpolated point when it falls inside
    the bracket and shrinks the step faster than bisection would, else bisects; the
    bracket always holds the sign change.
    """
    fa, fb = float(f(a)), float(f(b))
    if fa == 0.0:
        return float(a)
    if fb == 0.0:
        return float(b)
    if (fa > 0.0) == (fb > 0.0):
        raise ValueError("f(a) and f(b) must have opposite signs")
    c, fc = a, fa
    d = e = b - a
    for _ in range(int(maxiter)):
        if (fb > 0.0) == (fc > 0.0):          # keep the sign change between b and c
            c, fc = a, fa
            d = e = b - a
        if abs(fc) < abs(fb):                 # b: the best estimate so far
            a, b, c = b, c, b
            fa, fb, fc = fb, fc, fb
        tol = 0.5 * (xtol + rtol * abs(b))
        xm = 0.5 * (c - b)
        if abs(xm) <= tol or fb == 0.0:
            return float(b)
        if abs(e) >= tol and abs(fa) > abs(fb):
            s = fb / fa
            if a == c:                        # secant
                p, q = 2.0 * xm * s, 1.0 - s
            else:                             # inverse quadratic interpolation
                q, r = fa / fc, fb / fc
                p = s * (2.0 * xm * q * (q - r) - (b - a) * (r - 1.0))
                q = (q - 1.0) * (r - 1.0) * (s - 1.0)
            if p > 0.0:
                q = -q
            p = abs(p)
            if 2.0 * p < min(3.0 * xm * q - abs(tol * q), abs(e * q)):
                e, d = d, p / q               # interpolation accepted
            else:
                d = e = xm                    # bisection
        else:
            d = e = xm
        a, fa = b, fb
        b += d if abs(d) > tol else math.copysign(tol, xm)
        fb = float(f(b))
    raise RuntimeError(f"Brent's method did not converge in {maxiter} evaluations")


def _circle_thetas(e: int) -> np.ndarray:
    """The scan of the upper unit circle by :func:`_circle_values`: 4000 angles spaced
    geometrically from 1e-9 and at least 64 per turn of ``z^e``, linearly, up to pi."""
    n_lin = max(4000, 32 * (e + 1))
    return np.unique(np.concatenate([np.geomspace(1e-9, math.pi, 4000),
                                     np.linspace(0.0, math.pi, n_lin + 1)[1:]]))


def circle_scan_points(loop: LoopModel) -> int:
    """Angles of the unit circle :func:`stability_limit` scans for crossings.

    Parameters
    ----------
    loop : LoopModel

    Returns
    -------
    int
        The ``N`` of a limit labelled ``"sampled (N)"``: the scan finds every crossing
        whose neighbours on the circle are at least one scan step apart.
    """
    return int(_circle_thetas(char_parts(loop)[3]).size)


def _circle_values(A, C, e: int):
    """Real ``x`` for which ``x A(w) + C(w)`` has a root on the unit circle.

    ``A``, ``C``: vectorised functions of ``w = z - 1`` (evaluated unexpanded, see
    :func:`hapsim.analysis.loop.char_eval`); ``e``: the delay exponent, which sets how fast
    they turn round the circle. On ``z = e^{i theta}`` the root condition is ``x = -C/A``,
    real iff ``Im[C conj(A)] = 0``; that is solved for ``theta`` in ``(0, pi]`` (dense scan
    with at least 64 points per turn of ``z^e``, then Brent to ~1e-15). Returns ``(values,
    lossless, x_pi)``: the candidate values (unsorted, finite), whether ``-C/A`` is real all
    round the circle (a lossless loop: the scan finds no sign change), and ``-C/A`` at
    ``z = -1`` (nan where ``A(-1) = 0``).
    """
    def wof(theta):
        return -2.0 * np.sin(0.5 * theta) ** 2 + 1j * np.sin(theta)  # e^{i theta} - 1

    def g(theta):
        w = wof(theta)
        a, c = complex(A(w)), complex(C(w))
        return (c * np.conj(a)).imag / max(abs(c) * abs(a), 1e-300)

    thetas = _circle_thetas(e)
    wv = wof(thetas)
    av = A(wv)
    cv = C(wv)
    gv = (cv * np.conj(av)).imag / np.maximum(np.abs(cv) * np.abs(av), 1e-300)
    a, c = complex(A(-2.0 + 0j)), complex(C(-2.0 + 0j))
    x_pi = (-(c / a)).real if abs(a) > 1e-14 * max(abs(c), 1.0) else math.nan
    if np.max(np.abs(gv[thetas >= 1e-3])) < 1e-9:  # (tiny theta: cancellation noise)
        return [], True, x_pi
    vals = []
    for i in np.flatnonzero((gv[:-1] == 0.0) | (gv[:-1] * gv[1:] < 0)):
        if gv[i] == 0.0:
            th = thetas[i]
        else:
            try:
                th = brent_root(g, thetas[i], thetas[i + 1], xtol=1e-300, rtol=1e-15,
                                maxiter=200)
            except ValueError:  # scalar and vector rounding disagree on a tiny |g|
                th = 0.5 * (thetas[i] + thetas[i + 1])
        w = wof(th)
        a, c = complex(A(w)), complex(C(w))
        if abs(a) > 0:
            vals.append((-(c / a)).real)
    if math.isfinite(x_pi):
        vals.append(x_pi)
    return [v for v in vals if math.isfinite(v)], False, x_pi


def _kappa_max(loop: LoopModel, beta: float) -> float:
    """Dimensionless ``K_max T^2 / m`` for dimensionless ``beta = B T / m``."""
    P, Q, D, e = char_parts(loop)
    vals, lossless, k_pi = _circle_values(
        lambda w: np.polyval(P, w),
        lambda w: beta * np.polyval(Q, w) + (1.0 + w) ** e * np.polyval(D, w), e)
    if lossless:
        # Lossless loop (e.g. ideal hold, d = 0, B = -b0: the centred-difference
        # oscillator): K(theta) is real all round the circle, the poles sit on it for small
        # K (marginal stability) and leave it at z = -1.
        return k_pi if k_pi > 0 else 0.0
    cands = sorted({c for c in vals if c > 0})
    # stability is constant between consecutive crossings: test each interval's middle
    edges = [0.0] + cands
    for i, lo in enumerate(edges):
        hi = edges[i + 1] if i + 1 < len(edges) else (2.0 * lo if lo > 0 else 1.0)
        mid = math.sqrt(lo * hi) if lo > 0 else 0.5 * hi
        if not _stable_at(loop, mid, beta):
            return lo
    return math.inf


def stability_limit(loop: LoopModel, B: float = 0.0) -> float:
    """Exact largest stable virtual stiffness ``K_max(B)`` [N/m].

    Parameters
    ----------
    loop : LoopModel
    B : float, optional
        Virtual damping [N s/m].

    Returns
    -------
    float
        ``sup {K : the loop is stable for every K' in (0, K)}``, where the spectral radius
        reaches 1. ``0.0`` when no small positive ``K`` is stable (e.g. ZOH with
        ``b0 = B = 0``, or a delay without damping); ``inf`` when every ``K > 0`` is stable
        (no finite crossing, e.g. the ideal hold with large damping ratio; rare).
        For a lossless loop (``"ideal"``, ``d = 0``, ``B = -b0``; e.g. ``b0 = B = 0``) the
        poles stay on the unit circle (marginal stability) up to where they leave it at
        ``z = -1``: for ``b0 = B = 0`` the centred-difference limit ``4 m / T^2``.

    Notes
    -----
    On the boundary a pole is ``z = e^{i theta}`` and ``K(theta) = -(Q B + R)/P`` must be
    real: ``Im[(QB + R) conj(P)] = 0`` is solved for ``theta`` in ``(0, pi]`` (dense scan
    then Brent, relative precision ~1e-15), each root gives a candidate ``K``; between
    consecutive candidates stability cannot change, so each interval is classified by the
    spectral radius at one interior point. The boundary is the ``b = 0`` curve of the grid
    (Florens et al. Sec. 6.2).

    Raises
    ------
    ConfigError
        If ``B`` is not finite or ``|B| T/m`` exceeds
        :data:`hapsim.analysis.loop.MAX_PRODUCT` (key ``B``).
    """
    if not math.isfinite(float(B)):
        raise ConfigError(f"must be finite, got {B!r}", key="B")
    T, m = loop.period, loop.mass
    _, beta = scaled_gains(loop, 0.0, B)
    return _kappa_max(loop, beta) * m / (T * T)


def damping_limits(loop: LoopModel, K: float) -> list:
    """Exact range(s) of virtual damping ``B`` keeping the loop stable at a fixed ``K``.

    Parameters
    ----------
    loop : LoopModel
    K : float
        Virtual stiffness [N/m], finite.

    Returns
    -------
    list of (float, float)
        The maximal intervals ``(B_min, B_max)`` [N s/m] of ``B`` for which every closed-loop
        pole has ``|z| < 1``, in increasing order; bounds may be ``-inf`` / ``inf``; empty
        when no ``B`` stabilises this ``K``. For a delayed loop the set is bounded on both
        sides: too little damping and too much (the delayed backward-difference damper
        pumps energy near the Nyquist frequency) are both unstable, the lens of Florens
        et al. Fig. 8. Ideal hold, ``d = 0``, ``b0 = 0``: ``(0, (4 m/T^2 - K) T/2)``.

    Raises
    ------
    ConfigError
        If ``K`` is not finite or ``|K| T^2/m`` exceeds
        :data:`hapsim.analysis.loop.MAX_PRODUCT`.

    Notes
    -----
    Same method as :func:`stability_limit` with the roles of ``K`` and ``B`` exchanged: on
    the boundary a pole is ``z = e^{i theta}`` and ``B(theta) = -(P K + R)/Q`` must be real;
    each root of ``Im[(P K + R) conj(Q)] = 0`` in ``(0, pi]`` gives a candidate ``B``
    (relative precision ~1e-15 in ``theta``); stability is constant between consecutive
    candidates and is classified by the spectral radius at one interior point of each.
    """
    if not math.isfinite(float(K)):
        raise ConfigError(f"must be finite, got {K!r}", key="K")
    T, m = loop.period, loop.mass
    kappa, _ = scaled_gains(loop, K, 0.0)
    P, Q, D, e = char_parts(loop)
    vals, lossless, b_pi = _circle_values(
        lambda w: np.polyval(Q, w),
        lambda w: kappa * np.polyval(P, w) + (1.0 + w) ** e * np.polyval(D, w), e)
    if lossless:
        vals = [b_pi] if math.isfinite(b_pi) else []
    cands = sorted(set(vals))
    if not cands:
        return [(-math.inf, math.inf)] if _stable_at(loop, kappa, 0.0) else []
    edges = [-math.inf] + cands + [math.inf]
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        if math.isinf(lo):
            mid = hi - max(1.0, abs(hi))
        elif math.isinf(hi):
            mid = lo + max(1.0, abs(lo))
        else:
            mid = 0.5 * (lo + hi)
        if _stable_at(loop, kappa, mid):
            if out and out[-1][1] == lo:
                out[-1] = (out[-1][0], hi)
            else:
                out.append((lo, hi))
    scale = m / T
    return [(float(lo * scale), float(hi * scale)) for lo, hi in out]


def stability_boundary(loop: LoopModel, B_values) -> np.ndarray:
    """``K_max(B)`` [N/m] for each virtual damping in ``B_values`` [N s/m].

    Parameters
    ----------
    loop : LoopModel
    B_values : array_like, shape (n,)

    Returns
    -------
    ndarray, shape (n,)
        :func:`stability_limit` at each ``B`` (``0.0`` / ``inf`` as documented there).
    """
    return np.array([stability_limit(loop, float(B)) for B in np.ravel(B_values)])


def published_limits(loop: LoopModel, B: float = 0.0) -> dict:
    """First-order stiffness limits from the literature, for reference [N/m].

    Parameters
    ----------
    loop : LoopModel
    B : float, optional
        Virtual damping [N s/m].

    Returns
    -------
    dict
        ``passivity_K``: Colgate & Schenkel (1997), ``b0 > K T/2 + |B|`` i.e.
        ``K < 2 (b0 - |B|) / T`` (sufficient, ZOH, no delay; may be <= 0).
        ``diolaiti_K``: Diolaiti et al. (2006), ``K < (b0 + B) / (T/2 + d T)`` (first order
        in ``b0 T / m``). ``centred_difference_K``: ``4 m / T^2`` (ideal hold, d = 0,
        Florens et al. eq. (2) at ``T sqrt(k/m) = pi``).
    """
    T, m, b0, d = loop.period, loop.mass, loop.friction, loop.delay
    return {"passivity_K": 2.0 * (b0 - abs(B)) / T,
            "diolaiti_K": (b0 + B) / (T / 2.0 + d * T),
            "centred_difference_K": 4.0 * m / (T * T)}
