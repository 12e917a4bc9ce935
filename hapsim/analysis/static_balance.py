"""Whether an n-D scene is at rest at the positions it names: the net force on each
mass there, and how far the linearisation at rest puts the balance.

``hapsim check`` linearises a scene at the positions its masses name (``x0``, the port's
among them: :func:`hapsim.analysis.virtual_network.link_blocks`), which is where a run
starts. A scene whose forces do not balance there (a pre-stretched spring, an anchor
moved, a mass resting inside a contact) is not at rest: a run's masses move from those
positions first, the device's handle with them, and the felt matrices it measures are
about the balance, not about the positions named (the 2DIY's and the Falcon's runs say so
from their record from rest, :func:`hapsim.lockstep.exact_records`). This module says it
before any run, in numpy alone (no engine: ``hapsim check`` stays a fraction of a second):
the force laws are the engine's at rest (``v0`` = 0: no damping force), summed link by
link (:mod:`hapsim.kernels.nd`'s module notes):

* a spring-damper of rest length ``L`` between masses 1 and 2, ``d = x1 - x2``: on mass 1
  ``-K d`` when ``L = 0``, else ``-K (|d| - L) d / |d|`` (none at ``|d| = 0``);
* a sphere contact of threshold ``r``: ``-K (|d| - r) d / |d|`` on mass 1 while
  ``0 < |d| < r``;
* a plane ``normal . x = offset``: ``K p normal`` while the penetration
  ``p = offset - normal . x`` is positive;

each with the opposite force on mass 2. The balance's distance is the linear estimate
``delta = K^-1 F`` over the masses that move (the port's included: its device adds no
stiffness), with ``K`` the stiffness blocks of the linearisation ``check`` itself uses; a
force no stiffness of it holds (``F`` outside ``K``'s range) has no such distance. Unlike
``check``'s stability, which counts every contact and plane engaged, the balance counts
only those engaged at the positions named (a floor a mass does not touch holds nothing).
Forces only: a mass given a ``v0`` starts moving by the scene's own design, which is not
said here.
"""

from __future__ import annotations

import numpy as np

__all__ = ["net_forces", "not_at_rest", "NOT_AT_REST_M"]

#: The distance [m] from the positions named to the linearised balance beyond which a
#: scene is not at rest (:data:`hapsim.emulated.falcon_felt.NOT_AT_REST_M`'s micrometre:
#: the shipped scenes' ten-digit positions are at rest to ~1e-10 m).
NOT_AT_REST_M = 1e-6


def _positions(scene) -> dict:
    """Each mass's position as named [m], by name."""
    return {m.name: np.asarray(m.x0, float) for m in scene.masses}


def _contact_engaged(lk, pos: dict) -> bool:
    """A sphere contact acts: ``0 < |d| < threshold`` (:mod:`hapsim.kernels.nd`)."""
    return 0.0 < float(np.linalg.norm(pos[lk.m1] - pos[lk.m2])) < lk.threshold


def _penetration(pl, x) -> float:
    """A plane's penetration ``offset - normal . x`` [m] (it acts while positive)."""
    return pl.offset - float(pl.normal @ x)


def net_forces(scene) -> tuple[dict, dict]:
    """The net force of the links and planes on each mass that moves, at the positions
    the scene names, at rest (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND

    Returns
    -------
    forces : dict of str to ndarray, shape (n,)
        [N], for every mass of kind ``mass`` or ``port``.
    scale : dict of str to float
        For each, the sum of its terms' magnitudes [N]: the round-off of the sum is a few
        ulps of it.
    """
    n = scene.dimension
    pos = _positions(scene)
    moving = {m.name for m in scene.masses if m.kind != "ground"}
    F = {k: np.zeros(n) for k in moving}
    S = {k: 0.0 for k in moving}

    def add(a, b, f):
        for name, sign in ((a, 1.0), (b, -1.0)):
            if name in F:
                F[name] += sign * f
                S[name] += float(np.abs(f).sum())

    for lk in scene.links:
        d = pos[lk.m1] - pos[lk.m2]
        ln = float(np.linalg.norm(d))
        if lk.kind == "contact":
            if _contact_engaged(lk, pos):
                add(lk.m1, lk.m2, -lk.stiffness * (ln - lk.threshold) * d / ln)
        elif lk.length == 0:
            add(lk.m1, lk.m2, -lk.stiffness * d)
        elif ln > 0.0:
            add(lk.m1, lk.m2, -lk.stiffness * (ln - lk.length) * d / ln)
    for pl in scene.planes:
        for m in pl.masses:
            p = _penetration(pl, pos[m])
            if p > 0.0 and m in F:
                f = pl.stiffness * p * np.asarray(pl.normal, float)
                F[m] += f
                S[m] += float(np.abs(f).sum())
    return F, S


