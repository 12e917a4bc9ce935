"""Suite-wide guards.

A test that changes the process's signal dispositions or mask and leaves them so changes
every process the same pytest worker starts afterwards: SIG_IGN and a blocked mask are
inherited across ``exec``. A SIGINT ignored by a leaked ``signal.signal(SIGINT, SIG_IGN)``
makes the Ctrl-C tests of later children exit 0 (their SIGINT never arrives: exactly the
failure they showed once, ``(0, '')``), depending on which tests xdist had given the worker
before, a failure that follows the load, not the code. After each test the dispositions
and the mask are put back as they were; a test that left SIGINT or SIGTERM ignored or
blocked (what children inherit) fails, naming it. (Importing PortAudio blocks SIGPIPE in the
mask: restored without a failure, Python's children ignore SIGPIPE anyway.)
"""

from __future__ import annotations

import json
import os
import resource
import signal
import threading
import time

import pytest

# --- Bytecode for the suite's own processes (issue 31 item 2) -----------------------------
# A machine with PYTHONDONTWRITEBYTECODE set (this project's CI machine has it) writes no
# .pyc: every pytest worker then compiles the whole suite's and hapsim's sources to collect
# (17.6 CPU-s a process against 6.3 with .pyc, measured with `python -m pytest
# --collect-only -q -n 0`), and each of the ~300 `python -m hapsim` children the tests start
# compiles hapsim's modules again (~0.3 CPU-s each). This conftest is loaded by the pytest
# process before it starts its xdist workers, which, like every child of the suite, inherit
# its environment: from here on they write and read .pyc as a default Python does, in the
# __pycache__ folders numba's disk cache already fills (git-ignored).
if os.environ.pop("PYTHONDONTWRITEBYTECODE", None) is not None:
    import sys
    sys.dont_write_bytecode = False

#: Restored after every test.
_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGPIPE)
#: A test must leave these as it found them (the Ctrl-C and service-manager tests' signals).
_WATCHED = {signal.SIGINT, signal.SIGTERM}


def _mask() -> set:
    return set(signal.pthread_sigmask(signal.SIG_BLOCK, []))


@pytest.fixture(autouse=True)
def _signals_left_as_found():
    """Restore the signal dispositions and mask after each test; fail one that left
    SIGINT or SIGTERM ignored or blocked."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = {s: signal.getsignal(s) for s in _SIGNALS}
    mask = _mask()
    yield
    changed = {}
    for s in _SIGNALS:
        now = signal.getsignal(s)
        if now is not before[s] and now != before[s] and before[s] is not None:
            # what a child inherits across exec: an ignored signal (a Python handler is
            # reset to the default there; it is restored here all the same)
            if s in _WATCHED and now is signal.SIG_IGN:
                changed[signal.Signals(s).name] = (before[s], now)
            signal.signal(s, before[s])
    left = _mask()
    if left != mask:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
    blocked = sorted(signal.Signals(s).name for s in (left - mask) & _WATCHED)
    assert not changed and not blocked, (
        f"the test left signal state changed (inherited by every process this worker "
        f"starts next; restored now): dispositions {changed}, newly blocked {blocked}")


# --- Where the suite's time goes (issue 31 item 2) -------------------------------------
# Wall time on this shared 2-core machine follows the load; CPU seconds hardly do. With
# ``--cpu-time=N`` every test records the CPU seconds of the pytest worker
# (time.process_time: all its threads) and of the children it waited for
# (getrusage(RUSAGE_CHILDREN): every ``python -m hapsim``, jackd, simavr, cc it started),
# beside its wall seconds and the time it ended (``end``, seconds since the epoch: a
# worker's timeline, its idle end, a group's chain); the N heaviest are printed at the end
# and, with ``--cpu-time-json=PATH``, all of them written as JSON (tools/suite_time.py
# reads it, with the session's start and end).


def pytest_addoption(parser):
    group = parser.getgroup("cpu-time", "CPU seconds per test (tests/conftest.py)")
    group.addoption("--cpu-time", type=int, default=None, metavar="N",
                    help="record CPU seconds per test (worker + waited-for children); "
                         "print the N heaviest (0: none) at the end")
    group.addoption("--cpu-time-json", default=None, metavar="PATH",
                    help="with --cpu-time: write every test's figures to PATH as JSON "
                         "(and PATH + 'l', one JSON line per test as it ends)")


def _child_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Record CPU seconds (own, children) and wall seconds of one test's set-up, call and
    tear-down as the item's user properties (xdist ships them to the controller)."""
    if item.config.getoption("--cpu-time") is None:
        yield
        return
    w0, c0, k0 = time.perf_counter(), time.process_time(), _child_cpu()
    item.user_properties.append(("cpu_time_start", (w0, c0, k0)))
    yield


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_makereport(item, call):
    """Stamp each phase's report with the figures accumulated since the test began (the
    tear-down report carries the whole test)."""
    if item.config.getoption("--cpu-time") is None:
        return
    start = dict(item.user_properties).get("cpu_time_start")
    if start is None:
        return
    w0, c0, k0 = start
    item.user_properties[:] = [p for p in item.user_properties if p[0] != "cpu_time"]
    item.user_properties.append(("cpu_time", {
        "wall": time.perf_counter() - w0, "cpu": time.process_time() - c0,
        "children": _child_cpu() - k0, "pid": os.getpid(), "end": time.time()}))


