"""The Novint Falcon's delta after Stamper (1997), as parametrised by libnifalcon's
``FalconGeometry.h``: its geometry, presets and kinematics (:mod:`hapsim.kinematics`
states the conventions and the forward kinematics' method)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from hapsim.errors import ConfigError, KinematicsError
from hapsim.kinematics.common import JOINT_TURN, SINGULAR_SINE, degrees_text, finite, geometry_of, joint_angles, joint_torques, positive

__all__ = ["DeltaGeometry", "DELTA_PRESETS", "Delta"]


def _joint_batch(Q) -> np.ndarray:
    """``Q`` as an (N, 3) float array of thigh angles [rad] (of :meth:`Delta.forward_many`
    and :meth:`Delta.jacobian_many`).

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
    return Q


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
            object.__setattr__(self, name, positive(name, getattr(self, name)))
        for name in ("c", "d", "e", "f", "r", "s"):
            object.__setattr__(self, name, finite(name, getattr(self, name)))
        for name in ("d", "e"):
            if getattr(self, name) < 0:
                raise ConfigError(f"must be >= 0 [m], got {getattr(self, name)!r}", key=name)
        phi = tuple(self.phi_deg) if np.ndim(self.phi_deg) == 1 else ()
        if len(phi) != 3:
            raise ConfigError(f"must be 3 leg angles [deg], got {self.phi_deg!r}",
                              key="phi_deg")
        object.__setattr__(self, "phi_deg", tuple(finite("phi_deg", p) for p in phi))

    def to_dict(self) -> dict:
        """Fields as a JSON-ready dict (lengths [m], ``phi_deg`` [deg]).

        Returns
        -------
        dict
            ``a`` .. ``f``, ``r``, ``s`` [m] as floats and ``phi_deg``, a list of 3 [deg].
        """
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["phi_deg"] = list(self.phi_deg)
        return out


#: Named delta geometries. ``falcon``: Novint Falcon after Stamper, constants of
#: libnifalcon ``include/falcon/core/FalconGeometry.h`` (legs at 90, -30, -150 deg plus
#: its 15 deg offset ``OFFSET_ANGLE``).
DELTA_PRESETS = {
    "falcon": DeltaGeometry(a=0.060, b=0.1025, c=0.014, d=0.01125, e=0.01125, f=-0.025,
                            r=0.037233758, s=-0.027330909,
                            phi_deg=(105.0, -15.0, -135.0)),
}


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
        self.geometry = geometry = geometry_of(geometry, "delta", DELTA_PRESETS, DeltaGeometry)
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
        """Closure constraints ``g_i(p, q_i)`` [m^2], shape (3,) (class docstring).

        Parameters
        ----------
        p : array_like, shape (3,)
            Effector position [m].
        q : array_like, shape (3,)
            Joint angles [rad].

        Returns
        -------
        ndarray, shape (3,)
            ``g`` per leg [m^2]; zero where ``(p, q)`` is an assembly.
        """
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
            p = joint_angles(p, 3, turn=False)
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
        Q = _joint_batch(Q)
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
        q = joint_angles(q, 3)
        P, ok, Gp, Gq = self._solve_many(q[None])
        if not ok[0]:
            raise KinematicsError(f"no assembly at joints {degrees_text(q)}: the legs' closure "
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
        Q = _joint_batch(Q)
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
            q = joint_angles(q, 3)
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
        # :meth:`_classify`'s tests and solve for one configuration, without its batch's
        # arrays of names (0.17 ms of a loop's 0.26 ms per packet on the Falcon): the
        # same LAPACK calls on the same numbers, so the same bits
        with np.errstate(all="ignore"):
            norms = np.linalg.norm(Gp, axis=1)
            vol = abs(np.linalg.det(Gp / norms[:, None]))
            serial = bool(np.any(np.abs(Gq) < SINGULAR_SINE * norms * g.a))
        if not vol >= SINGULAR_SINE:
            raise KinematicsError(
                f"parallel singularity at joints {degrees_text(q)}: the legs' constraint normals "
                "are coplanar; the effector is not held there", joints=q, kind="parallel")
        if serial:
            i = int(np.argmin(np.abs(Gq) / (norms * g.a)))
            raise KinematicsError(
                f"serial singularity at joints {degrees_text(q)}: leg {i + 1} is stretched "
                "or folded in its plane; the effector cannot move along it",
                joints=q, kind="serial")
        return -np.linalg.solve(Gp, Gq[:, None] * np.eye(3))

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
        return joint_torques(self.jacobian(q), force, 3)
