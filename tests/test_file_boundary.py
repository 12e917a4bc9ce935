"""The file boundary a fuzz of every file option found (stop 92): an output written over a
device (as root, ``hapsim mock --report /dev/full`` made /dev/full a regular file), inputs
read from a pipe (a hang) or from /dev/zero (the memory filled), ``.partial`` files left by
a failed write, output paths found unwritable only after the work, a device file that is
no UTF-8 a traceback, and a one-column gesture read as one sample. One reader
(:func:`hapsim.outputs.read_input`) and one writer (:func:`hapsim.outputs.atomic_write`)
now stand at the boundary; each option is tested through them."""

from __future__ import annotations

import os
import stat
import threading
from pathlib import Path

import pytest

from hapsim.errors import ConfigError
from hapsim.outputs import atomic_write, read_input, write_json

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
WALL = str(CONFIGS / "wall.yaml")


def _returns_within(fn, seconds=20.0):
    """``fn()``'s exception (or None), asserting it returned within ``seconds`` (a read of
    a pipe never returns: the thread is left behind, the test fails)."""
    out = {}

    def call():
        try:
            fn()
        except BaseException as exc:       # noqa: BLE001 - handed to the test
            out["exc"] = exc
        out["done"] = True
    t = threading.Thread(target=call, daemon=True)
    t.start()
    t.join(seconds)
    assert out.get("done"), "still reading after 20 s"
    return out.get("exc")


def _readers(path):
    """Every reader of an input option, on ``path``."""
    import hapsim
    from hapsim.device_file import load_device
    from hapsim.device_model import load_profile
    return {"scene": lambda: hapsim.load_scene(path),
            "device file": lambda: load_device(path),
            "gesture": lambda: load_profile(path, "position", "m", key="--gesture"),
            "bytes": lambda: read_input(path)}


@pytest.mark.parametrize("kind", ["fifo", "folder", "/dev/zero"])
def test_no_input_option_reads_what_is_no_regular_file(tmp_path, kind):
    """A pipe, a folder or /dev/zero given as any input file: a ConfigError naming the
    file, at once (before: a pipe hung the command; /dev/zero was read until the memory
    ran out)."""
    if kind == "fifo":
        path = str(tmp_path / "in.yaml")
        os.mkfifo(path)
    elif kind == "folder":
        path = str(tmp_path / "in.yaml")
        os.mkdir(path)
    else:
        path = "/dev/zero"
        if not os.path.exists(path):
            pytest.skip("no /dev/zero on this machine")
    for name, read in _readers(path).items():
        exc = _returns_within(read)
        assert isinstance(exc, ConfigError), (name, exc)
        assert "regular file" in str(exc) and path in str(exc), (name, str(exc))


