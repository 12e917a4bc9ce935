"""Robust stability certified over the continuous ranges of a hand family, not sampled.

A grid of members can miss a narrow unstable band between two of its points (a grip
resonance: every corner and every grid member stable, grips between two of them not).
:func:`certify_family` proves the verdict over every member of the ranges, or finds an
unstable one, by a certified subdivision of the parameter box.

Method (Bauer-Fike on boxes). For a box of members with centre ``c`` the closed-loop state
matrix is ``A(p) = A(c) + E(p)``; ``E`` lives in the plant rows only (the hand changes the
plant's zero-order hold ``Ad = e^(Ac T)``, ``Bd = int_0^T e^(Ac s) ds b``; the delay line,
the virtual network and the correction do not change), so ``E = [dAd + dBd u^T; 0]``. If
``A(c) = V Lambda V^-1``, every eigenvalue of ``A(p)`` lies within ``kappa(V) ||E(p)||`` of
one of ``A(c)`` (Bauer & Fike 1960), so the whole box is stable when

    rho(A(c)) + kappa_2(V) sup_box ||E|| < 1.

The bound on ``E`` is rigorous: written in ``q = 1/mh`` (``1/(mc + mh)`` for a rigid grip)
and the other fields, ``Ac`` is affine in each variable separately (:func:`hapsim.analysis.hand.
hand_matrices`), so its logarithmic norm ``mu`` (convex) and the norm of each partial
derivative (affine in the others) take their maxima over the box at its vertices. With
``||e^(Ac t)|| <= e^(mu t)`` (Dahlquist 1959) and the mean value theorem along the box,

    ||dAd|| <= T e^(mu+ T) sum_j h_j ||dAc/dp_j||,
    ||dBd|| <= e^(mu+ T) sum_j h_j (T^2/2 ||dAc/dp_j|| ||b|| + T ||db/dp_j||),

``h_j`` the half-width of the box along ``p_j`` (``h_j ||dAc/dp_j||`` is half the largest
change of ``Ac`` along an edge of the box, exact since ``Ac`` is affine along it). Every
state is scaled to metres (velocities by ``T``, forces by ``T^2 / m``) before the norms are
taken (the exponentials themselves are bounded in energy-like coordinates, velocities
over the box's largest natural frequency, and carried over by the scalings' ratio). A box
that is not proven is bisected along the variable that contributes most; a box
whose centre is unstable is a counterexample (the family is certainly not robustly stable).
The subdivision stops at ``max_boxes``: the verdict is then not certified.

A second, often much tighter test is tried on every box (:func:`_mode_bound`): Gershgorin's
theorem on the columns of ``Lambda + V^-1 E V`` puts the poles of every member in disks
round the centre's poles whose radii scale with ``||E v_j||``, the change acting on each
mode: small for a mode the change hardly strains (hand and handle moving together at the
wall's frequency), where the norm of ``E`` sees the grip's stiffest direction. A box is
proven when either bound is below 1.

What is proven, exactly: the subdivision's bounds (Bauer-Fike, Gershgorin, the change of
the plant over a box) are theorems about the matrices computed, evaluated in floating
point. The computed decomposition's own inexactness is carried (its residual
``||A V - V Lambda||`` through ``kappa(V)`` and ``||V^-1||``), but the rounding of the
centre's matrix (its exponential and the loop's assembly), of the residual, ``kappa(V)``,
``||V^-1||`` and the norms themselves, and of the eigenvalues that find an unstable member,
is not bounded; the bounds are padded by a relative ``1e-6`` and ``1e-12`` against it, a
choice, not a derived bound. The verdict is therefore "certified in floating point: rounding
not bounded" (:data:`ARITHMETIC`, in the report and the JSON), not a proof in exact or
interval arithmetic (contrast :mod:`hapsim.analysis.limit_certificate`, exact rational
arithmetic). A family whose bound comes within the rounding of these computations
(amplified by ``kappa(V)``) of the circle is where it could be wrong; that distance is not
computed.

Only the zero-order hold is certified (the ideal hold's rows are a different realisation);
a pole within ``RIGID_TOL`` of ``z = 1`` (a free body) cannot be separated from the circle
either. Both fall back to the sampled verdict, and say so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapsim.analysis.family_loops import family_matrices, full_members
from hapsim.analysis.hand import HAND_FIELDS, hand_matrices, nominal_member, rigid_matrices
from hapsim.analysis.loop import STABILITY_TOL
from hapsim.analysis.scene_check import RIGID_TOL

__all__ = ["Certificate", "certify_family", "MAX_BOXES", "ARITHMETIC"]

#: What a certificate proves (module notes): its bounds in floating point, the computed
#: decomposition's residual carried, the rounding of the computations not bounded.
ARITHMETIC = "floating point: rounding not bounded"

#: Default most boxes of the subdivision before :func:`certify_family` gives up.
MAX_BOXES = 20000


@dataclass(frozen=True)
class Certificate:
    """Outcome of a certified subdivision of a hand family.

    Attributes
    ----------
    certified : bool
        The verdict holds for every member of the continuous ranges (proven stable, or an
        unstable member found).
    robust : bool or None
        Every member stable (None when not certified).
    boxes : int
        Boxes examined.
    method : str
        ``"certified"`` or why not (``"ideal hold"``, ``"free body (pole at z = 1)"``,
        ``"gave up after N boxes"``).
    counterexample : ndarray, shape (5,) or None
        An unstable member ``(mh, bh, kg, bg, kh)`` when one was found.
    counterexample_rho : float or None
        Its spectral radius.
    margin : float or None
        Smallest ``1 - (rho + kappa ||E||)`` over the proven boxes [-].
    arithmetic : str
        What the certificate proves: :data:`ARITHMETIC` (its bounds evaluated in floating
        point, their rounding not bounded; module notes).
    """

    certified: bool
    robust: bool | None
    boxes: int
    method: str
    counterexample: np.ndarray | None = None
    counterexample_rho: float | None = None
    margin: float | None = None
    arithmetic: str = ARITHMETIC

    def to_dict(self) -> dict:
        """JSON-ready dict (the counterexample as ``{field: value}``).

        Returns
        -------
        dict
            ``certified``, ``robust``, ``boxes``, ``method``, ``margin``, ``arithmetic``
            and ``counterexample``: None, or each
            :data:`~hapsim.analysis.hand.HAND_FIELDS` value and its ``spectral_radius``.
        """
        ce = None
        if self.counterexample is not None:
            ce = {f: float(v) for f, v in zip(HAND_FIELDS, self.counterexample)}
            ce["spectral_radius"] = self.counterexample_rho
        return {"certified": self.certified, "robust": self.robust, "boxes": self.boxes,
                "method": self.method, "counterexample": ce, "margin": self.margin,
                "arithmetic": self.arithmetic}


def _spans(hand) -> np.ndarray:
    out = []
    for f in HAND_FIELDS:
        v = getattr(hand, f, 0.0)
        lo, hi = (float(v[0]), float(v[1])) if isinstance(v, tuple) else (float(v), float(v))
        out.append((lo, hi))
    return np.array(out)


def _to_members(v: np.ndarray, mc: float, rigid: bool) -> np.ndarray:
    """Box variables ``(q, bh, kg, bg, kh)`` -> members ``(mh, bh, kg, bg, kh)``."""
    mem = v.copy()
    mem[..., 0] = 1.0 / v[..., 0] - (mc if rigid else 0.0)
    return mem


def _plant(mem: np.ndarray, mc: float, bc: float, rigid: bool):
    """Continuous ``(Ac, b)`` stacks of the members, state ``[x, v, ...]``."""
    if rigid:
        A, b = rigid_matrices(mc + mem[..., 0], bc + mem[..., 1], mem[..., 4])
        return A, b
    A, b = hand_matrices(mc, bc, mem)
    return A, np.broadcast_to(b, A.shape[:-1])


def _scales(names, T: float, m: float) -> np.ndarray:
    """Per-state factor to metres: velocities times ``T``, forces times ``T^2/m``."""
    out = []
    for n in names:
        if ".v[" in n:
            out.append(T)
        elif n.startswith("F[") or "force" in n.lower():
            out.append(T * T / m)
        else:
            out.append(1.0)
    return np.array(out)


@dataclass(frozen=True)
class _Boxes:
    """What every box of one subdivision shares, for :func:`_box_bound` and
    :func:`_mode_bound`.

    Attributes
    ----------
    ranged : list of int
        Indices of the variables ``(q, bh, kg, bg, kh)`` that span a range.
    corners : ndarray, shape (2**r, r)
        0/1 pattern of each vertex over the ranged variables.
    mc, bc : float
        Handle mass [kg] and friction [N s/m].
    rigid : bool
        Rigid grip (the variable ``q`` is ``1/(mc + mh)``).
    Sp : ndarray, shape (p,)
        Scaling of the plant states to metres (:func:`_scales`).
    T : float
        Sample period [s].
    """

    ranged: list
    corners: np.ndarray
    mc: float
    bc: float
    rigid: bool
    Sp: np.ndarray
    T: float

    def vertex_plants(self, lo_b, hi_b, cen):
        """Continuous plants ``(Ac, b)`` at every vertex of every box, shapes
        ``(n, 2**r, p, p)`` and ``(n, 2**r, p)``."""
        r = len(self.ranged)
        vert = np.repeat(cen[:, None, :], 2 ** r, axis=1)
        for k, j in enumerate(self.ranged):
            vert[:, :, j] = np.where(self.corners[None, :, k] > 0, hi_b[:, None, j],
                                     lo_b[:, None, j])
        return _plant(_to_members(vert, self.mc, self.rigid), self.mc, self.bc, self.rigid)


def certify_family(scene, calibrated, *, max_boxes: int = MAX_BOXES, batch: int = 256,
                   progress=None) -> Certificate:
    """Prove (or refute) the stability of every member of a scene's hand ranges.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        With a port, a device and ``device.hand`` (without one the family is one member).
    calibrated : mapping
        ``{link: (K, B)}`` of the target links (as :func:`hapsim.analysis.family.family`).
    max_boxes : int, optional
        Most boxes examined before giving up (then ``certified`` is False).
    batch : int, optional
        Boxes examined per batched eigenvalue call (best first: the boxes whose parent's
        spectral radius was largest).
    progress : callable, optional
        ``progress(done, total)`` after each level of the subdivision.

    Returns
    -------
    Certificate

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.family.family_matrices`.

    Notes
    -----
    Module docstring: Bauer & Fike (1960), the logarithmic norm bound of Dahlquist (1959)
    and the vertex property of separately convex functions on a box.
    """
    dev = scene.device
    hand = getattr(dev, "hand", None)
    T = scene.period
    mc, bc = float(dev.mass), float(dev.friction)
    if hand is None:
        mem = np.array([[0.0, 0.0, math.inf, 0.0, 0.0]])
        A, _ = family_matrices(scene, mem, calibrated=calibrated)
        rho = float(np.max(np.abs(np.linalg.eigvals(A[0]))))
        ok = rho <= 1.0 + STABILITY_TOL
        return Certificate(True, ok, 1, "certified", None if ok else mem[0],
                           None if ok else rho, 1.0 - rho if ok else None)
    if dev.hold != "zoh":
        return Certificate(False, None, 0, "ideal hold (only the zero-order hold is "
                                           "certified)")
    if float(dev.delay) % 1.0:
        # the bounds below perturb the plant through one Bd u^T; the split hold has two
        # (Gamma0, Gamma1: hapsim.analysis.subsample): not certified, said so
        return Certificate(False, None, 0, f"sub-sample delay {float(dev.delay):g} "
                                           "(only whole delays are certified; the sampled "
                                           "family's poles are exact)")
    spans = _spans(hand)
    rigid = not math.isfinite(spans[2, 1])
    lo_v, hi_v = spans[:, 0].copy(), spans[:, 1].copy()
    off = mc if rigid else 0.0
    lo_v[0], hi_v[0] = 1.0 / (spans[0, 1] + off), 1.0 / (spans[0, 0] + off)
    ranged = [j for j in range(5) if hi_v[j] > lo_v[j] and not (j == 2 and rigid)]
    r = len(ranged)
    corners = np.array([[(i >> k) & 1 for k in range(r)] for i in range(2 ** r)], float)
    nplant = 2 if rigid else 4
    # state scaling from the nominal member's layout
    _, names = family_matrices(scene, nominal_member(hand)[None, :], calibrated=calibrated)
    S = _scales(names, T, mc)
    Sp = S[:nplant]
    ctx = _Boxes(ranged, corners, mc, bc, rigid, Sp, T)
    uvec = _force_row(scene, calibrated, nplant)
    unorm = float(np.linalg.norm(uvec / S))
    # best first: the pending box whose parent came closest to the circle is examined first
    # (an unstable band is found in a few levels), in batches for the batched eig calls
    p_lo, p_hi, p_pr = lo_v[None, :], hi_v[None, :], np.array([np.inf])
    done, margin = 0, math.inf
    while p_lo.shape[0]:
        take = np.argsort(-p_pr, kind="stable")[:batch]
        keep = np.setdiff1d(np.arange(p_lo.shape[0]), take)
        boxes_lo, boxes_hi = p_lo[take], p_hi[take]
        p_lo, p_hi, p_pr = p_lo[keep], p_hi[keep], p_pr[keep]
        n = boxes_lo.shape[0]
        if done + n > max_boxes:
            return Certificate(False, None, done, f"gave up after {done} boxes")
        done += n
        cen = 0.5 * (boxes_lo + boxes_hi)
        A, _ = family_matrices(scene, full_members(_to_members(cen, mc, rigid)),
                               calibrated=calibrated)
        As = A * S[None, :, None] / S[None, None, :]   # D A D^-1
        w, V = np.linalg.eig(As)
        rho = np.abs(w).max(axis=1)
        if np.any(np.abs(w - 1.0) <= RIGID_TOL):
            return Certificate(False, None, done, "free body (pole at z = 1)")
        bad = np.flatnonzero(rho > 1.0 + STABILITY_TOL)
        if bad.size:
            i = bad[np.argmax(rho[bad])]
            return Certificate(True, False, done, "certified",
                               _to_members(cen[i], mc, rigid), float(rho[i]))
        kappa = np.linalg.cond(V)
        # the computed decomposition is not exact: A(c) V = V Lambda + Res, so A(c) is
        # V Lambda V^-1 + Res V^-1, a perturbation both bounds carry
        res = np.linalg.norm(As @ V - V * w[:, None, :], ord=2, axis=(-2, -1))
        with np.errstate(over="ignore", invalid="ignore"):
            Ac, bv = ctx.vertex_plants(boxes_lo, boxes_hi, cen)
            contrib = _box_bound(ctx, Ac, bv, unorm=unorm)
            winv = np.linalg.norm(np.linalg.inv(V), ord=2, axis=(-2, -1))
            bound = rho + kappa * (contrib.sum(axis=1) + res * winv) * (1.0 + 1e-6) + 1e-12
            gbound, gcontrib = _mode_bound(ctx, Ac, bv, w=w, V=V, us=uvec / S, As=As)
            gbound = gbound * (1.0 + 1e-6) + 1e-12
        bound = np.where(np.isnan(bound), np.inf, bound)
        gbound = np.where(np.isnan(gbound), np.inf, gbound)
        use_g = gbound < bound
        contrib = np.where(use_g[:, None], gcontrib, contrib)
        bound = np.minimum(bound, gbound)
        ok = bound < 1.0
        if ok.any():
            margin = min(margin, float((1.0 - bound[ok]).min()))
        nxt = np.flatnonzero(~ok)
        if progress is not None:
            progress(done, done + p_lo.shape[0] + 2 * nxt.size)
        if not nxt.size:
            continue
        if r == 0:
            return Certificate(False, None, done, "the bound does not prove the member")
        split = np.array(ranged)[np.argmax(contrib[nxt], axis=1)]
        lo, hi = boxes_lo[nxt], boxes_hi[nxt]
        ar = np.arange(nxt.size)
        a, c = lo[ar, split], hi[ar, split]
        geo = np.isin(split, (2, 4)) & (a > 0)     # stiffnesses span decades
        mid = np.where(geo, np.sqrt(np.abs(a * c)), 0.5 * (a + c))
        lo2, hi1 = lo.copy(), hi.copy()
        hi1[ar, split] = mid
        lo2[ar, split] = mid
        p_lo = np.concatenate([p_lo, lo, lo2])
        p_hi = np.concatenate([p_hi, hi1, hi])
        p_pr = np.concatenate([p_pr, rho[nxt], rho[nxt]])
    return Certificate(True, True, done, "certified", margin=margin)


def _box_bound(ctx: _Boxes, Ac, b, *, unorm: float):
    """Per box and ranged variable, the bound on ``||E||`` it contributes (module notes).

    The exponentials are bounded in energy-like coordinates ``G`` (velocities over the
    box's largest natural frequency ``w``, so a stiff grip is a rotation, not an
    ``e^(w T)`` growth) and carried to the closed loop's ``D`` (velocities times ``T``) by
    ``||D G^-1||`` and ``||G D^-1||``.

    Parameters
    ----------
    ctx : _Boxes
    Ac, b : ndarray, shapes (n, 2**r, p, p) and (n, 2**r, p)
        The plant at each vertex of each box (:meth:`_Boxes.vertex_plants`).
    unorm : float
        ``||u / S||``, the scaled held-force row's norm.

    Returns
    -------
    ndarray, shape (n, max(r, 1))
    """
    n = Ac.shape[0]
    Sp, T = ctx.Sp, ctx.T
    npl = Sp.size
    vel = np.arange(npl) % 2 == 1
    w2 = np.abs(Ac[..., vel, :][..., :, ~vel]).max(axis=(-2, -1)).max(axis=1)
    omega = np.sqrt(np.maximum(w2, 1e-6 / (T * T)))          # [1/s], per box
    energy = _contrib(ctx, Ac, b, np.where(vel[None, :], 1.0 / omega[:, None], 1.0), unorm)
    sampled = _contrib(ctx, Ac, b, np.broadcast_to(Sp, (n, npl)), unorm)
    return np.minimum(energy, sampled)      # each term bounded either way: the least


def _contrib(ctx: _Boxes, Ac, b, G, unorm: float):
    """The per-variable bounds of :func:`_box_bound` with the exponentials bounded in the
    coordinates ``G`` (shape (n, p): per box, the factor of each plant state)."""
    n, r = Ac.shape[0], len(ctx.ranged)
    Sp, T, corners = ctx.Sp, ctx.T, ctx.corners
    Acg = Ac * G[:, None, :, None] / G[:, None, None, :]      # G Ac G^-1
    bg = b * G[:, None, :]
    DG = np.abs(Sp[None, :] / G).max(axis=1)                  # ||D G^-1||
    GD = np.abs(G / Sp[None, :]).max(axis=1)                  # ||G D^-1||
    mu = np.linalg.eigvalsh(0.5 * (Acg + np.swapaxes(Acg, -1, -2)))[..., -1].max(axis=1)
    grow = np.exp(np.minimum(np.maximum(mu, 0.0) * T, 700.0))
    bmax = np.linalg.norm(bg, axis=-1).max(axis=1)
    dA = np.zeros((n, max(r, 1)))
    db = np.zeros((n, max(r, 1)))
    for k in range(r):
        up = corners[:, k] > 0
        dA[:, k] = 0.5 * np.linalg.norm(Acg[:, up] - Acg[:, ~up], ord=2,
                                        axis=(-2, -1)).max(axis=1)
        db[:, k] = 0.5 * np.linalg.norm(bg[:, up] - bg[:, ~up], axis=-1).max(axis=1)
    E_Ad = (DG * GD * T * grow)[:, None] * dA
    E_Bd = (DG * grow)[:, None] * (0.5 * T * T * dA * bmax[:, None] + T * db)
    return E_Ad + E_Bd * unorm


def _force_row(scene, calibrated, nplant: int) -> np.ndarray:
    """The row ``u`` mapping the closed-loop state to the held force (unscaled).

    ``u`` is the same for every member (:func:`hapsim.analysis.family.family_matrices` adds
    ``Bd u^T`` to the plant rows of one frame): recovered from the nominal member's plant
    row with the largest ``Bd``.
    """
    from hapsim.analysis.hand import body_zoh
    m0 = nominal_member(scene.device.hand)[None, :]
    A0, _ = family_matrices(scene, m0, calibrated=calibrated)
    Aw, Bd = body_zoh(float(scene.device.mass), float(scene.device.friction), m0,
                      scene.period)
    k = int(np.argmax(np.abs(Bd[0])))
    row = A0[0, k, :].copy()
    row[:nplant] -= Aw[0, k] + (np.arange(nplant) == k)
    return row / Bd[0, k]


def _mode_bound(ctx: _Boxes, Ac, b, *, w, V, us, As):
    """Column-Gershgorin bound on the poles of every member of each box, per mode.

    With ``A(c) = V Lambda V^-1`` (columns of ``V`` of unit norm, ``W = V^-1``) the poles of
    ``A(p) = A(c) + P F`` lie in the union over ``j`` of the disks centred at ``lambda_j``
    of radius ``sum_i |(W P F v_j)_i| <= (sum_i ||(W P)_i||) ||F v_j||`` (Gershgorin's
    theorem on the columns of ``Lambda + W P F V``). ``F v_j`` is small for a mode the
    change hardly strains (the hand and handle moving together): with
    ``dAd/dp_k v = int_0^T e^(Ac (T-s)) Ac_k e^(Ac s) v ds`` and
    ``||(e^(Ac s) - I) v|| <= s e^(mu+ s) ||Ac v||``,

        h_k ||dAd/dp_k v|| <= e^(mu+ T) (T ||h_k Ac_k v|| + T^2/2 ||h_k Ac_k|| e^(mu+ T) ||Ac v||)

    and the held force's share ``|u^T v_j|`` times the bound on ``dBd`` of
    :func:`_box_bound`; every supremum over the box is a maximum over its vertices (the
    quantities are affine in each variable, their norms convex). The computed decomposition's
    residual ``W (A(c) V - V Lambda)`` is added to each column's sum.

    Parameters
    ----------
    ctx : _Boxes
    Ac, b : ndarray, shapes (n, 2**r, p, p) and (n, 2**r, p)
        The plant at each vertex of each box (:meth:`_Boxes.vertex_plants`).
    w, V : ndarray, shapes (n, s) and (n, s, s)
        Eigenvalues and eigenvectors of each box centre's scaled closed loop ``As``.
    us : ndarray, shape (s,)
        The scaled held-force row ``u / S``.
    As : ndarray, shape (n, s, s)
        Each centre's scaled closed-loop matrix ``D A D^-1``.

    Returns
    -------
    bound : ndarray, shape (n,)
        ``max_j |lambda_j| + radius_j``.
    contrib : ndarray, shape (n, max(r, 1))
        Per ranged variable, its share of the radius of the worst mode.
    """
    n, r = Ac.shape[0], len(ctx.ranged)
    Sp, T, corners = ctx.Sp, ctx.T, ctx.corners
    npl = Sp.size
    Acs = Ac * Sp[:, None] / Sp                              # (n, nv, p, p)
    bs = b * Sp
    mu = np.linalg.eigvalsh(0.5 * (Acs + np.swapaxes(Acs, -1, -2)))[..., -1].max(axis=1)
    grow = np.exp(np.minimum(np.maximum(mu, 0.0) * T, 700.0))   # (n,)
    bmax = np.linalg.norm(bs, axis=-1).max(axis=1)
    Vn = V / np.linalg.norm(V, axis=1, keepdims=True)
    Wn = np.linalg.inv(Vn)
    SW = np.linalg.norm(Wn[:, :, :npl], axis=2).sum(axis=1)     # (n,)
    vp = Vn[:, :npl, :]                                          # (n, p, s)
    cu = np.abs(np.einsum("s,nsj->nj", us, Vn))                  # |u^T v_j|, (n, s)
    AcV = np.linalg.norm(np.einsum("nvab,nbj->nvaj", Acs, vp), axis=2).max(axis=1)  # (n, s)
    terms = np.zeros((n, max(r, 1), Vn.shape[2]))
    for k in range(r):
        up = corners[:, k] > 0
        Dk = 0.5 * (Acs[:, up] - Acs[:, ~up])                    # h_k Ac_k on each edge
        dkv = np.linalg.norm(np.einsum("neab,nbj->neaj", Dk, vp), axis=2).max(axis=1)
        dkn = np.linalg.norm(Dk, ord=2, axis=(-2, -1)).max(axis=1)
        dbk = 0.5 * np.linalg.norm(bs[:, up] - bs[:, ~up], axis=-1).max(axis=1)
        fad = grow[:, None] * (T * dkv + 0.5 * T * T * (dkn * grow)[:, None] * AcV)
        fbd = (grow * (0.5 * T * T * dkn * bmax + T * dbk))[:, None] * cu
        terms[:, k, :] = SW[:, None] * (fad + fbd)
    # the decomposition's residual: W (A(c) V - V Lambda) joins every column's sum
    resid = np.abs(Wn @ (As @ Vn - Vn * w[:, None, :])).sum(axis=1)  # (n, s)
    radius = terms.sum(axis=1) + resid                           # (n, s)
    per = np.abs(w) + radius
    jw = np.argmax(per, axis=1)
    return per.max(axis=1), terms[np.arange(n), :, jw]
