"""The BLAS pools of a hapsim command (hapsim.blas.size_pools): one thread, so no OpenBLAS
worker thread exists to spin beside another command's or beside the real-time loop; a
user's own pool size is kept. Each case runs in a fresh interpreter (a pool is sized when
its library loads). Speed is measured by tools/bench_pools.py, not here."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

PROBE = """
import json, os, sys
first = sys.argv[1]
if first == "numpy":
    import numpy
from hapsim.blas import size_pools
how = size_pools()
import numpy, scipy.linalg
numpy.linalg.svd(numpy.random.default_rng(0).standard_normal((200, 200)))
from threadpoolctl import threadpool_info
blas = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
print(json.dumps({"how": how, "blas": blas, "threads": len(os.listdir("/proc/self/task"))}))
"""


def probe(first: str, env_extra: dict) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                        "BLIS_NUM_THREADS")}
    env.update(env_extra, PYTHONPATH=ROOT)
    r = subprocess.run([sys.executable, "-c", PROBE, first], capture_output=True, text=True,
                       env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.mark.parametrize("first, how", [("hapsim", "environment"), ("numpy", "runtime")])
def test_a_command_runs_blas_on_one_thread_with_no_pool_threads(first, how):
    """Sized before numpy loads: OpenBLAS starts no worker (the process has one thread
    after an SVD); numpy loaded first: the loaded pools are limited to one thread."""
    out = probe(first, {})
    assert out["how"] == how
    assert out["blas"] and all(n == 1 for n in out["blas"]), out
    if how == "environment":
        assert out["threads"] == 1, out


def test_a_pool_size_the_user_set_is_kept():
    out = probe("hapsim", {"OPENBLAS_NUM_THREADS": "2"})
    assert out["how"] == "user" and all(n == 2 for n in out["blas"]), out


def test_the_command_line_sizes_the_pools(monkeypatch, capsys):
    """``hapsim COMMAND`` sizes them before it imports the command (hapsim.cli)."""
    from hapsim.cli import main
    for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
              "BLIS_NUM_THREADS"):
        monkeypatch.setenv(k, "")       # unset for size_pools; restored afterwards
    assert main(["check", os.path.join(ROOT, "configs", "wall.yaml"), "--json"]) == 0
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
