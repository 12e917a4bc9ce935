"""The closed loops of a hand family's members, stacked: the members
(:func:`family_members`), their closed-loop state matrices (:func:`family_matrices`: the
whole scene's matrix of :func:`hapsim.analysis.network.closed_loop`, differing only in its
plant rows) and their poles (:func:`family_poles`, one batched eigenvalue call).

Below both the sampled verdict (:mod:`hapsim.analysis.family`) and the certified one
(:mod:`hapsim.analysis.robust`), which build on these matrices.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.hand import (HAND_FIELDS, body_zoh, hand_stiffness, ideal_rows,
                                  members as hand_members)
from hapsim.analysis.loop import zoh_state_space
from hapsim.errors import ConfigError

__all__ = ["family_members", "full_members", "family_matrices", "family_poles",
           "require_port_scene"]


def family_members(scene, samples: int | None = None, *, grid: int = 9,
                   seed: int = 0) -> np.ndarray:
    """The members of a scene's hand family (one row, the rigid no-hand body, without one).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        With a port and a device.
    samples, grid, seed
        As :func:`hapsim.analysis.hand.members`.

    Returns
    -------
    ndarray, shape (n, 5)
        ``(mh, bh, kg, bg, kh)`` per member; without a hand, ``[[0, 0, inf, 0, 0]]``.
    """
    hand = getattr(scene.device, "hand", None)
    if hand is None:
        return np.array([[0.0, 0.0, math.inf, 0.0, 0.0]])
    return hand_members(hand, samples, grid=grid, seed=seed)



def full_members(mem) -> np.ndarray:
    """Members as rows of every :data:`~hapsim.analysis.hand.HAND_FIELDS` (a 4-column
    member has ``kh = 0``).

    Parameters
    ----------
    mem : array_like, shape (n, 4) or (n, 5), or (4,) / (5,)
        ``(mh, bh, kg, bg[, kh])`` per member.

    Returns
    -------
    ndarray, shape (n, 5)
    """
    mem = np.atleast_2d(np.asarray(mem, float))
    if mem.shape[1] < len(HAND_FIELDS):
        mem = np.concatenate([mem, np.zeros((mem.shape[0], len(HAND_FIELDS) - mem.shape[1]))],
                             axis=1)
    return mem



#: Why a family refuses a scene with an audio section (:func:`require_port_scene`).
FAMILY_AUDIO = ("a family of a scene with an audio section (the virtual network sub-stepped "
                "at audio.rate_hz) is not modelled; 'hapsim check' predicts this scene, or "
                "give the family a scene without audio")


def require_port_scene(scene, needs: str = "a family needs", audio: str = FAMILY_AUDIO) -> None:
    """Refuse a scene whose loop matrices at the device period cannot be built: the hand
    family's here, :func:`hapsim.bench.advise.advise`'s rate ladder.

    Parameters
    ----------
    scene : hapsim.scene.Scene
    needs : str, optional
        Who needs the port and device, the message's start (``"advise needs"``).
    audio : str, optional
        The message refusing an ``audio`` section (default: the family's).

    Raises
    ------
    ConfigError
        No port or no device section (key ``masses`` / ``device``), or an ``audio``
        section: the matrices step the virtual network at the device period only, while
        a multi-rate scene's loop is the product of its audio sub-steps
        (:mod:`hapsim.analysis.network`, multi-rate), so a family of it would judge
        another loop.
    """
    if scene.port is None or scene.device is None:
        first = getattr(scene.masses[0], "line", 0) if scene.masses else 0
        raise ConfigError(f"{needs} a scene with a port (a mass of kind 'port') and a "
                          "device section", file=scene.path,
                          line=None if scene.port else (first or None),
                          key="device" if scene.port else "masses")
    if getattr(scene, "audio", None) is not None:
        raise ConfigError(audio, file=scene.path, key="audio")


def family_matrices(scene, mem: np.ndarray, *, calibrated=None, integrator=None):
    """Closed-loop state matrices of a scene for every member of its hand family.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene with a port and a device (a device correction adds its state,
        :func:`hapsim.analysis.corrections.corrected_frame`).
    mem : ndarray, shape (n, 4)
        Members ``(mh, bh, kg, bg)``; the grip is rigid (``kg = inf``) for all or none.
    calibrated : mapping, optional
        ``{link: (K, B)}`` overrides (target links).
    integrator : str, optional
        Scheme of the virtual masses (default the scene's).

    Returns
    -------
    A : ndarray, shape (n, s, s)
        ``A[i]`` equals :func:`hapsim.analysis.network.closed_loop` ``(scene,
        member=mem[i])`` (same layout), built from one frame and the stacked plants.
    names : list of str
        State names.

    Raises
    ------
    ConfigError
        A scene without a port or device, rigid and compliant members mixed.
    """
    from hapsim.analysis.network import closed_loop_frame
    from hapsim.analysis.virtual_network import (check_integrator, network, virtual_blocks,
                                                 virtual_state_names)

    require_port_scene(scene)
    dev = scene.device
    mem = np.atleast_2d(np.asarray(mem, float))
    finite = np.isfinite(mem[:, 2])
    if finite.any() and not finite.all():
        raise ConfigError("members mix rigid and compliant grips", key="device.hand")
    integrator = integrator or getattr(scene, "integrator", None) or "centred"
    check_integrator(integrator, scene)
    net = network(scene, calibrated)
    T = scene.period
    blocks = virtual_blocks(net, integrator, T)
    corr = getattr(dev, "correction", None)
    if corr is not None and corr.get("kind") == "inertia_compensation" and not (
            float(corr.get("mass", 0.0)) < float(dev.mass) + mem[:, 0].min()):
        raise ConfigError(f"compensated mass {corr.get('mass')} kg must stay below the "
                          f"moving mass of every member (least {float(dev.mass) + mem[:, 0].min():g}"
                          " kg)", file=scene.path, key="device.correction.mass")
    A0, u, nplant, names = closed_loop_frame(scene, dev, scene.port.name, *blocks,
                                             virtual_state_names(net, integrator), mem[0],
                                             correction=corr)
    n = mem.shape[0]
    A = np.repeat(A0[None], n, axis=0)
    m, b0 = float(dev.mass), float(dev.friction)
    kh = hand_stiffness(mem)
    f = float(dev.delay) % 1.0
    if f > 0:                     # the split hold (hapsim.analysis.subsample), stacked
        Aw, _ = body_zoh(m, b0, mem, T)
        W0, G0 = body_zoh(m, b0, mem, (1.0 - f) * T)
        _, Gf = body_zoh(m, b0, mem, f * T)
        G1 = Gf + np.matmul(W0, Gf[..., None])[..., 0]
        A[:, :nplant, :nplant] = Aw + np.eye(Aw.shape[-1])
        A[:, :nplant, :] += G0[:, :, None] * u[None, None, :]
        A[:, :nplant, -1] += G1
        return A, names
    if finite.all() or (dev.hold == "zoh" and np.any(kh > 0)):
        Aw, Bd = body_zoh(m, b0, mem, T)
        Ad = Aw + np.eye(Aw.shape[-1])
    elif dev.hold == "zoh":
        Ad = np.empty((n, 2, 2))
        Bd = np.empty((n, 2))
        for i in range(n):
            Ad[i], Bd[i] = zoh_state_space(m + mem[i, 0], b0 + mem[i, 1], T)
    else:
        mass = m + mem[:, 0]
        x = (b0 + mem[:, 1]) * T / mass
        a = np.exp(-x)
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.where(x > 0, x / -np.expm1(-x), 1.0)
        tr, det, g = 1.0 + a, a, T * T / (mass * c)
        if np.any(kh > 0):            # the arm's real spring: impulse-invariant image
            tr, det, g = ideal_rows(mass, b0 + mem[:, 1], kh, T)
        A[:, 0, 0] = tr
        A[:, 0, 1] = -det
        A[:, 0, :] += g[:, None] * u[None, :]
        return A, names
    A[:, :nplant, :nplant] = Ad
    A[:, :nplant, :] += Bd[:, :, None] * u[None, None, :]
    return A, names



def family_poles(scene, mem: np.ndarray, *, calibrated=None) -> np.ndarray:
    """Closed-loop poles of every member, shape (n, s).

    Eigenvalues of :func:`family_matrices` (one batched ``numpy.linalg.eigvals`` call),
    with or without a device correction, for any scene with a port.

    Parameters
    ----------
    scene : hapsim.scene.Scene
    mem : ndarray, shape (n, 4)
    calibrated : mapping, optional
        ``{link: (K, B)}``.

    Returns
    -------
    ndarray of complex, shape (n, s)

    Raises
    ------
    ConfigError
        As :func:`family_matrices`.
    """
    A, _ = family_matrices(scene, mem, calibrated=calibrated)
    return np.linalg.eigvals(A)
