"""``python -m hapsim ARGV`` in the test's own process (issue 31 item 2: the suite's time).

A ``python -m hapsim`` child costs its interpreter and its imports (numpy, numba, scipy,
hapsim: ~1 CPU-s for ``run``, more for ``play``) before it does anything; the pytest worker
has them loaded already. Where the process boundary is not what a test is about (its exit
code, stdout and stderr are; not a signal, a tty, a kill -9, the entry point or the start-up
itself), :func:`hapsim_main` runs the same :func:`hapsim.cli.main` the child's
``hapsim.cli.entry`` runs, and puts back what a command may leave changed in a process
(the environment: ``hapsim.blas.size_pools`` sizes the BLAS pools there; the working
directory; the GIL switch interval ``hapsim play`` shortens; the collector ``hapsim run``
holds off during its loop). Signal dispositions and the mask are put back by
``tests/conftest.py`` after every test. What a command starts (the embedded mock, a board
emulation) is still a child process.
"""

from __future__ import annotations

import contextlib
import gc
import io
import os
import sys


def hapsim_main(argv: list[str], *, cwd: str | os.PathLike | None = None,
                env: dict[str, str] | None = None) -> tuple[int, str, str]:
    """Run ``hapsim ARGV`` in this process as its child would: exit code, stdout, stderr.

    Parameters
    ----------
    argv : list of str
        The arguments after ``hapsim`` (the command first).
    cwd : path, optional
        Working directory for the command (restored after it); this process's when None.
    env : dict of str to str, optional
        Variables set for the command only (e.g. ``TMPDIR``); the environment is restored
        after it either way.

    Returns
    -------
    code : int
        :func:`hapsim.cli.main`'s return value: the child's exit status (``entry`` exits
        with it).
    out, err : str
        What the command wrote on ``sys.stdout`` and ``sys.stderr`` (hapsim writes only
        through them: no file descriptor is written directly).
    """
    from hapsim.cli import main
    saved_env = dict(os.environ)
    saved_cwd = os.getcwd()
    saved_switch = sys.getswitchinterval()
    saved_gc = gc.isenabled()
    out, err = io.StringIO(), io.StringIO()
    try:
        if env:
            os.environ.update(env)
        if cwd is not None:
            os.chdir(cwd)
        if env and "TMPDIR" in env:
            import tempfile
            tempfile.tempdir = None          # re-read TMPDIR, as a new process would
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main([str(a) for a in argv])
    finally:
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        if env and "TMPDIR" in env:
            import tempfile
            tempfile.tempdir = None
        sys.setswitchinterval(saved_switch)
        if saved_gc:
            gc.enable()
    return code, out.getvalue(), err.getvalue()
