"""hapsim: a real-time haptic simulator daemon that tells you what you actually feel.

See ``README.md`` for the command line, ``hapsim.scene`` for the YAML scene format,
``hapsim.engine`` for the mass-interaction engine and ``hapsim.analysis`` for the
temporary hybrid system (THS) analysis of Florens, Voda & Urma.
"""



_QUIET_INTERRUPT = False


def _quiet_interrupt_at_start(force: bool = False) -> None:
    """Let Ctrl-C end the ``hapsim`` command quietly (exit 130) at any moment, imports included.

    Only when this package is imported as the command line (the ``hapsim`` console script,
    or ``python -m hapsim``), or with ``force`` (``hapsim/__main__.py``, however it is run,
    e.g. by ``runpy``); a program that imports hapsim as a library keeps its own SIGINT
    handler and ``sys.excepthook``. Installed once.

    Two holes are closed. A KeyboardInterrupt raised inside an import can come out as
    another exception (numpy turns it into an ``ImportError`` with a long message), so while
    any import is running (an ``importlib._bootstrap`` frame on the stack) SIGINT ends the
    process at once with ``hapsim: interrupted`` and status 130: nothing has been started
    that needs shutting down (``hapsim run`` installs its own handlers before it arms a
    device). Outside imports SIGINT raises KeyboardInterrupt as usual, which
    :func:`hapsim.cli.main` reports; one that escapes before ``main`` runs is reported by the
    ``sys.excepthook`` installed here.
    """
    import os
    import signal
    import sys
    global _QUIET_INTERRUPT
    argv0 = sys.argv[0] if sys.argv else ""
    # ``python -m hapsim`` shows "-m" while it imports the package; runpy.run_module from
    # another program gets here through __main__'s force=True (no walk of the call stack)
    if _QUIET_INTERRUPT or not (force or argv0 == "-m"
                                or os.path.basename(argv0) in ("hapsim", "hapsim.exe")):
        return
    _QUIET_INTERRUPT = True

    def say(fd: int, text: str) -> None:
        # the file descriptor itself, not sys.stdout / sys.stderr: leave() runs in a
        # signal handler, which may have interrupted a write to the same buffered stream
        # (whose re-entry raises RuntimeError, and the line would be lost)
        data = text.encode()
        try:
            while data:
                data = data[os.write(fd, data):]
        except OSError:
            pass

    def leave() -> None:
        _undo_started()
        try:
            for stream in (sys.stdout, sys.stderr):     # what was written before, first
                try:
                    stream.flush()
                except (OSError, ValueError, RuntimeError):
                    pass
            if "--json" in sys.argv[1:]:  # the promise of --json: one object on stdout
                # (written by hand: nothing may be imported while an import is cut short;
                # the shape of hapsim.cli.error_json)
                say(1, '{"error": {"type": "interrupted", "message": '
                       '"hapsim: interrupted", "file": null, "line": null, '
                       '"key": null}, "exit": 130}\n')
            say(2, "hapsim: interrupted\n")
        finally:
            os._exit(130)

    def on_sigint(signum, frame):
        while frame is not None:
            if frame.f_code.co_filename.startswith("<frozen importlib"):
                leave()
            frame = frame.f_back
        raise KeyboardInterrupt

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, on_sigint)
    previous = sys.excepthook

    def hook(kind, value, tb):
        if issubclass(kind, KeyboardInterrupt):
            leave()
        previous(kind, value, tb)

    sys.excepthook = hook


def _undo_started() -> None:
    """Undo what the command has started so far (the embedded mock's child, its report in
    the temporary directory: :func:`hapsim.spawn.run_stops`) before the process ends at
    once inside an import, SIGINT and SIGTERM held off meanwhile. Nothing to do, nothing
    imported, when :mod:`hapsim.spawn` was never loaded (nothing was started)."""
    import signal
    import sys
    spawn = sys.modules.get("hapsim.spawn")
    if spawn is None:
        return
    try:
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_IGN)
    except (ValueError, OSError):  # not the main thread
        pass
    try:
        spawn.run_stops()
    except BaseException:  # noqa: BLE001 - ending anyway
        pass


_quiet_interrupt_at_start()

from hapsim.errors import (ConfigError, DeviceError, HapsimError, ProtocolError,
                           UnstableConfigError)

__version__ = "0.1.0"

#: The Python API (:mod:`hapsim.api`), imported on first use: ``import hapsim`` stays as
#: light as the command line needs it.
_API = ("load_scene", "LoopModel", "check", "render", "calibrate", "stability", "family",
        "identify", "run", "play", "CheckReport", "RenderReport", "CalibrateReport",
        "StabilityReport", "FamilyReport", "IdentifyReport", "RunReport", "PlayReport",
        "load_scene_nd", "check_nd", "modes_nd", "run_nd", "CheckReportND", "ModesReportND",
        "RunReportND", "PlayReportND", "simulate", "SimulateReport", "SimulateReportND",
        "SimulateReportPorts")

__all__ = ["HapsimError", "ConfigError", "ProtocolError", "DeviceError",
           "UnstableConfigError", "__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        from hapsim import api
        return getattr(api, name)
    raise AttributeError(f"module 'hapsim' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))
