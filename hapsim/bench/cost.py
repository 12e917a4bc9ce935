"""Chart 2: accuracy of the virtual modes against CPU cost, per integrator.

Two virtual networks, no port: a single oscillator and a 50-mass string between two
grounds (the network of ``configs/string.yaml`` without its plucking port). For each
integrator and rate, the discrete modes are the eigenvalues ``z`` of the integrator's
one-step matrix (:func:`hapsim.bench.methods.virtual_update_matrix`, the map the kernels run;
tests check the two agree), read as ``s = ln(z)/T`` and compared with the continuous
eigenvalues ``lambda`` of the same network (:func:`continuous_network_eigenvalues`):

- frequency error ``max_i | |s_i| - |lambda_i| | / |lambda_i|``,
- damping error ``max_i |Re s_i - Re lambda_i| / |Re lambda_i|``.

The cost is measured in the same run: median over repeats of the wall time of
:meth:`hapsim.engine.Engine.run` divided by the samples [ns per simulated sample], and its
product with the rate, the CPU time per simulated second (what a real-time loop pays).
"""

from __future__ import annotations

import math
import time

import numpy as np

from hapsim.analysis.integrators import (INTEGRATORS, continuous_network_eigenvalues,
                                  spectral_radius_of, virtual_update_matrix)
from hapsim.scene import parse_scene

__all__ = ["oscillator_scene", "string_scene", "mode_errors", "time_per_sample",
           "accuracy_vs_cost", "FULL_RATES", "QUICK_RATES"]

#: Rates of the full chart [Hz].
FULL_RATES = (250.0, 500.0, 1000.0, 2000.0, 5000.0, 10000.0, 20000.0)
#: Rates of ``--quick`` [Hz].
QUICK_RATES = (500.0, 2000.0, 10000.0)


def oscillator_scene(rate_hz: float = 1000.0, *, mass: float = 0.1, K: float = 1000.0,
                     B: float = 0.2, integrator: str = "centred"):
    """A virtual mass on a spring-damper to a ground (``configs/oscillator.yaml``, damped).

    Parameters
    ----------
    rate_hz : float
        [Hz].
    mass, K, B : float
        [kg], [N/m], [N s/m].
    integrator : str

    Returns
    -------
    hapsim.scene.Scene
    """
    text = (f"rate_hz: {rate_hz!r}\nintegrator: {integrator}\nmasses:\n"
            f"  - {{name: anchor, kind: ground}}\n"
            f"  - {{name: bob, kind: mass, mass: {mass!r}, x0: 0.01}}\n"
            f"links:\n  - {{name: spring, kind: spring_damper, between: [bob, anchor], "
            f"stiffness: {K!r}, damping: {B!r}}}\n")
    return parse_scene(text, "<oscillator>")


def string_scene(rate_hz: float = 1000.0, *, n: int = 50, mass: float = 0.01,
                 K: float = 2000.0, B: float = 0.0005, integrator: str = "centred"):
    """``n`` beads between two grounds (``configs/string.yaml`` without its port).

    Parameters
    ----------
    rate_hz : float
        [Hz].
    n : int
        Number of beads.
    mass, K, B : float
        Bead mass [kg], segment stiffness [N/m] and damping [N s/m].
    integrator : str

    Returns
    -------
    hapsim.scene.Scene
        The middle bead starts displaced by 1 mm.
    """
    lines = [f"rate_hz: {rate_hz!r}", f"integrator: {integrator}", "masses:",
             "  - {name: left, kind: ground}"]
    for i in range(1, n + 1):
        x0 = 0.001 if i == (n + 1) // 2 else 0.0
        lines.append(f"  - {{name: s{i}, kind: mass, mass: {mass!r}, x0: {x0!r}}}")
    lines += ["  - {name: right, kind: ground}", "links:"]
    names = ["left"] + [f"s{i}" for i in range(1, n + 1)] + ["right"]
    for i in range(n + 1):
        lines.append(f"  - {{kind: spring_damper, between: [{names[i]}, {names[i + 1]}], "
                     f"stiffness: {K!r}, damping: {B!r}}}")
    return parse_scene("\n".join(lines) + "\n", "<string>")


