"""Device kinematics of the multi-DoF force-feedback devices: the pantograph and the delta.

Pure numpy; no daemon, scene or engine import. Every device here has as many actuated
joints as Cartesian degrees of freedom (n = 2 for the planar five-bar pantograph, n = 3 for
the Novint Falcon's delta), so its Jacobian ``J = dx/dq`` is square and, away from the
singularities, invertible:

- forward kinematics ``x = f(q)`` [m] from the joint angles ``q`` [rad];
- the Jacobian ``J(q) = df/dq`` [m/rad], by implicit differentiation of the closure
  constraints ``g(x, q) = 0``: ``J = -(dg/dx)^-1 dg/dq`` (Tsai, *Robot Analysis*, 1999,
  Sec. 4.3: the direct/inverse Jacobian pair of a parallel manipulator);
- the joint torques ``tau = J^T F`` [N m] that render a Cartesian force ``F`` [N] (virtual
  work);
- the Cartesian mass ``M = J^-T M_q J^-1`` [kg] of a joint-space inertia ``M_q``
  [kg m^2] (Khatib 1987, the operational-space inertia), used by
  :mod:`hapsim.analysis.ths_nd`.

Configurations the device cannot take (no assembly: the linkage does not close) and
singular ones (the Jacobian or its inverse does not exist: a serial singularity, where an
arm is stretched or folded, or a parallel one, where the handle gains a freedom) are
refused with :class:`hapsim.errors.KinematicsError`, which names the configuration and
the reason. Near a singularity the refusal uses the sine of the angle that vanishes there,
against :data:`SINGULAR_SINE` (the Jacobian's condition number grows like its inverse).

Geometries (sources):

- **Pantograph** (five-bar; Haply 2DIY, ``HaplyHaptics`` ``src/Haply/Pantograph.cpp``):
  proximal links ``l1``, ``l2`` driven at the base joints ``(0, 0)`` and ``(d, 0)``; elbows
  ``A = (l1 cos q1, l1 sin q1)``, ``B = (d + l2 cos q2, l2 sin q2)``; distal links ``L1``,
  ``L2``; the handle is the intersection of the circles of radius ``L1`` about ``A`` and
  ``L2`` about ``B`` with the larger ``y``. Haply: ``l = 0.05``, ``L = 0.07``,
  ``d = 0.02`` m (:data:`PANTOGRAPH_PRESETS`).
- **Delta** (Novint Falcon, after Stamper, *A Three Degree of Freedom Parallel
  Manipulator with Only Translational Degrees of Freedom*, PhD thesis, Univ. of Maryland
  1997, as parametrised by libnifalcon's ``FalconGeometry.h`` and its Stamper inverse
  kinematics): three legs at the angles ``phi_i`` about the ``z`` axis (90, -30, -150 deg
  plus the 15 deg mounting offset), each leg frame ``(u, v, w)`` with ``u = (cos phi,
  sin phi, 0)``, ``v = (-sin phi, cos phi, 0)``, ``w = z``, its base at ``(r, s)`` in
  ``(u, v)``. Leg ``i``: thigh of length ``a`` at the actuated angle ``q_i`` in the
  ``(u, w)`` plane, a parallelogram of side ``b`` at the angle ``theta3`` to ``v`` whose
  ends are offset by ``e`` (knee) and ``d`` (effector), and the effector centre offset by
  ``(c, f)`` in ``(u, v)``::

      pu + c = a cos q + (d + e + b sin theta3) cos theta2
      pv + f = b cos theta3
      pw     = a sin q + (d + e + b sin theta3) sin theta2

  Eliminating ``theta2`` and ``theta3`` (branch ``0 < theta3 < pi``,
  ``0 <= theta2 <= pi``) gives one closure constraint per leg, a torus about the knee:
  ``(rho - (d + e))^2 + (pv + f)^2 = b^2`` with
  ``rho = |(pu + c - a cos q, pw - a sin q)|``. Falcon: ``a = 60``, ``b = 102.5``,
  ``c = 14``, ``d = e = 11.25``, ``f = -25``, ``r = 37.233758``, ``s = -27.330909`` mm
  (:data:`DELTA_PRESETS`).

The delta's forward kinematics has no closed form (Stamper's is a degree-32 polynomial;
libnifalcon uses a lookup table and Newton steps): here it is trilateration on the three
spheres through each leg's knee, then Newton's method on the three torus constraints,
accepted only when the residual is at round-off and the solution lies on the stated
branch (the inverse kinematics of the result gives back the joints).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from hapsim.errors import ConfigError, KinematicsError

__all__ = ["SINGULAR_SINE", "PantographGeometry", "DeltaGeometry", "PANTOGRAPH_PRESETS",
           "DELTA_PRESETS", "Pantograph", "Delta", "cartesian_mass", "device"]

#: Refusal threshold near a singularity: the sine of the angle that vanishes there (the
#: angle between the two distal links of the pantograph, between a distal link and its
#: proximal one, the volume of the delta's constraint normals) must be at least this.
#: The Jacobian's condition number grows like its inverse: 1e-4 keeps it below ~1e4
#: times the link-length ratio, where a hand force still maps to finite torques and the
#: Cartesian mass is still meaningful.
SINGULAR_SINE = 1e-4


def _positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"must be a number [m], got {value!r}", key=name) from None
    if not math.isfinite(v) or v <= 0:
        raise ConfigError(f"must be a finite length > 0 [m], got {value!r}", key=name)
    return v


def _finite(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"must be a number, got {value!r}", key=name) from None
    if not math.isfinite(v):
        raise ConfigError(f"must be finite, got {value!r}", key=name)
    return v


#: The largest joint angle taken [rad]: one turn either way. A revolute joint's angle is
#: periodic, so nothing is lost; beyond it a value is a mistake (degrees given as radians
#: twice over, an overflow), and past ~1e16 rad its sine has no correct digit left.
JOINT_TURN = 2.0 * math.pi


def _joints(q, n: int, turn: bool = True) -> np.ndarray:
    """``q`` as a float array of shape (n,), finite and (with ``turn``) within one turn
    (:data:`JOINT_TURN`), else ConfigError (key ``joints``)."""
    try:
        a = np.asarray(q, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"must be {n} joint angles [rad], got {q!r}", key="joints") from None
    if a.shape != (n,):
        raise ConfigError(f"must be {n} joint angles [rad], got shape {a.shape}",
                          key="joints")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"must be finite, got {a.tolist()}", key="joints")
    if turn and np.any(np.abs(a) > JOINT_TURN):
        raise ConfigError(f"must be within one turn, -360..360 deg (a revolute joint's "
                          f"angle is periodic: give it modulo 360), got "
                          f"{[round(math.degrees(v), 6) for v in a.tolist()]} deg",
                          key="joints")
    return a


def _geometry(geometry, kind: str, presets: dict, cls: type):
    """``geometry`` itself when a ``cls``, else the preset of that name (ConfigError, key
    ``geometry``, naming the valid choices, otherwise)."""
    if isinstance(geometry, str):
        if geometry not in presets:
            raise ConfigError(f"unknown {kind} {geometry!r}; valid choices: "
                              f"{', '.join(presets)}", key="geometry")
        geometry = presets[geometry]
    if not isinstance(geometry, cls):
        raise ConfigError(f"must be a {cls.__name__} or a preset name, got {geometry!r}",
                          key="geometry")
    return geometry


def _deg(q) -> str:
    return "(" + ", ".join(f"{math.degrees(v):.6g}" for v in q) + ") deg"


# --------------------------------------------------------------------------- pantograph

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
            object.__setattr__(self, f, _positive(f, getattr(self, f)))
        d = _finite("d", self.d)
        if d < 0:
            raise ConfigError(f"must be >= 0 [m], got {self.d!r}", key="d")
        object.__setattr__(self, "d", d)

    @classmethod
    def symmetric(cls, l: float, L: float, d: float) -> "PantographGeometry":
        """The symmetric pantograph (``l1 = l2 = l``, ``L1 = L2 = L``) of Haply's
        ``--geometry l,L,d`` [m]."""
        return cls(l1=l, l2=l, L1=L, L2=L, d=d)

    def to_dict(self) -> dict:
        """Fields as a JSON-ready dict [m]."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class DeltaGeometry:
    """Stamper's delta geometry [m] and its leg angles [deg] (module docstring).

    Parameters
    ----------
    a : float > 0
        Thigh length (base joint to knee) [m].
    b : float > 0
        Side of the shin parallelogram [m].
    c : float
        Effector centre offset along the leg's ``u`` [m].
    d, e : float >= 0
        Parallelogram end offsets at the effector and at the knee [m].
    f : float
        Effector centre offset along the leg's ``v`` [m].
    r, s : float
        Leg base position in the leg's ``(u, v)`` [m].
    phi_deg : tuple of 3 float
        Leg angles about ``z`` [deg], mounting offset included.

    Raises
    ------
    ConfigError
        A non-finite value, ``a`` or ``b`` not > 0, ``d`` or ``e`` < 0, or not three
        leg angles; key: the field.
    """

    a: float
    b: float
    c: float
    d: float
    e: float
    f: float
    r: float = 0.0
    s: float = 0.0
    phi_deg: tuple = (90.0, -30.0, -150.0)

    def __post_init__(self) -> None:
        for name in ("a", "b"):
            object.__setattr__(self, name, _positive(name, getattr(self, name)))
        for name in ("c", "d", "e", "f", "r", "s"):
            object.__setattr__(self, name, _finite(name, getattr(self, name)))
        for name in ("d", "e"):
            if getattr(self, name) < 0:
                raise ConfigError(f"must be >= 0 [m], got {getattr(self, name)!r}", key=name)
        phi = tuple(self.phi_deg) if np.ndim(self.phi_deg) == 1 else ()
        if len(phi) != 3:
            raise ConfigError(f"must be 3 leg angles [deg], got {self.phi_deg!r}",
                              key="phi_deg")
        object.__setattr__(self, "phi_deg", tuple(_finite("phi_deg", p) for p in phi))

    def to_dict(self) -> dict:
        """Fields as a JSON-ready dict (lengths [m], ``phi_deg`` [deg])."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["phi_deg"] = list(self.phi_deg)
        return out


#: Named pantograph geometries. ``haply``: Haply 2DIY as in HaplyHaptics
#: ``src/Haply/Pantograph.cpp`` (l = 0.05, L = 0.07, d = 0.02 m).
PANTOGRAPH_PRESETS = {
    "haply": PantographGeometry.symmetric(0.05, 0.07, 0.02),
}

#: Named delta geometries. ``falcon``: Novint Falcon after Stamper, constants of
#: libnifalcon ``include/falcon/core/FalconGeometry.h`` (legs at 90, -30, -150 deg plus
#: its 15 deg offset ``OFFSET_ANGLE``).
DELTA_PRESETS = {
    "falcon": DeltaGeometry(a=0.060, b=0.1025, c=0.014, d=0.01125, e=0.01125, f=-0.025,
                            r=0.037233758, s=-0.027330909,
                            phi_deg=(105.0, -15.0, -135.0)),
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
        self.geometry = _geometry(geometry, "pantograph", PANTOGRAPH_PRESETS,
                                  PantographGeometry)

    def _solve(self, q):
        q = _joints(q, 2)
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
                f"no assembly at joints {_deg(q)}: the elbows are {r:.6g} m apart, the "
                f"distal links {g.L1:g} and {g.L2:g} m close only between "
                f"{abs(g.L1 - g.L2):g} and {g.L1 + g.L2:g} m (outside the workspace)",
                joints=q, kind="workspace")
        ex, ey = (bx - ax) / r, (by - ay) / r
        along = (g.L1 * g.L1 - g.L2 * g.L2 + r * r) / (2.0 * r)
        h = math.sqrt(max(g.L1 * g.L1 - along * along, 0.0))
        if abs(ex) < SINGULAR_SINE:
            q = np.array([q1, q2])
            raise KinematicsError(
                f"ambiguous assembly at joints {_deg(q)}: the elbows are vertically "
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
        q = _joints(q, 2)
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
                f"parallel singularity at joints {_deg(q)}: the distal links are aligned "
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
                        f"serial singularity at joints {_deg(q)}: arm {i + 1} is "
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
        return _torques(self.jacobian(q), force, 2)


# --------------------------------------------------------------------------- delta

def _solve3(A, r):
    """``A^-1 r`` of a 3x3 system by Cramer's rule (floats), None when singular."""
    (a, b, c), (d, e, f), (g, h, i) = A
    c0, c1, c2 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * c0 + b * c1 + c * c2
    if det == 0.0 or not math.isfinite(det):
        return None
    r0, r1, r2 = r
    return ((r0 * c0 + r1 * (c * h - b * i) + r2 * (b * f - c * e)) / det,
            (r0 * c1 + r1 * (a * i - c * g) + r2 * (c * d - a * f)) / det,
            (r0 * c2 + r1 * (b * g - a * h) + r2 * (a * e - b * d)) / det)


