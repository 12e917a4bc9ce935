"""``hapsim telemetry FILE``: the summary agrees with the run that wrote the file (seeded
faults), conversions are bit-exact both ways, a journal cut by a kill is read up to what is
intact and says what was lost, and a file that is not telemetry is one line and exit 2."""

from __future__ import annotations

import json
import os
import struct

import numpy as np
import pytest

from hapsim.cli import main
from hapsim.commands.telemetry import felt_energy
from hapsim.host.telemetry import COLUMNS, FLAG_LOST, load, write_journal

#: pytest-xdist (the README command runs several workers): its module-scoped fixture is built once, on
#: one worker.
pytestmark = pytest.mark.xdist_group("test_telemetry_cli")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WALL = os.path.join(ROOT, "configs", "wall.yaml")


@pytest.fixture(scope="module")
def faulted(tmp_path_factory):
    """One run of the real-time mock with seeded faults, on the simulated transport: its
    journal and report.

    The mock's virtual clock (:class:`hapsim.emulated.links.SimTransport`) makes the run
    the same on a quiet machine and under load: on the embedded mock behind a pty, a
    loaded machine makes the host fall behind, the backlog policy skips STATEs, and the
    journal then lacks rows the run's own passivity observer saw (its energy differed by
    28 % on a loaded machine). The journal's writer is the same as with a pty."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    d = tmp_path_factory.mktemp("tel")
    hst = str(d / "run.hst")
    rep = run_scene(load_scene(WALL), transport="sim", faults="drop=0.01,reset@700",
                    fault_seed=3, duration=1.5, telemetry=hst, handle_signals=False)
    assert rep.pop("exit_code") == 0
    return hst, json.loads(json.dumps(rep))


def tel_json(capsys, *args):
    code = main(["telemetry", *args, "--json"])
    out = capsys.readouterr().out
    return code, json.loads(out)


def test_summary_counts_are_the_runs_own(faulted, capsys):
    hst, rep = faulted
    code, s = tel_json(capsys, hst)
    assert code == 0
    lp = rep["loop"]
    assert s["samples"] == rep["telemetry"]["samples"] == lp["ticks"]
    assert s["late"] == lp["late"]
    # every sequence number the journal lacks was missed on the wire or skipped by the
    # backlog policy (newest STATE answered); a drop inside a burst counts as skipped
    assert s["seq"]["missing"] + s["seq"]["skipped"] == lp["missed"] + lp["skipped"]
    assert s["seq"]["skipped"] >= lp["skipped"]
    assert s["events"]["lost"] == lp["lost"] >= 1
    assert s["events"]["recovered"] == lp["recovered"] == lp["lost"]
    assert s["restarts"] == lp["recovered"]
    # the mock stamps each STATE with its clock at the tick: the median step is the period
    # measured 9.1e-16 relative (generic 9.1e-16), margin 1.1e6
    assert s["rate_hz"] == pytest.approx(1000.0, rel=1e-9)
    # the felt energy is the run's own passivity observer, recomputed from the journal:
    # exact, since every STATE has its row (on the virtual clock the host is never behind,
    # so the backlog policy skips none)
    assert s["seq"]["skipped"] == lp["skipped"] == 0
    # measured 0 (generic 0): exact on both targets
    assert s["felt_energy_j"]["max"] == pytest.approx(lp["energy_max_j"], rel=1e-9)
    # measured 0 (generic 0): exact on both targets
    assert s["felt_energy_j"]["end"] == pytest.approx(lp["energy_j"], rel=1e-9, abs=1e-15)
    assert s["integrity"] == {"format": "hst", "intact": True, "chunks": s["integrity"]["chunks"],
                              "torn_bytes": 0, "lost_rows": [], "damaged_after": 0,
                              "time_back": 0, "empty": False}
    cols = load(hst)
    assert s["force_n"] == {"min": cols["force"].min(), "max": cols["force"].max()}
    assert s["position_m"]["max"] == cols["position"].max()
    # the text says the same
    assert main(["telemetry", hst]) == 0
    text = capsys.readouterr().out
    assert f"lost {lp['lost']}, recovered {lp['recovered']}" in text
    assert f"late {lp['late']}" in text and "intact" in text


def test_felt_energy_restarts_at_a_recovery_and_matches_a_loop():
    rng = np.random.default_rng(5)
    x, f = rng.normal(size=40), rng.normal(size=40)
    flags = np.zeros(40, np.uint8)
    flags[25] = FLAG_LOST
    d = 2
    e = felt_energy(x, f, flags, d)
    want = np.zeros(40)
    for start, stop in ((0, 25), (25, 40)):
        acc = 0.0
        for k in range(start, stop):           # the loop's own order: E += f[k-1-d] dx
            j = k - start
            if j > d:
                acc += f[k - 1 - d] * (x[k] - x[k - 1])
            want[k] = acc
    # measured 0 (generic 0): exact on both targets (the loop's own order)
    np.testing.assert_allclose(e, want, rtol=1e-12, atol=1e-15)


def _same(a, b):
    for c in COLUMNS:
        assert a[c].dtype == b[c].dtype, c
        assert a[c].tobytes() == b[c].tobytes(), c


def test_conversions_round_trip_bit_exact(faulted, tmp_path, capsys):
    hst, _ = faulted
    info0: dict = {}
    orig = load(hst, info=info0)
    chain = [hst, str(tmp_path / "a.npz"), str(tmp_path / "b.csv"), str(tmp_path / "c.hst"),
             str(tmp_path / "d.csv"), str(tmp_path / "e.npz"), str(tmp_path / "f.hst")]
    for src, dst in zip(chain, chain[1:]):
        assert main(["telemetry", src, "--out", dst]) == 0
        assert f"wrote {dst}" in capsys.readouterr().out
        _same(orig, load(dst))
    # the events survive .hst -> .npz -> .hst (a .csv carries columns only)
    assert main(["telemetry", chain[0], "--out", chain[1]]) == 0
    assert main(["telemetry", chain[1], "--out", chain[3]]) == 0
    info: dict = {}
    load(chain[3], info=info)
    assert info["events"] == info0["events"] and info0["events"]
    capsys.readouterr()


def test_a_journal_cut_by_a_kill_reads_what_is_intact_and_says_what_was_lost(tmp_path,
                                                                             capsys):
    n = 1000
    rng = np.random.default_rng(1)
    cols = {"time": np.arange(n) * 1e-3, "position": rng.normal(size=n),
            "force": rng.normal(size=n), "seq": np.arange(n, dtype=np.int64),
            "turnaround_us": rng.uniform(10, 90, n), "late": np.zeros(n, np.int8),
            "flags": np.zeros(n, np.uint8)}
    whole = str(tmp_path / "whole.hst")
    write_journal(cols, whole, [{"event": "lost", "sample": 400}], chunk_rows=300)
    data = open(whole, "rb").read()
    cut = str(tmp_path / "cut.hst")
    # chunks: rows 0-299, 300-599, 600-899, 900-999, then the event; cut inside rows 600-899
    ends = []
    pos = 0
    while pos < len(data):
        _, _, hlen, plen, _ = struct.unpack_from("<4sHHII", data, pos)
        pos += 16 + hlen + plen
        ends.append(pos)
    hlen = struct.unpack_from("<4sHHII", data, ends[1])[2]
    torn = 16 + hlen + 100                     # its header whole, its payload cut
    open(cut, "wb").write(data[:ends[1] + torn])
    code, s = tel_json(capsys, cut)
    assert code == 0 and s["samples"] == 600
    ig = s["integrity"]
    assert ig["intact"] is False and ig["chunks"] == 2 and ig["lost_rows"] == [[600, 900]]
    assert ig["torn_bytes"] == torn
    assert main(["telemetry", cut]) == 0
    text = capsys.readouterr().out
    assert "cut short" in text and "rows 600..899" in text
    # cut inside a chunk's fixed head: the rows it held are unknown, and said so
    open(cut, "wb").write(data[:ends[0] + 7])
    code, s = tel_json(capsys, cut)
    assert code == 0 and s["samples"] == 300 and s["integrity"]["torn_bytes"] == 7
    assert main(["telemetry", cut]) == 0
    assert "count unknown" in capsys.readouterr().out
    # an empty journal (killed before its first chunk) is a run of 0 samples, not an error
    open(cut, "wb").close()
    code, s = tel_json(capsys, cut)
    assert code == 0 and s["samples"] == 0


@pytest.mark.parametrize("name, content, says", [
    ("x.hst", b"this is not a journal\n", "not a hapsim telemetry journal"),
    ("x.npz", b"PK\x03\x04 garbage", "cannot read telemetry"),
    ("x.csv", b"a,b,c\n1,2,3\n", "the first line must be the header"),
    ("x.csv", b"time,position,force,seq,turnaround_us,late,flags\n1,x,3,4,5,6,7\n",
     "cannot read telemetry"),
    ("x.txt", b"", "unknown telemetry format '.txt'; valid: .hst, .npz, .csv"),
    (None, None, "no such file"),
])
def test_a_file_that_is_not_telemetry_is_one_line_and_exit_2(tmp_path, capsys, name, content,
                                                             says):
    path = tmp_path / (name or "missing.hst")
    if content is not None:
        path.write_bytes(content)
    assert main(["telemetry", str(path)]) == 2
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and says in err, err
    assert cap.out == ""


def test_bad_options_are_one_line_and_exit_2(faulted, tmp_path, capsys):
    hst, _ = faulted
    for args, says in ((["--out", str(tmp_path / "x.parquet")], "valid: .hst, .npz, .csv"),
                       (["--out", str(tmp_path / "no" / "x.npz")], "does not exist"),
                       (["--out", hst], "the file being read"),
                       (["--plot", str(tmp_path / "x.nope")], "--plot"),
                       (["--delay", "-1"], "--delay")):
        assert main(["telemetry", hst, *args]) == 2, args
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and says in err, (args, err)


def test_plot_is_written(faulted, tmp_path, capsys):
    hst, _ = faulted
    png = tmp_path / "run.png"
    code, s = tel_json(capsys, hst, "--plot", str(png))
    assert code == 0 and s["plot"] == str(png)
    with open(png, "rb") as fh:
        assert fh.read(8) == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("ext", [".hst", ".npz", ".csv"])
def test_damaged_files_are_read_or_refused_never_a_traceback(faulted, tmp_path, capsys, ext):
    """A seeded fuzz of the run's file in each format: bytes flipped (one bit, or up to 50
    bytes set at random), the file cut short, or bytes inserted; ``hapsim telemetry`` on
    each is a summary (exit 0) or one line naming the file (exit 2), never an exception.
    Before, a flipped bit in an ``.npz`` member's header (numpy parses it as a Python
    literal: ``tokenize.TokenError``) and a garbled zip "version" (``NotImplementedError``)
    escaped as tracebacks, found by the same fuzz over 400 files."""
    import random
    hst, _ = faulted
    src = str(tmp_path / f"run{ext}")
    if ext == ".hst":
        src = hst
    else:
        assert main(["telemetry", hst, "--out", src]) == 0
        capsys.readouterr()
    clean = open(src, "rb").read()
    rng = random.Random(ext)
    codes = set()
    for i in range(42):
        data = bytearray(clean)
        how = i % 4 if i < 40 else i
        if how == 40:
            # the two the fuzz found, made certain (an .npz's members are stored whole):
            # a member's header dict opened with "(" (tokenize.TokenError) ...
            j = data.find(b"{'descr'") + 1
            data[j:j + 1] = b"(" if ext == ".npz" else data[j:j + 1]
        elif how == 41:
            # ... and its central directory's "version needed to extract" 21.9
            # (NotImplementedError)
            k = data.find(b"PK\x01\x02")
            if ext == ".npz":
                data[k + 6:k + 8] = (219).to_bytes(2, "little")
        elif how == 0:
            j = rng.randrange(len(data))
            data[j] ^= 1 << rng.randrange(8)
        elif how == 1:
            for _ in range(rng.randint(2, 50)):
                data[rng.randrange(len(data))] = rng.randrange(256)
        elif how == 2:
            data = data[:rng.randrange(len(data))]
        else:
            j = rng.randrange(len(data))
            data[j:j] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 20)))
        path = tmp_path / f"damaged{i}{ext}"
        path.write_bytes(bytes(data))
        code = main(["telemetry", str(path), "--json"])
        cap = capsys.readouterr()
        assert code in (0, 2), (i, how, code, cap.err[-500:])
        if code == 2:
            err = cap.err.strip()
            assert len(err.splitlines()) == 1 and str(path) in err, err
        else:
            json.loads(cap.out)
        codes.add(code)
    # the fuzz reached the refusal where a format has one for damage (a zip's checksums;
    # an .hst is read up to its last intact chunk, a .csv's numbers are read as numbers)
    assert ext != ".npz" or 2 in codes, codes


def test_a_runs_npz_keeps_its_losses_and_its_description(tmp_path, capsys):
    """A run's ``--telemetry FILE.npz`` keeps the loop's events (before, the export from
    memory wrote the columns only: "lost 0, recovered 0" of a run that lost its device
    and recovered), and the run's own description first (its units, delay and rate)."""
    from hapsim.commands.telemetry import described, read
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    npz = str(tmp_path / "run.npz")
    rep = run_scene(load_scene(WALL), transport="sim", faults="drop=0.01,reset@700",
                    fault_seed=3, duration=1.5, telemetry=npz, handle_signals=False)
    assert rep["exit_code"] == 0 and rep["loop"]["lost"] >= 1
    code, s = tel_json(capsys, npz)
    assert code == 0
    assert s["events"]["lost"] == rep["loop"]["lost"]
    assert s["events"]["recovered"] == rep["loop"]["recovered"]
    assert "run" not in s["events"]             # the description is no loop event
    said = described(read(npz)[1])
    assert said["delay"] == 1.0 and said["rate_hz"] == 1000.0
    assert said["units"]["position"] == "m" and s["units"]["force"] == "N"


