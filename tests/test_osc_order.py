"""A sender's OSC changes are handled in the order it sent them.

Bursts of random changes (link (K, B) stable and unstable, pause/resume, gain where no
sound runs, unknown addresses) are sent from one UDP socket without waiting for the
answers; the answers, the journal's accepted/refused records and the changes posted to the
sample loop must follow the send order, and the scene at the end must hold the last
accepted (K, B). Half the link changes ask for a K of 10^6-10^7 N/m, far above this loop's
stability limit, and must be refused; the other half (K 50-500 N/m, B 1-3 N s/m, where
the spectral radius stays below 0.9963 over the whole rectangle, so every ramp between two
of them too) must be accepted.
"""

from __future__ import annotations

import os
import socket

import numpy as np
import pytest

from hapsim.audio.control import Controller

from hapsim.audio.osc import serve_osc
from hapsim.pipeline.runner import prepare_scene
from hapsim.engine import Engine
from hapsim.scene import load_scene

#: pytest-xdist: live OSC control of a running daemon, no JACK server: its own group (the
#: module's tests on one worker, in turn), not the "sound" group, whose JACK servers must
#: not run two at a time; this module's waits overlap with them.
pytestmark = pytest.mark.xdist_group("osc_live")

SCENE = os.path.join(os.path.dirname(__file__), "data", "osc_wall.yaml")


def _f32(v):
    return float(np.float32(v))      # what an OSC float argument carries


def _burst(rng, n):
    msgs = []
    for _ in range(n):
        r = rng.random()
        if r < 0.6:
            K = float(rng.choice([rng.uniform(50.0, 500.0), rng.uniform(1e6, 1e7)]))
            msgs.append(("/hapsim/link/kb", ["wall", _f32(K), _f32(rng.uniform(1.0, 3.0))]))
        elif r < 0.8:
            msgs.append((str(rng.choice(["/hapsim/pause", "/hapsim/resume"])), []))
        elif r < 0.9:
            msgs.append(("/hapsim/gain", [_f32(rng.uniform(0.0, 1.0))]))
        else:
            msgs.append(("/hapsim/nowhere", [1.0]))
    return msgs


@pytest.mark.parametrize("seed", range(8))
def test_a_burst_of_changes_is_handled_in_send_order(seed):
    from pythonosc.osc_message import OscMessage
    from pythonosc.osc_message_builder import OscMessageBuilder

    rng = np.random.default_rng(seed)
    sc = prepare_scene(load_scene(SCENE))[0]
    ctl = Controller(sc, Engine(sc), ramp_s=0.01)
    server, _ = serve_osc(ctl, 0)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(60.0)
    msgs = _burst(rng, 10)
    try:
        for addr, args in msgs:
            b = OscMessageBuilder(address=addr)
            for a in args:
                b.add_arg(a)
            sock.sendto(b.build().dgram, server.server_address)
        answers = []
        for _ in msgs:
            m = OscMessage(sock.recvfrom(65536)[0])
            answers.append((m.address, m.params[0]))
    finally:
        server.shutdown()
        server.server_close()
        ctl.close()
    sent = [a for a, _ in msgs]
    assert [a for _, a in answers] == sent
    decided = [(e["address"], e["args"]) for e in ctl.journal
               if e["event"] in ("accepted", "refused")]
    assert decided == [(a, list(x)) for a, x in msgs]
    ok = [(a, x) for (a, x), (reply, _) in zip(msgs, answers) if reply == "/hapsim/ok"]
    # every huge K is refused, every moderate one accepted (the loop's limit lies between)
    for (a, x), (reply, _) in zip(msgs, answers):
        if a == "/hapsim/link/kb":
            assert (reply == "/hapsim/ok") == (x[1] < 1e6), (x, reply)
    posted = list(ctl._mail)
    assert [c.kind for c in posted] == [a.rsplit("/", 1)[1].replace("kb", "link")
                                        for a, _ in ok]
    kbs = [x for a, x in ok if a == "/hapsim/link/kb"]
    if kbs:
        assert (ctl.scene.link("wall").stiffness, ctl.scene.link("wall").damping) == \
            (kbs[-1][1], kbs[-1][2])
