"""``play``: a scene played live, in any dimension."""

from __future__ import annotations

import dataclasses
import os
from typing import Any


from hapsim.errors import ConfigError
from hapsim.option_values import check_kind, check_values
from hapsim.outputs import json_safe
from hapsim.api.common import MeasuredPair, load_scene, refuse_ports
from hapsim.results import Report


# ---------------------------------------------------------------------------- play
@dataclasses.dataclass(frozen=True)
class PlayReport(MeasuredPair, Report):
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
    scene : hapsim.scene.Scene, hapsim.scene.SceneND or str
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
    PlayReport or hapsim.api.PlayReportND
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

    from hapsim.pipeline.options import check_ramp
    from hapsim.pipeline.play import play_scene, stop_on_signals
    from hapsim.host.loop_types import StopFlag

    unknown = sorted(set(options) - set(PLAY_OPTIONS))
    if unknown:
        raise ConfigError(f"unknown option(s) {', '.join(unknown)}; valid: "
                          f"{', '.join(PLAY_OPTIONS)}, handle_signals", key=unknown[0])
    opts = {**PLAY_OPTIONS, **options}
    check_values("play", required=True, **{k: opts[k] for k in ("duration", "ramp",
                                                                 "pluck_every")})
    check_values("play", **{k: opts[k] for k in ("osc", "view", "rt_priority")})
    check_ramp("ramp" in options, opts["osc"], opts["view"])
    # the kinds the flags give (before: a number for journal or telemetry was a TypeError
    # when the file was written, after the play)
    for key, kind in (("jack_server", "a text"), ("journal", "a path"),
                      ("telemetry", "a path")):
        check_kind("--" + key.replace("_", "-"), opts[key], kind)
    check_kind("--lockstep", opts["lockstep"], "True or False", required=True)
    if opts["sound"] not in _SOUNDS:
        raise ConfigError(f"--sound: must be one of {', '.join(_SOUNDS)}, got "
                          f"{opts['sound']!r}", key="--sound")
    if isinstance(scene, (str, os.PathLike)):
        path = os.fspath(scene)
        scene = load_scene(path)
    else:
        path = scene.path
    refuse_ports(scene, "play")
    args = types.SimpleNamespace(scene=path, json=False, **opts)
    stop = StopFlag()
    if handle_signals:
        with stop_on_signals(stop):
            code, rep = play_scene(args, stop, scene)
    else:
        code, rep = play_scene(args, stop, scene)
    if "dof" in rep:
        return PlayReportND.from_dict(json_safe(rep), exit_code=code)
    return PlayReport.from_dict(json_safe(rep), exit_code=code)


@dataclasses.dataclass(frozen=True)
class PlayReportND(Report):
    """What ``hapsim play SCENE --json`` says of a 2-D or 3-D scene (:func:`hapsim.api.play`
    returns it for such a scene): its sound played live, its loop closed on the device's
    model, the changes taken.

    Attributes
    ----------
    scene : str
    dof : int
        The scene's dimension.
    rate_hz : float
    frames : int
        Frames (samples) played.
    seconds : float
        ``frames / rate_hz`` [s].
    wall_s : float
        Wall-clock time of the play [s].
    stop_reason : str
        ``"duration"``, ``"signal SIGINT"``, ``"view: stop button"``, ...
    scheduling : str
    note : str or None
        Why the loop was not checked before playing (a scene too large to analyse).
    loop : str
        ``"closed"`` (a port and a device) or ``"free"``.
    delay : int or None
        The device's delay [samples] of a closed loop.
    plucks : dict or None
        ``every_samples``, ``samples`` (the hand's profile) and ``direction``.
    sound : dict
        Backend, callback, block, channels, xruns, underruns, frames ahead, ...
    accepted, refused, felt, links, masses, journal
        With a checked loop only: live changes accepted and refused, the prediction now
        (``spectral_radius``, ``stable``, the felt matrices), each link's and plane's
        (K, B), each mass's mass [kg], the changes' journal.

    Other attributes: ``exit_code`` (0).
    """

    _OPTIONAL = ("accepted", "refused", "felt", "links", "masses", "journal")

    scene: str
    dof: int
    rate_hz: float
    frames: int
    seconds: float
    wall_s: float
    stop_reason: str
    scheduling: str
    note: str | None
    loop: str
    delay: int | None
    plucks: dict | None
    sound: dict
    accepted: int | None = None
    refused: int | None = None
    felt: dict | None = None
    links: dict | None = None
    masses: dict | None = None
    journal: list | None = None

    def text(self) -> str:
        """The human report ``hapsim play`` prints
        (:func:`hapsim.pipeline.play.play_nd_text`).

        Returns
        -------
        str
            Two or three lines, no trailing newline.
        """
        from hapsim.pipeline.play import play_nd_text
        return play_nd_text(self.to_dict())
