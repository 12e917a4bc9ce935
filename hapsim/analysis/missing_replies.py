"""A request-reply driver's 1-D loop as a switched system over the host's fresh, estimated
and skipped ticks.

A request-reply board (the Haply M3, the Hapkit sketch, the FireFader's ``.ino``) answers
each command; where an answer is overdue the host loop steps the engine with the position
extrapolated linearly from the last two records, at most
:data:`hapsim.host.host_clock.ESTIMATED_MAX` = 2 ticks in a row, then skips ticks (the
engine not stepped, the last force written again) until a record comes. The loop ``check``
predicts has every reading on time. Here each kind of tick has its own state matrix (the
exact zero-order hold of ``m x'' + b0 x' = f``, Florens et al. Sec. 6; the virtual
spring-damper ``f = -K r - B (r - r_prev) / T`` on the reading ``r``; ``d`` periods of
delay), and the growth of the loop over a periodic pattern of missing replies is the
spectral radius of the pattern's product per tick: over every pattern tried, a lower bound
of the switched system's joint spectral radius (Jungers, *The Joint Spectral Radius*,
2009, Sec. 1.2). ``tools/estimate_patterns.py`` charts it (docs/drivers.md, "Missing
replies and the loop's stability").
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = ["tick_matrices", "patterns", "growth", "worst_pattern", "wall_loop", "RULES",
           "MAX_RUN", "MAX_SHARE", "PERIOD_MAX"]

#: Most missing replies in a row the patterns hold, and their largest share of the ticks:
#: a board that answers late now and then, not one that has gone quiet (the host's
#: silence rules act there).
MAX_RUN = 2
MAX_SHARE = 0.25
#: Longest pattern a run's check tries [ticks].
PERIOD_MAX = 8
#: How the host steps a tick whose reply is missing: the kinds of the first, second...
#: missing reply in a row (``"S"``, a skipped tick, after them).
RULES = {"extrapolated (today)": ("E1", "E2"), "last record held": ("H1", "H2"),
         "skipped": ()}


def wall_loop(scene) -> tuple | None:
    """The loop this module models, read off a scene: spring-dampers from the port to
    ground only (their stiffness and damping summed, as :func:`hapsim.analysis.
    prediction.predict` renders them) and a zero-order hold.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        A 1-D scene (its delay a real number of periods).

    Returns
    -------
    tuple or None
        ``(m, b0, T, d, K, B)`` for :func:`tick_matrices`; None for another scene (no
        port or device, another link or mass, another hold, a delay not above 0).
    """
    from hapsim.analysis.prediction import port_links
    dev = scene.device
    if dev is None or scene.port is None:
        return None
    links = port_links(scene)
    if (not links or len(links) != len(scene.links) or dev.hold != "zoh"
            or not float(dev.delay) > 0
            or any(m.kind not in ("port", "ground") for m in scene.masses)):
        return None
    return (dev.mass, dev.friction, scene.period, float(dev.delay),
            sum(lk.stiffness for lk in links), sum(lk.damping for lk in links))


def tick_matrices(m: float, b0: float, T: float, d: float, K: float, B: float) -> dict:
    """The closed loop's state transition over one tick of each kind.

    The state is ``[x, v, q ..., r_prev, rec_1, rec_2]``: the device's position [m] and
    velocity [m/s], the forces written and not yet applied in full, the engine's last
    reading and the last two records [m]. A force computed from the reading of tick ``n``
    acts from ``(n + d) T`` on: for a whole ``d`` (``d`` forces queued, the oldest held
    over the period), or over a split period for a fraction ``d = k + delta`` (``k + 1``
    forces queued: the older over the period's first ``delta T``, the newer over the
    rest; the split hold of the modified z-transform, Jury 1964, as
    :mod:`hapsim.analysis.subsample` models it).

    Parameters
    ----------
    m, b0, T : float
        Moving mass [kg], viscous friction [N s/m], sample period [s] (all > 0; b0 >= 0).
    d : float
        Delay [periods], > 0 (a fraction below 1: the force of a reading acts within its
        own period, after ``d T``).
    K, B : float
        The virtual stiffness [N/m] and damping [N s/m] to ground.

    Returns
    -------
    dict
        ``"F"`` (a fresh record), ``"E1"``, ``"E2"`` (the first and second estimate,
        extrapolated from the last two records: ``2 rec_1 - rec_2``, ``3 rec_1 - 2
        rec_2``), ``"H1"``, ``"H2"`` (the last record held), ``"S"`` (a skipped tick: the
        last force written again): square arrays, ``d + 5`` states for a whole ``d``,
        ``floor(d) + 6`` otherwise.

    Raises
    ------
    ValueError
        ``d <= 0``.
    """
    from hapsim.analysis.loop import zoh_state_space
    d = float(d)
    if not d > 0:
        raise ValueError(f"the delay must be > 0 periods, got {d}")
    k = int(round(d)) if abs(d - round(d)) < 1e-12 else int(np.floor(d))
    whole = abs(d - k) < 1e-12
    Ad, Bd = zoh_state_space(m, b0, T)
    if whole:
        nq, B1, B2 = k, None, None
    else:
        A2, B2 = zoh_state_space(m, b0, (1.0 - (d - k)) * T)
        B1 = A2 @ zoh_state_space(m, b0, (d - k) * T)[1]
        nq = k + 1
    n = 2 + nq + 3
    eye = np.eye(n)
    iq, ir, i1, i2 = 2, 2 + nq, 3 + nq, 4 + nq

    def build(r, fresh: bool):
        M = np.zeros((n, n))
        # the force written this tick: from the reading, or the last one again (a skip)
        un = eye[iq] if r is None else -K * r - B / T * (r - eye[ir])
        if whole:
            # the queue's oldest (written d ticks ago) held over the period
            M[0:2] = Ad @ eye[0:2] + np.outer(Bd, eye[iq + nq - 1])
        else:
            # the oldest over the first delta T, the next (this tick's, k = 0) the rest
            newer = un if k == 0 else eye[iq + k - 1]
            M[0:2] = Ad @ eye[0:2] + np.outer(B1, eye[iq + k]) + np.outer(B2, newer)
        M[iq] = un                                  # the queue moves on one tick
        for j in range(1, nq):
            M[iq + j] = eye[iq + j - 1]
        if r is None:
            M[ir], M[i1], M[i2] = eye[ir], eye[i1], eye[i2]
        else:
            M[ir] = r
            M[i1], M[i2] = (r, eye[i1]) if fresh else (eye[i1], eye[i2])
        return M

    held = build(eye[i1], False)
    return {"F": build(eye[0], True), "E1": build(2 * eye[i1] - eye[i2], False),
            "E2": build(3 * eye[i1] - 2 * eye[i2], False), "H1": held, "H2": held,
            "S": build(None, False)}


def patterns(rule: tuple, period_max: int = PERIOD_MAX, max_run: int = MAX_RUN,
             max_share: float = MAX_SHARE) -> set:
    """Every periodic pattern of missing replies up to ``period_max`` ticks, with at most
    ``max_run`` in a row and a share of at most ``max_share``, each tick named by ``rule``.

    Parameters
    ----------
    rule : tuple of str
        The kinds of the first, second... missing reply in a row (:data:`RULES`);
        ``"S"`` after them.
    period_max, max_run : int
    max_share : float

    Returns
    -------
    set of tuple of str
        Each pattern from a fresh tick (``"F"``) on, one rotation each.
    """
    out = set()
    for L in range(1, int(period_max) + 1):
        for p in itertools.product((0, 1), repeat=L):
            if all(p) or sum(p) > max_share * L:
                continue
            s = p.index(0)
            q = p[s:] + p[:s]
            kinds, run = [], 0
            for miss in q:
                run = run + 1 if miss else 0
                if run > max_run:
                    break
                kinds.append("F" if not miss else rule[run - 1] if run <= len(rule) else "S")
            else:
                out.add(tuple(kinds))
    return out


def growth(mats: dict, pattern) -> float:
    """The loop's growth per tick over a periodic pattern: the spectral radius of the
    product of its ticks' matrices, to the power ``1 / len(pattern)``.

    Parameters
    ----------
    mats : dict
        :func:`tick_matrices`.
    pattern : sequence of str
        Kinds of tick, in order (non-empty).

    Returns
    -------
    float
        Above 1: the loop grows under that pattern repeated.
    """
    P = np.eye(next(iter(mats.values())).shape[0])
    for k in pattern:
        P = mats[k] @ P
    return float(max(abs(np.linalg.eigvals(P)))) ** (1.0 / len(pattern))


def worst_pattern(m: float, b0: float, T: float, d: int, K: float, B: float,
                  rule: tuple = RULES["extrapolated (today)"],
                  period_max: int = PERIOD_MAX) -> tuple:
    """The pattern of missing replies that grows the loop most, of :func:`patterns`.

    Parameters
    ----------
    m, b0, T, d, K, B
        As :func:`tick_matrices` (``d`` a real number of periods).
    rule : tuple of str
        How a missing reply's tick is stepped (default: the host's extrapolation).
    period_max : int
        Longest pattern [ticks].

    Returns
    -------
    (float, str)
        Its growth per tick and the pattern (``F`` fresh, ``E`` estimated, ``H`` the
        last record held, ``S`` skipped).
    """
    mats = tick_matrices(m, b0, T, d, K, B)
    g, p = max((growth(mats, p), p) for p in patterns(rule, period_max))
    return g, "".join(k[0] for k in p)
