"""Z-width measured: the stiffness limit K_max(B) located on the device from its records.

Haptics characterises a device by its Z-width, the range of impedances it renders stably
(Colgate & Brown 1994). Here, for each virtual damping ``B``, the wall's stiffness ``K`` is
raised safely on the device (the run's energy, force and position limits stay armed) and
the onset of growth is located from short records, not from a blow-up: each record's free
response is identified (:func:`hapsim.analysis.identify.measure_felt` through ``hapsim
run``'s own identification) and its felt pair gives the dominant pole's modulus

    rho = |z| = exp(-b T / (2 m))           (k = m |s|^2, b = -2 m Re s, z = e^(sT)),

which is < 1 while the wall's oscillation decays and > 1 once it grows: on the boundary
the felt damping is zero (Florens et al. Sec. 6.2: the boundary is the b = 0 curve of the
grid). The crossing is bracketed by raising ``K`` by a fixed ratio from below the
predicted limit, then refined by regula falsi (Illinois) on the measured ``b(K)``.

Predictions beside it: the linear boundary (:func:`hapsim.analysis.stability.stability_limit`),
and, for a device with Coulomb friction ``fc``, the boundary that friction moves. Coulomb
friction is not linear: on an oscillation of amplitude ``a`` at angular frequency ``w`` it
dissipates per cycle what a viscous ``b_eq = 4 fc / (pi a w)`` would (its describing
function, the first harmonic of ``-fc sign(v)``; Gelb & Vander Velde 1968), so a record
released from ``x0`` decays until the linear loop with friction ``b0 + b_eq(x0)`` is at its
limit: ``K_DF = K_max(b0 + 4 fc / (pi x0 w_c))`` with ``w_c`` the crossing pole's
frequency (solved by fixed point). Above ``K_DF`` an oscillation of amplitude ``x0`` grows;
below it, it decays and the handle sticks (Diolaiti et al. 2006 describe these regions: a
device may be stable against small motions in violation of the linear and passivity
limits).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.errors import ConfigError
from hapsim.outputs import finite_or_none

__all__ = ["Trial", "ZPoint", "predicted_coulomb", "locate_onset", "wall_scene",
           "device_loop", "release", "FORCE_SHARE", "MIN_GROWTH_TICKS", "RECORD_ATTEMPTS",
           "record_side", "default_dampings", "DEFAULT_DAMPINGS"]

#: ``hapsim zwidth``'s virtual dampings without ``--B`` on its reference device (0.1 kg
#: at 1 kHz, configs/wall.yaml's) [N s/m]; :func:`default_dampings` scales them to a
#: lighter or slower one.
DEFAULT_DAMPINGS = (0.0, 1.5, 4.0)
#: The reference device's mass times its rate [kg Hz]: 0.1 kg at 1 kHz.
_REFERENCE_M_RATE = 100.0

#: Fewest ticks before a safety stop for an unidentified record to count as growing: from
#: at most 30 % of the force limit a growth of 1 % per sample needs ~120 ticks to reach it,
#: and the force-limit stop 50 clamped samples more; a stop sooner is a device that started
#: out of place (undecided).
MIN_GROWTH_TICKS = 100

#: Most records taken at one K when each is disturbed (late, missed or stale ticks) and
#: cannot be identified: the host's stalls are rare and independent from record to record
#: (a record is lost with probability q, all n attempts with q^n).
RECORD_ATTEMPTS = 6


def record_side(b: float, b_unc: float, late_ticks: int, b_bound_late: float | None):
    """The side of the stability limit a record decides from its identified felt damping.

    A record without late ticks in its identified stretch is the loop's own free response
    (exact to round-off on the mock; its fit's interval only bounds the noise): its sign of
    ``b`` decides. One with late ticks had their forces taken out as a known input
    (:func:`hapsim.analysis.measurement.late_accounted`), wrong by at most
    :func:`hapsim.analysis.measurement.late_force_bound` at each of them; the worst case of
    that error through the fit's first-order sensitivity is ``b_bound_late``
    (:func:`hapsim.analysis.identify.measure_felt`'s ``late_bounded``: ``sum_j e_j |s_j|``,
    Seber & Wild 1989, Sec. 2.1). Its side is decided only when ``|b|`` exceeds that bound
    plus the fit's stated half-interval ``b_unc``; without the bound (late ticks not
    accounted), never.

    Parameters
    ----------
    b, b_unc : float
        Identified felt damping and its stated half-interval [N s/m].
    late_ticks : int
        Late ticks inside the identified stretch (accounted or not).
    b_bound_late : float or None
        Worst-case error of ``b`` from the late ticks' accounted forces [N s/m] (None: not
        bounded).

    Returns
    -------
    (growing, margin)
        ``growing``: True (``b < -margin``), False (``b > margin``) or None (undecided);
        ``margin`` [N s/m]: 0 without late ticks (the sign decides), ``inf`` when they are
        not bounded, else ``b_bound_late + b_unc``.
    """
    if not late_ticks:
        margin = 0.0
    elif b_bound_late is None or not math.isfinite(b_bound_late):
        margin = math.inf
    else:
        margin = float(b_bound_late) + float(b_unc)
    if b > margin:
        return False, margin
    if b < -margin:
        return True, margin
    return None, margin


#: Largest share of the device's force limit the wall's initial force ``K x0`` may take:
#: a clamped force is not the linear loop, and a growing record must stay clear of it.
FORCE_SHARE = 0.3


def release(x0: float, force_limit: float, K: float) -> float:
    """Release position for a wall of stiffness ``K`` [m]: ``x0``, reduced so that
    ``K x0 <= FORCE_SHARE * force_limit`` (no clamping while the record is measured).

    Parameters
    ----------
    x0 : float
        Release position asked for [m].
    force_limit : float
        The device's force limit [N] (``inf``: none).
    K : float
        Virtual wall stiffness [N/m] (``<= 0``: no reduction).

    Returns
    -------
    float
        ``min(x0, FORCE_SHARE * force_limit / K)`` [m] when ``K > 0`` and the limit is
        finite, else ``x0``.
    """
    if K > 0 and math.isfinite(force_limit):
        return min(float(x0), FORCE_SHARE * float(force_limit) / float(K))
    return float(x0)


@dataclass(frozen=True)
class Trial:
    """One short record on the device at a virtual (K, B).

    Attributes
    ----------
    K, B : float
        Virtual stiffness [N/m] and damping [N s/m].
    b, k : float or None
        Measured felt damping [N s/m] and stiffness [N/m] (None when not identified).
    b_unc : float
        Stated half-interval of ``b`` [N s/m] (0 when not given).
    rho : float or None
        Dominant pole modulus ``exp(-b T / (2 m))`` [-].
    growing : bool or None
        The record grows: its identified ``b < 0`` (a safety stop after a decaying stretch
        is a disturbance, not growth; with late ticks in the identified stretch only
        beyond their bound and the stated half-interval, :func:`record_side`);
        unidentified, a safety stop after at least :data:`MIN_GROWTH_TICKS` ticks of an
        undisturbed record. None when undecided.
    note : str
        Why a record is undecided, or the run's stop reason.
    """

    K: float
    B: float
    b: float | None
    k: float | None
    b_unc: float
    rho: float | None
    growing: bool | None
    note: str = ""

    def to_dict(self) -> dict:
        """JSON-ready dict of the attributes.

        Returns
        -------
        dict
            ``K``, ``B``, ``b``, ``k``, ``b_unc``, ``rho``, ``growing``, ``note`` as they
            are (:func:`dataclasses.asdict`; no non-finite check).
        """
        return dataclasses.asdict(self)


@dataclass
class ZPoint:
    """The measured and predicted stiffness limit at one virtual damping.

    Attributes
    ----------
    B : float
        Virtual damping [N s/m].
    K_max_predicted : float
        Linear boundary [N/m] (:func:`hapsim.analysis.stability.stability_limit`).
    K_max_predicted_coulomb : float or None
        Boundary with the device's Coulomb friction at the record's amplitude
        (:func:`predicted_coulomb`; None without Coulomb friction).
    K_max_measured : float or None
        Root of the measured ``b(K)`` between the last decaying and growing records [N/m].
    K_max_measured_interval : (float, float) or None
        Bracket: a record decays at the low end and grows at the high end, widened by the
        stated uncertainty of ``b`` carried through the slope of ``b(K)`` [N/m].
    trials : list of Trial
    note : str
    """

    B: float
    K_max_predicted: float
    K_max_predicted_coulomb: float | None = None
    K_max_measured: float | None = None
    K_max_measured_interval: tuple | None = None
    trials: list = field(default_factory=list)
    note: str = ""

    def to_dict(self) -> dict:
        """JSON-ready dict (``trials`` as dicts; non-finite values as None).

        Returns
        -------
        dict
            The attributes by name, ``K_max_measured_interval`` as a list of two (or
            None), ``trials`` as :meth:`Trial.to_dict` gives them.
        """
        f = finite_or_none
        iv = self.K_max_measured_interval
        return {"B": self.B, "K_max_predicted": f(self.K_max_predicted),
                "K_max_predicted_coulomb": f(self.K_max_predicted_coulomb),
                "K_max_measured": f(self.K_max_measured),
                "K_max_measured_interval": None if iv is None else [f(iv[0]), f(iv[1])],
                "trials": [t.to_dict() for t in self.trials], "note": self.note}


def default_dampings(mass, rate_hz: float) -> list:
    """``hapsim zwidth``'s virtual dampings when ``--B`` is not given [N s/m] (a rotary
    axis's [N m s/rad]): :data:`DEFAULT_DAMPINGS` on a device at least as heavy and fast as
    the reference (0.1 kg at 1 kHz), else the same dimensionless dampings ``B T / m``
    (0, 0.015, 0.04): scaled by ``m rate / (0.1 kg x 1 kHz)``.

    The sampled loop's stability region depends on ``K T^2 / m`` and ``B T / m`` (with
    the device's own ``b0 T / m`` and delay; the paper's eq. 12 normalised): 1.5 N s/m
    on the Haply joint of configs/haply.yaml (0.001 kg m^2 at 1 kHz) is ``B T / m`` = 1.5,
    where no stiffness is stable (K_max = 0: the sweep measured nothing and exited 1).
    Devices at or above the reference keep the old dampings (their ``B T / m`` is smaller,
    well inside the region).

    Parameters
    ----------
    mass : float or array_like
        The device's mass [kg] (an inertia on a rotary axis), or its mass matrix (its
        smallest eigenvalue counts: the lightest direction).
    rate_hz : float
        Sample rate [Hz].

    Returns
    -------
    list of float
        Increasing dampings, the first 0.
    """
    import numpy as np
    m = np.asarray(mass, float)
    m = float(np.min(np.linalg.eigvalsh(m))) if m.ndim == 2 else float(m)
    scale = min(1.0, m * float(rate_hz) / _REFERENCE_M_RATE)
    if not (math.isfinite(scale) and scale > 0):
        return list(DEFAULT_DAMPINGS)
    return [float(f"{B * scale:.6g}") for B in DEFAULT_DAMPINGS]


def device_loop(device, rate_hz: float, friction: float | None = None):
    """The linear loop model of a scene's device (optionally with another friction).

    Parameters
    ----------
    device : hapsim.scene.Device
    rate_hz : float
        Sample rate [Hz].
    friction : float, optional
        Viscous friction to use instead of the device's [N s/m].

    Returns
    -------
    hapsim.analysis.loop.LoopModel
    """
    from hapsim.analysis.loop import LoopModel
    loop = LoopModel.from_device(device, rate_hz)
    if friction is not None:
        d = loop.to_dict()
        d["friction"] = float(friction)
        d.pop("correction", None)
        loop = LoopModel(**d, correction=loop.correction)
    return loop


def predicted_coulomb(device, rate_hz: float, B: float, amplitude: float) -> float:
    """Stiffness limit with Coulomb friction, by its describing function (module notes).

    Parameters
    ----------
    device : hapsim.scene.Device
        With ``coulomb`` ``fc`` [N] (0: the linear limit).
    rate_hz : float
        [Hz].
    B : float
        Virtual damping [N s/m].
    amplitude : float > 0, or callable
        Oscillation amplitude the record starts from [m] (the excitation's ``x0``), or
        ``amplitude(K)`` when it depends on the wall (:func:`release`).

    Returns
    -------
    float
        ``K`` [N/m] where the loop with friction ``b0 + 4 fc / (pi a w_c)`` reaches the
        unit circle, ``w_c`` the crossing pole's angular frequency (fixed point, 30 steps
        at most, to 1e-10 relative).

    Raises
    ------
    ConfigError
        A non-positive amplitude with Coulomb friction.
    """
    from hapsim.analysis.coulomb_check import coulomb_equivalent_damping
    from hapsim.analysis.loop_poles import closed_loop_poles
    from hapsim.analysis.stability import stability_limit

    fc = float(getattr(device, "coulomb", 0.0) or 0.0)
    loop = device_loop(device, rate_hz)
    K = stability_limit(loop, B)
    if fc <= 0:
        return K
    amp = amplitude if callable(amplitude) else (lambda K, a=amplitude: a)
    amplitude = amp(K)
    if not amplitude > 0:
        raise ConfigError(f"must be > 0 with Coulomb friction, got {amplitude!r}",
                          key="excitation.x0")
    T = loop.period
    for _ in range(30):
        if not (math.isfinite(K) and K > 0):
            return K
        z = closed_loop_poles(loop, K, B)
        zc = z[np.argmin(np.abs(np.abs(z) - 1.0) + (np.abs(z.imag) < 1e-12))]
        w = abs(math.atan2(zc.imag, zc.real)) / T
        if w <= 0:
            return K
        beq = coulomb_equivalent_damping(fc, amp(K), w)
        K_new = stability_limit(device_loop(device, rate_hz, loop.friction + beq), B)
        if abs(K_new - K) <= 1e-10 * abs(K):
            return K_new
        K = K_new
    return K


def wall_scene(base, K: float, B: float, x0: float):
    """A one-link wall on the base scene's device: the port tied to a ground by (K, B).

    Parameters
    ----------
    base : hapsim.scene.Scene
        Gives the device, the rate and the safety limits.
    K, B : float
        Wall stiffness [N/m] and damping [N s/m].
    x0 : float
        Release from ``x0`` [m] (the excitation).

    Returns
    -------
    hapsim.scene.Scene
    """
    from hapsim.scene import Excitation, Link, Mass, Scene
    return Scene(rate_hz=base.rate_hz,
                 masses=(Mass(name="hand", kind="port"),
                         Mass(name="wall", kind="ground", x0=0.0)),
                 links=(Link(name="wall", kind="spring_damper", m1="hand", m2="wall",
                             stiffness=float(K), damping=float(B)),),
                 device=base.device, excitation=Excitation(x0=float(x0)), path=base.path,
                 safety=base.safety)


def locate_onset(measure, B: float, K_guess: float, *, tol: float = 2e-3,
                 start: float = 0.7, step: float = 1.15, max_trials: int = 16,
                 progress=None) -> tuple:
    """Raise ``K`` safely to the onset of growth and refine it from the records.

    Parameters
    ----------
    measure : callable
        ``measure(K, B) -> Trial`` (:func:`hapsim.commands.zwidth.run_measure`).
    B : float
        Virtual damping [N s/m].
    K_guess : float > 0
        Where to look [N/m] (a prediction); the search starts at ``start * K_guess``,
        below it, and the answer comes from the records only.
    tol : float
        Relative width of the final bracket.
    start, step : float
        First ``K`` as a fraction of the guess; ratio of each raise.
    max_trials : int
        Most records.
    progress : callable, optional
        ``progress(trial)`` after each record.

    Returns
    -------
    (K_measured, interval, trials, note)
        ``K_measured`` [N/m], ``interval`` ``(lo, hi)`` [N/m], the records, and a note.
        When a record is undecided before a bracket is found (a safety stop within
        :data:`MIN_GROWTH_TICKS`, or no identification), ``K_measured`` is the last two
        decaying records' ``b(K)`` extrapolated to 0 (the note says so) and the interval
        None; without two decaying records, None. An undecided record inside a bracket
        ends the refinement there: the bracket of the decided records is the interval
        (the note says so).

    Notes
    -----
    Regula falsi with the Illinois modification (Dowell & Jarratt 1971) on the measured
    ``b(K)``: the next ``K`` is the secant root of the bracketing records, whose retained
    end's value is halved when the same end is kept twice, so both ends converge.
    """
    if K_guess == 0.0:
        return None, None, [], ("no stiffness is predicted stable with this damping "
                                "(K_max = 0: the virtual damping alone destabilises the "
                                "sampled loop): take a smaller B")
    if not (K_guess > 0 and math.isfinite(K_guess)):
        return None, None, [], "no finite predicted limit to start below"
    trials = []

    def rec(K):
        t = measure(float(K), B)
        trials.append(t)
        if progress is not None:
            progress(t)
        return t

    def undecided(K, t):
        """No bracket: the decaying records' trend of b(K), extrapolated to b = 0 (the
        device was never driven past its limit), or nothing."""
        dec = sorted((x for x in trials if x.growing is False and x.b is not None),
                     key=lambda x: x.K)[-2:]
        why = f"record at K = {K:.6g} N/m undecided: {t.note}"
        if len(dec) == 2 and dec[1].b > 0 and dec[1].b < dec[0].b:
            root = dec[1].K - dec[1].b * (dec[1].K - dec[0].K) / (dec[1].b - dec[0].b)
            return root, None, trials, (why + "; K_max extrapolated from the last two "
                                        "decaying records (b(K) to 0), no interval")
        return None, None, trials, why

    K = start * K_guess
    t = rec(K)
    while t.growing is not False and len(trials) < max_trials:
        if t.growing is None:
            return undecided(K, t)
        K /= step ** 2                         # grows already: step down first
        t = rec(K)
    if t.growing is not False:
        return None, None, trials, (f"no decaying record down to K = {K:.6g} N/m (last: "
                                    f"{t.note or 'grew'})")
    lo = t
    hi = None
    while len(trials) < max_trials:
        K *= step
        t = rec(K)
        if t.growing is None:
            return undecided(K, t)
        if t.growing:
            hi = t
            break
        lo = t
    if hi is None:
        return None, None, trials, f"no growth up to K = {K:.6g} N/m"
    fa, fb = lo.b, hi.b
    side = 0
    refine_note = ""
    while len(trials) < max_trials and (hi.K - lo.K) > tol * lo.K:
        if fb is None or fa is None:
            Kn = 0.5 * (lo.K + hi.K)
        else:
            Kn = lo.K + (hi.K - lo.K) * fa / (fa - fb)
            Kn = min(max(Kn, lo.K + 1e-3 * (hi.K - lo.K)), hi.K - 1e-3 * (hi.K - lo.K))
        t = rec(Kn)
        if t.growing is None:
            # inside the bracket of two decided records: the bracket still holds the limit
            refine_note = f"refinement ended at K = {Kn:.6g} N/m, undecided: {t.note}"
            break
        if t.growing:
            hi, fb = t, t.b
            if side == 1 and fa is not None:
                fa *= 0.5
            side = 1
        else:
            lo, fa = t, t.b
            if side == -1 and fb is not None:
                fb *= 0.5
            side = -1
    if lo.b is not None and hi.b is not None and lo.b != hi.b:
        slope = (hi.b - lo.b) / (hi.K - lo.K)
        Km = lo.K - lo.b / slope
        dK = max(lo.b_unc, hi.b_unc) / abs(slope) if slope else 0.0
        interval = (min(lo.K, Km - dK), max(hi.K, Km + dK))
    else:            # the growing end stopped unidentified: the decaying records' trend
        dec = sorted((t for t in trials if t.growing is False and t.b is not None),
                     key=lambda t: t.K)[-2:]
        Km = 0.5 * (lo.K + hi.K)
        if len(dec) == 2 and dec[1].b != dec[0].b:
            root = dec[1].K - dec[1].b * (dec[1].K - dec[0].K) / (dec[1].b - dec[0].b)
            if lo.K <= root <= hi.K:
                Km = root
        interval = (lo.K, hi.K)
    note = refine_note or ("" if (hi.K - lo.K) <= tol * lo.K else (
        f"bracket not refined to {tol:g} within {max_trials} records"))
    return Km, interval, trials, note
