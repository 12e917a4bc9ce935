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


def test_a_run_that_collects_no_test_fails_ci(tmp_path):
    """pytest exits 5 when it collects nothing (tests/ renamed, testpaths wrong, every
    module failing to match): .ci/run then ends with 5, never 0. The script stops at the
    first failing command (``set -e``, ``pipefail``), the test command is its last one and
    nothing masks its status (no ``|| true``, ``|| :``, ``exit 0`` or trap); and pytest,
    with this project's own [tool.pytest.ini_options], exits 5 on a tests/ with no test."""
    import sys
    import tomllib
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    executed = [ln.strip() for ln in ci if ln.strip() and not ln.lstrip().startswith("#")]
    assert "set -euo pipefail" in executed
    assert executed[-1] == readme_test_command()
    assert executed[-1].rstrip().endswith("python -m pytest -q")
    masks = [ln for ln in executed if re.search(r"\|\|\s*(true|:)\s*$|\bexit 0\b|^trap\b", ln)]
    assert not masks, masks
    ini = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "helper.py").write_text("X = 1\n")    # a module, no test in it
    opts = "\n".join(f"{k} = {v!r}" if isinstance(v, str) else f"{k} = {v}"
                     for k, v in ini.items()).replace("'", '"')
    (tmp_path / "pyproject.toml").write_text(f"[tool.pytest.ini_options]\n{opts}\n")
    res = subprocess.run([sys.executable, "-m", "pytest", "-q"],      # the README command
                         cwd=tmp_path, capture_output=True, text=True)
    assert res.returncode == 5, (res.returncode, res.stdout[-500:])


def test_every_module_that_starts_a_jack_server_shares_the_sound_worker():
    """The README command runs two pytest-xdist workers with ``--dist loadgroup``; two
    private jackd servers (dummy backend) at once on a 2-core machine drop frames, so every
    module that starts one (``jackd`` on its command line, or the ``jack_server`` fixture)
    carries ``pytestmark``'s ``xdist_group("sound")`` and they all run on one worker."""
    starts = []
    for path in sorted((ROOT / "tests").glob("test_*.py")):
        if path.name == Path(__file__).name:
            continue
        text = path.read_text()
        if re.search(r"""["']jackd["']|^def test_\w+\([^)]*\bjack_server\b""", text, re.M):
            starts.append(path.name)
            marks = re.findall(r"^pytestmark\s*=.*?(?=^\S)", text + "\nEND", re.S | re.M)
            assert marks and re.search(r"""xdist_group\(\s*["']sound["']\s*\)""", marks[-1]), \
                f"{path.name} starts a JACK server but is not in xdist_group('sound')"
    assert "test_audio_live.py" in starts and "test_osc.py" in starts, starts
