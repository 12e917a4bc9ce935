"""How far the linear n-D check holds: the linearisation bound at an excitation amplitude.

:mod:`hapsim.analysis.scene_check` linearises a 2-D or 3-D scene felt through its
device at rest. A measurement excites the loop with a handle displacement of amplitude
``a`` [m]; the loop then departs from its linear image by second-order terms, from two
sources:

**The device's kinematics.** A pantograph's or a delta's Cartesian mass depends on where
the handle is: ``M(x) = J(q)^-T M_q J(q)^-1 + m_h I`` with ``q = q(x)``. Over a
displacement ``delta`` it changes by ``dM = (dM/dx . delta) + O(|delta|^2)``, and the
velocity-product (Coriolis and centrifugal) forces ``C(x, v) v``, whose Christoffel
symbols are half-sums of three derivatives of ``M`` (Khatib 1987; Siciliano et al.,
*Robotics*, 2009, Sec. 7.3.2), are at most ``(3/2) |dM/dx| |v|^2``. Relative to the
linear inertial force ``M x''`` (``~ M w^2 a``, and ``|v| ~ w a``) both are first order in
``a``, with the coefficient

    c_kin = (3/2) max_{|e| = 1} || M^-1/2 (dM/dx . e) M^-1/2 ||_2     [1/m]

(``dM/dx . e`` by central differences of ``M(q)`` along the joint direction
``J^-1 e``). The felt matrices' relative error from the kinematics is then
``eps_kin(a) = c_kin a`` to first order: a felt ``k = M |s|^2`` computed with the mass at
rest moves as the mass the loop actually has.

**The scene's Euclidean links and contacts.** The law ``F = K (1 - L/|d|) d`` (rest length
or threshold ``L``) has, about ``d0 = l0 e``, the second-order term
``(1/2) K H[delta, delta]`` with
``H[delta, delta] = (L/l0^2) (2 delta (e . delta) + e |delta|^2 - 3 e (e . delta)^2)``;
its norm is ``K L a^2 / l0^2 * s sqrt(1 + 3 c^2)`` with ``c = e . delta / a``,
``s = sqrt(1 - c^2)``, at most ``(2 / sqrt 3) K L a^2 / l0^2`` (at ``c^2 = 1/3``). Over the
linear term's scale ``K a`` each link contributes

    c_link = L / (sqrt(3) l0^2)     [1/m],

and a contact or plane stays engaged (the law stays smooth) only while ``a`` is below its
depth at rest (``L - l0`` for a contact, the penetration for a plane): beyond it the
loop is piecewise and no linear estimate holds. ``length: 0`` springs and engaged planes
are linear (``c = 0``).

**On the felt matrices.** A relative change ``eps`` of the loop's stiffness and inertia
terms scales each rendered ``s_i^2`` by at most ``1 +- eps``, so it moves ``s_i`` by at
most ``(eps/2) |s_i|`` to first order: the felt stiffness along a principal direction,
``k_i = m_i |s_i|^2``, by at most ``eps k_i``; the felt damping ``b_i = -2 m_i Re s_i`` by
at most ``m_i eps |s_i|``, i.e. ``eps |s_i| / (2 |Re s_i|) = eps / (2 zeta_i)`` relative
(``zeta_i`` the mode's damping ratio: a lightly damped mode's damping is the most
sensitive). The stated bounds are therefore

    eps_k(a) = (c_kin + max c_link) a,     eps_b(a) = eps_k(a) max_i |s_i| / (2 |Re s_i|),

first-order estimates of the relative departure of the felt stiffness and damping
matrices from the linear prediction (not certified: second-order terms in ``a`` are left
out, and the felt matrices' sensitivity is taken from the principal directions').
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from hapsim.outputs import finite_or_none

__all__ = ["LinearisationBound", "linearisation_bound", "kinematic_coefficient",
           "records_excursion", "bound_at_records", "engaged_contacts", "opening_motions"]


def kinematic_coefficient(kind: str, geometry: str, joints, joint_inertia,
                          hand_mass: float = 0.0, *, h: float = 1e-6) -> float:
    """``c_kin`` of a kinematic device at an operating point (module docstring) [1/m].

    Parameters
    ----------
    kind : {"pantograph", "delta"}
    geometry : str
        Preset of :mod:`hapsim.kinematics`.
    joints : array_like, shape (n,)
        Operating point [rad].
    joint_inertia : array_like, shape (n, n)
        ``M_q`` [kg m^2].
    hand_mass : float, optional
        [kg].
    h : float, optional
        Cartesian step of the central differences [m].

    Returns
    -------
    float
        ``(3/2) max_e ||M^-1/2 (dM/dx . e) M^-1/2||_2`` over unit ``e`` [1/m] (the maximum
        over 200 directions per dimension on the unit circle or a Fibonacci sphere; the
        map ``e -> dM/dx . e`` is linear, so its largest normalised value is reached on
        them to the sampling's resolution).

    Raises
    ------
    hapsim.errors.KinematicsError
        A configuration within ``h`` of a singularity or outside the workspace.
    """
    from hapsim.kinematics import cartesian_mass, device
    dev = device(kind, geometry)
    q0 = np.asarray(joints, float)
    n = q0.size
    Mq = np.asarray(joint_inertia, float)

    def mass(q):
        return cartesian_mass(dev.jacobian(q), Mq) + hand_mass * np.eye(n)
    M0 = mass(q0)
    w, V = np.linalg.eigh(M0)
    Wm = V @ np.diag(w ** -0.5) @ V.T
    Ji = np.linalg.inv(dev.jacobian(q0))
    # dM/dx . e is linear in e: the derivative along each Cartesian axis
    D = []
    for i in range(n):
        dq = Ji[:, i] * h
        D.append((mass(q0 + dq) - mass(q0 - dq)) / (2 * h))
    if n == 2:
        t = np.linspace(0, np.pi, 200, endpoint=False)
        E = np.column_stack([np.cos(t), np.sin(t)])
    else:
        k = np.arange(400) + 0.5
        phi = np.arccos(1 - k / 400)             # a hemisphere: e and -e give one norm
        th = np.pi * (1 + 5 ** 0.5) * k
        E = np.column_stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi),
                             np.cos(phi)])
    best = 0.0
    for e in E:
        dM = sum(e[i] * D[i] for i in range(n))
        best = max(best, float(np.max(np.abs(np.linalg.eigvalsh(Wm @ dM @ Wm)))))
    return 1.5 * best


@dataclass(frozen=True)
class LinearisationBound:
    """The linearisation bound of an n-D scene at an excitation amplitude.

    Attributes
    ----------
    amplitude : float
        ``a`` [m].
    kinematic : float
        ``c_kin`` [1/m] (0 for a cartesian device).
    link : float
        ``max c_link`` over the Euclidean links and contacts [1/m] (0 when none).
    link_name : str or None
        The link that sets it.
    depth : float
        The smallest depth at rest of a contact or plane [m] (0 when one is open at
        rest: the check takes it engaged; inf when none).
    depth_name : str or None
        Its name.
    damping_factor : float
        ``max_i |s_i| / (2 |Re s_i|)`` over the rendered poles [-] (nan without them).
    position_scale : float
        The largest coordinate of the scene's rest positions [m] (the masses' ``x0`` and
        the handle's), for :attr:`roundoff` (0 when unknown).
    opening : float
        The records' largest motion toward opening a contact or plane over that one's
        depth at rest [-] (:func:`bound_at_records`: a plane on the handle opens only
        along its normal); nan when no records were looked at: then ``a`` is taken
        against :attr:`depth` in every direction.
    opening_name : str or None
        The contact or plane of :attr:`opening`.
    opening_depth : float
        That one's depth at rest [m] (nan with :attr:`opening`; a plane on several
        masses has a depth for each).
    """

    amplitude: float
    kinematic: float
    link: float
    link_name: str | None
    depth: float
    depth_name: str | None
    damping_factor: float = math.nan
    position_scale: float = 0.0
    opening: float = math.nan
    opening_name: str | None = None
    opening_depth: float = math.nan

    @property
    def opens(self) -> bool:
        """Whether the motion reaches a contact's or a plane's depth (the law is not
        smooth there): :attr:`opening` at least 1 when measured, else ``a`` at least
        :attr:`depth`."""
        if not math.isnan(self.opening):
            return self.opening >= 1.0
        return self.amplitude >= self.depth

    @property
    def roundoff(self) -> float:
        """The binary64 round-off allowed the measured felt matrices, relative to the
        predicted matrix's largest entry [-]: ``100 eps X / a + 10^6 eps`` (``eps`` =
        2^-52, ``X`` = :attr:`position_scale`). The loop runs on absolute positions, so a
        deviation ``a`` from a rest at ``X`` is carried to ``eps X / a`` relative, and the
        fit (a least-squares solve, an eigendecomposition and the inverse eigenvalue
        problem: backward stable, their error a modest multiple of ``eps`` times their
        conditioning) adds its own; the factors leave a margin of about 30 over the
        largest departure measured on exact linear loops (shipped scenes at 1e-8 m: at
        most 1.5 ``eps X / a``; random 2-D and 3-D loops at 1e-3 m: at most 1.1e-11 =
        5e4 ``eps``). An allowance, not a certificate: without it a loop whose
        linearisation bound is 0 (a cartesian device and linear links) would be
        "differs" for its last bits."""
        eps = 2.0 ** -52
        if not (self.amplitude > 0):
            return math.inf
        return 100.0 * eps * self.position_scale / self.amplitude + 1e6 * eps

    @property
    def stiffness(self) -> float:
        """``eps_k(a) = (c_kin + c_link) a`` [-]: the stated relative departure of the felt
        stiffness matrix (module docstring); inf when the motion reaches a contact's or
        a plane's depth (:attr:`opens`: the law is not smooth there)."""
        if self.opens:
            return math.inf
        return (self.kinematic + self.link) * self.amplitude

    @property
    def damping(self) -> float:
        """``eps_b(a) = eps_k(a) max_i |s_i| / (2 |Re s_i|)`` [-] (module docstring)."""
        return self.stiffness * self.damping_factor

    def to_dict(self) -> dict:
        """JSON-ready dict: ``amplitude`` [m], ``kinematic_per_m``, ``link_per_m`` [1/m],
        ``link``, ``contact_depth`` [m] (None when none), ``contact``,
        ``damping_factor``, ``felt_stiffness`` and ``felt_damping`` (the relative bounds;
        None when a contact or plane opens, or without rendered poles), ``roundoff``
        (:attr:`roundoff`, relative), ``opening`` and ``opening_contact``
        (:attr:`opening`, None when not measured).

        Returns
        -------
        dict
            Those keys; ``link`` and ``contact`` the names (or None), non-finite numbers
            None (``amplitude``, ``kinematic_per_m`` and ``link_per_m`` as they are).
        """
        num = finite_or_none
        return {"amplitude": self.amplitude, "kinematic_per_m": self.kinematic,
                "link_per_m": self.link, "link": self.link_name,
                "contact_depth": num(self.depth), "contact": self.depth_name,
                "damping_factor": num(self.damping_factor),
                "felt_stiffness": num(self.stiffness), "felt_damping": num(self.damping),
                "roundoff": num(self.roundoff), "opening": num(self.opening),
                "opening_contact": self.opening_name}


