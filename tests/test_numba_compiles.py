"""tools/numba_compiles.py counts what numba compiles in every process a command starts:
a kernel compiled in the command's process and again in a child it starts (each with an
empty cache of its own) is two compilations, one of them repeated; a kernel loaded from
the disk cache is none."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

TOOL = Path(__file__).resolve().parents[1] / "tools" / "numba_compiles.py"

PROGRAM = textwrap.dedent("""
    import subprocess, sys
    from numba import njit

    @njit
    def twice(x):
        return 2 * x + 1

    @njit(cache=True)
    def kept(x):
        return x - 1

    assert twice(3) == 7
    assert twice(2.5) == 6.0          # a second signature of the same kernel
    assert kept(3) == 2               # compiled by the parent, loaded from the cache by the child
    if len(sys.argv) == 1:            # the parent: the same kernel again in a child
        subprocess.check_call([sys.executable, __file__, "child"])
""")


def test_compilations_in_every_process_are_counted(tmp_path):
    prog = tmp_path / "prog.py"
    prog.write_text(PROGRAM)
    out = tmp_path / "c.json"
    r = subprocess.run([sys.executable, str(TOOL), "--empty-cache", "--json", str(out), "--",
                        sys.executable, str(prog)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads(out.read_text())
    # twice's two signatures in the parent and in the child, kept's in the parent only
    assert s["compilations"] == 5 and s["processes"] == 2, s
    got = {(e["kernel"], e["signature"]): e["count"] for e in s["kernels"]}
    assert got == {("__main__.twice", "(int64,)"): 2, ("__main__.twice", "(float64,)"): 2,
                   ("__main__.kept", "(int64,)"): 1}, got
    assert sorted((e["kernel"], e["count"]) for e in s["repeated"]) == [
        ("__main__.twice", 2), ("__main__.twice", 2)], s["repeated"]
    assert s["cpu_s"] > 0 and "numba compiled 5 kernel signatures in 2 processes" in r.stdout
