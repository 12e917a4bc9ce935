"""A child Python process that runs part of this hapsim (the embedded mocks of
:mod:`hapsim.host.transport` and :mod:`hapsim.emulated.driver_mock`): its environment (the
parent's, with ``PYTHONPATH`` led by the directory that holds this package, so that the
child imports the same tree as its parent, installed or not) and the host's side of a
child served on a pseudo-terminal (:class:`PtyChild`); and what a command leaves to undo
when it stops at any moment (:func:`at_stop`, :func:`run_stops`): a child still running,
its report file in the temporary directory, a temporary folder."""

from __future__ import annotations

import atexit
import itertools
import json
import os
import subprocess
import threading
from typing import Callable

__all__ = ["package_root", "child_env", "PtyChild", "HandledBytes", "at_stop", "done",
           "run_stops", "inside_import", "StopFlag"]

#: What is still to undo, by token, in the order registered (:func:`at_stop`).
_STOPS: dict[int, Callable[[], None]] = {}
_TOKENS = itertools.count()
_STOPS_LOCK = threading.Lock()


def at_stop(undo: Callable[[], None]) -> int:
    """Register ``undo`` (end a child, remove a temporary file or folder) to be run when
    the command stops, whatever the way: :func:`run_stops` runs it at the end of every
    command (normal end, error, Ctrl-C, SIGTERM: :func:`hapsim.cli.main`) and at the
    interpreter's exit (``atexit``, for the Python API).

    Parameters
    ----------
    undo : callable
        ``undo()``, idempotent; an exception it raises is ignored.

    Returns
    -------
    int
        The token for :func:`done`, once the owner has undone it itself.
    """
    with _STOPS_LOCK:
        token = next(_TOKENS)
        _STOPS[token] = undo
    return token


def done(token: int | None) -> None:
    """Forget the ``undo`` of :func:`at_stop` (its owner has run it).

    Parameters
    ----------
    token : int or None
        :func:`at_stop`'s token; None, or one already forgotten: nothing happens.
    """
    with _STOPS_LOCK:
        _STOPS.pop(token, None)


def run_stops() -> None:
    """Run every registered ``undo`` not yet done, the latest first, and forget them.

    Notes
    -----
    Each runs once even when this is called from two places (the command's end, then
    ``atexit``); an exception (a second Ctrl-C included) from one does not keep the others
    from running.
    """
    while True:
        with _STOPS_LOCK:
            if not _STOPS:
                return
            token = max(_STOPS)
            undo = _STOPS.pop(token)
        try:
            undo()
        except BaseException:  # noqa: BLE001 - the others must still run
            pass


atexit.register(run_stops)


def inside_import(frame) -> bool:
    """Whether ``frame`` or one of its callers is in the import machinery.

    Parameters
    ----------
    frame : frame or None
        A signal handler's frame.

    Returns
    -------
    bool
        True when an exception raised there could come out of the import as another one
        (numpy turns a KeyboardInterrupt into an ``ImportError``): the process must end at
        once instead (:func:`hapsim.cli.main`'s SIGTERM, ``hapsim._quiet_interrupt_at_start``).
    """
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def package_root() -> str:
    """The directory holding the ``hapsim`` package.

    Returns
    -------
    str
        Absolute path (the parent of ``hapsim/``).
    """
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def child_env() -> dict:
    """A copy of ``os.environ`` with :func:`package_root` first on ``PYTHONPATH`` and
    ``HAPSIM_STATUS=0`` (no second status line on a shared terminal:
    :class:`hapsim.progress.Watch`).

    Returns
    -------
    dict
        The environment to pass to ``subprocess.Popen(env=...)``.
    """
    env = dict(os.environ)
    env["HAPSIM_STATUS"] = "0"      # the parent's status line is enough (progress.Watch)
    root = package_root()
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