def engaged_contacts(scene):
    """The contacts and planes of a scene with their depth at rest [m] (0: open at rest,
    taken engaged) and, where the handle's motion alone sets it, the motion toward opening
    that one: a callable taking the handle's displacements from rest ``D`` (shape
    (N, n) [m]) to how far each row went toward opening [m] (a plane on the handle:
    ``D . normal``, the penetration ``offset - normal . x`` falling as it grows; a
    contact between the handle and a ground mass: the distance's growth
    ``|x0 + D - c| - l0``, exact); None where other masses move too.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        The scene (its contacts, planes, masses' rest positions and port).

    Yields
    ------
    (str, float, callable or None)
        The contact's or plane's name, its depth at rest [m], the motion toward opening.
    """
    pos = {m.name: m.x0 for m in scene.masses}
    kind = {m.name: m.kind for m in scene.masses}
    port = getattr(scene.port, "name", None)
    for lk in scene.links:
        if lk.kind == "contact":
            l0 = float(np.linalg.norm(pos[lk.m1] - pos[lk.m2]))
            toward = None
            ends = {lk.m1, lk.m2}
            if port in ends and len(ends) == 2:
                other = (ends - {port}).pop()
                if kind[other] == "ground":
                    x0, c = np.asarray(pos[port], float), np.asarray(pos[other], float)
                    toward = (lambda D, x0=x0, c=c, l0=l0:
                              np.linalg.norm(x0 + D - c, axis=1) - l0)
            yield lk.name, max(lk.threshold - l0, 0.0), toward
    for pl in scene.planes:
        for m in pl.masses:
            normal = np.asarray(pl.normal, float)
            yield (pl.name, max(pl.offset - float(normal @ pos[m]), 0.0),
                   (lambda D, normal=normal: D @ normal) if m == port else None)


