"""The live view (hapsim/view) in a real headless browser: Debian's chromium and
chromium-driver through selenium (tools/view_browser.py, shared with the docs' screenshots).

One run of each kind, each a few seconds of wall clock once started: ``hapsim run`` of the
1-D wall (the page loads, its traces advance, a slider change reaches the engine at the
sample the run's journal says, a refused change is shown with its reason, the stop button
ends the run with its report), ``hapsim play`` of the 1-D wall (the same, the change's
sample checked against the play's telemetry), and ``hapsim play`` of the membrane on a private JACK dummy
server (the 3-D scene drawn, its traces advance, stop), and the same of the pantograph
(2-D, a 1000 Hz JACK server). Each takes its screenshot: into a temporary folder, or into
the folder ``HAPSIM_VIEW_SHOTS`` names (``HAPSIM_VIEW_SHOTS=docs python -m pytest -n 0
tests/test_view.py`` makes docs/view.md's figures); a test run never writes into the
checkout unless asked.
"""

from __future__ import annotations

import json
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tools"))

import view_browser as vb  # noqa: E402
from test_audio_live import dummy_jackd  # noqa: E402  (a private JACK dummy server)

pytestmark = pytest.mark.xdist_group("view_browser")


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    """Where the screenshots go: ``$HAPSIM_VIEW_SHOTS`` (relative to the repository) or a
    temporary folder."""
    asked = os.environ.get("HAPSIM_VIEW_SHOTS")
    return os.path.join(ROOT, asked) if asked else str(tmp_path_factory.mktemp("shots"))


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    why = vb.browser_missing()
    if why:
        pytest.skip(why)
    d = vb.open_browser(str(tmp_path_factory.mktemp("chromium-profile")))
    yield d
    d.quit()


def _set(driver, row_id: str, value: float) -> None:
    """Type ``value`` in a control's number box and commit it (its change event)."""
    driver.execute_script(
        "const n = document.querySelector(`#${arguments[0]} input[type=number]`);"
        "n.value = arguments[1]; n.dispatchEvent(new Event('change'));", row_id, value)


