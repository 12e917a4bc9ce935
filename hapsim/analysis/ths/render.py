"""Rendered (k, b) and calibration (k, b) -> (K, B), for a loop of any dimension.

Florens, Voda & Urma, Secs. 5-6; docs/design.md, 'The THS'. A 1-D
:class:`~hapsim.analysis.loop.LoopModel` takes the scalar closed forms: every computation
uses the dimensionless pieces of :mod:`hapsim.analysis.loop` in ``w = z - 1``, never
expanded (the delay factor ``(1 + w)^(d+1)`` is evaluated as a power, reduced modulo a
quadratic by binary powering, or found through the companion matrix in ``z``): the same
precision at every delay. A :class:`~hapsim.analysis.ths.matrix_loop.MatrixLoop` (n = 1, 2,
3 axes, or n ports) takes the matrix form: its state matrix's eigenvalues and the felt
matrices of :mod:`hapsim.analysis.ths.felt`, which for n = 1 is the scalar answer to
round-off (``tests/test_ths.py``).
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.analysis.loop import STABILITY_TOL, LoopModel, char_parts
from hapsim.analysis.loop_poles import roots_w, scaled_gains
from hapsim.analysis.modes import Mode, mode_from_pole, modes_from_poles, rendered_pair
from hapsim.analysis.ths.felt import MatrixRenderResult, render_state
from hapsim.analysis.ths.holds import state_matrix
from hapsim.outputs import finite_or_none as _f
from hapsim.analysis.ths.matrix_loop import MatrixLoop, gain_matrices
from hapsim.errors import ConfigError

__all__ = ["RenderResult", "CalibrationResult", "render", "calibrate", "calibrate_core",
           "check_target", "log_abs_w"]


def _modes_of(loop: LoopModel, w: np.ndarray) -> list[Mode]:
    return modes_from_poles(1.0 + w, loop.mass, loop.period, w=w)


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


def render(loop: LoopModel | MatrixLoop, K, B=0.0) -> RenderResult | MatrixRenderResult:
    """Inverse map ``(K, B) -> (k, b)``: the oscillator the user feels, for a loop of any
    dimension.

    Parameters
    ----------
    loop : LoopModel or MatrixLoop
        The simulator configuration: a 1-D loop, or a loop of n axes (n = 1, 2, 3, or n
        ports) with mass and friction matrices.
    K : float, or array_like, shape (n, n) (or (n,), or a scalar: times I) for a MatrixLoop
        Virtual stiffness [N/m].
    B : float, or array_like as ``K``, optional
        Virtual damping [N s/m].

    Returns
    -------
    RenderResult
        For a :class:`~hapsim.analysis.loop.LoopModel`: the rendered pair = least damped
        complex pair of the closed loop (largest ``|z|``); ``s = ln(z)/T``,
        ``k = m|s|^2``, ``b = -2 m Re s`` (Florens et al. Sec. 5;
        docs/design.md, 'The inverse map'). Other poles are reported as parasitic modes.
    MatrixRenderResult
        For a :class:`~hapsim.analysis.ths.matrix_loop.MatrixLoop`: the felt stiffness and
        damping matrices, principal directions and per-direction pairs
        (:mod:`hapsim.analysis.ths.felt`; Lancaster 2007), every pole and the spectral
        radius of the MIMO characteristic (:func:`~hapsim.analysis.ths.holds.state_matrix`).

    Raises
    ------
    ConfigError
        If ``K`` or ``B`` is not finite; for a 1-D loop, ``|K| T^2/m`` or ``|B| T/m``
        exceeds :data:`hapsim.analysis.loop.MAX_PRODUCT`; for a matrix loop, ``K`` or ``B``
        of the wrong shape.
    """
    if isinstance(loop, MatrixLoop):
        Kq, Bq = gain_matrices(loop, K, B)
        return render_state(state_matrix(loop, Kq, Bq), loop.mass, loop.period, K=Kq, B=Bq)
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


def check_target(loop: LoopModel, k: float, b: float) -> tuple[float, float]:
    """The checks :func:`calibrate` makes of a target before calibrating it.

    Parameters
    ----------
    loop : LoopModel
        The simulator configuration.
    k : float
        Target stiffness [N/m].
    b : float
        Target whole THS damping [N s/m].

    Returns
    -------
    (float, float)
        ``(k, b)`` as floats.

    Raises
    ------
    ConfigError
        If ``k <= 0`` or ``k``, ``b`` are not finite, or ``k T^2/m`` or ``|b| T/m`` exceeds
        :data:`hapsim.analysis.loop.MAX_PRODUCT` (key ``k`` or ``b``).
    """
    k = float(k)
    b = float(b)
    if not (math.isfinite(k) and math.isfinite(b)):
        raise ConfigError(f"target must be finite, got k={k!r}, b={b!r}", key="k")
    if k <= 0:
        raise ConfigError(f"target stiffness must be > 0 [N/m], got {k!r}", key="k")
    scaled_gains(loop, k, b, keys=("k", "b"))
    return k, b


def calibrate(loop: LoopModel | MatrixLoop, k: float, b: float) -> CalibrationResult:
    """Forward map ``(k, b) -> (K, B)``: virtual parameters rendering a target oscillator.

    Parameters
    ----------
    loop : LoopModel or MatrixLoop
        The simulator configuration; a matrix loop of one degree of freedom is calibrated
        as its 1-D loop (:meth:`~hapsim.analysis.ths.matrix_loop.MatrixLoop.to_loop_model`).
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
        :data:`hapsim.analysis.loop.MAX_PRODUCT`; a matrix loop of more than one degree of
        freedom (key ``dof``: felt matrices are predicted by :func:`render`, not
        calibrated).

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
    if isinstance(loop, MatrixLoop):
        if loop.dof != 1:
            raise ConfigError(f"calibrating felt matrices is not modelled: a felt target "
                              f"(k, b) is calibrated for a 1-D loop (n = 1); this loop has "
                              f"{loop.dof} degrees of freedom", key="dof")
        loop = loop.to_loop_model()
    k, b = check_target(loop, k, b)
    m, T = loop.mass, loop.period
    nan = math.nan

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
