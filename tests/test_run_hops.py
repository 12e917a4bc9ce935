"""``hapsim run SCENE`` reaches the host loop in at most 4 file hops (issue 30, "What must
be shown"): the call stack, traced with ``sys.setprofile`` at the loop's first call, read
as the sequence of package files it passes through (a hop: the next frame in another
file). Measured on main 2026-11-24: cli.py -> commands/run.py -> api/running.py ->
pipeline/runner.py -> host/loop.py (``HostLoop.run``), 4 hops; before the house's split
it was 9 (cli -> commands/run -> api -> daemon/runner -> fastloop -> loop -> fastloop ->
loop -> fastloop)."""

from __future__ import annotations

import os
import sys
import threading

from inproc import hapsim_main
from test_mock_persistent import ROOT, WALL

#: The issue's bound on the file hops from the command line to the loop.
MAX_HOPS = 4


def _stack_files(frame) -> list:
    """The package files of ``frame``'s stack, outermost first, consecutive repeats
    merged."""
    files = []
    while frame is not None:
        fn = frame.f_code.co_filename
        if os.sep + "hapsim" + os.sep in fn:
            files.append(fn.split(os.sep + "hapsim" + os.sep, 1)[1])
        frame = frame.f_back
    out = []
    for f in reversed(files):
        if not out or out[-1] != f:
            out.append(f)
    return out


def test_run_reaches_the_host_loop_in_four_file_hops():
    seen = []

    def prof(frame, event, arg):
        code = frame.f_code
        if (event == "call" and not seen and code.co_name == "run"
                and code.co_filename.endswith(os.path.join("host", "loop.py"))):
            seen.append(_stack_files(frame))
    sys.setprofile(prof)
    threading.setprofile(prof)
    try:
        code, out, err = hapsim_main(["run", WALL, "--lockstep", "--duration", "0.05"],
                                     cwd=ROOT)
    finally:
        sys.setprofile(None)
        threading.setprofile(None)
    assert code == 0, err
    assert seen, "the host loop's run was not called"
    files = seen[0]
    assert files[0] == "cli.py" and files[-1] == os.path.join("host", "loop.py"), files
    assert len(files) - 1 <= MAX_HOPS, " -> ".join(files)
