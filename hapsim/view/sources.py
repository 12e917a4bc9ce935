"""What the view reads from a running loop: rows it already records, positions it holds.

Each source is read by the view's server thread only, at the display's rate, without a
lock: the loop writes its arrays and appends to its lists as it always does, and a reader
that sees a row being written draws one stale point (the next frame draws it right). A
source never makes the loop wait and never allocates on its behalf.
"""

from __future__ import annotations

import collections

import numpy as np

from hapsim.outputs import finite_or_none as _num

__all__ = ["RunSource", "PlaySource", "ChunkSource", "scene_layout"]


def scene_layout(scene, protocol: str | None = None) -> dict:
    """The scene's masses, links and planes as the page draws them.

    Parameters
    ----------
    scene : hapsim.scene.Scene or hapsim.scene.SceneND
        The scene the loop runs (1-D, 2-D or 3-D).
    protocol : str, optional
        The protocol the run speaks (``--driver``); default the scene's
        ``device.protocol``. A 1-D rotary axis's (the Haply joint's) sets ``units``.

    Returns
    -------
    dict
        ``dim`` (1, 2 or 3), ``masses`` (``name``, ``kind`` in mass/ground/port, ``mass``
        [kg]), ``links`` (``name``, ``kind`` spring_damper/contact, ``i``, ``j`` mass
        indices, ``K`` [N/m], ``B`` [N s/m], ``threshold`` [m], ``length`` [m] (n-D rest
        length, 0 in 1-D)), ``planes`` (n-D plane contacts: ``name``, ``normal``,
        ``offset`` [m], ``K``, ``B``, ``masses`` indices), ``targets`` (the links given
        as a felt target: ``name``, ``k`` [N/m], ``b`` [N s/m]), ``rate_hz`` [Hz],
        ``units`` (:func:`hapsim.drivers.run_units`: the figures above are in a rotary
        joint's units where the 1-D axis is one; an n-D scene's are SI).
    """
    from hapsim.drivers import run_units
    dim = int(getattr(scene, "dimension", 1) or 1)
    names = [m.name for m in scene.masses]
    idx = {n: i for i, n in enumerate(names)}
    masses = [{"name": m.name, "kind": m.kind, "mass": float(getattr(m, "mass", 0.0) or 0.0)}
              for m in scene.masses]
    links = [{"name": lk.name, "kind": lk.kind, "i": idx[lk.m1], "j": idx[lk.m2],
              "K": _num(lk.stiffness), "B": _num(lk.damping),
              "threshold": _num(getattr(lk, "threshold", 0.0)),
              "length": _num(getattr(lk, "length", 0.0))} for lk in scene.links]
    targets = [{"name": lk.name, "k": float(lk.target[0]), "b": float(lk.target[1])}
               for lk in scene.links if getattr(lk, "target", None) is not None]
    planes = [{"name": p.name, "normal": [float(v) for v in p.normal],
               "offset": float(p.offset), "K": _num(p.stiffness), "B": _num(p.damping),
               "masses": [idx[n] for n in p.masses if n in idx]}
              for p in getattr(scene, "planes", ()) or ()]
    return {"dim": dim, "masses": masses, "links": links, "planes": planes,
            "targets": targets, "rate_hz": float(scene.rate_hz),
            "units": run_units(scene, protocol)}


class _Base:
    """Shared reading of an engine's positions and a controller's journal."""

    dim = 1

    def __init__(self, scene, engine_of, ctl=None, events=None) -> None:
        self.scene = scene
        self.rate_hz = float(scene.rate_hz)
        self.period = 1.0 / self.rate_hz
        self.engine_of = engine_of
        self.ctl = ctl
        self.events = events if events is not None else []

    def positions(self) -> np.ndarray:
        """Copy of every mass's position [m], shape (n_masses, dim)."""
        e = self.engine_of()
        if self.dim == 1:
            return np.asarray(e.positions, dtype=float).reshape(-1, 1)
        return np.array(e.step_rows[0], dtype=float).T

    def previous(self) -> np.ndarray | None:
        """Positions one sample earlier [m], shape (n_masses, dim); None when the engine
        does not keep them (an n-D engine in single precision keeps the step)."""
        e = self.engine_of()
        if self.dim == 1:
            return np.asarray(e.previous_positions, dtype=float).reshape(-1, 1)
        if getattr(e, "precision", "double") != "double":
            return None
        return np.array(e.step_rows[1], dtype=float).T