def test_run_wall_view_change_refusal_stop(browser, shots):
    # lockstep, paced by the host in real time: this test is about the page and the
    # controller, not the device's timing (a loaded 2-core box, the browser drawing beside
    # the loop, stalled a wall-clock mock into a safety stop: tools/view_bench.py measures
    # that side)
    r = vb.ViewRun(["run", "configs/wall.yaml", "--duration", "0", "--lockstep",
                    "--host-clocked", "--json"])
    try:
        browser.get(r.url)
        vb.wait_for(browser, "window.hapsimView && window.hapsimView.t.length > 20", 60)
        t1 = browser.execute_script("const S = window.hapsimView; return S.t[S.t.length-1]")
        t2 = vb.wait_for(browser, f"(() => {{ const S = window.hapsimView; "
                                  f"const t = S.t[S.t.length-1]; return t > {t1} + 0.1 && t }})()")
        assert t2 > t1                                  # the traces advance
        # offline: every file the page loaded came from the view's own address
        got = browser.execute_script(
            "return performance.getEntriesByType('resource').map(e => e.name)")
        assert got and all(u.startswith(r.url) for u in got), got
        vb.wait_for(browser, "window.hapsimView.grid !== null", 60)
        # the felt pair measured on the record so far (before the report's own)
        live = vb.wait_for(browser, "window.hapsimView.measurements.find("
                                    "q => !q.final && q.k !== undefined)", 120)
        browser.save_screenshot(os.path.join(shots, "view_wall.png"))
        # an accepted change: the wall's K from 1000 to 1100 N/m
        _set(browser, "ctl-wall-K", 1100)
        rep = vb.wait_for(browser, "window.hapsimView.replies.find(m => m.op === 'request')",
                          60)
        assert rep["ok"], rep
        try:
            start = vb.wait_for(browser, "window.hapsimView.journal.find("
                                         "j => j.event === 'ramp_start')", 60)
        except TimeoutError:
            raise AssertionError(browser.execute_script(
                "return JSON.stringify([window.hapsimView.journal, window.hapsimView.count,"
                " window.hapsimView.frames])")) from None
        # a refused change: K far beyond the stability boundary (K_max ~ 1313 N/m)
        _set(browser, "ctl-wall-K", 1e6)
        bad = vb.wait_for(browser, "window.hapsimView.replies.find(m => m.ok === false)", 60)
        assert "unstable" in bad["reason"]
        shown = browser.find_element("id", "reply")
        assert shown.get_attribute("class") == "refused"
        assert "unstable" in shown.text and "refused" in shown.text
        # the slider went back to the accepted value
        assert float(browser.execute_script(
            "return document.querySelector('#ctl-wall-K input[type=number]').value")) == 1100
        browser.find_element("id", "stop").click()
        vb.wait_for(browser, "window.hapsimView.report !== null", 60)
        text = browser.find_element("id", "report").text
        assert "view: stop button" in text
        code, out, err = r.finish(60)
    finally:
        r.kill()
    assert code == 0, err
    report = json.loads(out)
    assert report["loop"]["stop_reason"] == "view: stop button"
    changes = report["osc"]["changes"]
    assert [c["args"] for c in changes] == [["wall", 1100, 1.5]]
    # the engine took the change at the sample the page's journal said, and the run's
    # journal (the report) says the same sample
    assert changes[0]["sample"] == rep_sample(browser) and start["sample"] >= changes[0]["sample"]
    assert report["osc"]["refused"] == 1
    # the page's last measured pair is the report's (revised for the change, which came
    # within its record); the one measured live on the rows before it was the predicted
    # pair within its stated uncertainty (the report's verdict, on fewer rows)
    final = browser.execute_script("return window.hapsimView.measurements.find(q => q.final)")
    m = report["measured"]
    assert (final["k"], final["b"]) == (m["k"], m["b"])
    assert live["rows"] <= final["rows"] and live["within"] is True, live


