"""The modes of a 2-D or 3-D scene on its own: the eigenfrequencies and damping ratios of
the centred scheme, linearised at rest, with the grounds and the port held still.

With the moving masses' positions ``x`` (n per mass) and the links linearised at rest
(:func:`hapsim.analysis.scene_nd_check.link_blocks`: exact for ``length: 0`` springs), the
forces are ``F = -K x - (B / T)(x - x_prev)`` and the scheme
``x[n+1] = 2 x[n] - x[n-1] + T^2 M^-1 F[n]`` is the one-step map

    [x[n+1]; x[n]] = [[2 I - T^2 M^-1 K - T M^-1 B, -(I - T M^-1 B)], [I, 0]] [x[n]; x[n-1]]

whose eigenvalues ``z`` give each mode's frequency ``arg(z) / (2 pi T)`` [Hz] and damping
ratio ``-ln|z| / |ln z|`` (the discrete poles read as ``s = ln(z) / T``). A square mesh of
masses ``m`` joined to their four neighbours by ``length: 0`` springs ``(K, B)``, its edge
held, has the closed form of the discrete membrane (the discrete Laplacian's eigenvalues
``mu_pq = 4 [sin^2(p pi / (2 (N + 1))) + sin^2(q pi / (2 (N + 1)))]``, each mode
``z^2 - (2 - a - c) z + (1 - c) = 0`` with ``a = mu K T^2 / m``, ``c = mu B T / m``):
``tests/test_membrane.py`` checks one against the other.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hapsim.analysis.scene_nd_check import MAX_STATES_ND, link_blocks
from hapsim.errors import ConfigError

__all__ = ["ModeND", "SceneModesND", "scene_modes_nd"]


@dataclass(frozen=True)
class ModeND:
    """One oscillating mode: ``frequency_hz`` [Hz], ``damping_ratio`` [-], the ``axis``
    its shape moves most along (0..n-1), its ``shape`` (moving masses x n, unit norm,
    real part at the largest entry's phase) and the discrete pole ``z``."""

    frequency_hz: float
    damping_ratio: float
    axis: int
    shape: np.ndarray
    z: complex

    def to_dict(self) -> dict:
        """``frequency_hz``, ``damping_ratio``, ``axis`` (JSON-ready)."""
        return {"frequency_hz": self.frequency_hz, "damping_ratio": self.damping_ratio,
                "axis": self.axis}


@dataclass(frozen=True)
class SceneModesND:
    """Every oscillating mode of a scene, lowest frequency first; ``names`` are the moving
    masses (the rows of each shape), ``spectral_radius`` the largest ``|z|`` (> 1:
    the scheme diverges) and ``states`` the size of the one-step map."""

    modes: tuple
    names: tuple
    spectral_radius: float
    states: int

    @property
    def stable(self) -> bool:
        """Spectral radius within 1e-9 of 1 or below (marginal counts as stable)."""
        return self.spectral_radius <= 1.0 + 1e-9


def scene_modes_nd(scene) -> SceneModesND:
    """The modes of an n-D scene's virtual masses (module docstring).

    Parameters
    ----------
    scene : hapsim.scene_nd.SceneND
        A validated scene (a port, if any, is held at rest like a ground).

    Returns
    -------
    SceneModesND

    Raises
    ------
    ConfigError
        No moving mass, more than :data:`MAX_STATES_ND` states, or a degenerate
        Euclidean link (:func:`link_blocks`).
    """
    n, T = scene.dimension, scene.period
    moving = [m for m in scene.masses if m.kind == "mass"]
    if not moving:
        raise ConfigError("the scene has no moving mass: it has no modes", file=scene.path,
                          key="masses")
    N = n * len(moving)
    if 2 * N > MAX_STATES_ND:
        raise ConfigError(f"{2 * N} states (2 x {len(moving)} masses x {n} axes) exceed "
                          f"the {MAX_STATES_ND} analysed densely", file=scene.path,
                          key="masses")
    at = {m.name: i for i, m in enumerate(moving)}
    K = np.zeros((N, N))
    B = np.zeros((N, N))
    for _, a, b, Kl, Bl in link_blocks(scene):
        ia, ib = at.get(a), at.get(b) if b is not None else None
        for M, blk in ((K, Kl), (B, Bl)):
            if ia is not None:
                M[n * ia:n * ia + n, n * ia:n * ia + n] += blk
            if ib is not None:
                M[n * ib:n * ib + n, n * ib:n * ib + n] += blk
            if ia is not None and ib is not None:
                M[n * ia:n * ia + n, n * ib:n * ib + n] -= blk
                M[n * ib:n * ib + n, n * ia:n * ia + n] -= blk
    minv = np.repeat([1.0 / m.mass for m in moving], n)
    # axes that no link couples (length-0 springs only) are analysed one at a time: the
    # same eigenvalues, a smaller problem, and each mode along one axis exactly
    cross = np.ones((n, n), bool) ^ np.eye(n, dtype=bool)
    mask = np.tile(cross, (len(moving), len(moving)))
    groups = [np.arange(a, N, n) for a in range(n)] \
        if not (np.any(K[mask]) or np.any(B[mask])) else [np.arange(N)]
    modes, radius = [], 0.0
    for g in groups:
        Kg, Bg, mg = K[np.ix_(g, g)], B[np.ix_(g, g)], minv[g][:, None]
        I = np.eye(g.size)
        A = np.block([[2 * I - T * T * mg * Kg - T * mg * Bg, -(I - T * mg * Bg)],
                      [I, np.zeros_like(I)]])
        z, V = np.linalg.eig(A)
        radius = max(radius, float(np.max(np.abs(z))))
        for j in np.flatnonzero(z.imag > 1e-12):
            s = np.log(z[j]) / T
            full = np.zeros(N, complex)
            full[g] = V[:g.size, j]
            v = full.reshape(len(moving), n)
            k = np.unravel_index(np.argmax(np.abs(v)), v.shape)
            v = (v * np.exp(-1j * np.angle(v[k]))).real
            v = v / np.linalg.norm(v)
            modes.append(ModeND(float(np.angle(z[j]) / (2 * np.pi * T)),
                                float(-s.real / abs(s)), int(np.argmax((v * v).sum(0))),
                                v, complex(z[j])))
    modes.sort(key=lambda md: (md.frequency_hz, md.axis))
    return SceneModesND(tuple(modes), tuple(m.name for m in moving), radius, 2 * N)
