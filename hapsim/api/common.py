"""What the API's functions share: reading a scene in the dimension it declares, a
scene refused by dimension, a report's figure, a matrix or a figure of a ``--json`` object,
the digits a value is known to."""

from __future__ import annotations

import math
import os

import numpy as np

from hapsim.errors import ConfigError
from hapsim.option_values import check_kind

__all__ = ["load_scene", "load_scene_nd", "refuse_ports", "ONE_PORT_ONLY", "known_digits", "known_decimals", "draw_report",
           "MeasuredPair", "Charted",
           "one_d_scene", "figure", "n_d_scene", "scene_given", "matrix_list", "matrix_or_nan"]


def load_scene(path: str | os.PathLike):
    """Read and validate a scene file, in the dimension its ``dimension`` key declares.

    Parameters
    ----------
    path : str or path-like
        A YAML scene (docs/scenes.md; ``dimension: 2`` or ``3``: docs/dimensions.md).

    Returns
    -------
    hapsim.scene.Scene, hapsim.scene.SceneND or hapsim.scene.ScenePorts
        A :class:`~hapsim.scene.Scene` for a 1-D scene (no ``dimension`` key, or 1: as
        before), a :class:`~hapsim.scene.SceneND` for a 2-D or 3-D one, whose
        ``dimension`` says which (the functions taking it: :func:`check_nd`,
        :func:`modes_nd`, :func:`run_nd`), a :class:`~hapsim.scene.ScenePorts` for one
        with several ports (``devices:``; :func:`check` takes it, the other functions
        refuse it by name: :func:`refuse_ports`).

    Raises
    ------
    ConfigError
        An unreadable or invalid file: the message names the file, the line and the key,
        with the valid keys or choices.
    """
    from hapsim.scene import scene_dimension, scene_has_ports
    p = os.fspath(path)
    if scene_has_ports(p):
        from hapsim.scene import load_scene_ports
        return load_scene_ports(p)
    if scene_dimension(p) != 1:
        from hapsim.scene import load_scene_nd as _load_nd
        return _load_nd(p)
    from hapsim.scene import load_scene as _load
    return _load(p)


def draw_report(report, draw, path_or_ax, axes: bool = True):
    """``draw(report, ax=...)`` into new axes (None), given axes, or a figure file.

    Parameters
    ----------
    report : hapsim.results.Report
    draw : callable
        A :mod:`hapsim.plots` function, ``draw(report, ax=None) -> Figure``.
    path_or_ax : str, path-like, matplotlib.axes.Axes or None
        A figure file (checked first, written by :func:`hapsim.plots.save_figure`), axes
        to draw into, or None (new axes).
    axes : bool
        Whether the chart draws into given axes (False: a figure of its own, several
        panels; axes are refused rather than ignored).

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    ConfigError
        matplotlib missing, a path that cannot be written, or a target that is neither a
        path nor axes (key ``plot``; before: a number was an AttributeError, axes were
        ignored by the charts that draw their own figure, and the 2-D/3-D charts wrote
        ``x.png`` for a path ``x`` without extension).
    """
    from hapsim.plots import check_figure_path, is_axes, save_figure
    if isinstance(path_or_ax, (str, os.PathLike)):
        path = os.fspath(path_or_ax)
        check_figure_path(path, "plot")
        fig = draw(report)
        save_figure(fig, path)
        return fig
    if path_or_ax is not None:
        if not (axes and is_axes(path_or_ax)):
            raise ConfigError(f"must be a figure file's path{', axes' if axes else ''} or "
                              f"None, got {path_or_ax!r}", key="plot")
    return draw(report, ax=path_or_ax)


#: Why each command that takes one port refuses a scene with several ports (``devices:``),
#: one line each; what takes the scene instead. ``hapsim.commands.dimension`` says it at
#: the file's ``devices:`` line.
ONE_PORT_ONLY = {
    "advise": "it finds, for each link to the one port, the lowest rate and cheapest "
              "method that keep that port's felt (k, b), a pair of numbers, within "
              "tolerance; across several ports what is felt is a pair of matrices, which "
              "its tolerance does not cover yet; 'hapsim check SCENE' gives the felt "
              "matrices and 'hapsim stability --scene SCENE' each port's K_max",
    "family": "a family varies the hand at the one port (devices.NAME.hand is refused in "
              "a scene with several ports: no hand per port is built), so there is no "
              "hand to vary; 'hapsim check SCENE' gives the felt matrices of the devices "
              "as written",
    "zwidth": "the Z-width is a per-port measure: K_max(B) of a one-link wall on one "
              "device, raised until that device's record grows; 'hapsim stability "
              "--scene SCENE' gives each port's K_max in the coupled loop; a one-port "
              "scene with one port's devices.NAME values as its device: measures that "
              "device",
    "identify": "it identifies one device (mass, friction, delay, hold, ...) from the "
                "records of the one mock the scene's device: section models; a one-port "
                "scene with one port's devices.NAME values as its device: identifies "
                "that one",
    "play": "play closes one device's loop and plays the scene's audio: listening "
            "points; a scene with several ports has no audio: section and no virtual "
            "mass to hear (its reader refuses both), so there is nothing to play; "
            "'hapsim simulate SCENE --x0 PORT=M --out FILE.npz' gives the ports' motion",
}


