"""A small progress bar for long command-line work (stderr, only on a terminal)."""

from __future__ import annotations

import sys
import threading
import time
from typing import TextIO

__all__ = ["Progress", "Watch"]


class Progress:
    """Progress bar on ``stream`` that appears only when work lasts over ``delay`` seconds.

    Parameters
    ----------
    total : int
        Units of work in all (>= 0).
    label : str
        What is being done, printed before the bar.
    unit : str
        Name of a unit of work.
    stream : file-like, optional
        Where to draw (default ``sys.stderr``); nothing is drawn unless it is a terminal
        or ``force`` is True.
    delay : float
        Seconds before the bar first appears [s].
    force : bool
        Draw even when ``stream`` is not a terminal (one line per update).
    """

    def __init__(self, total: int, label: str, unit: str = "", stream: TextIO | None = None,
                 delay: float = 1.0, force: bool = False) -> None:
        self.total = max(int(total), 0)
        self.label = label
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.delay = delay
        self.enabled = force or bool(getattr(self.stream, "isatty", lambda: False)())
        self._t0 = time.monotonic()
        self._drawn = False
        self.last_done: int | None = None

    def update(self, done: int, total: int | None = None) -> None:
        """Report progress and redraw the bar (nothing before ``delay`` or off a terminal).

        Parameters
        ----------
        done : int
            Units of work finished so far (0..total).
        total : int, optional
            New total, when it changed (keeps the previous one when None).

        Notes
        -----
        The estimated time left is ``elapsed (1 - f) / f`` [s], ``f = done / total``
        (constant rate assumed).
        """
        if total is not None:
            self.total = total
        self.last_done = done
        if not self.enabled or time.monotonic() - self._t0 < self.delay:
            return
        self._draw(done)

    def redraw(self) -> None:
        """Draw the bar again with the last count and the time now (a :class:`Watch`
        does, while the work between two updates is long)."""
        if self.last_done is not None and self.enabled:
            self._draw(self.last_done)

    def _draw(self, done: int) -> None:
        frac = done / self.total if self.total else 1.0
        width = 30
        fill = int(round(frac * width))
        elapsed = time.monotonic() - self._t0
        eta = elapsed * (1 - frac) / frac if frac > 0 else float("nan")
        self.stream.write(f"\r{self.label} [{'#' * fill}{'.' * (width - fill)}] "
                          f"{100 * frac:5.1f}% {done}/{self.total} {self.unit} "
                          f"eta {eta:5.1f} s, {elapsed:.0f} s so far ")
        self.stream.flush()
        self._drawn = True

    def __enter__(self) -> "Progress":
        _BARS.append(self)
        return self

    def __exit__(self, *exc: object) -> None:
        if self in _BARS:
            _BARS.remove(self)
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()


#: The bars being drawn now (the watch redraws the latest instead of its own line).
_BARS: list = []


class _Watched:
    """A text stream whose writes :class:`Watch` sees (it clears its status line first)."""

    def __init__(self, stream, watch: "Watch") -> None:
        self._stream = stream
        self._watch = watch

    def write(self, text: str) -> int:
        """Write ``text`` after clearing the watch's line; the watch's clock restarts."""
        with self._watch.lock:
            self._watch.clear()
            n = self._stream.write(text)
            self._watch.last = time.monotonic()
            return n

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


class Watch:
    """Say on a terminal that a command is still working once it has been silent for
    ``quiet`` seconds: a status line on stderr (``hapsim zwidth: working ... 7 s``, or the
    latest :class:`Progress` bar redrawn), cleared before anything else is written.

    Parameters
    ----------
    label : str
        What is working (``hapsim zwidth``); :attr:`label` may be changed later (the
        command is known once its arguments are parsed) and :attr:`doing` says the step.
    quiet : float
        Silence before the line appears [s] (0.5: with the tick, at most 0.7 s after the
        last output, and under a second after the interpreter's start).
    tick : float
        Period of the watch's thread [s].

    Notes
    -----
    Only when ``sys.stderr`` is a terminal (a pipe or a file gets nothing extra) and the
    environment does not set ``HAPSIM_STATUS=0`` (the hapsim processes hapsim starts, e.g.
    the embedded mock sharing the terminal, set it: :func:`hapsim.spawn.child_env`): while
    active, ``sys.stdout`` and ``sys.stderr`` are wrapped so that each write clears the
    status line and restarts the clock (stdout counts only when it is the terminal too).
    The thread is a daemon: it never keeps the process alive. Issue 31: ``hapsim zwidth``
    was silent 28 s, ``hapsim identify`` 9 s, a numba compile 12.5 s.
    """

    def __init__(self, label: str, quiet: float = 0.5, tick: float = 0.2) -> None:
        self.label = label
        self.doing = ""
        self.quiet = quiet
        self.tick = tick
        self.lock = threading.RLock()
        self.last = time.monotonic()
        self._t0 = self.last
        self._drawn = False
        self._stop = threading.Event()
        self._saved = None
        self._err = None

    def clear(self) -> None:
        """Erase the status line if drawn (caller holds :attr:`lock`)."""
        if self._drawn:
            self._drawn = False
            try:
                self._err.write("\r\033[K")
                self._err.flush()
            except (OSError, ValueError):
                pass

    def _draw(self) -> None:
        now = time.monotonic()
        bar = _BARS[-1] if _BARS else None
        if bar is not None and bar.enabled and bar.last_done is not None:
            bar.redraw()             # through the wrapped stream: counts as output
            return
        with self.lock:
            what = f" ({self.doing})" if self.doing else ""
            try:
                self._err.write(f"\r\033[K{self.label}: working{what} ... "
                                f"{now - self._t0:.0f} s")
                self._err.flush()
            except (OSError, ValueError):
                return
            self._drawn = True

    def _run(self) -> None:
        while not self._stop.wait(self.tick):
            if time.monotonic() - self.last >= self.quiet:
                self._draw()

    def stop(self) -> None:
        """Draw nothing more (a command that serves until stopped: ``hapsim mock``)."""
        self._stop.set()
        with self.lock:
            if self._err is not None:
                self.clear()

    def __enter__(self) -> "Watch":
        import os
        err = sys.stderr
        if (not bool(getattr(err, "isatty", lambda: False)())
                or os.environ.get("HAPSIM_STATUS") == "0"):
            return self
        self._err = err
        self._saved = (sys.stdout, sys.stderr)
        sys.stderr = _Watched(err, self)
        out = sys.stdout
        if bool(getattr(out, "isatty", lambda: False)()):
            sys.stdout = _Watched(out, self)
        threading.Thread(target=self._run, name="hapsim-watch", daemon=True).start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._saved is None:
            return
        self._stop.set()
        with self.lock:
            self.clear()
        sys.stdout, sys.stderr = self._saved
        self._saved = None
