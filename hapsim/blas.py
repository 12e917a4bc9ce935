"""Limit the BLAS thread pool of this process (the daemon, the OSC analyst and play are
single-threaded by design).

A threaded OpenBLAS on a loaded machine turns a small SVD (the identification's matrix
pencil) into seconds of spinning threads, and idle BLAS threads compete with the real-time
loop. ``OPENBLAS_NUM_THREADS`` only works before numpy is imported, so this calls the
library's own ``openblas_set_num_threads`` on every OpenBLAS already loaded (threadpoolctl
does the same; it is used when installed).
"""

from __future__ import annotations

import ctypes

__all__ = ["limit_blas_threads"]

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
