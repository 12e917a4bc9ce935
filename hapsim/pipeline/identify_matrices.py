"""``hapsim identify --mock-scene SCENE --lockstep`` of a 2-D or 3-D scene: the device's
mass and friction matrices and its delay, identified from a record of its own excitation
(:func:`hapsim.analysis.device_matrices.fit_device_matrices`).

The device is the scene's, stepped in lockstep in process: a pantograph's or a delta's
joint-space dynamics with its kinematics to second order about the operating point
(:class:`hapsim.joint_device.LocalJointDeviceND`: the configuration-dependent inertia, the
velocity-product terms), a Cartesian device's exact zero-order hold; its delay is a FIFO
of whole periods. Nothing of it is read by the identification but its positions: the
excitation is designed from a probe, as the 1-D identification's (issue 29 item 4):

1. **Probe.** A force of 1/20 of ``force_limit`` along each axis in turn for
   ``PROBE_S``, then its opposite for as long (the velocity taken back); the largest
   displacement gives each axis's mass to within a factor of a few
   (``m ~ f t^2 / (2 |x|)``, the delay and friction ignored).
2. **Excitation.** A centring spring and damper on the readings, ``Kc = m_min (2 pi
   f_c)^2`` with ``f_c`` a hundredth of the rate (far inside any stability limit of a
   loop with up to ``max_delay`` periods of delay: ``Kc T^2 / m`` ~ 4e-3), critically
   damped for the largest mass estimate, plus a random force per axis held for 5-30
   periods, its amplitude the smaller of half the force limit and what moves the handle
   a third of the envelope.
3. **Safety.** The handle beyond the envelope stops the excitation (zero force) and the
   record is refused; the forces are clipped to the limit.
4. **Two amplitudes.** The same excitation again at a third of the amplitude: the fit's
   error from the device's nonlinearity (its kinematics) is first order in the motion, so
   the two fits' difference estimates it (Richardson extrapolation): the interval is
   twice that estimate, and the value is the smaller record's.

Over a port in real time this is not built: the refusal says so.
"""

from __future__ import annotations

import math

import numpy as np

from hapsim.errors import ConfigError, IdentificationError

__all__ = ["PROBE_S", "identify_matrices_lockstep"]

#: Length of each probe force [s].
PROBE_S = 0.01


class _Device:
    """The scene's device in lockstep: ``step(F)`` writes a force, the device holds it
    ``delay`` periods later; ``position()`` is the handle's displacement from rest [m]."""

    def __init__(self, scene) -> None:
        dev = scene.device
        self.n = scene.dimension
        self.fifo = [np.zeros(self.n) for _ in range(int(dev.delay))]
        if dev.kind in ("pantograph", "delta"):
            from hapsim.joint_device import LocalJointDeviceND
            self.joint = LocalJointDeviceND(scene, np.zeros(self.n), np.zeros(self.n))
            self.rest = self.joint.position().copy()
        else:
            from hapsim.analysis.ths.holds import zoh_blocks
            self.joint = None
            self.Ad, self.Bd = zoh_blocks(dev.mass, dev.friction, scene.period)
            self.s = np.zeros(2 * self.n)

    def position(self) -> np.ndarray:
        if self.joint is not None:
            return self.joint.position() - self.rest
        return self.s[:self.n].copy()

    def step(self, F) -> None:
        self.fifo.append(np.asarray(F, float).copy())
        u = self.fifo.pop(0)
        if self.joint is not None:
            self.joint.step(u)
        else:
            self.s = self.Ad @ self.s + self.Bd @ u


