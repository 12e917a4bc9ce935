"""Model no more than a scene needs: the lowest rate and cheapest method that are good enough.

:func:`advise_scene` answers, for each link to the port and for the scene as a whole, the
lowest sample rate (from :data:`RATES`) and the cheapest method that keep

1. **accuracy**: the felt ``(k, b)`` within ``tolerance`` (relative, on k and on b) of what the
   scene asks for: a ``target`` link asks for its ``(k, b)``; a plain link asks for
   ``(K, B + b0)`` (its own stiffness, its damping plus the device friction: the felt
   oscillator of a continuous, undelayed loop); for the scene as a whole, the least damped
   pair of the continuous-time loop (device + network, no sampling, no delay,
   :func:`hapsim.bench.methods.continuous_loop_matrix`);
2. **stability with margin**: the closed loop (device, hold, delay, integrator) stays stable
   when every link's ``(K, B)`` is multiplied by ``1 / margin`` (default ``margin = 0.95``:
   a 5 % gain margin; for one port-ground link this is ``K <= 0.95 K_max`` along the ray
   through ``(K, B)``).

Why a gain margin and not "spectral radius <= 0.95": the radius of any fixed continuous
oscillator tends to 1 as the rate grows (``|z| = exp(-zeta w T)``), so a bound on it would
forbid high rates for lightly damped scenes, the opposite of a safety margin. The gain margin
is rate-independent and means what the brief intends: a 5 % error in K or B (a heavier hand,
a drift in friction) does not make the loop unstable.

Methods, cheapest first: per port link ``naive`` (send ``K, B`` as written) then
``calibrated`` (send the ``(K, B)`` of :func:`hapsim.analysis.calibrate` for the wanted
``(k, b)``; free at run time, only the set-up solves two equations); per scene the
integrators of :data:`hapsim.bench.methods.COST_ORDER` (``exact`` excluded with contacts;
without virtual masses the integrator does not matter and ``centred`` is kept).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.analysis import LoopModel, calibrate, render, spectral_radius
from hapsim.analysis.family_loops import require_port_scene
from hapsim.analysis.modes import modes_from_poles, rendered_pair
from hapsim.analysis.integrators import (COST_ORDER, closed_loop_matrix, continuous_loop_matrix,
                                  spectral_radius_of)
from hapsim.errors import ConfigError, UnstableConfigError
from hapsim.outputs import finite_or_none

__all__ = ["RATES", "LinkAdvice", "Advice", "advise_scene", "board_timing",
           "felt_pair_error", "felt_matrix_error"]

#: Candidate rates [Hz]: the R10 preferred numbers from 250 Hz to 20 kHz.
RATES = (250.0, 315.0, 400.0, 500.0, 630.0, 800.0, 1000.0, 1250.0, 1600.0, 2000.0, 2500.0,
         3150.0, 4000.0, 5000.0, 6300.0, 8000.0, 10000.0, 12500.0, 16000.0, 20000.0)


def felt_pair_error(k: float, b: float, k_ref: float, b_ref: float) -> float:
    """``max(|k - k_ref| / k_ref, |b - b_ref| / b_ref)`` [-] (a zero reference is skipped).

    Parameters
    ----------
    k, b : float
        Felt stiffness [N/m] and damping [N s/m] (nan: no pair -> inf).
    k_ref, b_ref : float
        Wanted values.

    Returns
    -------
    float
    """
    if not (math.isfinite(k) and math.isfinite(b)):
        return math.inf
    e = 0.0
    if k_ref != 0:
        e = max(e, abs(k - k_ref) / abs(k_ref))
    if b_ref != 0:
        e = max(e, abs(b - b_ref) / abs(b_ref))
    return e


@dataclass(frozen=True)
class LinkAdvice:
    """Advice for one link to the port.

    Attributes
    ----------
    link : str
        Link name.
    wanted : tuple of float
        ``(k [N/m], b [N s/m])`` the link asks to be felt.
    rate_hz : float or None
        Lowest rate of :data:`RATES` that works; None when none does.
    method : str or None
        ``"naive"`` or ``"calibrated"``.
    K, B : float
        What to send at that rate [N/m], [N s/m] (nan when none).
    error : float
        Relative felt error at that rate [-].
    reason : str
        One line: why this choice.
    """

    link: str
    wanted: tuple
    rate_hz: float | None
    method: str | None
    K: float
    B: float
    error: float
    reason: str

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite floats become ``None``).

        Returns
        -------
        dict
            ``link``, ``wanted`` (``{k [N/m], b [N s/m]}``), ``rate_hz`` [Hz], ``method``,
            ``K`` [N/m], ``B`` [N s/m], ``error`` [-], ``reason``.
        """
        f = finite_or_none
        return {"link": self.link, "wanted": {"k": self.wanted[0], "b": self.wanted[1]},
                "rate_hz": self.rate_hz, "method": self.method, "K": f(self.K), "B": f(self.B),
                "error": f(self.error), "reason": self.reason}


