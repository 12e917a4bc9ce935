"""The view's server: static page and one WebSocket per open page, on its own thread.

The thread runs an asyncio loop (the ``websockets`` package serves both the page's files
over plain HTTP and the WebSocket). Every ``1 / fps`` seconds it reads the loop's source
(:mod:`hapsim.view.sources`) and sends each page one JSON frame: the new trace rows
(decimated), the masses' positions, the stored energy, the turnaround histogram, the
journal's new entries, the felt and measured (k, b). A page's requests (a live change, the
stop) are answered from a worker thread: :meth:`hapsim.audio.control.Controller.request`
checks a change by the same prediction as OSC (seconds on a large scene), and the stop
sets the run's :class:`~hapsim.host.loop_types.StopFlag` as SIGINT does.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import sys
import threading
import time

import numpy as np

from hapsim.errors import ConfigError

__all__ = ["ViewServer", "start_view", "require_websockets", "grid_for", "HIST_BINS"]

STATIC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "static")
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".txt": "text/plain; charset=utf-8"}
#: Bins of the turnaround histogram, over [0, 2 T] (T the sample period).
HIST_BINS = 40
#: Most trace points a frame carries (the rows between two frames are strided to this).
MOST_POINTS = 400


def require_websockets(flag: str = "--view") -> None:
    """Raise a ConfigError saying how to install the view when ``websockets`` is missing.

    Parameters
    ----------
    flag : str
        The option that asked for the view (the error's key).

    Raises
    ------
    ConfigError
        ``websockets`` cannot be imported (key ``flag``).
    """
    try:
        import websockets.asyncio.server  # noqa: F401
    except ImportError:
        raise ConfigError("the live view needs the 'websockets' package: pip install "
                          "'hapsim[view]' (or pip install websockets)", key=flag) from None


def grid_for(scene) -> dict | None:
    """The (k, b) grid of a 1-D scene's device loop, as ``hapsim map`` draws it.

    Parameters
    ----------
    scene : Scene
        A calibrated 1-D scene with a device (its mass [kg], friction b0 [N s/m], rate
        [Hz], integer delay [samples] and hold).

    Returns
    -------
    dict or None
        :meth:`hapsim.analysis.grid.GridResult.to_dict` over 7 target stiffnesses from a
        fifth to 1.6 times the predicted k and 7 target dampings from 0 to twice the
        predicted b (Florens, Voda & Urma Fig. 4: each (k, b) calibrated to (K, B); the
        b = 0 curve is the stability boundary); None for a fractional delay or a loop the
        grid cannot model.
    """
    from hapsim.analysis.grid import grid
    from hapsim.analysis.loop import LoopModel
    from hapsim.analysis.prediction import predict
    dev = scene.device
    if not float(dev.delay).is_integer():
        return None
    pred = predict(scene)
    k = float(pred.get("k") or 0.0)
    b = float(pred.get("b") or 0.0)
    if not (math.isfinite(k) and k > 0):
        return None
    loop = LoopModel(dev.mass, dev.friction, scene.rate_hz, int(dev.delay), dev.hold)
    b_hi = max(2.0 * b, 4.0 * math.sqrt(k) * math.sqrt(dev.mass) * 0.05, 1e-3)
    # the page draws the 7 x 7 nodes, the identity grid and the boundary; the finely
    # sampled iso curves (samples > 0) are not in to_dict: 560 more calibrations, 30 s of
    # the analysis process on a loaded 2-core box against 1.7 s without them
    g = grid(loop, np.linspace(0.2 * k, 1.6 * k, 7), np.linspace(0.0, b_hi, 7))
    return g.to_dict()


class ViewServer:
    """The live view of one run (start with :func:`start_view`).

    Parameters
    ----------
    source : RunSource, PlaySource or ChunkSource
        What the loop publishes (:mod:`hapsim.view.sources`).
    ctl : hapsim.audio.control.Controller or None
        The live changes' controller (None: the page shows no controls).
    stop : StopFlag
        The run's stop flag (the page's stop button requests it).
    port : int
        TCP port on 127.0.0.1 (0: any free port; :attr:`url` says which).
    what : str
        The command (``run`` or ``play``), shown on the page.
    fps : float
        Frames per second sent to each page [Hz].

    Attributes
    ----------
    url : str
        ``http://127.0.0.1:PORT/`` once started.
    report : dict or None
        The run's report once :meth:`finish` handed it over.
    """

    def __init__(self, source, ctl, stop, port: int = 0, what: str = "run",
                 fps: float = 10.0) -> None:
        from hapsim.view.sources import scene_layout
        self.source = source
        self.ctl = ctl
        self.stop = stop
        self.port = int(port)
        self.what = what
        self.fps = float(fps)
        self.layout = scene_layout(ctl.scene if ctl is not None else source.scene,
                                   getattr(source, "protocol", None))
        self.report = None
        self.grid = None
        self.url = None
        self.frames_sent = 0
        self._loop = None
        self._server = None
        self._thread = None
        self._started = threading.Event()
        self._error = None
        self._closing = None
        #: The felt pair measured on the run's record so far, oldest first (``rows``,
        #: ``k``, ``b``, ``k_unc``, ``b_unc`` ... of :func:`~hapsim.pipeline.measure.
        #: measure_record`, the run's own); the last one the report's once it is in.
        self.measurements: list[dict] = []
        self._measuring = None
        #: The analysis process of those measurements, apart from the controller's: a
        #: live change's stability checks (:meth:`hapsim.audio.control.Controller.request`,
        #: four predictions in the controller's one analysis process) must never queue
        #: behind a measurement of the growing record (on a loaded machine, in a process
        #: at nice 10, a change once waited over 60 s for its reply). Started at the
        #: first measurement, ended with the server.
        self._measurer = None

    # ---------------------------------------------------------------- control
    def start(self) -> "ViewServer":
        """Start the server thread; return once it listens (its address in :attr:`url`).

        Returns
        -------
        ViewServer
            This server.

        Raises
        ------
        ConfigError
            The port cannot be bound (key ``--view``).
        """
        self._thread = threading.Thread(target=self._main, name="hapsim-view", daemon=True)
        self._thread.start()
        self._started.wait(10.0)
        if self._error is not None:
            raise ConfigError(f"cannot serve the view on 127.0.0.1:{self.port}: "
                              f"{self._error}", key="--view")
        if self.layout["dim"] == 1 and self.source.scene is not None:
            threading.Thread(target=self._make_grid, name="hapsim-view-grid",
                             daemon=True).start()
        return self

    def finish(self, report: dict | None, linger_s: float = 1.0) -> None:
        """Hand the run's report to the open pages, then stop serving.

        Parameters
        ----------
        report : dict or None
            The run's report (shown on the page).
        linger_s : float
            Most time the pages get to receive it [s].
        """
        from hapsim.outputs import json_safe
        rep = json_safe(report) if report is not None else {}
        m = rep.get("measured")
        if self.record_rows and isinstance(m, dict):
            # the report's own measurement of the whole record: the last point (before
            # the report, which ends the pages' frames)
            final = {q: m[q] for q in self.source.measure_keys if q in m}
            final["rows"] = self.source.measured_rows
            final["final"] = True
            self.measurements.append(final)
        self.report = rep
        if self._loop is not None and self.clients:
            time.sleep(min(linger_s, 2.5 / self.fps))
        self.close()

    def close(self) -> None:
        """Stop the server and its thread (idempotent)."""
        lp = self._loop
        if lp is None:
            return
        self._loop = None
        try:
            lp.call_soon_threadsafe(self._closing.set)
        except RuntimeError:
            pass
        if self._thread is not None:
            self._thread.join(3.0)

    @property
    def clients(self) -> int:
        """Pages connected now."""
        return len(self._conns) if hasattr(self, "_conns") else 0

    # ------------------------------------------------------------ the thread
    def _make_grid(self) -> None:
        try:
            if self.ctl is not None:
                self.grid = self.ctl.analyst.call(grid_for, self.ctl.scene)
            else:
                self.grid = grid_for(self.source.scene)
        except Exception as exc:        # the grid is a picture: the page says why not
            self.grid = {"error": str(exc)}

    def _main(self) -> None:
        # The thread holds the GIL for a few milliseconds per frame. Descheduled while it
        # holds it (a loaded machine, the loop and the mock on SCHED_FIFO taking both
        # cores), it stalled the loop that waits for the GIL for seconds: at the lowest
        # real-time priority, where the process may take one, it runs as soon as a core
        # is free of the loop's and the mock's threads, ahead of ordinary load, and
        # hands the GIL back (the loop's own priority stays above it).
        if hasattr(os, "sched_setscheduler"):
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            except (OSError, PermissionError):
                pass
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        from websockets.asyncio.server import serve
        self._conns = set()
        self._closing = asyncio.Event()
        try:
            server = await serve(self._handler, "127.0.0.1", self.port,
                                 process_request=self._http, max_size=2 ** 16)
        except OSError as exc:
            self._error = exc.strerror or str(exc)
            self._started.set()
            return
        self._loop = asyncio.get_running_loop()
        port = server.sockets[0].getsockname()[1]
        self.url = f"http://127.0.0.1:{port}/"
        self._started.set()
        measuring = (asyncio.ensure_future(self._measure_growing())
                     if self.record_rows and self.ctl is not None else None)
        await self._closing.wait()
        if measuring is not None:
            measuring.cancel()
        if self._measurer is not None:
            self._measurer.close()
        server.close()
        await server.wait_closed()

    @property
    def record_rows(self) -> int:
        """Rows of the record the run's report measures (0: no live measurement)."""
        return int(getattr(self.source, "record_rows", 0) or 0)

    async def _measure_growing(self, every_s: float = 1.0, first: int = 250) -> None:
        """Measure the felt pair on the record so far, again each time it has grown by a
        quarter (at most once per ``every_s`` [s], one at a time, in the controller's
        analysis process: nothing here waits for it), until the record the report
        measures is whole."""
        last = 0
        while True:
            await asyncio.sleep(every_s)
            if not self.ctl.analyst.background or self.report is not None:
                return                  # the loop has ended (its analysis process too)
            if self._measuring is not None and not self._measuring.ready():
                continue
            if self.source.tel.wrapped and last >= self.source.tel.head:
                return                  # the report measures the head, measured already
            n = self.source.measured_rows
            if n < first or n < last + max(first, last // 4):
                continue
            args = self.source.record()
            if args is None:
                continue
            last = n
            self._measuring = self.submit_measurement(self.source.measure, args,
                                                      self.measurements.append)

    def submit_measurement(self, fn, args: tuple, done=None):
        """Run ``fn(*args)`` in the view's own analysis process (started at the first
        call; :attr:`_measurer`), never the controller's: a live change's checks do not
        wait for it.

        Parameters
        ----------
        fn : callable
            A module-level function (the child imports it).
        args : tuple
            Its arguments (pickled to the child).
        done : callable, optional
            ``done(result)`` when it ends (:meth:`hapsim.audio.analyst.Analyst.submit`).

        Returns
        -------
        object
            The handle, with ``ready()`` and ``wait(timeout)``.
        """
        if self._measurer is None:
            from hapsim.audio.analyst import Analyst
            self._measurer = Analyst(background=self.ctl is None
                                     or self.ctl.analyst.background)
        return self._measurer.submit(fn, args, done)

    def _http(self, connection, request):
        from websockets.datastructures import Headers
        from websockets.http11 import Response
        path = request.path.split("?", 1)[0]
        if path == "/ws":
            return None
        name = "index.html" if path in ("/", "") else path.lstrip("/")
        full = os.path.normpath(os.path.join(STATIC, name))
        if not full.startswith(STATIC + os.sep) or not os.path.isfile(full):
            return connection.respond(404, "not found\n")
        with open(full, "rb") as fh:
            body = fh.read()
        ext = os.path.splitext(full)[1]
        headers = Headers([("Content-Type", _TYPES.get(ext, "application/octet-stream")),
                           ("Content-Length", str(len(body))), ("Cache-Control", "no-store")])
        return Response(200, "OK", headers, body)

    async def _handler(self, ws) -> None:
        self._conns.add(ws)
        try:
            await ws.send(_dumps(self._hello()))
            reader = asyncio.ensure_future(self._reader(ws))
            state = {"since": 0, "journal": 0, "events": 0, "hist": np.zeros(HIST_BINS),
                     "grid": False, "report": False}
            period = 1.0 / self.fps
            while not reader.done():
                frame = self._frame(state)
                await ws.send(_dumps(frame))
                self.frames_sent += 1
                if state["report"]:
                    break
                try:
                    await asyncio.wait_for(asyncio.shield(reader), period)
                except asyncio.TimeoutError:
                    pass
            reader.cancel()
        except Exception as exc:        # a page closed mid-frame: nothing to do
            from websockets.exceptions import ConnectionClosed
            if not isinstance(exc, ConnectionClosed):
                print(f"hapsim {self.what}: live view: {type(exc).__name__}: {exc}",
                      file=sys.stderr, flush=True)
        finally:
            self._conns.discard(ws)

    async def _reader(self, ws) -> None:
        lp = asyncio.get_running_loop()
        async for msg in ws:
            try:
                req = json.loads(msg)
            except ValueError:
                continue
            reply = await lp.run_in_executor(None, self._answer, req)
            await ws.send(_dumps(reply))

    def _answer(self, req: dict) -> dict:
        """A page's request: ``{"op": "stop"}`` or ``{"op": "request", "address": ...,
        "args": [...]}`` (the OSC addresses of :mod:`hapsim.audio.control`)."""
        if not isinstance(req, dict):           # (a list or a number: an AttributeError
            return {"type": "reply", "ok": False,  # that ended the page's connection)
                    "reason": "a request is a JSON object {op, address, args}"}
        op = req.get("op")
        if op == "stop":
            self.stop.request(None, reason="view: stop button")
            return {"type": "reply", "op": "stop", "ok": True}
        if op == "request":
            address = str(req.get("address", ""))
            args = req.get("args") or []
            if not isinstance(args, list):      # (a word was split into its letters)
                return {"type": "reply", "op": op, "address": address, "ok": False,
                        "reason": "args must be a list"}
            if self.ctl is None:
                return {"type": "reply", "op": op, "address": address, "args": args,
                        "ok": False, "reason": "this run takes no live changes"}
            from hapsim.audio.messages import ADDRESSES
            if address not in ADDRESSES or address in ("/hapsim/felt", "/hapsim/loop",
                                                       "/hapsim/telemetry"):
                return {"type": "reply", "op": op, "address": address, "args": args,
                        "ok": False, "reason": "unknown change address"}
            ok, info = self.ctl.request(address, *args)
            out = {"type": "reply", "op": op, "address": address, "args": args, "ok": ok}
            if ok:
                out.update(ramp_s=info[0], k=info[1], b=info[2])
            else:
                out["reason"] = info
            return out
        return {"type": "reply", "op": op, "ok": False, "reason": "unknown request"}

    def _hello(self) -> dict:
        return {"type": "hello", "what": self.what, "layout": self.layout,
                "period_us": 1e6 / self.layout["rate_hz"],
                "controls": self.ctl is not None,
                "axis": int(getattr(self.source, "axis", 0)),
                "hist_bins": HIST_BINS}

    def _frame(self, st: dict) -> dict:
        src = self.source
        frame = {"type": "frame", "wall": time.time()}
        first, cols = src.rows(st["since"], 20 * int(src.rate_hz))
        n = len(cols["t"])
        st["since"] = first + n
        frame["count"] = int(first + n)
        if n:
            stride = max(1, -(-n // MOST_POINTS))
            frame["t"] = cols["t"][::stride].tolist()
            frame["x"] = cols["x"][::stride].tolist()
            frame["f"] = cols["f"][::stride].tolist()
            if "flags" in cols:
                from hapsim.host.telemetry import FLAG_ESTIMATED, FLAG_LATE
                fl = cols["flags"]
                frame["late_t"] = cols["t"][(fl & FLAG_LATE) != 0][:50].tolist()
                frame["est_t"] = cols["t"][(fl & FLAG_ESTIMATED) != 0][:50].tolist()
                frame["late_n"] = int(np.count_nonzero(fl & FLAG_LATE))
                frame["est_n"] = int(np.count_nonzero(fl & FLAG_ESTIMATED))
            if "turnaround_us" in cols:
                ta = cols["turnaround_us"]
                h, _ = np.histogram(ta, bins=HIST_BINS, range=(0.0, 2e6 / src.rate_hz))
                st["hist"] += h
                st["over"] = st.get("over", 0) + int(np.count_nonzero(ta > 2e6 / src.rate_hz))
                frame["hist"] = st["hist"].tolist()
                frame["hist_over"] = st["over"]
            if "xs" in cols:
                frame["port_f"] = cols["fs"][-1].tolist()
        try:
            pos = src.positions()
            frame["pos"] = pos.tolist()
            frame["energy"] = _energy(pos, src.previous(), self._scene(), src.period)
        except Exception:
            pass
        if "port_f" not in frame and n:
            frame["port_f"] = [float(cols["f"][-1])]
        ctl = self.ctl
        if ctl is not None:
            j = ctl.journal
            new = j[st["journal"]:st["journal"] + 50]
            st["journal"] += len(new)
            frame["journal"] = new
            f = ctl.felt
            frame["felt"] = {q: f.get(q) for q in ("k", "b", "f0_hz", "damping_ratio",
                                                   "stable", "spectral_radius",
                                                   "stiffness_limit", "port_K", "port_B")
                             if q in f}
            if self.record_rows:
                # the run's record so far, measured as the report will measure it
                got = self.measurements[st.get("measured", 0):]
                st["measured"] = len(self.measurements)
                if got:
                    frame["measurements"] = got
            else:
                m = ctl.measurement or {}
                frame["measured"] = {"k": ctl.measured[0], "b": ctl.measured[1],
                                     "k_unc": m.get("k_unc"), "b_unc": m.get("b_unc"),
                                     "why_not": ctl.unmeasured}
            frame["links"] = {lk.name: [lk.stiffness, lk.damping] for lk in
                              (*ctl.scene.links, *(getattr(ctl.scene, "planes", ()) or ()))}
            frame["masses"] = {mm.name: mm.mass for mm in ctl.scene.masses
                               if mm.kind == "mass"}
            frame["accepted"], frame["refused"] = ctl.accepted, ctl.refused
        ev = src.events
        new = [e for e in ev[st["events"]:st["events"] + 50]
               if not str(e.get("event", "")).startswith("osc ")]
        st["events"] = min(len(ev), st["events"] + 50)
        if new:
            frame["events"] = new
        if self.grid is not None and not st["grid"]:
            frame["grid"] = self.grid
            st["grid"] = True
        if self.report is not None:
            frame["report"] = self.report
            st["report"] = True
        return frame

    def _scene(self):
        return self.ctl.scene if self.ctl is not None else self.source.scene


def _energy(pos, prev, scene, T) -> float | None:
    """Stored energy of the scene [J]: kinetic ``m v^2 / 2`` of each mass (``v`` the
    backward difference of the positions over the sample period ``T``) plus potential
    ``K s^2 / 2`` of each link (``s`` its stretch: 1-D ``x2 - x1``; n-D the distance less
    the rest length; a contact only while engaged, ``s = threshold - gap``)."""
    e = 0.0
    names = {m.name: i for i, m in enumerate(scene.masses)}
    if prev is not None:
        v = (pos - prev) / T
        for i, m in enumerate(scene.masses):
            if m.kind == "mass":
                e += 0.5 * float(m.mass) * float(np.dot(v[i], v[i]))
    for lk in scene.links:
        d = pos[names[lk.m2]] - pos[names[lk.m1]]
        if pos.shape[1] == 1:
            gap = float(d[0])
            s = gap if lk.kind != "contact" else max(0.0, float(lk.threshold) - gap)
        else:
            r = float(np.linalg.norm(d))
            s = (r - float(getattr(lk, "length", 0.0)) if lk.kind != "contact"
                 else max(0.0, float(lk.threshold) - r))
        if math.isfinite(lk.stiffness):
            e += 0.5 * float(lk.stiffness) * s * s
    return e if math.isfinite(e) else None


def _dumps(obj) -> str:
    """JSON a browser parses: NaN and infinities as null, numpy scalars as numbers."""
    from hapsim.outputs import json_safe
    return json.dumps(json_safe(obj), allow_nan=False, default=_safe)


def _safe(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def start_view(source, ctl, stop, port: int, what: str = "run") -> ViewServer:
    """Start the live view and say its address on stderr.

    Parameters
    ----------
    source, ctl, stop, port, what
        As :class:`ViewServer`.

    Returns
    -------
    ViewServer
        Serving (:meth:`ViewServer.finish` hands it the report and stops it).

    Raises
    ------
    ConfigError
        ``websockets`` is not installed, or the port cannot be bound (key ``--view``).
    """
    require_websockets()
    v = ViewServer(source, ctl, stop, port, what).start()
    print(f"hapsim {what}: live view on {v.url}", file=sys.stderr, flush=True)
    return v
