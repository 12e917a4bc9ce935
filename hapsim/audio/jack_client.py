"""Opening a JACK client (:func:`open_client`): a server that runs but fails one open
handshake under load is tried again; no server at all is said at once. Used by
:class:`hapsim.audio.live.JackOutput` (the 1-D and the n-D live sound alike)."""

from __future__ import annotations

import time

from hapsim.errors import DeviceError

__all__ = ["open_client", "OPEN_RETRY_S"]

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