class _CpuTimeReport:
    """Controller side: gather the tear-down figures, print the heaviest, write JSON."""

    def __init__(self, config):
        self.config = config
        self.rows: dict[str, dict] = {}
        self.t0 = time.perf_counter()
        self.start = time.time()

    def pytest_runtest_logreport(self, report):
        if report.when != "teardown":
            return
        fig = dict(report.user_properties).get("cpu_time")
        if fig:
            row = dict(fig, worker=getattr(report, "node", None) and report.node.gateway.id
                       or "main", outcome=report.outcome)
            self.rows[report.nodeid] = row
            path = self.config.getoption("--cpu-time-json")
            if path:       # one line per test as it ends: a long run can be read midway
                with open(path + "l", "a") as f:
                    f.write(json.dumps(dict(row, test=report.nodeid)) + "\n")

    def pytest_terminal_summary(self, terminalreporter):
        n = self.config.getoption("--cpu-time")
        rows = sorted(self.rows.items(), key=lambda r: -(r[1]["cpu"] + r[1]["children"]))
        tot_cpu = sum(r["cpu"] for r in self.rows.values())
        tot_child = sum(r["children"] for r in self.rows.values())
        tot_wall = sum(r["wall"] for r in self.rows.values())
        tr = terminalreporter
        tr.write_sep("=", f"CPU seconds per test ({len(rows)} tests)")
        tr.write_line(f"total: own {tot_cpu:.1f} s + children {tot_child:.1f} s CPU; "
                      f"{tot_wall:.1f} s of test wall time; session "
                      f"{time.perf_counter() - self.t0:.1f} s; load {os.getloadavg()[0]:.2f}")
        for nodeid, r in rows[:n]:
            tr.write_line(f"{r['cpu'] + r['children']:8.2f} cpu {r['cpu']:7.2f} own "
                          f"{r['children']:7.2f} children {r['wall']:7.2f} wall  {nodeid}")
        path = self.config.getoption("--cpu-time-json")
        if path:
            with open(path, "w") as f:
                json.dump({"load": os.getloadavg(), "session_wall": time.perf_counter() - self.t0,
                           "session_start": self.start, "session_end": time.time(),
                           "tests": self.rows}, f, indent=0)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config):
    """How many workers ``-n auto`` (pyproject.toml's addopts) starts: one more than the
    machine's cores (``--maxprocesses`` caps it at 3), one on a single core.

    Much of the suite waits on real time (JACK and Pd, devices on the wall clock, browsers:
    the "sound" group alone is ~200-300 s of one worker's wall clock for ~50 CPU-s), and a
    group runs on one worker in turn; with as many workers as cores, such a worker left
    its core idle while the others queued. Measured beside one CPU-bound process on 2
    cores (``python tools/suite_time.py --busy 1 -- -n N --maxprocesses N``, warm
    caches, 2026-11-24): 2 workers 731 s, 3 workers 495 s, 4 workers 460 s. Four (and
    six) were tried as the default on 2026-11-24: of five full runs at four or six
    workers, three had a test fail on the load (a JACK underrun's time, a Haply
    re-synchronisation, the M3 run's lateness stop, the compiled loop's share), against
    none in the runs at three: the real-time tests' margin is worth the 7 %
    (docs/testing.md)."""
    n = os.cpu_count() or 1
    return 1 if n < 2 else n + 1


#: Longest silence [s] the README's test command leaves on a terminal before it shows that
#: tests are still running (issue 31: nothing a newcomer runs is silent over 2 s).
HEARTBEAT_S = 1.0


