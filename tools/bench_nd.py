"""Benchmark of the n-D engine kernels (hapsim.kernels.nd) against a straightforward
reference written here, same run.

Usage::

    python tools/bench_nd.py [--quick] [--json FILE]

The mesh: a 3-D grid of ``nx x ny x nz`` masses (1 g, spacing 1 cm), each joined to its
+x, +y and +z neighbours by a Euclidean spring-damper (K = 100 N/m, B = 0.001 N s/m, rest
length the spacing: miPhysics' SpringDamper3D), about 3 links per mass; the face z = 0 is
ground; every mass starts displaced at random by up to 1 mm (seeded).

It prints, for growing meshes:

* ns per mass-sample and per link-sample of hapsim's kernel (``run_nd``: the grid's +x,
  +y, +z links as three dense families whose forces each mass pulls as it advances, any
  other link in stripes cut into pieces per block of masses, structure of arrays, each
  block advanced while in cache), with the families and pieces it ran
  and of the reference (a numba loop over the links one at a time, positions as (N, 3)
  rows, forces scattered to both ends: the straightforward layout), and their ratio,
  both measured in this run as thread CPU time (``time.thread_time``: descheduling on a
  shared machine is not counted), the fastest of repeated short runs (the one least
  disturbed by other processes' use of the caches);
* the same for hapsim's kernel with every link in pieces (``pieces ns/mass``:
  ``Engine(scene, families=False)``, the layout before dense families), measured
  interleaved with the others;
* the same for hapsim's kernel in single precision (the same kernels compiled for float32,
  as ``engine: {precision: single}`` runs them) and its difference from the reference
  after 200 samples;
* the floor the arithmetic sets: ns per element of a loop doing nothing but one square
  root and one division (the Euclidean law's), measured the same way;
* the agreement of the two after the benchmark's samples (largest position difference,
  relative to the spacing: round-off, the forces are summed in another order);
* the cost of one step call from Python (75 masses, one sample): us per call and the
  transient bytes (tracemalloc), through the one-argument context (as
  :meth:`hapsim.engine.Engine.step`) and with the 38 arrays passed one by one;
* where the time goes (not with ``--quick``): the 5,324-mass mesh with the kernel whole
  and with one part taken out of its source (:data:`ABLATIONS`: the link forces, the
  forces pulled by each mass, the square root and division), measured alternately;
* the largest mesh each runs within the 44.1 kHz deadline (22.68 us per sample) and
  within 1 ms (1 kHz), by bisection on the mesh size measured at each step (the
  cube-ish meshes, then the rows of the next one: near 5,000 masses they step 264, not
  957, and 5,016 is tried), for hapsim in double and in single precision
  (``hapsim_single``) and the reference; at 44.1 kHz also hapsim stepped one compiled
  call per sample from Python (``hapsim_per_call``, ``hapsim_single_per_call``: a
  real-time loop's way; the others run blocks of samples per call, an audio buffer's).

With ``--faust`` it also runs a 1-D projection against Faust ``mi.lib``: a string of
``FAUST_BEADS`` beads (the string of ``tools/bench_engine.py``, without its port) as a 1-D
scene on :class:`hapsim.engine.Engine`, and its Faust twin (``tests/faust_gen.py``,
``faust -double``, ``g++ -O3``): the largest difference of the trajectories over 2,000
samples relative to the amplitude, and ns per mass-sample of both (Faust's driver times
blocks of 64 samples; thread CPU time for both), with their ratio.

The load average at the start and the end is printed (and written): figures measured
beside other CPU-bound work are not a quiet machine's. Reproduce the shipped figures with
``python tools/bench_nd.py --faust --json docs/bench_nd.json`` (about 5 minutes on a
quiet machine, Faust's build included; three times that beside a load of 20).

Exit code 0, or 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numba as nb
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "tools"))

import hapsim.kernels.nd as nd_kernels  # noqa: E402
from hapsim.kernels.layout import family_offsets, placed  # noqa: E402
from hapsim.kernels.nd import (BLOCK, context, euclid_layout,  # noqa: E402
                               link_lengths, run_context, run_context32, run_nd,
                               shared_params)

#: Beads of the string compared with Faust (Faust's build time grows with the string).
FAUST_BEADS = 300

T = 1.0 / 44100.0
SPACING = 0.01


@nb.njit(cache=True, nogil=True)
def reference_run(n, X, XP, F, t2m, i1, i2, k, z, rest):
    """The straightforward loop: one link at a time, (N, 3) rows, scattered forces,
    the previous length recomputed from the previous positions."""
    N = X.shape[0]
    for _ in range(n):
        for i in range(N):
            F[i, 0] = 0.0
            F[i, 1] = 0.0
            F[i, 2] = 0.0
        for j in range(i1.size):
            a = i1[j]
            b = i2[j]
            dx = X[a, 0] - X[b, 0]
            dy = X[a, 1] - X[b, 1]
            dz = X[a, 2] - X[b, 2]
            ln = np.sqrt(dx * dx + dy * dy + dz * dz)
            px = XP[a, 0] - XP[b, 0]
            py = XP[a, 1] - XP[b, 1]
            pz = XP[a, 2] - XP[b, 2]
            lp = np.sqrt(px * px + py * py + pz * pz)
            g = k[j] * (ln - rest[j]) + z[j] * (ln - lp)
            if ln > 0.0:
                g = g / ln
            else:
                g = 0.0
            F[a, 0] -= g * dx
            F[a, 1] -= g * dy
            F[a, 2] -= g * dz
            F[b, 0] += g * dx
            F[b, 1] += g * dy
            F[b, 2] += g * dz
        for i in range(N):
            for d in range(3):
                xn = 2.0 * X[i, d] - XP[i, d] + t2m[i] * F[i, d]
                XP[i, d] = X[i, d]
                X[i, d] = xn


def mesh(nx, ny, nz, seed=0):
    """Grid masses (N, 3), links (i1, i2) to +x, +y, +z neighbours, t2m (ground z = 0)."""
    idx = np.arange(nx * ny * nz).reshape(nz, ny, nx)
    zz, yy, xx = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    X0 = np.stack([xx, yy, zz], -1).reshape(-1, 3) * SPACING
    rng = np.random.default_rng(seed)
    X0 = X0 + rng.uniform(-1e-3, 1e-3, X0.shape) * (zz.reshape(-1, 1) > 0)
    i1 = np.concatenate([idx[:, :, :-1].ravel(), idx[:, :-1, :].ravel(), idx[:-1].ravel()])
    i2 = np.concatenate([idx[:, :, 1:].ravel(), idx[:, 1:, :].ravel(), idx[1:].ravel()])
    t2m = np.where(zz.ravel() > 0, T * T / 0.001, 0.0)
    return X0, i1, i2, t2m


#: The arguments of ``run_nd`` after ``n`` that Engine places in their pages
#: (:func:`hapsim.kernels.layout.family_offsets`), by index in ``Case.hap``.
PLACED_ARGS = {2: "x", 3: "xp", 5: "t2m", 12: "k", 13: "z", 14: "rest", 15: "lprev",
               35: "G"}


class Case:
    """Both engines' arrays for one mesh; hapsim's in ``dtype`` (float64, or float32:
    the single-precision engine, the same kernels compiled for float32)."""

    def __init__(self, nx, ny, nz, dtype=np.float64, dense=True):
        X0, i1, i2, t2m = mesh(nx, ny, nz)
        self.N, self.L = X0.shape[0], i1.size
        K, B = 100.0, 0.001
        k = np.full(self.L, K)
        z = np.full(self.L, B / T)
        rest = np.full(self.L, SPACING)
        # reference: (N, 3)
        self.ref = (np.ascontiguousarray(X0), X0.copy(), np.zeros_like(X0), t2m,
                    i1.astype(np.int64), i2.astype(np.int64), k, z, rest)
        # hapsim: (3, N), dense families and the other links' stripes cut into pieces
        # per block of masses (as Engine)
        pieces, ptr, fam, order = euclid_layout(i1, i2, self.N, BLOCK, dense=dense)
        real = order >= 0

        def slot(v):                      # per-link values in stripe order, 0 for padding
            out = np.zeros(order.size)
            out[real] = v[order[real]]
            return out
        empty_t = np.zeros((0, 4), np.int64)
        empty_p = np.zeros(ptr.size, np.int64)
        e = np.zeros(0)
        lprev = link_lengths(np.ascontiguousarray(X0.T), np.concatenate([pieces, fam]),
                             order.size)
        dn_fam = np.zeros((3 if len(fam) else 0, 4), np.int64)
        dn_fam[:len(fam)] = fam
        dn_G = np.zeros((9, int(fam[:, 1].max()) + self.N) if len(fam) else (0, 0))
        self.hap = (3, BLOCK, np.ascontiguousarray(X0.T), np.ascontiguousarray(X0.T),
                    np.zeros((3, self.N)), t2m, empty_t, empty_p, e, e, pieces, ptr,
                    slot(k), slot(z), slot(rest), lprev,
                    *shared_params(np.concatenate([pieces, fam]), order, slot(k), slot(z),
                                   slot(rest)),
                    np.zeros((3, BLOCK)),
                    np.zeros(0, np.int64), np.zeros(0, np.int64), e, e, e, e,
                    np.zeros(0, np.int64), np.zeros((3, 0)), e, e, e, dn_fam, dn_G, -1,
                    np.zeros(3))
        if dtype is not np.float64:   # single precision's velocity form: xp holds x - xp
            self.hap = self.hap[:3] + (np.zeros((3, self.N)),) + self.hap[4:]
        self.hap = tuple(a.astype(dtype) if isinstance(a, np.ndarray) and
                         a.dtype == np.float64 else a for a in self.hap)
        if len(fam):      # the streamed arrays placed in their pages as Engine does
            h = list(self.hap)
            off = family_offsets(self.N, fam, dn_G.shape[1] - self.N, h[2].itemsize,
                                 bool(h[16][pieces.shape[0]:].all()))
            for i, key in PLACED_ARGS.items():
                h[i] = placed(h[i], off[key])
            self.hap = tuple(h)
        self.families, self.pieces = fam.shape[0], pieces.shape[0]
        self.ctx = context(*self.hap, dtype=dtype)   # ctx[0] = 1: one sample per call
        self._run_ctx = run_context if dtype is np.float64 else run_context32

    def run_ref(self, n):
        reference_run(n, *self.ref)

    def run_hap(self, n):
        run_nd(n, *self.hap)

    def run_hap_calls(self, n):
        """``n`` samples, one compiled call each, as a real-time loop steps
        (:meth:`hapsim.engine.Engine.step`: one argument, the context)."""
        ctx = self.ctx
        run = self._run_ctx
        for _ in range(n):
            run(ctx)


def per_sample(fn, n, repeats):
    """Fewest thread-CPU seconds per sample of ``fn(n)`` over ``repeats`` runs."""
    out = []
    for _ in range(repeats):
        t0 = time.thread_time()
        fn(n)
        out.append((time.thread_time() - t0) / n)
    return min(out)


@nb.njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
def _sqrt_div(n, a, out):
    for _ in range(n):
        for i in range(a.size):
            s = np.sqrt(a[i])
            out[i] = 1.0 / s + s


def sqrt_div_floor(repeats):
    """ns per element of a loop of one square root and one division (vectorised)."""
    a = np.random.default_rng(1).uniform(1e-4, 2e-4, 8192)
    out = np.zeros_like(a)
    _sqrt_div(2, a, out)
    return per_sample(lambda n: _sqrt_div(n, a, out), 200, repeats) / a.size * 1e9


def largest(kind, deadline, quick):
    """Largest cube-ish mesh (masses) whose sample takes <= deadline: bisection on nx
    with ny = nx, nz = nx // 2 + 1, then between the last mesh that met it and the next
    (10 % apart near 5,000 masses: 4,851 and 5,808) on ny of the next one's ``(nx, ny,
    nz)`` (steps of ``nx * nz`` masses, 264 there: 5,016 is tried); returns it with the
    time measured when it was accepted (each size is measured once: a re-measurement on
    a loaded machine could land on either side)."""
    seen = {}

    def cost(nx, ny=None):
        key = (nx, nx if ny is None else ny)
        if key not in seen:
            c = Case(nx, key[1], nx // 2 + 1,
                     np.float32 if "single" in kind else np.float64)
            fn = {"hapsim": c.run_hap, "hapsim_per_call": c.run_hap_calls,
                  "hapsim_single": c.run_hap, "hapsim_single_per_call": c.run_hap_calls,
                  "reference": c.run_ref}[kind]
            n = max(3, int(0.01 / max(deadline, 1e-6)))
            fn(2)
            # the fastest of many short runs: on a shared machine, one run in a few
            # escapes the other processes' use of the core and its caches
            seen[key] = (per_sample(fn, n, 5 if quick else 31), c.N)
        return seen[key]
    lo, hi = 2, 4
    while True:
        t, _ = cost(hi)
        if t > deadline:
            break
        lo, hi = hi, hi * 2
        if hi > 400:
            break
    while hi - lo > 1:
        mid = (lo + hi) // 2
        t, _ = cost(mid)
        if t <= deadline:
            lo = mid
        else:
            hi = mid
    t, N = cost(lo)
    if hi - lo == 1 and cost(hi)[0] > deadline:
        # the meshes (hi, ny, nz) larger than lo's, bisected on ny
        nz = hi // 2 + 1
        a, b = -(-N // (hi * nz)), hi         # the fewest rows above N; hi's all fail
        if hi * a * nz == N:
            a += 1
        while a < b:
            mid = (a + b) // 2
            tm, Nm = cost(hi, mid)
            if tm <= deadline:
                t, N, a = tm, Nm, mid + 1
            else:
                b = mid
    return N, t


#: The families' link forces taken out (both the shared parameters' loop and the per-link
#: one): the rows keep the forces of the samples before.
_NO_LINKS = [("            if e < eu_sh.size and eu_sh[e]:\n", "            if e < 0:\n"), (
    """                _family(x, dn_G, 3 * r, _U(dn_fam[r, 0]), _U(dn_fam[r, 1]),
                        _U(dn_fam[r, 2]), _U(dn_fam[r, 3]), m0, m1, eu_k, eu_z, eu_rest,
                        eu_lprev)""", "                pass")]
#: Where the time goes: the kernel's own source with one part taken out (each
#: replacement must match the kernel's text: the profile fails rather than measure
#: something else after the kernel changes). Name -> [(old, new), ...].
ABLATIONS = {
    "no link forces (stale forces pulled, advance)": _NO_LINKS,
    "no pulled forces (link forces, advance)": [(
        "                F = _pulled(G, d, i, P, o0, o1, o2)\n",
        "                F = G[d, P + i]\n")],
    "advance only": _NO_LINKS + [(
        "                F = _pulled(G, d, i, P, o0, o1, o2)\n",
        "                F = G[d, P + i]\n")],
    "no square root or division (a multiplication each)": [(
        """    ln = np.sqrt(dx * dx + dy * dy + dz * dz)
    lp = lprev[j]
    lprev[j] = ln
    g = (k * (ln - rest) + z * (ln - lp)) / ln
    if not ln > 0.0:""",
        """    ln = (dx * dx + dy * dy + dz * dz) * 50.0
    lp = lprev[j]
    lprev[j] = ln
    g = (k * (ln - rest) + z * (ln - lp)) * ln
    if not ln > 0.0:""")],
}


def _ablated(name, edits, tmp):
    """The kernel module compiled from its source with ``edits`` applied (no cache)."""
    import importlib.util
    src = Path(nd_kernels.__file__).read_text().replace("cache=CACHE_OK", "cache=False")
    for old, new in edits:
        if old not in src:
            raise RuntimeError(f"profile {name!r}: the kernel's text changed; update ABLATIONS")
        src = src.replace(old, new)
    path = Path(tmp) / f"nd_ablated_{len(os.listdir(tmp))}.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def profile(dims, repeats) -> dict:
    """ns per mass-sample of the kernel and of each ablation (:data:`ABLATIONS`) on one
    mesh, measured alternately in this run (the fastest of ``repeats``): the differences
    are what each part costs in context (parts overlap in the out-of-order core: the
    shares need not add up)."""
    c = Case(*dims)
    n = max(5, int(4e5 // c.L))
    fns = {"full kernel": run_nd}
    with tempfile.TemporaryDirectory() as tmp:
        for name, edits in ABLATIONS.items():
            fns[name] = _ablated(name, edits, tmp).run_nd
        for fn in fns.values():
            fn(2, *c.hap)
        best = dict.fromkeys(fns, float("inf"))
        for _ in range(repeats):
            for name, fn in fns.items():
                t0 = time.thread_time()
                fn(n, *c.hap)
                best[name] = min(best[name], (time.thread_time() - t0) / n)
    return {"masses": c.N, "links": c.L,
            "parts": {k: {"ns_per_mass": v / c.N * 1e9} for k, v in best.items()}}


def per_call(repeats) -> dict:
    """The cost of one step call from Python on a small mesh (75 masses): us per call
    and transient bytes (tracemalloc) through the context (one argument, as Engine) and
    with the 38 arguments passed one by one."""
    import tracemalloc
    c = Case(5, 5, 3)
    args = (1, *c.hap)
    run_nd(*args)
    run_context(c.ctx)

    def direct(n):
        for _ in range(n):
            run_nd(*args)
    out = {"masses": c.N}
    for name, fn, one in (("context", c.run_hap_calls, lambda: run_context(c.ctx)),
                          ("arguments", direct, lambda: run_nd(*args))):
        out[f"{name}_us"] = per_sample(fn, 2000, repeats) * 1e6
        tracemalloc.start()
        one()
        tracemalloc.reset_peak()
        c0 = tracemalloc.get_traced_memory()[0]
        one()
        out[f"{name}_bytes"] = tracemalloc.get_traced_memory()[1] - c0
        tracemalloc.stop()
    return out


def faust_projection(n: int, repeats: int) -> dict:
    """The 1-D string of ``n`` beads on Engine against its Faust ``mi.lib`` twin.

    Returns a dict with ``beads``, ``max_rel_diff`` (over 2,000 samples, relative to the
    amplitude), ``hapsim_ns``, ``faust_ns`` (per mass-sample), ``ratio`` (hapsim / Faust)
    and ``faust_build_s``; or ``{"skipped": reason}``.
    """
    import bench_engine
    import faust_gen

    from hapsim.engine import Engine
    from hapsim.scene import LinkND, MassND, SceneND
    reason = faust_gen.tools_available()
    if reason is not None:
        return {"skipped": reason}
    sc = bench_engine.string_scene(n)
    sc = dataclasses.replace(sc, masses=tuple(m for m in sc.masses if m.kind != "port"),
                             links=tuple(lk for lk in sc.links if lk.kind != "contact"))
    nd = SceneND(1, sc.rate_hz,
                 tuple(MassND(m.name, m.kind, m.mass, np.array([m.x0]), np.array([m.v0]))
                       for m in sc.masses),
                 tuple(LinkND(lk.name, lk.kind, lk.m1, lk.m2, lk.stiffness, lk.damping,
                              0.0, 0.0) for lk in sc.links), (), None)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        exe = faust_gen.build(faust_gen.faust_program(sc), tmp, opt="-O3", timeout=600)
        build_s = time.perf_counter() - t0
        y = faust_gen.run_binary(exe, 2000)
        samples = max(640, int(2e7 / n))
        faust_s = faust_gen.bench_binary(exe, samples, repeats=repeats, block=64)
    eng = Engine(nd)
    x = np.empty_like(y)
    for s in range(2000):
        eng.step()
        x[s] = eng.x[0]
    diff = float(np.max(np.abs(x - y)) / np.max(np.abs(x)))
    hap_s = per_sample(eng.step, samples, repeats) * samples
    N = len(sc.masses) - 2            # beads (the two grounds do not move)
    return {"beads": n, "max_rel_diff": diff, "hapsim_ns": hap_s / (samples * N) * 1e9,
            "faust_ns": faust_s / (samples * N) * 1e9, "ratio": hap_s / faust_s,
            "faust_build_s": build_s}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="fewer sizes and repeats")
    p.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    p.add_argument("--faust", action="store_true",
                   help="also compare a 1-D projection with Faust mi.lib (builds it)")
    args = p.parse_args(argv)
    sizes = [(10, 10, 5), (22, 22, 11), (30, 30, 15)] if args.quick else \
        [(10, 10, 5), (20, 20, 10), (22, 22, 11), (30, 30, 15), (40, 40, 20),
         (60, 60, 30)]
    repeats = 5 if args.quick else 15
    load0 = os.getloadavg()[0]
    print(f"load average {load0:.2f} (1 min) on {os.cpu_count()} CPUs at the start")
    rows = []
    print(f"{'masses':>8} {'links':>8} {'families':>8} {'pieces':>6} {'hapsim ns/mass':>15} "
          f"{'ns/link':>8} {'ref ns/mass':>12} {'ns/link':>8} {'ratio':>6} {'max |dx|/h':>10} "
          f"{'single ns/mass':>15} {'single |dx|/h':>13} {'pieces ns/mass':>15}")
    for nx, ny, nz in sizes:
        c = Case(nx, ny, nz)
        c32 = Case(nx, ny, nz, np.float32)
        cp = Case(nx, ny, nz, dense=False)    # every link in pieces: the layout before
        n = max(5, int(4e5 // c.L))
        c.run_ref(2)
        c.run_hap(2)
        c32.run_hap(2)
        cp.run_hap(2)
        # agreement after the same samples from the same start
        c2 = Case(nx, ny, nz)
        c2.run_ref(200)
        c2.run_hap(200)
        err = float(np.max(np.abs(c2.ref[0].T - c2.hap[2]))) / SPACING
        c3 = Case(nx, ny, nz, np.float32)   # single precision after the same samples
        c3.run_hap(200)
        err32 = float(np.max(np.abs(c2.ref[0].T - c3.hap[2]))) / SPACING
        th = per_sample(c.run_hap, n, repeats)
        tr = per_sample(c.run_ref, n, repeats)
        t32 = per_sample(c32.run_hap, n, repeats)
        tp = per_sample(cp.run_hap, n, repeats)
        row = {"masses": c.N, "links": c.L, "families": c.families,
               "pieces": c.pieces,
               "hapsim_ns_per_mass": th / c.N * 1e9, "hapsim_ns_per_link": th / c.L * 1e9,
               "ref_ns_per_mass": tr / c.N * 1e9, "ref_ns_per_link": tr / c.L * 1e9,
               "ratio_ref_over_hapsim": tr / th, "max_rel_diff": err,
               "single_ns_per_mass": t32 / c.N * 1e9, "single_max_rel_diff": err32,
               "pieces_ns_per_mass": tp / c.N * 1e9}
        rows.append(row)
        print(f"{c.N:>8} {c.L:>8} {c.families:>8} {c.pieces:>6} {row['hapsim_ns_per_mass']:>15.2f} "
              f"{row['hapsim_ns_per_link']:>8.2f} {row['ref_ns_per_mass']:>12.2f} "
              f"{row['ref_ns_per_link']:>8.2f} {row['ratio_ref_over_hapsim']:>6.2f} "
              f"{err:>10.2e} {row['single_ns_per_mass']:>15.2f} {err32:>13.2e} "
              f"{row['pieces_ns_per_mass']:>15.2f}", flush=True)
    floor = sqrt_div_floor(repeats)
    print(f"one square root and one division alone: {floor:.2f} ns per element "
          f"(the Euclidean law needs both per link)", flush=True)
    out = {"rows": rows, "sqrt_div_ns": floor, "largest": {}}
    pc = per_call(repeats)
    out["per_call"] = pc
    print(f"one step call from Python ({pc['masses']} masses, 1 sample): through the "
          f"context {pc['context_us']:.2f} us and {pc['context_bytes']} B transient; "
          f"38 arguments {pc['arguments_us']:.2f} us and {pc['arguments_bytes']} B",
          flush=True)
    if not args.quick:
        pr = profile((22, 22, 11), repeats)
        out["profile"] = pr
        print(f"where the time goes ({pr['masses']} masses, ns per mass-sample):")
        for name, v in pr["parts"].items():
            print(f"  {name:<55} {v['ns_per_mass']:6.2f}", flush=True)
    for label, rate, deadline in (("44.1 kHz", "44100", 1.0 / 44100.0),
                                  ("1 kHz", "1000", 1e-3)):
        kinds = ("hapsim", "hapsim_per_call", "hapsim_single", "hapsim_single_per_call",
                 "reference") if rate == "44100" else ("hapsim", "hapsim_single", "reference")
        for kind in kinds:
            N, t = largest(kind, deadline, args.quick)
            out["largest"].setdefault(rate, {})[kind] = {
                "masses": N, "us_per_sample": t * 1e6}
            print(f"largest mesh within {label} ({deadline * 1e6:.2f} us/sample), {kind}: "
                  f"{N} masses ({t * 1e6:.2f} us/sample)", flush=True)
    if args.faust:
        fa = faust_projection(FAUST_BEADS, repeats)
        out["faust"] = fa
        if "skipped" in fa:
            print(f"Faust mi.lib comparison skipped: {fa['skipped']}")
        else:
            print(f"1-D string of {fa['beads']} beads, Engine against Faust mi.lib (-O3): "
                  f"largest difference {fa['max_rel_diff']:.1e} of the amplitude; "
                  f"{fa['hapsim_ns']:.2f} ns against {fa['faust_ns']:.2f} ns per mass-sample "
                  f"(hapsim / Faust = {fa['ratio']:.2f}; Faust build {fa['faust_build_s']:.0f} s)",
                  flush=True)
    out["load_average"] = [load0, os.getloadavg()[0]]
    print(f"load average {out['load_average'][1]:.2f} at the end")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