@pytest.mark.parametrize("ext", [".hst", ".npz"])
def test_a_joints_telemetry_is_summarised_in_its_units(tmp_path, capsys, ext):
    """The Haply joint's run (``configs/haply.yaml``, its ``device.protocol`` a rotary
    axis) writes its units in its telemetry, and ``hapsim telemetry`` says its position
    in radians and its force in newton metres, in the text, the JSON and the chart's
    axes; before, "position [m]" and "force [N]" of a joint turning 0.2 rad."""
    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    path = str(tmp_path / f"joint{ext}")
    rep = run_scene(load_scene(os.path.join(ROOT, "configs", "haply.yaml")),
                    transport="sim", duration=0.3, telemetry=path, handle_signals=False)
    assert rep["exit_code"] == 0
    assert main(["telemetry", path]) == 0
    text = capsys.readouterr().out
    assert "position [rad]: " in text and "force [N m]: " in text, text
    assert "[m]" not in text and "[N]" not in text
    code, s = tel_json(capsys, path)
    assert s["units"]["position"] == "rad" and s["units"]["force"] == "N m"
    # the same rows, whatever the label: the joint started at the scene's x0 (its first
    # reading, the start itself: exact)
    assert s["position_m"]["max"] == 0.2
    pytest.importorskip("matplotlib")
    from hapsim.commands.telemetry import described, felt_energy, read
    from hapsim.plots.telemetry import plot_telemetry
    cols, info = read(path)
    fig = plot_telemetry(cols, felt_energy(cols["position"], cols["force"], cols["flags"], 1),
                         info["events"], units=described(info)["units"])
    labels = [ax.get_ylabel() for ax in fig.axes]
    assert "position [mrad]" in labels and "force [N m]" in labels, labels


def test_the_felt_energy_takes_the_delay_the_run_stated(tmp_path, capsys):
    """Without ``--delay``, the felt energy is summed with the device's delay the run
    wrote in its file (2 here), not 1; ``--delay`` still overrides it; a ``.csv``
    (columns only) keeps the default 1."""
    import dataclasses

    from hapsim.pipeline.runner import run_scene
    from hapsim.scene import load_scene
    scene = load_scene(os.path.join(ROOT, "configs", "first_wall.yaml"))  # (stable at 2)
    scene = dataclasses.replace(scene, device=dataclasses.replace(scene.device, delay=2.0))
    hst = str(tmp_path / "d2.hst")
    rep = run_scene(scene, transport="sim", duration=0.3, telemetry=hst,
                    handle_signals=False)
    assert rep["exit_code"] == 0
    assert tel_json(capsys, hst)[1]["felt_energy_j"]["delay"] == 2
    assert tel_json(capsys, hst, "--delay", "1")[1]["felt_energy_j"]["delay"] == 1
    csv = str(tmp_path / "d2.csv")
    assert main(["telemetry", hst, "--out", csv]) == 0
    capsys.readouterr()
    assert tel_json(capsys, csv)[1]["felt_energy_j"]["delay"] == 1