class RunSource(_Base):
    """``hapsim run``: the telemetry arrays (:class:`hapsim.host.telemetry.Telemetry`)
    and the loop's event list.

    Parameters
    ----------
    scene : Scene
        The calibrated scene.
    tel : Telemetry
        The run's telemetry (rows ``0 .. tel.n - 1`` recorded).
    engine_of : callable
        ``engine_of() -> Engine``: the engine the loop steps now (a recovery rebuilds it).
    ctl : hapsim.audio.control.Controller, optional
        The live changes' controller.
    events : list of dict
        The loop's events (``LoopResult.events``: losses, recoveries, safety stops,
        live changes), appended by the loop.
    prep : PreparedRun, optional
        The run's preparation: with it and ``measure``, :meth:`record` hands the view the
        rows to measure the felt pair on as the record grows.
    hello_of : callable, optional
        ``hello_of() -> Hello or None``: the device's HELLO once the loop has it.
    measure : callable, optional
        ``measure(prep, cols, hello) -> dict``: the run's own measurement of a record so
        far (:func:`hapsim.pipeline.measure.measure_record`, given by the run: the view
        imports nothing of the pipeline), run in the controller's analysis process.
    measure_keys : tuple of str
        The keys of a measurement the page shows
        (:data:`hapsim.pipeline.measure.MEASURE_KEYS`).
    """

    def __init__(self, scene, tel, engine_of, ctl=None, events=None, prep=None,
                 hello_of=None, measure=None, measure_keys=()) -> None:
        super().__init__(scene, engine_of, ctl, events)
        self.measure = measure
        self.measure_keys = tuple(measure_keys)
        self.tel = tel
        self.prep = prep
        self.hello_of = hello_of

    @property
    def record_rows(self) -> int:
        """Most rows the report's measurement takes (0: none to measure live): the whole
        run while it fits in memory (the head and the ring), else the head alone."""
        if self.prep is None or self.measure is None:
            return 0
        return int(self.tel.capacity)

    @property
    def measured_rows(self) -> int:
        """Rows the report's measurement takes now: every row recorded until the ring has
        gone round, then the head (:func:`hapsim.pipeline.measure.identify_run`)."""
        return int(self.tel.head if self.tel.wrapped else self.tel.n)

    def record(self) -> tuple | None:
        """Arguments of :attr:`measure` for the rows the report would measure now
        (copies), or None when there is nothing to measure.

        Returns
        -------
        tuple or None
            ``(prep, cols, hello)``: the :class:`PreparedRun`, the telemetry columns of rows
            ``0 .. measured_rows - 1`` (dict of str to ndarray, shape (n,)) and the HELLO
            (None before the loop has it).
        """
        n = self.measured_rows
        if n <= 0 or self.prep is None or self.measure is None:
            return None
        cols = {c: np.array(v) for c, v in self.tel.columns((0, n)).items()}
        hello = self.hello_of() if self.hello_of is not None else None
        return (self.prep, cols, hello)

    @property
    def count(self) -> int:
        """Rows recorded so far."""
        return int(self.tel.n)

    def rows(self, since: int, most: int) -> tuple[int, dict]:
        """Rows ``[max(since, count - most), count)`` still in memory.

        Parameters
        ----------
        since : int
            The first row the reader has not had yet.
        most : int
            Most rows returned (the newest).

        Returns
        -------
        first : int
            Index of the first row returned.
        cols : dict of ndarray
            ``t`` [s], ``x`` [m], ``f`` [N], ``turnaround_us`` [us], ``flags`` (bits of
            :mod:`hapsim.host.telemetry`).
        """
        tel = self.tel
        n = int(tel.n)
        lo = max(since, n - most, 0)
        if tel.ring:
            lo = max(lo, n - tel.ring) if n > tel.capacity else lo
            idx = np.arange(lo, n)
            sl = np.where(idx < tel.head, idx, tel.head + (idx - tel.head) % max(tel.ring, 1))
        else:
            n = min(n, tel.head)
            lo = min(lo, n)
            sl = np.arange(lo, n)
        return lo, {"t": tel.time[sl], "x": tel.position[sl], "f": tel.force[sl],
                    "turnaround_us": tel.turnaround_us[sl], "flags": tel.flags[sl]}


