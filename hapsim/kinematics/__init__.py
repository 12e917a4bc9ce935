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
  :mod:`hapsim.analysis.ths`.

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

from hapsim.errors import ConfigError
from hapsim.kinematics.common import JOINT_TURN, SINGULAR_SINE, cartesian_mass
from hapsim.kinematics.delta import DELTA_PRESETS, Delta, DeltaGeometry
from hapsim.kinematics.pantograph import PANTOGRAPH_PRESETS, Pantograph, PantographGeometry

__all__ = ["SINGULAR_SINE", "JOINT_TURN", "PantographGeometry", "DeltaGeometry",
           "PANTOGRAPH_PRESETS", "DELTA_PRESETS", "Pantograph", "Delta", "cartesian_mass",
           "device"]


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
