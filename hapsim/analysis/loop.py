"""The sampled THS loop: real mass + friction, hold, delay, virtual spring/damper.

Real side ``m x'' + b0 x' = f`` (docs/design.md, 'The characteristic equation'). The pulse
transfer from force samples to position samples is ``G(z) = N(z) / D(z)``; the virtual element is
``F[n] = -K x[n-d] - B (x[n-d] - x[n-d-1]) / T``; the closed loop is

    z^(d+1) D(z) + N(z) (K z + (B/T)(z - 1)) = 0,  i.e.  P K + Q B + R = 0,
    P = z N,  Q = (z - 1) N / T,  R = z^(d+1) D          (Florens et al., eq. (1) of Sec. 6).

Numerics. The roots that matter cluster near ``z = 1`` when ``T`` is small, so every
computation is done on dimensionless polynomials in ``w = z - 1`` (the delta operator):
``kappa = K T^2 / m``, ``beta = B T / m``, ``N~ = N m / T^2``; then
``kappa P~ + beta Q~ + R~ = 0`` with ``P~ = z N~``, ``Q~ = (z - 1) N~``, ``R~ = z^(d+1) D``,
all with O(1) coefficients. ``1 - e^(-b0 T/m)`` and the hold coefficients are computed
with ``expm1`` or series, so 20 kHz loops keep ~1e-12 relative precision.

Long delays. ``R~ = (1 + w)^(d+1) D`` is never expanded: its coefficients in ``w`` are
binomials (1e14 at ``d = 50``) and the expanded polynomial lost every digit from
``d ~ 34``. The poles are the eigenvalues of the companion matrix *in z* (``z^(d+1) D(z)``
is three O(1) coefficients and ``d + 1`` zeros: the plant and the delay line as one state
matrix), Newton-polished in ``w`` on the unexpanded function (:func:`char_eval`);
unit-circle scans evaluate ``z^(d+1)`` as a power. Delays above :data:`MAX_DELAY` are
refused (cost).

The closed-loop poles and the spectral radius
(:func:`~hapsim.analysis.loop_poles.closed_loop_poles`,
:func:`~hapsim.analysis.loop_poles.spectral_radius`) are :mod:`hapsim.analysis.loop_poles`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapsim.analysis.subsample import split_delay, split_hold_body, split_numerator_w
from hapsim.errors import ConfigError
from hapsim.option_values import check_values
from hapsim.scene_schema import MASS_RANGE, MAX_DELAY, MAX_PRODUCT, RATE_RANGE, check_product

__all__ = ["LoopModel", "HOLDS", "MAX_DELAY", "check_delay", "char_eval", "RATE_RANGE",
           "MASS_RANGE", "MAX_PRODUCT", "check_range", "check_product", "plant", "characteristic",
           "char_parts", "w_to_z", "zoh_state_space", "STABILITY_TOL"]

#: Valid values of :attr:`LoopModel.hold`.
HOLDS = ("zoh", "ideal")

#: Tolerance on the spectral radius shared by every stability verdict (``render``,
#: ``check_scene``, the bench): ``max |z| <= 1 + STABILITY_TOL`` counts as stable and
#: ``| max |z| - 1 | <= STABILITY_TOL`` as *marginal* (lossless modes of an undamped loop,
#: e.g. the centred-difference oscillator, sit on the unit circle up to round-off, so the
#: sign of ``|z| - 1`` there says nothing).
STABILITY_TOL = 1e-9


def check_range(value: float, lo: float, hi: float, key: str, unit: str) -> None:
    """Refuse a value outside ``[lo, hi]`` (one line naming ``key`` and the range).

    Parameters
    ----------
    value : float
    lo, hi : float
        Valid range, in ``unit``.
    key : str
        Option or scene key named in the message.
    unit : str
        Unit shown, e.g. ``"Hz"``.

    Raises
    ------
    ConfigError
        When ``value`` is outside the range.
    """
    if not lo <= value <= hi:
        raise ConfigError(f"must be between {lo:g} and {hi:g} {unit}, got {value:g}", key=key)


def check_delay(delay, key: str = "delay") -> None:
    """Refuse a delay the analysis cannot afford.

    Parameters
    ----------
    delay : int
        Delay [samples].
    key : str, optional
        Name of the option or scene key, for the message.

    Raises
    ------
    ConfigError
        When ``delay > MAX_DELAY`` (the message gives the limit and its cost).
    """
    if delay > MAX_DELAY:
        raise ConfigError(f"must be <= {MAX_DELAY} samples, got {delay}: the closed loop "
                          f"has d + 3 poles, found as eigenvalues of a (d + 3)-square matrix "
                          f"(O(d^3): ~0.4 s at d = {MAX_DELAY}, seconds for a stability "
                          f"limit); {MAX_DELAY} samples is {MAX_DELAY / 1000:g} s at 1 kHz",
                          key=key)


@dataclass(frozen=True)
class LoopModel:
    """One simulator configuration seen from the THS.

    Parameters
    ----------
    mass : float > 0
        Real moving mass ``m`` (hand + handle) [kg].
    friction : float >= 0
        Real viscous friction ``b0`` [N s/m].
    rate_hz : float > 0
        Sample rate [Hz]; the period is ``T = 1 / rate_hz`` [s].
    delay : float >= 0
        Delay ``d`` [periods] from the sample a force is computed from to the instant it
        takes effect. A whole number is the plain hold (stored as an int: today's code
        path, bit for bit); ``d = m + f`` with ``0 < f < 1`` switches the held force
        ``f T`` into the period (the split hold, :mod:`hapsim.analysis.subsample`;
        modified z-transform, Franklin, Powell & Workman ch. 4, sec. 4.3).
    hold : {"zoh", "ideal"}
        ``"zoh"``: exact zero-order hold of ``m x'' + b0 x' = f``. ``"ideal"``: the paper's
        idealised sampled image, a centred-difference mass (Florens et al. eqs. (2)-(4)).
    hand_mass, hand_damping : float, optional
        Part of ``mass`` [kg] and of ``friction`` [N s/m] that is the hand's, behind the grip
        (:mod:`hapsim.analysis.hand`); only used with a finite ``grip_stiffness``.
    grip_stiffness, grip_damping : float, optional
        Grip spring [N/m] (``inf``: rigid, the default; then ``mass`` and ``friction`` are
        one body) and damper [N s/m] between hand and handle.
    stiffness : float, optional
        Real stiffness to ground [N/m] >= 0 (the hand's arm, on the hand mass behind a
        compliant grip, on the one body when rigid; :mod:`hapsim.analysis.hand`): the real
        spring of Florens et al. Table 1 case V. The plant is then the exact ZOH (or the
        ideal hold's impulse-invariant image) of the state-space model.
    correction : Correction or dict, optional
        Correction of the virtual element (:mod:`hapsim.analysis.corrections`; a mapping
        ``{kind: ..., ...}`` is read as a scene's ``device.correction``).

    Raises
    ------
    ConfigError
        On a non-positive mass or rate, a negative friction, a negative or non-finite
        delay, a fractional delay with the ideal hold, or an unknown hold; a mass outside :data:`MASS_RANGE`, a rate outside
        :data:`RATE_RANGE`, ``b0 T / m`` or ``kh T^2 / m > MAX_PRODUCT``, a delay above
        :data:`MAX_DELAY`, a negative ``stiffness``;
        a hand part not inside the whole, a compliant grip with the ideal hold; a
        ``correction`` that is no Correction or mapping of one; ``key`` names the field.

    Notes
    -----
    ``LoopModel(mass=1, friction=0, rate_hz=1, ...)`` gives the paper's normalised units
    (``m = T = 1``).
    """

    mass: float
    friction: float = 0.0
    rate_hz: float = 1000.0
    delay: int = 1
    hold: str = "zoh"
    hand_mass: float = 0.0
    hand_damping: float = 0.0
    grip_stiffness: float = math.inf
    grip_damping: float = 0.0
    correction: object = None
    stiffness: float = 0.0

    def __post_init__(self) -> None:
        def num(key, value, finite=True):
            try:
                if isinstance(value, (bool, str)):      # (a bool or a word is no number)
                    raise TypeError
                v = float(value)
            except (TypeError, ValueError):
                raise ConfigError(f"must be a number, got {value!r}", key=key) from None
            if finite and not math.isfinite(v):
                raise ConfigError(f"must be finite, got {value!r}", key=key)
            return v
        # the signs and the delay by the declarations the command line's --mass
        # --friction --rate --delay take (hapsim.option_values.API_OPTIONS): one message
        m = num("mass", self.mass, finite=False)
        check_values("loop", key_by="parameter", mass=m)
        check_range(m, *MASS_RANGE, "mass", "kg")
        b0 = num("friction", self.friction, finite=False)
        check_values("loop", key_by="parameter", friction=b0)
        r = num("rate_hz", self.rate_hz, finite=False)
        check_values("loop", key_by="parameter", rate_hz=r)
        check_range(r, *RATE_RANGE, "rate_hz", "Hz")
        check_product(b0, 1.0 / (r * m), "friction", "N s/m", "b0 T/m")
        d = self.delay
        check_values("loop", key_by="parameter", required=True, delay=d)
        whole, frac = split_delay(d)
        check_delay(whole)
        if not isinstance(self.hold, str) or self.hold not in HOLDS:
            raise ConfigError(f"unknown hold {self.hold!r}; valid choices: "
                              f"{', '.join(HOLDS)}", key="hold")
        if frac > 0 and self.hold != "zoh":
            raise ConfigError(f"a delay of {float(d):g} periods switches the force inside "
                              "the period: it needs hold: zoh (the idealised 'ideal' hold "
                              "has no time inside the period); valid: a whole delay with "
                              "'ideal'", key="delay")
        object.__setattr__(self, "mass", m)
        object.__setattr__(self, "friction", b0)
        object.__setattr__(self, "rate_hz", r)
        # a whole delay stays an int: the plain hold's code path, bit for bit
        object.__setattr__(self, "delay", whole if frac == 0.0 else float(d))
        if self.correction is not None:
            # (a Correction, or its mapping as a scene gives it: before, anything was
            # taken and the analysis failed on it with an AttributeError)
            from hapsim.analysis.corrections import Correction
            corr = self.correction
            if not isinstance(corr, (Correction, dict)):
                raise ConfigError(f"must be a Correction or its mapping {{kind: ...}}, got "
                                  f"{corr!r}", key="correction")
            object.__setattr__(self, "correction", Correction.from_dict(corr))
        kh = num("stiffness", self.stiffness)
        if kh < 0:
            raise ConfigError(f"must be >= 0 [N/m], got {self.stiffness!r}", key="stiffness")
        check_product(kh, 1.0 / (r * r * m), "stiffness", "N/m", "kh T^2/m")
        object.__setattr__(self, "stiffness", kh)
        for key in ("hand_mass", "hand_damping", "grip_stiffness", "grip_damping"):
            # numbers (the grip's stiffness may be inf: rigid), checked below when the
            # grip is compliant; before, a word was a ValueError from rigid
            v = num(key, getattr(self, key), finite=False)
            if math.isnan(v):
                raise ConfigError(f"must be a number, got {v!r}", key=key)
            object.__setattr__(self, key, v)
        if not self.rigid:
            mh, bh = float(self.hand_mass), float(self.hand_damping)
            if not (0 < mh < m) or not (0 <= bh <= b0) or not (self.grip_stiffness > 0) \
                    or not (self.grip_damping >= 0):
                raise ConfigError("a compliant grip needs 0 < hand_mass < mass, 0 <= "
                                  "hand_damping <= friction, grip_stiffness > 0, "
                                  "grip_damping >= 0", key="hand")
            if self.hold != "zoh":
                raise ConfigError("a compliant grip needs the zoh hold", key="hold")

    @property
    def rigid(self) -> bool:
        """Whether the hand is rigidly attached (or absent): one moving body."""
        return not math.isfinite(float(self.grip_stiffness))

    @property
    def generic(self) -> bool:
        """Whether the loop needs the general plant/controller path (hand, real spring or
        correction)."""
        return self.correction is not None or not self.rigid or self.stiffness > 0

    @property
    def delay_whole(self) -> int:
        """``m = floor(d)``: whole periods of the delay [samples]."""
        return int(math.floor(self.delay))

    @property
    def delay_fraction(self) -> float:
        """``f = d - floor(d)`` in ``[0, 1)``: the part of a period by which the force
        switches inside the period (:mod:`hapsim.analysis.subsample`) [-]; 0 for a whole
        delay."""
        return float(self.delay - math.floor(self.delay))

    @property
    def period(self) -> float:
        """Sample period ``T = 1 / rate_hz`` [s]."""
        return 1.0 / self.rate_hz

    @property
    def b0_T_over_m(self) -> float:
        """Dimensionless friction ``b0 T / m`` [-] (the paper's normalised ``b0``)."""
        return self.friction * self.period / self.mass

    @classmethod
    def from_device(cls, device, rate_hz: float, member=None, *,
                    correction=True) -> "LoopModel":
        """Loop model of a scene's device.

        Parameters
        ----------
        device : hapsim.scene.Device
            Anything with ``mass`` [kg], ``friction`` [N s/m], ``delay`` [samples] and
            ``hold`` attributes; optionally ``hand`` and ``correction``.
        rate_hz : float > 0
            Sample rate [Hz].
        member : array_like, shape (4,), optional
            ``(mh, bh, kg, bg)`` of the hand family (:mod:`hapsim.analysis.hand`); default
            its nominal member. The loop's ``mass``/``friction`` are then handle + hand.
        correction : bool or Correction, optional
            True: the device's own correction; False: none; or the correction to use.

        Returns
        -------
        LoopModel

        Raises
        ------
        ConfigError
            As for the constructor.
        """
        from hapsim.analysis.corrections import Correction
        from hapsim.analysis.hand import nominal_member

        m, b0 = float(device.mass), float(getattr(device, "friction", 0.0))
        hand = getattr(device, "hand", None)
        kw = {}
        if hand is not None or member is not None:
            row = (np.asarray(member, float) if member is not None
                   else nominal_member(hand))
            mh, bh, kg, bg = row[:4]
            m, b0 = m + mh, b0 + bh
            if row.size > 4 and row[4] > 0:
                kw["stiffness"] = float(row[4])
            if math.isfinite(kg):
                kw.update(hand_mass=float(mh), hand_damping=float(bh),
                          grip_stiffness=float(kg), grip_damping=float(bg))
        if correction is True:
            corr = Correction.from_dict(getattr(device, "correction", None))
        else:
            corr = correction or None
        return cls(mass=m, friction=b0, rate_hz=rate_hz, delay=getattr(device, "delay", 1),
                   hold=getattr(device, "hold", "zoh"), correction=corr, **kw)

    def to_dict(self) -> dict:
        """JSON-ready dict of the fields.

        Returns
        -------
        dict
            ``mass`` [kg], ``friction`` [N s/m], ``rate_hz`` [Hz], ``delay`` [samples],
            ``hold``.
        """
        out = {"mass": self.mass, "friction": self.friction, "rate_hz": self.rate_hz,
               "delay": self.delay, "hold": self.hold}
        if not self.rigid:
            out.update(hand_mass=self.hand_mass, hand_damping=self.hand_damping,
                       grip_stiffness=self.grip_stiffness, grip_damping=self.grip_damping)
        if self.stiffness > 0:
            out["stiffness"] = self.stiffness
        if self.correction is not None:
            out["correction"] = self.correction.to_dict()
        return out


# --------------------------------------------------------------------------- helpers

def _phi(x: float) -> tuple[float, float, float]:
    """``(psi, phi1, phi0)`` of ``x = b0 T / m``, accurate for small ``x``.

    ``psi = (1 - e^-x)/x``, ``phi1 = (e^-x - 1 + x)/x^2``, ``phi0 = (1 - e^-x - x e^-x)/x^2``;
    all tend to ``(1, 1/2, 1/2)`` as ``x -> 0``.
    """
    if x < 0.1:
        psi = phi1 = phi0 = 0.0
        term = 1.0  # (-x)^j / j!
        for j in range(25):
            psi += term / (j + 1)
            phi1 += term / ((j + 1) * (j + 2))
            phi0 += term * (j + 1) / ((j + 1) * (j + 2))
            term *= -x / (j + 1)
        return psi, phi1, phi0
    em = math.expm1(-x)  # e^-x - 1
    a = em + 1.0
    return -em / x, (em + x) / (x * x), (-em - x * a) / (x * x)


def zoh_state_space(mass: float, friction: float, period: float):
    """Exact zero-order-hold discretisation of ``m x'' + b0 x' = f``.

    Parameters
    ----------
    mass : float > 0
        Mass ``m`` [kg].
    friction : float >= 0
        Viscous friction ``b0`` [N s/m].
    period : float > 0
        Hold period ``T`` [s].

    Returns
    -------
    Ad : ndarray, shape (2, 2)
        State transition of ``[x, v]`` ([m], [m/s]) over one period.
    Bd : ndarray, shape (2,)
        Response of ``[x, v]`` to a unit force held over the period [m/N, m/(N s)].

    Notes
    -----
    Closed form, with ``x = b0 T / m``, ``a = e^-x``::

        Ad = [[1, T psi], [0, a]],   Bd = [T^2/m phi1, T/m psi]
        psi = (1 - a)/x,  phi1 = (a - 1 + x)/x^2

    (``b0 = 0``: ``Ad = [[1, T], [0, 1]]``, ``Bd = [T^2/(2m), T/m]``). Equal to
    ``expm([[A, b], [0, 0]] T)`` of the continuous system (tested against scipy).

    Raises
    ------
    ConfigError
        If ``mass <= 0``, ``friction < 0`` or ``period <= 0``.
    """
    m, b0, T = float(mass), float(friction), float(period)
    if m <= 0 or T <= 0 or b0 < 0:
        raise ConfigError("need mass > 0, friction >= 0, period > 0; got "
                          f"mass={mass!r}, friction={friction!r}, period={period!r}")
    x = b0 * T / m
    psi, phi1, _ = _phi(x)
    a = math.exp(-x)
    Ad = np.array([[1.0, T * psi], [0.0, a]])
    Bd = np.array([T * T / m * phi1, T / m * psi])
    return Ad, Bd


def _plant_w(loop: LoopModel):
    """Dimensionless plant in ``w = z - 1``: ``(N~, D)``, ``N~ = N m / T^2`` (highest first)."""
    x = loop.b0_T_over_m
    psi, phi1, phi0 = _phi(x)
    one_minus_a = x * psi  # 1 - e^-x, accurate
    D = np.array([1.0, one_minus_a, 0.0])  # (z - 1)(z - a) = w (w + 1 - a)
    if loop.hold == "ideal":
        Nn = np.array([1.0, 1.0])  # z
        if x > 0:
            D = D / psi  # eq. (4): times (b0T/m) / (1 - e^-b0T/m)
    else:
        Nn = np.array([phi1, phi1 + phi0])  # phi1 z + phi0
    return Nn, D


def _split_plant_w(loop: LoopModel):
    """Split-hold plant of a fractional delay, in ``w``: ``(Nf~, D, Nvf~)``.

    ``x = (T^2/m) Nf~ / (z D) u[n-m]`` and ``v = (T/m) Nvf~ / (z D) u[n-m]`` (module
    :mod:`hapsim.analysis.subsample`: ``c (zI - Phi)^-1 (Gamma0 + Gamma1/z)``), ``D`` the
    plain hold's denominator. Rigid body: closed form on ``Phi = [[1, p], [0, a]]``, where
    ``c adj(zI - Phi) g = (z - a) g1 + p g2`` (position) and ``(z - 1) g2`` (velocity);
    compliant grip or real stiffness: :func:`split_numerator_w` on the state space.
    """
    m, T, f = loop.mass, loop.period, loop.delay_fraction
    if loop.rigid and not loop.stiffness > 0:
        Phi, G0, G1 = split_hold_body(m, loop.friction, T, f)
        _, D = _plant_w(loop)
        p, one_minus_a = Phi[0, 1], D[1]

        def pos(g):        # (z - a) g1 + p g2 = g1 w + (g1 (1 - a) + p g2)
            return np.array([g[0], g[0] * one_minus_a + p * g[1]])
        Nf = np.polyadd(np.convolve([1.0, 1.0], pos(G0)), pos(G1)) * (m / (T * T))
        Nvf = np.polyadd(np.convolve([1.0, 1.0], [G0[1], 0.0]), [G1[1], 0.0]) * (m / T)
        return Nf, D, Nvf
    from hapsim.analysis.hand import body_zoh
    member = (loop.hand_mass, loop.hand_damping, loop.grip_stiffness, loop.grip_damping,
              loop.stiffness)
    mc, bc = m - loop.hand_mass, loop.friction - loop.hand_damping
    Aw, _ = body_zoh(mc, bc, member, T)
    W0, G0 = body_zoh(mc, bc, member, (1.0 - f) * T)
    _, Gf = body_zoh(mc, bc, member, f * T)
    G1 = Gf + W0 @ Gf
    rows = np.eye(Aw.shape[0])
    return (split_numerator_w(Aw, G0, G1, rows[0]) * (m / (T * T)), np.poly(Aw),
            split_numerator_w(Aw, G0, G1, rows[1]) * (m / T))


def _compliant_plant_w(loop: LoopModel):
    """State-space plant in ``w`` (compliant grip and/or real stiffness): ``(Nn, D, Nvn)``,
    scaled by the total mass.

    ``x = (T^2/m) Nn/D u`` and ``v = (T/m) Nvn/D u`` (handle position and velocity); from
    the delta-operator matrix ``Aw = Ad - I`` of :func:`hapsim.analysis.hand.body_zoh`:
    ``D = det(w I - Aw)``, ``c (w I - Aw)^-1 Bd = [det(w I - Aw + Bd c) - D] / D``. The
    ideal hold (rigid only) is the impulse-invariant image ``Ad = e^(AT)``,
    ``Bd = T Ad b`` (:func:`hapsim.analysis.hand.ideal_rows`); it has no velocity output.
    """
    from hapsim.analysis.hand import body_zoh, ideal_rows

    m, T = loop.mass, loop.period
    if loop.hold == "ideal":
        tr, det, g = (float(v) for v in ideal_rows(m, loop.friction, loop.stiffness, T))
        # x[n+1] = tr x[n] - det x[n-1] + g u: D = z^2 - tr z + det, N = g z (in w)
        return (np.array([1.0, 1.0]) * g * (m / (T * T)),
                np.array([1.0, 2.0 - tr, 1.0 - tr + det]), None)
    member = (loop.hand_mass, loop.hand_damping, loop.grip_stiffness, loop.grip_damping,
              loop.stiffness)
    Aw, Bd = body_zoh(m - loop.hand_mass, loop.friction - loop.hand_damping, member, T)
    D = np.poly(Aw)

    def num(i):
        c = np.zeros(Aw.shape[0])
        c[i] = 1.0
        return (np.poly(Aw - np.outer(Bd, c)) - D)[1:]
    return num(0) * (m / (T * T)), D, num(1) * (m / T)


def _plant_vel_w(loop: LoopModel):
    """Handle velocity numerator ``Nvn`` in ``w`` of the rigid ``"zoh"`` plant (None for
    ``"ideal"``): ``v = (T/m) psi (z - 1) / D u``, i.e. ``Nvn = psi w``."""
    if loop.hold != "zoh":
        return None
    psi, _, _ = _phi(loop.b0_T_over_m)
    return np.array([psi, 0.0])



def w_to_z(p):
    """Re-express a polynomial in ``w = z - 1`` as one in ``z``.

    Parameters
    ----------
    p : array_like of float, shape (n + 1,)
        Coefficients in ``w``, highest power first.

    Returns
    -------
    ndarray of float
        Coefficients in ``z``, highest power first (Horner's scheme on ``z - 1``; leading
        zeros trimmed, ``[0.0]`` for the zero polynomial).
    """
    out = np.array([0.0])
    zm1 = np.array([1.0, -1.0])
    for c in p:
        # np.polyadd(np.polymul(out, zm1), [c]), the same operations without its two
        # np.poly1d (their trim_zeros were three quarters of this function's time, and a
        # loop's poles ask for it three times): polymul convolves the factors with their
        # leading zeros dropped ([0.0] for none left), polyadd adds [c] zero-padded
        nz = np.flatnonzero(out)
        prod = np.convolve(out[nz[0]:] if nz.size else np.zeros(1), zm1)
        pad = np.zeros(prod.size)
        pad[-1] = c
        out = prod + pad
    return np.trim_zeros(out, "f") if np.any(out) else np.array([0.0])


def plant(loop: LoopModel):
    """Pulse transfer ``G(z) = N(z) / D(z)`` from force samples [N] to position samples [m].

    Parameters
    ----------
    loop : LoopModel

    Returns
    -------
    N : ndarray, shape (n,)
        Numerator coefficients in ``z``, highest power first [m/N].
    D : ndarray, shape (3,)
        Denominator coefficients in ``z``, highest power first (monic for ``"zoh"``).

    Notes
    -----
    ``"ideal"``: ``N = T^2/m z``, ``D = (z - 1)^2`` (Florens et al. eqs. (2)-(3)); for
    ``b0 > 0``, ``D = (z - 1)(z - e^(-b0T/m)) (b0T/m) / (1 - e^(-b0T/m))`` (eq. (4)).
    ``"zoh"``: ``Z{(1 - e^(-sT))/s / (m s^2 + b0 s)}``, i.e.
    ``N = T^2/m (phi1 z + phi0)``, ``D = (z - 1)(z - e^(-b0T/m))`` with
    ``phi1 = (e^-x - 1 + x)/x^2``, ``phi0 = (1 - e^-x - x e^-x)/x^2``, ``x = b0T/m``
    (``b0 = 0``: ``N = T^2/(2m) (z + 1)``). Equal to ``scipy.signal.cont2discrete``.
    """
    Nn, D = (_plant_w(loop) if loop.rigid and not loop.stiffness > 0
             else _compliant_plant_w(loop)[:2])
    T = loop.period
    return w_to_z(Nn) * (T * T / loop.mass), w_to_z(D)


def characteristic(loop: LoopModel):
    """Polynomials of the closed loop ``P(z) K + Q(z) B + R(z) = 0``.

    Parameters
    ----------
    loop : LoopModel

    Returns
    -------
    P : ndarray
        ``z N(z)`` [m/N], highest power first (``"ideal"``: ``T^2/m z``).
    Q : ndarray
        ``(z - 1) N(z) / T`` [m/(N s)], highest power first (``"ideal"``: ``T/m (z - 1)``).
    R : ndarray
        ``z^(d+1) D(z)`` [-], highest power first (``"ideal"``: ``z^d D(z)``).

    Notes
    -----
    Florens et al. Sec. 6 eq. (1). For ``"ideal"`` the common factor ``z`` of
    ``z N``, ``(z - 1) N`` and ``z^(d+1) D`` (``N = T^2/m z``) is removed, so with
    ``m = T = 1`` and ``b0 = 0`` these are exactly their eq. (2) (``d = 0``: ``P = z``,
    ``Q = z - 1``, ``R = (z - 1)^2``) and eq. (3) (``d = 1``: ``R = z (z - 1)^2``); with
    ``b0 > 0``, ``d = 1``, exactly eq. (4) (``R = z (z - 1)(z - e^-b0) b0/(1 - e^-b0)``).
    The closed loop then has ``d + 2`` poles (``"ideal"``) or ``d + 3`` (``"zoh"``).
    """
    Pw, Qw, D, e = char_parts(loop)
    T, m = loop.period, loop.mass
    return (w_to_z(Pw) * (T * T / m), w_to_z(Qw) * (T / m),
            np.concatenate([w_to_z(D), np.zeros(e)]))


def char_parts(loop: LoopModel):
    """Low-degree pieces of the characteristic function, never expanded.

    Returns ``(P~, Q~, D, e)`` (polynomials in ``w = z - 1``, highest first, degree <= 2)
    such that the closed loop is ``kappa P~(w) + beta Q~(w) + (1 + w)^e D(w) = 0``; ``e`` is
    ``d + 1`` (``"zoh"``) or ``d`` (``"ideal"``). For the ideal hold ``N = T^2/m z``, so
    ``z N``, ``(z - 1) N`` and ``z^(d+1) D`` share the factor ``z``; it is removed (it only
    adds a spurious pole at ``z = 0``), which leaves exactly Florens et al.'s eqs. (2)-(4):
    ``P~ = z``, ``Q~ = z - 1``, ``R~ = z^d D``. The ZOH numerator ``phi1 z + phi0`` has
    ``phi0 > 0``: no common factor there. Evaluating ``(1 + w)^e`` as a power keeps full precision at every
    delay, where the expanded polynomial (binomial coefficients up to ``C(e, e/2)``, 1e14 at
    ``e = 50``) loses it all.

    Parameters
    ----------
    loop : LoopModel

    Returns
    -------
    P, Q, D : ndarray, shape (<= 3,)
        Coefficients in ``w``, highest first (``loop.generic``: the expanded ``P~``,
        ``Q~``, ``R~``).
    e : int
        The power of ``(1 + w)`` multiplying ``D`` (0 when ``loop.generic``).
    """
    got = loop.__dict__.get("_char_parts")
    if got is None:
        got = _char_parts(loop)
        loop.__dict__["_char_parts"] = got
    return got


def _char_parts(loop: LoopModel):
    """:func:`char_parts` computed (its pieces are read-only copies: the loop keeps them,
    in its ``__dict__``, outside the dataclass' fields, for every later call; the loop is
    frozen, so they stay its own: a stability sweep asked for them once per evaluation,
    a sixth of a grid's time)."""
    P, Q, D, e = _char_parts_of(loop)
    out = []
    for a in (P, Q, D):
        a = np.array(a, copy=True)
        a.setflags(write=False)
        out.append(a)
    dP, dQ, dD = (np.polyder(a) for a in out)
    for a in (dP, dQ, dD):
        a.setflags(write=False)
    loop.__dict__["_char_derivatives"] = (dP, dQ, dD)
    return out[0], out[1], out[2], e


def _char_parts_of(loop: LoopModel):
    """The computation of :func:`char_parts` (same returns)."""
    if loop.delay_fraction > 0:
        # the split hold (hapsim.analysis.subsample): the plant N~f / (z D) behind the
        # whole delay m, i.e. one more pole (the force held from the previous period)
        Nf, D, Nvf = _split_plant_w(loop)
        if loop.generic:
            from hapsim.analysis.corrections import correction_polynomials
            P, Q, R = correction_polynomials(loop.correction, Nf, np.convolve([1.0, 1.0], D),
                                             Nvf, delay=loop.delay_whole, mass=loop.mass,
                                             period=loop.period, lead=loop.delay)
            return P, Q, R, 0
        return (np.convolve([1.0, 1.0], Nf), np.convolve([1.0, 0.0], Nf), D,
                loop.delay_whole + 2)
    if loop.generic:
        # a hand behind a grip or a correction: (P~, Q~, R~) expanded, e = 0
        # (hapsim.analysis.corrections.correction_polynomials)
        from hapsim.analysis.corrections import correction_polynomials
        if loop.rigid and not loop.stiffness > 0:
            Nn, D = _plant_w(loop)
            Nvn = _plant_vel_w(loop)
        else:
            Nn, D, Nvn = _compliant_plant_w(loop)
        P, Q, R = correction_polynomials(loop.correction, Nn, D, Nvn, delay=loop.delay,
                                         mass=loop.mass, period=loop.period)
        return P, Q, R, 0
    Nn, D = _plant_w(loop)
    e = loop.delay + 1
    if loop.hold == "ideal":
        Nn, e = np.array([1.0]), e - 1
    # np.polymul's products, without its two np.poly1d per call (the stability sweeps call
    # this per evaluation: numpy's trim_zeros in them was a third of a sweep's time); the
    # same np.convolve of the same arrays, Nn's leading zeros dropped as poly1d drops them
    Nn = np.atleast_1d(np.asarray(Nn, dtype=float))
    nz = np.flatnonzero(Nn)
    Nn = Nn[nz[0]:] if nz.size else np.zeros(1)
    return np.convolve([1.0, 1.0], Nn), np.convolve([1.0, 0.0], Nn), D, e


def char_eval(loop: LoopModel, kappa: float, beta: float, w, *, derivative: bool = False):
    """Characteristic function ``kappa P~ + beta Q~ + (1 + w)^e D`` at ``w = z - 1``.

    Parameters
    ----------
    loop : LoopModel
    kappa, beta : float
        Dimensionless ``K T^2 / m`` and ``B T / m``.
    w : complex or ndarray of complex
        Points ``w = z - 1``.
    derivative : bool, optional
        Also return the derivative with respect to ``w``.

    Returns
    -------
    f : complex or ndarray
        Value (dimensionless), same shape as ``w``.
    df : complex or ndarray
        Derivative, when ``derivative``.

    Notes
    -----
    Florens et al. Sec. 6 eq. (1) in the delta variable (module docstring); the delay factor
    ``z^e`` is a power, so the relative error is ``O(e eps)`` at any delay.
    """
    P, Q, D, e = char_parts(loop)
    w = np.asarray(w, dtype=complex)
    z = 1.0 + w
    ze = z ** e
    f = kappa * _horner(P, w) + beta * _horner(Q, w) + ze * _horner(D, w)
    if not derivative:
        return f
    dP, dQ, dD = loop.__dict__["_char_derivatives"]      # np.polyder of each, kept
    zem1 = z ** (e - 1) if e > 0 else np.zeros_like(z)
    df = (kappa * _horner(dP, w) + beta * _horner(dQ, w)
          + e * zem1 * _horner(D, w) + ze * _horner(dD, w))
    return f, df


def _horner(p, x):
    """``np.polyval(p, x)`` for an ndarray ``p`` (not a ``poly1d``): the same operations in
    the same order (``x = asanyarray(x)``, ``y = zeros_like(x)``, then ``y = y x + c`` per
    coefficient), bit for bit, without its other argument handling (a stability sweep
    evaluates ~150,000 times)."""
    x = np.asanyarray(x)
    y = np.zeros_like(x)
    for pv in p:
        y = y * x + pv
    return y
