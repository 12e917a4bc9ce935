"""The closed-loop state matrix of a scene coupled to its device, for every integrator.

This is the one place that assembles it (docs/design.md, 'A whole scene'): the whole sampled
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
:func:`hapsim.analysis.loop_poles.closed_loop_poles` (up to roots at ``z = 0``), whatever the
integrator (no virtual mass is integrated).

The virtual network's one-step maps for each integrator, single- and multi-rate, are
:mod:`hapsim.analysis.virtual_network`'s.

Linearisation: contacts are taken *engaged* (they act as spring_dampers), the stiffest
case the scene can reach; links given as a felt ``target`` need their calibrated (K, B).
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.body import is_compliant, ideal_shift, body_stiffness, device_body
from hapsim.analysis.loop import MAX_PRODUCT, check_product, zoh_state_space
from hapsim.analysis.kept import Kept
from hapsim.errors import ConfigError
from hapsim.analysis.virtual_network import (check_integrator, link_values, multirate_blocks,
                                             network, virtual_blocks, virtual_state_names)
from hapsim.scene import INTEGRATORS

__all__ = ["INTEGRATORS", "device_body", "body_stiffness", "plant_rows", "split_plant_rows",
           "closed_loop", "force_input", "port_io", "MAX_STATES", "state_count", "check_size"]

#: Closed loops kept (the newest), per scene object, integrator and gain
#: (:func:`closed_loop`; the nominal hand and no calibration overrides).
_KEPT = Kept(32)

#: Largest closed-loop state the analysis builds: every eigenvalue (and, with a port, both
#: eigenvector sets) of a dense n-square matrix, O(n^3) time and 16 n^2 bytes per matrix:
#: about 20 s (one core, loaded machine) and 64 MB at 2000 states, a string of ~1000
#: beads; 3000 beads would take a minute, 10^5 masses 160 GB.
MAX_STATES = 2000


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
        What each state is. Both are the caller's own copies: with the nominal hand and
        no ``calibrated``, the loop is built once per scene object (frozen), integrator
        and gain, and the newest 32 are kept (:class:`hapsim.analysis.kept.Kept`).

    Raises
    ------
    ConfigError
        Unknown integrator or hold, a ``target`` link without calibrated (K, B)
        ("calibrate first"), a calibrated value not finite or naming no link, a port
        without a device section; more than :data:`MAX_STATES` states; a link or the
        device beyond :data:`hapsim.analysis.loop.MAX_PRODUCT`.
    """
    integrator = integrator or getattr(scene, "integrator", None) or "centred"
    if calibrated is not None or member is not None:
        return _closed_loop(scene, integrator, calibrated, gain, member)
    # a measurement asks for the same model's loop many times (its responses, poles and
    # search): kept per scene object (frozen), returned as a copy the caller may change
    A, names = _KEPT.get((id(scene), integrator, float(gain)),
                         lambda: _closed_loop(scene, integrator, None, gain, None),
                         owner=scene)
    return A.copy(), list(names)


def _closed_loop(scene, integrator, calibrated, gain, member):
    """:func:`closed_loop`'s matrix, built."""
    check_integrator(integrator, scene)
    check_size(scene)
    net = network(scene, calibrated, gain=gain)
    _check_products(scene, calibrated, gain)
    T = scene.period
    audio = getattr(scene, "audio", None)
    if audio is None:
        Av, bp, bpp, cx, cp, cpp = virtual_blocks(net, integrator, T)
    else:
        from hapsim.scene import audio_substeps

        nsub = audio_substeps(audio.rate_hz, scene.rate_hz)
        Av, bp, bpp, cx, cp, cpp = multirate_blocks(
            virtual_blocks(net, integrator, T / nsub), nsub, audio.port_position,
            audio.port_force)
    vnames = virtual_state_names(net, integrator)
    if net.port < 0:
        return Av, vnames
    port = scene.port.name
    dev = scene.device
    if dev is None:
        raise ConfigError("a scene with a port needs a device section", file=scene.path,
                          key="device")
    A, u, nplant, names = closed_loop_frame(scene, dev, port, Av, bp, bpp, cx, cp, cpp,
                                            vnames, member,
                                            correction=getattr(dev, "correction", None))
    pr = plant_rows(dev, T, member)
    if pr is None:                       # ideal hold
        tr, det, g = ideal_shift(dev, T, member)
        A[0, 0], A[0, 1] = tr, -det
        A[0] += g * u
    elif float(dev.delay) % 1.0:         # the split hold: Gamma0 u + Gamma1 F held
        Ad, G0, G1 = split_plant_rows(dev, T, member)
        A[:nplant, :nplant] = Ad
        A[:nplant] += np.outer(G0, u)
        A[:nplant, -1] += G1
    else:
        Ad, Bd = pr
        A[:nplant, :nplant] = Ad
        A[:nplant] += np.outer(Bd, u)
    return A, names