def not_at_rest(scene, limit: float = NOT_AT_REST_M) -> dict | None:
    """Whether the scene is at rest at the positions it names (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    limit : float
        The balance's distance [m] beyond which it is not (default
        :data:`NOT_AT_REST_M`).

    Returns
    -------
    dict or None
        None when at rest: every net force within its round-off (64 ulps of its terms),
        or the linearised balance within ``limit`` of every position. Else ``mass`` (the
        mass with the largest net force), ``force`` (its net force [N], list of n),
        ``largest_force_n`` [N], ``balance_m`` (the largest distance [m] from the
        positions named to the linearised balance, over the moving masses; None when no
        stiffness of the linearisation holds the forces), ``balance_mass`` (where it is
        largest; None with it) and ``note`` (a sentence for ``hapsim check``).

    Raises
    ------
    ConfigError
        A Euclidean link whose masses coincide at the positions named
        (:func:`hapsim.analysis.virtual_network.link_blocks`), naming it.
    """
    from hapsim.analysis.virtual_network import link_blocks
    n = scene.dimension
    F, S = net_forces(scene)
    eps = np.finfo(float).eps
    off = {k: f for k, f in F.items() if np.abs(f).max() > 64 * eps * max(S[k], 1e-300)}
    if not off:
        return None
    names = sorted(F)
    idx = {k: i for i, k in enumerate(names)}
    pos = _positions(scene)
    # what holds a mass at the positions named: check's blocks less the contacts and the
    # (plane, mass) pairs not engaged there (check counts them engaged, for its stability:
    # here a floor a mass does not touch would hold it)
    links = {lk.name: lk for lk in scene.links}
    planes = {pl.name: pl for pl in scene.planes}
    K = np.zeros((n * len(names), n * len(names)))
    for name, a, b, Kl, _ in link_blocks(scene):
        lk = links.get(name)
        if b is None and name in planes:
            if not _penetration(planes[name], pos[a]) > 0.0:
                continue
        elif lk is not None and lk.kind == "contact" and not _contact_engaged(lk, pos):
            continue
        for p, q, sign in ((a, a, 1.0), (b, b, 1.0), (a, b, -1.0), (b, a, -1.0)):
            if p in idx and q in idx:
                i, j = idx[p], idx[q]
                K[n * i:n * i + n, n * j:n * j + n] += sign * Kl
    f = np.concatenate([F[k] for k in names])
    delta, *_ = np.linalg.lstsq(K, f, rcond=None)
    # held: the least-squares balance reproduces the force (F in K's range) to its
    # round-off (the solve's, a stiffness' condition times eps, within 1e-6 of it; the
    # forces', 64 ulps of their terms): else a force no stiffness at rest holds
    resid = np.abs(K @ delta - f).max()
    held = resid <= max(1e-6 * np.abs(f).max(), 64 * eps * max(S.values()))
    worst = max(off, key=lambda k: float(np.linalg.norm(off[k])))
    out = {"mass": worst, "force": off[worst].tolist(),
           "largest_force_n": float(np.linalg.norm(off[worst])),
           "balance_m": None, "balance_mass": None}
    if held:
        dist = np.linalg.norm(delta.reshape(-1, n), axis=1)
        if dist.max() <= limit:
            return None
        out["balance_m"] = float(dist.max())
        out["balance_mass"] = names[int(dist.argmax())]
    force = ", ".join(f"{v:+.4g}" for v in out["force"])
    where = (f"the linearisation at them puts the balance {out['balance_m'] * 1e3:.4g} mm "
             f"away (mass {out['balance_mass']!r})" if held else
             "no stiffness of the linearisation at them holds that force (the mass is "
             "carried away from them)")
    out["note"] = (f"not at rest at the positions named: the net force on {worst!r} is "
                   f"({force}) N, and {where}; this check is about the positions named, "
                   "where a run starts, and a run's masses move from them first")
    return out
