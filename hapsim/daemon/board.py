"""The emulated Hapkit 3 board: build the firmware and the simavr board program, start it.

The reference firmware (``firmware_protocol/firmware/hapkit``, C99 + avr-libc, built with
avr-gcc) runs cycle by cycle on simavr's ATmega328P inside ``hapkit_board``
(``firmware_protocol/firmware/sim``, C on libsimavr), which wires the device's physics to
the chip's pins and bridges its UART to a pseudo-terminal. Both are built with ``make``
when missing or older than their sources.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
from pathlib import Path

from hapsim.errors import DeviceError

ROOT = Path(__file__).resolve().parents[2] / "firmware_protocol" / "firmware"
FIRMWARE_DIR = ROOT / "hapkit"
BOARD_DIR = ROOT / "sim"
FIRMWARE_ELF = FIRMWARE_DIR / "hapkit.elf"
VECTORS_ELF = FIRMWARE_DIR / "hapkit_vectors.elf"
BOARD = BOARD_DIR / "hapkit_board"


def missing_tools() -> str | None:
    """What is missing to build and run the emulated board, or None.

    Returns
    -------
    str or None
        A sentence naming the missing programs/headers (the Debian packages gcc-avr,
        avr-libc, simavr, libsimavr-dev provide them), or None when all are present.
    """
    missing = [t for t in ("make", "cc", "avr-gcc") if shutil.which(t) is None]
    if not Path("/usr/include/simavr/sim_avr.h").exists() and not os.environ.get(
            "SIMAVR_INCLUDE"):
        missing.append("simavr headers (libsimavr-dev)")
    if not any(Path(d, "avr", "io.h").exists() for d in ("/usr/lib/avr/include",
                                                          "/usr/avr/include")):
        missing.append("avr-libc")
    if missing:
        return ("not installed: " + ", ".join(missing) +
                " (Debian packages gcc-avr, avr-libc, simavr, libsimavr-dev)")
    return None


def build(*, quiet: bool = True) -> dict:
    """Build the firmware (``hapkit.elf``, ``hapkit_vectors.elf``) and ``hapkit_board``.

    ``make`` rebuilds only what is missing or older than its sources; warnings are errors
    (``-Wall -Wextra -Werror``). The UART runs at the Makefile's ``BAUD`` (2 Mbaud).

    Parameters
    ----------
    quiet : bool
        Capture make's output (it is in the error on failure) instead of printing it.

    Returns
    -------
    dict
        ``board``, ``elf``, ``vectors_elf`` (paths as str), ``output`` (make's output:
        compiler lines and the ``avr-size`` table of flash and RAM use).

    Raises
    ------
    DeviceError
        A tool is missing (:func:`missing_tools`) or make failed (its output attached).
    """
    why = missing_tools()
    if why:
        raise DeviceError(f"cannot build the emulated Hapkit board: {why}")
    out = []
    for d, target in ((FIRMWARE_DIR, "all"), (BOARD_DIR, "hapkit_board")):
        r = subprocess.run(["make", "-C", str(d), target], capture_output=True, text=True)
        out.append(r.stdout + r.stderr)
        if r.returncode != 0:
            raise DeviceError(f"make in {d} failed (exit {r.returncode}):\n{out[-1]}")
        if not quiet:
            print(out[-1], end="", flush=True)
    return {"board": str(BOARD), "elf": str(FIRMWARE_ELF), "vectors_elf": str(VECTORS_ELF),
            "output": "".join(out)}


def board_command(device, excitation, *, elf: str | None = None, realtime: bool = False,
                  report: str | None = None, link: str | None = None,
                  wait_ms: float | None = None, duration: float | None = None) -> list[str]:
    """The ``hapkit_board`` command line for a scene's device and excitation.

    Parameters
    ----------
    device : hapsim.scene.Device
        ``mass`` [kg], ``friction`` b0 [N s/m] and ``coulomb`` [N] become the handle's
        physics (``delay``, ``hold`` and ``force_limit`` are the firmware's own).
    excitation : hapsim.scene.Excitation
        ``x0`` [m] and ``v0`` [m/s]: where the hand places the handle at each CONFIG; an
        ``impulse`` (force [N], start [s], duration [s]) becomes the hand's push.
    elf : str, optional
        Firmware ELF (default: the built ``hapkit.elf``).
    realtime : bool
        Lock the emulated clock to the wall clock (default: as fast as the host answers).
    report, link : str, optional
        JSON report file written on exit; symbolic link kept to the pty.
    wait_ms, duration : float, optional
        Longest wait for the host per STATE [ms]; emulated time to run [s].

    Returns
    -------
    list of str
        argv of the board program.
    """
    cmd = [str(BOARD), elf or str(FIRMWARE_ELF),
           "--mass", repr(float(device.mass)), "--friction", repr(float(device.friction)),
           "--coulomb", repr(float(getattr(device, "coulomb", 0.0) or 0.0)),
           "--x0", repr(float(excitation.x0 or 0.0)),
           "--v0", repr(float(excitation.v0 or 0.0))]
    imp = getattr(excitation, "impulse", None)
    if imp is not None:
        cmd += ["--hand-force", repr(float(imp.force)), "--hand-start", repr(float(imp.start)),
                "--hand-duration", repr(float(imp.duration))]
    if realtime:
        cmd.append("--realtime")
    if report:
        cmd += ["--report", report]
    if link:
        cmd += ["--link", link]
    if wait_ms is not None:
        cmd += ["--wait-ms", repr(float(wait_ms))]
    if duration is not None and math.isfinite(duration):
        cmd += ["--duration", repr(float(duration))]
    return cmd


# ---------------------------------------------------------------------------- the bound

def quantiser_gain(a: float) -> float:
    """Describing function of a mid-tread (round-to-nearest) quantiser of unit step.

    For an input ``a sin(wt)`` the first harmonic of the output is ``N(a) a sin(wt)`` with
    ``N(a) = 4 / (pi a) * sum_{i=1..n} sqrt(1 - ((2 i - 1) / (2 a))^2)``,
    ``n = floor(a + 1/2)`` (0 below half a step): Gelb & Vander Velde, *Multiple-Input
    Describing Functions and Nonlinear System Design* (1968), the quantiser entry of their
    table of describing functions.

    Parameters
    ----------
    a : float
        Input amplitude in quantiser steps, >= 0.

    Returns
    -------
    float
        N(a), -> 1 as a grows.
    """
    n = int(math.floor(a + 0.5))
    if n <= 0:
        return 0.0
    s = 0.0
    for i in range(1, n + 1):
        u = (2 * i - 1) / (2.0 * a)
        s += math.sqrt(max(0.0, 1.0 - u * u))
    return 4.0 / (math.pi * a) * s


def _max_gain_error(lo: float, hi: float, points: int = 4000) -> float:
    """max |N(a) - 1| over amplitudes a in [lo, hi] steps (dense grid)."""
    import numpy as np
    return max(abs(quantiser_gain(float(a)) - 1.0) for a in np.linspace(lo, hi, points))


def quantisation_bound(loop, K: float, B: float, x0: float, t_fit: float, q_x: float,
                       q_f: float, n_samples: int, sigmas: float = 4.0) -> dict:
    """How far the ADC and PWM quantisation may move the felt (k, b) from the THS
    prediction, derived from the two quantisers (nothing fitted).

    Two effects, added:

    1. **Loop gain.** Over the fit window the free response is a decaying sinusoid of
       amplitude A from ``x0`` down to ``A_min = x0 exp(-sigma t_fit)`` (sigma = b / 2m of
       the prediction). The position quantiser (step ``q_x``) passes its first harmonic
       with the gain N(A / q_x), the PWM quantiser (step ``q_f``) the force's with
       N(F / q_f), F >= K A (:func:`quantiser_gain`). So the virtual spring and damper act
       with K', B' in ``[K, B] (1 +- eps)``, ``eps = (1 + d_x)(1 + d_f) - 1``, ``d`` the
       largest |N - 1| over the window; the felt (k, b) lie within the THS map
       (:func:`hapsim.analysis.ths.render`) of the four corners (K (1 +- eps), B (1 +- eps)).
    2. **Observation.** The logged positions carry the quantisation error, uniform over one
       step: white noise of variance ``q_x^2 / 12`` (Widrow & Kollar, *Quantization Noise*,
       2008, ch. 4). A least-squares fit of ``A exp(-sigma t) cos(omega t + phi) + c`` to
       ``n_samples`` such samples has the covariance ``q_x^2 / 12 (J^T J)^-1`` (J: the
       model's Jacobian at the predicted parameters); ``sigmas`` standard deviations of
       k = m (omega^2 + sigma^2) and b = 2 m sigma are added.

    Parameters
    ----------
    loop : hapsim.analysis.loop.LoopModel
        The device side of the THS (m, b0, rate, delay, hold).
    K, B : float
        Virtual stiffness [N/m] and damping [N s/m].
    x0 : float
        Initial amplitude of the free response [m].
    t_fit : float
        Length of the fit window [s].
    q_x, q_f : float
        Position step [m] (HELLO.position_scale) and force step [N] (HELLO.force_scale).
    n_samples : int
        Samples in the fit window.
    sigmas : float
        Standard deviations of the observation noise term.

    Returns
    -------
    dict
        ``k``, ``b`` (predicted), ``dk``, ``db`` (the bounds), ``eps``, ``d_x``, ``d_f``,
        ``a_min`` [m], ``k_noise_sd``, ``b_noise_sd``.
    """
    import numpy as np

    from hapsim.analysis.ths import render

    pred = render(loop, K, B)
    m = loop.mass
    sig = pred.b / (2.0 * m)
    om = math.sqrt(max(pred.k / m - sig * sig, 0.0))
    a_min = x0 * math.exp(-sig * t_fit)
    d_x = _max_gain_error(a_min / q_x, x0 / q_x)
    d_f = _max_gain_error(K * a_min / q_f, K * x0 / q_f)
    eps = (1.0 + d_x) * (1.0 + d_f) - 1.0
    corners = [render(loop, K * (1 + u), B * (1 + v)) for u in (-eps, eps) for v in (-eps, eps)]
    dk_gain = max(abs(c.k - pred.k) for c in corners)
    db_gain = max(abs(c.b - pred.b) for c in corners)
    # observation noise through the least-squares fit
    t = np.arange(n_samples) / loop.rate_hz
    e = np.exp(-sig * t)
    J = np.column_stack([e * np.cos(om * t),                  # d/dA at A = x0, phi = 0
                         -x0 * e * np.sin(om * t),            # d/dphi
                         -x0 * t * e * np.cos(om * t),        # d/dsigma
                         -x0 * t * e * np.sin(om * t),        # d/domega
                         np.ones_like(t)])                    # d/dc
    cov = (q_x * q_x / 12.0) * np.linalg.inv(J.T @ J)
    gk = np.array([0, 0, 2 * m * sig, 2 * m * om, 0])          # k = m (om^2 + sig^2)
    gb = np.array([0, 0, 2 * m, 0, 0])                         # b = 2 m sig
    k_sd = float(math.sqrt(gk @ cov @ gk))
    b_sd = float(math.sqrt(gb @ cov @ gb))
    return {"k": float(pred.k), "b": float(pred.b), "dk": dk_gain + sigmas * k_sd,
            "db": db_gain + sigmas * b_sd, "eps": eps, "d_x": d_x, "d_f": d_f,
            "a_min": a_min, "k_noise_sd": k_sd, "b_noise_sd": b_sd}


def fit_free_response(position, period: float, mass: float, k_guess: float,
                      b_guess: float) -> dict:
    """Felt (k, b) of a logged free response: least squares on its dominant mode.

    Fits ``x(t) = A exp(-sigma t) cos(omega t + phi) + c`` (the THS's dominant pole pair
    ``s = -sigma +- i omega`` and an offset) and returns ``k = m |s|^2``, ``b = 2 m sigma``
    (the mapping of :func:`hapsim.daemon.runner.identify`). Unlike a matrix pencil of the
    full order, a fit of the one mode does not turn the sensor's quantisation into
    spurious poles.

    Parameters
    ----------
    position : ndarray, shape (n,)
        Positions [m], one per period, from the start of the free response.
    period : float
        Sample period T [s].
    mass : float
        m [kg].
    k_guess, b_guess : float
        Starting point [N/m], [N s/m] (the prediction).

    Returns
    -------
    dict
        ``k``, ``b``, ``rms_residual`` [m], ``samples``.
    """
    import numpy as np
    from scipy.optimize import least_squares

    y = np.asarray(position, dtype=float)
    t = np.arange(y.size) * period
    s0 = b_guess / (2 * mass)
    w0 = math.sqrt(max(k_guess / mass - s0 * s0, 1e-12))

    def res(p):
        a, ph, s, w, c = p
        return a * np.exp(-s * t) * np.cos(w * t + ph) + c - y

    sol = least_squares(res, [y[0], 0.0, s0, w0, 0.0], x_scale="jac")
    a, ph, s, w, c = sol.x
    return {"k": float(mass * (w * w + s * s)), "b": float(2 * mass * s),
            "rms_residual": float(np.sqrt(np.mean(sol.fun ** 2))), "samples": int(y.size)}
