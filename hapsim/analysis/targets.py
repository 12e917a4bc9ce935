"""Felt targets of a scene: calibrate every ``target: {k, b}`` link for its device.

The one place where a scene's targets become virtual (K, B); ``hapsim run``, ``hapsim
check`` and the bench all go through :func:`calibrate_targets` / :func:`apply_targets`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hapsim.analysis.loop import LoopModel
from hapsim.analysis.ths import CalibrationResult, calibrate
from hapsim.errors import ConfigError, UnrenderableTargetError

__all__ = ["TargetCalibration", "calibrate_targets", "apply_targets"]


@dataclass(frozen=True)
class TargetCalibration:
    """The calibration of one ``target`` link.

    Parameters
    ----------
    link : str
        Link name.
    line : int
        Line of the link in the scene file (0 when unknown).
    k : float
        Felt stiffness asked for [N/m].
    b : float
        Felt damping asked for [N s/m] (whole THS damping, real friction included).
    mass : float
        Device mass m the target oscillator is felt with [kg].
    result : CalibrationResult
        The analysis's answer: (K, B), renderability and reason.
    """

    link: str
    line: int
    k: float
    b: float
    mass: float
    result: CalibrationResult

    @property
    def renderable(self) -> bool:
        """Whether the target is rendered with every other pole better damped."""
        return bool(self.result.renderable)

    def to_dict(self) -> dict:
        """Plain-data form of the calibration.

        Returns
        -------
        dict
            ``link``, ``k`` [N/m], ``b`` [N s/m], ``K`` [N/m], ``B`` [N s/m],
            ``renderable``, ``reason``, and the target's ``f0_hz`` = ``sqrt(k/m)/(2 pi)``
            [Hz] and ``damping_ratio`` = ``b / (2 sqrt(k m))`` [-] (``m``: device mass).
        """
        res = self.result
        return {"link": self.link, "k": float(self.k), "b": float(self.b), "K": float(res.K),
                "B": float(res.B), "renderable": bool(res.renderable), "reason": res.reason,
                "f0_hz": math.sqrt(self.k / self.mass) / (2 * math.pi),
                "damping_ratio": self.b / (2 * math.sqrt(self.k) * math.sqrt(self.mass))}


def calibrate_targets(scene) -> list[TargetCalibration]:
    """Calibrate every uncalibrated ``target`` link of a scene at its rate.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene; targets are only allowed on a spring_damper between the port and a
        ground (the scene validator enforces it).

    Returns
    -------
    list of TargetCalibration
        One per target, in file order (empty when the scene has none).

    Raises
    ------
    ConfigError
        When the scene has targets but no device section.

    Notes
    -----
    Each target is the reference oscillator ``m s^2 + b s + k = 0`` of the device mass; the
    virtual (K, B) solve ``P K + Q B + R = 0`` at its poles (Florens, Voda & Urma eq. 1,
    docs/design.md, 'The forward map'), see :func:`hapsim.analysis.calibrate`.
    """
    targets = scene.unresolved_targets
    if not targets:
        return []
    if scene.device is None:
        raise ConfigError("target links need a device section to be calibrated",
                          file=scene.path, key="device")
    loop = LoopModel.from_device(scene.device, scene.rate_hz)
    return [TargetCalibration(lk.name, lk.line, float(lk.target[0]), float(lk.target[1]),
                              float(loop.mass), calibrate(loop, *lk.target))
            for lk in targets]


def apply_targets(scene):
    """Calibrate every target and write the (K, B) into the scene, refusing the impossible.

    Parameters
    ----------
    scene : hapsim.scene.Scene
        Validated scene.

    Returns
    -------
    scene : hapsim.scene.Scene
        The scene with every target link's stiffness and damping set.
    calibrations : list of TargetCalibration
        What was done, one per target.

    Raises
    ------
    UnrenderableTargetError
        When a target is not renderable with this device and rate (a ConfigError naming
        the file, the line and ``links.NAME.target``, with the analysis's reason).
    ConfigError
        When the scene has targets but no device section.
    """
    cals = calibrate_targets(scene)
    for c in cals:
        res = c.result
        if not c.renderable:
            rho = res.spectral_radius
            raise UnrenderableTargetError(
                f"target k = {c.k:g} N/m, b = {c.b:g} N s/m is not renderable with this device "
                f"at {scene.rate_hz:g} Hz: {res.reason}",
                file=scene.path, line=c.line or None, key=f"links.{c.link}.target",
                spectral_radius=rho if math.isfinite(rho) else None)
        scene = scene.with_link(c.link, stiffness=res.K, damping=res.B)
    return scene, cals