def force_input(scene, member=None) -> np.ndarray:
    """The column through which a force added to the one the device holds enters the
    closed loop of :func:`closed_loop`: ``s[n+1] = A s[n] + b w[n]`` for a force ``w[n]``
    [N] held over ``[nT, (n+1)T)`` on top of ``u[n] = F[n-d]`` (a late tick's known
    disturbance, :mod:`hapsim.applied`).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene with a port and a device.
    member : array_like, shape (4,), optional
        Hand member (default: nominal of ``device.hand``).

    Returns
    -------
    ndarray, shape (n,)
        ``b``: the plant's ``Bd`` in its rows (``"zoh"``), ``T^2 / (m c)`` in the first
        row (``"ideal"``, Florens et al. eq. (4)), 0 elsewhere (module notes: the force
        enters the plant only); a fractional delay: ``Gamma0`` in the plant's rows and 1
        in the held force's state (:func:`split_plant_rows`).

    Raises
    ------
    ConfigError
        As :func:`closed_loop`.
    """
    A, _ = closed_loop(scene, member=member)
    b = np.zeros(A.shape[0])
    dev = scene.device
    pr = plant_rows(dev, scene.period, member)
    if pr is None:
        b[0] = ideal_shift(dev, scene.period, member)[2]
    elif float(dev.delay) % 1.0:
        # the split hold: the force applied enters through Gamma0 over the period's last
        # (1 - f) T and is the one held over the next period's first f T (the last state)
        _, G0, _ = split_plant_rows(dev, scene.period, member)
        b[:G0.size] = G0
        b[-1] = 1.0
    else:
        Bd = np.asarray(pr[1], float)
        b[:Bd.size] = Bd
    return b


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
        ``p = 2`` (``[x, v]``, rigid body, :func:`hapsim.analysis.loop.zoh_state_space`;
        with the hand's stiffness :func:`hapsim.analysis.hand.body_zoh`) or ``p = 4``
        (``[xh, vh, xm, vm]``, compliant grip, :func:`hapsim.analysis.hand.hand_zoh`).
    """
    from hapsim.analysis.hand import body_zoh, nominal_member

    if dev.hold != "zoh":
        return None
    if is_compliant(dev, member) or body_stiffness(dev, member) > 0:
        mem = np.asarray(member if member is not None else nominal_member(dev.hand), float)
        Aw, Bd = body_zoh(float(dev.mass), float(dev.friction), mem, T)
        return Aw + np.eye(Aw.shape[-1]), Bd
    return zoh_state_space(*device_body(dev, member), T)


def split_plant_rows(dev, T: float, member=None):
    """Split hold of the device plant for its delay ``m + f``: ``(Ad, Gamma0, Gamma1)``.

    Parameters
    ----------
    dev : hapsim.scene.Device
        ``hold: zoh`` (a fractional delay needs it).
    T : float
        Period [s].
    member : array_like, shape (4,), optional
        Hand member (default: nominal of ``dev.hand``).

    Returns
    -------
    Ad : ndarray, shape (p, p)
        As :func:`plant_rows`.
    Gamma0, Gamma1 : ndarray, shape (p,)
        Response to the force held over the period's last ``(1 - f) T`` and first ``f T``
        (:func:`hapsim.analysis.subsample.split_hold`; ``f = 0``: ``Bd`` and zeros).

    Notes
    -----
    Modified z-transform (Franklin, Powell & Workman ch. 4, sec. 4.3; Astrom & Wittenmark
    sec. 2.3): ``Gamma0 = int_0^((1-f)T) e^(As) ds b``,
    ``Gamma1 = e^(A(1-f)T) int_0^(fT) e^(As) ds b``.
    """
    from hapsim.analysis.hand import body_zoh, nominal_member
    from hapsim.analysis.subsample import split_delay, split_hold_body

    _, f = split_delay(dev.delay, "device.delay")
    if is_compliant(dev, member) or body_stiffness(dev, member) > 0:
        mem = np.asarray(member if member is not None else nominal_member(dev.hand), float)
        m, b0 = float(dev.mass), float(dev.friction)
        Aw, _ = body_zoh(m, b0, mem, T)
        W0, G0 = body_zoh(m, b0, mem, (1.0 - f) * T)
        if f == 0.0:
            return Aw + np.eye(Aw.shape[-1]), G0, np.zeros_like(G0)
        _, Gf = body_zoh(m, b0, mem, f * T)
        return Aw + np.eye(Aw.shape[-1]), G0, Gf + W0 @ Gf
    return split_hold_body(*device_body(dev, member), T, f)


def closed_loop_frame(scene, dev, port, Av, bp, bpp, cx, cp, cpp, vnames, member=None,
                      correction=None):
    """Closed-loop matrix without the plant rows: ``(A, u, nplant, names)``.

    ``u`` is the row giving the force held over the coming period from the state; the
    plant rows ``0 .. nplant-1`` are left zero (except the ideal hold's shift row) for the
    caller (:func:`closed_loop`, or a family stacking many plants). A device
    ``correction`` (mapping or :class:`hapsim.analysis.corrections.Correction`) acts at the
    port and adds at most one state after the virtual ones
    (:func:`hapsim.analysis.corrections.corrected_frame`).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene (its period ``T`` [s] and path).
    dev : hapsim.scene.Device
        Its device (hold, delay [periods], mass [kg] and friction [N s/m]).
    port : str
        Port name (state names).
    Av, bp, bpp, cx, cp, cpp
        Blocks of :func:`hapsim.analysis.virtual_network.virtual_blocks`, shapes (2N, 2N),
        (2N,), (2N,), (2N,), float, float.
    vnames : list of str
        Names of the 2N virtual states.
    member : array_like, optional
        Hand member ``(mh, bh, kg, bg[, kh])``; None: the device's nominal hand.
    correction : dict or Correction, optional
        The device's correction; None: none.

    Returns
    -------
    A : ndarray, shape (n, n)
        Closed-loop matrix, plant rows left zero.
    u : ndarray, shape (n,)
        Row giving the force held over the coming period.
    nplant : int
        Plant states (2 or 4 for ``"zoh"``, 1 for ``"ideal"``).
    names : list of str
        The n state names.

    Raises
    ------
    ConfigError
        A bad ``correction`` mapping (:meth:`Correction.from_dict`), or as
        :func:`~hapsim.analysis.corrections.corrected_frame`.
    """
    from hapsim.analysis.corrections import Correction, corrected_frame

    corr = Correction.from_dict(correction) if correction is not None else None
    return corrected_frame(scene, dev, port, Av, bp, bpp, cx, cp, cpp, vnames, member, corr)


def port_io(scene, n: int):
    """Input and output columns of the port in the :func:`closed_loop` state.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene with a port and a device.
    n : int
        Size of the closed-loop state.

    Returns
    -------
    b : ndarray, shape (n,)
        Response of the state to a unit force [N] on the device held over one period (the
        hand's force: it enters like the device force, without the delay line): ``Bd`` of
        :func:`hapsim.analysis.loop.zoh_state_space` (``"zoh"``) or ``T^2 / (m c)``
        (``"ideal"``, Florens et al. eq. (4)) [m/N, m/(N s)].
    c : ndarray, shape (n,)
        Selects the port (device) position, state 0 [-].

    Notes
    -----
    ``c (zI - A)^-1 b`` is the transfer from a force on the handle to the port position,
    the impedance the hand feels; its residue at a pole weighs that mode at the port.
    """
    dev = scene.device
    T = scene.period
    b = np.zeros(n)
    if dev.hold == "zoh":
        _, Bd = plant_rows(dev, T)          # handle + hand when the device has a hand
        b[:Bd.size] = Bd
    else:
        b[0] = ideal_shift(dev, T)[2]
    c = np.zeros(n)
    c[0] = 1.0
    return b, c


def state_count(scene) -> int:
    """Size of the :func:`closed_loop` state, computed without building anything.

    Parameters
    ----------
    scene : hapsim.scene.Scene

    Returns
    -------
    int
        ``2 N`` (N moving masses) plus, with a port and a device, ``3 + d`` (``"zoh"``) or
        ``2 + d`` (``"ideal"``); a fractional ``d`` counts ``ceil(d)`` (the split hold's
        held force is one more state).
    """
    n = 2 * sum(1 for m in scene.masses if m.kind == "mass")
    dev = getattr(scene, "device", None)
    if scene.port is not None and dev is not None:
        n += (3 if dev.hold == "zoh" else 2) + math.ceil(float(dev.delay))
        if is_compliant(dev, None):
            n += 2                          # the hand's position and velocity
    return n


def check_size(scene) -> None:
    """Refuse, before any allocation, a scene whose closed loop exceeds :data:`MAX_STATES`.

    Parameters
    ----------
    scene : hapsim.scene.Scene

    Raises
    ------
    ConfigError
        Naming ``masses`` (or ``device.delay``), the state count, the limit and the cost.
    """
    n = state_count(scene)
    if n > MAX_STATES:
        n_mass = sum(1 for m in scene.masses if m.kind == "mass")
        raise ConfigError(f"the closed loop has {n} states ({n_mass} moving masses x 2"
                          + (f" + device and {scene.device.delay} delay samples"
                             if scene.port is not None and scene.device is not None else "")
                          + f"); the analysis takes every eigenvalue of a dense {n}-square "
                          f"matrix, O(n^3): at most {MAX_STATES} states (~20 s), about "
                          f"{MAX_STATES // 2} moving masses", file=scene.path, key="masses")


def _check_products(scene, calibrated, gain: float) -> None:
    """Refuse a link or device friction whose dimensionless product exceeds MAX_PRODUCT.

    ``|K| T^2 / m`` and ``|B| T / m`` with ``m`` the lightest moving end of the link (a
    virtual mass, or the device mass at the port; grounds do not move), ``b0 T / m``
    of the device and ``kh T^2 / mh`` of the hand's stiffness (largest stiffness, lightest
    hand of a range) (:data:`hapsim.analysis.loop.MAX_PRODUCT`, and its reason there).
    """
    T = scene.period
    inertia = {m.name: m.mass for m in scene.masses if m.kind == "mass"}
    dev = getattr(scene, "device", None)
    if scene.port is not None and dev is not None:
        inertia[scene.port.name] = float(dev.mass)
        try:
            check_product(float(dev.friction), T / float(dev.mass), "device.friction",
                          "N s/m", "b0 T/m")
        except ConfigError as exc:
            raise ConfigError(exc.reason, file=scene.path, key="device.friction") from None
        hand = getattr(dev, "hand", None)
        if hand is not None:       # the arm's spring acts on the hand (+ handle) mass
            from hapsim.analysis.hand import field_span
            kh, mh = field_span(hand.stiffness)[1], field_span(hand.mass)[0]
            try:
                check_product(kh, T * T / mh, "device.hand.stiffness", "N/m", "kh T^2/m")
            except ConfigError as exc:
                raise ConfigError(exc.reason, file=scene.path,
                                  key="device.hand.stiffness") from None
    for lk, K, B in link_values(scene, calibrated):
        ends = [inertia[n] for n in (lk.m1, lk.m2) if n in inertia]
        if not ends:
            continue
        m = min(ends)
        for val, scale, what, unit, field in ((K * gain, T * T / m, "K T^2/m", "N/m",
                                               "stiffness"),
                                              (B * gain, T / m, "B T/m", "N s/m", "damping")):
            if abs(val) * scale > MAX_PRODUCT:
                try:
                    check_product(val, scale, field, unit, what)
                except ConfigError as exc:
                    raise ConfigError(exc.reason, file=scene.path, line=lk.line or None,
                                      key=f"links.{lk.name}.{field}") from None
