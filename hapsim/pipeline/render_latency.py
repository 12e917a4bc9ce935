"""A driver's board that renders a command some time after it read the handle: the loop's
delay is the scene's and that latency, known only within bounds.

The Hapkit WHC2017 sketch reads its sensor and computes and writes the motor's duty in the
same branch of its loop (``Hapkit_arduino.ino:111-122``): the force computed from one
reading takes effect a period and the render's latency after it
(:data:`hapsim.drivers.hapkit_serial.RENDER_LATENCY_S`, 0.15-0.55 ms: its binary32
arithmetic's cycles, which the firmware's text does not fix). At 250 Hz that moves the
felt damping by up to 5 %: the scene's whole delay alone predicted ~5 % too much
(docs/testing.md, "The Hapkit sketch's output and timing"). hapsim models a real-valued
delay exactly (modified z-transform, :mod:`hapsim.analysis.subsample`).

The latency is a nuisance parameter of the verdict, and the measurement depends on it as
well as the prediction: the fit takes the loop's other poles from the model
(:func:`hapsim.pipeline.measure.identify_run`), so a board at 0.45 ms measured with the
model at 0.35 ms gives a felt k 0.04 % below what the board's own loop has (offline,
deterministic: ``hapkit_serial_offline_loop``), more than the prediction moves over the
whole range. Adding the prediction's spread over the range to the stated uncertainty (the
first design) left a matching board "differs". So the run states the prediction at the
range's middle before it runs (:func:`timed_prediction`: the stability check, the
report), and the measurement searches the latency within the bounds
(:func:`latency_search`): the one at which measurement and prediction agree best (the
larger of the k and b departures, each in its stated uncertainty), and the verdict is the
ordinary one of both k and b there: "within" where the device is as the scene states with
some latency within the bounds. The latency moves the felt damping most (5 % over the
range, k 0.05 %), so a device that differs in friction within what the range can mimic is
told by its k (the latency that would explain its b moves the predicted k too); a device
outside the range's reach differs at the nearest end. An unseen hold near the latency's
damping (tests/test_unseen_verdict.py, seed 22) moved the damping's own root 10 us off
and k outside its interval there; the least of the joint score is within.
The emulated board renders with its own latency
(:data:`hapsim.drivers.hapkit_serial.RENDER_S`), as the device does, whatever the scene
says.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from hapsim.analysis.prediction import timed_scene

__all__ = ["render_latency", "latency_middle", "timed_scene", "timed_prediction",
           "latency_refusal", "late_reading", "late_reading_s", "late_reading_refusal",
           "late_force", "missing_reply_warning",
           "latency_search",
           "SPREAD_POINTS", "REFINE_STEPS", "GOLDEN_STEPS", "REVIEW_LATENCIES"]

#: Latencies tried over a driver's range (ends included): for the prediction's spread
#: (the felt (k, b) move smoothly with the delay over a fraction of a period: on
#: configs/hapkit_serial.yaml 9 points and 65 give the same spread to 1e-4 of it) and
#: the measurement's first bracket of the latency (:func:`latency_search`).
SPREAD_POINTS = 9
#: Secant steps of :func:`latency_search` within its bracket, at most: the difference of
#: the measured and predicted felt damping is close to linear in the latency (offline on
#: configs/hapkit_serial.yaml, a board at 0.45 ms: 0.0024 N s/m per 0.05 ms either side),
#: so a few steps take it far inside the stated uncertainty.
REFINE_STEPS = 4
#: Latencies the review of a "differs" tries besides the one picked, the nearest to the
#: record first (:func:`_explained_elsewhere`).
REVIEW_LATENCIES = 3
#: Golden-section steps of :func:`latency_search` on its score about the best latency:
#: each narrows the interval to 0.618 of itself, 8 to 0.021 of two grid steps
#: (2 us on the Hapkit's 0.4 ms range).
GOLDEN_STEPS = 8


def render_latency(driver) -> tuple | None:
    """A driver's render latency bounds ``(lo, hi)`` [s], or None.

    Parameters
    ----------
    driver : type or hapsim.drivers.base.Driver or None
        A driver's class or instance (as configured: its ``render_latency_s``).

    Returns
    -------
    tuple of float or None
        Its ``render_latency_s`` (None: the board applies a command's force as it reads
        the handle, or there is no driver).
    """
    if driver is None:
        return None
    got = getattr(driver, "render_latency_s", None)
    if got is None:
        return None
    lo, hi = float(got[0]), float(got[1])
    return (lo, hi) if 0.0 <= lo <= hi else None


def latency_middle(scene, driver) -> float:
    """The render latency [s] a run states its prediction at: the middle of the driver's
    bounds (:func:`render_latency`), 0 where the loop takes none (no driver, bounds of 0,
    no device, or a hold other than ``zoh``, which takes whole delays only).

    Parameters
    ----------
    scene : hapsim.scene.Scene
    driver : type or hapsim.drivers.base.Driver or None

    Returns
    -------
    float
        >= 0 [s].
    """
    rng = render_latency(driver)
    if rng is None or rng[1] == 0.0 or scene.device is None or scene.device.hold != "zoh":
        return 0.0
    return 0.5 * (rng[0] + rng[1])


def timed_prediction(scene, driver) -> tuple:
    """The prediction of a run whose driver's board renders after its read: the scene
    timed at the middle of the driver's latency range, and how far the felt pair moves over
    the range.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene.
    driver : type or hapsim.drivers.base.Driver or None
        The run's driver (:func:`render_latency`).

    Returns
    -------
    tuple
        ``(model_scene, pred)``: the scene the loop is modelled with (``scene`` itself when
        the driver has no latency, or bounds of 0, or the hold is not ``zoh``) and
        :func:`hapsim.analysis.prediction.predict` of it; with a latency, ``pred`` also
        has ``render_latency_s`` (the bounds [s]), ``delay_modelled`` [periods],
        ``k_spread`` and ``b_spread`` (the largest departure of the felt k [N/m] and b
        [N s/m] over the range from the middle's, over :data:`SPREAD_POINTS` latencies:
        how much the latency can move the prediction, for the report; the verdict
        searches the latency instead, :func:`latency_search`; none where the loop at the
        middle is unstable: it has no felt pair, and the run refuses it); and, where the
        loop is stable at the middle but not at some latency of the range (the board may
        render that late: the run refuses it, ``check`` says unstable),
        ``unstable_latency_s`` (the latency of the largest spectral radius [s]) and
        ``unstable_spectral_radius``. The range is taken at :data:`SPREAD_POINTS`
        latencies, its ends included (a longer delay takes stability away: the end is
        where it goes first). With or without a latency, where the driver's board may
        have its reading taken late (``late_reading_periods``) and that makes the loop
        unstable, ``late_reading_unstable`` (:func:`late_reading`: the run refuses it,
        ``check`` says unstable).

    Raises
    ------
    ConfigError
        The scene cannot be analysed (no port or device).
    """
    from hapsim.analysis.prediction import predict
    mid = latency_middle(scene, driver)
    if not mid:
        pred = predict(scene)
        late_reading(scene, driver, pred, 0.0)
        return scene, pred
    lo, hi = render_latency(driver)
    model = timed_scene(scene, mid)
    pred = predict(model)
    ks, bs, unstable = [], [], []
    # an unstable loop (refused, or run with allow_unstable) has no felt pair to spread
    for r in np.linspace(lo, hi, SPREAD_POINTS) if pred.get("stable") is not False else ():
        p = predict(timed_scene(scene, float(r)), limit=False)   # (the pair, stability)
        if p.get("stable") is False:
            unstable.append((float(p["spectral_radius"]), float(r)))
        if p.get("k") is None or pred.get("k") is None:
            continue
        ks.append(abs(p["k"] - pred["k"]))
        bs.append(abs(p["b"] - pred["b"]))
    pred["render_latency_s"] = [lo, hi]
    pred["delay_modelled"] = float(model.device.delay)
    if unstable:
        # stable at the middle, not over the whole range: the board may run this loop
        pred["unstable_latency_s"] = max(unstable)[1]
        pred["unstable_spectral_radius"] = max(unstable)[0]
    if ks:
        pred["k_spread"] = float(max(ks))
        pred["b_spread"] = float(max(bs))
    late_reading(scene, driver, pred, hi)
    return model, pred


def late_reading(scene, driver, pred: dict, latest_s: float) -> None:
    """Whether the loop holds a reading taken late by the host: the scene with its
    board's latest render (``latest_s``) and the driver's ``late_reading_periods`` more
    periods in its delay (:attr:`hapsim.drivers.base.Driver.late_reading_periods`).

    A board whose reply can come near the host's next deadline (the Hapkit sketch's,
    up to 4.27 ms into a 4.96 ms period) has it taken a period late by a host that wakes
    a little late, and the loop steps with a reading a period old until the echo pairs it
    (:mod:`hapsim.drivers.late_replies`); a run of such readings is the loop with a
    delay a period longer, and a loop stable at its own delay but not at that one can run
    the device away (a 50 N/m spring at 5 ticks, stable up to 1.52 periods, ran the
    paddle to its 0.2 m envelope beside the suite's load). The delay is a real number
    of periods, modelled exactly (modified z-transform: Jury, *Theory and Application of
    the z-Transform Method*, 1964; :mod:`hapsim.analysis.subsample`).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene (its own delay).
    driver : type or hapsim.drivers.base.Driver or None
        The run's driver; nothing is checked without ``late_reading_periods`` > 0.
    pred : dict
        The prediction of the loop at the board's timing (:func:`timed_prediction`);
        nothing is checked where it is unstable already (at the latency's middle or at
        some latency of the range). Where the late reading makes the loop unstable, set
        ``pred["late_reading_unstable"]``: ``periods`` (the driver's), ``delay`` (the
        delay the loop was found unstable at [periods]) and ``spectral_radius`` there.
    latest_s : float
        The board's latest render after its read [s] (its bounds' end; 0 without).
    """
    n, extra_s = late_reading_s(scene, driver, latest_s)
    if (n <= 0 or scene.device is None or pred.get("stable") is False
            or pred.get("unstable_latency_s") is not None):
        return
    found = _unstable_later(scene, extra_s)
    if found is not None:
        pred["late_reading_unstable"] = {"periods": n, **found}


def late_reading_s(scene, driver, latest_s: float) -> tuple:
    """How late a board's reading may be taken: ``(periods, seconds)``, the driver's
    ``late_reading_periods`` (0 without a driver) and the time they and the board's
    latest render ``latest_s`` [s] add to the scene's delay (:func:`late_reading`).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The scene (its period).
    driver : type or hapsim.drivers.base.Driver or None
    latest_s : float
        The board's latest render after its read [s].

    Returns
    -------
    tuple
        ``(int, float)``.
    """
    n = int(getattr(driver, "late_reading_periods", 0) or 0) if driver is not None else 0
    return n, float(latest_s) + n * scene.period


def _unstable_later(scene, extra_s: float) -> dict | None:
    """``{"delay", "spectral_radius"}`` of the loop with ``extra_s`` [s] more in its
    delay (:func:`timed_scene`) where it is unstable there; None where it is stable."""
    from hapsim.analysis.prediction import predict
    at = timed_scene(scene, extra_s)
    p = predict(at, limit=False)
    if p.get("stable") is not False:
        return None
    return {"delay": float(at.device.delay), "spectral_radius": float(p["spectral_radius"])}


def late_force(scene, pred: dict, latest_s: float = 0.0) -> str | None:
    """Whether the loop holds a FORCE that comes a period late: a real-time run's warning.

    A device holds the last force it got (the framed mock, the boards' firmware), so a
    FORCE a host sends a period late (a loaded machine falling behind) makes the loop's
    delay a period longer for that stretch. A loop stable at its own delay but not at
    that one (``configs/wall.yaml``: K_max 1313 N/m at d = 1, 785 at d = 2, its wall
    1000 N/m) grows on a host that falls behind, to the force limit or the envelope's
    safety stop. The run goes on (on an unloaded host it holds), and says so. A board
    whose reading is itself taken late (``late_reading_periods``) is held to that
    instead, and refused (:func:`late_reading`). The delay is a real number of periods,
    modelled exactly (modified z-transform: Jury, 1964; :mod:`hapsim.analysis.subsample`).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene (its own delay).
    pred : dict
        The run's prediction (:func:`timed_prediction`). Nothing is said where it is
        unstable already, or a late reading makes it so; where a FORCE a period late
        does, ``pred["late_force_unstable"]``: ``delay`` [periods] and
        ``spectral_radius`` there.
    latest_s : float
        The board's latest render after its read [s] (its bounds' end; 0 without).

    Returns
    -------
    str or None
        The warning (None where the loop holds it).
    """
    if (scene.device is None or pred.get("stable") is False
            or pred.get("unstable_latency_s") is not None
            or pred.get("late_reading_unstable") is not None):
        return None
    found = _unstable_later(scene, float(latest_s) + scene.period)
    if found is None:
        return None
    pred["late_force_unstable"] = found
    return (f"the loop is stable at its own delay but not with a FORCE a period late "
            f"(d = {found['delay']:.4g}: spectral radius {found['spectral_radius']:.6g}): "
            f"a host that falls a period behind, on a loaded machine, grows it, and the "
            f"run then stops on its lateness guard (`hapsim stability --scene "
            f"{scene.path}`: the stiffness limits)")


def missing_reply_warning(scene, driver, pred: dict) -> str | None:
    """Whether the loop holds replies that go missing now and then: a real-time run's
    warning for a request-reply driver (:attr:`hapsim.drivers.base.Driver.request_reply`).

    Where a reply is overdue the host steps the engine with an estimated position, at most
    two ticks in a row, then skips ticks until a record comes (:mod:`hapsim.host.
    host_clock`). The loop is then a switched system, which can grow where every reading
    on time holds: on configs/haply.yaml's joint at 0.9 of ``check``'s damping limit, two
    missing replies in eight grow it 6 % a tick; such patterns hold that loop only to 71 %
    of the limit (docs/drivers.md, "Missing replies and the loop's stability"). The
    patterns tried: :func:`hapsim.analysis.missing_replies.patterns` (up to 8 ticks, at
    most 2 missing in a row and a quarter of the ticks); the growth a lower bound of the
    joint spectral radius (Jungers 2009). The run goes on (a link that answers in time
    holds it), and says so. Analysed for a scene of spring-dampers from the port to ground
    with a zero-order hold (the model's form; its delay a real number of periods, as the
    board runs it); others: None.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene at the board's timing (:func:`timed_prediction`'s
        model: its delay with the board's render latency).
    driver : type or hapsim.drivers.base.Driver or None
        The run's driver (None, lockstep or no request-reply: nothing checked).
    pred : dict
        The run's prediction; nothing is said where it is unstable already or refused.
        Where a pattern grows the loop, ``pred["missing_reply_unstable"]``:
        ``growth_per_tick`` and ``pattern`` (``F`` a reply, ``E`` an estimated tick,
        ``S`` a skipped one).

    Returns
    -------
    str or None
        The warning (None where every pattern holds the loop, or it is not analysed).
    """
    from hapsim.analysis.missing_replies import wall_loop, worst_pattern
    if (driver is None or not getattr(driver, "request_reply", False)
            or pred.get("stable") is False
            or pred.get("unstable_latency_s") is not None
            or pred.get("late_reading_unstable") is not None):
        return None
    loop = wall_loop(scene)
    if loop is None:
        return None
    g, pat = worst_pattern(*loop)
    # (a spectral radius of the products is rounded to ~1e-13: a margin of 1e-9 keeps a
    # loop at 1 to its rounding from being called growing)
    if not g > 1.0 + 1e-9:
        return None
    pred["missing_reply_unstable"] = {"growth_per_tick": g, "pattern": pat}
    return (f"the loop is stable with every reply on time but grows when the board's "
            f"replies go missing now and then (the pattern {pat}, repeated: F a reply, E a "
            f"tick stepped with the host's estimate, S a skipped tick; {g - 1:.2%} a "
            f"tick): a link that delays replies can run it to its safety stop "
            f"(`python tools/estimate_patterns.py {scene.path}` charts the damping that "
            f"holds it)")


def late_reading_refusal(scene, pred: dict):
    """The error refusing a loop that a reading taken late makes unstable
    (:func:`late_reading`, ``pred["late_reading_unstable"]``):
    :func:`hapsim.analysis.prediction.refusal` of the loop at that delay, its cause and
    the stiffness that would hold it first.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene (its own delay).
    pred : dict
        :func:`timed_prediction`'s, with ``late_reading_unstable``.

    Returns
    -------
    hapsim.errors.UnstableConfigError
    """
    from hapsim.analysis.prediction import predict, refusal
    from hapsim.errors import UnstableConfigError
    lr = pred["late_reading_unstable"]
    at = dataclasses.replace(scene, device=dataclasses.replace(scene.device,
                                                               delay=lr["delay"]))
    err = refusal(at, predict(at))
    n = lr["periods"]
    return UnstableConfigError(
        f"the board's reply can be taken {n} period{'s' if n != 1 else ''} late by a host "
        f"that wakes a little late (its driver's late_reading_periods), and the loop is "
        f"stable at the scene's delay but not at {lr['delay']:.4g} periods: {err}",
        spectral_radius=err.spectral_radius, stiffness_limit=err.stiffness_limit)


def latency_refusal(scene, pred: dict):
    """The error refusing a loop stable at the middle of its board's render latency but
    not at the latency :func:`timed_prediction` found unstable (``pred``'s
    ``unstable_latency_s``): :func:`hapsim.analysis.prediction.refusal` of the loop there,
    its cause first.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        The run's calibrated scene (its own delay).
    pred : dict
        :func:`timed_prediction`'s, with ``unstable_latency_s`` and ``render_latency_s``.

    Returns
    -------
    hapsim.errors.UnstableConfigError
    """
    from hapsim.analysis.prediction import predict, refusal
    from hapsim.errors import UnstableConfigError
    r = float(pred["unstable_latency_s"])
    lo, hi = pred["render_latency_s"]
    at = timed_scene(scene, r)
    err = refusal(at, predict(at))
    return UnstableConfigError(
        f"the board renders {lo * 1e3:g}-{hi * 1e3:g} ms after its read (its driver's "
        f"bounds), and the loop is stable at the middle but not at {r * 1e3:.3g} ms: "
        f"{err}", spectral_radius=err.spectral_radius, stiffness_limit=err.stiffness_limit)


def latency_search(prep, measure_at) -> dict:
    """The run's measurement with the board's render latency searched within its bounds
    (module notes): the latency at which measurement and prediction agree best, and the
    ordinary verdict of both k and b there.

    The score of a latency ``r`` is ``max(|k_m - k_p| / k_unc, |b_m - b_p| / b_unc)``, the
    measured pair and its stated uncertainty with the model's delay the scene's and
    ``r``, the prediction at ``r``: at most 1 where the verdict there is "within", so the
    device is as stated, with some latency within the bounds, where the least score is.
    It is evaluated at :data:`SPREAD_POINTS` latencies over the bounds; the bracket where
    ``b_m - b_p`` changes sign (the damping, which the latency moves most) is narrowed by
    the secant rule (:data:`REFINE_STEPS` at most), and the score's least is then sought
    by golden section over the grid step either side of the best latency so far
    (:data:`GOLDEN_STEPS`). The search's measurements leave out the review of a "differs"
    on a board's unseen holds (a test that may turn the verdict: made at each latency
    tried, it would have as many chances to explain a device that differs away; beside
    a load, a paddle with 0.3 N s/m of hidden friction said "within" so); the run's
    measurement is made again, whole, at the least score's latency and returned as it is
    (its verdict, intervals and notes those of the loop modelled there). Where its review
    lets a "differs" stand with the predicted loop unexplained, the records the search
    measured are tested too (:func:`_explained_elsewhere`): where the predicted loop at
    another latency explains the record with its breaks, the measurement is made again
    there, and taken if its own review lets no "differs" stand
    (``render_latency_review`` says so).

    Parameters
    ----------
    prep : hapsim.pipeline.run_types.PreparedRun
        The prepared run; ``prep.pred`` has ``render_latency_s`` (the bounds [s]).
        ``prep.pred`` is updated in place with the prediction at the latency found (the
        report's ``predicted``), ``render_latency_found_s`` [s] beside the bounds.
    measure_at : callable
        ``measure_at(prep_r, final) -> dict``: the measurement of the run modelled as
        ``prep_r`` (``prep`` with ``model_scene`` and ``pred`` at a latency); ``final``
        False while searching (the measurement's tests of the record that may turn a
        verdict, made once only: :func:`hapsim.pipeline.measure.identify_run`), True once
        at the latency found, ``"spread"`` at a bound after a "differs" (the loop the
        record measures found, the verdict's review left out: :func:`_latency_spread`).

    Returns
    -------
    dict
        The measurement at the latency found, with ``render_latency_s`` (that latency
        [s]), ``render_latency_bounds_s``, ``render_latency_tried`` (the measurements
        made, the last whole) and ``render_latency_note``.
    """
    import dataclasses
    import math

    from hapsim.analysis.prediction import predict
    lo, hi = (float(v) for v in prep.pred["render_latency_s"])
    cache: dict = {}

    def at(r: float):
        r = float(min(max(r, lo), hi))
        if r not in cache:
            model = timed_scene(prep.scene, r)
            p = predict(model, limit=False)     # (the run's is predicted whole below)
            m = measure_at(dataclasses.replace(prep, model_scene=model, pred=p), False)
            g = score = None
            if all(m.get(q) is not None and p.get(q) is not None for q in ("k", "b")):
                g = m["b"] - p["b"]
                tiny = 1e-300
                score = max(abs(m["k"] - p["k"]) / max(float(m.get("k_interval") or 0.0),
                                                       tiny),
                            abs(g) / max(float(m.get("b_interval") or 0.0), tiny))
            cache[r] = (m, p, g, score)
        return r, cache[r]

    def best_so_far():
        scored = [(r, c) for r, c in cache.items() if c[3] is not None]
        return min(scored, key=lambda rc: rc[1][3]) if scored else None

    n_grid = SPREAD_POINTS if hi > lo else 1
    grid = [float(v) for v in np.linspace(lo, hi, n_grid)]
    pts = [at(r) for r in grid]
    ok = [(r, c) for r, c in pts if c[2] is not None]
    for (r0, c0), (r1, c1) in zip(ok, ok[1:]):
        # the damping's bracket: regula falsi
        if c0[2] * c1[2] > 0.0:
            continue
        a, ga, b, gb = r0, c0[2], r1, c1[2]
        for _ in range(REFINE_STEPS):
            if ga == gb or (best_so_far() and best_so_far()[1][3] <= 0.1):
                break
            rc = at(a - ga * (b - a) / (gb - ga))
            if rc[1][2] is None:
                break
            if rc[1][2] * ga > 0.0:
                a, ga = rc[0], rc[1][2]
            else:
                b, gb = rc[0], rc[1][2]
        break
    best = best_so_far()
    if best is not None and n_grid > 1 and best[1][3] > 0.1:
        # the score's least near the best latency so far: golden section
        step = (hi - lo) / (n_grid - 1)
        a, b = max(lo, best[0] - step), min(hi, best[0] + step)
        phi = 0.5 * (math.sqrt(5.0) - 1.0)
        c, d = b - phi * (b - a), a + phi * (b - a)

        def sc(r):
            v = at(r)[1][3]
            return math.inf if v is None else v
        fc, fd = sc(c), sc(d)
        for _ in range(GOLDEN_STEPS):
            if fc <= fd:
                b, d, fd = d, c, fc
                c = b - phi * (b - a)
                fc = sc(c)
            else:
                a, c, fc = c, d, fd
                d = a + phi * (b - a)
                fd = sc(d)
        best = best_so_far()
    if best is None:
        best = at(0.5 * (lo + hi))                  # no pair anywhere: the middle's say
    r = best[0]
    model = timed_scene(prep.scene, r)
    p = predict(model)
    m = dict(measure_at(dataclasses.replace(prep, model_scene=model, pred=p), True))
    other = _explained_elsewhere(m, cache, r)
    if other is not None:
        # the predicted loop at another latency within the bounds explains the record
        # with its breaks: the run's measurement is made there, whole, with its review,
        # and taken where that review lets no "differs" stand
        model_o = timed_scene(prep.scene, other)
        p_o = predict(model_o)
        m_o = dict(measure_at(dataclasses.replace(prep, model_scene=model_o, pred=p_o),
                              True))
        if not _differs(m_o):
            r, p, m = other, p_o, m_o
            m["render_latency_review"] = (
                "the predicted loop at the latency picked did not explain the record "
                "with the breaks the board's unseen holds may have made; at this one "
                "it does")
    if m.get("within") is False and n_grid > 1 and _differs(m):
        # (a "not measurable" the review gave is no departure to widen: the spread's
        # verdict made again would have turned it back into "differs")
        _latency_spread(prep, m, p, r, (lo, hi), measure_at)
    m["render_latency_s"] = r
    m["render_latency_bounds_s"] = [lo, hi]
    m["render_latency_tried"] = len(cache) + 1
    m["render_latency_note"] = (
        f"the board renders {lo * 1e3:.2f}-{hi * 1e3:.2f} ms after its read: the loop "
        f"modelled with the latency within that at which measurement and prediction agree "
        f"best, {r * 1e3:.3f} ms (k and b compared there)")
    keep = {q: prep.pred[q] for q in ("render_latency_s", "k_spread", "b_spread")
            if q in prep.pred}
    prep.pred.clear()
    prep.pred.update(p)
    prep.pred.update(keep)
    prep.pred["render_latency_found_s"] = r
    prep.pred["delay_modelled"] = float(timed_scene(prep.scene, r).device.delay)
    return m


def _differs(m: dict) -> bool:
    """Whether a measurement's verdict is "measured differs" (not a review's "not
    measurable", nor a pair within)."""
    return str(m.get("verdict", "")).startswith("measured differs")


def _explained_elsewhere(m: dict, cache: dict, picked: float):
    """The latency, of those the search measured, at which the predicted loop with breaks
    explains the record of a board on its own tick whose "differs" the review at the
    latency picked let stand; None when there is none (or no such "differs").

    The latency is a nuisance parameter of the review's question, as of the verdict's:
    is the record the predicted loop's, with some latency within the bounds, with the
    breaks the board's unseen holds may have made
    (:func:`hapsim.analysis.unseen_verdict.break_prediction`)? The search picks the
    latency where the pair agrees best, and the unseen holds move the pair: on a paddle
    whose board took 74 of 242 commands late (tests/test_unseen_accepted.py) the latency
    picked was 0.17 ms off the board's own, where no break explains the record
    (chi-square 3e4 against 190), and at the board's own the record is explained with 7
    breaks (chi-square 9 against 880). The test is the least residual over the latency, a
    generalised likelihood ratio with the latency a nuisance (Kay, *Fundamentals of
    Statistical Signal Processing, Vol. II*, 1998, Sec. 6.5), its false alarm under a
    matching device at most the test's at the board's own latency. It is made at the
    :data:`REVIEW_LATENCIES` latencies the search measured whose records lie nearest the
    predicted loop with no break (:func:`hapsim.analysis.unseen_verdict.prediction_rss`):
    each test is a search of breaks (0.1-0.5 s on a default record), and a device that
    differs, whose "differs" every one of them lets stand, paid it at every latency
    tried (the suite's time grew ~0.3 s a wrong paddle); on that paddle the board's own
    latency came second of 23. A device that differs misfits every piece whatever the
    latency (module notes: the latency moves the felt damping by 5 % of it at most, and
    k hardly); the run's measurement is then made again, whole, at the latency found,
    its verdict its own.

    Parameters
    ----------
    m : dict
        The run's measurement at the latency picked.
    cache : dict
        ``{latency [s]: (measurement, prediction, ...)}``: the search's measurements, each
        with ``_tested`` (:func:`hapsim.pipeline.measure._identify_at`), popped here.
    picked : float
        The latency picked [s].

    Returns
    -------
    float or None
        The latency [s].
    """
    states = {r: c[0].pop("_tested", None) for r, c in cache.items()}
    test = m.get("prediction_test")
    if not (m.get("within") is False and test and test.get("explained") is False
            and _differs(m)):
        return None
    from hapsim.analysis.unseen_verdict import break_prediction, prediction_rss
    # the latencies tried, the nearest to the record first (its residual with no break):
    # a few only, each test a search of breaks over the record (0.1-0.5 s); on that
    # paddle the board's own latency came second of 23
    ranked = sorted((prediction_rss(st["position"], st["fit"], st["poles"]), r)
                    for r, st in states.items() if st is not None and r != picked)
    seen: list = []
    for _, r in ranked:
        if len(seen) >= REVIEW_LATENCIES:
            break
        if any(abs(r - q) <= 1e-9 for q in seen):
            continue                        # (the search's steps end on one latency)
        seen.append(r)
        st = states[r]
        got = break_prediction(st["position"], st["fit"], st["poles"], floor=st["floor"],
                               drop=st["drop"])
        if got["explained"]:
            return r
    return None


def _latency_spread(prep, m: dict, p: dict, r: float, bounds, measure_at) -> None:
    """A "differs" with the latency searched: the measured pair's stated half-widths
    widened to what it would be at the latency's bounds (in place).

    The search picks the latency at which measurement and prediction agree best: for a
    device that differs that says nothing of the board's own latency, and the measured
    pair, which the fit takes with the model's other poles, moves with the latency
    modelled. Its half-widths, stated at the latency picked, missed the board's own loop
    by up to ~100 of them on exact records (hidden friction of +0.05 N s/m, random
    paddles: the fixed point's b off by 1e-4 N s/m, stated +-1e-6). The pair is measured
    again, as the run's final measurement is but without its review of a "differs"
    (``measure_at(..., "spread")``), at the bound farther from the latency picked; the
    pair moves linearly with the latency (offline, a hidden friction of 0.05 N s/m: b
    0.116828, 0.116762, 0.116695 N s/m at 0.15, 0.20, 0.25 ms, equal steps to 2 %), so
    its move to the nearer bound is that one's in proportion. The half-widths become
    ``max(h, |m_end - m| + h_end)`` over both bounds (the nearer one's ``h_end`` the
    farther one's), and the verdict is made again with them
    (:func:`hapsim.analysis.measurement.verdict`): a departure the latency's share covers
    is no longer "differs". A bound that cannot be measured is named and the half-widths
    are those of the latency picked.
    """
    from hapsim.analysis.measurement import verdict
    from hapsim.analysis.prediction import predict
    if "k" not in m or m.get("k_interval") is None:
        return
    at = {"k_interval": m["k_interval"], "b_interval": m["b_interval"]}
    lo, hi = bounds
    far = lo if abs(r - lo) >= abs(hi - r) else hi
    near = hi if far == lo else lo
    model = timed_scene(prep.scene, far)
    me = measure_at(dataclasses.replace(prep, model_scene=model,
                                        pred=predict(model, limit=False)),
                    "spread")
    if "k" not in me or me.get("k_interval") is None:
        m["latency_spread"] = {"at_latency": at, "ends": [], "not_measured_s": [far]}
        m["latency_spread_note"] = (
            "the device differs and its latency is not known within the bounds; the pair "
            "could not be measured at its bound: the half-widths are those of the latency "
            "picked")
        return
    # the line through the two measurements, at the nearer bound (on the other side of
    # the latency picked, or the latency picked itself)
    share = (near - r) / (far - r)
    ends = [{"latency_s": far, "k": me["k"], "b": me["b"],
             "k_interval": me["k_interval"], "b_interval": me["b_interval"]},
            {"latency_s": near, "k": m["k"] + share * (me["k"] - m["k"]),
             "b": m["b"] + share * (me["b"] - m["b"]),
             "k_interval": me["k_interval"], "b_interval": me["b_interval"],
             "extrapolated": True}]
    dk = max(float(m["k_interval"]), *(abs(e["k"] - m["k"]) + float(e["k_interval"])
                                       for e in ends))
    db = max(float(m["b_interval"]), *(abs(e["b"] - m["b"]) + float(e["b_interval"])
                                       for e in ends))
    m["latency_spread"] = {"at_latency": at, "ends": ends, "not_measured_s": []}
    m["k_unc"], m["b_unc"] = max(float(m["k_unc"]), dk), max(float(m["b_unc"]), db)
    note = m.get("interval_note")
    verdict(p, m)
    m["interval_note"] = ((note + "; " if note else "") +
                          "with the pair's move to the latency's bounds (the device "
                          "differs: its own latency is not known within them)")
