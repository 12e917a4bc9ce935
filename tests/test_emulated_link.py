"""The emulated link (``emulated://NAME``): the host's end is a serial port as pyserial's
(hapsim.drivers.urlhandler), and the emulated board takes each host write at the time the
kernel stamped it with, whatever its own process's lateness (hapsim.emulated.stamped_link).

Over a pty the emulated board took the host's bytes when its process read them: on a
virtual machine that halts its idle CPUs, 0.3 ms late at the median and 1-2 ms at the 99th
percentile, and the Hapkit sketch's emulation took 10-65 % of the commands at another tick
than the period's (the board's ``tick_arrivals.off_period``), which no board on its own
processor does.
"""

from __future__ import annotations

import os
import pty
import socket
import threading
import time
import tty
from types import SimpleNamespace

import pytest
import serial

from hapsim.drivers.urlhandler import is_emulated, serial_for_url
from hapsim.emulated.driver_mock import serve
from hapsim.emulated.stamped_link import StampedReader, accept
from hapsim.spawn import PtyChild

#: How far a stamp moved to the monotonic clock may be from the write's own time [s]: the
#: real-time clock slewed by NTP runs at most 500 ppm off the monotonic one (adjtimex's
#: largest frequency offset), over the test's longest wait between a write and its read
#: (0.1 s): 50 us; a bound, not a measurement.
SLEW_BOUND_S = 500e-6 * 0.1


def _listener():
    """A listening link as an embedded mock makes it (PtyChild.open_link): its socket and
    URL (the report file PtyChild also names is left out)."""
    child = PtyChild()
    fd = child.open_link("hapsim-test-link-")
    child.close()                       # (no child: only its stop token and report name)
    return socket.socket(fileno=fd), child.port


def test_the_port_is_a_serial_port_over_packets():
    """Writes arrive whole as packets (a long one cut at 4096 bytes), reads are a stream
    with pyserial's timeouts, in_waiting counts what came, reset_input_buffer drops it, and
    a closed board end is a read error, not an endless wait."""
    lst, url = _listener()
    assert is_emulated(url) and not is_emulated("/dev/ttyACM0")
    ser = serial_for_url(url, baudrate=57600, timeout=0, write_timeout=1.0)
    conn = accept(lst)
    reader = StampedReader(conn)
    assert ser.write(b"\x11\xff" + bytes(8)) == 10
    long = bytes(range(256)) * 40                                  # 10,240 bytes
    ser.write(long)
    time.sleep(0.01)
    got = reader.read()
    assert [len(d) for d, _ in got] == [10, 4096, 4096, 2048]
    assert b"".join(d for d, _ in got[1:]) == long
    assert reader.stamped == 4 and reader.unstamped == 0
    assert ser.read(5) == b"" and ser.in_waiting == 0
    conn.send(b"abc")
    conn.send(b"defg")
    time.sleep(0.01)
    assert ser.in_waiting == 7
    assert ser.read(5) == b"abcde" and ser.read(10) == b"fg"
    ser.timeout = 0.05
    t = time.monotonic()
    assert ser.read(1) == b""
    assert time.monotonic() - t >= 0.05
    conn.send(b"xyz")
    time.sleep(0.01)
    ser.reset_input_buffer()
    assert ser.in_waiting == 0
    conn.close()
    with pytest.raises(serial.SerialException, match="closed its link"):
        ser.read(1)
    ser.close()
    lst.close()


def test_a_bad_or_absent_link_is_refused_with_its_name():
    with pytest.raises(serial.SerialException, match="emulated://NAME"):
        serial_for_url("emulated://", timeout=0)
    with pytest.raises(serial.SerialException, match="could not open port"):
        serial_for_url(f"emulated://hapsim-nobody-{os.getpid()}", timeout=0)


class _Recorder:
    """A board that records when each host write was taken (serve's ``now``) and is busy
    ``busy_s`` in its first read: its process late, as a loaded machine makes it."""

    clock = "wall"
    reply_delay_s = 0.0
    clamped = 0
    held = 0.0
    last_command = 0.0

    def __init__(self, busy_s: float, reply: bytes = b"") -> None:
        self.busy_s = busy_s
        self.reply = reply
        self.fed = []
        self.decoder = SimpleNamespace(stats={})

    def feed(self, data, now, writes=None):
        self.fed.append((bytes(data), now))
        if len(self.fed) == 1:
            time.sleep(self.busy_s)
        return self.reply

    def idle(self, silent_s):
        return b""

    def commands(self):
        return len(self.fed)

    def settles_on(self):
        return 0.0


def _host_writes(write, n: int = 12, gap_s: float = 0.003) -> list:
    """``n`` 10-byte writes ``gap_s`` apart: each one's bytes and the monotonic times just
    before and after its call."""
    out = []
    for i in range(n):
        data = bytes([0x11, i]) + bytes(8)
        t0 = time.monotonic()
        write(data)
        out.append((data, t0, time.monotonic()))
        time.sleep(gap_s)
    return out


