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

__all__ = ["limit_blas_threads", "size_pools", "preload_numba_blas", "POOL_ENV"]

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


def preload_numba_blas() -> bool:
    """Load ``scipy.linalg.cython_blas`` without importing the ``scipy.linalg`` package.

    numba imports ``scipy.linalg.cython_blas`` when it first sets up its compiler (its
    ``np.dot`` / ``np.linalg`` support checks that the BLAS bindings exist; numba
    0.5x-0.6x, ``numba.np.arraymath._check_blas``); importing it runs ``scipy.linalg``'s
    ``__init__``, ~0.15-0.3 s of the warm-up. With the extension module already in
    ``sys.modules`` under its full name that import finds it and nothing else is loaded;
    numba's BLAS calls at run time look the module up there too. A later
    ``import scipy.linalg`` works as usual and finds the same extension module.

    Returns
    -------
    bool
        True when the module is (now) in ``sys.modules``; False when scipy is not
        installed or the module could not be loaded (numba then imports it its own way).

    Notes
    -----
    Call it before the first numba compilation or cache load of the process. After it,
    ``scipy.linalg.cython_blas`` as an *attribute* of ``scipy.linalg`` exists only once
    something imports it as a submodule again (``import scipy.linalg.cython_blas``).
    """
    name = "scipy.linalg.cython_blas"
    if name in sys.modules or "scipy.linalg" in sys.modules:
        return name in sys.modules or _import_real(name)
    try:
        import importlib.machinery
        import importlib.util

        import scipy
        folder = os.path.join(os.path.dirname(scipy.__file__), "linalg")
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = os.path.join(folder, "cython_blas" + suffix)
            if os.path.exists(path):
                spec = importlib.util.spec_from_file_location(name, path)
                module = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(module)
                sys.modules[name] = module
                return True
    except Exception:   # noqa: BLE001 - any failure: numba imports scipy.linalg itself
        return False
    return False


def _import_real(name: str) -> bool:
    try:
        __import__(name)
        return True
    except ImportError:
        return False
