"""What the hand feels through the matrix loop: the rendered pairs, the felt stiffness and
damping matrices and their principal directions (the inverse map as matrices).

**The felt matrices.** In 1-D the felt ``(k, b)`` is the continuous oscillator
``m s^2 + b s + k = 0`` whose poles ``s = ln(z)/T`` are the rendered (least damped)
closed-loop pair ``z`` (Florens et al. Sec. 5). In n-D the closed loop has n rendered pairs
``z_i`` (:func:`rendered_pairs`: the n least damped complex pairs whose handle mode shapes
are independent), each with its mode shape ``u_i`` (the position part of the eigenvector,
n complex components). The felt ``(k, b)`` matrices are the unique real n x n pair such that
the continuous second-order system ``M x'' + b x' + k x = 0`` has exactly these 2n
eigenpairs ``(s_i, u_i)``, ``(conj s_i, conj u_i)``:

    k U + b U S = -M U S^2,   U = [u_1..u_n, conj u_1..conj u_n] (n x 2n),
    S = diag(s_1..s_n, conj s_1..conj s_n),   i.e.   [k  b] [U; U S] = -M U S^2,

the inverse quadratic eigenvalue problem (Lancaster, "Inverse spectral problems for
semisimple damped vibrating systems", SIAM J. Matrix Anal. Appl. 29(1), 2007; Lancaster &
Prells, J. Sound Vib. 283, 2005): with ``[U; U S]`` invertible the pair is unique and real.
The felt system therefore has the rendered poles *and* the rendered mode shapes: a hand
pushing along ``u_i`` feels the oscillator ``(m_i, k_i, b_i)``. For ``n = 1`` this is the
1-D map exactly; for a decoupled (diagonal) loop it is the 1-D map per axis. In general
``k`` and ``b`` are *not* symmetric: the sampled, delayed loop is not a symmetric
mechanical system, and its exact second-order image carries that (the symmetric parts
are the conservative stiffness and the dissipative damping; the antisymmetric parts are
circulatory and gyroscopic terms, of the order of the coupling times the delay). They
are symmetric when the loop is (e.g. ``M``, ``B0``, ``K``, ``B`` diagonal in one basis).

**Principal directions.** Each rendered mode moves the handle along an ellipse
``Re(u_i e^{i w t})``; its principal direction ``e_i`` is the ellipse's major axis (unit,
real). Along it the felt pair is ``k_i = m_i |s_i|^2``, ``b_i = -2 m_i Re s_i`` with the
modal mass ``m_i = e_i^T M e_i`` (the 1-D formulas with the mass felt along ``e_i``).

**Stiffness limit per direction.** ``K_max(e)``: the largest ``kappa`` such that the loop
with ``K = K0 + kappa e e^T`` (``K0`` the rest of the virtual stiffness) is stable for every
``kappa' in (0, kappa)``. The added stiffness is a rank-one feedback, so a pole crosses the
unit circle at ``z = e^{i theta}`` iff ``kappa = -1 / (c^T (z I - A0)^-1 b)`` is real
(:func:`hapsim.analysis.direction_limits.direction_limit`): exact crossings, classified by the spectral radius between
them, as :func:`hapsim.analysis.stability.stability_limit` does in 1-D.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.analysis.loop import STABILITY_TOL
from hapsim.analysis.ths.holds import state_matrix
from hapsim.analysis.ths.matrix_loop import MatrixLoop, as_matrix_loop
from hapsim.errors import ConfigError

__all__ = ["continuous_poles", "rendered_pairs", "rendered_pairs_of",
           "rendered_pairs_of_many", "felt_matrices",
           "MatrixRenderResult", "render_state"]


def continuous_poles(z, T: float) -> np.ndarray:
    """``s = ln(z) / T`` [1/s], accurate near ``z = 1`` (``log1p`` of ``|z|^2 - 1``).

    Parameters
    ----------
    z : array_like of complex
        Sampled poles [-] (non-zero).
    T : float
        Sample period [s].

    Returns
    -------
    ndarray of complex, shape of ``z``
        ``(ln|z| + i arg z) / T`` with ``arg z`` in ``(-pi, pi]``; ``ln|z|`` as
        ``log1p(2 Re w + |w|^2) / 2``, ``w = z - 1``, where ``|z|^2 > 1/2``, so that a
        pole near the unit circle keeps the relative precision of its damping (as
        :func:`hapsim.analysis.modes.log_z` for one pole); ``ln|z|`` itself inside, where
        that sum cancels (``|z| = 1e-9`` made it ``-1`` exactly: ``-inf`` for ``-20.7``);
        ``z = 0`` (a delay line's pole) gives ``-inf``, its true limit, without a warning.
    """
    z = np.asarray(z)
    w = z - 1.0
    x = 2.0 * w.real + w.real ** 2 + w.imag ** 2          # |z|^2 - 1
    with np.errstate(divide="ignore", invalid="ignore"):
        re = np.where(x > -0.5, 0.5 * np.log1p(np.maximum(x, -0.5)), np.log(np.abs(z)))
        s = (re + 1j * np.angle(z)) / T
    # z = 0: the quotient's -inf * 0 made its imaginary part NaN
    return np.where(np.isneginf(re), complex(-np.inf, 0.0), s)[()]


def rendered_pairs(loop: MatrixLoop, K, B=0.0):
    """The n rendered pairs of the closed loop and their handle mode shapes.

    Parameters
    ----------
    loop : MatrixLoop or hapsim.analysis.loop.LoopModel
        A 1-D loop as the case n = 1 (:func:`~hapsim.analysis.ths.matrix_loop.as_matrix_loop`).
    K, B : array_like
        Virtual stiffness [N/m] and damping [N s/m] matrices.

    Returns
    -------
    z : ndarray of complex, shape (m,)
        The rendered poles (``Im z > 0``), ``m <= n``: the least damped complex pairs
        (largest ``|z|``) taken in turn while their handle mode shapes stay independent
        (the 1-D rendered pair, Florens et al. Sec. 5, per mode); ``m < n`` when the loop
        has fewer such pairs (then no felt matrices exist).
    U : ndarray of complex, shape (n, m)
        Their mode shapes: the position part ``x[n]`` of each eigenvector, scaled to unit
        norm with its largest component real positive.
    poles : ndarray of complex
        Every closed-loop pole, largest ``|z|`` first.
    """
    loop = as_matrix_loop(loop)
    return rendered_pairs_of(state_matrix(loop, K, B), loop.dof, loop.period)


def rendered_pairs_of(A, n: int, period: float, *, keep=None):
    """:func:`rendered_pairs` of any closed-loop state matrix whose first ``n`` states
    are the handle position (a whole scene: :mod:`hapsim.analysis.scene_check`).

    Parameters
    ----------
    A : ndarray, shape (N, N)
        Closed-loop state matrix.
    n : int
        Degrees of freedom of the handle.
    period : float
        Sample period ``T`` [s].
    keep : callable, optional
        ``keep(z, V) -> ndarray of bool``, ``z`` shape (B, N) the eigenvalues and ``V``
        shape (B, N, N) the eigenvectors (columns) as ``np.linalg.eig`` gives them (here
        ``B = 1``): per pole, whether it may be taken for a rendered pair (a fit's poles
        its records determine, :func:`hapsim.analysis.pencil.fit_felt_nd`'s ``floor``).
        Default: every pole.

    Returns
    -------
    z, U, poles
        As :func:`rendered_pairs`; a pair whose handle part is below 1e-8 of its
        eigenvector's norm is a mode of the object the hand does not feel, never rendered.
    """
    z, V = np.linalg.eig(A)
    return _pairs_of_modes(z[None], V[None], n, period, keep)[0]


def rendered_pairs_of_many(A, n: int, period: float, *, keep=None) -> list:
    """:func:`rendered_pairs_of` of each of a stack of closed-loop state matrices, their
    eigen decompositions taken in one call (LAPACK's ``geev`` on each matrix, as one call
    on that matrix makes it) and the pairs chosen for all of them at once: the same
    pairs and shapes bit for bit, without the calls' overhead per matrix
    (:func:`hapsim.analysis.pencil.felt_sensitivity_nd`'s central differences take
    dozens at once).

    Parameters
    ----------
    A : ndarray, shape (B, N, N)
        Closed-loop state matrices.
    n, period, keep
        As :func:`rendered_pairs_of` (handle axes; ``T`` [s]; ``keep`` called once on
        the whole stack).

    Returns
    -------
    list of (z, U, poles)
        Per matrix, as :func:`rendered_pairs_of` (``poles`` complex even where every pole
        of that matrix is real).
    """
    z, V = np.linalg.eig(np.asarray(A))
    return _pairs_of_modes(z, V, n, period, keep)


def _pairs_of_modes(z, V, n: int, period: float, keep=None) -> list:
    """:func:`rendered_pairs_of` of each of a stack of state matrices from their
    eigenvalues ``z`` (B, N) and eigenvectors ``V`` (B, N, N; columns).

    Each matrix's candidates (its complex poles, largest ``|z|`` first) are taken in
    turn, one candidate of every matrix per round: the norms one by one (BLAS's dot, as
    ``np.linalg.norm`` takes them), the scalars by the same scalar operations, the
    shapes' array operations on the round's rows at once (element by element, the same
    bits), the rank tests as one stacked SVD per size (LAPACK's on each matrix)."""
    B = z.shape[0]
    ok = None if keep is None else np.asarray(keep(z, V), bool)
    order = np.argsort(-np.abs(z), axis=-1, kind="stable")
    z = np.take_along_axis(z, order, -1)
    V = np.take_along_axis(V, order[:, None, :], -1)
    cand = z.imag > 1e-12 * np.maximum(1.0, np.abs(z))
    if ok is not None:
        cand &= np.take_along_axis(ok, order, -1)
    s = np.zeros(z.shape, complex)
    s[cand] = continuous_poles(z[cand], period)
    todo = [list(np.flatnonzero(c)) for c in cand]
    chosen = [[] for _ in range(B)]
    shapes = [[] for _ in range(B)]
    taken = [np.zeros((2 * n, 0), complex) for _ in range(B)]
    active = list(range(B))
    while active:
        rows = []                                      # (matrix, pole, |u|) this round
        for b in active:
            while todo[b]:
                i = todo[b].pop(0)
                nu = np.linalg.norm(V[b, :n, i])
                if nu > 1e-8 * np.linalg.norm(V[b, :, i]):
                    rows.append((b, i, nu))
                    break                              # else: not seen at the handle
        if not rows:
            break
        bs = np.array([r[0] for r in rows])
        ii = np.array([r[1] for r in rows])
        u = V[bs, :n, ii] / np.array([r[2] for r in rows])[:, None]
        big = u[np.arange(len(rows)), np.argmax(np.abs(u), axis=1)]
        u = u * np.array([abs(x) / x for x in big])[:, None]
        # the inverse problem needs [W; W S] invertible: test the columns [u; s u / |s|]
        # of this pair with the ones taken (conjugates included), their rank at the
        # tolerance 1e-6 (np.linalg.matrix_rank's own test on the singular values)
        unit = [(si / abs(si) if si != 0 else 0.0) for si in map(complex, s[bs, ii])]
        up = np.array(unit, complex)[:, None]
        new = np.stack([np.concatenate([u, up * u], axis=1),
                        np.concatenate([u.conj(), np.conj(up) * u.conj()], axis=1)], axis=2)
        cols = [np.concatenate([taken[b], new[g]], axis=1) for g, b in enumerate(bs)]
        for k in {c.shape[1] for c in cols}:
            same = [g for g, c in enumerate(cols) if c.shape[1] == k]
            sv = np.linalg.svd(np.stack([cols[g] for g in same]), compute_uv=False)
            for g, full in zip(same, np.count_nonzero(sv > 1e-6, axis=1) == k):
                if full:
                    b = int(bs[g])
                    taken[b] = cols[g]
                    chosen[b].append(z[b, ii[g]])
                    shapes[b].append(u[g])
        active = [b for b in active if todo[b] and len(chosen[b]) < n]
    return [(np.array(c, complex),
             np.column_stack(sh) if sh else np.zeros((n, 0), complex), zb)
            for c, sh, zb in zip(chosen, shapes, z)]


def felt_matrices(mass, s, U) -> tuple[np.ndarray, np.ndarray]:
    """The felt stiffness and damping matrices of n rendered modes (module docstring).

    Parameters
    ----------
    mass : array_like, shape (n, n)
        Cartesian mass ``M`` [kg].
    s : array_like of complex, shape (n,)
        Continuous poles ``s_i = ln(z_i)/T`` [1/s] (one per pair).
    U : array_like of complex, shape (n, n)
        Their mode shapes (columns).

    Returns
    -------
    k : ndarray, shape (n, n)
        Felt stiffness [N/m].
    b : ndarray, shape (n, n)
        Felt damping [N s/m].

    Notes
    -----
    Solves ``[k b] [W; W S] = -M W S^2`` with ``W = [U, conj U]``,
    ``S = diag(s, conj s)`` (Lancaster 2007): the unique real pair whose continuous system
    ``M x'' + b x' + k x = 0`` has the eigenpairs ``(s_i, u_i)`` and their conjugates.
    ``n = 1``: ``k = m |s|^2``, ``b = -2 m Re s`` (the 1-D inverse map).

    Raises
    ------
    ConfigError
        Fewer than n modes, or mode shapes that do not determine the pair (``[W; W S]``
        singular).
    """
    M = np.asarray(mass, float)
    n = M.shape[0]
    s = np.asarray(s, complex)
    U = np.asarray(U, complex)
    if s.shape != (n,) or U.shape != (n, n):
        raise ConfigError(f"the felt matrices need {n} rendered pairs with independent "
                          f"mode shapes at the handle, the loop has {s.size}",
                          key="felt")
    W = np.hstack([U, U.conj()])
    S = np.concatenate([s, s.conj()])
    G = np.vstack([W, W * S])
    rhs = -(M @ (W * S * S))
    try:
        X = np.linalg.solve(G.T, rhs.T).T          # X G = rhs
    except np.linalg.LinAlgError:
        raise ConfigError("the rendered modes' shapes do not determine a felt (k, b) pair",
                          key="felt") from None
    return X[:, :n].real.copy(), X[:, n:].real.copy()


@dataclass(frozen=True)
class MatrixRenderResult:
    """What the hand feels through an n-DoF loop for virtual matrices ``(K, B)``.

    Attributes
    ----------
    dof : int
        n.
    K, B : ndarray, shape (n, n)
        The virtual stiffness [N/m] and damping [N s/m] analysed.
    felt_stiffness, felt_damping : ndarray, shape (n, n) or None
        The felt ``k`` [N/m] and ``b`` [N s/m] matrices (module docstring); None when the
        loop has fewer than n rendered pairs.
    directions : ndarray, shape (n, n) or None
        Principal directions (columns, unit) of the rendered modes, least damped first.
    direction_stiffness, direction_damping, direction_mass : ndarray, shape (n,) or None
        The felt pair along each direction (``k_i = m_i |s_i|^2`` [N/m],
        ``b_i = -2 m_i Re s_i`` [N s/m]) and its modal mass ``m_i`` [kg].
    rendered_poles : ndarray of complex, shape (<= n,)
        The rendered poles (``Im z > 0``).
    poles : ndarray of complex
        Every closed-loop pole, largest ``|z|`` first.
    spectral_radius : float
        ``max |z|`` [-].
    stable : bool
        ``spectral_radius <= 1 + STABILITY_TOL`` (the 1-D verdict's tolerance).
    note : str
        Empty, or why the felt matrices are None.
    """

    dof: int
    K: np.ndarray
    B: np.ndarray
    felt_stiffness: np.ndarray | None
    felt_damping: np.ndarray | None
    directions: np.ndarray | None
    direction_stiffness: np.ndarray | None
    direction_damping: np.ndarray | None
    direction_mass: np.ndarray | None
    rendered_poles: np.ndarray
    poles: np.ndarray
    spectral_radius: float
    stable: bool
    note: str = ""
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready dict (matrices as nested lists, non-finite numbers as None).

        Returns
        -------
        dict
            ``dof``, ``K``, ``B``, ``felt_stiffness``, ``felt_damping`` (n x n),
            ``principal_directions`` (list of n unit vectors), ``direction_stiffness``,
            ``direction_damping``, ``direction_mass``, ``spectral_radius``, ``stable``,
            ``rendered_poles`` (``[re, im]`` pairs), ``note``.
        """
        def clean(a):
            if a is None:
                return None
            a = np.asarray(a, float)
            return [clean(r) for r in a] if a.ndim > 1 else \
                [float(v) if math.isfinite(v) else None for v in a]
        return {"dof": self.dof, "K": clean(self.K), "B": clean(self.B),
                "felt_stiffness": clean(self.felt_stiffness),
                "felt_damping": clean(self.felt_damping),
                "principal_directions": None if self.directions is None
                else clean(self.directions.T),
                "direction_stiffness": clean(self.direction_stiffness),
                "direction_damping": clean(self.direction_damping),
                "direction_mass": clean(self.direction_mass),
                "spectral_radius": float(self.spectral_radius) if
                math.isfinite(self.spectral_radius) else None,
                "stable": bool(self.stable),
                "rendered_poles": [[float(z.real), float(z.imag)]
                                   for z in self.rendered_poles],
                "note": self.note}


def _major_axis(u: np.ndarray) -> np.ndarray:
    """Unit major axis of the ellipse ``Re(u e^{i t})`` (``u`` complex, shape (n,))."""
    R = np.column_stack([u.real, u.imag])
    w, V = np.linalg.eigh(R @ R.T)
    e = V[:, -1]
    j = int(np.argmax(np.abs(e)))
    return e if e[j] > 0 else -e


def render_state(A, mass, period: float, *, K=None, B=None) -> MatrixRenderResult:
    """:func:`hapsim.analysis.ths.render` of any closed-loop state matrix whose first n states are the
    handle position (n = the mass matrix's size).

    Parameters
    ----------
    A : ndarray, shape (N, N)
        Closed-loop state matrix.
    mass : ndarray, shape (n, n)
        Cartesian mass of hand + handle [kg].
    period : float
        Sample period ``T`` [s].
    K, B : ndarray, optional
        The virtual matrices to report (nan when not given).

    Returns
    -------
    MatrixRenderResult
    """
    M = np.asarray(mass, float)
    n = M.shape[0]
    Kq = np.full((n, n), np.nan) if K is None else K
    Bq = np.full((n, n), np.nan) if B is None else B
    zr, U, poles = rendered_pairs_of(A, n, period)
    rho = float(np.max(np.abs(poles))) if poles.size else 0.0
    stable = rho <= 1.0 + STABILITY_TOL
    common = dict(dof=n, K=Kq, B=Bq, rendered_poles=zr, poles=poles, spectral_radius=rho,
                  stable=stable)
    if zr.size < n:
        return MatrixRenderResult(felt_stiffness=None, felt_damping=None, directions=None,
                                  direction_stiffness=None, direction_damping=None,
                                  direction_mass=None,
                                  note=f"the closed loop has {zr.size} rendered pair(s) "
                                       f"with independent mode shapes at the handle, fewer "
                                       f"than {n}: no felt matrices", **common)
    s = continuous_poles(zr, period)
    k, b = felt_matrices(M, s, U)
    E = np.column_stack([_major_axis(U[:, i]) for i in range(n)])
    m = np.einsum("in,ij,jn->n", E, M, E)
    return MatrixRenderResult(felt_stiffness=k, felt_damping=b, directions=E,
                              direction_stiffness=m * np.abs(s) ** 2,
                              direction_damping=-2.0 * m * s.real, direction_mass=m, **common)
