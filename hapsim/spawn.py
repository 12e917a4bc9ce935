"""The environment of a child Python process that runs part of this hapsim (the embedded
mocks of :mod:`hapsim.daemon.transport` and :mod:`hapsim.driver_mock`): the parent's
environment with ``PYTHONPATH`` led by the directory that holds this package, so that the
child imports the same tree as its parent, installed or not."""

from __future__ import annotations

import os

__all__ = ["package_root", "child_env"]


def package_root() -> str:
    """The directory holding the ``hapsim`` package.

    Returns
    -------
    str
        Absolute path (the parent of ``hapsim/``).
    """
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def child_env() -> dict:
    """A copy of ``os.environ`` with :func:`package_root` first on ``PYTHONPATH``.

    Returns
    -------
    dict
        The environment to pass to ``subprocess.Popen(env=...)``.
    """
    env = dict(os.environ)
    root = package_root()
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env
