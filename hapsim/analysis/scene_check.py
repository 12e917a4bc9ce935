"""Scene-level closed-loop check: one state matrix for a whole scene coupled to its device.

docs/design.md, 'A whole scene': the whole sampled THS (device plant, force delay line, every
virtual mass integrated by the scene's ``integrator``, linearised links) is one linear
recursion ``s[n+1] = A s[n]``; its eigenvalues are the closed-loop poles of the scene as
the hand feels it. The matrix is built by :func:`hapsim.analysis.network.closed_loop`
(state layout, timing and the three integrators are described there); this module judges
it: stability verdict, the rendered pair at the port and every mode.

Linearisation: contacts are taken *engaged* (they act as spring_dampers), the stiffest
case the scene can reach; links given as a felt ``target`` need their calibrated (K, B).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.analysis.loop import STABILITY_TOL
from hapsim.analysis.modes import OBSERVABLE_TOL, Mode, modes_from_poles, rendered_pair
from hapsim.analysis.network import closed_loop, port_io

__all__ = ["SceneCheck", "check_scene", "scene_state_matrix", "STABILITY_TOL", "RIGID_TOL",
           "OBSERVABLE_TOL", "DEFECTIVE_COND"]

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
        def f(v):
            v = float(v)
            return v if math.isfinite(v) else None
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
    :func:`hapsim.analysis.loop.closed_loop_poles` ``(loop, K, B)`` up to roots at 0, and
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
