"""hapsim: a real-time haptic simulator daemon that tells you what you actually feel.

See ``README.md`` for the command line, ``hapsim.scene`` for the YAML scene format,
``hapsim.engine`` for the mass-interaction engine and ``hapsim.analysis`` for the
temporary hybrid system (THS) analysis of Florens, Voda & Urma.
"""



def _quiet_interrupt_at_start() -> None:
    """Let Ctrl-C end the ``hapsim`` command quietly (exit 130) at any moment, imports included.

    Only when this package is imported as the command line (the ``hapsim`` console script,
    or ``python -m hapsim``); a program that imports hapsim as a library keeps its own
    SIGINT handler and ``sys.excepthook``.

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
    argv0 = sys.argv[0] if sys.argv else ""
    if argv0 != "-m" and os.path.basename(argv0) not in ("hapsim", "hapsim.exe"):
        return

    def leave() -> None:
        try:
            sys.stderr.write("hapsim: interrupted\n")
            sys.stderr.flush()
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


_quiet_interrupt_at_start()

from hapsim.errors import (ConfigError, DeviceError, HapsimError, ProtocolError,
                           UnstableConfigError)

__version__ = "0.1.0"

__all__ = ["HapsimError", "ConfigError", "ProtocolError", "DeviceError",
           "UnstableConfigError", "__version__"]
