"""``hapsim zwidth --scene SCENE --lockstep`` of a 2-D or 3-D scene: the device's Z-width
for an isotropic wall (a spring-damper of rest length 0 from the handle to a ground at its
rest: the same ``(K, B)`` on every axis, what a point contact renders), measured from
lockstep records (:class:`hapsim.lockstep.LockstepND`).

Each trial releases the handle from ``x0`` along a direction that is no principal axis
(every mode excited) on the device at its operating point (the exact zero-order hold of
its Cartesian mass and friction, as ``hapsim run --lockstep``'s default), runs
``duration`` and reads the record's growth: a vector autoregression of
the loop's order fitted to its last two thirds gives the poles, ``rho`` the largest
modulus (:func:`_dominant_modulus`), and ``b = -2 m ln(rho) / T`` with ``m`` the smallest principal mass
(the sign of ``b`` is the side of the limit; its value the search's secant). The search
(:func:`hapsim.analysis.zwidth.locate_onset`) raises ``K`` from below the prediction to a
growing record and refines the bracket from the records alone. The prediction is exact:
:func:`hapsim.analysis.direction_limits.isotropic_limit`.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["isotropic_wall", "lockstep_measure"]


def isotropic_wall(path, K: float, B: float):
    """The scene at ``path`` with its virtual world replaced by one isotropic wall.

    Parameters
    ----------
    path : str or path-like
        A 2-D or 3-D scene file with a device.
    K, B : float
        The wall's stiffness [N/m] and damping [N s/m].

    Returns
    -------
    hapsim.scene.SceneND
        Its dimension, rate and device; a port ``hand``, a ground ``wall`` at the device's
        rest position and the spring-damper between them.

    Raises
    ------
    ConfigError
        A scene without a device section (key ``device``); as the reader for the scene's
        device.
    """
    import yaml

    from hapsim.errors import ConfigError
    from hapsim.scene import load_scene_nd, parse_scene_nd
    base = load_scene_nd(path)
    if base.device is None:
        raise ConfigError("the scene has no device section: no Z-width to measure",
                          file=str(path), key="device")
    with open(path, encoding="utf-8") as fh:
        doc = yaml.safe_load(fh)
    new = {"dimension": doc["dimension"], "rate_hz": doc["rate_hz"], "device": doc["device"],
           "masses": [{"name": "hand", "kind": "port"},
                      {"name": "wall", "kind": "ground",
                       "x0": [float(v) for v in base.device.position]}],
           "links": [{"name": "wall", "kind": "spring_damper", "between": ["hand", "wall"],
                      "stiffness": float(K), "damping": float(B)}]}
    return parse_scene_nd(yaml.safe_dump(new), str(path))


def lockstep_measure(path, x0: float, duration: float):
    """A measuring function for :func:`hapsim.analysis.zwidth.locate_onset` (module
    notes).

    Parameters
    ----------
    path : str or path-like
        The 2-D or 3-D scene file.
    x0 : float
        Release distance [m].
    duration : float
        Record length [s].

    Returns
    -------
    callable
        ``measure(K, B) -> hapsim.analysis.zwidth.Trial``.
    """
    from hapsim.analysis.zwidth import Trial
    from hapsim.lockstep import LockstepND
    base = isotropic_wall(path, 1.0, 0.0)
    n, T = base.dimension, base.period
    m = float(np.linalg.eigvalsh(base.device.mass)[0])
    u = np.array([1.0, 0.7, 0.4])[:n]
    u = x0 * u / np.linalg.norm(u)
    # the device at its operating point (the exact ZOH of its Cartesian mass and
    # friction): a joint-space record is no linear loop's, and its autoregression gave
    # pole moduli over 1 on records that decayed (the pantograph at B = 0: 1.03 at 40 N/m,
    # a quarter of the limit), so the limit was not decided to its digits
    joint = False
    N = max(30, round(duration / T))
    W = N // 3
    # the loop's order: n (d + 3) states, a vector AR of d + 3 lags (a sub-sample delay's
    # held force one more)
    order = int(math.floor(float(base.device.delay))) + 3 + (float(base.device.delay) % 1 > 0)

    def measure(K: float, B: float) -> Trial:
        scene = isotropic_wall(path, K, B)
        rec = LockstepND(scene, x0=u, joint_space=joint).step(N, record=True)
        if not np.all(np.isfinite(rec)):
            return Trial(K, B, None, None, 0.0, None, True, note="the record overflowed")
        rho = _dominant_modulus(rec[W:], order)
        b = -2.0 * m * math.log(rho) / T if rho > 0 else math.inf
        return Trial(K, B, b, None, 0.0, rho, rho > 1.0,
                     note="lockstep")
    return measure


def _dominant_modulus(rec: np.ndarray, order: int) -> float:
    """The largest pole modulus of a record of a linear loop's free response: a vector
    autoregression of ``order`` lags (a free response of ``n order`` states obeys one
    exactly: Cayley-Hamilton on the state matrix, observed through ``n`` positions;
    :func:`hapsim.analysis.pencil.ar_poles`), scaled to the record's RMS first (a growing
    record's late samples are orders larger)."""
    from hapsim.analysis.pencil import ar_poles
    x = rec / max(float(np.sqrt(np.mean(rec * rec))), 1e-300)
    return float(np.max(np.abs(ar_poles(x, order))))
