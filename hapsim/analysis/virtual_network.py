"""The virtual network of a scene: its links' values, its static stiffness and rest
position, and the one-step map of every integrator (the blocks
:func:`hapsim.analysis.network.closed_loop` couples to the device).

Integrators (one-step maps of the virtual network; derivations and stability limits in
:mod:`hapsim.kernels.schemes`, which runs the same maps sample by sample):

``centred``
    ``x[n+1] = 2 x[n] - x[n-1] + T^2 M^-1 F[n]``, link damping on the backward difference.
``symplectic_euler``
    ``v[n+1] = v[n] + T (M + T C)^-1 F[n]`` (own damping implicit, ``C`` diagonal), then
    ``x[n+1] = x[n] + T v[n+1]``.
``exact``
    ``[x; v][n+1] = Phi [x; v][n] + Gam u[n] + Psi (u[n] - u[n-1])`` with
    ``Phi = expm(A_c T)`` of the continuous network (port and grounds held over the period,
    Van Loan 1978).

Multi-rate (a scene with ``audio``, :class:`hapsim.scene.Audio`): the virtual network is
integrated at the audio period ``Ta = T / N``; one device period is the product of its N
audio steps with the port position brought up to the audio rate (held or linearly
interpolated between ``p[n-1]`` and ``p[n]``) and the port force brought down (mean or last
of the N sub-step forces), :func:`multirate_blocks`. The result has the shape of the
single-rate blocks, so the device side of the loop and the state names are unchanged.

Linearisation: contacts are taken *engaged* (they act as spring_dampers), the stiffest
case the scene can reach; links given as a felt ``target`` need their calibrated (K, B).
In 2-D and 3-D (:func:`link_blocks`) each link and plane is a pair of (n, n) stiffness and
damping blocks at the rest configuration, the Euclidean laws' Jacobians there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapsim.errors import ConfigError
from hapsim.scene import INTEGRATORS

__all__ = ["INTEGRATORS", "Network", "check_integrator", "link_values", "network",
           "virtual_blocks", "multirate_blocks", "virtual_state_names", "rest_position",
           "static_stiffness", "link_blocks",
           "MAX_STATES_ND"]


def check_integrator(integrator: str, scene=None) -> None:
    """Raise unless ``integrator`` is one of :data:`INTEGRATORS`.

    Parameters
    ----------
    integrator : str
        Name to check.
    scene : hapsim.scene.Scene, optional
        Named in the error (its file).

    Raises
    ------
    ConfigError
        Unknown integrator (key ``integrator``).
    """
    if integrator not in INTEGRATORS:
        raise ConfigError(f"unknown integrator {integrator!r}; valid choices: "
                          f"{', '.join(INTEGRATORS)}", file=getattr(scene, "path", None),
                          key="integrator")


def link_values(scene, calibrated=None) -> list[tuple]:
    """Every link of a scene with the (K, B) the linear model uses.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene.
    calibrated : mapping of str to (float, float), optional
        ``{link name: (K [N/m], B [N s/m])}`` overriding links (e.g. calibrated ``target``
        links).

    Returns
    -------
    list of (Link, float, float)
        ``(link, K [N/m], B [N s/m])`` in scene order.

    Raises
    ------
    ConfigError
        A ``target`` link without calibrated values ("calibrate first"), a non-finite
        value, or calibrated values naming no link.
    """
    calibrated = dict(calibrated or {})
    names = {lk.name for lk in scene.links}
    unknown = sorted(set(calibrated) - names)
    if unknown:
        raise ConfigError(f"calibrated values for unknown links {unknown}; links are "
                          f"{sorted(names)}", file=scene.path, key="links")
    out = []
    for lk in scene.links:
        K, B = lk.stiffness, lk.damping
        if lk.name in calibrated:
            K, B = (float(v) for v in calibrated[lk.name])
            if not (math.isfinite(K) and math.isfinite(B)):
                raise ConfigError(f"calibrated (K, B) = ({K}, {B}) are not finite",
                                  file=scene.path, line=lk.line or None,
                                  key=f"links.{lk.name}")
        elif not (math.isfinite(K) and math.isfinite(B)):
            if lk.target is not None:
                raise ConfigError(f"link {lk.name!r} is given as a felt target (k, b) = "
                                  f"{tuple(lk.target)}: calibrate first (hapsim check does; "
                                  "or pass calibrated={name: (K, B)})",
                                  file=scene.path, line=lk.line or None,
                                  key=f"links.{lk.name}")
            raise ConfigError(f"link {lk.name!r} has non-finite stiffness/damping "
                              f"({K}, {B})", file=scene.path, line=lk.line or None,
                              key=f"links.{lk.name}")
        out.append((lk, K, B))
    return out


@dataclass(frozen=True)
class Network:
    """The linearised virtual network of a scene (contacts engaged).

    Attributes
    ----------
    N : int
        Number of moving (``mass``) points.
    masses : ndarray, shape (N,)
        Their inertia [kg].
    LK, LB : ndarray, shape (n_points, n_points)
        Stiffness [N/m] and damping [N s/m] Laplacians over every point of the scene
        (``F = -LK x - LB v``).
    mob : ndarray of int64, shape (N,)
        Indices of the moving masses among the points.
    port : int
        Index of the port, -1 without one.
    names : list of str
        Names of the moving masses.
    """

    N: int
    masses: np.ndarray
    LK: np.ndarray
    LB: np.ndarray
    mob: np.ndarray
    port: int
    names: list


def network(scene, calibrated=None, *, gain: float = 1.0) -> Network:
    """Extract the linear virtual network of a scene.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene; contacts count as engaged spring_dampers.
    calibrated : mapping, optional
        ``{link: (K, B)}`` overrides (required for ``target`` links), see
        :func:`link_values`.
    gain : float, optional
        Every link's (K, B) multiplied by this (a gain-margin probe).

    Returns
    -------
    Network

    Raises
    ------
    ConfigError
        See :func:`link_values`.
    """
    from hapsim.kernels.matrices import laplacians

    links = link_values(scene, calibrated)
    idx = {m.name: i for i, m in enumerate(scene.masses)}
    i1 = [idx[lk.m1] for lk, _, _ in links]
    i2 = [idx[lk.m2] for lk, _, _ in links]
    LK, LB = laplacians(len(scene.masses), i1, i2, [K for _, K, _ in links],
                        [B for _, _, B in links])
    if gain != 1.0:
        LK, LB = LK * gain, LB * gain
    mob = np.array([i for i, m in enumerate(scene.masses) if m.kind == "mass"], dtype=np.int64)
    masses = np.array([scene.masses[i].mass for i in mob], dtype=float)
    port = scene.index(scene.port.name) if scene.port is not None else -1
    return Network(mob.size, masses, LK, LB, mob, port, [scene.masses[i].name for i in mob])


def static_stiffness(scene, calibrated=None) -> float | None:
    """Stiffness of the virtual network felt at the port by a slow push.

    The force the scene returns per metre when the port is moved so slowly that every
    virtual mass is at rest: grounds fixed, the other masses at their static equilibrium,
    contacts engaged (as :func:`network`), dampers silent. A scene whose least damped mode
    at the port is a mode of an object (a string's partial) is felt at that frequency with
    the stiffness ``m (2 pi f0)^2`` of the loop's pole, far from this one.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene.
    calibrated : mapping, optional
        ``{link: (K, B)}`` overrides, as :func:`link_values`.

    Returns
    -------
    float or None
        ``k_static`` [N/m] >= 0; None without a port.

    Raises
    ------
    ConfigError
        See :func:`link_values`.

    Notes
    -----
    With ``LK`` the stiffness Laplacian over the points, ``p`` the port and ``f`` the
    moving masses, the Schur complement ``LK_pp - LK_pf LK_ff^+ LK_fp`` (static
    condensation of the free points; Guyan, AIAA J. 3(2) 1965). The pseudo-inverse covers
    masses tied to neither the port nor a ground: they carry no static force.
    """
    if scene.port is None:
        return None
    net = network(scene, calibrated)
    p, f = net.port, net.mob
    k = float(net.LK[p, p])
    if f.size:
        kff = net.LK[np.ix_(f, f)]
        kfp = net.LK[f, p]
        k -= float(kfp @ np.linalg.lstsq(kff, kfp, rcond=None)[0])
    return max(k, 0.0)


def _link_arrays(net: Network):
    """Link arrays ``(i1, i2, k, b)`` rebuilt from the Laplacians (upper triangle)."""
    n = net.LK.shape[0]
    i1, i2, k, b = [], [], [], []
    for a in range(n):
        for c in range(a + 1, n):
            if net.LK[a, c] != 0.0 or net.LB[a, c] != 0.0:
                i1.append(a)
                i2.append(c)
                k.append(-net.LK[a, c])
                b.append(-net.LB[a, c])
    return (np.array(i1, dtype=np.int64), np.array(i2, dtype=np.int64), np.array(k, float),
            np.array(b, float))


def virtual_blocks(net: Network, integrator: str, T: float):
    """Linear one-step map of the virtual network with the port position as input.

    Parameters
    ----------
    net : Network
        From :func:`network`.
    integrator : {"centred", "symplectic_euler", "exact"}
        Scheme (module docstring).
    T : float
        Period [s].

    Returns
    -------
    Av : ndarray, shape (2N, 2N)
        ``X[n+1] = Av X[n] + bp p[n] + bpp p[n-1]``, ``X = [x; xp]`` (centred) or
        ``[x; v]`` (others) of the N moving masses [m, m/s]; ``p`` the port position [m].
    bp, bpp : ndarray, shape (2N,)
        Port input columns.
    cx : ndarray, shape (2N,)
        Port force ``F[n] = cx X[n] + cp p[n] + cpp p[n-1]`` [N].
    cp, cpp : float
        Port feed-through [N/m].

    Raises
    ------
    ConfigError
        Unknown integrator.
    """
    check_integrator(integrator)
    N, mob, p = net.N, net.mob, net.port
    Kmm = net.LK[np.ix_(mob, mob)]
    Bmm = net.LB[np.ix_(mob, mob)]
    Minv = 1.0 / net.masses if N else np.zeros(0)
    if p >= 0:
        Kmp = net.LK[mob, p]
        Bmp = net.LB[mob, p]
        Kpm, Bpm = net.LK[p, mob], net.LB[p, mob]
        Kpp, Bpp = net.LK[p, p], net.LB[p, p]
    else:
        Kmp = Bmp = Kpm = Bpm = np.zeros(N)
        Kpp = Bpp = 0.0
    I = np.eye(N)
    Z = np.zeros((N, N))
    # forces on the moving masses: F = -Kmm x - Bmm vm - Kmp p - Bmp (p - pp)/T
    if integrator == "centred":
        # vm = (x - xp)/T ; x+ = 2x - xp + T^2 M^-1 F
        G = T * T * Minv[:, None]
        g = T * T * Minv
        Ax = 2 * I - G * (Kmm + Bmm / T)
        Axp = -I + G * (Bmm / T)
        Av = np.block([[Ax, Axp], [I, Z]])
        bp = np.concatenate([-g * (Kmp + Bmp / T), np.zeros(N)])
        bpp = np.concatenate([g * (Bmp / T), np.zeros(N)])
        cx = np.concatenate([-(Kpm + Bpm / T), Bpm / T])
    elif integrator == "symplectic_euler":
        D = np.diag(np.diag(Bmm))
        H = T * np.linalg.inv(np.diag(net.masses) + T * D) if N else np.zeros((0, 0))
        # v+ = v + H F ; x+ = x + T v+
        Avv = I - H @ Bmm
        Avx = -H @ Kmm
        Av = np.block([[I + T * Avx, T * Avv], [Avx, Avv]])
        hp = -H @ (Kmp + Bmp / T)
        hpp = H @ (Bmp / T)
        bp = np.concatenate([T * hp, hp])
        bpp = np.concatenate([T * hpp, hpp])
        cx = np.concatenate([-Kpm, -Bpm])
    else:
        from hapsim.kernels.matrices import exact_matrices

        fixed = [p] if p >= 0 else []
        phi, gam, psi = exact_matrices(net.LK.shape[0], mob, net.masses, fixed,
                                       *_link_arrays(net), T)
        Av = phi
        if p >= 0:
            bp = gam[:, 0] + psi[:, 0]
            bpp = -psi[:, 0]
        else:
            bp = bpp = np.zeros(2 * N)
        cx = np.concatenate([-Kpm, -Bpm])
    cp = -(Kpp + Bpp / T)
    cpp = Bpp / T
    return Av, np.asarray(bp, float), np.asarray(bpp, float), np.asarray(cx, float), cp, cpp


def multirate_blocks(blocks, nsub: int, position: str = "hold", force: str = "mean"):
    """Compose N audio-rate steps of the virtual network into one device-rate step.

    Parameters
    ----------
    blocks : tuple
        ``(Av, bp, bpp, cx, cp, cpp)`` of :func:`virtual_blocks` at the audio period
        ``Ta = T / N``: ``X[j+1] = Av X[j] + bp q[j] + bpp q[j-1]``, sub-step port force
        ``f[j] = cx X[j] + cp q[j] + cpp q[j-1]``.
    nsub : int
        N >= 1, audio sub-steps per device period.
    position : {"hold", "linear"}
        Port position at sub-step ``j = 0 .. N-1`` of period n: ``q[j] = p[n]`` or
        ``q[j] = p[n-1] + (j + 1) / N (p[n] - p[n-1])``; ``q[-1] = p[n-1]`` in both (the
        last sub-step of the period before).
    force : {"mean", "last"}
        Force to the device: ``F[n] = (1/N) sum_j f[j]`` or ``f[N-1]``.

    Returns
    -------
    tuple
        ``(Ad, bpd, bppd, cxd, cpd, cppd)``, the same shapes as ``blocks``:
        ``X[n+1] = Ad X[n] + bpd p[n] + bppd p[n-1]``, ``F[n] = cxd X[n] + cpd p[n] +
        cppd p[n-1]`` at the device period (``X[n]`` the state at the start of period n).

    Raises
    ------
    ValueError
        ``nsub`` < 1 or an unknown mode.

    Notes
    -----
    Exact composition of the linear sub-step maps (state and the two port inputs carried as
    ``X[j] = M[j] X + u[j] p[n] + w[j] p[n-1]``); it is what
    :func:`hapsim.kernels.audio.run_periods` computes, so the closed loop's eigenvalues are
    those of the multi-rate engine coupled to the device.
    """
    Av, bp, bpp, cx, cp, cpp = blocks
    if nsub < 1 or position not in ("hold", "linear") or force not in ("mean", "last"):
        raise ValueError(f"bad multi-rate coupling: nsub={nsub}, position={position!r}, "
                         f"force={force!r}")
    n = Av.shape[0]
    M = np.eye(n)
    u = np.zeros(n)
    w = np.zeros(n)
    fx = np.zeros(n)
    fu = fw = 0.0
    a_prev, b_prev = 0.0, 1.0           # q[-1] = p[n-1]
    for j in range(nsub):
        a = 1.0 if position == "hold" else (j + 1) / nsub
        b = 1.0 - a
        gx = cx @ M
        gu = cx @ u + cp * a + cpp * a_prev
        gw = cx @ w + cp * b + cpp * b_prev
        if force == "mean":
            fx, fu, fw = fx + gx / nsub, fu + gu / nsub, fw + gw / nsub
        else:
            fx, fu, fw = gx, gu, gw
        M = Av @ M
        u = Av @ u + bp * a + bpp * a_prev
        w = Av @ w + bp * b + bpp * b_prev
        a_prev, b_prev = a, b
    return M, u, w, fx, float(fu), float(fw)


def virtual_state_names(net: Network, integrator: str) -> list[str]:
    """Names of the states of :func:`virtual_blocks`, in order.

    Parameters
    ----------
    net : Network
    integrator : {"centred", "symplectic_euler", "exact"}

    Returns
    -------
    list of str, length 2N
        ``"<mass>.x[n]"`` for every moving mass, then ``"<mass>.x[n-1]"`` (centred) or
        ``"<mass>.v[n]"`` (others).
    """
    second = ".x[n-1]" if integrator == "centred" else ".v[n]"
    return [f"{nm}.x[n]" for nm in net.names] + [nm + second for nm in net.names]


def rest_position(scene, calibrated=None) -> float | None:
    """Rest position of the port: the static equilibrium of the scene held by the device.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene with a port.
    calibrated : mapping, optional
        ``{link: (K, B)}`` overrides, as :func:`link_values`.

    Returns
    -------
    float or None
        The port position [m] at which every moving mass and the port are at rest with no
        hand force (the device's force is then zero), grounds at their ``x0``; each
        contact counts where it is closed at that rest (its spring term
        ``K (x1 - x2 + threshold)``, engine law; at the threshold itself that term is zero
        and the contact counts as closed), found by an active-set iteration from all
        engaged. None when the rest is not unique (a part of the scene floats freely)
        or without a port.

    Notes
    -----
    Static balance ``LK_ff x_f + LK_fg x_g + h = 0`` over the free points ``f`` (moving
    masses and the port) with grounds ``g`` fixed, ``h`` the thresholds' constant forces;
    a dense LU solve up to :data:`DENSE_REST_MAX` free points, a sparse one above
    (``O(n)`` for a string; ``scipy.sparse`` costs ~0.4 CPU-s to import in every process
    that predicts, for no gain on a handful of masses). The rest is "not unique" where a
    group of free points is joined to no ground by springs (with every stiffness positive
    the balance matrix, a weighted graph Laplacian with its grounded rows, is then
    singular and otherwise positive definite: Chung 1997, *Spectral Graph Theory*,
    Ch. 1), decided from the links, not from a pivot's rounding.
    """
    if scene.port is None:
        return None
    links = link_values(scene, calibrated)
    idx = {m.name: i for i, m in enumerate(scene.masses)}
    n = len(scene.masses)
    free = np.array([m.kind != "ground" for m in scene.masses])
    x = np.array([m.x0 if m.kind == "ground" else 0.0 for m in scene.masses], dtype=float)
    fi = np.flatnonzero(free)
    pos = -np.ones(n, dtype=np.int64)
    pos[fi] = np.arange(fi.size)
    engaged = {id(lk): True for lk, _, _ in links if lk.kind == "contact"}
    for _ in range(len(engaged) + 2):
        rows, cols, vals = [], [], []
        rhs = np.zeros(fi.size)
        held = _Held(n, ~free)
        for lk, K, _ in links:
            if lk.kind == "contact" and not engaged[id(lk)]:
                continue
            a, c = idx[lk.m1], idx[lk.m2]
            held.join(a, c, K)
            off = lk.threshold if lk.kind == "contact" else 0.0
            # force on a: -K (x_a - x_c + off); on c: the opposite
            for i, j, sgn in ((a, a, 1.0), (a, c, -1.0), (c, c, 1.0), (c, a, -1.0)):
                if free[i]:
                    if free[j]:
                        rows.append(pos[i])
                        cols.append(pos[j])
                        vals.append(sgn * K)
                    else:
                        rhs[pos[i]] -= sgn * K * x[j]
            if free[a]:
                rhs[pos[a]] -= K * off
            if free[c]:
                rhs[pos[c]] += K * off
        if not held.all_held(fi):
            return None
        xf = _solve_balance(rows, cols, vals, rhs, exact=held.positive)
        if xf is None:
            return None
        if not np.all(np.isfinite(xf)):
            return None
        xs = x.copy()
        xs[fi] = xf
        changed = False
        for lk, _, _ in links:
            if lk.kind == "contact":
                closed = xs[idx[lk.m2]] - xs[idx[lk.m1]] <= lk.threshold
                if closed != engaged[id(lk)]:
                    engaged[id(lk)] = closed
                    changed = True
        if not changed:
            return float(xs[idx[scene.port.name]])
    return float(xs[idx[scene.port.name]])


#: Most free points whose static balance :func:`rest_position` solves densely (LU with
#: partial pivoting, ``O(n^3)``: 200 points cost ~1 ms); above, a sparse LU.
DENSE_REST_MAX = 200


class _Held:
    """Which points springs join to a ground (union-find over the links' mass indices)."""

    def __init__(self, n: int, ground) -> None:
        self.parent = list(range(n))
        self.grounded = [bool(g) for g in ground]
        self.positive = True                       # every stiffness joined is > 0

    def _root(self, i: int) -> int:
        while self.parent[i] != i:
            self.parent[i] = self.parent[self.parent[i]]
            i = self.parent[i]
        return i

    def join(self, a: int, c: int, K: float) -> None:
        if not K > 0:
            self.positive = self.positive and K == 0
            return
        ra, rc = self._root(a), self._root(c)
        if ra != rc:
            self.parent[ra] = rc
            self.grounded[rc] = self.grounded[rc] or self.grounded[ra]

    def all_held(self, points) -> bool:
        """Every one of ``points`` in a group with a ground (always True where a negative
        stiffness makes the graph argument void: the solve decides then)."""
        return not self.positive or all(self.grounded[self._root(int(i))] for i in points)


def _solve_balance(rows, cols, vals, rhs, exact: bool = False) -> np.ndarray | None:
    """Solve the balance ``M x = rhs``, ``M`` given as (row, column, value) triplets whose
    repeats add (the COO convention); None where ``M`` is found singular. ``exact``: the
    caller knows ``M`` non-singular (every group grounded, stiffnesses positive), so a
    dense LU serves; otherwise the sparse LU, whose zero pivot says singular."""
    n = rhs.size
    if n == 0:
        return np.zeros(0)
    if exact and n <= DENSE_REST_MAX:
        M = np.zeros((n, n))
        np.add.at(M, (np.asarray(rows, dtype=np.intp), np.asarray(cols, dtype=np.intp)),
                  np.asarray(vals, dtype=float))
        try:
            return np.linalg.solve(M, rhs)
        except np.linalg.LinAlgError:
            return None
    import warnings

    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import MatrixRankWarning, spsolve
    M = coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsc()
    with warnings.catch_warnings():
        warnings.simplefilter("error", MatrixRankWarning)
        try:
            return np.atleast_1d(spsolve(M, rhs))
        except (MatrixRankWarning, RuntimeError):
            return None


#: Largest closed-loop state built (dense eigenvalues and eigenvectors: O(N^3)), the
#: 1-D analysis's bound (hapsim.analysis.network.MAX_STATES).
MAX_STATES_ND = 2000


def link_blocks(scene) -> list[tuple]:
    """Every link and plane of a scene as linear blocks at the rest configuration.

    Parameters
    ----------
    scene : hapsim.scene.SceneND

    Returns
    -------
    list of (name, a, b, Kl, Bl)
        Mass names ``a`` and ``b`` (``b`` None for a plane: to ground), stiffness block
        ``Kl`` [N/m] and damping block ``Bl`` [N s/m], shape (n, n) (:mod:`hapsim.analysis.scene_check`'s docstring: the linearisation
        at rest).

    Raises
    ------
    ConfigError
        A Euclidean link or contact whose masses coincide at rest (its direction is
        undefined: give them distinct ``x0`` or use ``length: 0``), naming the link.
    """
    n = scene.dimension
    pos = {m.name: m.x0 for m in scene.masses}
    I = np.eye(n)
    out = []
    for lk in scene.links:
        L = lk.threshold if lk.kind == "contact" else lk.length
        if lk.kind == "spring_damper" and L == 0:
            out.append((lk.name, lk.m1, lk.m2, lk.stiffness * I, lk.damping * I))
            continue
        d0 = pos[lk.m1] - pos[lk.m2]
        l0 = float(np.linalg.norm(d0))
        if not l0 > 0:
            raise ConfigError(f"the masses {lk.m1!r} and {lk.m2!r} coincide at rest, so the "
                              "direction of this Euclidean link is undefined there; give "
                              "them distinct x0 (or length: 0 for a linear spring)",
                              file=scene.path, line=lk.line, key=f"links.{lk.name}")
        e = d0 / l0
        P = np.outer(e, e)
        out.append((lk.name, lk.m1, lk.m2,
                    lk.stiffness * P + lk.stiffness * (1.0 - L / l0) * (I - P),
                    lk.damping * P))
    for pl in scene.planes:
        P = np.outer(pl.normal, pl.normal)
        for m in pl.masses:
            out.append((pl.name, m, None, pl.stiffness * P, pl.damping * P))
    return out
