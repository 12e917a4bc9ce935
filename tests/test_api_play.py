"""``hapsim.play`` (issue 32): ``hapsim play`` from Python, for any dimension.

The function is the command without its printing (:func:`hapsim.pipeline.play.play_scene`
behind both), so what a script gets is what ``hapsim play --json`` prints for the same
arguments: compared key by key on a 1-D wall (lockstep, no sound: the whole report, to the
bit), a 1-D chain through a real JACK dummy server (everything but the sound server's own
timing) and the 2-D test scene through one (idem). The live view from Python: the page's
WebSocket answers, and its stop button ends the play with its report.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import threading
import time

import pytest

import hapsim
from hapsim.cli import main
from test_audio_live import LINEAR, dummy_jackd
from tolerance import measured

#: pytest-xdist: private jackd servers, serialised with the other live sound tests.
pytestmark = pytest.mark.xdist_group("sound")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WALL = os.path.join("configs", "wall.yaml")
SCENE_2D = os.path.join("tests", "data", "play_nd_2d.yaml")
#: What the sound server decides, not the play: when it called back, how often it was
#: late or starved, how far it read before the client closed (1-D: ``consumed``,
#: ``periods``; n-D: ``read``), how often the loop waited for it.
SERVER_TIMING = ("xruns", "xrun_at_s", "underruns", "underrun_at_s", "loop_begin_s",
                 "active_monotonic_s",
                 "read", "consumed", "periods", "skipped", "waits")


def _cli(argv: list) -> tuple[int, dict]:
    """``hapsim play ... --json`` in this process: its exit code and its report."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["play", *argv, "--json"])
    return code, json.loads(out.getvalue())


def _as_json(report) -> dict:
    """The result as the command's JSON reads back (tuples as lists, NaN as null)."""
    return json.loads(json.dumps(report.to_dict()))


