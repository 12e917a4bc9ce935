"""The ``hapsim`` command line.

Each sub-command lives in its own module under :mod:`hapsim.commands` and exposes
``register(subparsers)``, which adds its parser and sets ``func`` to a callable
``func(args) -> int`` returning the exit code.

Exit codes (all commands)
-------------------------
0
    Success (for ``check``: the closed loop is stable).
1
    The command ran but the verdict is negative: unstable or unrenderable
    configuration, a device fault, a safety stop.
2
    Bad input: unknown option, invalid scene file, invalid argument value.
130
    Interrupted from the keyboard (Ctrl-C) before the command could finish; nothing is
    printed but ``hapsim COMMAND: interrupted``, at any moment, imports included.
    (``hapsim run`` catches SIGINT itself once its loop is armed and exits 0.)
    With ``--json``, stdout holds the ``interrupted`` error object (below) then.
143
    Terminated (SIGTERM) before the command installed its own handler: what it started
    (children, temporary files) is undone first; nothing is printed (``--json``: the
    ``interrupted`` object). (``hapsim run`` stops cleanly on SIGTERM once armed, exit 0.)
141
    stdout was closed by its reader (``hapsim check --json | head``): the command stops
    quietly, prints nothing more (no ``BrokenPipeError`` traceback) and exits 128 + SIGPIPE,
    the status a shell shows for ``yes | head``, so ``set -o pipefail`` treats hapsim as it
    treats any other writer cut short by its reader.

JSON (``--json``)
-----------------
A command given ``--json`` prints exactly one JSON object on stdout whatever the outcome.
On success or a negative verdict it is the command's result (with its own ``verdict`` or
``renderable`` field); when the command fails before it has a result (bad input, an
unstable scene refused, a device fault, Ctrl-C) it is :func:`error_json`'s::

    {"error": {"type": "ConfigError", "message": "...", "file": "s.yaml", "line": 3,
               "key": "links[0].stiffness"}, "exit": 2}

with ``type`` the exception class (``usage`` for a bad option, ``interrupted`` for
Ctrl-C), ``file``/``line``/``key`` when known (else null; a bad command-line value's key
is its flag as typed, ``--joints``), ``spectral_radius`` and
``stiffness_limit`` for an unstable configuration, and ``exit`` the exit code. The same
one-line message goes to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import importlib
import json
import math
import re
import sys

from hapsim import __version__, spawn
from hapsim.errors import ConfigError, HapsimError, UnstableConfigError
from hapsim.option_values import Number, check_numbers, typed_flag

#: Sub-command modules, in the order ``--help`` lists them.
COMMANDS = ("simulate", "render", "calibrate", "stability", "map", "check",
            "run", "mock", "bench", "advise",
            "play", "telemetry", "identify", "family", "compare_corrections",
            "kinematics", "zwidth")


#: Options people confuse: felt (k, b) of ``calibrate`` against virtual (K, B) of ``render``.
#: option -> (what it is, where it belongs, the option it is mistaken for)
_CASE_HINTS = {
    "--k": ("the felt stiffness k [N/m] of 'hapsim calibrate'", "--K"),
    "--b": ("the felt damping b [N s/m] of 'hapsim calibrate'", "--B"),
    "--K": ("the virtual stiffness K [N/m] of 'hapsim render'", "--k"),
    "--B": ("the virtual damping B [N s/m] of 'hapsim render' and 'stability'", "--b"),
}
_WHAT = {"--K": "the virtual stiffness simulated", "--B": "the virtual damping simulated",
         "--k": "the felt stiffness to render", "--b": "the felt damping to render"}

#: Exit code when the reader of stdout went away (128 + SIGPIPE, as a shell reports it).
EXIT_BROKEN_PIPE = 141

#: The argv being parsed (for the hints of :class:`HapsimArgumentParser`).
_ARGV: list[str] = []


class HapsimArgumentParser(argparse.ArgumentParser):
    """ArgumentParser whose errors add a hint for k/K and b/B mix-ups and feed ``--json``.

    Notes
    -----
    Sub-command parsers inherit the class (``add_subparsers`` uses the parent's class).
    The message of the last error is kept in ``last_usage_error`` for :func:`main`. A
    non-number given to a numeric option is raised as a :class:`ConfigError` keyed by the
    flag (:func:`_refuse_number`), as ``nan`` or a value out of its range is.
    """

    last_usage_error: str | None = None

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # argparse reads "-inf", "-nan" and "-1e3" as unknown options ("--B -inf":
        # "expected one argument"): they are values, checked by the option's range
        # (hapsim.option_values), as "-1" and "-.5" are
        self._negative_number_matcher = re.compile(
            r"^-(\d+\.?\d*|\.\d+)(e[+-]?\d+)?$|^-(inf|infinity|nan)$", re.IGNORECASE)
    #: The option the last error is about, as typed (``argument --seed: ...``), else None.
    last_usage_key: str | None = None

    def error(self, message: str):
        """argparse's contract: say ``message`` in one line keyed by the option as typed,
        then exit 2 (:class:`SystemExit`).

        Parameters
        ----------
        message : str
            argparse's message (``argument --seed: invalid int value: 'x'``), extended here
            with hints (a flag's case, a near option or sub-command).

        Raises
        ------
        ConfigError
            A non-number given to a numeric option (:func:`_refuse_number`).
        SystemExit
            Otherwise, status 2, after the sub-command's usage and the message on stderr.
        """
        given = {a.split("=", 1)[0] for a in _ARGV if a.startswith("--")}
        parser: argparse.ArgumentParser = self
        for action in self._actions:       # the top parser: ask the chosen sub-command's
            if isinstance(action, argparse._SubParsersAction):
                chosen = [action.choices[a] for a in _ARGV if a in action.choices]
                parser = chosen[0] if chosen else parser
        _refuse_number(parser, message)    # a non-number for a numeric option
        known = {o for a in parser._actions for o in a.option_strings}
        hints = []
        for opt, (what, other) in _CASE_HINTS.items():
            if opt in given and opt not in known:
                use = (f"for {_WHAT[other]} use {other}" if other in known
                       else f"{parser.prog} does not take it")
                hints.append(f"{opt} is {what}; {use}")
        if hints:
            message = f"{message} ({'; '.join(hints)})"
        if message.startswith("unrecognized arguments:"):
            message += _did_you_mean(message.split(":", 1)[1].split(), sorted(known))
        message += _command_did_you_mean(parser, message)
        HapsimArgumentParser.last_usage_error = f"{parser.prog}: {message}"
        HapsimArgumentParser.last_usage_key = _argument_key(parser, message)
        # the sub-command's usage, not the top-level one: that is the parser whose options
        # the user was typing (argparse reports a sub-command's leftovers from the top)
        parser.print_usage(sys.stderr)
        parser.exit(2, f"{parser.prog}: error: {message}\n")


def _refuse_number(parser: argparse.ArgumentParser, message: str) -> None:
    """Raise the :class:`ConfigError` of a non-number given to a numeric option.

    ``argument --joints: must be a finite number [deg], got 'abc'`` (the message of a
    :class:`~hapsim.option_values.Number` type) becomes what ``nan`` or a value out of range
    gets from :func:`~hapsim.option_values.check_numbers`: one line keyed by the flag as
    typed, exit 2, without the usage. Other messages: nothing (argparse's own error).

    Raises
    ------
    ConfigError
        With ``prog`` set to the command (``hapsim kinematics``), for :func:`_main`.
    """
    if not message.startswith("argument "):
        return
    name, _, reason = message[len("argument "):].partition(": ")
    for action in parser._actions:
        if (action.option_strings and "/".join(action.option_strings) == name
                and isinstance(action.type, Number) and reason.startswith("must be ")):
            exc = ConfigError(reason, key=typed_flag(action.option_strings, _ARGV))
            exc.prog = parser.prog
            raise exc


def _argument_key(parser: argparse.ArgumentParser, message: str) -> str | None:
    """The option an argparse message ``argument -n/--steps: ...`` is about, as typed."""
    if not message.startswith("argument "):
        return None
    name = message[len("argument "):].split(": ", 1)[0]
    for action in parser._actions:
        if action.option_strings and "/".join(action.option_strings) == name:
            return typed_flag(action.option_strings, _ARGV)
    return None


def _did_you_mean(unknown: list[str], known: list[str]) -> str:
    """``" (did you mean --duration?)"`` for each unknown option close to a known one.

    Parameters
    ----------
    unknown : list of str
        The arguments argparse did not recognise (``--duraton``, ``--duraton=2``, values).
    known : list of str
        The option strings of the parser being used.

    Returns
    -------
    str
        ``""`` when no unknown option is close to a known one (difflib's ratio >= 0.6).
    """
    options = [arg.split("=", 1)[0] for arg in unknown if arg.startswith("-")]
    hints = []
    for name in options:
        close = difflib.get_close_matches(name, known, n=3)
        # difflib's ratio scores a swap of two letters like any two edits (--polt is as
        # close to --port as to --plot): the same letters rearranged is the likelier typo
        close = sorted(close, key=lambda c: sorted(c) != sorted(name))
        if close:
            hints.append(f"{name}: did you mean {close[0]}?" if len(options) > 1
                         else f"did you mean {close[0]}?")
    return f" ({'; '.join(hints)})" if hints else ""


def _command_did_you_mean(parser: argparse.ArgumentParser, message: str) -> str:
    """``" (did you mean check?)"`` for a mistyped sub-command (``hapsim chekc``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The parser that refused the argument.
    message : str
        argparse's message, ``argument COMMAND: invalid choice: 'chekc' (choose from ...)``.

    Returns
    -------
    str
        ``""`` unless the refused word is a sub-command's name mistyped (the same rule as
        :func:`_did_you_mean`: difflib's ratio >= 0.6, the same letters rearranged first).
    """
    found = re.match(r"argument COMMAND: invalid choice: '([^']*)'", message)
    if not found:
        return ""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            names = sorted(action.choices)
            word = found.group(1)
            close = difflib.get_close_matches(word, names, n=3)
            close = sorted(close, key=lambda c: sorted(c) != sorted(word))
            return f" (did you mean {close[0]}?)" if close else ""
    return ""


def error_json(exc: BaseException | None, code: int, message: str,
               key: str | None = None) -> str:
    """The JSON object a ``--json`` command prints when it fails before having a result.

    Parameters
    ----------
    exc : BaseException or None
        The error (None for a usage error found by argparse).
    code : int
        The exit code (2 bad input, 1 negative verdict or device fault, 130 Ctrl-C).
    message : str
        The one-line message also printed on stderr.
    key : str, optional
        The key when ``exc`` has none (a usage error about one option: its flag).

    Returns
    -------
    str
        ``{"error": {"type", "message", "file", "line", "key", ...}, "exit": code}`` on one
        line (shape in the module docstring).
    """
    err = {"type": "usage" if exc is None else
           "interrupted" if isinstance(exc, KeyboardInterrupt) else type(exc).__name__,
           "message": message,
           "file": getattr(exc, "file", None), "line": getattr(exc, "line", None),
           "key": getattr(exc, "key", None) or key}
    for name in ("spectral_radius", "stiffness_limit"):
        value = getattr(exc, name, None)
        if isinstance(value, float) and math.isfinite(value):
            err[name] = value
    return json.dumps({"error": err, "exit": code})


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Build the top-level argument parser with every sub-command registered.

    Parameters
    ----------
    only : str, optional
        Register this command only (one of :data:`COMMANDS`): ``hapsim run`` then imports
        none of the other commands' modules (start-up time). Default: all of them.

    Returns
    -------
    argparse.ArgumentParser
        The parser; ``parse_args`` yields a namespace whose ``func`` runs the command.
    """
    parser = HapsimArgumentParser(
        prog="hapsim",
        description=(
            "Real-time haptic simulator for force-feedback devices (one axis, a 2-D "
            "pantograph or a 3-D delta). It runs a "
            "mass-interaction scene against a device (or its mock) and tells you the "
            "stiffness k and damping b you actually feel, for the virtual K and B you "
            "simulate (Florens, Voda & Urma's temporary hybrid system)."),
        epilog=(
            "examples:\n"
            "  hapsim run configs/wall.yaml             close the loop on the embedded mock\n"
            "  hapsim run configs/pantograph_wall.yaml  a 2-D scene: felt stiffness and damping matrices\n"
            "  hapsim check configs/delta_sphere.yaml   a 3-D scene: stable? which matrices are felt?\n"
            "  hapsim simulate configs/string.yaml --steps 2000 --out string.npz\n"
            "  hapsim render --mass 0.1 --friction 0.5 --rate 1000 --delay 1 --hold zoh --K 2000 --B 2\n"
            "  hapsim calibrate --mass 0.1 --friction 0.5 --rate 1000 --delay 1 --hold zoh --k 2000 --b 3\n"
            "\nexit codes: 0 success, 1 negative verdict (unstable, unrenderable, device fault),\n"
            "2 bad input, 130 interrupted (Ctrl-C), 141 stdout closed by its reader (| head).\n"
            "Run 'hapsim COMMAND --help' for each command."),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"hapsim {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in (only,) if only in COMMANDS else COMMANDS:
        module = importlib.import_module(f"hapsim.commands.{name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the ``hapsim`` command line.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; ``sys.argv[1:]`` when None.

    Returns
    -------
    int
        Exit code (see the module docstring).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    want_json = "--json" in argv
    previous = _raise_on_sigterm()
    from hapsim.progress import Watch
    with Watch("hapsim") as watch:      # a status line on a terminal after 0.8 s of silence
        try:
            return _main(argv, want_json, watch)
        except BrokenPipeError:
            # the reader of stdout is gone (``| head``): nothing more can be said there, and
            # saying it on stderr would only be noise; entry() silences stdout's final flush
            return EXIT_BROKEN_PIPE
        finally:
            watch.doing = "ending what it started"
            _undo_at_stop(previous)


class _UnitsWriter:
    """A text stream with its sentences said in a rotary axis's units
    (:func:`hapsim.drivers.in_axis_units`; every other attribute the stream's)."""

    def __init__(self, stream, units: dict):
        self._stream, self._units = stream, units

    def write(self, text):
        from hapsim.drivers import in_axis_units
        return self._stream.write(in_axis_units(text, self._units))

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def _in_scene_units(args):
    """Run a command with its stdout and stderr in the units of its 1-D scene's axis: a
    rotary joint's (the Haply's: radians, newton metres) where ``--driver`` or the
    scene's ``device.protocol`` names one (``identify``'s ``--mock-scene`` too). The 1-D
    analyses are written in SI words; a scene's figures are in its axis's units. Nothing
    changes on a linear axis, an n-D scene (its Cartesian coordinates are metres whatever
    its driver) or without a scene or a driver."""
    path = getattr(args, "scene", None) or getattr(args, "mock_scene", None)
    driver = getattr(args, "driver", None)
    driver = driver if isinstance(driver, str) else None
    units = None
    if isinstance(path, str):
        from hapsim.drivers import units_of
        from hapsim.scene import scene_dimension, scene_protocol
        units = units_of(scene_dimension(path), scene_protocol(path), driver)
    elif driver is not None:
        # (no scene: a 1-D device behind --driver, identify's; its refusals said "kg"
        # of a Haply joint whose fit said "kg m^2")
        from hapsim.drivers import units_of
        units = units_of(1, None, driver)
    if units is None or units["position"] == "m":
        yield
        return
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _UnitsWriter(out, units), _UnitsWriter(err, units)
    try:
        yield
    finally:
        sys.stdout, sys.stderr = out, err


class Terminated(KeyboardInterrupt):
    """SIGTERM received before a command installed its own handler: the command stops as
    on Ctrl-C (what it started is undone, :func:`hapsim.spawn.run_stops`), exit 143."""


#: Exit code after SIGTERM (128 + SIGTERM, as a shell reports it).
EXIT_TERMINATED = 143


def _raise_on_sigterm():
    """Make SIGTERM raise :class:`Terminated` (main thread, default disposition only).

    Returns
    -------
    object
        The previous handler, for :func:`_undo_at_stop`; None when nothing was changed.
    """
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        return None
    if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        return None

    def _terminated(signum, frame):
        if spawn.inside_import(frame):    # it could come out as an ImportError: end now
            for s in (signal.SIGINT, signal.SIGTERM):
                signal.signal(s, signal.SIG_IGN)
            spawn.run_stops()
            import os
            os._exit(EXIT_TERMINATED)
        raise Terminated()
    signal.signal(signal.SIGTERM, _terminated)
    return signal.SIG_DFL


def _undo_at_stop(previous) -> None:
    """Undo what the command left to undo (children, temporary files and folders:
    :func:`hapsim.spawn.run_stops`) with SIGINT and SIGTERM held off, then put the SIGTERM
    handler ``previous`` back (None: it was not changed)."""
    import signal
    import threading
    main_thread = threading.current_thread() is threading.main_thread()
    held = {}
    if main_thread:
        for s in (signal.SIGINT, signal.SIGTERM):
            held[s] = signal.signal(s, signal.SIG_IGN)
    try:
        spawn.run_stops()
    finally:
        for s, handler in held.items():
            signal.signal(s, handler)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _main(argv: list[str], want_json: bool, watch) -> int:
    """:func:`main` without the broken-pipe guard (``watch``: its status line, whose
    label becomes the command once known)."""
    command = "hapsim"
    try:
        _ARGV[:] = argv
        HapsimArgumentParser.last_usage_error = None
        HapsimArgumentParser.last_usage_key = None
        # the command named first: only its module is imported (the others' imports cost
        # start-up time); no command, or an unknown one: all, for the listing and the error
        first = next((a for a in argv if not a.startswith("-")), None)
        from hapsim.blas import size_pools
        size_pools()                      # one BLAS thread, before numpy loads (hapsim.blas)
        parser = build_parser(first)      # imports the command(s): Ctrl-C may land here
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # argparse exits 2 on bad input, 0 on --help
            code = int(exc.code or 0)
            if code and want_json:
                message = HapsimArgumentParser.last_usage_error or "bad arguments"
                print(error_json(None, code, message, HapsimArgumentParser.last_usage_key),
                      flush=True)
            return code
        except ConfigError as exc:  # a non-number for a numeric option (_refuse_number)
            return _fail(getattr(exc, "prog", command), exc, 2, f"error: {exc}", want_json)
        command = watch.label = f"hapsim {args.command}"
        if args.command == "mock":      # a server: silent until stopped is its normal state
            watch.stop()
        with _in_scene_units(args):     # (its refusals too)
            try:
                import numpy as np
                # overflow/invalid in the analysis of extreme loops shows up in the
                # results (nan, inf, an unstable verdict); numpy's RuntimeWarnings on
                # stderr only confuse (issue 10)
                with np.errstate(all="ignore"):
                    # every numeric option in its declared range, before any work
                    check_numbers(_subparser(parser, args.command), args, argv)
                    return int(args.func(args))
            except UnstableConfigError as exc:
                # a negative verdict (unstable, not renderable), even when a ConfigError
                return _fail(command, exc, 1, f"{type(exc).__name__}: {exc}", want_json)
            except ConfigError as exc:
                return _fail(command, exc, 2, f"error: {exc}", want_json)
            except HapsimError as exc:
                return _fail(command, exc, 1, f"{type(exc).__name__}: {exc}", want_json)
    except KeyboardInterrupt as exc:
        if isinstance(exc, Terminated):     # asked by a process: the code says it
            if want_json:
                print(error_json(exc, EXIT_TERMINATED, f"{command}: terminated"), flush=True)
            return EXIT_TERMINATED
        try:
            return _fail(command, exc, 130, "interrupted", want_json)
        except KeyboardInterrupt:  # a second Ctrl-C while saying so
            return 130


def _subparser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    """The parser of sub-command ``name`` in the top-level ``parser``."""
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices[name]


def _fail(command: str, exc: BaseException, code: int, text: str, want_json: bool) -> int:
    """Print ``command: text`` on stderr (and the JSON error); return ``code``.

    Bad input (exit 2) is one line: a line break in the message is printed as ``\\n``.
    """
    line = f"{command}: {text}"
    if code == 2:
        line = line.replace("\r", "\\r").replace("\n", "\\n")
    print(line, file=sys.stderr, flush=True)
    if want_json:
        print(error_json(exc, code, line), flush=True)
    return code


def entry() -> None:
    """The ``hapsim`` console script and ``python -m hapsim``: exit with :func:`main`'s code.

    Once :func:`main` has returned, SIGINT and SIGTERM are ignored (the command is over; a
    late Ctrl-C or SIGTERM must not change its exit code). After Ctrl-C (code 130) the process ends with
    ``os._exit(130)`` once stdout and stderr are flushed: CPython would otherwise re-raise SIGINT at exit (exit status -2 rather
    than 130) when the interrupt landed inside code run by ``PyRun_String`` during an
    import, even though :func:`main` handled it.
    """
    code = main()
    try:  # what is still buffered goes now, while a broken pipe can still be caught
        sys.stdout.flush()
    except BrokenPipeError:
        code = EXIT_BROKEN_PIPE
    except (OSError, ValueError):
        pass
    if code == EXIT_BROKEN_PIPE:
        _silence_stdout()
    try:  # the work is done: a Ctrl-C or a SIGTERM from now on (flush, interpreter
        import signal  # shut-down: ~0.2 s) changes nothing, and must not turn the exit
        # code into 1, -SIGINT or -SIGTERM (a SIGTERM there killed a finished run: -15)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    except (ValueError, OSError):  # not the main thread
        pass
    if code in (130, EXIT_TERMINATED):
        import os
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError, KeyboardInterrupt):
                pass
        os._exit(code)
    sys.exit(code)


def _silence_stdout() -> None:
    """Point stdout's file descriptor at /dev/null once its reader has gone.

    The interpreter flushes ``sys.stdout`` again at exit; with the pipe closed that flush
    would print ``Exception ignored ... BrokenPipeError`` on stderr. This is the recipe of
    the Python documentation (``signal`` module, "Note on SIGPIPE").
    """
    import os
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no real stdout (embedded): nothing to do
        pass


if __name__ == "__main__":  # pragma: no cover
    entry()
