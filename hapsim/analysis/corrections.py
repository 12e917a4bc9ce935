"""Correction means of the virtual element, as linear controllers of the sampled THS.

Florens, Voda & Urma Secs. 6.3 and 7 name them as future work: "k, b distortion
corrections", "additional speed and acceleration sensor ... to compensate the effect of
delay". Each correction changes the force law ``F[n]`` computed from the samples; the force
is applied ``d`` samples later under the hold, as for the plain loop
``F[n] = -K x[n] - B (x[n] - x[n-1]) / T`` (docs/design.md, 'The characteristic equation').

=========================  ==============================================================
kind                       force law (``x``: handle position samples, ``v``: handle
                           velocity samples, ``D = (x[n] - x[n-1]) / T``)
=========================  ==============================================================
``velocity_sensor``        ``F = -K x[n] - B v[n]`` (the device measures the velocity)
``velocity_filter``        ``F = -K x[n] - B vf[n]``,
                           ``vf[n] = a vf[n-1] + (1 - a) D[n]``, ``a = e^(-2 pi fc T)``
``prediction``             ``xp[n] = x[n] + h (x[n] - x[n-1])`` (``h`` samples ahead,
                           default the delay ``d``); ``F = -K xp[n] - B (xp[n]-xp[n-1])/T``
``inertia_compensation``   ``F = -K x[n] - B D[n] + Mc (x[n] - 2 x[n-1] + x[n-2]) / T^2``
                           (a negative virtual mass ``-Mc`` at the port, ``Mc < m``)
``virtual_coupling``       Colgate, Stanley & Brown (1995): a spring-damper ``(Kc, Bc)``
                           between the handle and a massless proxy ``y`` held by the
                           environment ``(K, B)``; each sample the proxy balances both,
                           ``Kc (x-y) + Bc (Dx - Dy) = K y + B Dy``; ``F = -(K y + B Dy)``
=========================  ==============================================================

Closed loop. With the plant ``x = (T^2/m) Nn(z)/D(z) u`` (and ``v = (T/m) Nv(z)/D(z) u``) and
``u[n] = F[n-d]``, each law is ``F = -(K Ck(z) + B Cb(z) + C0(z)) x`` with rational
``Ck, Cb, C0`` over one denominator ``E``; the characteristic polynomial is
``z^d D E + N (K Pk + B Pb + P0) = 0``, still the paper's ``P K + Q B + R = 0`` (Sec. 6 eq.
(1)), so :func:`hapsim.analysis.render`, :func:`~hapsim.analysis.calibrate`,
:func:`~hapsim.analysis.stability_limit` and the grid apply unchanged. For the virtual
coupling ``F = -Cc Ce/(Cc + Ce) x`` is not linear in ``(K, B)``, but the characteristic
polynomial ``[z^(d+1) D + N ac] ae + z^(d+1) D ac`` (``ac = z Cc``, ``ae = z Ce``) is.
All polynomials are dimensionless and in ``w = z - 1`` (:mod:`hapsim.analysis.loop`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapsim.errors import ConfigError
from hapsim.scene.elements import CORRECTIONS

__all__ = ["Correction", "CorrectionLaw", "CORRECTION_KINDS", "correction_polynomials",
           "passivity_bound", "filtered_passivity_bound"]

#: Corrections and their parameters (the scene validator's table).
CORRECTION_KINDS = CORRECTIONS


@dataclass(frozen=True)
class Correction:
    """One correction of the virtual element (module docstring).

    Parameters
    ----------
    kind : str
        One of :data:`CORRECTION_KINDS`.
    cutoff_hz : float
        ``velocity_filter``: cutoff ``fc`` of the first-order filter [Hz], > 0.
    horizon : float or None
        ``prediction``: samples ahead ``h`` [-], >= 0; None: the loop's delay.
    mass : float
        ``inertia_compensation``: compensated mass ``Mc`` [kg], 0 <= Mc < m.
    stiffness, damping : float
        ``virtual_coupling``: coupling ``Kc`` [N/m] > 0 and ``Bc`` [N s/m] >= 0.

    Raises
    ------
    ConfigError
        Unknown kind or a parameter out of range (key ``device.correction.<param>``).
    """

    kind: str
    cutoff_hz: float = math.nan
    horizon: float | None = None
    mass: float = 0.0
    stiffness: float = math.nan
    damping: float = 0.0

    def __post_init__(self):
        if self.kind not in CORRECTION_KINDS:
            raise ConfigError(f"unknown correction {self.kind!r}; valid choices: "
                              + ", ".join(CORRECTION_KINDS), key="device.correction.kind")

        def bad(key, why):
            raise ConfigError(why, key=f"device.correction.{key}")
        if self.kind == "velocity_filter" and not (self.cutoff_hz > 0
                                                   and math.isfinite(self.cutoff_hz)):
            bad("cutoff_hz", f"must be > 0 [Hz], got {self.cutoff_hz!r}")
        if self.kind == "prediction" and self.horizon is not None and not (
                math.isfinite(self.horizon) and self.horizon >= 0):
            bad("horizon", f"must be >= 0 [samples], got {self.horizon!r}")
        if self.kind == "inertia_compensation" and not (math.isfinite(self.mass)
                                                        and self.mass >= 0):
            bad("mass", f"must be >= 0 [kg], got {self.mass!r}")
        if self.kind == "virtual_coupling":
            if not (self.stiffness > 0 and math.isfinite(self.stiffness)):
                bad("stiffness", f"must be > 0 [N/m], got {self.stiffness!r}")
            if not (self.damping >= 0 and math.isfinite(self.damping)):
                bad("damping", f"must be >= 0 [N s/m], got {self.damping!r}")

    @classmethod
    def from_dict(cls, d: dict | None) -> "Correction | None":
        """Correction of a scene's ``device.correction`` mapping (None stays None).

        Parameters
        ----------
        d : dict or None
            ``{"kind": ..., param: value}``.

        Returns
        -------
        Correction or None

        Raises
        ------
        ConfigError
            As for the constructor, or an unknown parameter.
        """
        if d is None:
            return None
        if isinstance(d, Correction):
            return d
        kind = d.get("kind")
        if kind not in CORRECTION_KINDS:
            raise ConfigError(f"unknown correction {kind!r}; valid choices: "
                              + ", ".join(CORRECTION_KINDS), key="device.correction.kind")
        extra = set(d) - {"kind"} - set(CORRECTION_KINDS[kind])
        if extra:
            raise ConfigError(f"unknown keys {sorted(extra)} for {kind}; valid keys: "
                              + ", ".join(CORRECTION_KINDS[kind]), key="device.correction")
        return cls(kind, **{k: float(v) for k, v in d.items() if k != "kind"})

    def label(self) -> str:
        """Short human name with parameters, e.g. ``velocity_filter(fc=100 Hz)``.

        Returns
        -------
        str
            The kind and its parameters (a prediction's default horizon as ``h=d``).
        """
        if self.kind == "velocity_filter":
            return f"velocity_filter(fc={self.cutoff_hz:g} Hz)"
        if self.kind == "prediction":
            return "prediction(h=" + ("d" if self.horizon is None else f"{self.horizon:g}") + ")"
        if self.kind == "inertia_compensation":
            return f"inertia_compensation(Mc={self.mass:g} kg)"
        if self.kind == "virtual_coupling":
            return f"virtual_coupling(Kc={self.stiffness:g}, Bc={self.damping:g})"
        return self.kind

    def to_dict(self) -> dict:
        """JSON-ready ``{"kind": ..., param: value}`` (only the kind's parameters).

        Returns
        -------
        dict
            ``kind`` and each parameter of :data:`CORRECTION_KINDS` as a float (None for a
            default ``horizon``); :meth:`from_dict` reads it back.
        """
        out = {"kind": self.kind}
        for p in CORRECTION_KINDS[self.kind]:
            v = getattr(self, p)
            out[p] = None if v is None else float(v)
        return out

    def filter_pole(self, period: float) -> tuple[float, float]:
        """``(a, 1 - a)`` of the velocity filter, ``a = e^(-2 pi fc T)`` (accurate ``1 - a``).

        The pole of the first-order low-pass ``vf[n] = a vf[n-1] + (1 - a) v[n]`` with the
        cutoff ``fc`` (:attr:`cutoff_hz`) matched by the pole map ``z = e^(sT)``.

        Parameters
        ----------
        period : float
            Sample period ``T`` [s].

        Returns
        -------
        a, one_minus_a : float
            The pole [-] and ``1 - a`` (``-expm1(-2 pi fc T)``, exact for small ``fc T``).
        """
        x = 2.0 * math.pi * self.cutoff_hz * period
        return math.exp(-x), -math.expm1(-x)


def _trim(p) -> np.ndarray:
    """``p`` without its leading zeros (``[0.]`` when all are zero): what ``np.poly1d``
    keeps of a coefficient array."""
    p = np.atleast_1d(np.asarray(p))
    if p.size and p[0] != 0:                # the common case: nothing to trim
        return p
    nz = np.flatnonzero(p)
    return p[nz[0]:] if nz.size else np.zeros(1, p.dtype)


def _pm(*ps):
    """Product of polynomials (highest power first): ``np.polymul`` folded over ``ps``,
    the same ``np.convolve`` of the same trimmed arrays (bit for bit), without building
    two ``np.poly1d`` per factor (numpy's ``trim_zeros`` in them cost half of the stability
    sweeps' time: ``compare-corrections``, ``calibrate`` with a correction)."""
    out = np.array([1.0])
    for p in ps:
        out = np.convolve(_trim(out), _trim(p))
    return out


def correction_polynomials(corr: Correction, Nn, D, Nvn, *, delay: int, mass: float,
                           period: float, lead: float | None = None):
    """Dimensionless ``(P~, Q~, R~)`` in ``w = z - 1`` of a corrected loop.

    Parameters
    ----------
    corr : Correction or None
        None: the plain virtual element (``F = -K x[n] - B D[n]``).
    Nn, D : array_like
        Plant in ``w``: position ``x = (T^2/m) Nn/D u`` (highest power first).
    Nvn : array_like or None
        Handle velocity ``v = (T/m) Nvn/D u``; needed for ``velocity_sensor``.
    delay : int
        ``d`` [samples].
    mass : float
        Reference (total moving) mass ``m`` [kg] of the scaling.
    period : float
        ``T`` [s].
    lead : float, optional
        The loop's whole delay [periods], the prediction's default horizon, when it is not
        ``delay`` (a fractional delay ``m + f``: ``delay`` is ``m``, the plant carries
        ``f``, :mod:`hapsim.analysis.subsample`).

    Returns
    -------
    P, Q, R : ndarray
        ``kappa P + beta Q + R = 0`` with ``kappa = K T^2/m``, ``beta = B T/m`` (module
        docstring for each law).

    Raises
    ------
    ConfigError
        ``velocity_sensor`` without a velocity output (ideal hold), or
        ``inertia_compensation`` with ``Mc >= m`` (the loop's inertia would vanish).
    """
    z = np.array([1.0, 1.0])
    w = np.array([1.0, 0.0])
    Nn = np.asarray(Nn, float)
    D = np.asarray(D, float)
    zd = _pm(*([z] * delay))
    kind = None if corr is None else corr.kind
    if kind is None:
        return _pm(z, Nn), _pm(w, Nn), _pm(zd, z, D)
    if kind == "velocity_sensor":
        if Nvn is None:
            raise ConfigError("a velocity sensor needs hold: zoh (the ideal hold has no "
                              "velocity)", key="device.correction.kind")
        return Nn.copy(), np.asarray(Nvn, float), _pm(zd, D)
    if kind == "velocity_filter":
        _, eps = corr.filter_pole(period)
        E = np.array([1.0, eps])            # z - a = w + (1 - a)
        return _pm(Nn, E), eps * _pm(w, Nn), _pm(zd, D, E)
    if kind == "prediction":
        h = float((delay if lead is None else lead) if corr.horizon is None
                  else corr.horizon)
        Pi = np.array([1.0 + h, 1.0])       # z + h (z - 1) = (1 + h) w + 1
        return _pm(z, Pi, Nn), _pm(w, Pi, Nn), _pm(zd, z, z, D)
    if kind == "inertia_compensation":
        mu = corr.mass / mass
        if not mu < 1.0:
            raise ConfigError(f"compensated mass {corr.mass:g} kg must stay below the moving "
                              f"mass {mass:g} kg", key="device.correction.mass")
        return (_pm(z, z, Nn), _pm(z, w, Nn),
                np.polysub(_pm(zd, z, z, D), mu * _pm(w, w, Nn)))
    # virtual coupling
    kc = corr.stiffness * period * period / mass
    bc = corr.damping * period / mass
    ac = np.polyadd(kc * z, bc * w)
    zdD = _pm(zd, z, D)
    G1 = np.polyadd(zdD, _pm(Nn, ac))
    return _pm(z, G1), _pm(w, G1), _pm(zdD, ac)


def passivity_bound(controller, period: float, *, n: int = 20001) -> float:
    """Smallest real damping ``b0`` that makes a sampled controller passive (no delay).

    Parameters
    ----------
    controller : callable
        ``C(z)``, force per position of the discrete virtual element, vectorised over
        complex ``z`` [N/m].
    period : float
        ``T`` [s].
    n : int, optional
        Frequencies on ``(0, pi]`` of the scan (the supremum is then refined by a bounded
        scalar search).

    Returns
    -------
    float
        ``sup_theta T / (2 (1 - cos theta)) Re[(1 - e^(-i theta)) C(e^(i theta))]`` [N s/m]
        (Colgate & Schenkel 1997, Theorem 1: the ZOH device of friction ``b0`` with the
        sampled controller ``C`` is passive iff ``b0`` exceeds it).
    """
    from scipy.optimize import minimize_scalar

    T = float(period)

    def f(th):
        th = np.asarray(th, float)
        e = np.exp(1j * th)
        return T / (2.0 * (1.0 - np.cos(th))) * np.real((1.0 - 1.0 / e) * controller(e))

    th = np.linspace(1e-4, math.pi, n)
    v = f(th)
    i = int(np.argmax(v))
    best = float(v[i])
    lo, hi = th[max(i - 1, 0)], th[min(i + 1, n - 1)]
    if hi > lo:
        r = minimize_scalar(lambda t: -float(f(t)), bounds=(lo, hi), method="bounded",
                            options={"xatol": 1e-13})
        best = max(best, -float(r.fun))
    return max(best, float(f(math.pi)))


def filtered_passivity_bound(K: float, B: float, cutoff_hz: float, period: float) -> float:
    """Closed form of :func:`passivity_bound` for a spring and a filtered-velocity damper.

    Parameters
    ----------
    K : float
        Virtual stiffness [N/m].
    B : float >= 0
        Virtual damping on the filtered backward difference [N s/m].
    cutoff_hz : float > 0
        First-order filter cutoff [Hz].
    period : float
        ``T`` [s].

    Returns
    -------
    float
        ``K T / 2 + B (1 - a) / (1 + a)``, ``a = e^(-2 pi fc T)`` [N s/m]: Colgate &
        Schenkel's (1997) condition ``b0 > K T/2 + B`` with the damper seen through the
        filter; the supremum is at the Nyquist frequency (the filter's term
        ``(1 - a)(a - cos theta) / (1 - 2 a cos theta + a^2)`` decreases in ``cos theta``).
        ``fc -> inf`` gives back ``K T / 2 + B``.
    """
    x = 2.0 * math.pi * cutoff_hz * period
    a = math.exp(-x)
    return K * period / 2.0 + B * (-math.expm1(-x)) / (1.0 + a)


class CorrectionLaw:
    """The corrected virtual element run sample by sample (the loop's side of a correction).

    One port-ground spring-damper ``(K, B)`` with the correction ``corr`` (module
    docstring for each law). :func:`correction_polynomials` is its closed-loop analysis;
    the lockstep daemon runs this class and the two must agree (tests).

    Parameters
    ----------
    corr : Correction
    K, B : float
        Virtual stiffness [N/m] and damping [N s/m] of the link.
    period : float
        ``T`` [s].
    delay : int
        ``d`` [samples] (the default prediction horizon).

    Notes
    -----
    Allocation-free per sample (floats only). ``velocity_sensor`` needs the measured
    velocity passed to :meth:`step`; the others ignore it.
    """

    def __init__(self, corr: Correction, K: float, B: float, period: float, delay: int):
        self.corr = corr
        self.K, self.B, self.T = float(K), float(B), float(period)
        self.h = float(delay if corr.horizon is None else corr.horizon)
        if corr.kind == "velocity_filter":
            self.a, self.one_minus_a = corr.filter_pole(period)
        self.reset(0.0)

    def reset(self, x: float) -> None:
        """Start at rest at position ``x`` [m] (histories filled with ``x``).

        Parameters
        ----------
        x : float
            Port position [m]; the virtual coupling's proxy starts at its equilibrium
            ``x Kc / (Kc + K)``.
        """
        self.x1 = self.x2 = self.p1 = self.y1 = float(x)
        self.vf = 0.0
        if self.corr.kind == "virtual_coupling":
            c = self.corr
            self.y1 = float(x) * c.stiffness / (c.stiffness + self.K)

    def step(self, x: float, v: float = 0.0) -> float:
        """Force on the port for the position sample ``x`` [m] (and velocity ``v`` [m/s]).

        Parameters
        ----------
        x : float
            Position sample ``x[n]`` [m].
        v : float, optional
            Measured velocity [m/s]; read by ``velocity_sensor`` only (default 0).

        Returns
        -------
        float
            ``F[n]`` [N], to be applied ``d`` samples later.
        """
        K, B, T = self.K, self.B, self.T
        kind = self.corr.kind
        if kind == "velocity_sensor":
            f = -K * x - B * v
        elif kind == "velocity_filter":
            self.vf = self.a * self.vf + self.one_minus_a * (x - self.x1) / T
            f = -K * x - B * self.vf
        elif kind == "prediction":
            p = x + self.h * (x - self.x1)
            f = -K * p - B * (p - self.p1) / T
            self.p1 = p
        elif kind == "inertia_compensation":
            f = (-K * x - B * (x - self.x1) / T
                 + self.corr.mass * (x - 2.0 * self.x1 + self.x2) / (T * T))
        else:
            Kc, Bc = self.corr.stiffness, self.corr.damping
            y = ((Kc * x + Bc * (x - self.x1 + self.y1) / T + B * self.y1 / T)
                 / (Kc + Bc / T + K + B / T))
            f = -(K * y + B * (y - self.y1) / T)
            self.y1 = y
        self.x2 = self.x1
        self.x1 = x
        return f


# --------------------------------------------------------------------------- any scene

#: Extra closed-loop state a correction adds after the virtual states (name suffix).
_EXTRA_STATE = {"velocity_sensor": None, "velocity_filter": "vf[n-1] (filtered velocity)",
                "prediction": "x[n-2]", "inertia_compensation": "x[n-2]",
                "virtual_coupling": "y[n-1] (coupling proxy)"}


def corrected_frame(scene, dev, port, Av, bp, bpp, cx, cp, cpp, vnames, member=None,
                    corr=None):
    """Closed-loop matrix without the plant rows, for any scene with a port and a correction.

    The correction acts at the port: the virtual network's one-step map
    ``X[n+1] = Av X + bp q[n] + bpp qq[n]``, ``F[n] = cx X + cp q[n] + cpp qq[n]``
    (:func:`hapsim.analysis.virtual_network.virtual_blocks`) takes as its port position ``q`` and
    as the previous one ``qq`` (so ``(q - qq)/T`` is the velocity estimate the dampers at
    the port see) the corrected signals of the handle samples ``x``:

    =========================  ==============================================================
    kind                       ``q[n]``, ``qq[n]``, force
    =========================  ==============================================================
    none                       ``x[n]``, ``x[n-1]``
    ``velocity_sensor``        ``x[n]``, ``x[n] - T v[n]`` (measured handle velocity)
    ``velocity_filter``        ``x[n]``, ``x[n] - T vf[n]``,
                               ``vf[n] = a vf[n-1] + (1 - a)(x[n] - x[n-1])/T``
    ``prediction``             ``xp[n]``, ``xp[n-1]``, ``xp[n] = x[n] + h (x[n] - x[n-1])``
    ``inertia_compensation``   ``x[n]``, ``x[n-1]``; ``F += Mc (x[n] - 2x[n-1] + x[n-2])/T^2``
    ``virtual_coupling``       ``y[n]``, ``y[n-1]``: the port is a massless proxy tied to the
                               handle by ``(Kc, Bc)``, balanced each sample:
                               ``Kc (x - y) + Bc (Dx - Dy) + F_net(y) = 0``, ``F = F_net(y)``
    =========================  ==============================================================

    For a port tied to a ground by one spring_damper these are the laws of
    :class:`CorrectionLaw` (module docstring), so the poles are those of
    :func:`correction_polynomials` (up to roots at 0).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        For the error messages (its path) and the period ``T`` [s].
    dev : hapsim.scene.Device
        Device (hold, delay; the moving mass for the inertia limit).
    port : str
        Port name (state names).
    Av, bp, bpp, cx, cp, cpp
        Blocks of :func:`hapsim.analysis.virtual_network.virtual_blocks` (or
        :func:`~hapsim.analysis.virtual_network.multirate_blocks`), shapes (2N, 2N), (2N,), (2N,),
        (2N,), float, float.
    vnames : list of str
        Names of the 2N virtual states.
    member : array_like, shape (4,) or (5,), optional
        Hand member (plant layout: a compliant grip has 4 plant states).
    corr : Correction or None
        None gives the plain frame.

    Returns
    -------
    A : ndarray, shape (n, n)
        Closed-loop matrix with the plant rows ``0 .. nplant-1`` left zero (the ideal
        hold's are completed by the caller), state order: plant, ``x_port[n-1]``, delay
        line (d), virtual (2N), the correction's state (0 or 1), and for a fractional
        delay ``m + f`` (``d = m`` then) the force held over the period's first ``f T``
        (:func:`hapsim.analysis.subsample.held_plant`: the caller adds
        ``Gamma1`` times it to the plant rows).
    u : ndarray, shape (n,)
        Row giving the force held over the coming period.
    nplant : int
        Plant states (2 or 4 for ``"zoh"``, 1 for ``"ideal"``).
    names : list of str

    Raises
    ------
    ConfigError
        Unknown hold; ``velocity_sensor`` with the ideal hold; ``inertia_compensation``
        with ``Mc`` not below the moving mass (handle + hand).
    """
    from hapsim.analysis.body import is_compliant, device_body

    T = float(scene.period)
    if dev.hold == "zoh":
        if is_compliant(dev, member):
            names = [f"{port}.x[n] (handle position)", "device.v[n]", "hand.x[n]",
                     "hand.v[n]"]
        else:
            names = [f"{port}.x[n] (device position)", "device.v[n]"]
        names.append(f"{port}.x[n-1]")
    elif dev.hold == "ideal":
        names = [f"{port}.x[n] (device position)", f"{port}.x[n-1]"]
    else:
        raise ConfigError(f"unknown hold {dev.hold!r}; valid: zoh, ideal",
                          file=scene.path, key="device.hold")
    kind = None if corr is None else corr.kind
    if kind == "velocity_sensor" and dev.hold != "zoh":
        raise ConfigError("a velocity sensor needs hold: zoh (the ideal hold has no "
                          "velocity)", file=scene.path, key="device.correction.kind")
    from hapsim.analysis.subsample import split_delay
    d, frac = split_delay(dev.delay, "device.delay")
    nd = len(names)
    nplant = nd - 1
    names += [f"F[n-{i}] (port force, delay line)" for i in range(1, d + 1)]
    names += list(vnames)
    o = nd + d
    nv = len(vnames)
    extra = None if kind is None else _EXTRA_STATE[kind]
    if extra is not None:
        names.append(f"{port}.{extra}")
    n = len(names)
    ic = n - 1                                 # the correction's state (when it has one)
    ip, ipp = 0, nd - 1
    e = np.eye(n)
    X = np.zeros(n)
    X[o:o + nv] = cx                           # network force without the port terms
    q, qq, fx = e[ip], e[ipp], np.zeros(n)
    A = np.zeros((n, n))
    if kind == "velocity_sensor":
        qq = e[ip] - T * e[1]
    elif kind == "velocity_filter":
        a, eps = corr.filter_pole(T)
        vf = a * e[ic] + eps * (e[ip] - e[ipp]) / T
        qq = e[ip] - T * vf
        A[ic] = vf
    elif kind == "prediction":
        h = float(float(dev.delay) if corr.horizon is None else corr.horizon)
        q = (1.0 + h) * e[ip] - h * e[ipp]
        qq = (1.0 + h) * e[ipp] - h * e[ic]
        A[ic] = e[ipp]
    elif kind == "inertia_compensation":
        mass = device_body(dev, member)[0]
        if not corr.mass < mass:
            raise ConfigError(f"compensated mass {corr.mass:g} kg must stay below the moving "
                              f"mass {mass:g} kg", file=scene.path,
                              key="device.correction.mass")
        fx = corr.mass / (T * T) * (e[ip] - 2.0 * e[ipp] + e[ic])
        A[ic] = e[ipp]
    elif kind == "virtual_coupling":
        Kc, Bc = corr.stiffness, corr.damping
        y = ((Kc + Bc / T) * e[ip] - Bc / T * e[ipp] + (Bc / T + cpp) * e[ic] + X) \
            / (Kc + Bc / T - cp)
        q, qq = y, e[ic]
        A[ic] = y
    Frow = X + cp * q + cpp * qq + fx
    if d == 0:
        u = Frow
    else:
        u = np.zeros(n)
        u[nd + d - 1] = 1.0
        A[nd] = Frow
        for j in range(1, d):
            A[nd + j, nd + j - 1] = 1.0
    A[ipp, ip] = 1.0
    A[o:o + nv, o:o + nv] = Av
    A[o:o + nv] += np.outer(bp, q) + np.outer(bpp, qq)
    if frac > 0:
        # the split hold (hapsim.analysis.subsample.held_plant): the force u held over
        # the last (1 - f) T of this period is held over the first f T of the next, one
        # more state, last; the caller's plant rows take it through Gamma1
        A = np.pad(A, ((0, 1), (0, 1)))
        u = np.append(u, 0.0)
        A[n] = u
        names.append(f"F[n-{d + 1}] (port force, held the first {frac:g} T)")
    return A, u, nplant, names
