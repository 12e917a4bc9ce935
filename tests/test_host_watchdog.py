"""The host's watchdog for a board without one (issue 29: "the host never leaves a board
without a watchdog holding a torque for longer than a stated bound";
:mod:`hapsim.drivers.torque_watchdog`, :mod:`hapsim.drivers.host_watchdog`).

Each board here keeps its own clock (the emulated Haply M3 on the wall clock, served on a
pty by a thread while the host is silent), and the host's silence is a real one: the
test's thread sleeps, touching nothing, as a descheduled host does. The bound stated is
``bound_s + check_s`` plus the watchdog's wake-up latency, which it measures itself;
:data:`LATENCY_S` is the allowance for that latency on a loaded 2-core machine (measured:
1.5-2.1 ms beyond ``bound_s`` on a quiet one, within the check interval; 10 ms of
scheduling on top is the margin).
"""

from __future__ import annotations

import math
import os
import pty
import signal
import struct
import subprocess
import sys
import time
import tty

import firmware_protocol as fp
import pytest
from hapsim.drivers import get_driver
from hapsim.drivers.resync import HOLD_BOUND_S
from hapsim.drivers import torque_watchdog as tw
from hapsim.scene import Device, Excitation
from test_drivers import _states_within  # same directory

#: The watchdog's wake-up latency allowed beyond its check interval [s] (module notes).
LATENCY_S = 0.010
#: The host's silence in these tests [s]: five times the bound.
SILENCE_S = 5 * HOLD_BOUND_S
#: Records after the silence that show the link going on, and the wall time the loop
#: waits for them at most [s] (:func:`_run`).
AFTER_RECORDS = 20
AFTER_WAIT_S = 2.0
#: ``SCHED_FIFO`` priority of the emulated boards here, where the OS permits it: above
#: any host loop of the suite's other workers (10) and the watchdog (11), as a board's
#: own processor is never descheduled by a host (a board starved by the other workers'
#: real-time loops held a torque 87 ms on its own clock, the watchdog's zero write
#: waiting unread in its pty).
BOARD_PRIORITY = 12


def _link_device(dev):
    """A driver mock served in a thread on a fresh emulated link (``emulated://NAME``, as
    :class:`hapsim.emulated.driver_mock.EmbeddedDriverMock` makes it), the thread at
    :data:`BOARD_PRIORITY` where permitted: (its URL, stop flag, thread). The board takes
    each write, the host's and the watchdog's, at the time the kernel stamped it with
    (:mod:`hapsim.emulated.stamped_link`), as a board on its own processor takes its bytes
    when they come. (On a pty it took them when the pty's flip-buffer worker, a kernel
    thread of normal priority, had passed them on: behind other real-time tasks, the
    watchdog's zero write waited there up to 70 ms unseen, and a board held a force 113 ms
    against a stated 87, once in a fresh clone's CI; made again beside two SCHED_FIFO
    busy loops, 5 holds past the bound in 25 runs.) ``flag["conn"]``, the board's end
    once the host opened the port, sends bytes as from the board."""
    import threading

    from hapsim.emulated.driver_mock import serve
    from hapsim.emulated.stamped_link import connection
    from test_emulated_link import _listener  # same directory
    lst, url = _listener()
    flag = {"stop": False, "report": None, "conn": None}

    def run():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(BOARD_PRIORITY))
        except (AttributeError, OSError):   # not permitted: normal scheduling
            pass
        conn, reader = connection(lst.detach(), stop=lambda: flag["stop"])
        if conn is None:
            return
        flag["conn"] = conn
        with conn:
            flag["report"] = serve(conn.fileno(), dev, stop=lambda: flag["stop"],
                                   poll=0.004, stamped=reader)
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return url, flag, th


def _stop_link(flag, th) -> None:
    """Stop a board served by :func:`_link_device` and join its thread."""
    flag["stop"] = True
    th.join(2.0)
    assert not th.is_alive()


def _stated(wd: dict) -> float:
    """The bound a run states on a board's hold [s]: the hold bound, the check interval
    and :data:`LATENCY_S`, or the watchdog's own measured silence to a write's end when
    longer (a machine whose real-time tasks were throttled: 89 ms once, beside the suite's
    other workers' real-time loops; the run reports it, ``watchdog.longest_s``), or the
    longest host silence it did not run in (``missed_s``: 112 ms once, beside two
    SCHED_FIFO 50 busy loops)."""
    return max(HOLD_BOUND_S + wd["check_s"] + LATENCY_S, wd["longest_s"], wd["missed_s"])


#: How long a bare-pty test waits beyond the host's silence for the watchdog's write it
#: is owed [s]: the watchdog is a process of its own, and on a loaded machine it can wake
#: past the silence (its write came 90-118 ms after the host's bytes once, in a fresh
#: clone's CI, where the test's 100 ms sleep had ended); what it then states
#: (``longest_s``, ``overslept_s``) is what the tests compare.
OWED_WAIT_S = 2.0


def _silent(wd, seconds: float = SILENCE_S, owed: bool = True) -> None:
    """The host silent for ``seconds`` (the test's thread sleeps), then, when the silence
    is owed a write (``owed``: armed, a force held), until the watchdog made it (at most
    :data:`OWED_WAIT_S` more): a silence of the host lasts at least until the watchdog
    answered it, as a descheduled host's does."""
    before = wd.report()["fired"]
    time.sleep(seconds)
    end = time.monotonic() + OWED_WAIT_S
    while owed and wd.report()["fired"] == before and time.monotonic() < end:
        time.sleep(1e-3)


def _latency_bound(rep: dict) -> float:
    """The longest silence a watchdog's write may end [s]: the bound, a check, and its
    wake-up latency (:data:`LATENCY_S`, or what it measured of its own lateness when
    more: ``overslept_s`` past a check's end plus ``acted_s`` from the wake-up to the
    write's end)."""
    return rep["bound_s"] + rep["check_s"] + max(LATENCY_S, rep["overslept_s"] + rep["acted_s"])


def _read_all(fd: int, wait_s: float = 0.05) -> bytes:
    """What the pty's other end has to read within ``wait_s``."""
    import select
    out = b""
    end = time.monotonic() + wait_s
    while time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.005)
        if r:
            out += os.read(fd, 4096)
    return out


