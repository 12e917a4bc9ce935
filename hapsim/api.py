"""hapsim's Python API: the commands as functions that return typed results.

Flat, in python-control's style: load a scene, then ask what it feels like::

    import hapsim
    scene = hapsim.load_scene("configs/wall.yaml")
    r = hapsim.check(scene)          # CheckReport: r.k [N/m], r.b [N s/m], r.stable, ...
    fig = r.plot()                   # the closed-loop poles (needs the plot extra)

Each function returns a frozen dataclass whose fields are exactly the keys of the matching
command's ``--json`` object (``to_dict()`` gives that object back), so what a script reads
is what a program reading ``hapsim COMMAND --json`` reads:

============================  ==========================  ===========================
function                      result                      command
============================  ==========================  ===========================
:func:`check`                 :class:`CheckReport`        ``hapsim check SCENE``
:func:`render`                :class:`RenderReport`       ``hapsim render``
:func:`calibrate`             :class:`CalibrateReport`    ``hapsim calibrate``
:func:`stability`             :class:`StabilityReport`    ``hapsim stability``
:func:`family`                :class:`FamilyReport`       ``hapsim family SCENE``
:func:`identify`              :class:`IdentifyReport`     ``hapsim identify``
:func:`run`                   :class:`RunReport`          ``hapsim run SCENE``
:func:`play`                  :class:`PlayReport`,        ``hapsim play SCENE`` (any
                              :class:`PlayReportND`       dimension)
:func:`check_nd`              :class:`CheckReportND`      ``hapsim check SCENE`` (n-D)
:func:`modes_nd`              :class:`ModesReportND`      ``hapsim check SCENE`` (n-D,
                                                          no port)
:func:`run_nd`                :class:`RunReportND`        ``hapsim run SCENE
                                                          --lockstep`` (n-D)
============================  ==========================  ===========================

A 2-D or 3-D scene (``dimension: 2`` or ``3``) is read by :func:`load_scene` too (a
:class:`~hapsim.scene_nd.SceneND`, whose ``dimension`` says which) or
:func:`load_scene_nd`; the 1-D functions refuse it naming the n-D one.

``render``, ``calibrate`` and ``stability`` take a :class:`LoopModel` (the real side of
the loop: mass, friction, rate, delay, hold). Errors are those of the commands: a
:class:`~hapsim.errors.ConfigError` names the file, line and key; an
:class:`~hapsim.errors.UnstableConfigError` is a negative verdict. Compute and drawing are
apart: the ``plot()`` methods call :mod:`hapsim.plots`, the only module importing
matplotlib (the ``plot`` extra).
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import TYPE_CHECKING, Any

import numpy as np

from hapsim.errors import ConfigError, HapsimError, IdentificationError
from hapsim.option_values import check_values
from hapsim.outputs import json_safe
from hapsim.results import Report

if TYPE_CHECKING:     # bound for readers and checkers; at run time by __getattr__
    from hapsim.analysis.loop import LoopModel
    from hapsim.api_nd import (CheckReportND, ModesReportND, PlayReportND, RunReportND,
                               check_nd, load_scene_nd, modes_nd, run_nd, run_report_nd)

__all__ = ["load_scene", "LoopModel", "check", "render", "calibrate", "stability", "family",
           "identify", "calibrate_scale", "run", "play", "excite_and_fit", "known_digits",
           "known_decimals", "run_options", "CheckReport", "RenderReport", "CalibrateReport",
           "StabilityReport", "FamilyReport", "IdentifyReport", "RunReport", "PlayReport",
           "PLAY_OPTIONS", "Report", "load_scene_nd", "check_nd", "modes_nd", "run_nd",
           "run_report_nd", "CheckReportND", "ModesReportND", "RunReportND", "PlayReportND"]


#: Public names provided on first use (PEP 562), with the module that defines them:
#: importing the analysis costs more than the rest of this module together.
_LAZY = {"LoopModel": "hapsim.analysis.loop",
         # the 2-D and 3-D API (its own module: hapsim.api_nd)
         "load_scene_nd": "hapsim.api_nd",
         "check_nd": "hapsim.api_nd",
         "modes_nd": "hapsim.api_nd",
         "run_nd": "hapsim.api_nd",
         "run_report_nd": "hapsim.api_nd",
         "CheckReportND": "hapsim.api_nd",
         "ModesReportND": "hapsim.api_nd",
         "RunReportND": "hapsim.api_nd",
         "PlayReportND": "hapsim.api_nd"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value            # once: the next reads find it directly
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


def load_scene(path: str | os.PathLike):
    """Read and validate a scene file, in the dimension its ``dimension`` key declares.

    Parameters
    ----------
    path : str or path-like
        A YAML scene (docs/scenes.md; ``dimension: 2`` or ``3``: docs/dimensions.md).

    Returns
    -------
    hapsim.scene.Scene or hapsim.scene_nd.SceneND
        A :class:`~hapsim.scene.Scene` for a 1-D scene (no ``dimension`` key, or 1: as
        before), a :class:`~hapsim.scene_nd.SceneND` for a 2-D or 3-D one, whose
        ``dimension`` says which (the functions taking it: :func:`check_nd`,
        :func:`modes_nd`, :func:`run_nd`).

    Raises
    ------
    ConfigError
        An unreadable or invalid file: the message names the file, the line and the key,
        with the valid keys or choices.
    """
    from hapsim.scene_nd import scene_dimension
    p = os.fspath(path)
    if scene_dimension(p) != 1:
        from hapsim.scene_nd import load_scene_nd as _load_nd
        return _load_nd(p)
    from hapsim.scene import load_scene as _load
    return _load(p)


def _draw(report, draw, path_or_ax):
    """``draw(report, ax=...)`` into new axes (None), given axes, or a figure file (a path:
    checked first, written by :func:`hapsim.plots.save_figure`). Returns the figure."""
    from hapsim.plots import check_figure_path, save_figure
    if isinstance(path_or_ax, (str, os.PathLike)):
        path = os.fspath(path_or_ax)
        check_figure_path(path, "plot")
        fig = draw(report)
        save_figure(fig, path)
        return fig
    return draw(report, ax=path_or_ax)


def _scene(scene, what: str, why: str):
    """A 1-D Scene from a Scene or a path; a 2-D or 3-D one is refused, naming the
    function ``what`` and ``why`` (a ConfigError keyed ``dimension``)."""
    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)
    if getattr(scene, "dimension", 1) != 1:
        raise ConfigError(f"a {scene.dimension}-D scene: hapsim.{what} takes dimension 1 "
                          f"({why})", file=getattr(scene, "path", None), key="dimension")
    return scene


# ---------------------------------------------------------------------------- check
@dataclasses.dataclass(frozen=True)
class CheckReport(Report):
    """What ``hapsim check SCENE --json`` says: stability and the (k, b) felt at the port.

    Attributes
    ----------
    scene : str
        The scene's path.
    verdict : {"stable", "unstable"}
    rate_hz : float
        Device rate [Hz].
    device : dict or None
        ``mass`` [kg], ``friction`` [N s/m], ``delay`` [samples], ``hold``, ``correction``.
    calibrations : list of dict
        The (K, B) calibrated for each ``target`` link.
    stable, marginal : bool
        Spectral radius < 1 (marginal: within 1e-9 of 1, counted stable).
    spectral_radius : float
        Of the closed-loop state matrix.
    has_port : bool
    period : float
        T [s].
    reference_mass : float
        m [kg] the felt k, b are expressed with.
    integrator : str
    rendered : dict or None
        The felt mode: ``k`` [N/m], ``b`` [N s/m], ``f0_hz``, ``damping_ratio``, ``z_re``,
        ``z_im``, ``kind``, ``participation``.
    modes : list of dict
        Every mode, least damped first (same keys).
    eigenvalues : list of [float, float]
        Closed-loop eigenvalues z (real, imaginary).
    state_names : list of str
    calibrated : dict
        ``{link: [K, B]}``.
    static_k : float or None
        Stiffness a slow push feels at the port [N/m] (virtual masses at rest;
        :func:`hapsim.analysis.network.static_stiffness`).

    Other attributes (not in ``--json``): ``analysis`` (the
    :class:`~hapsim.analysis.scene_check.SceneCheck`), ``calibrated_scene`` (the scene
    with its targets calibrated), ``calibrations_made`` (their calibration results).
    """

    scene: str
    verdict: str
    rate_hz: float
    device: dict | None
    calibrations: list
    stable: bool
    marginal: bool
    spectral_radius: float
    has_port: bool
    period: float
    reference_mass: float
    integrator: str
    rendered: dict | None
    modes: list
    eigenvalues: list
    state_names: list
    calibrated: dict
    static_k: float | None

    @property
    def k(self) -> float:
        """Felt stiffness k [N/m] (NaN when nothing rings at the port)."""
        return _get(self.rendered, "k")

    @property
    def b(self) -> float:
        """Felt damping b [N s/m] (NaN when nothing rings at the port)."""
        return _get(self.rendered, "b")

    def plot(self, path_or_ax=None):
        """The closed-loop poles in the z-plane, the felt pair marked
        (:func:`hapsim.plots.plot_poles`).

        Parameters
        ----------
        path_or_ax : str, path-like or matplotlib.axes.Axes, optional
            A figure file to write (its extension picks the format), axes to draw into,
            or None (a new figure).

        Returns
        -------
        matplotlib.figure.Figure

        Raises
        ------
        ConfigError
            matplotlib missing (the hint names the plot extra), or a path that cannot be
            written (key ``plot``).
        """
        from hapsim.plots import plot_poles
        return _draw(self, plot_poles, path_or_ax)


def _get(d, key) -> float:
    v = None if d is None else d.get(key)
    return math.nan if v is None else float(v)


def check(scene):
    """Check a scene: stability of its closed loop and what is felt at its port.

    A scene of any dimension: a 2-D or 3-D one with a port gives its felt matrices
    (:func:`hapsim.api_nd.check_nd`, a :class:`CheckReportND`), one without a port its
    modes (:func:`hapsim.api_nd.modes_nd`, a :class:`ModesReportND`), as ``hapsim check``
    does.

    Parameters
    ----------
    scene : hapsim.scene.Scene, hapsim.scene_nd.SceneND or str
        A loaded scene, or the path of one.

    Returns
    -------
    CheckReport, CheckReportND or ModesReportND

    Raises
    ------
    ConfigError
        An invalid scene, or one too large to analyse.
    UnrenderableTargetError
        A ``target`` link the device cannot render (a negative verdict).

    Notes
    -----
    The eigenvalues of the closed-loop state matrix of the temporary hybrid system
    (Florens, Voda & Urma; docs/design.md, 'The THS'); the felt (k, b) are those of the
    least damped pole pair seen at the port, ``k = m |s|^2``, ``b = -2 m Re(s)``.
    """
    from hapsim.analysis.network import check_size, static_stiffness
    from hapsim.analysis.scene_check import check_scene
    from hapsim.analysis.targets import apply_targets

    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)               # in the dimension it declares
    if getattr(scene, "dimension", 1) != 1:
        from hapsim.api_nd import check_nd, modes_nd
        return check_nd(scene) if scene.port is not None else modes_nd(scene)
    scene, cals = apply_targets(scene)
    check_size(scene)
    chk = check_scene(scene)
    dev = scene.device
    d = {"scene": scene.path, "verdict": "stable" if chk.stable else "unstable",
         "rate_hz": scene.rate_hz,
         "device": None if dev is None else {
             "mass": dev.mass, "friction": dev.friction, "delay": dev.delay,
             "hold": dev.hold, "correction": getattr(dev, "correction", None)},
         "calibrations": [c.to_dict() for c in cals], **chk.to_dict(),
         "static_k": static_stiffness(scene) if chk.has_port else None}
    return CheckReport.from_dict(d, analysis=chk, calibrated_scene=scene, calibrations_made=cals)


# ---------------------------------------------------------------------------- a loop
@dataclasses.dataclass(frozen=True)
class RenderReport(Report):
    """What ``hapsim render --json`` says: the (k, b) felt for a virtual (K, B).

    Attributes
    ----------
    K, B : float
        Virtual stiffness [N/m] and damping [N s/m] simulated.
    k, b : float
        Felt stiffness [N/m] and damping [N s/m] (b includes the device's friction).
    f0_hz, damping_ratio : float
        Of the felt pole pair.
    stable, marginal : bool
    spectral_radius : float
    rendered : dict
        The felt mode (as :attr:`CheckReport.rendered`).
    modes : list of dict
    note : str or None
    loop : dict
        The :class:`LoopModel` (mass, friction, rate_hz, delay, hold).

    Other attributes: ``analysis``, the :class:`~hapsim.analysis.ths.RenderResult`.
    """

    K: float
    B: float
    k: float
    b: float
    f0_hz: float
    damping_ratio: float
    stable: bool
    marginal: bool
    spectral_radius: float
    rendered: dict | None
    modes: list
    note: str | None
    loop: dict

    @property
    def eigenvalues(self) -> list:
        """Closed-loop poles as [re, im] (from :attr:`modes`)."""
        return [[m["z_re"], m["z_im"]] for m in self.modes]

    def plot(self, path_or_ax=None):
        """The closed-loop poles in the z-plane (:func:`hapsim.plots.plot_poles`).

        Parameters
        ----------
        path_or_ax : str, path-like or matplotlib.axes.Axes, optional
            A figure file to write, axes to draw into, or None (a new figure).

        Returns
        -------
        matplotlib.figure.Figure

        Raises
        ------
        ConfigError
            matplotlib missing, or a path that cannot be written (key ``plot``).
        """
        from hapsim.plots import plot_poles
        return _draw(self, plot_poles, path_or_ax)


def render(loop, K: float, B: float = 0.0) -> RenderReport:
    """The stiffness k and damping b felt for a virtual spring K and damper B.

    Parameters
    ----------
    loop : LoopModel
        The real side: ``mass`` [kg], ``friction`` [N s/m], ``rate_hz`` [Hz], ``delay``
        [samples], ``hold`` (``"zoh"`` or ``"ideal"``).
    K : float
        Virtual stiffness [N/m].
    B : float
        Virtual damping [N s/m].

    Returns
    -------
    RenderReport

    Raises
    ------
    ConfigError
        A non-finite K or B (keyed ``--K`` / ``--B``: the declaration and message of
        ``hapsim render``'s, :data:`hapsim.option_values.API_OPTIONS`).

    Notes
    -----
    :func:`hapsim.analysis.ths.render`: the least damped closed-loop pole pair z,
    ``s = ln(z) / T``, ``k = m |s|^2``, ``b = -2 m Re(s)`` (Florens, Voda & Urma).
    """
    from hapsim.analysis.ths import render as _render
    check_values("render", K=K, B=B)
    r = _render(loop, K, B)
    return RenderReport.from_dict({**r.to_dict(), "loop": loop.to_dict()}, analysis=r)


@dataclasses.dataclass(frozen=True)
class CalibrateReport(Report):
    """What ``hapsim calibrate --json`` says: the (K, B) that render a felt (k, b).

    Attributes
    ----------
    k, b : float
        The target felt stiffness [N/m] and damping [N s/m].
    K, B : float
        The virtual stiffness [N/m] and damping [N s/m] to simulate.
    renderable : bool
    reason : str
    spectral_radius : float
    target : dict
        The target oscillator (``f0_hz``, ``damping_ratio``, ...).
    modes : list of dict
    loop : dict

    Other attributes: ``analysis``, the :class:`~hapsim.analysis.ths.CalibrationResult`.
    """

    k: float
    b: float
    K: float
    B: float
    renderable: bool
    reason: str
    spectral_radius: float
    target: dict
    modes: list
    loop: dict


def calibrate(loop, k: float, b: float) -> CalibrateReport:
    """The virtual (K, B) that make the hand feel (k, b).

    Parameters
    ----------
    loop : LoopModel
    k : float
        Felt stiffness to render [N/m], > 0.
    b : float
        Felt damping to render [N s/m].

    Returns
    -------
    CalibrateReport
        ``renderable`` False (with the reason) when no stable (K, B) renders it.

    Raises
    ------
    ConfigError
        ``k <= 0`` or a non-finite target (keyed ``--k`` / ``--b``, as ``hapsim
        calibrate`` says it: :data:`hapsim.option_values.API_OPTIONS`).

    Notes
    -----
    :func:`hapsim.analysis.ths.calibrate`: the inverse of :func:`render`, solved for the
    pole pair of the target oscillator (Florens, Voda & Urma).
    """
    from hapsim.analysis.ths import calibrate as _calibrate
    check_values("calibrate", k=k, b=b)
    c = _calibrate(loop, k, b)
    return CalibrateReport.from_dict({**c.to_dict(), "loop": loop.to_dict()}, analysis=c)


@dataclasses.dataclass(frozen=True)
class StabilityReport(Report):
    """What ``hapsim stability --json`` says: the largest stable K for a damping B.

    Attributes
    ----------
    K_max : float or None
        Exact stability limit [N/m] (None when unbounded).
    K_max_method : str
        ``"certified"`` (proven in exact arithmetic: no crossing of ``|z| = 1`` below, a
        guaranteed bracket; :mod:`hapsim.analysis.limit_certificate`) or ``"sampled (N)"``
        (the scan of ``N`` points of the circle, not proven between them).
    K_max_interval : [float, float] or None
        The guaranteed bracket ``[K_lo, K_hi]`` [N/m] when certified (``[0, 0]``: no
        ``K > 0`` stable; ``[None, None]``: every ``K > 0`` proven stable), else None.
    K_max_certificate : str
        What was proven (certified) or why it could not be (sampled).
    B : float
        Virtual damping [N s/m].
    spectral_radius_at_K_max, spectral_radius_error : float or None
        The spectral radius there, to the digits double arithmetic knows, and its error.
    passivity_K, diolaiti_K, centred_difference_K : float
        Published limits [N/m]: Colgate & Schenkel 1997 (passivity, sufficient), Diolaiti
        et al. 2006 (first order in b0 T / m), the centred difference (ideal, d = 0).
    loop : dict
    """

    K_max: float | None
    K_max_method: str
    K_max_interval: list | None
    K_max_certificate: str
    B: float
    spectral_radius_at_K_max: float | None
    spectral_radius_error: float | None
    passivity_K: float
    diolaiti_K: float
    centred_difference_K: float
    loop: dict


def stability(loop, B: float = 0.0) -> StabilityReport:
    """The largest virtual stiffness K the loop keeps stable, for a damping B.

    Parameters
    ----------
    loop : LoopModel
    B : float
        Virtual damping [N s/m].

    Returns
    -------
    StabilityReport

    Raises
    ------
    ConfigError
        A non-finite B (keyed ``--B``, as ``hapsim stability`` says it:
        :data:`hapsim.option_values.API_OPTIONS`).

    Notes
    -----
    :func:`hapsim.analysis.ths.stability_limit` (the exact boundary of the THS, a scan of
    the unit circle), proven by :func:`hapsim.analysis.limit_certificate.certify_limit`
    where exact arithmetic can (the crossing condition as a polynomial in ``cos theta``,
    Sturm's theorem, the Schur-Cohn-Jury test), beside
    :func:`hapsim.analysis.ths.published_limits`.
    """
    from hapsim.analysis.limit_certificate import certify_limit
    from hapsim.analysis.loop import spectral_radius_known
    from hapsim.analysis.ths import circle_scan_points, published_limits, stability_limit
    check_values("stability", B=B)
    kmax = stability_limit(loop, B)
    cert = certify_limit(loop, B, kmax, circle_scan_points(loop))
    rho = err = None
    if math.isfinite(kmax):
        rho, err = spectral_radius_known(loop, kmax, B)
        rho = known_digits(rho, err)
    iv = None if cert.interval is None else [
        v if math.isfinite(v) else None for v in cert.interval]
    return StabilityReport.from_dict({
        "K_max": kmax if math.isfinite(kmax) else None, "K_max_method": cert.method,
        "K_max_interval": iv, "K_max_certificate": cert.note, "B": B,
        "spectral_radius_at_K_max": rho, "spectral_radius_error": err,
        **published_limits(loop, B), "loop": loop.to_dict()})


# ---------------------------------------------------------------------------- family
@dataclasses.dataclass(frozen=True)
class FamilyReport(Report):
    """What ``hapsim family SCENE --json`` says: a family of hands, robustly stable or not.

    Attributes
    ----------
    scene : str
    verdict : str
    correction : dict or None
    members, corners : int
    robust : bool
    robust_method : str
    certificate : dict or None
    unstable : int
    corners_stable : bool
    worst, first_unstable : dict or None
    felt : dict
        The spread of the felt (k, b) over the members.
    links : dict
    calibrated : dict
    consistency : dict or None
        Parallel links and a real arm spring against a virtual one (when there are two).
    family_calibrations : list or None
        The minimax calibration of each target link (``calibrate=True``).

    Other attributes: ``analysis``, the :class:`~hapsim.analysis.family.FamilyResult`.
    """

    _OPTIONAL = ("consistency", "family_calibrations")

    scene: str
    verdict: str
    correction: dict | None
    members: int
    corners: int
    robust: bool
    robust_method: str
    certificate: dict | None
    unstable: int
    corners_stable: bool
    worst: dict | None
    first_unstable: dict | None
    felt: dict
    links: dict
    calibrated: dict
    consistency: dict | None = None
    family_calibrations: list | None = None

    def plot(self, path: str | os.PathLike | None = None, title: str | None = None):
        """Felt (k, b) of every member, coloured by spectral radius, and the spectral radius
        against the moving mass (:func:`hapsim.plots.family.plot_family`).

        Parameters
        ----------
        path : str or path-like, optional
            A figure file to write (its extension picks the format; ``hapsim family
            --plot``); None: a new figure only.
        title : str, optional
            Default: the scene's path.

        Returns
        -------
        matplotlib.figure.Figure

        Raises
        ------
        ConfigError
            matplotlib missing (the hint names the plot extra), or a path that cannot be
            written (key ``plot``).
        """
        from hapsim.plots.family import plot_family

        def draw(report, ax=None):          # two panels: a figure of its own
            return plot_family(report.analysis, title=title or report.scene)
        return _draw(self, draw, path)


def family(scene, samples: int | None = None, *, grid: int = 9, seed: int = 0,
           certify: int = 4096, calibrate: bool = False,
           correction: dict | None = None) -> FamilyReport:
    """A family of hands (the scene's ``device.hand`` ranges): robust stability, the spread
    of what is felt, and optionally the minimax calibration of its target links.

    Parameters
    ----------
    scene : hapsim.scene.Scene or str
    samples : int, optional
        Random members beside the corners and the nominal one (default: a grid).
    grid : int
        Grid points per range (>= 2) when ``samples`` is None.
    seed : int
        Seed of the samples.
    certify : int
        Most boxes of the certificate between members (0: the sampled verdict only).
    calibrate : bool
        Calibrate each ``target`` link for the whole family.
    correction : dict, optional
        A ``device.correction`` mapping in place of the scene's.

    Returns
    -------
    FamilyReport

    Raises
    ------
    ConfigError
        An invalid scene or value (a value keyed by the flag of ``hapsim family``:
        :data:`hapsim.option_values.API_OPTIONS`); ``calibrate`` without a target link.

    Notes
    -----
    :func:`hapsim.analysis.family.family` (Florens, Voda & Urma Sec. 4: a family of THS).
    """
    from hapsim.analysis.family import family as _family
    from hapsim.analysis.hand import hand_stiffness

    check_values("family", samples=samples, grid=grid, seed=seed, certify=certify)
    scene = _scene(scene, "family", "there is no family of a 2-D or 3-D THS yet; "
                   "hapsim.check gives its felt matrices")
    if correction is not None:
        scene = dataclasses.replace(scene, device=dataclasses.replace(
            scene.device, correction=correction))
    res = _family(scene, samples, grid=grid, seed=seed, certify=certify)
    rep = res.to_dict()
    if len(res.links) + bool((hand_stiffness(res.members) > 0).any()) >= 2:
        from hapsim.analysis.family import consistency
        c = consistency(scene, mem=res.members, calibrated=res.calibrated)
        rep["consistency"] = {k: v for k, v in c.items()
                              if k not in ("k", "b", "k_sum", "b_sum", "k_real")}
    if calibrate:
        from hapsim.analysis.family import calibrate_family
        targets = [lk.name for lk in scene.links if lk.target is not None]
        if not targets:
            raise ConfigError("calibrate needs a link given as target {k, b}",
                              file=scene.path, key="links")
        rep["family_calibrations"] = [calibrate_family(scene, name, mem=res.members).to_dict()
                                      for name in targets]
    from hapsim.analysis.robust import ARITHMETIC
    if not res.robust:
        # an unstable member: its eigenvalues computed in floating point (robust module)
        verdict = f"not robustly stable (certified in {ARITHMETIC})"
    elif res.robust_method == "certified":
        verdict = f"robustly stable (certified in {ARITHMETIC})"
    else:
        verdict = f"robustly stable on the samples only ({res.robust_method})"
    return FamilyReport.from_dict({"scene": scene.path, "verdict": verdict,
                               "correction": getattr(scene.device, "correction", None),
                               **rep}, analysis=res)


# ---------------------------------------------------------------------------- devices
@dataclasses.dataclass(frozen=True)
class IdentifyReport(Report):
    """What ``hapsim identify --json`` says: a device's mass, friction, delay and hold.

    Attributes
    ----------
    device : dict
        The fit (:meth:`hapsim.analysis.device_fit.DeviceFit.to_dict`): each quantity with
        its confidence interval, ``explained``, the residual.
    loop : dict
        The excitation run (samples, stop reason, late, clamped, ...).
    hand : bool
        Whether a hand held the handle (then mass and friction are the THS's).
    out, plot : str or None
        The files the command wrote (None from the API).
    note : str or None

    Other attributes: ``fit`` (the :class:`~hapsim.analysis.device_fit.DeviceFit`) and
    ``record`` (the excitation's columns and loop facts). Its chart (``plot`` is the
    command's file field here): :func:`hapsim.plots.plot_identify` ``(report)``.
    """

    _OPTIONAL = ("note",)

    device: dict
    loop: dict
    hand: bool
    out: str | None
    plot: str | None
    note: str | None = None

    def device_yaml(self, force_limit: float = 2.0, driver=None) -> str:
        """The ``device:`` section for a scene or ``hapsim run --device`` (as ``--out``;
        ``driver``: the :class:`hapsim.drivers.base.Driver` whose protocol it names)."""
        from hapsim.device_file import device_yaml
        return device_yaml(self.fit, force_limit, hand=self.hand, driver=driver)


def identify(port: str | None = None, *, driver: str = "framed", baud: int = 115200,
             device=None, force_limit: float = 2.0, envelope: float = 0.01,
             duration: float = 4.0, rate_hz: float = 1000.0, max_delay: int = 20,
             lockstep: bool = False, seed: int = 0, hand: bool = False,
             transport: str | None = None, progress: bool = False,
             handle_signals: bool = False,
             driver_options: dict | None = None,
             mock_options: dict | None = None,
             travel: float | None = None) -> IdentifyReport:
    """Excite a device (or its mock) and identify its mass, friction, delay and hold.

    Parameters
    ----------
    port : str, optional
        Serial port of the device; None: the embedded mock of ``device``.
    driver : str
        Its protocol (:data:`hapsim.drivers.DRIVERS`).
    baud : int
    device : hapsim.scene.Device, optional
        What the mock models (default m = 0.1 kg, b0 = 0.5 N s/m, d = 1).
    force_limit : float
        Largest force sent [N].
    envelope : float
        Position envelope [m] around the start; beyond it the excitation stops.
    duration : float
        Excitation length [s].
    rate_hz : float
        Loop rate [Hz].
    max_delay : int
        Largest device delay tried [samples].
    lockstep : bool
        Lockstep embedded mock (deterministic).
    seed : int
    hand : bool
        A hand holds the handle (the result is the THS's mass and damping).
    transport : {"inprocess", "pty", "serial"}, optional
        ``"inprocess"``: the lockstep mock called directly (no child process); default
        ``"serial"`` with a port, else the embedded mock on a pseudo-terminal.
    progress : bool
        A progress bar on stderr when it is a terminal.
    handle_signals : bool
        Stop cleanly on SIGINT/SIGTERM (a library leaves them to its caller by default).
    driver_options : dict, optional
        The driver's device parameters (``device.protocol_options``, e.g. the FireFader's
        ``full_scale``); the mass and friction found are in the units they set.
    mock_options : dict, optional
        A driver mock's hardware (e.g. ``{"full_scale": 1.56}``: a fader other than the
        one ``driver_options`` describe); default the driver's own.
    travel : float, optional
        The FireFader's travel between its end stops [m] (its datasheet's): a sweep between
        the stops finds its position scale first (``loop.travel_sweep``; the
        record's ``protocol_options`` carry it).

    Returns
    -------
    IdentifyReport

    Raises
    ------
    ConfigError
        Bad values (keyed by the flag of ``hapsim identify``:
        :data:`hapsim.option_values.API_OPTIONS`), an unknown driver.
    IdentificationError
        A record too short or that the fit cannot explain.
    DeviceError, ProtocolError
        As :func:`run`.

    Notes
    -----
    :func:`hapsim.analysis.device_fit.fit_device`: least squares of the sampled plant
    (mass, friction, Coulomb friction, delay, hold) on the recorded positions and forces.
    """
    from hapsim.drivers import DRIVERS
    if driver not in DRIVERS:
        raise ConfigError(f"unknown driver {driver!r}; valid: {', '.join(DRIVERS)}",
                          key="driver")
    check_values("identify", baud=baud, force_limit=force_limit, envelope=envelope,
                 duration=duration, rate_hz=rate_hz, max_delay=max_delay, seed=seed)
    fit, rec = excite_and_fit(port=port, baud=baud, device=device, force_limit=force_limit,
                         envelope=envelope, duration=duration, rate_hz=rate_hz,
                         max_delay=max_delay, lockstep=lockstep, seed=seed,
                         driver=None if driver == "framed" else driver, progress=progress,
                         transport=transport, handle_signals=handle_signals,
                         driver_options=driver_options, mock_options=mock_options,
                         travel=travel)
    d = {"device": fit.to_dict(), "loop": rec["loop"], "hand": bool(hand), "out": None,
         "plot": None}
    if hand:
        d["note"] = "mass and friction are the THS's: hand + handle, for this grip"
    return IdentifyReport.from_dict(json_safe(d), fit=fit, record=rec)


def excite_and_fit(*, port=None, baud=115200, device=None, force_limit=2.0, envelope=0.01,
             duration=4.0, rate_hz=1000.0, max_delay=20, lockstep=False, seed=0,
             transport=None, progress=True, handle_signals=True, driver=None,
             driver_options=None, mock_options=None, travel=None):
    """Excite, record and fit: what ``hapsim identify`` and :func:`identify` run.

    Parameters
    ----------
    port, baud : str, int
        Device port (None: a mock of ``device``) and baud rate.
    device : hapsim.scene.Device, optional
        What the mock models.
    force_limit, envelope, duration, rate_hz, max_delay, lockstep, seed
        As the options of the same names ([N], [m], [s], [Hz], [samples]).
    transport : {"inprocess", "pty", "serial"}, optional
        As :func:`hapsim.pipeline.identify_run.record`.
    progress, handle_signals : bool
        Progress bar on a terminal; clean stop on SIGINT/SIGTERM.
    driver : str, optional
        Device protocol (:data:`hapsim.drivers.DRIVERS`); default hapsim's own.
    driver_options : dict, optional
        The driver's device parameters (``device.protocol_options``: e.g. the FireFader's
        ``full_scale``); the mass and friction found are in the units they set.
    mock_options : dict, optional
        The driver mock's hardware (:func:`hapsim.pipeline.identify_run.record`).
    travel : float, optional
        The FireFader's travel between its end stops [m]
        (:func:`hapsim.pipeline.identify_run.record`).

    Returns
    -------
    (DeviceFit, dict)
        The fit and the record (:func:`hapsim.pipeline.identify_run.record`).

    Raises
    ------
    ConfigError
        Bad values; a record too short to fit (a safety stop at once).
    DeviceError, ProtocolError
        As ``hapsim run``.
    """
    from hapsim.analysis.device_fit import fit_device
    from hapsim.pipeline.identify_run import record
    check_values("identify", max_delay=max_delay)
    import signal
    import threading

    from hapsim.host.loop_types import StopFlag
    stop, old = None, {}
    if handle_signals and threading.current_thread() is threading.main_thread():
        # the handlers stay until the fit is made, as hapsim run's stay until its report:
        # a SIGINT/SIGTERM while the mock reports or the fit runs (seconds on a loaded
        # machine) asks for a stop already under way; with the default handler back
        # there it killed the process (-15), the record and the fit lost
        stop = StopFlag()
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, lambda signum, frame: stop.request(signum))
    try:
        rec = record(device, port=port, baud=baud, rate_hz=rate_hz, duration=duration,
                     force_limit=force_limit, envelope=envelope, max_delay=max_delay, seed=seed,
                     noise_seed=seed, transport=transport, lockstep=lockstep, progress=progress,
                     handle_signals=False, stop=stop, driver=driver,
                     driver_options=driver_options, mock_options=mock_options,
                     travel=travel)
        # the whole record: every stretch of consecutive STATEs is fitted, each from its
        # own initial state (a lost STATE is a gap, the mass and frictions are shared)
        seq = rec["seq"]
        a, b = 0, int(seq.size)
        rec["loop"]["fitted_rows"] = [a, b]
        rec["loop"]["gaps"] = int(np.count_nonzero(np.diff(seq) != 1))
        acc = rec.get("account")
        if acc is not None:
            rec["loop"]["account"] = acc.to_dict()
        try:
            fit = fit_device(rec["position"], rec["force"], rec["period"],
                             late=rec["late"], max_delay=max_delay + 1, applied=acc, seq=seq)
        except (ArithmeticError, np.linalg.LinAlgError, ValueError) as exc:
            if isinstance(exc, HapsimError):
                raise
            # the fit failed numerically: the record does not carry what the model needs
            raise IdentificationError(f"the record cannot be identified: the fit failed "
                                      f"({type(exc).__name__}: {exc}); "
                                      f"{_record_summary(rec, a, b)}") from None
        return fit, rec
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def calibrate_scale(bare: IdentifyReport, loaded: IdentifyReport, added_mass: float,
                    driver):
    """A driver's scale parameter from two identifications, without and with a known
    mass clamped to the handle (``hapsim identify --added-mass``).

    Parameters
    ----------
    bare, loaded : IdentifyReport
        :func:`identify` without and with ``added_mass`` on the handle, through ``driver``.
    added_mass : float > 0
        The clamped mass [kg] (an inertia [kg m^2] for a rotary axis).
    driver : hapsim.drivers.base.Driver
        The driver both records were taken through: its ``scale_option`` (the FireFader's
        ``full_scale``, the Haply board's ``resolution``) is the value assumed.

    Returns
    -------
    (ForceScale, DeviceFit, Driver)
        The gain and the parameter found (:func:`hapsim.analysis.calibration.
        full_scale_from_added_mass`: ``full_scale`` is the parameter whatever it is),
        ``bare``'s fit in the device's own units
        (:func:`~hapsim.analysis.calibration.rescale_fit`) and the driver with the
        parameter found (its :meth:`~hapsim.drivers.base.Driver.options` are what the
        device file's ``protocol_options`` then hold).

    Raises
    ------
    ConfigError
        A driver whose protocol carries SI units (nothing to calibrate), a bad mass, or
        the added mass not resolved by the two fits.
    """
    from hapsim.analysis.calibration import full_scale_from_added_mass, rescale_fit
    from hapsim.drivers import get_driver
    check_values("identify", added_mass=added_mass)
    opt = driver.scale_option
    if opt is None:
        raise ConfigError(f"the {driver.name} protocol carries SI units: no scale to "
                          f"calibrate (valid with --added-mass: the drivers firefader and "
                          f"haply)", key="--added-mass")
    sc = full_scale_from_added_mass(bare.fit.mass, loaded.fit.mass, added_mass,
                                    float(getattr(driver, opt)))
    fit = rescale_fit(bare.fit, sc, driver.scale_kind)
    opts = driver.options()
    opts[opt] = sc.full_scale
    return sc, fit, get_driver(driver.name, **opts)


def _record_summary(rec, a: int, b: int) -> str:
    """One phrase on a record: rows fitted, late ticks, the device's delay, its stop."""
    loop = rec["loop"]
    dd = loop.get("device_delay")
    return (f"rows {a}..{b}, {int(np.count_nonzero(rec['late'][a:b]))} late, device delay "
            f"{'not shown' if dd is None or dd < 0 else dd}, stop: {loop['stop_reason']}")


# ---------------------------------------------------------------------------- run
@dataclasses.dataclass(frozen=True)
class RunReport(Report):
    """What ``hapsim run SCENE --json`` says: the loop closed, what was felt, how it ran.

    Attributes
    ----------
    scene : str
    target : dict or None
        The first target link's (k, b) and renderability (``targets``: all of them).
    targets : list of dict
    virtual : dict
        The (K, B) simulated.
    predicted : dict
        ``k`` [N/m], ``b`` [N s/m], ``f0_hz``, ``damping_ratio``, ``stable``, ...
    measured : dict
        The same figures identified from the logged free response, with their
        uncertainty and the verdict (``error`` when nothing could be measured).
    loop : dict
        Rate, ticks, late, missed, turnaround, stop reason, the device's protocol, ...
    telemetry, osc, sound : dict or None
    error : dict or None
        ``type`` and ``message`` of the device error that ended the run (the device lost
        beyond recovery); None when it ran to its end.
    advice : dict or None
        What ``auto`` chose (rate and integrator).
    verdict : str
        ``"within"``, ``"differs"`` or ``"not measurable"``: ``measured``'s verdict in the
        word a 2-D/3-D run's report has at its top level (:class:`RunReportND`;
        :func:`hapsim.pipeline.report.verdict_summary`).
    within : bool or None
        Measured = predicted within the stated uncertainty (None: not measurable).
    reason : str
        The verdict in words (``measured``'s sentence).

    Other attributes: ``exit_code``, what ``hapsim run`` exits with (0, or 1 after a
    safety stop or a device fault).
    """

    _OPTIONAL = ("error", "advice")

    scene: str
    target: dict | None
    targets: list
    virtual: dict
    predicted: dict
    measured: dict
    loop: dict
    telemetry: dict | None
    osc: dict | None
    sound: dict | None
    error: dict | None = None
    advice: dict | None = None
    verdict: str | None = None
    within: bool | None = None
    reason: str | None = None

    @property
    def k(self) -> float:
        """Measured felt stiffness k [N/m] (NaN when nothing was measured)."""
        return _get(self.measured, "k")

    @property
    def b(self) -> float:
        """Measured felt damping b [N s/m] (NaN when nothing was measured)."""
        return _get(self.measured, "b")

    @property
    def ok(self) -> bool:
        """Ran to the end (or was stopped by a signal): what exit code 0 means."""
        return self.exit_code == 0

    def plot(self, path_or_ax=None):
        """The felt (k, b) of the run: simulated, predicted, measured (with its stated
        uncertainty) and the targets, in the (k, b) plane (:func:`hapsim.plots.plot_felt`).

        Parameters
        ----------
        path_or_ax : str, path-like or matplotlib.axes.Axes, optional
            A figure file to write (its extension picks the format), axes to draw into,
            or None (a new figure).

        Returns
        -------
        matplotlib.figure.Figure

        Raises
        ------
        ConfigError
            matplotlib missing (the hint names the plot extra), or a path that cannot be
            written (key ``plot``).
        """
        from hapsim.plots import plot_felt
        return _draw(self, plot_felt, path_or_ax)

    def text(self) -> str:
        """The human report ``hapsim run`` prints (:func:`hapsim.pipeline.report.format_report`).

        Returns
        -------
        str
            Several aligned lines, no trailing newline.
        """
        from hapsim.pipeline.report import format_report
        return format_report(self.to_dict())


#: RunOptions fields that are the run's own bookkeeping, not options of :func:`run`.
_RUN_INTERNAL = ("plan", "embedded")


def run_options() -> tuple:
    """The options :func:`run` takes: the fields of
    :class:`hapsim.pipeline.options.RunOptions` (what ``hapsim run``'s options become).

    Returns
    -------
    tuple of str
    """
    from hapsim.pipeline.options import RunOptions
    return tuple(f.name for f in dataclasses.fields(RunOptions)
                 if f.name not in _RUN_INTERNAL)


def run(scene, options=None, *, amplitude: float | None = None, **changes: Any):
    """Close the loop of a scene on a device (``port``) or on its mock, and measure it.

    A scene of any dimension: a 2-D or 3-D one measures its felt matrices
    (:func:`hapsim.api_nd.run_scene_nd`, a :class:`RunReportND`), a 1-D one its felt pair
    (below).

    ``hapsim run`` is this function with the options of its command line
    (:meth:`hapsim.pipeline.options.RunOptions.from_args`); it prints the result.

    Parameters
    ----------
    scene : hapsim.scene.Scene or str
    options : hapsim.pipeline.options.RunOptions, optional
        All the options at once (default: ``RunOptions(handle_signals=False)``: a library
        leaves SIGINT to its caller).
    amplitude : float, optional
        A 2-D or 3-D scene's excitation [m] (default 1e-8); a 1-D scene refuses it (its
        hand's start is the scene's ``excitation``).
    **changes
        Options by name, over ``options`` (:func:`run_options`): ``port`` (None: the
        embedded mock on a pseudo-terminal), ``duration`` [s], ``lockstep`` (deterministic
        mock), ``driver`` (default: the scene's ``device.protocol``), ``telemetry`` (a
        file), ``transport`` (``"inprocess"``: the lockstep mock called directly, no child
        process), ``handle_signals``, ...

    Returns
    -------
    RunReport or RunReportND
        Also when the run ended on a safety stop or a device fault (``ok`` False; a device
        lost beyond recovery: ``error``). A 2-D/3-D scene's :class:`RunReportND`.

    Raises
    ------
    ConfigError
        An invalid scene or option (an unknown option names the valid ones).
    UnstableConfigError
        An unstable loop without ``allow_unstable``, an unrenderable target.
    DeviceError, ProtocolError
        The port failed or the device was lost beyond recovery before anything ran.

    Notes
    -----
    The measured (k, b) are identified from the free response by the matrix pencil
    method (Hua & Sarkar 1990) beside the THS prediction (Florens, Voda & Urma).
    """
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import run_scene
    from hapsim.errors import DeviceError, ProtocolError

    valid = run_options()
    unknown = sorted(set(changes) - set(valid))
    if unknown:
        raise ConfigError(f"unknown option(s) {', '.join(unknown)}; valid: "
                          f"{', '.join(valid)}", key=unknown[0])
    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)               # in the dimension it declares
    opts = dataclasses.replace(options if options is not None
                               else RunOptions(handle_signals=False), **changes)
    if getattr(scene, "dimension", 1) != 1:
        from hapsim.api_nd import run_scene_nd
        return run_scene_nd(scene, opts, amplitude)
    if amplitude is not None:
        raise ConfigError("a 1-D scene's hand starts where its excitation says (x0, v0): "
                          "amplitude is for a 2-D or 3-D scene", key="amplitude")
    driver = opts.driver
    if driver is None and scene.device is not None:
        driver = scene.device.protocol
    try:
        rep = run_scene(scene, dataclasses.replace(opts, driver=driver))
    except (DeviceError, ProtocolError) as exc:
        rep = getattr(exc, "report", None)
        if rep is None:
            raise
    code = rep.pop("exit_code")
    return RunReport.from_dict(json_safe(rep), exit_code=code)


# ---------------------------------------------------------------------------- play
@dataclasses.dataclass(frozen=True)
class PlayReport(Report):
    """What ``hapsim play SCENE --json`` says of a 1-D scene: the loop played live on the
    embedded mock, the changes taken, the felt pair predicted and measured.

    Attributes
    ----------
    scene : str
    samples : int
        Device samples played (fewer than the duration's after a stop).
    rate_hz : float
    stop_reason : str
        ``"duration"``, ``"signal SIGINT"``, ``"view: stop button"``, ``"error"``, ...
    late : int
        Times the loop fell more than 20 ms behind the clock (then resynchronised).
    paced_by : str
        ``"sound"``, ``"clock"`` or ``"none"`` (lockstep).
    delay : int
        The loop's delay [device samples], the sound callback's lead included.
    scheduling : str
        The real-time priority taken (or why not).
    accepted, refused : int
        Live changes (OSC or the view) accepted and refused.
    felt : dict
        The prediction for the scene as it is now: ``k`` [N/m], ``b`` [N s/m],
        ``f0``, ``zeta``, ``spectral_radius``, ``stable``.
    measured : dict
        ``k``, ``b`` identified from a free response no change disturbed (None when
        none was: ``why_not``), with ``k_unc``, ``b_unc``, ``method``, ``samples_used``.
    error : str or None
        Why the play stopped early (the sound server stopped, its new block made the loop
        unstable).
    note : str or None
    links : dict
        Each link's (K, B) at the end.
    sound : dict or None
        The live sound's backend, block, lead, xruns, underruns, ...
    journal : list of dict
        The changes' requests, verdicts and ramps, with their samples.

    Other attributes: ``exit_code``, what ``hapsim play`` exits with (0, or 1 with
    ``error``).
    """

    scene: str
    samples: int
    rate_hz: float
    stop_reason: str
    late: int
    paced_by: str
    delay: int
    scheduling: str
    accepted: int
    refused: int
    felt: dict
    measured: dict
    error: str | None
    note: str | None
    links: dict
    sound: dict | None
    journal: list

    @property
    def k(self) -> float:
        """Measured felt stiffness k [N/m] (NaN when nothing was measured)."""
        return _get(self.measured, "k")

    @property
    def b(self) -> float:
        """Measured felt damping b [N s/m] (NaN when nothing was measured)."""
        return _get(self.measured, "b")

    @property
    def ok(self) -> bool:
        """Played to its end or was stopped (no error): what exit code 0 means."""
        return self.exit_code == 0

    def text(self) -> str:
        """The human report ``hapsim play`` prints (:func:`hapsim.pipeline.play.play_text`).

        Returns
        -------
        str
            Two or three lines, no trailing newline.
        """
        from hapsim.pipeline.play import play_text
        return play_text(self.to_dict())


#: ``hapsim play``'s options by keyword (argparse destination) and their defaults: the
#: keywords :func:`play` takes beside ``handle_signals``.
PLAY_OPTIONS = {"duration": 10.0, "sound": "auto", "jack_server": None, "osc": None,
                "view": None, "ramp": 0.05, "pluck_every": 0.0, "lockstep": False,
                "journal": None, "telemetry": None, "rt_priority": None}
_SOUNDS = ("auto", "jack", "sounddevice", "none")


def play(scene, *, handle_signals: bool = False, **options: Any):
    """Play a scene live, as an instrument (``hapsim play SCENE``), in any dimension.

    A 1-D scene: its embedded mock device closed on it at the device's rate in real time
    (``lockstep``: as fast as possible), the hand plucking with the scene's excitation,
    the sound of its ``audio`` section out through JACK or PortAudio. A 2-D or 3-D scene
    (with an ``audio`` section): its sound, its loop closed on the device's model in the
    sound's producer, paced by the sound card. Live changes come from ``osc`` and the
    ``view`` page, each checked before it is applied and ramped over ``ramp``.

    Parameters
    ----------
    scene : hapsim.scene.Scene, hapsim.scene_nd.SceneND or str
        A loaded scene or its path (its ``dimension`` picks the play).
    handle_signals : bool, optional
        SIGINT and SIGTERM end the play cleanly with its report, as on the command line
        (main thread only; default False: a library leaves SIGINT to its caller).
    **options
        ``hapsim play``'s options in Python spelling (:data:`PLAY_OPTIONS`, their
        defaults the command's): ``duration`` [s] (default 10), ``sound`` (``"auto"``,
        ``"jack"``, ``"sounddevice"``, ``"none"``), ``jack_server``, ``osc`` (an OSC
        port on localhost, 0: any free one), ``view`` (serve the live view,
        :mod:`hapsim.view`, on 127.0.0.1:PORT, 0: any free port; its address is printed
        on stderr; needs the ``view`` extra), ``ramp`` [s], ``pluck_every`` [s],
        ``lockstep`` (1-D), ``journal`` (a JSON file), ``telemetry`` (an npz file, 1-D),
        ``rt_priority``.

    Returns
    -------
    PlayReport or hapsim.api_nd.PlayReportND
        The command's ``--json`` object, by the scene's dimension; ``exit_code`` what
        the command exits with.

    Raises
    ------
    ConfigError
        An invalid scene or option (an unknown one names the valid ones; a number out of
        range gets the command's message, keyed by its flag; an option the n-D play does
        not take: ``lockstep``, ``telemetry``, ``sound="none"``); ``view`` without the
        websockets package.
    UnstableConfigError
        The scene's closed loop (with live sound, the sound callback's lead added to the
        device's delay) is unstable: nothing played.
    DeviceError
        No sound output could be opened (1-D: for ``sound="jack"`` or
        ``"sounddevice"``; ``"auto"`` then plays silently): nothing played.
    KeyboardInterrupt
        SIGINT without ``handle_signals``: the sound, the OSC server, the view and the
        analysis process are closed first, and no report is made.

    Notes
    -----
    The changes' check is the THS prediction (Florens, Voda & Urma) of the changed loop
    (the MIMO spectral radius in 2-D and 3-D); the measured (k, b) of a 1-D play are
    identified from free responses between plucks (matrix pencil, Hua & Sarkar 1990).
    """
    import types

    from hapsim.pipeline.play import play_scene, stop_on_signals
    from hapsim.host.loop_types import StopFlag

    unknown = sorted(set(options) - set(PLAY_OPTIONS))
    if unknown:
        raise ConfigError(f"unknown option(s) {', '.join(unknown)}; valid: "
                          f"{', '.join(PLAY_OPTIONS)}, handle_signals", key=unknown[0])
    opts = {**PLAY_OPTIONS, **options}
    check_values("play", **{k: opts[k] for k in ("duration", "osc", "view", "ramp",
                                                  "pluck_every", "rt_priority")})
    if opts["sound"] not in _SOUNDS:
        raise ConfigError(f"--sound: must be one of {', '.join(_SOUNDS)}, got "
                          f"{opts['sound']!r}", key="--sound")
    if isinstance(scene, (str, os.PathLike)):
        path = os.fspath(scene)
        scene = load_scene(path)
    else:
        path = scene.path
    args = types.SimpleNamespace(scene=path, json=False, **opts)
    stop = StopFlag()
    if handle_signals:
        with stop_on_signals(stop):
            code, rep = play_scene(args, stop, scene)
    else:
        code, rep = play_scene(args, stop, scene)
    if "dof" in rep:
        from hapsim.api_nd import PlayReportND
        return PlayReportND.from_dict(json_safe(rep), exit_code=code)
    return PlayReport.from_dict(json_safe(rep), exit_code=code)


def known_digits(value: float, error: float) -> float:
    """``value`` rounded to the digits that are known: to the decade at or above
    ``2 error`` (so the last digit shown is off by at most half a unit).

    Parameters
    ----------
    value : float
    error : float >= 0
        Its uncertainty (0 or non-finite: ``value`` unchanged).

    Returns
    -------
    float
    """
    if not (error > 0 and math.isfinite(error)):
        return value
    return round(value, known_decimals(error))


def known_decimals(error: float) -> int:
    """Decimals of a value known to ``error`` (> 0): ``-ceil(log10(2 error))``, >= 0.

    Parameters
    ----------
    error : float
        Half-width of what the value is known to (> 0, finite), in the value's unit.

    Returns
    -------
    int
        Decimals ``d`` to print: the unit of the last one, ``10**-d``, is at least the
        interval ``2 error``, so every digit printed is known (0 when ``error > 0.05``).

    Raises
    ------
    ValueError
        ``error <= 0`` (``math.log10``).
    """
    return max(0, -math.ceil(math.log10(2.0 * error)))
