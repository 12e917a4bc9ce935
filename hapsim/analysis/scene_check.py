"""Scene-level closed-loop check: one state matrix for a whole scene coupled to its device.

DESIGN.md Sec. 4, last bullet: the whole sampled THS (device plant, force delay line, every
virtual mass, linearised links) is one linear recursion ``s[n+1] = A s[n]``; its eigenvalues
are the closed-loop poles of the scene as the hand feels it.

State at sample ``n`` (``state_names`` spells it out):

=============================  =====================================================
``"zoh"`` hold                 ``x_dev[n]``, ``v_dev[n]`` (exact ZOH of
                               ``m x'' + b0 x' = f``), ``x_port[n-1]``
``"ideal"`` hold               ``x_dev[n]``, ``x_dev[n-1]`` (centred-difference image
                               of the mass, eq. (4) friction form)
force delay line (d states)    ``F[n-1], ..., F[n-d]`` (forces computed, not yet applied)
each virtual ``mass`` j        ``x_j[n]``, ``x_j[n-1]``
=============================  =====================================================

Grounds are constants: they enter the link forces as a constant input that drops out of
the linear dynamics (deviations from equilibrium), so they contribute no state.

Timing. At sample ``n`` the port position is the device sample, ``x_port[n] = x_dev[n]``;
every link force is computed from the positions at ``n`` and ``n - 1``
(``F = K (x1 - x2) + B ((x1 - x2) - (x1p - x2p)) / T``, ``-F`` on the first mass, ``+F`` on
the second); the virtual masses advance ``x[n+1] = 2 x[n] - x[n-1] + T^2 F / m``; the force
on the port computed at ``n``, ``F[n]``, is applied by the device over the period starting
at sample ``n + d``: the force held over ``[nT, (n+1)T)`` is ``u[n] = F[n-d]`` (``d = 0``: the
force computed from ``x[n]`` acts over the period that starts at ``n``). The device then
advances ``[x, v][n+1] = Ad [x, v][n] + Bd u[n]`` (``"zoh"``) or
``x[n+1] = (1+a) x[n] - a x[n-1] + T^2 u[n] / (m c)`` with ``a = e^(-b0T/m)``,
``c = (b0T/m) / (1 - a)`` (``"ideal"``, Florens et al. eq. (4); ``a = c = 1`` without
friction). For a port tied to a ground by a spring_damper this gives exactly
``z^(d+1) D(z) + N(z) (K z + (B/T)(z - 1)) = 0``, i.e. the poles of
:func:`hapsim.analysis.loop.closed_loop_poles` (up to roots at ``z = 0``).

Linearisation: contacts are taken *engaged* (they act as spring_dampers), the stiffest
case the scene can reach; links given as a felt ``target`` need their calibrated (K, B).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.analysis.loop import zoh_state_space
from hapsim.analysis.modes import Mode, modes_from_poles, rendered_pair
from hapsim.errors import ConfigError

__all__ = ["SceneCheck", "check_scene", "scene_state_matrix", "STABILITY_TOL", "RIGID_TOL"]

#: Spectral radius accepted as stable: ``max |z| <= 1 + STABILITY_TOL`` (lossless modes of an
#: undamped virtual network sit on the unit circle up to round-off).
STABILITY_TOL = 1e-9
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
        The felt oscillator at the port: least damped complex pair, with ``k``, ``b``
        expressed with the device mass [kg]; None without a port or without a pair.
    modes : list of Mode
        Every eigenvalue as a mode, least damped first (``k``, ``b`` with
        ``reference_mass``).
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

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite floats become ``None``).

        Returns
        -------
        dict
            Keys ``stable, marginal, spectral_radius, has_port, period, reference_mass,
            rendered (dict or None), modes (list of dict), eigenvalues (list of
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
            "rendered": None if self.rendered is None else self.rendered.to_dict(),
            "modes": [md.to_dict() for md in self.modes],
            "eigenvalues": [[f(z.real), f(z.imag)] for z in self.eigenvalues],
            "state_names": list(self.state_names),
            "calibrated": {k: [f(v[0]), f(v[1])] for k, v in self.calibrated.items()},
        }


def _link_values(scene, calibrated) -> list[tuple]:
    """(link, K, B) for every link, with calibrated values substituted."""
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


def scene_state_matrix(scene, *, calibrated=None):
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

    Returns
    -------
    A : ndarray, shape (n, n)
        ``s[n+1] = A s[n]`` (layout and timing: module docstring).
    state_names : list of str, length n
        What each state is.

    Raises
    ------
    ConfigError
        When a ``target`` link has no calibrated (K, B) ("calibrate first"), a calibrated
        value is not finite or names no link, or a port has no device section.
    """
    links = _link_values(scene, calibrated)
    T = scene.period
    port = scene.port
    names: list[str] = []
    slot: dict[str, tuple[int | None, int | None]] = {}  # mass -> (x[n] index, x[n-1] index)

    dev = None
    d = 0
    if port is not None:
        dev = scene.device
        if dev is None:
            raise ConfigError("a scene with a port needs a device section", file=scene.path,
                              key="device")
        d = int(dev.delay)
        if dev.hold == "zoh":
            names += [f"{port.name}.x[n] (device position)", "device.v[n]",
                      f"{port.name}.x[n-1]"]
            slot[port.name] = (0, 2)
        elif dev.hold == "ideal":
            names += [f"{port.name}.x[n] (device position)", f"{port.name}.x[n-1]"]
            slot[port.name] = (0, 1)
        else:
            raise ConfigError(f"unknown hold {dev.hold!r}; valid: zoh, ideal",
                              file=scene.path, key="device.hold")
        delay0 = len(names)
        names += [f"F[n-{i}] (port force, delay line)" for i in range(1, d + 1)]
    for m in scene.masses:
        if m.kind == "mass":
            slot[m.name] = (len(names), len(names) + 1)
            names += [f"{m.name}.x[n]", f"{m.name}.x[n-1]"]
    n = len(names)
    A = np.zeros((n, n))

    def unit(i):
        e = np.zeros(n)
        if i is not None:
            e[i] = 1.0
        return e

    def pos(name):
        i, ip = slot.get(name, (None, None))  # ground: constant, no state
        return unit(i), unit(ip)

    force = {m.name: np.zeros(n) for m in scene.masses}
    for lk, K, B in links:
        x1, x1p = pos(lk.m1)
        x2, x2p = pos(lk.m2)
        g = K * (x1 - x2) + B * ((x1 - x2) - (x1p - x2p)) / T
        force[lk.m1] = force[lk.m1] - g
        force[lk.m2] = force[lk.m2] + g

    for m in scene.masses:
        if m.kind != "mass":
            continue
        i, ip = slot[m.name]
        A[i] = 2.0 * unit(i) - unit(ip) + (T * T / m.mass) * force[m.name]
        A[ip] = unit(i)

    if port is not None:
        fport = force[port.name]
        if d == 0:
            u = fport
        else:
            u = unit(delay0 + d - 1)
            A[delay0] = fport
            for j in range(1, d):
                A[delay0 + j] = unit(delay0 + j - 1)
        mass, b0 = float(dev.mass), float(dev.friction)
        if dev.hold == "zoh":
            Ad, Bd = zoh_state_space(mass, b0, T)
            A[0] = Ad[0, 0] * unit(0) + Ad[0, 1] * unit(1) + Bd[0] * u
            A[1] = Ad[1, 0] * unit(0) + Ad[1, 1] * unit(1) + Bd[1] * u
            A[2] = unit(0)
        else:
            x = b0 * T / mass
            a = math.exp(-x)
            c = x / -math.expm1(-x) if x > 0 else 1.0
            A[0] = (1.0 + a) * unit(0) - a * unit(1) + (T * T / (mass * c)) * u
            A[1] = unit(0)
    return A, names


