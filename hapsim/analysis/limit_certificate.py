"""The stiffness limit K_max(B) certified: a guaranteed bracket in exact arithmetic.

:func:`hapsim.analysis.stability.stability_limit` finds where a pole of
``kappa A(z) + C(z) = 0`` (the THS's characteristic, ``A = P~``, ``C = beta Q~ + z^e D``,
:func:`hapsim.analysis.loop.char_parts`) reaches the unit circle by a dense scan of the
circle: two crossings between neighbouring scan points would be missed. Here the same
limit is proven, on the polynomial's double-precision coefficients taken as exact
rationals, by three facts checked in rational arithmetic (no rounding anywhere):

1. no ``kappa`` in ``(0, kappa_lo]`` puts a root on ``|z| = 1``;
2. at ``kappa_lo`` every root is inside the circle (the Schur-Cohn-Jury test);
3. at ``kappa_hi`` some root is on or outside it.

By continuity of the roots in ``kappa`` (a root can only leave the disc through the circle;
one going to infinity where the leading coefficient vanishes is outside before), 1 and 2
make every ``kappa`` in ``(0, kappa_lo]`` stable, and 3 bounds the limit:
``K_max in [kappa_lo, kappa_hi] m / T^2``.

Fact 1 is the root-locus crossing condition as a polynomial in ``x = cos theta``. On
``z = x + i y`` (``y = sin theta``), ``z^k = T_k(x) + i y U_(k-1)(x)`` (Chebyshev
polynomials of the first and second kind), so ``A(z) = A_r(x) + i y A_i(x)`` and likewise
``C``. For ``0 < theta < pi`` a root of ``kappa A + C`` on the circle needs
``kappa A_r + C_r = 0`` and ``kappa A_i + C_i = 0``, hence

    p(x) = A_r(x) C_i(x) - A_i(x) C_r(x) = 0,      kappa = N(x) / M(x),
    N = -(A_r C_r + (1 - x^2) A_i C_i),   M = A_r^2 + (1 - x^2) A_i^2 = |A|^2.

The real roots of ``p`` in ``(-1, 1)`` are isolated by Sturm sequences (Sturm 1829) with
exact bisection, and at each the signs of ``N`` and ``kappa_lo M - N`` are decided by
refining its isolating interval until neither has a root in it: a crossing lies in
``(0, kappa_lo]`` iff ``N > 0`` and ``kappa_lo M - N >= 0`` there. ``z = +-1`` are checked
directly (``kappa = -C(+-1) / A(+-1)``).

A lossless loop (``p`` vanishes identically: every ``kappa A + C`` is self-inversive, the
poles sit on the circle for small ``K``, marginal, which hapsim counts stable) is proven
through its derivative instead (Cohn 1922: :func:`_lossless`).

Where it cannot be proven the limit stays the scan's, labelled ``sampled (N)`` with the
scan's ``N`` points of the circle: a root on the circle for every ``K``, a characteristic of
degree above :data:`MAX_DEGREE` (a long delay: the exact arithmetic's cost grows fast), or
a limit whose neighbourhood the three facts do not bracket.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

from hapsim.analysis.loop import LoopModel, char_parts
from hapsim.analysis.loop_poles import scaled_gains

__all__ = ["LimitCertificate", "certify_limit", "MAX_DEGREE"]

#: Largest degree in ``z`` of the characteristic certified (``d + 3`` for a ZOH loop of
#: delay ``d``); above it the Sturm sequences' exact coefficients grow too long.
MAX_DEGREE = 16

#: Relative half-widths of the bracket tried, tightest first.
_WIDTHS = (Fraction(1, 10 ** 12), Fraction(1, 10 ** 9), Fraction(1, 10 ** 6))

#: Most bisections refining one root of ``p`` before the sign of ``N`` there is given up.
_MAX_REFINE = 120


@dataclass(frozen=True)
class LimitCertificate:
    """Whether ``K_max(B)`` is proven, and its guaranteed bracket.

    Attributes
    ----------
    certified : bool
        The three facts of the module notes hold in exact arithmetic.
    method : str
        ``"certified"`` or ``"sampled (N)"`` (``N`` points of the circle scanned).
    interval : (float, float) or None
        ``[K_lo, K_hi]`` [N/m] holding ``K_max`` (rounded outwards; ``(inf, inf)`` when
        every ``K > 0`` is proven stable, ``(0, 0)`` when none is); None when not
        certified.
    note : str
        What was proven, or why it could not be.
    """

    certified: bool
    method: str
    interval: tuple | None
    note: str = ""


# ----------------------------------------------------------------- exact polynomials
# lists of Fractions, lowest degree first

def _trim(p):
    p = list(p)
    while p and p[-1] == 0:
        p.pop()
    return p


def _add(p, q):
    n = max(len(p), len(q))
    return _trim([(p[i] if i < len(p) else 0) + (q[i] if i < len(q) else 0)
                  for i in range(n)])


def _scale(p, c):
    return _trim([c * v for v in p])


def _mul(p, q):
    if not p or not q:
        return []
    out = [Fraction(0)] * (len(p) + len(q) - 1)
    for i, a in enumerate(p):
        if a:
            for j, b in enumerate(q):
                out[i + j] += a * b
    return _trim(out)


def _eval(p, x):
    v = Fraction(0)
    for c in reversed(p):
        v = v * x + c
    return v


def _deriv(p):
    return _trim([i * p[i] for i in range(1, len(p))])


def _rem(p, q):
    p = list(p)
    while len(p) >= len(q) and p:
        f = p[-1] / q[-1]
        s = len(p) - len(q)
        for i, c in enumerate(q):
            p[s + i] -= f * c
        p = _trim(p[:-1])
    return p


def _monic_abs(p):
    """``p`` divided by ``|leading coefficient|`` (signs kept)."""
    return [c / abs(p[-1]) for c in p] if p else p


def _gcd(p, q):
    while q:
        p, q = q, _monic_abs(_rem(p, q))
    return _monic_abs(p)


def _quo(p, q):
    """Exact quotient ``p / q`` (``q`` divides ``p``)."""
    p = list(p)
    out = [Fraction(0)] * max(len(p) - len(q) + 1, 0)
    while len(p) >= len(q) and p:
        f = p[-1] / q[-1]
        s = len(p) - len(q)
        out[s] = f
        for i, c in enumerate(q):
            p[s + i] -= f * c
        p = _trim(p[:-1])
    return _trim(out)


def _sturm(p):
    seq = [_monic_abs(p), _monic_abs(_deriv(p))]
    while seq[-1] and len(seq[-1]) > 1:
        r = _rem(seq[-2], seq[-1])
        if not r:
            break
        seq.append(_monic_abs([-c for c in r]))
    return [s for s in seq if s]


def _changes(seq, x):
    vals = [v for v in (_eval(s, x) for s in seq) if v != 0]
    return sum(1 for a, b in zip(vals, vals[1:]) if (a > 0) != (b > 0))


def _roots_in(seq, a, b):
    """Distinct roots of ``seq[0]`` in ``(a, b]`` (Sturm's theorem)."""
    return _changes(seq, a) - _changes(seq, b)


def _from_float_w(coeffs):
    """A numpy polynomial in ``w`` (highest first) as exact coefficients in ``z = 1 + w``."""
    out = []
    for c in coeffs:                       # Horner in polynomials: out = out (z - 1) + c
        out = _add(_mul(out, [Fraction(-1), Fraction(1)]), [Fraction(float(c))])
    return out


def _circle_parts(p):
    """``(re, im)`` with ``p(x + i y) = re(x) + i y im(x)`` on ``x^2 + y^2 = 1``."""
    T = [[Fraction(1)], [Fraction(0), Fraction(1)]]
    U = [[], [Fraction(1)]]                # U[k] = U_(k-1); U_(-1) = 0, U_0 = 1
    two_x = [Fraction(0), Fraction(2)]
    while len(T) < len(p):
        T.append(_add(_mul(two_x, T[-1]), _scale(T[-2], -1)))
        U.append(_add(_mul(two_x, U[-1]), _scale(U[-2], -1)))
    re, im = [], []
    for k, c in enumerate(p):
        if c:
            re = _add(re, _scale(T[k], c))
            im = _add(im, _scale(U[k], c))
    return re, im


def schur_stable(p) -> bool:
    """Every root of ``p`` (exact real coefficients, lowest degree first) in ``|z| < 1``.

    Parameters
    ----------
    p : list of Fraction
        Coefficients, lowest degree first; the degree is that of the last non-zero one.

    Returns
    -------
    bool

    Notes
    -----
    Schur-Cohn (Jury) reduction, exact: ``p`` of degree ``n`` is Schur stable iff
    ``|p_0| < |p_n|`` and ``(p_n p(z) - p_0 z^n p(1/z)) / z`` (degree ``n - 1``) is
    (Schur 1917; Jury 1964).
    """
    p = _trim(p)
    while len(p) > 1:
        a0, an = p[0], p[-1]
        if abs(a0) >= abs(an):
            return False
        n = len(p) - 1
        q = [an * p[k] - a0 * p[n - k] for k in range(n + 1)]
        p = _monic_abs(_trim(q[1:]))
    return bool(p)


# ----------------------------------------------------------------- the certificate

class _Loop:
    """The exact pieces of the family ``kappa A(z) + C(z)`` (lowest degree first)."""

    @classmethod
    def of(cls, loop: LoopModel, beta: float) -> "_Loop":
        """The THS's characteristic at one ``beta``."""
        P, Q, D, e = char_parts(loop)
        return cls(_from_float_w(P), _add(_scale(_from_float_w(Q), Fraction(beta)),
                                          _mul([Fraction(0)] * e + [Fraction(1)],
                                               _from_float_w(D))))

    def __init__(self, A, C):
        self.A, self.C = A, C
        self.degree = max(len(A), len(C)) - 1
        Ar, Ai = _circle_parts(A)
        Cr, Ci = _circle_parts(C)
        one_m_x2 = [Fraction(1), Fraction(0), Fraction(-1)]
        self.p = _add(_mul(Ar, Ci), _scale(_mul(Ai, Cr), -1))
        self.N = _scale(_add(_mul(Ar, Cr), _mul(one_m_x2, _mul(Ai, Ci))), -1)
        self.M = _add(_mul(Ar, Ar), _mul(one_m_x2, _mul(Ai, Ai)))

    def char(self, kappa):
        return _add(_scale(self.A, kappa), self.C)

    def crossing_roots(self):
        """``(sq, intervals)``: ``sq`` the square-free part of ``p`` without the roots
        ``x = +-1``, and rational isolating intervals ``(a, b]`` inside [-1, 1] of its
        distinct roots in (-1, 1), each holding exactly one, ``sq(a) sq(b) != 0``; None
        when ``p`` vanishes identically (a lossless loop)."""
        if not self.p:
            return None
        sq = _quo(self.p, _gcd(self.p, _deriv(self.p))) if len(self.p) > 2 else self.p
        lo, hi = Fraction(-1), Fraction(1)
        for xe in (lo, hi):                    # z = +-1 are checked on their own: the
            if _eval(sq, xe) == 0:             # (simple) root divided out, none lost
                sq = _quo(sq, [-xe, Fraction(1)])
        if len(sq) < 2:
            return sq, []
        seq = _sturm(sq)
        out, todo = [], [(lo, hi, _roots_in(seq, lo, hi))]
        while todo:
            a, b, n = todo.pop()
            if n == 0:
                continue
            if n == 1:
                out.append((a, b))
                continue
            m = _split(sq, a, b)
            todo += [(a, m, _roots_in(seq, a, m)), (m, b, _roots_in(seq, m, b))]
        return sq, out


def _split(p, a, b):
    """A point strictly inside ``(a, b)`` where ``p != 0``: the middle, else one of the
    ``deg p + 1`` points ``a + (b - a) k / (deg p + 2)`` (at most ``deg p`` are roots)."""
    m = (a + b) / 2
    if _eval(p, m) != 0:
        return m
    n = len(p)
    return next(x for x in (a + (b - a) * Fraction(k, n + 1) for k in range(1, n + 1))
                if _eval(p, x) != 0)


def _sign_at_root(sq, a, b, f):
    """Sign of ``f`` at the one root of ``sq`` in ``(a, b]`` (-1, 0 or 1), or None if it
    cannot be separated from a root of ``f`` within :data:`_MAX_REFINE` bisections.

    On ``[a, b]`` inside ``[-1, 1]``, ``|f(x) - f(a)| <= (b - a) sum_k k |f_k|`` (mean value
    theorem): once ``|f(a)|`` exceeds that, ``f`` keeps its sign on the interval.
    """
    if not f:
        return 0
    lip = sum(k * abs(c) for k, c in enumerate(f))
    pa = _eval(sq, a)
    for _ in range(_MAX_REFINE):
        fa = _eval(f, a)
        if abs(fa) > (b - a) * lip:
            return 1 if fa > 0 else -1
        m = (a + b) / 2
        pm = _eval(sq, m)
        if pm == 0:
            fm = _eval(f, m)
            return (fm > 0) - (fm < 0)
        if (pm > 0) == (pa > 0):
            a, pa = m, pm
        else:
            b = m
    return None


def _crossing_below(L: _Loop, roots, kappa_hi) -> bool | None:
    """A ``kappa`` in ``(0, kappa_hi]`` puts a root on the circle (None: undecided)."""
    for zc in (Fraction(1), Fraction(-1)):
        a, c = _eval(L.A, zc), _eval(L.C, zc)
        if a == 0:
            if c == 0:
                return None                    # a root at z = +-1 for every kappa
            continue
        k = -c / a
        if 0 < k <= kappa_hi:
            return True
    sq, ivs = roots
    G = _add(_scale(L.M, kappa_hi), _scale(L.N, -1))
    for a, b in ivs:
        sn = _sign_at_root(sq, a, b, L.N)
        if sn is None:
            return None
        if sn <= 0:
            continue                           # kappa <= 0 there (or A = C = 0: see M)
        sm = _sign_at_root(sq, a, b, L.M)
        if sm is None or sm == 0:
            return None
        sg = _sign_at_root(sq, a, b, G)
        if sg is None:
            return None
        if sg >= 0:
            return True
    return False


def certify_limit(loop: LoopModel, B: float, K_max: float, scan_points: int) -> LimitCertificate:
    """Prove ``K_max(B)`` (from :func:`hapsim.analysis.stability.stability_limit`) or say why not.

    Parameters
    ----------
    loop : LoopModel
    B : float
        Virtual damping [N s/m].
    K_max : float
        The scan's limit [N/m] (``0``: no positive K stable; ``inf``: every K).
    scan_points : int
        Points of the circle the scan examined (the ``N`` of ``"sampled (N)"``).

    Returns
    -------
    LimitCertificate

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.loop_poles.scaled_gains`.

    Notes
    -----
    Module notes: the root-locus crossing condition on ``|z| = 1`` as a polynomial in
    ``cos theta``, Sturm's theorem (1829), the Schur-Cohn-Jury test (Jury 1964), all in
    exact rational arithmetic on the characteristic's double-precision coefficients.
    """
    T, m = loop.period, loop.mass
    _, beta = scaled_gains(loop, 0.0, B)
    sampled = f"sampled ({scan_points})"

    def no(reason):
        return LimitCertificate(False, sampled, None, reason)

    L = _Loop.of(loop, beta)
    if L.degree > MAX_DEGREE:
        return no(f"degree {L.degree} above {MAX_DEGREE} (a long delay): the scan's value")
    roots = L.crossing_roots()
    scale = Fraction(m) / (Fraction(T) * Fraction(T))      # kappa -> K [N/m]
    if roots is None:
        return _lossless(L, K_max, scale, no)
    if math.isinf(K_max):
        if _any_positive_crossing(L, roots) is False and schur_stable(L.char(Fraction(1))):
            return LimitCertificate(True, "certified", (math.inf, math.inf),
                                    "no pole on |z| = 1 for any K > 0")
        return no("no finite limit found but not proven")
    kappa = Fraction(K_max) / scale
    if kappa <= 0:
        for digits in (9, 12, 16, 24, 40):    # a K below every positive crossing
            k1 = Fraction(1, 10 ** digits)
            cross = _crossing_below(L, roots, k1)
            if cross is None:
                break
            if not cross:
                if not schur_stable(L.char(k1)):
                    return LimitCertificate(True, "certified", (0.0, 0.0),
                                            "unstable for every small K > 0")
                break
        return no("K_max = 0 not proven")
    why = "the bracket was not proven"
    for h in _WIDTHS:
        lo, hi = kappa * (1 - h), kappa * (1 + h)
        cross = _crossing_below(L, roots, lo)
        if cross is None:
            return no("a root of the crossing condition could not be separated")
        if cross:
            why = "a crossing below the scan's limit"
            break
        if not schur_stable(L.char(lo)):
            why = "unstable below the scan's limit"
            break
        if schur_stable(L.char(hi)):
            continue                               # not yet unstable: widen
        return LimitCertificate(True, "certified", _outwards(lo, hi, scale),
                                "no pole on |z| = 1 below")
    return no(why)


def _outwards(lo, hi, scale) -> tuple:
    return (math.nextafter(float(lo * scale), 0.0), math.nextafter(float(hi * scale), math.inf))


def _self_inversive(A, C) -> bool:
    """``A`` and ``C``, padded to the family's degree ``n``, both satisfy
    ``c_k = s c_(n-k)`` with the same sign ``s`` (real self-inversive polynomials)."""
    n = max(len(A), len(C)) - 1
    for s in (1, -1):
        if all((p[k] if k < len(p) else 0) == s * (p[n - k] if n - k < len(p) else 0)
               for p in (A, C) for k in range(n + 1)):
            return True
    return False


def _lossless(L: _Loop, K_max: float, scale, no) -> LimitCertificate:
    """A lossless loop (``p`` vanishes: every ``kappa A + C`` self-inversive): marginal below
    the limit, every pole on the circle and simple. Cohn's theorem (1922): a self-inversive
    polynomial has all its roots on ``|z| = 1`` iff its derivative has all its roots in
    ``|z| <= 1``, and then they are simple if the derivative's are strictly inside. The
    derivative family ``kappa A' + C'`` is proven Schur stable on ``(0, kappa_lo]`` as the
    loop itself is otherwise (no crossing, stable at ``kappa_lo``); at ``kappa_hi`` one of
    its roots lies beyond ``1 + 1e-9``, so a pole of the loop is off the circle."""
    if not (math.isfinite(K_max) and K_max > 0 and len(L.A) < len(L.C)
            and _self_inversive(L.A, L.C)):
        # (the leading coefficient must not depend on kappa: Cohn's theorem is for a
        # self-inversive polynomial of its full degree)
        return no("lossless loop: the poles stay on the circle below the limit")
    D = _Loop(_deriv(L.A), _deriv(L.C))
    roots = D.crossing_roots()
    if roots is None:
        return no("lossless loop whose derivative is lossless too")
    kappa = Fraction(K_max) / scale
    grow = Fraction(1) + Fraction(1, 10 ** 9)
    for h in _WIDTHS:
        lo, hi = kappa * (1 - h), kappa * (1 + h)
        if _crossing_below(D, roots, lo) is not False or not schur_stable(D.char(lo)):
            break
        dh = D.char(hi)
        if schur_stable([c * grow ** k for k, c in enumerate(dh)]):
            continue                               # not yet off the circle: widen
        return LimitCertificate(True, "certified", _outwards(lo, hi, scale),
                                "every pole on |z| = 1 and simple below (marginal, "
                                "counted stable; Cohn 1922), one off it above")
    return no("lossless loop: the poles stay on the circle below the limit, not proven")


def _any_positive_crossing(L: _Loop, roots) -> bool | None:
    """A ``kappa > 0`` puts a root on the circle (None: undecided)."""
    for zc in (Fraction(1), Fraction(-1)):
        a, c = _eval(L.A, zc), _eval(L.C, zc)
        if a == 0:
            if c == 0:
                return None
            continue
        if -c / a > 0:
            return True
    sq, ivs = roots
    for a, b in ivs:
        sn = _sign_at_root(sq, a, b, L.N)
        if sn is None:
            return None
        if sn > 0:
            sm = _sign_at_root(sq, a, b, L.M)
            if sm is None or sm == 0:
                return None
            return True
    return False
