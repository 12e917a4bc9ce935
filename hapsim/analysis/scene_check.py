"""Scene-level closed-loop check in every dimension: one state matrix for a whole scene coupled
to its device.

docs/design.md, 'A whole scene': the whole sampled THS (device plant, force delay line, every
virtual mass integrated by the scene's ``integrator``, linearised links) is one linear
recursion ``s[n+1] = A s[n]``; its eigenvalues are the closed-loop poles of the scene as
the hand feels it. The matrix is built by :func:`hapsim.analysis.network.closed_loop`
(state layout, timing and the three integrators are described there); this module judges
it: stability verdict, the rendered pair at the port and every mode.

Linearisation: contacts are taken *engaged* (they act as spring_dampers), the stiffest
case the scene can reach; links given as a felt ``target`` need their calibrated (K, B).

**2-D and 3-D scenes** (:func:`check_scene_nd`, the counterpart of :func:`check_scene` for
:class:`hapsim.scene.SceneND`): stability from the MIMO characteristic, the felt stiffness
and damping matrices at the port, with the same timing and the same linearisation
(docs/design.md, 'A whole scene'):

State at sample ``n`` (each block n-dimensional)::

    x_dev[n], v_dev[n]          the device (exact ZOH of M x'' + B0 x' = f, M and B0
                                matrices: hapsim.analysis.ths.zoh_matrices)
    x_port[n-1]                 for the port links' damping
    F[n-1], ..., F[n-d]         the force delay line (computed, not yet applied)
    x[n] of the N virtual masses, then x[n-1] of them   (centred scheme)
    F[n-d-1]                    a delay d + f (0 < f < 1) only: the force held over the
                                period's first f T (the split hold,
                                hapsim.analysis.ths.split_hold_matrices)

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

The felt matrices are those of :func:`hapsim.analysis.ths.render_state` (the inverse
quadratic eigenvalue problem on the n least damped pairs the hand feels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.analysis.direction_limits import direction_limit
from hapsim.analysis.loop import STABILITY_TOL
from hapsim.analysis.modes import OBSERVABLE_TOL, Mode, modes_from_poles, rendered_pair
from hapsim.analysis.network import closed_loop, port_io
from hapsim.analysis.virtual_network import MAX_STATES_ND, link_blocks
from hapsim.analysis.ths import (MatrixLoop, MatrixRenderResult, render_state, split_hold_matrices,
                                 zoh_matrices)
from hapsim.errors import ConfigError
from hapsim.outputs import finite_or_none

__all__ = ["SceneCheck", "check_scene", "scene_state_matrix", "STABILITY_TOL", "RIGID_TOL",
           "OBSERVABLE_TOL", "DEFECTIVE_COND", "closed_loop_nd", "SceneCheckND",
           "check_scene_nd", "port_link_matrices", "WorkspaceFelt", "felt_over_workspace",
           "felt_summary"]

# STABILITY_TOL (re-exported): spectral radius accepted as stable, ``max |z| <= 1 +
# STABILITY_TOL``; defined once in :mod:`hapsim.analysis.loop` and shared with ``render``.
#: Eigenvalues within this distance of ``z = 1`` are free (rigid-body) drift modes; a
#: defective double eigenvalue at 1 is computed as ``1 +- O(sqrt(eps))``, so such a cluster
#: is not counted as unstable.
RIGID_TOL = 1e-6


@dataclass(frozen=True)
class SceneCheck:
    """Result of :func:`check_scene`.

    Attributes
    ----------
    eigenvalues : ndarray of complex, shape (n,)
        Eigenvalues of the closed-loop state matrix (the scene's closed-loop poles).
    spectral_radius : float
        ``max |z|`` [-].
    stable : bool
        ``max |z| <= 1 + STABILITY_TOL``, eigenvalues within ``RIGID_TOL`` of ``z = 1`` (free
        drift, a double pole of a free mass) excepted.
    rendered : Mode or None
        The felt oscillator at the port: least damped complex pair observable at the port
        (participation >= :data:`hapsim.analysis.modes.OBSERVABLE_TOL`), with ``k``, ``b``
        expressed with the device mass [kg]; None without a port or without such a pair.
    modes : list of Mode
        Every eigenvalue as a mode, least damped first (``k``, ``b`` with
        ``reference_mass``), each with its participation at the port (with a port);
        modes below :data:`hapsim.analysis.modes.OBSERVABLE_TOL` are modes of the object
        the hand does not feel.
    state_names : list of str
        What each state is, in state-matrix order.
    reference_mass : float
        Mass used for ``k = m |s|^2`` and ``b = -2 m Re s`` [kg]: the device mass with a port
        (the hand feels through it), else the total virtual mass.
    marginal : bool
        Some eigenvalue sits on the unit circle (``| |z| - 1 | <= STABILITY_TOL``) or at
        ``z = 1``: a lossless or free mode that never decays.
    has_port : bool
        Whether the device loop is part of the matrix.
    period : float
        Sample period ``T`` [s].
    calibrated : dict
        ``{link name: (K, B)}`` substituted for ``target`` links.
    integrator : str
        Scheme of the virtual masses the matrix was built with (``centred``,
        ``symplectic_euler`` or ``exact``).
    """

    eigenvalues: np.ndarray
    spectral_radius: float
    stable: bool
    rendered: Mode | None
    modes: list
    state_names: list
    reference_mass: float = 1.0
    marginal: bool = False
    has_port: bool = False
    period: float = 1.0
    calibrated: dict = field(default_factory=dict)
    integrator: str = "centred"

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite floats become ``None``).

        Returns
        -------
        dict
            Keys ``stable, marginal, spectral_radius, has_port, period, reference_mass,
            integrator, rendered (dict or None), modes (list of dict), eigenvalues (list of
            [re, im]), state_names, calibrated``.
        """
        f = finite_or_none
        return {
            "stable": bool(self.stable),
            "marginal": bool(self.marginal),
            "spectral_radius": f(self.spectral_radius),
            "has_port": bool(self.has_port),
            "period": f(self.period),
            "reference_mass": f(self.reference_mass),
            "integrator": self.integrator,
            "rendered": None if self.rendered is None else self.rendered.to_dict(),
            "modes": [md.to_dict() for md in self.modes],
            "eigenvalues": [[f(z.real), f(z.imag)] for z in self.eigenvalues],
            "state_names": list(self.state_names),
            "calibrated": {k: [f(v[0]), f(v[1])] for k, v in self.calibrated.items()},
        }


#: An eigenvalue whose condition number ``1 / |y^H x|`` (unit left/right eigenvectors) is
#: above this belongs to a (nearly) defective cluster, whose residues are meaningless apart:
#: it counts as fully observable and does not set the participation scale.
DEFECTIVE_COND = 1e6


def _port_participation(A: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Eigenvalues of ``A`` and each one's participation at the port.

    Parameters
    ----------
    A : ndarray, shape (n, n)
        Closed-loop state matrix.
    b, c : ndarray, shape (n,)
        Port input and output columns (:func:`hapsim.analysis.network.port_io`).

    Returns
    -------
    ev : ndarray of complex, shape (n,)
        Eigenvalues.
    participation : ndarray of float, shape (n,)
        ``|r_i| / max_j |r_j|`` with ``r_i = (c x_i)(y_i^H b) / (y_i^H x_i)`` the residue of
        ``c (zI - A)^-1 b`` at ``z_i`` (``x_i``, ``y_i`` right and left eigenvectors; the
        partial-fraction expansion of a diagonalisable system, e.g. Kailath, *Linear
        Systems*, 1980, Sec. 6.2). The maximum is over the well-conditioned modes away
        from ``z = 0`` and ``z = 1``; ill-conditioned ones (:data:`DEFECTIVE_COND`) get 1.
    """
    from scipy.linalg import eig
    ev, yl, xr = eig(A, left=True, right=True)
    ev = ev.astype(complex)
    yb = yl.conj().T @ b
    cx = c @ xr
    yx = np.einsum("ij,ij->j", yl.conj(), xr)
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = 1.0 / np.abs(yx)
        r = np.abs(cx * yb) * cond
    mod = np.abs(ev)
    bad = ~(cond <= DEFECTIVE_COND) | ~np.isfinite(r)
    scale_ok = ~bad & (np.abs(ev - 1.0) > RIGID_TOL) & (mod > 1e-12 * max(1.0, mod.max()))
    scale = float(r[scale_ok].max()) if np.any(scale_ok) else float(np.nanmax(
        np.where(bad, 0.0, r), initial=0.0))
    part = np.where(bad, 1.0, r / scale if scale > 0 else 1.0)
    return ev, np.minimum(part, 1.0)


def scene_state_matrix(scene, *, calibrated=None, integrator=None):
    """The closed-loop state matrix of a scene coupled to its device.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A validated scene. With a port it needs its ``device`` (mass, friction, delay,
        hold); without one, only the virtual network is modelled (the engine's update
        matrix).
    calibrated : mapping of str to (float, float), optional
        ``{link name: (K [N/m], B [N s/m])}`` overriding links, e.g. calibrated ``target``
        links.
    integrator : {"centred", "symplectic_euler", "exact"}, optional
        Scheme of the virtual masses; ``scene.integrator`` when None.

    Returns
    -------
    A : ndarray, shape (n, n)
        ``s[n+1] = A s[n]`` (layout and timing: :mod:`hapsim.analysis.network`).
    state_names : list of str, length n
        What each state is.

    Raises
    ------
    ConfigError
        When a ``target`` link has no calibrated (K, B) ("calibrate first"), a calibrated
        value is not finite or names no link, a port has no device section, or the
        integrator is unknown.
    """
    return closed_loop(scene, integrator, calibrated=calibrated)


def check_scene(scene, *, calibrated=None, integrator=None) -> SceneCheck:
    """Closed-loop stability and rendered (k, b) of a whole scene felt through its device.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A validated scene (:func:`hapsim.scene.load_scene`).
    calibrated : mapping of str to (float, float), optional
        ``{link name: (K [N/m], B [N s/m])}`` for ``target`` links (see
        :func:`hapsim.analysis.loop.calibrate`) or any override.
    integrator : {"centred", "symplectic_euler", "exact"}, optional
        Scheme of the virtual masses; ``scene.integrator`` when None (what the engine
        runs).

    Returns
    -------
    SceneCheck
        Eigenvalues of :func:`scene_state_matrix`, spectral radius, verdict, the rendered
        pair at the port (least damped complex pair observable at the port, ``k = m |s|^2``, ``b = -2 m Re s`` with
        ``m`` the device mass, docs/design.md, 'The inverse map') and every mode.

    Raises
    ------
    ConfigError
        "calibrate first" for ``target`` links without calibrated values, an unknown
        integrator; see :func:`scene_state_matrix`.

    Notes
    -----
    For a port tied to a ground by one spring_damper (K, B) the eigenvalues are those of
    :func:`hapsim.analysis.loop_poles.closed_loop_poles` ``(loop, K, B)`` up to roots at 0, and
    ``rendered`` equals the pair of :func:`hapsim.analysis.loop.render`.
    """
    integrator = integrator or getattr(scene, "integrator", None) or "centred"
    A, names = scene_state_matrix(scene, calibrated=calibrated, integrator=integrator)
    cal = {k: (float(v[0]), float(v[1])) for k, v in dict(calibrated or {}).items()}
    has_port = scene.port is not None
    if has_port:
        from hapsim.analysis.network import device_body
        ref = device_body(scene.device)[0]
    else:
        ref = float(sum(m.mass for m in scene.masses if m.kind == "mass")) or 1.0
    if A.shape[0] == 0:
        return SceneCheck(eigenvalues=np.zeros(0, complex), spectral_radius=0.0, stable=True,
                          rendered=None, modes=[], state_names=names, reference_mass=ref,
                          marginal=False, has_port=has_port, period=scene.period,
                          calibrated=cal, integrator=integrator)
    part = None
    if has_port:
        ev, part = _port_participation(A, *port_io(scene, A.shape[0]))
    else:
        ev = np.linalg.eigvals(A).astype(complex)
    mod = np.abs(ev)
    radius = float(mod.max())
    near_one = np.abs(ev - 1.0) <= RIGID_TOL
    stable = bool(np.all((mod <= 1.0 + STABILITY_TOL) | near_one))
    marginal = bool(np.any((np.abs(mod - 1.0) <= STABILITY_TOL) | near_one))
    # Dead-beat states (delay line, held copies) give exact zeros computed as ~1e-17:
    # report them as z = 0 (both members of a conjugate pair alike).
    tiny = mod <= 1e-12 * max(1.0, radius)
    ev_r = np.where(tiny, 0.0, ev)
    modes = modes_from_poles(ev_r, ref, scene.period, participation=part)
    rendered = rendered_pair(modes) if has_port else None
    return SceneCheck(eigenvalues=ev, spectral_radius=radius, stable=stable,
                      rendered=rendered, modes=modes, state_names=names, reference_mass=ref,
                      marginal=marginal, has_port=has_port, period=scene.period,
                      calibrated=cal, integrator=integrator)


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
    loop = MatrixLoop(mass=dev.mass, friction=dev.friction, rate_hz=scene.rate_hz,
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


def felt_summary(r: dict) -> dict:
    """The verdict and the felt matrices of a :class:`~hapsim.analysis.ths.MatrixRenderResult`'s
    dict, as every n-D check's ``--json`` says them.

    Parameters
    ----------
    r : dict
        :meth:`hapsim.analysis.ths.MatrixRenderResult.to_dict`.

    Returns
    -------
    dict
        ``stable``, ``verdict`` (``stable`` or ``unstable``), ``spectral_radius``,
        ``felt_stiffness`` [N/m] and ``felt_damping`` [N s/m] (n x n),
        ``principal_directions``, ``direction_stiffness``, ``direction_damping``,
        ``direction_mass`` [kg].
    """
    keys = ("spectral_radius", "felt_stiffness", "felt_damping", "principal_directions",
            "direction_stiffness", "direction_damping", "direction_mass")
    return {"stable": bool(r["stable"]), "verdict": "stable" if r["stable"] else "unstable",
            **{k: r[k] for k in keys}}


@dataclass(frozen=True)
class SceneCheckND:
    """The n-D check of a scene (:func:`check_scene_nd`).

    Attributes
    ----------
    dof : int
        n.
    render : hapsim.analysis.ths.MatrixRenderResult
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
    render: MatrixRenderResult
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
        ``port_stiffness``, ``port_damping``, ``states``, ``rendered_poles``, ``note``.

        Returns
        -------
        dict
            Those keys (:func:`felt_summary` for the verdict, the felt matrices [N/m],
            [N s/m] and the directions; ``port_stiffness`` [N/m] and ``port_damping``
            [N s/m] as n lists of n) and ``stiffness_limits``: None, or per limit direction
            ``{"direction": n floats, "K_max": [N/m] or None when not finite}``.
        """
        r = self.render.to_dict()
        out = {"dof": self.dof, **felt_summary(r),
               "port_stiffness": self.port_stiffness.tolist(),
               "port_damping": self.port_damping.tolist(),
               "states": self.states, "rendered_poles": r["rendered_poles"],
               "stiffness_limits": None if self.stiffness_limits is None else [
                   {"direction": self.limit_directions[:, i].tolist(),
                    "K_max": float(v) if np.isfinite(v) else None}
                   for i, v in enumerate(self.stiffness_limits)],
               "note": r["note"]}
        return out


def port_link_matrices(scene) -> tuple[np.ndarray, np.ndarray, list]:
    """The virtual stiffness and damping the links at an n-D scene's port add up to.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port.

    Returns
    -------
    Kp : ndarray, shape (n, n)
        Sum of the port links' stiffness blocks [N/m] (:func:`link_blocks`).
    Bp : ndarray, shape (n, n)
        Sum of their damping blocks [N s/m].
    moving : list of str
        The moving masses a port link ends on (empty: every port link ends on a ground,
        and ``(Kp, Bp)`` is what the port feels of the virtual world, as in 1-D).
    """
    n = scene.dimension
    Kp, Bp = np.zeros((n, n)), np.zeros((n, n))
    port = scene.port.name
    kinds = {m.name: m.kind for m in scene.masses}
    moving = []
    for _, a, b, Kl, Bl in link_blocks(scene):
        if port in (a, b):
            Kp += Kl
            Bp += Bl
            other = b if a == port else a
            if other is not None and kinds[other] != "ground":
                moving.append(other)
    return Kp, Bp, moving


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
    Kp, Bp, moving = port_link_matrices(scene)
    grounded = not moving
    r = render_state(A, scene.device.mass, scene.period, K=Kp, B=Bp)
    E = lim = None
    if grounded:
        loop = MatrixLoop(mass=scene.device.mass, friction=scene.device.friction,
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
        :meth:`hapsim.analysis.ths.MatrixLoop.from_device` (the scene's joint
        inertia and friction, hand mass and damping, rate and delay), felt through
        :func:`hapsim.analysis.ths.render` with the scene's port ``K`` and ``B``
        (the inverse quadratic eigenvalue problem; module docstring).

    Raises
    ------
    ConfigError
        A Cartesian device (no joints: no workspace).
    """
    from hapsim.analysis.ths import render
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
            loop = MatrixLoop.from_device(kin, q, Mq, Bq, hand_mass=mh, hand_damping=bh,
                                          rate_hz=scene.rate_hz, delay=dev.delay)
            x = kin.forward(q)
        except (KinematicsError, ConfigError):
            continue
        r = render(loop, K, B)
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
