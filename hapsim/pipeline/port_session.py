"""The session side of a 2-D or 3-D measurement over a port
(:func:`hapsim.pipeline.felt_port.measure_felt_port`): the device's HELLO asked and
checked (and its compact frames), the device brought to silence between records, the
port opened again after a loss, and the name of a requested stop. Each waits on the
transport's own clock (a virtual clock's in :class:`hapsim.emulated.links.SimTransport`).
"""

from __future__ import annotations

import time

import firmware_protocol as fp
from hapsim.errors import DeviceError, ProtocolError
from hapsim.host.loop_types import SENSORS_TRIES, SENSORS_WAIT, signame

__all__ = ["clock_of", "handshake_nd", "drain", "quiesce", "reopen_port", "stop_reason"]


def clock_of(transport):
    """The transport's clock and its sleep.

    Parameters
    ----------
    transport : transport of :mod:`hapsim.host.transport`

    Returns
    -------
    (callable, callable)
        ``clock()`` [s] of a virtual-clock transport (its ``clock``), else
        :func:`time.monotonic`; ``sleep(s)``: its ``sleep``, else :func:`time.sleep`.
    """
    return (getattr(transport, "clock", time.monotonic),
            getattr(transport, "sleep", time.sleep))


def handshake_nd(transport, n: int, timeout: float = 1.0,
                 compact_rate: float | None = None) -> fp.Hello:
    """Ask the device's HELLO and check it speaks version 1 with ``n`` axes; then, when
    ``compact_rate`` is given, the device applies its forces in steps (HELLO
    ``force_scale > 0``) and the transport can (``set_compact``), ask for the compact
    frames (SENSORS_REQUEST bit COMPACT, ``PROTOCOL.md`` §4 "Compact frames", as the 1-D
    host does for such a device: :mod:`hapsim.host.handshake`).

    A device that offers them (the Hapkit pantograph's leader) then sends STATE_COMPACT and
    takes FORCE_COMPACT: 32 bytes a tick on the wire instead of 64 and no binary64 codec on
    its 8-bit chip, which leaves the host ~4,000 cycles more of the 1 kHz period
    (``docs/pantograph.md``). A device that does not answer within ``SENSORS_TRIES *
    SENSORS_WAIT``, or leaves the bit out, keeps the full frames.

    Parameters
    ----------
    transport : transport of :mod:`hapsim.host.transport`
    n : int
        Axes the scene has.
    timeout : float
        Wait per request [s] (3 requests), on the transport's clock.
    compact_rate : float, optional
        The session's tick rate [Hz] (the compact STATE's time is ``seq / rate``); None:
        full frames.

    Returns
    -------
    firmware_protocol.Hello

    Raises
    ------
    DeviceError
        No HELLO after 3 requests; the port failed.
    ProtocolError
        Another protocol version or another number of axes.
    """
    clock, _ = clock_of(transport)
    for _ in range(3):
        transport.send(fp.HelloRequest(fp.PROTOCOL_VERSION))
        end = clock() + timeout
        while clock() < end:
            for m in transport.receive(0.02):
                if isinstance(m, fp.Hello):
                    if m.protocol_version != fp.PROTOCOL_VERSION:
                        raise ProtocolError(f"device speaks protocol version "
                                            f"{m.protocol_version}, hapsim "
                                            f"{fp.PROTOCOL_VERSION}")
                    if m.n_axes != n:
                        raise ProtocolError(f"device has {m.n_axes} axes, the scene "
                                            f"{n} (dimension)")
                    _ask_compact(transport, m, compact_rate)
                    return m
    raise DeviceError("no HELLO from the device after 3 requests\nlast frames:\n"
                      + transport.last_frames())


def _ask_compact(transport, hello, rate: float | None) -> bool:
    """The compact frames asked of a device that applies its forces in steps (module
    notes of :func:`handshake_nd`); True when the session uses them."""
    set_compact = getattr(transport, "set_compact", None)
    if set_compact is None:
        return False
    set_compact(None)                           # full frames until the device says so
    if rate is None or not hello.force_scale > 0:
        return False
    clock, _ = clock_of(transport)
    for _ in range(SENSORS_TRIES):
        transport.send(fp.SensorsRequest(fp.FEATURE_COMPACT))
        end = clock() + SENSORS_WAIT
        while clock() < end:
            for m in transport.receive(0.02):
                if type(m) is fp.Sensors:
                    if m.enabled & fp.FEATURE_COMPACT:
                        set_compact(float(rate))
                        return True
                    return False
    return False


