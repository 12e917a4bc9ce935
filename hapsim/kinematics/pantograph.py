"""The planar five-bar pantograph (Haply 2DIY, ``HaplyHaptics`` ``src/Haply/Pantograph.cpp``):
its geometry, presets and kinematics (:mod:`hapsim.kinematics` states the conventions)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from hapsim.errors import ConfigError, KinematicsError
from hapsim.kinematics.common import SINGULAR_SINE, degrees_text, finite, geometry_of, joint_angles, joint_torques, positive

__all__ = ["PantographGeometry", "PANTOGRAPH_PRESETS", "Pantograph"]


@dataclass(frozen=True)
class PantographGeometry:
    """Lengths of a planar five-bar pantograph [m].

    Parameters
    ----------
    l1, l2 : float > 0
        Proximal (driven) links of joint 1 (base at the origin) and joint 2 (base at
        ``(d, 0)``) [m].
    L1, L2 : float > 0
        Distal links from the elbows ``A`` and ``B`` to the handle [m].
    d : float >= 0
        Distance between the two base joints along ``x`` [m].

    Raises
    ------
    ConfigError
        A length that is not finite and > 0 (``d``: >= 0); key: the field.
    """

    l1: float
    l2: float
    L1: float
    L2: float
    d: float

    def __post_init__(self) -> None:
        for f in ("l1", "l2", "L1", "L2"):
            object.__setattr__(self, f, positive(f, getattr(self, f)))
        d = finite("d", self.d)
        if d < 0:
            raise ConfigError(f"must be >= 0 [m], got {self.d!r}", key="d")
        object.__setattr__(self, "d", d)

    @classmethod
    def symmetric(cls, l: float, L: float, d: float) -> "PantographGeometry":
        """The symmetric pantograph (``l1 = l2 = l``, ``L1 = L2 = L``) of Haply's
        ``--geometry l,L,d`` [m].

        Parameters
        ----------
        l : float > 0
            Proximal links [m].
        L : float > 0
            Distal links [m].
        d : float >= 0
            Distance between the base joints [m].

        Returns
        -------
        PantographGeometry

        Raises
        ------
        ConfigError
            As the constructor.
        """
        return cls(l1=l, l2=l, L1=L, L2=L, d=d)

    def to_dict(self) -> dict:
        """Fields as a JSON-ready dict [m].

        Returns
        -------
        dict
            ``l1``, ``l2``, ``L1``, ``L2``, ``d`` [m] as floats.
        """
        return {f.name: getattr(self, f.name) for f in fields(self)}


#: Named pantograph geometries. ``haply``: Haply 2DIY as in HaplyHaptics
#: ``src/Haply/Pantograph.cpp`` (l = 0.05, L = 0.07, d = 0.02 m).
PANTOGRAPH_PRESETS = {
    "haply": PantographGeometry.symmetric(0.05, 0.07, 0.02),
}


class Pantograph:
    """The planar five-bar pantograph: forward kinematics, Jacobian, ``tau = J^T F``.

    Parameters
    ----------
    geometry : PantographGeometry or str, optional
        Lengths [m], or a key of :data:`PANTOGRAPH_PRESETS` (default ``"haply"``).

    Notes
    -----
    Closure constraints ``|P - A|^2 = L1^2``, ``|P - B|^2 = L2^2``; differentiating,
    ``Phi dP = D dq`` with ``Phi = [(P - A)^T; (P - B)^T]`` and
    ``D = diag((P - A).A', (P - B).B')`` (``A' = dA/dq1``, ``B' = dB/dq2``), so
    ``J = Phi^-1 D``. ``Phi`` is singular when the distal links are aligned (parallel
    singularity, the workspace boundary ``|AB| = L1 + L2`` or ``|L1 - L2|``), ``D`` when a
    distal link is aligned with its proximal one (serial singularity).
    """

    dof = 2

    def __init__(self, geometry: PantographGeometry | str = "haply") -> None:
        self.geometry = geometry_of(geometry, "pantograph", PANTOGRAPH_PRESETS,
                                  PantographGeometry)

    def _solve(self, q):
        q = joint_angles(q, 2)
        ax, ay, bx, by, px, py = self._points(q[0], q[1])
        return q, np.array([ax, ay]), np.array([bx, by]), np.array([px, py])

    def _points(self, q1: float, q2: float) -> tuple:
        """Elbows ``A``, ``B`` and handle ``P`` at joints ``(q1, q2)`` [rad], as six floats
        [m] (scalar arithmetic: no array is made, for the real-time loops)."""
        g = self.geometry
        c1, s1, c2, s2 = math.cos(q1), math.sin(q1), math.cos(q2), math.sin(q2)
        ax, ay = g.l1 * c1, g.l1 * s1
        bx, by = g.d + g.l2 * c2, g.l2 * s2
        r = math.hypot(bx - ax, by - ay)
        if not (abs(g.L1 - g.L2) < r < g.L1 + g.L2):
            q = np.array([q1, q2])
            raise KinematicsError(
                f"no assembly at joints {degrees_text(q)}: the elbows are {r:.6g} m apart, the "
                f"distal links {g.L1:g} and {g.L2:g} m close only between "
                f"{abs(g.L1 - g.L2):g} and {g.L1 + g.L2:g} m (outside the workspace)",
                joints=q, kind="workspace")
        ex, ey = (bx - ax) / r, (by - ay) / r
        along = (g.L1 * g.L1 - g.L2 * g.L2 + r * r) / (2.0 * r)
        h = math.sqrt(max(g.L1 * g.L1 - along * along, 0.0))
        if abs(ex) < SINGULAR_SINE:
            q = np.array([q1, q2])
            raise KinematicsError(
                f"ambiguous assembly at joints {degrees_text(q)}: the elbows are vertically "
                "aligned, so both closures of the linkage have the same y (the "
                "larger-y branch is undefined)", joints=q, kind="workspace")
        hs = h if ex > 0 else -h                    # along the normal n = (-e_y, e_x)
        return ax, ay, bx, by, ax + along * ex - hs * ey, ay + along * ey + hs * ex

    def forward(self, q) -> np.ndarray:
        """Handle position.

        Parameters
        ----------
        q : array_like, shape (2,)
            Joint angles ``(q1, q2)`` [rad].

        Returns
        -------
        ndarray, shape (2,)
            ``(x, y)`` [m]: the larger-``y`` intersection of the circles of radius
            ``L1`` about ``A`` and ``L2`` about ``B`` (class docstring).

        Raises
        ------
        ConfigError
            ``q`` not two finite numbers within one turn (key ``joints``).
        KinematicsError
            No assembly (``|AB|`` outside ``(|L1 - L2|, L1 + L2)``) or both closures at
            the same ``y``.
        """
        return self._solve(q)[3]

    def forward_at(self, q1: float, q2: float) -> tuple:
        """:meth:`forward` on two floats, as a tuple: no array is made (the real-time
        loops' per-sample use; ``q`` is not validated).

        Parameters
        ----------
        q1, q2 : float
            Joint angles [rad].

        Returns
        -------
        tuple of float
            ``(x, y)`` [m].

        Raises
        ------
        KinematicsError
            As :meth:`forward`.
        """
        _, _, _, _, px, py = self._points(q1, q2)
        return px, py

    def jacobian(self, q) -> np.ndarray:
        """``J = dx/dq`` [m/rad] at ``q``.

        Parameters
        ----------
        q : array_like, shape (2,)
            Joint angles [rad].

        Returns
        -------
        ndarray, shape (2, 2)
            ``J[i, j] = d x_i / d q_j`` = ``Phi^-1 D`` (class docstring).

        Raises
        ------
        KinematicsError
            As :meth:`forward`, or a singular configuration: distal links aligned
            (parallel, ``kind="parallel"``) or a distal link aligned with its proximal one
            (serial, ``kind="serial"``), to within :data:`SINGULAR_SINE`.
        """
        q = joint_angles(q, 2)
        j00, j01, j10, j11 = self.jacobian_at(q[0], q[1])
        return np.array([[j00, j01], [j10, j11]])

    def jacobian_at(self, q1: float, q2: float) -> tuple:
        """:meth:`jacobian` on two floats, as ``(J00, J01, J10, J11)`` [m/rad]: no array
        is made (the real-time loops' per-sample use; ``q`` is not validated). ``Phi``'s
        2 x 2 inverse by its adjugate over ``det Phi`` (the cross product, bounded away
        from 0 by the parallel-singularity test).

        Parameters
        ----------
        q1, q2 : float
            Joint angles [rad].

        Returns
        -------
        tuple of float

        Raises
        ------
        KinematicsError
            As :meth:`jacobian`.
        """
        g = self.geometry
        ax, ay, bx, by, px, py = self._points(q1, q2)
        pax, pay, pbx, pby = px - ax, py - ay, px - bx, py - by
        cross = pax * pby - pay * pbx
        if abs(cross) < SINGULAR_SINE * g.L1 * g.L2:
            q = np.array([q1, q2])
            raise KinematicsError(
                f"parallel singularity at joints {degrees_text(q)}: the distal links are aligned "
                f"(sine of their angle {cross / (g.L1 * g.L2):.3g}); the handle is not "
                "held there", joints=q, kind="parallel")
        # d1 = PA . dA/dq1, d2 = PB . dB/dq2
        d1 = g.l1 * (-pax * math.sin(q1) + pay * math.cos(q1))
        d2 = g.l2 * (-pbx * math.sin(q2) + pby * math.cos(q2))
        if abs(d1) < SINGULAR_SINE * g.l1 * g.L1 or abs(d2) < SINGULAR_SINE * g.l2 * g.L2:
            q = np.array([q1, q2])
            for i, (dd, l, L) in enumerate(((d1, g.l1, g.L1), (d2, g.l2, g.L2))):
                if abs(dd) < SINGULAR_SINE * l * L:
                    raise KinematicsError(
                        f"serial singularity at joints {degrees_text(q)}: arm {i + 1} is "
                        "stretched or folded (its distal link along its proximal one); "
                        "the handle cannot move along that arm", joints=q, kind="serial")
        # J = Phi^-1 diag(d1, d2), Phi = [[PA], [PB]]: Phi^-1 = [[pby, -pay], [-pbx, pax]] / cross
        return (pby * d1 / cross, -pay * d2 / cross, -pbx * d1 / cross, pax * d2 / cross)

    def torques(self, q, force) -> np.ndarray:
        """Joint torques ``tau = J^T F`` [N m] rendering the handle force ``F`` [N].

        Parameters
        ----------
        q : array_like, shape (2,)
            Joint angles [rad].
        force : array_like, shape (2,)
            Cartesian force on the handle [N].

        Returns
        -------
        ndarray, shape (2,)
            Torques [N m] (virtual work: ``tau . dq = F . dx``).

        Raises
        ------
        ConfigError
            ``force`` not two finite numbers (key ``force``).
        KinematicsError
            As :meth:`jacobian`.
        """
        return joint_torques(self.jacobian(q), force, 2)
