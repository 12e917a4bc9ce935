"""The late-tick rule: which FORCE a device applied at a tick, and whether the tick is late.

Written once, here, on plain integers, and read by every path that needs it: the Python
host loop (:meth:`hapsim.host.loop.HostLoop._drive`, the plain functions), the compiled
host loop (:mod:`hapsim.host.fastloop`: the same functions, ``register_jitable``, are
compiled into it) and the account of a record (:func:`hapsim.applied.
account_from_force_seq`, through :func:`late_ticks`). The rule is the protocol's
(``firmware_protocol/PROTOCOL.md`` §4 and the mock notes):

- STATE ``n`` carries ``force_seq``, the ``seq`` of the FORCE applied from tick ``n`` on,
  valid when the status has ``FORCE_APPLIED``. A device that has never set that bit
  (written before it existed) names a FORCE whenever ``force_seq`` is set; one that has set
  it once names none on a STATE without it. So whether a STATE names a FORCE depends on
  ``flags_applied``: whether the device has set the bit on this or an earlier STATE of the
  record (a running OR, as a host reading the stream in order knows it).
- The tick delay a STATE shows is ``(seq - force_seq) mod 2^32``; one "ahead" (more than
  half the counter) is a stale field and names nothing.
- With the device delay ``d``, tick ``seq`` is *due* from ``seq >= d`` (the device's tick
  counter restarts at CONFIG; FORCE 0 answers STATE 0 and is applied at tick ``d``). A due
  tick is *late* when the device says it overran (``OVERRUN``: it held an older force),
  when its watchdog zeroed the force (``WATCHDOG_TRIPPED``), or when the FORCE it names is
  not the one answering STATE ``seq - d`` (an older one, or none). With ``d = 0`` (the
  lockstep mock only) ``force_seq`` names the previous period's force, since FORCE ``n``
  is not known when STATE ``n`` leaves: only ``OVERRUN`` says a tick is late.

A protocol ambiguity stays: before a device has ever set ``FORCE_APPLIED``, a STATE with
``force_seq = 0`` names FORCE 0 or none (PROTOCOL.md §4); a host loop reading the stream in
order must read it as FORCE 0. The account of a whole record knows from any later row that
the device sets the bit (``flags0``) and reads it as none: the two differ on at most the
first due tick after a CONFIG (tick ``d``, when FORCE 0 was not applied there), where the
account says late and the loop cannot.

numba's on-disk cache keys a compiled function on its own source file only: the compiled
host loop inlines these functions, so ``hapsim/host/fastloop_kernels.py`` holds the SHA-256
of this file and the others it compiles in (``COMPILED_SOURCES_SHA256``; it compiles
without the cache while that is stale, and ``tests/test_compiled_loop_sources.py`` asks for
the update, which edits fastloop_kernels.py so that numba rebuilds its cache).
"""

from __future__ import annotations

import numba as nb
from numba.extending import register_jitable

from firmware_protocol.codec import (STATUS_FORCE_APPLIED, STATUS_OVERRUN,
                                     STATUS_WATCHDOG_TRIPPED)
from hapsim.kernels.sources import cache_ok

__all__ = ["SEQ_MASK", "SEQ_HALF", "STATUS_FORCE_APPLIED", "STATUS_OVERRUN",
           "STATUS_WATCHDOG_TRIPPED", "named_delay", "tick_late", "late_ticks",
           "held_force", "sent_ring_size"]

#: STATE.seq and FORCE.seq are u32 counters.
SEQ_MASK = 0xFFFFFFFF
#: A difference of more than half the counter is "behind", not ahead.
SEQ_HALF = 0x80000000

#: The sources :func:`late_ticks` compiles in (the protocol's status bits), and their
#: SHA-256 (:mod:`hapsim.kernels.sources`: numba keys its disk cache on this file alone).
COMPILED_SOURCES = ("firmware_protocol/codec.py",)
COMPILED_SOURCES_SHA256 = "4050cbef419c816a976ebfe661937a3ba04e21f2810924f56c4a87bbc5524ffa"
#: Whether numba's disk cache may serve :func:`late_ticks`.
CACHE_OK = cache_ok(COMPILED_SOURCES, COMPILED_SOURCES_SHA256)


@register_jitable
def named_delay(seq: int, force_seq: int, status: int, flags_applied: bool) -> int:
    """Ticks between a STATE and the FORCE it names as applied (module notes).

    Parameters
    ----------
    seq, force_seq : int
        STATE fields (u32; ``force_seq`` -1 where the protocol carries none).
    status : int
        STATE status bits.
    flags_applied : bool
        The device has set ``STATUS_FORCE_APPLIED`` on this or an earlier STATE.

    Returns
    -------
    int
        ``(seq - force_seq) mod 2^32`` [ticks], or -1 when the STATE names no FORCE
        (none carried, the bit clear on a device that sets it, or a stale field ahead).
    """
    if force_seq < 0:
        return -1
    if flags_applied and (status & STATUS_FORCE_APPLIED) == 0:
        return -1
    t = (seq - force_seq) & SEQ_MASK
    if t >= SEQ_HALF:
        return -1
    return t


@register_jitable
def tick_late(seq: int, force_seq: int, status: int, d: int, flags_applied: bool) -> bool:
    """Whether the device held another force than FORCE ``seq - d`` at tick ``seq``
    (module notes).

    Parameters
    ----------
    seq, force_seq : int
        STATE fields (u32; ``force_seq`` -1 where the protocol carries none).
    status : int
        STATE status bits.
    d : int >= 0
        The device's delay [ticks].
    flags_applied : bool
        The device has set ``STATUS_FORCE_APPLIED`` on this or an earlier STATE.

    Returns
    -------
    bool
        True for a due tick (``seq >= d``) that overran, whose watchdog zeroed the force,
        or that names another FORCE than ``seq - d`` (with ``d = 0``: overran only).
    """
    if seq < d:
        return False
    if status & STATUS_OVERRUN:
        return True
    if d == 0:
        return False
    if status & STATUS_WATCHDOG_TRIPPED:
        return True
    return named_delay(seq, force_seq, status, flags_applied) != d


