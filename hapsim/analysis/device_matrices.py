"""A device's mass and friction matrices from a record of its positions under known forces,
in any dimension (``hapsim identify`` of a 2-D or 3-D device; n = 1 is a 1-DoF one).

The model is the device's exact zero-order hold (:func:`hapsim.analysis.ths.zoh_blocks`):
with ``Z = -M^-1 B0 T``, ``E = e^Z`` and ``phi1, phi2`` its first two phi-functions,

``x[k+1] = x[k] + T phi1 v[k] + T^2 phi2 M^-1 u[k]``, ``v[k+1] = E v[k] + T phi1 M^-1 u[k]``

for the force ``u[k]`` held over period ``k``. The velocity, which a device does not
report, is eliminated (``phi1`` and ``E`` commute: both are functions of ``Z``): the steps
``D[k] = x[k] - x[k-1]`` obey the vector ARX model

``D[k+2] = E D[k+1] + G1 u[k] + G2 u[k+1]``, ``G1 = T^2 (phi1^2 - E phi2) M^-1``,
``G2 = T^2 phi2 M^-1``,

linear in ``(E, G1, G2)``: ordinary least squares over the record (the forces are known
inputs, the host's own, so a closed loop's feedback does not bias it: Ljung, *System
Identification*, 2nd ed. 1999, sec. 13.4, for a noise-free or white-noise output). The
delay ``d`` (the force written at sample ``k`` is ``u[k + d]``) is the whole number of
periods whose fit leaves the smallest residual. ``M`` and ``B0`` follow from ``E`` and
``G2``: ``Z = log E`` (the principal logarithm: ``E``'s eigenvalues are real and in
(0, 1] for a symmetric positive definite ``M`` and semi-definite ``B0``), ``M^-1 = phi2(Z)^-1
G2 / T^2``, ``B0 = -M Z / T``; ``G1``, not used, checks the model (its misfit, relative).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hapsim.analysis.identify import COVERAGE
from hapsim.errors import ConfigError

__all__ = ["arx_taps", "DeviceMatrices", "fit_device_matrices"]


def arx_taps(mass, friction, period: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exact ARX taps ``(E, G1, G2)`` of a device (module notes).

    Parameters
    ----------
    mass : array_like, shape (n, n)
        ``M`` [kg], invertible.
    friction : array_like, shape (n, n)
        ``B0`` [N s/m].
    period : float
        ``T`` [s].

    Returns
    -------
    E, G1, G2 : ndarray, shape (n, n)
        ``E`` [-]; ``G1``, ``G2`` [m/N].
    """
    from hapsim.analysis.ths.holds import zoh_blocks
    M = np.atleast_2d(np.asarray(mass, float))
    n = M.shape[0]
    Ad, Bd = zoh_blocks(M, np.atleast_2d(np.asarray(friction, float)), float(period))
    E = Ad[n:, n:]
    G2 = Bd[:n]
    G1 = Ad[:n, n:] @ Bd[n:] - E @ G2
    return E, G1, G2


@dataclass(frozen=True)
class DeviceMatrices:
    """A device identified from a record (:func:`fit_device_matrices`).

    Attributes
    ----------
    mass : ndarray, shape (n, n)
        ``M`` [kg] (its symmetric part; ``asymmetry`` says what was dropped).
    friction : ndarray, shape (n, n)
        ``B0`` [N s/m] (its symmetric part).
    delay : int
        ``d`` [periods].
    residual : float
        RMS of the ARX residual over the RMS of the steps ``D`` [-] at ``delay``.
    runner_up : float
        The same at the next best delay [-] (how clearly the delay stands out).
    misfit : float
        ``|G1 - G1(M, B0)| / |G1|`` [-] (Frobenius): the unused tap against the model
        (a device the linear model holds gives round-off and its nonlinearity).
    asymmetry : float
        ``|X - X^T| / |X|`` [-], the larger for ``M`` and ``B0``.
    samples : int
        Rows of the fit.
    mass_se, friction_se : ndarray, shape (n, n)
        Each entry's standard error [kg], [N s/m]: the least-squares covariance of the
        taps (the residual taken as white) carried to ``M`` and ``B0`` to first order. On a
        record of an exactly linear device it is the fit's round-off.
    """

    mass: np.ndarray
    friction: np.ndarray
    delay: int
    residual: float
    runner_up: float
    misfit: float
    asymmetry: float
    samples: int
    mass_se: np.ndarray = None
    friction_se: np.ndarray = None

    def to_dict(self) -> dict:
        """JSON-ready fields.

        Returns
        -------
        dict
            Every attribute by name: ``mass`` [kg], ``friction`` [N s/m] and their
            standard errors as n lists of n (the errors None when not computed), the rest
            as they are.
        """
        return {"mass": self.mass.tolist(), "friction": self.friction.tolist(),
                "delay": self.delay, "residual": self.residual,
                "runner_up": self.runner_up, "misfit": self.misfit,
                "asymmetry": self.asymmetry, "samples": self.samples,
                "mass_se": None if self.mass_se is None else self.mass_se.tolist(),
                "friction_se": None if self.friction_se is None
                else self.friction_se.tolist()}


