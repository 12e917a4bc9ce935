"""The experiment of Table 1 of Florens, Voda & Urma: real and virtual springs do not add up.

A real mass ``m`` is coupled to

    I    a real spring ``k``                 continuous:  m x'' + k x = 0
    II   a virtual spring ``K``              sampled loop (m/T^2)(z - 1)^2 + K z = 0 (eq. 1),
                                             K tuned by eq. (2) so that II rings like I
    III  two real springs (2k)               continuous:  m x'' + 2 k x = 0
    IV   two virtual springs (2K)            sampled loop (m/T^2)(z - 1)^2 + 2 K z = 0
    V    a virtual K and a real k            sampled loop around the real mass-spring

in the paper's idealised simulator: no computation delay (d = 0), "no holder" (the ideal
sampled image, docs/design.md, 'The characteristic equation': the image of the real mass
is the centred-difference mass
``x[n+1] - 2 x[n] + x[n-1] = T^2 f[n] / m``) and no damping. Eq. (2),
``K = (m/T^2)(2 - 2 cos(T sqrt(k/m)))``, makes II equal to I exactly; III, IV and V then
differ, and more so as ``k T^2 / m`` grows: the hybrid real/virtual world is not consistent
with either world alone (paper Sec. 3).

Choice for V (documented, not in the paper). The real spring belongs to the plant:
``m x'' + k x = f``. Its sampled image is taken *in the same ideal spirit* as the plain mass:
the force samples act as impulses of area ``T f[n]`` at ``t = nT`` (the input for which the
image of the mass alone is exactly the centred-difference mass above, since
``x[n+1] - 2x[n] + x[n-1] = T^2 f[n]/m`` holds exactly for impulses). With
``w0 = sqrt(k/m)`` the exact pulse transfer of the mass-spring to such impulses is

    G(z) = (T / (m w0)) sin(w0 T) z / (z^2 - 2 cos(w0 T) z + 1),

(it tends to ``T^2 z / (m (z - 1)^2)`` as ``k -> 0``), and V's closed loop with ``d = 0``,
``F[n] = -K x[n]``, is ``z^2 - (2 cos(w0 T) - (T sin(w0 T) / (m w0)) K) z + 1 = 0``. So V differs
from III only by what the virtual spring adds, and from IV only by what the real spring
adds.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.analysis.modes import modes_from_poles
from hapsim.errors import ConfigError

__all__ = ["tuned_stiffness", "table1_experiment", "table1_markdown", "DEFAULT_K_VALUES"]

#: Default sweep of ``k T^2 / m`` (the last value puts IV beyond its stability limit).
DEFAULT_K_VALUES = (0.01, 0.1, 0.5, 1.0, 2.0, 3.0)


def tuned_stiffness(k: float, mass: float = 1.0, period: float = 1.0) -> float:
    """Virtual stiffness that rings like a real spring: Florens et al. eq. (2).

    Parameters
    ----------
    k : float >= 0
        Real stiffness [N/m]; ``T sqrt(k/m) < pi`` for a one-to-one tuning.
    mass : float > 0
        Real mass ``m`` [kg].
    period : float > 0
        Sample period ``T`` [s].

    Returns
    -------
    float
        ``K = (m/T^2)(2 - 2 cos(T sqrt(k/m)))`` [N/m].
    """
    return mass / period ** 2 * (2.0 - 2.0 * math.cos(period * math.sqrt(k / mass)))


def _sampled(coeffs, mass: float, period: float):
    """(omega [rad/s], |z|max, stable) of the least damped mode of a real polynomial."""
    poles = np.roots(np.asarray(coeffs, dtype=float))
    modes = modes_from_poles(poles, mass, period)
    top = modes[0]
    radius = max(abs(complex(p)) for p in poles)
    return 2.0 * math.pi * top.f0_hz, radius, radius < 1.0 + 1e-12


def table1_experiment(k_values=DEFAULT_K_VALUES, *, mass: float = 1.0,
                      period: float = 1.0) -> list[dict]:
    """Eigenfrequencies of the five couplings of Florens et al. Table 1.

    Parameters
    ----------
    k_values : sequence of float > 0
        Real stiffnesses ``k`` [N/m]; with the defaults ``m = T = 1`` these are the
        normalised ``k T^2 / m``. Each must satisfy ``T sqrt(k/m) < pi`` (eq. 2 is then
        one-to-one).
    mass : float > 0, default 1.0
        Real mass ``m`` [kg].
    period : float > 0, default 1.0
        Sample period ``T`` [s].

    Returns
    -------
    list of dict
        One dict per ``k``, with keys

        ``k``, ``kT2_m`` (``k T^2 / m``), ``K`` (eq. 2) [N/m];
        ``w_I``, ``w_II``, ``w_III``, ``w_IV``, ``w_V``: eigenfrequency of each system
        [rad/s] (undamped natural frequency ``|s|``, ``s = ln(z)/T`` for the sampled ones;
        for an unstable system, ``|s|`` of its least damped mode);
        ``stable_II``, ``stable_IV``, ``stable_V`` (bool: spectral radius <= 1);
        ``radius_IV``, ``radius_V`` (spectral radius);
        ``dev_II_I``, ``dev_IV_III``, ``dev_V_III``, ``dev_IV_V``: relative frequency
        deviations ``w_a / w_b - 1``;
        ``kfelt_IV``, ``kfelt_V``: the real stiffness that would ring like IV and V,
        ``m w^2``, divided by ``2k`` (1 would be consistent) [-].

    Raises
    ------
    ConfigError
        On non-positive ``k``, ``mass``, ``period``, or ``T sqrt(k/m) >= pi``.

    Notes
    -----
    I and III are continuous (``w = sqrt(k/m)``, ``sqrt(2k/m)``); II and IV are the roots of
    eq. (1) ``(m/T^2)(z-1)^2 + K z = 0`` with ``K`` and ``2K``; V uses the ideal sampled
    image of the real mass-spring (module docstring).
    """
    if not (mass > 0 and period > 0 and math.isfinite(mass) and math.isfinite(period)):
        raise ConfigError("mass and period must be positive numbers", key="mass/period")
    rows = []
    c = mass / period ** 2
    for k in k_values:
        k = float(k)
        if not (k > 0 and math.isfinite(k)):
            raise ConfigError(f"each k must be a positive number, got {k!r}", key="k_values")
        w0 = math.sqrt(k / mass)
        if w0 * period >= math.pi:
            raise ConfigError(f"T sqrt(k/m) = {w0 * period:.4g} >= pi: eq. (2) cannot tune a "
                              "virtual spring to that frequency", key="k_values")
        K = tuned_stiffness(k, mass, period)
        w_I, w_III = w0, math.sqrt(2.0 * k / mass)
        # (m/T^2)(z - 1)^2 + K z = c z^2 + (K - 2c) z + c
        w_II, _, st_II = _sampled([c, K - 2.0 * c, c], mass, period)
        w_IV, r_IV, st_IV = _sampled([c, 2.0 * K - 2.0 * c, c], mass, period)
        # z^2 - (2 cos(w0 T) - (T sin(w0 T) / (m w0)) K) z + 1
        gain = period * math.sin(w0 * period) / (mass * w0)
        w_V, r_V, st_V = _sampled([1.0, -(2.0 * math.cos(w0 * period) - gain * K), 1.0],
                                  mass, period)
        rows.append({
            "k": k, "kT2_m": k * period ** 2 / mass, "K": K,
            "w_I": w_I, "w_II": w_II, "w_III": w_III, "w_IV": w_IV, "w_V": w_V,
            "stable_II": st_II, "stable_IV": st_IV, "stable_V": st_V,
            "radius_IV": r_IV, "radius_V": r_V,
            "dev_II_I": w_II / w_I - 1.0, "dev_IV_III": w_IV / w_III - 1.0,
            "dev_V_III": w_V / w_III - 1.0, "dev_IV_V": w_IV / w_V - 1.0,
            "kfelt_IV": mass * w_IV ** 2 / (2.0 * k), "kfelt_V": mass * w_V ** 2 / (2.0 * k),
        })
    return rows


def table1_markdown(rows: list[dict]) -> str:
    """Format :func:`table1_experiment` rows as a Markdown table.

    Parameters
    ----------
    rows : list of dict
        Output of :func:`table1_experiment`.

    Returns
    -------
    str
        A Markdown table (frequencies in rad/s, i.e. rad per sample for ``T = 1``;
        deviations ``w_a / w_b - 1`` in percent; felt stiffness ``m w^2`` over ``2k``).
    """
    head = ("| k T²/m | K (eq. 2) | ω I | ω II | ω III (2k) | ω IV (2K) | ω V (K + k) "
            "| IV vs III | V vs III | IV vs V | felt k IV / 2k | felt k V / 2k |\n"
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n")
    out = []
    for r in rows:
        w_iv = f"{r['w_IV']:.5f}" + ("" if r["stable_IV"] else
                                     f" (unstable, \\|z\\| = {r['radius_IV']:.3f})")
        out.append(f"| {r['kT2_m']:g} | {r['K']:.5f} | {r['w_I']:.5f} | {r['w_II']:.5f} "
                   f"| {r['w_III']:.5f} | {w_iv} | {r['w_V']:.5f} "
                   f"| {100 * r['dev_IV_III']:+.3g} % | {100 * r['dev_V_III']:+.3g} % "
                   f"| {100 * r['dev_IV_V']:+.3g} % | {r['kfelt_IV']:.4f} | {r['kfelt_V']:.4f} |")
    return head + "\n".join(out) + "\n"
