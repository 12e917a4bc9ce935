"""The known inputs taken out through the loop the record measured, not the predicted one.

A run's record carries inputs the host knows but the linear THS does not make: a late
tick's older force, a board's output stage (the Hapkit sketch's 256 square-root levels,
the M3's duty), a board's write holds, the host's clamp. The measurement takes each out
as the loop's response to it (:func:`hapsim.analysis.measurement.late_accounted`,
:func:`hapsim.analysis.error_response.disturbance_response`) and fits what is left. That
response is computed through a loop, and the loop at hand is the predicted one: exact for
a device that is what the scene states, but for a device that differs (a hidden friction,
more mass) the correction leaves ``(G_true - G_pred) * w`` in the record, a response at
the *predicted* poles, which pulls the fitted pair toward the prediction. Cut into
stretches (a loaded host's late writes), the record's later stretches, where that
leftover is largest beside the decayed response, weigh as much as the first: on the
Hapkit sketch with 0.3 N s/m of hidden friction and 8-15 rows cut, b was measured at
0.30-0.48 N s/m against 0.478 through the true loop, with stated half-widths of 0.004-0.03
(0.4-10 of them off), and beside a CPU-bound process one such run said "within" of a
device that differs (tests/test_loop_refit.py; the wall-clock test in
tests/test_hapkit_serial_tick.py).

The fix is a fixed point. Let ``M(p)`` be the measured pair (k, b) when the known inputs
are taken out through a loop whose felt pair is ``p`` (the device's mass and friction
chosen so: :func:`device_at_pair`, the rest of the scene kept), ``p0`` the prediction and
``M0 = M(p0)`` the first measurement. The loop the record measures is the ``p*`` with
``M(p*) = p*``. To first order ``M(p) = M0 + A (p - p0)``, with ``A = dM/dp`` taken by two
finite differences (secant slopes over the departure ``M0 - p0``), so the first step is
``p = p0 + (I - A)^-1 (M0 - p0)``, and Broyden's steps on ``F(p) = M(p) - p`` follow
while ``M(p)`` and ``p`` differ by more than :data:`SETTLED` of the stated uncertainty
(Kelley, *Iterative Methods for Linear and Nonlinear Equations*, SIAM 1995, Sec. 7.2).
The measurement at ``p*`` is the run's, and its stated half-widths carry the fixed
point's own gain: an error ``e`` of the fit at a fixed loop moves ``p*`` by
``(I - A)^-1 e``, with ``A`` taken again at ``p*``, so the half-widths are taken through
``|(I - A)^-1|`` (row sums: the worst case over their box). A record
whose measurement follows the loop it is corrected with as fast as the loop itself
(``|det(I - A)|`` below :data:`SINGULAR`) cannot tell the two apart and is not measurable.
"""

from __future__ import annotations

import cmath
import dataclasses
import math

import numpy as np

__all__ = ["SETTLED", "SINGULAR", "MAX_PASSES", "RESTARTS", "pair_of", "device_at_pair",
           "frictionless_near_pair", "through_measured_loop"]

#: A fixed point is reached when the loop's pair and the pair measured through it differ
#: by less than this fraction of the stated half-widths.
SETTLED = 0.1
#: ``|det(I - A)|`` below which the record cannot tell the loop from its correction.
SINGULAR = 0.05
#: Broyden steps after the first two.
MAX_PASSES = 3
#: Restarts of the Broyden steps, each from the point made nearest a fixed point with
#: slopes made again there: from a first measurement far from the loop the record
#: measures, the first round's updates had not converged in 2 of 6 wall-clock runs of a
#: hidden friction of 0.3 N s/m beside two CPU-bound processes (stop 56).
RESTARTS = 2


def pair_of(scene, mass: float):
    """The felt pair (k [N/m], b [N s/m]) of a scene's loop, expressed with ``mass``.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A calibrated scene with a port and a device.
    mass : float
        The mass [kg] the pair is expressed with (``k = m |s|^2``, ``b = -2 m Re s``;
        docs/design.md, 'The inverse map').

    Returns
    -------
    ndarray, shape (2,), or None
        None when the loop renders no felt pair.
    """
    from hapsim.analysis.prediction import predicted_poles
    try:
        _, felt = predicted_poles(scene)
    except Exception:                       # a loop the analysis cannot build
        return None
    if felt is None or felt == 0:             # (z = 0: a delay line's pole, no pair)
        return None
    from hapsim.analysis.ths import continuous_poles
    s = complex(continuous_poles(complex(felt), scene.period))
    return np.array([mass * abs(s) ** 2, -2.0 * mass * s.real])