class PtyChild:
    """The host's side of a child process served on a pseudo-terminal's master that writes
    a JSON report when it exits (the embedded mocks): its end and its report.

    A subclass starts the child in its ``__init__``: :meth:`open_pty` (the pty, the
    report's path), then :meth:`start` (the child, given the master).

    Attributes
    ----------
    proc : subprocess.Popen
        The child.
    report_path : str
        The JSON file the child writes on exit (removed by :meth:`close`).
    _slave : int or None
        This object's descriptor of the pty's slave, kept open until the host has opened
        the port (so the child never reads EIO before), closed by :meth:`release_slave`.
    """

    proc: subprocess.Popen | None = None
    report_path: str
    port: str
    _slave: int | None = None

    def open_pty(self, prefix: str) -> int:
        """A new pseudo-terminal, its slave in raw mode and kept open (``port`` its path),
        and a fresh ``report_path`` (a name in the temporary directory, no file yet).

        Parameters
        ----------
        prefix : str
            The report file's name prefix.

        Returns
        -------
        int
            The master's descriptor, for :meth:`start` (which closes it).
        """
        import pty
        import tty
        master, slave = pty.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        self._slave = slave
        self._new_report(prefix)
        return master

    def open_link(self, prefix: str) -> int:
        """A new emulated link (``emulated://NAME``, :mod:`hapsim.drivers.urlhandler`):
        a listening packet socket for the child, ``port`` its URL, and a fresh
        ``report_path`` (as :meth:`open_pty`). The child takes the host's writes at the
        times the kernel stamped them with (:mod:`hapsim.emulated.stamped_link`).

        Parameters
        ----------
        prefix : str
            The report file's name prefix.

        Returns
        -------
        int
            The listening socket's descriptor, for :meth:`start` (which closes it).

        Raises
        ------
        OSError
            No Unix packet socket here.
        """
        import socket
        name = f"hapsim-board-{os.getpid()}-{os.urandom(4).hex()}"
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            sock.bind("\0" + name)             # (an abstract name: no file to remove)
            sock.listen(1)
        except OSError:
            sock.close()
            raise
        self.port = "emulated://" + name
        self._new_report(prefix)
        return sock.detach()

    def _new_report(self, prefix: str) -> None:
        import tempfile
        fd, self.report_path = tempfile.mkstemp(prefix=prefix, suffix=".json")
        os.close(fd)
        os.unlink(self.report_path)
        # the child writes its report when it exits: a stop at any moment from now on
        # (Ctrl-C during the imports, before the owner's try) ends it and removes that
        self._stop_token = at_stop(self.close)

    def start(self, cmd: list, master: int) -> None:
        """Start the child ``cmd`` with ``master`` passed (``pass_fds``), this package
        first on its path (:func:`child_env`), no stdin, in a new session (a Ctrl-C at the
        terminal reaches only the host); ``master`` is closed here either way.

        Parameters
        ----------
        cmd : list of str
            The child's command line (it names ``master`` and ``report_path``).
        master : int
            :meth:`open_pty`'s descriptor.

        Raises
        ------
        OSError
            The child cannot be started.
        """
        # a SIGINT or SIGTERM inside Popen (after the fork, before it returns) raised
        # there and lost the child: no handle to end it, and its report, written when
        # it exited, was left in /tmp (a Ctrl-C 0.23 s into `hapsim run`, once in a
        # fresh-clone suite). Held until self.proc is set, then delivered: the stop's
        # close() ends the child and removes the report.
        held = _hold_stop_signals()
        try:
            self.proc = subprocess.Popen(cmd, pass_fds=(master,), env=child_env(),
                                         stdin=subprocess.DEVNULL, start_new_session=True)
        finally:
            os.close(master)
            _deliver_stop_signals(held)

    def release_slave(self) -> None:
        """Close this object's copy of the slave (once the host has opened the port)."""
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None

    def end(self, grace_s: float = 2.0) -> None:
        """SIGTERM the child (a mock zeroes its force and writes its report), SIGKILL it
        after ``grace_s`` [s]; it is reaped either way.

        Parameters
        ----------
        grace_s : float
            Longest wait after the SIGTERM [s].
        """
        self.proc.terminate()
        try:
            self.proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def report(self, timeout: float = 3.0) -> dict | None:
        """Wait for the child to exit and return its JSON report.

        Parameters
        ----------
        timeout : float
            Longest wait for the child to exit by itself [s] (it does when the host closes
            the port); then it is ended (:meth:`end`).

        Returns
        -------
        dict or None
            The child's report (what it holds: the subclass's ``report_path``); None when
            it wrote none (killed, or crashed).
        """
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.end()
        try:
            with open(self.report_path) as fh:
                return json.load(fh)
        except (OSError, ValueError):
            return None

    def close(self) -> None:
        """Close the slave, end the child if still running, remove the report file
        (idempotent)."""
        self.release_slave()
        proc = getattr(self, "proc", None)      # None: stopped before the child started
        if proc is not None and proc.poll() is None:
            self.end()
        try:
            os.unlink(self.report_path)
        except OSError:
            pass
        done(getattr(self, "_stop_token", None))


def _hold_stop_signals():
    """SIGINT and SIGTERM recorded, not acted on, until :func:`_deliver_stop_signals`
    (main thread only: elsewhere Python runs no handler); the previous handlers and the
    signals that came, or None."""
    import signal
    if threading.current_thread() is not threading.main_thread():
        return None
    came: list = []
    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        old[sig] = signal.getsignal(sig)
        if old[sig] in (signal.SIG_IGN, None):
            continue
        signal.signal(sig, lambda s, f: came.append(s))
    return old, came


def _deliver_stop_signals(held) -> None:
    """The previous handlers back, then each signal that came while held sent again."""
    import signal
    if held is None:
        return
    old, came = held
    for sig, h in old.items():
        if h not in (signal.SIG_IGN, None):
            signal.signal(sig, h)
    for sig in dict.fromkeys(came):
        signal.raise_signal(sig)


