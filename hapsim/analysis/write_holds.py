"""The host's write timing on a board that keeps its own time (issue 29, the wrong-verdict
class): each force acts from when the board takes its write to when it takes the next, so
hold ``k`` lasts ``T + delta_k``, not ``T``. The record is then, exactly, the loop of
exact periods with the device's state changed at each sample by the motion over the
hold's excess (:func:`hold_bounds`); the host knows each write's time, so the changes are
estimated with their signs (:func:`hold_corrections`), their motion through the loop is
taken off the record (:func:`hold_motion`) and only what the estimate leaves enters the
stated uncertainty. Dimension-free: the Haply 2DIY's records (n = 2,
:mod:`hapsim.pipeline.haply2_host`) and a 1-D driver's telemetry (n = 1,
:func:`write_time_terms`: the Haply M3) use the same functions.
"""

from __future__ import annotations

import math
import types

import numpy as np

__all__ = ["HOLD_CUT_PERIODS", "VELOCITY_WINDOW", "device_matrices", "hold_bounds", "hold_corrections",
           "hold_motion", "state_change_responses", "write_time_terms"]

#: A hold (the interval between two of the host's writes) more than this many periods
#: off one period is cut from the records on a board that keeps its own time, as a stall
#: is (:func:`hapsim.pipeline.haply2_host.usable_rows`); the smaller departures are corrected and what the correction
#: leaves enters the stated uncertainty (:func:`hold_corrections`). Measured
#: (tools/driver_timing.py, two CPU-bound processes, in-process board): most holds
#: within 10 us of a period, pairs of 100-900 us (one late write) a few times a record.
#: It was 0.1 while each hold entered at its worst case (:func:`hold_bounds`: a kept hold
#: off by 0.5-1.4 ms made the write-timing term of the felt stiffness 4.6 and 9.8 % in two
#: runs); corrected, those cuts were what left correct runs "partly within" (2 of 10: up
#: to 80 of a record's 200 rows cut, the damping's term along one direction over 0.25
#: without any write-timing term). Half a period: the host's loop re-times itself
#: when that far behind (:func:`hapsim.pipeline.haply2_record.record_realtime`), and a hold of 500 us is still corrected to
#: within its remainder's bound (``tests/test_haply2_writetime.py``).
HOLD_CUT_PERIODS = 0.5
#: The half-width of the window of readings a 1-D run's velocity at a write is estimated
#: from (:func:`hold_corrections`' ``window``, :func:`write_time_terms`) [rows]. From a
#: hold's two readings the encoder's rounding (half a count over a period) was the
#: correction's largest error on the Haply M3 (4880 counts per revolution): its share of
#: the stated uncertainty of k 70 times the uncorrected run's whole uncertainty over
#: random loops (``tests/test_haply_writetime.py``'s); over 2m + 1 readings the
#: rounding's gain falls as ``1 / m`` while the friction's remainder,
#: ``|M^-1 B| V tau^2 / 2``, grows as ``m^2``: m = 4 left the uncertainty 10 times the
#: uncorrected one, m = 8 8 times with the largest hold's departure in every window's
#: bound, 1.1-1.2 times with each window's own (``configs/haply.yaml`` in real time).
VELOCITY_WINDOW = 8