@dataclass(frozen=True)
class Advice:
    """What a scene needs: :func:`advise_scene`'s answer.

    Attributes
    ----------
    ok : bool
        Some rate of :data:`RATES` and some method meet tolerance and margin.
    rate_hz : float or None
        Lowest such rate for the whole scene [Hz].
    integrator : str or None
        Cheapest integrator at that rate.
    links : list of LinkAdvice
        One per link touching the port.
    error : float
        Felt error of the whole scene at the advised rate/integrator [-].
    spectral_radius : float
        Closed-loop spectral radius there (with the advised values, gain 1) [-].
    reason : str
        One line for the scene.
    tolerance, margin : float
        The criteria used.
    calibrated : dict
        ``{link: (K, B)}`` :meth:`apply` writes (calibrated links at the advised rate).
    board : dict or None
        The timing of the board the scene's ``device.protocol`` names, which the advice
        took (:func:`board_timing`): ``protocol``, ``rates`` (the ladder's rates it
        holds [Hz]), ``render_latency_s`` (the middle of its render latency's bounds [s],
        added to the device's delay at each rate: the felt pair is calibrated there) and
        ``render_latency_end_s`` (the bounds' end, where the margin's stability is held
        too) and ``late_reading_periods`` (the driver's: the margin is held with that many
        periods more after the end too); None on hapsim's framed protocol.
    """

    ok: bool
    rate_hz: float | None
    integrator: str | None
    links: list = field(default_factory=list)
    error: float = math.nan
    spectral_radius: float = math.nan
    reason: str = ""
    tolerance: float = 0.01
    margin: float = 0.95
    calibrated: dict = field(default_factory=dict)
    board: dict | None = None

    def apply(self, scene):
        """The scene at the advised rate and integrator, calibrated links written in.

        Parameters
        ----------
        scene : hapsim.scene.Scene
            The scene that was advised.

        Returns
        -------
        hapsim.scene.Scene

        Raises
        ------
        UnstableConfigError
            When the advice found nothing (``ok`` False); the message is :attr:`reason`.
        """
        if not self.ok:
            raise UnstableConfigError(self.reason, spectral_radius=self.spectral_radius)
        out = dataclasses.replace(scene.with_rate(self.rate_hz), integrator=self.integrator)
        for name, (K, B) in self.calibrated.items():
            out = out.with_link(name, stiffness=K, damping=B)
        return out

    def to_dict(self) -> dict:
        """JSON-ready dict (non-finite floats become ``None``).

        Returns
        -------
        dict
            ``ok``, ``rate_hz`` [Hz], ``integrator``, ``error`` [-], ``spectral_radius``
            [-], ``reason``, ``tolerance``, ``margin``, ``links`` (list of
            :meth:`LinkAdvice.to_dict`), ``calibrated`` and ``board``.
        """
        f = finite_or_none
        return {"ok": self.ok, "rate_hz": self.rate_hz, "integrator": self.integrator,
                "error": f(self.error), "spectral_radius": f(self.spectral_radius),
                "reason": self.reason, "tolerance": self.tolerance, "margin": self.margin,
                "links": [lk.to_dict() for lk in self.links],
                "calibrated": {k: [float(v[0]), float(v[1])] for k, v in self.calibrated.items()},
                "board": self.board}


def _wanted(lk, b0: float) -> tuple[float, float]:
    if lk.target is not None:
        return float(lk.target[0]), float(lk.target[1])
    return float(lk.stiffness), float(lk.damping) + b0