class Delta:
    """The Novint Falcon's delta after Stamper: forward kinematics, Jacobian, ``J^T F``.

    Parameters
    ----------
    geometry : DeltaGeometry or str, optional
        Geometry [m], or a key of :data:`DELTA_PRESETS` (default ``"falcon"``).

    Notes
    -----
    Constraints ``g_i(x, q_i) = (rho_i - (d + e))^2 + (pv_i + f)^2 - b^2 = 0`` (module
    docstring); ``J = -(dg/dx)^-1 diag(dg_i/dq_i)``. ``dg/dx`` singular: a parallel
    singularity (the effector gains a freedom); ``dg_i/dq_i = 0``: a serial one (leg ``i``
    stretched or folded in its plane).
    """

    dof = 3

    def __init__(self, geometry: DeltaGeometry | str = "falcon") -> None:
        self.geometry = geometry = _geometry(geometry, "delta", DELTA_PRESETS, DeltaGeometry)
        phi = np.radians(geometry.phi_deg)
        #: rows: leg i's u and v axes in the base frame (x, y)
        self._u = np.stack([np.cos(phi), np.sin(phi)], axis=1)
        self._v = np.stack([-np.sin(phi), np.cos(phi)], axis=1)

    @property
    def leg_axes(self) -> np.ndarray:
        """Each leg's ``u`` axis in the base frame's ``(x, y)``, shape (3, 2) [-]."""
        return self._u.copy()

    # leg frame of effector positions P (N, 3): (pu, pv, pw), each (N, 3) (leg = column)
    def _leg(self, P):
        g = self.geometry
        pu = P[:, :2] @ self._u.T - g.r
        pv = P[:, :2] @ self._v.T - g.s
        return pu, pv, np.repeat(P[:, 2:3], 3, axis=1)

    def residual(self, p, q) -> np.ndarray:
        """Closure constraints ``g_i(p, q_i)`` [m^2], shape (3,) (class docstring)."""
        return self._eval(np.asarray(p, float)[None], np.asarray(q, float)[None])[0][0]

    def _eval(self, P, Q):
        """For N configurations (``P``, ``Q`` of shape (N, 3)): constraints ``g`` (N, 3),
        ``dg/dp`` (N, 3, 3), ``dg_i/dq_i`` (N, 3), and per leg ``dw``, ``rho`` (N, 3)."""
        g = self.geometry
        pu, pv, pw = self._leg(P)
        cq, sq = np.cos(Q), np.sin(Q)
        du = pu + g.c - g.a * cq
        dw = pw - g.a * sq
        rho = np.hypot(du, dw)
        de = g.d + g.e
        r = (rho - de) ** 2 + (pv + g.f) ** 2 - g.b * g.b
        with np.errstate(divide="ignore", invalid="ignore"):
            k = 2.0 * (rho - de) / rho
        gu, gv = k * du, 2.0 * (pv + g.f)
        Gp = np.empty(P.shape[:1] + (3, 3))
        Gp[:, :, 0] = gu * self._u[:, 0] + gv * self._v[:, 0]
        Gp[:, :, 1] = gu * self._u[:, 1] + gv * self._v[:, 1]
        Gp[:, :, 2] = k * dw
        Gq = k * g.a * (du * sq - dw * cq)
        return r, Gp, Gq, dw, rho

    def inverse(self, p) -> np.ndarray:
        """Joint angles of an effector position (Stamper's inverse kinematics).

        Parameters
        ----------
        p : array_like, shape (3,)
            Effector position [m].

        Returns
        -------
        ndarray, shape (3,)
            ``q`` [rad], in ``(-pi, pi]``, on the branch ``0 < theta3 < pi``,
            ``0 <= theta2 <= pi`` (module docstring): per leg
            ``theta3 = acos((pv + f)/b)``, ``L = d + e + b sin theta3`` and
            ``q = 2 atan(t)`` with ``t`` the root
            ``-(l1 + sqrt(l1^2 - 4 l2 l0)) / (2 l2)`` of ``l2 t^2 + l1 t + l0 = 0``,
            ``l0 = |(pu + c, pw)|^2 + a^2 - L^2 - 2a(pu + c)``, ``l1 = -4 a pw``,
            ``l2 = |(pu + c, pw)|^2 + a^2 - L^2 + 2a(pu + c)`` (the tangent half-angle
            form of ``|(pu + c - a cos q, pw - a sin q)| = L``).

        Raises
        ------
        ConfigError
            ``p`` not three finite numbers (key ``position``).
        KinematicsError
            ``p`` out of reach of some leg (``kind="workspace"``).
        """
        g = self.geometry
        try:
            p = _joints(p, 3, turn=False)
        except ConfigError as exc:
            raise ConfigError(exc.reason.replace("joint angles [rad]", "coordinates [m]"),
                              key="position") from None
        pu, pv, pw = (v[0] for v in self._leg(p[None]))
        cos3 = (pv + g.f) / g.b
        if np.any(np.abs(cos3) >= 1.0):
            i = int(np.argmax(np.abs(cos3)))
            raise KinematicsError(
                f"position {p.tolist()} m is out of reach of leg {i + 1}: its "
                f"parallelogram would need cos theta3 = {cos3[i]:.6g}",
                joints=None, kind="workspace", key="position")
        L = g.d + g.e + g.b * np.sqrt(1.0 - cos3 * cos3)
        U = pu + g.c
        n2 = U * U + pw * pw + g.a * g.a - L * L
        l0 = n2 - 2.0 * g.a * U
        l1 = -4.0 * g.a * pw
        l2 = n2 + 2.0 * g.a * U
        disc = l1 * l1 - 4.0 * l2 * l0
        if np.any(disc < 0) or np.any(l2 == 0):
            i = int(np.argmin(disc))
            raise KinematicsError(
                f"position {p.tolist()} m is out of reach of leg {i + 1}: its thigh "
                "circle does not meet the shin's", joints=None, kind="workspace",
                key="position")
        t = -(l1 + np.sqrt(disc)) / (2.0 * l2)
        return 2.0 * np.arctan(t)

    def _trilaterate(self, Q, R2):
        """Initial guesses (N, 3): the larger-``z`` point at the distances ``sqrt(R2)``
        (N, 3) from the three knee centres ``(a cos q - c, -f, a sin q)`` of each leg
        frame; nan where the spheres do not meet."""
        g = self.geometry
        ku = g.a * np.cos(Q) - g.c + g.r
        kv = -g.f + g.s
        K = np.empty(Q.shape + (3,))
        K[..., 0] = ku * self._u[:, 0] + kv * self._v[:, 0]
        K[..., 1] = ku * self._u[:, 1] + kv * self._v[:, 1]
        K[..., 2] = g.a * np.sin(Q)
        with np.errstate(divide="ignore", invalid="ignore"):
            ex = K[:, 1] - K[:, 0]
            dx = np.linalg.norm(ex, axis=1)
            ex = ex / dx[:, None]
            t = K[:, 2] - K[:, 0]
            i = np.einsum("ij,ij->i", ex, t)
            ey = t - i[:, None] * ex
            j = np.linalg.norm(ey, axis=1)
            ey = ey / j[:, None]
            ez = np.cross(ex, ey)
            x = (R2[:, 0] - R2[:, 1] + dx * dx) / (2.0 * dx)
            y = (R2[:, 0] - R2[:, 2] + i * i + j * j) / (2.0 * j) - i / j * x
            z = np.sqrt(R2[:, 0] - x * x - y * y)    # nan: the spheres do not meet
            base = K[:, 0] + x[:, None] * ex + y[:, None] * ey
            z = np.where(ez[:, 2] >= 0, z, -z)     # the larger-z intersection
            return base + z[:, None] * ez

    def _grid(self, n=9):
        """An ``n^3`` grid of the box ``|x|, |y| <= R``, ``0 <= z <= R`` the legs reach
        (``R = a + b + d + e + |c| + |(r, s)|``), shape (n^3, 3) [m]."""
        g = self.geometry
        reach = g.a + g.b + g.d + g.e + abs(g.c) + math.hypot(g.r, g.s)
        axis = np.linspace(-reach, reach, n)
        return np.stack(np.meshgrid(axis, axis, np.linspace(0.0, reach, n),
                                    indexing="ij"), -1).reshape(-1, 3)

    def _initial(self, Q):
        """Newton's starting points (N, 3): of the candidates, the one with the smallest
        constraint residual on the Falcon's side (every shin in front of its knee): the
        point on the spheres ``|p - K|^2 = b^2 + 2 rho (d + e) - (d + e)^2`` through the
        knee centres (the torus with ``rho = d + e + b``, shins square to ``v``),
        re-trilaterated twice with each leg's ``rho`` at the estimate, and a 9^3 grid of
        the box the legs reach (where the spheres miss, near the reach's edge)."""
        g = self.geometry
        de = g.d + g.e
        cands = []
        P = self._trilaterate(Q, np.full(Q.shape, (g.b + de) ** 2))
        cands.append(P)
        for _ in range(2):
            with np.errstate(invalid="ignore"):
                rho = self._eval(np.nan_to_num(P), Q)[4]
                P = self._trilaterate(Q, g.b * g.b + 2.0 * rho * de - de * de)
            cands.append(P)
        grid = self._grid()
        best = np.full(Q.shape, np.nan)
        score = np.full(Q.shape[0], np.inf)
        with np.errstate(invalid="ignore"):
            for C in cands:
                r, _, _, dw, _ = self._eval(np.nan_to_num(C), Q)
                sc = np.where(np.all(np.isfinite(C), axis=1), np.max(np.abs(r), axis=1),
                              np.inf)
                take = sc < score
                best[take], score[take] = C[take], sc[take]
            # the grid only where the spheres do not meet (near the reach's edge)
            poor = np.flatnonzero(~np.isfinite(score))
            if poor.size:
                Qp = np.repeat(Q[poor], grid.shape[0], axis=0)
                Cp = np.tile(grid, (poor.size, 1))
                r, _, _, dw, _ = self._eval(Cp, Qp)
                sc = np.where(np.all(dw >= 0, axis=1), np.max(np.abs(r), axis=1), np.inf)
                sc = sc.reshape(poor.size, grid.shape[0])
                k = np.argmin(sc, axis=1)
                scb = sc[np.arange(poor.size), k]
                take = scb < score[poor]
                best[poor[take]] = grid[k[take]]
                score[poor[take]] = scb[take]
        return best

    def forward_many(self, Q) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics of many configurations at once (workspace maps).

        Parameters
        ----------
        Q : array_like, shape (N, 3)
            Thigh angles [rad], finite.

        Returns
        -------
        P : ndarray, shape (N, 3)
            Effector positions [m] (as :meth:`forward`); nan where not assembled.
        ok : ndarray of bool, shape (N,)
            Whether each configuration assembles on the Falcon's branch with a residual
            at round-off.

        Raises
        ------
        ConfigError
            ``Q`` not of shape (N, 3), not finite or beyond one turn (key ``joints``).
        """
        Q = np.asarray(Q, dtype=float)
        if Q.ndim != 2 or Q.shape[1] != 3 or not np.all(np.isfinite(Q)):
            raise ConfigError(f"must be finite joint angles of shape (N, 3) [rad], got "
                              f"shape {Q.shape}", key="joints")
        if np.any(np.abs(Q) > JOINT_TURN):
            raise ConfigError("must be within one turn, -360..360 deg (a revolute joint's "
                              "angle is periodic: give it modulo 360)", key="joints")
        P, ok = self._solve_many(Q)[:2]
        P = P.copy()
        P[~ok] = np.nan
        return P, ok

    def _newton(self, P, Q, live, iters=40):
        """Newton's method on the closure constraints from ``P`` (N, 3) where ``live``."""
        g = self.geometry
        P = np.where(live[:, None], P, 0.0)
        for _ in range(iters):
            r, Gp = self._eval(P, Q)[:2]
            with np.errstate(all="ignore"):
                det = np.linalg.det(Gp)
                good = live & np.isfinite(det) & (det != 0)
                step = np.zeros_like(P)
                if np.any(good):
                    step[good] = np.linalg.solve(Gp[good], r[good][:, :, None])[:, :, 0]
            live = good
            # damped: halve a step (up to 8 times) while it does not lower max |g|
            r0 = np.max(np.abs(r), axis=1)
            lam = np.ones(P.shape[0])
            for _ in range(8):
                Pt = P - lam[:, None] * step
                rt = np.max(np.abs(self._eval(Pt, Q)[0]), axis=1)
                worse = live & ~(rt < r0) & (r0 > 1e-13 * g.b * g.b)
                if not np.any(worse):
                    break
                lam = np.where(worse, 0.5 * lam, lam)
            P = P - lam[:, None] * step
            if not np.any(np.abs(step[live]) >= 1e-14 * g.b):   # all converged (or nan)
                break
        return P, live

    def _accept(self, P, Q, live):
        g = self.geometry
        r, Gp, Gq, dw, rho = self._eval(P, Q)
        # the branch of the module docstring: theta3 in (0, pi) (rho > d + e) and
        # theta2 in [0, pi] (pw >= a sin q), i.e. the same joints from the inverse
        ok = (live & np.all(np.isfinite(P), axis=1)
              & np.all(np.abs(r) <= 1e-12 * g.b * g.b, axis=1)
              & np.all(rho > g.d + g.e, axis=1) & np.all(dw >= -1e-12 * g.b, axis=1))
        return ok, Gp, Gq

    def _solve_many(self, Q):
        P0 = self._initial(Q)
        P, live = self._newton(P0, Q, np.all(np.isfinite(P0), axis=1))
        ok, Gp, Gq = self._accept(P, Q, live)
        for i in np.flatnonzero(~ok):
            # near a leg's full stretch the best guess can fall into another closure of
            # the legs: Newton from every grid point in front of the knees, the first on
            # the branch (unique there) wins
            grid = self._grid()
            Qi = np.broadcast_to(Q[i], grid.shape)
            dw = self._eval(grid, Qi)[3]
            front = grid[np.all(dw >= 0, axis=1)]
            if not front.size:
                continue
            Qi = np.broadcast_to(Q[i], front.shape)
            Pi, livei = self._newton(front, Qi, np.ones(front.shape[0], bool))
            oki, Gpi, Gqi = self._accept(Pi, Qi, livei)
            if np.any(oki):
                k = int(np.argmax(oki))
                P[i], ok[i], Gp[i], Gq[i] = Pi[k], True, Gpi[k], Gqi[k]
        return P, ok, Gp, Gq

    def _solve(self, q):
        q = _joints(q, 3)
        P, ok, Gp, Gq = self._solve_many(q[None])
        if not ok[0]:
            raise KinematicsError(f"no assembly at joints {_deg(q)}: the legs' closure "
                                  "has no solution on the Falcon's branch (outside the "
                                  "workspace)", joints=q, kind="workspace")
        return q, P[0], Gp[0], Gq[0]

    def forward(self, q) -> np.ndarray:
        """Effector position.

        Parameters
        ----------
        q : array_like, shape (3,)
            Thigh angles ``(q1, q2, q3)`` [rad].

        Returns
        -------
        ndarray, shape (3,)
            ``(x, y, z)`` [m]: the solution of the three closure constraints on the
            Falcon's branch (module docstring), residual at round-off.

        Raises
        ------
        ConfigError
            ``q`` not three finite numbers within one turn (key ``joints``).
        KinematicsError
            No assembly (outside the workspace, ``kind="workspace"``).
        """
        return self._solve(q)[1]

    def jacobian_many(self, Q) -> tuple[np.ndarray, np.ndarray]:
        """Jacobians of many configurations at once (workspace maps).

        Parameters
        ----------
        Q : array_like, shape (N, 3)
            Thigh angles [rad].

        Returns
        -------
        J : ndarray, shape (N, 3, 3)
            ``dx/dq`` [m/rad] as :meth:`jacobian`; nan where refused.
        status : ndarray of str, shape (N,)
            ``"ok"``, ``"workspace"``, ``"parallel"`` or ``"serial"`` (the
            :class:`~hapsim.errors.KinematicsError` kind :meth:`jacobian` would raise).

        Raises
        ------
        ConfigError
            ``Q`` not of shape (N, 3), not finite or beyond one turn (key ``joints``).
        """
        Q = np.asarray(Q, dtype=float)
        if Q.ndim != 2 or Q.shape[1] != 3 or not np.all(np.isfinite(Q)):
            raise ConfigError(f"must be finite joint angles of shape (N, 3) [rad], got "
                              f"shape {Q.shape}", key="joints")
        if np.any(np.abs(Q) > JOINT_TURN):
            raise ConfigError("must be within one turn, -360..360 deg (a revolute joint's "
                              "angle is periodic: give it modulo 360)", key="joints")
        P, ok, Gp, Gq = self._solve_many(Q)
        status, J = self._classify(ok, Gp, Gq)
        return J, status

    def _classify(self, ok, Gp, Gq):
        g = self.geometry
        status = np.where(ok, "ok", "workspace").astype("<U9")
        with np.errstate(all="ignore"):
            norms = np.linalg.norm(Gp, axis=2)
            vol = np.abs(np.linalg.det(Gp / norms[:, :, None]))
            status[ok & ~(vol >= SINGULAR_SINE)] = "parallel"
            serial = np.any(np.abs(Gq) < SINGULAR_SINE * norms * g.a, axis=1)
        status[(status == "ok") & serial] = "serial"
        J = np.full(Gp.shape, np.nan)
        good = status == "ok"
        if np.any(good):
            J[good] = -np.linalg.solve(Gp[good], Gq[good][:, :, None] * np.eye(3))
        return status, J

    def jacobian(self, q) -> np.ndarray:
        """``J = dx/dq`` [m/rad] at ``q``.

        Parameters
        ----------
        q : array_like, shape (3,)
            Thigh angles [rad].

        Returns
        -------
        ndarray, shape (3, 3)
            ``-(dg/dx)^-1 diag(dg_i/dq_i)`` (class docstring).

        Raises
        ------
        KinematicsError
            As :meth:`forward`, or singular: the constraint normals (rows of ``dg/dx``,
            normalised) span a volume below :data:`SINGULAR_SINE` (parallel,
            ``kind="parallel"``), or a leg's ``|dg_i/dq_i|`` is below
            :data:`SINGULAR_SINE` times its scale ``|dg_i/dx| a`` (serial,
            ``kind="serial"``).
        """
        q, _, Gp, Gq = self._solve(q)
        return self._jacobian_at(q, Gp, Gq)

    def forward_jacobian(self, q, guess=None) -> tuple[np.ndarray, np.ndarray]:
        """Effector position and Jacobian in one solve, by Newton's method from ``guess``
        when it is given (a loop's last position: a few iterations instead of
        :meth:`forward`'s search for a start), else as :meth:`forward`.

        Parameters
        ----------
        q : array_like, shape (3,)
            Thigh angles [rad].
        guess : array_like, shape (3,), optional
            A position near the solution [m]; where Newton's method from it does not end
            on the Falcon's branch with a residual at round-off (the acceptance of
            :meth:`forward`), the full solve is done.

        Returns
        -------
        x : ndarray, shape (3,)
            As :meth:`forward` [m] (the branch's solution is unique: the same point).
        J : ndarray, shape (3, 3)
            As :meth:`jacobian` [m/rad].

        Raises
        ------
        ConfigError
            ``q`` not three finite numbers within one turn (key ``joints``).
        KinematicsError
            As :meth:`jacobian`.
        """
        if guess is not None:
            q = _joints(q, 3)
            got = self._track(q, guess)
            if got is not None:
                return got[0], self._jacobian_at(q, got[1], got[2])
        q, p, Gp, Gq = self._solve(q)
        return p.copy(), self._jacobian_at(q, Gp, Gq)

    def _track(self, q, guess, iters: int = 12):
        """Newton's method on floats (the constraints of :meth:`_eval`, one configuration)
        from ``guess``: ``(p, dg/dp, dg_i/dq_i)`` when it ends on the Falcon's branch with
        a residual at round-off (:meth:`_accept`'s tests), else None."""
        g = self.geometry
        try:
            x, y, z = (float(v) for v in guess)
        except (TypeError, ValueError):
            return None
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            return None
        de, b2, a = g.d + g.e, g.b * g.b, g.a
        legs = [(float(self._u[i, 0]), float(self._u[i, 1]), float(self._v[i, 0]),
                 float(self._v[i, 1]), math.cos(float(q[i])), math.sin(float(q[i])))
                for i in range(3)]
        tol = 1e-14 * g.b
        for it in range(iters + 1):
            r, G, gq, ok = [], [], [], True
            for ux, uy, vx, vy, cq, sq in legs:
                pu = x * ux + y * uy - g.r
                pv = x * vx + y * vy - g.s
                du = pu + g.c - a * cq
                dw = z - a * sq
                rho = math.hypot(du, dw)
                if rho == 0.0:
                    return None
                k = 2.0 * (rho - de) / rho
                gu, gv = k * du, 2.0 * (pv + g.f)
                r.append((rho - de) ** 2 + (pv + g.f) ** 2 - b2)
                G.append((gu * ux + gv * vx, gu * uy + gv * vy, k * dw))
                gq.append(k * a * (du * sq - dw * cq))
                ok = ok and rho > de and dw >= -1e-12 * g.b
            done = it > 0 and max(abs(s) for s in step) < tol
            if done or it == iters:
                if ok and all(abs(v) <= 1e-12 * b2 for v in r):
                    return (np.array([x, y, z]), np.array(G), np.array(gq))
                return None
            step = _solve3(G, r)
            if step is None:
                return None
            x, y, z = x - step[0], y - step[1], z - step[2]
        return None

    def _jacobian_at(self, q, Gp, Gq):
        """``J`` from the constraint derivatives at a solution; singular ones refused."""
        g = self.geometry
        status, J = self._classify(np.array([True]), Gp[None], Gq[None])
        if status[0] == "parallel":
            raise KinematicsError(
                f"parallel singularity at joints {_deg(q)}: the legs' constraint normals "
                "are coplanar; the effector is not held there", joints=q, kind="parallel")
        if status[0] == "serial":
            norms = np.linalg.norm(Gp, axis=1)
            i = int(np.argmin(np.abs(Gq) / (norms * g.a)))
            raise KinematicsError(
                f"serial singularity at joints {_deg(q)}: leg {i + 1} is stretched "
                "or folded in its plane; the effector cannot move along it",
                joints=q, kind="serial")
        return J[0]

    def torques(self, q, force) -> np.ndarray:
        """Joint torques ``tau = J^T F`` [N m] rendering the effector force ``F`` [N].

        Parameters
        ----------
        q : array_like, shape (3,)
            Thigh angles [rad].
        force : array_like, shape (3,)
            Cartesian force [N].

        Returns
        -------
        ndarray, shape (3,)
            Torques [N m] (virtual work).

        Raises
        ------
        ConfigError
            ``force`` not three finite numbers (key ``force``).
        KinematicsError
            As :meth:`jacobian`.
        """
        return _torques(self.jacobian(q), force, 3)


