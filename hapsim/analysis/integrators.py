"""The methods compared: integrators of the virtual masses and their stability limits.

Every integrator is written here as a *linear* one-step map of the virtual network (contacts
taken engaged, the stiffest case), so that its poles, its accuracy against the continuous
network and its stability inside the whole THS loop (device mass, friction, hold, delay) are
eigenvalue problems. The numba kernels of :mod:`hapsim.kernels.schemes` and
:mod:`hapsim.kernels.cordis` run the same maps sample by sample; the tests check that the two
agree.

Closed-form limits (one mass ``m``, spring ``K`` and damper ``B`` to a ground; ``T`` period;
derivations in :mod:`hapsim.kernels.schemes`, Jury's criterion):

==================  ===========================================  =====================
integrator          stability                                    cost per sample
==================  ===========================================  =====================
centred             ``K < 4 m/T^2 - 2 B/T`` and ``B < 2 m/T``    O(links)
symplectic_euler    ``K < 4 m/T^2 + 2 B/T`` (any ``B >= 0``)     O(links), + 1 divide
exact               always (passive network: ``|e^(lambda T)|    O(N^2) dense
                    <= 1``)
==================  ===========================================  =====================

A network has one such limit per mode; for an undamped network both explicit schemes need
``T^2 lambda_max(M^-1 LK) < 4`` (``lambda_max``: largest eigenvalue of the stiffness
over the masses, ``LK`` the stiffness Laplacian). With a port the device closes the loop and
the limit is the spectral radius of :func:`closed_loop_matrix`; for a single port-ground
link it is :func:`hapsim.analysis.stability_limit` (the ``b = 0`` curve of Florens, Voda &
Urma, Sec. 6.2), whatever the integrator (no virtual mass is integrated).
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.network import INTEGRATORS, closed_loop

from hapsim.analysis.virtual_network import check_integrator
from hapsim.analysis.virtual_network import network as _network
from hapsim.analysis.virtual_network import virtual_blocks as _virtual_blocks
from hapsim.analysis.loop import STABILITY_TOL
from hapsim.analysis.scene_check import RIGID_TOL

__all__ = ["INTEGRATORS", "COST_ORDER", "oscillator_poles", "oscillator_limits",
           "virtual_update_matrix", "closed_loop_matrix", "continuous_network_eigenvalues",
           "continuous_loop_matrix", "StabilityMargin", "stability_margin",
           "calibrate_targets", "spectral_radius_of"]

#: Integrators from cheapest to dearest per sample (measured by ``hapsim bench``).
COST_ORDER = ("centred", "symplectic_euler", "exact")


def _check_integrator(integrator: str) -> None:
    check_integrator(integrator)


# --------------------------------------------------------------------------- one oscillator

def oscillator_poles(integrator: str, mass: float, K: float, B: float, period: float) -> np.ndarray:
    """Closed-form discrete poles of one virtual mass on a spring-damper to a ground.

    Parameters
    ----------
    integrator : {"centred", "symplectic_euler", "exact"}
    mass : float > 0
        Mass ``m`` [kg].
    K : float >= 0
        Stiffness [N/m].
    B : float >= 0
        Damping [N s/m].
    period : float > 0
        ``T`` [s].

    Returns
    -------
    ndarray of complex, shape (2,)
        Roots of ``z^2 + (kappa + beta - 2) z + (1 - beta)`` (centred),
        ``(1 + beta) z^2 + (kappa - beta - 2) z + 1`` (symplectic_euler), or
        ``exp(s T)`` with ``m s^2 + B s + K = 0`` (exact); ``kappa = K T^2/m``,
        ``beta = B T/m``.

    Raises
    ------
    ConfigError
        Unknown integrator.
    """
    _check_integrator(integrator)
    m, T = float(mass), float(period)
    kap, bet = K * T * T / m, B * T / m
    if integrator == "centred":
        c = [1.0, kap + bet - 2.0, 1.0 - bet]
    elif integrator == "symplectic_euler":
        c = [1.0 + bet, kap - bet - 2.0, 1.0]
    else:
        s = np.roots([m, B, K]).astype(complex)
        return np.exp(s * T)
    return np.roots(c).astype(complex)


def oscillator_limits(integrator: str, mass: float, period: float, B: float = 0.0) -> dict:
    """Closed-form stability limits of one virtual oscillator (module table).

    Parameters
    ----------
    integrator : {"centred", "symplectic_euler", "exact"}
    mass : float > 0
        ``m`` [kg].
    period : float > 0
        ``T`` [s].
    B : float >= 0, optional
        Damping [N s/m].

    Returns
    -------
    dict
        ``K_max`` [N/m] (largest stable K at this B; ``inf`` for exact), ``B_max``
        [N s/m] (largest stable B at K -> 0+; ``inf`` when none) and ``formula`` (str).
        Source: Jury's criterion on the characteristic quadratics of
        :func:`oscillator_poles` (derivation in :mod:`hapsim.kernels.schemes`).
    """
    _check_integrator(integrator)
    m, T = float(mass), float(period)
    if integrator == "centred":
        return {"K_max": 4 * m / T ** 2 - 2 * B / T, "B_max": 2 * m / T,
                "formula": "K < 4 m/T^2 - 2 B/T, B < 2 m/T (Jury on z^2 + (kappa+beta-2) z "
                           "+ 1 - beta)"}
    if integrator == "symplectic_euler":
        return {"K_max": 4 * m / T ** 2 + 2 * B / T, "B_max": math.inf,
                "formula": "K < 4 m/T^2 + 2 B/T, any B >= 0 (Jury on (1+beta) z^2 + "
                           "(kappa-beta-2) z + 1)"}
    return {"K_max": math.inf, "B_max": math.inf,
            "formula": "unconditionally stable for K, B >= 0 (poles exp(s T))"}


# --------------------------------------------------------------------------- networks

def virtual_update_matrix(scene, integrator: str | None = None, *, calibrated=None) -> np.ndarray:
    """One-step matrix of the virtual network alone (port and grounds held still).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene; contacts are taken engaged.
    integrator : str, optional
        Scheme; ``scene.integrator`` when None.
    calibrated : mapping, optional
        ``{link: (K, B)}`` overrides (required for ``target`` links).

    Returns
    -------
    ndarray, shape (2N, 2N)
        ``X[n+1] = A X[n]`` with ``X = [x; xp]`` (centred) or ``[x; v]`` of the N moving masses.

    Raises
    ------
    ConfigError
        Unknown integrator; uncalibrated target links.
    """
    integrator = integrator or getattr(scene, "integrator", "centred")
    _check_integrator(integrator)
    net = _network(scene, calibrated)
    return _virtual_blocks(net, integrator, scene.period)[0]


def continuous_network_eigenvalues(scene, *, calibrated=None) -> np.ndarray:
    """Eigenvalues ``lambda`` [1/s] of the continuous virtual network (port and grounds still).

    Parameters
    ----------
    scene : hapsim.scene.Scene
    calibrated : mapping, optional
        As :func:`virtual_update_matrix`.

    Returns
    -------
    ndarray of complex, shape (2N,)
        Eigenvalues of ``[[0, I], [-M^-1 LK_mm, -M^-1 LB_mm]]``: the exact modes the
        integrators approximate (``z = exp(lambda T)``).
    """
    net = _network(scene, calibrated)
    N = net.N
    Minv = 1.0 / net.masses
    A = np.zeros((2 * N, 2 * N))
    A[:N, N:] = np.eye(N)
    A[N:, :N] = -Minv[:, None] * net.LK[np.ix_(net.mob, net.mob)]
    A[N:, N:] = -Minv[:, None] * net.LB[np.ix_(net.mob, net.mob)]
    return np.linalg.eigvals(A)


def closed_loop_matrix(scene, integrator: str | None = None, *, calibrated=None,
                       gain: float = 1.0) -> np.ndarray:
    """Closed-loop state matrix of a scene, integrated by ``integrator``, felt through its device.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene (contacts engaged). Without a port: the virtual network alone.
    integrator : str, optional
        Scheme; ``scene.integrator`` when None.
    calibrated : mapping, optional
        ``{link: (K, B)}`` overrides (required for ``target`` links).
    gain : float, optional
        Every link's (K, B) multiplied by this (a gain-margin probe).

    Returns
    -------
    ndarray, shape (n, n)
        ``s[n+1] = A s[n]``; states: device (``"zoh"``: x, v, x_port[n-1]; ``"ideal"``: x,
        x[n-1]), the delay line ``F[n-1..n-d]``, then the virtual states: the matrix of
        :func:`hapsim.analysis.network.closed_loop` (state names there), which
        :func:`hapsim.analysis.scene_check.scene_state_matrix` also returns.

    Raises
    ------
    ConfigError
        Unknown integrator, uncalibrated targets, a port without device.
    """
    return closed_loop(scene, integrator, calibrated=calibrated, gain=gain)[0]


def continuous_loop_matrix(scene, *, calibrated=None) -> np.ndarray:
    """Continuous-time closed loop of a scene and its device: the reference of what is felt.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        With a port and device. ``target`` links count as ``K = k``, ``B = b - b0`` (the
        felt oscillator they ask for), other links as given (contacts engaged).
    calibrated : mapping, optional
        Overrides (K, B) per link.

    Returns
    -------
    ndarray, shape (2 + 2N, 2 + 2N)
        ``d/dt [x_dev, v_dev, x_m, v_m] = A [...]`` with
        ``m x_dev'' = -b0 x_dev' - LK_pp x_dev - LB_pp v_dev - LK_pm x_m - LB_pm v_m`` and the
        virtual masses as in :func:`continuous_network_eigenvalues`, the port moving with the
        device (no sampling, no delay, no hold).
    """
    b0 = float(scene.device.friction)
    cal = dict(calibrated or {})
    for lk in scene.links:
        if lk.target is not None and lk.name not in cal and not math.isfinite(lk.stiffness):
            cal[lk.name] = (lk.target[0], lk.target[1] - b0)
    net = _network(scene, cal)
    N, mob, p = net.N, net.mob, net.port
    idx = np.concatenate([[p], mob]).astype(np.int64)
    LK = net.LK[np.ix_(idx, idx)]
    LB = net.LB[np.ix_(idx, idx)].copy()
    LB[0, 0] += b0
    Minv = 1.0 / np.concatenate([[float(scene.device.mass)], net.masses])
    n = N + 1
    A = np.zeros((2 * n, 2 * n))
    A[:n, n:] = np.eye(n)
    A[n:, :n] = -Minv[:, None] * LK
    A[n:, n:] = -Minv[:, None] * LB
    return A


# --------------------------------------------------------------------------- margin

def spectral_radius_of(A: np.ndarray) -> tuple[float, bool]:
    """Spectral radius of a one-step matrix and the stability verdict.

    Parameters
    ----------
    A : ndarray, shape (n, n)

    Returns
    -------
    radius : float
        ``max |z|`` [-] (0 for an empty matrix).
    stable : bool
        ``|z| <= 1 + STABILITY_TOL`` for every eigenvalue, eigenvalues within ``RIGID_TOL``
        of ``z = 1`` (free drift) excepted: the convention of
        :func:`hapsim.analysis.check_scene`.
    """
    if A.shape[0] == 0:
        return 0.0, True
    ev = np.linalg.eigvals(A)
    mod = np.abs(ev)
    near_one = np.abs(ev - 1.0) <= RIGID_TOL
    return float(mod.max()), bool(np.all((mod <= 1.0 + STABILITY_TOL) | near_one))


def calibrate_targets(scene) -> tuple[dict, list[str]]:
    """Calibrate every uncalibrated ``target`` link of a scene at its rate.

    Parameters
    ----------
    scene : hapsim.scene.Scene

    Returns
    -------
    calibrated : dict
        ``{link name: (K [N/m], B [N s/m])}`` for the renderable targets.
    problems : list of str
        One line per target that is not renderable (with the reason).
    """
    from hapsim.analysis.targets import calibrate_targets as _calibrate

    cal, problems = {}, []
    for c in _calibrate(scene):
        res = c.result
        if not c.renderable:
            problems.append(f"link {c.link!r}: target (k, b) = {(c.k, c.b)} not renderable at "
                            f"{scene.rate_hz:g} Hz: {res.reason}")
        if math.isfinite(res.K) and math.isfinite(res.B):
            cal[c.link] = (res.K, res.B)
    return cal, problems


class StabilityMargin(tuple):
    """``(ok, spectral_radius, limit_description)``, also readable by attribute.

    Attributes
    ----------
    ok : bool
        The closed loop (device + delay + scene, integrated by the scene's integrator) is
        stable and every target link is renderable.
    spectral_radius : float
        ``max |z|`` of that loop [-] (nan when a target has no calibration at all).
    limit_description : str
        The integrator's limit in closed form, the figures for this scene and the verdict.
    """

    __slots__ = ()

    def __new__(cls, ok: bool, spectral_radius: float, limit_description: str):
        return super().__new__(cls, (bool(ok), float(spectral_radius), str(limit_description)))

    ok = property(lambda self: self[0])
    spectral_radius = property(lambda self: self[1])
    limit_description = property(lambda self: self[2])


def stability_margin(scene, *, calibrated=None) -> StabilityMargin:
    """Is the scene inside the stability boundary of the method it would run with?

    For the daemon: refuse the scene when ``ok`` is False (raise
    :class:`hapsim.errors.UnstableConfigError` with ``limit_description``).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene; its ``integrator``, ``rate_hz`` and ``device`` are used. ``target``
        links are calibrated first (:func:`calibrate_targets`) unless given in
        ``calibrated``.
    calibrated : mapping, optional
        ``{link name: (K [N/m], B [N s/m])}`` overrides.

    Returns
    -------
    StabilityMargin
        ``(ok, spectral_radius, limit_description)``.

    Raises
    ------
    ConfigError
        Unknown integrator, a port without a device section.

    Notes
    -----
    Contacts are taken engaged (the stiffest case). The verdict is the spectral radius of
    :func:`closed_loop_matrix` (convention of :func:`spectral_radius_of`); the description
    adds the closed-form limit of the integrator (:func:`oscillator_limits`) and, for the
    virtual network, the ratio ``T^2 lambda_max(M^-1 LK) / 4`` to the explicit schemes' limit.
    """
    integrator = getattr(scene, "integrator", "centred")
    _check_integrator(integrator)
    cal = dict(calibrated or {})
    problems: list[str] = []
    if scene.unresolved_targets:
        auto, problems = calibrate_targets(scene)
        for k, v in auto.items():
            cal.setdefault(k, v)
        missing = [lk.name for lk in scene.unresolved_targets if lk.name not in cal]
        if missing:
            return StabilityMargin(False, math.nan, "; ".join(problems))
    A = closed_loop_matrix(scene, integrator, calibrated=cal)
    rho, stable = spectral_radius_of(A)
    T = scene.period
    net = _network(scene, cal)
    parts = [f"integrator {integrator}: {oscillator_limits(integrator, 1.0, T)['formula']}"]
    if net.N:
        Kmm = net.LK[np.ix_(net.mob, net.mob)]
        lam = float(np.max(np.linalg.eigvals(Kmm / net.masses[:, None]).real))
        ratio = T * T * lam / 4.0
        parts.append(f"virtual network T^2 lambda_max(M^-1 K)/4 = {ratio:.4g}"
                     + (" (explicit schemes need < 1 without damping)"
                        if integrator != "exact" else ""))
    if net.port >= 0:
        dev = scene.device
        parts.append(f"closed loop with the device (m = {dev.mass:g} kg, b0 = "
                     f"{dev.friction:g} N s/m, d = {dev.delay}, hold {dev.hold}, "
                     f"{scene.rate_hz:g} Hz): spectral radius {rho:.12g}")
    else:
        parts.append(f"spectral radius {rho:.12g}")
    parts.append("stable" if stable else "UNSTABLE: beyond the boundary of this method")
    parts.extend(problems)
    return StabilityMargin(stable and not problems, rho, "; ".join(parts))
