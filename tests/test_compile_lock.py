"""The suite's workers compile a numba kernel once between them (tests/conftest.py,
``_one_compiler_per_kernel``): a worker that meets a kernel another is compiling waits for
it, then loads what it saved to the disk cache instead of compiling it again."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

TESTS = str(Path(__file__).resolve().parent)

KERNEL = textwrap.dedent("""
    from numba import njit

    @njit(cache=True)
    def twice(x):
        return 2 * x + 1
""")

HOLDER = textwrap.dedent("""
    import fcntl, os, sys
    sys.path[:0] = [{tests!r}, {mod!r}]
    import conftest, kernel
    fd = os.open(conftest.compile_lock_path(kernel.twice), os.O_CREAT | os.O_RDWR)
    fcntl.lockf(fd, fcntl.LOCK_EX)             # compiling, as another worker would be
    print("held", flush=True)
    sys.stdin.readline()
    assert kernel.twice(3) == 7                # compiles and saves to the cache
    os.close(fd)
""")

WAITER = textwrap.dedent("""
    import sys
    sys.path[:0] = [{tests!r}, {mod!r}]
    import conftest
    conftest._one_compiler_per_kernel()
    import kernel
    assert kernel.twice(3) == 7
    print(sum(kernel.twice._cache_hits.values()), sum(kernel.twice._cache_misses.values()))
""")


def test_a_second_worker_waits_and_loads_what_the_first_compiled(tmp_path):
    mod = tmp_path / "mod"
    mod.mkdir()
    (mod / "kernel.py").write_text(KERNEL)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    fmt = {"tests": TESTS, "mod": str(mod)}
    holder = subprocess.Popen([sys.executable, "-c", HOLDER.format(**fmt)], env=env,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        waiter = subprocess.Popen([sys.executable, "-c", WAITER.format(**fmt)], env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(3.0)        # its imports done, it waits on the lock (or compiled: fails)
        assert waiter.poll() is None, waiter.communicate()
        holder.stdin.write("go\n")
        holder.stdin.flush()
        assert holder.wait(60) == 0
        out, err = waiter.communicate(timeout=60)
        assert waiter.returncode == 0, err[-2000:]
        hits, misses = (int(v) for v in out.split())
        assert (hits, misses) == (1, 0)       # loaded from the cache, not compiled again
    finally:
        holder.kill()
        holder.wait()


def test_a_worker_collects_after_the_first_one():
    """tests/conftest.py's ``pytest_collection``: while one worker collects (holds the
    exclusive lock), another waits, and collects once it is released. The lock is held
    three times as long as the same child takes with the lock free, so a child that did
    not wait would have ended."""
    import fcntl
    from conftest import collect_lock_path
    root = Path(TESTS).parent
    env = dict(os.environ, PYTEST_XDIST_WORKER="gw7")
    cmd = [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:xdist",
           "-p", "no:cacheprovider", "-o", "addopts=", "tests/test_inproc.py"]

    def start():
        return subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
    t0 = time.monotonic()
    free = start()
    out, _ = free.communicate(timeout=120)
    alone = time.monotonic() - t0
    assert free.returncode == 0 and "collected" in out, out
    fd = os.open(collect_lock_path(root), os.O_CREAT | os.O_RDWR, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)          # the first worker, collecting
        child = start()
        time.sleep(max(3.0, 3.0 * alone))
        assert child.poll() is None              # waiting for the first one's collection
    finally:
        os.close(fd)                             # the first one is done
    out, _ = child.communicate(timeout=120)
    assert child.returncode == 0 and "collected" in out, out