def test_watchdog_writes_zero_once_per_silence_and_hands_its_writes_to_the_host():
    """On a bare pty: a host whose last write left a force and who writes nothing for five
    bounds gets exactly one zero write, taken by the host with a time after the bound; a
    host that writes within the bound gets none; a last write of zero force is no hold
    (none); disarmed, none; and the next host write hands the watchdog's writes to the
    host first, which are on the wire before its own bytes."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    wd = tw.TorqueWatchdog(os.ttyname(slave), b"\x02\x01ZERO", HOLD_BOUND_S)
    taken = []

    class Port:
        def write(self, data):
            os.write(slave, data)
    port = Port()
    try:
        wd.arm()
        t0 = time.monotonic_ns()
        taken.extend(wd.write(port, b"HOST", True))
        _silent(wd)
        assert _read_all(master) == b"HOST" + b"\x02\x01ZERO"
        got = wd.take()
        assert len(got) == 1 and got[0] - t0 >= HOLD_BOUND_S * 1e9
        assert taken == [] and wd.take() == ()
        gaps, t = [], time.monotonic()
        for _ in range(int(SILENCE_S / (HOLD_BOUND_S / 4))):    # a host in time
            taken.extend(wd.write(port, b"H", True))
            time.sleep(HOLD_BOUND_S / 4)
            gaps.append(time.monotonic() - t)
            t = time.monotonic()
        taken.extend(wd.write(port, b"Z", False))               # zero force: no hold
        _silent(wd, owed=False)
        wire = _read_all(master, 0.01)
        # (no zero write: unless a loaded machine let this thread sleep beyond the bound)
        assert wire == b"H" * len(gaps) + b"Z" or max(gaps) > HOLD_BOUND_S, (wire, gaps)
        extra = len(wd.take()) + len(taken)
        taken.clear()
        taken.extend(wd.write(port, b"HOST", True))
        wd.arm(False)
        _silent(wd, owed=False)
        assert _read_all(master, 0.01) == b"HOST" and wd.take() == () and taken == []
        wd.arm()
        taken.extend(wd.write(port, b"HOST", True))
        _silent(wd)
        taken.extend(wd.write(port, b"NEXT", False))
        assert len(taken) == 1
        assert _read_all(master) == b"HOST" + b"\x02\x01ZERO" + b"NEXT"
        rep = wd.report()
        assert rep["fired"] == 2 + extra and HOLD_BOUND_S <= rep["longest_s"] <= (
            _latency_bound(rep)), rep
    finally:
        wd.close()
        os.close(slave)
        os.close(master)


def test_watchdog_refuses_a_port_that_is_no_device_and_quits_with_its_parent():
    """A URL or a missing path: no watchdog, the reason given. A host that dies without
    closing it: the watchdog process quits by itself (it polls its parent)."""
    wd, why = tw.start_watchdog("socket://localhost:1", b"\0", HOLD_BOUND_S)
    assert wd is None and "not a device file" in why
    with pytest.raises(OSError, match="could not take"):
        tw.TorqueWatchdog("/nonexistent/tty", b"\0", HOLD_BOUND_S)
    master, slave = pty.openpty()
    code = ("import os, sys; sys.path.insert(0, {root!r}); "
            "from hapsim.drivers.torque_watchdog import TorqueWatchdog as W; "
            "w = W({path!r}, b'\\0', 0.02); print(w._proc.pid, flush=True); os._exit(0)"
            ).format(root=os.path.dirname(os.path.dirname(tw.__file__)).rsplit("/hapsim", 1)[0],
                     path=os.ttyname(slave))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=30)
    pid = int(out.stdout.split()[0])
    end = time.monotonic() + 2.0
    while os.path.exists(f"/proc/{pid}") and time.monotonic() < end:
        try:                                # (reap it if it became ours: it did not)
            with open(f"/proc/{pid}/stat") as f:
                if f.read().split()[2] == "Z":
                    break
        except OSError:
            break
        time.sleep(0.01)
    alive = os.path.exists(f"/proc/{pid}")
    if alive:
        with open(f"/proc/{pid}/stat") as f:
            alive = f.read().split()[2] != "Z"
    os.close(slave)
    os.close(master)
    assert not alive


def _host_code(port: str, bound_s: float, holding: bool, end: str,
               robust: tuple | None = None) -> str:
    """A host process's code: a watchdog on ``port`` with ``bound_s`` (and ``robust``),
    armed, the host's write ``HOST`` (``holding``: leaving a force held), the watchdog's
    pid printed, then ``end``."""
    root = os.path.dirname(os.path.dirname(tw.__file__)).rsplit("/hapsim", 1)[0]
    return "\n".join([
        "import os, sys, time",
        f"sys.path.insert(0, {root!r})",
        "from hapsim.drivers.torque_watchdog import TorqueWatchdog as W",
        f"w = W({port!r}, b'ZERO', {bound_s!r}, robust={robust!r})",
        f"fd = os.open({port!r}, os.O_WRONLY | os.O_NOCTTY)",
        "class P:",
        "    def write(self, d):",
        "        os.write(fd, d)",
        "w.arm()",
        f"w.write(P(), b'HOST', {holding!r})",
        "print(w._proc.pid, flush=True)",
        end])


def _gone(pid: int) -> bool:
    """Whether process ``pid`` has ended (gone, or a zombie)."""
    if not os.path.exists(f"/proc/{pid}"):
        return True
    with open(f"/proc/{pid}/stat") as f:
        return f.read().split()[2] == "Z"


@pytest.mark.parametrize("holding", [True, False])
def test_a_host_that_dies_holding_a_force_gets_one_zero_write(holding):
    """A host that dies (``os._exit``: killed, crashed; nothing closed) armed, right after
    writing a force: the watchdog writes the zero command once, within its check interval
    of the death (long before its 2 s silence bound), then quits; a host whose last write
    was zero force gets nothing. Before, the watchdog quit at once, and a board without a
    watchdog of its own held the dead host's force for good."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    code = _host_code(os.ttyname(slave), 2.0, holding, "os._exit(0)")
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=30)
        t_dead = time.monotonic()
        pid = int(out.stdout.split()[0])
        # the check interval is 0.5 s: the write within it (and a loaded machine's
        # scheduling: 0.5 s more), far from the 2 s bound
        wire, t_zero = b"", None
        end = t_dead + 1.2
        while time.monotonic() < end:
            wire += _read_all(master, 0.01)
            if t_zero is None and b"ZERO" in wire:
                t_zero = time.monotonic()
        gone = _gone(pid)
    finally:
        os.close(slave)
        os.close(master)
    assert wire == (b"HOST" + b"ZERO" if holding else b"HOST"), wire
    if holding:
        assert t_zero - t_dead < 1.0, t_zero - t_dead
    assert gone


@pytest.mark.parametrize("case", ["no angle", "angle", "no value"])
def test_a_dying_host_with_a_robust_write_gets_the_robust_one(case):
    """A host that dies armed right after writing a force, its watchdog holding a robust
    write (the M3's: a set-up whose float is the encoder offset; the 2DIY's: no value):
    the dying write is the robust one (no host is left to account its set-up, and the
    host may have died in the bytes that lost the board its place), its float the angle
    the host last published, else the one it was given, else written as it is."""
    import struct
    data = b"RBST" + struct.pack("<f", 12.5) + b"END"
    robust = (data, None) if case == "no value" else (data, 4)
    master, slave = pty.openpty()
    tty.setraw(slave)
    end = ("w.angle(30.0)\n" if case == "angle" else "") + "os._exit(0)"
    code = _host_code(os.ttyname(slave), 2.0, True, end, robust=robust)
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=30)
        pid = int(out.stdout.split()[0])
        wire = b""
        end_t = time.monotonic() + 1.2         # (the check interval 0.5 s, and 0.5 s more)
        while time.monotonic() < end_t and not wire.endswith(b"END"):
            wire += _read_all(master, 0.01)
        end_t = time.monotonic() + 3.0
        while not _gone(pid) and time.monotonic() < end_t:
            time.sleep(0.01)
        gone = _gone(pid)
    finally:
        os.close(slave)
        os.close(master)
    want = data if case != "angle" else b"RBST" + struct.pack("<f", 30.0) + b"END"
    assert wire == b"HOST" + want, wire
    assert gone


