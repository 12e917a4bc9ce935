"""The device-clocked source of STATEs: each usable STATE answered as it arrives.

:class:`DeviceClock` is the part of :class:`hapsim.host.loop.HostLoop` that reads the
device's STATEs for the device-clocked loop (:meth:`HostLoop._drive` answers them): it
drops stale, implausible, wrong-axes and unarmed STATEs, applies the backlog policy
(:func:`_newer_waiting`: a skipped STATE is yielded with ``t_rx = -1``, and
:meth:`HostLoop._drive` steps the scene with it and records it in the telemetry's skipped
STATEs' record), restarts the scene at the first armed STATE after a CONFIG and
declares the device lost on silence. It reads the loop's ``config``, ``tel``, ``stop``,
``result``, ``transport`` and ``measured`` (the notes of :mod:`hapsim.host.loop`).
"""

from __future__ import annotations

import math
import time

import firmware_protocol as fp
from hapsim.host.loop_types import LostDevice as _Lost
from hapsim.host.loop_types import SEQ_HALF as _HALF
from hapsim.host.loop_types import SEQ_MASK as _U32
from hapsim.host.telemetry import FLAG_SKIPPED

__all__ = ["DeviceClock"]


class DeviceClock:
    """The device-clocked loop's source of STATEs (a base of
    :class:`~hapsim.host.loop.HostLoop`)."""

    # ------------------------------------------------------------------ device-clocked
    def _device_clocked_stretch(self, n_max: int) -> None:
        """The hot loop, from the next armed STATE until the end, a stop, or a loss: each
        STATE is answered as it arrives (:meth:`_device_states`, :meth:`_drive`)."""
        self._drive(n_max, self._device_states(n_max))

    def _receive_hook(self):
        """The ``receive(timeout)`` the device-clocked source reads messages with: the
        transport's (a subclass may run samples before returning what is left,
        :mod:`hapsim.host.fastloop`)."""
        return self.transport.receive

    def _device_states(self, n_max: int):
        """The device-clocked source of :meth:`_drive`: every usable STATE, as it arrives.

        Drops stale, implausible, wrong-axes and (before the first armed one) unarmed
        STATEs, notes FAULTs and HELLOs, records bad frames, restarts the scene at the
        first armed STATE after a CONFIG, and raises :class:`_Lost` on silence (no usable
        STATE for :meth:`_silence`; ``state_timeout`` for the first after a CONFIG) or a
        disarmed STATE after arming.

        Yields
        ------
        (State, float, int)
            The STATE, its position [m] (NaN for a non-finite first one), and
            ``perf_counter_ns()`` when its frame was read.
        """
        cfg = self.config
        tel = self.tel
        stop = self.stop
        res = self.result
        rate = float(cfg.rate_hz)
        State = fp.State
        armed_bit = fp.STATUS_ARMED
        applied_bit = fp.STATUS_FORCE_APPLIED
        isfinite = math.isfinite
        perf = time.perf_counter_ns
        clock = self._clock
        receive = self._receive_hook()
        self._expect = -1
        silence = self._silence()
        # a device (re)starting after CONFIG gets state_timeout for its first STATE
        first_wait = max(silence, cfg.state_timeout)
        poll = min(0.1, silence)
        newest = cfg.backlog == "newest"
        ahead_max = silence * rate + 2.0
        self._last_rx = clock()
        ds = self._dstats
        nbad = self._nbad
        mv = self.measured
        while tel.n < n_max and not stop.set:
            # wait no longer than the silence still allowed: the loss is declared when it
            # runs out (to 1 us), not a poll later
            allowed = first_wait if self._fresh else silence
            left = self._last_rx + allowed - clock()
            msgs = receive(poll if left > poll else (left if left > 1e-6 else 0.0))
            t_rx = perf()
            if ds is not None and (ds.bad_crc + ds.bad_cobs + ds.overlong + ds.malformed
                                   + ds.unknown_type) != nbad:
                nbad = self._snap_bad(ds.bad_crc + ds.bad_cobs + ds.overlong
                                      + ds.malformed + ds.unknown_type)
            if not msgs:
                if clock() - self._last_rx >= allowed - 1e-6:
                    raise _Lost(f"no STATE from the device for {allowed:g} s")
                continue
            used = False
            for j, msg in enumerate(msgs):
                tm = type(msg)
                if tm is not State:
                    if self._note_other(msg):
                        break
                    continue
                if len(msg.position) != 1:
                    res.bad_axes += 1
                    continue
                seq = msg.seq
                if not msg.status & armed_bit:
                    if self._fresh:
                        res.unarmed += 1
                        continue
                    raise _Lost("the device reports itself disarmed (reset?)")
                x = msg.position[0]
                resumes = self._fresh
                if self._fresh:
                    if self._check_applied and msg.status & applied_bit:
                        res.earlier_session += 1  # a FORCE applied since CONFIG: none sent
                        continue
                    if not isfinite(x):
                        x = math.nan          # _drive stops on it (non-finite position)
                    else:
                        self._resume(x)
                        self._expect = seq
                if self._expect >= 0:
                    gap = (seq - self._expect) & _U32
                    if gap >= _HALF:
                        res.stale += 1            # duplicated or reordered: older
                        continue
                    if gap:
                        if gap > (clock() - self._last_rx + silence) * rate + 2.0:
                            res.implausible += 1  # further ahead than time allows
                            continue
                        res.missed += gap
                # only a STATE used keeps the device alive: a host ignoring every STATE
                # (stale, implausible) is as good as deaf, and loses it
                self._last_rx = clock()
                self._expect = (seq + 1) & _U32
                used = True
                if mv is not None:
                    mv.take(seq)                  # its VELOCITY came just before it
                if (newest and not resumes and j + 1 < len(msgs)
                        and _newer_waiting(msgs, j, seq, ahead_max)):
                    res.skipped += 1              # backlog: a newer STATE is waiting
                    self._skip_flag = FLAG_SKIPPED
                    yield msg, x, -1              # not answered; the scene still steps
                    continue
                yield msg, x, t_rx            # _drive answers it (or stops: no resume)
                if tel.n >= n_max:
                    break
            if (not used and not stop.set
                    and clock() - self._last_rx >= (first_wait if self._fresh else silence) - 1e-6):
                # frames came, but no STATE the loop could use for the silence allowed
                raise _Lost(f"no usable STATE from the device for "
                            f"{first_wait if self._fresh else silence:g} s")


def _newer_waiting(msgs, j: int, seq: int, ahead_max: float) -> bool:
    """Whether a STATE newer than ``seq`` waits after ``msgs[j]`` (the backlog policy).

    Parameters
    ----------
    msgs : list
        Messages of one read, in arrival order.
    j : int
        Index of the STATE ``seq`` in it.
    seq : int
        Its sequence number (u32).
    ahead_max : float
        Most samples a newer STATE may be ahead (``silence * rate + 2``: a STATE further
        ahead is implausible and does not count).

    Returns
    -------
    bool
        True when a later armed 1-axis STATE is ahead by 1 .. ``ahead_max``.
    """
    State = fp.State
    for m in msgs[j + 1:]:
        if type(m) is State and len(m.position) == 1 and m.status & fp.STATUS_ARMED:
            ahead = (m.seq - seq) & _U32
            if 0 < ahead < _HALF and ahead <= ahead_max:
                return True
    return False
