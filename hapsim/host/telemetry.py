"""Per-sample telemetry of the host loop: a preallocated head and ring, drained off the hot path.

The loop writes one row per sample *by index* into arrays allocated before it starts
(docs/design.md, rule 4: no allocation, no file I/O in the hot loop; data leaves through a ring
buffer). The storage is a *head* of ``head`` rows, kept for the whole run (the free
response that identification needs is at the start), followed by a *ring* of ``ring`` rows
that the rows after the head go round (:meth:`Telemetry.slot`); ``ring = 0`` is a plain
buffer of ``head`` rows, which is all a bounded run that fits in memory needs. So a run can
be open-ended: memory holds the head and the last ``ring`` rows, the journal all of them.

- :class:`ChunkWriter`, a writer thread that drains the rows recorded so far from the head
  and the ring to a chunked journal (``.hst``) every ``interval`` (50 ms): a ``kill -9`` of
  the daemon loses at most the rows of the last interval plus the chunk being written, and
  the file stays readable (:func:`load` reads every complete chunk and ignores a torn last
  one). It also journals the loop's loss / recovery events as they happen, so a killed
  run keeps its fault history. When it falls so far behind that the loop has gone round
  the ring over rows it had not written, those rows are counted (``lost_rows``), never
  waited for: the loop does not block.
- The *skipped STATEs' record*: when the loop falls behind and the backlog policy
  (``newest``) answers only the newest of several waiting STATEs, the scene still steps
  with each skipped one, whose row is never written (the answered row is flagged
  :data:`FLAG_SKIPPED`). Each such step is kept beside the rows, in arrays allocated with
  them (:attr:`Telemetry.skip_row`, :attr:`Telemetry.skip_x`: the row it preceded and its
  position; :attr:`Telemetry.skip_meta`: its seq, force_seq, status and time; both loops
  write them, nothing is allocated per sample), so that the contact replay
  (:mod:`hapsim.pipeline.contact_replay`) steps them too and the measurement puts them back
  in the record as the rows they would have been. The row format is
  unchanged; the record is bounded (``skips`` entries): past it the steps are only counted
  (:attr:`Telemetry.skip_n`) and the replay knows it (:meth:`Telemetry.skipped`). It lives
  in memory for the run's own measurement (not in the journal or the exports).
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

An *event chunk* has ``"rows": 0``, no payload and an ``"event"`` object in its header (the
loop's event: ``lost``, ``attempt``, ``recovered``, ... with ``t``, ``sample``, ``state``,
``reason``; :func:`load` returns them in ``info["events"]``); readers that do not know it
read it as an empty chunk.

Columns
-------
In file order (a chunk's header names them with their dtypes):

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
``flags`` [-]
    Bits (uint8): :data:`FLAG_LATE` (as ``late``), :data:`FLAG_LOST` (first sample after
    the device was lost and recovered: the scene restarted here), :data:`FLAG_RAMP` (force
    scaled by the ramp after a recovery), :data:`FLAG_CLAMPED` (force clamped at the
    limit), :data:`FLAG_SKIPPED` (older STATEs waiting with this one were skipped),
    :data:`FLAG_ESTIMATED` (no sample came: the position was extrapolated). Files
    written before this column existed read as 0.
``force_seq`` [-]
    STATE.force_seq of the sample (int64): the seq of the FORCE the device applied from
    this tick on (PROTOCOL.md §4; -1 in a file written before this column existed, or
    from a driver whose protocol has none). With ``status``, the account of the force the
    device applied per tick (:mod:`hapsim.applied`).
``status`` [-]
    STATE.status bits of the sample (uint16; 0 in older files).
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
           "write_journal", "save_columns", "CHUNK_HEAD", "DTYPES",
           "CHUNK_MAGIC", "CHUNK_VERSION", "FLAG_LATE", "FLAG_LOST", "FLAG_RAMP",
           "FLAG_CLAMPED", "FLAG_SKIPPED", "FLAG_ESTIMATED"]

#: Magic bytes that open each journal chunk.
CHUNK_MAGIC = b"HSTC"
#: Journal chunk format version.
CHUNK_VERSION = 1
CHUNK_HEAD = struct.Struct("<4sHHII")    # magic, version, header and payload length, crc
DTYPES = {"time": "<f8", "position": "<f8", "force": "<f8", "seq": "<i8",  # in a file
           "turnaround_us": "<f8", "late": "|i1", "flags": "|u1", "force_seq": "<i8",
           "status": "<u2"}
#: Value of a column absent from an older file (else 0).
_MISSING = {"force_seq": -1}

#: Column names, in file order.
COLUMNS = ("time", "position", "force", "seq", "turnaround_us", "late", "flags", "force_seq",
           "status")

#: ``flags`` bit: the device held an older force at this tick (as the ``late`` column).
FLAG_LATE = 1
#: ``flags`` bit: first sample after the device was lost and recovered (scene restarted).
FLAG_LOST = 2
#: ``flags`` bit: the force was scaled by the ramp that follows a recovery.
FLAG_RAMP = 4
#: ``flags`` bit: the force was clamped at the force limit.
FLAG_CLAMPED = 8
#: ``flags`` bit: older STATEs were waiting with this one and were skipped (the backlog
#: policy answers the newest; :attr:`hapsim.host.loop.LoopResult.skipped`).
FLAG_SKIPPED = 16
#: ``flags`` bit: no sample came for this tick (a driver's missing reply): the loop
#: stepped the scene with a position extrapolated from the two before (the row's
#: ``position``), so its clock and the device's stay one; a measurement interpolates it.
FLAG_ESTIMATED = 32


class Telemetry:
    """Preallocated telemetry buffer of a run: a head kept whole, then a ring.

    Parameters
    ----------
    head : int
        Rows kept for the whole run (>= 0): rows ``0 .. head - 1``.
    ring : int
        Rows the later rows go round (>= 0): row ``r >= head`` is kept in slot
        ``head + (r - head) % ring`` until row ``r + ring`` overwrites it. 0: no ring, at
        most ``head`` rows are recorded (the loop stops there).
    skips : int, optional
        Entries of the skipped STATEs' record (>= 0; default ``head``: one per row the
        measurement reads).

    Attributes
    ----------
    time, position, force, turnaround_us : ndarray of float64, shape (head + ring,)
        Columns [s], [m], [N], [us], by slot (:meth:`slot`).
    seq : ndarray of int64, shape (head + ring,)
        STATE sequence numbers.
    late : ndarray of int8, shape (head + ring,)
        1 where the device held an older force (late FORCE).
    flags : ndarray of uint8, shape (head + ring,)
        :data:`FLAG_LATE` | :data:`FLAG_LOST` | :data:`FLAG_RAMP` | :data:`FLAG_CLAMPED`.
    force_seq : ndarray of int64, shape (head + ring,)
        STATE.force_seq per sample (-1: the protocol carries none).
    status : ndarray of uint16, shape (head + ring,)
        STATE.status per sample.
    n : int
        Rows recorded in all (the loop writes a row's slot, then raises ``n``).
    capacity : int
        ``head + ring`` slots.
    skip_row : ndarray of int64, shape (skips,)
        Per skipped STATE the scene stepped with, in order: the row it preceded (the row
        then written next, flagged :data:`FLAG_SKIPPED`).
    skip_x : ndarray of float64, shape (skips,)
        Its position [m].
    skip_meta : ndarray of int64, shape (skips, 4)
        Its STATE's ``seq``, ``force_seq``, ``status`` and ``time_us`` [us].
    skip_n : int
        Skipped STATEs the scene stepped with in all (beyond ``skips``: counted only).
    drain : callable or None
        When set (by the owner of a :class:`ChunkWriter`, for a loop that is not
        real-time: virtual clock, lockstep), the loop calls it from its own thread each
        half lap of the ring, so a loop faster than real time never outruns the writer. A
        real-time loop leaves it None and never waits.

    Raises
    ------
    ValueError
        On a negative ``head``, ``ring`` or ``skips``.
    """

    def __init__(self, head: int, ring: int = 0, skips: int | None = None) -> None:
        head, ring = int(head), int(ring)
        skips = head if skips is None else int(skips)
        if head < 0 or ring < 0 or skips < 0:
            raise ValueError(f"head, ring and skips must be >= 0, got {head}, {ring}, "
                             f"{skips}")
        self.head = head
        self.ring = ring
        self.capacity = capacity = head + ring
        self.time = np.zeros(capacity)
        self.position = np.zeros(capacity)
        self.force = np.zeros(capacity)
        self.seq = np.zeros(capacity, dtype=np.int64)
        self.turnaround_us = np.zeros(capacity)
        self.late = np.zeros(capacity, dtype=np.int8)
        self.flags = np.zeros(capacity, dtype=np.uint8)
        self.force_seq = np.full(capacity, -1, dtype=np.int64)
        self.status = np.zeros(capacity, dtype=np.uint16)
        self.skip_row = np.zeros(skips, dtype=np.int64)
        self.skip_x = np.zeros(skips)
        self.skip_meta = np.zeros((skips, 4), dtype=np.int64)
        self.skip_n = 0
        # np.zeros maps untouched zero pages: writing them once here moves the page
        # faults (the kernel allocating memory) out of the hot loop (docs/design.md, rule 4)
        for a in (self.time, self.position, self.force, self.seq, self.turnaround_us,
                  self.late, self.flags, self.status, self.skip_row, self.skip_x,
                  self.skip_meta):
            a.fill(1)
            a.fill(0)
        self.force_seq.fill(-1)
        self.n = 0
        self.drain = None

    @property
    def max_rows(self) -> int | None:
        """Most rows the buffer can record: ``head`` without a ring, else None (any)."""
        return None if self.ring else self.head

    @property
    def wrapped(self) -> bool:
        """True once rows have been overwritten in memory (only the journal has them)."""
        return self.n > self.capacity

    def slot(self, row: int) -> int:
        """Slot of row ``row`` (>= 0) in the arrays (the loop computes the same inline).

        Parameters
        ----------
        row : int
            Row index since the start of the run.

        Returns
        -------
        int
            ``row`` in the head, else ``head + (row - head) % ring``.

        Raises
        ------
        IndexError
            A row beyond the head of a buffer without a ring.
        """
        if row < self.head:
            return row
        if not self.ring:
            raise IndexError(f"row {row} beyond the {self.head} rows of a buffer without ring")
        return self.head + (row - self.head) % self.ring

    def skipped(self) -> tuple[np.ndarray, np.ndarray, int]:
        """The skipped STATEs' record (module notes), for the contact replay.

        Returns
        -------
        rows : ndarray of int64, shape (m,)
            The row each recorded skipped STATE preceded, non-decreasing
            (``m = min(skip_n, skips)``).
        positions : ndarray of float64, shape (m,)
            Their positions [m].
        complete_below : int
            Every skipped STATE before a row below it is recorded: ``n`` when none was
            dropped, else the row of the last recorded one (that row's may be incomplete).
        """
        m = min(self.skip_n, self.skip_row.size)
        below = self.n if self.skip_n <= m else (int(self.skip_row[m - 1]) if m else 0)
        return self.skip_row[:m], self.skip_x[:m], below

    def skipped_ticks(self) -> np.ndarray:
        """The recorded skipped STATEs' fields, in the order of :meth:`skipped`.

        Returns
        -------
        ndarray of int64, shape (m, 4)
            Per entry its STATE's ``seq``, ``force_seq``, ``status``, ``time_us`` [us].
        """
        return self.skip_meta[:min(self.skip_n, self.skip_meta.shape[0])]

    def rows_in_memory(self) -> list[tuple[int, int]]:
        """The rows still in memory.

        Returns
        -------
        list of (int, int)
            Row ranges ``[a, b)``, in order: all ``n`` rows until the ring has gone round,
            then the head and the last ``ring`` rows.
        """
        n, h = self.n, self.head
        if n <= self.capacity:
            return [(0, n)] if n else []
        return [(0, h), (n - self.ring, n)] if h else [(n - self.ring, n)]

    def columns(self, rows: tuple[int, int] | None = None) -> dict[str, np.ndarray]:
        """The rows in memory by column name, in row order.

        Parameters
        ----------
        rows : (int, int), optional
            Only rows ``[a, b)`` (they must be in memory); default: every row in memory
            (all ``n`` rows until the ring wraps; then the head and the last ``ring``).

        Returns
        -------
        dict of str to ndarray
            The columns of :data:`COLUMNS`, each shape (m,): views when the rows are
            contiguous in memory, copies otherwise.
        """
        ranges = [rows] if rows is not None else self.rows_in_memory()
        arrays = {c: getattr(self, c) for c in COLUMNS}
        parts: dict[str, list] = {c: [] for c in COLUMNS}
        for a, b in ranges:
            if b <= a:
                continue
            sa = self.slot(a)
            sb = self.slot(b - 1) + 1
            for c in COLUMNS:
                col = arrays[c]
                parts[c].append(col[sa:sb] if sb > sa else
                                np.concatenate([col[sa:self.capacity], col[self.head:sb]]))
        out = {}
        for c in COLUMNS:
            ps = parts[c]
            out[c] = ps[0] if len(ps) == 1 else (np.concatenate(ps) if ps else
                                                 arrays[c][:0])
        return out

    def write(self, path: str) -> str:
        """Write the rows in memory to ``path`` atomically.

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


def _write_columns(cols: dict, path: str, events: list | None = None,
                   key: str = "--telemetry") -> str:
    """Write columns to ``.npz`` / ``.csv`` atomically (see :meth:`Telemetry.write`); an
    ``.npz`` also keeps ``events`` (JSON text in the array ``events``) when given."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".npz", ".csv"):
        raise ConfigError(f"unknown telemetry format {ext or '(none)'!r}; valid: .npz, .csv",
                          key=key)
    cols = _complete(cols)
    tmp = f"{path}.partial"
    try:
        if ext == ".npz":
            extra = {"events": np.array(json.dumps(events))} if events else {}
            with open(tmp, "wb") as fh:
                np.savez(fh, **cols, **extra)
        else:
            # %.17g round-trips every float64 exactly (seq, late, flags are integers)
            data = np.column_stack([cols[c].astype(float) for c in COLUMNS])
            np.savetxt(tmp, data, delimiter=",", header=",".join(COLUMNS), comments="",
                       fmt=["%.17g", "%.17g", "%.17g", "%d", "%.17g", "%d", "%d", "%d", "%d"])
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _complete(cols: dict) -> dict:
    """``cols`` with every column of :data:`COLUMNS` (an absent one as :func:`_absent`)."""
    n = int(np.asarray(cols["seq"]).size)
    return {c: (cols[c] if c in cols else _absent(c, n)) for c in COLUMNS}


def _absent(c: str, n: int) -> np.ndarray:
    """Column ``c`` of ``n`` rows for a file written before it existed."""
    return np.full(n, _MISSING.get(c, 0), dtype=DTYPES[c])


def load_telemetry(path: str) -> dict[str, np.ndarray]:
    """Read a telemetry file written by :meth:`Telemetry.write`.

    Parameters
    ----------
    path : str
        ``.npz`` or ``.csv`` file.

    Returns
    -------
    dict of str to ndarray
        The columns of :data:`COLUMNS`, each shape (n,); ``seq`` as int64, ``late`` int8,
        ``flags`` uint8 (zeros for a file written before that column existed).
    """
    if path.lower().endswith(".hst"):
        return load(path)
    if path.lower().endswith(".npz"):
        with np.load(path) as z:
            n = z["seq"].size
            return {c: (np.asarray(z[c]) if c in z.files else _absent(c, n))
                    for c in COLUMNS}
    with open(path) as fh:
        names = fh.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    n = data.shape[0]
    out = {c: (data[:, names.index(c)] if c in names else _absent(c, n))
           .astype(np.dtype(DTYPES[c]).newbyteorder("=")) for c in COLUMNS}
    return out


class ChunkWriter:
    """Writer thread draining the recorded rows of a :class:`Telemetry` to a journal.

    Parameters
    ----------
    telemetry : Telemetry
        The buffer the loop fills (rows ``[0, telemetry.n)`` are complete: the loop writes a
        row before it raises ``n``).
    path : str
        Journal file (created or truncated); conventionally ``.hst``.
    interval : float
        Time between two drains [s] (> 0); 0.05 keeps a ``kill -9`` loss under 100 ms.
    events : list of dict, optional
        The loop's event list (:attr:`hapsim.host.loop.LoopResult.events`), appended to
        by the loop: each new event is journaled as an event chunk at the next drain.

    Attributes
    ----------
    rows_written : int
        Rows drained so far (on disk, or counted in ``lost_rows``).
    lost_rows : int
        Rows the loop overwrote in the ring before this thread drained them (it fell more
        than ``ring`` rows behind); counted, never waited for.
    chunks : int
        Chunks written (rows and events).
    events_written : int
        Events journaled.
    error : OSError or None
        The error that stopped the thread (disk full, ...), if any.

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
    off the hot loop). A ring slot being rewritten while it is copied is detected: after
    the copy, rows the loop may have reached since (``r <= n_now - ring``, one row of
    margin for the row being written) are dropped and counted in ``lost_rows``.
    """

    def __init__(self, telemetry: "Telemetry", path: str, interval: float = 0.05,
                 events: list | None = None) -> None:
        if not interval > 0:
            raise ValueError(f"interval must be > 0, got {interval!r}")
        self.tel = telemetry
        self.path = path
        self.interval = float(interval)
        self.events = events
        self.rows_written = 0
        self.lost_rows = 0
        self.chunks = 0
        self.events_written = 0
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._done = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="hapsim-telemetry",
                                        daemon=True)
        self.error = None

    def start(self) -> "ChunkWriter":
        """Start the thread.

        Returns
        -------
        ChunkWriter
            ``self``.
        """
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._done.wait(self.interval):
            try:
                self.flush()
            except OSError as exc:      # disk full, ...: keep the loop running, report later
                self.error = exc
                return

    def _chunk(self, header: dict, payload: bytes = b"") -> None:
        os.write(self._fd, _chunk_bytes(header, payload))
        self.chunks += 1

    def flush(self) -> int:
        """Drain the rows recorded since the last drain, then the new events.

        Returns
        -------
        int
            Rows written to the journal by this call (rows lost to the ring not counted).

        Raises
        ------
        OSError
            When the journal cannot be written.
        """
        with self._lock:
            tel = self.tel
            n = tel.n
            a = self.rows_written
            wrote = 0
            if n > a:
                head, ring = tel.head, tel.ring
                pieces = []
                if a < head:
                    pieces.append((a, min(n, head)))
                if n > head and ring:
                    lo = max(a, head)
                    floor = n - ring + 1          # below: overwritten, or being overwritten
                    if lo < floor:
                        self.lost_rows += floor - lo
                        lo = floor
                    if n > lo:
                        pieces.append((lo, n))
                copies = [(lo, hi, {c: np.array(v, copy=True)
                                    for c, v in tel.columns((lo, hi)).items()})
                          for lo, hi in pieces]
                safe = tel.n - ring + 1 if ring else 0   # the loop went on meanwhile
                for lo, hi, cols in copies:
                    if lo >= head and lo < safe:
                        cut = min(safe, hi)
                        self.lost_rows += cut - lo
                        cols = {c: v[cut - lo:] for c, v in cols.items()}
                        lo = cut
                    if hi <= lo:
                        continue
                    self._chunk(*_rows_chunk(cols, lo, hi - lo))
                    wrote += hi - lo
                self.rows_written = n
            ev = self.events
            if ev is not None:
                while self.events_written < len(ev):
                    e = ev[self.events_written]
                    self._chunk(_event_header(e, tel.n))
                    self.events_written += 1
            return wrote

    def note(self, event: dict) -> None:
        """Journal ``event`` now, apart from the loop's events (a run's description: its
        axis's units and its delay, which ``hapsim telemetry`` reads back).

        Raises
        ------
        OSError
            When the journal cannot be written.
        """
        with self._lock:
            self._chunk(_event_header(event, self.tel.n))

    def close(self) -> None:
        """Stop the thread, drain the last rows and events, close the file (idempotent)."""
        self._done.set()
        if self._thread.is_alive():
            self._thread.join()
        if self._fd is not None:
            try:
                self.flush()
            finally:
                os.close(self._fd)
                self._fd = None


def _chunk_bytes(header: dict, payload: bytes = b"") -> bytes:
    """One journal chunk: fixed head, JSON header, payload (module docstring)."""
    h = json.dumps(header, separators=(",", ":")).encode()
    crc = zlib.crc32(payload, zlib.crc32(h))
    return CHUNK_HEAD.pack(CHUNK_MAGIC, CHUNK_VERSION, len(h), len(payload), crc) + h + payload


def _rows_chunk(cols: dict, first: int, rows: int) -> tuple[dict, bytes]:
    """Header and payload of a rows chunk holding ``cols`` (rows ``first ..``)."""
    payload = b"".join(np.ascontiguousarray(cols[c], dtype=DTYPES[c]).tobytes()
                       for c in COLUMNS)
    return ({"columns": list(COLUMNS), "dtypes": [DTYPES[c] for c in COLUMNS],
             "rows": rows, "first": first}, payload)


def _event_header(event: dict, n: int) -> dict:
    """Header of an event chunk (placed at the event's sample, else at row ``n``)."""
    return {"columns": [], "dtypes": [], "rows": 0, "first": int(event.get("sample", n)),
            "event": event}


def write_journal(cols: dict, path: str, events: list | None = None,
                  chunk_rows: int = 65536) -> str:
    """Write columns (and events) as a chunked journal ``.hst``, atomically.

    Parameters
    ----------
    cols : dict of str to ndarray
        The columns of :data:`COLUMNS`, each shape (n,) (cast to the journal's dtypes).
    path : str
        Output file (conventionally ``.hst``).
    events : list of dict, optional
        Loop events (``event``, ``sample``, ...), written as event chunks after the rows.
    chunk_rows : int
        Rows per chunk (> 0).

    Returns
    -------
    str
        ``path``; :func:`load` reads the same columns back bit for bit.

    Raises
    ------
    OSError
        When the file cannot be written (the temporary file is removed).
    """
    cols = _complete(cols)
    n = int(np.asarray(cols["seq"]).size)
    tmp = f"{path}.partial"
    try:
        with open(tmp, "wb") as fh:
            for a in range(0, n, chunk_rows):
                b = min(n, a + chunk_rows)
                fh.write(_chunk_bytes(*_rows_chunk({c: np.asarray(cols[c])[a:b]
                                                    for c in COLUMNS}, a, b - a)))
            for e in events or ():
                fh.write(_chunk_bytes(_event_header(e, n)))
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def save_columns(cols: dict, path: str, events: list | None = None,
                 key: str = "--out") -> str:
    """Write telemetry columns in the format of ``path``'s extension.

    Parameters
    ----------
    cols : dict of str to ndarray
        The columns of :data:`COLUMNS`, each shape (n,).
    path : str
        ``.hst`` (journal, with the events), ``.npz`` (with the events) or ``.csv``
        (columns only; floats as ``%.17g``, so every value reads back exactly).
    events : list of dict, optional
        Loop events to keep (``.hst``, ``.npz``).
    key : str
        Option named in an error.

    Returns
    -------
    str
        ``path``.

    Raises
    ------
    ConfigError
        On an unknown extension (key ``key``; valid: .hst, .npz, .csv).
    OSError
        When the file cannot be written.
    """
    if path.lower().endswith(".hst"):
        return write_journal(cols, path, events)
    try:
        return _write_columns(cols, path, events, key=key)
    except ConfigError:
        ext = os.path.splitext(path)[1].lower() or "(none)"
        raise ConfigError(f"unknown telemetry format {ext!r}; valid: .hst, .npz, .csv",
                          key=key) from None


def load(path: str, *, info: dict | None = None) -> dict[str, np.ndarray]:
    """Read a telemetry file: a chunked journal (``.hst``), ``.npz`` or ``.csv``.

    Parameters
    ----------
    path : str
        The file. A journal is read chunk by chunk; reading stops at the first chunk that
        is incomplete (torn by a kill), fails its CRC, or does not start with the magic.
    info : dict, optional
        Filled with ``chunks`` (complete chunks read), ``rows``, ``torn_bytes`` (bytes
        ignored at the end), ``torn_rows`` (rows ``[a, b)`` of a torn last chunk whose
        header survived, else None), ``events`` (the loop's journaled events, list of dict)
        and ``gaps`` (row ranges ``[a, b)`` missing between chunks: rows the writer lost to
        the ring) for a journal.

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
    events: list = []
    gaps: list = []
    expect = 0
    while pos + CHUNK_HEAD.size <= len(data):
        magic, version, hlen, plen, crc = CHUNK_HEAD.unpack_from(data, pos)
        if magic != CHUNK_MAGIC or version != CHUNK_VERSION:
            break
        a = pos + CHUNK_HEAD.size
        b = a + hlen + plen
        if b > len(data):
            break
        header, payload = data[a:a + hlen], data[a + hlen:b]
        if zlib.crc32(payload, zlib.crc32(header)) != crc:
            break
        try:
            h = json.loads(header)
            n = int(h["rows"])
            if "event" in h:
                events.append(h["event"])
            elif n and int(h.get("first", expect)) > expect:
                gaps.append((expect, int(h["first"])))
            if n:
                expect = int(h.get("first", expect)) + n
            off = 0
            got = {}
            for c, dt in zip(h["columns"], h["dtypes"]):
                size = n * np.dtype(dt).itemsize
                got[c] = np.frombuffer(payload, dtype=dt, count=n, offset=off)
                off += size
        except (ValueError, KeyError, TypeError):
            break
        for c in COLUMNS:
            parts[c].append(got[c] if c in got else _absent(c, n))
        chunks += 1
        rows += n
        pos = b
    if info is not None:
        info.update(chunks=chunks, rows=rows, torn_bytes=len(data) - pos, events=events,
                    gaps=gaps, torn_rows=_torn_rows(data, pos))
    return {c: (np.concatenate(parts[c]) if parts[c] else np.zeros(0, dtype=DTYPES[c]))
            .astype(np.dtype(DTYPES[c]).newbyteorder("=")) for c in COLUMNS}


def _torn_rows(data: bytes, pos: int) -> tuple[int, int] | None:
    """Rows ``[a, b)`` announced by the torn chunk at ``pos`` when its header is whole."""
    if pos + CHUNK_HEAD.size > len(data):
        return None
    magic, version, hlen, _, _ = CHUNK_HEAD.unpack_from(data, pos)
    a = pos + CHUNK_HEAD.size
    if magic != CHUNK_MAGIC or a + hlen > len(data):
        return None
    try:
        h = json.loads(data[a:a + hlen])
        first, rows = int(h["first"]), int(h["rows"])
    except (ValueError, KeyError, TypeError):
        return None
    return (first, first + rows) if rows else None


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