@pytest.mark.parametrize("sig", ["SIGINT", "SIGSTOP", "SIGHUP"])
def test_a_terminals_signal_to_the_host_leaves_the_watchdog_working(sig):
    """A terminal's Ctrl-C, Ctrl-Z or hang-up goes to the whole foreground process group:
    the host's, which must not take its watchdog with it. A host holding a force gets
    the zero command within the bound and its check (and a loaded machine's 0.3 s) after
    the signal, whether it died (Ctrl-C, hang-up: the dying write) or is stopped
    (Ctrl-Z: the silence's write). Before, the watchdog shared the host's group: Ctrl-C
    and the hang-up killed it with its host, Ctrl-Z stopped it, and the board held the
    force. (Ctrl-Z's stop is sent as SIGSTOP here: this host's group, a session of its
    own for the test, is orphaned, and the kernel discards a SIGTSTP to an orphaned
    group.)"""
    import signal
    master, slave = pty.openpty()
    tty.setraw(slave)
    bound = 0.2
    host = subprocess.Popen([sys.executable, "-c", _host_code(os.ttyname(slave), bound,
                                                              True, "time.sleep(30)")],
                            stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        wd_pid = int(host.stdout.readline())
        assert _read_all(master, 0.05) == b"HOST"
        t_sig = time.monotonic()
        os.killpg(host.pid, getattr(signal, sig))      # (the host's group, as a terminal)
        wire, t_zero = b"", None
        while time.monotonic() < t_sig + bound + 1.0:
            wire += _read_all(master, 0.01)
            if b"ZERO" in wire:
                t_zero = time.monotonic()
                break
        assert wire == b"ZERO", (sig, wire)
        assert t_zero - t_sig < bound + bound / 4 + 0.3, (sig, t_zero - t_sig)
    finally:
        for s in (signal.SIGCONT, signal.SIGKILL):
            try:
                os.killpg(host.pid, s)
            except ProcessLookupError:
                pass
        host.wait(10)
        end = time.monotonic() + 3.0            # (its parent gone: it quits)
        while not _gone(wd_pid) and time.monotonic() < end:
            time.sleep(0.01)
        os.close(slave)
        os.close(master)
    assert _gone(wd_pid)


def _board(name: str, seed: int = 0):
    """An emulated board of driver ``name`` on the wall clock, its driver and rate [Hz]."""
    from hapsim.emulated.driver_mock import FireFaderDevice, HapkitSerialDevice, HaplyDevice
    if name == "haply":
        dev = Device(mass=1e-3, friction=1e-2, delay=1, force_limit=0.12)
        return HaplyDevice(dev, 1000.0, Excitation(), clock="wall"), get_driver("haply"), 1e3
    if name == "hapkit-serial":
        # (a friction that keeps the handle, pushed by up to 1 N for 0.5 s, inside the
        # driver's plausible 0.5 m: at 0.1 N s/m it ran past it at 5 ticks a period and
        # its replies were taken for garbled bytes, a re-synchronisation)
        dev = Device(mass=0.05, friction=2.0, delay=1, force_limit=2.0)
        rate = get_driver(name).native_rate_hz          # 5 of the sketch's ticks
        return HapkitSerialDevice(dev, rate, Excitation(), seed=seed), get_driver(name), rate
    dev = Device(mass=0.05, friction=0.1, delay=1, force_limit=0.38)
    drv = get_driver("firefader")
    drv.arming_records = 0                  # (its enable's ramp: not this test's)
    return FireFaderDevice(dev, 250.0, Excitation(), boot_s=0.0), drv, 250.0


def _run(name: str, silence_s: float, at: int = 40, force: float = 0.05, seed: int = 0,
         stray: bytes = b"", stray_at: int | None = None, before_stop_s: float = 0.0,
         again_s: float = 0.0, watchdog_stopped: bool = False):
    """The emulated board ``name`` behind its driver's transport: armed, ``at`` ticks of
    ``force``, the host silent ``silence_s``, 40 ticks more at a fifth of it, STOP;
    ``stray`` bytes read by the host alone as from the board at tick ``stray_at``
    (None: just before the silence; no bytes: nothing); ``before_stop_s``: the host
    silent that long again between its last FORCE and its STOP; ``again_s``: silent that
    long again after its first FORCE after the silence; ``watchdog_stopped``: the
    watchdog process stopped through the silence, let go after the next FORCE.
    Returns (the transport's report, the board's report, STATEs after the silence)."""
    from hapsim.drivers.transport import DriverTransport
    board, drv, rate = _board(name, seed)
    path, flag, th = _link_device(board)
    try:
        tr = DriverTransport(drv, path, delay=1, inertia=1e-3 if name == "haply" else None)
        tr.send(fp.Config(rate, 50_000, 1.0))
        assert _states_within(tr, 3.0), name
        after = []
        for k in range(at + 40):
            if stray and k == (at if stray_at is None else stray_at):
                # the board's answers to the commands before read first (on a loaded
                # machine an answer late by a few ms came after the stray bytes, in the
                # same read: a record after them, so nothing for the robust write, once
                # in a fresh clone's CI), for at most half the hold bound (the host's
                # watchdog would write in a longer wait, before the stray bytes)
                quiet_until = time.monotonic() + HOLD_BOUND_S / 2
                while time.monotonic() < quiet_until:
                    time.sleep(0.002)
                    if not tr.receive(0.0):
                        break
                flag["conn"].send(stray)    # bytes that make no record, read alone
                time.sleep(0.005)
                tr.receive(0.0)
                # whether the host read them as the evidence they are (not so when a
                # board's late answer came after them in the same read)
                suspected = bool(tr._wd_suspect)
            if k == at:
                if watchdog_stopped:
                    os.kill(tr.watchdog._proc.pid, signal.SIGSTOP)
                time.sleep(silence_s)       # the host does not run
            if k == at + 1:
                time.sleep(again_s)
            tr.send(fp.Force(k, (force if k < at else force / 5,)))
            if k == at and watchdog_stopped:
                os.kill(tr.watchdog._proc.pid, signal.SIGCONT)
            time.sleep(1.0 / rate)
            got = [m for m in tr.receive(0.0) if type(m) is fp.State]
            if k >= at:
                after += got
        # "the records go on" is a property of the link, not of 40 ticks of a loaded
        # machine: the loop goes on at a fifth of the force until AFTER_RECORDS records
        # came after the silence, for at most AFTER_WAIT_S (in a fresh clone's CI at load
        # 9.7 a robust write's set-up left 2 records in the 40 ticks)
        k = at + 40
        until = time.monotonic() + AFTER_WAIT_S
        while len(after) < AFTER_RECORDS and time.monotonic() < until:
            tr.send(fp.Force(k, (force / 5,)))
            time.sleep(1.0 / rate)
            after += [m for m in tr.receive(0.0) if type(m) is fp.State]
            k += 1
        time.sleep(before_stop_s)
        tr.send(fp.Stop())
        time.sleep(0.02)
        rep = tr.report()
        tr.close()
    finally:
        _stop_link(flag, th)
    if stray:
        rep["stray_suspected"] = suspected
    return rep, flag["report"], after


def _m3_run(silence_s: float):
    """:func:`_run` on the M3."""
    return _run("haply", silence_s)


@pytest.mark.parametrize("seed", range(4))
def test_every_board_that_holds_its_force_is_zeroed_within_the_bound(seed):
    """The property, over random boards that hold a force longer than the bound (the M3,
    the Hapkit sketch, the FireFader's .ino), random silences of 0-100 ms at a random
    tick and random forces: the board never holds a non-zero force longer than the stated
    bound plus a period; a silence beyond the bound and the check interval is answered
    by exactly one zero write, one within the bound by none; each zero write's answer is
    taken as such (no re-synchronisation) and the records go on."""
    import numpy as np
    rng = np.random.default_rng(seed)
    name = ("haply", "hapkit-serial", "firefader")[seed % 3]
    silence = float(rng.uniform(0.0, 5 * HOLD_BOUND_S))
    limit = {"haply": 0.1, "hapkit-serial": 1.0, "firefader": 0.3}[name]
    rep, board, after = _run(name, silence, at=int(rng.integers(20, 60)),
                             force=float(rng.uniform(0.2, 1.0)) * limit, seed=seed)
    wd = rep["watchdog"]
    info = (name, silence, wd, {k: rep[k] for k in ("watchdog_zeroed", "watchdog_replies",
                                                     "resyncs", "unprompted", "commands")})
    assert wd["running"], info
    stated = _stated(wd)
    period = 1e-3 if name == "haply" else 4e-3
    # the board takes every write at its kernel stamp (_link_device), however late its
    # thread runs, and the watchdog's stated silence runs to its write's end: the hold
    # is that silence plus how much longer the board took to act on the zero write than
    # on the force (within a period: the Hapkit sketch's 1.56 ms read, a tick and its
    # render; measured beside two CPU-bound processes and a SCHED_FIFO one, the
    # emulators 35-46 ms late: at most 0.3 ms past the stated bound in 80 runs). The
    # board thread's lateness (longest_gap_s) is still allowed: beside two SCHED_FIFO 50
    # busy loops the FireFader's .ino held a force to its own 0.1 s silence rule, 39-42
    # ms past the stated bound, once in 20-40 runs, unexplained (the watchdog counted a
    # write in that silence; the board took none before its rule)
    late = board["longest_gap_s"]
    assert board["longest_hold_s"] <= stated + period + 1e-3 + late, (
        board["longest_hold_s"], late, info)
    # the silence's write: the zero command past the bound, none short of it (at least
    # one: beside the suite's real-time workers and other load a host may stall past
    # the bound once more in its 80 ticks, a write of its own: once seen, the Hapkit
    # sketch written twice for one 51 ms silence; the accounting below is exact
    # whatever their number). No byte lost: no robust write, however long the silence
    if silence >= HOLD_BOUND_S + wd["check_s"] + LATENCY_S:
        assert wd["fired"] >= 1, info
    assert wd["robust"] == 0, info
    assert rep["watchdog_zeroed"] == wd["fired"], info
    # each zero write's answer is the watchdog's, or -- where the host, stalled, wrote its
    # next command before it read that answer -- taken for that command, whose own answer
    # then comes with nothing left to answer ("unprompted"): the pairing of a board that
    # numbers nothing is by the order of the writes (once in a fresh clone's CI, beside
    # the numerical pass: the FireFader, fired 1, watchdog_replies 0, unprompted 1). Never
    # lost, never a re-synchronisation
    assert rep["watchdog_replies"] <= wd["fired"], info
    assert rep["unprompted"] >= wd["fired"] - rep["watchdog_replies"], info
    # (other answers left unclaimed, "unprompted", are this harness's: 1 a run for the
    # Hapkit sketch on a quiet machine with no silence and no watchdog, 2-3 beside the
    # suite's other workers, 1 once for the M3 with no zero write made; not asserted)
    assert rep["resyncs"] == 0, info
    # (a quarter of the 40 ticks after it: beside the suite's workers, 18 of them once)
    assert len(after) >= 10, info


@pytest.mark.parametrize("seed", range(3))
def test_the_first_force_after_a_watchdogs_write_is_watched_too(seed):
    """The property, over random boards, silences and forces: the host silent past the
    bound (the watchdog's zero write), then one force written, then silent past the
    bound again: that force is watched as any other, zeroed within the stated bound by
    a write of its own. (The transport told the watchdog the first force written after
    a watchdog's write was none -- its own force set to zero by taking that write, just
    before writing the force -- and the second silence got no write: a Hapkit held
    0.04 N 59.5 ms against a stated 40, beside two CPU-bound processes.)"""
    import numpy as np
    rng = np.random.default_rng(100 + seed)
    name = ("haply", "hapkit-serial", "firefader")[seed % 3]
    limit = {"haply": 0.1, "hapkit-serial": 1.0, "firefader": 0.3}[name]
    silence, again = (float(v) for v in rng.uniform(2.5, 5.0, 2) * HOLD_BOUND_S)
    rep, board, _ = _run(name, silence, at=int(rng.integers(20, 60)),
                         force=float(rng.uniform(0.5, 1.0)) * limit, seed=seed,
                         again_s=again)
    wd = rep["watchdog"]
    info = (name, silence, again, wd, board["longest_hold_s"])
    # (at least one write each silence: beside the suite's workers the host may stall
    # past the bound once more)
    assert wd["running"] and wd["fired"] >= 2, info
    assert board["longest_hold_s"] <= _stated(wd) + (1e-3 if name == "haply" else 4e-3) \
        + 1e-3 + board["longest_gap_s"], info   # (the property test's bound)


def test_a_silence_the_watchdog_did_not_run_in_is_stated():
    """The watchdog process stopped (``SIGSTOP``: as one that real-time tasks above it,
    or their throttling, keep off every core) through a host silence of five bounds, and
    let go after the host's next write: no write, the board held the force the whole
    silence, and the host counts that silence as one the watchdog missed (``missed``,
    ``missed_s``), so the bound the run states covers the hold and its report line says
    so. (Before, the stated bound was the answered silences' alone: 35 ms stated of a
    101 ms hold, a FireFader beside two SCHED_FIFO 50 busy loops.)"""
    from hapsim.drivers.torque_watchdog import watchdog_text
    rep, board, _ = _run("haply", SILENCE_S, at=30, watchdog_stopped=True)
    wd = rep["watchdog"]
    assert wd["running"] and wd["missed"] >= 1 and wd["missed_s"] >= SILENCE_S, wd
    assert board["longest_hold_s"] >= SILENCE_S, board      # (held: so this can fail)
    assert board["longest_hold_s"] <= _stated(wd) + 1e-3 + 1e-3, (board["longest_hold_s"], wd)
    assert "got none, the watchdog not run" in watchdog_text(wd, "the zero command"), wd


def test_m3_host_silence_bounded_by_the_watchdog_and_accounted():
    """The M3 (no watchdog) holding 0.05 N m while its host is silent for five bounds:
    the host's watchdog zeroes it once, the board held the torque no longer than the
    stated bound, its answer to the watchdog's write is taken as such (no
    re-synchronisation: a link that lost no byte gets no robust write however long the
    silence) and the records go on after the silence.
    The same run with no watchdog holds the torque the whole silence (so this test can
    fail)."""
    rep, board, after = _m3_run(SILENCE_S)
    wd = rep["watchdog"]
    # (at least: beside the suite's real-time workers the host may stall once more)
    assert wd["running"] and wd["fired"] >= 1 and wd["robust"] == 0, wd
    assert rep["watchdog_zeroed"] == wd["fired"], rep
    # (each answer the watchdog's, or taken for the host's next command written before
    # it was read, that command's own then unprompted: the property test's accounting)
    assert rep["watchdog_replies"] <= wd["fired"], rep
    assert rep["unprompted"] >= wd["fired"] - rep["watchdog_replies"], rep
    assert rep["resyncs"] == 0, rep
    stated = _stated(wd)
    # the board took the zero write at its kernel stamp (_link_device), the end of the
    # watchdog's stated silence at the latest (1 ms: the margin of the property test)
    assert board["longest_hold_s"] <= stated + 1e-3, (
        board["longest_hold_s"], board["longest_gap_s"], wd)
    assert len(after) >= AFTER_RECORDS


def test_m3_bytes_that_make_no_record_before_a_silence_get_the_robust_write():
    """Bytes the host reads that make no record (the board may have lost its place) just
    before the host falls silent, with no command of the host between them: the
    watchdog's write in that silence is the robust one (the driver's stop at the host's
    last angle), counted as a re-synchronisation of its own, and the board holds its
    torque no longer than the stated bound. (When the host told the watchdog only at its
    next command, this silence got the plain zero command, which a board whose parser
    lost the motor's address does not take: a torque held 94 ms of a 300 ms stall.)"""
    for _ in range(8):
        # the condition made: the stray bytes read as the last before the silence (a
        # board's answer late past the drain, on a loaded machine, came after them in
        # the same read once in a whole suite: a record, no evidence; that run tests the
        # plain silence, above, and is made again; 3 tries were all spent so once in a
        # fresh clone's CI beside the numerical pass)
        rep, board, after = _run("haply", SILENCE_S, stray=b"\x07\x07")
        if rep["stray_suspected"]:
            break
    assert rep["stray_suspected"], rep
    wd = rep["watchdog"]
    # (the silence's write robust: one per silence. A later stall of a loaded host, the
    # board back in step, gets the plain zero command, rightly: robust == fired failed
    # so beside two bursts; the board's hold below fails where this silence got the plain
    # one, which the board that lost its place does not take)
    assert wd["running"] and wd["robust"] >= 1 and wd["fired"] >= wd["robust"], wd
    assert rep["resync_reasons"].get("watchdog") == wd["robust"], rep["resync_reasons"]
    assert board["longest_hold_s"] <= _stated(wd) + 1e-3, (
        board["longest_hold_s"], board["longest_gap_s"], wd)
    assert len(after) >= AFTER_RECORDS


def test_a_lossy_links_long_silence_gets_the_robust_write_too():
    """A link that has shown it loses bytes (stray bytes read at tick 10, records after
    them), then a host silence of five bounds: the zero command at the bound, then, past
    ``ROBUST_AFTER`` bounds, the robust write at the last angle the host published (a
    parser that lost its place in the last bytes before the silence, unseen, takes no
    zero command), counted as the watchdog's re-synchronisation; the records go on."""
    rep, board, after = _run("haply", SILENCE_S, stray=b"\x07\x07", stray_at=10)
    wd = rep["watchdog"]
    assert wd["running"] and wd["fired"] >= 2 and wd["robust"] >= 1, wd
    assert rep["resync_reasons"].get("watchdog") == wd["robust"], rep["resync_reasons"]
    assert rep["watchdog_zeroed"] == wd["fired"], rep
    assert board["longest_hold_s"] <= _stated(wd) + 1e-3, (
        board["longest_hold_s"], board["longest_gap_s"], wd)
    assert len(after) >= AFTER_RECORDS


def test_m3_host_silence_without_the_watchdog_holds_the_torque(monkeypatch):
    """The control: the watchdog not started (its reason reported), the board holds the
    torque through the whole silence."""
    monkeypatch.setattr(tw, "start_watchdog", lambda *a, **k: (None, "off for the test"))
    rep, board, _ = _m3_run(SILENCE_S)
    assert rep["watchdog"] == {"running": False, "why": "off for the test"}
    # the whole silence: the writes around it taken at their kernel stamps (on a pty,
    # when the board's thread ran: 98.7 ms of 100 once under the suite's load)
    assert board["longest_hold_s"] >= SILENCE_S, board


def _2diy_run(monkeypatch, silence_s: float, at_tick: int = 30, stray: bytes = b"",
              stray_tick: int | None = None, records: list | None = None):
    """The 2DIY's measurement over its emulated link (the board in its child process, on
    its own clock), the host silent ``silence_s`` once, at the ``at_tick``-th tick of the
    loop (in the first record); ``stray`` bytes written to the board (through the host's
    own port, as a host byte too many) at the ``stray_tick``-th tick, 3 ms before the
    tick goes on (the board's parser takes them alone); ``records``, a list, gets the
    loop's records (:func:`hapsim.pipeline.haply2_record.record_realtime`'s, each with the
    measurement's ``usable`` rows). Returns (the measurement, the board's report)."""
    from pathlib import Path

    from hapsim.lockstep import identification_plan
    from hapsim.pipeline.haply2_embedded import Embedded2DIY
    from hapsim.pipeline.haply2_host import measure_felt_haply2_port
    from hapsim.pipeline.haply2_realign import Realigner
    from hapsim.scene import load_scene_nd
    wall = Path(__file__).resolve().parent.parent / "configs" / "pantograph_wall.yaml"
    ticks = {"n": 0}
    tick_end = Realigner.tick_end

    def silent_once(self, k, got, resynced):
        ticks["n"] += 1
        if stray and ticks["n"] == stray_tick:
            port[0].write(stray)
            time.sleep(0.003)
        if ticks["n"] == at_tick:
            time.sleep(silence_s)           # the host does not run (not the port either)
        return tick_end(self, k, got, resynced)
    monkeypatch.setattr(Realigner, "tick_end", silent_once)
    if records is not None:
        import hapsim.pipeline.haply2_host as host
        loop = host.record_realtime

        def kept(*a, **k):
            records.append(loop(*a, **k))
            return records[-1]
        monkeypatch.setattr(host, "record_realtime", kept)
    # the host's port, kept for the stray bytes (the measurement opens it)
    import hapsim.drivers.urlhandler as urlhandler
    port = [None]
    opened = urlhandler.serial_for_url

    def keep(*a, **k):
        port[0] = opened(*a, **k)
        return port[0]
    monkeypatch.setattr(urlhandler, "serial_for_url", keep)
    sc = load_scene_nd(wall)
    N = 60
    child = Embedded2DIY(str(wall), "gen3", amplitude=1e-4, cpr=2.0 ** 22,
                         rt_priority=BOARD_PRIORITY)
    try:
        r = measure_felt_haply2_port(child.port, sc, "gen3", amplitude=1e-4,
                                     resolution=2.0 ** 22, samples=N,
                                     plan=identification_plan(sc, N), probe_wiring=False)
        child.release_slave()
        rep = child.report(5.0)
    finally:
        child.close()
    return r, rep


def test_2diy_host_silence_bounded_by_the_watchdog_and_accounted(monkeypatch):
    """The 2DIY (no watchdog) over its pty, the host silent for five bounds in its first
    record: the host's watchdog zeroes both torques once, the board held a torque no
    longer than the stated bound plus a period, its reply to the zero write is taken as
    such (every reply read by its record's end counted against the writes, the
    watchdog's among them; no re-synchronisation), and the board is left at zero."""
    r, rep = _2diy_run(monkeypatch, SILENCE_S)
    wd = r["watchdog"]
    assert wd["running"] and sum(wd["zeroed"]) == wd["fired"] >= 1, wd
    assert wd["replies"] == wd["zeroed"], wd
    assert r["resyncs"][0] == 0, (r["resyncs"], wd)       # (the record of the silence)
    if sum(r["resyncs"]):
        # a loaded machine held the board's child past a later record's closing wait: that
        # record re-armed (tests/test_haply2_realtime.py: its replies may come after it)
        assert all(p <= w + e for p, w, e in
                   zip(r["replies"], r["writes"], r["rearm_writes"])), \
            (r["replies"], r["writes"], r["rearm_writes"])
    else:
        assert r["replies"] == r["writes"], (r["replies"], r["writes"], wd)
    stated = _stated(wd)
    assert rep["longest_hold_s"] <= stated + 2e-3 + rep["longest_gap_s"], (
        rep["longest_hold_s"], rep["longest_gap_s"], wd)
    assert rep["held_at_end"] == 0.0


def test_2diy_host_silence_without_the_watchdog_holds_the_torque(monkeypatch):
    """The control: no watchdog started (its reason reported), the 2DIY holds its
    torques through the whole silence."""
    monkeypatch.setattr(tw, "start_watchdog", lambda *a, **k: (None, "off for the test"))
    r, rep = _2diy_run(monkeypatch, SILENCE_S)
    assert r["watchdog"]["running"] is False
    # the silence, less how late the board took the write made before it: the hold runs
    # from the board's taking of that write to its taking of the next, so a first write
    # delivered late shortens it (0.0989 s once under the suite's load, against the 0.1 s
    # asserted before); the emulator's own lateness (longest_gap_s) bounds that delay, as
    # it bounds the watchdog's hold from above in the test before. And far beyond what a
    # watchdog lets a board hold: the control's point.
    assert rep["longest_hold_s"] >= SILENCE_S - rep["longest_gap_s"], (
        rep["longest_hold_s"], rep["longest_gap_s"])
    assert rep["longest_hold_s"] > 2 * (HOLD_BOUND_S + LATENCY_S), rep["longest_hold_s"]


def _lossy_parser_states(n_states: int, loss: float = 0.005):
    """The M3 board's parser (firmware V1.5, :class:`hapsim.emulated.haply_firmware.
    CommandDecoder`) after its arming and 1-200 host writes of random torques, each byte
    lost with probability ``loss`` (seeded): the states a host may stall in. Yields
    (decoder, a function feeding bytes and returning the torque motor 1 holds)."""
    import random

    from hapsim.drivers.haply import DEFAULT_ID, write_packet
    from hapsim.emulated.haply_firmware import CommandDecoder
    drv = get_driver("haply")
    for seed in range(n_states):
        rng = random.Random(seed)
        dec = CommandDecoder(absent=255)
        held = [0.0]

        def feed(b, dec=dec, held=held):
            for c in dec.commands(b):
                if c[0] == "write" and 0 in c[2]:
                    held[0] = c[2][0]
            return held[0]
        feed(drv.arm())
        for _ in range(1 + seed % 200):
            w = write_packet(DEFAULT_ID, rng.uniform(-0.12, 0.12))
            feed(bytes(b for b in w if rng.random() >= loss))
        yield dec, feed


def test_the_robust_write_zeroes_a_board_whatever_its_parser_lost():
    """Over 3,000 parser states a lossy link leaves the M3 board in: the zero command
    leaves a torque held in some (the motor's address lost to a reset read out of a
    torque's bytes: no write reaches it; 300 of 20,000 states measured, 1.5 %), the
    watchdog's robust write (the driver's stop at the host's last angle, the angle
    patched in as the watchdog does) zeroes the torque, sets the motor up again and
    the encoder at that angle, in every one."""
    from hapsim.drivers.host_watchdog import robust_stop
    data, at = robust_stop(get_driver("haply"))
    angle = struct.pack("<f", 12.5)
    robust = data[:at] + angle + data[at + 4:]
    zero = get_driver("haply").encode_force(0.0)
    held_by_zero = 0
    for dec, feed in _lossy_parser_states(3000):
        snapshot = (bytes(dec._buf), list(dec.motor_addr), list(dec.encoder_addr),
                    dict(dec.stats))
        held_by_zero += feed(zero) != 0.0
        dec._buf[:], dec.motor_addr, dec.encoder_addr = (snapshot[0], snapshot[1],
                                                         snapshot[2])
        assert feed(robust) == 0.0
        assert dec.motor_addr[0] != 0 and dec.encoder_offset[0] == 12.5, snapshot
    assert held_by_zero > 0          # (the class the robust write exists for)


def test_a_suspect_board_gets_the_robust_write_with_the_hosts_angle():
    """On a bare pty: the host says the board may have lost its place, with its last
    angle: the silence's write is the robust one, that angle in it, counted as robust
    (taken by the host once); a host that says it is in step gets the zero command."""
    from hapsim.drivers.host_watchdog import robust_stop
    master, slave = pty.openpty()
    tty.setraw(slave)
    data, at = robust_stop(get_driver("haply"))
    with pytest.raises(ValueError, match="index"):
        tw.TorqueWatchdog(os.ttyname(slave), b"ZERO", HOLD_BOUND_S, robust=(b"abc", 0))
    wd = tw.TorqueWatchdog(os.ttyname(slave), b"ZERO", HOLD_BOUND_S, robust=(data, at))

    class Port:
        def write(self, b):
            os.write(slave, b)
    try:
        wd.arm()
        wd.suspect(True, 12.5)
        wd.write(Port(), b"HOST", True)
        _silent(wd)
        want = data[:at] + struct.pack("<f", 12.5) + data[at + 4:]
        assert _read_all(master) == b"HOST" + want
        assert len(wd.take()) == 1 and wd.take_robust() == (1, 12.5)
        assert wd.take_robust()[0] == 0
        wd.suspect(False)
        wd.write(Port(), b"HOST", True)
        _silent(wd)
        assert _read_all(master) == b"HOST" + b"ZERO"
        assert len(wd.take()) == 1 and wd.take_robust()[0] == 0
        assert wd.report()["robust"] == 1 and wd.report()["fired"] == 2
    finally:
        wd.close()
        os.close(slave)
        os.close(master)


class _Frames:
    """A reply decoder's reach stand-in: 100 deg/s^2 times tau^2 [deg]."""

    def reach_deg(self, k, tau):
        return 100.0 * tau * tau


class _WD:
    """The host's view of a watchdog that made ``robust`` robust writes at ``value`` deg."""

    def __init__(self, robust, value):
        self.pending, self.value, self.said = robust, value, []

    def take_robust(self):
        n, self.pending = self.pending, 0
        return n, self.value

    def suspect(self, on, value=0.0):
        self.said.append((on, value))

    def angle(self, value):
        self.said.append(("angle", value))


def _transport(robust=0, value=30.0):
    """The transport's watchdog accounting (Watched, Resynchronising) on a stand-in
    state: commands 1-10 sent 1 ms apart from t = 1 s, 1-9 answered, the last two
    records at commands 8 and 9 (0.49 and 0.5 rad)."""
    from hapsim.drivers.host_watchdog import Watched
    from hapsim.drivers.resync import RING, Resynchronising

    class T(Watched, Resynchronising):
        def _clock(self):
            return 5.0

        def _now_us(self):
            return 5_000_000                 # the host takes the writes 4 s later

        def _extrapolate(self, seq):
            v = (self._x_last - self._x_prev) / (self._s_last - self._s_prev)
            return self._x_last + v * (seq - self._s_last)

    t = T()
    t.stats = {"watchdog_zeroed": 0, "missing": 0}
    t._init_resync()
    t.watchdog, t._wd_cmds, t._wd_robust, t._wd_suspect = _WD(robust, value), set(), True, False
    t._wd_angle_s, t._wd_lossy, t._damaged, t._desyncs = -1, False, 0, 0
    t._wd_base = None
    t._sent_us = [0] * RING
    t._sent_bytes, t._wd_zero = [b""] * RING, b"ZERO"
    for c in range(1, 11):
        t._sent_us[c] = 1_000_000 + 1000 * c
    t._t0, t._cmd, t._answered, t._floor, t._force = 0, 10, 9, 9, 0.1
    t._x_prev, t._s_prev, t._x_last, t._s_last = 0.49, 8, 0.5, 9
    t._frames, t._anchor_us = _Frames(), 0
    return t


class _BarePort:
    """A watchdog on a bare pty, armed, with the host's port (``write``) and the master
    the test reads (``with _BarePort() as (wd, port, master)``)."""

    def __enter__(self):
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)
        self.wd = tw.TorqueWatchdog(os.ttyname(self.slave), b"ZERO", HOLD_BOUND_S)
        self.wd.arm()
        return self.wd, self, self.master

    def write(self, b: bytes) -> None:
        os.write(self.slave, b)

    def __exit__(self, *exc) -> None:
        self.wd.close()
        os.close(self.slave)
        os.close(self.master)