class PlaySource(_Base):
    """``hapsim play`` (1-D): the arrays of device position and port force it fills.

    Parameters
    ----------
    scene : Scene
    xs, fs : ndarray, shape (steps,)
        Position [m] and force [N] per sample, written by the play loop.
    engine : Engine
    ctl : Controller
        Its ``sample`` counts the samples polled (row ``sample - 1`` is being computed).
    """

    def __init__(self, scene, xs, fs, engine, ctl) -> None:
        super().__init__(scene, lambda: engine, ctl)
        self.xs, self.fs = xs, fs

    @property
    def count(self) -> int:
        """Rows complete so far."""
        return max(0, min(int(self.ctl.sample) - 1, self.xs.size))

    def rows(self, since: int, most: int) -> tuple[int, dict]:
        """As :meth:`RunSource.rows` (no turnaround or flags: the play loop has no link).

        Parameters
        ----------
        since : int
            The first row the reader has not had yet.
        most : int
            Most rows returned (the newest).

        Returns
        -------
        first : int
            Index of the first row returned.
        cols : dict of ndarray
            ``t`` [s], ``x`` [m], ``f`` [N], each shape (rows,).
        """
        n = self.count
        lo = max(since, n - most, 0)
        t = np.arange(lo, n) * self.period
        return lo, {"t": t, "x": self.xs[lo:n], "f": self.fs[lo:n]}


class ChunkSource(_Base):
    """An n-D loop (``hapsim play`` of a 2-D or 3-D scene): the port's position and force
    handed over by the loop's chunk callback into a bounded deque.

    Parameters
    ----------
    scene : SceneND
    engine : Engine
    ctl : ControllerND or None
    maxlen : int
        Most pending rows; the oldest are dropped when the view falls behind (the loop
        never waits: ``deque.append`` is atomic and bounded).
    """

    def __init__(self, scene, engine, ctl=None, maxlen: int = 4096) -> None:
        super().__init__(scene, lambda: engine, ctl)
        self.dim = int(scene.dimension)
        self.queue: collections.deque = collections.deque(maxlen=maxlen)
        self._count = 0
        self.scene_index = {m.name: i for i, m in enumerate(scene.masses)}
        self.axis = self._trace_axis(scene)

    @staticmethod
    def _trace_axis(scene) -> int:
        """The axis the traces show: the excitation's main direction for a loop with a
        port, else the listened axis (a membrane heard along z moves along z), else 0."""
        exc = getattr(scene, "excitation", None)
        d = getattr(exc, "direction", None)
        if getattr(scene, "port", None) is not None and d is not None:
            return int(np.argmax(np.abs(np.asarray(d, dtype=float))))
        listen = getattr(scene, "audio", None) or ()      # n-D: a tuple of ListenND
        return int(getattr(listen[0], "axis", 0)) if listen else 0

    def probe(self) -> np.ndarray:
        """Position [m], shape (dim,), of the scene's first listened mass (a free loop's
        trace: it has no port), else of its first mass.

        Returns
        -------
        ndarray, shape (dim,)
            A copy [m].
        """
        listen = getattr(self.scene, "audio", None) or ()
        name = getattr(listen[0], "mass", None) if listen else None
        i = self.scene_index.get(name, 0)
        return np.array(self.engine_of().step_rows[0][:, i], dtype=float)

    def push(self, sample: int, x, f) -> None:
        """Called by the loop: one row (the sample index, port position [m] and force
        [N], each shape (dim,)); never blocks.

        Parameters
        ----------
        sample : int
            The sample's index.
        x : ndarray, shape (dim,)
            The port's position [m].
        f : ndarray, shape (dim,)
            The port's force [N].
        """
        self.queue.append((int(sample), x, f))

    @property
    def count(self) -> int:
        """Rows handed over so far."""
        return self._count

    def rows(self, since: int, most: int) -> tuple[int, dict]:
        """The rows handed over since the last call (``since`` and ``most`` bound them as
        in :meth:`RunSource.rows`); ``x``, ``f`` are the traced :attr:`axis`, ``xs``,
        ``fs`` every axis, shape (rows, dim).

        Parameters
        ----------
        since : int
            The first row the reader has not had yet (returned as ``first`` when none came).
        most : int
            Most rows returned (the newest; older ones handed over are dropped).

        Returns
        -------
        first : int
            The sample index of the first row returned.
        cols : dict of ndarray
            ``t`` [s], ``x`` [m], ``f`` [N], shape (rows,); ``xs`` [m], ``fs`` [N], shape
            (rows, dim), only when rows came.
        """
        got = []
        while self.queue:
            got.append(self.queue.popleft())
        got = got[-most:]
        if not got:
            return since, {"t": np.zeros(0), "x": np.zeros(0), "f": np.zeros(0)}
        self._count = got[-1][0] + 1
        s = np.array([g[0] for g in got])
        X = np.array([np.ravel(g[1]) for g in got], dtype=float)
        F = np.array([np.ravel(g[2]) for g in got], dtype=float)
        a = min(self.axis, X.shape[1] - 1)
        return int(s[0]), {"t": s * self.period, "x": X[:, a], "f": F[:, a],
                           "xs": X, "fs": F}
