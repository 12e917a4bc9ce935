"""``.ci/run`` runs exactly the README's test command, so the two cannot drift apart."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def readme_test_command() -> str:
    """The one-line ``sh`` block that follows "Install and run the tests" in README.md."""
    text = (ROOT / "README.md").read_text()
    start = text.index("Install and run the tests")
    block = re.search(r"```sh\n(.*?)```", text[start:], re.S)
    lines = [ln for ln in block.group(1).splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    return lines[0]


def test_ci_runs_the_readme_test_command_verbatim():
    cmd = readme_test_command()
    assert "pytest" in cmd and ".[test]" in cmd
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    executed = [ln for ln in ci if ln.strip() and not ln.lstrip().startswith("#")]
    assert executed.count(cmd) == 1, f"{cmd!r} not a line of .ci/run"
    # and nothing else in .ci/run runs tests or installs the package another way
    others = [ln for ln in executed if ln != cmd]
    assert not [ln for ln in others if re.search(r"pytest|pip install|venv", ln)], others


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
def test_ci_script_parses():
    res = subprocess.run(["bash", "-n", str(ROOT / ".ci" / "run")], capture_output=True,
                         text=True)
    assert res.returncode == 0, res.stderr
