"""The rough edges of the command line (issue 21): each with its message and exit code.

- stdout closed by its reader (``| head``): no traceback, exit 141 (128 + SIGPIPE);
- an unknown option: the sub-command's usage and "did you mean", exit 2;
- Ctrl-C with ``--json``: the ``interrupted`` object on stdout, exit 130.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hapsim.cli import EXIT_BROKEN_PIPE, _did_you_mean, build_parser, main
from test_new_user import interrupted  # same directory (pytest prepend import mode)

ROOT = Path(__file__).resolve().parents[1]
WALL = str(ROOT / "configs" / "wall.yaml")
LOOP = ["--mass", "0.1", "--friction", "0.5", "--rate", "1000", "--delay", "1",
        "--hold", "zoh"]


class ClosedPipe(io.TextIOBase):
    """A stdout whose reader has gone: every write raises what a closed pipe raises."""

    def writable(self):
        return True

    def write(self, s):
        raise BrokenPipeError(32, "Broken pipe")


def journal(tmp_path) -> str:
    from hapsim.daemon.telemetry import write_journal
    n = 500
    rng = np.random.default_rng(2)
    cols = {"time": np.arange(n) * 1e-3, "position": rng.normal(size=n) * 1e-3,
            "force": rng.normal(size=n), "seq": np.arange(n, dtype=np.int64),
            "turnaround_us": rng.uniform(10, 90, n), "late": np.zeros(n, np.int8),
            "flags": np.zeros(n, np.uint8)}
    return write_journal(cols, str(tmp_path / "t.hst"))


@pytest.mark.parametrize("argv", [
    ["check", WALL, "--json"], ["check", WALL],
    ["render", *LOOP, "--K", "2000", "--B", "2"],
    ["render", *LOOP, "--K", "2000", "--B", "2", "--json"],
    ["calibrate", *LOOP, "--k", "2000", "--b", "3"],
    ["stability", *LOOP, "--B", "2"],
    ["telemetry", "JOURNAL", "--json"], ["telemetry", "JOURNAL"],
], ids=lambda a: " ".join(Path(x).name for x in a))
def test_closed_stdout_is_quiet_exit_141(argv, tmp_path, monkeypatch, capsys):
    """A reader that went away (``| head``) ends the command with 141 and nothing on
    stderr, whatever the command was printing (text, JSON, help)."""
    argv = [journal(tmp_path) if a == "JOURNAL" else a for a in argv]
    monkeypatch.setattr(sys, "stdout", ClosedPipe())
    assert main(argv) == EXIT_BROKEN_PIPE == 128 + signal.SIGPIPE
    assert capsys.readouterr().err == ""


def test_head_on_a_real_pipe_leaves_no_traceback():
    """The console entry on a real pipe whose reader has closed: no ``BrokenPipeError``,
    no "Exception ignored" from the interpreter's last flush, status 141."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r, w = os.pipe()
    os.close(r)       # the reader is gone before hapsim writes a byte
    p = subprocess.run([sys.executable, "-m", "hapsim", "render", *LOOP, "--K", "1000",
                        "--json"], stdout=w, stderr=subprocess.PIPE, text=True, env=env,
                       cwd=ROOT, timeout=120)
    os.close(w)
    assert p.stderr == "" and p.returncode == EXIT_BROKEN_PIPE, (p.returncode, p.stderr)


def test_unknown_option_names_the_subcommand_and_the_close_option(capsys):
    """``run SCENE --duraton 2``: the usage of ``hapsim run`` (not the top level) and the
    option meant; exit 2; with ``--json`` the same message in the usage error object."""
    assert main(["run", WALL, "--duraton", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: hapsim run ")
    assert err.rstrip().endswith("hapsim run: error: unrecognized arguments: --duraton 2 "
                                 "(did you mean --duration?)"), err
    assert main(["check", WALL, "--jsn"]) == 2
    assert "usage: hapsim check " in (e := capsys.readouterr().err) \
        and "(did you mean --json?)" in e
    assert main(["run", WALL, "--duraton=2", "--sed", "3", "--json"]) == 2
    got = json.loads(capsys.readouterr().out)
    assert got["exit"] == 2 and got["error"]["type"] == "usage"
    assert got["error"]["message"] == (
        "hapsim run: unrecognized arguments: --duraton=2 --sed 3 "
        "(--duraton: did you mean --duration?; --sed: did you mean --seed?)")


def test_far_from_every_option_no_guess(capsys):
    assert main(["check", WALL, "--zzzzqqq"]) == 2
    err = capsys.readouterr().err
    assert "unrecognized arguments: --zzzzqqq" in err and "did you mean" not in err


def _long_options():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sub.choices.items():
        known = sorted(o for a in p._actions for o in a.option_strings)
        for opt in known:
            if opt.startswith("--") and len(opt) >= 6:
                yield name, opt, known


def test_every_option_is_found_again_from_a_transposition():
    """For every long option of every command: the option with two inner letters swapped
    (a typo argparse's prefix matching does not absorb) is suggested back."""
    missed = []
    for name, opt, known in _long_options():
        i = len(opt) // 2
        typo = opt[:i] + opt[i + 1] + opt[i] + opt[i + 2:]
        if typo == opt:
            continue
        hint = _did_you_mean([typo], known)
        if hint != f" (did you mean {opt}?)":
            missed.append((name, opt, typo, hint))
    assert not missed


@pytest.mark.parametrize("argv", [["check", "configs/wall.yaml", "--json"],
                                  ["run", "configs/wall.yaml", "--json", "--duration", "5"]],
                         ids=["check", "run"])
def test_ctrl_c_with_json_prints_the_interrupted_object(tmp_path, argv):
    """Ctrl-C 0.1 s after the interpreter is up (hapsim still importing): stdout holds the
    ``interrupted`` object the README promises, stderr one line, exit 130."""
    code, out, err = interrupted(argv, 0.1, tmp_path)
    assert code == 130, (code, err)
    assert err.strip().splitlines()[-1].endswith("interrupted") and "Traceback" not in err
    got = json.loads(out)
    assert got == {"error": {"type": "interrupted", "message": "hapsim: interrupted",
                             "file": None, "line": None, "key": None}, "exit": 130}