class _Heartbeat:
    """On a terminal, a dim ``·`` for every :data:`HEARTBEAT_S` in which no test reported.

    With ``-q`` pytest prints a character per result; the tests that wait on real time (a
    JACK server, a device on the wall clock, a browser) can hold every worker for several
    seconds, and the workers' start-up prints nothing for ~5 s: a newcomer saw a terminal
    stand still for up to 5 s. The controller's own thread writes the mark through the
    terminal reporter (its line width counted, so the ``[ NN%]`` column stays aligned)
    only while the main thread waits on the workers. Nothing in a log (not a terminal)
    or in a worker."""

    def __init__(self, config) -> None:
        self.config = config
        self.last = time.monotonic()
        self.done = threading.Event()
        threading.Thread(target=self._beat, name="pytest-heartbeat", daemon=True).start()

    def pytest_runtest_logreport(self, report) -> None:
        self.last = time.monotonic()

    def pytest_collectreport(self, report) -> None:
        self.last = time.monotonic()

    def pytest_unconfigure(self, config) -> None:
        self.done.set()

    def _beat(self) -> None:
        while not self.done.wait(0.25):
            now = time.monotonic()
            if now - self.last < HEARTBEAT_S:
                continue
            tr = self.config.pluginmanager.get_plugin("terminalreporter")
            if tr is None:
                continue
            self.last = now
            try:
                tr.write("\u00b7", light=True)
                tr.flush()
            except (OSError, ValueError):      # the terminal closed under pytest
                return


def pytest_configure(config):
    """One BLAS thread in every pytest process, as every ``hapsim`` command runs
    (hapsim.blas): two workers on two cores, each with an OpenBLAS pool as large as the
    machine, spin on each other's cores (an SVD of the matrix pencil took 14 s of CPU that
    way; the first in-process ``hapsim.cli.main`` of a worker used to shrink its pool, so
    a test's cost depended on which tests the worker had run before). Children keep the
    sizing of their own command line (nothing is put in the environment)."""
    import sys
    if not hasattr(config, "workerinput") and sys.stdout.isatty():
        config.pluginmanager.register(_Heartbeat(config), "heartbeat")
    from hapsim.blas import limit_blas_threads
    import numpy  # noqa: F401  (loads numpy's OpenBLAS: its pool is limited below)
    import scipy.linalg  # noqa: F401  (and scipy's)
    limit_blas_threads(1)
    _one_compiler_per_kernel()
    from hang_guard import register     # (a test that hangs ends with its tracebacks)
    register(config)
    if config.getoption("--cpu-time") is not None and not hasattr(config, "workerinput"):
        config.pluginmanager.register(_CpuTimeReport(config), "cpu-time-report")


def pytest_sessionstart(session):
    """Under ``.ci/run``: say that the README's pytest has started (the package is
    installed by then), by creating the file ``$HAPSIM_CI_FIRST_PASS_STARTED`` names; the
    second numerical pass, which waits for it, then starts beside this one at nice 19
    (docs/testing.md). The controller only; nothing without the variable."""
    path = os.environ.get("HAPSIM_CI_FIRST_PASS_STARTED")
    if path and not hasattr(session.config, "workerinput"):
        with open(path, "a"):
            pass


#: Longest a pytest process waits for another to finish compiling a kernel [s] before it
#: compiles the kernel itself (a compilation of the largest kernel takes ~20 CPU-s).
COMPILE_WAIT_S = 300.0


def compile_lock_path(dispatcher) -> str | None:
    """The lock file of a cached numba dispatcher's compilations (its kernel and its cache
    folder), None for one without a disk cache."""
    import hashlib
    import tempfile
    where = getattr(getattr(dispatcher, "_cache", None), "_cache_path", None)
    if where is None:
        return None
    folder = os.path.join(tempfile.gettempdir(), f"hapsim-numba-locks-{os.getuid()}")
    os.makedirs(folder, exist_ok=True)
    fn = dispatcher.py_func
    name = f"{where}:{fn.__module__}.{fn.__qualname__}"
    return os.path.join(folder, hashlib.sha1(name.encode()).hexdigest() + ".lock")


