"""The first state's response of a free linear recursion, compiled: the loop's impulse
responses to a sensor error and to a force error (:mod:`hapsim.analysis.error_response`).

One run's measurement asks for them at every model its searches try (a render latency, a
refitted device): as numpy steps in Python they cost ~8 us per sample, a third of a
second for the hundred models of a lossy Hapkit record; here a few nanoseconds per state
entry.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["first_state_response"]


@nb.njit(cache=True, nogil=True)
def first_state_response(A, s1, s2, n):
    """``out[k] = s_k[0]`` for ``k = 1 .. n-1`` of ``s_1 = s1``, ``s_2 = A s1 + s2``,
    ``s_(k+1) = A s_k`` after; ``out[0] = 0``.

    Parameters
    ----------
    A : ndarray, shape (p, p), float64, C-contiguous
        The recursion's matrix.
    s1, s2 : ndarray, shape (p,), float64
        The first state and the input added at the second step (zeros: none).
    n : int >= 0
        The response's length.

    Returns
    -------
    ndarray, shape (n,)
        ``[0, s_1[0], s_2[0], ...]``.

    Notes
    -----
    Each step is ``A s`` summed over the columns in order, as a matrix-vector product;
    its rounding is the product's (a few units in the last place of each step's entries),
    not a BLAS kernel's order bit for bit.
    """
    p = A.shape[0]
    out = np.zeros(max(n, 0))
    s = s1.copy()
    t = np.empty(p)
    for k in range(1, n):
        out[k] = s[0]
        for i in range(p):
            acc = 0.0
            for j in range(p):
                acc += A[i, j] * s[j]
            t[i] = acc
        if k == 1:
            for i in range(p):
                t[i] += s2[i]
        s, t = t, s
    return out