def hold_bounds(rec: dict, scene, J, delta, *, latency_s: float = 0.0) -> dict:
    """How far each hold's length moved the device: the bounds of the state changes that
    the host's real write times add to the loop of exact periods (issue 29: the host's
    write-timing term of the stated uncertainty).

    The board takes write ``k`` at ``s_k`` and, in the same pass, reads the encoders
    (row ``k``'s sample, ``x(s_k)``) and sets the torques, held until it takes the next
    (firmware V1.5, ``.ino`` lines 77 and 89; :class:`hapsim.emulated.haply2_board.
    Haply2DIYBoard`). The loop predicted holds each torque exactly ``T``; over the
    real hold ``h_k = s_k - s_(k-1) = T + delta_k`` the device's state ``z = [x, v]``
    reaches ``z(s_(k-1) + T)`` and then moves on by
    ``w_k = integral of dz/dt from s_(k-1) + T to s_k`` under the same torque (for
    ``delta_k < 0``, minus that motion continued). So the record is, exactly, the loop
    of exact periods with the state changed by ``w_k`` at each sample ``k``: a change of
    the device's state that the loop then carries (:func:`hapsim.lockstep.state_responses`),
    with ``|w_k,x| <= |delta_k| v_k`` and ``|w_k,v| <= |delta_k| a_k`` (the mean value
    bound), ``v_k``, ``a_k`` bounds of the handle's speed and acceleration within
    ``|delta_k|`` of ``s_k``. A hold's start and end shifted together (a constant
    latency) change nothing: only the lengths count.

    ``delta_k`` from the host's clock: write ``k`` began at ``b_k`` (``rec["write_s"]``,
    its first column), and the board took it a latency after that is constant up to
    ``latency_s`` (an in-process board is fed inside the write, at its start; over a
    port the latency is the write call's, the link's and the board's next pass, which
    the host cannot see: the verdict's fallback, :func:`measure_felt_haply2_port`):
    ``|delta_k| <= |b_k - b_(k-1) - T| + latency_s``.
    Speed: over hold ``k`` the mean velocity is ``(x_k - x_(k-1)) / h_k`` and no
    instant within ``|delta_k|`` of it departs from it by more than
    ``a_max (h_k + |delta_k|)``, so ``v_k = (|x_k - x_(k-1)| + 2 |eps|) / h_lo
    + a_max (T + 2 |delta_k|)`` (``h_lo = b_k - b_(k-1) - latency_s`` the hold's
    shortest length, ``eps`` the readings' rounding through ``J``; where a reading is
    missing, the record's largest speed bound). Acceleration:
    ``a_k = (|F_k| + b_max v_k) / m_min``, ``F_k = J^-T tau`` of the torque held over
    hold ``k`` (row ``k - 2``'s, written with write ``k - 1``), ``m_min``, ``b_max`` the
    Cartesian mass's and friction's extreme eigenvalues at rest, ``a_max`` its largest
    over the record (as :func:`hapsim.pipeline.haply2_host.estimate_bounds`: no hand on the handle, the
    velocity-product terms left out). Each axis is bounded by the norm.

    Parameters
    ----------
    rec : dict
        :func:`hapsim.pipeline.haply2_record.record_realtime`'s record: ``write_s`` (N, 2) [s], ``position`` (N, 2)
        [m], ``torque`` (N, 2) [N m], optionally ``readings`` (N, 2) [m].
    scene : hapsim.scene.SceneND
        The scene (its period ``T``, the device's mass and friction at rest).
    J : ndarray, shape (2, 2)
        The Jacobian at rest [m/rad].
    delta : array_like, shape (2,)
        The readings' rounding per joint [rad].
    latency_s : float, optional
        How much the link's latency may vary between two writes [s] (0: constant).

    Returns
    -------
    dict
        ``delta`` (N,) the bound of ``|delta_k|`` [s] (0 at row 0, the record's start),
        ``position`` (N, 2) [m] and ``velocity`` (N, 2) [m/s]: the bounds of ``w_k``
        per axis. All 0 where the writes were exactly ``T`` apart.

    See Also
    --------
    hold_corrections : the same changes estimated with their signs (the measurement's
        correction), this worst case kept where a change is not estimated.
    """
    T = scene.period
    w = np.asarray(rec["write_s"], float)
    N = w.shape[0]
    dl = np.zeros(N)
    if N > 1:
        dl[1:] = np.abs(np.diff(w[:, 0]) - T) + float(latency_s)
    dl = np.where(np.isfinite(dl), dl, np.inf)
    n = np.asarray(J).shape[0]
    out = {"delta": dl, "position": np.zeros((N, n)), "velocity": np.zeros((N, n))}
    if not np.any(dl):
        return out
    eps = float(np.linalg.norm(np.abs(J) @ np.asarray(delta, float)))
    x = np.asarray(rec.get("readings", rec["position"]), float)
    Md, Bd = device_matrices(scene)
    m_min = float(np.min(np.linalg.eigvalsh(Md)))
    b_max = float(np.max(np.abs(np.linalg.eigvalsh(0.5 * (Bd + Bd.T)))))
    F = np.linalg.norm(np.linalg.solve(J.T, np.asarray(rec["torque"], float).T).T, axis=1)
    Fk = np.zeros(N)                                  # the force held over hold k
    Fk[2:] = F[:N - 2]
    step = np.full(N, np.nan)
    step[1:] = np.linalg.norm(np.diff(x, axis=0), axis=1)
    h_lo = np.full(N, T)                              # the hold's shortest length
    h_lo[1:] = np.maximum(np.diff(w[:, 0]) - float(latency_s), 1e-6 * T)
    mean = (step + 2 * eps) / h_lo
    v_rec = float(np.nanmax(mean)) if np.isfinite(mean).any() else 0.0
    mean = np.where(np.isfinite(mean), mean, v_rec)
    a_max = (float(np.max(F, initial=0.0)) + b_max * v_rec) / m_min
    v = mean + a_max * (T + 2 * np.where(np.isfinite(dl), dl, 0.0))
    a = (Fk + b_max * v) / m_min
    pos = np.where(np.isinf(dl), np.inf, dl * v)
    vel = np.where(np.isinf(dl), np.inf, dl * a)
    pos[0] = vel[0] = 0.0
    out["position"] = np.repeat(pos[:, None], n, axis=1)
    out["velocity"] = np.repeat(vel[:, None], n, axis=1)
    return out