def linearisation_bound(scene, amplitude: float, rendered_poles=None) -> LinearisationBound:
    """The linearisation bound of a scene felt through its device (module docstring).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device.
    amplitude : float
        Excitation amplitude ``a`` [m] (> 0).
    rendered_poles : array_like of complex, optional
        The rendered poles ``z_i`` of the scene's check (for ``damping_factor``:
        ``s_i = ln(z_i) / T``).

    Returns
    -------
    LinearisationBound

    Raises
    ------
    hapsim.errors.ConfigError
        ``amplitude`` not a positive finite number.
    """
    from hapsim.errors import ConfigError
    a = float(amplitude)
    if not (math.isfinite(a) and a > 0):
        raise ConfigError(f"must be a positive number [m], got {amplitude!r}",
                          key="amplitude")
    dev = scene.device
    c_kin = 0.0
    if dev.joints is not None:
        c_kin = kinematic_coefficient(dev.kind, dev.geometry, dev.joints,
                                      dev.joint_inertia, dev.hand_mass)
    pos = {m.name: m.x0 for m in scene.masses}
    c_link, link_name = 0.0, None
    for lk in scene.links:
        L = lk.threshold if lk.kind == "contact" else lk.length
        if L == 0:
            continue
        l0 = float(np.linalg.norm(pos[lk.m1] - pos[lk.m2]))
        c = L / (math.sqrt(3.0) * l0 * l0)
        if c > c_link:
            c_link, link_name = c, lk.name
    depth, depth_name = math.inf, None
    for name, dep, _ in engaged_contacts(scene):
        if dep < depth:
            depth, depth_name = dep, name
    factor = math.nan
    if rendered_poles is not None and len(rendered_poles):
        sp = np.log(np.asarray(rendered_poles, complex)) * scene.rate_hz
        factor = float(np.max(np.abs(sp) / (2.0 * np.abs(sp.real))))
    scale = max([float(np.max(np.abs(x))) for x in pos.values() if x is not None]
                + [float(np.max(np.abs(dev.position)))])
    return LinearisationBound(amplitude=a, kinematic=c_kin, link=c_link,
                              link_name=link_name, depth=depth, depth_name=depth_name,
                              damping_factor=factor, position_scale=scale)


