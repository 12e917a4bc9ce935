"""Full linear convolution of real arrays by FFT, on ``numpy.fft``.

The fits' error propagation convolves long records with a response
(:mod:`hapsim.analysis.error_response`, :mod:`hapsim.analysis.identify`,
:mod:`hapsim.analysis.pencil`). ``scipy.signal.fftconvolve`` does it, but importing
``scipy.signal`` costs about 1 CPU-s (it imports ``scipy.stats``, ``scipy.interpolate`` and
``scipy.optimize``), paid by every ``hapsim run`` or ``hapsim identify`` process that
measures; ``numpy.fft`` (pocketfft, as scipy's) is already loaded with numpy. This module
computes what ``fftconvolve(a, b, mode="full", axes=axes)`` computes for real inputs, in
the same way (zero-padding to a 5-smooth length, real transforms, the product, the
inverse, the full output), so the two agree to the round-off of an FFT convolution
(``tests/test_fftconv.py`` checks both against the direct sum).
"""

from __future__ import annotations

import numpy as np

__all__ = ["fftconvolve", "fast_length"]


def fast_length(n: int) -> int:
    """The smallest ``2^a 3^b 5^c`` not below ``n`` (a length pocketfft transforms fast).

    Parameters
    ----------
    n : int
        Required length, ``n >= 1``.

    Returns
    -------
    int
        The padded length (``scipy.fft.next_fast_len(n, real=True)``'s 5-smooth rule).

    Raises
    ------
    ValueError
        ``n < 1``.
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"a transform length must be at least 1, not {n}")
    best = 1 << max(n - 1, 0).bit_length()          # the next power of two: an upper bound
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            # the least power of two that lifts p35 to n or above
            q = -(-n // p35)
            m = p35 * (1 << max(q - 1, 0).bit_length())
            if m < best:
                best = m
            p35 *= 3
        p5 *= 5
    return best


def fftconvolve(a, b, axes=None) -> np.ndarray:
    """Full linear convolution of two real arrays along ``axes``, by FFT.

    Parameters
    ----------
    a, b : array_like of float
        Inputs of the same number of dimensions; along the axes not convolved their
        sizes broadcast (equal, or one of them 1).
    axes : int or sequence of int, optional
        The axes convolved (default: all).

    Returns
    -------
    ndarray
        Shape ``a.shape[i] + b.shape[i] - 1`` along a convolved axis ``i``, the broadcast
        size along the others: ``out[n] = sum_k a[k] b[n - k]`` (``np.convolve``'s full
        mode, per axis), as ``scipy.signal.fftconvolve(a, b, mode="full", axes=axes)``
        (Cooley & Tukey 1965's convolution theorem; rounding error of order
        ``log2(N) eps |a| |b|``, Higham 2002, Sec. 24.1). Empty when either input is.

    Raises
    ------
    ValueError
        Inputs of different dimensions, or sizes that do not broadcast.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.ndim != b.ndim:
        raise ValueError(f"inputs of {a.ndim} and {b.ndim} dimensions")
    if a.size == 0 or b.size == 0:
        return np.zeros(0)
    if a.ndim == 0:
        return a * b
    if axes is None:
        ax = list(range(a.ndim))
    else:
        ax = sorted({int(i) % a.ndim for i in np.atleast_1d(axes)})
    shape = []
    for i in range(a.ndim):
        if i in ax:
            shape.append(a.shape[i] + b.shape[i] - 1)
        elif a.shape[i] == b.shape[i] or 1 in (a.shape[i], b.shape[i]):
            shape.append(max(a.shape[i], b.shape[i]))
        else:
            raise ValueError(f"sizes {a.shape[i]} and {b.shape[i]} along axis {i} do not "
                             "broadcast")
    fshape = [fast_length(shape[i]) for i in ax]
    A = np.fft.rfftn(a, fshape, axes=ax)
    B = np.fft.rfftn(b, fshape, axes=ax)
    out = np.fft.irfftn(A * B, fshape, axes=ax)
    return out[tuple(slice(s) for s in shape)].copy()
