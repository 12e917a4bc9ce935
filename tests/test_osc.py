"""Live control over OSC: ``hapsim play --osc`` driven by a python-osc client and by Pd.

Each test starts the daemon as a child process (real time, no sound, a duration far longer
than the test needs), sends changes (one of them unstable), waits for their replies and
effects however long a loaded machine takes, then ends the daemon by SIGTERM and checks: the accepted ones are applied (the scene's links at the end, and
the felt k measured from the free responses after the change equals the prediction for the
new (K, B) to 1e-6 relative), the refused one is not (answer /hapsim/refused with the
reason), everything is journaled.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time

import pytest

from hapsim.analysis.loop import LoopModel
from hapsim.analysis.ths import render
from test_audio_live import jack_server  # noqa: F401  (the private JACK server fixture)

#: pytest-xdist (the README command runs several workers): a private jackd and Pd/OSC clients:
#: serialised with the other live-sound tests.
pytestmark = pytest.mark.xdist_group("sound")

SCENE = os.path.join(os.path.dirname(__file__), "data", "osc_wall.yaml")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


#: The daemons' --duration [s]: never reached; the tests end them by a signal (:func:`stop`)
#: once their replies are in, so a loaded machine cannot end the play before them.
LONG_S = 600.0


def start_daemon(duration=LONG_S, extra=()):
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "hapsim", "play", SCENE, "--osc", "0",
                             "--sound", "none", "--duration", str(duration),
                             "--pluck-every", "0.4", "--json", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=ROOT,
                            text=True)
    line = proc.stderr.readline()
    if "OSC on" not in line:
        proc.kill()
        pytest.fail(f"daemon did not start: {line}{proc.stderr.read()}")
    port = int(line.strip().rsplit(":", 1)[1])
    return proc, port


def finish(proc):
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    try:
        return json.loads(out)
    except ValueError:
        pytest.fail(f"not one JSON report on stdout: {out[:300]!r}; stderr: {err[-500:]}")


def stop(proc, sig=signal.SIGTERM):
    """End a daemon by ``sig`` (unless it ended already); its JSON report."""
    if proc.poll() is None:
        proc.send_signal(sig)
    return finish(proc)


def wait_for(c, address, done, what, timeout=60.0):
    """Ask ``address`` until ``done(params)`` (a loaded machine's pace), at most ``timeout``
    seconds; the last params."""
    deadline = time.monotonic() + timeout
    while True:
        addr, p = c.ask(address)
        assert addr == address, (addr, p)
        if done(p):
            return p
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: not within {timeout:g} s (last {address} {p})")
        time.sleep(0.05)


#: binary32's machine epsilon [-]: an OSC float is binary32 (what Pd reads), within half of
#: it (one rounding, u = eps / 2: Higham Sec. 2.1) of the double the daemon sent
F32 = 2.0 ** -23


def felt_k(K, B):
    return render(LoopModel(0.1, 0.5, 1000.0, 1, "zoh"), K, B).k


#: The longest a reply may take while the daemon runs [s]: a hang's bound, not a pace (a
#: loaded machine delays the daemon's OSC thread by seconds; a daemon that has ended fails
#: at once, with its stderr).
REPLY_S = 120.0


class Client:
    """A python-osc client that sends from one UDP socket and reads the replies on it.

    ``proc`` (the daemon): a reply is waited for as long as the daemon runs (at most
    :data:`REPLY_S`), never for a fixed time a loaded machine can stretch; one that has
    ended fails the test at once with its stderr. Requests and replies stay paired: a reply
    is never given up on, so a late one cannot answer the next request."""

    def __init__(self, port, proc=None):
        self.addr = ("127.0.0.1", port)
        self.proc = proc
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(1.0)

    def ask(self, address, *args):
        from pythonosc.osc_message import OscMessage
        from pythonosc.osc_message_builder import OscMessageBuilder

        b = OscMessageBuilder(address=address)
        for a in args:
            b.add_arg(a)
        self.sock.sendto(b.build().dgram, self.addr)
        deadline = time.monotonic() + REPLY_S
        while True:
            try:
                data, _ = self.sock.recvfrom(65536)
                break
            except (socket.timeout, TimeoutError):
                if self.proc is not None and self.proc.poll() is not None:
                    pytest.fail(f"the daemon ended (exit {self.proc.returncode}) before "
                                f"answering {address}: {self.proc.stderr.read()[-800:]}")
                if time.monotonic() > deadline:
                    pytest.fail(f"no answer to {address} within {REPLY_S:g} s")
        msg = OscMessage(data)
        return msg.address, list(msg.params)


class Sink:
    """A UDP socket that receives a daemon's ``/hapsim/tel`` stream, drained by a thread
    as it arrives: read only at the end, its receive buffer (~200 KB, a few hundred
    datagrams) overflowed while a loaded machine made the test last longer, and the kernel
    dropped the newest datagrams (those after a change)."""

    def __init__(self):
        import threading
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.data = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self):
        while not self._stop.is_set():
            try:
                self.data.append(self.sock.recvfrom(65536)[0])
            except (socket.timeout, TimeoutError):
                pass
            except OSError:
                return

    def close(self, linger=0.2):
        """Stop after ``linger`` seconds without a datagram; the datagrams received."""
        n = -1
        while n != len(self.data):
            n = len(self.data)
            time.sleep(linger)
        self._stop.set()
        self._thread.join()
        self.sock.close()
        return self.data


def test_python_osc_client_changes_are_checked_ramped_and_felt(tmp_path):
    """Changes (accepted, refused: unstable, unknown link, a ground's mass), the felt and
    loop queries, and the telemetry stream: every /hapsim/tel t x f k b carries the device
    position the run logged at sample t * rate (its --telemetry file) and the felt k of
    the scene in force."""
    tel_file = str(tmp_path / "tel.npz")
    proc, port = start_daemon(extra=("--telemetry", tel_file))
    c = Client(port, proc)
    sink = Sink()
    try:
        addr, p = c.ask("/hapsim/telemetry", "127.0.0.1", sink.port, 100.0)
        assert addr == "/hapsim/ok" and p[0] == "/hapsim/telemetry"
        addr, p = c.ask("/hapsim/link/stiffness", "wall", 700.0)
        assert addr == "/hapsim/ok" and p[0] == "/hapsim/link/stiffness"
        # OSC floats are binary32 (what Pd reads): within F32 (its eps, twice the rounding's
        # bound; the daemon's felt k is the test's render up to double round-off); measured
        # 2.4e-8 at worst on both targets
        assert p[1] == pytest.approx(0.05, rel=F32)
        assert p[2] == pytest.approx(felt_k(700.0, 1.0), rel=F32)
        addr, p = c.ask("/hapsim/link/stiffness", "wall", 1.0e6)      # unstable at d = 1
        assert addr == "/hapsim/refused" and "unstable" in p[1]
        addr, p = c.ask("/hapsim/link/stiffness", "nowhere", 10.0)
        assert addr == "/hapsim/refused" and "nowhere" in p[1]
        addr, p = c.ask("/hapsim/mass", "wall", 1.0)                  # a ground
        assert addr == "/hapsim/refused"
        # a pluck after the ramp: a free response, measured (not NaN)
        p = wait_for(c, "/hapsim/felt", lambda p: p[4] == p[4], "no free response measured")
        assert p[0] == pytest.approx(felt_k(700.0, 1.0), rel=F32)    # binary32: its eps
        # measured = predicted: measured 0 (generic 0), the same binary32 on both targets;
        # the bound: one binary32 rounding each side (eps32 / 2 each) over the float64
        # identification's own error (1e-13 relative, tests/test_audio_live.py)
        assert p[4] == pytest.approx(p[0], rel=2 * F32)
        addr, p = c.ask("/hapsim/loop")
        assert addr == "/hapsim/loop" and p[2] == 1 and p[3] == 1 and p[4] == 3
        # 0.8 s of samples played since the stream was asked for (at the start): 80 /hapsim/tel
        wait_for(c, "/hapsim/loop", lambda p: p[0] >= 800, "800 samples")
    finally:
        rep = stop(proc)
    assert rep["stop_reason"] == "signal SIGTERM"
    assert rep["links"]["wall"] == [700.0, 1.0]
    # measured 9.6e-16 relative (generic 2.7e-15), margin 3.6e8
    assert rep["measured"]["k"] == pytest.approx(felt_k(700.0, 1.0), rel=1e-6)
    _check_telemetry_stream(sink, tel_file, rep["rate_hz"])
    events = [(e["event"], e["address"]) for e in rep["journal"]]
    assert ("accepted", "/hapsim/link/stiffness") in events
    assert ("ramp_end", "link") in events
    assert sum(e == "refused" for e, _ in events) == 3


def _check_telemetry_stream(sink, tel_file, rate):
    """The /hapsim/tel messages that reached ``sink`` against the run's telemetry file."""
    import numpy as np
    from pythonosc.osc_message import OscMessage

    msgs = [OscMessage(d) for d in sink.close()]
    with np.load(tel_file) as z:
        pos = z["position"]
    tel = [m.params for m in msgs if m.address == "/hapsim/tel"]
    assert len(tel) > 50, len(tel)               # 100 Hz over >= 0.8 s
    n = np.array([round(t * rate) for t, *_ in tel])
    x = np.array([p[1] for p in tel])
    # measured 0 (generic 0): exact on both targets
    np.testing.assert_allclose(x, pos[n].astype(np.float32), rtol=1e-6, atol=1e-12)
    k_new = felt_k(700.0, 1.0)
    # the change's felt k, as binary32: within F32 (its eps)
    assert any(abs(p[3] - k_new) <= F32 * k_new for p in tel)


PATCH = """#N canvas 0 50 600 400 12;
#X obj 10 10 loadbang;
#X msg 10 40 connect 127.0.0.1 {port};
#X obj 10 330 netsend -u -b;
#X obj 10 70 delay 100;
#X msg 10 100 list wall 600;
#X obj 10 200 oscformat hapsim link stiffness;
#X obj 10 240 list prepend send;
#X obj 10 270 list trim;
#X obj 200 70 delay 300;
#X msg 200 100 list wall 1e+06;
#X obj 400 70 delay 600;
#X msg 400 100 \\; pd quit;
#X connect 0 0 1 0;
#X connect 1 0 2 0;
#X connect 0 0 3 0;
#X connect 3 0 4 0;
#X connect 4 0 5 0;
#X connect 5 0 6 0;
#X connect 6 0 7 0;
#X connect 7 0 2 0;
#X connect 0 0 8 0;
#X connect 8 0 9 0;
#X connect 9 0 5 0;
#X connect 0 0 10 0;
#X connect 10 0 11 0;
"""


def run_patch(text, port, tmp_path):
    """Run a Pd patch (``text`` with ``{port}``) headless, ``pd -nogui -nosound``, to its
    end (the patch quits itself)."""
    patch = tmp_path / "send.pd"
    patch.write_text(text.format(port=port))
    pd = subprocess.run(["pd", "-nogui", "-nosound", "-open", str(patch)],
                        capture_output=True, text=True, timeout=60)
    assert pd.returncode == 0, pd.stderr


def test_pd_patch_sends_changes_over_osc(tmp_path):
    """A Pd patch run headless (pd -nogui -nosound) sends, with [oscformat] into
    [netsend -u -b], K = 600 (stable: applied, then felt) and K = 1e6 (unstable: refused),
    and quits from inside the patch."""
    if shutil.which("pd") is None:
        pytest.skip("pd not installed: apt-get install puredata")
    proc, port = start_daemon()
    try:
        run_patch(PATCH, port, tmp_path)
        c = Client(port, proc)   # both changes answered, then a free response measured after
        wait_for(c, "/hapsim/loop", lambda p: (p[3], p[4]) == (1, 1), "Pd's two changes")
        wait_for(c, "/hapsim/felt", lambda p: p[4] == p[4], "no free response measured")
    finally:
        rep = stop(proc)
    assert rep["links"]["wall"] == [600.0, 1.0]
    got = [(e["event"], e["args"]) for e in rep["journal"] if e["event"] in ("accepted", "refused")]
    assert got == [("accepted", ["wall", 600.0]), ("refused", ["wall", 1e6])], got
    # measured 0 (generic 0): exact on both targets
    assert rep["felt"]["k"] == pytest.approx(felt_k(600.0, 1.0), rel=1e-9)
    # measured 2.6e-15 relative (generic 1.7e-15), margin 3.8e8
    assert rep["measured"]["k"] == pytest.approx(rep["felt"]["k"], rel=1e-6)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_play_ends_on_a_signal_with_its_report(tmp_path, sig):
    """SIGINT (Ctrl-C) or SIGTERM mid-play, as hapsim run: the loop ends, the report (JSON
    alone on stdout) covers what was played, with the signal as stop reason, the telemetry
    file holds exactly those samples, exit 0."""
    import numpy as np

    tel_file = str(tmp_path / "tel.npz")
    proc, port = start_daemon(extra=("--telemetry", tel_file))
    try:
        played = wait_for(Client(port, proc), "/hapsim/loop", lambda p: p[0] >= 300,
                          "300 samples")[0]
    finally:
        rep = stop(proc, sig)
    assert rep["stop_reason"] == f"signal {sig.name}"
    assert played <= rep["samples"] < LONG_S * rep["rate_hz"]
    with np.load(tel_file) as z:
        assert z["position"].size == z["force"].size == rep["samples"]
        assert np.all(np.isfinite(z["position"])) and np.any(z["position"] != 0)


def test_run_osc_changes_the_running_daemon():
    """hapsim run --osc (real-time embedded mock on a pty): an accepted change is ramped
    into the running engine and reported with its prediction, a refused one is not.

    The run keeps its default real-time priority (SCHED_FIFO where permitted, as a user's
    run): at normal priority on a loaded CI machine its host was once descheduled long
    enough for the lateness guard to stop the wall (stable to 3 periods of delay; a 60 ms
    stall of the host stops it, "grow it x2.4"), which is the guard's business, not this
    test's."""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    hst = os.path.join(os.environ.get("TMPDIR", "/tmp"), f"osc-{os.getpid()}.hst")
    proc = subprocess.Popen([sys.executable, "-m", "hapsim", "run", SCENE, "--osc", "0",
                             "--duration", "0", "--json", "--telemetry", hst],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=ROOT,
                            text=True)
    port = None
    for _ in range(50):
        line = proc.stderr.readline()
        if "OSC on" in line:
            port = int(line.strip().rsplit(":", 1)[1])
            break
        if not line:
            break
    if port is None:
        proc.kill()
        pytest.fail(f"run did not start its OSC server: {proc.stderr.read()}")
    c = Client(port, proc)
    try:
        assert c.ask("/hapsim/link/damping", "wall", 3.0)[0] == "/hapsim/ok"
        addr, p = c.ask("/hapsim/link/kb", "wall", 5.0e5, 3.0)
        assert addr == "/hapsim/refused" and "unstable" in p[1]
        addr, p = c.ask("/hapsim/felt")
        # the predicted b as binary32: within F32 (its eps)
        assert p[1] == pytest.approx(render(LoopModel(0.1, 0.5, 1000.0, 1, "zoh"), 400.0,
                                            3.0).b, rel=F32)
        _ramped(c)
    finally:
        rep = stop(proc)       # --duration 0: open-ended, until the signal
    assert rep["loop"]["stop_reason"] == "signal SIGTERM"
    osc = rep["osc"]
    assert (osc["accepted"], osc["refused"]) == (1, 1)
    assert osc["links"]["wall"] == [400.0, 3.0]
    assert [e["event"] for e in osc["journal"] if e["event"].startswith("ramp")] == \
        ["ramp_start", "ramp_end"]
    from hapsim.host.telemetry import load
    try:
        info = {}
        load(hst, info=info)
        events = [e["event"] for e in info["events"] if e["event"].startswith("osc ")]
    finally:
        os.remove(hst)
    assert events[:2] == ["osc request", "osc accepted"] and "osc refused" in events


SOUND_PAGE = os.path.join(ROOT, "docs", "sound.md")
STRING = os.path.join(ROOT, "configs", "audio_string.yaml")


def _readme_block(lang):
    """The fenced code block of ``lang`` in docs/sound.md ('Sound and OSC control')."""
    import re
    sec = open(SOUND_PAGE).read()
    m = re.search(r"```" + lang + r"\n(.*?)```", sec, re.S)
    assert m, f"docs/sound.md: no ```{lang} block"
    return m.group(1)


def _ramped(c, ramp_samples=200):
    """Wait until the loop has played ``ramp_samples`` more samples (the default ramp,
    0.05 s at the string's 1 kHz device rate, ends within them)."""
    s0 = c.ask("/hapsim/loop")[1][0]
    wait_for(c, "/hapsim/loop", lambda p: p[0] >= s0 + ramp_samples, "the ramp's end")


def play_daemon(scene, jack_server, *extra, duration=LONG_S):
    """hapsim play on ``scene``, sound through the test's JACK server, OSC on any free
    port; the process and that port."""
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "hapsim", "play", str(scene), "--osc", "0",
                             "--sound", "jack", "--jack-server", jack_server,
                             "--duration", str(duration), "--json", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=ROOT,
                            text=True)
    seen = []
    for _ in range(50):
        line = proc.stderr.readline()
        seen.append(line)
        if "OSC on" in line:
            return proc, int(line.strip().rsplit(":", 1)[1])
        if not line:
            break
    proc.kill()
    pytest.fail(f"play did not start its OSC server: {''.join(seen)}{proc.stderr.read()}")


def _play_string(jack_server, duration=LONG_S):
    """hapsim play on the shipped string (:func:`play_daemon`)."""
    return play_daemon(STRING, jack_server, duration=duration)


def test_readme_pd_patch_drives_the_shipped_string(jack_server, tmp_path):
    """The Pd patch of docs/sound.md, as printed (only its port changed), opened headless by pd
    against hapsim play on configs/audio_string.yaml: its changes arrive, are accepted and
    applied (the pluck's (K, B) at the end, the gain's ramp journaled)."""
    if shutil.which("pd") is None:
        pytest.skip("pd not installed: apt-get install puredata")
    patch_text = _readme_block("pd")
    assert "connect 127.0.0.1 9000;" in patch_text
    proc, port = _play_string(jack_server)
    patch = tmp_path / "readme.pd"
    patch.write_text(patch_text.replace("connect 127.0.0.1 9000;", f"connect 127.0.0.1 {port};"))
    pd = subprocess.Popen(["pd", "-nogui", "-nosound", "-open", str(patch)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        c = Client(port, proc)
        wait_for(c, "/hapsim/loop", lambda p: p[3] >= 2, "the patch's two changes")
        _ramped(c)
        rep = stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
        pd.kill()
        pd_err = pd.communicate()[1]
    got = [(e["event"], e["address"], e["args"]) for e in rep["journal"]
           if e["event"] in ("accepted", "refused")]
    assert got == [("accepted", "/hapsim/link/kb", ["pluck", 150.0, 2.0]),
                   ("accepted", "/hapsim/gain", [0.5])], (got, pd_err[-500:])
    assert rep["links"]["pluck"] == [150.0, 2.0]
    assert ("ramp_end", "gain") in [(e["event"], e["address"]) for e in rep["journal"]]
    assert rep["sound"]["backend"] == "JackOutput"


def test_readme_supercollider_lines_drive_the_shipped_string(jack_server):
    """Each ``n.sendMsg`` line of docs/sound.md's SuperCollider snippet, replayed by a
    python-osc client against hapsim play on configs/audio_string.yaml, gets the answer its
    comment states (ok, refused: unstable, felt), and the accepted values are applied."""
    import re

    lines = [ln for ln in _readme_block("supercollider").splitlines() if "sendMsg" in ln]
    assert len(lines) >= 4
    proc, port = _play_string(jack_server)
    c = Client(port, proc)
    try:
        for ln in lines:
            call, comment = (ln.split("//", 1) + [""])[:2]
            args = [a.strip() for a in re.search(r"sendMsg\((.*)\)", call).group(1).split(",")]
            args = [a.strip('"') if a.startswith('"') else float(a) for a in args]
            addr, p = c.ask(*args)
            want = ("/hapsim/refused" if "refused" in comment else
                    "/hapsim/felt" if "/hapsim/felt" in comment else "/hapsim/ok")
            assert addr == want, (ln, addr, p)
            if want == "/hapsim/refused":
                assert "unstable" in p[1], p
        _ramped(c)
    finally:
        rep = stop(proc)
    assert rep["links"]["pluck"] == [150.0, 2.0]
    assert rep["accepted"] == 3 and rep["refused"] == 1
