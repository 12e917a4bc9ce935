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


#: The second pass of the numerical tests, on another BLAS kernel and numba target, beside
#: the first at the lowest priority (without pytest's cache, which the first writes).
NUMERICAL_PASS = 'nice -n 19 python -m pytest -q -m "numerical or soak" -p no:cacheprovider'


def _executed(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def test_ci_runs_the_readme_test_command_verbatim():
    cmd = readme_test_command()
    assert "pytest" in cmd and ".[test]" in cmd
    executed = _executed((ROOT / ".ci" / "run").read_text())
    assert executed.count(cmd) == 1, f"{cmd!r} not a line of .ci/run"
    # and nothing else in .ci/run runs tests or installs the package another way: the one
    # other pytest line is the numerical tests' second pass, which waits for the README's
    # pytest to start (tests/conftest.py creates the file) before it runs
    others = [ln.strip() for ln in executed if ln != cmd]
    runs = [ln for ln in others if re.search(r"\bpython3?\s+-m\s+(pytest|pip|venv)\b|"
                                             r"^\s*(pytest|pip3?)\b", ln)]
    assert runs == [NUMERICAL_PASS], runs
    wait = 'while [ ! -e "$HAPSIM_CI_FIRST_PASS_STARTED" ]; do'
    assert others.index(wait) < others.index(NUMERICAL_PASS)
    assert "HAPSIM_CI_FIRST_PASS_STARTED" in (ROOT / "tests" / "conftest.py").read_text()


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
def test_ci_script_parses():
    res = subprocess.run(["bash", "-n", str(ROOT / ".ci" / "run")], capture_output=True,
                         text=True)
    assert res.returncode == 0, res.stderr


_STUB_PYTHON = r"""#!/usr/bin/env bash
# stands for python/python3 in a copy of .ci/run: logs each call, exits as told
echo "$* | ${OPENBLAS_CORETYPE:-} ${NUMBA_CPU_NAME:-} ${NUMBA_CACHE_DIR:-}" >> "$CI_LOG"
case "$*" in
  "-m venv .venv") mkdir -p .venv/bin && echo ': activated' > .venv/bin/activate; exit "$VENV_RC";;
  -m\ pip\ *) exit "$PIP_RC";;
  "-m pytest -q")
    # as tests/conftest.py does at the session's start; then wait (10 s at most) for the
    # second pass to begin beside it
    touch "$HAPSIM_CI_FIRST_PASS_STARTED"
    for i in $(seq 100); do [ -e "$CI_LOG.second" ] && echo beside >> "$CI_LOG" && break; sleep 0.1; done
    exit "$PYTEST_RC";;
  "-m pytest -q -m numerical or soak -p no:cacheprovider") touch "$CI_LOG.second"; exit "$NUMERICAL_RC";;
esac
echo "unexpected call: $*" >&2; exit 99
"""


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
@pytest.mark.parametrize("venv, pip, readme, numerical, status, said", [
    (0, 0, 0, 0, 0, None),
    (0, 0, 5, 0, 5, "collected no test (exit 5) in the README's test command"),
    (0, 0, 1, 0, 1, "exit 1 in the README's test command"),
    (0, 0, 0, 5, 5, "collected no test (exit 5) in the second numerical pass"),
    (0, 0, 0, 1, 1, "exit 1 in the second numerical pass"),
    (0, 1, 0, 0, 1, "exit 1 in the README's test command"),
    (1, 0, 0, 0, 1, "exit 1 in the README's test command"),
])
def test_ci_fails_loudly_on_any_failing_step(tmp_path, venv, pip, readme, numerical, status,
                                             said):
    """The real .ci/run, with python, python3 and the Debian parts' commands stood in by
    stubs that exit as told: CI ends with the status of the first failing step, says which
    and (exit 5) that nothing was collected, in the README's command and in the second
    pass alike; a venv or pip failure, which ``set -e`` does not stop inside an ``&&``
    list, fails it too; the second pass starts once the first pass's pytest has (beside
    it, at nice 19), with the other BLAS kernel, numba target and a cache of its own, and
    counts only after a green first one."""
    res, log, repo = _stubbed_ci(tmp_path, venv, pip, readme, numerical)
    assert res.returncode == status, (res.returncode, res.stdout, res.stderr)
    if said is None:
        assert "FAILED" not in res.stderr, res.stderr
    else:
        assert f"ci: FAILED" in res.stderr and said in res.stderr, res.stderr
    calls = log.read_text().splitlines()
    second = [c for c in calls if c.startswith("-m pytest -q -m numerical or soak")]
    if venv or pip:
        assert not second, calls            # no pytest started: nothing to run beside
    elif not readme:
        # (an absolute cache: a child started in another directory finds the same one)
        assert second == ["-m pytest -q -m numerical or soak -p no:cacheprovider | Sandybridge "
                          f"generic {repo}/.venv/numba-generic"], calls
        first = [c for c in calls if c.startswith("-m pytest -q |")]
        assert first == ["-m pytest -q |   "], calls      # the host's own kernels first
        assert "beside" in calls, calls     # it ran while the first pass had not ended
    assert not list(tmp_path.glob("tmp.*")), "the run's files are left"
    # whatever the outcome, the second pass's process group is gone with CI
    _nothing_left(tmp_path, 2.0)


def _nothing_left(tmp_path, within: float) -> None:
    """No process names ``tmp_path`` (the run's files, under TMPDIR, are on the second
    pass's command line) ``within`` seconds after CI ended."""
    import time
    end = time.monotonic() + within
    while True:
        ps = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout
        if str(tmp_path) not in ps or time.monotonic() > end:
            break
        time.sleep(0.05)
    assert str(tmp_path) not in ps, ps


def _stubbed_ci(tmp_path, venv, pip, readme, numerical, extra=None, timeout=60):
    """The real .ci/run in a clone under ``tmp_path`` with python, python3 and the Debian
    parts' commands stubbed (exit statuses as given; ``extra``: more stubs, name ->
    script); ``(completed process, calls log, clone)``; ``timeout`` [s] for the run."""
    repo, stubs = tmp_path / "clone", tmp_path / "stubs"
    (repo / ".ci").mkdir(parents=True)
    stubs.mkdir()
    shutil.copy(ROOT / ".ci" / "run", repo / ".ci" / "run")
    for name in ("python", "python3"):
        (stubs / name).write_text(_STUB_PYTHON)
    for name in ("faust", "avr-gcc", "simavr", "jackd", "pd", "dpkg", "apt-get"):
        (stubs / name).write_text("#!/usr/bin/env bash\nexit 0\n")
    for name, script in (extra or {}).items():
        (stubs / name).write_text(script)
    for f in stubs.iterdir():
        f.chmod(0o755)
    log = tmp_path / "calls.log"
    env = {"PATH": f"{stubs}:/usr/bin:/bin", "HOME": str(tmp_path), "CI_LOG": str(log),
           "VENV_RC": str(venv), "PIP_RC": str(pip), "PYTEST_RC": str(readme),
           "NUMERICAL_RC": str(numerical), "TMPDIR": str(tmp_path)}
    res = subprocess.run(["bash", str(repo / ".ci" / "run")], env=env, capture_output=True,
                         text=True, timeout=timeout)
    return res, log, repo


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
def test_a_second_pass_the_trap_missed_ends_with_ci(tmp_path):
    """The venv fails at once and CI's trap misses the second pass's group (here its PID
    file read back as a group that does not exist, as a trap running while that group is
    still being made may): the pass, waiting for a first pass that never starts, ends
    with CI instead of holding CI's output open for ever. (This stop's fresh-clone CI: a
    stubbed run whose venv failed printed its failure and exited, and its output stayed
    open past 60 s, beside the suite's load.)"""
    cat = (f"#!/usr/bin/env bash\ncase \"$1\" in */second.pid) echo 999999999;; "
           f"*) exec {shutil.which('cat')} \"$@\";; esac\n")
    res, _, _ = _stubbed_ci(tmp_path, 1, 0, 0, 0, {"cat": cat}, timeout=20)
    assert res.returncode == 1 and "ci: FAILED" in res.stderr, (res.returncode, res.stderr)
    _nothing_left(tmp_path, 10.0)