def _match(zd: np.ndarray, lam: np.ndarray, T: float, integrator: str):
    """Pair discrete poles with continuous eigenvalues (upper half plane); ``s_d`` per ``lambda``."""
    lam_u = np.sort_complex(lam[lam.imag > 0])
    lam_u = lam_u[np.argsort(lam_u.imag)]
    if integrator == "exact":
        # z = exp(lambda T) by construction: nearest pole, log on lambda's branch
        zc = np.exp(lam_u * T)
        zu = list(zd)
        out = []
        for lc, z in zip(lam_u, zc):
            j = int(np.argmin(np.abs(np.array(zu) - z)))
            zz = zu.pop(j)
            s = np.log(zz) / T
            kk = round((lc.imag - s.imag) * T / (2 * math.pi))
            out.append(s + 2j * math.pi * kk / T)
        return lam_u, np.array(out)
    zu = zd[zd.imag > 1e-14]
    if zu.size != lam_u.size:
        return lam_u, None
    s = np.log(zu) / T
    s = s[np.argsort(s.imag)]
    return lam_u, s


def mode_errors(scene, integrator: str) -> dict:
    """Frequency and damping errors of an integrator's modes against the continuous network.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A network without port.
    integrator : str

    Returns
    -------
    dict
        ``stable`` (bool), ``spectral_radius``, ``freq_err`` and ``damp_err`` (max relative
        errors, None when unstable or when the discrete modes do not pair up, e.g. a mode
        pushed onto the real axis), ``modes`` (number of oscillating modes).
    """
    A = virtual_update_matrix(scene, integrator)
    rho, stable = spectral_radius_of(A)
    zd = np.linalg.eigvals(A)
    lam = continuous_network_eigenvalues(scene)
    out = {"stable": stable, "spectral_radius": rho, "freq_err": None, "damp_err": None,
           "modes": int(np.sum(lam.imag > 0))}
    if not stable:
        return out
    lam_u, s = _match(zd, lam, scene.period, integrator)
    if s is None:
        return out
    fe = np.abs(np.abs(s) - np.abs(lam_u)) / np.abs(lam_u)
    de = np.abs(s.real - lam_u.real) / np.abs(lam_u.real)
    out["freq_err"] = float(fe.max())
    out["damp_err"] = float(de.max())
    return out


def time_per_sample(scene, *, samples: int = 20000, repeats: int = 5) -> float:
    """Median CPU wall time of :meth:`Engine.run` per sample [ns] (compiled, nothing recorded).

    Parameters
    ----------
    scene : hapsim.scene.Scene
    samples : int
        Samples per repeat.
    repeats : int
        Repeats (median taken).

    Returns
    -------
    float
        [ns / sample].
    """
    from hapsim.engine import Engine

    eng = Engine(scene)
    eng.run(10, record=[])  # compile / load cache
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        eng.run(samples, record=[])
        times.append((time.perf_counter_ns() - t0) / samples)
    return float(np.median(times))


def accuracy_vs_cost(rates=FULL_RATES, *, samples: int = 20000, repeats: int = 5,
                     integrators=INTEGRATORS, string_n: int = 50) -> dict:
    """Data of chart 2.

    Parameters
    ----------
    rates : sequence of float
        [Hz].
    samples, repeats : int
        Timing budget (:func:`time_per_sample`).
    integrators : sequence of str
    string_n : int
        Beads of the string.

    Returns
    -------
    dict
        JSON-ready: ``networks``: list of ``{name, description, ns_per_sample {integrator:
        ns}, ratio_to_centred {integrator: x}, points: [{integrator, rate_hz, stable,
        spectral_radius, freq_err, damp_err, cpu_ms_per_simulated_s}]}``.
    """
    nets = [("oscillator", "m = 0.1 kg, K = 1000 N/m, B = 0.2 N s/m to ground",
             oscillator_scene),
            ("string", f"{string_n} beads of 10 g, 2000 N/m and 0.0005 N s/m segments",
             lambda r, integrator="centred": string_scene(r, n=string_n, integrator=integrator))]
    out = {"networks": [], "samples": samples, "repeats": repeats,
           "freq_err": "max_i ||s_i| - |lambda_i|| / |lambda_i|",
           "damp_err": "max_i |Re s_i - Re lambda_i| / |Re lambda_i|"}
    for name, desc, make in nets:
        ns = {}
        for integ in integrators:
            ns[integ] = time_per_sample(make(1000.0, integrator=integ), samples=samples,
                                        repeats=repeats)
        pts = []
        for integ in integrators:
            for r in rates:
                e = mode_errors(make(r, integrator=integ), integ)
                e.update({"integrator": integ, "rate_hz": float(r),
                          "cpu_ms_per_simulated_s": ns[integ] * r * 1e-6})
                pts.append(e)
        base = ns.get("centred", next(iter(ns.values())))
        out["networks"].append({"name": name, "description": desc, "ns_per_sample": ns,
                                "ratio_to_centred": {k: v / base for k, v in ns.items()},
                                "points": pts})
    return out