class StopFlag:
    """A flag a signal handler sets to end the loop cleanly (zero force, STOP, flush).

    Attributes
    ----------
    set : bool
        True once a stop was requested (stored in :attr:`shared`).
    signal : int or None
        Number of the signal that set it, if any.
    shared : ndarray of int64, shape (1,)
        The flag itself (1: stop requested), read by the compiled loop
        (:mod:`hapsim.host.fastloop`) while it runs without the GIL.
    """

    def __init__(self) -> None:
        import numpy as np   # here: the command line sizes BLAS pools before numpy loads
        self.shared = np.zeros(1, dtype=np.int64)
        self.signal = None

    @property
    def set(self) -> bool:
        """True once a stop was requested."""
        return bool(self.shared[0])

    @set.setter
    def set(self, value: bool) -> None:
        self.shared[0] = 1 if value else 0

    #: What asked for the stop when no signal did (the live view's stop button), said
    #: as the loop's stop reason; None otherwise.
    reason: str | None = None

    def request(self, signum: int | None = None, reason: str | None = None) -> None:
        """Request a stop (safe to call from a signal handler: two attribute stores).

        Parameters
        ----------
        signum : int, optional
            Number of the signal that asked (``signal.SIGINT``, ``signal.SIGTERM``); the
            loop reports ``"signal NAME"`` as the stop reason. None: another caller.
        reason : str, optional
            The stop reason another caller reports (e.g. ``"view: stop button"``).
        """
        if reason is not None:
            self.reason = reason
        self.set = True
        self.signal = signum


class HandledBytes:
    """A lockstep mock's account of the bytes it has handled, shared with the host.

    A mock stepped one period per command (named lockstep, a test device) has no time of
    its own: a slow mock process and a lost packet cannot be told apart by how long the
    host waited. This account tells them apart without time: the mock publishes, after
    each read it has wholly handled (parsed, stepped, answered), the bytes it has read
    from the host and the bytes it has written to it. When the first equals what the
    host wrote and the second what the host read, the mock has nothing more to say: a
    command still unanswered then got no answer (a packet lost or damaged by the link's
    injected faults), and asking again steps the mock exactly as on a quiet host. There
    is no such account on a real wire (the driver protocols have no sequence number):
    hardware and a mock on its own clock never have one.

    The account is a 24-byte file mapped by both processes: a sequence word (odd while
    the mock writes), then the two totals, little-endian uint64 (a seqlock: the reader
    retries a torn read).

    Parameters
    ----------
    path : str
        The file (created by :meth:`create`).
    """

    SIZE = 24

    def __init__(self, path: str) -> None:
        import mmap
        self.path = path
        with open(path, "r+b") as fh:
            self._mm = mmap.mmap(fh.fileno(), self.SIZE)
        self._seq = 0

    @classmethod
    def create(cls, prefix: str = "hapsim-handled-") -> "HandledBytes":
        """A new account (zeros) in the temporary directory.

        Parameters
        ----------
        prefix : str
            The file's name prefix.

        Returns
        -------
        HandledBytes
        """
        import tempfile
        fd, path = tempfile.mkstemp(prefix=prefix)
        os.write(fd, bytes(cls.SIZE))
        os.close(fd)
        return cls(path)

    def publish(self, read: int, written: int) -> None:
        """The mock's side: ``read`` bytes read from the host, ``written`` written to it,
        every one handled (totals since the start).

        Parameters
        ----------
        read, written : int
            The totals [bytes], >= 0 (stored as uint64).
        """
        import struct
        mm = self._mm
        self._seq += 1
        struct.pack_into("<Q", mm, 0, self._seq)          # odd: being written
        struct.pack_into("<QQ", mm, 8, int(read), int(written))
        self._seq += 1
        struct.pack_into("<Q", mm, 0, self._seq)

    def totals(self) -> tuple[int, int]:
        """The host's side: the last totals published, ``(read, written)`` [bytes].

        Returns
        -------
        tuple of int
            ``(read, written)`` [bytes], read whole (a torn read retried).
        """
        import struct
        mm = self._mm
        while True:
            s1 = struct.unpack_from("<Q", mm, 0)[0]
            r, w = struct.unpack_from("<QQ", mm, 8)
            if not s1 & 1 and struct.unpack_from("<Q", mm, 0)[0] == s1:
                return r, w

    def close(self, unlink: bool = False) -> None:
        """Unmap (idempotent); ``unlink``: remove the file too (the host's side).

        Parameters
        ----------
        unlink : bool
            Also remove the file (a missing one ignored).
        """
        try:
            self._mm.close()
        except (BufferError, ValueError):      # pragma: no cover
            pass
        if unlink:
            try:
                os.unlink(self.path)
            except OSError:
                pass
