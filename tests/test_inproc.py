"""``tests/inproc.hapsim_main``: a command in the test's process gives what its child would
(exit code, stdout, stderr, the descriptors' writes included) and leaves the process as it
found it (issue 31 item 2: the tests that use it instead of ``python -m hapsim``)."""

from __future__ import annotations

import gc
import json
import os
import sys
import tempfile

import pytest

from hapsim import cli
from hapsim.analysis.loop import LoopModel
from hapsim.analysis.ths import render
from inproc import hapsim_main

LOOP = ["--mass", "0.1", "--friction", "0.5", "--rate", "1000", "--delay", "1",
        "--hold", "zoh"]


def _state() -> tuple:
    return (dict(os.environ), os.getcwd(), tempfile.tempdir, tempfile.gettempdir(),
            sys.getswitchinterval(), gc.isenabled(), sys.stdout, sys.stderr)


def test_a_command_gives_its_code_and_streams_and_the_process_is_left_as_found(tmp_path):
    """``render --K 1000 --B 2 --json`` (a stable loop) from another folder with a variable
    and TMPDIR set: exit 0, its report on stdout is the library's render of the same loop
    (the same floats, from the same function), nothing on stderr; a usage error is exit 2 with nothing on stdout.
    Afterwards the environment, folder, temporary folder, switch interval, collector and
    streams are what they were."""
    before = _state()
    code, out, err = hapsim_main(["render", *LOOP, "--K", "1000", "--B", "2", "--json"],
                                 cwd=tmp_path,
                                 env={"TMPDIR": str(tmp_path), "HAPSIM_INPROC_TEST": "1"})
    assert code == 0 and err == "", err
    want = render(LoopModel(0.1, 0.5, 1000.0, 1, "zoh"), 1000.0, 2.0)
    assert json.loads(out)["k"] == want.k and json.loads(out)["b"] == want.b
    assert _state() == before
    code, out, err = hapsim_main(["render", *LOOP, "--K", "1000", "--jsn"])
    assert code == 2 and out == "" and "(did you mean --json?)" in err, err
    assert _state() == before


def test_what_reaches_the_descriptors_is_the_commands_output_in_order(monkeypatch):
    """A write on file descriptor 1 or 2 (a C library's, a child's) is part of the
    command's stdout or stderr, in order with what it prints, as in a child's pipes; the
    command's return value is the code."""
    def command(argv, want_json, watch):
        print("printed", flush=True)
        os.write(1, b"on fd 1\n")
        print("to stderr", file=sys.stderr, flush=True)
        os.write(2, b"on fd 2\n")
        return 3
    monkeypatch.setattr(cli, "_main", command)
    assert hapsim_main(["anything"]) == (3, "printed\non fd 1\n", "to stderr\non fd 2\n")


def test_a_command_that_does_not_end_is_interrupted_and_fails(monkeypatch):
    """A hang is bounded: past ``timeout`` the command gets SIGINT (it ends as on Ctrl-C:
    exit 130 here) and the caller an AssertionError naming it."""
    import time

    def command(argv, want_json, watch):
        try:
            time.sleep(60)
        except KeyboardInterrupt:
            return 130
        return 0
    monkeypatch.setattr(cli, "_main", command)
    with pytest.raises(AssertionError, match=r"hapsim stuck did not end within 0.2 s"):
        hapsim_main(["stuck"], timeout=0.2)