def hold_corrections(rec: dict, scene, J, delta, *, latency_s: float = 0.0,
                     first_torque=None, rounding_apart: bool = False,
                     window: int = 0) -> dict:
    """The state changes the host's write timing made, estimated from the record with
    their signs, and the bounds of what that estimate leaves (issue 29: the known holds
    corrected, only the remainder in the stated uncertainty).

    :func:`hold_bounds` bounds each hold's state change ``w_k`` whatever its sign; but the
    host knows each hold's departure ``delta_k`` with its sign, from its write times
    (``delta_hat_k = b_k - b_(k-1) - T``, ``|delta_k - delta_hat_k| <= L``, ``L`` =
    ``latency_s`` the variation of the latency the host cannot see), and the device's
    velocity and acceleration at each sample from the readings and the force held. The
    device (Cartesian mass ``M``, friction ``B`` at rest; no hand on the handle in a free
    response; the velocity-product terms, second order in the amplitude, left out as
    in :func:`hapsim.pipeline.haply2_host.estimate_bounds`) under the force ``F_k = J^-T tau`` held constant over
    hold ``k`` (row ``k - 2``'s torque) moves, with ``a(t) = M^-1 (F_k - B v(t))``:

    * over the hold ``h_k``, by Taylor's theorem with the integral remainder,
      ``x_k - x_(k-1) = h v_k - h^2/2 a_k - R``, ``a_k = M^-1 (F_k - B v_k)`` the
      acceleration just before ``s_k`` and ``|R| <= |M^-1 B| a_max h^3 / 6``
      (``|a(t) - a_k| <= |M^-1 B| a_max |t - s_k|``), so
      ``(I + h/2 M^-1 B) v_k = (x_k - x_(k-1)) / h + h/2 M^-1 F_k + R / h``;
      the estimate ``v_hat`` solves this with ``R = 0``, the readings and ``h_hat``;
    * over the departure (as :func:`hold_bounds`: the motion from ``s_k - delta_k`` to
      ``s_k``, for ``delta_k < 0`` minus the motion continued under ``F_k``),
      ``w_x = delta v_k - delta^2/2 a_k + R_x``, ``|R_x| <= |M^-1 B| a_max |delta|^3/6``,
      and ``w_v = delta a_k + R_v``, ``|R_v| <= |M^-1 B| a_max delta^2 / 2``; the
      estimate ``w_hat = [delta_hat v_hat - delta_hat^2/2 a_hat, delta_hat a_hat]``,
      ``a_hat = M^-1 (F_k - B v_hat)``.

    The remainder's bounds, with ``D = |delta_hat| + L``, ``h_lo``/``h_hi`` =
    ``h_hat -/+ L``, ``c = 1 / (1 - h_hi |M^-1 B| / 2)`` (a bound of
    ``|(I + h/2 M^-1 B)^-1|``), ``eps`` the readings' rounding through ``J``,
    ``e_F = 2^-24 |J^-T| |tau|`` (the torque's float32), ``V_k`` =
    ``(|x_k - x_(k-1)| + 2 eps) / h_lo + a_max h_hi`` (a bound of ``|v_k|``):

    * ``|v_hat - v_k| <= e_v = c (2 eps / h_lo + |M^-1 B| a_max h_hi^2 / 6
      + h_hi/2 |M^-1| e_F) + L c ((|x_k - x_(k-1)| + 2 eps) / h_lo^2 + |M^-1 F_k| / 2)
      + L c^2 |M^-1 B| V_k / 2`` (the readings, ``R``, the torque, and ``h`` known only
      to ``L``: the derivative of the solution over ``h``);
    * ``|a_hat - a_k| <= e_a = |M^-1| e_F + |M^-1 B| e_v``;
    * ``|w_x - w_hat_x| <= D e_v + L |v_hat| + D^2/2 e_a + L (2 |delta_hat| + L)/2
      |a_hat| + |M^-1 B| a_max D^3 / 6``;
    * ``|w_v - w_hat_v| <= D e_a + L |a_hat| + |M^-1 B| a_max D^2 / 2``.

    ``a_max`` is :func:`hold_bounds`'s bound of the acceleration over the record; each
    axis is bounded by the norm. A row without both readings (an estimated or damaged
    sample), row 1 without ``first_torque`` (the torque held over the first hold, written
    with row 0's write, is not in the record), a hold with ``c`` not finite, or a hold
    not finite is not corrected: its ``w_hat`` is 0 and its bound :func:`hold_bounds`'s.
    With writes exactly ``T`` apart and ``L = 0`` everything is 0 (the record is left as
    it is). Not in the bound: the mass and the Jacobian changing with the configuration
    over the record's excursion (first order in the amplitude, as the velocity-product
    terms; the linearisation bound's part of the uncertainty), and a board other than
    the scene's (a wrong loop: its correction is off by the departure times the holds'
    effect, second order, as the wire's other terms computed on the predicted loop).

    Parameters
    ----------
    rec : dict
        As :func:`hold_bounds` (``write_s``, ``position``, ``torque``, optionally
        ``readings``: used, uncorrected, for the velocities).
    scene : hapsim.scene.SceneND
    J : ndarray, shape (2, 2)
        The Jacobian at rest [m/rad].
    delta : array_like, shape (2,)
        The readings' rounding per joint [rad].
    latency_s : float, optional
        ``L`` [s] (0: the latency constant).
    first_torque : array_like, shape (2,), optional
        The torque row 0's write carried [N m], held over the first hold:
        :func:`hapsim.pipeline.haply2_record.record_realtime`'s row 0 is the arming's zero write (0, 0), whose reply is
        sample 0. Without it, row 1 is not corrected.
    rounding_apart : bool, optional
        Leave the readings' rounding out of the remainder's bounds (``e_v``'s
        ``2 eps / h_lo``) and return, per row, its gains instead (``rounding_gain``): the
        remainder's change per unit error of the difference of the two readings,
        ``c D / h_lo (1 + D |M^-1 B| / 2)`` in position and ``c D |M^-1 B| / h_lo`` in
        velocity, for a caller that states the sensor's rounding as a random error
        (the 1-D measurement, :func:`write_time_terms`). False: in the bounds (the 2DIY).
        The gains are standard-deviation multipliers: a reading error of sd ``s``, independent
        from row to row, makes the remainders no larger than white noise of sd
        ``max(gain) s`` through the loop (Cauchy-Schwarz over the rows that share a
        reading).
    window : int, optional
        0 (the default): ``v_hat`` from the hold's two readings, as above. ``m > 0``: from
        the readings of rows ``k - m .. k + m`` (those read, in a stretch of holds within
        :data:`HOLD_CUT_PERIODS` of a period): the motion the known forces made from
        ``s_k`` (constant over each hold, ``M^-1 F`` double-integrated over the host's
        write times) taken off, a straight line ``x_k + v (t - s_k)`` fitted by least
        squares (weights ``c_j``, ``sum c_j = 0``); what the fit leaves is the friction's
        part of the motion, at most ``|M^-1 B| V tau^2 / 2`` at ``tau = s_j - s_k``, so
        ``e_v = |M^-1 B| V S2 / 2 + |M^-1| e_F S2 / 2 + eps S1 + 2 L S1 (V + a_max
        tau_max)`` with ``S1 = sum |c_j|``, ``S2 = sum |c_j| tau_j^2`` (the rounding's
        ``eps S1`` apart with ``rounding_apart``: the gains per reading ``j``,
        ``sqrt((2 m + 1) sum_k G_k^2 c_kj^2)`` over the windows ``k`` that hold it,
        ``G_k`` the remainder's factor ``D (1 + D |M^-1 B| / 2)`` or ``D |M^-1 B|``: by
        Cauchy-Schwarz, ``sum_j (sum_k G_k c_kj u_k)^2 <= max_j (sum_k G_k^2 c_kj^2)
        (2 m + 1) sum_k u_k^2`` for any sensitivity ``u`` of the fit through the loop).
        The rounding's share falls as ``m^-1.5``: from adjacent readings it was the
        correction's largest error on a 1-D joint read to a few thousand counts.

    Returns
    -------
    dict
        ``delta`` (N,) [s], as :func:`hold_bounds`'s; ``state`` (N, 4): ``w_hat``
        ``[x, v]`` [m, m/s] per row (:meth:`hapsim.lockstep.LockstepND.step`'s
        ``state_error``); ``position`` (N, 2) [m] and ``velocity`` (N, 2) [m/s]: the
        bounds of ``w - w_hat`` per axis; ``corrected`` (N,) bool.
    """
    out, su = _hold_setup(rec, scene, J, delta, latency_s=latency_s,
                           first_torque=first_torque, rounding_apart=rounding_apart)
    if su is None:
        return out
    N, b, L = su.N, su.b, su.L
    pos, vel = out["position"].copy(), out["velocity"].copy()
    ks = np.arange(1 if first_torque is not None else 2, N)
    dX = np.diff(su.x, axis=0)            # row k - 1: x[k] - x[k - 1]
    h = b[ks] - b[ks - 1]
    good = (np.isfinite(dX).all(axis=1)[ks - 1] & np.isfinite(h)
            & np.isfinite(out["delta"])[ks] & (h - L > 0) & ((h + L) * su.nMiB < 2))
    ks, h = ks[good], h[good]
    if ks.size:
        rows = _corrected_rows(su, ks, h, dX[ks - 1], window=window,
                               rounding_apart=rounding_apart)
        out["state"][ks] = rows["state"]
        out["corrected"][ks] = True
        pos[ks] = rows["pos"][:, None]
        vel[ks] = rows["vel"][:, None]
        if rounding_apart and window:
            # per reading, the squared weights of the windows that hold it (docstring; a
            # hold further off is cut, :func:`write_time_terms`: its change not used),
            # summed over the windows in the order of their rows
            acc = np.zeros((N, 2))
            np.add.at(acc, rows["acc_rows"], rows["acc_terms"])
            out["rounding_gain"] = np.sqrt((2 * window + 1) * acc)
        elif rounding_apart:
            out["rounding_gain"][ks] = rows["gain"]
    elif rounding_apart and window:
        out["rounding_gain"] = np.sqrt((2 * window + 1) * np.zeros((N, 2)))
    out["position"], out["velocity"] = pos, vel
    return out


