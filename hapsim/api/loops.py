"""``render``, ``calibrate``, ``stability``: the real side of a 1-DoF loop
(:class:`hapsim.analysis.loop.LoopModel`) with a virtual spring."""

from __future__ import annotations

import dataclasses
import math


from hapsim.option_values import check_values
from hapsim.api.common import Charted, known_digits
from hapsim.results import Report


# ---------------------------------------------------------------------------- a loop
@dataclasses.dataclass(frozen=True)
class RenderReport(Charted, Report):
    """What ``hapsim render --json`` says: the (k, b) felt for a virtual (K, B).

    Attributes
    ----------
    K, B : float
        Virtual stiffness [N/m] and damping [N s/m] simulated.
    k, b : float
        Felt stiffness [N/m] and damping [N s/m] (b includes the device's friction).
    f0_hz, damping_ratio : float
        Of the felt pole pair.
    stable, marginal : bool
    spectral_radius : float
    rendered : dict
        The felt mode (as :attr:`CheckReport.rendered`).
    modes : list of dict
    note : str or None
    loop : dict
        The :class:`LoopModel` (mass, friction, rate_hz, delay, hold).

    Other attributes: ``analysis``, the :class:`~hapsim.analysis.ths.RenderResult`.
    """

    K: float
    B: float
    k: float
    b: float
    f0_hz: float
    damping_ratio: float
    stable: bool
    marginal: bool
    spectral_radius: float
    rendered: dict | None
    modes: list
    note: str | None
    loop: dict

    @property
    def eigenvalues(self) -> list:
        """Closed-loop poles as [re, im] (from :attr:`modes`)."""
        return [[m["z_re"], m["z_im"]] for m in self.modes]


def render(loop, K: float, B: float = 0.0) -> RenderReport:
    """The stiffness k and damping b felt for a virtual spring K and damper B.

    Parameters
    ----------
    loop : LoopModel
        The real side: ``mass`` [kg], ``friction`` [N s/m], ``rate_hz`` [Hz], ``delay``
        [samples], ``hold`` (``"zoh"`` or ``"ideal"``).
    K : float
        Virtual stiffness [N/m].
    B : float
        Virtual damping [N s/m].

    Returns
    -------
    RenderReport

    Raises
    ------
    ConfigError
        A non-finite K or B (keyed ``--K`` / ``--B``: the declaration and message of
        ``hapsim render``'s, :data:`hapsim.option_values.API_OPTIONS`).

    Notes
    -----
    :func:`hapsim.analysis.ths.render`: the least damped closed-loop pole pair z,
    ``s = ln(z) / T``, ``k = m |s|^2``, ``b = -2 m Re(s)`` (Florens, Voda & Urma).
    """
    from hapsim.analysis.ths import render as _render
    check_values("render", required=True, K=K, B=B)
    r = _render(loop, K, B)
    return RenderReport.from_dict({**r.to_dict(), "loop": loop.to_dict()}, analysis=r)


@dataclasses.dataclass(frozen=True)
class CalibrateReport(Report):
    """What ``hapsim calibrate --json`` says: the (K, B) that render a felt (k, b).

    Attributes
    ----------
    k, b : float
        The target felt stiffness [N/m] and damping [N s/m].
    K, B : float
        The virtual stiffness [N/m] and damping [N s/m] to simulate.
    renderable : bool
    reason : str
    spectral_radius : float
    target : dict
        The target oscillator (``f0_hz``, ``damping_ratio``, ...).
    modes : list of dict
    loop : dict

    Other attributes: ``analysis``, the :class:`~hapsim.analysis.ths.CalibrationResult`.
    """

    k: float
    b: float
    K: float
    B: float
    renderable: bool
    reason: str
    spectral_radius: float
    target: dict
    modes: list
    loop: dict