def records_excursion(records, origin=None, usable=None) -> float:
    """The largest distance from the operating point that the fitted rows of some records
    reach.

    Parameters
    ----------
    records : list of ndarray, each shape (N, n)
        Handle positions [m] (absolute, with ``origin``; or already about the operating
        point). NaN rows (a sample that never came) are skipped.
    origin : array_like, shape (n,), optional
        The operating point [m] (default the origin).
    usable : list of ndarray of bool, each shape (N,), optional
        The rows each record's fit used (default all).

    Returns
    -------
    float
        ``max |x_k - origin|`` over the records' usable, finite rows [m]; 0 when there
        are none.
    """
    top = 0.0
    for j, r in enumerate(records):
        d = np.linalg.norm(np.asarray(r, float)
                           - (0.0 if origin is None else np.asarray(origin, float)), axis=1)
        keep = _rows(r, usable, j)
        if keep.any():
            top = max(top, float(d[keep].max()))
    return top


def bound_at_records(scene, amplitude: float, records, rendered_poles=None, *,
                     origin=None, usable=None, free=None) -> tuple:
    """The linearisation bound at the largest excursion the records reached, never below
    the hand's ``amplitude``; where a known input's response was taken out of them
    (``free``), at the excursion times its ratio to what is left.

    The bound (module docstring) is a statement about motion within ``a`` of the
    operating point, and a contact's law is smooth only while that motion stays within
    its depth. The hand's starts do not bound the motion: a start moving at
    ``a / (10 T)`` carries the handle past ``a`` (2.2 ``a`` on
    ``configs/pantograph_wall.yaml``), and so do a torque held through a host stall and
    a lost byte's garbage torque. The emulated 2DIY's hand once let go at the set-up, and
    its board coasted under no torque through the host's drain before the record's
    first write: 3.6 ``a``, out of the wall (depth 0.5 mm) at ``a`` = 0.3 mm, where a
    bound stated at ``a`` let the felt stiffness fitted on a contact that opened, 5 %
    off the prediction, pass as "within". Every measurement therefore states its bound
    here, at what its records did.

    A known input's response taken out of the records through the linear loop (a late
    tick's held force, :mod:`hapsim.pipeline.felt_port`) leaves its departure from the
    linear loop in them: about ``c ex`` of a motion ``ex``, ``c ex^2`` [m], against the
    free response the fit sees, of ``ex_f``. Relative to that response it is
    ``c ex (ex / ex_f)``: the bound is taken at ``ex^2 / ex_f`` where that is more than
    ``ex``. Host stalls of 4-50 ms before 2 % of the FORCEs on the simulated clock carried
    the 2DIY's wall to 1.4-494 times ``ex_f`` (22 nm), and the felt matrices up to 10.7
    times the bound at ``ex`` off the prediction, 4 runs of 18 beyond it (a fresh-clone
    CI run under the suite's load, 487 late ticks: 2.1 times); taken at ``ex^2 / ex_f``,
    at most 0.10 of it (``tests/test_bound_at_records.py``).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    amplitude : float
        The hand's ``a`` [m] (> 0).
    records : list of ndarray, each shape (N, n)
        As :func:`records_excursion`.
    rendered_poles : array_like of complex, optional
        As :func:`linearisation_bound`.
    origin, usable : optional
        As :func:`records_excursion`.
    free : list of ndarray, each shape (N, n), optional
        The records with the known inputs' response taken out (about the operating
        point, as ``records`` less ``origin``): what the fit sees. None: the records
        themselves.

    Returns
    -------
    (LinearisationBound, float)
        The bound at ``max(amplitude, excursion, excursion^2 / max(amplitude,
        free excursion))`` and the excursion [m].

    Raises
    ------
    hapsim.errors.ConfigError
        As :func:`linearisation_bound`.
    """
    D = [np.asarray(r, float) - (0.0 if origin is None else np.asarray(origin, float))
         for r in records]
    ex = records_excursion(D, None, usable)
    at = max(float(amplitude), ex)
    if free is not None:
        ex_f = max(float(amplitude), records_excursion(free, None, usable))
        at = max(at, ex * ex / ex_f)
    bound = linearisation_bound(scene, at, rendered_poles)
    worst, name, depth = 0.0, None, math.nan
    for nm, dep, toward in opening_motions(scene, D, ex, usable):
        ratio = toward / dep if dep > 0 else math.inf
        if ratio > worst or name is None:
            worst, name, depth = ratio, nm, dep
    if name is None:
        return bound, ex
    return dataclasses.replace(bound, opening=worst, opening_name=name,
                               opening_depth=depth), ex


