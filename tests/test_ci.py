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
NUMERICAL_PASS = "nice -n 19 python -m pytest -q -m numerical -p no:cacheprovider"


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
    wait = 'while [ ! -e "$HAPSIM_CI_FIRST_PASS_STARTED" ]; do sleep 0.5; done'
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
  "-m pytest -q -m numerical -p no:cacheprovider") touch "$CI_LOG.second"; exit "$NUMERICAL_RC";;
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
    repo, stubs = tmp_path / "clone", tmp_path / "stubs"
    (repo / ".ci").mkdir(parents=True)
    stubs.mkdir()
    shutil.copy(ROOT / ".ci" / "run", repo / ".ci" / "run")
    for name in ("python", "python3"):
        (stubs / name).write_text(_STUB_PYTHON)
    for name in ("faust", "avr-gcc", "simavr", "jackd", "pd", "dpkg", "apt-get"):
        (stubs / name).write_text("#!/usr/bin/env bash\nexit 0\n")
    for f in stubs.iterdir():
        f.chmod(0o755)
    log = tmp_path / "calls.log"
    env = {"PATH": f"{stubs}:/usr/bin:/bin", "HOME": str(tmp_path), "CI_LOG": str(log),
           "VENV_RC": str(venv), "PIP_RC": str(pip), "PYTEST_RC": str(readme),
           "NUMERICAL_RC": str(numerical), "TMPDIR": str(tmp_path)}
    res = subprocess.run(["bash", str(repo / ".ci" / "run")], env=env, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == status, (res.returncode, res.stdout, res.stderr)
    if said is None:
        assert "FAILED" not in res.stderr, res.stderr
    else:
        assert f"ci: FAILED" in res.stderr and said in res.stderr, res.stderr
    calls = log.read_text().splitlines()
    second = [c for c in calls if c.startswith("-m pytest -q -m numerical")]
    if venv or pip:
        assert not second, calls            # no pytest started: nothing to run beside
    elif not readme:
        # (an absolute cache: a child started in another directory finds the same one)
        assert second == ["-m pytest -q -m numerical -p no:cacheprovider | Sandybridge "
                          f"generic {repo}/.venv/numba-generic"], calls
        first = [c for c in calls if c.startswith("-m pytest -q |")]
        assert first == ["-m pytest -q |   "], calls      # the host's own kernels first
        assert "beside" in calls, calls     # it ran while the first pass had not ended
    assert not list(tmp_path.glob("tmp.*")), "the run's files are left"
    # whatever the outcome, the second pass's process group is gone with CI (its command
    # line names the run's files, under TMPDIR)
    import time
    for _ in range(40):
        ps = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout
        if str(tmp_path) not in ps:
            break
        time.sleep(0.05)
    assert str(tmp_path) not in ps, ps


def test_a_run_that_collects_no_test_exits_5(tmp_path):
    """pytest exits 5 when it collects nothing (tests/ renamed, testpaths wrong, every
    module failing to match) or deselects everything (no test carries ``-m numerical``'s
    marker); .ci/run turns that into a failure (test above). Checked here with this
    project's own [tool.pytest.ini_options]; and the marker is carried in tests/."""
    import sys
    import tomllib
    ini = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    assert any(m.startswith("numerical:") for m in ini["markers"])
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "helper.py").write_text("X = 1\n")    # a module, no test in it
    opts = "\n".join(f"{k} = {v!r}" if isinstance(v, str) else f"{k} = {v}"
                     for k, v in ini.items()).replace("'", '"')
    (tmp_path / "pyproject.toml").write_text(f"[tool.pytest.ini_options]\n{opts}\n")
    # the README command; without hypothesis's pytest plugin, which imports hypothesis in
    # every pytest process whether a test uses it or not (measured 2.1 CPU-s each: 6.4 of
    # this run's 8.4 with the two workers) and has no say in the exit status
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:hypothesispytest"],
                         cwd=tmp_path, capture_output=True, text=True)
    assert res.returncode == 5, (res.returncode, res.stdout[-500:])
    (tmp_path / "tests" / "test_plain.py").write_text("def test_x():\n    pass\n")
    # (-n 0: the deselection is pytest's own, xdist's controller exits 5 alike, measured;
    # two more worker start-ups would cost ~5 s CPU)
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0", "-m", "numerical",
                          "-p", "no:hypothesispytest"],
                         cwd=tmp_path, capture_output=True, text=True)
    assert res.returncode == 5, (res.returncode, res.stdout[-500:])
    carriers = [p.name for p in (ROOT / "tests").glob("test_*.py")
                if re.search(r"pytest\.mark\.numerical\b", p.read_text())]
    assert carriers, "no test module carries the 'numerical' marker"


def test_every_module_that_starts_a_jack_server_shares_the_sound_worker():
    """The README command runs several pytest-xdist workers with ``--dist loadgroup``; two
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
