"""Per-sample telemetry of the host loop: preallocated arrays, written off the hot path.

The loop writes one row per sample *by index* into arrays allocated before it starts
(CONVENTIONS §4: no allocation, no file I/O in the hot loop). Two ways to the disk:

- :class:`ChunkWriter`, a writer thread that appends the rows recorded so far to a chunked
  journal (``.hst``) every ``interval`` (50 ms): a ``kill -9`` of the daemon loses at most
  the rows of the last interval plus the chunk being written, and the file stays readable
  (:func:`load` reads every complete chunk and ignores a torn last one);
- :meth:`Telemetry.write`, the ``.npz`` / ``.csv`` export at the end of a run, atomic
  (temporary file, then ``os.replace``); :func:`convert` turns a journal into either.

Chunk format (version 1, little-endian), repeated::

    magic  4 bytes  b"HSTC"
    u16    version  1
    u16    hlen     length of the JSON header
    u32    plen     length of the payload [bytes]
    u32    crc      zlib.crc32 of header + payload
    header hlen bytes of UTF-8 JSON: {"columns": [...], "dtypes": [...], "rows": n,
                                      "first": index of the chunk's first row}
    payload         the columns one after the other, each ``rows`` values of its dtype

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

import json
import os
import struct
import threading
import zlib

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["Telemetry", "load_telemetry", "COLUMNS", "ChunkWriter", "load", "convert",
           "CHUNK_MAGIC", "CHUNK_VERSION"]

#: Magic bytes that open each journal chunk.
CHUNK_MAGIC = b"HSTC"
#: Journal chunk format version.
CHUNK_VERSION = 1
_HEAD = struct.Struct("<4sHHII")
_DTYPES = {"time": "<f8", "position": "<f8", "force": "<f8", "seq": "<i8",
           "turnaround_us": "<f8", "late": "|i1"}

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
        # np.zeros maps untouched zero pages: writing them once here moves the page
        # faults (the kernel allocating memory) out of the hot loop (CONVENTIONS §4)
        for a in (self.time, self.position, self.force, self.seq, self.turnaround_us,
                  self.late):
            a.fill(1)
            a.fill(0)
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
        return _write_columns(self.columns(), path)


def _write_columns(cols: dict, path: str) -> str:
    """Write columns to ``.npz`` / ``.csv`` atomically (see :meth:`Telemetry.write`)."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".npz", ".csv"):
        raise ConfigError(f"unknown telemetry format {ext or '(none)'!r}; valid: .npz, .csv",
                          key="--telemetry")
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
    if path.lower().endswith(".hst"):
        return load(path)
    if path.lower().endswith(".npz"):
        with np.load(path) as z:
            return {c: np.asarray(z[c]) for c in COLUMNS}
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    out = {c: data[:, i] for i, c in enumerate(COLUMNS)}
    out["seq"] = out["seq"].astype(np.int64)
    out["late"] = out["late"].astype(np.int8)
    return out