def test_a_host_stopped_after_its_stamp_is_counted_from_its_last_bytes():
    """A host that wrote a force, ran 0.9 bound without writing, then stamped its next
    write and stopped before the bytes, for five bounds: the board holds the force of
    the last bytes, so the silence the watchdog answers and states (``longest_s``) runs
    from that write's start, not from the stamp. (Before, it ran from the stamp: a
    Hapkit held a force 120 ms against a stated 62, the stamp 58 ms after the bytes,
    beside two SCHED_FIFO 50 busy loops.)"""
    with _BarePort() as (wd, port, master):
        t_bytes = time.monotonic_ns()
        wd.write(port, b"HOST", True)       # a force, written whole
        time.sleep(0.9 * HOLD_BOUND_S)      # in time, no write yet
        # the next write's stamp; a loaded machine's test thread may wake past the
        # bound, and the watchdog's write then went before the stamp (taken here: the
        # host's own beat takes it so). The write owed is then made, once: the silence
        # owes no second (once in a fresh clone's CI: _silent waited its 2 s for a
        # write already taken, and take() had none)
        early = wd.beat()
        wd.hold(True)
        _silent(wd, owed=not early)         # stopped before its bytes
        got = early + wd.take()
        assert _read_all(master) == b"HOST" + b"ZERO" and len(got) == 1, got
        # (the watchdog's write counted before it was made: within its stated silence)
        assert got[0] - t_bytes <= wd.report()["longest_s"] * 1e9, (
            (got[0] - t_bytes) * 1e-9, wd.report())