def drain(transport, quiet: float = 0.03, limit: float = 1.0, counts=None) -> bool:
    """Read and drop until nothing but disarmed STATEs came for ``quiet`` seconds (at most
    ``limit``), on the transport's clock: a device sends STATE every tick, armed or not
    (``PROTOCOL.md`` §5.1: the Hapkit firmware does), so a disarmed device is never
    silent.

    Parameters
    ----------
    transport : transport of :mod:`hapsim.host.transport`
    quiet, limit : float
        [s].
    counts : object, optional
        Its ``hellos`` counts the HELLOs read (the device restarted its hand's cycle).

    Returns
    -------
    bool
        True when it went quiet, False when armed frames kept coming.

    Raises
    ------
    DeviceError
        The port failed.
    """
    clock, _ = clock_of(transport)
    now = clock()
    end = now + limit
    last = now
    while now < end:
        for m in transport.receive(quiet):
            if not (isinstance(m, fp.State) and not m.status & fp.STATUS_ARMED):
                last = clock()
            if counts is not None and isinstance(m, fp.Hello):
                counts.hellos += 1              # the device (re)started its hand's cycle
        now = clock()
        if now - last >= quiet:
            return True
    return False


def quiesce(transport, tries: int = 4, counts=None) -> bool:
    """STOP until the device falls silent (a STOP lost or a CONFIG held back by the link
    can leave it armed, ticking a session the host does not want).

    Parameters
    ----------
    transport : transport of :mod:`hapsim.host.transport`
    tries : int
        STOPs sent at most, each followed by :func:`drain` (0.3 s at most).
    counts : object, optional
        As :func:`drain`'s.

    Returns
    -------
    bool
        True when the device fell silent.

    Raises
    ------
    DeviceError
        The port failed.
    """
    for _ in range(tries):
        transport.send(fp.Stop())
        if drain(transport, 0.03, 0.3, counts):
            return True
    return False


def stop_reason(stop) -> str:
    """What ended a measurement a stop was requested of, as the 1-D loop says it
    (:class:`hapsim.host.loop.HostLoop`'s ``stop_reason``).

    Parameters
    ----------
    stop : hapsim.spawn.StopFlag
        A flag that is set.

    Returns
    -------
    str
        ``"signal NAME"`` (a signal's), the stop's own ``reason`` (another caller's, e.g.
        the live view's stop button), or ``"stop requested"``.
    """
    if getattr(stop, "signal", None) is not None:
        return f"signal {signame(stop.signal)}"
    return getattr(stop, "reason", None) or "stop requested"


def reopen_port(transport, counts, *, first, last, since: float, until: float,
                tried: int = 0, most: int | None = None, backoff: float = 0.05,
                backoff_max: float = 1.0, stopped=None) -> bool:
    """After a loss (the port failed, the device fell silent or said no HELLO): open the
    port again with backoff until it comes back; the caller asks HELLO again.

    Parameters
    ----------
    transport : transport of :mod:`hapsim.host.transport`
        One with ``reopen()``; another cannot come back.
    counts : object
        Its ``reconnect_attempts`` counts every attempt (the run's total).
    first, last : DeviceError
        The loss's first error and its latest (the first line of each is named in the
        error, as the 1-D loop's recovery does).
    since, until : float
        The transport's clock [s] at the loss's start, and past which the device is lost
        for good (``since`` plus the time allowed, ``--reconnect-time``).
    tried : int
        Attempts already made for this loss.
    most : int, optional
        Attempts allowed for this loss (``--reconnect-attempts``); None: no limit but
        ``until``.
    backoff, backoff_max : float
        First wait between attempts [s], doubled up to ``backoff_max``.
    stopped : callable, optional
        ``stopped()`` True: a stop was requested (Ctrl-C, SIGTERM); the waiting ends.

    Returns
    -------
    bool
        True when the port is open again, False when a stop ended the waiting.

    Raises
    ------
    DeviceError
        The device lost for good: the time or the attempts allowed used up, or a
        transport that cannot reopen (``last`` itself).
    """
    if not hasattr(transport, "reopen"):
        raise last
    clock, sleep = clock_of(transport)
    wait = backoff
    while stopped is None or not stopped():
        if clock() + wait > until or (most is not None and tried >= most):
            raise DeviceError(
                f"device lost ({str(first).splitlines()[0]}); it did not come back in time: "
                f"{tried} attempts to open the port again in {clock() - since:.3g} s (last: "
                f"{str(last).splitlines()[0]})\nlast frames:\n" + transport.last_frames())
        sleep(wait)
        wait = min(2 * wait, backoff_max)
        tried += 1
        counts.reconnect_attempts += 1
        try:
            transport.reopen()
            return True
        except DeviceError as exc:
            last = exc
    return False
