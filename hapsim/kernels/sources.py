"""Which sources a numba-compiled module compiles in, and whether its disk cache is fresh.

numba keys its on-disk cache of a function on the modification time and size of the
function's own file only (numba documentation, "Cache invalidation": "changes in other
files are not tracked"). A cached function that calls a jitted function of another module,
or reads that module's constants, keeps the other module's old code after an edit to it.
A module that compiles others in therefore holds, as a literal in its own file, the
SHA-256 of those sources (:func:`sources_digest`), and caches only while it matches
(:func:`cache_ok`); ``tests/test_compiled_loop_sources.py`` asks for the literal to be
updated when it no longer matches, and that edit to the module's own file is what makes
numba rebuild its cache. The host loop (:mod:`hapsim.host.fastloop_kernels`), the compiled mock
(:mod:`hapsim.emulated.fastmock`), the multi-rate audio kernel (:mod:`hapsim.kernels.audio`),
the late-tick rule (:mod:`hapsim.kernels.ticks`) and the JACK callback
(:mod:`hapsim.audio.jack_native`) use it.

Plain Python (no numba): importable from any floor.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os

__all__ = ["source_paths", "sources_digest", "cache_ok", "LOOP_SOURCES", "MOCK_SOURCES",
           "numba_cache_dir", "loop_stamp"]

#: The modules, besides ``hapsim/host/fastloop_kernels.py``, whose code or constants numba
#: compiles into the compiled host loop (the late-tick rule, the lateness guard, the I/O
#: primitives, the engine kernels and their argument table, the telemetry flags, the
#: protocol's constants). numba keys its on-disk cache of a function on its own file's
#: modification time and size only, so an edit to one of these alone would leave the cached loop on the old code: ``fastloop_kernels.py`` holds their
#: SHA-256 (:data:`hapsim.host.fastloop_kernels.COMPILED_SOURCES_SHA256`), compiles without
#: the cache when it does not match, and ``tests/test_compiled_loop_sources.py`` asks for
#: it to be updated (which touches ``fastloop_kernels.py``, so numba recompiles).
LOOP_SOURCES = ("hapsim/kernels/compiled_io.py", "hapsim/host/telemetry.py",
                "hapsim/kernels/ticks.py", "hapsim/kernels/late_growth.py",
                "hapsim/kernels/cordis.py",
                "hapsim/kernels/schemes.py", "hapsim/kernels/arguments.py",
                "firmware_protocol/codec.py")


#: The modules whose code or constants numba compiles into the compiled mock
#: (``hapsim/emulated/fastmock.py``: the I/O primitives, the protocol's constants), for the
#: same reason as :data:`LOOP_SOURCES` (``fastmock.COMPILED_SOURCES_SHA256``).
MOCK_SOURCES = ("hapsim/kernels/compiled_io.py", "firmware_protocol/codec.py")

#: The ``hapsim`` package directory.
_HAPSIM = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def source_paths(rels) -> list[str]:
    """Absolute paths of sources named relative to the repository.

    Parameters
    ----------
    rels : sequence of str
        ``"hapsim/..."`` or ``"firmware_protocol/..."`` paths with ``/`` separators.

    Returns
    -------
    list of str
        The files (``firmware_protocol`` located without importing it: where it is
        installed, else beside the ``hapsim`` package).
    """
    spec = importlib.util.find_spec("firmware_protocol")
    fp_dir = os.path.dirname(spec.origin) if spec and spec.origin else \
        os.path.join(os.path.dirname(_HAPSIM), "firmware_protocol")
    out = []
    for rel in rels:
        top, rest = rel.split("/", 1)
        out.append(os.path.join(_HAPSIM if top == "hapsim" else fp_dir, *rest.split("/")))
    return out


def sources_digest(paths) -> str:
    """SHA-256 (hex) of the named source files, in order, each as its base name and bytes.

    Parameters
    ----------
    paths : sequence of str
        Files (absolute paths, :func:`source_paths`).

    Returns
    -------
    str
        64 hex digits; a file that cannot be read contributes its name only (the digest
        then differs and the module compiles without numba's cache).
    """
    h = hashlib.sha256()
    for p in paths:
        h.update(os.path.basename(p).encode() + b"\0")
        try:
            with open(p, "rb") as f:
                h.update(f.read())
        except OSError:
            pass
        h.update(b"\0")
    return h.hexdigest()


def cache_ok(rels, digest: str) -> bool:
    """Whether a module compiling in the sources ``rels`` may use numba's disk cache.

    Parameters
    ----------
    rels : sequence of str
        The sources it compiles in (:func:`source_paths`' form).
    digest : str
        The SHA-256 the module holds for them (a literal in its own file).

    Returns
    -------
    bool
        True when the sources are those the digest names; False (compile afresh, never
        load a cache built from older sources) otherwise.
    """
    return sources_digest(source_paths(rels)) == digest


def numba_cache_dir(source: str) -> str:
    """The folder numba caches the compiled functions of the module ``source`` in.

    numba's own order (``numba.core.caching``, 0.5x-0.6x): ``NUMBA_CACHE_DIR`` when set
    (a sub-folder named after the module's folder and the SHA-1 of its path), else the
    module's ``__pycache__`` when it can be written, else the user's cache folder
    (``$XDG_CACHE_HOME/numba`` or ``~/.cache/numba``, the same sub-folder).

    Parameters
    ----------
    source : str
        Path of the Python module.

    Returns
    -------
    str
        The folder (it may not exist yet).
    """
    import hashlib
    folder = os.path.dirname(os.path.abspath(source))
    sub = os.path.basename(folder) + "_" + hashlib.sha1(folder.encode()).hexdigest()
    if os.environ.get("NUMBA_CACHE_DIR"):
        return os.path.join(os.environ["NUMBA_CACHE_DIR"], sub)
    tree = os.path.join(folder, "__pycache__")
    if os.access(tree if os.path.isdir(tree) else folder, os.W_OK):
        return tree
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "numba", sub)


def loop_stamp(kernel_fn: str) -> str:
    """The stamp file :func:`hapsim.host.fastloop.warm_up` leaves once the compiled host
    loop for the kernel ``kernel_fn`` is in numba's cache (the loop is compiled per
    kernel, which numba's index of the loop's functions does not show without numba).

    Parameters
    ----------
    kernel_fn : str
        The engine kernel's function name, e.g. ``run_sd``
        (:func:`hapsim.pipeline.startup.scene_kernel`).

    Returns
    -------
    str
        Path of ``hapsim-loop.<kernel_fn>.stamp`` in the loop module's numba cache folder
        (:func:`numba_cache_dir`; it may not exist).
    """
    return os.path.join(numba_cache_dir(source_paths(["hapsim/host/fastloop_kernels.py"])[0]),
                        f"hapsim-loop.{kernel_fn}.stamp")