def device_at_pair(scene, pair, mass: float, start=None):
    """The scene's device with the mass and friction whose loop renders ``pair``.

    Newton's method on the felt pole (two real equations, the device's mass and friction
    the unknowns; finite-difference Jacobian), from ``start`` (default the scene's device).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's model (its links, rate, delay and hold kept).
    pair : array_like, shape (2,)
        The wanted felt (k [N/m], b [N s/m]), expressed with ``mass``.
    mass : float
        The mass [kg] the pair is expressed with.
    start : hapsim.scene.Device, optional
        Where the search starts.

    Returns
    -------
    hapsim.scene.Device or None
        None when no device with a positive mass and a friction >= 0 renders the pair
        (an overdamped pair, a pair only a negative friction renders, or Newton's method
        not converging in 40 steps).
    """
    target = _target_pole(scene, pair, mass)
    if target is None:
        return None
    dev = start if start is not None else scene.device
    x = np.array([float(dev.mass), float(dev.friction)])

    def felt(v):
        return _felt_pole(scene, dev, v[0], v[1]) if v[0] > 0 else None

    for _ in range(40):
        z = felt(x)
        if z is None:
            return None
        r = np.array([(z - target).real, (z - target).imag])
        if np.max(np.abs(r)) <= 1e-13:
            break
        J = np.empty((2, 2))
        for i in range(2):
            h = 1e-7 * max(abs(x[i]), float(dev.mass) if i == 0 else 1e-3 * float(dev.mass)
                           / scene.period)
            xi = x.copy()
            xi[i] += h
            zi = felt(xi)
            if zi is None:
                return None
            J[:, i] = [(zi - z).real / h, (zi - z).imag / h]
        try:
            step = np.linalg.solve(J, r)
        except np.linalg.LinAlgError:
            return None
        # never through a zero mass or a negative friction (no such device: the scene
        # refuses it, and an iterate there ended the search): halve the step, and give
        # up where it has no length left (a pair only a negative friction renders)
        for _ in range(60):
            if x[0] - step[0] > 0 and x[1] - step[1] >= 0:
                break
            step = step / 2.0
        else:
            return None
        x = x - step
    else:
        return None
    return dataclasses.replace(dev, mass=float(x[0]), friction=float(x[1]))


def frictionless_near_pair(scene, pair, mass: float, start=None):
    """The scene's device without friction whose loop renders the felt pole nearest
    ``pair``'s: where :func:`device_at_pair` finds no device because the pair needs a
    negative friction (a loop the record measures at or near ``b0 = 0``).

    The mass minimises ``|z(m) - z*|``, ``z*`` the pair's sampled pole (Brent's bounded
    search, ``scipy.optimize.minimize_scalar``, over a quarter to four times the start's
    mass): the pole's distance, not the pair's, so that k and b weigh as the loop does.

    Parameters
    ----------
    scene, pair, mass
        As :func:`device_at_pair` (the model, the wanted felt (k [N/m], b [N s/m]) and
        the mass [kg] it is expressed with).
    start : hapsim.scene.Device, optional
        Its mass bounds the search (default the scene's device).

    Returns
    -------
    hapsim.scene.Device or None
        The device (friction 0), or None when the pair is no underdamped pole or no mass
        in the bounds gives the loop a felt pair.
    """
    from scipy.optimize import minimize_scalar
    target = _target_pole(scene, pair, mass)
    if target is None:
        return None
    dev = start if start is not None else scene.device

    def dist(v):
        z = _felt_pole(scene, dev, v, 0.0)
        return math.inf if z is None else abs(z - target)

    m0 = float(dev.mass)
    got = minimize_scalar(dist, bounds=(0.25 * m0, 4.0 * m0), method="bounded",
                          options={"xatol": 1e-12 * m0})
    return (dataclasses.replace(dev, mass=float(got.x), friction=0.0)
            if math.isfinite(float(got.fun)) else None)


def _felt_pole(scene, dev, mass, friction):
    """The felt pole of ``scene``'s loop with ``dev`` at ``mass`` [kg] and ``friction``
    [N s/m], complex, or None (no felt pair, or a device the scene refuses: a negative
    friction is no such device)."""
    from hapsim.analysis.prediction import predicted_poles
    try:
        z = predicted_poles(dataclasses.replace(scene, device=dataclasses.replace(
            dev, mass=float(mass), friction=float(friction))))[1]
    except Exception:
        return None
    return None if z is None else complex(z)


def _target_pole(scene, pair, mass: float):
    """The sampled felt pole of ``pair`` (k, b) expressed with ``mass``, or None for an
    overdamped pair."""
    k, b = float(pair[0]), float(pair[1])
    re = -b / (2.0 * mass)
    im2 = k / mass - re * re
    if not (math.isfinite(im2) and im2 > 0):
        return None
    return cmath.exp(complex(re, math.sqrt(im2)) * scene.period)


