"""What a run of a scene on its device is predicted to feel, and why an unstable one is
refused.

:func:`prepare_scene` calibrates the felt targets, :func:`predict` gives the closed loop's
felt pair, stability and identification order (the THS map of Florens, Voda & Urma for one
port link, :func:`hapsim.analysis.check_scene` otherwise), :func:`predicted_poles` the poles
the measurement (:mod:`hapsim.analysis.measurement`) compares with, :func:`refusal` the
error naming what is beyond which limit. Used by the daemon's runner, ``hapsim play`` and
the OSC controller alike; nothing here runs a loop.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hapsim.analysis.targets import apply_targets
from hapsim.errors import ConfigError, UnstableConfigError, dash
from hapsim.scene import Scene

__all__ = ["prepare_scene", "timed_scene", "predict", "predicted_poles", "has_offset",
           "port_links", "refusal", "require_device"]


_ZERO_POLE = 1e-9



def _analysis():
    """The analysis functions the runner uses, by name."""
    import hapsim.analysis as an
    return {name: getattr(an, name) for name in (
        "LoopModel", "closed_loop_poles", "render", "calibrate", "stability_limit",
        "fit_rendered", "check_scene")}



def port_links(scene: Scene):
    """The spring-dampers between the port and a ground (the links :func:`predict` renders
    as one port-ground wall).

    Parameters
    ----------
    scene : Scene

    Returns
    -------
    list of hapsim.scene.Link
        Empty without a port.
    """
    port = scene.port
    grounds = {m.name for m in scene.masses if m.kind == "ground"}
    return [lk for lk in scene.links if lk.kind == "spring_damper" and port is not None
            and {lk.m1, lk.m2} <= ({port.name} | grounds) and port.name in (lk.m1, lk.m2)]



def _links_at_port(scene: Scene):
    """Every link with the port at one end (contacts included, taken engaged)."""
    port = scene.port
    if port is None:
        return []
    return [lk for lk in scene.links if port.name in (lk.m1, lk.m2)]



def require_device(scene):
    """The scene's device, refusing a scene a run cannot close a loop on: no mass of kind
    ``port`` (nothing for a device to feel) or no device section. One refusal for every
    dimension and command (a 1-D, 2-D or 3-D scene: its masses' kinds and lines are the
    same fields).

    Parameters
    ----------
    scene : hapsim.scene.Scene or hapsim.scene.SceneND

    Returns
    -------
    hapsim.scene.Device or hapsim.scene.DeviceND
        ``scene.device``.

    Raises
    ------
    ConfigError
        No port (key ``masses``, the file and the first mass's line, the kinds its masses
        are, and what to do: a port, or ``hapsim check`` / ``hapsim simulate``, which take
        a scene without one), or a port without a device section (key ``device``).
    """
    if scene.port is None:
        first = scene.masses[0] if scene.masses else None
        kinds = sorted({m.kind for m in scene.masses})
        raise ConfigError(
            "the scene has no port: nothing for a device to feel (no mass is of kind "
            f"'port'; its masses are {', '.join(map(repr, kinds)) or 'none'}): give the "
            "handle's mass 'kind: port', or use 'hapsim check' or 'hapsim simulate', "
            "which take a scene without one",
            file=scene.path, line=(getattr(first, "line", 0) or None), key="masses")
    if scene.device is None:
        raise ConfigError("the scene has a port but no device section", file=scene.path,
                          key="device")
    return scene.device



def timed_scene(scene: Scene, latency_s: float) -> Scene:
    """The scene with ``latency_s`` [s] added to its device's delay (in periods): the loop
    of a board that renders that long after its read.

    Parameters
    ----------
    scene : Scene
        A scene with a device (hold ``zoh``: a fractional delay needs it).
    latency_s : float
        >= 0 [s].

    Returns
    -------
    Scene
        ``device.delay`` = the scene's + ``latency_s / T``, a real number of periods
        (modified z-transform: :mod:`hapsim.analysis.subsample`).
    """
    dev = scene.device
    d = float(dev.delay) + float(latency_s) / scene.period
    return dataclasses.replace(scene, device=dataclasses.replace(dev, delay=d))


def prepare_scene(scene: Scene, rate_hz: float | None = None, latency_s: float = 0.0):
    """Apply a rate override and calibrate every ``target`` link.

    Parameters
    ----------
    scene : Scene
        Validated scene with a port and a device.
    rate_hz : float, optional
        Rate override [Hz].
    latency_s : float, optional
        A board's render latency after its read [s] (the middle of its driver's bounds:
        :func:`hapsim.pipeline.render_latency.latency_middle`): the targets are calibrated
        for the loop with it in the delay (:func:`timed_scene`), the loop the board runs;
        the scene returned keeps its own device (its delay as written).

    Returns
    -------
    scene : Scene
        The scene with calibrated (K, B).
    targets : list of dict
        One per target link: ``link``, ``k``, ``b`` [N/m, N s/m], ``K``, ``B``,
        ``renderable``, ``reason``, ``f0_hz``, ``damping_ratio`` of the target oscillator.

    Raises
    ------
    ConfigError
        No port or device.
    UnrenderableTargetError
        A target is not renderable (message: file, line, ``links.NAME.target`` and the
        analysis's reason); a ConfigError and an UnstableConfigError.
    """
    if rate_hz is not None:
        scene = scene.with_rate(rate_hz)
    require_device(scene)
    if latency_s:
        timed, cals = apply_targets(timed_scene(scene, latency_s))
        scene = dataclasses.replace(timed, device=scene.device)
    else:
        scene, cals = apply_targets(scene)
    return scene, [c.to_dict() for c in cals]



def predict(scene: Scene, *, limit: bool = True) -> dict:
    """Predicted closed loop of a (calibrated) scene coupled to its device.

    Parameters
    ----------
    scene : Scene
        Calibrated scene with a port and a device.
    limit : bool, optional
        Compute ``stiffness_limit`` (the report's K_max; two thirds of a prediction's
        time). False: left None, for a caller that reads the pair and the stability only
        (the ~20 latencies a render-latency search and its spread predict at,
        :mod:`hapsim.pipeline.render_latency`; the run's own prediction has it).

    Returns
    -------
    dict
        ``k``, ``b`` [N/m, N s/m], ``f0_hz``, ``damping_ratio`` of the rendered pair (None
        when no pair), ``stable``, ``spectral_radius``, ``order`` (number of non-zero
        closed-loop poles, the identification order), ``stiffness_limit`` [N/m] of a
        port-ground spring at the summed B of the links at the port (the limit of those
        links alone, not of the felt k of a scene with virtual masses), ``port_K``,
        ``port_B`` [N/m, N s/m] (the links at the port, summed), ``source``
        (``"render"`` or ``"check_scene"``).

    Raises
    ------
    ConfigError
        When the scene cannot be analysed (no port/device).
    """
    dev = require_device(scene)
    an = _analysis()
    loop = an["LoopModel"].from_device(dev, scene.rate_hz)
    plinks = port_links(scene)
    B_port = sum(lk.damping for lk in _links_at_port(scene))
    K_port = sum(lk.stiffness for lk in plinks) if plinks else 0.0
    out = {"k": None, "b": None, "f0_hz": None, "damping_ratio": None, "stable": None,
           "spectral_radius": None, "order": None, "stiffness_limit": None, "source": None,
           "port_K": float(sum(lk.stiffness for lk in _links_at_port(scene))),
           "port_B": float(B_port)}
    try:
        if limit:
            out["stiffness_limit"] = float(an["stability_limit"](loop, B_port))
    except Exception:  # the limit is advisory in the report
        out["stiffness_limit"] = None
    single = len(scene.links) == 1 and len(plinks) == 1 and all(
        m.kind != "mass" for m in scene.masses) and scene.audio is None  # multi-rate: matrix
    if single:
        r = an["render"](loop, K_port, B_port)
        poles = np.asarray(an["closed_loop_poles"](loop, K_port, B_port))
        out.update(source="render", stable=bool(r.stable), spectral_radius=float(r.spectral_radius),
                   order=int(np.sum(np.abs(poles) > _ZERO_POLE)))
        if r.rendered is not None:
            out.update(k=float(r.k), b=float(r.b), f0_hz=float(r.f0_hz),
                       damping_ratio=float(r.damping_ratio))
        return out
    chk = an["check_scene"](scene)
    # identification order: the non-zero poles the port shows (a mode the hand cannot see,
    # participation below OBSERVABLE_TOL, is absent from the port's record)
    from hapsim.analysis.modes import OBSERVABLE_TOL
    order = sum(2 if md.kind == "pair" else 1 for md in chk.modes
                if abs(md.z) > _ZERO_POLE
                and (md.participation is None or md.participation >= OBSERVABLE_TOL))
    out.update(source="check_scene", stable=bool(chk.stable),
               spectral_radius=float(chk.spectral_radius), order=int(order))
    md = chk.rendered
    if md is not None:
        out.update(k=float(md.k), b=float(md.b), f0_hz=float(md.f0_hz),
                   damping_ratio=float(md.damping_ratio))
    return out



def has_offset(scene: Scene) -> bool:
    """Whether the port's free response settles away from 0 (identify with ``offset``).

    Decided from the scene's static equilibrium
    (:func:`hapsim.analysis.virtual_network.rest_position`: grounds' ``x0``, contact thresholds,
    every link), not from a list of causes; Coulomb friction (the mock's) stops the port
    anywhere in its dead band: an offset. A scene whose rest is not unique (a free part)
    has a pole at ``z = 1`` among the predicted ones, which the identification order
    counts and which carries the constant: no differencing then.

    Parameters
    ----------
    scene : Scene
        Scene with a device.

    Returns
    -------
    bool
    """
    from hapsim.analysis.virtual_network import rest_position
    dev = scene.device
    if dev.coulomb > 0:
        return True
    x = rest_position(scene)
    if x is None:
        return False
    scale = max([abs(m.x0) for m in scene.masses if m.kind == "ground"]
                + [abs(lk.threshold) for lk in scene.links if lk.kind == "contact"] + [0.0])
    return abs(x) > 1e-12 * scale



def _mass_limits(scene: Scene) -> list:
    """Closed-form limit of the scene's integrator at each virtual mass (module table of
    :mod:`hapsim.analysis.integrators`), the links at the mass summed (contacts engaged).

    Parameters
    ----------
    scene : Scene
        Calibrated scene.

    Returns
    -------
    list of dict
        One per virtual mass, worst first: ``mass`` (name), ``m`` [kg], ``K``, ``B`` (sums
        over its links) [N/m, N s/m], ``K_max`` [N/m] (``oscillator_limits`` at ``B``; <= 0
        when ``B`` alone is beyond the scheme), ``formula``, ``ratio`` (``K / K_max``; inf
        when ``K_max <= 0``), ``rate_hz`` (the rate above which the closed form holds, None
        when no rate does: exact integrator).
    """
    from hapsim.analysis.integrators import oscillator_limits
    integ = getattr(scene, "integrator", "centred")
    T = scene.period
    out = []
    for ms in scene.masses:
        if ms.kind != "mass":
            continue
        links = [lk for lk in scene.links if ms.name in (lk.m1, lk.m2)]
        K = sum(lk.stiffness for lk in links)
        B = sum(lk.damping for lk in links)
        lim = oscillator_limits(integ, ms.mass, T, B)
        kmax = float(lim["K_max"])
        ratio = (K / kmax if kmax > 0 else math.inf) if K > 0 or kmax <= 0 else 0.0
        m = float(ms.mass)
        root = math.sqrt(4 * B * B + 16 * m * K)
        if integ == "centred":      # 4 m f^2 - 2 B f > K and B < 2 m f
            rate = max((2 * B + root) / (8 * m), B / (2 * m))
        elif integ == "symplectic_euler":   # 4 m f^2 + 2 B f > K
            rate = (-2 * B + root) / (8 * m)
        else:
            rate = None
        out.append({"mass": ms.name, "m": m, "K": K, "B": B, "K_max": kmax,
                    "formula": lim["formula"], "ratio": ratio, "rate_hz": rate})
    out.sort(key=lambda d: -d["ratio"])
    return out



def refusal(scene: Scene, pred: dict) -> UnstableConfigError:
    """The error refusing an unstable scene, naming what is beyond which limit.

    Three cases: a virtual mass beyond its integrator's closed-form limit
    (:func:`_mass_limits`; advice: lower the stiffness there, another integrator, a higher
    rate), the links at the port beyond the THS limit ``stability_limit`` (advice: lower K,
    a higher rate, and raise B only where that raises ``K_max``), or neither closed form
    but the whole loop (:func:`hapsim.analysis.integrators.stability_margin`: coupled modes).

    Parameters
    ----------
    scene : Scene
        Calibrated scene the analysis found unstable.
    pred : dict
        Its :func:`predict` result.

    Returns
    -------
    UnstableConfigError
        With the spectral radius and the stiffness limit of the case found.
    """
    from hapsim.analysis.integrators import stability_margin
    dev = scene.device
    integ = getattr(scene, "integrator", "centred")
    rho = pred["spectral_radius"]
    head = (f"{scene.path}: the closed loop is unstable: spectral radius {rho:.9g} >= 1 "
            f"(integrator {integ}; device m = {dev.mass:g} kg, b0 = {dev.friction:g} N s/m, "
            f"d = {dev.delay}, {dev.hold}, {scene.rate_hz:g} Hz)")
    tail = "; or pass --allow-unstable to run it under the safety stops"
    at_port = _links_at_port(scene)
    B = sum(lk.damping for lk in at_port)
    K = sum(lk.stiffness for lk in at_port)
    lim = pred["stiffness_limit"]
    port_bad = lim is not None and K >= lim
    masses = _mass_limits(scene)
    worst = masses[0] if masses and masses[0]["ratio"] >= 1.0 else None
    try:
        margin = stability_margin(scene).limit_description
    except Exception:  # the description is advice; the verdict is pred's
        margin = None
    if worst is not None:
        w = worst
        limit = (f"K < {w['K_max']:.6g} N/m" if w["K_max"] > 0
                 else f"no K: B = {w['B']:g} N s/m is beyond its damping limit")
        port = (f"the links at the port are within their limit (K = {K:g} N/m < K_max = "
                f"{lim:.6g} N/m at B = {B:g} N s/m)" if lim is not None and not port_bad
                else f"the links at the port are beyond their limit too (K = {K:g} N/m, "
                     f"K_max = {dash(lim, '.6g')} N/m at B = {B:g} N s/m)")
        alt = []
        if integ == "centred":
            from hapsim.analysis.integrators import oscillator_limits
            kse = oscillator_limits("symplectic_euler", w["m"], scene.period, w["B"])["K_max"]
            alt.append(f"symplectic_euler (K < {kse:.6g} N/m here: "
                       f"{'enough' if w['K'] < kse else 'not enough'})")
        if integ != "exact":
            alt.append("exact (no limit for a passive network)")
        rate = (f", or raise the rate above {w['rate_hz']:.6g} Hz (closed form)"
                if w["rate_hz"] else "")
        net = margin or f"integrator {integ}: {w['formula']}"
        msg = (f"{head}. {port[0].upper() + port[1:]}; the virtual network is not: {net}. "
               f"Virtual mass {w['mass']!r} ({w['m']:g} kg): its links sum to K = "
               f"{w['K']:g} N/m, B = {w['B']:g} N s/m; {integ} allows {limit} "
               f"(K / K_max = {w['ratio']:.4g}). Lower the stiffness at {w['mass']!r} below "
               f"{max(w['K_max'], 0.0):.6g} N/m, use integrator {' or '.join(alt)}{rate}{tail}")
        return UnstableConfigError(msg, spectral_radius=rho, stiffness_limit=w["K_max"])
    if port_bad:
        an = _analysis()
        raise_b = False
        try:
            loop = an["LoopModel"].from_device(dev, scene.rate_hz)
            raise_b = float(an["stability_limit"](loop, 1.25 * B + 0.1)) > lim
        except Exception:  # advice only
            pass
        msg = (f"{head}: the links at the port (contacts engaged: K = {K:g} N/m, B = {B:g} "
               f"N s/m) are beyond the stiffness limit K_max = {lim:.6g} N/m at this B. "
               f"Lower K{', raise B' if raise_b else ''} or raise the rate{tail}")
        return UnstableConfigError(msg, spectral_radius=rho, stiffness_limit=lim)
    msg = (f"{head}: no single link or mass is beyond its closed-form limit (links at the "
           f"port K = {K:g} N/m < K_max = {dash(lim, '.6g')} N/m at B = {B:g} N s/m), the "
           f"coupled modes are" + (f": {margin}" if margin else "") +
           f". Lower the stiffnesses, use another integrator"
           f"{' (symplectic_euler, exact)' if integ == 'centred' else ''} or raise the "
           f"rate{tail}")
    return UnstableConfigError(msg, spectral_radius=rho, stiffness_limit=lim)



def predicted_poles(scene: Scene):
    """Predicted non-zero closed-loop poles seen at the port and the felt one (or None).

    The same models as :func:`predict`: the THS map for one port link, ``check_scene``
    (observable modes, conjugates added) otherwise.

    Parameters
    ----------
    scene : Scene
        Calibrated scene with a port and a device.

    Returns
    -------
    poles : ndarray of complex, shape (order,)
        The non-zero poles (``|z| > 1e-9``) the port's record shows.
    felt : complex or None
        The felt pole (None when the loop renders no pair).
    """
    an = _analysis()
    dev = scene.device
    plinks = port_links(scene)
    single = len(scene.links) == 1 and len(plinks) == 1 and all(
        m.kind != "mass" for m in scene.masses) and scene.audio is None
    if single:
        loop = an["LoopModel"].from_device(dev, scene.rate_hz)
        K = sum(lk.stiffness for lk in plinks)
        B = sum(lk.damping for lk in _links_at_port(scene))
        r = an["render"](loop, K, B)
        z = np.asarray(an["closed_loop_poles"](loop, K, B), dtype=complex)
        felt = None if r.rendered is None else complex(r.rendered.z)
        return z[np.abs(z) > _ZERO_POLE], felt
    from hapsim.analysis.modes import OBSERVABLE_TOL
    chk = an["check_scene"](scene)
    z = []
    for md in chk.modes:
        if abs(md.z) > _ZERO_POLE and (md.participation is None
                                       or md.participation >= OBSERVABLE_TOL):
            z += [md.z, complex(md.z).conjugate()] if md.kind == "pair" else [md.z]
    felt = None if chk.rendered is None else complex(chk.rendered.z)
    return np.asarray(z, dtype=complex), felt
