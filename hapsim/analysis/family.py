"""Families of THS: the hand varies, what is felt and whether every member is stable.

Florens, Voda & Urma Sec. 4: the simulator must be judged over "the whole family of
possible parameter sets that the THS may get along its variations". The family here is
the hand of the device section (:class:`hapsim.scene.Hand`, each field a value or a range):
its members are the range corners, the nominal member and a grid or seeded samples
(:func:`hapsim.analysis.hand.members`).

For every member the closed-loop state matrix of the whole scene
(:func:`hapsim.analysis.network.closed_loop`) differs only in its plant rows, so the
family is one stack of matrices and one batched ``numpy.linalg.eigvals`` call. The felt
pair is the least damped complex pair, ``k = m |s|^2``, ``b = -2 m Re s`` with ``m`` the
member's total moving mass (handle + hand), ``s = ln(z)/T`` (docs/design.md,
'The inverse map').
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from hapsim.analysis.hand import HAND_FIELDS, hand_stiffness
from hapsim.analysis.family_loops import (family_matrices, family_members, family_poles,
                                          full_members, require_port_scene)
from hapsim.analysis.loop import STABILITY_TOL
from hapsim.analysis.scene_check import RIGID_TOL
from hapsim.errors import ConfigError
from hapsim.outputs import finite_or_none as _f

__all__ = ["FamilyResult", "FamilyCalibration", "family", "family_matrices", "family_poles",
           "felt_pairs",
           "felt_links", "family_error", "calibrate_family", "consistency",
           "family_members"]


def felt_pairs(ev: np.ndarray, mass, period: float):
    """Felt ``(k, b)`` and spectral radius of every row of eigenvalues (vectorised).

    Parameters
    ----------
    ev : ndarray of complex, shape (n, s)
        Closed-loop poles per member.
    mass : float or ndarray, shape (n,)
        Reference mass per member [kg].
    period : float
        ``T`` [s].

    Returns
    -------
    k, b : ndarray, shape (n,)
        ``m |s|^2`` [N/m] and ``-2 m Re s`` [N s/m] of the least damped complex pair
        (largest ``|z|`` among poles with ``Im z > 0``); nan when a member has none.
    rho : ndarray, shape (n,)
        Spectral radius ``max |z|``.
    stable : ndarray of bool, shape (n,)
        ``rho <= 1 + STABILITY_TOL``, poles within ``RIGID_TOL`` of ``z = 1`` excepted
        (as :func:`hapsim.analysis.check_scene`).
    """
    mod = np.abs(ev)
    rho = mod.max(axis=1)
    near_one = np.abs(ev - 1.0) <= RIGID_TOL
    stable = np.all((mod <= 1.0 + STABILITY_TOL) | near_one, axis=1)
    cplx = ev.imag > 1e-12 * np.maximum(mod, 1e-300)
    score = np.where(cplx, mod, -1.0)
    j = np.argmax(score, axis=1)
    z = ev[np.arange(ev.shape[0]), j]
    has = score[np.arange(ev.shape[0]), j] > 0
    s = np.log(np.where(has, z, 1.0)) / period
    m = np.broadcast_to(np.asarray(mass, float), rho.shape)
    k = np.where(has, m * np.abs(s) ** 2, np.nan)
    b = np.where(has, -2.0 * m * s.real, np.nan)
    return k, b, rho, stable


def _one_link_scene(scene, lk):
    """The scene reduced to the port, one ground and one link between them."""
    keep = {lk.m1, lk.m2}
    masses = tuple(m for m in scene.masses if m.name in keep)
    return dataclasses.replace(scene, masses=masses, links=(lk,))


def felt_links(scene, calibrated=None) -> list:
    """The links whose felt ``(k, b)`` a family reports: every spring_damper between the
    port and a ground (targets first, in file order).

    Parameters
    ----------
    scene : hapsim.scene.Scene
    calibrated : mapping, optional
        ``{link: (K, B)}`` for target links.

    Returns
    -------
    list of (Link, float, float)
        ``(link, K [N/m], B [N s/m])``.
    """
    if scene.port is None:
        return []
    kinds = {m.name: m.kind for m in scene.masses}
    cal = dict(calibrated or {})
    out = []
    for lk in scene.links:
        ends = {kinds[lk.m1], kinds[lk.m2]}
        if lk.kind == "spring_damper" and ends == {"port", "ground"}:
            K, B = cal.get(lk.name, (lk.stiffness, lk.damping))
            out.append((lk, float(K), float(B)))
    out.sort(key=lambda t: t[0].target is None)
    return out


def _stats(v: np.ndarray, nominal: float) -> dict:
    ok = np.isfinite(v)
    if not ok.any():
        return {"min": None, "max": None, "nominal": None, "spread": None}
    lo, hi = float(v[ok].min()), float(v[ok].max())
    return {"min": lo, "max": hi, "nominal": _f(nominal),
            "spread": (hi - lo) / abs(nominal) if math.isfinite(nominal) and nominal else None}


@dataclass(frozen=True)
class FamilyResult:
    """What a family of THS feels, and whether all of it is stable.

    Attributes
    ----------
    members : ndarray, shape (n, 5)
        ``(mh, bh, kg, bg, kh)`` per member (:data:`hapsim.analysis.hand.HAND_FIELDS`); rows
        ``0 .. corners-1`` are the range corners, row ``corners`` the nominal member.
    corners : int
        Number of corner members.
    mass : ndarray, shape (n,)
        Total moving mass (handle + hand) per member [kg].
    rho : ndarray, shape (n,)
        Spectral radius of the whole scene per member.
    stable : ndarray of bool, shape (n,)
        Verdict per member.
    k, b : ndarray, shape (n,)
        Felt pair at the port of the whole scene per member [N/m, N s/m].
    links : dict
        ``{link name: {"K", "B", "k": ndarray (n,), "b": ndarray (n,)}}``: the felt pair of
        each port-ground spring_damper alone (:func:`felt_links`) on the member (with the
        hand's stiffness to ground, when it has one: :func:`consistency` separates them).
    calibrated : dict
        ``{link: (K, B)}`` used for target links (calibrated on the nominal member).
    period : float
        ``T`` [s].
    """

    members: np.ndarray
    corners: int
    mass: np.ndarray
    rho: np.ndarray
    stable: np.ndarray
    k: np.ndarray
    b: np.ndarray
    links: dict = field(default_factory=dict)
    calibrated: dict = field(default_factory=dict)
    period: float = 1e-3
    certificate: object = None

    @property
    def robust(self) -> bool:
        """Whether no member is known unstable: every sampled member stable and, when the
        ranges were certified (:mod:`hapsim.analysis.robust`), no unstable member found
        between them. Over the continuous ranges only when :attr:`robust_method` is
        ``"certified"``."""
        cert = self.certificate
        if cert is not None and cert.certified and not cert.robust:
            return False
        return bool(np.all(self.stable))

    @property
    def robust_method(self) -> str:
        """``"certified"`` (the verdict holds for every member of the continuous ranges:
        proven by :func:`hapsim.analysis.robust.certify_family`, or an unstable member is a
        proof; in floating point, its rounding not bounded:
        :data:`hapsim.analysis.robust.ARITHMETIC`) or ``"sampled (N)"`` (N members
        examined, nothing said between them)."""
        cert = self.certificate
        if not np.all(self.stable) or (cert is not None and cert.certified):
            return "certified"
        return f"sampled ({self.members.shape[0]})"

    @property
    def worst(self) -> int:
        """Index of the member with the largest spectral radius."""
        return int(np.argmax(self.rho))

    def member_dict(self, i: int) -> dict:
        """Member ``i`` as ``{field: value}`` plus its verdict, spectral radius and felt pair.

        Parameters
        ----------
        i : int
            Row of :attr:`members`.

        Returns
        -------
        dict
            Each :data:`~hapsim.analysis.hand.HAND_FIELDS` value (``grip_stiffness``
            ``"rigid"`` when infinite), ``index``, ``corner`` (bool), ``stable``,
            ``spectral_radius`` [-], ``k`` [N/m] and ``b`` [N s/m]; non-finite numbers None.
        """
        out = {f: _f(self.members[i, j]) for j, f in enumerate(HAND_FIELDS)}
        out["grip_stiffness"] = ("rigid" if not math.isfinite(self.members[i, 2])
                                 else float(self.members[i, 2]))
        out.update(index=int(i), corner=bool(i < self.corners), stable=bool(self.stable[i]),
                   spectral_radius=_f(self.rho[i]), k=_f(self.k[i]), b=_f(self.b[i]))
        return out

    def to_dict(self) -> dict:
        """JSON-ready summary.

        Returns
        -------
        dict
            ``members`` (count), ``corners``, ``robust``, ``robust_method``
            (:attr:`robust_method`), ``certificate`` (the subdivision's
            :meth:`hapsim.analysis.robust.Certificate.to_dict`, or None), ``worst``
            (:meth:`member_dict`),
            ``unstable`` (count), ``first_unstable`` (member dict or None),
            ``corners_stable``, ``felt`` (``k``, ``b`` stats: min, max, nominal, spread =
            (max - min) / nominal), ``links`` (per link: K, B and the same stats),
            ``calibrated``.
        """
        nom = self.corners
        bad = np.flatnonzero(~self.stable)
        links = {}
        for name, d in self.links.items():
            links[name] = {"K": d["K"], "B": d["B"], "k": _stats(d["k"], d["k"][nom]),
                           "b": _stats(d["b"], d["b"][nom])}
        return {"members": int(self.members.shape[0]), "corners": int(self.corners),
                "robust": self.robust, "robust_method": self.robust_method,
                "certificate": (None if self.certificate is None
                                else self.certificate.to_dict()),
                "unstable": int(bad.size),
                "corners_stable": bool(np.all(self.stable[:self.corners])),
                "worst": self.member_dict(self.worst),
                "first_unstable": self.member_dict(int(bad[0])) if bad.size else None,
                "felt": {"k": _stats(self.k, self.k[nom]), "b": _stats(self.b, self.b[nom])},
                "links": links,
                "calibrated": {k: [float(v[0]), float(v[1])] for k, v in
                               self.calibrated.items()}}


def family(scene, samples: int | None = None, *, grid: int = 9, seed: int = 0,
           calibrated=None, mem: np.ndarray | None = None,
           certify: int = 0) -> FamilyResult:
    """Felt (k, b), spectral radius and verdict of every member of a scene's hand family.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene with a port and a device section (``device.hand`` optional).
    samples : int, optional
        Seeded random members after the corners (default: a grid of ``grid`` points per
        ranged field).
    grid : int, optional
        Grid points per ranged field.
    seed : int, optional
        Sampling seed.
    calibrated : mapping, optional
        ``{link: (K, B)}``; default: every target link calibrated on the nominal member
        (:func:`hapsim.analysis.targets.apply_targets`).
    mem : ndarray, shape (n, 4) or (n, 5), optional
        Explicit members (overrides ``samples``/``grid``; no corners then: ``corners = 0``
        and row 0 is taken as nominal).
    certify : int, optional
        When > 0 and every sampled member is stable, certify the verdict over the
        continuous ranges with at most this many boxes
        (:func:`hapsim.analysis.robust.certify_family`); 0: sampled only.

    Returns
    -------
    FamilyResult

    Raises
    ------
    ConfigError
        No port/device, a correction on the device, an unrenderable target.
    """
    from hapsim.analysis.targets import apply_targets

    require_port_scene(scene)
    if calibrated is None:
        sc, cals = apply_targets(scene)
        calibrated = {c.link: (c.result.K, c.result.B) for c in cals}
    corners = 0
    if mem is None:
        mem = family_members(scene, samples, grid=grid, seed=seed)
        hand = getattr(scene.device, "hand", None)
        if hand is not None:
            from hapsim.analysis.hand import ranged_fields
            corners = 2 ** len(ranged_fields(hand))
    mem = full_members(mem)
    T = scene.period
    mass = float(scene.device.mass) + mem[:, 0]
    k, b, rho, stable = felt_pairs(family_poles(scene, mem, calibrated=calibrated), mass, T)
    links = {}
    for lk, K, B in felt_links(scene, calibrated):
        sub = _one_link_scene(scene, lk)
        cal = {lk.name: (K, B)} if lk.name in calibrated else None
        if len(scene.links) == 1:
            lk_k, lk_b = k, b
        else:
            lk_k, lk_b, _, _ = felt_pairs(family_poles(sub, mem, calibrated=cal), mass, T)
        links[lk.name] = {"K": K, "B": B, "k": lk_k, "b": lk_b,
                          "target": None if lk.target is None else tuple(lk.target)}
    cert = None
    if certify > 0 and np.all(stable):
        from hapsim.analysis.robust import certify_family
        cert = certify_family(scene, calibrated, max_boxes=int(certify))
    return FamilyResult(members=mem, corners=corners, mass=mass, rho=rho, stable=stable,
                        k=k, b=b, links=links, calibrated=dict(calibrated), period=T,
                        certificate=cert)


# --------------------------------------------------------------------------- minimax

@dataclass(frozen=True)
class FamilyCalibration:
    """Virtual (K, B) of one link for a whole family: minimax against nominal.

    Attributes
    ----------
    link : str
        Link name.
    k, b : float
        Target felt stiffness [N/m] and damping [N s/m].
    K, B : float
        Minimax virtual stiffness [N/m] and damping [N s/m].
    error : float
        Worst relative error over the family at (K, B):
        ``max_i max(|k_i - k| / k, |b_i - b| / b)`` [-] (``inf`` if a member is unstable).
    limiting : int
        Index of the member that sets ``error``.
    nominal_K, nominal_B : float
        Calibration on the nominal member alone (:func:`hapsim.analysis.calibrate`).
    nominal_error : float
        The same figure of merit at the nominal calibration.
    stable : bool
        Every member stable at (K, B).
    members : ndarray, shape (n, 5)
        The family (:data:`hapsim.analysis.hand.HAND_FIELDS`).
    """

    link: str
    k: float
    b: float
    K: float
    B: float
    error: float
    limiting: int
    nominal_K: float
    nominal_B: float
    nominal_error: float
    stable: bool
    members: np.ndarray

    def to_dict(self) -> dict:
        """JSON-ready dict of every attribute (``members`` as its count, ``limiting`` as
        the member's ``{mass, damping, grip_stiffness, grip_damping, index}``).

        Returns
        -------
        dict
            ``link``, ``k``, ``b``, ``K``, ``B``, ``error``, ``limiting`` (every
            :data:`~hapsim.analysis.hand.HAND_FIELDS` value, ``stiffness`` included, and
            ``index``), ``stable``, ``nominal`` (``K``, ``B``, ``error``) and ``members``
            (the count); non-finite ``K``, ``B``, errors and member values as None.
        """
        lim = {f: _f(self.members[self.limiting, j]) for j, f in enumerate(HAND_FIELDS)}
        lim["index"] = int(self.limiting)
        return {"link": self.link, "k": self.k, "b": self.b, "K": _f(self.K), "B": _f(self.B),
                "error": _f(self.error), "limiting": lim, "stable": bool(self.stable),
                "nominal": {"K": _f(self.nominal_K), "B": _f(self.nominal_B),
                            "error": _f(self.nominal_error)},
                "members": int(self.members.shape[0])}


def family_error(scene, link, k: float, b: float, mem: np.ndarray, K: float, B: float):
    """Worst relative felt-(k, b) error of one link over a family, and where it is.

    Parameters
    ----------
    scene : hapsim.scene.Scene
    link : hapsim.scene.Link
        A spring_damper between the port and a ground.
    k, b : float
        Target [N/m], [N s/m].
    mem : ndarray, shape (n, 4) or (n, 5)
        Members.
    K, B : float
        Virtual (K, B) of the link.

    Returns
    -------
    (float, int, bool)
        ``max_i max(|k_i - k|/k, |b_i - b|/b)`` (``inf`` when a member is unstable or rings
        no pair), the index of the worst member, and whether every member is stable.
    """
    sub = _one_link_scene(scene, link)
    ev = family_poles(sub, mem, calibrated={link.name: (float(K), float(B))})
    kk, bb, rho, stable = felt_pairs(ev,
                                     float(scene.device.mass) + mem[:, 0], scene.period)
    err = np.maximum(np.abs(kk - k) / k, np.abs(bb - b) / b)
    err = np.where(stable & np.isfinite(err), err, np.inf)
    i = int(np.argmax(np.where(np.isfinite(err), err, np.inf)))
    if not np.all(stable):
        i = int(np.argmax(rho))
    return float(err[i]), i, bool(np.all(stable))


def calibrate_family(scene, link_name: str, k: float | None = None, b: float | None = None,
                     mem: np.ndarray | None = None, *, samples: int | None = None,
                     grid: int = 5, seed: int = 0) -> FamilyCalibration:
    """Minimax calibration: the (K, B) whose worst felt error over the family is least.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        With a port, a device (``device.hand`` gives the family) and the link.
    link_name : str
        A spring_damper between the port and a ground.
    k, b : float, optional
        Target; default the link's ``target``.
    mem : ndarray, shape (n, 4) or (n, 5), optional
        The family (default :func:`family_members` with ``samples``/``grid``/``seed``).

    Returns
    -------
    FamilyCalibration

    Raises
    ------
    ConfigError
        Unknown link, a link that is not port-ground, no target given.

    Notes
    -----
    ``min_(K, B) max_i max(|k_i - k|/k, |b_i - b|/b)``: a non-smooth minimax, solved by
    ``scipy.optimize.minimize`` (Nelder-Mead, in ``log K`` and ``B``) started from the
    calibration (Florens et al. Sec. 5; :func:`hapsim.analysis.calibrate`) of the nominal
    member and of every corner; the best end point is kept. The nominal calibration is one
    of the starts, so the minimax error is never worse than the nominal one.
    """
    from scipy.optimize import minimize

    from hapsim.analysis.loop import LoopModel
    from hapsim.analysis.ths import calibrate

    links = {lk.name: lk for lk, _, _ in felt_links(scene, {
        lk.name: (0.0, 0.0) for lk in scene.links if lk.target is not None})}
    if link_name not in links:
        raise ConfigError(f"no spring_damper between the port and a ground named "
                          f"{link_name!r}; valid: {', '.join(links) or '(none)'}",
                          file=scene.path, key="links")
    lk = links[link_name]
    if k is None or b is None:
        if lk.target is None:
            raise ConfigError(f"link {link_name!r} has no target {{k, b}}", file=scene.path,
                              key=f"links.{link_name}.target")
        k, b = lk.target
    k, b = float(k), float(b)
    if mem is None:
        mem = family_members(scene, samples, grid=grid, seed=seed)
    mem = full_members(mem)
    hand = getattr(scene.device, "hand", None)
    ncorner = 0
    if hand is not None:
        from hapsim.analysis.hand import nominal_member, ranged_fields
        ncorner = 2 ** len(ranged_fields(hand))
        nominal = nominal_member(hand)
    else:
        nominal = mem[0]
    starts = []
    for row in [nominal] + [mem[i] for i in range(min(ncorner, mem.shape[0]))]:
        c = calibrate(LoopModel.from_device(scene.device, scene.rate_hz, row), k, b)
        if math.isfinite(c.K) and math.isfinite(c.B) and c.K > 0:
            starts.append((c.K, c.B))
    if not starts:
        raise ConfigError(f"target (k, b) = ({k:g}, {b:g}) has no calibration on any "
                          "corner or the nominal member", file=scene.path,
                          key=f"links.{link_name}.target")
    nK, nB = starts[0]
    n_err, _, _ = family_error(scene, lk, k, b, mem, nK, nB)

    def cost(p):
        e, _, _ = family_error(scene, lk, k, b, mem, math.exp(p[0]), p[1])
        return e if math.isfinite(e) else 1e6

    best = (n_err if math.isfinite(n_err) else 1e6, nK, nB)
    for K0, B0 in starts:
        r = minimize(cost, [math.log(K0), B0], method="Nelder-Mead",
                     options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 400,
                              "initial_simplex": [[math.log(K0), B0],
                                                  [math.log(K0) + 0.1, B0],
                                                  [math.log(K0), B0 + 0.1 * max(abs(B0), b)]]})
        if r.fun < best[0]:
            best = (float(r.fun), math.exp(r.x[0]), float(r.x[1]))
    _, K, B = best
    err, lim, stable = family_error(scene, lk, k, b, mem, K, B)
    return FamilyCalibration(link=link_name, k=k, b=b, K=K, B=B, error=err, limiting=lim,
                             nominal_K=nK, nominal_B=nB, nominal_error=n_err, stable=stable,
                             members=mem)


# --------------------------------------------------------------------------- consistency

def consistency(scene, samples: int | None = None, *, grid: int = 9, seed: int = 0,
                calibrated=None, mem: np.ndarray | None = None) -> dict:
    """Table 1 generalised: is the felt assembly the assembly of the felt parts?

    Florens, Voda & Urma Sec. 3 / Table 1: two virtual springs tuned to ring like a real
    one each do not ring like two real springs together (case IV), nor does a virtual
    spring with a real one (case V). Here, for every member of the hand family, the felt
    pair of the whole scene ``(k, b)`` is set against the parallel assembly of the felt
    parts, where the parts are every spring_damper between the port and a ground and, when
    the hand has a stiffness to ground ``kh`` (``device.hand.stiffness``), that real
    spring:

    - a virtual link's part is the pair it makes felt alone, on the member *without* the
      real spring (``kh = 0``);
    - the real spring's part is itself, ``kh`` (a real spring is felt as it is);
    - ``k_sum = kh + sum k_i``, ``b_sum = sum b_i - (n - 1) b_real`` over the ``n``
      virtual links (each ``b_i`` carries the real damping ``b_real`` = device friction +
      hand damping once; the assembly carries it once).

    Parameters
    ----------
    scene : hapsim.scene.Scene
    samples, grid, seed, calibrated, mem
        As :func:`family`.

    Returns
    -------
    dict
        ``links`` (names of the virtual parts), ``real_spring`` (bool: ``kh > 0`` in some
        member), ``members`` (count), ``k_ratio`` / ``b_ratio``: stats (``min``, ``max``,
        ``nominal``) of ``k / k_sum`` and ``b / b_sum`` (1 is consistent), ``worst_k``,
        ``worst_b``: largest ``|ratio - 1|``; ``k``, ``k_sum``, ``b``, ``b_sum``,
        ``k_real``: ndarrays, shape (n,), per member.

    Raises
    ------
    ConfigError
        Fewer than two parts (two port-ground spring_dampers, or one and the hand's
        stiffness).

    Notes
    -----
    With ``m = T = 1``, ``d = 0``, the ideal hold, no damping, one virtual link tuned by
    eq. (2) and ``kh = k``, ``k / k_sum`` is Table 1's felt k V / 2k
    (:func:`hapsim.analysis.table1.table1_experiment`, tested to 1e-9); with two virtual
    links and no ``kh``, felt k IV / 2k.
    """
    res = family(scene, samples, grid=grid, seed=seed, calibrated=calibrated, mem=mem)
    names = list(res.links)
    k_real = hand_stiffness(res.members)
    real = bool(np.any(k_real > 0))
    if len(names) + real < 2:
        raise ConfigError("consistency needs two or more parts between the port and a "
                          "ground: spring_dampers in parallel, or one and the hand's "
                          "stiffness (device.hand.stiffness)", file=scene.path, key="links")
    parts = res
    if real:                 # each virtual part felt without the real spring
        mem0 = res.members.copy()
        mem0[:, 4] = 0.0
        parts = family(scene, calibrated=res.calibrated, mem=mem0)
    b_real = float(scene.device.friction) + res.members[:, 1]
    k_sum = k_real + sum(parts.links[n]["k"] for n in names)
    b_sum = (sum(parts.links[n]["b"] for n in names) - (len(names) - 1) * b_real
             if names else b_real)
    with np.errstate(invalid="ignore", divide="ignore"):
        kr = res.k / k_sum
        br = res.b / b_sum
    nom = res.corners
    return {"links": names, "real_spring": real, "members": int(res.members.shape[0]),
            "k_ratio": _stats(kr, kr[nom]), "b_ratio": _stats(br, br[nom]),
            "worst_k": float(np.nanmax(np.abs(kr - 1.0))),
            "worst_b": float(np.nanmax(np.abs(br - 1.0))),
            "k": res.k, "k_sum": k_sum, "b": res.b, "b_sum": b_sum, "k_real": k_real}