def test_a_host_stopped_before_its_bytes_then_again_gets_a_write_each_time():
    """A host stopped between its write's stamp and its bytes for five bounds (the
    watchdog writes the zero command in that silence), which then writes its stale
    force and is stopped again at once for five bounds: the second silence gets a write
    of its own. Before, the silence was counted from the first stamp alone, already
    answered: an independent M3 board model held that force through the whole second
    stop (50 ms, tools/independent_boards)."""
    with _BarePort() as (wd, port, master):
        wd.beat()                           # (the first half of the host's write)
        wd.hold(True)
        _silent(wd)                         # stopped before its bytes
        began = time.monotonic_ns()
        port.write(b"HOST")                 # its stale force, when it runs again
        wd.hold(True, began)                # (the second half: from the write's start)
        _silent(wd)                         # stopped again at once
        assert _read_all(master) == b"ZERO" + b"HOST" + b"ZERO"
        assert len(wd.take()) == 2


def test_the_hosts_account_of_a_robust_write_is_its_own_resync():
    """A robust write taken (made 20 ms after the host's last command, taken 4 s later):
    two command numbers (its zero writes around the set-up) whose answers are dropped,
    the host's unanswered command missing, a re-synchronisation counted ("watchdog"),
    the frame's bound the reach up to the write (not to the take) plus the angle written
    against the estimate; two robust writes in one take: four numbers, the host's
    commands alone made missing; a plain write: one number, no re-synchronisation."""
    import math as m
    t = _transport(robust=1, value=30.0)
    t_ns = (1_010_000 + 20_000) * 1000              # 20 ms after command 10
    t._wd_take((t_ns,))
    assert t._cmd == 12 and t._wd_cmds == {11, 12}
    assert t.stats["resyncs"] == 1 and t.stats["resync_reasons"]["watchdog"] == 1
    assert t._answered == 10 and t.stats["missing"] == 1 and t._floor == 9
    from hapsim.drivers.resync import RESYNC_GAP_S
    tau = (t_ns // 1000 - t._sent_us[9]) * 1e-6 + RESYNC_GAP_S
    x_est = 0.5 + 0.01 * 2                         # command 11 extrapolated
    # the reach to the write, the estimate's steps ahead of the last record (counted
    # from the command after the first number, one step conservative), the angle
    # written against the estimate
    want = m.radians(100.0 * tau * tau) + (11 + 1 - 9 - 1) * 0.01 + abs(m.radians(30.0) - x_est)
    # (derived: a few roundings of quantities of order 1)
    assert t.stats["frame_bound"] == pytest.approx(want, rel=1e-12)
    assert t.stats["frame_bound"] < m.radians(100.0 * 4.0 ** 2)   # not to the take
    assert t.watchdog.said[-1][0] is False          # the next write: the zero command
    two = _transport(robust=2)
    two._wd_take((t_ns, t_ns))
    assert two._cmd == 14 and two._wd_cmds == {11, 12, 13, 14}
    assert two._answered == 10 and two.stats["missing"] == 1 and two.stats["resyncs"] == 2
    plain = _transport(robust=0)
    plain._wd_take((t_ns,))
    assert plain._cmd == 11 and plain._wd_cmds == {11} and plain.stats["resyncs"] == 0
    assert plain._answered == 9 and plain.stats["missing"] == 0


def test_the_host_suspects_a_board_on_bytes_that_made_no_record():
    """The watchdog is told the board may have lost its place as soon as bytes read since
    the last record made none (with the last angle), and that it no longer is when a
    record comes; only on a change; never before a record gave an angle. Once the link
    has shown it loses bytes (a desync, a damaged reply: not bytes that made no record
    alone, a reply split across two reads), the last angle is published once per new
    record (a long silence's robust write carries it); before, none is."""
    t = _transport()
    said = t.watchdog.said
    t._wd_note()                          # in step, no byte lost: nothing to say
    assert said == []
    t._rx_since_record = 3
    t._wd_note()                          # (the same value, exactly)
    assert said == [(True, math.degrees(0.5))]
    t._desyncs = 1                        # (the decoder's: the link loses bytes)
    t._wd_note()
    assert said[1:] == [("angle", math.degrees(0.5))]
    t._wd_note()
    assert len(said) == 2                 # (a change only)
    t._rx_since_record = 0
    t._x_last, t._s_last = 0.75, 10
    t._wd_note()                          # a new record: its angle, then in step
    assert said[2:] == [("angle", math.degrees(0.75)), (False, math.degrees(0.75))]
    t._wd_note()
    assert len(said) == 4                 # (the same record: nothing new)
    t._s_last, t._rx_since_record = -1, 5
    t._wd_note()                          # no record yet: no angle to set up at
    assert len(said) == 4
    clean = _transport()
    clean._x_last, clean._s_last = 0.75, 10
    clean._wd_note()                      # a new record on a link that lost nothing
    assert clean.watchdog.said == []
    clean._damaged = 1                    # a damaged reply: the link loses bytes
    clean._wd_note()
    assert clean.watchdog.said == [("angle", math.degrees(0.75))]


def _fill(fd: int) -> int:
    """Fill a non-blocking pty's buffer until it takes not one byte more [bytes written].
    The kernel moves a pty's bytes to the reading side's buffer in a work item of its
    own, so a buffer that refused a write may take more a moment later (once, 61 bytes
    after a refused 4 kB write: this test's full buffer took the whole command): full
    only when a single byte is refused after that work has had its time, twice."""
    n, refused = 0, 0
    while refused < 2:
        try:
            n += os.write(fd, b"\0" * (4096 if not refused else 1))
            refused = 0
        except BlockingIOError:
            refused += 1
            time.sleep(0.02)
    return n


def test_a_write_goes_out_whole_or_not_at_all():
    """The watchdog's write to a port opened by path (non-blocking: a hung device never
    holds it): a full buffer refuses the whole write (counted, tried again), and a
    buffer with room for part of it gets the rest as it drains, never a command cut
    short (which would leave the board's parser inside it)."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    fd = os.open(os.ttyname(slave), os.O_WRONLY | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        filler = _fill(fd)
        try:                              # (refused: the buffer is full, _fill)
            tw._write_whole(fd, b"X" * 61)
            x = b"X" * 61                 # (the kernel made room after all: all of it)
        except BlockingIOError:
            x = b""
        got = bytearray()

        def drain():
            time.sleep(0.05)
            while len(got) < filler + len(x) + 61:
                got.extend(os.read(master, 65536))
        import threading
        th = threading.Thread(target=drain)
        th.start()
        tw._write_whole(fd, b"Y" * 61, patience=1.0)     # waits, then all of it
        th.join(5.0)
        assert bytes(got[filler:]) == x + b"Y" * 61 and got.count(b"X") == len(x)
    finally:
        os.close(fd)
        os.close(slave)
        os.close(master)


def test_a_write_the_port_took_part_of_is_finished_before_anything_else(monkeypatch,
                                                                        tmp_path):
    """The watchdog's loop (in a thread here) against a port that takes two bytes of its
    zero command and then no more for longer than :data:`~hapsim.drivers.
    torque_watchdog.REST_S`: the rest is kept and finished at the next checks, first
    (refused once, then taken), and the command is never written again from its start
    (which would leave the board's parser inside the first copy: the host's writes
    after it read wrongly); one write counted. Before, a write cut short was an error,
    counted, and the next check wrote the whole command again."""
    import threading
    calls = []

    def writer(port):
        def write(data, patience=0.0):
            calls.append(bytes(data))
            if len(calls) == 1:
                return bytes(data[2:])              # (two bytes taken, the rest stuck)
            if len(calls) == 2:
                raise BlockingIOError               # (still no room)
            return b""
        return write
    monkeypatch.setattr(tw, "_writer", writer)
    path = tmp_path / "page"
    path.write_bytes(b"\0" * tw._SIZE)
    page = tw._Page(os.open(path, os.O_RDWR))
    page.set("beat", time.monotonic_ns() - 10**9)  # (a host silent for 1 s)
    page.set("armed", 1)
    page.set("holding", 1)
    stop: list = []
    th = threading.Thread(target=tw._serve, args=(str(path), "fake", b"ZERO",
                                                  int(HOLD_BOUND_S * 1e9), os.getppid(),
                                                  0), kwargs={"stop": stop})
    th.start()
    end = time.monotonic() + 5.0
    while len(calls) < 3 and time.monotonic() < end:
        time.sleep(0.005)
    time.sleep(5 * HOLD_BOUND_S)                   # (time for a wrong second write)
    stop.append(1)
    th.join(5.0)
    os.close(page.fd)
    assert calls == [b"ZERO", b"RO", b"RO"], calls
    assert page.get("counts") >> 32 == 1 and page.get("failed") == 0


@pytest.mark.parametrize("with_watchdog", [True, False])
def test_the_direction_probe_has_the_watchdog_beside_it(with_watchdog, monkeypatch):
    """identify's direction probe on the M3 (its torque pulses on the board's own clock,
    :func:`hapsim.drivers.haply_probe.probe_port`), the host silent for five bounds in
    the middle of its first pulse: the host's watchdog zeroes the pulse within the
    stated bound, its write answered and read as a late reply, and the probe still finds
    the direction; without it the board holds the pulse the whole silence (the control:
    before, the probe had none, and an identify over a lossy M3 held a torque 54 ms)."""
    from hapsim.drivers.exchange import Exchange
    from hapsim.drivers.haply_probe import probe_port
    if not with_watchdog:
        monkeypatch.setattr(tw, "start_watchdog", lambda *a, **k: (None, "off for the test"))
    reports = []                            # (the probe's watchdog's, at its close)
    close = tw.TorqueWatchdog.close
    monkeypatch.setattr(tw.TorqueWatchdog, "close",
                        lambda self: (close(self), reports.append(self.report())))
    reply = Exchange.reply
    zero = get_driver("haply").encode_force(0.0)
    state = {"done": False}

    def silent_once(self, data):
        if not state["done"] and not data.endswith(zero):
            state["done"] = True
            self.link.write(data)           # (the pulse's first write goes out)
            time.sleep(SILENCE_S)           # then the host does not run
        return reply(self, data)
    monkeypatch.setattr(Exchange, "reply", silent_once)
    board, drv, _ = _board("haply")
    path, flag, th = _link_device(board)
    try:
        found = probe_port(drv, path, force_limit=0.05, envelope=0.5, rate_hz=1000.0)
    finally:
        _stop_link(flag, th)
    rep = flag["report"]
    assert state["done"] and found.motor_direction in (0, 1)
    if with_watchdog:
        # the stated bound (the watchdog's own measured silence when longer) and 1 ms,
        # as in the tests above
        assert reports and reports[-1]["fired"] >= 1, reports
        assert rep["longest_hold_s"] <= _stated(reports[-1]) + 1e-3, (
            rep["longest_hold_s"], reports)
    else:
        # the whole silence (the writes taken at their kernel stamps, _link_device)
        assert rep["longest_hold_s"] >= SILENCE_S, rep


@pytest.mark.parametrize("name", ["haply", "hapkit-serial", "firefader"])
def test_a_zero_write_just_before_the_stop_is_answered_as_the_watchdogs(name):
    """The host silent past the hold bound between its last FORCE and its STOP (a stall
    there, once in a fresh clone's CI): the watchdog's zero write is taken at the stop and
    its answer read before the stop's own probe and bytes
    (:meth:`hapsim.drivers.host_watchdog.Watched._wd_stop`), so every zero write the
    watchdog made is counted as answered; before, the last one's answer went to the
    Hapkit's tick probe or unread (fired 2, answered 1). A run whose emulated board was
    itself late by more than the host's wait (``STOP_WAIT_S``: the board's answer may
    come after it, as no board on its own processor is) is made again, at most three
    runs (the host late past the wait is the next test's)."""
    from hapsim.drivers.host_watchdog import STOP_WAIT_S
    late = []
    for _ in range(3):
        rep, board, after = _run(name, 0.0, before_stop_s=3 * HOLD_BOUND_S)
        gap = float((board or {}).get("longest_gap_s") or 0.0)
        if gap < STOP_WAIT_S:
            break
        late.append(f"{gap * 1e3:.0f} ms")
    else:
        pytest.fail(f"the emulated board was late by the host's wait or more in every run "
                    f"({', '.join(late)}): the machine's load, not the stop")
    wd = rep["watchdog"]
    info = (name, wd, {k: rep[k] for k in ("watchdog_zeroed", "watchdog_replies", "resyncs")})
    assert wd["running"] and wd["fired"] >= 1, info
    assert rep["watchdog_zeroed"] == rep["watchdog_replies"] == wd["fired"], info


@pytest.mark.parametrize("name", ["haply", "hapkit-serial", "firefader"])
def test_a_host_descheduled_past_the_stops_wait_still_reads_the_watchdogs_answer(
        name, monkeypatch):
    """What the test above leaves to the scheduler, made every time: the host is back
    from a stall only when its wait at the stop for the watchdog's answers is over
    (``STOP_WAIT_S`` set below the board's round trip: the wait ends before it begins),
    the answers already in the port. The stop reads what has arrived all the same, so
    every zero write is counted as answered; before, the loop's deadline ended it unread
    (once in a fresh clone's CI, the Hapkit sketch's: fired 3, answered 2)."""
    from hapsim.drivers import host_watchdog as hw
    monkeypatch.setattr(hw, "STOP_WAIT_S", -1.0)
    rep, board, after = _run(name, 0.0, before_stop_s=3 * HOLD_BOUND_S)
    wd = rep["watchdog"]
    info = (name, wd, {k: rep[k] for k in ("watchdog_zeroed", "watchdog_replies", "resyncs")})
    assert wd["running"] and wd["fired"] >= 1, info
    assert rep["watchdog_zeroed"] == rep["watchdog_replies"] == wd["fired"], info


def _burst(seconds: float, seed: int) -> None:
    """A real-time load for the figures below: ``SCHED_FIFO`` 50 (above the boards, the
    watchdog and every host loop), busy 5-60 ms, asleep 20-100 ms, for ``seconds``."""
    import random
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
    rng, end = random.Random(seed), time.monotonic() + seconds
    while time.monotonic() < end:
        t = time.monotonic() + rng.uniform(0.005, 0.06)
        while time.monotonic() < t:
            pass
        time.sleep(rng.uniform(0.02, 0.1))


if __name__ == "__main__":
    # the figures docs/drivers.md quotes ("The stated bound"): ``runs`` random silences
    # (0-100 ms) of each board, the longest hold against the stated bound plus a period
    # [ms], beside ``bursts`` real-time loads (_burst, as root) and ``hogs`` CPU-bound
    # processes (PYTHONPATH=. python tests/test_host_watchdog.py [runs] [bursts] [hogs])
    import multiprocessing

    import numpy as np
    args = [int(a) for a in sys.argv[1:4]]
    runs, bursts, hogs = args + [20, 0, 0][len(args):]
    rt = [multiprocessing.Process(target=_burst, args=(3600.0, i), daemon=True)
          for i in range(bursts)]
    for p in rt:
        p.start()
    busy = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(hogs)]
    try:
        print(f"load {os.getloadavg()[0]:.1f}, {os.cpu_count()} CPUs, {bursts} bursts, "
              f"{hogs} hogs")
        for name in ("haply", "hapkit-serial", "firefader"):
            rng, past, worst, late = np.random.default_rng(7), 0, -math.inf, 0.0
            for _ in range(runs):
                rep, board, _ = _run(name, float(rng.uniform(0.0, 5 * HOLD_BOUND_S)),
                                     at=int(rng.integers(20, 60)), force=0.05, seed=1)
                over = board["longest_hold_s"] - _stated(rep["watchdog"]) - (
                    1e-3 if name == "haply" else 4e-3)
                past += over > 1e-3
                worst, late = max(worst, over), max(late, board["longest_gap_s"])
            print(f"{name:14s} {runs} runs: hold past stated + period by at most "
                  f"{worst * 1e3:+.1f} ms, {past} past it by more than 1 ms; the board "
                  f"thread up to {late * 1e3:.1f} ms late")
    finally:
        for p in rt + busy:
            p.kill()