def _hold_setup(rec: dict, scene, J, delta, *, latency_s: float = 0.0, first_torque=None,
                rounding_apart: bool = False):
    """What :func:`hold_corrections` computes before its rows (the same arguments): its
    output with :func:`hold_bounds`' bounds and nothing corrected yet, and the record's
    quantities its rows read.

    Parameters
    ----------
    rec, scene, J, delta, latency_s, first_torque, rounding_apart
        As :func:`hold_corrections`.

    Returns
    -------
    (dict, types.SimpleNamespace or None)
        The output so far; ``T``, ``L``, ``N``, ``b`` (the write times, (N,)), ``x``
        (the readings, (N, n)), ``Mi``, ``B``, ``MiB``, ``nMi``, ``nMiB``, ``eps``,
        ``Fall``, ``eFall`` (the force held over each hold and its float32 error,
        (N + 1, n) and (N + 1,)), ``a_max`` and ``ok_hold`` ((N,) bool), as the
        docstring of :func:`hold_corrections` names them; None when no hold departs
        from a period (nothing to correct).
    """
    T = scene.period
    L = float(latency_s)
    out = hold_bounds(rec, scene, J, delta, latency_s=L)
    N = len(out["delta"])
    n = np.asarray(J).shape[0]
    out["state"] = np.zeros((N, 2 * n))
    out["corrected"] = np.zeros(N, bool)
    if rounding_apart:
        out["rounding_gain"] = np.zeros((N, 2))
    if not np.any(out["delta"]):
        return out, None
    b = np.asarray(rec["write_s"], float)[:, 0]
    x = np.asarray(rec.get("readings", rec["position"]), float)
    M, B = device_matrices(scene)
    Mi = np.linalg.inv(M)
    MiB = Mi @ B
    nMi, nMiB = float(np.linalg.norm(Mi, 2)), float(np.linalg.norm(MiB, 2))
    eps = float(np.linalg.norm(np.abs(J) @ np.asarray(delta, float)))
    tau = np.asarray(rec["torque"], float)
    Fall = np.linalg.solve(J.T, tau.T).T
    eFall = 2.0 ** -24 * np.linalg.norm(np.abs(np.linalg.inv(J.T)) @ np.abs(tau).T, axis=0)
    # the force held over hold k is row k - 1's of these (row k - 2's torque; row -1:
    # the torque of row 0's write)
    Fall = np.vstack([np.zeros((1, n)) if first_torque is None else
                      np.linalg.solve(J.T, np.asarray(first_torque, float)), Fall])
    eFall = np.concatenate([[0.0 if first_torque is None else 2.0 ** -24 * float(
        np.linalg.norm(np.abs(np.linalg.inv(J.T)) @ np.abs(np.asarray(first_torque, float))))],
        eFall])
    # a_max as hold_bounds's: the force's largest, the record's largest speed bound
    m_min = float(np.min(np.linalg.eigvalsh(M)))
    b_max = float(np.max(np.abs(np.linalg.eigvalsh(0.5 * (B + B.T)))))
    steps = np.linalg.norm(np.diff(x, axis=0), axis=1)
    h_all = np.maximum(np.diff(b) - L, 1e-6 * T)
    mean = (steps + 2 * eps) / h_all
    v_rec = float(np.nanmax(mean)) if np.isfinite(mean).any() else 0.0
    a_max = (float(np.max(np.linalg.norm(Fall, axis=1), initial=0.0)) + b_max * v_rec) / m_min
    ok_hold = np.zeros(N, bool)           # hold i (s_(i-1) .. s_i) known and near a period
    ok_hold[1 if first_torque is not None else 2:] = True
    ok_hold[1:] &= np.abs(np.diff(b) - T) <= HOLD_CUT_PERIODS * T
    read = np.isfinite(x).all(axis=1)
    ok_hold[1:] &= read[1:] & read[:-1]
    ok_hold[0] = False
    return out, types.SimpleNamespace(T=T, L=L, N=N, b=b, x=x, Mi=Mi, B=B, MiB=MiB, nMi=nMi,
                                      nMiB=nMiB, eps=eps, Fall=Fall, eFall=eFall,
                                      a_max=a_max, ok_hold=ok_hold)


