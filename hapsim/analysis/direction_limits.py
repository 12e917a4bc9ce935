"""The n-D loop's stiffness limits (docs/stability.md): along one direction of the port
(:func:`direction_limit`: the largest ``kappa`` such that the loop with ``K = K0 + kappa e
e^T`` stays stable, found from the exact crossings of the unit circle, classified by the
spectral radius between them, as :func:`hapsim.analysis.stability.stability_limit` does in 1-D),
along several directions (:func:`direction_limits`), and over a device's workspace
(:func:`workspace_limits`). The loop's model is :mod:`hapsim.analysis.ths`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapsim.analysis.ths import (MatrixLoop, gain_matrices, split_hold_matrices, state_matrix,
                                 zoh_matrices)
from hapsim.analysis.loop import STABILITY_TOL
from hapsim.errors import ConfigError

__all__ = ["direction_limit", "direction_limits", "isotropic_limit", "WorkspaceLimits",
           "workspace_limits"]


def _resolvent_scalar(A0: np.ndarray, b: np.ndarray, c: np.ndarray, z: np.ndarray):
    """``c^T (z I - A0)^-1 b`` for many ``z`` (batched solves, chunked to ~300 MB)."""
    z = np.asarray(z, complex).ravel()
    N = A0.shape[0]
    out = np.empty(z.shape, complex)
    chunk = max(1, int(2e7 // (N * N)))
    I = np.eye(N)
    for lo in range(0, z.size, chunk):
        zz = z[lo:lo + chunk]
        Z = zz[:, None, None] * I - A0
        with np.errstate(all="ignore"):
            try:
                y = np.linalg.solve(Z, np.broadcast_to(b.astype(complex), (zz.size, N))
                                    [:, :, None])[:, :, 0]
                out[lo:lo + chunk] = y @ c
            except np.linalg.LinAlgError:       # a pole exactly on the scan: one by one
                for k, zk in enumerate(zz):
                    try:
                        out[lo + k] = c @ np.linalg.solve(zk * I - A0, b.astype(complex))
                    except np.linalg.LinAlgError:
                        out[lo + k] = np.inf
    return out


def _rank_one(loop: MatrixLoop, K0, B, e):
    """``A(kappa) = A0 - kappa b c^T`` for ``K = K0 + kappa e e^T``."""
    n, d = loop.dof, loop.delay
    A0 = state_matrix(loop, K0, B)
    N = A0.shape[0]
    bvec = np.zeros(N)
    if d % 1:       # the split hold: K enters F[n-m], which the plant and h both take
        m = int(math.floor(d))
        _, G0, _ = split_hold_matrices(loop)
        bvec[:2 * n] = G0 @ e
        bvec[N - n:] = e
        d = m
    else:
        _, Bd = zoh_matrices(loop)
        bvec[:2 * n] = Bd @ e
    cvec = np.zeros(N)
    blk = slice(0, n) if d == 0 else slice((d + 1) * n, (d + 2) * n)
    cvec[blk] = e
    return A0, bvec, cvec


def direction_limit(loop: MatrixLoop, direction, B=0.0, K0=0.0, *,
                    scan: int = 2048, delays=None) -> float:
    """Largest stable stiffness added along one direction, ``K_max(e)`` [N/m].

    Parameters
    ----------
    loop : MatrixLoop
    direction : array_like, shape (n,)
        The direction ``e`` (normalised here).
    B : array_like, optional
        Virtual damping matrix [N s/m].
    K0 : array_like, optional
        The rest of the virtual stiffness [N/m] (default none).
    scan : int, optional
        Points of the unit-circle scan before each crossing is refined.
    delays : sequence of float, shape (n,), optional
        A delay per axis [periods] (several ports, each its own device:
        :func:`hapsim.analysis.ths.state_matrix`); default the loop's one delay.

    Returns
    -------
    float
        ``sup {kappa : the loop with K0 + kappa' e e^T is stable for all kappa' in
        (0, kappa)}`` [N/m]; ``0.0`` when no small positive ``kappa`` is stable, ``inf``
        when every one is.

    Notes
    -----
    ``A(kappa) = A0 - kappa b c^T`` (``b = [Bd e; 0]``, ``c`` picks ``e^T x[n-d]``), so
    ``det(zI - A(kappa)) = det(zI - A0) (1 + kappa c^T (zI - A0)^-1 b)``: a pole is on the
    unit circle at ``z = e^{i theta}`` iff ``kappa = -1 / G(z)`` with
    ``G = c^T (zI - A0)^-1 b`` real; ``Im G(e^{i theta}) = 0`` is scanned on
    ``theta in (0, pi]`` and refined by Brent's method, and stability between consecutive
    candidate ``kappa`` is constant, so each interval is classified by the spectral radius
    at one interior point (the 1-D method of :func:`hapsim.analysis.stability.stability_limit`).
    For ``n = 1`` and ``K0 = 0`` it is that 1-D limit.

    Raises
    ------
    ConfigError
        A zero or non-finite direction, bad ``K0`` or ``B``.
    """
    from hapsim.analysis.stability import brent_root
    n = loop.dof
    e = np.asarray(direction, float).reshape(-1)
    if e.shape != (n,) or not np.all(np.isfinite(e)) or not np.linalg.norm(e) > 0:
        raise ConfigError(f"must be a non-zero vector of {n} finite components, got "
                          f"{direction!r}", key="direction")
    e = e / np.linalg.norm(e)
    K0q, Bq = gain_matrices(loop, K0, B)
    if delays is None:
        A0, bvec, cvec = _rank_one(loop, K0q, Bq, e)
    else:
        A0 = state_matrix(loop, K0q, Bq, delays=delays)
        D = state_matrix(loop, K0q + np.outer(e, e), Bq, delays=delays) - A0
        bvec, cvec = _factor_rank_one(D)
        if bvec is None:        # ports whose delays' whole parts differ: rank > 1
            return _classify(A0, D, _kron_crossings(A0, D))
    theta = np.linspace(0.0, math.pi, scan + 1)[1:]
    G = _resolvent_scalar(A0, bvec, cvec, np.exp(1j * theta))

    def img(t):
        return float(_resolvent_scalar(A0, bvec, cvec, np.array([np.exp(1j * t)]))[0].imag)
    cands = []
    im = G.imag
    for i in range(len(theta) - 1):
        if np.isfinite(im[i]) and np.isfinite(im[i + 1]) and im[i] * im[i + 1] < 0:
            # Brent's zero (the 1-D limit's own, hapsim.analysis.stability): no
            # scipy.optimize import (~0.3 CPU-s) in a command that checks an n-D scene
            t = brent_root(img, theta[i], theta[i + 1], xtol=1e-15, rtol=1e-14)
            g = _resolvent_scalar(A0, bvec, cvec, np.array([np.exp(1j * t)]))[0]
            cands.append(-1.0 / g.real)
        elif im[i] == 0 and np.isfinite(G[i].real) and G[i].real != 0:
            cands.append(-1.0 / G[i].real)
    g_pi = G[-1]                     # theta = pi: z = -1, G real
    if np.isfinite(g_pi.real) and g_pi.real != 0:
        cands.append(-1.0 / g_pi.real)
    return _classify(A0, -np.outer(bvec, cvec), cands)


def _classify(A0: np.ndarray, D: np.ndarray, cands) -> float:
    """The first candidate crossing past which ``A0 + kappa D`` is unstable [N/m]: the
    stability between two consecutive crossings is that at one interior point."""
    cands = sorted({c for c in cands if c > 0 and math.isfinite(c)})

    def stable_at(kappa):
        A = A0 + kappa * D
        return float(np.max(np.abs(np.linalg.eigvals(A)))) <= 1.0 + STABILITY_TOL
    edges = [0.0] + cands
    for i, lo in enumerate(edges):
        hi = edges[i + 1] if i + 1 < len(edges) else (2.0 * lo if lo > 0 else 1.0)
        mid = math.sqrt(lo * hi) if lo > 0 else 0.5 * hi
        if not stable_at(mid):
            return lo
    return math.inf


def _factor_rank_one(D: np.ndarray):
    """``(b, c)`` with ``D = -b c^T`` when ``D`` is rank one to round-off, else
    ``(None, None)``. Ports whose delays share their whole part change the state matrix
    by a rank-one term when ``K`` gains ``kappa e e^T`` (their split holds take
    ``F[n-m]`` from one block of positions); otherwise one term per whole part."""
    i, j = np.unravel_index(int(np.argmax(np.abs(D))), D.shape)
    if D[i, j] == 0:
        return None, None
    u, v = D[:, j].copy(), D[i, :] / D[i, j]
    # the entries are single products and sums of a few (state_matrix): a rank-one D
    # leaves a residue of a few units in the last place of its largest entry
    if np.max(np.abs(D - np.outer(u, v))) > 64 * np.finfo(float).eps * abs(D[i, j]) * len(D):
        return None, None
    return -u, v


def _kron_crossings(A0: np.ndarray, D: np.ndarray) -> list[float]:
    """Every real ``kappa > 0`` at which ``A(kappa) = A0 + kappa D`` has two eigenvalues
    with ``z_i z_j = 1`` (a pair on the unit circle, ``z`` and its conjugate, or ``z =
    +-1``), whatever the rank of ``D``: ``det(A(kappa) (x) A(kappa) - I) = 0`` (the
    Kronecker product's eigenvalues are the products ``z_i z_j``; Stephanos 1900, Horn &
    Johnson, *Topics in Matrix Analysis* thm. 4.2.12), a quadratic eigenvalue problem in
    ``kappa`` solved by its companion linearisation (Tisseur & Meerbergen, SIAM Rev. 43
    2001, sec. 3.4) and each real root polished on the spectral radius by Brent's method.
    Real reciprocal pairs off the circle are spurious candidates, which the
    classification between candidates ignores."""
    import scipy.linalg
    from hapsim.analysis.stability import brent_root
    N = A0.shape[0]
    M = N * N
    C0, C1, C2 = (np.kron(A0, A0) - np.eye(M), np.kron(A0, D) + np.kron(D, A0),
                  np.kron(D, D))
    L = np.block([[np.zeros((M, M)), np.eye(M)], [-C0, -C1]])
    R = np.block([[np.eye(M), np.zeros((M, M))], [np.zeros((M, M)), C2]])
    with np.errstate(all="ignore"):
        w = scipy.linalg.eigvals(L, R)
    w = w[np.isfinite(w)]
    raw = sorted({float(x.real) for x in w if x.real > 0 and abs(x.imag) <= 1e-6 * abs(x)})

    def excess(kappa):
        return float(np.max(np.abs(np.linalg.eigvals(A0 + kappa * D)))) - 1.0
    out = []
    for k in raw:
        for h in (1e-9, 1e-7, 1e-5):      # the eigensolver's root to a sign change
            lo, hi = k * (1 - h), k * (1 + h)
            if excess(lo) * excess(hi) < 0:
                k = brent_root(excess, lo, hi, xtol=0.0, rtol=1e-15)
                break
        out.append(k)
    return out


def isotropic_limit(loop: MatrixLoop, B=0.0, delays=None) -> float:
    """Largest stable isotropic stiffness ``kappa`` [N/m]: the loop with ``K = kappa I``
    (a spring of rest length 0 from the handle to a ground: the same law on every axis)
    and the virtual damping ``B``.

    Parameters
    ----------
    loop : MatrixLoop
    B : array_like, optional
        Virtual damping matrix [N s/m] (a scalar: times I).
    delays : sequence of float, optional
        A delay per axis [periods] (:func:`hapsim.analysis.ths.state_matrix`).

    Returns
    -------
    float
        ``sup {kappa : stable for all kappa' in (0, kappa)}`` [N/m]; 0.0 when no small
        positive ``kappa`` is stable, ``inf`` when every one is.

    Notes
    -----
    ``A(kappa) = A0 + kappa D`` with ``D`` of rank up to ``n``: the crossings of the unit
    circle are the real roots of ``det(A(kappa) (x) A(kappa) - I) = 0``
    (:func:`_kron_crossings`), each interval between them classified by the spectral
    radius at one interior point, as :func:`direction_limit`. For ``n = 1`` it is the 1-D
    limit :func:`hapsim.analysis.stability.stability_limit`.

    Raises
    ------
    ConfigError
        ``B`` not finite or of the wrong shape.
    """
    n = loop.dof
    K0q, Bq = gain_matrices(loop, 0.0, B)
    A0 = state_matrix(loop, K0q, Bq, delays=delays)
    D = state_matrix(loop, K0q + np.eye(n), Bq, delays=delays) - A0
    return _classify(A0, D, _kron_crossings(A0, D))


def direction_limits(loop: MatrixLoop, directions=None, B=0.0, K0=0.0) -> np.ndarray:
    """:func:`direction_limit` along several directions [N/m].

    Parameters
    ----------
    loop : MatrixLoop
    directions : array_like, shape (n, m), optional
        Directions as columns; default the principal axes of the Cartesian mass
        (eigenvectors of ``M``, lightest first: where the limit is lowest for an
        isotropic friction).
    B, K0 : array_like, optional
        As :func:`direction_limit`.

    Returns
    -------
    ndarray, shape (m,)
        ``K_max`` along each direction [N/m].
    """
    if directions is None:
        directions = np.linalg.eigh(loop.mass)[1]
    D = np.asarray(directions, float)
    return np.array([direction_limit(loop, D[:, i], B, K0) for i in range(D.shape[1])])


@dataclass(frozen=True)
class WorkspaceLimits:
    """The stiffness limit over a device's workspace (configuration-dependent mass).

    Attributes
    ----------
    joints : ndarray, shape (N, n)
        The joint configurations [rad].
    positions : ndarray, shape (N, n)
        Handle positions [m] (nan where refused).
    status : list of str, length N
        ``"ok"`` or the refusal kind (``"workspace"``, ``"serial"``, ``"parallel"``).
    mass_eigenvalues : ndarray, shape (N, n)
        Eigenvalues of ``M(q)`` [kg], ascending.
    limits : ndarray, shape (N, n)
        ``K_max`` [N/m] along the principal axes of ``M(q)`` (lightest first).
    """

    joints: np.ndarray
    positions: np.ndarray
    status: list
    mass_eigenvalues: np.ndarray
    limits: np.ndarray


def workspace_limits(device, joints, joint_inertia, joint_friction=0.0, *,
                     hand_mass: float = 0.0, hand_damping: float = 0.0,
                     rate_hz: float = 1000.0, delay: int = 1, B=0.0,
                     progress=None) -> WorkspaceLimits:
    """``K_max`` along the principal axes of the Cartesian mass at many configurations.

    Parameters
    ----------
    device : hapsim.kinematics.Pantograph or hapsim.kinematics.Delta
    joints : array_like, shape (N, n)
        Joint configurations [rad].
    joint_inertia, joint_friction, hand_mass, hand_damping, rate_hz, delay
        As :meth:`MatrixLoop.from_device`.
    B : array_like, optional
        Virtual damping matrix [N s/m].
    progress : callable, optional
        ``progress(done, total)`` after each configuration.

    Returns
    -------
    WorkspaceLimits
        Refused configurations keep their status and nan values.
    """
    from hapsim.errors import KinematicsError
    Q = np.asarray(joints, float)
    N, n = Q.shape
    pos = np.full((N, n), np.nan)
    lam = np.full((N, n), np.nan)
    lim = np.full((N, n), np.nan)
    status = []
    for i, q in enumerate(Q):
        try:
            loop = MatrixLoop.from_device(device, q, joint_inertia, joint_friction,
                                          hand_mass=hand_mass, hand_damping=hand_damping,
                                          rate_hz=rate_hz, delay=delay)
        except KinematicsError as exc:
            status.append(exc.kind or "workspace")
        else:
            status.append("ok")
            pos[i] = device.forward(q)
            w, V = np.linalg.eigh(loop.mass)
            lam[i] = w
            lim[i] = direction_limits(loop, V, B)
        if progress is not None:
            progress(i + 1, N)
    return WorkspaceLimits(joints=Q, positions=pos, status=status, mass_eigenvalues=lam,
                           limits=lim)