def _pair(m: dict):
    return np.array([float(m["k"]), float(m["b"])])


def through_measured_loop(scene, measured: dict, fit_at, start=None) -> dict:
    """The measurement with its known inputs taken out through the loop it measures
    (module notes).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's model (the predicted loop).
    measured : dict
        The measurement with the known inputs taken out through ``scene``'s loop
        (``k``, ``b``, ``k_unc``, ``b_unc``).
    fit_at : callable
        ``fit_at(device) -> dict``: the same measurement with the known inputs taken out
        through the loop of ``device`` (the scene's other parts kept).
    start : hapsim.scene.Device, optional
        The device whose loop ``measured`` took the known inputs through (default the
        scene's).

    Returns
    -------
    dict
        The measurement at the fixed point, its ``k_unc``, ``b_unc`` through the fixed
        point's gain, with ``loop_refit``: ``passes`` (fits made), ``gain`` (the 2x2
        ``(I - A)^-1``), ``device`` (the mass [kg] and friction [N s/m] of the loop the
        known inputs were taken through), ``moved`` (k, b: how far the fixed point is
        from the first measurement) and ``first_unc`` (the first measurement's
        half-widths, which the fixed point settles to :data:`SETTLED` of); or, when the record cannot tell the loop from its
        correction, when no device renders the pairs the search needs or no fixed point
        is found, no pair and ``error`` (never the first measurement, which the predicted
        loop pulled toward the prediction).
    """
    from hapsim.analysis.network import device_body
    mass = device_body(scene.device)[0]
    dev = scene.device if start is None else start
    if measured.get("method") == "pencil":
        # an exact record: the modes reproduce it to round-off, which a correction through
        # another loop than the device's would not let them (its leftover is no free
        # response of the loop)
        return dict(measured, loop_refit={"passes": 0, "exact": True})
    p0 = pair_of(dataclasses.replace(scene, device=dev), mass)
    if p0 is None:
        return measured
    m0 = _pair(measured)
    u0 = np.array([float(measured.get("k_unc", 0.0)), float(measured.get("b_unc", 0.0))])
    scale = np.array([abs(p0[0]), max(abs(p0[1]), 1e-3 * math.sqrt(abs(p0[0]) * mass))])
    u = np.maximum(u0, 1e-6 * scale)
    F0 = m0 - p0
    passes = 0

    def failed(why, **info):
        # the first measurement took the known inputs through the predicted loop, which
        # pulls it toward the prediction: without the loop it measures, no pair is stated
        out = {q: v for q, v in measured.items()
               if q not in ("k", "b", "f0_hz", "damping_ratio")}
        out["error"] = (f"the known inputs (late ticks, the board's output stage or write "
                        f"holds) could not be taken out through the loop the record "
                        f"measures: {why}")
        out["loop_refit"] = {"passes": passes, **info}
        return out

    why = ""                        # the last fit through a loop that measured nothing

    def at(p, find=device_at_pair):
        """The measurement through the loop of pair ``p``, its device found by ``find``
        (:func:`device_at_pair`, or :func:`frictionless_near_pair`: the nearest), or None
        (no such device, or no measurement through its loop: its reason kept for the
        error)."""
        nonlocal passes, why
        d = find(scene, p, mass, dev)
        if d is None:
            return None
        got = fit_at(d)
        passes += 1
        if "k" not in got:
            why = str(got.get("error") or got.get("verdict") or "")
            return None
        return d, got

    def near(what):
        # the measurement's own reason at the last loop tried, when it gave one
        return what + (f" (there: {why})" if why else "")

    def settled(F, m):
        um = np.array([float(m.get("k_unc", 0.0)), float(m.get("b_unc", 0.0))])
        # (against the first measurement's half-widths too: near the loop the record
        # measures, a record with no sensor error passes for an exact one, whose
        # half-widths are its round-off; the loop's own search is good to 1e-6 of the pair)
        return bool(np.all(np.abs(F) <= np.maximum(SETTLED * np.maximum(um, u),
                                                  1e-6 * scale)))

    def slopes(p, m, h):
        """dM/dp at ``p`` by finite differences of steps ``h``, and the points made."""
        A, pts = np.empty((2, 2)), []
        for i in range(2):
            for step in (h[i], -h[i]):
                q = p.copy()
                q[i] += step
                got = at(q)
                if got is not None:
                    break
            else:
                return None, pts
            pts.append((q, got[0], got[1]))
            A[:, i] = (_pair(got[1]) - _pair(m)) / step
        return A, pts

    # the secant slopes, steps of the departure's size (at least 3 half-widths), then
    # Broyden's method on F(p) = M(p) - p (Kelley 1995, Sec. 7.2), a step halved where no
    # device renders its pair or no measurement is made through its loop; any point made
    # that is a fixed point ends the search (a secant over a departure the correction
    # pulled almost whole toward the prediction is nearly singular, and its far end is
    # the fixed point itself)
    A, pts = slopes(p0, measured, np.maximum(np.maximum(np.abs(F0), 3.0 * u), 1e-4 * scale))
    if A is None:
        return failed(near(f"no device near the pair {p0.tolist()} gives a measurement"))
    best = None
    for q, d, mq in pts:
        if settled(_pair(mq) - q, mq):
            best = (q, d, mq)
    p, F, m, d = p0, F0, measured, dev
    J = A - np.eye(2)
    # every point made, for a restart: its departure in the first half-widths
    seen = [(float(np.max(np.abs(F0) / u)), p0, F0, measured, dev)]
    seen += [(float(np.max(np.abs(_pair(mq) - q) / u)), q, _pair(mq) - q, mq, dq)
             for q, dq, mq in pts]
    for rnd in range(RESTARTS + 1):
        if rnd and best is None:
            # Broyden's updates converge near the root only (Kelley 1995, Sec. 7.2): from
            # the point nearest a fixed point so far, slopes made again there
            _, p, F, m, d = min(seen, key=lambda s: s[0])
            A, pts2 = slopes(p, m, np.maximum(np.maximum(np.abs(F), 3.0 * u),
                                              1e-4 * scale))
            if A is None:
                break
            for q, dq, mq in pts2:
                if settled(_pair(mq) - q, mq):
                    best = (q, dq, mq)
            J = A - np.eye(2)
        for _ in range(2 + MAX_PASSES):
            if best is not None:
                break
            try:
                step = -np.linalg.solve(J, F)
            except np.linalg.LinAlgError:
                step = _pair(pts[-1][2]) - p if pts else F      # (the plain iteration's)
            for lam in (1.0, 0.5, 0.25, 0.125):
                got = at(p + lam * step)
                if got is not None:
                    pn = p + lam * step
                    break
            else:
                # every fraction of the step needs a negative friction (the loop the
                # record measures at or near b0 = 0: its fixed point on that edge, which
                # Broyden's steps overshoot): the frictionless loop nearest the step's
                # pair, taken at its own pair
                got = at(p + step, frictionless_near_pair)
                pn = None if got is None else pair_of(
                    dataclasses.replace(scene, device=got[0]), mass)
                if pn is None:
                    return failed(near(f"no device near the pair {(p + step).tolist()} "
                                       f"gives a measurement"))
                if not np.any(pn != p):
                    return failed(f"no fixed point in {passes} fits (the pair measured "
                                  f"is {F.tolist()} from the loop's last, at b0 = 0)")
            Fn = _pair(got[1]) - pn
            if np.any(pn != p):         # (a step of no length: no secant to update by)
                J = J + np.outer((Fn - F) - J @ (pn - p), pn - p) / float((pn - p) @ (pn - p))
            p, F, d, m = pn, Fn, got[0], got[1]
            seen.append((float(np.max(np.abs(F) / u)), p, F, m, d))
            if settled(F, m):
                best = (p, d, m)
        if best is not None:
            p, d, m = best
            break
    if best is None:
        return failed(f"no fixed point in {passes} fits (the pair measured is "
                      f"{F.tolist()} from the loop's last)")
    # the fixed point's gain, from slopes at it (3 of its half-widths)
    um = np.array([float(m.get("k_unc", 0.0)), float(m.get("b_unc", 0.0))])
    A, _ = slopes(p, m, np.maximum(3.0 * np.maximum(um, u), 1e-4 * scale))
    if A is None:
        return failed(near(f"no device near the fixed point {p.tolist()} gives a "
                           f"measurement"))
    IA = np.eye(2) - A
    det = float(np.linalg.det(IA))
    if not (math.isfinite(det) and abs(det) >= SINGULAR):
        return failed(f"the correction moves the measurement as much as the loop it is "
                      f"taken through (|det(I - A)| = {abs(det):.2g} < {SINGULAR}): the "
                      f"record cannot tell the device from its correction", A=A.tolist())
    G = np.linalg.inv(IA)
    F = _pair(m) - p
    out = dict(m)
    # the fit's errors through the fixed point's gain, and what is left of its distance
    # from the fixed point
    gu = np.abs(G) @ (um + np.abs(F))
    out["k_unc"], out["b_unc"] = float(gu[0]), float(gu[1])
    out["loop_refit"] = {"passes": passes, "gain": G.tolist(),
                         "device": [float(d.mass), float(d.friction)],
                         "moved": (_pair(m) - m0).tolist(), "first_unc": u0.tolist()}
    return out