def _rows_matvec(A, X):
    """``A @ X[i]`` for every row ``i`` of ``X`` (shape (K, n); ``A`` (n, n) or (K, n, n)),
    each product as numpy forms the one of a matrix and a vector (the same BLAS call per
    row: the same numbers, bit for bit)."""
    return np.matmul(A, X[:, :, None])[:, :, 0]


def _rows_dot(X, Y):
    """``X[i].dot(Y[i])`` for every row, each as numpy forms a vector's dot product."""
    return np.matmul(X[:, None, :], Y[:, :, None])[:, 0, 0]


def _scalar_pow(v, e):
    """``v[i] ** e`` as a binary64 scalar's power is (``pow``), elementwise (an array's
    ``** 2`` is a square instead)."""
    return np.array([t ** e for t in v], float)


def _corrected_rows(su, ks, h, dx, *, window, rounding_apart):
    """:func:`hold_corrections`' estimate and bounds on the rows ``ks`` it corrects (``su``
    its set-up, :func:`_hold_setup`; ``h`` the rows' holds, ``dx`` their readings'
    differences), all rows at once: each row's operations those of its docstring in the order written there
    (elementwise, and numpy's own matrix-vector products, dot products, solves and
    reductions row by row: the numbers of a loop over the rows, bit for bit). The
    windows of all ``2 m + 1`` readings are fitted together; the shorter ones (at a
    record's ends and its cuts) by :func:`_window_velocity`.

    Returns
    -------
    dict
        ``state`` (K, 2 n), ``pos`` and ``vel`` (K,); with ``rounding_apart`` and a
        window, ``acc_rows`` (M,) and ``acc_terms`` (M, 2), each window's readings' rows
        and squared weights in the order of the rows ``ks``; with ``rounding_apart``
        alone, ``gain`` (K, 2).
    """
    T, L, b, x, ok_hold = su.T, su.L, su.b, su.x, su.ok_hold
    Mi, B, MiB, nMi, nMiB, eps, a_max = su.Mi, su.B, su.MiB, su.nMi, su.nMiB, su.eps, su.a_max
    F, eF = su.Fall[ks - 1], su.eFall[ks - 1]
    eF_max = float(np.max(su.eFall)) if window else 0.0
    QV = _known_motion(b, su.Fall, Mi) if window else None
    K, n = dx.shape
    dh = h - T
    h_lo, h_hi = h - L, h + L
    c = 1.0 / (1.0 - h_hi * nMiB / 2)
    MiF = _rows_matvec(Mi, F)
    ndx = np.sqrt(_rows_dot(dx, dx))
    V = (ndx + 2 * eps) / h_lo + a_max * h_hi
    v_hat = np.empty((K, n))
    fitted = np.zeros(K, bool)
    sc1, sc2, sq, tmax = np.zeros(K), np.zeros(K), np.zeros(K), np.zeros(K)
    lo = ks - 1
    cws = [None] * K
    if window:
        m = int(window)
        N = len(b)
        bad = np.concatenate(([0], np.cumsum(~np.asarray(ok_hold, bool))))
        # a whole window: ok_hold on rows k - m + 1 .. k + m, rows k - m .. k + m there
        inside = (ks - m >= 0) & (ks + m <= N - 1)
        full = np.zeros(K, bool)
        kin = ks[inside]
        full[inside] = bad[kin + m + 1] - bad[kin - m + 1] == 0
        f = np.flatnonzero(full)
        if f.size:
            kf = ks[f]
            idx = kf[:, None] + np.arange(-m, m + 1)
            Q, Vq = QV
            tau = b[idx] - b[kf][:, None]
            y = x[idx] - (Q[idx] - Q[kf][:, None, :] - tau[:, :, None] * Vq[kf][:, None, :])
            tc = tau - (np.add.reduce(tau, axis=1) / (2 * m + 1))[:, None]
            cf = tc / _rows_dot(tc, tc)[:, None]
            ac = np.abs(cf)
            v_hat[f] = np.matmul(cf[:, None, :], y)[:, 0, :]
            sc1[f] = np.add.reduce(ac, axis=1)
            sc2[f] = _rows_dot(ac, tau ** 2)
            sq[f] = np.sqrt(_rows_dot(cf, cf))
            tmax[f] = np.maximum.reduce(np.abs(tau), axis=1)
            fitted[f] = True
            lo[f] = kf - m
            for i, r in zip(f, cf):
                cws[i] = r
        for i in np.flatnonzero(~full):
            fit = _window_velocity(int(ks[i]), m, b, x, QV, ok_hold)
            if fit is not None:
                v_hat[i], sc1[i], sc2[i], sq[i], tmax[i], lo[i], cws[i] = fit
                fitted[i] = True
    s = ~fitted                           # the hold's two readings: the solve
    if s.any():
        hs = h[s]
        A = np.eye(n) + (hs / 2)[:, None, None] * MiB
        rhs = dx[s] / hs[:, None] + (hs / 2)[:, None] * MiF[s]
        v_hat[s] = np.linalg.solve(A, rhs[:, :, None])[:, :, 0]
    nMiF = np.sqrt(_rows_dot(MiF, MiF))
    e_v = np.where(
        fitted,
        nMiB * V * sc2 / 2 + nMi * eF_max * sc2 / 2 + (0.0 if rounding_apart else eps * sc1)
        + 2 * L * sc1 * (V + a_max * tmax),
        c * ((0.0 if rounding_apart else 2 * eps / h_lo)
             + nMiB * a_max * _scalar_pow(h_hi, 2) / 6 + h_hi / 2 * nMi * eF)
        + L * c * ((ndx + 2 * eps) / _scalar_pow(h_lo, 2) + nMiF / 2)
        + L * c * c * nMiB * V / 2)
    # the rounding's gain on v_hat (sd multiplier)
    g_r = np.where(fitted, sq * np.sqrt(2 * window + 1), 2 * c / h_lo)
    a_hat = _rows_matvec(Mi, F - _rows_matvec(B, v_hat))
    out = {"state": np.concatenate([dh[:, None] * v_hat - (dh * dh / 2)[:, None] * a_hat,
                                    dh[:, None] * a_hat], axis=1)}
    e_a = nMi * eF + nMiB * e_v
    D = np.abs(dh) + L
    nv, na = np.sqrt(_rows_dot(v_hat, v_hat)), np.sqrt(_rows_dot(a_hat, a_hat))
    out["pos"] = (D * e_v + L * nv + D * D / 2 * e_a + L * (2 * np.abs(dh) + L) / 2 * na
                  + nMiB * a_max * _scalar_pow(D, 3) / 6)
    out["vel"] = D * e_a + L * na + nMiB * a_max * D * D / 2
    if rounding_apart and window:
        G2 = np.stack([D * (1 + D * nMiB / 2), D * nMiB], axis=1) ** 2
        rows_, terms = [], []
        for i in np.flatnonzero(np.abs(dh) <= HOLD_CUT_PERIODS * T):
            cw = cws[i] if cws[i] is not None else np.array([-c[i] / h_lo[i],
                                                             c[i] / h_lo[i]])
            rows_.append(np.arange(lo[i], lo[i] + cw.size))
            terms.append(np.multiply.outer(cw * cw, G2[i]))
        out["acc_rows"] = np.concatenate(rows_) if rows_ else np.zeros(0, int)
        out["acc_terms"] = np.concatenate(terms) if terms else np.zeros((0, 2))
    elif rounding_apart:
        out["gain"] = np.stack([g_r * D * (1 + D * nMiB / 2), g_r * D * nMiB], axis=1)
    return out


