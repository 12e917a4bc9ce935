"""Start-up of ``hapsim run``: what it costs, and the one import it can skip.

``hapsim run`` reaches its first sample after: the interpreter, the command's imports,
the scene, the prediction, the device (the embedded mock's child process starts first)
and the numba warm-up (kernels loaded from numba's on-disk cache, in a thread while the
device starts and says HELLO). Measured with ``python -X importtime`` (issue 13), two
things cost more than the rest: ``scipy.optimize`` (the stability limit's root finder,
now :func:`hapsim.analysis.stability.brent_root`) and ``scipy.linalg``, which numba imports the
first time it sets up its compiler, even to load a cached function, only to check that
its BLAS bindings (``scipy.linalg.cython_blas``) exist. :func:`preload_numba_blas` loads
that one extension module by itself, so that numba's check passes without the package.

The first run with an empty numba cache compiles the kernels it needs (tens of seconds on
a small machine). :func:`announce_compilation` says so on stderr before anything is
compiled, from the files in numba's cache alone (numba is not imported for it), and
:func:`compile_notice` lets the warm-up report each part as it is done.
"""

from __future__ import annotations

import os
import sys
import time

from hapsim.blas import preload_numba_blas
from hapsim.kernels.sources import (LOOP_SOURCES, MOCK_SOURCES, loop_stamp, numba_cache_dir,
                                   source_paths)
from hapsim.kernels.sources import sources_digest as _digest

__all__ = ["process_start", "preload_numba_blas", "start_embedded_mock", "numba_cache_dir",
           "cache_is_fresh", "loop_stamp", "loop_is_fresh", "LOOP_SOURCES", "MOCK_SOURCES",
           "loop_sources",
           "sources_digest", "scene_kernel", "choose_loop",
           "compiled_loop_possible", "run_compile_parts", "part_is_fresh", "part_functions",
           "reset_announcements", "announce_compilation", "compile_notice"]


