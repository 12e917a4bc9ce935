"""Opening a JACK client (:func:`open_client`): a server that runs but fails one open
handshake under load is tried again; no server at all is said at once. Ending a Python
process callback before its client is deactivated, and its Python notification callbacks
before it is closed (:class:`PythonProcessEnd`: jack2 cancels a thread still in Python,
and the process then hangs for ever). Used by
:class:`hapsim.audio.live.JackOutput` (the 1-D and the n-D live sound alike)."""

from __future__ import annotations

import os
import threading
import time

from hapsim.errors import DeviceError

__all__ = ["open_client", "OPEN_RETRY_S", "PythonProcessEnd", "END_WAIT_S"]

#: How long [s] :meth:`PythonProcessEnd.end` waits for the process thread to end itself:
#: a period or two on a running server (5.3 ms at 256 frames and 48 kHz); a server that
#: runs no cycle (stopped, or its driver stalled) leaves the thread waiting in JACK's own
#: code, outside Python, where cancelling it is harmless.
END_WAIT_S = 2.0

#: Waits [s] before the second and third attempt to open a JACK client on a server that
#: runs: on a loaded machine its open handshake can fail once (its socket read cut short:
#: "JackSocketClientChannel read fail", "Cannot open hapsim client"; seen in a loaded
#: test suite) and answer the next. No server at all (``server_failed``: the library
#: could not connect) is said at once.
OPEN_RETRY_S = (0.2, 0.5)


def open_client(jack, name: str, server: str | None):
    """A JACK client on ``server`` (never starting one), tried again after each of
    :data:`OPEN_RETRY_S` when the open fails on a server that runs (jackd2's
    ``jack_client_open`` sets ``JackServerFailed`` when it cannot connect at all, only
    ``JackFailure`` when the connected server's open request fails).

    Parameters
    ----------
    jack : module
        The ``jack`` module (JACK-Client).
    name : str
        The client's name.
    server : str or None
        The server's name (None: the default server).

    Returns
    -------
    jack.Client

    Raises
    ------
    DeviceError
        No server of that name runs, or every attempt failed (the last status named).
    """
    tries = len(OPEN_RETRY_S) + 1
    for i in range(tries):
        try:
            return jack.Client(name, no_start_server=True, servername=server)
        except jack.JackOpenError as exc:
            named = f"JACK server{' ' + repr(server) if server else ''}"
            if exc.status.server_failed:
                raise DeviceError(f"no {named} running ({exc})") from None
            if i + 1 == tries:
                raise DeviceError(f"the {named} runs but did not open hapsim's client "
                                  f"({exc}; {tries} attempts over "
                                  f"{sum(OPEN_RETRY_S):g} s)") from None
            time.sleep(OPEN_RETRY_S[i])


class PythonProcessEnd:
    """Lets a Python JACK process callback end its thread itself before the client is
    deactivated, so that no thread dies inside Python.

    jack2 stops a client's process thread in ``jack_deactivate`` (and so in
    ``jack_client_close``) with ``pthread_cancel`` and ``pthread_join``
    (``common/JackClient.cpp``, ``JackClient::Deactivate``: ``fThread.Kill()``;
    ``posix/JackPosixThread.cpp``, ``Kill``), after the server has taken the client out
    of its graph. A cycle still running then (a callback late, or its thread waiting for
    the GIL on a loaded machine) is cancelled inside Python: the thread dies holding the
    GIL (or the GIL's mutex), and the process waits for it for ever (seen: a test's
    recording client, its main thread in ``take_gil`` after ``deactivate()``, the
    process thread gone).

    jack2 ends the thread cleanly when the process callback returns non-zero
    (``JackClient::CycleSignalAux`` → ``End``: the client marked inactive, the thread's
    ``pthread_exit``, outside Python); JACK-Client returns non-zero for a callback that
    raises ``jack.CallbackExit``. The callback calls :meth:`check` first; :meth:`end`
    asks it to raise, and waits until its thread has exited. ``deactivate()`` then finds
    the client inactive and cancels nothing.

    ``jack_client_close`` stops the notification thread the same way
    (``JackSocketClientChannel::Stop``), so a Python xrun or buffer-size callback running
    then hangs the process too. The server notifies a client only of the events it has a
    callback for (``fCallback``, which ``jack_set_xrun_callback`` sets on an inactive
    client): :meth:`end_notifications`, after the deactivation, unsets them and waits for
    any still running (each counted by :meth:`note`) before the close.

    Attributes
    ----------
    tid : int or None
        The process thread's native id (Linux: its ``/proc/self/task`` entry), known from
        the callback's first call.
    ending : bool
        :meth:`end` was called: the callback's next :meth:`check` raises.
    notes : int
        Notification callbacks running now (:meth:`note`).
    """

    def __init__(self) -> None:
        self.tid: int | None = None
        self.ending = False
        self.notes = 0

    def note(self, delta: int) -> None:
        """A notification callback begins (``+1``, its first line) or returns (``-1``,
        in its ``finally``).

        Parameters
        ----------
        delta : int
            ``+1`` or ``-1``, added to :attr:`notes`.
        """
        self.notes += delta

    def end_notifications(self, jack, client, timeout_s: float = END_WAIT_S) -> bool:
        """After ``client.deactivate()``: unset its xrun and buffer-size callbacks (the
        server then sends neither) and wait until none runs.

        Parameters
        ----------
        jack : module
            The ``jack`` module (JACK-Client).
        client : jack.Client
            The deactivated client.
        timeout_s : float
            The longest wait [s].

        Returns
        -------
        bool
            True when no notification callback runs any more.
        """
        lib, ffi = jack._lib, jack._ffi
        lib.jack_set_xrun_callback(client._ptr, ffi.NULL, ffi.NULL)
        lib.jack_set_buffer_size_callback(client._ptr, ffi.NULL, ffi.NULL)
        # (one already read from the socket may be waiting for the GIL: let it in)
        time.sleep(0.02)
        t_end = time.monotonic() + timeout_s
        while self.notes and time.monotonic() < t_end:
            time.sleep(0.001)
        return not self.notes

    def check(self, jack) -> None:
        """The process callback's first call: note its thread; raise
        ``jack.CallbackExit`` once :meth:`end` asked for it.

        Parameters
        ----------
        jack : module
            The ``jack`` module (JACK-Client).

        Raises
        ------
        jack.CallbackExit
            After :meth:`end`: JACK-Client's wrapper returns non-zero, jack2 ends the
            thread.
        """
        if self.tid is None:
            self.tid = threading.get_native_id()
        if self.ending:
            raise jack.CallbackExit

    def end(self, timeout_s: float = END_WAIT_S) -> bool:
        """Ask the callback to end its thread, and wait until the thread has exited
        (polling ``/proc/self/task/<tid>`` every millisecond).

        Parameters
        ----------
        timeout_s : float
            The longest wait [s] (:data:`END_WAIT_S`).

        Returns
        -------
        bool
            True when the thread is known to have exited; False when the wait ran out
            (no cycle ran: the thread waits in JACK's code, outside Python) or where
            ``/proc`` shows no threads (the caller then deactivates as before).
        """
        self.ending = True
        if not os.path.isdir("/proc/self/task"):
            return False
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if self.tid is not None and not os.path.exists(f"/proc/self/task/{self.tid}"):
                return True
            time.sleep(0.001)
        return False