def identify_matrices_lockstep(scene, *, force_limit: float = 2.0, envelope: float = 0.01,
                               duration: float = 4.0, max_delay: int = 20, seed: int = 0,
                               progress=None) -> dict:
    """Identify a 2-D or 3-D scene's device in lockstep (module notes).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        A scene with a device (its own rate is the loop's).
    force_limit : float, optional
        Largest force [N] along any axis.
    envelope : float, optional
        Largest distance of the handle from rest [m].
    duration : float, optional
        Excitation length [s].
    max_delay : int, optional
        Largest delay searched [periods].
    seed : int, optional
        The random forces' seed.
    progress : callable, optional
        ``progress(done, total)`` every tenth of the excitation.

    Returns
    -------
    dict
        Of the record at a third of the amplitude: ``fit``
        (:class:`hapsim.analysis.device_matrices.DeviceMatrices`), ``samples``,
        ``excursion`` (the handle's largest distance from rest [m]), ``largest_force``
        [N], ``probe_mass`` (the probe's estimate per axis [kg]), ``centring`` (``Kc``
        [N/m], ``Bc`` [N s/m]), ``amplitude`` [N]; ``mass_half_width`` [kg] and
        ``friction_half_width`` [N s/m], one for every entry of each matrix (twice the
        Richardson estimate of the linearisation's error from the two amplitudes, plus
        ten of the fit's largest standard error); and
        ``large``, the same of the record at the full amplitude.

    Raises
    ------
    ConfigError
        A scene without a device, or with a sub-sample delay (whole periods only here);
        non-positive limits.
    IdentificationError
        The handle left the envelope or the probe did not move it (a force limit too small
        to move it within the probe), or the record does not determine the device.
    """
    dev = scene.device
    if dev is None:
        raise ConfigError("the scene has no device section", file=scene.path, key="device")
    if float(dev.delay) % 1:
        raise ConfigError(f"a sub-sample delay ({float(dev.delay):g} periods): identifying "
                          "a 2-D or 3-D device takes whole periods", file=scene.path,
                          key="device.delay")
    if not (force_limit > 0 and envelope > 0 and duration > 0):
        raise ConfigError("force limit, envelope and duration must be positive",
                          key="--force-limit")
    big = _record(scene, force_limit, envelope, duration, max_delay, seed, progress, 0)
    small = _record(scene, force_limit, envelope, duration, max_delay, seed, progress, 1,
                    scale=1.0 / 3.0)
    fb, fs = big["fit"], small["fit"]
    if fb.delay != fs.delay:
        raise IdentificationError(f"the two records disagree on the delay ({fb.delay} and "
                                  f"{fs.delay} periods): the device is not the linear "
                                  "model (a longer --duration, a smaller --envelope)")
    # Richardson on the amplitude: the linearisation's error is first order in it, so the
    # small record's is ~(small - big) / (3 - 1); the interval is twice that, the largest
    # entry's for the whole matrix (entry by entry it failed, up to 2.1 times, in 3 of 24
    # records; over the matrix the error was at most 0.68 of this half-width over 48
    # records of the pantograph and the delta at envelopes of 3-20 mm, seeds 0-7), plus
    # ten of the small record's largest standard error (its rounding on a linear device:
    # the error was at most 3.1 of it over 60 random linear devices of 1-3 axes,
    # tests/test_identify_matrices.py)
    dm = float(np.abs(fs.mass - fb.mass).max()) + 10 * float(fs.mass_se.max())
    db = float(np.abs(fs.friction - fb.friction).max()) + 10 * float(fs.friction_se.max())
    return {**small, "mass_half_width": dm, "friction_half_width": db, "large": big}


def _record(scene, force_limit, envelope, duration, max_delay, seed, progress, part,
            scale: float = 1.0) -> dict:
    """One probe, excitation and fit; the excitation's amplitude times ``scale``."""
    from hapsim.analysis.device_matrices import fit_device_matrices
    n, T = scene.dimension, scene.period
    rng = np.random.default_rng(seed)
    d = _Device(scene)
    xs, Fs = [], []

    def tick(F):
        x = d.position()
        if not np.all(np.isfinite(x)) or np.linalg.norm(x) > envelope:
            d.step(np.zeros(n))
            raise IdentificationError(
                f"safety: the handle went {np.linalg.norm(x):.4g} m from rest, beyond the "
                f"envelope {envelope:g} m: a smaller --force-limit or a larger --envelope")
        xs.append(x)
        Fs.append(np.asarray(F, float))
        d.step(F)
        return x

    # 1. the probe: f along each axis, then -f as long, then still
    f = force_limit / 20.0
    P = max(2, round(PROBE_S / T))
    m_est = np.empty(n)
    for i in range(n):
        e = np.zeros(n)
        e[i] = f
        x0 = d.position()
        peak = 0.0
        for F in [e] * P + [-e] * P + [np.zeros(n)] * (max_delay + P):
            peak = max(peak, float(np.linalg.norm(tick(F) - x0)))
        if not peak > 0:
            raise IdentificationError(f"the probe's {f:g} N along axis {i + 1} did not move "
                                      "the handle: it is blocked or held")
        m_est[i] = f * (P * T) ** 2 / (2.0 * peak)
    # 2. the excitation: a centring spring-damper on the readings and held random forces
    # (the record is the excitation's alone: the probe's force is the same in both
    # records, and what is fitted must scale with the amplitude for the interval)
    del xs[:], Fs[:]
    wc = 2 * math.pi * scene.rate_hz / 100.0
    Kc = float(np.min(m_est)) * wc * wc
    Bc = 2.0 * math.sqrt(Kc * float(np.max(m_est)))
    A = min(force_limit / 2.0, Kc * envelope / 3.0) * scale
    N = max(1, round(duration / T))
    w, hold = np.zeros(n), 0
    prev = d.position()
    for k in range(N):
        if hold == 0:
            w, hold = rng.uniform(-A, A, n), int(rng.integers(5, 31))
        hold -= 1
        x = d.position()
        F = np.clip(-Kc * x - Bc * (x - prev) / T + w, -force_limit, force_limit)
        prev = x
        tick(F)
        if progress is not None and (k + 1) % max(1, N // 10) == 0:
            progress(part * N + k + 1, 2 * N)
    for _ in range(max_delay + 1):               # zero force, the record closed
        d.step(np.zeros(n))
    X, F = np.array(xs), np.array(Fs)
    try:
        fit = fit_device_matrices(X, F, T, max_delay=max_delay)
    except ConfigError as exc:
        # (what makes a record carry more: longer, or moved further above its noise)
        raise IdentificationError(
            f"{exc} ({len(X)} samples of {T * len(X):g} s: a longer --duration, or a "
            f"larger --envelope or --force-limit, gives the fit more to go on)") from None
    return {"fit": fit, "samples": len(X),
            "excursion": float(np.max(np.linalg.norm(X, axis=1))),
            "largest_force": float(np.max(np.abs(F))), "probe_mass": m_est.tolist(),
            "centring": [Kc, Bc], "amplitude": A}
