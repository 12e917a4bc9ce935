"""The compiled loop's port step (cacheable) and its silence rule, on the bare stretch.

The compiled loop calls the engine's kernel through :func:`hapsim.host.fastloop_kernels._port_step`
(a kernel named by a tag whose type selects it, so that numba loads the loop from its disk
cache and compiles only that kernel into it); each of the kernels of ``hapsim.kernels``
must step exactly as the engine's own call does.
"""
from __future__ import annotations

import dataclasses
import math
import os
import socket
import time

import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.host import fastloop, fastloop_kernels
from hapsim.engine import Engine
from hapsim.scene import load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STRING = os.path.join(ROOT, "configs", "string.yaml")
WALL = os.path.join(ROOT, "configs", "wall.yaml")


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
        kind, pack = fastloop_kernels.kernel_pack(b)
        assert kind == fastloop_kernels.kernel_tag(len(kind) - 1)
        seen.add(len(kind) - 1)
        kick = 1e-3 * rng.standard_normal(a._x.size)
        for eng in (a, b):
            eng._x += kick
        x_init = a._x.copy()
        for n in range(300):
            drive = 2e-3 * math.sin(n / 17.0)
            for eng in (a, b):
                if eng._port >= 0:
                    eng._x[eng._port] = drive
            a.kernel_pack.kernel(1, *a.kernel_pack.args, fastloop._REC, fastloop._OUT, 0)
            fastloop_kernels._port_step(kind, pack, fastloop._REC, fastloop._OUT)
        assert np.array_equal(a._x, b._x), name
        assert np.array_equal(a._f, b._f), name
        assert not np.array_equal(a._x, x_init), name      # the scene moved
    fk = fastloop_kernels
    assert seen == {fk.K_MASSES, fk.K_SD, fk.K_CONTACT, fk.K_SD_CONTACT, fk.K_SYMPLECTIC,
                    fk.K_EXACT}


def test_kernel_pack_names_the_arrays_the_kernel_takes():
    """Engine.kernel_pack: the state leads the kernel's arguments, every named array and
    scheme value is one of them (the same object), the port is the scene's; so the
    compiled loop reads them by name, not by position."""
    for name, sc in _scenes():
        eng = Engine(sc)
        kp = eng.kernel_pack
        assert all(a is b for a, b in zip(kp.args[:6], kp.state)), name
        named = list(kp.scheme.values()) + list(kp.sd or ()) + list(kp.contact or ())
        for a in named:
            assert any(a is b for b in kp.args[6:]), name
        assert kp.port == (sc.index(sc.port.name) if sc.port is not None else -1), name
        assert (kp.sd is not None) == ("spring_damper" in sc.kinds), name
        assert (kp.contact is not None) == ("contact" in sc.kinds), name
        kp.state[0][kp.state[3]] += 1e-3      # a kick through the pack moves the engine
        eng.step(5)
        assert np.array_equal(eng.x[0].copy(), kp.state[0]), name
        assert np.any(eng.x[0].copy() != 0.0), name


@pytest.mark.parametrize("waiting", [True, False])
def test_silence_run_out_still_takes_the_states_waiting_in_the_port(waiting):
    """After a stall of the compiled thread past the silence (a return to Python that waited
    for the GIL), a STATE already in the port's buffer is answered, as the Python loop's
    ``receive(0)`` reads it; only an empty port is silence (``R_IDLE``: Python declares the
    loss)."""
    a, b = socket.socketpair()
    try:
        sc = fastloop._scratch(Engine(load_scene(WALL)), a.fileno())
        sc["iv"][fastloop_kernels.I_NMAX] = 1
        sc["pv"][fastloop_kernels.P_SILENCE] = sc["pv"][fastloop_kernels.P_POLL] = 0.05
        sc["pv"][fastloop_kernels.P_CLAMP_MAX] = 1e9                     # no safety stop
        sc["fv"][fastloop_kernels.F_LAST_RX] = time.monotonic() - 1.0     # 1 s ago: run out
        if waiting:
            b.sendall(fp.encode(fp.State(0, 0, fp.STATUS_ARMED, 0, (0.001,))))
            time.sleep(0.01)
        code = fastloop._run_stretch(sc)
        if waiting:
            assert code == fastloop_kernels.R_DONE and sc["iv"][fastloop_kernels.I_N] == 1
            b.settimeout(5.0)
            msgs = fp.StreamDecoder().feed(b.recv(64))
            assert [type(m).__name__ for m in msgs] == ["Force"] and msgs[0].seq == 0
        else:
            assert code == fastloop_kernels.R_IDLE and sc["iv"][fastloop_kernels.I_N] == 0
    finally:
        a.close()
        b.close()