def process_start() -> float:
    """When this process started, on the clock of :func:`time.monotonic` [s].

    Returns
    -------
    float
        Start time [s] (Linux: the start time in ``/proc/self/stat``, 10 ms resolution,
        carried from ``CLOCK_BOOTTIME`` to ``CLOCK_MONOTONIC``); elsewhere the time this
        module was imported.
    """
    try:
        with open("/proc/self/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        started_boot = int(fields[19]) / os.sysconf("SC_CLK_TCK")   # starttime (field 22)
        now_mono = time.monotonic()
        now_boot = time.clock_gettime(time.CLOCK_BOOTTIME)
        return now_mono - (now_boot - started_boot)
    except (OSError, ValueError, IndexError, AttributeError):
        return _IMPORTED


_IMPORTED = time.monotonic()


def cache_is_fresh(source: str, function: str) -> bool:
    """Whether numba's cache holds ``function`` of module ``source`` compiled from the
    module as it is now (an index file written after the module's last change).

    Parameters
    ----------
    source : str
        Path of the Python module.
    function : str
        The function's qualified name in it (``run_sd``).

    Returns
    -------
    bool
        False when no index exists or every index is older than the module (numba then
        compiles: it keys its cache on the module's modification time).
    """
    return _any_fresh(source, function)


_HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: The compiled host loop's numba code (numba keys its cache on this file).
_LOOP_KERNELS = os.path.join(_HERE, "host", "fastloop_kernels.py")


def scene_kernel(scene) -> tuple[str, str]:
    """The module path and the function name of the engine kernel ``scene`` runs
    (:data:`hapsim.kernels.cordis.KERNELS` by link kinds, the integrator's kernel, or the
    multi-rate kernel of a scene with ``audio``).

    Parameters
    ----------
    scene : Scene
        A 1-D scene (its ``audio``, ``integrator`` and link kinds).

    Returns
    -------
    tuple of str
        ``(module path, function)``, e.g. ``(".../hapsim/kernels/cordis.py", "run_sd")``;
        an integrator other than ``"centred"`` or ``"symplectic_euler"`` gives
        ``run_exact``.
    """
    if getattr(scene, "audio", None) is not None:
        return os.path.join(_HERE, "kernels", "audio.py"), "run_periods"
    if scene.integrator == "centred":
        kinds = frozenset(lk.kind for lk in scene.links)
        fn = {frozenset(): "run_masses", frozenset({"spring_damper"}): "run_sd",
              frozenset({"contact"}): "run_contact"}.get(kinds, "run_sd_contact")
        return os.path.join(_HERE, "kernels", "cordis.py"), fn
    fn = "run_symplectic_euler" if scene.integrator == "symplectic_euler" else "run_exact"
    return os.path.join(_HERE, "kernels", "schemes.py"), fn


def loop_sources(rels=LOOP_SOURCES) -> list[str]:
    """The absolute paths of :data:`LOOP_SOURCES` (or of ``rels``, the same form:
    :func:`hapsim.kernels.sources.source_paths`).

    Parameters
    ----------
    rels : sequence of str, optional
        Paths relative to the repository (default :data:`LOOP_SOURCES`).

    Returns
    -------
    list of str
        The absolute paths, in the same order.
    """
    return source_paths(rels)


def sources_digest(paths=None) -> str:
    """SHA-256 (hex) of the named source files (:func:`hapsim.kernels.sources.sources_digest`).

    Parameters
    ----------
    paths : sequence of str, optional
        Files; :func:`loop_sources` by default.

    Returns
    -------
    str
        64 hex digits; a file that cannot be read contributes its name only (the digest
        then differs and the compiled loop compiles without numba's cache).
    """
    return _digest(loop_sources() if paths is None else paths)


def loop_is_fresh(scene) -> bool:
    """Whether the compiled host loop for ``scene``'s kernel is in numba's cache: its
    stamp is newer than the loop's module, the kernel's module and every module the loop
    compiles in (:data:`LOOP_SOURCES`).

    Parameters
    ----------
    scene : Scene
        The scene (:func:`scene_kernel` names its kernel).

    Returns
    -------
    bool
        False also when the stamp or a source cannot be read.
    """
    src, fn = scene_kernel(scene)
    try:
        at = os.stat(loop_stamp(fn)).st_mtime
        return all(at >= os.stat(p).st_mtime for p in (_LOOP_KERNELS, src, *loop_sources()))
    except OSError:
        return False


def compiled_loop_possible(scene, *, framed: bool = True, osc=None, sound=None,
                           host_clocked: bool = False) -> bool:
    """Whether a run of ``scene`` with these options can use the compiled host loop (else
    the Python loop runs, and :func:`hapsim.pipeline.runner.run_loop` reports why): the
    framed protocol on a device clock, no live OSC or sound, no device correction, no
    multi-rate audio model. A run that cannot use it does not compile it.

    Parameters
    ----------
    scene : Scene
        The scene to run.
    framed : bool
        The device speaks the framed protocol (no ``--driver``).
    osc, sound : optional
        ``--osc`` and ``--sound`` (None: not given).
    host_clocked : bool
        ``--host-clocked``.

    Returns
    -------
    bool
    """
    dev = scene.device
    return (framed and osc is None and sound is None and not host_clocked
            and (dev is None or getattr(dev, "correction", None) is None)
            and getattr(scene, "audio", None) is None)


def choose_loop(requested: str, scene) -> str:
    """The host loop a run uses: ``requested`` unless it is ``"auto"``, which takes the
    compiled loop when it is in numba's cache for the scene's kernel, and otherwise the
    Python loop (the reference: the same forces bit for bit) for this run.

    Parameters
    ----------
    requested : {"auto", "compiled", "python"}
        ``hapsim run --loop``.
    scene : Scene
        The scene to run.

    Returns
    -------
    {"compiled", "python"}
    """
    if requested != "auto":
        return requested
    return "compiled" if loop_is_fresh(scene) else "python"


def run_compile_parts(scene, *, compiled_loop: bool) -> list[tuple[str, str, str]]:
    """What ``hapsim run`` compiles before its first sample: ``(what, module, function)``
    for each part, the scene's engine kernel and, with the compiled host loop, the loop.

    Parameters
    ----------
    scene : Scene
        The scene to run (its integrator and link kinds name the kernel).
    compiled_loop : bool
        The run answers the device with the compiled host loop.

    Returns
    -------
    list of tuple of str
        ``(description, module path, function)``: the part is compiled unless numba's
        cache holds that function (:func:`cache_is_fresh`; for the loop, its stamp:
        :func:`loop_is_fresh`).
    """
    src, fn = scene_kernel(scene)
    parts = [("the engine's kernels", src, fn)]
    if compiled_loop:
        parts.append(("the compiled host loop", _LOOP_KERNELS, "answer_stretch"))
    return parts


_STEP1D = os.path.join(_HERE, "kernels", "step1d.py")


def part_functions(part) -> list[tuple[str, str]]:
    """The compiled functions a part of :func:`run_compile_parts` stands for, as
    ``(module path, function)``: the part's own and, for an engine kernel ``run_X``, its
    one-argument runner ``step_X`` of :mod:`hapsim.kernels.step1d` (which the engine's step
    and port_step call, and the warm-up compiles with the kernel).

    Parameters
    ----------
    part : tuple of str
        ``(description, module path, function)``.

    Returns
    -------
    list of tuple of str
    """
    what, src, fn = part
    out = [(src, fn)]
    if fn.startswith("run_") and os.path.dirname(src) == os.path.dirname(_STEP1D):
        out.append((_STEP1D, "step_" + fn[len("run_"):]))
    return out


def part_is_fresh(part, scene=None) -> bool:
    """Whether a part of :func:`run_compile_parts` is in numba's cache (every function of
    :func:`part_functions`; the compiled loop by its stamp, :func:`loop_is_fresh`).

    Parameters
    ----------
    part : tuple of str
        ``(description, module path, function)``.
    scene : Scene, optional
        The scene run; without it the compiled loop is judged by numba's index files
        (:func:`cache_is_fresh`) like any other part.

    Returns
    -------
    bool
    """
    what, src, fn = part
    if src == _LOOP_KERNELS and scene is not None:
        return loop_is_fresh(scene)
    return all(cache_is_fresh(s, f) for s, f in part_functions(part))


_NOTICE = None
_SAID: set = set()


def reset_announcements() -> None:
    """Forget what this process announced (at the start of each run of a command)."""
    global _NOTICE
    _NOTICE = None
    _SAID.clear()


def _any_fresh(source: str, function_glob: str) -> bool:
    import glob
    mod = os.path.splitext(os.path.basename(source))[0]
    tag = f"py{sys.version_info[0]}{sys.version_info[1]}{getattr(sys, 'abiflags', '')}"
    pattern = os.path.join(glob.escape(numba_cache_dir(source)),
                           f"{mod}.{function_glob}-*.{tag}.nbi")
    try:
        changed = os.stat(source).st_mtime
        return any(os.stat(p).st_mtime >= changed for p in glob.glob(pattern))
    except OSError:
        return False


def announce_compilation(parts, *, scene=None, command: str = "hapsim run",
                         stream=None) -> bool:
    """Say on ``stream`` (stderr) which of ``parts`` numba will compile, before it does.

    Nothing is printed when every part is in numba's cache or was announced already by
    this run (:func:`reset_announcements` starts a run). Otherwise one line names the
    parts, says it happens once and where the result is kept, and :func:`compile_notice`
    returns a reporter for the warm-up.

    Parameters
    ----------
    parts : list of tuple
        :func:`run_compile_parts` (a function of None: compiled, whatever the cache).
    scene : Scene, optional
        The scene the parts are for (the compiled loop's freshness is per kernel).
    command : str
        The command's name, which starts the line.
    stream : file, optional
        Where to print (default ``sys.stderr``).

    Returns
    -------
    bool
        True when something will be compiled (announced now or before).
    """
    global _NOTICE
    given = stream
    stream = sys.stderr if stream is None else stream
    cold = [(what, src) for what, src, fn in parts if what not in _SAID
            and (fn is None or not part_is_fresh((what, src, fn), scene))]
    if not cold:
        return bool(_SAID & {what for what, _, _ in parts})
    names = " and ".join(what for what, _ in cold)
    where = sorted({numba_cache_dir(src) for _, src in cold})
    print(f"{command}: compiling {names} with numba (once: the first run after an install "
          f"or an update; later runs load them from {', '.join(where)}) ...",
          file=stream, flush=True)
    _SAID.update(what for what, _ in cold)
    if _NOTICE is None:
        t0 = time.monotonic()

        def notice(what: str) -> None:
            # sys.stderr looked up when the warm-up ends, not when it was announced: the
            # notice outlives the command that announced it (a later run_scene in the same
            # process, e.g. zwidth's records after a run, finishes the warm-up), whose
            # stderr may be closed by then (a test's captured stream: 'I/O operation on
            # closed file' on a fresh clone's cold cache)
            print(f"{command}: compiled {what} ({time.monotonic() - t0:.1f} s since the "
                  f"announcement)", file=sys.stderr if given is None else given,
                  flush=True)
        _NOTICE = notice
    return True


def compile_notice():
    """The reporter :func:`announce_compilation` set up (``notice(what)`` prints that
    ``what`` is compiled and the time since), or None when nothing was announced.

    Returns
    -------
    callable or None
        ``notice(what: str) -> None``, or None.
    """
    return _NOTICE


def start_embedded_mock(scene, *, rate_hz: float | None = None, lockstep: bool = False,
                        seed: int = 0, faults: str | None = None, fault_seed: int = 0,
                        rt_priority: int = 0, tick: str = "auto"):
    """Start ``hapsim run``'s embedded mock device before the rest of the run's imports.

    The mock's child process (its interpreter, numpy, numba and the compiled tick: about
    half a second) then starts beside the host's own imports, prediction and numba warm-up
    instead of after them. :func:`hapsim.pipeline.runner.run_scene` takes it
    (``embedded=``) as :func:`~hapsim.pipeline.runner.connect` would have started it.

    Parameters
    ----------
    scene : Scene
        The scene to run (its device, excitation, rate and file).
    rate_hz : float, optional
        ``--rate`` (the native rate the mock announces); default the scene's.
    lockstep, seed, faults, fault_seed
        As :class:`hapsim.emulated.links.EmbeddedMock`.
    rt_priority : int
        ``SCHED_FIFO`` priority the child takes once its start-up is done (0: none; not
        for a lockstep mock, paced by the answers).
    tick : {"auto", "compiled", "python"}
        The mock's real-time ticks.

    Returns
    -------
    EmbeddedMock or None
        None when the run would refuse the scene before starting a device (no port or
        device section, or a delay below one period outside lockstep:
        :func:`hapsim.emulated.mock.require_whole_delay`): the run then says why, alone
        (the mock started would have said its own refusal beside it).

    Raises
    ------
    ConfigError
        A bad fault SPEC.
    """
    dev = scene.device
    if dev is None or scene.port is None or (float(dev.delay) < 1 and not lockstep):
        return None
    from hapsim.emulated.links import EmbeddedMock
    base_dir = os.path.dirname(os.path.abspath(scene.path)) if scene.path != "<string>" \
        else None
    return EmbeddedMock(dev, scene.excitation, float(rate_hz or scene.rate_hz),
                        lockstep=lockstep, seed=seed, base_dir=base_dir, faults=faults,
                        fault_seed=fault_seed, rt_priority=rt_priority, tick=tick)
