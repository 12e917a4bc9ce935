"""Per-sample telemetry of the host loop: preallocated arrays, written off the hot path.

The loop writes one row per sample *by index* into arrays allocated before it starts
(CONVENTIONS §4: no allocation, no file I/O in the hot loop); the file is written once, after
the loop (or after a signal stopped it), atomically: temporary file, then ``os.replace``.

Columns
-------
``time`` [s]
    Device time of the position sample (STATE.time_us / 1e6).
``position`` [m]
    Device position of the sample.
``force`` [N]
    Force sent in answer (after the host-side clamp).
``seq`` [-]
    STATE sequence number (int64).
``turnaround_us`` [us]
    Host time from the STATE frame read to the FORCE frame written.
``late`` [-]
    1 when the device reported holding an older force at this tick (its FORCE came too
    late: ``seq - force_seq != d`` or STATUS_OVERRUN), else 0 (int8).
"""

from __future__ import annotations

import os

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["Telemetry", "load_telemetry", "COLUMNS"]

#: Column names, in file order.
COLUMNS = ("time", "position", "force", "seq", "turnaround_us", "late")


class Telemetry:
    """Preallocated telemetry buffer of a run.

    Parameters
    ----------
    capacity : int
        Largest number of samples recorded (>= 0); rows beyond it are not recorded.

    Attributes
    ----------
    time, position, force, turnaround_us : ndarray of float64, shape (capacity,)
        Columns [s], [m], [N], [us]; only the first :attr:`n` rows are valid.
    seq : ndarray of int64, shape (capacity,)
        STATE sequence numbers.
    late : ndarray of int8, shape (capacity,)
        1 where the device held an older force (late FORCE).
    n : int
        Rows recorded.
    """

    def __init__(self, capacity: int) -> None:
        capacity = int(capacity)
        if capacity < 0:
            raise ValueError(f"capacity must be >= 0, got {capacity}")
        self.capacity = capacity
        self.time = np.zeros(capacity)
        self.position = np.zeros(capacity)
        self.force = np.zeros(capacity)
        self.seq = np.zeros(capacity, dtype=np.int64)
        self.turnaround_us = np.zeros(capacity)
        self.late = np.zeros(capacity, dtype=np.int8)
        self.n = 0

    def columns(self) -> dict[str, np.ndarray]:
        """Views of the valid rows, by column name (shape (n,) each)."""
        n = self.n
        return {"time": self.time[:n], "position": self.position[:n], "force": self.force[:n],
                "seq": self.seq[:n], "turnaround_us": self.turnaround_us[:n],
                "late": self.late[:n]}

    def write(self, path: str) -> str:
        """Write the valid rows to ``path`` atomically.

        Parameters
        ----------
        path : str
            ``.npz`` (one array per column) or ``.csv`` (header ``time,position,...``).

        Returns
        -------
        str
            ``path``.

        Raises
        ------
        ConfigError
            On an unknown extension.
        OSError
            When the file cannot be written (the temporary file is removed).
        """
        ext = os.path.splitext(path)[1].lower()
        if ext not in (".npz", ".csv"):
            raise ConfigError(f"unknown telemetry format {ext or '(none)'!r}; valid: .npz, .csv",
                              key="--telemetry")
        cols = self.columns()
        tmp = f"{path}.partial"
        try:
            if ext == ".npz":
                with open(tmp, "wb") as fh:
                    np.savez(fh, **cols)
            else:
                data = np.column_stack([cols[c].astype(float) for c in COLUMNS])
                np.savetxt(tmp, data, delimiter=",", header=",".join(COLUMNS), comments="",
                           fmt=["%.9f", "%.17g", "%.17g", "%d", "%.1f", "%d"])
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        return path


def load_telemetry(path: str) -> dict[str, np.ndarray]:
    """Read a telemetry file written by :meth:`Telemetry.write`.

    Parameters
    ----------
    path : str
        ``.npz`` or ``.csv`` file.

    Returns
    -------
    dict of str to ndarray
        The columns of :data:`COLUMNS`, each shape (n,); ``seq`` as int64, ``late`` int8.
    """
    if path.lower().endswith(".npz"):
        with np.load(path) as z:
            return {c: np.asarray(z[c]) for c in COLUMNS}
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    out = {c: data[:, i] for i, c in enumerate(COLUMNS)}
    out["seq"] = out["seq"].astype(np.int64)
    out["late"] = out["late"].astype(np.int8)
    return out
