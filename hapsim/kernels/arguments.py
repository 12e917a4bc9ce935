"""Each 1-D engine kernel's arguments, declared once (issue 30).

The 1-D kernels (:mod:`hapsim.kernels.cordis`, :mod:`hapsim.kernels.schemes`,
:func:`hapsim.kernels.audio.run_periods`) take 10 to 32 positional arguments. Three callers
pass them: the engine, which lays its arrays out in that order (:class:`hapsim.engine.KernelPack`,
``MultiRatePack``), the one-argument runners of :mod:`hapsim.kernels.step1d`, which rebuild
them from an int64 context, and the compiled host loop's port step
(:func:`hapsim.host.fastloop_kernels.kernel_pack`). Each reads the order from
:data:`KERNELS`, so that adding a kernel or an argument is one entry here (and the kernel's
own ``def``; ``tests/test_kernel_arguments.py`` holds the two equal).

Each argument has a name (the kernel's parameter name), a type and a role:

========  ==================================================================================
role      what it is and who provides it
========  ==================================================================================
count     the samples (device periods) to advance: ``ctx[0]`` of a runner, 1 in the loop
head      an integer parameter (``int64``, or ``bool`` stored as 0/1): a context's ``ctx[1:]``
state     one of the engine's arrays or floats: :attr:`KernelPack.args` (in this order)
call      a per-call buffer (the port positions, audio frames, forces, ``rec``, ``out``)
row       a first row to write (``row0``, ``arow0``): ``int64`` 0 from a step
========  ==================================================================================

Types: ``F`` float64 array (n,), ``I`` int64 array (n,), ``F2`` float64 array (r, c),
``FLOAT`` a float (a 1-element float64 array in a context, taken as ``[0]``), ``INT`` int64,
``BOOL`` bool.

The compiled callers' kernel calls are generated from the table (:func:`call_function`):
step1d's at import, as numba functions that numba inlines into the runners' IR, the
compiled loop's by its ``@overload`` when numba types the loop. The call compiled is the
call written out by hand, with the same argument expressions, so the kernels compile for
the same signatures (six of the seven runners compile to the hand-written calls' machine
code; step_periods rebuilds two more arrays in its loop) and the callers,
whose functions stay in their files, keep numba's disk cache. Plain Python: no numba.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

__all__ = ["Arg", "Kernel", "KERNELS", "COUNT", "HEAD", "STATE", "CALL", "ROW", "F", "I", "F2",
           "FLOAT", "INT", "BOOL", "ROLES", "STATE_NAMES", "SD_NAMES", "CONTACT_NAMES", "take",
           "call_function"]

# roles
COUNT, HEAD, STATE, CALL, ROW = ROLES = ("count", "head", "state", "call", "row")
# types
F, I, F2, FLOAT, INT, BOOL = "f8[:]", "i8[:]", "f8[:, :]", "f8", "i8", "b1"


class Arg(NamedTuple):
    """One argument of a kernel.

    Attributes
    ----------
    name : str
        The kernel's parameter name.
    type : str
        ``F``, ``I``, ``F2``, ``FLOAT``, ``INT`` or ``BOOL`` (numba's spelling).
    role : str
        ``COUNT``, ``HEAD``, ``STATE``, ``CALL`` or ``ROW`` (module docstring).
    """

    name: str
    type: str
    role: str


class Kernel(NamedTuple):
    """A kernel's module and its arguments in its order.

    Attributes
    ----------
    module : str
        The module of :mod:`hapsim.kernels` that defines it (``"cordis"``, ``"schemes"``,
        ``"audio"``).
    args : tuple of Arg
        Every parameter of the kernel's ``def``, in order.
    """

    module: str
    args: tuple


def _args(*groups) -> tuple:
    return tuple(Arg(name, typ, role) for group in groups for name, typ, role in group)


_N = (("n", INT, COUNT),)
#: The engine's state (:attr:`hapsim.engine.KernelPack.state`, ``hapsim.kernels.cordis``).
_STATE = (("x", F, STATE), ("xp", F, STATE), ("f", F, STATE), ("mobile", I, STATE),
          ("t2m", F, STATE), ("fixed", I, STATE))
_SD = (("sd_i1", I, STATE), ("sd_i2", I, STATE), ("sd_k", F, STATE), ("sd_z", F, STATE))
_CONTACT = (("c_i1", I, STATE), ("c_i2", I, STATE), ("c_k", F, STATE), ("c_z", F, STATE),
            ("c_thr", F, STATE))
_RECORD = (("rec", I, CALL), ("out", F2, CALL), ("row0", INT, ROW))

#: Each 1-D kernel's arguments, by its function name, in the order of its ``def``.
KERNELS = {
    "run_masses": Kernel("cordis", _args(_N, _STATE, _RECORD)),
    "run_sd": Kernel("cordis", _args(_N, _STATE, _SD, _RECORD)),
    "run_contact": Kernel("cordis", _args(_N, _STATE, _CONTACT, _RECORD)),
    "run_sd_contact": Kernel("cordis", _args(_N, _STATE, _SD, _CONTACT, _RECORD)),
    "run_symplectic_euler": Kernel("schemes", _args(
        _N, _STATE, (("v", F, STATE), ("c", F, STATE), ("T", FLOAT, STATE)), _SD, _CONTACT,
        _RECORD)),
    "run_exact": Kernel("schemes", _args(
        _N, _STATE, (("v", F, STATE), ("T", FLOAT, STATE), ("phi", F2, STATE),
                     ("gam", F2, STATE), ("psi", F2, STATE), ("snew", F, STATE),
                     ("sold", F, STATE), ("uold", F, STATE)), _SD, _RECORD)),
    "run_periods": Kernel("audio", _args(
        _N, (("nsub", INT, HEAD), ("linear", BOOL, HEAD), ("last", BOOL, HEAD),
             ("port", INT, HEAD), ("pos", F, CALL)), _STATE, _SD, _CONTACT,
        (("l_idx", I, STATE), ("l_code", I, STATE), ("l_gain", F, STATE),
         ("inv_ta", FLOAT, STATE), ("audio", F2, CALL), ("arow0", INT, ROW),
         ("force", F, CALL)), _RECORD)),
}


#: The names of the engine's state, of a spring-damper's and of a contact's arrays (the
#: groups the engine builds; :attr:`hapsim.engine.KernelPack.state`, ``sd``, ``contact``).
STATE_NAMES = tuple(name for name, _, _ in _STATE)
SD_NAMES = tuple(name for name, _, _ in _SD)
CONTACT_NAMES = tuple(name for name, _, _ in _CONTACT)


def take(kernel: str, named: dict, roles=(STATE,)) -> tuple:
    """A kernel's arguments of the given roles, in its order, taken by name.

    Parameters
    ----------
    kernel : str
        A key of :data:`KERNELS`.
    named : dict
        Values by argument name (more may be given).
    roles : sequence of str
        The roles taken: ``(STATE,)`` the engine's arguments (:attr:`KernelPack.args`),
        ``(HEAD,)`` the integer head, ``(STATE, CALL)`` the arrays of a
        :mod:`hapsim.kernels.step1d` context, every role the whole call.

    Returns
    -------
    tuple
        ``named[name]`` for each argument of those roles (the same objects).

    Raises
    ------
    KeyError
        An unknown kernel, or an argument of those roles missing from ``named``.
    """
    return tuple(named[a.name] for a in KERNELS[kernel].args if a.role in roles)


def call_function(kernel: str, fn: Callable, params: str,
                  expression: Callable[[Arg, int, int], str], namespace: dict) -> Callable:
    """A Python function that calls ``fn`` with its arguments written out one by one: the
    implementation a numba ``@overload`` returns, so the call compiles into its caller.

    Parameters
    ----------
    kernel : str
        A key of :data:`KERNELS`.
    fn : callable
        The kernel (its numba dispatcher).
    params : str
        The generated function's parameters, as written in its ``def`` (the overload's).
    expression : callable
        ``expression(arg, i, j) -> str``: the source text of argument ``arg``, with ``i``
        its position among the kernel's ``head`` arguments (for ``HEAD``) or among its
        ``state`` and ``call`` arguments (the arrays a context holds, in order), ``j`` its
        position among the ``state`` arguments alone (-1 for the others).
    namespace : dict
        The globals the expressions name (``fn`` is added).

    Returns
    -------
    callable
        ``def impl(<params>): fn(<expressions>)``.

    Raises
    ------
    KeyError
        An unknown kernel.
    """
    parts = []
    heads = arrays = states = 0
    for a in KERNELS[kernel].args:
        if a.role == HEAD:
            parts.append(expression(a, heads, -1))
            heads += 1
        elif a.role in (STATE, CALL):
            parts.append(expression(a, arrays, states if a.role == STATE else -1))
            arrays += 1
            states += a.role == STATE
        else:
            parts.append(expression(a, -1, -1))
    source = f"def impl({params}):\n    fn({', '.join(parts)})\n"
    ns = dict(namespace, fn=fn)
    exec(compile(source, f"<hapsim.kernels.arguments: {kernel}>", "exec"), ns)
    return ns["impl"]
