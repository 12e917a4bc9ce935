"""Real-time scheduling for the duration of a loop (Linux ``SCHED_FIFO``), where permitted.

A Python loop at 1 kHz on a shared machine is preempted by every other runnable process:
on a 2-core machine with three CPU-bound processes, ``hapsim run configs/wall.yaml`` saw
124 late ticks in 1,000 and a turnaround p99 of 970 us under the default policy, against 1
late tick and 67 us under ``SCHED_FIFO`` priority 10. Linux's real-time throttling
(``/proc/sys/kernel/sched_rt_runtime_us``, 95 % by default) keeps a runaway real-time
thread from locking a core.
"""

from __future__ import annotations

import os

__all__ = ["RealtimePriority", "sleep_until_ns"]


class RealtimePriority:
    """Context manager: the calling thread runs ``SCHED_FIFO`` at ``priority`` inside it.

    Processes started inside inherit the policy (it survives fork and exec), so the embedded
    mock device gets it too. Where the OS refuses (no ``CAP_SYS_NICE``, no ``SCHED_FIFO`` on
    the platform) nothing changes and :attr:`note` says why; the previous policy is restored
    on exit.

    Parameters
    ----------
    priority : int
        ``SCHED_FIFO`` priority, 1..99; 0 leaves scheduling alone.

    Attributes
    ----------
    active : bool
        Whether real-time scheduling was obtained.
    note : str
        What happened, for the loop report (e.g. ``"SCHED_FIFO 10"``).
    """

    def __init__(self, priority: int) -> None:
        if not 0 <= int(priority) <= 99:
            from hapsim.errors import ConfigError
            raise ConfigError(f"must be 0 (off) or a SCHED_FIFO priority 1..99, got {priority}",
                              key="--rt-priority")
        self.priority = int(priority)
        self.active = False
        self.note = "normal (not requested)"
        self._saved: tuple[int, object] | None = None

    def __enter__(self) -> "RealtimePriority":
        if self.priority == 0:
            return self
        if not hasattr(os, "sched_setscheduler"):
            self.note = "normal (SCHED_FIFO not available on this platform)"
            return self
        try:
            saved = (os.sched_getscheduler(0), os.sched_getparam(0))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
        except OSError as exc:
            self.note = f"normal (SCHED_FIFO {self.priority} refused: {exc.strerror or exc})"
            return self
        self._saved = saved
        self.active = True
        self.note = f"SCHED_FIFO {self.priority}"
        return self

    def __exit__(self, *exc: object) -> None:
        if self._saved is not None:
            policy, param = self._saved
            try:
                os.sched_setscheduler(0, policy, param)
            except OSError:  # pragma: no cover - lowering priority is always permitted
                pass
            self._saved = None


def _libc_clock_nanosleep():
    """libc's ``clock_nanosleep`` through ctypes (the call releases the GIL), or None."""
    import ctypes
    import ctypes.util
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.clock_nanosleep
    except (OSError, AttributeError):  # pragma: no cover - not Linux / glibc
        return None
    fn.argtypes = (ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p)
    fn.restype = ctypes.c_int
    return fn


_CLOCK_NANOSLEEP = _libc_clock_nanosleep()
_CLOCK_MONOTONIC = 1
_TIMER_ABSTIME = 1


def sleep_until_ns(deadline_ns: int) -> None:
    """Sleep until ``time.monotonic_ns()`` reaches ``deadline_ns``, without spinning.

    An absolute-deadline sleep (POSIX ``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)``):
    no drift from computing a relative duration late, restarted after a signal; under
    ``SCHED_FIFO`` the kernel's timer slack is 0, so the wake-up is as early as the timer
    allows and a real-time thread leaves its core to others meanwhile (a spin would be
    throttled by ``sched_rt_runtime_us``). Falls back on ``time.sleep``.

    Parameters
    ----------
    deadline_ns : int
        Deadline on ``time.monotonic_ns`` (CLOCK_MONOTONIC) [ns]; in the past: no sleep.
    """
    import ctypes
    import time

    if _CLOCK_NANOSLEEP is None:  # pragma: no cover - not Linux / glibc
        rem = deadline_ns - time.monotonic_ns()
        if rem > 0:
            time.sleep(rem * 1e-9)
        return
    ts = (ctypes.c_long * 2)(deadline_ns // 1_000_000_000, deadline_ns % 1_000_000_000)
    while _CLOCK_NANOSLEEP(_CLOCK_MONOTONIC, _TIMER_ABSTIME, ctypes.byref(ts), None) == 4:
        pass    # EINTR: a signal (its Python handler runs after the return); sleep on