def _differs(a: dict, b: dict) -> dict:
    """The keys whose values differ (for the assertion's message)."""
    return {k: (a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}


def _without_server_timing(rep: dict) -> dict:
    rep = dict(rep)
    rep.pop("wall_s", None)
    if rep.get("sound"):
        rep["sound"] = {k: v for k, v in rep["sound"].items() if k not in SERVER_TIMING}
    return rep


@pytest.fixture(autouse=True)
def _in_root(monkeypatch):
    """In the repository; the last identification waited for as long as it takes (a
    loaded machine can take more than the play's 3 s, which would drop it from one of
    the two reports compared and not the other)."""
    import hapsim.pipeline.play as play
    monkeypatch.chdir(ROOT)
    monkeypatch.setattr(play, "END_WAIT_S", 120.0)


def test_1d_lockstep_play_is_the_commands_report_to_the_bit():
    """The wall played in lockstep without sound (its hand's impulse, one free response
    measured): the result's fields are the command's keys, and every value is the
    command's, from a path or from the loaded scene; the measured pair is the predicted
    one (the THS's closed form), to the identification's round-off."""
    argv = [WALL, "--sound", "none", "--lockstep", "--duration", "0.5"]
    code, cli = _cli(argv)
    r = hapsim.play(WALL, sound="none", lockstep=True, duration=0.5)
    assert isinstance(r, hapsim.PlayReport) and r.extra == {}
    assert (r.exit_code, r.ok) == (code, True) == (0, True)
    assert _as_json(r) == cli
    assert (r.samples, r.paced_by, r.stop_reason) == (500, "none", "duration")
    assert r.measured["why_not"] is None
    # measured 0 (k) and 6.0e-14 (b) relative on this CPU, margin 1e4 for another BLAS
    # kernel and numba target (the identification's SVD; test_audio_live saw a factor 7)
    assert r.k == pytest.approx(r.felt["k"], rel=measured(6.0e-14, 1e4))
    assert r.b == pytest.approx(r.felt["b"], rel=measured(6.0e-14, 1e4))
    loaded = hapsim.play(hapsim.load_scene(WALL), sound="none", lockstep=True,
                         duration=0.5)
    assert _as_json(loaded) == cli
    assert r.text().splitlines()[0].startswith(f"played {WALL} for 0.5 s (500 samples")


def test_1d_play_with_live_jack_sound_is_the_commands_report(tmp_path):
    """A 1-D chain heard through a private JACK dummy server (48 kHz, 256-frame blocks):
    played from Python and from the command line, the reports agree in everything the
    play decides (samples, the delay with the callback's lead, the measured pair, the
    journal, the frames pushed); only the server's timing (xruns, starved blocks) may
    differ."""
    path = tmp_path / "linear.yaml"
    path.write_text(LINEAR)
    jack = dummy_jackd(48000, 256)
    server = next(jack)
    try:
        argv = [str(path), "--sound", "jack", "--jack-server", server, "--duration", "0.5"]
        code, cli = _cli(argv)
        r = hapsim.play(str(path), sound="jack", jack_server=server, duration=0.5)
    finally:
        jack.close()
    assert code == r.exit_code == 0
    assert r.sound["backend"] == "JackOutput" and r.paced_by == "sound"
    assert (r.samples, r.sound["pushed"], r.delay) == (500, 500, 7)   # 1 + ceil(256 / 48)
    mine, theirs = _without_server_timing(_as_json(r)), _without_server_timing(cli)
    assert mine == theirs, (_differs(mine["sound"], theirs["sound"])
                            or _differs(mine, theirs))


def test_2d_play_is_the_commands_report():
    """The 2-D test scene (a handle on a wall holding a chain, heard at two points),
    plucked every 0.1 s through a private JACK dummy server at its 8 kHz: a
    :class:`hapsim.PlayReportND` whose fields are the command's keys, 4000 frames written,
    the same report as the command's but for the server's timing."""
    jack = dummy_jackd(8000, 128)
    server = next(jack)
    try:
        argv = [SCENE_2D, "--sound", "jack", "--jack-server", server, "--duration", "0.5",
                "--pluck-every", "0.1"]
        code, cli = _cli(argv)
        r = hapsim.play(SCENE_2D, sound="jack", jack_server=server, duration=0.5,
                        pluck_every=0.1)
    finally:
        jack.close()
    assert isinstance(r, hapsim.PlayReportND) and r.extra == {}
    assert code == r.exit_code == 0
    assert (r.dof, r.loop, r.frames, r.stop_reason) == (2, "closed", 4000, "duration")
    assert r.plucks["every_samples"] == 800 and r.sound["written"] == 4000
    mine, theirs = _without_server_timing(_as_json(r)), _without_server_timing(cli)
    assert mine == theirs, (_differs(mine["sound"], theirs["sound"])
                            or _differs(mine, theirs))
    assert r.text().splitlines()[0].startswith(f"played {SCENE_2D} (2-D, loop closed)")


def test_an_nd_play_refuses_what_it_does_not_take_and_a_bad_option_is_named():
    """Nothing is played: an option the n-D play does not take is the command's
    ConfigError (keyed by its flag), an unknown keyword names the valid ones, a sound
    that is no choice names the choices."""
    with pytest.raises(hapsim.ConfigError) as e:
        hapsim.play(SCENE_2D, lockstep=True)
    assert e.value.key == "--lockstep"
    with pytest.raises(hapsim.ConfigError) as e:
        hapsim.play(SCENE_2D, sound="none")
    assert e.value.key == "--sound"
    with pytest.raises(hapsim.ConfigError, match="valid: duration, sound"):
        hapsim.play(WALL, port="/dev/null")
    with pytest.raises(hapsim.ConfigError, match="auto, jack, sounddevice, none"):
        hapsim.play(WALL, sound="alsa")


def test_an_unstable_1d_loop_is_refused_before_playing(tmp_path, capsys):
    """The wall beyond its stability limit (K 2000 N/m against K_max 1313): the function
    raises UnstableConfigError with the command's reason; the command exits 1 with it."""
    with open(WALL, encoding="utf-8") as fh:
        text = fh.read()
    assert "stiffness: 1000.0" in text
    path = tmp_path / "hard.yaml"
    path.write_text(text.replace("stiffness: 1000.0", "stiffness: 2000.0", 1))
    with pytest.raises(hapsim.UnstableConfigError, match="is unstable") as e:
        hapsim.play(str(path), sound="none", lockstep=True, duration=0.1)
    assert e.value.spectral_radius > 1.0
    assert main(["play", str(path), "--sound", "none", "--lockstep", "--duration",
                 "0.1"]) == 1
    err = capsys.readouterr().err
    # the refusal's line as every command's (hapsim run's on the same loop)
    assert f"hapsim play: UnstableConfigError: the closed loop of {path} is unstable" in err


def test_play_view_from_python_serves_the_page_and_stops_it(capfd):
    """``hapsim.play(..., view=0)`` in a thread: the view's address on stderr, its page
    served, its WebSocket says hello for ``play`` and sends frames whose sample count
    advances; its stop request ends the play before its 60 s, the result's
    ``stop_reason`` the stop button's, and the last frame carries that report."""
    pytest.importorskip("websockets")
    from urllib.request import urlopen

    from websockets.sync.client import connect
    got = {}

    def play():
        try:
            got["r"] = hapsim.play(WALL, sound="none", view=0, duration=60.0)
        except BaseException as exc:       # noqa: BLE001 - reported by the test
            got["exc"] = exc

    t = threading.Thread(target=play, daemon=True)
    t.start()
    err, url, end = "", None, time.monotonic() + 120
    while url is None and time.monotonic() < end and t.is_alive():
        err += capfd.readouterr().err
        m = re.search(r"hapsim play: live view on (http://127\.0\.0\.1:\d+/)", err)
        url = m.group(1) if m else None
        time.sleep(0.1)
    assert url is not None, (err, got)
    with urlopen(url, timeout=30) as page:
        assert b"<html" in page.read().lower()
    with connect(url.replace("http://", "ws://") + "ws", open_timeout=30) as ws:
        hello = json.loads(ws.recv(30))
        assert hello["type"] == "hello" and hello["what"] == "play"
        assert hello["layout"]["dim"] == 1 and hello["controls"] is True
        counts = []
        while len(counts) < 2 or counts[-1] <= counts[0]:
            f = json.loads(ws.recv(30))
            if f.get("type") == "frame":
                counts.append(f["count"])
        ws.send(json.dumps({"op": "stop"}))
        report = None
        while report is None:
            f = json.loads(ws.recv(60))
            report = f.get("report")
    t.join(60)
    assert not t.is_alive() and "exc" not in got, got
    r = got["r"]
    assert r.stop_reason == "view: stop button" and r.ok
    assert counts[0] < r.samples < 60000
    assert report["stop_reason"] == "view: stop button"
    assert report["samples"] == r.samples


def test_docs_play_example_runs_as_written(capsys):
    """docs/api.md's play example prints the text block after it."""
    with open(os.path.join(ROOT, "docs", "api.md"), encoding="utf-8") as fh:
        text = fh.read()
    m = re.search(r"<!-- test: python play -->\n```python\n(.*?)^```\n\nprints\n\n```text\n"
                  r"(.*?)^```", text, re.S | re.M)
    assert m, "docs/api.md lost its tested play example"
    capsys.readouterr()
    exec(compile(m.group(1), "docs/api.md", "exec"), {})
    assert capsys.readouterr().out == m.group(2)


@pytest.mark.parametrize("handle", [True, False])
def test_ctrl_c_ends_the_play_with_its_report_or_raises_leaving_nothing_running(handle,
                                                                                capfd):
    """SIGINT during ``hapsim.play`` (its view open): with ``handle_signals`` the play ends
    cleanly with its report (``stop_reason: signal SIGINT``), as the command does;
    without, the caller's KeyboardInterrupt comes out of it; either way the analysis
    process is gone and the view's port is closed."""
    import multiprocessing
    import signal
    import socket
    assert threading.current_thread() is threading.main_thread()
    before = set(multiprocessing.active_children())
    port = {}

    def interrupt():
        err, end = "", time.monotonic() + 120
        while time.monotonic() < end:
            err += capfd.readouterr().err
            m = re.search(r"live view on http://127\.0\.0\.1:(\d+)/", err)
            if m:
                port["n"] = int(m.group(1))
                time.sleep(1.0)                     # the loop is running by now
                os.kill(os.getpid(), signal.SIGINT)
                return
            time.sleep(0.05)

    t = threading.Thread(target=interrupt, daemon=True)
    t.start()
    if handle:
        r = hapsim.play(WALL, sound="none", view=0, duration=60.0, handle_signals=True)
        assert r.stop_reason == "signal SIGINT" and r.ok and 0 < r.samples < 60000
    else:
        with pytest.raises(KeyboardInterrupt):
            hapsim.play(WALL, sound="none", view=0, duration=60.0)
    t.join(10)
    assert "n" in port
    assert set(multiprocessing.active_children()) <= before
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port["n"]), timeout=5).close()