def refuse_ports(scene, what: str) -> None:
    """Refuse a scene with several ports by name, for a function that takes one port.

    Parameters
    ----------
    scene : object
        A loaded scene (anything but a :class:`~hapsim.scene.ScenePorts` passes).
    what : str
        The function's name (``"run"``), said in the refusal.

    Raises
    ------
    ConfigError
        ``scene`` has several ports (key ``devices``, its file): the reason, and what takes
        it (``hapsim.check``; ``hapsim run SCENE --lockstep``).
    """
    from hapsim.scene import ScenePorts
    if isinstance(scene, ScenePorts):
        why = ONE_PORT_ONLY.get(what)
        raise ConfigError(f"a scene with several ports ({', '.join(scene.ports)}): "
                          f"hapsim.{what} takes one port"
                          + (f": {why}" if why else "; hapsim.check, hapsim.simulate and "
                             "hapsim.run (in lockstep, or the FireFader's two faders in "
                             "real time) take several (docs/ports.md)"),
                          file=scene.path, key="devices")


def one_d_scene(scene, what: str, why: str):
    """A 1-D scene from a scene or a path, for a function that takes dimension 1 only.

    Parameters
    ----------
    scene : hapsim.scene.Scene or str or path-like
    what : str
        The function's name (``"family"``).
    why : str
        Why it takes dimension 1 only, and what to use instead.

    Returns
    -------
    hapsim.scene.Scene

    Raises
    ------
    ConfigError
        A 2-D or 3-D scene (key ``dimension``); an unreadable or invalid file.
    """
    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)
    scene_given(scene)
    refuse_ports(scene, what)
    if getattr(scene, "dimension", 1) != 1:
        raise ConfigError(f"a {scene.dimension}-D scene: hapsim.{what} takes dimension 1 "
                          f"({why})", file=getattr(scene, "path", None), key="dimension")
    return scene


def figure(d, key) -> float:
    """A figure of a ``--json`` object as a float.

    Parameters
    ----------
    d : dict or None
    key : str

    Returns
    -------
    float
        ``d[key]``, NaN when ``d`` is None or the key is missing or None.
    """
    v = None if d is None else d.get(key)
    return math.nan if v is None else float(v)


def load_scene_nd(path: str | os.PathLike):
    """Read and validate a 2-D or 3-D scene file (docs/dimensions.md).

    Parameters
    ----------
    path : str or path-like
        A YAML scene with ``dimension: 2`` or ``3``.

    Returns
    -------
    hapsim.scene.SceneND

    Raises
    ------
    ConfigError
        An unreadable or invalid file (file, line and key named), or a 1-D scene (read
        it with :func:`load_scene`).
    """
    from hapsim.scene import load_scene_nd as _load
    return _load(os.fspath(path))


def n_d_scene(scene):
    """A 2-D or 3-D scene from a scene or a path (:func:`load_scene_nd`).

    Parameters
    ----------
    scene : hapsim.scene.SceneND or str or path-like

    Returns
    -------
    hapsim.scene.SceneND

    Raises
    ------
    ConfigError
        An unreadable or invalid file (file, line, key).
    """
    if isinstance(scene, (str, os.PathLike)):
        return load_scene_nd(scene)
    return scene_given(scene)


def scene_given(scene):
    """``scene`` when it is a loaded scene of any kind, else a ConfigError keyed ``scene``
    (before: a number or None passed as a scene was an AttributeError deep in the
    analysis).

    Parameters
    ----------
    scene : object

    Returns
    -------
    hapsim.scene.Scene or hapsim.scene.SceneND or hapsim.scene.ScenePorts

    Raises
    ------
    ConfigError
        ``scene`` is no scene (a path is loaded by the callers, not here).
    """
    from hapsim.scene import Scene, SceneND, ScenePorts
    if not isinstance(scene, (Scene, SceneND, ScenePorts)):
        raise ConfigError(f"must be a scene (hapsim.load_scene) or a scene file's path, "
                          f"got {scene!r}", key="scene")
    return scene