def calibrate(loop, k: float, b: float) -> CalibrateReport:
    """The virtual (K, B) that make the hand feel (k, b).

    Parameters
    ----------
    loop : LoopModel
    k : float
        Felt stiffness to render [N/m], > 0.
    b : float
        Felt damping to render [N s/m].

    Returns
    -------
    CalibrateReport
        ``renderable`` False (with the reason) when no stable (K, B) renders it.

    Raises
    ------
    ConfigError
        ``k <= 0`` or a non-finite target (keyed ``--k`` / ``--b``, as ``hapsim
        calibrate`` says it: :data:`hapsim.option_values.API_OPTIONS`).

    Notes
    -----
    :func:`hapsim.analysis.ths.calibrate`: the inverse of :func:`render`, solved for the
    pole pair of the target oscillator (Florens, Voda & Urma).
    """
    from hapsim.analysis.ths import calibrate as _calibrate
    check_values("calibrate", required=True, k=k, b=b)
    c = _calibrate(loop, k, b)
    return CalibrateReport.from_dict({**c.to_dict(), "loop": loop.to_dict()}, analysis=c)


@dataclasses.dataclass(frozen=True)
class StabilityReport(Report):
    """What ``hapsim stability --json`` says: the largest stable K for a damping B.

    Attributes
    ----------
    K_max : float or None
        Exact stability limit [N/m] (None when unbounded).
    K_max_method : str
        ``"certified"`` (proven in exact arithmetic: no crossing of ``|z| = 1`` below, a
        guaranteed bracket; :mod:`hapsim.analysis.limit_certificate`) or ``"sampled (N)"``
        (the scan of ``N`` points of the circle, not proven between them).
    K_max_interval : [float, float] or None
        The guaranteed bracket ``[K_lo, K_hi]`` [N/m] when certified (``[0, 0]``: no
        ``K > 0`` stable; ``[None, None]``: every ``K > 0`` proven stable), else None.
    K_max_certificate : str
        What was proven (certified) or why it could not be (sampled).
    B : float
        Virtual damping [N s/m].
    spectral_radius_at_K_max, spectral_radius_error : float or None
        The spectral radius there, to the digits double arithmetic knows, and its error.
    passivity_K, diolaiti_K, centred_difference_K : float
        Published limits [N/m]: Colgate & Schenkel 1997 (passivity, sufficient), Diolaiti
        et al. 2006 (first order in b0 T / m), the centred difference (ideal, d = 0).
    loop : dict
    """

    K_max: float | None
    K_max_method: str
    K_max_interval: list | None
    K_max_certificate: str
    B: float
    spectral_radius_at_K_max: float | None
    spectral_radius_error: float | None
    passivity_K: float
    diolaiti_K: float
    centred_difference_K: float
    loop: dict


def stability(loop, B: float = 0.0) -> StabilityReport:
    """The largest virtual stiffness K the loop keeps stable, for a damping B.

    Parameters
    ----------
    loop : LoopModel
    B : float
        Virtual damping [N s/m].

    Returns
    -------
    StabilityReport

    Raises
    ------
    ConfigError
        A non-finite B (keyed ``--B``, as ``hapsim stability`` says it:
        :data:`hapsim.option_values.API_OPTIONS`).

    Notes
    -----
    :func:`hapsim.analysis.stability.stability_limit` (the exact boundary of the THS, a scan of
    the unit circle), proven by :func:`hapsim.analysis.limit_certificate.certify_limit`
    where exact arithmetic can (the crossing condition as a polynomial in ``cos theta``,
    Sturm's theorem, the Schur-Cohn-Jury test), beside
    :func:`hapsim.analysis.stability.published_limits`.
    """
    from hapsim.analysis.limit_certificate import certify_limit
    from hapsim.analysis.loop_poles import spectral_radius_known
    from hapsim.analysis.stability import circle_scan_points, published_limits, stability_limit
    check_values("stability", required=True, B=B)
    kmax = stability_limit(loop, B)
    cert = certify_limit(loop, B, kmax, circle_scan_points(loop))
    rho = err = None
    if math.isfinite(kmax):
        rho, err = spectral_radius_known(loop, kmax, B)
        rho = known_digits(rho, err)
    iv = None if cert.interval is None else [
        v if math.isfinite(v) else None for v in cert.interval]
    return StabilityReport.from_dict({
        "K_max": kmax if math.isfinite(kmax) else None, "K_max_method": cert.method,
        "K_max_interval": iv, "K_max_certificate": cert.note, "B": B,
        "spectral_radius_at_K_max": rho, "spectral_radius_error": err,
        **published_limits(loop, B), "loop": loop.to_dict()})