def test_an_input_over_the_size_bound_is_refused_before_it_is_read(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_bytes(b"#" * 4096)
    with pytest.raises(ConfigError, match="more than"):
        read_input(str(path), limit=1024)
    assert read_input(str(path), limit=4096) == b"#" * 4096


def test_a_device_file_that_is_no_utf8_is_refused_as_a_scene_is(tmp_path):
    """A device file with a Latin-1 byte: refused with the scene reader's message
    (before: a UnicodeDecodeError traceback)."""
    from hapsim.device_file import load_device
    path = tmp_path / "dev.yaml"
    path.write_bytes(b"device: {mass: 0.1}  # r\xe9glage\n")
    with pytest.raises(ConfigError) as info:
        load_device(str(path))
    assert "UTF-8" in str(info.value)


def test_a_one_column_gesture_is_refused_not_read_as_one_sample(tmp_path):
    from hapsim.device_model import load_profile
    path = tmp_path / "g.csv"
    path.write_text("0.0\n0.001\n0.002\n0.003\n")
    with pytest.raises(ConfigError, match="1 column"):
        load_profile(str(path), "position", "m", key="--gesture")
    path.write_text("time,position\n0.0,0.0\n0.001,0.001\n")
    t, x = load_profile(str(path), "position", "m", key="--gesture")
    assert t.tolist() == [0.0, 0.001] and x.tolist() == [0.0, 0.001]


def test_the_writer_never_replaces_a_device_or_a_pipe_and_leaves_nothing_on_failure(
        tmp_path):
    """:func:`atomic_write` (every output file goes through it): a pipe at the path is
    refused and stays a pipe (a device likewise: /dev/full was replaced by a file, as
    root); a write that fails leaves the old file whole and no ``.partial``; one that
    succeeds replaces it whole."""
    fifo = str(tmp_path / "out.json")
    os.mkfifo(fifo)
    for write in (lambda: write_json(fifo, {"a": 1}),
                  lambda: atomic_write(fifo, "w").__enter__()):
        with pytest.raises(ConfigError, match="not a regular file"):
            write()
        assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    path = tmp_path / "out.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(str(path), "w") as fh:
            fh.write("half")
            raise RuntimeError("disk full")
    assert path.read_text() == "old" and not Path(f"{path}.partial").exists()
    with atomic_write(str(path), "w") as fh:
        fh.write("new")
    assert path.read_text() == "new" and not Path(f"{path}.partial").exists()


#: Each command's output option, and the ways its path cannot be written.
OUTPUTS = [
    (["mock", "--once", "--report", "{out}"], "--report", ".json"),
    (["play", WALL, "--sound", "none", "--lockstep", "--duration", "0.05", "--journal",
      "{out}"], "--journal", ".json"),
    (["play", WALL, "--sound", "none", "--lockstep", "--duration", "0.05", "--telemetry",
      "{out}"], "--telemetry", ".npz"),
    (["simulate", str(CONFIGS / "audio_string.yaml"), "--steps", "10", "--audio", "{out}"],
     "--audio", ".wav"),
    (["simulate", WALL, "--steps", "10", "--out", "{out}"], "--out", ".npz"),
    (["identify", "--lockstep", "--duration", "0.5", "--out", "{out}"], "--out", ".yaml")]


@pytest.mark.parametrize("argv, flag, ext, where", [
    (*o, w) for o in OUTPUTS for w in ("fifo", "missing folder")] + [
    # (a report's and a journal's name is free: JSON whatever its extension)
    (*o, "wrong extension") for o in OUTPUTS if o[1] not in ("--report", "--journal")])
def test_every_output_option_is_checked_before_the_work(tmp_path, capsys, argv, flag, ext,
                                                         where):
    """Each command's output file that cannot be written (a pipe, a missing folder) is
    refused by its flag before the work, exit 2, and a pipe stays a pipe (before: the
    mock's report replaced it at the exit, play and simulate --audio failed after the
    work with a traceback)."""
    from hapsim.cli import main
    out = {"fifo": str(tmp_path / ("o" + ext)), "missing folder": str(
        tmp_path / "no" / ("o" + ext)), "wrong extension": str(tmp_path / "o.txt")}[where]
    if where == "fifo":
        os.mkfifo(out)
    code = main([a.replace("{out}", out) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and f"{flag}: " in err, (code, err)
    if where == "fifo":
        assert stat.S_ISFIFO(os.stat(out).st_mode)
    assert not list(tmp_path.rglob("*.partial"))


def test_a_damaged_or_reordered_journal_is_never_summarised_as_intact(tmp_path, capsys):
    """A run's journal, damaged the ways a disk or a copy damages a file: a flipped byte
    in a middle chunk (before: summarised as a tail cut by a kill, the intact chunks
    after it silently dropped), a chunk written twice, two chunks swapped (before:
    "intact", the energy counted twice), an empty file (before: "0 chunks, intact").
    ``hapsim telemetry --json``'s ``integrity`` says what happened to each; the file as
    written stays intact."""
    import json

    import hapsim
    from hapsim.cli import main
    from hapsim.host.telemetry import CHUNK_MAGIC
    hst = tmp_path / "run.hst"
    hapsim.run(WALL, lockstep=True, duration=1.0, telemetry=str(hst), handle_signals=False,
               telemetry_interval=1e-4)            # (a chunk every few samples)
    data = hst.read_bytes()
    starts = [i for i in range(len(data)) if data.startswith(CHUNK_MAGIC, i)]
    assert len(starts) >= 6
    chunk = [data[a:b] for a, b in zip(starts, starts[1:] + [len(data)])]

    def integrity(raw):
        path = tmp_path / "x.hst"
        path.write_bytes(raw)
        assert main(["telemetry", str(path), "--json"]) == 0
        return json.loads(capsys.readouterr().out)["integrity"]
    whole = integrity(data)
    assert whole["intact"] and whole["damaged_after"] == 0
    mid = len(chunk) // 2
    flipped = bytearray(data)
    flipped[starts[mid] + len(chunk[mid]) // 2] ^= 0xFF
    ig = integrity(bytes(flipped))
    assert not ig["intact"] and ig["damaged_after"] == len(chunk) - mid - 1, ig
    ig = integrity(b"".join(chunk[:mid + 1] + [chunk[mid]] + chunk[mid + 1:]))
    assert not ig["intact"] and ig["time_back"] >= 1, ig
    ig = integrity(b"".join(chunk[:mid] + [chunk[mid + 1], chunk[mid]] + chunk[mid + 2:]))
    assert not ig["intact"] and ig["time_back"] >= 1, ig
    ig = integrity(b"")
    assert not ig["intact"] and ig["empty"], ig


def test_a_telemetry_file_of_the_wrong_shape_is_refused_or_read_safely(tmp_path, capsys):
    """``hapsim telemetry`` on an ``.npz`` whose events are no list of objects, a CSV under
    an ``.npz`` name, a pipe, and a journal whose run description is damaged (half its
    units, a word for its delay): exit 2 with one line for the first three (before: an
    AttributeError; numpy's advice to load the file unsafely; "no such file"), the
    description ignored for the last, its SI units and delay 1 taken (before: a KeyError)."""
    import json

    import numpy as np

    import hapsim
    from hapsim.cli import main
    from hapsim.host.telemetry import COLUMNS, load, save_columns
    npz = tmp_path / "run.npz"
    hapsim.run(WALL, lockstep=True, duration=0.3, telemetry=str(npz), handle_signals=False)
    with np.load(npz) as z:
        cols = {c: z[c] for c in z.files if c in COLUMNS}
    bad_events = tmp_path / "events.npz"
    np.savez(bad_events, **cols, events=np.array(json.dumps({"a": 1})))
    csv_npz = tmp_path / "csv.npz"
    csv_npz.write_text("time,position,force,seq\n0,0,0,0\n")
    fifo = tmp_path / "pipe.hst"
    os.mkfifo(fifo)
    for path, says in ((bad_events, "events are not a list"), (csv_npz, "not an .npz"),
                       (fifo, "not a regular file")):
        assert main(["telemetry", str(path)]) == 2, path
        err = capsys.readouterr().err
        assert says in err and "pickle" not in err and len(err.strip().splitlines()) == 1, err
    hst = tmp_path / "desc.hst"
    save_columns(load(str(npz)), str(hst), events=[
        {"event": "run", "units": {"position": "rad"}, "delay": "x", "rate_hz": -1}])
    assert main(["telemetry", str(hst), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["units"]["position"] == "m" and s["felt_energy_j"]["delay"] == 1


@pytest.mark.parametrize("column, value", [("flags", 1.5), ("seq", "x"), ("position", 1j),
                                           ("status", "ok")])
def test_a_telemetry_column_of_the_wrong_kind_is_refused(tmp_path, capsys, column, value):
    """An ``.npz`` whose column is not the numbers its kind needs (whole numbers for
    ``seq``, ``flags``, ``status``; real ones for ``position``): exit 2 naming the column
    (before: a TypeError in the summary)."""
    import numpy as np

    import hapsim
    from hapsim.cli import main
    npz = tmp_path / "run.npz"
    hapsim.run(WALL, lockstep=True, duration=0.2, telemetry=str(npz), handle_signals=False)
    with np.load(npz) as z:
        cols = {c: z[c] for c in z.files}
    cols[column] = np.full(cols["seq"].shape, value)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **cols)
    assert main(["telemetry", str(bad)]) == 2
    assert f"column {column!r}" in capsys.readouterr().err


@pytest.mark.parametrize("out, fail_at, code", [("t.hst", 1, 0), ("t.npz", 1, 0),
                                                ("t.npz", None, 0), ("t.hst", 0, 2)])
def test_a_full_disk_under_the_telemetry_is_said_not_a_traceback(tmp_path, capsys,
                                                                 monkeypatch, out, fail_at,
                                                                 code):
    """``hapsim run --telemetry`` whose journal's chunk ``fail_at`` (and every later one)
    fails as on a full disk, or whose ``.npz`` export fails (``fail_at`` None): the run
    ends with its report, which says the journal writer stopped and, for an ``.npz``,
    that the journal has the rows; a journal that cannot take its first chunk is refused
    by its flag, exit 2 (before: OSError tracebacks from the writer's last flush and from
    the export)."""
    import errno

    from hapsim.cli import main
    from hapsim.host import telemetry as tm
    from hapsim.pipeline import runner

    real = tm.ChunkWriter._chunk

    def chunk(self, *a):
        if fail_at is not None and self.chunks >= fail_at:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, *a)
    monkeypatch.setattr(tm.ChunkWriter, "_chunk", chunk)
    if fail_at is None:
        def full(*a, **k):
            raise OSError(errno.ENOSPC, "No space left on device")
        monkeypatch.setattr(runner, "save_columns", full)
    got = main(["run", WALL, "--lockstep", "--duration", "1", "--telemetry",
                str(tmp_path / out)])
    cap = capsys.readouterr()
    assert got == code and "Traceback" not in cap.err, (got, cap.err[-2000:])
    if code == 0:
        assert "journal writer stopped" in cap.out, cap.out[-2000:]
        if fail_at is None:     # (with the journal cut, the .npz is written from memory)
            assert f"{tmp_path / out}.hst has the rows" in cap.out, cap.out[-2000:]
    else:
        assert "--telemetry: cannot write" in cap.err, cap.err


@pytest.mark.parametrize("ext", [".npz", ".hst"])
def test_a_torn_journal_converted_stays_not_intact(tmp_path, capsys, ext):
    """``hapsim telemetry cut.hst --out X`` of a journal cut by a kill: X's own summary
    says it was converted from a file that was not intact, with the figures (before: an
    ``.npz`` or ``.hst`` made from it said "intact")."""
    import json

    import hapsim
    from hapsim.cli import main
    hst = tmp_path / "run.hst"
    hapsim.run(WALL, lockstep=True, duration=1.0, telemetry=str(hst), handle_signals=False,
               telemetry_interval=1e-4)
    data = hst.read_bytes()
    cut = tmp_path / "cut.hst"
    cut.write_bytes(data[:len(data) * 2 // 3])
    out = tmp_path / f"out{ext}"
    assert main(["telemetry", str(cut), "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["telemetry", str(out), "--json"]) == 0
    ig = json.loads(capsys.readouterr().out)["integrity"]
    assert not ig["intact"] and ig["converted_from"]["torn_bytes"] > 0, ig
    assert main(["telemetry", str(out)]) == 0
    assert "NOT INTACT: converted from a file that was not" in capsys.readouterr().out