def test_play_1d_view_change_refusal_stop(browser, tmp_path):
    """``hapsim play`` of the 1-D wall (silent, paced by the clock) with its view: the page
    loads, draws the 1-D scene and its traces advance; a change of the wall's K made on
    the page (ramp 0: a step) reaches the engine at the sample the journal names, which
    the play's own telemetry shows independently (its port force is the wall's law with
    the old K on every row before that sample and with the new K on every row from it);
    a refused change is shown with its reason; the stop button ends the play with its
    report."""
    import numpy as np

    from tolerance import rel_tol
    tel, journal = tmp_path / "t.npz", tmp_path / "journal.json"
    r = vb.ViewRun(["play", "configs/wall.yaml", "--sound", "none", "--duration", "120",
                    "--ramp", "0", "--telemetry", str(tel), "--journal", str(journal),
                    "--json"])
    try:
        browser.get(r.url)
        vb.wait_for(browser, "window.hapsimView && window.hapsimView.t.length > 20", 60)
        assert browser.execute_script("return window.hapsimView.layout.dim") == 1
        t1 = browser.execute_script("const S = window.hapsimView; return S.t[S.t.length-1]")
        vb.wait_for(browser, f"(() => {{ const S = window.hapsimView; "
                             f"return S.t[S.t.length-1] > {t1} + 0.1 }})()")
        # an accepted change: the wall's K from 1000 to 1100 N/m
        _set(browser, "ctl-wall-K", 1100)
        rep = vb.wait_for(browser, "window.hapsimView.replies.find(m => m.op === 'request')",
                          60)
        assert rep["ok"], rep
        start = vb.wait_for(browser, "window.hapsimView.journal.find("
                                     "j => j.event === 'ramp_start')", 60)
        # a refused change: K far beyond the stability boundary (K_max ~ 1313 N/m)
        _set(browser, "ctl-wall-K", 1e6)
        bad = vb.wait_for(browser, "window.hapsimView.replies.find(m => m.ok === false)", 60)
        assert "unstable" in bad["reason"]
        shown = browser.find_element("id", "reply")
        assert shown.get_attribute("class") == "refused" and "unstable" in shown.text
        browser.find_element("id", "stop").click()
        vb.wait_for(browser, "window.hapsimView.report !== null", 60)
        assert "view: stop button" in browser.find_element("id", "report").text
        code, out, err = r.finish(60)
    finally:
        r.kill()
    assert code == 0, err
    report = json.loads(out)
    assert report["stop_reason"] == "view: stop button" and report["samples"] < 120000
    assert (report["accepted"], report["refused"]) == (1, 1)
    assert report["links"]["wall"] == [1100, 1.5]
    # the page's journal, the report's and the journal file name the same sample
    ramp = [j for j in report["journal"] if j["event"] == "ramp_start"]
    assert [j["sample"] for j in ramp] == [start["sample"]]
    with open(journal, encoding="utf-8") as fh:
        assert [j["sample"] for j in json.load(fh) if j["event"] == "ramp_start"] == \
            [start["sample"]]
    # the engine: f[n] = -(K x[n] + B (x[n] - x[n-1]) / T) at the wall (ground at 0)
    z = np.load(tel)
    x, f = z["position"], z["force"]
    assert x.size == report["samples"]
    T, B = 1.0 / report["rate_hz"], 1.5
    xp = np.r_[x[0], x[:-1]]
    scale = 1100 * np.abs(x) + B * (np.abs(x) + np.abs(xp)) / T
    tol = rel_tol(8) * scale    # the engine's and this sum's roundings: a few each side

    def law(K):
        return np.abs(f + K * x + B * (x - xp) / T)[1:] <= tol[1:]
    n0 = start["sample"]
    old, new = law(1000.0), law(1100.0)
    assert 1 < n0 < x.size - 1
    assert old[:n0 - 1].all() and not old[n0 - 1:].any(), (n0, np.flatnonzero(~old)[:5] + 1)
    assert new[n0 - 1:].all(), np.flatnonzero(~new[n0 - 1:])[:5] + n0


def rep_sample(browser) -> int:
    """The sample the page's journal gives the accepted change."""
    return browser.execute_script(
        "return window.hapsimView.journal.find(j => j.event === 'accepted').sample")


@pytest.mark.parametrize("which,rate,period", [("membrane", 44100, 256),
                                                ("pantograph", 1000, 64)])
def test_play_nd_view(browser, shots, tmp_path, which, rate, period):
    """An n-D play (its JACK server at the scene's rate) drawn and stopped from the page."""
    scene = (vb.pantograph_with_listen(str(tmp_path)) if which == "pantograph"
             else os.path.join("configs", "membrane.yaml"))
    jack = dummy_jackd(rate, period)
    server = next(jack)
    try:
        _play_nd(browser, scene, server, which, shots)
    finally:
        jack.close()


def _play_nd(browser, scene, jack_server, which, shots):
    r = vb.ViewRun(["play", scene, "--sound", "jack", "--jack-server", jack_server,
                    "--duration", "60", "--json"])
    try:
        browser.get(r.url)
        # one trace row per producer chunk (256 samples): the pantograph's 1000 Hz gives
        # about 4 a second, 16 in the page's 4 s window
        points = 20 if which == "membrane" else 5
        vb.wait_for(browser, f"window.hapsimView && window.hapsimView.t.length > {points}", 60)
        dim = browser.execute_script("return window.hapsimView.layout.dim")
        assert dim == (2 if which == "pantograph" else 3)
        # the traces show the axis the scene moves along: the membrane heard along z
        label = browser.find_element("css selector", "#traces .u-legend").text
        assert ("position z" if which == "membrane" else "position y") in label
        n0 = browser.execute_script("return window.hapsimView.count")
        vb.wait_for(browser, f"window.hapsimView.count > {n0}")
        browser.save_screenshot(os.path.join(shots, f"view_{which}.png"))
        browser.find_element("id", "stop").click()
        vb.wait_for(browser, "window.hapsimView.report !== null", 60)
        code, out, err = r.finish(60)
    finally:
        r.kill()
    assert code == 0, err
    assert json.loads(out)["stop_reason"] == "view: stop button"


