"""A test that hangs ends its process with every thread's traceback, and the run goes on.

A suite that hangs never ends: CI waits for ever and says nothing of where. Seen: a worker
stuck for minutes in a JACK client's close, its main thread waiting for a GIL that a thread
jack2 had cancelled still held (docs/sound.md, "The native callback"). pytest-timeout's
thread and signal methods both need the GIL to act, so neither ends that process;
``faulthandler.dump_traceback_later`` (``exit=True``) runs in C on a thread of its own,
writes every thread's Python stack without the GIL, and ``_exit``\\ s.

Each test arms it for :data:`HANG_S` (``HAPSIM_TEST_HANG_S`` overrides it) and disarms it
at its end. On a pytest-xdist worker the traceback goes, after the test's id, to a file
in a folder the controller made (``HAPSIM_TEST_HANG_DIR``); the worker's crash fails that
test, xdist starts another worker, and the controller prints the file at the end of the
run. Without xdist the traceback goes to standard error and the run ends there.

Registered by ``tests/conftest.py``'s ``pytest_configure``; ``tests/test_hang_guard.py``
runs a hanging test under it (``-p hang_guard``).
"""

from __future__ import annotations

import faulthandler
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

#: Longest one test may take [s]: the slowest takes ~22 s alone and ~35 s in the whole
#: suite beside its load (``--cpu-time``), so 300 s is no test's normal time.
HANG_S = 300.0
#: The folder the workers write their hang files into (set by the controller).
HANG_DIR_ENV = "HAPSIM_TEST_HANG_DIR"


def _hang_s() -> float:
    return float(os.environ.get("HAPSIM_TEST_HANG_S", HANG_S))


class _Guard:
    """One process's guard: where its traceback goes, armed around each test."""

    def __init__(self, config) -> None:
        self.worker = getattr(config, "workerinput", {}).get("workerid")
        folder = os.environ.get(HANG_DIR_ENV)
        if self.worker is not None and folder and os.path.isdir(folder):
            self.file = open(Path(folder) / f"{self.worker}-{os.getpid()}.txt", "w")
        else:
            self.file = _terminal_stderr(config)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item, nextitem):
        f = self.file
        if self.worker is not None and f.seekable():    # (the test's id first)
            f.seek(0)
            f.truncate()
            f.write(f"{item.nodeid}\n")
        f.flush()
        faulthandler.dump_traceback_later(_hang_s(), exit=True, file=f)
        try:
            yield
        finally:
            faulthandler.cancel_dump_traceback_later()


def _terminal_stderr(config):
    """The standard error pytest itself started with: under ``--capture=fd`` (the
    default) file descriptor 2 is a capture file while a test runs, lost at ``_exit``;
    pytest's capture keeps the original's duplicate (its ``targetfd_save``)."""
    capman = config.pluginmanager.getplugin("capturemanager")
    try:
        fd = capman._global_capturing.err.targetfd_save
        return os.fdopen(os.dup(fd), "w")
    except Exception:     # (--capture=sys or no: descriptor 2 is the terminal's)
        return sys.__stderr__


class _Report:
    """The controller's side under xdist: make the folder, print what hung, remove it."""

    def __init__(self) -> None:
        self.folder = tempfile.mkdtemp(prefix="hapsim-test-hang-")
        os.environ[HANG_DIR_ENV] = self.folder      # (the workers start after this)

    def pytest_terminal_summary(self, terminalreporter):
        hung = []
        for p in sorted(Path(self.folder).glob("*.txt")):
            text = p.read_text(errors="replace")
            if "Thread 0x" in text or "Current thread" in text:
                hung.append(text)
        shutil.rmtree(self.folder, ignore_errors=True)
        if not hung:
            return
        tr = terminalreporter
        tr.write_sep("=", f"tests that hung past {_hang_s():g} s (tests/hang_guard.py)")
        for text in hung:
            head, _, stacks = text.partition("\n")
            tr.write_line(f"{head}: every thread's stack when its process was ended")
            tr.write_line(stacks.rstrip())


def register(config) -> None:
    """Register the guard (a test's process) or the report (an xdist controller)."""
    if hasattr(config, "workerinput") or not config.pluginmanager.hasplugin("xdist") \
            or not _uses_workers(config):
        config.pluginmanager.register(_Guard(config), "hapsim-hang-guard")
    else:
        config.pluginmanager.register(_Report(), "hapsim-hang-report")


def pytest_configure(config):
    """As a plugin of its own (``-p hang_guard``): :func:`register`."""
    register(config)


def _uses_workers(config) -> bool:
    """Whether this controller runs its tests on xdist workers (``-n`` other than 0)."""
    n = getattr(config.option, "numprocesses", None)
    return n not in (None, 0)
