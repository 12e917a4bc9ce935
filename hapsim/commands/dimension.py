"""What the commands that take a 1-D scene only say of a 2-D or 3-D one: each its reason
and what to use instead (issue 30 item 2: every capability in every dimension, or refused
by name with the reason).

``check``, ``simulate``, ``run``, ``play``, ``mock --scene``, ``stability --scene``,
``identify --mock-scene --lockstep``, ``zwidth --scene --lockstep`` and ``advise`` take a
scene of any dimension (:func:`hapsim.load_scene` reads every dimension); the commands
below read it with the 1-D reader, whose refusal (at the file's ``dimension`` line) is
given their reason here.
"""

from __future__ import annotations

import os

from hapsim.errors import ConfigError

__all__ = ["ONE_D_ONLY", "load_one_d_scene", "refuse_ports_scene"]

#: Why each command takes dimension 1 only, and what a 2-D or 3-D scene has instead.
ONE_D_ONLY = {
    "family": "a family of 2-D or 3-D THS (the hand as stiffness and damping matrices) is "
              "not built yet; 'hapsim check SCENE' gives the felt matrices of its one hand",
}


def load_one_d_scene(path: str | os.PathLike, command: str, flag: str | None = None):
    """The 1-D scene at ``path`` for ``command``; a 2-D or 3-D scene refused with the
    command's reason (:data:`ONE_D_ONLY`).

    Parameters
    ----------
    path : str or path-like
        The scene file.
    command : str
        A key of :data:`ONE_D_ONLY`.
    flag : str, optional
        The option that named the file (``--mock-scene``), said in the refusal.

    Returns
    -------
    hapsim.scene.Scene

    Raises
    ------
    ConfigError
        A 2-D or 3-D scene (its file, the ``dimension`` line, key ``dimension``), a scene
        with several ports (:func:`refuse_ports_scene`), or any error of the 1-D reader
        (file, line, key).
    """
    from hapsim.scene import load_scene
    try:
        return load_scene(path)
    except ConfigError as exc:
        if exc.key == "devices":
            refuse_ports_scene(path, command, flag)
        if exc.key != "dimension":
            raise
        from hapsim.scene import scene_dimension
        n = scene_dimension(path)
        if n == 1:
            raise                      # a bad dimension value: the reader's own message
        given = f" ({flag})" if flag else ""
        raise ConfigError(f"a {n}-D scene{given}: hapsim {command} takes dimension 1: "
                          f"{ONE_D_ONLY[command]}", file=exc.file, line=exc.line,
                          key="dimension") from None


def refuse_ports_scene(path: str | os.PathLike, command: str, flag: str | None = None
                       ) -> None:
    """Refuse a scene with several ports (``devices:``) for ``command``, which takes one
    port, with the command's own reason (:data:`hapsim.api.common.ONE_PORT_ONLY`); a
    scene without several ports passes.

    Parameters
    ----------
    path : str or path-like
        The scene file.
    command : str
        A key of :data:`hapsim.api.common.ONE_PORT_ONLY`.
    flag : str, optional
        The option that named the file (``--mock-scene``), said in the refusal.

    Raises
    ------
    ConfigError
        The scene has several ports: one line naming the file, the line of ``devices:``
        and key ``devices``, the command and why it takes one port.
    """
    from hapsim.api.common import ONE_PORT_ONLY
    from hapsim.scene import load_scene, scene_has_ports
    if not scene_has_ports(path):
        return
    try:
        load_scene(path)                 # the one-port reader: its refusal has the line
    except ConfigError as exc:
        if exc.key != "devices":
            raise
        given = f" ({flag})" if flag else ""
        raise ConfigError(f"a scene with several ports{given}: hapsim {command} takes one "
                          f"port: {ONE_PORT_ONLY[command]}", file=exc.file, line=exc.line,
                          key="devices") from None
