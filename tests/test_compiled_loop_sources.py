"""The compiled host loop never runs an older rule than the Python loop (issue 19).

numba keys its disk cache of a function on the modification time and size of the
function's own file (numba docs, "Cache invalidation": changes in other files are not
tracked). ``hapsim/daemon/fastloop.py`` compiles in the late-tick rule
(``hapsim/kernels/ticks.py``), the I/O primitives, the engine kernels, the telemetry flags
and the protocol's constants: it holds their SHA-256, and these tests keep it true.
"""
from __future__ import annotations

import ast
import os

import numba
import pytest

from hapsim.daemon import fastloop, fastmock, startup


def test_the_digest_in_fastloop_names_the_sources_compiled_in():
    """Fails after an edit to a module the loop compiles in, until the digest is updated
    (which edits fastloop.py, so numba's cache of the loop is invalidated)."""
    now = startup.sources_digest()
    assert fastloop.COMPILED_SOURCES_SHA256 == now, (
        f"update the digest in fastloop.py (this touches fastloop.py so numba recompiles): "
        f'COMPILED_SOURCES_SHA256 = "{now}"')
    assert fastloop.CACHE_OK


def test_the_digest_in_fastmock_names_the_sources_compiled_in():
    """The compiled mock, the same way (its functions inline the I/O primitives and the
    protocol's constants)."""
    now = startup.sources_digest(startup.loop_sources(startup.MOCK_SOURCES))
    assert fastmock.COMPILED_SOURCES_SHA256 == now, (
        f"update the digest in fastmock.py (this touches fastmock.py so numba recompiles): "
        f'COMPILED_SOURCES_SHA256 = "{now}"')
    assert fastmock.CACHE_OK


@pytest.mark.parametrize("module, sources", [(fastloop, startup.LOOP_SOURCES),
                                             (fastmock, startup.MOCK_SOURCES)])
def test_every_hapsim_module_a_compiled_module_imports_from_is_listed_or_python_only(
        module, sources):
    """The class, not one file: every module fastloop.py (fastmock.py) imports names from
    is either in its sources (numba freezes its functions and constants into the compiled
    code) or only used from Python (listed here, with why)."""
    python_only = {"hapsim.daemon.loop",      # HostLoop, LostDevice, safety_reason: Python
                   "hapsim.errors",           # DeviceError: raised and caught in Python
                   "hapsim.daemon.startup"}   # the digest itself, the stamps
    listed = {s[:-3].replace("/", ".") for s in sources}
    tree = ast.parse(open(module.__file__).read())
    mods = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.split(".")[0] in ("hapsim", "firmware_protocol"):
                # "from hapsim.kernels import cordis": the module is the imported name
                for a in node.names:
                    full = f"{node.module}.{a.name}"
                    mods.add(full if full in listed else node.module)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "firmware_protocol":
                    mods.add("firmware_protocol.codec")   # its names are the codec's
    assert mods, module.__name__
    assert mods - python_only - listed == set()
    for rel in sources:
        assert any(p.endswith(os.path.join(*rel.split("/"))) and os.path.isfile(p)
                   for p in startup.loop_sources(sources)), rel


def test_a_changed_source_makes_the_digest_and_the_freshness_change(tmp_path, monkeypatch):
    """An edit to ticks.py alone changes the digest (the loop then compiles without the
    cache) and makes the loop's stamp stale (``--loop auto`` takes the Python loop)."""
    srcs = startup.loop_sources()
    copies = []
    for p in srcs:
        q = tmp_path / str(len(copies)) / os.path.basename(p)
        q.parent.mkdir()
        q.write_bytes(open(p, "rb").read())
        copies.append(str(q))
    before = startup.sources_digest(copies)
    assert before == startup.sources_digest(srcs)
    ticks = next(c for c in copies if c.endswith("ticks.py"))
    with open(ticks, "a") as f:
        f.write("\n# a changed rule\n")
    assert startup.sources_digest(copies) != before

    # freshness: a stamp newer than fastloop.py and the kernel is still stale when
    # ticks.py is newer than it
    monkeypatch.setattr(startup, "loop_sources", lambda: copies)
    kernel_src = tmp_path / "kernel.py"
    kernel_src.write_text("")
    monkeypatch.setattr(startup, "scene_kernel", lambda scene: (str(kernel_src), "run_sd"))
    stamp = tmp_path / "stamp"
    monkeypatch.setattr(startup, "loop_stamp", lambda fn: str(stamp))
    monkeypatch.setattr(startup, "_FASTLOOP", str(kernel_src))
    for c in copies:
        os.utime(c, (1_000_000, 1_000_000))
    os.utime(kernel_src, (1_000_000, 1_000_000))
    stamp.write_text("")
    os.utime(stamp, (2_000_000, 2_000_000))
    assert startup.loop_is_fresh(None)
    os.utime(ticks, (3_000_000, 3_000_000))                  # ticks.py edited after
    assert not startup.loop_is_fresh(None)


def test_the_loop_functions_are_cached_only_under_a_matching_digest():
    """The compiled loop's functions carry ``cache=CACHE_OK``: with a stale digest numba
    compiles them afresh rather than load a loop built from older sources."""
    for mod in (fastloop, fastmock):
        fns = [v for v in vars(mod).values()
               if isinstance(v, numba.core.registry.CPUDispatcher)
               and v.py_func.__module__ == mod.__name__]
        assert fns, mod.__name__
        for fn in fns:
            assert fn.targetoptions.get("nogil") is True
            assert (fn._cache.__class__.__name__ != "NullCache") == mod.CACHE_OK, fn