def matrix_list(x):
    """A matrix as nested lists of floats for ``--json``.

    Parameters
    ----------
    x : array_like, shape (n, n), or None

    Returns
    -------
    list of list of float, or None
    """
    return None if x is None else np.asarray(x, float).tolist()


def matrix_or_nan(m, n: int) -> np.ndarray:
    """A report's matrix as an array, NaN where there is none.

    Parameters
    ----------
    m : array_like, shape (n, n), or None
    n : int
        The dimension.

    Returns
    -------
    ndarray, shape (n, n)
    """
    return np.full((n, n), math.nan) if m is None else np.array(m, float)


def known_digits(value: float, error: float) -> float:
    """``value`` rounded to the digits that are known: to the decade at or above
    ``2 error`` (so the last digit shown is off by at most half a unit), tens or
    thousands included (987654 known to 2000 is 990000).

    Parameters
    ----------
    value : float
    error : float >= 0
        Its uncertainty (0 or not finite, an uncertainty unknown: ``value`` unchanged).

    Returns
    -------
    float

    Raises
    ------
    ConfigError
        ``value`` or ``error`` not a number, or ``error`` negative (keyed by the
        argument).
    """
    check_kind("value", value, "a number", required=True)
    check_kind("error", error, "a number", required=True)
    if error < 0:
        raise ConfigError(f"must be a number >= 0 (an uncertainty), got {error!r}",
                          key="error")
    if error == 0 or not math.isfinite(error) or not math.isfinite(value):
        return value
    # (before: floored at 0 decimals, as known_decimals is for printing, it kept the
    # units' digits of a value known to thousands)
    return round(value, -math.ceil(math.log10(2.0 * error)))


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
    ConfigError
        ``error`` not a finite number > 0 (keyed ``error``).
    """
    check_kind("error", error, "a number", required=True)
    if not (error > 0 and math.isfinite(error)):
        raise ConfigError(f"must be a finite number > 0 (an uncertainty), got {error!r}",
                          key="error")
    return max(0, -math.ceil(math.log10(2.0 * error)))


class MeasuredPair:
    """What a 1-D report that measured the felt pair reads from its ``measured`` object
    and its exit code (:class:`hapsim.api.RunReport`, :class:`hapsim.api.PlayReport`): a
    mixin before :class:`hapsim.results.Report`, with no field of its own."""

    @property
    def k(self) -> float:
        """Measured felt stiffness k [N/m] (NaN when nothing was measured)."""
        return figure(self.measured, "k")

    @property
    def b(self) -> float:
        """Measured felt damping b [N s/m] (NaN when nothing was measured)."""
        return figure(self.measured, "b")

    @property
    def ok(self) -> bool:
        """Ran or played to its end, or was stopped by a signal, with no device error:
        what exit code 0 means. A report read back from its JSON (no ``exit_code``) is
        judged by the command's rule on what it says (:meth:`exit_rule`; before: an
        AttributeError)."""
        code = getattr(self, "exit_code", None)
        return code == 0 if code is not None else self.exit_rule()

    def exit_rule(self) -> bool:
        """Whether the command exited 0, from the report's content: no ``error``.

        Returns
        -------
        bool
        """
        return not getattr(self, "error", None)


class Charted:
    """The chart of a 1-D report that draws into given axes, a new figure or a file: a mixin
    before :class:`hapsim.results.Report`, with no field of its own; the class names its
    :mod:`hapsim.plots` function in ``_chart``."""

    _chart = "plot_poles"

    def plot(self, path_or_ax=None):
        """The report's chart: for :class:`hapsim.api.CheckReport` and
        :class:`hapsim.api.RenderReport` the closed-loop poles in the z-plane, the felt pair
        marked (:func:`hapsim.plots.plot_poles`); for :class:`hapsim.api.RunReport` the
        felt (k, b) of the run: simulated, predicted, measured (with its stated uncertainty)
        and the targets, in the (k, b) plane (:func:`hapsim.plots.plot_felt`).

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
        import hapsim.plots
        return draw_report(self, getattr(hapsim.plots, self._chart), path_or_ax)