def _port_links(scene):
    port = scene.port
    return [lk for lk in scene.links if port is not None and port.name in (lk.m1, lk.m2)]


def board_timing(scene, rates) -> tuple:
    """The ladder and the render latency of the board a 1-D scene's ``device.protocol``
    names: the rates of ``rates`` it holds (:meth:`hapsim.drivers.base.Driver.
    board_rates`: the Hapkit sketch's whole ticks) and the middle of its render
    latency's bounds, as ``hapsim run`` and ``check`` predict with it
    (:func:`hapsim.pipeline.render_latency.timed_prediction`).

    Parameters
    ----------
    scene : hapsim.scene.Scene
    rates : list of float
        The ladder [Hz], increasing.

    Returns
    -------
    tuple
        ``(rates, latencies, board)``: the ladder the board holds, the latencies [s]
        added to the device's delay, ``(middle, end, late)`` of the bounds (``(0, 0, 0)``
        without one, or with an ideal hold, which takes whole delays only: the felt pair
        is calibrated at the middle, the margin's stability held at both, the limit
        falling with the delay; ``late``, the driver's ``late_reading_periods``: the
        margin is held with that many periods more after the end too, as the run's
        refusal holds the loop, :func:`hapsim.pipeline.render_latency.late_reading`)
        and :attr:`Advice.board` (None on hapsim's framed protocol).
    """
    from hapsim.drivers import device_driver
    drv = device_driver(scene.device)
    if drv is None:
        return rates, (0.0, 0.0), None
    from hapsim.pipeline.render_latency import latency_middle, render_latency
    held = drv.board_rates(rates)
    lat = latency_middle(scene, drv)
    end = render_latency(drv)[1] if lat else 0.0
    late = int(getattr(drv, "late_reading_periods", 0) or 0)
    return held, (lat, end, late), {"protocol": scene.device.protocol, "rates": held,
                                    "render_latency_s": lat, "render_latency_end_s": end,
                                    "late_reading_periods": late}


def _delay(scene, rate_hz: float, latency_s: float):
    """The device's delay [periods] at ``rate_hz`` with its board's render latency
    ``latency_s`` [s] added (:func:`hapsim.analysis.prediction.timed_scene`: the same
    floats as ``run`` and ``check``)."""
    if not latency_s:
        return scene.device.delay
    from hapsim.analysis.prediction import timed_scene
    return timed_scene(scene.with_rate(rate_hz), latency_s).device.delay


def _advise_link(scene, lk, tolerance: float, margin: float, rates,
                 latency_s: tuple = (0.0, 0.0, 0)) -> LinkAdvice:
    """Lowest rate and cheapest method for one port link, taken against a ground."""
    dev = scene.device
    k, b = _wanted(lk, dev.friction)
    kinds = {m.name: m.kind for m in scene.masses}
    other = lk.m2 if kinds.get(lk.m1) == "port" else lk.m1
    against = "a ground" if kinds.get(other) == "ground" else \
        f"virtual mass {other!r} taken as immovable (stiffest case)"
    to_ground = kinds.get(other) == "ground"
    methods = ("calibrated",) if lk.target is not None else \
        (("naive", "calibrated") if to_ground else ("naive",))
    for r in rates:
        loop = LoopModel(dev.mass, dev.friction, r, _delay(scene, r, latency_s[0]), dev.hold)
        n_late = latency_s[2] if len(latency_s) > 2 else 0
        late = LoopModel(dev.mass, dev.friction, r,
                         _delay(scene, r, latency_s[1]) + n_late, dev.hold)
        for method in methods:
            if method == "naive":
                K, B = lk.stiffness, lk.damping
            else:
                if k <= 0:
                    continue
                c = calibrate(loop, k, b)
                if not c.renderable:
                    continue
                K, B = c.K, c.B
            res = render(loop, K, B)
            if not res.stable:
                continue
            err = felt_pair_error(res.k, res.b, k, b)
            if err > tolerance and to_ground:
                continue  # a link to a virtual mass is judged for accuracy with the scene
            if spectral_radius(loop, K / margin, B / margin) >= 1.0 or (
                    (latency_s[1] or n_late)
                    and spectral_radius(late, K / margin, B / margin) >= 1.0):
                continue
            why = (f"{method} at {r:g} Hz is the first rate of the ladder with felt error "
                   f"{err:.2g} <= {tolerance:g} and stable at (K, B)/{margin:g}; against {against}"
                   if to_ground else
                   f"{method} at {r:g} Hz is the first rate stable at (K, B)/{margin:g} against "
                   f"{against}; its accuracy is judged with the whole scene")
            if method == "calibrated" and lk.target is None:
                why += f"; naive (K, B) = ({lk.stiffness:g}, {lk.damping:g}) errs more there"
            return LinkAdvice(lk.name, (k, b), r, method, K, B, err, why)
    return LinkAdvice(lk.name, (k, b), None, None, math.nan, math.nan, math.inf,
                      f"no rate up to {rates[-1]:g} Hz renders (k, b) = ({k:g}, {b:g}) within "
                      f"{tolerance:g} with a {margin:g} gain margin on this device "
                      f"(m = {dev.mass:g} kg, b0 = {dev.friction:g}, d = {dev.delay}, "
                      f"{dev.hold}); lower the stiffness, add damping or reduce the delay")


