"""A Python file that is no package's module (a tool of ``tools/``, the protocol's vector
oracle, another test file's helpers) loaded as a module, for the tests that check it."""

from __future__ import annotations

import importlib.util
from pathlib import Path


def load_module(path: str | Path, name: str | None = None):
    """Load the file ``path`` as a new module.

    Parameters
    ----------
    path : str or Path
        The ``.py`` file.
    name : str, optional
        The module's name (default: the file's stem).

    Returns
    -------
    module
        The file executed as a module (a new one at each call; not in ``sys.modules``).
    """
    path = Path(path)
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