def _one_compiler_per_kernel() -> None:
    """The suite's workers compile each numba kernel once between them, not once each.

    On a fresh clone numba's disk cache is empty, and the workers (three on two cores)
    meet the same kernels at about the same time: each compiled the live loop's stretch
    (~20 CPU-s) for itself. Here a cached dispatcher's ``compile`` (numba's first use of a
    signature in a process: a load from the disk cache, or a compilation that saves to it)
    holds a file lock named after the kernel and its cache folder, so a second worker waits
    for the first and then loads what it saved. Kernels call kernels but never back (a call
    graph without cycles), so two processes cannot each hold a lock the other waits for;
    after :data:`COMPILE_WAIT_S` a waiting worker compiles anyway. The ``hapsim`` processes
    the tests start are not concerned (they load what the workers saved)."""
    import fcntl

    from numba.core.dispatcher import Dispatcher
    if getattr(Dispatcher.compile, "_hapsim_locked", False):
        return
    unlocked = Dispatcher.compile

    def compile(self, sig):
        path = compile_lock_path(self)
        if path is None:                           # not cached: nothing to share
            return unlocked(self, sig)
        fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o600)
        try:
            end = time.monotonic() + COMPILE_WAIT_S
            held = False
            while not held and time.monotonic() < end:
                try:
                    fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    held = True
                except OSError:
                    time.sleep(0.05)
            return unlocked(self, sig)
        finally:
            os.close(fd)                           # releases the lock, if held
    compile._hapsim_locked = True
    Dispatcher.compile = compile


# --- Which kernels this run computes with (issue 31 item 1: CI's second numerical pass) ---


def _kernels() -> tuple[list[str], str]:
    """The loaded OpenBLAS libraries' kernel architectures and numba's code target."""
    import numpy  # noqa: F401  (loads numpy's BLAS)
    import scipy.linalg  # noqa: F401  (and scipy's)
    from threadpoolctl import threadpool_info
    blas = sorted({f"{i['internal_api']} {i.get('architecture') or '?'}"
                   for i in threadpool_info() if i.get("user_api") == "blas"})
    from numba.core import config as nbconfig
    target = nbconfig.CPU_NAME or "host"
    return blas, target


def pytest_report_header(config):
    """Name the BLAS kernels and numba target in the header; when the run asks for others
    (``OPENBLAS_CORETYPE``, CI's second pass) and did not get them, stop: a pass that
    silently ran on the host's own kernels would repeat the first one."""
    blas, target = _kernels()
    want = os.environ.get("OPENBLAS_CORETYPE")
    if want and any(b.startswith("openblas") and b.split()[1].lower() != want.lower()
                    for b in blas):
        raise pytest.UsageError(f"OPENBLAS_CORETYPE={want} asked, but the BLAS kernels "
                                f"loaded are {blas}")
    return f"kernels: BLAS {', '.join(blas) or 'none found'}; numba target {target}"


# --- One lockstep run per shipped scene, shared (issue 31 item 2) ------------------------
# tests/test_contact_verdict.py and tests/test_scene_measurability.py both run every shipped
# 1-D scene with a port in lockstep, in process, and assert different things on the same
# report: a lockstep run is deterministic (the same record, bit for bit), so it is made
# once per worker (both tests carry xdist_group("shipped_lockstep"): one worker). The
# string scenes' felt-pair fits cost ~60 CPU-s a run.
_SHIPPED_RUNS: dict = {}


@pytest.fixture(scope="session")
def shipped_lockstep_run():
    """``run(path) -> (report, said)``: ``hapsim.pipeline.runner.run_scene`` of the scene
    at ``path`` in lockstep, in process (no signal handlers), and the messages its
    ``on_precheck`` received; made once per worker, a deep copy handed to each caller."""
    import copy

    def run(path):
        key = str(path)
        if key not in _SHIPPED_RUNS:
            from hapsim.pipeline.runner import run_scene
            from hapsim.scene import load_scene
            said: list = []
            rep = run_scene(load_scene(key), transport="inprocess", lockstep=True,
                            handle_signals=False, on_precheck=said.append)
            _SHIPPED_RUNS[key] = (rep, said)
        rep, said = _SHIPPED_RUNS[key]
        return copy.deepcopy(rep), list(said)
    return run


# --- xdist_group under pytest 9 -------------------------------------------------------------
# pytest-xdist's --dist loadgroup tells the controller a test's group by appending
# "@group" to its node id on the worker (``item._nodeid = ...``, xdist 3.8). pytest 9 keeps
# the node id in ``item._id`` (a NodeId) and no longer reads ``_nodeid``, so the suffix was
# lost and every xdist_group silently ignored: the "sound" tests' JACK servers ran on both
# workers at once, and a group's shared set-up was made on each worker. The same suffix is
# set here (NodeId.parse keeps the string as given), only where xdist's own did not take.


