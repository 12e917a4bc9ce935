"""A live view of a running scene in the browser (``hapsim run|play ... --view [PORT]``).

The page (served on 127.0.0.1, nothing fetched from outside the machine) shows the scene
(masses, links, contacts lit when engaged, the handle and the hand's force), the loop
(position, force and stored-energy traces; late ticks, estimated samples and safety events
marked; the turnaround histogram against the sample period), the temporary hybrid system's
(k, b) grid (the distortion map of ``hapsim map``, Florens, Voda & Urma Figs. 4, 7-9) with
the target, the prediction and the measured pair, and controls: the live changes of
:mod:`hapsim.audio.control` (the same requests and stability check as OSC) and a stop
button (the run ends as on Ctrl-C, with its report).

The view never touches the loop: a server thread reads what the loop already publishes
(the telemetry arrays, the engine's positions, a bounded ``collections.deque`` the loop
appends to) at the display's rate; nothing the loop does waits on it.

The WebSocket server is the ``websockets`` package (the optional extra ``view``:
``pip install 'hapsim[view]'``); the traces are drawn by uPlot (MIT, vendored in
``hapsim/view/static``), the scene and the grid on a plain canvas.
"""

from __future__ import annotations

from hapsim.view.server import ViewServer, require_websockets, start_view
from hapsim.view.sources import ChunkSource, PlaySource, RunSource

__all__ = ["ViewServer", "start_view", "require_websockets", "RunSource", "PlaySource",
           "ChunkSource"]
