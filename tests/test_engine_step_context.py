"""The 1-D engine's step as one compiled call with one argument (hapsim/kernels/step1d.py):
bit for bit the kernels called directly with their arguments, for every kernel (each set of
link kinds, chain or not, each integrator, the multi-rate model in its port modes), and no
allocation per call (the real-time rule; with its arguments passed one by one the call made
0.6-0.85 KB, a multi-rate step 0.5 MB)."""

from __future__ import annotations

import dataclasses
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from hapsim.bench.cost import string_scene
from hapsim.engine import Engine
from hapsim.kernels import step1d
from hapsim.scene import load_scene
from test_engine import random_network  # same directory (pytest prepend import mode)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
_REC = np.empty(0, dtype=np.int64)
_OUT = np.empty((0, 0))


def _state(eng: Engine) -> list:
    """Every array the kernel updates, as bytes (bitwise comparison, NaN-safe)."""
    arrs = [eng._x, eng._xp, eng._f] + [a for a in eng._args if isinstance(a, np.ndarray)]
    return [a.tobytes() for a in arrs]


def _scenes():
    """Scenes of every kernel: masses only, springs, contacts, both, chain and network,
    with and without a port, in each integrator that takes them."""
    rng = np.random.default_rng(23)
    out = []
    for seed in range(3):
        net = random_network(np.random.default_rng(seed), with_fixed=bool(seed % 2 == 0))
        out += [("network", net),
                ("springs", dataclasses.replace(net, links=tuple(
                    lk for lk in net.links if lk.kind == "spring_damper"))),
                ("contacts", dataclasses.replace(net, links=tuple(
                    lk for lk in net.links if lk.kind == "contact"))),
                ("masses", dataclasses.replace(net, links=()))]
    out.append(("chain", string_scene(n=int(rng.integers(5, 40)), K=1500.0)))
    out.append(("string", load_scene(CONFIGS / "string.yaml")))
    scenes = []
    for name, sc in out:
        for integ in ("centred", "symplectic_euler", "exact"):
            if integ == "exact" and any(lk.kind == "contact" for lk in sc.links):
                continue
            scenes.append((f"{name}-{integ}", dataclasses.replace(sc, integrator=integ)))
    return scenes


SCENES = _scenes()


@pytest.mark.parametrize("name,scene", SCENES, ids=[n for n, _ in SCENES])
def test_step_and_port_step_equal_the_direct_kernel_call_bit_for_bit(name, scene):
    """Random splits of 300 samples into step(n) calls and port_step at random positions:
    every state array equals, bit for bit, that of an engine whose kernel is called with
    its arguments one by one (the call the context replaces)."""
    a, b = Engine(scene), Engine(scene)
    assert step1d.RUNNERS[a._kernel] is a._step_run
    rng = np.random.default_rng(len(name))
    done = ports = 0
    while done < 300:
        n = int(rng.integers(0, 40))
        a.step(n)
        b._kernel(n, *b._args, _REC, _OUT, 0)
        done += n
        if a.port_index >= 0:
            p = float(rng.normal(0, 0.005))
            fa = a.port_step(p)
            b._x[b.port_index] = p
            b._kernel(1, *b._args, _REC, _OUT, 0)
            assert np.float64(fa).tobytes() == b._f[b.port_index].tobytes()
            ports += 1
        assert _state(a) == _state(b), (name, done)
    assert a.sample == done + ports
    assert not np.array_equal(a._x, Engine(scene)._x)      # the scene moved


@pytest.mark.parametrize("position,force", [("hold", "mean"), ("linear", "last"),
                                            ("linear", "mean")])
def test_multirate_step_and_port_step_equal_the_direct_calls(position, force):
    """A scene with ``audio``: step(n) holds the port and drops the sound as run(n) does
    (the reference), port_step gives the force and frames of the direct multi-rate call."""
    base = load_scene(CONFIGS / "audio_string.yaml")
    scene = dataclasses.replace(base, audio=dataclasses.replace(
        base.audio, port_position=position, port_force=force))
    a, b = Engine(scene), Engine(scene)
    assert a.substeps > 1
    rng = np.random.default_rng(7)
    pos1, force1 = np.zeros(1), np.zeros(1)
    frames = np.zeros_like(b.frames)
    steps = 0
    for _ in range(12):
        n = int(rng.integers(0, 30))
        steps += n
        a.step(n)
        b.run(n, [])
        p = float(rng.normal(0, 0.003))
        fa = a.port_step(p)
        pos1[0] = p
        b._periods(1, pos1, frames, 0, force1, _REC, _OUT, 0)
        assert np.float64(fa).tobytes() == force1.tobytes()
        assert a.frames.tobytes() == frames.tobytes()
        assert [x.tobytes() for x in (a._x, a._xp, a._f)] == \
            [x.tobytes() for x in (b._x, b._xp, b._f)]
    assert a.sample == steps + 12 and b.sample == steps      # b's port periods uncounted


def _transient(f) -> int:
    """Peak bytes traced while ``f()`` runs, over those traced before [bytes]."""
    tracemalloc.reset_peak()
    c0 = tracemalloc.get_traced_memory()[0]
    f()
    return tracemalloc.get_traced_memory()[1] - c0


@pytest.mark.parametrize("config", ["wall.yaml", "string.yaml", "audio_string.yaml"])
def test_step_and_port_step_make_no_array(config):
    """step(1), step(50) and port_step: transient memory below that of making one small
    array (measured the same way in the same run): the one-argument dispatch is all that
    is left (the kernels' 14-32 arguments passed one by one made 608-848 B per call, and a
    multi-rate step its 0.5 MB of run() buffers)."""
    eng = Engine(load_scene(CONFIGS / config))
    eng.step(1)
    if eng.port_index >= 0:
        eng.port_step(0.0)
    tracemalloc.start()
    try:
        calls = [lambda: eng.step(1), lambda: eng.step(50)]
        if eng.port_index >= 0:
            calls.append(lambda: eng.port_step(0.001))
        # the least of 8 calls: an allocation made by every call shows in each, while
        # another thread's (xdist's channel) lands in one window now and then
        peaks = [min(_transient(c) for _ in range(8)) for c in calls]
        one = min(_transient(lambda: np.empty(1)) for _ in range(8))
    finally:
        tracemalloc.stop()
    assert max(peaks) < one, (peaks, one)


@pytest.mark.parametrize("name,scene", SCENES[:4] + SCENES[-6:] + [
    ("audio", load_scene(CONFIGS / "audio_string.yaml"))], ids=lambda v: v if isinstance(
        v, str) else "")
def test_start_up_checks_the_cache_of_the_runner_the_engine_calls(name, scene):
    """``hapsim run`` announces a compilation unless numba's cache holds every function its
    warm-up compiles: the engine part names the runner this engine's step calls (found by
    name in step1d.py, without importing numba)."""
    from hapsim.pipeline import startup
    eng = Engine(scene)
    part = startup.run_compile_parts(scene, compiled_loop=False)[0]
    runner = eng._step_run
    assert (step1d.__file__, runner.__name__) in [
        (str(Path(s)), f) for s, f in startup.part_functions(part)]
    assert runner.__name__ == "step_" + part[2][len("run_"):]
