"""The n-DoF loop closed in-process, in lockstep: the n-D engine coupled to the exact
sampled device (the first piece of issue 23's n-DoF mock).

One sample ``n`` (the timing of :mod:`hapsim.analysis.scene_check`, so the analysis's
state matrix is exactly this loop's one-step map for a linear scene):

1. the port is at the device sample ``x_dev[n]``;
2. the engine advances (:class:`hapsim.engine.Engine`), computing the force on the
   port ``F[n]`` from the positions at ``n`` and ``n - 1``;
3. ``F[n]`` enters the delay line; the device holds ``u[n] = F[n-d]`` over the period and
   advances exactly, ``[x, v][n+1] = Ad [x, v][n] + Bd u[n]``
   (:func:`hapsim.analysis.ths.zoh_matrices` of its Cartesian mass and friction).

No protocol and no pseudo-terminal yet: the n-axis device, its mock behind a port, the
hand's excitation and the identification of the felt matrices from a record are what is
left of the n-DoF run.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.ths import MatrixLoop, split_hold_matrices, zoh_matrices
from hapsim.engine import Engine
from hapsim.errors import ConfigError
from hapsim.analysis.felt_matrices import FELT_QUANTITIES, felt_deviation
from hapsim.joint_device import JointDeviceND

__all__ = ["LockstepND", "measure_felt_lockstep", "excitation_starts", "default_samples",
           "identification_plan", "error_responses", "state_responses", "wire_terms_nd",
           "relative_terms", "beyond", "largest_start", "START_MARGIN",
           "exact_differences"]


class LockstepND:
    """An n-D scene felt through its device, closed in-process.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device.
    x0, v0 : array_like, shape (n,), optional
        The device's initial displacement from its rest position [m] and velocity [m/s].
    joint_space : bool, optional
        Integrate a kinematic device's joint-space dynamics (:class:`JointDeviceND`: the
        configuration-dependent inertia and the velocity-product terms) instead of the
        exact ZOH of its Cartesian mass at rest.

    Raises
    ------
    ConfigError
        No port or device; ``x0``/``v0`` not n finite numbers; ``joint_space`` with a
        cartesian device.
    """

    def __init__(self, scene, x0=None, v0=None, joint_space: bool = False) -> None:
        if scene.port is None or scene.device is None:
            raise ConfigError("the lockstep loop needs a port and its device",
                              file=scene.path, key="masses")
        n = scene.dimension
        self.n = n
        dev = scene.device
        lm = MatrixLoop(mass=dev.mass, friction=dev.friction, rate_hz=scene.rate_hz,
                        delay=dev.delay)
        self.Ad, self.Bd = zoh_matrices(lm)
        # a sub-sample delay m + f: the device holds the previous force over the period's
        # first f T (the split hold, hapsim.analysis.ths.split_hold_matrices)
        self.split = float(dev.delay) % 1.0
        if self.split > 0:
            if joint_space:
                raise ConfigError(f"a sub-sample delay ({float(dev.delay):g} periods) is "
                                  "modelled on the Cartesian device; the joint-space model "
                                  "applies whole periods: use a whole delay or the "
                                  "Cartesian model", file=scene.path, key="device.delay")
            _, self._G0, self._G1 = split_hold_matrices(lm)
            self._held = np.zeros(n)
        self.engine = Engine(scene)
        self.rest = dev.position.copy()

        def vec(v, key):
            a = np.zeros(n) if v is None else np.asarray(v, float)
            if a.shape != (n,) or not np.all(np.isfinite(a)):
                raise ConfigError(f"must be {n} finite numbers, got {v!r}", key=key)
            return a
        self.state = np.concatenate([vec(x0, "x0"), vec(v0, "v0")])  # deviation, velocity
        self.delay = np.zeros((int(dev.delay), n))     # F[n-1], ..., F[n-d] (whole d)
        p = self.rest + self.state[:n]
        # the port's previous position: where it was one period ago at the initial velocity
        self.engine.xp[:, self.engine.port] = p - self.state[n:] * scene.period
        self.engine.x[:, self.engine.port] = p
        self.joint = JointDeviceND(scene, p, self.state[n:]) if joint_space else None

    def step(self, samples: int = 1, record: bool = False, *, reading_error=None,
             force_error=None, state_error=None, forces=None):
        """Advance the loop.

        Parameters
        ----------
        samples : int
            Samples to run.
        record : bool, optional
            Return the device positions.
        reading_error : ndarray, shape (samples, n), optional
            An error of the host's reading [m]: at sample ``i`` the engine is given the
            handle at ``x_dev[i] + reading_error[i]``, and the record holds that reading
            (a sensor's or a wire's rounding, observed and fed back through the links).
        force_error : ndarray, shape (samples, n), optional
            A force error [N] added to the force the device holds over sample ``i``
            (a wire's rounding of the force it is sent).
        state_error : ndarray, shape (samples, 2 n), optional
            A change of the device's state ``[x, v]`` [m, m/s] at sample ``i``, before it
            is read: the device really is there (unlike a reading error), e.g. the motion
            over a hold longer or shorter than a period
            (:func:`hapsim.pipeline.haply2_host.hold_bounds`). Cartesian model only.
        forces : ndarray, shape (samples, n), optional
            Filled with the port force the engine computes at each sample [N] (before
            the delay line and ``force_error``).

        Returns
        -------
        ndarray, shape (samples, n) or None
            The device's position deviation ``x_dev[n]`` [m] at each sample, before the
            step, plus ``reading_error`` (when ``record``).

        Raises
        ------
        ConfigError
            ``state_error`` with the joint-space model.
        """
        n = self.n
        out = np.empty((samples, n)) if record else None
        eng = self.engine
        if state_error is not None and self.joint is not None:
            raise ConfigError("a state error is modelled on the Cartesian device only",
                              key="state_error")
        for i in range(int(samples)):
            if state_error is not None:
                self.state = self.state + state_error[i]
            x = self.state[:n]
            if reading_error is not None:
                x = x + reading_error[i]
            if record:
                out[i] = x
            eng.set_port_position(self.rest + x)
            eng.step()
            F = eng.port_force
            if forces is not None:
                forces[i] = F
            if self.delay.shape[0]:
                u = self.delay[-1].copy()
                self.delay[1:] = self.delay[:-1]
                self.delay[0] = F
            else:
                u = F
            if force_error is not None:
                u = u + force_error[i]
            if self.joint is not None:
                self.joint.step(u)
                self.state = np.concatenate([self.joint.position() - self.rest,
                                             np.zeros(n)])
            elif self.split > 0:
                self.state = self.Ad @ self.state + self._G0 @ u + self._G1 @ self._held
                self._held = u
            else:
                self.state = self.Ad @ self.state + self.Bd @ u
        return out


def measure_felt_lockstep(scene, amplitude: float = 1e-8, samples: int | None = None,
                          progress=None, joint_space: bool = False) -> dict:
    """The felt matrices measured from lockstep free responses, against the prediction.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device.
    amplitude : float, optional
        Excitation amplitude ``a`` [m]: record ``i`` starts the handle displaced by
        ``a e_i``, record ``n + i`` moving at ``a / (10 T) e_i`` (``e_i`` the axes).
    samples : int, optional
        Samples per record (default ``max(300, 20 x`` the prediction order ``x n)``).
    progress : callable, optional
        ``progress(done, total)`` after each record.
    joint_space : bool, optional
        The device as :class:`JointDeviceND` (its kinematic nonlinearity in the loop).

    Returns
    -------
    dict
        ``measured`` (:func:`hapsim.analysis.pencil.fit_felt_nd`'s dict of the
        records minus the record from rest, which removes the loop's response to a rest
        that is not exactly an equilibrium: exact for a linear loop), ``predicted``
        (:class:`hapsim.analysis.scene_check.SceneCheckND`), ``deviation`` (the largest
        difference of the felt stiffness and damping matrices, each over the predicted
        matrix's largest entry [-]; None without felt matrices), ``bound``
        (:class:`hapsim.analysis.linearisation.LinearisationBound` at the larger of
        ``a`` and ``excursion``), ``excursion`` (the largest distance [m] of the handle
        from rest over the records: a start moving at ``a / (10 T)`` carries it past
        ``a``), ``order``, ``records``, ``samples``.

    Raises
    ------
    ConfigError
        As :class:`LockstepND`, :func:`hapsim.analysis.scene_check.closed_loop_nd`;
        ``amplitude`` not positive; ``samples`` too short for the order.
    """
    from hapsim.analysis.pencil import fit_felt_nd
    from hapsim.analysis.linearisation import bound_at_records, linearisation_bound
    chk, order, N = identification_plan(scene, samples)
    a = linearisation_bound(scene, amplitude, chk.render.rendered_poles).amplitude
    n = scene.dimension
    T = scene.period
    starts = excitation_starts(n, a, T)[1:]
    rest = LockstepND(scene, joint_space=joint_space).step(N, record=True)
    raw, recs = [rest], []
    for j, (x0, v0) in enumerate(starts):
        r = LockstepND(scene, x0=x0, v0=v0, joint_space=joint_space).step(N, record=True)
        raw.append(r)
        recs.append(r - rest)
        if progress is not None:
            progress(j + 1, len(starts))
    # the bound at the largest excursion the records reached (as over a port): a start
    # moving at a / (10 T) carries the handle past a, and the departure grows with it
    bound, excursion = bound_at_records(scene, a, raw, chk.render.rendered_poles)
    fit = fit_felt_nd(recs, scene.device.mass, T, order)
    dev = felt_deviation(fit, chk)
    return {"measured": fit, "predicted": chk, "deviation": dev, "bound": bound,
            "order": order, "records": len(recs), "samples": N, "excursion": excursion}


def default_samples(order: int, n: int) -> int:
    """Samples per identification record: ``max(300, 20 p n)`` for prediction order
    ``p`` and ``n`` axes (ten times the regression's ``2 p n`` minimum, so the fit is
    overdetermined tenfold).

    Parameters
    ----------
    order : int
        The prediction order ``p``, >= 1.
    n : int
        Axes (or ports: :func:`hapsim.lockstep_ports.measure_felt_ports`).

    Returns
    -------
    int
        Samples per record, >= 300.
    """
    return max(300, 20 * int(order) * int(n))


def excitation_starts(n: int, amplitude: float, period: float) -> list:
    """The initial states of the identification records, the record from rest first.

    Parameters
    ----------
    n : int
        Axes.
    amplitude : float
        ``a`` [m].
    period : float
        Sample period ``T`` [s].

    Returns
    -------
    list of (x0, v0)
        ``2 n + 1`` pairs, each of shape (n,) [m], [m/s]: rest ``(0, 0)``; the handle
        displaced by ``a e_i``; the handle moving at ``a / (10 T) e_i`` (``e_i`` the axes).
        Every mode of the loop is excited by one of them unless it is unobservable from
        the handle (:func:`hapsim.analysis.pencil.fit_felt_nd`).
    """
    z = np.zeros(n)
    e = np.eye(n)
    return ([(z, z)] + [(amplitude * e[i], z) for i in range(n)]
            + [(z, amplitude / (10.0 * period) * e[i]) for i in range(n)])


def exact_differences(scene, amplitude: float, samples: int) -> list:
    """The exact records from the hand's starts, each minus the record from rest
    (:func:`exact_records`).

    Parameters
    ----------
    scene, amplitude, samples
        As :func:`exact_records`.

    Returns
    -------
    list of ndarray
        ``2 n`` arrays of shape (samples, n) [m], the displacement starts first.

    Raises
    ------
    ConfigError
        As :class:`LockstepND`.
    """
    recs = exact_records(scene, amplitude, samples)
    return [r - recs[0] for r in recs[1:]]


def exact_records(scene, amplitude: float, samples: int) -> list:
    """The exact records from rest and from the hand's starts (:class:`LockstepND`, the
    device's own loop, no rounding on any wire): the handle's displacements from the
    operating point.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 2-D or 3-D scene with a port and a device.
    amplitude : float
        The hand's ``a`` [m] (:func:`excitation_starts`).
    samples : int
        Samples per record.

    Returns
    -------
    list of ndarray
        ``2 n + 1`` arrays of shape (samples, n) [m], the one from rest first (it stays
        at 0 when the scene is at rest at its joints, and drifts to the scene's
        equilibrium when it is not).

    Raises
    ------
    ConfigError
        As :class:`LockstepND`.
    """
    return [LockstepND(scene, x0=x0, v0=v0).step(int(samples), record=True)
            for x0, v0 in excitation_starts(scene.dimension, amplitude, scene.period)]


#: The fraction of the start at which the exact records reach a contact's depth or the
#: joints' envelope that a designed start takes (the records' excursion is linear in
#: ``a``; the margin leaves the second-order terms and a real-time run's write timing
#: 10 %: the 2DIY's wall-clock records reach 0.99 of the lockstep ones' excursion,
#: tests/test_haply2_cuts.py).
START_MARGIN = 0.9


def largest_start(scene, samples: int, envelope_rad: float, *,
                  reference: float = 1e-4, records=None) -> tuple:
    """The largest hand start ``a`` whose records stay in the scene's linear range: no
    engaged contact opens and no joint leaves ``envelope_rad`` of its rest, with
    :data:`START_MARGIN`.

    The exact records (:class:`LockstepND`, no rounding, the device's own joint-space
    loop) from the :func:`excitation_starts` at ``reference`` give the motion toward each
    contact's opening (:func:`hapsim.analysis.linearisation.bound_at_records`: a plane
    along its normal, a contact with a ground mass by its distance) and the largest
    excursion; both are linear in ``a`` to first order (the loop linearised at rest), so
    the start at which the first of them reaches its limit is ``reference`` over that
    ratio. The joints' envelope at the handle is ``envelope_rad`` times the smallest
    singular value of the device's Jacobian ``J(q0)`` at rest (``|dq| <= |dx| / s_min``).
    The record from rest's own motion ``r`` counts first: a scene not at rest at its
    joints (its links' and contacts' forces not balanced there) drifts toward its
    equilibrium from every start, so a limit ``L`` allows the start's share
    ``START_MARGIN L - r`` (0 when the drift alone reaches it); at rest ``r`` is the
    round-off (7e-11 m on configs/pantograph_wall.yaml).
    A start moving at ``a / (10 T)`` carries the handle past ``a``: on
    configs/pantograph_wall.yaml 2.19 ``a`` in all (along the wall's tangent) and 1.07
    ``a`` toward the wall's opening, so the start there is 0.84 of the depth (0.42 mm of
    0.5 mm), not 0.9.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 2-D or 3-D scene with a port and a linkage device (``kind``, ``geometry``,
        ``joints`` at rest [rad]).
    samples : int
        Samples per record (:func:`identification_plan`'s ``N``).
    envelope_rad : float
        The largest joint departure from rest the records may make [rad] (> 0).
    reference : float, optional
        The start the exact records are taken at [m] (> 0; any small one: first order).
    records : list of ndarray, optional
        :func:`exact_records` at ``reference`` and ``samples``, when the caller has taken
        them already (not taken again).

    Returns
    -------
    (float, str, float)
        ``a`` [m] (0 when a contact is open at rest, the limit then <= 0, or when the
        record from rest's drift alone reaches the margin), what limits it (``"contact
        NAME"`` or ``"envelope"``) and that limit [m]: the contact's depth at rest or the
        envelope at the handle.

    Raises
    ------
    ConfigError
        A non-positive ``envelope_rad`` or ``reference``; as :class:`LockstepND`.
    """
    from hapsim.analysis.linearisation import opening_motions, records_excursion
    from hapsim.kinematics import device
    if not (envelope_rad > 0 and reference > 0):
        raise ConfigError(f"the envelope ({envelope_rad!r} rad) and the reference start "
                          f"({reference!r} m) must be positive", key="envelope_rad")
    recs = records if records is not None else exact_records(scene, reference, samples)
    rest, diffs = recs[0], [r - recs[0] for r in recs[1:]]
    excursion = records_excursion(diffs)
    opens = opening_motions(scene, diffs, excursion)
    dev = scene.device
    J = device(dev.kind, dev.geometry).jacobian(np.asarray(dev.joints, float))
    env = float(envelope_rad) * float(np.linalg.svd(J, compute_uv=False)[-1])
    shallow = min(opens, key=lambda o: o[1], default=None)    # the first shallowest
    if shallow is not None and shallow[1] <= 0.0:
        return 0.0, f"contact {shallow[0]}", shallow[1]
    # the record from rest's own motion (a scene not at rest at its joints drifts to its
    # equilibrium, whatever the start) comes first; the start's share is linear in a
    drift = records_excursion([rest])
    # entry by entry (a plane on several masses is one entry per mass, one name)
    rest_toward = [t for _, _, t in opening_motions(scene, [rest], drift)]
    best = ((START_MARGIN * env - drift) * reference / excursion, "envelope", env)
    for (nm, dep, toward), r_t in zip(opens, rest_toward, strict=True):
        if toward > 0.0:
            a_c = (START_MARGIN * dep - r_t) * reference / toward
            if a_c < best[0]:
                best = (a_c, f"contact {nm}", dep)
    return max(best[0], 0.0), best[1], float(best[2])


def identification_plan(scene, samples: int | None = None) -> tuple:
    """The prediction, the prediction order and the record length of an identification.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device.
    samples : int, optional
        Samples per record (default :func:`default_samples`).

    Returns
    -------
    (SceneCheckND, int, int)
        :func:`hapsim.analysis.scene_check.check_scene_nd`'s result, the order ``p``
        (the loop's states over n) and the samples per record ``N``.

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.scene_check.check_scene_nd`; ``samples`` fewer than
        the regression's ``2 p n`` unknowns.
    """
    from hapsim.analysis.scene_check import check_scene_nd
    chk = check_scene_nd(scene)
    n = scene.dimension
    order = chk.states // n
    N = int(samples) if samples is not None else default_samples(order, n)
    if N < 2 * order * n:
        raise ConfigError(f"must be at least {2 * order * n} samples for this loop "
                          f"({chk.states} states), got {N}", key="samples")
    return chk, order, N


def error_responses(scene, samples: int, *, size: float = 1e-9) -> tuple:
    """The loop's impulse responses to a reading error and to a force error, per axis.

    The lockstep loop (:class:`LockstepND`) run from rest with a unit error at sample 0
    along each axis, minus the run without it, over the error's size: the record's
    change at each later sample. A reading error is logged (the direct term, the identity
    at sample 0) and fed back through the scene's links as a force; a force error moves
    the device from the next sample. Exact for a linear loop (superposition); for a scene
    with Euclidean links or contacts, the linearisation at rest to ``O(size)`` relative.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device.
    samples : int
        Length ``L`` of the responses.
    size : float, optional
        The error's size [m] or [N] for the runs.

    Returns
    -------
    (ndarray, ndarray)
        Shapes (L, n, n): the response to a reading error [m/m] and to a force error
        [m/N]; ``[t, :, j]`` the record's change at sample ``t`` for a unit error along
        axis ``j`` at sample 0.

    Raises
    ------
    ConfigError
        As :class:`LockstepND`.
    """
    n = scene.dimension
    return _unit_responses(scene, samples, (("reading_error", n, 0, size),
                                            ("force_error", n, 0, size)))


def _unit_responses(scene, samples: int, kinds) -> tuple:
    """The lockstep loop's change, per unit, from a change at sample 0 along each axis:
    for each ``(keyword, width, offset, h)`` of ``kinds``, :meth:`LockstepND.step` with
    ``keyword`` an (L, width) array holding ``h`` at ``[0, offset + j]``, minus the run
    without it, over ``h`` (shape (L, n, n) each, ``[t, :, j]`` for axis ``j``)."""
    n = scene.dimension
    L = int(samples)
    rest = LockstepND(scene).step(L, record=True)
    out = []
    for keyword, width, offset, h in kinds:
        r = np.zeros((L, n, n))
        for j in range(n):
            e = np.zeros((L, width))
            e[0, offset + j] = h
            r[:, :, j] = (LockstepND(scene).step(L, record=True, **{keyword: e})
                          - rest) / h
        out.append(r)
    return tuple(out)


def state_responses(scene, samples: int, *, size: float = 1e-9) -> tuple:
    """The loop's responses to a change of the device's state at sample 0, per axis: of
    its position and of its velocity (:meth:`LockstepND.step`'s ``state_error``).

    As :func:`error_responses`: the lockstep loop from rest with the change, minus the
    run without it, over the change's size (``size`` [m] for a position, ``size / T``
    [m/s] for a velocity: a comparable motion over a period). Unlike a reading error the
    device really moved: the record changes from sample 0 on by the loop's free response
    to the new state. Exact for a linear loop; for a scene with Euclidean links or
    contacts, the linearisation at rest to ``O(size)`` relative.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A validated scene with a port and a device.
    samples : int
        Length ``L`` of the responses.
    size : float, optional
        The position change's size [m] for the runs.

    Returns
    -------
    (ndarray, ndarray)
        Shapes (L, n, n): the response to a position change [m/m] and to a velocity
        change [m/(m/s)]; ``[t, :, j]`` the record's change at sample ``t`` for a unit
        change along axis ``j`` at sample 0.

    Raises
    ------
    ConfigError
        As :class:`LockstepND`.
    """
    n = scene.dimension
    return _unit_responses(scene, samples, (("state_error", 2 * n, 0, size),
                                            ("state_error", 2 * n, n, size / scene.period)))


def wire_terms_nd(scene, diffs, chk, order: int, errors, *, usable=None,
                  mass=None, responses=None, period=None, box: bool = False,
                  settle: float | None = None, sensitivity=None,
                  floor: float | None = None, added=None) -> dict:
    """The wire's term of the stated uncertainty: the first-order worst case of the felt
    matrices' change, as a whole and along each principal direction, under bounded
    errors of the readings and of the forces, and changes of the device's state.

    Each error enters the records through the loop (:func:`error_responses`: a reading
    error is observed and fed back through the links, a force error moves the device;
    :func:`state_responses`: a state change is the device moved),
    and the fit to first order (:func:`hapsim.analysis.pencil.felt_sensitivity_nd`);
    the rest record's errors enter every difference. For a felt entry ``o`` the worst
    case, whatever the errors' signs and correlation, is Hoelder's
    ``sum |(s * H)[o]| bound`` (:func:`hapsim.analysis.pencil.worst_case_nd`). The
    felt stiffness along a unit direction ``e`` is ``e^T k e`` (:func:`felt_directions`),
    a linear form in the entries: its first-order change is the same linear form of
    theirs, ``sum_ab e_a e_b dk_ab``, whose worst case is Hoelder's on the combined
    sensitivity ``sum_ab e_a e_b s[ab]`` (no larger than ``sum_ab |e_a e_b| wc_ab``, and
    smaller where the entries' changes cancel along ``e``); likewise for the damping.
    A rounding of a smooth signal a few counts wide is not white noise, so no
    first-order statistical interval is taken for it (the Falcon's and the 2DIY's
    verdicts draw their rounding through the loop instead,
    :mod:`hapsim.analysis.wire_rounding`, and take this worst case for their other
    errors).

    The fit is so ill-conditioned that errors within the bounds leave the region where
    its first-order sensitivity holds (:mod:`hapsim.analysis.wire_box`): with ``box``
    the worst case stated is the largest of this first-order worst case taken at the
    records and at each statement's worst errors inside the bounds (the mean value
    theorem's bound with its supremum over the error box sampled,
    :func:`hapsim.analysis.wire_box.box_worst_case`); the one at the records alone is
    reported as ``first_order``.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        The scene the records were taken of.
    diffs : sequence of ndarray, each shape (N, n)
        The ``2n`` records minus the record from rest, as fitted [m].
    chk : hapsim.analysis.scene_check.SceneCheckND
        The prediction.
    order : int
        The fit's order.
    errors : sequence of (str, array_like, bounds)
        Each ``(kind, G, bounds)``: ``kind`` ``"reading"`` (an error of the position
        read, [m] at the handle per unit), ``"force"`` (of the force held, [N] at the
        handle per unit), ``"position"`` or ``"velocity"`` (a change of the device's
        state at the sample, [m] or [m/s] at the handle per unit: it moved, e.g. over a
        hold longer or shorter than a period, :func:`state_responses`); ``G`` shape (n, m), the map from the error's ``m``
        coordinates to the handle's (e.g. ``J(q0)`` for joint angles, ``J(q0)^-T`` for
        joint torques, the identity for Cartesian ones); ``bounds`` the errors' bounds in
        those coordinates: shape (m,) for every sample of every record, or a list of
        ``2n + 1`` arrays of shape (N, m) or (m,), the record from rest first.
    usable : sequence of array_like of bool, shape (N,), optional
        Per difference, the rows of its undisturbed stretches, as fitted
        (:func:`hapsim.analysis.pencil.fit_felt_nd`'s ``usable``). An error at any row,
        cut out or not, enters the rows fitted through the loop's response (one that
        ended before a stretch only changes its initial state, which a free response's
        fit hardly sees).
    mass : array_like, shape (n, n), optional
        The felt matrices' mass [kg] (default ``scene.device.mass``; several ports:
        :func:`hapsim.analysis.ports.port_loop`'s).
    responses : tuple of ndarray, optional
        The reading's and the force's :func:`error_responses` (several ports:
        :func:`port_error_responses`); default computed from ``scene``.
    period : float, optional
        The records' sample period [s] (default ``scene.period``; records taken every
        ``D``-th sample: ``D T``, with ``responses`` sampled likewise).
    box : bool, optional
        State the worst case over the error box (above; the 2DIY's measurement) instead
        of the first-order one at the records (default: the first-order term, whose
        callers, the Falcon's feasibility among them, scale it linearly with the
        errors' size).
    settle : float, optional
        With ``box``: stop sampling the box once every statement's relative term exceeds
        ``settle`` (the limit of a statement: which statements are made is then known;
        :func:`hapsim.analysis.wire_box.box_worst_case`'s ``settled``). The terms are
        then lower bounds of the full sampling's and ``box_complete`` is False.
    sensitivity : list of ndarray, optional
        :func:`hapsim.analysis.pencil.felt_sensitivity_nd` of ``diffs`` with this
        ``mass``, period, ``order`` and ``usable``, already computed (not None): taken
        at the records instead of computing it again (a caller stating several error
        kinds of the same records, :func:`hapsim.emulated.falcon_felt.quantiser_terms`).
    floor : float, optional
        :func:`hapsim.analysis.pencil.fit_felt_nd`'s: the fit's pairs the records do not
        determine never taken for rendered ones, at the records and at every point of
        the box (the fit the measurement states must be made with the same ``floor``).
    added : ndarray, shape (2 n^2 + 2 n,), optional
        A worst case of other errors added to each statement's (absolute, this layout:
        :func:`hapsim.analysis.wire_rounding.rounding_term`'s rounding term beside the
        box of the errors that are not rounding).

    Returns
    -------
    dict
        ``felt_stiffness``, ``felt_damping``: the worst case over the entries, over the
        predicted matrix's largest entry [-]; ``directions``: for each of the two, a list
        of n relative terms along the principal directions of :func:`felt_directions`
        (over ``|e_i^T X e_i|``; inf when it is 0); ``first_order``: the same terms at
        the records alone (:func:`relative_terms`); ``box`` True with ``box``;
        ``box_complete`` with ``settle`` (every point of the box sampled). Every
        term inf (``first_order`` None) when the records, or a copy moved within the
        bounds, give no sensitivity (no felt matrices).

    Raises
    ------
    ConfigError
        As :func:`error_responses`; an error ``kind`` not ``"reading"``, ``"force"``,
        ``"position"`` or ``"velocity"``.
    """
    from hapsim.analysis.pencil import felt_sensitivity_nd
    from hapsim.analysis.wire_box import box_worst_case, statement_terms
    r = chk.render
    n = r.dof
    mass = scene.device.mass if mass is None else mass
    inf = {"felt_stiffness": math.inf, "felt_damping": math.inf,
           "directions": {q: [math.inf] * n for q in FELT_QUANTITIES},
           "first_order": None}
    if r.felt_stiffness is None or r.directions is None:
        return inf
    N = int(np.asarray(diffs[0]).shape[0])
    E = np.asarray(r.directions, float)
    kinds = ("reading", "force", "position", "velocity")
    for kind, _, _ in errors:
        if kind not in kinds:
            raise ConfigError(f"an error's kind must be one of {', '.join(kinds)}, got "
                              f"{kind!r}", key="errors")
    resp = dict(zip(kinds[:2], error_responses(scene, N) if responses is None
                    else responses))
    if any(kind in kinds[2:] for kind, _, _ in errors):
        resp.update(zip(kinds[2:], state_responses(scene, N)))
    # per kind: its response through G, and the bounds in the order of ``sens`` (the
    # differences, then the rest record)
    plan = [(resp[kind] @ np.asarray(G, float),
             list(bounds[1:]) + [bounds[0]] if isinstance(bounds, (list, tuple))
             else [bounds] * (len(diffs) + 1)) for kind, G, bounds in errors]

    def terms_at(d, sens=None):
        if sens is None:
            sens = felt_sensitivity_nd(d, mass, scene.period if period is None else period,
                                       order, usable=usable, floor=floor)
        if sens is None:
            return None
        # the rest record's errors enter each difference
        return statement_terms(list(sens) + [-sum(sens)], E, plan)
    plus = 0.0 if added is None else np.asarray(added, float)
    if not box:
        got = terms_at(diffs, sensitivity)
        return inf if got is None else relative_terms(chk, got[0] + plus, got[0])
    settled = None if settle is None else (lambda wc: beyond(chk, wc, settle))
    got = box_worst_case(terms_at, [np.asarray(x, float) for x in diffs], rest_last=True,
                         settled=settled)
    if got is None:
        return {**inf, "box": True} | ({} if settle is None else {"box_complete": True})
    out = {**relative_terms(chk, got[1] + plus, got[0]), "box": True}
    if settle is not None:
        out["box_complete"] = bool(got[2])
    return out


def beyond(chk, wc, limit: float) -> np.ndarray:
    """Per worst case of :func:`wire_terms_nd`'s layout, whether the statement it belongs
    to is beyond ``limit`` (a felt matrix: its largest entry's relative term; a principal
    direction: its own), as :func:`relative_terms` makes them relative.

    Parameters
    ----------
    chk : hapsim.analysis.scene_check.SceneCheckND
        The prediction.
    wc : ndarray, shape (2 n^2 + 2 n,)
        Worst cases in :func:`relative_terms`'s layout.
    limit : float
        The relative limit [-].

    Returns
    -------
    ndarray of bool, shape (2 n^2 + 2 n,)
    """
    rel = relative_terms(chk, wc)
    n = np.asarray(chk.render.felt_stiffness).shape[0]
    out = []
    for q in FELT_QUANTITIES:
        out += [rel[q] > limit] * (n * n)
    for q in FELT_QUANTITIES:
        out += [d > limit for d in rel["directions"][q]]
    return np.asarray(out, bool)


def relative_terms(chk, wc, first=None) -> dict:
    """The wire's relative terms of the felt statements from their worst cases.

    Parameters
    ----------
    chk : hapsim.analysis.scene_check.SceneCheckND
        The prediction (its felt matrices and principal directions ``e_i``).
    wc : ndarray, shape (2 n^2 + 2 n,)
        The worst-case change of the felt stiffness entries [N/m], the damping entries
        [N s/m], then of ``e_i^T k e_i`` and ``e_i^T b e_i`` (:func:`wire_terms_nd`).
    first : ndarray, optional
        The same at first order at the records (reported as ``first_order``).

    Returns
    -------
    dict
        ``felt_stiffness``, ``felt_damping`` (the largest entry's over the predicted
        matrix's largest entry [-]), ``directions`` (per quantity, over
        ``|e_i^T X e_i|``, inf when it is 0) and ``first_order`` (the same dict of
        ``first``, or None).
    """
    r = chk.render
    n = np.asarray(r.felt_stiffness).shape[0]
    E = np.asarray(r.directions, float)
    wc = np.asarray(wc, float)
    out, dirs = {}, {}
    for qi, q in enumerate(FELT_QUANTITIES):
        P = np.asarray(getattr(r, q), float)
        out[q] = float(np.max(wc[qi * n * n:(qi + 1) * n * n]) / np.max(np.abs(P)))
        wd = wc[2 * n * n + qi * n: 2 * n * n + (qi + 1) * n]
        row = []
        for i in range(n):
            p = abs(float(E[:, i] @ P @ E[:, i]))
            row.append(float(wd[i] / p) if p > 0 else math.inf)
        dirs[q] = row
    out["directions"] = dirs
    out["first_order"] = None if first is None else relative_terms(chk, first)
    return out