#: The modules whose tests close real-time loops over a pty or a port (a host at
#: ``SCHED_FIFO`` and an emulated board on its own clock), found by sampling the processes
#: at ``SCHED_FIFO`` during a whole-suite run: 85 such tests, about 275 of the suite's
#: 2,350 worker-seconds, two of them running at once in 19 % of the samples on 2 cores.
#: Each claims what one loop does beside CPU-bound load, not two real-time loops sharing
#: two cores: they run in one xdist group, one at a time (a module with a group of its
#: own keeps it: its tests run in turn already).
REALTIME_MODULES = frozenset({
    "test_bench_advise", "test_counts_verdict", "test_daemon_pty", "test_drivers",
    "test_faders_realtime", "test_falcon_spring", "test_falcon_watchdog", "test_firmware",
    "test_hapkit_serial_tick", "test_haply2_prediction", "test_haply2_probe",
    "test_haply2_realtime", "test_haply2_watchdog", "test_host_watchdog",
    "test_identify_excitation", "test_identify_late", "test_mock_board",
    "test_mock_persistent", "test_output_stage", "test_run_nd_faults", "test_run_nd_stop",
    "test_stop_cleanup", "test_throttled_host", "test_wallclock"})


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """On a pytest-xdist worker with ``--dist loadgroup``: the tests of
    :data:`REALTIME_MODULES` in the group ``realtime``; give each test that carries
    ``xdist_group(name)`` the node id ``<id>@<name>`` the controller's LoadGroupScheduling
    groups by (what pytest-xdist itself does where ``item._nodeid`` is the node id)."""
    if not getattr(config.option, "loadgroup", False):
        return
    for item in items:
        mod = getattr(item, "module", None)
        if (mod is not None and mod.__name__.rpartition(".")[2] in REALTIME_MODULES
                and item.get_closest_marker("xdist_group") is None):
            item.add_marker(pytest.mark.xdist_group("realtime"))
    for item in items:
        names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default"))
                        for m in item.iter_markers("xdist_group")})
        if not names:
            continue
        nodeid = item.nodeid
        if nodeid.rfind("@") > nodeid.rfind("]"):
            continue                                   # xdist's suffix took
        if hasattr(item, "_id"):
            from _pytest.nodeid import NodeId
            item._id = NodeId.parse(f"{nodeid}@{'_'.join(names)}")


#: Longest a pytest-xdist worker waits for the first worker's collection [s].
COLLECT_WAIT_S = 180.0


def collect_lock_path(rootpath) -> str:
    """The lock file of the workers' collections of the suite at ``rootpath``."""
    import hashlib
    import tempfile
    folder = os.path.join(tempfile.gettempdir(), f"hapsim-numba-locks-{os.getuid()}")
    os.makedirs(folder, exist_ok=True)
    name = hashlib.sha1(str(rootpath).encode()).hexdigest()
    return os.path.join(folder, f"collect-{name}.lock")


@pytest.hookimpl(hookwrapper=True)
def pytest_collection(session):
    """pytest-xdist workers collect after the first one, not all at once.

    Collecting imports every test module, which pytest assertion-rewrites and caches as
    ``.pyc`` beside it, and hapsim's modules, cached the same way. On a fresh clone that
    cache is empty: the workers (four on two cores) each compiled all of it, ~16 CPU-s a
    worker over a warm collection (``python -m pytest --collect-only -q -n 0`` ~22 against
    ~5.5 CPU-s). Here the first worker to get there collects alone (an exclusive lock),
    and the others, waiting on a shared lock, then collect together from its cache. The
    tests start once every worker has collected, so a warm run waits ~one warm
    collection more. After :data:`COLLECT_WAIT_S` a waiting worker collects anyway."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        yield
        return
    import fcntl
    fd = os.open(collect_lock_path(session.config.rootpath), os.O_CREAT | os.O_RDWR, 0o600)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)      # the first: collect alone
        except OSError:
            end = time.monotonic() + COLLECT_WAIT_S
            while time.monotonic() < end:
                try:
                    fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                    break
                except OSError:
                    time.sleep(0.1)
        yield
    finally:
        os.close(fd)                                 # releases the lock, if held


def pytest_collection_finish(session):
    """The heap built by the imports and the collection frozen out of the collector
    (``gc.freeze``), once, after one full collection.

    A pytest process holds numpy, scipy, numba and every test module: a full collection
    walks all of it, 0.07-0.2 s each time. :meth:`hapsim.host.loop.HostLoop.run` collects
    before arming a device on the wall clock (so that no collector pause falls in its run),
    and the interpreter's own oldest-generation collections come on top; in the suite's
    profile (2026-11-24) the loop's collection alone took 16 CPU-s. Frozen, those objects
    (modules, functions, test items: none of them becomes garbage before the process ends)
    are no longer walked; what the tests create still is. The product's collection is
    unchanged; only what it walks in a test process is smaller."""
    import gc
    gc.collect()
    gc.freeze()