@pytest.mark.parametrize("key, value", [
    ("duration", None), ("ramp", None), ("pluck_every", None), ("duration", "x"),
    ("journal", 1.0), ("telemetry", [1, 2]), ("jack_server", 3), ("lockstep", "yes")])
def test_play_refuses_a_keyword_of_the_wrong_kind_by_its_flag(key, value):
    """:func:`hapsim.play` with None for a number that has a default, a number for
    a path or a server's name, a word for a flag: a ConfigError keyed by the command's
    flag, before anything plays (before: TypeErrors, the journal's and the telemetry's
    after the play, when the file was written)."""
    from hapsim.errors import ConfigError
    with pytest.raises(ConfigError) as info:
        hapsim.play("configs/wall.yaml", **{"sound": "none", "duration": 0.05,
                                            key: value})
    assert info.value.key == "--" + key.replace("_", "-"), info.value.key


def test_a_play_too_long_to_record_is_refused_before_it_starts(capsys):
    """``hapsim play --duration 1e8`` (1e11 samples at 1 kHz, 4 TiB of records): one
    line keyed ``--duration`` with the figures, exit 2 (before: numpy's traceback asking
    for 745 GiB)."""
    assert main(["play", "configs/wall.yaml", "--sound", "none", "--duration", "1e8"]) == 2
    err = capsys.readouterr().err
    assert "error: --duration: 1e+11 samples of a play" in err and "Traceback" not in err