def _known_motion(b, Fall, Mi):
    """The motion the known forces alone make, from ``s_0``, at each write: ``Q`` [m]
    and ``V`` [m/s] (N, n), each hold's ``M^-1 F`` integrated exactly over its length
    (a hold not finite counts 0: no window crosses it)."""
    dt = np.diff(b)
    dt = np.where(np.isfinite(dt), dt, 0.0)[:, None]
    N = len(b)
    A = (Mi @ np.asarray(Fall[:N - 1], float).T).T         # hold i's: Fall[i - 1]
    n = A.shape[1]
    V, Q = np.zeros((N, n)), np.zeros((N, n))
    V[1:] = np.cumsum(A * dt, axis=0)
    Q[1:] = np.cumsum(V[:-1] * dt + A * dt * dt / 2, axis=0)
    return Q, V


def _window_velocity(k: int, m: int, b, x, QV, ok_hold):
    """:func:`hold_corrections`' velocity at ``s_k`` from the readings of rows
    ``k - m .. k + m`` (its ``window``): ``(v_hat, S1, S2, sqrt(sum c_j^2), tau_max,
    first row, c)``, or
    None with fewer than three readings. The window stops at a hold not ``ok_hold`` (far
    off a period, its force unknown, a reading missing at its end); the known forces'
    motion from ``s_k`` is ``Q_j - Q_k - V_k (s_j - s_k)`` (:func:`_known_motion`)."""
    lo = k
    while lo > k - m and lo - 1 >= 0 and ok_hold[lo]:
        lo -= 1
    hi = k
    while hi < k + m and hi + 1 < len(b) and ok_hold[hi + 1]:
        hi += 1
    if hi - lo < 2:
        return None
    Q, V = QV
    tau = b[lo:hi + 1] - b[k]
    y = x[lo:hi + 1] - (Q[lo:hi + 1] - Q[k] - tau[:, None] * V[k])
    # (ndarray.mean, .sum, numpy.max and numpy.sqrt without their wrappers: the same
    # reductions, bit for bit)
    tc = tau - np.add.reduce(tau) / tau.size
    c = tc / float(tc @ tc)
    ac = np.abs(c)
    return (c @ y, float(np.add.reduce(ac)), float(ac @ tau ** 2), math.sqrt(c @ c),
            float(np.maximum.reduce(np.abs(tau))), lo, c)


