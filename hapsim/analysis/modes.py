"""Closed-loop poles as physical modes (the THS read as a mass-spring-damper).

A discrete pole ``z`` of the sampled closed loop is mapped to its continuous
equivalent ``s = ln(z) / T`` and then to the oscillator ``m s^2 + b s + k = 0`` that
has ``s`` (and its conjugate) as poles, with ``m`` the real (hand + handle) mass:

    k = m |s|^2,     b = -2 m Re(s),
    f0_hz = |s| / (2 pi) = sqrt(k / m) / (2 pi),   damping_ratio = b / (2 sqrt(k m)) = -Re(s) / |s|.

``f0_hz`` is therefore the *undamped natural frequency* of the equivalent oscillator,
not the damped frequency ``|Im s| / (2 pi)``; the two coincide for light damping.
This is the inverse map of Florens, Voda & Urma, Sec. 5 ((K, B) -> (k, b)) and
docs/design.md, 'The inverse map'.

Real poles are kept as ``kind="real"`` modes, converted with the same formulas. For
``z in (0, 1)`` their ``k`` and ``b`` are those of the critically damped oscillator with a
double pole at ``s`` (``damping_ratio = 1``): indicative only, since a single real pole
is not an oscillator. A real pole
``z in (0, 1)`` has a real ``s < 0``. A real *negative* ``z`` has no continuous
equivalent (it alternates sign every sample): ``s`` is then the principal value
``(ln|z| + i pi) / T``, i.e. an oscillation at the Nyquist frequency, and the mode is still
reported as ``kind="real"``. A pole at ``z = 0`` (a pure delay state, dead-beat) gives
``s = -inf``; its ``k``, ``b`` and ``f0_hz`` are ``inf``.

**A 2-D or 3-D scene's own modes** (:func:`scene_modes_nd`). The modes of a 2-D or 3-D scene on its own: the eigenfrequencies and damping ratios of
the centred scheme, linearised at rest, with the grounds and the port held still.

With the moving masses' positions ``x`` (n per mass) and the links linearised at rest
(:func:`hapsim.analysis.virtual_network.link_blocks`: exact for ``length: 0`` springs), the
forces are ``F = -K x - (B / T)(x - x_prev)`` and the scheme
``x[n+1] = 2 x[n] - x[n-1] + T^2 M^-1 F[n]`` is the one-step map

    [x[n+1]; x[n]] = [[2 I - T^2 M^-1 K - T M^-1 B, -(I - T M^-1 B)], [I, 0]] [x[n]; x[n-1]]

whose eigenvalues ``z`` give each mode's frequency ``arg(z) / (2 pi T)`` [Hz] and damping
ratio ``-ln|z| / |ln z|`` (the discrete poles read as ``s = ln(z) / T``). A square mesh of
masses ``m`` joined to their four neighbours by ``length: 0`` springs ``(K, B)``, its edge
held, has the closed form of the discrete membrane (the discrete Laplacian's eigenvalues
``mu_pq = 4 [sin^2(p pi / (2 (N + 1))) + sin^2(q pi / (2 (N + 1)))]``, each mode
``z^2 - (2 - a - c) z + (1 - c) = 0`` with ``a = mu K T^2 / m``, ``c = mu B T / m``):
``tests/test_membrane.py`` checks one against the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapsim.outputs import finite_or_none

__all__ = ["Mode", "modes_from_poles", "rendered_pair", "log_abs", "log_z", "OBSERVABLE_TOL",
           "ModeND", "SceneModesND", "scene_modes_nd"]

#: A mode whose :attr:`Mode.participation` at the port is below this is not felt: the hand
#: cannot excite it nor see it (e.g. the antisymmetric mode of a string held at its centre,
#: participation ~1e-16: round-off of an exact zero). Such modes are reported as modes of
#: the object, never as the rendered pair.
OBSERVABLE_TOL = 1e-8

#: Poles with ``|Im z| <= _REAL_TOL * max(1, |z|)`` are treated as real.
_REAL_TOL = 1e-12


def log_abs(z: complex) -> float:
    """``ln |z|`` computed accurately for ``z`` near 1.

    Parameters
    ----------
    z : complex
        A pole.

    Returns
    -------
    float
        ``ln |z|`` (``-inf`` for ``z = 0``). Uses ``log1p(2 Re w + |w|^2) / 2`` with
        ``w = z - 1`` when ``|w|`` is small, so that damping near the unit circle keeps
        its relative precision.
    """
    z = complex(z)
    if z == 0:
        return -math.inf
    w = z - 1.0
    if abs(w) < 0.5:
        return 0.5 * math.log1p(2.0 * w.real + w.real * w.real + w.imag * w.imag)
    return math.log(abs(z))


def log_z(z: complex, w: complex | None = None) -> complex:
    """Principal value of ``ln z``, accurate near ``z = 1``.

    Parameters
    ----------
    z : complex
        A pole.
    w : complex, optional
        ``z - 1`` if known more accurately than by subtraction.

    Returns
    -------
    complex
        ``ln|z| + i arg z``, with ``arg z in (-pi, pi]``; ``-inf`` for ``z = 0``.
    """
    z = complex(z)
    if z == 0:
        return complex(-math.inf, 0.0)
    if w is not None and abs(w) < 0.5:
        w = complex(w)
        re = 0.5 * math.log1p(2.0 * w.real + w.real * w.real + w.imag * w.imag)
        return complex(re, math.atan2(w.imag, 1.0 + w.real))
    return complex(log_abs(z), math.atan2(z.imag, z.real))


@dataclass(frozen=True)
class Mode:
    """One mode of the sampled closed loop, read as a mass-spring-damper.

    Attributes
    ----------
    z : complex
        Discrete pole (for a pair: the member with ``Im z > 0``).
    s : complex
        Continuous equivalent ``ln(z) / T`` [1/s] (principal value).
    f0_hz : float
        Undamped natural frequency ``|s| / (2 pi) = sqrt(k/m) / (2 pi)`` [Hz].
    damping_ratio : float
        ``-Re(s) / |s| = b / (2 sqrt(k m))`` [-]; negative for a growing mode.
    k : float
        Equivalent stiffness ``m |s|^2`` [N/m] (``m``: the loop's real mass).
    b : float
        Equivalent damping ``-2 m Re(s)`` [N s/m] (whole THS damping, real + virtual).
    kind : str
        ``"pair"`` (complex-conjugate pair) or ``"real"`` (single real pole).
    participation : float or None
        How much the mode shows at the port: ``|residue|`` of the transfer from a force on
        the device to the port position, relative to the largest one [-]
        (:func:`hapsim.analysis.scene_check.check_scene`); None where not computed (a
        single THS loop, where every pole is a pole of that transfer).
    """

    z: complex
    s: complex
    f0_hz: float
    damping_ratio: float
    k: float
    b: float
    kind: str
    participation: float | None = None

    @property
    def modulus(self) -> float:
        """``|z|`` [-]: the mode decays iff ``< 1``."""
        return abs(self.z)

    @property
    def stable(self) -> bool:
        """True iff ``|z| < 1``."""
        return abs(self.z) < 1.0

    def to_dict(self) -> dict:
        """JSON-ready dict; non-finite floats become ``None``.

        Returns
        -------
        dict
            Keys ``z_re, z_im, abs_z, s_re, s_im, f0_hz, damping_ratio, k, b, kind,
            participation``.
        """
        f = finite_or_none
        return {"z_re": f(self.z.real), "z_im": f(self.z.imag), "abs_z": f(abs(self.z)),
                "s_re": f(self.s.real), "s_im": f(self.s.imag), "f0_hz": f(self.f0_hz),
                "damping_ratio": f(self.damping_ratio), "k": f(self.k), "b": f(self.b),
                "kind": self.kind, "participation": f(self.participation)}


def mode_from_pole(z: complex, mass: float, period: float, kind: str,
                   w: complex | None = None, participation: float | None = None) -> Mode:
    """Build one :class:`Mode` from a discrete pole.

    Parameters
    ----------
    z : complex
        Discrete pole.
    mass : float > 0
        Real mass ``m`` [kg].
    period : float > 0
        Sample period ``T`` [s].
    kind : {"pair", "real"}
        Mode kind.
    w : complex, optional
        ``z - 1`` computed more accurately than by subtraction.
    participation : float, optional
        :attr:`Mode.participation`.

    Returns
    -------
    Mode
        With ``s = ln(z)/T``, ``k = m|s|^2``, ``b = -2 m Re s`` (docs/design.md,
        'The inverse map').
    """
    z = complex(z)
    s = log_z(z, w) / period
    if z == 0:
        return Mode(z=z, s=complex(-math.inf, 0.0), f0_hz=math.inf, damping_ratio=1.0, k=math.inf, b=math.inf,
                    kind=kind, participation=participation)
    wn = abs(s)
    k = mass * wn * wn
    b = -2.0 * mass * s.real
    zeta = -s.real / wn if wn > 0 else math.nan
    return Mode(z=z, s=s, f0_hz=wn / (2.0 * math.pi), damping_ratio=zeta, k=k, b=b,
                kind=kind, participation=participation)


def modes_from_poles(poles, mass: float, period: float, *, w=None,
                     participation=None) -> list[Mode]:
    """Group the poles of a real polynomial into modes.

    Parameters
    ----------
    poles : array_like of complex, shape (n,)
        Closed-loop poles, closed under conjugation (roots of a real polynomial).
    mass : float > 0
        Real mass ``m`` [kg] used for ``k`` and ``b``.
    period : float > 0
        Sample period ``T`` [s].
    w : array_like of complex, shape (n,), optional
        ``poles - 1`` computed accurately (e.g. roots of the characteristic polynomial in
        ``w = z - 1``); improves ``s`` near ``z = 1``.
    participation : array_like of float, shape (n,), optional
        :attr:`Mode.participation` of each pole (a pair takes the larger of its two).

    Returns
    -------
    list of Mode
        One ``"pair"`` mode per conjugate pair (represented by ``Im z > 0``), one
        ``"real"`` mode per real pole, sorted least damped first (largest ``|z|`` first;
        ties: pairs before real modes, then by frequency).

    Raises
    ------
    ValueError
        If the complex poles are not closed under conjugation.
    """
    z = np.asarray(poles, dtype=complex).ravel()
    ww = None if w is None else np.asarray(w, dtype=complex).ravel()
    tol = _REAL_TOL * np.maximum(1.0, np.abs(z))
    upper = z.imag > tol
    lower = z.imag < -tol
    if int(upper.sum()) != int(lower.sum()):
        raise ValueError("poles are not closed under conjugation: "
                         f"{int(upper.sum())} with Im > 0, {int(lower.sum())} with Im < 0")
    modes = []
    for i in range(z.size):
        if lower[i]:
            continue
        kind = "pair" if upper[i] else "real"
        zi = z[i] if upper[i] else complex(z[i].real, 0.0)
        wi = None
        if ww is not None:
            wi = ww[i] if upper[i] else complex(ww[i].real, 0.0)
        pi = None
        if participation is not None:
            pi = float(participation[i])
            if upper[i]:
                j = int(np.argmin(np.where(lower, np.abs(z - np.conj(z[i])), np.inf)))
                pi = max(pi, float(participation[j]))
        modes.append(mode_from_pole(zi, mass, period, kind, wi, pi))
    modes.sort(key=lambda md: (-abs(md.z), md.kind != "pair", md.f0_hz))
    return modes


def rendered_pair(modes) -> Mode | None:
    """The rendered oscillator: the least damped complex pair the hand can feel.

    Parameters
    ----------
    modes : iterable of Mode
        Modes of one closed loop.

    Returns
    -------
    Mode or None
        The ``"pair"`` mode with the largest ``|z|`` (Florens et al. Sec. 5,
        docs/design.md, 'The inverse map') among those observable at the port
        (participation None or at least
        :data:`OBSERVABLE_TOL`), or None when there is no such pair.
    """
    best = None
    for md in modes:
        if md.participation is not None and not md.participation >= OBSERVABLE_TOL:
            continue
        if md.kind == "pair" and (best is None or abs(md.z) > abs(best.z)):
            best = md
    return best


@dataclass(frozen=True)
class ModeND:
    """One oscillating mode: ``frequency_hz`` [Hz], ``damping_ratio`` [-], the ``axis``
    its shape moves most along (0..n-1), its ``shape`` (moving masses x n, unit norm,
    real part at the largest entry's phase) and the discrete pole ``z``."""

    frequency_hz: float
    damping_ratio: float
    axis: int
    shape: np.ndarray
    z: complex

    def to_dict(self) -> dict:
        """``frequency_hz``, ``damping_ratio``, ``axis`` (JSON-ready).

        Returns
        -------
        dict
            Eigenfrequency [Hz], damping ratio [-] and axis (int); no ``shape``, no ``z``.
        """
        return {"frequency_hz": self.frequency_hz, "damping_ratio": self.damping_ratio,
                "axis": self.axis}


@dataclass(frozen=True)
class SceneModesND:
    """Every oscillating mode of a scene, lowest frequency first; ``names`` are the moving
    masses (the rows of each shape), ``spectral_radius`` the largest ``|z|`` (> 1:
    the scheme diverges) and ``states`` the size of the one-step map."""

    modes: tuple
    names: tuple
    spectral_radius: float
    states: int

    @property
    def stable(self) -> bool:
        """Spectral radius within 1e-9 of 1 or below (marginal counts as stable)."""
        return self.spectral_radius <= 1.0 + 1e-9


def scene_modes_nd(scene) -> SceneModesND:
    """The modes of an n-D scene's virtual masses (module docstring).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene (a port, if any, is held at rest like a ground).

    Returns
    -------
    SceneModesND

    Raises
    ------
    ConfigError
        No moving mass, more than
        :data:`hapsim.analysis.virtual_network.MAX_STATES_ND` states, or a degenerate
        Euclidean link (:func:`hapsim.analysis.virtual_network.link_blocks`).
    """
    from hapsim.analysis.virtual_network import MAX_STATES_ND, link_blocks
    from hapsim.errors import ConfigError
    n, T = scene.dimension, scene.period
    moving = [m for m in scene.masses if m.kind == "mass"]
    if not moving:
        raise ConfigError("the scene has no moving mass: it has no modes", file=scene.path,
                          key="masses")
    N = n * len(moving)
    if 2 * N > MAX_STATES_ND:
        raise ConfigError(f"{2 * N} states (2 x {len(moving)} masses x {n} axes) exceed "
                          f"the {MAX_STATES_ND} analysed densely", file=scene.path,
                          key="masses")
    at = {m.name: i for i, m in enumerate(moving)}
    K = np.zeros((N, N))
    B = np.zeros((N, N))
    for _, a, b, Kl, Bl in link_blocks(scene):
        ia, ib = at.get(a), at.get(b) if b is not None else None
        for M, blk in ((K, Kl), (B, Bl)):
            if ia is not None:
                M[n * ia:n * ia + n, n * ia:n * ia + n] += blk
            if ib is not None:
                M[n * ib:n * ib + n, n * ib:n * ib + n] += blk
            if ia is not None and ib is not None:
                M[n * ia:n * ia + n, n * ib:n * ib + n] -= blk
                M[n * ib:n * ib + n, n * ia:n * ia + n] -= blk
    minv = np.repeat([1.0 / m.mass for m in moving], n)
    # axes that no link couples (length-0 springs only) are analysed one at a time: the
    # same eigenvalues, a smaller problem, and each mode along one axis exactly
    cross = np.ones((n, n), bool) ^ np.eye(n, dtype=bool)
    mask = np.tile(cross, (len(moving), len(moving)))
    groups = [np.arange(a, N, n) for a in range(n)] \
        if not (np.any(K[mask]) or np.any(B[mask])) else [np.arange(N)]
    modes, radius = [], 0.0
    for g in groups:
        Kg, Bg, mg = K[np.ix_(g, g)], B[np.ix_(g, g)], minv[g][:, None]
        I = np.eye(g.size)
        A = np.block([[2 * I - T * T * mg * Kg - T * mg * Bg, -(I - T * mg * Bg)],
                      [I, np.zeros_like(I)]])
        z, V = np.linalg.eig(A)
        radius = max(radius, float(np.max(np.abs(z))))
        for j in np.flatnonzero(z.imag > 1e-12):
            s = np.log(z[j]) / T
            full = np.zeros(N, complex)
            full[g] = V[:g.size, j]
            v = full.reshape(len(moving), n)
            k = np.unravel_index(np.argmax(np.abs(v)), v.shape)
            v = (v * np.exp(-1j * np.angle(v[k]))).real
            v = v / np.linalg.norm(v)
            modes.append(ModeND(float(np.angle(z[j]) / (2 * np.pi * T)),
                                float(-s.real / abs(s)), int(np.argmax((v * v).sum(0))),
                                v, complex(z[j])))
    modes.sort(key=lambda md: (md.frequency_hz, md.axis))
    return SceneModesND(tuple(modes), tuple(m.name for m in moving), radius, 2 * N)