def opening_motions(scene, displacements, excursion: float, usable=None) -> list:
    """How far records went toward each engaged contact's opening.

    A plane on the handle along its normal, a contact with a ground mass by the
    distance's growth, every other one by the motion's norm, ``excursion`` (the port's
    records do not say how the masses it touches move): :func:`engaged_contacts`.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    displacements : list of ndarray, each shape (N, n)
        The handle's displacements from the operating point [m] (or records'
        differences from the one from rest: the motion they add to it).
    excursion : float
        Their largest norm [m] (:func:`records_excursion`).
    usable : optional
        As :func:`records_excursion`.

    Returns
    -------
    list of (str, float, float)
        Per engaged contact or plane: its name, its depth at rest [m] and the records'
        largest motion toward its opening [m] (>= 0).
    """
    out = []
    for nm, dep, motion in engaged_contacts(scene):
        toward = excursion if motion is None else max(
            [0.0] + [float(np.max(motion(d)[_rows(d, usable, j)], initial=0.0))
                     for j, d in enumerate(displacements)])
        out.append((nm, float(dep), float(toward)))
    return out


def _rows(r, usable, j) -> np.ndarray:
    """The rows of record ``j`` to look at: finite, and usable when said."""
    keep = np.isfinite(np.asarray(r, float)).all(axis=1)
    if usable is not None and usable[j] is not None:
        keep &= np.asarray(usable[j], bool)[:keep.size]
    return keep
