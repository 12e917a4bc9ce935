"""Closed-loop check of a 2-D or 3-D scene felt through its device: stability from the MIMO
characteristic, the felt stiffness and damping matrices at the port.

The n-D counterpart of :mod:`hapsim.analysis.network` / :func:`hapsim.analysis.check_scene`
for :class:`hapsim.scene.SceneND`, with the same timing and the same linearisation
(docs/design.md, 'A whole scene'):

State at sample ``n`` (each block n-dimensional)::

    x_dev[n], v_dev[n]          the device (exact ZOH of M x'' + B0 x' = f, M and B0
                                matrices: hapsim.analysis.ths_nd.zoh_matrices)
    x_port[n-1]                 for the port links' damping
    F[n-1], ..., F[n-d]         the force delay line (computed, not yet applied)
    x[n] of the N virtual masses, then x[n-1] of them   (centred scheme)
    F[n-d-1]                    a delay d + f (0 < f < 1) only: the force held over the
                                period's first f T (the split hold,
                                hapsim.analysis.ths_nd.split_hold_matrices)

At sample ``n`` the port is at the device sample; every link's force is computed from
the positions at ``n`` and ``n - 1``; the virtual masses advance
``x[n+1] = 2 x[n] - x[n-1] + T^2 F / m``; the force on the port ``F[n]`` is applied over the
period starting at ``n + d``.

Linearisation at the rest configuration (the scene's ``x0``, the port at the device's
handle position), every contact and plane engaged (the stiffest case, as in 1-D): a link
between ``a`` and ``b`` with ``d0 = x0_a - x0_b``, ``l0 = |d0|``, ``e = d0 / l0`` acts
with the stiffness and damping blocks

- ``length: 0`` spring_damper: ``K I`` and ``B I`` (exact: the law is linear);
- Euclidean law with rest length ``L`` (``length > 0``, or a contact with
  ``L = threshold``): ``K e e^T + K (1 - L / l0) (I - e e^T)`` (the axial stiffness and
  the geometric stiffness of the tension ``K (l0 - L)``) and ``B e e^T``; it needs
  ``l0 > 0``;
- a plane with unit normal ``u`` on a mass: ``K u u^T`` and ``B u u^T`` to ground.

The felt matrices are those of :func:`hapsim.analysis.ths_nd.render_state` (the inverse
quadratic eigenvalue problem on the n least damped pairs the hand feels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapsim.analysis.direction_limits import direction_limit
from hapsim.analysis.ths_nd import (LoopModelND, RenderND, render_state, split_hold_matrices,
                                    zoh_matrices)
from hapsim.errors import ConfigError

__all__ = ["link_blocks", "closed_loop_nd", "SceneCheckND", "check_scene_nd",
           "MAX_STATES_ND", "WorkspaceFelt", "felt_over_workspace"]

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
        ``Kl`` [N/m] and damping block ``Bl`` [N s/m], shape (n, n) (module docstring).

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


def closed_loop_nd(scene) -> tuple[np.ndarray, list]:
    """The closed-loop state matrix of an n-D scene coupled to its device.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device.

    Returns
    -------
    A : ndarray, shape (N, N)
        ``s[n+1] = A s[n]`` (layout and timing in the module docstring).
    names : list of str
        What each block of n states is.

    Raises
    ------
    ConfigError
        No port or device, a degenerate Euclidean link (:func:`link_blocks`), or more
        than :data:`MAX_STATES_ND` states.
    """
    if scene.port is None or scene.device is None:
        raise ConfigError("the n-D check needs a port and its device", file=scene.path,
                          key="masses")
    n, T, dev = scene.dimension, scene.period, scene.device
    d = int(math.floor(dev.delay))
    split = float(dev.delay) % 1.0 > 0      # the split hold: one more block, last
    virt = [m for m in scene.masses if m.kind == "mass"]
    Nv = len(virt)
    N = n * (3 + d + 2 * Nv + split)
    if N > MAX_STATES_ND:
        raise ConfigError(f"the closed loop would have {N} states, more than "
                          f"{MAX_STATES_ND} (dense eigenvalues, O(N^3))", file=scene.path,
                          key="masses")
    # node order: the port, then the virtual masses
    node = {scene.port.name: 0}
    node.update({m.name: 1 + i for i, m in enumerate(virt)})
    nodes = 1 + Nv
    Kg = np.zeros((nodes * n, nodes * n))
    Bg = np.zeros_like(Kg)

    def blk(i):
        return slice(i * n, (i + 1) * n)
    for _, a, b, Kl, Bl in link_blocks(scene):
        ia, ib = node.get(a), node.get(b)        # None: a ground (constant)
        for i, j, sgn in ((ia, ia, 1), (ib, ib, 1), (ia, ib, -1), (ib, ia, -1)):
            if i is None or j is None:
                continue
            Kg[blk(i), blk(j)] += sgn * Kl
            Bg[blk(i), blk(j)] += sgn * Bl
    # force on the nodes at n: F = -(Kg + Bg/T) X[n] + (Bg/T) X[n-1]
    Fx, Fxp = -(Kg + Bg / T), Bg / T
    # state blocks
    XP, VP, XPP = 0, 1, 2

    def fd(k):                                   # F[n-k], k = 1..d
        return 2 + k

    def xv(i):
        return 3 + d + i

    def xvp(i):
        return 3 + d + Nv + i
    cur = [XP] + [xv(i) for i in range(Nv)]     # X[n] blocks, node order
    prev = [XPP] + [xvp(i) for i in range(Nv)]  # X[n-1] blocks
    A = np.zeros((N, N))
    loop = LoopModelND(mass=dev.mass, friction=dev.friction, rate_hz=scene.rate_hz,
                       delay=dev.delay)
    if split:
        # F[n-d] enters through Gamma0 and is held over the next period's first f T
        # (block H); Gamma1 takes H (hapsim.analysis.subsample.held_plant)
        Ad, Bd, G1 = split_hold_matrices(loop)
        H = 3 + d + 2 * Nv
    else:
        Ad, Bd = zoh_matrices(loop)

    def put(r, c, M):
        A[blk(r), blk(c)] += M
    A[:2 * n, :2 * n] = Ad
    # port force row: F[n] = Fx[0, :] X[n] + Fxp[0, :] X[n-1]
    port_row = [(cur[j], Fx[blk(0), blk(j)]) for j in range(nodes)] + \
               [(prev[j], Fxp[blk(0), blk(j)]) for j in range(nodes)]
    if d == 0:
        for c, M in port_row:                   # u[n] = F[n]
            put(XP, c, Bd[:n] @ M)
            put(VP, c, Bd[n:] @ M)
            if split:
                put(H, c, M)
    else:
        put(XP, fd(d), Bd[:n])                  # u[n] = F[n-d]
        put(VP, fd(d), Bd[n:])
        if split:
            put(H, fd(d), np.eye(n))
        for c, M in port_row:                   # F[(n+1)-1] = F[n]
            put(fd(1), c, M)
        for k in range(2, d + 1):
            put(fd(k), fd(k - 1), np.eye(n))
    if split:
        put(XP, H, G1[:n])
        put(VP, H, G1[n:])
    put(XPP, XP, np.eye(n))
    for i, m in enumerate(virt):
        g = T * T / m.mass
        put(xv(i), xv(i), 2.0 * np.eye(n))
        put(xv(i), xvp(i), -np.eye(n))
        for j in range(nodes):
            put(xv(i), cur[j], g * Fx[blk(1 + i), blk(j)])
            put(xv(i), prev[j], g * Fxp[blk(1 + i), blk(j)])
        put(xvp(i), xv(i), np.eye(n))
    names = (["x_dev[n]", "v_dev[n]", "x_port[n-1]"] + [f"F[n-{k}]" for k in range(1, d + 1)]
             + [f"x[n] {m.name}" for m in virt] + [f"x[n-1] {m.name}" for m in virt]
             + ([f"F[n-{d + 1}] (held the first f T)"] if split else []))
    return A, names


@dataclass(frozen=True)
class SceneCheckND:
    """The n-D check of a scene (:func:`check_scene_nd`).

    Attributes
    ----------
    dof : int
        n.
    render : hapsim.analysis.ths_nd.RenderND
        Felt matrices at the port, principal directions, poles, spectral radius.
    port_stiffness, port_damping : ndarray, shape (n, n)
        The links at the port taken as port-to-ground springs (the sum of their blocks)
        [N/m], [N s/m]: the virtual (K, B) when every port link ends on a ground.
    states : int
        Size of the closed-loop state.
    limit_directions : ndarray, shape (n, n) or None
        The principal axes of the device's Cartesian mass (columns, lightest first).
    stiffness_limits : ndarray, shape (n,) or None
        ``K_max`` [N/m] along each of them
        (:func:`hapsim.analysis.direction_limits.direction_limit`, with the port damping and the
        rest of the port stiffness); None when a port link ends on a moving mass (the
        limit of a port-ground spring says nothing about the felt k then, as in 1-D).
    """

    dof: int
    render: RenderND
    port_stiffness: np.ndarray
    port_damping: np.ndarray
    states: int
    limit_directions: np.ndarray | None = None
    stiffness_limits: np.ndarray | None = None

    @property
    def stable(self) -> bool:
        """The MIMO verdict (spectral radius within the 1-D tolerance of 1)."""
        return self.render.stable

    def to_dict(self) -> dict:
        """JSON-ready dict: ``dof``, ``stable``, ``spectral_radius``, ``felt_stiffness``,
        ``felt_damping`` (n x n), ``principal_directions``, the per-direction pairs,
        ``port_stiffness``, ``port_damping``, ``states``, ``rendered_poles``, ``note``."""
        r = self.render.to_dict()
        out = {"dof": self.dof, "stable": bool(self.stable),
               "verdict": "stable" if self.stable else "unstable",
               "spectral_radius": r["spectral_radius"],
               "felt_stiffness": r["felt_stiffness"], "felt_damping": r["felt_damping"],
               "principal_directions": r["principal_directions"],
               "direction_stiffness": r["direction_stiffness"],
               "direction_damping": r["direction_damping"],
               "direction_mass": r["direction_mass"],
               "port_stiffness": self.port_stiffness.tolist(),
               "port_damping": self.port_damping.tolist(),
               "states": self.states, "rendered_poles": r["rendered_poles"],
               "stiffness_limits": None if self.stiffness_limits is None else [
                   {"direction": self.limit_directions[:, i].tolist(),
                    "K_max": float(v) if np.isfinite(v) else None}
                   for i, v in enumerate(self.stiffness_limits)],
               "note": r["note"]}
        return out


def check_scene_nd(scene, progress=None) -> SceneCheckND:
    """Closed-loop stability and felt matrices of an n-D scene felt through its device.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port.
    progress : callable, optional
        ``progress(done, total)`` after each direction's stiffness limit (the long part
        when the delay is long: the limit's scan grows with the loop's order).

    Returns
    -------
    SceneCheckND
        From the eigenvalues and eigenvectors of :func:`closed_loop_nd` (the MIMO
        characteristic; Li, Tavakoli & Huang 2014: not axis by axis).

    Raises
    ------
    ConfigError
        As :func:`closed_loop_nd`.
    """
    A, _ = closed_loop_nd(scene)
    n = scene.dimension
    Kp = np.zeros((n, n))
    Bp = np.zeros((n, n))
    port = scene.port.name
    grounded = True
    kinds = {m.name: m.kind for m in scene.masses}
    for _, a, b, Kl, Bl in link_blocks(scene):
        if port in (a, b):
            Kp += Kl
            Bp += Bl
            other = b if a == port else a
            grounded = grounded and (other is None or kinds[other] == "ground")
    r = render_state(A, scene.device.mass, scene.period, K=Kp, B=Bp)
    E = lim = None
    if grounded:
        loop = LoopModelND(mass=scene.device.mass, friction=scene.device.friction,
                           rate_hz=scene.rate_hz, delay=scene.device.delay)
        E = np.linalg.eigh(scene.device.mass)[1]
        lim = np.empty(n)
        for i in range(n):
            lim[i] = direction_limit(loop, E[:, i], Bp,
                                     Kp - float(E[:, i] @ Kp @ E[:, i])
                                     * np.outer(E[:, i], E[:, i]))
            if progress is not None:
                progress(i + 1, n)
    return SceneCheckND(dof=n, render=r, port_stiffness=Kp, port_damping=Bp,
                        states=A.shape[0], limit_directions=E, stiffness_limits=lim)


@dataclass(frozen=True)
class WorkspaceFelt:
    """The workspace of a scene's device and the felt stiffness over it
    (:func:`felt_over_workspace`).

    Attributes
    ----------
    workspace : ndarray, shape (W, n)
        Handle positions [m] of a joint grid about the operating point (refused
        configurations left out).
    positions : ndarray, shape (E, n)
        Handle positions [m] where the felt matrices were computed.
    felt_stiffness, felt_damping : ndarray, shape (E, n, n)
        The felt ``k`` [N/m] and ``b`` [N s/m] there (nan where the loop has fewer than n
        rendered pairs or is unstable).
    stable : ndarray of bool, shape (E,)
        The MIMO verdict there.
    span_deg : float
        Half-width of the joint grid about the operating point [deg].
    note : str
        Empty, or why there are no felt matrices over the workspace.
    """

    workspace: np.ndarray
    positions: np.ndarray
    felt_stiffness: np.ndarray
    felt_damping: np.ndarray
    stable: np.ndarray
    span_deg: float
    note: str = ""


def felt_over_workspace(scene, *, span_deg: float = 30.0, points: int = 24,
                        ellipses: int = 4) -> WorkspaceFelt:
    """Where the handle of a scene's kinematic device can go, and what the port's links
    feel like at those places (the configuration-dependent Cartesian mass).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a pantograph or delta device. When its port links all end
        on grounds they are the port-ground stiffness ``K`` and damping ``B`` matrices of
        :class:`SceneCheckND`, moved with the handle; when one ends on a moving mass the
        felt matrices are the scene's own and none is computed over the workspace
        (``note`` says so).
    span_deg : float, optional
        Half-width of the joint grid about the scene's joints [deg].
    points : int, optional
        Grid points per joint for the workspace (the delta: ``points // 2`` per joint).
    ellipses : int, optional
        Grid points per joint where the felt matrices are computed (the delta: one
        fewer).

    Returns
    -------
    WorkspaceFelt
        At each grid configuration ``q``: the loop of
        :meth:`hapsim.analysis.ths_nd.LoopModelND.from_device` (the scene's joint
        inertia and friction, hand mass and damping, rate and delay), felt through
        :func:`hapsim.analysis.ths_nd.render_nd` with the scene's port ``K`` and ``B``
        (the inverse quadratic eigenvalue problem; module docstring).

    Raises
    ------
    ConfigError
        A Cartesian device (no joints: no workspace).
    """
    from hapsim.analysis.ths_nd import render_nd
    from hapsim.errors import KinematicsError
    from hapsim.kinematics import device as make
    dev = scene.device
    if dev is None or dev.joints is None:
        raise ConfigError("the workspace is a kinematic device's (pantograph, delta): a "
                          "cartesian device has none", file=scene.path, key="device.kind")
    chk_links = link_blocks(scene)
    kinds = {m.name: m.kind for m in scene.masses}
    port = scene.port.name
    n = scene.dimension
    K = np.zeros((n, n))
    B = np.zeros((n, n))
    note = ""
    for _, a, b, Kl, Bl in chk_links:
        if port in (a, b):
            other = b if a == port else a
            if other is not None and kinds[other] != "ground":
                note = (f"the port link to the moving mass {other!r}: the felt matrices "
                        "are the scene's, at the handle only")
                ellipses = 0
            K += Kl
            B += Bl
    kin = make(dev.kind, dev.geometry)
    q0 = np.asarray(dev.joints, float)
    span = np.radians(span_deg)

    def grid(m):
        axes = [np.linspace(q - span, q + span, m) for q in q0]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, n)
    W = []
    for q in grid(points if n == 2 else max(3, points // 2)):
        try:
            W.append(kin.forward(q))
        except KinematicsError:
            continue
    P, Ks, Bs, ok = [], [], [], []
    Mq, Bq, mh, bh = dev.joint_inertia, dev.joint_friction, dev.hand_mass, dev.hand_damping
    for q in (grid(ellipses if n == 2 else ellipses - 1) if ellipses > 1 else ()):
        try:
            loop = LoopModelND.from_device(kin, q, Mq, Bq, hand_mass=mh, hand_damping=bh,
                                           rate_hz=scene.rate_hz, delay=dev.delay)
            x = kin.forward(q)
        except (KinematicsError, ConfigError):
            continue
        r = render_nd(loop, K, B)
        good = r.felt_stiffness is not None and r.stable
        P.append(x)
        Ks.append(r.felt_stiffness if good else np.full((n, n), np.nan))
        Bs.append(r.felt_damping if good else np.full((n, n), np.nan))
        ok.append(bool(r.stable))
    return WorkspaceFelt(workspace=np.array(W).reshape(-1, n),
                         positions=np.array(P).reshape(-1, n),
                         felt_stiffness=np.array(Ks).reshape(-1, n, n),
                         felt_damping=np.array(Bs).reshape(-1, n, n),
                         stable=np.array(ok, bool), span_deg=float(span_deg), note=note)
