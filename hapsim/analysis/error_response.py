"""Responses of the closed loop to errors at its two ends and to a known disturbance:
the sensor's error (observed and fed back), a force error at the device (a late tick, a
wire's rounding) and a known force disturbance convolved through the loop (docs/design.md,
'Identification'). ``run``'s measurement and its stated uncertainty are built on them.
"""

from __future__ import annotations

import numpy as np

from hapsim.analysis.kept import Kept

__all__ = ["sensor_inputs", "sensor_error_response", "force_error_response", "disturbance_response"]

#: Responses kept: one run's measurement asks for the same scene's two responses at the
#: record's length from four places per fit (the fit, its wire and late-tick terms, the
#: unseen holds' search), at each latency its search tries. Shared, read-only.
_KEPT = Kept(16)


def _remembered(kind: str, scene, n: int, compute) -> np.ndarray:
    """``compute()`` made read-only, kept by the scene object and length (:class:`Kept`)."""
    def made():
        out = compute()
        out.setflags(write=False)
        return out
    return _KEPT.get((kind, id(scene), int(n)), made, owner=scene)


def sensor_inputs(scene):
    """The closed loop and the two columns through which the position sensor's error
    enters it: ``s[n+1] = A s[n] + g e[n] + h e[n-1]`` for a reading ``x[n] + e[n]``.

    The links see the reading where the closed loop of
    :func:`hapsim.analysis.network.closed_loop` has the measured positions ``x[n]`` and
    ``x[n-1]``: ``g`` and ``h`` are those two states' columns of ``A`` less the same
    loop's with every link at zero gain (the device's own dynamics, which sees the true
    position, taken out).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene with a port and a device (calibrated: no ``target`` links).

    Returns
    -------
    (ndarray, ndarray, ndarray, list of str)
        ``A`` shape (n, n), ``g`` and ``h`` shape (n,) [per m of error], and the states'
        names (:func:`~hapsim.analysis.network.closed_loop`'s).

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.network.closed_loop`.
    """
    from hapsim.analysis.network import closed_loop

    A, names = closed_loop(scene)
    A0, _ = closed_loop(scene, gain=0.0)
    ipp = 2 if scene.device.hold == "zoh" else 1
    return A, A[:, 0] - A0[:, 0], A[:, ipp] - A0[:, ipp], names


def sensor_error_response(scene, n: int) -> np.ndarray:
    """Impulse response from the position sensor's error to the logged position.

    The host reads ``x[n] + e[n]``: the error is logged (direct term 1) and, through the
    virtual links, fed back as a force, so that it also moves the handle. With the
    closed-loop state ``s[n+1] = A s[n]`` of :func:`hapsim.analysis.network.closed_loop`,
    the error enters where the measured positions ``x[n]`` and ``x[n-1]`` do: the columns
    ``g``, ``h`` of those two states that the links contribute (``A`` minus the same loop
    with every link at zero gain). Then ``s[n+1] = A s[n] + g e[n] + h e[n-1]`` and the
    response is ``1, c g, c (A g + h), c A (A g + h), ...``.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene with a port and a device (calibrated: no ``target`` links).
    n : int
        Length of the response.

    Returns
    -------
    ndarray, shape (n,)
        Logged-position response to a unit sensor error at sample 0 [m/m]; read-only
        (the same scene object and length share one array).

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.network.closed_loop`.
    """
    return _remembered("sensor", scene, n, lambda: _sensor_response(scene, n))


def _sensor_response(scene, n: int) -> np.ndarray:
    from hapsim.kernels.impulse import first_state_response

    A, g, h, _ = sensor_inputs(scene)
    out = first_state_response(np.ascontiguousarray(A, float), np.asarray(g, float),
                               np.asarray(h, float), max(int(n), 0))
    if out.size:      # (empty: a run refused before its first STATE)
        out[0] = 1.0
    return out


def force_error_response(scene, n: int) -> np.ndarray:
    """Impulse response from a force error at the device to the logged position [m/N].

    ``h[0] = 0``, ``h[k] = c A^(k-1) b`` (``A``: :func:`hapsim.analysis.network.closed_loop`,
    ``b``: :func:`hapsim.analysis.network.force_input`, ``c``: the logged position): how a
    force held over one period that differs from the one computed (a late tick, a wire's
    rounding) moves the handle afterwards, the loop closed.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated, calibrated scene with a port and a device.
    n : int
        Length.

    Returns
    -------
    ndarray, shape (n,)
        Read-only (the same scene object and length share one array).

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.network.closed_loop`.
    """
    return _remembered("force", scene, n, lambda: _force_response(scene, n))


def _force_response(scene, n: int) -> np.ndarray:
    from hapsim.analysis.network import closed_loop, force_input
    from hapsim.kernels.impulse import first_state_response

    if int(n) < 2:
        return np.zeros(max(int(n), 0))
    A, _ = closed_loop(scene)
    b = np.asarray(force_input(scene), float)
    return first_state_response(np.ascontiguousarray(A, float), b, np.zeros_like(b),
                                int(n))


def disturbance_response(scene, w, *, starts=None, response=None) -> np.ndarray:
    """Logged-position response of the closed loop to a known force disturbance.

    A late tick holds an older force than the loop's ``u[n] = F[n-d]``: the device applied
    ``u[n] + w[n]`` with ``w[n]`` known from its STATEs
    (:meth:`hapsim.applied.AppliedAccount.disturbance`). The loop is linear, so the
    record is the undisturbed loop's plus ``x_w[n] = sum_{j<n} c A^(n-1-j) b w[j]`` with
    ``A`` of :func:`hapsim.analysis.network.closed_loop`, ``b`` of
    :func:`hapsim.analysis.network.force_input` and ``c`` the logged position (state 0):
    the convolution of ``w`` with the loop's impulse response (superposition of a linear
    time-invariant system driven by a known input).

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated, calibrated scene with a port and a device.
    w : array_like, shape (n,)
        Disturbance force per sample [N].
    starts : array_like of int, optional
        Rows where the record restarts (a gap in the STATEs, the scene restarted after a
        recovery): the response is summed within each stretch only, from its first row
        (what came before is the stretch's initial state, i.e. part of its free response).
    response : ndarray, optional
        :func:`force_error_response` of the scene, at least ``n`` long (computed when
        None).

    Returns
    -------
    ndarray, shape (n,)
        ``x_w`` [m].

    Raises
    ------
    ConfigError
        As :func:`hapsim.analysis.network.closed_loop`.
    """
    from hapsim.analysis.fftconv import fftconvolve

    w = np.asarray(w, float)
    n = w.size
    out = np.zeros(n)
    nz = np.flatnonzero(w)
    if n < 2 or nz.size == 0:
        return out
    h = force_error_response(scene, n) if response is None else np.asarray(response, float)
    edges = sorted({0, n, *(int(a) for a in (starts if starts is not None else ())
                            if 0 < int(a) < n)})
    for a, b in zip(edges[:-1], edges[1:]):
        seg = w[a:b]
        k = np.flatnonzero(seg)
        if k.size == 0:
            continue
        first = a + int(k[0])             # the response is needed from here to b
        m = b - first
        out[first:b] = (fftconvolve(w[first:b], h[:m])[:m] if m > 64
                        else np.convolve(w[first:b], h[:m])[:m])
    return out