def hold_motion(scene, state: np.ndarray, *, responses=None, seq=None) -> np.ndarray:
    """The record's change that the state changes ``state`` made: the loop of exact
    periods (the scene's predicted loop) run with them minus without, so that
    ``position - hold_motion(scene, w_hat)`` is the record with the estimated changes of
    :func:`hold_corrections` removed. Exact for a linear loop; for a scene with contacts
    or Euclidean links, its linearisation at rest to the changes' size relative (as
    :func:`hapsim.lockstep.state_responses`). An n-D scene runs
    :class:`hapsim.lockstep.LockstepND`; a 1-D one convolves the changes with
    :func:`state_change_responses` (:func:`hapsim.analysis.error_response.
    disturbance_response`, within each stretch of consecutive ``seq``).

    Parameters
    ----------
    scene : hapsim.scene.SceneND or hapsim.scene.Scene
    state : ndarray, shape (N, 2 n)
        The changes ``[x, v]`` [m, m/s] at each sample.
    responses : (ndarray, ndarray), optional
        1-D only: :func:`state_change_responses`, at least N long.
    seq : ndarray of int, shape (N,), optional
        1-D only: the rows' sequence numbers (a gap restarts the sum).

    Returns
    -------
    ndarray, shape (N, n); shape (N,) for a 1-D scene
        [m]; zeros (no run) when every change is 0.
    """
    state = np.asarray(state, float)
    N, n = state.shape[0], state.shape[1] // 2
    one_d = np.ndim(scene.device.mass) == 0        # the 1-D stack's scalar mass
    if not np.any(state):
        return np.zeros(N) if one_d else np.zeros((N, n))
    if one_d:
        from hapsim.analysis.error_response import disturbance_response
        Rp, Rv = responses if responses is not None else state_change_responses(scene, N)
        starts = None if seq is None else np.flatnonzero(
            np.diff(np.asarray(seq, np.int64)) != 1) + 1
        return (disturbance_response(scene, state[:, 0], starts=starts, response=Rp)
                + disturbance_response(scene, state[:, 1], starts=starts, response=Rv))
    from hapsim.lockstep import LockstepND
    return (LockstepND(scene).step(N, record=True, state_error=state)
            - LockstepND(scene).step(N, record=True))



def device_matrices(scene) -> tuple:
    """The device's mass and friction as matrices at rest: the n-D device's Cartesian
    ones, a 1-D device's scalars as 1 x 1.

    Parameters
    ----------
    scene : hapsim.scene.Scene or hapsim.scene.SceneND

    Returns
    -------
    (ndarray, ndarray)
        Mass [kg] and viscous friction [N s/m], shapes (n, n).
    """
    return (np.atleast_2d(np.asarray(scene.device.mass, float)),
            np.atleast_2d(np.asarray(scene.device.friction, float)))


def state_change_responses(scene, n: int) -> tuple:
    """A 1-D loop's responses to a change of the device's state at sample 0: of its
    position and of its velocity (the 1-D :func:`hapsim.lockstep.state_responses`).

    The device really moved (unlike a sensor's error): with the closed-loop state
    ``s[k+1] = A s[k]`` of :func:`hapsim.analysis.network.closed_loop` (state 0 the
    device position read at the sample, state 1 its velocity), a change ``e`` at sample 0
    before it is read gives the record ``(A^i e)[0]`` at sample ``i``: ``1, ...`` for a
    unit position, ``0, ...`` for a unit velocity (superposition of a linear
    time-invariant loop).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A validated, calibrated 1-D scene with a port and a device.
    n : int
        Length.

    Returns
    -------
    (ndarray, ndarray)
        Shapes (n,): the record's change per unit position change [m/m] and per unit
        velocity change [m/(m/s)].

    Raises
    ------
    ConfigError
        As :func:`~hapsim.analysis.network.closed_loop`; a loop whose state 1 is not the
        device's velocity (another hold than the zero-order one).
    """
    from hapsim.analysis.network import closed_loop
    from hapsim.errors import ConfigError
    A, names = closed_loop(scene)
    if len(names) < 2 or not str(names[1]).startswith("device.v"):
        raise ConfigError("the loop's state has no device velocity at index 1 "
                          f"({names[:2]}): no state change response", key="device.hold")
    n = max(int(n), 0)
    out = []
    for j in (0, 1):
        s = np.zeros(A.shape[0])
        s[j] = 1.0
        r = np.zeros(n)
        for i in range(n):
            r[i] = s[0]
            s = A @ s
        out.append(r)
    return out[0], out[1]