def _felt(A: np.ndarray, mass: float, T: float | None):
    ev = np.linalg.eigvals(A)
    if T is None:  # continuous: map s -> z = e^{sT} with T = 1 (any) via modes of e^{s}
        s = ev
        pairs = s[s.imag > 0]
        if pairs.size == 0:
            return math.nan, math.nan
        p = pairs[np.argmax(pairs.real)]
        return mass * abs(p) ** 2, -2.0 * mass * p.real
    ev = np.where(np.abs(ev) <= 1e-12 * max(1.0, np.abs(ev).max()), 0.0, ev)
    pair = rendered_pair(modes_from_poles(ev, mass, T))
    if pair is None:
        return math.nan, math.nan
    return pair.k, pair.b


def advise_scene(scene, tolerance: float = 0.01, *, margin: float = 0.95,
                 rates=RATES) -> Advice:
    """The lowest rate and the cheapest method that make a scene good enough.

    Parameters
    ----------
    scene : hapsim.scene.Scene or hapsim.scene.SceneND
        Validated scene with a port and a device section; a 2-D or 3-D one gets the rate
        alone (:func:`_advise_space`: its felt matrices against ``(K, B + B0)``).
    tolerance : float > 0, optional
        Relative error allowed on the felt k and on the felt b (default 1 %).
    margin : float in (0, 1], optional
        Gain margin: stable with every (K, B) divided by ``margin`` (module docstring).
    rates : sequence of float, optional
        Candidate rates, increasing [Hz].

    Returns
    -------
    Advice
        ``ok`` False (with the reason) when no candidate works.

    Raises
    ------
    ConfigError
        Non-positive tolerance, margin outside (0, 1], a scene without port or device, a
        scene with an audio section (multi-rate: not modelled here).

    Notes
    -----
    The scene rate is at least the highest rate any port link needs; from there the rates
    are tried in increasing order and, at each, the integrators cheapest first: the whole
    closed loop (:func:`hapsim.bench.methods.closed_loop_matrix`, contacts engaged) must be
    stable at gain ``1/margin`` and its felt pair within ``tolerance`` of the continuous
    loop's (:func:`hapsim.bench.methods.continuous_loop_matrix`).
    """
    if not (isinstance(tolerance, (int, float)) and tolerance > 0 and math.isfinite(tolerance)):
        raise ConfigError(f"must be > 0, got {tolerance!r}", key="tolerance")
    if not (0 < margin <= 1):
        raise ConfigError(f"must be in (0, 1], got {margin!r}", key="margin")
    # its loop matrices (hapsim.bench.methods) step the network at the device period only,
    # and the rate ladder meets rates the audio rate is no multiple of
    require_port_scene(scene, "advise needs", "advise does not model a scene with an audio "
                       "section (the virtual network sub-stepped at audio.rate_hz); 'hapsim "
                       "check' predicts it at its own rate")
    rates = [float(r) for r in rates]
    if getattr(scene, "dimension", 1) > 1:
        return _advise_space(scene, tolerance, margin, rates)
    dev = scene.device
    rates, lat, board = board_timing(scene, rates)
    if not rates:
        return Advice(False, None, None, reason=f"the {dev.protocol} board holds none of "
                      f"the ladder's rates (hapsim run refuses them: its period must hold "
                      f"a command and its answer, in whole ticks of a board on its own "
                      f"tick)", tolerance=tolerance, margin=margin, board=board)
    link_adv = [_advise_link(scene, lk, tolerance, margin, rates, lat)
                for lk in _port_links(scene)]
    bad = [la for la in link_adv if la.rate_hz is None]
    if bad:
        return Advice(False, None, None, link_adv, reason=f"link {bad[0].link!r}: "
                      f"{bad[0].reason}", tolerance=tolerance, margin=margin, board=board)
    floor = max([la.rate_hz for la in link_adv], default=rates[0])
    has_mass = any(m.kind == "mass" for m in scene.masses)
    schemes = [s for s in COST_ORDER
               if not (s == "exact" and "contact" in scene.kinds)] if has_mass else ["centred"]
    # continuous reference: link values as wanted (targets as k, b - b0)
    ref_cal = {}
    for lk in scene.links:
        if lk.target is not None:
            ref_cal[lk.name] = (lk.target[0], lk.target[1] - dev.friction)
    k_ref, b_ref = _felt(continuous_loop_matrix(scene, calibrated=ref_cal), dev.mass, None)
    last = ""
    for r in [x for x in rates if x >= floor]:
        sc = scene.with_rate(r)
        late = None
        n_late = lat[2] if len(lat) > 2 else 0
        if lat[0] or n_late:
            late = dataclasses.replace(sc, device=dataclasses.replace(
                dev, delay=_delay(scene, r, lat[1]) + n_late))
            sc = dataclasses.replace(sc, device=dataclasses.replace(
                dev, delay=_delay(scene, r, lat[0])))
        loop = LoopModel(dev.mass, dev.friction, r, _delay(scene, r, lat[0]), dev.hold)
        cal = {}
        for la in link_adv:
            lk = scene.link(la.link)
            if lk.target is not None or la.method == "calibrated":
                c = calibrate(loop, *la.wanted)
                if c.renderable:
                    cal[lk.name] = (c.K, c.B)
        if any(lk.target is not None and lk.name not in cal for lk in scene.links):
            last = f"a target is not renderable at {r:g} Hz"
            continue
        for integ in schemes:
            A = closed_loop_matrix(sc, integ, calibrated=cal)
            rho, stable = spectral_radius_of(A)
            _, stable_m = spectral_radius_of(closed_loop_matrix(sc, integ, calibrated=cal,
                                                                gain=1.0 / margin))
            if late is not None and stable_m:     # the board may render that late
                _, stable_m = spectral_radius_of(closed_loop_matrix(
                    late, integ, calibrated=cal, gain=1.0 / margin))
            if not (stable and stable_m):
                last = f"{integ} at {r:g} Hz: not stable with margin (radius {rho:.6g})"
                continue
            k_f, b_f = _felt(A, dev.mass, sc.period)
            err = felt_pair_error(k_f, b_f, k_ref, b_ref)
            if err > tolerance:
                last = f"{integ} at {r:g} Hz: felt error {err:.3g} > {tolerance:g}"
                continue
            why_i = ("no virtual mass: the integrator does not matter, centred is cheapest"
                     if not has_mass else
                     f"{integ} is the cheapest integrator stable with margin and within "
                     f"tolerance at this rate")
            reason = (f"{r:g} Hz: felt (k, b) = ({k_f:.6g}, {b_f:.6g}) vs continuous "
                      f"({k_ref:.6g}, {b_ref:.6g}), error {err:.2g} <= {tolerance:g}; "
                      f"radius {rho:.9g}, stable at gain 1/{margin:g}; {why_i}"
                      + (f"; port links need >= {floor:g} Hz" if link_adv else ""))
            return Advice(True, r, integ, link_adv, err, rho, reason, tolerance, margin, cal,
                          board)
    return Advice(False, None, None, link_adv,
                  reason=f"no rate up to {rates[-1]:g} Hz and no integrator keeps the scene "
                         f"within {tolerance:g} and stable with margin {margin:g} (last: {last})",
                  tolerance=tolerance, margin=margin, board=board)