def _torques(J: np.ndarray, force, n: int) -> np.ndarray:
    try:
        F = np.asarray(force, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"must be {n} force components [N], got {force!r}",
                          key="force") from None
    if F.shape != (n,) or not np.all(np.isfinite(F)):
        raise ConfigError(f"must be {n} finite force components [N], got {force!r}",
                          key="force")
    return J.T @ F


def cartesian_mass(J, joint_inertia) -> np.ndarray:
    """Cartesian (operational-space) mass ``M = J^-T M_q J^-1`` [kg].

    Parameters
    ----------
    J : array_like, shape (n, n)
        Jacobian ``dx/dq`` [m/rad], invertible.
    joint_inertia : array_like, shape (n,) or (n, n)
        Joint-space inertia ``M_q`` [kg m^2] (a vector: its diagonal), symmetric
        positive definite.

    Returns
    -------
    ndarray, shape (n, n)
        ``M`` [kg], symmetric (symmetrised against round-off). The same map takes a
        joint friction ``B_q`` [N m s/rad] to the Cartesian friction [N s/m].

    Notes
    -----
    Kinetic energy ``1/2 dq^T M_q dq = 1/2 dx^T M dx`` with ``dx = J dq`` (Khatib 1987).

    Raises
    ------
    ConfigError
        Shapes that do not match, or ``M_q`` not symmetric positive semi-definite
        (key ``joint_inertia``).
    KinematicsError
        ``J`` singular.
    """
    J = np.asarray(J, float)
    n = J.shape[0]
    Mq = np.asarray(joint_inertia, float)
    if Mq.ndim == 1:
        Mq = np.diag(Mq)
    if J.shape != (n, n) or Mq.shape != (n, n) or not np.all(np.isfinite(Mq)):
        raise ConfigError(f"needs a square Jacobian and a matching joint inertia; got "
                          f"{J.shape} and {np.shape(joint_inertia)}", key="joint_inertia")
    # eigenvalues of M_q scaled to entries <= 1: LAPACK's symmetric solver does not
    # converge on entries near the double range (a joint inertia of 1e308, issue 31)
    sq = max(float(np.max(np.abs(Mq))), np.finfo(float).tiny)
    if not np.allclose(Mq, Mq.T, rtol=1e-12, atol=0) or \
            np.min(np.linalg.eigvalsh(0.5 * (Mq / sq) + 0.5 * (Mq.T / sq))) < 0:
        raise ConfigError("must be symmetric positive semi-definite", key="joint_inertia")
    try:
        Jinv = np.linalg.inv(J)
    except np.linalg.LinAlgError:
        raise KinematicsError("the Jacobian is singular: no Cartesian mass there",
                              joints=None, kind="serial") from None
    M = Jinv.T @ Mq @ Jinv
    return 0.5 * (M + M.T)


def device(kind: str, geometry=None):
    """A kinematic device by name.

    Parameters
    ----------
    kind : {"pantograph", "delta"}
    geometry : PantographGeometry, DeltaGeometry or str, optional
        Its geometry or preset name (default: ``"haply"``, ``"falcon"``).

    Returns
    -------
    Pantograph or Delta

    Raises
    ------
    ConfigError
        Unknown ``kind`` or geometry (the valid choices named).
    """
    if kind == "pantograph":
        return Pantograph("haply" if geometry is None else geometry)
    if kind == "delta":
        return Delta("falcon" if geometry is None else geometry)
    raise ConfigError(f"unknown device kind {kind!r}; valid choices: pantograph, delta",
                      key="kind")