def write_time_terms(scene, cols: dict, *, quantum: float, position_rel: float = 0.0,
                     latency_s: float = 0.0, flag_estimated: int = 0, responses=None) -> dict:
    """The host's write timing in a 1-D driver's run on a board that holds each force from
    when it takes the write (:func:`hold_corrections` with ``n = 1``): the estimated
    motion to take off the record, the bounds of what that leaves, and the holds to cut.

    Row ``k`` is the reply to command ``k``, written at ``cols["time"][k]`` (the host's
    clock when it sent it: :class:`hapsim.drivers.transport.DriverTransport`'s
    ``time_us``); the force row ``k`` computed goes out with command ``k + 1``, so hold
    ``k`` (from command ``k - 1``'s arrival to command ``k``'s) holds row ``k - 2``'s
    force: the scene's delay of one period, the board's own (a scene stating another
    delay is not corrected: the caller's test). Readings: the rows not flagged
    ``flag_estimated``; the 1-D device's position is its own coordinate (``J = 1``),
    read to ``quantum / 2 + position_rel max |x|``. A hold more than
    :data:`HOLD_CUT_PERIODS` off a period (a late host, a stall, a gap in ``seq``) is
    cut: rows ``k - 1 .. k + 2``, its change neither corrected nor bounded (a change
    before a stretch is its initial state).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated 1-D scene.
    cols : dict of ndarray
        Telemetry columns ``time`` [s], ``position`` [m], ``force`` [N], ``seq``,
        ``flags``, shape (N,).
    quantum : float
        The sensor's step [m].
    position_rel : float, optional
        The wire's relative rounding of a position (binary32: 2^-24).
    latency_s : float, optional
        How much the link's latency may vary between writes, unseen by the host [s].
    flag_estimated : int, optional
        The telemetry flag of an estimated (not read) row.
    responses : (ndarray, ndarray), optional
        :func:`state_change_responses` of the scene, at least N long (computed if None).

    Returns
    -------
    dict
        ``motion`` (N,) [m] the estimated changes' record, to subtract; ``bounds``: a list
        of ``(e, response)`` (the remainder's bound per row [m] and [m/s] with the
        position and velocity responses: ``identify``'s ``bounds``); ``wire``: the
        readings' rounding in the estimate, as ``(sd, response)`` pairs (``identify``'s
        ``wire``: a random error, as the sensor's own); ``cut`` (N,) bool;
        ``delta`` (N,) [s] each hold's departure bound; ``corrected`` (N,) bool;
        ``hold_s`` the largest departure among the rows not cut [s].

    Raises
    ------
    ConfigError
        As :func:`state_change_responses`.
    """
    T = scene.period
    t = np.asarray(cols["time"], float)
    x = np.asarray(cols["position"], float)
    N = x.size
    d = 1
    est = (np.asarray(cols.get("flags", np.zeros(N)), np.int64) & int(flag_estimated)) != 0 \
        if flag_estimated else np.zeros(N, bool)
    read = np.where(est, np.nan, x)
    rec = {"write_s": t[:, None], "position": x[:, None], "readings": read[:, None],
           "torque": np.asarray(cols["force"], float)[:, None]}
    J = np.eye(1)
    dlt = [0.5 * float(quantum) + float(position_rel) * float(np.max(np.abs(x), initial=0.0))]
    hc = hold_corrections(rec, scene, J, dlt, latency_s=latency_s, rounding_apart=True,
                          window=VELOCITY_WINDOW)
    cut = np.zeros(N, bool)
    if N > 1:
        seq = np.asarray(cols.get("seq", np.arange(N)), np.int64)
        off = np.abs(np.diff(t) - T)
        bad = ~(off <= HOLD_CUT_PERIODS * T) | (np.diff(seq) != 1)
        mark = np.zeros(N + 1, np.int64)
        for k in np.flatnonzero(bad) + 1:
            mark[max(k - 1, 0)] += 1
            mark[min(k + d + 2, N)] -= 1
        cut = np.cumsum(mark[:N]) > 0
    keep = ~cut
    state = np.where(keep[:, None], hc["state"], 0.0)
    if responses is None:
        responses = state_change_responses(scene, N)
    Rp, Rv = responses
    motion = hold_motion(scene, state, responses=(Rp, Rv), seq=cols.get("seq"))
    pos = np.where(keep, hc["position"][:, 0], 0.0)
    vel = np.where(keep, hc["velocity"][:, 0], 0.0)
    bounds = [(e, r) for e, r in ((pos, Rp), (vel, Rv)) if np.any(e)]
    # the readings' rounding in the estimate, as the sensor's own is stated: a random
    # error e_j, uniform within +-eps (sd eps / sqrt(3)), entering the rows whose windows
    # hold it; no worse than white noise of sd max(gain) eps / sqrt(3) through the position
    # and velocity responses (hold_corrections' rounding_apart; per reading, the rows cut
    # counted too: an upper bound)
    g = hc["rounding_gain"]
    wire = [(float(np.max(g[:, j], initial=0.0)) * dlt[0] / np.sqrt(3.0), r)
            for j, r in enumerate((Rp, Rv))]
    wire = [(sd, r) for sd, r in wire if sd > 0]
    return {"motion": motion, "bounds": bounds, "wire": wire, "cut": cut,
            "delta": hc["delta"],
            "corrected": hc["corrected"] & keep,
            "hold_s": float(np.max(np.where(keep, hc["delta"], 0.0), initial=0.0))}