def test_measure_record_is_the_reports_measurement(tmp_path):
    """The live measurement (:func:`hapsim.view.sources.measure_record`) on a run's whole
    record is the report's ``measured`` to the last bit (the same identification on the same
    rows); on the first quarter it agrees with it within the two stated uncertainties (the
    wall with sensor noise and a quantised position, so that they are not round-off:
    measured 0.066 N/m and 0.0004 N s/m apart against 0.38 and 0.004 stated)."""
    import numpy as np

    import hapsim
    from hapsim.api import load_scene
    from hapsim.pipeline.options import RunOptions
    from hapsim.pipeline.runner import prepare_run
    from hapsim.pipeline.measure import measure_record
    with open(os.path.join(ROOT, "configs", "wall.yaml"), encoding="utf-8") as fh:
        text = fh.read()
    scene = tmp_path / "noisy_wall.yaml"
    scene.write_text(text.replace("  force_limit: 10.0", "  noise: 2.0e-6\n"
                                  "  position_resolution: 1.0e-6\n  force_limit: 10.0"))
    tel = str(tmp_path / "t.npz")
    rep = hapsim.run(str(scene), duration=1.0, transport="inprocess", lockstep=True,
                     telemetry=tel).to_dict()
    z = np.load(tel)
    prep = prepare_run(load_scene(str(scene)), RunOptions(duration=1.0))
    # (every array of the file: its events, the run's description first, are not read)
    whole = measure_record(prep, {c: z[c] for c in z.files})
    assert "events" in z.files
    m = rep["measured"]
    assert m["k_unc"] > 1e-5 * m["k"]     # the noise states it (an exact record: 1e-15)
    assert (whole["k"], whole["b"], whole["rows"]) == (m["k"], m["b"], z["seq"].size)
    part = measure_record(prep, {c: z[c][:250] for c in z.files if c != "events"})
    assert part["rows"] == 250
    assert abs(part["k"] - m["k"]) <= part["k_unc"] + m["k_unc"]
    assert abs(part["b"] - m["b"]) <= part["b_unc"] + m["b_unc"]


def test_trace_axis_of_nd_plays():
    """An n-D play traces the axis its scene moves along: the membrane's listened z, the
    pantograph's listened y (its handle pressed along y), not always x."""
    from hapsim.api import load_scene_nd
    from hapsim.view.sources import ChunkSource
    assert ChunkSource._trace_axis(load_scene_nd(os.path.join(ROOT, "configs",
                                                              "membrane.yaml"))) == 2
    tmp = os.path.join(ROOT, "configs", "pantograph_wall.yaml")
    assert ChunkSource._trace_axis(load_scene_nd(tmp)) == 0        # no listen point: x
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        assert ChunkSource._trace_axis(load_scene_nd(vb.pantograph_with_listen(d))) == 1


def test_view_without_websockets_says_how_to_install(monkeypatch, capsys):
    """``--view`` without the websockets package: exit 2 before anything starts, with the
    install command (``hapsim[view]``)."""
    from hapsim.cli import main
    monkeypatch.setitem(sys.modules, "websockets", None)
    monkeypatch.setitem(sys.modules, "websockets.asyncio.server", None)
    assert main(["run", "configs/wall.yaml", "--view", "0", "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert "--view" in err and "pip install 'hapsim[view]'" in err
