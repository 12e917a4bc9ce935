"""The compiled host loop never runs an older rule than the Python loop (issue 19).

numba keys its disk cache of a function on the modification time and size of the
function's own file (numba docs, "Cache invalidation": changes in other files are not
tracked). ``hapsim/host/fastloop_kernels.py`` (the compiled host loop's numba code,
which :mod:`hapsim.host.fastloop` drives) compiles in the late-tick rule
(``hapsim/kernels/ticks.py``), the I/O primitives, the engine kernels, the telemetry flags
and the protocol's constants: it holds their SHA-256, and these tests keep it true.
"""
from __future__ import annotations

import ast
import importlib
import importlib.util
import os

import numba
import numba.core.ccallback
import pytest

from hapsim.host import fastloop_kernels

from hapsim.emulated import fastmock

from hapsim.pipeline import startup
from hapsim.kernels import sources as sources_mod


def test_the_digest_in_fastloop_kernels_names_the_sources_compiled_in():
    """Fails after an edit to a module the loop compiles in, until the digest is updated
    (which edits fastloop_kernels.py, so numba's cache of the loop is invalidated)."""
    now = startup.sources_digest()
    assert fastloop_kernels.COMPILED_SOURCES_SHA256 == now, (
        f"update the digest in fastloop_kernels.py (this touches fastloop_kernels.py so numba "
        f'recompiles): COMPILED_SOURCES_SHA256 = "{now}"')
    assert fastloop_kernels.CACHE_OK


def test_the_digest_in_fastmock_names_the_sources_compiled_in():
    """The compiled mock, the same way (its functions inline the I/O primitives and the
    protocol's constants)."""
    now = startup.sources_digest(startup.loop_sources(startup.MOCK_SOURCES))
    assert fastmock.COMPILED_SOURCES_SHA256 == now, (
        f"update the digest in fastmock.py (this touches fastmock.py so numba recompiles): "
        f'COMPILED_SOURCES_SHA256 = "{now}"')
    assert fastmock.CACHE_OK


@pytest.mark.parametrize("module, sources", [(fastloop_kernels, startup.LOOP_SOURCES),
                                             (fastmock, startup.MOCK_SOURCES)])
def test_every_hapsim_module_a_compiled_module_imports_from_is_listed_or_python_only(
        module, sources):
    """The class, not one file: every module fastloop_kernels.py (fastmock.py) imports names from
    is either in its sources (numba freezes its functions and constants into the compiled
    code) or only used from Python (listed here, with why)."""
    python_only = {"hapsim.kernels.sources"}   # the digest itself, the stamps
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

    # freshness: a stamp newer than fastloop_kernels.py and the kernel is still stale when
    # ticks.py is newer than it
    monkeypatch.setattr(startup, "loop_sources", lambda: copies)
    kernel_src = tmp_path / "kernel.py"
    kernel_src.write_text("")
    monkeypatch.setattr(startup, "scene_kernel", lambda scene: (str(kernel_src), "run_sd"))
    stamp = tmp_path / "stamp"
    monkeypatch.setattr(startup, "loop_stamp", lambda fn: str(stamp))
    monkeypatch.setattr(startup, "_LOOP_KERNELS", str(kernel_src))
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
    for mod in (fastloop_kernels, fastmock):
        fns = [v for v in vars(mod).values()
               if isinstance(v, numba.core.registry.CPUDispatcher)
               and v.py_func.__module__ == mod.__name__]
        assert fns, mod.__name__
        for fn in fns:
            assert fn.targetoptions.get("nogil") is True
            assert (fn._cache.__class__.__name__ != "NullCache") == mod.CACHE_OK, fn


# ------------------------------------------------------------ every cached compiled module
# The class, not the two loops: any module of hapsim whose numba code is cached on disk and
# compiles in another module's functions or constants holds their digest
# (hapsim.kernels.sources). Imports only used from Python, per module, with why:
PYTHON_ONLY = {
    "hapsim.audio.jack_native": {"hapsim.audio.sources"},   # FrameRing, LiveSound: Python
    "hapsim.host.fastloop_kernels": {"hapsim.kernels.sources"},
    "hapsim.emulated.fastmock": {"hapsim.kernels.sources"},
    # the network's matrices, set up in Python at construction (never in a kernel)
    "hapsim.kernels.schemes": {"hapsim.kernels.matrices"},
}
PACKAGE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


#: numba's compiling decorators (a ``cache=`` keyword elsewhere, an argument of an
#: ordinary function, is no disk cache of compiled code)
NUMBA_DECORATORS = {"njit", "jit", "cfunc", "vectorize", "guvectorize", "generated_jit"}


def _numba_decorator(func) -> bool:
    """Whether a call's callee is one of :data:`NUMBA_DECORATORS` (``numba.njit``,
    ``njit``, ``nb.cfunc`` ...)."""
    name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
    return name in NUMBA_DECORATORS


