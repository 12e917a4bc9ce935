"""The braking after a safety stop on the device's motion, one law for every dimension.

Zero force alone leaves a moving device to its own friction, which carries it
``M_f^-1 M v`` further (a Hapkit paddle of 0.1 kg on 0.3 N s/m: 0.33 s times its speed;
a 2DIY joint of 2e-4 kg m^2 on 1e-3 N m s/rad: 0.2 s times its speed). After a stop on
the motion the host instead answers each reading with the damping

``tau = -B v``,  ``B = g M / T``,  ``g = BRAKE_GAIN``

(clamped to the device's force or torque limit), ``v`` the backward difference of the
last two readings, until :data:`REST_READINGS` speeds in a row are below a rest speed or
:data:`BRAKE_MAX_S` has passed; then zero force. In one dimension ``M`` is the mass at
the port (hand and handle, :meth:`hapsim.host.recovery.Recovery._brake`); in two and
three it is the device's joint-space inertia ``M_q`` and ``v`` the joints' velocities
(:func:`brake_damping` says why).

Each mode sees the scalar gain. With ``B = g M / T``, ``M^-1 B T = g I``: a frictionless
mass matrix, a zero-order hold and ``d`` periods of delay give, on every eigenvector of
``M``, the same scalar loop. With the velocity taken as the true one at each tick it is
``v(k+1) = v(k) - g v(k - d)``, whose roots stay inside the unit circle for
``g < 2 sin(pi / (2 (2 d + 1)))`` (the delayed first-order difference equation's bound,
Levin & May 1976, *Theor. Popul. Biol.* 9, 178-187; Kuruklis 1994, *J. Math. Anal.
Appl.* 188, 719-731): 0.25 holds to ``d = 5``. With the velocity a backward difference of
the sampled positions (what the host has) the loop of each mode is
``z^(d+2) - z^(d+1) + (g / 2)(z + 1) = 0`` (:func:`brake_mode_polynomial`; derived in its
notes), also stable at ``g = 0.25`` for ``d <= 5`` (spectral radius 0.994 at ``d = 5``,
1.011 at ``d = 6``): the same delay range. The exact sampled loop of any ``M``, friction
and delay is :func:`hapsim.analysis.stability.brake_loop_matrix` (``tests/test_brake_nd.py``
checks it against both closed forms and over random devices). A true inertia larger than the ``M`` used (a hand
holding the handle) lowers every mode's gain into ``(0, g]``, still inside the bound.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import dash

__all__ = ["BRAKE_GAIN", "BRAKE_MAX_S", "REST_READINGS", "IGNORED_TICKS", "brake_damping",
           "brake_rest", "gain_bound", "brake_mode_polynomial", "Brake", "brake_text"]

#: The braking's gain ``g = B T / m`` (module notes): stable for a delay up to 5 periods.
BRAKE_GAIN = 0.25
#: The longest braking [s] before the zero force (a device still moving then is one a
#: hand or a mis-stated mass keeps moving; zero force is then the safe end).
BRAKE_MAX_S = 0.25
#: Speeds in a row below the rest speed that end the braking.
REST_READINGS = 3
#: The share of the workspace the coast left after the braking may take (the rest speed,
#: :func:`brake_rest`).
REST_SHARE = 0.01
#: Ticks past the one a braking FORCE was due at (its seq plus the delay) after which a
#: device still naming an older FORCE is taken as applying none of the host's: the braking
#: gives way to STOP (the device zeroes its force at once, firmware_protocol/PROTOCOL.md
#: §STOP) rather than leave it holding a stale force until its watchdog.
IGNORED_TICKS = 3


def brake_damping(mass, rate_hz: float):
    """The braking damping after a safety stop, ``B = g M / T`` (module notes).

    In two and three dimensions ``M`` is the device's joint-space inertia ``M_q``
    [kg m^2] and ``B`` acts on the joints' velocities [N m s/rad], not the Cartesian mass
    through the Jacobian: ``M_q`` is the device's own constant (the scene states it; the
    Cartesian mass ``J^-T M_q J^-1`` changes with the configuration and grows without bound
    near a singularity, where a device flung out of its envelope may be), the joints are
    what the encoders read and the motors drive (no Jacobian between, so no kinematic
    solve far from the operating point), and a hand's mass on the handle only adds
    ``m_h J^T J`` to the true joint inertia: every mode's gain is then
    ``g`` times an eigenvalue of ``(M_q + m_h J^T J)^-1 M_q``, in ``(0, g]``, inside the
    stability bound. The Cartesian mass with the hand would be exact for a hand that holds
    on and four times too strong for a light device whose hand let go.

    Parameters
    ----------
    mass : float or array_like, shape (n, n)
        The mass at the port [kg] (or inertia [kg m^2] on a rotary axis), or an n-D
        device's joint-space inertia matrix [kg m^2] (symmetric positive definite).
    rate_hz : float
        The loop's rate ``1/T`` [Hz].

    Returns
    -------
    float or ndarray, shape (n, n)
        ``BRAKE_GAIN * mass * rate_hz`` [N s/m, N m s/rad]: a float for a scalar mass (the
        1-D number, the same two products), a matrix for a matrix. No braking (0.0, or a
        zero matrix) for a mass that is not finite and positive (definite), or a rate
        that is not finite and positive. Source: the module notes.
    """
    r = float(rate_hz)
    if np.ndim(mass) == 0:
        m = float(mass)
        if not (math.isfinite(m) and m > 0.0 and math.isfinite(r) and r > 0.0):
            return 0.0
        return BRAKE_GAIN * m * r
    M = np.atleast_2d(np.asarray(mass, float))
    zero = np.zeros_like(M)
    if (M.shape[0] != M.shape[1] or not np.all(np.isfinite(M)) or not math.isfinite(r)
            or not r > 0.0 or not np.allclose(M, M.T, rtol=1e-12, atol=0.0)):
        return zero
    if np.min(np.linalg.eigvalsh(0.5 * (M + M.T))) <= 0.0:
        return zero
    return BRAKE_GAIN * M * r


def brake_rest(extent: float, mass, friction) -> float:
    """The rest speed that ends the braking: the coast friction alone would still give
    from it, ``v m / b``, is :data:`REST_SHARE` of the workspace ``extent``.

    Parameters
    ----------
    extent : float
        The workspace's extent [m, or rad for joints].
    mass, friction : float or array_like, shape (n, n)
        Mass [kg] (inertia [kg m^2]) and viscous friction [N s/m] (N m s/rad).

    Returns
    -------
    float
        ``REST_SHARE * extent * lambda`` [m/s, rad/s], ``lambda`` the smallest rate
        ``b / m`` of the friction (the smallest eigenvalue of ``M^-1 B_f``, the slowest
        coast); without friction ``lambda`` = 1/s (the share in a second). The 1-D
        run's (:mod:`hapsim.pipeline.runner`, the workspace its position bound) and the
        n-D drivers' (the joints' workspace).
    """
    M = np.atleast_2d(np.asarray(mass, float))
    Bf = np.atleast_2d(np.asarray(friction, float))
    lam = 0.0
    if np.all(np.isfinite(M)) and np.all(np.isfinite(Bf)):
        try:
            w = np.linalg.eigvals(np.linalg.solve(M, Bf)).real
            lam = float(np.min(w)) if w.size else 0.0
        except np.linalg.LinAlgError:
            lam = 0.0
    return REST_SHARE * float(extent) * (lam if lam > 0.0 else 1.0)


def gain_bound(delay: int) -> float:
    """The largest stable gain of ``v(k+1) = v(k) - g v(k - d)``, ``2 sin(pi / (2 (2 d +
    1)))`` (Levin & May 1976; Kuruklis 1994).

    Parameters
    ----------
    delay : int
        ``d`` >= 0 [periods].

    Returns
    -------
    float
        The bound (its loop's roots on the unit circle there, inside below it).
    """
    return 2.0 * math.sin(math.pi / (2 * (2 * int(delay) + 1)))


def brake_mode_polynomial(gain: float, delay: int) -> np.ndarray:
    """One mode's characteristic polynomial of the braking with a backward-difference
    velocity, ``z^(d+2) - z^(d+1) + (g / 2) z + g / 2`` (highest power first).

    Parameters
    ----------
    gain : float
        ``g = B T / m`` of the mode.
    delay : int
        ``d`` >= 0: the periods between the reading the velocity ends at and the period
        its force is held over.

    Returns
    -------
    ndarray, shape (d + 3,)

    Notes
    -----
    A frictionless mass ``m`` under a zero-order-held force ``f[k]``: ``v[k+1] = v[k] +
    (T / m) f[k]`` and ``x[k+1] - x[k] = T v[k] + (T^2 / 2m) f[k]``. The host's velocity
    ``y[k] = (x[k] - x[k-1]) / T`` and ``f[k] = -B y[k-d]``, ``g = B T / m``: ``y[k+1] =
    v[k] - (g / 2) y[k-d]`` and ``v[k+1] = v[k] - g y[k-d]``; eliminating ``v`` in ``z``
    gives the polynomial times ``z^-d``.
    """
    d = int(delay)
    p = np.zeros(d + 3)
    p[0], p[1] = 1.0, -1.0
    p[-2] += 0.5 * gain
    p[-1] += 0.5 * gain
    return p


class Brake:
    """The braking law of every dimension, reading by reading (module notes).

    Parameters
    ----------
    damping : float or array_like, shape (n, n)
        ``B`` (:func:`brake_damping`) [N s/m, N m s/rad].
    limit : float
        The force or torque limit [N, N m] each component is held within: the whole
        vector is scaled down when one is over (its direction kept, so the torque stays
        against the velocity through ``B``: ``-v^T s B v <= 0``, no power given), and the
        largest set to the limit exactly (in 1-D, ``min(max(-B v, -lim), lim)``).
    rest : float
        The rest speed (:func:`brake_rest`) [m/s, rad/s]: the largest component's
        magnitude below it for :data:`REST_READINGS` readings in a row ends the braking.

    Attributes
    ----------
    v : ndarray, shape (n,) or None
        The velocity of the last two readings (None before two).
    v_start : ndarray, shape (n,) or None
        The first velocity.
    still : int
        Speeds in a row below ``rest``.
    """

    def __init__(self, damping, limit: float, rest: float) -> None:
        B = np.asarray(damping, float)
        self.n = 1 if B.ndim == 0 else B.shape[0]
        self.B = B.reshape(1, 1) if B.ndim == 0 else B
        self.scalar = B.ndim == 0
        self.limit = float(limit)
        self.rest = float(rest)
        self.prev = None
        self.v = self.v_start = None
        self.still = 0

    @property
    def at_rest(self) -> bool:
        """:data:`REST_READINGS` speeds in a row below the rest speed."""
        return self.still >= REST_READINGS

    def observe(self, position, dt: float | None) -> None:
        """Take one reading: the velocity ``(q - q_prev) / dt`` from the last.

        Parameters
        ----------
        position : array_like, shape (n,)
            The reading [m, rad].
        dt : float or None
            Its time after the last reading [s] (None or not positive: the reading only
            restarts the difference, as a repeated device time does).
        """
        q = np.array(position, float).reshape(self.n)
        if self.prev is not None and dt is not None and dt > 0.0:
            self.v = (q - self.prev) / dt
            if self.v_start is None:
                self.v_start = self.v
            self.still = self.still + 1 if float(np.max(np.abs(self.v))) < self.rest else 0
        self.prev = q

    def command(self) -> np.ndarray:
        """The braking force or torques ``-B v`` within the limit (zero before a velocity).

        Returns
        -------
        ndarray, shape (n,)
        """
        if self.v is None:
            return np.zeros(self.n)
        f = -(self.B @ self.v)
        a = np.abs(f)
        i = int(np.argmax(a))
        lim = self.limit
        if a[i] > lim:
            f = f * (lim / a[i])
            f[i] = math.copysign(lim, f[i])
            np.clip(f, -lim, lim, out=f)
        return f

    def report(self, periods: int, seconds: float, ended: str, late: int = 0) -> dict:
        """What the braking did, as the run reports it (``loop.brake``).

        Parameters
        ----------
        periods : int
            Braking FORCEs sent [periods].
        seconds : float
            The braking's duration [s].
        ended : {"rest", "time", "port", "ignored"}
            Why it ended (below).
        late : int
            Periods the host itself was late (held longer than two periods).

        Returns
        -------
        dict
            ``damping`` (a float in 1-D, else nested lists), ``periods``, ``seconds``,
            ``v_start``, ``v_end`` (floats in 1-D, else lists; None before two
            readings), ``ended`` (``"rest"``, ``"time"``, ``"port"``, ``"ignored"``: the
            device applied none of the host's FORCEs, STOP sent at once), ``late``.
        """
        def out(v):
            if v is None:
                return None
            return float(v[0]) if self.scalar else [float(x) for x in v]
        return {"damping": float(self.B[0, 0]) if self.scalar else self.B.tolist(),
                "periods": int(periods), "seconds": float(seconds),
                "v_start": out(self.v_start), "v_end": out(self.v), "ended": ended,
                "late": int(late)}


def brake_text(report: dict, damping_unit: str = "N s/m", speed_unit: str = "m/s") -> str:
    """One report line of a braking (:meth:`Brake.report`'s dict).

    Parameters
    ----------
    report : dict
        The braking's report.
    damping_unit, speed_unit : str
        The units of its damping and speeds (``"N m s/rad"``, ``"rad/s"`` for joints).

    Returns
    -------
    str
        ``"braked after the stop: damping B unit over P periods (S s), speed v0 -> v1
        unit, ended: E"`` (or, when the device took none of the host's FORCEs before it
        began, ``"no braking after the stop: ..."``); an n-D braking's damping is its
        matrix's diagonal and its speeds the largest component's magnitude.
    """
    def speed(v):
        return v if v is None or np.ndim(v) == 0 else float(np.max(np.abs(v)))
    if report["ended"] == "ignored" and not report["periods"]:
        return ("no braking after the stop: the device applied none of the host's FORCEs "
                f"(its last STATE named a FORCE more than the delay + {IGNORED_TICKS} "
                "ticks old): STOP sent at once")
    B = report["damping"]
    damp = (f"{B:.3g}" if np.ndim(B) == 0 else
            "diag(" + ", ".join(f"{float(x):.3g}" for x in np.diag(np.asarray(B))) + ")")
    return (f"braked after the stop: damping {damp} {damping_unit} over "
            f"{report['periods']} periods ({report['seconds']:.3f} s), speed "
            f"{dash(speed(report['v_start']), '.3g')} -> {dash(speed(report['v_end']), '.3g')} "
            f"{speed_unit}, ended: {report['ended']}"
            + (" (the device applied none of the braking's FORCEs: STOP sent)"
               if report["ended"] == "ignored" else ""))
