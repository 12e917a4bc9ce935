"""The wire's rounding term of the n-D felt matrices, by Monte-Carlo over the rounding's
phase (issue 29): the spread of the run's own fit over records of the predicted loop
rounded as the device rounds them, with the quantisers in the loop.

Why. A device's readings are whole encoder counts and its torques whole motor commands
(or binary32 numbers); where each count's edge falls relative to the motion is set by the
encoder's zero, an unknown fraction of a count (and by the trajectory), not by an
adversary who knows the fit. The 1-D measurement states the sensor's rounding as
observation noise of variance ``q^2 / 12`` (Widrow & Kollar, *Quantization Noise*, 2008,
ch. 4: :mod:`hapsim.analysis.quantisation`). The n-D fit (a vector linear prediction,
:func:`hapsim.analysis.pencil.fit_felt_nd`) is too ill-conditioned for a first-order
variance to hold (its fast modes' poles are set by the errors alone:
:mod:`hapsim.analysis.wire_box`), and the worst case over the errors' box, which covers
that, takes every sign pattern of ``N`` rounding errors: to first order up to ``sqrt(3 N)``
times the standard deviation of what uniform rounding does (Hoelder's sum of ``|s_i| q/2``
against the root-sum-square ``q/sqrt(12) |s|_2``; on configs/falcon_spring.yaml at its
largest start,
40 times the stiffness matrix's largest entry at the exact records, where 400 draws of
the rounding moved it at most 0.093).

What is computed (:func:`rounding_term`). The exact records of the loop the prediction
describes (:class:`hapsim.lockstep.LockstepND`, the device's Cartesian mass at rest, no
rounding) from the run's hand starts, and ``R`` draws of the same loop with its
quantisers inside it (:func:`rounded_records`): each reading the joint angle rounded to
the device's count on a grid offset by a uniform fraction of a count per joint (the
encoder's zero), then mapped to the handle through ``J(q0)``, observed and fed back
through the scene (the engine's force from the rounded readings); each torque ``J(q0)^T
F`` rounded as the device rounds it (a motor command's grid at a uniform phase per joint,
or binary32), its error moving the device. Each draw is refitted by the run's own fit
(a callable: its records, its rows, its floor), and each statement's change from the
exact records' fit taken, the felt matrices' entries and the felt stiffness and damping
along each principal direction (the layout of :func:`hapsim.lockstep.relative_terms`).
What is stated is :data:`ROUNDING_MARGIN` times the largest change over the draws.

Because each draw carries the quantisers in the loop, the describing-function (loop
gain) part of rounding (Gelb & Vander Velde 1968; :func:`hapsim.analysis.quantisation.
quantiser_gain_bound`) is in the draws as well as the observation part: on
configs/falcon_spring.yaml the loop with its counts renders a felt stiffness 1-5 % above
the linear loop's along its principal directions and a damping 34-84 % above, against
about -0.6 % and 17-39 % for the same roundings applied to the exact records afterwards
(``tools/rounding_figures.py falcon``).

The fit's fragile classes (:mod:`hapsim.analysis.wire_box`'s notes) stay covered: a draw
whose fit gives no felt matrices (a pair of the loop turned real or under the fit's
floor) or renders a pair that is not nearest a rendered pair of the exact records' fit
(a noise pair outranking a loop pair) makes every statement's term infinite: "not
measurable", as the box's term does.

Coverage. Under the model (the rounding phases uniform and independent of everything
else, the loop the predicted one), the run's own rounding is one more draw from the same
distribution as the ``R`` draws: averaged over the draws' seeds, the probability that its
change exceeds the largest of ``R`` exchangeable draws is at most ``1 / (R + 1)`` (order
statistics, H. A. David and H. N. Nagaraja, *Order Statistics*, 3rd ed., 2003, Sec. 2.5;
for a quantile: the largest of ``R`` exceeds the ``q``-quantile with probability
``1 - q^R``). That is no guarantee for one scene: the seed is fixed (a statement a
function of its records), and for one scene its draws' largest may fall low (a random
field at 60 rows: 6.7 % of fresh draws beyond it), and per verdict, several statements
at once, the rate is higher (3-9 % of phases at 60 rows, 0-3 % at 300 with some
statement beyond the draws' largest). The margin covers that scatter and the model's
departures from the device where it was measured, at :data:`ROUNDING_MIN_ROWS` rows and
more (its notes); shorter records keep the errors' box.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["Rounding", "rounded_records", "rounding_term", "rounding_wire", "noise_pair",
           "exact_loop", "stretch_loop", "virtual_response", "rounding_applies",
           "ROUNDING_DRAWS", "ROUNDING_MARGIN", "ROUNDING_SEED", "ROUNDING_MIN_ROWS"]

#: Draws of the rounding's phase per term [-]: the largest of 100 exchangeable draws is
#: exceeded by one more with probability 1/101 (module notes). Each draw costs one fit
#: (a few ms at 7 records of 300 rows in 3-D: the 100 draws and the loop ~0.5 s of CPU
#: on configs/falcon_spring.yaml, one BLAS thread) and its share of the vectorised loop.
ROUNDING_DRAWS = 100
#: The factor over the largest change of the draws that is stated [-]: it covers the
#: model's departures from the device (the predicted loop linearised, its Cartesian mass
#: at rest, the phases uniform). Measured against the emulated Falcon itself (its packets,
#: the delta's joint-space dynamics, its encoders' index at uniform sub-count offsets;
#: each statement's change against the same records through an encoder 64 times finer,
#: over the run's largest change of 100 draws: ``tools/rounding_figures.py``,
#: docs/rounding_falcon*.json): at most 0.88 on configs/falcon_spring.yaml (60 offsets),
#: 1.08 over 20 random spring fields x 5 offsets (1 of 800 statements above 1, the
#: exchangeable rate 1/101), 0.95 with 1 byte in 200 lost (records cut, 224
#: statements), 0.94 at 60 rows (240). Cut records fitted about each stretch's own
#: equilibrium, before the run's common one, reached 1.40 (10 of 240 above 1). 1.5
#: leaves a factor 1.39 over the worst departure measured.
ROUNDING_MARGIN = 1.5
#: The draws' seed: a fixed one, so a statement is a function of its records (the
#: lockstep run's and the prediction before it agree bit for bit); the device's own
#: phase is independent of it.
ROUNDING_SEED = 29
#: The fewest samples per record at which the draws' term is taken [-]; shorter records
#: keep the worst case over the errors' box for the rounding too (the callers,
#: :func:`rounding_applies`). Where it was measured, at the run's default of 300 rows: on
#: random spring fields on the Falcon the largest of fresh draws of the same model reached
#: 1.26 times the seeded largest, the emulated Falcon itself 1.08 of it, the emulated
#: 2DIY on configs/pantograph_circle.yaml over 600 encoder phases 0.79 (model scans 0.94):
#: inside :data:`ROUNDING_MARGIN`. With fewer rows the fit's changes have heavier tails:
#: fresh draws reached 1.5-2.1 times the seeded largest on the 2DIY at 150 rows and 2.3
#: at 60 on the Falcon, and a matching emulated 2DIY was called "differs" at 3 of 1,500
#: encoder phases at 150 rows (its felt damping 0.212 off against 0.207 stated;
#: tests/test_wire_rounding.py), where the box said "partly within".
ROUNDING_MIN_ROWS = 300


def rounding_applies(samples: int) -> bool:
    """Whether the draws' term is taken for records of ``samples`` rows
    (:data:`ROUNDING_MIN_ROWS`); else the errors' box for the rounding too.

    Parameters
    ----------
    samples : int
        Samples per record ``N``.

    Returns
    -------
    bool
    """
    return int(samples) >= ROUNDING_MIN_ROWS


class Rounding:
    """A device's quantisers on its joints (module notes).

    Parameters
    ----------
    jacobian : array_like, shape (n, m)
        ``J(q0)``: joint angles [rad] to handle [m] at the operating point; its transpose
        maps the handle's force [N] to the joint torques [N m].
    joints : array_like, shape (m,)
        The joints' angles at the operating point ``q0`` [rad].
    count : array_like, shape (m,)
        A reading's count per joint [rad] (> 0).
    binary32_degrees : bool, optional
        The angle reaches the host as a binary32 number of degrees (the 2DIY: the count
        rounded, then ``360 c / res`` in single precision).
    command : array_like, shape (m,), optional
        A torque's command count per joint [N m] (the Falcon's motor command); None: no
        grid.
    binary32_torque : bool, optional
        The torque reaches the device as a binary32 number (the 2DIY).

    Raises
    ------
    ConfigError
        A count or a command count not positive and finite, or shapes that do not agree.
    """

    def __init__(self, jacobian, joints, count, *, binary32_degrees: bool = False,
                 command=None, binary32_torque: bool = False) -> None:
        self.J = np.asarray(jacobian, float)
        self.q0 = np.asarray(joints, float)
        m = self.q0.size
        self.count = np.broadcast_to(np.asarray(count, float), (m,)).copy()
        self.command = (None if command is None else
                        np.broadcast_to(np.asarray(command, float), (m,)).copy())
        if self.J.ndim != 2 or self.J.shape[1] != m:
            raise ConfigError(f"the Jacobian must be (n, {m}), got {self.J.shape}",
                              key="jacobian")
        for name, v in (("count", self.count), ("command", self.command)):
            if v is not None and not (np.all(np.isfinite(v)) and np.all(v > 0)):
                raise ConfigError(f"a {name} must be positive and finite, got {v!r}",
                                  key=name)
        self.Jinv = np.linalg.pinv(self.J)
        self.binary32_degrees = bool(binary32_degrees)
        self.binary32_torque = bool(binary32_torque)

    def read(self, q, phase):
        """The joint angles the host reads: each rounded to the nearest point of the
        count's grid offset by ``phase`` counts, ``c (round(q / c - phase) + phase)``,
        then to binary32 degrees when the device sends them so (the encoder's zero at an
        unknown fraction of a count: module notes).

        Parameters
        ----------
        q : ndarray, shape (R, m)
            The joints' true angles [rad], one row per draw.
        phase : ndarray, shape (R, m)
            Each draw's grid offset per joint [counts], in [0, 1).

        Returns
        -------
        ndarray, shape (R, m)
            The angles read [rad].
        """
        c = self.count
        out = c * (np.round(q / c - phase) + phase)
        if self.binary32_degrees:
            out = np.radians(np.degrees(out).astype(np.float32).astype(float))
        return out

    def torque(self, tau, phase):
        """The joint torques the device applies: each rounded to the command's grid offset
        by ``phase`` command counts (as :meth:`read`), then to binary32 when sent so; the
        torque itself without a grid or binary32.

        Parameters
        ----------
        tau : ndarray, shape (R, m)
            The torques the host computed [N m], one row per draw.
        phase : ndarray, shape (R, m)
            Each draw's grid offset per joint [command counts], in [0, 1).

        Returns
        -------
        ndarray, shape (R, m)
            The torques applied [N m].
        """
        out = tau
        if self.command is not None:
            c = self.command
            out = c * (np.round(out / c - phase) + phase)
        if self.binary32_torque:
            out = out.astype(np.float32).astype(float)
        return out


def exact_loop(scene, amplitude: float, samples: int) -> list:
    """The exact records of the predicted loop from the hand's starts and the port force
    computed at each sample (:class:`hapsim.lockstep.LockstepND`, no rounding).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A 2-D or 3-D scene with a port and a device.
    amplitude : float
        The hand's ``a`` [m] (:func:`hapsim.lockstep.excitation_starts`).
    samples : int
        Samples per record ``N``.

    Returns
    -------
    list of (ndarray, ndarray)
        ``2 n + 1`` pairs, the record from rest first: the handle's displacement from the
        operating point (N, n) [m] and the port force (N, n) [N].

    Raises
    ------
    ConfigError
        As :class:`hapsim.lockstep.LockstepND`.
    """
    from hapsim.lockstep import LockstepND, excitation_starts
    n, N = scene.dimension, int(samples)
    out = []
    for x0, v0 in excitation_starts(n, amplitude, scene.period):
        F = np.empty((N, n))
        X = LockstepND(scene, x0=x0, v0=v0).step(N, record=True, forces=F)
        out.append((X, F))
    return out


def virtual_response(scene, samples: int, *, size: float = 1e-9) -> np.ndarray:
    """The scene's port force per unit change of the port's position at one sample: the
    engine from rest with the port moved by ``size`` at sample 0 only, less the engine
    left at rest, over ``size`` (exact for a linear scene; the linearisation at rest to
    ``O(size)`` relative otherwise), trailing exact zeros cut.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A scene with a port.
    samples : int
        The longest response taken ``L``.
    size : float, optional
        The change [m].

    Returns
    -------
    ndarray, shape (L', n, n)
        ``[k, :, j]`` the force change [N/m] at sample ``k`` for a unit change along
        axis ``j`` at sample 0 (``L' <= L``, at least 1).
    """
    from hapsim.engine import Engine
    n, L = scene.dimension, int(samples)

    def run(j):
        eng = Engine(scene)
        rest = np.asarray(scene.device.position, float)
        eng.set_port_position(rest, at_rest=True)
        F = np.empty((L, n))
        for k in range(L):
            p = rest.copy()
            if k == 0 and j >= 0:
                p[j] += size
            eng.set_port_position(p)
            eng.step()
            F[k] = eng.port_force
        return F
    base = run(-1)
    V = np.stack([(run(j) - base) / size for j in range(n)], axis=2)
    live = np.flatnonzero(np.any(V != 0.0, axis=(1, 2)))
    return V[:int(live[-1]) + 1 if live.size else 1]


def rounded_records(scene, rounding: Rounding, exact, draws: int, seed, *,
                    feedback: bool = True, V=None) -> list:
    """``draws`` copies of the exact records with the device's quantisers in the loop
    (module notes), each at its own uniform phases.

    The loop is the predicted one linearised at the operating point: the device's exact
    zero-order hold of its Cartesian mass and friction, the delay line, and the scene's
    force as the engine's response to the readings' change (:func:`virtual_response`,
    a causal convolution); its change from the exact records is carried per draw, so a
    draw is the exact records plus the rounding's effect. Checked against
    :class:`hapsim.lockstep.LockstepND` fed the same errors (``tests/
    test_wire_rounding.py``: equal to round-off on a linear scene).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    rounding : Rounding
        The device's quantisers.
    exact : list of tuple
        :func:`exact_loop`'s ``(X, F)`` per record, or :func:`stretch_loop`'s ``(X, F,
        starts)``: ``starts`` (N,) bool the rows where a stretch of the loop begins (the
        rounding's change carried from the row before is dropped there: before a
        stretch it only changes the stretch's initial state, which its fit takes).
    draws : int
        ``R`` (>= 1).
    seed : int or numpy.random.Generator
        The phases' source (per draw: the readings' phases, then the commands').
    feedback : bool, optional
        The quantisers in the loop (default); False: the exact records rounded
        afterwards and the exact torques' rounding added through the loop, for
        comparison only (the observation part alone, no loop gain).
    V : ndarray, optional
        :func:`virtual_response`'s, already computed.

    Returns
    -------
    list of ndarray
        Per record, shape (R, N, n): the handle positions the host reads, as
        displacements from the operating point [m].
    """
    from hapsim.analysis.ths import MatrixLoop, split_hold_matrices, zoh_matrices
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    R = int(draws)
    n = scene.dimension
    dev = scene.device
    lm = MatrixLoop(mass=dev.mass, friction=dev.friction, rate_hz=scene.rate_hz,
                    delay=dev.delay)
    Ad, Bd = zoh_matrices(lm)
    split = float(dev.delay) % 1.0
    if split > 0:
        _, G0, G1 = split_hold_matrices(lm)
    d = int(dev.delay)
    N = exact[0][0].shape[0]
    if V is None:
        V = virtual_response(scene, N)
    Lv = V.shape[0]
    Vr = V[::-1]
    J, Jinv, q0 = rounding.J, rounding.Jinv, rounding.q0
    m = q0.size
    ph = rng.uniform(0.0, 1.0, (R, 2 * m))
    ph_r, ph_c = ph[:, :m], ph[:, m:]
    out = []
    for item in exact:
        X, F = item[0], item[1]
        starts = item[2] if len(item) > 2 else np.zeros(N, bool)
        s = np.zeros((R, 2 * n))           # the device's state less the exact one
        line = np.zeros((R, max(d, 1), n))  # the force changes in the delay line
        held = np.zeros((R, n))
        dy = np.zeros((R, N, n))           # the readings less the exact ones
        Y = np.empty((R, N, n))
        first = 0
        for t in range(N):
            if starts[t]:
                s[:], line[:], held[:], first = 0.0, 0.0, 0.0, t
            x = X[t] + s[:, :n]
            q = q0 + (x if feedback else X[t] + 0.0 * x) @ Jinv.T
            e = (rounding.read(q, ph_r) - q) @ J.T
            Y[:, t] = x + e
            dy[:, t] = s[:, :n] + e
            k0 = max(first, t - Lv + 1)
            dF = np.einsum("kab,rkb->ra", Vr[Lv - (t + 1 - k0):], dy[:, k0:t + 1])
            tau = (F[t] + (dF if feedback else 0.0 * dF)) @ J
            du = (dF if feedback else 0.0 * dF) + (rounding.torque(tau, ph_c) - tau) @ Jinv
            if d:
                u = line[:, d - 1].copy()
                line[:, 1:d] = line[:, :d - 1]
                line[:, 0] = du
            else:
                u = du
            if split > 0:
                s = s @ Ad.T + u @ G0.T + held @ G1.T
                held = u
            else:
                s = s @ Ad.T + u @ Bd.T
        out.append(Y)
    return out


def _var(records, p: int) -> np.ndarray:
    """The vector linear prediction ``y[k] = sum_j y[k-j] C_j`` of exact free responses
    (least squares over every record; exact on a loop observable with index ``p``):
    ``C`` shape (n p, n), the lags stacked newest first."""
    rows, rhs = [], []
    for y in records:
        for k in range(p, y.shape[0]):
            rows.append(y[k - p:k][::-1].ravel())
            rhs.append(y[k])
    return np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]


def _basis(C, n: int, p: int, L: int) -> np.ndarray:
    """The prediction's free responses over ``L`` rows from each of its ``n p`` unit
    initial conditions (the first ``p`` rows, oldest first): shape (L, n, n p)."""
    B = np.zeros((max(L, p), n, n * p))
    for j in range(n * p):
        B[p - 1 - j // n, j % n, j] = 1.0
    for k in range(p, L):
        B[k] = np.einsum("ja,jb->ab", C, B[k - p:k][::-1].reshape(n * p, n * p))
    return B[:L]


def stretch_loop(scene, records, usable, order: int, exact, equilibrium=None) -> list:
    """The predicted loop's free responses at a run's own stretches: per record, each
    stretch of undisturbed rows (a run of ``usable`` rows) replaced by the predicted
    loop's free response that fits its rows best (least squares over its rows, with
    its own equilibrium), with the port force the scene computes from it.

    A record cut at its disturbances (a lost reply, a host stall, a re-synchronisation
    whose set-up gives the handle the hand's next start) holds stretches that are free
    responses of the loop from initial states no hand start names: the rounding's draws
    (:func:`rounded_records`) take these as the loop's exact motion there, so the draws
    round what the run's own stretches carried, at their own amplitude.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    records : sequence of ndarray, each shape (N, n)
        The records as read: the handle's displacement from the operating point [m]
        (rows outside ``usable`` ignored; NaN allowed there).
    usable : sequence of ndarray of bool, each shape (N,)
        Per record, the rows fitted.
    order : int
        The prediction's order ``p`` (the loop's states over ``n``).
    exact : list
        :func:`exact_loop`'s whole records (the predicted loop's prediction is fitted on
        them, :func:`_var`).
    equilibrium : array_like, shape (n,), optional
        The records' common equilibrium [m] (the run's affine fit's, as displacement
        from the operating point): every stretch's free response about it, as the fit
        takes them; None: each record's own, fitted with its stretches.

    Returns
    -------
    list of (ndarray, ndarray, ndarray)
        Per record ``(X, F, starts)``: the displacement (N, n) [m] (the record's own rows
        outside the stretches, 0 where not finite), the port force (N, n) [N] (the
        scene's response to ``X`` within each stretch, :func:`virtual_response`, plus
        the force at rest) and the stretches' first rows (N,) bool.
    """
    n, p = scene.dimension, int(order)
    C = _var([X - exact[0][0] for X, _ in exact[1:]], p)
    N = np.asarray(records[0]).shape[0]
    V = virtual_response(scene, N)
    F_rest = exact[0][1][0]
    out = []
    for y, u in zip(records, usable):
        y = np.where(np.isfinite(y), np.asarray(y, float), 0.0)
        u = np.asarray(u, bool)
        X = y.copy()
        starts = np.zeros(N, bool)
        edge = np.diff(np.concatenate(([0], u.astype(np.int8), [0])))
        spans = list(zip(np.flatnonzero(edge == 1), np.flatnonzero(edge == -1)))
        # one least-squares problem per record: each stretch its own initial state, the
        # record's equilibrium shared (or given)
        m = n * p * len(spans)
        A = np.zeros((int(sum(b - a for a, b in spans)) * n,
                      m + (n if equilibrium is None else 0)))
        rhs = np.zeros(A.shape[0])
        row = 0
        for i, (a, b) in enumerate(spans):
            starts[a] = True
            L = b - a
            A[row:row + L * n, i * n * p:(i + 1) * n * p] = \
                _basis(C, n, p, L).reshape(L * n, n * p)
            if equilibrium is None:
                A[row:row + L * n, m:] = np.tile(np.eye(n), (L, 1))
                rhs[row:row + L * n] = y[a:b].ravel()
            else:
                rhs[row:row + L * n] = (y[a:b] - np.asarray(equilibrium, float)).ravel()
            row += L * n
        if spans:
            got = A @ np.linalg.lstsq(A, rhs, rcond=None)[0]
            if equilibrium is not None:
                got = got + np.tile(np.asarray(equilibrium, float), row // n)
            row = 0
            for a, b in spans:
                X[a:b] = got[row:row + (b - a) * n].reshape(b - a, n)
                row += (b - a) * n
        F = np.tile(F_rest, (N, 1))
        for a, b in spans:
            for t in range(a, b):
                k = np.arange(a, t + 1)[::-1][:V.shape[0]]
                F[t] = F_rest + np.einsum("kab,kb->a", V[:k.size], X[k])
        out.append((X, F, starts))
    return out


def _changes(fit, ref, E) -> np.ndarray:
    """Each statement's change from ``ref`` (absolute; :func:`hapsim.lockstep.
    relative_terms`' layout: the stiffness entries, the damping entries, then along each
    direction the stiffness, then the damping)."""
    out = []
    for q in ("felt_stiffness", "felt_damping"):
        out.append(np.abs(np.asarray(fit[q]) - np.asarray(ref[q])).ravel())
    for q in ("felt_stiffness", "felt_damping"):
        D = np.asarray(fit[q]) - np.asarray(ref[q])
        out.append(np.abs(np.einsum("ai,ab,bi->i", E, D, E)))
    return np.concatenate(out)


def noise_pair(fit, ref) -> bool:
    """Whether a fit renders a pair nearer one of the loop's poles that the loop does not
    render (its fast modes', which the records' errors alone set) than any pair it
    renders: a noise pair outranking a pair of the loop (module notes).

    Two rendered pairs nearest the same pair of the loop are not counted: the loop's
    pairs may nearly coincide (an isotropic field's), and the rounding's bias moves them.

    Parameters
    ----------
    fit : dict
        :func:`hapsim.analysis.pencil.fit_felt_nd`'s result with felt matrices
        (``rendered_poles``).
    ref : dict
        The same fit of the loop's exact records (``poles``: every pole of the loop,
        ``rendered_poles``: the rendered ones).

    Returns
    -------
    bool
    """
    up = lambda z: np.where(np.imag(z) < 0, np.conj(z), z)    # noqa: E731
    rend = np.unique(np.round(up(np.asarray(ref["rendered_poles"], complex)), 14))
    rest = np.unique(np.round(up(np.asarray(ref["poles"], complex)), 14))
    rest = rest[np.min(np.abs(rest[:, None] - rend[None]), axis=1)
                > 1e-9 * np.maximum(np.abs(rest), 1.0)]
    if rest.size == 0:
        return False
    for z in up(np.asarray(fit["rendered_poles"], complex)):
        if np.min(np.abs(rest - z)) < np.min(np.abs(rend - z)):
            return True
    return False


def rounding_term(scene, chk, rounding: Rounding, amplitude: float, samples: int, fit, *,
                  draws: int = ROUNDING_DRAWS, seed=ROUNDING_SEED,
                  margin: float = ROUNDING_MARGIN, exact=None, progress=None) -> dict:
    """The wire's rounding term of every felt statement (module notes): ``margin`` times
    the largest change of the run's own fit over ``draws`` draws of the rounding's phase.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        The scene (the predicted loop).
    chk : hapsim.analysis.scene_check.SceneCheckND
        The prediction (its principal directions).
    rounding : Rounding
        The device's quantisers.
    amplitude : float
        The hand's ``a`` [m] of the run's starts.
    samples : int
        Samples per record ``N``.
    fit : callable
        ``fit(records) -> dict`` the run's own fit (:func:`hapsim.analysis.pencil.
        fit_felt_nd`'s result) of ``2 n + 1`` records (N, n), the one from rest first, of
        the handle's displacement from the operating point [m]: its differences or
        offset, its rows, its floor. A :class:`~hapsim.errors.ConfigError` it raises
        counts as no felt matrices.
    draws : int, optional
        ``R`` (:data:`ROUNDING_DRAWS`).
    seed : int or numpy.random.Generator, optional
        :data:`ROUNDING_SEED`.
    margin : float, optional
        :data:`ROUNDING_MARGIN`.
    exact : list, optional
        :func:`exact_loop`'s at ``amplitude`` and ``samples``, already computed.
    progress : callable, optional
        ``progress(done, total)`` after each block of draws.

    Returns
    -------
    dict or None
        None when the exact records' fit gives no felt matrices. Else ``wc`` (shape
        (2 n^2 + 2 n,), :func:`hapsim.lockstep.relative_terms`' layout, absolute [N/m],
        [N s/m]: ``margin`` times ``largest``, inf everywhere when a draw lost a pair or
        rendered a noise pair), ``largest`` (the largest change over the draws, same
        layout), ``median`` (the median change), ``draws``, ``lost`` (draws without felt
        matrices), ``noise`` (draws rendering a pair not the loop's), ``margin``,
        ``reference`` (the exact records' fit).
    """
    n = scene.dimension
    N = int(samples)
    if exact is None:
        exact = exact_loop(scene, amplitude, N)

    def refit(recs):
        try:
            f = fit(recs)
        except ConfigError:
            return None
        return f if f.get("felt_stiffness") is not None else None
    ref = refit([e[0] for e in exact])
    if ref is None:
        return None
    E = np.asarray(chk.render.directions, float)
    V = virtual_response(scene, N)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    R = int(draws)
    block = 25
    changes, lost, noise = [], 0, 0
    done = 0
    while done < R:
        b = min(block, R - done)
        Ys = rounded_records(scene, rounding, exact, b, rng, V=V)
        for r in range(b):
            f = refit([Y[r] for Y in Ys])
            if f is None:
                lost += 1
                continue
            if noise_pair(f, ref):
                noise += 1
            changes.append(_changes(f, ref, E))
        done += b
        if progress is not None:
            progress(done, R)
    C = np.array(changes) if changes else np.full((1, 2 * n * n + 2 * n), math.inf)
    largest = C.max(axis=0)
    wc = np.full_like(largest, math.inf) if (lost or noise) else float(margin) * largest
    return {"wc": wc, "largest": largest, "median": np.median(C, axis=0), "draws": R,
            "lost": lost, "noise": noise, "margin": float(margin), "reference": ref}


def rounding_wire(chk, term) -> dict:
    """The wire's relative terms of a :func:`rounding_term` for
    :func:`hapsim.analysis.felt_matrices.felt_verdict`.

    Parameters
    ----------
    chk : hapsim.analysis.scene_check.SceneCheckND
        The prediction.
    term : dict or None
        :func:`rounding_term`'s (None: the exact records give no felt matrices).

    Returns
    -------
    dict
        ``felt_stiffness``, ``felt_damping``, ``directions`` (:func:`hapsim.lockstep.
        relative_terms` of ``term["wc"]``; inf with ``term`` None), ``how`` (the words a
        reason names the term by), ``rounding`` (``draws``, ``lost``, ``noise``,
        ``margin``, and ``largest``, ``median``: the relative terms of the draws' largest
        and median change, for the report).
    """
    from hapsim.lockstep import relative_terms
    n = chk.render.dof
    if term is None:
        inf = {"felt_stiffness": math.inf, "felt_damping": math.inf,
               "directions": {q: [math.inf] * n for q in ("felt_stiffness",
                                                          "felt_damping")}}
        return {**inf, "how": "the exact records' fit gives no felt matrices",
                "rounding": None}
    out = relative_terms(chk, term["wc"])
    out.pop("first_order", None)
    pick = lambda t: {k: t[k] for k in ("felt_stiffness", "felt_damping",   # noqa: E731
                                        "directions")}
    out["how"] = (f"{term['margin']:g} times the largest change of {term['draws']} draws "
                  "of the rounding's phase")
    out["rounding"] = {"draws": term["draws"], "lost": term["lost"], "noise": term["noise"],
                       "margin": term["margin"],
                       "largest": pick(relative_terms(chk, term["largest"])),
                       "median": pick(relative_terms(chk, term["median"]))}
    return out