def sent_ring_size(watchdog_us: float, rate_hz: float, d: int) -> int:
    """Entries of the ring of sent FORCEs :func:`held_force` reads: a power of two that
    holds every FORCE a device may still hold (its watchdog's periods and the delay, with
    room), at least 64; 4096 for a device without a watchdog (``watchdog_us <= 0``).

    Parameters
    ----------
    watchdog_us : float
        The device's watchdog (CONFIG's) [us] (<= 0: none).
    rate_hz : float
        The loop's rate [Hz].
    d : int
        The device's delay [ticks].

    Returns
    -------
    int
    """
    periods = int(watchdog_us * rate_hz / 1e6)
    if periods <= 0:
        return 4096
    need = max(periods + int(d) + 4, 64)
    return 1 << (need - 1).bit_length()


@register_jitable
def held_force(ring, seq, force_seq, status, d, flags_applied, held):
    """The force the device held over the period that ends at STATE ``seq`` [N], from the
    FORCEs the host sent.

    STATE ``seq`` names the FORCE applied from its tick on (``d >= 1``), or over the period
    before it (``d = 0``: module notes). The force a STATE names as held is, in this order:

    - zero when it names none: ``FORCE_APPLIED`` clear on a device that sets it, or a
      FORCE too recent to have been applied (``seq - force_seq < max(d, 1)``: a FORCE is
      applied ``d`` ticks after the STATE it answers at the earliest; before a device has
      set the bit, ``force_seq = 0`` is also "none yet");
    - zero under the watchdog (``WATCHDOG_TRIPPED``);
    - what the previous STATE named when it names the same FORCE: the device holds its
      last force over a late tick, and that is the watchdog's zero once it zeroed it (the
      watchdog fed again by a FORCE not yet due leaves the bit clear while the zero is
      held, ``force_seq`` still naming the last FORCE received in time);
    - else the named FORCE's value, as the host sent it (``ring``), or the previous one's
      when the ring does not hold it (not sent this stretch: the STATE it answered was
      skipped, or it came before the stretch).

    A protocol without ``force_seq`` is taken on time (FORCE ``seq - max(d, 1)``); a
    stale field ahead of the STATE changes nothing. The host loops' passivity observer
    integrates this force, the one held, not the one sent (Hannaford & Ryu 2002: the
    work really done on the hand; a FORCE that came late was never applied).

    Parameters
    ----------
    ring : array_like of float, shape (2, R)
        Row 0: the ``seq`` of the FORCE sent in each slot ``seq % R`` (-1: none); row 1:
        its force [N]. R a power of two (:func:`sent_ring_size`).
    seq, force_seq, status, d, flags_applied
        As :func:`tick_late`.
    held : sequence of float, length 2
        The force the previous STATE named as held [N] and which FORCE (-1: none): 0 and
        -1 at a stretch's start; updated in place to this STATE's.

    Returns
    -------
    float
        The force held over the period before this STATE [N]: the one the previous STATE
        named (``d >= 1``), or this one's (``d = 0``).
    """
    prev, prev_named = held[0], held[1]
    f, named = prev, prev_named             # a stale field ahead: nothing known
    lag = named_delay(seq, force_seq, status, flags_applied)
    if lag < 0 and force_seq < 0:
        lag = d if d > 0 else 1             # no field: taken on time
    if lag < 0:
        if flags_applied and (status & STATUS_FORCE_APPLIED) == 0:
            f, named = 0.0, -1.0            # none applied
    elif lag < (d if d > 0 else 1):
        f, named = 0.0, -1.0                # too recent to be applied: none yet
    else:
        want = (seq - lag) & SEQ_MASK
        named = want
        if status & STATUS_WATCHDOG_TRIPPED:
            f = 0.0
        elif want != prev_named:
            j = want % len(ring[0])
            if ring[0][j] == want:
                f = ring[1][j]
    held[0] = f
    held[1] = named
    return f if d == 0 else prev


@nb.njit(cache=CACHE_OK, nogil=True)
def late_ticks(seq, force_seq, status, d, flags0, tick, late, flags):
    """The rule over a record, row by row in order (:func:`named_delay`, :func:`tick_late`).

    Parameters
    ----------
    seq, force_seq, status : ndarray of int64, shape (n,)
        STATE fields of each row (``force_seq`` -1 where the protocol carries none).
    d : int
        The device's delay [ticks]; < 0: not known yet (``late`` is left untouched).
    flags0 : bool
        ``flags_applied`` before the first row: a host loop's own knowledge so far; a
        whole record's reader may know from any of its rows that the device sets the bit.
    tick : ndarray of int64, shape (n,)
        Out: :func:`named_delay` of each row (-1: names none) [ticks].
    late : ndarray of bool, shape (n,)
        Out: :func:`tick_late` of each row (when ``d >= 0``).
    flags : ndarray of bool, shape (n,)
        Out: ``flags_applied`` at each row (the running OR of ``FORCE_APPLIED``).
    """
    fa = flags0
    for k in range(seq.size):
        if status[k] & STATUS_FORCE_APPLIED:
            fa = True
        flags[k] = fa
        tick[k] = named_delay(seq[k], force_seq[k], status[k], fa)
        if d >= 0:
            late[k] = tick_late(seq[k], force_seq[k], status[k], d, fa)
