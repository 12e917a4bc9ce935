"""Accuracy of the n-D engine in single precision (``engine: {precision: single}``)
against double precision and against closed forms, over long renders.

Usage::

    python tools/precision_nd.py [--seconds S] [--json FILE]

Three scenes, each rendered in both precisions (:class:`hapsim.engine.Engine`) for
``S`` seconds at 44.1 kHz (default 2):

``membrane``
    The shipped sounding membrane (``configs/membrane.yaml``: 12 x 12 masses, length-0
    springs, struck across its plane). Its motion across the plane is linear and has a
    closed form written here: the discrete membrane's modes (sine series of the grid's
    Dirichlet Laplacian), each a scalar recursion of the centred scheme. Reported: the
    listened mass's position against the closed form (largest difference over the
    render, relative to the largest position, and over its last 0.1 s relative to that
    window's), the five strongest spectral peaks [Hz] of its velocity, and the drift of
    the in-plane coordinates (they should not move) [m].
``euclid_membrane``
    The same membrane with Euclidean links of rest length h / 2 (pretensioned: its
    transverse stiffness is the links' tension), so the state's in-plane coordinates are
    absolute positions up to 0.13 m that the length of every link is computed from.
    Single against double: the listened position's largest difference relative to its
    largest value, the spectral peaks, the in-plane drift, and the mechanical energy
    (kinetic ``m v^2 / 2`` with ``v`` the backward difference, plus ``K (|d| - L)^2 / 2``
    per link; computed in float64 from each engine's state) at the end relative to the
    start.
``grid``
    The benchmark's 3-D grid mesh (``tools/bench_nd.py``: 22 x 22 x 11 masses, Euclidean
    links, the face z = 0 held, every mass displaced at random): a cubic lattice without
    diagonals, a mechanism whose motion is not a smooth function of round-off, so the
    two precisions' trajectories part (reported, not a measure of error); its energy
    (as above) and the mean displacement of its masses, both precisions.

Exit code 0, or 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

import make_nd_scenes as gen  # noqa: E402

from hapsim.engine import Engine  # noqa: E402
from hapsim.scene import parse_scene_nd  # noqa: E402

RATE = 44100
T = 1.0 / RATE


def modal_membrane(n_samples: int) -> np.ndarray:
    """The listened mass's position across the plane [m], samples 1..n, of the shipped
    membrane, from its modes (closed form; module docstring of tests/test_membrane.py):
    mode ``(p, q)`` of the grid's Dirichlet Laplacian (eigenvalue ``mu_pq``, shape
    ``sqrt(2 / (N + 1)) sin(p i pi / (N + 1))`` per axis) follows
    ``y+ = (2 - a - c) y - (1 - c) y-`` with ``a = mu K T^2 / m``, ``c = mu B T / m``."""
    N = gen.MEMBRANE_N
    p = np.arange(1, N + 1)
    S = np.sqrt(2.0 / (N + 1)) * np.sin(np.outer(p, p) * np.pi / (N + 1))
    s2 = np.sin(p * np.pi / (2 * (N + 1))) ** 2
    mu = 4 * (s2[:, None] + s2[None, :])
    a = mu * gen.MEMBRANE_K * T * T / gen.MEMBRANE_M
    c = mu * gen.MEMBRANE_B * T / gen.MEMBRANE_M
    si, sj = gen.MEMBRANE_STRIKE
    li, lj = gen.MEMBRANE_LISTEN
    y = np.zeros((N, N))
    ym = np.outer(S[:, si - 1], S[:, sj - 1]) * (-T * 0.5)     # x_prev = x0 - T v0
    w = np.outer(S[:, li - 1], S[:, lj - 1])
    out = np.empty(n_samples)
    for k in range(n_samples):
        y, ym = (2 - a - c) * y - (1 - c) * ym, y
        out[k] = (w * y).sum()
    return out


def peaks(v: np.ndarray, count: int = 5) -> list[float]:
    """The ``count`` strongest spectral peaks of ``v`` [Hz] (Hann window, parabolic
    interpolation of the log magnitude), strongest first."""
    spec = np.abs(np.fft.rfft((v - v.mean()) * np.hanning(v.size)))
    ks = [k for k in range(2, spec.size - 1) if spec[k] > spec[k - 1] and spec[k] >= spec[k + 1]]
    out = []
    for k in sorted(ks, key=lambda k: -spec[k])[:count]:
        y0, y1, y2 = np.log(spec[k - 1:k + 2])
        out.append(float((k + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)) * RATE / v.size))
    return out


def energy(X, XP, m, i1, i2, K, L) -> float:
    """Mechanical energy [J] of a state (float64 whatever the engine's precision):
    kinetic from the backward difference, potential of the Euclidean links."""
    X = np.asarray(X, float)
    XP = np.asarray(XP, float)
    v = (X - XP) / T
    d = X[:, i1] - X[:, i2]
    ln = np.sqrt((d * d).sum(axis=0))
    return float(0.5 * (m * (v * v).sum(axis=0)).sum() + 0.5 * (K * (ln - L) ** 2).sum())


def render(eng: Engine, n: int, listen: int, every: int, i1, i2, K, L):
    """Positions of mass ``listen`` across the last axis per sample, and the energy
    every ``every`` samples."""
    m = np.array([mm.mass if mm.kind == "mass" else 0.0 for mm in eng.scene.masses])
    z = np.empty(n)
    e = [energy(eng.x, eng.xp, m, i1, i2, K, L)]
    for k in range(n):
        eng.step()
        z[k] = eng.x[-1, listen]
        if (k + 1) % every == 0:
            e.append(energy(eng.x, eng.xp, m, i1, i2, K, L))
    return z, np.array(e)


def links_of(scene):
    names = [m.name for m in scene.masses]
    i1 = np.array([names.index(lk.m1) for lk in scene.links])
    i2 = np.array([names.index(lk.m2) for lk in scene.links])
    K = np.array([lk.stiffness for lk in scene.links])
    L = np.array([lk.length for lk in scene.links])
    return i1, i2, K, L


def membranes(seconds: float) -> dict:
    n = int(round(seconds * RATE))
    out = {}
    text = gen.membrane()
    for name, scene_text in (("membrane", text),
                             ("euclid_membrane", text.replace(
                                 f"damping: {gen.MEMBRANE_B:g}}}",
                                 f"damping: {gen.MEMBRANE_B:g}, length: "
                                 f"{gen.MEMBRANE_H / 2:g}}}"))):
        scene = parse_scene_nd(scene_text, name)
        li, lj = gen.MEMBRANE_LISTEN
        listen = [m.name for m in scene.masses].index(f"m{li}_{lj}")
        i1, i2, K, L = links_of(scene)
        x0 = np.array([m.x0 for m in scene.masses]).T
        res = {}
        for prec in ("double", "single"):
            eng = Engine(scene, precision=prec)
            t0 = time.perf_counter()
            z, e = render(eng, n, listen, 441, i1, i2, K, L)
            res[prec] = {"z": z, "energy": e,
                         "drift_m": float(np.max(np.abs(np.asarray(eng.x[:2], float)
                                                        - x0[:2]))),
                         "seconds": time.perf_counter() - t0}
        row = {"samples": n}
        tail = slice(n - RATE // 10, n)
        if name == "membrane":
            ref = modal_membrane(n)
            for prec in ("double", "single"):
                z = res[prec]["z"]
                row[f"{prec}_vs_closed_form"] = float(np.max(np.abs(z - ref)) / np.max(np.abs(ref)))
                row[f"{prec}_vs_closed_form_tail"] = float(
                    np.max(np.abs(z[tail] - ref[tail])) / np.max(np.abs(ref[tail])))
            row["closed_form_peaks_hz"] = peaks(np.diff(ref))
        zd, zs = res["double"]["z"], res["single"]["z"]
        row["single_vs_double"] = float(np.max(np.abs(zs - zd)) / np.max(np.abs(zd)))
        row["single_vs_double_tail"] = float(
            np.max(np.abs(zs[tail] - zd[tail])) / np.max(np.abs(zd[tail])))
        for prec in ("double", "single"):
            e = res[prec]["energy"]
            row[f"{prec}_peaks_hz"] = peaks(np.diff(res[prec]["z"]))
            row[f"{prec}_drift_m"] = res[prec]["drift_m"]
            row[f"{prec}_energy_end_over_start"] = float(e[-1] / e[0])
        row["single_energy_vs_double_max"] = float(
            np.max(np.abs(res["single"]["energy"] - res["double"]["energy"])
                   / res["double"]["energy"]))
        out[name] = row
    return out


def grid(seconds: float) -> dict:
    """The benchmark mesh in both precisions: energy and mean displacement."""
    import bench_nd
    n = int(round(seconds * RATE))
    nx, ny, nz = 22, 22, 11
    X0, i1, i2, t2m = bench_nd.mesh(nx, ny, nz)
    m = np.where(t2m > 0, 0.001, 0.0)
    K, L = 100.0, bench_nd.SPACING
    out = {"masses": int(X0.shape[0]), "links": int(i1.size), "samples": n}
    res = {}
    for prec, dt in (("double", np.float64), ("single", np.float32)):
        c = bench_nd.Case(nx, ny, nz, dt)
        x, xp = c.hap[2], c.hap[3]

        def prev():          # single precision's state holds x[n] - x[n-1] (velocity form)
            return xp if dt is np.float64 else np.asarray(x, float) - xp
        e = [energy(x, prev(), m, i1, i2, K, L)]
        for _ in range(n // 441):
            c.run_hap(441)
            e.append(energy(x, prev(), m, i1, i2, K, L))
        res[prec] = (np.array(e), np.asarray(x, float).copy())
        free = t2m > 0
        out[f"{prec}_energy_end_over_start"] = float(e[-1] / e[0])
        out[f"{prec}_mean_displacement_m"] = float(
            np.mean(np.linalg.norm(np.asarray(x, float)[:, free] - X0.T[:, free], axis=0)))
    out["single_energy_vs_double_max"] = float(
        np.max(np.abs(res["single"][0] - res["double"][0]) / res["double"][0]))
    out["single_vs_double_max_m"] = float(np.max(np.abs(res["single"][1] - res["double"][1])))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=2.0, help="render length [s] (> 0.2)")
    p.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = p.parse_args(argv)
    if not args.seconds > 0.2:
        p.error("--seconds must be > 0.2")
    out = {"seconds": args.seconds, "rate_hz": RATE}
    out.update(membranes(args.seconds))
    out["grid"] = grid(args.seconds)
    print(json.dumps(out, indent=1))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
