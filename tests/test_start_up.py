"""Start-up paths: the compiled loop's cacheable port step and the lazy scipy import.

The compiled loop calls the engine's kernel through :func:`hapsim.daemon.fastloop._port_step`
(a kernel chosen by an integer, so that numba loads the loop from its disk cache); each of
the kernels of ``hapsim.kernels`` must step exactly as the engine's own call does. The
stability prediction finds its unit-circle roots without scipy (its import cost 0.6 s of
every ``hapsim run``): the root finder is checked against closed-form roots.
"""
from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from hapsim.analysis.ths import _root_bracketed
from hapsim.daemon import fastloop
from hapsim.engine import Engine
from hapsim.scene import load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STRING = os.path.join(ROOT, "configs", "string.yaml")


def _scenes():
    """String scene variants covering every kernel: link kinds x integrators."""
    base = load_scene(STRING)
    kept = {"none": (), "sd": ("spring_damper",), "contact": ("contact",),
            "both": ("spring_damper", "contact")}
    out = []
    for name, kinds in kept.items():
        links = tuple(lk for lk in base.links if lk.kind in kinds)
        sc = dataclasses.replace(base, links=links)
        out.append((f"centred-{name}", sc))
        if name == "both":
            out.append(("symplectic", dataclasses.replace(sc, integrator="symplectic_euler")))
        if name == "sd":
            out.append(("exact", dataclasses.replace(sc, integrator="exact")))
    return out


def test_port_step_equals_the_engine_kernel_for_every_kernel():
    rng = np.random.default_rng(7)
    seen = set()
    for name, sc in _scenes():
        a, b = Engine(sc), Engine(sc)
        kind, pack = fastloop.kernel_pack(b)
        seen.add(kind)
        kick = 1e-3 * rng.standard_normal(a._x.size)
        for eng in (a, b):
            eng._x += kick
        x_init = a._x.copy()
        for n in range(300):
            drive = 2e-3 * math.sin(n / 17.0)
            for eng in (a, b):
                if eng._port >= 0:
                    eng._x[eng._port] = drive
            a._kernel(1, *a._args, fastloop._REC, fastloop._OUT, 0)
            fastloop._port_step(kind, pack, fastloop._REC, fastloop._OUT)
        assert np.array_equal(a._x, b._x), name
        assert np.array_equal(a._f, b._f), name
        assert not np.array_equal(a._x, x_init), name      # the scene moved
    assert seen == {fastloop.K_MASSES, fastloop.K_SD, fastloop.K_CONTACT, fastloop.K_SD_CONTACT,
                    fastloop.K_SYMPLECTIC, fastloop.K_EXACT}


def test_root_finder_hits_closed_form_roots():
    rng = np.random.default_rng(3)
    for _ in range(300):
        r = rng.uniform(-5.0, 5.0)
        s = 10.0 ** rng.uniform(-9.0, 1.0)            # bracket widths over 10 decades
        lo, hi = r - s * rng.uniform(0.01, 1.0), r + s * rng.uniform(0.01, 1.0)
        p = int(rng.integers(1, 4))                    # simple or triple root, any slope
        c = 10.0 ** rng.uniform(-6.0, 6.0)
        sign = -1.0 if rng.random() < 0.5 else 1.0
        x = _root_bracketed(lambda t: sign * c * (t - r) ** (2 * p - 1)
                            + sign * c * 1e-3 * (t - r) * (1.0 + 0.5 * math.sin(t)), lo, hi)
        assert abs(x - r) <= 8.0 * math.ulp(max(abs(r), s)) + 1e-300, (r, lo, hi, p, x)
    # g(a) and g(b) of the same sign: the midpoint (the documented fallback)
    assert _root_bracketed(lambda t: 1.0 + t * t, 0.0, 2.0) == 1.0


def test_a_run_imports_no_scipy_optimize_before_its_first_sample():
    code = ("import sys\n"
            "from hapsim.scene import load_scene\n"
            "from hapsim.daemon.runner import predict, prepare_scene\n"
            f"predict(prepare_scene(load_scene({STRING!r}))[0])\n"
            "print(sorted(m for m in sys.modules if m.startswith('scipy.optimize')))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=ROOT), cwd=ROOT, timeout=120)
    assert p.returncode == 0, p.stderr[-800:]
    assert p.stdout.strip() == "[]"
