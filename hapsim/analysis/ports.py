"""The THS of a scene with several ports, each felt through its own device: the ports
stacked as the axes of one n-D loop (issue 30 item 3).

A 1-D scene with P ports (:class:`hapsim.scene.ScenePorts`) is the n-D loop of
:mod:`hapsim.analysis.ths` with ``n = P`` axes, axis ``i`` the position of port ``i``
(docs/ports.md):

- **Real side.** Each port's device ``m_i x_i'' + b0_i x_i' = F_i``: the block-diagonal
  (here diagonal) mass ``M = diag(m_i)`` [kg] and friction ``B0 = diag(b0_i)`` [N s/m];
  their exact zero-order hold is :func:`hapsim.analysis.ths.zoh_matrices`, which for a
  diagonal ``M`` and ``B0`` is each device's own 1-D hold.
- **Virtual side.** Every link is a ``spring_damper`` between two ports or between a port
  and a ground (the scheme's law, docs/design.md 'The scheme'), so the force on the ports
  is ``F[n] = -K x[n] - B (x[n] - x[n-1]) / T`` with the P x P port stiffness ``K`` [N/m]
  and damping ``B`` [N s/m] assembled from the links as a network's stiffness matrix is
  (a link of ``(k, c)`` between ports ``i`` and ``j`` adds ``k`` at ``(i, i)`` and
  ``(j, j)`` and ``-k`` at ``(i, j)`` and ``(j, i)``; to a ground, ``k`` at ``(i, i)``).
- **Delay.** Port ``i``'s device applies the force computed from the positions ``d_i``
  samples before (:func:`hapsim.analysis.ths.state_matrix` with ``delays``), whole or
  sub-sample, each port its own (each axis its own split hold: the FireFader's fader B,
  read 150 us before fader A, is 0.7625 periods behind at 250 Hz where A is 0.725).

The felt matrices across ports, ``k`` and ``b`` (P x P), and the stability of the coupled
loop (its spectral radius) are :func:`hapsim.analysis.ths.render_state`'s (Lancaster's
inverse quadratic eigenvalue problem; Li, Tavakoli & Huang, IEEE TCST 2014: the coupled
loop's stability from its MIMO characteristic, never port by port). Two uncoupled ports
are each port's own 1-D felt pair on the diagonal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hapsim.analysis.scene_check import felt_summary
from hapsim.analysis.ths import MatrixLoop, MatrixRenderResult, render_state, state_matrix

__all__ = ["port_matrices", "port_loop", "ports_state_matrix", "PortsCheck", "check_ports",
           "stable_ports_check"]


def port_matrices(scene) -> tuple[np.ndarray, np.ndarray]:
    """The scene's port stiffness and damping matrices.

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
        A validated scene with several ports (links between ports and to grounds).

    Returns
    -------
    K : ndarray, shape (P, P)
        Port stiffness [N/m] (symmetric; ports in :attr:`ScenePorts.ports` order).
    B : ndarray, shape (P, P)
        Port damping [N s/m].

    Notes
    -----
    The assembly of a spring network's stiffness matrix (each link's element matrix
    ``k [[1, -1], [-1, 1]]`` added at its two ends, a ground's row and column dropped;
    e.g. Bathe, *Finite Element Procedures*, 1996, Sec. 4.2), of the link law
    ``F = K (x1 - x2) + B ((x1 - x2) - (x1p - x2p)) / T`` (docs/design.md, 'The scheme').
    """
    axis = {n: i for i, n in enumerate(scene.ports)}
    P = len(axis)
    K = np.zeros((P, P))
    B = np.zeros((P, P))
    for lk in scene.links:
        i, j = axis.get(lk.m1), axis.get(lk.m2)       # None: a ground
        for a, b, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
            if a is not None and b is not None:
                K[a, b] += sign * lk.stiffness
                B[a, b] += sign * lk.damping
    return K, B


def port_loop(scene) -> tuple[MatrixLoop, tuple | None]:
    """The n-D loop of the ports' devices, and the per-port delays when they differ.

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts

    Returns
    -------
    loop : hapsim.analysis.ths.MatrixLoop
        ``dof = P``, ``mass = diag(m_i)`` [kg], ``friction = diag(b0_i)`` [N s/m], the
        scene's rate, ``delay`` the ports' common delay (the largest when they differ).
    delays : tuple of int or float, or None
        Each port's delay [periods] when they differ (ints when all are whole), else
        None (the loop's one delay, sub-sample or not).
    """
    devs = [d for _, d in scene.devices]
    delays = [float(d.delay) for d in devs]
    same = len(set(delays)) == 1
    loop = MatrixLoop(mass=np.diag([float(d.mass) for d in devs]),
                      friction=np.diag([float(d.friction) for d in devs]),
                      rate_hz=scene.rate_hz, delay=devs[0].delay if same else max(delays))
    if same:
        return loop, None
    whole = all(x % 1 == 0 for x in delays)
    return loop, tuple(int(x) if whole else x for x in delays)


def ports_state_matrix(scene) -> np.ndarray:
    """The coupled loop's state matrix (:func:`hapsim.analysis.ths.state_matrix`).

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts

    Returns
    -------
    ndarray, shape (P (d + 3), P (d + 3)); ``P (m + 4)`` for a sub-sample delay
        ``m + f`` (the largest ``m``)
        ``s[n+1] = A s[n]``, the first P states the ports' positions [m], ``d`` the
        largest delay.
    """
    loop, delays = port_loop(scene)
    K, B = port_matrices(scene)
    return state_matrix(loop, K, B, delays=delays)


@dataclass(frozen=True)
class PortsCheck:
    """The check of a scene with several ports (:func:`check_ports`).

    Attributes
    ----------
    ports : tuple of str
        The ports, in axis order.
    render : hapsim.analysis.ths.MatrixRenderResult
        Felt stiffness ``k`` [N/m] and damping ``b`` [N s/m] across ports (P x P),
        principal directions, poles, spectral radius.
    port_stiffness, port_damping : ndarray, shape (P, P)
        The scene's ``K`` [N/m] and ``B`` [N s/m] (:func:`port_matrices`).
    delays : tuple of float
        Each port's delay [periods].
    states : int
        Size of the closed loop's state.
    """

    ports: tuple
    render: MatrixRenderResult
    port_stiffness: np.ndarray
    port_damping: np.ndarray
    delays: tuple
    states: int

    @property
    def stable(self) -> bool:
        """The coupled loop's verdict (spectral radius within the 1-D tolerance of 1)."""
        return self.render.stable

    def to_dict(self) -> dict:
        """JSON-ready dict: ``ports``, ``dof``, ``stable``, ``verdict`` (``stable`` or
        ``unstable``), ``spectral_radius``, ``felt_stiffness`` and ``felt_damping`` (P x P,
        rows and columns in ``ports`` order), ``principal_directions``, the per-direction
        pairs, ``port_stiffness``, ``port_damping``, ``delays``, ``states``,
        ``rendered_poles``, ``note``.

        Returns
        -------
        dict
            Those keys (:func:`hapsim.analysis.scene_check.felt_summary` for the verdict
            and the felt matrices); ``port_stiffness`` [N/m] and ``port_damping`` [N s/m]
            as P lists of P, ``delays`` as P floats [periods].
        """
        r = self.render.to_dict()
        return {"ports": list(self.ports), "dof": len(self.ports), **felt_summary(r),
                "port_stiffness": self.port_stiffness.tolist(),
                "port_damping": self.port_damping.tolist(),
                "delays": [float(d) for d in self.delays], "states": self.states,
                "rendered_poles": r["rendered_poles"], "note": r["note"]}


def check_ports(scene) -> PortsCheck:
    """Felt matrices across ports and the coupled loop's stability.

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
        A validated scene with several ports.

    Returns
    -------
    PortsCheck
        From the eigenvalues and eigenvectors of :func:`ports_state_matrix`
        (:func:`hapsim.analysis.ths.render_state`).
    """
    loop, _ = port_loop(scene)
    K, B = port_matrices(scene)
    A = ports_state_matrix(scene)
    r = render_state(A, loop.mass, scene.period, K=K, B=B)
    return PortsCheck(ports=scene.ports, render=r, port_stiffness=K, port_damping=B,
                      delays=tuple(float(d.delay) for _, d in scene.devices),
                      states=A.shape[0])


def stable_ports_check(scene, allow_unstable: bool = False,
                       override: str = "allow_unstable") -> PortsCheck:
    """:func:`check_ports`, refused when the coupled loop is unstable unless
    ``allow_unstable`` (every run of several ports: in lockstep and in real time).

    Parameters
    ----------
    scene : hapsim.scene.ScenePorts
        Two or three ports, each its own device.
    allow_unstable : bool, optional
        Measure an unstable coupled loop anyway (its check is returned).
    override : str, optional
        The user's name for ``allow_unstable`` (a flag or a field), named in the refusal.

    Returns
    -------
    PortsCheck
        The check (:func:`check_ports`).

    Raises
    ------
    UnstableConfigError
        A spectral radius of the coupled loop of 1 or more, unless ``allow_unstable``
        (the n-D scenes' twin: :func:`hapsim.api.running.stable_prediction_nd`).
    """
    from hapsim.errors import UnstableConfigError
    chk = check_ports(scene)
    if not chk.stable and not allow_unstable:
        raise UnstableConfigError(
            f"the coupled loop of {', '.join(chk.ports)} is unstable (spectral radius "
            f"{chk.render.spectral_radius:.9g}); {override} runs it anyway",
            spectral_radius=chk.render.spectral_radius)
    return chk
