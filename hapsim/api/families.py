"""``family``: a family of THS (the hand's stiffness varying), its robust verdict."""

from __future__ import annotations

import dataclasses
import os


from hapsim.errors import ConfigError
from hapsim.option_values import check_values
from hapsim.api.common import draw_report, one_d_scene
from hapsim.results import Report


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
        return draw_report(self, draw, path, axes=False)


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

    check_values("family", samples=samples)     # (None: the grid)
    check_values("family", required=True, grid=grid, seed=seed, certify=certify)
    scene = one_d_scene(scene, "family", "there is no family of a 2-D or 3-D THS yet; "
                   "hapsim.check gives its felt matrices")
    if correction is not None:
        scene = dataclasses.replace(scene, device=dataclasses.replace(
            scene.device, correction=correction))
    scene, ends, board = _board_family(scene)
    res = _family(scene, samples, grid=grid, seed=seed, certify=certify)
    for lat, end, late in ends if res.robust else ():
        # the board may render anywhere in its bounds, and its reading be taken late: the
        # family there, the (K, B) calibrated at the middle sent as they are; an unstable
        # member is the verdict's
        at = _family(end, samples, grid=grid, seed=seed, certify=certify,
                     calibrated=res.calibrated)
        if not at.robust:
            res, scene = at, end
            if late:
                board.update(late_reading_unstable={"periods": late,
                                                    "delay": float(end.device.delay)})
            else:
                board.update(unstable_latency_s=lat,
                             delay_modelled=float(end.device.delay))
            break
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
    if board is not None:
        rep["board"] = board
    return FamilyReport.from_dict({"scene": scene.path, "verdict": verdict,
                               "correction": getattr(scene.device, "correction", None),
                               **rep}, analysis=res)


def _board_family(scene) -> tuple:
    """The family's scene as the board its ``device.protocol`` names runs it: at the
    board's rate, the render latency's middle in the delay (``hapsim check``'s loop,
    :func:`hapsim.api.checking.board_loop`), and the scenes at the latency's two bounds
    the robust verdict holds too, and the scene with the board's reading taken late
    (its driver's ``late_reading_periods`` more periods after the bounds' end, as the run
    holds the loop: :func:`hapsim.pipeline.render_latency.late_reading`);
    ``(scene, ((latency [s], scene, late periods), ...), board)``, the ``board`` dict None
    (and no bounds) on hapsim's framed protocol."""
    from hapsim.analysis.prediction import timed_scene
    from hapsim.api.checking import at_board_rate
    from hapsim.pipeline.render_latency import late_reading_s, latency_middle, render_latency
    scene, drv = at_board_rate(scene)
    if drv is None:
        return scene, (), None
    mid = latency_middle(scene, drv)
    lo, hi = render_latency(drv) if mid else (0.0, 0.0)
    n, late_s = late_reading_s(scene, drv, hi)
    late = [(late_s, timed_scene(scene, late_s), n)] if n else []
    if not mid:
        return scene, tuple(late), {"protocol": scene.device.protocol,
                                    "rate_hz": scene.rate_hz}
    timed = timed_scene(scene, mid)
    ends = [(lat, timed_scene(scene, lat), 0) for lat in (lo, hi)] + late
    return timed, tuple(ends), {
        "protocol": scene.device.protocol, "rate_hz": scene.rate_hz,
        "render_latency_s": [lo, hi], "delay_modelled": float(timed.device.delay)}
