"""A small progress bar for long command-line work (stderr, only on a terminal)."""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["Progress"]


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
        if not self.enabled or time.monotonic() - self._t0 < self.delay:
            return
        frac = done / self.total if self.total else 1.0
        width = 30
        fill = int(round(frac * width))
        elapsed = time.monotonic() - self._t0
        eta = elapsed * (1 - frac) / frac if frac > 0 else float("nan")
        self.stream.write(f"\r{self.label} [{'#' * fill}{'.' * (width - fill)}] "
                          f"{100 * frac:5.1f}% {done}/{self.total} {self.unit} "
                          f"eta {eta:5.1f} s ")
        self.stream.flush()
        self._drawn = True

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: object) -> None:
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()
