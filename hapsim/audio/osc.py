"""The OSC front end of live control: :func:`serve_osc` maps the addresses of
:data:`hapsim.audio.messages.ADDRESSES` to a :class:`hapsim.audio.control.Controller` and
answers each request; :func:`send_telemetry` streams the loop's samples to a subscriber.
The addresses and replies are tabled in :mod:`hapsim.audio.messages`."""

from __future__ import annotations

import math
import threading

import numpy as np

from hapsim.audio.control import Controller
from hapsim.audio.messages import ADDRESSES, Refused, number, telemetry_args

__all__ = ["serve_osc", "send_telemetry"]


def serve_osc(ctl: Controller, port: int, host: str = "127.0.0.1", status=None):
    """Start the OSC server of a :class:`Controller` on a thread.

    Parameters
    ----------
    ctl : Controller
    port : int
        UDP port (0: any free port; the server's ``server_address`` says which).
    host : str
        Address to listen on (localhost by default).
    status : callable, optional
        ``status() -> dict`` with ``xruns`` and ``underruns`` for ``/hapsim/loop``.

    Returns
    -------
    server : pythonosc.osc_server.BlockingOSCUDPServer
        Running (``server.shutdown()`` stops it). One thread serves the datagrams in the
        order they arrive, so a sender's changes are checked, applied, journaled and
        answered in the order it sent them (a thread per datagram, as
        ``ThreadingOSCUDPServer`` does, let a quick ``/hapsim/gain`` overtake a
        ``/hapsim/link/kb`` still being checked, and two changes of one link end in
        either order).
    telemetry : dict
        ``{"client": SimpleUDPClient or None, "every": samples}``: where and how often the
        sample loop sends ``/hapsim/tel`` (set by ``/hapsim/telemetry``).
    """
    from pythonosc import dispatcher as osc_dispatcher
    from pythonosc import osc_server, udp_client
    from pythonosc.osc_message_builder import OscMessageBuilder

    tel = {"client": None, "every": 20}
    sock_holder = {}

    def reply(addr, address, *values):
        b = OscMessageBuilder(address=address)
        for v in values:
            b.add_arg(v)
        sock_holder["server"].socket.sendto(b.build().dgram, addr)

    def on_change(client, address, *args):
        ok, info = ctl.request(address, *args)
        if ok:
            reply(client, "/hapsim/ok", address, *info)
        else:
            reply(client, "/hapsim/refused", address, info)

    def on_felt(client, address, *args):
        reply(client, "/hapsim/felt", *ctl.felt_reply())

    def on_loop(client, address, *args):
        st = status() if status is not None else {}
        reply(client, "/hapsim/loop", int(ctl.sample), number(ctl.felt.get("spectral_radius")),
              int(bool(ctl.felt.get("stable"))), int(ctl.accepted), int(ctl.refused),
              int(st.get("xruns", 0)), int(st.get("underruns", 0)))

    def on_telemetry(client, address, *args):
        import socket
        try:
            host_, port_, every = telemetry_args(args, ctl.scene.rate_hz)
            socket.getaddrinfo(host_, port_, type=socket.SOCK_DGRAM)   # a name it can reach
            new = udp_client.SimpleUDPClient(host_, port_)
        except Refused as exc:
            reply(client, "/hapsim/refused", address, str(exc))
            return
        except (OSError, ValueError, UnicodeError) as exc:      # (before: a traceback)
            reply(client, "/hapsim/refused", address, f"host {args[0]!r}: {exc}")
            return
        tel["every"], tel["client"] = every, new
        ctl.log("telemetry", address, args)
        reply(client, "/hapsim/ok", address, 0.0, math.nan, math.nan)

    d = osc_dispatcher.Dispatcher()
    for a in ADDRESSES:
        if a == "/hapsim/felt":
            d.map(a, on_felt, needs_reply_address=True)
        elif a == "/hapsim/loop":
            d.map(a, on_loop, needs_reply_address=True)
        elif a == "/hapsim/telemetry":
            d.map(a, on_telemetry, needs_reply_address=True)
        else:
            d.map(a, on_change, needs_reply_address=True)
    def on_unknown(client, address, *args):
        # returns None: python-osc sends a handler's return value back as a message (a
        # tuple here was its BuildError traceback on stderr)
        ctl.log("refused", address, args, reason="unknown address")
        reply(client, "/hapsim/refused", address,
              f"unknown address; valid: {', '.join(ADDRESSES)}")

    d.set_default_handler(on_unknown, needs_reply_address=True)
    server = osc_server.BlockingOSCUDPServer((host, port), d)
    sock_holder["server"] = server
    threading.Thread(target=server.serve_forever, name="hapsim-osc", daemon=True).start()
    return server, tel


def send_telemetry(tel: dict, t: float, x, f, ctl: Controller) -> None:
    """Send one ``/hapsim/tel t x f k b`` message when a telemetry client is set
    (called by the sample loop every ``tel["every"]`` samples; UDP, never blocks long).

    Parameters
    ----------
    tel : dict
        :func:`serve_osc`'s telemetry dict.
    t : float
        Time [s].
    x, f : float or array_like
        Device position [m] and port force [N]: a number (1-D) or n of each (a 2-D or
        3-D scene: ``/hapsim/tel t x1 .. xn f1 .. fn k b``).
    ctl : Controller
        Its felt ``k``, ``b`` are sent.
    """
    c = tel.get("client")
    if c is not None:
        try:
            c.send_message("/hapsim/tel", [float(t), *(float(v) for v in np.ravel(x)),
                                           *(float(v) for v in np.ravel(f)),
                                           number(ctl.felt.get("k")), number(ctl.felt.get("b"))])
        except (OSError, OverflowError, ValueError):    # (a subscriber gone: not the loop's)
            pass