def check_scene(scene, *, calibrated=None) -> SceneCheck:
    """Closed-loop stability and rendered (k, b) of a whole scene felt through its device.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A validated scene (:func:`hapsim.scene.load_scene`).
    calibrated : mapping of str to (float, float), optional
        ``{link name: (K [N/m], B [N s/m])}`` for ``target`` links (see
        :func:`hapsim.analysis.loop.calibrate`) or any override.

    Returns
    -------
    SceneCheck
        Eigenvalues of :func:`scene_state_matrix`, spectral radius, verdict, the rendered
        pair at the port (least damped complex pair, ``k = m |s|^2``, ``b = -2 m Re s`` with
        ``m`` the device mass, DESIGN.md Sec. 4) and every mode.

    Raises
    ------
    ConfigError
        "calibrate first" for ``target`` links without calibrated values; see
        :func:`scene_state_matrix`.

    Notes
    -----
    For a port tied to a ground by one spring_damper (K, B) the eigenvalues are those of
    :func:`hapsim.analysis.loop.closed_loop_poles` ``(loop, K, B)`` up to roots at 0, and
    ``rendered`` equals the pair of :func:`hapsim.analysis.loop.render`.
    """
    A, names = scene_state_matrix(scene, calibrated=calibrated)
    cal = {k: (float(v[0]), float(v[1])) for k, v in dict(calibrated or {}).items()}
    has_port = scene.port is not None
    if has_port:
        ref = float(scene.device.mass)
    else:
        ref = float(sum(m.mass for m in scene.masses if m.kind == "mass")) or 1.0
    if A.shape[0] == 0:
        return SceneCheck(eigenvalues=np.zeros(0, complex), spectral_radius=0.0, stable=True,
                          rendered=None, modes=[], state_names=names, reference_mass=ref,
                          marginal=False, has_port=has_port, period=scene.period,
                          calibrated=cal)
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
    modes = modes_from_poles(ev_r, ref, scene.period)
    rendered = rendered_pair(modes) if has_port else None
    return SceneCheck(eigenvalues=ev, spectral_radius=radius, stable=stable,
                      rendered=rendered, modes=modes, state_names=names, reference_mass=ref,
                      marginal=marginal, has_port=has_port, period=scene.period,
                      calibrated=cal)