def _lstsq(x: np.ndarray, u: np.ndarray, n: int, spread: bool = False):
    """The taps at one delay, the relative residual; None when the regressors are rank
    deficient (each column scaled to unit RMS first: steps [m] and forces [N] differ by
    orders of magnitude). With ``spread``, also each tap's standard error (the residual's
    RMS per output times ``sqrt(diag((X^T X)^-1))``, the least-squares covariance)."""
    D = np.diff(x, axis=0)                       # D[j] = x[j+1] - x[j]
    # rows k: D[k+1] = E D[k] + G1 u[k] + G2 u[k+1] (D indexed from 0 as x[k+1] - x[k])
    Y = D[1:]
    X = np.hstack([D[:-1], u[:len(D) - 1], u[1:len(D)]])
    c = np.sqrt(np.mean(X * X, axis=0))
    if not np.all(c > 0) or np.linalg.matrix_rank(X / c) < 3 * n:
        return None, np.inf
    theta, *_ = np.linalg.lstsq(X / c, Y, rcond=None)
    theta = theta / c[:, None]
    r = Y - X @ theta
    scale = float(np.sqrt(np.mean(Y * Y)))
    res = float(np.sqrt(np.mean(r * r))) / scale
    if not spread:
        return theta, res
    Xs = X / c
    dof = max(1, len(Y) - Xs.shape[1])
    sigma = np.sqrt(np.sum(r * r, axis=0) / dof)                  # per output, shape (n,)
    g = np.sqrt(np.diag(np.linalg.inv(Xs.T @ Xs))) / c            # per regressor
    # and the solve's own rounding: a backward-stable least squares moves each solution
    # by ~ p eps cond(X) |theta| (Higham 2002, thm. 20.3, small residual; p = the
    # columns, as tests/tolerance.py takes a modestly growing function of the size)
    sv = np.linalg.svd(Xs, compute_uv=False)
    rnd = Xs.shape[1] * np.finfo(float).eps * (sv[0] / sv[-1]) * np.abs(theta * c[:, None])
    return theta, res, np.hypot(g[:, None] * sigma[None, :], rnd / c[:, None])


