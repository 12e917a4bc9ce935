"""Each 1-D kernel's arguments are declared once (issue 30): ``hapsim/kernels/arguments.py``.

The engine, the one-argument runners (:mod:`hapsim.kernels.step1d`) and the compiled
loop's port step (:mod:`hapsim.host.fastloop_kernels`) take a kernel's argument order from
that table; these tests hold the table equal to each kernel's own ``def`` (a kernel edited
without its entry, or an entry without its kernel, fails here by name), its types equal to
what the engine passes for random scenes of every kind, and its kernels those the three
callers know. That each caller's call is bit for bit the direct call is
``tests/test_engine_step_context.py`` and ``tests/test_compiled_port_step.py``.
"""

from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import numpy as np
import pytest

from hapsim.engine import Engine
from hapsim.host import fastloop_kernels
from hapsim.kernels import arguments, audio, cordis, schemes, step1d
from hapsim.scene import load_scene
from test_engine import random_network  # same directory (pytest prepend import mode)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
MODULES = {"cordis": cordis, "schemes": schemes, "audio": audio}
#: The 1-D kernels outside the table, with why: the live sound's kernel steps a ring of
#: port positions from the JACK callback (hapsim.audio), not one of the three callers.
NOT_DECLARED = {"run_frames"}


def mismatch(name: str, kernel: arguments.Kernel) -> str | None:
    """What differs between a table entry and its kernel's ``def`` (None: nothing).

    The kernel's Python function (``py_func`` of its dispatcher) is read with
    :func:`inspect.signature`: its parameter names, in order, must be the entry's; the
    entry must start with the one count and name its roles and types among the known."""
    fn = getattr(MODULES[kernel.module], name, None)
    if fn is None:
        return f"{kernel.module} has no {name}"
    params = list(inspect.signature(fn.py_func).parameters)
    declared = [a.name for a in kernel.args]
    if params != declared:
        return f"{name}: def takes {params}, the table declares {declared}"
    if [a.role for a in kernel.args].count(arguments.COUNT) != 1 or \
            kernel.args[0].role != arguments.COUNT:
        return f"{name}: one count first"
    for a in kernel.args:
        if a.role not in arguments.ROLES or a.type not in (
                arguments.F, arguments.I, arguments.F2, arguments.FLOAT, arguments.INT,
                arguments.BOOL):
            return f"{name}: {a}"
    return None


@pytest.mark.parametrize("name", sorted(arguments.KERNELS))
def test_the_table_is_each_kernels_signature(name):
    assert mismatch(name, arguments.KERNELS[name]) is None


def test_a_drifted_entry_is_caught():
    """The check fails on the class of drift: two arguments swapped, one dropped, one
    added, a kernel renamed (each on every entry)."""
    for name, k in arguments.KERNELS.items():
        a = k.args
        drifts = [a[:1] + a[2:3] + a[1:2] + a[3:], a[:-1],
                  a + (arguments.Arg("extra", arguments.F, arguments.STATE),)]
        for args in drifts:
            assert mismatch(name, k._replace(args=args)) is not None, (name, args)
        assert mismatch(name + "_gone", k) is not None


def test_the_three_callers_know_the_declared_kernels():
    """Every ``run_*`` kernel of cordis, schemes and audio is declared (but those listed
    aside, with why); step1d has a runner ``step_X`` for each (start-up finds it by that
    name), the compiled loop a kind for each one not multi-rate, the engine's centred
    kernels and integrators are among them."""
    found = {n for mod in MODULES.values() for n, f in vars(mod).items()
             if n.startswith("run_") and hasattr(f, "py_func")}
    assert found - NOT_DECLARED == set(arguments.KERNELS)
    fns = {getattr(MODULES[k.module], n): n for n, k in arguments.KERNELS.items()}
    assert set(step1d.RUNNERS) == set(fns)
    for fn, runner in step1d.RUNNERS.items():
        assert runner.__name__ == "step_" + fns[fn][len("run_"):]
    assert set(fastloop_kernels.KERNEL_NAMES.values()) == {
        n for n, k in arguments.KERNELS.items() if k.module != "audio"}
    assert set(cordis.KERNELS.values()) | {schemes.run_symplectic_euler,
                                           schemes.run_exact} <= set(fns)


