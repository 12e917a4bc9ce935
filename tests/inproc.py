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

import gc
import io
import os
import sys
import tempfile


def hapsim_main(argv: list[str], *, cwd: str | os.PathLike | None = None,
                env: dict[str, str] | None = None,
                timeout: float = 300.0) -> tuple[int, str, str]:
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
    timeout : float
        Longest the command may take [s] (a hang's bound, as a subprocess's
        ``communicate(timeout=...)``): then SIGINT is sent to this process (the command
        stops as on Ctrl-C) and AssertionError is raised once it has returned.

    Raises
    ------
    AssertionError
        The command did not end within ``timeout`` seconds.

    Returns
    -------
    code : int
        :func:`hapsim.cli.main`'s return value: the child's exit status (``entry`` exits
        with it).
    out, err : str
        What was written on file descriptors 1 and 2 while it ran (through ``sys.stdout``
        and ``sys.stderr``, by a library, or by a child it started), as a child's pipes
        would hold it.
    """
    import signal
    import threading

    from hapsim.cli import main
    timed_out = threading.Event()

    def interrupt():
        timed_out.set()
        os.kill(os.getpid(), signal.SIGINT)

    timer = threading.Timer(timeout, interrupt)
    timer.daemon = True
    saved_env = dict(os.environ)
    saved_cwd = os.getcwd()
    saved_switch = sys.getswitchinterval()
    saved_gc = gc.isenabled()
    saved_tempdir = tempfile.tempdir
    saved_streams = sys.stdout, sys.stderr
    saved_fds = []
    files = [tempfile.TemporaryFile(), tempfile.TemporaryFile()]
    try:
        for f in saved_streams:
            try:
                f.flush()
            except (OSError, ValueError):
                pass
        # file descriptors 1 and 2 point at the two files, and sys.stdout / sys.stderr write
        # straight through to them: what the command prints, what a library writes on the
        # descriptors (LAPACK's messages), and what a child it starts writes there, in the
        # order written, as in the pipes of a child process (neither is a terminal)
        for fd, f in zip((1, 2), files):
            saved_fds.append(os.dup(fd))
            os.dup2(f.fileno(), fd)
        sys.stdout, sys.stderr = (
            io.TextIOWrapper(open(os.dup(fd), "wb", buffering=0), encoding="utf-8",
                             errors="backslashreplace" if fd == 2 else "strict",
                             write_through=True)
            for fd in (1, 2))
        if env:
            os.environ.update(env)
            if "TMPDIR" in env:
                tempfile.tempdir = None      # read TMPDIR again, as a new process would
        if cwd is not None:
            os.chdir(cwd)
        timer.start()
        try:
            code = main([str(a) for a in argv])
        finally:
            timer.cancel()
    finally:
        for stream in (sys.stdout, sys.stderr):
            if stream not in saved_streams:
                try:
                    stream.close()
                except (OSError, ValueError):
                    pass
        sys.stdout, sys.stderr = saved_streams
        for fd, saved in zip((1, 2), saved_fds):
            os.dup2(saved, fd)
            os.close(saved)
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        tempfile.tempdir = saved_tempdir
        sys.setswitchinterval(saved_switch)
        if saved_gc:
            gc.enable()
    out, err = [], []
    for f, text in zip(files, (out, err)):
        f.seek(0)
        text.append(f.read().decode("utf-8", "backslashreplace"))
        f.close()
    if timed_out.is_set():
        raise AssertionError(f"hapsim {' '.join(map(str, argv))} did not end within "
                             f"{timeout:g} s (interrupted): exit {code}; stderr: "
                             f"{err[0][-2000:]}")
    return code, out[0], err[0]