def _cached_numba_modules():
    """Dotted names of hapsim's modules with a numba decorator given ``cache=``."""
    out = []
    for root, _, files in os.walk(os.path.join(PACKAGE, "hapsim")):
        for name in files:
            if not name.endswith(".py"):
                continue
            path = os.path.join(root, name)
            text = open(path).read()
            if "cache" not in text:         # no ``cache=`` keyword can be in it: no parse
                continue                    # (this runs at collection, in every worker)
            tree = ast.parse(text)
            if any(isinstance(n, ast.Call) and _numba_decorator(n.func)
                   and any(k.arg == "cache" for k in n.keywords) for n in ast.walk(tree)):
                rel = os.path.relpath(path, PACKAGE)[:-3]
                out.append(rel.replace(os.sep, "."))
    return sorted(out)


def _imported_modules(module_name):
    """hapsim / firmware_protocol modules ``module_name`` imports names from (any level)."""
    mod = importlib.import_module(module_name)
    tree = ast.parse(open(mod.__file__).read())
    mods = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.split(".")[0] in ("hapsim", "firmware_protocol"):
                for a in node.names:       # "from hapsim.kernels import audio": a module
                    full = f"{node.module}.{a.name}"
                    is_mod = importlib.util.find_spec(node.module) is not None and \
                        os.path.isfile(os.path.join(PACKAGE, *full.split(".")) + ".py")
                    mods.add(full if is_mod else node.module)
    return mod, mods


def test_the_scan_finds_the_known_cached_modules():
    """The scan sees the modules known to cache compiled code (else the next test would
    pass on nothing)."""
    found = set(_cached_numba_modules())
    assert {"hapsim.kernels.cordis", "hapsim.kernels.audio", "hapsim.kernels.nd",
            "hapsim.kernels.ticks", "hapsim.audio.jack_native",
            "hapsim.host.fastloop_kernels", "hapsim.emulated.fastmock"} <= found, found


@pytest.mark.parametrize("module_name", _cached_numba_modules())
def test_every_cached_module_holds_the_digest_of_what_it_compiles_in(module_name):
    """A cached module importing names from another of hapsim's modules (or the
    protocol's) lists it in ``COMPILED_SOURCES`` (or it is used from Python only, listed
    above), holds their current SHA-256 and caches only while it matches."""
    if module_name == "hapsim.audio.jack_native":
        pytest.importorskip("jack")
    mod, mods = _imported_modules(module_name)
    mods -= PYTHON_ONLY.get(module_name, set())
    mods.discard("hapsim.kernels.sources")            # the digest itself
    if not mods:
        assert not hasattr(mod, "COMPILED_SOURCES"), module_name
        return
    listed = {s[:-3].replace("/", ".") for s in mod.COMPILED_SOURCES}
    assert mods <= listed, (module_name, sorted(mods - listed))
    for m in mods:                  # what they compile in is compiled in here too
        inner = getattr(importlib.import_module(m), "COMPILED_SOURCES", ())
        assert set(inner) <= set(mod.COMPILED_SOURCES), (module_name, m)
    now = sources_mod.sources_digest(sources_mod.source_paths(mod.COMPILED_SOURCES))
    assert mod.COMPILED_SOURCES_SHA256 == now, (
        f"update the digest in {mod.__file__} (this touches it so numba recompiles): "
        f'COMPILED_SOURCES_SHA256 = "{now}"')
    assert mod.CACHE_OK
    compiled = [v for v in vars(mod).values()
                if isinstance(v, (numba.core.registry.CPUDispatcher,
                                  numba.core.ccallback.CFunc))
                and v.__wrapped__.__module__ == module_name]
    assert compiled, module_name
    for fn in compiled:             # cached only under a matching digest
        if getattr(fn, "py_func", fn.__wrapped__).__code__.co_filename.startswith("<"):
            # generated from a table (hapsim.kernels.arguments): no file numba could cache
            # it by, and it needs none: inlined into its callers' IR, which are cached
            assert fn.targetoptions.get("inline") == "always", fn
            continue
        assert (fn._cache.__class__.__name__ != "NullCache") == mod.CACHE_OK, fn


def test_a_changed_compiled_in_source_turns_the_cache_off(tmp_path, monkeypatch):
    """:func:`hapsim.kernels.sources.cache_ok` on copies: true for the digest of the
    sources as they are, false after one byte is appended to one of them."""
    src = os.path.join(PACKAGE, "hapsim", "kernels", "cordis.py")
    copy = tmp_path / "hapsim" / "kernels" / "cordis.py"
    copy.parent.mkdir(parents=True)
    copy.write_bytes(open(src, "rb").read())
    monkeypatch.setattr(sources_mod, "_HAPSIM", str(tmp_path / "hapsim"))
    rels = ("hapsim/kernels/cordis.py",)
    d = sources_mod.sources_digest([src])
    assert sources_mod.cache_ok(rels, d)
    with open(copy, "a") as f:
        f.write("\n")
    assert not sources_mod.cache_ok(rels, d)