def felt_matrix_error(k, b, k_ref, b_ref) -> float:
    """:func:`felt_pair_error` of matrices: ``max(|k - k_ref| / |k_ref|, |b - b_ref| /
    |b_ref|)`` [-] in the spectral norm (a zero reference is skipped).

    Parameters
    ----------
    k, b : ndarray, shape (n, n) or None
        Felt stiffness [N/m] and damping [N s/m] matrices (None: no felt matrices -> inf).
    k_ref, b_ref : ndarray, shape (n, n)
        Wanted matrices.

    Returns
    -------
    float
    """
    if k is None or b is None or not (np.all(np.isfinite(k)) and np.all(np.isfinite(b))):
        return math.inf
    e = 0.0
    for x, ref in ((k, k_ref), (b, b_ref)):
        nr = float(np.linalg.norm(ref, 2))
        if nr > 0:
            e = max(e, float(np.linalg.norm(np.asarray(x) - ref, 2)) / nr)
    return e


def _advise_space(scene, tolerance: float, margin: float, rates) -> Advice:
    """:func:`advise_scene` of a 2-D or 3-D scene: the lowest rate whose felt matrices are
    within ``tolerance`` of what the port links ask, ``(K, B + B0)`` (the continuous-time
    loop's, no sampling, no delay: the port's links to grounds and the device's friction),
    and whose loop is stable with every ``(K, B)`` divided by ``margin`` (the MIMO state
    matrix, :func:`hapsim.analysis.ths.state_matrix`). The n-D engine has one integrator
    (centred) and no per-link calibration across axes: the advice is the rate."""
    from hapsim.analysis.scene_check import closed_loop_nd, port_link_matrices
    from hapsim.analysis.ths import MatrixLoop, render_state, state_matrix
    if scene.port is None or scene.device is None:
        raise ConfigError("the scene has no port: nothing is felt, no rate to advise "
                          "('hapsim check SCENE' gives its modes)", file=scene.path,
                          key="masses")
    dev = scene.device
    Kp, Bp, moving = port_link_matrices(scene)
    if moving:
        raise ConfigError(
            f"a port link ends on the moving mass {moving[0]!r}: the continuous-time "
            "felt matrices of a network with virtual masses are not built yet, so there "
            "is no reference to advise a rate against ('hapsim check SCENE' gives its "
            "felt matrices at its rate)", file=scene.path, key="links")
    wanted_b = Bp + dev.friction
    best, why = None, "no rate to try"
    for r in rates:
        sc = dataclasses.replace(scene, rate_hz=float(r))
        A, _ = closed_loop_nd(sc)
        res = render_state(A, dev.mass, sc.period, K=Kp, B=Bp)
        err = felt_matrix_error(res.felt_stiffness, res.felt_damping, Kp, wanted_b)
        loop = MatrixLoop(mass=dev.mass, friction=dev.friction, rate_hz=float(r),
                          delay=dev.delay)
        rho_m = float(np.max(np.abs(np.linalg.eigvals(
            state_matrix(loop, Kp / margin, Bp / margin)))))
        if err <= tolerance and rho_m < 1.0:
            best = (float(r), err, float(res.spectral_radius), rho_m)
            break
        why = (f"no rate of the ladder up to {r:g} Hz keeps the felt matrices within "
               f"{tolerance:g} of (K, B + B0) and the loop stable at (K, B)/{margin:g}: "
               f"at {r:g} Hz the error is {err:.3g} and the radius with margin "
               f"{rho_m:.9f} (the delay's lag costs damping as K T (d + 1/2): a larger "
               f"--tolerance, or less stiffness for this damping)")
    if best is None:
        return Advice(False, None, None, [], math.nan, math.nan, why, tolerance, margin)
    r, err, rho, rho_m = best
    reason = (f"{r:g} Hz is the first rate of the ladder whose felt matrices are within "
              f"{err:.2g} <= {tolerance:g} of (K, B + B0) (spectral norm) with radius "
              f"{rho:.9f}, stable at (K, B)/{margin:g} (radius {rho_m:.9f}); the 2-D/3-D "
              "engine has one integrator, centred, and no per-link calibration: the "
              "advice is the rate")
    return Advice(True, r, "centred", [], err, rho, reason, tolerance, margin)
