"""The BLAS thread pools of a hapsim process: sized once, deliberately, and never spinning
beside the real-time loop.

Every ``hapsim`` command runs its linear algebra with one BLAS thread
(:func:`size_pools`, called by the command line before numpy is imported): OpenBLAS's
worker threads spin while they wait for work, so two analyses at once on a 2-core machine,
each with a pool as large as the machine, spin on each other's cores (issue 19: two
``hapsim check`` on a 500-bead string took 44 s each against 1.4 s alone). The analysis'
matrices (a few thousand states at most) gain little from a second thread, and a process
whose pool has one thread has no pool threads at all, so a background prediction (``play``,
``run --osc``) in the loop's process runs its BLAS calls in its own thread and nothing
spins beside the loop. ``tools/bench_pools.py`` measures it (each of two concurrent
commands against one alone). A user's own ``OPENBLAS_NUM_THREADS`` (or ``OMP_NUM_THREADS``,
``MKL_NUM_THREADS``, ``BLIS_NUM_THREADS``) is kept.

A threaded OpenBLAS on a loaded machine turns a small SVD (the identification's matrix
pencil) into seconds of spinning threads, and idle BLAS threads compete with the real-time
loop. ``OPENBLAS_NUM_THREADS`` only works before numpy is imported, so this calls the
library's own ``openblas_set_num_threads`` on every OpenBLAS already loaded (threadpoolctl
does the same; it is used when installed).
"""

from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["limit_blas_threads", "size_pools", "POOL_ENV"]

#: Environment variables that size a BLAS / OpenMP pool when the library loads.
POOL_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")

_SYMBOLS = ("openblas_set_num_threads", "openblas_set_num_threads64_",
            "scipy_openblas_set_num_threads", "scipy_openblas_set_num_threads64_")


def limit_blas_threads(n: int = 1) -> bool:
    """Set the thread count of every loaded OpenBLAS to ``n``.

    Parameters
    ----------
    n : int
        Threads (>= 1).

    Returns
    -------
    bool
        True when at least one library was limited.
    """
    try:
        import threadpoolctl  # type: ignore
        threadpoolctl.threadpool_limits(n, user_api="blas")
        return True
    except Exception:
        pass
    done = False
    try:
        with open("/proc/self/maps") as fh:
            paths = {line.split()[-1] for line in fh if "openblas" in line.lower()
                     and line.split()[-1].startswith("/")}
    except OSError:
        return False
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for sym in _SYMBOLS:
            fn = getattr(lib, sym, None)
            if fn is not None:
                try:
                    fn(ctypes.c_int(n))
                    done = True
                except Exception:
                    pass
    return done


def size_pools(threads: int = 1) -> str:
    """Size the BLAS pools of this process (and its children) for a hapsim command.

    Before numpy is imported the pool sizes are set in the environment, so OpenBLAS never
    starts worker threads (children, e.g. the embedded mock, inherit it); once it is loaded
    (a caller that imported numpy first) the loaded libraries are limited at run time
    (:func:`limit_blas_threads`). A size the user set in the environment is kept.

    Parameters
    ----------
    threads : int
        BLAS threads per process (>= 1).

    Returns
    -------
    str
        ``"user"`` (the environment already sized a pool: kept), ``"environment"`` (set
        before numpy loaded) or ``"runtime"`` (numpy was loaded: limited in place).
    """
    if any(os.environ.get(k) for k in POOL_ENV):
        return "user"
    for k in POOL_ENV:
        os.environ[k] = str(int(threads))
    if "numpy" in sys.modules:
        limit_blas_threads(threads)
        return "runtime"
    return "environment"