def _conforms(value, typ: str) -> bool:
    """Whether a value the engine passes has the declared type."""
    if typ == arguments.FLOAT:
        return type(value) is float
    if typ == arguments.INT:
        return type(value) is int
    if typ == arguments.BOOL:
        return type(value) is bool
    dtype, ndim = {arguments.F: (np.float64, 1), arguments.I: (np.int64, 1),
                   arguments.F2: (np.float64, 2)}[typ]
    return (isinstance(value, np.ndarray) and value.dtype == dtype and value.ndim == ndim
            and value.flags.c_contiguous)


def _scenes(seeds=range(6)):
    """Random networks (seeded) of every link set, with and without fixed masses, in every
    integrator that takes them."""
    for seed in seeds:
        rng = np.random.default_rng(seed)
        net = random_network(rng, n_mass=int(rng.integers(1, 12)),
                             n_links=int(rng.integers(0, 16)), with_fixed=seed % 2 == 0)
        for kinds in ((), ("spring_damper",), ("contact",), ("spring_damper", "contact")):
            sc = dataclasses.replace(net, links=tuple(lk for lk in net.links
                                                      if lk.kind in kinds))
            for integ in ("centred", "symplectic_euler", "exact"):
                if integ == "exact" and "contact" in kinds:
                    continue
                yield f"{seed}-{'+'.join(kinds) or 'masses'}-{integ}", \
                    dataclasses.replace(sc, integrator=integ)


def test_the_declared_types_are_what_the_engine_passes():
    """For random scenes of every kernel, the engine's :attr:`KernelPack.args` are the
    kernel's state arguments, each of its declared type, and the state's named arrays are
    those of the table's names (the compiled loop and the runners read them by that)."""
    seen = set()
    for label, sc in _scenes():
        eng = Engine(sc)
        kp = eng.kernel_pack
        name = kp.kernel.__name__
        seen.add(name)
        state = [a for a in arguments.KERNELS[name].args if a.role == arguments.STATE]
        assert len(kp.args) == len(state), label
        for a, value in zip(state, kp.args):
            assert _conforms(value, a.type), (label, a)
        assert [a.name for a in state[:6]] == list(arguments.STATE_NAMES), label
        assert all(x is y for x, y in zip(kp.args, kp.state)), label
    assert seen == {n for n, k in arguments.KERNELS.items() if k.module != "audio"}


def test_the_multirate_pack_has_the_declared_types():
    """A scene with audio: the head and the state of :class:`MultiRatePack` are
    ``run_periods``' head and state arguments, each of its declared type."""
    eng = Engine(load_scene(CONFIGS / "audio_string.yaml"))
    head, state = eng.multirate_pack
    args = arguments.KERNELS["run_periods"].args
    heads = [a for a in args if a.role == arguments.HEAD]
    states = [a for a in args if a.role == arguments.STATE]
    assert len(head) == len(heads) and len(state) == len(states)
    for a, value in list(zip(heads, head)) + list(zip(states, state)):
        assert _conforms(value, a.type), a
    assert all(x is y for x, y in zip(state, eng.kernel_pack.state))


def test_schemes_build_orders_its_arguments_as_declared():
    """:func:`hapsim.kernels.schemes.build` still returns the scheme kernels' arguments in
    order (the engine takes them by name from the table): the same objects, in the same
    order, as the table's order over its named values."""
    for label, sc in _scenes(range(3)):
        if sc.integrator == "centred":
            continue
        eng = Engine(sc)
        kp = eng.kernel_pack
        ei, ef = np.empty(0, np.int64), np.empty(0)
        sd = kp.sd or (ei, ei, ef, ef)
        ct = kp.contact or (ei, ei, ef, ef, ef)
        kernel, args, extras = schemes.build(sc.integrator, eng.sim_period, *kp.state,
                                             sd=sd, contact=ct)
        named = {**dict(zip(arguments.STATE_NAMES, kp.state)),
                 **dict(zip(arguments.SD_NAMES, sd)),
                 **dict(zip(arguments.CONTACT_NAMES, ct)), **extras}
        assert kernel is kp.kernel, label
        taken = arguments.take(kernel.__name__, named)
        assert len(taken) == len(args), label
        assert all(x is y for x, y in zip(taken, args)), label