class ChunkWriter:
    """Writer thread appending the recorded rows of a :class:`Telemetry` to a journal.

    Parameters
    ----------
    telemetry : Telemetry
        The buffer the loop fills (rows ``[0, telemetry.n)`` are complete: the loop writes a
        row before it raises ``n``).
    path : str
        Journal file (created or truncated); conventionally ``.hst``.
    interval : float
        Time between two chunks [s] (> 0); 0.05 keeps a ``kill -9`` loss under 100 ms.

    Attributes
    ----------
    rows_written : int
        Rows on disk so far.
    chunks : int
        Chunks written.

    Raises
    ------
    OSError
        When the file cannot be created.

    Notes
    -----
    Each chunk is one ``os.write`` of header + payload on an unbuffered descriptor, so a
    killed process leaves whole chunks plus at most one torn chunk, which :func:`load`
    ignores. Not ``fsync``-ed: a process kill keeps the page cache; a power cut may lose
    more. The thread copies rows out of the preallocated arrays (its allocations happen
    off the hot loop).
    """

    def __init__(self, telemetry: "Telemetry", path: str, interval: float = 0.05) -> None:
        if not interval > 0:
            raise ValueError(f"interval must be > 0, got {interval!r}")
        self.tel = telemetry
        self.path = path
        self.interval = float(interval)
        self.rows_written = 0
        self.chunks = 0
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hapsim-telemetry",
                                        daemon=True)
        self.error = None

    def start(self) -> "ChunkWriter":
        """Start the thread; returns self."""
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._done.wait(self.interval):
            try:
                self.flush()
            except OSError as exc:      # disk full, ...: keep the loop running, report later
                self.error = exc
                return

    def flush(self) -> int:
        """Append the rows recorded since the last chunk; returns how many."""
        n = self.tel.n
        a = self.rows_written
        if n <= a:
            return 0
        cols = self.tel.columns()
        parts = [np.ascontiguousarray(cols[c][a:n], dtype=_DTYPES[c]).tobytes() for c in COLUMNS]
        payload = b"".join(parts)
        header = json.dumps({"columns": list(COLUMNS), "dtypes": [_DTYPES[c] for c in COLUMNS],
                             "rows": n - a, "first": a}, separators=(",", ":")).encode()
        crc = zlib.crc32(payload, zlib.crc32(header))
        os.write(self._fd, _HEAD.pack(CHUNK_MAGIC, CHUNK_VERSION, len(header), len(payload),
                                      crc) + header + payload)
        self.rows_written = n
        self.chunks += 1
        return n - a

    def close(self) -> None:
        """Stop the thread, write the last rows, close the file (idempotent)."""
        self._done.set()
        if self._thread.is_alive():
            self._thread.join()
        if self._fd is not None:
            try:
                self.flush()
            finally:
                os.close(self._fd)
                self._fd = None


def load(path: str, *, info: dict | None = None) -> dict[str, np.ndarray]:
    """Read a telemetry file: a chunked journal (``.hst``), ``.npz`` or ``.csv``.

    Parameters
    ----------
    path : str
        The file. A journal is read chunk by chunk; reading stops at the first chunk that
        is incomplete (torn by a kill), fails its CRC, or does not start with the magic.
    info : dict, optional
        Filled with ``chunks`` (complete chunks read), ``rows``, ``torn_bytes`` (bytes
        ignored at the end) for a journal.

    Returns
    -------
    dict of str to ndarray
        The columns of :data:`COLUMNS`, each shape (n,) (``seq`` int64, ``late`` int8).

    Raises
    ------
    OSError
        When the file cannot be read.
    """
    if not path.lower().endswith(".hst"):
        return load_telemetry(path)
    with open(path, "rb") as fh:
        data = fh.read()
    pos = 0
    parts: dict[str, list] = {c: [] for c in COLUMNS}
    chunks = rows = 0
    while pos + _HEAD.size <= len(data):
        magic, version, hlen, plen, crc = _HEAD.unpack_from(data, pos)
        if magic != CHUNK_MAGIC or version != CHUNK_VERSION:
            break
        a = pos + _HEAD.size
        b = a + hlen + plen
        if b > len(data):
            break
        header, payload = data[a:a + hlen], data[a + hlen:b]
        if zlib.crc32(payload, zlib.crc32(header)) != crc:
            break
        try:
            h = json.loads(header)
            n = int(h["rows"])
            off = 0
            got = {}
            for c, dt in zip(h["columns"], h["dtypes"]):
                size = n * np.dtype(dt).itemsize
                got[c] = np.frombuffer(payload, dtype=dt, count=n, offset=off)
                off += size
        except (ValueError, KeyError, TypeError):
            break
        for c in COLUMNS:
            parts[c].append(got.get(c, np.zeros(n, dtype=_DTYPES[c])))
        chunks += 1
        rows += n
        pos = b
    if info is not None:
        info.update(chunks=chunks, rows=rows, torn_bytes=len(data) - pos)
    return {c: (np.concatenate(parts[c]) if parts[c] else np.zeros(0, dtype=_DTYPES[c]))
            .astype(np.dtype(_DTYPES[c]).newbyteorder("=")) for c in COLUMNS}


def convert(src: str, dst: str) -> str:
    """Convert a telemetry file (e.g. a journal left by a killed run) to ``.npz`` / ``.csv``.

    Parameters
    ----------
    src : str
        ``.hst``, ``.npz`` or ``.csv``.
    dst : str
        ``.npz`` or ``.csv`` (written atomically).

    Returns
    -------
    str
        ``dst``.

    Raises
    ------
    ConfigError
        On an unknown output extension.
    """
    return _write_columns(load(src), dst)
