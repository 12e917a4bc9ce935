"""The closed-loop state matrix of a scene coupled to its device, for every integrator.

This is the one place that assembles it (DESIGN.md Sec. 4, last bullet): the whole sampled
THS (device plant, force delay line, every virtual mass integrated by the scene's
``integrator``, linearised links) is one linear recursion ``s[n+1] = A s[n]``; its
eigenvalues are the closed-loop poles of the scene as the hand feels it.
:func:`hapsim.analysis.scene_check.scene_state_matrix`, :func:`hapsim.analysis.check_scene`
and :mod:`hapsim.bench.methods` all use :func:`closed_loop`.

State at sample ``n`` (:func:`closed_loop` returns the names):

=============================  =====================================================
``"zoh"`` hold                 ``x_dev[n]``, ``v_dev[n]`` (exact ZOH of
                               ``m x'' + b0 x' = f``), ``x_port[n-1]``
``"ideal"`` hold               ``x_dev[n]``, ``x_dev[n-1]`` (the paper's ideal sampled
                               image of the mass, Florens et al. eq. (4))
force delay line (d states)    ``F[n-1], ..., F[n-d]`` (forces computed, not yet applied)
virtual masses (N moving)      ``x[n]`` of all N, then ``x[n-1]`` of all N (``centred``)
                               or ``v[n]`` of all N (``symplectic_euler``, ``exact``)
=============================  =====================================================

Grounds are constants: they enter the link forces as a constant input that drops out of
the linear dynamics (deviations from equilibrium), so they contribute no state.

Timing. At sample ``n`` the port position is the device sample, ``x_port[n] = x_dev[n]``;
the virtual network advances one step of its integrator (:func:`virtual_blocks`) with the
port as an input, and computes the force on the port, ``F[n]``, from the positions (and,
for the velocity-state schemes, velocities) at ``n`` and the port at ``n`` and ``n - 1``.
``F[n]`` is applied by the device over the period starting at sample ``n + d``: the force
held over ``[nT, (n+1)T)`` is ``u[n] = F[n-d]``. The device then advances
``[x, v][n+1] = Ad [x, v][n] + Bd u[n]`` (``"zoh"``) or
``x[n+1] = (1+a) x[n] - a x[n-1] + T^2 u[n] / (m c)`` with ``a = e^(-b0T/m)``,
``c = (b0T/m) / (1 - a)`` (``"ideal"``, Florens et al. eq. (4); ``a = c = 1`` without
friction). For a port tied to a ground by a spring_damper this gives exactly
``z^(d+1) D(z) + N(z) (K z + (B/T)(z - 1)) = 0``, i.e. the poles of
:func:`hapsim.analysis.loop.closed_loop_poles` (up to roots at ``z = 0``), whatever the
integrator (no virtual mass is integrated).

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

Linearisation: contacts are taken *engaged* (they act as spring_dampers), the stiffest
case the scene can reach; links given as a felt ``target`` need their calibrated (K, B).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapsim.analysis.loop import zoh_state_space
from hapsim.errors import ConfigError
from hapsim.scene import INTEGRATORS

__all__ = ["INTEGRATORS", "Network", "check_integrator", "link_values", "network",
           "device_body", "plant_rows",
           "virtual_blocks", "virtual_state_names", "closed_loop"]


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
    from hapsim.kernels.schemes import laplacians

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
        from hapsim.kernels.schemes import exact_matrices

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


def closed_loop(scene, integrator: str | None = None, *, calibrated=None,
                gain: float = 1.0, member=None) -> tuple[np.ndarray, list[str]]:
    """Closed-loop state matrix of a scene, integrated by ``integrator``, felt through its device.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene (contacts engaged). With a port it needs its ``device`` (mass,
        friction, delay, hold); without one, only the virtual network is modelled (the
        engine's update matrix, port and grounds still).
    integrator : {"centred", "symplectic_euler", "exact"}, optional
        Scheme of the virtual masses; ``scene.integrator`` when None.
    calibrated : mapping of str to (float, float), optional
        ``{link name: (K [N/m], B [N s/m])}`` overrides (required for ``target`` links).
    gain : float, optional
        Every link's (K, B) multiplied by this (a gain-margin probe).
    member : array_like, shape (4,), optional
        Hand member ``(mh, bh, kg, bg)`` (:mod:`hapsim.analysis.hand`); default the nominal
        member of ``device.hand``. A compliant grip adds the hand's position and velocity
        after the device velocity (states ``[xh, vh, xm, vm]``).

    Returns
    -------
    A : ndarray, shape (n, n)
        ``s[n+1] = A s[n]``, ``n = (3 | 2) + d + 2N`` (``+ 2`` for a compliant grip) with a port (``"zoh"`` | ``"ideal"``
        hold, ``d`` samples of delay, N moving masses), ``2N`` without. Layout and timing:
        module docstring.
    state_names : list of str, length n
        What each state is.

    Raises
    ------
    ConfigError
        Unknown integrator or hold, a ``target`` link without calibrated (K, B)
        ("calibrate first"), a calibrated value not finite or naming no link, a port
        without a device section.
    """
    integrator = integrator or getattr(scene, "integrator", None) or "centred"
    check_integrator(integrator, scene)
    net = network(scene, calibrated, gain=gain)
    T = scene.period
    Av, bp, bpp, cx, cp, cpp = virtual_blocks(net, integrator, T)
    vnames = virtual_state_names(net, integrator)
    if net.port < 0:
        return Av, vnames
    port = scene.port.name
    dev = scene.device
    if dev is None:
        raise ConfigError("a scene with a port needs a device section", file=scene.path,
                          key="device")
    if getattr(dev, "correction", None) is not None:
        raise ConfigError("a device correction is analysed on the one-link loop "
                          "(hapsim compare-corrections, LoopModel(correction=...)), not in "
                          "the scene state matrix", file=scene.path, key="device.correction")
    A, u, nplant, names = _frame(scene, dev, port, Av, bp, bpp, cx, cp, cpp, vnames, member)
    pr = plant_rows(dev, T, member)
    if pr is None:                       # ideal hold
        mass, b0 = device_body(dev, member)
        x = b0 * T / mass
        a = math.exp(-x)
        c = x / -math.expm1(-x) if x > 0 else 1.0
        A[0, 0], A[0, 1] = 1.0 + a, -a
        A[0] += T * T / (mass * c) * u
    else:
        Ad, Bd = pr
        A[:nplant, :nplant] = Ad
        A[:nplant] += np.outer(Bd, u)
    return A, names


def device_body(dev, member=None) -> tuple[float, float]:
    """Total moving mass [kg] and friction [N s/m] of a device (handle + hand).

    Parameters
    ----------
    dev : hapsim.scene.Device
    member : array_like, shape (4,), optional
        Hand member ``(mh, bh, kg, bg)``; default the nominal member of ``dev.hand``.

    Returns
    -------
    (float, float)
        ``(m + mh, b0 + bh)`` (``(m, b0)`` without a hand): the mass the felt
        ``k = m |s|^2``, ``b = -2 m Re s`` are expressed with.
    """
    from hapsim.analysis.hand import nominal_member

    m, b0 = float(dev.mass), float(dev.friction)
    hand = getattr(dev, "hand", None)
    if member is None and hand is None:
        return m, b0
    mh, bh = (member if member is not None else nominal_member(hand))[:2]
    return m + float(mh), b0 + float(bh)


def _compliant(dev, member) -> bool:
    hand = getattr(dev, "hand", None)
    if member is not None:
        return math.isfinite(float(member[2]))
    return hand is not None and not hand.rigid


def plant_rows(dev, T: float, member=None):
    """ZOH of the device plant: ``(Ad, Bd)``, position first; None for the ideal hold.

    Parameters
    ----------
    dev : hapsim.scene.Device
    T : float
        Period [s].
    member : array_like, shape (4,), optional
        Hand member (default: nominal of ``dev.hand``).

    Returns
    -------
    (ndarray (p, p), ndarray (p,)) or None
        ``p = 2`` (``[x, v]``, rigid body, :func:`hapsim.analysis.loop.zoh_state_space`)
        or ``p = 4`` (``[xh, vh, xm, vm]``, compliant grip,
        :func:`hapsim.analysis.hand.hand_zoh`).
    """
    from hapsim.analysis.hand import hand_zoh, nominal_member

    if dev.hold != "zoh":
        return None
    if _compliant(dev, member):
        mem = np.asarray(member if member is not None else nominal_member(dev.hand), float)
        Aw, Bd = hand_zoh(float(dev.mass), float(dev.friction), mem, T)
        return Aw + np.eye(4), Bd
    return zoh_state_space(*device_body(dev, member), T)


def _frame(scene, dev, port, Av, bp, bpp, cx, cp, cpp, vnames, member=None):
    """Closed-loop matrix without the plant rows: ``(A, u, nplant, names)``.

    ``u`` is the row giving the force held over the coming period from the state; the
    plant rows ``0 .. nplant-1`` are left zero (except the ideal hold's shift row) for the
    caller (:func:`closed_loop`, or a family stacking many plants).
    """
    T = scene.period
    if dev.hold == "zoh":
        if _compliant(dev, member):
            names = [f"{port}.x[n] (handle position)", "device.v[n]", "hand.x[n]",
                     "hand.v[n]"]
        else:
            names = [f"{port}.x[n] (device position)", "device.v[n]"]
        names.append(f"{port}.x[n-1]")
    elif dev.hold == "ideal":
        names = [f"{port}.x[n] (device position)", f"{port}.x[n-1]"]
    else:
        raise ConfigError(f"unknown hold {dev.hold!r}; valid: zoh, ideal",
                          file=scene.path, key="device.hold")
    d = int(dev.delay)
    nd = len(names)
    nplant = nd - 1
    names += [f"F[n-{i}] (port force, delay line)" for i in range(1, d + 1)]
    names += vnames
    n = len(names)
    A = np.zeros((n, n))
    ip, ipp = 0, nd - 1        # port position at n and n - 1
    o = nd + d                 # first virtual state
    # port force row F[n]
    Frow = np.zeros(n)
    Frow[o:] = cx
    Frow[ip] += cp
    Frow[ipp] += cpp
    if d == 0:
        u = Frow
    else:
        u = np.zeros(n)
        u[nd + d - 1] = 1.0
        A[nd] = Frow
        for j in range(1, d):
            A[nd + j, nd + j - 1] = 1.0
    A[ipp, 0] = 1.0
    A[o:, o:] = Av
    A[o:, ip] += bp
    A[o:, ipp] += bpp
    return A, u, nplant, names