def _serve_in_thread(fd, dev, stamped=None, faults=None):
    done = {}
    th = threading.Thread(target=lambda: done.setdefault(
        "rep", serve(fd, dev, stamped=stamped, poll=0.01, faults=faults)), daemon=True)
    th.start()
    return th, done


def test_the_board_takes_each_write_at_its_time_whatever_its_lateness():
    """The board's process busy for 40 ms in its first read while the host writes a command
    every 3 ms: over the emulated link the intervals between the commands' takings are the
    writes' own, to the time a write's call takes (the stamp falls inside it) and the
    clocks' slew; over a pty, the control, the commands written meanwhile were taken
    together when the process read them, 3 ms apart written and none apart taken."""
    lst, url = _listener()
    ser = serial_for_url(url, timeout=0, write_timeout=1.0)
    conn = accept(lst)
    dev = _Recorder(busy_s=0.04)
    th, done = _serve_in_thread(conn.fileno(), dev, stamped=StampedReader(conn))
    writes = _host_writes(ser.write)
    time.sleep(0.02)
    ser.close()
    th.join(5)
    assert not th.is_alive() and done["rep"]["link"] == {"stamped": 12, "unstamped": 0}
    assert [d for d, _ in dev.fed] == [d for d, _, _ in writes]
    bound = max(t1 - t0 for _, t0, t1 in writes) + SLEW_BOUND_S
    taken = [t for _, t in dev.fed]
    written = [t0 for _, t0, _ in writes]
    for a, b, wa, wb in zip(taken, taken[1:], written, written[1:]):
        # the stamp lies within its write's call: a bound, derived above
        assert abs((b - a) - (wb - wa)) <= bound, (b - a, wb - wa, bound)
    lst.close()

    # the control: the same board on a pty takes the writes when its process reads them
    master, slave = pty.openpty()
    tty.setraw(slave)
    dev_pty = _Recorder(busy_s=0.04)
    th, done = _serve_in_thread(master, dev_pty)
    writes = _host_writes(lambda b: os.write(slave, b))
    time.sleep(0.02)
    os.close(slave)
    th.join(5)
    os.close(master)
    took = {}
    for data, t in dev_pty.fed:
        for i in range(0, len(data), 10):
            took.setdefault(data[i + 1], t)
    gaps = [took[b[1]] - took[a[1]] for (a, _, _), (b, _, _) in zip(writes, writes[1:])]
    assert min(gaps) == 0.0, gaps       # (the class the emulated link removes)


def test_a_starved_board_reads_nothing_during_its_silence_on_the_link_too():
    """serve's ``slow`` hook (a board process starved 0.2 s after each answer: nothing read
    meanwhile) keeps its meaning on the emulated link: the writes that came during a
    silence are taken together at its end, not at their stamps (tools/driver_timing.py
    --starve, the host's silences rule).

    The host writes its first command alone and the others once the board has taken it
    (a loaded machine may otherwise run the board's thread late enough to read two writes
    at once, both then taken at their stamps before the silence: CI saw it once). What
    came when is then told from the writes' own times, whatever the load."""
    lst, url = _listener()
    ser = serial_for_url(url, timeout=0, write_timeout=1.0)
    conn = accept(lst)
    dev = _Recorder(busy_s=0.0, reply=b"r")
    silence = 0.2
    th, done = _serve_in_thread(conn.fileno(), dev, stamped=StampedReader(conn),
                                faults={"slow": 1.0, "slow_s": silence})
    first = _host_writes(ser.write, n=1, gap_s=0.0)
    t_end = time.monotonic() + 5.0
    while not dev.fed and time.monotonic() < t_end:
        time.sleep(0.0005)
    taken_at = time.monotonic()             # the board's silence starts after this
    assert dev.fed, "the board never took the first write"
    writes = first + _host_writes(ser.write, n=11, gap_s=0.003)
    time.sleep(2 * silence + 0.1)
    ser.close()
    th.join(5)
    assert not th.is_alive() and done["rep"]["starved"]["silences"] >= 2
    taken = [t for _, t in dev.fed]
    assert [d for d, _ in dev.fed] == [d for d, _, _ in writes]
    # (the board's times count from its own start: moved to the host's clock by the first
    # write, whose stamp lies within its call: to that call's length and the clocks' slew)
    shift = taken[0] - writes[0][1]
    tol = writes[0][2] - writes[0][1] + SLEW_BOUND_S
    # its answer's silence ends at least `silence` after the first was taken (a sleep
    # never ends early; it starts after the board took the write): every write whose
    # call ended before that was read at the silence's end, all at one time
    end = taken[1]
    assert end - taken[0] >= silence, taken[:2]
    during = [i for i, (_, _, t1) in enumerate(writes[1:], 1) if t1 + tol < end - shift]
    assert during and during[0] == 1, (writes[1], end - shift)   # (the host wrote at once)
    assert all(taken[i] == end for i in during), taken
    # and none was taken before its write
    assert all(taken[i] - shift >= writes[i][1] - tol for i in range(len(writes))), taken
    lst.close()