def fit_device_matrices(x, forces, period: float, max_delay: int = 5) -> DeviceMatrices:
    """Fit ``M``, ``B0`` and the delay ``d`` to a record (module notes).

    Parameters
    ----------
    x : array_like, shape (N, n)
        The device's positions [m], read at the start of each period.
    forces : array_like, shape (N, n)
        The forces written after each reading [N]; the device holds ``forces[k]`` over
        period ``k + d``.
    period : float
        ``T`` [s].
    max_delay : int, optional
        Largest delay searched [periods].

    Returns
    -------
    DeviceMatrices

    Raises
    ------
    ConfigError
        Shapes that differ or fewer than ``10 (3 n + d)`` samples (key ``record``); a
        record that does not determine the model (no motion, forces that do not excite
        every axis: the regressors' matrix rank deficient) or whose fit is not a device
        (``E`` with an eigenvalue outside (0, 1], an ``M`` not positive definite).
    """
    x = np.asarray(x, float)
    F = np.asarray(forces, float)
    if x.ndim == 1:
        x, F = x[:, None], F.reshape(-1, 1)
    N, n = x.shape
    if F.shape != x.shape or not (np.all(np.isfinite(x)) and np.all(np.isfinite(F))):
        raise ConfigError(f"positions and forces must be finite and of one shape, got "
                          f"{x.shape} and {F.shape}", key="record")
    T = float(period)
    if N < 10 * (3 * n + max_delay):
        raise ConfigError(f"{N} samples cannot determine {3 * n * n} taps over delays up "
                          f"to {max_delay}: record at least {10 * (3 * n + max_delay)}",
                          key="record")
    fits = []
    for d in range(int(max_delay) + 1):
        # u[k] = F[k - d]: the rows from k = d on
        theta, res = _lstsq(x[d:], F[:N - d], n)
        if theta is None:
            raise ConfigError("the record does not determine the device: no motion, or "
                              "forces that do not excite every axis", key="record")
        fits.append((res, d, theta))
    fits.sort(key=lambda f: f[0])
    res, d, theta = fits[0]
    _, _, se = _lstsq(x[d:], F[:N - d], n, spread=True)
    E, G1 = theta[:n].T, theta[n:2 * n].T
    ev = np.linalg.eigvals(E)
    try:
        M, B0 = _recover(theta, n, T)
    except (np.linalg.LinAlgError, ValueError):
        # (taps from which no M follows: the check below refuses them, as it did
        # before M was needed for its bound)
        M = B0 = np.full((n, n), np.nan)
    Ms, Bs = (M + M.T) / 2, (B0 + B0.T) / 2
    # A device's E is similar to a symmetric matrix through M^(1/2): its eigenvalues are
    # real, and those of the fitted E lie within sqrt(cond M) ||dE||_2 of them (Bauer &
    # Fike 1960); dE taken as COVERAGE times the taps' standard errors (Frobenius norm,
    # above the 2-norm). A symmetric device (the delta's x and y, a double eigenvalue)
    # splits into a complex pair of that order: 3.2e-5 on a 1 s record of
    # configs/delta_sphere.yaml, against 8.5e-5 of standard error, was refused as "not a
    # device" under a fixed 1e-6.
    lam = np.linalg.eigvalsh(Ms) if np.all(np.isfinite(Ms)) else np.zeros(n)
    kappa = float(np.sqrt(lam[-1] / lam[0])) if lam[0] > 0 else 1.0
    tol = max(1e-6, COVERAGE * kappa * float(np.linalg.norm(se[:n])))
    if not (np.all(np.abs(ev.imag) <= tol) and np.all(ev.real > 0)
            and np.all(ev.real <= 1 + tol)):
        raise ConfigError(f"the fit is not a device: E's eigenvalues {np.round(ev, 6)} "
                          f"(a device with friction has them real, in (0, 1], within "
                          f"{tol:.2g}, the fit's error)", key="record")
    if not np.all(np.isfinite(Ms)):
        raise ConfigError("the fit is not a device: no mass matrix follows from its taps",
                          key="record")
    # the taps' standard errors carried to M and B0 (first order: one tap at a time,
    # the changes added in quadrature, Ljung 1999 sec. 9.3)
    vm, vb = np.zeros((n, n)), np.zeros((n, n))
    for i in range(theta.shape[0]):
        for j in (range(n) if i < n or i >= 2 * n else ()):   # E and G2 make M, B0
            t = theta.copy()
            t[i, j] += se[i, j]
            Mi, Bi = _recover(t, n, T)
            vm += ((Mi + Mi.T) / 2 - Ms) ** 2
            vb += ((Bi + Bi.T) / 2 - Bs) ** 2
    if not np.all(np.linalg.eigvalsh(Ms) > 0):
        raise ConfigError("the fit is not a device: its mass matrix is not positive "
                          "definite", key="record")
    _, G1m, _ = arx_taps(Ms, Bs, T)
    asym = max(float(np.linalg.norm(M - M.T) / np.linalg.norm(M)),
               float(np.linalg.norm(B0 - B0.T) / max(np.linalg.norm(B0), 1e-300)))
    return DeviceMatrices(mass=Ms, friction=Bs, delay=d, residual=res,
                          runner_up=fits[1][0] if len(fits) > 1 else np.inf,
                          misfit=float(np.linalg.norm(G1 - G1m) / np.linalg.norm(G1)),
                          asymmetry=asym, samples=len(x) - d - 2,
                          mass_se=np.sqrt(vm), friction_se=np.sqrt(vb))


def _recover(theta: np.ndarray, n: int, T: float):
    """``(M, B0)`` from the taps (module notes): ``Z = log E``, ``M^-1 = phi2(Z)^-1 G2 /
    T^2``, ``B0 = -M Z / T``."""
    from scipy.linalg import logm
    from hapsim.analysis.ths.holds import phi_functions
    E, G2 = theta[:n].T, theta[2 * n:].T
    Z = np.real(logm(E))
    M = np.linalg.inv(np.linalg.solve(phi_functions(Z)[2], G2) / (T * T))
    return M, -M @ Z / T
