"""Suite-wide guards.

A test that changes the process's signal dispositions or mask and leaves them so changes
every process the same pytest worker starts afterwards: SIG_IGN and a blocked mask are
inherited across ``exec``. A SIGINT ignored by a leaked ``signal.signal(SIGINT, SIG_IGN)``
makes the Ctrl-C tests of later children exit 0 (their SIGINT never arrives: exactly the
failure they showed once, ``(0, '')``), depending on which tests xdist had given the worker
before, a failure that follows the load, not the code. After each test the dispositions
and the mask are put back as they were; a test that left SIGINT or SIGTERM ignored or
blocked (what children inherit) fails, naming it. (Importing PortAudio blocks SIGPIPE in the
mask: restored without a failure, Python's children ignore SIGPIPE anyway.)
"""

from __future__ import annotations

import signal
import threading

import pytest

#: Restored after every test.
_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGPIPE)
#: A test must leave these as it found them (the Ctrl-C and service-manager tests' signals).
_WATCHED = {signal.SIGINT, signal.SIGTERM}


def _mask() -> set:
    return set(signal.pthread_sigmask(signal.SIG_BLOCK, []))


@pytest.fixture(autouse=True)
def _signals_left_as_found():
    """Restore the signal dispositions and mask after each test; fail one that left
    SIGINT or SIGTERM ignored or blocked."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = {s: signal.getsignal(s) for s in _SIGNALS}
    mask = _mask()
    yield
    changed = {}
    for s in _SIGNALS:
        now = signal.getsignal(s)
        if now is not before[s] and now != before[s] and before[s] is not None:
            # what a child inherits across exec: an ignored signal (a Python handler is
            # reset to the default there; it is restored here all the same)
            if s in _WATCHED and now is signal.SIG_IGN:
                changed[signal.Signals(s).name] = (before[s], now)
            signal.signal(s, before[s])
    left = _mask()
    if left != mask:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
    blocked = sorted(signal.Signals(s).name for s in (left - mask) & _WATCHED)
    assert not changed and not blocked, (
        f"the test left signal state changed (inherited by every process this worker "
        f"starts next; restored now): dispositions {changed}, newly blocked {blocked}")
